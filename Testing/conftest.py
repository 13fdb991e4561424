"""Shared fixtures: small simulated sweeps with known ground truth.

Sessions share them (simulated once per test run), so tests stay fast. The small
sweeps keep the reference field of view (38.4 mm deep x 48 mm wide) at 0.3 mm pixels.
Fixtures are read-only by convention: never modify a simulation's arrays in a test.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from BoneUSRecon.Logic.segmentation.params import (
    RimParams,
    SegmentationParams,
    SettleParams,
    ShadowPathParams,
)
from BoneUSRecon.Logic.simulation import Simulation, SimulationParams, simulate
from BoneUSRecon.Logic.sweep import Sweep

#: Parameters of the small sweeps: 40 frames of 128 rows x 160 columns at 0.3 mm.
SMALL: dict[str, Any] = {
    "bone": "clavicle",
    "n_frames": 40,
    "width": 160,
    "height": 128,
    "spacing_mm": 0.3,
}

#: Real data shipped in the repository (BSD 3-Clause, see its LICENSE): the PLUS
#: recording BoneUltrasound_L14 and its device-set configuration.
SAMPLE_DATA = Path(__file__).resolve().parents[1] / "Resources" / "SampleData"


def sample_data(name: str) -> Path:
    """The file ``name`` of ``Resources/SampleData``; raises (never skips) when missing.

    The recording is part of the repository so that the real-data tests run on every
    clone and in CI: a missing file is a broken checkout, not a reason to skip.
    """
    path = SAMPLE_DATA / name
    if not path.is_file():
        raise FileNotFoundError(f"{path}: sample data missing from the checkout")
    return path


#: The real recording (21 frames of 820 x 616 at 0.085 mm) and its calibration.
REAL_MHA = sample_data("BoneUltrasound_L14.igs.mha")
REAL_XML = sample_data("BoneUltrasound_L14_config.xml")

#: The geometry of issue 10's cadaver sweep (475 x 405 pixels at 0.108 mm), for
#: ``small_simulation(**CADAVER, ...)``.
CADAVER: dict[str, Any] = {"width": 475, "height": 405, "spacing_mm": 0.108}

_CACHE: dict[tuple[tuple[str, Any], ...], Simulation] = {}


def replayed(sweep: Sweep, frames: Any, poses: np.ndarray | None = None) -> Sweep:
    """The sweep's frames in the order given, 20 frames/s, as a recording would hold
    them (a frame repeated: the probe held at its pose; back down: a way back), with
    ``poses`` instead of theirs if given (tracker jitter)."""
    idx = np.asarray(frames)
    return dataclasses.replace(
        sweep,
        frames=sweep.frames[idx],
        image_to_reference=sweep.image_to_reference[idx] if poses is None else poses,
        timestamps=np.arange(idx.size) / 20.0,
        valid=sweep.valid[idx],
        invalid_reasons={},
    )


#: The segmentation with the shadow gate flat from 1 on (``shadow_gate_max`` 1), as before
#: session 46: tests of a mechanism whose situation arises on their sweeps only with it
#: (with the gate rising on where the shadow is deep, the bone wins there first).
FLAT_GATE = SegmentationParams(shadowpath=ShadowPathParams(shadow_gate_max=1.0))

#: The per-frame step as several mechanism tests measure it: the candidates not settled
#: nor their flat ends followed (settle.py and rim.py, branch onset) and the shadow gate
#: flat from 1 on; each test says which of its frames need which.
FLAT_BARE = dataclasses.replace(
    FLAT_GATE.shadowpath, settle=SettleParams(enabled=False), rim=RimParams(enabled=False)
)


def small_simulation(**params: Any) -> Simulation:
    """Simulate with :data:`SMALL` defaults overridden by ``params``; cached per parameter set."""
    full = {**SMALL, **params}
    key = tuple(sorted(full.items()))
    if key not in _CACHE:
        _CACHE[key] = simulate(SimulationParams(**full))
    return _CACHE[key]


@pytest.fixture(scope="session")
def sim_small() -> Simulation:
    """Clavicle, 40 frames, 128 x 160 pixels at 0.3 mm, no corruption, seed 0."""
    return small_simulation(seed=0)


@pytest.fixture(scope="session")
def sim_small_corrupted() -> Simulation:
    """As :func:`sim_small` with 10 % corrupted frames (4 frames, all three kinds), seed 1."""
    return small_simulation(seed=1, corrupted_fraction=0.1)


@pytest.fixture(scope="session")
def sim_factory() -> Callable[..., Simulation]:
    """``sim_factory(**params)``: a cached small simulation (defaults :data:`SMALL`).

    Example: ``sim_factory(bone="radius", seed=3, reverse=True)``.
    """
    return small_simulation

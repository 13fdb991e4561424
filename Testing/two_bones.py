"""Simulated forearms for the bone-point tests: the ulna swept, the radius 18 mm beside
it, and where on them a user would click (reference mm, from the simulator's truth)."""

from __future__ import annotations

import functools

import numpy as np

from BoneUSRecon.Logic.simulation import Simulation, SimulationParams, simulate
from BoneUSRecon.Logic.simulation.sections import bone_sections
from BoneUSRecon.Logic.sweep import Sweep, pixels_to_reference


@functools.cache
def forearm(realism: str, seed: int, width: int = 160, n_frames: int = 12) -> Simulation:
    """An ulna sweep with the radius 18 mm beside it (cached)."""
    return simulate(
        SimulationParams(
            bone="ulna",
            neighbour_mm=18.0,
            n_frames=n_frames,
            width=width,
            height=136,
            spacing_mm=0.32,
            realism=realism,
            seed=seed,
        )
    )


@functools.cache
def forearm_beside(
    bone: str, neighbour_mm: float, seed: int, realism: str = "hard", n_frames: int = 12
) -> Simulation:
    """A forearm bone swept in the middle of a 51 mm image (320 x 256 at 0.16 mm), the
    other forearm bone ``neighbour_mm`` beside it (14: their tops touch; cached)."""
    return simulate(
        SimulationParams(
            bone=bone,
            neighbour_mm=neighbour_mm,
            n_frames=n_frames,
            width=320,
            height=256,
            spacing_mm=0.16,
            realism=realism,
            seed=seed,
        )
    )


def neighbour_top(sim: Simulation, sweep: Sweep, frame: int) -> np.ndarray:
    """The top of the neighbouring bone's section in a frame, reference mm (the point a
    user clicks on it), from the simulator's analytic neighbour."""
    s = sim.path.s - sim.geometry.length / 2 + sim.neighbour.length / 2  # as simulate()
    top = bone_sections(sim.neighbour, sweep.image_to_reference, s, sweep.width).top_j[frame]
    i = int(np.nanargmin(top))
    return pixels_to_reference(sweep.image_to_reference[frame], np.array([[i, top[i]]]))[0]


def bone_top(sim: Simulation, sweep: Sweep, frame: int, shift: int = 0) -> np.ndarray:
    """The middle of the swept bone's true contour in a frame, reference mm."""
    c = sim.true_contours_px[frame] - (shift, 0)
    return pixels_to_reference(sweep.image_to_reference[frame], c[len(c) // 2][None])[0]


def on_bones(sim: Simulation, sweep: Sweep, result) -> tuple[float, float, int]:
    """Median over the accepted frames of their points' median distance (mm) to the
    swept bone and to its neighbour (the simulator's analytic surfaces), and how many."""
    acc = result.accepted
    to_bone = [np.median(sim.geometry.distance(c.points_mm(sweep))) for c in acc]
    to_nb = [np.median(sim.neighbour.distance(c.points_mm(sweep))) for c in acc]
    return float(np.median(to_bone)), float(np.median(to_nb)), len(acc)


def off_centre(sim: Simulation) -> tuple[Sweep, int]:
    """The sweep's frames cut to 128 columns with the ulna's middle at column 24 (0.62
    of the half-width off the middle) and the radius 18 mm beside it near the middle:
    a bone swept near the image's edge. The poses move with the first column kept."""
    sw = sim.sweep
    mid = np.median([0.5 * (c[0, 0] + c[-1, 0]) for c in sim.true_contours_px if len(c)])
    a = int(round(mid)) - 24
    m = sw.image_to_reference.copy()
    m[:, :3, 3] += a * m[:, :3, 0]
    frames = np.ascontiguousarray(sw.frames[:, :, a : a + 128])
    return sw.replace(frames=frames, image_to_reference=m), a

"""The self-test's scenario: a simulated sweep through a scene, checked in millimetres.

Shared by the module's ``ScriptedLoadableModuleTest`` (inside Slicer) and by the pytest
suite (with ``slicer-core``), so the check that runs in Slicer is the one CI runs too.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

__all__ = ["ACCURACY", "SelfTestResult", "simulatedSweep", "runSelfTest"]

#: Acceptance thresholds on the simulated clavicle (no corruption), in mm. The paper
#: reports a 1.16 mm mean surface-to-gold distance on a real phantom; a noise-free
#: simulation must do at least as well.
ACCURACY = {
    "surface_to_truth_mean_mm": 1.0,
    "gold_to_surface_mean_mm": 1.2,
    "pose_roundtrip_mm": 1e-6,
}


@dataclass(frozen=True)
class SelfTestResult:
    """Numbers measured by :func:`runSelfTest` (mm unless said)."""

    surface_to_truth_mean_mm: float
    """Mean distance from the surface's vertices to the true bone surface."""
    surface_to_truth_p95_mm: float
    """95th percentile of the same."""
    gold_to_surface_mean_mm: float
    """Mean distance from the gold points (digitised bone) to the surface (the paper's measure)."""
    pose_roundtrip_mm: float
    """Largest displacement of an image corner between the simulated sweep and the one read back from the scene."""
    n_frames: int
    """Frames in the simulated sweep."""
    seconds: float
    """Wall time of the reconstruction through the scene."""
    nodes: Any = field(default=None, repr=False, compare=False)
    """The :class:`BoneSurfaceReconstructionLib.mrml.MRMLReconstruction`."""

    def failures(self) -> list[str]:
        """Which :data:`ACCURACY` thresholds were exceeded (empty when all pass)."""
        return [
            f"{k} = {getattr(self, k):.4g} > {limit}"
            for k, limit in ACCURACY.items()
            if not getattr(self, k) <= limit
        ]


def simulatedSweep(
    n_frames: int = 40, width: int = 160, height: int = 128, spacing_mm: float = 0.3, seed: int = 0
) -> Any:
    """A small simulated clavicle sweep (:class:`BoneUSRecon.Logic.simulation.Simulation`).

    The defaults are the pytest suite's ``sim_small`` (Testing/conftest.py): 40 frames of
    128 x 160 pixels at 0.3 mm, no corruption.
    """
    from BoneUSRecon.Logic.simulation import SimulationParams, simulate

    return simulate(
        SimulationParams(
            bone="clavicle",
            n_frames=n_frames,
            width=width,
            height=height,
            spacing_mm=spacing_mm,
            seed=seed,
        )
    )


def runSelfTest(
    scene: Any, *, simulation: Any = None, params: Any = None, progress: Any = None
) -> SelfTestResult:
    """Put a simulated sweep in ``scene``, reconstruct it through the MRML adapter, measure.

    Parameters
    ----------
    scene : vtkMRMLScene
        ``slicer.mrmlScene`` inside Slicer, or a ``slicer-core`` scene.
    simulation : Simulation, optional
        Default: :func:`simulatedSweep`.
    params : ReconstructionParams, optional
    progress : ProgressCallback, optional
    """
    import time

    from BoneSurfaceReconstructionLib import mrml
    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.vtkio import polydata_points

    sim = simulation if simulation is not None else simulatedSweep()
    nodes = mrml.sweep_to_scene(sim.sweep, scene, name="SimulatedSweep")
    t0 = time.perf_counter()
    out = mrml.reconstruct_from_scene(nodes.browser, params=params, progress=progress)
    seconds = time.perf_counter() - t0
    # The scene holds the valid frames only (sweep_to_scene leaves invalid ones out).
    read_back = out.sweep
    pose_err = float(
        np.abs(read_back.corners_mm(np.arange(read_back.n_frames)) - sim.sweep.corners_mm()).max()
    )
    verts = polydata_points(out.surface_node.GetPolyData())
    d = sim.distance_to_truth(verts)
    ev = evaluate_surface(out.surface_node.GetPolyData(), sim.gold)
    return SelfTestResult(
        surface_to_truth_mean_mm=float(np.mean(d)),
        surface_to_truth_p95_mm=float(np.percentile(d, 95)),
        gold_to_surface_mean_mm=float(ev.mean),
        pose_roundtrip_mm=pose_err,
        n_frames=int(sim.sweep.n_frames),
        seconds=seconds,
        nodes=out,
    )

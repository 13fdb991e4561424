"""MRML adapter: Slicer scene nodes <-> :mod:`BoneUSRecon.Logic`.

Part of the Slicer module's helpers (not of the pip-installed library): the module's
Logic reaches the library through it and :mod:`BoneUSRecon.Logic`, never through
:mod:`BoneUSRecon.Widgets`. The one place that knows 3D Slicer's scene (MRML), in
three files along its seams:

* :mod:`.mrml_sweep`: sweeps <-> MRML (frames and poses read from a sequence browser
  or volume sequence, with the coordinate convention; a sweep written back as nodes;
  PLUS files loaded);
* :mod:`.mrml_display`: the results shown (surface coloured by distance, points);
* this module: the pipeline run on a sweep in the scene (:func:`reconstruct_from_scene`),
  and every public name of the other two, so ``mrml.sweep_to_scene`` etc. keep working.

It works on the nodes it is given (any ``vtkMRMLScene``: the Slicer application's, or
one built with the ``slicer-core`` package from PyPI) and imports :mod:`slicer` only
inside the one function that needs Slicer's Sequences logic, so importing it never
loads Slicer, Qt, or VTK rendering. The module's parameters become the library's in
:func:`BoneSurfaceReconstructionLib.parameters.parameters_from_widget_values`.
"""

from __future__ import annotations

from collections.abc import Sequence as SequenceABC
from dataclasses import dataclass
from typing import Any

import numpy as np

from BoneSurfaceReconstructionLib.mrml_display import (
    DISTANCE_COLOR_NODE_NAME,
    distance_color_node,
    show_points,
    show_surface,
)
from BoneSurfaceReconstructionLib.mrml_sweep import (
    SweepNodes,
    load_sweep_file,
    sweep_from_browser,
    sweep_from_node,
    sweep_from_sequences,
    sweep_to_scene,
)
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.progress import ProgressCallback
from BoneUSRecon.Logic.sweep import Sweep

__all__ = [
    "SweepNodes",
    "MRMLReconstruction",
    "DISTANCE_COLOR_NODE_NAME",
    "sweep_from_node",
    "sweep_from_browser",
    "sweep_from_sequences",
    "sweep_to_scene",
    "load_sweep_file",
    "distance_color_node",
    "show_surface",
    "show_points",
    "reconstruct_from_scene",
    "bone_points_from_node",
]


@dataclass(frozen=True)
class MRMLReconstruction:
    """What :func:`reconstruct_from_scene` produced."""

    sweep: Sweep
    """The sweep read from the scene (reference = Slicer world, RAS)."""
    reconstruction: Any
    """The :class:`~BoneUSRecon.Logic.pipeline.Reconstruction`."""
    surface_node: Any
    """``vtkMRMLModelNode`` of the surface, ``Distance`` shown through a colour table."""
    points_node: Any
    """Model (or markups) node of the segmented points."""
    registration: Any = None
    """The registration to a bone model, when one was asked for (the Slicer module's
    ``BoneSurfaceReconstructionLib.registration.SceneRegistration``)."""


def bone_points_from_node(node: Any) -> np.ndarray:
    """The control points of a markups point list in world (RAS) mm, ``(K, 3)``.

    The sweep's reference coordinates are Slicer's world (:mod:`.mrml_sweep`), so a
    point placed on the bone in a slice or the reconstructed volume is a bone point as
    it is (``RejectionParams.bone_points``). ``None``: no points, ``(0, 3)``.
    """
    if node is None:
        return np.empty((0, 3))
    pts = []
    for k in range(node.GetNumberOfControlPoints()):
        # A point still being placed (its position undefined) is no point yet.
        status = getattr(node, "GetNthControlPointPositionStatus", None)
        if status is not None and status(k) != getattr(node, "PositionDefined", status(k)):
            continue
        xyz = [0.0, 0.0, 0.0]
        node.GetNthControlPointPositionWorld(k, xyz)
        pts.append(xyz)
    return np.array(pts, dtype=float).reshape(-1, 3)


def reconstruct_from_scene(
    input_node: Any,
    *,
    transform_sequence: Any = None,
    calibration: Any = None,
    params: Any = None,
    surface_node: Any = None,
    points_node: Any = None,
    progress: ProgressCallback | None = None,
) -> MRMLReconstruction:
    """Reconstruct the bone surface of a sweep in the scene; put the results in the scene.

    Parameters
    ----------
    input_node : vtkMRMLSequenceBrowserNode, vtkMRMLSequenceNode or vtkMRMLScalarVolumeNode
        See :func:`sweep_from_node`.
    transform_sequence : vtkMRMLSequenceNode, optional
        With a volume sequence not under a browser: the per-frame transforms.
    calibration : ndarray (4, 4) or vtkMRMLLinearTransformNode, optional
        PLUS ``ImageToProbe`` (pixel -> mm); see the module docstring.
    params : ReconstructionParams, optional
        Default: the paper's (see :func:`~BoneSurfaceReconstructionLib.parameters.parameters_from_widget_values`).
    surface_node, points_node : optional
        Nodes to fill; new ones are added to the scene if None.
    progress : ProgressCallback, optional
        Called with stage ``"mrml"`` while reading frames, then the pipeline's stages.

    Raises
    ------
    BoneUSReconError
        Bad input nodes, or the pipeline finding nothing to reconstruct.
    """
    from BoneUSRecon.Logic.pipeline import ReconstructionParams, reconstruct

    if input_node is None:
        raise BoneUSReconError("no input selected: pick a sequence browser or a volume sequence")
    scene = input_node.GetScene()
    sweep = sweep_from_node(
        input_node, transform_sequence, calibration=calibration, progress=progress
    )
    recon = reconstruct(sweep, params if params is not None else ReconstructionParams(), progress)
    base = input_node.GetName() or "Sweep"
    surface_node = show_surface(recon.surface, scene, node=surface_node, name=f"{base}-BoneSurface")
    points_node = show_points(recon.points, scene, node=points_node, name=f"{base}-SegmentedPoints")
    for key, value in _flat_summary(recon.summary).items():
        surface_node.SetAttribute(f"BoneUSRecon.{key}", value)
    return MRMLReconstruction(sweep, recon, surface_node, points_node)


def _flat_summary(summary: Any) -> dict[str, str]:
    """Scalar entries of the pipeline's summary as strings (for node attributes)."""
    out: dict[str, str] = {}
    if not isinstance(summary, dict):
        return out
    for k, v in summary.items():
        if isinstance(v, (bool, int, float, str, np.integer, np.floating)):
            out[str(k)] = f"{v:.4g}" if isinstance(v, (float, np.floating)) else str(v)
        elif isinstance(v, SequenceABC) and not isinstance(v, str) and len(v) <= 4:
            out[str(k)] = " ".join(str(x) for x in v)
    return out

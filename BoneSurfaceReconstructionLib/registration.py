"""Registration in the scene: a model node (the reconstructed surface) onto a bone model node.

A thin adapter between MRML nodes and :func:`BoneUSRecon.Logic.registration.register`:
both models are taken in world coordinates (RAS, through any linear parent transform),
the result goes into a linear transform node whose *to parent* matrix maps the source
onto the target (put the source model under it, and it lands on the target), and into a
copy of the source model moved onto the target. The quality figures are stored as node
attributes (``BoneUSRecon.registration.*``) and returned. Nothing here imports
``slicer``: it runs on any MRML scene, Slicer's or one from the ``slicer-core`` package.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

__all__ = ["SceneRegistration", "registerModelToModel", "summaryText"]


@dataclass(frozen=True)
class SceneRegistration:
    """What :func:`registerModelToModel` produced."""

    registration: Any
    """The :class:`BoneUSRecon.Logic.registration.Registration` (matrix in RAS, mm)."""
    transformNode: Any
    """``vtkMRMLLinearTransformNode``: source -> target as its *to parent* transform."""
    registeredNode: Any
    """``vtkMRMLModelNode``: the source moved onto the target."""


def _worldPolyData(node: Any, what: str) -> Any:
    """The node's polydata in world coordinates (a copy), normals moved along."""
    from BoneSurfaceReconstructionLib.mrml_sweep import _to_world
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.registration import transform_polydata

    if node is None or not node.IsA("vtkMRMLModelNode"):
        raise BoneUSReconError(f"the {what} must be a model node")
    pd = node.GetPolyData()
    if pd is None or pd.GetNumberOfPoints() == 0:
        raise BoneUSReconError(f"the {what} model {node.GetName()!r} is empty")
    return transform_polydata(pd, _to_world(node))


def registerModelToModel(
    sourceNode: Any,
    targetNode: Any,
    *,
    transformNode: Any = None,
    registeredNode: Any = None,
    params: Any = None,
    init: Any = None,
    landmarks: Any = None,
    reconstruction: Any = None,
) -> SceneRegistration:
    """Rigidly register ``sourceNode``'s surface onto ``targetNode`` (both model nodes).

    :param sourceNode: the reconstructed surface (its ``Normals`` are used when present);
        the registered model is this surface moved onto the target.
    :param reconstruction: optional ``Reconstruction`` whose surface ``sourceNode`` shows
        (world coordinates): its segmented points are registered instead of the
        surface's vertices, each facing its probe (more accurate along a shaft: see
        ``BoneUSRecon.Logic.registration.register_reconstruction``).
    :param targetNode: the bone model (CT or MRI, mm).
    :param transformNode: linear transform node to fill (new if None).
    :param registeredNode: model node for the moved source (new if None).
    :param params: ``RegistrationParams`` (default: identity start, robust ICP).
    :param init: 4x4 initial source -> target matrix (RAS), optional.
    :param landmarks: ``(source (K, 3), target (K, 3))`` RAS points, optional.
    :raises BoneUSReconError: (a ValueError) bad nodes, units, landmarks, or no overlap.
    """
    from BoneSurfaceReconstructionLib.mrml import show_surface
    from BoneUSRecon.Logic.registration import (
        RegistrationParams,
        model_from_polydata,
        register_polydata,
        register_reconstruction,
        transform_polydata,
    )
    from BoneUSRecon.Logic.sweep import matrix_to_vtk

    source = _worldPolyData(sourceNode, "source")
    target = _worldPolyData(targetNode, "target")
    p = params if params is not None else RegistrationParams()
    if reconstruction is not None:
        reg = register_reconstruction(
            reconstruction,
            model_from_polydata(target, targetNode.GetName()),
            p,
            init=init,
            landmarks=landmarks,
            model_path=targetNode.GetName(),
        )
    else:
        reg = register_polydata(
            source,
            target,
            p,
            init=init,
            landmarks=landmarks,
            source_path=sourceNode.GetName(),
            target_path=targetNode.GetName(),
        )
    scene = sourceNode.GetScene()
    if transformNode is None:
        transformNode = scene.AddNewNodeByClass(
            "vtkMRMLLinearTransformNode", f"{sourceNode.GetName()}-To-{targetNode.GetName()}"
        )
    transformNode.SetMatrixTransformToParent(matrix_to_vtk(reg.matrix))
    for key, value in (
        ("rms_mm", f"{reg.rms_mm:.4g}"),
        ("median_mm", f"{reg.median_mm:.4g}"),
        ("inlier_share", f"{reg.inlier_share:.4g}"),
        ("condition", f"{reg.condition:.4g}"),
        ("reliable", str(reg.reliable)),
        ("reasons", "; ".join(reg.reasons)),
    ):
        transformNode.SetAttribute(f"BoneUSRecon.registration.{key}", value)
    registeredNode = show_surface(
        transform_polydata(source, reg.matrix),
        scene,
        node=registeredNode,
        name=f"{sourceNode.GetName()}-Registered",
    )
    return SceneRegistration(reg, transformNode, registeredNode)


def summaryText(result: SceneRegistration) -> str:
    """Quality figures in one paragraph for the module panel."""
    reg = result.registration
    rows = reg.summary_rows()
    return "Registration: " + "; ".join(f"{k} {v}" for k, v in rows)

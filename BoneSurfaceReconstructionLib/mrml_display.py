"""Display of the results in the scene: the surface coloured by distance, the points.

Part of the MRML adapter (:mod:`BoneSurfaceReconstructionLib.mrml`); works on any
``vtkMRMLScene`` and never imports Slicer, Qt or VTK rendering.
"""

from __future__ import annotations

from typing import Any

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkPolyData

from BoneSurfaceReconstructionLib.mrml_sweep import _node_label
from BoneUSRecon.Logic.errors import BoneUSReconError

__all__ = ["DISTANCE_COLOR_NODE_NAME", "distance_color_node", "show_surface", "show_points"]

#: Name of the colour table created for the ``Distance`` scalars (reused if present).
DISTANCE_COLOR_NODE_NAME = "BoneUSRecon Distance"

# Colour stops near -> far (viridis-like: dark blue, teal, green, yellow), chosen so the
# map reads in grey scale too, as in the paper's Fig. 4 (grey = distance).
_COLOR_STOPS = np.array(
    [
        [0.267, 0.005, 0.329],
        [0.231, 0.322, 0.545],
        [0.129, 0.569, 0.549],
        [0.369, 0.788, 0.384],
        [0.993, 0.906, 0.144],
    ]
)


# ------------------------------------------------------------------------------------
# Reconstruction -> MRML
# ------------------------------------------------------------------------------------
def distance_color_node(scene: Any) -> Any:
    """The colour table for ``Distance`` (mm): found by name, else created (256 colours)."""
    node = scene.GetFirstNodeByName(DISTANCE_COLOR_NODE_NAME)
    if node is not None and node.IsA("vtkMRMLColorTableNode"):
        return node
    node = scene.CreateNodeByClass("vtkMRMLColorTableNode")
    node.SetName(DISTANCE_COLOR_NODE_NAME)
    node.SetTypeToUser()
    node.SetNumberOfColors(256)
    x = np.linspace(0.0, 1.0, len(_COLOR_STOPS))
    s = np.linspace(0.0, 1.0, 256)
    rgb = np.column_stack([np.interp(s, x, _COLOR_STOPS[:, c]) for c in range(3)])
    for k, (r, g, b) in enumerate(rgb):
        node.SetColor(k, float(r), float(g), float(b), 1.0)
    node.SetAttribute("Category", "BoneUSRecon")
    scene.AddNode(node)
    node.UnRegister(None)
    return node


def _ensure_display(node: Any) -> Any:
    disp = node.GetDisplayNode()
    if disp is None:
        node.CreateDefaultDisplayNodes()
        disp = node.GetDisplayNode()
    return disp


def show_surface(
    surface: vtkPolyData,
    scene: Any,
    *,
    node: Any = None,
    name: str = "BoneSurface",
    scalar_range: tuple[float, float] | None = None,
) -> Any:
    """Put the reconstructed surface in a ``vtkMRMLModelNode``, coloured by ``Distance``.

    Parameters
    ----------
    surface : vtkPolyData
        Triangles with the point array ``Distance`` (mm), and ``Extrapolated`` (1 on the
        flank strips of ``SurfaceParams.flank_extension_mm``) if it was extended; every
        point array is kept in the node.
    scene : vtkMRMLScene
    node : vtkMRMLModelNode, optional
        Node to fill (its previous geometry is replaced); a new one if None.
    name : str
        Name of a new node.
    scalar_range : (float, float), optional
        Colour range in mm; default 0 .. the 95th percentile of ``Distance`` over the
        points that are not ``Extrapolated`` (so that a few far points do not wash out
        the map, and the extrapolated flanks, farther from the data by design, show in
        the far colour instead of compressing the imaged part's colours).

    Returns
    -------
    vtkMRMLModelNode
    """
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLModelNode", name)
    elif not node.IsA("vtkMRMLModelNode"):
        raise BoneUSReconError(f"the output surface must be a model node, got {_node_label(node)}")
    pd = vtkPolyData()
    pd.DeepCopy(surface)
    node.SetAndObservePolyData(pd)
    disp = _ensure_display(node)
    dist = pd.GetPointData().GetArray("Distance")
    if dist is not None:
        pd.GetPointData().SetActiveScalars("Distance")
        d = numpy_support.vtk_to_numpy(dist)
        extrapolated = pd.GetPointData().GetArray("Extrapolated")
        if extrapolated is not None:
            d = d[numpy_support.vtk_to_numpy(extrapolated) == 0]
        d = d[np.isfinite(d)]
        if scalar_range is None:
            hi = float(np.percentile(d, 95)) if d.size else 1.0
            scalar_range = (0.0, hi if hi > 0 else 1.0)
        disp.SetActiveScalarName("Distance")
        disp.SetAndObserveColorNodeID(distance_color_node(scene).GetID())
        disp.SetScalarRangeFlag(disp.UseManualScalarRange)
        disp.SetScalarRange(*scalar_range)
        disp.SetScalarVisibility(True)
    disp.SetBackfaceCulling(False)  # an open surface: both sides must show
    disp.SetVisibility(True)
    return node


def show_points(
    points: vtkPolyData | np.ndarray,
    scene: Any,
    *,
    node: Any = None,
    name: str = "SegmentedPoints",
) -> Any:
    """Put the segmented contour points in a model node (default) or a markups node.

    A model node of vertices keeps the point arrays (``Frame``, ``Intensity``,
    ``Confidence``) and stays fast with tens of thousands of points; a
    ``vtkMRMLMarkupsFiducialNode`` (if given as ``node``) gets one locked, unlabelled
    control point per point.

    Returns
    -------
    vtkMRMLModelNode or vtkMRMLMarkupsFiducialNode
    """
    if isinstance(points, vtkPolyData):
        pd = vtkPolyData()
        pd.DeepCopy(points)
        xyz = (
            numpy_support.vtk_to_numpy(pd.GetPoints().GetData()).astype(float)
            if pd.GetPoints() is not None
            else np.empty((0, 3))
        )
    else:
        from BoneUSRecon.Logic.vtkio import points_to_polydata

        xyz = np.asarray(points, float).reshape(-1, 3)
        pd = points_to_polydata(xyz)
    if node is None:
        node = scene.AddNewNodeByClass("vtkMRMLModelNode", name)
    if node.IsA("vtkMRMLMarkupsFiducialNode"):
        vp = vtkPoints()
        vp.SetData(numpy_support.numpy_to_vtk(np.ascontiguousarray(xyz), deep=True))
        node.RemoveAllControlPoints()
        node.SetControlPointPositionsWorld(vp)
        node.SetLocked(True)
        disp = _ensure_display(node)
        if disp is not None:
            disp.SetPointLabelsVisibility(False)
            disp.SetSelectedColor(1.0, 0.85, 0.0)
        return node
    if not node.IsA("vtkMRMLModelNode"):
        raise BoneUSReconError(
            f"the output points must be a model or markups fiducial node, got {_node_label(node)}"
        )
    node.SetAndObservePolyData(pd)
    disp = _ensure_display(node)
    disp.SetScalarVisibility(False)
    disp.SetColor(1.0, 0.85, 0.0)  # yellow, as the segmented points in the paper's Fig. 4
    disp.SetPointSize(4.0)
    disp.SetRepresentation(disp.PointsRepresentation)
    disp.SetVisibility(True)
    return node

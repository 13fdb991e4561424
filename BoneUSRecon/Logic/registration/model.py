"""The target bone model: checked (triangles, manifold) and sampled for ICP."""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from BoneUSRecon.Logic.errors import BoneUSReconError

__all__ = ["BoneModel", "bone_model", "model_from_polydata"]


@dataclass(frozen=True, eq=False)
class BoneModel:
    """A target bone model prepared for ICP: sample points with normals and a kd-tree.

    Attributes
    ----------
    vertices : ndarray (V, 3)
    faces : ndarray (F, 3)
    points : ndarray (M, 3)
        Vertices with a normal, then triangle centres: what ICP matches against.
    normals : ndarray (M, 3)
        Unit normals at ``points`` (area-weighted at vertices).
    border : ndarray of bool (M,)
        On the model's open border (a cropped model): never matched.
    tree : cKDTree
        Over ``points``.
    """

    vertices: np.ndarray
    faces: np.ndarray
    points: np.ndarray
    normals: np.ndarray
    border: np.ndarray
    tree: cKDTree

    @property
    def extent_mm(self) -> float:
        """Diagonal of the bounding box (mm)."""
        return float(np.linalg.norm(np.ptp(self.vertices, axis=0)))

    @property
    def n_border_edges(self) -> int:
        return int(self.border.sum())


def bone_model(
    vertices: np.ndarray, faces: np.ndarray, path: str | os.PathLike[str] | None = None
) -> BoneModel:
    """Check a triangle mesh and prepare it for :func:`register`.

    Parameters
    ----------
    vertices : ndarray (V, 3)
        Coordinates (mm).
    faces : ndarray of int (F, 3)
    path : path-like, optional
        The file it came from, named in errors.

    Raises
    ------
    BoneUSReconError
        No triangles, non-finite coordinates, a flat or point-sized model, or a
        non-manifold mesh (an edge shared by more than two triangles: several
        surfaces glued together, normals meaningless there).
    """
    v = np.asarray(vertices, float).reshape(-1, 3)
    f = np.asarray(faces, np.int64).reshape(-1, 3)
    if f.shape[0] == 0 or v.shape[0] < 3:
        raise BoneUSReconError(
            "the model has no triangles (empty, or a point cloud: a bone model must be a surface mesh)",
            path,
        )
    if f.min() < 0 or f.max() >= v.shape[0]:
        raise BoneUSReconError("the model's triangles refer to missing vertices", path)
    if not np.isfinite(v).all():
        raise BoneUSReconError("the model has NaN or infinite coordinates", path)
    fn = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    area2 = np.linalg.norm(fn, axis=1)
    keep = area2 > 1e-12 * max(float(np.ptp(v, axis=0).max()) ** 2, 1e-300)
    f, fn, area2 = f[keep], fn[keep], area2[keep]
    if f.shape[0] == 0:
        raise BoneUSReconError("the model's triangles all have zero area", path)
    edges = np.sort(np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]]), axis=1)
    key = edges[:, 0] * np.int64(v.shape[0]) + edges[:, 1]
    uniq, inv, counts = np.unique(key, return_inverse=True, return_counts=True)
    if (counts > 2).any():
        n_bad = int((counts > 2).sum())
        raise BoneUSReconError(
            f"the model is not a manifold surface: {n_bad} edges are shared by more than two "
            "triangles (clean it, e.g. keep the largest connected surface, before registering)",
            path,
        )
    # Vertex normals: area-weighted sums of the triangle normals around each vertex.
    vn = np.zeros_like(v)
    for c in range(3):
        for k in range(3):
            vn[:, k] += np.bincount(f[:, c], weights=fn[:, k], minlength=v.shape[0])
    nlen = np.linalg.norm(vn, axis=1)
    used = nlen > 0
    on_border_edge = (counts == 1)[inv].reshape(3, -1).T  # (F, 3): edge 01, 12, 20
    border_v = np.zeros(v.shape[0], bool)
    for k, (a, b) in enumerate(((0, 1), (1, 2), (2, 0))):
        border_v[f[on_border_edge[:, k], a]] = True
        border_v[f[on_border_edge[:, k], b]] = True
    border_f = on_border_edge.any(axis=1)
    pts = np.concatenate([v[used], v[f].mean(axis=1)])
    nrm = np.concatenate([vn[used] / nlen[used, None], fn / area2[:, None]])
    border = np.concatenate([border_v[used], border_f])
    ext = np.ptp(v, axis=0)
    if np.sort(ext)[1] <= 1e-9:
        raise BoneUSReconError("the model is flat or a line (no volume to register to)", path)
    return BoneModel(v, f, pts, nrm, border, cKDTree(pts))


def model_from_polydata(pd: Any, path: str | os.PathLike[str] | None = None) -> BoneModel:
    """:func:`bone_model` of a ``vtkPolyData`` (polygons and strips triangulated)."""
    from vtkmodules.util import numpy_support
    from vtkmodules.vtkFiltersCore import vtkTriangleFilter

    if (
        pd is None
        or pd.GetNumberOfPoints() == 0
        or pd.GetNumberOfPolys() + pd.GetNumberOfStrips() == 0
    ):
        raise BoneUSReconError(
            "the model has no triangles (empty, or a point cloud: a bone model must be a surface mesh)",
            path,
        )
    tf = vtkTriangleFilter()
    tf.SetInputData(pd)
    tf.PassVertsOff()
    tf.PassLinesOff()
    tf.Update()
    out = tf.GetOutput()
    v = numpy_support.vtk_to_numpy(out.GetPoints().GetData()).astype(float)
    conn = numpy_support.vtk_to_numpy(out.GetPolys().GetConnectivityArray()).astype(np.int64)
    return bone_model(v, conn.reshape(-1, 3), path)

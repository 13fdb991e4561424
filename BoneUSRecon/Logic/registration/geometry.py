"""Rigid-transform helpers: applying, comparing, landmarks, principal axes, units."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.registration.model import BoneModel

__all__ = [
    "transform_points",
    "transform_polydata",
    "rotation_matrix",
    "rigid_error",
    "landmark_transform",
    "principal_axes",
    "check_units",
    "patch_normal",
]


def transform_points(matrix: np.ndarray, points: np.ndarray) -> np.ndarray:
    """``points (K, 3)`` mapped by the homogeneous ``matrix (4, 4)``."""
    m = np.asarray(matrix, float)
    return np.asarray(points, float).reshape(-1, 3) @ m[:3, :3].T + m[:3, 3]


def transform_polydata(pd: Any, matrix: np.ndarray) -> Any:
    """A copy of ``pd`` moved by ``matrix`` (points, normals and every array kept)."""
    from vtkmodules.vtkCommonTransforms import vtkTransform
    from vtkmodules.vtkFiltersGeneral import vtkTransformPolyDataFilter

    from BoneUSRecon.Logic.sweep import matrix_to_vtk

    t = vtkTransform()
    t.SetMatrix(matrix_to_vtk(np.asarray(matrix, float)))
    f = vtkTransformPolyDataFilter()
    f.SetTransform(t)
    f.SetInputData(pd)
    f.Update()
    return f.GetOutput()


def rotation_matrix(w: np.ndarray) -> np.ndarray:
    """Rotation matrix of the rotation vector ``w`` (rad), Rodrigues' formula."""
    a = float(np.linalg.norm(w))
    if a < 1e-15:
        return np.eye(3)
    k = w / a
    kx = np.array([[0, -k[2], k[1]], [k[2], 0, -k[0]], [-k[1], k[0], 0]])
    return np.eye(3) + np.sin(a) * kx + (1 - np.cos(a)) * (kx @ kx)


def rigid_error(estimate: np.ndarray, truth: np.ndarray, points: np.ndarray) -> dict[str, float]:
    """How far ``estimate`` is from ``truth``: target error at ``points`` and the pose error.

    Parameters
    ----------
    estimate, truth : ndarray (4, 4)
        SOURCE -> TARGET transforms.
    points : ndarray (K, 3)
        Targets in SOURCE coordinates (e.g. the imaged bone surface).

    Returns
    -------
    dict
        ``tre_median_mm``, ``tre_p95_mm``, ``tre_max_mm`` (distance between the two
        images of each point), ``rotation_deg`` (angle of the residual rotation) and
        ``translation_mm`` (of the points' centroid).
    """
    p = np.asarray(points, float).reshape(-1, 3)
    d = np.linalg.norm(transform_points(estimate, p) - transform_points(truth, p), axis=1)
    r = np.asarray(estimate, float)[:3, :3] @ np.asarray(truth, float)[:3, :3].T
    ang = float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1.0, 1.0))))
    c = p.mean(axis=0)
    dc = float(
        np.linalg.norm(transform_points(estimate, c[None]) - transform_points(truth, c[None]))
    )
    return {
        "tre_median_mm": float(np.median(d)),
        "tre_p95_mm": float(np.percentile(d, 95)),
        "tre_max_mm": float(d.max()),
        "rotation_deg": ang,
        "translation_mm": dc,
    }


def landmark_transform(source: np.ndarray, target: np.ndarray) -> tuple[np.ndarray, float]:
    """Least-squares rigid transform of paired points (Kabsch / Horn, no scaling).

    Parameters
    ----------
    source, target : ndarray (K, 3)
        The same K >= 3 anatomical points in SOURCE and TARGET coordinates (mm).

    Returns
    -------
    matrix : ndarray (4, 4)
        SOURCE -> TARGET.
    rms : float
        Fiducial registration error: RMS distance between the mapped source
        landmarks and the target ones (mm).

    Raises
    ------
    BoneUSReconError
        Fewer than 3 pairs, different counts, non-finite values, or (nearly) collinear
        landmarks (a rotation about their line is then free).

    Examples
    --------
    >>> s = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10]])
    >>> m, e = landmark_transform(s, s + [1.0, 2.0, 3.0])
    >>> np.round(m[:3, 3], 6).tolist(), round(e, 9)
    ([1.0, 2.0, 3.0], 0.0)
    """
    s = np.asarray(source, float)
    t = np.asarray(target, float)
    if s.ndim != 2 or s.shape[1:] != (3,) or t.ndim != 2 or t.shape[1:] != (3,):
        raise BoneUSReconError(f"landmarks must be (K, 3) arrays, got {s.shape} and {t.shape}")
    if s.shape[0] != t.shape[0]:
        raise BoneUSReconError(
            f"the two landmark files hold {s.shape[0]} and {t.shape[0]} points; they must be the same points, paired in order"
        )
    if s.shape[0] < 3:
        raise BoneUSReconError(
            f"need at least 3 paired landmarks for a rigid transform, got {s.shape[0]}"
        )
    if not (np.isfinite(s).all() and np.isfinite(t).all()):
        raise BoneUSReconError("landmarks contain NaN or infinity")
    cs, ct = s.mean(0), t.mean(0)
    for name, x in (("source", s - cs), ("target", t - ct)):
        sv = np.linalg.svd(x, compute_uv=False)
        if sv[1] < 1e-3 * max(sv[0], 1e-300) or sv[1] < 1e-6:
            raise BoneUSReconError(
                f"the {name} landmarks are (nearly) on one line: a rotation about it would be free; "
                "choose at least 3 points that are not aligned"
            )
    h = (s - cs).T @ (t - ct)
    u, _, vt = np.linalg.svd(h)
    d = np.sign(np.linalg.det(vt.T @ u.T)) or 1.0
    r = vt.T @ np.diag([1.0, 1.0, d]) @ u.T
    m = np.eye(4)
    m[:3, :3] = r
    m[:3, 3] = ct - r @ cs
    rms = float(np.sqrt(np.mean(np.sum((transform_points(m, s) - t) ** 2, axis=1))))
    return m, rms


def principal_axes(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Centroid, axes (rows, decreasing variance, right-handed) and singular values."""
    c = p.mean(axis=0)
    _, sv, vt = np.linalg.svd(p - c, full_matrices=False)
    if np.linalg.det(vt) < 0:
        vt[2] = -vt[2]
    return c, vt, sv / np.sqrt(max(len(p), 1))


def check_units(
    source: np.ndarray,
    model: BoneModel,
    source_path: str | os.PathLike[str] | None = None,
    model_path: str | os.PathLike[str] | None = None,
) -> None:
    """Refuse inputs whose sizes say they are not both in millimetres.

    A bone model exported in metres is 1000x too small: the closest fit would be a
    point-sized model inside the sweep, reported with a large residual at best. A
    localized sweep sees a few cm of one bone, so its extent is at most a few times
    the model's and at least ~1/50 of it (a 10 mm patch of a 500 mm femur); a ratio of
    ~1000 either way means metres (a human bone is 10-600 mm long, a sweep 5-300 mm).

    Raises
    ------
    BoneUSReconError
        Names the input that looks like metres (or another unit) and both sizes.
    """
    ext_s = float(np.linalg.norm(np.ptp(np.asarray(source, float).reshape(-1, 3), axis=0)))
    ext_m = model.extent_mm
    if ext_s <= 0:
        raise BoneUSReconError("the source points all coincide", source_path)
    ratio = ext_s / ext_m
    if ratio > 20.0:
        unit = (
            " (is it in metres? it would be about 1000x too small)" if 200 <= ratio <= 5000 else ""
        )
        raise BoneUSReconError(
            f"the model is {ext_m:.4g} across but the source {ext_s:.4g}: both must be in mm{unit}",
            model_path,
        )
    if ratio < 1.0 / 200.0:
        unit = (
            " (is it in metres? it would be about 1000x too small)"
            if 1 / 5000 <= ratio <= 1 / 200
            else ""
        )
        raise BoneUSReconError(
            f"the source is {ext_s:.4g} across but the model {ext_m:.4g}: both must be in mm{unit}",
            source_path,
        )


def patch_normal(points: np.ndarray) -> np.ndarray:
    """The mean normal of a point cloud seen from one side: its least principal axis.

    An ultrasound sweep sees the bone from the probe's side only, so its points form a
    patch whose local normals stay within ~70 deg of this axis, while the far side of
    the bone faces away. (Local normals from neighbours are no substitute: segmented
    points lie on contours ~0.1-0.3 mm apart within a frame and 1-3 mm apart across
    frames, so their neighbourhoods are lines, whose normal is undefined.) Which side
    is out is unknown: :func:`register` tries both.
    """
    return principal_axes(np.asarray(points, float).reshape(-1, 3))[1][2]

"""Rigid registration of the reconstructed bone (or its segmented points) to a bone model.

The paper's purpose is navigation: the bone surface seen by localized ultrasound is
registered to the pre-operative CT (or MRI) model. :func:`register` finds the rigid
transform ``T`` (4x4, mm) that maps SOURCE coordinates (the sweep's reference frame) to
TARGET coordinates (the model's), in three steps:

1. **Initial alignment** (:class:`RegistrationParams.init`): the identity or a given
   matrix (the sweep is already roughly in the model's frame), paired landmarks
   (Kabsch/Horn least squares, :func:`landmark_transform`), or a global search over
   the principal axes' ambiguities (axis sign, roll, position along the model).
2. **Robust point-to-plane ICP**: nearest model point (``scipy.spatial.cKDTree`` on
   the model's vertices and triangle centres, each with its normal), Tukey's biweight
   on the point-to-plane residuals at a MAD scale, correspondences gated by distance
   and never on the model's open border (a cropped model), a damped 6x6 Gauss-Newton
   step. The robust weights handle the outliers and the partial overlap a localized
   sweep implies (it sees the top of a few cm of one bone).
3. **Honest quality figures** (:class:`Registration`): residual RMS, median and p95,
   inlier share, and how well the surface pins each degree of freedom: the
   eigenvalues of the 6x6 point-to-plane normal matrix (rotations scaled by the
   source's radius, so all six are in mm^2 per mm^2). A weak eigenvalue turns into a
   *sliding range*: how far the source can move along that direction before its RMS
   residual grows by the residual itself. A straight featureless shaft slides along its
   axis and turns about it; the result then says so by name and is not ``reliable``.

Why not a library ICP: small_gicp (fast C++ point-to-plane and GICP) estimates normals
from neighbouring points and rejects outliers only by a hard distance cut; Open3D is a
large dependency with the same hard cut. The model here has exact mesh normals, the
robust weights and the normal matrix are what the quality figures need, and the only
heavy part (nearest neighbours) is scipy's C kd-tree, so the loop is ~100 lines of
numpy and a 6x6 solve per iteration.
"""

from __future__ import annotations

import os
import time
from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np
from scipy.spatial import cKDTree

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.robust import mad_scale, robust_weights

__all__ = [
    "INIT_METHODS",
    "RegistrationParams",
    "Registration",
    "BoneModel",
    "bone_model",
    "model_from_polydata",
    "landmark_transform",
    "check_units",
    "register",
    "register_polydata",
    "patch_normal",
    "transform_points",
    "transform_polydata",
    "rigid_error",
]

#: Initial alignments :func:`register` knows.
INIT_METHODS = ("identity", "landmarks", "search")


@dataclass(frozen=True)
class RegistrationParams:
    """Parameters of :func:`register` (mm, degrees, shares in 0..1).

    Attributes
    ----------
    init : {"identity", "landmarks", "search"}
        Initial alignment. ``"identity"``: the given ``init`` matrix (default the
        identity), for a sweep already roughly (within ~15 mm / 15 deg) in the model's
        frame, e.g. after a tracked pointer touched the bone. ``"landmarks"``: the
        least-squares fit of >= 3 paired points. ``"search"``: principal axes of source
        and model with their ambiguities tried (see :func:`register`).
    max_distance_mm : float
        Correspondences farther than this from the model are ignored at the start
        (mm). 25: a 15 mm / 15 deg start moves points of a 60 mm patch by up to ~23 mm.
    min_distance_mm : float
        The distance gate shrinks with the residual scale (10 scales) but never below
        this (mm). 2: a few times the ~0.3 mm accuracy of a reconstructed surface, so a
        good point is never cut.
    noise_floor_mm : float
        Floor on the robust residual scale (mm): residuals below it count as exact. 0.1:
        below the ~0.2 mm error of our reconstructions (Testing/benchmarks/README.md).
    robust : {"tukey", "huber", "none"}
        Weights of the point-to-plane residuals (Tukey's biweight gives gross outliers
        weight 0; :mod:`.robust`).
    max_iterations : int
        ICP iterations at most. 100: from 15 mm / 15 deg away the point-to-plane steps
        converge in 10-30 (measured on the simulated sweeps).
    tolerance_mm : float
        Stop when an iteration moves no source point by more than this (mm).
    max_source_points : int
        Source points used by the iterations (a deterministic random subset; the final
        figures use all points). 2500: the transform's precision saturates far below
        (measured: the same target error with 4000), and an iteration stays ~10 ms.
    damping : float
        Levenberg damping of the 6x6 step, relative to its largest eigenvalue. 1e-6
        keeps an unconstrained direction (a cylinder's axis) from drifting in each
        step while leaving constrained ones untouched.
    min_overlap : float
        Below this share of source points near the model (at the start, or as inliers
        at the end) the inputs do not overlap: an error, not a transform. 0.2.
    min_inlier_share : float
        Below this share of inliers the result is flagged unreliable. 0.6: a good
        registration of our reconstructions keeps > 90 %.
    max_rms_mm : float
        Above this inlier residual RMS (mm) the result is flagged unreliable: the
        shapes do not match (wrong bone, wrong side, a wrong local optimum). 1.0.
    max_sliding_mm : float
        A degree of freedom whose sliding range (see the module docstring) exceeds this
        (mm) is weakly constrained; the result is then flagged unreliable. Also the
        distance beyond which two alignments count as different. 2.0: the target error
        a trusted registration must meet (issue 14).
    search_offsets_mm : float
        ``"search"``: step of the positions tried along the model's long axis (mm).
    search_rolls : int
        ``"search"``: rotations about the long axis tried (evenly spaced).
    max_normal_angle_deg : float
        A source point pairs only with model points whose normal is within this angle
        of its own (degrees): 60, well beyond the 15 deg of a poor start, well short of
        the 180 deg of the far side of a thin bone.
    patch_normal_angle_deg : float
        The same for a source without normals, whose points all take the patch's mean
        normal (:func:`patch_normal`; degrees). 80: the top of a shaft seen by a
        sweep has normals up to ~70 deg from its mean; the far side is beyond 110.
    start_rolls_deg, start_shifts_mm : tuple of float
        Besides the initial alignment, ICP also starts rolled by +- each angle about
        the source's long axis and shifted by +- each distance along it (every
        combination; see ``_local_starts``): the local optima of a patch of a shaft.
        15 deg and 10 mm: 9 starts; the best is kept, and a distinct one fitting about
        as well flags the result as ambiguous.
    coarse_iterations : int
        ICP iterations per start on a subset before the best is refined.
    coarse_points : int
        Size of that subset. 300: enough to rank basins apart by their residual
        (they differ by millimetres), cheap enough for 9 starts.
    """

    init: str = "identity"
    max_distance_mm: float = 25.0
    min_distance_mm: float = 2.0
    noise_floor_mm: float = 0.1
    robust: str = "tukey"
    max_iterations: int = 100
    tolerance_mm: float = 1e-4
    max_source_points: int = 2500
    damping: float = 1e-6
    min_overlap: float = 0.2
    min_inlier_share: float = 0.6
    max_rms_mm: float = 1.0
    max_sliding_mm: float = 2.0
    search_offsets_mm: float = 10.0
    search_rolls: int = 8
    max_normal_angle_deg: float = 60.0
    patch_normal_angle_deg: float = 80.0
    start_rolls_deg: tuple[float, ...] = (15.0,)
    start_shifts_mm: tuple[float, ...] = (10.0,)
    coarse_iterations: int = 12
    coarse_points: int = 300

    def __post_init__(self) -> None:
        if self.init not in INIT_METHODS:
            raise BoneUSReconError(
                f"RegistrationParams.init must be one of {', '.join(INIT_METHODS)}, got {self.init!r}"
            )
        if self.robust not in ("tukey", "huber", "none"):
            raise BoneUSReconError(
                f"RegistrationParams.robust must be tukey, huber or none, got {self.robust!r}"
            )
        for name in (
            "max_distance_mm",
            "min_distance_mm",
            "noise_floor_mm",
            "tolerance_mm",
            "max_rms_mm",
            "max_sliding_mm",
            "search_offsets_mm",
            "max_normal_angle_deg",
            "patch_normal_angle_deg",
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, float)) and np.isfinite(v) and v > 0):
                raise BoneUSReconError(
                    f"RegistrationParams.{name} must be a positive number, got {v!r}"
                )
        if self.min_distance_mm > self.max_distance_mm:
            raise BoneUSReconError(
                f"RegistrationParams.min_distance_mm ({self.min_distance_mm}) exceeds max_distance_mm ({self.max_distance_mm})"
            )
        for name in ("min_overlap", "min_inlier_share"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise BoneUSReconError(
                    f"RegistrationParams.{name} must be between 0 and 1, got {v!r}"
                )
        for name, lo in (
            ("max_iterations", 1),
            ("max_source_points", 50),
            ("search_rolls", 1),
            ("coarse_points", 50),
            ("coarse_iterations", 1),
        ):
            v = getattr(self, name)
            if not (isinstance(v, (int, np.integer)) and v >= lo):
                raise BoneUSReconError(
                    f"RegistrationParams.{name} must be an integer >= {lo}, got {v!r}"
                )
        for name in ("start_rolls_deg", "start_shifts_mm"):
            v = getattr(self, name)
            if not (
                isinstance(v, tuple)
                and all(isinstance(x, (int, float)) and np.isfinite(x) and x > 0 for x in v)
            ):
                raise BoneUSReconError(
                    f"RegistrationParams.{name} must be a tuple of positive numbers, got {v!r}"
                )
        if not (0.0 <= self.damping < 1.0):
            raise BoneUSReconError(
                f"RegistrationParams.damping must be in [0, 1), got {self.damping!r}"
            )


@dataclass(frozen=True, eq=False)
class Registration:
    """A rigid registration and its quality figures (mm unless said).

    Attributes
    ----------
    matrix : ndarray (4, 4)
        SOURCE -> TARGET (``x_target = matrix @ x_source``, homogeneous, mm).
    initial : ndarray (4, 4)
        The initial alignment ICP started from.
    rms_mm, median_mm, p95_mm : float
        Point-to-plane residuals of the inliers at the end.
    inlier_share : float
        Share of the source points kept by the robust weights and the distance gate.
    n_source, n_inliers : int
    iterations : int
    converged : bool
        The last step moved no point by more than the tolerance.
    eigenvalues : ndarray (6,)
        Of the normalised 6x6 point-to-plane normal matrix, increasing (unitless:
        mean squared residual change per squared mm of motion; rotations in mm at the
        source's RMS radius).
    condition : float
        Largest over smallest eigenvalue.
    sliding_mm : ndarray (6,)
        For each eigen-direction, the motion (mm) that grows the residual RMS by
        ``sqrt(2)``: ``residual / sqrt(eigenvalue)``.
    directions : tuple of str
        Each eigen-direction in words (``"translation along the bone's long axis"``).
    reliable : bool
        No reason below.
    reasons : tuple of str
        Why the result should not be trusted (weak directions named), empty if reliable.
    landmark_rms_mm : float or None
        Fiducial registration error of the landmarks (their RMS residual) when used.
    long_axis : ndarray (3,)
        The source's principal direction (its long axis), in source coordinates.
    seconds : float
    """

    matrix: np.ndarray
    initial: np.ndarray
    rms_mm: float
    median_mm: float
    p95_mm: float
    inlier_share: float
    n_source: int
    n_inliers: int
    iterations: int
    converged: bool
    eigenvalues: np.ndarray
    condition: float
    sliding_mm: np.ndarray
    directions: tuple[str, ...]
    reliable: bool
    reasons: tuple[str, ...]
    landmark_rms_mm: float | None = None
    long_axis: np.ndarray = field(default_factory=lambda: np.zeros(3))
    seconds: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        """Plain-Python summary (JSON-ready)."""
        d = asdict(self)
        for k, v in d.items():
            if isinstance(v, np.ndarray):
                d[k] = v.tolist()
            elif isinstance(v, tuple):
                d[k] = list(v)
        return d

    def summary_rows(self) -> list[tuple[str, str]]:
        """``(key, value)`` lines for a human summary (CLI, Slicer panel)."""
        weak = int(np.argmin(self.eigenvalues))
        rows = [
            (
                "residual RMS/median/p95",
                f"{self.rms_mm:.3f} / {self.median_mm:.3f} / {self.p95_mm:.3f} mm",
            ),
            ("inliers", f"{self.n_inliers} of {self.n_source} ({100 * self.inlier_share:.1f}%)"),
            ("iterations", f"{self.iterations}{'' if self.converged else ' (not converged)'}"),
            (
                "weakest direction",
                f"{self.directions[weak]}: slides {_fmt_mm(self.sliding_mm[weak])}",
            ),
            ("condition", f"{self.condition:.3g}"),
        ]
        if self.landmark_rms_mm is not None:
            rows.append(("landmark RMS", f"{self.landmark_rms_mm:.3f} mm"))
        rows.append(("reliable", "yes" if self.reliable else "NO: " + "; ".join(self.reasons)))
        return rows


def _fmt_mm(v: float) -> str:
    return "unbounded" if not np.isfinite(v) or v > 1e4 else f"{v:.2f} mm"


# ------------------------------------------------------------------------------------
# The model
# ------------------------------------------------------------------------------------
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


# ------------------------------------------------------------------------------------
# Small geometry helpers
# ------------------------------------------------------------------------------------
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


def _rotation(w: np.ndarray) -> np.ndarray:
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


def _principal_axes(p: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
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


# ------------------------------------------------------------------------------------
# ICP
# ------------------------------------------------------------------------------------
@dataclass
class _IcpState:
    matrix: np.ndarray
    iterations: int = 0
    converged: bool = False
    scale: float = 1.0
    gate: float = 1.0


@dataclass(frozen=True, eq=False)
class _Cloud:
    """Source points with unit normals and the angle a model normal may differ by."""

    points: np.ndarray
    normals: np.ndarray
    max_angle_deg: float

    def subset(self, k: int) -> _Cloud:
        """A deterministic random subset of at most ``k`` points."""
        if len(self.points) <= k:
            return self
        idx = np.sort(np.random.default_rng(0).choice(len(self.points), size=k, replace=False))
        return _Cloud(self.points[idx], self.normals[idx], self.max_angle_deg)

    def flipped(self) -> _Cloud:
        return _Cloud(self.points, -self.normals, self.max_angle_deg)


#: Nearest model points considered per source point: the nearest one that faces the
#: same way and is not on the border is used.
_K_NEAREST = 4


def _match(
    model: BoneModel, m: np.ndarray, src: _Cloud, gate: float, params: RegistrationParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Correspondences at pose ``m``: (moved points, mask into them, residuals, normals).

    A source point pairs with the nearest model point within ``gate`` that is not on
    the model's open border and, when the source has normals, whose normal is within
    ``src.max_angle_deg`` of the source's: a patch pushed inside a thin bone would
    otherwise pair with the far side of the bone and flip onto it.
    """
    p = transform_points(m, src.points)
    d, idx = model.tree.query(p, k=_K_NEAREST, distance_upper_bound=gate)
    good = np.isfinite(d)
    jj = np.where(good, idx, 0)
    good &= ~model.border[jj]
    ns = src.normals @ m[:3, :3].T
    cosang = np.einsum("kj,kij->ki", ns, model.normals[jj])
    good &= cosang >= np.cos(np.radians(src.max_angle_deg))
    ok = good.any(axis=1)
    first = np.argmax(good, axis=1)
    j = jj[np.arange(len(p)), first][ok]
    n = model.normals[j]
    r = np.einsum("ij,ij->i", p[ok] - model.points[j], n)
    return p, ok, r, n


def _weights(r: np.ndarray, params: RegistrationParams) -> tuple[np.ndarray, float]:
    scale = mad_scale(r, params.noise_floor_mm)
    if params.robust == "none":
        return np.ones_like(r), scale
    return robust_weights(r, scale, params.robust), scale


def _icp(
    src: _Cloud,
    model: BoneModel,
    init: np.ndarray,
    params: RegistrationParams,
    *,
    max_iterations: int | None = None,
    tolerance_mm: float | None = None,
) -> _IcpState:
    """Robust point-to-plane ICP from ``init``; returns the final state."""
    tol = params.tolerance_mm if tolerance_mm is None else tolerance_mm
    st = _IcpState(matrix=np.array(init, float), gate=params.max_distance_mm)
    pts = src.points
    radius = float(np.sqrt(np.mean(np.sum((pts - pts.mean(0)) ** 2, axis=1)))) or 1.0
    n_iter = params.max_iterations if max_iterations is None else max_iterations
    for it in range(n_iter):
        m = st.matrix
        p, ok, r, n = _match(model, m, src, st.gate, params)
        if ok.sum() < 6:
            break
        w, scale = _weights(r, params)
        st.scale = scale
        q = p[ok]
        c = np.average(q, axis=0, weights=w) if w.sum() > 0 else q.mean(0)
        jac = np.hstack([np.cross(q - c, n), n])  # d r / d (omega, t), about c
        a = jac.T @ (w[:, None] * jac)
        b = -jac.T @ (w * r)
        lam = params.damping * max(float(np.linalg.eigvalsh(a)[-1]), 1e-12)
        x = np.linalg.solve(a + lam * np.eye(6), b)
        dr = _rotation(x[:3])
        step = np.eye(4)
        step[:3, :3] = dr
        step[:3, 3] = c - dr @ c + x[3:]
        st.matrix = step @ m
        st.iterations = it + 1
        # The gate follows the residual scale: wide while far, tight once aligned.
        st.gate = float(
            np.clip(10.0 * 4.685 * scale, params.min_distance_mm, params.max_distance_mm)
        )
        if np.linalg.norm(x[:3]) * radius + np.linalg.norm(x[3:]) < tol:
            st.converged = True
            break
    return st


def _describe(v: np.ndarray, radius: float, long_axis: np.ndarray, centre: np.ndarray) -> str:
    """One eigen-direction ``(omega * radius, t)`` of the normal matrix in words."""
    rot, tr = v[:3], v[3:]
    if rot @ rot >= tr @ tr:
        ax = rot / np.linalg.norm(rot)
        if abs(ax @ long_axis) > np.cos(np.radians(25)):
            return "rotation about the bone's long axis"
        return f"rotation about the axis ({ax[0]:+.2f}, {ax[1]:+.2f}, {ax[2]:+.2f}) through ({centre[0]:.1f}, {centre[1]:.1f}, {centre[2]:.1f}) mm"
    d = tr / np.linalg.norm(tr)
    if abs(d @ long_axis) > np.cos(np.radians(25)):
        return "translation along the bone's long axis"
    return f"translation along ({d[0]:+.2f}, {d[1]:+.2f}, {d[2]:+.2f})"


def _quality(
    cloud: _Cloud, model: BoneModel, st: _IcpState, params: RegistrationParams
) -> dict[str, Any]:
    """Residuals, inliers and the constraint analysis at the final transform (all points)."""
    src = cloud.points
    gate = float(np.clip(10.0 * 4.685 * st.scale, params.min_distance_mm, params.max_distance_mm))
    p, ok, r, n = _match(model, st.matrix, cloud, gate, params)
    w, scale = _weights(r, params) if r.size else (np.zeros(0), params.noise_floor_mm)
    inl = w > 0
    res = np.abs(r[inl])
    n_in = int(inl.sum())
    out: dict[str, Any] = {
        "n_inliers": n_in,
        "inlier_share": n_in / max(len(src), 1),
        "rms_mm": float(np.sqrt(np.mean(res**2))) if n_in else float("nan"),
        "median_mm": float(np.median(res)) if n_in else float("nan"),
        "p95_mm": float(np.percentile(res, 95)) if n_in else float("nan"),
    }
    # The source's own long axis, in target coordinates (where the analysis is done).
    _, axes, _ = _principal_axes(src)
    long_axis = st.matrix[:3, :3] @ axes[0]
    out["long_axis"] = axes[0]
    if n_in < 6:
        out.update(
            eigenvalues=np.zeros(6),
            condition=float("inf"),
            sliding_mm=np.full(6, np.inf),
            directions=("all six degrees of freedom",) * 6,
        )
        return out
    q, nn, ww = p[ok][inl], n[inl], w[inl]
    c = np.average(q, axis=0, weights=ww)
    radius = float(np.sqrt(np.average(np.sum((q - c) ** 2, axis=1), weights=ww)))
    jac = np.hstack([np.cross(q - c, nn) / radius, nn])
    a = jac.T @ (ww[:, None] * jac) / ww.sum()
    evals, evecs = np.linalg.eigh(a)
    evals = np.maximum(evals, 0.0)
    # The residual a weak direction must overcome: the observed scatter, floored.
    sigma = max(out["rms_mm"], params.noise_floor_mm)
    with np.errstate(divide="ignore"):
        sliding = np.where(evals > 0, sigma / np.sqrt(evals), np.inf)
    dirs = tuple(_describe(evecs[:, k], radius, long_axis, c) for k in range(6))
    out.update(
        eigenvalues=evals,
        condition=float(evals[-1] / evals[0]) if evals[0] > 0 else float("inf"),
        sliding_mm=sliding,
        directions=dirs,
    )
    return out


def _reasons(q: dict[str, Any], st: _IcpState, params: RegistrationParams) -> list[str]:
    reasons = []
    for k in np.argsort(q["sliding_mm"])[::-1]:
        s = q["sliding_mm"][k]
        if s > params.max_sliding_mm:
            what = (
                "unconstrained"
                if s > 20 * params.max_sliding_mm
                else f"weakly constrained (slides {s:.1f} mm)"
            )
            reasons.append(
                f"{q['directions'][k]} is {what}: the imaged surface lacks features in that direction"
            )
    if q["inlier_share"] < params.min_inlier_share:
        reasons.append(
            f"only {100 * q['inlier_share']:.0f}% of the source points fit the model "
            f"(at least {100 * params.min_inlier_share:.0f}% expected)"
        )
    if not q["rms_mm"] <= params.max_rms_mm:
        reasons.append(
            f"residual RMS {q['rms_mm']:.2f} mm exceeds {params.max_rms_mm:g} mm: the shapes do not match well"
        )
    if not st.converged:
        reasons.append(f"ICP did not converge in {st.iterations} iterations")
    return reasons


def patch_normal(points: np.ndarray) -> np.ndarray:
    """The mean normal of a point cloud seen from one side: its least principal axis.

    An ultrasound sweep sees the bone from the probe's side only, so its points form a
    patch whose local normals stay within ~70 deg of this axis, while the far side of
    the bone faces away. (Local normals from neighbours are no substitute: segmented
    points lie on contours ~0.1-0.3 mm apart within a frame and 1-3 mm apart across
    frames, so their neighbourhoods are lines, whose normal is undefined.) Which side
    is out is unknown: :func:`register` tries both.
    """
    return _principal_axes(np.asarray(points, float).reshape(-1, 3))[1][2]


def _search_inits(
    src: np.ndarray, model: BoneModel, params: RegistrationParams
) -> list[np.ndarray]:
    """Candidate initial transforms from the principal axes, with their ambiguities.

    The source (a patch of one bone) and the model (the whole bone) share a long axis,
    not a centroid nor the two short axes: try both signs of the long axis, rolls about
    it, and positions along the model's length.
    """
    cs, axs, _ = _principal_axes(src)
    cm, axm, svm = _principal_axes(model.vertices)
    half = np.ptp(model.vertices @ axm[0]) / 2
    len_s = np.ptp(src @ axs[0])
    span = max(half - len_s / 2, 0.0)
    offsets = np.arange(-span, span + 1e-9, params.search_offsets_mm) if span > 0 else np.zeros(1)
    out = []
    for sign in (1.0, -1.0):
        for k in range(params.search_rolls):
            roll = _rotation(axm[0] * (2 * np.pi * k / params.search_rolls))
            a_s = np.array([sign * axs[0], sign * axs[1], axs[2]])  # right-handed either way
            r = roll @ axm.T @ a_s
            for off in offsets:
                m = np.eye(4)
                m[:3, :3] = r
                m[:3, 3] = cm + axm[0] * off - r @ cs
                out.append(m)
    return out


def _local_starts(src: np.ndarray, m0: np.ndarray, params: RegistrationParams) -> list[np.ndarray]:
    """Starts around ``m0``: rolls about and shifts along the source's long axis.

    Point-to-plane ICP on a patch of a long bone has local optima exactly there (the
    patch rolls around the shaft or slides along it, measured: from 10 mm / 10 deg away
    about half of the single starts end 4-8 mm off with a 1.6 mm residual); a grid of
    starts 10 deg / 8 mm apart covers the 15 mm / 15 deg the initialisation promises.
    """
    c, axes, _ = _principal_axes(src)
    ct = transform_points(m0, c[None])[0]
    a = m0[:3, :3] @ axes[0]
    out = []
    for roll in (0.0, *params.start_rolls_deg, *(-r for r in params.start_rolls_deg)):
        for shift in (0.0, *params.start_shifts_mm, *(-x for x in params.start_shifts_mm)):
            if roll == 0.0 and shift == 0.0:
                continue
            r = _rotation(a * np.radians(roll))
            m = np.eye(4)
            m[:3, :3] = r
            m[:3, 3] = ct - r @ ct + a * shift
            out.append(m @ m0)
    return out


def _score(src: _Cloud, model: BoneModel, m: np.ndarray, params: RegistrationParams) -> float:
    """Mean truncated squared point-to-plane residual (mm^2): unmatched points count as
    the truncation, so a pose that leaves part of the source off the model pays for it."""
    tau = params.min_distance_mm
    _, ok, r, _ = _match(model, m, src, tau, params)
    e = np.full(len(src.points), tau**2)
    e[ok] = np.minimum(r**2, tau**2)
    return float(e.mean())


def _best_of(
    src: _Cloud,
    model: BoneModel,
    starts: list[tuple[np.ndarray, bool]],
    params: RegistrationParams,
) -> tuple[_IcpState, bool, tuple[float, float, float] | None]:
    """ICP from the best of ``starts``, and a distinct alternative fitting about as well.

    Each start (a matrix, and whether the source's normals are flipped: a patch normal
    has no known side) runs a short ICP on a subset of ``coarse_points``, ranked by
    :func:`_score`; the best is refined on ``src``. The best-ranked start that ended
    more than ``max_sliding_mm`` away runs on (on the subset): if it stays that far
    with a residual within a factor 2 of the best's (floored at the noise), the surface
    matches in two places and the answer is ambiguous. Returns ``(state, flipped,
    None)`` or ``(state, flipped, (distance mm, alternative RMS, best RMS))``.
    """
    sides = {False: src.subset(params.coarse_points)}
    sides[True] = sides[False].flipped()
    pts = sides[False].points
    ranked = []
    for m, flip in starts:
        # Ranking needs the basin, not the last micron: a looser tolerance.
        c = sides[flip]
        stc = _icp(c, model, m, params, max_iterations=params.coarse_iterations, tolerance_mm=0.01)
        ranked.append((_score(c, model, stc.matrix, params), stc.matrix, flip))
    ranked.sort(key=lambda t: t[0])
    b_flip = ranked[0][2]
    best = _icp(src.flipped() if b_flip else src, model, ranked[0][1], params)
    b_score = _score(sides[b_flip], model, best.matrix, params)
    floor = params.noise_floor_mm**2

    def apart(m: np.ndarray) -> float:
        d = transform_points(m, pts) - transform_points(best.matrix, pts)
        return float(np.median(np.linalg.norm(d, axis=1)))

    for sc, m, flip in ranked[1:]:
        if sc > 2.0 * max(b_score, floor) + floor:
            break
        if apart(m) <= params.max_sliding_mm:
            continue
        other = _icp(sides[flip], model, m, params, max_iterations=2 * params.coarse_iterations)
        a_score = _score(sides[flip], model, other.matrix, params)
        dist = apart(other.matrix)
        if dist > params.max_sliding_mm and a_score <= 2.0 * max(b_score, floor):
            if a_score < b_score:  # the alternative is the better one: refine it instead
                best = _icp(src.flipped() if flip else src, model, other.matrix, params)
                a_score, b_score, b_flip = b_score, a_score, flip
            return best, b_flip, (dist, float(np.sqrt(a_score)), float(np.sqrt(b_score)))
        break
    return best, b_flip, None


def register(
    source: np.ndarray,
    model: BoneModel,
    params: RegistrationParams = RegistrationParams(),
    *,
    source_normals: np.ndarray | None = None,
    init: np.ndarray | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    source_path: str | os.PathLike[str] | None = None,
    model_path: str | os.PathLike[str] | None = None,
) -> Registration:
    """Rigidly register ``source`` points to a bone ``model``.

    Parameters
    ----------
    source : ndarray (K, 3)
        The reconstructed surface's vertices or the segmented points (mm, SOURCE frame).
    model : BoneModel
        From :func:`bone_model` / :func:`model_from_polydata` (mm, TARGET frame).
    params : RegistrationParams
    source_normals : ndarray (K, 3), optional
        Outward normals of the source (a reconstructed surface has them, pointing to
        the probe). Without them they are estimated from the points' neighbours
        the source is taken as a patch seen from one side: its :func:`patch_normal`
        stands for every point's (within ``patch_normal_angle_deg``), both sides tried.
    init : ndarray (4, 4), optional
        Initial SOURCE -> TARGET matrix for ``init="identity"`` (default the identity).
    landmarks : (ndarray (K, 3), ndarray (K, 3)), optional
        Paired source and target landmarks; required by ``init="landmarks"`` (and
        then used instead of ``init``).
    source_path, model_path : path-like, optional
        Named in errors.

    Returns
    -------
    Registration

    Raises
    ------
    BoneUSReconError
        Too few or non-finite source points, a unit mismatch (:func:`check_units`),
        bad landmarks, or inputs that do not overlap (fewer than ``min_overlap`` of
        the source points near the model at the start or fitting it at the end: a
        clear failure instead of a silent wrong transform).
    """
    t0 = time.perf_counter()
    src = np.asarray(source, float).reshape(-1, 3)
    if src.shape[0] < 6:
        raise BoneUSReconError(f"need at least 6 source points, got {src.shape[0]}", source_path)
    if not np.isfinite(src).all():
        raise BoneUSReconError("source points contain NaN or infinity", source_path)
    check_units(src, model, source_path, model_path)
    oriented = source_normals is not None
    if oriented:
        nrm = np.asarray(source_normals, float).reshape(-1, 3)
        if nrm.shape != src.shape:
            raise BoneUSReconError(f"{len(nrm)} source normals for {len(src)} points", source_path)
        length = np.linalg.norm(nrm, axis=1)
        good = np.isfinite(length) & (length > 0)
        nrm = np.where(good[:, None], nrm / np.where(good, length, 1.0)[:, None], 0.0)
    else:
        nrm = np.broadcast_to(patch_normal(src), src.shape)
    angle = params.max_normal_angle_deg if oriented else params.patch_normal_angle_deg
    cloud = _Cloud(src, np.ascontiguousarray(nrm), angle)
    sub = cloud.subset(params.max_source_points)
    lm_rms = None
    method = "landmarks" if landmarks is not None else params.init
    if method == "landmarks":
        if landmarks is None:
            raise BoneUSReconError("init='landmarks' needs paired source and target landmarks")
        m0, lm_rms = landmark_transform(*landmarks)
    elif method == "search":
        m0 = np.eye(4)
    else:
        m0 = np.eye(4) if init is None else np.asarray(init, float)
        if m0.shape != (4, 4) or not np.isfinite(m0).all():
            raise BoneUSReconError(
                f"the initial transform must be a finite 4x4 matrix, got shape {m0.shape}"
            )
        if (
            not np.allclose(m0[:3, :3] @ m0[:3, :3].T, np.eye(3), atol=1e-4)
            or np.linalg.det(m0[:3, :3]) < 0
        ):
            raise BoneUSReconError(
                "the initial transform is not rigid (a rotation and a translation)"
            )
    if method == "search":
        mats = _search_inits(sub.points, model, params)
    else:
        # Overlap at the start: a start far from the model is refused, not "registered".
        d0, _ = model.tree.query(
            transform_points(m0, sub.points), distance_upper_bound=params.max_distance_mm
        )
        near0 = float(np.isfinite(d0).mean())
        if near0 < params.min_overlap:
            raise BoneUSReconError(
                f"the source and the model do not overlap: only {100 * near0:.0f}% of the source points lie "
                f"within {params.max_distance_mm:g} mm of the model at the initial alignment (give paired "
                "landmarks or an initial matrix, or use the global search)",
                source_path,
            )
        mats = [m0, *_local_starts(sub.points, m0, params)]
    # A patch normal has no known side: every start is tried with both.
    starts = [(m, flip) for m in mats for flip in ((False,) if oriented else (False, True))]
    st, flipped, alt = _best_of(sub, model, starts, params)
    q = _quality(cloud.flipped() if flipped else cloud, model, st, params)
    if q["inlier_share"] < params.min_overlap:
        raise BoneUSReconError(
            f"registration failed: only {100 * q['inlier_share']:.0f}% of the source points fit the model "
            f"at the end (at least {100 * params.min_overlap:.0f}% needed); the inputs do not overlap or "
            "the initial alignment is too far off",
            source_path,
        )
    reasons = _reasons(q, st, params)
    if alt is not None:
        reasons.append(
            f"another alignment {alt[0]:.1f} mm away (median over the source points) fits about as well "
            f"(residual {alt[1]:.2f} against {alt[2]:.2f} mm): the imaged surface matches the model in two places"
        )
    return Registration(
        matrix=st.matrix,
        initial=m0,
        rms_mm=q["rms_mm"],
        median_mm=q["median_mm"],
        p95_mm=q["p95_mm"],
        inlier_share=q["inlier_share"],
        n_source=int(src.shape[0]),
        n_inliers=q["n_inliers"],
        iterations=st.iterations,
        converged=st.converged,
        eigenvalues=q["eigenvalues"],
        condition=q["condition"],
        sliding_mm=q["sliding_mm"],
        directions=q["directions"],
        reliable=not reasons,
        reasons=tuple(reasons),
        landmark_rms_mm=lm_rms,
        long_axis=q["long_axis"],
        seconds=time.perf_counter() - t0,
    )


def register_polydata(
    source: Any,
    target: Any,
    params: RegistrationParams = RegistrationParams(),
    *,
    init: np.ndarray | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    source_path: str | os.PathLike[str] | None = None,
    target_path: str | os.PathLike[str] | None = None,
) -> Registration:
    """:func:`register` on ``vtkPolyData``: the source's points (a surface or a point
    cloud; its point ``Normals`` used when present) to the target's triangles. See
    :func:`register` for the arguments."""
    from vtkmodules.util import numpy_support

    from BoneUSRecon.Logic.vtkio import polydata_points

    model = model_from_polydata(target, target_path)
    pts = polydata_points(source)
    if pts.shape[0] == 0:
        raise BoneUSReconError("the source has no points", source_path)
    arr = source.GetPointData().GetNormals()
    normals = numpy_support.vtk_to_numpy(arr).astype(float) if arr is not None else None
    return register(
        pts,
        model,
        params,
        source_normals=normals,
        init=init,
        landmarks=landmarks,
        source_path=source_path,
        model_path=target_path,
    )

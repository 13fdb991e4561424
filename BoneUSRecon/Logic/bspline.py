"""Least-squares tensor-product B-spline surface (paper section II.D), robustly weighted.

Surface ``S(u, v) = sum_a sum_c N_a,p(u) M_c,q(v) C_ac`` with ``e x f`` control points
``C`` (15 x 6 by default) and degrees ``p, q`` (2, 2: the paper's quadratic splines),
fitted to the resampled grid ``P_ij`` (rows i = slices, columns j = rays).

Parameterisation
    ``u_i``: the grid's natural one, the arc length of the slice centres along the bone
    axis (:attr:`ResampledGrid.axis_position`), scaled to [0, 1]; without it, the
    chord length averaged over the columns (Piegl & Tiller, *The NURBS Book*, 9.2.2).
    ``v_j``: the ray angle scaled to [0, 1] (uniform rays give uniform v); without it,
    averaged chord length over the rows.

Knots
    Clamped (``p + 1`` end knots at 0 and 1), interior knots by de Boor's averaging
    for approximation (Piegl & Tiller eq. 9.68-9.69): each interior knot is an average
    of data parameters, so that every knot span holds data (Schoenberg-Whitney).

Solvers (``FitParams.method``)
    ``"separable"``: de Boor's two stages as in the paper: one weighted least-squares
    curve fit down each column (u direction, ``n`` systems, batched), giving ``e x n``
    intermediate points; then one fit across each of the ``e`` rows of intermediate
    points (v direction). This is exactly the tensor-product least-squares solution
    when the weights factor as ``w_ij = a_i b_j`` (complete grid, per-frame times
    per-ray weights): the normal matrix is then a Kronecker product. With missing
    entries or per-point weights it is *not* exact: column ``j`` is fitted with its own
    weights ``w_ij`` (with the same small smoothing penalty as below, so a column with
    gaps is still solvable; without it such a column is dropped) and the row stage
    weighs intermediate point ``(k, j)`` by the share of basis function ``k``'s mass in
    column ``j`` that carried data (an intermediate point over a gap was only
    extrapolated; weighing whole columns instead gave 1.0 mm mean gold distance on a
    simulated clavicle, this 0.18 mm, direct 0.176 mm).
    ``"direct"`` (default): the exact weighted tensor-product least squares,
    ``min sum_ij w_ij |S(u_i, v_j) - P_ij|^2``, by its ``ef x ef`` normal equations
    built with Kronecker structure (``B_u^T W B_u`` per column, then contracted with
    ``B_v``), which honours any per-point weight and missing entries (weight 0, never
    filled in). It costs about the same (``ef = 75`` unknowns).

Robust reweighting (beyond the paper)
    Iteratively reweighted least squares on the point-to-surface residuals: Huber
    weights for the first iterations (a safe start), then Tukey's biweight, which gives
    exactly zero weight to gross outliers. Weights are per point *and* per frame (a
    frame's weight from its median residual), so a whole false contour that slipped
    through segmentation is rejected even when its points agree among themselves.
    Scales are 1.4826 x the median residual, floored at ``min_scale_mm``.
    A frame's residual is the median offset of its grid points from their fitted
    points *along the surface normal* there, not of the full distances
    ``|S(u_i, v_j) - P_ij|``: a grid point's parameters are only nominal (the slice's
    axis position, the ray's angle), so where slices are sparse or tilted the spline
    meets a correct contour a little along the surface from ``(u_i, v_j)``, an offset
    within the surface that says nothing about whether the contour is on the bone.
    Judged by the full distance, two correct frames of a simulated clavicle where the
    probe sped up (5 mm between slices) had median residuals of 0.7 mm (0.03 mm from
    the true bone) and were rejected with the one false contour, which opened a hole
    there (gold mean 0.38 mm, 92 % within 1 mm); judged along the normal only the false
    contour (1.4 mm off) goes (0.20 mm, 98 %). A single point is judged by its normal
    offset together with how far its offset within the surface differs from its
    frame's median one: a correct slice met off its nominal parameters slides as a
    whole, which is no evidence against a point (judged by full distances, all points
    of three correct frames of a simulated 60-frame clavicle were dropped: 0.31 mm
    gold mean, now 0.22 mm), while an odd point at a contour's end that bends the
    thinly held edge of the surface toward itself slides unlike its frame (judged by
    the normal offset alone, a simulated ulna's edge flapped 0.6 mm off the bone:
    0.25 mm gold mean against 0.20 mm).
    :attr:`FitResult.residuals` are the full distances.

A small second-difference penalty (``smoothing``, relative to the normal matrix's
mean diagonal; 0 disables it) keeps control points with no data under them (gaps,
ends) determined; on supported areas its effect is ~1e-7 mm.

Thin data (beyond the paper; ``direct`` method)
    A control point whose basis function covers only the tail of the data (a flank
    where the contours stop, the ends of a long sweep with most of the grid empty) is
    fitted to a handful of points weighted by a tiny basis value: nearly singular, it
    swings far off the bone (metres of curve on a real 300 mm sweep). The directions of
    the control net that the data determine poorly (generalised eigenvectors of the
    normal matrix against a complete grid's, eigenvalue below ``thin_share``) are
    given a smoothness penalty of weight ``thin_weight``: second differences along the
    bone (the net continues straight on), third differences around it (the section
    continues with its curvature: a second difference around would flatten a round
    section wherever a direction of a few points is taken whole); the others keep the
    plain least-squares solution, so the covered surface is not biased.
    ``thin_weight=0`` with ``robust="none"`` is the paper's plain least squares.
"""

from __future__ import annotations

import functools
import warnings
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np
from scipy.interpolate import BSpline
from scipy.linalg import LinAlgError, cho_factor, cho_solve, eigh, solve_triangular
from threadpoolctl import ThreadpoolController

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.params_check import check_fields
from BoneUSRecon.Logic.robust import mad_scale, robust_weights, row_medians

__all__ = [
    "FitParams",
    "BSplineSurface",
    "FitResult",
    "fit_surface",
    "fewer_control_points",
    "averaging_knots",
    "distinct_params",
    "basis_matrix",
    "fit_curve",
    "thin_basis",
    "ThinBasis",
]


@dataclass(frozen=True)
class FitParams:
    """Parameters of the surface fit.

    Attributes
    ----------
    degree : (int, int)
        Degrees ``(p, q)`` in u (along the bone) and v (around it). Paper II.D: quadratic
        ``(2, 2)``. Order = degree + 1.
    n_control_points : (int, int)
        Numbers ``(e, f)`` of control points in u and v. Paper II.D: 15 x 5 "for
        elongated bones as the ulna and radius", ``e`` and ``f`` "chosen depending on
        the form of the bones". Default 15 x 6 (ours): our rays span the whole arc the
        segmentation saw, its flanks followed down to 70 degrees and more (ray spans of
        100-230 degrees, against 3 quadratic spans across at ``f = 5``), and a
        crest-shaped section (tibia) bends faster than 3 spans follow. Measured with
        ``f`` = 5 / 6 / 7 / 9 (gold mean, each sweep's own segmentation; session 30 in
        ``Testing/benchmarks/README.md``): hard simulated sweeps whose rays span over
        180 degrees 0.309 / 0.278 / 0.288 / 0.286 mm (20 sweeps, seeds 109, 113) and
        0.329 / 0.295 / 0.305 / 0.299 mm (seeds 53, 59); narrower spans (standard,
        grey) 0.184 / 0.183 / 0.183 / 0.184 mm; the L14 recording 0.337 -> 0.313 mm
        at 6, its cadaver-level copy 1.63 -> 1.42 mm. The cost: on clean standard
        sweeps the sixth control point follows a flank's sparse, noisier contour ends
        more closely (area within 0.35 mm of the bone 0.993 -> 0.990 over 28 sweeps;
        the test clavicle's 99th percentile 0.39 -> 0.80 mm). The keyword
        ``control_points`` (its former name) is still accepted, with a
        ``DeprecationWarning``.
    method : str
        ``"direct"`` (exact weighted tensor-product least squares, default) or
        ``"separable"`` (the paper's de Boor two-stage scheme); see module docstring.
    robust : str
        ``"tukey"`` (Huber start then Tukey, default), ``"huber"`` or ``"none"`` (the
        paper's plain least squares). Ours.
    robust_iterations : int
        Maximum reweighting iterations (count); stops earlier when weights settle.
    per_frame : bool
        Also weight each frame by its median offset along the surface normal (rejects
        whole false contours; see the module docstring).
    min_scale_mm : float
        Floor of the robust residual scale (mm): about the segmentation noise, so clean
        data are not trimmed. Ours (0.15 mm, ~1 pixel).
    smoothing : float
        Relative weight of the second-difference penalty on control points (unitless,
        relative to the mean diagonal of the normal matrix). 1e-8: bias ~1e-7 mm.
    thin_weight : float
        Weight of the smoothness penalty on the directions of the control net that the
        data leave undetermined (unitless, relative to the mean diagonal of a complete
        grid's normal matrix; ``direct`` method only; see the module docstring). 1:
        bending such a direction costs as much as one fully covered control point's
        data, so the net continues past the data straight on along the bone and with
        its curvature around it (the spline stays near
        the bone instead of swinging: curve lengths of 1.8 m were seen on a real 300 mm
        sweep with 62 % of the grid empty, and a flap under a flank of the real L14
        recording), while the determined directions stay plain least squares, with no
        bias. 0: the paper's plain least squares (with only ``smoothing``). Ours.
    thin_share : float
        A direction of the control net is thin when the data say less than this share
        of what a complete grid would (generalised eigenvalue of the normal matrix
        against the complete grid's, 0..1]. 0.001: removes the flap of the real L14
        recording (as 0.002-0.02 do) while a 300 mm tube with 30 % of its grid covered
        keeps its accuracy (0.056 mm worst against 0.057 mm without the penalty; 0.13
        and 0.2 mm at 0.002 and 0.005: directions that still hold data get bent). Ours.
    fewer_if_short : bool
        When the grid holds fewer slices (rays) with data than ``n_control_points``
        asks along (around) the bone, fit fewer: along, half the slices (at least
        ``degree + 1``); around, as many as the rays; then fewer along while the grid's
        points are fewer than the control points. Never below ``degree + 1`` (such a
        grid is refused as before). :attr:`FitResult.n_control_points` says what was
        fitted. Why half: a short sweep (the spine phantom's 11 slices, a short
        recording with some frames rejected) otherwise gets no surface at all, and as
        many control points as slices interpolates each slice's noise. Measured on 12
        frames kept out of each of 44 simulated sweeps (seed 241; session 43 in
        ``Testing/benchmarks/README.md``), gold mean with 3 / 5 / 6 / 8 / 10 / 12
        control points along: 0.231 / 0.238 / **0.229** / 0.255 / 0.292 / 0.535 mm (3
        fits of 44 failed at 12). True (ours); False refuses a grid too short for what
        was asked, as :func:`.pipeline.params_with` does for control points a user
        gives.
    """

    degree: tuple[int, int] = (2, 2)
    n_control_points: tuple[int, int] = (15, 6)
    method: str = "direct"
    robust: str = "tukey"
    robust_iterations: int = 6
    per_frame: bool = True
    min_scale_mm: float = 0.15
    smoothing: float = 1e-8
    thin_weight: float = 1.0
    thin_share: float = 0.001
    fewer_if_short: bool = True

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=("min_scale_mm",),
            non_negative=("robust_iterations", "smoothing", "thin_weight"),
            within={"thin_share": "(0, 1]"},
            choices={"method": ("direct", "separable"), "robust": ("tukey", "huber", "none")},
        )
        (p, q), (e, f) = self.degree, self.n_control_points
        if p < 1 or q < 1:
            raise BoneUSReconError(f"FitParams.degree must be at least 1, got {self.degree}")
        if e < p + 1 or f < q + 1:
            raise BoneUSReconError(
                f"{e} x {f} control points are too few for degree {p} {q}: need at "
                f"least degree + 1 in each direction"
            )

    @property
    def control_points(self) -> tuple[int, int]:
        """Deprecated name of :attr:`n_control_points`."""
        warnings.warn(
            "FitParams.control_points is now n_control_points", DeprecationWarning, stacklevel=2
        )
        return self.n_control_points


def _accept_old_control_points(init: Callable[..., None]) -> Callable[..., None]:
    """``FitParams(control_points=...)``, the former keyword, still works (with a warning)."""

    @functools.wraps(init)
    def __init__(self: FitParams, *args: Any, control_points: Any = None, **kwargs: Any) -> None:
        if control_points is not None:
            warnings.warn(
                "FitParams(control_points=...) is now n_control_points=...",
                DeprecationWarning,
                stacklevel=2,
            )
            kwargs["n_control_points"] = control_points
        init(self, *args, **kwargs)

    return __init__


FitParams.__init__ = _accept_old_control_points(FitParams.__init__)  # type: ignore[method-assign]


#: Data parameters closer than this share of a mean knot span are one position when
#: knots are placed and slices counted (:func:`distinct_params`).
SAME_POSITION = 0.01


def distinct_params(params: np.ndarray, tol: float) -> np.ndarray:
    """Sorted parameters with each run of neighbours closer than ``tol`` made one (its mean).

    De Boor's averaging assumes distinct data parameters. A probe held still records
    frames at one pose (a pause at the start of a PLUS recording, where the operator
    starts recording and then moves; a sweep there and back crosses its own slices):
    ten frames at one pose put two interior knots on the clamped end knot, a basis
    function vanished, and the fit's system was singular (an internal error). Frames
    that close add data, not positions: the knots are placed over the positions, and
    the count of slices a fit needs is a count of positions. ``tol`` is
    :data:`SAME_POSITION` of a mean knot span (0.1 mm on a 130 mm sweep fitted with 15
    control points), far under any knot span, so a sweep moving at any speed keeps
    its positions; a pause with the tracker's jitter (~0.05-0.2 mm) mostly merges.

    Parameters
    ----------
    params : ndarray, shape (r,)
        Sorted parameters.
    tol : float
        Largest gap between neighbours still taken as one position.

    Returns
    -------
    ndarray, shape (r',)
    """
    ub = np.asarray(params, float)
    if ub.size < 2:
        return ub
    run = np.cumsum(np.r_[True, np.diff(ub) > tol]) - 1
    return np.bincount(run, ub) / np.bincount(run)


def averaging_knots(params: np.ndarray, n_ctrl: int, degree: int) -> np.ndarray:
    """Clamped knot vector by de Boor's averaging for approximation (NURBS Book 9.69).

    Over the distinct positions of ``params`` (:func:`distinct_params`).

    Parameters
    ----------
    params : ndarray, shape (r,)
        Sorted data parameters in [0, 1].
    n_ctrl : int
        Number of control points.
    degree : int

    Returns
    -------
    ndarray, shape (n_ctrl + degree + 1,)
    """
    ub = distinct_params(params, SAME_POSITION / max(n_ctrl - degree, 1))
    if ub.size < n_ctrl:  # too few positions for these knots: the fit refuses the count
        ub = np.asarray(params, float)
    r = ub.size
    n_int = n_ctrl - degree - 1
    d = r / (n_ctrl - degree)
    j = np.arange(1, n_int + 1)
    i = np.floor(j * d).astype(int)
    alpha = j * d - i
    interior = (1 - alpha) * ub[np.clip(i - 1, 0, r - 1)] + alpha * ub[np.clip(i, 0, r - 1)]
    return np.r_[np.zeros(degree + 1), interior, np.ones(degree + 1)]


def _tensor_eval(bu: np.ndarray, ctrl: np.ndarray, bv: np.ndarray) -> np.ndarray:
    """``S[i, j] = sum_ab Bu[i, a] C[a, b] Bv[j, b]`` by two matrix products."""
    e, f, d = ctrl.shape
    x = (bu @ ctrl.reshape(e, f * d)).reshape(-1, f, d)  # (m, f, 3)
    return np.matmul(np.swapaxes(x, 1, 2), bv.T).transpose(0, 2, 1)  # (m, n, 3)


def basis_matrix(x: np.ndarray, knots: np.ndarray, degree: int) -> np.ndarray:
    """Dense B-spline collocation matrix ``B[i, a] = N_a,p(x_i)`` (x clipped to [0, 1]).

    Parameters
    ----------
    x : ndarray, shape (n,)
        Parameter values in [0, 1].
    knots : ndarray
        Clamped knot vector (length ``number of basis functions + degree + 1``).
    degree : int
        Spline degree ``p``.

    Returns
    -------
    ndarray, shape (n, len(knots) - degree - 1)
    """
    x = np.clip(np.asarray(x, float), knots[degree], knots[-degree - 1])
    return BSpline.design_matrix(x, knots, degree).toarray()


@dataclass(frozen=True, eq=False)
class BSplineSurface:
    """A clamped tensor-product B-spline surface on [0, 1] x [0, 1].

    Attributes
    ----------
    control_points : ndarray, shape (e, f, 3)
        mm.
    knots_u, knots_v : ndarray
        Clamped knot vectors, lengths ``e + p + 1`` and ``f + q + 1``.
    degrees : (int, int)
        ``(p, q)``.
    """

    control_points: np.ndarray
    knots_u: np.ndarray
    knots_v: np.ndarray
    degrees: tuple[int, int]

    def evaluate(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Points on the grid ``u x v``: shape ``(len(u), len(v), 3)`` in mm."""
        bu = basis_matrix(np.atleast_1d(u), self.knots_u, self.degrees[0])
        bv = basis_matrix(np.atleast_1d(v), self.knots_v, self.degrees[1])
        return _tensor_eval(bu, self.control_points, bv)

    def evaluate_points(self, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        """Points at paired parameters ``(u[k], v[k])``: shape ``(K, 3)``."""
        bu = basis_matrix(np.atleast_1d(u), self.knots_u, self.degrees[0])
        bv = basis_matrix(np.atleast_1d(v), self.knots_v, self.degrees[1])
        return np.einsum("ka,abd,kb->kd", bu, self.control_points, bv, optimize=True)

    def to_scipy(self) -> list[object]:
        """The three coordinate surfaces as ``scipy.interpolate.NdBSpline`` (for checks)."""
        from scipy.interpolate import NdBSpline

        return [
            NdBSpline((self.knots_u, self.knots_v), self.control_points[..., k], self.degrees)
            for k in range(3)
        ]


@dataclass(frozen=True, eq=False)
class FitResult:
    """Outcome of :func:`fit_surface`.

    Attributes
    ----------
    surface : BSplineSurface
    u, v : ndarray, shapes (m,), (n,)
        Parameters of the grid rows and columns.
    residuals : ndarray, shape (m, n)
        Distance (mm) from each grid point to its fitted point ``S(u_i, v_j)``; NaN where
        the grid had no point.
    weights : ndarray, shape (m, n)
        Final weights (0 for missing entries and rejected outliers).
    frame_weights : ndarray, shape (m,)
        Final per-frame weights (ones unless ``per_frame``).
    rms_mm : float
        RMS residual over the points kept (weight > 0), mm.
    rms_all_mm : float
        RMS residual over all grid points, mm.
    iterations : int
        Reweighting iterations done.
    method : str
    """

    surface: BSplineSurface
    u: np.ndarray
    v: np.ndarray
    residuals: np.ndarray
    weights: np.ndarray
    frame_weights: np.ndarray
    rms_mm: float
    rms_all_mm: float
    iterations: int
    method: str

    @property
    def n_points(self) -> int:
        """Grid points present (finite)."""
        return int(np.isfinite(self.residuals).sum())

    @property
    def n_control_points(self) -> tuple[int, int]:
        """The control points fitted, ``(e, f)`` (fewer than asked on a short grid:
        :attr:`FitParams.fewer_if_short`)."""
        e, f = self.surface.control_points.shape[:2]
        return int(e), int(f)

    @property
    def n_outliers(self) -> int:
        """Grid points present but given zero weight."""
        return int((np.isfinite(self.residuals) & (self.weights <= 0)).sum())


def _chord_params(points: np.ndarray, axis: int) -> np.ndarray:
    """Chord-length parameters along ``axis`` averaged over the other axis (NaN-aware)."""
    p = np.moveaxis(points, axis, 0)  # (r, s, 3)
    step = np.linalg.norm(np.diff(p, axis=0), axis=-1)  # NaN where either end missing
    with np.errstate(invalid="ignore"):
        cnt = np.isfinite(step).sum(axis=1)
        mean = np.where(cnt > 0, np.nansum(step, axis=1) / np.maximum(cnt, 1), np.nan)
    fill = np.nanmean(mean) if np.isfinite(mean).any() else 1.0
    mean = np.where(np.isfinite(mean) & (mean > 0), mean, fill)
    s = np.r_[0.0, np.cumsum(mean)]
    return s / s[-1] if s[-1] > 0 else np.linspace(0, 1, s.size)


def _normalise(x: np.ndarray) -> np.ndarray:
    x = np.asarray(x, float)
    span = x[-1] - x[0]
    if not np.all(np.diff(x) >= 0) or span <= 0:
        raise BoneUSReconError("surface parameters must be increasing")
    return (x - x[0]) / span


def _basis_derivative_matrix(x: np.ndarray, knots: np.ndarray, degree: int) -> np.ndarray:
    """First derivatives ``N'_a,p(x_i)`` of the basis functions (x clipped to [0, 1]).

    Same shape and conventions as :func:`basis_matrix`: ``B' @ C`` is the curve's
    derivative at ``x`` for control points ``C``.
    """
    x = np.clip(np.asarray(x, float), knots[degree], knots[-degree - 1])
    n_basis = len(knots) - degree - 1
    return BSpline(knots, np.eye(n_basis), degree)(x, nu=1)


def _cross3(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``np.cross(a, b)`` over a last axis of length 3, by components."""
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return np.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def _norm3(a: np.ndarray) -> np.ndarray:
    """Euclidean norm over the last axis (NaN where any component is NaN)."""
    return np.sqrt(np.einsum("...d,...d->...", a, a))


def _offsets(diff: np.ndarray, su: np.ndarray, sv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Split grid-point offsets into the part along the normal and an odd tangential part.

    Parameters
    ----------
    diff : ndarray, shape (m, n, 3)
        Grid point minus fitted point (NaN where missing).
    su, sv : ndarray, shape (m, n, 3)
        The surface's partial derivatives there (normal ``su x sv``).

    Returns
    -------
    normal : ndarray, shape (m, n)
        ``|diff . n|`` (the whole ``|diff|`` where the surface is degenerate).
    point : ndarray, shape (m, n)
        ``sqrt(normal^2 + |t - median_row(t)|^2)``, ``t`` the tangential part of
        ``diff`` in the surface's frame (along ``su``, and ``n x su``): what a single
        point is judged by (module docstring).
    """
    # Cross products and norms written out per component: np.cross and np.linalg.norm
    # over a last axis of 3 cost several times more on grids of thousands of points,
    # and this runs once per robust iteration.
    nrm = _cross3(su, sv)
    length = _norm3(nrm)[..., None]
    ok = length > 1e-12 * max(float(np.nanmax(length, initial=0.0)), 1e-300)
    regular = bool(ok.all())  # the usual case: no degenerate point, no masking needed
    unit = nrm / length if regular else np.where(ok, nrm / np.where(ok, length, 1.0), 0.0)
    along = np.einsum("mnd,mnd->mn", diff, unit)
    normal = np.abs(along) if regular else np.where(ok[..., 0], np.abs(along), _norm3(diff))
    # Tangential offset in the surface's own frame (along u, and normal x that), so the
    # row medians are those of intrinsic coordinates: unchanged by a rigid motion.
    eu = su / np.maximum(_norm3(su), 1e-300)[..., None]
    ev = _cross3(unit, eu)
    tang = np.stack(
        [np.einsum("mnd,mnd->mn", diff, eu), np.einsum("mnd,mnd->mn", diff, ev)], axis=-1
    )
    if not regular:
        tang = np.where(ok, tang, 0.0)
    med = np.stack([row_medians(tang[..., k]) for k in range(2)], axis=-1)
    point = np.sqrt(normal**2 + np.sum((tang - med[:, None]) ** 2, axis=-1))
    return normal, point


def _second_diff(n: int) -> np.ndarray:
    return np.diff(np.eye(n), 2, axis=0) if n > 2 else np.zeros((0, n))


def fit_curve(
    x: np.ndarray,
    points: np.ndarray,
    weights: np.ndarray,
    knots: np.ndarray,
    degree: int,
    smoothing: float = 0.0,
) -> np.ndarray:
    """Weighted least-squares B-spline curves, batched (the separable scheme's stage).

    Parameters
    ----------
    x : ndarray, shape (r,)
        Parameters.
    points : ndarray, shape (r, b, d)
        ``b`` curves of ``r`` points each (NaN ignored).
    weights : ndarray, shape (r, b)
    knots : ndarray
    degree : int
    smoothing : float
        Relative second-difference penalty (as in :class:`FitParams`); 0 = plain LSQ.

    Returns
    -------
    ctrl : ndarray, shape (n_ctrl, b, d)
        NaN for curves whose system is singular (too few weighted points).
    """
    bmat = basis_matrix(x, knots, degree)  # (r, a)
    w = np.where(np.isfinite(points).all(-1), weights, 0.0)
    p = np.nan_to_num(points)
    nmat = np.einsum("rb,ra,rc->bac", w, bmat, bmat)  # (b, a, a)
    rhs = np.einsum("rb,ra,rbd->bad", w, bmat, p)
    if smoothing > 0:
        d2 = _second_diff(bmat.shape[1])
        scale = np.einsum("baa->b", nmat)[:, None, None] / bmat.shape[1]
        nmat = nmat + smoothing * scale * (d2.T @ d2)[None]
    ctrl = np.full((bmat.shape[1], points.shape[1], points.shape[2]), np.nan)
    eig_min = np.linalg.eigvalsh(nmat)[:, 0]
    ok = eig_min > 1e-10 * np.maximum(np.einsum("baa->b", nmat), 1e-300)
    if ok.any():
        ctrl[:, ok] = np.moveaxis(np.linalg.solve(nmat[ok], rhs[ok]), 0, 1)
    return ctrl


def _penalty(e: int, f: int, around: int = 2) -> np.ndarray:
    """Second differences of the control net along u, ``around``-th along v (ef x ef)."""
    du = _second_diff(e)
    dv = np.diff(np.eye(f), around, axis=0) if f > around else np.zeros((0, f))
    return np.kron(du.T @ du, np.eye(f)) + np.kron(np.eye(e), dv.T @ dv)


def _normal_equations(
    bu: np.ndarray, bv: np.ndarray, w: np.ndarray, p: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """Normal matrix ``(ef, ef)`` and right-hand side ``(ef, 3)`` of the weighted fit."""
    e, f = bu.shape[1], bv.shape[1]
    m, n = w.shape
    # Normal matrix sum_ij w_ij (Bu_i (x) Bv_j)(Bu_i (x) Bv_j)^T with Kronecker structure,
    # as matrix products (BLAS) rather than one big einsum:
    # T_j = Bu^T diag(w_:j) Bu, then N[(a,c),(b,d)] = sum_j T_j[a,b] Bv_jc Bv_jd.
    wb = w.T[:, :, None] * bu[None]  # (n, m, e)
    t = np.matmul(np.swapaxes(wb, 1, 2), bu)  # (n, e, e)
    vv = (bv[:, :, None] * bv[:, None, :]).reshape(n, f * f)
    nmat = (t.reshape(n, e * e).T @ vv).reshape(e, e, f, f)
    nmat = nmat.transpose(0, 2, 1, 3).reshape(e * f, e * f)
    rhs = bu.T @ (w[..., None] * p).reshape(m, n * 3)  # (e, n*3)
    rhs = np.matmul(rhs.reshape(e, n, 3).transpose(0, 2, 1), bv)  # (e, 3, f)
    return nmat, rhs.transpose(0, 2, 1).reshape(e * f, 3)


def _solve_direct(
    bu: np.ndarray,
    bv: np.ndarray,
    w: np.ndarray,
    p: np.ndarray,
    smoothing: float,
    pen: np.ndarray | None = None,
    thin: _ThinSetup | None = None,
) -> np.ndarray:
    """Weighted tensor-product least squares by the normal equations.

    ``thin``: the thin-data penalty's fixed parts (see :func:`thin_basis`), split
    afresh for these weights (a frame the robust weights drop leaves its directions
    thin). ``pen`` is the ``smoothing`` penalty (second differences both ways).
    """
    e, f = bu.shape[1], bv.shape[1]
    nmat, rhs = _normal_equations(bu, bv, w, p)
    pen = _penalty(e, f) if pen is None else pen
    try:
        if thin is not None:
            basis = thin_basis(
                nmat, thin.nfull, thin.penalty, thin.weight, thin.share, whitening=thin.whitening
            )
            if basis is not None:
                return basis.solve(nmat, rhs).reshape(e, f, 3)
        if smoothing > 0:
            nmat = nmat + smoothing * np.trace(nmat) / (e * f) * pen
        cf = cho_factor(nmat)
        diag = np.abs(np.diag(cf[0]))
        if diag.min() <= 1e-7 * diag.max():
            raise LinAlgError("ill-conditioned")
        return cho_solve(cf, rhs).reshape(e, f, 3)
    except LinAlgError:
        raise BoneUSReconError(
            f"the grid points do not determine {e} x {f} control points (too few valid "
            "points under some control points); use fewer control points"
        ) from None


@dataclass(frozen=True, eq=False)
class _ThinSetup:
    """What the thin-data split holds fixed over a fit's robust iterations."""

    nfull: np.ndarray  # normal matrix of a complete grid at weight 1
    weight: float  # FitParams.thin_weight
    share: float  # FitParams.thin_share
    whitening: np.ndarray  # _whitening(nfull)
    penalty: np.ndarray  # _penalty(e, f, around=3), unweighted


@dataclass(frozen=True, eq=False)
class ThinBasis:
    """The control net's thin directions, and what tells the determined ones apart.

    Attributes
    ----------
    thin : ndarray, shape (ef, t)
        The thin generalised eigenvectors ``Q`` (see :func:`thin_basis`).
    constraint : ndarray, shape (t, ef)
        ``Q^T N_full``: the determined directions ``W`` are the ``N_full``-orthogonal
        complement of ``Q``, i.e. the ``c`` with ``Q^T N_full c = 0``.
    penalty : ndarray, shape (ef, ef)
        The weighted penalty (second differences along the bone, third around it).
    """

    thin: np.ndarray
    constraint: np.ndarray
    penalty: np.ndarray

    def solve(self, nmat: np.ndarray, rhs: np.ndarray) -> np.ndarray:
        """Control points ``(ef, 3)``: least squares on the determined directions, then ``Q``.

        The least squares on ``span(W)`` is solved as one constrained problem (KKT
        system: ``N c + C^T l = rhs``, ``C c = 0``), so the determined eigenvectors
        are never needed: only the few thin ones are computed (a full ``eigh`` took
        a fifth of the fit's time at 24-30 rays). Then ``z`` minimises data + penalty
        over ``Q`` with ``W a`` held.
        """
        q, cons, pw = self.thin, self.constraint, self.penalty
        n, t = nmat.shape[0], q.shape[1]
        kkt = np.zeros((n + t, n + t))
        kkt[:n, :n] = nmat
        kkt[:n, n:] = cons.T
        kkt[n:, :n] = cons
        kkt[:n, :n] += 1e-12 * max(float(np.trace(nmat)) / n, 1e-300) * np.eye(n)
        good = np.linalg.solve(kkt, np.vstack([rhs, np.zeros((t, rhs.shape[1]))]))[:n]
        qp = q.T @ pw
        lhs = q.T @ nmat @ q + qp @ q
        lhs += 1e-10 * max(float(np.trace(lhs)) / lhs.shape[0], 1e-300) * np.eye(lhs.shape[0])
        z = np.linalg.solve(lhs, q.T @ rhs - (q.T @ nmat + qp) @ good)
        return good + q @ z


def thin_basis(
    nmat: np.ndarray,
    nfull: np.ndarray,
    pen: np.ndarray,
    weight: float,
    share: float,
    whitening: np.ndarray | None = None,
) -> ThinBasis | None:
    """Split the control net into what the data determine and what they leave thin.

    The generalised eigenproblem ``N x = mu N_full x`` (``N`` the weighted normal
    matrix, ``N_full`` the one of a complete grid at weight 1; eigenvectors
    ``N_full``-orthonormal) splits the control net's space into directions the data
    determine (``mu >= share``: at least that share of what a complete grid would say)
    and thin ones (``mu < share``: flanks past the last contour ends, gaps, the ends of
    a long sweep). With ``c = W a + Q z`` (``W``, ``Q`` the determined and the thin
    eigenvectors), ``a`` is the least-squares solution on ``W`` alone, unbiased, and
    ``z`` minimises data + ``weight * mean(diag N_full) * |D c|^2`` (``pen``: second
    differences of the whole control net along the bone, third around it; see the
    module docstring). With second differences around, on a tube whose flank is cut in
    its first 10 frames, a direction holding a few points taken whole bent the mesh's
    edge 0.14-0.21 mm off the tube at 12, 14, 19, 24 and 29 rays; third differences
    leave 0.03-0.065 mm, and 88 simulated sweeps' gold mean 0.2284 -> 0.2274 mm
    (session 40). A
    penalty on all of ``c`` instead pulled the covered surface 0.1-0.6 mm off the data
    (tube with a hole, the real L14 recording) at weights that tame the thin parts.

    Parameters
    ----------
    nmat, nfull : ndarray, shape (ef, ef)
    pen : ndarray, shape (ef, ef)
        Smoothness penalty (unweighted; :func:`_penalty` with ``around=3`` in the fit).
    weight, share : float
        ``FitParams.thin_weight`` and ``thin_share``.
    whitening : ndarray, shape (ef, ef), optional
        :func:`_whitening` of ``nfull`` when already computed (it is the same for every
        robust iteration of a fit).

    Returns
    -------
    ThinBasis or None
        ``None`` when no direction is thin (or ``weight`` is 0): plain least squares.
    """
    if not weight > 0:
        return None
    li = _whitening(nfull) if whitening is None else whitening
    if li is None:
        return None
    # Only the eigenpairs under ``share`` (driver "evr", relatively robust
    # representations: the divide-and-conquer default took 0.5 s instead of 1 ms at
    # 75 x 75 with multi-threaded BLAS on a loaded machine).
    mu, u = eigh(li @ nmat @ li.T, driver="evr", subset_by_value=(-np.inf, share))
    if not mu.size:
        return None
    q = li.T @ u
    pw = weight * float(np.mean(np.diag(nfull))) * pen
    return ThinBasis(q, q.T @ nfull, pw)


def _whitening(nfull: np.ndarray) -> np.ndarray | None:
    """``L^-1`` of the Cholesky factor ``L`` of ``N_full`` (to standard form), or None."""
    n = nfull.shape[0]
    ridge = 1e-12 * np.trace(nfull) / n
    try:
        low = np.linalg.cholesky(nfull + ridge * np.eye(n))
    except np.linalg.LinAlgError:
        return None
    return solve_triangular(low, np.eye(n), lower=True)


def _solve_separable(
    u: np.ndarray,
    v: np.ndarray,
    ku: np.ndarray,
    kv: np.ndarray,
    deg: tuple[int, int],
    w: np.ndarray,
    p: np.ndarray,
    smoothing: float = 0.0,
) -> np.ndarray:
    # Stage 1: curve fit down each column j (over u): e intermediate points per column.
    inter = fit_curve(u, p, w, ku, deg[0], smoothing)  # (e, n, 3)
    col_ok = np.isfinite(inter).all(axis=(0, 2))
    # Stage-2 weight of intermediate point (k, j): the weighted share of basis k's mass
    # in column j that had data, so an intermediate point standing over a gap (where
    # the column fit only extrapolated) counts little. Scaling a whole row k of weights
    # does not change that row's fit, so tensor weights a_i b_j still give exactly the
    # tensor-product solution.
    bu = basis_matrix(u, ku, deg[0])  # (m, e)
    support = (bu.T @ w) / np.maximum(bu.sum(axis=0), 1e-300)[:, None]  # (e, n)
    support = np.where(col_ok[None, :], support, 0.0)
    # Stage 2: curve fit across each row of intermediate points (over v).
    rows = np.moveaxis(np.nan_to_num(inter), 1, 0)  # (n, e, 3): the e rows as curves
    ctrl = fit_curve(v, rows, support.T, kv, deg[1], smoothing)
    if not np.isfinite(ctrl).all():
        raise BoneUSReconError(
            "the grid has too few complete columns for the requested control points "
            "(separable fit); use fewer control points or method 'direct'"
        )
    return np.moveaxis(ctrl, 0, 1)  # (e, f, 3)


@functools.cache
def _blas() -> ThreadpoolController:
    """The BLAS libraries numpy and SciPy loaded (looked up once: ~1 ms)."""
    return ThreadpoolController()


def fewer_control_points(
    used: tuple[int, int, int], degree: tuple[int, int], asked: tuple[int, int]
) -> tuple[int, int]:
    """The control points to fit on a grid too short for ``asked`` (see
    :attr:`FitParams.fewer_if_short`); ``asked`` itself where the grid holds it.

    ``used``: the grid's slices, rays and points holding data. A count that cannot
    reach ``degree + 1`` is left as asked, for the fit to refuse with its message.
    """
    (rows, cols, points), (p, q), (e, f) = used, degree, asked
    if rows < p + 1 or cols < q + 1:
        return e, f
    if rows < e:
        e = max(p + 1, rows // 2)
    f = min(f, cols)
    while e * f > points and e > p + 1:
        e -= 1
    return e, f


def fit_surface(
    grid_points: np.ndarray,
    params: FitParams = FitParams(),
    *,
    u: np.ndarray | None = None,
    v: np.ndarray | None = None,
    weights: np.ndarray | None = None,
) -> FitResult:
    """Fit a tensor-product B-spline surface to an (m, n) grid with missing entries.

    The fit's linear algebra runs on one BLAS thread (``threadpoolctl``; the limit is
    the process's while the fit runs). Its matrices are small (90 unknowns at 15 x 6
    control points): on two cores, multithreaded OpenBLAS took 70-95 ms per fit of a
    40-slice grid against 25 ms on one thread, waking its threads for products of
    90 x 90 matrices, and its threaded products round the last bits differently, so a
    batch worker (one BLAS thread, :data:`.batch.WORKER_ENV`) and a single run
    differed by 1e-11 mm. On one thread the surface is the same bit for bit wherever
    it is fitted.

    Parameters
    ----------
    grid_points : ndarray, shape (m, n, 3)
        Grid points in mm; NaN entries are missing (weight 0).
    params : FitParams
    u, v : ndarray, optional
        Increasing row / column parameters (any scale; normalised to [0, 1]). Default:
        averaged chord length (see module docstring). The pipeline passes the axis arc
        length and the ray angles.
    weights : ndarray, shape (m, n), optional
        Prior weights (default 1).

    Returns
    -------
    FitResult

    Raises
    ------
    BoneUSReconError
        Too few valid points, rows or columns for the requested control points, or a
        singular system.

    Examples
    --------
    >>> uu, vv = np.meshgrid(np.linspace(0, 30, 20), np.linspace(-1, 1, 9), indexing="ij")
    >>> grid = np.stack([uu, 5 * vv, 2 - vv**2], axis=-1)
    >>> fit = fit_surface(grid, FitParams(n_control_points=(5, 4)), u=uu[:, 0], v=vv[0])
    >>> bool(fit.rms_mm < 1e-6)  # a quadratic in (u, v) is in the spline space
    True
    """
    with _blas().limit(limits=1, user_api="blas"):
        return _fit_surface(grid_points, params, u, v, weights)


def _fit_surface(
    grid_points: np.ndarray,
    params: FitParams,
    u: np.ndarray | None,
    v: np.ndarray | None,
    weights: np.ndarray | None,
) -> FitResult:
    """:func:`fit_surface` (run on one BLAS thread)."""
    pts = np.asarray(grid_points, float)
    if pts.ndim != 3 or pts.shape[2] != 3:
        raise BoneUSReconError(f"grid points must have shape (m, n, 3), got {pts.shape}")
    m, n = pts.shape[:2]
    (p, q), (e, f) = params.degree, params.n_control_points
    present = np.isfinite(pts).all(-1)
    w0 = np.ones((m, n)) if weights is None else np.asarray(weights, float).copy()
    w0 = np.where(present, w0, 0.0)
    uu = _chord_params(pts, 0) if u is None else _normalise(u)
    vv = _chord_params(pts, 1) if v is None else _normalise(v)
    if uu.size != m or vv.size != n:
        raise BoneUSReconError("u and v must have one value per grid row and column")
    has_data = (w0 > 0).any(axis=1)
    rows_used = int(has_data.sum())
    # Slices at one position (a probe held still) count once (distinct_params).
    positions = distinct_params(uu[has_data], SAME_POSITION / max(e - p, 1)).size
    cols_used = int((w0 > 0).any(axis=0).sum())
    n_valid = int((w0 > 0).sum())
    if params.fewer_if_short:
        e, f = fewer_control_points((positions, cols_used, n_valid), (p, q), (e, f))
    if positions < e or cols_used < f or n_valid < e * f:
        at = f" at {positions} positions" if positions < rows_used else ""
        raise BoneUSReconError(
            f"too few valid grid points for {e} x {f} control points: {n_valid} points "
            f"in {rows_used} slices{at} x {cols_used} rays (need at least {e} slices, "
            f"{f} rays and {e * f} points); use fewer control points"
        )
    ku = averaging_knots(uu, e, p)
    kv = averaging_knots(vv, f, q)
    bu = basis_matrix(uu, ku, p)
    bv = basis_matrix(vv, kv, q)
    dbu = _basis_derivative_matrix(uu, ku, p)
    dbv = _basis_derivative_matrix(vv, kv, q)
    pz = np.nan_to_num(pts)
    pen = _penalty(e, f)
    # The thin-data split (direct method only): the normal matrix of a complete grid at
    # weight 1, what "determined by the data" is measured against, its whitening, and
    # the thin directions' penalty, which keeps the curvature around the bone
    # (thin_basis); all fixed for the fit, so made once, and only when used.
    thin = None
    if params.method == "direct" and params.thin_weight > 0:
        nfull = np.kron(bu.T @ bu, bv.T @ bv)
        whitening = _whitening(nfull)
        if whitening is not None:
            thin_pen = _penalty(e, f, around=3)
            thin = _ThinSetup(nfull, params.thin_weight, params.thin_share, whitening, thin_pen)

    def solve(w: np.ndarray) -> np.ndarray:
        if params.method == "direct":
            return _solve_direct(bu, bv, w, pz, params.smoothing, pen, thin)
        return _solve_separable(
            uu, vv, ku, kv, (p, q), w, np.where(present[..., None], pts, np.nan), params.smoothing
        )

    def difference(ctrl: np.ndarray) -> np.ndarray:
        # Grid point minus fitted point (NaN where missing): the residuals' norm, and
        # what the robust weights split (computed once per fit, shared by both).
        return np.where(present[..., None], pts - _tensor_eval(bu, ctrl, bv), np.nan)

    def robust_residuals(ctrl: np.ndarray, diff: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        # What the weights judge (module docstring, "Robust reweighting"): per frame
        # the offset along the normal, per point also its odd slide within the surface.
        return _offsets(diff, _tensor_eval(dbu, ctrl, bv), _tensor_eval(bu, ctrl, dbv))

    w = w0
    ctrl = solve(w)
    diff = difference(ctrl)
    res = _norm3(diff)
    frame_w = np.ones(m)
    iterations = 0
    if params.robust != "none":
        for it in range(params.robust_iterations):
            kind = "huber" if (params.robust == "huber" or it < 2) else "tukey"
            nres, pres = robust_residuals(ctrl, diff)
            r = np.where(present, pres, 0.0)
            scale = mad_scale(pres[w > 0], params.min_scale_mm)
            pw = robust_weights(r, scale, kind)
            if params.per_frame:
                fr = row_medians(np.where(w0 > 0, nres, np.nan))
                fscale = mad_scale(fr[(w0 > 0).any(axis=1)], params.min_scale_mm)
                frame_w = robust_weights(fr, fscale, kind)
            new_w = w0 * pw * frame_w[:, None]
            try:
                new_ctrl = solve(new_w)
            except BoneUSReconError:
                break  # weights removed too much: keep the last well-posed fit
            iterations = it + 1
            change = np.abs(new_w - w).max()
            w, ctrl = new_w, new_ctrl
            diff = difference(ctrl)
            res = _norm3(diff)
            if change < 1e-2:  # weights settled: further iterations move < 0.01 mm
                break
    kept = present & (w > 0)
    rms = float(np.sqrt(np.mean(res[kept] ** 2))) if kept.any() else float("nan")
    rms_all = float(np.sqrt(np.nanmean(res**2)))
    return FitResult(
        surface=BSplineSurface(ctrl, ku, kv, (p, q)),
        u=uu,
        v=vv,
        residuals=res,
        weights=w,
        frame_weights=frame_w,
        rms_mm=rms,
        rms_all_mm=rms_all,
        iterations=iterations,
        method=params.method,
    )

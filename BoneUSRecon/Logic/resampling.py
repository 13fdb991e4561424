"""Ray resampling of the segmented contours into an m x n grid (paper section II.C).

The segmented points are dense within a slice (~0.1 mm apart) but sparse between
slices (0.2-2 mm, up to 20 mm in the paper), so they are put on a regular grid first:

1. **Slice centre** ``c(i)``: the centre of an algebraic (Kasa) circle fit to the
   slice's contour, in the slice plane. The imaged upper bone surface is an arc of a
   roughly round cross-section, so that centre sits inside the bone, which is where
   rays should start. When the fit is degenerate (a flat contour, radius outside
   ``[min_radius_mm, max_radius_mm]``) the centre is put half a chord below the
   chord's midpoint instead.
2. **Central axis**: a *robust penalised cubic spline* through the centres, parameterised by
   the frames' position along the sweep (projection of the image centres, which come
   from tracking and so do not suffer from segmentation failures, on their principal
   direction). A straight line, as in the paper, cannot follow the S-shaped clavicle
   (its axis bends by several millimetres over the sweep), so rays from a line would
   start off-centre and hit the contour at inconsistent angles; the spline follows
   the bend while its bandwidth (``axis_bandwidth_mm``, 10 mm) keeps it
   smooth. Frames whose centres come from false contours are down-weighted by
   iteratively reweighted fitting (Huber, then Tukey; gross outliers from the running
   median of their neighbours left out of the first fit) so they do not pull the axis.
3. ``c(i)`` is **updated** to where the axis crosses slice ``i``'s plane (Newton on
   the spline parameter, all slices at once).
4. **Rays**: ``n`` rays in the slice plane from ``c(i)`` at regular angles. Angles
   are measured in the slice plane from the image's "up" direction (toward the
   transducer, minus the row axis), positive toward the column axis, so the same
   ray index means the same direction in every slice. A grid vertex is the first
   intersection of the ray with the polyline joining consecutive contour points
   (segments longer than ``max_gap_mm`` are gaps, not bridged). A ray that misses is
   a NaN entry: never an invented point.

The mean resampling distance (paper: 0.14 mm) is the mean, over grid vertices, of the
distance from the vertex to the nearer end of the contour segment it lies on.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

import numpy as np
from scipy.interpolate import BSpline
from scipy.ndimage import median_filter

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.params_check import check_fields
from BoneUSRecon.Logic.robust import mad_scale, robust_weights
from BoneUSRecon.Logic.sweep import Sweep, frame_planes

__all__ = ["ResamplingParams", "ResampledGrid", "resample"]


#: Upper bound on rays per slice: more rays than a contour has points (a few hundred)
#: add no information, and memory and time grow with them (100,000 rays on a
#: 150-frame sweep took 35 s and 4 GB).
MAX_RAYS = 1000


@dataclass(frozen=True)
class ResamplingParams:
    """Parameters of the ray resampling.

    Attributes
    ----------
    n_rays : int
        Rays per slice (count). Paper II.C: 15. Default 24 (ours): each ray gives the
        fit one sample of the contour, and 15 rays over a 100-230 degree arc sample a
        crest or a flank's end 7-16 degrees apart, so the fit's 6 control points across
        see few points where the section bends most; 24 rays sample them 4-10 degrees
        apart, still far below the contours' own density (a few hundred points).
        Measured (session 40 in ``Testing/benchmarks/README.md``, each sweep's own
        segmentation), 15 -> 24 rays over 88 simulated sweeps (seeds 241, 251): gold
        mean 0.2366 -> 0.2284 mm (every harness group better), the surface's
        area-weighted distance to the true bone 0.129 -> 0.108 mm, its area within
        0.35 mm 0.934 -> 0.954; over 54 more (seeds 173, 179) gold 0.3009 -> 0.2928 mm
        and area 0.922 -> 0.935; the L14 recording 0.312 -> 0.311 mm. 30 rays: 0.2255,
        0.104, 0.957, but resampling and fitting 250 frames took 55 ms against 48 at 24
        (issue 11's bound: 50 ms); 45 rays 0.2250, no further gain.
    angle_span_deg : float or None
        Angle between the first and last ray (degrees). ``None``: chosen from the data
        (see ``auto_span_quantile``) so the rays cover what the probe saw (ours; the
        paper gives no value).
    angle_step_deg : float or None
        Angle between consecutive rays (degrees); when given it overrides
        ``angle_span_deg`` (span = step x (n_rays - 1)). The paper calls it theta.
    angle_centre_deg : float or None
        Direction of the middle ray, degrees from "up" toward the column axis.
        ``None``: the middle of the data's median angular extent.
    auto_span_quantile : float
        For the automatic span: the rays run from this quantile of the slices' first
        contour angles to the (1 - this) quantile of their last ones (0..0.5). 0: from
        the widest contour end to the widest on the other side, so no segmented point
        is out of the rays' reach; end rays that miss are NaN and the mesh is trimmed
        there. Measured on simulated sweeps of the five bones (150 frames): mean gold
        distance 0.18-0.24 mm at 0, 0.19-0.25 mm at 0.1, 0.23-0.28 mm at 0.5.
    rays : str
        ``"fixed"`` (the paper's: the same regular angles in every slice) or
        ``"extent"`` (regular angles spanning each slice's own contour, first and last
        ray on the contour's ends: no missing entries, and the surface reaches exactly
        as far as the segmentation did; v then means "position along the visible arc").
        Measured worse on simulated sweeps (the segmented ends jitter from frame to
        frame, so v does too: clavicle p95 0.56 vs 0.50 mm, humerus 1.47 vs 0.93 mm),
        hence not the default.
    axis : str
        ``"spline"`` (robust smoothing spline, default, follows curved bones) or
        ``"line"`` (robust straight line, the paper's choice).
    axis_bandwidth_mm : float
        Smoothing bandwidth of the spline axis (mm along the sweep): bends shorter than
        this are smoothed out. 10 mm: bones bend over several centimetres, while centre
        noise and false contours change from one frame to the next (our choice; the
        circle centres of faint or crest-shaped contours scatter by several mm from
        frame to frame on the hard simulated sweeps, and at 5 mm the axis followed
        them: over the lead's harness sweeps the surface's gold distance went 0.334 ->
        0.313 mm (seeds 53, 59) and 0.264 -> 0.256 mm (61, 67) from 5 to 10 mm, the
        L14 recording's 0.333 -> 0.337 mm and its cadaver-level copy's 1.648 -> 1.619).
    min_radius_mm, max_radius_mm : float
        Accepted range of the circle fit's radius (mm); outside it the chord fallback
        is used. 1-40 mm spans the cross-sections of the long bones in question.
    max_gap_mm : float
        Contour segments longer than this (mm) are treated as gaps (our choice; the
        segmentation joins points closer than 10 pixels, about 2-3 mm).
    axis_chord_share : float
        A slice whose contour's chord (first to last point) is shorter than this share
        of the sweep's median chord leaves its circle centre out of the axis fit (0..1;
        0: every slice's counts; if fewer than 3 slices would remain, all count). A
        circle fitted to a short arc can put its centre anywhere along the arc's normal
        (for a given point noise the centre's error grows as the inverse square of the
        chord), so a 3 mm piece at the end of a sweep bent the axis toward itself and
        the rays cast from there fanned over 90 degrees of that piece. Weighing such a
        centre down is not enough at a sweep's end, where nothing else holds the
        axis's last stretch (a synthetic tube with three 3 mm end pieces: 4.9 mm off
        the axis unweighed, 4.7 mm at weight (chord / (0.5 x median))**2, 0.02 mm
        left out); left out, the axis continues from the slices that measure it.
        Relative to the sweep's own contours, no length in mm. 0.5 (ours; session 30
        in ``Testing/benchmarks/README.md``): over 132 simulated sweeps gold mean
        0.2324 -> 0.2301 mm, six sweeps better by 0.02-0.19 mm (S tibia grey seed 59
        0.559 -> 0.366), none worse by 0.02; the L14 recording and its copies
        unchanged.
    """

    n_rays: int = 24
    angle_span_deg: float | None = None
    angle_step_deg: float | None = None
    angle_centre_deg: float | None = None
    auto_span_quantile: float = 0.0
    rays: str = "fixed"
    axis: str = "spline"
    axis_bandwidth_mm: float = 10.0
    min_radius_mm: float = 1.0
    max_radius_mm: float = 40.0
    max_gap_mm: float = 3.0
    axis_chord_share: float = 0.5

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=("axis_bandwidth_mm", "max_gap_mm", "min_radius_mm", "max_radius_mm"),
            within={"auto_span_quantile": "[0, 0.5]", "axis_chord_share": "[0, 1]"},
        )
        if self.n_rays < 2:
            raise BoneUSReconError(f"need at least 2 rays per slice, got {self.n_rays}")
        if self.n_rays > MAX_RAYS:
            raise BoneUSReconError(
                f"at most {MAX_RAYS} rays per slice, got {self.n_rays} (the paper uses 15)"
            )
        if self.rays not in ("fixed", "extent"):
            raise BoneUSReconError(f"unknown ray mode {self.rays!r}; use 'fixed' or 'extent'")
        if self.axis not in ("spline", "line"):
            raise BoneUSReconError(f"unknown axis model {self.axis!r}; use 'spline' or 'line'")
        if self.angle_span_deg is not None and not 0 < self.angle_span_deg < 360:
            raise BoneUSReconError(
                f"angle span must be in (0, 360) degrees, got {self.angle_span_deg}"
            )
        if self.angle_step_deg is not None and not (
            0 < self.angle_step_deg * (self.n_rays - 1) < 360
        ):
            raise BoneUSReconError(f"angle step {self.angle_step_deg} degrees is out of range")
        if self.min_radius_mm >= self.max_radius_mm:
            raise BoneUSReconError(
                f"ResamplingParams.min_radius_mm ({self.min_radius_mm}) must be below "
                f"max_radius_mm ({self.max_radius_mm})"
            )


@dataclass(frozen=True, eq=False)
class ResampledGrid:
    """The m x n grid of resampled points (rows = slices in sweep order along the axis).

    Attributes
    ----------
    points : ndarray, shape (m, n, 3)
        Grid vertices in reference mm; NaN where the ray missed the contour.
    frames : ndarray of int, shape (m,)
        Frame index (in the sweep file) of each row.
    centres : ndarray, shape (m, 3)
        Updated slice centres ``c(i)`` (on the axis), mm.
    raw_centres : ndarray, shape (m, 3)
        Centres from the per-slice circle fits, before the axis update, mm.
    angles : ndarray, shape (n,)
        Ray angles (radians from "up", toward the column axis); with per-slice rays
        (``rays="extent"``) their mean over slices.
    ray_angles : ndarray, shape (m, n)
        The ray angles of each slice (rows of ``angles`` for fixed rays).
    up, lateral : ndarray, shape (m, 3)
        Unit in-plane directions defining the angles (minus row axis, column axis).
    axis_position : ndarray, shape (m,)
        Arc length (mm) of the centres along the axis: the natural u parameter.
    axis_weights : ndarray, shape (m,)
        Robust weight of each slice's raw centre in the axis fit (0 = outlier).
    extent : ndarray, shape (m, 2)
        Angles (radians, as ``angles``) of the contour's two ends seen from the updated
        centre: where the data stop between rays. The mesh is trimmed there, not at the
        last ray that hit (:mod:`BoneUSRecon.Logic.surface`).
    mean_resampling_distance_mm : float
        Mean distance (mm) from the grid vertices to the nearer original contour point
        of the segment they lie on.
    """

    points: np.ndarray
    frames: np.ndarray
    centres: np.ndarray
    raw_centres: np.ndarray
    angles: np.ndarray
    ray_angles: np.ndarray
    up: np.ndarray
    lateral: np.ndarray
    axis_position: np.ndarray
    axis_weights: np.ndarray
    extent: np.ndarray
    mean_resampling_distance_mm: float

    @property
    def valid(self) -> np.ndarray:
        """(m, n) bool: entries where the ray hit the contour."""
        return np.isfinite(self.points).all(axis=-1)

    @property
    def coverage(self) -> float:
        """Share of grid entries that hold a point (0..1)."""
        return float(self.valid.mean()) if self.valid.size else 0.0

    @property
    def shape(self) -> tuple[int, int]:
        """``(m, n)``."""
        return int(self.points.shape[0]), int(self.points.shape[1])


def _pad(contours: Sequence[np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """Stack ragged (K_i, d) arrays into (m, Kmax, d) with NaN padding and a mask."""
    kmax = max(c.shape[0] for c in contours)
    d = contours[0].shape[1]
    out = np.full((len(contours), kmax, d), np.nan)
    for r, c in enumerate(contours):  # one copy per slice; the hot work below is batched
        out[r, : c.shape[0]] = c
    return out, np.logical_and.reduce(np.isfinite(out), axis=-1)


def _circle_centres(xy: np.ndarray, mask: np.ndarray, rmin: float, rmax: float) -> np.ndarray:
    """Batched Kasa circle fit; chord fallback where degenerate. Returns (m, 2)."""
    x = np.where(mask, xy[..., 0], 0.0)
    y = np.where(mask, xy[..., 1], 0.0)
    one = mask.astype(float)
    # Normal equations of  min sum (x^2 + y^2 + D x + E y + F)^2, one 3x3 per slice.
    cols = np.stack([x, y, one], axis=-1)  # (m, K, 3)
    a = np.matmul(np.swapaxes(cols, 1, 2), cols)  # batched BLAS, faster than einsum
    b = -np.matmul(np.swapaxes(cols, 1, 2), (x * x + y * y)[..., None])[..., 0]
    det = np.linalg.det(a)
    scale = np.einsum("mii->m", a) ** 3 + 1e-300
    ok = np.abs(det) > 1e-12 * scale
    sol = np.zeros_like(b)
    if ok.any():
        sol[ok] = np.linalg.solve(a[ok], b[ok][..., None])[..., 0]
    cx, cy = -sol[:, 0] / 2, -sol[:, 1] / 2
    r2 = cx**2 + cy**2 - sol[:, 2]
    radius = np.sqrt(np.maximum(r2, 0.0))
    # Chord fallback: half a chord below the chord's midpoint (y is "up").
    first, last = _contour_ends(xy, mask)
    mid = (first + last) / 2
    half = np.linalg.norm(last - first, axis=1) / 2
    fallback = mid - np.stack([np.zeros_like(half), np.maximum(half, rmin)], axis=1)
    good = ok & (r2 > 0) & (radius >= rmin) & (radius <= rmax)
    # A circle whose centre lies above the arc means a concave contour: not a bone top.
    mean_y = np.nanmean(np.where(mask, xy[..., 1], np.nan), axis=1)
    good &= cy < mean_y
    return np.where(good[:, None], np.stack([cx, cy], axis=1), fallback)


def _contour_ends(xy: np.ndarray, mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """First and last point of each slice's padded contour, (m, 2) each."""
    return xy[:, 0], xy[np.arange(xy.shape[0]), mask.sum(axis=1) - 1]


def _chord_weights(xy: np.ndarray, mask: np.ndarray, params: ResamplingParams) -> np.ndarray:
    """Per-slice weight (0 or 1) of its circle centre in the axis fit, from its
    contour's chord (``ResamplingParams.axis_chord_share``; contours ordered along
    themselves). A slice left out has axis weight 0, so it does not set the fixed
    rays' span either (only slices whose centre the axis trusts do)."""
    m = xy.shape[0]
    if not params.axis_chord_share > 0 or m == 0:
        return np.ones(m)
    first, last = _contour_ends(xy, mask)
    chord = np.linalg.norm(last - first, axis=1)
    ref = params.axis_chord_share * float(np.median(chord))
    keep = chord >= ref
    if not ref > 0 or keep.sum() < 3:
        return np.ones(m)
    return keep.astype(float)


def _fit_axis(
    t: np.ndarray, c: np.ndarray, params: ResamplingParams, prior: np.ndarray | None = None
) -> tuple[Callable[..., np.ndarray], np.ndarray]:
    """Robust axis c(t): penalised cubic spline or line, IRLS Huber then Tukey.

    ``prior``: per-slice weights the robust ones are multiplied by (the centres'
    reliability, :func:`_chord_weights`); None: 1.

    The spline is a P-spline (Eilers & Marx): cubic B-splines with knots every
    ``axis_bandwidth_mm`` along the sweep and a light second-difference penalty, which
    smooths like a smoothing spline of that bandwidth, keeps knot spans without
    centres (blocks of failed frames) well defined, and costs one small banded solve
    per iteration (scipy's ``make_smoothing_spline`` has one knot per frame and is
    ~50x slower here).

    Returns a callable ``f(t, nu=0) -> (m, 3)`` and the final per-slice weights.
    """
    m = t.size
    # Gross outliers left out of the first fit: centres farther from the running median
    # of their neighbours (5 slices) than Tukey's cut-off (4.685 robust spreads). With
    # knots every bandwidth and a slice every few mm the spline has nearly a degree of
    # freedom per centre, so an unweighted first fit follows an outlying centre, its
    # neighbours take the residual, and the robust weights then reject the good centres
    # beside it (standard clavicle, seed 53: one frame's contour 7 points shorter and
    # the axis bent to a centre 9 mm off; the surface's gold distance 0.18 -> 0.43 mm).
    # Only gross ones: down-weighting the others too (Huber) changed clean sweeps' fits.
    r0 = np.linalg.norm(c - median_filter(c, size=(min(5, m), 1), mode="nearest"), axis=1)
    w = (r0 < 4.685 * mad_scale(r0, floor=0.3, empty=1.0)).astype(float)
    if (w > 0).sum() < max(3, m // 4):
        w = np.ones(m)
    prior = np.ones(m) if prior is None else prior
    w = w * prior
    length = max(float(t[-1] - t[0]), 1e-6)
    use_line = params.axis == "line" or m < 5
    if not use_line:
        n_int = max(1, int(np.ceil(length / params.axis_bandwidth_mm)))
        k = 3
        knots = np.r_[np.full(k, t[0]), np.linspace(t[0], t[-1], n_int + 1), np.full(k, t[-1])]
        basis = BSpline.design_matrix(t, knots, k).toarray()  # (m, nb)
        nb = basis.shape[1]
        d2 = np.diff(np.eye(nb), 2, axis=0)
        pen = d2.T @ d2
    f = None
    for it in range(6):
        if use_line:
            sw = w.sum()
            t0 = (w * t).sum() / sw
            c0 = (w[:, None] * c).sum(0) / sw
            dt = t - t0
            slope = ((w * dt)[:, None] * (c - c0)).sum(0) / max((w * dt * dt).sum(), 1e-12)

            def f(tt, nu=0, c0=c0, t0=t0, slope=slope):
                tt = np.asarray(tt, float)
                if nu == 0:
                    return c0 + (tt - t0)[:, None] * slope
                return np.broadcast_to(slope, (tt.size, 3)).copy()

        else:
            a = basis.T @ (w[:, None] * basis)
            lam = 1e-3 * max(np.trace(a) / nb, 1e-12)
            coef = np.linalg.solve(a + lam * pen, basis.T @ (w[:, None] * c))
            f = BSpline(knots, coef, k, extrapolate=True)
        r = np.linalg.norm(c - f(t), axis=1)
        scale = mad_scale(r[w > 0], floor=0.3, empty=1.0)  # 0.3 mm: below that, centres are "exact"
        w = robust_weights(r, scale, "huber" if it < 2 else "tukey") * prior
        if (w > 0).sum() < max(3, m // 4):  # never let the fit reject most slices
            w = np.maximum(w, 1e-3)
    assert f is not None
    return f, w


def resample(
    contours_mm: Sequence[tuple[int, np.ndarray]],
    sweep: Sweep,
    params: ResamplingParams = ResamplingParams(),
) -> ResampledGrid:
    """Resample per-slice bone contours onto an m x n grid of ray intersections.

    Parameters
    ----------
    contours_mm : sequence of (frame, ndarray (K, 3))
        Accepted contours in reference mm, points ordered along the contour (as given
        by ``SegmentationResult.contours_mm``); slices with fewer than 2 points are
        skipped.
    sweep : Sweep
        The sweep the frames belong to (slice planes come from its poses).
    params : ResamplingParams

    Returns
    -------
    ResampledGrid
        Rows ordered along the sweep direction; rows in which no ray hit the contour
        are dropped.

    Raises
    ------
    BoneUSReconError
        Fewer than 3 usable slices.
    """
    items = [
        (int(k), np.asarray(p, float).reshape(-1, 3))
        for k, p in contours_mm
        if np.asarray(p).reshape(-1, 3).shape[0] >= 2
    ]
    if len(items) < 3:
        raise BoneUSReconError(
            f"only {len(items)} slices with a bone contour; at least 3 are needed to "
            "resample a surface",
            sweep.source,
        )
    frames = np.array([k for k, _ in items])
    origin, axes, normal = frame_planes(sweep.image_to_reference[frames])
    lateral = axes[:, :, 0]
    up = -axes[:, :, 1]

    # Order slices along the sweep by the tracked image centres (independent of the
    # segmentation, so a false contour cannot reorder slices).
    hw = np.array([(sweep.width - 1) / 2, (sweep.height - 1) / 2, 0.0, 1.0])
    img_centre = np.einsum("mab,b->ma", sweep.image_to_reference[frames, :3, :], hw)
    mean = img_centre.mean(0)
    direction = np.linalg.svd(img_centre - mean, full_matrices=False)[2][0]
    # Orient the direction with the mean plane normal so u increases consistently.
    if direction @ normal.mean(0) < 0:
        direction = -direction
    t = (img_centre - mean) @ direction
    order = np.argsort(t, kind="stable")
    frames, origin, lateral, up, normal, t = (
        frames[order],
        origin[order],
        lateral[order],
        up[order],
        normal[order],
        t[order],
    )
    pts3, mask = _pad([items[o][1] for o in order])
    # Strictly increasing t for the spline (frames at the same position happen when
    # the probe pauses): add a negligible ramp.
    t = t + np.arange(t.size) * 1e-6

    # In-plane 2D coordinates (x = lateral, y = up) relative to each frame's origin.
    rel = pts3 - origin[:, None, :]
    xy = np.matmul(rel, np.stack([lateral, up], axis=-1))  # (m, K, 2)
    c2 = _circle_centres(xy, mask, params.min_radius_mm, params.max_radius_mm)
    raw_centres = origin + c2[:, :1] * lateral + c2[:, 1:] * up

    axis_fn, axis_w = _fit_axis(t, raw_centres, params, _chord_weights(xy, mask, params))
    # Where the axis crosses each slice plane: g(s) = (a(s) - o_i) . n_i = 0, Newton
    # from s = t_i, all slices at once.
    s = t.copy()
    for _ in range(4):
        a = axis_fn(s)
        da = axis_fn(s, 1)
        g = np.einsum("md,md->m", a - origin, normal)
        dg = np.einsum("md,md->m", da, normal)
        step = np.where(np.abs(dg) > 1e-9, g / np.where(dg == 0, 1, dg), 0.0)
        s = s - np.clip(step, -20.0, 20.0)
    centres = axis_fn(s)
    # Guard: project onto the plane exactly (Newton leaves ~1e-9 mm).
    centres = centres - np.einsum("md,md->m", centres - origin, normal)[:, None] * normal
    crel = centres - origin
    cxy = np.stack([np.einsum("md,md->m", crel, lateral), np.einsum("md,md->m", crel, up)], 1)
    q = xy - cxy[:, None, :]  # contour points relative to the updated centre
    theta = np.where(mask, np.arctan2(q[..., 0], q[..., 1]), np.nan)
    lo, hi = np.nanmin(theta, axis=1), np.nanmax(theta, axis=1)

    if params.rays == "extent":
        # A hair inside the ends so the end rays cross the end segments.
        eps = 1e-7 * np.maximum(hi - lo, 1e-9)
        ray_angles = np.linspace(lo + eps, hi - eps, int(params.n_rays), axis=1)  # (m, n)
    else:
        # The span comes from slices whose centre agrees with the axis: a false contour
        # (deeper, so wider as seen from the centre) must not stretch the rays.
        trusted = axis_w > 0.5
        if trusted.sum() < 3:
            trusted = np.ones_like(trusted)
        ray_angles = np.broadcast_to(
            _ray_angles(q[trusted], mask[trusted], params), (q.shape[0], int(params.n_rays))
        )
    radius, near = _cast_rays(q, mask, ray_angles, params.max_gap_mm)
    d = np.stack([np.sin(ray_angles), np.cos(ray_angles)], axis=-1)  # (m, n, 2)
    pts2 = radius[..., None] * d  # (m, n, 2) relative to centre
    grid = (
        centres[:, None, :] + pts2[..., 0:1] * lateral[:, None, :] + pts2[..., 1:2] * up[:, None, :]
    )
    # Drop slices no ray hit: they carry no information for the fit.
    keep = np.isfinite(radius).any(axis=1)
    if keep.sum() < 3:
        raise BoneUSReconError(
            f"the rays hit the contours in only {int(keep.sum())} slices; at least 3 are "
            "needed (check the angle span)",
            sweep.source,
        )
    mean_dist = float(np.nanmean(near)) if np.isfinite(near).any() else float("nan")

    centres_k = centres[keep]
    arc = np.r_[0.0, np.cumsum(np.linalg.norm(np.diff(centres_k, axis=0), axis=1))]
    return ResampledGrid(
        points=grid[keep],
        frames=frames[keep],
        centres=centres_k,
        raw_centres=raw_centres[keep],
        angles=ray_angles[keep].mean(axis=0),
        ray_angles=np.array(ray_angles[keep]),
        up=up[keep],
        lateral=lateral[keep],
        axis_position=arc,
        axis_weights=axis_w[keep],
        extent=np.stack([lo, hi], axis=1)[keep],
        mean_resampling_distance_mm=mean_dist,
    )


def _cast_rays(
    q: np.ndarray, mask: np.ndarray, angles: np.ndarray, max_gap: float
) -> tuple[np.ndarray, np.ndarray]:
    """First crossing of each ray with each slice's contour polyline.

    Parameters
    ----------
    q : ndarray, shape (m, K, 2)
        Contour points relative to the slice centre (x lateral, y up), NaN-padded.
    mask : ndarray of bool, shape (m, K)
    angles : ndarray, shape (m, n)
        Regularly spaced ray angles of each slice (radians from up toward lateral).
    max_gap : float
        Segments longer than this are gaps.

    Returns
    -------
    radius : ndarray, shape (m, n)
        Distance along the ray to the first crossing; NaN where the ray misses.
    near : ndarray, shape (m, n)
        Distance from the crossing to the nearer end of the crossed segment.

    Notes
    -----
    Rather than testing every (segment, ray) pair, each segment is tested only against
    the rays whose angle lies between its end points' angles (at most a few, as
    segments are much shorter than the ray spacing), so the work is O(m K), not
    O(m K n). Regular angles make "which rays" an index range.
    """
    m, n = angles.shape
    pa, pb = q[:, :-1], q[:, 1:]
    ok = mask[:, :-1] & mask[:, 1:]
    ok &= np.linalg.norm(pb - pa, axis=-1) <= max_gap
    theta = np.arctan2(q[..., 0], q[..., 1])
    ta, tb = theta[:, :-1], theta[:, 1:]
    ok &= np.abs(tb - ta) < np.pi  # a segment across "straight down" wraps: no ray there
    step = ((angles[:, -1] - angles[:, 0]) / (n - 1))[:, None]
    step = np.where(step > 0, step, 1.0)
    a0 = angles[:, :1]
    fa, fb = (ta - a0) / step, (tb - a0) / step
    lo = np.ceil(np.minimum(fa, fb) - 1e-9)
    hi = np.floor(np.maximum(fa, fb) + 1e-9)
    lo = np.where(ok, np.maximum(lo, 0), 1)
    hi = np.where(ok, np.minimum(hi, n - 1), 0)
    count = (hi - lo + 1).astype(int)
    sl, sg = np.nonzero(count > 0)
    first = lo[sl, sg].astype(int)
    cnt = count[sl, sg]
    # Expand segments crossing several rays into one candidate per (segment, ray).
    rep = np.repeat(np.arange(sl.size), cnt)
    offs = np.arange(rep.size) - np.repeat(np.cumsum(cnt) - cnt, cnt)
    sl, sg, ray = sl[rep], sg[rep], first[rep] + offs
    a, b = pa[sl, sg], pb[sl, sg]
    e = b - a
    dx, dy = np.sin(angles[sl, ray]), np.cos(angles[sl, ray])
    # t d = a + s e  ->  t = (a x e) / (d x e)   (2D cross products)
    den = dx * e[:, 1] - dy * e[:, 0]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (a[:, 0] * e[:, 1] - a[:, 1] * e[:, 0]) / den
    good = (np.abs(den) > 1e-12) & (t > 0)
    sl, ray, t, a, b = sl[good], ray[good], t[good], a[good], b[good]
    dx, dy = dx[good], dy[good]
    radius = np.full((m, n), np.nan)
    near = np.full((m, n), np.nan)
    if t.size:
        key = sl * n + ray
        order = np.lexsort((t, key))  # by (slice, ray), nearest crossing first
        _, firsts = np.unique(key[order], return_index=True)
        pick = order[firsts]
        radius.flat[key[pick]] = t[pick]
        v = t[pick, None] * np.stack([dx[pick], dy[pick]], axis=1)
        near.flat[key[pick]] = np.minimum(
            np.linalg.norm(v - a[pick], axis=1), np.linalg.norm(v - b[pick], axis=1)
        )
    return radius, near


def _ray_angles(q: np.ndarray, mask: np.ndarray, params: ResamplingParams) -> np.ndarray:
    """Regularly spaced ray angles (radians), from the parameters or the data."""
    n = int(params.n_rays)
    if params.angle_centre_deg is None or (
        params.angle_span_deg is None and params.angle_step_deg is None
    ):
        ang = np.arctan2(q[..., 0], q[..., 1])  # from "up" toward lateral
        ang = np.where(mask, ang, np.nan)
        qa = params.auto_span_quantile
        lo = float(np.nanquantile(np.nanmin(ang, axis=1), qa))
        hi = float(np.nanquantile(np.nanmax(ang, axis=1), 1.0 - qa))
    if params.angle_step_deg is not None:
        span = np.deg2rad(params.angle_step_deg) * (n - 1)
    elif params.angle_span_deg is not None:
        span = np.deg2rad(params.angle_span_deg)
    else:
        span = hi - lo
    centre = (
        np.deg2rad(params.angle_centre_deg)
        if params.angle_centre_deg is not None
        else (lo + hi) / 2
    )
    return centre + np.linspace(-span / 2, span / 2, n)

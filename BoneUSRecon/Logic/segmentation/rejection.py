"""Per-frame confidence and rejection of implausible contours.

Checks, the same for every segmenter, measured on the frame itself (not on the
segmenter's internal score, so a segmenter cannot vouch for its own mistakes):

* unshadowed ends: end points with no shadow under them (a contour running from the
  bone onto a tissue layer at its edge) are trimmed first.
* ``no bone found``: the segmenter returned nothing.
* ``contour too short``: lateral extent below ``min_length_mm`` or too few points.
* ``low contrast``: the mean ``Dif`` (bright band against above and below) is weak.
* ``no acoustic shadow``: the region 1-5 mm under the contour is not much darker than
  the echo itself (a tissue layer or noise, not bone: the paper's false positives were
  "images with important noise on the acoustic shadow under the bone").
* ``jump`` (after all frames): the contour's typical depth difference from what its
  neighbouring frames predict at the same columns (a robust Theil-Sen line through
  their depths along the sequence) exceeds ``jump_mm``: bones are continuous and the
  probe moves smoothly. In kept frames, single points off that prediction by more
  than ``point_jump_mm``, or beyond the neighbours' lateral extent by more than
  ``extend_mm``, are dropped.

The confidence in [0, 1] is the product of soft versions of these checks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BoneUSRecon.Logic.segmentation.params import RejectionParams

__all__ = [
    "FrameEvidence",
    "frame_evidence",
    "frame_verdict",
    "neighbour_deviation",
    "point_shadow_ratio",
    "trim_unshadowed_ends",
    "trim_kinked_ends",
]


@dataclass(frozen=True)
class FrameEvidence:
    """Image evidence under a contour (grey values 0..255, lengths mm)."""

    length_mm: float
    n_points: int
    echo: float
    above: float
    shadow: float

    @property
    def contrast(self) -> float:
        """Mean ``Dif`` in grey/255 units (2 echo - above - shadow)."""
        return (2 * self.echo - self.above - self.shadow) / 255.0

    @property
    def shadow_ratio(self) -> float:
        """Shadow intensity relative to the echo's (0 = black shadow)."""
        return self.shadow / max(self.echo, 1.0)


def frame_evidence(
    image: np.ndarray, points_px: np.ndarray, spacing: tuple[float, float]
) -> FrameEvidence:
    """Measure echo, above and shadow intensities along a contour.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W)
    points_px : ndarray, shape (K, 2)
    spacing : (sx, sy)
    """
    sx, sy = float(spacing[0]), float(spacing[1])
    k = points_px.shape[0]
    if k == 0:
        return FrameEvidence(0.0, 0, 0.0, 0.0, 0.0)
    h, w = image.shape
    i = np.clip(np.rint(points_px[:, 0]).astype(np.intp), 0, w - 1)
    j = np.rint(points_px[:, 1]).astype(np.intp)

    def band(a_mm: float, b_mm: float) -> float:
        a = int(np.floor(a_mm / sy))
        b = max(a + 1, int(np.ceil(b_mm / sy)))
        rows = j[:, None] + np.arange(a, b)[None, :]
        inside = (rows >= 0) & (rows < h)
        if not inside.any():
            return float("nan")
        vals = image[np.clip(rows, 0, h - 1), i[:, None]].astype(np.float64)
        return float(vals[inside].mean())

    echo = band(-0.3, 0.3)
    above = band(-1.8, -0.4)
    shadow = band(1.0, 5.0)
    if not np.isfinite(shadow):  # contour at the very bottom: no room for a shadow
        shadow = echo
    if not np.isfinite(above):
        above = 0.0
    length = float(np.ptp(points_px[:, 0]) * sx) if k > 1 else 0.0
    return FrameEvidence(length, k, echo, above, shadow)


def _band_means(
    image: np.ndarray, i: np.ndarray, j: np.ndarray, a_mm: float, b_mm: float, sy: float
) -> np.ndarray:
    """Per point, the mean grey value of rows ``j + [a_mm, b_mm)`` in column ``i`` (NaN outside)."""
    h = image.shape[0]
    a = int(np.floor(a_mm / sy))
    b = max(a + 1, int(np.ceil(b_mm / sy)))
    rows = j[:, None] + np.arange(a, b)[None, :]
    inside = (rows >= 0) & (rows < h)
    vals = image[np.clip(rows, 0, h - 1), i[:, None]].astype(np.float64)
    n = inside.sum(axis=1)
    total = np.where(inside, vals, 0.0).sum(axis=1)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def point_shadow_ratio(
    image: np.ndarray, points_px: np.ndarray, spacing: tuple[float, float]
) -> np.ndarray:
    """Per point, mean intensity 1-5 mm below over the echo's (+-0.3 mm), shape (K,).

    Points with no room for a shadow below get 1 (no evidence of a shadow). The
    ratios are smoothed by a running median of 5 points (speckle).
    """
    from scipy.ndimage import median_filter

    sy = float(spacing[1])
    w = image.shape[1]
    i = np.clip(np.rint(points_px[:, 0]).astype(np.intp), 0, w - 1)
    j = np.rint(points_px[:, 1]).astype(np.intp)
    echo = _band_means(image, i, j, -0.3, 0.3, sy)
    shadow = _band_means(image, i, j, 1.0, 5.0, sy)
    ratio = np.where(np.isfinite(shadow), shadow / np.maximum(echo, 1.0), 1.0)
    if ratio.size >= 5:
        ratio = median_filter(ratio, size=5, mode="nearest")
    return ratio


def trim_unshadowed_ends(
    image: np.ndarray,
    points_px: np.ndarray,
    spacing: tuple[float, float],
    max_ratio: float,
    split_mm: float = 1.0,
) -> np.ndarray:
    """Mask keeping the contour minus its unshadowed ends and side branches.

    A contour that runs from the bone onto a tissue layer at its edge keeps going
    where nothing is dark below: those end points are cut, up to the first point with a
    shadow (ratio at most ``max_ratio`` and at most 2.5 times the contour's median
    ratio, floor 0.2). When such an unshadowed run at least ``split_mm`` long lies
    *inside* the contour (a fascia bridging the bone and something dark further on,
    e.g. the shadow of a neighbouring bone), the contour is split there and only the
    part with the most shadowed points is kept. Shorter interior runs are left to the
    frame's checks (speckle, a dropout of the echo).
    """
    keep = np.ones(points_px.shape[0], bool)
    if points_px.shape[0] == 0:
        return keep
    ratio = point_shadow_ratio(image, points_px, spacing)
    # Relative to the contour's own shadow: a tissue layer next to a bone with a black
    # shadow stands out even if it is darker below than max_ratio.
    limit = min(max_ratio, max(0.2, 2.5 * float(np.median(ratio))))
    shadowed = ratio <= limit
    if not shadowed.any():
        return keep  # the whole frame will be judged (and rejected) as unshadowed
    first, last = np.flatnonzero(shadowed)[[0, -1]]
    # Inside the contour, only clearly unshadowed runs split it: well above the
    # contour's own typical ratio too (coarse images, where the 1-5 mm window is a
    # few pixels holding the echo's tail, have a high ratio all along the bone).
    inner = ratio <= max(limit, 1.6 * float(np.median(ratio)))
    inner[:first] = False
    inner[last + 1 :] = False
    idx = np.flatnonzero(inner)
    # Split between consecutive shadowed points separated by a long unshadowed run.
    gap_mm = np.diff(points_px[idx, 0]) * float(spacing[0])
    long_run = (np.diff(idx) > 1) & (gap_mm >= split_mm)
    parts = np.split(idx, np.flatnonzero(long_run) + 1)
    best = max(parts, key=len)
    keep[:] = False
    keep[best[0] : best[-1] + 1] = True
    return keep


def _slope(x: np.ndarray, z: np.ndarray) -> float:
    """Least-squares slope dz/dx (0 for fewer than two distinct x)."""
    if x.size < 2 or np.ptp(x) <= 0:
        return 0.0
    xc = x - x.mean()
    return float((xc * (z - z.mean())).sum() / (xc * xc).sum())


def trim_kinked_ends(
    points_px: np.ndarray,
    spacing: tuple[float, float],
    window_mm: float = 1.5,
    steep: float = 0.8,
    flat_fraction: float = 0.3,
    max_cut_mm: float = 6.0,
) -> np.ndarray:
    """Mask cutting an end that leaves a steep flank of the bone on a flat line.

    Seen from the probe a bone's cross-section is convex: going outwards from its top
    the contour gets deeper ever more steeply. A contour whose end instead turns
    abruptly from a steep flank (outward slope >= ``steep`` over ``window_mm``) to
    nearly flat (slope <= ``flat_fraction`` of that) has run onto a tissue layer that
    meets the bone there (a fascia at the level of the bone's flank, whose region
    below is partly shadowed by the widening bone, so the shadow test cannot tell).
    The flat part is cut when it is at most ``max_cut_mm`` long.
    """
    n = points_px.shape[0]
    keep = np.ones(n, bool)
    if n < 6:
        return keep
    x = points_px[:, 0] * float(spacing[0])
    z = points_px[:, 1] * float(spacing[1])
    # At least ~3 points per slope on coarse images (0.6 mm pixels: 1.5 mm is 2.5 px).
    step = float(np.median(np.diff(x))) if n > 1 else float(spacing[0])
    window_mm = max(window_mm, 3.0 * step)
    for side in (-1, 1):  # -1: left end (outward = decreasing x), 1: right end
        xo = side * x  # outward coordinate: increases towards this end
        end = xo.max()
        best_k, best_drop = -1, 0.0
        for k in np.flatnonzero((end - xo <= max_cut_mm) & (end - xo >= 0.5 * window_mm)):
            inner = (xo <= xo[k]) & (xo >= xo[k] - window_mm)
            outer = (xo >= xo[k]) & (xo <= xo[k] + window_mm)
            s_in, s_out = _slope(xo[inner], z[inner]), _slope(xo[outer], z[outer])
            if s_in >= steep and s_out <= flat_fraction * s_in and s_in - s_out > best_drop:
                best_k, best_drop = int(k), s_in - s_out
        if best_k >= 0:
            keep &= side * x <= side * x[best_k]
    return keep


def frame_verdict(ev: FrameEvidence, params: RejectionParams) -> tuple[float, str]:
    """Confidence in [0, 1] and the rejection reason ("" when plausible)."""
    p = params
    if ev.n_points == 0:
        return 0.0, "no bone found"
    c_len = float(np.clip(ev.length_mm / (3 * p.min_length_mm), 0, 1))
    c_con = float(np.clip(ev.contrast / (3 * p.min_contrast), 0, 1))
    c_sh = float(np.clip(1 - ev.shadow_ratio / (1.5 * p.max_shadow_ratio), 0, 1))
    conf = (c_len * c_con * c_sh) ** (1 / 3)
    if ev.n_points < p.min_points or ev.length_mm < p.min_length_mm:
        return conf, f"contour too short ({ev.length_mm:.1f} mm)"
    if ev.contrast < p.min_contrast:
        return conf, f"low contrast (Dif {ev.contrast:.2f})"
    if ev.shadow_ratio > p.max_shadow_ratio:
        return conf, f"no acoustic shadow (shadow/echo {ev.shadow_ratio:.2f})"
    if conf < p.min_confidence:
        return conf, f"low confidence ({conf:.2f})"
    return conf, ""


def neighbour_deviation(
    contours: dict[int, np.ndarray],
    order: list[int],
    sy: float,
    window: int,
    margin_px: float = 0.0,
) -> tuple[dict[int, np.ndarray], dict[int, float]]:
    """Per frame and point, the depth difference (mm) from its neighbouring frames.

    For each point of frame ``f``, the neighbours' depth at the same column
    (interpolated along their contours, and held constant up to ``margin_px`` beyond
    their ends) is collected from the ``window`` accepted frames on each side that
    cover that column; the reference is their median (so one bad neighbour does not
    matter). The depth is predicted at the frame by a Theil-Sen line through the
    neighbours' depths against their position in the sequence, so a bone that
    deepens steadily along the sweep is no jump, and one bad neighbour does not
    matter. Points that fewer than two neighbours cover get ``inf`` (unsupported:
    nothing near them in the neighbouring frames); frames with fewer than two
    neighbours get NaN (unknown).

    Returns
    -------
    deviation : dict frame -> ndarray (K,)
        Signed depth differences in mm.
    scatter : dict frame -> float
        Median absolute residual (mm) of the neighbours about their own line: how
        much depth varies between frames in this part of the sweep.

    Parameters
    ----------
    contours : dict frame -> ndarray (K, 2)
        Contours ``(i, j)`` ordered by increasing ``i``.
    order : list of int
        The accepted frames in acquisition order.
    sy : float
        mm per row.
    window : int
    margin_px : float
        Columns a contour may extend beyond its neighbours' ends and still be compared.
    """
    out: dict[int, np.ndarray] = {}
    scatter: dict[int, float] = {}
    for pos, f in enumerate(order):
        a = contours[f]
        neigh = order[max(0, pos - window) : pos] + order[pos + 1 : pos + 1 + window]
        ref = np.full((len(neigh), a.shape[0]), np.nan)
        for r, g in enumerate(neigh):
            b = contours[g]
            inside = (a[:, 0] >= b[0, 0] - margin_px) & (a[:, 0] <= b[-1, 0] + margin_px)
            ref[r, inside] = np.interp(a[inside, 0], b[:, 0], b[:, 1])
        dev = np.full(a.shape[0], np.nan if len(neigh) < 2 else np.inf)
        ok = np.isfinite(ref).sum(axis=0) >= 2
        if ok.any():
            pred, spread = _theil_sen_at_zero(ref[:, ok], _offsets(order, pos, neigh))
            dev[ok] = (a[ok, 1] - pred) * sy
            scatter[f] = float(np.median(spread)) * sy
        out[f] = dev
    return out, scatter


def _nanmedian0(a: np.ndarray) -> np.ndarray:
    """Median over axis 0 ignoring NaN; every column needs one finite value.

    (np.nanmedian goes through masked arrays for small inputs and is ~10x slower.)
    """
    srt = np.sort(a, axis=0)  # NaN sorts last
    n = np.isfinite(a).sum(axis=0)
    cols = np.arange(a.shape[1])
    lo = srt[np.maximum((n - 1) // 2, 0), cols]
    hi = srt[np.maximum(n // 2, 0), cols]
    return 0.5 * (lo + hi)


def _offsets(order: list[int], pos: int, neigh: list[int]) -> np.ndarray:
    """Positions of the neighbours in the accepted sequence relative to ``pos``."""
    where = {f: p for p, f in enumerate(order)}
    return np.array([where[g] - pos for g in neigh], dtype=float)


def _theil_sen_at_zero(depth: np.ndarray, x: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust line through ``depth[r, k]`` at positions ``x[r]``, evaluated at 0, per column ``k``.

    Slope: median of the pairwise slopes; intercept: median of ``depth - slope x``;
    spread: median absolute residual about the line.
    NaN entries (neighbours not covering a column) are ignored; every column must have
    at least two finite entries.
    """
    r1, r2 = np.triu_indices(x.size, 1)
    slopes = (depth[r2] - depth[r1]) / (x[r2] - x[r1])[:, None]
    slope = _nanmedian0(slopes)
    intercept = _nanmedian0(depth - slope[None, :] * x[:, None])
    spread = _nanmedian0(np.abs(depth - intercept - slope[None, :] * x[:, None]))
    return intercept, spread

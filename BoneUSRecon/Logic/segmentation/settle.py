"""Settle: a contour running on a layer just over the bone is moved down onto the bone.

On hard simulated sweeps 16 % of the kept points lay more than 0.5 mm from the bone,
and 68 % of those lay 0.5-3 mm *over* it (2 % under it): a fascia converging on the
bone's shoulder, or a layer or a run of speckle capping a faint top, that the optimal
path of :mod:`.candidates` follows because its echo is brighter. The evidence cannot
tell them apart there: its shadow windows start ``shadow_gap_mm`` (1.5 mm) under a line
so that an echo's blur and the reverberation under it do not count against the bone,
and a layer 1 mm over the bone then has the bone's own shadow in its windows.

What tells them apart is where the shadow *starts*. Along the beam the bone is where
the tissue ends and the shadow begins: the **onset** ``log(above / below)`` of the mean
``work / tissue`` in short windows above and below a pixel (``window_mm``; the per-depth
tissue level divided out, so gain, TGC and attenuation do not tilt it; the window
above capped at the tissue level, so an echo in it does not pass for the tissue the
sound crossed) is high at the bone's surface. Under a layer over the bone lie tissue
and then the bone's echo, so the layer's own onset is low and the bone's, 0.5-3 mm
under it, high. Inside the shadow (a far cortex, a reverberation copy) both windows
are in shadow, so nothing there wins.

Per candidate point the onset is read at every depth from just over the point to
``depth_mm`` under it, in robust z units of this frame's own onset spread (1.4826 MAD
over the usable field: what speckle and texture alone produce), averaged along the
contour over ``run_mm`` (a layer runs for mm; one grain of speckle does not). A point
moves, onto the echo peak just above the best deeper onset (full-resolution column
profile), where that onset beats its own (within ``own_mm``: a bright echo's onset lies
up to ~0.5 mm under its peak) by ``gain_z``, and the picture is that of a layer over a
bone (each test averaged along the contour alike):

* the point's line is thin: tissue (no brighter than the tissue level at its depth)
  comes within ``thin_mm`` under it (a fascia is thin). The L14 forearm's cortex is a band ~1 mm thick
  (1-1.5 mm along the beam on its flanks) over a bone that passes sound; its top is the
  surface, and without this test points of its flanks went 2-3 mm into the bone;
* tissue lies between the two lines (``gap_ratio``), and the new point is an echo,
  brighter than the tissue level (``echo_ratio``);
* the bone's shadow is under the new point (:mod:`.evidence`'s shadow z-score at least
  ``shadow_z``): without it a line under a layer is just another line.

Every level is a ratio of the same frame's grey levels at nearby places, in units of
that frame's spread or of its per-depth tissue level: no grey level and no level fitted
to one data source. Applied per frame to each candidate before its flanks are followed
(a settled end on the bone's flank is followed down it, one on the layer was not), so
a live reconstruction gets the same contours as an offline one. Vectorised over the
points of all of a frame's candidates at once. Figures: ``Testing/benchmarks/README.md``
("Settle").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from scipy.ndimage import median_filter, uniform_filter1d

from BoneUSRecon.Logic.segmentation.detection import sample_bilinear
from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps
from BoneUSRecon.Logic.segmentation.features import median1d, mm_to_px
from BoneUSRecon.Logic.segmentation.params import SettleParams

__all__ = ["onset_z", "settle_points", "settle_candidates"]

_EPS = 1e-3  # guards log(0) in black regions (no decision rests on it)
_BAD = -1e3  # onset of a depth outside the image: never the best


def onset_z(ev: EvidenceMaps, window_mm: tuple[float, float]) -> np.ndarray:
    """Robust z-score of the shadow onset along the beam per working pixel, shape (h, w).

    ``log(above / below)``: the mean of ``work / tissue`` over rows ``window_mm`` (from,
    to) above the pixel against that below it, centred on its median over the usable
    columns and scaled by 1.4826 x the median absolute deviation. Rows whose windows
    leave the image and unusable columns are 0.
    """
    a = mm_to_px(window_mm[0], ev.dy)
    b = max(a + 1, mm_to_px(window_mm[1], ev.dy))
    w = ev.work / ev.tissue[:, None]
    h = w.shape[0]
    cs = np.zeros((h + 1, w.shape[1]), np.float32)
    np.cumsum(w, axis=0, out=cs[1:])
    r = np.arange(h)
    above = (cs[np.clip(r - a + 1, 0, h)] - cs[np.clip(r - b, 0, h)]) / (b - a + 1)
    below = (cs[np.clip(r + b + 1, 0, h)] - cs[np.clip(r + a, 0, h)]) / (b - a + 1)
    # Above is tissue at most: an echo in the window above (a pixel just under a bright
    # line) must not pass for the tissue the sound crossed, or any bright line would
    # have an onset under it, shadow or not.
    np.minimum(above, 1.0, out=above)
    o = np.log((above + _EPS) / (below + _EPS))
    inside = (r - b >= 0) & (r + b < h)
    v = o[inside][:, ev.usable][::2, ::2].ravel()  # every 4th pixel is plenty for a median
    if v.size < 10:
        return np.zeros_like(o)
    med = median1d(v)
    o -= med
    o *= 1.0 / max(1.4826 * median1d(np.abs(v - med)), 1e-3)
    o[~inside] = 0.0
    o[:, ~ev.usable] = 0.0
    return o


def settle_points(
    ev: EvidenceMaps,
    contours_px: Sequence[np.ndarray],
    spacing: tuple[float, float],
    params: SettleParams = SettleParams(),  # noqa: B008 (frozen dataclass)
) -> list[np.ndarray]:
    """Each contour with the points that run on a layer over the bone moved onto it.

    Parameters
    ----------
    ev : EvidenceMaps
        The frame's evidence (working image, tissue level, usable columns, pixel sizes).
    contours_px : sequence of ndarray, each (K, 2)
        ``(i, j)`` pixels, ordered along the contour.
    spacing : (sx, sy)
        mm per column and per row.
    params : SettleParams

    Returns
    -------
    list of ndarray
        The contours; one with no point moved is the same object.
    """
    p = params
    out = list(contours_px)
    use = [n for n, c in enumerate(out) if len(c) >= 3]
    if not p.enabled or not use:
        return out
    oz = onset_z(ev, p.window_mm)
    h, w = oz.shape
    pts = np.concatenate([np.asarray(out[n], float) for n in use])
    sizes = [len(out[n]) for n in use]
    col = np.clip(np.rint((pts[:, 0] + 0.5) / ev.fx - 0.5).astype(np.intp), 0, w - 1)
    r0 = np.rint((pts[:, 1] + 0.5) / ev.fy - 0.5).astype(np.intp)
    own = mm_to_px(p.own_mm, ev.dy, minimum=0)
    d = np.arange(-1, mm_to_px(p.depth_mm, ev.dy) + 1)
    rr = r0[:, None] + d
    g = np.where((rr >= 0) & (rr < h), oz[np.clip(rr, 0, h - 1), col[:, None]], _BAD)
    # Averaged along each contour over run_mm (its own points: the filter runs per contour).
    sx = float(spacing[0])
    cut = np.cumsum([0, *sizes])
    spans = []  # (first, end, points per run_mm) per contour
    for lo, hi in zip(cut[:-1], cut[1:], strict=True):
        step = median1d(np.hypot(*np.diff(pts[lo:hi], axis=0).T)) * sx
        spans.append((lo, hi, max(1, int(round(p.run_mm / max(step, 1e-6))))))
    for lo, hi, m in spans:
        if m > 1:
            g[lo:hi] = uniform_filter1d(g[lo:hi], m, axis=0, mode="nearest")
    n_own = own + 2  # offsets -1 .. own
    mine = g[:, :n_own].max(axis=1)
    best = g[:, n_own:].argmax(axis=1) + n_own
    gain = g[np.arange(g.shape[0]), best] - mine
    # And the bone's shadow must be there: under the new point the region is darker than
    # the tissue beside it at the same depth (:mod:`.evidence`'s shadow z-score, averaged
    # alike). Without it (a phantom bone that passes sound) a line under a layer is just
    # another line, and the onset alone would favour whichever lies over a darker patch.
    rb = np.clip(r0 + d[best], 0, h - 1)
    sz = ev.shadow_z[rb, col].astype(float)
    for lo, hi, m in spans:
        if m > 1:
            sz[lo:hi] = uniform_filter1d(sz[lo:hi], m, mode="nearest")
    # The new point: the echo peak just above the onset, on the full-resolution column
    # profile (``colmean``: the working column's mean at every image row).
    py = ev.dy / ev.fy  # mm per image row
    onset = (r0 + d[best] + 0.5) * ev.fy - 0.5
    lo = np.rint(onset - 0.6 / py).astype(np.intp)
    rows = np.clip(
        lo[:, None] + np.arange(max(2, int(round(0.8 / py)))), 0, ev.colmean.shape[0] - 1
    )
    peak = rows[np.arange(rows.shape[0]), ev.colmean[rows, col[:, None]].argmax(axis=1)]
    # And tissue must lie between the two lines: a layer and the bone have soft tissue
    # between them (no brighter than the tissue level at its depth: the frame's own
    # per-depth level); a thick echo (a cortex band, the L14 forearm's ~1 mm) is bright
    # from its top, the surface, down to where its shadow starts. Judged on the working
    # rows strictly between the point and the new echo's peak, averaged along the contour.
    rel = ev.work / ev.tissue[:, None]
    r_new = np.floor((peak + 0.5) / ev.fy - 0.5).astype(np.intp)
    between = (rr > r0[:, None]) & (rr < r_new[:, None]) & (rr < h)
    column = rel[np.clip(rr, 0, h - 1), col[:, None]]
    trough = np.where(between, column, 10.0).min(axis=1)
    # The line the point is on must be thin (the tissue comes within ``thin_mm`` under it):
    # a thick echo band's top is the bone's surface, whatever lies under the band.
    dark = (column <= p.gap_ratio) & between
    thin = dark[:, : mm_to_px(p.thin_mm, ev.dy, minimum=0) + 2].any(axis=1).astype(float)
    echo = rel[np.clip(r_new, 0, h - 1), col]
    for lo, hi, m in spans:
        if m > 1:
            trough[lo:hi] = median_filter(trough[lo:hi], m, mode="nearest")
            echo[lo:hi] = median_filter(echo[lo:hi], m, mode="nearest")
            thin[lo:hi] = uniform_filter1d(thin[lo:hi], m, mode="nearest")
    move = (
        (gain >= p.gain_z)
        & (sz >= p.shadow_z)
        & (trough <= p.gap_ratio)
        & (echo > p.echo_ratio)
        & (thin >= 0.5)
    )
    if not move.any():
        return out
    new = pts.copy()
    new[move, 1] = peak[move]
    for k, n in enumerate(use):
        if move[cut[k] : cut[k + 1]].any():
            out[n] = new[cut[k] : cut[k + 1]]
    return out


def settle_candidates(
    image: np.ndarray,
    ev: EvidenceMaps,
    candidates: Sequence,
    spacing: tuple[float, float],
    params: SettleParams = SettleParams(),  # noqa: B008 (frozen dataclass)
) -> list:
    """:func:`settle_points` on the candidates that may be chosen (reverberation copies
    are never chosen and stay as they are); a candidate whose points moved gets its grey
    values re-sampled; strengths are unchanged."""
    cands = list(candidates)
    which = [n for n, c in enumerate(cands) if not c.reverberation]
    if not params.enabled or not which:
        return cands
    new = settle_points(ev, [cands[n].points_px for n in which], spacing, params)
    for n, pts in zip(which, new, strict=True):
        if pts is not cands[n].points_px:
            cands[n] = dataclasses.replace(
                cands[n], points_px=pts, intensity=sample_bilinear(np.asarray(image), pts)
            )
    return cands

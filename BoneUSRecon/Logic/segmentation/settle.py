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

from collections.abc import Sequence

import numpy as np

from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps
from BoneUSRecon.Logic.segmentation.features import median1d, mm_to_px
from BoneUSRecon.Logic.segmentation.params import SettleParams
from BoneUSRecon.Logic.segmentation.sampling import with_points

__all__ = ["onset_z", "settle_points", "settle_candidates"]

_EPS = 1e-3  # guards log(0) in black regions (no decision rests on it)
_BAD = -1e3  # onset of a depth outside the image: never the best


def onset_z(
    ev: EvidenceMaps,
    window_mm: tuple[float, float],
    rows: tuple[int, int] | None = None,
    rel: np.ndarray | None = None,
    cols: np.ndarray | None = None,
) -> np.ndarray:
    """Robust z-score of the shadow onset along the beam per working pixel.

    ``log(above / below)``: the mean of ``work / tissue`` over rows ``window_mm`` (from,
    to) above the pixel against that below it (above capped at 1, the tissue level),
    centred on its median over the usable field and scaled by 1.4826 x its median
    absolute deviation (both from every third row and usable column). Rows whose
    windows leave the image and unusable columns are 0.

    Parameters
    ----------
    ev : EvidenceMaps
    window_mm : (from, to)
    rows : (first, end), optional
        Only these working rows (the z-scale still comes from the whole field).
    rel : ndarray, optional
        ``ev.work / ev.tissue[:, None]`` when already computed.
    cols : ndarray of int, optional
        Only these working columns, in this order (the z-scale still comes from the
        whole field).

    Returns
    -------
    ndarray, shape (end - first, w) or (end - first, len(cols))
    """
    a = mm_to_px(window_mm[0], ev.dy)
    b = max(a + 1, mm_to_px(window_mm[1], ev.dy))
    w = ev.work / ev.tissue[:, None] if rel is None else rel
    h = w.shape[0]
    # The sums down the columns read only: every third usable one (the scale's sample)
    # and those asked for (each column's sum in the same order as over the whole image).
    scale_cols = np.flatnonzero(ev.usable)[::3]
    if cols is None:
        need, c_out, c_scale = slice(None), slice(None), scale_cols
    else:
        seen = np.zeros(w.shape[1], bool)
        seen[scale_cols] = True
        seen[cols] = True
        need = np.flatnonzero(seen)
        at = np.cumsum(seen) - 1
        c_out, c_scale = at[cols], at[scale_cols]
    sub = w[:, need]
    cs = np.zeros((h + 1, sub.shape[1]), np.float32)
    np.cumsum(sub, axis=0, out=cs[1:])

    def onset(r: np.ndarray, c: slice | np.ndarray) -> np.ndarray:
        above = cs[np.clip(r - a + 1, 0, h)][:, c] - cs[np.clip(r - b, 0, h)][:, c]
        below = cs[np.clip(r + b + 1, 0, h)][:, c] - cs[np.clip(r + a, 0, h)][:, c]
        above *= 1.0 / (b - a + 1)
        below *= 1.0 / (b - a + 1)
        # Above is tissue at most: an echo in the window above (a pixel just under a
        # bright line) must not pass for the tissue the sound crossed, or any bright
        # line would have an onset under it, shadow or not.
        np.minimum(above, 1.0, out=above)
        above += _EPS
        below += _EPS
        return np.log(above / below)

    lo, hi = (0, h) if rows is None else (max(0, rows[0]), min(h, rows[1]))
    r = np.arange(lo, hi)
    usable = ev.usable if cols is None else ev.usable[cols]
    out = onset(r, c_out) if hi > lo else np.zeros((0, usable.size), np.float32)
    sample = np.arange(b, h - b, 3)
    v = onset(sample, c_scale).ravel() if sample.size else sample
    if v.size < 10:
        return np.zeros_like(out)
    med = median1d(v)
    out -= med
    out *= 1.0 / max(1.4826 * median1d(np.abs(v - med)), 1e-3)
    out[(r - b < 0) | (r + b >= h)] = 0.0
    out[:, ~usable] = 0.0
    return out


def _run_mean(a: np.ndarray, first: np.ndarray, end: np.ndarray, half: np.ndarray) -> np.ndarray:
    """Mean of ``a`` (n, ...) over ``+-half[i]`` points around each point ``i``, the window
    clipped to its own contour ``[first[i], end[i])``: all contours in one set of calls."""
    cs = np.zeros((a.shape[0] + 1,) + a.shape[1:])
    np.cumsum(a, axis=0, out=cs[1:])
    i = np.arange(a.shape[0])
    lo = np.maximum(i - half, first)
    hi = np.minimum(i + half + 1, end)
    n = (hi - lo).reshape((-1,) + (1,) * (a.ndim - 1))
    return (cs[hi] - cs[lo]) / n


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
    h, w = ev.work.shape
    pts = np.concatenate([np.asarray(out[n], float) for n in use])
    sizes = np.array([len(out[n]) for n in use])
    col = np.clip(np.rint((pts[:, 0] + 0.5) / ev.fx - 0.5).astype(np.intp), 0, w - 1)
    r0 = np.rint((pts[:, 1] + 0.5) / ev.fy - 0.5).astype(np.intp)
    d = np.arange(-1, mm_to_px(p.depth_mm, ev.dy) + 1)
    rr = r0[:, None] + d
    inside = (rr >= 0) & (rr < h)
    rc = np.clip(rr, 0, h - 1)
    # The onset only on the rows and columns the points reach (its scale from the
    # whole field).
    rel = ev.work / ev.tissue[:, None]
    top, bottom = int(rc.min()), int(rc.max()) + 1
    seen = np.zeros(w, bool)
    seen[col] = True
    oz = onset_z(ev, p.window_mm, (top, bottom), rel, np.flatnonzero(seen))
    g = np.where(inside, oz[rc - top, (np.cumsum(seen) - 1)[col][:, None]], _BAD)
    # Every test is averaged along its own contour over run_mm (windows clipped to the
    # contour: all contours in one set of calls).
    cut = np.cumsum(np.r_[0, sizes])
    first = np.repeat(cut[:-1], sizes)
    end = np.repeat(cut[1:], sizes)
    seg = np.hypot(*np.diff(pts, axis=0).T) * float(spacing[0])
    step = np.array([median1d(seg[a : b - 1]) for a, b in zip(cut[:-1], cut[1:], strict=True)])
    half = np.repeat(
        np.maximum(0, np.rint(p.run_mm / np.maximum(step, 1e-6)).astype(int) // 2), sizes
    )
    g = _run_mean(g, first, end, half)
    # A point's own onset: the best within own_mm under it *across the line*, so along
    # the beam own_mm / cos(slope) (on a 55-degree flank an echo 0.3 mm thick spans
    # 0.5 mm of the beam, and its shadow starts under that).
    cos = np.abs(np.gradient(pts[:, 0] * float(spacing[0])))
    slope_len = np.hypot(cos, np.gradient(pts[:, 1] * float(spacing[1])))
    cos = _run_mean(cos, first, end, half) / np.maximum(
        _run_mean(slope_len, first, end, half), 1e-9
    )
    own = np.rint(p.own_mm / np.maximum(cos, 0.3) / ev.dy).astype(np.intp)
    is_own = d[None, :] <= own[:, None]
    mine = np.where(is_own, g, _BAD).max(axis=1)
    best = np.where(is_own, _BAD, g).argmax(axis=1)
    gain = g[np.arange(g.shape[0]), best] - mine
    if not ((gain >= p.gain_z) & (mine <= p.own_max_z)).any():
        return out  # most frames: nothing to move, the other tests not needed
    # The new point: the echo peak just above the onset, on the full-resolution column
    # profile (``colmean``: the working column's mean at every image row).
    py = ev.dy / ev.fy  # mm per image row
    onset = (r0 + d[best] + 0.5) * ev.fy - 0.5
    lo = np.rint(onset - 0.6 / py).astype(np.intp)
    rows = np.clip(
        lo[:, None] + np.arange(max(2, int(round(0.8 / py)))), 0, ev.colmean.shape[0] - 1
    )
    peak = rows[np.arange(rows.shape[0]), ev.colmean[rows, col[:, None]].argmax(axis=1)]
    r_new = np.clip(np.floor((peak + 0.5) / ev.fy - 0.5).astype(np.intp), 0, h - 1)
    # The bone's shadow must be there: under the new point the region is darker than
    # the tissue beside it at the same depth (:mod:`.evidence`'s shadow z-score).
    # Without it (a phantom bone that passes sound) a line under a layer is just
    # another line, and the onset alone would favour whichever lies over a darker patch.
    # Tissue must lie between the two lines (a layer and the bone have soft tissue
    # between them, no brighter than the tissue level at its depth: the frame's own
    # per-depth level), on the working rows strictly between the point and the new echo;
    # the new point is an echo (brighter than that level); the line the point is on is
    # thin (tissue comes within ``thin_mm`` under it): a thick echo band (a cortex band,
    # the L14 forearm's ~1 mm) is bright from its top, the surface, down to where its
    # shadow starts.
    column = rel[rc, col[:, None]]
    between = (rr > r0[:, None]) & (rr < r_new[:, None]) & inside
    tests = np.column_stack(
        [
            ev.shadow_z[r_new, col],
            np.minimum(np.where(between, column, 2.0).min(axis=1), 2.0),
            rel[r_new, col],
            ((column <= p.gap_ratio) & between)[:, : mm_to_px(p.thin_mm, ev.dy, minimum=0) + 2].any(
                axis=1
            ),
        ]
    )
    sz, trough, echo, thin = _run_mean(tests, first, end, half).T
    move = (
        (gain >= p.gain_z)
        & (mine <= p.own_max_z)
        & (sz >= p.shadow_z)
        & (trough <= p.gap_ratio)
        & (echo > p.echo_ratio)
        & (thin >= 0.5)
        & (cos >= np.cos(np.radians(p.max_slope_deg)))
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
    return with_points(image, cands, which, new)

"""Flanks: follow a candidate contour down the bone's flanks, where one depth per column fails.

The optimal path of :mod:`.candidates` has one depth per working column, so a flank of
70 degrees gets a column every ~0.9 mm of its length, the echo there is weak (specular
reflection goes away from the probe: ~15 % of the top's amplitude at 60 degrees), its
score is measured with vertical windows that a steep line crosses obliquely, and the
path's "no bone" state, a fascia crossing the flank or a wiggle the convexity cut takes
for a turn end the contour early: on unseen simulated sweeps 97 % of the gold points the
surface missed lay on flanks steeper than 45 degrees, with no contour point near them.

Here each end of a candidate that already descends outward (``min_start_deg``) is
followed along the bone, step by step in arc length (``step_mm``), not column by column:

1. **Start and direction.** The trace starts ``retreat_mm`` inside the end, or farther
   back (by up to ``restart_mm``) while the contour there is still steeper than
   ``restart_deg``: where one depth per column samples the flank poorly (and the path's
   last columns drift off it) the trace takes over. The outward direction and the
   curvature come from ``fit_mm`` of contour inside the start (three points, second
   order). A bone's cross-section is convex seen from the probe, so the extrapolated arc
   turns only downward (curvature >= 0, at most ``max_curvature``) and never past
   ``max_deg`` (a beam from above cannot see under the bone).
2. **Ridge across the flank.** Across the arc a band of +-``band_mm`` is sampled on the
   working image (block-averaged, speckle reduced). A sample's echo is its log ratio to
   the mean of the tissue just outward of it (``outside_mm``, on the side of the flank
   away from the bone): the echo measured *across* the flank whatever its slope. It
   counts up to double as the bone's shadow lies under the sample along the beam
   (:mod:`.evidence`'s shadow z-score over ``shadow_z``: under a flank lies the bone;
   beside the shadow's edge under the bone's widest point lies tissue, which gains
   nothing; with no shadow, as on the L14 forearm, the echo alone carries the trace).
   Averaged along the trace over ``run_mm``, the ridge is the best path through the band
   moving at most one sample per step, and only inward (a Viterbi: a line needs no jump;
   a convex flank only steepens, a layer running off it is flatter; a confined path finds
   far fewer chance alignments of speckle than a free maximum).
3. **Stop rule from this frame's own speckle.** The same search (same band width, same
   averaging, same confined path) runs through a null band ``null_mm`` outward, in the
   tissue beside the flank; pooled over the frame's traces, its median and robust
   spread (1.4826 MAD) say what speckle alone produces with this probe, gain and depth.
   The trace continues while its ridge exceeds that median by ``stop_z`` spreads and
   ends at its last such step before ``gap_mm`` under it (a short dropout is bridged).
   Both sides of the comparison are ratios of grey levels of the same frame at nearby
   places, searched the same way, so the rule holds on any recording (a bright L14 echo
   2.7x its tissue and the cadaver's 1.35x alike) and the search itself cannot make
   speckle look like a ridge: no grey level, no level fitted to one data source.
4. **Points.** Each step's ridge is refined on the full-resolution image along the
   normal (parabolic peak of a profile averaged over three parallel lines, median of
   three along the trace). The trace replaces the contour beyond its start where it
   reaches at least as far (arc length) as the contour did; otherwise the contour stays.

What is never extended: reverberation copies (never chosen); ends that are flat or
rise outward (a fascia or a layer at the bone's level is flat; the far cortex seen
from inside the shadow is concave); a trace whose ridge is speckle-level from its
start. The candidates' strengths are unchanged, so the sweep-level choice weighs the
same evidence; applied per frame in :func:`.candidates.frame_candidates`, a live
reconstruction gets the same contours as an offline one.

Vectorised: all traces of a frame are sampled together, the evidence, the null and the
stop rule are operations on (trace, step, offset) arrays; Python loops only over the
steps of the path search (a few ufunc calls each) and its backtrack (on floats), and
over the few candidates when their points are put back together. Figures (coverage,
accuracy, speed) are in ``Testing/benchmarks/README.md`` ("Flanks").
"""

from __future__ import annotations

import dataclasses
from collections.abc import Generator, Sequence

import numpy as np

from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps
from BoneUSRecon.Logic.segmentation.features import median1d, mm_to_px
from BoneUSRecon.Logic.segmentation.params import FlankParams, RimParams
from BoneUSRecon.Logic.segmentation.rim import RadiusPaths, follow_rims_steps, run_rims
from BoneUSRecon.Logic.segmentation.sampling import (
    bilinear_at,
    median3,
    refine_across,
    with_points,
)

__all__ = ["extend_flanks", "extend_candidates", "extend_candidates_steps"]

_EPS = 1e-3  # grey/255: guards log(0) in black regions (no decision rests on it)
_BAD = -1e3  # evidence of a sample outside the usable image: any window holding one is
# under every level (the evidence itself is a log ratio of a few units at most)


def _ends(
    contours_mm: Sequence[np.ndarray], p: FlankParams
) -> tuple[np.ndarray, np.ndarray, dict[int, np.ndarray]]:
    """The extendable ends: ``(T, 3)`` contour, side, start arc length; ``(T, 5)`` geometry;
    the arc length (mm) at each point of every contour that has an end.

    Geometry per end: start point ``x, z`` (mm), outward direction ``phi`` (radians below
    the lateral axis, outward), curvature ``kappa`` (1/mm, >= 0), ``side`` (-1: the
    first point's end, towards smaller columns; +1: the last point's end). The start is
    ``retreat_mm`` inside the end, or farther back in steps of ``fit_mm / 2`` (up to
    ``restart_mm``) while the contour there is still steeper than ``restart_deg``: where
    one depth per column samples a flank poorly the trace takes over. All contours at
    once: their arc lengths are laid end to end (1 mm apart) and interpolated together.
    """
    use = [n for n, x in enumerate(contours_mm) if x.shape[0] >= 4]
    if not use:
        return np.empty((0, 3)), np.empty((0, 5)), {}
    xs = [contours_mm[n] for n in use]
    sizes = np.array([x.shape[0] for x in xs])
    pts = np.concatenate(xs)
    seg = np.hypot(*np.diff(pts, axis=0).T)
    first = np.cumsum(sizes)[:-1]  # index of each later contour's first point
    seg[first - 1] = 1.0  # the jump between contours: 1 mm of arc, never queried
    s = np.concatenate(([0.0], np.cumsum(seg)))
    s0 = s[np.r_[0, first]]
    length = s[np.cumsum(sizes) - 1] - s0
    h = 0.5 * p.fit_mm
    n_j = int(round(p.restart_mm / h)) + 1  # candidate starts
    dist = p.retreat_mm + h * np.arange(n_j + 2)  # from the end: starts and 2 points inward
    rel = np.concatenate(
        [np.broadcast_to(dist, (length.size, dist.size)), length[:, None] - dist], axis=1
    )
    q = (s0[:, None] + np.clip(rel, 0.0, length[:, None])).ravel()
    qx = np.interp(q, s, pts[:, 0]).reshape(-1, 2, n_j + 2)  # (contour, end, point)
    qz = np.interp(q, s, pts[:, 1]).reshape(-1, 2, n_j + 2)
    side = np.array([-1.0, 1.0])[:, None]
    a, b, c = slice(0, n_j), slice(1, n_j + 1), slice(2, n_j + 2)
    tx = side * (3 * qx[..., a] - 4 * qx[..., b] + qx[..., c])  # outward tangent, 2nd order
    tz = 3 * qz[..., a] - 4 * qz[..., b] + qz[..., c]
    phi = np.arctan2(tz, tx)  # (contour, end, start)
    inner = np.arctan2(qz[..., b] - qz[..., c], side * (qx[..., b] - qx[..., c]))
    outer = np.arctan2(qz[..., a] - qz[..., b], side * (qx[..., a] - qx[..., b]))
    # The start: the first candidate (from the end) not steeper than restart_deg, and
    # within the contour's own half (the two ends' points apart); -1 if none is.
    n_fit = (dist[2:] <= 0.5 * length[:, None]).sum(axis=1)
    calm = phi < np.radians(p.restart_deg)
    j = np.where(calm.any(axis=-1), calm.argmax(axis=-1), n_j - 1)
    j = np.minimum(j, (n_fit - 1)[:, None])
    jj = np.maximum(j, 0)[..., None]
    phi = np.take_along_axis(phi, jj, axis=-1)[..., 0]
    bend = np.take_along_axis(outer - inner, jj, axis=-1)[..., 0]
    kappa = np.clip(bend / h, 0.0, p.max_curvature)
    ok = (j >= 0) & (phi >= np.radians(p.min_start_deg)) & (phi < np.radians(p.max_deg))
    cc, e = np.nonzero(ok)
    jc = j[cc, e]
    start = np.where(e == 0, dist[jc], length[cc] - dist[jc])
    sides = side[e, 0]
    ends = np.column_stack([np.asarray(use)[cc], sides, start])
    geo = np.column_stack([qx[cc, e, jc], qz[cc, e, jc], phi[cc, e], kappa[cc, e], sides])
    bounds = np.r_[0, np.cumsum(sizes)]
    arc = {use[n]: s[bounds[n] : bounds[n + 1]] - s0[n] for n in set(cc.tolist())}
    return ends, geo, arc


def extend_flanks(
    image: np.ndarray,
    ev: EvidenceMaps,
    contours_px: Sequence[np.ndarray],
    spacing: tuple[float, float],
    params: FlankParams = FlankParams(),  # noqa: B008 (frozen dataclass)
) -> list[np.ndarray]:
    """Each contour continued down its flanks while the echo holds (see the module docstring).

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W)
        The frame (for the full-resolution refinement).
    ev : EvidenceMaps
        The frame's evidence (its working image, usable columns and pixel sizes).
    contours_px : sequence of ndarray, each (K, 2)
        ``(i, j)`` pixels, ordered along the contour by increasing ``i``.
    spacing : (sx, sy)
        mm per column and per row.
    params : FlankParams

    Returns
    -------
    list of ndarray
        The contours, each with its flanks extended where a trace held (the others
        unchanged, the same objects).
    """
    p = params
    out = list(contours_px)
    if not p.enabled or not out:
        return out
    sx, sy = float(spacing[0]), float(spacing[1])
    scale = np.array([sx, sy])
    mm = [np.asarray(c, float) * scale for c in out]
    ends, geo, arc = _ends(mm, p)
    if not ends.shape[0]:
        return out
    x0, z0, phi0, kappa, side = (c[:, None] for c in geo.T)
    ds = p.step_mm
    n_step = max(2, int(np.ceil(p.max_mm / ds)))
    phi_max = np.radians(p.max_deg)
    # Centre line of the extrapolated arc (mid-point rule) and its outward normal.
    k = ds * np.arange(0.5, n_step + 1)  # arc length at the mid-steps, then one more
    phi = np.minimum(phi0 + kappa * k, phi_max)
    cos, sin = np.cos(phi), np.sin(phi)
    cx = np.cumsum(cos[:, :-1], axis=1)
    cx *= side * ds
    cx += x0
    cz = np.cumsum(sin[:, :-1], axis=1)
    cz *= ds
    cz += z0
    # Normals at the steps (between the mid-steps' directions: their mean, renormalised
    # implicitly by the small turn per step).
    nx = side * 0.5 * (sin[:, :-1] + sin[:, 1:])  # outward: away from the bone
    nz = -0.5 * (cos[:, :-1] + cos[:, 1:])
    # Offsets across the arc: the band, then outward far enough for the null band and
    # the outside windows of every sample of both; inward for the shadow window.
    do = p.offset_mm
    m = mm_to_px(p.band_mm, do)
    oa, ob = mm_to_px(p.outside_mm[0], do), mm_to_px(p.outside_mm[1], do)
    nc = mm_to_px(p.null_mm, do)
    off = do * np.arange(-m, nc + m + ob + 1)
    # Working-image coordinates ((mm / spacing + 0.5) / block - 0.5); samples outside
    # the image or in columns without contact are invalid.
    fx, fy = sx * ev.fx, sy * ev.fy
    wi = (cx[..., None] + off * nx[..., None]) / fx + (0.5 / ev.fx - 0.5)
    wj = (cz[..., None] + off * nz[..., None]) / fy + (0.5 / ev.fy - 0.5)
    hw, ww = ev.work.shape
    valid = (wi >= 0) & (wi <= ww - 1) & (wj >= 0) & (wj <= hw - 1)
    v = bilinear_at(ev.work, wi, wj)
    valid &= ev.usable[np.rint(np.clip(wi, 0, ww - 1)).astype(np.intp)]
    # For each sample q: the echo across the flank, the log ratio of the sample to the
    # mean of the samples oa..ob outward of it (the tissue beside the flank), whatever
    # the flank's slope; counted up to twice as the bone's shadow lies under the sample
    # along the beam (``evidence`` shadow z-score, vertical windows: under a flank lies
    # the bone, under the tissue beside the shadow's edge lies tissue, so the edge of
    # the shadow under the bone's widest point gains nothing; with no shadow, as on the
    # L14 forearm, the echo alone carries the trace).
    n_t, n_o = v.shape[0], v.shape[-1]
    n_e = n_o - ob
    cs = np.zeros((n_t, n_step, n_o + 1))
    np.cumsum(v, axis=-1, out=cs[..., 1:])
    outside = cs[..., ob + 1 :] - cs[..., oa : oa + n_e]
    outside *= 1.0 / (ob - oa + 1)
    outside += _EPS
    e = np.log(v[..., :n_e] + _EPS)
    e -= np.log(outside)
    g = bilinear_at(ev.shadow_z, wi[..., :n_e], wj[..., :n_e])
    g *= 1.0 / p.shadow_z
    np.clip(g, 0.0, 1.0, out=g)
    g *= np.maximum(e, 0.0)
    e += g
    # A sample whose windows reach an invalid one is invalid; averaged along the trace
    # over ``run`` steps (a ridge parallel to the arc adds up, speckle does not), a
    # window holding an invalid sample stays far under every level.
    nbad = np.zeros((n_t, n_step, n_o + 1), np.int32)
    np.cumsum(~valid, axis=-1, out=nbad[..., 1:])
    e[nbad[..., ob + 1 :] != nbad[..., :n_e]] = _BAD
    n_run = max(1, int(round(p.run_mm / ds)))
    e = _moving_mean(e, n_run)
    # The ridge: the best continuous path through the band (one offset step per step at
    # most); the null: the same path search through the null band.
    paths, vals = _continuous_paths(
        np.concatenate([e[..., : 2 * m + 1], e[..., nc : nc + 2 * m + 1]]), m
    )
    pick, ridge, null = paths[:n_t], vals[:n_t], vals[n_t:]
    level = _stop_level(null, n_run, p.stop_z)
    if level is None:
        return out  # no tissue beside the flanks to measure speckle on: no extension
    good = ridge >= level
    # The trace ends at its last good step before ``gap`` bad steps in a row.
    gap = max(1, int(round(p.gap_mm / ds)))
    cb = np.zeros((n_t, n_step + gap + 1), np.intp)
    np.cumsum(~good, axis=1, out=cb[:, 1 : n_step + 1])
    cb[:, n_step + 1 :] = cb[:, n_step : n_step + 1] + np.arange(1, gap + 1)
    first = (cb[:, gap:] - cb[:, :-gap] == gap).argmax(axis=1)  # a bad stretch opens
    idx = np.arange(n_step)
    last = np.where(good & (idx < first[:, None]), idx, -1).max(axis=1)
    # Ridge points (offset smoothed along the trace), refined on the full image.
    t_i, k_i = np.nonzero(idx <= last[:, None])
    o = off[median3(pick)][t_i, k_i]
    nxk, nzk = nx[t_i, k_i], nz[t_i, k_i]
    rx, rz = refine_across(
        image, cx[t_i, k_i] + o * nxk, cz[t_i, k_i] + o * nzk, nxk, nzk, sx, sy, p.refine_mm
    )
    # Assemble: the trace (outermost first on the left) replaces the contour beyond its
    # start where it reached at least as far (arc length) as the contour did.
    pts = np.stack([rx / sx, rz / sy], axis=1)
    cut = np.searchsorted(t_i, np.arange(n_t + 1))
    by: dict[int, list] = {}
    for t, (ci, sd, s0) in enumerate(ends.tolist()):
        tail = s0 if sd < 0 else arc[int(ci)][-1] - s0
        if (last[t] + 1) * ds < tail:
            continue  # the trace stopped short of where the contour went: keep the contour
        by.setdefault(int(ci), [None, None, 0.0, np.inf])
        slot = by[int(ci)]
        piece = pts[cut[t] : cut[t + 1]]
        if sd < 0:
            slot[0], slot[2] = piece[::-1], s0
        else:
            slot[1], slot[3] = piece, s0
    for ci, (left, right, s_lo, s_hi) in by.items():
        s = arc[ci]
        parts = [np.asarray(out[ci], float)[(s > s_lo) & (s < s_hi)]]
        if left is not None:
            parts.insert(0, left)
        if right is not None:
            parts.append(right)
        out[ci] = np.concatenate(parts)
    return out


def _stop_level(null: np.ndarray, n_run: int, stop_z: float) -> float | None:
    """The ridge level a trace must reach: the null paths' median plus ``stop_z`` robust
    spreads (1.4826 MAD), over the windows clear of invalid samples; None under 10 such.

    One invalid sample among the ``n_run`` a window averages pulls its mean to about
    ``_BAD / n_run`` (-250), far under every valid one (a log ratio of a few units),
    yet over the half of ``_BAD`` a wholly invalid window sits at: pooled, such windows
    set the median and spread themselves. On the L14 recording 17 of 20 frames' pools
    held such windows (null bands leaving the image's usable columns): the median level
    2.07 with them, 1.74 without; on its cadaver-level copy, frame 14 (one end near the
    image's edge), median -250, spread 185, a level no ridge reaches.
    """
    pool = null[null > 0.5 * _BAD / n_run]
    if pool.size < 10:
        return None
    med = median1d(pool)
    spread = 1.4826 * median1d(np.abs(pool - med))
    return med + stop_z * max(spread, 1e-6)


def _moving_mean(a: np.ndarray, n: int) -> np.ndarray:
    """Mean over ``n`` consecutive steps (axis 1) around each, the ends repeated beyond."""
    if n <= 1:
        return a
    lo = (n - 1) // 2
    k = a.shape[1]
    pad = np.empty((a.shape[0], k + n) + a.shape[2:])
    pad[:, 0] = 0.0
    pad[:, 1 : lo + 1] = a[:, :1]
    pad[:, lo + 1 : lo + 1 + k] = a
    pad[:, lo + 1 + k :] = a[:, -1:]
    np.cumsum(pad, axis=1, out=pad)
    out = pad[:, n:] - pad[:, :-n]
    out *= 1.0 / n
    return out


def _continuous_paths(bands: np.ndarray, centre: int) -> tuple[np.ndarray, np.ndarray]:
    """Best paths through ``bands`` (N, K, B) moving at most one offset inward per step.

    Viterbi over the K steps, vectorised over the N bands; each path starts within one
    offset of ``centre`` (offsets increase outward, away from the bone). Returns the
    offsets ``(N, K)`` and the values along them. A ridge is a line: following it needs
    no jump across the band, and a path confined so finds far fewer chance alignments of
    speckle than a free maximum per step. It may turn down more steeply than the arc
    (a convex bone's flank only steepens outward; the curvature may be underestimated),
    never flatter: a layer running off the flank, the bright tissue under a vessel, is
    flatter than the flank it leaves (on the hard simulated tibia with a vessel, points
    added off the bone by more than 0.5 mm: 49 of 216 when the path could also move
    outward, 15 of 203 so). The forward pass keeps only the scores (two ufunc calls per
    step); the backtrack recomputes each step's choice from them, as in
    :func:`.candidates._optimal_path`.
    """
    n, n_k, n_b = bands.shape
    acc = np.full((n_k, n, n_b + 2), -np.inf)  # padded by -inf on both sides
    lo, hi = max(0, centre - 1), min(n_b, centre + 2)
    acc[0, :, lo + 1 : hi + 1] = bands[:, 0, lo:hi]
    for k in range(1, n_k):
        prev, cur = acc[k - 1], acc[k, :, 1:-1]
        np.maximum(prev[:, 1:-1], prev[:, 2:], out=cur)  # from b, or from b + 1 (outer)
        cur += bands[:, k]
    # Backtrack on Python floats: a few paths of a few tens of steps, where a numpy
    # call per step costs more than the arithmetic.
    path = np.empty((n, n_k), np.intp)
    path[:, -1] = acc[-1, :, 1:-1].argmax(axis=1)
    scores = acc.tolist()
    for r, b in enumerate(path[:, -1].tolist()):
        for k in range(n_k - 1, 0, -1):
            c, d = scores[k - 1][r][b + 1 : b + 3]  # predecessors b, b + 1 (padded)
            if d > c:
                b += 1
            path[r, k - 1] = b
    rows = np.arange(n)
    vals = bands[rows[:, None], np.arange(n_k), path]
    return path, vals


def extend_candidates(
    image: np.ndarray,
    ev: EvidenceMaps,
    candidates: Sequence,
    spacing: tuple[float, float],
    params: FlankParams = FlankParams(),  # noqa: B008 (frozen dataclass)
    rim: RimParams | None = None,
) -> list:
    """:func:`extend_flanks` on the points of each candidate that may be chosen, then
    :func:`.rim.follow_rims` on from their ends (``rim``; None: not).

    Reverberation copies are left as they are (never chosen); a candidate whose points
    changed gets its grey values re-sampled; strengths are unchanged.
    """
    return run_rims(extend_candidates_steps(image, ev, candidates, spacing, params, rim))


def extend_candidates_steps(
    image: np.ndarray,
    ev: EvidenceMaps,
    candidates: Sequence,
    spacing: tuple[float, float],
    params: FlankParams = FlankParams(),  # noqa: B008 (frozen dataclass)
    rim: RimParams | None = None,
) -> Generator[RadiusPaths, np.ndarray, list]:
    """:func:`extend_candidates` as a generator: yields the rim's path requests
    (:func:`.rim.follow_rims_steps`), is sent their paths, returns the candidates."""
    cands = list(candidates)
    which = [n for n, c in enumerate(cands) if not c.reverberation]
    if not which:
        return cands
    old = [cands[n].points_px for n in which]
    new = extend_flanks(image, ev, old, spacing, params) if params.enabled else list(old)
    if rim is not None and rim.enabled:
        # Both ends, on from where the arc tracer left them, of the strongest
        # ``rim.candidates`` only (candidates come strongest first: the bone is among
        # them, and each trace costs ~1 ms at 480x640).
        ends = [(q < rim.candidates,) * 2 for q in range(len(new))]
        traced = yield from follow_rims_steps(image, ev, new, ends, spacing, rim)
        added = [_added(a, b) for a, b in zip(new, traced, strict=True)]
        cands = with_points(image, cands, which, traced)
        for n, ab in zip(which, added, strict=True):
            if ab != (0, 0):
                cands[n] = dataclasses.replace(cands[n], rim_ends=ab)
        return cands
    return with_points(image, cands, which, new)


def _added(before: np.ndarray, after: np.ndarray) -> tuple[int, int]:
    """Points :func:`.rim.follow_rims` put before and after ``before`` in ``after``."""
    if after is before:
        return (0, 0)
    extra = after.shape[0] - before.shape[0]
    lead = int(np.flatnonzero((after[: extra + 1] == before[0]).all(axis=1))[0])
    return (lead, extra - lead)

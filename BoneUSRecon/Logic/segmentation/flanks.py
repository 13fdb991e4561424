"""Flanks: follow a candidate contour down the bone's flanks, where one depth per column fails.

The optimal path of :mod:`.candidates` has one depth per working column, so a flank of
70 degrees gets a column every ~0.9 mm of its length, the echo there is weak (specular
reflection goes away from the probe: ~15 % of the top's amplitude at 60 degrees), its
score is measured with vertical windows that a steep line crosses obliquely, and the
path's "no bone" state, a fascia crossing the flank or a wiggle the convexity cut takes
for a turn end the contour early: on unseen simulated sweeps 97 % of the gold points the
surface missed lay on flanks steeper than 45 degrees, with no contour point near them.

Here each end of a candidate that already descends outward (``min_start_deg``) is
continued along the bone, step by step in arc length, not column by column:

1. **Direction.** From ``retreat_mm`` inside the end (the path's last columns are its
   least certain), the outward direction and the curvature of the contour are taken
   over ``fit_mm`` of it (three points, second order). A bone's cross-section is convex
   seen from the probe, so the extrapolated arc turns only downward (curvature >= 0,
   at most ``max_curvature``) and never past ``max_deg`` (a beam from above cannot see
   under the bone): the trace cannot turn onto a layer running off the bone, which is
   flatter than the flank it leaves.
2. **Ridge.** Across the arc, a band of +-``band_mm`` is sampled on the working image
   (block-averaged, speckle reduced); at each sample the echo evidence is the log ratio
   of the sample to the mean of the tissue just outward of it (``outside_mm``, on the
   side of the flank away from the bone), i.e. the echo measured *across the flank*
   whatever its slope. Per step the ridge is the best sample of the band.
3. **Stop rule from this frame's own speckle.** The same search (same band width, same
   maximum over it, same averaging over ``run_mm`` along the trace) is run on a null
   band ``null_mm`` outward, in the tissue beside the flank; over all traces of the frame
   its median and robust spread (1.4826 MAD) say what speckle alone produces with this
   probe, gain and depth. The trace continues while its averaged ridge evidence
   exceeds that median by ``stop_z`` spreads, and ends at its last such step before a
   stretch of ``gap_mm`` under it. Both sides of the comparison are ratios of grey
   levels of the same frame at the same places, so the rule holds on any recording
   (a bright L14 echo 2.7x its tissue and the cadaver's 1.35x alike); a maximum over
   the band is compared with a maximum over a band of the same size, so the search
   itself does not make speckle look like a ridge.
4. **Points.** Each step's ridge is refined on the full-resolution image along the
   normal (parabolic peak of a profile averaged over three parallel lines). The trace
   replaces the contour beyond its start only when it reaches beyond the contour's end.

What is never extended: reverberation copies (never chosen); ends that are flat or
rise outward (a fascia, a layer at the bone's level, the far cortex seen from inside
the shadow is concave); a trace whose evidence is speckle-level from its start. The
candidates' strengths are unchanged, so the sweep-level choice weighs the same evidence.

Vectorised: every trace of a frame is sampled in one call, the ridge and null are
reductions over (trace, step, offset) arrays; only the set-up of each end (a few
scalars per candidate) is a Python loop.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np
from scipy.ndimage import uniform_filter1d

from BoneUSRecon.Logic.segmentation.detection import sample_bilinear
from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps
from BoneUSRecon.Logic.segmentation.features import mm_to_px
from BoneUSRecon.Logic.segmentation.params import FlankParams

__all__ = ["extend_flanks", "extend_candidates"]

_EPS = 1e-3  # grey/255: guards log(0) in black regions (no decision rests on it)
_DEBUG = None
_BAD = -10.0  # ridge evidence of a step outside the usable image: always under the stop level


def _median3(a: np.ndarray) -> np.ndarray:
    """Median of three along the last axis (ends kept), vectorised over the others."""
    if a.shape[-1] < 3:
        return a
    x, y, z = a[..., :-2], a[..., 1:-1], a[..., 2:]
    mid = np.maximum(np.minimum(x, y), np.minimum(np.maximum(x, y), z))
    return np.concatenate([a[..., :1], mid, a[..., -1:]], axis=-1)


def _ends(
    contours_mm: Sequence[np.ndarray], p: FlankParams
) -> tuple[list[tuple[int, int, float]], np.ndarray]:
    """The extendable ends: ``[(contour, side, start arc length)]`` and ``(T, 5)`` geometry.

    Geometry per end: start point ``x, z`` (mm), outward direction ``phi`` (radians below
    the lateral axis, outward), curvature ``kappa`` (1/mm, >= 0), ``side`` (-1: the
    first point's end, towards smaller columns; +1: the last point's end).
    """
    h = 0.5 * p.fit_mm
    lo, hi = np.radians(p.min_start_deg), np.radians(p.max_deg)
    ends, geo = [], []
    for ci, x in enumerate(contours_mm):
        if x.shape[0] < 4:
            continue
        s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(x, axis=0).T))))
        length = float(s[-1])
        if length < 2.0 * (p.retreat_mm + p.fit_mm):
            continue  # too short to give a direction at both ends
        sa = p.retreat_mm
        q = np.array([sa, sa + h, sa + 2 * h, length - sa, length - sa - h, length - sa - 2 * h])
        qx, qz = np.interp(q, s, x[:, 0]), np.interp(q, s, x[:, 1])
        for side, k in ((-1, 0), (1, 3)):
            a = np.array([qx[k], qz[k]])
            b = np.array([qx[k + 1], qz[k + 1]])
            c = np.array([qx[k + 2], qz[k + 2]])
            t = 3 * a - 4 * b + c  # outward tangent at a (second order), unnormalised
            phi = np.arctan2(t[1], side * t[0])
            u1, u2 = b - c, a - b
            bend = np.arctan2(u2[1], side * u2[0]) - np.arctan2(u1[1], side * u1[0])
            if not (lo <= phi < hi):
                continue
            kappa = float(np.clip(bend / h, 0.0, p.max_curvature))
            ends.append((ci, side, float(sa if side < 0 else length - sa)))
            geo.append((a[0], a[1], phi, kappa, side))
    return ends, np.array(geo, float).reshape(-1, 5)


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
    ends, geo = _ends(mm, p)
    if not ends:
        return out
    x0, z0, phi0, kappa, side = geo.T
    ds = p.step_mm
    n_step = max(2, int(np.ceil(p.max_mm / ds)))
    phi_max = np.radians(p.max_deg)
    k = np.arange(1, n_step + 1)
    # Centre line of the extrapolated arc (mid-point rule) and its outward normal.
    phi_mid = np.minimum(phi0[:, None] + kappa[:, None] * (k - 0.5) * ds, phi_max)
    cx = x0[:, None] + ds * np.cumsum(side[:, None] * np.cos(phi_mid), axis=1)
    cz = z0[:, None] + ds * np.cumsum(np.sin(phi_mid), axis=1)
    phi = np.minimum(phi0[:, None] + kappa[:, None] * k * ds, phi_max)
    nx, nz = side[:, None] * np.sin(phi), -np.cos(phi)  # outward: away from the bone
    # Offsets across the arc: the band, then outward far enough for the null band and
    # the outside windows of every sample of both.
    do = p.offset_mm
    m = mm_to_px(p.band_mm, do)
    oa, ob = mm_to_px(p.outside_mm[0], do), mm_to_px(p.outside_mm[1], do)
    nc = mm_to_px(p.null_mm, do)
    ia, ib = mm_to_px(p.inside_mm[0], do), mm_to_px(p.inside_mm[1], do)
    off = do * np.arange(-m - ib, nc + m + ob + 1)
    px = (cx[..., None] + off * nx[..., None]) / sx
    pz = (cz[..., None] + off * nz[..., None]) / sy
    # Working-image coordinates; samples outside it or in columns without contact are
    # invalid.
    wi = (px + 0.5) / ev.fx - 0.5
    wj = (pz + 0.5) / ev.fy - 0.5
    hw, ww = ev.work.shape
    valid = (wi >= 0) & (wi <= ww - 1) & (wj >= 0) & (wj <= hw - 1)
    valid &= ev.usable[np.clip(np.rint(wi), 0, ww - 1).astype(np.intp)]
    v = sample_bilinear(ev.work, np.column_stack([wi.ravel(), wj.ravel()])).reshape(wi.shape)
    v[~valid] = np.nan
    # Across the flank, for each sample q (offset index ib + j, j = 0 ..): the echo, its
    # log ratio to the mean of the samples oa..ob outward (tissue), and the shadow, the
    # log ratio of that tissue to the mean of the samples ia..ib inward. The shadow
    # counts up to as much as the echo: a bone's flank has tissue outward and, where
    # the bone stops the sound, shadow inward; a shadow's edge with no echo (under the
    # bone's widest point) counts nothing, and with no shadow (the L14 forearm) the
    # echo alone carries the trace.
    cs = np.concatenate([np.zeros(v.shape[:-1] + (1,)), np.cumsum(v, axis=-1)], axis=-1)
    n_e = v.shape[-1] - ob - ib
    q = ib + np.arange(n_e)
    outside = (cs[..., q + ob + 1] - cs[..., q + oa]) / (ob - oa + 1)
    inside = (cs[..., q - ia + 1] - cs[..., q - ib]) / (ib - ia + 1)
    log_out = np.log(outside + _EPS)
    echo = np.log(v[..., q] + _EPS) - log_out
    e = echo + np.clip(log_out - np.log(inside + _EPS), 0.0, np.maximum(echo, 0.0))
    # Averaged along the trace first (a ridge parallel to the arc adds up, speckle does
    # not), then the best offset of each band: the ridge, and the null in the tissue.
    size = max(1, int(round(p.run_mm / ds)))
    ok = ~np.isnan(e)
    e = uniform_filter1d(np.where(ok, e, _BAD), size, axis=1, mode="nearest")
    ok = uniform_filter1d(ok.astype(float), size, axis=1, mode="nearest") > 1 - 1e-9
    e = np.where(ok, e, _BAD)
    # The ridge: the best continuous path through the band (one offset step per step at
    # most); the null: the same path search through the null band.
    bands = np.stack([e[..., : 2 * m + 1], e[..., nc : nc + 2 * m + 1]], axis=1)
    paths, vals = _continuous_paths(bands, m)
    pick = paths[:, 0]
    ridge_s, null_s = vals[:, 0], vals[:, 1]
    null_full = null_s > _BAD
    pool = null_s[null_full]
    if pool.size < 10:
        return out  # no tissue beside the flanks to measure speckle on: no extension
    med = float(np.median(pool))
    spread = 1.4826 * float(np.median(np.abs(pool - med)))
    good = ridge_s >= med + p.stop_z * max(spread, 1e-6)
    # The trace ends at its last good step before ``gap`` bad steps in a row.
    gap = max(1, int(round(p.gap_mm / ds)))
    bad = np.concatenate([~good, np.ones((good.shape[0], gap), bool)], axis=1)
    run = np.lib.stride_tricks.sliding_window_view(bad, gap, axis=1)[:, : n_step + 1].all(axis=-1)
    first = run.argmax(axis=1)  # first step opening a bad stretch (n_step if none)
    idx = np.arange(n_step)
    last = np.where(good & (idx[None, :] < first[:, None]), idx[None, :], -1).max(axis=1)
    reach = (last + 1) * ds
    use = np.ones(len(ends), bool)
    if _DEBUG is not None:
        _DEBUG.update(locals())
    if not use.any():
        return out
    # Ridge points (offset smoothed along the trace), refined on the full image.
    o = off[ib + _median3(pick)]
    rx = cx + o * nx
    rz = cz + o * nz
    rx, rz = _refine_across(image, rx, rz, nx, nz, scale, p.refine_mm)
    if _DEBUG is not None:
        _DEBUG.update(rx=rx, rz=rz)
    # Assemble: the trace (outermost first on the left) replaces the contour beyond its start.
    traced: dict[tuple[int, int], np.ndarray] = {}
    for t, (ci, sd, _) in enumerate(ends):
        if use[t]:
            pts = np.column_stack([rx[t, : last[t] + 1], rz[t, : last[t] + 1]]) / scale
            traced[(ci, sd)] = pts
    starts = {(ci, sd): s0 for ci, sd, s0 in ends}
    for ci in {c for c, _ in traced}:
        x = mm[ci]
        s = np.concatenate(([0.0], np.cumsum(np.hypot(*np.diff(x, axis=0).T))))
        keep = np.ones(s.size, bool)
        parts = []
        if (ci, -1) in traced:
            keep &= s > starts[(ci, -1)]
            parts.append(traced[(ci, -1)][::-1])
        if (ci, 1) in traced:
            keep &= s < starts[(ci, 1)]
        parts.append(np.asarray(out[ci], float)[keep])
        if (ci, 1) in traced:
            parts.append(traced[(ci, 1)])
        out[ci] = np.concatenate(parts, axis=0)
    return out


def _continuous_paths(bands: np.ndarray, centre: int) -> tuple[np.ndarray, np.ndarray]:
    """Best paths through ``bands`` (..., K, B) moving at most one offset per step.

    Viterbi over the K steps, vectorised over the leading axes; each path starts within
    one offset of ``centre``. Returns the offsets ``(..., K)`` and the values along them.
    A ridge is a line: following it needs no jump across the band, and a path confined
    so finds far fewer chance alignments of speckle than a free maximum per step.
    """
    lead, (n_k, n_b) = bands.shape[:-2], bands.shape[-2:]
    acc = np.full(lead + (n_b,), -np.inf)
    lo, hi = max(0, centre - 1), min(n_b, centre + 2)
    acc[..., lo:hi] = bands[..., 0, lo:hi]
    pad = np.full(lead + (n_b + 2,), -np.inf)
    choice = np.empty((n_k,) + lead + (n_b,), np.intp)
    for k in range(1, n_k):
        pad[..., 1:-1] = acc
        three = np.stack([pad[..., :-2], pad[..., 1:-1], pad[..., 2:]])
        ch = three.argmax(axis=0)
        choice[k] = ch
        acc = np.take_along_axis(three, ch[None], axis=0)[0] + bands[..., k, :]
    path = np.empty(lead + (n_k,), np.intp)
    b = acc.argmax(axis=-1)
    path[..., -1] = b
    for k in range(n_k - 1, 0, -1):
        b = b + np.take_along_axis(choice[k], b[..., None], axis=-1)[..., 0] - 1
        path[..., k - 1] = b
    vals = np.take_along_axis(bands, path[..., None], axis=-1)[..., 0]
    return path, vals


def _refine_across(
    image: np.ndarray,
    rx: np.ndarray,
    rz: np.ndarray,
    nx: np.ndarray,
    nz: np.ndarray,
    scale: np.ndarray,
    half_mm: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Ridge points ``(T, K)`` mm moved to the echo's peak along the normal at full resolution.

    The profile across the flank (+-``half_mm``, half-pixel steps) is the mean of three
    parallel lines half a pixel apart along the flank (speckle averages, the echo does
    not), smoothed over three samples; the peak is fitted by a parabola.
    """
    step = 0.5 * float(scale.min())
    n = max(1, int(round(half_mm / step)))
    u = step * np.arange(-n - 1, n + 2)  # one extra each side for the parabola
    tx, tz = -nz, nx  # along the flank (sign irrelevant: symmetric lines)
    lines = np.array([-step, 0.0, step])
    qx = rx[..., None, None] + u[:, None] * nx[..., None, None] + lines * tx[..., None, None]
    qz = rz[..., None, None] + u[:, None] * nz[..., None, None] + lines * tz[..., None, None]
    ij = np.column_stack([(qx / scale[0]).ravel(), (qz / scale[1]).ravel()])
    prof = sample_bilinear(np.asarray(image), ij).reshape(qx.shape).mean(axis=-1)
    prof[..., 1:-1] = (prof[..., :-2] + prof[..., 1:-1] + prof[..., 2:]) / 3.0
    core = prof[..., 1:-1]
    kk = core.argmax(axis=-1) + 1
    y0 = np.take_along_axis(prof, (kk - 1)[..., None], axis=-1)[..., 0]
    y1 = np.take_along_axis(prof, kk[..., None], axis=-1)[..., 0]
    y2 = np.take_along_axis(prof, (kk + 1)[..., None], axis=-1)[..., 0]
    den = y0 - 2 * y1 + y2
    frac = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
    d = step * (kk - n - 1 + np.clip(frac, -0.5, 0.5))
    d = _median3(d)
    return rx + d * nx, rz + d * nz


def extend_candidates(
    image: np.ndarray,
    ev: EvidenceMaps,
    candidates: Sequence,
    spacing: tuple[float, float],
    params: FlankParams = FlankParams(),  # noqa: B008 (frozen dataclass)
) -> list:
    """:func:`extend_flanks` on the points of each candidate that may be chosen.

    Reverberation copies are left as they are (never chosen); a candidate whose points
    changed gets its grey values re-sampled; strengths are unchanged.
    """
    cands = list(candidates)
    which = [n for n, c in enumerate(cands) if not c.reverberation]
    if not params.enabled or not which:
        return cands
    new = extend_flanks(image, ev, [cands[n].points_px for n in which], spacing, params)
    for n, pts in zip(which, new, strict=True):
        if pts is not cands[n].points_px:
            cands[n] = dataclasses.replace(
                cands[n], points_px=pts, intensity=sample_bilinear(np.asarray(image), pts)
            )
    return cands

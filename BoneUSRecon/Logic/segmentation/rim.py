"""Rim: follow a contour's ends on round the bone's outline in polar coordinates.

:mod:`.flanks` follows a contour's end that already descends, along an arc extrapolated
from the end's own direction and curvature. Where the path stopped on a shoulder (a
flat end, as on the L14 forearm's right side, whose bone passes sound: no shadow under
its flank holds the path there), that tracer does not start, and an arc from the end
would run straight out while the bone turns down beside it: 10-20 mm of flank at 50-70
degrees were missing from every frame, and the surface's mean distance to the reference
contours was 1.86 mm. Where the arc tracer did start, its stop rule (its ridge over the
null by 4 spreads, the echo alone) ends it where a steep flank's echo fades: on the hard
simulated sweeps two thirds of the true contour steeper than 60 degrees had no point
near it.

A bone's cross-section is convex, so seen from a point inside it its outline is one
radius per direction. Ends are followed on in polar coordinates about the centre of the
circle fitted to the whole contour: every end of a contour with a faint echo (weaker
than its own shadow's contrast, as the cadaver's) or with no shadow (the L14 forearm),
flat or already followed by the arc tracer; of a bright echo over a shadow only the
flat ends (``max_start_deg``: followed on from the arc tracer's ends, its line took
fasciae touching the flank on the standard simulated sweeps). The circle is Kasa's
algebraic fit (for a round bone the centre of the cross-section, for a crest a point
inside it):

1. **Band.** For directions from the end's outward, every ``step_mm`` of arc, up to
   ``max_deg`` from the beam's up direction about the circle's centre (a bound on the
   search: a flank straighter than the circle lies past 90 degrees from it; step 6
   limits the outline's slope), the working image is sampled along the ray over the
   end's radius +-``band_mm``.
2. **A line or an edge across the outline.** A sample's echo is the smaller of its log
   ratios to the mean of the samples ``outside_mm`` further out along the ray (the
   tissue beside the bone) and as far in (``inside``): a line, not a step. A layer lying over the bone
   has the bone's echo inside it and is no line by this measure (on hard simulated
   sweeps the share of the points the rim added farther than 1 mm from the bone went
   from 18-65 % to 0-18 % per sweep with it: none on the sweep with fascia running off
   the bone).
   Or, where larger, an edge (``edge_mm``): the log ratio of the mean grey just
   outward of the sample to the mean just inward. On a steep flank the echo fades
   (specular reflection goes away from the probe; the cadaver's oval "echoes strongly
   only on the side facing the probe") and the outline is the edge between the tissue
   beside the bone and its shadow. A layer has tissue on both sides (no edge); a bone
   that passes sound is brighter inside (a negative edge, the line alone decides, as on
   the L14 recording); used for a faint echo only (a bright one stays a line down the
   flank, and an edge beside it is more often a shadow's side widened by the beam).
   With the ends followed on and the edge, on the hard simulated sweeps (seeds 5 and 7,
   160 x 128) the true contour steeper than 45 degrees covered within 0.5 mm went from
   0.57 to 0.68 of its points, steeper than 60 from 0.33 to 0.38, and the surface's
   mean distance to the true contours from 0.30 to 0.24 mm (figures:
   ``Testing/benchmarks/README.md``, "The rim follows the ends on").
   Averaged over ``run_mm`` of arc.
3. **Path.** The best path through the band, starting at the end's own radius, the
   radius changing by at most ``max_step_mm`` per step: the outline may depart from
   the circle by ~34 degrees, as a crest's or a humerus's straight flank does from a
   circle fitted to its top (it lies outside the circle, at directions past 90 degrees
   from its centre: hence ``max_deg`` 110; the outline's own slope ends the trace, step
   6). Outward faster than one radial sample per step only where the outline so
   implied still descends ``min_descent_deg``: a fascia leaving the bone at its level
   runs nearly flat, and a flat end's trace otherwise ran on along it. With these, on
   the hard simulated humerus, tibia and radius (seeds 53 and 59, 475 x 405) the true
   contour steeper than 60 degrees covered within 0.5 mm went from 0.39 / 0.42 to
   0.48 / 0.54 and the surface's mean gold distance from 0.66 / 0.55 to 0.45 / 0.42 mm
   (the humerus of seed 53: 1.15 -> 0.54 mm); over the benchmark's 24 sweeps of those
   seeds, 0.45 -> 0.38 mm.
4. **Stop.** The trace continues while its echo is at least ``keep`` of the contour's
   own (measured the same way along its own rays: this bone's echo in this frame) and
   above what the same search gives in the tissue ``null_mm`` further out (median of the
   frame's null paths, plus ``stop_z`` robust spreads), and ends at its last such step
   before ``gap_mm`` under it (or before up to ``fade_mm`` under ``keep`` but every step
   over the null, where the echo returns after it for at least as long: a real bone's
   echo dims where its outline turns, as on the L14 forearm's right shoulder, and a
   line that dimmed is no line that ended; a step at the null's level is one), at an
   unusable column (outside the field of view or without contact) or at the image's
   edge. Near that edge a sample whose windows cross it is measured on their part
   inside (``part_window_share`` of each at least; :func:`_partial_windows`), so a
   flank that runs into the edge is followed to about a millimetre of it, not
   ``outside_mm[1]`` short of it (the L14 recording's left flank: every contour ended
   1.7 mm inside the field; its reconstruction 0.305 -> 0.286 mm from the reference). The null stays on whole windows. Both levels are
   ratios of grey levels of the same frame: no grey level, none fitted to one data
   source. The null alone is not the rule (as it is in :mod:`.flanks`): the tissue
   beside a real bone holds fasciae as bright as a flank's echo (on the L14
   recording's cadaver-level copy a null floor of 1 or 2 spreads stopped traces on the
   flank: reconstruction 2.4 or 3.3 mm from the reference against 1.9 mm with the
   median alone).
5. **Points.** Each step's point is refined on the full-resolution image along its ray
   (:func:`.sampling.refine_across`) and appended to the contour's end.
6. **Slope.** The trace ends before its outline descends steeper than a beam from
   above can see (:func:`_outline_prefix`).

Only contours of at least ``min_points`` points with a good circle fit (centre below the
contour's shallowest point, radius within ``radius_mm``) are followed, after the arc
tracer; reverberation copies never are. Below the shallowest point, not the deepest:
the test is that the contour is convex seen from the probe (a bowl, such as the far
cortex seen inside the shadow, has its centre above all of it; a layer has a radius
over ``radius_mm``). A contour the arc tracer has already taken down a crest's or a
humerus's straight flank reaches below the centre of the circle fitted to it (the
flank is straighter than that circle), yet its other end, and the rest of that flank
past the arc tracer's stop, are on the outline; with the centre required below the
deepest point no end of such a contour was followed (on the hard simulated humerus,
tibia and radius of seed 53 at 475 x 405, 620 of the 2930 samples of the true contour
steeper than 60 degrees with no kept point within 0.5 mm lay beyond such ends). Ends
below the centre are followed as far as ``max_deg`` and the slope limits allow. With
it the true contour steeper than 60 degrees covered within 0.5 mm went 0.536 -> 0.577
on 13 hard simulated sweeps (seeds 5, 7, 53) and 0.551 -> 0.593 on 8 unseen ones,
kept points unchanged in accuracy (``Testing/benchmarks/README.md``, "Session 31,
branch flank31"); the standard and grey-shadow sweeps and the L14 recording (whose
contours keep their ends above the circle's centre) are unchanged.

Applied per frame to every candidate (:func:`.flanks.extend_candidates`), so live and
offline get the same contours. Vectorised over all traces of a frame (and their nulls);
Python loops only over the steps of the path search. Figures: ``Testing/benchmarks/README.md`` ("Rim").
"""

from __future__ import annotations

from collections.abc import Generator, Sequence
from typing import NamedTuple, TypeVar

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view

from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps
from BoneUSRecon.Logic.segmentation.features import median1d
from BoneUSRecon.Logic.segmentation.params import RimParams
from BoneUSRecon.Logic.segmentation.sampling import bilinear_at, refine_across

__all__ = [
    "RadiusPaths",
    "follow_rims",
    "follow_rims_steps",
    "kasa_circle",
    "radius_paths_many",
    "run_rims",
]

_T = TypeVar("_T")

_EPS = 1e-3
_BAD = -1e3
#: Smallest own level a measure is scaled by, log ratio (5 % over the reference grey:
#: an own edge under it is no shadow, and the edge measure is not used).
_MIN_LEVEL = 0.05


def _edge_ratio(
    raw_out: np.ndarray, cap_out: np.ndarray, inn: np.ndarray, dark: float
) -> np.ndarray:
    """The edge measure from an outward window's mean (``raw_out``), its mean with each
    sample capped at the tissue level (``cap_out``) and the inward window's (``inn``).

    ``log(cap_out / inn)``: tissue outward brighter than the inside; less
    ``log(raw_out / cap_out)``: whatever outward is brighter than the tissue (an echo
    line: under a line, its lower side would be an edge as good as the outline's). All
    plus ``dark`` (a tenth of the frame's tissue grey: a grain of black is no edge).
    """
    c = np.log(cap_out + dark)
    return 2.0 * c - np.log(raw_out + dark) - np.log(inn + dark)


def _window_mean(cs: np.ndarray, centre: int, near: int, far: int, n: int, side: int) -> np.ndarray:
    """Mean of the samples ``near`` .. ``far`` grid steps outward (``side`` 1) or inward
    (-1) of each of ``n`` samples, from the cumulative sum ``cs`` (a leading 0) along the
    last axis of samples on a grid running outward; sample ``b`` sits at grid index
    ``b + centre``."""
    lo, hi = (centre + near, centre + far + 1) if side > 0 else (centre - far, centre - near + 1)
    return (cs[..., hi : hi + n] - cs[..., lo : lo + n]) / (far - near + 1)


def _invalid(nbad: np.ndarray, lo: int, hi: int, n: int) -> np.ndarray:
    """Invalid samples among grid indices ``b + lo .. b + hi`` for each of ``n`` samples
    ``b``, from ``nbad``, the cumulative count of invalid ones (a leading 0)."""
    return nbad[..., hi + 1 : hi + 1 + n] - nbad[..., lo : lo + n]


def _partial_windows(
    g: np.ndarray,
    valid: np.ndarray,
    nbad: np.ndarray,
    bad: np.ndarray,
    k0: int,
    k1: int,
    n: int,
    share: float,
) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
    """The samples near the image's or field of view's edge measured on part windows.

    ``g``, ``valid``: the samples on the radial grid and whether each lies in the usable
    image; ``nbad`` the cumulative count of invalid ones (a leading 0); ``bad`` the
    samples (grid index ``b + k1``) whose span ``b .. b + 2 k1`` holds an invalid one.
    Of those, the ones whose own sample is valid and whose windows (``k0 .. k1`` out
    and in) each hold at least ``share`` of their samples valid: ``(mask, outside
    means, inside means)`` over the valid samples, the means in the order of
    ``mask``'s True entries. None when no sample qualifies (or ``share`` is 1).

    A window's mean is the tissue level beside the sample; a part of it past the
    speckle's grain estimates the same level (noisier), while a window that crosses
    the field's edge into black would take the edge for tissue. Without part windows
    every trace stops ``k1`` samples (``outside_mm[1]``) short of the field's edge:
    1.75 mm of a flank that runs into the edge is never followed.
    """
    if share >= 1.0 or not bad.any():
        return None
    full = k1 - k0 + 1
    need = max(1, int(np.ceil(share * full - 1e-9)))
    centre_ok = valid[..., k1 : k1 + n]
    # Invalid samples in each window: outward k1 + k0 .. 2 k1, inward 0 .. k1 - k0.
    bad_out = _invalid(nbad, k1 + k0, 2 * k1, n)
    bad_in = _invalid(nbad, 0, k1 - k0, n)
    part = bad & centre_ok & (full - bad_out >= need) & (full - bad_in >= need)
    if not part.any():
        return None
    rows, cols = np.nonzero(part)
    # Only the part windows' rows are summed again, over their valid samples.
    ur, inv = np.unique(rows, return_inverse=True)
    gv = np.where(valid[ur], g[ur], 0.0)
    cs = np.zeros((ur.size, gv.shape[1] + 1))
    np.cumsum(gv, axis=-1, out=cs[..., 1:])
    b = cols + k1
    out_sum = cs[inv, b + k1 + 1] - cs[inv, b + k0]
    in_sum = cs[inv, b - k0 + 1] - cs[inv, b - k1]
    return (
        part,
        out_sum / (full - bad_out[rows, cols]),
        in_sum / (full - bad_in[rows, cols]),
    )


def _beam_pixels(
    shape: tuple[int, int], wi: np.ndarray, wj: np.ndarray
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The working pixels nearest to points ``(wi, wj)`` (working columns, rows) on an
    image of ``shape``: their rows and columns, each pixel once, and per point the index
    of its pixel in them.

    Along the beam a point is read at its nearest pixel (:func:`_beam_edge`): the
    measures once per pixel, not once per point (the grid of :func:`follow_rims`
    samples every 0.1 mm along its rays, three points a working pixel at 480x640).
    """
    h, w = shape
    col = np.rint(np.clip(wi, 0, w - 1)).astype(np.intp)
    row = np.rint(np.clip(wj, 0, h - 1)).astype(np.intp)
    flat = row * w + col
    seen = np.zeros(h * w, bool)
    seen[flat] = True
    pix = np.flatnonzero(seen)
    at = np.empty(h * w, np.intp)
    at[pix] = np.arange(pix.size)
    return pix // w, pix % w, at[flat]


def _beam_rows(rows: float, gap: float) -> tuple[int, int]:
    """The rows of a window of :func:`_beam_edge` (at least 1) and its gap, whole rows."""
    return max(1, int(round(rows))), int(round(gap))


def _column_sums(
    ev: EvidenceMaps, col: np.ndarray, depth: int
) -> tuple[tuple[np.ndarray, np.ndarray], np.ndarray]:
    """Cumulative sums down the working image's columns ``col`` (each once, a leading
    row of 0, rows ``0 .. depth - 1``) capped at the tissue level and as it is: the
    windows of :func:`_beam_edge`, once a frame; and the index of each of ``col`` in
    them.

    Only the columns and depths the windows read: the same sums, each summed down its
    column in the same order as over the whole image.
    """
    seen = np.zeros(ev.work.shape[1], bool)
    seen[col] = True
    cols = np.flatnonzero(seen)
    sub = ev.work[:depth, cols]
    cu = np.zeros((depth + 1, cols.size))
    np.cumsum(np.minimum(sub, ev.tissue_beside[:depth, None]), axis=0, out=cu[1:])
    cw = np.zeros((depth + 1, cols.size))
    np.cumsum(sub, axis=0, out=cw[1:])
    return (cu, cw), (np.cumsum(seen) - 1)[col]


def _beam_edge(
    sums: tuple[np.ndarray, np.ndarray],
    row: np.ndarray,
    col: np.ndarray,
    h: int,
    rows: float,
    dark: float,
    gap: float = 0.0,
) -> np.ndarray:
    """:func:`_edge_ratio` along the beam: ``rows`` working rows above each pixel against
    as many below, ``gap`` rows clear of it either side, on an image of ``h`` rows
    (``sums``: :func:`_column_sums` of the frame, ``col`` the pixels' columns in it)."""
    k, o = _beam_rows(rows, gap)
    a0, a1 = np.clip(row - o - k, 0, h), np.clip(row - o, 0, h)
    b0, b1 = np.minimum(row + 1 + o, h), np.minimum(row + 1 + o + k, h)
    na, nb = np.maximum(a1 - a0, 1), np.maximum(b1 - b0, 1)
    # The window ends as flat indices into the sums (a gather by flat index costs a
    # third of a 2-D fancy index's; the same values), each shared by both sums.
    n = sums[0].shape[1]
    cu, cw = sums[0].ravel(), sums[1].ravel()
    a0, a1, b0, b1 = (r * n + col for r in (a0, a1, b0, b1))
    cap = (cu.take(a1) - cu.take(a0)) / na
    raw = (cw.take(a1) - cw.take(a0)) / na
    below = (cw.take(b1) - cw.take(b0)) / nb
    return _edge_ratio(raw, cap, below, dark)


def _capped(values: np.ndarray, rows: np.ndarray, level: np.ndarray) -> np.ndarray:
    """``values`` capped at the tissue ``level`` of their (fractional) working rows."""
    return np.minimum(values, np.interp(rows, np.arange(level.size), level))


def _outline_prefix(
    contour: np.ndarray,
    piece: np.ndarray,
    edge: np.ndarray,
    side: float,
    spacing: tuple[float, float],
    p: RimParams,
) -> int:
    """How many points of a trace (``piece``, pixels, outward from the contour's end;
    ``edge``: where the edge measure placed them) keep to a bone's outline seen from
    above, by the trace's own descent.

    The descent (degrees below the horizontal, outward) is measured over ``slope_mm`` of
    the contour's end and the trace together. Past the bone's widest point the edge of
    its shadow runs straight down, tissue beside it and the shadow within: the trace
    ends before its first point placed by the edge measure steeper than
    ``edge_slope_deg``, or any point steeper than ``max_slope_deg``: an echo is a
    reflector at a steeper slope than an edge (the L14 forearm's band runs down to ~80
    degrees on its right flank: capping its echo at 75 took the recording's
    reconstruction from 0.41 to 0.46 mm from the reference).
    """
    sx, sy = spacing
    # The contour's last slope_mm before its end, in outward order, then the trace.
    xy = np.asarray(contour, float) * (sx, sy)
    end = xy[0] if side < 0 else xy[-1]
    close = np.hypot(*(xy - end).T) <= p.slope_mm
    tail = xy[close][::-1] if side < 0 else xy[close]
    seq = np.concatenate([tail, piece * (sx, sy)])
    # Centred differences over slope_mm of arc (at least 0.8 of it each side).
    s = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(seq, axis=0).T))])
    half = 0.5 * p.slope_mm
    lo = np.maximum(np.searchsorted(s, s - half, side="right") - 1, 0)
    hi = np.minimum(np.searchsorted(s, s + half), s.size - 1)
    ok = (s - s[lo] >= 0.8 * half) & (s[hi] - s >= 0.8 * half)
    deg = np.degrees(np.arctan2(seq[hi, 1] - seq[lo, 1], side * (seq[hi, 0] - seq[lo, 0])))
    deg = deg[tail.shape[0] :]
    steep = (deg > p.max_slope_deg) | (edge & (deg > p.edge_slope_deg))
    bad = np.flatnonzero(ok[tail.shape[0] :] & steep)
    return int(bad[0]) if bad.size else piece.shape[0]


def _first_stop(good: np.ndarray, faded: np.ndarray, gap: int, fade: int) -> np.ndarray:
    """Per trace, the first step of its first dropout that is not bridged (its length if none).

    A dropout is a run of steps not ``good``. It is bridged when shorter than ``gap``
    steps, or when at most ``fade`` steps long, ``faded`` at every step (over the null:
    the echo dimmed, it did not end) and followed by at least as many good steps (the
    line returns). One that runs to the trace's last step never is.

    Parameters
    ----------
    good, faded : ndarray of bool, shape (T, S)
    gap, fade : int
        Steps.

    Returns
    -------
    ndarray of int, shape (T,)
    """
    n_t, n = good.shape
    pad = np.zeros((n_t, 1), np.int8)
    d = np.diff(np.concatenate([pad, (~good).view(np.int8), pad], axis=1), axis=1)
    t, a = np.nonzero(d == 1)  # dropouts' first steps, by trace then step
    b = np.nonzero(d == -1)[1]  # and their ends (exclusive), in the same order
    length = b - a
    # (np.r_'s arrays by np.concatenate: np.r_ costs ~5 us of Python per call.)
    nxt = np.where(np.concatenate((t[1:] == t[:-1], [False])), np.concatenate((a[1:], [n])), n)
    cs = np.zeros((n_t, n + 1), np.intp)
    np.cumsum(~faded, axis=1, out=cs[:, 1:])
    vanished = cs[t, b] - cs[t, a]  # steps of the dropout at or under the null level
    bridged = (b < n) & (
        (length < gap) | ((length <= fade) & (vanished == 0) & (nxt - b >= length))
    )
    first = np.full(n_t, n, np.intp)
    np.minimum.at(first, t[~bridged], a[~bridged])
    return first


def kasa_circle(x: np.ndarray, z: np.ndarray) -> tuple[float, float, float]:
    """Algebraic least-squares circle through points ``(x, z)``: ``(cx, cz, radius)``."""
    a = np.column_stack([x, z, np.ones_like(x)])
    c = np.linalg.lstsq(a, x * x + z * z, rcond=None)[0]
    cx, cz = 0.5 * c[0], 0.5 * c[1]
    return float(cx), float(cz), float(np.sqrt(max(c[2] + cx * cx + cz * cz, 0.0)))


def _radius_paths(e: np.ndarray, start: int, ms: int, up: np.ndarray | None = None) -> np.ndarray:
    """Viterbi over the steps of each trace: the radius index per step, ``(T, S)``.

    ``e`` (T, S, B): the score of radius index b at step s; every path starts at
    ``start`` and moves at most ``ms`` indices per step, the best total wins (the first
    of equal scores: the smaller move, as ``argmax`` over the moves -ms .. ms). ``up``
    (T, S), if given: at most this many indices outward (increasing) into step s.

    The loop over the steps is bound by its numpy calls (the arrays are small): the
    traces' states lie in one contiguous run, ``ms`` states of -inf between two traces
    (as the padding at the run's ends: a move reaches at most ``ms`` states, so no
    trace reads another's), and each step is ``2 ms`` maxima of shifted slices and one
    sum. No moves are stored: the backtrack takes, per step, the ``argmax`` of the
    state's predecessors among the stored scores (the same comparisons of the same
    doubles as a forward ``argmax``, so the same path).
    """
    n_tr, n_step, nb = e.shape
    wp = nb + 2 * ms  # a trace's states and its padding
    run = n_tr * wp - 2 * ms  # positions ms .. n_tr wp - ms of a step's scores
    # Every step's run (positions ms .. ms + run) is written by the loop: -inf is
    # filled only into the first step and the two ends (written once, not twice: the
    # batched requests of :func:`radius_paths_many` make these arrays a few MB).
    acc = np.empty((n_step, n_tr * wp))
    acc[0] = -np.inf
    acc[:, :ms] = -np.inf
    acc[:, ms + run :] = -np.inf
    base = np.arange(n_tr) * wp  # trace i's state b at base[i] + ms + b
    acc[0, base + ms + start] = e[:, 0, start]
    # The scores in the same layout, -inf in the padding (which then stays -inf).
    ep = np.empty((n_step, n_tr, wp))
    ep[:, :, :ms] = -np.inf
    ep[:, :, ms + nb :] = -np.inf
    ep[:, :, ms : ms + nb] = e.transpose(1, 0, 2)
    ep = ep.reshape(n_step, -1)
    best = np.empty(run)
    maximum, add = np.maximum, np.add
    # barred[t][j]: the outward move by ms - j (j < ms) into step t is over some trace's
    # limit there (most steps have none: a plain maximum).
    barred = [[False] * ms for _ in range(n_step)]
    if up is not None:
        # Predecessor prev[q + j - ms] moves into q by ms - j (outward when positive):
        # allowed where j >= ms - up, per position of the run and step (j < ms only;
        # inward moves are never barred), as ``where=`` masks of the maxima.
        # (Per trace, then repeated over its states: the same masks as comparing the
        # limits repeated per state, a quarter of the bytes.)
        allowed = np.arange(ms)[:, None, None] >= (ms - up.T)[None]  # (ms, S, T)
        allowed = np.repeat(allowed, wp, axis=2)[:, :, ms : ms + run]  # (ms, S, run)
        barred = (np.arange(ms) < (ms - up).max(axis=0)[:, None]).tolist()
    # Unbarred steps: the maxima of adjacent pairs first (pair[i] = max(prev[i],
    # prev[i + 1])), then every other pair and the last predecessor: ms + 1 calls for
    # the 2 ms + 1 predecessors instead of 2 ms (maxima of the same values: the same
    # scores).
    pair = np.empty(run + 2 * ms - 1)
    n_pair = pair.size
    for t in range(1, n_step):
        prev = acc[t - 1]  # predecessors of position q: prev[q - ms .. q + ms]
        if not any(barred[t]):
            maximum(prev[:n_pair], prev[1 : 1 + n_pair], out=pair)
            maximum(pair[:run], prev[2 * ms : 2 * ms + run], out=best)
            for j in range(2, 2 * ms, 2):
                maximum(best, pair[j : j + run], out=best)
            add(best, ep[t, ms : ms + run], out=acc[t, ms : ms + run])
            continue
        # The inward and straight moves first (never barred), then the outward ones
        # (where allowed): the same maxima, so the same scores.
        maximum(prev[ms : ms + run], prev[ms + 1 : ms + 1 + run], out=best)
        for j in range(ms + 2, 2 * ms + 1):
            maximum(best, prev[j : j + run], out=best)
        for j in range(ms):
            if barred[t][j]:
                maximum(best, prev[j : j + run], out=best, where=allowed[j, t])
            else:
                maximum(best, prev[j : j + run], out=best)
        add(best, ep[t, ms : ms + run], out=acc[t, ms : ms + run])
    # The backtrack: each trace's state as the first of its predecessors' positions in a
    # step's row of ``acc`` (its position less ms), its predecessors read as one window
    # of 2 ms + 1 (moves -ms .. ms), those over the step's outward limit at -inf.
    win = sliding_window_view(acc, 2 * ms + 1, axis=1)  # win[t, i] = acc[t, i .. i + 2 ms]
    lo_step = np.empty((n_step, n_tr), np.intp)
    lo_step[-1] = base + acc[-1].reshape(n_tr, wp)[:, ms : ms + nb].argmax(axis=1)
    if up is not None:
        moves = np.arange(-ms, ms + 1)
        over = np.where(moves < -up.T[:, :, None], -np.inf, 0.0)  # (S, T, moves)
    for t in range(n_step - 1, 0, -1):
        cand = win[t - 1][lo_step[t]]
        if any(barred[t]):
            cand += over[t]
        add(lo_step[t], cand.argmax(axis=1), out=lo_step[t - 1])
        lo_step[t - 1] -= ms
    path = (lo_step - base).T
    return path


class RadiusPaths(NamedTuple):
    """The arguments of one :func:`_radius_paths` a :func:`follow_rims_steps` asks for."""

    e: np.ndarray
    start: int
    ms: int
    up: np.ndarray | None


def run_rims(steps: Generator[RadiusPaths, np.ndarray, _T]) -> _T:
    """The value of a generator of :class:`RadiusPaths` requests (:func:`follow_rims_steps`,
    :func:`.flanks.extend_candidates_steps`), each request solved on its own."""
    try:
        ask = next(steps)
        while True:
            ask = steps.send(_radius_paths(*ask))
    except StopIteration as done:
        return done.value


def radius_paths_many(asks: Sequence[RadiusPaths]) -> list[np.ndarray]:
    """``[_radius_paths(*a) for a in asks]`` (the same paths), the requests of the same
    steps, radii, start and reach solved by one loop.

    :func:`_radius_paths` is bound by its ~10 numpy calls per step (51 steps, each on a
    few thousand states of one frame's traces), not by the arithmetic; the traces of the
    frames of a batch (:func:`.candidates.frame_candidates_many`) stacked make each call
    do the work of all of them. Each trace's states lie apart from every other's (its
    own padding), so a trace's path is the one it has alone; a request without an
    outward limit is given the limit ``ms`` (every move allowed, the same maxima).
    """
    out: list[np.ndarray | None] = [None] * len(asks)
    groups: dict[tuple[int, int, int, int], list[int]] = {}
    for q, a in enumerate(asks):
        groups.setdefault((a.e.shape[1], a.e.shape[2], a.start, a.ms), []).append(q)
    for (n_step, _, start, ms), idx in groups.items():
        if len(idx) == 1:
            out[idx[0]] = _radius_paths(*asks[idx[0]])
            continue
        e = np.concatenate([asks[q].e for q in idx])
        up = None
        if any(asks[q].up is not None for q in idx):
            up = np.concatenate(
                [
                    asks[q].up
                    if asks[q].up is not None
                    else np.full((asks[q].e.shape[0], n_step), ms, np.intp)
                    for q in idx
                ]
            )
        path = _radius_paths(e, start, ms, up)
        cut = np.cumsum([0] + [asks[q].e.shape[0] for q in idx])
        for k, q in enumerate(idx):
            out[q] = path[cut[k] : cut[k + 1]]
    return out  # type: ignore[return-value]


def follow_rims(
    image: np.ndarray,
    ev: EvidenceMaps,
    contours_px: Sequence[np.ndarray],
    ends: Sequence[tuple[bool, bool]],
    spacing: tuple[float, float],
    params: RimParams = RimParams(),  # noqa: B008 (frozen dataclass)
) -> list[np.ndarray]:
    """Each contour continued round its outline at the ends flagged in ``ends``.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W)
    ev : EvidenceMaps
    contours_px : sequence of ndarray, each (K, 2)
        ``(i, j)`` pixels, ordered by increasing ``i``.
    ends : sequence of (bool, bool)
        Per contour: follow its first end (smaller columns), its last end.
    spacing : (sx, sy)
    params : RimParams

    Returns
    -------
    list of ndarray
        The contours, extended where a trace held (the others the same objects).
    """
    return run_rims(follow_rims_steps(image, ev, contours_px, ends, spacing, params))


def follow_rims_steps(
    image: np.ndarray,
    ev: EvidenceMaps,
    contours_px: Sequence[np.ndarray],
    ends: Sequence[tuple[bool, bool]],
    spacing: tuple[float, float],
    params: RimParams = RimParams(),  # noqa: B008 (frozen dataclass)
) -> Generator[RadiusPaths, np.ndarray, list[np.ndarray]]:
    """:func:`follow_rims` as a generator: yields the :class:`RadiusPaths` it needs
    (at most one), is sent the paths, returns the contours (the caller may solve the
    paths of several frames together: :func:`radius_paths_many`)."""
    p = params
    out = list(contours_px)
    if not p.enabled:
        return out
    sx, sy = float(spacing[0]), float(spacing[1])
    # The traces: (contour, side, circle centre cx, cz, end radius r0 and direction
    # phi0, the contour's x, z in mm).
    rows, flat = [], []
    for n, (c, (lo, hi)) in enumerate(zip(out, ends, strict=True)):
        if not (lo or hi) or len(c) < p.min_points:
            continue
        x, z = c[:, 0] * sx, c[:, 1] * sy
        cx, cz, rad = kasa_circle(x, z)
        # Convex seen from the probe: the centre below the contour's shallowest point
        # (not its deepest: a flank already followed down may reach below the centre).
        if not (cz > z.min() and p.radius_mm[0] <= rad <= p.radius_mm[1]):
            continue
        # Arc length from each end to the contour's first break (consecutive points
        # over join_mm apart): an end cut off by one is a piece apart, not the outline's.
        seg = np.hypot(np.diff(x), np.diff(z))
        brk = np.flatnonzero(seg > p.join_mm)
        runs = (
            seg[: brk[0]].sum() if brk.size else seg.sum(),
            seg[brk[-1] + 1 :].sum() if brk.size else seg.sum(),
        )
        for side, want, run in ((-1.0, lo, runs[0]), (1.0, hi, runs[1])):
            if not want or run < p.fit_mm:
                continue
            k = 0 if side < 0 else -1
            r0 = float(np.hypot(x[k] - cx, z[k] - cz))
            phi0 = float(np.arctan2(side * (x[k] - cx), cz - z[k]))
            if phi0 >= np.radians(p.max_deg) - 1e-6:
                continue
            # The end's own outward slope over the last fit_mm of contour.
            q = np.hypot(x - x[k], z - z[k]) <= p.fit_mm
            qi = np.flatnonzero(q)
            far = qi[np.argmax(np.abs(qi - (0 if side < 0 else len(x) - 1)))]
            dx_, dz_ = side * (x[k] - x[far]), z[k] - z[far]
            flat.append(not (dx_ > 0 and np.degrees(np.arctan2(dz_, dx_)) >= p.max_start_deg))
            rows.append((n, side, cx, cz, r0, phi0, x, z))
    if not rows:
        return out
    fx, fy = sx * ev.fx, sy * ev.fy
    k0 = int(round(p.outside_mm[0] / p.offset_mm))
    k1 = int(round(p.outside_mm[1] / p.offset_mm))
    # The contour's own echo, measured the same way along its own rays: as a line, and
    # as the edge between the tissue beside the bone and its shadow (beyond the line:
    # the windows outside_mm out, capped at the tissue level, and as far in).
    ke = int(round(p.edge_mm / p.offset_mm))
    # The edge's ratios are of means over a few speckle grains, which can be near black
    # in a dark shadow: both sides get a tenth of the frame's typical tissue grey (a
    # level of this recording) so a grain of black is no edge.
    dark = 0.1 * median1d(ev.tissue)
    win = p.offset_mm * np.arange(k0, k1 + 1)
    nw = win.size
    radial = np.concatenate(([0.0], win, -win))  # the rays' offsets: np.r_[0.0, win, -win]
    # Once per contour (both its ends' rows share its rays).
    levels: dict[int, tuple[float, float]] = {}
    for n, _, ccx, ccz, _, _, x, z in rows:
        if n in levels:
            continue
        ph = np.arctan2(x - ccx, ccz - z)
        ri = np.hypot(x - ccx, z - ccz)[:, None] + radial
        qi = (ccx + np.sin(ph)[:, None] * ri) / fx + (0.5 / ev.fx - 0.5)
        qj = (ccz - np.cos(ph)[:, None] * ri) / fy + (0.5 / ev.fy - 0.5)
        s = bilinear_at(ev.work, qi, qj)
        c0 = np.log(s[:, 0] + _EPS)
        out_mean = s[:, 1 : 1 + nw].mean(axis=1)
        in_mean = s[:, 1 + nw :].mean(axis=1)
        own = c0 - np.log(out_mean + _EPS)
        if p.inside:
            own = np.minimum(own, c0 - np.log(in_mean + _EPS))
        capped = _capped(s[:, 1 : 1 + nw], qj[:, 1 : 1 + nw], ev.tissue_beside).mean(axis=1)
        levels[n] = (median1d(own), median1d(_edge_ratio(out_mean, capped, in_mean, dark)))
    own_line = np.array([levels[r[0]][0] for r in rows])
    own_edge = np.array([levels[r[0]][1] for r in rows])
    # Both measures in units of the contour's own (the stop level is then ``keep`` for
    # either). The edge is for a faint echo, one weaker than the contour's own shadow
    # contrast (the cadaver's 1.35x the tissue over a shadow 0.65 of it; the hard
    # simulated sweeps): there specular loss takes the flank's echo under the speckle.
    # A bright echo stays a line down the flank, and an edge beside it is more often a
    # shadow's side widened by the beam (on the standard simulated clavicle, seed 0,
    # the surface's area within 0.35 mm of the bone went from 0.998 to 0.95 with the
    # edge there, 0.994 without). A contour with no shadow under it (a bone that passes
    # sound, the L14 forearm) gets no edge measure either.
    faint = (own_edge > _MIN_LEVEL) & (own_line < own_edge)
    # A bright echo over a shadow: its end that already descends is the arc tracer's
    # (:mod:`.flanks`), whose stop rule (the shadow under the wall) ended it; followed
    # on there, the line took fasciae touching the flank on the standard simulated
    # sweeps (the surface's 99th-percentile distance to the bone 0.23 -> 0.32 mm on the
    # clavicle, seed 0). Only its flat ends are followed. A faint echo's ends all are
    # (the edge carries them), and so are those of a contour with no shadow, where the
    # arc tracer has only the echo to go on (the L14 forearm: reconstruction 0.47 mm
    # from the reference with flat ends only, 0.41 with all).
    use = faint | (own_edge <= _MIN_LEVEL) | np.array(flat)
    if not use.any():
        return out
    if not use.all():
        rows = [r for r, u in zip(rows, use, strict=True) if u]
        own_line, own_edge, faint = own_line[use], own_edge[use], faint[use]
    n_t = len(rows)
    side = np.array([r[1] for r in rows])[:, None]
    cx = np.array([r[2] for r in rows])[:, None]
    cz = np.array([r[3] for r in rows])[:, None]
    r0 = np.array([r[4] for r in rows])
    phi0 = np.array([r[5] for r in rows])
    dphi = p.step_mm / r0
    n_step = int(np.ceil(((np.radians(p.max_deg) - phi0) / dphi).max())) + 1
    n_step = min(n_step, int(np.ceil(p.max_mm / p.step_mm)) + 1)
    phi = phi0[:, None] + dphi[:, None] * np.arange(n_step)
    live = phi <= np.radians(p.max_deg)
    # Only the live steps are sampled and measured, one row each (a step past max_deg
    # scores _BAD whatever it measures; a quarter of the steps on the hard simulated
    # sweeps): every measure is along its step's ray alone.
    tr, st = np.nonzero(live)
    line_unit = np.maximum(own_line, _MIN_LEVEL)[tr, None]
    use_edge = (faint & (ke > 0))[tr, None]  # edge_mm 0: the line alone
    m = int(round(p.band_mm / p.offset_mm))
    off = p.offset_mm * np.arange(-m, m + 1)
    sin, cos = np.sin(phi)[tr, st, None], np.cos(phi)[tr, st, None]
    hw, ww = ev.work.shape
    nb = off.size
    # Outward window of band sample b: radii off[b] + outs, i.e. indices b + k0 .. b + k1
    # on a regular grid of offset_mm; sample that grid once.
    # The null band (the same search in the tissue beside the bone, null_mm out) on the
    # same radial grid, ``shift`` samples further out.
    shift = int(round(p.null_mm / p.offset_mm))
    ne = nb + shift
    # ... and k1 samples further in, for the window inward of each sample.
    grid = off[0] + p.offset_mm * np.arange(-k1, ne + k1 + 1)
    radius = r0[tr, None] + grid
    gi = cx[tr] + side[tr] * sin * radius
    gi /= fx
    gi += 0.5 / ev.fx - 0.5
    gj = cz[tr] - cos * radius
    gj /= fy
    gj += 0.5 / ev.fy - 0.5
    gvalid = (gi >= 0) & (gi <= ww - 1) & (gj >= 0) & (gj <= hw - 1)
    gvalid &= ev.usable[np.rint(np.clip(gi, 0, ww - 1)).astype(np.intp)]
    g = bilinear_at(ev.work, gi, gj)
    cs = np.zeros((g.shape[0], g.shape[1] + 1))
    np.cumsum(g, axis=-1, out=cs[..., 1:])
    # Sample b of the band is grid index b + k1; its windows k0 .. k1 samples out and in.
    outside = _window_mean(cs, k1, k0, k1, ne, 1)
    inside = _window_mean(cs, k1, k0, k1, ne, -1)
    # Samples whose windows reach outside the image or its field of view: measured on
    # the part of their windows inside it where each keeps at least
    # ``part_window_share`` of its samples, otherwise not at all (``bad``).
    nbad = np.zeros((g.shape[0], g.shape[1] + 1), np.int32)
    np.cumsum(~gvalid, axis=-1, out=nbad[..., 1:])
    bad = _invalid(nbad, 0, 2 * k1, ne) > 0
    partial = _partial_windows(g, gvalid, nbad, bad, k0, k1, ne, p.part_window_share)
    if partial is not None:
        part, out_p, in_p = partial
        outside[part], inside[part] = out_p, in_p
        bad &= ~part
    centre = np.log(g[..., k1 : k1 + ne] + _EPS)
    e = centre - np.log(outside + _EPS)
    if p.inside:
        # A line, not a step: brighter than what lies inward too (a layer over the bone
        # has the bone's echo under it; the bone has its shadow, or on a phantom that
        # passes sound, its fainter inside).
        np.minimum(e, centre - np.log(inside + _EPS), out=e)
    e /= line_unit
    # Traces whose contour casts a shadow: their line is weighed by the shadow along the
    # beam (below), and the faint ones among them may also follow an edge.
    shaded = (own_edge > _MIN_LEVEL)[tr]
    edge_won = None
    if shaded.any():
        s_idx = np.flatnonzero(shaded)
        s_ = slice(None) if s_idx.size == shaded.size else s_idx
        gi_s, gj_s = gi[s_], gj[s_]
        # Along the beam: each point on its nearest working pixel (the measures once
        # per pixel, on the sums of the pixels' columns down to the deepest window).
        row, col, at = _beam_pixels((hw, ww), gi_s[..., k1 : k1 + ne], gj_s[..., k1 : k1 + ne])
        k_across = (p.outside_mm[1] - p.outside_mm[0]) / ev.dy, p.outside_mm[0] / ev.dy
        reach = max(sum(_beam_rows(p.edge_mm / ev.dy, 0.0)), sum(_beam_rows(*k_across)))
        sums, col = _column_sums(ev, col, min(hw, int(row.max()) + 1 + reach))
        # A bone that casts a shadow casts it under its flank's echo too; a fascia
        # running off the flank has tissue under it, and a ring inside the shadow (a far
        # cortex, a reverberation) has the shadow over it. Where the contour has a
        # shadow, a line counts in full only over at least half its own shadow's
        # contrast along the beam (on the standard simulated radius, seed 1, traces ran
        # on along such fasciae 1-2 mm off the bone). Bright contours too: when only
        # faint ones' lines were weighed so, a bright contour's trace on the hard
        # simulated tibia with fascia (seed 5) ran on along the fascia up to 4.8 mm off
        # the bone without the descent limit, and on the standard clavicle (seed 0,
        # frame 9) along a layer 3 mm off it from a piece the path had stepped onto; the
        # hard sweeps of seeds 5 and 7 kept 3.4 % of their points over 1 mm from the
        # bone, 3.3 % since.
        # (Its windows clear of the line, as the contour's own shadow contrast was measured.)
        across = _beam_edge(sums, row, col, hw, k_across[0], dark, k_across[1])[at]
        shade = np.clip(2.0 * across / own_edge[tr[s_], None], 0.0, 1.0)
        e_s = e[s_]
        e_s = np.minimum(e_s, e_s * shade)
        if ke and use_edge.any():
            # Or an edge: the tissue outward brighter than the inside over ``edge_mm``
            # either side (grid indices b + k1 + 1 .. b + k1 + ke and b + k1 - ke ..
            # b + k1 - 1). On a steep flank the echo fades (specular reflection goes away
            # from the probe) and the outline is where the tissue beside the bone meets
            # its shadow; a layer has tissue on both sides. Outward samples count at most
            # at the tissue level of their depth: under a bright line (a thick echo
            # band's lower side, a fascia's) the outward window holds the line, which is
            # no tissue beside a shadow. (Measured on the faint traces' steps only, ``f``
            # among the shaded: the others' scores are the line's alone.)
            f = np.flatnonzero(use_edge[shaded, 0])
            f = slice(None) if f.size == e_s.shape[0] else f
            # The faint steps among all live steps (f: among the shaded ones).
            fi = s_ if isinstance(f, slice) else s_idx[f]
            cs_f, gj_f = cs[fi], gj[fi]
            cap = np.zeros_like(cs_f)
            np.cumsum(_capped(g[fi], gj_f, ev.tissue_beside), axis=-1, out=cap[..., 1:])
            edge = _edge_ratio(
                _window_mean(cs_f, k1, 1, ke, ne, 1),
                _window_mean(cap, k1, 1, ke, ne, 1),
                _window_mean(cs_f, k1, 1, ke, ne, -1),
                dark,
            )
            if partial is not None:
                # A partial window's sample is measured as a line only, unless the
                # edge's own (shorter) windows lie wholly inside the image.
                edge[_invalid(nbad[fi], k1 - ke, k1 + ke, ne) > 0] = -np.inf
            # ... and along the beam: a point of the outline is seen from above, tissue
            # over it and the shadow under it. Past the bone's widest point the edge of
            # its shadow has the bone's shadow over it too: no outline there (on the hard
            # simulated radius, seed 43, a trace ran on down the shadow's side 5 mm off
            # the bone).
            beam = _beam_edge(sums, row, col, hw, p.edge_mm / ev.dy, dark)[at[f]]
            np.minimum(edge, beam, out=edge)
            tf, sf = tr[fi], st[fi]
            edge /= own_edge[tf, None]
            e_f = e_s[f]
            edge_won = np.zeros((n_t, n_step, nb), bool)
            edge_won[tf, sf] = edge[..., :nb] > e_f[..., :nb]
            e_s[f] = np.maximum(e_f, edge)
        e[s_] = e_s
    e[bad] = _BAD
    e_live, e = e, np.full((2 * n_t, n_step, nb), _BAD)  # traces, then nulls
    e[tr, st] = e_live[:, :nb]
    null_e = e_live[:, shift : shift + nb]
    if partial is not None:
        # The null is what whole windows give in the tissue beside the bone: a part
        # window's sample (noisier, and only near the field's edge) is left out of it.
        null_e = np.where(part[:, shift : shift + nb], _BAD, null_e)
    e[n_t + tr, st] = null_e
    own_e = e[:n_t].copy()  # each step's own value, before the average along the trace
    run = max(1, int(round(p.run_mm / p.step_mm)))
    if run > 1:
        ce = np.zeros((2 * n_t, n_step + 1, nb))
        np.cumsum(e, axis=1, out=ce[:, 1:])
        i = np.arange(n_step)
        lo = np.clip(i - run // 2, 0, n_step)
        hi = np.clip(i - run // 2 + run, 0, n_step)
        e = (ce[:, hi] - ce[:, lo]) / (hi - lo)[None, :, None]
    # The path: Viterbi over the steps, the radius moving at most max_step per step.
    ms = max(1, int(round(p.max_step_mm / p.offset_mm)))
    # Outward, faster than one radial sample per step, only where the outline so implied
    # still descends at least min_descent_deg: the radius grows by g over a step of
    # step_mm where the outline runs atan(g / step_mm) flatter than the circle.
    # Past 90 degrees + min_descent_deg about the centre any outward move keeps that
    # descent (tan would turn negative there: clipped just under a right angle).
    lean = np.clip(phi - np.radians(p.min_descent_deg), 0.0, np.radians(89.0))
    up = np.clip(np.floor(p.step_mm * np.tan(lean) / p.offset_mm + 1e-9), 1, ms).astype(np.intp)
    path = yield RadiusPaths(e, m, ms, None if (up >= ms).all() else np.concatenate([up, up]))
    tt = np.arange(2 * n_t)
    vals = e[tt[:, None], np.arange(n_step), path]
    ridge, null, path = vals[:n_t], vals[n_t:], path[:n_t]
    tt = tt[:n_t]
    # What speckle and the tissue's own layers give with the same search, pooled over
    # the frame's traces (median and robust spread).
    pool = null[(null > 0.5 * _BAD) & live]
    if pool.size < 10:
        return out
    med = median1d(pool)
    floor = med + p.stop_z * max(1.4826 * median1d(np.abs(pool - med)), 1e-6)
    good = ridge >= max(p.keep, floor)
    good &= ridge > 0.5 * _BAD
    gap = max(1, int(round(p.gap_mm / p.step_mm)))
    # A longer dropout whose every step stays over the null floor (the echo faded, it
    # did not end) is bridged where the line returns after it (``fade_mm``).
    first = _first_stop(good, ridge > floor, gap, int(round(p.fade_mm / p.step_mm)))
    steps = np.arange(n_step)
    # The average along the trace carries a ridge ``run_mm / 2`` past its end: the trace
    # ends at its last step whose own value holds too.
    held = good & (own_e[tt[:, None], steps, path] >= max(p.keep, floor))
    last = np.where(held & (steps < first[:, None]) & (steps > 0), steps, -1).max(axis=1)
    # Points (step 0 is the end itself), refined along the ray on the full image.
    t_i, k_i = np.nonzero((steps >= 1) & (steps <= last[:, None]))
    if t_i.size == 0:
        return out
    rad = r0[t_i] + off[path[t_i, k_i]]
    ph = phi[t_i, k_i]
    sd = side[t_i, 0]
    nx, nz = sd * np.sin(ph), -np.cos(ph)
    px, pz = cx[t_i, 0] + nx * rad, cz[t_i, 0] + nz * rad
    rx, rz = refine_across(image, px, pz, nx, nz, sx, sy, p.refine_mm)
    won = np.zeros(t_i.size, bool)
    if edge_won is not None:
        # Where the edge decided there is no echo peak to refine onto (the profile's
        # brightest sample lies in the tissue outward): the path's own radius stays.
        won = edge_won[t_i, k_i, path[t_i, k_i]]
        rx, rz = np.where(won, px, rx), np.where(won, pz, rz)
    pts = np.stack([rx / sx, rz / sy], axis=1)
    cut = np.searchsorted(t_i, np.arange(n_t + 1))
    for q, (n, sd_q, *_rest) in enumerate(rows):
        piece = pts[cut[q] : cut[q + 1]]
        c = np.asarray(out[n], float)
        if piece.shape[0]:
            piece = piece[: _outline_prefix(c, piece, won[cut[q] : cut[q + 1]], sd_q, (sx, sy), p)]
        if piece.shape[0] < p.min_steps:
            continue
        out[n] = np.concatenate([piece[::-1], c]) if sd_q < 0 else np.concatenate([c, piece])
    return out

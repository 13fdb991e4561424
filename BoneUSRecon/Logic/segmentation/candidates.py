"""Per-frame step: candidate bone contours of one frame (pure; cacheable per frame).

:func:`frame_candidates` scores the frame (:mod:`.evidence`), then finds up to
``max_candidates`` contours by repeated optimal paths across columns (dynamic
programming with a "no bone" state), each pass suppressing a band around what the
previous passes found, so the bone, a fascia above it and a reverberation below it
are all offered to the sweep-level choice (:mod:`.track`) instead of one of them
being decided here.

Look-alikes handled per frame (each with a simulated test in
``Testing/test_segmentation.py``):

* **skin line / no contact** at the image edges: columns without contact score 0, and
  a line without soft tissue above it (gel, air) scores 0 (:mod:`.evidence`, cover).
* **fascia / tendon**: a bright line with tissue, not shadow, beneath: its shadow
  z-score is ~0, so its score is ~0 (:mod:`.evidence`).
* **vessel with ring-down**: the lumen under the anterior wall is dark only for a few
  mm, with enhancement or ring-down under it; the long (shadow-depth) window sees it.
  The posterior wall has anechoic lumen above it: no cover. Nor is the lumen a shadow
  for what lies under it: a vessel over the bone does not make the bone a far cortex
  "in a shadow" (:func:`_without_lumens`; tests in ``Testing/test_augment_lookalikes.py``,
  the vessel drawn into the real recording).
* **a line over another echo** (a fascia over the bone): bone stops the sound, so
  anything under it returns much fainter than its echo; a candidate with an echo at
  least ``beneath_ratio`` as bright under most of its columns, and tissue (not
  shadow) between them, is marked ``echo_beneath`` and valued less by the track.
* **no first interface** (the far cortex, a band, under a grey shadow): bone is the
  first strong reflector along the beam, so nothing under it is anatomy. A candidate
  is marked ``echo_beneath`` when it lies under a brighter candidate, within its
  columns, with shadow between them (:func:`_mark_echo_beneath`); never from the grey
  over it alone (a muscle lying on the bone is as dark as a grey shadow). Regions are
  judged on profiles that follow a candidate's shape and take the median over its
  columns (:func:`_underside_profile`), so speckle averages out and ratios of a few
  tenths are measurable.
* **reverberation copies**: a candidate lying, column by column, at twice the depth of
  a shallower one (probe-face reverberation: the echo travels the path twice), or one
  of a series of equally spaced parallel copies under a line (reverberation inside a
  layer) is marked ``reverberation`` and never chosen: sound that made a copy did not
  come from a new interface. A series is found from the profile of any of its lines
  (:func:`_series`: three or more equally spaced, fading lines over dark troughs);
  its top, added if no pass found it, carries the series' evidence
  (:func:`_mark_series`): under a grey shadow the copies, with the darkest shadow
  beneath them, outscore the faint reflector itself. A top made over a copy's
  columns is followed on past them (:func:`_extend_top`): the copies of a convex bone
  narrow out on its sides.

* **a bone beside it joined on** (the fibula 10-15 mm under the tibia's top, the ulna
  beside a radius): a contour whose flank, past its deepest point, climbs back up
  onto the neighbour is cut at that point (:func:`_cut_climbing_ends`; tests in
  ``Testing/test_fibula.py``).

Layers over the bone: a candidate that runs on a fascia or a run of speckle just over
the bone (its shadow windows, 1.5 mm under it, hold the bone's own shadow) is moved down
onto the bone where the shadow starts under it (:mod:`.settle`), before its flanks are
followed.

Flanks: the path may change depth by up to ``max_slope`` (tan 72 degrees) per lateral
mm with a small quadratic penalty, and the shadow windows hang below each column (the
inside of a convex bone lies below every point of its upper surface, so the shadow
holds on the flanks); past the path's reach each candidate is followed down the
flanks in arc length by :mod:`.flanks` (one depth per column samples a 70-degree flank
poorly, and its echo fades there). Nothing trims the ends of a contour afterwards but the convexity cut
(:func:`convex_part`: a layer meeting the bone); when a layer climbs above the bone's
top the cut is made around the layer, so each convex piece of a contour is weighed on
its own evidence and the strongest kept; pieces lying over one shadow (a line flagged
``echo_beneath`` under them: what cast it is one reflector) are joined instead.
"""

from __future__ import annotations

import dataclasses
from bisect import bisect_left, bisect_right
from collections.abc import Callable, Generator, Sequence
from dataclasses import dataclass, field

import numpy as np
from scipy.ndimage import gaussian_filter1d, maximum_filter1d, median_filter, minimum_filter1d

from BoneUSRecon.Logic.segmentation.detection import sample_bilinear
from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps, bone_evidence
from BoneUSRecon.Logic.segmentation.features import (
    ceil_px,
    median1d,
    mm_to_px,
    sorted_row_percentiles,
)
from BoneUSRecon.Logic.segmentation.flanks import extend_candidates_steps
from BoneUSRecon.Logic.segmentation.params import ShadowPathParams
from BoneUSRecon.Logic.segmentation.rim import RadiusPaths, radius_paths_many
from BoneUSRecon.Logic.segmentation.settle import settle_candidates

__all__ = [
    "BoneCandidate",
    "FrameCandidates",
    "frame_candidates",
    "frame_candidates_many",
    "candidates_from_points",
]

_EPS = 1e-3  # grey/255: guards log(0) in black regions


@dataclass(frozen=True, eq=False)
class BoneCandidate:
    """One candidate bone contour of a frame.

    Attributes
    ----------
    points_px : ndarray, shape (K, 2)
        ``(i, j)`` = (column, row), sub-pixel, ordered by increasing ``i``.
    intensity : ndarray, shape (K,)
        Grey value (0..255) at each point.
    strength : float
        Evidence above the null level summed along the contour, score x mm.
    echo_z, shadow_z : float
        Median echo and shadow z-scores along the contour.
    reverberation : bool
        A reverberation copy of a shallower candidate (never chosen).
    echo_beneath : bool
        An echo at least ``beneath_ratio`` as bright lies under it and it casts no
        shadow (sound went through: soft tissue, not bone), or it lies in the shadow of a
        shallower candidate (far cortex); the track values it less.
    guided : bool
        Found by the search guided by the bone track (:mod:`.recovery`), not by the
        frame's own passes.
    rim_ends : (int, int)
        Points :mod:`.rim` added before the first and after the last of the contour it
        was given (the least certain: a trace following the outline round on its own
        frame's evidence).
    """

    points_px: np.ndarray
    intensity: np.ndarray
    strength: float
    echo_z: float
    shadow_z: float
    reverberation: bool = False
    echo_beneath: bool = False
    guided: bool = False
    rim_ends: tuple[int, int] = (0, 0)

    def kept_run(self, a: int, b: int) -> BoneCandidate:
        """The candidate with only its points ``a .. b - 1`` (a cut at its ends), the rim's
        points among them still counted as the rim's."""
        n = self.points_px.shape[0]
        rim = (max(0, self.rim_ends[0] - a), max(0, self.rim_ends[1] - (n - b)))
        return dataclasses.replace(
            self, points_px=self.points_px[a:b], intensity=self.intensity[a:b], rim_ends=rim
        )

    @property
    def core_px(self) -> np.ndarray:
        """``points_px`` without the rim's points: what the sweep-level steps compare.

        The track's links and the recovery's priors measure how far apart two frames'
        contours lie; a rim trace that ran from a look-alike's end down onto the bone's
        flank (a false echo over the bone) would make the look-alike link to its
        neighbours, and one that ran on past the bone in a neighbour would bend a
        recovery's prior. The rim's points join the contour the track chose.
        """
        a, b = self.rim_ends
        return self.points_px[a : self.points_px.shape[0] - b] if a or b else self.points_px


@dataclass(frozen=True, eq=False)
class FrameCandidates:
    """The candidates of one frame, strongest first, and why there is none if so.

    ``fov_px``: the first and last image columns of the imaged field of view, when
    known (the track prefers a bone near its middle over a neighbouring one,
    :func:`.track.central_track`; None: no such preference for this frame).
    ``level``: the frame's tissue level (:meth:`.evidence.EvidenceMaps.frame_level`;
    None: not measured), which :mod:`.recovery` compares with the sweep's.
    """

    candidates: tuple[BoneCandidate, ...]
    spacing: tuple[float, float]
    reason: str = ""
    extras: dict = field(default_factory=dict)
    fov_px: tuple[float, float] | None = None
    level: float | None = None

    @property
    def usable(self) -> tuple[BoneCandidate, ...]:
        """Candidates that may be chosen (not reverberation copies)."""
        return tuple(c for c in self.candidates if not c.reverberation)


def _optimal_path(gain: np.ndarray, shift_cost: np.ndarray, switch: float) -> np.ndarray:
    """Best path through ``gain`` (h, w) with a no-bone state; rows per column, -1 = no bone.

    The loop over columns is bound by the number of numpy calls, not by ``h``: each
    column takes one reduction over the shifts laid out as (shift, row) rows, and no
    back-pointers are stored; the backtrack recomputes the one step it needs per column
    from the stored scores (same arithmetic, so the same path).

    Most calls are the small bands of :func:`_trace_band` (~20 x 20, a switch cost no
    path pays), where the fixed costs per call and per column dominate: the window view
    is made directly (``sliding_window_view``'s checks cost as much as ten columns),
    the no-bone bookkeeping is skipped where the no-bone score provably never rises,
    and the backtrack runs on Python floats.
    """
    h, w = gain.shape
    n = shift_cost.size
    d = n // 2
    # score[c, d + j]: best path ending at row j of column c (padded by -inf for the window).
    score = np.full((w, h + 2 * d), -np.inf)
    score[:, d : d + h] = gain.T
    # win[c] = (shift, row) view of column c's padded scores (win[c, s, j] = score[c, j +
    # s]: sliding_window_view's view); inner[c] = its unpadded scores.
    step = score.itemsize
    # (An ndarray made on score's buffer: as_strided's view, without its ~4 us of Python.)
    win = np.ndarray((w, n, h), score.dtype, score, 0, (score.strides[0], step, step))
    inner = score[:, d : d + h]
    null_before = [0.0] * w  # Python floats: a list store per column is cheapest
    null_back = np.full(w, -1, dtype=np.intp)
    # cand[s] = previous column's score shifted by s - d, minus its cost; cand[n] = from no-bone.
    cand = np.empty((n + 1, h))
    shifts = cand[:n]
    from_null = cand[n]
    # The cost laid out as (shift, row): a ufunc with a broadcast (n, 1) operand, or with
    # the self-overlapping window as operand (numpy copies it first), costs 2-3x more
    # per call than a copy then an in-place subtract of same-shape arrays.
    cost = np.repeat(np.asarray(shift_cost, dtype=float)[:, None], h, axis=1)
    best = np.empty(h)
    null = 0.0
    from_null.fill(null - switch)  # refilled only when the no-bone score changes
    free = bool((shift_cost >= 0).all())  # no shift scores above its source row
    subtract, reduce_max = np.subtract, np.maximum.reduce
    # With costs >= 0 no score exceeds the sum of the columns' best gains (positive
    # part) so far: where that sum stays under half the switch cost (rounding is far
    # smaller), the no-bone score never rises from 0 and the column's maximum is never
    # needed (the shortcut it allows gives the full step's values). The same scores.
    if free and float(np.maximum(gain.max(axis=0), 0.0).sum()) <= 0.5 * switch:
        for wprev, cur in zip(win[:-1], inner[1:], strict=True):
            shifts[...] = wprev
            subtract(shifts, cost, out=shifts)
            reduce_max(cand, axis=0, out=best)
            cur += best
        w_loop = 1  # the general loop below has no column left
    else:
        w_loop = w
    for c, wprev, prev, cur in zip(
        range(1, w_loop), win[: w_loop - 1], inner[: w_loop - 1], inner[1:w_loop], strict=True
    ):
        null_before[c] = null
        jb = int(prev.argmax())
        top = prev.item(jb)
        if top < null - switch and free:
            # Every shift scores below leaving no-bone (costs are >= 0): the best
            # predecessor of every row is the no-bone state, exactly.
            cur += null - switch
            continue
        shifts[...] = wprev
        subtract(shifts, cost, out=shifts)
        reduce_max(cand, axis=0, out=best)  # the ufunc itself: no wrapper per call
        cur += best
        if top - switch > null:
            null = top - switch
            null_back[c] = jb
            from_null.fill(null - switch)
    last = score[w - 1, d : d + h]
    jb = int(last.argmax())
    state = jb if last[jb] > null else -1
    # Python scalars for the per-column lookups (the same double arithmetic).
    leave = [x - switch for x in null_before]
    back = null_back.tolist()
    cl = np.asarray(shift_cost, dtype=float).tolist()
    path = [-1] * w
    for c in range(w - 1, 0, -1):
        path[c] = state
        if state >= 0:
            # The best predecessor on Python floats (the same double subtractions; the
            # first of equal values, as argmax): cheaper than three numpy calls on a
            # handful of values (as in _optimal_paths).
            row = score[c - 1, state : state + n].tolist()
            k, peak = 0, row[0] - cl[0]
            for q in range(1, n):
                val = row[q] - cl[q]
                if val > peak:
                    k, peak = q, val
            state = -1 if leave[c] > peak else state + k - d
        else:
            state = back[c]
    path[0] = state
    return np.array(path, dtype=np.intp)


def _optimal_paths(
    gains: Sequence[np.ndarray],
    shift_cost: np.ndarray | Sequence[np.ndarray],
    switch: float,
    scratch: dict | None = None,
) -> list[np.ndarray]:
    """:func:`_optimal_path` of several gains at once (the same paths), one column loop for all.

    ``shift_cost``: one for all gains, or one per gain (each of odd size, shifts ``-d ..
    d``, symmetric and 0 for no shift, as :func:`_path_steps` makes them; each gain's
    path is the one :func:`_optimal_path` finds with its own). Costs of fewer shifts
    are padded to the most with ``+inf`` (a shift it cannot take scores ``-inf``, never
    the maximum: the same maxima).

    The column loop of one ~150-row gain is bound by its ~6 numpy calls per column, not
    by the arithmetic; stacking the gains of several frames makes each call do the work
    of all of them (16 frames: about half the time per gain). Each gain keeps its own
    size: rows past its height are ``-inf`` (as the window padding of one gain), columns
    past its width are never read back, and each gain's no-bone score is the one after
    its own last column. The column shortcut of :func:`_optimal_path` is not taken: it
    gives exactly what the full step gives (every shift scores below leaving no-bone,
    so the maximum is the no-bone score, and the no-bone score does not rise).

    ``scratch``: a dict the caller keeps between calls (e.g. the passes of one batch);
    the scores' array (~19 MB for 30 480x640 frames) is kept in it and reused when large
    enough: a fresh one costs its page faults at every call, as much as a fifth of the
    column loop.
    """
    m = len(gains)
    costs = (
        [np.asarray(shift_cost, dtype=float)] * m
        if isinstance(shift_cost, np.ndarray)
        else [np.asarray(c, dtype=float) for c in shift_cost]
    )
    if not all(np.array_equal(c, c[::-1]) and c[c.size // 2] == 0 for c in costs):
        raise ValueError("shift costs must be symmetric (-k as +k rows) and 0 for no shift")
    n = max(c.size for c in costs)
    d = n // 2
    own = costs  # each gain's own costs (the backtrack's)
    padded = np.full((n, m), np.inf)
    for i, ci in enumerate(costs):
        padded[(n - ci.size) // 2 : (n + ci.size) // 2, i] = ci
    hs = [g.shape[0] for g in gains]
    ws = [g.shape[1] for g in gains]
    hmax, wmax = max(hs), max(ws)
    # score[c, i, d + j]: best path of gain i ending at row j of column c.
    hp = hmax + 2 * d
    size = wmax * m * hp
    kept = scratch.get("score") if scratch is not None else None
    if kept is None or kept.size < size:
        kept = np.empty(size)
        if scratch is not None:
            scratch["score"] = kept
    score = kept[:size].reshape(wmax, m, hp)
    # -inf only where no gain is copied (each gain's padding rows, rows past its height
    # and columns past its width): the same array as filling it all first, without
    # writing the ~19 MB twice.
    for i, g in enumerate(gains):
        score[: ws[i], i, d : d + hs[i]] = g.T
        score[: ws[i], i, :d] = -np.inf
        score[: ws[i], i, d + hs[i] :] = -np.inf
        score[ws[i] :, i] = -np.inf
    # Each column's scores as one contiguous run of the gains' padded rows (gain after
    # gain, d rows of -inf between them): shift s of every row of every gain is one slice
    # of the run, so each numpy call runs over one long contiguous row. (Laid out as
    # (shift, gain, row) views, numpy's loops restart at every one of the m x n short
    # rows: 2-4x the time per element at 24 gains.) The d padding rows between two gains
    # are computed too (2 d per gain): their gain is -inf, so they stay -inf, and a
    # shift reaches at most d rows: a gain's rows never read another gain's.
    run = m * hp - 2 * d  # positions d .. m hp - d of a column's run
    flat = score.reshape(wmax, m * hp)
    inner = flat[:, d : d + run]
    # The shifts in pairs: -k and +k cost the same, and the larger of two scores less a
    # cost is the larger score less the cost (rounding keeps order): the maxima of the
    # better of each pair less its cost, of no shift (no cost: the score itself) and of
    # leaving no-bone are the same maxima (a third less arithmetic than every shift
    # less its cost). cand[k - 1]: the better of shifts -k, +k less its cost; cand[d]:
    # from no-bone.
    cand = np.empty((d + 1, run))
    shifts = cand[:d]
    from_null = cand[d]
    # Each position's cost per shift and no-bone score are its gain's.
    cost = np.repeat(padded[d + 1 :], hp, axis=1)[:, d : d + run]
    best = np.empty(run)
    top = np.empty(m)
    null = np.zeros(m)
    null_before = np.zeros((wmax + 1, m))  # row c: each no-bone score before column c
    rose = np.zeros((wmax, m), dtype=bool)  # the no-bone score rose at column c
    from_null.fill(-switch)
    subtract, reduce_max, maximum = np.subtract, np.maximum.reduce, np.maximum
    for c in range(1, wmax):
        null_before[c] = null
        reduce_max(score[c - 1], axis=1, out=top)
        prev = flat[c - 1]  # shift s of position q reads prev[q + d + s]
        for k in range(1, d + 1):
            maximum(prev[d - k : d - k + run], prev[d + k : d + k + run], out=shifts[k - 1])
        subtract(shifts, cost, out=shifts)
        reduce_max(cand, axis=0, out=best)
        maximum(best, prev[d : d + run], out=best)
        inner[c] += best
        up = top - switch > null
        if up.any():
            np.copyto(null, top - switch, where=up)
            rose[c] = up
            from_null[...] = (null - switch).repeat(hp)[d : d + run]
    null_before[wmax] = null
    # Backtrack each gain as _optimal_path does (the same comparisons on the same doubles).
    paths = []
    for i in range(m):
        w, h = ws[i], hs[i]
        sc = score[:, i]
        shift_cost = own[i]
        nv, cl = shift_cost.size, shift_cost.tolist()
        # The gain's own window: its d_i shifts either side, inside the d rows of padding.
        lo = d - shift_cost.size // 2
        nb = null_before[:, i].tolist()
        # Columns where the no-bone score rose, ascending (the only ones a no-bone
        # stretch can have been entered from).
        rose_at = np.flatnonzero(rose[:w, i]).tolist()
        path = np.full(w, -1, dtype=np.intp)
        last = sc[w - 1, d : d + h]
        jb = int(last.argmax())
        state = jb if last[jb] > nb[w] else -1
        c = w - 1
        while c > 0:
            if state >= 0:
                path[c] = state
                # The best predecessor on Python floats (the same double subtractions;
                # the first of equal values, as argmax): cheaper than three numpy calls
                # on a handful of values.
                row = sc[c - 1, lo + state : lo + state + nv].tolist()
                k, peak = 0, row[0] - cl[0]
                for q in range(1, nv):
                    val = row[q] - cl[q]
                    if val > peak:
                        k, peak = q, val
                state = -1 if nb[c] - switch > peak else state + k - (d - lo)
                c -= 1
            else:
                # No bone from column c back to the last column at or before it where
                # the no-bone score rose (path stays -1 there): left from the previous
                # column's best row; none such, no bone down to column 0. (The same
                # states as stepping column by column: the no-bone state stays where
                # its score did not rise.)
                q = bisect_right(rose_at, c) - 1
                if q < 0:
                    break
                c = rose_at[q]
                state = int(sc[c - 1, d : d + h].argmax())
                c -= 1
        if c == 0:
            path[0] = state
        paths.append(path)
    return paths


def _path_steps(ev: EvidenceMaps, p: ShadowPathParams) -> tuple[np.ndarray, int]:
    """The optimal path's cost per depth shift between neighbouring columns (``(2 n + 1,)``
    for shifts ``-n .. n`` rows: up to ``max_slope`` depth per lateral mm, quadratic in
    the slope) and the fewest working columns a contour may have (``min_length_mm``):
    one definition for every path of the per-frame step and of the guided search
    (:mod:`.recovery`)."""
    n_shift = max(1, ceil_px(p.max_slope * ev.dx / ev.dy))
    steps = np.arange(-n_shift, n_shift + 1)
    shift_cost = p.slope_penalty * (steps * ev.dy / ev.dx) ** 2 * ev.dx
    return shift_cost, max(2, ceil_px(p.min_length_mm / ev.dx))


def _groups(path: np.ndarray, ev: EvidenceMaps, p: ShadowPathParams) -> list[np.ndarray]:
    """Columns of each group of bone runs of ``path`` (short gaps with small steps merged)."""
    cols = np.flatnonzero(path >= 0)
    if cols.size == 0:
        return []
    breaks = (cols[1:] - cols[:-1] > 1).nonzero()[0]
    # (np.r_'s values, by np.concatenate: np.r_ costs ~5 us of Python per call.)
    starts = np.concatenate(([0], breaks + 1))
    ends = np.concatenate((breaks, [cols.size - 1]))
    groups: list[list[int]] = [[0]]
    for r in range(1, starts.size):
        a, b = cols[ends[r - 1]], cols[starts[r]]
        gap_mm = (b - a - 1) * ev.dx
        step_mm = abs(path[b] - path[a]) * ev.dy
        if gap_mm <= p.merge_gap_mm and step_mm <= p.merge_step_mm:
            groups[-1].append(r)
        else:
            groups.append([r])
    return [np.concatenate([cols[starts[r] : ends[r] + 1] for r in g]) for g in groups]


def _refine(
    image: np.ndarray,
    ev: EvidenceMaps,
    cols: np.ndarray,
    rows_w: np.ndarray,
    p: ShadowPathParams,
    sy: float,
) -> np.ndarray:
    """Sub-pixel ``(i, j)`` of the echo peak near working rows ``rows_w`` in columns ``cols``."""
    return _refine_many(image, ev, [(cols, rows_w)], p, sy)[0]


def _refine_many(
    image: np.ndarray,
    ev: EvidenceMaps,
    contours: list[tuple[np.ndarray, np.ndarray]],
    p: ShadowPathParams,
    sy: float,
) -> list[np.ndarray]:
    """:func:`_refine` of several contours ``(cols, rows_w)`` of one frame at once.

    Every step but the lateral median works column by column (the profile's smoothing
    runs along each column's own profile), so the columns of all of a frame's
    candidates are refined in one set of numpy calls (the same values as one call per
    contour); the lateral median then runs per contour, over its own ends.
    """
    sizes = [c.size for c, _ in contours]
    cols = np.concatenate([c for c, _ in contours])
    rows_w = np.concatenate([r for _, r in contours])
    hh_full = ev.colmean.shape[0]
    centre = (rows_w + 0.5) * ev.fy - 0.5
    half = mm_to_px(p.refine_mm, sy)
    sig = p.refine_sigma_mm / sy
    pad = int(np.ceil(3 * sig)) if sig >= 0.5 else 0
    off = np.arange(-half - pad - 1, half + pad + 2)
    rows = _clip_rows(np.rint(centre).astype(np.intp)[:, None] + off[None, :], 0, hh_full - 1)
    prof = ev.colmean[rows, cols[:, None]]
    if pad:
        prof = gaussian_filter1d(prof, sig, axis=1, mode="nearest")
    core = slice(pad + 1, pad + 2 * half + 2)
    k = prof[:, core].argmax(axis=1) + pad + 1
    r = np.arange(cols.size)
    y0, y1, y2 = prof[r, k - 1], prof[r, k], prof[r, k + 1]
    denom = y0 - 2 * y1 + y2
    frac = np.where(denom < 0, 0.5 * (y0 - y2) / np.where(denom < 0, denom, -1.0), 0.0)
    j_all = rows[r, k] + np.clip(frac, -0.5, 0.5) + p.surface_offset_mm / sy
    i_all = (cols + 0.5) * ev.fx - 0.5
    # Lateral median over ~0.6 mm: removes single-column speckle jumps.
    size = max(1, int(round(0.6 / ev.dx)) | 1)
    out = []
    start = 0
    for n in sizes:
        j, i = j_all[start : start + n], i_all[start : start + n]
        start += n
        if size == 3 and j.size >= 3:
            # The usual size: the median of three is one of them, so min/max give
            # exactly ``median_filter(j, 3, mode="nearest")`` without scipy's per-call
            # cost.
            pj = np.concatenate((j[:1], j, j[-1:]))
            a, b, c = pj[:-2], pj[1:-1], pj[2:]
            j = np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))
        elif size > 1 and j.size >= size:
            j = median_filter(j, size=size, mode="nearest")
        out.append(np.column_stack([i, j]))
    return out


def _is_copy(deep: np.ndarray, shallow: np.ndarray, depth0: float, tol: float) -> bool:
    """``deep`` (rows) lies at twice the depth of ``shallow`` (rows), column by column.

    ``depth0`` is the row of the probe face (0): the echo of a reflector at depth ``d``
    that bounces once more off the probe face arrives as if from ``2 d``.
    """
    ratio = (deep - depth0) / np.maximum(shallow - depth0, 1e-6)
    # Column by column, not on average: an arc that happens to lie at about twice the
    # depth of a flat fascia on the whole is no copy of it.
    # np.percentile's value read from the sorted values (sorted_row_percentiles: the
    # same operations, without np.percentile's ~150 us of checks per call).
    dev = np.abs(ratio - 2.0)
    dev.sort()
    return bool(sorted_row_percentiles(dev[None, :], (90.0,))[0, 0] <= 2.0 * tol)


def _fov_px(ev: EvidenceMaps) -> tuple[float, float] | None:
    """First and last image columns of ``ev``'s field of view (None if empty)."""
    cols = np.flatnonzero(ev.usable if ev.fov is None else ev.fov)
    if cols.size == 0:
        return None
    return float(cols[0] * ev.fx), float((cols[-1] + 1) * ev.fx - 1)


def _clip_rows(rows: np.ndarray, lo: int, hi: int) -> np.ndarray:
    """``np.clip(rows, lo, hi)`` of integer rows (the same values): two ufuncs, without
    ``np.clip``'s layers of Python wrappers (~80 calls per frame)."""
    return np.minimum(np.maximum(rows, lo), hi)


def _runs(idx: np.ndarray) -> list[np.ndarray]:
    """``np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)`` of ascending indices: the
    runs of consecutive ones, as views of ``idx`` (the same arrays), without
    ``np.split``'s ~30 us of Python per call (a few tens of calls per frame)."""
    cut = ((idx[1:] - idx[:-1] > 1).nonzero()[0] + 1).tolist()
    return [idx[a:b] for a, b in zip([0, *cut], [*cut, idx.size], strict=True)]


def _dense_rows(cands: list[dict], width: int | None = None) -> None:
    """Give each candidate ``dense``: its row per working column, NaN where it is absent
    (``width`` columns; None: up to the last column any candidate reaches)."""
    w = max(int(c["cols"][-1]) for c in cands) + 1 if width is None else width
    for c in cands:
        d = np.full(w, np.nan)
        d[c["cols"]] = c["rows"]
        c["dense"] = d


def _present(c: dict) -> np.ndarray:
    """``~isnan(c["dense"])``, kept with the array it was made from: candidates are
    compared pairwise thousands of times per sweep, the mask is made once per candidate."""
    d = c["dense"]
    kept = c.get("present")
    if kept is None or kept[0] is not d:
        kept = c["present"] = (d, ~np.isnan(d))
    return kept[1]


def _common(a: dict, b: dict) -> np.ndarray:
    """Columns (ascending) where both candidates lie (``_dense_rows`` first)."""
    return (_present(a) & _present(b)).nonzero()[0]


def _mark_reverberations(cands: list[dict], p: ShadowPathParams) -> None:
    """Flag candidates that are reverberation copies of a shallower, overlapping one."""
    tol = p.reverb_tolerance
    for c in cands:
        for s in cands:
            if s is c:
                continue
            # A copy lies under its original (it is never wider) and is fainter. (The
            # cheap tests first: s's own width bounds the columns in common.)
            if c["grey"] > s["grey"] or s["cols"].size < 0.8 * c["cols"].size:
                continue
            common = _common(c, s)
            if common.size < 0.8 * c["cols"].size:
                continue
            dc, ds = c["dense"][common], s["dense"][common]
            if median1d(dc - ds) <= 0:
                continue  # s is not above c
            if _is_copy(dc, ds, -0.5, tol):
                c["reverb"] = True
                break
            # Equal spacing: a third line at the same offset (s, c, then c + offset).
            off = dc - ds
            med_off = median1d(off)
            if np.std(off) > tol * med_off + 1:
                continue  # not parallel: not a copy
            for t in cands:
                if t is c or t is s:
                    continue
                cm = _common(t, c)
                if cm.size < 0.5 * c["cols"].size:
                    continue
                off2 = t["dense"][cm] - c["dense"][cm]
                if abs(median1d(off2) - med_off) <= tol * med_off + 1:
                    c["reverb"] = True
                    t["reverb"] = True
            if c.get("reverb"):
                break


def _without_lumens(lr: np.ndarray, ev: EvidenceMaps, p: ShadowPathParams) -> np.ndarray:
    """``lr`` with every vessel lumen read as tissue (0), for the tests of what lies in a
    shadow (:func:`_mark_echo_beneath`).

    A lumen returns almost nothing, as a shadow does, but it is no shadow: a round
    region darker than ``lumen_ratio`` of the tissue at its depth, ``lumen_mm`` high and
    wide (height and width within a factor 2 of each other, filling half its box), closed
    on every side (inside the usable columns, under the near field, above the last row),
    with tissue beside it (1 mm each side at its depths, on median not darker than
    ``under_ratio``: the level a shadow is told by) and the tissue right under it (1 mm,
    column by column) brighter than the typical on median: posterior enhancement, the
    sound that crossed the fluid unattenuated. A shadow has only more shadow under it and
    beside a dark patch in it, and runs on down to the image's bottom or across a bone's
    width. Without this, a vessel lying a few mm over the bone read as the shadow the
    bone "lies in" (the L14 grey-shadow copy with a vessel 1 mm over it: in frames 3 and
    12 the region over the bone read 0.76-0.77 of the tissue level, under 0.8, and the
    track lay on a layer 21 mm off in every frame).

    Levels are the frame's own (``lr`` is relative to the tissue at each depth); sizes in
    mm: no grey level enters.
    """
    if p.lumen_ratio <= 0:
        return lr
    from scipy.ndimage import find_objects, label

    h, w = lr.shape
    top = ev.field_top + mm_to_px(p.near_field_mm, ev.dy, minimum=0)
    dark = lr < np.float32(np.log(p.lumen_ratio))
    dark[:top] = False
    dark[:, ~ev.usable] = False
    lab, n = label(dark)
    if n == 0:
        return lr
    lo, hi = p.lumen_mm
    areas = np.bincount(lab.ravel(), minlength=n + 1)
    least = 0.5 * (lo / ev.dx) * (lo / ev.dy)
    under = mm_to_px(1.0, ev.dy)
    side = mm_to_px(1.0, ev.dx)
    tissue = float(np.log(p.under_ratio))
    big = np.flatnonzero(areas >= least)
    big = big[big > 0]  # label 0 is the background
    if big.size == 0:
        return lr
    # Speckle makes thousands of small dark patches per frame, tens of a lumen's least
    # area: only those are numbered 1 .. len(big) (the rest 0) for scipy's find_objects
    # (on every patch it builds a slice each: ~2 ms a frame; on these, ~0.2 ms, half
    # the time of taking the boxes from their pixels), their shape and place tested on
    # arrays, and the few left looked at one by one.
    renum = np.zeros(n + 1, lab.dtype)
    renum[big] = np.arange(1, big.size + 1)
    boxes = find_objects(renum[lab], big.size)  # each has pixels: no None
    big = big.astype(lab.dtype)
    r0, r1, c0, c1 = (
        np.array([b[axis].start if end else b[axis].stop for b in boxes], np.intp)
        for axis, end in ((0, True), (0, False), (1, True), (1, False))
    )
    height, width = (r1 - r0) * ev.dy, (c1 - c0) * ev.dx
    unusable = np.concatenate([[0], np.cumsum(~ev.usable)])
    ok = (
        (height >= lo)
        & (height <= hi)
        & (width >= lo)
        & (width <= hi)
        & (height <= 2.0 * width)
        & (width <= 2.0 * height)
        & (areas[big] >= 0.5 * (r1 - r0) * (c1 - c0))  # not a ragged region
        & (r0 > top)  # closed: not open to the near field or the image's edges
        & (r1 + under <= h)
        & (c0 >= side)
        & (c1 + side <= w)
    )
    # ... nor to a margin or an uncoupled edge (no unusable column within 1 mm).
    ok[ok] &= unusable[c0[ok]] == unusable[c0[ok] - side]
    ok[ok] &= unusable[c1[ok] + side] == unusable[c1[ok]]
    out = None
    for k, a, b, c, d in zip(
        big[ok].tolist(),
        r0[ok].tolist(),
        r1[ok].tolist(),
        c0[ok].tolist(),
        c1[ok].tolist(),
        strict=True,
    ):
        # Tissue on both sides at its depths, not a shadow's grey (a dark patch in a
        # bone's shadow has shadow beside it).
        flanks = np.concatenate([lr[a:b, c - side : c], lr[a:b, d : d + side]], axis=1)
        if median1d(flanks) <= tissue:
            continue
        m = lab[a:b, c:d] == k
        cols = np.flatnonzero(m.any(axis=0))
        last = a + m.shape[0] - 1 - np.argmax(m[::-1, cols], axis=0)
        rows = last[None, :] + np.arange(1, under + 1)[:, None]
        if median1d(lr[rows, c + cols[None, :]]) <= 0:
            continue  # no enhancement under it: a shadow's dark
        if out is None:
            out = lr.copy()
        out[a:b, c:d][m] = 0.0
    return lr if out is None else out


def _log_ratio(ev: EvidenceMaps) -> np.ndarray:
    """``log(work / tissue_beside(row))`` less the frame's ``log_tissue_ratio``, (h, w).

    Plain tissue is ~0 in it at any gain and depth; a shadow is negative, an echo
    positive.
    """
    lr = np.log(ev.work + np.float32(_EPS))
    lr -= (np.log(ev.tissue_beside + np.float32(_EPS)) + np.float32(ev.log_tissue_ratio))[:, None]
    return lr


def _underside_profile(
    lr: np.ndarray, c: dict, reach: int, only: np.ndarray | None = None
) -> np.ndarray:
    """The log ratio ``lr`` along ``c`` shifted by ``-reach .. reach`` rows, shape (2 reach + 1,).

    Row ``reach + k`` is the median over ``c``'s columns (those in ``only``, if given)
    of ``lr`` at ``k`` rows under (``k < 0``: above) the contour, following its shape:
    lines parallel to it (its reverberation copies) stand out of the speckle, which
    the median over tens of columns averages away. NaN where the shifted contour
    leaves the image on most columns.
    """
    h = lr.shape[0]
    cols, rows = c["cols"], c["rows"]
    if only is not None:
        m = np.isin(cols, only, assume_unique=True)
        cols, rows = cols[m], rows[m]
    if cols.size == 0:
        return np.full(2 * reach + 1, np.nan)
    if cols.size > 48:  # every n-th column: enough for a median, bounded cost
        step = int(np.ceil(cols.size / 48))
        cols, rows = cols[::step], rows[::step]
    k = np.arange(-reach, reach + 1)
    mid = cols.size // 2
    w = lr.shape[1]
    if int(rows.min()) >= reach and int(rows.max()) + reach < h:
        # Every shifted row inside the image (the usual case): no clipping, no NaN, and
        # the flat indices as the contour's own plus a row's length per shift (the same
        # indices; a few numpy calls fewer on ~100 x 48 values).
        lw = np.ravel(lr).take((rows * w + cols)[None, :] + (k * w)[:, None])
        lw.partition(mid, axis=1)
        return lw[:, mid].astype(float)
    rr = rows[None, :] + k[:, None]
    # Rows past the image repeat its edge; the median is NaN where most of them are.
    # (Gathered by flat index: half the time of the 2-D fancy index, the same values.)
    lw = np.ravel(lr).take(_clip_rows(rr, 0, h - 1) * w + cols)
    lw.partition(mid, axis=1)  # a fresh gather: partitioned in place (no wrapper, no copy)
    prof = lw[:, mid].astype(float)
    # "Under half of the columns inside", counted in integers (mean < 0.5 exactly).
    prof[2 * ((rr >= 0) & (rr < h)).sum(axis=1) < cols.size] = np.nan
    return prof


def _own_profile(c: dict, lr: np.ndarray, reach: int) -> np.ndarray:
    """:func:`_underside_profile` of a candidate along its own shape over all its
    columns, made once and kept in ``c["prof"]`` (the series and the shadow tests read
    it; dropped where the map it was read on changes)."""
    if "prof" not in c:
        c["prof"] = _underside_profile(lr, c, reach)
    return c["prof"]


def _profile_peaks(prof: np.ndarray, reach: int) -> tuple[np.ndarray, np.ndarray]:
    """``prof`` with NaN as -10, and the offsets of its local maxima brighter than tissue."""
    # np.nan_to_num's values (its wrapper costs ~5x the work on a profile's ~100 values;
    # an infinite value, never seen, is left to it).
    v = np.where(np.isnan(prof), -10.0, prof)
    if np.isinf(v).any():
        v = np.nan_to_num(prof, nan=-10.0)
    is_peak = np.zeros(v.size, bool)
    is_peak[1:-1] = (v[1:-1] >= v[:-2]) & (v[1:-1] > v[2:]) & (v[1:-1] > 0)
    return v, is_peak.nonzero()[0] - reach


def _series(
    vp: tuple[np.ndarray, np.ndarray],
    reach: int,
    min_px: int,
    dark: float,
    tol: float,
    *,
    strict: bool,
) -> list[int]:
    """Offsets (rows) of an equally spaced series of lines in a profile.

    ``vp`` is :func:`_profile_peaks` of an :func:`_underside_profile`.

    A member is a local maximum of the profile brighter than the tissue (> 0);
    consecutive members lie ``d`` apart, ``d`` the same for the whole series within
    ``tol`` (relative) + 1 row. A series has three members or more, and the troughs
    between its members are, on average, darker than ``dark`` (a log ratio): the sound
    between reverberation copies comes back from nothing, shadow not tissue (layers of
    soft tissue have tissue between them).

    ``strict`` (the profile follows the reflector's own shape, so its copies are
    parallel to it and sharp in the profile): offset 0 must be the top, no line
    between two members is brighter than the upper one, every trough is darker than the tissue
    over the top and their mean by ``dark`` more (soft tissue layers have the same
    tissue between them as above them), and the series
    must fade: each copy is no brighter than the line above it (part of the sound is
    lost at every bounce), beyond the speckle left in the profile (0.15 in log; the
    deepest member is exempt, the far cortex may lie where it falls), and the top is
    the brightest. Without, the profile may follow another line's shape (a far cortex,
    whose shape the copies do not share, lying anywhere under them), so the series is
    sought among the lines above offset 0, which may or may not be a member,
    brightness is not judged, and the troughs need only be darker than half of
    ``dark`` on average (a profile along another line's shape blurs them; a top found
    so is confirmed strictly from its own profile).

    Returns the members' offsets, shallowest first, or ``[0]`` when there is no series.
    """
    v, peaks = vp
    # Plain Python on the handful of peaks and the profile's values (the same float64
    # values, the same comparisons): ~1,000 calls per sweep, where numpy's per-call
    # cost outweighs the work.
    plist = peaks.tolist()
    # A series needs two lines besides the top (strict: below offset 0; loose: three
    # above it): most profiles stop here.
    if strict:
        if sum(q >= min_px for q in plist) < 2:
            return [0]
    elif sum(q <= -min_px for q in plist) < 3:
        return [0]
    vl = v.tolist()
    lids: list[float | None] = []  # valid()'s tissue level over the top, once made

    def step_from(k: int, d: float, sign: int) -> int | None:
        # The nearest peak to ``want``, the shallower of two as near, within the
        # tolerance: ``plist`` is ascending, so only the peaks either side of ``want``
        # can be nearest (bisection: the profile's ~20 peaks are not all read at each
        # of the ~8,000 steps a sweep takes).
        want = k + sign * d
        err = tol * d + 1.0 + 1e-9
        i = bisect_left(plist, want)
        best = None
        if i > 0 and abs(plist[i - 1] - want) < err:
            best, err = plist[i - 1], abs(plist[i - 1] - want)
        if i < len(plist) and abs(plist[i] - want) < err:
            best = plist[i]
        return best if best is not None and (best - k) * sign >= min_px else None

    def chain(start: int, d: float, signs: tuple[int, ...]) -> list[int]:
        members = [start]
        for sgn in signs:
            k = start
            while (nxt := step_from(k, d, sgn)) is not None and nxt <= 0:
                members.append(nxt)
                k = nxt
        return sorted(set(members))

    def valid(members: list[int]) -> bool:
        if len(members) < 3:
            return False
        m = [q + reach for q in members]
        troughs = [min(vl[a + 1 : b]) for a, b in zip(m[:-1], m[1:], strict=True)]
        if len(troughs) < 8:
            # np.mean's value: under 8 values numpy adds them in order (its pairwise
            # sum starts at 8); a loop, not sum() (Python 3.12's is compensated).
            total = 0.0
            for t in troughs:
                total += t
            mean_trough = total / len(troughs)
        else:
            mean_trough = float(np.mean(troughs))
        if mean_trough >= (dark if strict else 0.5 * dark):
            return False
        if not strict:
            return True
        # The troughs are shadow: darker than the tissue over the reflector, every one
        # (soft-tissue layers have the same tissue between them as above them).
        # (The tissue's level is the profile's alone: made once per profile, not again
        # for each chain tried.)
        if not lids:
            cover = v[max(0, reach - reach // 2) : max(1, reach - min_px)]
            cover = cover[cover > -10.0]
            lids.append(median1d(cover) if cover.size else None)
        lid = lids[0]
        if lid is None:
            return False
        if mean_trough >= lid + dark or max(troughs) >= lid:
            return False
        if troughs[0] >= dark:
            return False
        # Only shadow between copies: no line between two members brighter than
        # either (a brighter layer between them is tissue, not a gap in a shadow; and
        # a copy is the brightest return since its reflector, nothing came back
        # between them: S radius s101, reverberation 0.45, frames 22-25, a layer 2.8
        # mm over the bone passed for a top with "copies" at 0.06 and 0.02 over a long
        # spacing, the bone's own echo, 0.21, between it and the first).
        # Offset 0 is the candidate's traced row, which may lie a row off its own
        # echo's crest: a peak one row under it is the top's own echo, not a line
        # between, and the top's value is its crest's (S humerus grey s709, frame 32:
        # the bone's row 0.86, its crest a row down 0.90, read as a brighter line
        # between it and its first copy at 0.52, so no series, no inherited strength,
        # and the track took a fascia leaving the crest, 1.96 mm off).
        crest = max(vl[max(0, reach - 1) : reach + 2])
        val = {q: (crest if q == 0 else vl[q + reach]) for q in members}
        for a, b in zip(members[:-1], members[1:], strict=True):
            inner = [vl[q + reach] for q in plist if a < q < b and not (a == 0 and q == 1)]
            if inner and max(inner) > min(val[a], val[b]) + 0.05:
                return False
        vals = [val[q] for q in members]
        # The deepest member is exempt from fading: the far cortex may lie where the
        # last copy falls (it is still dimmer than the top).
        fades = all(y - x <= 0.15 for x, y in zip(vals[:-2], vals[1:-1], strict=True))
        return fades and vals[0] >= max(vals) - 0.05

    def continues_up(d: float) -> bool:
        """Whether the series goes on above offset 0: a line one spacing over it, at
        least as bright (within the fading's 0.15), with shadow (a trough darker than
        half of ``dark``: the reflector's echo tail blurs the first trough, -0.33
        between the grey radius s71's top and first copy, -1.4 to -2.3 under the copy)
        between. Then 0 is a copy, not the reflector: the reflector has
        tissue over it, its first copy has the shadow and the reflector's own echo
        (which a shorter series under the copy would otherwise pass for a top). A
        fainter line over a dark layer is tissue over the bone, not its reflector."""
        up = step_from(0, d, -1)
        return (
            up is not None
            and vl[up + reach] >= vl[reach] - 0.15
            and min(vl[up + reach + 1 : reach]) < 0.5 * dark
        )

    if strict:
        # From offset 0 down, the spacing set by one of the nearest lines below (the
        # nearest may be speckle or the echo's own tail).
        for q in sorted(q for q in plist if q >= min_px)[:3]:
            members = [0]
            k = 0
            while (nxt := step_from(k, float(q), 1)) is not None:
                members.append(nxt)
                k = nxt
            # The longest valid run from the top: the chain may run on past the
            # series' end onto a line that is no copy (the far cortex where the last
            # copy falls, brighter than the copy over it), which fails the whole
            # chain but not the copies above it (S clavicle grey s109, frames 37-39:
            # top 0.95, copies 0.53 / 0.59 / 0.63 over troughs -1.1 to -2.5, the far
            # cortex 0.91 four rows under the third copy: the near cortex had no
            # candidate and the far cortex was the frames' only one).
            for n in range(len(members), 2, -1):
                if valid(members[:n]):
                    return members[:n] if not continues_up(float(members[1])) else [0]
        return [0]
    # Loose: a series among the lines above offset 0 (0 itself may be a copy or lie
    # under the series, as a far cortex does), the spacing set by a line and the next
    # one above it; the longest series wins.
    above = sorted((q for q in plist if q <= -min_px), reverse=True)  # nearest first
    best: list[int] = [0]
    for i, q in enumerate(above[:4]):
        nxt_up = [u for u in above[i + 1 :] if u <= q - min_px]
        if not nxt_up:
            continue
        d = float(q - nxt_up[0])
        members = chain(q, d, (-1, 1))
        # (Only a longer series can win: valid() is a pure test, asked only then.)
        if len(members) > len(best) and valid(members):
            best = members
    return best


def _trace_band(
    ev: EvidenceMaps,
    cols: np.ndarray,
    base: np.ndarray,
    rw: int,
    shift_cost: np.ndarray,
    lr: np.ndarray,
    half: int,
    dark: float,
) -> np.ndarray:
    """Rows of a reverberation series' top within ``rw`` rows of ``base`` over ``cols``.

    An optimal path (the passes' slope costs) through the echo z-score (positive part)
    in that band, so the line is followed continuously: a per-column maximum hops
    between the reflector, a layer over it and a copy under it wherever the band holds
    more than one (the band comes from another line's shape, which fits the reflector
    at its middle, not at its flanks). Rows whose trough half a spacing (``half`` rows)
    under them is not darker than ``dark`` (log ratio ``lr`` to the tissue beside, over
    three rows) count a fifth: the reflector of a series has its copies' shadow right
    under it (the series' own definition, :func:`_series`), a layer over it has tissue
    or the reflector there. Both levels are the series' own, measured in the frame.
    """
    h = ev.echo_z.shape[0]
    r0, r1 = max(0, int(base.min()) - rw), min(h, int(base.max()) + rw + 1)
    # (In place on fresh arrays, a few tens of rows by columns: the per-call cost of the
    # temporaries dominates; the same float32 then float64 operations.)
    g = ev.echo_z[r0:r1].take(cols, axis=1)
    np.maximum(g, 0, out=g)
    gain = g.astype(float)
    gain *= ev.dx
    gain += 1e-3
    rr = np.arange(r0, r1)[:, None]
    if r0 + half >= 1 and r1 + half <= h - 1:
        # The trough rows r + half lie inside (the usual case): three row slices of
        # ``lr``'s block, summed in float32 in the same order as below.
        k = r1 - r0
        blk = lr[r0 + half - 1 : r1 + half + 1].take(cols, axis=1)
        trough = blk[:k] + blk[1 : k + 1]
        trough += blk[2:]
        trough /= 3.0
    else:
        t = _clip_rows(rr + half, 1, h - 2)
        # The trough rows ``t`` are consecutive (clipped at the ends): ``lr``'s columns
        # are gathered once over their span, then rows taken from that block (the same
        # values).
        t0 = int(t[0, 0]) - 1
        blk = lr[t0 : int(t[-1, 0]) + 2][:, cols]
        ti = t[:, 0] - t0
        trough = (blk[ti - 1] + blk[ti] + blk[ti + 1]) / 3.0
    # A fifth where the trough is not dark (x 1.0 elsewhere: the value itself).
    np.multiply(gain, 0.2, out=gain, where=~(trough < dark))
    gain[np.abs(rr - base) > rw] = -1e3  # outside the band
    n = cols.size
    if n >= 8:
        # Every other column (the better row of each pair, slope costs doubled; rows
        # in between interpolated): half the path's work (speed), and a reflector's
        # shape barely changes over two columns.
        m = n // 2
        pair = np.maximum(gain[:, 0 : 2 * m : 2], gain[:, 1 : 2 * m : 2])
        path = _optimal_path(pair, shift_cost * 2.0, 1e6)
        ok = path >= 0
        if ok.sum() >= 2:
            x = np.arange(m) * 2 + 0.5
            rows = np.rint(np.interp(np.arange(n), x[ok], path[ok] + r0)).astype(np.intp)
            inb = np.abs(rows - base) <= rw
            return np.where(inb, rows, _clip_rows(base, 0, h - 1))
    # A switch cost no path pays: the top runs over all of the columns.
    path = _optimal_path(gain, shift_cost, 1e6)
    return np.where(path >= 0, path + r0, _clip_rows(base, 0, h - 1))


def _extend_top(
    ev: EvidenceMaps,
    lr: np.ndarray,
    cols: np.ndarray,
    rows: np.ndarray,
    half: int,
    dark: float,
    p: ShadowPathParams,
) -> tuple[np.ndarray, np.ndarray]:
    """A series' top made from a copy's columns, continued past them along its own echo.

    A copy spans only the part of the reflector its sound came back from (the copies
    of a convex bone fade and narrow out on its sides), so a top made over the copy's
    columns stops short of the bone's flanks, and the flank tracer (:mod:`.flanks`)
    need not take over from there: under the top lie the copies, not shadow, so its
    echo counts single there. Each end is followed column by column outward
    (:func:`_trace_top_end`) from the middle half of the top, where the copy's shape
    fits the reflector (out on the sides a copy curves down more than its reflector,
    and the band traced along it may hook down there), or, where that trace stops
    short of the copy's end, from the end itself.
    """
    n = cols.size
    q = n // 4
    parts: list[tuple[int, list[tuple[int, int]]]] = []  # per side: kept index, trace
    for side, inner, end in ((-1, q, 0), (1, n - 1 - q, n - 1)):
        got = _trace_top_end(ev, lr, cols, rows, inner, side, half, dark, p) if q else []
        if not got or (got[-1][0] - cols[end]) * side <= 0:
            inner = end
            got = _trace_top_end(ev, lr, cols, rows, end, side, half, dark, p)
        parts.append((inner, got))
    (a, left), (b, right) = parts
    left = left[::-1]
    cc = [g[0] for g in left] + cols[a : b + 1].tolist() + [g[0] for g in right]
    rr = [g[1] for g in left] + rows[a : b + 1].tolist() + [g[1] for g in right]
    return np.asarray(cc, dtype=np.intp), np.asarray(rr, dtype=np.intp)


def _trace_top_end(
    ev: EvidenceMaps,
    lr: np.ndarray,
    cols: np.ndarray,
    rows: np.ndarray,
    at: int,
    side: int,
    half: int,
    dark: float,
    p: ShadowPathParams,
) -> list[tuple[int, int]]:
    """``(column, row)`` of a series' top (``cols``, ``rows``) followed outward
    (``side`` -1: towards smaller columns) from its point ``at``.

    Column by column while the reflector's defining evidence holds: an echo above the
    tissue over it (echo z > 0) with the series' dark trough half a spacing (``half``
    rows) under it (``lr`` below ``dark`` over three rows; beside the bone lies tissue,
    not a trough), and while it stays convex seen from the probe: outward it only
    descends, each step at most one row less steep than the last, up to
    ``series_extend_deg``; past that the flank tracer (:mod:`.flanks`) takes over with
    its stop rule measured on the frame's speckle. One failing column is bridged, two
    end the trace; columns without contact are stepped over (no evidence either way),
    up to ``merge_gap_mm``. Levels are the series' own, measured in the frame.
    """
    h, w = ev.echo_z.shape
    down = max(1, ceil_px(np.tan(np.radians(p.series_extend_deg)) * ev.dx / ev.dy))
    skip = mm_to_px(p.merge_gap_mm, ev.dx)
    c, r = int(cols[at]), int(rows[at])
    r_in = int(rows[min(max(at - 3 * side, 0), cols.size - 1)])
    step = max(0, int(round((r - r_in) / 3.0)))  # the descent per column at the start
    got: list[tuple[int, int]] = []
    misses = skipped = 0
    usable, echo = ev.usable, ev.echo_z
    while misses < 2 and skipped <= skip:
        c += side
        if c < 0 or c >= w:
            break
        if not usable[c]:
            skipped += 1
            continue
        skipped = 0
        # The candidate rows (a handful) one by one on numpy float32 scalars: the same
        # float32 sums and comparisons as on arrays, without a dozen numpy calls per
        # column. The first of equal echoes wins, as argmax (a NaN first of all).
        last = min(r + down, h - half - 2)  # the trough's rows inside the image
        if r + max(0, step - 1) > last:
            break
        at, best = -1, -np.inf
        for q in range(r + max(0, step - 1), last + 1):
            t = q + half
            trough = (lr[t - 1, c] + lr[t, c] + lr[t + 1, c]) / 3.0
            e = echo[q, c] if trough < dark else -np.inf
            if e != e:  # NaN: argmax's pick, and no echo > 0
                at, best = q, e
                break
            if at < 0 or e > best:
                at, best = q, e
        if best > 0:
            step, r = at - r, at
            got.append((c, r))
            misses = 0
        else:
            misses += 1  # bridged: the next column is searched from the same row
    return got


def _curves_down(rows: np.ndarray) -> bool:
    """Whether a contour (rows per column) is deeper in its middle third than at its
    ends (a bowl seen from the probe: the back wall of a convex bone, not its front)."""
    n = rows.size
    e = max(1, n // 6)
    return n >= 6 and median1d(rows[n // 3 : n - n // 3]) > median1d(
        np.concatenate((rows[:e], rows[-e:]))
    )


def _mirrored(c: dict) -> dict:
    """``c``'s columns with its shape mirrored in depth (same top and bottom rows).

    The shape hypothesis for the near cortex when ``c`` is the far one: a convex
    cross-section's back wall curves the other way from its front. Only a hypothesis:
    a top made along it must still be confirmed from its own profile.
    """
    rows = c["rows"].min() + c["rows"].max() - c["rows"]
    dense = np.full(c["dense"].size, np.nan)
    dense[c["cols"]] = rows
    return {"cols": c["cols"], "rows": rows, "dense": dense}


def _kept_top(t: dict, ev: EvidenceMaps, p: ShadowPathParams) -> dict:
    """A series' top made by :func:`_mark_series` (``cols``, ``rows``, ``echo``, ``dense``
    and what its tests kept) with its strength, shadow and grey, keys in the order the
    pass candidates have."""
    rows, cols = t["rows"], t["cols"]
    sc = ev.score[rows, cols]
    out = {
        "cols": cols,
        "rows": rows,
        "strength": float((sc - p.null_z).sum() * ev.dx),
        "shadow": median1d(ev.shadow_z[rows, cols]),
        "grey": median1d(ev.work[rows, cols]),
    }
    out.update(t)  # echo, dense, then the profile and peaks confirmed() kept
    return out


def _mark_series(
    cands: list[dict], ev: EvidenceMaps, lr: np.ndarray, p: ShadowPathParams
) -> list[dict]:
    """Reverberation series: the top line is the reflector, the lines under it its copies.

    Sound caught between a strong specular reflector (bone, whose acoustic impedance
    is about twice soft tissue's) and the probe face, or inside the cortex, returns
    as copies of the echo at equal depth steps under it, with shadow (nothing) between
    them: a stack of three or more equally spaced, fading lines over dark troughs
    (:func:`_series`) is one reflector and its copies, wherever and whatever the grey
    levels. Soft-tissue layers that happen to lie at equal depths have tissue, not
    shadow, between them, so they never form a series.

    A series is first seen from any candidate's profile (loosely: the candidate may be
    a far cortex, not parallel to the copies), then confirmed strictly from its top's
    own profile (parallel copies, fading, the top brightest). The top is an existing
    candidate at the series' offset, or one made by moving the candidate's shape up to
    the strongest echo within half a spacing per column (a pass may have taken only
    the copies, whose shadow beneath is darker than the reflector's). A candidate that
    curves down (a bowl: the far cortex, the back wall of a convex bone) is also read
    along its mirror image, the shape of the bone's front and so of the copies
    (:func:`_mirrored`), up to the near field (the near cortex lies a bone's thickness
    over it) and, failing that, over its middle half; its own echo, not being a copy,
    does not veto the top (``copy_echo_ratio``); the top is traced along the echo in its band
    (:func:`_trace_band`) and, made over a copy's columns, followed on past them along
    its own echo (:func:`_extend_top`: a copy spans only part of its reflector); a top
    so traced onto a line a pass found already is that line. When the shallowest
    member of a loose series is no confirmed top (a speckle peak of the tissue over the
    bone, with tissue under it) the next one down is tried, never past a member with
    shadow under it; when the next member down (past the echo's tail) is a confirmed
    top too, with more echo, it is the reflector (a copy returns less). The top must be
    a first interface: below the near field (gel, skin, lens echoes), with tissue, not
    shadow, right above it (the 1.5-3 mm over it, where a far cortex has a copy or a
    trough; higher, a layer of darker tissue under the skin over a shallow bone reads
    as dark too; shadow there is as dark as the series' own troughs, a darker muscle
    layer is not), and shadow right under it (its first trough). The top's row may lie
    a row off its echo's crest: the crest is its own echo (:func:`_series`). The copies
    are flagged ``reverb`` (never chosen) and the top
    gets the strongest member's strength (the whole stack is its evidence). Returns
    the candidates with such tops added.
    """
    reach = mm_to_px(p.far_shadow_mm, ev.dy)
    min_px = max(2, mm_to_px(p.series_min_mm, ev.dy))
    dark = float(np.log(p.series_trough_ratio))
    h = ev.work.shape[0]
    nf = ev.field_top + mm_to_px(p.near_field_mm, ev.dy, minimum=0)
    gap = mm_to_px(p.shadow_gap_mm, ev.dy, minimum=1)
    shift_cost = _path_steps(ev, p)[0]
    sup = mm_to_px(p.suppress_mm, ev.dy)
    added: list[dict] = []

    def confirmed(t: dict) -> bool:
        prof = _own_profile(t, lr, reach)
        if "peaks" not in t:
            t["peaks"] = _profile_peaks(prof, reach)
        # The near-field test first (cheap; the same answer in either order).
        depth = median1d(t["rows"])
        if depth < nf:
            return False
        members = _series(t["peaks"], reach, min_px, dark, p.reverb_tolerance, strict=True)
        if len(members) < 3:
            return False
        # Rows in the near field (gel, skin) say nothing of what lies over the
        # reflector: over a bone 3-4 mm deep most of the window is skin (S clavicle
        # grey s109, frames 37-39, the near cortex 3.9 mm deep).
        lo = max(reach - 2 * gap, reach - (int(depth) - nf))
        above = prof[lo : reach - gap]
        above = above[np.isfinite(above)]
        # Shadow over the top (a far cortex's: it lies in the near cortex's shadow) is
        # as dark as the shadow between the copies, one and the same shadow: what lies
        # over the top reads as shadow only where it is darker than ``under_ratio`` of
        # the tissue and than half the troughs' mean (in log), however dark the troughs.
        # A layer of darker muscle over the bone is tissue: 0.78 of the frame's level
        # over the grey humerus (seed 709, frame 32) whose troughs read 0.32-0.004 of it.
        v = t["peaks"][0]
        rows = [q + reach for q in members]
        troughs = [v[a + 1 : b].min() for a, b in zip(rows[:-1], rows[1:], strict=True)]
        shade = min(float(np.log(p.under_ratio)), 0.5 * float(np.mean(troughs)))
        return not (above.size >= gap and median1d(above) < shade)

    def top_at(
        c: dict, shape: dict, top: int, d: float, copy: bool = True
    ) -> tuple[dict, bool] | None:
        """The series' top ``top`` rows from ``shape`` over c's columns, if confirmed:
        an existing candidate there, or one made from the shape moved up to the
        strongest echo near it; and whether it is new. ``copy``: ``c`` is a member of
        the series (else it lies under it: a far cortex, its own reflector)."""
        rw = max(1, int(0.45 * d))
        best = None
        for t in cands + added:
            if t is c or t.get("reverb"):
                continue
            # t's offset from the shape hangs on neither the top nor the spacing: made
            # once per shape while c is read (``offsets``, emptied for each c; nothing it
            # reads changes meanwhile), not again for each member tried.
            key = (id(t), id(shape))
            if key not in offsets:
                cm = _common(t, c)
                offsets[key] = (
                    median1d(t["dense"][cm] - shape["dense"][cm])
                    if cm.size >= 0.5 * c["cols"].size
                    else None
                )
            off = offsets[key]
            if off is not None and abs(off - top) <= rw:
                best = t
                break
        new = best is None
        if new:
            base = shape["rows"] + top
            if median1d(base) < nf:
                return None  # in the near field: no first interface (as confirmed() rules)
            base = _clip_rows(base, 0, h - 1)
            half = int(round(d / 2))
            rows = _trace_band(ev, c["cols"], base, rw, shift_cost, lr, half, dark)
            cols = c["cols"]
            if copy:
                # Made over a copy's columns: on past them along its own echo. (Read
                # over a far cortex, a bowl whose mirror is only a shape hypothesis, the
                # top is not followed: the trough rule holds anywhere in the shadow.)
                cols, rows = _extend_top(ev, lr, cols, rows, half, dark, p)
            dense = np.full(c["dense"].size, np.nan)
            dense[cols] = rows
            # Its strength, shadow and grey are made once it is kept (:func:`_kept_top`):
            # most tops made here fail the tests below.
            best = {"cols": cols, "rows": rows, "echo": median1d(ev.echo_z[rows, cols])}
            best["dense"] = dense
            # Traced onto a line a pass found already, over half of its columns
            # (within the band the passes suppress around a line: one line), the top
            # is that line, not a second version of it that strays off it elsewhere
            # and, followed on along the echo, lies over it (tibia with a vessel, seed
            # 5, frame 14: a top on the bone's left half and 1-4 mm over its right
            # half put the bone in its shadow, coverage 1.00 -> 0.62).
            # (All the lines at once, as rows of their dense rows, made once per c:
            # where either is absent the difference is NaN, never within ``sup``, so
            # each count is its count over the columns in common; the first line over
            # half is the one the loop over them took.)
            if not others:
                pool = [t for t in cands + added if t is not c and not t.get("reverb")]
                width = c["dense"].size
                others.append(
                    (pool, np.array([t["dense"] for t in pool]).reshape(len(pool), width))
                )
            pool, stacked = others[0]
            on = np.count_nonzero(np.abs(stacked - dense) <= sup, axis=1)
            hit = (on >= 0.5 * cols.size).nonzero()[0]
            if hit.size:
                best, new = pool[int(hit[0])], False
        # A copy returns less than its reflector; over the shadow it may stand out
        # more, but a line with much more echo contrast than the top was not made by it.
        # A line under the series (a far cortex) is no copy: it says nothing of the
        # top's echo (with strong reverberation, S tibia s101, the far cortex's echo z
        # 1.4-1.7 in a dark shadow, the near cortex's under 1 over its tissue).
        if (copy and c["echo"] > p.copy_echo_ratio * max(best["echo"], 0.0)) or not confirmed(best):
            return None
        return (_kept_top(best, ev, p) if new else best), new

    # top_at's, while one c is read: the lines' offsets from the shape, and the lines
    # (not c, no copy) with their dense rows stacked.
    offsets: dict[tuple[int, int], float | None] = {}
    others: list[tuple[list[dict], np.ndarray]] = []
    for c in list(cands):
        if c.get("reverb"):
            continue
        offsets.clear()
        others.clear()
        bowl = _curves_down(c["rows"])
        top_itself = confirmed(c)  # (makes c's own profile)
        if top_itself and not bowl:
            c["series_top"] = True
            continue
        # The series seen loosely along c's shape; a bowl (the far cortex of a convex
        # bone, curving the other way from the near one and its copies) first along its
        # mirror image. Its top: the shallowest member confirmed from its own profile
        # (the loose chain may reach up into speckle peaks of the tissue over the bone).
        found_top = None
        # The near cortex lies a bone's thickness over the far one, often more than the
        # shadow window: a bowl is read along its mirror image up to the near field
        # (hard tibia, reverberation 0.45, S s101 frames 26-39: the far cortex 19-26 mm
        # deep, the near cortex and its five copies 6-20 mm; within ``far_shadow_mm``
        # (12 mm) over the far cortex two copies showed and no series). Over all its
        # columns first, then over the middle half only: the mirror of a bowl fits the
        # copies' dome near its bottom, less and less out on its sides (the tibia's
        # series, spacing 2.5 mm, shows only so); the whole width first, as a chain
        # read over the middle alone may climb one spacing higher onto a layer over
        # the bone (S clavicle s101, frames 20-21: a layer 2.45 mm over the bone).
        if bowl:
            # One mirror image for both of its reads (its profile and peaks are each
            # read's own), and the depth it is read up to.
            mirror, up_to = _mirrored(c), max(reach, int(median1d(c["rows"])) - nf)
        for read in ("mirror", "mirror middle", "own") if bowl else ("own",):
            at, shape = reach, c
            if read != "own":
                at, shape = up_to, mirror
                n_cols = c["cols"].size
                q = n_cols // 4
                # Over the middle half: the profile of the mirror's columns q .. n - q - 1
                # (its columns are distinct: the columns ``only`` would keep).
                middle = {
                    "cols": mirror["cols"][q : n_cols - q],
                    "rows": mirror["rows"][q : n_cols - q],
                }
                shape["prof"] = _underside_profile(
                    lr, middle if read == "mirror middle" else shape, at
                )
                shape["peaks"] = _profile_peaks(shape["prof"], at)
            members = _series(shape["peaks"], at, min_px, dark, p.reverb_tolerance, strict=False)
            v = shape["peaks"][0]
            on = min(abs(m) for m in members) <= 1  # c is a member: a copy
            for i in range(len(members) - 2):
                found_top = top_at(c, shape, members[i], members[i + 1] - members[i], on)
                if found_top is not None:
                    # A copy returns less than its reflector: where the next member
                    # down, past the echo's tail (``shadow_gap_mm``: nearer, it is
                    # the same echo), is a confirmed top too, with more echo, the one
                    # found is a layer one spacing over the bone, not its reflector
                    # (S radius grey s701, frame 31: a layer 2.6 mm over the bone,
                    # echo z 1.0, took the stack's strength and the track; s179 frame
                    # 27: a member 1.2 mm under the top, read at half the spacing).
                    if i + 3 < len(members) and members[i + 1] - members[i] >= gap:
                        below = top_at(
                            c, shape, members[i + 1], members[i + 2] - members[i + 1], on
                        )
                        if below is not None and below[0]["echo"] > found_top[0]["echo"]:
                            found_top, i = below, i + 1
                    members = members[i:]
                    break
                # A member with shadow under it is in the series: no deeper top.
                a, b = members[i] + at, members[i + 1] + at
                if float(v[a + 1 : b].min()) < dark:
                    break
            if found_top is not None:
                break
        if found_top is None:
            # A bowl with copies of its own and no series over it: a top after all.
            if top_itself:
                c["series_top"] = True
            continue
        best, new = found_top
        if new:
            added.append(best)
        # On the series: a copy; under it: in the reflector's shadow (a far cortex).
        if min(abs(m) for m in members) <= 1:
            c["reverb"] = True
        else:
            c["beneath"] = True
        best["series_top"] = True
        best["inherit"] = max(best.get("inherit", -np.inf), c["strength"])
    return cands + added


#: Share of a lower candidate's columns that must lie under an upper one for the upper
#: to speak for it (:func:`_mark_echo_beneath`): to cast its shadow over it (a shadow is
#: as wide as its reflector), or to have let the sound through to a dome under it.
_WITHIN = 0.8


def _mark_echo_beneath(
    cands: list[dict], ev: EvidenceMaps, lr: np.ndarray, p: ShadowPathParams
) -> None:
    """Flag candidates that are no first interface: under a shadow, or over an echo.

    Bone is the first strong reflector along the beam: it stops the sound, so nothing
    under it is anatomy but the far cortex and reverberation. For two candidates over
    the same columns, the upper ``c`` and the lower ``b``:

    * the region between them (under ``c``, following its shape,
      :func:`_underside_profile`) comes back darker than ``under_ratio`` of the
      frame's typical tissue-to-level ratio, or of the tissue right over ``c`` where
      that is brighter (under the near field: gel, skin and lens echoes are no tissue
      the sound crossed; geometric means: bright copies in the shadow do not outweigh
      it), and ``b`` is no dome (below), or ``c`` tops a reverberation series: ``b``
      lies in ``c``'s shadow and is flagged (the far cortex, a band) if it lies within
      ``c``'s columns (a shadow is as wide as its reflector); either way ``c`` is not
      flagged for it;
    * a dome ``b`` at least two shadow gaps under ``c`` (and no copy: those are skipped)
      is no far cortex: the sound reached it through ``c``, whatever the grey between
      them, and ``b`` is not in ``c``'s shadow; ``c`` is judged by the echo rule below
      if ``b`` lies within its columns, else not for ``b`` at all (below);
    * otherwise, with tissue between them, an echo ``b`` at least ``beneath_ratio`` as
      bright as ``c`` means the sound went through ``c``: ``c`` is soft tissue (a fascia
      over the bone) and is flagged.

    Both are ratios measured in the frame itself, so they hold at any gain and
    contrast. The tissue over ``c`` is the sound's own path to it: a shadow is darker
    than what the sound crossed to cast it, whatever the rest of the frame holds. With
    the frame's typical level alone, a hard radius (seed 2, 320 x 256) with the ulna
    18 mm beside it read its interior, reverberation bands and all, at 0.81-0.82 of
    the typical tissue (``under_ratio`` 0.8) but 0.73-0.77 of the brighter tissue over
    it, so the far cortex under it went unflagged and carried the track in all 12
    frames (wrong share 1.0 -> 0).

    What lies in a bone's shadow is its far cortex, a bowl (the back wall of a convex
    bone), and reverberation copies, flagged before this runs (:func:`_mark_reverberations`,
    :func:`_mark_series`: they are skipped here, and so is all under a series' top). A
    dome (:func:`_is_dome`) under ``c`` that is neither is an interface the sound
    reached through ``c``: the region between them is tissue however dark it reads (a
    muscle lying on the bone), and ``b`` is not in ``c``'s shadow. ``c`` is then judged
    by the echo rule only where ``b`` lies within its columns (0.8 of ``b``'s, the
    share the shadow rule asks): a dome partly beside ``c`` may be another bone, deeper
    (a hard ulna with the radius 14 mm beside, seed 1019: judged on any overlap, the
    ulna was flagged in 16 of 40 frames and the track took a layer 9 mm off in all 40).
    Measured with a muscle at 0.6 of the tissue's grey under a fascia 1.5 times the
    bone's echo (:func:`.simulation.augment.add_muscle`): the bone under the fascia's
    arch was flagged as lying in its shadow and the fascia carried the track (the L14
    recording and its grey-shadow copy, recall 0; hard simulated sweeps of five bones
    at 0.3 mm, seeds 3 and 7, muscle 6 mm: recall 0-0.15 in all 10); with domes out of
    the shadow test, the L14 copies hold (recall 1.00) and 8 of the 10 (the tibia's
    bone and fascia both unflagged, the fascia the stronger); the harness's means
    unchanged on five seed pairs, one of 80 bone-free-end sweeps two frames short at
    the bone's end (Testing/benchmarks/README.md, session 52). Flagging ``c`` for any such dome within
    its columns (it let the sound through), whatever their echoes, held all 10 but lost
    the same ulna (seeds 1013, 1019): not done. Where a far cortex lies under the bone
    at the fascia's spacing over it, the three read as an equally spaced series and
    the bone as a copy (hard radius and clavicle at 0.108 mm, muscle 9 mm): open.
    Candidates closer than two shadow gaps are judged on ``c``'s own shadow z-score
    instead (no room between them to measure).

    A shadow is judged under a candidate that could have cast it, never from the grey
    over ``b`` alone: a muscle lying on the bone (pronator quadratus, brachialis) is
    speckle at a lower level, and with grey shadows no level tells it from a shadow.
    A rule that flagged any ``b`` whose region 1.5-12 mm above read under
    ``under_ratio`` of the frame's typical tissue ("in a shadow whatever cast it")
    flagged the bone itself in most frames of the hard simulated sweeps (76 of 120 on
    three of seed 173) and, on the L14 grey-shadow copy with a muscle of 0.7 of the
    tissue's grey over the bone (:func:`.simulation.augment.add_muscle`), the bone in
    most frames: the track took a layer 9 mm over it (recall 0). Without it the
    harness's 352 sweeps (seeds 173-919) keep the same recall and wrong share but for
    the last frame of one sweep and its corrupted twin (R humerus hard s701), the gold
    of each seed pair within 0.0005 mm (Testing/benchmarks/README.md, session 50).
    """
    gap = mm_to_px(p.shadow_gap_mm, ev.dy, minimum=1)
    reach = mm_to_px(p.far_shadow_mm, ev.dy)
    dark = float(np.log(p.under_ratio))
    # The near field (gel, the skin line, lens echoes: never tissue at a tissue level)
    # is no cover: rows of the profile over c's median row that lie in it are left out.
    near = ev.field_top + mm_to_px(p.near_field_mm, ev.dy, minimum=0)
    offsets = np.arange(-reach, -gap)

    def rows_over(c: dict) -> np.ndarray:
        return offsets + median1d(c["rows"])

    for c in cands:
        if c.get("reverb"):
            continue
        for b in cands:
            if b is c or b.get("reverb"):
                continue
            common = _common(c, b)
            # Under most of c, or c over most of b (a long fascia over the bone).
            if common.size < 0.5 * min(c["cols"].size, b["cols"].size):
                continue
            off = median1d(b["dense"][common] - c["dense"][common])
            if off <= 0:
                continue  # b is not below c
            # What lies in a shadow comes back dimmer than what cast it; under a
            # series' top, whose troughs are shadow, whatever its grey (the far cortex
            # may come back brighter than a faint near cortex).
            if b["grey"] < c["grey"] or c.get("series_top"):
                if c.get("series_top"):
                    shadowed = True
                elif off >= 2 * gap + 1 and _is_dome(
                    b["cols"] * ev.dx, b["rows"] * ev.dy, p.dome_mm
                ):
                    # Neither far cortex (a bowl) nor copy (skipped above): the sound
                    # reached it through c, and what lies between is tissue. Partly
                    # beside c, it may be another bone: no sign either way.
                    if common.size < _WITHIN * b["cols"].size:
                        continue
                    shadowed = False
                elif off >= 2 * gap + 1:
                    # Under c over the columns b lies under, following c's shape.
                    if common.size < c["cols"].size:
                        prof = _underside_profile(lr, c, reach, common)
                    else:
                        prof = _own_profile(c, lr, reach)
                    seg = prof[reach + gap : reach + min(reach, int(off) - gap) + 1]
                    seg = seg[np.isfinite(seg)]
                    shadowed = seg.size > 0 and median1d(seg) < dark
                    if seg.size and not shadowed:
                        # Darker than the tissue the sound came through to c, where
                        # that is brighter than the frame's typical tissue (its cover,
                        # the rows over c along its shape).
                        cover = prof[: reach - gap]
                        cover = cover[np.isfinite(cover) & (rows_over(c) >= near)]
                        if cover.size >= gap:
                            shadowed = median1d(seg) < dark + max(0.0, median1d(cover))
                else:
                    shadowed = c["shadow"] >= p.shadow_z_full
                if shadowed:
                    # b is flagged only within the columns of what cast the shadow (a
                    # shadow is as wide as its reflector). A b reaching beyond them (a
                    # far cortex whose pass runs on along the tissue beside) is no
                    # sign that sound went through c either: shadow, not tissue,
                    # lies between them. With the z-scores' nulls over the tissue (an
                    # option) such far cortices flagged the series' top over them
                    # (grey-shadow clavicle seed 5: near cortex offered in 30 frames,
                    # 34 with this rule; Testing/benchmarks/README.md, branch tgrey).
                    if common.size >= _WITHIN * b["cols"].size:
                        b["beneath"] = True
                    continue
            if b["grey"] >= p.beneath_ratio * c["grey"]:
                c["beneath"] = True


def _apex(x: np.ndarray, z: np.ndarray) -> int:
    """Index of a contour's apex: its shallowest point away from the ends (the middle
    60 % of its lateral span), so a contour that climbs onto a layer at one end does not
    have its apex there. ``x`` lateral and ``z`` depth, in mm."""
    x0, x1 = x.min(), x.max()
    span = x1 - x0
    mid = (x >= x0 + 0.2 * span) & (x <= x1 - 0.2 * span)
    # Array methods, not numpy's functions: ~40 calls per frame on tens of values, where
    # the functions' wrappers cost more than the work (the same indices).
    idx = mid.nonzero()[0]
    return int(idx[z[idx].argmin()]) if idx.size else int(z.argmin())


def _outward_slopes(
    xo: np.ndarray, zo: np.ndarray, w_in: float, w_out: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Outward descent slopes along one side of a contour, from its apex outward.

    ``xo`` is the lateral distance from the apex (mm, increasing: columns are distinct
    and ordered) and ``zo`` the depth (mm) of the side's points. For each inner point
    ``k`` the descent over ``w_in`` just inside it and over ``w_out`` just outside it:
    the windows are index ranges ``[lo, k]`` and ``[k, hi]`` of ``xo``. Returns ``k,
    lo, s_in, s_out, ok``, ``ok`` where both windows hold a point besides ``k`` and the
    outer one spans at least half of ``w_out``.
    """
    k = np.arange(1, xo.size - 1)
    xk = xo[1:-1]  # xo[k] (a slice: fewer numpy calls per contour)
    # (The array's method: np.searchsorted's wrapper costs as much as the search here.)
    lo = xo.searchsorted(xk - w_in, side="left")
    hi = xo.searchsorted(xk + w_out, side="right")
    hi -= 1
    return (k, lo, *_window_slopes(xo, zo, k, lo, hi, w_out))


def _window_slopes(
    xo: np.ndarray, zo: np.ndarray, k: np.ndarray, lo: np.ndarray, hi: np.ndarray, w_out: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``s_in, s_out, ok`` of :func:`_outward_slopes` for given windows ``[lo, k]`` and
    ``[k, hi]`` (index arrays into ``xo``, ``zo``): shared with :func:`convex_part`,
    which measures both sides of an apex on their concatenation."""
    xk, zk = xo[k], zo[k]
    d_out = xo[hi] - xk
    s_in = (zk - zo[lo]) / np.maximum(xk - xo[lo], 1e-6)
    s_out = (zo[hi] - zk) / np.maximum(d_out, 1e-6)
    ok = (k - lo >= 1) & (hi - k >= 1) & (d_out >= 0.5 * w_out)
    return s_in, s_out, ok


def convex_part(
    points_px: np.ndarray, spacing: tuple[float, float], p: ShadowPathParams
) -> np.ndarray:
    """Mask of the part of a contour that stays convex, seen from the probe, around its top.

    A long bone's cross-section is convex: going outwards from its shallowest point the
    contour descends ever more steeply (a crest's flanks, an oval's sides). A contour
    that, going outwards, turns from descending at least ``kink_slope`` (depth per
    lateral mm, over ``kink_mm``; over at least half of it, or by ``valley_mm``: a grain
    over the top is no flank) to descending less than a third of that has left the
    bone onto a layer meeting it (a fascia running off the crest at the bone's level).
    Only the part beyond such a turn is dropped, so a flank is kept down to where it
    ends, however steep.
    """
    n = points_px.shape[0]
    keep = np.ones(n, bool)
    if n < 6:
        return keep
    x = points_px[:, 0] * float(spacing[0])
    z = points_px[:, 1] * float(spacing[1])
    top = _apex(x, z)
    win = p.kink_mm
    # Each side's points outward from the apex (views, lateral distance from it), then
    # both sides measured by one set of numpy calls on their concatenation (numpy's
    # per-call cost dominates on a contour's tens of points; each side's windows are
    # searched in its own points, so the same indices and the same values as
    # :func:`_outward_slopes` per side).
    xa = np.abs(x - x[top])
    sides = [
        (side, xo, zs)
        for side, xo, zs in ((-1, xa[top::-1], z[top::-1]), (1, xa[top:], z[top:]))
        if xo.size >= 4
    ]
    if not sides:
        return keep
    xs, zs, ks, los, his = [], [], [], [], []
    start = 0  # the side's first point in the concatenation
    for _, xo, zo in sides:
        xk = xo[1:-1]
        ks.append(np.arange(start + 1, start + xo.size - 1))
        los.append(xo.searchsorted(xk - win, side="left") + start)
        his.append(xo.searchsorted(xk + win, side="right") + (start - 1))
        xs.append(xo)
        zs.append(zo)
        start += xo.size
    xo, zo = np.concatenate(xs), np.concatenate(zs)
    k, lo, hi = np.concatenate(ks), np.concatenate(los), np.concatenate(his)
    s_in, s_out, ok = _window_slopes(xo, zo, k, lo, hi, win)
    # The descent inward of the turn measured over at least half of kink_mm, as the
    # outward one is, or a drop of valley_mm (a hop's, as _fill_excursions reads one): a
    # grain a few tenths of a mm over the top is neither, and taken for a flank it cut a
    # 20 mm dome down to 3 mm (hard simulated tibia, seed 113, frame 15; on the tibia
    # with the fibula, seed 131, 0.40 -> 0.29 mm from gold).
    ok &= (xo[k] - xo[lo] >= 0.5 * win) | (zo[k] - zo[lo] >= p.valley_mm)
    cut = k[ok & (s_in >= p.kink_slope) & (s_out < s_in / 3.0)].tolist()
    start = 0
    for side, xo_side, _ in sides:
        end = start + xo_side.size
        first = next((q for q in cut if start <= q < end), None)
        if first is not None:
            # The points past the turn: side index k + 1 on, i.e. top -+ (k + 1) on.
            j = first - start + 1
            if side < 0:
                keep[: top - j + 1] = False
            else:
                keep[top + j :] = False
        start = end
    return keep


def frame_candidates(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
) -> FrameCandidates:
    """Candidate bone contours of one frame, strongest first.

    Pure: depends on this frame only (no prior from other frames), so it can run as a
    frame arrives and its result can be cached; :func:`.track.select_bone_track`
    then chooses among the candidates of all frames.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W)
    spacing : (sx, sy)
        mm per column and per row.
    params : ShadowPathParams

    Returns
    -------
    FrameCandidates
    """
    return frame_candidates_many([image], [spacing], params)[0]


def frame_candidates_many(
    images: Sequence[np.ndarray],
    spacings: Sequence[tuple[float, float]],
    params: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
    evidence: Sequence[EvidenceMaps | None] | None = None,
) -> list[FrameCandidates]:
    """:func:`frame_candidates` of several frames (the same results), their paths solved together.

    The frames advance pass by pass in step; the optimal paths asked at each step are
    solved by one column loop (:func:`_optimal_paths`), which costs about half as much
    per frame for 16 frames or more. Memory: the frames' evidence maps are held at once
    (~1 MB per 480x640 frame). ``evidence``: each frame's :func:`.evidence.bone_evidence`
    with these ``params``, when the caller has it already (None: computed here); it is
    read, never changed.
    """
    evs = list(evidence) if evidence is not None else [None] * len(images)
    gens = [
        _frame_candidates_steps(img, sp, params, ev)
        for img, sp, ev in zip(images, spacings, evs, strict=True)
    ]
    out: list[FrameCandidates | None] = [None] * len(gens)
    pending: dict[int, tuple[np.ndarray, np.ndarray, float] | RadiusPaths] = {}
    scratch: dict = {}  # the passes' optimal paths reuse one scores' array

    def advance(i: int, path: np.ndarray | None) -> None:
        try:
            pending[i] = next(gens[i]) if path is None else gens[i].send(path)
        except StopIteration as done:
            out[i] = done.value

    for i in range(len(gens)):
        advance(i, None)
    while pending:
        asked, pending = pending, {}
        # The rim's paths (:mod:`.rim`) of the frames that reached it, solved together
        # (:func:`.rim.radius_paths_many`: the same paths).
        rims = [i for i, a in asked.items() if isinstance(a, RadiusPaths)]
        if rims:
            solved = radius_paths_many([asked.pop(i) for i in rims])  # type: ignore[misc]
            for i, path in zip(rims, solved, strict=True):
                advance(i, path)
        # Paths are solved together when their switch is the same, each with its own
        # costs: frames' spacings (from their poses) differ in the last bits, and
        # grouping by equal costs split a 30-frame batch into 5-10 column loops; by the
        # costs' size, into two (a slope limit of 3.000...01 rows or 2.999...9 rounds
        # up to 4 or 3 shifts), the smaller loop costing nearly as much as the larger.
        groups: dict[float, list[int]] = {}
        for i, (_, _, switch) in asked.items():  # type: ignore[misc]
            groups.setdefault(switch, []).append(i)
        for idx in groups.values():
            switch = asked[idx[0]][2]
            gains = [asked[i][0] for i in idx]
            if len(idx) == 1:
                paths = [_optimal_path(gains[0], asked[idx[0]][1], switch)]
            else:
                paths = _optimal_paths(gains, [asked[i][1] for i in idx], switch, scratch)
            for i, path in zip(idx, paths, strict=True):
                advance(i, path)
    assert all(fc is not None for fc in out)  # every frame's steps ran to their end
    return out  # type: ignore[return-value]


def _frame_candidates_steps(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: ShadowPathParams,
    evidence: EvidenceMaps | None = None,
) -> Generator[tuple[np.ndarray, np.ndarray, float] | RadiusPaths, np.ndarray, FrameCandidates]:
    """:func:`frame_candidates` as a generator: yields each optimal path it needs as
    ``(gain, shift_cost, switch)`` and the rim's paths as :class:`.rim.RadiusPaths`, is
    sent the path(s), returns the FrameCandidates. ``evidence``: the frame's
    :func:`.evidence.bone_evidence`, if computed already."""
    p = params
    sp = (float(spacing[0]), float(spacing[1]))
    img = np.asarray(image)
    ev = bone_evidence(img, sp, p) if evidence is None else evidence
    if ev is None:
        return FrameCandidates((), sp, "image too small")
    if not ev.usable.any():
        return FrameCandidates((), sp, "no imaged field of view")
    h, w = ev.score.shape
    gain = ev.score - np.float32(p.null_z)
    gain *= np.float32(ev.dx)
    shift_cost, min_cols = _path_steps(ev, p)
    n_shift = shift_cost.size // 2
    sup = mm_to_px(p.suppress_mm, ev.dy)
    found: list[dict] = []
    for _ in range(p.n_passes):
        pos = gain > 0
        pos_rows = pos.any(axis=1)
        if not pos_rows.any():
            break
        rr = np.flatnonzero(pos_rows)
        cc = np.flatnonzero(pos.any(axis=0))
        # Only the box holding positive gains matters (3-5x less work on typical frames).
        r0, r1 = max(0, rr[0] - 2 * n_shift), min(h, rr[-1] + 1 + 2 * n_shift)
        c0, c1 = cc[0], cc[-1] + 1
        path = np.full(w, -1, dtype=np.intp)
        # The optimal path is asked of the caller (frame_candidates_many solves the
        # paths of several frames at once).
        sub = yield gain[r0:r1, c0:c1], shift_cost, p.switch_cost
        path[c0:c1] = np.where(sub >= 0, sub + r0, -1)
        groups = _groups(path, ev, p)
        if not groups:
            break
        for cols in groups:
            rows = path[cols]
            if cols.size >= min_cols:
                s = ev.score[rows, cols]
                found.append(
                    {
                        "cols": cols,
                        "rows": rows,
                        "strength": float((s - p.null_z).sum() * ev.dx),
                        "shadow": median1d(ev.shadow_z[rows, cols]),
                        "echo": median1d(ev.echo_z[rows, cols]),
                        "grey": median1d(ev.work[rows, cols]),
                    }
                )
            # Suppress a band around what was found (bone, fascia or copy alike).
            band = rows[None, :] + np.arange(-sup, sup + 1)[:, None]
            if int(rows.min()) >= sup and int(rows.max()) + sup < h:
                gain[band, cols] = -1.0  # the whole band inside: no mask to apply
            else:
                ok = (band >= 0) & (band < h)
                gain[band[ok], np.broadcast_to(cols, band.shape)[ok]] = -1.0
    if not found:
        return FrameCandidates((), sp, "no bone found", level=ev.frame_level())
    _dense_rows(found, w)
    _mark_reverberations(found, p)
    lr = _log_ratio(ev)
    found = _mark_series(found, ev, lr, p)
    # What lies in a shadow is judged with vessels' lumens read as tissue (the profiles
    # of the candidates over a lumen's columns taken again).
    lr_beneath = _without_lumens(lr, ev, p)
    if lr_beneath is not lr:
        over = (lr_beneath != lr).any(axis=0)
        for c in found:
            if over[c["cols"]].any():
                c.pop("prof", None)
    _mark_echo_beneath(found, ev, lr_beneath, p)
    made: list[tuple] = []
    domes: list[tuple] = []  # pieces offered besides their path's best (_separate_domes)
    # Every candidate's sub-pixel rows in one go (the same values as one at a time).
    refined = _refine_many(img, ev, [(c["cols"], c["rows"]) for c in found], p, sp[1])
    for c, pts in zip(found, refined, strict=True):
        # A narrow excursion over the bone is no apex (see _fill_excursions): the convex
        # pieces are cut on the contour with it filled in, and its points then dropped.
        # A reverberation series' top is traced inside a band along another line's shape
        # (_trace_band), not a free path: a short stretch of it above the rest may be the
        # reflector itself over a copy (clavicle under the grey shadow, seed 5: four
        # frames lost their candidate on the bone when it was filled in).
        calm, filled = (
            (np.ones(len(pts), bool), pts) if c.get("series_top") else _fill_excursions(pts, sp, p)
        )
        # Of the contour's convex pieces, the one with the most evidence is the candidate.
        pieces = []
        for m in _convex_pieces(filled, sp, p, min_cols, ev.shadow_z[c["rows"], c["cols"]]):
            if not calm.all() and (m & calm).any():
                m = m & calm  # an excursion's points are not the bone's
            cols, rows = c["cols"][m], c["rows"][m]
            pieces.append((float((ev.score[rows, cols] - p.null_z).sum() * ev.dx), m, cols, rows))
        best = max(pieces, key=lambda q: q[0])  # the piece around the apex is always offered
        if c.get("series_top") and best[0] <= 0:
            # A series' top with no piece above the null level (its shadow is its
            # copies' band): the least negative piece is merely the shortest; the
            # reflector is the piece that echoes most (its evidence is the series').
            best = max(pieces, key=lambda q: median1d(ev.echo_z[q[3], q[2]]))
        span = _shadowed_span(c, found) if not c.get("reverb") else None
        if span is not None and len(pieces) > 1:
            # Over one shadow the pieces are one reflector: a shadow is as wide as what
            # cast it, so the pieces lying over the shadowed line's columns (80 % of
            # theirs; the far cortex, flagged as lying in a shadow) are joined. A faint near cortex
            # (a tibia under a grey shadow, score near the null level) whose path steps
            # ~1 mm at its flank is otherwise cut there and only the short bright piece
            # offered; a layer meeting the bone runs past the shadow and stays cut off.
            # Unless two of them are domes (_piece_is_dome): two bones side by side
            # (radius and ulna 14 mm apart) cast one wide shadow whose far line runs
            # under both, yet are two reflectors; a crest's or a flank's pieces fall
            # one way, only its top is a dome. Geometry and flags only: no grey level
            # (benchmarks README, branches tibia and lead s33).
            inside = [q for q in pieces if np.mean((q[2] >= span[0]) & (q[2] <= span[1])) >= 0.8]
            if len(inside) > 1 and sum(_piece_is_dome(pts, q, sp, p, min_cols) for q in inside) < 2:
                jm = np.logical_or.reduce([q[1] for q in inside])
                jc, jr = c["cols"][jm], c["rows"][jm]
                best = (float((ev.score[jr, jc] - p.null_z).sum() * ev.dx), jm, jc, jr)
        # Besides the best piece, every other piece that is a dome of its own (a second
        # bone the path ran on to over the gap between them, :func:`_separate_domes`).
        chosen = [(best, made)]
        if not c.get("reverb") and len(pieces) > 1:
            chosen += [(q, domes) for q in _separate_domes(pieces, best, pts, sp, p, min_cols)]
        for (strength, m, cols, rows), into in chosen:
            # A layer running off the bone's shoulder is cut off (see _shoulder_cut);
            # the flanks are then followed from the cut end like any other (:mod:`.flanks`).
            if not c.get("reverb"):
                sk, strength = _cut_at_shoulder(
                    pts[m],
                    cols,
                    rows,
                    strength,
                    ev,
                    lambda cols=cols, rows=rows: _underside_step(lr, cols, rows, ev.dy),
                    sp,
                    p,
                    min_cols,
                )
                if sk is not None:
                    m = np.flatnonzero(m)[sk]
                    cols, rows = cols[sk], rows[sk]
            # A reverberation series' top carries the evidence of its copies.
            strength = max(strength, c.get("inherit", -np.inf))
            into.append(
                (
                    pts[m],
                    strength,
                    median1d(ev.echo_z[rows, cols]),
                    median1d(ev.shadow_z[rows, cols]),
                    bool(c.get("reverb", False)),
                    bool(c.get("beneath", False)),
                )
            )
    made.sort(key=lambda q: -q[1])
    # The domes come on top of the budget: a second bone's piece takes no other
    # candidate's place (a weak near cortex of the bone swept, on a forearm), and the
    # room it takes is no other's either.
    made = made[: p.max_candidates]
    if domes:
        made = sorted(made + domes, key=lambda q: -q[1])
    # Past the path's reach: each candidate kept followed down the bone's flanks
    # (:mod:`.flanks`; strengths unchanged, so the same candidates are kept, in the same
    # order, and those cut off are not traced).
    # A candidate running on a layer just over the bone is first moved onto it where the
    # shadow starts under it (:mod:`.settle`), so its flanks are followed from the bone.
    # The grey values of the kept candidates' points, sampled in one call (the same
    # values as one candidate at a time; those cut off are not sampled).
    grey = sample_bilinear(img, np.concatenate([q[0] for q in made]))
    cut = np.cumsum([0] + [q[0].shape[0] for q in made]).tolist()
    out = [BoneCandidate(q[0], grey[cut[k] : cut[k + 1]], *q[1:]) for k, q in enumerate(made)]
    settled = settle_candidates(img, ev, out, sp, p.settle)
    out = [_past_the_settled_wall(a, b, sp, p, min_cols) for a, b in zip(out, settled, strict=True)]
    out = yield from extend_candidates_steps(img, ev, out, sp, p.flanks, p.rim)
    out = [_cut_climbing_ends(c, sp, p.climb_mm) for c in out]
    # Each piece judged on its settled contour before a layer beyond its wall was
    # dropped (that drop found the same layer; the extension keeps order and count).
    out = _mark_branches(out, [c.points_px for c in settled], ev, sp, p)
    # A candidate none of whose own path's points survived the cuts is no candidate: a
    # rim trace that climbed over the contour it started from, the contour then cut
    # away as a climbing end (hard humerus at 475 x 405 swept by an unsteady hand,
    # ``bench_sweeps.py --groups motion``, seed 197, frame 12: 32 rim points and no
    # path point left; the track, which compares the path's points, stopped on it).
    out = [c for c in out if c.core_px.shape[0]]
    if not out:
        return FrameCandidates((), sp, "no bone found", level=ev.frame_level())
    return FrameCandidates(
        tuple(out), sp, "", {"work_px": (ev.fx, ev.fy)}, _fov_px(ev), ev.frame_level()
    )


def _cut_climbing_ends(
    cand: BoneCandidate, spacing: tuple[float, float], climb: float = 1.0
) -> BoneCandidate:
    """``cand`` without the end of a flank that climbs back towards the probe.

    Seen from above, the upper surface of a convex bone only goes deeper from its top
    outward, down to the widest point of its section. A contour that, on one side of
    its top, went down a flank by at least ``2 * climb`` and then climbs back by more
    than ``climb`` mm (``ShadowPathParams.climb_mm``; 0: off) past its deepest point
    has left the bone there: it ran across the gap onto the top of a bone beside it
    (the fibula 10-15 mm under the tibia's top and ~20 mm lateral: the tibia's flank
    ends just above the fibula's medial side, and the path or the rim went on up over
    it, in one contour; the radius beside an ulna) or onto a layer. That side is cut
    back to its deepest point. :func:`convex_part` misses it when the climb is short
    and follows a steep drop (its windows then straddle the gap). The descent must be
    a flank followed down, no step of it more than half of it: a contour switching
    between two lines (a layer over the bone, the bone) jumps down and up again
    without having left the bone. And the side must not go on down past the climb: a
    path that stepped up onto a fascia for a few columns, after which the rim followed
    the flank on down, is on the bone again. The top must be one (neither side climbs
    within ``2 * climb`` of it laterally), so a concave line (a far cortex, a bowl) is
    left whole; and lines flagged as copies or as lying over an echo are not bone tops
    and are left as they are. Geometry alone, in mm: no grey level, so it holds at any
    gain or contrast.
    """
    pts = cand.points_px
    n = pts.shape[0]
    if climb <= 0 or n < 6 or cand.reverberation or cand.echo_beneath:
        return cand
    x = pts[:, 0] * float(spacing[0])
    z = pts[:, 1] * float(spacing[1])
    top = _apex(x, z)
    near = np.abs(x - x[top]) <= 2 * climb
    if z[top] - z[near].min() > climb:
        return cand  # not a top: a concave line's shallowest point in its middle
    keep = [0, n]
    for side in (-1, 1):
        zs = z[top::-1] if side < 0 else z[top:]
        deepest = np.maximum.accumulate(zs)
        up = (deepest - zs > climb).nonzero()[0]
        if up.size == 0:
            continue
        j = int(zs[: up[0]].argmax())  # the deepest point before the climb
        drop = zs[j] - zs[0]
        if drop < 2 * climb or np.diff(zs[: j + 1]).max() > 0.5 * drop:
            continue  # no flank followed down before it (none, or a jump between lines)
        if zs[up[0] :].max() > zs[j] + climb:
            continue  # the flank goes on deeper past the climb: an excursion onto a layer
        if side < 0:
            keep[0] = top - j
        else:
            keep[1] = top + j + 1
    a, b = keep
    if (a, b) == (0, n):
        return cand
    return cand.kept_run(a, b)


def _mark_branches(
    out: list[BoneCandidate],
    shapes: list[np.ndarray],
    ev: EvidenceMaps,
    spacing: tuple[float, float],
    p: ShadowPathParams,
) -> list[BoneCandidate]:
    """``out`` (followed down their flanks) with each layer branching off another
    candidate's contour flagged ``echo_beneath`` (no first interface). ``shapes``: each
    candidate's own contour as the piece judged (its settled points, before
    :func:`_past_the_settled_wall`; one per candidate, in ``out``'s order).

    A fascia leaving the bone's shoulder may be offered as a piece of its own: the last
    few mm of the bone's wall (its root) and the layer running on, level, over the
    wall's descent. The whole bone is offered in the same frame (its wall followed by
    :mod:`.flanks`). The piece lies within that contour's columns, on it at one end
    (within ``suppress_mm``, the band a path pass takes as one line) and over it on
    the half away from there (median offset more than ``suppress_mm``). Sound reached
    the wall under the layer through the layer, so the layer is no first interface:
    the same flag as :func:`_mark_echo_beneath`'s for a line over an echo. That rule
    compares the whole contours' greys, which a fascia brighter than a steep wall's
    echo passes (0.6 of it here); and a piece shorter than ``shoulder_min_mm`` with
    2-4 mm of wall kept is too short for :func:`_shoulder_cut`.

    It generalises because it is the geometry of two candidates of one frame against
    each other, in mm, with the band the passes already use: no new constant and no
    grey level. Only a piece that leaves a longer contour and rises over it is flagged:
    the bone's own apex piece lies on the whole contour at every column; a far cortex
    or a copy lies under the bone, not over it; and the whole contour itself, which has
    nothing over it that shares its root, is never flagged. A bone's piece over a longer
    contour that dives under it would have to be a path into the bone's own shadow
    (gains under the null level), which the optimal path does not take over the bright
    bone.
    (Measured: hard tibia seed 5, frame 24, under the nulls over tissue: the piece
    x 98-122, 4 mm of wall and the fascia's root, 3.15 score x mm against the whole
    bone's 2.48, linked the track to the fascia in frame 25, 2.6 mm off; flagged, both
    frames are on the bone, 0.09 mm; see Testing/benchmarks/README.md, branch tlayer.)
    """
    if len(out) < 2:
        return out
    same = mm_to_px(p.suppress_mm, spacing[1])
    res = list(out)
    # Each b's points in lateral order, made once (not again for every a: the same array).
    ordered: dict[int, np.ndarray] = {}
    for i, (a, pa) in enumerate(zip(out, shapes, strict=True)):
        if a.reverberation or a.echo_beneath or pa.shape[0] < 2:
            continue
        lo, hi = pa[:, 0].min(), pa[:, 0].max()
        for j, b in enumerate(out):
            if j == i or b.reverberation or b.echo_beneath:
                continue
            if j not in ordered:
                ordered[j] = b.points_px[b.points_px[:, 0].argsort(kind="stable")]
            pb = ordered[j]
            if lo < pb[0, 0] - ev.fx or hi > pb[-1, 0] + ev.fx:
                continue  # not within b's columns (to a working column)
            off = np.interp(pa[:, 0], pb[:, 0], pb[:, 1]) - pa[:, 1]  # +: b under a
            if abs(off[0]) <= same:
                far = off[off.size // 2 :]  # the half away from the root
            elif abs(off[-1]) <= same:
                far = off[: (off.size + 1) // 2]
            else:
                continue  # no root on b's contour
            if median1d(far) <= same:
                continue  # on b (or under it): no branch
            res[i] = dataclasses.replace(a, echo_beneath=True)
            break
    return res


def _past_the_settled_wall(
    before: BoneCandidate,
    after: BoneCandidate,
    spacing: tuple[float, float],
    p: ShadowPathParams,
    min_cols: int,
) -> BoneCandidate:
    """``after`` (``before`` settled, :mod:`.settle`) without a layer left beyond the
    wall the settle found.

    A fascia crossing the bone's shoulder just over it: the path runs from the dome onto
    it and on, and the settle moves the points where the bone's wall lies under the
    layer down onto the wall, leaving the layer's points beyond (where the wall is
    deeper than the settle looks) on the layer. Going outward from the apex a long
    bone's cross-section only descends (it is convex). Where the outermost settled
    points on a side are a wall (two or more consecutive points, descending outward)
    and every point beyond them lies more than ``valley_mm`` (five times the contour's
    jitter) over its foot, those points cannot be the bone and are dropped, when they
    run at least ``min_cols`` (``min_length_mm``: shorter runs are speckle, the
    passes' own rule; a point or two past the foot is the flank trace's). A single
    settled point (a grain; on the L14 cadaver copy one such point would have dropped
    20 points of a candidate) or a side whose outer part comes back down to the foot
    (the dome going on) drops nothing. It generalises because it is the convexity of a
    long bone's cross-section, in mm, on the contour the settle gives, with the
    settle's own finding of where the wall is; no new constant, no grey level. Strength
    unchanged, as for the settle. (Measured: standard clavicle seed 1 with corrupted
    frames, frame 11 under the nulls over tissue: columns 99-112 kept on the fascia,
    1.5-4.4 mm off; see Testing/benchmarks/README.md, branch tlayer.)
    """
    pa, pb = before.points_px, after.points_px
    n = pb.shape[0]
    if pb is pa or pa.shape != pb.shape or n < 2 * min_cols:
        return after
    moved = np.flatnonzero(np.abs(pb[:, 1] - pa[:, 1]) > 0)
    if moved.size == 0:
        return after
    z = pb[:, 1] * float(spacing[1])
    top = _apex(pb[:, 0] * float(spacing[0]), z)
    lift = p.valley_mm
    keep = np.ones(n, bool)
    for side in (-1, 1):
        ms = moved[moved < top][::-1] if side < 0 else moved[moved > top]
        if ms.size < 2:
            continue
        # The settled run at the outer end: consecutive points, descending outward.
        breaks = np.flatnonzero(np.abs(np.diff(ms)) > 1)
        run = ms[breaks[-1] + 1 :] if breaks.size else ms
        if run.size < 2 or z[run[-1]] <= z[run[0]]:
            continue
        o = int(run[-1])
        beyond = slice(0, o) if side < 0 else slice(o + 1, n)
        if len(range(n)[beyond]) >= min_cols and z[beyond].max() < z[o] - lift:
            keep[beyond] = False
    if keep.all() or keep.sum() < min_cols:
        return after
    return dataclasses.replace(after, points_px=pb[keep], intensity=after.intensity[keep])


def _shadowed_span(c: dict, cands: list[dict]) -> tuple[int, int] | None:
    """Column span of a candidate flagged ``beneath`` (in a shadow, or under a
    brighter line: :func:`_mark_echo_beneath`) lying under ``c`` over most of its own
    columns, or None: ``c`` is then what shadows it, one reflector over that span."""
    for b in cands:
        if b is c or not b.get("beneath") or b.get("reverb"):
            continue
        common = _common(c, b)
        if (
            common.size >= 0.5 * b["cols"].size
            and median1d(b["dense"][common] - c["dense"][common]) > 0
        ):
            return int(b["cols"].min()), int(b["cols"].max())
    return None


def _underside_step(lr: np.ndarray, cols: np.ndarray, rows: np.ndarray, dy: float) -> np.ndarray:
    """Per point of a contour (working pixels): the log ratio ``lr`` just above it less
    the log ratio just under it (0.5-2 mm each side, past the echo's own blur).

    Under a bone's wall lies its shadow, darker than the tissue over the wall: a step
    of a few tenths or more; under a layer of soft tissue lies tissue as bright as over
    it (about 0), or the bone's own echo where the layer lies on it (negative). ``lr``
    is the frame's log ratio to the tissue beside at each depth, so a shaded column (a
    skin gap over it) darkens both sides alike and the step holds. (Measured: starting
    the window under it at ``shadow_gap_mm`` instead, past a real echo's tail, cost the
    L14 recording's grey-shadow copy flank coverage 0.66 -> 0.62.)
    """
    h = lr.shape[0]
    a = max(1, mm_to_px(0.5, dy))
    b = max(a + 1, mm_to_px(2.0, dy))
    k = np.arange(a, b + 1)
    below = lr[_clip_rows(rows[:, None] + k, 0, h - 1), cols[:, None]].mean(axis=1)
    above = lr[_clip_rows(rows[:, None] - k, 0, h - 1), cols[:, None]].mean(axis=1)
    return above - below


def _cut_at_shoulder(
    pts: np.ndarray,
    cols: np.ndarray,
    rows: np.ndarray,
    strength: float,
    ev: EvidenceMaps,
    step: Callable[[], np.ndarray],
    spacing: tuple[float, float],
    p: ShadowPathParams,
    min_cols: int,
) -> tuple[np.ndarray | None, float]:
    """A candidate's points (``pts``, on working ``cols``, ``rows``) with a layer running
    off the bone's shoulder cut off (:func:`_shoulder_cut`; ``step``: its underside
    steps, computed only when a turn is found): the mask of the points kept, or None when
    nothing is cut or too little (under ``min_cols``) would be left, and the strength.

    A long layer cut off takes its evidence with it (the strength is recomputed over the
    points kept); a short one leaves the candidate's strength as it was: its windows
    hold the bone's own shadow (why the path ran on along it), and recomputed the hard
    tibia's bone candidates fell under their far cortex's (seed 5, frame 35: 3.4 -> 0.4
    score x mm). One rule for the frame's own passes and the guided search
    (:mod:`.recovery`).
    """
    keep = _shoulder_cut(pts, spacing, step, p)
    if keep.sum() < min_cols or keep.all():
        return None, strength
    if _cut_mm(pts, keep, spacing[0]) >= p.shoulder_min_mm:
        strength = float((ev.score[rows[keep], cols[keep]] - p.null_z).sum() * ev.dx)
    return keep, strength


def _cut_mm(pts: np.ndarray, keep: np.ndarray, sx: float) -> float:
    """Lateral extent (mm) of the longest run cut off either end of ``pts`` by ``keep``."""
    k = np.flatnonzero(keep)
    runs = [pts[: k[0]], pts[k[-1] + 1 :]]
    return max((float(np.ptp(r[:, 0])) * sx for r in runs if len(r) > 1), default=0.0)


def _hops_up(xo: np.ndarray, z: np.ndarray, up: float, run: float) -> bool:
    """Whether a contour's part outward from a turn (``xo`` mm from it, depths ``z`` mm)
    climbs by at least ``up`` from one point to the next (the path stepping from one
    line onto another over it) and runs on at least ``run`` mm past that step."""
    k = np.flatnonzero(z[:-1] - z[1:] >= up)
    return bool(k.size and xo[-1] - xo[k[0] + 1] >= run)


def _shoulder_cut(
    pts: np.ndarray,
    spacing: tuple[float, float],
    step: np.ndarray | Callable[[], np.ndarray],
    p: ShadowPathParams,
) -> np.ndarray:
    """Mask of a convex piece without a layer running off the bone's shoulder.

    A fascia running off the bone at its level meets the dome where the wall is still
    gentle, so :func:`convex_part` (a turn from descending at least ``kink_slope``)
    lets it through, and the path follows it, level or gently descending, past the
    bone's wall: the contour is kept 1-3 mm off the bone on average, or the sweep's
    track slides along the layer onto a wrong structure. Two things tell the layer from
    the wall, both measured on this contour in this frame:

    * **shape**: going outward from the apex a convex bone only steepens; the layer
      turns flatter: its descent over ``2 kink_mm`` outward falls under half the
      descent over ``kink_mm`` just inside, which is at least ``shoulder_slope``; and
      it runs on for at least ``shoulder_min_mm`` (a shorter gentle stretch may be the
      bone's own relief);
    * **what lies under it** (:func:`_underside_step`): under the wall the bone's
      shadow, under the layer tissue or the bone's echo. The part beyond the turn is
      cut only when its median step is under ``shoulder_step_ratio`` of that of the
      part inside it (a ratio of the contour's own values: no grey level).

    The turn is sought outward from the apex (:func:`_apex`, in the middle 60 % of the
    span) and, when the contour's shallowest point lies at one of its ends, inward from
    that end too: the path ran along a layer rising gently towards the bone and climbed
    the bone's wall where the two met, and stopped there (radius, hard, seed 43: the
    apex of the middle lay on the layer, which linked the bone of one frame to the layer
    of the next). Seen from that end the climb is the wall and the long gentle stretch
    the layer: the same turn and the same underside ratio decide, and two things of the
    shape that premise implies. The layer beyond lies wholly under the wall's foot and
    falls away from it (it rises towards the bone and meets the wall there), never
    rising back by more than the least descent the turn asks of the wall
    (``shoulder_slope`` over ``kink_mm``): a dome beyond, or a hook at the other end, is
    not it (under a grey shadow the underside of the bone is as noisy as a layer's, and
    the ratio alone cut domes away and kept a hook onto a layer over them: clavicle seed
    13 lost 4 frames, humerus seed 43 one). And the contour is no bowl (both ends over
    its middle third: the far cortex, whose ends are its shallowest points whatever lies
    beyond them). It generalises because nothing in it depends on which end the bone is
    at, and all of it is the contour's own shape and the ratio of its own underside
    steps: no grey level and no new constant.

    **A shorter layer** (``shoulder_short_mm`` up to ``shoulder_min_mm`` beyond the turn,
    off the apex's sides only) is cut as well where the bone's shadow is clear under the
    part inside (its median step at least ``shoulder_short_step``, a log ratio of the
    frame's grey levels) and the underside ratio holds, when the part kept is at least
    ``shoulder_min_mm`` wide and the part beyond never rises over the turn by more
    than the least descent the turn asks of the wall (``shoulder_slope`` over
    ``kink_mm``), nor descends over its whole extent by more than ``shoulder_slope`` per
    mm (a wall flattening to a part that still descends is the bone's flank: hard tibia,
    seed 5 with its first quarter bone-free, frame 24, a left flank near a vessel
    descending 23 degrees was cut, and the track then kept the fascia alone in frames
    25, 28 and 29, 2.6-3.4 mm off): a fascia leaving the crest at the bone's level runs
    level or falls away gently, and the path follows it 4-7 mm before its windows leave the bone's shadow
    (hard tibia, seed 5, frames 24-35: 148 of 941 kept points over 1 mm from the bone,
    38 of 1001 with the cut). A shorter part kept leaves the track's links and the
    recovery's band (both on the contour without the rim's points) too little to go on:
    cut to 5 mm, the same tibia's frame 35 gave its neighbours a 3 mm band, their faint
    tops were not found and frames 36-39 were lost (recall 0.975 -> 0.9); a layer
    climbing over the turn is :func:`convex_part`'s and the excursions'.
    **A hop onto a layer over the turn.** The short part beyond may rise over the turn
    when it gets there by a hop: one point to the next ``valley_mm`` or more shallower
    (five times the contour's jitter; the path stepping from the bone onto a line over
    it, which a bone's surface, descending outward from its apex, never does), onto a
    layer running on at least ``shoulder_short_mm`` past the hop (the short layer's own
    floor; a shorter climb at the end is the end's rule, see above, and a dome beyond
    rises smoothly: both keep the rule above). The underside ratio still
    decides, and the cut is at the turn as for any short layer (standard clavicle seed
    1 with corrupted frames, frame 13, under the nulls over tissue: the path hopped
    0.9 mm up onto a fascia crossing the right shoulder and ran on 4 mm, 2-3.5 mm off
    the bone). Cutting at the hop instead kept a 5 mm piece of the hard tibia's
    shoulder (seed 5, frame 24) that linked the track to the fascia in frame 25.
    ``shoulder_min_mm`` stays the floor where the shadow is
    faint or absent: a bone that passes sound (the L14 forearm, whose 5-7 mm plateau
    before its flank that floor was set for) has no step under its dome (0.02-0.25 on
    most of its turns), and there a gentle stretch beyond a turn may be its own relief.
    It generalises for the reasons above: the contour's shape, and the underside steps
    as ratios of the frame's own grey levels (a shadow at most ~0.74 of the tissue over
    it; the cadaver's 0.65 passes); no absolute grey level.

    Lengths and slopes in mm, so the rule holds at any pixel size. The first such turn
    from the apex on each side is cut; the cut end is followed down the wall by
    :mod:`.flanks` where its echo holds. ``step`` is the step per point, or a function
    giving it (computed only when a turn is found: most contours have none).
    """
    n = pts.shape[0]
    keep = np.ones(n, bool)
    if n < 8:
        return keep
    x = pts[:, 0] * float(spacing[0])
    z = pts[:, 1] * float(spacing[1])
    top = _apex(x, z)  # as convex_part takes it
    w_in, w_out = p.kink_mm, 2.0 * p.kink_mm
    # From the contour's shallowest point too when it lies at an end (outside the middle
    # 60 % that _apex looks in) and the contour is no bowl: inwards only (see above).
    end = int(np.argmin(z))
    sides = [(top, -1), (top, 1)]
    e, mid = max(1, n // 6), median1d(z[n // 3 : n - n // 3])
    if end != top and not (median1d(z[:e]) < mid and median1d(z[-e:]) < mid):
        sides.append((end, -1 if end > top else 1))
    for start, side in sides:
        idx = np.arange(start, -1, -1) if side < 0 else np.arange(start, n)
        # A short layer (under shoulder_min_mm) only off the apex's sides (see above).
        least = min(p.shoulder_min_mm, p.shoulder_short_mm) if start == top else p.shoulder_min_mm
        if idx.size < 6 or abs(x[idx[-1]] - x[start]) < least + 0.5 * w_in:
            continue  # too short a side to hold a turn and a layer beyond it
        xo = np.abs(x[idx] - x[start])
        k, lo, s_in, s_out, ok = _outward_slopes(xo, z[idx], w_in, w_out)
        ok &= xo[k] - xo[lo] >= 0.5 * w_in
        ok &= xo[-1] - xo[k] >= least
        for kk in k[ok & (s_in >= p.shoulder_slope) & (s_out < 0.5 * s_in)]:
            if callable(step):
                step = step()
            beyond = xo[-1] - xo[kk]
            if beyond < p.shoulder_min_mm and (
                median1d(step[idx[: kk + 1]]) < p.shoulder_short_step
                or abs(x[idx[kk]] - x[n - 1 if side < 0 else 0]) < p.shoulder_min_mm
                or (
                    z[idx[kk + 1 :]].min() < z[idx[kk]] - p.shoulder_slope * w_in
                    and not _hops_up(xo[kk:], z[idx[kk:]], p.valley_mm, p.shoulder_short_mm)
                )
                or z[idx[-1]] - z[idx[kk]] > p.shoulder_slope * beyond
            ):
                continue
            if start != top:
                # A layer falling away from the wall's foot: wholly under the foot, and
                # never rising back by the least descent the turn asks of the wall.
                zb = z[idx[kk + 1 :]]
                if (
                    zb.min() < z[idx[kk]]
                    or (np.maximum.accumulate(zb) - zb).max() > p.shoulder_slope * w_in
                ):
                    continue
            si, sb = median1d(step[idx[: kk + 1]]), median1d(step[idx[kk + 1 :]])
            if si > 0 and sb < p.shoulder_step_ratio * si:
                keep[idx[kk + 1 :]] = False
                break
    return keep


#: Half-width of the gap between two bones side by side, mm: the bottom of a dip whose
#: shadow tells that gap from a groove in one bone (:func:`_valley_runs`), and half the
#: least gap between a path's best piece and a second bone's (:func:`_separate_domes`).
#: The gap is a few mm of tissue; its edges are the bones' flanks.
_GAP_MM = 1.0


def _separate_domes(
    pieces: list[tuple[float, np.ndarray, np.ndarray, np.ndarray]],
    best: tuple[float, np.ndarray, np.ndarray, np.ndarray],
    pts: np.ndarray,
    spacing: tuple[float, float],
    p: ShadowPathParams,
    min_cols: int,
) -> list[tuple[float, np.ndarray, np.ndarray, np.ndarray]]:
    """The pieces of one path, besides ``best``, that are domes of their own: evidence
    above the null level, beside ``best`` (no column in common), both ends at least
    ``dome_mm`` deeper than the piece's apex (:func:`_apex`), over at least ``min_cols``
    working columns (:func:`_piece_is_dome`).

    One optimal path may run over two bones side by side (the radius and the ulna, the
    tibia and the fibula) without leaving them for the no-bone state over the few mm
    of tissue between them: its convex pieces are then the two bones, and only the
    piece with the most evidence was offered, so the other bone had no candidate in
    that frame (simulated forearm, ulna 18 mm beside the radius swept: the radius had
    none in frames 0-5 of seed 127, and the track followed the ulna there). A layer
    running off the bone's shoulder, the other piece a path usually leaves, is flat or
    falls one way: no dome. Offered as candidates of their own, each with its own
    evidence, they let the sweep-level choice take the bone it follows in every frame.
    No gap is asked between the two pieces: bones 14 mm apart touch in the image, and
    the path's pieces over them met at the valley (radius and ulna, 320 x 256 at 0.16
    mm: an ulna 0.1 of the half-width off the middle had no candidate in 8 of 12 frames
    with a 2 mm gap asked). A crest's corners part its contour into pieces that touch
    too, but of those only the top is a dome: at worst its top is offered besides its
    flank, both on the bone. Geometry of the contour alone, in mm: no grey level.
    """
    return [
        q
        for q in pieces
        if q[0] > 0 and not (q[1] & best[1]).any() and _piece_is_dome(pts, q, spacing, p, min_cols)
    ]


def _piece_is_dome(
    pts: np.ndarray,
    piece: tuple[float, np.ndarray, np.ndarray, np.ndarray],
    spacing: tuple[float, float],
    p: ShadowPathParams,
    min_cols: int,
) -> bool:
    """Whether a convex piece of a path (its mask into ``pts``, points in pixels) may be
    a bone's top of its own: a dome (:func:`_is_dome`) over at least ``min_cols`` working
    columns (the passes' shortest contour). A shorter hump is a grain: offered, a 2.8 mm
    one of 4 points beside a hard tibia's top took the track and was rejected as too
    short. (A distance asked between two tops was tried and dropped: a path's pieces
    need not part at the valley; one ran from the ulna's top over the valley up the
    radius's flank, its shallowest point beside the radius's top.) Geometry in mm: no
    grey level."""
    if piece[2].size < min_cols:
        return False
    m = piece[1]
    return _is_dome(pts[m, 0] * spacing[0], pts[m, 1] * spacing[1], p.dome_mm)


def _is_dome(x: np.ndarray, z: np.ndarray, dome_mm: float) -> bool:
    """Whether a contour (lateral ``x``, depth ``z``, mm) has its apex (:func:`_apex`)
    inside, with both its ends at least ``dome_mm`` deeper."""
    if x.size < 3:
        return False
    k = _apex(x, z)
    return 0 < k < x.size - 1 and min(z[0], z[-1]) - z[k] >= dome_mm


def _fill_excursions(
    pts: np.ndarray, spacing: tuple[float, float], p: ShadowPathParams
) -> tuple[np.ndarray, np.ndarray]:
    """Narrow excursions above a contour: the mask of the points outside them, and the
    points with each excursion filled in (moved down onto the contour's closing).

    The optimal path may hop, for a few columns, onto a bright grain or a short layer
    just above the bone (up and back down within ``min_length_mm``: shorter runs are
    speckle, the passes' own rule) and the shallowest point of the contour is then on
    the hop: :func:`convex_part` takes it as the apex and cuts the dome on both sides of
    it into pieces, and only one piece is offered (on the hard simulated sweeps at
    0.108 mm a dome of 12 mm came out as its 6 mm right half). A bone's surface has no
    bump that narrow (a crest's top is ~5 mm wide): the points lying more than
    ``valley_mm`` above the contour's morphological closing over ``min_length_mm`` (the
    depth profile with every upward excursion narrower than that filled in), with the
    whole excursion down to a fifth of that (its feet), are dropped. The convex cut is
    made on the filled-in contour, not on one with a gap where the excursion was: a hop
    where a layer meets the dome's side leaves the layer's turn onto the dome in the
    filled contour (the cut sees it), while across a gap wider than ``kink_mm`` the cut
    sees nothing (clean clavicle seed 0, frame 13: 1.6 mm of layer kept). Depths and
    widths in mm, so it holds at any pixel size; no grey level.
    """
    n = pts.shape[0]
    keep = np.ones(n, bool)
    x = pts[:, 0] * float(spacing[0])
    span = float(x[-1] - x[0]) if n else 0.0
    if n < 6 or span <= 2 * p.min_length_mm:
        return keep, pts
    z = pts[:, 1] * float(spacing[1])
    if float(z.max() - z.min()) < p.valley_mm:
        return keep, pts  # no room for an excursion that high
    # On a regular grid of the contour's own lateral sampling (gaps bridged linearly).
    dx = span / (n - 1)
    grid = x[0] + dx * np.arange(n)
    regular = bool(np.abs(x - grid).max() < 1e-6 * max(dx, 1e-9))
    zg = z if regular else np.interp(grid, x, z)
    size = max(3, ceil_px(p.min_length_mm / dx) | 1)
    # The morphological closing (maximum then minimum filter, as grey_closing).
    closed = minimum_filter1d(maximum_filter1d(zg, size, mode="nearest"), size, mode="nearest")
    if not regular:
        closed = np.interp(x, grid, closed)
    lift = closed - z
    if not (lift >= p.valley_mm).any():
        return keep, pts
    # The whole excursion goes, down to the contour's jitter (a fifth of valley_mm):
    # its feet too, or the stump left on the dome is taken for its apex.
    out = lift > 0.2 * p.valley_mm
    # Where the padded mask changes: np.diff of np.r_[False, out, False] (not_equal of
    # neighbours, for booleans) without np.r_'s and np.diff's Python layers.
    pad = np.zeros(out.size + 2, bool)
    pad[1:-1] = out
    edges = (pad[1:] != pad[:-1]).nonzero()[0]
    for a, b in zip(edges[::2], edges[1::2], strict=True):
        if lift[a:b].max() >= p.valley_mm:
            keep[a:b] = False
    filled = pts.copy()
    filled[~keep, 1] = closed[~keep] / float(spacing[1])
    return keep, filled


def _valley_runs(
    pts: np.ndarray,
    spacing: tuple[float, float],
    valley_mm: float,
    shadow: np.ndarray,
    dome_mm: float = ShadowPathParams.dome_mm,
) -> list[np.ndarray]:
    """Index runs of a contour split where a layer meets the bone in a valley.

    A long bone's top seen from the probe is mostly one dome. A dip deeper than
    ``valley_mm`` below the shallowest point on *each* side of it is either where a
    layer meets the bone (a fascia crossing its flank and climbing away from it) or a
    groove in the bone itself (the bicipital groove, the grooves beside Lister's
    tubercle). The bone casts its shadow on both sides of a groove; a layer has tissue
    beneath it. So the contour is cut at the dip's deepest point only when one side has
    less than a third of the other side's shadow (median shadow z-score: units of this
    frame's own spread, so the rule holds at any gain or contrast; measured: a fascia
    meeting the clavicle 0.06-0.19 of the bone's side, a concave bone surface spanning
    the image whose deep side's shadow windows reach the image bottom 0.43-0.46); a
    groove stays whole. Depths are in mm, so the rule holds at any pixel size. Each cut point is in
    both runs.

    Nor is a dip whose sides both cast a shadow and are domes of their own (an apex
    inside, both ends ``dome_mm`` deeper) and whose bottom (the points within ``_GAP_MM``
    of its deepest, laterally) has less than a third of the lesser side's a groove: the
    bone under a groove casts its shadow there too, while between two bones side by side
    (the radius and the ulna, the tibia and the fibula) lies tissue. (A concave surface
    spanning the image has no tissue beside its deepest stretch to measure the shadow
    against, so its bottom reads as shadowless too; its sides are no domes.) On a
    simulated forearm with the ulna 18 mm beside the radius swept, one path ran over
    both (sides 0.45 and 0.42, the gap's bottom -0.5), and the track crossed from the
    ulna to the radius over that one contour (seed 127, frames 0-6).
    """
    n = pts.shape[0]
    z = pts[:, 1] * float(spacing[1])
    left = np.minimum.accumulate(z)
    right = np.minimum.accumulate(z[::-1])[::-1]
    dip = np.minimum(z - left, z - right)
    deep = (dip >= valley_mm).nonzero()[0]
    if deep.size == 0:
        return [np.arange(n)]
    cuts = []
    for r in _runs(deep):
        k = int(r[np.argmax(dip[r])])
        a, b = median1d(shadow[: k + 1]), median1d(shadow[k:])
        if min(a, b) < max(a, b) / 3.0:
            cuts.append(k)
        elif min(a, b) > 0:
            # Two shadows with tissue between: two bones side by side, not a groove.
            x = pts[:, 0] * float(spacing[0])
            near = np.abs(x - x[k]) <= _GAP_MM
            if (
                median1d(shadow[near]) < min(a, b) / 3.0
                and _is_dome(x[: k + 1], z[: k + 1], dome_mm)
                and _is_dome(x[k:], z[k:], dome_mm)
            ):
                cuts.append(k)
    bounds = [0, *cuts, n - 1]
    return [np.arange(a, b + 1) for a, b in zip(bounds[:-1], bounds[1:], strict=True)]


def _convex_pieces(
    pts: np.ndarray,
    spacing: tuple[float, float],
    p: ShadowPathParams,
    min_cols: int,
    shadow: np.ndarray | None = None,
) -> list[np.ndarray]:
    """Masks of the convex pieces of a contour: the part around each apex, then each run cut off.

    A path that runs from the bone onto a layer meeting it (a fascia climbing off the
    crest) is two structures. With ``shadow`` (the shadow z-score at each point) the
    contour is first split where a layer meets the bone in a valley
    (:func:`_valley_runs`); in each part, when the layer climbs above the bone's top,
    the apex lies on the layer and :func:`convex_part` keeps the layer. Every run cut
    off (at least ``min_cols`` points) is offered too, as its own candidate with its own
    evidence, so the sweep-level choice sees the bone whichever piece holds the apex.
    """
    pieces: list[np.ndarray] = []
    n = pts.shape[0]
    runs = [np.arange(n)]
    if shadow is not None:
        runs = _valley_runs(pts, spacing, p.valley_mm, shadow, p.dome_mm)
        runs = [r for r in runs if r.size >= min_cols]
    for part in runs or [np.arange(n)]:
        keep = np.zeros(n, bool)
        keep[part[convex_part(pts[part], spacing, p)]] = True
        pieces.append(keep)
        rest = part[~keep[part]]
        if rest.size >= min_cols:
            for run in _runs(rest):
                if run.size >= min_cols:
                    sub = run[convex_part(pts[run], spacing, p)]
                    if sub.size >= min_cols:
                        m = np.zeros(n, bool)
                        m[sub] = True
                        pieces.append(m)
    return pieces


def candidates_from_points(
    image: np.ndarray,
    points_px: np.ndarray,
    spacing: tuple[float, float],
    params: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
    reason: str = "no bone found",
    extras: dict | None = None,
) -> FrameCandidates:
    """Wrap another segmenter's contour (the snake's) as the one candidate of a frame.

    Its strength is measured on the same evidence maps as shadowpath's candidates, so
    the sweep-level choice treats every segmenter alike.
    """
    sp = (float(spacing[0]), float(spacing[1]))
    ex = dict(extras or {})
    pts = np.asarray(points_px, dtype=float).reshape(-1, 2)
    if pts.shape[0] == 0:
        return FrameCandidates((), sp, reason, ex)
    ev = bone_evidence(image, sp, params)
    if ev is None:
        return FrameCandidates((), sp, "image too small", ex)
    rj, ci = ev.work_index(pts)
    s = ev.score[rj, ci]
    length = float(np.ptp(pts[:, 0]) * sp[0]) if len(pts) > 1 else 0.0
    strength = float(np.mean(s - params.null_z) * length)
    cand = BoneCandidate(
        pts,
        sample_bilinear(np.asarray(image), pts),
        strength,
        float(np.median(ev.echo_z[rj, ci])),
        float(np.median(ev.shadow_z[rj, ci])),
    )
    return FrameCandidates((cand,), sp, "", ex, _fov_px(ev), ev.frame_level())

"""Sweep-level step: one bone track through the candidates of all frames.

:func:`select_bone_track` chooses at most one candidate per frame so that the chosen
contours form one continuous surface in 3D, by a longest path through a directed
acyclic graph (a Viterbi over frames that may skip up to ``max_skip`` frames):

* a node is a candidate; its value is its strength relative to the sweep's own typical
  strength (the median over frames of each frame's strongest candidate), capped at
  ``strength_cap``: sweep-level normalisation, so a faint recording and a bright one
  are judged alike;
* an edge links a candidate of frame ``f`` to one of frame ``g`` (``f < g <= f +
  max_skip + 1``); its cost is ``(d / tol)^2`` where ``d`` is the median in-plane
  distance (mm) from the points of ``g``'s candidate to ``f``'s contour projected into
  ``g``'s plane through both poses (``ImageToReference``), and ``tol = tolerance_mm +
  tolerance_per_mm * z`` grows with ``z``, the distance (mm) between the contours
  along the sweep (out of plane). It is a distance to a contour, not a depth at a
  column, so a steep flank that slides sideways between frames is no jump. Contours
  farther apart than ``max_deviation`` tolerances, or not overlapping, are not linked;
  nor is a contour lying wholly a step (``max_step_mm + step_per_mm * z``) under or
  over the other: the tolerance's growth along the sweep is for a surface inclined to
  it (its flanks sliding sideways), while a whole contour a step under the bone's is
  its far cortex or a reverberation band in its shadow;
* each skipped frame costs ``miss_cost``; so does a frame with candidates past the
  track's ends (:func:`_extend_ends`: the chosen track is carried on through nodes in
  its lane where their value and that credit beat their links' cost).

The tolerance is the sweep's own where its contours demand it: a tracker's noise moves
every frame's contour in its neighbours' planes, however exact the segmentation, and a
tolerance set for an optical tracker breaks an electromagnetic one's track at one frame
in seven. The least deviation between the contours of consecutive frames, on median
over the sweep, is the sweep's frame-to-frame deviation; where it is
``min_tolerance_scale`` times ``typical_deviation`` tolerances or more and the poses
jitter (``pose_jitter_mm``), both terms of the tolerance are scaled up so that it is
``typical_deviation`` (:func:`tolerance_scale`; with exact poses, a steady hand's or an
unsteady one's, or over an anatomy that changes fast under smooth poses, it stays).

A caller may rule frames out beforehand (``exclude``: the frames :mod:`.ends` judged
bone-free): their candidates are no nodes, and they keep the reason given.

Where two bones are in view the track follows the one near the middle of the image
(:func:`central_track`), or, given the user's bone points (``bone_points``), the one
through them (:func:`pointed_track`, :mod:`.bone_point`).

One decision over the whole sweep: no prior chained from an earlier frame, no rounds
of rejection. Frames whose candidates are all off the track are rejected as "jump from
neighbouring frames" (the distance to the track is in the frame's ``detail``).
"""

from __future__ import annotations

from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, replace

import numpy as np

from BoneUSRecon.Logic.segmentation.bone_point import OFF_POINT, point_marks
from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate, FrameCandidates
from BoneUSRecon.Logic.segmentation.features import median1d
from BoneUSRecon.Logic.segmentation.params import RejectionParams
from BoneUSRecon.Logic.sweep import frame_planes, pixels_to_reference

__all__ = ["TrackChoice", "select_bone_track", "tolerance_scale", "scale_warnings", "REASONS"]

#: Rejection reasons (one category each; values go to ``FrameContour.detail``).
REASONS = {
    "none": "no bone found",
    "jump": "jump from neighbouring frames",
    "short": "contour too short",
    "reverb": "reverberation copy",
    "weak": "no bone evidence along the contour",
    "noshadow": "no bone shadow under it (sweep end)",
    "offpoint": OFF_POINT,
}

_SAMPLE_MM = 0.5  # contours are compared at ~this point spacing (speed; 1-2 px apart)

#: A frame's plane: origin, in-plane axes, normal (reference mm; :func:`frame_planes`).
Plane = tuple[np.ndarray, np.ndarray, np.ndarray]
#: A node's contour in its own plane, (lateral, depth) mm, and its box there
#: (:func:`_node_points`).
PlaneNode = tuple[np.ndarray, tuple[float, float, float, float]]
#: Fewest contours off the middle that make :func:`_nearer_middle` look for a track
#: nearer it (one or two are a bone's edge or a layer for a frame or two, not a lane).
_MIN_OFF = 3
#: Shift of a track's contours' lateral middles over two frames, mm, over which a
#: shift of more than half their width is a change of lane (:func:`_shifted`).
_LANE_SHIFT_MM = 6.0
#: Track contours nearest a frame whose median span is the track's lane there
#: (:func:`_in_lane`: one contour over two bones is outvoted by its two neighbours).
_LANE_NEAREST = 3
#: Frames a chain carrying the track on past its ends may skip between two of its
#: contours (:func:`_chain`; inside the track, ``max_skip``: both sides vouch there).
_END_SKIP = 1


@dataclass(frozen=True, eq=False)
class TrackChoice:
    """The chosen candidate of every frame.

    Attributes
    ----------
    chosen : ndarray of int, shape (N,)
        Index into each frame's candidates, -1 where the frame is not on the track.
    confidence : ndarray, shape (N,)
        In [0, 1]: relative strength times continuity with the track's neighbours.
    reason : list of str
        Rejection category per frame ("" on the track).
    detail : list of str
        The value behind a rejection (e.g. "4.2 mm"), "" otherwise.
    """

    chosen: np.ndarray
    confidence: np.ndarray
    reason: list[str]
    detail: list[str]


def _sampled(pts_px: np.ndarray, spacing: tuple[float, float]) -> np.ndarray:
    """Every n-th point so that consecutive points are ~``_SAMPLE_MM`` apart."""
    step = max(1, int(round(_SAMPLE_MM / max(float(spacing[0]), 1e-6))))
    if pts_px.shape[0] <= 2 * step:
        return pts_px
    return pts_px[::step]


def _project(
    a_ref: np.ndarray, origin: np.ndarray, axes: np.ndarray, normal: np.ndarray
) -> np.ndarray:
    """Contour ``(K, 3)`` mm into a frame's plane: ``(K, 3)`` = lateral, depth, |out of plane| mm."""
    rel = a_ref - origin
    # The three columns filled in place: np.column_stack's values without its wrapper
    # (called once per pair of frames and contour, ~14 per frame).
    out = np.empty((rel.shape[0], 3))
    out[:, 0] = rel @ axes[:, 0]
    out[:, 1] = rel @ axes[:, 1]
    np.abs(rel @ normal, out=out[:, 2])
    return out


def _overlap_share(a_x: tuple[float, float], b_x: tuple[float, float]) -> float:
    """The lateral overlap share of :func:`_in_plane_deviation` from the contours' lateral
    ``(min, max)`` mm: a's extent widened by 1 mm each side, relative to the shorter."""
    lo, hi = a_x[0] - 1.0, a_x[1] + 1.0
    overlap = max(0.0, min(hi, b_x[1]) - max(lo, b_x[0]))
    return overlap / max(min(hi - lo, float(b_x[1] - b_x[0]) + 2.0), 1e-6)


def _in_plane_deviation(
    a: np.ndarray,
    b_mm: np.ndarray,
    *,
    a_x: tuple[float, float] | None = None,
    b_x: tuple[float, float] | None = None,
) -> tuple[float, float, float]:
    """``(median in-plane distance mm, overlap share, median out-of-plane mm)`` of b to a.

    ``a``: contour a projected into b's plane (:func:`_project`); ``b_mm``: b's
    ``(lateral, depth)`` mm in its own plane. The overlap is relative to the shorter of
    the two contours (a partial contour of the bone overlaps a full one completely).
    ``a_x``, ``b_x``: the lateral ``(min, max)`` of a and b when the caller has them
    already (:func:`_links`: its boxes; the same values, fewer numpy calls per pair).
    """
    ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
    bx, by = b_mm[:, 0], b_mm[:, 1]
    a_min, a_max = a_x if a_x is not None else (ax.min(), ax.max())
    lo, hi = a_min - 1.0, a_max + 1.0
    bx_min, bx_max = b_x if b_x is not None else (bx.min(), bx.max())
    share = _overlap_share((a_min, a_max), (bx_min, bx_max))
    if bx_min < lo or bx_max > hi:
        inside = (bx >= lo) & (bx <= hi)
        if not inside.any():
            return np.inf, 0.0, median1d(az)
        bx, by = bx[inside], by[inside]
    # Squared distances built in place (the same operations as the plain expression).
    d2 = np.subtract.outer(bx, ax)
    d2 *= d2
    dy = np.subtract.outer(by, ay)
    dy *= dy
    d2 += dy
    near = d2.argmin(axis=1)
    d = np.sqrt(d2[np.arange(near.size), near])
    return median1d(d), share, median1d(az[near])


def _stepped(
    a: np.ndarray,
    b_mm: np.ndarray,
    max_step_mm: float,
    *,
    a_x: tuple[float, float] | None = None,
    a_sorted: tuple[np.ndarray, np.ndarray] | None = None,
) -> bool:
    """Whether contour b lies wholly under (or over) a, by more than ``max_step_mm``.

    ``a``, ``b_mm`` as in :func:`_in_plane_deviation`. Over their common columns, the
    depth of b less a's depth at the same lateral position: b is stepped when nine in
    ten of these have one sign and their median exceeds ``max_step_mm``. ``a_x`` (a's
    lateral min, max) and ``a_sorted`` (a's lateral and depth ordered by
    ``np.argsort`` of the lateral) may come from the caller, computed once per contour.
    """
    lo, hi = a_x if a_x is not None else (a[:, 0].min(), a[:, 0].max())
    bi = b_mm[(b_mm[:, 0] >= lo) & (b_mm[:, 0] <= hi)]
    if bi.shape[0] == 0:
        return False
    if a_sorted is None:
        o = np.argsort(a[:, 0])
        a_sorted = (a[o, 0], a[o, 1])
    step = bi[:, 1] - np.interp(bi[:, 0], *a_sorted)
    if not abs(median1d(step)) > max_step_mm:
        return False
    # Shares by counting: the same float as ``(step > 0).mean()`` (an exact count over
    # the size), without mean's per-call overhead.
    n = step.size
    return max(np.count_nonzero(step > 0) / n, np.count_nonzero(step < 0) / n) >= 0.9


def _deviation(
    a_ref: np.ndarray, b_px: np.ndarray, b_pose: np.ndarray, b_spacing: tuple[float, float]
) -> tuple[float, float, float]:
    """:func:`_in_plane_deviation` of contour b (its pixels, its pose) to a (reference mm)."""
    origin, axes, normal = frame_planes(b_pose)
    a = _project(a_ref, origin[0], axes[0], normal[0])
    return _in_plane_deviation(a, b_px * np.asarray(b_spacing, dtype=float))


# The pieces of the track that only depend on one frame, or on one pair of frames, are
# the functions below: :func:`select_bone_track` runs them over a whole sweep, and
# :class:`~.track_incremental.IncrementalTrack` (live) once per frame or pair as frames
# arrive, so both choose the same track.


def _frame_reason(fc: FrameCandidates) -> str:
    """Why a frame cannot be on the track whatever its neighbours ("" if it can)."""
    if not fc.usable:
        return REASONS["reverb"] if fc.candidates else REASONS["none"]
    if max(c.strength for c in fc.usable) <= 0:
        return REASONS["weak"]
    return ""


def _is_node(cand: BoneCandidate) -> bool:
    """A candidate the track may pass through."""
    # No evidence above the null level along the contour (e.g. a snake
    # stopped in speckle): not a candidate.
    return not cand.reverberation and cand.strength > 0


def _typical_strength(frames: Sequence[FrameCandidates]) -> float:
    """The sweep's typical strength: the median over frames of each one's strongest."""
    best = [max((c.strength for c in fc.usable), default=np.nan) for fc in frames]
    best_arr = np.asarray(best, dtype=float)
    pos = best_arr[np.isfinite(best_arr) & (best_arr > 0)]
    return float(np.median(pos)) if pos.size else 1.0


def _node_value(cand: BoneCandidate, typical: float, p: RejectionParams) -> float:
    """A node's value on a path: its strength relative to the sweep's typical one."""
    return min(max(cand.strength, 0.0) / typical, p.strength_cap) * (
        p.beneath_factor if cand.echo_beneath else 1.0
    )


def _node_points(
    cand: BoneCandidate, spacing: tuple[float, float], pose: np.ndarray
) -> tuple[np.ndarray, np.ndarray, tuple[float, float, float, float]]:
    """A node's sampled contour: reference mm, (lateral, depth) mm in its plane, and its
    bounding box there (most pairs, a fascia and the bone mm apart in depth, are ruled
    out on the boxes without the point-to-contour distances)."""
    pts = _sampled(cand.core_px, spacing)
    b = pts * np.asarray(spacing, dtype=float)
    box = (float(b[:, 0].min()), float(b[:, 0].max()), float(b[:, 1].min()), float(b[:, 1].max()))
    return pixels_to_reference(pose, pts), b, box


def _links(
    a_ref: np.ndarray,
    plane: Plane,
    b_nodes: Sequence[PlaneNode],
    p: RejectionParams,
) -> list[tuple[int, float]]:
    """Edges from contour a (reference mm) to a later frame's nodes.

    ``plane`` is that frame's ``(origin, axes, normal)``; ``b_nodes`` its nodes'
    ``(lateral-depth mm, box)`` (:func:`_node_points`). Returns ``(index into b_nodes,
    deviation d / tol)`` for each node that may follow a; the edge costs ``dev ** 2``.
    """
    return _links_many([a_ref], plane, b_nodes, p)[0]


#: Pairs of contours whose point distances :func:`_links_many` computes in one go are
#: taken in chunks of at most this many (b point, a point) distances (memory bound; a
#: 480x640 frame's ~60 pairs of ~14-35 sampled points take ~20,000-70,000).
_PAIR_CHUNK = 2**20

#: :func:`_links_many` tests the boxes of up to this many pairs of contours in a plain
#: loop, and measures up to a quarter as many pairs one at a time with the pair
#: functions (for so few, fewer numpy calls than the arrays for all at once).
_FEW_PAIRS = 12


def _links_many(
    a_refs: Sequence[np.ndarray],
    plane: Plane,
    b_nodes: Sequence[PlaneNode],
    p: RejectionParams,
) -> list[list[tuple[int, float]]]:
    """``[_links(a, plane, b_nodes, p) for a in a_refs]``: every contour ``a`` of earlier
    frames against one later frame's nodes, the same edges in the same order.

    The pairs that pass the boxes' tests are measured together: the contours hold a few
    tens of sampled points, so a pair's :func:`_in_plane_deviation` and :func:`_stepped`
    were bound by their ~40 numpy calls, not by the arithmetic (~60 pairs per frame of a
    hard 480x640 sweep). Here the pairs' points are padded to common sizes (a's with an
    infinite lateral, never the nearest; b's masked) and each quantity is one array
    operation over all pairs, elementwise the same operations as the functions' on one
    pair; the medians are order statistics of sorted rows (NaN, past the masked points,
    sorts last), :func:`~.features.median1d`'s values. Only ``np.interp`` stays per pair.
    """
    out: list[list[tuple[int, float]]] = [[] for _ in a_refs]
    if not b_nodes:
        return out
    projected: list[tuple[np.ndarray, float, float]] = []  # a, its lateral min and max
    a_box = np.empty((len(a_refs), 5))  # x0, x1, y0, y1, z1 of each a in b's plane
    for ia, a_ref in enumerate(a_refs):
        # Contour a in the later frame's plane, once for all of its candidates.
        a = _project(a_ref, *plane)
        # Column minima and maxima in two reductions (the same values as five).
        (x0, y0, _), (x1, y1, z1) = a.min(axis=0).tolist(), a.max(axis=0).tolist()
        projected.append((a, x0, x1))
        a_box[ia] = x0, x1, y0, y1, z1
    if not a_refs:
        return out
    # The pairs whose boxes may link. A box apart (laterally, or in depth by more than
    # a's reach) rules a pair out, and so does the lateral overlap share
    # (:func:`_overlap_share`, from the boxes: the value _in_plane_deviation gives;
    # about one pair in eight is ruled out on it without the point distances).
    if len(a_refs) * len(b_nodes) <= _FEW_PAIRS:
        pairs = []
        for ia, (x0, x1, y0, y1, z1) in enumerate(a_box.tolist()):
            reach = p.max_deviation * (p.tolerance_mm + p.tolerance_per_mm * z1)
            for ib, (_, bb) in enumerate(b_nodes):
                if bb[0] > x1 + 1.0 or bb[1] < x0 - 1.0 or bb[2] > y1 + reach or bb[3] < y0 - reach:
                    continue
                if _overlap_share((x0, x1), bb[:2]) >= p.min_overlap_share:
                    pairs.append([ia, ib])
    else:
        # Every a against every b at once (the same float operations as pair by pair).
        b_box = np.array([bb for _, bb in b_nodes])
        v_x0, v_x1, v_y0, v_y1, v_z1 = (a_box[:, k : k + 1] for k in range(5))
        v_reach = p.max_deviation * (p.tolerance_mm + p.tolerance_per_mm * v_z1)
        bx0, bx1, by0, by1 = b_box.T
        near_box = (bx0 <= v_x1 + 1.0) & (bx1 >= v_x0 - 1.0)
        near_box &= (by0 <= v_y1 + v_reach) & (by1 >= v_y0 - v_reach)
        v_lo, v_hi = v_x0 - 1.0, v_x1 + 1.0
        overlap = np.maximum(0.0, np.minimum(v_hi, bx1) - np.maximum(v_lo, bx0))
        share = overlap / np.maximum(np.minimum(v_hi - v_lo, (bx1 - bx0) + 2.0), 1e-6)
        pairs = np.argwhere(near_box & (share >= p.min_overlap_share)).tolist()
    if len(pairs) <= _FEW_PAIRS // 4:
        # A pair or two (e.g. a guided candidate against one frame's nodes): one at a
        # time, by the pair functions themselves (fewer numpy calls than the padding).
        for ia, ib in pairs:
            a, ax0, ax1 = projected[ia]
            b, bb = b_nodes[ib]
            dev, _, zo = _in_plane_deviation(a, b, a_x=(ax0, ax1), b_x=bb[:2])
            if not np.isfinite(dev):
                continue
            tol = p.tolerance_mm + p.tolerance_per_mm * zo
            if dev > p.max_deviation * tol:
                continue
            if not _stepped(a, b, p.max_step_mm + p.step_per_mm * zo, a_x=(ax0, ax1)):
                out[ia].append((ib, dev / tol))
        return out
    ka = max(a.shape[0] for a, _, _ in projected)
    kb = max(b.shape[0] for b, _ in b_nodes)
    a_pad = np.zeros((len(projected), ka, 3))
    a_pad[:, :, 0] = np.inf  # a padding point is infinitely far: never the nearest
    for ia, (a, _, _) in enumerate(projected):
        a_pad[ia, : a.shape[0]] = a
    b_pad = np.zeros((len(b_nodes), kb, 2))
    b_real = np.zeros((len(b_nodes), kb), dtype=bool)
    for ib, (b, _) in enumerate(b_nodes):
        b_pad[ib, : b.shape[0]] = b
        b_real[ib, : b.shape[0]] = True
    lateral = np.array([(x0, x1) for _, x0, x1 in projected])
    a_sorted: dict[int, tuple[np.ndarray, np.ndarray]] = {}  # made once per contour a
    per_chunk = max(1, _PAIR_CHUNK // (ka * kb))
    for s0 in range(0, len(pairs), per_chunk):
        chunk = pairs[s0 : s0 + per_chunk]
        ia_c = np.array([q[0] for q in chunk], dtype=np.intp)
        ib_c = np.array([q[1] for q in chunk], dtype=np.intp)
        ax, ay, az = a_pad[ia_c, :, 0], a_pad[ia_c, :, 1], a_pad[ia_c, :, 2]
        bx, by = b_pad[ib_c, :, 0], b_pad[ib_c, :, 1]
        # _in_plane_deviation of each pair: b's points within a's lateral extent +- 1 mm.
        a_lo, a_hi = lateral[ia_c, 0:1], lateral[ia_c, 1:2]
        inside = b_real[ib_c] & (bx >= a_lo - 1.0) & (bx <= a_hi + 1.0)
        d2 = bx[:, :, None] - ax[:, None, :]
        d2 *= d2
        dy = by[:, :, None] - ay[:, None, :]
        dy *= dy
        d2 += dy
        near = d2.argmin(axis=2)
        d = np.sqrt(np.take_along_axis(d2, near[:, :, None], axis=2)[:, :, 0])
        z = np.take_along_axis(az, near, axis=1)
        # Both medians from one sort (the rows of d, then those of z).
        meds = _masked_medians(np.concatenate((d, z)), np.concatenate((inside, inside)))
        d_med, z_med = meds[: len(chunk)], meds[len(chunk) :]
        near_enough = []  # (ia, ib, d, tol, z) of the pairs within the deviation
        for (ia, ib), dv, zv in zip(chunk, d_med, z_med, strict=True):
            if not np.isfinite(dv):  # no point of b beside a
                continue
            tol = p.tolerance_mm + p.tolerance_per_mm * zv
            if dv > p.max_deviation * tol:
                continue  # tested before the step (either rules the pair out)
            near_enough.append((ia, ib, dv, tol, zv))
        if not near_enough:
            continue
        # _stepped of those pairs: b's depth less a's at the same lateral position, over
        # b's points within a's lateral extent. np.interp per pair, on those points only
        # (it computes slopes one of two ways depending on how many points it is given).
        bx_n = b_pad[[q[1] for q in near_enough], :, 0]
        lo_hi = lateral[[q[0] for q in near_enough]]
        within = b_real[[q[1] for q in near_enough]]
        within &= (bx_n >= lo_hi[:, 0:1]) & (bx_n <= lo_hi[:, 1:2])
        step = np.zeros((len(near_enough), kb))
        for r, ((ia, ib, _, _, _), w) in enumerate(zip(near_enough, within, strict=True)):
            if ia not in a_sorted:
                a = projected[ia][0]
                o = np.argsort(a[:, 0])
                a_sorted[ia] = (a[o, 0], a[o, 1])
            b = b_nodes[ib][0]
            sel = b[w[: b.shape[0]]]
            step[r, w] = sel[:, 1] - np.interp(sel[:, 0], *a_sorted[ia])
        common = within
        s_med = _masked_medians(step, common)
        n_up = np.count_nonzero((step > 0) & common, axis=1).tolist()
        n_down = np.count_nonzero((step < 0) & common, axis=1).tolist()
        n_all = np.count_nonzero(common, axis=1).tolist()
        for (ia, ib, dv, tol, zv), sm, up, down, nc in zip(
            near_enough, s_med, n_up, n_down, n_all, strict=True
        ):
            # As _stepped: no common point, or the median step within the allowed one,
            # or under nine in ten of one sign: not stepped (shares as counts / size).
            stepped = (
                nc > 0
                and abs(sm) > p.max_step_mm + p.step_per_mm * zv
                and max(up / nc, down / nc) >= 0.9
            )
            if not stepped:
                out[ia].append((ib, dv / tol))
    return out


#: Fewest pairs of consecutive frames the sweep's own deviation is taken over (fewer:
#: the tolerance stands).
_MIN_PAIRS = 5


def _pair_deviation(
    a_refs: Sequence[np.ndarray],
    plane: Plane,
    b_nodes: Sequence[PlaneNode],
    p: RejectionParams,
) -> float:
    """The least deviation (tolerances of ``p``) of any link from frame a's nodes to the
    next frame's (inf if none links): the bone's, wherever it is among them."""
    devs = [dev for row in _links_many(a_refs, plane, b_nodes, p) for _, dev in row]
    return min(devs) if devs else np.inf


def pose_jitter(origins: np.ndarray) -> float:
    """Median distance (mm) of each frame's image origin ``(N, 3)`` from the midpoint of
    its two neighbours' (0 under three frames): a tracker's noise, frame by frame."""
    o = np.asarray(origins, dtype=float)
    if o.shape[0] < 3:
        return 0.0
    r = o[1:-1] - 0.5 * (o[:-2] + o[2:])
    return median1d(np.sqrt(np.einsum("ij,ij->i", r, r)))


def tolerance_scale(
    pair_deviations: Sequence[float], p: RejectionParams, jitter_mm: float = np.inf
) -> float:
    """The factor the link tolerance is scaled by for a sweep (1: it stands).

    ``pair_deviations``: per pair of consecutive frames, the least deviation of a link
    between their nodes in ``p``'s own tolerances (inf: none linked). Their median over
    the sweep over ``typical_deviation``, rounded to a quarter, up to
    ``max_tolerance_scale``; 1 under ``min_tolerance_scale``, under ``_MIN_PAIRS``
    linked pairs, with ``typical_deviation`` 0, or where the poses run smooth
    (``jitter_mm``, :func:`pose_jitter`, under ``pose_jitter_mm``: the deviation is then
    the anatomy's, not the tracker's).

    Why it generalises: the deviation is measured on the sweep itself, between its own
    contours, in the tolerance's own units; the bone's contours are among each pair's
    candidates, and the least deviation of a pair is the bone's or smaller, so a
    look-alike never inflates it. Rounded to quarters, a live session's scale changes
    only a few times as frames arrive (each change relinks its frames).
    """
    v = np.asarray([d for d in pair_deviations if np.isfinite(d)], dtype=float)
    if p.typical_deviation <= 0 or v.size < _MIN_PAIRS or jitter_mm < p.pose_jitter_mm:
        return 1.0
    g = float(np.rint(median1d(v) / p.typical_deviation * 4.0)) / 4.0
    if g < p.min_tolerance_scale:  # at least 1 (validated)
        return 1.0
    return min(p.max_tolerance_scale, g)


def scale_warnings(scale: float) -> tuple[str, ...]:
    """What the user should know of a tolerance scaled by ``scale`` (one sentence; none
    at 1), with the likely causes: the poses' noise, or an anatomy whose cross-section
    changes fast between frames (the spine phantom's: 2.5)."""
    if scale == 1.0:
        return ()
    return (
        f"the contours of neighbouring frames deviate {scale:g} times as much as exact "
        f"poses over a long bone make them (a noisy tracker, or anatomy changing fast "
        f"between frames): the track's link tolerance was scaled by {scale:g}",
    )


def scaled_tolerance(p: RejectionParams, scale: float) -> RejectionParams:
    """``p`` with both terms of the link tolerance times ``scale`` (``p`` itself at 1)."""
    if scale == 1.0:
        return p
    return replace(
        p, tolerance_mm=p.tolerance_mm * scale, tolerance_per_mm=p.tolerance_per_mm * scale
    )


def _masked_medians(values: np.ndarray, mask: np.ndarray) -> list[float]:
    """Per row, :func:`~.features.median1d` of ``values[row][mask[row]]`` (inf where none).

    The masked values set to NaN sort last: the order statistics of each row's own
    values, and the two middle ones of an even count averaged in float64, as
    :func:`~.features.median1d` does.
    """
    v = np.where(mask, values, np.nan)
    v.sort(axis=1)
    cnt = mask.sum(axis=1)
    k = cnt // 2
    rows = np.arange(v.shape[0])
    hi = v[rows, k]
    lo = v[rows, np.maximum(k - 1, 0)]
    med = np.where(cnt % 2 == 1, hi, (lo + hi) / 2)
    med[cnt == 0] = np.inf
    return med.tolist()


def select_bone_track(
    frames: Sequence[FrameCandidates],
    image_to_reference: np.ndarray,
    params: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
    exclude: Mapping[int, tuple[str, str]] | None = None,
) -> TrackChoice:
    """Choose one candidate (or none) per frame: one continuous bone track.

    Parameters
    ----------
    frames : sequence of FrameCandidates
        Per frame, in acquisition order (the output of
        :func:`~.candidates.frame_candidates` or any segmenter wrapped by
        :func:`~.candidates.candidates_from_points`).
    image_to_reference : ndarray, shape (N, 4, 4)
        The frames' poses, in the same order.
    params : RejectionParams
    exclude : mapping of int to (str, str), optional
        Frames that may not be on the track (their candidates are no nodes), each with
        the rejection reason and detail it keeps (:func:`.ends.cut_ends_and_choose_again`:
        the frames the ends cut judged bone-free). The sweep's typical strength is
        still taken over all frames.

    Returns
    -------
    TrackChoice
    """
    p = params
    n = len(frames)
    poses = np.asarray(image_to_reference, dtype=float).reshape(n, 4, 4)
    reason = [_frame_reason(fc) for fc in frames]
    detail = [""] * n
    exclude = exclude or {}
    for f, (r, d) in exclude.items():
        reason[f], detail[f] = r, d
    chosen = np.full(n, -1, dtype=np.intp)
    conf = np.zeros(n)
    nodes = [
        (f, c)
        for f, fc in enumerate(frames)
        for c, cand in enumerate(fc.candidates)
        if _is_node(cand) and f not in exclude
    ]
    if not nodes:
        return TrackChoice(chosen, conf, reason, detail)

    # The sweep's own frame-to-frame deviation, over every frame's nodes (ruled out or
    # not), and the tolerance scaled to it (:func:`tolerance_scale`). Each node's
    # geometry is made once, for this and for the links.
    every = [
        {
            c: _node_points(cand, fc.spacing, poses[f])
            for c, cand in enumerate(fc.candidates)
            if _is_node(cand)
        }
        for f, fc in enumerate(frames)
    ]
    origin, axes, normal = frame_planes(poses)
    pair_devs = [
        _pair_deviation(
            [gm[0] for gm in every[f - 1].values()],
            (origin[f], axes[f], normal[f]),
            [gm[1:] for gm in every[f].values()],
            p,
        )
        if every[f - 1] and every[f]
        else np.inf
        for f in range(1, n)
    ]
    p = scaled_tolerance(p, tolerance_scale(pair_devs, p, pose_jitter(origin)))
    m = len(nodes)
    typical = _typical_strength(frames)
    value = np.array([_node_value(frames[f].candidates[c], typical, p) for f, c in nodes])
    geometry = [every[f][c] for f, c in nodes]
    ref = [gm[0] for gm in geometry]
    by_frame: dict[int, list[int]] = {}
    for k, (f, _) in enumerate(nodes):
        by_frame.setdefault(f, []).append(k)
    # The edges (a, b, deviation, cost of the frames skipped) in the order the forward
    # pass visits them: for each frame g, every node of the frames before it that may
    # link to it, in frame order, their links to g's nodes made together (_links_many).
    edges: list[tuple[int, int, float, float]] = []
    for g in sorted(by_frame):
        ks = by_frame[g]
        b_nodes = [geometry[kb][1:] for kb in ks]
        kas = [ka for f in range(max(0, g - p.max_skip - 1), g) for ka in by_frame.get(f, ())]
        links = _links_many([ref[ka] for ka in kas], (origin[g], axes[g], normal[g]), b_nodes, p)
        for ka, pairs in zip(kas, links, strict=True):
            gap = p.miss_cost * (g - nodes[ka][0] - 1)
            edges.extend((ka, ks[i], dev, gap) for i, dev in pairs)

    def forward(value: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        score = value.copy()  # best path value ending at each node (a path may start anywhere)
        back = np.full(m, -1, dtype=np.intp)
        link_dev = np.zeros(m)
        for ka, kb, dev, gap in edges:
            s = score[ka] - dev**2 - gap + value[kb]
            if s > score[kb]:
                score[kb], back[kb], link_dev[kb] = s, ka, dev
        return score, back, link_dev

    value, (score, back, link_dev), path = pointed_track(
        frames, poses, nodes, value, forward, p, reason, detail
    )
    return _finish(
        frames, poses, nodes, value, score, back, link_dev, reason, p, detail=detail, path=path
    )


#: A forward pass: the nodes' best path scores, back-pointers and link deviations.
Pass = tuple[np.ndarray, np.ndarray, np.ndarray]
#: The forward pass over given node values.
Forward = Callable[[np.ndarray], Pass]
#: Node values, their forward pass, and the track's path (None: not traced).
Choice = tuple[np.ndarray, Pass, list[int] | None]


def _need(nodes: list[tuple[int, int]], p: RejectionParams) -> int:
    """Frames a track must link: ``min_track_frames``, or every frame with a node if
    fewer."""
    return min(p.min_track_frames, len({f for f, _ in nodes}))


def _path(score: np.ndarray, back: np.ndarray, need: int) -> list[int]:
    """The nodes of the best-valued path that links at least ``need`` frames, last
    first ([] if none): the track :func:`_finish` takes. Nodes ruled out (value -inf,
    :func:`central_track`) end no path."""
    m = score.size
    length = np.zeros(m, dtype=np.intp)
    for k in range(m):  # nodes are in frame order, so a predecessor comes first
        length[k] = 1 + (length[back[k]] if back[k] >= 0 else 0)
    ends = [k for k in np.argsort(-score) if length[k] >= need and np.isfinite(score[k])]
    path: list[int] = []
    k = int(ends[0]) if ends else -1
    while k >= 0:
        path.append(k)
        k = int(back[k])
    return path


def _offcentre(
    frames: Sequence[FrameCandidates], nodes: list[tuple[int, int]], path: list[int]
) -> float | None:
    """Median over ``path``'s frames of its contour's lateral middle's distance from the
    middle of the imaged field of view, in its half-widths (None: no frame on it knows
    its field of view)."""
    u = []
    for k in path:
        fov = frames[nodes[k][0]].fov_px
        if fov is not None and fov[1] > fov[0]:
            mid = _mid_column(frames, nodes[k])
            u.append(abs(mid - 0.5 * (fov[0] + fov[1])) / (0.5 * (fov[1] - fov[0])))
    return median1d(np.asarray(u)) if u else None


def _in_lane(
    frames: Sequence[FrameCandidates], nodes: list[tuple[int, int]], path: list[int]
) -> np.ndarray:
    """Nodes lying over the columns of ``path``'s contours, and the path's own: at
    least half their width inside the lane of the path in their frame, or covering at
    least half of the lane (a contour running over the lane and on over the bone beside
    it: ruled out with the lane, since half of it is off the bone kept; on the
    simulated ulna with the radius 14 mm beside, seed 163, two such contours in the
    last frames, 0.3-0.35 of the half-width off the middle, took the track back onto
    the radius there: recall 0.85, wrong share 0.15; 1.00 and 0 since).

    The lane in a frame is the median start and end of the spans of the path's
    contours in the ``_LANE_NEAREST`` frames on it nearest that frame (the frame's own
    among them when it is on the path): one contour running over two bones side by
    side (along a fascia between them at their level, where a track may cross from one
    to the other) is wider than the bone's lane, and with its two neighbours on one
    bone the lane stays that bone's (on a simulated forearm with the radius 14 mm beside the ulna
    swept, seed 151, such a contour in the frames where the track crossed put the
    whole of the other bone in the lane).
    """
    on = sorted((nodes[k][0], nodes[k][1]) for k in path)
    track_f = np.array([f for f, _ in on])
    spans = np.array([_span(frames, node) for node in on])
    n_near = min(_LANE_NEAREST, len(on))
    out = np.zeros(len(nodes), bool)
    lanes: dict[int, tuple[float, float]] = {}  # by frame: a frame's nodes share its lane
    for q, node in enumerate(nodes):
        lane = lanes.get(node[0])
        if lane is None:
            near = np.argsort(np.abs(track_f - node[0]), kind="stable")[:n_near]
            lane = lanes[node[0]] = (median1d(spans[near, 0]), median1d(spans[near, 1]))
        lo, hi = own = _span(frames, node)
        cover = _overlap(own, lane)
        out[q] = cover >= 0.5 * max(hi - lo, 1.0) or cover >= 0.5 * max(lane[1] - lane[0], 1.0)
    # The path's contours are its lane's, a joining one wider than the lane too (ruled
    # out with the lane, it is not left for a track chosen again to take).
    out[list(path)] = True
    return out


def central_track(
    frames: Sequence[FrameCandidates],
    nodes: list[tuple[int, int]],
    value: np.ndarray,
    forward: Forward,
    p: RejectionParams,
) -> Choice:
    """The node values and the forward pass (``forward(value)``: scores, back-pointers
    and link deviations) the track is taken from, and its path (:func:`_path`; None when
    not traced here): the best track, moved to the bone nearer the middle of the field
    of view (:func:`_nearer_middle`) and kept to one bone over the sweep
    (:func:`_one_lane`), each only where another bone track is found.
    """
    value, out, path = _nearer_middle(frames, nodes, value, forward, p)
    if not p.one_lane:
        return value, out, path
    if path is None:
        path = _path(out[0], out[1], _need(nodes, p))
    return _one_lane(frames, nodes, value, out, path, forward, p)


def _extend_ends(
    frames: Sequence[FrameCandidates],
    poses: np.ndarray,
    nodes: list[tuple[int, int]],
    choice: Choice,
    forward: Forward,
    p: RejectionParams,
) -> Choice:
    """The track ``choice`` carried on past its ends (``extend_ends``): the best chain of
    nodes in its lane before its first frame, and after its last, each node worth its
    value plus ``miss_cost``, taken where it adds value.

    Inside a track a frame left off costs ``miss_cost``; past its ends it cost
    nothing, so a frame joined at an end only where its own value beat its link's
    squared deviation. Where the bone is weaker at one end of the sweep than in its
    middle (deeper, an unsteady probe) its contours' values (relative to the sweep's
    typical strength) are about what a link within tolerance costs, and the track
    stopped short of frames showing it: the unsteady-hand hard tibia s229 lost frames
    0-5, whose candidates lay on the bone (0.04-0.09 mm) in a chain at 0.5-0.75 of
    the link tolerance (recall 0.80, gold 10.1 mm: no surface over the sweep's first
    30 mm). A frame past the end left off now costs what it costs inside. Not in the
    dynamic programme itself (a credit per frame of a track's span, tried in session
    36, let the best path skip frames for look-alikes farther on, then
    :func:`_one_lane` cut it short): here the track is the one the lane rules chose,
    and only its ends grow, skips still costing ``miss_cost`` a frame, through nodes
    in its own lane (:func:`_lane_through`: at least half of a node's width within
    the lateral extent of the nearest track contours projected into its plane, with
    the link tolerance's slack; a contour running on over a bone beside is not half
    within it). The lane is taken through the poses, not in image columns as
    :func:`_in_lane` takes it: an unsteady hand moves the probe sideways by a third of
    a radius's width between frames 5-8 mm apart (the unsteady-hand hard radius s229,
    frames 2 and 4: columns 178-250 and 110-206, both on the bone).

    A node earns the credit only if it is worth at least the credit itself: past an
    end only one side vouches for it, and a node with next to no evidence of its own
    can lie anywhere its one link allows (the unsteady-hand hard tibia s179, frame 0:
    a piece 2.8 mm wide worth 0.09 of the typical strength, 8.9 mm off the bone, linked
    to frame 1's contour on the bone at 0.34 of the tolerance through a tilted probe).
    A guided contour (:mod:`.recovery`, searched past the end inside the band the
    track's contours allow) needs no such floor: the band vouches for it, not its own
    evidence (the hard ulna at the cadaver's geometry, s241, frame 39: 0.11 mm from the
    bone, worth 0.08; session 39).

    Why it generalises: it reads no grey level, only the track's own values and
    tolerances, and what it adds past a bone's end (a fascia or the skin line carrying
    on in 3D) is judged by the ends cut (:mod:`.ends`, a shadow step relative to the
    track's typical frame) as before.
    """
    value, out, path = choice
    if p.extend_ends and path is None:
        path = _path(out[0], out[1], _need(nodes, p))
    if not p.extend_ends or not path:
        return value, out, path
    score, back, link_dev = out
    back, link_dev, path = back.copy(), link_dev.copy(), list(path)
    frame_of = np.array([f for f, _ in nodes])
    # A node worth less than the credit is left out, unless a search the track's
    # contours guided found it (the band they allow vouches for it).
    floor = (value >= p.miss_cost) | np.array([frames[f].candidates[c].guided for f, c in nodes])
    grown = False
    # Round by round: the lane past an end is taken from the track's contours nearest
    # it, those just added among them (a lane taken 10-20 mm away, through a tilting
    # probe, no longer holds the bone's contour: the unsteady-hand radius s229, frame
    # 1). Each round adds at least a node, so there are at most as many rounds.
    while True:
        first, last = path[-1], path[0]
        past = (frame_of < nodes[first][0]) | (frame_of > nodes[last][0])
        may = _lane_through(frames, poses, nodes, path, past & floor, p)
        before = _chain(
            value, forward, p, may & (frame_of < nodes[first][0]), first, True, frame_of
        )
        after = _chain(value, forward, p, may & (frame_of > nodes[last][0]), last, False, frame_of)
        if not before and not after:
            break
        for k, (b, d) in (before | after).items():
            back[k], link_dev[k] = b, d
        path = sorted(after, key=lambda k: -nodes[k][0]) + path
        path += [k for k in sorted(before, key=lambda k: -nodes[k][0]) if k != first]
        grown = True
    if not grown:
        return choice
    return value, (score, back, link_dev), path


def _chain(
    value: np.ndarray,
    forward: Forward,
    p: RejectionParams,
    may: np.ndarray,
    end: int,
    leading: bool,
    frame_of: np.ndarray,
) -> dict[int, tuple[int, float]]:
    """:func:`_extend_ends`' chain of the nodes ``may`` (each worth its value plus
    ``miss_cost``) leading to the track's node ``end`` (``leading``) or from it: the
    back-pointer and link deviation each node of it takes, ``end``'s own too when
    leading ({} when no chain adds value).

    The best chain of the forward pass, then, outward from ``end``, its part up to the
    first link skipping more than ``_END_SKIP`` frames, cut where its summed gain is
    greatest (if positive). Past an end only one side vouches for a chain, and a bone
    shows in the frames next to the track's end: a chain stepping over frames there is
    a structure that comes and goes (S clavicle s29, its last 10 frames bone-free: a
    chain of frames 32, 35 and 39, two and three frames apart, one of them over a dark
    shade the ends cut took for a shadow).
    """
    if not may.any():
        return {}
    v = np.full(value.size, -np.inf)
    v[may] = value[may] + p.miss_cost
    if leading:
        # Chains ending at the track's first node (a node after it cannot precede it).
        v[end] = value[end]
        s, b, d = forward(v)
        if not s[end] > value[end]:
            return {}
        k = end
    else:
        # Chains starting at the track's last node: it carries more than any chain
        # without it could gain (values at most strength_cap plus the credit a node).
        v[end] = value[end] + 1.0 + (p.strength_cap + p.miss_cost) * value.size
        s, b, d = forward(v)
        gain = np.where(may, s - v[end], -np.inf)
        k = int(np.argmax(gain))
        if not gain[k] > 0:
            return {}
    # The chain's links outward from the track: (node beyond, node nearer, deviation;
    # a link's deviation is kept on its later node).
    links: list[tuple[int, int, float]] = []
    if leading:
        while b[k] >= 0:
            links.append((int(b[k]), k, float(d[k])))
            k = int(b[k])
    else:
        seq = []
        while k != end:
            seq.append(k)
            k = int(b[k])
        links = [(k, int(b[k]), float(d[k])) for k in reversed(seq)]
    best, total, keep = 0.0, 0.0, 0
    for i, (k, near, dev) in enumerate(links):
        gap = abs(int(frame_of[k]) - int(frame_of[near])) - 1
        if gap > _END_SKIP:
            break
        total += value[k] + p.miss_cost - dev**2 - p.miss_cost * gap
        if total > best:
            best, keep = total, i + 1
    chain: dict[int, tuple[int, float]] = {}
    for k, near, dev in links[:keep]:
        if leading:
            chain[near] = (k, dev)
            chain[k] = (-1, 0.0)  # the track's new first node (until one further out)
        else:
            chain[k] = (near, dev)
    return chain


def _lane_through(
    frames: Sequence[FrameCandidates],
    poses: np.ndarray,
    nodes: list[tuple[int, int]],
    path: list[int],
    which: np.ndarray,
    p: RejectionParams,
) -> np.ndarray:
    """Of the nodes ``which`` (bool per node), those at least half of whose width lies
    within the track's lane in their frame (:func:`_extend_ends`): the median lateral
    start and end of the ``_LANE_NEAREST`` contours of ``path`` nearest that frame,
    projected into its plane through the poses (mm), widened on each side by
    ``tolerance_per_mm`` times the distance along the sweep to the nearest of them.

    The widening is the link tolerance's growth: a bone surface inclined to the sweep
    moves its contour sideways as well as in depth from frame to frame, and a frame
    shows a part of the bone's top, not always the same part (the unsteady-hand hard
    radius s229, frame 1, 7.7 mm from frame 2: its contour 204-270 px, frame 2's
    projected into it 168-236 px, both on the bone). A bone beside (its middle 14 mm
    or more from the one swept) lies outside by more than that at a frame's spacing.
    """
    out = np.zeros(len(nodes), bool)
    on = np.array(sorted(nodes[k][0] for k in path))
    by_frame = {nodes[k][0]: k for k in path}
    lanes: dict[int, tuple[float, float]] = {}
    for q in np.flatnonzero(which).tolist():
        f, c = nodes[q]
        if f not in lanes:
            origin, axes, normal = frame_planes(poses[f][None])
            ext = []
            for g in on[np.argsort(np.abs(on - f), kind="stable")[:_LANE_NEAREST]].tolist():
                cand = frames[g].candidates[nodes[by_frame[g]][1]]
                ref = pixels_to_reference(poses[g], _sampled(cand.core_px, frames[g].spacing))
                a = _project(ref, origin[0], axes[0], normal[0])
                ext.append((float(a[:, 0].min()), float(a[:, 0].max()), median1d(np.abs(a[:, 2]))))
            e = np.asarray(ext)
            slack = p.tolerance_per_mm * float(e[:, 2].min())
            lanes[f] = (median1d(e[:, 0]) - slack, median1d(e[:, 1]) + slack)
        sx = float(frames[f].spacing[0])
        lo, hi = _span(frames, (f, c))
        own = (lo * sx, hi * sx)
        out[q] = _overlap(own, lanes[f]) >= 0.5 * max(own[1] - own[0], sx)
    return out


def _one_lane(
    frames: Sequence[FrameCandidates],
    nodes: list[tuple[int, int]],
    value: np.ndarray,
    out: Pass,
    path: list[int],
    forward: Forward,
    p: RejectionParams,
    *,
    pointed: np.ndarray | None = None,
    plain: np.ndarray | None = None,
) -> Choice:
    """:func:`central_track`'s second step (``one_lane``), keeping the track to one
    bone: where it changes lanes (two of its contours two frames apart share no
    column, or their lateral middles lie farther apart than half their mean width:
    :func:`_shifted`), the track is chosen again without the nodes over the columns of its
    stretches off the bone swept (:func:`_in_lane`), and that one is taken if it links
    at least as many frames, its contours in those stretches' frames reach into the
    bone swept's lane (:func:`_reaches`), and it carries at least ``lane_value`` of
    the first's value.

    Two bones side by side (the radius and the ulna) can each be linked to a contour
    that runs over both, along a fascia between them at their level, and a track can
    cross from one to the other over it: every link is within tolerance. A bone cannot
    leave its own columns within two frames (a few mm of sweep; a freehand sweep drifts
    laterally by far less than a bone's width in that time), so such a pair marks a
    change of lane, whatever the contours' grey levels. The stretch on the bone swept
    is the one nearest the middle of the field of view (the operator keeps it there;
    :func:`_nearer_middle`), the longest where that is not known. The conditions keep
    a bone that drifts across the image, or that shows one part of its top then
    another, as it was (no other contour reaches its lane in those frames), and never
    move a track that was on one bone all along to another: hard radius seed 1 with
    the ulna 24 mm beside showed contours of the radius two frames apart at columns
    112-154 and 156-214, and without the reach condition the track moved to the ulna
    in its last 4 frames.

    Measured on two-bone sweeps (radius and ulna, hard, seeds 1-8, 320 x 256 at 0.16
    mm, the other bone 14, 18 or 24 mm beside): see ``Testing/benchmarks/README.md``,
    "Session 32 (lead)".

    ``pointed`` (bool per node, :func:`pointed_track`): the nodes near the user's bone
    points. The stretch on the bone swept is then the one through the most of them
    (the user said which bone), they are never ruled out, the track chosen again
    must pass through as many; instead of linking as many frames it need only have a
    contour in ``lane_frames`` of the frames of the stretches off the bone swept (a
    stretch on the other bone is replaced where the pointed one shows, not kept for
    want of as many frames; a bone showing one part of its top then another has
    nothing else there, and stays). ``plain``: the node values the value condition
    compares (``value`` carries the points' bonus); None: ``value``.
    """
    on = sorted(path, key=lambda k: nodes[k][0])
    spans = [_span(frames, nodes[k]) for k in on]
    sx = [float(frames[nodes[k][0]].spacing[0]) for k in on]
    # Changes of lane where two contours two frames apart share no column; first also
    # where their middles moved apart (:func:`_shifted`), and if the track so chosen
    # again is not taken, with the first kind alone (a bone showing one part of its top
    # then another cuts its own track into stretches too short to stand for it).
    tried: list[list[int]] = []
    for shifted in (True, False):
        cuts = _lane_cuts(spans, sx, shifted)
        if not cuts or cuts in tried:
            continue
        tried.append(cuts)
        moved_to = _lane_kept(
            frames, nodes, value, path, on, spans, cuts, forward, p, pointed, plain
        )
        if moved_to is not None:
            return moved_to
    return value, out, path


def _lane_cuts(spans: list[tuple[float, float]], sx: list[float], shifted: bool) -> list[int]:
    """Where a track (its contours' spans in frame order, columns of ``sx`` mm) changes
    lanes: after index ``j`` of each cut, for :func:`_one_lane`. Two contours two
    frames apart that share no column (or, with ``shifted``, whose middles moved apart,
    :func:`_shifted`) change lanes; the contour between goes with the side it shares
    more columns with."""
    cuts: list[int] = []
    for i in range(len(spans) - 2):
        if _overlap(spans[i], spans[i + 2]) <= 0 or (
            shifted and _shifted(spans[i], spans[i + 2], sx[i])
        ):
            j = (
                i + 1
                if _overlap(spans[i + 1], spans[i]) >= _overlap(spans[i + 1], spans[i + 2])
                else i
            )
            if not cuts or cuts[-1] != j:
                cuts.append(j)
    return cuts


def _lane_kept(
    frames: Sequence[FrameCandidates],
    nodes: list[tuple[int, int]],
    value: np.ndarray,
    path: list[int],
    on: list[int],
    spans: list[tuple[float, float]],
    cuts: list[int],
    forward: Forward,
    p: RejectionParams,
    pointed: np.ndarray | None,
    plain: np.ndarray | None,
) -> Choice | None:
    """:func:`_one_lane`'s track chosen again with the lanes of the stretches off the
    bone swept ruled out (``on``: ``path`` in frame order, ``spans`` its contours'
    spans, ``cuts`` its changes of lane), if taken by :func:`_one_lane`'s conditions;
    else None."""
    stretches = [on[a + 1 : b + 1] for a, b in zip([-1, *cuts], [*cuts, len(on) - 1], strict=True)]
    u = [_offcentre(frames, nodes, st) for st in stretches]
    if pointed is not None:
        main = max(stretches, key=lambda st: (int(pointed[st].sum()), len(st)))
    elif all(v is not None for v in u):
        main = stretches[int(np.argmin(u))]
    else:
        main = max(stretches, key=len)
    span_of = dict(zip(on, spans, strict=True))
    main_spans = [(nodes[k][0], span_of[k]) for k in main]
    ruled = np.zeros(len(nodes), bool)
    for st in stretches:
        if st is not main and st:
            ruled |= _in_lane(frames, nodes, st)
    ruled &= ~_in_lane(frames, nodes, main)
    if pointed is not None:
        ruled &= ~pointed
    other = np.where(ruled, -np.inf, value)
    alt = forward(other)
    path2 = _path(alt[0], alt[1], _need(nodes, p))
    moved = {nodes[k][0] for st in stretches if st is not main for k in st}
    worth = value if plain is None else plain
    if (
        (
            len(path2) >= len(path)
            if pointed is None
            else len({nodes[k][0] for k in path2} & moved) >= p.lane_frames * len(moved)
        )
        and all(_reaches(frames, nodes[k], main_spans) for k in path2 if nodes[k][0] in moved)
        and float(np.where(ruled, -np.inf, worth)[path2].sum())
        >= p.lane_value * float(worth[path].sum())
        and (pointed is None or int(pointed[path2].sum()) >= int(pointed[path].sum()))
    ):
        return other, alt, path2
    return None


def _shifted(a: tuple[float, float], b: tuple[float, float], sx: float) -> bool:
    """Whether two contours' lateral middles (columns of ``sx`` mm) lie farther apart
    than half their mean width (more than half of each lies beside the other) and than
    ``_LANE_SHIFT_MM``.

    Two bones that touch in the image show wide partial contours that share columns
    across the valley, so a track crossing from one to the other two frames apart is no
    change of lane by shared columns alone: on the simulated radius with the ulna 14
    mm beside (475 x 405, hard, seed 109) the track held the ulna in frames 0-15
    (columns ~95-220) and the radius after (~180-300), the contours of frames 15 and
    18 sharing 32 columns (recall 0.57, wrong share 0.40; 1.00 and 0 with this). A
    sweep's drift moves a contour by a small part of its width in two frames (a few mm
    of sweep). A bone showing one part of its top then another moves its contours'
    middles too, by up to half its width: hence the floor in mm, under what two bones
    side by side lie apart (their centres 14 mm or more). Where it still cuts a bone's
    own track (a hard ulna at 320 x 256, seed 15: parts of its top 6.1 mm apart two
    frames apart, the track then in stretches none of which linked as many frames),
    :func:`_one_lane` falls back to the plain cuts.
    """
    d = abs(0.5 * (a[0] + a[1] - b[0] - b[1]))
    return d > 0.25 * ((a[1] - a[0]) + (b[1] - b[0])) and d * sx > _LANE_SHIFT_MM


def _span(frames: Sequence[FrameCandidates], node: tuple[int, int]) -> tuple[float, float]:
    """Lateral extent (image columns) of a node's contour core."""
    x = frames[node[0]].candidates[node[1]].core_px[:, 0]
    return float(x.min()), float(x.max())


def _reaches(
    frames: Sequence[FrameCandidates],
    node: tuple[int, int],
    lane: list[tuple[int, tuple[float, float]]],
    k: int = 3,
) -> bool:
    """Whether ``node``'s contour shares a column with the lane: the columns the ``k``
    contours of ``lane`` (frame, span) nearest its frame span together (a contour of
    the bone may show only part of its top; three frames show it whole)."""
    near = sorted(lane, key=lambda fs: abs(fs[0] - node[0]))[:k]
    lane_span = (min(sp[0] for _, sp in near), max(sp[1] for _, sp in near))
    return _overlap(_span(frames, node), lane_span) > 0


def _overlap(a: tuple[float, float], b: tuple[float, float]) -> float:
    """Length of the intersection of two lateral extents (<= 0: disjoint)."""
    return min(a[1], b[1]) - max(a[0], b[0])


def _nearer_middle(
    frames: Sequence[FrameCandidates],
    nodes: list[tuple[int, int]],
    value: np.ndarray,
    forward: Forward,
    p: RejectionParams,
) -> Choice:
    """:func:`central_track`'s first step: ``value`` as it is, or, when the best
    track runs off the middle of the field of view over some of its frames and another
    bone track runs nearer it there, with the columns of its contours off the middle
    ruled out (value -inf).

    Two bones in view (the radius beside the ulna, the fibula beside the tibia, 15-30
    mm apart, in a 40-50 mm wide image): both are continuous tracks of bone echo over
    shadow, and the bigger or brighter one has the more evidence; on simulated forearms
    with the neighbour 18 mm beside the ulna (475 x 405 at 0.108 mm), the ulna's sweeps
    followed the radius in 5 of 8. The operator keeps the bone swept in the middle of
    the image (that is what keeps it in view along a freehand sweep), so where at least
    ``_MIN_OFF`` of the best track's contours lie farther than ``lane_offcentre`` of the
    half-width from the middle, the track is chosen again without the nodes over their
    columns (:func:`_in_lane`), and that one is taken if, in those contours' frames, it
    lies at least ``lane_gain`` nearer the middle (on median), links at least
    ``lane_frames`` of the first's frames and of those contours' frames, and carries at
    least ``lane_value`` of its value (a bone, not a vessel or a fascia that comes and
    goes; the bone swept showing only its side in the last frames, with nothing nearer
    the middle there, stays: hard simulated tibia, seed 5, 160 x 128). Shares of the field of
    view and of the sweep's own track: no grey level. A centred bone (the usual sweep)
    never triggers the second pass.

    Only the contours off the middle, not the whole track: a track may cross from the
    bone beside to the one in the middle part way along the sweep (over a contour
    joining them, or a partial contour of each in turn) and then holds the bone swept
    in the rest of its frames. Judged on the whole track (its median), such a track was
    either left as it was (its median under the bar: the simulated radius with the ulna
    14 mm beside, seed 127, 25 frames of 40 on the ulna) or moved off the bone swept in
    the frames where it already held it (their columns ruled out with the rest: the
    ulna, seed 151, recall 0.57).
    """
    out = forward(value)
    if p.lane_offcentre >= 1.0:
        return value, out, None
    need = _need(nodes, p)
    path = _path(out[0], out[1], need)
    u = {k: _offcentre(frames, nodes, [k]) for k in path}
    off = [k for k in path if (u[k] or 0.0) > p.lane_offcentre]
    if len(off) < _MIN_OFF:
        return value, out, path
    lane = _in_lane(frames, nodes, off)
    if lane.all():
        return value, out, path
    other = np.where(lane, -np.inf, value)
    alt = forward(other)
    path2 = _path(alt[0], alt[1], need)
    there = {nodes[k][0] for k in off}
    u1 = median1d(np.asarray([u[k] for k in off]))
    u2 = _offcentre(frames, nodes, [k for k in path2 if nodes[k][0] in there])
    if (
        u2 is not None
        and u2 <= u1 - p.lane_gain
        and len(path2) >= p.lane_frames * len(path)
        and len({nodes[k][0] for k in path2} & there) >= p.lane_frames * len(there)
        and float(other[path2].sum()) >= p.lane_value * float(value[path].sum())
    ):
        return other, alt, path2
    return value, out, path


def pointed_track(
    frames: Sequence[FrameCandidates],
    poses: np.ndarray,
    nodes: list[tuple[int, int]],
    value: np.ndarray,
    forward: Forward,
    p: RejectionParams,
    reason: list[str],
    detail: list[str],
) -> Choice:
    """:func:`central_track`'s values, forward pass and path, or, with the user's bone
    points (``p.bone_points``, :mod:`.bone_point`), the track through them.

    In a point's frames the candidates away from it are ruled out (value -inf), and a
    frame left without a candidate gets the reason :data:`.bone_point.OFF_POINT`
    (``reason`` and ``detail`` are changed in place, frames without a reason only).
    Points with no candidate near them are left out (:func:`.bone_point.point_marks`);
    with none left, this is :func:`central_track`.

    The track the points ask for:

    * :func:`central_track`'s own where it agrees with them (through a candidate near
      a point, through none they rule out), unless the track through them (below) is
      that track and more frames: a point on the bone the default track follows
      changes nothing. The points say which bone; elsewhere the default's rules know
      best, and without them a track through the points crossed to the other bone
      away from them (hard radius seed 127 at the cadaver's geometry, the ulna 18 mm
      beside, a point in frame 20: the track crossed to the ulna in its last 3
      frames, recall 1.00 -> 0.93; ``Testing/benchmarks/README.md``);
    * otherwise the best track through the most candidates near a point: each is
      worth more than any track could gain or lose elsewhere in the forward pass.
      It is kept to the pointed bone as the default track is kept to the one in the
      middle: :func:`_nearer_point` (the bone swept lies where the points are in the
      image, which may be off its middle), then :func:`_one_lane` with the stretch
      through the points as the bone swept (a stretch in another lane replaced
      where the pointed bone shows in ``lane_frames`` of its frames, even if the
      track links fewer frames: the user said which bone). :func:`_nearer_middle` is
      not applied.

    The values returned (and so the confidences) are the plain ones, ruled-out nodes
    -inf.
    """
    mark, off = point_marks(frames, poses, nodes, p)
    if not (mark > 0).any():
        return _extend_ends(
            frames, poses, nodes, central_track(frames, nodes, value, forward, p), forward, p
        )
    for f, (r, d) in off.items():
        if not reason[f]:
            reason[f], detail[f] = r, d
    ruled = np.where(mark < 0, -np.inf, value)
    # More than a track's value (at most strength_cap per frame) and its costs (links
    # at most max_deviation tolerances long, skips) over all frames with nodes.
    per_frame = p.strength_cap + p.max_deviation**2 + p.miss_cost * (p.max_skip + 1)
    bonus = 1.0 + per_frame * len({f for f, _ in nodes})
    boosted = np.where(mark > 0, ruled + bonus, ruled)
    out = forward(boosted)
    path = _path(out[0], out[1], _need(nodes, p))
    # The default track, where it agrees with the points (through a candidate near one,
    # through none they rule out), unless the track through them is that track and more.
    plain_value, plain_out, plain_path = central_track(frames, nodes, value, forward, p)
    if plain_path is None:
        plain_path = _path(plain_out[0], plain_out[1], _need(nodes, p))
    agrees = (mark[plain_path] > 0).any() and not (mark[plain_path] < 0).any()
    if agrees and not set(plain_path) < set(path):
        return _extend_ends(frames, poses, nodes, (plain_value, plain_out, plain_path), forward, p)
    if not path:
        return ruled, out, path
    boosted, out, path = _nearer_point(
        frames,
        nodes,
        boosted,
        out,
        path,
        forward,
        p,
        pointed=mark > 0,
        plain=ruled,
        column=_point_column(frames, poses, nodes, [k for k in path if mark[k] > 0], p),
    )
    if p.one_lane:
        boosted, out, path = _one_lane(
            frames, nodes, boosted, out, path, forward, p, pointed=mark > 0, plain=ruled
        )
    boosted, out, path = _extend_ends(frames, poses, nodes, (boosted, out, path), forward, p)
    return np.where(np.isneginf(boosted), -np.inf, ruled), out, path


def _point_column(
    frames: Sequence[FrameCandidates],
    poses: np.ndarray,
    nodes: list[tuple[int, int]],
    at: list[int],
    p: RejectionParams,
) -> float | None:
    """The image column of the bone points, on median over the frames of the nodes
    ``at`` (in each, the point nearest its plane, projected into it); None if none."""
    pts = np.asarray(p.bone_points, dtype=float).reshape(-1, 3)
    cols = []
    for k in at:
        f = nodes[k][0]
        origin, axes, normal = frame_planes(np.asarray(poses[f], dtype=float)[None])
        rel = pts - origin[0]
        q = int(np.argmin(np.abs(rel @ normal[0])))
        cols.append(float(rel[q] @ axes[0][:, 0]) / float(frames[f].spacing[0]))
    return float(np.median(cols)) if cols else None


def _mid_column(frames: Sequence[FrameCandidates], node: tuple[int, int]) -> float:
    """The lateral middle (image column) of a node's contour core."""
    lo, hi = _span(frames, node)
    return 0.5 * (lo + hi)


def _nearer_point(
    frames: Sequence[FrameCandidates],
    nodes: list[tuple[int, int]],
    value: np.ndarray,
    out: Pass,
    path: list[int],
    forward: Forward,
    p: RejectionParams,
    *,
    pointed: np.ndarray,
    plain: np.ndarray,
    column: float | None,
) -> Choice:
    """:func:`_nearer_middle` for a track through the user's bone points
    (:func:`pointed_track`): the bone swept lies where the points are in the image,
    not necessarily in its middle.

    ``value`` carries the points' bonus, ``plain`` not; ``pointed`` (bool per node):
    the nodes near a point; ``column``: the reference, the points' image column in
    the frames of the track's nodes near them (:func:`_point_column`; the point's,
    not its contour's: a contour near the point may run along a fascia over both
    bones). Where contours of the track lie farther than ``lane_offcentre`` of the
    half-width from it (the operator keeps the bone swept where it is in the image,
    as :func:`_nearer_middle` reads the middle), the track is chosen again without
    the nodes over their columns (:func:`_in_lane`; never those near a point), and
    that one is taken if it passes through as many nodes near a
    point, lies at least ``lane_gain`` nearer the reference on median over its
    frames, has a contour in at least ``lane_frames`` of the frames whose contours
    were away (the bone is replaced there, not dropped: a bone drifting across the
    image has nothing else in its lane) and carries at least ``lane_value`` of the
    first's plain value: :func:`_nearer_middle`'s conditions with the reference at the
    points. Two bones that touch (radius and ulna 14 mm apart) share columns, so
    :func:`_one_lane` sees no change of lane where the track crosses between them:
    hard radius seed 4 (320 x 256 at 0.16 mm, 20 frames) with a point in frame 15
    followed the ulna in frames 0-13 (recall 0.30, wrong 0.70; 0.70 and 0 without the
    point, 1.00 and 0 with it now).
    """
    on = sorted(path, key=lambda k: nodes[k][0])
    half = []
    for k in on:
        fov = frames[nodes[k][0]].fov_px
        if fov is not None and fov[1] > fov[0]:
            half.append(0.5 * (fov[1] - fov[0]))
    if column is None or not half or p.lane_offcentre >= 1.0:
        return value, out, path
    h, ref = float(np.median(half)), column
    u = {k: abs(_mid_column(frames, nodes[k]) - ref) / h for k in on}
    away = [k for k in on if u[k] > p.lane_offcentre and not pointed[k]]
    if not away:
        return value, out, path
    ruled = _in_lane(frames, nodes, away) & ~pointed
    other = np.where(ruled, -np.inf, value)
    alt = forward(other)
    path2 = _path(alt[0], alt[1], _need(nodes, p))
    away_f = {nodes[k][0] for k in away}
    u2 = [abs(_mid_column(frames, nodes[k]) - ref) / h for k in path2]
    if (
        path2
        and int(pointed[path2].sum()) >= int(pointed[path].sum())
        and float(np.median(u2)) <= float(np.median(list(u.values()))) - p.lane_gain
        and len([k for k in path2 if nodes[k][0] in away_f]) >= p.lane_frames * len(away_f)
        and float(np.where(ruled, -np.inf, plain)[path2].sum())
        >= p.lane_value * float(plain[path].sum())
    ):
        return other, alt, path2
    return value, out, path


def _finish(
    frames: Sequence[FrameCandidates],
    poses: np.ndarray,
    nodes: list[tuple[int, int]],
    value: np.ndarray,
    score: np.ndarray,
    back: np.ndarray,
    link_dev: np.ndarray,
    reason: list[str],
    p: RejectionParams,
    keys: Sequence[int] | None = None,
    details: dict[tuple[int, int, int, int], str] | None = None,
    explain: bool = True,
    detail: list[str] | None = None,
    path: list[int] | None = None,
) -> TrackChoice:
    """The track from the dynamic programme's scores and back-pointers (``nodes`` in
    frame order), and why each frame off it is off it.

    ``keys`` (one per frame, stable while the frames are kept) and ``details`` let a
    caller that solves again and again (live) keep the rejection details between
    solves: a detail depends only on the frame, its nearest frame on the track, that
    frame's choice and position. ``explain`` False leaves the details empty (a caller
    that only needs the choice). ``detail``: the details of the frames given a reason
    beforehand (ruled out of the track; "" elsewhere). ``path``: the track's nodes, when
    :func:`central_track` traced them already (None: traced here).
    """
    n = len(frames)
    chosen = np.full(n, -1, dtype=np.intp)
    conf = np.zeros(n)
    reason = list(reason)
    detail = list(detail) if detail is not None else [""] * n
    by_frame: dict[int, list[int]] = {}
    for k, (f, _) in enumerate(nodes):
        by_frame.setdefault(f, []).append(k)
    # The track: the best-valued end whose path links at least ``min_track_frames``
    # frames (fewer if the sweep has fewer): one frame alone, or two, can be speckle
    # that happens to look like a line; a bone continues through the sweep.
    need = min(p.min_track_frames, len(by_frame))
    on_track = _path(score, back, need) if path is None else path
    if not (back >= 0).any() or (not on_track and len(by_frame) < 2 * need):
        # No two frames link, or a handful of frames (under twice ``need``) of which
        # none links ``need`` (scattered frames, tens of mm apart, where a chance pair
        # of speckle pieces may link and the bone's candidates do not; measured: 4
        # frames 80 x 64 at 0.6 mm all lost as "jumps"): continuity cannot be checked,
        # so each frame is judged alone, its strongest candidate kept (the track has
        # nothing to choose between). A longer sweep with no such path keeps nothing.
        for f, ks in by_frame.items():
            k = max(ks, key=lambda q: value[q])
            if np.isfinite(value[k]):  # not a node ruled out (central_track)
                chosen[f] = nodes[k][1]
                conf[f] = min(1.0, value[k])
        return TrackChoice(chosen, conf, reason, detail)
    for k in on_track:
        f, c = nodes[k]
        chosen[f] = c
        conf[f] = min(1.0, value[k]) * float(np.exp(-0.5 * link_dev[k] ** 2))
    # Rejected frames with candidates: how far their best candidate lies from the track.
    track_frames = np.flatnonzero(chosen >= 0)
    for f, fc in enumerate(frames):
        if chosen[f] >= 0 or reason[f]:
            continue
        reason[f] = REASONS["jump"]
        if track_frames.size and explain:
            g = int(track_frames[np.argmin(np.abs(track_frames - f))])
            key = (keys[f], keys[g], int(chosen[g]), g) if keys is not None else None
            if details is not None and key in details:
                detail[f] = details[key]
                continue
            g_ref = pixels_to_reference(
                poses[g], _sampled(frames[g].candidates[chosen[g]].core_px, frames[g].spacing)
            )
            devs = [
                _deviation(g_ref, _sampled(c.core_px, fc.spacing), poses[f], fc.spacing)[0]
                for c in fc.usable
            ]
            dmin = min(devs)
            detail[f] = (
                f"{dmin:.1f} mm from frame {g}"
                if np.isfinite(dmin)
                else f"no overlap with frame {g}"
            )
            if details is not None and key is not None:
                details[key] = detail[f]
    return TrackChoice(chosen, conf, reason, detail)

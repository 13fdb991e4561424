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
* each skipped frame costs ``miss_cost``.

One decision over the whole sweep: no prior chained from an earlier frame, no rounds
of rejection. Frames whose candidates are all off the track are rejected as "jump from
neighbouring frames" (the distance to the track is in the frame's ``detail``).
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from BoneUSRecon.Logic.segmentation.candidates import FrameCandidates
from BoneUSRecon.Logic.segmentation.features import median1d
from BoneUSRecon.Logic.segmentation.params import RejectionParams
from BoneUSRecon.Logic.sweep import frame_planes, pixels_to_reference

__all__ = ["TrackChoice", "select_bone_track", "REASONS"]

#: Rejection reasons (one category each; values go to ``FrameContour.detail``).
REASONS = {
    "none": "no bone found",
    "jump": "jump from neighbouring frames",
    "short": "contour too short",
    "reverb": "reverberation copy",
    "weak": "no bone evidence along the contour",
}

_SAMPLE_MM = 0.5  # contours are compared at ~this point spacing (speed; 1-2 px apart)


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
    return np.column_stack([rel @ axes[:, 0], rel @ axes[:, 1], np.abs(rel @ normal)])


def _in_plane_deviation(a: np.ndarray, b_mm: np.ndarray) -> tuple[float, float, float]:
    """``(median in-plane distance mm, overlap share, median out-of-plane mm)`` of b to a.

    ``a``: contour a projected into b's plane (:func:`_project`); ``b_mm``: b's
    ``(lateral, depth)`` mm in its own plane. The overlap is relative to the shorter of
    the two contours (a partial contour of the bone overlaps a full one completely).
    """
    ax, ay, az = a[:, 0], a[:, 1], a[:, 2]
    bx, by = b_mm[:, 0], b_mm[:, 1]
    lo, hi = ax.min() - 1.0, ax.max() + 1.0
    overlap = max(0.0, min(hi, bx.max()) - max(lo, bx.min()))
    share = overlap / max(min(hi - lo, float(np.ptp(bx)) + 2.0), 1e-6)
    inside = (bx >= lo) & (bx <= hi)
    if not inside.any():
        return np.inf, 0.0, median1d(az)
    d2 = (bx[inside, None] - ax[None, :]) ** 2 + (by[inside, None] - ay[None, :]) ** 2
    near = d2.argmin(axis=1)
    d = np.sqrt(d2[np.arange(near.size), near])
    return median1d(d), share, median1d(az[near])


def _deviation(
    a_ref: np.ndarray, b_px: np.ndarray, b_pose: np.ndarray, b_spacing: tuple[float, float]
) -> tuple[float, float, float]:
    """:func:`_in_plane_deviation` of contour b (its pixels, its pose) to a (reference mm)."""
    origin, axes, normal = frame_planes(b_pose)
    a = _project(a_ref, origin[0], axes[0], normal[0])
    return _in_plane_deviation(a, b_px * np.asarray(b_spacing, dtype=float))


def select_bone_track(
    frames: Sequence[FrameCandidates],
    image_to_reference: np.ndarray,
    params: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
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

    Returns
    -------
    TrackChoice
    """
    p = params
    n = len(frames)
    poses = np.asarray(image_to_reference, dtype=float).reshape(n, 4, 4)
    reason = [""] * n
    detail = [""] * n
    chosen = np.full(n, -1, dtype=np.intp)
    conf = np.zeros(n)
    nodes: list[tuple[int, int]] = []  # (frame, candidate index)
    for f, fc in enumerate(frames):
        for c, cand in enumerate(fc.candidates):
            # No evidence above the null level along the contour (e.g. a snake
            # stopped in speckle): not a candidate.
            if not cand.reverberation and cand.strength > 0:
                nodes.append((f, c))
    best = [max((c.strength for c in fc.usable), default=np.nan) for fc in frames]
    best_arr = np.asarray(best, dtype=float)
    pos = best_arr[np.isfinite(best_arr) & (best_arr > 0)]
    typical = float(np.median(pos)) if pos.size else 1.0
    for f, fc in enumerate(frames):
        if not fc.usable:
            reason[f] = REASONS["reverb"] if fc.candidates else REASONS["none"]
        elif max(c.strength for c in fc.usable) <= 0:
            reason[f] = REASONS["weak"]
    if not nodes:
        return TrackChoice(chosen, conf, reason, detail)

    m = len(nodes)
    value = np.array(
        [
            min(max(frames[f].candidates[c].strength, 0.0) / typical, p.strength_cap)
            * (p.beneath_factor if frames[f].candidates[c].echo_beneath else 1.0)
            for f, c in nodes
        ]
    )
    ref = [
        pixels_to_reference(
            poses[f], _sampled(frames[f].candidates[c].points_px, frames[f].spacing)
        )
        for f, c in nodes
    ]
    by_frame: dict[int, list[int]] = {}
    for k, (f, _) in enumerate(nodes):
        by_frame.setdefault(f, []).append(k)
    score = value.copy()  # best path value ending at each node (a path may start anywhere)
    back = np.full(m, -1, dtype=np.intp)
    link_dev = np.zeros(m)
    origin, axes, normal = frame_planes(poses)
    b_mm = [
        _sampled(frames[f].candidates[c].points_px, frames[f].spacing)
        * np.asarray(frames[f].spacing, dtype=float)
        for f, c in nodes
    ]
    # Bounding boxes (lateral, depth) of every node in its own plane: most pairs (a
    # fascia and the bone, mm apart in depth) are ruled out on them without the
    # point-to-contour distances.
    box = [
        (float(b[:, 0].min()), float(b[:, 0].max()), float(b[:, 1].min()), float(b[:, 1].max()))
        for b in b_mm
    ]
    for g in sorted(by_frame):
        for f in range(max(0, g - p.max_skip - 1), g):
            for ka in by_frame.get(f, ()):
                # Contour a in g's plane, once for all of g's candidates.
                a = _project(ref[ka], origin[g], axes[g], normal[g])
                reach = p.max_deviation * (
                    p.tolerance_mm + p.tolerance_per_mm * float(a[:, 2].max())
                )
                a_box = (
                    float(a[:, 0].min()),
                    float(a[:, 0].max()),
                    float(a[:, 1].min()),
                    float(a[:, 1].max()),
                )
                for kb in by_frame[g]:
                    bb = box[kb]
                    if (
                        bb[0] > a_box[1] + 1.0
                        or bb[1] < a_box[0] - 1.0
                        or bb[2] > a_box[3] + reach
                        or bb[3] < a_box[2] - reach
                    ):
                        continue
                    d, share, z = _in_plane_deviation(a, b_mm[kb])
                    if share < p.min_overlap_share or not np.isfinite(d):
                        continue
                    tol = p.tolerance_mm + p.tolerance_per_mm * z
                    if d > p.max_deviation * tol:
                        continue
                    s = score[ka] - (d / tol) ** 2 - p.miss_cost * (g - f - 1) + value[kb]
                    if s > score[kb]:
                        score[kb], back[kb], link_dev[kb] = s, ka, d / tol
    # The track: the best-valued end whose path links at least ``min_track_frames``
    # frames (fewer if the sweep has fewer): one frame alone, or two, can be speckle
    # that happens to look like a line; a bone continues through the sweep.
    if not (back >= 0).any():
        # No two frames link (a sweep of a few scattered frames, tens of mm apart):
        # continuity cannot be checked, so each frame is judged alone, its strongest
        # candidate kept (the track has nothing to choose between).
        for f, ks in by_frame.items():
            k = max(ks, key=lambda q: value[q])
            chosen[f] = nodes[k][1]
            conf[f] = min(1.0, value[k])
        return TrackChoice(chosen, conf, reason, detail)
    need = min(p.min_track_frames, len(by_frame))
    length = np.zeros(m, dtype=np.intp)
    for k in range(m):  # nodes are in frame order, so a predecessor comes first
        length[k] = 1 + (length[back[k]] if back[k] >= 0 else 0)
    ends = [k for k in np.argsort(-score) if length[k] >= need]
    on_track: list[int] = []
    k = int(ends[0]) if ends else -1
    while k >= 0:
        on_track.append(k)
        k = int(back[k])
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
        if track_frames.size:
            g = int(track_frames[np.argmin(np.abs(track_frames - f))])
            g_ref = pixels_to_reference(
                poses[g], _sampled(frames[g].candidates[chosen[g]].points_px, frames[g].spacing)
            )
            devs = [
                _deviation(g_ref, _sampled(c.points_px, fc.spacing), poses[f], fc.spacing)[0]
                for c in fc.usable
            ]
            dmin = min(devs)
            detail[f] = (
                f"{dmin:.1f} mm from frame {g}"
                if np.isfinite(dmin)
                else f"no overlap with frame {g}"
            )
    return TrackChoice(chosen, conf, reason, detail)

"""Synthetic frames of candidate contours in lanes, for the track's tests (two bones in
view, bone points): each lane a straight contour at one depth over a range of columns."""

from __future__ import annotations

import numpy as np

from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate, FrameCandidates
from BoneUSRecon.Logic.segmentation.params import RejectionParams
from BoneUSRecon.Logic.segmentation.track import TrackChoice, select_bone_track
from BoneUSRecon.Logic.segmentation.track_incremental import IncrementalTrack

S = 0.25  # mm per pixel of the synthetic frames
W = 200  # their width in pixels (50 mm)
DEPTH_MM = 8.0  # the depth every synthetic contour lies at
STEP_MM = 1.4  # the frames' spacing along the sweep (z)


def make_lanes(
    n: int, lanes: list[tuple[float, float, float, set[int] | None]], fov: bool = True
) -> tuple[list[FrameCandidates], np.ndarray]:
    """``n`` frames ``STEP_MM`` apart along z, each with one candidate per lane ``(first
    column, last column, strength, frames it shows in or None for all)``, ``DEPTH_MM``
    deep; ``fov``: the frames know their field of view (all ``W`` columns)."""
    frames, poses = [], []
    for k in range(n):
        cands = []
        for a, b, strength, where in lanes:
            if where is not None and k not in where:
                continue
            i = np.arange(a, b + 1, 2.0)
            pts = np.column_stack([i, np.full(i.size, DEPTH_MM / S)])
            cands.append(BoneCandidate(pts, np.full(i.size, 200.0), strength, 3.0, 2.0))
        cands.sort(key=lambda c: -c.strength)
        frames.append(FrameCandidates(tuple(cands), (S, S), fov_px=(0.0, W - 1.0) if fov else None))
        m = np.eye(4)
        m[0, 0] = m[1, 1] = S
        m[2, 3] = STEP_MM * k
        poses.append(m)
    return frames, np.stack(poses)


def both_solvers(
    frames: list[FrameCandidates],
    poses: np.ndarray,
    params: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
) -> TrackChoice:
    """The batch choice, checked equal to the incremental one (live's solver): choices,
    confidences, reasons and details."""
    batch = select_bone_track(frames, poses, params)
    track = IncrementalTrack(params)
    for fc, pose in zip(frames, poses, strict=True):
        track.add(fc, pose)
    inc = track.solve()
    np.testing.assert_array_equal(inc.chosen, batch.chosen)
    np.testing.assert_array_equal(inc.confidence, batch.confidence)
    assert inc.reason == batch.reason and inc.detail == batch.detail
    return batch


def lane_of(frames: list[FrameCandidates], chosen: np.ndarray) -> set[float]:
    """First columns of the chosen candidates."""
    return {float(frames[k].candidates[c].points_px[0, 0]) for k, c in enumerate(chosen) if c >= 0}

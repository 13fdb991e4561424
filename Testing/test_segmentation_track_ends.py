"""The bone track carried on past its ends (``RejectionParams.extend_ends``).

A frame left off inside a track costs ``miss_cost``; one past its ends used to cost
nothing, so a weak end of the bone (deeper, an unsteady probe: values under half the
sweep's typical strength) was left off although its contours linked within tolerance
(the unsteady-hand hard tibia s229 lost frames 0-5 and the surface its first 30 mm).
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate, FrameCandidates
from BoneUSRecon.Logic.segmentation.params import RejectionParams
from BoneUSRecon.Logic.segmentation.track import select_bone_track
from BoneUSRecon.Logic.segmentation.track_incremental import IncrementalTrack

_PX = 0.1  # mm per pixel
_STEP = 3.0  # mm between frames: link tolerance 1 + 0.4 * 3 = 2.2 mm
_COLS = np.arange(20.0, 140.0, 2.0)


def _frame(row: float, strength: float, beside: bool = False) -> FrameCandidates:
    """A frame with a flat contour at ``row`` of the given strength; ``beside``: a
    strong contour over other columns too (a neighbouring bone, never linked to it)."""
    cands = [
        BoneCandidate(
            np.column_stack([_COLS, np.full(_COLS.size, row)]),
            np.full(_COLS.size, 200.0),
            strength,
            3.0,
            2.0,
        )
    ]
    if beside:
        far = _COLS + 300.0
        cands.append(
            BoneCandidate(
                np.column_stack([far, np.full(far.size, 60.0)]),
                np.full(far.size, 200.0),
                10.0,
                3.0,
                2.0,
            )
        )
    return FrameCandidates(tuple(cands), (_PX, _PX))


def _poses(n: int) -> np.ndarray:
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, 0, 0] = m[:, 1, 1] = _PX
    m[:, 2, 3] = _STEP * np.arange(n)
    return m


def _weak_start(n_weak: int = 4, n: int = 12) -> list[FrameCandidates]:
    """Frames 0..n_weak-1 show the bone at 0.4 of the sweep's typical strength, each
    1.5 mm deeper than the next (links at 0.68 tolerance: cost 0.47, more than the
    value, less than the value and ``miss_cost``); the rest strong and level."""
    return [
        _frame(60.0 + 15.0 * (n_weak - k), 4.0) if k < n_weak else _frame(60.0, 10.0)
        for k in range(n)
    ]


def test_a_weak_end_of_the_bone_linked_within_tolerance_joins_the_track():
    frames, poses = _weak_start(), _poses(12)
    ch = select_bone_track(frames, poses)
    assert (ch.chosen == 0).all()
    assert not any(ch.reason)
    # Without: the track starts where the strong frames do (the old trade at its ends).
    off = select_bone_track(frames, poses, RejectionParams(extend_ends=False))
    assert (off.chosen[:4] == -1).all() and (off.chosen[4:] == 0).all()
    assert set(off.reason[:4]) == {"jump from neighbouring frames"}


def test_the_last_frames_too_and_not_a_node_worth_less_than_the_credit():
    # The weak frames at the end of the sweep (the same stretch reversed).
    frames, poses = _weak_start()[::-1], _poses(12)
    assert (select_bone_track(frames, poses).chosen == 0).all()
    # A contour 1.1 mm off (0.5 tolerance: cost 0.25) worth 0.1 of the typical
    # strength: with the credit it would add value, but a node worth less than the
    # credit itself earns none (one side vouches for it), so the track ends before.
    frames2 = [_frame(60.0, 10.0) for _ in range(11)] + [_frame(71.0, 1.0)]
    ch = select_bone_track(frames2, poses)
    assert (ch.chosen[:11] == 0).all() and ch.chosen[11] == -1
    # Worth the credit (0.3 of the typical strength), the same contour joins.
    frames2[11] = _frame(71.0, 3.0)
    assert (select_bone_track(frames2, poses).chosen == 0).all()


def test_a_guided_contour_past_an_end_joins_though_worth_less_than_the_credit():
    """The recovery's search past the track's end (one side guiding) found the bone's
    contour in the last frame (hard ulna at the cadaver's geometry, s241, frame 39:
    0.11 mm from the bone, worth 0.08 of the typical strength, 0.6 mm from frame 38's).
    The floor on a node's value past an end keeps out a weak piece the frame's own
    passes found beside the bone; a guided contour lies in the band the track's
    contours allow, which is what vouches for it, so the floor does not apply."""
    poses = _poses(12)
    frames = [_frame(60.0, 10.0) for _ in range(11)] + [_frame(71.0, 1.0)]
    assert select_bone_track(frames, poses).chosen[11] == -1  # the floor, unguided
    guided = dataclasses.replace(frames[11].candidates[0], guided=True)
    frames[11] = dataclasses.replace(frames[11], candidates=(guided,))
    ch = select_bone_track(frames, poses)
    assert (ch.chosen == 0).all()
    track = IncrementalTrack(RejectionParams())
    for fc, pose in zip(frames, poses, strict=True):
        track.add(fc, pose)
    assert (track.solve().chosen == ch.chosen).all()


def test_the_track_grows_along_the_bone_not_onto_a_stronger_bone_beside():
    """Past the start, a neighbouring bone beside (other columns), stronger than the
    weak end of the bone swept, is not taken: the growth follows links from the track's
    first contour."""
    frames = [
        _frame(60.0 + 15.0 * (4 - k), 4.0, beside=k < 4) if k < 4 else _frame(60.0, 10.0)
        for k in range(12)
    ]
    ch = select_bone_track(frames, _poses(12))
    assert (ch.chosen == 0).all()


def test_the_track_does_not_grow_over_a_joining_contour_onto_the_bone_beside():
    """Before the bone's first strong frame, a contour running over both bones (along a
    fascia between them) and then the bone beside alone, each linked to the next within
    tolerance as the weak end in :func:`_weak_start` is: not in the track's lane (the
    joining contour lies two thirds beside it), so the track does not grow onto them."""
    frames = _weak_start()
    for k in range(4):
        cols = np.arange(20.0, 440.0, 2.0) if k == 3 else _COLS + 300.0
        row = 60.0 + 15.0 * (4 - k)
        cand = BoneCandidate(
            np.column_stack([cols, np.full(cols.size, row)]),
            np.full(cols.size, 200.0),
            4.0,
            3.0,
            2.0,
        )
        frames[k] = FrameCandidates((cand,), (_PX, _PX))
    ch = select_bone_track(frames, _poses(12))
    assert (ch.chosen[4:] == 0).all()
    assert (ch.chosen[:4] == -1).all()


def test_past_an_end_the_track_steps_over_one_frame_at_most():
    """Past the last strong frame, nothing in the next frame(s), then a contour half a
    tolerance off worth 0.4 (one frame skipped) or 0.8 (two skipped) of the typical
    strength: each adds value with the credit, but a bone shows in the frames next to
    the track's end; a chain stepping over two of them is a structure that comes and
    goes, and is not taken."""
    empty = FrameCandidates((), (_PX, _PX))
    poses = _poses(12)
    # One frame skipped: 6 mm apart, tolerance 3.4 mm, half of it 1.7 mm = 17 px.
    frames = [_frame(60.0, 10.0) for _ in range(10)] + [empty, _frame(77.0, 4.0)]
    ch = select_bone_track(frames, poses)
    assert (ch.chosen[:10] == 0).all() and ch.chosen[11] == 0
    assert (select_bone_track(frames, poses, RejectionParams(extend_ends=False)).chosen[11]) == -1
    # Two frames skipped: 9 mm apart, tolerance 4.6 mm, half of it 2.3 mm = 23 px.
    frames = [_frame(60.0, 10.0) for _ in range(9)] + [empty, empty, _frame(83.0, 8.0)]
    ch = select_bone_track(frames, poses)
    assert (ch.chosen[:9] == 0).all() and ch.chosen[11] == -1


@pytest.mark.parametrize("reverse", [False, True], ids=["start", "end"])
def test_the_live_track_grows_its_ends_as_the_batch_one(reverse):
    frames, poses = _weak_start(), _poses(12)
    if reverse:
        frames = frames[::-1]
    track = IncrementalTrack()
    for k, (fc, m) in enumerate(zip(frames, poses, strict=True)):
        track.add(fc, m)
        live, batch = track.solve(), select_bone_track(frames[: k + 1], poses[: k + 1])
        np.testing.assert_array_equal(live.chosen, batch.chosen)
        np.testing.assert_array_equal(live.confidence, batch.confidence)
        assert live.reason == batch.reason
    assert (track.solve().chosen == 0).all()


def test_extend_ends_is_a_parameter():
    assert RejectionParams().extend_ends
    assert not dataclasses.replace(RejectionParams(), extend_ends=False).extend_ends

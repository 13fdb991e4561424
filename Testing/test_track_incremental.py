"""The incremental bone track (live) chooses exactly what the batch track chooses.

:class:`~BoneUSRecon.Logic.segmentation.track_incremental.IncrementalTrack` links each
frame once as it arrives and re-runs only the dynamic programme at a refit; it must give
the same :class:`TrackChoice` (choices, confidences, reasons, details) as
:func:`~BoneUSRecon.Logic.segmentation.track.select_bone_track` over the same
candidates, after every frame, and after frames are dropped (live thinning).
"""

from __future__ import annotations

import numpy as np
import pytest

from BoneUSRecon.Logic.segmentation import frame_candidates_for
from BoneUSRecon.Logic.segmentation.track import TrackChoice, select_bone_track
from BoneUSRecon.Logic.segmentation.track_incremental import IncrementalTrack
from BoneUSRecon.Logic.sweep import pixel_spacing


def _candidates(sim):
    sw = sim.sweep
    idx = sw.valid_indices
    sp = pixel_spacing(sw.image_to_reference)
    frames = [frame_candidates_for(sw.frames[k], (float(sp[k, 0]), float(sp[k, 1]))) for k in idx]
    return frames, sw.image_to_reference[idx]


def _assert_same(a: TrackChoice, b: TrackChoice) -> None:
    np.testing.assert_array_equal(a.chosen, b.chosen)
    np.testing.assert_array_equal(a.confidence, b.confidence)  # bit for bit
    assert a.reason == b.reason
    assert a.detail == b.detail


CASES = [
    {"seed": 1, "corrupted_fraction": 0.1},
    {"bone": "tibia", "realism": "hard", "seed": 2},  # far cortex and bands: real choices
    {"bone": "humerus", "realism": "hard", "seed": 3, "corrupted_fraction": 0.1},
]


@pytest.mark.parametrize("params", CASES, ids=["clavicle", "tibia-hard", "humerus-hard"])
def test_incremental_track_equals_batch(sim_factory, params):
    frames, poses = _candidates(sim_factory(**params))
    n = len(frames)
    track = IncrementalTrack()
    for k in range(n):
        track.add(frames[k], poses[k])
        if k % 6 == 2 or k == n - 1:  # refits along the way
            _assert_same(track.solve(), select_bone_track(frames[: k + 1], poses[: k + 1]))
    full = track.solve()
    # The sweep gives the track something to decide: frames with several candidates,
    # and frames off the track for continuity, not only for having no candidate.
    assert sum(len(fc.usable) > 1 for fc in frames) >= 5
    assert "jump from neighbouring frames" in full.reason
    assert (full.chosen >= 0).sum() >= n // 2


@pytest.mark.parametrize("params", CASES[:2], ids=["clavicle", "tibia-hard"])
def test_incremental_track_after_dropping_frames(sim_factory, params):
    """Thinning (every other frame), then an irregular choice: frames that become
    neighbours are linked, in spare time or at the solve, and the track is the batch one."""
    frames, poses = _candidates(sim_factory(**params))
    track = IncrementalTrack()
    for fc, m in zip(frames, poses, strict=True):
        track.add(fc, m)
    keep = list(range(0, len(frames), 2))
    track.keep(range(0, len(track), 2))
    assert track.owed > 0  # frames 10..18 apart (old numbering) were never linked
    owed = track.owed
    assert track.work(0.0) >= 1 and track.owed < owed  # some now, the rest at the solve
    _assert_same(track.solve(), select_bone_track([frames[i] for i in keep], poses[keep]))
    assert track.owed == 0
    sub = [0, 1, 2, 6, 7, 12, 13, 14, 15]
    track.keep(sub)
    kept = [keep[i] for i in sub]
    _assert_same(track.solve(), select_bone_track([frames[i] for i in kept], poses[kept]))
    # New frames after the drop link to the kept ones.
    for i in range(kept[-1] + 1, min(kept[-1] + 6, len(frames))):
        track.add(frames[i], poses[i])
        kept.append(i)
    _assert_same(track.solve(), select_bone_track([frames[i] for i in kept], poses[kept]))


def test_incremental_track_empty_and_refused(sim_small):
    track = IncrementalTrack()
    ch = track.solve()
    assert ch.chosen.size == 0
    frames, poses = _candidates(sim_small)
    track.add(frames[0], poses[0])
    with pytest.raises(IndexError):
        track.keep([0, 3])

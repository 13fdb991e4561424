"""The sweep-level track with the candidates seen at the cadaver's image geometry.

At 475 x 405 pixels of 0.108 mm (issue 10's cadaver sweep) the segmenter's candidates on
the bone are often partial pieces (half of the contour, a different half from one frame
to the next), and bright far-cortex / fascia candidates marked ``echo_beneath`` are the
strongest of most frames. The track must still follow the bone through every frame.
Candidates here are built from the simulator's true contours and poses, so what is
tested is the track's choice alone.
"""

from __future__ import annotations

import numpy as np

from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate, FrameCandidates
from BoneUSRecon.Logic.segmentation.track import select_bone_track
from BoneUSRecon.Logic.segmentation.track_incremental import IncrementalTrack
from BoneUSRecon.Logic.sweep import pixel_spacing


def _truth(sim_factory):
    sim = sim_factory(bone="tibia", seed=5)
    sw = sim.sweep
    idx = [k for k in sw.valid_indices if len(sim.true_contours_px[k]) >= 20]
    sp = pixel_spacing(sw.image_to_reference)
    spacing = (float(sp[idx[0], 0]), float(sp[idx[0], 1]))
    contours = [np.asarray(sim.true_contours_px[k], dtype=float) for k in idx]
    return contours, sw.image_to_reference[idx], spacing


def _cand(pts: np.ndarray, strength: float, beneath: bool = False) -> BoneCandidate:
    return BoneCandidate(pts, np.full(len(pts), 200.0), strength, 2.0, 1.0, False, beneath)


def _same(a, b) -> None:
    np.testing.assert_array_equal(a.chosen, b.chosen)
    np.testing.assert_array_equal(a.confidence, b.confidence)


def test_partial_pieces_of_the_bone_link_frame_to_frame(sim_factory):
    """Each frame offers only a piece of the bone, alternately its left and right part
    (meeting end to end, overlapping by < ``min_overlap_share``): consecutive pieces lie
    on one contour, so every frame is on the track (on the old code the track linked
    only every other frame, the same halves, and rejected the rest as jumps)."""
    contours, poses, spacing = _truth(sim_factory)
    frames = []
    for k, c in enumerate(contours):
        c = c[np.argsort(c[:, 0])]
        half = len(c) // 2
        piece = c[: half + 1] if k % 2 == 0 else c[half - 1 :]
        frames.append(FrameCandidates((_cand(piece, 5.0),), spacing))
    ch = select_bone_track(frames, poses)
    assert (ch.chosen == 0).all(), ch.reason
    live = IncrementalTrack()
    for fc, pose in zip(frames, poses, strict=True):
        live.add(fc, pose)
    _same(live.solve(), ch)


def test_bright_candidates_with_an_echo_beneath_do_not_set_the_unit(sim_factory):
    """Every frame's strongest candidate is a bright far cortex (``echo_beneath``, 8 mm
    under the bone); the bone is 3x weaker and, every other frame, 1 mm deeper (a thick
    echo). The nodes' unit is the strongest value a node can have: the bone's frames are
    worth a full unit and all are kept (with the far cortex as unit the bone's value
    was 0.3, under the cost of the 1 mm offsets, and every other frame was rejected)."""
    contours, poses, spacing = _truth(sim_factory)
    frames = []
    for k, c in enumerate(contours):
        bone = c + [0.0, (1.0 / spacing[1]) * (k % 2)]
        far = c + [0.0, 8.0 / spacing[1]]
        frames.append(FrameCandidates((_cand(far, 10.0, True), _cand(bone, 3.0)), spacing))
    ch = select_bone_track(frames, poses)
    assert (ch.chosen == 1).all(), ch.reason
    live = IncrementalTrack()
    for fc, pose in zip(frames, poses, strict=True):
        live.add(fc, pose)
    _same(live.solve(), ch)

"""Two bones in view (the radius and the ulna, the tibia and the fibula): each is a
candidate of its own (``candidates._valley_runs``, ``candidates._separate_domes``) and
the track follows the one in the middle of the image (``track.central_track``,
``RejectionParams.lane_*``)."""

from __future__ import annotations

import dataclasses
import types

import numpy as np
import pytest
from lane_frames import both_solvers, lane_of, make_lanes
from scipy.spatial import cKDTree
from two_bones import forearm_beside

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.segmentation.candidates import (
    FrameCandidates,
    _dense_rows,
    _mark_echo_beneath,
    _separate_domes,
    _valley_runs,
    frame_candidates,
)
from BoneUSRecon.Logic.segmentation.params import RejectionParams, SegmentationParams
from BoneUSRecon.Logic.segmentation.track import _in_lane
from BoneUSRecon.Logic.simulation import SimulationParams, simulate
from BoneUSRecon.Logic.simulation.scoring import score_simulation


def test_the_bone_in_the_middle_is_followed_over_a_stronger_one_beside_it():
    # A neighbour toward the left edge (columns 10-60: 0.65 of the half-width off the
    # middle) with 1.5x the evidence of the bone in the middle (columns 80-120).
    frames, poses = make_lanes(12, [(10, 60, 12.0, None), (80, 120, 8.0, None)])
    assert lane_of(frames, both_solvers(frames, poses).chosen) == {80.0}
    # Without the rule the stronger one wins: the rule is what chose.
    off = RejectionParams(lane_offcentre=1.0)
    assert lane_of(frames, both_solvers(frames, poses, off).chosen) == {10.0}


def test_an_off_centre_bone_stays_when_nothing_else_is_a_bone_track():
    # A look-alike in the middle in 3 of 12 frames (a vessel or a fascia comes and goes).
    frames, poses = make_lanes(12, [(10, 60, 12.0, None), (80, 120, 8.0, {3, 4, 5})])
    assert lane_of(frames, both_solvers(frames, poses).chosen) == {10.0}
    # A track in the middle with too little evidence (a tenth: a fascia).
    frames, poses = make_lanes(12, [(10, 60, 12.0, None), (80, 120, 1.0, None)])
    assert lane_of(frames, both_solvers(frames, poses).chosen) == {10.0}
    # Frames whose field of view is not known: no preference.
    frames, poses = make_lanes(12, [(10, 60, 12.0, None), (80, 120, 8.0, None)], fov=False)
    assert lane_of(frames, both_solvers(frames, poses).chosen) == {10.0}


def test_a_bone_near_the_middle_is_never_second_guessed():
    # The bone at 0.3 of the half-width, a weaker track nearer the middle beside it.
    frames, poses = make_lanes(12, [(115, 145, 12.0, None), (85, 105, 8.0, None)])
    assert lane_of(frames, both_solvers(frames, poses).chosen) == {115.0}


def _beside(bone: str, neighbour_mm: float = 18.0, **kw: object):
    """A simulated forearm sweep of ``bone`` with the other forearm bone ``neighbour_mm``
    beside it (toward the wrist the two come 18 mm close; both show whole)."""
    return simulate(SimulationParams(bone=bone, neighbour_mm=neighbour_mm, **kw))


@pytest.mark.parametrize(("realism", "seed"), [("standard", 1), ("hard", 2)])
def test_two_forearm_bones_in_view_the_swept_one_is_segmented(realism, seed):
    """The ulna swept in the middle of a 51 mm image, the radius 18 mm beside it (toward
    the wrist the two come that close): the radius's bigger echo had the track."""
    sim = _beside(
        "ulna", n_frames=12, width=160, height=136, spacing_mm=0.32, realism=realism, seed=seed
    )
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] >= 0.8 and s["wrong_share"] == 0.0
    assert s["median_mm"] <= 0.3
    p = SegmentationParams()
    off = dataclasses.replace(p, rejection=dataclasses.replace(p.rejection, lane_offcentre=1.0))
    assert score_simulation(segment_sweep(sim.sweep, off), sim).summary()["wrong_share"] >= 0.5


@pytest.mark.parametrize("bad", [0.0, -18.0])
def test_neighbour_distance_must_be_positive(bad):
    with pytest.raises(BoneUSReconError, match="neighbour_mm"):
        SimulationParams(bone="ulna", neighbour_mm=bad)


@pytest.mark.parametrize(
    ("field", "value"), [("lane_offcentre", -0.1), ("lane_frames", 1.5), ("lane_value", -1.0)]
)
def test_lane_parameters_are_checked(field, value):
    with pytest.raises(BoneUSReconError, match=field):
        RejectionParams(**{field: value})


def _two_domes(gap_depth_mm: float = 2.0) -> np.ndarray:
    """A contour over two domes (tops 6 mm deep at columns 50 and 150, 0.1 mm pixels)
    meeting in a valley ``gap_depth_mm`` under the tops at column 100."""
    i = np.arange(0.0, 200.0)
    z = 6.0 + gap_depth_mm * np.minimum(np.abs(i - 50.0), np.abs(i - 150.0)) / 50.0
    return np.column_stack([i, z / 0.1])


def test_a_valley_with_tissue_under_it_between_two_shadows_parts_two_bones():
    pts = _two_domes()
    gap = np.abs(pts[:, 0] - 100.0) <= 12.0
    shadow = np.where(gap, -0.5, 0.8)
    runs = _valley_runs(pts, (0.1, 0.1), 0.5, shadow)
    assert [(int(r[0]), int(r[-1])) for r in runs] == [(0, 100), (100, 199)]
    # A groove: the bone's shadow under its bottom too. Stays whole.
    assert len(_valley_runs(pts, (0.1, 0.1), 0.5, np.full(200, 0.8))) == 1
    # The same valley without a dip in the shadow under it: a groove as well.
    assert len(_valley_runs(pts, (0.1, 0.1), 0.5, np.where(gap, 0.6, 0.8))) == 1
    # A concave surface spanning the image (no tissue beside its deepest stretch, so
    # its bottom reads shadowless too): its sides are no domes, it stays whole.
    bowl = np.column_stack(
        [pts[:, 0], (6.0 + 2.0 * (1.0 - np.abs(pts[:, 0] - 100.0) / 100.0)) / 0.1]
    )
    assert len(_valley_runs(bowl, (0.1, 0.1), 0.5, shadow)) == 1


def test_a_second_dome_of_one_path_is_offered_a_flat_run_is_not():
    pts = _two_domes()
    p = SegmentationParams().shadowpath

    def piece(strength: float, mask: np.ndarray) -> tuple:
        # The pieces a path over two bones leaves (columns: one per point here).
        return (strength, mask, np.flatnonzero(mask), np.zeros(int(mask.sum()), np.intp))

    def offered(pieces: list, best: tuple, contour: np.ndarray = pts) -> list:
        return _separate_domes(pieces, best, contour, (0.1, 0.1), p, 20)

    left, right = pts[:, 0] <= 80.0, pts[:, 0] >= 120.0
    best, dome = piece(5.0, left), piece(3.0, right)
    assert offered([best, dome], best) == [dome]
    # A dome touching the best piece (two bones 14 mm apart meet at the valley): offered.
    touching = piece(3.0, pts[:, 0] > 80.0)
    assert offered([best, touching], best) == [touching]
    # A hump shorter than the passes' shortest contour: a grain, not offered.
    grain = piece(3.0, np.abs(pts[:, 0] - 150.0) <= 5.0)
    assert offered([best, grain], best) == []
    # A crest: its top is the best piece, its flank touching it falls one way: not offered.
    crest = np.column_stack([pts[:, 0], (6.0 + 0.08 * np.abs(pts[:, 0] - 50.0)) / 0.1])
    top, flank = piece(5.0, np.abs(pts[:, 0] - 50.0) <= 20.0), piece(3.0, pts[:, 0] > 70.0)
    assert offered([top, flank], top, crest) == []
    # No evidence above the null level: not offered.
    weak = piece(-0.5, right)
    assert offered([best, weak], best) == []
    # A layer running on flat (or falling one way) from the bone's shoulder.
    flat = pts.copy()
    flat[right, 1] = pts[100, 1]
    assert offered([best, dome], best, flat) == []


@pytest.mark.parametrize("seed", [127, 3])
def test_the_bone_swept_is_offered_in_every_frame_beside_its_neighbour(seed):
    """Radius swept, the ulna 18 mm beside it, at the cadaver's 0.108 mm: one path may run
    over both bones, and the radius was then no candidate of its frame (7 of 8 frames
    offered it before the valley between two shadows was cut and second domes offered)."""
    s = _beside("radius", n_frames=8, width=475, height=405, spacing_mm=0.108, seed=seed)
    p = SegmentationParams().shadowpath
    for f in range(8):
        truth = np.asarray(s.true_contours_px[f]) * 0.108
        fc = frame_candidates(np.asarray(s.sweep.frames[f]), (0.108, 0.108), p)
        d = [np.median(cKDTree(truth).query(c.points_px * 0.108)[0]) for c in fc.usable]
        assert min(d) < 0.5, f


@pytest.mark.parametrize(("seed", "before"), [(8, 1.0), (3, 0.58)])
def test_two_bones_that_touch_are_two_candidates_and_the_swept_one_is_followed(seed, before):
    """The ulna swept, the radius 14 mm beside it (the two touch in the image, no tissue
    between their tops), standard realism, 320 x 256 at 0.16 mm. One path runs over both
    bones; its pieces met at the valley, so the ulna's was not offered (a gap of 2 mm was
    asked between two domes), and the far line under both joined them into one contour
    (pieces over one shadow). Before: wrong share ``before``, the track on the radius."""
    sim = forearm_beside("ulna", 14.0, seed, realism="standard")
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] >= 0.9 and s["wrong_share"] == 0.0, (s, before)
    assert s["median_mm"] <= 0.1


def _lanes_of(frames: list[FrameCandidates], chosen: np.ndarray) -> list[float]:
    """First column of each frame's chosen candidate (NaN: none)."""
    return [
        float(frames[k].candidates[c].points_px[0, 0]) if c >= 0 else np.nan
        for k, c in enumerate(chosen)
    ]


def test_a_track_crossing_to_the_bone_beside_over_a_joining_contour_is_kept_to_one():
    """The bone in the middle (columns 80-120) over 12 frames, weak in the last four; in
    frame 8 a contour runs over both bones (columns 50-110, a fascia joining them at
    their level) and a stronger bone beside (columns 20-70) shows in the last three.
    Every link is within tolerance, so the best track crossed over; kept to one lane it
    follows the bone in the middle in every frame."""
    frames, poses = make_lanes(
        12,
        [
            (80, 120, 8.0, set(range(8))),
            (80, 120, 2.0, {8, 9, 10, 11}),
            (50, 110, 12.0, {8}),
            (20, 70, 10.0, {9, 10, 11}),
        ],
    )
    lanes = _lanes_of(frames, both_solvers(frames, poses).chosen)
    assert lanes[:8] == [80.0] * 8 and lanes[9:] == [80.0] * 3
    # The control, with neither rule: the track crosses. (With one_lane off alone the
    # nearer-middle step moves its three contours off the middle since session 34.)
    off = RejectionParams(one_lane=False, lane_offcentre=1.0)
    assert _lanes_of(frames, both_solvers(frames, poses, off).chosen)[9:] == [20.0] * 3
    no_lane = RejectionParams(one_lane=False)
    assert _lanes_of(frames, both_solvers(frames, poses, no_lane).chosen)[9:] == [80.0] * 3


def _handover(
    middle: tuple[int, int],
    beside: tuple[int, int],
    early: set[int],
    late: set[int],
    s_middle: tuple[float, float],
    s_beside: tuple[float, float],
) -> list[tuple[int, int, float, set[int]]]:
    """Lanes of :func:`make_lanes` for two bones handing the evidence over: the bone in
    the middle and the one beside (first and last columns), each with its strength in
    the ``early`` and the ``late`` frames."""
    return [
        (*middle, s_middle[0], early),
        (*middle, s_middle[1], late),
        (*beside, s_beside[0], early),
        (*beside, s_beside[1], late),
    ]


def test_a_track_crossing_from_the_bone_beside_to_the_middle_one_keeps_the_middle_one() -> None:
    """The bone in the middle (columns 80-120) in all 24 frames, faint in frames 0-12;
    the bone off the middle (150-195) strong in those, faint after; a contour joining
    them in frame 13. The best track crosses from the bone beside to the middle one
    there. Moved to the middle, it keeps the middle bone over the whole sweep: only the
    lane of the track's contours off the middle is ruled out. Before, the whole track's
    lane was, the middle bone's frames after the crossing with it, the track so chosen
    linked too few frames, and the crossing stayed (the simulated ulna with the radius
    14 mm beside, seed 151: recall 0.57)."""
    lanes = _handover(
        (80, 120), (150, 195), set(range(13)), set(range(14, 24)), (3.0, 6.0), (10.0, 2.0)
    )
    frames, poses = make_lanes(24, [*lanes, (85, 195, 12.0, {13})])
    lanes = _lanes_of(frames, both_solvers(frames, poses).chosen)
    # Frame 13 has only the joining contour, ruled out with the bone beside's lane.
    assert lanes[:13] == [80.0] * 13 and np.isnan(lanes[13]) and lanes[14:] == [80.0] * 10


def test_a_crossing_between_bones_that_share_columns_is_a_change_of_lane() -> None:
    """Two bones that touch: the one beside (columns 40-115) strong in frames 0-7, the
    one nearer the middle (90-150) strong in 8-15, each faint in the other's frames.
    The contours of frames 7 and 9 share columns, yet their middles lie farther apart
    than half their width: a change of lane, and kept to one the track holds the bone
    nearer the middle in every frame (it crossed before: the simulated radius with the
    ulna 14 mm beside, seed 109, recall 0.57)."""
    lanes = _handover(
        (90, 150), (40, 115), set(range(8)), set(range(8, 16)), (3.0, 10.0), (10.0, 3.0)
    )
    frames, poses = make_lanes(16, lanes)
    assert _lanes_of(frames, both_solvers(frames, poses).chosen) == [90.0] * 16
    crossing = RejectionParams(one_lane=False)
    assert _lanes_of(frames, both_solvers(frames, poses, crossing).chosen)[:8] == [40.0] * 8


def test_a_bone_showing_parts_of_its_top_apart_is_still_kept_from_its_neighbour() -> None:
    """Hard ulna, the radius 14 mm beside (320 x 256, seed 15): the ulna's contours
    show parts of its top whose middles lie 6 mm apart two frames apart, and its last
    two frames went to the radius. Cut at the moved middles too, the track falls into
    stretches none of which links as many frames; cut where contours share no column
    alone, it is kept to the ulna (recall 0.83 and wrong share 0.17 with the first
    kind of cut alone)."""
    sim = forearm_beside("ulna", 14.0, 15)
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] == 1.0 and s["wrong_share"] == 0.0


def test_one_contour_over_both_bones_does_not_put_the_bone_beside_in_the_lane() -> None:
    """The lane in a frame is the median span of the track's three nearest contours: a
    track on the bone beside (columns 150-195) whose contour in frame 5 runs over both
    bones (85-195) has the middle bone (80-120) outside its lane there."""
    frames, poses = make_lanes(
        10,
        [(80, 120, 3.0, None), (150, 195, 10.0, set(range(10)) - {5}), (85, 195, 12.0, {5})],
    )
    nodes = [(k, c) for k, fc in enumerate(frames) for c in range(len(fc.candidates))]
    path = [q for q, (k, c) in enumerate(nodes) if frames[k].candidates[c].points_px[0, 0] > 84]
    lane = _in_lane(frames, nodes, path)
    middle = [q for q, (k, c) in enumerate(nodes) if frames[k].candidates[c].points_px[0, 0] == 80]
    assert not lane[middle].any()
    assert lane[path].all()  # the path's own contours, the joining one too


def test_a_contour_covering_the_lane_and_running_on_beside_it_is_in_the_lane() -> None:
    """A contour over the lane of the bone beside (columns 150-195) and on over the
    middle bone (60-195, frame 2) lies two thirds outside the lane, yet covers all of
    it: it is in the lane (ruled out with it, a track chosen again cannot take it and
    with it the bone beside; the simulated ulna with the radius 14 mm beside, seed 163,
    went back to the radius in its last frames over two such contours). The middle
    bone's own contours are not."""
    frames, poses = make_lanes(
        6, [(80, 120, 3.0, None), (150, 195, 10.0, None), (60, 195, 5.0, {2})]
    )
    nodes = [(k, c) for k, fc in enumerate(frames) for c in range(len(fc.candidates))]
    first = {q: frames[k].candidates[c].points_px[0, 0] for q, (k, c) in enumerate(nodes)}
    lane = _in_lane(frames, nodes, [q for q, x in first.items() if x == 150])
    assert all(lane[q] for q, x in first.items() if x == 60)
    assert not any(lane[q] for q, x in first.items() if x == 80)


def test_a_bone_drifting_across_the_image_or_showing_one_flank_then_the_other_stays():
    """Lateral drift (5 columns per frame, 1.4 mm of sweep) never leaves a contour's
    columns within two frames; a bone showing its left flank, then all of it in one
    frame, then its right flank, has no other candidate in the right flank's frames:
    both tracks are as without the rule, over every frame."""
    drift = [(20 + 5 * k, 60 + 5 * k, 8.0, {k}) for k in range(12)]
    flanks = [(80, 98, 8.0, set(range(6))), (80, 122, 8.0, {6}), (104, 122, 8.0, set(range(7, 12)))]
    for lanes in (drift, flanks):
        frames, poses = make_lanes(12, lanes)
        on = both_solvers(frames, poses).chosen
        np.testing.assert_array_equal(
            on, both_solvers(frames, poses, RejectionParams(one_lane=False)).chosen
        )
        assert (on >= 0).all()


def _radius_beside(seed: int, neighbour_mm: float = 18.0):
    """A hard radius swept in the middle of a 51 mm image (320 x 256 at 0.16 mm, 12
    frames), the ulna ``neighbour_mm`` beside it."""
    return forearm_beside("radius", neighbour_mm, seed)


def test_the_track_does_not_cross_to_the_neighbour_over_a_fascia_joining_them():
    """Hard radius seed 1, the ulna 14 mm beside it (their tops touch): in frame 6 a
    contour runs from the radius's top along the fascia off its flank onto the ulna
    (columns 26-172; the fascia ends on the ulna's flank), and with neither lane rule
    the track follows the ulna in frames 7-11 (wrong share 0.42); kept to one lane,
    every frame is on the radius. (The ulna 18 mm beside, seed 1, showed this while the
    simulated fascia ran on under the ulna; with it ending at the ulna, none of seeds
    1-16 crosses there.)"""
    sim = _radius_beside(1, 14.0)
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] == 1.0 and s["wrong_share"] == 0.0 and s["median_mm"] <= 0.2
    # The control, with neither lane rule (the nearer-middle step alone also keeps it
    # to the radius since session 34).
    p = SegmentationParams()
    rej = dataclasses.replace(p.rejection, one_lane=False, lane_offcentre=1.0)
    off = dataclasses.replace(p, rejection=rej)
    assert score_simulation(segment_sweep(sim.sweep, off), sim).summary()["wrong_share"] >= 0.2


@pytest.mark.parametrize(("seed", "frame"), [(2, 7), (6, 9), (7, 4)])
def test_the_far_cortex_under_the_bone_is_flagged_where_bright_tissue_covers_it(seed, frame):
    """Hard radius, the ulna 18 mm beside it: in these frames the interior between the
    near and the far cortex reads 0.82 of the frame's typical tissue (reverberation
    bands), 0.73-0.77 of the brighter tissue over the bone. Judged against the frame's
    level alone the far cortex, 9-12 mm under the bone's top in the shadow, goes
    unflagged (in seed 2 the track then follows it in all 12 frames); against the
    tissue the sound crossed it is flagged and the track is on the bone. (Seed 2 frame
    9 showed it too while the simulated fascia ran on under the ulna: the far cortex
    there is now brighter than the faint near cortex over it and not flagged, yet
    never chosen.)"""
    sim = _radius_beside(seed)
    sp = SegmentationParams().shadowpath
    t = np.asarray(sim.true_contours_px[frame]) * 0.16
    fc = frame_candidates(np.asarray(sim.sweep.frames[frame]), (0.16, 0.16), sp)
    far = [c for c in fc.usable if np.median(cKDTree(t).query(c.points_px * 0.16)[0]) > 5.0]
    deep = [c for c in far if np.median(c.points_px[:, 1]) * 0.16 > t[:, 1].max()]
    assert deep and all(c.echo_beneath for c in deep)
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["wrong_share"] == 0.0 and s["recall"] >= 0.7


def test_a_track_on_one_bone_all_along_is_not_moved_to_the_bone_beside():
    """The bone in the middle shows the left part of its top (columns 100-140, then
    100-160 in frame 6), then the right part (142-180): contours two frames apart share
    no column. The bone beside (20-70) shows in frames 8-11, linked to frame 6 over a
    contour reaching both (frame 7, 40-150). Choosing the track without the right
    part's lane would move it to the bone beside over as many frames; that track does
    not reach the middle bone's lane there, so the track stays on the middle bone."""
    frames, poses = make_lanes(
        12,
        [
            (100, 140, 8.0, set(range(6))),
            (100, 160, 8.0, {6}),
            (142, 180, 8.0, set(range(7, 12))),
            (40, 150, 4.0, {7}),
            (20, 70, 6.0, {8, 9, 10, 11}),
        ],
    )
    on = both_solvers(frames, poses).chosen
    off = both_solvers(frames, poses, RejectionParams(one_lane=False)).chosen
    np.testing.assert_array_equal(on, off)
    assert _lanes_of(frames, on)[7:] == [142.0] * 5


def _line_over(lower: np.ndarray) -> list[bool]:
    """``echo_beneath`` of a flat line (working row 100, columns 10-109, 0.16 mm
    pixels) and of a contour ``lower`` under it (rows per column), as
    :func:`candidates._mark_echo_beneath` flags them: bright tissue over the line (1.12
    of the frame's typical), tissue between the two reading 0.83 of it (0.74 of that
    cover), shadow under the lower one, whose grey is 0.9 of the line's."""
    cols = np.arange(10, 110)
    lower = np.rint(lower).astype(np.intp)
    lr = np.zeros((300, 120))
    lr[25:100, cols] = np.log(1.12)
    lr[100, cols] = np.log(3.0)
    for i, r in zip(cols, lower, strict=True):
        lr[101:r, i] = np.log(0.83)
        lr[r, i] = np.log(2.5)
        lr[r + 1 :, i] = np.log(0.4)
    line = {"cols": cols, "rows": np.full(cols.size, 100), "grey": 1.0, "shadow": 0.0}
    under = {"cols": cols, "rows": lower, "grey": 0.9, "shadow": 0.0}
    cands = [line, under]
    _dense_rows(cands)
    ev = types.SimpleNamespace(dx=0.16, dy=0.16, field_top=0)
    _mark_echo_beneath(cands, ev, lr, SegmentationParams().shadowpath)
    return [bool(c.get("beneath")) for c in cands]


def test_a_bone_top_under_a_fascia_is_not_taken_for_a_far_cortex():
    """A dome (a bone's top) under a bright line (a fascia over it), tissue between
    reading 0.83 of the frame's typical tissue and 0.74 of the bright tissue over the
    line, as a radius's interior reads over its far cortex (seed 2 above): the dome is
    judged against the frame's level, is not flagged, and the line over it is (the
    sound went through it). A bowl in its place (the back wall of a convex bone: a far
    cortex) is judged against the tissue over the line and flagged. (This stood on the
    hard radius seed 6 with the ulna 14 mm beside, frame 5, while the simulated fascia
    ran on under the ulna: the "dome" was that fascia, 2.5 mm under the ulna's top in
    its shadow; no radius sweep of seeds 1-36, the ulna 14 or 18 mm beside, shows a
    bone's top the rule keeps unflagged since.)"""
    x = np.arange(10, 110) - 59.5
    dome = 150.0 + 0.004 * x**2  # apex 150, ends 10 rows (1.6 mm) deeper
    bowl = 160.0 - 0.004 * x**2
    assert _line_over(dome) == [True, False]
    assert _line_over(bowl) == [False, True]

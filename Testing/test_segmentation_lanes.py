"""Two bones in view: the track follows the one in the middle of the image
(``track.central_track``, ``RejectionParams.lane_*``)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate, FrameCandidates
from BoneUSRecon.Logic.segmentation.params import RejectionParams, SegmentationParams
from BoneUSRecon.Logic.segmentation.track import select_bone_track
from BoneUSRecon.Logic.segmentation.track_incremental import IncrementalTrack
from BoneUSRecon.Logic.simulation import SimulationParams, simulate
from BoneUSRecon.Logic.simulation.scoring import score_simulation

_S = 0.25  # mm per pixel of the synthetic frames
_W = 200  # their width in pixels (50 mm)


def _lanes(
    n: int, lanes: list[tuple[float, float, float, set[int] | None]], fov: bool = True
) -> tuple[list[FrameCandidates], np.ndarray]:
    """Frames 1.4 mm apart, each with one candidate per lane ``(first column, last
    column, strength, frames it shows in or None for all)``, 8 mm deep."""
    frames, poses = [], []
    for k in range(n):
        cands = []
        for a, b, strength, where in lanes:
            if where is not None and k not in where:
                continue
            i = np.arange(a, b + 1, 2.0)
            pts = np.column_stack([i, np.full(i.size, 8.0 / _S)])
            cands.append(BoneCandidate(pts, np.full(i.size, 200.0), strength, 3.0, 2.0))
        cands.sort(key=lambda c: -c.strength)
        frames.append(
            FrameCandidates(tuple(cands), (_S, _S), fov_px=(0.0, _W - 1.0) if fov else None)
        )
        m = np.eye(4)
        m[0, 0] = m[1, 1] = _S
        m[2, 3] = 1.4 * k
        poses.append(m)
    return frames, np.stack(poses)


def _lane_of(frames: list[FrameCandidates], chosen: np.ndarray) -> set[float]:
    """First columns of the chosen candidates."""
    return {float(frames[k].candidates[c].points_px[0, 0]) for k, c in enumerate(chosen) if c >= 0}


def _both(frames, poses, params=RejectionParams()):  # noqa: B008 (frozen dataclass)
    """The batch choice, checked equal to the incremental one."""
    batch = select_bone_track(frames, poses, params)
    track = IncrementalTrack(params)
    for fc, pose in zip(frames, poses, strict=True):
        track.add(fc, pose)
    inc = track.solve()
    np.testing.assert_array_equal(inc.chosen, batch.chosen)
    np.testing.assert_array_equal(inc.confidence, batch.confidence)
    return batch


def test_the_bone_in_the_middle_is_followed_over_a_stronger_one_beside_it():
    # A neighbour toward the left edge (columns 10-60: 0.65 of the half-width off the
    # middle) with 1.5x the evidence of the bone in the middle (columns 80-120).
    frames, poses = _lanes(12, [(10, 60, 12.0, None), (80, 120, 8.0, None)])
    assert _lane_of(frames, _both(frames, poses).chosen) == {80.0}
    # Without the rule the stronger one wins: the rule is what chose.
    off = RejectionParams(lane_offcentre=1.0)
    assert _lane_of(frames, _both(frames, poses, off).chosen) == {10.0}


def test_an_off_centre_bone_stays_when_nothing_else_is_a_bone_track():
    # A look-alike in the middle in 3 of 12 frames (a vessel or a fascia comes and goes).
    frames, poses = _lanes(12, [(10, 60, 12.0, None), (80, 120, 8.0, {3, 4, 5})])
    assert _lane_of(frames, _both(frames, poses).chosen) == {10.0}
    # A track in the middle with too little evidence (a tenth: a fascia).
    frames, poses = _lanes(12, [(10, 60, 12.0, None), (80, 120, 1.0, None)])
    assert _lane_of(frames, _both(frames, poses).chosen) == {10.0}
    # Frames whose field of view is not known: no preference.
    frames, poses = _lanes(12, [(10, 60, 12.0, None), (80, 120, 8.0, None)], fov=False)
    assert _lane_of(frames, _both(frames, poses).chosen) == {10.0}


def test_a_bone_near_the_middle_is_never_second_guessed():
    # The bone at 0.3 of the half-width, a weaker track nearer the middle beside it.
    frames, poses = _lanes(12, [(115, 145, 12.0, None), (85, 105, 8.0, None)])
    assert _lane_of(frames, _both(frames, poses).chosen) == {115.0}


@pytest.mark.parametrize(("realism", "seed"), [("standard", 1), ("hard", 2)])
def test_two_forearm_bones_in_view_the_swept_one_is_segmented(realism, seed):
    """The ulna swept in the middle of a 51 mm image, the radius 18 mm beside it (toward
    the wrist the two come that close): the radius's bigger echo had the track."""
    sim = simulate(
        SimulationParams(
            bone="ulna",
            n_frames=12,
            width=160,
            height=136,
            spacing_mm=0.32,
            realism=realism,
            seed=seed,
            neighbour_mm=18.0,
        )
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

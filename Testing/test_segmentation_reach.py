"""A track contour's level run past its neighbours' reach cut off (issue 10:
:mod:`BoneUSRecon.Logic.segmentation.reach`).

A layer leaving the bone's top at its level (a fascia off the crest) carries a contour
on past the bone where no turn of the contour marks the bone's end; the frames on either
side say how far the bone reaches.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import CADAVER, FLAT_GATE, small_simulation

from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate
from BoneUSRecon.Logic.segmentation.params import RejectionParams
from BoneUSRecon.Logic.segmentation.reach import beyond_reach

SP = (0.1, 0.1)  # mm per pixel


def _cand(x_mm: np.ndarray, z_mm: np.ndarray) -> BoneCandidate:
    pts = np.column_stack([x_mm / SP[0], z_mm / SP[1]])
    return BoneCandidate(pts, np.full(len(pts), 200.0), 10.0, 2.0, 2.0)


def _dome(
    x: np.ndarray, centre: float = 20.0, radius: float = 8.0, top: float = 10.0
) -> np.ndarray:
    return top + radius - np.sqrt(np.clip(radius**2 - (x - centre) ** 2, 0.0, None))


def test_a_level_run_past_the_reach_is_cut_and_the_dome_kept():
    """A dome 12-28 mm whose contour runs on level from its right shoulder to 38 mm: with
    the neighbours reaching 12-28 mm, the run past 30 mm is cut, the dome kept whole."""
    x = np.arange(12.0, 38.0, 0.1)
    z = np.where(x <= 24.0, _dome(x), _dome(np.array([24.0]))[0] + 0.05 * (x - 24.0))
    keep = beyond_reach(_cand(x, z), SP, (12.0, 28.0))
    assert keep is not None
    assert np.all(keep[x <= 30.0 - 1e-6]) and not np.any(keep[x > 30.0 + 1e-6])


@pytest.mark.parametrize(
    ("case", "x_end", "slope"),
    [
        ("a flank followed further down than the neighbours", 36.0, 0.8),
        ("a level run short of beyond_min_mm past the margin", 32.0, 0.0),
    ],
)
def test_what_is_not_cut(case, x_end, slope):
    """Past the neighbours' reach a flank descends: kept; a short level run (a frame that
    sees a broad shoulder a little further than its neighbours): kept."""
    x = np.arange(12.0, x_end, 0.1)
    z = np.where(x <= 26.0, _dome(x), _dome(np.array([26.0]))[0] + slope * (x - 26.0))
    assert beyond_reach(_cand(x, z), SP, (12.0, 28.0)) is None, case


def test_a_fascia_off_the_shoulder_is_cut_from_a_track_frame():
    """Hard ulna at the cadaver's geometry (475 x 405 at 0.108 mm), seed 197 (held out,
    session 35), frame 21: the contour ran from the bone's top on along a fascia leaving
    its right shoulder at its level, 10.6 mm past the frames on either side, 3.6 mm off
    the bone on median. Cut, it lies on the bone; no other frame moves off it. With
    the shadow gate flat from 1 on (as before session 46): rising on to 2 where the
    shadow is deep, the contour there no longer takes the fascia at all."""
    sim = small_simulation(bone="ulna", seed=197, realism="hard", **CADAVER)
    sw = sim.sweep
    base = FLAT_GATE
    on = segment_sweep(sw, base)
    off = segment_sweep(
        sw,
        dataclasses.replace(base, rejection=dataclasses.replace(base.rejection, trim_beyond=False)),
    )

    def median_mm(c) -> float:
        return float(np.median(sim.distance_to_truth(sw.to_reference(c.frame, c.points_px))))

    assert off.contours[21].accepted and median_mm(off.contours[21]) > 3.0
    assert on.contours[21].accepted and median_mm(on.contours[21]) < 0.5
    for a, b in zip(off.contours, on.contours, strict=True):
        if a.accepted and a.frame != 21 and median_mm(a) < 1.0:
            assert b.accepted and median_mm(b) < 1.0


def test_a_climb_past_the_reach_onto_another_top_is_cut_at_the_valley():
    """A dome over 12-28 mm (the neighbours' reach) whose contour runs on over a valley
    at 27.3 mm, up onto a second top at 33 mm (4.7 mm over the valley) and down its far
    flank to 42 mm (as a rim trace follows it): the run past the reach descends (not
    level), yet climbs onto another top first. Cut at the valley's bottom, the dome
    kept whole; with ``beyond_climb_mm`` 0 nothing is cut."""
    x = np.arange(12.0, 42.0, 0.1)
    z = np.minimum(_dome(x), 10.0 + 0.15 * (x - 33.0) ** 2)
    params = RejectionParams()
    keep = beyond_reach(_cand(x, z), SP, (12.0, 28.0), params)
    assert keep is not None
    valley = x[np.argmax(np.where((x > 20.0) & (x < 33.0), z, -np.inf))]  # 27.3 mm
    assert np.all(keep[x <= valley + 1e-6]) and not np.any(keep[x > valley + 1e-6])
    off = dataclasses.replace(params, beyond_climb_mm=0.0)
    assert beyond_reach(_cand(x, z), SP, (12.0, 28.0), off) is None


def test_a_narrow_hop_onto_a_layer_over_the_flank_is_no_other_top():
    """A dome whose flank, followed down past the neighbours' reach (12-28 mm) to 40 mm,
    hops for 0.4 mm onto a layer 1.5 mm over it at 34 mm (a contour switching lines on
    a flank, hard tibia s173 frame 24): no top of another bone, nothing is cut."""
    x = np.arange(12.0, 40.0, 0.1)
    z = np.where(x <= 26.0, _dome(x), _dome(np.array([26.0]))[0] + 0.8 * (x - 26.0))
    z = np.where((x > 33.8) & (x < 34.2), z - 1.5, z)
    assert beyond_reach(_cand(x, z), SP, (12.0, 28.0)) is None


def test_a_contour_over_the_valley_onto_the_bone_beside_is_cut_from_a_track_frame():
    """Hard radius with the ulna 14 mm beside (their tops touch) at the cadaver's
    geometry (475 x 405 at 0.108 mm), seed 173 (session 36), frame 28: the path ran from
    the ulna's top over the valley and along the fascia onto the radius, its rim
    followed the ulna's far flank down; 42 % of its points lay on the ulna (11 mm past
    the frames on either side), none of its pieces cut (the valley's two shadows 0.14
    and 0.36: not a third; its ulna side no dome of its own). Cut at the valley, it lies
    on the radius; no accepted frame keeps points on the ulna."""
    sim = small_simulation(bone="radius", seed=173, realism="hard", neighbour_mm=14.0, **CADAVER)
    sw = sim.sweep
    res = segment_sweep(sw)

    def ulna_share(c) -> float:
        p = sw.to_reference(c.frame, c.points_px)
        return float(np.mean(sim.neighbour.distance(p) < sim.geometry.distance(p)))

    c28 = res.contours[28]
    assert c28.accepted and ulna_share(c28) < 0.05
    assert np.median(sim.distance_to_truth(sw.to_reference(28, c28.points_px))) < 0.2
    assert all(ulna_share(c) < 0.1 for c in res.contours if c.accepted)

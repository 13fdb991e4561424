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
from conftest import CADAVER, small_simulation

from BoneUSRecon.Logic.segmentation import SegmentationParams, segment_sweep
from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate
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
    the bone on median. Cut, it lies on the bone; no other frame moves off it."""
    sim = small_simulation(bone="ulna", seed=197, realism="hard", **CADAVER)
    sw = sim.sweep
    on = segment_sweep(sw)
    base = SegmentationParams()
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

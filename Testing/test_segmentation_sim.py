"""Segmentation against the simulator's ground truth (mm), on the shared small sweeps."""

from __future__ import annotations

import numpy as np
import pytest

from BoneUSRecon.Logic.segmentation import SegmentationParams, segment_sweep


@pytest.fixture(scope="module")
def shadowpath_clean(sim_small):
    return segment_sweep(sim_small.sweep)


@pytest.fixture(scope="module")
def shadowpath_corrupted(sim_small_corrupted):
    return segment_sweep(sim_small_corrupted.sweep)


def distances(result, sim):
    return sim.distance_to_truth(result.points_mm(sim.sweep).xyz)


def test_shadowpath_accuracy_mm(shadowpath_clean, sim_small):
    d = distances(shadowpath_clean, sim_small)
    assert np.median(d) <= 0.15
    assert np.percentile(d, 95) <= 0.5
    assert np.mean(d > 2.0) < 0.01
    # It covers the bone: nearly every frame kept, most of each visible contour found.
    assert len(shadowpath_clean.accepted) >= 0.9 * sim_small.sweep.n_frames
    cover = []
    for c in shadowpath_clean.accepted:
        t = sim_small.true_contours_px[c.frame]
        if len(t) > 1:
            cover.append(np.ptp(c.points_px[:, 0]) / np.ptp(t[:, 0]))
    assert np.median(cover) > 0.8


def test_shadowpath_matches_true_contour_in_pixels(shadowpath_clean, sim_small):
    """Sub-pixel: the depth error along the true contour is a fraction of a pixel."""
    errs = []
    for c in shadowpath_clean.accepted:
        t = sim_small.true_contours_px[c.frame]
        if len(t) < 2:
            continue
        inside = (c.points_px[:, 0] >= t[0, 0]) & (c.points_px[:, 0] <= t[-1, 0])
        errs.append(c.points_px[inside, 1] - np.interp(c.points_px[inside, 0], t[:, 0], t[:, 1]))
    e = np.abs(np.concatenate(errs))
    assert np.median(e) < 0.3  # pixels (0.3 mm each)


def test_corrupted_frames_never_reach_the_fit(shadowpath_corrupted, sim_small_corrupted):
    sim = sim_small_corrupted
    r = shadowpath_corrupted
    d = distances(r, sim)
    # Whatever was kept is on the bone.
    assert np.percentile(d, 95) <= 0.5
    assert np.mean(d > 2.0) < 0.01
    # Frames without bone (probe lifted) are always rejected, with a reason.
    for f, kind in sim.corruption_kinds.items():
        if kind == "contact_loss":
            assert f in r.rejected and r.rejected[f]
    # A kept corrupted frame must be on the bone (e.g. the bone under a false echo).
    for c in r.accepted:
        if c.frame in sim.corruption_kinds:
            dc = sim.distance_to_truth(c.points_mm(sim.sweep))
            assert np.median(dc) < 0.5, (c.frame, sim.corruption_kinds[c.frame])
    # Clean frames are almost all kept.
    clean = set(range(sim.sweep.n_frames)) - set(sim.corruption_kinds)
    assert len(clean & set(r.rejected)) <= 1


def test_paper_snake_on_the_simulator(sim_small):
    r = segment_sweep(sim_small.sweep, SegmentationParams(method="snake"))
    d = distances(r, sim_small)
    # The paper's method is less accurate than the default but finds the bone. Since
    # the simulator's shadow is grey with reverberation copies of the bone echo
    # (simulator version 2, as on real recordings), the snake rising from below is
    # caught by them unless restarted above a contour with shadow on both sides: it
    # kept 6/40 frames without the restarts, 27/40 with them.
    assert np.median(d) <= 0.5
    assert np.mean(d > 2.0) < 0.05
    assert len(r.accepted) >= 0.5 * sim_small.sweep.n_frames
    assert max(c.extras["restarts"] for c in r.contours) >= 1
    iters = [c.extras["iterations"] for c in r.contours]
    assert max(iters) <= 300


def test_black_margins_are_outside_the_field_of_view(sim_factory):
    """Scan-converted frames: black columns beside the image; no contour point there."""
    sim = sim_factory(seed=4, black_margin_px=30)
    m, w = 30, sim.sweep.width
    assert not np.asarray(sim.sweep.frames)[:, :, :m].any()
    assert all(((c[:, 0] >= m) & (c[:, 0] < w - m)).all() for c in sim.true_contours_px)
    r = segment_sweep(sim.sweep)
    assert len(r.accepted) >= 0.9 * sim.sweep.n_frames
    for c in r.accepted:
        # Not in the margin, nor within the 0.5 mm next to it.
        assert c.points_px[:, 0].min() >= m and c.points_px[:, 0].max() <= w - 1 - m
    d = distances(r, sim)
    assert np.median(d) <= 0.15 and np.percentile(d, 95) <= 0.5 and np.mean(d > 2.0) < 0.01


# -- issue 10: the real-data conditions, one at a time and together ------------------
def _hard(sim_factory, conditions, bone="radius"):
    from BoneUSRecon.Logic.simulation.scoring import score_simulation

    sim = sim_factory(bone=bone, seed=0, realism="hard", hard_conditions=tuple(conditions))
    return score_simulation(segment_sweep(sim.sweep), sim).summary()


@pytest.mark.parametrize("condition", ["skin_gap", "fascia", "vessel", "crest", "depth_ramp"])
def test_look_alikes_are_not_taken_for_bone(sim_factory, condition):
    """Skin over a no-contact gap with reverberation copies, fascia off the bone, a vessel
    with ring-down, a crest-shaped bone, a bone rising from 25 to 5 mm: each alone keeps
    nearly every frame on the bone and none on the look-alike (measured on radius and
    clavicle: recall 0.85-1.00, wrong 0)."""
    s = _hard(sim_factory, [condition])
    assert s["recall"] >= 0.8
    assert s["wrong_share"] <= 0.02
    assert s["median_mm"] <= 0.1
    if condition == "crest":
        # Down the flanks: the steepest slope reached is the true contour's.
        assert s["steepest_deg"] >= s["true_steepest_deg"] - 5.0


def test_all_real_data_conditions_together(sim_factory):
    """Echo 1.34x the tissue above, grey shadow, crest, fascia, skin gap, vessel, depth
    ramp at once: no frame on a wrong structure, nearly all on the bone (measured 0.93
    on this small clavicle sweep since the reverberation series and first-reflector
    rules, 0.62 before them; the segmenter before issue 10 found no bone at all)."""
    s = _hard(
        sim_factory,
        ["low_contrast", "grey_shadow", "crest", "fascia", "skin_gap", "vessel", "depth_ramp"],
        bone="clavicle",
    )
    assert s["wrong_share"] <= 0.02
    assert s["recall"] >= 0.85
    assert s["median_mm"] <= 0.3

"""End to end on small simulated sweeps: accuracy in mm against the simulator's truth."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import CADAVER, replayed
from vtkmodules.util import numpy_support

from BoneUSRecon.Logic.bspline import FitParams
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.pipeline import (
    Reconstruction,
    ReconstructionParams,
    control_point_table,
    params_with,
    reconstruct,
    reconstruction_from_segmentation,
    surface_from_contours,
)
from BoneUSRecon.Logic.surface import surface_area, triangle_centroids
from BoneUSRecon.Logic.sweep import pixels_to_reference


def area_within(sim, surface, tol):
    c, a = triangle_centroids(surface)
    return float((a * (sim.distance_to_truth(c) <= tol)).sum() / a.sum())


@pytest.fixture(scope="module")
def recon_small(sim_small) -> Reconstruction:
    return reconstruct(sim_small.sweep)


@pytest.fixture(scope="module")
def recon_corrupted(sim_small_corrupted) -> Reconstruction:
    return reconstruct(sim_small_corrupted.sweep)


def test_clean_sweep_accuracy_in_mm(sim_small, recon_small):
    r = recon_small
    ev = evaluate_surface(r.surface, sim_small.gold)
    # gold carries 0.2 mm noise (mean ~0.16 mm): the surface adds little to it
    assert ev.mean < 0.25
    assert ev.p95 < 0.65
    assert ev.within_1 > 0.97
    # the surface itself stays on the true bone: 0.975 of its area within 0.35 mm at the
    # default 15 x 6 control points, 0.992 at the paper's 15 x 5 (the sixth control
    # point across follows the left flank's edge, 46-61 degrees from up, where few
    # frames' contours reach, less smoothly; over 28 standard sweeps 0.993 -> 0.990, over
    # 60 hard ones 0.904 -> 0.933: Testing/benchmarks/README.md, session 30)
    assert area_within(sim_small, r.surface, 0.35) > 0.97
    c, _ = triangle_centroids(r.surface)
    # 99th percentile of the triangles' distance to the bone, seeds 0-3: 0.42, 0.34,
    # 0.36, 0.26 mm (with the rim's former max_deg 80 / max_step_mm 0.1: 0.28, 0.47,
    # 0.46, 0.50; this sweep is seed 0): the surface's edge where the flanks end. On
    # seed 0 the short shoulder cut (branch fascia) takes a layer 1-3.4 mm off the bone
    # out of frame 15 together with the flank beyond its turn (0.32 mm without it). At the
    # default 15 x 6 control points (session 30) 0.80 mm on seed 0 (0.39 at 15 x 5): that
    # left flank's edge (above); seeds 1-5: 0.54, 0.34, 0.40, 0.80, 0.31. At the default
    # 24 rays (session 40) seeds 0-5: 0.99, 0.39, 0.28, 0.36, 0.44, 0.20 (15 rays: 0.60,
    # 0.53, 0.34, 0.40, 0.79, 0.31): seed 0's far triangles (1.6 % of the area, 0.8 % at
    # 15 rays) lie on its left flank, rays -64 to -50 degrees in frames 22-28, where the
    # finer rays sample more of its contours' off-bone flank ends; every other seed's
    # edge comes closer (88 harness sweeps: area-weighted p99 0.94 -> 0.80 mm).
    assert np.percentile(sim_small.distance_to_truth(c), 99) < 1.1


def test_summary_timings_and_arrays(sim_small, recon_small):
    r = recon_small
    s = r.summary
    assert s["frames"] == 40 and s["segmented_frames"] + s["rejected_frames"] == 40
    assert s["grid_shape"] == [r.grid.shape[0], 24]
    assert 0.6 < s["grid_coverage"] <= 1.0
    assert 0 < s["mean_resampling_distance_mm"] < 0.15  # paper: 0.14 mm
    assert 0 < s["fit_rms_mm"] < 0.2
    assert s["surface_triangles"] == r.surface.GetNumberOfCells() > 100
    assert set(r.timings) >= {"segment", "resample", "fit", "surface", "total"}
    pd = r.surface.GetPointData()
    assert pd.GetScalars().GetName() == "Distance"
    assert pd.GetNormals() is not None and pd.GetTCoords() is not None
    # segmented points carry the segmentation's arrays
    assert r.points.GetNumberOfPoints() == r.segmentation.n_points
    assert r.points.GetPointData().GetArray("Frame") is not None


def test_corrupted_frames_do_not_bend_the_surface(sim_small_corrupted, recon_corrupted):
    sim, r = sim_small_corrupted, recon_corrupted
    ev = evaluate_surface(r.surface, sim.gold)
    assert ev.mean < 0.27 and ev.p95 < 0.7 and ev.within_1 > 0.96
    assert area_within(sim, r.surface, 0.35) > 0.95
    # every corrupted frame whose contour is far from the truth was rejected somewhere
    fit_rejected = set(r.summary["fit_rejected_frames"])
    for c in r.segmentation.accepted:
        d = sim.distance_to_truth(c.points_mm(sim.sweep))
        if np.median(d) > 1.0:
            assert c.frame in fit_rejected


def test_plain_least_squares_is_worse_with_false_contours(sim_small, recon_small):
    # Inject false contours (5 mm too deep) into 10% of the true contours: the paper's
    # plain least squares bends, the robust fit does not.
    sw = sim_small.sweep
    cont = [
        (k, pixels_to_reference(sw.image_to_reference[k], c))
        for k, c in enumerate(sim_small.true_contours_px)
        if len(c) >= 2
    ]
    bad = {k for k, _ in cont[5::10]}
    down = -sw.image_to_reference[0, :3, 1] / np.linalg.norm(sw.image_to_reference[0, :3, 1])
    fake = [(k, p - 5.0 * down if k in bad else p) for k, p in cont]
    params = ReconstructionParams()
    plain = dataclasses.replace(params, fit=FitParams(robust="none"))
    _, fit_r, surf_r = surface_from_contours(fake, sw, params)
    _, _, surf_p = surface_from_contours(fake, sw, plain)
    assert area_within(sim_small, surf_r, 0.35) > 0.97
    assert area_within(sim_small, surf_p, 0.35) < area_within(sim_small, surf_r, 0.35) - 0.1
    assert (fit_r.frame_weights == 0).sum() >= len(bad) - 1


def test_reversed_sweep_equally_accurate(sim_factory):
    sim = sim_factory(seed=0, reverse=True)
    r = reconstruct(sim.sweep)
    ev = evaluate_surface(r.surface, sim.gold)
    assert ev.mean < 0.25 and ev.within_1 > 0.97


@pytest.mark.parametrize("where", ["start", "middle"])
def test_a_probe_held_still_is_reconstructed_as_well(sim_small, recon_small, where):
    # A PLUS recording often starts (or pauses) with the probe at rest: frames at one
    # pose. Ten of them put two knots on the clamped end knot and the fit's system was
    # singular (an internal error); they are one position for the knots now.
    n = sim_small.sweep.n_frames
    frames = (
        np.r_[[0] * 10, np.arange(n)]
        if where == "start"
        else np.r_[np.arange(20), [20] * 10, np.arange(21, n)]
    )
    r = reconstruct(replayed(sim_small.sweep, frames))
    ev = evaluate_surface(r.surface, sim_small.gold)
    plain = evaluate_surface(recon_small.surface, sim_small.gold)
    assert r.fit.n_control_points == recon_small.fit.n_control_points
    assert ev.mean < plain.mean + 0.03 and ev.within_1 > 0.97


@pytest.mark.parametrize("bone", ["clavicle", "tibia"])
def test_a_sweep_there_and_back_gives_the_surface_of_one_pass(sim_factory, bone):
    # The two passes' slices interleave along the bone in pairs at one position. The
    # slice spacing was the median step along the bone (the pairs' ~0: every step of
    # one pass a hole) and the edge filter's neighbours were the twins (it filtered
    # nothing): a hard tibia lost a quarter of its area, 0.24 -> 0.53 mm. Measured as
    # the probe moves (frame to frame) and beyond the twins, it is one pass's surface.
    sim = sim_factory(bone=bone, realism="hard", seed=3)
    n = sim.sweep.n_frames
    one = reconstruct(sim.sweep)
    both = reconstruct(replayed(sim.sweep, np.r_[np.arange(n), np.arange(n - 1)[::-1]]))
    a1, a2 = surface_area(one.surface), surface_area(both.surface)
    g1 = evaluate_surface(one.surface, sim.gold).mean
    g2 = evaluate_surface(both.surface, sim.gold).mean
    assert abs(a2 / a1 - 1) < 0.015
    assert g2 < g1 + 0.03


def tracked_at_rest(params: ReconstructionParams) -> ReconstructionParams:
    """``params`` with frames at rest tracked and fitted as any (``at_rest_mm`` 0)."""
    seg = params.segmentation
    rej = dataclasses.replace(seg.rejection, at_rest_mm=0.0)
    return dataclasses.replace(params, segmentation=dataclasses.replace(seg, rejection=rej))


def test_a_short_sweep_held_still_counts_its_positions_not_its_frames(sim_small):
    # Twelve frames of which nine at one pose, all tracked and fitted (at_rest_mm 0, as
    # with a tracker jittering more than it): three or four positions along the bone
    # (as the track keeps the far frames), so three control points along, not six
    # (half of twelve "slices"); four are refused, naming the positions.
    frames = np.r_[[0] * 9, 10, 20, 30]
    sweep = replayed(sim_small.sweep, frames)
    r = reconstruct(sweep, tracked_at_rest(ReconstructionParams()))
    assert r.fit.n_control_points[0] == 3
    with pytest.raises(BoneUSReconError, match=r"slices at [34] positions x"):
        reconstruct(sweep, tracked_at_rest(params_with(n_control_points=(4, 6))))


def test_frames_at_rest_stand_for_one_and_do_not_weigh_the_track(sim_factory):
    # A hard ulna held 2 s (60 frames, 0.05 mm of tracker jitter) at the end of its
    # sweep: tracked frame by frame (at_rest_mm 0), the held frame's candidates weigh
    # sixty times and carry the whole track onto a look-alike (gold 15.4 mm against
    # 0.248). Taken at rest, they stand for one frame: the sweep's own track and
    # surface, point for point, and each held frame has its contour.
    sim = sim_factory(bone="ulna", realism="hard", seed=241, **CADAVER)
    n = sim.sweep.n_frames
    idx = np.r_[np.arange(n), [n - 1] * 60]
    poses = sim.sweep.image_to_reference[idx].copy()
    poses[n:, :3, 3] += np.random.default_rng(0).normal(0, 0.05, (60, 3))
    sweep = replayed(sim.sweep, idx, poses)
    plain, rest = reconstruct(sim.sweep), reconstruct(sweep)
    still = [c for c in rest.segmentation.contours if "at_rest_of" in c.extras]
    assert len(still) >= 50 and all(c.extras["at_rest_of"] == n - 1 for c in still)
    kept = {c.frame: c for c in plain.segmentation.contours}[n - 1]
    assert all(np.array_equal(c.points_px, kept.points_px) for c in still)
    a = numpy_support.vtk_to_numpy(plain.surface.GetPoints().GetData())
    b = numpy_support.vtk_to_numpy(rest.surface.GetPoints().GetData())
    assert a.shape == b.shape and np.allclose(a, b)


def test_table_one_decreases_then_flattens(sim_small, recon_small):
    rows = control_point_table(recon_small, sim_small.gold, (5, 10, 15))
    assert [e for e, _ in rows] == [5, 10, 15]
    d = dict(rows)
    assert d[5] > d[15]  # 5 control points cannot follow the S-shaped clavicle
    assert d[15] < 0.25
    # same fit as the reconstruction for the default count
    assert d[15] == pytest.approx(evaluate_surface(recon_small.surface, sim_small.gold).mean)


def test_progress_reports_every_stage(sim_small):
    seen = []
    reconstruct(sim_small.sweep, progress=lambda s, d, t: seen.append(s))
    assert {"segment", "resample", "fit", "surface"} <= set(seen)


def test_blank_sweep_refused_with_file_name(sim_small, tmp_path):
    sw = sim_small.sweep.replace(
        frames=np.zeros_like(sim_small.sweep.frames), source=tmp_path / "blank.mha"
    )
    with pytest.raises(BoneUSReconError, match="blank.mha"):
        reconstruct(sw)


def test_more_control_points_than_slices_refused(sim_small, recon_small):
    params = params_with(n_control_points=(60, 5))  # asked for: fitted as asked or refused
    assert not params.fit.fewer_if_short
    with pytest.raises(BoneUSReconError, match="too few valid grid points for 60 x 5"):
        surface_from_contours(
            recon_small.segmentation.contours_mm(sim_small.sweep), sim_small.sweep, params
        )


def test_a_short_sweep_gets_fewer_control_points_and_says_so(sim_small, recon_small):
    # Ten slices cannot carry the default 15 control points along: five are fitted, the
    # summary says so, and the surface lies on the bone between the slices kept.
    kept = [c for c in recon_small.segmentation.contours if c.accepted][5:15]
    seg = dataclasses.replace(recon_small.segmentation, contours=tuple(kept))
    recon = reconstruction_from_segmentation(sim_small.sweep, seg)
    assert recon.summary["control_points"] == [5, 6]
    assert any("not 15 x 6" in w for w in recon.summary["warnings"])
    c, _ = triangle_centroids(recon.surface)
    assert np.percentile(sim_small.distance_to_truth(c), 95) < 0.35
    # The default count passed explicitly (as the Slicer module does) is the same ceiling.
    same = params_with(n_control_points=(15, 6))
    assert same.fit.fewer_if_short
    assert reconstruction_from_segmentation(sim_small.sweep, seg, same).summary[
        "control_points"
    ] == [5, 6]


def test_distance_texture_matches_segmented_points(recon_small):
    from scipy.spatial import cKDTree

    r = recon_small
    pts = numpy_support.vtk_to_numpy(r.surface.GetPoints().GetData())
    seg = r.segmentation.points_mm(r.sweep).xyz
    dist = numpy_support.vtk_to_numpy(r.surface.GetPointData().GetArray("Distance"))
    assert np.allclose(dist, cKDTree(seg).query(pts)[0])

"""Flank extension of the model mesh (SurfaceParams.flank_extension_mm): the strips past
the data's side edges follow a convex bone, stop at the steepest slope, and bring the
surface to gold points the contours did not reach."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import FLAT_BARE
from test_resampling import RADIUS, axis_point, tube_sweep
from vtkmodules.util import numpy_support

from BoneUSRecon.Logic.bspline import FitParams, fit_surface
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.pipeline import ReconstructionParams, reconstruct
from BoneUSRecon.Logic.resampling import ResamplingParams, resample
from BoneUSRecon.Logic.segmentation import SegmentationParams
from BoneUSRecon.Logic.simulation import SimulationParams, simulate
from BoneUSRecon.Logic.simulation.core import sample_gold
from BoneUSRecon.Logic.surface import SurfaceParams, surface_polydata

ARC_DEG = 40.0  # the contours reach 40 degrees down each side of the tube's top


def _points(pd):
    return numpy_support.vtk_to_numpy(pd.GetPoints().GetData())


def _extrapolated(pd):
    return numpy_support.vtk_to_numpy(pd.GetPointData().GetArray("Extrapolated")).astype(bool)


def _slope_deg(pts):
    """Angle of each point on the tube from its top (= the surface's slope, degrees)."""
    rel = pts - axis_point(pts[:, 0])
    return np.degrees(np.arctan2(np.abs(rel[:, 1]), rel[:, 2]))


@pytest.fixture(scope="module")
def tube_top():
    """The tube of test_resampling seen only over its top +-40 degrees (planes x = const)."""
    sweep, contours, _ = tube_sweep(m=40, tilt_deg=0.0)
    cut = [(k, p[_slope_deg(p) <= ARC_DEG]) for k, p in contours]
    grid = resample(cut, sweep)
    fit = fit_surface(grid.points, FitParams(), u=grid.axis_position, v=grid.angles)
    return grid, fit, np.concatenate([p for _, p in cut])


def test_off_by_default_and_no_array(tube_top):
    grid, fit, seg = tube_top
    pd = surface_polydata(fit, grid, seg)
    assert pd.GetPointData().GetArray("Extrapolated") is None
    assert _slope_deg(_points(pd)).max() < ARC_DEG + 1.0


def test_strips_follow_the_tube_down_its_flanks(tube_top):
    grid, fit, seg = tube_top
    pd = surface_polydata(fit, grid, seg, SurfaceParams(flank_extension_mm=2.0))
    pts, ext = _points(pd), _extrapolated(pd)
    assert ext.any() and not ext.all()
    r = np.linalg.norm(pts - axis_point(pts[:, 0]), axis=1)
    # A circle continued along its own curvature: on the 6 mm tube within 0.1 mm.
    assert np.abs(r[ext] - RADIUS).max() < 0.1
    # 2 mm of arc past +-40 degrees on a 6 mm radius: to ~59 degrees on both sides.
    reach = np.degrees(2.0 / RADIUS)
    side = np.sign((pts - axis_point(pts[:, 0]))[:, 1])
    for s in (-1, 1):
        top = _slope_deg(pts[ext & (side == s)]).max()
        assert ARC_DEG + reach - 2.0 < top < ARC_DEG + reach + 1.0
    # The "Distance" array (to the nearest data point) grows to the strip's length.
    dist = numpy_support.vtk_to_numpy(pd.GetPointData().GetArray("Distance"))
    assert 1.5 < dist[ext].max() < 2.2


def test_strips_stop_at_the_steepest_slope(tube_top):
    grid, fit, seg = tube_top
    for max_deg in (50.0, 70.0):
        pd = surface_polydata(
            fit, grid, seg, SurfaceParams(flank_extension_mm=10.0, flank_max_deg=max_deg)
        )
        pts, ext = _points(pd), _extrapolated(pd)
        slope = _slope_deg(pts[ext])
        # One 0.25 mm step past the limit at most (2.4 degrees on this tube).
        assert max_deg - 3.0 < slope.max() < max_deg + 3.0


def test_no_strip_where_the_edge_rises_outward():
    """A bowl (concave seen from the probe, e.g. the far cortex) is not extended."""
    sweep, contours, _ = tube_sweep(m=30, tilt_deg=0.0)
    bowl = []
    for k, p in contours:
        c = axis_point(p[:, 0])
        q = p.copy()
        q[:, 2] = 2 * c[:, 2] - p[:, 2] + 2 * RADIUS  # mirrored: the arc opens upward
        bowl.append((k, q[_slope_deg(p) <= ARC_DEG]))
    grid = resample(bowl, sweep)
    fit = fit_surface(grid.points, FitParams(), u=grid.axis_position, v=grid.angles)
    pd = surface_polydata(fit, grid, None, SurfaceParams(flank_extension_mm=2.0))
    assert not _extrapolated(pd).any()


@pytest.mark.parametrize(
    "field, value",
    [
        ("flank_extension_mm", -1.0),
        ("flank_max_deg", 90.0),
        ("flank_max_deg", 0.0),
        ("min_frame_weight", 1.0),
        ("min_frame_weight", -0.1),
    ],
)
def test_bad_parameters_refused(field, value):
    with pytest.raises(BoneUSReconError, match=field):
        SurfaceParams(**{field: value})


def test_hard_sweep_gold_nearer_with_the_strips():
    """Hard simulated humerus (0.3 mm, 24 frames): the contours stop short of the flanks
    (echo faded); 1 mm of strip brings the surface nearer to the gold points; the strip's
    distance to the true bone (the simulator's analytic surface) is bounded."""
    sim = simulate(
        SimulationParams(
            bone="humerus",
            seed=5,
            realism="hard",
            n_frames=24,
            width=160,
            height=128,
            spacing_mm=0.3,
        )
    )
    # The strips measured on contours as they stopped before settle.py and rim.py: with
    # them this sweep's contours reach further down its flanks, some past the bone, and
    # the strip 0.7-1 mm out is 2.25 mm off the bone on median (at its seam 0.23 mm): the
    # extension stays opt-in (Testing/benchmarks/README.md, branch onset). And with the
    # shadow gate flat from 1 on, as when they were measured: rising on to 2 where the
    # shadow is deep (session 46) these contours end elsewhere on the flanks and the
    # strip's seam lies 0.92 mm off the bone.
    bare = FLAT_BARE
    # The strips' bounds below were measured on the paper's 15 x 5 control points: they
    # continue the surface's edge, and at the default 15 x 6 this sweep's edge bends
    # more (seam 0.37 mm, 0.7-1 mm out 1.48 mm; gold 0.757 -> 0.789 mm without strips):
    # Testing/benchmarks/README.md, session 30. And on the paper's 15 rays: at the
    # default 24 the edge reaches this sweep's sparse flank ends and the seam lies farther
    # off the bone (session 40).
    rec = reconstruct(
        sim.sweep,
        ReconstructionParams(
            segmentation=SegmentationParams(shadowpath=bare),
            fit=FitParams(n_control_points=(15, 5)),
            resampling=ResamplingParams(n_rays=15),
        ),
    )
    seg = rec.segmentation.points_mm(sim.sweep).xyz
    params = dataclasses.replace(rec.params.surface, flank_extension_mm=1.0)
    ext = surface_polydata(rec.fit, rec.grid, seg, params)
    # Gold on the whole upper bone, the faded flanks too (sim.gold holds only the bone
    # some frame shows, since session 41): what the strips reach for.
    gold = sample_gold(sim, faded=True)
    before = evaluate_surface(rec.surface, gold)
    after = evaluate_surface(ext, gold)
    assert after.mean < before.mean - 0.03
    assert after.within_1 > before.within_1
    # Measured here: on the bone at its seam (0.06 mm median), 1.05 mm off 0.7-1 mm
    # out: the extrapolation is not accurate on hard sweeps (why it is off by default;
    # Testing/benchmarks/README.md, branch recon). Bound it so a worse one fails.
    pts, flag = _points(ext), _extrapolated(ext)
    reach = numpy_support.vtk_to_numpy(ext.GetPointData().GetArray("Distance"))
    d = sim.geometry.distance(pts)
    seam = np.median(d[flag & (reach < 0.3)])
    far = np.median(d[flag & (reach > 0.7)])
    print(f"strip off the bone: {seam:.2f} mm at its seam, {far:.2f} mm at 0.7-1 mm out")
    assert seam < 0.3 and far < 1.3

"""The model mesh: geometry against an analytic tube, arrays, trimming, atomic writers."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.spatial import cKDTree
from test_resampling import RADIUS, axis_point, tube_sweep
from vtkmodules.util import numpy_support

from BoneUSRecon.Logic.bspline import FitParams, fit_surface
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.resampling import ResamplingParams, resample
from BoneUSRecon.Logic.surface import SurfaceParams, surface_area, surface_polydata
from BoneUSRecon.Logic.vtkio import read_polydata, write_polydata


def arr(pd, name):
    return numpy_support.vtk_to_numpy(pd.GetPointData().GetArray(name))


@pytest.fixture(scope="module")
def tube():
    sweep, contours, _ = tube_sweep(m=40, tilt_deg=0.0)  # planes x = const: exact circles
    grid = resample(contours, sweep, ResamplingParams(angle_span_deg=120, angle_centre_deg=0))
    fit = fit_surface(grid.points, FitParams(), u=grid.axis_position, v=grid.angles)
    seg = np.concatenate([p for _, p in contours])
    return sweep, contours, grid, fit, seg


def test_mesh_lies_on_the_tube_with_outward_normals(tube):
    _, _, grid, fit, seg = tube
    pd = surface_polydata(fit, grid, seg)
    pts = numpy_support.vtk_to_numpy(pd.GetPoints().GetData())
    c = axis_point(pts[:, 0])
    radial = pts - c
    r = np.linalg.norm(radial, axis=1)
    # 15 x 5 quadratic spline vs a bent tube of radius 6 mm: within 0.05 mm
    assert np.abs(r - RADIUS).max() < 0.05
    normals = arr(pd, "Normals")
    assert np.einsum("kd,kd->k", normals, radial / r[:, None]).min() > 0.98
    # covers the 120 deg x 60 mm that the rays saw: area ~ 6 * 2.094 * 60 mm^2
    assert surface_area(pd) == pytest.approx(RADIUS * np.deg2rad(120) * 60.0, rel=0.03)


def test_arrays_tcoords_and_distance(tube):
    _, _, grid, fit, seg = tube
    pd = surface_polydata(fit, grid, seg)
    pts = numpy_support.vtk_to_numpy(pd.GetPoints().GetData())
    tc = numpy_support.vtk_to_numpy(pd.GetPointData().GetTCoords())
    assert tc.shape == (pts.shape[0], 2) and tc.min() >= 0 and tc.max() <= 1
    # TCoords are float32 (VTK convention): 6e-8 in u is ~4e-6 mm on a 60 mm bone
    assert np.allclose(fit.surface.evaluate_points(tc[:, 0], tc[:, 1]), pts, atol=1e-4)
    d = arr(pd, "Distance")
    assert pd.GetPointData().GetScalars().GetName() == "Distance"
    assert np.allclose(d, cKDTree(seg).query(pts)[0])
    # at most half the 1.54 mm slice spacing from a segmented point
    assert 0.6 < d.max() < 60 / 39 / 2 + 0.05


def test_trimmed_to_where_there_was_data():
    sweep, contours, _ = tube_sweep(m=40, tilt_deg=0.0)
    # the lateral half (+y side) missing in frames 15..24
    cut = [(k, p[p[:, 1] < axis_point(p[:1, 0])[0, 1]] if 15 <= k < 25 else p) for k, p in contours]
    grid = resample(cut, sweep, ResamplingParams(angle_span_deg=120, angle_centre_deg=0))
    fit = fit_surface(grid.points, FitParams(), u=grid.axis_position, v=grid.angles)
    pd = surface_polydata(fit, grid)
    pts = numpy_support.vtk_to_numpy(pd.GetPoints().GetData())
    rel_y = pts[:, 1] - axis_point(pts[:, 0])[:, 1]
    # frames 15..24 lie at x = 23.1..36.9 mm; the edge is smoothed over the 3 mm window
    hole = (pts[:, 0] > 25.0) & (pts[:, 0] < 35.0) & (rel_y > 1.5)
    assert not hole.any()
    # the hole is ~9-10 slice gaps x half the 120 deg arc: ~95 mm^2 of the 754 mm^2
    full_area = RADIUS * np.deg2rad(120) * 60.0
    assert 0.83 * full_area < surface_area(pd) < 0.9 * full_area
    # max_distance_mm trims too; and nothing left is an error
    near = surface_polydata(fit, grid, params=SurfaceParams(max_distance_mm=0.6))
    # cut along triangle edges where the (non-linear) distance crosses 0.6 mm
    assert arr(near, "Distance").max() <= 0.6 + SurfaceParams().step_mm
    assert surface_area(near) < 0.8 * surface_area(pd)
    with pytest.raises(BoneUSReconError, match="no part"):
        surface_polydata(fit, grid, params=SurfaceParams(max_distance_mm=1e-6))


@pytest.mark.parametrize("ext", [".vtp", ".vtk", ".stl", ".ply", ".obj"])
def test_written_by_extension(tube, tmp_path, ext):
    _, _, grid, fit, seg = tube
    pd = surface_polydata(fit, grid, seg)
    out = write_polydata(pd, tmp_path / f"bone{ext}")
    assert out.stat().st_size > 0
    assert [p.name for p in tmp_path.iterdir()] == [f"bone{ext}"]  # no temp files left
    if ext in (".vtp", ".vtk"):
        back = read_polydata(out)
        assert back.GetNumberOfCells() == pd.GetNumberOfCells()
        assert np.allclose(arr(back, "Distance"), arr(pd, "Distance"))


def test_unknown_extension_refused_and_nothing_written(tube, tmp_path):
    _, _, grid, fit, seg = tube
    pd = surface_polydata(fit, grid, seg)
    with pytest.raises(BoneUSReconError, match="unknown output extension"):
        write_polydata(pd, tmp_path / "bone.xyz")
    assert list(tmp_path.iterdir()) == []


def test_bad_surface_params_refused():
    with pytest.raises(BoneUSReconError):
        SurfaceParams(step_mm=0)
    for bad in ({"support_window_mm": -1}, {"gap_factor": 0}, {"max_distance_mm": 0}):
        with pytest.raises(BoneUSReconError, match=next(iter(bad))):
            SurfaceParams(**bad)


def test_long_gaps_between_slices_are_not_bridged():
    sweep, contours, _ = tube_sweep(m=40, tilt_deg=0.0)
    kept = [c for c in contours if not 15 <= c[0] < 25]  # 10 slices missing: 17 mm gap
    grid = resample(kept, sweep, ResamplingParams(angle_span_deg=120, angle_centre_deg=0))
    fit = fit_surface(grid.points, FitParams(), u=grid.axis_position, v=grid.angles)
    holed = surface_polydata(fit, grid)
    bridged = surface_polydata(fit, grid, params=SurfaceParams(gap_factor=None))
    x_h = numpy_support.vtk_to_numpy(holed.GetPoints().GetData())[:, 0]
    x_b = numpy_support.vtk_to_numpy(bridged.GetPoints().GetData())[:, 0]
    assert not ((x_h > 28) & (x_h < 32)).any()  # mid-gap: > 3 slice spacings from data
    assert ((x_b > 28) & (x_b < 32)).any()
    # bridging is still accurate on a smooth tube (the spline spans the gap)
    assert surface_area(bridged) > surface_area(holed) * 1.1

"""Gold-to-surface distances: exact point-to-triangle distances on meshes with known geometry."""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.vtkCommonDataModel import vtkPolyData
from vtkmodules.vtkFiltersCore import vtkTriangleFilter
from vtkmodules.vtkFiltersSources import vtkPlaneSource, vtkSphereSource

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface, point_to_surface_distances


def square(size=10.0, res=4) -> vtkPolyData:
    ps = vtkPlaneSource()
    ps.SetOrigin(0, 0, 0)
    ps.SetPoint1(size, 0, 0)
    ps.SetPoint2(0, size, 0)
    ps.SetResolution(res, res)
    tf = vtkTriangleFilter()
    tf.SetInputConnection(ps.GetOutputPort())
    tf.Update()
    return tf.GetOutput()


def test_distances_to_a_square_are_exact_inside_and_beyond_the_edge():
    rng = np.random.default_rng(0)
    pts = rng.uniform(-3, 13, (400, 3))
    d, closest = point_to_surface_distances(square(), pts)
    cx, cy = np.clip(pts[:, 0], 0, 10), np.clip(pts[:, 1], 0, 10)
    truth = np.sqrt((pts[:, 0] - cx) ** 2 + (pts[:, 1] - cy) ** 2 + pts[:, 2] ** 2)
    # exact to round-off although the mesh has only 32 triangles (not vertex distances)
    assert np.abs(d - truth).max() < 1e-9
    assert np.allclose(closest, np.c_[cx, cy, np.zeros_like(cx)], atol=1e-9)


def test_statistics_match_known_distances():
    heights = np.r_[np.full(50, 0.2), np.full(30, 0.7), np.full(15, 1.5), np.full(5, 3.0)]
    rng = np.random.default_rng(1)
    signs = rng.choice([-1.0, 1.0], heights.size)
    gold = np.c_[rng.uniform(1, 9, (heights.size, 2)), signs * heights]
    ev = evaluate_surface(square(), gold)
    assert ev.n == 100
    assert np.isclose(ev.mean, heights.mean())
    assert np.isclose(ev.rms, np.sqrt(np.mean(heights**2)))
    assert np.isclose(ev.median, 0.45)  # between the 50th (0.2) and 51st (0.7) values
    assert np.isclose(ev.p95, np.percentile(heights, 95))
    assert np.isclose(ev.max, 3.0)
    assert (ev.within_0_5, ev.within_1, ev.within_2) == (0.5, 0.8, 0.95)
    d = ev.as_dict()
    assert d["mean_mm"] == ev.mean and "distances_mm" not in d
    assert len(ev.as_dict(with_distances=True)["distances_mm"]) == 100


def test_sphere_distance_within_tessellation_error():
    s = vtkSphereSource()
    s.SetRadius(10.0)
    s.SetThetaResolution(120)
    s.SetPhiResolution(120)
    s.Update()
    rng = np.random.default_rng(2)
    dirs = rng.normal(size=(200, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    r = rng.uniform(11, 13, 200)
    ev = evaluate_surface(s.GetOutput(), dirs * r[:, None])
    # chordal error of a 120-segment sphere of radius 10 is < 0.004 mm
    assert np.abs(ev.distances - (r - 10)).max() < 0.01


@pytest.mark.parametrize(
    "gold, match",
    [
        (np.empty((0, 3)), "non-empty"),
        (np.ones((4, 2)), "non-empty"),
        (np.array([[0.0, 0.0, np.nan]]), "NaN"),
    ],
)
def test_bad_gold_refused(gold, match):
    with pytest.raises(BoneUSReconError, match=match):
        evaluate_surface(square(), gold)


def test_empty_surface_refused():
    with pytest.raises(BoneUSReconError, match="no triangles"):
        evaluate_surface(vtkPolyData(), np.zeros((3, 3)))


def test_point_cloud_is_not_a_surface():
    # Vertex cells only: distances would be to the points, not to a surface.
    from BoneUSRecon.Logic.vtkio import points_to_polydata

    cloud = points_to_polydata(np.random.default_rng(0).normal(size=(30, 3)))
    assert cloud.GetNumberOfCells() == 30
    with pytest.raises(BoneUSReconError, match="no surface triangles"):
        evaluate_surface(cloud, np.zeros((3, 3)))
    assert evaluate_surface(square(), np.zeros((1, 3))).n == 1

"""Registration to a bone model against ground truth: the simulator's bone, moved by known
rigid transforms, and the sweep's reconstruction (or its points) registered back.

Target registration error (TRE) is measured at the imaged bone surface (the simulator's
gold points, in the sweep's frame): the distance between where the estimate and the
truth put each point.
"""

from __future__ import annotations

import numpy as np
import pytest
from vtkmodules.util import numpy_support

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.registration import (
    RegistrationParams,
    bone_model,
    landmark_transform,
    model_from_polydata,
    patch_normal,
    register,
    register_polydata,
    rigid_error,
    transform_points,
)
from BoneUSRecon.Logic.simulation.bones import BONE_SPECS, BoneGeometry, BoneSpec
from BoneUSRecon.Logic.vtkio import polydata_points, triangles_to_polydata


def rotation(axis, deg: float) -> np.ndarray:
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    return np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k


def rigid(axis, deg: float, shift, centre) -> np.ndarray:
    """Rotation by ``deg`` about ``axis`` through ``centre``, then ``shift`` (mm)."""
    m = np.eye(4)
    m[:3, :3] = rotation(axis, deg)
    m[:3, 3] = np.asarray(centre) - m[:3, :3] @ np.asarray(centre) + np.asarray(shift, float)
    return m


def random_motion(rng: np.random.Generator, deg: float, mm: float, centre) -> np.ndarray:
    d = rng.normal(size=3)
    return rigid(rng.normal(size=3), deg, d / np.linalg.norm(d) * mm, centre)


@pytest.fixture(scope="module")
def recon(sim_small):
    from BoneUSRecon.Logic.pipeline import reconstruct

    return reconstruct(sim_small.sweep)


@pytest.fixture(scope="module")
def source(recon):
    """The reconstructed surface's vertices and outward normals (sweep frame, mm)."""
    s = recon.surface
    return polydata_points(s), numpy_support.vtk_to_numpy(s.GetPointData().GetNormals()).astype(
        float
    )


@pytest.fixture(scope="module")
def mesh(sim_small):
    """The simulated clavicle as a closed model of ~20,000 triangles (sweep frame)."""
    g = sim_small.geometry
    return g.closed_mesh(*g.closed_mesh_params(20_000))


def moved_model(mesh, truth: np.ndarray):
    v, f = mesh
    return bone_model(transform_points(truth, v), f)


# ---- the model ----------------------------------------------------------------------
@pytest.mark.parametrize("bone", ["clavicle", "radius"])
def test_closed_bone_mesh_is_watertight_outward_and_sized(bone) -> None:
    g = BoneGeometry(BONE_SPECS[bone])
    v, f = g.closed_mesh(*g.closed_mesh_params(50_000))
    assert abs(len(f) - 50_000) < 500
    directed = np.concatenate([f[:, [0, 1]], f[:, [1, 2]], f[:, [2, 0]]])
    # every directed edge once and its reverse once: closed, consistently oriented
    assert len(np.unique(directed, axis=0)) == len(directed)
    assert {tuple(e) for e in directed[:2000, ::-1]} <= {tuple(e) for e in directed}
    volume = np.einsum("ij,ij->i", v[f[:, 0]], np.cross(v[f[:, 1]], v[f[:, 2]])).sum() / 6
    ss = np.linspace(0, g.length, 400)
    a, b = g.semi_axes(ss)
    arc = np.linalg.norm(g.axis_derivative(ss), axis=1)  # the sections are normal to the axis
    assert volume == pytest.approx(
        np.pi * np.mean(a * b * arc) * g.length, rel=0.01
    )  # > 0: outward
    model = bone_model(v, f)
    assert model.n_border_edges == 0


def test_bad_models_are_refused() -> None:
    v = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [5, 5, 5]])
    with pytest.raises(BoneUSReconError, match="no triangles"):
        bone_model(v, np.empty((0, 3), int))
    fan = np.array([[0, 1, 2], [0, 1, 3], [0, 1, 4]])  # edge 0-1 in three triangles
    with pytest.raises(BoneUSReconError, match="not a manifold"):
        bone_model(v, fan)
    with pytest.raises(BoneUSReconError, match="no triangles"):
        from BoneUSRecon.Logic.vtkio import points_to_polydata

        model_from_polydata(points_to_polydata(v))
    with pytest.raises(BoneUSReconError, match="missing vertices"):
        bone_model(v, np.array([[0, 1, 9]]))


# ---- landmarks ----------------------------------------------------------------------
def test_landmarks_recover_a_large_motion_exactly() -> None:
    rng = np.random.default_rng(3)
    src = rng.uniform(-50, 50, (6, 3))
    truth = rigid([1, 2, 3], 130.0, [100.0, -40.0, 25.0], [0, 0, 0])
    m, rms = landmark_transform(src, transform_points(truth, src))
    np.testing.assert_allclose(m, truth, atol=1e-9)
    assert rms < 1e-9
    noisy = transform_points(truth, src) + rng.normal(0, 0.5, src.shape)
    m, rms = landmark_transform(src, noisy)
    assert 0.1 < rms < 1.0 and rigid_error(m, truth, src)["tre_median_mm"] < 1.0


@pytest.mark.parametrize(
    "src, tgt, match",
    [
        (np.zeros((2, 3)), np.zeros((2, 3)), "at least 3"),
        (np.eye(3), np.eye(4)[:, :3], "3 and 4 points"),
        (np.array([[0.0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3]]), np.eye(4)[:, :3], "one line"),
        (np.full((3, 3), np.nan), np.eye(3), "NaN"),
    ],
)
def test_bad_landmarks_are_refused(src, tgt, match) -> None:
    with pytest.raises(BoneUSReconError, match=match):
        landmark_transform(src, tgt)


# ---- accuracy -----------------------------------------------------------------------
def test_surface_registers_from_10mm_10deg_with_sub_half_mm_tre(sim_small, source, mesh) -> None:
    pts, nrm = source
    rng = np.random.default_rng(0)
    for _ in range(3):
        truth = random_motion(rng, 10.0, 10.0, pts.mean(0))
        reg = register(pts, moved_model(mesh, truth), source_normals=nrm)
        err = rigid_error(reg.matrix, truth, sim_small.gold)
        assert err["tre_median_mm"] <= 0.5 and err["tre_p95_mm"] <= 1.0, err
        assert reg.reliable, reg.reasons
        assert reg.rms_mm < 0.3 and reg.inlier_share > 0.95
        assert reg.converged and np.all(np.diff(reg.eigenvalues) >= 0)


def test_points_without_normals_register_from_15mm_15deg(sim_small, recon, mesh) -> None:
    pts = polydata_points(recon.points)  # the segmented points: no normals
    truth = rigid([0.3, -1.0, 0.5], 15.0, [9.0, -8.0, 8.5], pts.mean(0))
    reg = register(pts, moved_model(mesh, truth))
    err = rigid_error(reg.matrix, truth, sim_small.gold)
    assert err["tre_median_mm"] <= 0.5, err
    assert err["rotation_deg"] < 0.5
    assert reg.inlier_share > 0.9 and reg.rms_mm < 0.3


def test_landmark_start_from_far_away(sim_small, source, mesh) -> None:
    pts, nrm = source
    truth = rigid([0.2, 1.0, -0.4], 120.0, [150.0, 60.0, -80.0], pts.mean(0))
    # Three landmarks picked on the sweep's surface, their model positions off by ~3 mm
    lm_src = pts[[0, len(pts) // 2, len(pts) - 1]]
    lm_tgt = transform_points(truth, lm_src) + np.array(
        [[2.0, -1.0, 1.5], [-1.5, 2.0, 0.5], [1.0, 1.0, -2.5]]
    )
    reg = register(pts, moved_model(mesh, truth), source_normals=nrm, landmarks=(lm_src, lm_tgt))
    assert reg.landmark_rms_mm > 1.0
    err = rigid_error(reg.matrix, truth, sim_small.gold)
    assert err["tre_median_mm"] <= 0.5, err
    # without them, the identity start is refused, not silently "registered"
    with pytest.raises(BoneUSReconError, match="do not overlap"):
        register(pts, moved_model(mesh, truth), source_normals=nrm)


def test_partial_overlap_with_a_cropped_model(sim_small, source, mesh) -> None:
    pts, nrm = source
    v, f = mesh
    keep = v[f].mean(axis=1)[:, 0] < 15.0  # the model stops mid-sweep: an open border
    truth = random_motion(np.random.default_rng(5), 10.0, 10.0, pts.mean(0))
    model = bone_model(transform_points(truth, v), f[keep])
    assert model.n_border_edges > 0
    reg = register(pts, model, source_normals=nrm)
    err = rigid_error(reg.matrix, truth, sim_small.gold[sim_small.gold[:, 0] < 15.0])
    assert err["tre_median_mm"] <= 0.5, err
    assert 0.3 < reg.inlier_share < 0.8  # the part beyond the model is left out, not fitted


def test_outlier_points_are_ignored(sim_small, source, mesh) -> None:
    pts, nrm = source
    rng = np.random.default_rng(7)
    n_out = len(pts) // 5
    lo, hi = pts.min(0) - 5.0, pts.max(0) + 5.0
    bad = rng.uniform(lo, hi, (n_out, 3))
    bad_n = rng.normal(size=(n_out, 3))
    truth = random_motion(rng, 10.0, 10.0, pts.mean(0))
    reg = register(
        np.vstack([pts, bad]), moved_model(mesh, truth), source_normals=np.vstack([nrm, bad_n])
    )
    err = rigid_error(reg.matrix, truth, sim_small.gold)
    assert err["tre_median_mm"] <= 0.5, err
    assert reg.inlier_share < 0.95  # the outliers are not counted as fitting
    assert reg.rms_mm < 0.5


def test_global_search_without_any_initial_alignment(sim_small, source, mesh) -> None:
    pts, nrm = source
    truth = rigid([0.0, 0.3, 1.0], 75.0, [40.0, -25.0, 10.0], pts.mean(0))
    reg = register(
        pts, moved_model(mesh, truth), RegistrationParams(init="search"), source_normals=nrm
    )
    err = rigid_error(reg.matrix, truth, sim_small.gold)
    assert err["tre_median_mm"] <= 0.5 or not reg.reliable, (err, reg.reasons)
    assert err["tre_median_mm"] <= 0.5, err  # the clavicle's S-shape has one best fit


def test_featureless_cylinder_is_flagged_with_the_sliding_named() -> None:
    spec = BoneSpec("cylinder", 120.0, (16.0, 16.0), (16.0, 16.0), 5.0, 0.0, 0.5, 0.0, 0.0, 0.0)
    g = BoneGeometry(spec)
    v, f = g.closed_mesh(*g.closed_mesh_params(20_000))
    s, phi = np.meshgrid(np.linspace(35, 85, 60), np.linspace(np.pi / 2 - 0.9, np.pi / 2 + 0.9, 30))
    rng = np.random.default_rng(2)
    pts = g.surface(s.ravel(), phi.ravel()) + rng.normal(0, 0.1, (s.size, 3))
    nrm = g.normals(s.ravel(), phi.ravel())
    truth = rigid([1.0, 0.5, 0.2], 8.0, [4.0, 3.0, -5.0], pts.mean(0))
    reg = register(pts, bone_model(transform_points(truth, v), f), source_normals=nrm)
    assert not reg.reliable
    text = " ".join(reg.reasons)
    assert "translation along the bone's long axis is unconstrained" in text, text
    assert "rotation about the bone's long axis is" in text, text  # unconstrained or weakly
    # The well-constrained directions are still fine: the patch sits on the cylinder.
    assert reg.rms_mm < 0.2 and reg.inlier_share > 0.9
    assert reg.sliding_mm[0] > 100 and reg.sliding_mm[1] > 10 and reg.sliding_mm[2] < 1.0
    assert reg.condition > 1e4


# ---- bad input ----------------------------------------------------------------------
def test_model_in_metres_is_named(source, mesh) -> None:
    pts, nrm = source
    v, f = mesh
    with pytest.raises(BoneUSReconError, match="metres"):
        register(pts, bone_model(v / 1000.0, f), model_path="ct_model.stl")
    with pytest.raises(BoneUSReconError, match="metres") as exc:
        register(pts / 1000.0, bone_model(v, f), source_path="surface.vtp")
    assert "surface.vtp" in str(exc.value)


def test_non_overlapping_inputs_fail_clearly(source, mesh) -> None:
    pts, nrm = source
    v, f = mesh
    far = bone_model(v + [0.0, 300.0, 0.0], f)
    with pytest.raises(BoneUSReconError, match="do not overlap"):
        register(pts, far, source_normals=nrm)


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"init": "magic"}, "init must be one of"),
        ({"max_distance_mm": -1.0}, "max_distance_mm"),
        ({"min_distance_mm": 50.0}, "exceeds"),
        ({"min_overlap": 1.5}, "min_overlap"),
        ({"start_rolls_deg": (-5.0,)}, "start_rolls_deg"),
        ({"max_iterations": 0}, "max_iterations"),
    ],
)
def test_parameters_are_checked(kwargs, match) -> None:
    with pytest.raises(BoneUSReconError, match=match):
        RegistrationParams(**kwargs)


def test_non_rigid_initial_matrix_is_refused(source, mesh) -> None:
    pts, nrm = source
    with pytest.raises(BoneUSReconError, match="not rigid"):
        register(pts, moved_model(mesh, np.eye(4)), init=np.diag([2.0, 1.0, 1.0, 1.0]))


def test_patch_normal_of_a_top_patch_is_vertical(sim_small) -> None:
    g = sim_small.geometry
    s, phi = np.meshgrid(np.linspace(20, 100, 50), np.linspace(1.0, 2.1, 20))
    n = patch_normal(g.surface(s.ravel(), phi.ravel()))
    assert abs(n[2]) > 0.95  # the bone is seen from above (+z)


def test_register_polydata_uses_the_surface_normals(sim_small, recon, mesh) -> None:
    v, f = mesh
    truth = rigid([0, 0, 1], 5.0, [3.0, 2.0, -4.0], polydata_points(recon.surface).mean(0))
    reg = register_polydata(recon.surface, triangles_to_polydata(transform_points(truth, v), f))
    assert rigid_error(reg.matrix, truth, sim_small.gold)["tre_median_mm"] <= 0.5
    d = reg.as_dict()
    assert d["reliable"] is True and len(d["matrix"]) == 4 and len(d["directions"]) == 6


def test_simulation_bone_model_polydata_is_a_closed_model(sim_small) -> None:
    pd = sim_small.bone_model_polydata(5_000)
    assert abs(pd.GetNumberOfPolys() - 5_000) < 200
    model = model_from_polydata(pd)
    assert model.n_border_edges == 0
    # every vertex of the tube lies on the analytic bone
    assert sim_small.distance_to_truth(model.vertices[:-2]).max() < 1e-6


def test_reconstruction_points_face_their_probe_from_15mm_15deg(sim_small, recon, mesh) -> None:
    from BoneUSRecon.Logic.registration import register_reconstruction, towards_probe

    up = towards_probe(recon.points, sim_small.sweep.image_to_reference)
    assert np.all(up[:, 2] > 0.8)  # the simulated probe looks down (-z) at the bone
    rng = np.random.default_rng(11)
    for _ in range(2):
        truth = random_motion(rng, 15.0, 15.0, sim_small.gold.mean(0))
        reg = register_reconstruction(recon, moved_model(mesh, truth))
        err = rigid_error(reg.matrix, truth, sim_small.gold)
        assert err["tre_median_mm"] <= 0.5, err
        assert reg.reliable and reg.inlier_share > 0.9

"""Registration through Slicer's MRML (slicer-core): transform files read and written by
Slicer's own transform storage node, and the module's registration of model nodes."""

from __future__ import annotations

import sys
from pathlib import Path

import numpy as np
import pytest

slicer = pytest.importorskip("slicer")  # the PyPI package slicer-core (test extra)

from vtkmodules.vtkCommonMath import vtkMatrix4x4  # noqa: E402

from BoneUSRecon.Logic.registration import rigid_error, transform_points  # noqa: E402
from BoneUSRecon.Logic.sweep import matrix_to_vtk, vtk_to_matrix  # noqa: E402
from BoneUSRecon.Logic.transform_io import LPS_TO_RAS, read_transform, write_transform  # noqa: E402
from BoneUSRecon.Logic.vtkio import polydata_points, triangles_to_polydata  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))  # as Slicer does for the module's folder


def _rigid(axis, deg, shift, centre):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k
    m[:3, 3] = np.asarray(centre) - m[:3, :3] @ np.asarray(centre) + np.asarray(shift, float)
    return m


def _to_parent(node) -> np.ndarray:
    m = vtkMatrix4x4()
    node.GetMatrixTransformToParent(m)
    return vtk_to_matrix(m)


@pytest.fixture()
def scene():
    return slicer.vtkMRMLScene()


@pytest.mark.parametrize("ext", [".tfm", ".h5"])
def test_slicer_reads_our_itk_file_as_the_source_to_target_transform(scene, tmp_path, ext) -> None:
    # Our files' coordinates are LPS (as Slicer assumes for files); its scene is RAS.
    t = _rigid([0.3, -0.4, 1.0], 25.0, [12.0, -7.0, 30.0], [40.0, 10.0, -5.0])
    path = write_transform(t, tmp_path / f"T{ext}")
    node = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
    storage = scene.AddNewNodeByClass("vtkMRMLTransformStorageNode")
    storage.SetFileName(str(path))
    assert storage.ReadData(node) == 1
    np.testing.assert_allclose(_to_parent(node), LPS_TO_RAS @ t @ LPS_TO_RAS, atol=1e-9)
    # A source model point, loaded into the scene (LPS -> RAS) and put under the node,
    # lands where T puts it (seen in RAS).
    p_lps = np.array([3.0, -20.0, 7.0])
    p_ras = p_lps * [-1, -1, 1]
    moved = node.GetTransformToParent().TransformPoint(*p_ras)
    np.testing.assert_allclose(
        np.array(moved) * [-1, -1, 1], transform_points(t, p_lps[None])[0], atol=1e-9
    )


@pytest.mark.parametrize("ext", [".tfm", ".h5"])
def test_we_read_slicer_written_transforms(scene, tmp_path, ext) -> None:
    t = _rigid([1.0, 0.2, 0.0], -40.0, [5.0, 5.0, -9.0], [0.0, 0.0, 0.0])
    node = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode")
    node.SetMatrixTransformToParent(matrix_to_vtk(LPS_TO_RAS @ t @ LPS_TO_RAS))
    storage = scene.AddNewNodeByClass("vtkMRMLTransformStorageNode")
    storage.SetFileName(str(tmp_path / f"S{ext}"))
    assert storage.WriteData(node) == 1
    np.testing.assert_allclose(read_transform(tmp_path / f"S{ext}"), t, atol=1e-9)
    # and with RAS inputs, the scene's own matrix comes back
    np.testing.assert_allclose(
        read_transform(tmp_path / f"S{ext}", coordinates="RAS"), _to_parent(node), atol=1e-9
    )


@pytest.fixture(scope="module")
def recon(sim_small):
    from BoneUSRecon.Logic.pipeline import reconstruct

    return reconstruct(sim_small.sweep)


def test_register_model_nodes_in_the_scene(scene, sim_small, recon) -> None:
    from BoneSurfaceReconstructionLib import mrml
    from BoneSurfaceReconstructionLib.registration import registerModelToModel, summaryText

    pts = polydata_points(recon.surface)
    truth = _rigid([0.0, 0.4, 1.0], 8.0, [-6.0, 7.0, 5.0], pts.mean(0))
    g = sim_small.geometry
    v, f = g.closed_mesh(*g.closed_mesh_params(20_000))
    source = mrml.show_surface(recon.surface, scene, name="Surface")
    # The bone model sits under a parent transform (as a CT model placed in the scene):
    # registration works in world coordinates.
    parent = scene.AddNewNodeByClass("vtkMRMLLinearTransformNode", "CTPlacement")
    placement = _rigid([1, 0, 0], 30.0, [0.0, 20.0, 0.0], [0, 0, 0])
    parent.SetMatrixTransformToParent(matrix_to_vtk(placement))
    target = scene.AddNewNodeByClass("vtkMRMLModelNode", "BoneModel")
    target.SetAndObservePolyData(
        triangles_to_polydata(transform_points(np.linalg.inv(placement) @ truth, v), f)
    )
    target.SetAndObserveTransformNodeID(parent.GetID())

    out = registerModelToModel(source, target)
    with_points = registerModelToModel(source, target, reconstruction=recon)
    assert (
        rigid_error(_to_parent(with_points.transformNode), truth, sim_small.gold)["tre_median_mm"]
        <= 0.5
    )
    world_truth = truth  # source is in world already; target's world = placement @ local
    assert (
        rigid_error(_to_parent(out.transformNode), world_truth, sim_small.gold)["tre_median_mm"]
        <= 0.5
    )
    assert out.transformNode.GetAttribute("BoneUSRecon.registration.reliable") == "True"
    np.testing.assert_allclose(
        slicer.util.arrayFromModelPoints(out.registeredNode),
        transform_points(_to_parent(out.transformNode), pts),
        atol=1e-4,
    )
    assert "residual RMS" in summaryText(out)
    # A second run refills the same nodes.
    n = scene.GetNumberOfNodesByClass("vtkMRMLLinearTransformNode")
    again = registerModelToModel(
        source, target, transformNode=out.transformNode, registeredNode=out.registeredNode
    )
    assert again.transformNode is out.transformNode
    assert scene.GetNumberOfNodesByClass("vtkMRMLLinearTransformNode") == n


def test_bad_nodes_raise_value_errors(scene, recon) -> None:
    from BoneSurfaceReconstructionLib import mrml
    from BoneSurfaceReconstructionLib.registration import registerModelToModel

    source = mrml.show_surface(recon.surface, scene, name="Surface")
    empty = scene.AddNewNodeByClass("vtkMRMLModelNode", "Empty")
    with pytest.raises(ValueError, match="empty"):
        registerModelToModel(source, empty)
    with pytest.raises(ValueError, match="model node"):
        registerModelToModel(source, scene.AddNewNodeByClass("vtkMRMLLinearTransformNode"))
    metres = scene.AddNewNodeByClass("vtkMRMLModelNode", "Metres")
    pd = triangles_to_polydata(polydata_points(recon.surface)[:3] / 1000.0, [[0, 1, 2]])
    metres.SetAndObservePolyData(pd)
    with pytest.raises(ValueError):
        registerModelToModel(source, metres)

"""Atomic outputs, output-path checks and the geometry/point readers and writers."""

from __future__ import annotations

import os
import stat

import numpy as np
import pytest

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import (
    atomic_path,
    check_input_file,
    check_output_dir,
    check_output_path,
)
from BoneUSRecon.Logic.vtkio import (
    SURFACE_EXTENSIONS,
    points_to_polydata,
    polydata_points,
    read_points,
    read_polydata,
    write_points_csv,
    write_polydata,
)


def test_error_is_one_line_and_names_file():
    e = BoneUSReconError("bad\nthing   here", "/x/y.mha")
    assert str(e) == "/x/y.mha: bad thing here"
    assert isinstance(e, ValueError)


def test_atomic_path_leaves_nothing_on_failure(tmp_path):
    target = tmp_path / "out.txt"
    with pytest.raises(RuntimeError):
        with atomic_path(target) as tmp:
            tmp.write_text("partial")
            raise RuntimeError("boom")
    assert list(tmp_path.iterdir()) == []


def test_atomic_path_replaces_existing_only_on_success(tmp_path):
    target = tmp_path / "out.txt"
    target.write_text("old")
    with pytest.raises(KeyboardInterrupt):
        with atomic_path(target) as tmp:
            tmp.write_text("new")
            raise KeyboardInterrupt
    assert target.read_text() == "old"
    with atomic_path(target) as tmp:
        tmp.write_text("new")
    assert target.read_text() == "new"
    assert sorted(p.name for p in tmp_path.iterdir()) == ["out.txt"]


def test_check_output_path_errors(tmp_path):
    with pytest.raises(BoneUSReconError, match="unknown output extension"):
        check_output_path(tmp_path / "a.xyz", SURFACE_EXTENSIONS)
    with pytest.raises(BoneUSReconError, match="does not exist"):
        check_output_path(tmp_path / "missing" / "a.vtp", SURFACE_EXTENSIONS)
    # /sys refuses new files even to root (a chmod'ed folder would not, under root).
    with pytest.raises(BoneUSReconError, match="not writable"):
        check_output_path("/sys/a.vtp", SURFACE_EXTENSIONS)
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(stat.S_IRUSR | stat.S_IXUSR)
    try:
        if not os.access(ro, os.W_OK):  # only meaningful when not root
            with pytest.raises(BoneUSReconError, match="not writable"):
                check_output_path(ro / "a.vtp", SURFACE_EXTENSIONS)
    finally:
        ro.chmod(stat.S_IRWXU)


def test_check_output_dir(tmp_path):
    assert check_output_dir(tmp_path / "new") == tmp_path / "new"  # may be created
    assert check_output_dir(tmp_path) == tmp_path  # or exist
    (tmp_path / "f").write_text("x")
    with pytest.raises(BoneUSReconError, match="overlay path exists and is not a folder"):
        check_output_dir(tmp_path / "f", "overlay")
    with pytest.raises(BoneUSReconError, match="does not exist"):
        check_output_dir(tmp_path / "no" / "such")
    with pytest.raises(BoneUSReconError, match="not writable"):
        check_output_dir("/sys/new_folder")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["f"]  # the probes left nothing


def test_check_input_file_errors(tmp_path):
    with pytest.raises(BoneUSReconError, match="no such file"):
        check_input_file(tmp_path / "nope.mha")
    (tmp_path / "empty.mha").write_bytes(b"")
    with pytest.raises(BoneUSReconError, match="empty"):
        check_input_file(tmp_path / "empty.mha")
    with pytest.raises(BoneUSReconError, match="directory"):
        check_input_file(tmp_path)


@pytest.mark.parametrize("ext", SURFACE_EXTENSIONS)
def test_write_read_polydata_round_trip(tmp_path, ext):
    rng = np.random.default_rng(0)
    pts = rng.normal(size=(50, 3))
    pd = points_to_polydata(pts, {"Frame": np.arange(50, dtype=np.int32)})
    out = write_polydata(pd, tmp_path / f"p{ext}")
    assert out.exists() and out.stat().st_size > 0
    assert [p.name for p in tmp_path.iterdir()] == [f"p{ext}"]
    if ext in (".vtp", ".vtk", ".ply"):
        back = polydata_points(read_polydata(out))
        np.testing.assert_allclose(back, pts, atol=1e-5)
    if ext in (".vtp", ".vtk"):
        assert read_polydata(out).GetPointData().GetArray("Frame") is not None


@pytest.mark.parametrize("ext", SURFACE_EXTENSIONS)
def test_every_written_surface_format_reads_back(tmp_path, ext):
    # What reconstruct writes, evaluate and view must read (an .obj used to be refused).
    from vtkmodules.vtkFiltersSources import vtkSphereSource

    src = vtkSphereSource()
    src.SetRadius(10.0)
    src.Update()
    mesh = src.GetOutput()
    back = read_polydata(write_polydata(mesh, tmp_path / f"s{ext}"))
    assert back.GetNumberOfPolys() == mesh.GetNumberOfPolys() > 0
    r = np.linalg.norm(polydata_points(back), axis=1)
    np.testing.assert_allclose(r, 10.0, atol=1e-4)


def test_fast_vtp_reads_back_the_same(tmp_path):
    """The live flavour of .vtp (LZ4, raw appended data) keeps points, cells and arrays."""
    from vtkmodules.vtkFiltersSources import vtkSphereSource

    src = vtkSphereSource()
    src.SetThetaResolution(40)
    src.Update()
    mesh = src.GetOutput()
    dist = np.linspace(0.0, 1.0, mesh.GetNumberOfPoints())
    mesh.GetPointData().AddArray(
        points_to_polydata(np.zeros((dist.size, 3)), {"Distance": dist})
        .GetPointData()
        .GetArray("Distance")
    )
    slow = write_polydata(mesh, tmp_path / "slow.vtp")
    fast = write_polydata(mesh, tmp_path / "fast.vtp", fast=True)
    assert b"LZ4" in fast.read_bytes()[:2000] and b"LZ4" not in slow.read_bytes()[:2000]
    a, b = read_polydata(slow), read_polydata(fast)
    np.testing.assert_array_equal(polydata_points(a), polydata_points(b))
    assert a.GetNumberOfPolys() == b.GetNumberOfPolys() == mesh.GetNumberOfPolys()
    back = b.GetPointData().GetArray("Distance")
    np.testing.assert_array_equal([back.GetValue(i) for i in range(dist.size)], dist)


def test_points_csv_round_trip_and_header_order(tmp_path):
    pts = np.array([[1.0, 2.0, 3.0], [4.0, 5.0, 6.5]])
    write_points_csv(pts, tmp_path / "g.csv")
    np.testing.assert_allclose(read_points(tmp_path / "g.csv"), pts)
    (tmp_path / "h.csv").write_text("id;z;y;x\n0;3;2;1\n1;6;5;4\n")
    np.testing.assert_allclose(read_points(tmp_path / "h.csv"), [[1, 2, 3], [4, 5, 6]])
    (tmp_path / "n.txt").write_text("1 2 3\n4 5 6\n")
    np.testing.assert_allclose(read_points(tmp_path / "n.txt"), [[1, 2, 3], [4, 5, 6]])


@pytest.mark.parametrize(
    "text, match",
    [
        ("x,y,z\n", "header only"),
        ("x,y,z\n1,2,abc\n", "numeric"),
        ("x,y,z\n1,2\n", "numeric"),
        ("x,y,z\n1,nan,3\n", "NaN"),
        ("# only a comment\n", "no points"),
    ],
)
def test_read_points_bad_csv(tmp_path, text, match):
    p = tmp_path / "g.csv"
    p.write_text(text)
    with pytest.raises(BoneUSReconError, match=match) as info:
        read_points(p)
    assert str(p) in str(info.value)


def test_read_polydata_bad_files(tmp_path):
    p = tmp_path / "s.vtp"
    p.write_text("this is not xml")
    with pytest.raises(BoneUSReconError, match="could not read"):
        read_polydata(p)
    q = tmp_path / "s.abc"
    q.write_text("1")
    with pytest.raises(BoneUSReconError, match="unknown surface format"):
        read_polydata(q)

"""The reconstruct, evaluate and table commands: outputs, summaries, one-line refusals."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.sequence_io import write_sweep
from BoneUSRecon.Logic.vtkio import read_polydata, write_points_csv


@pytest.fixture(scope="module")
def files(sim_small, tmp_path_factory):
    d = tmp_path_factory.mktemp("cli_recon")
    sweep = write_sweep(sim_small.sweep, d / "sweep.mha")
    gold = write_points_csv(sim_small.gold, d / "gold.csv")
    return sweep, gold


@pytest.fixture(scope="module")
def done(files, tmp_path_factory):
    """One full reconstruct run with every output, shared by the tests that read them."""
    sweep, gold = files
    out = tmp_path_factory.mktemp("cli_out")
    args = [
        "reconstruct",
        str(sweep),
        "-o",
        str(out / "bone.vtp"),
        "--gold",
        str(gold),
        "--points-out",
        str(out / "points.vtp"),
        "--json",
        "-q",
    ]
    return out, args


def run(capsys, argv):
    code = main(argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def assert_refused(capsys, argv, match, outdir: Path | None = None):
    before = set(os.listdir(outdir)) if outdir is not None else None
    code, out, err = run(capsys, argv)
    assert code == 2
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bone-us-recon: error:"), err
    assert match in lines[0]
    assert "Traceback" not in err
    if outdir is not None:
        assert set(os.listdir(outdir)) == before  # nothing written, no temp files


def test_reconstruct_json_outputs_and_accuracy(capsys, sim_small, done):
    out, args = done
    code, stdout, err = run(capsys, args)
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["summary"]["grid_shape"][1] == 24
    ev = doc["evaluation"]
    assert ev["n"] == sim_small.gold.shape[0]
    assert ev["mean_mm"] < 0.25 and ev["within_1mm"] > 0.97
    surf = read_polydata(out / "bone.vtp")
    assert surf.GetPointData().GetArray("Distance") is not None
    # the file on disk gives the same evaluation as the command printed
    assert evaluate_surface(surf, sim_small.gold).mean == pytest.approx(ev["mean_mm"], abs=1e-6)
    pts = read_polydata(out / "points.vtp")
    assert pts.GetNumberOfPoints() == doc["summary"]["segmented_points"]
    assert sorted(os.listdir(out)) == ["bone.vtp", "points.vtp"]


def test_reconstruct_text_summary_and_options(capsys, files, tmp_path):
    sweep, gold = files
    code, stdout, err = run(
        capsys,
        [
            "reconstruct",
            str(sweep),
            "-o",
            str(tmp_path / "b.stl"),
            "--degree",
            "3",
            "2",
            "--control-points",
            "10",
            "4",
            "--rays",
            "11",
            "--fit-method",
            "separable",
            "--robust",
            "none",
            "--axis",
            "line",
            "--points-out",
            str(tmp_path / "p.csv"),
            "-q",
        ],
    )
    assert code == 0, err
    assert "frames used" in stdout and "fit residual" in stdout and "11 rays" in stdout
    assert (tmp_path / "b.stl").stat().st_size > 0
    assert (tmp_path / "p.csv").read_text().startswith("x,y,z")


def test_evaluate_command(capsys, sim_small, done, files):
    out, args = done
    if not (out / "bone.vtp").exists():
        assert main(args) == 0
        capsys.readouterr()
    _, gold = files
    code, stdout, err = run(capsys, ["evaluate", str(out / "bone.vtp"), str(gold), "--json"])
    assert code == 0, err
    doc = json.loads(stdout)
    ref = evaluate_surface(read_polydata(out / "bone.vtp"), sim_small.gold)
    assert doc["mean_mm"] == pytest.approx(ref.mean)
    assert doc["within_1mm"] == pytest.approx(ref.within_1)
    code, stdout, _ = run(capsys, ["evaluate", str(out / "bone.vtp"), str(gold)])
    assert code == 0 and "95th percentile" in stdout and "within 1 mm" in stdout
    empty = out / "empty.csv"
    empty.write_text("x,y,z\n")
    try:
        assert_refused(capsys, ["evaluate", str(out / "bone.vtp"), str(empty)], "empty.csv")
    finally:
        empty.unlink()


def test_table_command_with_plot(capsys, files, tmp_path):
    sweep, gold = files
    png = tmp_path / "table.png"
    code, stdout, err = run(
        capsys,
        [
            "table",
            str(sweep),
            "--gold",
            str(gold),
            "--control-points",
            "5",
            "15",
            "--plot",
            str(png),
            "--json",
            "-q",
        ],
    )
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["control_points"] == [5, 15]
    assert doc["mean_distance_mm"][0] > doc["mean_distance_mm"][1]
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert sorted(os.listdir(tmp_path)) == ["table.png"]


@pytest.mark.parametrize(
    "extra, match",
    [
        (["--degree", "0", "2"], "degree must be at least 1"),
        (["--control-points", "2", "5"], "too few for degree"),
        (["--rays", "0"], "at least 2 rays"),
        (["--segmenter", "magic"], "unknown segmenter"),
    ],
)
def test_reconstruct_absurd_parameters_refused(capsys, files, tmp_path, extra, match):
    sweep, _ = files
    assert_refused(
        capsys, ["reconstruct", str(sweep), "-o", str(tmp_path / "b.vtp"), *extra], match, tmp_path
    )


def test_reconstruct_more_control_points_than_data_refused(capsys, files, tmp_path):
    sweep, _ = files
    assert_refused(
        capsys,
        [
            "reconstruct",
            str(sweep),
            "-o",
            str(tmp_path / "b.vtp"),
            "--control-points",
            "80",
            "5",
            "-q",
        ],
        "too few valid grid points for 80 x 5",
        tmp_path,
    )


def test_reconstruct_bad_paths_refused(capsys, files, tmp_path):
    sweep, gold = files
    assert_refused(
        capsys,
        ["reconstruct", str(sweep), "-o", str(tmp_path / "nope" / "b.vtp")],
        "does not exist",
        tmp_path,
    )
    assert_refused(
        capsys,
        ["reconstruct", str(sweep), "-o", str(tmp_path / "b.xyz")],
        "unknown output extension",
        tmp_path,
    )
    assert_refused(
        capsys,
        ["reconstruct", str(tmp_path / "missing.mha"), "-o", str(tmp_path / "b.vtp")],
        "no such file",
        tmp_path,
    )
    assert_refused(
        capsys,
        [
            "reconstruct",
            str(sweep),
            "-o",
            str(tmp_path / "b.vtp"),
            "--points-out",
            str(tmp_path / "p.stl"),
        ],
        "unknown output extension",
        tmp_path,
    )
    bad_gold = tmp_path / "bad.csv"
    bad_gold.write_text("x,y,z\n1,2,oops\n")
    assert_refused(
        capsys,
        ["reconstruct", str(sweep), "-o", str(tmp_path / "b.vtp"), "--gold", str(bad_gold)],
        "bad.csv",
        tmp_path,
    )
    not_dir = tmp_path / "file"
    not_dir.write_text("x")
    assert_refused(
        capsys,
        ["reconstruct", str(sweep), "-o", str(tmp_path / "b.vtp"), "--report", str(not_dir)],
        "not a folder",
        tmp_path,
    )


def test_reconstruct_refuses_a_foreign_report_folder_before_the_work(
    capsys, files, tmp_path, monkeypatch
):
    # A folder holding other files is refused up front, not after minutes of work:
    # reading the sweep would already be too late.
    import BoneUSRecon.Logic.sequence_io as sequence_io

    def too_late(*args, **kwargs):
        raise AssertionError("the sweep was read before the report folder was checked")

    monkeypatch.setattr(sequence_io, "read_sweep", too_late)
    sweep, _ = files
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("precious")
    assert_refused(
        capsys,
        ["reconstruct", str(sweep), "-o", str(tmp_path / "b.vtp"), "--report", str(foreign)],
        "not a BoneUSRecon report",
        tmp_path,
    )
    assert os.listdir(foreign) == ["thesis.tex"]


@pytest.mark.skipif(os.geteuid() == 0, reason="root can write anywhere")
def test_unwritable_output_folder_refused(capsys, files, tmp_path):
    sweep, _ = files
    ro = tmp_path / "ro"
    ro.mkdir()
    ro.chmod(0o555)
    try:
        assert_refused(
            capsys, ["reconstruct", str(sweep), "-o", str(ro / "b.vtp")], "not writable", ro
        )
    finally:
        ro.chmod(0o755)


def test_evaluate_bad_inputs_refused(capsys, files, tmp_path):
    _, gold = files
    assert_refused(capsys, ["evaluate", str(tmp_path / "none.vtp"), str(gold)], "no such file")
    junk = tmp_path / "junk.vtp"
    junk.write_text("not a vtp file")
    assert_refused(capsys, ["evaluate", str(junk), str(gold)], "junk.vtp")
    pts_only = tmp_path / "pts.vtp"
    from BoneUSRecon.Logic.vtkio import points_to_polydata, write_polydata

    write_polydata(points_to_polydata(np.random.default_rng(0).normal(size=(20, 3))), pts_only)
    assert_refused(capsys, ["evaluate", str(pts_only), str(gold)], "no surface triangles")


def test_table_bad_inputs_refused(capsys, files, tmp_path):
    sweep, gold = files
    assert_refused(
        capsys,
        ["table", str(sweep), "--gold", str(gold), "--plot", str(tmp_path / "t.jpg")],
        "unknown output extension",
        tmp_path,
    )
    assert_refused(
        capsys,
        ["table", str(sweep), "--gold", str(gold), "--control-points", "1"],
        "too few for degree",
        tmp_path,
    )
    assert_refused(
        capsys, ["table", str(sweep), "--gold", str(tmp_path / "g.csv")], "no such file", tmp_path
    )


def test_reconstruct_flank_extension_option(capsys, files, tmp_path):
    """--flank-extension reaches SurfaceParams: strips flagged 'Extrapolated' in the mesh;
    a negative length is refused in one line, with nothing written."""
    from vtk.util.numpy_support import vtk_to_numpy

    sweep, _ = files
    out = tmp_path / "ext.vtp"
    code, _, err = run(
        capsys, ["reconstruct", str(sweep), "-o", str(out), "--flank-extension", "1.5", "-q"]
    )
    assert code == 0, err
    flags = vtk_to_numpy(read_polydata(out).GetPointData().GetArray("Extrapolated"))
    assert 0 < flags.sum() < flags.size
    bad = tmp_path / "bad"
    bad.mkdir()
    assert_refused(
        capsys,
        ["reconstruct", str(sweep), "-o", str(bad / "x.vtp"), "--flank-extension", "-1"],
        "flank_extension_mm",
        bad,
    )

"""No output overwrites an input or another output (issue 12, item 1).

Every command that writes checks its paths with
:func:`BoneUSRecon.Logic.fileio.check_distinct_paths` before any work: one line, exit
status 2, every file unchanged and nothing new in the folder. ``demo`` into a folder
holding files it did not write refuses unless ``--force``.
"""

from __future__ import annotations

import hashlib
import os
from pathlib import Path

import pytest

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import check_distinct_paths
from BoneUSRecon.Logic.sequence_io import write_sweep
from BoneUSRecon.Logic.vtkio import write_points_csv


@pytest.fixture()
def files(sim_small, tmp_path: Path) -> dict[str, Path]:
    """A sweep, its gold points and a surface, in a fresh folder per test."""
    sweep = write_sweep(sim_small.sweep, tmp_path / "sweep.mha")
    gold = write_points_csv(sim_small.gold, tmp_path / "gold.csv")
    (tmp_path / "surface.vtp").write_bytes(b"<VTKFile> stands in for a surface </VTKFile>\n")
    return {"sweep": sweep, "gold": gold, "surface": tmp_path / "surface.vtp", "dir": tmp_path}


def _snapshot(folder: Path) -> dict[str, str]:
    return {
        str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
        if p.is_file()
        else "dir"
        for p in sorted(folder.rglob("*"))
    }


def _refused(capsys, argv: list[str], folder: Path, *words: str) -> str:
    before = _snapshot(folder)
    code = main(argv)
    err = capsys.readouterr().err
    lines = err.strip().splitlines()
    assert code == 2, err
    assert len(lines) == 1 and lines[0].startswith("bone-us-recon: error: "), err
    for w in words:
        assert w in lines[0], (w, lines[0])
    assert _snapshot(folder) == before, "a file was written or changed"
    return lines[0]


def test_reconstruct_points_out_onto_gold_is_refused(capsys, files) -> None:
    f = files
    line = _refused(
        capsys,
        [
            "reconstruct",
            str(f["sweep"]),
            "-o",
            str(f["dir"] / "s.vtp"),
            "--gold",
            str(f["gold"]),
            "--points-out",
            str(f["gold"]),
            "-q",
        ],
        f["dir"],
        "gold.csv",
        "--points-out",
        "input --gold",
    )
    assert "overwrite" in line


def test_reconstruct_two_outputs_on_one_path_are_refused(capsys, files) -> None:
    f = files
    a = f["dir"] / "a.vtp"
    _refused(
        capsys,
        ["reconstruct", str(f["sweep"]), "-o", str(a), "--points-out", str(a), "-q"],
        f["dir"],
        "a.vtp",
        "--points-out",
        "-o",
        "same path",
    )


def test_reconstruct_output_onto_sweep_or_report_around_inputs_is_refused(capsys, files) -> None:
    f = files
    # The same file by another spelling ("./x/../x") is caught too.
    other = f["dir"] / "." / ".." / f["dir"].name / "sweep.mha"
    _refused(
        capsys,
        ["reconstruct", str(f["sweep"]), "-o", str(other), "-q"],
        f["dir"],
        "-o",
        "input SWEEP",
    )
    # The report folder is replaced as a whole: no input and no output may sit inside.
    _refused(
        capsys,
        [
            "reconstruct",
            str(f["sweep"]),
            "-o",
            str(f["dir"] / "s.vtp"),
            "--report",
            str(f["dir"]),
            "-q",
        ],
        f["dir"],
        "SWEEP",
        "--report",
    )
    (f["dir"] / "rep").mkdir()
    _refused(
        capsys,
        [
            "reconstruct",
            str(f["sweep"]),
            "-o",
            str(f["dir"] / "rep" / "s.vtp"),
            "--report",
            str(f["dir"] / "rep"),
            "-q",
        ],
        f["dir"],
        "-o",
        "--report",
    )


def test_symlinked_input_is_recognised(capsys, files) -> None:
    f = files
    link = f["dir"] / "link.csv"
    os.symlink(f["gold"], link)
    _refused(
        capsys,
        [
            "reconstruct",
            str(f["sweep"]),
            "-o",
            str(f["dir"] / "s.vtp"),
            "--gold",
            str(f["gold"]),
            "--points-out",
            str(link),
            "-q",
        ],
        f["dir"],
        "link.csv",
        "--gold",
    )


def test_segment_table_view_refuse_outputs_onto_inputs(capsys, files) -> None:
    f = files
    _refused(
        capsys,
        ["segment", str(f["sweep"]), "-o", str(f["sweep"]), "-q"],
        f["dir"],
        "-o",
        "input SWEEP",
    )
    png = f["dir"] / "shot.png"
    png.write_bytes(b"\x89PNG not really")
    _refused(
        capsys,
        ["table", str(f["sweep"]), "--gold", str(f["gold"]), "--plot", str(f["gold"]), "-q"],
        f["dir"],
        "--plot",
        "input --gold",
    )
    _refused(
        capsys,
        ["view", str(f["surface"]), "--gold", str(png), "--screenshot", str(png), "-q"],
        f["dir"],
        "--screenshot",
        "input --gold",
    )


def test_check_distinct_paths_unit(tmp_path: Path) -> None:
    a, b = tmp_path / "a.csv", tmp_path / "b.csv"
    a.write_text("1,2,3\n")
    os.link(a, b)  # a hard link is the same file under another name
    with pytest.raises(BoneUSReconError, match="would overwrite the input --gold"):
        check_distinct_paths(inputs={"--gold": a}, outputs={"--points-out": b})
    # Options not given (None) and distinct paths pass; plain iterables are accepted.
    check_distinct_paths(
        inputs={"--gold": a, "--calibration": None},
        outputs={"-o": tmp_path / "s.vtp", "--points-out": None},
        output_folders={"--report": tmp_path / "rep"},
    )
    with pytest.raises(BoneUSReconError, match="same path"):
        check_distinct_paths(outputs=[tmp_path / "x.vtp", tmp_path / "sub" / ".." / "x.vtp"])
    with pytest.raises(BoneUSReconError, match="inside the folder --report"):
        check_distinct_paths(
            inputs={"SWEEP": tmp_path / "r" / "s.mha"}, output_folders={"--report": tmp_path / "r"}
        )


def test_demo_refuses_a_folder_of_other_files_unless_forced(capsys, tmp_path: Path) -> None:
    out = tmp_path / "mine"
    out.mkdir()
    (out / "sweep.mha").write_text("my own recording\n")
    (out / "gold.csv").write_text("1,2,3\n")
    _refused(
        capsys,
        ["demo", str(out), "--frames", "30", "--size", "128x96", "--no-table", "--no-report", "-q"],
        tmp_path,
        "mine",
        "--force",
    )
    # --report onto OUTDIR, or around it, is refused before any work too.
    _refused(
        capsys,
        ["demo", str(tmp_path / "new"), "--report", str(tmp_path / "new"), "-q"],
        tmp_path,
        "--report",
    )
    _refused(
        capsys,
        ["demo", str(tmp_path / "new"), "--report", str(tmp_path), "-q"],
        tmp_path,
        "OUTDIR",
        "inside the folder --report",
    )


@pytest.mark.parametrize("force", [False, True])
def test_demo_rewrites_its_own_folder_and_forced_ones(capsys, tmp_path: Path, force: bool) -> None:
    out = tmp_path / "d"
    argv = [
        "demo",
        str(out),
        "--frames",
        "30",
        "--size",
        "128x96",
        "--no-table",
        "--no-report",
        "-q",
        "--json",
    ]
    if force:
        out.mkdir()
        (out / "notes.txt").write_text("kept\n")
        assert main([*argv, "--force"]) == 0
        assert (out / "notes.txt").read_text() == "kept\n"
    else:
        assert main(argv) == 0
        assert main(argv) == 0, capsys.readouterr().err  # an earlier demo's folder
    assert (out / "sweep.mha").stat().st_size > 0 and (out / ".bone-us-recon-demo").exists()

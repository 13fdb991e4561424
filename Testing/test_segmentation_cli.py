"""``bone-us-recon segment``: outputs, overlays and one-line refusals of bad input."""

from __future__ import annotations

import os

import pytest
from test_segmentation import analytic_sweep

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.sequence_io import write_sweep
from BoneUSRecon.Logic.vtkio import read_polydata


@pytest.fixture(scope="module")
def sweep_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("seg")
    return write_sweep(analytic_sweep(8, no_bone=(3,)), d / "sweep.mha")


@pytest.fixture(scope="module")
def black_file(tmp_path_factory):
    d = tmp_path_factory.mktemp("segblack")
    return write_sweep(analytic_sweep(3, black=True), d / "black.mha")


def test_segment_writes_points_and_overlays(sweep_file, tmp_path, capsys):
    out = tmp_path / "pts.vtp"
    ov = tmp_path / "ov"
    assert main(["segment", str(sweep_file), "-o", str(out), "--overlay", str(ov), "-q"]) == 0
    pd = read_polydata(out)
    assert pd.GetNumberOfPoints() > 100
    for name in ("Frame", "Intensity", "Confidence"):
        assert pd.GetPointData().GetArray(name) is not None
    pngs = sorted(p.name for p in ov.glob("*.png"))
    assert pngs == [f"frame_{k:04d}.png" for k in range(8)]
    text = capsys.readouterr().out
    # Frame 3 has no bone, only the analytic frame's faint fascia at 3 mm: it is off the
    # track ("jump from neighbouring frames") or has no candidate ("no bone found").
    assert "rejected" in text
    assert "jump from neighbouring frames" in text or "no bone found" in text


def test_segment_json_and_snake(sweep_file, tmp_path, capsys):
    import json

    out = tmp_path / "pts.ply"
    assert main(["segment", str(sweep_file), "-o", str(out), "--segmenter", "snake", "--json"]) == 0
    s = json.loads(capsys.readouterr().out)
    assert s["method"] == "snake" and s["accepted"] >= 1 and "3" in s["rejected_frames"]
    assert out.exists()


@pytest.mark.parametrize(
    "case, message",
    [
        ("missing", "no such file"),
        ("extension", "unknown output extension"),
        ("folder", "does not exist"),
        ("black", "no bone contour found in any frame"),
    ],
)
def test_segment_refuses_bad_input(case, message, sweep_file, black_file, tmp_path, capsys):
    src, out = str(sweep_file), tmp_path / "pts.vtp"
    if case == "missing":
        src = str(tmp_path / "nope.mha")
    elif case == "extension":
        out = tmp_path / "pts.xyz"
    elif case == "folder":
        out = tmp_path / "missing" / "pts.vtp"
    elif case == "black":
        src = str(black_file)
    assert main(["segment", src, "-o", str(out), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bone-us-recon: error:") and message in err[0]
    assert not out.exists()
    assert not [p for p in os.listdir(tmp_path) if p.startswith(".")]  # no temp leftovers


def test_cli_segmenter_names_match_logic():
    from BoneUSRecon.cli.segment import SEGMENTER_NAMES
    from BoneUSRecon.Logic.segmentation import SEGMENTERS

    assert sorted(SEGMENTER_NAMES) == sorted(SEGMENTERS)

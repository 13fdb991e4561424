"""``bone-us-recon info``: the summary it prints, and its refusals of bad input."""

from __future__ import annotations

import json
import os
import subprocess
import sys

import numpy as np
import pytest
from test_sequence_io import (
    BAD_NAMES,
    REAL_MHA,
    REAL_XML,
    N,
    bad_case,
    image_to_probe,
    make_file,
    simple_sweep,
    tracked_transforms,
    write_xml,
)

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.sequence_io import read_sweep, write_sweep


def run_cli(capsys, *argv):
    status = main(["info", *map(str, argv)])
    out = capsys.readouterr()
    return status, out.out, out.err


def test_info_json_matches_the_sweep(tmp_path, capsys):
    valid = np.array([True, True, False, True, True, True])
    sweep = simple_sweep(valid=valid)
    path = write_sweep(sweep, tmp_path / "s.mha")
    status, out, err = run_cli(capsys, path, "--json")
    assert status == 0 and err == ""
    info = json.loads(out)
    assert info["frames"] == N and info["valid_frames"] == 5
    assert (info["width"], info["height"]) == (sweep.width, sweep.height)
    assert info["transform"] == "ImageToReference"
    assert info["invalid_frames"] == {"2": "ImageToReference status INVALID"}
    # Spacing from the column norms of the poses (0.2 and 0.3 mm), not ElementSpacing.
    assert info["spacing_mm"] == pytest.approx([0.2, 0.3])
    # Bounds by hand: the four image corners of every valid frame through its pose.
    w, h = sweep.width - 1, sweep.height - 1
    corners = np.array([[0, 0, 0, 1], [w, 0, 0, 1], [w, h, 0, 1], [0, h, 0, 1]], float)
    pts = np.concatenate([(m @ corners.T).T[:, :3] for m in sweep.image_to_reference[valid]])
    expected = np.column_stack([pts.min(0), pts.max(0)]).ravel()
    assert info["bounds_mm"] == pytest.approx(expected.tolist())
    assert info["duration_s"] == pytest.approx(0.75)
    centre = np.array([w / 2, h / 2, 0, 1])
    c = np.array([(m @ centre)[:3] for m in sweep.image_to_reference[valid]])
    assert info["sweep_length_mm"] == pytest.approx(
        np.linalg.norm(np.diff(c, axis=0), axis=1).sum()
    )


def test_info_text(tmp_path, capsys):
    t = tracked_transforms()
    path = make_file(tmp_path / "s.mha", transforms=t, statuses={"ProbeToTracker": {0: "MISSING"}})
    xml = write_xml(tmp_path / "c.xml", image_to_probe())
    status, out, err = run_cli(capsys, path, "--calibration", xml, "-q")
    assert status == 0 and err == ""
    lines = {ln.split(":")[0].strip(): ln.split(":", 1)[1].strip() for ln in out.splitlines()[1:]}
    assert lines["frames"] == str(N) and lines["valid frames"] == str(N - 1)
    assert lines["spacing"] == "0.2 x 0.2 mm/px"
    assert lines["transform"] == "inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe"
    assert "frame 0: ProbeToTracker status MISSING" in lines["invalid frames"]
    for key in ("width x height", "sweep length", "duration", "bounds"):
        assert key in lines
    # --transform picks another chain.
    status, out, _ = run_cli(
        capsys, path, "--calibration", xml, "--transform", "ImageToTracker", "--json"
    )
    assert json.loads(out)["transform"] == "ProbeToTracker * ImageToProbe"


def test_info_real_recording(capsys):
    status, out, _ = run_cli(capsys, REAL_MHA, "--calibration", REAL_XML, "--json")
    info = json.loads(out)
    assert status == 0
    assert (info["frames"], info["valid_frames"], info["width"], info["height"]) == (
        21,
        21,
        820,
        616,
    )
    assert info["spacing_mm"] == pytest.approx([0.085, 0.085], abs=0.001)
    s = read_sweep(REAL_MHA, calibration=REAL_XML)
    assert info["bounds_mm"] == pytest.approx(s.bounds_mm().tolist())
    assert info["bounds_mm"][1] - info["bounds_mm"][0] > 40  # a 70 x 52 mm image, tilted


def test_info_names_the_options_the_logic_message_is_about(tmp_path, capsys):
    # The Logic says "a calibration (ImageToProbe) file" and "the pose"; the CLI adds
    # the option that gives each.
    path = make_file(tmp_path / "s.mha", transforms=tracked_transforms())
    status, _, err = run_cli(capsys, path, "-q")
    assert status == 2
    assert err.rstrip().endswith("give a calibration (ImageToProbe) file (--calibration XML)")
    status, _, err = run_cli(capsys, path, "-q", "--transform", "reference")
    assert status == 2
    assert err == (
        f"bone-us-recon: error: {path}: the pose 'reference' is not a transform "
        "name like ImageToReference (--transform)\n"
    )


@pytest.mark.parametrize("name", BAD_NAMES)
def test_info_bad_input_one_line_exit_2(tmp_path, capsys, name):
    path, kw, match = bad_case(tmp_path, name)
    argv = [path]
    if "calibration" in kw:
        argv += ["--calibration", kw["calibration"]]
    before = set(os.listdir(tmp_path))
    status, out, err = run_cli(capsys, *argv)
    assert status == 2
    assert out == ""
    assert err.endswith("\n") and err.count("\n") == 1, err
    line = err.strip().rsplit("\r", 1)[-1]  # (a progress bar may have been erased with \r)
    assert line.startswith("bone-us-recon: error: ")
    named = kw.get("calibration") if "calibration" in name else path
    assert os.fspath(named) in line
    assert "Traceback" not in err
    assert set(os.listdir(tmp_path)) == before  # nothing written


def test_info_bad_input_quiet_is_exactly_the_error(tmp_path, capsys):
    path, _, _ = bad_case(tmp_path, "truncated data")
    status, out, err = run_cli(capsys, path, "-q")
    assert status == 2
    assert err.startswith("bone-us-recon: error: ") and err.count("\n") == 1
    assert "truncated data" in err and "\r" not in err


def test_info_as_a_process(tmp_path):
    """The real entry point: exit status 2 and a single stderr line, no traceback."""
    path, _, _ = bad_case(tmp_path, "corrupt zlib")
    r = subprocess.run(
        [sys.executable, "-m", "BoneUSRecon", "info", str(path)],
        capture_output=True,
        cwd=os.fspath(tmp_path),
    )
    assert r.returncode == 2 and r.stdout == b""
    # Bytes, not text: text mode would turn a progress bar's \r into line breaks.
    assert r.stderr.count(b"\n") == 1 and b"Traceback" not in r.stderr
    line = r.stderr.strip().rsplit(b"\r", 1)[-1].decode()
    assert line.startswith("bone-us-recon: error: ")
    assert "corrupt compressed (zlib) data" in line

"""The error and interruption contract every sub-command shares."""

from __future__ import annotations

import argparse
import subprocess
import sys

import pytest

from BoneUSRecon.cli import build_parser, main
from BoneUSRecon.cli.common import ProgressBar, run_guarded
from BoneUSRecon.Logic.errors import BoneUSReconError


def _run(func, capsys, **kw):
    status = run_guarded(func, argparse.Namespace(**kw))
    return status, capsys.readouterr()


def test_bad_input_is_one_line_exit_2(capsys):
    def f(args):
        raise BoneUSReconError("DimSize disagrees\nwith the data", "/d/s.mha")

    status, out = _run(f, capsys)
    assert status == 2
    assert out.err == "bone-us-recon: error: /d/s.mha: DimSize disagrees with the data\n"
    assert out.out == ""


def test_interrupt_exit_130(capsys):
    def f(args):
        raise KeyboardInterrupt

    status, out = _run(f, capsys)
    assert status == 130 and "interrupted" in out.err and "Traceback" not in out.err


def test_os_error_one_line(capsys):
    def f(args):
        raise PermissionError(13, "Permission denied", "/root/x.vtp")

    status, out = _run(f, capsys)
    assert status == 2
    assert out.err.strip() == "bone-us-recon: error: /root/x.vtp: Permission denied"


def test_internal_error_one_line_unless_debug(capsys):
    def f(args):
        raise ZeroDivisionError("oops")

    status, out = _run(f, capsys, debug=False)
    assert status == 1 and len(out.err.strip().splitlines()) == 1
    status, out = _run(f, capsys, debug=True)
    assert "Traceback" in out.err


def test_progress_bar_quiet_is_silent(capsys):
    with ProgressBar(quiet=True) as bar:
        bar("segment", 1, 10)
    assert capsys.readouterr().err == ""
    with ProgressBar() as bar:  # stderr is not a terminal under capsys
        bar("segment", 1, 3)
    assert capsys.readouterr().err == ""
    with ProgressBar(force=True) as bar:
        for k in range(3):
            bar("segment", k + 1, 3)
    assert "segment" in capsys.readouterr().err


def test_help_and_unknown_command():
    assert build_parser().prog == "bone-us-recon"
    with pytest.raises(SystemExit) as e:
        main(["no-such-command"])
    assert e.value.code == 2


def test_python_dash_m_entry_point():
    r = subprocess.run(
        [sys.executable, "-m", "BoneUSRecon", "--version"], capture_output=True, text=True
    )
    assert r.returncode == 0 and r.stdout.startswith("bone-us-recon ")


def test_parser_start_up_loads_no_numerics():
    # Building the parser (what ``--help`` and every command's start-up do) must not
    # import numpy, scipy or VTK: that cost ~1 s before any work. The check can fail:
    # the control import of the simulator does load them.
    code = (
        "import sys\n"
        "from BoneUSRecon.cli import build_parser\n"
        "build_parser()\n"
        "heavy = sorted(m for m in ('numpy', 'scipy', 'vtkmodules', 'skimage', 'SimpleITK') "
        "if m in sys.modules)\n"
        "import BoneUSRecon.Logic.simulation.core\n"
        "print(heavy, 'numpy' in sys.modules)\n"
    )
    r = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert r.returncode == 0, r.stderr[-2000:]
    assert r.stdout.strip() == "[] True"


def test_simulate_help_defaults_match_the_simulator():
    # The simulate and demo parsers take the bones and defaults from the light
    # simulation.params; what they show must be the simulator's own.
    from BoneUSRecon.Logic.simulation import BONES, SimulationParams
    from BoneUSRecon.Logic.simulation.bones import BONE_SPECS

    parser = build_parser()
    a = parser.parse_args(["simulate", "ulna", "out"])
    d = SimulationParams()
    assert tuple(BONES) == tuple(BONE_SPECS)
    width, height = (int(v) for v in a.size.split("x"))  # --size WxH (issue 12)
    assert {
        "n_frames": a.frames,
        "width": width,
        "height": height,
        "spacing_mm": a.spacing,
        "seed": a.seed,
    } == {k: getattr(d, k) for k in ("n_frames", "width", "height", "spacing_mm", "seed")}
    with pytest.raises(SystemExit):
        parser.parse_args(["demo", "--bone", "femur"])
    assert parser.parse_args(["demo", "--bone", BONES[0]]).bone == BONES[0]


def test_shared_summary_rows():
    from types import SimpleNamespace

    from BoneUSRecon.cli.common import (
        evaluation_rows,
        json_default,
        parse_size,
        reconstruction_rows,
    )

    s = {
        "segmented_frames": 30,
        "valid_frames": 38,
        "frames": 40,
        "rejected_frames": 8,
        "fit_rejected_frames": [3, 9],
        "grid_shape": (30, 15),
        "grid_coverage": 0.987,
    }
    assert reconstruction_rows(s) == [
        ("frames used", "30 of 38 valid (40 in file)"),
        ("frames rejected", "8 by segmentation, 2 by the robust fit"),
        ("grid", "30 slices x 15 rays, 98.7% covered"),
    ]
    ev = SimpleNamespace(
        n=5,
        mean=1.25,
        rms=1.5,
        median=1.0,
        p95=2.5,
        max=3.0,
        within_0_5=0.2,
        within_1=0.4,
        within_2=0.8,
    )
    rows = dict(evaluation_rows(ev, " (paper)"))
    assert rows["distance mean/RMS"] == "1.250 / 1.500 mm (paper)"
    assert rows["within 0.5/1/2 mm"] == "20.0% / 40.0% / 80.0%"
    import numpy as np

    assert json_default(np.arange(3)) == [0, 1, 2] and json_default(np.float32(0.5)) == 0.5
    assert parse_size("320X256") == (320, 256)
    with pytest.raises(BoneUSReconError, match="must look like 1100x700"):
        parse_size("big")

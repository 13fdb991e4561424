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

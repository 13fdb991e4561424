"""One spelling per option across commands, notes on ignored input, tidy JSON
(issue 12, item 7).

* Image sizes are ``--size WxH`` in demo, simulate and view (simulate's ``--width`` and
  ``--height`` still work, hidden); control points are ``--along E`` and ``--around F``
  in reconstruct and table (``--control-points`` still works, hidden).
* ``--calibration`` given for a sweep whose poses do not use it prints one note.
* A plain 3D image is refused without suggesting ``--calibration``.
* JSON floats are printed as people write them (0.15, not 0.15000000000000002).
"""

from __future__ import annotations

import argparse
import json
import re
from pathlib import Path

import numpy as np
import pytest
from conftest import REAL_XML

from BoneUSRecon.cli import build_parser, main
from BoneUSRecon.cli.reconstruct import params_from_args
from BoneUSRecon.Logic.sequence_io import write_sweep


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _shown_options(p: argparse.ArgumentParser) -> set[str]:
    return {o for a in p._actions if a.help != argparse.SUPPRESS for o in a.option_strings}


def test_one_spelling_for_sizes_and_control_points() -> None:
    subs = _subparsers()
    for name, p in subs.items():
        shown = _shown_options(p)
        assert not {"--width", "--height"} & shown, name
        assert "--control-points" not in shown, name
    for name in ("demo", "simulate", "view"):
        assert "--size" in _shown_options(subs[name]), name
    for name in ("reconstruct", "table"):
        assert {"--along", "--around"} <= _shown_options(subs[name]), name


def test_old_spellings_still_work_and_agree() -> None:
    subs = _subparsers()
    p = subs["reconstruct"]
    new = params_from_args(p.parse_args(["s.mha", "-o", "x.vtp", "--along", "12", "--around", "7"]))
    old = params_from_args(p.parse_args(["s.mha", "-o", "x.vtp", "--control-points", "12", "7"]))
    assert new == old and new.fit.n_control_points == (12, 7)
    only_along = params_from_args(p.parse_args(["s.mha", "-o", "x.vtp", "--along", "9"]))
    assert only_along.fit.n_control_points == (9, 6)
    t = subs["table"]
    assert t.parse_args(["s", "--gold", "g", "--along", "5", "10"]).counts == [5, 10]
    assert t.parse_args(["s", "--gold", "g", "--control-points", "5", "10"]).counts == [5, 10]


def test_simulate_size_and_hidden_width_height(tmp_path: Path, capsys) -> None:
    base = ["simulate", "clavicle", "--frames", "12", "-q", "--json"]
    assert main([*base[:2], str(tmp_path / "a"), *base[2:], "--size", "96x80"]) == 0
    doc = json.loads(capsys.readouterr().out)
    assert (doc["width"], doc["height"]) == (96, 80)
    assert (
        main([*base[:2], str(tmp_path / "b"), *base[2:], "--width", "100", "--height", "96"]) == 0
    )
    doc = json.loads(capsys.readouterr().out)
    assert (doc["width"], doc["height"]) == (100, 96)
    assert main([*base[:2], str(tmp_path / "c"), *base[2:], "--size", "96by80"]) == 2
    assert "--size must look like" in capsys.readouterr().err


@pytest.fixture(scope="module")
def sim_file(sim_small, tmp_path_factory: pytest.TempPathFactory) -> Path:
    return write_sweep(sim_small.sweep, tmp_path_factory.mktemp("spell") / "s.mha")


def test_unused_calibration_gives_one_note(sim_file: Path, capsys) -> None:
    assert main(["info", str(sim_file), "--calibration", str(REAL_XML), "-q"]) == 0
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("bone-us-recon: note: ")
    assert "--calibration not used" in err[0] and "ImageToReference" in err[0]
    assert main(["info", str(sim_file), "-q"]) == 0
    assert capsys.readouterr().err == ""


def test_used_calibration_gives_no_note(capsys) -> None:
    from conftest import REAL_MHA

    assert main(["info", str(REAL_MHA), "--calibration", str(REAL_XML), "-q"]) == 0
    assert "note" not in capsys.readouterr().err


def test_plain_3d_image_is_not_told_to_add_a_calibration(tmp_path: Path, capsys) -> None:
    import SimpleITK as sitk

    vol = tmp_path / "volume.mha"
    sitk.WriteImage(sitk.GetImageFromArray(np.zeros((8, 16, 16), np.uint8)), str(vol))
    for extra in ([], ["--calibration", str(REAL_XML)]):
        assert main(["info", str(vol), *extra, "-q"]) == 2
        err = capsys.readouterr().err.strip()
        assert len(err.splitlines()) == 1 and "volume.mha" in err
        assert "plain image" in err and "not a tracked sweep" in err
        assert "--calibration" not in err


def test_json_floats_are_rounded(sim_factory, tmp_path: Path, capsys) -> None:
    # 0.15 mm pixels: the poses give 0.15000000000000002 back before rounding.
    sim = sim_factory(spacing_mm=0.15, n_frames=12, width=96, height=80)
    path = write_sweep(sim.sweep, tmp_path / "s.mha")
    assert main(["info", str(path), "--json", "-q"]) == 0
    out = capsys.readouterr().out
    assert json.loads(out)["spacing_mm"] == [0.15, 0.15]
    assert not re.search(r"\d\.\d*(0{6,}|9{6,})\d", out), out

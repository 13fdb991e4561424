"""All sub-commands share one style: option names, help, summary and error contract."""

from __future__ import annotations

import argparse

import numpy as np
import pytest

from BoneUSRecon.cli import COMMANDS, build_parser, main
from BoneUSRecon.Logic.vtkio import read_points, write_points


def _subparsers() -> dict[str, argparse.ArgumentParser]:
    parser = build_parser()
    action = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    return dict(action.choices)


def _options(p: argparse.ArgumentParser) -> dict[str, argparse.Action]:
    return {s: a for a in p._actions for s in a.option_strings}


def test_every_command_shares_quiet_debug_and_one_json_help():
    subs = _subparsers()
    assert set(subs) == set(COMMANDS)
    json_helps = set()
    for name, p in subs.items():
        opts = _options(p)
        assert {"-q", "--quiet", "--debug"} <= set(opts), name
        if "--json" in opts:
            json_helps.add(opts["--json"].help)
    assert json_helps == {"print one JSON object instead of the summary"}


def test_commands_reading_a_sweep_take_calibration_and_transform():
    for name, p in _subparsers().items():
        opts = _options(p)
        positional = [a.metavar for a in p._actions if not a.option_strings]
        if "SWEEP" in positional or "--sweep" in opts:
            assert {"--calibration", "--transform"} <= set(opts), name
        if "--output" in opts:
            assert "-o" in opts, name


def test_corrupted_fraction_has_one_name_everywhere():
    for name in ("simulate", "demo"):
        opts = _options(_subparsers()[name])
        assert {"--corrupted", "--corrupt"} <= set(opts), name
        assert opts["--corrupted"] is opts["--corrupt"]


def test_write_points_formats(tmp_path):
    from BoneUSRecon.Logic.vtkio import points_to_polydata

    pts = np.random.default_rng(0).normal(size=(25, 3)) * 10
    pd = points_to_polydata(pts, {"Frame": np.arange(25)})
    for ext in (".vtp", ".vtk", ".ply", ".csv"):
        out = write_points(pd, tmp_path / f"p{ext}")
        np.testing.assert_allclose(read_points(out), pts, atol=1e-5)
    # An STL holds triangles only: a point cloud would be written empty, so it is refused.
    from BoneUSRecon.Logic.errors import BoneUSReconError

    with pytest.raises(BoneUSReconError, match="unknown output extension"):
        write_points(pd, tmp_path / "p.stl")
    assert sorted(p.suffix for p in tmp_path.iterdir()) == [".csv", ".ply", ".vtk", ".vtp"]


def test_segment_writes_csv_and_refuses_stl(capsys, sim_small, tmp_path):
    from BoneUSRecon.Logic.sequence_io import write_sweep

    sweep = write_sweep(sim_small.sweep, tmp_path / "s.mha")
    assert main(["segment", str(sweep), "-o", str(tmp_path / "p.stl"), "-q"]) == 2
    err = capsys.readouterr().err
    assert err.startswith("bone-us-recon: error:") and "'.stl'" in err
    assert main(["segment", str(sweep), "-o", str(tmp_path / "p.csv"), "-q"]) == 0
    capsys.readouterr()
    pts = read_points(tmp_path / "p.csv")
    # Points on the simulated bone, in reference millimetres: near the gold points.
    from scipy.spatial import cKDTree

    d, _ = cKDTree(sim_small.gold).query(pts)
    assert len(pts) > 100 and np.median(d) < 1.0
    assert sorted(p.name for p in tmp_path.iterdir()) == ["p.csv", "s.mha"]


def test_cli_and_slicer_module_build_the_same_parameters():
    # Both go through Logic.pipeline.params_with: same values, same refusals.
    from dataclasses import asdict

    from BoneSurfaceReconstructionLib.parameters import parameters_from_widget_values
    from BoneUSRecon.cli.reconstruct import params_from_args
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.pipeline import params_with

    args = build_parser().parse_args(
        [
            "reconstruct",
            "s.mha",
            "-o",
            "b.vtp",
            "--segmenter",
            "snake",
            "--degree",
            "3",
            "1",
            "--control-points",
            "10",
            "4",
            "--rays",
            "21",
            "--flank-extension",
            "2.5",
        ]
    )
    cli = params_from_args(args)
    module = parameters_from_widget_values(
        {
            "segmenter": "snake",
            "degreeU": 3,
            "degreeV": 1,
            "controlPointsU": 10,
            "controlPointsV": 4,
            "rays": 21,
            "flankExtension": 2.5,
        }
    )
    assert asdict(cli) == asdict(module)
    assert (
        cli.segmentation.method,
        cli.fit.degree,
        cli.fit.n_control_points,
        cli.resampling.n_rays,
        cli.surface.flank_extension_mm,
    ) == ("snake", (3, 1), (10, 4), 21, 2.5)
    assert asdict(params_with()) != asdict(cli)
    for kw, match in [
        ({"segmenter": "magic"}, "unknown segmenter 'magic'"),
        ({"n_control_points": (3, 5), "degree": (3, 2)}, "too few"),
        ({"rays": 0}, "at least 2 rays"),
        ({"flank_extension_mm": -1}, "flank_extension_mm must be >= 0"),
    ]:
        with pytest.raises(BoneUSReconError, match=match):
            params_with(**kw)

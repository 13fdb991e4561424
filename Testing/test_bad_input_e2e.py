"""Bad input, end to end, for every command (issue 7, section 1).

Each case runs a real command line and checks the contract of
:mod:`BoneUSRecon.cli.common`: exit status 2, exactly one line on stderr of the form
``bone-us-recon: error: <file>: <problem>`` naming the offending file (or option) and
the problem, no traceback, and nothing left in the output folder (neither the output
nor a temporary ``.part`` file).

Bad sweeps are derived from the shared small simulation (40 frames of 128 x 160 px):
frames all black, pure noise, a probe held still (all poses equal, or jittering by
0.05 mm), too few frames, too few tracked frames.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.sequence_io import write_sweep
from BoneUSRecon.Logic.sweep import Sweep
from BoneUSRecon.Logic.vtkio import write_points_csv

#: A place even root cannot write (chmod does not stop root; sysfs does).
UNWRITABLE = Path("/sys")


@pytest.fixture(scope="module")
def bad(sim_small, tmp_path_factory) -> dict[str, Path]:
    """Input files, good and bad, in a read-only-by-convention folder."""
    d = tmp_path_factory.mktemp("bad_inputs")
    s = sim_small.sweep
    n = s.n_frames
    rng = np.random.default_rng(7)
    m = s.image_to_reference
    files: dict[str, Path] = {}

    def put(name: str, sweep: Sweep) -> None:
        files[name] = write_sweep(sweep, d / f"{name}.mha")

    put("good", s)
    put("black", s.replace(frames=np.zeros_like(s.frames)))
    put("noise", s.replace(frames=rng.integers(0, 256, s.frames.shape, dtype=np.uint8)))
    # Probe held still: every frame has the pose of the middle one (the images still
    # show bone, so segmentation succeeds and only the geometry is degenerate).
    still = np.repeat(m[n // 2][None], n, axis=0)
    put("still", s.replace(image_to_reference=still))
    jitter = still.copy()
    jitter[:, :3, 3] += rng.normal(0.0, 0.05, (n, 3))  # tracking noise, 0.05 mm
    put("jitter", s.replace(image_to_reference=jitter))
    # Four frames spread over the whole sweep: it moves, but 4 slices cannot carry the
    # 15 control points along the bone.
    k = np.linspace(0, n - 1, 4).astype(int)
    put("four", Sweep(s.frames[k].copy(), m[k].copy(), s.timestamps[k].copy(), s.valid[k].copy()))
    valid = np.zeros(n, bool)
    valid[[0, n - 1]] = True  # only two tracked frames
    put("two_tracked", s.replace(valid=valid))
    files["gold"] = write_points_csv(sim_small.gold, d / "gold.csv")
    (d / "garbage.mha").write_text("this is not a sequence file\n")
    files["garbage"] = d / "garbage.mha"
    (d / "header_only.csv").write_text("x,y,z\n")
    files["empty_gold"] = d / "header_only.csv"
    return files


@pytest.fixture(scope="module")
def surface(bad, tmp_path_factory) -> Path:
    """A good reconstructed surface (for evaluate and view)."""
    out = tmp_path_factory.mktemp("bad_surface") / "bone.vtp"
    assert main(["reconstruct", str(bad["good"]), "-o", str(out), "-q"]) == 0
    return out


def refused(capsys, argv: list[str], *, names: str, problem: str, outdir: Path | None) -> str:
    """Run ``argv`` and check the error contract; return the error line."""
    before = sorted(os.listdir(outdir)) if outdir is not None else None
    code = main(argv)
    cap = capsys.readouterr()
    lines = cap.err.strip().splitlines()
    assert code == 2, (code, cap.err)
    assert len(lines) == 1, cap.err
    line = lines[0]
    assert line.startswith("bone-us-recon: error: "), line
    assert "Traceback" not in cap.err and "Traceback" not in cap.out
    assert names in line, f"error does not name {names!r}: {line}"
    assert problem in line, f"error does not say {problem!r}: {line}"
    if outdir is not None:
        assert sorted(os.listdir(outdir)) == before, "output or temporary file left behind"
    return line


# -- sweeps a surface cannot be built from --------------------------------------------

NO_SURFACE = [
    ("black", "no bone contour found"),
    ("noise", "no bone contour found"),
    ("still", "the probe does not move"),
    ("jitter", "the probe does not move"),
    ("two_tracked", "only 2 slices with a bone contour"),
]


@pytest.mark.parametrize(("name", "problem"), NO_SURFACE)
def test_reconstruct_refuses_sweeps_without_a_surface(capsys, bad, tmp_path, name, problem):
    refused(
        capsys,
        [
            "reconstruct",
            str(bad[name]),
            "-o",
            str(tmp_path / "s.vtp"),
            "--points-out",
            str(tmp_path / "p.vtp"),
            "-q",
        ],
        names=f"{name}.mha",
        problem=problem,
        outdir=tmp_path,
    )


@pytest.mark.parametrize(("name", "problem"), [NO_SURFACE[0], NO_SURFACE[2], NO_SURFACE[4]])
def test_table_refuses_sweeps_without_a_surface(capsys, bad, tmp_path, name, problem):
    refused(
        capsys,
        [
            "table",
            str(bad[name]),
            "--gold",
            str(bad["gold"]),
            "--plot",
            str(tmp_path / "t.png"),
            "-q",
        ],
        names=f"{name}.mha",
        problem=problem,
        outdir=tmp_path,
    )


def test_four_frames_are_fitted_with_fewer_control_points(capsys, bad, tmp_path):
    # The default 15 control points along are a ceiling a short sweep lowers, with a
    # warning; 14 asked for are fitted as asked or refused; Table I's rows are as asked.
    out = tmp_path / "b.vtp"
    assert main(["reconstruct", str(bad["four"]), "-o", str(out), "-q"]) == 0
    assert out.exists()
    assert "control points, not 15 x 6" in capsys.readouterr().err
    refused(
        capsys,
        ["reconstruct", str(bad["four"]), "-o", str(tmp_path / "c.vtp"), "--along", "14"],
        names="four.mha",
        problem="too few valid grid points for 14 x 6",
        outdir=tmp_path,
    )
    refused(
        capsys,
        ["table", str(bad["four"]), "--gold", str(bad["gold"]), "-q"],
        names="four.mha",
        problem="too few valid grid points for 5 x 6",
        outdir=tmp_path,
    )


@pytest.mark.parametrize("name", ["black", "noise"])
def test_segment_refuses_sweeps_without_bone(capsys, bad, tmp_path, name):
    refused(
        capsys,
        [
            "segment",
            str(bad[name]),
            "-o",
            str(tmp_path / "p.vtp"),
            "--overlay",
            str(tmp_path / "ov"),
            "-q",
        ],
        names=f"{name}.mha",
        problem="no bone contour found",
        outdir=tmp_path,
    )


def test_segment_and_info_accept_a_still_probe(capsys, bad, tmp_path):
    """Segmenting and describing a still sweep is fine: only a surface needs motion."""
    assert main(["segment", str(bad["still"]), "-o", str(tmp_path / "p.vtp"), "-q"]) == 0
    assert main(["info", str(bad["still"]), "--json"]) == 0
    assert '"sweep_length_mm": 0.0' in capsys.readouterr().out


@pytest.mark.parametrize("command", ["info", "segment", "reconstruct", "table"])
def test_every_sweep_reader_refuses_garbage_and_missing_files(capsys, bad, tmp_path, command):
    extra = {
        "info": [],
        "segment": ["-o", str(tmp_path / "p.vtp")],
        "reconstruct": ["-o", str(tmp_path / "s.vtp")],
        "table": ["--gold", str(bad["gold"])],
    }[command]
    refused(
        capsys,
        [command, str(bad["garbage"]), *extra, "-q"],
        names="garbage.mha",
        problem="not a MetaIO metafile",
        outdir=tmp_path,
    )
    refused(
        capsys,
        [command, str(tmp_path / "missing.mha"), *extra, "-q"],
        names="missing.mha",
        problem="no such file",
        outdir=tmp_path,
    )


# -- awkward but valid sweeps: refused by nothing, reconstructed as well as a clean one --


@pytest.mark.parametrize("kind", ["retraced", "repeated_poses", "paused"])
def test_awkward_sweeps_reconstruct_accurately(capsys, sim_small, tmp_path, kind):
    """A sweep retraced over the same poses, every pose recorded twice (a tracker
    slower than the video), and a probe resting (20 frames, 0.05 mm jitter) before it
    moves: all must give the clean sweep's accuracy against the gold points."""
    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.vtkio import read_polydata

    s = sim_small.sweep
    n = s.n_frames
    m = s.image_to_reference
    order = {
        "retraced": np.r_[np.arange(n), np.arange(n)[::-1]],
        "repeated_poses": np.repeat(np.arange(n), 2),
        "paused": np.r_[np.zeros(20, int), np.arange(n)],
    }[kind]
    poses = m[order].copy()
    if kind == "paused":
        poses[:20, :3, 3] += np.random.default_rng(3).normal(0.0, 0.05, (20, 3))
    sweep = s.replace(
        frames=s.frames[order],
        image_to_reference=poses,
        timestamps=np.arange(order.size) * 0.05,
        valid=s.valid[order],
    )
    path = write_sweep(sweep, tmp_path / f"{kind}.mha")
    out = tmp_path / "bone.vtp"
    assert main(["reconstruct", str(path), "-o", str(out), "-q"]) == 0, capsys.readouterr().err
    ev = evaluate_surface(read_polydata(out), sim_small.gold)
    assert ev.mean < 0.3 and ev.within_1 > 0.95, (ev.mean, ev.within_1)


# -- absurd parameters ------------------------------------------------------------------

ABSURD = [
    (["--control-points", "500", "5"], "too few valid grid points for 500 x 5 control points"),
    (["--control-points", "15", "200"], "too few valid grid points for 15 x 200 control points"),
    (["--control-points", "0", "5"], "control points are too few"),
    (["--control-points", "-3", "5"], "control points are too few"),
    (["--degree", "0", "2"], "degree must be at least 1"),
    (["--degree", "2", "-1"], "degree must be at least 1"),
    (["--degree", "20", "2"], "too few for degree 20 2"),
    (["--rays", "0"], "need at least 2 rays"),
    (["--rays", "-4"], "need at least 2 rays"),
    (["--rays", "100000"], "at most 1000 rays per slice"),
    (["--segmenter", "magic"], "unknown segmenter 'magic'"),
]


@pytest.mark.parametrize(
    ("options", "problem"), ABSURD, ids=lambda v: " ".join(v) if isinstance(v, list) else None
)
def test_reconstruct_refuses_absurd_parameters(capsys, bad, tmp_path, options, problem):
    # Parameter errors name the option's values; the ones found on the data name the sweep.
    names = "good.mha" if problem.startswith("too few valid") else problem.split()[0]
    refused(
        capsys,
        ["reconstruct", str(bad["good"]), "-o", str(tmp_path / "s.vtp"), *options, "-q"],
        names=names,
        problem=problem,
        outdir=tmp_path,
    )


@pytest.mark.parametrize(
    ("options", "problem"),
    [
        (["--control-points", "5", "500"], "too few valid grid points for 500 x 6"),
        (["--control-points", "0"], "0 x 6 control points are too few"),
        (["--around", "0"], "15 x 0 control points are too few"),
        (["--degree", "0", "0"], "degree must be at least 1"),
        (["--rays", "0"], "need at least 2 rays"),
    ],
)
def test_table_refuses_absurd_parameters(capsys, bad, tmp_path, options, problem):
    names = "good.mha" if problem.startswith("too few valid") else problem.split()[0]
    refused(
        capsys,
        [
            "table",
            str(bad["good"]),
            "--gold",
            str(bad["gold"]),
            "--plot",
            str(tmp_path / "t.png"),
            *options,
            "-q",
        ],
        names=names,
        problem=problem,
        outdir=tmp_path,
    )


@pytest.mark.parametrize(
    ("options", "problem"),
    [
        (["--frames", "1"], "need at least 2 frames"),
        (["--frames", "-5"], "need at least 2 frames"),
        (["--width", "0"], "at least 16 x 16 pixels"),
        (["--spacing", "0"], "pixel spacing must be a positive"),
        (["--spacing", "-0.3"], "pixel spacing must be a positive"),
        (["--corrupt", "2"], "corrupted fraction must be between 0 and 1"),
        (["--invalid", "-0.1"], "invalid fraction must be between 0 and 1"),
        (["--width", "100000"], "at most 2048 pixels per side"),
        (["--frames", "10000000"], "would need 819.2 GB in memory"),
        (["--bone-free", "10"], "--bone-free must look like FIRST,LAST"),
        (["--bone-free", "0,-2"], "--bone-free frame counts must not be negative"),
        (["--frames", "10", "--bone-free", "5,4"], "bone_free_frames: (5, 4) leaves fewer than 2"),
    ],
)
def test_simulate_refuses_absurd_parameters(capsys, tmp_path, options, problem):
    refused(
        capsys,
        ["simulate", "clavicle", str(tmp_path / "sim"), *options, "-q"],
        names=problem.split()[0],
        problem=problem,
        outdir=tmp_path,
    )


@pytest.mark.parametrize(
    ("options", "problem"),
    [
        (["--frames", "0"], "need at least 2 frames"),
        (["--size", "0x0"], "at least 16 x 16 pixels"),
        (["--size", "abc"], "--size must look like"),
        (["--spacing", "-1"], "pixel spacing must be a positive"),
        (["--corrupted", "3"], "--corrupted must be between"),
        (["--frames", "10000000"], "would need 819.2 GB in memory"),
    ],
)
def test_demo_refuses_absurd_parameters(capsys, tmp_path, options, problem):
    refused(
        capsys,
        ["demo", str(tmp_path / "demo"), *options, "-q"],
        names=problem.split()[0],
        problem=problem,
        outdir=tmp_path,
    )


def test_demo_too_small_to_fit_leaves_no_folder(capsys, tmp_path):
    """Simulated fine, but 2 frames make no surface: OUTDIR is removed."""
    refused(
        capsys,
        [
            "demo",
            str(tmp_path / "demo"),
            "--frames",
            "2",
            "--size",
            "80x64",
            "--spacing",
            "0.6",
            "--no-report",
            "--no-table",
            "-q",
        ],
        names="sweep.mha",
        problem="only 2 slices with a bone contour",
        outdir=tmp_path,
    )


def test_view_refuses_absurd_size(capsys, surface, tmp_path):
    refused(
        capsys,
        ["view", str(surface), "--screenshot", str(tmp_path / "v.png"), "--size", "0x0", "-q"],
        names="--size",
        problem="out of range",
        outdir=tmp_path,
    )


# -- unwritable, missing and unknown outputs ---------------------------------------------


def _output_cases(bad: dict[str, Path], surface: Path, target: Path) -> dict[str, list[str]]:
    """Each command with its output put at ``target`` (a file path)."""
    folder = target.with_suffix("")
    return {
        "segment": ["segment", str(bad["good"]), "-o", str(target.with_suffix(".vtp"))],
        "reconstruct": ["reconstruct", str(bad["good"]), "-o", str(target.with_suffix(".vtp"))],
        "reconstruct --points-out": [
            "reconstruct",
            str(bad["good"]),
            "-o",
            "IGNORED.vtp",
            "--points-out",
            str(target.with_suffix(".vtp")),
        ],
        "reconstruct --report": [
            "reconstruct",
            str(bad["good"]),
            "-o",
            "IGNORED.vtp",
            "--report",
            str(folder),
        ],
        "segment --overlay": [
            "segment",
            str(bad["good"]),
            "-o",
            "IGNORED.vtp",
            "--overlay",
            str(folder),
        ],
        "table --plot": [
            "table",
            str(bad["good"]),
            "--gold",
            str(bad["gold"]),
            "--plot",
            str(target.with_suffix(".png")),
        ],
        "view --screenshot": [
            "view",
            str(surface),
            "--screenshot",
            str(target.with_suffix(".png")),
        ],
        "simulate": [
            "simulate",
            "clavicle",
            str(folder),
            "--frames",
            "10",
            "--width",
            "80",
            "--height",
            "64",
            "--spacing",
            "0.6",
        ],
        "demo": ["demo", str(folder), "--frames", "20", "--size", "80x64", "--spacing", "0.6"],
    }


CASES = [
    "segment",
    "reconstruct",
    "reconstruct --points-out",
    "reconstruct --report",
    "segment --overlay",
    "table --plot",
    "view --screenshot",
    "simulate",
    "demo",
]


def _redirect_ignored(argv: list[str], tmp_path: Path) -> list[str]:
    return [str(tmp_path / "main.vtp") if a == "IGNORED.vtp" else a for a in argv]


@pytest.mark.parametrize("case", CASES)
def test_output_in_unwritable_folder(capsys, bad, surface, tmp_path, case):
    argv = _redirect_ignored(_output_cases(bad, surface, UNWRITABLE / "out.x")[case], tmp_path)
    line = refused(capsys, [*argv, "-q"], names="/sys/out", problem="/sys", outdir=tmp_path)
    assert "writ" in line or "Operation not permitted" in line or "cannot create" in line, line


@pytest.mark.parametrize("case", [c for c in CASES if c not in ("simulate", "demo")])
def test_output_in_missing_folder(capsys, bad, surface, tmp_path, case):
    """(simulate and demo create their OUTDIR with its parents, by design.)"""
    argv = _redirect_ignored(
        _output_cases(bad, surface, tmp_path / "nowhere" / "out.x")[case], tmp_path
    )
    refused(
        capsys,
        [*argv, "-q"],
        names="out",
        problem="'" + str(tmp_path / "nowhere") + "' does not exist",
        outdir=tmp_path,
    )
    assert not (tmp_path / "nowhere").exists()


@pytest.mark.parametrize(
    "argv_fn",
    [
        lambda b, s, t: ["segment", str(b["good"]), "-o", str(t / "p.xyz")],
        lambda b, s, t: ["reconstruct", str(b["good"]), "-o", str(t / "s.xyz")],
        lambda b, s, t: ["reconstruct", str(b["good"]), "-o", str(t / "s")],
        lambda b, s, t: [
            "reconstruct",
            str(b["good"]),
            "-o",
            str(t / "s.vtp"),
            "--points-out",
            str(t / "p.xyz"),
        ],
        lambda b, s, t: [
            "table",
            str(b["good"]),
            "--gold",
            str(b["gold"]),
            "--plot",
            str(t / "t.xyz"),
        ],
        lambda b, s, t: ["view", str(s), "--screenshot", str(t / "v.xyz")],
    ],
    ids=["segment", "reconstruct", "reconstruct-no-suffix", "points-out", "table-plot", "view"],
)
def test_unknown_output_extension(capsys, bad, surface, tmp_path, argv_fn):
    refused(
        capsys,
        [*argv_fn(bad, surface, tmp_path), "-q"],
        names=str(tmp_path),
        problem="unknown output extension",
        outdir=tmp_path,
    )


# -- evaluate and view inputs ----------------------------------------------------------


@pytest.mark.parametrize(
    ("argv", "names", "problem"),
    [
        (["evaluate", "{surface}", "{empty_gold}"], "header_only.csv", "no points"),
        (["evaluate", "{garbage}", "{gold}"], "garbage.mha", "unknown surface format"),
        (["evaluate", "{out}/none.vtp", "{gold}"], "none.vtp", "no such file"),
        (
            ["reconstruct", "{good}", "-o", "{out}/s.vtp", "--gold", "{empty_gold}"],
            "header_only.csv",
            "no points",
        ),
        (
            ["view", "{surface}", "--screenshot", "{out}/v.png", "--gold", "{empty_gold}"],
            "header_only.csv",
            "no points",
        ),
        (
            ["view", "{surface}", "--screenshot", "{out}/v.png", "--sweep", "{garbage}"],
            "garbage.mha",
            "not a MetaIO metafile",
        ),
    ],
    ids=[
        "evaluate-empty-gold",
        "evaluate-garbage-surface",
        "evaluate-missing-surface",
        "reconstruct-empty-gold",
        "view-empty-gold",
        "view-garbage-sweep",
    ],
)
def test_evaluate_and_view_refuse_bad_inputs(capsys, bad, surface, tmp_path, argv, names, problem):
    files = {**{k: str(v) for k, v in bad.items()}, "surface": surface, "out": tmp_path}
    refused(
        capsys,
        [*(a.format(**files) for a in argv), "-q"],
        names=names,
        problem=problem,
        outdir=tmp_path,
    )


# -- the real command line: what a user sees --------------------------------------------


@pytest.mark.parametrize(
    ("argv", "problem"),
    [
        (["reconstruct", "{black}", "-o", "{out}/s.vtp"], "no bone contour found"),
        (["reconstruct", "{still}", "-o", "{out}/s.vtp"], "the probe does not move"),
    ],
)
def test_command_line_process_prints_one_line(bad, tmp_path, argv, problem):
    """A real ``python -m BoneUSRecon`` process (no progress bar, no warnings on stderr)."""
    names = {"black": bad["black"], "still": bad["still"], "out": tmp_path}
    argv = [a.format(**names) for a in argv]
    proc = subprocess.run(
        [sys.executable, "-m", "BoneUSRecon", *argv],
        capture_output=True,
        text=True,
        timeout=120,
        env={**os.environ, "PYTHONWARNINGS": "default"},
    )
    assert proc.returncode == 2, proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and problem in lines[0] and ".mha" in lines[0], proc.stderr
    assert proc.stdout == ""
    assert os.listdir(tmp_path) == []


@pytest.mark.parametrize(
    "argv",
    [
        ["reconstruct", "s.mha", "-o", "s.vtp", "--rays", "abc"],
        ["reconstruct", "s.mha", "-o", "s.vtp", "--degree", "2"],
        ["demo", "--size", "-80x64"],
        ["table", "s.mha", "--gold", "g.csv", "--control-points"],
        ["segment", "s.mha"],
        ["no-such-command"],
    ],
)
def test_argument_errors_are_one_line(capsys, argv):
    """argparse's own refusals follow the same style: one line, exit 2, no usage block."""
    with pytest.raises(SystemExit) as exc:
        main(argv)
    assert exc.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("bone-us-recon") and ": error: " in err[0] and "--help" in err[0], err

"""The register command (and reconstruct --register-to): transforms written in every
format agree with the truth; every bad input is one line, exit 2, nothing written."""

from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np
import pytest

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.registration import rigid_error, transform_points
from BoneUSRecon.Logic.sequence_io import write_sweep
from BoneUSRecon.Logic.transform_io import read_transform, write_transform
from BoneUSRecon.Logic.vtkio import (
    points_to_polydata,
    polydata_points,
    read_polydata,
    triangles_to_polydata,
    write_points_csv,
    write_polydata,
)


def _rigid(axis, deg, shift, centre):
    a = np.asarray(axis, float) / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    t = np.radians(deg)
    m = np.eye(4)
    m[:3, :3] = np.eye(3) + np.sin(t) * k + (1 - np.cos(t)) * k @ k
    m[:3, 3] = centre - m[:3, :3] @ centre + np.asarray(shift, float)
    return m


@pytest.fixture(scope="module")
def files(sim_small, tmp_path_factory):
    """The reconstructed surface, the bone model moved by a known transform, and friends."""
    from BoneUSRecon.Logic.pipeline import reconstruct

    d = tmp_path_factory.mktemp("cli_register")
    rec = reconstruct(sim_small.sweep)
    surf = write_polydata(rec.surface, d / "surface.vtp")
    pts = polydata_points(rec.surface)
    truth = _rigid([0.2, 0.5, 1.0], 10.0, [6.0, -5.0, 6.0], pts.mean(0))
    g = sim_small.geometry
    v, f = g.closed_mesh(*g.closed_mesh_params(20_000))
    tv = transform_points(truth, v)
    far = _rigid([1.0, 0.0, 0.3], 100.0, [120.0, 40.0, 0.0], pts.mean(0))
    lm = pts[[10, len(pts) // 2, len(pts) - 10, len(pts) // 3]]
    out = {
        "dir": d,
        "surface": surf,
        "truth": truth,
        "gold": sim_small.gold,
        "model": write_polydata(triangles_to_polydata(tv, f), d / "model.stl"),
        "model_far": write_polydata(
            triangles_to_polydata(transform_points(far, v), f), d / "far.vtp"
        ),
        "far": far,
        "model_m": write_polydata(triangles_to_polydata(tv / 1000.0, f), d / "model_m.ply"),
        "lm_src": write_points_csv(lm, d / "lm_src.csv"),
        "lm_tgt": write_points_csv(transform_points(far, lm) + 0.5, d / "lm_tgt.csv"),
        "lm_two": write_points_csv(lm[:2], d / "lm_two.csv"),
        "points": write_points_csv(polydata_points(rec.points), d / "points.csv"),
        "sweep": write_sweep(sim_small.sweep, d / "sweep.mha"),
    }
    bad_v = np.array([[0.0, 0, 0], [10, 0, 0], [0, 10, 0], [0, 0, 10], [5, 5, 5]])
    out["nonmanifold"] = write_polydata(
        triangles_to_polydata(bad_v, [[0, 1, 2], [0, 1, 3], [0, 1, 4]]), d / "nm.vtp"
    )
    out["cloud"] = write_polydata(points_to_polydata(tv[::50]), d / "cloud.vtp")
    (d / "empty.stl").write_bytes(b"")
    out["empty"] = d / "empty.stl"
    return out


def run(capsys, argv):
    code = main(argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def assert_refused(capsys, argv, match, outdir: Path):
    before = set(os.listdir(outdir))
    code, out, err = run(capsys, [str(a) for a in argv])
    assert code == 2, err
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bone-us-recon: error:"), err
    assert match in lines[0], lines[0]
    assert set(os.listdir(outdir)) == before  # nothing written, no temp files


@pytest.mark.parametrize("ext", [".txt", ".tfm", ".h5"])
def test_register_writes_the_transform_in_each_format(capsys, files, tmp_path, ext) -> None:
    out = tmp_path / f"T{ext}"
    moved = tmp_path / "moved.vtp"
    code, stdout, err = run(
        capsys,
        [
            "register",
            str(files["surface"]),
            str(files["model"]),
            "-o",
            str(out),
            "--registered",
            str(moved),
            "-q",
        ],
    )
    assert code == 0, err
    assert "reliable" in stdout and "UNRELIABLE" not in err
    m = read_transform(out)
    e = rigid_error(m, files["truth"], files["gold"])
    assert e["tre_median_mm"] <= 0.5, e
    # the registered surface is the source moved by the written transform
    np.testing.assert_allclose(
        polydata_points(read_polydata(moved)),
        transform_points(m, polydata_points(read_polydata(files["surface"]))),
        atol=1e-6,
    )


def test_register_json_from_points_with_an_initial_matrix(capsys, files, tmp_path) -> None:
    init = write_transform(
        _rigid([0, 0, 1], 3.0, [2.0, 0.0, 0.0], np.zeros(3)) @ files["truth"], tmp_path / "init.tfm"
    )
    out = tmp_path / "T.txt"
    code, stdout, err = run(
        capsys,
        [
            "register",
            str(files["points"]),
            str(files["model"]),
            "-o",
            str(out),
            "--init",
            str(init),
            "--registered",
            str(tmp_path / "moved.csv"),
            "--json",
        ],
    )
    assert code == 0, err
    doc = json.loads(stdout)
    from BoneUSRecon.Logic.vtkio import read_points

    np.testing.assert_allclose(
        read_points(tmp_path / "moved.csv"),
        transform_points(np.array(doc["matrix"]), read_points(files["points"])),
        atol=1e-5,
    )
    assert (
        doc["output"] == str(out)
        and len(doc["eigenvalues"]) == 6
        and doc["reliable"] in (True, False)
    )
    assert doc["inlier_share"] > 0.8 and doc["rms_mm"] < 0.5
    assert (
        rigid_error(np.array(doc["matrix"]), files["truth"], files["gold"])["tre_median_mm"] <= 0.5
    )


def test_register_with_landmarks_from_far_away(capsys, files, tmp_path) -> None:
    out = tmp_path / "T.txt"
    argv = [
        "register",
        files["surface"],
        files["model_far"],
        "-o",
        out,
        "--landmarks",
        files["lm_src"],
        files["lm_tgt"],
        "-q",
    ]
    code, stdout, err = run(capsys, [str(a) for a in argv])
    assert code == 0, err
    assert "landmark RMS" in stdout
    assert rigid_error(read_transform(out), files["far"], files["gold"])["tre_median_mm"] <= 0.5


def test_reconstruct_register_to_in_one_step(capsys, files, tmp_path) -> None:
    t = tmp_path / "T.tfm"
    argv = [
        "reconstruct",
        files["sweep"],
        "-o",
        tmp_path / "s.vtp",
        "--register-to",
        files["model"],
        "--transform-out",
        t,
        "--json",
        "-q",
    ]
    code, stdout, err = run(capsys, [str(a) for a in argv])
    assert code == 0, err
    doc = json.loads(stdout)
    assert doc["registration"]["reliable"] is True
    assert rigid_error(read_transform(t), files["truth"], files["gold"])["tre_median_mm"] <= 0.5


@pytest.mark.parametrize(
    "argv, match",
    [
        (["register", "{surface}", "{model_m}", "-o", "{out}/T.txt"], "metres"),
        (["register", "{surface}", "{nonmanifold}", "-o", "{out}/T.txt"], "not a manifold"),
        (["register", "{surface}", "{empty}", "-o", "{out}/T.txt"], "file is empty"),
        (["register", "{surface}", "{cloud}", "-o", "{out}/T.txt"], "no triangles"),
        (["register", "{surface}", "{model_far}", "-o", "{out}/T.txt"], "do not overlap"),
        (
            [
                "register",
                "{surface}",
                "{model}",
                "-o",
                "{out}/T.txt",
                "--landmarks",
                "{lm_two}",
                "{lm_two}",
            ],
            "at least 3",
        ),
        (
            [
                "register",
                "{surface}",
                "{model}",
                "-o",
                "{out}/T.txt",
                "--landmarks",
                "{lm_src}",
                "{lm_two}",
            ],
            "4 and 2 points",
        ),
        (["register", "{surface}", "{model}", "-o", "{out}/T.vtp"], "unknown output extension"),
        (
            ["register", "{points}", "{model}", "-o", "{out}/T.txt", "--registered", "{out}/m.stl"],
            "point set",
        ),
        (
            ["register", "{surface}", "{model}", "-o", "{out}/T.txt", "--registered", "{surface}"],
            "would overwrite the input SOURCE",
        ),
        (
            ["register", "{surface}", "{model}", "-o", "{out}/T.txt", "--init", "{lm_src}"],
            "unknown transform format",
        ),
        (
            ["register", "{surface}", "{model}", "-o", "{out}/T.txt", "--init", "{out}/none.txt"],
            "no such file",
        ),
        (
            [
                "register",
                "{surface}",
                "{model}",
                "-o",
                "{out}/T.txt",
                "--search",
                "--landmarks",
                "{lm_src}",
                "{lm_tgt}",
            ],
            "one initial alignment",
        ),
        (
            ["reconstruct", "{sweep}", "-o", "{out}/s.vtp", "--register-to", "{model}"],
            "--transform-out",
        ),
        (
            ["reconstruct", "{sweep}", "-o", "{out}/s.vtp", "--register-init", "{lm_src}"],
            "needs --register-to",
        ),
        (
            [
                "reconstruct",
                "{sweep}",
                "-o",
                "{out}/s.vtp",
                "--register-to",
                "{model_m}",
                "--transform-out",
                "{out}/T.txt",
            ],
            "metres",
        ),
    ],
)
def test_bad_input_is_one_line_and_writes_nothing(capsys, files, tmp_path, argv, match) -> None:
    names = {k: v for k, v in files.items() if isinstance(v, (str, Path))}
    argv = [a.format(out=tmp_path, **names) for a in argv]
    assert_refused(capsys, argv, match, tmp_path)
    assert_refused(capsys, argv, match, files["dir"])  # inputs' folder untouched too


def test_transform_files_reject_garbage(tmp_path) -> None:
    from BoneUSRecon.Logic.errors import BoneUSReconError

    (tmp_path / "bad.tfm").write_text("not a transform\n")
    with pytest.raises(BoneUSReconError, match="bad.tfm"):
        read_transform(tmp_path / "bad.tfm")
    (tmp_path / "bad.txt").write_text("1 0 0\n0 1 0\n")
    with pytest.raises(BoneUSReconError, match="4x4"):
        read_transform(tmp_path / "bad.txt")
    with pytest.raises(BoneUSReconError, match="last row"):
        write_transform(np.ones((4, 4)), tmp_path / "x.txt")
    assert not (tmp_path / "x.txt").exists()


def test_ras_coordinates_conjugate_the_itk_file(tmp_path) -> None:
    m = _rigid([0, 1, 1], 20.0, [3.0, -4.0, 5.0], np.array([10.0, 0, 0]))
    write_transform(m, tmp_path / "lps.tfm")
    write_transform(m, tmp_path / "ras.tfm", coordinates="RAS")
    np.testing.assert_allclose(
        read_transform(tmp_path / "ras.tfm", coordinates="RAS"), m, atol=1e-9
    )
    d = np.diag([-1.0, -1, 1, 1])
    np.testing.assert_allclose(read_transform(tmp_path / "ras.tfm"), d @ m @ d, atol=1e-9)


def test_unreliable_result_is_written_and_flagged_on_stderr(capsys, tmp_path) -> None:
    from BoneUSRecon.Logic.simulation.bones import BoneGeometry, BoneSpec

    g = BoneGeometry(
        BoneSpec("cylinder", 120.0, (16.0, 16.0), (16.0, 16.0), 5.0, 0.0, 0.5, 0.0, 0.0, 0.0)
    )
    v, f = g.closed_mesh(*g.closed_mesh_params(5_000))
    s, phi = np.meshgrid(np.linspace(35, 85, 40), np.linspace(np.pi / 2 - 0.9, np.pi / 2 + 0.9, 20))
    write_points_csv(g.surface(s.ravel(), phi.ravel()), tmp_path / "patch.csv")
    write_polydata(triangles_to_polydata(v, f), tmp_path / "cyl.stl")
    code, stdout, err = run(
        capsys,
        [
            "register",
            str(tmp_path / "patch.csv"),
            str(tmp_path / "cyl.stl"),
            "-o",
            str(tmp_path / "T.txt"),
        ],
    )
    assert code == 0 and (tmp_path / "T.txt").is_file()
    assert "reliable                : NO" in stdout or "NO:" in stdout
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith(
        "bone-us-recon: warning: registration UNRELIABLE"
    )
    assert "translation along the bone's long axis" in lines[0]


def test_json_is_strict_even_when_a_direction_is_unbounded(capsys, tmp_path) -> None:
    from BoneUSRecon.Logic.simulation.bones import BoneGeometry, BoneSpec

    g = BoneGeometry(
        BoneSpec("cylinder", 120.0, (16.0, 16.0), (16.0, 16.0), 5.0, 0.0, 0.5, 0.0, 0.0, 0.0)
    )
    v, f = g.closed_mesh(*g.closed_mesh_params(5_000))
    s, phi = np.meshgrid(np.linspace(35, 85, 40), np.linspace(np.pi / 2 - 0.9, np.pi / 2 + 0.9, 20))
    write_points_csv(g.surface(s.ravel(), phi.ravel()), tmp_path / "patch.csv")
    write_polydata(triangles_to_polydata(v, f), tmp_path / "cyl.stl")
    argv = [
        "register",
        str(tmp_path / "patch.csv"),
        str(tmp_path / "cyl.stl"),
        "-o",
        str(tmp_path / "T.txt"),
        "--json",
    ]
    code, stdout, _ = run(capsys, argv)
    assert code == 0
    doc = json.loads(stdout, parse_constant=lambda c: pytest.fail(f"non-JSON constant {c}"))
    assert doc["reliable"] is False and (doc["sliding_mm"][0] is None or doc["sliding_mm"][0] > 1e4)
    # an exactly singular direction (infinite sliding, infinite condition) is null in JSON
    import dataclasses

    from BoneUSRecon.Logic.registration import Registration

    fields = {f.name: doc[f.name] for f in dataclasses.fields(Registration) if f.name in doc}
    fields.update(condition=float("inf"), sliding_mm=np.array([np.inf, 1.0, 1, 1, 1, 1]))
    strict = json.dumps(Registration(**fields).as_dict(), allow_nan=False)
    assert json.loads(strict)["condition"] is None

"""The batch command (issue 15): a cohort of sweeps on Dask, equal to single runs.

A handful of tiny simulated sweeps (24 frames of 96 x 128 pixels), written once per
module, plus a broken file, a missing file and a registration row. The reference is
``bone-us-recon reconstruct`` run on each sweep alone. Dask clusters cost seconds to
start, so one ``dask scheduler`` with two ``dask worker`` processes (separate
processes on 127.0.0.1, started and stopped here) serves most tests; one test uses the
default local cluster, one interrupts it.
"""

from __future__ import annotations

import csv
import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from vtkmodules.util.numpy_support import vtk_to_numpy

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.batch import SUMMARY_COLUMNS, read_manifest
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.sequence_io import write_sweep
from BoneUSRecon.Logic.vtkio import read_polydata, write_points_csv

ROOT = Path(__file__).resolve().parents[1]
TINY = {"n_frames": 24, "width": 128, "height": 96}
#: (file stem, bone, seed, with gold)
SWEEPS = [("a", "clavicle", 0, True), ("b", "radius", 1, True), ("c", "tibia", 2, False)]


def _env() -> dict[str, str]:
    """This checkout first on the path of every process we start (workers included)."""
    path = os.environ.get("PYTHONPATH", "")
    return {**os.environ, "PYTHONPATH": f"{ROOT}{os.pathsep}{path}" if path else str(ROOT)}


@pytest.fixture(scope="module")
def cohort(sim_factory, tmp_path_factory):
    """Sweeps, gold files, a broken sweep and the manifest (paths relative to it)."""
    d = tmp_path_factory.mktemp("cohort")
    (d / "data").mkdir()
    for stem, bone, seed, gold in SWEEPS:
        sim = sim_factory(bone=bone, seed=seed, **TINY)
        write_sweep(sim.sweep, d / "data" / f"{stem}.mha")
        if gold:
            write_points_csv(sim.gold, d / "data" / f"{stem}_gold.csv")
    good = (d / "data" / "a.mha").read_bytes()
    (d / "data" / "broken.mha").write_bytes(good[: len(good) // 2])  # truncated pixel data
    (d / "data" / "model.stl").write_text("solid bone\nendsolid bone\n")
    rows = [
        "sweep,name,gold,target,rays,control-points",
        "data/a.mha,,data/a_gold.csv,,,",
        "data/b.mha,,data/b_gold.csv,,,",
        "data/c.mha,,,,,",
        "data/broken.mha,,,,,",
        "data/missing.mha,,,,,",
        "data/a.mha,,,,11,10 4",  # same stem: named a-2
        "data/c.mha,registered,,data/model.stl,,",
    ]
    (d / "manifest.csv").write_text("\n".join(rows) + "\n")
    return d


#: Rows of the cohort that succeed: name -> (sweep stem, reconstruct's extra options).
OK = {
    "a": ("a", []),
    "b": ("b", []),
    "c": ("c", []),
    "a-2": ("a", ["--rays", "11", "--control-points", "10", "4"]),
}
FAILED = {"broken", "missing", "registered"}


@pytest.fixture(scope="module")
def singles(cohort, tmp_path_factory):
    """``reconstruct`` on each successful row's sweep alone: name -> (surface, points)."""
    out = tmp_path_factory.mktemp("singles")
    refs = {}
    for name, (stem, extra) in OK.items():
        surf, pts = out / f"{name}.vtp", out / f"{name}_points.vtp"
        argv = ["reconstruct", str(cohort / "data" / f"{stem}.mha"), "-o", str(surf)]
        assert main([*argv, "--points-out", str(pts), "-q", *extra]) == 0
        refs[name] = (surf, pts)
    return refs


@pytest.fixture(scope="module")
def scheduler(tmp_path_factory):
    """``dask scheduler`` and ``dask worker`` (2 processes, 1 thread) on 127.0.0.1."""
    d = tmp_path_factory.mktemp("dask")
    info = d / "scheduler.json"
    env = _env()
    common = {"cwd": d, "env": env, "stdout": subprocess.DEVNULL, "stderr": subprocess.DEVNULL}
    # --idle-timeout / --death-timeout: they end by themselves should this test die.
    sched = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "dask",
            "scheduler",
            "--host",
            "127.0.0.1",
            "--port",
            "0",
            "--no-dashboard",
            "--dashboard-address",
            "127.0.0.1:0",
            "--scheduler-file",
            str(info),
            "--idle-timeout",
            "300s",
        ],
        **common,
    )
    procs = [sched]
    try:
        # The scheduler creates its file before it writes it (not atomically): wait
        # until it holds the JSON, not only until it exists (an empty read failed CI once).
        t_end = time.monotonic() + 60
        doc = None
        while doc is None and time.monotonic() < t_end and sched.poll() is None:
            try:
                doc = json.loads(info.read_text())
            except (FileNotFoundError, json.JSONDecodeError):
                time.sleep(0.1)
        assert doc is not None, "dask scheduler wrote no scheduler file within 60 s"
        address = doc["address"]
        assert address.startswith("tcp://127.0.0.1:")
        procs.append(
            subprocess.Popen(
                [
                    sys.executable,
                    "-m",
                    "dask",
                    "worker",
                    address,
                    "--nworkers",
                    "2",
                    "--nthreads",
                    "1",
                    "--host",
                    "127.0.0.1",
                    "--no-dashboard",
                    "--death-timeout",
                    "30s",
                ],
                **common,
            )
        )
        from distributed import Client

        with Client(address, timeout="30s") as client:
            client.wait_for_workers(2, timeout=60)
        yield address
    finally:
        for p in reversed(procs):
            p.terminate()
        for p in reversed(procs):
            try:
                p.wait(timeout=20)
            except subprocess.TimeoutExpired:
                p.kill()
                p.wait()


def run(capsys, argv):
    code = main(argv)
    cap = capsys.readouterr()
    return code, cap.out, cap.err


def arrays(path: Path) -> dict[str, np.ndarray]:
    pd = read_polydata(path)
    out = {"points": vtk_to_numpy(pd.GetPoints().GetData())}
    if pd.GetNumberOfPolys():
        out["triangles"] = vtk_to_numpy(pd.GetPolys().GetConnectivityArray())
    data = pd.GetPointData()
    for i in range(data.GetNumberOfArrays()):
        out[data.GetArrayName(i)] = vtk_to_numpy(data.GetArray(i))
    return out


def assert_same_as_single(folder: Path, ref: tuple[Path, Path]) -> None:
    for mine, theirs in ((folder / "surface.vtp", ref[0]), (folder / "points.vtp", ref[1])):
        a, b = arrays(mine), arrays(theirs)
        assert a.keys() == b.keys()
        for k in a:
            np.testing.assert_array_equal(a[k], b[k], err_msg=f"{mine}: {k}")


def no_leftovers(outdir: Path) -> None:
    hidden = [p.name for p in outdir.rglob(".*")]
    assert hidden == [], hidden


# --------------------------------------------------------------------------- manifest


def test_manifest_names_paths_and_overrides(cohort):
    jobs = read_manifest(cohort / "manifest.csv")
    assert [j.name for j in jobs] == ["a", "b", "c", "broken", "missing", "a-2", "registered"]
    assert (
        jobs[0].sweep == cohort / "data" / "a.mha"
        and jobs[0].gold == cohort / "data" / "a_gold.csv"
    )
    assert jobs[2].gold is None and jobs[6].target == cohort / "data" / "model.stl"
    a2 = jobs[5]
    assert (a2.params.resampling.n_rays, a2.params.fit.n_control_points) == (11, (10, 4))
    assert jobs[0].params == read_manifest(cohort / "manifest.csv")[1].params  # defaults
    m = cohort / "along.csv"
    m.write_text("sweep,along,around\ndata/a.mha,9,\ndata/a.mha,,4\n")
    assert [j.params.fit.n_control_points for j in read_manifest(m)] == [(9, 6), (15, 4)]


def test_manifest_bone_points_are_per_sweep(cohort):
    # reconstruct's --bone-point, one or several points per row (reference mm).
    m = cohort / "points.csv"
    m.write_text('sweep,bone-points\ndata/a.mha,"12.5 -3 40; 14, -3, 60"\ndata/a.mha,\n')
    jobs = read_manifest(m)
    assert jobs[0].params.segmentation.rejection.bone_points == (
        (12.5, -3.0, 40.0),
        (14.0, -3.0, 60.0),
    )
    assert jobs[1].params.segmentation.rejection.bone_points == ()


@pytest.mark.parametrize(
    ("text", "match"),
    [
        ("name,gold\nx,y\n", "no 'sweep' column"),
        ("sweep,colour\na.mha,red\n", "unknown column 'colour'"),
        ("sweep,rays,Rays\na.mha,3,3\n", "appears twice"),
        ("sweep,rays\na.mha,many\n", "line 2: column 'rays' must be an integer"),
        ("sweep,degree\na.mha,2\n", "line 2: column 'degree' must be two integers"),
        ("sweep,segmenter\na.mha,magic\n", "line 2: unknown segmenter 'magic'"),
        ("sweep,control_points\na.mha,2 2\n", "line 2: "),
        ("sweep,name\na.mha,x\nb.mha,x\n", "name 'x' is given to more than one sweep"),
        ("sweep,along,control-points\na.mha,9,9 5\n", "line 2: give 'control-points' or"),
        ("sweep,around\na.mha,0\n", "line 2: "),
        ("sweep,bone-points\na.mha,1 2\n", "line 2: column 'bone-points' must be points of three"),
        ("sweep,bone_points\na.mha,1 2 nan\n", "line 2: column 'bone-points' must be points"),
        ("sweep,name\na.mha,../up\n", "cannot be a folder name"),
        ("sweep,name\na.mha,summary.csv\n", "cannot be a folder name"),
        ("sweep,gold\n,g.csv\n", "line 2: empty 'sweep' cell"),
        ("sweep\n", "no sweeps listed"),
        ("", "file is empty"),
    ],
)
def test_bad_manifest_is_refused_before_any_work(capsys, tmp_path, text, match):
    m = tmp_path / "m.csv"
    m.write_text(text)
    with pytest.raises(BoneUSReconError, match=match):
        read_manifest(m)
    code, out, err = run(capsys, ["batch", str(m), str(tmp_path / "out"), "-q"])
    assert code == 2 and out == ""
    lines = err.strip().splitlines()
    assert len(lines) == 1 and lines[0].startswith("bone-us-recon: error:") and "m.csv" in lines[0]
    assert not (tmp_path / "out").exists()


def test_bad_invocation_exits_2_and_writes_nothing(capsys, cohort, tmp_path):
    m = str(cohort / "manifest.csv")
    cases = [
        (["batch", m, str(tmp_path / "o"), "--workers", "0"], "--workers must be at least 1"),
        (
            ["batch", m, str(tmp_path / "o"), "--workers", "2", "--scheduler", "tcp://127.0.0.1:1"],
            "not with --scheduler",
        ),
        (["batch", m, str(cohort / "manifest.csv")], "not a folder"),
        (["batch", m, str(tmp_path / "no" / "o")], "does not exist"),
    ]
    for argv, match in cases:
        code, out, err = run(capsys, [*argv, "-q"])
        assert code == 2, (argv, err)
        assert match in err and err.count("\n") == 1 and "Traceback" not in err, err
    assert sorted(os.listdir(tmp_path)) == []
    # A folder of someone else's files where a sweep's folder would go.
    (tmp_path / "o" / "b").mkdir(parents=True)
    (tmp_path / "o" / "b" / "thesis.tex").write_text("mine")
    code, _, err = run(capsys, ["batch", m, str(tmp_path / "o"), "-q"])
    assert code == 2 and "is not a batch output" in err
    assert os.listdir(tmp_path / "o") == ["b"]


def test_outputs_never_land_on_inputs(capsys, cohort, tmp_path):
    # A sweep named 'data' would be written as OUTDIR/data: the folder of the inputs.
    m = tmp_path / "m.csv"
    m.write_text(f"sweep,name\n{cohort / 'data' / 'a.mha'},data\n")
    code, _, err = run(capsys, ["batch", str(m), str(cohort), "-q"])
    assert code == 2 and "data: is an input of the batch" in err, err
    # The manifest itself where summary.csv would go.
    s = tmp_path / "summary.csv"
    s.write_text(f"sweep\n{cohort / 'data' / 'a.mha'}\n")
    code, _, err = run(capsys, ["batch", str(s), str(tmp_path), "-q"])
    assert code == 2 and "summary.csv: is an input of the batch" in err, err
    assert sorted(os.listdir(tmp_path)) == ["m.csv", "summary.csv"]


# --------------------------------------------------------------------------- running


def test_batch_on_a_scheduler_equals_single_runs(capsys, cohort, singles, scheduler, tmp_path):
    out = tmp_path / "out"
    argv = ["batch", str(cohort / "manifest.csv"), str(out), "--scheduler", scheduler, "--json"]
    code, stdout, err = run(capsys, argv)
    assert code == 1, err
    doc = json.loads(stdout)
    assert (doc["sweeps"], doc["ok"], doc["failed"], doc["resumed"]) == (7, 4, 3, 0)
    # The failures are named on stderr, one line each, and the others went on.
    failed_lines = [ln for ln in err.splitlines() if ln.startswith("bone-us-recon: failed: ")]
    assert {ln.split(": ")[2] for ln in failed_lines} == FAILED, err
    errors = {r["name"]: r["error"] for r in doc["rows"] if r["status"] == "failed"}
    assert "broken.mha" in errors["broken"]
    assert "missing.mha: no such file" in errors["missing"]
    assert errors["registered"].endswith(
        "model.stl: could not read any points (corrupt or not this format)"
    )

    for name, ref in singles.items():
        assert sorted(os.listdir(out / name)) == ["points.vtp", "summary.json", "surface.vtp"]
        assert_same_as_single(out / name, ref)
    for name in FAILED:
        assert os.listdir(out / name) == ["summary.json"]
    no_leftovers(out)

    with open(out / "summary.csv", newline="") as f:
        table = list(csv.DictReader(f))
    assert tuple(table[0]) == SUMMARY_COLUMNS
    by_name = {r["name"]: r for r in table}
    assert [r["name"] for r in table] == [r["name"] for r in doc["rows"]]
    for name in OK:
        r = by_name[name]
        assert r["status"] == "ok" and r["error"] == ""
        assert int(r["frames_used"]) + int(r["frames_rejected"]) == int(r["valid_frames"]) == 24
        assert float(r["time_total_s"]) > float(r["time_segment_s"]) > 0
    assert by_name["a-2"]["rays"] == "11" and by_name["a-2"]["control_points"] == "10 4"
    # Accuracy against the simulator's gold points where given.
    for name in ("a", "b"):
        assert int(by_name[name]["gold_points"]) > 1000
        assert float(by_name[name]["mean_mm"]) < 0.3, by_name[name]
    assert by_name["c"]["mean_mm"] == ""
    pq = pytest.importorskip("pyarrow.parquet")
    t = pq.read_table(out / "summary.parquet")
    assert t.column("name").to_pylist() == list(by_name)
    used = [int(r["frames_used"]) if r["frames_used"] else None for r in table]
    assert t.column("frames_used").to_pylist() == used and used.count(None) == 3
    assert str(t.schema.field("mean_mm").type) == "double"

    # --resume: nothing to do, so no Dask at all (this scheduler address is dead).
    before = {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file()}
    dead = ["--scheduler", "tcp://127.0.0.1:9"]
    code, stdout, err = run(capsys, [*argv[:3], *dead, "--resume", "--json"])
    assert code == 1, err
    doc2 = json.loads(stdout)
    assert doc2["resumed"] == 7
    assert [{**r, "resumed": False} for r in doc2["rows"]] == doc["rows"]
    assert {p: p.stat().st_mtime_ns for p in out.rglob("*") if p.is_file() and p.parent != out} == {
        p: t for p, t in before.items() if p.parent != out
    }

    # A changed input or parameter makes exactly that sweep run again.
    os.utime(cohort / "data" / "b_gold.csv", ns=(time.time_ns(), time.time_ns()))
    code, stdout, err = run(capsys, [*argv, "--resume"])
    assert code == 1, err
    rows = {r["name"]: r for r in json.loads(stdout)["rows"]}
    assert [n for n, r in rows.items() if not r["resumed"]] == ["b"]
    assert_same_as_single(out / "b", singles["b"])
    no_leftovers(out)


def test_logic_api_reports_progress_per_sweep(cohort, singles, scheduler, tmp_path):
    from BoneUSRecon.Logic import read_manifest as read
    from BoneUSRecon.Logic import run_batch

    m = tmp_path / "m.csv"
    m.write_text(f"sweep\n{cohort / 'data' / 'b.mha'}\n{cohort / 'data' / 'nope.mha'}\n")
    calls = []
    result = run_batch(
        read(m), tmp_path / "out", scheduler=scheduler, progress=lambda *a: calls.append(a)
    )
    assert calls == [("sweeps", 0, 2), ("sweeps", 1, 2), ("sweeps", 2, 2)]
    assert [r["status"] for r in result.rows] == ["ok", "failed"]
    assert [r["name"] for r in result.failed] == ["nope"]
    assert result.summary_files[0] == tmp_path / "out" / "summary.csv"
    assert_same_as_single(tmp_path / "out" / "b", singles["b"])


def test_report_option_writes_each_sweeps_report(capsys, cohort, scheduler, tmp_path):
    m = tmp_path / "m.csv"
    m.write_text(f"sweep,gold\n{cohort / 'data' / 'a.mha'},{cohort / 'data' / 'a_gold.csv'}\n")
    out = tmp_path / "out"
    code, stdout, err = run(
        capsys, ["batch", str(m), str(out), "--scheduler", scheduler, "--report"]
    )
    assert code == 0, err
    assert "1 ok, 0 failed" in stdout
    report = out / "a" / "report"
    assert (report / "index.html").stat().st_size > 10_000
    doc = json.loads((report / "report.json").read_text())
    summary = json.loads((out / "a" / "summary.json").read_text())
    assert "report/index.html" in summary["outputs"]
    # The report shows the accuracy the summary recorded.
    assert doc["evaluation"]["mean_mm"] == pytest.approx(summary["row"]["mean_mm"])
    # The report is part of the fingerprint: without --report the sweep runs again.
    code, stdout, err = run(
        capsys, ["batch", str(m), str(out), "--scheduler", scheduler, "--resume", "--json"]
    )
    assert code == 0 and json.loads(stdout)["resumed"] == 0, err
    assert not report.exists()
    no_leftovers(out)


@pytest.mark.slow
@pytest.mark.skipif(sys.platform != "linux", reason="a terminal's process group")
def test_local_cluster_ctrl_c_then_resume_equals_single_runs(cohort, singles, scheduler, tmp_path):
    """Default local cluster, stopped by SIGINT to the whole process group (a
    terminal's Ctrl-C reaches the workers too); the finished sweeps equal single runs
    and are kept, the others leave nothing; ``--resume`` does the rest."""
    data = cohort / "data"
    m = tmp_path / "m.csv"
    lines = ["sweep,name,rays,control-points"]
    for k in range(3):
        lines += [
            f"{data / 'a.mha'},a-2_{k},11,10 4",
            f"{data / 'b.mha'},b_{k},,",
            f"{data / 'c.mha'},c_{k},,",
        ]
    m.write_text("\n".join(lines) + "\n")
    out = tmp_path / "out"
    argv = [sys.executable, "-m", "BoneUSRecon", "batch", str(m), str(out), "--workers", "2"]
    proc = subprocess.Popen(
        argv,
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
        env=_env(),
        start_new_session=True,
    )
    try:
        # Interrupt once one sweep is finished and others are part-way.
        t_end = time.monotonic() + 180
        while proc.poll() is None and time.monotonic() < t_end:
            names = [p.name for p in out.iterdir()] if out.exists() else []
            if any(n.endswith(".part") for n in names) and any(
                not n.startswith(".") for n in names
            ):
                os.killpg(proc.pid, signal.SIGINT)
                break
            time.sleep(0.005)
        stdout, err = proc.communicate(timeout=60)
    finally:
        if proc.poll() is None:
            os.killpg(proc.pid, signal.SIGKILL)
            proc.wait()
    assert proc.returncode == 130, err
    assert stdout == "" and "Traceback" not in err, err
    assert err.strip().splitlines() == [
        f"bone-us-recon: interrupted; finished sweeps are kept in {out}, unfinished ones left "
        "nothing (rerun with --resume to go on)"
    ]
    finished = sorted(os.listdir(out))
    assert 1 <= len(finished) < 9, finished
    no_leftovers(out)
    for name in finished:
        assert_same_as_single(out / name, singles[name.split("_")[0]])

    done = subprocess.run(
        [*argv[:-2], "--scheduler", scheduler, "--resume", "--json"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=300,
    )
    assert done.returncode == 0, done.stderr
    doc = json.loads(done.stdout)
    assert (doc["ok"], doc["resumed"]) == (9, len(finished))
    for r in doc["rows"]:
        assert_same_as_single(out / r["name"], singles[r["name"].split("_")[0]])
    no_leftovers(out)


FORK_SERVER_PROBE = """
import multiprocessing, os, signal, sys
from multiprocessing import forkserver
if sys.argv[1] == "numpy":
    import numpy
from BoneUSRecon.Logic.batch import start_worker_server
start_worker_server(fork_this_process=True)
pid = forkserver._forkserver._forkserver_pid
with open(f"/proc/{pid}/cmdline") as f, open("/proc/self/cmdline") as g:
    forked = f.read() == g.read()
with multiprocessing.get_context("forkserver").Pool(1) as pool:
    ppid, sigint = pool.apply(os.getppid), pool.apply(signal.getsignal, (signal.SIGINT,))
print(forked, ppid == pid, sigint == signal.SIG_IGN, signal.getsignal(signal.SIGINT) is signal.SIG_IGN)
"""


@pytest.mark.skipif(
    sys.platform != "linux" or sys.version_info >= (3, 14),
    reason="/proc; Python 3.14's fork server has another handshake (the plain one is used)",
)
@pytest.mark.parametrize("numpy_first", [False, True])
def test_command_forks_its_own_fork_server(numpy_first):
    """The command's fork server is a fork of it after its imports (one import set for
    the command and the workers), unless numpy was imported before (its BLAS thread
    count is then set): a fresh interpreter. Either way the workers ignore SIGINT and
    the caller does not."""
    r = subprocess.run(
        [sys.executable, "-c", FORK_SERVER_PROBE, "numpy" if numpy_first else "-"],
        capture_output=True,
        text=True,
        env=_env(),
        timeout=120,
    )
    assert r.returncode == 0, r.stderr
    assert r.stdout.split() == [str(not numpy_first), "True", "True", "False"], r.stdout


def test_target_column_registers_the_sweep(sim_factory, tmp_path):
    # A row with `target` registers the segmented points to that bone model: the
    # summary holds the SOURCE -> TARGET matrix, which undoes the model's known shift.
    from BoneUSRecon.Logic.batch import run_sweep
    from BoneUSRecon.Logic.registration import rigid_error, transform_points
    from BoneUSRecon.Logic.vtkio import triangles_to_polydata, write_polydata

    sim = sim_factory(bone="clavicle", seed=0, **TINY)
    write_sweep(sim.sweep, tmp_path / "s.mha")
    v, f = sim.geometry.closed_mesh(*sim.geometry.closed_mesh_params(20_000))
    truth = np.eye(4)
    truth[:3, 3] = [3.0, -2.0, 4.0]
    write_polydata(triangles_to_polydata(transform_points(truth, v), f), tmp_path / "model.stl")
    (tmp_path / "m.csv").write_text("sweep,target\ns.mha,model.stl\n")
    (job,) = read_manifest(tmp_path / "m.csv")
    out = tmp_path / "out"
    out.mkdir()
    row = run_sweep(job, out)
    assert row["status"] == "ok", row
    doc = json.loads((out / "s" / "summary.json").read_text())
    matrix = np.asarray(doc["registration"]["matrix"])
    assert rigid_error(matrix, truth, sim.gold)["tre_median_mm"] <= 0.5

"""Benchmark: ``bone-us-recon batch`` against running the sweeps one after another (issue 15).

Makes a cohort of ``--sweeps`` rows (default 20, as in the issue): ``--sweeps`` - 2
clean simulated sweeps (five bones in turn, one seed each; by default the simulator's
reference sweep: 150 frames of 256 x 320 pixels at 0.15 mm) and two broken ones (one truncated, one not a sequence
file at all), writes a manifest with gold points, and runs, each as
a fresh process as a user would:

1. ``bone-us-recon batch MANIFEST OUT --workers W`` (local Dask cluster, W processes
   of one thread; start-up included);
2. the same sweeps one after another in one Python process (``read_sweep`` +
   ``reconstruct`` + writing the surface and points; imports once): the strict
   baseline;
3. the same, split over ``--workers`` plain processes started together (sweeps dealt
   out in turn; no Dask): the control, what the cores give without any engine. Its
   CPU over the one process's is what running processes side by side costs on this
   machine (shared caches, other users); the batch's CPU over the control's is
   Dask's own;
4. a shell loop of ``bone-us-recon reconstruct SWEEP -o ... --points-out ...``, one
   command per sweep: what the batch replaces;
5. ``batch --resume`` again: must do no work.

It prints wall time, our CPU time (every descendant process, workers included) and the
cores we obtained (CPU / wall), the CPU the *other* processes of the machine used
meanwhile (from ``/proc/stat``), the throughput ratios, and a CPU-normalised ratio
(``2 x`` serial CPU / batch CPU: the ratio two idle cores would give if both workers
stay busy). It then checks that the batch's results equal the shell loop's arrays
(surface points, triangles, every point array) and that the two broken sweeps, and
only they, failed.

All processes run with ``OMP_NUM_THREADS=1`` (and the other BLAS thread variables), as
Dask's workers do, so that the serial runs use one core; ``--all-cores`` leaves them.

Run::

    python Testing/benchmarks/bench_batch.py [--sweeps 20] [--frames 150] [--size 256x320] [--workers 2]
        [--segmenter snake] [--workdir DIR] [--skip-shell-loop]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
BONES = ("clavicle", "radius", "ulna", "tibia", "humerus")
THREAD_VARS = ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS")

SERIAL_SCRIPT = """
import sys, json
from pathlib import Path
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.pipeline import params_with, reconstruct
from BoneUSRecon.Logic.sequence_io import read_sweep
from BoneUSRecon.Logic.vtkio import write_points, write_polydata
out = Path(sys.argv[1]); params = params_with(segmenter=sys.argv[2]); failed = []
for s in sys.argv[3:]:
    try:
        r = reconstruct(read_sweep(s), params)
    except BoneUSReconError as exc:
        failed.append(str(exc)); continue
    write_polydata(r.surface, out / (Path(s).stem + ".vtp"))
    write_points(r.points, out / (Path(s).stem + "_points.vtp"))
print(json.dumps(failed))
"""


def env(all_cores: bool) -> dict[str, str]:
    e = dict(os.environ)
    e["PYTHONPATH"] = os.pathsep.join(p for p in (str(ROOT), e.get("PYTHONPATH", "")) if p)
    if not all_cores:
        e.update(dict.fromkeys(THREAD_VARS, "1"))
    return e


def machine_busy_s() -> float:
    """CPU seconds all processes of the machine have used since boot (/proc/stat)."""
    try:
        fields = [int(v) for v in Path("/proc/stat").read_text().split("\n")[0].split()[1:]]
    except OSError:
        return float("nan")
    idle = fields[3] + (fields[4] if len(fields) > 4 else 0)
    return (sum(fields[:8]) - idle) / os.sysconf("SC_CLK_TCK")


class TreeCPU(threading.Thread):
    """CPU seconds used by this process's descendants, polled every 50 ms.

    ``getrusage(RUSAGE_CHILDREN)`` misses processes that are not waited for by their
    parent chain, such as the workers forked by multiprocessing's fork server (which
    is left to exit on its own), so every descendant is sampled while it runs (the
    last < 50 ms of each is missed; the same rule for every phase).
    """

    def __init__(self) -> None:
        super().__init__(daemon=True)
        self.seen: dict[tuple[int, float], float] = {}
        self.stop = threading.Event()

    def run(self) -> None:
        import psutil

        me = psutil.Process()
        while not self.stop.is_set():
            for c in me.children(recursive=True):
                try:
                    t = c.cpu_times()
                    self.seen[(c.pid, c.create_time())] = t.user + t.system
                except psutil.Error:
                    pass
            self.stop.wait(0.05)

    def total(self) -> float:
        self.stop.set()
        self.join()
        return sum(self.seen.values())


class Phase:
    """Wall, our CPU (all descendants) and the machine's CPU over a ``with`` block."""

    def __enter__(self) -> Phase:
        self.tree = TreeCPU()
        self.tree.start()
        self.t, self.busy = time.perf_counter(), machine_busy_s()
        return self

    def __exit__(self, *exc: object) -> None:
        self.wall = time.perf_counter() - self.t
        self.cpu = self.tree.total()
        self.others = max(0.0, machine_busy_s() - self.busy - self.cpu)

    def line(self, label: str, n: int) -> str:
        return (
            f"{label:<34} {self.wall:8.1f} s wall {n / self.wall:6.3f} sweeps/s  "
            f"CPU {self.cpu:7.1f} s ({self.cpu / self.wall:4.2f} cores)  "
            f"others {self.others / self.wall:4.2f} cores"
        )


def make_cohort(
    d: Path, n: int, frames: int, h: int, w: int, segmenter: str
) -> tuple[Path, list[Path]]:
    sys.path.insert(0, str(ROOT))
    from BoneUSRecon.Logic.sequence_io import write_sweep
    from BoneUSRecon.Logic.simulation import SimulationParams, simulate
    from BoneUSRecon.Logic.vtkio import write_points_csv

    d.mkdir(parents=True, exist_ok=True)
    sweeps = []
    for i in range(n):
        s = d / f"s{i:02d}.mha"
        g = d / f"s{i:02d}_gold.csv"
        if not s.exists():
            p = SimulationParams(
                bone=BONES[i % len(BONES)],
                seed=i,
                n_frames=frames,
                width=w,
                height=h,
                spacing_mm=0.15 * 320 / w,  # the reference field of view, 48 mm wide
            )
            sim = simulate(p)
            write_sweep(sim.sweep, s)
            write_points_csv(sim.gold, g)
        sweeps.append(s)
    # Two broken sweeps: pixel data cut in half, and a file that is no sequence at all.
    b1, b2 = d / "broken_truncated.mha", d / "broken_garbage.mha"
    data = sweeps[0].read_bytes()
    b1.write_bytes(data[: len(data) // 2])
    b2.write_text("this is not a PLUS sequence file\n")
    sweeps[3:3] = [b1]
    sweeps[12:12] = [b2]
    rows = ["sweep,gold,segmenter"] + [
        f"{s.name},{'' if s.stem.startswith('broken') else s.stem + '_gold.csv'},{segmenter}"
        for s in sweeps
    ]
    m = d / f"manifest_{segmenter}.csv"
    m.write_text("\n".join(rows) + "\n")
    return m, sweeps


def arrays(path: Path) -> dict[str, object]:
    from vtkmodules.util.numpy_support import vtk_to_numpy

    from BoneUSRecon.Logic.vtkio import read_polydata

    pd = read_polydata(path)
    out = {"points": vtk_to_numpy(pd.GetPoints().GetData())}
    if pd.GetNumberOfPolys():
        out["triangles"] = vtk_to_numpy(pd.GetPolys().GetConnectivityArray())
    for i in range(pd.GetPointData().GetNumberOfArrays()):
        out[pd.GetPointData().GetArrayName(i)] = vtk_to_numpy(pd.GetPointData().GetArray(i))
    return out


def same(a: Path, b: Path) -> bool:
    import numpy as np

    x, y = arrays(a), arrays(b)
    return x.keys() == y.keys() and all(np.array_equal(x[k], y[k]) for k in x)


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--sweeps", type=int, default=20, help="sweeps simulated (two more are broken)")
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--size", default="256x320", help="frame height x width in pixels")
    ap.add_argument("--workers", type=int, default=2)
    ap.add_argument(
        "--segmenter",
        default="shadowpath",
        help="shadowpath (default) or snake (the paper's, several times the work per sweep)",
    )
    ap.add_argument("--workdir", help="keep (and reuse) the simulated sweeps here")
    ap.add_argument("--skip-shell-loop", action="store_true")
    ap.add_argument("--all-cores", action="store_true", help="leave the BLAS thread variables")
    args = ap.parse_args()
    # 18 good + 2 broken = 20 rows by default, as in the issue.
    n_good = args.sweeps - 2
    work = Path(args.workdir) if args.workdir else Path(tempfile.mkdtemp(prefix="bench_batch."))
    h, w = (int(v) for v in args.size.lower().split("x"))
    data = work / f"cohort_{n_good}x{args.frames}x{h}x{w}"
    t = time.perf_counter()
    manifest, sweeps = make_cohort(data, n_good, args.frames, h, w, args.segmenter)
    print(
        f"cohort: {len(sweeps)} sweeps ({n_good} good of {args.frames} frames {h}x{w}, 2 broken) "
        f"in {data} ({time.perf_counter() - t:.1f} s)"
    )
    e = env(args.all_cores)
    py = [sys.executable, "-m", "BoneUSRecon"]
    n = len(sweeps)
    for sub in ("batch", "serial", "loop", *(f"plain{i}" for i in range(args.workers))):
        if (work / sub).exists():
            import shutil

            shutil.rmtree(work / sub)
        (work / sub).mkdir()

    with Phase() as batch:
        r = subprocess.run(
            [
                *py,
                "batch",
                str(manifest),
                str(work / "batch"),
                "--workers",
                str(args.workers),
                "--json",
                "-q",
            ],
            capture_output=True,
            text=True,
            env=e,
        )
    assert r.returncode in (0, 1), r.stderr
    doc = json.loads(r.stdout)
    print(batch.line(f"batch --workers {args.workers}", n))

    with Phase() as serial:
        r2 = subprocess.run(
            [
                sys.executable,
                "-c",
                SERIAL_SCRIPT,
                str(work / "serial"),
                args.segmenter,
                *map(str, sweeps),
            ],
            capture_output=True,
            text=True,
            env=e,
        )
    assert r2.returncode == 0, r2.stderr
    print(serial.line("one process, one after another", n))

    with Phase() as plain:
        procs = [
            subprocess.Popen(
                [
                    sys.executable,
                    "-c",
                    SERIAL_SCRIPT,
                    str(work / f"plain{i}"),
                    args.segmenter,
                    *map(str, sweeps[i :: args.workers]),
                ],
                stdout=subprocess.DEVNULL,
                stderr=subprocess.PIPE,
                text=True,
                env=e,
            )
            for i in range(args.workers)
        ]
        errs = [p.communicate()[1] for p in procs]
    assert all(p.returncode == 0 for p in procs), errs
    print(plain.line(f"{args.workers} plain processes (no Dask)", n))

    loop = None
    if not args.skip_shell_loop:
        with Phase() as loop:
            for s in sweeps:
                subprocess.run(
                    [
                        *py,
                        "reconstruct",
                        str(s),
                        "-o",
                        str(work / "loop" / f"{s.stem}.vtp"),
                        "--points-out",
                        str(work / "loop" / f"{s.stem}_points.vtp"),
                        "--segmenter",
                        args.segmenter,
                        "-q",
                    ],
                    capture_output=True,
                    env=e,
                )
        print(loop.line("shell loop of reconstruct commands", n))

    with Phase() as resume:
        r3 = subprocess.run(
            [*py, "batch", str(manifest), str(work / "batch"), "--resume", "--json", "-q"],
            capture_output=True,
            text=True,
            env=e,
        )
    doc3 = json.loads(r3.stdout)
    print(
        resume.line("batch --resume (nothing to do)", n)
        + f"  resumed {doc3['resumed']} of {doc3['sweeps']}"
    )

    print()
    print(
        f"throughput batch / one process      : {serial.wall / batch.wall:.2f}x wall, "
        f"{2 * serial.cpu / batch.cpu:.2f}x CPU-normalised (2 x serial CPU / batch CPU)"
    )
    print(
        f"throughput {args.workers} plain processes / one: {serial.wall / plain.wall:.2f}x wall, "
        f"{2 * serial.cpu / plain.cpu:.2f}x CPU-normalised (the cores' own limit)"
    )
    if loop is not None:
        print(
            f"throughput batch / shell loop       : {loop.wall / batch.wall:.2f}x wall, "
            f"{2 * loop.cpu / batch.cpu:.2f}x CPU-normalised"
        )
    print(
        f"batch overhead (CPU) over one process: {batch.cpu - serial.cpu:+.1f} s "
        f"({(batch.cpu - serial.cpu) / n:+.2f} s per sweep), of which side-by-side processes "
        f"{plain.cpu - serial.cpu:+.1f} s and Dask {batch.cpu - plain.cpu:+.1f} s"
    )

    ok = [row for row in doc["rows"] if row["status"] == "ok"]
    failed = [row["name"] for row in doc["rows"] if row["status"] != "ok"]
    ref = work / ("loop" if loop is not None else "serial")
    equal = sum(
        same(work / "batch" / row["name"] / "surface.vtp", ref / f"{row['name']}.vtp")
        and same(work / "batch" / row["name"] / "points.vtp", ref / f"{row['name']}_points.vtp")
        for row in ok
    )
    means = [row["mean_mm"] for row in ok]
    print(
        f"results: {len(ok)} ok, equal to single runs ({ref.name}): {equal} of {len(ok)}; "
        f"failed: {', '.join(failed)} (exit status {r.returncode})"
    )
    print(
        f"accuracy: mean gold distance {min(means):.3f}-{max(means):.3f} mm over {len(means)} sweeps"
    )
    print(
        f"resume: exit {r3.returncode}, {doc3['resumed']} of {doc3['sweeps']} skipped, "
        f"{resume.wall:.1f} s"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

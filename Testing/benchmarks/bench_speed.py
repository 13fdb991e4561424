"""Speed benchmark (issue 7 section 3): our reconstruction against scikit-image's snake.

For a 150-frame 256x320 sweep and a 250-frame 480x640 one (simulated clavicle, same
48 x 38 mm field of view, uncompressed .mha), prints

* time per stage of an in-process run: read (``read_sweep``), segment, resample, fit,
  surface (mesh, Distance array) and write (``write_polydata``), and frames/s;
* the whole ``bone-us-recon reconstruct SWEEP -o OUT.vtp`` command in a fresh process
  (``python -m BoneUSRecon``, start-up and imports included): wall time (best and
  median of ``--repeat`` runs), CPU time, frames/s;
* ``skimage.segmentation.active_contour`` on the same frames, as in scikit-image's
  own example: Gaussian smoothing (sigma 3) then the snake with 100 points,
  ``boundary_condition='free'``, ``max_num_iter=300``, started from a horizontal line
  across the image at mid-depth; all frames, or ``--snake-frames N`` of them evenly
  spaced with the total extrapolated (said so in the output);
* the ratio (whole command) / (scikit-image snake alone). Targets: < 0.25, aim 0.1;
  and >= 30 frames/s for the whole command on the 480x640 sweep on one core.

By default everything runs on one core (``OMP_NUM_THREADS`` etc. set to 1 before
numpy is imported, for this process and the command); ``--all-cores`` leaves them.
Wall times on a shared machine are noisy: CPU times are printed beside them, and
ratios are given for both.

Run::

    python Testing/benchmarks/bench_speed.py [--sizes 150x256x320 250x480x640]
        [--repeat 3] [--snake-frames N] [--workdir DIR] [--profile] [--all-cores]

``--workdir`` keeps (and reuses) the simulated sweeps; ``--profile`` prints the top
functions of a cProfile of the in-process run.
"""

from __future__ import annotations

import os
import sys

if "--all-cores" not in sys.argv:
    for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
        os.environ[_v] = "1"

import argparse  # noqa: E402
import cProfile  # noqa: E402
import io  # noqa: E402
import pstats  # noqa: E402
import resource  # noqa: E402
import statistics  # noqa: E402
import subprocess  # noqa: E402
import tempfile  # noqa: E402
import time  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

FOV_WIDTH_MM = 48.0  # the simulator's default field of view: 320 px x 0.15 mm


def parse_size(text: str) -> tuple[int, int, int]:
    n, h, w = (int(v) for v in text.lower().split("x"))
    return n, h, w


def make_sweep(folder: Path, n: int, h: int, w: int) -> Path:
    """Simulate (or reuse) a clean clavicle sweep of n frames of h x w pixels."""
    from BoneUSRecon.Logic.sequence_io import write_sweep
    from BoneUSRecon.Logic.simulation import SimulationParams, simulate

    path = folder / f"clavicle_{n}x{h}x{w}.mha"
    if not path.exists():
        t = time.perf_counter()
        sim = simulate(
            SimulationParams(
                bone="clavicle", n_frames=n, width=w, height=h, spacing_mm=FOV_WIDTH_MM / w, seed=0
            )
        )
        write_sweep(sim.sweep, path)
        print(f"  simulated {path.name} in {time.perf_counter() - t:.1f} s")
    return path


def stages_in_process(path: Path, out: Path, profile: bool) -> dict[str, float]:
    """Seconds per stage of one in-process reconstruction."""
    from BoneUSRecon.Logic.pipeline import reconstruct
    from BoneUSRecon.Logic.sequence_io import read_sweep
    from BoneUSRecon.Logic.vtkio import write_polydata

    prof = cProfile.Profile() if profile else None
    t0 = time.perf_counter()
    c0 = time.process_time()
    if prof:
        prof.enable()
    sweep = read_sweep(path)
    t1 = time.perf_counter()
    recon = reconstruct(sweep)
    t2 = time.perf_counter()
    write_polydata(recon.surface, out)
    t3 = time.perf_counter()
    if prof:
        prof.disable()
        s = io.StringIO()
        pstats.Stats(prof, stream=s).sort_stats("tottime").print_stats(15)
        print("\n".join("    " + line for line in s.getvalue().splitlines()[:40]))
    tm = recon.timings
    return {
        "read": t1 - t0,
        "segment": tm["segment"],
        "resample": tm["resample"],
        "fit": tm["fit"],
        "surface": tm["surface"],
        "write": t3 - t2,
        "total": t3 - t0,
        "cpu": time.process_time() - c0,
        "reconstruct_other": (t2 - t1) - tm["total"],
    }


def whole_command(path: Path, out: Path, repeat: int) -> tuple[list[float], list[float]]:
    """Wall and CPU seconds of ``python -m BoneUSRecon reconstruct`` runs."""
    root = Path(__file__).resolve().parents[2]
    walls, cpus = [], []
    for _ in range(repeat):
        before = resource.getrusage(resource.RUSAGE_CHILDREN)
        t = time.perf_counter()
        subprocess.run(
            [sys.executable, "-m", "BoneUSRecon", "reconstruct", str(path), "-o", str(out), "-q"],
            check=True,
            cwd=root,
            stdout=subprocess.DEVNULL,
        )
        walls.append(time.perf_counter() - t)
        after = resource.getrusage(resource.RUSAGE_CHILDREN)
        cpus.append((after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime))
    return walls, cpus


def skimage_snake(path: Path, n_frames: int | None) -> tuple[float, float, int, int]:
    """Wall and CPU seconds of scikit-image's snake on the sweep's frames (extrapolated
    to all frames when a subset is used); returns (wall, cpu, frames run, frames)."""
    from skimage.filters import gaussian
    from skimage.segmentation import active_contour

    from BoneUSRecon.Logic.sequence_io import read_sweep

    sweep = read_sweep(path)
    idx = sweep.valid_indices
    run = (
        idx
        if not n_frames or n_frames >= idx.size
        else idx[np.linspace(0, idx.size - 1, n_frames).astype(int)]
    )
    h, w = sweep.height, sweep.width
    init = np.stack([np.full(100, (h - 1) / 2.0), np.linspace(0, w - 1, 100)], axis=1)  # (row, col)
    t, c = time.perf_counter(), time.process_time()
    for _, frame in sweep.iter_frames(run):
        smooth = gaussian(frame, sigma=3, preserve_range=False)
        active_contour(
            smooth,
            init,
            alpha=0.015,
            beta=10,
            gamma=0.001,
            boundary_condition="free",
            max_num_iter=300,
        )
    wall, cpu = time.perf_counter() - t, time.process_time() - c
    scale = idx.size / run.size
    return wall * scale, cpu * scale, int(run.size), int(idx.size)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument(
        "--sizes",
        nargs="+",
        default=["150x256x320", "250x480x640"],
        help="sweeps as FRAMESxHEIGHTxWIDTH (default: 150x256x320 250x480x640)",
    )
    ap.add_argument("--repeat", type=int, default=3, help="runs of the whole command (default 3)")
    ap.add_argument(
        "--snake-frames",
        type=int,
        default=None,
        help="run scikit-image's snake on this many frames and extrapolate (default: all)",
    )
    ap.add_argument("--workdir", type=Path, help="keep and reuse the simulated sweeps here")
    ap.add_argument("--profile", action="store_true", help="cProfile the in-process run")
    ap.add_argument("--all-cores", action="store_true", help="do not pin BLAS/OpenMP to one thread")
    args = ap.parse_args(argv)

    import platform

    import skimage

    print(
        f"bench_speed: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores "
        f"({'all' if args.all_cores else 'one'} used), Python {platform.python_version()}, "
        f"numpy {np.__version__}, scikit-image {skimage.__version__}"
    )
    with tempfile.TemporaryDirectory(prefix="bench_speed_") as tmp:
        folder = args.workdir or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        rows = []
        for size in args.sizes:
            n, h, w = parse_size(size)
            print(f"\n== {n} frames of {h}x{w} px ({n * h * w / 2**20:.0f} MB)")
            path = make_sweep(folder, n, h, w)
            out = Path(tmp) / "surface.vtp"
            st = stages_in_process(path, out, args.profile)
            print(
                "  in-process stages (s): "
                + ", ".join(
                    f"{k} {st[k]:.3f}"
                    for k in ("read", "segment", "resample", "fit", "surface", "write")
                )
            )
            print(
                f"  in-process total {st['total']:.2f} s ({st['cpu']:.2f} s CPU): "
                f"{n / st['total']:.0f} frames/s; segmentation alone {n / st['segment']:.0f} frames/s"
            )
            walls, cpus = whole_command(path, out, args.repeat)
            best, med = min(walls), statistics.median(walls)
            print(
                f"  whole command (start-up included), {args.repeat} runs: wall best {best:.2f} s, "
                f"median {med:.2f} s, CPU {min(cpus):.2f} s -> {n / best:.1f} frames/s "
                f"(median {n / med:.1f}; by CPU {n / min(cpus):.1f})"
            )
            sw, sc, ran, total = skimage_snake(path, args.snake_frames)
            note = "" if ran == total else f" (run on {ran} frames, extrapolated to {total})"
            print(
                f"  skimage active_contour (gaussian + 100 pts, free, 300 iter): wall {sw:.2f} s, "
                f"CPU {sc:.2f} s, {sw / total * 1e3:.0f} ms/frame{note}"
            )
            print(
                f"  ratio whole command / skimage snake: wall {best / sw:.3f} (median {med / sw:.3f}), "
                f"CPU {min(cpus) / sc:.3f}   [target < 0.25, aim 0.10]"
            )
            rows.append((size, n / best, best / sw, min(cpus) / sc))
        print("\nsummary: size, command frames/s (best wall), ratio to skimage (wall), ratio (CPU)")
        for size, fps, rw, rc in rows:
            print(f"  {size:<14} {fps:7.1f} fps   {rw:.3f}   {rc:.3f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

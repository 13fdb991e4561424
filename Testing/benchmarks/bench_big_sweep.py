"""Big-sweep benchmark (issue 7 section 2, issue 11 section 4): long and dense sweeps.

Writes a synthetic 2,000-frame 480x640 uncompressed PLUS sequence (614 MB of pixels:
speckle, a bright convex bone echo whose depth drifts along the sweep, and its
acoustic shadow; the probe advances ``--step-mm`` per frame, 0.05 mm by default: 100 mm
in all; ``--frames 1000 --step-mm 0.3`` is issue 11's 300 mm, 1,000-frame sweep) with
:func:`write_sweep`, never holding it in memory (frames are generated in chunks into
a temporary memory map first). Then runs ``bone-us-recon reconstruct`` on it in a
fresh process and prints, against the data size:

* ``ru_maxrss`` (the command's own, from ``wait4``): the peak resident set (counts touched pages of the memory-mapped
  sweep, which are page cache the kernel can drop, as well as private memory);
* peak ``RssAnon`` (sampled from ``/proc/PID/status`` every 20 ms): the private
  memory the process really holds; a float64 copy of the sweep would be 4.9 GB;
* peak ``RssFile``: mapped file pages resident at once;
* the same for a process that only imports the command line (fixed overhead);
* the time of each stage, triangles per mm^2, and accuracy against the synthetic bone
  (known exactly): mean, p95 and share within 1 mm of 1,145 gold points sampled on it
  with 0.2 mm noise (as the simulator's), and the area-weighted p95 distance from the
  surface to it.

The command runs on one core (``OMP_NUM_THREADS=1`` and the like, ``--threads``); wall
and CPU time are both printed (the machine may be shared).

The simulator is not used: it would need minutes and holds its sweep in memory.

Target: peak memory well below the data size plus a fixed overhead.

Run::

    python Testing/benchmarks/bench_big_sweep.py [--frames 2000] [--width 640] [--height 480]
        [--keep DIR] [--compressed]
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

import numpy as np

SPACING_MM = 0.075  # 640 px x 0.075 mm = 48 mm, the simulator's field of view
STEP_MM = 0.05  # probe advance per frame


def bone_depth(k: np.ndarray, x: np.ndarray, n: int, h: int, w: int) -> np.ndarray:
    """Depth (mm below the transducer) of the synthetic bone top at frame ``k``, column ``x`` (mm).

    At 45 % of the image depth, drifting by +-10 % over the sweep; convex cross-section.
    """
    xc = w * SPACING_MM / 2
    depth_mm = h * SPACING_MM
    return depth_mm * (0.45 + 0.1 * np.sin(2 * np.pi * 1.5 * k / n)) + 0.012 * (x - xc) ** 2


def wobble(k: np.ndarray) -> np.ndarray:
    """Lateral offset of the probe (mm) at frame ``k``."""
    return 0.2 * np.sin(np.asarray(k, float) / 150.0)


def truth_distance(p: np.ndarray, n: int, h: int, w: int, step: float) -> np.ndarray:
    """Distance (mm) from reference points to the synthetic bone surface.

    The surface is ``y = -bone_depth(k, x - wobble(k))`` with ``k = -z / step``: the
    vertical offset divided by the slope's norm (exact for a plane, within 0.01 mm here:
    the curvature radius is >= 40 mm against offsets of a few tenths).
    """
    k = -p[:, 2] / step
    x = p[:, 0] - wobble(k)
    d = bone_depth(k, x, n, h, w)
    dx = 0.024 * (x - w * SPACING_MM / 2)
    dk = h * SPACING_MM * 0.1 * 2 * np.pi * 1.5 / n * np.cos(2 * np.pi * 1.5 * k / n)
    dz = -dk / step  # d(depth)/dz
    return np.abs(p[:, 1] + d) / np.sqrt(1 + dx**2 + dz**2)


def truth_gold(n: int, h: int, w: int, step: float, count: int = 1145, seed: int = 0) -> np.ndarray:
    """Gold points on the synthetic bone, uniform in (frame, column), 0.2 mm noise per axis.

    Columns within 1 mm of the image's sides are left out (as a digitiser reaches what
    the probe saw); uniform in (k, x) is close to uniform by area (slopes < 0.6).
    """
    rng = np.random.default_rng(seed)
    k = rng.uniform(0, n - 1, count)
    x = rng.uniform(1.0, (w - 1) * SPACING_MM - 1.0, count)
    p = np.stack([x + wobble(k), -bone_depth(k, x, n, h, w), -k * step], axis=1)
    return p + rng.normal(0.0, 0.2, p.shape)


def synthetic_frames(k0: int, k1: int, n: int, h: int, w: int, bank: np.ndarray) -> np.ndarray:
    """Frames k0..k1-1 (uint8): speckle, a convex bone echo and its shadow (vectorised)."""
    k = np.arange(k0, k1, dtype=np.float32)[:, None, None]
    y = (np.arange(h, dtype=np.float32) * SPACING_MM)[None, :, None]  # depth, mm
    x = (np.arange(w, dtype=np.float32) * SPACING_MM)[None, None, :]  # lateral, mm
    d = bone_depth(k, x, n, h, w)
    tissue = 60.0 + 50.0 * np.exp(-y / 6.0)
    echo = 200.0 * np.exp(-(((y - d) / 0.3) ** 2))
    shadow = np.where(y > d + 0.45, 0.12, 1.0)
    # Speckle: a bank of multiplicative patterns, rolled so neighbouring frames differ.
    sp = np.stack([np.roll(bank[int(i) % len(bank)], int(i) * 7, axis=1) for i in range(k0, k1)])
    img = (tissue * sp + echo * (0.7 + 0.3 * sp)) * shadow
    return np.clip(img, 0, 255).astype(np.uint8)


def make_big_sweep(
    path: Path, n: int, h: int, w: int, compress: bool = False, step: float = STEP_MM
) -> float:
    """Write the synthetic sweep to ``path`` (zlib when ``compress``); return seconds taken."""
    from BoneUSRecon.Logic.sequence_io import write_sweep
    from BoneUSRecon.Logic.sweep import Sweep

    t = time.perf_counter()
    rng = np.random.default_rng(0)
    bank = rng.gamma(2.0, 0.5, (8, h, w)).astype(np.float32)
    # Pixel (i, j) -> (i * s, -j * s, -k * step): rows go down in depth, frames advance.
    m = np.tile(np.diag([SPACING_MM, -SPACING_MM, -1.0, 1.0]), (n, 1, 1))
    m[:, 2, 3] = -np.arange(n) * step
    m[:, 0, 3] = wobble(np.arange(n))  # a little lateral wobble
    with tempfile.TemporaryDirectory(prefix="bench_big_", dir=path.parent) as tmp:
        frames = np.lib.format.open_memmap(
            Path(tmp) / "frames.npy", mode="w+", dtype=np.uint8, shape=(n, h, w)
        )
        for k0 in range(0, n, 25):
            k1 = min(n, k0 + 25)
            frames[k0:k1] = synthetic_frames(k0, k1, n, h, w, bank)
        frames.flush()
        write_sweep(
            Sweep(frames, m, np.arange(n) / 30.0, np.ones(n, bool)), path, compress=compress
        )
        del frames
    return time.perf_counter() - t


def status_kb(pid: int) -> dict[str, int]:
    out = {}
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "RssAnon", "RssFile"):
                out[key] = int(value.split()[0])
    except OSError:
        pass
    return out


def run_measured(argv: list[str], env: dict[str, str] | None = None) -> dict[str, float]:
    """Run a command; return wall s, CPU s, its own ru_maxrss MB and sampled peaks (MB)."""
    t = time.perf_counter()
    with tempfile.TemporaryFile("w+") as out, tempfile.TemporaryFile("w+") as err:
        proc = subprocess.Popen(argv, stdout=out, stderr=err, text=True, env=env)
        peaks = {"VmRSS": 0, "RssAnon": 0, "RssFile": 0}
        stop = threading.Event()

        def sample() -> None:
            while not stop.is_set():
                for key, v in status_kb(proc.pid).items():
                    peaks[key] = max(peaks[key], v)
                time.sleep(0.02)

        th = threading.Thread(target=sample, daemon=True)
        th.start()
        # wait4 gives this child's own rusage (RUSAGE_CHILDREN would mix in others').
        _, status, ru = os.wait4(proc.pid, 0)
        proc.returncode = os.waitstatus_to_exitcode(status)
        stop.set()
        th.join()
        wall = time.perf_counter() - t
        out.seek(0)
        err.seek(0)
        stdout, stderr = out.read(), err.read()
    if proc.returncode != 0:
        raise SystemExit(f"command failed ({proc.returncode}): {stderr.strip()}")
    return {
        "wall_s": wall,
        "cpu_s": ru.ru_utime + ru.ru_stime,
        "maxrss_mb": ru.ru_maxrss / 1024,
        "peak_rss_mb": peaks["VmRSS"] / 1024,
        "peak_anon_mb": peaks["RssAnon"] / 1024,
        "peak_file_mb": peaks["RssFile"] / 1024,
        "stdout": stdout,
    }


def surface_accuracy(path: Path, n: int, h: int, w: int, step: float) -> dict[str, float]:
    """Gold-point statistics and area-weighted surface-to-truth p95 (mm) of a surface file."""
    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.surface import triangle_centroids
    from BoneUSRecon.Logic.vtkio import read_polydata

    surf = read_polydata(path)
    ev = evaluate_surface(surf, truth_gold(n, h, w, step))
    c, a = triangle_centroids(surf)
    d = truth_distance(c, n, h, w, step)
    o = np.argsort(d)
    p95 = float(d[o][np.searchsorted(np.cumsum(a[o]) / a.sum(), 0.95)])
    return {"mean": ev.mean, "p95": ev.p95, "within_1": ev.within_1, "truth_p95": p95}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--step-mm", type=float, default=STEP_MM, help="probe advance per frame (mm)")
    ap.add_argument(
        "--threads", type=int, default=1, help="BLAS/OpenMP threads of the command (default 1)"
    )
    ap.add_argument("--keep", type=Path, help="write (or reuse) the sweep in this folder")
    ap.add_argument(
        "--compressed",
        action="store_true",
        help="zlib-compressed data (inflated by the reader into a temporary file-backed map)",
    )
    ap.add_argument("--make", type=Path, help=argparse.SUPPRESS)  # internal: write the sweep only
    args = ap.parse_args(argv)
    n, h, w = args.frames, args.height, args.width
    if args.make:
        make_big_sweep(args.make, n, h, w, args.compressed, args.step_mm)
        return 0
    print(
        f"bench_big_sweep: {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} cores"
    )
    with tempfile.TemporaryDirectory(prefix="bench_big_sweep_") as tmp:
        folder = args.keep or Path(tmp)
        folder.mkdir(parents=True, exist_ok=True)
        path = folder / (
            f"big_{n}x{h}x{w}_{args.step_mm:g}mm{'_zlib' if args.compressed else ''}.mha"
        )
        if not path.exists():
            # In a child process: this one must stay small, because a child's
            # ru_maxrss starts from its parent's resident set at fork time.
            t = time.perf_counter()
            subprocess.run(
                [
                    sys.executable,
                    __file__,
                    "--make",
                    str(path),
                    "--frames",
                    str(n),
                    "--height",
                    str(h),
                    "--width",
                    str(w),
                    "--step-mm",
                    str(args.step_mm),
                ]
                + (["--compressed"] if args.compressed else []),
                check=True,
            )
            print(f"wrote {path.name} in {time.perf_counter() - t:.1f} s")
        data_mb = n * h * w / 2**20
        print(
            f"sweep: {n} frames of {h}x{w} uint8 = {data_mb:.0f} MB of pixels "
            f"(float64 copy would be {8 * data_mb / 1024:.1f} GB), file {path.stat().st_size / 2**20:.0f} MB"
        )
        out = Path(tmp) / "surface.vtp"
        env = dict(os.environ)
        for var in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS"):
            env[var] = str(args.threads)
        r = run_measured(
            [
                sys.executable,
                "-m",
                "BoneUSRecon",
                "reconstruct",
                str(path),
                "-o",
                str(out),
                "--json",
                "-q",
            ],
            env,
        )
        doc = json.loads(r["stdout"])
        accuracy = surface_accuracy(out, n, h, w, args.step_mm)
        base = run_measured(
            [
                sys.executable,
                "-c",
                "from BoneUSRecon.cli import build_parser; build_parser();"
                "import BoneUSRecon.Logic.pipeline, BoneUSRecon.Logic.sequence_io",
            ]
        )
        s = doc["summary"]
        tm = doc["timings_s"]
        print(
            f"reconstruct ({n * args.step_mm:.0f} mm sweep, {args.threads} thread(s)): "
            f"{s['segmented_frames']} of {s['frames']} frames segmented, grid "
            f"{s['grid_shape'][0]}x{s['grid_shape'][1]}, fit RMS {s['fit_rms_mm']:.3f} mm; "
            f"wall {r['wall_s']:.1f} s, CPU {r['cpu_s']:.1f} s, {n / r['wall_s']:.0f} frames/s; "
            f"stages (s): " + ", ".join(f"{k} {v:.2f}" for k, v in tm.items())
        )
        print(
            f"surface: {s['surface_triangles']} triangles, {s['surface_area_mm2']:.0f} mm^2, "
            f"{s['surface_triangles'] / s['surface_area_mm2']:.1f} per mm^2; surface stage "
            f"{100 * tm['surface'] / tm['total']:.1f} % of the run; gold (1,145 points): mean "
            f"{accuracy['mean']:.3f} mm, p95 {accuracy['p95']:.3f} mm, within 1 mm "
            f"{100 * accuracy['within_1']:.1f} %; surface-to-true-bone p95 "
            f"{accuracy['truth_p95']:.3f} mm"
        )
        print(
            f"{'':<26}{'maxrss MB':>10}{'peak RSS MB':>12}{'peak anon MB':>13}{'peak file MB':>13}"
        )
        for label, m in (("reconstruct", r), ("imports only (overhead)", base)):
            print(
                f"{label:<26}{m['maxrss_mb']:>10.0f}{m['peak_rss_mb']:>12.0f}"
                f"{m['peak_anon_mb']:>13.0f}{m['peak_file_mb']:>13.0f}"
            )
        over = r["peak_rss_mb"] - base["peak_rss_mb"]
        print(
            f"peak RSS above the import overhead: {over:.0f} MB = {100 * over / data_mb:.1f}% of the "
            f"data size; private (anon) above overhead: {r['peak_anon_mb'] - base['peak_anon_mb']:.0f} MB"
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

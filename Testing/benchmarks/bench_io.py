"""Benchmark: reading a big tracked sweep with bounded memory (issue 7).

Writes a 2,000-frame 640x480 uncompressed PLUS sequence (about 614 MB) to a temporary
folder, then, each in a fresh process so that the peak resident set is its own:

* ``read``: :func:`read_sweep` only (header parse + memory map);
* ``index``: read, then touch every frame by indexing ``sweep.frames[k]``;
* ``iter_frames``: read, then iterate with :meth:`Sweep.iter_frames`, which releases
  the mapped pages as it goes.

For each it prints wall time and the peak memory: ``ru_maxrss`` (peak resident set,
which counts touched file-backed pages of a memory map, reclaimable page cache) and
the peak anonymous memory (``RssAnon``, sampled while iterating: what the process
really holds). Run::

    python Testing/benchmarks/bench_io.py [--frames 2000] [--width 640] [--height 480]
        [--compressed] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import subprocess
import sys
import tempfile
import time
from pathlib import Path

CHILD = r"""
import json, resource, sys, time
t0 = time.perf_counter()
import numpy as np
from BoneUSRecon.Logic.sequence_io import read_sweep

def anon_kb():
    for line in open("/proc/self/status"):
        if line.startswith("RssAnon:"):
            return int(line.split()[1])
    return 0

mode, path = sys.argv[1], sys.argv[2]
base_rss = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss
base_anon = anon_kb()
t_import = time.perf_counter() - t0
t = time.perf_counter()
s = read_sweep(path)
t_read = time.perf_counter() - t
peak_anon = anon_kb()
t = time.perf_counter()
total = 0
if mode == "index":
    for k in range(s.n_frames):
        total += int(s.frames[k].sum(dtype=np.uint64))
        if k % 50 == 0:
            peak_anon = max(peak_anon, anon_kb())
elif mode == "iter_frames":
    for k, f in s.iter_frames():
        total += int(f.sum(dtype=np.uint64))
        if k % 50 == 0:
            peak_anon = max(peak_anon, anon_kb())
t_iter = time.perf_counter() - t
peak_anon = max(peak_anon, anon_kb())
print(json.dumps(dict(
    import_s=t_import, read_s=t_read, iterate_s=t_iter, checksum=total,
    frames=s.n_frames, memmap=isinstance(s.frames, np.memmap),
    maxrss_mb=resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024,
    base_rss_mb=base_rss / 1024, peak_anon_mb=peak_anon / 1024, base_anon_mb=base_anon / 1024,
)))
"""


def make_sweep_file(path: Path, n: int, h: int, w: int, compressed: bool) -> float:
    """Write the big sweep without ever holding it in memory; return seconds taken."""
    import numpy as np

    from BoneUSRecon.Logic.sequence_io import write_sweep
    from BoneUSRecon.Logic.sweep import Sweep

    rng = np.random.default_rng(0)
    # One speckle-like frame broadcast to all N (zero stride: 300 kB, not 600 MB);
    # the writer streams a few frames at a time.
    frame = rng.gamma(2.0, 40.0, (h, w)).clip(0, 255).astype(np.uint8)
    frames = np.broadcast_to(frame, (n, h, w))
    m = np.tile(np.diag([0.1, 0.1, 1.0, 1.0]), (n, 1, 1))
    m[:, 2, 3] = np.arange(n) * 0.2
    sweep = Sweep(frames, m, np.arange(n) / 30.0, np.ones(n, bool))
    t = time.perf_counter()
    write_sweep(sweep, path, compress=compressed)
    return time.perf_counter() - t


def measure(mode: str, path: Path) -> dict:
    root = Path(__file__).resolve().parents[2]
    out = subprocess.run(
        [sys.executable, "-c", CHILD, mode, str(path)],
        capture_output=True,
        text=True,
        check=True,
        cwd=root,
    )
    return json.loads(out.stdout)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    ap.add_argument("--frames", type=int, default=2000)
    ap.add_argument("--width", type=int, default=640)
    ap.add_argument("--height", type=int, default=480)
    ap.add_argument("--compressed", action="store_true", help="zlib-compressed data")
    ap.add_argument("--keep", type=Path, help="write the sweep here and keep it")
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory(prefix="bench_io_") as tmp:
        folder = args.keep or Path(tmp)
        path = folder / "big_sweep.mha"
        n, h, w = args.frames, args.height, args.width
        t_write = make_sweep_file(path, n, h, w, args.compressed)
        size_mb = path.stat().st_size / 2**20
        data_mb = n * h * w / 2**20
        print(
            f"sweep: {n} frames of {h}x{w} uint8, {data_mb:.0f} MB of pixels, file "
            f"{size_mb:.0f} MB ({'zlib' if args.compressed else 'uncompressed'}); "
            f"written in {t_write:.2f} s ({data_mb / t_write:.0f} MB/s)"
        )
        print(
            f"{'mode':<12} {'read s':>7} {'iterate s':>9} {'fps':>8} {'maxrss MB':>10} "
            f"{'peak anon MB':>12} {'import MB':>9}  memmap"
        )
        for mode in ("read", "index", "iter_frames"):
            r = measure(mode, path)
            fps = r["frames"] / r["iterate_s"] if mode != "read" else float("nan")
            print(
                f"{mode:<12} {r['read_s']:7.3f} {r['iterate_s']:9.3f} {fps:8.0f} "
                f"{r['maxrss_mb']:10.0f} {r['peak_anon_mb']:12.0f} {r['base_rss_mb']:9.0f}  "
                f"{r['memmap']}"
            )
        print(
            "maxrss counts touched pages of the memory map (reclaimable page cache); "
            "peak anon is memory the process really holds."
        )
    return 0


if __name__ == "__main__":
    sys.exit(main())

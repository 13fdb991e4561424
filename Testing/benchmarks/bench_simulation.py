"""Benchmark of the phantom simulator: speed and image figures, per bone.

Run: ``python Testing/benchmarks/bench_simulation.py [--frames 150] [--width 320]
[--height 256] [--spacing 0.15]``. Prints, per bone, the simulation time and frame
rate, the measured bone size, the bone-line / shadow / soft-tissue grey levels along
the true contours, and the cost of writing the files and of exact distances to the
truth for 10^5 points. No asserts: figures to read and to compare between versions.
"""

from __future__ import annotations

import argparse
import tempfile
import time

import numpy as np

from BoneUSRecon.Logic.simulation import BONES, SimulationParams, simulate, write_simulation


def _band(frame: np.ndarray, contour: np.ndarray, offset_px: float) -> float:
    i = contour[:, 0].astype(int)
    j = np.clip(np.rint(contour[:, 1] + offset_px).astype(int), 0, frame.shape[0] - 1)
    return float(frame[j, i].mean())


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--spacing", type=float, default=0.15)
    ap.add_argument("--corrupt", type=float, default=0.1)
    args = ap.parse_args()

    print(
        f"{args.frames} frames of {args.height} x {args.width} at {args.spacing} mm, "
        f"{args.corrupt:.0%} corrupted"
    )
    head = (
        f"{'bone':<9} {'time s':>7} {'frames/s':>9} {'cpu s':>6} {'width mm':>11} "
        f"{'depth mm':>8} {'line':>5} {'shadow':>6} {'above':>5} {'swept mm':>8}"
    )
    print(head)
    print("-" * len(head))
    last = None
    for bone in BONES:
        p = SimulationParams(
            bone=bone,
            n_frames=args.frames,
            width=args.width,
            height=args.height,
            spacing_mm=args.spacing,
            corrupted_fraction=args.corrupt,
        )
        t0, c0 = time.perf_counter(), time.process_time()
        sim = simulate(p)
        dt, dc = time.perf_counter() - t0, time.process_time() - c0
        a, _ = sim.geometry.semi_axes(np.linspace(*sim.swept_range_mm, 100))
        sp = args.spacing
        clean = [k for k in range(sim.sweep.n_frames) if k not in sim.corruption_kinds]
        line = np.mean([_band(sim.sweep.frames[k], sim.true_contours_px[k], 0) for k in clean])
        shadow = np.mean(
            [_band(sim.sweep.frames[k], sim.true_contours_px[k], 1.0 / sp) for k in clean]
        )
        above = np.mean(
            [_band(sim.sweep.frames[k], sim.true_contours_px[k], -1.5 / sp) for k in clean]
        )
        depth = np.median([sim.true_contours_px[k][:, 1].min() * sp for k in clean])
        swept = sim.swept_range_mm[1] - sim.swept_range_mm[0]
        print(
            f"{bone:<9} {dt:7.2f} {args.frames / dt:9.1f} {dc:6.2f} "
            f"{2 * a.min():5.1f}-{2 * a.max():4.1f} {depth:8.1f} {line:5.0f} {shadow:6.0f} "
            f"{above:5.0f} {swept:8.1f}"
        )
        last = sim

    assert last is not None
    with tempfile.TemporaryDirectory() as d:
        t0 = time.perf_counter()
        paths = write_simulation(last, d)
        dt = time.perf_counter() - t0
        sizes = ", ".join(f"{k} {v.stat().st_size / 1e6:.2f} MB" for k, v in paths.items())
    print(f"write_simulation: {dt:.2f} s ({sizes})")

    rng = np.random.default_rng(0)
    g = last.geometry
    s = rng.uniform(0, g.length, 100_000)
    phi = rng.uniform(0, 2 * np.pi, 100_000)
    d = rng.uniform(-1.0, 5.0, 100_000)
    q = g.surface(s, phi) + d[:, None] * g.normals(s, phi)
    t0 = time.perf_counter()
    dist = last.distance_to_truth(q)
    dt = time.perf_counter() - t0
    print(
        f"distance_to_truth: 10^5 points in {dt:.2f} s, max error {np.abs(dist - np.abs(d)).max():.1e} mm"
    )
    gd = last.distance_to_truth(last.gold)
    print(
        f"gold: {len(last.gold)} points, distance to truth rms {np.sqrt(np.mean(gd**2)):.3f} mm, "
        f"max {gd.max():.2f} mm"
    )


if __name__ == "__main__":
    main()

"""Segmentation benchmark (issue 3 section 4): accuracy, rejection and speed per segmenter.

For simulated sweeps of every bone with 10 % corrupted frames, prints per segmenter:
median and 95th-percentile distance (mm) of the kept points to the true bone surface,
the share of kept points farther than 2 mm, the share of corrupted frames rejected
("caught") and the share either rejected or kept with their points on the bone
("harmless"), and frames per second; then the time per frame of
``skimage.segmentation.active_contour`` (100 points, 300 iterations, free ends) on the
same frames, as a ratio. Also times the default segmenter on 480x640 frames and runs
both segmenters on the real PLUS recording in Resources/SampleData (overlays written with --overlay).

Run: ``python Testing/benchmarks/bench_segmentation.py [--frames 60] [--overlay DIR]``
Targets for the default: median <= 0.15 mm, p95 <= 0.5 mm, < 1 % beyond 2 mm,
>= 10x faster per frame than skimage's snake.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from BoneUSRecon.Logic.segmentation import SEGMENTERS, SegmentationParams, segment_sweep
from BoneUSRecon.Logic.simulation import BONES, SimulationParams, simulate

# The recording shipped in Resources/SampleData, found by the tests' helper.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from conftest import REAL_MHA, REAL_XML  # noqa: E402

REAL = REAL_MHA


def skimage_seconds_per_frame(frames: np.ndarray, n: int = 5) -> float:
    """Mean time of skimage's active_contour (100 points, 300 iterations, free ends)."""
    from skimage.filters import gaussian
    from skimage.segmentation import active_contour

    ts = []
    for k in np.linspace(0, len(frames) - 1, n).astype(int):
        img = np.asarray(frames[k])
        h, w = img.shape
        init = np.column_stack([np.full(100, h / 2.0), np.linspace(0, w - 1, 100)])
        t = time.perf_counter()
        active_contour(
            gaussian(img, 1.0, preserve_range=False),
            init,
            boundary_condition="free",
            max_num_iter=300,
            convergence=0.0,
        )
        ts.append(time.perf_counter() - t)
    return float(np.mean(ts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=60)
    ap.add_argument("--width", type=int, default=320)
    ap.add_argument("--height", type=int, default=256)
    ap.add_argument("--overlay", type=Path, help="write real-data overlays here")
    args = ap.parse_args()
    warnings.simplefilter("ignore")

    print(
        f"{'bone':9} {'segmenter':10} {'median':>7} {'p95':>7} {'>2mm%':>6} "
        f"{'caught':>7} {'harmless':>8} {'fps':>7} {'skimage x':>9}"
    )
    allv: dict[str, list[np.ndarray]] = {m: [] for m in SEGMENTERS}
    for bone in BONES:
        sim = simulate(
            SimulationParams(
                bone=bone,
                n_frames=args.frames,
                width=args.width,
                height=args.height,
                corrupted_fraction=0.1,
                seed=3,
            )
        )
        sk = skimage_seconds_per_frame(sim.sweep.frames)
        corrupted = set(sim.corruption_kinds)
        for m in SEGMENTERS:
            t = time.perf_counter()
            try:
                r = segment_sweep(sim.sweep, SegmentationParams(method=m))
            except Exception as exc:  # the snake may find nothing: report, continue
                print(f"{bone:9} {m:10} failed: {exc}")
                continue
            dt = (time.perf_counter() - t) / sim.sweep.n_valid
            pts = r.points_mm(sim.sweep)[0]
            d = sim.distance_to_truth(pts)
            allv[m].append(d)
            caught = len(corrupted & set(r.rejected)) / max(1, len(corrupted))
            # Harmless: rejected, or kept with its points on the bone (a false echo's
            # bone found underneath it is a success, not a miss).
            harmless = 0
            for c in r.contours:
                if c.frame in corrupted:
                    if not c.accepted:
                        harmless += 1
                    elif np.median(sim.distance_to_truth(c.points_mm(sim.sweep))) < 0.5:
                        harmless += 1
            harmless_share = harmless / max(1, len(corrupted))
            print(
                f"{bone:9} {m:10} {np.median(d):7.3f} {np.percentile(d, 95):7.3f} "
                f"{100 * np.mean(d > 2):6.2f} {caught:7.2f} {harmless_share:8.2f} "
                f"{1 / dt:7.1f} {sk / dt:9.1f}"
            )
    for m, ds in allv.items():
        if ds:
            d = np.concatenate(ds)
            print(
                f"{'ALL':9} {m:10} {np.median(d):7.3f} {np.percentile(d, 95):7.3f} "
                f"{100 * np.mean(d > 2):6.2f}"
            )

    # Speed on 480x640 frames (issue 7 target: ~15-20 ms per frame for the default).
    sim = simulate(SimulationParams(bone="radius", n_frames=20, width=640, height=480, seed=4))
    t = time.perf_counter()
    segment_sweep(sim.sweep)
    dt = (time.perf_counter() - t) / sim.sweep.n_frames
    sk = skimage_seconds_per_frame(sim.sweep.frames, n=3)
    print(
        f"480x640 shadowpath: {1e3 * dt:.1f} ms/frame ({1 / dt:.0f} frames/s); "
        f"skimage active_contour {1e3 * sk:.0f} ms/frame; ratio {sk / dt:.0f}x"
    )

    if REAL.exists():
        from BoneUSRecon.Logic.sequence_io import read_sweep

        sw = read_sweep(REAL, calibration=REAL_XML)
        for m in SEGMENTERS:
            t = time.perf_counter()
            try:
                r = segment_sweep(sw, SegmentationParams(method=m))
            except Exception as exc:
                print(f"real {m}: {exc}")
                continue
            dt = (time.perf_counter() - t) / sw.n_valid
            print(f"real {m}: {r.summary()} {1e3 * dt:.1f} ms/frame")
            if args.overlay:
                from BoneUSRecon.Widgets.overlay import write_overlays

                write_overlays(sw.frames, r.contours, args.overlay / m, every=5)


if __name__ == "__main__":
    main()

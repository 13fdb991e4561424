"""Real-data benchmark: the default segmenter on the PLUS recording shipped in Resources/SampleData and on augmentations of it.

Prints, for the recording itself, the frames accepted, the per-frame contour extent
(mm) and the time per frame; then, for each augmentation (mirror, gain -30 % / +30 %,
multiplicative speckle, 0.15 mm pixels, a crop, and all of them at once), the frames
accepted and how far the contour moved in reference mm from the original's (median,
95th percentile, share > 2 mm, over the part both contours cover), the share of the
original contour found again ("cover") and of points found beyond its ends
("beyond"). Also the segmenter's speed on 480 x 640 simulated frames.

Run: ``python Testing/benchmarks/bench_real.py [--overlay DIR]`` (with --overlay, PNGs of
all 21 frames with their contours).
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np

from BoneUSRecon.Logic.segmentation import segment_frame, segment_sweep
from BoneUSRecon.Logic.sequence_io import read_sweep
from BoneUSRecon.Logic.simulation import SimulationParams, augment, simulate

# The recording shipped in Resources/SampleData, found by the tests' helper.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from conftest import REAL_MHA, REAL_XML  # noqa: E402

REAL = REAL_MHA


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--overlay", type=Path, help="write overlays of the 21 real frames here")
    args = ap.parse_args()
    warnings.simplefilter("ignore")

    sw = read_sweep(REAL, calibration=REAL_XML)
    t = time.perf_counter()
    r = segment_sweep(sw)
    dt = (time.perf_counter() - t) / sw.n_valid
    sx = float(sw.spacing_mm[0])
    ext = [float(np.ptp(c.points_px[:, 0]) * sx) for c in r.accepted]
    print(
        f"real: {len(r.accepted)}/{sw.n_valid} frames accepted, {1e3 * dt:.1f} ms/frame (820x616)"
    )
    print(f"  contour extent mm: min {min(ext):.1f} median {np.median(ext):.1f} max {max(ext):.1f}")
    print("  per frame:", " ".join(f"{e:.1f}" for e in ext))
    if args.overlay:
        from BoneUSRecon.Widgets.overlay import write_overlays

        write_overlays(sw.frames, r.contours, args.overlay)

    print(
        f"{'augmentation':13} {'accepted':>8} {'median':>7} {'p95':>6} {'>2mm%':>6} {'cover':>6} {'beyond':>6}"
    )
    for name, fn in augment.RECORDING_AUGMENTATIONS.items():
        aug = fn(sw)
        r2 = segment_sweep(aug)
        n = len(r2.accepted)
        d, cover, beyond = augment.contour_agreement(sw, r, aug, r2)
        print(
            f"{name:13} {n:8d} {np.median(d):7.3f} {np.percentile(d, 95):6.3f} "
            f"{100 * np.mean(d > 2):6.2f} {np.median(cover):6.2f} {np.median(beyond):6.2f}"
        )

    # Speed of the segmenter alone (no rejection) on 480 x 640 frames.
    sim = simulate(SimulationParams(bone="radius", n_frames=20, width=640, height=480, seed=4))
    sp = tuple(float(v) for v in sim.sweep.spacing_mm)
    frames = np.asarray(sim.sweep.frames)
    segment_frame(frames[0], sp)
    t = time.perf_counter()
    for f in frames:
        segment_frame(f, sp)
    dt = (time.perf_counter() - t) / len(frames)
    print(f"480x640 shadowpath segmenter alone: {1e3 * dt:.1f} ms/frame ({1 / dt:.0f} frames/s)")


if __name__ == "__main__":
    main()

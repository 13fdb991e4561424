"""Real-data benchmark: the default segmenter on the PLUS recording shipped in Resources/SampleData and on augmentations of it.

Prints, for the recording itself, the frames accepted, the per-frame contour extent
(mm) and the time per frame; then, for each augmentation (mirror, gain -30 % / +30 %,
multiplicative speckle, 0.15 mm pixels, a crop, a curvilinear probe's sector, mirror,
0.15 mm pixels, gain and speckle at once, and another scanner's display chain: display
curves of gamma 0.6 and 1.6, depth gains darker or brighter with depth, 0.15 mm of
smoothing, a noise floor of 12 grey levels), the frames
accepted and how far the contour moved in reference mm from the original's (median,
95th percentile, share > 2 mm, over the part both contours cover), the share of the
original contour found again ("cover") and of points found beyond its ends
("beyond"). Then the reconstruction of the recording and of its hard and look-alike copies scored
against the reference contours of ``Testing/data/L14_reference.csv`` as gold points
(mapped to 3D by each frame's pose: the only real-sweep reconstruction figure we can
compute here), with, as an oracle for diagnosis only, the same segmentation completed
by the reference beyond the kept contours' left / right ends (where the error comes
from). Also the segmenter's speed on 480 x 640 simulated frames.

Run: ``python Testing/benchmarks/bench_real.py [--overlay DIR]`` (with --overlay, PNGs of
all 21 frames with their contours).
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.pipeline import ReconstructionParams, reconstruction_from_segmentation
from BoneUSRecon.Logic.segmentation import segment_frame, segment_sweep
from BoneUSRecon.Logic.segmentation.result import FrameContour, SegmentationResult
from BoneUSRecon.Logic.sequence_io import read_sweep
from BoneUSRecon.Logic.simulation import SimulationParams, augment, simulate
from BoneUSRecon.Logic.simulation.scoring import read_reference_csv
from BoneUSRecon.Logic.sweep import Sweep, pixels_to_reference

# The recording shipped in Resources/SampleData, found by the tests' helper.
sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from conftest import REAL_MHA, REAL_XML  # noqa: E402

REAL = REAL_MHA
REFERENCE = Path(__file__).resolve().parents[1] / "data" / "L14_reference.csv"


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

    reconstruction_against_reference(sw, r)

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


def reconstruction_against_reference(sw: Sweep, r: SegmentationResult) -> None:
    """Gold mean distance of the recording's surface, gold = the reference contours in 3D."""
    ref = read_reference_csv(REFERENCE)
    gold = np.concatenate(
        [pixels_to_reference(sw.image_to_reference[f], ref[f].astype(float)) for f in sorted(ref)]
    )

    def beyond(side: str) -> Callable[[FrameContour], FrameContour]:
        # Oracle: the reference's points past the kept contour's ends on one side or both.
        def edit(c: FrameContour) -> FrameContour:
            t = ref.get(c.frame)
            if not c.accepted or t is None or not len(c.points_px):
                return c
            x = c.points_px[:, 0]
            k = np.zeros(len(t), bool)
            if "L" in side:
                k |= t[:, 0] < x.min()
            if "R" in side:
                k |= t[:, 0] > x.max()
            return dataclasses.replace(
                c,
                points_px=np.r_[c.points_px, t[k].astype(float)],
                intensity=np.r_[c.intensity, np.zeros(int(k.sum()))],
            )

        return edit

    def row(name: str, sweep: Sweep, seg: SegmentationResult) -> None:
        try:
            rec = reconstruction_from_segmentation(sweep, seg, ReconstructionParams())
        except BoneUSReconError as e:
            print(f"{name:34} no surface: {e.message.split(': ')[-1][:60]}")
            return
        e = evaluate_surface(rec.surface, gold)
        d = np.asarray(e.distances)
        print(f"{name:34} {e.mean:6.3f} {e.median:6.3f} {e.p95:6.2f} {100 * np.mean(d <= 1):6.1f}")

    print(f"reconstruction vs the reference contours ({len(gold)} gold points), mm:")
    print(f"{'case':34} {'mean':>6} {'median':>6} {'p95':>6} {'<=1mm%':>6}")
    row("recording", sw, r)
    for side, label in (("L", "left end"), ("R", "right end"), ("LR", "both ends")):
        fixed = dataclasses.replace(r, contours=tuple(map(beyond(side), r.contours)))
        row(f"  oracle: + reference past {label}", sw, fixed)
    copies = {"cadaver": lambda s: augment.harden(s, bone_contours=ref)}
    copies.update(augment.HARD_AUGMENTATIONS)
    # The look-alikes of issue 10 drawn in (a no-contact gap, a fascia, a vessel), on
    # the recording and on its cadaver copy.
    look = augment.LOOKALIKE_AUGMENTATIONS["lookalikes"]
    copies["look-alikes"] = lambda s: look(s, ref)
    copies["cadaver+look-alikes"] = lambda s: look(augment.harden(s, bone_contours=ref), ref)
    for name, fn in copies.items():
        aug = fn(sw)
        row(f"{name} copy", aug, segment_sweep(aug))


if __name__ == "__main__":
    main()

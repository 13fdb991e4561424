"""Frame recall and wrong-structure share over many simulated sweeps, seed by seed (issue 10).

The benchmark the segmentation branches and wrap-ups of ``Testing/benchmarks/README.md``
cite as "the lead's harness": per sweep, the default segmenter's frames kept, frame
recall (share of frames showing bone whose kept points lie on the true surface,
median < 1 mm), wrong-structure share (median > 3 mm), kept points' median distance
(mm) and coverage of the true contour, and the CPU time; then the mean over the sweeps,
the lowest recall and the highest wrong share. ``--reconstruct`` adds each sweep's
surface: gold mean distance (mm) and share of the gold within 1 mm.

Groups of sweeps (40 frames each, per seed):

* ``real``: the five bones, ``realism="hard"``, 475 x 405 pixels at 0.108 mm (the
  cadaver sweep's geometry);
* ``small``: the five bones, hard, 160 x 128 at 0.3 mm, plus the standard humerus and
  clavicle;
* ``grey``: the five bones with the grey shadow alone, 160 x 128 at 0.3 mm;
* ``realstd``: the five bones, standard realism, at the cadaver geometry.
* ``twobones``: the radius and the ulna, standard and hard, at the cadaver geometry
  with the other forearm bone 18 mm beside the one swept (toward the wrist; both show
  whole in the image).
* ``touching``: as ``twobones`` with the other bone 14 mm beside (the two bones' tops
  touch in the image: no tissue between them at their level).
* ``tibiafibula``: the tibia, standard and hard, at the cadaver geometry with the
  fibula (:data:`.simulation.bones.NEIGHBOURS`: 15 mm deeper than the tibia's top)
  20 mm lateral (nearly whole in the 51 mm wide image) and 24 mm (its medial half), as
  in issue 10's lower-leg sweeps.

* ``motion``: the five bones, hard, at the cadaver geometry, swept by an unsteady
  hand: the probe tilted up to 12 degrees, 4 mm of lateral and 2 mm of depth jitter,
  its speed varying by 0.8 (:data:`MOTION`; the simulator's defaults are 4 degrees,
  1.5 mm, 0.7 mm and 0.4).
* ``corrupted``: the five bones, hard, at the cadaver geometry, 15 % of the frames
  corrupted (:mod:`.simulation.corruption`: clutter in the shadow, a false echo over
  the bone, the probe off the skin). Frames with the probe off the skin show no bone;
  a contour kept there counts as a wrong structure.

``--bone-point swept`` gives each sweep a bone point (``RejectionParams.bone_points``)
on the swept bone: the middle of its true contour in the middle frame, as a user would
click on it (``swept-late``: in the frame 90 % of the way through those showing it,
which a live session reaches late). ``--off-centre`` (``twobones`` only) simulates the sweeps 640 columns wide
and keeps 360 of them, with the swept bone's middle 0.65 of the half-width off the
image's middle and its neighbour near the middle: a bone swept near the image's edge,
which the lane rule (``track.central_track``) trades for the neighbour.

``--live N`` segments each sweep as a live session does: its frames fed one at a
time to a :class:`~BoneUSRecon.Logic.live.LiveReconstructor` (no network: the same
reconstructor ``bone-us-recon live`` feeds), a refit every ``N`` frames, and the final
refit scored; the line adds, over the refits during the scan, the share of their kept
frames whose points lie on the swept bone (median < 1 mm) before and after the frames
reached the bone point, and the final refit's warnings.

A seed nobody tuned on is the measure of a change; compare two checkouts on the same
seeds (``PYTHONPATH`` set to each).

Run::

    python Testing/benchmarks/bench_sweeps.py --seeds 53 59 [--groups real small]
        [--reconstruct] [--bone-point swept] [--off-centre] [--live N]
"""

from __future__ import annotations

import argparse
import dataclasses
import time
import warnings

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.pipeline import (
    ReconstructionParams,
    params_with,
    reconstruction_from_segmentation,
)
from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.simulation import BONES, Simulation, SimulationParams, simulate
from BoneUSRecon.Logic.simulation.scoring import score_simulation

GEOMETRY = {
    "R": {"width": 475, "height": 405, "spacing_mm": 0.108},
    "S": {"width": 160, "height": 128, "spacing_mm": 0.3},
}


def cases(group: str, seed: int) -> list[tuple[str, SimulationParams]]:
    """The sweeps of one group for one seed, named as the README's tables name them."""

    def sim(bone: str, geo: str, **kw: object) -> SimulationParams:
        return SimulationParams(bone=bone, n_frames=40, seed=seed, **GEOMETRY[geo], **kw)

    if group == "real":
        return [(f"R {b} hard s{seed}", sim(b, "R", realism="hard")) for b in BONES]
    if group == "small":
        return [(f"S {b} hard s{seed}", sim(b, "S", realism="hard")) for b in BONES] + [
            (f"S {b} std s{seed}", sim(b, "S")) for b in ("humerus", "clavicle")
        ]
    if group == "grey":
        return [
            (f"S {b} grey s{seed}", sim(b, "S", realism="hard", hard_conditions=("grey_shadow",)))
            for b in BONES
        ]
    if group == "realstd":
        return [(f"R {b} std s{seed}", sim(b, "R")) for b in BONES]
    if group == "twobones":
        return [
            (f"R {b} {r[:4]} 18mm s{seed}", sim(b, "R", realism=r, neighbour_mm=18.0))
            for b in ("radius", "ulna")
            for r in ("standard", "hard")
        ]
    if group == "touching":
        return [
            (f"R {b} {r[:4]} 14mm s{seed}", sim(b, "R", realism=r, neighbour_mm=14.0))
            for b in ("radius", "ulna")
            for r in ("standard", "hard")
        ]
    if group == "tibiafibula":
        return [
            (f"R tibia {r[:4]} fib{mm:g} s{seed}", sim("tibia", "R", realism=r, neighbour_mm=mm))
            for r in ("standard", "hard")
            for mm in (20.0, 24.0)
        ]
    if group == "motion":
        return [
            (f"R {b} hard motion s{seed}", sim(b, "R", realism="hard", **MOTION)) for b in BONES
        ]
    if group == "corrupted":
        return [
            (f"R {b} hard corrupt s{seed}", sim(b, "R", realism="hard", corrupted_fraction=0.15))
            for b in BONES
        ]
    raise ValueError(f"unknown group {group!r}")


#: ``motion``: a freehand hand steadier than none (the simulator's defaults: tilt 4
#: degrees, lateral jitter 1.5 mm, depth jitter 0.7 mm, speed varying by 0.4).
MOTION = {
    "tilt_deg": 12.0,
    "lateral_jitter_mm": 4.0,
    "depth_jitter_mm": 2.0,
    "speed_variation": 0.8,
}


#: ``--off-centre``: simulated width, kept width (columns) and the swept bone's offset
#: from the kept image's middle, in its half-widths.
OFF_CENTRE = (640, 360, 0.65)


def off_centre(sim: Simulation) -> Simulation:
    """The simulation with its frames cut to ``OFF_CENTRE[1]`` columns, the swept bone's
    middle ``OFF_CENTRE[2]`` of the half-width off the middle, away from its neighbour;
    poses and true contours moved with the first column kept."""
    _, width, u = OFF_CENTRE
    sw = sim.sweep
    mid = float(np.median([0.5 * (c[0, 0] + c[-1, 0]) for c in sim.true_contours_px if len(c)]))
    # The side of the neighbour along the image's columns (+1: toward higher columns).
    assert sim.neighbour is not None
    side = np.sign(float(sim.neighbour.offset @ sw.image_to_reference[len(sw.frames) // 2, :3, 0]))
    at = width / 2 - side * u * width / 2  # the bone's column in the kept image
    a = int(round(mid - at))
    m = sw.image_to_reference.copy()
    m[:, :3, 3] += a * m[:, :3, 0]
    kept = sw.replace(
        frames=np.ascontiguousarray(sw.frames[:, :, a : a + width]), image_to_reference=m
    )
    contours = [
        c[(c[:, 0] >= a) & (c[:, 0] <= a + width - 1)] - (a, 0) for c in sim.true_contours_px
    ]
    return dataclasses.replace(sim, sweep=kept, true_contours_px=contours)


def swept_point(sim: Simulation, at: float = 0.5) -> np.ndarray:
    """The middle of the swept bone's true contour in the middle frame (of those that
    show it; ``at``: that fraction of the way through them), reference mm: where a
    user clicks on the bone."""
    shown = [k for k, c in enumerate(sim.true_contours_px) if len(c)]
    k = shown[min(int(at * len(shown)), len(shown) - 1)]
    c = sim.true_contours_px[k]
    return sim.sweep.to_reference(k, c[len(c) // 2][None])[0]


def live_segment(
    sim: Simulation, seg_params: object, every: int
) -> tuple[object, list[tuple[int, float]], list[str]]:
    """The sweep fed frame by frame to a live reconstructor, a refit every ``every``
    frames: the final refit's segmentation, per refit (frames received, share of its
    kept frames on the swept bone: median distance < 1 mm), and the final warnings."""
    from BoneUSRecon.Logic.live import LiveReconstructor

    params = dataclasses.replace(ReconstructionParams(), segmentation=seg_params)
    live = LiveReconstructor(params)
    sw = sim.sweep
    on: list[tuple[int, float]] = []
    for n, (k, image) in enumerate(sw.iter_frames(), start=1):
        live.add_frame(image, sw.image_to_reference[k], sw.timestamps[k])
        if n % every == 0 and n < sw.n_frames:
            try:
                acc = live.refit(with_points=False).segmentation.accepted
            except BoneUSReconError:
                continue  # not enough frames yet
            d = [
                np.median(sim.distance_to_truth(sw.to_reference(c.frame, c.points_px))) for c in acc
            ]
            on.append((n, float(np.mean(np.array(d) < 1.0))))
    final = live.refit(final=True)
    return final.segmentation, on, list(final.summary["warnings"])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[53, 59])
    ap.add_argument(
        "--groups",
        nargs="+",
        default=["real", "small"],
        choices=[
            "real",
            "small",
            "grey",
            "realstd",
            "twobones",
            "touching",
            "tibiafibula",
            "motion",
            "corrupted",
        ],
    )
    ap.add_argument("--reconstruct", action="store_true", help="also the surface's gold distance")
    ap.add_argument(
        "--bone-point",
        choices=["none", "swept", "swept-late"],
        default="none",
        help="a bone point on the swept bone (its true contour's middle, middle frame; "
        "swept-late: 90 %% of the way through the frames showing it)",
    )
    ap.add_argument(
        "--off-centre",
        action="store_true",
        help="twobones: the swept bone near the image's edge, its neighbour in the middle",
    )
    ap.add_argument(
        "--live",
        type=int,
        default=0,
        metavar="N",
        help="segment as a live session does, a refit every N frames (0: batch)",
    )
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    from BoneUSRecon.Logic.sweep import frame_planes

    recall, wrong, gold = [], [], []
    for seed in args.seeds:
        for group in args.groups:
            for name, p in cases(group, seed):
                if args.off_centre:
                    p = dataclasses.replace(p, width=OFF_CENTRE[0])
                s = simulate(p)
                if args.off_centre:
                    s = off_centre(s)
                at = {"swept": 0.5, "swept-late": 0.9}.get(args.bone_point)
                points = [swept_point(s, at)] if at is not None else []
                seg_params = params_with(bone_points=points).segmentation
                t = time.process_time()
                try:
                    if args.live:
                        r, on, warned = live_segment(s, seg_params, args.live)
                    else:
                        r = segment_sweep(s.sweep, seg_params)
                except BoneUSReconError as e:
                    print(f"{name:28} no contour: {e}", flush=True)
                    recall.append(0.0)
                    wrong.append(0.0)
                    continue
                dt = time.process_time() - t
                sc = score_simulation(r, s).summary()
                recall.append(sc["recall"])
                wrong.append(sc["wrong_share"])
                line = (
                    f"{name:28} {sc['kept']:3d}/{sc['frames']:<3d} rec {sc['recall']:.2f} "
                    f"wrong {sc['wrong_share']:.2f} med {sc['median_mm']:.3f} "
                    f"cover {sc['coverage']:.2f} {dt:5.1f} s"
                )
                if args.live:
                    # The first frame whose plane passes near the point (the whole sweep
                    # without one): refits before it, and from it on.
                    reach = s.sweep.n_frames
                    if points:
                        o, _, nrm = frame_planes(s.sweep.image_to_reference)
                        z = np.abs(np.einsum("nk,nk->n", points[0] - o, nrm))
                        near = z <= seg_params.rejection.point_plane_mm
                        reach = int(np.argmax(near)) + 1 if near.any() else reach
                    before = [f for n, f in on if n < reach]
                    after = [f for n, f in on if n >= reach]
                    line += (
                        f"  live refits on bone: before the point "
                        f"{np.mean(before) if before else float('nan'):.2f} ({len(before)}), "
                        f"after {np.mean(after) if after else float('nan'):.2f} ({len(after)})"
                        f"; warnings {len(warned)}"
                    )
                if args.reconstruct:
                    try:
                        rec = reconstruction_from_segmentation(s.sweep, r, ReconstructionParams())
                        ev = evaluate_surface(rec.surface, s.gold)
                        d = np.asarray(ev.distances)
                        gold.append((ev.mean, float(np.mean(d <= 1.0))))
                        line += f"  gold {ev.mean:.3f} mm, {100 * gold[-1][1]:.1f} % <= 1 mm"
                    except BoneUSReconError as e:
                        line += f"  no surface: {e}"
                print(line, flush=True)
    a, w = np.array(recall), np.array(wrong)
    print(
        f"MEAN over {a.size} sweeps: recall {a.mean():.3f} wrong {w.mean():.3f} "
        f"(lowest recall {a.min():.2f}, highest wrong {w.max():.2f})"
    )
    if gold:
        g = np.array(gold)
        print(f"MEAN gold {g[:, 0].mean():.3f} mm, {100 * g[:, 1].mean():.1f} % within 1 mm")


if __name__ == "__main__":
    main()

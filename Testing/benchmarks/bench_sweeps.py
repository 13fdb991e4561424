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

A seed nobody tuned on is the measure of a change; compare two checkouts on the same
seeds (``PYTHONPATH`` set to each).

Run::

    python Testing/benchmarks/bench_sweeps.py --seeds 53 59 [--groups real small]
        [--reconstruct]
"""

from __future__ import annotations

import argparse
import time
import warnings

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.pipeline import ReconstructionParams, reconstruction_from_segmentation
from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.simulation import BONES, SimulationParams, simulate
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
    raise ValueError(f"unknown group {group!r}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[53, 59])
    ap.add_argument(
        "--groups",
        nargs="+",
        default=["real", "small"],
        choices=["real", "small", "grey", "realstd", "twobones"],
    )
    ap.add_argument("--reconstruct", action="store_true", help="also the surface's gold distance")
    args = ap.parse_args()
    warnings.simplefilter("ignore")

    recall, wrong, gold = [], [], []
    for seed in args.seeds:
        for group in args.groups:
            for name, p in cases(group, seed):
                s = simulate(p)
                t = time.process_time()
                try:
                    r = segment_sweep(s.sweep)
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

"""A curvilinear probe's field: the segmenter on simulated sweeps blacked out outside a sector.

Scan conversion of a convex (or steered) probe draws a sector, black outside it: the
near rows of the columns at the image's sides are black, the deep rows not. Per sweep
(the five bones, hard realism, 475 x 405 at 0.108 mm, 40 frames) the linear field and
the same frames under :func:`BoneUSRecon.Logic.simulation.augment.sector` (the top row
keeping ``--top`` of the width) are segmented and reconstructed; printed: frame recall,
wrong-structure share, the kept points' coverage of the true contour (median over
frames) and the surface's gold mean distance (mm), and the means over the sweeps.
The gold covers the bone the linear field shows, so the sector's figure also counts
what its narrower field cannot see.

Run::

    python Testing/benchmarks/bench_sector.py [--seeds 5 7] [--top 0.5 0.7]
"""

from __future__ import annotations

import argparse
import dataclasses
import warnings

import numpy as np

from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.pipeline import ReconstructionParams, reconstruction_from_segmentation
from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.simulation import BONES, SimulationParams, augment, simulate
from BoneUSRecon.Logic.simulation.scoring import score_simulation


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[5, 7])
    ap.add_argument("--top", type=float, nargs="+", default=[0.5, 0.7])
    ap.add_argument("--bones", nargs="+", default=list(BONES))
    a = ap.parse_args()
    warnings.simplefilter("ignore")
    rows: dict[str, list[tuple[float, float, float, float]]] = {}
    for seed in a.seeds:
        for bone in a.bones:
            sim = simulate(
                SimulationParams(
                    bone=bone,
                    n_frames=40,
                    seed=seed,
                    realism="hard",
                    width=475,
                    height=405,
                    spacing_mm=0.108,
                )
            )
            line = f"{bone:9s} s{seed}"
            fields = [("linear", sim)] + [
                (f"sector {t:g}", dataclasses.replace(sim, sweep=augment.sector(sim.sweep, t)))
                for t in a.top
            ]
            for name, s in fields:
                r = segment_sweep(s.sweep)
                sc = score_simulation(r, s)
                cover = float(np.median([f.coverage for f in sc.frames if np.isfinite(f.coverage)]))
                rec = reconstruction_from_segmentation(s.sweep, r, ReconstructionParams())
                gold = evaluate_surface(rec.surface, s.gold).mean
                rows.setdefault(name, []).append((sc.recall, sc.wrong_share, cover, gold))
                line += f"  {name}: rec {sc.recall:.2f} wrong {sc.wrong_share:.2f} cover {cover:.2f} gold {gold:.3f}"
            print(line, flush=True)
    for name, v in rows.items():
        m = np.mean(np.array(v), axis=0)
        print(
            f"mean {name:10s} recall {m[0]:.3f} wrong {m[1]:.3f} cover {m[2]:.3f} gold {m[3]:.3f} mm"
        )


if __name__ == "__main__":
    main()

"""One segmentation rule off and on, on the same simulated sweeps (an A/B of a rule).

Each sweep is simulated once and segmented twice, with a boolean field of the
segmentation's parameters off and then at its default (on), e.g. ``rejection.extend_ends``;
both rows are printed, frame recall, wrong-structure share, median point distance and
coverage (:mod:`BoneUSRecon.Logic.simulation.scoring`), and where the kept frames differ
both surfaces' mean gold distance. Sweeps are the groups of ``bench_sweeps.py`` and, with
``--free``, hard sweeps of every bone at both geometries whose first or last 3 or 10 of 40
frames show no bone (``SimulationParams.bone_free_frames``: a frame kept there is wrong).

Run: ``python Testing/benchmarks/bench_ablation.py rejection.extend_ends --seeds 229 237
--groups motion [--free]``. Measured: ``Testing/benchmarks/README.md``, session 38.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import warnings
from pathlib import Path

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.pipeline import ReconstructionParams, reconstruction_from_segmentation
from BoneUSRecon.Logic.segmentation import SegmentationParams, segment_sweep
from BoneUSRecon.Logic.simulation import BONES, SimulationParams, simulate
from BoneUSRecon.Logic.simulation.scoring import score_simulation

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sweeps import GEOMETRY, cases  # noqa: E402

GROUPS = ("real", "small", "grey", "realstd", "twobones", "touching", "tibiafibula")
GROUPS += ("motion", "corrupted")


def with_flag(params: SegmentationParams, flag: str, on: bool) -> SegmentationParams:
    """``params`` with the boolean field ``flag`` ("section.field") set to ``on``."""
    section, field = flag.split(".")
    sub = getattr(params, section)
    if not isinstance(getattr(sub, field), bool):
        raise SystemExit(f"{flag} is not a boolean parameter")
    return dataclasses.replace(params, **{section: dataclasses.replace(sub, **{field: on})})


def free_cases(seed: int) -> list[tuple[str, SimulationParams]]:
    """Hard sweeps of every bone, both geometries, 3 or 10 bone-free frames at an end."""
    return [
        (
            f"{geo} {b} free{fr} s{seed}",
            SimulationParams(
                bone=b,
                n_frames=40,
                seed=seed,
                realism="hard",
                bone_free_frames=fr,
                **GEOMETRY[geo],
            ),
        )
        for geo in ("S", "R")
        for b in BONES
        for fr in ((3, 0), (0, 3), (10, 0), (0, 10))
    ]


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("flag", help='a boolean segmentation parameter, "section.field"')
    ap.add_argument("--seeds", type=int, nargs="+", default=[229])
    ap.add_argument("--groups", nargs="*", default=[], choices=GROUPS)
    ap.add_argument("--free", action="store_true", help="also the bone-free-end sweeps")
    args = ap.parse_args()
    warnings.simplefilter("ignore")
    params = {on: with_flag(SegmentationParams(), args.flag, on) for on in (False, True)}
    todo = []
    for seed in args.seeds:
        for g in args.groups:
            todo += cases(g, seed)
        if args.free:
            todo += free_cases(seed)
    rows: dict[bool, list[tuple[float, float, float, float]]] = {False: [], True: []}
    changed = 0
    for name, p in todo:
        sim = simulate(p)
        res = {}
        for on in (False, True):
            try:
                res[on] = segment_sweep(sim.sweep, params[on])
            except BoneUSReconError as e:
                print(f"{name:30} {args.flag}={on}: no contour: {e}", flush=True)
        if len(res) < 2:
            continue
        line = f"{name:30}"
        for on in (False, True):
            sc = score_simulation(res[on], sim).summary()
            rows[on].append((sc["recall"], sc["wrong_share"], sc["median_mm"], sc["coverage"]))
            line += (
                f" | rec {sc['recall']:.3f} wr {sc['wrong_share']:.3f}"
                f" med {sc['median_mm']:.3f} cov {sc['coverage']:.3f}"
            )
        kept = {on: [c.accepted for c in res[on].contours] for on in res}
        if kept[False] != kept[True]:
            changed += 1
            for on in (False, True):
                try:
                    rec = reconstruction_from_segmentation(
                        sim.sweep, res[on], ReconstructionParams()
                    )
                    line += f" gold{'-+'[on]} {evaluate_surface(rec.surface, sim.gold).mean:.3f}"
                except BoneUSReconError:
                    line += f" gold{'-+'[on]} none"
            line += "  CHANGED"
        print(line, flush=True)
    for on in (False, True):
        t = np.array(rows[on])
        if t.size:
            print(
                f"{args.flag}={on}: {len(t)} sweeps, recall {t[:, 0].mean():.4f} wrong "
                f"{t[:, 1].mean():.4f} median {t[:, 2].mean():.4f} mm cover {t[:, 3].mean():.4f}"
                f" (lowest recall {t[:, 0].min():.2f}, highest wrong {t[:, 1].max():.2f})"
            )
    print(f"kept frames changed in {changed} of {len(rows[True])} sweeps")


if __name__ == "__main__":
    main()

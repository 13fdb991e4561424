"""Frame recall / wrong share of the default segmenter with optional features switched on (issue 10, item 5).

Runs ``shadowpath`` (only) on the rows of ``bench_segmentation.py --table-only`` that
the features could change: every bone standard and hard (seed 5), each hard condition
alone on the tibia (seed 5), the grey shadow alone on the small bones and the hard
tibia / humerus at seeds 5, 7, 13, and the real L14 recording with its augmentations
(scored against ``Testing/data/L14_reference.csv``). Prints one line per case: frames
kept / scored, recall, wrong share, median and p95 distance (mm), seconds.

``--set name=value`` (repeatable) sets a ``ShadowPathParams`` field, e.g.
``--set confidence_weight=0.5`` or ``--set phase_weight=0.5``; without it the
defaults run (the "before" column). ``--only SUBSTR`` keeps the cases whose name
contains one of the given substrings.

Run::

    python Testing/benchmarks/bench_features.py [--set confidence_weight=0.5] [--only tibia L14]
"""

from __future__ import annotations

import argparse
import ast
import sys
import time
import warnings
from dataclasses import fields, replace
from pathlib import Path

from BoneUSRecon.Logic.segmentation import SegmentationParams, ShadowPathParams, segment_sweep
from BoneUSRecon.Logic.simulation import BONES, HARD_CONDITIONS, SimulationParams, simulate

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_segmentation import RECORDINGS, _row  # noqa: E402


def cases() -> list[tuple[str, SimulationParams]]:
    """The simulated cases: (name, parameters)."""

    def sim(
        bone: str, seed: int = 5, realism: str = "standard", cond: str = ""
    ) -> SimulationParams:
        kw = dict(n_frames=40, width=160, height=128, spacing_mm=0.3, seed=seed)
        if cond:
            kw["hard_conditions"] = (cond,)
        return SimulationParams(bone=bone, realism=realism, **kw)

    out = [(f"{b} standard", sim(b)) for b in BONES]
    out += [(f"{b} hard", sim(b, realism="hard")) for b in BONES]
    out += [(f"tibia hard:{c}", sim("tibia", realism="hard", cond=c)) for c in HARD_CONDITIONS]
    for seed in (7, 13):
        out += [(f"{b} hard s{seed}", sim(b, seed, "hard")) for b in ("tibia", "humerus")]
    for b in ("radius", "ulna", "clavicle"):
        out += [(f"{b} grey_shadow s{s}", sim(b, s, "hard", "grey_shadow")) for s in (5, 7, 13)]
    return out


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--set", action="append", default=[], help="ShadowPathParams field=value")
    ap.add_argument("--only", nargs="+", default=None, help="case name substrings")
    ap.add_argument("--no-real", action="store_true", help="skip the L14 rows")
    args = ap.parse_args(argv)
    warnings.simplefilter("ignore")
    names = {f.name for f in fields(ShadowPathParams)}
    over = {}
    for item in args.set:
        key, _, val = item.partition("=")
        if key not in names:
            ap.error(f"unknown ShadowPathParams field {key!r}")
        over[key] = ast.literal_eval(val)
    params = SegmentationParams(shadowpath=replace(ShadowPathParams(), **over))
    print(f"shadowpath with {over or 'defaults'}", flush=True)

    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.simulation.scoring import (
        read_reference_csv,
        score_reference,
        score_simulation,
    )

    def run(sweep):  # type: ignore[no-untyped-def]
        try:
            return segment_sweep(sweep, params)
        except BoneUSReconError:
            return None

    def keep(name: str) -> bool:
        return args.only is None or any(s in name for s in args.only)

    for name, sp in cases():
        if not keep(name):
            continue
        s = simulate(sp)
        t = time.perf_counter()
        r = run(s.sweep)
        dt = time.perf_counter() - t
        print(
            _row(name, "shadowpath", None if r is None else score_simulation(r, s).summary(), dt),
            flush=True,
        )
    if args.no_real:
        return 0
    from BoneUSRecon.Logic.sequence_io import read_sweep
    from BoneUSRecon.Logic.simulation import augment

    name, mha, xml, csv = RECORDINGS[0]
    if not (mha.exists() and csv.exists()):
        print(f"{name}: recording or reference absent, skipped")
        return 0
    sw = read_sweep(mha, calibration=xml)
    ref = read_reference_csv(csv)
    variants = {"": sw} | {f" {k}": f(sw) for k, f in augment.HARD_AUGMENTATIONS.items()}
    variants[" cadaver"] = augment.harden(sw, bone_contours=ref)
    for suffix, s in variants.items():
        if not keep(f"{name}{suffix}"):
            continue
        t = time.perf_counter()
        r = run(s)
        dt = time.perf_counter() - t
        row = None if r is None else score_reference(r, s, ref).summary()
        print(_row(f"{name}{suffix}", "shadowpath", row, dt), flush=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

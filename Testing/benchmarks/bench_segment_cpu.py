"""CPU time of ``segment_sweep`` per frame (default shadowpath), one core (issues 10 and 11).

Simulates 480x640 sweeps (clavicle and tibia, standard and hard realism) at 0.15 and
0.075 mm per pixel and prints, per sweep, the CPU time (``time.process_time``, best of
``--repeat`` runs: the machine may be shared, and CPU time is what one core spends) of
``segment_sweep`` per frame and the frames/s it allows. ``OMP_NUM_THREADS`` and the like
are set to 1 before numpy is imported.

``--against DIR`` loads a second checkout's package (``DIR/BoneUSRecon``) side by side
and alternates the two on the same sweeps, run by run (on a shared machine the load
drifts between separate runs by more than the difference measured); it prints both
and checks that they give the same contours.

Target (issue 10): >= 30 frames/s at 480x640, 0.15 mm, on one core.

Run::

    python Testing/benchmarks/bench_segment_cpu.py [--frames 30] [--repeat 3]
        [--spacings 0.15 0.075] [--cases clavicle:standard tibia:hard] [--against DIR]
"""

from __future__ import annotations

import os

for _v in ("OMP_NUM_THREADS", "OPENBLAS_NUM_THREADS", "MKL_NUM_THREADS", "NUMEXPR_NUM_THREADS"):
    os.environ[_v] = "1"

import argparse  # noqa: E402
import importlib  # noqa: E402
import sys  # noqa: E402
import time  # noqa: E402
from collections.abc import Callable  # noqa: E402
from pathlib import Path  # noqa: E402

import numpy as np  # noqa: E402

from BoneUSRecon.Logic.segmentation import segment_sweep  # noqa: E402
from BoneUSRecon.Logic.simulation import SimulationParams, simulate  # noqa: E402


def load_other(root: Path) -> Callable:
    """``segment_sweep`` of the package under ``root``, loaded beside the current one."""
    ours = {k: v for k, v in sys.modules.items() if k.split(".")[0] == "BoneUSRecon"}
    for k in ours:
        del sys.modules[k]
    sys.path.insert(0, str(root))
    try:
        seg = importlib.import_module("BoneUSRecon.Logic.segmentation")
        fn = seg.segment_sweep  # lazy attributes resolve now, from root
        seg.frame_candidates_for, seg.select_bone_track  # noqa: B018
    finally:
        sys.path.remove(str(root))
        for k in [k for k in sys.modules if k.split(".")[0] == "BoneUSRecon"]:
            del sys.modules[k]
        sys.modules.update(ours)
    return fn


def same(a, b) -> bool:  # type: ignore[no-untyped-def]
    """Two segmentation results with the same contours, decisions and confidences."""
    return all(
        np.array_equal(x.points_px, y.points_px)
        and (x.accepted, x.reason, x.detail, x.confidence)
        == (y.accepted, y.reason, y.detail, y.confidence)
        for x, y in zip(a.contours, b.contours, strict=True)
    )


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=30)
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--spacings", type=float, nargs="+", default=[0.15, 0.075])
    ap.add_argument("--against", type=Path, help="another checkout to alternate with")
    ap.add_argument(
        "--cases",
        nargs="+",
        default=["clavicle:standard", "clavicle:hard", "tibia:standard", "tibia:hard"],
        help="bone:realism pairs",
    )
    args = ap.parse_args(argv)
    runs: dict[str, Callable] = {"this": segment_sweep}
    if args.against is not None:
        runs = {"other": load_other(args.against.resolve()), "this": segment_sweep}
    print(f"segment_sweep CPU per frame, 480x640, {args.frames} frames, best of {args.repeat}")
    for spacing in args.spacings:
        for case in args.cases:
            bone, realism = case.split(":")
            sim = simulate(
                SimulationParams(
                    bone=bone,
                    n_frames=args.frames,
                    width=640,
                    height=480,
                    spacing_mm=spacing,
                    realism=realism,
                    seed=0,
                )
            )
            n = int(sim.sweep.valid_indices.size)
            best = dict.fromkeys(runs, float("inf"))
            out = {}
            for r in range(args.repeat):
                for name in list(runs) if r % 2 == 0 else list(runs)[::-1]:
                    c0 = time.process_time()
                    out[name] = runs[name](sim.sweep)
                    best[name] = min(best[name], time.process_time() - c0)
            line = "  ".join(
                f"{name} {1e3 * t / n:6.2f} ms/frame {n / t:6.1f} frames/s"
                for name, t in best.items()
            )
            if len(runs) > 1:
                line += f"  ({100 * (best['this'] / best['other'] - 1):+.0f} %, "
                line += "same contours)" if same(out["this"], out["other"]) else "CONTOURS DIFFER)"
            print(f"  {spacing:5.3f} mm  {bone:9s} {realism:8s}  {line}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

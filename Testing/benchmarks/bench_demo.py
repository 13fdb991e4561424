"""Benchmark: ``bone-us-recon demo`` end to end (issue 5: under 30 s on two cores).

Runs the demo command as a user would (a fresh ``python -m BoneUSRecon demo`` process,
so imports count) ``--repeat`` times into temporary folders, and prints the wall time
of each run, the time per stage measured in-process (simulate, write, reconstruct,
evaluate, Table I, report), and the accuracy the demo reports. Run::

    python Testing/benchmarks/bench_demo.py [--repeat 3] [--frames 150] [--keep DIR]
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path


def stages(frames: int, outdir: Path) -> dict[str, float]:
    """Time each step of the demo in this process (after imports)."""
    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.pipeline import control_point_table, reconstruct
    from BoneUSRecon.Logic.simulation import SimulationParams, simulate, write_simulation
    from BoneUSRecon.Logic.vtkio import read_points
    from BoneUSRecon.Widgets.report import write_report

    t: dict[str, float] = {}
    t0 = time.perf_counter()
    sim = simulate(SimulationParams(n_frames=frames, corrupted_fraction=0.05))
    t["simulate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    files = write_simulation(sim, outdir)
    gold = read_points(files["gold"])
    t["write simulation"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    recon = reconstruct(sim.sweep)
    t["reconstruct"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    ev = evaluate_surface(recon.surface, gold)
    t["evaluate"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    table = control_point_table(recon, gold)
    t["Table I (4 refits)"] = time.perf_counter() - t0
    t0 = time.perf_counter()
    write_report(
        recon,
        outdir / "report",
        gold=gold,
        evaluation=ev,
        table=table,
        truth_px=sim.true_contours_px,
    )
    t["report"] = time.perf_counter() - t0
    return t


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeat", type=int, default=3)
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--keep", metavar="DIR", help="keep the last demo's output here")
    args = ap.parse_args()

    print(f"bone-us-recon demo, {args.frames} frames, {os.cpu_count()} CPUs")
    walls = []
    doc = {}
    with tempfile.TemporaryDirectory() as tmp:
        for r in range(args.repeat):
            out = Path(args.keep) if args.keep and r == args.repeat - 1 else Path(tmp) / f"run{r}"
            t0 = time.perf_counter()
            proc = subprocess.run(
                [
                    sys.executable,
                    "-m",
                    "BoneUSRecon",
                    "demo",
                    str(out),
                    "--frames",
                    str(args.frames),
                    "--json",
                ],
                capture_output=True,
                text=True,
                check=True,
            )
            walls.append(time.perf_counter() - t0)
            doc = json.loads(proc.stdout)
            print(
                f"  run {r + 1}: {walls[-1]:.1f} s wall (command's own timer "
                f"{doc['elapsed_s']:.1f} s)"
            )
        print(f"  best {min(walls):.1f} s, worst {max(walls):.1f} s (goal: < 30 s)")
        ev = doc["evaluation"]
        print(
            f"  accuracy: mean {ev['mean_mm']:.3f} mm, RMS {ev['rms_mm']:.3f} mm, "
            f"p95 {ev['p95_mm']:.3f} mm, within 1 mm {100 * ev['within_1mm']:.1f} % "
            f"(paper: 1.16 to 1.71 mm mean)"
        )
        print(
            "  Table I: "
            + ", ".join(f"e={r['control_points']}: {r['mean_mm']:.3f} mm" for r in doc["table_i"])
        )
        print("stages, in-process (after imports):")
        for name, sec in stages(args.frames, Path(tmp) / "stages").items():
            print(f"  {name:<20} {sec:6.2f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())

"""Reconstruction benchmark (issue 4 section 5): accuracy against the truth, and speed.

For simulated sweeps of every bone, clean and with 10 % corrupted frames, runs the
whole pipeline (default segmenter -> resampling -> robust B-spline fit -> mesh) and
prints:

* mean and 95th-percentile distance (mm) from the simulator's gold points (digitised
  on the imaged upper bone surface with 0.2 mm noise, so ~0.16 mm mean is the floor)
  to the reconstructed surface;
* the share of gold points within 1 mm (``<=1mm%``); the simulator digitises gold on
  the bone the sweep imaged, between the first and last frames' planes
  (``gold_region="imaged"``); ``sw mean`` / ``sw<=1mm%`` give the old definition
  (``"swept"``: the whole axis range, up to ~4 mm beyond an end plane on a wide bone);
* the share of the surface *area* within 0.35 mm of the true bone (triangle centroids,
  area-weighted, exact distance from the simulator);
* frames rejected by segmentation and by the robust fit.

Then times resampling + fitting for a 250-frame sweep (median of repeats; the
simulator's true contours as input, ~80 points per frame like the segmenter's).
With ``--truth-contours`` the accuracy rows use the true contours too, isolating
steps C-D from segmentation. ``--control-points`` prints Table I per bone. ``--paper``
runs the paper's choices (snake, straight axis, separable plain least squares).

Run: ``python Testing/benchmarks/bench_reconstruction.py [--frames 150] [--bones clavicle ulna]``
Also: the surface's area-weighted p95 distance to the true bone (``s2t p95``),
triangles per mm^2 and the time of each stage (and the surface stage's share of the
whole run).

Targets (issue 11): mean <= 0.22 mm and p95 <= 0.55 mm clean; <= 0.25 / 0.65 mm with
10 % corruption; >= 98 % of gold within 1 mm; surface-to-true-bone p95 <= 0.35 mm
(and >= 95 % of the area within 0.35 mm); 5-25 triangles per mm^2; the surface stage
<= 10 % of the run; resampling + fitting < 50 ms for 250 frames.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
import warnings

import numpy as np

from BoneUSRecon.Logic.bspline import fit_surface
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.pipeline import (
    ReconstructionParams,
    control_point_table,
    reconstruct,
    surface_from_contours,
)
from BoneUSRecon.Logic.resampling import resample
from BoneUSRecon.Logic.simulation import BONES, SimulationParams, sample_gold, simulate
from BoneUSRecon.Logic.surface import triangle_centroids
from BoneUSRecon.Logic.sweep import pixels_to_reference

TARGETS = {0.0: (0.22, 0.55), 0.1: (0.25, 0.65)}


def true_contours(sim):
    sw = sim.sweep
    return [
        (k, pixels_to_reference(sw.image_to_reference[k], c))
        for k, c in enumerate(sim.true_contours_px)
        if len(c) >= 2 and sw.valid[k]
    ]


def area_within(sim, surface, tol: float = 0.35) -> float:
    c, a = triangle_centroids(surface)
    return float((a * (sim.distance_to_truth(c) <= tol)).sum() / a.sum())


def truth_p95(sim, surface) -> float:
    """Area-weighted 95th percentile of the surface's distance to the true bone (mm)."""
    c, a = triangle_centroids(surface)
    d = sim.distance_to_truth(c)
    o = np.argsort(d)
    cum = np.cumsum(a[o]) / a.sum()
    return float(d[o][np.searchsorted(cum, 0.95)])


def density(surface) -> float:
    """Triangles per mm^2."""
    return surface.GetNumberOfCells() / float(triangle_centroids(surface)[1].sum())


def time_resample_fit(n_frames: int, repeats: int, seed: int) -> tuple[float, float, float]:
    sim = simulate(SimulationParams(bone="clavicle", n_frames=n_frames, seed=seed))
    cont = true_contours(sim)
    p = ReconstructionParams()
    resample(cont, sim.sweep, p.resampling)  # warm-up (imports, caches)
    tr, tf, cpu = [], [], []
    for _ in range(repeats):
        c0 = time.process_time()
        t0 = time.perf_counter()
        g = resample(cont, sim.sweep, p.resampling)
        t1 = time.perf_counter()
        fit_surface(g.points, p.fit, u=g.axis_position, v=g.angles)
        t2 = time.perf_counter()
        cpu.append(time.process_time() - c0)
        tr.append(t1 - t0)
        tf.append(t2 - t1)
    npts = float(np.mean([c.shape[0] for _, c in cont]))
    return float(np.median(tr)), float(np.median(tf)), float(np.median(cpu)), npts


def run_one(sim, params, truth: bool):
    if truth:
        timings: dict[str, float] = {}
        grid, fit, surf = surface_from_contours(
            true_contours(sim), sim.sweep, params, timings=timings
        )
        return grid, fit, surf, timings, 0, 0.0, None
    recon = reconstruct(sim.sweep, params)
    t = recon.timings
    return (
        recon.grid,
        recon.fit,
        recon.surface,
        t,
        recon.summary["rejected_frames"],
        t["segment"],
        recon,
    )


def paper_params() -> ReconstructionParams:
    """The paper's pipeline: snake, straight axis, de Boor separable LSQ, no reweighting."""
    p = ReconstructionParams()
    return dataclasses.replace(
        p,
        segmentation=dataclasses.replace(p.segmentation, method="snake"),
        resampling=dataclasses.replace(p.resampling, axis="line"),
        fit=dataclasses.replace(p.fit, method="separable", robust="none"),
    )


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--frames", type=int, default=150)
    ap.add_argument("--bones", nargs="+", default=list(BONES))
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--truth-contours", action="store_true", help="skip segmentation")
    ap.add_argument("--control-points", action="store_true", help="also print Table I")
    ap.add_argument(
        "--timing-frames", type=int, default=250, help="frames of the timed sweep (0: no timing)"
    )
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument(
        "--paper",
        action="store_true",
        help="the paper's choices: snake segmenter, straight axis, separable plain least squares",
    )
    ap.add_argument("--json", help="also write the rows to this JSON file")
    ap.add_argument(
        "--thin-weight", type=float, help="FitParams.thin_weight (default: its default)"
    )
    ap.add_argument("--step-mm", type=float, help="SurfaceParams.step_mm (default: its default)")
    ap.add_argument(
        "--corrupted",
        type=float,
        nargs="+",
        default=[0.0, 0.1],
        choices=sorted(TARGETS),
        help="corrupted-frame fractions to run (default both)",
    )
    args = ap.parse_args()
    warnings.simplefilter("ignore")

    rows = []
    hdr = (
        f"{'bone':9} {'corr':>4} {'mean':>6} {'p95':>6} {'<=1mm%':>7} {'sw mean':>7} {'sw<=1mm%':>8} {'area<=.35%':>10} {'s2t p95':>7} "
        f"{'tri/mm2':>7} {'rej.seg':>7} {'rej.fit':>7} {'cover%':>6} {'seg s':>6} {'res ms':>6} "
        f"{'fit ms':>6} {'srf ms':>6} {'srf%':>5}  targets"
    )
    print(hdr)
    for bone in args.bones:
        for corr in args.corrupted:
            sim = simulate(
                SimulationParams(
                    bone=bone, n_frames=args.frames, corrupted_fraction=corr, seed=args.seed
                )
            )
            params = paper_params() if args.paper else ReconstructionParams()
            if args.thin_weight is not None:
                params = dataclasses.replace(
                    params, fit=dataclasses.replace(params.fit, thin_weight=args.thin_weight)
                )
            if args.step_mm is not None:
                params = dataclasses.replace(
                    params, surface=dataclasses.replace(params.surface, step_mm=args.step_mm)
                )
            t0 = time.perf_counter()
            try:
                grid, fit, surf, timings, rej_seg, seg_s, recon = run_one(
                    sim, params, args.truth_contours
                )
            except BoneUSReconError as exc:
                print(f"{bone:9} {corr:4.1f} FAILED: {exc}", flush=True)
                rows.append(
                    {"bone": bone, "corrupted": corr, "error": str(exc), "meets_targets": False}
                )
                continue
            ev = evaluate_surface(surf, sim.gold)
            ev_sw = evaluate_surface(surf, sample_gold(sim, "swept"))
            aw = area_within(sim, surf)
            tp95 = truth_p95(sim, surf)
            dens = density(surf)
            cd_ms = 1000 * (timings["resample"] + timings["fit"])
            total = timings.get("total", timings["resample"] + timings["fit"] + timings["surface"])
            srf_share = timings["surface"] / total
            tm, tp = TARGETS[corr]
            ok = (
                ev.mean <= tm
                and ev.p95 <= tp
                and aw >= 0.95
                and ev.within_1 >= 0.98
                and tp95 <= 0.35
                and 5 <= dens <= 25
            )
            row = {
                "bone": bone,
                "corrupted": corr,
                "mean_mm": ev.mean,
                "p95_mm": ev.p95,
                "within_1mm": ev.within_1,
                "swept_gold": {
                    "mean_mm": ev_sw.mean,
                    "p95_mm": ev_sw.p95,
                    "within_1mm": ev_sw.within_1,
                },
                "area_within_0_35mm": aw,
                "surface_to_truth_p95_mm": tp95,
                "triangles_per_mm2": dens,
                "stage_s": {k: float(v) for k, v in timings.items()},
                "surface_share": srf_share,
                "rejected_segmentation": rej_seg,
                "rejected_fit": int((fit.frame_weights <= 0).sum()),
                "corrupted_frames": int(len(sim.corrupted)),
                "grid_coverage": grid.coverage,
                "resampling_distance_mm": grid.mean_resampling_distance_mm,
                "segment_s": seg_s,
                "resample_fit_ms": cd_ms,
                "total_s": time.perf_counter() - t0,
                "meets_targets": ok,
            }
            rows.append(row)
            print(
                f"{bone:9} {corr:4.1f} {ev.mean:6.3f} {ev.p95:6.3f} {100 * ev.within_1:7.1f} "
                f"{ev_sw.mean:7.3f} {100 * ev_sw.within_1:8.1f} "
                f"{100 * aw:10.1f} {tp95:7.3f} {dens:7.1f} {rej_seg:7d} {row['rejected_fit']:7d} "
                f"{100 * grid.coverage:6.1f} {seg_s:6.1f} {1000 * timings['resample']:6.1f} "
                f"{1000 * timings['fit']:6.1f} {1000 * timings['surface']:6.1f} {100 * srf_share:5.1f}  "
                f"{'ok' if ok else 'MISSED'} (<= {tm}/{tp})",
                flush=True,
            )
            if args.control_points and recon is not None:
                table = control_point_table(recon, sim.gold, (5, 10, 15, 20, 30))
                print("          Table I: " + "  ".join(f"e={e}: {d:.3f}" for e, d in table))
    means = np.array([[r["mean_mm"], r["p95_mm"]] for r in rows if "mean_mm" in r]).reshape(-1, 2)
    if means.size:
        print(
            f"all: mean of means {means[:, 0].mean():.3f} mm, worst p95 {means[:, 1].max():.3f} mm, "
            f"{sum(r['meets_targets'] for r in rows)}/{len(rows)} rows meet the targets"
        )

    timing = None
    if args.timing_frames >= 2:  # 0 (or 1): no timing asked (a sweep needs two frames)
        tr, tf, cpu, npts = time_resample_fit(args.timing_frames, args.repeats, args.seed)
        print(
            f"timing ({args.timing_frames} frames, {npts:.0f} contour points/frame, median of "
            f"{args.repeats}): resample {1000 * tr:.1f} ms + fit {1000 * tf:.1f} ms = "
            f"{1000 * (tr + tf):.1f} ms wall, {1000 * cpu:.1f} ms CPU (target < 50 ms; wall "
            f"time is inflated when other processes share the cores)"
        )
        timing = {"resample": 1000 * tr, "fit": 1000 * tf, "cpu": 1000 * cpu}
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"rows": rows, "timing_ms": timing}, f, indent=2)


if __name__ == "__main__":
    main()

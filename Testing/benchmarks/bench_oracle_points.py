"""Benchmark: what a sweep's gold distance would be with parts of its points made true.

Where the reconstruction error of a hard simulated sweep comes from (issue 10): the
sweep is segmented as the pipeline does, then reconstructed from the same
segmentation with one kind of error removed using the simulator's true contours
(an oracle, for diagnosis only; nothing here is a method):

* ``as segmented``: the pipeline's figure;
* ``wrong frames dropped``: accepted frames whose points lie 2 mm or more (median)
  from the true contour are rejected;
* ``points > 2 mm dropped`` / ``points > 1 mm dropped``: only the kept points that far
  from the true contour are removed;
* ``true contour within kept span``: each accepted frame's points replaced by the true
  contour over the same columns (point accuracy made perfect, lateral reach unchanged);
* ``kept + missed true columns``: the true contour's columns beyond the kept contour's
  ends added (lateral reach made perfect, kept points unchanged), in all frames or in
  the first / second half of the sweep only.

Usage (from the worktree, ``PYTHONPATH`` set to it)::

    python Testing/benchmarks/bench_oracle_points.py --bone tibia --seeds 5,7 --geometry S

``S`` is 160 x 128 pixels at 0.3 mm, ``R`` 475 x 405 at 0.108 mm (the hard-sweep rows of
``Testing/benchmarks/README.md``), 40 frames, ``realism="hard"``.
"""

from __future__ import annotations

import argparse
import dataclasses
from collections.abc import Callable

import numpy as np
from scipy.spatial import cKDTree

from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.pipeline import ReconstructionParams, reconstruction_from_segmentation
from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.segmentation.result import FrameContour
from BoneUSRecon.Logic.simulation import SimulationParams, simulate

GEOMETRY = {
    "S": {"width": 160, "height": 128, "spacing_mm": 0.3},
    "R": {"width": 475, "height": 405, "spacing_mm": 0.108},
}


def _variants(sim, sp: float) -> dict[str, Callable[[FrameContour], FrameContour]]:
    """The oracle edits of one frame's contour, by name."""

    def dist(c: FrameContour) -> np.ndarray:
        t = sim.true_contours_px[c.frame]
        if not len(t) or not len(c.points_px):
            return np.full(len(c.points_px), np.inf)
        return cKDTree(t).query(c.points_px)[0] * sp

    def drop_wrong(c: FrameContour) -> FrameContour:
        if not c.accepted or np.median(dist(c)) < 2.0:
            return c
        return dataclasses.replace(c, accepted=False, reason="oracle")

    def drop_far(lim: float) -> Callable[[FrameContour], FrameContour]:
        def f(c: FrameContour) -> FrameContour:
            if not c.accepted:
                return c
            k = dist(c) <= lim
            return dataclasses.replace(c, points_px=c.points_px[k], intensity=c.intensity[k])

        return f

    def true_span(c: FrameContour) -> FrameContour:
        t = sim.true_contours_px[c.frame]
        if not c.accepted or not len(t) or not len(c.points_px):
            return c
        x = c.points_px[:, 0]
        k = (t[:, 0] >= x.min()) & (t[:, 0] <= x.max())
        if k.sum() < 2:
            return dataclasses.replace(c, accepted=False, reason="oracle")
        return dataclasses.replace(c, points_px=t[k], intensity=np.zeros(int(k.sum())))

    def missed(lo: int, hi: int) -> Callable[[FrameContour], FrameContour]:
        def f(c: FrameContour) -> FrameContour:
            t = sim.true_contours_px[c.frame]
            if not (lo <= c.frame <= hi) or not c.accepted or not len(t) or not len(c.points_px):
                return c
            x = c.points_px[:, 0]
            k = (t[:, 0] < x.min()) | (t[:, 0] > x.max())
            return dataclasses.replace(
                c,
                points_px=np.r_[c.points_px, t[k]],
                intensity=np.r_[c.intensity, np.zeros(int(k.sum()))],
            )

        return f

    n = len(sim.true_contours_px)
    return {
        "as segmented": lambda c: c,
        "wrong frames dropped": drop_wrong,
        "points > 2 mm dropped": drop_far(2.0),
        "points > 1 mm dropped": drop_far(1.0),
        "true contour within kept span": true_span,
        "kept + missed true columns": missed(0, n - 1),
        "  same, first half of frames": missed(0, n // 2 - 1),
        "  same, second half of frames": missed(n // 2, n - 1),
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--bone", default="tibia")
    ap.add_argument("--seeds", default="5,7")
    ap.add_argument("--geometry", choices=sorted(GEOMETRY), default="S")
    a = ap.parse_args()
    geo = GEOMETRY[a.geometry]
    for seed in (int(s) for s in a.seeds.split(",")):
        sim = simulate(SimulationParams(bone=a.bone, seed=seed, realism="hard", n_frames=40, **geo))
        seg = segment_sweep(sim.sweep)
        for name, edit in _variants(sim, geo["spacing_mm"]).items():
            s2 = dataclasses.replace(seg, contours=tuple(edit(c) for c in seg.contours))
            rec = reconstruction_from_segmentation(sim.sweep, s2, ReconstructionParams())
            ev = evaluate_surface(rec.surface, sim.gold)
            d = np.asarray(ev.distances)
            n_pts = sum(len(c.points_px) for c in s2.accepted)
            print(
                f"{a.geometry} {a.bone} seed {seed}  {name:32s} gold mean {ev.mean:.3f} mm"
                f"  within 1 mm {np.mean(d <= 1.0):.3f}  points {n_pts}",
                flush=True,
            )


if __name__ == "__main__":
    main()

"""Frame recall and wrong-structure share when the hard preset's imaging levels move (issue 10).

The ``hard`` preset reproduces one cadaver sweep's levels (echo ~1.3x the tissue above,
shadow ~0.65 of the tissue beside it, reverberation bands, ...). A real recording from
another scanner, preset, probe or limb sits elsewhere: a segmenter whose rules were
tuned on the preset's exact levels would hold on the preset and fail there. This
benchmark moves one level at a time away from the preset, over the range real
recordings span, and prints, per level, what the images measure
(:func:`~BoneUSRecon.Logic.simulation.levels.echo_levels`: echo / tissue above, shadow /
tissue beside) and what the default segmenter does on them (frame recall, wrong-structure
share, kept points' median distance), pooled over the five bones and the seeds.

Levels moved (each row changes one; the others stay at the preset's):

* ``bone_amplitude``: the bone echo's contrast over the tissue above (1.1x-1.7x);
* ``shadow_transmission``: how grey the shadow is (0.5-0.85 of the tissue beside);
* ``reverb_amplitude``: the reverberation bands in the shadow;
* ``far_cortex``: the far cortex's echo deep in the shadow;
* ``display_max_db``: the display's log-compression (where muscle sits in grey);
* ``psf_lateral_mm`` / ``psf_axial_mm``: speckle grain size (probe frequency, focus);
* ``tgc_compensation``: how much of the depth attenuation the scanner's TGC undoes
  (tissue darker or brighter with depth);
* ``noise_floor``: electronic noise;
* ``fascia_strength``: the fascia off the crest brighter than the bone.

Run::

    python Testing/benchmarks/bench_levels.py [--seeds 5 7] [--geometry S|R]
        [--only bone_amplitude shadow_transmission]
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from dataclasses import replace
from pathlib import Path

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.simulation import BONES, SimulationParams, echo_levels, simulate
from BoneUSRecon.Logic.simulation.scoring import score_simulation

# The harness's two geometries (one definition, in bench_sweeps).
sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_sweeps import GEOMETRY  # noqa: E402

#: Per level: where it lives (``hard`` preset or ``imaging``) and the values tried; the
#: preset's own value is the row "preset".
LEVELS: dict[str, tuple[str, tuple[float, ...]]] = {
    "bone_amplitude": ("hard", (1.9, 2.2, 3.2, 4.5)),
    "shadow_transmission": ("hard", (0.05, 0.2, 0.3)),
    "reverb_amplitude": ("hard", (0.0, 0.45)),
    "far_cortex": ("hard", (0.0, 0.9)),
    "display_max_db": ("hard", (17.0, 25.0, 30.0)),
    "psf_lateral_mm": ("imaging", (0.18, 0.5)),
    "psf_axial_mm": ("imaging", (0.08, 0.25)),
    "tgc_compensation": ("imaging", (0.5, 1.0)),
    "noise_floor": ("imaging", (0.05, 0.4)),
    "fascia_strength": ("hard", (0.8, 1.5)),
}


def params_for(base: SimulationParams, level: str | None, value: float | None) -> SimulationParams:
    """``base`` with one level set (``level`` None: the preset itself)."""
    if level is None:
        return base
    where, _ = LEVELS[level]
    if where == "hard":
        return replace(base, hard=replace(base.hard, **{level: value}))
    return replace(base, imaging=replace(base.imaging, **{level: value}))


def run_row(
    level: str | None, value: float | None, seeds: list[int], geo: str, n_frames: int
) -> dict[str, float]:
    """Pooled figures of one row over the five bones and ``seeds``."""
    rec, wrong, med, ratios, shadow, cpu = [], [], [], [], [], 0.0
    for seed in seeds:
        for bone in BONES:
            base = SimulationParams(
                bone=bone, n_frames=n_frames, seed=seed, realism="hard", **GEOMETRY[geo]
            )
            s = simulate(params_for(base, level, value))
            lv = echo_levels(s.sweep.frames, s.true_contours_px, float(s.params.spacing_mm))
            ratios.append(lv["echo_to_above"])
            shadow.append(lv["shadow_to_beside"])
            t = time.process_time()
            try:
                r = segment_sweep(s.sweep)
            except BoneUSReconError:
                rec.append(0.0)
                wrong.append(0.0)
                continue
            cpu += time.process_time() - t
            sc = score_simulation(r, s).summary()
            rec.append(sc["recall"])
            wrong.append(sc["wrong_share"])
            if np.isfinite(sc["median_mm"]):
                med.append(sc["median_mm"])
    return {
        "echo_to_above": float(np.nanmedian(ratios)),
        "shadow_to_beside": float(np.nanmedian(shadow)),
        "recall": float(np.mean(rec)),
        "lowest": float(np.min(rec)),
        "wrong": float(np.mean(wrong)),
        "highest_wrong": float(np.max(wrong)),
        "median_mm": float(np.median(med)) if med else float("nan"),
        "cpu_s": cpu,
    }


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", default=[5, 7])
    ap.add_argument("--geometry", choices=sorted(GEOMETRY), default="S")
    ap.add_argument("--frames", type=int, default=40)
    ap.add_argument("--only", nargs="+", choices=sorted(LEVELS), default=sorted(LEVELS))
    args = ap.parse_args()
    warnings.simplefilter("ignore")

    rows: list[tuple[str | None, float | None]] = [(None, None)]
    rows += [(lv, v) for lv in LEVELS if lv in args.only for v in LEVELS[lv][1]]
    print(
        f"{'level':>28}  echo/above shadow/beside  recall (lowest)  wrong (highest)  "
        f"median mm  cpu s"
    )
    for level, value in rows:
        f = run_row(level, value, args.seeds, args.geometry, args.frames)
        name = "preset" if level is None else f"{level}={value:g}"
        print(
            f"{name:>28}  {f['echo_to_above']:10.2f} {f['shadow_to_beside']:13.2f}  "
            f"{f['recall']:6.3f} ({f['lowest']:.2f})  {f['wrong']:6.3f} ({f['highest_wrong']:.2f})"
            f"  {f['median_mm']:9.3f}  {f['cpu_s']:5.1f}",
            flush=True,
        )


if __name__ == "__main__":
    main()

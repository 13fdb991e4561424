"""Phantom simulator: tracked freehand sweeps over a bone with a known true surface.

Our ground truth for tests, benchmarks and the demo. Small files, one per stage:

* :mod:`.bones` -- the bones as smooth generalised cylinders (analytic surface,
  exact point-to-surface distance, dense mesh).
* :mod:`.motion` -- the freehand probe path (poses per frame).
* :mod:`.sections` -- where each image plane cuts the bone (the true contours).
* :mod:`.imaging` -- B-mode image formation (speckle, tissue, bone echo, shadow).
* :mod:`.corruption` -- frames that fool a per-frame segmenter.
* :mod:`.core` -- :func:`simulate` and :func:`write_simulation`.
* :mod:`.hard` -- the ``hard`` realism preset (``SimulationParams(realism="hard")``):
  the conditions of a real cadaver sweep (issue 10), each switchable.
* :mod:`.levels` -- grey levels round a bone contour (echo, tissue above, shadow,
  tissue beside), to check the preset and the augmentations against the real levels.
* :mod:`.augment` -- augmentations of a recorded sweep (mirror, gain, speckle,
  resampling, crop) with consistent poses, to test on real data without new data.

Simulator version 2 (compared with the real L14 recording): the shadow under bone is
grey (speckle at ~15-40 % of the tissue's grey level, ``shadow_transmission`` 0.22)
with faint reverberation copies of the bone echo every 3 mm; the bone echo has a
~0.5-1 mm tail *below* the surface (its peak stays on the true surface, which is
what the segmenters report); oblique flanks are weaker (``specular_exponent`` 3);
the echo has occasional dropouts; optional black margins beside the image
(``black_margin_px``) as in scan-converted recordings.

Examples
--------
>>> from BoneUSRecon.Logic.simulation import SimulationParams, simulate
>>> sim = simulate(SimulationParams(bone="ulna", n_frames=8, width=64, height=64, spacing_mm=0.6))
>>> float(sim.distance_to_truth(sim.geometry.surface(50.0, 1.0)[None])[0]) < 1e-6
True
"""

from __future__ import annotations

from BoneUSRecon.Logic._lazy import lazy_attributes
from BoneUSRecon.Logic.simulation.names import (
    BONES,
    CORRUPTION_KINDS,
    GOLD_REGIONS,
    HARD_CONDITIONS,
    REALISMS,
)

# The rest is imported lazily (PEP 562), as in BoneUSRecon.Logic: the simulator loads
# numpy, scipy and VTK, and even params.py costs ~9 ms, while the CLI's parsers only
# list the names (see .names).
_LAZY = {
    "HardParams": "params",
    "ImagingParams": "params",
    "SimulationParams": "params",
    "BONE_SPECS": "bones",
    "BoneGeometry": "bones",
    "BoneSpec": "bones",
    "SIMULATOR_VERSION": "core",
    "Simulation": "core",
    "check_output_dir": "core",
    "check_params": "core",
    "sample_gold": "core",
    "simulate": "core",
    "simulation_info": "core",
    "write_simulation": "core",
    "echo_levels": "levels",
}

__all__ = [
    "BONES",
    "BONE_SPECS",
    "CORRUPTION_KINDS",
    "GOLD_REGIONS",
    "HARD_CONDITIONS",
    "REALISMS",
    "SIMULATOR_VERSION",
    "BoneGeometry",
    "BoneSpec",
    "HardParams",
    "ImagingParams",
    "Simulation",
    "SimulationParams",
    "check_output_dir",
    "check_params",
    "echo_levels",
    "sample_gold",
    "simulate",
    "simulation_info",
    "write_simulation",
]

__getattr__, __dir__ = lazy_attributes(__name__, _LAZY, __all__)

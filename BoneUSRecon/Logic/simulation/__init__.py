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
  resampling, crop, display chains, the cadaver's levels, look-alikes drawn in) with
  consistent poses, to test on real data without new data.

As on the real L14 recording (``SIMULATOR_VERSION`` 2), the shadow under bone is
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

import lazy_loader

# The simulator's names and the reference sweep's defaults are defined here, importing
# nothing: the CLI's ``simulate`` and ``demo`` parsers list them at start-up, and
# :class:`.params.SimulationParams` takes its defaults from here (one list). The rest is
# imported on first use, from the names listed in ``__init__.pyi`` (as in
# BoneUSRecon.Logic): the simulator loads numpy, SciPy and VTK.

#: The bones the simulator knows (the long bones of the paper's introduction).
BONES = ("radius", "ulna", "tibia", "humerus", "clavicle")

#: Kinds of corrupted frames: the failures of a per-frame segmenter.
CORRUPTION_KINDS = ("shadow_clutter", "false_echo", "contact_loss")

# The reference sweep: 150 frames of 256 x 320 pixels at 0.15 mm (a 38 x 48 mm
# field of view, usual for a 7.5 MHz linear probe) over the paper's clavicle phantom.
DEFAULT_BONE = "clavicle"
DEFAULT_FRAMES = 150
DEFAULT_WIDTH = 320
DEFAULT_HEIGHT = 256
DEFAULT_SPACING_MM = 0.15
DEFAULT_SEED = 0

#: Where the gold points are digitised (``SimulationParams.gold_region``): ``imaged``
#: (between the planes of the first and last frames that showed bone) or ``swept``
#: (the whole axis range those frames' sections touch, the definition before issue 11's
#: follow-up).
GOLD_REGIONS = ("imaged", "swept")

#: Realism presets: ``standard`` (simulator version 2, tuned on the L14 recording) and
#: ``hard`` (the levels measured on a real cadaver sweep, issue 10; see :mod:`.hard`).
REALISMS = ("standard", "hard")

#: The conditions of the ``hard`` preset, each switchable (``SimulationParams.hard_conditions``):
#: a low-contrast bone echo, a grey shadow with reverberation bands and far-cortex
#: echoes, a crest-shaped then oval bone, bright fascia running off the bone at its
#: level, a skin edge over a no-contact gap with reverberation copies, a vessel, and
#: a bone depth going from 25 to 5 mm along the sweep.
HARD_CONDITIONS = (
    "low_contrast",
    "grey_shadow",
    "crest",
    "fascia",
    "skin_gap",
    "vessel",
    "depth_ramp",
)

__getattr__, _, _lazy_names = lazy_loader.attach_stub(__name__, __file__)
__all__ = [
    "BONES",
    "CORRUPTION_KINDS",
    "DEFAULT_BONE",
    "DEFAULT_FRAMES",
    "DEFAULT_HEIGHT",
    "DEFAULT_SEED",
    "DEFAULT_SPACING_MM",
    "DEFAULT_WIDTH",
    "GOLD_REGIONS",
    "HARD_CONDITIONS",
    "REALISMS",
    *_lazy_names,
]


def __dir__() -> list[str]:
    return __all__

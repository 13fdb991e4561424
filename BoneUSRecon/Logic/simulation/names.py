"""The simulator's names and reference-sweep defaults, importing nothing.

The CLI's ``simulate`` and ``demo`` parsers list these at start-up (every command's
``--help``): importing :mod:`.params` would cost ~9 ms (making its frozen
dataclasses), the simulator itself numpy, scipy and VTK. :class:`.params.SimulationParams`
takes its defaults from here, so there is one list.
"""

__all__ = [
    "BONES",
    "CORRUPTION_KINDS",
    "DEFAULT_BONE",
    "DEFAULT_FRAMES",
    "DEFAULT_WIDTH",
    "DEFAULT_HEIGHT",
    "DEFAULT_SPACING_MM",
    "DEFAULT_SEED",
    "REALISMS",
    "HARD_CONDITIONS",
    "GOLD_REGIONS",
]

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

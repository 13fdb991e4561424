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

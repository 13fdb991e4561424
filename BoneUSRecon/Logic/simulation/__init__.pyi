# The public API of BoneUSRecon.Logic.simulation, as in BoneUSRecon/Logic/__init__.pyi:
# type checkers read it, and lazy_loader.attach_stub (in __init__.py) imports each name
# from here on first use. Only `from .module import name` lines, and the constants
# defined in __init__.py itself.
from .bones import BONE_SPECS, BoneGeometry, BoneSpec
from .core import (
    SIMULATOR_VERSION,
    Simulation,
    check_output_dir,
    check_params,
    sample_gold,
    simulate,
    simulation_info,
    write_simulation,
)
from .levels import echo_levels
from .params import HardParams, ImagingParams, SimulationParams

BONES: tuple[str, ...]
CORRUPTION_KINDS: tuple[str, ...]
DEFAULT_BONE: str
DEFAULT_FRAMES: int
DEFAULT_HEIGHT: int
DEFAULT_SEED: int
DEFAULT_SPACING_MM: float
DEFAULT_WIDTH: int
GOLD_REGIONS: tuple[str, ...]
HARD_CONDITIONS: tuple[str, ...]
REALISMS: tuple[str, ...]

__all__ = [
    "BONES",
    "BONE_SPECS",
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

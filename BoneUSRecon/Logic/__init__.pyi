# The public API of BoneUSRecon.Logic: type checkers read it, and
# lazy_loader.attach_stub (in __init__.py) imports each name from here on first use.
# Only `from .module import name` lines: lazy_loader parses them.
from .batch import read_manifest, run_batch
from .bspline import FitParams, fit_surface
from .errors import BoneUSReconError
from .evaluation import Evaluation, evaluate_surface
from .pipeline import Reconstruction, ReconstructionParams, control_point_table, reconstruct
from .registration import Registration, RegistrationParams, register
from .resampling import ResamplingParams, resample
from .segmentation import SegmentationParams, segment_sweep
from .sequence_io import read_calibration, read_sweep, write_sweep
from .simulation import SimulationParams, simulate
from .surface import SurfaceParams, surface_polydata
from .sweep import Sweep
from .transform_io import read_transform, write_transform
from .vtkio import read_points, read_polydata, write_polydata

__all__ = [
    "BoneUSReconError",
    "Sweep",
    "read_sweep",
    "write_sweep",
    "read_calibration",
    "simulate",
    "SimulationParams",
    "segment_sweep",
    "SegmentationParams",
    "resample",
    "ResamplingParams",
    "fit_surface",
    "FitParams",
    "surface_polydata",
    "SurfaceParams",
    "evaluate_surface",
    "Evaluation",
    "reconstruct",
    "ReconstructionParams",
    "Reconstruction",
    "control_point_table",
    "register",
    "RegistrationParams",
    "Registration",
    "read_transform",
    "write_transform",
    "read_points",
    "read_polydata",
    "write_polydata",
    "read_manifest",
    "run_batch",
]

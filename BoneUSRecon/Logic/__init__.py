"""BoneUSRecon.Logic: the computation, with no Slicer, Qt or VTK rendering.

Data flows one way::

    sequence_io -> segmentation -> resampling -> bspline (fitting) -> surface / evaluation

each a module of pure functions on numpy arrays with a thin VTK edge
(``vtkImageData``, ``vtkTransform``, ``vtkPolyData``). :mod:`.pipeline` chains them;
the CLI, the Slicer module and the viewer are shells over it.
"""

from __future__ import annotations

from BoneUSRecon.Logic._lazy import lazy_attributes
from BoneUSRecon.Logic.errors import BoneUSReconError

# The public API, imported lazily (PEP 562) so that importing one stage does not load
# every other (and so that stages importing ``BoneUSRecon.Logic.sweep`` never cycle).
# Even Sweep: it loads numpy and VTK, and every CLI command's start-up (``--help``)
# passes through this package via ``Logic.errors``.
_LAZY = {
    "Sweep": "sweep",
    "read_sweep": "sequence_io",
    "write_sweep": "sequence_io",
    "read_calibration": "sequence_io",
    "simulate": "simulation",
    "SimulationParams": "simulation",
    "segment_sweep": "segmentation",
    "SegmentationParams": "segmentation",
    "resample": "resampling",
    "ResamplingParams": "resampling",
    "fit_surface": "bspline",
    "FitParams": "bspline",
    "surface_polydata": "surface",
    "SurfaceParams": "surface",
    "evaluate_surface": "evaluation",
    "Evaluation": "evaluation",
    "reconstruct": "pipeline",
    "ReconstructionParams": "pipeline",
    "Reconstruction": "pipeline",
    "control_point_table": "pipeline",
    "read_points": "vtkio",
    "read_polydata": "vtkio",
    "write_polydata": "vtkio",
    "read_manifest": "batch",
    "run_batch": "batch",
}

__all__ = ["BoneUSReconError", *_LAZY]

__getattr__, __dir__ = lazy_attributes(__name__, _LAZY, __all__)

"""BoneUSRecon.Logic: the computation, with no Slicer, Qt or VTK rendering.

Data flows one way::

    sequence_io -> segmentation -> resampling -> bspline (fitting) -> surface / evaluation

each a module of pure functions on numpy arrays with a thin VTK edge
(``vtkImageData``, ``vtkTransform``, ``vtkPolyData``). :mod:`.pipeline` chains them;
the CLI, the Slicer module and the viewer are shells over it.
"""

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.sweep import Sweep

__all__ = ["BoneUSReconError", "Sweep"]

"""BoneUSRecon.Logic: the computation, with no Slicer, Qt or VTK rendering.

Data flows one way::

    sequence_io -> segmentation -> resampling -> bspline (fitting) -> surface / evaluation

each a module of pure functions on numpy arrays with a thin VTK edge
(``vtkImageData``, ``vtkTransform``, ``vtkPolyData``). :mod:`.pipeline` chains them;
the CLI, the Slicer module and the viewer are shells over it.

The public names are listed once, in ``__init__.pyi``: type checkers read their real
types there, and :func:`lazy_loader.attach_stub` imports each on first use (as
scikit-image does), so that every CLI command's start-up (``--help``), which passes
through this package via ``Logic.errors``, loads no numpy, SciPy or VTK.
"""

from __future__ import annotations

import lazy_loader

__getattr__, __dir__, __all__ = lazy_loader.attach_stub(__name__, __file__)

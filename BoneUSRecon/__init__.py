"""BoneUSRecon: bone surface reconstruction from tracked freehand ultrasound.

The computation lives in :mod:`BoneUSRecon.Logic` (numpy in, numpy out, VTK only at
the edge; never Slicer, Qt or VTK rendering). :mod:`BoneUSRecon.Widgets` holds what a
person sees (viewer, report). :mod:`BoneUSRecon.cli` is the ``bone-us-recon`` command.
"""

__version__ = "0.1.0"
__all__ = ["__version__"]

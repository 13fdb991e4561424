"""BoneUSRecon.Widgets: what a person sees.

* :mod:`.render`: off-screen rendering helpers shared by the viewer and the report
  (the only place that imports VTK's rendering modules, through pyvista).
* :mod:`.viewer`: :func:`~.viewer.show_surface`, the interactive pyvista window (or an
  off-screen screenshot).
* :mod:`.report`: :func:`~.report.write_report`, a self-contained HTML report of a
  reconstruction.
* :mod:`.overlay`: contours drawn on B-mode frames (PNG, Pillow).

The adapter between Slicer's MRML scene and BoneUSRecon is the Slicer module's own
(``BoneSurfaceReconstructionLib.mrml``): the module never imports this package.

Submodules are imported on demand: importing this package loads nothing heavy.
"""

__all__ = ["render", "viewer", "report", "overlay"]

"""Helpers of the Bone Surface Reconstruction Slicer module.

Kept in a sub-package because Slicer treats every ``.py`` file beside the module file
as a module of its own. Nothing here imports ``slicer`` at import time:

* :mod:`.dependencies`: checking that ``import BoneUSRecon`` works inside Slicer, and installing
  missing pure-Python requirements with Slicer's pip helper (never VTK).
* :mod:`.live`: Live mode, a surface that grows while OpenIGTLinkIF updates the image
  (its panel is the only part that imports Qt, when the widget is built).
* :mod:`.parameters`: the module's parameters (defaults, ranges) and their mapping onto
  :class:`BoneUSRecon.Logic.pipeline.ReconstructionParams`.
* :mod:`.selftest`: the simulated-sweep check shared by the module's self-test and the
  pytest suite.
"""

__all__ = ["dependencies", "live", "parameters", "selftest"]

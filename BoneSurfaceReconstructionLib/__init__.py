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
* :mod:`.mrml`: the MRML adapter, scene nodes <-> :mod:`BoneUSRecon.Logic` (the
  module reaches the library through it and Logic, never through BoneUSRecon.Widgets).
* :mod:`.registration`: registering the reconstructed surface to a bone model node
  (output: a linear transform node and the registered model, with quality figures).
* :mod:`.sampledata`: the shipped PLUS recording in Slicer's Sample Data module.

What the module file imports when Slicer loads it (``dependencies``, ``parameters``)
stays importable by Python 3.9, so that an old Slicer shows why the module cannot run
(:func:`.dependencies.unsupportedReason`) instead of a SyntaxError.
"""

__all__ = ["dependencies", "live", "mrml", "parameters", "registration", "sampledata", "selftest"]

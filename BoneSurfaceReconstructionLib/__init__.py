"""Helpers of the Bone Surface Reconstruction Slicer module.

Kept in a sub-package because Slicer treats every ``.py`` file beside the module file
as a module of its own. Nothing here imports ``slicer`` at import time:

* :mod:`.dependencies`: checking that ``import BoneUSRecon`` works inside Slicer, and installing
  missing pure-Python requirements with Slicer's pip helper (never VTK).
* :mod:`.parameters`: the module's parameters (defaults, ranges) and their mapping onto
  :class:`BoneUSRecon.Logic.pipeline.ReconstructionParams`.
* :mod:`.selftest`: the simulated-sweep check shared by the module's self-test and the
  pytest suite.
* :mod:`.registration`: registering the reconstructed surface to a bone model node
  (output: a linear transform node and the registered model, with quality figures).
"""

__all__ = ["dependencies", "parameters", "registration", "selftest"]

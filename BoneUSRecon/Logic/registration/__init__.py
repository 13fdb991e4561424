"""Rigid registration of the reconstructed bone (or its segmented points) to a bone model.

The paper's purpose is navigation: the bone surface seen by localized ultrasound is
registered to the pre-operative CT (or MRI) model. :func:`register` finds the rigid
transform ``T`` (4x4, mm) that maps SOURCE coordinates (the sweep's reference frame) to
TARGET coordinates (the model's), in three steps:

1. **Initial alignment** (:class:`RegistrationParams.init`): the identity or a given
   matrix (the sweep is already roughly in the model's frame), paired landmarks
   (Kabsch/Horn least squares, :func:`landmark_transform`), or a global search over
   the principal axes' ambiguities (axis sign, roll, position along the model).
2. **Robust point-to-plane ICP** (:mod:`.icp`): nearest model point
   (``scipy.spatial.cKDTree`` on the model's vertices and triangle centres, each with
   its normal) facing the same way as the source point, Tukey's biweight on the
   point-to-plane residuals at a MAD scale, correspondences gated by distance and never
   on the model's open border (a cropped model), a damped 6x6 Gauss-Newton step; run
   from the initial alignment and from starts rolled about and shifted along the bone's
   axis (its local optima), the best kept. The robust weights handle the outliers and
   the partial overlap a localized sweep implies (it sees the top of a few cm of one
   bone).
3. **Honest quality figures** (:mod:`.quality`, :class:`Registration`): residual RMS, median and p95,
   inlier share, and how well the surface pins each degree of freedom: the
   eigenvalues of the 6x6 point-to-plane normal matrix (rotations scaled by the
   source's radius, so all six are in mm^2 per mm^2). A weak eigenvalue turns into a
   *sliding range*: how far the source can move along that direction before its RMS
   residual grows by the residual itself. A straight featureless shaft slides along its
   axis and turns about it; the result then says so by name and is not ``reliable``.

One job per file: :mod:`.params`, :mod:`.result`, :mod:`.model` (the target mesh),
:mod:`.geometry` (transforms, landmarks, units), :mod:`.icp`, :mod:`.quality` and
:mod:`.core` (:func:`register`). :mod:`.icp` says why it is not a library's ICP.
"""

from __future__ import annotations

from BoneUSRecon.Logic.registration.core import (
    register,
    register_polydata,
    register_reconstruction,
    towards_probe,
)
from BoneUSRecon.Logic.registration.geometry import (
    check_units,
    landmark_transform,
    patch_normal,
    rigid_error,
    transform_points,
    transform_polydata,
)
from BoneUSRecon.Logic.registration.model import BoneModel, bone_model, model_from_polydata
from BoneUSRecon.Logic.registration.params import INIT_METHODS, RegistrationParams
from BoneUSRecon.Logic.registration.result import Registration

__all__ = [
    "INIT_METHODS",
    "RegistrationParams",
    "Registration",
    "BoneModel",
    "bone_model",
    "model_from_polydata",
    "landmark_transform",
    "check_units",
    "register",
    "register_polydata",
    "register_reconstruction",
    "towards_probe",
    "patch_normal",
    "transform_points",
    "transform_polydata",
    "rigid_error",
]

"""The module's user-facing parameters: defaults, ranges, and what they become.

Two tables (:data:`INT_PARAMETERS`, :data:`FLOAT_PARAMETERS`) feed the
``@parameterNodeWrapper`` class of the module file (its ``WithinRange`` bounds and
defaults) and the tests that check the ``.ui`` file, so the three cannot drift apart.
The defaults are the paper's (Lopez-Perez et al., Sect. II-C/D): quadratic splines
(p = q = 2), e = 15 by f = 5 control points for elongated bones, 15 rays per frame,
except where the library measured better (f = 6, 24 rays); the flank extension (ours)
is off by default, as in the library.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from typing import Any

__all__ = [
    "INT_PARAMETERS",
    "FLOAT_PARAMETERS",
    "NODE_PARAMETERS",
    "PATH_PARAMETERS",
    "CHOICE_PARAMETERS",
    "SEGMENTER_FALLBACK",
    "segmenterNames",
    "parameters_from_widget_values",
    "widgetValues",
    "calibrationPath",
    "calibrationMatrix",
]

#: name -> (default, minimum, maximum, tooltip) for the integer parameters.
INT_PARAMETERS: dict[str, tuple[int, int, int, str]] = {
    "controlPointsU": (
        15,
        4,
        60,
        "B-spline control points along the sweep (e; paper: 15 for ulna/radius, 10-15 best).",
    ),
    "controlPointsV": (
        6,
        3,
        30,
        "B-spline control points across the bone (f; paper: 5 for ulna/radius; 6 follows flanks and crests).",
    ),
    "degreeU": (2, 1, 5, "B-spline degree along the sweep (p; paper: 2, quadratic)."),
    "degreeV": (2, 1, 5, "B-spline degree across the bone (q; paper: 2, quadratic)."),
    "rays": (
        24,
        3,
        90,
        "Rays cast per frame when resampling the contours (n; paper: 15; 24 samples crests and flank ends more finely).",
    ),
}

#: name -> (default, minimum, maximum, tooltip) for the float parameters (a
#: ``QDoubleSpinBox`` each: Slicer's parameter-node GUI connector binds a float to a
#: ``QDoubleSpinBox`` or ``ctkSliderWidget``, not to a ``ctkDoubleSpinBox``).
#: ``flankExtension`` is ``SurfaceParams.flank_extension_mm``: off by default there
#: (it brings gold points closer but moves the surface's own mean away from the bone;
#: measured at 1 and 2 mm, see its docstring); the range stops at 10 mm.
FLOAT_PARAMETERS: dict[str, tuple[float, float, float, str]] = {
    "flankExtension": (
        0.0,
        0.0,
        10.0,
        "Continue the surface this far (mm) past the segmented points down the bone's "
        "flanks (convex, at most 70 degrees steep). This part is extrapolated, not "
        "imaged: its points are flagged by the point array 'Extrapolated' (1) of the "
        "output model, and their Distance colour says how far past the data they reach "
        "(the colour range is set on the imaged part alone). 0: off.",
    ),
}

#: node parameters -> MRML class names offered in their selector.
NODE_PARAMETERS: dict[str, tuple[str, ...]] = {
    "inputNode": ("vtkMRMLSequenceBrowserNode", "vtkMRMLSequenceNode"),
    "transformSequence": ("vtkMRMLSequenceNode",),
    "outputSurface": ("vtkMRMLModelNode",),
    "outputPoints": ("vtkMRMLModelNode", "vtkMRMLMarkupsFiducialNode"),
    "targetModel": ("vtkMRMLModelNode",),
    "outputTransform": ("vtkMRMLLinearTransformNode",),
    "registeredModel": ("vtkMRMLModelNode",),
    "bonePoints": ("vtkMRMLMarkupsFiducialNode",),
}

#: path parameters (a ctkPathLineEdit each).
PATH_PARAMETERS = ("calibrationFile",)

#: choice parameters (a QComboBox each).
CHOICE_PARAMETERS = ("segmenter",)

# The parameter node's values that make up ReconstructionParams (widgetValues).
_VALUE_NAMES = ("segmenter", *INT_PARAMETERS, *FLOAT_PARAMETERS)

#: Used only when BoneUSRecon cannot be imported yet (its own dependency lazy_loader
#: not installed, or Python older than 3.10), while Slicer loads the module: a copy of
#: ``BoneUSRecon.Logic.segmentation.SEGMENTER_NAMES`` (a test keeps them equal).
SEGMENTER_FALLBACK = ("shadowpath", "snake")


def segmenterNames() -> tuple[str, ...]:
    """``BoneUSRecon.Logic.segmentation.SEGMENTER_NAMES``, the default first.

    Read without loading numpy, SciPy or VTK (the package defines the names itself).
    """
    try:
        from BoneUSRecon.Logic.segmentation import SEGMENTER_NAMES
    except Exception:  # noqa: BLE001
        # Called while Slicer loads the module: dependencies may not be installed yet
        # (ImportError) or be of a version that fails to import; the module must load
        # anyway (the Apply button installs them), so offer the known names.
        return SEGMENTER_FALLBACK
    return tuple(SEGMENTER_NAMES)


def calibrationPath(path: Any) -> str | None:
    """``path`` as a string, or None when no file is set (None, ``""``, or ``Path()`` == ".")."""
    text = "" if path is None else os.fspath(path).strip()
    return None if text in ("", ".") else text


def calibrationMatrix(path: Any) -> Any:
    """The PLUS ``ImageToProbe`` matrix from a configuration XML, or None if no file is set."""
    text = calibrationPath(path)
    if text is None:
        return None
    from BoneUSRecon.Logic.sequence_io import read_calibration

    return read_calibration(text)


def widgetValues(parameterNode: Any) -> dict[str, Any]:
    """The parameter node's values that make up the reconstruction parameters.

    ``segmenter`` and every name of :data:`INT_PARAMETERS` and :data:`FLOAT_PARAMETERS`,
    as stored in the node: what :func:`parameters_from_widget_values` takes.
    """
    return {name: getattr(parameterNode, name) for name in _VALUE_NAMES}


def parameters_from_widget_values(values: Mapping[str, Any]) -> Any:
    """The :class:`~BoneUSRecon.Logic.pipeline.ReconstructionParams` for the module's values.

    The one place the module's parameters (the names of :data:`INT_PARAMETERS`,
    :data:`FLOAT_PARAMETERS` and ``segmenter``) become the library's; the explicit
    ``process`` arguments, the parameter node and the live session all come through here.

    Parameters
    ----------
    values : mapping
        ``segmenter``, ``controlPointsU``/``V``, ``degreeU``/``V``, ``rays``,
        ``flankExtension`` (mm, ``SurfaceParams.flank_extension_mm``); a missing or
        ``None`` value keeps the library's default.

    Returns
    -------
    ReconstructionParams

    Raises
    ------
    BoneUSReconError
        (a ValueError) An unknown name in ``values``, or values the library refuses
        (fewer control points than degree + 1, an unknown segmenter, a negative flank
        extension).
    """
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.pipeline import ReconstructionParams, params_with

    given = {k: v for k, v in values.items() if v is not None}
    unknown = sorted(set(given) - set(_VALUE_NAMES))
    if unknown:
        raise BoneUSReconError(f"unknown module parameter {unknown[0]!r}")
    degree = None
    if "degreeU" in given or "degreeV" in given:
        p, q = ReconstructionParams().fit.degree
        degree = (given.get("degreeU", p), given.get("degreeV", q))
    return params_with(
        segmenter=given.get("segmenter"),
        along=given.get("controlPointsU"),
        around=given.get("controlPointsV"),
        degree=degree,
        rays=given.get("rays"),
        flank_extension_mm=given.get("flankExtension"),
    )

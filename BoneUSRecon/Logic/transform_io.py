"""Reading and writing rigid transforms: a 4x4 text matrix, or an ITK transform file.

Our transforms map SOURCE coordinates to TARGET coordinates (``x_t = T @ x_s``,
homogeneous, mm): the *modelling* convention, what moves the source onto the target.

* ``.txt``: the 4x4 matrix ``T`` itself, row-major, one row per line (mm), ``#``
  comments allowed. Read back exactly.
* ``.tfm`` / ``.h5``: an ITK transform file, written with SimpleITK, which 3D Slicer
  (and every ITK tool) loads as a linear transform. ITK's conventions differ twice
  (Slicer's documentation, developer guide > Transforms):

  - **direction**: ITK stores the *resampling* transform, from the fixed (target)
    space to the moving (source) space: the file holds ``inv(T)``. Slicer loads it as
    the node's "transform from parent", so the node's *to parent* is ``T``: put the
    source model under it and it lands on the target.
  - **coordinates**: ITK's world, and the coordinates of every file Slicer reads (its
    model files included, when they do not say otherwise), is LPS; Slicer's scene is
    RAS and it converts with ``diag(-1, -1, 1)`` on load. Our surfaces and models are
    files too, read with their coordinates as stored, so ``T`` already is an LPS
    transform and is written unchanged (``coordinates="LPS"``, the default). If the
    inputs' coordinates are RAS (a model exported from Slicer's scene as RAS, or a
    sweep recorded in a RAS frame), pass ``coordinates="RAS"``: the file then holds
    ``D inv(T) D`` with ``D = diag(-1, -1, 1, 1)``, which Slicer turns back into ``T``
    in its RAS scene.

  Checked in ``Testing/test_registration_slicer.py`` with slicer-core's own
  ``vtkMRMLTransformStorageNode``: the node read from our file has
  ``TransformToParent == D T D`` (RAS) for an LPS ``T``.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import Any

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import atomic_path, check_input_file, check_output_path

__all__ = ["TRANSFORM_EXTENSIONS", "COORDINATES", "write_transform", "read_transform", "LPS_TO_RAS"]

#: Extensions :func:`write_transform` and :func:`read_transform` understand.
TRANSFORM_EXTENSIONS = (".txt", ".tfm", ".h5")
#: Coordinate conventions of the inputs a transform refers to.
COORDINATES = ("LPS", "RAS")
#: LPS <-> RAS change of basis (its own inverse).
LPS_TO_RAS = np.diag([-1.0, -1.0, 1.0, 1.0])


def _check_matrix(matrix: np.ndarray, path: str | os.PathLike[str] | None = None) -> np.ndarray:
    m = np.asarray(matrix, float)
    if m.shape != (4, 4) or not np.isfinite(m).all():
        raise BoneUSReconError(f"expected a finite 4x4 matrix, got shape {m.shape}", path)
    if not np.allclose(m[3], [0, 0, 0, 1], atol=1e-9):
        raise BoneUSReconError(
            f"the last row of a 4x4 transform must be 0 0 0 1, got {m[3].tolist()}", path
        )
    if abs(np.linalg.det(m[:3, :3])) < 1e-12:
        raise BoneUSReconError("the transform is singular", path)
    return m


def _check_coordinates(coordinates: str) -> str:
    c = str(coordinates).upper()
    if c not in COORDINATES:
        raise BoneUSReconError(f"coordinates must be LPS or RAS, got {coordinates!r}")
    return c


def write_transform(
    matrix: np.ndarray, path: str | os.PathLike[str], *, coordinates: str = "LPS"
) -> Path:
    """Write a SOURCE -> TARGET transform atomically; the format follows the extension.

    Parameters
    ----------
    matrix : ndarray (4, 4)
        SOURCE -> TARGET (mm).
    path : path-like
        ``.txt`` (the matrix, row-major), ``.tfm`` or ``.h5`` (ITK: see the module
        docstring for the conventions).
    coordinates : {"LPS", "RAS"}
        The convention of the SOURCE and TARGET files' coordinates (ITK files only).

    Returns
    -------
    Path

    Raises
    ------
    BoneUSReconError
        Unknown extension, unwritable folder, a matrix that is not a 4x4 transform.
    """
    p = check_output_path(path, TRANSFORM_EXTENSIONS)
    m = _check_matrix(matrix)
    c = _check_coordinates(coordinates)
    with atomic_path(p) as tmp:
        if p.suffix.lower() == ".txt":
            np.savetxt(
                tmp,
                m,
                fmt="%.12g",
                header="BoneUSRecon rigid transform, SOURCE -> TARGET: x_target = M @ x_source "
                "(homogeneous, mm, row-major)",
            )
        else:
            import SimpleITK as sitk

            f = np.linalg.inv(m)  # ITK: fixed (target) -> moving (source)
            if c == "RAS":
                f = LPS_TO_RAS @ f @ LPS_TO_RAS
            tx = sitk.AffineTransform(3)
            tx.SetMatrix(f[:3, :3].ravel().tolist())
            tx.SetTranslation(f[:3, 3].tolist())
            sitk.WriteTransform(tx, str(tmp))
    return p


def read_transform(path: str | os.PathLike[str], *, coordinates: str = "LPS") -> np.ndarray:
    """Read a SOURCE -> TARGET transform written by :func:`write_transform` (or by ITK/Slicer).

    Parameters
    ----------
    path : path-like
        ``.txt`` (4x4 row-major; comments ``#``), ``.tfm`` or ``.h5`` (an ITK linear
        transform, a composite of linear transforms included).
    coordinates : {"LPS", "RAS"}
        As :func:`write_transform`.

    Returns
    -------
    ndarray (4, 4)

    Raises
    ------
    BoneUSReconError
        Missing or unreadable file, not 16 numbers, a non-linear ITK transform.
    """
    p = check_input_file(path)
    c = _check_coordinates(coordinates)
    ext = p.suffix.lower()
    if ext not in TRANSFORM_EXTENSIONS:
        raise BoneUSReconError(
            f"unknown transform format {ext or '(none)'!r}; use one of {', '.join(TRANSFORM_EXTENSIONS)}",
            p,
        )
    if ext == ".txt":
        try:
            rows = [
                ln.replace(",", " ").split()
                for ln in p.read_text(encoding="utf-8").splitlines()
                if ln.strip() and not ln.lstrip().startswith("#")
            ]
            m = np.array([[float(x) for x in r] for r in rows], dtype=float)
        except (ValueError, UnicodeDecodeError):
            raise BoneUSReconError("expected a 4x4 matrix of numbers (4 rows of 4)", p) from None
        if m.shape != (4, 4):
            raise BoneUSReconError(f"expected a 4x4 matrix (4 rows of 4 numbers), got {m.shape}", p)
        return _check_matrix(m, p)
    import SimpleITK as sitk

    try:
        tx = sitk.ReadTransform(str(p))
    except RuntimeError:
        raise BoneUSReconError("not an ITK transform file SimpleITK can read", p) from None
    f = _itk_matrix(tx, p)
    if c == "RAS":
        f = LPS_TO_RAS @ f @ LPS_TO_RAS
    return _check_matrix(np.linalg.inv(f), p)


def _itk_matrix(tx: Any, path: Path) -> np.ndarray:
    """The 4x4 matrix of a linear ITK transform (composites multiplied out)."""
    import SimpleITK as sitk

    if hasattr(tx, "Downcast"):
        tx = tx.Downcast()
    if isinstance(tx, sitk.CompositeTransform):
        out = np.eye(4)
        # ITK applies a composite's transforms last-added first: T0(T1(...(x))).
        for k in range(tx.GetNumberOfTransforms()):
            out = out @ _itk_matrix(tx.GetNthTransform(k), path)
        return out
    if tx.GetDimension() != 3:
        raise BoneUSReconError(f"the ITK transform is {tx.GetDimension()}D, expected 3D", path)
    if isinstance(tx, sitk.TranslationTransform):
        m = np.eye(4)
        m[:3, 3] = tx.GetOffset()
        return m
    if not hasattr(tx, "GetMatrix"):
        raise BoneUSReconError(
            f"the ITK transform is a {tx.GetName()}, not a linear transform", path
        )
    a = np.array(tx.GetMatrix(), float).reshape(3, 3)
    t = np.array(tx.GetTranslation(), float)
    centre = np.array(tx.GetCenter(), float) if hasattr(tx, "GetCenter") else np.zeros(3)
    m = np.eye(4)
    m[:3, :3] = a
    m[:3, 3] = t + centre - a @ centre
    return m

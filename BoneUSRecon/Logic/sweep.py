"""The tracked sweep: B-mode frames with one ``ImageToReference`` pose per frame.

Conventions (used everywhere in BoneUSRecon):

* ``frames`` has shape ``(N, H, W)``: frame ``k``, row ``j`` (depth, 0 nearest the
  transducer), column ``i`` (lateral, along the transducer): the PLUS ``MF``
  orientation (image x along the marked side of the transducer, image y pointing
  away from it), which is the one PLUS calibrations and poses refer to. Frames are ``uint8`` (see :mod:`BoneUSRecon.Logic.metaio` for how
  other pixel types are brought to 0..255). The array may be a read-only memory map;
  code must never modify it in place nor copy it whole into floating point.
* ``image_to_reference[k]`` is a 4x4 matrix mapping the homogeneous pixel index
  ``(i, j, 0, 1)`` to millimetres in the reference (patient/phantom) frame. Its
  first two columns carry the pixel spacing, so spacing is derived from their norms,
  never from the MetaIO ``ElementSpacing`` (PLUS writes ``1 1 1`` there).
* ``valid[k]`` is False for frames whose transform or image status is not OK, or whose
  pose is unusable (NaN, singular). Invalid frames are kept in the array (indices stay
  those of the file) but are never used.
"""

from __future__ import annotations

import contextlib
import dataclasses
import mmap
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonMath import vtkMatrix4x4
from vtkmodules.vtkCommonTransforms import vtkTransform

from BoneUSRecon.Logic.errors import BoneUSReconError

__all__ = ["Sweep", "pixel_spacing", "pixels_to_reference", "frame_planes", "frames_at_rest"]


def pixel_spacing(image_to_reference: np.ndarray) -> np.ndarray:
    """Pixel spacing (mm) per frame from the transform's first two column norms.

    Parameters
    ----------
    image_to_reference : ndarray, shape (4, 4) or (N, 4, 4)

    Returns
    -------
    ndarray, shape (2,) or (N, 2)
        ``[sx, sy]``: millimetres per column step and per row step.
    """
    m = np.asarray(image_to_reference, dtype=float)
    return np.linalg.norm(m[..., :3, :2], axis=-2)


def pixels_to_reference(image_to_reference: np.ndarray, ij: np.ndarray) -> np.ndarray:
    """Map pixel positions ``(i, j)`` (column, row; sub-pixel allowed) to reference mm.

    Parameters
    ----------
    image_to_reference : ndarray, shape (4, 4)
    ij : ndarray, shape (K, 2)

    Returns
    -------
    ndarray, shape (K, 3)
    """
    m = np.asarray(image_to_reference, dtype=float)
    ij = np.asarray(ij, dtype=float).reshape(-1, 2)
    return ij @ m[:3, :2].T + m[:3, 3]


def frames_at_rest(
    image_to_reference: np.ndarray, shape: tuple[int, int], tol_mm: float
) -> np.ndarray:
    """Which frames the probe recorded at rest, and the frame each stands for.

    A frame is at rest when no corner of its image lies more than ``tol_mm`` from
    where it lay in the last frame that moved (in the order given: the order of
    recording); that frame stands for it. The first frame moves.

    Parameters
    ----------
    image_to_reference : ndarray, shape (N, 4, 4)
    shape : (int, int)
        The frames' ``(H, W)``.
    tol_mm : float
        0: no frame is at rest.

    Returns
    -------
    ndarray of int, shape (N,)
        For each frame the index of the frame standing for it (its own if it moved).
    """
    m = np.asarray(image_to_reference, float)
    n = m.shape[0]
    rep = np.arange(n)
    if n < 2 or not tol_mm > 0:
        return rep
    h, w = shape
    c = np.array([[0, 0, 0, 1], [w - 1, 0, 0, 1], [0, h - 1, 0, 1], [w - 1, h - 1, 0, 1]], float)
    corners = np.einsum("nij,kj->nki", m, c)[..., :3]
    last = 0
    # Sequential by nature (each frame is judged against the last that moved); a few
    # vector operations per frame, the frames' pixels untouched.
    for k in range(1, n):
        if np.linalg.norm(corners[k] - corners[last], axis=1).max() <= tol_mm:
            rep[k] = last
        else:
            last = k
    return rep


def frame_planes(image_to_reference: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Plane of each frame in reference mm.

    Returns
    -------
    origin : ndarray, shape (N, 3)
        Where pixel (0, 0) lands.
    axes : ndarray, shape (N, 3, 2)
        Unit vectors of the image's column (i) and row (j) directions.
    normal : ndarray, shape (N, 3)
        Unit normal ``x_axis x y_axis``.
    """
    m = np.asarray(image_to_reference, dtype=float).reshape(-1, 4, 4)
    origin = m[:, :3, 3].copy()
    axes = m[:, :3, :2] / np.linalg.norm(m[:, :3, :2], axis=1, keepdims=True)
    normal = np.cross(axes[:, :, 0], axes[:, :, 1])
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    return origin, axes, normal


@dataclass(frozen=True, eq=False)
class Sweep:
    """A tracked freehand ultrasound sweep.

    Parameters
    ----------
    frames : ndarray of uint8, shape (N, H, W)
        B-mode frames in MF orientation (see module docstring).
    image_to_reference : ndarray of float64, shape (N, 4, 4)
        Pixel ``(i, j, 0, 1)`` -> reference mm, per frame.
    timestamps : ndarray of float64, shape (N,)
        Seconds. Zeros when the file has none; NaN for single frames without one.
    valid : ndarray of bool, shape (N,)
        Frames usable for reconstruction.
    source : Path, optional
        The file the sweep was read from.
    transform_name : str
        How the pose was obtained, e.g. ``"ImageToReference"`` or
        ``"inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe"``.
    invalid_reasons : dict[int, str]
        Why each invalid frame was dropped (``{frame: "ProbeToTracker status MISSING"}``).
    metadata : dict
        Other header fields worth keeping (orientation, device names, ...).
    """

    frames: np.ndarray
    image_to_reference: np.ndarray
    timestamps: np.ndarray
    valid: np.ndarray
    source: Path | None = None
    transform_name: str = "ImageToReference"
    invalid_reasons: dict[int, str] = field(default_factory=dict)
    metadata: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        f = self.frames
        src = self.source
        if f.ndim != 3:
            raise BoneUSReconError(f"frames must have shape (N, H, W), got {f.shape}", src)
        n = f.shape[0]
        if n == 0:
            raise BoneUSReconError("the sweep has zero frames", src)
        m = np.asarray(self.image_to_reference, dtype=np.float64)
        if m.shape != (n, 4, 4):
            raise BoneUSReconError(f"expected {n} 4x4 transforms, got shape {m.shape}", src)
        t = np.asarray(self.timestamps, dtype=np.float64).reshape(-1)
        if t.shape != (n,):
            raise BoneUSReconError(f"expected {n} timestamps, got {t.shape[0]}", src)
        v = np.asarray(self.valid, dtype=bool).reshape(-1)
        if v.shape != (n,):
            raise BoneUSReconError(f"expected {n} valid flags, got {v.shape[0]}", src)
        object.__setattr__(self, "image_to_reference", m)
        object.__setattr__(self, "timestamps", t)
        object.__setattr__(self, "valid", v)
        if self.source is not None:
            object.__setattr__(self, "source", Path(self.source))

    # -- shape -----------------------------------------------------------------------
    @property
    def n_frames(self) -> int:
        """Number of frames in the file, valid or not."""
        return int(self.frames.shape[0])

    @property
    def n_valid(self) -> int:
        """Number of usable frames."""
        return int(self.valid.sum())

    @property
    def height(self) -> int:
        """Rows per frame (H)."""
        return int(self.frames.shape[1])

    @property
    def width(self) -> int:
        """Columns per frame (W)."""
        return int(self.frames.shape[2])

    @property
    def valid_indices(self) -> np.ndarray:
        """Indices of the usable frames."""
        return np.flatnonzero(self.valid)

    # -- geometry --------------------------------------------------------------------
    @property
    def spacing_mm(self) -> np.ndarray:
        """``[sx, sy]`` mm per pixel: median over valid frames of the column norms."""
        idx = self.valid_indices if self.n_valid else np.arange(self.n_frames)
        return np.median(pixel_spacing(self.image_to_reference[idx]), axis=0)

    def to_reference(self, frame: int, ij: np.ndarray) -> np.ndarray:
        """Pixel positions ``(K, 2)`` of ``frame`` to reference mm ``(K, 3)``."""
        return pixels_to_reference(self.image_to_reference[frame], ij)

    def corners_mm(self, frames: np.ndarray | None = None) -> np.ndarray:
        """Image corners in reference mm, shape ``(len(frames), 4, 3)`` (valid frames by default)."""
        idx = self.valid_indices if frames is None else np.asarray(frames)
        w, h = self.width - 1, self.height - 1
        c = np.array([[0, 0, 0, 1], [w, 0, 0, 1], [w, h, 0, 1], [0, h, 0, 1]], float)
        return np.einsum("nab,kb->nka", self.image_to_reference[idx], c)[..., :3]

    def bounds_mm(self) -> np.ndarray:
        """``[xmin, xmax, ymin, ymax, zmin, zmax]`` of the valid frames' corners."""
        pts = self.corners_mm().reshape(-1, 3)
        return np.column_stack([pts.min(0), pts.max(0)]).reshape(-1)

    def image_centres(self, frames: np.ndarray | None = None) -> np.ndarray:
        """Where each frame is: its image centre in reference mm, shape ``(K, 3)``.

        The centre is pixel ``((W - 1) / 2, (H - 1) / 2)``, the middle of the pixel grid
        (pixel centres at integer indices). Valid frames by default, else ``frames``
        (indices). The one definition used for the sweep length, the slice gaps and the
        ordering of slices along the sweep.

        Examples
        --------
        >>> m = np.tile(np.diag([0.5, 0.5, 1.0, 1.0]), (3, 1, 1))
        >>> m[:, 0, 3] = [0.0, 2.0, 4.0]  # the probe moves 2 mm along x per frame
        >>> s = Sweep(np.zeros((3, 5, 9), np.uint8), m, np.zeros(3), np.ones(3, bool))
        >>> s.image_centres()
        array([[2., 1., 0.],
               [4., 1., 0.],
               [6., 1., 0.]])
        >>> s.sweep_length_mm()
        4.0
        """
        idx = self.valid_indices if frames is None else np.asarray(frames, dtype=int)
        centre = np.array([(self.width - 1) / 2, (self.height - 1) / 2, 0.0, 1.0])
        return np.einsum("nab,b->na", self.image_to_reference[idx, :3, :], centre)

    def sweep_length_mm(self) -> float:
        """Path length of the image centre over the valid frames, in mm."""
        if self.n_valid < 2:
            return 0.0
        c = self.image_centres()
        return float(np.linalg.norm(np.diff(c, axis=0), axis=1).sum())

    def duration_s(self) -> float:
        """Time between the first and last valid frame, in seconds."""
        t = self.timestamps[self.valid]
        t = t[np.isfinite(t)]  # frames without a timestamp field read as NaN
        return float(t.max() - t.min()) if t.size else 0.0

    def iter_frames(
        self, indices: np.ndarray | None = None, *, release_every: int = 32
    ) -> Iterator[tuple[int, np.ndarray]]:
        """Yield ``(k, frame)`` for the valid frames (or ``indices``), one at a time.

        Each frame is a private C-contiguous ``uint8`` copy (``H x W``), so callers may
        modify it. When the frames are a memory map, its pages are released every
        ``release_every`` frames (``madvise(MADV_DONTNEED)``; they stay in the OS page
        cache), so iterating a 600 MB sweep does not grow the resident set by 600 MB.

        Examples
        --------
        >>> s = Sweep(np.zeros((3, 2, 4), np.uint8), np.tile(np.eye(4), (3, 1, 1)),
        ...           np.zeros(3), np.array([True, False, True]))
        >>> [k for k, _ in s.iter_frames()]
        [0, 2]
        """
        idx = self.valid_indices if indices is None else np.asarray(indices, dtype=int)
        mm = _backing_mmap(self.frames)
        for count, k in enumerate(idx, start=1):
            yield int(k), np.array(self.frames[k], dtype=np.uint8, order="C")
            if mm is not None and count % max(1, release_every) == 0:
                _release(mm)
        if mm is not None:
            _release(mm)

    def replace(self, **changes: Any) -> Sweep:
        """A copy with some fields replaced (frames are shared, not copied)."""
        return dataclasses.replace(self, **changes)

    # -- VTK edge --------------------------------------------------------------------
    def frame_image(self, k: int) -> vtkImageData:
        """Frame ``k`` as a 2D ``vtkImageData`` in pixel units (spacing 1, origin 0).

        The pose is kept separately (:meth:`frame_transform`), as in Slicer's volume
        sequences where ``IJKToRAS`` and the frame's transform are two things.
        """
        img = vtkImageData()
        img.SetDimensions(self.width, self.height, 1)
        arr = numpy_support.numpy_to_vtk(
            np.ascontiguousarray(self.frames[k]).reshape(-1), deep=True
        )
        arr.SetName("Intensity")
        img.GetPointData().SetScalars(arr)
        return img

    def frame_matrix(self, k: int) -> vtkMatrix4x4:
        """``ImageToReference`` of frame ``k`` as a ``vtkMatrix4x4``."""
        return matrix_to_vtk(self.image_to_reference[k])

    def frame_transform(self, k: int) -> vtkTransform:
        """``ImageToReference`` of frame ``k`` as a ``vtkTransform``."""
        t = vtkTransform()
        t.SetMatrix(self.frame_matrix(k))
        return t

    def to_vtk(self) -> tuple[list[vtkImageData], list[vtkTransform]]:
        """All frames as ``vtkImageData`` and all poses as ``vtkTransform``."""
        return (
            [self.frame_image(k) for k in range(self.n_frames)],
            [self.frame_transform(k) for k in range(self.n_frames)],
        )

    @classmethod
    def from_vtk(
        cls,
        images: list[vtkImageData],
        transforms: list[vtkTransform | vtkMatrix4x4],
        *,
        timestamps: np.ndarray | None = None,
        valid: np.ndarray | None = None,
        source: Path | None = None,
    ) -> Sweep:
        """Build a sweep from per-frame ``vtkImageData`` and poses.

        Each image's own spacing and origin are folded into the pose, so an image in
        mm (spacing 0.1) with an identity-scaled transform gives the same sweep as an
        image in pixels with the scale in the transform.
        """
        if len(images) != len(transforms):
            raise BoneUSReconError(f"{len(images)} images but {len(transforms)} transforms", source)
        if not images:
            raise BoneUSReconError("the sweep has zero frames", source)
        frames, mats = [], []
        for img, tr in zip(images, transforms, strict=True):
            w, h, d = img.GetDimensions()
            if d != 1:
                raise BoneUSReconError(f"expected 2D frames, got dimensions {(w, h, d)}", source)
            a = numpy_support.vtk_to_numpy(img.GetPointData().GetScalars())
            if a.ndim > 1:  # RGB(A): use the first component (B-mode is grey)
                a = a[:, 0]
            frames.append(a.reshape(h, w))
            m = vtk_to_matrix(tr)
            sx, sy, _ = img.GetSpacing()
            ox, oy, oz = img.GetOrigin()
            ijk_to_img = np.array(
                [[sx, 0, 0, ox], [0, sy, 0, oy], [0, 0, 1, oz], [0, 0, 0, 1]], float
            )
            mats.append(m @ ijk_to_img)
        stack = np.stack(frames)
        if stack.dtype != np.uint8:
            from BoneUSRecon.Logic.intensity import to_uint8

            stack = to_uint8(stack)
        n = stack.shape[0]
        return cls(
            frames=stack,
            image_to_reference=np.stack(mats),
            timestamps=np.zeros(n) if timestamps is None else timestamps,
            valid=np.ones(n, bool) if valid is None else valid,
            source=source,
        )


def _backing_mmap(a: np.ndarray) -> mmap.mmap | None:
    """The ``mmap`` behind a (view of a) ``numpy.memmap``, if any."""
    mm = getattr(a, "_mmap", None)
    # Never for copy-on-write ("c") maps: dropping their pages would lose changes.
    if getattr(a, "mode", "c") not in ("r", "r+", "w+"):
        return None
    return mm if isinstance(mm, mmap.mmap) else None


def _release(mm: mmap.mmap) -> None:
    """Drop a read-only file mapping's pages from this process (not from the cache)."""
    if hasattr(mm, "madvise") and hasattr(mmap, "MADV_DONTNEED"):
        with contextlib.suppress(OSError, ValueError):
            mm.madvise(mmap.MADV_DONTNEED)


def matrix_to_vtk(m: np.ndarray) -> vtkMatrix4x4:
    """A 4x4 numpy array as a ``vtkMatrix4x4``."""
    out = vtkMatrix4x4()
    out.DeepCopy(np.asarray(m, dtype=float).reshape(-1).tolist())
    return out


def vtk_to_matrix(t: vtkTransform | vtkMatrix4x4) -> np.ndarray:
    """A ``vtkTransform`` or ``vtkMatrix4x4`` as a 4x4 numpy array."""
    m = t.GetMatrix() if hasattr(t, "GetMatrix") else t
    return np.array([[m.GetElement(r, c) for c in range(4)] for r in range(4)], float)

"""Sweeps <-> MRML: frames and poses read from the scene's nodes, and written back.

Part of the MRML adapter (:mod:`BoneSurfaceReconstructionLib.mrml`). It works on the
nodes it is given (any ``vtkMRMLScene``: the Slicer application's, or one built with the
``slicer-core`` package from PyPI) and imports :mod:`slicer` only inside the one
function that needs Slicer's Sequences logic, so importing this module never loads
Slicer, Qt, or VTK rendering.

Coordinate convention
---------------------
Slicer's world is RAS (right, anterior, superior; millimetres). Each frame of a volume
sequence is a 2D ``vtkMRMLScalarVolumeNode`` (dimensions ``W x H x 1``) whose
``IJKToRAS`` matrix maps the voxel index ``(i, j, 0)`` to its own RAS position; the frame
may sit under a transform (for tracked ultrasound: an ``ImageToReference`` proxy
transform, or a chain ``ImageToProbe`` -> ``ProbeToTracker`` -> ...). The adapter
reconstructs exactly what Slicer displays::

    image_to_reference[k] = ParentTransformToWorld[k] @ IJKToRAS[k]

so the BoneUSRecon "reference" frame *is* Slicer's world (RAS), the voxel index ``i``
is the image column and ``j`` the row (PLUS ``MF`` orientation: row 0 nearest the
transducer), and the output surface needs no transform. If the frames show in the
right place in Slicer's views, the reconstruction is in the right place. (Readers that
convert MetaIO's LPS to RAS give frames an ``IJKToRAS`` with flipped axes: that is
part of what Slicer displays and is followed as such. :func:`load_sweep_file`
sidesteps the question for PLUS files: frames in pixel units, ``IJKToRAS`` the
identity, under their ``ImageToReference`` transform, exactly PLUS's convention.)

When a PLUS probe calibration is given instead (``calibration``: ``ImageToProbe``,
pixel ``(i, j, 0, 1)`` -> probe mm, as in the PLUS configuration XML), the image's own
geometry is ignored, as PLUS does: ``image_to_reference[k] = ParentTransformToWorld[k]
@ calibration``; the frame must then sit under the probe's tracking transform.
"""

from __future__ import annotations

import os
import weakref
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkCollection
from vtkmodules.vtkCommonDataModel import vtkImageData
from vtkmodules.vtkCommonMath import vtkMatrix4x4

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.intensity import to_uint8
from BoneUSRecon.Logic.progress import ProgressCallback, report
from BoneUSRecon.Logic.sweep import Sweep, matrix_to_vtk, vtk_to_matrix

__all__ = [
    "SweepNodes",
    "sweep_from_node",
    "sweep_from_browser",
    "sweep_from_sequences",
    "sweep_to_scene",
    "load_sweep_file",
]


# ------------------------------------------------------------------------------------
# MRML -> Sweep
# ------------------------------------------------------------------------------------
def _node_label(node: Any) -> str:
    return f"{node.GetClassName()} {node.GetName()!r}" if node is not None else "None"


def _is_volume_sequence(seq: Any) -> bool:
    return (
        seq is not None
        and seq.IsA("vtkMRMLSequenceNode")
        and seq.GetNumberOfDataNodes() > 0
        and seq.GetNthDataNode(0).IsA("vtkMRMLScalarVolumeNode")
    )


def _sequence_source(seq: Any) -> Path | None:
    """The file a sequence was loaded from, if Slicer knows it (for error messages)."""
    st = seq.GetStorageNode() if hasattr(seq, "GetStorageNode") else None
    name = st.GetFileName() if st is not None else None
    return Path(name) if name else None


def _index_times(seq: Any) -> np.ndarray:
    """Index values as seconds when numeric (PLUS time stamps), else frame numbers."""
    n = seq.GetNumberOfDataNodes()
    try:
        t = np.array([float(seq.GetNthIndexValue(k)) for k in range(n)])
    except ValueError:
        return np.arange(n, dtype=float)
    if seq.GetIndexUnit() == "ms":
        t = t / 1000.0
    return t


def _image_array(image: vtkImageData | None, label: str) -> np.ndarray:
    """A 2D frame ``(H, W)`` from a ``vtkImageData`` of dimensions ``W x H x 1`` (a copy)."""
    if image is None or image.GetPointData().GetScalars() is None:
        raise BoneUSReconError(f"{label} has no image data")
    w, h, d = image.GetDimensions()
    if d != 1:
        raise BoneUSReconError(
            f"{label} is a {w}x{h}x{d} volume; expected 2D ultrasound frames (depth 1)"
        )
    a = numpy_support.vtk_to_numpy(image.GetPointData().GetScalars())
    if a.ndim > 1:  # RGB(A) B-mode capture: the grey level is the first component
        a = a[:, 0]
    return np.array(a.reshape(h, w))  # copy: proxy nodes reuse their buffers


def _ijk_to_ras(volume: Any) -> np.ndarray:
    m = vtkMatrix4x4()
    volume.GetIJKToRASMatrix(m)
    return vtk_to_matrix(m)


def _to_world(node: Any) -> np.ndarray:
    """The matrix from ``node``'s coordinates to world (identity if not transformed)."""
    parent = node.GetParentTransformNode()
    if parent is None:
        return np.eye(4)
    if not parent.IsTransformToWorldLinear():
        raise BoneUSReconError(
            f"{_node_label(node)} is under a non-linear transform "
            f"({parent.GetName()!r}); harden or remove it first"
        )
    m = vtkMatrix4x4()
    parent.GetMatrixTransformToWorld(m)
    return vtk_to_matrix(m)


def _calibration_matrix(calibration: Any) -> np.ndarray | None:
    """``calibration`` as a 4x4 array: None, an array, or a linear transform node."""
    if calibration is None:
        return None
    if hasattr(calibration, "GetMatrixTransformToParent"):
        m = vtkMatrix4x4()
        calibration.GetMatrixTransformToParent(m)
        return vtk_to_matrix(m)
    c = np.asarray(calibration, dtype=float)
    if c.shape != (4, 4) or not np.isfinite(c).all():
        raise BoneUSReconError(f"calibration must be a finite 4x4 matrix, got shape {c.shape}")
    return c


def _assemble(
    frames: list[np.ndarray],
    poses: list[np.ndarray],
    times: np.ndarray,
    *,
    source: Path | None,
    transform_name: str,
    metadata: dict[str, Any],
) -> Sweep:
    shapes = {f.shape for f in frames}
    if len(shapes) != 1:
        raise BoneUSReconError(
            f"frames differ in size ({', '.join(f'{w}x{h}' for h, w in sorted(shapes))}); "
            "a sweep needs one image size",
            source,
        )
    stack = np.stack(frames)
    if stack.dtype != np.uint8:
        stack = to_uint8(stack)
    mats = np.stack(poses)
    # A frame whose pose is unusable (NaN from an invalid tracker sample, or a plane
    # that collapsed) is kept but marked invalid, as the PLUS reader does.
    finite = np.isfinite(mats).all(axis=(1, 2))
    area = np.zeros(len(mats))
    area[finite] = np.linalg.norm(np.cross(mats[finite, :3, 0], mats[finite, :3, 1]), axis=1)
    valid = finite & (area > 1e-12)
    reasons = {
        int(k): ("pose is not finite" if not finite[k] else "pose is singular")
        for k in np.flatnonzero(~valid)
    }
    if not valid.any():
        raise BoneUSReconError("no frame has a usable pose (all NaN or singular)", source)
    return Sweep(
        frames=stack,
        # identity where unusable, as the PLUS reader does, so no NaN reaches geometry code
        image_to_reference=np.where(valid[:, None, None], mats, np.eye(4)),
        timestamps=times,
        valid=valid,
        source=source,
        transform_name=transform_name,
        invalid_reasons=reasons,
        metadata=metadata,
    )


_LOGICS: weakref.WeakKeyDictionary[Any, Any] = weakref.WeakKeyDictionary()


def _sequences_logic(scene: Any) -> Any:
    """Slicer's Sequences logic: the application's, or a private one on ``scene``.

    Imported here, and only here, so that the rest of this module runs without Slicer.
    """
    import slicer  # noqa: PLC0415 (lazy on purpose: see the module docstring)

    modules = getattr(slicer, "modules", None)
    if modules is not None and hasattr(modules, "sequences"):
        logic = modules.sequences.logic()
        if logic.GetMRMLScene() is scene:
            return logic
    logic = _LOGICS.get(scene)
    if logic is None:  # one per scene: creating it registers node classes (again)
        logic = slicer.vtkSlicerSequencesLogic()
        logic.SetMRMLScene(scene)
        _LOGICS[scene] = logic
    return logic


def sweep_from_browser(
    browser: Any,
    *,
    image_sequence: Any = None,
    calibration: Any = None,
    progress: ProgressCallback | None = None,
) -> Sweep:
    """Build a :class:`Sweep` from a ``vtkMRMLSequenceBrowserNode``.

    The browser is stepped through every frame of the image sequence, so each frame's
    pose is whatever Slicer shows for it, whatever the transform hierarchy (the
    image proxy under an ``ImageToReference`` proxy, or under a chain of static and
    tracked transforms). The browser's selected item is restored afterwards.

    Parameters
    ----------
    browser : vtkMRMLSequenceBrowserNode
    image_sequence : vtkMRMLSequenceNode, optional
        The volume sequence to use; by default the browser's master sequence if it
        holds volumes, else its first synchronized volume sequence.
    calibration : ndarray (4, 4) or vtkMRMLLinearTransformNode, optional
        PLUS ``ImageToProbe`` (pixel -> mm). See the module docstring.
    progress : ProgressCallback, optional
        Called as ``progress("mrml", done, total)``.

    Raises
    ------
    BoneUSReconError
        No volume sequence, frames that are not 2D or differ in size, a non-linear
        transform above the image, or no usable pose.
    """
    if browser is None or not browser.IsA("vtkMRMLSequenceBrowserNode"):
        raise BoneUSReconError(f"expected a sequence browser node, got {_node_label(browser)}")
    scene = browser.GetScene()
    if scene is None:
        raise BoneUSReconError(f"{_node_label(browser)} is not in a scene")
    master = browser.GetMasterSequenceNode()
    if image_sequence is None:
        synced = vtkCollection()
        browser.GetSynchronizedSequenceNodes(synced, True)
        candidates = [master] + [
            synced.GetItemAsObject(k) for k in range(synced.GetNumberOfItems())
        ]
        image_sequence = next((s for s in candidates if _is_volume_sequence(s)), None)
        if image_sequence is None:
            raise BoneUSReconError(
                f"{_node_label(browser)} browses no sequence of scalar volumes (image frames)"
            )
    elif not _is_volume_sequence(image_sequence):
        raise BoneUSReconError(f"{_node_label(image_sequence)} is not a sequence of scalar volumes")
    elif not browser.IsSynchronizedSequenceNodeID(image_sequence.GetID(), True):
        raise BoneUSReconError(
            f"{_node_label(image_sequence)} is not browsed by {_node_label(browser)}"
        )

    logic = _sequences_logic(scene)
    calib = _calibration_matrix(calibration)
    source = _sequence_source(image_sequence)
    n = image_sequence.GetNumberOfDataNodes()
    frames: list[np.ndarray] = []
    poses: list[np.ndarray] = []
    previous = browser.GetSelectedItemNumber()
    label = _node_label(image_sequence)
    try:
        for k in range(n):
            value = image_sequence.GetNthIndexValue(k)
            item = (
                master.GetItemNumberFromIndexValue(value, False)
                if master is not image_sequence
                else k
            )
            browser.SetSelectedItemNumber(max(int(item), 0))
            logic.UpdateProxyNodesFromSequences(browser)
            proxy = browser.GetProxyNode(image_sequence)
            if proxy is None:
                raise BoneUSReconError(f"{_node_label(browser)} has no proxy node for {label}")
            frames.append(_image_array(proxy.GetImageData(), f"{label} frame {k}"))
            local = calib if calib is not None else _ijk_to_ras(proxy)
            poses.append(_to_world(proxy) @ local)
            report(progress, "mrml", k + 1, n)
    finally:
        browser.SetSelectedItemNumber(previous)
        logic.UpdateProxyNodesFromSequences(browser)
    return _assemble(
        frames,
        poses,
        _index_times(image_sequence),
        source=source,
        transform_name=(
            "ParentTransformToWorld * ImageToProbe(calibration)"
            if calib is not None
            else "ParentTransformToWorld * IJKToRAS"
        ),
        metadata={
            "mrml_browser": browser.GetName(),
            "mrml_image_sequence": image_sequence.GetName(),
        },
    )


def sweep_from_sequences(
    volume_sequence: Any,
    transform_sequence: Any = None,
    *,
    calibration: Any = None,
    progress: ProgressCallback | None = None,
) -> Sweep:
    """Build a :class:`Sweep` from a volume sequence and (optionally) a transform sequence.

    Without a browser the two sequences are paired by index value (time stamp): each
    frame takes the transform at its index value (or the latest one before it, as the
    Sequences module does for numeric indices). The pose of frame ``k`` is
    ``T[k] @ IJKToRAS[k]`` (or ``T[k] @ calibration``), where ``T[k]`` is the transform's
    matrix to its parent; without a transform sequence, ``T[k]`` is the identity, i.e.
    the frames are placed by their own ``IJKToRAS``.

    Raises
    ------
    BoneUSReconError
        Not a volume sequence, an empty or non-linear transform sequence, frames not 2D.
    """
    if not _is_volume_sequence(volume_sequence):
        raise BoneUSReconError(
            f"{_node_label(volume_sequence)} is not a sequence of scalar volumes"
        )
    if transform_sequence is not None:
        if (
            not transform_sequence.IsA("vtkMRMLSequenceNode")
            or transform_sequence.GetNumberOfDataNodes() == 0
            or not transform_sequence.GetNthDataNode(0).IsA("vtkMRMLLinearTransformNode")
        ):
            raise BoneUSReconError(
                f"{_node_label(transform_sequence)} is not a sequence of linear transforms"
            )
    calib = _calibration_matrix(calibration)
    label = _node_label(volume_sequence)
    n = volume_sequence.GetNumberOfDataNodes()
    frames: list[np.ndarray] = []
    poses: list[np.ndarray] = []
    m = vtkMatrix4x4()
    for k in range(n):
        vol = volume_sequence.GetNthDataNode(k)
        frames.append(_image_array(vol.GetImageData(), f"{label} frame {k}"))
        local = calib if calib is not None else _ijk_to_ras(vol)
        t = np.eye(4)
        if transform_sequence is not None:
            value = volume_sequence.GetNthIndexValue(k)
            tr = transform_sequence.GetDataNodeAtValue(value, False)
            tr = tr if tr is not None else transform_sequence.GetNthDataNode(0)
            tr.GetMatrixTransformToParent(m)
            t = vtk_to_matrix(m)
        poses.append(t @ local)
        report(progress, "mrml", k + 1, n)
    name = transform_sequence.GetName() if transform_sequence is not None else "identity"
    return _assemble(
        frames,
        poses,
        _index_times(volume_sequence),
        source=_sequence_source(volume_sequence),
        transform_name=f"{name} * {'ImageToProbe(calibration)' if calib is not None else 'IJKToRAS'}",
        metadata={"mrml_image_sequence": volume_sequence.GetName()},
    )


def sweep_from_node(
    node: Any,
    transform_sequence: Any = None,
    *,
    calibration: Any = None,
    progress: ProgressCallback | None = None,
) -> Sweep:
    """Build a :class:`Sweep` from whichever input node the user picked.

    * a ``vtkMRMLSequenceBrowserNode``: :func:`sweep_from_browser`;
    * a ``vtkMRMLSequenceNode`` of volumes: if a browser browses it (and no transform
      sequence is given), through that browser; else :func:`sweep_from_sequences`;
    * a ``vtkMRMLScalarVolumeNode`` that is a browser's proxy (the image shown in the
      views): through that browser.
    """
    if node is None:
        raise BoneUSReconError("no input selected: pick a sequence browser or a volume sequence")
    scene = node.GetScene()
    if node.IsA("vtkMRMLSequenceBrowserNode"):
        return sweep_from_browser(node, calibration=calibration, progress=progress)
    if node.IsA("vtkMRMLSequenceNode"):
        if transform_sequence is None and scene is not None:
            browser = _sequences_logic(scene).GetFirstBrowserNodeForSequenceNode(node)
            if browser is not None:
                return sweep_from_browser(
                    browser, image_sequence=node, calibration=calibration, progress=progress
                )
        return sweep_from_sequences(
            node, transform_sequence, calibration=calibration, progress=progress
        )
    if node.IsA("vtkMRMLScalarVolumeNode") and scene is not None:
        browser = _sequences_logic(scene).GetFirstBrowserNodeForProxyNode(node)
        if browser is not None:
            seq = browser.GetSequenceNode(node)
            return sweep_from_browser(
                browser, image_sequence=seq, calibration=calibration, progress=progress
            )
        raise BoneUSReconError(
            f"{_node_label(node)} is a single image, not a sweep; pick its sequence browser"
        )
    raise BoneUSReconError(
        f"cannot read a sweep from {_node_label(node)}; pick a sequence browser or a volume sequence"
    )


# ------------------------------------------------------------------------------------
# Sweep -> MRML
# ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class SweepNodes:
    """The nodes :func:`sweep_to_scene` created."""

    browser: Any
    """``vtkMRMLSequenceBrowserNode`` browsing both sequences."""
    image_sequence: Any
    """``vtkMRMLSequenceNode`` of 2D ``vtkMRMLScalarVolumeNode`` frames in pixel units."""
    transform_sequence: Any
    """``vtkMRMLSequenceNode`` of ``vtkMRMLLinearTransformNode``: ``ImageToReference``, pixel -> mm."""
    image_proxy: Any
    """The browser's image proxy, under :attr:`transform_proxy`."""
    transform_proxy: Any
    """The browser's transform proxy."""
    frames: np.ndarray
    """Sweep frame index of each sequence item."""


def sweep_to_scene(
    sweep: Sweep, scene: Any, *, name: str = "Sweep", valid_only: bool = True
) -> SweepNodes:
    """Put a sweep into a scene the way SlicerIGT/PLUS recordings look in Slicer.

    Each frame becomes a 2D scalar volume in pixel units (``IJKToRAS`` the identity)
    under an ``ImageToReference`` transform that carries the pixel spacing: the sweep's
    ``image_to_reference`` itself. That is how a PLUS recording appears in Slicer (its
    MetaIO ``ElementSpacing`` is 1, the millimetres live in the transforms), and it
    makes the trip scene -> :func:`sweep_from_node` bit-exact (a spacing divided out
    and multiplied back in would change poses by ~1e-16 mm, enough to flip threshold
    decisions downstream). Both sequences are indexed by time stamp (frame number if
    time stamps do not increase) and browsed together, the image proxy under the
    transform proxy.

    Parameters
    ----------
    sweep : Sweep
    scene : vtkMRMLScene
    name : str
        Prefix of the created node names.
    valid_only : bool
        Leave out invalid frames (their poses are unusable; Slicer could not show them).
    """
    idx = sweep.valid_indices if valid_only else np.arange(sweep.n_frames)
    if idx.size == 0:
        raise BoneUSReconError("the sweep has no valid frame to put in the scene", sweep.source)
    t = sweep.timestamps[idx]
    use_time = idx.size == 1 or bool(np.all(np.diff(t) > 0))
    values = [repr(float(x)) for x in t] if use_time else [str(int(k)) for k in idx]

    iseq = scene.AddNewNodeByClass("vtkMRMLSequenceNode", f"{name}-Image")
    tseq = scene.AddNewNodeByClass("vtkMRMLSequenceNode", f"{name}-ImageToReference")
    for seq in (iseq, tseq):
        seq.SetIndexName("time" if use_time else "frame")
        seq.SetIndexUnit("s" if use_time else "")
        seq.SetIndexType(seq.NumericIndex)

    mats = np.nan_to_num(sweep.image_to_reference[idx])
    for n_k, (k, value) in enumerate(zip(idx, values, strict=True)):
        vol = scene.CreateNodeByClass("vtkMRMLScalarVolumeNode")
        vol.SetName(f"{name}-Image_{int(k):04d}")
        img = sweep.frame_image(int(k))
        img.GetPointData().GetScalars().SetName("ImageScalars")  # Slicer's volume name
        vol.SetAndObserveImageData(img)  # spacing 1, origin 0, identity directions
        iseq.SetDataNodeAtValue(vol, value)
        vol.UnRegister(None)  # the sequence holds its own copy

        m = mats[n_k].copy()
        if np.linalg.norm(m[:3, 2]) < 1e-9:
            # PLUS calibrations may leave the k column at zero; give the image plane a
            # normal one pixel long so that Slicer can invert the transform (k never
            # matters for 2D frames, and columns i, j and the origin stay untouched).
            normal = np.cross(m[:3, 0], m[:3, 1])
            pixel = np.sqrt(np.linalg.norm(m[:3, 0]) * np.linalg.norm(m[:3, 1]))
            m[:3, 2] = normal / max(np.linalg.norm(normal), 1e-300) * pixel
        tr = scene.CreateNodeByClass("vtkMRMLLinearTransformNode")
        tr.SetName(f"{name}-ImageToReference_{int(k):04d}")
        tr.SetMatrixTransformToParent(matrix_to_vtk(m))
        tseq.SetDataNodeAtValue(tr, value)
        tr.UnRegister(None)

    logic = _sequences_logic(scene)  # first: it registers the browser node class
    browser = scene.AddNewNodeByClass("vtkMRMLSequenceBrowserNode", f"{name}-Browser")
    browser.SetAndObserveMasterSequenceNodeID(iseq.GetID())
    browser.AddSynchronizedSequenceNodeID(tseq.GetID())
    logic.UpdateProxyNodesFromSequences(browser)
    iproxy = browser.GetProxyNode(iseq)
    tproxy = browser.GetProxyNode(tseq)
    iproxy.SetName(f"{name}-Image")
    tproxy.SetName(f"{name}-ImageToReference")
    iproxy.SetAndObserveTransformNodeID(tproxy.GetID())
    return SweepNodes(browser, iseq, tseq, iproxy, tproxy, idx)


def load_sweep_file(
    path: str | os.PathLike[str],
    scene: Any,
    *,
    calibration: str | os.PathLike[str] | None = None,
    transform: str | None = None,
    name: str | None = None,
    progress: ProgressCallback | None = None,
) -> SweepNodes:
    """Read a PLUS sequence file with BoneUSRecon's reader and put it in the scene.

    For recordings Slicer's own reader does not pose as wanted: BoneUSRecon's reader
    composes the pose chain (``inv(ReferenceToTracker) @ ProbeToTracker @ ImageToProbe``
    with the calibration XML), drops frames whose status is not OK, and the result is
    laid out as :func:`sweep_to_scene` does (frames in pixels under ``ImageToReference``).

    Parameters
    ----------
    path : path-like
        PLUS ``.mha``/``.mhd`` sequence.
    scene : vtkMRMLScene
    calibration, transform : optional
        As :func:`BoneUSRecon.Logic.sequence_io.read_sweep`.
    name : str, optional
        Node name prefix (default: the file name without its extensions).

    Raises
    ------
    BoneUSReconError
        Unreadable file or calibration (one line naming the file).
    """
    from BoneUSRecon.Logic.sequence_io import read_sweep

    sweep = read_sweep(path, calibration=calibration, transform=transform, progress=progress)
    return sweep_to_scene(sweep, scene, name=name or Path(path).name.split(".")[0])

"""Reading and writing PLUS sequence metafiles as :class:`~BoneUSRecon.Logic.sweep.Sweep`.

:func:`read_sweep` assembles a sweep from the file's header and pixels
(:mod:`.metaio`) and its per-frame poses (:mod:`.poses`, which also reads the PLUS
device-set XML holding the probe calibration); :func:`write_sweep` writes one back as a
PLUS sequence. Names from those modules that callers import from here stay importable.
"""

from __future__ import annotations

import os
import zlib
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import atomic_path, check_output_path
from BoneUSRecon.Logic.intensity import to_uint8
from BoneUSRecon.Logic.metaio import ELEMENT_TYPES, MetaHeader, read_header, read_pixels
from BoneUSRecon.Logic.poses import (
    find_chain,
    read_calibration,
    split_transform_name,
    sweep_transforms,
)
from BoneUSRecon.Logic.progress import ProgressCallback, report
from BoneUSRecon.Logic.sweep import Sweep

__all__ = [
    "ELEMENT_TYPES",
    "MetaHeader",
    "read_header",
    "read_sweep",
    "write_sweep",
    "read_calibration",
    "sweep_transforms",
]

# Aliases for callers that import the chain search from here (BoneUSRecon.Logic.live).
_find_path = find_chain
_split_name = split_transform_name

# zlib level 1: several times faster than the default 6 on speckle images, for a
# few per cent larger files.
_ZLIB_LEVEL = 1


# ------------------------------------------------------------------------------------
# Reading
# ------------------------------------------------------------------------------------
def _frame_values(hdr: MetaHeader, key: str) -> dict[int, str]:
    return {k: v for k, v in hdr.frame_fields.get(key, {}).items() if k < hdr.n_frames}


def read_sweep(
    path: str | os.PathLike[str],
    *,
    calibration: str | os.PathLike[str] | None = None,
    transform: str | None = None,
    progress: ProgressCallback | None = None,
) -> Sweep:
    """Read a PLUS sequence metafile into a :class:`~BoneUSRecon.Logic.sweep.Sweep`.

    Parameters
    ----------
    path : path-like
        ``.mha`` (data inline) or ``.mhd`` (data in ``.raw``/``.zraw``).
    calibration : path-like, optional
        PLUS device-set XML with ``<Transform From="Image" To="Probe" Matrix=.../>``,
        used when the file has no ``ImageToReferenceTransform``.
    transform : str, optional
        Pose to use (default ``ImageToReference``); see :mod:`.poses`.
    progress : callable, optional
        ``progress(stage, done, total)``.

    Returns
    -------
    Sweep
        Frames in MF orientation as ``uint8`` (a read-only memory map for
        uncompressed ``MET_UCHAR`` data), poses, timestamps, validity.

    Raises
    ------
    BoneUSReconError
        Any malformed input (one line naming the file and the problem), or when no
        frame is usable.
    """
    hdr = read_header(path)
    mats, problems, name = sweep_transforms(hdr, calibration=calibration, transform=transform)
    n = hdr.n_frames

    for k, status in _frame_values(hdr, "ImageStatus").items():
        if status.upper() != "OK" and not problems[k]:
            problems[k] = f"ImageStatus {status}"
    ts_fields = _frame_values(hdr, "Timestamp")
    timestamps = np.full(n, np.nan) if ts_fields else np.zeros(n)
    for k, text in ts_fields.items():
        try:
            timestamps[k] = float(text)
        except ValueError:
            raise BoneUSReconError(
                f"Seq_Frame{k:04d}_Timestamp: not a number: {text[:40]!r}", hdr.path
            ) from None

    valid = np.array([not p for p in problems], dtype=bool)
    reasons = {k: p for k, p in enumerate(problems) if p}
    if not valid.any():
        first = next(iter(reasons.items()))
        raise BoneUSReconError(
            f"every frame is invalid ({n} of {n}; frame {first[0]}: {first[1]})", hdr.path
        )

    report(progress, "read", 0, 2)
    pixels = read_pixels(hdr)
    report(progress, "read", 1, 2)
    frames = pixels if pixels.dtype == np.uint8 else to_uint8(pixels)
    report(progress, "read", 2, 2)
    meta: dict[str, Any] = {
        "element_type": hdr.element_type,
        "orientation": hdr.orientation,
        "compressed": hdr.compressed,
        "channels": hdr.channels,
        "data_file": str(hdr.data_file),
        "transforms": hdr.transform_names(),
    }
    for key in ("UltrasoundImageType", "UltrasoundImageOrientation"):
        if key in hdr.fields:
            meta[key] = hdr.fields[key]
    if calibration is not None:
        meta["calibration"] = str(calibration)
    return Sweep(
        frames=frames,
        image_to_reference=mats,
        timestamps=timestamps,
        valid=valid,
        source=hdr.path,
        transform_name=name,
        invalid_reasons=reasons,
        metadata=meta,
    )


# ------------------------------------------------------------------------------------
# Writing
# ------------------------------------------------------------------------------------
def _fmt_matrix(m: np.ndarray) -> str:
    # repr() gives the shortest text that reads back to the same double.
    return " ".join(repr(float(x)) for x in np.asarray(m, float).reshape(-1))


def _frame_chunks(frames: np.ndarray, chunk_bytes: int = 16 << 20) -> Iterator[bytes]:
    """The frames' bytes in C order, a few frames at a time (never the whole sweep)."""
    n = frames.shape[0]
    per = max(1, chunk_bytes // max(1, frames[0].nbytes))
    for a in range(0, n, per):
        yield np.ascontiguousarray(frames[a : a + per], dtype=np.uint8).tobytes()


_CSIZE_PLACEHOLDER_WIDTH = 20


def _header_text(sweep: Sweep, *, compressed: bool, data_file: str) -> str:
    n, h, w = sweep.frames.shape
    lines = [
        "ObjectType = Image",
        "NDims = 3",
        "AnatomicalOrientation = RAI",
        "BinaryData = True",
        "BinaryDataByteOrderMSB = False",
        "CenterOfRotation = 0 0 0",
        f"CompressedData = {compressed}",
    ]
    if compressed:
        # Padded so the real size can be patched in after streaming (as PLUS does).
        lines.append("CompressedDataSize = " + " " * _CSIZE_PLACEHOLDER_WIDTH)
    lines += [
        f"DimSize = {w} {h} {n}",
        "Kinds = domain domain list",
        "ElementNumberOfChannels = 1",
        "ElementSpacing = 1 1 1",
        "ElementType = MET_UCHAR",
        "Offset = 0 0 0",
        "TransformMatrix = 1 0 0 0 1 0 0 0 1",
        "UltrasoundImageOrientation = MF",
        "UltrasoundImageType = BRIGHTNESS",
    ]
    name = "ImageToReference"
    for k in range(n):
        tag = f"Seq_Frame{k:04d}"
        ok = "OK" if sweep.valid[k] else "INVALID"
        lines.append(f"{tag}_{name}Transform = {_fmt_matrix(sweep.image_to_reference[k])}")
        lines.append(f"{tag}_{name}TransformStatus = {ok}")
        lines.append(f"{tag}_Timestamp = {float(sweep.timestamps[k])!r}")
        lines.append(f"{tag}_ImageStatus = OK")
    lines.append(f"ElementDataFile = {data_file}")
    return "\n".join(lines) + "\n"


def _write_data(f: Any, frames: np.ndarray, compressed: bool) -> int:
    """Write pixel data to the open file; return the number of bytes written."""
    written = 0
    if compressed:
        c = zlib.compressobj(_ZLIB_LEVEL)
        for chunk in _frame_chunks(frames):
            out = c.compress(chunk)
            f.write(out)
            written += len(out)
        out = c.flush()
        f.write(out)
        written += len(out)
    else:
        for chunk in _frame_chunks(frames):
            f.write(chunk)
            written += len(chunk)
    return written


def _patch_csize(f: Any, header: str, size: int) -> None:
    key = "CompressedDataSize = "
    pos = header.index(key) + len(key)
    text = str(size).ljust(_CSIZE_PLACEHOLDER_WIDTH)
    f.seek(len(header[:pos].encode("latin-1")))
    f.write(text.encode("latin-1"))


def write_sweep(
    sweep: Sweep,
    path: str | os.PathLike[str],
    *,
    compress: bool = False,
    progress: ProgressCallback | None = None,
) -> Path:
    """Write a sweep as a PLUS sequence metafile, atomically.

    Frames are written in ``MF`` orientation as ``MET_UCHAR``; the pose of each frame
    as ``Seq_FrameNNNN_ImageToReferenceTransform`` with ``...TransformStatus`` ``OK``
    for valid frames and ``INVALID`` otherwise, plus ``..._Timestamp`` and
    ``..._ImageStatus``. Reading the file back gives the same frames, poses,
    timestamps and validity.

    Parameters
    ----------
    sweep : Sweep
    path : path-like
        ``.mha`` (one file) or ``.mhd`` (header plus ``.raw``, or ``.zraw`` when
        compressed, beside it; the data file is written first).
    compress : bool
        zlib-compress the pixel data (``CompressedData = True``).
    progress : callable, optional

    Returns
    -------
    Path
        The written header file.
    """
    p = check_output_path(path, (".mha", ".mhd"))
    frames = sweep.frames if sweep.frames.dtype == np.uint8 else to_uint8(sweep.frames)
    report(progress, "write", 0, 1)
    if p.suffix.lower() == ".mha":
        header = _header_text(sweep, compressed=compress, data_file="LOCAL")
        with atomic_path(p) as tmp, open(tmp, "wb") as f:
            f.write(header.encode("latin-1"))
            size = _write_data(f, frames, compress)
            if compress:
                _patch_csize(f, header, size)
    else:
        data_path = p.with_suffix(".zraw" if compress else ".raw")
        with atomic_path(data_path) as tmp, open(tmp, "wb") as f:
            size = _write_data(f, frames, compress)
        header = _header_text(sweep, compressed=compress, data_file=data_path.name)
        if compress:
            header = header.replace(
                "CompressedDataSize = " + " " * _CSIZE_PLACEHOLDER_WIDTH,
                f"CompressedDataSize = {size}",
            )
        with atomic_path(p) as tmp:
            tmp.write_bytes(header.encode("latin-1"))
    report(progress, "write", 1, 1)
    return p

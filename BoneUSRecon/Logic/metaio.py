"""MetaIO sequence headers and pixel data (``.mha`` / ``.mhd`` + ``.raw``/``.zraw``).

A PLUS sequence file is a MetaIO image: a text header of ``Key = Value`` lines, the
last of which is ``ElementDataFile``, then the pixel data (inline for ``LOCAL``, else
in the named file). The pixel data is a ``W x H x N`` stack of frames; per-frame
fields ``Seq_FrameNNNN_<Field>`` carry the tracking:

* ``Seq_FrameNNNN_<From>To<To>Transform``: 16 numbers, row-major 4x4;
* ``Seq_FrameNNNN_<From>To<To>TransformStatus``: ``OK`` or anything else (invalid);
* ``Seq_FrameNNNN_Timestamp`` (s) and ``Seq_FrameNNNN_ImageStatus``.

This module parses and checks the header (:func:`read_header`) and reads the pixels
(:func:`read_pixels`); :mod:`.poses` turns the transform fields into poses and
:mod:`.sequence_io` assembles both into a :class:`~BoneUSRecon.Logic.sweep.Sweep`
(and writes sweeps back).

Why a small parser rather than SimpleITK
----------------------------------------
SimpleITK reads these headers (``GetMetaDataKeys`` exposes the ``Seq_Frame`` fields)
but always loads the whole image into memory, and its errors on malformed files are
long multi-line ITK exceptions. The parser below reads only the header, then maps
uncompressed data with :class:`numpy.memmap` (frames are read lazily, so a 600 MB
2,000-frame sweep costs almost no memory until frames are touched) and inflates
compressed data with a streaming :mod:`zlib` decompressor straight into the output
buffer (a temporary file-backed map for very large sweeps). It also gives one-line
errors that name the problem. SimpleITK serves as the test oracle on the same files.

Touched pages of a memory map count in the process's resident set until the OS
reclaims them; :meth:`Sweep.iter_frames` releases them as it goes, so a consumer that
walks all frames through it keeps its footprint flat (``Testing/benchmarks/bench_io.py``
measures it; figures in ``Testing/benchmarks/README.md``).

Image orientation
-----------------
``UltrasoundImageOrientation`` says how the stored image axes relate to the
transducer (PLUS, ``igsioCommon.h``): the first letter is the transducer axis along
image x (columns): ``M`` marked or ``U`` unmarked side; the second along image y
(rows): ``F`` far from or ``N`` near the transducer. PLUS stores its calibration and
poses for ``MF`` images and converts other orientations to ``MF`` by flipping (its
``vtkPlusUsImageConverter``: ``U`` flips x, ``N`` flips y). We do the same, as
memory-map views (no copy): ``UF`` -> reverse columns, ``MN`` -> reverse rows,
``UN`` -> both; ``MF`` (and a missing field) -> unchanged. The header transforms are
used as they are, since they already refer to the ``MF`` image.

Pixel types
-----------
``MET_UCHAR`` is used as is; ``MET_CHAR``, ``MET_USHORT``, ``MET_SHORT``,
``MET_FLOAT`` and ``MET_DOUBLE`` are brought to ``uint8`` by
:func:`BoneUSRecon.Logic.intensity.to_uint8` (see there for the rules). Multi-channel
frames (``ElementNumberOfChannels`` > 1, grey B-mode stored as RGB) use channel 0.
"""

from __future__ import annotations

import os
import re
import tempfile
import zlib
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import check_input_file
from BoneUSRecon.Logic.sweep import _backing_mmap, _release

__all__ = ["ELEMENT_TYPES", "TRANSFORM_NAME_RE", "MetaHeader", "read_header", "read_pixels"]

#: MetaIO element types we read, and their numpy types (byte order set per file).
ELEMENT_TYPES: dict[str, str] = {
    "MET_UCHAR": "u1",
    "MET_CHAR": "i1",
    "MET_USHORT": "u2",
    "MET_SHORT": "i2",
    "MET_FLOAT": "f4",
    "MET_DOUBLE": "f8",
}

#: Orientation -> (flip rows, flip columns) to reach MF (see module docstring).
_ORIENTATION_FLIPS: dict[str, tuple[bool, bool]] = {
    "MF": (False, False),
    "MN": (True, False),
    "UF": (False, True),
    "UN": (True, True),
}

_MAX_LINE = 1 << 20  # a header line longer than this is binary data, not a header
_KEY_RE = re.compile(r"^[A-Za-z_][A-Za-z0-9_.\-]*$")
_FRAME_KEY_RE = re.compile(r"^Seq_Frame(\d+)_(\S+)$")
#: A transform name ``<From>To<To>`` (PLUS spelling: the target frame starts upper case).
TRANSFORM_NAME_RE = re.compile(r"^([A-Za-z0-9]+?)To([A-Z][A-Za-z0-9]*)$")
# Above this many decompressed bytes, inflate into a temporary file-backed map
# rather than RAM, so that big compressed sweeps keep memory bounded too.
_INFLATE_TO_DISK_BYTES = 256 * 1024 * 1024
_CHUNK = 1 << 20
_RELEASE_BYTES = 64 << 20


# ------------------------------------------------------------------------------------
# Header
# ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class MetaHeader:
    """A parsed, checked MetaIO sequence header.

    Attributes
    ----------
    path : Path
        The header file.
    fields : dict[str, str]
        Global fields (not ``Seq_Frame...``), in file order.
    frame_fields : dict[str, dict[int, str]]
        ``field name -> {frame index -> value}`` for ``Seq_FrameNNNN_<name>``.
    dim_size : tuple of int
        ``(W, H, N)``: columns, rows, frames.
    channels : int
        ``ElementNumberOfChannels``.
    element_type : str
        The MetaIO type name, e.g. ``"MET_UCHAR"``.
    dtype : numpy.dtype
        Pixel type with the file's byte order.
    compressed : bool
        ``CompressedData = True`` (zlib).
    compressed_size : int or None
        ``CompressedDataSize`` when given.
    data_file : Path
        File holding the pixel data (``path`` itself for ``LOCAL``).
    data_offset : int
        Byte offset of the pixel data in ``data_file``.
    orientation : str
        ``UltrasoundImageOrientation`` (``"MF"`` when absent).
    """

    path: Path
    fields: dict[str, str]
    frame_fields: dict[str, dict[int, str]]
    dim_size: tuple[int, int, int]
    channels: int
    element_type: str
    dtype: np.dtype
    compressed: bool
    compressed_size: int | None
    data_file: Path
    data_offset: int
    orientation: str

    @property
    def n_frames(self) -> int:
        """Number of frames (``DimSize[2]``)."""
        return self.dim_size[2]

    @property
    def data_bytes(self) -> int:
        """Bytes of uncompressed pixel data the header promises."""
        w, h, n = self.dim_size
        return w * h * n * self.channels * self.dtype.itemsize

    def transform_names(self) -> list[str]:
        """``AToB`` names of all transforms in the header (per-frame and global)."""
        names = [k[: -len("Transform")] for k in self.frame_fields if k.endswith("Transform")]
        names += [k[: -len("Transform")] for k in self.fields if k.endswith("Transform")]
        return list(dict.fromkeys(n for n in names if TRANSFORM_NAME_RE.match(n)))


def _split_header(path: Path) -> tuple[dict[str, str], dict[str, dict[int, str]], int]:
    """Read ``Key = Value`` lines up to ``ElementDataFile``; return fields and data offset."""
    fields: dict[str, str] = {}
    frame_fields: dict[str, dict[int, str]] = defaultdict(dict)
    with open(path, "rb") as f:
        lineno = 0
        while True:
            line = f.readline(_MAX_LINE)
            lineno += 1
            if not line:
                if not fields:
                    raise BoneUSReconError("not a MetaIO metafile (no header)", path)
                raise BoneUSReconError("header has no ElementDataFile field", path)
            if len(line) >= _MAX_LINE and not line.endswith(b"\n"):
                raise BoneUSReconError(
                    f"not a MetaIO metafile (line {lineno} is not a header line)", path
                )
            # latin-1 never fails to decode; bad bytes are caught by the key check.
            text = line.decode("latin-1").replace("\t", " ").strip()
            if not text:
                continue
            key, sep, value = text.partition("=")
            key, value = key.strip(), value.strip()
            if not sep or not _KEY_RE.match(key) or not value.isprintable():
                if not fields:
                    raise BoneUSReconError(
                        "not a MetaIO metafile (expected 'Key = Value' header lines)", path
                    )
                raise BoneUSReconError(
                    f"malformed header line {lineno} (expected 'Key = Value'): {text[:40]!r}",
                    path,
                )
            m = _FRAME_KEY_RE.match(key)
            if m:
                frame_fields[m.group(2)][int(m.group(1))] = value
            else:
                fields[key] = value
            if key == "ElementDataFile":
                return fields, dict(frame_fields), f.tell()


def _int_list(fields: dict[str, str], key: str, path: Path, count: int | None = None) -> list[int]:
    raw = fields.get(key)
    if raw is None:
        raise BoneUSReconError(f"header has no {key} field", path)
    try:
        vals = [int(v) for v in raw.split()]
    except ValueError:
        raise BoneUSReconError(f"{key} must be integers, got {raw[:40]!r}", path) from None
    if count is not None and len(vals) != count:
        raise BoneUSReconError(f"{key} must have {count} values, got {raw[:40]!r}", path)
    return vals


def _bool_field(fields: dict[str, str], key: str, path: Path, default: bool) -> bool:
    raw = fields.get(key)
    if raw is None:
        return default
    if raw.lower() in ("true", "1", "yes"):
        return True
    if raw.lower() in ("false", "0", "no"):
        return False
    raise BoneUSReconError(f"{key} must be True or False, got {raw[:40]!r}", path)


def read_header(path: str | os.PathLike[str]) -> MetaHeader:
    """Parse and check the header of a MetaIO sequence file (no pixel data is read).

    Parameters
    ----------
    path : path-like
        ``.mha`` or ``.mhd`` file.

    Returns
    -------
    MetaHeader

    Raises
    ------
    BoneUSReconError
        Missing or empty file, not a metafile, a single 2D image, zero frames, unknown
        ``ElementType``, no ``ElementDataFile``, unsupported layout.
    """
    path = check_input_file(path)
    fields, frame_fields, offset = _split_header(path)

    ndims = _int_list(fields, "NDims", path, 1)[0]
    if ndims == 2:
        raise BoneUSReconError(
            "a single 2D image (NDims = 2), not a sequence of tracked frames", path
        )
    if ndims != 3:
        raise BoneUSReconError(f"expected NDims = 3 (a sequence of 2D frames), got {ndims}", path)
    dims = _int_list(fields, "DimSize", path, 3)
    w, h, n = dims
    if w < 1 or h < 1 or n < 0:
        raise BoneUSReconError(f"DimSize must be positive, got {fields['DimSize']!r}", path)
    if n == 0:
        raise BoneUSReconError("the sequence has zero frames (DimSize ... 0)", path)

    etype = fields.get("ElementType")
    if etype is None:
        raise BoneUSReconError("header has no ElementType field", path)
    if etype not in ELEMENT_TYPES:
        raise BoneUSReconError(
            f"unknown ElementType {etype[:30]!r}; supported: {', '.join(ELEMENT_TYPES)}", path
        )
    channels = (
        _int_list(fields, "ElementNumberOfChannels", path, 1)[0]
        if ("ElementNumberOfChannels" in fields)
        else 1
    )
    if channels < 1:
        raise BoneUSReconError(f"ElementNumberOfChannels must be >= 1, got {channels}", path)
    msb = _bool_field(fields, "BinaryDataByteOrderMSB", path, False) or _bool_field(
        fields, "ElementByteOrderMSB", path, False
    )
    dtype = np.dtype(ELEMENT_TYPES[etype]).newbyteorder(">" if msb else "<")
    if not _bool_field(fields, "BinaryData", path, True):
        raise BoneUSReconError("ASCII pixel data (BinaryData = False) is not supported", path)
    compressed = _bool_field(fields, "CompressedData", path, False)
    csize = None
    if "CompressedDataSize" in fields:
        csize = _int_list(fields, "CompressedDataSize", path, 1)[0]
        if csize < 0:
            raise BoneUSReconError(f"CompressedDataSize must be >= 0, got {csize}", path)

    edf = fields["ElementDataFile"]
    if edf.upper() == "LOCAL":
        data_file, data_offset = path, offset
    elif edf.upper() == "LIST" or "%" in edf or len(edf.split()) > 1:
        raise BoneUSReconError(
            f"ElementDataFile {edf[:40]!r}: multi-file data is not supported", path
        )
    else:
        data_file = path.parent / edf
        try:
            found = data_file.is_file()
        except (OSError, ValueError):  # name too long, NUL byte
            found = False
        if not found:
            raise BoneUSReconError(f"data file {edf!r} named by ElementDataFile not found", path)
        data_offset = 0
        if "HeaderSize" in fields:
            hs = _int_list(fields, "HeaderSize", path, 1)[0]
            if hs == -1 and not compressed:  # MetaIO: data at the end of the file
                w_, h_, n_ = dims
                data_offset = data_file.stat().st_size - w_ * h_ * n_ * channels * dtype.itemsize
                data_offset = max(data_offset, 0)
            elif hs >= 0:
                data_offset = hs
            else:
                raise BoneUSReconError(f"HeaderSize {hs} is not supported", path)

    orientation = fields.get("UltrasoundImageOrientation", "MF").upper()
    if orientation in ("", "??", "XX"):
        orientation = "MF"
    # PLUS also writes three-letter forms (MFA, MFD): the third letter is the z axis,
    # which does not matter for 2D frames.
    if orientation[:2] not in _ORIENTATION_FLIPS:
        raise BoneUSReconError(
            f"unknown UltrasoundImageOrientation {orientation[:10]!r}; expected MF, MN, UF or UN",
            path,
        )
    return MetaHeader(
        path=path,
        fields=fields,
        frame_fields=frame_fields,
        dim_size=(w, h, n),
        channels=channels,
        element_type=etype,
        dtype=dtype,
        compressed=compressed,
        compressed_size=csize,
        data_file=data_file,
        data_offset=data_offset,
        orientation=orientation[:2],
    )


# ------------------------------------------------------------------------------------
# Pixel data
# ------------------------------------------------------------------------------------
def _dims_text(hdr: MetaHeader) -> str:
    w, h, n = hdr.dim_size
    ch = f", {hdr.channels} channels" if hdr.channels > 1 else ""
    return f"DimSize {w} {h} {n} ({hdr.element_type}{ch})"


# zlib's best ratio is about 1032:1; more than this is a wrong DimSize, not data.
_ZLIB_MAX_RATIO = 1100


def _inflate(hdr: MetaHeader) -> np.ndarray:
    """Stream-inflate zlib data into a flat uint8 buffer of exactly ``data_bytes``."""
    expected = hdr.data_bytes
    stored = max(hdr.data_file.stat().st_size - hdr.data_offset, 0)
    if hdr.compressed_size is not None:
        stored = min(stored, hdr.compressed_size)
    if expected > _ZLIB_MAX_RATIO * stored + 1024:
        # Checked before allocating, so a corrupt DimSize cannot exhaust memory.
        raise BoneUSReconError(
            f"{_dims_text(hdr)} disagrees with the data: {expected} bytes cannot come "
            f"from {stored} bytes of compressed data",
            hdr.data_file,
        )
    out: np.ndarray
    if expected > _INFLATE_TO_DISK_BYTES:
        # Backed by an anonymous temporary file: the OS pages it, RAM stays bounded.
        tmp = tempfile.TemporaryFile(prefix="boneusrecon-inflate-")
        tmp.truncate(expected)
        out = np.memmap(tmp, dtype=np.uint8, mode="w+", shape=(expected,))
        tmp.close()  # the map keeps the (already unlinked) file alive
    else:
        out = np.empty(expected, np.uint8)
    mm = _backing_mmap(out)
    d = zlib.decompressobj()
    pos = 0
    remaining = hdr.compressed_size
    src = hdr.data_file
    with open(src, "rb") as f:
        f.seek(hdr.data_offset)
        while not d.eof:
            want = _CHUNK if remaining is None else min(_CHUNK, remaining)
            chunk = f.read(want) if want > 0 else b""
            if not chunk:
                raise BoneUSReconError(
                    f"truncated compressed data: it ends after inflating to {pos} of the "
                    f"{expected} bytes that {_dims_text(hdr)} needs",
                    src,
                )
            if remaining is not None:
                remaining -= len(chunk)
            while chunk:
                try:
                    # Cap the output so that wrong DimSize cannot blow up memory.
                    piece = d.decompress(chunk, max(expected - pos, 0) + 1)
                except zlib.error as exc:
                    raise BoneUSReconError(f"corrupt compressed (zlib) data: {exc}", src) from None
                if pos + len(piece) > expected:
                    raise BoneUSReconError(
                        f"{_dims_text(hdr)} disagrees with the data: it inflates to more "
                        f"than the {expected} bytes expected",
                        src,
                    )
                out[pos : pos + len(piece)] = np.frombuffer(piece, np.uint8)
                if mm is not None and pos // _RELEASE_BYTES != (pos + len(piece)) // _RELEASE_BYTES:
                    _release(mm)  # written pages go to the temporary file, not RSS
                pos += len(piece)
                chunk = d.unconsumed_tail
                if d.eof:
                    break
    if pos != expected:
        raise BoneUSReconError(
            f"{_dims_text(hdr)} disagrees with the data: it inflates to {pos} bytes, "
            f"expected {expected}",
            src,
        )
    return out


def read_pixels(hdr: MetaHeader) -> np.ndarray:
    """The frames of a sequence file, in ``MF`` orientation and the file's pixel type.

    Parameters
    ----------
    hdr : MetaHeader
        From :func:`read_header`.

    Returns
    -------
    ndarray, shape (N, H, W)
        A read-only memory map (views flipped to ``MF``, channel 0) for uncompressed
        data, else the inflated array.

    Raises
    ------
    BoneUSReconError
        The data is truncated, longer than ``DimSize`` says, or corrupt.
    """
    w, h, n = hdr.dim_size
    c = hdr.channels
    shape = (n, h, w, c) if c > 1 else (n, h, w)
    if hdr.compressed:
        raw = _inflate(hdr)
        arr = raw.view(hdr.dtype).reshape(shape)
    else:
        size = hdr.data_file.stat().st_size
        available = size - hdr.data_offset
        expected = hdr.data_bytes
        if available < expected:
            raise BoneUSReconError(
                f"truncated data: {_dims_text(hdr)} needs {expected} bytes but the file "
                f"holds {max(available, 0)}",
                hdr.data_file,
            )
        if available > expected:
            raise BoneUSReconError(
                f"{_dims_text(hdr)} disagrees with the data: expected {expected} bytes, "
                f"the file holds {available}",
                hdr.data_file,
            )
        arr = np.memmap(
            hdr.data_file, dtype=hdr.dtype, mode="r", offset=hdr.data_offset, shape=shape
        )
    if c > 1:
        arr = arr[..., 0]
    flip_rows, flip_cols = _ORIENTATION_FLIPS[hdr.orientation]
    if flip_rows:
        arr = arr[:, ::-1, :]
    if flip_cols:
        arr = arr[:, :, ::-1]
    return arr

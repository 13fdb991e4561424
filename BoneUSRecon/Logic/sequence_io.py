"""Reading and writing PLUS sequence metafiles (``.mha`` / ``.mhd`` + ``.raw``/``.zraw``).

A PLUS sequence file is a MetaIO image: a text header of ``Key = Value`` lines, the
last of which is ``ElementDataFile``, then the pixel data (inline for ``LOCAL``, else
in the named file). The pixel data is a ``W x H x N`` stack of frames; per-frame
fields ``Seq_FrameNNNN_<Field>`` carry the tracking:

* ``Seq_FrameNNNN_<From>To<To>Transform``: 16 numbers, row-major 4x4;
* ``Seq_FrameNNNN_<From>To<To>TransformStatus``: ``OK`` or anything else (invalid);
* ``Seq_FrameNNNN_Timestamp`` (s) and ``Seq_FrameNNNN_ImageStatus``.

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
walks all frames through it keeps its footprint flat (``Testing/benchmarks/bench_io.py``:
2,000 frames of 640x480 read in 0.16 s and iterated with no growth of peak RSS).

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

Choosing the pose
-----------------
The pose of frame ``k`` is ``ImageToReference``: taken directly when the file has
``ImageToReferenceTransform``, otherwise composed along the chain of available
transforms, normally ``inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe``.
``ImageToProbe`` (the probe calibration, which carries the mm/pixel scale) comes from
``calibration=`` (a PLUS device-set XML; it wins when given, the user asked for it),
else from a per-frame or global ``ImageToProbeTransform`` header field.
``transform="ImageToTracker"`` (any ``ImageTo<X>``) picks another target frame;
``transform="ProbeToTracker"`` (any ``<A>To<B>``) means "the pose given by that
transform": ``ProbeToTracker * ImageToProbe``.
"""

from __future__ import annotations

import os
import re
import tempfile
import xml.etree.ElementTree as ET
import zlib
from collections import defaultdict, deque
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import atomic_path, check_input_file, check_output_path
from BoneUSRecon.Logic.intensity import to_uint8
from BoneUSRecon.Logic.progress import ProgressCallback, report
from BoneUSRecon.Logic.sweep import Sweep, _backing_mmap, _release

__all__ = [
    "ELEMENT_TYPES",
    "MetaHeader",
    "read_header",
    "read_sweep",
    "write_sweep",
    "read_calibration",
    "sweep_transforms",
]

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
_TRANSFORM_RE = re.compile(r"^([A-Za-z0-9]+?)To([A-Z][A-Za-z0-9]*)$")
# Above this many decompressed bytes, inflate into a temporary file-backed map
# rather than RAM, so that big compressed sweeps keep memory bounded too.
_INFLATE_TO_DISK_BYTES = 256 * 1024 * 1024
_CHUNK = 1 << 20
_RELEASE_BYTES = 64 << 20
# zlib level 1: several times faster than the default 6 on speckle images, for a
# few per cent larger files.
_ZLIB_LEVEL = 1


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
        return list(dict.fromkeys(n for n in names if _TRANSFORM_RE.match(n)))


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
    channels = _int_list(fields, "ElementNumberOfChannels", path, 1)[0] if (
        "ElementNumberOfChannels" in fields
    ) else 1
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


def _read_pixels(hdr: MetaHeader) -> np.ndarray:
    """Pixel data as ``(N, H, W)`` in the file's orientation and type (lazy if possible)."""
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
        arr = np.memmap(hdr.data_file, dtype=hdr.dtype, mode="r", offset=hdr.data_offset, shape=shape)
    if c > 1:
        arr = arr[..., 0]
    flip_rows, flip_cols = _ORIENTATION_FLIPS[hdr.orientation]
    if flip_rows:
        arr = arr[:, ::-1, :]
    if flip_cols:
        arr = arr[:, :, ::-1]
    return arr


# ------------------------------------------------------------------------------------
# Transforms
# ------------------------------------------------------------------------------------
def _parse_matrix(text: str, what: str, path: Path) -> np.ndarray:
    parts = text.split()
    if len(parts) != 16:
        raise BoneUSReconError(f"{what}: expected 16 numbers, got {len(parts)}", path)
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise BoneUSReconError(f"{what}: non-numeric value in {text[:60]!r}", path) from None
    return np.array(vals, dtype=np.float64).reshape(4, 4)


@dataclass
class _Link:
    """One transform ``From -> To`` per frame, with per-frame problems."""

    name: str
    matrices: np.ndarray  # (N, 4, 4), identity where unusable
    problem: list[str]  # per frame, "" if usable
    source: str  # "frames", "header", "calibration"


def _frame_link(hdr: MetaHeader, name: str) -> _Link:
    n = hdr.n_frames
    mats = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    problem = [f"{name} missing"] * n
    values = hdr.frame_fields.get(name + "Transform", {})
    statuses = hdr.frame_fields.get(name + "TransformStatus", {})
    for k, text in values.items():
        if k >= n:
            continue
        m = _parse_matrix(text, f"Seq_Frame{k:04d}_{name}Transform", hdr.path)
        status = statuses.get(k, "OK")
        if status.upper() != "OK":
            problem[k] = f"{name} status {status}"
        elif not np.all(np.isfinite(m)):
            problem[k] = f"{name} has NaN or infinite values"
        else:
            mats[k] = m
            problem[k] = ""
    return _Link(name, mats, problem, "frames")


def _const_link(name: str, m: np.ndarray, n: int, source: str) -> _Link:
    mats = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    if np.all(np.isfinite(m)):
        mats[:] = m
        problem = [""] * n
    else:
        problem = [f"{name} has NaN or infinite values"] * n
    return _Link(name, mats, problem, source)


def _invert(link: _Link) -> _Link:
    m = link.matrices
    det = np.linalg.det(m)
    scale = np.abs(m[:, :3, :3]).max(axis=(1, 2)) ** 3
    bad = ~(np.abs(det) > 1e-12 * np.maximum(scale, 1e-300))
    problem = list(link.problem)
    safe = m.copy()
    for k in np.flatnonzero(bad):
        if not problem[k]:
            problem[k] = f"{link.name} is singular"
        safe[k] = np.eye(4)
    inv = np.linalg.inv(safe)
    a, b = _TRANSFORM_RE.match(link.name).groups()  # type: ignore[union-attr]
    return _Link(f"{b}To{a}", inv, problem, link.source)


def _split_name(name: str) -> tuple[str, str] | None:
    if name.endswith("Transform"):
        name = name[: -len("Transform")]
    m = _TRANSFORM_RE.match(name)
    return (m.group(1), m.group(2)) if m else None


def _find_path(edges: dict[str, tuple[str, str]], start: str, goal: str) -> list[tuple[str, bool]] | None:
    """Shortest chain of transforms from frame ``start`` to ``goal``.

    Returns a list of ``(name, inverted)`` applied in order, or None.
    """
    adj: dict[str, list[tuple[str, str, bool]]] = defaultdict(list)
    for name, (a, b) in edges.items():
        adj[a].append((b, name, False))
        adj[b].append((a, name, True))
    prev: dict[str, tuple[str, str, bool]] = {}
    seen = {start}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        if node == goal:
            break
        # Prefer forward use of a transform over inverting one (PLUS names transforms
        # so that the chain to the reference is mostly forward); ties by name, so the
        # choice never depends on header order.
        for nxt, name, inverted in sorted(adj[node], key=lambda t: (t[2], t[1])):
            if nxt not in seen:
                seen.add(nxt)
                prev[nxt] = (node, name, inverted)
                queue.append(nxt)
    if goal not in seen:
        return None
    steps: list[tuple[str, bool]] = []
    node = goal
    while node != start:
        p, name, inverted = prev[node]
        steps.append((name, inverted))
        node = p
    return steps[::-1]


def _chain_text(steps: list[tuple[str, bool]]) -> str:
    return " * ".join(f"inv({n})" if inv else n for n, inv in reversed(steps))


def sweep_transforms(
    hdr: MetaHeader,
    *,
    calibration: str | os.PathLike[str] | None = None,
    transform: str | None = None,
) -> tuple[np.ndarray, list[str], str]:
    """Compose the per-frame ``ImageToReference`` (or the named target) pose.

    Parameters
    ----------
    hdr : MetaHeader
    calibration : path-like, optional
        PLUS device-set XML with the ``Image -> Probe`` calibration.
    transform : str, optional
        Target pose name (see module docstring). Default ``ImageToReference``.

    Returns
    -------
    matrices : ndarray, shape (N, 4, 4)
        Pixel ``(i, j, 0, 1)`` -> target frame mm; identity where unusable.
    problems : list of str
        Per frame, why it cannot be used ("" if it can).
    name : str
        The chain used, e.g. ``"inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe"``.
    """
    path = hdr.path
    edges: dict[str, tuple[str, str]] = {}
    sources: dict[str, str] = {}
    for key in hdr.frame_fields:
        if key.endswith("Transform"):
            ab = _split_name(key)
            if ab:
                edges[key[: -len("Transform")]] = ab
                sources[key[: -len("Transform")]] = "frames"
    for key in hdr.fields:
        if key.endswith("Transform"):
            ab = _split_name(key)
            if ab and key[: -len("Transform")] not in edges:
                edges[key[: -len("Transform")]] = ab
                sources[key[: -len("Transform")]] = "header"
    file_edges = sorted(edges)
    calib: np.ndarray | None = None
    if calibration is not None:
        calib = read_calibration(calibration)
        edges["ImageToProbe"] = ("Image", "Probe")
        sources["ImageToProbe"] = "calibration"

    have = ", ".join(sorted(edges)) or "none"
    if transform is None:
        target_name = "ImageToReference"
    else:
        target_name = transform[: -len("Transform")] if transform.endswith("Transform") else transform
    ab = _split_name(target_name)
    if ab is None:
        raise BoneUSReconError(
            f"--transform {transform!r} is not a transform name like ImageToReference", path
        )
    a, b = ab
    if a == b:
        raise BoneUSReconError(f"--transform {transform!r} maps a frame to itself", path)
    if a == "Image":
        steps = _find_path(edges, "Image", b)
    elif target_name in edges:
        # The image must reach frame A without the named transform itself, otherwise
        # "StylusToTracker" would be reached by going out and back along it.
        others = {k: v for k, v in edges.items() if k != target_name}
        head = _find_path(others, "Image", a)
        steps = None if head is None else head + [(target_name, False)]
    else:
        raise BoneUSReconError(
            f"the file has no {target_name} transform (it has: {have})", path
        )
    if steps is None and not file_edges:
        # A plain image stack: no calibration can give it poses.
        raise BoneUSReconError(
            "no transforms in the file: it is a plain image (a 3D volume or a stack of "
            "frames), not a tracked sweep; a PLUS sequence records a pose per frame "
            "(e.g. ProbeToTrackerTransform, ImageToReferenceTransform)",
            path,
        )
    if steps is None:
        if target_name == "ImageToReference":
            missing = [
                t for t in ("ReferenceToTracker", "ProbeToTracker", "ImageToProbe") if t not in edges
            ]
            # The calibration only helps when it is the one missing link.
            hint = (
                " (give the probe calibration with --calibration XML)"
                if missing == ["ImageToProbe"]
                else ""
            )
            raise BoneUSReconError(
                "no usable transform: no ImageToReferenceTransform and cannot compose "
                "inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe: missing "
                f"{', '.join(missing) or 'a link'}{hint}; the file has: {have}",
                path,
            )
        goal = b if a == "Image" else a
        raise BoneUSReconError(
            f"no usable transform: no chain of transforms from Image to {goal} for "
            f"{target_name}; the file has: {have}",
            path,
        )

    # Overflow in absurd (e.g. 1e300) matrices just makes those frames invalid.
    with np.errstate(all="ignore"):
        return _compose(hdr, steps, sources, calib)


def _compose(
    hdr: MetaHeader,
    steps: list[tuple[str, bool]],
    sources: dict[str, str],
    calib: np.ndarray | None,
) -> tuple[np.ndarray, list[str], str]:
    """Multiply the chain's links per frame and check each composed pose."""
    path, n = hdr.path, hdr.n_frames
    total = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    problems = [""] * n
    for name, inverted in steps:
        if sources[name] == "frames":
            link = _frame_link(hdr, name)
        elif sources[name] == "calibration":
            assert calib is not None
            link = _const_link(name, calib, n, "calibration")
        else:
            link = _const_link(
                name, _parse_matrix(hdr.fields[name + "Transform"], name + "Transform", path), n, "header"
            )
        if inverted:
            link = _invert(link)
        total = link.matrices @ total
        problems = [p or q for p, q in zip(problems, link.problem, strict=True)]

    # Frame-level checks on the composed pose: finite, affine, non-degenerate plane.
    finite = np.all(np.isfinite(total), axis=(1, 2))
    safe = np.where(finite[:, None, None], total, np.eye(4))
    affine_k = np.all(np.abs(safe[:, 3, :] - [0, 0, 0, 1]) <= 1e-6, axis=1)
    c0, c1 = safe[:, :3, 0], safe[:, :3, 1]
    n0, n1 = np.linalg.norm(c0, axis=1), np.linalg.norm(c1, axis=1)
    cross = np.linalg.norm(np.cross(c0, c1), axis=1)
    degenerate = ~(cross > 1e-9 * n0 * n1) | ~(n0 > 0) | ~(n1 > 0)
    for k in range(n):
        if problems[k]:
            continue
        if not finite[k]:
            problems[k] = "pose has NaN or infinite values"
        elif not affine_k[k]:
            problems[k] = "pose is not an affine transform (last row is not 0 0 0 1)"
        elif degenerate[k]:
            problems[k] = "pose is singular (image axes collapse)"
    total[np.array([bool(p) for p in problems], dtype=bool)] = np.eye(4)
    name = _chain_text(steps)
    return total, problems, name


# ------------------------------------------------------------------------------------
# Public API
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
        Pose to use (default ``ImageToReference``); see the module docstring.
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
    pixels = _read_pixels(hdr)
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


def read_calibration(
    xml_path: str | os.PathLike[str], *, from_frame: str = "Image", to_frame: str = "Probe"
) -> np.ndarray:
    """Read a transform from a PLUS device-set configuration XML.

    Looks for ``<CoordinateDefinitions><Transform From=.. To=.. Matrix=".."/>``; the
    reverse transform (``From=to_frame To=from_frame``) is inverted if that is what
    the file holds.

    Parameters
    ----------
    xml_path : path-like
    from_frame, to_frame : str
        Coordinate frame names, default ``Image`` -> ``Probe`` (the probe calibration).

    Returns
    -------
    ndarray, shape (4, 4)

    Raises
    ------
    BoneUSReconError
        Missing file, not XML, no such transform, bad or singular matrix.
    """
    p = check_input_file(xml_path)
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise BoneUSReconError(f"not a valid XML file: {exc}", p) from None
    what = f'<Transform From="{from_frame}" To="{to_frame}">'
    for el in root.iter("Transform"):
        a, b = el.get("From"), el.get("To")
        if (a, b) not in ((from_frame, to_frame), (to_frame, from_frame)):
            continue
        text = el.get("Matrix")
        if text is None:
            raise BoneUSReconError(f"{what} has no Matrix attribute", p)
        m = _parse_matrix(text, f"{what} Matrix", p)
        if not np.all(np.isfinite(m)):
            raise BoneUSReconError(f"{what} Matrix has NaN or infinite values", p)
        if abs(np.linalg.det(m)) < 1e-12 * max(np.abs(m[:3, :3]).max(), 1e-300) ** 3:
            raise BoneUSReconError(f"{what} Matrix is singular", p)
        return m if a == from_frame else np.linalg.inv(m)
    raise BoneUSReconError(f"no {what} in the file's <CoordinateDefinitions>", p)


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

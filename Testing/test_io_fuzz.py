"""Fuzzing the sequence-file reader: random and mutated files never crash it.

Whatever the bytes, :func:`read_sweep` either returns a Sweep or raises
:class:`BoneUSReconError` (the one clean, one-line error); any other exception,
a warning (pytest turns warnings into errors), or a hang is a bug.
"""

from __future__ import annotations

import os
import tempfile
import zlib
from pathlib import Path

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from test_sequence_io import build_fields, frames_u8, pixel_bytes, tracked_transforms

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.sequence_io import read_sweep
from BoneUSRecon.Logic.sweep import Sweep

# BONEUSRECON_FUZZ_EXAMPLES=5000 for a deep run; the suite's default stays fast.
FUZZ = settings(
    max_examples=int(os.environ.get("BONEUSRECON_FUZZ_EXAMPLES", "150")),
    deadline=None,
    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large],
)

KEYS = [
    "ObjectType",
    "NDims",
    "DimSize",
    "ElementType",
    "ElementDataFile",
    "CompressedData",
    "CompressedDataSize",
    "BinaryData",
    "BinaryDataByteOrderMSB",
    "ElementByteOrderMSB",
    "ElementNumberOfChannels",
    "HeaderSize",
    "UltrasoundImageOrientation",
    "ImageToProbeTransform",
    "Seq_Frame0000_ImageToReferenceTransform",
    "Seq_Frame0001_ImageToReferenceTransform",
    "Seq_Frame0000_ImageToReferenceTransformStatus",
    "Seq_Frame0000_Timestamp",
    "Seq_Frame0000_ImageStatus",
    "Seq_Frame0000_ProbeToTrackerTransform",
    "Seq_Frame0000_ReferenceToTrackerTransform",
]
VALUES = [
    "3",
    "2",
    "0",
    "-1",
    "1",
    "4 3 2",
    "4 3 0",
    "99999 99999 99999",
    "MET_UCHAR",
    "MET_SHORT",
    "MET_FLOAT",
    "MET_DOUBLE",
    "MET_FOO",
    "LOCAL",
    "data.raw",
    "LIST",
    "True",
    "False",
    "MF",
    "UN",
    "nan",
    "1e308",
    "OK",
    "MISSING",
    "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0 1",
    "1 0 0 0 0 1 0 0 0 0 1 0 0 0 0",
    "0 0 0 0 0 0 0 0 0 0 0 0 0 0 0 0",
    "",
]
TEXT = st.text(st.characters(codec="latin-1"), max_size=30)


def _read(data: bytes, name: str = "s.mha", extra: dict[str, bytes] | None = None, **kw) -> None:
    with tempfile.TemporaryDirectory() as d:
        p = Path(d) / name
        p.write_bytes(data)
        for fname, content in (extra or {}).items():
            (Path(d) / fname).write_bytes(content)
        try:
            s = read_sweep(p, **kw)
        except BoneUSReconError as exc:
            assert "\n" not in str(exc)
            return
        assert isinstance(s, Sweep)
        assert s.frames.dtype == np.uint8 and s.n_valid >= 1
        assert np.all(np.isfinite(s.image_to_reference))
        np.asarray(s.frames[-1]).sum()  # the data really is there


def _text(fields: list[list[str]]) -> bytes:
    return "".join(f"{k} = {v}\n" for k, v in fields).encode("latin-1")


@FUZZ
@given(
    lines=st.lists(
        st.tuples(st.one_of(st.sampled_from(KEYS), TEXT), st.one_of(st.sampled_from(VALUES), TEXT)),
        max_size=25,
    ),
    tail=st.binary(max_size=200),
)
def test_random_headers(lines, tail):
    body = "".join(f"{k} = {v}\n" for k, v in lines).encode("latin-1")
    _read(body + tail)


@FUZZ
@given(st.binary(max_size=400))
def test_random_bytes(data):
    _read(data)


FRAMES = frames_u8(4, 6, 8)
GOOD = build_fields(FRAMES)
GOOD_Z = build_fields(FRAMES, compressed=True)
TRACKED = build_fields(
    FRAMES, transforms=dict(tracked_transforms(4), ImageToProbe=np.tile(np.eye(4), (4, 1, 1)))
)
RAW = pixel_bytes(FRAMES)
ZRAW = zlib.compress(RAW)


@st.composite
def mutated_header(draw):
    """A valid header with a few lines deleted, duplicated, re-valued or re-keyed."""
    fields, data = draw(st.sampled_from([(GOOD, RAW), (GOOD_Z, ZRAW), (TRACKED, RAW)]))
    fields = [list(kv) for kv in fields]
    for _ in range(draw(st.integers(1, 4))):
        i = draw(st.integers(0, len(fields) - 1))
        op = draw(st.sampled_from(["delete", "duplicate", "value", "key", "numbers"]))
        if op == "delete":
            del fields[i]
        elif op == "duplicate":
            fields.insert(i, list(fields[i]))
        elif op == "value":
            fields[i][1] = draw(st.one_of(st.sampled_from(VALUES), TEXT))
        elif op == "key":
            fields[i][0] = draw(st.one_of(st.sampled_from(KEYS), TEXT))
        else:  # perturb one number of a numeric field
            parts = fields[i][1].split()
            if parts:
                j = draw(st.integers(0, len(parts) - 1))
                parts[j] = draw(
                    st.sampled_from(["nan", "inf", "-1", "0", "1e308", "x", "2.5", "99999"])
                )
                fields[i][1] = " ".join(parts)
        if not fields:
            break
    return _text(fields) + data


@FUZZ
@given(mutated_header())
def test_mutated_headers(data):
    _read(data)


@FUZZ
@given(
    which=st.sampled_from(["raw", "z"]),
    cut=st.floats(0, 1),
    flips=st.lists(st.tuples(st.floats(0, 1), st.integers(0, 255)), max_size=6),
)
def test_truncated_and_corrupted_files(which, cut, flips):
    data = bytearray(_text(GOOD) + RAW if which == "raw" else _text(GOOD_Z) + ZRAW)
    for pos, byte in flips:
        data[int(pos * (len(data) - 1))] = byte
    _read(bytes(data[: max(1, int(cut * len(data)))]))


@FUZZ
@given(
    data_file=st.one_of(
        st.sampled_from(["data.raw", "data.zraw", "missing.raw", "a" * 300, "."]), TEXT
    ),
    compressed=st.booleans(),
    cut=st.integers(0, 400),
)
def test_mhd_data_files(data_file, compressed, cut):
    fields = [list(kv) for kv in (GOOD_Z if compressed else GOOD)]
    fields[-1][1] = data_file
    payload = (ZRAW if compressed else RAW)[: len(RAW) - cut]
    _read(_text(fields), name="s.mhd", extra={"data.raw": payload, "data.zraw": payload})


@settings(max_examples=40, deadline=None)
@given(
    shape=st.tuples(st.integers(1, 5), st.integers(1, 7), st.integers(1, 9)),
    seed=st.integers(0, 2**32 - 1),
    name=st.sampled_from(["s.mha", "s.mhd"]),
    compress=st.booleans(),
    data=st.data(),
)
def test_round_trip_property(shape, seed, name, compress, data):
    """Any sweep written and read back has the same frames, poses, times and validity."""
    from scipy.spatial.transform import Rotation

    from BoneUSRecon.Logic.sequence_io import write_sweep

    n, h, w = shape
    rng = np.random.default_rng(seed)
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix() * rng.uniform(
        0.01, 2, (n, 1, 3)
    )
    m[:, :3, 3] = rng.normal(0, 1e3, (n, 3))
    valid = np.array(data.draw(st.lists(st.booleans(), min_size=n, max_size=n)))
    valid[rng.integers(n)] = True
    times = np.array(
        data.draw(st.lists(st.floats(-1e9, 1e9, allow_nan=False), min_size=n, max_size=n))
    )
    sweep = Sweep(rng.integers(0, 256, (n, h, w), dtype=np.uint8), m, times, valid)
    with tempfile.TemporaryDirectory() as d:
        back = read_sweep(write_sweep(sweep, Path(d) / name, compress=compress))
        assert np.array_equal(np.asarray(back.frames), sweep.frames)
        assert np.array_equal(back.image_to_reference[valid], m[valid])
        assert np.array_equal(back.timestamps, times)
        assert np.array_equal(back.valid, valid)
        del back  # release the memory map before the folder goes

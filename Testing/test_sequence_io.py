"""PLUS sequence metafile reading and writing, checked against SimpleITK and by hand.

The helpers at the top build sequence files field by field (so that each test states
exactly what the file holds); ``test_cli_info.py`` reuses them for its bad-input cases.
"""

from __future__ import annotations

import os
import zlib
from pathlib import Path

import numpy as np
import pytest
import SimpleITK as sitk
from conftest import REAL_MHA, REAL_XML  # Resources/SampleData, in the repository
from scipy.spatial.transform import Rotation

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.sequence_io import (
    read_calibration,
    read_header,
    read_sweep,
    write_sweep,
)
from BoneUSRecon.Logic.sweep import Sweep

N, H, W = 6, 10, 14
SPACING = 0.2  # mm per pixel of the synthetic calibration

MET = {
    np.dtype(np.uint8): "MET_UCHAR",
    np.dtype(np.int8): "MET_CHAR",
    np.dtype(np.uint16): "MET_USHORT",
    np.dtype(np.int16): "MET_SHORT",
    np.dtype(np.float32): "MET_FLOAT",
    np.dtype(np.float64): "MET_DOUBLE",
}


# ---------------------------------------------------------------------------------
# File builders
# ---------------------------------------------------------------------------------
def rigid(seed: int, n: int = N, scale: float = 1.0) -> np.ndarray:
    """``n`` random rigid 4x4 transforms (rotation scaled by ``scale``), translations in mm."""
    rng = np.random.default_rng(seed)
    m = np.tile(np.eye(4), (n, 1, 1))
    m[:, :3, :3] = Rotation.random(n, random_state=seed).as_matrix() * scale
    m[:, :3, 3] = rng.uniform(-100, 100, (n, 3))
    return m


def image_to_probe() -> np.ndarray:
    """A calibration: 0.2 mm pixels, rotated and offset like a real probe's."""
    m = np.eye(4)
    m[:3, :3] = Rotation.from_euler("xyz", [5, -80, 3], degrees=True).as_matrix() * SPACING
    m[:3, 3] = [12.7, 50.8, -0.5]
    return m


def mat_text(m: np.ndarray) -> str:
    return " ".join(repr(float(v)) for v in np.asarray(m).reshape(-1))


def frames_u8(n: int = N, h: int = H, w: int = W, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (n, h, w), dtype=np.uint8)


def build_fields(
    frames: np.ndarray,
    *,
    transforms: dict[str, np.ndarray] | None = None,
    statuses: dict[str, dict[int, str]] | None = None,
    image_status: dict[int, str] | None = None,
    timestamps: np.ndarray | None = None,
    orientation: str | None = "MF",
    compressed: bool = False,
    msb: bool = False,
    global_fields: dict[str, str] | None = None,
) -> list[list[str]]:
    """The header as an editable list of ``[key, value]`` (ElementDataFile last)."""
    n, h, w = frames.shape[:3]
    ch = frames.shape[3] if frames.ndim == 4 else 1
    f = [
        ["ObjectType", "Image"],
        ["NDims", "3"],
        ["BinaryData", "True"],
        ["BinaryDataByteOrderMSB", str(msb)],
        ["CompressedData", str(compressed)],
        ["DimSize", f"{w} {h} {n}"],
        ["ElementNumberOfChannels", str(ch)],
        ["ElementSpacing", "1 1 1"],
        ["ElementType", MET[frames.dtype.newbyteorder("=")]],
    ]
    if orientation is not None:
        f.append(["UltrasoundImageOrientation", orientation])
    for k, v in (global_fields or {}).items():
        f.append([k, v])
    transforms = {"ImageToReference": rigid(1)[:n]} if transforms is None else transforms
    statuses = statuses or {}
    for k in range(n):
        for name, mats in transforms.items():
            f.append([f"Seq_Frame{k:04d}_{name}Transform", mat_text(mats[k])])
            f.append(
                [f"Seq_Frame{k:04d}_{name}TransformStatus", statuses.get(name, {}).get(k, "OK")]
            )
        ts = 10.0 + 0.1 * k if timestamps is None else timestamps[k]
        f.append([f"Seq_Frame{k:04d}_Timestamp", repr(float(ts))])
        f.append([f"Seq_Frame{k:04d}_ImageStatus", (image_status or {}).get(k, "OK")])
    f.append(["ElementDataFile", "LOCAL"])
    return f


def pixel_bytes(frames: np.ndarray, *, compressed: bool = False, msb: bool = False) -> bytes:
    a = frames.astype(frames.dtype.newbyteorder(">" if msb else "<"))
    raw = np.ascontiguousarray(a).tobytes()
    return zlib.compress(raw) if compressed else raw


def write_file(
    path: Path, fields: list[list[str]], data: bytes, *, data_file: str | None = None
) -> Path:
    """Write header (+ data inline, or into ``data_file`` beside it)."""
    fields = [list(kv) for kv in fields]
    if data_file is not None:
        for kv in fields:
            if kv[0] == "ElementDataFile":
                kv[1] = data_file
        (path.parent / data_file).write_bytes(data)
        data = b""
    text = "".join(f"{k} = {v}\n" for k, v in fields)
    path.write_bytes(text.encode("latin-1") + data)
    return path


def make_file(path: Path, frames: np.ndarray | None = None, **kw) -> Path:
    """A valid sequence file (kwargs go to :func:`build_fields`)."""
    frames = frames_u8() if frames is None else frames
    fields = build_fields(frames, **kw)
    data = pixel_bytes(frames, compressed=kw.get("compressed", False), msb=kw.get("msb", False))
    return write_file(path, fields, data)


def set_field(fields: list[list[str]], key: str, value: str | None) -> list[list[str]]:
    """Change (or with None, remove) a header field."""
    out = [list(kv) for kv in fields if not (kv[0] == key and value is None)]
    for kv in out:
        if kv[0] == key:
            kv[1] = value
    return out


def tracked_transforms(n: int = N) -> dict[str, np.ndarray]:
    return {"ProbeToTracker": rigid(2, n), "ReferenceToTracker": rigid(3, n)}


def expected_chain(t: dict[str, np.ndarray], calib: np.ndarray) -> np.ndarray:
    return np.linalg.inv(t["ReferenceToTracker"]) @ t["ProbeToTracker"] @ calib


def write_xml(path: Path, m: np.ndarray, frm: str = "Image", to: str = "Probe") -> Path:
    rows = "\n".join(" ".join(repr(float(v)) for v in r) for r in m)
    path.write_text(
        f'<PlusConfiguration version="2.3">\n  <CoordinateDefinitions>\n'
        f'    <Transform From="{frm}" To="{to}" Matrix="\n{rows}" Error="0.5"/>\n'
        f"  </CoordinateDefinitions>\n</PlusConfiguration>\n"
    )
    return path


def simple_sweep(n: int = N, valid: np.ndarray | None = None) -> Sweep:
    m = rigid(4, n) @ np.diag([SPACING, SPACING * 1.5, 1.0, 1.0])
    return Sweep(
        frames=frames_u8(n),
        image_to_reference=m,
        timestamps=np.linspace(3.25, 4.0, n) + 1e-7,
        valid=np.ones(n, bool) if valid is None else valid,
    )


# ---------------------------------------------------------------------------------
# Round trips
# ---------------------------------------------------------------------------------
@pytest.mark.parametrize("name", ["s.mha", "s.mhd"])
@pytest.mark.parametrize("compress", [False, True])
def test_write_read_round_trip(tmp_path, name, compress):
    valid = np.array([True, False, True, True, False, True])
    sweep = simple_sweep(valid=valid)
    out = write_sweep(sweep, tmp_path / name, compress=compress)
    back = read_sweep(out)
    assert np.array_equal(np.asarray(back.frames), sweep.frames)
    assert np.array_equal(back.image_to_reference[valid], sweep.image_to_reference[valid])
    assert np.array_equal(back.timestamps, sweep.timestamps)
    assert np.array_equal(back.valid, valid)
    assert set(back.invalid_reasons) == {1, 4}
    assert "ImageToReference status INVALID" in back.invalid_reasons[1]
    assert back.transform_name == "ImageToReference"
    expected = {"s.mha"} if name == "s.mha" else {"s.mhd", "s.zraw" if compress else "s.raw"}
    assert {p.name for p in tmp_path.iterdir()} == expected  # no temporary files left
    # SimpleITK, an independent reader, sees the same pixels and per-frame fields.
    img = sitk.ReadImage(str(out))
    assert np.array_equal(sitk.GetArrayFromImage(img), sweep.frames)
    keys = set(img.GetMetaDataKeys())
    for k in (
        "ImageToReferenceTransform",
        "ImageToReferenceTransformStatus",
        "Timestamp",
        "ImageStatus",
    ):
        assert f"Seq_Frame0005_{k}" in keys
    got = np.array(img.GetMetaData("Seq_Frame0002_ImageToReferenceTransform").split(), float)
    assert np.allclose(got.reshape(4, 4), sweep.image_to_reference[2], rtol=1e-5, atol=1e-4)


def test_uncompressed_read_is_memory_mapped(tmp_path):
    out = write_sweep(simple_sweep(), tmp_path / "s.mha")
    back = read_sweep(out)
    assert isinstance(back.frames, np.memmap)
    assert not back.frames.flags.writeable
    back_c = read_sweep(write_sweep(simple_sweep(), tmp_path / "c.mha", compress=True))
    assert not isinstance(back_c.frames, np.memmap)


def test_write_is_atomic_on_failure(tmp_path, monkeypatch):
    import BoneUSRecon.Logic.sequence_io as sio

    def boom(f, frames, compressed):
        f.write(b"partial")
        raise KeyboardInterrupt

    monkeypatch.setattr(sio, "_write_data", boom)
    for name in ("s.mha", "s.mhd"):
        with pytest.raises(KeyboardInterrupt):
            write_sweep(simple_sweep(), tmp_path / name)
    assert list(tmp_path.iterdir()) == []


def test_write_rejects_bad_output(tmp_path):
    with pytest.raises(BoneUSReconError, match="unknown output extension"):
        write_sweep(simple_sweep(), tmp_path / "s.nrrd")
    with pytest.raises(BoneUSReconError, match="does not exist"):
        write_sweep(simple_sweep(), tmp_path / "missing" / "s.mha")


def test_write_copes_with_memory_mapped_flipped_frames(tmp_path):
    make_file(tmp_path / "un.mha", orientation="UN")
    src = read_sweep(tmp_path / "un.mha")
    assert src.frames.strides[1] < 0 and src.frames.strides[2] < 0
    back = read_sweep(write_sweep(src, tmp_path / "copy.mha", compress=True))
    assert np.array_equal(back.frames, src.frames)


# ---------------------------------------------------------------------------------
# Pixel types, layouts, orientation
# ---------------------------------------------------------------------------------
@pytest.mark.parametrize(
    "dtype, values, expected",
    [
        (np.uint8, [0, 7, 255], [0, 7, 255]),
        (np.int8, [-128, 0, 127], [0, 128, 255]),  # signed: shifted by +128
        (np.int8, [0, 5, 127], [0, 5, 127]),  # already within 0..255: kept
        (np.uint16, [0, 17, 255], [0, 17, 255]),  # 8-bit data stored wide: kept
        (np.int16, [3, 100, 200], [3, 100, 200]),
        (np.float32, [0.0, 0.5, 1.0], [0, 128, 255]),  # normalised: x 255
        (np.float64, [0.0, 12.4, 250.0], [0, 12, 250]),  # 0..255 floats: rounded
    ],
)
def test_element_types_exact_mappings(tmp_path, dtype, values, expected):
    frames = np.resize(np.array(values, dtype=dtype), (N, H, W))
    ref = np.resize(np.array(expected, dtype=np.uint8), (N, H, W))
    path = make_file(tmp_path / "s.mha", frames)
    assert np.array_equal(read_sweep(path).frames, ref)


@pytest.mark.parametrize("dtype", [np.uint16, np.int16, np.float32, np.float64])
@pytest.mark.parametrize("compress", [False, True])
def test_element_types_wide_range_rescaled_like_simpleitk_reads(tmp_path, dtype, compress):
    """Files written by SimpleITK (an independent writer) in each type: the pixels we
    read are SimpleITK's pixels mapped linearly (percentiles to 0..255)."""
    rng = np.random.default_rng(5)
    lo, hi = (-3000, 4000) if np.dtype(dtype).kind in "if" else (0, 4000)
    vals = rng.uniform(lo, hi, (N, H, W))
    frames = vals.astype(dtype)
    img = sitk.GetImageFromArray(frames)
    for k in range(N):
        img.SetMetaData(f"Seq_Frame{k:04d}_ImageToReferenceTransform", mat_text(rigid(1)[k]))
    path = tmp_path / "s.mha"
    sitk.WriteImage(img, str(path), compress)
    back = read_sweep(path)
    truth = sitk.GetArrayFromImage(sitk.ReadImage(str(path))).astype(float)
    p_lo, p_hi = np.percentile(truth, [0.5, 99.5])
    ref = np.clip(np.rint((truth - p_lo) * 255 / (p_hi - p_lo)), 0, 255)
    assert back.frames.dtype == np.uint8
    assert np.abs(back.frames.astype(float) - ref).max() <= 1
    assert np.corrcoef(back.frames.ravel(), truth.ravel())[0, 1] > 0.99


@pytest.mark.parametrize("dtype", [np.uint16, np.int16, np.float32, np.float64])
def test_big_endian_data(tmp_path, dtype):
    frames = np.resize(np.array([0, 9, 200], dtype=dtype), (N, H, W))
    path = make_file(tmp_path / "s.mha", frames, msb=True)
    assert read_header(path).dtype.byteorder == ">"
    assert np.array_equal(read_sweep(path).frames, frames.astype(np.uint8))


def test_multichannel_uses_first_channel(tmp_path):
    grey = frames_u8()
    rgb = np.stack([grey, 255 - grey, grey // 2], axis=-1)
    path = make_file(tmp_path / "s.mha", rgb)
    assert np.array_equal(read_sweep(path).frames, grey)


@pytest.mark.parametrize("compress", [False, True])
def test_mhd_with_separate_data_file(tmp_path, compress):
    frames = frames_u8()
    fields = build_fields(frames, compressed=compress)
    data_name = "data.zraw" if compress else "data.raw"
    path = write_file(
        tmp_path / "s.mhd", fields, pixel_bytes(frames, compressed=compress), data_file=data_name
    )
    back = read_sweep(path)
    assert np.array_equal(np.asarray(back.frames), frames)
    assert back.metadata["data_file"].endswith(data_name)
    assert np.array_equal(sitk.GetArrayFromImage(sitk.ReadImage(str(path))), frames)


@pytest.mark.parametrize(
    "orientation, flip",
    [
        ("MF", ()),
        ("MN", (1,)),
        ("UF", (2,)),
        ("UN", (1, 2)),
        ("mn", (1,)),
        ("UFA", (2,)),
        (None, ()),
    ],
)
def test_orientation_converted_to_mf(tmp_path, orientation, flip):
    """PLUS (vtkPlusUsImageConverter): U flips image x (columns), N flips image y (rows);
    the transforms in the file refer to the MF image and are used unchanged."""
    mf = frames_u8()
    stored = np.flip(mf, axis=flip) if flip else mf
    poses = rigid(1)
    path = make_file(tmp_path / "s.mha", stored, orientation=orientation)
    back = read_sweep(path)
    assert np.array_equal(back.frames, mf)
    assert np.allclose(back.image_to_reference, poses)
    assert isinstance(back.frames, np.memmap)  # flips are views, not copies


def test_unknown_orientation(tmp_path):
    with pytest.raises(BoneUSReconError, match="UltrasoundImageOrientation"):
        read_sweep(make_file(tmp_path / "s.mha", orientation="XZ"))


# ---------------------------------------------------------------------------------
# Poses: chains, calibration, statuses
# ---------------------------------------------------------------------------------
def test_chain_with_calibration_xml(tmp_path):
    t = tracked_transforms()
    t["StylusToTracker"] = rigid(9)
    calib = image_to_probe()
    path = make_file(tmp_path / "s.mha", transforms=t)
    xml = write_xml(tmp_path / "config.xml", calib)
    # Logic messages speak of files, not CLI options (the Slicer module shows them too).
    with pytest.raises(
        BoneUSReconError, match=r"missing ImageToProbe.*calibration \(ImageToProbe\) file"
    ) as e:
        read_sweep(path)
    assert "--" not in str(e.value) and e.value.parameter == "calibration"
    s = read_sweep(path, calibration=xml)
    assert s.transform_name == "inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe"
    assert np.allclose(s.image_to_reference, expected_chain(t, calib), atol=1e-9)
    assert np.allclose(s.spacing_mm, SPACING)
    # Pixel (3, 4) by hand through the chain: rigid maps keep the 0.2 mm pixel size.
    p = np.linalg.solve(t["ReferenceToTracker"][0], t["ProbeToTracker"][0] @ calib @ [3, 4, 0, 1])
    assert np.allclose(s.to_reference(0, np.array([[3.0, 4.0]]))[0], p[:3])


def test_calibration_xml_reverse_transform_is_inverted(tmp_path):
    calib = image_to_probe()
    xml = write_xml(tmp_path / "c.xml", np.linalg.inv(calib), frm="Probe", to="Image")
    assert np.allclose(read_calibration(xml), calib)


@pytest.mark.parametrize("per_frame", [False, True])
def test_calibration_from_header_field(tmp_path, per_frame):
    t = tracked_transforms()
    calib = image_to_probe()
    if per_frame:
        tt = dict(t, ImageToProbe=np.tile(calib, (N, 1, 1)))
        path = make_file(tmp_path / "s.mha", transforms=tt)
    else:
        path = make_file(
            tmp_path / "s.mha",
            transforms=t,
            global_fields={"ImageToProbeTransform": mat_text(calib)},
        )
    s = read_sweep(path)
    assert np.allclose(s.image_to_reference, expected_chain(t, calib), atol=1e-9)
    # An explicit calibration file wins over the header's.
    other = calib.copy()
    other[:3, 3] += [1.0, 2.0, 3.0]
    s2 = read_sweep(path, calibration=write_xml(tmp_path / "c.xml", other))
    assert np.allclose(s2.image_to_reference, expected_chain(t, other), atol=1e-9)


def test_named_transforms(tmp_path):
    t = tracked_transforms()
    calib = image_to_probe()
    t["ImageToReference"] = expected_chain(t, calib)
    path = make_file(tmp_path / "s.mha", transforms=t)
    xml = write_xml(tmp_path / "c.xml", calib)
    assert np.allclose(read_sweep(path).image_to_reference, t["ImageToReference"])
    for name in ("ImageToTracker", "ImageToTrackerTransform", "ProbeToTracker"):
        s = read_sweep(path, calibration=xml, transform=name)
        assert np.allclose(s.image_to_reference, t["ProbeToTracker"] @ calib, atol=1e-9)
        assert s.transform_name == "ProbeToTracker * ImageToProbe"
    with pytest.raises(BoneUSReconError, match="no StylusToTracker transform"):
        read_sweep(path, calibration=xml, transform="StylusToTracker")
    with pytest.raises(BoneUSReconError, match="pose 'reference' is not a transform name") as e:
        read_sweep(path, transform="reference")
    assert "--" not in str(e.value) and e.value.parameter == "transform"
    with pytest.raises(BoneUSReconError, match="to itself") as e:
        read_sweep(path, transform="ImageToImage")
    assert e.value.parameter == "transform"
    with pytest.raises(BoneUSReconError, match="from Image to Patient"):
        read_sweep(path, calibration=xml, transform="ImageToPatient")


def test_missing_tracking_link_is_named(tmp_path):
    path = make_file(tmp_path / "s.mha", transforms={"ProbeToTracker": rigid(2)})
    with pytest.raises(BoneUSReconError, match="missing ReferenceToTracker, ImageToProbe") as e:
        read_sweep(path)
    # A calibration alone would not help here, so the message does not ask for one.
    assert "calibration" not in str(e.value) and e.value.parameter is None


def test_statuses_invalidate_frames(tmp_path):
    t = tracked_transforms()
    t["StylusToTracker"] = rigid(9)
    t["ReferenceToTracker"][4] = 0.0  # singular: cannot be inverted
    t["ProbeToTracker"][5, 0, 0] = np.nan
    statuses = {
        "ProbeToTracker": {1: "MISSING"},
        "ReferenceToTracker": {2: "OUT_OF_VIEW"},
        "StylusToTracker": {0: "MISSING", 3: "MISSING"},  # not in the chain: harmless
    }
    path = make_file(
        tmp_path / "s.mha", transforms=t, statuses=statuses, image_status={3: "INVALID"}
    )
    s = read_sweep(path, calibration=write_xml(tmp_path / "c.xml", image_to_probe()))
    assert s.valid.tolist() == [True, False, False, False, False, False]
    r = s.invalid_reasons
    assert r[1] == "ProbeToTracker status MISSING"
    assert r[2] == "ReferenceToTracker status OUT_OF_VIEW"
    assert r[3] == "ImageStatus INVALID"
    assert r[4] == "ReferenceToTracker is singular"
    assert "NaN" in r[5] and "ProbeToTracker" in r[5]
    assert np.all(np.isfinite(s.image_to_reference))


def test_missing_transform_in_some_frames(tmp_path):
    frames = frames_u8()
    fields = build_fields(frames)
    fields = [kv for kv in fields if kv[0] != "Seq_Frame0002_ImageToReferenceTransform"]
    s = read_sweep(write_file(tmp_path / "s.mha", fields, pixel_bytes(frames)))
    assert s.valid.tolist() == [True, True, False, True, True, True]
    assert s.invalid_reasons[2] == "ImageToReference missing"


def test_degenerate_pose_invalid(tmp_path):
    m = rigid(1)
    m[2, :3, 1] = m[2, :3, 0]  # image axes parallel: the plane collapses
    m[3, 3] = [0, 0, 1, 1]  # not affine
    s = read_sweep(make_file(tmp_path / "s.mha", transforms={"ImageToReference": m}))
    assert s.valid.tolist() == [True, True, False, False, True, True]
    assert "singular" in s.invalid_reasons[2] and "affine" in s.invalid_reasons[3]


def test_timestamps(tmp_path):
    ts = np.array([100.5, 100.6, 100.75, 101.0, 101.125, 102.0])
    s = read_sweep(make_file(tmp_path / "s.mha", timestamps=ts))
    assert np.array_equal(s.timestamps, ts)
    assert s.duration_s() == pytest.approx(1.5)


def test_frames_without_timestamps(tmp_path):
    frames = frames_u8()
    fields = [kv for kv in build_fields(frames) if not kv[0].endswith("_Timestamp")]
    s = read_sweep(write_file(tmp_path / "s.mha", fields, pixel_bytes(frames)))
    assert np.array_equal(s.timestamps, np.zeros(N)) and s.duration_s() == 0.0


def test_progress_callback(tmp_path):
    calls = []
    read_sweep(make_file(tmp_path / "s.mha"), progress=lambda *a: calls.append(a))
    assert calls[-1] == ("read", 2, 2)


# ---------------------------------------------------------------------------------
# The shared real recording
# ---------------------------------------------------------------------------------
# Frame 0 of BoneUltrasound_L14.igs.mha and the calibration of its config XML,
# copied from the files by hand.
REAL_PROBE0 = np.array(
    [
        [0.853646, -0.501315, 0.141319, 257.956],
        [-0.50173, -0.718613, 0.481521, -52.6852],
        [-0.13984, -0.481953, -0.864966, 25.5612],
        [0, 0, 0, 1],
    ]
)
REAL_REF0 = np.array(
    [
        [-0.61495, 0.0616122, -0.786156, 307.759],
        [-0.148385, -0.988175, 0.0386253, -88.1807],
        [-0.77448, 0.140406, 0.61682, -54.9176],
        [0, 0, 0, 1],
    ]
)
REAL_CALIB = np.array(
    [
        [0.000796231, 0.0854272, 0.000850194, 12.74],
        [-0.0853999, 0.000772721, 0.00233653, 50.76],
        [0.00232863, -0.000871617, 0.0853992, -0.5],
        [0, 0, 0, 1],
    ]
)


def test_real_recording():
    s = read_sweep(REAL_MHA, calibration=REAL_XML)
    assert (s.n_frames, s.width, s.height, s.n_valid) == (21, 820, 616, 21)
    assert np.allclose(s.spacing_mm, 0.085, atol=0.001)
    assert s.transform_name == "inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe"
    assert np.allclose(read_calibration(REAL_XML), REAL_CALIB)
    # Frame 0 pose by hand: pixel (410, 300) -> Probe -> Tracker -> Reference.
    ij = np.array([410.0, 300.0, 0.0, 1.0])
    in_probe = REAL_CALIB @ ij
    in_tracker = REAL_PROBE0 @ in_probe
    in_ref = np.linalg.solve(REAL_REF0, in_tracker)
    assert np.allclose(s.to_reference(0, ij[None, :2])[0], in_ref[:3], atol=1e-6)
    # Bounds of all image corners; each frame's corners sit 70 mm x 52.6 mm apart.
    b = s.bounds_mm()
    assert np.all(b[1::2] > b[::2])
    c = s.corners_mm()
    assert np.allclose(np.linalg.norm(c[:, 1] - c[:, 0], axis=1), 819 * 0.08544, atol=0.05)
    assert np.allclose(np.linalg.norm(c[:, 3] - c[:, 0], axis=1), 615 * 0.08544, atol=0.05)
    assert np.all(b[::2] <= c.reshape(-1, 3).min(0) + 1e-9)
    assert s.timestamps[0] == pytest.approx(232.542071)
    assert s.duration_s() == pytest.approx(234.2611 - 232.542071, abs=1e-5)
    # Pixels agree with SimpleITK.
    truth = sitk.GetArrayFromImage(sitk.ReadImage(str(REAL_MHA)))
    assert np.array_equal(s.frames, truth)


def test_real_recording_all_poses_match_simpleitk_metadata():
    """Every frame's pose, recomposed from the fields as SimpleITK reads them."""
    s = read_sweep(REAL_MHA, calibration=REAL_XML)
    reader = sitk.ImageFileReader()
    reader.SetFileName(str(REAL_MHA))
    reader.ReadImageInformation()

    def field(k, name):
        return np.array(reader.GetMetaData(f"Seq_Frame{k:04d}_{name}").split(), float).reshape(4, 4)

    for k in range(21):
        ref = np.linalg.inv(field(k, "ReferenceToTrackerTransform"))
        expected = ref @ field(k, "ProbeToTrackerTransform") @ REAL_CALIB
        assert np.allclose(s.image_to_reference[k], expected, atol=1e-9)
        assert s.timestamps[k] == float(reader.GetMetaData(f"Seq_Frame{k:04d}_Timestamp"))


def test_real_recording_round_trip(tmp_path):
    s = read_sweep(REAL_MHA, calibration=REAL_XML)
    back = read_sweep(write_sweep(s, tmp_path / "real.mha", compress=True))
    assert np.array_equal(back.frames, s.frames)
    assert np.array_equal(back.image_to_reference, s.image_to_reference)
    assert np.array_equal(back.timestamps, s.timestamps)


# ---------------------------------------------------------------------------------
# Bad input: one clear error naming the file (the CLI side is in test_cli_info.py)
# ---------------------------------------------------------------------------------
def _bad_cases(tmp: Path) -> dict[str, tuple[Path, dict, str]]:
    """name -> (path, read_sweep kwargs, regex the message must match)."""
    frames = frames_u8()
    good = build_fields(frames)
    data = pixel_bytes(frames)
    cases: dict[str, tuple[Path, dict, str]] = {}

    def add(name, fields, payload, match, **kw):
        cases[name] = (write_file(tmp / f"{name}.mha", fields, payload), kw, match)

    cases["missing file"] = (tmp / "nope.mha", {}, "no such file")
    (tmp / "empty.mha").write_bytes(b"")
    cases["empty file"] = (tmp / "empty.mha", {}, "file is empty")
    (tmp / "png.mha").write_bytes(b"\x89PNG\r\n\x1a\n" + bytes(range(256)) * 4)
    cases["not a metafile (binary)"] = (tmp / "png.mha", {}, "not a MetaIO metafile")
    (tmp / "text.mha").write_text("hello world\nthis is not a header\n")
    cases["not a metafile (text)"] = (tmp / "text.mha", {}, "not a MetaIO metafile")
    add("truncated data", good, data[:-100], "truncated data")
    add(
        "dimsize too small",
        set_field(good, "DimSize", f"{W} {H} {N - 1}"),
        data,
        "disagrees with the data",
    )
    add("no ElementDataFile", good[:-1], b"", "no ElementDataFile")
    add(
        "unknown ElementType",
        set_field(good, "ElementType", "MET_LONG_LONG"),
        data,
        "unknown ElementType",
    )
    add("no ElementType", set_field(good, "ElementType", None), data, "no ElementType")
    zgood = build_fields(frames, compressed=True)
    zdata = bytearray(zlib.compress(data))
    zdata[40:60] = b"\xff" * 20
    add("corrupt zlib", zgood, bytes(zdata), r"corrupt compressed \(zlib\) data")
    add("truncated zlib", zgood, zlib.compress(data)[:-50], "truncated compressed data")
    add(
        "zlib dimsize",
        set_field(zgood, "DimSize", f"{W} {H} {N + 2}"),
        zlib.compress(data),
        "disagrees with the data",
    )
    add(
        "non-numeric transform",
        set_field(
            good, "Seq_Frame0003_ImageToReferenceTransform", "1 0 0 0 0 1 0 x 0 0 1 0 0 0 0 1"
        ),
        data,
        "Seq_Frame0003_ImageToReferenceTransform: non-numeric",
    )
    add(
        "transform wrong count",
        set_field(good, "Seq_Frame0001_ImageToReferenceTransform", "1 0 0 0 0 1 0 0 0 0 1 0"),
        data,
        "Seq_Frame0001_ImageToReferenceTransform: expected 16 numbers, got 12",
    )
    add(
        "no usable transform",
        build_fields(frames, transforms={"StylusToTracker": rigid(3)}),
        data,
        "no usable transform.*missing ReferenceToTracker, ProbeToTracker, ImageToProbe",
    )
    add(
        "every frame invalid",
        build_fields(frames, statuses={"ImageToReference": {k: "INVALID" for k in range(N)}}),
        data,
        r"every frame is invalid \(6 of 6; frame 0: ImageToReference status INVALID\)",
    )
    nan = np.full((N, 4, 4), np.nan)
    add(
        "NaN transforms",
        build_fields(frames, transforms={"ImageToReference": nan}),
        data,
        "every frame is invalid.*NaN",
    )
    add(
        "singular transforms",
        build_fields(frames, transforms={"ImageToReference": np.zeros((N, 4, 4))}),
        data,
        "every frame is invalid.*affine|every frame is invalid.*singular",
    )
    add("zero frames", set_field(good, "DimSize", f"{W} {H} 0"), b"", "zero frames")
    two_d = set_field(set_field(good, "NDims", "2"), "DimSize", f"{W} {H}")
    add("2D image", two_d, frames[0].tobytes(), r"single 2D image \(NDims = 2\)")
    add("bad DimSize", set_field(good, "DimSize", "14 ten 6"), data, "DimSize must be integers")
    add(
        "bad timestamp",
        set_field(good, "Seq_Frame0002_Timestamp", "noon"),
        data,
        "Seq_Frame0002_Timestamp: not a number",
    )
    mhd_missing = set_field(good, "ElementDataFile", "gone.raw")
    cases["missing data file"] = (
        write_file(tmp / "nodata.mhd", mhd_missing, b""),
        {},
        "data file 'gone.raw' named by ElementDataFile not found",
    )
    cases["missing calibration file"] = (
        write_file(
            tmp / "tracked.mha", build_fields(frames, transforms=tracked_transforms()), data
        ),
        {"calibration": tmp / "nope.xml"},
        "nope.xml: no such file",
    )
    (tmp / "broken.xml").write_text("<PlusConfiguration><CoordinateDefinitions>")
    cases["broken calibration xml"] = (
        tmp / "tracked.mha",
        {"calibration": tmp / "broken.xml"},
        "broken.xml: not a valid XML file",
    )
    write_xml(tmp / "other.xml", np.eye(4), frm="Stylus", to="StylusTip")
    cases["calibration without ImageToProbe"] = (
        tmp / "tracked.mha",
        {"calibration": tmp / "other.xml"},
        'other.xml: no <Transform From="Image" To="Probe">',
    )
    return cases


BAD_NAMES = [
    "missing file",
    "empty file",
    "not a metafile (binary)",
    "not a metafile (text)",
    "truncated data",
    "dimsize too small",
    "no ElementDataFile",
    "unknown ElementType",
    "no ElementType",
    "corrupt zlib",
    "truncated zlib",
    "zlib dimsize",
    "non-numeric transform",
    "transform wrong count",
    "no usable transform",
    "every frame invalid",
    "NaN transforms",
    "singular transforms",
    "zero frames",
    "2D image",
    "bad DimSize",
    "bad timestamp",
    "missing data file",
    "missing calibration file",
    "broken calibration xml",
    "calibration without ImageToProbe",
]


def bad_case(tmp_path: Path, name: str) -> tuple[Path, dict, str]:
    """Build all bad-input files in ``tmp_path`` and return the one called ``name``."""
    return _bad_cases(tmp_path)[name]


def test_bad_case_list_is_complete(tmp_path):
    assert sorted(_bad_cases(tmp_path)) == sorted(BAD_NAMES)


@pytest.mark.parametrize("name", BAD_NAMES)
def test_bad_input_raises_clear_error(tmp_path, name):
    path, kw, match = bad_case(tmp_path, name)
    with pytest.raises(BoneUSReconError, match=match) as exc:
        read_sweep(path, **kw)
    msg = str(exc.value)
    assert "\n" not in msg
    named = kw.get("calibration") if "calibration" in name else path
    assert msg.startswith(f"{os.fspath(named)}: ") or msg.startswith(os.fspath(path))


# ---------------------------------------------------------------------------------
# Memory: big sweeps are mapped, not loaded (benchmark: benchmarks/bench_io.py)
# ---------------------------------------------------------------------------------
def _big_sweep_file(tmp_path: Path, n: int = 200, h: int = 400, w: int = 400) -> Path:
    frame = np.random.default_rng(0).integers(0, 256, (h, w), dtype=np.uint8)
    m = np.tile(np.diag([0.1, 0.1, 1.0, 1.0]), (n, 1, 1))
    m[:, 2, 3] = np.arange(n) * 0.2
    sweep = Sweep(np.broadcast_to(frame, (n, h, w)), m, np.arange(n) / 30.0, np.ones(n, bool))
    return write_sweep(sweep, tmp_path / "big.mha")


def test_read_allocates_far_less_than_the_data(tmp_path):
    import tracemalloc

    path = _big_sweep_file(tmp_path)  # 32 MB of pixels
    tracemalloc.start()
    try:
        s = read_sweep(path)
        _, peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert s.frames.nbytes == 200 * 400 * 400
    assert peak < 2 * 2**20, f"read_sweep allocated {peak / 2**20:.1f} MB"


def _rss_file_kb() -> int:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("RssFile:"):
            return int(line.split()[1])
    raise AssertionError("no RssFile")


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="needs Linux /proc")
def test_iter_frames_releases_mapped_pages(tmp_path):
    path = _big_sweep_file(tmp_path)
    s = read_sweep(path)
    before = _rss_file_kb()
    total = sum(int(f[::7, ::7].sum()) for _, f in s.iter_frames())
    grown_iter = _rss_file_kb() - before
    s2 = read_sweep(path)
    before = _rss_file_kb()
    total2 = sum(int(np.asarray(s2.frames[k])[::7, ::7].sum()) for k in range(s2.n_frames))
    grown_index = _rss_file_kb() - before
    assert total == total2
    # Plain indexing keeps every touched page mapped (~31 MB); iter_frames does not.
    assert grown_index > 20_000, grown_index
    assert grown_iter < 10_000, grown_iter


def test_crlf_header_and_header_size(tmp_path):
    frames = frames_u8()
    fields = build_fields(frames)
    text = "".join(f"{k} = {v}\r\n" for k, v in fields)
    (tmp_path / "crlf.mha").write_bytes(text.encode() + pixel_bytes(frames))
    assert np.array_equal(read_sweep(tmp_path / "crlf.mha").frames, frames)
    # .mhd whose data file starts with a 100-byte preamble skipped by HeaderSize.
    fields = set_field(fields, "ElementDataFile", None) + [
        ["HeaderSize", "100"],
        ["ElementDataFile", "d.raw"],
    ]
    path = write_file(tmp_path / "h.mhd", fields, b"")
    (tmp_path / "d.raw").write_bytes(b"\0" * 100 + pixel_bytes(frames))
    assert np.array_equal(read_sweep(path).frames, frames)
    fields = [kv if kv[0] != "HeaderSize" else ["HeaderSize", "-1"] for kv in fields]
    path = write_file(tmp_path / "h2.mhd", fields, b"")
    assert np.array_equal(read_sweep(path).frames, frames)  # -1: data at the end


# ---------------------------------------------------------------------------------
# Intensity mapping details
# ---------------------------------------------------------------------------------
def test_to_uint8_nan_and_chunking(monkeypatch):
    import BoneUSRecon.Logic.intensity as inten

    rng = np.random.default_rng(3)
    a = rng.normal(1000, 300, (12, 20, 30)).astype(np.float32)
    a[0, 0, 0] = np.nan
    whole = inten.to_uint8(a)
    monkeypatch.setattr(inten, "_CHUNK_BYTES", 1)  # one frame per chunk
    assert np.array_equal(inten.to_uint8(a), whole)
    assert whole[0, 0, 0] == 0
    lo, hi = np.percentile(a[np.isfinite(a)], [0.5, 99.5])
    ref = np.clip(np.rint((a - lo) * 255 / (hi - lo)), 0, 255)
    finite = np.isfinite(a)
    assert np.abs(whole[finite].astype(float) - ref[finite]).max() <= 1
    assert np.array_equal(inten.to_uint8(np.full((2, 3, 4), np.nan)), np.zeros((2, 3, 4), np.uint8))
    assert np.array_equal(
        inten.to_uint8(np.full((2, 3), 7000, np.uint16)), np.zeros((2, 3), np.uint8)
    )

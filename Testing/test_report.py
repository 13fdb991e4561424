"""The HTML report: real pictures, the numbers of ``evaluate``, atomic folder, a browser.

Most tests use a small analytic stand-in for a reconstruction (a half-cylinder bone
imaged by a 30-frame sweep with known tilt and spacing), so the ground truth of every
number on the page is known in millimetres and degrees; ``test_demo.py`` covers the
report of the real pipeline.
"""

from __future__ import annotations

import base64
import io
import json
import os
import re
import shutil
import subprocess
from pathlib import Path
from types import SimpleNamespace

import numpy as np
import pytest
from PIL import Image

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.segmentation import FrameContour, SegmentationParams, SegmentationResult
from BoneUSRecon.Logic.sweep import Sweep
from BoneUSRecon.Logic.vtkio import points_to_polydata
from BoneUSRecon.Widgets import report as rep

R_MM = 8.0  # bone radius
Z_AXIS = -20.0  # bone axis depth below the probe face
GAP_MM = 1.5  # distance between frames along the bone
TILT_DEG = 1.0  # each frame is tilted by this much more than the previous one (about y)
N, H, W, S = 30, 96, 128, 0.25  # frames, rows, columns, mm per pixel


def _rot_y(deg: float) -> np.ndarray:
    a = np.radians(deg)
    return np.array([[np.cos(a), 0, np.sin(a)], [0, 1, 0], [-np.sin(a), 0, np.cos(a)]])


def _standin(rejected: tuple[int, ...] = (4, 17), invalid: int = 25) -> SimpleNamespace:
    """A reconstruction-shaped object with exactly known geometry."""
    import pyvista as pv
    from scipy.spatial import cKDTree

    rng = np.random.default_rng(0)
    mats = np.zeros((N, 4, 4))
    for k in range(N):
        # Column i -> +y (lateral), row j -> -z (depth); frame k tilted by k*TILT about y,
        # rotating about the image centre so that centres stay GAP_MM apart along x.
        rot = _rot_y(k * TILT_DEG - N * TILT_DEG / 2)
        lin = rot @ np.array([[0, 0], [S, 0], [0, -S]])
        centre_px = np.array([(W - 1) / 2, (H - 1) / 2])
        centre_mm = np.array([k * GAP_MM, 0.0, -(H - 1) / 2 * S])
        mats[k, :3, :2] = lin
        mats[k, :3, 2] = rot[:, 0]
        mats[k, :3, 3] = centre_mm - lin @ centre_px
        mats[k, 3, 3] = 1
    frames = rng.integers(0, 50, (N, H, W), dtype=np.uint8)
    valid = np.ones(N, bool)
    valid[invalid] = False
    contours = []
    i = np.arange(W, dtype=float)
    for k in range(N):
        if not valid[k]:
            continue
        y = (i - (W - 1) / 2) * S
        keep = np.abs(y) < 0.9 * R_MM
        # Approximate row of the bone top (frames are nearly perpendicular to x).
        j = (-Z_AXIS - np.sqrt(R_MM**2 - y[keep] ** 2)) / S
        ij = np.column_stack([i[keep], j])
        frames[k, np.round(j).astype(int), i[keep].astype(int)] = 230
        ok = k not in rejected
        contours.append(
            FrameContour(
                k,
                ij,
                np.full(len(ij), 230.0),
                0.9 if ok else 0.1,
                ok,
                "" if ok else "no acoustic shadow below the contour: score 0.12",
            )
        )
    sweep = Sweep(
        frames=frames,
        image_to_reference=mats,
        timestamps=np.arange(N) * 0.05,
        valid=valid,
        invalid_reasons={invalid: "ProbeToTracker status MISSING"},
    )
    seg = SegmentationResult(tuple(contours), "standin", SegmentationParams())
    pts = np.concatenate([c.points_mm(sweep) for c in seg.accepted])
    x = np.linspace(-2, N * GAP_MM, 80)
    th = np.linspace(-1.3, 1.3, 60)
    X, T = np.meshgrid(x, th, indexing="ij")
    grid = pv.StructuredGrid(X, R_MM * np.sin(T), Z_AXIS + R_MM * np.cos(T))
    surface = grid.extract_surface(algorithm="dataset_surface").triangulate()
    surface.point_data["Distance"] = cKDTree(pts).query(np.asarray(surface.points))[0]
    return SimpleNamespace(
        sweep=sweep,
        segmentation=seg,
        surface=surface,
        points=points_to_polydata(pts, {"Frame": np.zeros(len(pts))}),
        summary={"frames_used": len(seg.accepted), "fit_rms_mm": 0.1},
        timings={"segmentation": 1.0, "fit": 0.2},
    )


def _gold(n: int = 400) -> tuple[np.ndarray, np.ndarray]:
    """Gold points at known radial offsets (mm) outside the cylinder."""
    rng = np.random.default_rng(1)
    x = rng.uniform(5, 35, n)
    th = rng.uniform(-1.0, 1.0, n)
    off = rng.uniform(0.0, 1.5, n)
    r = R_MM + off
    return np.column_stack([x, r * np.sin(th), Z_AXIS + r * np.cos(th)]), off


@pytest.fixture(scope="module")
def standin() -> SimpleNamespace:
    return _standin()


@pytest.fixture(scope="module")
def written(standin: SimpleNamespace, tmp_path_factory: pytest.TempPathFactory):
    gold, offsets = _gold()
    out = tmp_path_factory.mktemp("rep") / "report"
    steps: list[tuple[str, int, int]] = []
    index = rep.write_report(
        standin,
        out,
        gold=gold,
        table=[(5, 1.4), (10, 1.1), (15, 1.0), (20, 0.95)],
        parameters={"fit": {"control_points": [15, 5]}},
        progress=lambda *a: steps.append(a),
    )
    return SimpleNamespace(index=index, out=out, gold=gold, offsets=offsets, steps=steps)


def _images(page: str) -> dict[str, np.ndarray]:
    out = {}
    for name, b64 in re.findall(
        r'<img id="img-([^"]+)"[^>]*src="data:image/png;base64,([^"]+)"', page
    ):
        out[name] = np.asarray(Image.open(io.BytesIO(base64.b64decode(b64))).convert("RGB"))
    return out


def _is_picture(img: np.ndarray, min_colours: int = 8, min_std: float = 10.0) -> bool:
    packed = (
        (img[..., 0].astype(np.int32) << 16) | (img[..., 1].astype(np.int32) << 8) | img[..., 2]
    )
    return float(img.std()) > min_std and np.unique(packed).size >= min_colours


def test_page_holds_every_section_as_real_pictures(written: SimpleNamespace) -> None:
    page = written.index.read_text(encoding="utf-8")
    assert written.index == written.out / "index.html"
    imgs = _images(page)
    assert {
        "surface-top",
        "surface-oblique",
        "histogram",
        "table-i",
        "gold-errors",
        "sweep",
    } <= set(imgs)
    # The sweep picture outlines invalid frame 25 in orange.
    sw = imgs["sweep"].astype(int)
    assert ((np.abs(sw - [0xFF, 0x95, 0x00]).max(axis=2)) < 40).sum() > 20
    frames = sorted(k for k in imgs if k.startswith("frame-"))
    # Rejected frames 4 and 17 are shown among the sample, and marked as such.
    assert "frame-0004" in frames and "frame-0017" in frames and len(frames) >= 6
    assert page.count('class="rejected"') == 2
    for name, img in imgs.items():
        assert _is_picture(img), name
    # The surface pictures are coloured by Distance (viridis), with red points.
    top = imgs["surface-top"].astype(int)
    assert ((top[..., 0] > 200) & (top[..., 1] < 100) & (top[..., 2] < 100)).sum() > 50
    assert (top[..., 2] > top[..., 0] + 40).sum() > 1000  # the blue/purple end of viridis
    assert not np.array_equal(imgs["surface-top"], imgs["surface-oblique"])
    # Gold offsets run 0 to 1.5 mm: the error map shows both ends of coolwarm.
    err = imgs["gold-errors"].astype(int)
    assert ((err[..., 2] > 150) & (err[..., 0] < 120)).sum() > 30  # blue: near
    assert ((err[..., 0] > 150) & (err[..., 2] < 90)).sum() > 30  # red: far
    # The same pictures are beside the page as files, byte for byte decodable.
    files = sorted(p.stem for p in (written.out / "figures").glob("*.png"))
    assert len(files) == len(imgs)
    for sec in (
        "sweep-section",
        "surface-section",
        "accuracy-section",
        "table-section",
        "overlay-section",
        "parameters-section",
        "versions-section",
    ):
        assert f'id="{sec}"' in page
    assert "control_points" in page and "vtk" in page and "numpy" in page
    assert written.steps[-1][1] == written.steps[-1][2]


def test_accuracy_numbers_are_those_of_evaluate_surface(
    written: SimpleNamespace, standin: SimpleNamespace
) -> None:
    page = written.index.read_text(encoding="utf-8")
    ev = evaluate_surface(standin.surface, written.gold)
    shown = {k: float(v) for k, v in re.findall(r'data-key="([^"]+)" data-value="([^"]+)"', page)}
    expected = ev.as_dict()
    assert set(shown) == set(expected)
    for k, v in expected.items():
        assert shown[k] == pytest.approx(v, rel=1e-12), k
    # ... and those are the true distances of the gold points (known offsets, mm):
    # the mesh is a chord approximation of the cylinder, off by < 0.02 mm.
    assert ev.mean == pytest.approx(written.offsets.mean(), abs=0.02)
    assert ev.max == pytest.approx(written.offsets.max(), abs=0.02)
    assert re.search(rf'id="headline-mean">{ev.mean:.2f} mm', page)
    assert f"{100 * ev.within_1:.1f} %" in page
    data = json.loads((written.out / "report.json").read_text())
    assert data["evaluation"]["mean_mm"] == pytest.approx(ev.mean, rel=1e-12)
    assert [r["mean_mm"] for r in data["table_i"]] == [1.4, 1.1, 1.0, 0.95]


def test_sweep_summary_matches_the_known_geometry(standin: SimpleNamespace) -> None:
    s = rep.sweep_summary(standin.sweep, standin.segmentation)
    assert s["frames"] == N and s["valid_frames"] == N - 1
    assert s["invalid_reasons"] == {"ProbeToTracker status MISSING": 1}
    assert s["frames_used"] == N - 1 - 2 and s["frames_rejected"] == 2
    assert s["rejected_reasons"] == {"no acoustic shadow below the contour": 2}
    assert s["spacing_mm"] == pytest.approx([S, S])
    # Consecutive valid frames: 1.5 mm and 1 degree apart, except across the invalid
    # frame 25 (3 mm, 2 degrees).
    assert s["slice_gap_mm"]["median"] == pytest.approx(GAP_MM, abs=1e-9)
    assert s["slice_gap_mm"]["max"] == pytest.approx(2 * GAP_MM, abs=1e-9)
    assert s["slice_tilt_deg"]["min"] == pytest.approx(TILT_DEG, abs=1e-6)
    assert s["slice_tilt_deg"]["max"] == pytest.approx(2 * TILT_DEG, abs=1e-6)
    # Frames span -15..+14 degrees; the mean plane sits near the middle.
    assert s["tilt_range_deg"] == pytest.approx(14.5, abs=0.6)
    assert s["sweep_length_mm"] == pytest.approx(standin.sweep.sweep_length_mm())
    assert s["sweep_length_mm"] == pytest.approx(GAP_MM * (N - 1), abs=1e-6)


def test_sweep_numbers_on_the_page(written: SimpleNamespace, standin: SimpleNamespace) -> None:
    page = written.index.read_text(encoding="utf-8")
    assert re.search(r'id="frames-used">27<', page)
    assert re.search(r'id="frames-rejected">2<', page)
    assert f'id="sweep-length">{GAP_MM * (N - 1):.1f}<' in page
    assert "1.00 to 2.00 deg" in page


def test_report_folder_is_replaced_atomically(
    tmp_path: Path, standin: SimpleNamespace, monkeypatch: pytest.MonkeyPatch
) -> None:
    out = tmp_path / "r"
    first = rep.write_report(standin, out)
    assert (out / rep.REPORT_MARKER).exists() and "accuracy-section" not in first.read_text()
    before = first.read_text()

    # A failure part-way leaves the previous report untouched and no temporary folder.
    def boom() -> dict:
        raise KeyboardInterrupt

    monkeypatch.setattr(rep, "software_versions", boom)
    with pytest.raises(KeyboardInterrupt):
        rep.write_report(standin, out, gold=_gold(50)[0])
    assert first.read_text() == before
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]
    monkeypatch.undo()

    # A second report replaces the first.
    second = rep.write_report(standin, out, gold=_gold(50)[0])
    assert "accuracy-section" in second.read_text()
    assert sorted(p.name for p in tmp_path.iterdir()) == ["r"]


def test_refuses_folders_that_are_not_reports(tmp_path: Path, standin: SimpleNamespace) -> None:
    foreign = tmp_path / "mine"
    foreign.mkdir()
    (foreign / "thesis.tex").write_text("precious")
    with pytest.raises(BoneUSReconError, match="not a BoneUSRecon report"):
        rep.write_report(standin, foreign)
    assert (foreign / "thesis.tex").read_text() == "precious"
    a_file = tmp_path / "file"
    a_file.write_text("x")
    with pytest.raises(BoneUSReconError, match="not a folder"):
        rep.write_report(standin, a_file)
    with pytest.raises(BoneUSReconError, match="does not exist"):
        rep.write_report(standin, tmp_path / "no" / "such")
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file", "mine"]


def test_sample_frames_spread_and_include_rejected(standin: SimpleNamespace) -> None:
    frames = rep.sample_frames(standin.segmentation, n_accepted=5, n_rejected=4)
    assert 4 in frames and 17 in frames
    accepted = [f for f in frames if f not in (4, 17)]
    assert len(accepted) == 5 and accepted[0] == 0 and accepted[-1] == N - 1
    assert frames == sorted(frames)


def _chromium() -> str | None:
    if os.environ.get("BONEUSRECON_NO_CHROMIUM") == "1":
        return None
    return shutil.which("chromium") or shutil.which("chromium-browser")


@pytest.mark.skipif(_chromium() is None, reason="chromium is not installed")
def test_page_renders_in_a_headless_browser(written: SimpleNamespace, tmp_path: Path) -> None:
    shot = tmp_path / "page.png"
    cmd = [
        _chromium(),
        "--headless",
        "--no-sandbox",
        "--disable-gpu",
        "--disable-quic",
        "--no-first-run",
        "--disable-background-networking",
        "--disable-component-update",
        "--disable-sync",
        f"--user-data-dir={tmp_path / 'profile'}",
        f"--screenshot={shot}",
        "--window-size=1200,3000",
        written.index.as_uri(),
    ]
    subprocess.run(cmd, check=True, capture_output=True, timeout=60)
    img = np.asarray(Image.open(shot).convert("RGB")).astype(int)
    assert img.shape[:2] == (3000, 1200)
    assert _is_picture(img.astype(np.uint8), min_colours=100)
    # The embedded pictures were decoded by the browser: the page holds many strongly
    # coloured pixels (colour map, histogram bars), which text alone would not give.
    sat = img.max(axis=2) - img.min(axis=2)
    assert (sat > 80).mean() > 0.02
    # Text is there too (dark pixels on white), not a browser error page.
    assert (img.max(axis=2) < 60).mean() > 0.002

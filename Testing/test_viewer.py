"""The viewer (``show_surface`` / ``bone-us-recon view``), through its off-screen screenshot."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.sweep import Sweep
from BoneUSRecon.Logic.vtkio import write_points_csv, write_polydata
from BoneUSRecon.Widgets import render
from BoneUSRecon.Widgets.viewer import show_surface, with_distance

R_MM, Z_AXIS, LENGTH = 8.0, -20.0, 40.0


def _surface(distance: bool = True):
    import pyvista as pv

    x = np.linspace(0, LENGTH, 50)
    th = np.linspace(-1.2, 1.2, 30)
    X, T = np.meshgrid(x, th, indexing="ij")
    grid = pv.StructuredGrid(X, R_MM * np.sin(T), Z_AXIS + R_MM * np.cos(T))
    mesh = grid.extract_surface(algorithm="dataset_surface").triangulate()
    if distance:
        mesh.point_data["Distance"] = np.abs(np.sin(np.asarray(mesh.points)[:, 0] / 6.0)) * 2.0
    return mesh


def _points(n: int = 300, lift: float = 0.0, seed: int = 0) -> np.ndarray:
    rng = np.random.default_rng(seed)
    x, th = rng.uniform(0, LENGTH, n), rng.uniform(-1.1, 1.1, n)
    r = R_MM + lift
    return np.column_stack([x, r * np.sin(th), Z_AXIS + r * np.cos(th)])


def _sweep(n: int = 20, invalid: int = 7) -> Sweep:
    s = 0.3
    mats = np.zeros((n, 4, 4))
    for k in range(n):
        mats[k] = [[0, 0, 1, k * 2.0], [s, 0, 0, -64 * s / 2], [0, -s, 0, 0.0], [0, 0, 0, 1]]
    valid = np.ones(n, bool)
    valid[invalid] = False
    return Sweep(
        frames=np.zeros((n, 100, 64), np.uint8),
        image_to_reference=mats,
        timestamps=np.arange(n) * 0.1,
        valid=valid,
    )


def _load(path: Path) -> np.ndarray:
    return np.asarray(Image.open(path).convert("RGB")).astype(int)


def _count(img: np.ndarray, rgb: tuple[int, int, int], tol: int = 40) -> int:
    return int((np.abs(img - np.array(rgb)).max(axis=2) <= tol).sum())


RED = (0xFF, 0x3B, 0x30)
ORANGE = (0xFF, 0x95, 0x00)


def test_screenshot_shows_the_surface_points_and_frames(tmp_path: Path) -> None:
    out = tmp_path / "all.png"
    got = show_surface(
        _surface(),
        points=_points(),
        gold=_points(60, 0.5, 1),
        sweep=_sweep(),
        screenshot=out,
        window_size=(800, 500),
    )
    assert got == out
    img = _load(out)
    assert img.shape == (500, 800, 3)
    assert img.std() > 20 and np.unique(img.reshape(-1, 3), axis=0).shape[0] > 200
    assert _count(img, RED) > 100  # segmented points (and their legend entry)
    assert _count(img, ORANGE, 30) > 50  # the outline of invalid frame 7
    assert _count(img, (0, 0, 0), 20) > 100  # gold points and the scalar bar's text

    bare = tmp_path / "bare.png"
    show_surface(_surface(), screenshot=bare, window_size=(800, 500))
    img2 = _load(bare)
    assert _count(img2, RED) < 5 and _count(img2, ORANGE, 30) < 5
    # Coloured by Distance: many distinct viridis colours across the surface.
    sat = img2.max(axis=2) - img2.min(axis=2)
    assert (sat > 60).mean() > 0.05

    # A surface from elsewhere, without Distance and without points: plain colour, no
    # scalar bar, still a picture.
    plain = tmp_path / "plain.png"
    show_surface(_surface(distance=False), screenshot=plain, window_size=(800, 500))
    img3 = _load(plain)
    assert img3.std() > 10
    sat3 = img3.max(axis=2) - img3.min(axis=2)
    assert (sat3 > 60).mean() < 0.005 < ((img3.sum(axis=2) < 600).mean())


def test_window_toggles_layers_and_picking_reports_distances() -> None:
    from BoneUSRecon.Widgets.viewer import _add_interaction

    mesh = _surface()
    gold = _points(50, 0.7, 3)
    pl, actors = render.make_plotter(
        mesh, points=_points(), gold=gold, sweep=_sweep(), off_screen=True, window_size=(400, 300)
    )
    try:
        cb = _add_interaction(pl, mesh, actors, gold, render.DEFAULT_STYLE)
        assert {
            "toggle:points",
            "toggle:gold",
            "toggle:frames",
            "toggle:invalid_frames",
            "pick",
        } <= set(cb)
        cb["toggle:gold"](False)
        assert not actors["gold"].GetVisibility() and actors["points"].GetVisibility()
        cb["toggle:gold"](True)
        assert actors["gold"].GetVisibility()
        k = 123
        v = np.asarray(mesh.points)[k]
        text = cb["pick"](v)
        d = float(mesh.point_data["Distance"][k])
        assert f"{d:.2f} mm" in text
        # Distance to the nearest gold point, by brute force (gold lies 0.7 mm out).
        nearest = np.linalg.norm(gold - v, axis=1).min()
        assert nearest >= 0.7 - 1e-9 and f"nearest gold point: {nearest:.2f} mm" in text
        assert cb["pick"](None) is None
    finally:
        pl.close()


def test_distance_is_computed_from_points_when_missing() -> None:
    surf = _surface(distance=False)
    pts = _points(400, lift=0.0)
    mesh = with_distance(surf, pts)
    d = np.asarray(mesh.point_data["Distance"])
    # Brute force: distance from each vertex to the nearest point.
    v = np.asarray(surf.points)
    brute = np.sqrt(((v[:, None, :] - pts[None, :, :]) ** 2).sum(-1)).min(axis=1)
    np.testing.assert_allclose(d, brute, atol=1e-9)
    # A surface that has Distance keeps it.
    s2 = _surface()
    np.testing.assert_array_equal(
        with_distance(s2, pts).point_data["Distance"], s2.point_data["Distance"]
    )


def test_view_directions_lay_the_bone_horizontally() -> None:
    pts = np.asarray(_surface().points)
    toward = np.array([0.0, 0.0, 1.0])  # the probe is above (+z)
    dirs = render.view_directions(pts, toward)
    n, up = dirs["top"]
    np.testing.assert_allclose(n, toward, atol=1e-9)
    long_axis = np.array([1.0, 0.0, 0.0])
    for d, u in dirs.values():
        assert abs(u @ long_axis) < 1e-9 and abs(d @ u) < 1e-9
    d, _ = dirs["oblique"]
    assert np.degrees(np.arccos(abs(d @ n))) > 30
    # Without a probe direction the convex (upper) side of the arch faces the viewer.
    for flip in (1.0, -1.0):
        arch = pts * np.array([1.0, 1.0, flip])
        n, _ = render.view_directions(arch)["top"]
        assert n @ np.array([0.0, 0.0, flip]) > 0.99


def test_view_cli_screenshot_and_summary(tmp_path: Path, capsys: pytest.CaptureFixture) -> None:
    surf = tmp_path / "surface.vtp"
    write_polydata(_surface(), surf)
    pts = write_points_csv(_points(), tmp_path / "points.csv")
    gold = write_points_csv(_points(50, 0.4, 2), tmp_path / "gold.csv")
    from BoneUSRecon.Logic.sequence_io import write_sweep

    sweep = write_sweep(_sweep(), tmp_path / "sweep.mha")
    shot = tmp_path / "view.png"
    rc = main(
        [
            "view",
            str(surf),
            "--points",
            str(pts),
            "--gold",
            str(gold),
            "--sweep",
            str(sweep),
            "--screenshot",
            str(shot),
            "--size",
            "640x400",
            "-q",
        ]
    )
    out = capsys.readouterr()
    assert rc == 0, out.err
    assert "screenshot" in out.out and str(shot) in out.out and "1 invalid" in out.out
    img = _load(shot)
    assert img.shape == (400, 640, 3) and _count(img, ORANGE, 30) > 20


@pytest.mark.parametrize(
    "args, message",
    [
        (["missing.vtp"], "no such file"),
        (["{surf}", "--screenshot", "{tmp}/x.jpg"], "unknown output extension"),
        (["{surf}", "--screenshot", "{tmp}/nodir/x.png"], "does not exist"),
        (["{surf}", "--gold", "{tmp}/bad.csv", "--screenshot", "{tmp}/x.png"], "x,y,z"),
        (["{surf}", "--size", "big", "--screenshot", "{tmp}/x.png"], "--size"),
        (["{surf}"], "no display"),
    ],
)
def test_view_cli_refuses_bad_input_in_one_line(
    tmp_path: Path,
    capsys: pytest.CaptureFixture,
    monkeypatch: pytest.MonkeyPatch,
    args: list[str],
    message: str,
) -> None:
    monkeypatch.delenv("DISPLAY", raising=False)
    monkeypatch.delenv("WAYLAND_DISPLAY", raising=False)
    monkeypatch.setattr("sys.platform", "linux")
    surf = tmp_path / "surface.vtp"
    write_polydata(_surface(), surf)
    (tmp_path / "bad.csv").write_text("x,y,z\n1,2,three\n")
    argv = ["view"] + [a.format(surf=surf, tmp=tmp_path) for a in args]
    rc = main(argv)
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and err.startswith("bone-us-recon: error:") and message in err
    assert not list(tmp_path.glob("*.png")) and not list(tmp_path.glob(".*part*"))


def test_show_surface_refuses_empty_surface(tmp_path: Path) -> None:
    import pyvista as pv

    with pytest.raises(BoneUSReconError, match="no points"):
        show_surface(pv.PolyData(), screenshot=tmp_path / "e.png")
    assert not (tmp_path / "e.png").exists()

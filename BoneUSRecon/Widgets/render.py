"""Off-screen rendering shared by the viewer and the report (pyvista on VTK).

This is the only place in BoneUSRecon that imports VTK's rendering modules (through
pyvista); :mod:`BoneUSRecon.Logic` never does. On a Linux machine without a display the
render window is VTK's EGL one (needs ``libegl1`` and ``libgl1-mesa-dri``), chosen
before VTK would first try X and print a warning about it.

Conventions of every picture: the surface coloured by its ``Distance`` point array (mm)
with a scalar bar, segmented points in red (the paper's Fig. 4 draws them in yellow,
which vanishes against the upper end of most colour maps), gold points in black,
the sweep's frames as grey outlines (invalid frames in orange).
"""

from __future__ import annotations

import io
import os
import sys
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError

if TYPE_CHECKING:  # pragma: no cover
    import pyvista as pv

    from BoneUSRecon.Logic.sweep import Sweep

__all__ = [
    "Style",
    "has_display",
    "use_offscreen_backend",
    "preload_rendering",
    "as_pyvista",
    "distance_array",
    "sweep_outlines",
    "view_directions",
    "make_plotter",
    "render_views",
    "render_error_map",
    "set_camera",
    "add_scale_bar",
    "add_orientation_marker",
    "nice_length",
    "scene_points",
    "screenshot",
    "png_bytes",
    "save_png",
]


@dataclass(frozen=True)
class Style:
    """Colours and sizes of every BoneUSRecon picture."""

    #: matplotlib colour map for the surface's ``Distance`` (sequential: 0 mm is dark).
    cmap: str = "viridis"
    #: Colour of the segmented (contour) points, as in the paper's Fig. 4 overlay.
    points_color: str = "#ff3b30"
    #: Colour of the gold-standard points.
    gold_color: str = "black"
    #: Colour of valid frame outlines, and of invalid ones.
    outline_color: str = "#b4b4b4"
    invalid_outline_color: str = "#ff9500"
    #: On-screen size of points, in pixels.
    point_size: float = 5.0
    background: str = "white"
    #: Text colour (scalar bar, labels); must contrast with ``background``.
    text_color: str = "black"


DEFAULT_STYLE = Style()


def has_display() -> bool:
    """True when an interactive window can be opened (always on macOS/Windows)."""
    if not sys.platform.startswith("linux"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def use_offscreen_backend() -> None:
    """On a display-less Linux, make VTK create EGL render windows (no X attempt).

    VTK's default factory tries X first and prints ``bad X server connection`` on
    stderr before falling back to EGL; the CLI's output must stay clean.
    """
    if not has_display():
        os.environ.setdefault("VTK_DEFAULT_OPENGL_WINDOW", "vtkEGLRenderWindow")


#: VTK modules pyvista loads lazily at the first render (vtk 9.6, pyvista 0.49):
#: imported up front by :func:`preload_rendering`. Names missing from another VTK
#: build are skipped.
_LAZY_VTK_MODULES = (
    "vtkRenderingCore",
    "vtkRenderingOpenGL2",
    "vtkRenderingContext2D",
    "vtkRenderingContextOpenGL2",
    "vtkRenderingFreeType",
    "vtkRenderingAnnotation",
    "vtkRenderingVolume",
    "vtkRenderingVolumeOpenGL2",
    "vtkRenderingUI",
    "vtkRenderingMatplotlib",
    "vtkRenderingHyperTreeGrid",
    "vtkInteractionStyle",
    "vtkInteractionWidgets",
    "vtkChartsCore",
    "vtkViewsCore",
    "vtkViewsContext2D",
    "vtkPythonContext2D",
    "vtkImagingMath",
    "vtkIOImage",
)


def preload_rendering() -> None:
    """Import pyvista and VTK's rendering modules now, before a command's long work.

    VTK's compiled modules turn any exception raised while they import their
    dependencies into ``ImportError: Failed to load vtk...``; a Ctrl-C landing in
    such an import (pyvista imports them lazily, at the first render: in the middle
    of ``reconstruct --report``) then looked like an internal error. Importing them
    while the command starts makes that window short and early; the CLI also treats
    any failure after a SIGINT as the interruption it is
    (:func:`BoneUSRecon.cli.common.run_guarded`).
    """
    import importlib

    use_offscreen_backend()
    import pyvista  # noqa: F401
    import pyvista.plotting  # noqa: F401

    for name in _LAZY_VTK_MODULES:
        try:
            importlib.import_module(f"vtkmodules.{name}")
        except ModuleNotFoundError:
            continue


def as_pyvista(data: Any) -> pv.PolyData:
    """Wrap a ``vtkPolyData`` (or an ``(K, 3)`` array of points) as ``pyvista.PolyData``."""
    import pyvista as pv

    if isinstance(data, pv.PolyData):
        return data
    if isinstance(data, np.ndarray):
        return pv.PolyData(np.asarray(data, dtype=float).reshape(-1, 3))
    return pv.wrap(data)


def distance_array(surface: Any) -> np.ndarray | None:
    """The surface's ``Distance`` point array (mm) as numpy, or None when it has none."""
    mesh = as_pyvista(surface)
    if "Distance" not in mesh.point_data:
        return None
    return np.asarray(mesh.point_data["Distance"], dtype=float)


def sweep_outlines(sweep: Sweep, max_frames: int = 60) -> tuple[pv.PolyData, pv.PolyData]:
    """Rectangles of the sweep's image planes in reference mm.

    Parameters
    ----------
    sweep : Sweep
    max_frames : int
        At most this many outlines (evenly spaced, first and last kept), so that a
        250-frame sweep stays readable.

    Returns
    -------
    valid, invalid : pyvista.PolyData
        Closed line loops, one per frame, for valid and for invalid frames.
    """
    import pyvista as pv

    idx = np.arange(sweep.n_frames)
    if idx.size > max_frames:
        idx = np.unique(np.linspace(0, idx.size - 1, max_frames).round().astype(int))
    out = []
    for frames in (idx[sweep.valid[idx]], idx[~sweep.valid[idx]]):
        if frames.size == 0:
            out.append(pv.PolyData())
            continue
        corners = sweep.corners_mm(frames).reshape(-1, 3)
        base = 4 * np.arange(frames.size)[:, None]
        loops = np.column_stack([np.full(frames.size, 5), base + [0, 1, 2, 3, 0]])
        out.append(pv.PolyData(corners, lines=loops.reshape(-1)))
    return out[0], out[1]


def view_directions(
    points: np.ndarray, toward_viewer: np.ndarray | None = None
) -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """Two camera directions that show a partial bone surface well.

    The bone's long axis (first principal axis of ``points``) is laid horizontally.
    ``top`` looks down on the surface from ``toward_viewer`` (the side the probe was
    on: it is the side the upper bone surface faces); ``oblique`` turns 55 degrees
    about the long axis and 25 degrees along it, to show the relief.

    Parameters
    ----------
    points : ndarray, shape (K, 3)
        Surface points.
    toward_viewer : ndarray, shape (3,), optional
        Direction from the surface toward the viewer; when not given, the third
        principal axis, signed toward the surface's convex side.

    Returns
    -------
    dict
        ``name -> (direction from focal point to camera (unit), view-up (unit))``.
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    centred = p - p.mean(axis=0)
    # SVD of a (K, 3) array: cheap and robust principal axes.
    _, _, vt = np.linalg.svd(centred, full_matrices=False)
    long_axis = vt[0]
    if toward_viewer is None:
        # Look at the convex side: on an arch most of the area lies near the apex, so
        # the median height along the thin axis exceeds the mean on the apex side.
        n = vt[2]
        h = centred @ n
        if np.median(h) < h.mean():
            n = -n
    else:
        n = np.asarray(toward_viewer, dtype=float)
    n = n - long_axis * (n @ long_axis)  # make it orthogonal to the long axis
    if np.linalg.norm(n) < 1e-9:
        n = vt[2]
    n /= np.linalg.norm(n)
    up = np.cross(n, long_axis)
    up /= np.linalg.norm(up)

    def turn(v: np.ndarray, axis: np.ndarray, deg: float) -> np.ndarray:
        # Rodrigues' rotation of v about a unit axis.
        a = np.radians(deg)
        return v * np.cos(a) + np.cross(axis, v) * np.sin(a) + axis * (axis @ v) * (1 - np.cos(a))

    # Elevate 55 degrees about the long axis, then lean 25 degrees along it; the view-up
    # stays orthogonal to the long axis so the bone still lies horizontally.
    d1 = turn(n, long_axis, 55.0)
    up1 = turn(up, long_axis, 55.0)
    d2 = np.cos(np.radians(25.0)) * d1 + np.sin(np.radians(25.0)) * long_axis
    return {"top": (n, up), "oblique": (d2 / np.linalg.norm(d2), up1)}


#: Where the colour bar sits (normalised viewport): horizontal, centred, near the
#: bottom, since bones are long and lie horizontally.
_BAR = {"position_x": 0.3, "position_y": 0.035, "height": 0.075, "width": 0.4}


def _bar_args(title: str, style: Style) -> dict[str, Any]:
    # No VTK title: vtkScalarBarActor puts it on the side of the tick labels, where
    # it overlaps them. _add_bar_title writes it above the bar; the labels go below.
    return {
        "title": "",
        "color": style.text_color,
        "vertical": False,
        **_BAR,
        "fmt": "%.2f",
        "n_labels": 5,
        "label_font_size": 14,
        "title_font_size": 1,
    }


def _add_bar_title(pl: pv.Plotter, title: str, style: Style) -> None:
    """Put the colour bar's tick labels below it and ``title`` above it (no overlap)."""
    from vtkmodules.vtkRenderingCore import vtkTextActor

    for bar in pl.scalar_bars.values():
        bar.SetTextPositionToPrecedeScalarBar()  # labels below the colour strip
    text = vtkTextActor()
    text.SetInput(title)
    prop = text.GetTextProperty()
    prop.SetFontSize(16)
    prop.SetColor(_rgb(style.text_color))
    prop.SetJustificationToCentered()
    prop.SetVerticalJustificationToBottom()
    text.GetPositionCoordinate().SetCoordinateSystemToNormalizedViewport()
    text.SetPosition(
        _BAR["position_x"] + _BAR["width"] / 2, _BAR["position_y"] + _BAR["height"] + 0.005
    )
    pl.add_actor(text, name="bar-title", reset_camera=False)


#: The colour bar's box in pixels (bottom margin, height, strip share of the height):
#: fixed in pixels because its tick labels are (14 px); a box in window fractions
#: squeezes the labels onto the strip in some window heights.
_BAR_PX = {"bottom": 8, "height": 40, "bar_ratio": 0.32}


def _layout_bar(pl: pv.Plotter) -> None:
    """Size the colour bar and its title for the current window height (see _BAR_PX)."""
    height = max(int(pl.window_size[1]), 1)
    y0, h = _BAR_PX["bottom"] / height, _BAR_PX["height"] / height
    for bar in pl.scalar_bars.values():
        bar.SetPosition(_BAR["position_x"], y0)
        bar.SetHeight(h)
        bar.SetBarRatio(_BAR_PX["bar_ratio"])
    title = pl.actors.get("bar-title")
    if title is not None:
        title.SetPosition(_BAR["position_x"] + _BAR["width"] / 2, y0 + h + 3 / height)


def _rgb(color: str) -> tuple[float, float, float]:
    from matplotlib.colors import to_rgb

    r, g, b = to_rgb(color)
    return (r, g, b)


def nice_length(mm: float) -> float:
    """The largest 1, 2 or 5 times a power of ten not above ``mm`` (a scale bar length).

    >>> nice_length(37.0), nice_length(9.9), nice_length(0.3)
    (20.0, 5.0, 0.2)
    """
    if not np.isfinite(mm) or mm <= 0:
        return 1.0
    p = 10.0 ** np.floor(np.log10(mm))
    return float(max(m * p for m in (1.0, 2.0, 5.0) if m * p <= mm * (1 + 1e-9)))


def add_scale_bar(pl: pv.Plotter, style: Style = DEFAULT_STYLE, *, fraction: float = 0.15) -> float:
    """Draw a scale bar (a line of a round length in mm, labelled) at the lower right.

    Exact for the parallel projection :func:`set_camera` uses: one window pixel is
    ``2 * parallel_scale / window height`` mm at every depth. Call it after the camera
    is set (again after each change); it replaces the previous bar.

    Returns
    -------
    float
        The bar's length in mm.
    """
    from vtkmodules.vtkCommonCore import vtkPoints
    from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData
    from vtkmodules.vtkRenderingCore import (
        vtkActor2D,
        vtkCoordinate,
        vtkPolyDataMapper2D,
        vtkTextActor,
    )

    width, height = pl.window_size
    mm_per_px = 2.0 * float(pl.camera.parallel_scale) / max(height, 1)
    length = nice_length(fraction * width * mm_per_px)
    px = length / mm_per_px
    x1, y = width - 30.0, 28.0
    x0 = x1 - px
    pts = vtkPoints()
    for xy in ((x0, y + 6), (x0, y), (x1, y), (x1, y + 6)):
        pts.InsertNextPoint(xy[0], xy[1], 0.0)
    lines = vtkCellArray()
    lines.InsertNextCell(4, [0, 1, 2, 3])
    poly = vtkPolyData()
    poly.SetPoints(pts)
    poly.SetLines(lines)
    mapper = vtkPolyDataMapper2D()
    mapper.SetInputData(poly)
    coord = vtkCoordinate()
    coord.SetCoordinateSystemToDisplay()
    mapper.SetTransformCoordinate(coord)
    bar = vtkActor2D()
    bar.SetMapper(mapper)
    bar.GetProperty().SetColor(_rgb(style.text_color))
    bar.GetProperty().SetLineWidth(2)
    label = vtkTextActor()
    label.SetInput(f"{length:g} mm")
    prop = label.GetTextProperty()
    prop.SetFontSize(15)
    prop.SetColor(_rgb(style.text_color))
    prop.SetJustificationToCentered()
    label.SetDisplayPosition(int((x0 + x1) / 2), int(y + 8))
    pl.add_actor(bar, name="scale-bar", reset_camera=False)
    pl.add_actor(label, name="scale-bar-label", reset_camera=False)
    return length


#: Where the orientation triad goes (normalised viewport): lower left by default.
LOWER_LEFT = (0.0, 0.0, 0.14, 0.28)
UPPER_RIGHT = (0.86, 0.72, 1.0, 1.0)


def add_orientation_marker(pl: pv.Plotter, viewport: Sequence[float] = LOWER_LEFT) -> None:
    """An x/y/z axes triad of the reference frame in a corner (``viewport``).

    It turns with the camera, so a reader sees how the view is oriented (the sweep's
    reference coordinates are the tracker's, not a patient's: hence x, y, z).
    """
    pl.add_axes(
        viewport=tuple(viewport), line_width=2, color="black", xlabel="x", ylabel="y", zlabel="z"
    )


def _dot_size(n: int, largest: float) -> float:
    """Point size in pixels: dense clouds (thousands of points) would hide the surface
    under full-size dots, so shrink them with the square root of the count."""
    return float(np.clip(largest * np.sqrt(300.0 / max(n, 1)), 2.0, largest))


def make_plotter(
    surface: Any,
    *,
    points: Any = None,
    gold: Any = None,
    sweep: Sweep | None = None,
    off_screen: bool = True,
    window_size: Sequence[int] = (900, 600),
    style: Style = DEFAULT_STYLE,
    clim: Sequence[float] | None = None,
    scalar_bar: bool = True,
    title: str | None = None,
    axes_viewport: Sequence[float] = LOWER_LEFT,
) -> tuple[pv.Plotter, dict[str, Any]]:
    """A plotter showing the surface, its points, the gold points and the sweep.

    Parameters
    ----------
    surface : vtkPolyData or pyvista.PolyData
        Coloured by its ``Distance`` point array when it has one.
    points, gold : vtkPolyData, pyvista.PolyData or ndarray (K, 3), optional
        Segmented points and gold-standard points.
    sweep : Sweep, optional
        Its frames are drawn as outlines.
    off_screen : bool
        Render without a window (for screenshots).
    clim : (float, float), optional
        Colour range in mm; ``[0, max Distance]`` by default.
    axes_viewport : (x0, y0, x1, y1)
        Corner of the x/y/z orientation triad (:func:`add_orientation_marker`).

    Returns
    -------
    plotter : pyvista.Plotter
    actors : dict
        ``"surface"``, ``"points"``, ``"gold"``, ``"frames"``, ``"invalid_frames"``
        (absent when not drawn), for the viewer's toggles.
    """
    if off_screen:
        use_offscreen_backend()
    import pyvista as pv

    mesh = as_pyvista(surface)
    if mesh.n_points == 0:
        raise BoneUSReconError("the surface has no points")
    pl = pv.Plotter(off_screen=off_screen, window_size=list(window_size))
    pl.set_background(style.background)
    actors: dict[str, Any] = {}
    dist = distance_array(mesh)
    if dist is not None and np.isfinite(dist).any():
        lo, hi = (0.0, float(np.nanmax(dist))) if clim is None else map(float, clim)
        hi = max(hi, lo + 1e-6)
        actors["surface"] = pl.add_mesh(
            mesh,
            scalars="Distance",
            cmap=style.cmap,
            clim=(lo, hi),
            nan_color="lightgrey",
            smooth_shading=True,
            show_scalar_bar=scalar_bar,
            scalar_bar_args=_bar_args("Distance (mm)", style) if scalar_bar else None,
        )
        if scalar_bar:
            _add_bar_title(pl, "Distance (mm)", style)
    else:
        actors["surface"] = pl.add_mesh(mesh, color="#d9c8a9", smooth_shading=True)
    for name, cloud, color in (
        ("points", points, style.points_color),
        ("gold", gold, style.gold_color),
    ):
        c = as_pyvista(cloud) if cloud is not None else None
        if c is not None and c.n_points:
            actors[name] = pl.add_mesh(
                pv.PolyData(np.asarray(c.points)),
                color=color,
                point_size=_dot_size(c.n_points, style.point_size),
                render_points_as_spheres=True,
            )
    if sweep is not None:
        valid, invalid = sweep_outlines(sweep)
        if valid.n_points:
            # Opaque (a light grey, not a translucent one): translucent geometry makes
            # VTK lay the colour bar's tick labels out over its strip.
            actors["frames"] = pl.add_mesh(valid, color=style.outline_color, line_width=1)
        if invalid.n_points:
            actors["invalid_frames"] = pl.add_mesh(
                invalid, color=style.invalid_outline_color, line_width=1.5
            )
    if title:
        pl.add_text(title, position="upper_left", font_size=10, color=style.text_color)
    add_orientation_marker(pl, axes_viewport)
    return pl, actors


def _toward_probe(sweep: Sweep | None) -> np.ndarray | None:
    """Mean direction from depth toward the transducer (minus the image row axis)."""
    if sweep is None or sweep.n_valid == 0:
        return None
    from BoneUSRecon.Logic.sweep import frame_planes

    _, axes, _ = frame_planes(sweep.image_to_reference[sweep.valid_indices])
    d = -axes[:, :, 1].mean(axis=0)
    n = np.linalg.norm(d)
    return d / n if n > 1e-9 else None


def set_camera(
    pl: pv.Plotter,
    points: np.ndarray,
    direction: np.ndarray,
    up: np.ndarray,
    *,
    margin: float = 1.08,
    reserve_bottom: float = 0.2,
    reserve_top: float = 0.0,
) -> None:
    """Look at ``points`` from ``direction`` (parallel projection), filling the window.

    Parameters
    ----------
    pl : pyvista.Plotter
    points : ndarray, shape (K, 3)
        What must fit in the view.
    direction : ndarray, shape (3,)
        Unit vector from the data toward the camera.
    up : ndarray, shape (3,)
        Unit view-up, orthogonal to ``direction``.
    margin : float
        Extra room around the data (1 = touching the edges).
    reserve_bottom : float
        Fraction of the window height kept free at the bottom (for the scalar bar).
    reserve_top : float
        Fraction kept free at the top (for a title or legend).
    """
    p = np.asarray(points, dtype=float).reshape(-1, 3)
    d = np.asarray(direction, dtype=float)
    up = np.asarray(up, dtype=float)
    right = np.cross(up, d)
    # Extent of the data in the view plane: VTK's own reset fits a bounding sphere,
    # which leaves a long bone small in a wide window.
    x, y = p @ right, p @ up
    w, h = float(np.ptp(x)) or 1.0, float(np.ptp(y)) or 1.0
    centre = p.mean(axis=0)
    centre = (
        centre
        + right * ((x.max() + x.min()) / 2 - centre @ right)
        + up * ((y.max() + y.min()) / 2 - centre @ up)
    )
    width, height = pl.window_size
    aspect = width / max(height, 1)
    usable = 1.0 - reserve_bottom - reserve_top
    scale = max(h * margin / (2 * usable), w * margin / (2 * aspect))
    focus = centre - up * ((reserve_bottom - reserve_top) * scale)
    depth = float(np.ptp(p @ d)) + 10.0 * max(w, h)
    # Setting camera_position (not the camera's fields) also tells pyvista the camera
    # is set, so its first render does not replace it with the default view.
    pl.camera_position = [tuple(focus + d * depth), tuple(focus), tuple(up)]
    pl.camera.parallel_projection = True
    pl.camera.parallel_scale = scale
    pl.reset_camera_clipping_range()


def scene_points(actors: dict[str, Any], max_points: int = 20000) -> np.ndarray:
    """Points of everything drawn (subsampled), to fit the view to the visible data."""
    from vtkmodules.util import numpy_support

    chunks = []
    for actor in actors.values():
        mapper = actor.GetMapper()
        # pyvista feeds mappers through a pipeline that has not run before the first
        # render, so the mapper's input is empty until that pipeline is updated.
        data = None
        if mapper is not None:
            if mapper.GetInputAlgorithm() is not None:
                mapper.GetInputAlgorithm().Update()
            data = mapper.GetInput()
        if data is not None and data.GetNumberOfPoints():
            chunks.append(numpy_support.vtk_to_numpy(data.GetPoints().GetData()))
            continue
        b = np.asarray(actor.GetBounds(), dtype=float)
        if np.all(np.isfinite(b)) and b[1] >= b[0]:
            chunks.append(np.array([[x, y, z] for x in b[0:2] for y in b[2:4] for z in b[4:6]]))
    if not chunks:
        return np.zeros((1, 3))
    pts = np.concatenate(chunks).astype(float)
    step = max(1, pts.shape[0] // max_points)
    return pts[::step]


def render_views(
    surface: Any,
    *,
    points: Any = None,
    gold: Any = None,
    sweep: Sweep | None = None,
    views: Sequence[str] = ("top", "oblique"),
    window_size: Sequence[int] = (900, 600),
    style: Style = DEFAULT_STYLE,
    show_frames: bool = False,
    fit_height: bool = False,
) -> dict[str, np.ndarray]:
    """Render the surface off-screen from named viewpoints (see :func:`view_directions`).

    Parameters
    ----------
    surface, points, gold
        As in :func:`make_plotter`.
    sweep : Sweep, optional
        Used to orient the ``top`` view toward the probe; drawn only when
        ``show_frames``.
    views : sequence of str
        Names among ``"top"``, ``"oblique"``.
    window_size : (int, int)
        Image size in pixels; with ``fit_height`` the height is a maximum.
    fit_height : bool
        Shrink each image's height to the data's aspect (a long bone seen from above
        is a thin strip), between 35 % of the width and ``window_size[1]``.

    Returns
    -------
    dict
        ``view name -> RGB image (H, W, 3) uint8``.
    """
    mesh = as_pyvista(surface)
    pl, actors = make_plotter(
        mesh,
        points=points,
        gold=gold,
        sweep=sweep if show_frames else None,
        off_screen=True,
        window_size=window_size,
        style=style,
    )
    try:
        pts = np.asarray(mesh.points, dtype=float)
        dirs = view_directions(pts, _toward_probe(sweep))
        fit = scene_points(actors)
        out = {}
        for name in views:
            if name not in dirs:
                raise ValueError(f"unknown view {name!r}; use one of {', '.join(dirs)}")
            d, up = dirs[name]
            if fit_height:
                w = int(window_size[0])
                span = np.ptp(fit @ np.cross(up, d)) or 1.0
                need = (
                    w * np.ptp(fit @ up) / span * 1.08 / 0.8
                )  # margin, colour bar with title and labels
                pl.window_size = [w, int(np.clip(need, 0.35 * w, window_size[1]))]
            set_camera(pl, fit, d, up)
            add_scale_bar(pl, style)
            out[name] = screenshot(pl)
        return out
    finally:
        pl.close()


def screenshot(pl: pv.Plotter) -> np.ndarray:
    """Render the plotter now and return its image as ``(H, W, 3)`` uint8."""
    # pyvista's screenshot() renders only the first time; later camera changes need an
    # explicit render (which, conversely, does nothing before the first one).
    _layout_bar(pl)
    pl.render()
    return np.asarray(pl.screenshot(None, return_img=True))[..., :3].copy()


def png_bytes(image: np.ndarray) -> bytes:
    """Encode an ``(H, W, 3|4)`` uint8 image as PNG bytes (Pillow)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(np.ascontiguousarray(image)).save(buf, format="PNG")
    return buf.getvalue()


def save_png(image: np.ndarray, path: str | os.PathLike[str]) -> Path:
    """Write an image as PNG atomically (via :func:`~BoneUSRecon.Logic.fileio.atomic_path`)."""
    from BoneUSRecon.Logic.fileio import atomic_path, check_output_path

    p = check_output_path(path, (".png",))
    with atomic_path(p) as tmp:
        tmp.write_bytes(png_bytes(image))
    return p


def render_error_map(
    surface: Any,
    gold: np.ndarray,
    distances: np.ndarray,
    *,
    sweep: Sweep | None = None,
    view: str = "top",
    window_size: Sequence[int] = (1000, 620),
    style: Style = DEFAULT_STYLE,
) -> np.ndarray:
    """The surface in plain colour with the gold points coloured by their distance to it.

    Shows where the reconstruction is off, which the histogram cannot.

    Parameters
    ----------
    surface : vtkPolyData or pyvista.PolyData
    gold : ndarray, shape (K, 3)
        Gold points (mm).
    distances : ndarray, shape (K,)
        Their distances to the surface (mm), e.g. ``Evaluation.distances``.
    sweep : Sweep, optional
        Orients the ``top`` view toward the probe.
    view : {"top", "oblique"}
    window_size : (int, int)
        Width, and the largest height (the height follows the data's aspect).

    Returns
    -------
    ndarray of uint8, shape (H, W, 3)
    """
    use_offscreen_backend()
    import pyvista as pv

    mesh = as_pyvista(surface)
    g = pv.PolyData(np.asarray(gold, dtype=float).reshape(-1, 3))
    dist = np.asarray(distances, dtype=float).reshape(-1)
    g.point_data["gold distance"] = dist
    # Colour range: a few far outliers must not wash out the rest; values above the
    # range take the top colour.
    top = float(np.nanmax(dist)) if dist.size else 1.0
    hi = max(min(top, max(1.0, 2.0 * float(np.nanpercentile(dist, 95)))), 1e-3)
    pl = pv.Plotter(off_screen=True, window_size=list(window_size))
    try:
        pl.set_background(style.background)
        actors = {
            "surface": pl.add_mesh(mesh, color="#c8c8c8", smooth_shading=True),
            "gold": pl.add_mesh(
                g,
                scalars="gold distance",
                cmap="coolwarm",
                clim=(0.0, hi),
                point_size=_dot_size(g.n_points, style.point_size + 2),
                render_points_as_spheres=True,
                scalar_bar_args=_bar_args("", style),
            ),
        }
        _add_bar_title(
            pl,
            "gold point to surface (mm" + (f"; {hi:.2f} or more: dark red)" if top > hi else ")"),
            style,
        )
        add_orientation_marker(pl)
        pts = np.asarray(mesh.points, dtype=float)
        d, up = view_directions(pts, _toward_probe(sweep))[view]
        fit = scene_points(actors)
        w = int(window_size[0])
        span = np.ptp(fit @ np.cross(up, d)) or 1.0
        need = w * np.ptp(fit @ up) / span * 1.08 / 0.8
        pl.window_size = [w, int(np.clip(need, 0.35 * w, window_size[1]))]
        set_camera(pl, fit, d, up)
        add_scale_bar(pl, style)
        return screenshot(pl)
    finally:
        pl.close()

"""Interactive inspection of a reconstructed surface (pyvista window), or a screenshot.

The window shows the surface coloured by its ``Distance`` point array (mm) with a
scalar bar, check boxes that show or hide the segmented points, the gold points and
the sweep's frame outlines, and picking (press ``P`` over the surface, or right-click)
reports the picked point's coordinates and its ``Distance`` (and its distance to the
nearest gold point when gold points are shown). With ``screenshot=...`` nothing opens:
the same scene is rendered off-screen to a PNG.
"""

from __future__ import annotations

import os
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from scipy.spatial import cKDTree

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Widgets import render

if TYPE_CHECKING:  # pragma: no cover
    from BoneUSRecon.Logic.sweep import Sweep

__all__ = ["show_surface", "with_distance"]


def with_distance(surface: Any, points: Any) -> Any:
    """The surface (as ``pyvista.PolyData``) with a ``Distance`` array, added if missing.

    A surface written by BoneUSRecon carries ``Distance`` (mm from each vertex to the
    nearest segmented point, as the paper's Fig. 4 texture). For a surface from
    elsewhere it is computed here from ``points`` when they are given; otherwise the
    surface is returned unchanged.
    """
    mesh = render.as_pyvista(surface)
    if "Distance" in mesh.point_data or points is None:
        return mesh
    pts = np.asarray(render.as_pyvista(points).points, dtype=float)
    if pts.size == 0:
        return mesh
    mesh = mesh.copy(deep=False)
    mesh.point_data["Distance"] = cKDTree(pts).query(np.asarray(mesh.points, float))[0]
    mesh.set_active_scalars("Distance")
    return mesh


def _legend(pl: Any, actors: dict[str, Any], style: render.Style) -> None:
    entries = []
    if "points" in actors:
        entries.append(["segmented points", style.points_color])
    if "gold" in actors:
        entries.append(["gold points", style.gold_color])
    if "frames" in actors:
        entries.append(["frames", style.outline_color])
    if "invalid_frames" in actors:
        entries.append(["invalid frames", style.invalid_outline_color])
    if entries:
        pl.add_legend(
            entries,
            bcolor=style.background,
            border=False,
            size=(0.2, 0.032 * len(entries) + 0.01),
            loc="lower left",
            face="circle",
        )


def show_surface(
    surface: Any,
    *,
    points: Any = None,
    gold: Any = None,
    sweep: Sweep | None = None,
    screenshot: str | os.PathLike[str] | None = None,
    window_size: tuple[int, int] = (1100, 700),
    title: str = "BoneUSRecon",
    view: str = "oblique",
) -> Path | None:
    """Show a surface in an interactive window, or render it to a PNG.

    Parameters
    ----------
    surface : vtkPolyData or pyvista.PolyData
        The reconstructed surface; coloured by its ``Distance`` array (computed from
        ``points`` when missing, see :func:`with_distance`).
    points : vtkPolyData, pyvista.PolyData or ndarray (K, 3), optional
        Segmented contour points (mm).
    gold : vtkPolyData, pyvista.PolyData or ndarray (K, 3), optional
        Gold-standard points (mm).
    sweep : Sweep, optional
        Its frames are drawn as outlines (invalid frames in orange).
    screenshot : path-like, optional
        Render off-screen to this PNG (atomically) and return its path.
    window_size : (int, int)
        Window or image size in pixels.
    title : str
        Window title, and the caption of the screenshot.
    view : {"oblique", "top"}
        Initial viewpoint (see :func:`BoneUSRecon.Widgets.render.view_directions`).

    Returns
    -------
    Path or None
        The screenshot's path, or None after the window was closed.

    Raises
    ------
    BoneUSReconError
        Bad output path, an empty surface, or no display for an interactive window.
    """
    style = render.DEFAULT_STYLE
    out = None
    if screenshot is not None:
        from BoneUSRecon.Logic.fileio import check_output_path

        out = check_output_path(screenshot, (".png",))
    elif not render.has_display():
        raise BoneUSReconError(
            "no display for an interactive window (DISPLAY is not set); "
            "use --screenshot PNG to render to a file"
        )
    mesh = with_distance(surface, points)
    if mesh.n_points == 0:
        raise BoneUSReconError("the surface has no points")
    pl, actors = render.make_plotter(
        mesh,
        points=points,
        gold=gold,
        sweep=sweep,
        off_screen=out is not None,
        window_size=window_size,
        style=style,
        title=title,
        axes_viewport=render.UPPER_RIGHT,  # the legend and check boxes are lower left
    )
    try:
        pts = np.asarray(mesh.points, dtype=float)
        d, up = render.view_directions(pts, render._toward_probe(sweep))[view]
        fit = render.scene_points(actors)
        if out is not None:
            _legend(pl, actors, style)  # the window has labelled check boxes instead
            render.set_camera(pl, fit, d, up, reserve_top=0.06)
            render.add_scale_bar(pl, style)  # exact for this still image's camera
            image = render.screenshot(pl)
            return render.save_png(image, out)
        _add_interaction(pl, mesh, actors, gold, style)
        render.set_camera(pl, fit, d, up, reserve_top=0.06)
        pl.show(title=title)
        return None
    finally:
        pl.close()


def _add_interaction(
    pl: Any, mesh: Any, actors: dict[str, Any], gold: Any, style: render.Style
) -> dict[str, Any]:
    """Check boxes for the optional layers, and picking that reports distances.

    Returns the callbacks (``"toggle:<layer>"`` and ``"pick"``), for tests.
    """
    callbacks: dict[str, Any] = {}
    y = 10.0
    for key, label, colour in (
        ("invalid_frames", "invalid frames", style.invalid_outline_color),
        ("frames", "frames", style.outline_color),
        ("gold", "gold points", style.gold_color),
        ("points", "segmented points", style.points_color),
    ):
        actor = actors.get(key)
        if actor is None:
            continue

        def toggle(flag: bool, actor: Any = actor) -> None:
            actor.SetVisibility(bool(flag))

        # Each box is filled with its layer's colour, so the boxes are the legend.
        pl.add_checkbox_button_widget(
            toggle,
            value=True,
            position=(10.0, y),
            size=28,
            border_size=3,
            color_on=colour,
            color_off="white",
        )
        pl.add_text(label, position=(45, int(y) + 4), font_size=10, color=style.text_color)
        callbacks[f"toggle:{key}"] = toggle
        y += 36.0

    tree = cKDTree(np.asarray(mesh.points, dtype=float))
    dist = render.distance_array(mesh)
    gold_pts = None if gold is None else np.asarray(render.as_pyvista(gold).points, float)
    gold_tree = cKDTree(gold_pts) if gold_pts is not None and gold_pts.size else None

    def on_pick(point: Any) -> str | None:
        if point is None:
            return None
        p = np.asarray(point, dtype=float).reshape(3)
        _, k = tree.query(p)
        text = f"picked ({p[0]:.1f}, {p[1]:.1f}, {p[2]:.1f}) mm"
        if dist is not None:
            text += f"\nDistance to nearest segmented point: {dist[k]:.2f} mm"
        if gold_tree is not None:
            text += f"\nnearest gold point: {gold_tree.query(p)[0]:.2f} mm"
        pl.add_text(text, position="upper_right", font_size=10, color=style.text_color, name="pick")
        return text

    pl.enable_point_picking(
        callback=on_pick,
        show_message="P or right-click on the surface: show its distance",
        font_size=10,
        color=style.points_color,
        point_size=10,
    )
    callbacks["pick"] = on_pick
    return callbacks

"""``bone-us-recon view SURFACE``: look at a reconstructed surface (pyvista window).

Without ``--screenshot`` an interactive window opens; with it the scene is rendered
off-screen to the PNG and the command exits (no display needed).
"""

from __future__ import annotations

import argparse
from typing import Any

from BoneUSRecon.cli.common import (
    GOLD_HELP,
    SURFACE_HELP,
    SWEEP_HELP,
    ProgressBar,
    add_calibration_option,
    add_common_options,
    check_distinct_paths,
    parse_size,
    print_summary,
    read_sweep_args,
)

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``view`` sub-command."""
    p = subparsers.add_parser(
        "view",
        help="show a surface coloured by Distance, with points, gold points and frames",
        description="Open an interactive window showing SURFACE coloured by its Distance "
        "array (mm) with a scalar bar; check boxes toggle the segmented points, the gold "
        "points and the sweep's frame outlines; press P (or right-click) on the surface "
        "to show the distance there. With --screenshot, render off-screen to a PNG and "
        "exit.",
    )
    p.add_argument("surface", metavar="SURFACE", help=SURFACE_HELP)
    p.add_argument(
        "--points",
        metavar="POINTS",
        help="segmented points (.vtp/.vtk/.ply or CSV with x,y,z columns)",
    )
    p.add_argument("--gold", metavar="GOLD", help=GOLD_HELP)
    p.add_argument("--sweep", metavar="SWEEP", help=f"{SWEEP_HELP}: draw its frames as outlines")
    add_calibration_option(p)
    p.add_argument(
        "--screenshot", metavar="PNG", help="render off-screen to this PNG and exit (no window)"
    )
    p.add_argument(
        "--view",
        choices=("oblique", "top"),
        default="oblique",
        help="viewpoint: 'top' looks from the probe side, 'oblique' (default) shows the relief",
    )
    p.add_argument(
        "--size",
        metavar="WxH",
        default="1100x700",
        help="window or image size in pixels (default 1100x700)",
    )
    add_common_options(p)
    p.set_defaults(func=run)


def _size(text: str) -> tuple[int, int]:
    from BoneUSRecon.Logic.errors import BoneUSReconError

    w, h = parse_size(text, example="1100x700")
    if not (16 <= w <= 8192 and 16 <= h <= 8192):
        raise BoneUSReconError(f"--size {text!r} is out of range (16..8192 pixels per side)")
    return w, h


def run(args: argparse.Namespace) -> int:
    """Read the inputs (all checked before any window opens), then show or screenshot."""
    from BoneUSRecon.Logic.fileio import check_output_path
    from BoneUSRecon.Logic.vtkio import read_points, read_polydata

    size = _size(args.size)
    check_distinct_paths(
        inputs={
            "SURFACE": args.surface,
            "--points": args.points,
            "--gold": args.gold,
            "--sweep": args.sweep,
            "--calibration": args.calibration,
        },
        outputs={"--screenshot": args.screenshot},
    )
    if args.screenshot:
        check_output_path(args.screenshot, (".png",))
    surface = read_polydata(args.surface)
    points = read_points(args.points) if args.points else None
    gold = read_points(args.gold) if args.gold else None
    sweep = None
    if args.sweep:
        with ProgressBar(quiet=args.quiet) as bar:
            sweep = read_sweep_args(args, bar)

    from BoneUSRecon.Widgets.viewer import show_surface

    out = show_surface(
        surface,
        points=points,
        gold=gold,
        sweep=sweep,
        screenshot=args.screenshot,
        window_size=size,
        title=f"BoneUSRecon: {args.surface}",
        view=args.view,
    )
    if out is not None:
        rows: list[tuple[str, Any]] = [
            ("surface", args.surface),
            ("vertices", surface.GetNumberOfPoints()),
        ]
        if points is not None:
            rows.append(("segmented points", len(points)))
        if gold is not None:
            rows.append(("gold points", len(gold)))
        if sweep is not None:
            rows.append(
                ("frames drawn", f"{sweep.n_frames} ({sweep.n_frames - sweep.n_valid} invalid)")
            )
        rows.append(("screenshot", str(out)))
        print_summary("view", rows)
    return 0

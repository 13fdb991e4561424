"""``bone-us-recon table SWEEP --gold GOLD``: the paper's Table I on your data."""

from __future__ import annotations

import argparse
from typing import Any

from BoneUSRecon.cli.common import (
    GOLD_HELP,
    SWEEP_HELP,
    ProgressBar,
    add_calibration_option,
    add_common_options,
    add_json_option,
    check_distinct_paths,
    check_sweep_args,
    print_json,
    print_warnings,
    read_sweep_args,
)
from BoneUSRecon.cli.reconstruct import add_reconstruction_options, params_from_args

__all__ = ["register", "run", "write_table_plot"]


def register(subparsers: Any) -> None:
    """Add the ``table`` sub-command."""
    p = subparsers.add_parser(
        "table",
        help="mean gold-to-surface distance for each number of control points (Table I)",
        description="Reconstruct once, then refit the surface with each number of control "
        "points along the bone and print the mean distance from the gold points, as in "
        "the paper's Table I.",
    )
    p.add_argument("sweep", metavar="SWEEP", help=SWEEP_HELP)
    p.add_argument("--gold", required=True, metavar="GOLD", help=GOLD_HELP)
    add_calibration_option(p)
    add_reconstruction_options(p, control_points=False)
    # --along/--around, as in ``reconstruct``; --control-points E... still works (hidden).
    p.add_argument(
        "--along",
        dest="counts",
        nargs="+",
        type=int,
        metavar="E",
        default=[5, 10, 15, 20],
        help="numbers of control points along the bone to try (default 5 10 15 20)",
    )
    p.add_argument(
        "--control-points",
        dest="counts",
        nargs="+",
        type=int,
        default=argparse.SUPPRESS,
        help=argparse.SUPPRESS,
    )
    p.add_argument(
        "--around",
        type=int,
        metavar="F",
        help="control points around the bone, kept fixed (default 6; the paper: 5)",
    )
    p.add_argument("--plot", metavar="PNG", help="also plot the table to this PNG file")
    add_json_option(p)
    add_common_options(p)
    p.set_defaults(func=run)


def write_table_plot(rows: list[tuple[int, float]], path: Any, title: str = "") -> None:
    """Plot mean distance against control points to a PNG, atomically.

    The report's figure (:func:`BoneUSRecon.Widgets.report.table_figure`): distance
    axis from 0 mm, the paper's Table I beside this run's curve.
    """
    from BoneUSRecon.Logic.fileio import atomic_path
    from BoneUSRecon.Widgets.report import table_png

    data = table_png(rows, title)
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def run(args: argparse.Namespace) -> int:
    """Reconstruct, refit per count, print (and plot) the table."""
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.fileio import check_output_path
    from BoneUSRecon.Logic.pipeline import control_point_table, params_with, reconstruct
    from BoneUSRecon.Logic.vtkio import read_points

    check_sweep_args(args)
    check_distinct_paths(
        inputs={"SWEEP": args.sweep, "--calibration": args.calibration, "--gold": args.gold},
        outputs={"--plot": args.plot},
    )
    plot = check_output_path(args.plot, (".png",)) if args.plot else None
    params = params_from_args(args)
    if args.around is not None:
        params = params_with(params, around=args.around)
    for e in args.counts:  # refuse absurd counts before the work
        params_with(params, along=e)
    if len(set(args.counts)) != len(args.counts):
        raise BoneUSReconError("control-point counts repeat")
    gold = read_points(args.gold)
    with ProgressBar(quiet=args.quiet or args.json) as bar:
        sweep = read_sweep_args(args, bar)
        recon = reconstruct(sweep, params, progress=bar)
        rows = control_point_table(recon, gold, args.counts, progress=bar)
    if plot is not None:
        write_table_plot(rows, plot, title=f"Table I: {sweep.source.name if sweep.source else ''}")
    if args.json:
        print_json(
            {
                "control_points": [r[0] for r in rows],
                "mean_distance_mm": [r[1] for r in rows],
                "control_points_around": params.fit.n_control_points[1],
                "gold_points": int(gold.shape[0]),
                "plot": str(plot) if plot else None,
                "warnings": recon.summary["warnings"],
            }
        )
        print_warnings(recon.summary["warnings"])
        return 0
    print("TABLE I  AVERAGE RECONSTRUCTION ERROR")
    print(f"  {'Number of control points':>24}  {'Average distance (mm)':>21}")
    for e, d in rows:
        print(f"  {e:>24d}  {d:>21.3f}")
    if plot:
        print(f"  plot: {plot}")
    print_warnings(recon.summary["warnings"])  # e.g. a bone point the track does not reach
    return 0

"""``bone-us-recon evaluate SURFACE GOLD``: distances from gold points to a surface."""

from __future__ import annotations

import argparse
from typing import Any

from BoneUSRecon.cli.common import (
    GOLD_HELP,
    SURFACE_HELP,
    add_common_options,
    add_json_option,
    print_json,
    print_summary,
)

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``evaluate`` sub-command."""
    p = subparsers.add_parser(
        "evaluate",
        help="distances from gold-standard points to a surface",
        description="Exact point-to-triangle distances from each gold point to the surface: "
        "mean, RMS, median, 95th percentile, maximum, and the share within 0.5, 1 and 2 mm.",
    )
    p.add_argument("surface", metavar="SURFACE", help=SURFACE_HELP)
    p.add_argument("gold", metavar="GOLD", help=GOLD_HELP)
    add_json_option(p)
    p.add_argument("--distances", action="store_true", help="with --json, include every distance")
    add_common_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Read both files, measure, print."""
    from BoneUSRecon.Logic.evaluation import check_surface, evaluate_surface
    from BoneUSRecon.Logic.vtkio import read_points, read_polydata

    surface = read_polydata(args.surface)
    check_surface(surface, args.surface)  # before reading the gold points
    gold = read_points(args.gold)
    ev = evaluate_surface(surface, gold)
    if args.json:
        print_json(ev.as_dict(with_distances=args.distances))
        return 0
    print_summary(
        f"Distances from {ev.n} gold points to {args.surface}",
        [
            ("mean", f"{ev.mean:.3f} mm"),
            ("RMS", f"{ev.rms:.3f} mm"),
            ("median", f"{ev.median:.3f} mm"),
            ("95th percentile", f"{ev.p95:.3f} mm"),
            ("max", f"{ev.max:.3f} mm"),
            ("within 0.5 mm", f"{100 * ev.within_0_5:.1f}%"),
            ("within 1 mm", f"{100 * ev.within_1:.1f}%"),
            ("within 2 mm", f"{100 * ev.within_2:.1f}%"),
        ],
    )
    return 0

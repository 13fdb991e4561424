"""``bone-us-recon info SWEEP``: what is in a tracked sweep, without reconstructing it."""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING, Any

from BoneUSRecon.cli.common import (
    SWEEP_HELP,
    ProgressBar,
    add_calibration_option,
    add_common_options,
    add_json_option,
    print_json,
    print_summary,
    read_sweep_args,
)

if TYPE_CHECKING:
    from BoneUSRecon.Logic.sweep import Sweep

__all__ = ["register", "run", "sweep_info"]


def register(subparsers: Any) -> None:
    """Add the ``info`` sub-command."""
    p = subparsers.add_parser(
        "info",
        help="summarise a PLUS sequence file (frames, size, spacing, extent, pose)",
        description="Print the frames, valid frames, image size, pixel spacing, sweep "
        "length, duration, bounds and the transform chain of a PLUS sequence file.",
    )
    p.add_argument("sweep", metavar="SWEEP", help=SWEEP_HELP)
    add_calibration_option(p)
    add_json_option(p)
    add_common_options(p)
    p.set_defaults(func=run)


def sweep_info(sweep: Sweep) -> dict[str, Any]:
    """The facts ``info`` prints, as a JSON-ready dict.

    Parameters
    ----------
    sweep : Sweep

    Returns
    -------
    dict
        ``frames``, ``valid_frames``, ``invalid_frames`` ({frame: reason}), ``width``,
        ``height``, ``spacing_mm`` ([sx, sy]), ``sweep_length_mm``, ``duration_s``,
        ``bounds_mm`` ([xmin, xmax, ymin, ymax, zmin, zmax] of the valid frames'
        image corners in the reference frame), ``transform``, ``source`` and the
        file's pixel type, orientation and compression.
    """
    meta = sweep.metadata
    return {
        "source": str(sweep.source) if sweep.source else None,
        "frames": sweep.n_frames,
        "valid_frames": sweep.n_valid,
        "invalid_frames": {str(k): v for k, v in sorted(sweep.invalid_reasons.items())},
        "width": sweep.width,
        "height": sweep.height,
        "spacing_mm": [float(v) for v in sweep.spacing_mm],
        "sweep_length_mm": sweep.sweep_length_mm(),
        "duration_s": sweep.duration_s(),
        "bounds_mm": [float(v) for v in sweep.bounds_mm()],
        "transform": sweep.transform_name,
        "element_type": meta.get("element_type"),
        "orientation": meta.get("orientation"),
        "compressed": meta.get("compressed"),
    }


def run(args: argparse.Namespace) -> int:
    """Read the sweep and print its summary."""
    with ProgressBar(quiet=args.quiet or args.json) as bar:
        sweep = read_sweep_args(args, bar)
    info = sweep_info(sweep)
    if args.json:
        print_json(info)
        return 0
    b = info["bounds_mm"]
    invalid = info["invalid_frames"]
    rows: list[tuple[str, Any]] = [
        ("frames", info["frames"]),
        ("valid frames", info["valid_frames"]),
        ("width x height", f"{info['width']} x {info['height']} px"),
        ("spacing", f"{info['spacing_mm'][0]:.4g} x {info['spacing_mm'][1]:.4g} mm/px"),
        ("sweep length", f"{info['sweep_length_mm']:.1f} mm"),
        ("duration", f"{info['duration_s']:.2f} s"),
        (
            "bounds",
            f"x {b[0]:.1f}..{b[1]:.1f}, y {b[2]:.1f}..{b[3]:.1f}, z {b[4]:.1f}..{b[5]:.1f} mm",
        ),
        ("transform", info["transform"]),
        (
            "pixels",
            f"{info['element_type']}, {info['orientation']}"
            + (", zlib-compressed" if info["compressed"] else ""),
        ),
    ]
    if invalid:
        first = next(iter(invalid.items()))
        rows.append(("invalid frames", f"{len(invalid)} (e.g. frame {first[0]}: {first[1]})"))
    print_summary(str(sweep.source), rows)
    return 0

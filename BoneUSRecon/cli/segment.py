"""``bone-us-recon segment SWEEP -o POINTS.vtp``: bone contour points of a sweep."""

from __future__ import annotations

import argparse
import dataclasses
from pathlib import Path
from typing import Any

from BoneUSRecon.cli.common import (
    SWEEP_HELP,
    ProgressBar,
    add_bone_point_option,
    add_calibration_option,
    add_common_options,
    add_json_option,
    check_distinct_paths,
    check_sweep_args,
    print_json,
    print_summary,
    print_warnings,
    read_sweep_args,
    removed_on_failure,
)

# Imports nothing more (the segmentation package loads its segmenters lazily): the
# parser's start-up stays light. Re-exported for the tests.
from BoneUSRecon.Logic.segmentation import SEGMENTER_NAMES

__all__ = ["register", "run", "SEGMENTER_NAMES"]


def register(subparsers: Any) -> None:
    """Add the ``segment`` sub-command."""
    p = subparsers.add_parser(
        "segment",
        help="segment the bone contour in every frame and write the kept points",
        description="Segment the bone surface echo in every valid frame, reject "
        "implausible frames (no shadow, jump, no bone), and write the kept points in "
        "reference millimetres with point arrays Frame, Intensity and Confidence.",
    )
    p.add_argument("sweep", metavar="SWEEP", help=SWEEP_HELP)
    p.add_argument(
        "-o",
        "--output",
        required=True,
        metavar="POINTS",
        help="output points (.vtp .vtk with Frame/Intensity/Confidence, .ply, or .csv x,y,z)",
    )
    add_calibration_option(p)
    p.add_argument(
        "--segmenter",
        default="shadowpath",
        choices=SEGMENTER_NAMES,
        help="segmenter (default: shadowpath; 'snake' is the paper's active contour)",
    )
    p.add_argument(
        "--overlay",
        metavar="DIR",
        help="also write PNG overlays of the contours (rejected frames marked) into DIR",
    )
    p.add_argument(
        "--overlay-every",
        type=int,
        default=1,
        metavar="N",
        help="write one accepted frame's overlay in N (rejected frames always; default 1)",
    )
    add_bone_point_option(p)
    add_json_option(p)
    add_common_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Read, segment, write points (and overlays), print a summary."""
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.fileio import check_output_dir, check_output_path
    from BoneUSRecon.Logic.reasons import count_reasons
    from BoneUSRecon.Logic.segmentation import (
        SegmentationParams,
        points_polydata,
        segment_sweep,
    )
    from BoneUSRecon.Logic.vtkio import POINT_OUT_EXTENSIONS, write_points

    # Check everything the user gave before any work.
    check_sweep_args(args)
    check_distinct_paths(
        inputs={"SWEEP": args.sweep, "--calibration": args.calibration},
        outputs={"-o": args.output, "--overlay": args.overlay},
    )
    out = check_output_path(args.output, POINT_OUT_EXTENSIONS)
    if args.overlay:
        check_output_dir(args.overlay, "overlay")
    if args.overlay_every < 1:
        raise BoneUSReconError(f"--overlay-every must be >= 1, got {args.overlay_every}")

    params = dataclasses.replace(SegmentationParams(), method=args.segmenter)
    if args.bone_point:
        rejection = dataclasses.replace(params.rejection, bone_points=args.bone_point)
        params = dataclasses.replace(params, rejection=rejection)
    with ProgressBar(quiet=args.quiet or args.json) as bar:
        sweep = read_sweep_args(args, bar)
        result = segment_sweep(sweep, params, progress=bar)
    overlays = []
    # Two outputs: if the overlays fail (or Ctrl-C), the points file is removed again.
    with removed_on_failure(out, args.overlay):
        write_points(points_polydata(result, sweep), out)
        if args.overlay:
            from BoneUSRecon.Widgets.overlay import write_overlays

            overlays = write_overlays(
                sweep.frames, result.contours, args.overlay, every=args.overlay_every
            )
    summary = result.summary()
    summary.update(
        {
            # Counted by kind (numbers stripped) in one place, whatever the rules' wording.
            "rejection_reasons": count_reasons(result.rejected),
            "output": str(out),
            "rejected_frames": {str(k): v for k, v in result.rejected.items()},
            "segment_s": result.timings.get("segment_s"),
            "frames_per_s": result.timings.get("frames_per_s"),
            "overlays": len(overlays),
        }
    )
    if args.json:
        print_json(summary)
        print_warnings(result.warnings)
        return 0
    rows = [
        ("segmenter", summary["method"]),
        ("frames", summary["frames"]),
        ("accepted", summary["accepted"]),
        ("rejected", summary["rejected"]),
        ("points", summary["points"]),
        ("mean confidence", summary["mean_confidence"]),
        ("frames/s", summary["frames_per_s"]),
        ("output", summary["output"]),
    ]
    for reason, n in summary["rejection_reasons"].items():
        rows.append((f"  rejected: {reason}", n))
    if args.overlay:
        rows.append(("overlays", f"{len(overlays)} PNG in {args.overlay}"))
    print_summary(f"{Path(args.sweep).name}: bone contours", rows)
    print_warnings(result.warnings)
    return 0

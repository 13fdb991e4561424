"""``bone-us-recon reconstruct SWEEP -o SURFACE``: sweep file in, bone surface file out."""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

from BoneUSRecon.cli.common import (
    GOLD_HELP,
    SWEEP_HELP,
    ProgressBar,
    add_bone_point_option,
    add_calibration_option,
    add_common_options,
    add_json_option,
    check_distinct_paths,
    check_sweep_args,
    evaluation_rows,
    print_json,
    print_summary,
    print_warnings,
    read_sweep_args,
    reconstruction_rows,
    removed_on_failure,
)

__all__ = ["register", "run", "add_reconstruction_options", "params_from_args"]


def add_reconstruction_options(p: argparse.ArgumentParser, *, control_points: bool = True) -> None:
    """Stage options shared with ``table`` and ``live``: segmenter, degree, control
    points, rays, fit method, robust weights, axis model, flank extension, bone points."""
    p.add_argument(
        "--segmenter",
        metavar="NAME",
        help="bone segmenter: 'shadowpath' (default, more accurate) or 'snake' (the paper's)",
    )
    p.add_argument(
        "--degree",
        nargs=2,
        type=int,
        metavar=("P", "Q"),
        help="B-spline degrees along and around the bone (default 2 2: quadratic)",
    )
    if control_points:
        # --along/--around, as in ``table``; --control-points E F still works (hidden).
        p.add_argument(
            "--along", type=int, metavar="E", help="control points along the bone (default 15)"
        )
        p.add_argument(
            "--around",
            type=int,
            metavar="F",
            help="control points around the bone (default 6; the paper: 5)",
        )
        p.add_argument(
            "--control-points", nargs=2, type=int, metavar=("E", "F"), help=argparse.SUPPRESS
        )
    p.add_argument(
        "--rays", type=int, metavar="N", help="rays per slice (default 24; the paper: 15)"
    )
    p.add_argument(
        "--fit-method",
        choices=("direct", "separable"),
        help="surface least squares: 'direct' (exact weighted tensor-product, default) or "
        "'separable' (the paper's de Boor column-then-row fits)",
    )
    p.add_argument(
        "--robust",
        choices=("tukey", "huber", "none"),
        help="robust reweighting of the fit (default tukey; 'none' is the paper's plain least squares)",
    )
    p.add_argument(
        "--axis",
        choices=("spline", "line"),
        help="central axis through the slice centres (default spline; 'line' is the paper's)",
    )
    p.add_argument(
        "--flank-extension",
        type=float,
        metavar="MM",
        help="continue each cross-section down its flanks MM past the segmented points "
        "(convex, at most 70 degrees; flagged by the point array 'Extrapolated'; default 0: off)",
    )
    add_bone_point_option(p)


def params_from_args(args: argparse.Namespace) -> Any:
    """Build :class:`ReconstructionParams` from the options (raises on absurd values)."""
    from BoneUSRecon.Logic.pipeline import params_with

    return params_with(
        segmenter=getattr(args, "segmenter", None),
        degree=getattr(args, "degree", None),
        n_control_points=getattr(args, "control_points", None),
        along=getattr(args, "along", None),
        around=getattr(args, "around", None),
        rays=getattr(args, "rays", None),
        fit_method=getattr(args, "fit_method", None),
        robust=getattr(args, "robust", None),
        axis=getattr(args, "axis", None),
        flank_extension_mm=getattr(args, "flank_extension", None),
        bone_points=getattr(args, "bone_point", None),
    )


def register(subparsers: Any) -> None:
    """Add the ``reconstruct`` sub-command."""
    p = subparsers.add_parser(
        "reconstruct",
        help="reconstruct the bone surface from a tracked sweep",
        description="Segment the bone contour in every frame, resample it on rays, fit a "
        "tensor-product B-spline surface and write it as a mesh (.vtp .vtk .stl .ply "
        ".obj, chosen by extension) with a 'Distance' array (mm to the nearest "
        "segmented point).",
    )
    p.add_argument("sweep", metavar="SWEEP", help=SWEEP_HELP)
    p.add_argument("-o", "--output", required=True, metavar="SURFACE", help="output surface file")
    add_calibration_option(p)
    add_reconstruction_options(p)
    p.add_argument(
        "--points-out",
        metavar="POINTS",
        help="also write the segmented points (.vtp .vtk .ply with Frame/Intensity/Confidence, or .csv)",
    )
    p.add_argument("--gold", metavar="GOLD", help=f"{GOLD_HELP}, to evaluate against")
    p.add_argument("--report", metavar="DIR", help="also write an HTML report into this folder")
    from BoneUSRecon.cli.register import add_register_to_options

    add_register_to_options(p)
    add_json_option(p)
    add_common_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Reconstruct and write the surface (and points, report); print the summary."""
    from dataclasses import asdict

    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.fileio import check_output_path
    from BoneUSRecon.Logic.pipeline import reconstruct
    from BoneUSRecon.Logic.vtkio import (
        POINT_OUT_EXTENSIONS,
        SURFACE_EXTENSIONS,
        read_points,
        write_points,
        write_polydata,
    )

    # Everything that can be checked is checked before the (long) work starts.
    check_sweep_args(args)
    check_distinct_paths(
        inputs={"SWEEP": args.sweep, "--calibration": args.calibration, "--gold": args.gold},
        outputs={"-o": args.output, "--points-out": args.points_out},
        output_folders={"--report": args.report},
    )
    out = check_output_path(args.output, SURFACE_EXTENSIONS)
    pts_out = check_output_path(args.points_out, POINT_OUT_EXTENSIONS) if args.points_out else None
    report_dir = None
    if args.report:
        from BoneUSRecon.Widgets.report import check_report_folder

        report_dir = check_report_folder(args.report)
        from BoneUSRecon.Widgets.render import preload_rendering

        preload_rendering()  # a Ctrl-C during the work must not land in VTK's imports
    params = params_from_args(args)
    from BoneUSRecon.cli import register as reg_cli

    inputs = [args.sweep, args.calibration, args.gold]
    transform_out = reg_cli.check_register_to(args, [out, pts_out, report_dir], inputs)
    gold = read_points(args.gold) if args.gold else None

    # Several outputs: if a later one fails (or Ctrl-C), the earlier ones are removed.
    outputs = (out, pts_out, report_dir, transform_out)
    with ProgressBar(quiet=args.quiet or args.json) as bar, removed_on_failure(*outputs):
        recon = reconstruct(read_sweep_args(args, bar), params, progress=bar)
        reg = None
        if transform_out is not None:
            reg = reg_cli.register_reconstruction(args, recon, transform_out)
        evaluation = evaluate_surface(recon.surface, gold) if gold is not None else None
        write_polydata(recon.surface, out)
        if pts_out is not None:
            write_points(recon.points, pts_out)
        report_index = None
        if report_dir is not None:
            from BoneUSRecon.Widgets.report import write_report

            report_index = write_report(
                recon,
                report_dir,
                gold=gold,
                evaluation=evaluation,
                parameters=asdict(params),
                progress=bar,
            )

    s = recon.summary
    if args.json:
        doc: dict[str, Any] = {
            "output": str(out),
            "points_output": str(pts_out) if pts_out else None,
            "report": str(report_index) if report_index else None,
            "summary": s,
            "timings_s": recon.timings,
            "evaluation": evaluation.as_dict() if evaluation is not None else None,
            "registration": reg.as_dict() if reg is not None else None,
        }
        print_json(doc)
        print_warnings(s["warnings"])
        if reg is not None:
            reg_cli.warn_unreliable(reg)
        return 0
    rows: list[tuple[str, Any]] = [
        *reconstruction_rows(s),
        ("resampling distance", f"{s['mean_resampling_distance_mm']:.3f} mm mean"),
        (
            "fit residual",
            f"{s['fit_rms_mm']:.3f} mm RMS ({s['fit_outlier_points']} outlier points)",
        ),
        ("surface", f"{s['surface_triangles']} triangles, {s['surface_area_mm2']:.0f} mm^2"),
        ("time", f"{recon.timings['total']:.2f} s"),
    ]
    if evaluation is not None:
        rows += evaluation_rows(evaluation)
    rows.append(("written", str(out)))
    if pts_out:
        rows.append(("points", str(pts_out)))
    if report_index:
        rows.append(("report", str(report_index)))
    if reg is not None:
        rows += [(f"registration {k}", v) for k, v in reg.summary_rows()]
        rows.append(("transform", str(transform_out)))
    print_summary(f"Reconstructed {Path(args.sweep).name}", rows)
    print_warnings(s["warnings"])
    if reg is not None:
        reg_cli.warn_unreliable(reg)
    return 0

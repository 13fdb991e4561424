"""``bone-us-recon demo [OUTDIR]``: the paper's gold-standard experiment, end to end.

Simulates a clavicle phantom sweep with a few corrupted frames (and its 1145
digitised gold points), reconstructs the bone surface, measures it against the gold
points, computes the Table I curve, and writes everything with an HTML report into
OUTDIR. Needs no input file; about 15 s on two cores.
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path
from typing import Any

from BoneUSRecon.cli.common import (
    ProgressBar,
    add_common_options,
    add_json_option,
    check_distinct_paths,
    evaluation_rows,
    json_default,
    parse_size,
    print_json,
    print_summary,
    print_warnings,
    reconstruction_rows,
    removed_on_failure,
)

__all__ = ["register", "run", "DEFAULT_OUTDIR"]

DEFAULT_OUTDIR = "bone-us-recon-demo"
#: File that marks a folder as written by ``demo``: only such (or empty, or new)
#: folders are written into without ``--force``.
DEMO_MARKER = ".bone-us-recon-demo"
#: The paper's Table I range of mean distances on its clavicle phantom (mm).
PAPER_RANGE_MM = (1.16, 1.71)


def register(subparsers: Any) -> None:
    """Add the ``demo`` sub-command."""
    # The package's constants import nothing: the parser's start-up stays light.
    from BoneUSRecon.Logic.simulation import BONES

    p = subparsers.add_parser(
        "demo",
        help="simulate the paper's clavicle phantom, reconstruct, evaluate, write a report",
        description="Simulate a tracked sweep over a clavicle phantom with a few corrupted "
        "frames and 1145 gold points, reconstruct its upper surface, measure the "
        "distance from the gold points to it, compute the Table I curve (5, 10, 15, 20 "
        "control points) and write the sweep, the surface, the points, the gold points "
        "and an HTML report into OUTDIR.",
    )
    p.add_argument(
        "outdir",
        metavar="OUTDIR",
        nargs="?",
        default=DEFAULT_OUTDIR,
        help=f"output folder, created if needed (default ./{DEFAULT_OUTDIR})",
    )
    p.add_argument(
        "--bone", choices=BONES, default="clavicle", help="simulated bone (default clavicle)"
    )
    p.add_argument(
        "--frames",
        type=int,
        default=150,
        metavar="N",
        help="frames in the sweep (default 150; the paper: 50 to 250)",
    )
    p.add_argument(
        "--size", metavar="WxH", default="320x256", help="image size in pixels (default 320x256)"
    )
    p.add_argument(
        "--spacing",
        type=float,
        default=None,
        metavar="MM",
        help="pixel spacing in mm (default: a 48 x 38 mm field of view)",
    )
    p.add_argument(
        "--corrupted",
        "--corrupt",
        dest="corrupted",
        type=float,
        default=0.05,
        metavar="FRACTION",
        help="fraction of corrupted frames (default 0.05)",
    )
    p.add_argument("--seed", type=int, default=0, metavar="S", help="random seed (default 0)")
    p.add_argument("--report", metavar="DIR", help="report folder (default OUTDIR/report)")
    p.add_argument("--no-report", action="store_true", help="do not write the HTML report")
    p.add_argument(
        "--force",
        action="store_true",
        help="write into OUTDIR even if it holds files the demo did not write "
        "(files named like the demo's outputs are replaced)",
    )
    p.add_argument(
        "--no-table",
        action="store_true",
        help="skip the Table I curve (refits with 5, 10, 15, 20 control points)",
    )
    p.add_argument(
        "--live",
        action="store_true",
        help="instead: replay the sweep over OpenIGTLink on 127.0.0.1 at 30 frames/s "
        "(as 'serve') and reconstruct it live (as 'live'), then compare with offline",
    )
    add_json_option(p)
    add_common_options(p)
    p.set_defaults(func=run)


def check_demo_folder(outdir: Path, force: bool = False) -> None:
    """Refuse an existing folder holding files the demo did not write, unless ``force``.

    The demo writes ``sweep.mha``, ``gold.csv`` and more under fixed names; in a folder
    of someone's own data those would be silently replaced. A new folder, an empty one
    or an earlier demo's (it holds :data:`DEMO_MARKER`) is fine.

    Raises
    ------
    BoneUSReconError
        The folder holds other files and ``force`` is false.
    """
    from BoneUSRecon.Logic.errors import BoneUSReconError

    if force or not outdir.is_dir() or (outdir / DEMO_MARKER).exists():
        return
    if any(outdir.iterdir()):
        raise BoneUSReconError(
            "folder holds files the demo did not write; choose a new or empty folder, "
            "or pass --force to replace the demo's files in it",
            outdir,
        )


def _params(args: argparse.Namespace) -> Any:
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.simulation import SimulationParams, check_params

    w, h = parse_size(args.size, example="320x256")
    # Keep the default 48 x 38 mm field of view when only the pixel count changes.
    spacing = args.spacing if args.spacing is not None else 0.15 * 320 / max(w, 1)
    if not 0.0 <= args.corrupted <= 0.5:
        raise BoneUSReconError(f"--corrupted must be between 0 and 0.5, got {args.corrupted}")
    params = SimulationParams(
        bone=args.bone,
        n_frames=args.frames,
        width=w,
        height=h,
        spacing_mm=spacing,
        corrupted_fraction=args.corrupted,
        seed=args.seed,
    )
    check_params(params)
    return params


def run(args: argparse.Namespace) -> int:
    """Simulate, reconstruct, evaluate, write; print where everything is."""
    if args.live:  # serve + live together (issue 16): see cli/live.py
        from BoneUSRecon.cli.live import run_demo

        return run_demo(args, _params(args))
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.fileio import atomic_path, json_ready
    from BoneUSRecon.Logic.pipeline import ReconstructionParams, control_point_table, reconstruct
    from BoneUSRecon.Logic.simulation import simulate, write_simulation
    from BoneUSRecon.Logic.vtkio import read_points, write_polydata

    t0 = time.perf_counter()
    # Everything checkable is checked before the work starts.
    sim_params = _params(args)
    outdir = Path(args.outdir)
    if outdir.exists() and not outdir.is_dir():
        raise BoneUSReconError("output path exists and is not a folder", outdir)
    check_demo_folder(outdir, force=args.force)
    report_dir = None
    if not args.no_report:
        from BoneUSRecon.Widgets.report import check_report_folder

        report_dir = Path(args.report) if args.report else outdir / "report"
        check_distinct_paths(outputs={"OUTDIR": outdir}, output_folders={"--report": report_dir})
        if report_dir.exists() or report_dir.parent.is_dir():  # else OUTDIR is made below
            check_report_folder(report_dir)
        from BoneUSRecon.Widgets.render import preload_rendering

        preload_rendering()  # a Ctrl-C during the work must not land in VTK's imports
    params = ReconstructionParams()

    # OUTDIR is removed again if this run created it and then fails: no partial output.
    with ProgressBar(quiet=args.quiet or args.json) as bar, removed_on_failure(outdir):
        sim = simulate(sim_params, progress=bar)
        files = write_simulation(sim, outdir, progress=bar)
        (outdir / DEMO_MARKER).write_text("written by bone-us-recon demo\n")
        # Evaluate against the gold points as written (CSV, 1e-6 mm), so that
        # ``bone-us-recon evaluate surface.vtp gold.csv`` gives the very same numbers.
        gold = read_points(files["gold"])
        # The sweep as written: summaries and the report name its file, not "(in memory)".
        recon = reconstruct(sim.sweep.replace(source=files["sweep"]), params, progress=bar)
        evaluation = evaluate_surface(recon.surface, gold)
        table = None if args.no_table else control_point_table(recon, gold, progress=bar)
        files["surface"] = write_polydata(recon.surface, outdir / "surface.vtp")
        files["points"] = write_polydata(recon.points, outdir / "points.vtp")
        doc = {
            "simulation": {
                "bone": sim_params.bone,
                "frames": sim_params.n_frames,
                "corrupted_frames": [int(k) for k in sim.corrupted],
                "seed": sim_params.seed,
            },
            "summary": recon.summary,
            "evaluation": evaluation.as_dict(),
            "table_i": None
            if table is None
            else [{"control_points": int(c), "mean_mm": float(m)} for c, m in table],
            "timings_s": recon.timings,
        }
        with atomic_path(outdir / "evaluation.json") as tmp:
            tmp.write_text(json.dumps(json_ready(doc), indent=2, default=json_default))
        files["evaluation"] = outdir / "evaluation.json"
        if report_dir is not None:
            files["report"] = _write_report(
                recon, report_dir, sim, gold, evaluation, table, sim_params, params, bar
            )
    elapsed = time.perf_counter() - t0

    s, e = recon.summary, evaluation
    paths = {k: str(v) for k, v in files.items()}
    if args.json:
        print_json({**doc, "files": paths, "elapsed_s": elapsed})
        print_warnings(s["warnings"])
        return 0
    n_corrupt = len(sim.corrupted)
    caught = len(
        set(int(k) for k in sim.corrupted)
        & (set(recon.segmentation.rejected) | set(s.get("fit_rejected_frames", [])))
    )
    rows: list[tuple[str, Any]] = [
        (
            "sweep",
            f"{sim_params.n_frames} frames of {sim_params.width}x{sim_params.height} px, "
            f"{n_corrupt} corrupted ({caught} of them rejected)",
        ),
        *reconstruction_rows(s),
        *evaluation_rows(e, f" (paper: {PAPER_RANGE_MM[0]} to {PAPER_RANGE_MM[1]} mm mean)"),
        (
            "not like for like",
            "the paper's phantom was real: its figure includes tracking, "
            "calibration and registration error, which a simulation has not",
        ),
    ]
    if table is not None:
        rows.append(("Table I (e: mean mm)", ", ".join(f"{c}: {m:.3f}" for c, m in table)))
    rows.append(("time", f"{elapsed:.1f} s"))
    labels = {
        "sweep": "sweep (PLUS .mha)",
        "truth": "true bone surface",
        "gold": "gold points",
        "json": "simulation parameters",
        "surface": "reconstructed surface",
        "points": "segmented points",
        "evaluation": "numbers (JSON)",
        "report": "report (open in a browser)",
    }
    rows += [(labels.get(k, k), v) for k, v in paths.items()]
    print_summary(f"Demo: {sim_params.bone} phantom, reconstructed and evaluated", rows)
    print_warnings(s["warnings"])
    return 0


def _write_report(
    recon: Any,
    report_dir: Path,
    sim: Any,
    gold: Any,
    evaluation: Any,
    table: Any,
    sim_params: Any,
    params: Any,
    bar: Any,
) -> Path:
    from dataclasses import asdict

    from BoneUSRecon.Widgets.report import write_report

    parameters = {"simulation": asdict(sim_params), "reconstruction": asdict(params)}
    return write_report(
        recon,
        report_dir,
        gold=gold,
        evaluation=evaluation,
        table=table,
        parameters=parameters,
        progress=bar,
        truth_px=sim.true_contours_px,
        simulated=True,
        title=f"simulated {sim_params.bone} phantom, {sim_params.n_frames} frames, "
        f"seed {sim_params.seed}",
    )

"""``bone-us-recon batch MANIFEST OUTDIR``: reconstruct a cohort of sweeps on Dask."""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import Any

from BoneUSRecon.cli.common import (
    PROG,
    ProgressBar,
    add_common_options,
    add_json_option,
    print_json,
    print_summary,
)

__all__ = ["register", "run", "write_report_for_batch"]

MANIFEST_HELP = (
    "CSV with a header: 'sweep' (required), optional 'name', 'calibration', 'transform', "
    "'gold', 'target', and per-row overrides named as reconstruct's options ('segmenter', "
    "'degree', 'control-points' or 'along'/'around', 'rays', 'fit-method', 'robust', "
    "'axis', 'bone-points'; pairs as '15 5', bone points as 'X Y Z; X Y Z' in the sweep's "
    "reference mm); paths relative to the manifest"
)


def register(subparsers: Any) -> None:
    """Add the ``batch`` sub-command."""
    p = subparsers.add_parser(
        "batch",
        help="reconstruct every sweep of a manifest, in parallel (Dask), resumably",
        description="Reconstruct every sweep listed in MANIFEST, one Dask task per sweep, "
        "on a local cluster (one single-threaded process per core) or on a running "
        "dask.distributed scheduler. Each sweep's surface.vtp, points.vtp and "
        "summary.json go to OUTDIR/NAME/; OUTDIR/summary.csv (and summary.parquet when "
        "pyarrow is installed) has one row per sweep. A failing sweep is recorded and "
        "the others go on. Exit status: 0 all succeeded, 1 some failed, 2 bad manifest "
        "or options, 130 interrupted (finished sweeps are kept).",
    )
    p.add_argument("manifest", metavar="MANIFEST", help=MANIFEST_HELP)
    p.add_argument("outdir", metavar="OUTDIR", help="output folder (created if missing)")
    p.add_argument(
        "--workers",
        type=int,
        metavar="N",
        help="worker processes of the local cluster (default: the machine's cores)",
    )
    p.add_argument(
        "--scheduler",
        metavar="ADDRESS",
        help="use a running dask.distributed scheduler, e.g. tcp://HOST:8786 (its "
        "workers must see the files at the same paths)",
    )
    p.add_argument(
        "--resume",
        action="store_true",
        help="skip sweeps already done (or failed in their own task) with the same parameters "
        "and unchanged inputs",
    )
    p.add_argument(
        "--report", action="store_true", help="also write each sweep's HTML report (NAME/report/)"
    )
    add_json_option(p)
    add_common_options(p)
    p.set_defaults(func=run)


def write_report_for_batch(
    recon: Any, folder: Path, gold: Any, evaluation: Any, parameters: dict[str, Any]
) -> Any:
    """The batch's report writer (runs on the workers; Logic never imports rendering)."""
    from BoneUSRecon.Widgets.report import write_report

    return write_report(recon, folder, gold=gold, evaluation=evaluation, parameters=parameters)


def run(args: argparse.Namespace) -> int:
    """Run the batch; print the summary table; 1 when a sweep failed."""
    from BoneUSRecon.Logic.batch import read_manifest, run_batch, start_worker_server
    from BoneUSRecon.Logic.errors import BoneUSReconError

    if args.workers is not None and args.workers < 1:
        raise BoneUSReconError(f"--workers must be at least 1, got {args.workers}")
    if args.scheduler is not None and args.workers is not None:
        raise BoneUSReconError("--workers is for the local cluster; not with --scheduler")
    if args.scheduler is None and not args.resume:
        start_worker_server(fork_this_process=True)  # one import set for us and the workers
    jobs = read_manifest(args.manifest)
    try:
        with ProgressBar(quiet=args.quiet or args.json) as bar:
            result = run_batch(
                jobs,
                args.outdir,
                workers=args.workers,
                scheduler=args.scheduler,
                resume=args.resume,
                report_writer=write_report_for_batch if args.report else None,
                manifest=args.manifest,
                progress=bar,
            )
    except KeyboardInterrupt:
        print(
            f"\n{PROG}: interrupted; finished sweeps are kept in {args.outdir}, unfinished "
            "ones left nothing (rerun with --resume to go on)",
            file=sys.stderr,
        )
        return 130
    failed = result.failed
    if args.json:
        print_json(
            {
                "outdir": str(Path(args.outdir)),
                "summary_files": [str(p) for p in result.summary_files],
                "sweeps": len(result.rows),
                "ok": len(result.rows) - len(failed),
                "failed": len(failed),
                "resumed": result.resumed,
                "rows": result.rows,
            }
        )
    else:
        ok = [r for r in result.rows if r["status"] == "ok"]
        rows: list[tuple[str, Any]] = [
            (
                "sweeps",
                f"{len(ok)} ok, {len(failed)} failed, {result.resumed} resumed (already done)",
            ),
        ]
        means = [r["mean_mm"] for r in ok if r.get("mean_mm") is not None]
        if means:
            rows.append(
                (
                    "gold distance",
                    f"mean {sum(means) / len(means):.3f} mm over {len(means)} sweeps "
                    f"(worst {max(means):.3f} mm)",
                )
            )
        times = [r["time_total_s"] for r in ok if not r.get("resumed") and r.get("time_total_s")]
        if times:
            rows.append(("time per sweep", f"{sum(times) / len(times):.2f} s mean"))
        rows += [("summary", str(p)) for p in result.summary_files]
        print_summary(f"Batch of {len(result.rows)} sweeps into {args.outdir}", rows)
    for r in failed:
        print(f"{PROG}: failed: {r['name']}: {r['error']}", file=sys.stderr)
    return 1 if failed else 0

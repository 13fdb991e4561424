"""``bone-us-recon simulate BONE OUTDIR``: a phantom sweep with its ground truth."""

from __future__ import annotations

import argparse
from typing import Any

from BoneUSRecon.cli.common import (
    ProgressBar,
    add_common_options,
    add_json_option,
    parse_size,
    print_json,
    print_summary,
    removed_on_failure,
)

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``simulate`` sub-command."""
    # The package's constants import nothing: the parser's start-up stays light (no
    # numpy, scipy, nor the ~9 ms of making the parameter dataclasses).
    from BoneUSRecon.Logic import simulation as names

    d = argparse.Namespace(
        n_frames=names.DEFAULT_FRAMES,
        width=names.DEFAULT_WIDTH,
        height=names.DEFAULT_HEIGHT,
        spacing_mm=names.DEFAULT_SPACING_MM,
        seed=names.DEFAULT_SEED,
    )
    p = subparsers.add_parser(
        "simulate",
        help="simulate a tracked freehand sweep over a bone, with its true surface",
        description="Simulate a tracked freehand ultrasound sweep over a bone and write "
        "OUTDIR/sweep.mha (PLUS sequence, ImageToReferenceTransform per frame), "
        "OUTDIR/truth.vtp (the true bone surface), OUTDIR/gold.csv (digitised points on "
        "the imaged upper surface, with noise) and OUTDIR/simulation.json (parameters, "
        "corrupted frames). Deterministic for a seed.",
    )
    p.add_argument("bone", metavar="BONE", help=f"one of: {', '.join(names.BONES)}")
    p.add_argument("outdir", metavar="OUTDIR", help="output folder (created if missing)")
    p.add_argument(
        "--frames",
        type=int,
        default=d.n_frames,
        metavar="N",
        help=f"number of frames (default {d.n_frames})",
    )
    p.add_argument(
        "--size",
        metavar="WxH",
        default=f"{d.width}x{d.height}",
        help=f"image size in pixels, as in demo and view (default {d.width}x{d.height})",
    )
    # Earlier spellings, still accepted (not shown in --help): they override --size.
    p.add_argument("--width", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument("--height", type=int, default=None, help=argparse.SUPPRESS)
    p.add_argument(
        "--spacing",
        type=float,
        default=d.spacing_mm,
        metavar="MM",
        help=f"pixel spacing in mm (default {d.spacing_mm})",
    )
    p.add_argument(
        "--corrupted",
        "--corrupt",
        dest="corrupt",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="fraction of corrupted frames: clutter in the shadow, false bone-like echo, "
        "loss of probe contact (default 0)",
    )
    p.add_argument(
        "--invalid",
        type=float,
        default=0.0,
        metavar="FRACTION",
        help="fraction of frames flagged as untracked (TransformStatus INVALID; default 0)",
    )
    p.add_argument(
        "--seed", type=int, default=d.seed, metavar="S", help=f"random seed (default {d.seed})"
    )
    p.add_argument("--reverse", action="store_true", help="sweep from the far end back")
    p.add_argument(
        "--realism",
        choices=names.REALISMS,
        default=names.REALISMS[0],
        help="image realism: 'standard' (default) or 'hard', the levels of a real cadaver sweep: "
        "low-contrast bone echo, grey shadow with reverberation, crest-shaped bone, fascia off "
        "the bone, a no-contact skin edge, a vessel, depth 25 -> 5 mm",
    )
    p.add_argument(
        "--hard-conditions",
        dest="hard_conditions",
        metavar="LIST",
        default=",".join(names.HARD_CONDITIONS),
        help="with --realism hard: comma-separated conditions to apply, some of "
        f"{', '.join(names.HARD_CONDITIONS)} (default all)",
    )
    p.add_argument(
        "--bone-free",
        dest="bone_free",
        metavar="FIRST,LAST",
        default="0,0",
        help="frames at the start and at the end of the sweep that show no bone (a sweep "
        "running past the bone's end), e.g. 0,10 (default 0,0)",
    )
    p.add_argument(
        "--no-neighbour",
        dest="neighbour",
        action="store_false",
        help="forearm bones: do not show the other bone (radius/ulna) beside the target "
        "(nor the fibula beside a tibia given --neighbour-mm)",
    )
    p.add_argument(
        "--neighbour-mm",
        type=float,
        default=None,
        metavar="MM",
        help="forearm bones: the other bone's distance from the target, axis to axis "
        "(default 26 mm, mid-shaft; 15-20 toward the wrist, where both show whole); "
        "tibia: show the fibula MM lateral, 15 mm deeper (default: no fibula)",
    )
    add_json_option(p)
    add_common_options(p)
    p.set_defaults(func=run)


def _bone_free(text: str) -> tuple[int, int]:
    """``--bone-free FIRST,LAST``: two frame counts, not negative."""
    from BoneUSRecon.Logic.errors import BoneUSReconError

    try:
        first, last = (int(v) for v in str(text).split(","))
    except ValueError:
        raise BoneUSReconError(
            f"--bone-free must look like FIRST,LAST (two frame counts, e.g. 0,10), got {text!r}"
        ) from None
    if first < 0 or last < 0:
        raise BoneUSReconError(f"--bone-free frame counts must not be negative, got {text!r}")
    return first, last


def run(args: argparse.Namespace) -> int:
    """Simulate, write the files and print where they are."""
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.simulation import (
        HARD_CONDITIONS,
        SimulationParams,
        check_output_dir,
        check_params,
        simulate,
        write_simulation,
    )

    width, height = parse_size(args.size, example="320x256")
    conditions = tuple(c.strip() for c in str(args.hard_conditions).split(",") if c.strip())
    unknown = [c for c in conditions if c not in HARD_CONDITIONS]
    if unknown:
        raise BoneUSReconError(
            f"unknown hard condition {unknown[0]!r}; use some of {', '.join(HARD_CONDITIONS)}"
        )
    params = SimulationParams(
        realism=args.realism,
        hard_conditions=conditions,
        bone=str(args.bone).lower(),
        n_frames=args.frames,
        width=args.width if args.width is not None else width,
        height=args.height if args.height is not None else height,
        spacing_mm=args.spacing,
        corrupted_fraction=args.corrupt,
        invalid_fraction=args.invalid,
        seed=args.seed,
        reverse=args.reverse,
        neighbour=args.neighbour,
        neighbour_mm=args.neighbour_mm,
        bone_free_frames=_bone_free(args.bone_free),
    )
    # Refuse bad input before any work is done or any folder is made.
    check_params(params)
    check_output_dir(args.outdir)
    with ProgressBar(quiet=args.quiet or args.json) as bar, removed_on_failure(args.outdir):
        sim = simulate(params, progress=bar)
        paths = write_simulation(sim, args.outdir, progress=bar)
    sweep = sim.sweep
    info: dict[str, Any] = {
        "bone": params.bone,
        "frames": sweep.n_frames,
        "valid_frames": sweep.n_valid,
        "width": sweep.width,
        "height": sweep.height,
        "spacing_mm": [float(v) for v in sweep.spacing_mm],
        "sweep_length_mm": sweep.sweep_length_mm(),
        "seed": params.seed,
        "realism": params.realism,
        "corrupted_frames": [int(k) for k in sim.corrupted],
        "corruption_kinds": {str(k): v for k, v in sim.corruption_kinds.items()},
        "gold_points": int(sim.gold.shape[0]),
        "files": {k: str(v) for k, v in paths.items()},
    }
    if args.json:
        print_json(info)
        return 0
    print_summary(
        f"Simulated {params.bone} sweep",
        [
            ("frames", f"{sweep.n_frames} ({sweep.n_valid} valid)"),
            ("image", f"{sweep.width} x {sweep.height} pixels"),
            ("spacing (mm)", info["spacing_mm"]),
            ("sweep length (mm)", info["sweep_length_mm"]),
            (
                "corrupted frames",
                ", ".join(f"{k} ({v})" for k, v in sim.corruption_kinds.items()) or "none",
            ),
            ("seed", params.seed),
            (
                "realism",
                params.realism
                if params.realism == "standard"
                else f"hard ({', '.join(params.hard_conditions)})",
            ),
            ("sweep", paths["sweep"]),
            ("true surface", paths["truth"]),
            ("gold points", f"{paths['gold']} ({info['gold_points']} points)"),
            ("parameters", paths["json"]),
        ],
    )
    return 0

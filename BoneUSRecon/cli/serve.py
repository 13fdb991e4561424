"""``bone-us-recon serve SWEEP --port P``: replay a recorded sweep as a PLUS server would.

For demos, tests and users without hardware: ``bone-us-recon live`` (or Slicer's
OpenIGTLinkIF) connects to it as to a PlusServer.
"""

from __future__ import annotations

import argparse
import sys
from typing import Any

from BoneUSRecon.cli.common import (
    SWEEP_HELP,
    add_calibration_option,
    add_common_options,
    check_sweep_args,
    print_summary,
    read_sweep_args,
)

__all__ = ["register", "run"]


def register(subparsers: Any) -> None:
    """Add the ``serve`` sub-command."""
    from BoneUSRecon.cli.live import DEFAULT_PORT

    p = subparsers.add_parser(
        "serve",
        help="replay a recorded sweep over OpenIGTLink, as a PLUS server",
        description="Stream the frames of a sweep over OpenIGTLink at a given rate: "
        "IMAGE messages carrying their ImageToReference matrix (--mode image, the "
        "default), IMAGE plus an ImageToReference TRANSFORM (--mode transform), or, with "
        "--calibration, IMAGE plus ProbeToTracker and ReferenceToTracker TRANSFORMs as "
        "PlusServer sends them (--mode plus). Streaming starts when a client connects.",
    )
    p.add_argument("sweep", metavar="SWEEP", help=SWEEP_HELP)
    p.add_argument(
        "--host",
        default="127.0.0.1",
        help="address to listen on (default 127.0.0.1; 0.0.0.0 for every interface)",
    )
    p.add_argument("--port", type=int, default=DEFAULT_PORT, help=f"port (default {DEFAULT_PORT})")
    p.add_argument(
        "--fps",
        type=float,
        metavar="F",
        help="frames per second (default: the sweep's own rate, else 30)",
    )
    p.add_argument(
        "--loop", action="store_true", help="start again after the last frame (until Ctrl-C)"
    )
    p.add_argument(
        "--mode",
        choices=("image", "transform", "plus"),
        help="how poses are sent (default: plus with --calibration, else image)",
    )
    add_calibration_option(p)
    for action in p._actions:  # same options as the readers', one more use worth saying
        if action.dest == "calibration":
            action.help = (
                "PLUS device-set XML with the ImageToProbe calibration: reads the sweep when it "
                "has no ImageToReference, and sends ProbeToTracker and ReferenceToTracker as "
                "PlusServer does (--mode plus, the default with it)"
            )
    add_common_options(p)
    p.set_defaults(func=run)


def run(args: argparse.Namespace) -> int:
    """Serve until the sweep is done (or Ctrl-C with --loop)."""
    from BoneUSRecon.cli.igtl import SweepServer
    from BoneUSRecon.Logic.errors import BoneUSReconError
    from BoneUSRecon.Logic.sequence_io import read_calibration

    check_sweep_args(args)
    if not 0 <= args.port < 65536:
        raise BoneUSReconError(f"--port must be in 0..65535, got {args.port}")
    mode = args.mode or ("plus" if args.calibration else "image")
    if mode == "plus" and not args.calibration:
        raise BoneUSReconError(
            "--mode plus needs --calibration XML (the ImageToProbe it sends ProbeToTracker for)"
        )
    calibration = read_calibration(args.calibration) if args.calibration else None
    sweep = read_sweep_args(args)
    server = SweepServer(
        sweep,
        args.host,
        args.port,
        fps=args.fps,
        loop=args.loop,
        mode=mode,
        calibration=calibration,
    )
    # One line naming the real port (useful with --port 0), flushed: scripts wait for it.
    print(
        f"serve: {sweep.n_frames} frames of {sweep.width}x{sweep.height} at {server.fps:g} "
        f"frames/s on {server.host}:{server.port} ({mode} mode){', looping' if args.loop else ''}; "
        "Ctrl-C stops",
        file=sys.stderr,
        flush=True,
    )
    interrupted = False
    try:
        sent = server.serve()
    except KeyboardInterrupt:
        interrupted = True
        sent = server.sent
    finally:
        server.close()
    if not args.quiet:
        print_summary(
            f"Served {args.sweep}",
            [("frames sent", sent), ("end", "stopped (Ctrl-C)" if interrupted else "sweep done")],
        )
    return 0

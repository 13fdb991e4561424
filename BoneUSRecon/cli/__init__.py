"""The ``bone-us-recon`` command line: a thin shell over :mod:`BoneUSRecon.Logic`.

Each sub-command lives in its own module of this package and exposes
``register(subparsers)``, which adds its parser and sets ``func`` to a function
``run(args) -> int``. :func:`main` provides what every command shares: ``--quiet``,
``--debug``, one-line errors with exit status 2, and clean interruption.
"""

from __future__ import annotations

import argparse
import importlib
import sys
from collections.abc import Sequence
from typing import NoReturn

from BoneUSRecon import __version__
from BoneUSRecon.cli.common import PROG, plain_bone_point_numbers, run_guarded

__all__ = ["main", "entry_point", "build_parser"]

# Order is the order shown in --help.
COMMANDS = (
    "demo",
    "info",
    "simulate",
    "segment",
    "reconstruct",
    "evaluate",
    "register",
    "table",
    "batch",
    "view",
    "serve",
    "live",
)


class _Parser(argparse.ArgumentParser):
    """argparse with our one-line error style: no usage block (it is in ``--help``).

    Sub-parsers are made of the same class, so every command gets it.
    """

    def error(self, message: str) -> NoReturn:
        self.exit(2, f"{self.prog}: error: {' '.join(message.split())} (see {self.prog} --help)\n")


def build_parser() -> argparse.ArgumentParser:
    """The full argument parser (all sub-commands)."""
    parser = _Parser(
        prog="bone-us-recon",
        description="Bone surface reconstruction from tracked freehand ultrasound.",
    )
    parser.add_argument("--version", action="version", version=f"%(prog)s {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND")
    sub.required = True
    for name in COMMANDS:
        try:
            module = importlib.import_module(f"BoneUSRecon.cli.{name}")
        except ModuleNotFoundError as exc:  # command not built in this checkout
            if exc.name == f"BoneUSRecon.cli.{name}":
                continue
            raise
        module.register(sub)
    return parser


def main(argv: Sequence[str] | None = None) -> int:
    """Run the command line; returns the exit status (0 ok, 2 bad input, 130 interrupted)."""
    try:
        parser = build_parser()  # imports the commands: Ctrl-C may land here too
    except KeyboardInterrupt:
        print(f"\n{PROG}: interrupted; no output was written", file=sys.stderr)
        return 130
    args = parser.parse_args(plain_bone_point_numbers(sys.argv[1:] if argv is None else argv))
    return run_guarded(args.func, args)


def entry_point() -> None:
    """The ``bone-us-recon`` executable: :func:`main`, then exit with its status.

    After an interrupt the outputs are already removed and the message printed, so
    the process leaves at once (``os._exit``) instead of running the interpreter's
    finalisation, where a second Ctrl-C (or one still pending from a worker thread)
    would end it by SIGINT (status -2) instead of the promised 130.
    """
    status = main()
    if status == 130:
        import os

        for stream in (sys.stdout, sys.stderr):
            try:
                stream.flush()
            except (OSError, ValueError):
                pass
        os._exit(130)
    sys.exit(status)


if __name__ == "__main__":  # pragma: no cover
    entry_point()

"""What every sub-command shares: options, error style, progress bar, summaries.

Error contract: a problem with the user's input is one line on stderr,
``bone-us-recon: error: <file>: <problem>``, exit status 2, no traceback and no
output file (writers go through :func:`BoneUSRecon.Logic.fileio.atomic_path`).
Ctrl-C prints ``bone-us-recon: interrupted`` and exits with 130.
"""

from __future__ import annotations

import argparse
import contextlib
import decimal
import json
import math
import os
import shutil
import signal
import sys
import threading
import traceback
from collections.abc import Callable, Iterable, Iterator, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any

from BoneUSRecon.Logic.errors import BoneUSReconError

# The one check that no output overwrites an input or another output: every command
# that writes calls it (re-exported here so commands import it with their other helpers).
from BoneUSRecon.Logic.fileio import check_distinct_paths
from BoneUSRecon.Logic.progress import ProgressCallback

if TYPE_CHECKING:  # the CLI's start-up must not import numpy/VTK
    from BoneUSRecon.Logic.sweep import Sweep

__all__ = [
    "PROG",
    "GOLD_HELP",
    "SURFACE_HELP",
    "SWEEP_HELP",
    "add_common_options",
    "add_calibration_option",
    "add_json_option",
    "check_sweep_args",
    "check_distinct_paths",
    "read_sweep_args",
    "with_option_names",
    "parse_size",
    "error",
    "notice",
    "run_guarded",
    "ProgressBar",
    "print_summary",
    "print_json",
    "json_default",
    "reconstruction_rows",
    "evaluation_rows",
    "removed_on_failure",
]

PROG = "bone-us-recon"

#: Help texts of the inputs several commands take, worded once.
GOLD_HELP = "gold-standard points: CSV x,y,z (mm) or a VTK point file"
SURFACE_HELP = "surface file (.vtp .vtk .stl .ply .obj)"
SWEEP_HELP = "PLUS sequence file (.mha or .mhd)"


def add_common_options(parser: argparse.ArgumentParser) -> None:
    """``--quiet`` and ``--debug``, on every sub-command."""
    parser.add_argument("-q", "--quiet", action="store_true", help="no progress bar on stderr")
    parser.add_argument("--debug", action="store_true", help="show a traceback on internal errors")


def add_calibration_option(parser: argparse.ArgumentParser) -> None:
    """``--calibration XML`` and ``--transform NAME`` for commands that read a sweep."""
    parser.add_argument(
        "--calibration",
        metavar="XML",
        help="PLUS device-set XML holding the ImageToProbe calibration "
        "(needed when the sweep has no ImageToReference transform)",
    )
    parser.add_argument(
        "--transform",
        metavar="NAME",
        help="name of the per-frame pose to use, e.g. ImageToReference or "
        "ProbeToTracker (default: ImageToReference when present)",
    )


def _finite_mm(text: str) -> float:
    """A coordinate of ``--bone-point``: a finite number (argparse names the option)."""
    try:
        value = float(text)
    except ValueError:
        value = float("nan")
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not a finite number of mm")
    return value


def add_bone_point_option(parser: argparse.ArgumentParser) -> None:
    """``--bone-point X Y Z`` (repeatable), for commands that segment."""
    parser.add_argument(
        "--bone-point",
        nargs=3,
        type=_finite_mm,
        action="append",
        metavar=("X", "Y", "Z"),
        help="a point on the bone to follow, in the sweep's reference mm (e.g. a markup "
        "placed on it in Slicer); where two bones are in view the track follows the one "
        "through it (repeatable; points on one bone)",
    )


def plain_bone_point_numbers(argv: Sequence[str]) -> list[str]:
    """``argv`` with the three values after each ``--bone-point`` written out in plain
    decimals where they are finite numbers in exponent form (``-1e3`` -> ``-1000``).

    argparse takes a word starting with ``-`` for an option unless it reads as a plain
    negative number, so ``--bone-point 1 2 -1e3`` stopped with "expected 3 arguments";
    a coordinate a user pastes from another tool may well be written so. Anything else
    (a word, ``-inf``) is left for the option's own check to name.
    """
    out = list(argv)
    for i, word in enumerate(out):
        if word != "--bone-point":
            continue
        for j in range(i + 1, min(i + 4, len(out))):
            try:
                value = decimal.Decimal(out[j])
            except decimal.InvalidOperation:
                continue
            if value.is_finite() and out[j].startswith("-"):
                out[j] = format(value, "f")
    return out


def print_warnings(warnings: Iterable[str]) -> None:
    """One stderr line per warning of a result (e.g. a bone point the track missed)."""
    for text in warnings:
        print(f"{PROG}: warning: {text}", file=sys.stderr)


def add_json_option(parser: argparse.ArgumentParser) -> None:
    """``--json``: print one JSON object (see :func:`print_json`) instead of the summary."""
    parser.add_argument(
        "--json", action="store_true", help="print one JSON object instead of the summary"
    )


def check_sweep_args(args: argparse.Namespace) -> None:
    """Check, before any work, that ``args.sweep`` and ``--calibration`` are readable files."""
    from BoneUSRecon.Logic.fileio import check_input_file

    check_input_file(args.sweep)
    if getattr(args, "calibration", None):
        check_input_file(args.calibration)


def read_sweep_args(args: argparse.Namespace, progress: ProgressCallback | None = None) -> Sweep:
    """Read ``args.sweep`` with the pose chosen by ``--calibration`` and ``--transform``.

    Parameters
    ----------
    args : argparse.Namespace
        Parsed options of a command that called :func:`add_calibration_option`.
    progress : ProgressCallback, optional
        Reading progress.

    Returns
    -------
    Sweep
    """
    from BoneUSRecon.Logic.sequence_io import read_sweep

    with with_option_names({"calibration": "--calibration XML", "transform": "--transform"}):
        sweep = read_sweep(
            args.sweep, calibration=args.calibration, transform=args.transform, progress=progress
        )
    if args.calibration and "ImageToProbe" not in (sweep.transform_name or ""):
        notice(
            f"{args.calibration}: --calibration not used: the sweep's own "
            f"{sweep.transform_name} poses already map pixels to millimetres"
        )
    return sweep


@contextlib.contextmanager
def with_option_names(options: dict[str, str]) -> Iterator[None]:
    """Add the command-line option to Logic errors about one of its arguments.

    Logic messages speak of files and values (the Slicer module shows them too); an
    error whose :attr:`~BoneUSRecon.Logic.errors.BoneUSReconError.parameter` is a key
    of ``options`` is raised again with that option named at the end.

    Parameters
    ----------
    options : dict
        Logic argument name -> option as the user types it, e.g.
        ``{"calibration": "--calibration XML"}``.

    Examples
    --------
    >>> with with_option_names({"transform": "--transform"}):
    ...     raise BoneUSReconError("the pose 'X' is not a transform name", "s.mha",
    ...                            parameter="transform")
    Traceback (most recent call last):
    ...
    BoneUSRecon.Logic.errors.BoneUSReconError: s.mha: the pose 'X' is not a transform name (--transform)
    """
    try:
        yield
    except BoneUSReconError as exc:
        flag = options.get(exc.parameter or "")
        if flag is None:
            raise
        raise BoneUSReconError(
            f"{exc.message} ({flag})", exc.path, parameter=exc.parameter
        ) from None


def notice(message: str) -> None:
    """Print a one-line note on stderr (something the user asked for was not done)."""
    print(f"{PROG}: note: {' '.join(str(message).split())}", file=sys.stderr)


def parse_size(text: str, option: str = "--size", example: str = "1100x700") -> tuple[int, int]:
    """Parse a ``WxH`` size option into ``(width, height)`` pixels.

    Parameters
    ----------
    text : str
        The option's value, e.g. ``"1100x700"`` (``X`` works too).
    option, example : str
        The option's name and an example value, for the error message.

    Raises
    ------
    BoneUSReconError
        Not two integers joined by ``x``.
    """
    from BoneUSRecon.Logic.errors import BoneUSReconError

    try:
        w, h = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise BoneUSReconError(f"{option} must look like {example}, got {text!r}") from None
    return w, h


def error(message: str) -> int:
    """Print a one-line error and return exit status 2."""
    print(f"{PROG}: error: {' '.join(str(message).split())}", file=sys.stderr)
    return 2


class _SigintSeen:
    """SIGINT handler that remembers it fired, then raises KeyboardInterrupt as usual.

    Some extension modules replace an exception raised inside them by their own: VTK's
    compiled modules report a KeyboardInterrupt that lands while they import as
    ``ImportError: Failed to load vtk...``. Knowing that Ctrl-C was pressed, the
    command reports the interruption whatever exception it arrives as. Once it has
    fired, errors in finalizers ("Exception ignored in: ...", e.g. a pyvista Plotter
    whose construction the interrupt cut short) are silenced: they are consequences of
    the interruption, and the one-line message already says what happened.
    """

    def __init__(self) -> None:
        self.fired = False

    def __call__(self, signum: int, frame: object) -> None:
        self.fired = True
        sys.unraisablehook = _ignore_unraisable
        raise KeyboardInterrupt


def _ignore_unraisable(unraisable: object) -> None:
    """``sys.unraisablehook`` after Ctrl-C (see :class:`_SigintSeen`)."""


def _interrupted() -> int:
    print(f"\n{PROG}: interrupted; no output was written", file=sys.stderr)
    return 130


def run_guarded(func: Callable[[argparse.Namespace], int], args: argparse.Namespace) -> int:
    """Run a sub-command, turning every failure into a one-line message and a status.

    Ctrl-C gives exit status 130 even when it surfaces as another exception (see
    :class:`_SigintSeen`).
    """
    sigint = _SigintSeen()
    previous = None
    # Only in the main thread and over Python's default handler (not over a caller's).
    if (
        threading.current_thread() is threading.main_thread()
        and signal.getsignal(signal.SIGINT) is signal.default_int_handler
    ):
        previous = signal.signal(signal.SIGINT, sigint)
    try:
        return int(func(args) or 0)
    except KeyboardInterrupt:
        return _interrupted()
    except BaseException as exc:
        if sigint.fired:
            return _interrupted()
        if isinstance(exc, BoneUSReconError):
            return error(str(exc))
        if isinstance(exc, (OSError, MemoryError)):
            name = getattr(exc, "filename", None)
            msg = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
            return error(f"{name}: {msg}" if name else msg)
        if not isinstance(exc, Exception):  # SystemExit and the like pass through
            raise
        # An internal bug: still one line unless --debug.
        if getattr(args, "debug", False):
            traceback.print_exc()
        else:
            print(
                f"{PROG}: internal error: {type(exc).__name__}: {' '.join(str(exc).split())} "
                "(run with --debug for a traceback)",
                file=sys.stderr,
            )
        return 1
    finally:
        if previous is not None:
            signal.signal(signal.SIGINT, previous)


def _state(p: Path) -> tuple[int, int, int] | None:
    try:
        st = os.stat(p)
    except OSError:
        return None
    return (st.st_ino, st.st_mtime_ns, st.st_size)


@contextlib.contextmanager
def removed_on_failure(*paths: str | os.PathLike[str] | None) -> Iterator[None]:
    """Undo a command's outputs if it fails or is interrupted part-way.

    Each file is written atomically, but a command with several outputs (surface,
    points, report; or a folder of files) can be stopped between two of them. Then
    the files this run wrote are removed, and the folders it created, so that "no
    output was written" holds. Folders that existed before are left alone, and so are
    files this run had not yet replaced. ``None`` entries are ignored.
    """
    items = [Path(p) for p in paths if p is not None]
    before = {p: _state(p) for p in items}
    try:
        yield
    except BaseException:
        for p in items:
            now = _state(p)
            if now is None or now == before[p]:
                continue
            if p.is_dir():
                if before[p] is None:
                    shutil.rmtree(p, ignore_errors=True)
            else:
                with contextlib.suppress(OSError):
                    p.unlink()
        raise


class ProgressBar:
    """A :data:`ProgressCallback` drawing one tqdm bar per stage on stderr.

    Use as a context manager; ``quiet=True`` makes it silent. By default the bar is
    drawn only when stderr is a terminal, so logs and pipes get the one-line summary
    and errors without carriage-return clutter; ``force=True`` draws it anyway.
    """

    def __init__(self, quiet: bool = False, *, force: bool = False) -> None:
        self.quiet = quiet or not (force or sys.stderr.isatty())
        self._bar: Any = None
        self._stage: str | None = None

    def __call__(self, stage: str, done: int, total: int) -> None:
        if self.quiet:
            return
        from tqdm import tqdm

        if stage != self._stage or self._bar is None:
            self.close()
            self._stage = stage
            self._bar = tqdm(
                total=total, desc=stage, file=sys.stderr, leave=False, unit="", dynamic_ncols=True
            )
        self._bar.total = total
        self._bar.n = done
        self._bar.refresh()

    def close(self) -> None:
        if self._bar is not None:
            self._bar.close()
            self._bar = None
            self._stage = None

    def __enter__(self) -> ProgressCallback:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _fmt(value: Any) -> str:
    if isinstance(value, float):
        return f"{value:.4g}"
    if isinstance(value, (list, tuple)):
        return " ".join(_fmt(v) for v in value)
    return str(value)


def print_summary(title: str, rows: Iterable[tuple[str, Any]]) -> None:
    """Print ``title`` then aligned ``key: value`` lines on stdout."""
    rows = list(rows)
    # Keys align up to a width; a longer one (e.g. a long rejection reason) just
    # pushes its own value, instead of padding every line of the summary.
    width = min(max((len(k) for k, _ in rows), default=0), 26)
    print(title)
    for key, value in rows:
        print(f"  {key:<{width}} : {_fmt(value)}")


def reconstruction_rows(summary: dict[str, Any]) -> list[tuple[str, Any]]:
    """Summary rows on frames and grid of a :attr:`Reconstruction.summary` (reconstruct, demo)."""
    s = summary
    return [
        (
            "frames used",
            f"{s['segmented_frames']} of {s['valid_frames']} valid ({s['frames']} in file)",
        ),
        (
            "frames rejected",
            f"{s['rejected_frames']} by segmentation, "
            f"{len(s['fit_rejected_frames'])} by the robust fit",
        ),
        (
            "grid",
            f"{s['grid_shape'][0]} slices x {s['grid_shape'][1]} rays, "
            f"{100 * s['grid_coverage']:.1f}% covered",
        ),
    ]


def evaluation_rows(ev: Any, paper_note: str = "") -> list[tuple[str, Any]]:
    """Summary rows of an :class:`~BoneUSRecon.Logic.evaluation.Evaluation` (reconstruct, demo)."""
    return [
        ("gold points", ev.n),
        ("distance mean/RMS", f"{ev.mean:.3f} / {ev.rms:.3f} mm{paper_note}"),
        ("distance median/p95/max", f"{ev.median:.3f} / {ev.p95:.3f} / {ev.max:.3f} mm"),
        (
            "within 0.5/1/2 mm",
            f"{100 * ev.within_0_5:.1f}% / {100 * ev.within_1:.1f}% / {100 * ev.within_2:.1f}%",
        ),
    ]


def json_default(o: Any) -> Any:
    """``json.dumps(default=...)`` for numpy arrays and scalars; anything else as text."""
    import numpy as np

    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    return str(o)


def print_json(obj: Any) -> None:
    """Print ``obj`` as one JSON document on stdout (numpy values converted, floats
    rounded to 12 significant digits by :func:`~BoneUSRecon.Logic.fileio.json_ready`)."""
    from BoneUSRecon.Logic.fileio import json_ready

    print(json.dumps(json_ready(obj), default=json_default, indent=2))

"""Progress reporting through a plain callback (no Qt, no terminal assumptions).

Long-running Logic functions accept ``progress: ProgressCallback | None`` and call it
as ``progress(stage, done, total)``; the CLI turns that into a bar on stderr, the
Slicer module into its progress dialog.
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["ProgressCallback", "report", "Cancelled", "cancellable"]

ProgressCallback = Callable[[str, int, int], None]


class Cancelled(Exception):  # noqa: N818 (a request, not an error)
    """The user asked to stop: raised by a progress callback to unwind the work.

    Not an error (it is no :class:`~BoneUSRecon.Logic.errors.BoneUSReconError`):
    callers catch it and report "cancelled", never "failed". Logic functions leave no
    output behind when it passes through them, as with any exception.
    """


def cancellable(
    should_stop: Callable[[], bool], progress: ProgressCallback | None = None
) -> ProgressCallback:
    """A progress callback that polls ``should_stop()`` and raises :class:`Cancelled`.

    The Slicer module's Cancel button only sets a flag; the Logic checks it at every
    progress report (every frame, every stage), so the work stops within one step.

    Examples
    --------
    >>> stop = []
    >>> cb = cancellable(lambda: bool(stop))
    >>> cb("segment", 1, 10)
    >>> stop.append(True)
    >>> cb("segment", 2, 10)
    Traceback (most recent call last):
    ...
    BoneUSRecon.Logic.progress.Cancelled: cancelled during segment (2 of 10)
    """

    def callback(stage: str, done: int, total: int) -> None:
        if should_stop():
            raise Cancelled(f"cancelled during {stage} ({done} of {total})")
        if progress is not None:
            progress(stage, done, total)

    return callback


def report(progress: ProgressCallback | None, stage: str, done: int, total: int) -> None:
    """Call ``progress`` if one was given.

    Parameters
    ----------
    progress : ProgressCallback or None
        The caller's callback; ``None`` makes this a no-op.
    stage : str
        Stage name (``"segment"``, ``"fit"``, ...).
    done, total : int
        Work done so far and in all, in the stage's own units (frames, steps).
    """
    if progress is not None:
        progress(stage, done, total)

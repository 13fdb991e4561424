"""Progress reporting through a plain callback (no Qt, no terminal assumptions).

Long-running Logic functions accept ``progress: ProgressCallback | None`` and call it
as ``progress(stage, done, total)``; the CLI turns that into a bar on stderr, the
Slicer module into its progress dialog.
"""

from __future__ import annotations

from collections.abc import Callable

__all__ = ["ProgressCallback", "report"]

ProgressCallback = Callable[[str, int, int], None]


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

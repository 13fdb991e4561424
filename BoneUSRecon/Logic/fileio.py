"""Atomic output files and output-path checks shared by every writer.

Outputs are written to a temporary file in the destination folder and renamed into
place (``os.replace`` is atomic on POSIX and Windows), so a crash, an error or Ctrl-C
never leaves a half-written file under the user's chosen name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Iterator
from pathlib import Path

from BoneUSRecon.Logic.errors import BoneUSReconError

__all__ = ["atomic_path", "check_output_path", "check_input_file"]


def check_input_file(path: str | os.PathLike[str]) -> Path:
    """Return ``path`` as a Path if it is an existing, non-empty regular file.

    Raises
    ------
    BoneUSReconError
        If the file is missing, a directory, or empty.
    """
    p = Path(path)
    if not p.exists():
        raise BoneUSReconError("no such file", p)
    if p.is_dir():
        raise BoneUSReconError("is a directory, expected a file", p)
    if p.stat().st_size == 0:
        raise BoneUSReconError("file is empty", p)
    return p


def check_output_path(
    path: str | os.PathLike[str], extensions: Iterable[str] | None = None
) -> Path:
    """Check, before any work is done, that ``path`` can be written.

    Parameters
    ----------
    path : path-like
        The output file.
    extensions : iterable of str, optional
        Allowed suffixes (lower case, with the dot, e.g. ``".vtp"``).

    Raises
    ------
    BoneUSReconError
        Unknown extension, missing folder, or a folder that cannot be written.
    """
    p = Path(path)
    if extensions is not None:
        allowed = sorted(set(extensions))
        if p.suffix.lower() not in allowed:
            raise BoneUSReconError(
                f"unknown output extension {p.suffix or '(none)'!r}; use one of {', '.join(allowed)}",
                p,
            )
    parent = p.parent if str(p.parent) else Path(".")
    if not parent.is_dir():
        raise BoneUSReconError(f"output folder {str(parent)!r} does not exist", p)
    # Probe by creating a file: os.access() says yes to root on read-only mounts.
    try:
        with tempfile.TemporaryFile(dir=parent):
            pass
    except OSError:
        raise BoneUSReconError(f"output folder {str(parent)!r} is not writable", p) from None
    if p.is_dir():
        raise BoneUSReconError("output path is a directory", p)
    return p


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Yield a temporary path beside ``path``; move it onto ``path`` on success.

    The temporary file keeps ``path``'s suffix so that writers choosing a format by
    extension (VTK, Pillow) behave the same. On any exception (including
    KeyboardInterrupt) the temporary file is removed and ``path`` is untouched.

    Examples
    --------
    >>> import tempfile, pathlib
    >>> d = pathlib.Path(tempfile.mkdtemp())
    >>> with atomic_path(d / "a.txt") as tmp:
    ...     _ = tmp.write_text("hello")
    >>> (d / "a.txt").read_text()
    'hello'
    """
    p = Path(path)
    parent = p.parent if str(p.parent) else Path(".")
    fd, tmp_name = tempfile.mkstemp(prefix=f".{p.stem}.", suffix=f".part{p.suffix}", dir=parent)
    os.close(fd)
    tmp = Path(tmp_name)
    try:
        yield tmp
        if not tmp.exists() or tmp.stat().st_size == 0:
            raise BoneUSReconError("writer produced no data", p)
        # mkstemp creates 0600 files; give the result the usual umask-based mode.
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o666 & ~umask)
        os.replace(tmp, p)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            tmp.unlink()
        raise

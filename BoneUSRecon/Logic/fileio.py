"""Atomic output files and output-path checks shared by every writer.

Outputs are written to a temporary file in the destination folder and renamed into
place (``os.replace`` is atomic on POSIX and Windows), so a crash, an error or Ctrl-C
never leaves a half-written file under the user's chosen name.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterable, Iterator, Mapping
from pathlib import Path

from BoneUSRecon.Logic.errors import BoneUSReconError

__all__ = [
    "atomic_path",
    "check_output_path",
    "check_output_dir",
    "check_writable_folder",
    "check_input_file",
    "can_create_file_in",
    "check_distinct_paths",
    "json_ready",
]

#: What :func:`check_distinct_paths` takes: ``{label: path}`` (``None`` paths are
#: skipped) or plain paths (then the path is its own label).
PathsArg = Mapping[str, "str | os.PathLike[str] | None"] | Iterable["str | os.PathLike[str] | None"]


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
    check_writable_folder(p.parent if str(p.parent) else Path("."), p, label="output folder")
    if p.is_dir():
        raise BoneUSReconError("output path is a directory", p)
    return p


def check_writable_folder(
    folder: str | os.PathLike[str], subject: str | os.PathLike[str], *, label: str = "folder"
) -> None:
    """Check that ``folder`` exists and that files can be created in it.

    Parameters
    ----------
    folder : path-like
        The folder that will receive the output.
    subject : path-like
        The output the user named; errors name it.
    label : str
        How the message calls ``folder`` (e.g. ``"output folder"``).

    Raises
    ------
    BoneUSReconError
        The folder is missing or not writable.
    """
    f = Path(folder)
    if not f.is_dir():
        raise BoneUSReconError(f"{label} {str(f)!r} does not exist", subject)
    if not can_create_file_in(f):
        raise BoneUSReconError(f"{label} {str(f)!r} is not writable", subject)


def can_create_file_in(folder: str | os.PathLike[str]) -> bool:
    """Whether a file can be created in the existing folder ``folder``.

    Probes by creating (and removing) a temporary file: ``os.access()`` says yes to
    root on read-only mounts.
    """
    try:
        with tempfile.TemporaryFile(dir=folder):
            pass
    except OSError:
        return False
    return True


def check_output_dir(path: str | os.PathLike[str], what: str = "output") -> Path:
    """Check, before any work, that the folder ``path`` can be written or created.

    The folder may exist (files are written into it) or not (its parent must exist).

    Parameters
    ----------
    path : path-like
        The output folder.
    what : str
        What the folder is for, used in the message (``"report"``, ``"overlay"``).

    Raises
    ------
    BoneUSReconError
        A file is in the way, or the folder (or its missing parent) cannot be written.
    """
    d = Path(path)
    if d.exists() and not d.is_dir():
        raise BoneUSReconError(f"{what} path exists and is not a folder", d)
    check_writable_folder(d if d.is_dir() else (d.parent if str(d.parent) else Path(".")), d)
    return d


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


def json_ready(obj: object, digits: int = 12) -> object:
    """``obj`` with numpy values made plain and floats rounded to ``digits`` significant digits.

    Binary floating point prints 0.15 computed as 3 * 0.05 as ``0.15000000000000002``;
    12 significant digits keep every measured value (a 1e-12 relative change is far
    below any pixel, pose or distance error) and print it as people write it.

    Examples
    --------
    >>> json_ready({"spacing_mm": [3 * 0.05, 0.1 + 0.2], "n": 3})
    {'spacing_mm': [0.15, 0.3], 'n': 3}
    """
    import math

    if isinstance(obj, dict):
        return {
            str(k) if not isinstance(k, str) else k: json_ready(v, digits) for k, v in obj.items()
        }
    if isinstance(obj, (list, tuple)):
        return [json_ready(v, digits) for v in obj]
    if hasattr(obj, "tolist") and hasattr(obj, "dtype"):  # numpy array or scalar
        return json_ready(obj.tolist(), digits)
    if isinstance(obj, bool) or obj is None or isinstance(obj, (int, str)):
        return obj
    if isinstance(obj, float):
        return float(f"{obj:.{digits}g}") if math.isfinite(obj) else obj
    if isinstance(obj, os.PathLike):
        return os.fspath(obj)
    return obj


def _labelled(paths: PathsArg | None) -> list[tuple[str, Path]]:
    if paths is None:
        return []
    items: Iterable[tuple[str, str | os.PathLike[str] | None]]
    if isinstance(paths, Mapping):
        items = paths.items()
    else:
        items = ((os.fspath(p), p) for p in paths if p is not None)
    return [(str(label), Path(p)) for label, p in items if p is not None and str(p) != ""]


def _same_path(a: Path, b: Path) -> bool:
    """Whether ``a`` and ``b`` name the same file: same inode when both exist (hard
    links, symbolic links, ``./x`` vs ``x``), else the same resolved path."""
    with contextlib.suppress(OSError):
        if a.exists() and b.exists():
            return os.path.samefile(a, b)
    return os.path.normcase(os.path.realpath(a)) == os.path.normcase(os.path.realpath(b))


def _inside(path: Path, folder: Path) -> bool:
    """Whether ``path`` lies inside ``folder`` (resolved; the folder itself excluded)."""
    p = Path(os.path.normcase(os.path.realpath(path)))
    f = Path(os.path.normcase(os.path.realpath(folder)))
    return p != f and f in p.parents


def check_distinct_paths(
    *,
    inputs: PathsArg | None = None,
    outputs: PathsArg | None = None,
    output_folders: PathsArg | None = None,
) -> None:
    """Refuse, before any work, an output that would overwrite an input or another output.

    Every command that writes files calls this once with everything it reads and
    everything it writes, so that e.g. ``reconstruct S.mha -o s.vtp --gold g.csv
    --points-out g.csv`` stops with one line instead of replacing the gold points.

    Parameters
    ----------
    inputs : mapping of label to path, or iterable of paths, optional
        Files the command reads, e.g. ``{"SWEEP": args.sweep, "--gold": args.gold}``.
        ``None`` values (options not given) are skipped.
    outputs : mapping or iterable, optional
        Files (or folders filled with named files) the command writes. Each must
        differ from every input and from every other output.
    output_folders : mapping or iterable, optional
        Folders the command replaces as a whole (e.g. the HTML report folder). Besides
        differing from every input and output, no input or other output may lie inside
        one (it would be deleted with the folder's old contents).

    Raises
    ------
    BoneUSReconError
        Naming the path and the two options that collide.

    Examples
    --------
    >>> check_distinct_paths(inputs={"--gold": "g.csv"}, outputs={"-o": "s.vtp"})
    >>> check_distinct_paths(inputs={"--gold": "g.csv"}, outputs={"--points-out": "g.csv"})
    Traceback (most recent call last):
    ...
    BoneUSRecon.Logic.errors.BoneUSReconError: g.csv: --points-out would overwrite the input --gold; choose another output path
    """
    ins = _labelled(inputs)
    outs = _labelled(outputs)
    folders = _labelled(output_folders)
    written = outs + folders
    for i, (label, path) in enumerate(written):
        for in_label, in_path in ins:
            if _same_path(path, in_path):
                raise BoneUSReconError(
                    f"{label} would overwrite the input {in_label}; choose another output path",
                    path,
                )
        for other_label, other in written[:i]:
            if _same_path(path, other):
                raise BoneUSReconError(
                    f"{label} and {other_label} name the same path; give each output its own",
                    path,
                )
    for f_label, folder in folders:
        for label, path in ins:
            if _inside(path, folder):
                raise BoneUSReconError(
                    f"the input {label} lies inside the folder {f_label}, which is replaced "
                    "as a whole; choose another folder",
                    path,
                )
        for label, path in outs + [x for x in folders if x[1] is not folder]:
            if _inside(path, folder):
                raise BoneUSReconError(
                    f"{label} lies inside the folder {f_label}, which is replaced as a "
                    "whole; choose another folder",
                    path,
                )

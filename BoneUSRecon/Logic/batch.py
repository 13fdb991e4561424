"""Cohorts: reconstruct every sweep of a manifest, in parallel on Dask, resumably.

A *manifest* is a CSV file with a header. ``sweep`` is required; ``name``,
``calibration``, ``transform``, ``gold`` and ``target`` are optional, and so are
per-row overrides of the reconstruction parameters, named as the ``reconstruct``
command's options (``segmenter``, ``degree``, ``control-points`` or ``along`` /
``around``, ``rays``, ``fit-method``, ``robust``, ``axis``, ``bone-points``; ``-`` or
``_`` alike; pairs as ``"15 5"``, bone points as ``"12.5 -3 40; 14 -3 60"``: reference mm
of points on the bone to follow, the sweep's own, ``--bone-point``).
Relative paths are relative to the manifest's folder. An empty cell means the
default.

:func:`run_batch` runs one Dask task per sweep (:func:`run_sweep`), on a local
cluster of single-threaded worker processes or on an existing ``dask.distributed``
scheduler. A task receives paths and parameters, never arrays: each worker reads its
sweep itself (memory-mapped), so memory is bounded by one sweep per worker. A task
writes ``OUTDIR/NAME/`` (``surface.vtp``, ``points.vtp``, ``summary.json``, and the
report when asked) into a hidden temporary folder renamed into place when complete.
``summary.json`` records a fingerprint of the parameters and of the input files'
identity, so that ``resume=True`` skips the sweeps whose outputs are complete and
current. A sweep that fails is a ``failed`` row with its one-line error; the others go
on. Dask is imported only when there is work to do.
"""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import hashlib
import json
import logging
import math
import os
import shutil
import signal
import threading
import time
import uuid
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import atomic_path, check_input_file, check_output_dir
from BoneUSRecon.Logic.progress import ProgressCallback, report

__all__ = [
    "MANIFEST_COLUMNS",
    "PARAMETER_COLUMNS",
    "SUMMARY_COLUMNS",
    "BatchJob",
    "BatchResult",
    "read_manifest",
    "fingerprint",
    "completed_row",
    "run_sweep",
    "run_batch",
    "start_worker_server",
    "write_summary",
]

#: Path columns of a manifest (relative to the manifest's folder).
PATH_COLUMNS = ("sweep", "calibration", "gold", "target")
#: Parameter overrides, named as ``reconstruct``'s options, mapped to
#: :func:`BoneUSRecon.Logic.pipeline.params_with` keywords, with their kind.
PARAMETER_COLUMNS: dict[str, str] = {
    "segmenter": "text",
    "degree": "pair",
    "control_points": "pair",
    "along": "int",
    "around": "int",
    "rays": "int",
    "fit_method": "text",
    "robust": "text",
    "axis": "text",
    "bone_points": "points",
}
#: Every column a manifest may have.
MANIFEST_COLUMNS = ("name", *PATH_COLUMNS, "transform", *PARAMETER_COLUMNS)

#: Columns of ``summary.csv``, in order (empty where they do not apply).
SUMMARY_COLUMNS = (
    "name",
    "sweep",
    "status",
    "error",
    "resumed",
    "frames",
    "valid_frames",
    "frames_used",
    "frames_rejected",
    "frames_rejected_by_fit",
    "segmenter",
    "control_points",
    "rays",
    "grid_coverage",
    "fit_rms_mm",
    "surface_triangles",
    "gold_points",
    "mean_mm",
    "rms_mm",
    "median_mm",
    "p95_mm",
    "max_mm",
    "within_1mm",
    "time_read_s",
    "time_segment_s",
    "time_resample_s",
    "time_fit_s",
    "time_surface_s",
    "time_write_s",
    "time_total_s",
    "outdir",
)

_TEXT = ("name", "sweep", "status", "error", "segmenter", "control_points", "outdir")
_INT = ("frames", "valid_frames", "frames_used", "frames_rejected", "frames_rejected_by_fit",
        "rays", "surface_triangles", "gold_points")  # fmt: skip
#: Each summary column's kind: ``text``, ``int``, ``float`` or ``bool`` (Parquet types).
SUMMARY_TYPES = {
    k: "text" if k in _TEXT else "int" if k in _INT else "bool" if k == "resumed" else "float"
    for k in SUMMARY_COLUMNS
}

#: Files of a finished sweep's folder (the report folder is added when asked).
SURFACE_FILE = "surface.vtp"
POINTS_FILE = "points.vtp"
SUMMARY_FILE = "summary.json"
REPORT_DIR = "report"
#: Names a sweep may not take: the batch's own files in OUTDIR.
RESERVED_NAMES = ("summary.csv", "summary.parquet")
#: ``summary.json``'s ``kind``: marks a folder as this module's output.
SUMMARY_KIND = "BoneUSRecon batch sweep"

#: ``report_writer(recon, folder, gold, evaluation, parameters)``: writes the HTML report
#: (kept out of Logic, which never imports rendering; the CLI passes one).
ReportWriter = Callable[[Any, Path, Any, Any, dict[str, Any]], Any]


@dataclass(frozen=True)
class BatchJob:
    """One manifest row, checked and resolved.

    Attributes
    ----------
    name : str
        Output folder name under OUTDIR (unique in the manifest).
    sweep : Path
        The sequence file (absolute).
    calibration, gold, target : Path or None
        Device-set XML, gold points, bone model to register to (absolute).
    transform : str or None
        Pose name for :func:`~BoneUSRecon.Logic.sequence_io.read_sweep`.
    overrides : dict
        The row's parameter cells as given (column -> text), for the record.
    params : ReconstructionParams
        Defaults (or the batch's base) with the row's overrides.
    line : int
        Line in the manifest (for messages).
    """

    name: str
    sweep: Path
    calibration: Path | None = None
    gold: Path | None = None
    target: Path | None = None
    transform: str | None = None
    overrides: dict[str, str] = dataclasses.field(default_factory=dict)
    params: Any = None
    line: int = 0

    def inputs(self) -> dict[str, Path]:
        """The input files by role (``sweep``, ``calibration``, ``gold``, ``target``)."""
        return {k: getattr(self, k) for k in PATH_COLUMNS if getattr(self, k) is not None}


@dataclass(frozen=True)
class BatchResult:
    """What :func:`run_batch` did.

    Attributes
    ----------
    rows : list of dict
        One per job, in manifest order, with the keys of :data:`SUMMARY_COLUMNS`.
    summary_files : list of Path
        ``summary.csv`` (and ``summary.parquet`` when pyarrow is importable).
    """

    rows: list[dict[str, Any]]
    summary_files: list[Path]

    @property
    def failed(self) -> list[dict[str, Any]]:
        """The rows whose status is ``failed``."""
        return [r for r in self.rows if r["status"] != "ok"]

    @property
    def resumed(self) -> int:
        """How many sweeps were skipped as already done."""
        return sum(bool(r.get("resumed")) for r in self.rows)


# --------------------------------------------------------------------------- manifest


def _column_key(header: str) -> str:
    return "_".join(header.strip().lower().replace("-", " ").split())


def _parse_override(kind: str, text: str, column: str, where: str, manifest: Path) -> Any:
    try:
        if kind == "int":
            return int(text)
        if kind == "pair":
            values = [int(v) for v in text.lower().replace("x", " ").replace(";", " ").split()]
            if len(values) != 2:
                raise ValueError
            return tuple(values)
        if kind == "points":  # reconstruct's --bone-point X Y Z, points apart by ';'
            points = [tuple(float(v) for v in p.replace(",", " ").split()) for p in text.split(";")]
            if any(len(p) != 3 or not all(math.isfinite(v) for v in p) for p in points):
                raise ValueError
            return points
    except ValueError:
        expected = {
            "int": "an integer",
            "pair": "two integers such as '15 5'",
            "points": "points of three finite numbers (mm) such as '12.5 -3 40; 14 -3 60'",
        }[kind]
        raise BoneUSReconError(
            f"{where}: column '{column}' must be {expected}, got {text!r}", manifest
        ) from None
    return text


def _check_name(name: str, where: str, manifest: Path) -> None:
    bad = (
        not name
        or name.startswith(".")  # hidden names are the batch's temporary folders
        or any(c in name for c in "/\\\0")
        or name in RESERVED_NAMES
    )
    if bad:
        raise BoneUSReconError(
            f"{where}: name {name!r} cannot be a folder name (no '/', no leading '.', "
            f"not {' or '.join(RESERVED_NAMES)})",
            manifest,
        )


def read_manifest(path: str | os.PathLike[str], base_params: Any = None) -> list[BatchJob]:
    """Read and check a batch manifest (CSV with a header; see the module docstring).

    Parameters
    ----------
    path : path-like
        The manifest. Relative paths in it are relative to its folder.
    base_params : ReconstructionParams, optional
        Parameters the rows' overrides apply to (default: the paper's).

    Returns
    -------
    list of BatchJob
        In manifest order. Names default to the sweep file's stem, made unique with
        ``-2``, ``-3``, ... (explicit names must be unique).

    Raises
    ------
    BoneUSReconError
        Missing file, no ``sweep`` column, an unknown or repeated column, an empty
        ``sweep`` cell, a bad name, a parameter that is not a number or that
        :func:`~BoneUSRecon.Logic.pipeline.params_with` refuses; the message names
        the line. Whether the listed files exist is checked per sweep, when run.
    """
    from BoneUSRecon.Logic.pipeline import ReconstructionParams, params_with

    manifest = check_input_file(path).resolve()
    folder = manifest.parent
    try:
        text = manifest.read_text(encoding="utf-8-sig")
    except UnicodeDecodeError:
        raise BoneUSReconError("not a text (UTF-8) CSV file", manifest) from None
    reader = csv.reader(text.splitlines())
    header = next(reader, None)
    if not header or not any(h.strip() for h in header):
        raise BoneUSReconError("no header line (need at least a 'sweep' column)", manifest)
    keys = [_column_key(h) for h in header]
    for k, h in zip(keys, header, strict=True):
        if k not in MANIFEST_COLUMNS:
            raise BoneUSReconError(
                f"unknown column {h.strip()!r}; columns are {', '.join(MANIFEST_COLUMNS)}", manifest
            )
    dupes = sorted({k for k in keys if keys.count(k) > 1})
    if dupes:
        raise BoneUSReconError(f"column {dupes[0]!r} appears twice", manifest)
    if "sweep" not in keys:
        raise BoneUSReconError("no 'sweep' column in the header", manifest)

    rows: list[tuple[int, dict[str, str]]] = []
    for cells in reader:
        line = reader.line_num
        if not any(c.strip() for c in cells):
            continue  # blank lines are allowed
        if len(cells) > len(keys):
            raise BoneUSReconError(
                f"line {line}: {len(cells)} cells for {len(keys)} columns", manifest
            )
        rows.append((line, {k: c.strip() for k, c in zip(keys, cells, strict=False)}))
    if not rows:
        raise BoneUSReconError("no sweeps listed", manifest)

    explicit = [r.get("name", "") for _, r in rows if r.get("name")]
    seen = sorted({n for n in explicit if explicit.count(n) > 1})
    if seen:
        raise BoneUSReconError(f"name {seen[0]!r} is given to more than one sweep", manifest)
    taken = set(explicit)

    jobs: list[BatchJob] = []
    for line, row in rows:
        where = f"line {line}"
        if not row.get("sweep"):
            raise BoneUSReconError(f"{where}: empty 'sweep' cell", manifest)
        files = {
            k: (folder / Path(row[k]).expanduser()).resolve() if row.get(k) else None
            for k in PATH_COLUMNS
        }
        sweep = files["sweep"]
        assert sweep is not None
        name = row.get("name", "")
        if name:
            _check_name(name, where, manifest)
        else:
            stem = sweep.stem.lstrip(".") or "sweep"  # a leading '.' marks our temporaries
            name, count = stem, 1
            while name in taken or name in RESERVED_NAMES:
                count += 1
                name = f"{stem}-{count}"
            taken.add(name)
        overrides = {k: row[k] for k in PARAMETER_COLUMNS if row.get(k)}
        values = {
            k: _parse_override(PARAMETER_COLUMNS[k], v, k.replace("_", "-"), where, manifest)
            for k, v in overrides.items()
        }
        # ``along``/``around`` (reconstruct's --along E / --around F) set one of the
        # two control-point counts; the other keeps its value.
        along, around = values.pop("along", None), values.pop("around", None)
        if along is not None or around is not None:
            if "control_points" in values:
                raise BoneUSReconError(
                    f"{where}: give 'control-points' or 'along'/'around', not both", manifest
                )
            base = (base_params or ReconstructionParams()).fit.n_control_points
            values["control_points"] = (
                base[0] if along is None else along,
                base[1] if around is None else around,
            )
        try:
            if "control_points" in values:  # the column's name, params_with's n_control_points
                values["n_control_points"] = values.pop("control_points")
            params = params_with(base_params, **values)
        except (BoneUSReconError, ValueError, TypeError) as exc:
            msg = exc.message if isinstance(exc, BoneUSReconError) else str(exc)
            raise BoneUSReconError(f"{where}: {msg}", manifest) from None
        jobs.append(
            BatchJob(
                name=name,
                sweep=sweep,
                calibration=files["calibration"],
                gold=files["gold"],
                target=files["target"],
                transform=row.get("transform") or None,
                overrides=overrides,
                params=params,
                line=line,
            )
        )
    return jobs


# --------------------------------------------------------------------------- identity


def _file_identity(p: Path) -> list[Any] | None:
    try:
        st = p.stat()
    except OSError:
        return None
    return [str(p), st.st_size, st.st_mtime_ns]


def fingerprint(job: BatchJob, *, with_report: bool = False) -> str:
    """A hash of everything a sweep's outputs depend on.

    The parameters (all of them, not only the overrides), the pose name, whether a
    report is written, the package version, and each input file's identity: path,
    size and modification time (as ``make`` and ``rsync`` judge a file changed;
    hashing the content would read every sweep, gigabytes for a cohort). A ``.mhd``
    header's pixel file (``.raw``/``.zraw`` of the same stem) counts as an input.

    Returns
    -------
    str
        Hex SHA-256.
    """
    from dataclasses import asdict

    from BoneUSRecon import __version__

    inputs = {k: _file_identity(p) for k, p in job.inputs().items()}
    if job.sweep.suffix.lower() == ".mhd":
        for ext in (".raw", ".zraw"):
            data = job.sweep.with_suffix(ext)
            if data.exists():
                inputs[f"sweep{ext}"] = _file_identity(data)
    doc = {
        "version": __version__,
        "params": asdict(job.params),
        "transform": job.transform,
        "report": bool(with_report),
        "inputs": inputs,
    }
    return hashlib.sha256(json.dumps(doc, sort_keys=True, default=str).encode()).hexdigest()


def completed_row(job: BatchJob, outdir: str | os.PathLike[str], fp: str) -> dict[str, Any] | None:
    """The summary row of an earlier run of ``job``, if still valid.

    Valid when ``OUTDIR/NAME/summary.json`` has the fingerprint ``fp`` and every
    output it lists is there with the size it recorded. A sweep that failed in its
    own task (a bad file, no bone found) has such a record and fails the same way on
    the same inputs, so it is not run again until its inputs or parameters change; a
    sweep whose worker died has no record and is run again.

    Returns
    -------
    dict or None
        The recorded row (with ``resumed`` set), or None when the sweep must be run.
    """
    folder = Path(outdir) / job.name
    try:
        doc = json.loads((folder / SUMMARY_FILE).read_text())
    except (OSError, ValueError):
        return None
    if not isinstance(doc, dict) or doc.get("kind") != SUMMARY_KIND:
        return None
    if doc.get("fingerprint") != fp or doc.get("row", {}).get("status") not in ("ok", "failed"):
        return None
    for rel, size in doc.get("outputs", {}).items():
        p = folder / rel
        if not p.is_file() or p.stat().st_size != size:
            return None
    return {**doc["row"], "resumed": True}


# --------------------------------------------------------------------------- one sweep


class _Cancelled(Exception):
    """The batch that started this task was stopped (its run marker is gone)."""


def _cancel_check(marker: Path | None) -> ProgressCallback | None:
    """A progress callback that raises :class:`_Cancelled` once ``marker`` is gone.

    Workers of a remote scheduler keep running a task after the client left; this
    stops them at the next progress report (checked at most every 0.5 s).
    """
    if marker is None:
        return None
    last = [0.0]

    def check(stage: str, done: int, total: int) -> None:
        now = time.monotonic()
        if now - last[0] >= 0.5:
            last[0] = now
            if not marker.exists():
                raise _Cancelled(str(marker))

    return check


def _one_line(exc: BaseException) -> str:
    if isinstance(exc, BoneUSReconError):
        return str(exc)
    if isinstance(exc, OSError) and exc.strerror:
        return f"{exc.filename}: {exc.strerror}" if exc.filename else exc.strerror
    return " ".join(f"internal error: {type(exc).__name__}: {exc}".split())


def registration_hook(target: Path) -> Callable[[Any], dict[str, Any]]:
    """The function that registers a reconstruction to the bone model ``target``.

    The model is read and checked here, before the sweep's work starts, so that a row
    with a bad model fails at once. The returned function registers the segmented
    points (:func:`BoneUSRecon.Logic.registration.register_reconstruction`, from the
    sweep's own frame: the identity start, as ``reconstruct --register-to``) and returns
    the JSON-ready figures stored in the sweep's ``summary.json`` under
    ``registration`` (the SOURCE -> TARGET ``matrix`` included).

    Raises
    ------
    BoneUSReconError
        The model cannot be read or is not a usable bone surface (named).
    """
    from BoneUSRecon.Logic.registration import model_from_polydata, register_reconstruction
    from BoneUSRecon.Logic.vtkio import read_polydata

    model = model_from_polydata(read_polydata(target), target)

    def register(recon: Any) -> dict[str, Any]:
        return register_reconstruction(recon, model, model_path=target).as_dict()

    return register


def _empty_row(job: BatchJob) -> dict[str, Any]:
    row: dict[str, Any] = dict.fromkeys(SUMMARY_COLUMNS)
    row.update(name=job.name, sweep=str(job.sweep), resumed=False, outdir=job.name)
    return row


def run_sweep(
    job: BatchJob,
    outdir: str | os.PathLike[str],
    *,
    fp: str = "",
    report_writer: ReportWriter | None = None,
    token: str | None = None,
    marker: str | os.PathLike[str] | None = None,
) -> dict[str, Any]:
    """Reconstruct one sweep into ``OUTDIR/NAME/``: the task a Dask worker runs.

    Everything is written into a hidden folder ``OUTDIR/.NAME.TOKEN.part`` then renamed
    to ``OUTDIR/NAME`` (an earlier folder of that name is replaced), so the folder is
    either complete or absent. A failed sweep gets a folder holding only
    ``summary.json`` with its error.

    Parameters
    ----------
    job : BatchJob
    outdir : path-like
        The batch's output folder (exists).
    fp : str
        :func:`fingerprint` of the job, stored for ``resume``.
    report_writer : callable, optional
        Writes the HTML report into ``NAME/report`` (see :data:`ReportWriter`).
    token : str, optional
        The run's identity, in temporary names (so that the run can remove its own).
    marker : path-like, optional
        A file that exists while the batch runs; once it is gone the task stops and
        leaves nothing.

    Returns
    -------
    dict
        The summary row (keys :data:`SUMMARY_COLUMNS`); ``status`` is ``ok`` or
        ``failed`` with ``error`` the one-line reason. Only an interrupt or a
        cancelled batch raises.
    """
    from dataclasses import asdict

    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.pipeline import reconstruct
    from BoneUSRecon.Logic.sequence_io import read_sweep
    from BoneUSRecon.Logic.vtkio import read_points, write_points, write_polydata

    t_start = time.perf_counter()
    out = Path(outdir)
    token = token or uuid.uuid4().hex[:12]
    mark = Path(marker) if marker is not None else None
    check = _cancel_check(mark)
    tmp = out / f".{job.name}.{token}.part"
    tmp.mkdir()
    row = _empty_row(job)
    doc: dict[str, Any] = {"kind": SUMMARY_KIND, "fingerprint": fp, "job": _job_record(job)}
    try:
        try:
            for p in job.inputs().values():
                check_input_file(p)
            register = registration_hook(job.target) if job.target is not None else None
            t0 = time.perf_counter()
            sweep = read_sweep(
                job.sweep, calibration=job.calibration, transform=job.transform, progress=check
            )
            t_read = time.perf_counter() - t0
            recon = reconstruct(sweep, job.params, progress=check)
            evaluation = None
            if job.gold is not None:
                evaluation = evaluate_surface(recon.surface, read_points(job.gold))
            if register is not None:
                doc["registration"] = register(recon)
            t0 = time.perf_counter()
            write_polydata(recon.surface, tmp / SURFACE_FILE)
            write_points(recon.points, tmp / POINTS_FILE)
            if report_writer is not None:
                report_writer(
                    recon,
                    tmp / REPORT_DIR,
                    read_points(job.gold) if job.gold is not None else None,
                    evaluation,
                    asdict(job.params),
                )
            t_write = time.perf_counter() - t0
            row.update(_ok_fields(recon, evaluation))
            t = recon.timings
            row.update(
                status="ok",
                time_read_s=t_read,
                time_segment_s=t.get("segment"),
                time_resample_s=t.get("resample"),
                time_fit_s=t.get("fit"),
                time_surface_s=t.get("surface"),
                time_write_s=t_write,
            )
            doc.update(
                summary=recon.summary,
                timings_s={**t, "read": t_read, "write": t_write},
                evaluation=evaluation.as_dict() if evaluation is not None else None,
                parameters=asdict(job.params),
            )
        except (_Cancelled, KeyboardInterrupt):
            raise
        except Exception as exc:  # a failing sweep is a row; the batch goes on
            for child in list(tmp.iterdir()):
                if child.is_dir():
                    shutil.rmtree(child)
                else:
                    child.unlink()
            row.update(status="failed", error=_one_line(exc))
        row["time_total_s"] = time.perf_counter() - t_start
        doc["row"] = row
        doc["outputs"] = {
            str(p.relative_to(tmp)): p.stat().st_size for p in sorted(tmp.rglob("*")) if p.is_file()
        }
        with atomic_path(tmp / SUMMARY_FILE) as f:
            f.write_text(json.dumps(doc, indent=2, default=_json_default))
        if mark is not None and not mark.exists():
            raise _Cancelled(str(mark))
        _publish(tmp, out / job.name, token)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return row


def _json_default(o: Any) -> Any:
    if hasattr(o, "tolist"):
        return o.tolist()
    if hasattr(o, "item"):
        return o.item()
    return str(o)


def _job_record(job: BatchJob) -> dict[str, Any]:
    rec: dict[str, Any] = {k: str(v) for k, v in job.inputs().items()}
    rec.update(name=job.name, transform=job.transform, overrides=job.overrides, line=job.line)
    return rec


def _ok_fields(recon: Any, evaluation: Any) -> dict[str, Any]:
    s = recon.summary
    fields: dict[str, Any] = {
        "frames": s["frames"],
        "valid_frames": s["valid_frames"],
        "frames_used": s["segmented_frames"],
        "frames_rejected": s["rejected_frames"],
        "frames_rejected_by_fit": len(s["fit_rejected_frames"]),
        "segmenter": s["segmenter"],
        "control_points": " ".join(str(v) for v in s["control_points"]),
        "rays": s["grid_shape"][1],
        "grid_coverage": float(s["grid_coverage"]),
        "fit_rms_mm": float(s["fit_rms_mm"]),
        "surface_triangles": s["surface_triangles"],
    }
    if evaluation is not None:
        ev = evaluation.as_dict()
        fields.update(
            gold_points=ev["n"],
            **{
                k: float(ev[k])
                for k in ("mean_mm", "rms_mm", "median_mm", "p95_mm", "max_mm", "within_1mm")
            },
        )
    return fields


def _publish(tmp: Path, final: Path, token: str) -> None:
    """Rename the finished ``tmp`` folder to ``final``, replacing an earlier one."""
    old = None
    if final.exists():
        old = final.with_name(f".{final.name}.{token}.old")
        os.replace(final, old)
    try:
        os.replace(tmp, final)
    except BaseException:
        if old is not None and not final.exists():
            os.replace(old, final)
        raise
    if old is not None:
        shutil.rmtree(old, ignore_errors=True)


# --------------------------------------------------------------------------- summary


def write_summary(rows: Sequence[dict[str, Any]], outdir: str | os.PathLike[str]) -> list[Path]:
    """Write ``summary.csv`` (and ``summary.parquet`` when pyarrow is importable), atomically.

    Parameters
    ----------
    rows : sequence of dict
        Rows with the keys of :data:`SUMMARY_COLUMNS` (missing ones are left empty).
    outdir : path-like

    Returns
    -------
    list of Path
        The files written.
    """
    out = Path(outdir)
    written = []
    csv_path = out / "summary.csv"
    with atomic_path(csv_path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
        w = csv.DictWriter(f, fieldnames=SUMMARY_COLUMNS, extrasaction="ignore")
        w.writeheader()
        for r in rows:
            w.writerow({k: _csv_cell(r.get(k)) for k in SUMMARY_COLUMNS})
    written.append(csv_path)
    try:
        import pyarrow as pa
        import pyarrow.parquet as pq
    except ImportError:  # Parquet is a bonus: the CSV holds the same
        return written
    # Typed columns: a column of ints with gaps stays ints, one of all gaps stays typed.
    types = {"text": pa.string(), "int": pa.int64(), "float": pa.float64(), "bool": pa.bool_()}
    table = pa.table(
        {
            k: pa.array([_typed(r.get(k), kind) for r in rows], type=types[kind])
            for k, kind in SUMMARY_TYPES.items()
        }
    )
    pq_path = out / "summary.parquet"
    with atomic_path(pq_path) as tmp:
        pq.write_table(table, tmp)
    written.append(pq_path)
    return written


def _typed(v: Any, kind: str) -> Any:
    if v is None or v == "":
        return None
    return {"text": str, "int": int, "float": float, "bool": bool}[kind](v)


def _csv_cell(v: Any) -> Any:
    if v is None:
        return ""
    if isinstance(v, float):
        return f"{v:.6g}"
    return v


# --------------------------------------------------------------------------- the batch


def _check_outdir(jobs: Sequence[BatchJob], out: Path, manifest: Path | None) -> None:
    """Refuse to write where an input is, or into a folder this module did not write."""
    inputs = {p for j in jobs for p in j.inputs().values()}
    if manifest is not None:
        inputs.add(Path(manifest).resolve())
    outputs = {out / n for n in RESERVED_NAMES} | {out / j.name for j in jobs}
    for p in sorted(inputs):
        for o in outputs:
            if p == o or o in p.parents:
                raise BoneUSReconError("is an input of the batch; choose another OUTDIR", o)
    for j in jobs:
        folder = out / j.name
        if not folder.exists():
            continue
        if not folder.is_dir():
            raise BoneUSReconError("exists and is not a folder (the sweep's output folder)", folder)
        try:
            kind = json.loads((folder / SUMMARY_FILE).read_text()).get("kind")
        except (OSError, ValueError, AttributeError):
            kind = None
        if kind != SUMMARY_KIND and any(folder.iterdir()):
            raise BoneUSReconError(
                "folder exists and is not a batch output; choose another OUTDIR or name", folder
            )


@contextlib.contextmanager
def _sigint_ignored() -> Iterator[None]:
    """Ignore SIGINT while the local cluster starts its worker processes.

    A terminal's Ctrl-C goes to the whole process group. Processes started while
    SIGINT is ignored keep ignoring it (the disposition survives ``exec``, and Python
    then installs no KeyboardInterrupt handler), so the workers never die mid-task with
    a traceback: only this process handles Ctrl-C, and stops them in order. (Blocking
    the signal instead is not enough: the processes are started from Dask's threads.)
    The price: a Ctrl-C during the cluster's start-up, a few seconds, is ignored.
    """
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    old = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, old)


@contextlib.contextmanager
def _environ(**values: str) -> Iterator[None]:
    """Environment variables set while processes that should inherit them start."""
    old = {k: os.environ.get(k) for k in values}
    os.environ.update(values)
    try:
        yield
    finally:
        for k, v in old.items():
            if v is None:
                os.environ.pop(k, None)
            else:
                os.environ[k] = v


@contextlib.contextmanager
def _dask_client(workers: int | None, scheduler: str | None) -> Iterator[Any]:
    """A ``distributed.Client`` on ``scheduler`` or on a new local cluster."""
    try:
        import dask
        from distributed import Client, LocalCluster
    except ImportError:
        raise BoneUSReconError(
            "batch runs need dask.distributed: pip install 'BoneUSRecon[batch]'"
        ) from None

    # Dask's own warnings (slow event loop, ports) are not the user's business here;
    # errors still show. Its housekeeping is tuned for interactive analysis: the
    # workers' statistical profiler (a stack sample every 10 ms) and 20-100 ms ticks
    # cost a few % of a core per process, idle or not; a sweep takes seconds, so the
    # batch samples less often. ``worker-saturation`` 1: one sweep per worker at a
    # time, the rest queued at the scheduler, so that memory holds one sweep per worker
    # and no worker sits idle while another has two queued.
    quiet = {
        "distributed.logging.distributed": "error",
        "distributed.admin.tick.limit": "1h",
        "distributed.admin.tick.interval": "1s",
        "distributed.admin.system-monitor.interval": "2s",
        "distributed.worker.memory.monitor-interval": "1s",
        "distributed.worker.profile.enabled": False,
        "distributed.scheduler.worker-saturation": 1.0,
        # One task per sweep, queued at the scheduler: nothing to steal, no replicas
        # for the memory manager to drop, no dashboard or metrics to serve.
        "distributed.scheduler.work-stealing": False,
        "distributed.scheduler.active-memory-manager.start": False,
        "distributed.scheduler.http.routes": [],
        "distributed.worker.http.routes": [],
        # Dask's variables for the workers it starts, less the malloc trim threshold
        # (see WORKER_ENV).
        "distributed.nanny.pre-spawn-environ": {
            k: v for k, v in WORKER_ENV.items() if not k.startswith("DASK_")
        },
    }
    logging.getLogger("distributed").setLevel(logging.ERROR)
    # The client's event loop logs through tornado: on Ctrl-C distributed's own
    # cancellation callback (``sync``'s ``cancel``) can raise in it, and tornado prints
    # that with a traceback (NameError on ``future``, distributed 2026.8; seen once
    # in five runs of the suite's Ctrl-C test). The interruption itself is reported by
    # the caller; what the loop logs then is plumbing, not the user's business.
    logging.getLogger("tornado.application").setLevel(logging.CRITICAL)
    with dask.config.set(quiet):
        if scheduler is not None:
            try:
                client = Client(scheduler, timeout="10s")
            except (OSError, TimeoutError, ValueError) as exc:
                raise BoneUSReconError(
                    f"cannot reach the Dask scheduler {scheduler!r}: {' '.join(str(exc).split())}"
                ) from None
            with client:
                yield client
            return
        n = workers or _cores()
        cluster = None
        try:
            # Spawned workers (no fork server) read Dask's configuration from the
            # environment at start-up.
            with (
                dask.config.set(_preload_workers()),
                _sigint_ignored(),
                _environ(DASK_LOGGING__DISTRIBUTED=WORKER_ENV["DASK_LOGGING__DISTRIBUTED"]),
            ):
                cluster = LocalCluster(
                    n_workers=n,
                    threads_per_worker=1,
                    processes=True,
                    dashboard_address=None,
                    # No dashboard, but the scheduler's HTTP endpoints still bind a port:
                    # any free one (the default 8787 may be another cluster's).
                    scheduler_kwargs={"dashboard_address": "127.0.0.1:0"},
                    scheduler_port=0,
                    host="127.0.0.1",
                )
            with Client(cluster) as client:
                yield client
        finally:
            if cluster is not None:
                cluster.close(timeout=20)


#: What every worker needs, imported once by (or before) the fork server, not per worker.
WORKER_PRELOAD = (
    "distributed",
    "numpy",
    "scipy",
    "vtkmodules",
    "BoneUSRecon.Logic.batch",
    "BoneUSRecon.Logic.pipeline",
    "BoneUSRecon.Logic.sequence_io",
    "BoneUSRecon.Logic.vtkio",
)


#: Set for the fork server, so for every local worker: Dask's own thread limits for
#: worker processes (``distributed.nanny.pre-spawn-environ``; one BLAS thread per
#: single-threaded worker), and its logging at ``critical``: a sweep's failure reaches
#: the client through its future, and what a worker logs at ``error`` is its own
#: plumbing, e.g. a heartbeat to a scheduler already closed after Ctrl-C, printed with
#: a traceback on a loaded machine (seen in the suite's Ctrl-C test). Not Dask's
#: ``MALLOC_TRIM_THRESHOLD_=65536``: setting it also fixes glibc's mmap threshold at
#: 128 KiB, so every frame-sized temporary array is mapped and unmapped afresh: 2.5x
#: the page faults and ~0.09 s more system CPU per reference sweep (~4 %; measured
#: on the one-process baseline of bench_batch.py). A worker holds one sweep at a
#: time, so the memory trimming would return is one sweep's, which the next reuses.
WORKER_ENV = {
    "OMP_NUM_THREADS": "1",
    "MKL_NUM_THREADS": "1",
    "OPENBLAS_NUM_THREADS": "1",
    "DASK_LOGGING__DISTRIBUTED": "critical",
}


def start_worker_server(*, fork_this_process: bool = False) -> None:
    """Start the fork server that local workers are forked from (idempotent).

    Dask starts each worker by default as a fresh interpreter ("spawn") that imports
    numpy, SciPy, VTK and the pipeline anew: about 2 s of CPU per worker, as much as
    a small sweep. The fork server imports :data:`WORKER_PRELOAD` once, and each worker
    is forked from it (without this process's threads, unlike a plain fork). Called
    early (the CLI calls it before reading the manifest), a fresh fork server's imports
    overlap this process's. It starts with SIGINT ignored (see :func:`_sigint_ignored`) and with
    :data:`WORKER_ENV`, and passes both on. No-op where there is no fork server
    (Windows: workers are spawned).

    Parameters
    ----------
    fork_this_process : bool
        Import :data:`WORKER_PRELOAD` here, under :data:`WORKER_ENV` (so this process
        keeps one BLAS thread), and make the fork server a fork of this process: the
        imports are paid once for this process and the workers, not twice (~2 s of
        CPU, measured in bench_batch.py). For a command line process that does no
        numerical work itself; taken only while this process has a single thread and
        has not imported numpy, and where ``multiprocessing.forkserver`` is laid out
        as in Python 3.8-3.13 (see :func:`_fork_server_here`); else the plain fork
        server.
    """
    import multiprocessing
    import multiprocessing.forkserver

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return
    multiprocessing.get_context("forkserver").set_forkserver_preload(list(WORKER_PRELOAD))
    with _environ(**WORKER_ENV):
        if fork_this_process and _fork_server_here():
            return
        with _sigint_ignored():
            multiprocessing.forkserver.ensure_running()


def _fork_server_here() -> bool:
    """Start ``multiprocessing``'s fork server as a fork of this process, after its imports.

    ``multiprocessing.forkserver.ensure_running`` starts the server as a fresh
    interpreter that imports the preload list itself; no public option forks it from
    the caller instead, so this does what ``ensure_running`` does (same listener, same
    "alive" pipe, same server loop, :func:`multiprocessing.forkserver.main`) with
    ``os.fork`` in place of the new interpreter, and records the server where
    ``ensure_running`` looks for it. Forking is safe only while this process runs one
    thread. The fork is made with SIGINT ignored, which the server and its workers
    keep; the imports before it can still be interrupted.

    Returns
    -------
    bool
        False (nothing done) when this process has other threads or has imported
        numpy already (its BLAS thread count is set), or ``multiprocessing.forkserver``
        is not laid out as this expects (Python 3.14 adds an authentication key).
    """
    import importlib
    import socket
    import sys
    from multiprocessing import connection, forkserver, resource_tracker, util

    server = getattr(forkserver, "_forkserver", None)
    fields = ("_forkserver_address", "_forkserver_alive_fd", "_forkserver_pid", "_lock")
    if (
        server is None
        or not all(hasattr(server, f) for f in fields)
        or hasattr(server, "_forkserver_authkey")
        or threading.active_count() > 1
        or "numpy" in sys.modules
    ):
        return False
    for name in WORKER_PRELOAD:
        importlib.import_module(name)
    with server._lock:
        if server._forkserver_pid is not None:
            return False  # one is running: ensure_running checks it is alive
        resource_tracker.ensure_running()
        with socket.socket(socket.AF_UNIX) as listener:
            address = connection.arbitrary_address("AF_UNIX")  # type: ignore[attr-defined]
            listener.bind(address)
            if not util.is_abstract_socket_namespace(address):
                os.chmod(address, 0o600)
            listener.listen()
            alive_r, alive_w = os.pipe()
            if threading.active_count() > 1:  # an import started a thread
                os.close(alive_r)
                os.close(alive_w)
                return False
            with _sigint_ignored():  # kept by the server and its workers
                pid = os.fork()
                if pid == 0:  # the server: serve until every client is gone, then exit
                    code = 1
                    try:
                        os.close(alive_w)
                        forkserver.main(listener.fileno(), alive_r, [])
                    except SystemExit:
                        code = 0
                    finally:
                        os._exit(code)
            os.close(alive_r)
        server._forkserver_address = address
        server._forkserver_alive_fd = alive_w
        server._forkserver_pid = pid
    return True


def _preload_workers() -> dict[str, Any]:
    """The Dask configuration that starts local workers from :func:`start_worker_server`."""
    import multiprocessing

    if "forkserver" not in multiprocessing.get_all_start_methods():
        return {}
    start_worker_server()
    return {"distributed.worker.multiprocessing-method": "forkserver"}


def _cores() -> int:
    """The cores this process may use (its affinity mask, else the machine's count)."""
    try:
        return len(os.sched_getaffinity(0))
    except (AttributeError, OSError):
        return os.cpu_count() or 1


def run_batch(
    jobs: Sequence[BatchJob],
    outdir: str | os.PathLike[str],
    *,
    workers: int | None = None,
    scheduler: str | None = None,
    resume: bool = False,
    report_writer: ReportWriter | None = None,
    manifest: str | os.PathLike[str] | None = None,
    progress: ProgressCallback | None = None,
) -> BatchResult:
    """Reconstruct every job on Dask and write the per-sweep folders and the summary.

    Parameters
    ----------
    jobs : sequence of BatchJob
        From :func:`read_manifest`.
    outdir : path-like
        Output folder (created if missing; its parent must exist).
    workers : int, optional
        Worker processes of the local cluster (one thread each; default: the
        machine's cores). Ignored with ``scheduler``.
    scheduler : str, optional
        Address of a running ``dask.distributed`` scheduler (``tcp://HOST:PORT``);
        its workers must see the same files at the same paths.
    resume : bool
        Skip sweeps whose outputs are complete and current (:func:`completed_row`).
    report_writer : callable, optional
        Also write each sweep's HTML report (see :data:`ReportWriter`).
    manifest : path-like, optional
        The manifest, so that it is never written over.
    progress : ProgressCallback, optional
        ``progress("sweeps", done, total)`` as sweeps finish.

    Returns
    -------
    BatchResult

    Raises
    ------
    BoneUSReconError
        Bad OUTDIR (unwritable, an input, a folder that is not ours), bad ``workers``,
        unreachable scheduler. Failing sweeps do not raise: they are rows.
    KeyboardInterrupt
        After stopping the tasks and removing their unfinished folders; the finished
        sweeps' folders stay (``resume`` picks them up), no summary is written.
    """
    if not jobs:
        raise BoneUSReconError("no sweeps to run")
    if workers is not None and workers < 1:
        raise BoneUSReconError(f"--workers must be at least 1, got {workers}")
    out = check_output_dir(outdir, "batch output").resolve()
    _check_outdir(jobs, out, Path(manifest) if manifest is not None else None)
    created = not out.exists()
    out.mkdir(exist_ok=True)
    try:
        return _run_batch(jobs, out, workers, scheduler, resume, report_writer, progress)
    except BaseException:
        if created and not any(out.iterdir()):
            out.rmdir()  # nothing was finished: leave no trace, not even the folder
        raise


def _run_batch(
    jobs: Sequence[BatchJob],
    out: Path,
    workers: int | None,
    scheduler: str | None,
    resume: bool,
    report_writer: ReportWriter | None,
    progress: ProgressCallback | None,
) -> BatchResult:
    with_report = report_writer is not None
    fps = {j.name: fingerprint(j, with_report=with_report) for j in jobs}
    rows: dict[str, dict[str, Any]] = {}
    if resume:
        for j in jobs:
            prev = completed_row(j, out, fps[j.name])
            if prev is not None:
                rows[j.name] = prev
    todo = [j for j in jobs if j.name not in rows]
    total = len(jobs)
    report(progress, "sweeps", len(rows), total)
    if todo:
        _run_on_dask(todo, out, fps, rows, workers, scheduler, report_writer, progress, total)
    ordered = [rows[j.name] for j in jobs]
    return BatchResult(rows=ordered, summary_files=write_summary(ordered, out))


def _run_on_dask(
    todo: Sequence[BatchJob],
    out: Path,
    fps: dict[str, str],
    rows: dict[str, dict[str, Any]],
    workers: int | None,
    scheduler: str | None,
    report_writer: ReportWriter | None,
    progress: ProgressCallback | None,
    total: int,
) -> None:
    token = uuid.uuid4().hex[:12]
    marker = out / f".batch.{token}.running"
    marker.touch()
    log = logging.getLogger("distributed")
    level = log.level
    try:
        with _dask_client(workers, scheduler) as client:
            from distributed import as_completed

            futures, by_key = [], {}
            try:
                for j in todo:
                    fut = client.submit(
                        run_sweep,
                        j,
                        str(out),
                        fp=fps[j.name],
                        report_writer=report_writer,
                        token=token,
                        marker=str(marker),
                        key=f"sweep-{token}-{j.name}",
                        pure=False,
                        retries=0,
                    )
                    futures.append(fut)
                    by_key[fut.key] = j
                for fut in as_completed(futures):
                    j = by_key[fut.key]
                    try:
                        rows[j.name] = fut.result()
                    except Exception as exc:  # the worker died (killed, out of memory)
                        row = _empty_row(j)
                        row.update(status="failed", error=_task_error(exc))
                        rows[j.name] = row
                    report(progress, "sweeps", len(rows), total)
            except BaseException:
                # Running tasks see the marker gone and stop (a remote worker keeps
                # running a task its client left); queued ones are cancelled. The
                # gathers the cancellation leaves unanswered the scheduler logs as
                # errors ("Couldn't gather keys ... forgotten"; once in the CI's Ctrl-C
                # test, session 47): plumbing of the interruption, which the caller
                # reports, until the cluster is closed.
                log.setLevel(logging.CRITICAL)
                marker.unlink(missing_ok=True)
                with contextlib.suppress(Exception):
                    client.cancel(futures)
                raise
    finally:
        log.setLevel(level)
        marker.unlink(missing_ok=True)
        _remove_parts(out, token)


def _task_error(exc: BaseException) -> str:
    if type(exc).__name__ == "KilledWorker":
        return "the worker process died while running this sweep (out of memory?)"
    return _one_line(exc)


def _remove_parts(out: Path, token: str) -> None:
    for p in out.glob(f".*.{token}.part"):
        shutil.rmtree(p, ignore_errors=True)

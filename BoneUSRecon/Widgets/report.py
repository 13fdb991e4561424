"""A self-contained HTML report of one reconstruction (the pictures of the paper, and more).

:func:`write_report` writes a folder holding ``index.html`` (every picture embedded as a
base64 PNG, so the page alone can be mailed or archived), the same pictures as PNG files
in ``figures/`` for reuse, and ``report.json`` with every number shown on the page. The
folder is built in a temporary folder beside the destination and renamed into place, so
an error or Ctrl-C never leaves a half-written report.

The page holds: a sweep summary (frames used and rejected, spacing, sweep length, tilt
between slices), contour overlays for a sample of frames (rejected ones marked), the
surface rendered off-screen and coloured by ``Distance`` with the segmented points on it
(the paper's Fig. 4) from two viewpoints, with gold points a histogram of the
gold-to-surface distances and the accuracy table, the Table I curve when given, the
parameters and the software versions.
"""

from __future__ import annotations

import base64
import contextlib
import dataclasses
import datetime as _dt
import html
import json
import os
import platform
import shutil
import sys
import tempfile
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from BoneUSRecon import __version__
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import check_writable_folder, json_ready
from BoneUSRecon.Logic.progress import ProgressCallback, report
from BoneUSRecon.Logic.reasons import count_reasons, format_reason_counts

__all__ = [
    "write_report",
    "check_report_folder",
    "sweep_summary",
    "software_versions",
    "histogram_png",
    "table_png",
    "table_figure",
    "human_label",
    "human_value",
    "sample_frames",
    "REPORT_MARKER",
    "PAPER_TABLE_I",
]

#: File that marks a folder as a BoneUSRecon report: only such (or empty) folders are
#: replaced by :func:`write_report`.
REPORT_MARKER = ".bone-us-recon-report"

#: The paper's Table I: mean distance from the surface to the 1145 digitised points of the
#: clavicle phantom, for 5, 10, 15 and 20 control points. The table header says cm; the
#: text (Sect. IV, "an error of 1,16mm") shows the values are millimetres.
PAPER_TABLE_I: dict[int, float] = {5: 1.71, 10: 1.32, 15: 1.26, 20: 1.16}

# Accuracy table rows: key of Evaluation.as_dict() (also the evaluate command's JSON),
# label, unit ("%" for shares in 0..1).
_ACCURACY_ROWS = (
    ("n", "gold points", ""),
    ("mean_mm", "mean distance", "mm"),
    ("rms_mm", "RMS distance", "mm"),
    ("median_mm", "median distance", "mm"),
    ("p95_mm", "95th percentile", "mm"),
    ("max_mm", "maximum distance", "mm"),
    ("within_0_5mm", "within 0.5 mm", "%"),
    ("within_1mm", "within 1 mm", "%"),
    ("within_2mm", "within 2 mm", "%"),
)


# -- numbers -------------------------------------------------------------------------
def _stats(x: np.ndarray) -> dict[str, float]:
    x = np.asarray(x, dtype=float)
    x = x[np.isfinite(x)]
    if x.size == 0:
        return {"min": float("nan"), "median": float("nan"), "max": float("nan")}
    return {"min": float(x.min()), "median": float(np.median(x)), "max": float(x.max())}


def sweep_summary(sweep: Any, segmentation: Any = None) -> dict[str, Any]:
    """Facts about a sweep (and its segmentation) for the report, JSON-ready.

    Parameters
    ----------
    sweep : Sweep
    segmentation : SegmentationResult, optional

    Returns
    -------
    dict
        ``frames``, ``valid_frames``, ``invalid_frames`` (tracking/image status),
        ``invalid_reasons`` ({reason: count}), ``width``/``height`` (px),
        ``spacing_mm`` ([sx, sy]), ``image_size_mm`` ([width, depth]),
        ``sweep_length_mm``, ``duration_s``, ``slice_gap_mm`` and ``slice_tilt_deg``
        (min/median/max between consecutive valid frames: distance between image
        centres, angle between image planes), ``tilt_range_deg`` (largest angle of a
        frame's plane to the mean plane); with a segmentation also
        ``frames_used``, ``frames_rejected`` and ``rejected_reasons`` ({reason: count}).
    """
    from BoneUSRecon.Logic.sweep import frame_planes

    idx = sweep.valid_indices
    sx, sy = (float(v) for v in sweep.spacing_mm)
    out: dict[str, Any] = {
        "source": str(sweep.source) if getattr(sweep, "source", None) else None,
        "frames": sweep.n_frames,
        "valid_frames": sweep.n_valid,
        "invalid_frames": sweep.n_frames - sweep.n_valid,
        "invalid_reasons": count_reasons(sweep.invalid_reasons),
        "width": sweep.width,
        "height": sweep.height,
        "spacing_mm": [sx, sy],
        "image_size_mm": [sx * (sweep.width - 1), sy * (sweep.height - 1)],
        "sweep_length_mm": sweep.sweep_length_mm(),
        "duration_s": sweep.duration_s(),
        "transform": getattr(sweep, "transform_name", ""),
    }
    if idx.size >= 2:
        m = sweep.image_to_reference[idx]
        c = sweep.image_centres(idx)
        _, _, normal = frame_planes(m)
        # Planes, not oriented normals: a flipped frame is not tilted by 180 degrees.
        cos_pair = np.abs(np.sum(normal[1:] * normal[:-1], axis=1)).clip(0.0, 1.0)
        mean_n = normal * np.sign(normal @ normal[0])[:, None]
        mean_n = mean_n.mean(axis=0)
        mean_n /= np.linalg.norm(mean_n)
        cos_mean = np.abs(normal @ mean_n).clip(0.0, 1.0)
        out["slice_gap_mm"] = _stats(np.linalg.norm(np.diff(c, axis=0), axis=1))
        out["slice_tilt_deg"] = _stats(np.degrees(np.arccos(cos_pair)))
        out["tilt_range_deg"] = float(np.degrees(np.arccos(cos_mean.min())))
    if segmentation is not None:
        contours = tuple(getattr(segmentation, "contours", ()))
        rejected = {c.frame: c.reason for c in contours if not c.accepted}
        out["segmentation_method"] = getattr(segmentation, "method", "")
        out["frames_used"] = sum(1 for c in contours if c.accepted)
        out["frames_rejected"] = len(rejected)
        out["rejected_reasons"] = count_reasons(rejected)
    return out


def software_versions() -> dict[str, str]:
    """Versions of Python, the platform and every library the result depends on."""
    from importlib import metadata

    out = {
        "BoneUSRecon": __version__,
        "Python": sys.version.split()[0],
        "platform": platform.platform(),
    }
    for dist in (
        "numpy",
        "scipy",
        "scikit-image",
        "SimpleITK",
        "vtk",
        "pyvista",
        "matplotlib",
        "pillow",
    ):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "not installed"
    return out


# -- pictures ------------------------------------------------------------------------
def _figure(size: tuple[float, float]) -> Any:
    # A bare Figure on the Agg canvas: no pyplot, so no global backend state is touched.
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    fig = Figure(figsize=size, dpi=100, layout="constrained")
    FigureCanvasAgg(fig)
    return fig


def _fig_png(fig: Any) -> bytes:
    import io

    buf = io.BytesIO()
    fig.savefig(buf, format="png", facecolor="white")
    return buf.getvalue()


def histogram_png(distances: np.ndarray, evaluation: dict[str, Any] | None = None) -> bytes:
    """Histogram of gold-to-surface distances (mm) as PNG bytes, mean and p95 marked."""
    d = np.asarray(distances, dtype=float)
    d = d[np.isfinite(d)]
    fig = _figure((7.0, 3.6))
    ax = fig.add_subplot()
    hi = float(d.max()) if d.size else 1.0
    bins = np.linspace(0.0, max(hi, 1e-3) * 1.0001, 41)
    ax.hist(d, bins=bins, color="#4a78b5", edgecolor="white", linewidth=0.5)
    if d.size:
        ev = evaluation or {}
        mean = float(ev.get("mean_mm", np.mean(d)))
        p95 = float(ev.get("p95_mm", np.percentile(d, 95)))
        ax.axvline(mean, color="#d62728", lw=1.5, label=f"mean {mean:.2f} mm")
        ax.axvline(p95, color="#ff7f0e", lw=1.5, ls="--", label=f"95th percentile {p95:.2f} mm")
        ax.legend(frameon=False)
    ax.set_xlabel("distance from gold point to surface (mm)")
    ax.set_ylabel("gold points")
    ax.set_title(f"Gold-to-surface distances (n = {d.size})")
    return _fig_png(fig)


def table_png(table: Sequence[tuple[int, float]], title: str = "") -> bytes:
    """The Table I curve (mean distance against control points) with the paper's values.

    PNG bytes of :func:`table_figure` (the report and ``table --plot`` draw the same).
    """
    return _fig_png(table_figure(table, title))


def table_figure(table: Sequence[tuple[int, float]], title: str = "") -> Any:
    """The Table I curve as a matplotlib Figure, its distance axis starting at 0 mm.

    From zero so that the height of a point is its distance: a curve from 0.23 to
    0.26 mm must not look as steep as the paper's 1.16 to 1.71 mm.
    """
    counts = np.array([c for c, _ in table], dtype=float)
    means = np.array([m for _, m in table], dtype=float)
    fig = _figure((6.0, 3.6))
    ax = fig.add_subplot()
    ax.plot(counts, means, "o-", color="#4a78b5", label="this reconstruction")
    pc = sorted(PAPER_TABLE_I)
    ax.plot(
        pc,
        [PAPER_TABLE_I[c] for c in pc],
        "s--",
        color="#888888",
        label="paper, Table I (clavicle phantom)",
    )
    ax.set_xlabel("control points along the bone (e)")
    ax.set_ylabel("mean distance (mm)")
    ax.set_ylim(bottom=0.0)
    ax.set_xticks(sorted(set(counts.astype(int).tolist()) | set(pc)))
    ax.grid(alpha=0.3)
    ax.legend(frameon=False)
    ax.set_title(title or "Table I: mean distance against the number of control points")
    return fig


def sample_frames(
    segmentation: Any,
    n_accepted: int = 6,
    n_rejected: int = 4,
    fit_rejected: Sequence[int] = (),
    n_fit_rejected: int = 2,
) -> list[int]:
    """Frames to show as overlays: accepted ones evenly spread, plus rejected ones.

    Parameters
    ----------
    segmentation : SegmentationResult
    n_accepted, n_rejected : int
        How many accepted and segmentation-rejected frames to show (evenly spread).
    fit_rejected : sequence of int
        Frames whose contour the robust surface fit discarded as outliers; up to
        ``n_fit_rejected`` of them are shown as well.

    Returns
    -------
    list of int
        Frame indices in file order, without repeats.
    """
    contours = tuple(getattr(segmentation, "contours", ()))
    fit_set = {int(f) for f in fit_rejected}
    acc = [c.frame for c in contours if c.accepted and c.frame not in fit_set]
    rej = [c.frame for c in contours if not c.accepted]
    fit = sorted(c.frame for c in contours if c.accepted and c.frame in fit_set)
    pick = []
    for frames, n in ((acc, n_accepted), (rej, n_rejected), (fit, n_fit_rejected)):
        if frames and n > 0:
            k = np.unique(np.linspace(0, len(frames) - 1, min(n, len(frames))).round().astype(int))
            pick += [frames[i] for i in k]
    return sorted(set(pick))


def _overlay_image(
    sweep: Any,
    contour: Any,
    truth_px: np.ndarray | None = None,
    min_width: int = 320,
    fit_rejected: bool = False,
) -> np.ndarray:
    """One contour overlay (:func:`BoneUSRecon.Widgets.overlay.overlay_image`) as RGB."""
    from BoneUSRecon.Widgets.overlay import overlay_image

    # Short: the caption under the picture gives the reason in full.
    if not contour.accepted:
        label = f"frame {contour.frame}: REJECTED"
    elif fit_rejected:
        label = f"frame {contour.frame}: fit outlier"
    else:
        label = f"frame {contour.frame}: accepted"
    scale = max(1, int(np.ceil(min_width / max(sweep.width, 1))))
    img = overlay_image(
        sweep.frames[contour.frame],
        contour.points_px,
        accepted=bool(contour.accepted),
        label=label,
        truth_px=truth_px,
        scale=scale,
    )
    return np.asarray(img.convert("RGB"))


def _png(image: np.ndarray) -> bytes:
    from BoneUSRecon.Widgets.render import png_bytes

    return png_bytes(image)


# -- the page ------------------------------------------------------------------------
_CSS = """
body{font-family:system-ui,-apple-system,"Segoe UI",Roboto,sans-serif;margin:0 auto;
max-width:1120px;padding:1.5em;color:#222;line-height:1.4}
h1{font-size:1.6em;margin-bottom:.2em}h2{border-bottom:1px solid #ddd;padding-bottom:.2em;
margin-top:1.8em}.sub{color:#666;margin-top:0}table{border-collapse:collapse;margin:.6em 0}
td,th{border:1px solid #ddd;padding:.25em .7em;text-align:left;vertical-align:top}
th{background:#f4f4f4}td.num{text-align:right;font-variant-numeric:tabular-nums}
figure{margin:.6em 0;display:inline-block;vertical-align:top}figcaption{color:#555;
font-size:.9em;max-width:1000px}img{max-width:100%;border:1px solid #eee}
.grid{display:flex;flex-wrap:wrap;gap:10px}.grid figure{width:32%;margin:0}
.rejected figcaption{color:#c0392b;font-weight:bold}.rejected img{border:3px solid #e74c3c}
.outlier figcaption{color:#b9770e;font-weight:bold}.outlier img{border:3px solid #f39c12}pre{background:#f7f7f7;padding:.8em;
overflow-x:auto;font-size:.85em}.big{font-size:1.25em;margin-bottom:.2em}
.caveat{color:#555;margin-top:0;max-width:60em}
"""


def _num(value: Any, digits: int = 2) -> str:
    if isinstance(value, (int, np.integer)):
        return str(int(value))
    try:
        v = float(value)
    except (TypeError, ValueError):
        return html.escape(str(value))
    return "n/a" if not np.isfinite(v) else f"{v:.{digits}f}"


def _kv_table(rows: Sequence[tuple[str, str]], table_id: str) -> str:
    body = "".join(f"<tr><th>{html.escape(k)}</th><td>{v}</td></tr>" for k, v in rows)
    return f'<table id="{table_id}">{body}</table>'


def _img(name: str, data: bytes, alt: str, caption: str, cls: str = "") -> str:
    b64 = base64.b64encode(data).decode("ascii")
    c = f' class="{cls}"' if cls else ""
    return (
        f'<figure{c}><img id="img-{html.escape(name)}" alt="{html.escape(alt)}" '
        f'src="data:image/png;base64,{b64}"><figcaption>{caption}</figcaption></figure>'
    )


def _range(s: dict[str, float], unit: str, digits: int = 2) -> str:
    return (
        f"{_num(s['min'], digits)} to {_num(s['max'], digits)} {unit} "
        f"(median {_num(s['median'], digits)})"
    )


def _counts(d: dict[str, int]) -> str:
    return html.escape(format_reason_counts(d))


def _sweep_rows(s: dict[str, Any]) -> list[tuple[str, str]]:
    rows = [
        ("source", html.escape(str(s.get("source") or "(in memory)"))),
        ("frames in the sweep", str(s["frames"])),
    ]
    inv = f"{s['invalid_frames']}"
    if s["invalid_reasons"]:
        inv += f" ({_counts(s['invalid_reasons'])})"
    rows.append(("frames without a usable pose or image", inv))
    if "frames_used" in s:
        rows.append(
            (
                "frames used (bone contour accepted)",
                f'<span id="frames-used">{s["frames_used"]}</span>',
            )
        )
        rej = f'<span id="frames-rejected">{s["frames_rejected"]}</span>'
        if s["rejected_reasons"]:
            rej += f" ({_counts(s['rejected_reasons'])})"
        rows.append(("frames rejected by the segmentation", rej))
    sx, sy = s["spacing_mm"]
    rows += [
        (
            "image size",
            f"{s['width']} x {s['height']} px = "
            f"{_num(s['image_size_mm'][0], 1)} x {_num(s['image_size_mm'][1], 1)} mm",
        ),
        ("pixel spacing", f"{sx:.4f} x {sy:.4f} mm (column x row)"),
        (
            "sweep length",
            f'<span id="sweep-length">{_num(s["sweep_length_mm"], 1)}</span> mm '
            f"(path of the image centre), {_num(s['duration_s'], 1)} s",
        ),
    ]
    if "slice_gap_mm" in s:
        rows += [
            ("distance between consecutive slices", _range(s["slice_gap_mm"], "mm")),
            ("tilt between consecutive slices", _range(s["slice_tilt_deg"], "deg")),
            (
                "tilt range (largest angle to the mean image plane)",
                f"{_num(s['tilt_range_deg'], 1)} deg",
            ),
        ]
    rows.append(("pose", html.escape(str(s.get("transform", "")))))
    return rows


def _accuracy_rows(ev: dict[str, Any]) -> str:
    rows = []
    for key, label, unit in _ACCURACY_ROWS:
        if key not in ev:
            continue
        v = ev[key]
        shown = (
            _num(100.0 * float(v), 1) + " %"
            if unit == "%"
            else (_num(v, 3) + (f" {unit}" if unit else ""))
        )
        rows.append(
            f'<tr><th>{label}</th><td class="num" data-key="{key}" '
            f'data-value="{float(v)!r}">{shown}</td></tr>'
        )
    return f'<table id="accuracy">{"".join(rows)}</table>'


def _table_i(table: Sequence[tuple[int, float]]) -> str:
    rows = []
    for count, mean in table:
        paper = PAPER_TABLE_I.get(int(count))
        rows.append(
            f'<tr><td class="num">{int(count)}</td><td class="num" data-count="{int(count)}"'
            f' data-value="{float(mean)!r}">{_num(mean, 3)}</td>'
            f'<td class="num">{"" if paper is None else _num(paper, 2)}</td></tr>'
        )
    return (
        '<table id="table-i"><tr><th>control points (e)</th><th>mean distance (mm)</th>'
        f"<th>paper (mm)</th></tr>{''.join(rows)}</table>"
    )


def _jsonable(obj: Any) -> Any:
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _jsonable(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, dict):
        return {str(k): _jsonable(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [_jsonable(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return obj.tolist() if obj.size <= 64 else f"array{obj.shape}"
    if isinstance(obj, np.generic):
        return obj.item()
    if isinstance(obj, (str, int, float, bool)) or obj is None:
        return obj
    return str(obj)


def _evaluation_dict(evaluation: Any) -> tuple[dict[str, Any], np.ndarray]:
    """``(numbers without distances, distances)`` from an Evaluation or its as_dict()."""
    if hasattr(evaluation, "as_dict"):
        d, dist = evaluation.as_dict(), evaluation.distances
    else:
        d = dict(evaluation)
        dist = d.pop("distances_mm", d.pop("distances", []))
    return _jsonable(d), np.asarray(dist, dtype=float)


# -- folder --------------------------------------------------------------------------
def check_report_folder(path: str | os.PathLike[str]) -> Path:
    """Check, before any work, that a report can be written to the folder ``path``.

    The folder may be missing (it is created), empty, or an earlier report (it is
    replaced); anything else is refused so that no one's files are deleted.

    Raises
    ------
    BoneUSReconError
        Missing or unwritable parent folder, a file in the way, or a folder that
        holds other things than a BoneUSRecon report.
    """
    outdir = Path(path)
    # The parent, not the folder: the report is built beside it and renamed into place.
    check_writable_folder(outdir.parent if str(outdir.parent) else Path("."), outdir)
    if outdir.exists():
        if not outdir.is_dir():
            raise BoneUSReconError("exists and is not a folder", outdir)
        if any(outdir.iterdir()) and not (outdir / REPORT_MARKER).exists():
            raise BoneUSReconError(
                "folder exists and is not a BoneUSRecon report; choose a new or empty folder",
                outdir,
            )
    return outdir


@contextlib.contextmanager
def _atomic_dir(outdir: Path) -> Any:
    """Yield a temporary folder beside ``outdir``; swap it into place on success."""
    parent = outdir.parent if str(outdir.parent) else Path(".")
    tmp = Path(tempfile.mkdtemp(prefix=f".{outdir.name}.", suffix=".part", dir=parent))
    try:
        yield tmp
        (tmp / REPORT_MARKER).write_text("BoneUSRecon report folder\n")
        umask = os.umask(0)
        os.umask(umask)
        os.chmod(tmp, 0o777 & ~umask)  # mkdtemp makes 0700 folders
        old = None
        if outdir.exists():
            old = Path(tempfile.mkdtemp(prefix=f".{outdir.name}.", suffix=".old", dir=parent))
            os.replace(outdir, old / "r")
        os.replace(tmp, outdir)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def write_report(
    recon: Any,
    outdir: str | os.PathLike[str],
    *,
    gold: np.ndarray | None = None,
    evaluation: Any = None,
    table: Sequence[tuple[int, float]] | None = None,
    parameters: dict[str, Any] | None = None,
    progress: ProgressCallback | None = None,
    truth_px: Sequence[np.ndarray] | None = None,
    title: str | None = None,
    simulated: bool = False,
) -> Path:
    """Write the HTML report of a reconstruction into the folder ``outdir``.

    Parameters
    ----------
    recon : Reconstruction
        From :func:`BoneUSRecon.Logic.pipeline.reconstruct` (uses its ``sweep``,
        ``segmentation``, ``surface``, ``points``, ``summary`` and ``timings``).
    outdir : path-like
        The report folder; created, or replaced if it is an earlier report (or empty).
    gold : ndarray, shape (K, 3), optional
        Gold-standard points (mm); the accuracy is computed with
        :func:`BoneUSRecon.Logic.evaluation.evaluate_surface` unless ``evaluation`` is
        given.
    evaluation : Evaluation, optional
        An evaluation already computed (shown as is).
    table : list of (int, float), optional
        The Table I curve: ``(control points, mean distance mm)``.
    parameters : dict, optional
        The parameters to list (default: ``recon.params`` when it has them).
    progress : ProgressCallback, optional
        Called as ``progress("report", done, total)``.
    truth_px : list of ndarray (K, 2), optional
        Per frame (indexed by frame number) the true contour in pixels, e.g. a
        simulation's ``true_contours_px``; drawn in yellow on the overlays.
    title : str, optional
        What was reconstructed (default: the sweep's file name).
    simulated : bool
        The sweep is simulated: the headline says why its accuracy is not comparable
        with the paper's real-phantom figures.

    Returns
    -------
    Path
        ``outdir / "index.html"``.

    Raises
    ------
    BoneUSReconError
        ``outdir`` cannot be written, or exists and is not a report folder.
    """
    out = check_report_folder(outdir)
    sweep = recon.sweep
    seg = getattr(recon, "segmentation", None)
    has_gold = gold is not None or evaluation is not None
    total = 4 + int(has_gold) + int(bool(table))
    step = 0

    def tick() -> None:
        nonlocal step
        step += 1
        report(progress, "report", step, total)

    report(progress, "report", 0, total)
    summary = sweep_summary(sweep, seg)
    figures: dict[str, bytes] = {}
    # report.json lists these in insertion order: sweep, reconstruction, timings_s, then
    # each section's numbers in the order the sections are built.
    recon_summary = _jsonable(dict(getattr(recon, "summary", {}) or {}))
    timings = _jsonable(dict(getattr(recon, "timings", {}) or {}))
    numbers: dict[str, Any] = {
        "sweep": summary,
        "reconstruction": recon_summary,
        "timings_s": timings,
    }

    surface_html = _surface_section(recon, recon_summary, figures, numbers)
    tick()
    accuracy_html = ""
    if has_gold:
        accuracy_html = _accuracy_section(recon, gold, evaluation, simulated, figures, numbers)
        tick()
    table_html = ""
    if table:
        table_html = _table_section(table, figures, numbers)
        tick()
    overlay_html = ""
    if seg is not None:
        overlay_html = _overlay_section(recon, summary, recon_summary, truth_px, figures)
    tick()
    if parameters is None:
        p = getattr(recon, "params", None)
        parameters = _jsonable(p) if p is not None else {}
    versions = software_versions()
    numbers["parameters"] = _jsonable(parameters)
    numbers["versions"] = versions
    tick()

    source = title or summary.get("source") or "in-memory sweep"
    sections = [_title_section(source)]
    if has_gold:
        sections.append(
            _section("accuracy-section", "Accuracy against the gold points", accuracy_html)
        )
    sections.append(_section("surface-section", "Surface", surface_html))
    if table_html:
        sections.append(_section("table-section", "Table I: control points", table_html))
    sections.append(_sweep_section(summary, figures))
    if overlay_html:
        sections.append(_section("overlay-section", "Contours on sample frames", overlay_html))
    if recon_summary or timings:
        sections.append(_reconstruction_section(recon_summary, timings))
    sections.append(_parameters_section(parameters))
    sections.append(_versions_section(versions))
    _write_folder(out, figures, numbers, _page(source, sections))
    report(progress, "report", total, total)
    return out / "index.html"


# -- the sections ----------------------------------------------------------------------
# Each builds one part of the page: it returns the part's HTML and adds its pictures to
# ``figures`` (name -> PNG bytes) and its numbers to ``numbers`` (for report.json).
def _section(section_id: str, heading: str, body: str) -> str:
    return f'<h2 id="{section_id}">{heading}</h2>{body}'


def _surface_section(
    recon: Any, recon_summary: dict[str, Any], figures: dict[str, bytes], numbers: dict[str, Any]
) -> str:
    """The surface from two viewpoints, coloured by ``Distance`` (paper Fig. 4)."""
    from BoneUSRecon.Widgets.render import distance_array, render_views

    sweep = recon.sweep
    views = render_views(
        recon.surface,
        points=getattr(recon, "points", None),
        sweep=sweep,
        window_size=(1000, 620),
        fit_height=True,
    )
    # The sweep section's picture, rendered here with the surface's scene settings.
    figures["sweep"] = _png(
        render_views(
            recon.surface,
            sweep=sweep,
            views=("oblique",),
            window_size=(1000, 560),
            show_frames=True,
        )["oblique"]
    )
    dist = distance_array(recon.surface)
    surf_caption = (
        "Reconstructed surface coloured by <i>Distance</i>, the distance (mm) "
        "from each vertex to the nearest segmented point; red dots are the "
        "segmented contour points (the paper's Fig. 4)."
    )
    if dist is not None and np.isfinite(dist).any():
        numbers["surface_distance_mm"] = {
            "mean": float(np.nanmean(dist)),
            "max": float(np.nanmax(dist)),
        }
    else:
        surf_caption = (
            "Reconstructed surface (it has no <i>Distance</i> array); red dots "
            "are the segmented contour points."
        )
    figs_html = []
    for name, image in views.items():
        figures[f"surface_{name}"] = _png(image)
        what = "seen from the probe's side" if name == "top" else "oblique view showing the relief"
        figs_html.append(
            _img(
                f"surface-{name}",
                figures[f"surface_{name}"],
                f"surface, {name} view",
                f"{surf_caption} {what.capitalize()}.",
            )
        )
    surface_html = "".join(figs_html)
    n_vert = int(recon.surface.GetNumberOfPoints())
    n_pts = 0 if getattr(recon, "points", None) is None else int(recon.points.GetNumberOfPoints())
    surface_html += (
        f"<p>{n_vert} surface vertices, {n_pts} segmented points. "
        "A scale bar (lower right) gives the size; the x, y, z triad (lower "
        "left) the orientation of the sweep's reference frame.</p>"
    )
    return surface_html + _holes_note(recon_summary)


def _holes_note(recon_summary: dict[str, Any]) -> str:
    """Why the surface has notches and holes (trimmed to the data), with the grid cover."""
    cover = recon_summary.get("grid_coverage")
    grid = recon_summary.get("grid_shape")
    cover_text = (
        f" ({100 * float(cover):.0f} % of the {grid[0]} slices x {grid[1]} rays "
        "grid holds a contour point)"
        if cover is not None and grid
        else ""
    )
    return (
        '<p id="holes-note"><b>Notches and holes in the surface</b> are where no '
        f"segmented contour supports it{cover_text}: the surface is trimmed to the data "
        "rather than extrapolated. They appear where a ray around the bone met no contour "
        "(the bone's flanks, steep to the beam, often return no echo) and beyond the "
        "first and last slices with a contour; rejected frames leave gaps between "
        "slices, which the fit bridges.</p>"
    )


def _accuracy_section(
    recon: Any,
    gold: np.ndarray | None,
    evaluation: Any,
    simulated: bool,
    figures: dict[str, bytes],
    numbers: dict[str, Any],
) -> str:
    """Headline mean distance, the accuracy table, the histogram and the error map."""
    if evaluation is None:
        from BoneUSRecon.Logic.evaluation import evaluate_surface

        evaluation = evaluate_surface(recon.surface, np.asarray(gold, dtype=float))
    ev, ev_dist = _evaluation_dict(evaluation)
    numbers["evaluation"] = ev
    figures["histogram"] = histogram_png(ev_dist, ev)
    gold_pts = np.asarray(gold, dtype=float) if gold is not None else None
    if gold_pts is not None and len(gold_pts) == len(ev_dist):
        from BoneUSRecon.Widgets.render import render_error_map

        figures["gold_errors"] = _png(
            render_error_map(recon.surface, gold_pts, ev_dist, sweep=recon.sweep)
        )
    caveat = (
        "This sweep is simulated: it has no tracking, calibration, registration or "
        "speed-of-sound error, which the paper's figure includes and which would "
        "add to this one on a real phantom, so the two are not like for like."
        if simulated
        else "The paper's figure includes its tracking, calibration and registration "
        "error; compare with it only for a like experiment."
    )
    return (
        f'<p class="big">Mean distance from the gold points to the surface: '
        f'<b id="headline-mean">{_num(ev.get("mean_mm"), 2)} mm</b> '
        f"(the paper reports 1.16 to 1.71 mm on its real clavicle phantom).</p>"
        f'<p id="headline-caveat" class="caveat">{caveat}</p>'
        + _accuracy_rows(ev)
        + _img(
            "histogram",
            figures["histogram"],
            "histogram of distances",
            "Distances from each gold point to the nearest point of the surface.",
        )
        + (
            _img(
                "gold-errors",
                figures["gold_errors"],
                "gold points by distance",
                "Where the surface is off: the gold points coloured by their distance "
                "to the (grey) surface, seen from the probe's side.",
            )
            if "gold_errors" in figures
            else ""
        )
    )


def _table_section(
    table: Sequence[tuple[int, float]], figures: dict[str, bytes], numbers: dict[str, Any]
) -> str:
    """The Table I curve: mean distance against the number of control points."""
    table = [(int(c), float(m)) for c, m in table]
    numbers["table_i"] = [{"control_points": c, "mean_mm": m} for c, m in table]
    figures["table_i"] = table_png(table)
    return _table_i(table) + _img(
        "table-i",
        figures["table_i"],
        "Table I curve",
        "Mean gold-to-surface distance when the surface is refitted with e control "
        "points along the bone (the paper's Table I).",
    )


def _overlay_section(
    recon: Any,
    summary: dict[str, Any],
    recon_summary: dict[str, Any],
    truth_px: Sequence[np.ndarray] | None,
    figures: dict[str, bytes],
) -> str:
    """Contours drawn on a sample of frames: accepted, rejected and fit outliers."""
    seg = recon.segmentation
    by_frame = {c.frame: c for c in seg.contours}
    fit_rej = [int(f) for f in (recon_summary.get("fit_rejected_frames") or [])]
    tiles = []
    for k in sample_frames(seg, fit_rejected=fit_rej):
        c = by_frame[k]
        truth = truth_px[k] if truth_px is not None and k < len(truth_px) else None
        outlier = bool(c.accepted and k in fit_rej)
        data = _png(_overlay_image(recon.sweep, c, truth, fit_rejected=outlier))
        figures[f"frame_{k:04d}"] = data
        conf = _num(getattr(c, "confidence", float("nan")), 2)
        if not c.accepted:
            cap = f"frame {k}: REJECTED: {html.escape(c.reason or 'no reason given')}"
        elif outlier:
            cap = (
                f"frame {k}: accepted by the segmentation (confidence {conf}), "
                "discarded as an outlier by the robust surface fit"
            )
        else:
            cap = f"frame {k}: accepted, {len(c.points_px)} points, confidence {conf}"
        cls = "rejected" if not c.accepted else ("outlier" if outlier else "")
        tiles.append(_img(f"frame-{k:04d}", data, f"frame {k}", cap, cls))
    n_rej = summary.get("frames_rejected", 0)
    return (
        f"<p>{len(tiles)} frames of {len(by_frame)} segmented "
        f"({n_rej} rejected in all, {len(fit_rej)} more discarded by the robust fit; "
        "rejected frames are outlined in red, fit outliers in orange, "
        "accepted contours drawn in green"
        + ("; the true contour in yellow" if truth_px is not None else "")
        + ").</p>"
        f'<div class="grid">{"".join(tiles)}</div>'
    )


def _title_section(source: Any) -> str:
    now = _dt.datetime.now(_dt.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")
    return (
        f"<h1>Bone surface reconstruction</h1><p class='sub'>"
        f"{html.escape(str(source))} &middot; BoneUSRecon {__version__} &middot; {now}</p>"
    )


def _sweep_section(summary: dict[str, Any], figures: dict[str, bytes]) -> str:
    """The sweep's numbers and its image planes around the surface."""
    return _section(
        "sweep-section",
        "Sweep",
        _kv_table(_sweep_rows(summary), "sweep")
        + _img(
            "sweep",
            figures["sweep"],
            "the sweep's image planes",
            "The image planes of the sweep (grey; frames without a usable "
            "pose in orange) around the reconstructed surface.",
        ),
    )


def _reconstruction_section(recon_summary: dict[str, Any], timings: dict[str, Any]) -> str:
    """The reconstruction's summary and the time of each stage."""
    rows = [
        (human_label(k), html.escape(human_value(k, v)))
        for k, v in recon_summary.items()
        if v is not None and v != "" and k != "source"
    ]
    rows += [
        (f"time: {_TIME_LABELS.get(k, human_label(k))}", f"{_num(v, 2)} s")
        for k, v in timings.items()
    ]
    return _section("recon-section", "Reconstruction", _kv_table(rows, "reconstruction"))


def _parameters_section(parameters: Any) -> str:
    params_json = json.dumps(_jsonable(parameters), indent=2, default=str)
    return _section(
        "parameters-section",
        "Parameters",
        "<details><summary>every parameter of this run (JSON; also in "
        "report.json)</summary>"
        f'<pre id="parameters">{html.escape(params_json)}</pre></details>',
    )


def _versions_section(versions: dict[str, str]) -> str:
    rows = [(k, html.escape(v)) for k, v in versions.items()]
    return _section("versions-section", "Software", _kv_table(rows, "versions"))


def _page(source: Any, sections: Sequence[str]) -> str:
    return (
        "<!DOCTYPE html>\n<html lang='en'><head><meta charset='utf-8'>"
        "<meta name='viewport' content='width=device-width, initial-scale=1'>"
        f"<title>BoneUSRecon report: {html.escape(Path(str(source)).name)}</title>"
        f"<style>{_CSS}</style></head><body>\n" + "\n".join(sections) + "\n</body></html>\n"
    )


def _write_folder(out: Path, figures: dict[str, bytes], numbers: dict[str, Any], page: str) -> None:
    """Write the page, its pictures and report.json, atomically (see :func:`_atomic_dir`)."""
    with _atomic_dir(out) as tmp:
        (tmp / "figures").mkdir()
        for name, data in figures.items():
            (tmp / "figures" / f"{name}.png").write_bytes(data)
        (tmp / "report.json").write_text(
            json.dumps(json_ready(_jsonable(numbers)), indent=2, default=str)
        )
        (tmp / "index.html").write_text(page, encoding="utf-8")


#: Labels of :attr:`Reconstruction.summary` keys on the page (keys not listed here,
#: e.g. added later, get :func:`human_label`'s generic form).
_RECON_LABELS = {
    "frames": "frames in the file",
    "valid_frames": "frames with a usable pose and image",
    "segmented_frames": "frames with an accepted bone contour",
    "rejected_frames": "frames rejected by the segmentation",
    "rejected": "rejected frames (frame: reason)",
    "segmenter": "segmenter",
    "segmented_points": "segmented contour points",
    "grid_shape": "resampling grid (slices x rays)",
    "grid_coverage": "grid cells holding a contour point",
    "mean_resampling_distance_mm": "mean distance from a grid point to its contour",
    "axis_length_mm": "length of the central axis",
    "degree": "B-spline degrees (along x around)",
    "control_points": "control points (along x around)",
    "fit_method": "least-squares method",
    "fit_rms_mm": "fit residual, RMS of the kept points",
    "fit_rms_all_mm": "fit residual, RMS of all points",
    "fit_outlier_points": "points down-weighted as outliers",
    "fit_rejected_frames": "frames discarded by the robust fit",
    "surface_points": "surface vertices",
    "surface_triangles": "surface triangles",
    "surface_area_mm2": "surface area",
}
_TIME_LABELS = {
    "segment": "segmentation",
    "resample": "resampling",
    "fit": "surface fit",
    "surface": "meshing",
    "total": "total",
}
_UNITS = (("_mm2", "mm\u00b2"), ("_mm", "mm"), ("_deg", "deg"), ("_px", "px"), ("_s", "s"))


def human_label(key: str) -> str:
    """A page label for a summary key: ``"fit_rms_mm"`` -> ``"fit residual, RMS ..."``.

    Known keys have a written label; any other loses its unit suffix (shown with the
    value by :func:`human_value`) and its underscores.
    """
    if key in _RECON_LABELS:
        return _RECON_LABELS[key]
    for suffix, _ in _UNITS:
        if key.endswith(suffix):
            key = key[: -len(suffix)]
            break
    return key.replace("_", " ").strip() or "value"


def human_value(key: str, value: Any) -> str:
    """A summary value as text, with the unit its key names (``_mm``, ``_mm2``, ...)."""
    if key in ("grid_shape", "degree", "control_points") and isinstance(value, (list, tuple)):
        return " x ".join(str(v) for v in value)
    if key.endswith("coverage") and isinstance(value, float):
        return f"{100 * value:.1f} %"
    if key == "rejected" and isinstance(value, dict):
        return "; ".join(f"frame {k}: {v}" for k, v in value.items()) or "none"
    if isinstance(value, (list, tuple)) and not value:
        return "none"
    text = _fmt_value(value)
    for suffix, unit in _UNITS:
        if key.endswith(suffix) and isinstance(value, (int, float)):
            return f"{text} {unit}"
    return text


def _fmt_value(v: Any) -> str:
    if isinstance(v, float):
        return f"{v:.4g}"
    if isinstance(v, (list, tuple)):
        return ", ".join(_fmt_value(x) for x in v)
    if isinstance(v, dict):
        return "; ".join(f"{k}: {_fmt_value(x)}" for k, x in v.items())
    return str(v)

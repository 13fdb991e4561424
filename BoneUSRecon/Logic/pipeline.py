"""The whole reconstruction: segmentation -> resampling -> B-spline fit -> surface mesh.

:func:`reconstruct` chains the stages of the paper (B, C, D) on a :class:`Sweep` and
times each; :func:`surface_from_contours` runs only C and D on contours obtained
elsewhere (e.g. a simulator's true contours); :func:`control_point_table` reproduces
the paper's Table I (mean gold-to-surface distance against the number of control
points).
"""

from __future__ import annotations

import dataclasses
import time
import warnings
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from vtkmodules.vtkCommonDataModel import vtkPolyData

from BoneUSRecon.Logic.bspline import FitParams, FitResult, fit_surface
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.params_check import check_fields
from BoneUSRecon.Logic.progress import ProgressCallback, report
from BoneUSRecon.Logic.resampling import ResampledGrid, ResamplingParams, resample
from BoneUSRecon.Logic.segmentation import (
    SegmentationParams,
    SegmentationResult,
    points_polydata,
    segment_sweep,
)
from BoneUSRecon.Logic.surface import SurfaceParams, surface_area, surface_polydata
from BoneUSRecon.Logic.sweep import Sweep

__all__ = [
    "ReconstructionParams",
    "Reconstruction",
    "reconstruct",
    "surface_from_contours",
    "reconstruction_from_segmentation",
    "control_point_table",
    "params_with",
]


@dataclass(frozen=True)
class ReconstructionParams:
    """All parameters of :func:`reconstruct`, one dataclass per stage.

    Attributes
    ----------
    segmentation : SegmentationParams
        Paper II.B (segmenter name, snake parameters, rejection).
    resampling : ResamplingParams
        Paper II.C (rays, axis).
    fit : FitParams
        Paper II.D (degrees, control points, robust weights).
    surface : SurfaceParams
        Mesh sampling and trimming.
    """

    segmentation: SegmentationParams = field(default_factory=SegmentationParams)
    resampling: ResamplingParams = field(default_factory=ResamplingParams)
    fit: FitParams = field(default_factory=FitParams)
    surface: SurfaceParams = field(default_factory=SurfaceParams)

    def __post_init__(self) -> None:
        check_fields(self)  # each part is an instance of its class (which checked itself)


@dataclass(frozen=True, eq=False)
class Reconstruction:
    """Everything a reconstruction produced.

    Attributes
    ----------
    sweep : Sweep
    segmentation : SegmentationResult
    grid : ResampledGrid
    fit : FitResult
    surface : vtkPolyData
        The trimmed mesh with ``Normals``, ``TCoords`` and ``Distance``.
    points : vtkPolyData
        The accepted segmented points with ``Frame``, ``Intensity``, ``Confidence``.
    summary : dict
        Frames used and rejected, grid coverage, fit residual, ... (JSON-ready).
    timings : dict[str, float]
        Seconds per stage (``segment``, ``resample``, ``fit``, ``surface``, ``points``:
        the segmented points' polydata, ``total``).
    params : ReconstructionParams
    """

    sweep: Sweep
    segmentation: SegmentationResult
    grid: ResampledGrid
    fit: FitResult
    surface: vtkPolyData
    points: vtkPolyData
    summary: dict[str, Any]
    timings: dict[str, float]
    params: ReconstructionParams


def params_with(
    base: ReconstructionParams | None = None,
    *,
    segmenter: str | None = None,
    degree: Sequence[int] | None = None,
    n_control_points: Sequence[int] | None = None,
    along: int | None = None,
    around: int | None = None,
    rays: int | None = None,
    fit_method: str | None = None,
    robust: str | None = None,
    axis: str | None = None,
    control_points: Sequence[int] | None = None,
    flank_extension_mm: float | None = None,
    bone_points: Sequence[Sequence[float]] | np.ndarray | None = None,
) -> ReconstructionParams:
    """``base`` with the user's choices: what the CLI options and the Slicer module set.

    Parameters
    ----------
    base : ReconstructionParams, optional
        Values for everything left ``None`` (default: the paper's defaults).
    segmenter : str, optional
        A name in :data:`BoneUSRecon.Logic.segmentation.SEGMENTERS`.
    degree, n_control_points : (int, int), optional
        Spline degrees ``(p, q)`` and numbers of control points ``(e, f)``, along and
        around the bone.
    along, around : int, optional
        One of the two control-point counts (``e`` or ``f``), the other kept (from
        ``n_control_points`` if given, else from ``base``).
    control_points : (int, int), optional
        Former name of ``n_control_points`` (``DeprecationWarning``).
    rays : int, optional
        Rays per slice.
    fit_method : {"direct", "separable"}, optional
    robust : {"tukey", "huber", "none"}, optional
    axis : {"spline", "line"}, optional
    flank_extension_mm : float, optional
        How far each cross-section of the surface is continued down its flanks past the
        data, mm (:class:`~BoneUSRecon.Logic.surface.SurfaceParams`; 0 is off).
    bone_points : sequence of (x, y, z), optional
        Points on the bone to follow, reference mm (a markup placed on the bone; where
        two bones are in view, the one to segment): ``RejectionParams.bone_points``,
        see :mod:`BoneUSRecon.Logic.segmentation.bone_point`. An empty sequence clears
        them.

    Returns
    -------
    ReconstructionParams

    Raises
    ------
    BoneUSReconError
        Unknown segmenter; absurd values, as refused by :class:`SegmentationParams`,
        :class:`FitParams`, :class:`ResamplingParams` and :class:`SurfaceParams` (e.g.
        fewer control points than degree + 1, a negative flank extension, a bone point
        without three finite coordinates).
    """
    p = ReconstructionParams() if base is None else base
    seg = p.segmentation
    if segmenter is not None:
        seg = dataclasses.replace(seg, method=segmenter)  # SegmentationParams checks the name
    if bone_points is not None:  # RejectionParams checks them (three finite numbers each)
        rej = dataclasses.replace(seg.rejection, bone_points=bone_points)
        seg = dataclasses.replace(seg, rejection=rej)
    if control_points is not None:
        warnings.warn(
            "params_with(control_points=...) is now n_control_points=...",
            DeprecationWarning,
            stacklevel=2,
        )
        n_control_points = control_points if n_control_points is None else n_control_points
    if along is not None or around is not None:
        e, f = p.fit.n_control_points if n_control_points is None else n_control_points
        n_control_points = (e if along is None else along, f if around is None else around)
    # FitParams and ResamplingParams coerce and check the values (15.0 -> 15; 15.5 refused).
    fit_changes: dict[str, Any] = {
        k: v
        for k, v in (
            ("degree", None if degree is None else tuple(degree)),
            ("n_control_points", None if n_control_points is None else tuple(n_control_points)),
            ("method", fit_method),
            ("robust", robust),
        )
        if v is not None
    }
    res_changes: dict[str, Any] = {
        k: v for k, v in (("n_rays", rays), ("axis", axis)) if v is not None
    }
    surface = p.surface
    if flank_extension_mm is not None:  # SurfaceParams checks the value
        surface = dataclasses.replace(surface, flank_extension_mm=float(flank_extension_mm))
    fit = dataclasses.replace(p.fit, **fit_changes)  # FitParams checks the values
    if fit.n_control_points != p.fit.n_control_points:
        # Control points asked for, other than the base's, are fitted as asked or
        # refused (an absurd request is an error); the base's count is a ceiling a short
        # grid lowers (FitParams.fewer_if_short), however it is passed (Slicer always
        # passes it). Compared once FitParams has coerced them (15.0 -> 15).
        fit = dataclasses.replace(fit, fewer_if_short=False)
    return dataclasses.replace(
        p,
        segmentation=seg,
        fit=fit,
        resampling=dataclasses.replace(p.resampling, **res_changes),
        surface=surface,
    )


def surface_from_contours(
    contours_mm: Sequence[tuple[int, np.ndarray]],
    sweep: Sweep,
    params: ReconstructionParams = ReconstructionParams(),
    *,
    segmented_points: np.ndarray | None = None,
    progress: ProgressCallback | None = None,
    timings: dict[str, float] | None = None,
) -> tuple[ResampledGrid, FitResult, vtkPolyData]:
    """Paper steps C and D on given contours: resample, fit, mesh.

    Parameters
    ----------
    contours_mm : sequence of (frame, ndarray (K, 3))
        Contours in reference mm, ordered along each contour.
    sweep : Sweep
    params : ReconstructionParams
        Its ``resampling``, ``fit`` and ``surface`` parts are used.
    segmented_points : ndarray (K, 3), optional
        Points for the ``Distance`` array (default: all contour points).
    progress : ProgressCallback, optional
    timings : dict, optional
        Filled with seconds for ``resample``, ``fit`` and ``surface``.

    Returns
    -------
    grid, fit, surface
    """
    t = timings if timings is not None else {}
    t0 = time.perf_counter()
    _check_probe_moves([k for k, _ in contours_mm], sweep)
    report(progress, "resample", 0, 1)
    grid = resample(contours_mm, sweep, params.resampling)
    t1 = time.perf_counter()
    report(progress, "fit", 0, 1)
    fit = fit_surface(grid.points, params.fit, u=grid.axis_position, v=grid.angles)
    t2 = time.perf_counter()
    report(progress, "surface", 0, 1)
    if segmented_points is None:
        segmented_points = np.concatenate([np.asarray(p).reshape(-1, 3) for _, p in contours_mm])
    surf = surface_polydata(fit, grid, segmented_points, params.surface)
    t3 = time.perf_counter()
    report(progress, "surface", 1, 1)
    t.update(resample=t1 - t0, fit=t2 - t1, surface=t3 - t2)
    return grid, fit, surf


#: Below this extent of the image centres along the sweep (mm) the probe was held
#: still: the slices are one cross-section seen again and again, and no surface along
#: the bone can be built (tracking jitter alone spans a few tenths of a mm).
MIN_SWEEP_EXTENT_MM = 2.0


def _check_probe_moves(frames: Sequence[int], sweep: Sweep) -> None:
    """Refuse sweeps whose segmented frames do not advance along the bone."""
    idx = np.asarray(frames, dtype=int)
    if idx.size < 2:
        return  # resample() gives the "too few slices" error
    hw = np.array([(sweep.width - 1) / 2, (sweep.height - 1) / 2, 0.0, 1.0])
    c = np.einsum("nab,b->na", sweep.image_to_reference[idx, :3, :], hw)
    c = c - c.mean(0)
    extent = float(np.ptp(c @ np.linalg.svd(c, full_matrices=False)[2][0]))
    if not extent >= MIN_SWEEP_EXTENT_MM:
        raise BoneUSReconError(
            f"the probe does not move: the {idx.size} frames with a bone contour span "
            f"only {extent:.2f} mm (at least {MIN_SWEEP_EXTENT_MM:g} mm are needed to "
            "build a surface along the bone)",
            sweep.source,
        )


def reconstruct(
    sweep: Sweep,
    params: ReconstructionParams = ReconstructionParams(),
    progress: ProgressCallback | None = None,
) -> Reconstruction:
    """Reconstruct the imaged bone surface from a tracked sweep.

    Parameters
    ----------
    sweep : Sweep
    params : ReconstructionParams
    progress : ProgressCallback, optional
        Called with stages ``segment``, ``resample``, ``fit``, ``surface``.

    Returns
    -------
    Reconstruction

    Raises
    ------
    BoneUSReconError
        No bone found, too few usable slices, or too few grid points for the requested
        control points (each names the sweep file when known).
    """
    t0 = time.perf_counter()
    seg = segment_sweep(sweep, params.segmentation, progress)
    return reconstruction_from_segmentation(
        sweep, seg, params, segment_s=time.perf_counter() - t0, progress=progress
    )


def reconstruction_from_segmentation(
    sweep: Sweep,
    seg: SegmentationResult,
    params: ReconstructionParams = ReconstructionParams(),  # noqa: B008 (frozen dataclass)
    *,
    segment_s: float = 0.0,
    progress: ProgressCallback | None = None,
    with_points: bool = True,
) -> Reconstruction:
    """Resample, fit and mesh a segmentation: :func:`reconstruct` after its first step.

    Used by :func:`reconstruct` and by live reconstruction, which segments frames as
    they arrive and refits from the segmentation so far.

    Parameters
    ----------
    sweep : Sweep
        The sweep ``seg`` was made from (its poses place the contours).
    seg : SegmentationResult
    params : ReconstructionParams
    segment_s : float
        Seconds the segmentation took (reported in the timings).
    progress : callable, optional
    with_points : bool
        Build :attr:`Reconstruction.points`; False leaves an empty polydata (a live
        refit that only shows the surface saves a fifth of its time).

    Returns
    -------
    Reconstruction
    """
    timings: dict[str, float] = {"segment": segment_s}
    t0 = time.perf_counter()
    # The surface from the frames that moved: a frame at rest repeats the contour of the
    # frame standing for it (RejectionParams.at_rest_mm), one position, not more data.
    contours = [(c.frame, c.points_mm(sweep)) for c in seg.accepted if "at_rest_of" not in c.extras]
    # The contours' points, without mapping every contour a second time.
    pts = np.concatenate([c for _, c in contours]) if contours else np.empty((0, 3))
    try:
        # A probe that never moved is told so, whatever frames stand for the others.
        _check_probe_moves([c.frame for c in seg.accepted], sweep)
        grid, fit, surf = surface_from_contours(
            contours, sweep, params, segmented_points=pts, progress=progress, timings=timings
        )
    except BoneUSReconError as exc:
        if exc.path is None and sweep.source is not None:
            raise BoneUSReconError(exc.message, sweep.source) from None
        raise
    t1 = time.perf_counter()
    points = points_polydata(seg, sweep) if with_points else vtkPolyData()
    timings["points"] = time.perf_counter() - t1
    timings["total"] = segment_s + time.perf_counter() - t0
    return Reconstruction(
        sweep=sweep,
        segmentation=seg,
        grid=grid,
        fit=fit,
        surface=surf,
        points=points,
        summary=_summary(sweep, seg, grid, fit, surf, params),
        timings=timings,
        params=params,
    )


def _summary(
    sweep: Sweep,
    seg: SegmentationResult,
    grid: ResampledGrid,
    fit: FitResult,
    surf: vtkPolyData,
    params: ReconstructionParams,
) -> dict[str, Any]:
    rejected = seg.rejected
    down = grid.frames[fit.frame_weights <= 0]
    area = surface_area(surf)
    return {
        "source": str(sweep.source) if sweep.source else None,
        "frames": sweep.n_frames,
        "valid_frames": sweep.n_valid,
        "segmented_frames": len(seg.accepted),
        "rejected_frames": len(rejected),
        "rejected": {str(k): v for k, v in sorted(rejected.items())},
        "segmenter": seg.method,
        "segmented_points": seg.n_points,
        "grid_shape": list(grid.shape),
        "grid_coverage": grid.coverage,
        "mean_resampling_distance_mm": grid.mean_resampling_distance_mm,
        "axis_length_mm": float(grid.axis_position[-1]),
        "degree": list(params.fit.degree),
        "control_points": list(fit.n_control_points),
        "fit_method": fit.method,
        "fit_rms_mm": fit.rms_mm,
        "fit_rms_all_mm": fit.rms_all_mm,
        "fit_outlier_points": fit.n_outliers,
        "fit_rejected_frames": [int(k) for k in down],
        "surface_points": int(surf.GetNumberOfPoints()),
        "surface_triangles": int(surf.GetNumberOfCells()),
        "surface_area_mm2": area,
        "surface_triangles_per_mm2": surf.GetNumberOfCells() / area if area > 0 else 0.0,
        "bone_points": [list(q) for q in params.segmentation.rejection.bone_points],
        "warnings": list(seg.warnings) + _fit_warnings(grid, fit, params),
    }


def _fit_warnings(grid: ResampledGrid, fit: FitResult, params: ReconstructionParams) -> list[str]:
    """What the user should know of the fit: fewer control points than asked."""
    if fit.n_control_points == params.fit.n_control_points:
        return []
    (e, f), (e0, f0) = fit.n_control_points, params.fit.n_control_points
    return [
        f"{int(grid.valid.any(axis=1).sum())} slices hold data: the surface has {e} x {f} "
        f"control points, not {e0} x {f0} (FitParams.fewer_if_short)"
    ]


def control_point_table(
    source: Sweep | Reconstruction,
    gold: np.ndarray,
    counts: Sequence[int] = (5, 10, 15, 20),
    params: ReconstructionParams = ReconstructionParams(),
    progress: ProgressCallback | None = None,
) -> list[tuple[int, float]]:
    """The paper's Table I: mean gold-to-surface distance for each number of control points.

    The number of control points along the bone (``e``) varies; ``f`` and the degrees
    stay those of ``params.fit`` (or of the reconstruction's parameters). Segmentation
    and resampling are done once.

    Parameters
    ----------
    source : Sweep or Reconstruction
        A sweep (reconstructed first) or a finished reconstruction (its grid reused).
    gold : ndarray, shape (K, 3)
        Gold-standard points (mm).
    counts : sequence of int
        Control-point counts ``e`` (paper: 5, 10, 15, 20).
    params : ReconstructionParams
        Used when ``source`` is a sweep.
    progress : ProgressCallback, optional

    Returns
    -------
    list of (e, mean distance mm)
    """
    if not len(counts):
        raise BoneUSReconError("no control-point counts given")
    recon = source if isinstance(source, Reconstruction) else reconstruct(source, params, progress)
    p = recon.params
    grid = recon.grid
    seg_pts = recon.segmentation.points_mm(recon.sweep).xyz
    rows: list[tuple[int, float]] = []
    for n, e in enumerate(counts):
        report(progress, "table", n, len(counts))
        # Each count as asked (Table I's rows), none lowered on a short grid.
        fp = dataclasses.replace(
            p.fit, n_control_points=(int(e), p.fit.n_control_points[1]), fewer_if_short=False
        )
        try:
            fit = fit_surface(grid.points, fp, u=grid.axis_position, v=grid.angles)
        except BoneUSReconError as exc:  # name the sweep, as reconstruct() does
            if exc.path is None and recon.sweep.source is not None:
                raise BoneUSReconError(exc.message, recon.sweep.source) from None
            raise
        surf = surface_polydata(fit, grid, seg_pts, p.surface)
        rows.append((int(e), evaluate_surface(surf, gold).mean))
    report(progress, "table", len(counts), len(counts))
    return rows

"""Segment a whole sweep: per-frame segmenter, temporal prior, confidence, rejection."""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.progress import ProgressCallback, report
from BoneUSRecon.Logic.segmentation.detection import Detection
from BoneUSRecon.Logic.segmentation.params import SEGMENTER_NAMES, SegmentationParams
from BoneUSRecon.Logic.segmentation.rejection import (
    frame_evidence,
    frame_verdict,
    neighbour_deviation,
    trim_kinked_ends,
    trim_unshadowed_ends,
)
from BoneUSRecon.Logic.segmentation.result import FrameContour, SegmentationResult
from BoneUSRecon.Logic.segmentation.shadowpath import shadowpath_frame
from BoneUSRecon.Logic.segmentation.snake import snake_frame
from BoneUSRecon.Logic.sweep import Sweep, pixel_spacing

__all__ = [
    "SEGMENTERS",
    "FrameSegmenter",
    "segment_frame",
    "segment_sweep",
    "frame_candidate",
    "select_contours",
]

#: ``(image uint8 (H, W), spacing (sx, sy), params, prior_px or None) -> Detection``
FrameSegmenter = Callable[
    [np.ndarray, tuple[float, float], SegmentationParams, "np.ndarray | None"], Detection
]


def _snake(image, spacing, params, prior):  # type: ignore[no-untyped-def]
    return snake_frame(image, spacing, params.snake, params.posterior, prior)


def _shadowpath(image, spacing, params, prior):  # type: ignore[no-untyped-def]
    return shadowpath_frame(image, spacing, params.shadowpath, prior)


#: Segmenters by name. "shadowpath" (default) is the more accurate; "snake" is the paper's.
SEGMENTERS: dict[str, FrameSegmenter] = {"shadowpath": _shadowpath, "snake": _snake}
# SegmentationParams checks a name against SEGMENTER_NAMES (import-free); keep them one list.
assert tuple(SEGMENTERS) == SEGMENTER_NAMES


def segment_frame(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: SegmentationParams = SegmentationParams(),  # noqa: B008 (frozen dataclass)
    prior_px: np.ndarray | None = None,
) -> Detection:
    """Run the segmenter named by ``params.method`` on one frame (no rejection)."""
    # params.method was checked when the SegmentationParams was made.
    return SEGMENTERS[params.method](np.asarray(image), spacing, params, prior_px)


def segment_sweep(
    sweep: Sweep,
    params: SegmentationParams = SegmentationParams(),  # noqa: B008 (frozen dataclass)
    progress: ProgressCallback | None = None,
) -> SegmentationResult:
    """Segment every valid frame of ``sweep`` and reject implausible contours.

    Frames are processed in file order; each frame's segmenter is seeded by the last
    *accepted* contour (the paper's initialisation rule for the snake, a temporal prior
    for shadowpath), so a failed frame does not lead the next one astray. After all
    frames, contours that jump away from their neighbours are rejected too.

    Parameters
    ----------
    sweep : Sweep
    params : SegmentationParams
    progress : callable, optional
        ``progress("segment", done, total)``.

    Returns
    -------
    SegmentationResult

    Raises
    ------
    BoneUSReconError
        No valid frame, or no bone contour in any frame (an unknown segmenter is
        refused by :class:`SegmentationParams` itself).
    """
    idx = sweep.valid_indices
    if idx.size == 0:
        raise BoneUSReconError("no valid frame to segment", sweep.source)
    spacing_all = pixel_spacing(sweep.image_to_reference)
    t0 = time.perf_counter()
    dets: dict[int, Detection] = {}
    verdicts: dict[int, tuple[float, str]] = {}
    prior: np.ndarray | None = None
    # iter_frames releases the memory-mapped pages as it goes: a 600 MB sweep is
    # segmented without its pages piling up in the resident set.
    for n, (k, image) in enumerate(sweep.iter_frames(idx)):
        sp = (float(spacing_all[k, 0]), float(spacing_all[k, 1]))
        dets[k], conf, reason = frame_candidate(image, sp, params, prior)
        verdicts[k] = (conf, reason)
        if not reason:
            prior = dets[k].points_px
        report(progress, "segment", n + 1, int(idx.size))
    t_seg = time.perf_counter() - t0
    result = select_contours(dets, verdicts, spacing_all, params, {"segment_s": t_seg})
    if not result.accepted:
        raise BoneUSReconError("no bone contour found in any frame", sweep.source)
    return result


def frame_candidate(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: SegmentationParams,
    prior_px: np.ndarray | None,
) -> tuple[Detection, float, str]:
    """One frame's contour with its per-frame checks: the work done once per frame.

    The segmenter, then the trimming of unshadowed and kinked ends, then the frame's
    confidence and verdict (:mod:`.rejection`). Live reconstruction
    (:mod:`BoneUSRecon.Logic.live`) calls it as each frame arrives.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W)
    spacing : (float, float)
        mm per column and per row.
    params : SegmentationParams
    prior_px : ndarray (K, 2) or None
        The last accepted contour (temporal prior).

    Returns
    -------
    detection, confidence, reason
        ``reason`` is "" when the frame passes the per-frame checks.
    """
    rej = params.rejection
    det = segment_frame(image, spacing, params, prior_px)
    trim = trim_unshadowed_ends(image, det.points_px, spacing, rej.max_shadow_ratio)
    trim[trim] = trim_kinked_ends(det.points_px[trim], spacing)
    if not trim.all():
        det = Detection(
            det.points_px[trim],
            det.intensity[trim],
            {**det.extras, "trimmed_points": int((~trim).sum())},
        )
    ev = frame_evidence(image, det.points_px, spacing)
    conf, reason = frame_verdict(ev, rej)
    if det.empty:
        reason = str(det.extras.get("reason", "no bone found"))
    return det, conf, reason


def select_contours(
    dets: dict[int, Detection],
    verdicts: dict[int, tuple[float, str]],
    spacing_all: np.ndarray,
    params: SegmentationParams,
    timings: dict[str, float] | None = None,
) -> SegmentationResult:
    """The sweep-level step: neighbour consistency over all frames' candidates.

    Parameters
    ----------
    dets, verdicts : dict keyed by frame index, in frame order
        What :func:`frame_candidate` returned for each frame (``verdicts[k]`` is
        ``(confidence, reason)``).
    spacing_all : ndarray, shape (N, 2)
        mm per column and per row of every frame of the sweep.
    params : SegmentationParams
    timings : dict, optional
        Seconds already spent (``segment_s``); ``frames_per_s`` is derived from it.

    Returns
    -------
    SegmentationResult
        Possibly with no accepted frame (the caller decides whether that is an error).
    """
    t0 = time.perf_counter()
    rej = params.rejection
    dets = dict(dets)
    verdicts = dict(verdicts)
    idx = np.fromiter(dets, dtype=int, count=len(dets))

    # Neighbour consistency. A bad frame also spoils its neighbours' predictions, so
    # frames are rejected one at a time per neighbourhood (the worst first) and the
    # rest judged again without it. Tolerances grow with the scatter of the
    # neighbours about their own trend (sparse sweeps). Then, in frames kept, points
    # off their neighbours' prediction (or beyond their lateral extent) are dropped.
    sy = float(np.median(spacing_all[idx, 1]))
    margin = rej.extend_mm / float(np.median(spacing_all[idx, 0]))
    keep = {k: np.ones(d.points_px.shape[0], bool) for k, d in dets.items()}
    for _ in range(idx.size):
        order = [k for k in dets if not verdicts[k][1]]
        devs, scatter = neighbour_deviation(
            {k: dets[k].points_px for k in order}, order, sy, rej.jump_window, margin
        )
        bad: dict[int, float] = {}
        n_order = len(order)
        for p, (k, dev) in enumerate(devs.items()):
            finite = np.isfinite(dev)
            if np.isnan(dev).all():
                continue
            tol = max(rej.jump_mm, 3.0 * scatter.get(k, 0.0))
            if p == 0 or p == n_order - 1:
                tol *= 2.0  # extrapolated from one side only: less sure
            typical = float(np.median(np.abs(dev[finite]))) if finite.any() else np.inf
            if typical > tol:
                bad[k] = typical / tol
        if not bad:
            break
        pos = {k: p for p, k in enumerate(order)}
        for k, ratio in bad.items():
            near = [g for g in bad if abs(pos[g] - pos[k]) <= rej.jump_window]
            if ratio < max(bad[g] for g in near):
                continue  # a worse frame nearby goes first
            conf = verdicts[k][0]
            dev = devs[k]
            finite = np.isfinite(dev)
            if finite.any():
                typical = float(np.median(np.abs(dev[finite])))
                conf *= float(np.exp(-((typical / rej.jump_mm) ** 2)))
                why = f"jump of {typical:.1f} mm from neighbouring frames"
            else:
                conf, why = 0.0, "no overlap with neighbouring frames"
            verdicts[k] = (conf, why)
    order = [k for k in dets if not verdicts[k][1]]
    devs, scatter = neighbour_deviation(
        {k: dets[k].points_px for k in order}, order, sy, rej.jump_window, margin
    )
    for k, dev in devs.items():
        off = ~np.isnan(dev) & (np.abs(dev) > max(rej.point_jump_mm, 3.0 * scatter.get(k, 0.0)))
        if off.any():
            keep[k] = ~off
            verdicts[k] = (verdicts[k][0] * (1.0 - off.sum() / dev.size), "")
    for k in dets:
        if not keep[k].all():
            d = dets[k]
            remaining = d.points_px[keep[k]]
            length = (
                float(np.ptp(remaining[:, 0]) * spacing_all[k, 0]) if len(remaining) > 1 else 0.0
            )
            dets[k] = Detection(
                remaining,
                d.intensity[keep[k]],
                {**d.extras, "dropped_points": int((~keep[k]).sum())},
            )
            if not verdicts[k][1] and (
                len(remaining) < rej.min_points or length < rej.min_length_mm
            ):
                verdicts[k] = (
                    verdicts[k][0],
                    f"contour too short after dropping off-neighbour points ({length:.1f} mm)",
                )

    t_seg = (timings or {}).get("segment_s", 0.0) + time.perf_counter() - t0
    contours = []
    for k, det in dets.items():
        conf, reason = verdicts[k]
        contours.append(
            FrameContour(
                frame=k,
                points_px=det.points_px,
                intensity=det.intensity,
                confidence=float(np.clip(conf, 0.0, 1.0)),
                accepted=not reason,
                reason=reason,
                extras=det.extras,
            )
        )
    return SegmentationResult(
        tuple(contours),
        params.method,
        params,
        {"segment_s": t_seg, "frames_per_s": idx.size / max(t_seg, 1e-9)},
    )


def with_method(params: SegmentationParams, method: str) -> SegmentationParams:
    """``params`` with another segmenter name."""
    return dataclasses.replace(params, method=method)

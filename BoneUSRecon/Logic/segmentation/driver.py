"""Segment a whole sweep: per-frame candidates, then one bone track over the sweep.

Two public steps, usable separately (e.g. live, as frames arrive):

* :func:`frame_candidates_for` (per frame, pure): the candidate contours of one frame
  for the segmenter named by ``params.method``;
* :func:`select_bone_track` (sweep level, :mod:`.track`): one candidate or none per
  frame, chosen jointly over the frames so far.

Between the two, offline, frames off the track are searched again inside the band the
track allows (:mod:`.recovery`; shadowpath only), and the track is chosen once more;
after the ends cut, track frames whose contour strays from their neighbours' are
searched the same way and their contour replaced where the search agrees with them.
The ends cut (:mod:`.ends`) has the track chosen again without the frames it cut, the
first track's (before recovery) and the final one's alike.

:func:`segment_sweep` runs both over a sweep and packs the result.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.progress import ProgressCallback, report
from BoneUSRecon.Logic.segmentation.bone_point import check_bone_points, point_warnings
from BoneUSRecon.Logic.segmentation.candidates import (
    BoneCandidate,
    FrameCandidates,
    candidates_from_points,
    frame_candidates,
    frame_candidates_many,
)
from BoneUSRecon.Logic.segmentation.detection import Detection, empty_detection
from BoneUSRecon.Logic.segmentation.ends import (
    cut_ends_and_choose_again,
    shadow_steps,
    steps_array,
)
from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps, bone_evidence
from BoneUSRecon.Logic.segmentation.params import SEGMENTER_NAMES, SegmentationParams
from BoneUSRecon.Logic.segmentation.reach import trim_beyond
from BoneUSRecon.Logic.segmentation.recovery import applies as recovery_applies
from BoneUSRecon.Logic.segmentation.recovery import recheck_track, recover_frames, with_chosen
from BoneUSRecon.Logic.segmentation.recovery import settings as recovery_settings
from BoneUSRecon.Logic.segmentation.result import FrameContour, SegmentationResult
from BoneUSRecon.Logic.segmentation.snake import snake_frame
from BoneUSRecon.Logic.segmentation.track import (
    REASONS,
    TrackChoice,
    scale_warnings,
    select_bone_track,
)
from BoneUSRecon.Logic.segmentation.track_incremental import IncrementalTrack
from BoneUSRecon.Logic.sweep import Sweep, frames_at_rest, pixel_spacing

__all__ = [
    "SEGMENTERS",
    "FrameSegmenter",
    "segment_frame",
    "frame_candidates_for",
    "select_bone_track",
    "contours_from_track",
    "with_frames_at_rest",
    "segment_sweep",
]

#: ``(image uint8 (H, W), spacing (sx, sy), params, prior_px or None) -> FrameCandidates``
FrameSegmenter = Callable[
    [np.ndarray, tuple[float, float], SegmentationParams, "np.ndarray | None"], FrameCandidates
]


def _snake(image, spacing, params, prior):  # type: ignore[no-untyped-def]
    # The paper's snake starts 50 px below the previous frame's contour (its own rule,
    # kept for the paper's method); its contour is the frame's one candidate.
    det = snake_frame(image, spacing, params.snake, params.posterior, prior)
    reason = str(det.extras.get("reason", "no bone found"))
    return candidates_from_points(
        image, det.points_px, spacing, params.shadowpath, reason, det.extras
    )


def _shadowpath(image, spacing, params, prior):  # type: ignore[no-untyped-def]
    return frame_candidates(image, spacing, params.shadowpath)


#: Frames segmented together by :func:`segment_sweep` with shadowpath (their optimal
#: paths share one column loop, :func:`~.candidates.frame_candidates_many`). Measured on
#: 480x640 frames (bench_big_sweep's), segmentation CPU per frame against one at a time:
#: 8 frames -11 %, 16 -31 %, 32 -36 %; the frames' evidence maps, ~1 MB each, are held
#: meanwhile (32 MB at 32).
BATCH_FRAMES = 32

#: Evidence maps kept from the per-frame step for the recovery's search of frames off
#: the track and of the track's straying frames (:func:`~.recovery.guided_candidate`
#: reads the same maps; kept, they are not computed twice) when all of the sweep's fit in this many bytes (which frames
#: recovery searches is known only once the track is chosen): a 480x640 frame's maps
#: take ~1.8 MB at 0.15 mm per pixel, ~1.0 MB at 0.075 mm, so a 30-frame sweep at
#: 0.15 mm keeps them (recovery searched 1-11 of its frames on the hard presets, ~5 ms
#: of evidence each), while a long sweep keeps none: its peak memory (issue 7's
#: 2,000-frame sweep) stays as it was.
EVIDENCE_CACHE_BYTES = 64 * 2**20


#: Segmenters by name. "shadowpath" (default) offers several candidates per frame from
#: contrast-adaptive evidence; "snake" is the paper's.
SEGMENTERS: dict[str, FrameSegmenter] = {"shadowpath": _shadowpath, "snake": _snake}
# SegmentationParams checks a name against SEGMENTER_NAMES (import-free); keep them one list.
assert tuple(SEGMENTERS) == SEGMENTER_NAMES


def frame_candidates_for(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: SegmentationParams = SegmentationParams(),  # noqa: B008 (frozen dataclass)
    prior_px: np.ndarray | None = None,
) -> FrameCandidates:
    """Candidate contours of one frame for the segmenter named by ``params.method``.

    ``prior_px`` (the previous frame's contour) is used by the paper's snake only, for
    its initialisation; shadowpath depends on the frame alone.
    """
    return SEGMENTERS[params.method](np.asarray(image), spacing, params, prior_px)


def segment_frame(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: SegmentationParams = SegmentationParams(),  # noqa: B008 (frozen dataclass)
    prior_px: np.ndarray | None = None,
) -> Detection:
    """The strongest candidate of one frame (no sweep-level choice), as a Detection."""
    fc = frame_candidates_for(image, spacing, params, prior_px)
    if not fc.usable:
        return empty_detection(**{**fc.extras, "reason": fc.reason or REASONS["none"]})
    c = fc.usable[0]
    return Detection(c.points_px, c.intensity, {**fc.extras, "strength": c.strength})


def contours_from_track(
    frame_indices: np.ndarray,
    frames: list[FrameCandidates],
    choice: TrackChoice,
    params: SegmentationParams = SegmentationParams(),  # noqa: B008 (frozen dataclass)
) -> tuple[FrameContour, ...]:
    """One :class:`FrameContour` per frame from the track's choice (rejections explained).

    Rejected frames keep their strongest candidate's points so overlays show what was
    refused.
    """
    rej = params.rejection
    out = []
    for n, (k, fc) in enumerate(zip(frame_indices, frames, strict=True)):
        c = int(choice.chosen[n])
        reason, detail = choice.reason[n], choice.detail[n]
        if c >= 0:
            cand = fc.candidates[c]
            length = (
                float(np.ptp(cand.points_px[:, 0]) * fc.spacing[0])
                if len(cand.points_px) > 1
                else 0.0
            )
            if len(cand.points_px) < rej.min_points or length < rej.min_length_mm:
                reason, detail = REASONS["short"], f"{length:.1f} mm"
        else:
            cand = fc.usable[0] if fc.usable else (fc.candidates[0] if fc.candidates else None)
        pts = cand.points_px if cand is not None else np.empty((0, 2))
        inten = cand.intensity if cand is not None else np.empty(0)
        extras = dict(fc.extras)
        if cand is not None:
            extras.update(strength=cand.strength, echo_z=cand.echo_z, shadow_z=cand.shadow_z)
            if cand.guided:
                extras["recovered"] = True
        extras["candidates"] = len(fc.candidates)
        out.append(
            FrameContour(
                frame=int(k),
                points_px=pts,
                intensity=inten,
                confidence=float(np.clip(choice.confidence[n], 0.0, 1.0)) if not reason else 0.0,
                accepted=not reason,
                reason=reason,
                detail=detail,
                extras=extras,
            )
        )
    return tuple(out)


def with_frames_at_rest(
    contours: tuple[FrameContour, ...], at_rest: dict[int, int]
) -> tuple[FrameContour, ...]:
    """``contours`` with a copy of each frame's for the frames at rest it stands for
    (``at_rest``: frame -> the frame that moved), flagged ``extras["at_rest_of"]``,
    in frame order."""
    if not at_rest:
        return contours
    by_frame = {c.frame: c for c in contours}
    copies = [
        dataclasses.replace(by_frame[k], frame=f, extras={**by_frame[k].extras, "at_rest_of": k})
        for f, k in at_rest.items()
    ]
    return tuple(sorted((*contours, *copies), key=lambda c: c.frame))


def segment_sweep(
    sweep: Sweep,
    params: SegmentationParams = SegmentationParams(),  # noqa: B008 (frozen dataclass)
    progress: ProgressCallback | None = None,
) -> SegmentationResult:
    """Segment every valid frame of ``sweep``: candidates per frame, one track per sweep.

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
    # The user's bone points must lie on the sweep: checked before any work.
    check_bone_points(
        sweep.image_to_reference[idx], (sweep.height, sweep.width), params.rejection, sweep.source
    )
    # Frames the probe recorded at rest are not tracked: each takes the contour of the
    # frame that stands for it (RejectionParams.at_rest_mm).
    stands = frames_at_rest(
        sweep.image_to_reference[idx], (sweep.height, sweep.width), params.rejection.at_rest_mm
    )
    moved = stands == np.arange(idx.size)
    at_rest = {int(idx[n]): int(idx[stands[n]]) for n in np.flatnonzero(~moved).tolist()}
    idx = idx[moved]
    spacing_all = pixel_spacing(sweep.image_to_reference)
    t0 = time.perf_counter()
    frames: list[FrameCandidates] = []
    prior: np.ndarray | None = None
    # iter_frames releases the memory-mapped pages as it goes: a 600 MB sweep is
    # segmented without its pages piling up in the resident set.
    kept: dict[int, EvidenceMaps] = {}  # frame position -> its evidence maps
    if params.method == "shadowpath" and SEGMENTERS["shadowpath"] is _shadowpath:
        # Shadowpath depends on each frame alone: BATCH_FRAMES frames at a time, their
        # optimal paths solved together (the same candidates, less CPU per frame).
        batch: list[tuple[np.ndarray, tuple[float, float]]] = []
        room: int | None = None  # bytes left for kept maps, set at the first frame's
        for n, (k, image) in enumerate(sweep.iter_frames(idx)):
            batch.append((image, (float(spacing_all[k, 0]), float(spacing_all[k, 1]))))
            if len(batch) == BATCH_FRAMES or n + 1 == idx.size:
                images, spacings = zip(*batch, strict=True)
                evs = [bone_evidence(im, sp, params.shadowpath) for im, sp in batch]
                for m, ev in enumerate(evs, start=n + 1 - len(batch)):
                    if ev is None:
                        continue
                    if room is None:  # every frame of a sweep has the same size
                        room = EVIDENCE_CACHE_BYTES if recovery_applies(params) else 0
                        room = room if idx.size * ev.nbytes <= room else 0
                    if ev.nbytes <= room:
                        kept[m], room = ev, room - ev.nbytes
                frames += frame_candidates_many(images, spacings, params.shadowpath, evs)
                del evs
                for done in range(n + 2 - len(batch), n + 2):  # one report per frame
                    report(progress, "segment", done, int(idx.size))
                batch = []
    else:
        for n, (k, image) in enumerate(sweep.iter_frames(idx)):
            sp = (float(spacing_all[k, 0]), float(spacing_all[k, 1]))
            fc = frame_candidates_for(image, sp, params, prior)
            frames.append(fc)
            prior = fc.usable[0].points_px if fc.usable else None
            report(progress, "segment", n + 1, int(idx.size))
    poses = sweep.image_to_reference[idx]
    # select_bone_track's choice, by the incremental track (the same track bit for bit,
    # :mod:`.track_incremental`): the links between frames (nearly all of the track's
    # CPU) are made once, and the track chosen again after recovery makes only the
    # guided candidates' links (on hard 480x640 sweeps, the track's CPU halved).
    track = IncrementalTrack(params.rejection)
    for fc, pose in zip(frames, poses, strict=True):
        track.add(fc, pose)
    # The link tolerance scaled to the sweep's own frame-to-frame deviation
    # (:func:`.track.tolerance_scale`): the track and every step after it use it.
    track.rescale()
    rejection = track.rejection
    steps: dict[BoneCandidate, np.ndarray] = {}  # shadow steps measured (:mod:`.ends`)

    def track_steps(fcs: list[FrameCandidates], choice: TrackChoice) -> np.ndarray:
        """The shadow step of each track frame's chosen candidate (each measured once)."""
        on = np.flatnonzero(choice.chosen >= 0)
        cands = [fcs[n].candidates[int(choice.chosen[n])] for n in on.tolist()]
        todo = [i for i, c in enumerate(cands) if c not in steps]
        images = (image for _, image in sweep.iter_frames(idx[on[todo]]))
        for i, image in zip(todo, images, strict=True):
            sp = fcs[int(on[i])].spacing
            steps[cands[i]] = shadow_steps(image, cands[i].points_px, sp, params.ends)
        return steps_array(steps[c] for c in cands)

    if recovery_applies(params):
        # Frames off the track searched again inside the band the track allows, then
        # one track over all frames again (:mod:`.recovery`); past the track's ends too
        # (one side guiding) when the ends cut below judges what is found there. The
        # first track's bone-free ends are cut first, the track chosen again without
        # them (:func:`.ends.cut_ends_and_choose_again`): the band of a frame next to
        # them is not to lead into frames judged to show no bone.
        first = track.solve(explain=False)  # its rejection details would be replaced
        if params.ends.choose_again:
            first = cut_ends_and_choose_again(
                first,
                lambda ex: track.solve(explain=False, exclude=ex),
                lambda ch, fcs=frames: track_steps(fcs, ch),
                params.ends,
            )
        frames, searched = recover_frames(
            frames,
            first,
            poses,
            lambda n: np.asarray(sweep.frames[int(idx[n])]),
            params.shadowpath,
            rejection,
            recovery_settings(params),
            kept.get,
        )
        # The guided candidate is its frame's last (recovery.with_candidate).
        extra = {f: frames[f].candidates[-1] for f in searched}
    else:
        extra = {}
    # The track's ends cut back where its frames cast no bone shadow, and the track
    # chosen again without the frames cut (:mod:`.ends`).
    choice = cut_ends_and_choose_again(
        track.solve(extra=extra),
        lambda ex: track.solve(extra=extra, exclude=ex),
        lambda ch, fcs=frames: track_steps(fcs, ch),
        params.ends,
    )
    if recovery_applies(params):
        # Track frames whose contour strays from their neighbours' searched again,
        # the contour replaced where the search agrees with them (:mod:`.recovery`).
        frames, choice, _ = recheck_track(
            frames,
            choice,
            poses,
            lambda n: np.asarray(sweep.frames[int(idx[n])]),
            params.shadowpath,
            rejection,
            params.recovery,
            kept.get,
        )
    kept.clear()
    # A level run past the reach of the track frames on either side cut off (a layer
    # leaving the bone's top at its level, :mod:`.reach`).
    frames, choice = with_chosen(frames, choice, trim_beyond(frames, choice, poses, rejection))
    contours = with_frames_at_rest(contours_from_track(idx, frames, choice, params), at_rest)
    t_seg = time.perf_counter() - t0
    result = SegmentationResult(
        contours,
        params.method,
        params,
        {"segment_s": t_seg, "frames_per_s": idx.size / max(t_seg, 1e-9)},
        # A tolerance scaled to the sweep's deviation, then bone points the track does
        # not reach (none given: nothing mapped).
        warnings=scale_warnings(track.scale)
        + (
            point_warnings(
                [
                    (c.frame, sweep.to_reference(c.frame, c.points_px))
                    for c in contours
                    if c.accepted
                ],
                sweep.image_to_reference,
                params.rejection,
            )
            if params.rejection.bone_points
            else ()
        ),
    )
    if not result.accepted:
        raise BoneUSReconError("no bone contour found in any frame", sweep.source)
    return result

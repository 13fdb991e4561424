"""Live reconstruction: the surface grows while the user scans.

Frames arrive one at a time (from an OpenIGTLink server, :mod:`BoneUSRecon.cli.igtl`, or a
Slicer volume node that OpenIGTLinkIF updates). :class:`LiveReconstructor` does the
per-frame work once, as each frame arrives: the frame's candidate bone contours, and
their links to the candidates of the frames before it
(:class:`~BoneUSRecon.Logic.segmentation.track_incremental.IncrementalTrack`: the
projections and distances that are nearly all of the bone track's cost). At each
refit it does the sweep-level work over all frames so far, as
:func:`~BoneUSRecon.Logic.segmentation.segment_sweep` does it offline: the track's
dynamic programme over the stored links (one bone track chosen jointly over the
frames, the same as offline, bit for bit); the frames off the track searched again
inside the band the track allows (:mod:`~BoneUSRecon.Logic.segmentation.recovery`,
from the pixels kept for them; a frame's result is cached while its neighbouring
track frames and their choices stay the same; past the track's ends too, one side
guiding, as offline); the track again with the guided candidates (only their links
are made, once per candidate); its bone-free ends cut back
(:mod:`~BoneUSRecon.Logic.segmentation.ends`) from the shadow step under each
candidate, measured once when the candidate was made, while the frame's pixels were
at hand, and the track chosen again without the frames cut (the first track's too,
before the search); the track frames whose contour strays from their neighbours' searched again
and replaced where the search agrees with them (cached as the search of frames off
the track is); then resampling, fit and mesh. Every refit therefore equals an offline
:func:`~BoneUSRecon.Logic.pipeline.reconstruct` of the frames so far, except where a
frame that had been on the track (its pixels dropped) falls off it with a new prior,
or starts to stray from new neighbours, and cannot be searched again (counted in ``LiveReconstructor.recovery_counts``; none
on the tests' sweeps and ``bench_live.py``'s). At 480x640, one core: ~12 ms per
frame, ~0.13 s per refit of 300-400 frames (``Testing/benchmarks/bench_live.py``).

The calls into the segmentation stage are isolated in :func:`_segment_one`,
:func:`_guided` and :func:`_select`; the rest is
:func:`~BoneUSRecon.Logic.pipeline.reconstruction_from_segmentation`, as in
:func:`~BoneUSRecon.Logic.pipeline.reconstruct`.

:class:`PoseAssembler` turns a stream of IMAGE and TRANSFORM messages into posed
frames (the image's own matrix, a named transform, or the PLUS chain with a
calibration), and :class:`SweepRecorder` saves what was received as a PLUS sequence,
streamed to disk so that memory stays flat however long the session.

Nothing here knows about sockets: this module is pure computation on numpy arrays.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
import time
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import check_output_path
from BoneUSRecon.Logic.params_check import check_fields
from BoneUSRecon.Logic.pipeline import (
    Reconstruction,
    ReconstructionParams,
    reconstruction_from_segmentation,
)
from BoneUSRecon.Logic.poses import find_chain, read_calibration, split_transform_name
from BoneUSRecon.Logic.segmentation import (
    SegmentationParams,
    SegmentationResult,
)
from BoneUSRecon.Logic.segmentation.bone_point import off_sweep_points, point_warnings
from BoneUSRecon.Logic.segmentation.candidates import (
    BoneCandidate,
    FrameCandidates,
    frame_candidates_many,
)
from BoneUSRecon.Logic.segmentation.driver import contours_from_track, frame_candidates_for
from BoneUSRecon.Logic.segmentation.ends import (
    candidate_steps,
    cut_ends_and_choose_again,
    shadow_steps,
    steps_array,
    unmeasured,
)
from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps, bone_evidence
from BoneUSRecon.Logic.segmentation.reach import trim_beyond
from BoneUSRecon.Logic.segmentation.recovery import applies as recovery_applies
from BoneUSRecon.Logic.segmentation.recovery import (
    off_skin,
    prior_frames,
    recheck_candidate,
    recheck_prior,
    recover_frame,
    sweep_level,
    with_candidate,
    with_chosen,
)
from BoneUSRecon.Logic.segmentation.recovery import settings as recovery_settings
from BoneUSRecon.Logic.segmentation.result import FrameContour
from BoneUSRecon.Logic.segmentation.track import TrackChoice, scale_warnings
from BoneUSRecon.Logic.segmentation.track_incremental import IncrementalTrack
from BoneUSRecon.Logic.sequence_io import write_sweep
from BoneUSRecon.Logic.sweep import Sweep, frames_at_rest, pixel_spacing

__all__ = [
    "LiveParams",
    "LiveReconstructor",
    "PosedFrame",
    "PoseAssembler",
    "SweepRecorder",
]


@dataclass(frozen=True)
class LiveParams:
    """How a live session receives frames and refits.

    Attributes
    ----------
    update_every_s : float
        Seconds between refits (default 1.0). A refit chooses the bone track over all
        kept frames (with recovery) and refits the surface: 0.07-0.13 s of one core
        for 100-400 frames of 480x640, ~0.2 s on the hard preset
        (``Testing/benchmarks/bench_live.py``). A session spaces
        refits that take longer than this by their own duration, so that frames
        keep at least half of the time.
    queue_frames : int
        Frames waiting to be processed before new ones are dropped (default 64:
        about 2 s at 30 frames/s, ~20 MB at 480x640; covers a refit and a burst).
    max_frames : int
        Frames kept for the surface (default 400: 13 s at 30 frames/s, more than the
        paper's longest sweep of 250 and ~25 slices per control point along the
        bone; ~2 MB of contours and track links, plus the pixels of the frames off the
        bone track, 6 MB at 480x640 on ``bench_live.py``, 37 MB on its hard preset; a
        live refit plus writing the surface then takes ~0.12 s of one core at 480x640,
        within the 0.2 s a refit may lag). When reached, every other kept frame is dropped and from then on
        only every second arriving frame is processed (then every fourth, ...): the
        whole scanned extent stays covered at a halved density, and memory and refit
        time stay bounded. Frames that become neighbours are linked in the time the
        frames not processed leave.
    pose_tolerance_s : float
        Largest timestamp difference between an image and a transform paired with
        it (default 0.02 s). PLUS stamps all messages of one tracked frame with the
        same time, so a matching pose is normally exact; 20 ms tolerates servers that
        stamp on sending and stays below the 33 ms between frames at 30 frames/s.
    reconnect_s : float
        After the server closes the connection, how long to try reconnecting before
        the session ends (default 3 s: a restarted PlusServer is back within that).
    keep_all_pixels : bool
        Keep the pixels of every kept frame, not only of those off the bone track
        (default False). Recovery (:mod:`~BoneUSRecon.Logic.segmentation.recovery`)
        searches frames off the track; a frame dropped its pixels when a refit found it
        on the track, and should it fall off later with new neighbours it is not
        searched: the one difference from offline. True makes every refit equal the
        offline reconstruction at the cost of ``max_frames`` frames of pixels (123 MB at
        480x640 and 400 frames; off the track only: 6 MB at most on
        ``bench_live.py``'s sweep, 37 MB on its hard one, where 3 of 150 frames then
        differ from offline; ``Testing/benchmarks/README.md``).
    """

    update_every_s: float = 1.0
    queue_frames: int = 64
    max_frames: int = 400
    pose_tolerance_s: float = 0.02
    reconnect_s: float = 3.0
    keep_all_pixels: bool = False

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=("update_every_s", "queue_frames"),
            non_negative=("pose_tolerance_s", "reconnect_s"),
            within={"max_frames": "[10, inf)"},
        )


# ------------------------------------------------------------------------------------
# The calls into the segmentation and surface stages (one place to rewire)
# ------------------------------------------------------------------------------------
def _segment_one(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: SegmentationParams,
    prior_px: np.ndarray | None,
    keep_evidence: bool = False,
) -> tuple[FrameCandidates, EvidenceMaps | None]:
    """Per-frame step, done once per frame: the frame's candidate bone contours, and
    with ``keep_evidence`` (shadowpath) the evidence maps they were found on, for
    recovery to search the frame with again (the same maps it would compute)."""
    if keep_evidence and params.method == "shadowpath":
        ev = bone_evidence(image, spacing, params.shadowpath)
        return frame_candidates_many([image], [spacing], params.shadowpath, [ev])[0], ev
    return frame_candidates_for(image, spacing, params, prior_px), None


def _guided(
    frames: list[_Frame],
    choice: TrackChoice,
    params: SegmentationParams,
    counts: dict[str, int],
) -> dict[int, BoneCandidate]:
    """The guided candidates of the frames off the track, as offline recovery finds them
    (:func:`~BoneUSRecon.Logic.segmentation.recovery.recover_frame`).

    A frame's guided candidate depends on its pixels and on its prior: the nearest
    track frames on either side, their chosen candidates, the link tolerance (the
    band searched; rescaled as frames arrive) and whether the frame is in contact (its
    level against the frames' so far). It is cached per frame with that prior's
    identity and searched again only when the prior changed. A frame whose pixels were
    dropped (it was on the track at an earlier refit) and whose prior changed cannot be
    searched: the one way a live refit may differ from offline, counted in
    ``counts["no_pixels"]``.
    """
    out: dict[int, BoneCandidate] = {}
    rec = recovery_settings(params)  # one-sided past the track's ends, as offline
    reach = params.rejection.max_skip + 1
    fcs = [fr.candidates for fr in frames]
    poses = [fr.pose for fr in frames]
    median_level = sweep_level(fcs)
    for f in np.flatnonzero(choice.chosen < 0).tolist():
        near = prior_frames(choice.chosen, f, reach, rec.both_sides)
        if near is None:
            continue
        fr = frames[f]
        # The band searched is the link tolerance, scaled to the frames' deviation, and
        # the frame is searched only if in contact by the level of the frames so far:
        # both part of the prior (a search made before a rescale, or before the sweep's
        # level moved the verdict, is not reused after it).
        contact = not off_skin(fr.candidates, median_level, rec.contact_level)
        key = (
            _tolerance(params),
            contact,
            *((frames[g].uid, int(choice.chosen[g])) for g in near),
        )
        if fr.guided is not None and fr.guided[0] == key:
            cand = fr.guided[1]
            counts["reused"] += 1
        elif fr.image is None:
            counts["no_pixels"] += 1
            continue
        else:
            cand = recover_frame(
                fcs,
                choice,
                poses,
                f,
                lambda _, im=fr.image: im,  # type: ignore[misc]
                params.shadowpath,
                params.rejection,
                rec,
                lambda _, ev=fr.evidence: ev,  # type: ignore[misc]
                median_level,
            )
            # Its shadow step (:mod:`~BoneUSRecon.Logic.segmentation.ends`) measured now,
            # while the pixels are at hand: the ends cut may need it at any later refit.
            step = (
                shadow_steps(fr.image, cand.points_px, fr.candidates.spacing, params.ends)
                if cand is not None and params.ends.enabled
                else unmeasured()
            )
            fr.guided = (key, cand, step)
            counts["searched"] += 1
        if cand is not None:
            out[f] = cand
    return out


def _track_steps(frames: list[_Frame], choice: TrackChoice) -> np.ndarray:
    """The shadow step of each track frame's chosen candidate, in track order: its own
    (measured as it arrived) or its guided one's (measured when found)."""
    out = []
    for n in np.flatnonzero(choice.chosen >= 0).tolist():
        fr, c = frames[n], int(choice.chosen[n])
        if c < len(fr.steps):
            out.append(fr.steps[c])
        else:  # the guided candidate, appended after the frame's own
            assert fr.guided is not None and fr.guided[1] is not None
            out.append(fr.guided[2])
    return steps_array(out)


def _tolerance(params: SegmentationParams) -> tuple[float, float]:
    """The link tolerance a search is made with (:func:`~BoneUSRecon.Logic.segmentation.
    track.scaled_tolerance` changes it as frames arrive)."""
    return (params.rejection.tolerance_mm, params.rejection.tolerance_per_mm)


def _prior_key(frame: _Frame) -> tuple[Any, ...] | None:
    """The prior of the frame's guided candidate (it names the candidate)."""
    return frame.guided[0] if frame.guided is not None else None


def _candidate_key(frame: _Frame, c: int) -> tuple[Any, ...]:
    """Names candidate ``c`` of a frame across refits: its own candidates by index, its
    guided candidate (the index past them) by the prior that found it."""
    if c < len(frame.candidates.candidates):
        return (frame.uid, c)
    return (frame.uid, c, _prior_key(frame))


def _rechecked(
    frames: list[_Frame],
    fcs: list[FrameCandidates],
    choice: TrackChoice,
    params: SegmentationParams,
    counts: dict[str, int],
) -> tuple[dict[int, BoneCandidate], set[int]]:
    """The replacements of the track's straying contours, as offline
    (:func:`~BoneUSRecon.Logic.segmentation.recovery.recheck_track`), and the track
    frames whose pixels a later refit may need.

    A frame's verdict depends on its pixels, its track contour and its prior (the
    nearest track frames on both sides and their contours, and the link tolerance): it
    is cached with their names and made again only when one of them changed. A
    straying frame keeps its pixels (its prior may change), as does a track frame
    without a track frame on each side yet (it may stray once it has them). A straying
    frame whose pixels were dropped (it did not stray when a refit last judged it) is
    not searched: counted in ``counts["no_pixels"]``, as for recovery.
    """
    out: dict[int, BoneCandidate] = {}
    keep: set[int] = set()
    rec = params.recovery
    if not rec.recheck:
        return out, keep
    reach = params.rejection.max_skip + 1
    poses = [fr.pose for fr in frames]
    for f in np.flatnonzero(choice.chosen >= 0).tolist():
        fr = frames[f]
        near = prior_frames(choice.chosen, f, reach, True)
        if near is None:
            keep.add(f)
            continue
        c = int(choice.chosen[f])
        key = (
            _tolerance(params),
            *(_candidate_key(frames[g], int(choice.chosen[g])) for g in (f, *near)),
        )
        if fr.recheck is None or fr.recheck[0] != key:
            got = recheck_prior(fcs, choice, poses, f, params.rejection, rec)
            if got is None:
                fr.recheck = (key, None, False)
            elif fr.image is None:
                counts["no_pixels"] += 1
                continue
            else:
                cand = recheck_candidate(
                    fr.image,
                    fcs[f].spacing,
                    fcs[f].candidates[c],
                    *got,
                    params.shadowpath,
                    params.rejection,
                    rec,
                    fr.evidence,
                )
                fr.recheck = (key, cand, True)
                counts["rechecked"] += 1
        if fr.recheck[2]:
            keep.add(f)
        if fr.recheck[1] is not None:
            out[f] = fr.recheck[1]
    return out, keep


def _select(
    frames: list[_Frame],
    track: IncrementalTrack,
    params: SegmentationParams,
    t_seg: float,
    counts: dict[str, int],
    keep_pixels: bool = False,
) -> SegmentationResult:
    """Sweep-level step at each refit: one bone track over all frames so far, exactly
    as :func:`~BoneUSRecon.Logic.segmentation.segment_sweep` chooses it offline
    (``track`` holds the same frames, linked as they arrived): the track, the frames
    off it searched again inside the band it allows (:func:`_guided`), and the track
    again with the guided candidates (only their links are made, once per candidate).
    Then the track's straying contours searched again (:func:`_rechecked`). Frames on
    the first track give up their pixels (recovery never searches them) unless
    ``keep_pixels`` (``LiveParams.keep_all_pixels``), or the recheck may need them
    (a straying frame, a track frame without a track frame on each side yet).

    A frame's contour record depends only on the frame, its guided candidate, its
    position and the track's verdict on it: records whose verdict did not change
    since the last refit are reused (most of them), the others made again.
    """
    # The link tolerance scaled to the frames' own deviation, as offline
    # (:func:`~BoneUSRecon.Logic.segmentation.track.tolerance_scale`).
    track.rescale()
    given, params = params, replace(params, rejection=track.rejection)
    extra: dict[int, BoneCandidate] = {}
    again: dict[int, BoneCandidate] = {}  # track contours replaced (_rechecked)
    first: TrackChoice | None = None
    if recovery_applies(params):
        # The first track's choice only (its rejection details would be replaced),
        # its bone-free ends cut and the track chosen again without them, as offline.
        first = track.solve(explain=False)
        if params.ends.choose_again:
            first = cut_ends_and_choose_again(
                first,
                lambda ex: track.solve(explain=False, exclude=ex),
                lambda ch: _track_steps(frames, ch),
                params.ends,
            )
        extra = _guided(frames, first, params, counts)
    # The track's bone-free ends cut back as offline (:mod:`~BoneUSRecon.Logic.
    # segmentation.ends`), from the steps measured when each candidate was made, and
    # the track chosen again without the frames cut.
    choice = cut_ends_and_choose_again(
        track.solve(extra=extra),
        lambda ex: track.solve(extra=extra, exclude=ex),
        lambda ch: _track_steps(frames, ch),
        params.ends,
    )
    fcs = [
        with_candidate(fr.candidates, extra[n]) if n in extra else fr.candidates
        for n, fr in enumerate(frames)
    ]
    if first is not None:
        # The track's straying contours searched again and replaced where the search
        # agrees with their neighbours, as offline (after the ends cut).
        again, keep = _rechecked(frames, fcs, choice, params, counts)
        fcs, choice = with_chosen(fcs, choice, again)
        for n in np.flatnonzero(first.chosen >= 0).tolist():
            if n in keep:
                continue
            frames[n].evidence = None  # 6x the pixels: never kept for all frames
            if not keep_pixels:
                frames[n].image = None
    # A level run past the reach of the track frames on either side cut off, as offline
    # (:mod:`~BoneUSRecon.Logic.segmentation.reach`).
    cut = trim_beyond(fcs, choice, [fr.pose for fr in frames], params.rejection)
    fcs, choice = with_chosen(fcs, choice, cut)
    verdicts = [
        (
            n,
            int(choice.chosen[n]),
            choice.reason[n],
            choice.detail[n],
            float(choice.confidence[n]),
            _prior_key(frames[n]) if n in extra else None,
            frames[n].recheck[0] if n in again else None,  # type: ignore[index]
            _cut_key(cut[n]) if n in cut else None,
        )
        for n in range(len(frames))
    ]
    todo = [n for n, fr in enumerate(frames) if fr.contour is None or fr.contour[0] != verdicts[n]]
    if todo:
        sub = TrackChoice(
            choice.chosen[todo],
            choice.confidence[todo],
            [choice.reason[n] for n in todo],
            [choice.detail[n] for n in todo],
        )
        made = contours_from_track(np.array(todo), [fcs[n] for n in todo], sub, params)
        for n, c in zip(todo, made, strict=True):
            frames[n].contour = (verdicts[n], c)
    contours = tuple(fr.contour[1] for fr in frames)  # type: ignore[index]
    return SegmentationResult(
        contours,
        params.method,
        given,
        {"segment_s": t_seg, "frames_per_s": len(frames) / max(t_seg, 1e-9)},
        warnings=scale_warnings(track.scale),
    )


def _cut_key(cand: BoneCandidate) -> tuple[int, float, float]:
    """What a contour cut by :func:`~BoneUSRecon.Logic.segmentation.reach.trim_beyond`
    keeps (its points' count and first and last columns): its record is made again
    when the cut changes."""
    pts = cand.points_px
    return (int(pts.shape[0]), float(pts[0, 0]), float(pts[-1, 0]))


def _point_warnings(
    seg: SegmentationResult, sweep: Sweep, params: ReconstructionParams, final: bool
) -> tuple[tuple[str, ...], bool]:
    """The user's bone points judged against the frames so far, one sentence each, and
    whether one of them is not reached yet (off every frame so far, or no accepted
    contour near it).

    A point no accepted contour reaches in the frames near it is reported at every
    refit, as offline (:func:`~BoneUSRecon.Logic.segmentation.bone_point.point_warnings`).
    A point off every frame so far is reported only at the ``final`` refit, with the
    offline error's sentence (:func:`~BoneUSRecon.Logic.segmentation.bone_point.
    off_sweep_points`): during the scan the probe may not have reached it yet, and at
    the end the scan cannot be given again, so its surface (made as without the point)
    is kept and the point reported rather than refused.
    """
    rej = params.segmentation.rejection
    poses = sweep.image_to_reference
    off = off_sweep_points(poses, (sweep.height, sweep.width), rej)
    unreached = point_warnings(seg.contours_mm(sweep), poses, rej, skip=off)
    said = (tuple(off[q] for q in sorted(off)) if final else ()) + unreached
    return said, bool(off or unreached)


# ------------------------------------------------------------------------------------
# The reconstructor
# ------------------------------------------------------------------------------------
@dataclass
class _Frame:
    uid: int  # unique within the session (the cache keys name frames by it)
    pose: np.ndarray
    timestamp: float
    candidates: FrameCandidates
    #: The pixels, while recovery may search the frame (see :class:`LiveReconstructor`).
    image: np.ndarray | None = None
    #: Its evidence maps (:func:`~BoneUSRecon.Logic.segmentation.evidence.bone_evidence`)
    #: while it is among the newest frames (:data:`LIVE_EVIDENCE_BYTES`) and no refit
    #: found it on the first track: a search of the frame (at the next refit, and again
    #: whenever its prior changes) reads them instead of computing them.
    evidence: EvidenceMaps | None = None
    #: The shadow steps under each of its candidates, (n, 2) (:func:`~BoneUSRecon.Logic.
    #: segmentation.ends.shadow_steps`), measured on arrival; NaN with the ends cut off.
    steps: np.ndarray = field(default_factory=lambda: steps_array(()))
    #: The prior of the frame's last search (:func:`_guided`), what it found and that
    #: candidate's shadow steps.
    guided: tuple[tuple[tuple[int, int], ...], BoneCandidate | None, np.ndarray] | None = None
    #: The names of the frame's track contour and its prior at its last recheck
    #: (:func:`_rechecked`), the contour found to replace it (or None), and whether it
    #: strayed (was searched).
    recheck: tuple[tuple[Any, ...], BoneCandidate | None, bool] | None = None
    #: The track's verdict at the last refit and the contour record made from it.
    contour: tuple[tuple[Any, ...], FrameContour] | None = None

    @property
    def reason(self) -> str:
        """The per-frame verdict: "" when the frame has a usable candidate, else why not."""
        if self.candidates.usable:
            return ""
        return self.candidates.reason or "no bone found"


#: Live refits wait for this many frames with a contour per control point along the
#: bone. With barely as many slices as control points the fit interpolates and swings
#: wildly between them (a 15-slice fit of the test sweep spans 380 mm and meshes into
#: 1.3 million points, 2 s); two slices per control point make it a least-squares fit.
MIN_FRAMES_PER_CONTROL_POINT = 2


#: The newest frames keep their evidence maps up to this many bytes together (~1.8 MB
#: per 480x640 frame at 0.15 mm per pixel: 17 frames; ~1.0 MB at 0.075 mm: 33 frames),
#: so that recovery reads them instead of computing them again. On ``bench_live.py``'s
#: hard sweep (0.075 mm, a refit every 30 frames) 75 of its 90 searches are of frames
#: at most 32 frames old (the other 15: older frames whose prior changed).
LIVE_EVIDENCE_BYTES = 32 * 2**20


class LiveReconstructor:
    """Frames in one at a time, a surface out whenever asked.

    Parameters
    ----------
    params : ReconstructionParams
        As for :func:`~BoneUSRecon.Logic.pipeline.reconstruct`.
    live : LiveParams
        ``max_frames`` bounds what is kept (see there).

    Notes
    -----
    Frames must arrive in acquisition order: each frame's segmenter is seeded by the
    last frame that passed its per-frame checks, exactly as in
    :func:`~BoneUSRecon.Logic.segmentation.segment_sweep`. The contours and poses are
    kept, and the pixels (uint8) of a frame only while recovery may search it: from
    its arrival until a refit finds it on the (first) track, with a track frame on
    each side and a contour that does not stray from theirs, when they are dropped
    for good (recovery searches only frames off that track, and the recheck straying
    track frames). On ``bench_live.py`` (480x640) that was 11 frames at a median
    refit, 19 at most (5.8 MB) before the recheck; the newest
    of them also keep their evidence maps (:data:`LIVE_EVIDENCE_BYTES`, at most
    32 MB), which recovery reads instead of computing them again; with
    recovery off (``params.segmentation.recovery.enabled`` False, or the snake) no
    pixels are kept. Should a frame whose pixels were dropped fall off the track later
    with neighbours it was not searched between, it is not searched (the one
    difference from offline, counted in :attr:`recovery_counts`). The
    :attr:`Reconstruction.sweep` of a refit carries blank frames (a zero-stride
    array) with the real poses.

    Bone points (``params.segmentation.rejection.bone_points``) steer the track as
    offline once frames pass near them; the track before that may lie on the other
    bone, and moves when the probe reaches a point. So while a point is not reached
    (off every frame so far, or no accepted contour near it) every frame keeps its
    pixels, as with ``LiveParams.keep_all_pixels`` (at most ``max_frames`` frames,
    123 MB at 480x640), and the frames the move leaves off the track are searched as
    offline. Without that, a point on the swept bone 90 % of the way through off-centre
    forearm sweeps gave a final recall of 0.90 against offline's 0.98
    (``Testing/benchmarks/README.md``). Each refit's warnings judge the points against
    the frames so far (:func:`_point_warnings`).

    Examples
    --------
    >>> from BoneUSRecon.Logic.simulation import SimulationParams, simulate
    >>> sim = simulate(SimulationParams(n_frames=30, width=120, height=96, spacing_mm=0.4))
    >>> live = LiveReconstructor()
    >>> for k, image in sim.sweep.iter_frames():
    ...     _ = live.add_frame(image, sim.sweep.image_to_reference[k], sim.sweep.timestamps[k])
    >>> live.refit().summary["segmented_frames"] > 20
    True
    """

    def __init__(
        self,
        params: ReconstructionParams = ReconstructionParams(),  # noqa: B008 (frozen)
        live: LiveParams = LiveParams(),  # noqa: B008 (frozen)
    ) -> None:
        self.params = params
        self.live = live
        self._frames: list[_Frame] = []
        self._track = IncrementalTrack(params.segmentation.rejection)
        self._prior: np.ndarray | None = None
        self._shape: tuple[int, int] | None = None
        self._stride = 1
        self._arrived = 0
        self._since_thinning = 0
        self._segment_s = 0.0
        self._processed = 0
        #: Frames given to :meth:`add_frame`, frames not processed because of
        #: ``max_frames`` thinning, frames refused for a different image size, frames
        #: recorded at rest (``RejectionParams.at_rest_mm``).
        self.counts = {"added": 0, "thinned": 0, "wrong_size": 0, "at_rest": 0}
        self._moved: np.ndarray | None = None  # the pose of the last frame that moved
        #: Over all refits, frames off the track with a prior: searched, their cached
        #: guided candidate reused, not searched for want of pixels (see
        #: :func:`_guided` and :func:`_rechecked`: the only difference from offline);
        #: and straying track frames searched again (:func:`_rechecked`).
        self.recovery_counts = {"searched": 0, "reused": 0, "no_pixels": 0, "rechecked": 0}
        self._keep_pixels = recovery_applies(params.segmentation)
        #: A bone point the track does not reach yet (:func:`_point_warnings`): every
        #: frame keeps its pixels meanwhile.
        self._points_open = bool(params.segmentation.rejection.bone_points)

    @property
    def n_frames(self) -> int:
        """Frames kept for the surface."""
        return len(self._frames)

    @property
    def shape(self) -> tuple[int, int] | None:
        """``(H, W)`` of the frames, fixed by the first one."""
        return self._shape

    def add_frame(self, image: np.ndarray, pose: np.ndarray, timestamp: float = 0.0) -> str | None:
        """Segment one frame and keep its contour.

        Parameters
        ----------
        image : ndarray of uint8, shape (H, W)
            B-mode frame in MF orientation (row 0 nearest the transducer).
        pose : ndarray, shape (4, 4)
            ``ImageToReference``: pixel ``(i, j, 0, 1)`` to reference mm.
        timestamp : float
            Seconds.

        Returns
        -------
        str or None
            The per-frame verdict: ``""`` when the contour passed the per-frame checks,
            else why not; ``None`` when the frame was not processed (recorded at rest,
            thinned, or its size differs from the first frame's).
        """
        img = np.asarray(image)
        if img.ndim != 2 or img.dtype != np.uint8:
            raise BoneUSReconError(f"a frame must be a 2D uint8 array, got {img.dtype} {img.shape}")
        m = np.asarray(pose, dtype=np.float64)
        if m.shape != (4, 4):
            raise BoneUSReconError(f"a pose must be 4x4, got {m.shape}")
        self.counts["added"] += 1
        if self._shape is None:
            self._shape = (int(img.shape[0]), int(img.shape[1]))
        elif img.shape != self._shape:
            self.counts["wrong_size"] += 1
            return None
        self._arrived += 1
        # A frame recorded at rest is not processed: offline it is not tracked either
        # (segment_sweep gives it the contour of the frame that moved), and the surface
        # is fitted from the frames that moved.
        tol = self.params.segmentation.rejection.at_rest_mm
        if (
            self._moved is not None
            and frames_at_rest(np.stack([self._moved, m]), img.shape, tol)[1] == 0
        ):
            self.counts["at_rest"] += 1
            return None
        self._moved = m
        if self._since_thinning % self._stride:
            self._since_thinning += 1
            self.counts["thinned"] += 1
            # A frame not processed leaves the time a processed one takes: spend it on
            # the links the last thinning left owed, so the next refit need not.
            if self._track.owed:
                t0 = time.perf_counter()
                self._track.work(self._segment_s / max(self._processed, 1))
                self._segment_s += time.perf_counter() - t0
            return None
        self._since_thinning += 1
        self._processed += 1
        sx, sy = pixel_spacing(m)
        t0 = time.perf_counter()
        fc, ev = _segment_one(
            img, (float(sx), float(sy)), self.params.segmentation, self._prior, self._keep_pixels
        )
        self._track.add(fc, m)  # links to its predecessors, once
        # The ends cut's measure under each candidate, while the pixels are here (the
        # track may choose any of them at a later refit, when they may be gone).
        steps = candidate_steps(img, fc, self.params.segmentation.ends)
        self._segment_s += time.perf_counter() - t0
        # Pixels kept until the frame is on the track (recovery may search it), or
        # always (``keep_all_pixels``).
        kept = np.array(img, copy=True) if self._keep_pixels else None
        frame = _Frame(self._processed - 1, m, float(timestamp), fc, kept, ev, steps)
        reason = frame.reason
        if not reason:
            self._prior = fc.usable[0].points_px  # as segment_sweep seeds the next frame
        self._frames.append(frame)
        # Evidence maps for the newest frames only (LIVE_EVIDENCE_BYTES): a frame is
        # searched first at the refit after it arrives, and again while the track's end
        # moves past it; an older frame's search is mostly reused.
        if ev is not None:
            newest = max(1, LIVE_EVIDENCE_BYTES // max(ev.nbytes, 1))
            if len(self._frames) > newest:
                self._frames[-newest - 1].evidence = None
        if len(self._frames) >= self.live.max_frames:
            self._thin()
        return reason

    @property
    def owed(self) -> int:
        """Pairs of frames still to link after a thinning (see :meth:`work`)."""
        return self._track.owed

    def work(self, budget_s: float) -> bool:
        """Spare time (nothing to process): link frames that a thinning made neighbours.

        Refits make what is still owed themselves; linking ahead keeps the first refit
        after a thinning as fast as the others.

        Parameters
        ----------
        budget_s : float
            CPU seconds to spend at most (one pair of frames is linked at least).

        Returns
        -------
        bool
            Whether anything was left to do.
        """
        if not self._track.owed:
            return False
        t0 = time.perf_counter()
        self._track.work(budget_s)
        self._segment_s += time.perf_counter() - t0
        return True

    def _thin(self) -> None:
        """Keep every other frame and process every ``2 * stride``-th from now on."""
        self._frames = self._frames[::2]
        self._track.keep(range(0, len(self._track), 2))
        self._stride *= 2
        self._since_thinning = 1  # the frame just added counts as processed

    def sweep(self) -> Sweep:
        """The kept frames as a :class:`Sweep` (poses and timestamps; blank pixels)."""
        if not self._frames or self._shape is None:
            raise BoneUSReconError("no frame received yet")
        n = len(self._frames)
        h, w = self._shape
        return Sweep(
            frames=np.broadcast_to(np.zeros((), np.uint8), (n, h, w)),
            image_to_reference=np.stack([f.pose for f in self._frames]),
            timestamps=np.array([f.timestamp for f in self._frames]),
            valid=np.ones(n, bool),
            transform_name="ImageToReference (live)",
        )

    def refit(self, *, final: bool = False, with_points: bool = True) -> Reconstruction:
        """Select over all frames so far, resample, fit and mesh.

        Parameters
        ----------
        final : bool
            The end of a session: fit whatever there is. Otherwise (live refits) it
            waits for ``MIN_FRAMES_PER_CONTROL_POINT`` frames with a contour per
            control point along the bone. Either way the bone track is chosen over all
            kept frames, as :func:`~BoneUSRecon.Logic.pipeline.reconstruct` does (only
            the dynamic programme runs here, over the links made as frames arrived,
            ~10 ms for 400 frames, then the search of the frames off the track whose
            neighbours changed and the programme again with what it found;
            ``max_frames`` bounds the frames kept). The final refit also reports
            the user's bone points that lie off every kept frame (see below).
        with_points : bool
            Build :attr:`Reconstruction.points` (the segmented points as polydata);
            False leaves it empty, which saves a fifth of a live refit that only
            shows the surface.

        Returns
        -------
        Reconstruction
            Its ``summary["warnings"]`` (and ``segmentation.warnings``) name the bone
            points (``RejectionParams.bone_points``) no accepted contour reaches in
            the frames near them, as offline, and at the ``final`` refit also those off
            every frame: offline an error, here a warning, the scan being over
            (:func:`_point_warnings`; during the scan a point not reached yet is no
            fault).

        Raises
        ------
        BoneUSReconError
            Not enough yet: no frame, no contour, too few slices, or the probe has not
            moved far enough.
        """
        sweep = self.sweep()
        t0 = time.perf_counter()
        frames = self._frames
        need = MIN_FRAMES_PER_CONTROL_POINT * self.params.fit.n_control_points[0]
        n_ok = sum(not f.reason for f in frames)
        if not final and n_ok < need:
            raise BoneUSReconError(f"waiting for frames: {n_ok} of {need} with a bone contour")
        seg = _select(
            frames,
            self._track,
            self.params.segmentation,
            self._segment_s,
            self.recovery_counts,
            # Until the track reaches every bone point, it may move to another bone
            # when the probe reaches one: the frames off that track are then to be
            # searched, so every frame keeps its pixels (see the class's notes).
            self.live.keep_all_pixels or self._points_open,
        )
        if not seg.accepted:
            raise BoneUSReconError("no bone contour found yet")
        if self.params.segmentation.rejection.bone_points:
            said, self._points_open = _point_warnings(seg, sweep, self.params, final)
            seg = replace(seg, warnings=seg.warnings + said)
        t_seg = self._segment_s + time.perf_counter() - t0
        return reconstruction_from_segmentation(
            sweep, seg, self.params, segment_s=t_seg, with_points=with_points
        )

    @property
    def pixels_kept(self) -> int:
        """Frames whose pixels are kept (off the track at the last refit, or newer)."""
        return sum(f.image is not None for f in self._frames)

    def memory_bytes(self) -> int:
        """Approximate bytes held for the kept frames (contours, poses, track links,
        the pixels of frames off the track)."""
        return int(
            sum(
                sum(c.points_px.nbytes + c.intensity.nbytes + 200 for c in f.candidates.candidates)
                + 200
                + f.steps.nbytes
                + (f.image.nbytes if f.image is not None else 0)
                + (f.evidence.nbytes if f.evidence is not None else 0)
                for f in self._frames
            )
            + self._track.memory_bytes()
        )


# ------------------------------------------------------------------------------------
# From messages to posed frames
# ------------------------------------------------------------------------------------
@dataclass(frozen=True)
class PosedFrame:
    """One received frame with its pose, or why it has none.

    Attributes
    ----------
    image : ndarray of uint8 (H, W), or None when the pixels are unusable
    pose : ndarray (4, 4) or None
        ``ImageToReference``; None when ``problem`` is set.
    timestamp : float
        Seconds (the message's timestamp).
    problem : str
        "" when the frame can be used, else why not (e.g. ``"ProbeToTracker status
        INVALID"``, ``"ProbeToTracker missing"``).
    """

    image: np.ndarray | None
    pose: np.ndarray | None
    timestamp: float
    problem: str = ""


def _pose_problem(m: np.ndarray) -> str:
    """Why a composed pose cannot be used ("" if it can); as sequence_io judges a frame."""
    if not np.all(np.isfinite(m)):
        return "pose has NaN or infinite values"
    if np.any(np.abs(m[3] - [0, 0, 0, 1]) > 1e-6):
        return "pose is not an affine transform (last row is not 0 0 0 1)"
    c0, c1 = m[:3, 0], m[:3, 1]
    n0, n1 = np.linalg.norm(c0), np.linalg.norm(c1)
    if not (np.linalg.norm(np.cross(c0, c1)) > 1e-9 * n0 * n1 and n0 > 0 and n1 > 0):
        return "pose is singular (image axes collapse)"
    return ""


def frame_pixels(image: np.ndarray) -> tuple[np.ndarray | None, str]:
    """An IMAGE message's voxels ``(K, J, I[, C])`` as one uint8 frame ``(H, W)``.

    Grey B-mode sent as RGB(A) uses its first channel, as the file reader does. Other
    pixel types are refused: the file reader maps them to 0..255 from the levels of
    the whole recording, which a stream does not have yet.
    """
    a = np.asarray(image)
    if a.ndim == 4:
        a = a[..., 0]
    if a.ndim == 3:
        if a.shape[0] != 1:
            return None, f"a 3D image ({a.shape[0]} slices), expected one 2D frame"
        a = a[0]
    if a.ndim != 2 or min(a.shape) < 2:
        return None, f"image of shape {np.shape(image)} is not a 2D frame"
    if a.dtype != np.uint8:
        return None, f"pixel type {a.dtype} (send 8-bit B-mode frames)"
    return np.ascontiguousarray(a), ""


class PoseAssembler:
    """Pair IMAGE and TRANSFORM messages into posed frames.

    Three ways to get ``ImageToReference``, as :func:`~BoneUSRecon.Logic.sequence_io.read_sweep`:

    * default: the IMAGE's own matrix (PLUS ``EmbeddedTransformToFrame="Reference"``);
    * ``transform="ImageToReference"`` (any ``ImageTo<X>``): a TRANSFORM of that name,
      or a chain of received transforms reaching it (e.g. the PLUS chain
      ``inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe`` with ``calibration``
      giving ``ImageToProbe`` from a PLUS device-set XML); ``transform="ProbeToTracker"``
      (any ``<A>To<B>``) means the pose given by that transform, as for files;
    * ``calibration`` alone: target ``ImageToReference`` through the chain.

    With a transform, the IMAGE's matrix is taken as pixels to the ``Image`` frame
    (PLUS ``EmbeddedTransformToFrame="Image"``: pixel units) and composed after the
    chain. Transforms pair with an image when their timestamps agree within
    ``tolerance_s``; a transform flagged invalid (metadata ``TransformStatus`` or
    ``Status`` not ``OK``, or NaN values) makes that frame unusable. PLUS may send an
    image before or after its transforms, so an image waits for them until the next
    image arrives.

    Parameters
    ----------
    transform : str, optional
    calibration : path-like, optional
    image_name : str, optional
        Device name of the IMAGE stream to use (default: the first one seen).
    tolerance_s : float
    """

    def __init__(
        self,
        *,
        transform: str | None = None,
        calibration: str | os.PathLike[str] | None = None,
        image_name: str | None = None,
        tolerance_s: float = LiveParams.pose_tolerance_s,
    ) -> None:
        self.image_name = image_name
        self.tolerance_s = float(tolerance_s)
        self.calibration = None if calibration is None else read_calibration(calibration)
        if transform is None and calibration is None:
            self.target: str | None = None
        else:
            name = transform or "ImageToReference"
            name = name[: -len("Transform")] if name.endswith("Transform") else name
            ab = split_transform_name(name)
            if ab is None or ab[0] == ab[1]:
                raise BoneUSReconError(
                    f"--transform {transform!r} is not a transform name like ImageToReference"
                )
            self.target = name
        self._latest: dict[str, tuple[float, np.ndarray, str]] = {}
        self._pending: tuple[np.ndarray | None, np.ndarray, float, str] | None = None
        #: IMAGE messages of other devices, ignored.
        self.other_images = 0

    @property
    def mode(self) -> str:
        """How poses are obtained, for the summary."""
        if self.target is None:
            return "the IMAGE message's matrix"
        return self.target + (" (calibration ImageToProbe)" if self.calibration is not None else "")

    # -- input -----------------------------------------------------------------------
    def add_transform(
        self, name: str, matrix: np.ndarray, timestamp: float, status: str = "OK"
    ) -> list[PosedFrame]:
        """A TRANSFORM message arrived; returns the frames it completes (0 or 1)."""
        if self.target is None:
            return []
        name = name[: -len("Transform")] if name.endswith("Transform") else name
        m = np.asarray(matrix, dtype=np.float64)
        problem = ""
        if status.upper() != "OK":
            problem = f"{name} status {status}"
        elif m.shape != (4, 4) or not np.all(np.isfinite(m)):
            problem = f"{name} has NaN or infinite values"
        self._latest[name] = (float(timestamp), m, problem)
        if self._pending is not None:
            frame = self._try(*self._pending)
            if frame is not None:
                self._pending = None
                return [frame]
        return []

    def add_image(
        self, name: str, voxels: np.ndarray, matrix: np.ndarray, timestamp: float
    ) -> list[PosedFrame]:
        """An IMAGE message arrived; returns the frames now decided (0, 1 or 2)."""
        if self.image_name is None:
            self.image_name = name
        if name != self.image_name:
            self.other_images += 1
            return []
        out = self.flush()
        image, problem = frame_pixels(voxels)
        item = (image, np.asarray(matrix, dtype=np.float64), float(timestamp), problem)
        frame = self._try(*item)
        if frame is None:
            self._pending = item
        else:
            out.append(frame)
        return out

    def flush(self) -> list[PosedFrame]:
        """The image still waiting for transforms, declared unusable (end of stream)."""
        if self._pending is None:
            return []
        image, _, ts, problem = self._pending
        self._pending = None
        return [PosedFrame(image, None, ts, problem or self._missing(ts))]

    # -- pairing ---------------------------------------------------------------------
    def _try(
        self, image: np.ndarray | None, ijk: np.ndarray, ts: float, problem: str
    ) -> PosedFrame | None:
        if problem:
            return PosedFrame(image, None, ts, problem)
        if self.target is None:
            return self._posed(image, ijk, ts)
        steps = self._steps()
        if steps is None:
            return None
        total = np.eye(4)
        for name, inverted in steps:
            if name == "ImageToProbe" and self.calibration is not None:
                m = self.calibration
            else:
                t, m, bad = self._latest[name]
                if abs(t - ts) > self.tolerance_s:
                    return None  # not this frame's pose (yet)
                if bad:
                    return PosedFrame(image, None, ts, bad)
            if inverted:
                if abs(np.linalg.det(m)) < 1e-12 * max(np.abs(m[:3, :3]).max(), 1e-300) ** 3:
                    return PosedFrame(image, None, ts, f"{name} is singular")
                m = np.linalg.inv(m)
            total = m @ total
        return self._posed(image, total @ ijk, ts)

    @staticmethod
    def _posed(image: np.ndarray | None, pose: np.ndarray, ts: float) -> PosedFrame:
        problem = _pose_problem(pose)
        return PosedFrame(image, None if problem else pose, ts, problem)

    def _edges(self) -> dict[str, tuple[str, str]]:
        edges = {n: ab for n in self._latest if (ab := split_transform_name(n)) is not None}
        if self.calibration is not None:
            edges["ImageToProbe"] = ("Image", "Probe")
        return edges

    def _steps(self) -> list[tuple[str, bool]] | None:
        """The chain of transforms giving the target pose from what was received."""
        assert self.target is not None
        edges = self._edges()
        a, b = split_transform_name(self.target)  # type: ignore[misc]
        if a == "Image":
            return find_chain(edges, "Image", b)
        if self.target not in edges:
            return None
        others = {k: v for k, v in edges.items() if k != self.target}
        head = find_chain(others, "Image", a)
        return None if head is None else head + [(self.target, False)]

    def _missing(self, ts: float) -> str:
        """Why an image found no pose: which transform is missing or stale."""
        assert self.target is not None
        steps = self._steps()
        if steps is None:
            have = ", ".join(sorted(self._latest)) or "none"
            need = "the calibration" if self.calibration is None else "a chain"
            return f"no {self.target}: no chain of received transforms (received: {have}; {need}?)"
        for name, _ in steps:
            if name in self._latest and abs(self._latest[name][0] - ts) > self.tolerance_s:
                return f"{name} missing for this frame"
        return f"{self.target} missing"


# ------------------------------------------------------------------------------------
# Recording
# ------------------------------------------------------------------------------------
@dataclass
class _Recorded:
    poses: list[np.ndarray] = field(default_factory=list)
    timestamps: list[float] = field(default_factory=list)
    valid: list[bool] = field(default_factory=list)


class SweepRecorder:
    """Save received frames as a PLUS sequence, pixels streamed to disk as they come.

    The pixels go to a hidden temporary file beside the output (memory stays flat
    however long the session); :meth:`finish` writes the sequence with
    :func:`~BoneUSRecon.Logic.sequence_io.write_sweep` (atomically) and removes it.
    Frames whose pose is unusable are kept with status ``INVALID``, as PLUS records
    them.

    Parameters
    ----------
    path : path-like
        ``.mha`` or ``.mhd`` output.
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = check_output_path(path, (".mha", ".mhd"))
        parent = self.path.parent if str(self.path.parent) else Path(".")
        fd, name = tempfile.mkstemp(prefix=f".{self.path.stem}.", suffix=".frames", dir=parent)
        self._file = os.fdopen(fd, "wb")
        self._tmp = Path(name)
        self._shape: tuple[int, int] | None = None
        self._meta = _Recorded()

    @property
    def n_frames(self) -> int:
        """Frames recorded so far."""
        return len(self._meta.valid)

    def add(self, image: np.ndarray, pose: np.ndarray | None, timestamp: float) -> bool:
        """Append a frame (``pose`` None: invalid); False if its size differs from the first."""
        if self._shape is None:
            self._shape = (int(image.shape[0]), int(image.shape[1]))
        elif image.shape != self._shape:
            return False
        self._file.write(np.ascontiguousarray(image, dtype=np.uint8).tobytes())
        self._meta.poses.append(np.eye(4) if pose is None else np.asarray(pose, float))
        self._meta.timestamps.append(float(timestamp))
        self._meta.valid.append(pose is not None)
        return True

    def finish(self) -> Path | None:
        """Write the sequence file; None (and nothing written) when no frame came."""
        try:
            self._file.close()
            if not self.n_frames or self._shape is None:
                return None
            h, w = self._shape
            frames = np.memmap(self._tmp, dtype=np.uint8, mode="r", shape=(self.n_frames, h, w))
            sweep = Sweep(
                frames=frames,
                image_to_reference=np.stack(self._meta.poses),
                timestamps=np.array(self._meta.timestamps),
                valid=np.array(self._meta.valid, bool),
            )
            out = write_sweep(sweep, self.path)
            del frames, sweep
            return out
        finally:
            self.discard()

    def discard(self) -> None:
        """Remove the temporary pixel file (nothing is written)."""
        with contextlib.suppress(OSError):
            self._file.close()
        with contextlib.suppress(OSError):
            self._tmp.unlink()


def stats_row(recon: Reconstruction | None) -> dict[str, Any]:
    """Frames used and rejected and the grid coverage of a refit, for status lines."""
    if recon is None:
        return {"used": 0, "rejected": 0, "coverage": 0.0}
    s = recon.summary
    return {
        "used": int(s["segmented_frames"]) - len(s["fit_rejected_frames"]),
        "rejected": int(s["rejected_frames"]) + len(s["fit_rejected_frames"]),
        "coverage": float(s["grid_coverage"]),
    }

"""Sweep-level step: frames off the bone track searched again, guided by the track.

The per-frame step (:mod:`.candidates`) offers each frame's contours without knowing
its neighbours, so it must find the bone on the frame's own evidence. On real-like
images that fails in two ways (measured at the cadaver's geometry, hard realism, seed
5, 200 frames): in 4-8 frames of 40 no candidate lies on the bone (the faint top scores
as low as the speckle around it, so a pass takes a fascia or a copy instead), and in
1-7 the bone is offered only as a piece that meets its neighbours' pieces end to end
(overlap share 0.21 < ``min_overlap_share``), so no link reaches it.

Once the track is chosen, its contours say where the bone lies in a frame off the
track: :func:`recover_frames` projects the nearest track contours before and after the
frame into its plane through the poses, interpolates them (weighted by closeness along
the sweep), and runs the same optimal path as the per-frame step through the frame's
own evidence, only inside the band the track's links would accept
(``tolerance_mm + tolerance_per_mm * z`` around the interpolated contour; ``z`` the
distance along the sweep to the nearer track frame, :func:`guided_candidate`). The
contour found there is added to the frame's candidates and the track is chosen again
over all frames (:func:`.track.select_bone_track`), so
the guided contour is linked, valued and judged like any other: it joins the track
only if it links within tolerance to both sides and carries evidence above the null
level along at least ``min_share`` of the band.

Between two track frames the frame's own shadow is not asked to prove the bone anew
where the search on its score finds nothing: a second search opens the shadow gate
from the tissue level on (:func:`vouched_evidence`), for a top over a grey shadow whose
reverberation bands read at the tissue level under it. Past the track's ends, where
the nearer track frame alone vouches, too: :mod:`.ends` judges what it finds.

Why it generalises: nothing here reads a grey level. The band is the track's own
continuity tolerance, the evidence is the frame's robust z-scores (:mod:`.evidence`),
and the share is of the columns the neighbours' bone spans in this frame. Between
two track frames both sides agree on where the bone is, so a look-alike can enter only
where it lies within the tolerance of the bone (and a fascia at the bone's level
beside it lies outside the neighbours' lateral extent). At the ends of the track only
one side would vouch, and beyond the last frame showing bone there is no bone to find,
so frames outside the track's span are not searched by default (``both_sides``; with
the bone removed from the last frames of simulated sweeps, a one-sided search found
"bone" in the band in 7 of 24 sweeps: a layer at the bone's level carries on there).
:mod:`.ends` judges what is found past the track's ends (a bone shadow under it,
relative to the track's typical frame), and ``EndsParams.search_past_ends`` has those
frames searched with one side guiding (:func:`settings`, offline and live alike).

The same search judges the track's own frames (:func:`recheck_track`, after the ends
cut): a track frame may carry a contour 1-1.8 mm over a faint top (a run of speckle or
a layer capping the dome, wider than the per-frame step's excursion rule takes), which
links to its neighbours within tolerance. Where its contour strays from the
interpolation of the nearest track frames on both sides (:func:`stray`: at least
``min_stray`` of the nearer link tolerance on median), the frame is searched as a
frame off the track, and the guided contour replaces its own only if it agrees with
the neighbours (stray at most ``max_stray_ratio`` of its own) and is at least as wide
(evidence above the null level over at least as many mm). Why it generalises: the
same band and evidence as recovery, judged by the track's own tolerance, no grey
level; the frame's own evidence still decides where in the band the contour runs.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import replace

import numpy as np

from BoneUSRecon.Logic.segmentation.candidates import (
    BoneCandidate,
    FrameCandidates,
    _cut_at_shoulder,
    _groups,
    _log_ratio,
    _optimal_path,
    _path_steps,
    _refine,
    _underside_step,
)
from BoneUSRecon.Logic.segmentation.detection import sample_bilinear
from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps, bone_evidence, shadow_gate
from BoneUSRecon.Logic.segmentation.features import median1d
from BoneUSRecon.Logic.segmentation.flanks import extend_candidates
from BoneUSRecon.Logic.segmentation.params import (
    RecoveryParams,
    RejectionParams,
    SegmentationParams,
    ShadowPathParams,
)
from BoneUSRecon.Logic.segmentation.track import TrackChoice, _project, _sampled
from BoneUSRecon.Logic.sweep import frame_planes, pixels_to_reference

__all__ = [
    "applies",
    "settings",
    "prior_frames",
    "track_prior",
    "guided_candidate",
    "across_field",
    "vouched_evidence",
    "recover_frame",
    "recover_frames",
    "sweep_level",
    "off_skin",
    "stray",
    "recheck_prior",
    "recheck_frame",
    "recheck_candidate",
    "recheck_track",
    "with_candidate",
    "with_chosen",
]

#: A prior: per neighbouring track contour, its (lateral mm, depth mm) in the frame's
#: plane ordered by lateral position, and its median distance along the sweep (mm).
Prior = list[tuple[np.ndarray, np.ndarray, float]]


def applies(params: SegmentationParams) -> bool:
    """Whether a segmentation with these parameters searches frames off the track again:
    recovery on, and the shadowpath segmenter (the guided search is its optimal path on
    its evidence; the paper's snake has none). :func:`.driver.segment_sweep` and a live
    session ask the same question here."""
    return params.method == "shadowpath" and params.recovery.enabled


def settings(params: SegmentationParams) -> RecoveryParams:
    """The recovery settings a segmentation with these parameters searches with:
    ``params.recovery``, one-sided (``both_sides`` False) past the track's ends when
    the ends cut (:mod:`.ends`) is on to judge what is found there
    (``EndsParams.search_past_ends``). :func:`.driver.segment_sweep` and a live
    session take them from here."""
    if params.ends.enabled and params.ends.search_past_ends:
        return replace(params.recovery, both_sides=False)
    return params.recovery


def prior_frames(
    chosen: np.ndarray, f: int, reach: int, both_sides: bool = True
) -> list[int] | None:
    """The track frames a prior for frame ``f`` is made of (:func:`track_prior`).

    The nearest track frame before ``f`` and the nearest after it, each at most
    ``reach`` frames away; ``None`` when there is none, or only one and ``both_sides``.
    With the frames' candidates and poses, these and their chosen candidates are all
    a prior depends on (a live session caches guided candidates by them).
    """
    on = np.flatnonzero(np.asarray(chosen) >= 0)
    before = on[(on < f) & (on >= f - reach)]
    after = on[(on > f) & (on <= f + reach)]
    near = [int(before[-1])] if before.size else []
    near += [int(after[0])] if after.size else []
    if not near or (both_sides and len(near) < 2):
        return None
    return near


def track_prior(
    frames: Sequence[FrameCandidates],
    choice: TrackChoice,
    poses: np.ndarray | Sequence[np.ndarray],
    f: int,
    reach: int,
    both_sides: bool = True,
) -> Prior | None:
    """The track's contours nearest to frame ``f`` (before and after), in ``f``'s plane.

    Parameters
    ----------
    frames : sequence of FrameCandidates
    choice : TrackChoice
        The track over ``frames``.
    poses : ndarray, shape (N, 4, 4), or sequence of (4, 4)
        ``ImageToReference`` of each frame.
    f : int
        The frame to search.
    reach : int
        Track frames at most this many frames away are used.
    both_sides : bool
        Require a track frame on each side (else ``None``).

    Returns
    -------
    list of (lateral, depth, z) or None
        ``lateral`` ascending, mm; ``depth`` mm; ``z`` the median out-of-plane distance.
    """
    near = prior_frames(choice.chosen, f, reach, both_sides)
    if near is None:
        return None
    origin, axes, normal = frame_planes(np.asarray(poses[f], dtype=float)[None])
    prior: Prior = []
    for g in near:
        cand = frames[g].candidates[int(choice.chosen[g])]
        ref = pixels_to_reference(poses[g], _sampled(cand.core_px, frames[g].spacing))
        a = _project(ref, origin[0], axes[0], normal[0])
        o = np.argsort(a[:, 0], kind="stable")
        prior.append((a[o, 0], a[o, 1], median1d(a[:, 2])))
    return prior


def guided_candidate(
    image: np.ndarray,
    spacing: tuple[float, float],
    prior: Prior,
    shadowpath: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
    rejection: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
    min_share: float = RecoveryParams.min_share,
    max_offset: float = RecoveryParams.max_offset,
    evidence: EvidenceMaps | None = None,
) -> BoneCandidate | None:
    """The bone contour of one frame inside the band a track prior allows, or None.

    The per-frame step's optimal path (same evidence, slope costs and no-bone state)
    through the frame's score, restricted to ``tol = tolerance_mm + tolerance_per_mm
    * z`` around the prior's depth at each column (where two contours of the prior
    overlap, their depths are averaged with weights ``1 / (z + 0.1 mm)``: the nearer
    frame counts more; the tolerance is the nearer one's). The run with the most
    evidence above the null level is kept if it spans at least ``min_share`` of the
    prior's usable columns and its median depth offset from the prior is at most
    ``max_offset`` of the wider link tolerance (the unit the rule was measured in);
    it is then refined to sub-pixel and followed down its flanks as every candidate
    is.

    Why the nearer contour's tolerance where both sides cover a column: the track's
    link tolerance grows with the distance along the sweep (``tolerance_per_mm``) for
    a surface inclined to the sweep, whose depth at a column drifts with that
    distance; between two track frames the interpolation follows the drift from both
    sides, so what is left to allow for is the bone's change over the distance to the
    nearer frame, which vouches with its own link tolerance. The farther frame's wider
    band only admits layers over a faint top: with it, the hard radius (seed 13, 0.3
    mm, frame 27, track frames 2.4 and 2.9 mm away, band +-2.2 mm) and the hard ulna
    (seed 29, frame 18, 2.1 and 5.7 mm away, band +-3.3 mm) were recovered on speckle
    1.4-1.5 mm over the bone's faint top, while the interpolated contour lay within
    0.5 mm of it (0.40 and 0.15 mm with the nearer band). No grey level and no new
    constant: the band is the nearer link's own tolerance.

    Where the frame's own score holds no such run, the band is searched again on
    :func:`vouched_evidence` (the shadow gate open from the tissue level on): a top
    over a grey shadow whose reverberation bands fill the shadow windows (see there).
    Between two track frames both vouch for the bone; past the track's ends (searched
    one-sided only with the ends cut on, ``EndsParams.search_past_ends``) the nearer
    track frame does, and the cut judges the contour by its shadow as any found
    there. One-sided too since session 34: a hard tibia rising to 5 mm under the skin
    in its last frames (160 x 128, seed 157) lost its last three, the top's shadow
    z-score 0.3-0.8 under reverberation bands, and the surface was 0.65 mm from gold
    (0.34 with them); with the last quarter or the first 3 frames of 70 hard sweeps
    bone-free (160 x 128, seeds 5-19; 475 x 405, seeds 5 and 151), no bone-free frame
    was kept either way (benchmarks README, lead session 34).

    ``evidence``: the frame's :func:`.evidence.bone_evidence` with ``shadowpath``, if
    the caller kept it (the same result; None: computed here).
    """
    sp, rp = shadowpath, rejection
    spc = (float(spacing[0]), float(spacing[1]))
    img = np.asarray(image)
    ev = bone_evidence(img, spc, sp) if evidence is None else evidence
    if ev is None:
        return None
    found = _guided_in_band(img, spc, ev, prior, sp, rp, min_share, max_offset)
    if found is None:
        # Nothing on the frame's own score, and the track vouches for the bone's
        # shadow: searched again asking only that the frame's shadow not refute it
        # (:func:`vouched_evidence`). What that search finds counts only if the gate is
        # what hid it: its shadow, on median, short of the gate's full opening (over a
        # shadow the frame proves, the echo alone did not pay off). Past the track's
        # ends one side vouches, and :mod:`.ends` then judges what is found by its
        # shadow against the track's typical frame, as any contour found there.
        found = _guided_in_band(
            img, spc, vouched_evidence(ev, sp), prior, sp, rp, min_share, max_offset
        )
        if found is not None and not found.shadow_z < sp.shadow_z_full:
            found = None
    if found is not None and across_field(found.core_px, ev, spc):
        return None
    return found


#: A run of a contour's points whose depths stay within this of its first one is level (mm).
_LEVEL_MM = 0.5
#: ... and a contour is lines across the field when at least this share of its points
#: lie in level runs whose line runs on at their depth over at least this share of the
#: usable columns on each side of the contour, echoing there at least half as strongly
#: as the run.
_ACROSS_SHARE = 0.8


def across_field(points_px: np.ndarray, ev: EvidenceMaps, spacing: tuple[float, float]) -> bool:
    """Whether a contour is made of level lines that run on across the whole field of view.

    A guided contour (:func:`guided_candidate`) must be part of a bone: a convex
    outline, whose depth changes along it and which ends where its flanks turn down.
    A contour made of level runs (depth within ``_LEVEL_MM`` along each), each of whose
    lines carries on at its depth over nearly every usable column on both sides of the
    contour with at least half the run's own echo (``echo_z`` within 0.3 mm of that
    depth), is layers across the field: with the probe off the skin, the frame holds
    only the lens's reverberation, equally spaced bands across the whole image, and the
    guided band found one at the bone's depth, or stepped down over several along the
    bone's expected outline (the simulator's contact loss, hard realism, 475 x 405, seed
    173: 4 of 5 sweeps kept frame 30 so, 0.5-1.1 mm from where the bone would be; one
    band, 0.1-0.2 mm deep from end to end but for a flank tracer's bent end, or three,
    with 0.65-1.1 of its echo on both sides; the sweeps' own bone contours there are 2-9
    mm deep end to end; with the rule 3 of the 4 no longer keep it: the radius's two
    deeper bands fade over half the field's columns on one side). A bone's top meets at
    most a fascia running off one side of it, not lines across the image on both, and
    its flanks are no level runs.

    Why it generalises: the shape in mm, the echo as this frame's z-score relative to
    the contour's own, the columns the frame's own usable field: no grey level.
    """
    pts = np.asarray(points_px, float)
    n = pts.shape[0]
    if n < 3:
        return False
    pts = pts[np.argsort(pts[:, 0], kind="stable")]
    wj, wi = ev.work_index(pts)
    cols = np.arange(ev.echo_z.shape[1])
    beside = [(cols < wi.min()) & ev.usable, (cols > wi.max()) & ev.usable]
    if not (beside[0].any() and beside[1].any()):
        return False
    k = max(1, int(round(0.3 / ev.dy)))
    z = pts[:, 1] * float(spacing[1])
    # Level runs, left to right (a loop over the contour's points: guided contours only,
    # a few per sweep).
    starts = [0]
    for i in range(1, n):
        if abs(z[i] - z[starts[-1]]) > _LEVEL_MM:
            starts.append(i)
    starts.append(n)
    across = 0
    for a, b in zip(starts[:-1], starts[1:], strict=True):
        if b - a < 3:
            continue
        own = median1d(ev.echo_z[wj[a:b], wi[a:b]])
        if not own > 0:
            continue
        row = int(np.median(wj[a:b]))
        line = ev.echo_z[max(0, row - k) : row + k + 1].max(axis=0) >= 0.5 * own
        if all(np.mean(line[side]) >= _ACROSS_SHARE for side in beside):
            across += b - a
    return across >= _ACROSS_SHARE * n


def _guided_in_band(
    img: np.ndarray,
    spc: tuple[float, float],
    ev: EvidenceMaps,
    prior: Prior,
    sp: ShadowPathParams,
    rp: RejectionParams,
    min_share: float,
    max_offset: float,
) -> BoneCandidate | None:
    """:func:`guided_candidate`'s search on the evidence maps ``ev`` (its score read)."""
    h, w = ev.score.shape
    # Working-grid centres in mm (the same mapping as :func:`.candidates._refine`).
    xw = ((np.arange(w) + 0.5) * ev.fx - 0.5) * spc[0]
    yw = ((np.arange(h) + 0.5) * ev.fy - 0.5) * spc[1]
    num, den, tol = np.zeros(w), np.zeros(w), np.full(w, np.inf)
    wide = np.zeros(w)
    for lat, depth, z in prior:
        inside = (xw >= lat[0]) & (xw <= lat[-1])
        wt = 1.0 / (z + 0.1)
        num[inside] += wt * np.interp(xw[inside], lat, depth)
        den[inside] += wt
        link = rp.tolerance_mm + rp.tolerance_per_mm * z
        # The band: the nearest vouching contour's tolerance (see the docstring); the
        # offset rule below keeps the widest as its unit (it was measured in it).
        tol[inside] = np.minimum(tol[inside], link)
        wide[inside] = np.maximum(wide[inside], link)
    tol[den == 0] = 0.0
    cols = np.flatnonzero((den > 0) & ev.usable)
    shift_cost, min_cols = _path_steps(ev, sp)
    if cols.size < min_cols:
        return None
    c0, c1 = int(cols[0]), int(cols[-1]) + 1
    expect = np.full(c1 - c0, np.nan)
    expect[cols - c0] = num[cols] / den[cols]
    band = np.abs(yw[:, None] - expect[None, :]) <= tol[None, c0:c1]  # NaN: False
    gain = (ev.score[:, c0:c1].astype(float) - sp.null_z) * ev.dx
    gain[~band] = -1e3  # outside the band: never on the path
    path = np.full(w, -1, dtype=np.intp)
    path[c0:c1] = _optimal_path(gain, shift_cost, sp.switch_cost)
    best: tuple[float, np.ndarray] | None = None
    for g in _groups(path, ev, sp):
        if g.size < min_cols:
            continue
        s = float((ev.score[path[g], g] - sp.null_z).sum() * ev.dx)
        if best is None or s > best[0]:
            best = (s, g)
    if best is None or best[1].size < min_share * cols.size:
        return None
    strength, g = best
    rows = path[g]
    # The bone continues smoothly between the track's frames: its contour lies near
    # the interpolated one (measured on 82 recovered frames on the bone: median offset
    # 0.12 of the wider link tolerance, then the band's half-width, p95 0.40, max
    # 0.74), while a structure crossing the band (a false echo above the bone, a layer
    # meeting it) follows it only in part (0.60-0.68 on the three look-alikes
    # recovered without this rule).
    offset = median1d(np.abs(yw[rows] - expect[g - c0])) / median1d(wide[g])
    if offset > max_offset:
        return None
    pts = _refine(img, ev, g, rows, sp, spc[1])
    # A layer running off the bone's shoulder is cut off as in the frame's own passes
    # (:func:`.candidates._shoulder_cut`, its strength likewise): the band follows the
    # neighbours' contours, and where one ran on along such a layer the guided path
    # runs on along it (radius, hard, seed 43, frame 34: 30 of 51 points on a fascia
    # 1.5 mm off the bone; cut, 3 of 71 after the rim).
    keep, strength = _cut_at_shoulder(
        pts,
        g,
        rows,
        strength,
        ev,
        lambda: _underside_step(_log_ratio(ev), g, rows, ev.dy),
        spc,
        sp,
        min_cols,
    )
    if keep is not None:
        g, rows, pts = g[keep], rows[keep], pts[keep]
    cand = BoneCandidate(
        pts,
        sample_bilinear(img, pts),
        strength,
        median1d(ev.echo_z[rows, g]),
        median1d(ev.shadow_z[rows, g]),
        guided=True,
    )
    return extend_candidates(img, ev, [cand], spc, sp.flanks, sp.rim)[0]


def vouched_evidence(ev: EvidenceMaps, shadowpath: ShadowPathParams) -> EvidenceMaps:
    """``ev`` with its score's shadow gate fully open from the tissue level on.

    The per-frame score is the echo z-score times a shadow gate rising from 0 at
    ``shadow_z_zero`` (brighter than the tissue beside: tissue under a layer) to 1 at
    ``shadow_z_full`` (darker: a shadow proven in the frame itself). Here the gate
    rises over the lower half of that range only, to 1 at the shadow's null centre
    (z = 0, the tissue at that depth): darker-than-tissue is no longer asked of the
    frame, brighter-than-tissue still closes the gate as before.

    Used by :func:`guided_candidate`, where the track vouches for the bone (a track
    frame on each side, or past its ends the nearer one, the ends cut judging what is
    found) and the search on the frame's own score found nothing: the neighbours'
    contours were chosen on their own frames' shadow, and what is left to ask of this
    frame is where its echo runs in the band and that no layer with tissue beneath it
    takes its place. A contour so found is kept only if its median shadow z-score is
    under ``shadow_z_full`` (the gate is what hid it; over a shadow the frame proves,
    the echo alone did not pay off: a prior moved 2-4 mm up into the tissue over the
    hard tibia, seed 7, found such a run 2-3 mm off the bone, shadow z 1.5-1.8, echo
    z 0.8-1.0; the tops found over the grey shadow had shadow z -0.34..0.46 and echo
    z 1.26-1.62, 17 frames of 6 sweeps). Why the frame's own shadow cannot be asked
    for more: under a grey shadow (0.65 of the tissue beside, filled with equally spaced
    reverberation bands and the far cortex's echo), a specular top sends its
    reverberation copies down the columns right under it, so the shadow windows under
    the top read at the tissue level. Measured on the lead's harness, S radius grey
    seed 71 and S clavicle grey seed 73 (160 x 128): along the true top of the frames
    the track skipped the shadow z-score was -0.7..0.3 over the dome (median -0.1 to
    0.1), the echo z-score 1.3-1.9, so the score (0.3-0.7) stayed under ``null_z``
    and the guided search found no run, though the track's interpolated contour lay
    within 0.04-0.07 mm (median) of the true top; the frame's own candidates were the
    first reverberation copy (2.2-2.4 mm under the top) and the far cortex. No grey
    level and no new constant: the gate's own ends and the null's centre.
    """
    lo = float(shadowpath.shadow_z_zero)
    hi = float(shadowpath.shadow_z_full)
    if not lo < 0.0 < hi:  # the tissue level is not inside the gate's ramp
        return ev
    gate = shadow_gate(ev.shadow_z, lo, hi)
    vouched = shadow_gate(ev.shadow_z, lo, 0.0)
    # The score divided by its gate and multiplied by the vouched one (score is 0 where
    # the gate is: both gates close at the same z), capped as the score is.
    score = np.divide(ev.score * vouched, gate, out=np.zeros_like(ev.score), where=gate > 0)
    np.minimum(score, np.float32(shadowpath.max_z), out=score)
    return replace(ev, score=score.astype(np.float32, copy=False))


def recover_frames(
    frames: Sequence[FrameCandidates],
    choice: TrackChoice,
    poses: np.ndarray,
    image_of: Callable[[int], np.ndarray],
    shadowpath: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
    rejection: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
    params: RecoveryParams = RecoveryParams(),  # noqa: B008 (frozen dataclass)
    evidence_of: Callable[[int], EvidenceMaps | None] | None = None,
) -> tuple[list[FrameCandidates], list[int]]:
    """Frames off the track with a guided candidate added (:func:`guided_candidate`).

    Parameters
    ----------
    frames : sequence of FrameCandidates
    choice : TrackChoice
        The track over ``frames`` (:func:`.track.select_bone_track`).
    poses : ndarray, shape (N, 4, 4)
    image_of : callable
        ``image_of(n)``: the pixels of frame ``n`` (index into ``frames``); called
        only for the frames searched.
    shadowpath, rejection, params
        The per-frame evidence, the track's tolerances, and this step's settings.
    evidence_of : callable, optional
        ``evidence_of(n)``: frame ``n``'s evidence maps if the caller kept them (None:
        computed from its pixels); called only for the frames searched.

    Returns
    -------
    frames : list of FrameCandidates
        ``frames`` with one candidate appended where the search found one.
    searched : list of int
        The frames whose candidates changed.
    """
    out = list(frames)
    changed: list[int] = []
    if not params.enabled:
        return out, changed
    poses = np.asarray(poses, dtype=float)
    median = sweep_level(frames)
    for f in np.flatnonzero(np.asarray(choice.chosen) < 0).tolist():
        cand = recover_frame(
            frames, choice, poses, f, image_of, shadowpath, rejection, params, evidence_of, median
        )
        if cand is None:
            continue
        out[f] = with_candidate(frames[f], cand)
        changed.append(f)
    return out, changed


def recover_frame(
    frames: Sequence[FrameCandidates],
    choice: TrackChoice,
    poses: np.ndarray | Sequence[np.ndarray],
    f: int,
    image_of: Callable[[int], np.ndarray],
    shadowpath: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
    rejection: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
    params: RecoveryParams = RecoveryParams(),  # noqa: B008 (frozen dataclass)
    evidence_of: Callable[[int], EvidenceMaps | None] | None = None,
    median_level: float | None = None,
) -> BoneCandidate | None:
    """The guided candidate of one frame off the track (None: not searched, or nothing
    found); :func:`recover_frames` for each such frame, and a live session for the
    frames whose prior (:func:`prior_frames`) changed. ``image_of(f)`` and
    ``evidence_of(f)`` (the frame's evidence maps if kept) are called only when the
    frame is searched; ``median_level`` is :func:`sweep_level` of ``frames`` if the
    caller has it (computed here otherwise).
    """
    if median_level is None:
        median_level = sweep_level(frames)
    if off_skin(frames[f], median_level, params.contact_level):
        return None
    prior = track_prior(frames, choice, poses, f, rejection.max_skip + 1, params.both_sides)
    if prior is None:
        return None
    return guided_candidate(
        image_of(f),
        frames[f].spacing,
        prior,
        shadowpath,
        rejection,
        params.min_share,
        params.max_offset,
        evidence_of(f) if evidence_of is not None else None,
    )


def sweep_level(frames: Sequence[FrameCandidates]) -> float | None:
    """The median of the frames' tissue levels (None: no frame has one)."""
    levels = [fc.level for fc in frames if fc.level is not None]
    return float(np.median(levels)) if levels else None


def off_skin(frame: FrameCandidates, median_level: float | None, contact_level: float) -> bool:
    """Whether ``frame``'s tissue level is under ``contact_level`` of the sweep's median
    frame's (``median_level``, :func:`sweep_level`; ``RecoveryParams.contact_level``):
    the probe off the skin.

    The level is relative to the sweep's own frames, so gain, depth and scanner do not
    matter; only the loss of the body's backscatter does (contact loss: the lens's
    reverberation over the noise floor). Frames with no level measured are never off
    the skin. A live session compares with the frames so far.
    """
    own = frame.level
    if not contact_level > 0 or own is None or median_level is None:
        return False
    return own < contact_level * median_level


def stray(
    cand: BoneCandidate,
    spacing: tuple[float, float],
    prior: Prior,
    rejection: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
) -> float:
    """How far a contour strays from the depth a track prior interpolates.

    The median, over the contour's points (sampled as the track samples them) that the
    prior covers, of ``|depth - interpolated depth| / tol``: the interpolation and
    ``tol`` (the nearer covering track frame's link tolerance) as the guided band of
    :func:`guided_candidate` makes them, so 1 is the band's edge. NaN when the prior
    covers fewer than two of its points.
    """
    xy = _sampled(cand.core_px, spacing) * np.asarray(spacing, dtype=float)
    x = xy[:, 0]
    num, den, tol = np.zeros(x.size), np.zeros(x.size), np.full(x.size, np.inf)
    for lat, depth, z in prior:
        inside = (x >= lat[0]) & (x <= lat[-1])
        wt = 1.0 / (z + 0.1)
        num[inside] += wt * np.interp(x[inside], lat, depth)
        den[inside] += wt
        link = rejection.tolerance_mm + rejection.tolerance_per_mm * z
        tol[inside] = np.minimum(tol[inside], link)
    ok = den > 0
    if np.count_nonzero(ok) < 2:
        return float("nan")
    return median1d(np.abs(xy[ok, 1] - num[ok] / den[ok]) / tol[ok])


def recheck_prior(
    frames: Sequence[FrameCandidates],
    choice: TrackChoice,
    poses: np.ndarray | Sequence[np.ndarray],
    f: int,
    rejection: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
    params: RecoveryParams = RecoveryParams(),  # noqa: B008 (frozen dataclass)
) -> tuple[Prior, float] | None:
    """The prior of track frame ``f`` and its contour's :func:`stray` from it, when the
    frame is to be searched again (:func:`recheck_frame`): ``params.recheck`` on, a
    track frame on each side within ``max_skip + 1`` frames, and a stray of at least
    ``params.min_stray``. None otherwise."""
    if not params.recheck or choice.chosen[f] < 0:
        return None
    prior = track_prior(frames, choice, poses, f, rejection.max_skip + 1, True)
    if prior is None:
        return None
    fc = frames[f]
    own = stray(fc.candidates[int(choice.chosen[f])], fc.spacing, prior, rejection)
    if not own >= params.min_stray:
        return None
    return prior, own


def recheck_frame(
    frames: Sequence[FrameCandidates],
    choice: TrackChoice,
    poses: np.ndarray | Sequence[np.ndarray],
    f: int,
    image_of: Callable[[int], np.ndarray],
    shadowpath: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
    rejection: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
    params: RecoveryParams = RecoveryParams(),  # noqa: B008 (frozen dataclass)
    evidence_of: Callable[[int], EvidenceMaps | None] | None = None,
) -> BoneCandidate | None:
    """The contour that replaces track frame ``f``'s, or None (kept as it is).

    A track frame whose contour strays from its neighbours' interpolation
    (:func:`recheck_prior`) is searched as a frame off the track is
    (:func:`guided_candidate`, both sides guiding). The guided contour replaces the
    frame's when it agrees with the neighbours (its :func:`stray` at most
    ``params.max_stray_ratio`` of the frame's own) and is at least as wide as the
    frame's contour (its evidence above the null level over at least as many mm).
    """
    got = recheck_prior(frames, choice, poses, f, rejection, params)
    if got is None:
        return None
    fc = frames[f]
    own = fc.candidates[int(choice.chosen[f])]
    return recheck_candidate(
        image_of(f),
        fc.spacing,
        own,
        *got,
        shadowpath,
        rejection,
        params,
        evidence_of(f) if evidence_of is not None else None,
    )


def recheck_candidate(
    image: np.ndarray,
    spacing: tuple[float, float],
    own: BoneCandidate,
    prior: Prior,
    own_stray: float,
    shadowpath: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
    rejection: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
    params: RecoveryParams = RecoveryParams(),  # noqa: B008 (frozen dataclass)
    evidence: EvidenceMaps | None = None,
) -> BoneCandidate | None:
    """:func:`recheck_frame`'s search and verdict, given the frame's pixels, its track
    contour ``own``, and the prior and stray :func:`recheck_prior` found (a live session
    calls it with the pixels it kept)."""
    g = guided_candidate(
        image,
        spacing,
        prior,
        shadowpath,
        rejection,
        params.min_share,
        params.max_offset,
        evidence,
    )
    if g is None:
        return None
    if not stray(g, spacing, prior, rejection) <= params.max_stray_ratio * own_stray:
        return None
    if np.ptp(g.points_px[:, 0]) < np.ptp(own.points_px[:, 0]):
        return None
    return g


def recheck_track(
    frames: Sequence[FrameCandidates],
    choice: TrackChoice,
    poses: np.ndarray,
    image_of: Callable[[int], np.ndarray],
    shadowpath: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
    rejection: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
    params: RecoveryParams = RecoveryParams(),  # noqa: B008 (frozen dataclass)
    evidence_of: Callable[[int], EvidenceMaps | None] | None = None,
) -> tuple[list[FrameCandidates], TrackChoice, list[int]]:
    """The track with the contours of its straying frames replaced (:func:`recheck_frame`).

    Every frame is judged against the track as given (a replacement does not move
    its neighbours' priors). Returns the frames (a replaced frame's guided contour
    appended, :func:`with_candidate`), the choice naming it, and the frames replaced.
    """
    if not params.recheck:
        return list(frames), choice, []
    poses = np.asarray(poses, dtype=float)
    found: dict[int, BoneCandidate] = {}
    for f in np.flatnonzero(np.asarray(choice.chosen) >= 0).tolist():
        cand = recheck_frame(
            frames, choice, poses, f, image_of, shadowpath, rejection, params, evidence_of
        )
        if cand is not None:
            found[f] = cand
    out, choice = with_chosen(frames, choice, found)
    return out, choice, list(found)


def with_candidate(fc: FrameCandidates, cand: BoneCandidate) -> FrameCandidates:
    """``fc`` with a guided candidate appended (the last candidate; the frame then has one)."""
    return replace(fc, candidates=(*fc.candidates, cand), reason="")


def with_chosen(
    frames: Sequence[FrameCandidates], choice: TrackChoice, cands: dict[int, BoneCandidate]
) -> tuple[list[FrameCandidates], TrackChoice]:
    """``frames`` with each of ``cands`` (by frame) appended (:func:`with_candidate`), and
    ``choice`` with it chosen in its frame: a track frame's contour replaced (rechecked
    here, cut by :mod:`.reach`)."""
    out = list(frames)
    if not cands:
        return out, choice
    chosen = np.array(choice.chosen, copy=True)
    for n, cand in cands.items():
        out[n] = with_candidate(out[n], cand)
        chosen[n] = len(out[n].candidates) - 1
    return out, replace(choice, chosen=chosen)

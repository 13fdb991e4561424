"""Sweep-level step: a track contour's level run, or climb onto another top, past its
neighbours' reach cut off.

The per-frame step may carry a contour from the bone's top on along a layer that leaves
it at its level: a fascia running off the crest (issue 10's cadaver: "bright fascia runs
off the crest at the bone's level"), or a fascia over the valley onto the bone beside.
Where the layer leaves the bone near its apex, before the bone has turned down, no
turn of the contour marks where the bone ends (:func:`.candidates.convex_part` cuts at
a flank that turns flat), and the contour links to its neighbours over the bone's
part: the track keeps it whole, and the layer's points lie 1-10 mm off the bone (hard
ulna at 475 x 405, seed 197, frame 21: 10.6 mm of fascia past the bone's shoulder, the
contour 3.6 mm off the bone on median; hard radius with the ulna 18 mm beside, seed
173, frame 13: 17.8 mm of fascia and ulna, 7.1 mm).

The frames on either side say how far the bone reaches: a bone's width changes little
between neighbouring frames (the sweep moves along it). :func:`trim_beyond` takes, for
each track frame with a track frame on each side (within ``max_skip + 1`` frames), the
lateral reach of those two contours in its plane (the outermost either reaches, whole
contours) and looks at the frame's points more than ``beyond_margin_mm`` past it. Past
its widest point a bone's outline only descends, so a run there that does not (its
depths, to their 80th percentile, within ``beyond_level_mm`` of the contour's depth at
the reach's edge) and that runs on for at least ``beyond_min_mm`` is no bone: it is cut
off. A flank that one frame follows further down than its neighbours descends, and is
kept; so is a short run past the reach (a neighbour's end a little short).

A run past the reach that descends may still have left the bone: over the valley onto
the bone beside, whose top lies past the reach, and down that bone's far flank (the rim
follows it). Outward from the frame's shallowest point inside the reach, a bone's
outline never climbs back up; where the contour climbs at least ``beyond_climb_mm``
over the deepest point inward of it, onto a top at least ``beyond_min_mm`` across of
which some lies past the margin, it is cut from that valley's bottom on (hard radius with the ulna 14 mm beside, their tops touching, seed 173, frame
28: the path ran from the ulna's top over the valley and along a fascia onto the radius,
42 % of its points on the ulna, 11 mm past the frames on either side). The per-frame
splits miss it on their own evidence: :func:`.candidates._valley_runs` asks one side of
the valley for less than a third of the other's shadow (0.14 against 0.36) or both sides
to be domes (the path began at the ulna's top: no dome); :func:`.candidates.
_cut_climbing_ends` asks for a flank followed down without a jump (the path stepped
from the fascia into the valley). The track's lane rules (:func:`.track._in_lane`) rule
whole contours in or out, and the contour lay over the radius's lane. A narrower climb
is a contour hopping for a few columns onto a layer just over a flank, on the bone
before and after it (hard tibia, seed 173, frame 24: 0.4 mm across, 1.6 mm over the
flank, its neighbours' contours short of the flank): left to the level rule.

Why it generalises: the poses, the contours' own extents and depths in mm; no grey
level. Applied offline and live alike, after the track's rechecked contours
(:mod:`.recovery`), before the contours are made.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate, FrameCandidates
from BoneUSRecon.Logic.segmentation.params import RejectionParams
from BoneUSRecon.Logic.segmentation.recovery import prior_frames
from BoneUSRecon.Logic.segmentation.track import TrackChoice, _project
from BoneUSRecon.Logic.sweep import frame_planes, pixels_to_reference

__all__ = ["beyond_reach", "trim_beyond"]


def beyond_reach(
    cand: BoneCandidate,
    spacing: tuple[float, float],
    reach: tuple[float, float],
    params: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
) -> np.ndarray | None:
    """The mask of ``cand``'s points kept when its level runs past ``reach`` (lateral mm,
    the neighbours' outermost extent in the frame's plane), or its runs from a valley
    up onto another top past it, are cut off; None when nothing is cut. See the module
    docstring."""
    pts = cand.points_px
    if pts.shape[0] < 3:
        return None
    x = pts[:, 0] * float(spacing[0])
    z = pts[:, 1] * float(spacing[1])
    keep = np.ones(x.size, bool)
    m = params.beyond_margin_mm
    within = np.flatnonzero((x >= reach[0]) & (x <= reach[1]))
    # The frame's top where its neighbours see the bone: the climb's valley is sought
    # outward from it.
    top = int(within[np.argmin(z[within])]) if within.size else -1
    for side, edge in ((-1, reach[0] - m), (1, reach[1] + m)):
        past = x < edge if side < 0 else x > edge
        inner = np.flatnonzero(~past)
        if not past.any() or inner.size == 0:
            continue
        if np.abs(x[past] - edge).max() < params.beyond_min_mm:
            continue  # a short run past the reach: a neighbour's end a little short
        at = inner[0] if side < 0 else inner[-1]  # the contour at the reach's edge
        if np.percentile(z[past], 80.0) <= z[at] + params.beyond_level_mm:
            keep &= ~past
        if top >= 0 and params.beyond_climb_mm > 0:
            keep &= ~_onto_another_top(
                x, z, top, side, past, params.beyond_climb_mm, params.beyond_min_mm
            )
    if keep.all():
        return None
    # The path's own points (not only a rim trace) must remain: the sweep-level steps
    # compare those (:attr:`.candidates.BoneCandidate.core_px`).
    a, b = cand.rim_ends
    return keep if keep[a : keep.size - b].any() else None


def _onto_another_top(
    x: np.ndarray, z: np.ndarray, top: int, side: int, past: np.ndarray, climb: float, wide: float
) -> np.ndarray:
    """The mask of the points, on ``side`` (-1 left, 1 right) of the contour's point
    ``top``, from the bottom of a valley outward, the bottom kept, where the contour
    climbs out of it onto another top past the neighbours' reach (``past``): a run of
    points at least ``climb`` mm over the deepest point inward of them, at least
    ``wide`` mm across, that lies past the reach; all False when there is none. ``x``,
    ``z``: lateral and depth, mm."""
    out = np.zeros(x.size, bool)
    seq = np.arange(top, -1, -1) if side < 0 else np.arange(top, x.size)
    zs, xs = z[seq], x[seq]
    risen = np.maximum.accumulate(zs) - zs  # height over the deepest point inward of it
    up = np.flatnonzero(risen >= climb)
    for run in np.split(up, np.flatnonzero(np.diff(up) > 1) + 1) if up.size else []:
        # A hop of a few columns onto a layer just over the bone is no top (a contour
        # switching between the two lines on a flank: hard tibia s173, frame 24).
        if past[seq[run]].any() and abs(xs[run[-1]] - xs[run[0]]) >= wide:
            valley = int(np.argmax(zs[: run[0] + 1]))  # the deepest point before the climb
            out[seq[valley + 1 :]] = True
            break
    return out


def trim_beyond(
    frames: Sequence[FrameCandidates],
    choice: TrackChoice,
    poses: np.ndarray | Sequence[np.ndarray],
    params: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
) -> dict[int, BoneCandidate]:
    """The track frames whose chosen contour is cut (:func:`beyond_reach`), with the cut
    contour: ``{frame index: candidate}`` (the others as they are; empty with
    ``params.trim_beyond`` off).

    Every frame is judged against the track as given (a cut does not move its
    neighbours' reach).
    """
    out: dict[int, BoneCandidate] = {}
    if not params.trim_beyond:
        return out
    chosen = np.asarray(choice.chosen)
    reach_frames = params.max_skip + 1
    for f in np.flatnonzero(chosen >= 0).tolist():
        near = prior_frames(chosen, f, reach_frames, True)
        if near is None:
            continue
        origin, axes, normal = frame_planes(np.asarray(poses[f], dtype=float)[None])
        lo, hi = np.inf, -np.inf
        for g in near:
            cand = frames[g].candidates[int(chosen[g])]
            ref = pixels_to_reference(poses[g], cand.points_px)
            lat = _project(ref, origin[0], axes[0], normal[0])[:, 0]
            lo, hi = min(lo, float(lat.min())), max(hi, float(lat.max()))
        own = frames[f].candidates[int(chosen[f])]
        keep = beyond_reach(own, frames[f].spacing, (lo, hi), params)
        if keep is not None:
            idx = np.flatnonzero(keep)  # a contiguous run: the cuts are at the ends
            out[f] = own.kept_run(int(idx[0]), int(idx[-1]) + 1)
    return out

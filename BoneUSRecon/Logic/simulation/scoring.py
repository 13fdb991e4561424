"""Frame-level scores of a bone segmentation against the truth (issue 10, item 7).

Pooled point distances hide what a user sees: a sweep where half the frames found
nothing and a few sat on a fascia can still have a small median. So, per frame:

* the **median distance** (mm) of its kept points to the true bone surface;
* **frame recall**: the share of frames showing bone whose kept points lie on the true
  surface (median < ``on_bone_mm``, 1 mm);
* **wrong-structure share**: the share of frames kept with a median > ``wrong_mm``
  (3 mm) from the bone, or kept where no bone is shown (a fascia, the skin, a
  reverberation);
* **point accuracy**: median, 95th percentile and share > 2 mm of all kept points;
* **flank coverage**: the share of the true visible contour (one point per image
  column: a share of its width) with a kept point within ``cover_mm`` (1 mm), and the
  steepest in-plane slope of the true contour where a kept point lies on it, beside
  the steepest slope the true contour has.

The truth is either a simulation (:func:`score_simulation`: exact distance to the
analytic surface, true visible contour per frame) or reference contours drawn on a
real recording (:func:`score_reference`: distance to the reference polyline of the
frame, in mm). Pure numpy on the contours' reference-mm points.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

if TYPE_CHECKING:
    from BoneUSRecon.Logic.segmentation.result import SegmentationResult
    from BoneUSRecon.Logic.simulation.core import Simulation
    from BoneUSRecon.Logic.sweep import Sweep

__all__ = [
    "FrameScore",
    "SweepScore",
    "contour_slopes_deg",
    "densify_px",
    "polyline_distance",
    "read_reference_csv",
    "score_frames",
    "score_reference",
    "score_simulation",
]

#: A frame's kept points "lie on the bone" when their median distance is below this (mm).
ON_BONE_MM = 1.0
#: A kept frame is on a wrong structure when its median distance exceeds this (mm).
WRONG_MM = 3.0
#: A true contour point is covered when a kept point lies within this (mm).
COVER_MM = 1.0


@dataclass(frozen=True)
class FrameScore:
    """The score of one frame."""

    #: Frame index in the sweep.
    frame: int
    #: The truth shows bone in this frame (a non-empty true visible contour).
    shows_bone: bool
    #: The segmentation kept (accepted) a contour with points in this frame.
    kept: bool
    #: Median distance (mm) of the kept points to the truth; NaN when not kept.
    median_mm: float
    #: Share of the true visible contour with a kept point within ``cover_mm``; 0 when
    #: not kept, NaN when no bone is shown.
    coverage: float
    #: Steepest slope (degrees) of the true contour where a kept point lies within
    #: ``cover_mm`` of it; NaN when none.
    steepest_deg: float
    #: Steepest slope (degrees) of the true visible contour; NaN when no bone is shown.
    true_steepest_deg: float

    @property
    def on_bone(self) -> bool:
        """Kept, shows bone, and its median distance is below 1 mm."""
        return self.kept and self.shows_bone and self.median_mm < ON_BONE_MM

    @property
    def wrong(self) -> bool:
        """Kept on something else: median > 3 mm, or no bone shown."""
        return self.kept and (not self.shows_bone or self.median_mm > WRONG_MM)


@dataclass(frozen=True, eq=False)
class SweepScore:
    """Frame-level and point-level scores of one segmented sweep."""

    #: One score per scored frame (the sweep's valid frames), in frame order.
    frames: tuple[FrameScore, ...]
    #: Distances (mm) of all kept points to the truth, pooled.
    distances: np.ndarray

    @property
    def frames_with_bone(self) -> int:
        """Number of frames whose truth shows bone."""
        return sum(f.shows_bone for f in self.frames)

    @property
    def recall(self) -> float:
        """Share of the frames showing bone whose kept points lie on it (median < 1 mm)."""
        n = self.frames_with_bone
        return sum(f.on_bone for f in self.frames) / n if n else float("nan")

    @property
    def wrong_share(self) -> float:
        """Share of the scored frames kept on a wrong structure (median > 3 mm or no bone)."""
        return sum(f.wrong for f in self.frames) / len(self.frames) if self.frames else float("nan")

    @property
    def kept(self) -> int:
        """Number of frames with a kept contour."""
        return sum(f.kept for f in self.frames)

    def summary(self) -> dict[str, Any]:
        """Figures for a benchmark line or JSON (NaN where undefined)."""
        d = self.distances
        on = [f for f in self.frames if f.shows_bone]
        cov = np.array([f.coverage for f in on], float)
        steep = np.array([f.steepest_deg for f in on if f.on_bone], float)
        true_steep = np.array([f.true_steepest_deg for f in on], float)
        nan = float("nan")
        return {
            "frames": len(self.frames),
            "frames_with_bone": self.frames_with_bone,
            "kept": self.kept,
            "recall": self.recall,
            "wrong_share": self.wrong_share,
            "median_mm": float(np.median(d)) if d.size else nan,
            "p95_mm": float(np.percentile(d, 95)) if d.size else nan,
            "over_2mm": float(np.mean(d > 2.0)) if d.size else nan,
            "coverage": float(np.mean(cov)) if cov.size else nan,
            "steepest_deg": float(np.nanmedian(steep)) if np.isfinite(steep).any() else nan,
            "true_steepest_deg": float(np.nanmedian(true_steep))
            if np.isfinite(true_steep).any()
            else nan,
        }


def contour_slopes_deg(points_mm: np.ndarray) -> np.ndarray:
    """In-plane slope (degrees from the image's lateral axis) at each point of a contour.

    ``points_mm`` (K, 2) are ``(lateral, depth)`` in mm along the contour; the slope of
    point k is that of the chord between its neighbours (one-sided at the ends).
    """
    p = np.asarray(points_mm, float)
    if p.shape[0] < 2:
        return np.full(p.shape[0], np.nan)
    d = np.gradient(p, axis=0)
    return np.degrees(np.arctan2(np.abs(d[:, 1]), np.abs(d[:, 0])))


def polyline_distance(points: np.ndarray, polyline: np.ndarray) -> np.ndarray:
    """Distance from each point (K, D) to a polyline (M, D) (its segments; a point if M = 1)."""
    q = np.asarray(points, float)
    a = np.asarray(polyline, float)
    if a.shape[0] == 0:
        return np.full(q.shape[0], np.inf)
    if a.shape[0] == 1:
        return np.linalg.norm(q - a[0], axis=1)
    s0, s1 = a[:-1], a[1:]
    seg = s1 - s0
    L2 = np.maximum(np.einsum("md,md->m", seg, seg), 1e-30)
    t = np.clip(np.einsum("kmd,md->km", q[:, None, :] - s0[None], seg) / L2, 0.0, 1.0)
    foot = s0[None] + t[..., None] * seg[None]
    return np.sqrt(np.min(np.einsum("kmd,kmd->km", q[:, None] - foot, q[:, None] - foot), axis=1))


def densify_px(contour_px: np.ndarray) -> np.ndarray:
    """A contour ``(M, 2)`` pixels ordered by ``i``, resampled to one point per column.

    Reference contours are stored as sparser polylines; coverage is a share of width,
    counted on one point per column as for the simulator's true contours.
    """
    c = np.asarray(contour_px, float).reshape(-1, 2)
    if c.shape[0] < 2:
        return c
    i = np.arange(np.ceil(c[0, 0]), np.floor(c[-1, 0]) + 1)
    return np.column_stack([i, np.interp(i, c[:, 0], c[:, 1])]) if i.size >= 2 else c


def score_frames(
    kept: Mapping[int, np.ndarray],
    truth: Mapping[int, np.ndarray],
    frames: list[int],
    distance: Callable[[int, np.ndarray], np.ndarray],
    slopes: Mapping[int, np.ndarray],
    *,
    cover_mm: float = COVER_MM,
) -> SweepScore:
    """Score kept contours frame by frame.

    Parameters
    ----------
    kept : mapping frame -> (K, 3)
        Kept (accepted) points per frame, reference mm; frames absent or empty: not kept.
    truth : mapping frame -> (M, 3)
        The true visible contour per frame, reference mm, one point per image column;
        absent or empty: the frame shows no bone.
    frames : list of int
        The frames to score (the sweep's valid frames).
    distance : callable ``(frame, points (K, 3)) -> (K,)``
        Distance (mm) of points of a frame to the truth (the true surface, or the
        frame's reference polyline).
    slopes : mapping frame -> (M,)
        In-plane slope (degrees) of the true contour at each of its points.
    cover_mm : float
        A true point is covered when a kept point lies within this distance.

    Returns
    -------
    SweepScore
    """
    out, pooled = [], []
    for k in frames:
        t = np.asarray(truth.get(k, np.empty((0, 3))), float).reshape(-1, 3)
        p = np.asarray(kept.get(k, np.empty((0, 3))), float).reshape(-1, 3)
        shows, has = t.shape[0] > 0, p.shape[0] > 0
        med, cov, steep = float("nan"), (0.0 if shows else float("nan")), float("nan")
        sl = np.asarray(slopes.get(k, np.full(t.shape[0], np.nan)), float)
        if has:
            d = np.asarray(distance(k, p), float)
            pooled.append(d)
            med = float(np.median(d))
            if shows:
                near = np.sqrt(((t[:, None, :] - p[None, :, :]) ** 2).sum(-1)).min(1) <= cover_mm
                cov = float(np.mean(near))
                if near.any() and np.isfinite(sl[near]).any():
                    steep = float(np.nanmax(sl[near]))
        out.append(
            FrameScore(
                frame=int(k),
                shows_bone=shows,
                kept=has,
                median_mm=med,
                coverage=cov,
                steepest_deg=steep,
                true_steepest_deg=float(np.nanmax(sl))
                if shows and np.isfinite(sl).any()
                else float("nan"),
            )
        )
    return SweepScore(
        frames=tuple(out), distances=np.concatenate(pooled) if pooled else np.empty(0)
    )


def _kept_mm(result: SegmentationResult, sweep: Sweep) -> dict[int, np.ndarray]:
    return {c.frame: c.points_mm(sweep) for c in result.accepted if c.points_px.shape[0]}


def _slopes(sweep: Sweep, contours_px: Mapping[int, np.ndarray]) -> dict[int, np.ndarray]:
    sx, sy = (float(v) for v in sweep.spacing_mm)
    return {k: contour_slopes_deg(np.asarray(c, float) * [sx, sy]) for k, c in contours_px.items()}


def score_simulation(
    result: SegmentationResult,
    sim: Simulation,
    *,
    cover_mm: float = COVER_MM,
    beyond_mm: float = 1.5,
) -> SweepScore:
    """Score a segmentation of a simulated sweep against its exact truth.

    Distances are to the analytic bone surface (exact), for points within ``beyond_mm``
    of the frame's true visible contour (``sim.true_contours_px``: a flank followed a
    little further than the visible limit still counts at its true distance); farther
    from it, the distance to that contour: the far cortex, deep in the shadow, lies on
    the bone's surface too but is not the imaged surface. Every valid frame is scored.
    """
    sw = sim.sweep
    frames = [k for k in range(sw.n_frames) if sw.valid[k]]
    px = {k: sim.true_contours_px[k] for k in frames if len(sim.true_contours_px[k])}
    truth = {k: sw.to_reference(k, c) for k, c in px.items()}

    def dist(k: int, p: np.ndarray) -> np.ndarray:
        d = sim.distance_to_truth(p)
        if k not in truth:
            return d
        dc = polyline_distance(p, truth[k])
        return np.where(dc <= beyond_mm, d, dc)

    return score_frames(
        _kept_mm(result, sw), truth, frames, dist, _slopes(sw, px), cover_mm=cover_mm
    )


def read_reference_csv(path: str | os.PathLike[str]) -> dict[int, np.ndarray]:
    """Reference contours from a CSV of ``frame,i,j`` rows (header first), per frame
    ``(M, 2)`` pixels ordered by ``i`` (the format of ``Testing/data/*_reference.csv``)."""
    a = np.loadtxt(path, delimiter=",", skiprows=1, ndmin=2)
    out: dict[int, np.ndarray] = {}
    for k in np.unique(a[:, 0]).astype(int):
        c = a[a[:, 0] == k, 1:3]
        out[int(k)] = c[np.argsort(c[:, 0], kind="stable")]
    return out


def score_reference(
    result: SegmentationResult,
    sweep: Sweep,
    reference_px: Mapping[int, np.ndarray],
    *,
    cover_mm: float = COVER_MM,
    beyond_mm: float = 1.0,
) -> SweepScore:
    """Score a segmentation of a recording against reference contours drawn on it.

    ``reference_px`` maps a frame to its reference bone contour ``(M, 2)`` pixels
    ``(i, j)`` ordered by ``i`` (see ``Testing/data/README.md``); an empty contour means
    the frame shows no bone; frames absent from it are not scored (no reference could
    be drawn). Distances are to the frame's reference polyline in reference mm, so
    they carry the reference's own error (a few tenths of a mm). Kept points more than
    ``beyond_mm`` beyond the reference's ends (a flank the reference stops short of)
    are not measured; a frame whose kept points all lie beyond them counts as kept on
    something else.
    """
    sx = float(sweep.spacing_mm[0])
    frames = [k for k in range(sweep.n_frames) if sweep.valid[k] and k in reference_px]
    px = {k: densify_px(c) for k, c in reference_px.items() if len(c)}
    truth = {k: sweep.to_reference(k, c) for k, c in px.items()}
    kept: dict[int, np.ndarray] = {}
    for c in result.accepted:
        if c.frame not in reference_px or not c.points_px.shape[0]:
            continue
        p = np.asarray(c.points_px, float)
        if c.frame in px:
            ref = px[c.frame]
            inside = (p[:, 0] >= ref[0, 0] - beyond_mm / sx) & (
                p[:, 0] <= ref[-1, 0] + beyond_mm / sx
            )
            # All beyond the ends: one point far off stands for the frame (wrong structure).
            p = p[inside] if inside.any() else p[:1]
        kept[c.frame] = sweep.to_reference(c.frame, p)

    def dist(k: int, p: np.ndarray) -> np.ndarray:
        if k not in truth:
            return np.full(len(p), np.inf)
        d = polyline_distance(p, truth[k])
        ref = px[k]
        ij = np.linalg.solve(
            sweep.image_to_reference[k][:3, :3], (p - sweep.image_to_reference[k][:3, 3]).T
        ).T
        out = (ij[:, 0] < ref[0, 0] - beyond_mm / sx) | (ij[:, 0] > ref[-1, 0] + beyond_mm / sx)
        return np.where(out, np.inf, d)

    return score_frames(kept, truth, frames, dist, _slopes(sweep, px), cover_mm=cover_mm)

"""Per-frame contours and the sweep's segmentation result."""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, NamedTuple

import numpy as np

from BoneUSRecon.Logic.segmentation.params import SegmentationParams
from BoneUSRecon.Logic.sweep import Sweep

__all__ = ["FrameContour", "SegmentationPoints", "SegmentationResult"]


class SegmentationPoints(NamedTuple):
    """Every kept point of a sweep (:meth:`SegmentationResult.points_mm`), one row each.

    A named tuple: ``result.points_mm(sweep).xyz`` reads better than ``[0]``, and
    ``pts, frame, intensity, confidence = ...`` still unpacks.
    """

    xyz: np.ndarray
    """Positions in reference mm, (K, 3)."""
    frame: np.ndarray
    """Frame index of each point in the sweep, (K,) int64."""
    intensity: np.ndarray
    """Grey level of the image at each point, (K,)."""
    confidence: np.ndarray
    """Its frame's contour confidence, (K,)."""


@dataclass(frozen=True, eq=False)
class FrameContour:
    """The bone contour of one frame.

    Parameters
    ----------
    frame : int
        Index of the frame in the sweep (file order).
    points_px : ndarray, shape (K, 2)
        ``(i, j)`` = (column, row), sub-pixel, ordered by increasing ``i``. Kept even
        when the frame is rejected, so overlays can show what was refused.
    intensity : ndarray, shape (K,)
        Grey value (0..255) at each point.
    confidence : float
        In [0, 1]; see :mod:`BoneUSRecon.Logic.segmentation.track`.
    accepted : bool
        False when the frame was rejected; its points never reach the surface fit.
    reason : str
        Why it was rejected ("" when accepted): one category, no numbers.
    detail : str
        The value behind the reason (e.g. "4.2 mm from frame 17"), "" if none.
    """

    frame: int
    points_px: np.ndarray
    intensity: np.ndarray
    confidence: float
    accepted: bool
    reason: str = ""
    detail: str = ""
    extras: dict[str, Any] = field(default_factory=dict, repr=False)

    def points_mm(self, sweep: Sweep) -> np.ndarray:
        """The points in reference mm through the frame's ``ImageToReference``, (K, 3)."""
        return sweep.to_reference(self.frame, self.points_px)


@dataclass(frozen=True, eq=False)
class SegmentationResult:
    """The contours of a sweep, one per valid frame in file order."""

    contours: tuple[FrameContour, ...]
    method: str
    params: SegmentationParams
    timings: dict[str, float] = field(default_factory=dict)
    #: What the user should know of the result, one sentence each (e.g. a bone point
    #: the track does not reach, :func:`.bone_point.point_warnings`).
    warnings: tuple[str, ...] = ()

    @property
    def accepted(self) -> tuple[FrameContour, ...]:
        """The accepted contours, in frame order."""
        return tuple(c for c in self.contours if c.accepted)

    @property
    def rejected(self) -> dict[int, str]:
        """``{frame: reason}`` of the rejected frames."""
        return {c.frame: c.reason for c in self.contours if not c.accepted}

    @property
    def n_points(self) -> int:
        """Number of kept points (accepted frames only)."""
        return int(sum(c.points_px.shape[0] for c in self.accepted))

    def contours_mm(self, sweep: Sweep) -> list[tuple[int, np.ndarray]]:
        """``[(frame, points (K, 3) mm)]`` of the accepted frames, ordered along each contour."""
        return [(c.frame, c.points_mm(sweep)) for c in self.accepted]

    def points_mm(self, sweep: Sweep) -> SegmentationPoints:
        """All kept points of the accepted frames, with their frame, intensity and confidence."""
        acc = self.accepted
        if not acc:
            return SegmentationPoints(
                np.empty((0, 3)), np.empty(0, np.int64), np.empty(0), np.empty(0)
            )
        pts = np.concatenate([c.points_mm(sweep) for c in acc])
        frame = np.concatenate([np.full(c.points_px.shape[0], c.frame, np.int64) for c in acc])
        inten = np.concatenate([c.intensity for c in acc])
        conf = np.concatenate([np.full(c.points_px.shape[0], c.confidence) for c in acc])
        return SegmentationPoints(pts, frame, inten, conf)

    def summary(self) -> dict[str, Any]:
        """Counts and rejection reasons, for the CLI and the report."""
        from BoneUSRecon.Logic.reasons import count_reasons

        # Counted by kind, numbers stripped, in the one place every summary uses.
        reasons = count_reasons(self.rejected)
        return {
            "method": self.method,
            "frames": len(self.contours),
            "accepted": len(self.accepted),
            # Accepted frames whose contour the track-guided search found (.recovery).
            "recovered": sum(bool(c.extras.get("recovered")) for c in self.accepted),
            "rejected": len(self.contours) - len(self.accepted),
            "points": self.n_points,
            "rejection_reasons": reasons,
            "mean_confidence": float(np.mean([c.confidence for c in self.accepted]))
            if self.accepted
            else 0.0,
            "warnings": list(self.warnings),
        }

"""Per-frame confidence and rejection of implausible contours.

Checks, the same for every segmenter, measured on the frame itself (not on the
segmenter's internal score, so a segmenter cannot vouch for its own mistakes):

* ``no bone found``: the segmenter returned nothing.
* ``contour too short``: lateral extent below ``min_length_mm`` or too few points.
* ``low contrast``: the mean ``Dif`` (bright band against above and below) is weak.
* ``no acoustic shadow``: the region 1-5 mm under the contour is not much darker than
  the echo itself (a tissue layer or noise, not bone: the paper's false positives were
  "images with important noise on the acoustic shadow under the bone").
* ``jump``: the contour's depth differs from its neighbouring frames' (median over a
  window) by more than ``jump_mm``: bones are continuous and the probe moves smoothly.

The confidence in [0, 1] is the product of soft versions of these checks.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BoneUSRecon.Logic.segmentation.params import RejectionParams

__all__ = ["FrameEvidence", "frame_evidence", "frame_verdict", "neighbour_jumps"]


@dataclass(frozen=True)
class FrameEvidence:
    """Image evidence under a contour (grey values 0..255, lengths mm)."""

    length_mm: float
    n_points: int
    echo: float
    above: float
    shadow: float

    @property
    def contrast(self) -> float:
        """Mean ``Dif`` in grey/255 units (2 echo - above - shadow)."""
        return (2 * self.echo - self.above - self.shadow) / 255.0

    @property
    def shadow_ratio(self) -> float:
        """Shadow intensity relative to the echo's (0 = black shadow)."""
        return self.shadow / max(self.echo, 1.0)


def frame_evidence(
    image: np.ndarray, points_px: np.ndarray, spacing: tuple[float, float]
) -> FrameEvidence:
    """Measure echo, above and shadow intensities along a contour.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W)
    points_px : ndarray, shape (K, 2)
    spacing : (sx, sy)
    """
    sx, sy = float(spacing[0]), float(spacing[1])
    k = points_px.shape[0]
    if k == 0:
        return FrameEvidence(0.0, 0, 0.0, 0.0, 0.0)
    h, w = image.shape
    i = np.clip(np.rint(points_px[:, 0]).astype(np.intp), 0, w - 1)
    j = np.rint(points_px[:, 1]).astype(np.intp)

    def band(a_mm: float, b_mm: float) -> float:
        a = int(np.floor(a_mm / sy))
        b = max(a + 1, int(np.ceil(b_mm / sy)))
        rows = j[:, None] + np.arange(a, b)[None, :]
        inside = (rows >= 0) & (rows < h)
        if not inside.any():
            return float("nan")
        vals = image[np.clip(rows, 0, h - 1), i[:, None]].astype(np.float64)
        return float(vals[inside].mean())

    echo = band(-0.3, 0.3)
    above = band(-1.8, -0.4)
    shadow = band(1.0, 5.0)
    if not np.isfinite(shadow):  # contour at the very bottom: no room for a shadow
        shadow = echo
    if not np.isfinite(above):
        above = 0.0
    length = float(np.ptp(points_px[:, 0]) * sx) if k > 1 else 0.0
    return FrameEvidence(length, k, echo, above, shadow)


def frame_verdict(ev: FrameEvidence, params: RejectionParams) -> tuple[float, str]:
    """Confidence in [0, 1] and the rejection reason ("" when plausible)."""
    p = params
    if ev.n_points == 0:
        return 0.0, "no bone found"
    c_len = float(np.clip(ev.length_mm / (3 * p.min_length_mm), 0, 1))
    c_con = float(np.clip(ev.contrast / (3 * p.min_contrast), 0, 1))
    c_sh = float(np.clip(1 - ev.shadow_ratio / (1.5 * p.max_shadow_ratio), 0, 1))
    conf = (c_len * c_con * c_sh) ** (1 / 3)
    if ev.n_points < p.min_points or ev.length_mm < p.min_length_mm:
        return conf, f"contour too short ({ev.length_mm:.1f} mm)"
    if ev.contrast < p.min_contrast:
        return conf, f"low contrast (Dif {ev.contrast:.2f})"
    if ev.shadow_ratio > p.max_shadow_ratio:
        return conf, f"no acoustic shadow (shadow/echo {ev.shadow_ratio:.2f})"
    if conf < p.min_confidence:
        return conf, f"low confidence ({conf:.2f})"
    return conf, ""


def _depth_deviation(a: np.ndarray, b: np.ndarray, sy: float) -> float:
    """Median |depth difference| (mm) of contour ``a`` against ``b`` where they overlap."""
    lo, hi = b[0, 0], b[-1, 0]
    m = (a[:, 0] >= lo) & (a[:, 0] <= hi)
    if m.sum() < 2:
        return float("nan")
    return float(np.median(np.abs(a[m, 1] - np.interp(a[m, 0], b[:, 0], b[:, 1]))) * sy)


def neighbour_jumps(
    contours: dict[int, np.ndarray], order: list[int], sy: float, window: int
) -> dict[int, float]:
    """Per frame, the median depth deviation (mm) from its ``window`` accepted neighbours each side.

    ``order`` lists the accepted frames in acquisition order; frames with no
    overlapping neighbour get NaN.
    """
    out: dict[int, float] = {}
    for pos, f in enumerate(order):
        neigh = order[max(0, pos - window) : pos] + order[pos + 1 : pos + 1 + window]
        devs = [_depth_deviation(contours[f], contours[g], sy) for g in neigh]
        devs = [d for d in devs if np.isfinite(d)]
        out[f] = float(np.median(devs)) if len(devs) >= 2 else float("nan")
    return out

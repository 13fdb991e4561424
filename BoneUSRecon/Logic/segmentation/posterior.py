"""The paper's posterior choice of snake points (section II.B, end).

1. Keep points whose intensity exceeds ``I_mean + k_intensity * I_var`` (mean and
   variance over the snake's points, 8-bit grey values as in the paper).
2. Keep the longest connected run, two consecutive kept points being connected when
   closer than ``neighbour_px`` reference pixels (10 px = 1 mm, whatever the image's
   pixel size: the distance is measured in mm, so 0.05 and 0.15 mm/px images behave
   the same).

"Longest" is the largest number of points (the paper's snake has equally spaced
points laterally, so this is also the longest lateral extent).
"""

from __future__ import annotations

import numpy as np

from BoneUSRecon.Logic.segmentation.params import REFERENCE_PIXEL_MM, PosteriorParams

__all__ = ["posterior_choice"]


def posterior_choice(
    points_px: np.ndarray,
    intensity: np.ndarray,
    spacing: tuple[float, float],
    params: PosteriorParams = PosteriorParams(),  # noqa: B008 (frozen dataclass)
) -> np.ndarray:
    """Boolean mask of the snake points kept by the posterior choice.

    Parameters
    ----------
    points_px : ndarray, shape (n, 2)
        Snake points ``(i, j)`` in contour order.
    intensity : ndarray, shape (n,)
        Grey value (0..255) at each point.
    spacing : (sx, sy)
        mm per column and per row.

    Examples
    --------
    >>> pts = np.column_stack([np.arange(6.0) * 6, np.zeros(6)])
    >>> posterior_choice(pts, np.array([0, 200, 210, 205, 0, 220.0]), (0.1, 0.1)).tolist()
    [False, True, True, True, False, False]
    """
    pts = np.asarray(points_px, dtype=float)
    val = np.asarray(intensity, dtype=float)
    keep = np.zeros(val.shape, bool)
    if val.size == 0:
        return keep
    thr = val.mean() + params.k_intensity * val.var()
    cand = np.flatnonzero(val > thr)
    if cand.size == 0:
        return keep
    mm = pts[cand] * np.asarray(spacing, dtype=float)
    gap = np.linalg.norm(np.diff(mm, axis=0), axis=1)
    link = gap < params.neighbour_px * REFERENCE_PIXEL_MM
    # Runs of linked candidates: a new run starts after every broken link.
    run_id = np.r_[0, np.cumsum(~link)]
    counts = np.bincount(run_id)
    best = int(np.argmax(counts))
    keep[cand[run_id == best]] = True
    return keep

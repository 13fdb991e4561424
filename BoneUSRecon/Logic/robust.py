"""Robust statistics shared by the axis fit (resampling) and the surface fit (bspline).

M-estimator weights and the MAD scale that sets them: the paper fits by plain least
squares; these keep a few wrong frames or points from pulling the fit (Huber for the
first, convex iterations, then Tukey's biweight, which gives gross outliers weight 0).
"""

from __future__ import annotations

import numpy as np

__all__ = ["robust_weights", "mad_scale", "row_medians"]


def robust_weights(r: np.ndarray, scale: float, kind: str) -> np.ndarray:
    """Huber or Tukey biweight weights of residuals ``r`` at ``scale``.

    Parameters
    ----------
    r : ndarray
        Residuals (mm); their absolute values are used.
    scale : float
        Residual scale (mm), e.g. :func:`mad_scale`.
    kind : {"huber", "tukey"}
        Tuning constants give 95% efficiency on Gaussian residuals (Huber 1.345,
        Tukey 4.685 times ``scale``).

    Returns
    -------
    ndarray
        Weights in [0, 1], shaped like ``r``.
    """
    r = np.abs(np.asarray(r, dtype=float))
    if kind == "huber":
        k = 1.345 * scale
        return np.where(r <= k, 1.0, k / np.maximum(r, 1e-300))
    if kind == "tukey":
        c = 4.685 * scale
        return np.where(r < c, (1.0 - (r / c) ** 2) ** 2, 0.0)
    raise ValueError(f"unknown robust weight {kind!r}")


def mad_scale(r: np.ndarray, floor: float = 0.0, *, empty: float | None = None) -> float:
    """Robust residual scale: 1.4826 x the median absolute finite residual.

    Parameters
    ----------
    r : ndarray
        Residuals (mm); non-finite entries are ignored.
    floor : float
        Smallest scale returned (mm): below it residuals count as exact.
    empty : float, optional
        Scale when ``r`` has no finite entry (default ``floor``).

    Returns
    -------
    float
    """
    r = np.abs(np.asarray(r, dtype=float))
    r = r[np.isfinite(r)]
    if r.size == 0:
        return floor if empty is None else empty
    return max(float(1.4826 * np.median(r)), floor)


def row_medians(a: np.ndarray) -> np.ndarray:
    """Median of the finite entries of each row of a 2-D array (0 for empty rows).

    Sorts with NaN last and picks the middle of the finite count: without
    ``np.nanmedian``'s per-row overhead (and its warning on empty rows).
    """
    cnt = np.isfinite(a).sum(axis=1)
    srt = np.sort(np.where(np.isfinite(a), a, np.inf), axis=1)
    lo = np.clip((cnt - 1) // 2, 0, a.shape[1] - 1)
    hi = np.clip(cnt // 2, 0, a.shape[1] - 1)
    rows = np.arange(a.shape[0])
    med = 0.5 * (srt[rows, lo] + srt[rows, hi])
    return np.where(cnt > 0, med, 0.0)

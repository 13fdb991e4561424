"""Image features shared by the segmenters: the paper's regional contrast ``Dif``.

``Dif(j) = 2 M_mid - M_up - M_down`` (paper eq. 3) where the three means are taken,
in each column, over the band centred on row ``j``, the region right above it and the
shadow region right below it (paper Fig. 1). Column means over sliding windows are
differences of one cumulative sum, so the whole map costs a few passes over the
image whatever the region sizes.
"""

from __future__ import annotations

import numpy as np

__all__ = [
    "median1d",
    "column_window_mean",
    "column_cumsum",
    "row_minimum_filter",
    "region_means",
    "dif_map",
    "block_mean",
    "mm_to_px",
    "band_means",
    "sorted_row_percentiles",
    "sorted_row_medians",
    "sorted_percentile",
]


#: From this many values on, :func:`median1d` of an even count partitions once and takes
#: a maximum (faster than a two-kth partition above about a thousand values; below, the
#: extra calls cost more).
_ONE_KTH_FROM = 1024


def median1d(values: np.ndarray) -> float:
    """``float(np.median(values))`` of a small finite 1-D array, by one partition.

    ``np.median`` costs ~30 us of checks per call on the few tens of values of a
    contour, called hundreds of times per frame; same value (the two middle values
    averaged in the array's own dtype, as ``np.mean`` does).
    """
    a = np.asarray(values).ravel()
    n = a.size
    if n == 0:
        return float("nan")
    k = n // 2
    # A copy partitioned in place: what ``np.partition`` does, without its wrapper (this
    # is called ~75 times per frame).
    part = a.copy()
    if n % 2:
        part.partition(k)
        return float(part[k])
    if n >= _ONE_KTH_FROM:
        # Partitioning at two kth costs ~6x one on thousands of values (numpy selects
        # twice over the whole array); after one partition at k, the (k-1)-th order
        # statistic is the largest of the k values before it: the same element.
        part.partition(k)
        return float((part[:k].max() + part[k]) / 2)
    part.partition((k - 1, k))
    return float((part[k - 1] + part[k]) / 2)


def mm_to_px(mm: float, spacing: float, minimum: int = 1) -> int:
    """``mm`` as a whole number of pixels of size ``spacing`` (at least ``minimum``)."""
    return max(minimum, int(round(mm / spacing)))


def ceil_px(ratio: float) -> int:
    """``ceil(ratio)`` of a length over a pixel size, immune to the last bit of rounding.

    A pixel size read from poses or headers carries float noise (0.30000000000000004 mm
    beside 0.3 in 10-30 % of a simulated sweep's frames): a plain ceil of 0.9 mm over it
    gives 3 in some frames and 4 in others, and the frames of one sweep were read with
    different path slopes (branch tshoulder, session 28).
    """
    return int(np.ceil(ratio - 1e-9))


def column_cumsum(image: np.ndarray) -> np.ndarray:
    """``csum`` with ``csum[k] = image[:k].sum(0)`` (a leading row of 0), in ``image``'s dtype.

    ``np.cumsum(image, axis=0)``'s values (each column summed in order, row by row),
    added a row at a time: numpy accumulates along a first axis column by column, with
    a strided inner loop (~1.4x the time at a working image's 240 x 320).
    """
    csum = np.empty((image.shape[0] + 1,) + image.shape[1:], image.dtype)
    csum[0] = 0
    add = np.add
    for k in range(image.shape[0]):
        add(csum[k], image[k], out=csum[k + 1])
    return csum


def row_minimum_filter(values: np.ndarray, size: int) -> np.ndarray:
    """``scipy.ndimage.minimum_filter1d(values, size, axis=1, mode="nearest")`` of a 2-D
    array, for an odd ``size``: the same values, in ``values``' dtype.

    Minima over runs of 1, 2, 4, ... columns, each the minimum of two runs of half its
    length, then the window as two overlapping runs (a minimum is exact, so any cover of
    the window gives the same value): ~log2(size) passes of ``np.minimum`` over the
    rows, ~5x faster than scipy's filter at a working image's 288 x 384 (~1 ms a frame).
    scipy's filter is used where the array holds a NaN (its comparisons order NaN
    differently from ``np.minimum``'s propagation).
    """
    half = size // 2
    if values.ndim != 2 or size % 2 == 0 or half == 0:
        from scipy.ndimage import minimum_filter1d

        return minimum_filter1d(values, size, axis=1, mode="nearest")
    w = values.shape[1]
    # mode "nearest": the edge columns repeated ``half`` times each side.
    run = np.concatenate(
        (
            np.repeat(values[:, :1], half, axis=1),
            values,
            np.repeat(values[:, -1:], half, axis=1),
        ),
        axis=1,
    )
    span = 1  # run[:, i]: the minimum of the padded columns i .. i + span - 1
    while 2 * span <= size:
        run = np.minimum(run[:, :-span], run[:, span:])
        span *= 2
    out = np.minimum(run[:, :w], run[:, size - span : size - span + w])
    if np.isnan(out).any():  # a NaN anywhere in the input reaches the output
        from scipy.ndimage import minimum_filter1d

        return minimum_filter1d(values, size, axis=1, mode="nearest")
    return out


def column_window_mean(csum: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """Mean over rows ``[start[j], stop[j])`` of every column, from a cumulative sum.

    Parameters
    ----------
    csum : ndarray, shape (H + 1, W)
        ``csum[k] = image[:k].sum(0)``.
    start, stop : ndarray of int, shape (H,)
        Window per output row; clipped to the image. Empty windows give 0.

    Returns
    -------
    ndarray, shape (H, W)
    """
    h = csum.shape[0] - 1
    a = np.clip(start, 0, h)
    b = np.clip(stop, 0, h)
    n = np.maximum(b - a, 1).astype(csum.dtype)
    return (csum[b] - csum[a]) / n[:, None]


def region_means(
    image: np.ndarray, mid_px: int, up_px: int, down_px: int, *, gap_px: int = 0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """``M_up``, ``M_mid``, ``M_down`` (paper Fig. 1) at every pixel.

    Parameters
    ----------
    image : ndarray, shape (H, W), float
    mid_px : int
        Height of the band centred on the pixel (rows ``j - mid//2 .. j + mid - mid//2 - 1``).
    up_px, down_px : int
        Heights of the regions right above and right below the band.
    gap_px : int
        Rows skipped between the band and the region below (0 in the paper).

    Returns
    -------
    m_up, m_mid, m_down : ndarray, shape (H, W)
    """
    h = image.shape[0]
    csum = np.zeros((h + 1, image.shape[1]), dtype=np.float32)
    np.cumsum(image, axis=0, dtype=np.float32, out=csum[1:])
    j = np.arange(h)
    top = j - mid_px // 2
    bot = top + mid_px
    m_mid = column_window_mean(csum, top, bot)
    m_up = column_window_mean(csum, top - up_px, top)
    m_down = column_window_mean(csum, bot + gap_px, bot + gap_px + down_px)
    return m_up, m_mid, m_down


def dif_map(image: np.ndarray, mid_px: int, up_px: int, down_px: int) -> np.ndarray:
    """The paper's regional contrast ``2 M_mid - M_up - M_down`` at every pixel."""
    m_up, m_mid, m_down = region_means(image, mid_px, up_px, down_px)
    return 2.0 * m_mid - m_up - m_down


def block_mean(image: np.ndarray, fy: int, fx: int) -> np.ndarray:
    """Average non-overlapping ``fy x fx`` blocks (trailing partial blocks dropped).

    Returns float32 in the units of ``image``. Used to build the working image of the
    default segmenter: averaging (not sub-sampling) also averages out speckle.
    """
    h, w = image.shape
    hh, ww = h // fy, w // fx
    a = np.asarray(image[: hh * fy, : ww * fx], dtype=np.float32)
    if fy == 1 and fx == 1:
        return a
    return a.reshape(hh, fy, ww, fx).mean(axis=(1, 3), dtype=np.float32)


def band_means(
    image: np.ndarray, i: np.ndarray, j: np.ndarray, a_mm: float, b_mm: float, sy: float
) -> np.ndarray:
    """Per point, the mean grey value of rows ``j + [a_mm, b_mm)`` in column ``i`` (NaN outside)."""
    h = image.shape[0]
    a = int(np.floor(a_mm / sy + 1e-9))  # as ceil_px: immune to the pixel size's last bit
    b = max(a + 1, ceil_px(b_mm / sy))
    rows = j[:, None] + np.arange(a, b)[None, :]
    inside = (rows >= 0) & (rows < h)
    vals = image[np.clip(rows, 0, h - 1), i[:, None]].astype(np.float64)
    n = inside.sum(axis=1)
    total = np.where(inside, vals, 0.0).sum(axis=1)
    return np.where(n > 0, total / np.maximum(n, 1), np.nan)


def sorted_row_percentiles(rows: np.ndarray, q: tuple[float, ...]) -> np.ndarray:
    """``np.percentile(rows, q, axis=1)`` of rows already sorted, shape ``(len(q), H)``.

    The same values by the same operations as numpy's default ("linear") method: the
    order statistics are read at their positions (the rows are sorted, so no
    partition is needed: ``np.percentile`` partitions again, ~3x the cost at the
    tissue level's sizes), then interpolated in float64 from the nearer end (numpy's
    ``_lerp``). ``Testing/test_segmentation_speed_paths.py`` compares it with
    ``np.percentile``.
    """
    n = rows.shape[1]
    quant = np.true_divide(np.asarray(q, dtype=float), 100)
    virtual = (n - 1) * quant
    prev = np.floor(virtual)
    gamma = virtual - prev  # float64, as numpy's (its rule for the ends below)
    i0 = prev.astype(np.intp)
    i1 = i0 + 1
    top = virtual >= n - 1
    i0[top] = i1[top] = -1
    low = virtual < 0
    i0[low] = i1[low] = 0
    a = rows[:, i0].T
    b = rows[:, i1].T
    diff = b - a
    g = gamma[:, None]
    out = np.add(a, diff * g)
    np.subtract(b, diff * (1 - g), out=out, where=g >= 0.5, casting="unsafe")
    return out


def sorted_percentile(values: np.ndarray, q: float) -> float:
    """``float(np.percentile(values, q))`` of a 1-D array already sorted, ``q`` a Python
    number.

    A Python ``q`` makes numpy interpolate in the array's own dtype (its "weak" scalar:
    a float32 array gives a float32 value), unlike :func:`sorted_row_percentiles`'s
    float64; the same operations otherwise (the order statistics read at their
    positions, numpy's ``_lerp`` from the nearer end). ``np.percentile`` partitions
    again and checks for NaN: ~50 us on the evidence baseline's hundred values.
    """
    n = values.shape[0]
    virtual = (n - 1) * np.true_divide(q, 100)
    prev = np.floor(virtual)
    gamma = float(virtual - prev)
    if virtual >= n - 1:
        i0 = i1 = -1
    elif virtual < 0:
        i0 = i1 = 0
    else:
        i0 = int(prev)
        i1 = i0 + 1
    a, b = values[i0], values[i1]
    diff = b - a
    return float(b - diff * (1 - gamma) if gamma >= 0.5 else a + diff * gamma)


def sorted_row_medians(rows: np.ndarray) -> np.ndarray:
    """``np.median(rows, axis=1)`` of finite rows already sorted (the middle, or the mean
    of the two middle values in the rows' dtype, as ``np.median`` takes it)."""
    n = rows.shape[1]
    k = n // 2
    if n % 2:
        return rows[:, k].copy()
    out = rows[:, k - 1] + rows[:, k]
    out /= 2
    return out

"""Bringing pixel types to the common 8-bit range used by the segmenters.

B-mode images are almost always 8-bit already (PLUS writes ``MET_UCHAR``). Other
types are mapped to ``uint8`` so that every threshold in the segmenters (which the
paper states for 8-bit images) keeps its meaning:

* ``uint8``: unchanged (no copy).
* ``int8`` (``MET_CHAR``): shifted by +128 (signed storage of an 8-bit image).
* Wider integer and floating types: linearly rescaled so that the 0.5th..99.5th
  percentile of the whole sweep spans 0..255, clipped. Percentiles instead of the
  min/max so that a few saturated or dead pixels do not squash the image. NaN -> 0.
"""

from __future__ import annotations

import numpy as np

__all__ = ["to_uint8"]


def to_uint8(frames: np.ndarray) -> np.ndarray:
    """Return ``frames`` as ``uint8`` following the rules in the module docstring.

    Parameters
    ----------
    frames : ndarray
        Any real pixel type.

    Returns
    -------
    ndarray of uint8, same shape.

    Examples
    --------
    >>> to_uint8(np.array([-128, 0, 127], dtype=np.int8)).tolist()
    [0, 128, 255]
    """
    a = np.asarray(frames)
    if a.dtype == np.uint8:
        return a
    if a.dtype == np.int8:
        return (a.astype(np.int16) + 128).astype(np.uint8)
    # Percentiles on a subsample: exact enough and cheap on big sweeps.
    flat = a.reshape(-1)
    step = max(1, flat.size // 1_000_000)
    sample = flat[::step].astype(np.float64)
    sample = sample[np.isfinite(sample)]
    if sample.size == 0:
        return np.zeros(a.shape, np.uint8)
    lo, hi = np.percentile(sample, [0.5, 99.5])
    if hi <= lo:
        hi = lo + 1.0
    out = np.empty(a.shape, np.uint8)
    # Chunk over frames so a big sweep is never held whole in float64.
    for k in range(a.shape[0] if a.ndim == 3 else 1):
        src = a[k] if a.ndim == 3 else a
        f = (np.nan_to_num(src.astype(np.float32), nan=lo) - lo) * (255.0 / (hi - lo))
        dst = out[k] if a.ndim == 3 else out
        np.clip(np.rint(f), 0, 255, out=f)
        dst[...] = f.astype(np.uint8)
    return out

"""Bringing pixel types to the common 8-bit range used by the segmenters.

B-mode images are almost always 8-bit already (PLUS writes ``MET_UCHAR``). Other
types are mapped to ``uint8`` so that every threshold in the segmenters (which the
paper states for 8-bit images) keeps its meaning. The rules, in order:

* ``uint8`` (``MET_UCHAR``): unchanged (no copy; a memory map stays a memory map).
* Integers whose values all lie in 0..255 (an 8-bit image stored in a wider type,
  e.g. ``MET_USHORT`` or ``MET_SHORT``, or ``MET_CHAR`` holding 0..127): values kept.
* ``int8`` (``MET_CHAR``) with negative values: shifted by +128 (signed storage of
  an 8-bit signal, as RF-like data centred on 0 is stored); order-preserving.
* Floats whose values all lie in 0..1 (normalised intensities): multiplied by 255.
* Floats whose values all lie in 0..255: rounded.
* Anything else (e.g. 12/16-bit data, dB floats): linearly rescaled so that the
  0.5th..99.5th percentile of the whole sweep spans 0..255, clipped. Percentiles
  rather than min/max so a few saturated or dead pixels do not squash the image.

NaN becomes 0. The work is done a few frames at a time, so a large (memory-mapped)
sweep is never held whole in floating point.
"""

from __future__ import annotations

import numpy as np

__all__ = ["to_uint8"]

_CHUNK_BYTES = 16 << 20


def _chunks(a: np.ndarray) -> range:
    per = max(1, _CHUNK_BYTES // max(1, a[0].nbytes)) if a.ndim >= 1 and len(a) else 1
    return range(0, a.shape[0], per) if a.ndim >= 1 else range(1)


def _finite_range(a: np.ndarray) -> tuple[float, float]:
    """Min and max of the finite values, a chunk at a time (NaN if none)."""
    lo, hi = np.inf, -np.inf
    per = _chunks(a).step if a.ndim >= 1 else 1
    for s in _chunks(a):
        c = np.asarray(a[s : s + per])
        if c.dtype.kind == "f":
            c = c[np.isfinite(c)]
        if c.size:
            lo, hi = min(lo, float(c.min())), max(hi, float(c.max()))
    return (lo, hi) if lo <= hi else (np.nan, np.nan)


def _percentiles(a: np.ndarray) -> tuple[float, float]:
    """0.5th and 99.5th percentiles from a subsample of frames and pixels."""
    frames = a[:: max(1, a.shape[0] // 64)] if a.ndim == 3 else a
    flat = np.asarray(frames, dtype=np.float64).reshape(-1)
    flat = flat[:: max(1, flat.size // 1_000_000)]
    flat = flat[np.isfinite(flat)]
    lo, hi = np.percentile(flat, [0.5, 99.5])
    return float(lo), float(hi)


def _map(a: np.ndarray, scale: float, offset: float) -> np.ndarray:
    """``rint(a * scale + offset)`` clipped to 0..255, NaN -> 0, a chunk at a time."""
    out = np.empty(a.shape, np.uint8)
    if a.ndim == 0 or a.size == 0:
        return out
    per = _chunks(a).step
    for s in _chunks(a):
        f = np.asarray(a[s : s + per], dtype=np.float64) * scale + offset
        f = np.nan_to_num(f, nan=0.0, posinf=255.0, neginf=0.0)
        np.clip(np.rint(f), 0, 255, out=f)
        out[s : s + per] = f.astype(np.uint8)
    return out


def to_uint8(frames: np.ndarray) -> np.ndarray:
    """Return ``frames`` as ``uint8`` following the rules in the module docstring.

    Parameters
    ----------
    frames : ndarray
        Any real pixel type, typically ``(N, H, W)``.

    Returns
    -------
    ndarray of uint8, same shape.

    Examples
    --------
    >>> to_uint8(np.array([-128, 0, 127], dtype=np.int8)).tolist()
    [0, 128, 255]
    >>> to_uint8(np.array([0, 17, 255], dtype=np.uint16)).tolist()
    [0, 17, 255]
    >>> to_uint8(np.array([0.0, 0.5, 1.0])).tolist()
    [0, 128, 255]
    """
    a = np.asarray(frames)
    if a.dtype == np.uint8:
        return a
    # Absurd values (1e308) may overflow to inf on the way; they end up clipped.
    with np.errstate(all="ignore"):
        return _to_uint8(a)


def _to_uint8(a: np.ndarray) -> np.ndarray:
    if a.dtype == np.bool_:
        return a.astype(np.uint8) * np.uint8(255)
    if a.dtype.kind not in "iuf":
        raise TypeError(f"cannot convert pixel type {a.dtype} to uint8")
    if a.ndim == 0 or a.size == 0:
        return _map(a, 1.0, 0.0)
    lo, hi = _finite_range(a)
    if not np.isfinite(lo):  # all NaN
        return np.zeros(a.shape, np.uint8)
    if a.dtype.kind in "iu":
        if lo >= 0 and hi <= 255:
            return _map(a, 1.0, 0.0)
        if a.dtype == np.int8:
            return _map(a, 1.0, 128.0)
    else:
        if lo >= 0 and hi <= 1:
            return _map(a, 255.0, 0.0)
        if lo >= 0 and hi <= 255:
            return _map(a, 1.0, 0.0)
    plo, phi = _percentiles(a)
    if phi <= plo:
        phi = plo + 1.0
    scale = 255.0 / (phi - plo)
    return _map(a, scale, -plo * scale)

"""Sampling along lines on a frame: the helpers :mod:`.flanks`, :mod:`.rim` and :mod:`.settle` share.

Bilinear samples at arrays of points (the flat-index form of
:func:`.detection.sample_bilinear`), a median of three along a trace, and the
full-resolution refinement of ridge points along their normals.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Sequence

import numpy as np

from BoneUSRecon.Logic.segmentation.detection import sample_bilinear

__all__ = ["bilinear_at", "median3", "refine_across", "with_points"]


def median3(a: np.ndarray) -> np.ndarray:
    """Median of three along the last axis (ends kept), vectorised over the others."""
    if a.shape[-1] < 3:
        return a
    x, y, z = a[..., :-2], a[..., 1:-1], a[..., 2:]
    mid = np.maximum(np.minimum(x, y), np.minimum(np.maximum(x, y), z))
    return np.concatenate([a[..., :1], mid, a[..., -1:]], axis=-1)


def bilinear_at(a: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Bilinear sample of ``a`` (h, w) at column ``x``, row ``y`` (any shape), clamped.

    The flat-index form of :func:`.detection.sample_bilinear` for arrays of points (a
    third of its numpy calls; the same values inside the image).
    """
    h, w = a.shape
    x = np.clip(x, 0, w - 1.000001)
    y = np.clip(y, 0, h - 1.000001)
    x0 = x.astype(np.intp)
    y0 = y.astype(np.intp)
    x -= x0
    y -= y0
    i = y0 * w
    i += x0
    flat = a.ravel()
    # The four neighbours by one index array into shifted views (no index arrays i + 1,
    # i + w, i + w + 1; ``take`` gathers ~10 % faster than indexing, the same values).
    v00, v01, v10, v11 = flat.take(i), flat[1:].take(i), flat[w:].take(i), flat[w + 1 :].take(i)
    if flat.dtype.kind != "f":  # grey values: differences must not wrap
        v00, v01, v10, v11 = (c.astype(np.float32) for c in (v00, v01, v10, v11))
    top = v01 - v00
    top *= x
    top += v00
    bot = v11 - v10
    bot *= x
    bot += v10
    bot -= top
    bot *= y
    bot += top
    return bot


def refine_across(
    image: np.ndarray,
    rx: np.ndarray,
    rz: np.ndarray,
    nx: np.ndarray,
    nz: np.ndarray,
    sx: float,
    sy: float,
    half_mm: float,
) -> tuple[np.ndarray, np.ndarray]:
    """Ridge points ``(N,)`` mm moved to the echo's peak along their normals, full resolution.

    The profile across the flank (+-``half_mm``, half-pixel steps) is the mean of three
    parallel lines half a pixel apart along the flank (speckle averages, the echo does
    not), smoothed over three samples; the peak is fitted by a parabola. Offsets along a
    trace are smoothed by a median of three (one speckle grain does not bend it).
    """
    if rx.size == 0:
        return rx, rz
    step = 0.5 * min(sx, sy)
    n = max(1, int(round(half_mm / step)))
    u = step * np.arange(-n - 1, n + 2)  # one extra each side for the parabola
    along = step * np.array([-1.0, 0.0, 1.0])
    # (N, len(u), 3): across by u, along the flank (-nz, nx) by ``along``.
    qx = (rx[:, None, None] + u[:, None] * nx[:, None, None] - along * nz[:, None, None]) / sx
    qz = (rz[:, None, None] + u[:, None] * nz[:, None, None] + along * nx[:, None, None]) / sy
    prof = bilinear_at(np.asarray(image), qx, qz).sum(axis=-1)
    sm = prof[:, :-2] + prof[:, 1:-1] + prof[:, 2:]  # index i: centred on u[i + 1]
    kk = sm[:, 1:-1].argmax(axis=1) + 1  # the peak, with a neighbour on each side
    r = np.arange(kk.size)
    y0, y1, y2 = sm[r, kk - 1], sm[r, kk], sm[r, kk + 1]
    den = y0 - 2 * y1 + y2
    frac = np.where(den < 0, 0.5 * (y0 - y2) / np.where(den < 0, den, -1.0), 0.0)
    d = u[kk + 1] + step * np.clip(frac, -0.5, 0.5)
    d = median3(d)
    return rx + d * nx, rz + d * nz


def with_points(
    image: np.ndarray, cands: list, which: Sequence[int], points: Sequence[np.ndarray]
) -> list:
    """``cands`` with candidate ``which[k]`` given ``points[k]`` where those are new
    objects, its grey values re-sampled as every candidate's
    (:func:`.candidates.frame_candidates`; one sample of all changed points); strengths
    and flags unchanged."""
    changed = [
        (n, pts) for n, pts in zip(which, points, strict=True) if pts is not cands[n].points_px
    ]
    if changed:
        grey = sample_bilinear(np.asarray(image), np.concatenate([pts for _, pts in changed]))
        cut = np.cumsum([0] + [pts.shape[0] for _, pts in changed])
        for q, (n, pts) in enumerate(changed):
            cands[n] = dataclasses.replace(
                cands[n], points_px=pts, intensity=grey[cut[q] : cut[q + 1]]
            )
    return cands

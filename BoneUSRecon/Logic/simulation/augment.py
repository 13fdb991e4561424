"""Augmentations of a recorded sweep, with the poses kept consistent.

Used to test the segmenter on *real* data without new recordings: the same anatomy
seen mirrored, with another gain, with extra speckle, at a coarser pixel size or
through a smaller window must give the same bone, in reference millimetres. Every
function returns a new :class:`~BoneUSRecon.Logic.sweep.Sweep` whose
``image_to_reference`` maps the new pixels to the same place as the old ones
(``M' = M A`` with ``A`` the new-to-old pixel map), so contours found on the augmented
sweep compare directly, in mm, with those of the original.
"""

from __future__ import annotations

import numpy as np

from BoneUSRecon.Logic.sweep import Sweep

__all__ = ["flip_lateral", "scale_gain", "add_speckle", "resample_spacing", "crop"]


def _with(sweep: Sweep, frames: np.ndarray, a: np.ndarray | None = None) -> Sweep:
    m = np.asarray(sweep.image_to_reference, float)
    if a is not None:
        m = m @ a
    return sweep.replace(frames=np.ascontiguousarray(frames, np.uint8), image_to_reference=m)


def flip_lateral(sweep: Sweep) -> Sweep:
    """Mirror every frame left-right (the probe turned round, or MF read as MN)."""
    w = sweep.frames.shape[2]
    a = np.eye(4)
    a[0, 0], a[0, 3] = -1.0, w - 1.0  # new column i' is old column w - 1 - i'
    return _with(sweep, sweep.frames[:, :, ::-1], a)


def scale_gain(sweep: Sweep, factor: float) -> Sweep:
    """Multiply the displayed grey values by ``factor`` (clipped to 0..255): a gain change."""
    f = np.asarray(sweep.frames, np.float32) * np.float32(factor)
    return _with(sweep, np.clip(np.rint(f), 0, 255).astype(np.uint8))


def add_speckle(sweep: Sweep, strength: float = 0.3, seed: int = 0) -> Sweep:
    """Multiply every pixel by independent gamma noise of mean 1 and std ``strength``.

    Multiplicative, like speckle: black margins stay black, bright echoes get grainy.
    """
    rng = np.random.default_rng(seed)
    k = 1.0 / strength**2  # gamma shape: std / mean = 1 / sqrt(k)
    noise = rng.gamma(k, 1.0 / k, sweep.frames.shape).astype(np.float32)
    f = np.asarray(sweep.frames, np.float32) * noise
    return _with(sweep, np.clip(np.rint(f), 0, 255).astype(np.uint8))


def resample_spacing(sweep: Sweep, spacing_mm: float) -> Sweep:
    """Resample every frame to square pixels of ``spacing_mm`` (anti-aliased)."""
    from scipy.ndimage import gaussian_filter, map_coordinates

    sx, sy = (float(v) for v in sweep.spacing_mm)
    n, h, w = sweep.frames.shape
    h2 = max(2, int(round(h * sy / spacing_mm)))
    w2 = max(2, int(round(w * sx / spacing_mm)))
    fx, fy = w / w2, h / h2
    # Anti-aliasing blur (sigma (f - 1) / 2 per axis, as skimage's resize), then linear
    # interpolation at the new pixel centres. scipy, not skimage: the Logic package's
    # requirements stay numpy + scipy (Slicer installs them).
    img = np.asarray(sweep.frames, np.float32)
    sig = (0.0, max(0.0, (fy - 1) / 2), max(0.0, (fx - 1) / 2))
    if any(sig):
        img = gaussian_filter(img, sig, mode="nearest")
    jj = (np.arange(h2) + 0.5) * fy - 0.5
    ii = (np.arange(w2) + 0.5) * fx - 0.5
    out = np.empty((n, h2, w2), np.float32)
    grid = np.meshgrid(jj, ii, indexing="ij")
    for k in range(n):
        out[k] = map_coordinates(img[k], grid, order=1, mode="nearest")
    # New pixel centre (i' + 0.5) * fx - 0.5 is the old column.
    a = np.eye(4)
    a[0, 0], a[0, 3] = fx, 0.5 * (fx - 1.0)
    a[1, 1], a[1, 3] = fy, 0.5 * (fy - 1.0)
    return _with(sweep, np.clip(np.rint(out), 0, 255).astype(np.uint8), a)


def crop(sweep: Sweep, rows: tuple[int, int], cols: tuple[int, int]) -> Sweep:
    """Keep rows ``rows[0]:rows[1]`` and columns ``cols[0]:cols[1]`` of every frame."""
    a = np.eye(4)
    a[0, 3], a[1, 3] = cols[0], rows[0]
    return _with(sweep, sweep.frames[:, rows[0] : rows[1], cols[0] : cols[1]], a)

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

from collections.abc import Callable
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from BoneUSRecon.Logic.sweep import Sweep

if TYPE_CHECKING:
    from BoneUSRecon.Logic.segmentation.result import SegmentationResult

__all__ = [
    "flip_lateral",
    "scale_gain",
    "add_speckle",
    "resample_spacing",
    "crop",
    "RECORDING_AUGMENTATIONS",
    "contour_agreement",
]


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


#: The augmentations the shared L14 recording (820 x 616 pixels) is checked with, by
#: ``Testing/test_real_recording.py`` and ``Testing/benchmarks/bench_real.py`` alike
#: (the crop's rows and columns are chosen for that image size).
RECORDING_AUGMENTATIONS: dict[str, Callable[[Sweep], Sweep]] = {
    "flip": lambda s: flip_lateral(s),
    "gain-30%": lambda s: scale_gain(s, 0.7),
    "gain+30%": lambda s: scale_gain(s, 1.3),
    "speckle": lambda s: add_speckle(s, 0.3, seed=1),
    "0.15mm": lambda s: resample_spacing(s, 0.15),
    "crop": lambda s: crop(s, (40, 560), (150, 700)),
    "all": lambda s: add_speckle(
        scale_gain(resample_spacing(flip_lateral(s), 0.15), 0.7),
        0.3,
        seed=2,
    ),
}


def contour_agreement(
    sweep: Sweep,
    result: SegmentationResult,
    augmented: Sweep,
    augmented_result: SegmentationResult,
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """How well the contours of an augmented sweep match the original's, in reference mm.

    Parameters
    ----------
    sweep, result : Sweep, SegmentationResult
        The original sweep and its segmentation.
    augmented, augmented_result : Sweep, SegmentationResult
        An augmented copy (poses kept consistent) and its segmentation.

    Returns
    -------
    distances : ndarray
        Distances (mm) of the augmented contours' points to the original contour of
        the same frame, for the points within its ends, all frames pooled.
    cover : ndarray
        Per frame both accepted: the share of the original contour (a dense polyline)
        with an augmented point closer than 0.5 mm.
    beyond : ndarray
        Per frame both accepted: the share of augmented points beyond the ends of the
        original contour.
    """
    ref = {c.frame: c.points_mm(sweep) for c in result.accepted}
    dist, cover, beyond = [], [], []
    for c in augmented_result.accepted:
        if c.frame not in ref:
            continue
        a = ref[c.frame]
        # The original contour as a dense polyline (points ~0.25 mm apart).
        t = np.linspace(0, len(a) - 1, 20 * len(a))
        dense = np.column_stack([np.interp(t, np.arange(len(a)), a[:, q]) for q in range(3)])
        p = c.points_mm(augmented)
        d, k = cKDTree(dense).query(p)
        # Points beyond the ends of the original contour (one runs further down a
        # flank than the other) have no counterpart: judged by ``beyond`` only.
        inside = (k > 0) & (k < len(dense) - 1)
        dist.append(d[inside])
        beyond.append(np.mean(~inside))
        cover.append(np.mean(cKDTree(p).query(dense)[0] < 0.5))
    return np.concatenate(dist), np.array(cover), np.array(beyond)

"""Augmentations of a recorded sweep, with the poses kept consistent.

Used to test the segmenter on *real* data without new recordings: the same anatomy
seen mirrored, with another gain, with extra speckle, at a coarser pixel size, through
a smaller window or through another scanner's display chain (its display curve, depth
gain, speckle reduction and noise floor) must give the same bone, in reference
millimetres. Every function returns a new :class:`~BoneUSRecon.Logic.sweep.Sweep` whose
``image_to_reference`` maps the new pixels to the same place as the old ones
(``M' = M A`` with ``A`` the new-to-old pixel map), so contours found on the augmented
sweep compare directly, in mm, with those of the original.

Harder copies: :func:`harden` gives a recording the cadaver's levels of issue 10 (a dim
echo, a grey shadow with reverberation bands), and :func:`no_contact`,
:func:`add_fascia` and :func:`add_vessel` draw the simulator's look-alikes into it (a
skin line over a no-contact gap, a fascia off the bone's flank, a vessel over the bone)
with grey levels taken from the recording itself: the rules against look-alikes tested
on real texture (``Testing/test_augment_lookalikes.py``).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator, Mapping
from typing import TYPE_CHECKING

import numpy as np
from scipy.spatial import cKDTree

from BoneUSRecon.Logic.simulation.levels import echo_levels
from BoneUSRecon.Logic.simulation.motion import smooth_noise
from BoneUSRecon.Logic.simulation.params import HardParams
from BoneUSRecon.Logic.sweep import Sweep

if TYPE_CHECKING:
    from BoneUSRecon.Logic.segmentation.result import SegmentationResult

__all__ = [
    "flip_lateral",
    "scale_gain",
    "add_speckle",
    "resample_spacing",
    "crop",
    "sector",
    "screen_capture",
    "display_curve",
    "depth_gain",
    "smooth",
    "add_noise",
    "RECORDING_AUGMENTATIONS",
    "HARD_AUGMENTATIONS",
    "tissue_level",
    "harden",
    "no_contact",
    "add_fascia",
    "add_vessel",
    "add_muscle",
    "LOOKALIKE_AUGMENTATIONS",
    "contour_agreement",
]


def _with(sweep: Sweep, frames: np.ndarray, a: np.ndarray | None = None) -> Sweep:
    m = np.asarray(sweep.image_to_reference, float)
    if a is not None:
        m = m @ a
    return sweep.replace(frames=np.ascontiguousarray(frames, np.uint8), image_to_reference=m)


def _inside(sweep: Sweep, out: np.ndarray) -> Sweep:
    """``out`` rounded to uint8, black wherever the recording is (outside the imaged
    field a scan converter writes exact black, which :mod:`.segmentation` reads as
    the field's edge; a display step acts inside it only)."""
    f = np.asarray(sweep.frames)
    out = np.where(f > 0, np.clip(np.rint(out), 0, 255), 0)
    return _with(sweep, out.astype(np.uint8))


def flip_lateral(sweep: Sweep) -> Sweep:
    """Mirror every frame left-right (the probe turned round, or MF read as MN)."""
    w = sweep.frames.shape[2]
    a = np.eye(4)
    a[0, 0], a[0, 3] = -1.0, w - 1.0  # new column i' is old column w - 1 - i'
    return _with(sweep, sweep.frames[:, :, ::-1], a)


def scale_gain(sweep: Sweep, factor: float) -> Sweep:
    """Multiply the displayed grey values by ``factor`` (clipped to 0..255): a gain change."""
    return _inside(sweep, np.asarray(sweep.frames, np.float32) * np.float32(factor))


def add_speckle(sweep: Sweep, strength: float = 0.3, seed: int = 0) -> Sweep:
    """Multiply every pixel by independent gamma noise of mean 1 and std ``strength``.

    Multiplicative, like speckle: black margins stay black, bright echoes get grainy.
    """
    rng = np.random.default_rng(seed)
    k = 1.0 / strength**2  # gamma shape: std / mean = 1 / sqrt(k)
    noise = rng.gamma(k, 1.0 / k, sweep.frames.shape).astype(np.float32)
    return _inside(sweep, np.asarray(sweep.frames, np.float32) * noise)


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


def sector(sweep: Sweep, top_share: float = 0.7) -> Sweep:
    """Black out every frame outside a sector: a curvilinear (or steered) probe's field.

    The imaged area's top row keeps the middle ``top_share`` of its width, the bottom
    row all of it, the sides straight between (the field of a convex probe whose
    apex lies above the image, as scan conversion draws it, black outside). Pixels keep
    their place, so the poses are unchanged.
    """
    if not 0 < top_share <= 1:
        raise ValueError(f"top_share must be in (0, 1], got {top_share}")
    f = np.asarray(sweep.frames)
    lit = _lit(f)
    rows, cols = np.flatnonzero(lit.any(axis=1)), np.flatnonzero(lit.any(axis=0))
    if rows.size < 2 or cols.size < 2:
        return _with(sweep, f)
    r0, r1, c0, c1 = rows[0], rows[-1], cols[0], cols[-1]
    depth = (np.arange(f.shape[1])[:, None] - r0) / (r1 - r0)
    half = 0.5 * (c1 - c0) * (top_share + (1.0 - top_share) * np.clip(depth, 0.0, 1.0))
    inside = np.abs(np.arange(f.shape[2])[None, :] - 0.5 * (c0 + c1)) <= half
    return _with(sweep, np.where(inside[None], f, 0))


def screen_capture(
    sweep: Sweep,
    margins_mm: tuple[float, float, float, float] = (6.0, 10.0, 8.0, 12.0),
    *,
    frame_line: bool = True,
    seed: int = 0,
) -> Sweep:
    """Every frame as a frame grabber captures the scanner's screen: the image inside a
    black screen with its user interface (a loose clip rectangle records the same).

    ``margins_mm``: black above, left, under and right of the image (top, left,
    bottom, right), in the image's own pixel size. Drawn in them: text lines (glyphs
    about 0.8 mm tall, white) over and under the image, a grey-scale bar and a depth
    ruler (a dot every 5 mm) to its right, a focus marker to its left and, with
    ``frame_line``, a grey line framing the image one pixel off it. The poses follow the
    image (a pixel keeps its millimetres).
    """
    f = np.asarray(sweep.frames)
    n, h, w = f.shape
    sx, sy = (float(v) for v in sweep.spacing_mm)
    top, left = round(margins_mm[0] / sy), round(margins_mm[1] / sx)
    bottom, right = round(margins_mm[2] / sy), round(margins_mm[3] / sx)
    out = np.zeros((n, h + top + bottom, w + left + right), np.uint8)
    out[:, top : top + h, left : left + w] = f
    x1 = left + w  # first column right of the image
    if right >= round(3.5 / sx):  # the ruler's dots and the grey-scale bar
        for y in range(top, top + h, max(1, round(5.0 / sy))):
            out[
                :, y : y + max(1, round(0.25 / sy)), x1 + round(0.7 / sx) : x1 + round(1.2 / sx)
            ] = 220
        bar = slice(top + round(1.5 / sy), top + min(h, round(26.0 / sy)))
        ramp = np.linspace(255, 0, bar.stop - bar.start).astype(np.uint8)
        out[:, bar, x1 + round(2.5 / sx) : x1 + round(3.5 / sx)] = ramp[None, :, None]
    if left >= round(1.5 / sx):  # the focus marker: a small triangle pointing at the image
        y0 = top + h // 2
        for d in range(round(0.7 / sx)):
            half = round(0.7 / sy) - d
            out[:, y0 - half : y0 + half + 1, left - round(1.0 / sx) + d] = 200
    rng = np.random.default_rng(seed)
    gh, gw = max(1, round(0.8 / sy)), max(1, round(0.55 / sx))
    for y, x in (
        (round(1.2 / sy), round(1.0 / sx)),
        (round(3.2 / sy), round(1.0 / sx)),
        (round(1.2 / sy), left + w // 2),
        (top + h + round(2.5 / sy), round(2.0 / sx)),
    ):
        for k in range(12):  # a line of twelve glyphs
            g = rng.random((gh, gw)) < 0.5
            xs = x + k * round(0.7 / sx)
            region = out[:, y : y + gh, xs : xs + gw]
            region[:, g[: region.shape[1], : region.shape[2]]] = 255
    if frame_line:
        out[:, top - 2, left - 2 : x1 + 2] = 128
        out[:, top + h + 1, left - 2 : x1 + 2] = 128
        out[:, top - 2 : top + h + 2, left - 2] = 128
        out[:, top - 2 : top + h + 2, x1 + 1] = 128
    a = np.eye(4)
    a[0, 3], a[1, 3] = -left, -top
    return _with(sweep, out, a)


def display_curve(sweep: Sweep, gamma: float) -> Sweep:
    """Map every grey ``g`` to ``255 (g / 255) ** gamma``: another scanner's display
    curve (dynamic range / log compression setting). ``gamma`` < 1 lifts the dark
    greys toward the bright ones (a narrower dynamic range), > 1 spreads them."""
    if not gamma > 0:
        raise ValueError(f"gamma must be positive, got {gamma}")
    f = np.asarray(sweep.frames, np.float32) / np.float32(255.0)
    return _inside(sweep, 255.0 * f ** np.float32(gamma))


def depth_gain(sweep: Sweep, top: float, bottom: float) -> Sweep:
    """Multiply the rows by a gain running linearly from ``top`` (first row) to
    ``bottom`` (last row): another time-gain-compensation setting."""
    h = sweep.frames.shape[1]
    ramp = np.linspace(top, bottom, h, dtype=np.float32)[None, :, None]
    return _inside(sweep, np.asarray(sweep.frames, np.float32) * ramp)


def smooth(sweep: Sweep, sigma_mm: float) -> Sweep:
    """Gaussian blur of ``sigma_mm`` inside the field: a scanner's speckle reduction
    or frame persistence (the echo grows thicker and dimmer, speckle finer)."""
    from scipy.ndimage import gaussian_filter

    sx, sy = (float(v) for v in sweep.spacing_mm)
    sig = (0.0, sigma_mm / sy, sigma_mm / sx)
    return _inside(sweep, gaussian_filter(np.asarray(sweep.frames, np.float32), sig))


def add_noise(sweep: Sweep, std: float, seed: int = 0) -> Sweep:
    """Add independent Gaussian noise of ``std`` grey levels inside the field: the
    electronic noise floor of a higher gain or a weaker probe (it greys the shadow,
    unlike :func:`add_speckle`, which scales with the echo)."""
    rng = np.random.default_rng(seed)
    noise = rng.normal(0.0, std, sweep.frames.shape).astype(np.float32)
    return _inside(sweep, np.asarray(sweep.frames, np.float32) + noise)


def _lit(frames: np.ndarray) -> np.ndarray:
    """Pixels inside the imaged area (H, W): rows and columns not black in every frame."""
    f = np.asarray(frames)
    cols = f.max(axis=(0, 1)) > 0
    rows = f.max(axis=(0, 2)) > 0
    return rows[:, None] & cols[None, :]


def _in_field(sweep: Sweep, out: np.ndarray, lit: np.ndarray) -> Sweep:
    """``out`` (float greys) rounded to uint8, black outside the imaged area ``lit``
    (:func:`_lit`): a scan converter's margins stay exactly black."""
    out = np.where(lit[None], out, 0.0)
    return _with(sweep, np.clip(np.rint(out), 0, 255).astype(np.uint8))


def tissue_level(
    frames: np.ndarray, spacing_mm: float, smooth_mm: float = 2.0, upper_half: bool = True
) -> np.ndarray:
    """The grey of soft tissue at each depth (H,): the per-row median of the local means
    (1 mm) of the imaged pixels, over the whole sweep, smoothed over depth.

    With ``upper_half`` (default) the median of the row's brighter half: shadows (dark)
    and bone echoes (bright, few) are both a minority of a row's pixels at bone depth,
    so this keeps shadows out without letting the few bright echoes in: the level of
    the tissue *beside* a shadow. Without, the plain median: the typical grey at that
    depth. Derived from the recording itself: it follows its gain, TGC and depth.
    """
    from scipy.ndimage import gaussian_filter1d, uniform_filter

    f = np.asarray(frames, np.float32)
    lit = _lit(f)
    n = max(1, int(round(1.0 / spacing_mm)))
    local = uniform_filter(f, (1, n, n))
    h = f.shape[1]
    level = np.full(h, np.nan, np.float32)
    for j in np.flatnonzero(lit.any(1)):
        v = local[:, j, lit[j]].reshape(-1)
        level[j] = np.median(v[v >= np.median(v)]) if upper_half else np.median(v)
    ok = np.isfinite(level)
    level = np.interp(np.arange(h), np.flatnonzero(ok), level[ok]).astype(np.float32)
    return np.maximum(gaussian_filter1d(level, smooth_mm / spacing_mm, mode="nearest"), 1.0)


def _bone_shadow_gain(
    f: np.ndarray, contours: Mapping[int, np.ndarray], sp: float, ratio: float
) -> np.ndarray:
    """Gain (N, H, W) that brings the shadow under each frame's bone contour to ``ratio``
    of the tissue just above the bone, column by column (1 elsewhere).

    Contours: ``(M, 2)`` pixels ``(i, j)`` ordered by ``i``, by frame; frames without one
    are left as they are. Per column: the tissue above is the median 1-3 mm above the
    contour, the shadow the median 1.5-8 mm under it (the bands ``levels.echo_levels``
    measures), both smoothed over 1 mm of columns (speckle); everything from 1.5 mm
    under the contour down is scaled by ``ratio * above / shadow`` (0.25-4x).
    """
    from scipy.ndimage import uniform_filter1d

    n, h, w = f.shape
    gain = np.ones_like(f)
    rows = np.arange(h)[:, None]
    a0, a1, s0, s1 = (max(1, int(round(v / sp))) for v in (1.0, 3.0, 1.5, 8.0))
    box = max(1, int(round(1.0 / sp)))
    for k, c in contours.items():
        c = np.asarray(c, float).reshape(-1, 2)
        if not 0 <= k < n or c.shape[0] < 2:
            continue
        i = np.arange(max(0, int(np.ceil(c[0, 0]))), min(w - 1, int(np.floor(c[-1, 0]))) + 1)
        if i.size < 2:
            continue
        jc = np.rint(np.interp(i, c[:, 0], c[:, 1])).astype(int)
        d = rows - jc[None, :]  # rows relative to the contour, (h, columns)
        img = f[k][:, i]
        m_a = uniform_filter1d(np.nanmedian(np.where((d >= -a1) & (d <= -a0), img, np.nan), 0), box)
        m_s = uniform_filter1d(np.nanmedian(np.where((d >= s0) & (d <= s1), img, np.nan), 0), box)
        g = np.clip(ratio * m_a / np.maximum(m_s, 1.0), 0.25, 4.0).astype(np.float32)
        gain[k][:, i] = np.where(d >= s0, g[None, :], 1.0)
    return gain


def harden(
    sweep: Sweep,
    *,
    echo_ratio: float | None = 1.3,
    shadow_ratio: float | None = 0.65,
    reverb: float = 0.35,
    reverb_mm: float = 2.5,
    reverb_copies: int = 3,
    echo_percentile: float = 99.9,
    bone_contours: Mapping[int, np.ndarray] | None = None,
    shadow_to_above: float = 0.54,
    seed: int = 0,
) -> Sweep:
    """Make a recording look like the hard cadaver sweep of issue 10.

    Levels come from each recording itself, per depth, never from absolute greys
    (:func:`tissue_level` ``T(j)``: the grey of soft tissue at each depth):

    * ``shadow_ratio``: where the local mean (3 mm box) falls below ``shadow_ratio * T``
      (a shadow), pixels are scaled up towards that level (at most 4x) and the rest of
      the deficit is filled with speckle (gamma noise of mean 1): the shadow becomes
      mid-grey, 0.65 of the tissue at its depth (the cadaver's level), still textured.
      A recording whose shadow is already that grey is left as it is.
    * ``reverb``: in the lifted shadow, ``reverb_copies`` copies of the bright excess over
      ``T`` in the 3.5 mm just above the shadow (the bone line), shifted down by
      ``m * reverb_mm``, the m-th at ``reverb * 0.75 ** (m - 1)``: equally spaced bands.
    * ``echo_ratio``: grey above the typical tissue grey at its depth ``M(j)`` (the plain
      per-row median, ``tissue_level(upper_half=False)``) is compressed in ratio,
      ``g' = M (g / M) ** gamma`` where ``g > M`` (a softer display curve for the bright
      end; darker pixels untouched), ``gamma`` per frame such that the frame's
      brightest echoes (the ``echo_percentile`` of ``g / M`` over the imaged area: the
      bone line, a few tenths of a per cent of the pixels) come out at ``echo_ratio``
      times the tissue (the cadaver: the echo 1.35x the tissue above it). The softer
      curve lowers the tissue's own level (its bright half) but not the grey under the
      typical level, so on its own it would make the shadow greyer relative to the
      tissue beside it than the recording's (L14: 0.80 -> 0.93 of the tissue at its
      depth, i.e. the shadow erased, beyond any real recording described); the dark
      end is therefore scaled with the tissue, row by row (the ratio of ``T`` after and
      before), so every pixel at or under the typical grey keeps its ratio to the tissue
      beside it: only the echo is compressed.
    * ``bone_contours`` (by frame, ``(M, 2)`` pixels ``(i, j)`` ordered by ``i``: the
      simulator's true contours or the reference contours of ``Testing/data``): the
      shadow is then the region from 1.5 mm under each contour down, and is brought,
      lifted or darkened, column by column, to ``shadow_to_above`` of the median grey
      1-3 mm above the bone as displayed after the echo step (the cadaver: 0.40 of an
      echo 1.35x the tissue above, i.e. 0.54), instead of the ``shadow_ratio`` rule
      (no bands). A recording whose shadow is not darker than the tissue beside it (the
      L14's, whose region under the bone is brighter than the tissue beside it at
      that depth) gets no shadow from a rule that must find one; this gives it the
      cadaver's.

    Levels measured with ``levels.echo_levels`` on the reference contours of
    ``Testing/data`` (echo / tissue above, shadow / echo, shadow / tissue beside at
    the same depth; the cadaver: 1.35, 0.40, 0.65): L14 as recorded 4.29, 0.15, 1.67
    (the tissue beside its shadow is darker than the shadow); ``low-contrast`` 1.48,
    0.42 (was 1.43, 0.48 before the dark end followed the tissue); ``hard`` 1.43, 0.45,
    1.12 (was 1.40, 0.51, 1.05); ``cadaver`` (with the reference contours) 1.48, 0.35,
    shadow 0.52 of the tissue above (cadaver 0.54). Spine phantom (its tissue above the
    bone saturated: echo 1.02x): ``grey-shadow`` 0.62 of the tissue beside, ``hard``
    0.92, 0.26, 0.67 (was 0.91, 0.31, 0.75).

    None (or 0 for ``reverb``) skips a step. The black margins of a scan-converted
    recording stay black. Poses are unchanged (no pixel moves).
    """
    from scipy.ndimage import uniform_filter

    sp = float(np.mean(sweep.spacing_mm))
    f = np.asarray(sweep.frames, np.float32)
    lit = _lit(f)
    t = tissue_level(f, sp)[None, :, None]
    out = f.copy()
    lifted = f
    if shadow_ratio is not None and bone_contours is None:
        n = max(1, int(round(3.0 / sp)))
        target = np.float32(shadow_ratio) * t
        broad = uniform_filter(f, (1, n, n))
        shadow = (broad < target) & lit[None]
        gain = np.clip(target / np.maximum(broad, 1.0), 1.0, 4.0)
        deficit = np.clip(target - broad * gain, 0.0, None)
        noise = np.random.default_rng(seed).gamma(2.0, 0.5, f.shape).astype(np.float32)
        out = np.where(shadow, f * gain + deficit * noise, f)
        if reverb > 0 and shadow.any():
            # The line just above the shadow (within 3.5 mm: the 3 mm box puts the
            # shadow's edge ~1.5 mm below the bone line), copied down into it.
            n = max(1, int(round(3.5 / sp)))
            cs = np.concatenate(
                [np.zeros_like(shadow[:, :1], np.int32), np.cumsum(shadow, axis=1, dtype=np.int32)],
                axis=1,
            )
            h = f.shape[1]
            hi = np.minimum(np.arange(h) + n + 1, h)
            near = (cs[:, hi] - cs[:, 1 : h + 1]) > 0  # any shadow 1..n rows below
            excess = np.where(near & ~shadow, np.clip(out - t, 0.0, None), 0.0).astype(np.float32)
            step = max(1, int(round(reverb_mm / sp)))
            band = np.zeros_like(out)
            for m in range(1, reverb_copies + 1):
                if m * step < f.shape[1]:
                    band[:, m * step :] += (
                        np.float32(reverb * 0.75 ** (m - 1)) * excess[:, : -m * step]
                    )
            out = np.where(shadow, out + band, out)
        lifted = out.copy()
    if echo_ratio is not None:
        # The typical tissue grey at each depth, of the recording as it came (the
        # lifted shadow would raise it).
        level = tissue_level(f, sp, upper_half=False)[:, None]
        for k in range(f.shape[0]):
            rho = out[k] / level
            top = float(np.percentile(rho[lit], echo_percentile))
            if top <= echo_ratio:
                continue  # already as faint as asked
            gamma = np.float32(np.log(echo_ratio) / np.log(top))
            out[k] = np.where(rho > 1.0, level * rho**gamma, out[k])
        # The softer curve lowers the tissue's own level (its bright half), not the
        # grey at or under the typical level: the shadow would come out greyer relative
        # to the tissue beside it than it was (L14: 0.80 -> 0.93 of the tissue at its
        # depth). Scale the dark end with the tissue, row by row, so each pixel at or
        # under the typical grey keeps its ratio to the tissue beside it.
        drop = tissue_level(out, sp) / tissue_level(f if shadow_ratio is None else lifted, sp)
        dark = out <= level[None]
        out = np.where(dark, out * np.minimum(drop, 1.0)[None, :, None], out)
    if shadow_ratio is not None and bone_contours is not None:
        # The shadow under the given bone, brought to the cadaver's level relative to the
        # tissue above the bone as displayed (after the echo step), lifted or darkened;
        # its texture kept (a gain, no fill, no bands).
        out = out * _bone_shadow_gain(out, bone_contours, sp, shadow_to_above)
    return _in_field(sweep, out, lit)


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
    "sector": lambda s: sector(s, 0.7),
    "screen": lambda s: screen_capture(s),
    "all": lambda s: add_speckle(
        scale_gain(resample_spacing(flip_lateral(s), 0.15), 0.7),
        0.3,
        seed=2,
    ),
    # Another scanner's display chain: its curve, its depth gain, its smoothing, its
    # noise floor (each within what B-mode presets span).
    "gamma0.6": lambda s: display_curve(s, 0.6),
    "gamma1.6": lambda s: display_curve(s, 1.6),
    "tgc-deep-dark": lambda s: depth_gain(s, 1.3, 0.6),
    "tgc-deep-bright": lambda s: depth_gain(s, 0.7, 1.4),
    "smooth0.15mm": lambda s: smooth(s, 0.15),
    "noise12": lambda s: add_noise(s, 12.0, seed=3),
}


#: Augmentations that give a recording the hard cadaver levels of issue 10 (see
#: :func:`harden`): the echo compressed to 1.3x the tissue, the shadow lifted to 0.65
#: of the tissue at its depth with reverberation bands, and each alone. Kept apart from
#: :data:`RECORDING_AUGMENTATIONS` (which the segmenter already holds on).
HARD_AUGMENTATIONS: dict[str, Callable[[Sweep], Sweep]] = {
    "low-contrast": lambda s: harden(s, shadow_ratio=None, reverb=0.0),
    "grey-shadow": lambda s: harden(s, echo_ratio=None),
    "hard": lambda s: harden(s),
}


# -- Look-alikes drawn into a recording (issue 10, item 2) -------------------------------
#
# The simulator's look-alikes (``realism="hard"``: a skin line over a no-contact gap, a
# fascia off the crest, a vessel) tested on real texture: each is drawn into a recorded
# sweep with the simulator's geometry (:class:`~.params.HardParams`) and with grey levels
# taken from the recording itself (its brightest echo, its bone echo, its darkest
# imaged grey), never absolute greys. The bone stays where it was, so the reference
# contours score the copy as they score the recording. Lines are drawn as Gaussian
# profiles across, with a texture correlated along them (a specular line is not
# speckle), composited with ``max`` (a bright line hides what lies under it).

_HARD = HardParams()


def _frame_echo_grey(img: np.ndarray, contour: np.ndarray, sp: float) -> float:
    """The bone echo's grey in one frame: :func:`~.levels.echo_levels`' ``echo`` (the
    brightest grey within 0.15 mm of each contour point, median); NaN if unmeasurable."""
    return float(echo_levels(img[None], [contour], sp)["echo"])


def _line_texture(rng: np.random.Generator, n: int, width: int, sp: float) -> np.ndarray:
    """(n, width) gain of mean 1 varying along a line over ~1 mm (std 0.25, >= 0.3)."""
    t = np.stack([smooth_noise(rng, width, max(1.0, 1.0 / sp)) for _ in range(n)])
    return np.clip(1.0 + 0.25 * t, 0.3, None).astype(np.float32)


def _band_profile(rows: np.ndarray, centre: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian profile across a line: ``rows`` (H, 1), ``centre`` (..., W) -> (..., H, W)."""
    return np.exp(-0.5 * ((rows - centre[..., None, :]) / sigma) ** 2).astype(np.float32)


def _check_side(side: int) -> None:
    if side not in (1, -1):
        raise ValueError(f"side must be 1 (the last columns) or -1 (the first), got {side!r}")


def _sorted_contour(c: np.ndarray) -> np.ndarray:
    c = np.asarray(c, float).reshape(-1, 2)
    return c[np.argsort(c[:, 0], kind="stable")]


def _drawn_frames(
    bone_contours: Mapping[int, np.ndarray], n: int
) -> Iterator[tuple[int, np.ndarray]]:
    """The frames of a sweep of ``n`` frames that a look-alike is drawn in: those with a
    contour of 3 points or more, each with its contour sorted by column."""
    for k, c in bone_contours.items():
        c = _sorted_contour(c)
        if 0 <= k < n and c.shape[0] >= 3:
            yield k, c


def no_contact(
    sweep: Sweep,
    *,
    side: int = 1,
    share: float = _HARD.gap_fraction,
    depth_mm: float = _HARD.gap_depth_mm,
    copies: int = _HARD.gap_copies,
    decay: float = _HARD.gap_decay,
    transmission: float = _HARD.gap_transmission,
    line_mm: float = 0.4,
    seed: int = 0,
) -> Sweep:
    """The probe loses contact at one lateral edge: issue 10's second cadaver pass, where
    two thirds of the frames took this skin line for the bone.

    Over the outer ``share`` of the imaged width on ``side`` (+1: the last columns; -1:
    the first), varying smoothly along the sweep (+-15 %), the skin curves away from the
    probe face, ``1.2 + depth_mm u**2`` mm under it (``u`` 0 -> 1 across the gap, 1 at
    the edge). Above the skin the gap returns nothing: the
    recording's own darkest imaged grey (2nd percentile), textured. The skin line is as
    bright as the frame's brightest echo (99.9th percentile of its imaged pixels: the
    level a line must reach to pass for bone, whatever the gain), and ``copies``
    reverberation copies lie under it at 2, 3, ... times its depth below the probe face
    (sound bouncing between the face and the skin), each ``decay`` of the previous. The
    tissue under the skin is dimmed to ``transmission`` of its grey (poor coupling).
    Geometry and levels are the simulator's ``skin_gap`` (:class:`~.params.HardParams`);
    the bone is not moved (the skin lifts off it), so reference contours still hold
    where it is shown.
    """
    _check_side(side)
    f = np.asarray(sweep.frames, np.float32)
    n, h, w = f.shape
    sp = float(np.mean(sweep.spacing_mm))
    lit = _lit(f)
    rows_lit, cols_lit = np.flatnonzero(lit.any(1)), np.flatnonzero(lit.any(0))
    if rows_lit.size == 0:
        return sweep
    top, c0, c1 = float(rows_lit[0]), float(cols_lit[0]), float(cols_lit[-1])
    rng = np.random.default_rng(seed)
    width = np.clip(share * (1.0 + 0.15 * smooth_noise(rng, n, max(1.0, n / 6))), 0.05, 0.45)
    width = width * (c1 - c0)
    cols = np.arange(w, dtype=np.float32)[None, :]
    u = (cols - (c1 - width[:, None])) if side > 0 else ((c0 + width[:, None]) - cols)
    u = np.clip(u / width[:, None], 0.0, 1.0)
    gap = (u > 0)[:, None, :]
    skin = top + (1.2 + depth_mm * u**2) / sp  # (n, w) rows
    rows = np.arange(h, dtype=np.float32)[:, None]
    above = gap & (rows[None] < skin[:, None, :])
    floor = np.float32(np.percentile(f[:, lit], 2.0))
    speckle = rng.gamma(4.0, 0.25, f.shape).astype(np.float32)
    out = np.where(above, floor * speckle, np.where(gap, f * np.float32(transmission), f))
    sigma = max(line_mm / sp, 1.0)
    line = np.zeros_like(f)
    for m in range(1, copies + 2):
        prof = _band_profile(rows, top + m * (skin - top), sigma)
        line = np.maximum(line, np.float32(decay ** (m - 1)) * prof)
    bright = np.array([np.percentile(f[k][lit], 99.9) for k in range(n)], np.float32)
    tex = _line_texture(rng, n, w, sp)[:, None, :]
    out = np.maximum(out, np.where(gap, line * bright[:, None, None] * tex, 0.0))
    return _in_field(sweep, out, lit)


def add_fascia(
    sweep: Sweep,
    bone_contours: Mapping[int, np.ndarray],
    *,
    side: int = 1,
    attach_mm: float = _HARD.fascia_attach_mm,
    length_mm: float = _HARD.fascia_length_mm,
    slope: float = _HARD.fascia_slope,
    strength: float = 1.0,
    line_mm: float = 0.3,
    seed: int = 0,
) -> Sweep:
    """A bright fascia leaving the bone's flank at the bone's level: issue 10's cadaver,
    where "bright fascia runs off the crest at the bone's level".

    In each frame with a contour (``(M, 2)`` pixels ``(i, j)``: the reference contours),
    the fascia leaves the flank on ``side`` (+1: towards larger columns) where it lies
    ``attach_mm`` under the bone's top and runs ``length_mm`` outward, descending
    ``slope`` mm per mm (wandering +-0.02 along the sweep), fading in over its first mm
    and out over its last 3, as the simulator's ``fascia``. Its grey is ``strength``
    times this frame's own bone echo grey (:func:`_frame_echo_grey`; the cadaver: a
    fascia as bright as the bone). Beneath it lies what the recording has there: tissue
    over the flank, the bone's shadow farther in.
    """
    _check_side(side)
    f = np.asarray(sweep.frames, np.float32)
    n, h, w = f.shape
    sp = float(np.mean(sweep.spacing_mm))
    lit = _lit(f)
    rng = np.random.default_rng(seed)
    wiggle = smooth_noise(rng, n, max(1.0, n / 6))
    tex = _line_texture(rng, n, w, sp)
    rows = np.arange(h, dtype=np.float32)[:, None]
    cols = np.arange(w, dtype=np.float32)
    out = f.copy()
    for k, c in _drawn_frames(bone_contours, n):
        jtop = float(c[:, 1].min())
        apex = float(c[np.argmin(c[:, 1]), 0])
        outward = c[(c[:, 0] - apex) * side > 0][:: 1 if side > 0 else -1]
        hit = outward[outward[:, 1] >= jtop + attach_mm / sp]
        grey = _frame_echo_grey(f[k], c, sp)
        if hit.shape[0] == 0 or not np.isfinite(grey):
            continue
        i0, j0 = hit[0]
        run = (cols - i0) * side  # columns outward from where it leaves the bone
        on = (run >= 0) & (run * sp <= length_mm)
        fj = j0 + run * (slope + 0.02 * wiggle[k])
        fade = np.clip(run * sp, 0.3, 1.0) * np.clip((length_mm - run * sp) / 3.0, 0.0, 1.0)
        amp = np.where(on, strength * grey * fade * tex[k], 0.0).astype(np.float32)
        out[k] = np.maximum(out[k], amp[None, :] * _band_profile(rows, fj, max(line_mm / sp, 1.0)))
    return _in_field(sweep, out, lit)


def add_vessel(
    sweep: Sweep,
    bone_contours: Mapping[int, np.ndarray],
    *,
    lateral_mm: float = 3.0,
    gap_mm: float = 3.0,
    radius_mm: float = _HARD.vessel_radius_mm,
    wall: float = 0.8,
    enhancement: float = 1.3,
    enhancement_mm: float = _HARD.vessel_enhancement_mm,
    ringdown_mm: float = _HARD.ringdown_mm,
    copies: int = _HARD.ringdown_copies,
    decay: float = _HARD.ringdown_decay,
    seed: int = 0,
) -> Sweep:
    """A vessel lying on the bone (the radial artery on the distal radius, the tibial
    vessels beside the tibia): a dark round lumen with bright walls, posterior
    enhancement and ring-down under its back wall.

    Per frame with a contour, the lumen (``radius_mm``) lies ``lateral_mm`` from the
    bone's top towards larger columns (negative: smaller), its back wall ``gap_mm`` over
    the bone there (3 mm: a thin muscle between, as the pronator quadratus under the
    radial artery; frames with no room above the bone get none). The lumen returns the recording's
    own darkest imaged grey (2nd percentile), textured; its front and back walls are
    specular where the beam meets them square, at ``wall`` times the frame's bone echo
    grey; the tissue under the lumen (the bone's echo included) is brightened up to
    ``enhancement`` (grey gain) fading over ``enhancement_mm``; ``copies`` ring-down
    lines follow the back wall every ``ringdown_mm``, each ``decay`` of the previous.
    Geometry as the simulator's ``vessel`` (:class:`~.params.HardParams`), placed over
    the bone rather than beside it (a recording's bone may fill its width).
    """
    f = np.asarray(sweep.frames, np.float32)
    n, h, w = f.shape
    sp = float(np.mean(sweep.spacing_mm))
    lit = _lit(f)
    rows_lit = np.flatnonzero(lit.any(1))
    if rows_lit.size == 0:
        return sweep
    rng = np.random.default_rng(seed)
    floor = np.float32(np.percentile(f[:, lit], 2.0))
    r = radius_mm / sp
    rows = np.arange(h, dtype=np.float32)[:, None]
    cols = np.arange(w, dtype=np.float32)[None, :]
    sigma = max(0.3 / sp, 1.0)
    out = f.copy()
    for k, c in _drawn_frames(bone_contours, n):
        ci = float(c[np.argmin(c[:, 1]), 0]) + lateral_mm / sp
        if not c[0, 0] <= ci <= c[-1, 0]:
            continue
        cj = float(np.interp(ci, c[:, 0], c[:, 1])) - gap_mm / sp - r
        grey = _frame_echo_grey(f[k], c, sp)
        if cj - r < rows_lit[0] + 1.0 / sp or not np.isfinite(grey):
            continue
        dx, dy = cols - ci, rows - cj
        inside = dx**2 + dy**2 < r**2
        half = np.sqrt(np.clip(r**2 - dx**2, 0.0, None))  # (1, w): lumen half-height
        across = np.clip(1.0 - (dx / r) ** 2, 0.0, 1.0)
        below = np.clip((dy - half) * sp / enhancement_mm, 0.0, None)
        gain = 1.0 + (enhancement - 1.0) * across * np.exp(-below) * (dy > half)
        img = np.where(inside, floor * rng.gamma(4.0, 0.25, (h, w)), f[k] * gain)
        face = np.where(np.abs(dx) < 0.9 * r, np.sqrt(across), 0.0)[0]  # specular walls
        lines = [(cj - half[0], 1.0)] + [
            (cj + half[0] + m * ringdown_mm / sp, decay**m) for m in range(copies + 1)
        ]
        for row, a in lines:
            amp = (wall * grey * a * face).astype(np.float32)
            img = np.maximum(img, amp[None, :] * _band_profile(rows, row, sigma))
        out[k] = img
    return _in_field(sweep, out, lit)


def add_muscle(
    sweep: Sweep,
    bone_contours: Mapping[int, np.ndarray],
    *,
    ratio: float = 0.7,
    gap_mm: float = 1.0,
    thickness_mm: float = 9.0,
    beyond_mm: float = 5.0,
    edge_mm: float = 1.0,
    fascia: float = 0.0,
    line_mm: float = 0.3,
    along: tuple[float, float] = (0.0, 1.0),
    seed: int = 0,
) -> Sweep:
    """A hypoechoic muscle lying on the bone (the pronator quadratus on the distal radius
    and ulna, the brachialis on the humerus, the supinator on the radius): a band of
    tissue over the bone darker than the rest of the frame's soft tissue.

    Per frame with a contour, the band runs from ``gap_mm`` to ``gap_mm + thickness_mm``
    over the bone, following its outline (level with the contour's ends past them) and
    ``beyond_mm`` past its ends; its grey is the recording's own times ``ratio`` (its
    texture kept: a muscle is speckle at a lower level, not a shadow's floor), the
    edges softened over ``edge_mm``. ``fascia`` > 0 also draws the muscle's fascia along
    the band's top at that share of the frame's bone echo grey (:func:`_frame_echo_grey`):
    a bright line over a darker band, the shape of a bone's echo over its shadow.
    Beside the band, at the same depths, the tissue keeps the recording's level.
    ``along``: the stretch of the sweep the muscle covers, as shares of its frames
    (``(0, 0.4)``: the first 40 %, as the pronator quadratus covers the distal 4-6 cm
    of a forearm sweep); the frames outside it are left as they are.
    """
    if not 0.0 <= along[0] < along[1] <= 1.0:
        raise ValueError(f"along must be 0 <= start < end <= 1, got {along}")
    f = np.asarray(sweep.frames, np.float32)
    n, h, w = f.shape
    sp = float(np.mean(sweep.spacing_mm))
    lit = _lit(f)
    rng = np.random.default_rng(seed)
    tex = _line_texture(rng, n, w, sp)
    rows = np.arange(h, dtype=np.float32)[:, None]
    cols = np.arange(w, dtype=np.float32)
    out = f.copy()
    for k, c in _drawn_frames(bone_contours, n):
        if not along[0] * n <= k < along[1] * n:
            continue
        bone = np.interp(cols, c[:, 0], c[:, 1]).astype(np.float32)  # level past the ends
        # mm over the bone at each pixel, and laterally outside the contour's ends.
        over = (bone[None, :] - rows) * sp
        past = np.maximum(c[0, 0] - cols, cols - c[-1, 0]) * sp - beyond_mm
        lateral = np.clip(0.5 - past / edge_mm, 0.0, 1.0)
        inside = (
            np.clip((over - gap_mm) / edge_mm + 0.5, 0.0, 1.0)
            * np.clip((gap_mm + thickness_mm - over) / edge_mm + 0.5, 0.0, 1.0)
            * lateral[None, :]
        )
        img = f[k] * (1.0 - (1.0 - ratio) * inside)
        grey = _frame_echo_grey(f[k], c, sp) if fascia > 0 else np.nan
        if np.isfinite(grey):
            top = bone - (gap_mm + thickness_mm) / sp
            amp = fascia * grey * tex[k] * lateral
            img = np.maximum(img, amp[None, :] * _band_profile(rows, top, max(line_mm / sp, 1.0)))
        out[k] = img
    return _in_field(sweep, out, lit)


#: The look-alikes of issue 10 drawn into a recording with its reference contours
#: (``(sweep, contours) -> sweep``), each alone (the vessel also 1 mm over the bone: its
#: lumen right over it) and the first three at once; with the cadaver's levels
#: (:func:`harden`) they make the hardest copy of a recording we can score. Also a
#: hypoechoic muscle on the bone (0.7 of the tissue's grey), and darker (0.6) under its
#: own fascia as bright as the bone: a bright line over a darker band, over the bone;
#: each also over one end of the sweep only (``-end``: the first 40 %, as the pronator
#: quadratus over a forearm's distal end; with the fascia, the last half, the fascia
#: 1.5 times as bright as the bone), where the frames with the muscle differ from the
#: sweep's typical frame and the bone is carried by the frames without it; and that
#: fascia over the whole sweep (``muscle-bright-fascia``: a bright arch over a dark
#: band in every frame, the bone under it dimmer than the arch).
LOOKALIKE_AUGMENTATIONS: dict[str, Callable[[Sweep, Mapping[int, np.ndarray]], Sweep]] = {
    "no-contact": lambda s, c: no_contact(s, side=1),
    "no-contact-left": lambda s, c: no_contact(s, side=-1),
    "fascia": lambda s, c: add_fascia(s, c, side=1),
    "vessel": lambda s, c: add_vessel(s, c),
    "vessel-on-bone": lambda s, c: add_vessel(s, c, gap_mm=1.0),
    "lookalikes": lambda s, c: no_contact(add_vessel(add_fascia(s, c, side=-1), c), side=1),
    "muscle": lambda s, c: add_muscle(s, c),
    "muscle-fascia": lambda s, c: add_muscle(s, c, ratio=0.6, fascia=1.0),
    "muscle-end": lambda s, c: add_muscle(s, c, along=(0.0, 0.4)),
    "muscle-fascia-end": lambda s, c: add_muscle(s, c, ratio=0.6, fascia=1.5, along=(0.5, 1.0)),
    "muscle-bright-fascia": lambda s, c: add_muscle(s, c, ratio=0.6, fascia=1.5),
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

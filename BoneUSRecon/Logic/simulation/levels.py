"""Grey levels around a bone contour: echo, tissue above, shadow, tissue beside.

The measurements of issue 10 (on a real cadaver sweep: the echo ~1.35x the grey of the
tissue just above it, the shadow ~0.40 of the echo and ~0.65 of the tissue beside it at
the same depth), made the same way on any image with a known bone contour: the
simulator's true contours, or the reference contours of the real recordings
(``Testing/data/``). Used to check that the ``hard`` preset and the real-recording
augmentations hit those levels. Ratios of grey values, as the issue measured them, not
absolute greys: they hold for any gain.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

__all__ = ["echo_levels"]


def _band(
    img: np.ndarray, ii: np.ndarray, jj: np.ndarray, mm: tuple[float, float], sign: int, sp: float
) -> np.ndarray:
    """Grey values from ``mm[0]`` to ``mm[1]`` above (``sign`` -1) or below (+1) each point."""
    offs = sign * np.arange(int(round(mm[0] / sp)), int(round(mm[1] / sp)) + 1)
    rows = jj[:, None] + offs[None, :]
    ok = (rows >= 0) & (rows < img.shape[0])
    return img[rows[ok], np.broadcast_to(ii[:, None], rows.shape)[ok]]


def echo_levels(
    frames: np.ndarray,
    contours_px: Sequence[np.ndarray],
    spacing_mm: float,
    *,
    above_mm: tuple[float, float] = (1.0, 3.0),
    below_mm: tuple[float, float] = (1.5, 8.0),
    beside_gap_mm: float = 3.0,
) -> dict[str, float]:
    """Median grey levels round the bone contours of a sweep, and their ratios.

    Per frame with a contour (``(K, 2)`` pixels ``(i, j)``):

    * ``echo``: the brightest grey within +-0.15 mm (at least one row) of each contour
      point (the echo's peak is on the surface; speckle moves it by a row), median;
    * ``above``: the tissue ``above_mm`` (from, to) above the contour, median;
    * ``shadow``: ``below_mm`` below the contour (past the echo's tail), median;
    * ``beside``: the same rows as the shadow at the contour's median depth, in the
      columns at least ``beside_gap_mm`` from the contour's ends and not black
      (scan-conversion margins), median.

    Returns
    -------
    dict
        Medians over frames of ``echo``, ``above``, ``shadow``, ``beside`` and of the
        per-frame ratios ``echo_to_above``, ``shadow_to_echo``, ``shadow_to_beside``;
        ``frames``: how many frames were measured. NaN where nothing could be measured.
    """
    frames = np.asarray(frames)
    _, h, w = frames.shape
    sp = float(spacing_mm)
    r = max(1, int(round(0.15 / sp)))
    per: dict[str, list[float]] = {k: [] for k in ("echo", "above", "shadow", "beside")}
    for k, c in enumerate(contours_px):
        c = np.asarray(c, float)
        if c.shape[0] < 3:
            continue
        img = frames[k]
        ii = np.clip(np.rint(c[:, 0]).astype(int), 0, w - 1)
        jj = np.rint(c[:, 1]).astype(int)

        rows = jj[:, None] + np.arange(-r, r + 1)[None, :]
        ok = (rows >= 0) & (rows < h)
        peak = np.where(ok, img[np.clip(rows, 0, h - 1), ii[:, None]], 0).max(1)
        above = _band(img, ii, jj, above_mm, -1, sp)
        shadow = _band(img, ii, jj, below_mm, 1, sp)
        jm = int(np.median(jj))
        r0, r1 = np.clip(
            [jm + int(round(below_mm[0] / sp)), jm + int(round(below_mm[1] / sp)) + 1], 0, h
        )
        gap = int(round(beside_gap_mm / sp))
        cols = np.arange(w)
        side = (cols < ii.min() - gap) | (cols > ii.max() + gap)
        block = img[r0:r1][:, side]
        lit = block[:, block.max(0) > 0] if block.size else block
        per["echo"].append(float(np.median(peak)))
        per["above"].append(float(np.median(above)) if above.size else np.nan)
        per["shadow"].append(float(np.median(shadow)) if shadow.size else np.nan)
        per["beside"].append(float(np.median(lit)) if lit.size else np.nan)
    a = {k: np.array(v, float) for k, v in per.items()}
    out = {
        name: float(np.nanmedian(v)) if np.isfinite(v).any() else np.nan for name, v in a.items()
    }
    with np.errstate(divide="ignore", invalid="ignore"):
        ratios = {
            "echo_to_above": a["echo"] / a["above"],
            "shadow_to_echo": a["shadow"] / a["echo"],
            "shadow_to_beside": a["shadow"] / a["beside"],
        }
    for name, r in ratios.items():
        r = r[np.isfinite(r)]
        out[name] = float(np.median(r)) if r.size else np.nan
    out["frames"] = float(a["echo"].size)
    return out

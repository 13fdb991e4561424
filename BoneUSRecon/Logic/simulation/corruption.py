"""Corrupted frames: the three ways a per-frame bone segmenter is fooled.

* ``shadow_clutter``: bright clutter and a reverberation copy of the bone echo inside
  the acoustic shadow (the paper's false positives: "important noise on the acoustic
  shadow under the bone"). The bone is still visible.
* ``false_echo``: a bright, bone-like curved echo above the bone, casting its own
  shadow (a calcification, a gas bubble, a tendon seen at normal incidence). The bone
  below is dimmed but still there.
* ``contact_loss``: the probe lifts off the skin: a dark frame with near-field
  reverberation bands and no bone.

The functions act on one frame's complex echo field (before gain and log compression),
so the corrupted frames go through the same speckle and display chain as the others.
"""

from __future__ import annotations

import numpy as np

from BoneUSRecon.Logic.simulation.params import CORRUPTION_KINDS

__all__ = ["choose_corrupted", "shadow_clutter", "false_echo", "contact_loss"]

# Frames at the very start are never corrupted: a segmenter (the paper's snake) starts
# from the first frames, and an operator starts recording with the bone in view.
_CLEAN_START = 2


def choose_corrupted(n_frames: int, fraction: float, rng: np.random.Generator) -> dict[int, str]:
    """Pick ``round(fraction * n_frames)`` frames and a kind for each.

    Kinds are drawn in turn from a shuffled cycle of :data:`CORRUPTION_KINDS`, so that
    each kind is represented as soon as there are three corrupted frames.

    Returns
    -------
    dict
        ``{frame index: kind}`` sorted by frame.
    """
    count = int(round(fraction * n_frames))
    pool = np.arange(min(_CLEAN_START, n_frames), n_frames)
    count = min(count, pool.size)
    if count <= 0:
        return {}
    frames = np.sort(rng.choice(pool, size=count, replace=False))
    kinds = [CORRUPTION_KINDS[i] for i in rng.permutation(len(CORRUPTION_KINDS))]
    return {int(f): kinds[i % len(kinds)] for i, f in enumerate(frames)}


def _rows(height: int) -> np.ndarray:
    return np.arange(height, dtype=np.float32)[:, None]


def shadow_clutter(
    field: np.ndarray,
    speckle: np.ndarray,
    top_j: np.ndarray,
    bone_line: np.ndarray,
    spacing: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Fill part of the shadow with bright clutter and a reverberation of the bone line.

    Parameters
    ----------
    field : complex ndarray (H, W)
        The frame's echo field, shadow applied.
    speckle : complex ndarray (H, W)
        Unit-RMS speckle (not shadowed), used as the clutter's texture.
    top_j : ndarray (W,)
        Bone row per column (NaN: no bone).
    bone_line : complex ndarray (H, W)
        The bone echo alone; a shifted, weaker copy is the reverberation.
    spacing : float
        mm per pixel.
    """
    h, w = field.shape
    present = np.isfinite(top_j)
    if not present.any():
        return field
    cols = np.flatnonzero(present)
    top = np.where(present, top_j, np.inf)
    rows = _rows(h)
    i = np.arange(w, dtype=np.float32)[None, :]
    below = (rows > top[None, :] + 1.0 / spacing) & present[None, :]
    clutter = np.full((h, w), 0.4, np.float32)  # raised noise over the whole shadow
    for _ in range(int(rng.integers(2, 6))):
        ic = rng.uniform(cols[0], cols[-1])
        jc = np.interp(ic, cols, top_j[cols]) + rng.uniform(1.5, 8.0) / spacing
        si = rng.uniform(1.0, 3.0) / spacing
        sj = rng.uniform(0.4, 1.5) / spacing
        clutter += rng.uniform(2.0, 5.0) * np.exp(
            -0.5 * (((i - ic) / si) ** 2 + ((rows - jc) / sj) ** 2)
        )
    out = field + speckle * clutter * below
    # Reverberation: a fainter copy of the bone echo 2-5 mm deeper.
    shift = int(round(rng.uniform(2.0, 5.0) / spacing))
    if shift < h:
        rev = np.zeros_like(bone_line)
        rev[shift:] = bone_line[: h - shift]
        out = out + rng.uniform(0.3, 0.6) * rev
    return out


def false_echo(
    field: np.ndarray,
    top_j: np.ndarray,
    skin_px: float,
    amplitude: float,
    line_sigma_px: float,
    spacing: float,
    rng: np.random.Generator,
) -> np.ndarray:
    """Add a bright bone-like arc above the bone, with its own acoustic shadow.

    Parameters
    ----------
    field : complex ndarray (H, W)
        The frame's echo field, bone echo included (the false echo's shadow dims it).
    top_j : ndarray (W,)
    skin_px : float
        Depth of the skin line (rows): the echo lies below it.
    amplitude : float
        Bone echo amplitude at normal incidence; the false echo gets 60-100 % of it.
    line_sigma_px : float
        Axial sigma of the echo line (rows).
    """
    h, w = field.shape
    present = np.isfinite(top_j)
    top_min = float(np.nanmin(top_j)) if present.any() else 0.6 * h
    cols = np.flatnonzero(present) if present.any() else np.arange(w)
    ic = rng.uniform(cols[0], cols[-1])
    half = rng.uniform(0.12, 0.3) * w
    # Between the skin and the bone, in the lower half of that gap when there is room.
    lo = skin_px + 1.0 / spacing
    hi = max(lo, top_min - 1.5 / spacing)
    jc = rng.uniform(0.5 * (lo + hi), hi) if hi > lo else lo
    i = np.arange(w, dtype=np.float32)
    x = (i - ic) / half
    taper = np.sqrt(np.clip(1.0 - x**2, 0.0, 1.0))  # fades at both ends, like bone edges
    jf = jc + rng.uniform(0.5, 2.0) / spacing * x**2  # convex-up, like the top of a bone
    rows = _rows(h)
    d = rows - jf[None, :]
    amp = rng.uniform(0.6, 1.0) * amplitude * taper
    phase = np.exp(1j * rng.uniform(0, 2 * np.pi))
    line = (amp[None, :] * np.exp(-0.5 * (d / line_sigma_px) ** 2) * phase).astype(np.complex64)
    dim = rng.uniform(0.7, 0.9)
    shadow = 1.0 - dim * taper[None, :] * np.clip(
        (d - 2 * line_sigma_px) / max(line_sigma_px, 1.0) + 0.5, 0.0, 1.0
    )
    return field * shadow.astype(np.float32) + line


def contact_loss(
    shape: tuple[int, int], speckle: np.ndarray, spacing: float, rng: np.random.Generator
) -> np.ndarray:
    """The field of a frame with the probe off the skin: reverberation bands in the dark.

    Parameters
    ----------
    shape : (H, W)
    speckle : complex ndarray (H, W)
        Unit-RMS speckle, used to texture the bands.
    """
    h, w = shape
    rows = _rows(h)
    period = rng.uniform(1.0, 2.0) / spacing  # transducer-lens ringing, ~1-2 mm apart
    sigma = max(0.15 / spacing, 0.7)
    bands = np.zeros((h, 1), np.float32)
    for m in range(1, 12):
        bands += 4.0 * 0.6 ** (m - 1) * np.exp(-0.5 * ((rows - m * period) / sigma) ** 2)
    # Partial contact varies across the face: a smooth lateral modulation.
    x = np.linspace(0, 1, w, dtype=np.float32)[None, :]
    lateral = 0.6 + 0.4 * np.cos(2 * np.pi * (x * rng.uniform(0.3, 1.2) + rng.uniform(0, 1)))
    return (0.1 * speckle + bands * lateral * (0.6 + 0.4 * np.abs(speckle))).astype(np.complex64)

"""What a per-frame segmenter returns, before confidence and rejection."""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

__all__ = ["Detection", "empty_detection"]


@dataclass(frozen=True, eq=False)
class Detection:
    """A bone contour found in one frame.

    Parameters
    ----------
    points_px : ndarray, shape (K, 2)
        ``(i, j)`` = (column, row), sub-pixel, ordered by increasing ``i``.
    intensity : ndarray, shape (K,)
        Grey value (0..255) of the image at each point.
    extras : dict
        Segmenter-specific diagnostics (snake energies, iterations, ...).
    """

    points_px: np.ndarray
    intensity: np.ndarray
    extras: dict = field(default_factory=dict)

    @property
    def empty(self) -> bool:
        """True when no point was found."""
        return self.points_px.shape[0] == 0


def empty_detection(**extras: object) -> Detection:
    """A detection with no points."""
    return Detection(np.empty((0, 2)), np.empty(0), dict(extras))


def sample_bilinear(image: np.ndarray, ij: np.ndarray) -> np.ndarray:
    """Bilinear sample of ``image`` (H, W) at sub-pixel ``(i, j)`` points, clamped to the image."""
    h, w = image.shape
    i = np.clip(ij[:, 0], 0, w - 1)
    j = np.clip(ij[:, 1], 0, h - 1)
    i0 = np.minimum(np.floor(i).astype(np.intp), w - 2 if w > 1 else 0)
    j0 = np.minimum(np.floor(j).astype(np.intp), h - 2 if h > 1 else 0)
    fi = i - i0
    fj = j - j0
    i1 = np.minimum(i0 + 1, w - 1)
    j1 = np.minimum(j0 + 1, h - 1)
    a = image[j0, i0] * (1 - fi) + image[j0, i1] * fi
    b = image[j1, i0] * (1 - fi) + image[j1, i1] * fi
    return (a * (1 - fj) + b * fj).astype(np.float64)

"""The result of a registration and its quality figures."""

from __future__ import annotations

from dataclasses import asdict, dataclass, field
from typing import Any

import numpy as np

__all__ = ["Registration"]


@dataclass(frozen=True, eq=False)
class Registration:
    """A rigid registration and its quality figures (mm unless said).

    Attributes
    ----------
    matrix : ndarray (4, 4)
        SOURCE -> TARGET (``x_target = matrix @ x_source``, homogeneous, mm).
    initial : ndarray (4, 4)
        The initial alignment ICP started from.
    rms_mm, median_mm, p95_mm : float
        Point-to-plane residuals of the inliers at the end.
    inlier_share : float
        Share of the source points kept by the robust weights and the distance gate.
    n_source, n_inliers : int
    iterations : int
    converged : bool
        The last step moved no point by more than the tolerance.
    eigenvalues : ndarray (6,)
        Of the normalised 6x6 point-to-plane normal matrix, increasing (unitless:
        mean squared residual change per squared mm of motion; rotations in mm at the
        source's RMS radius).
    condition : float
        Largest over smallest eigenvalue.
    sliding_mm : ndarray (6,)
        For each eigen-direction, the motion (mm) that grows the residual RMS by
        ``sqrt(2)``: ``residual / sqrt(eigenvalue)``.
    directions : tuple of str
        Each eigen-direction in words (``"translation along the bone's long axis"``).
    reliable : bool
        No reason below.
    reasons : tuple of str
        Why the result should not be trusted (weak directions named), empty if reliable.
    landmark_rms_mm : float or None
        Fiducial registration error of the landmarks (their RMS residual) when used.
    long_axis : ndarray (3,)
        The source's principal direction (its long axis), in source coordinates.
    seconds : float
    """

    matrix: np.ndarray
    initial: np.ndarray
    rms_mm: float
    median_mm: float
    p95_mm: float
    inlier_share: float
    n_source: int
    n_inliers: int
    iterations: int
    converged: bool
    eigenvalues: np.ndarray
    condition: float
    sliding_mm: np.ndarray
    directions: tuple[str, ...]
    reliable: bool
    reasons: tuple[str, ...]
    landmark_rms_mm: float | None = None
    long_axis: np.ndarray = field(default_factory=lambda: np.zeros(3))
    seconds: float = 0.0

    def as_dict(self) -> dict[str, Any]:
        """Plain-Python summary (strict JSON: an unbounded sliding range or condition
        is ``None``, as JSON has no infinity)."""

        def plain(v: Any) -> Any:
            if isinstance(v, (np.ndarray, list, tuple)):
                return [plain(x) for x in (v.tolist() if isinstance(v, np.ndarray) else v)]
            if isinstance(v, (float, np.floating)):
                return float(v) if np.isfinite(v) else None
            return v

        return {k: plain(v) for k, v in asdict(self).items()}

    def summary_rows(self) -> list[tuple[str, str]]:
        """``(key, value)`` lines for a human summary (CLI, Slicer panel)."""
        weak = int(np.argmin(self.eigenvalues))
        rows = [
            (
                "residual RMS/median/p95",
                f"{self.rms_mm:.3f} / {self.median_mm:.3f} / {self.p95_mm:.3f} mm",
            ),
            ("inliers", f"{self.n_inliers} of {self.n_source} ({100 * self.inlier_share:.1f}%)"),
            ("iterations", f"{self.iterations}{'' if self.converged else ' (not converged)'}"),
            (
                "weakest direction",
                f"{self.directions[weak]}: slides {fmt_mm(self.sliding_mm[weak])}",
            ),
            ("condition", f"{self.condition:.3g}"),
        ]
        if self.landmark_rms_mm is not None:
            rows.append(("landmark RMS", f"{self.landmark_rms_mm:.3f} mm"))
        rows.append(("reliable", "yes" if self.reliable else "NO: " + "; ".join(self.reasons)))
        return rows


def fmt_mm(v: float) -> str:
    return "unbounded" if not np.isfinite(v) or v > 1e4 else f"{v:.2f} mm"

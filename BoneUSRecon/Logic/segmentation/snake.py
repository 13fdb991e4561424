"""The paper's open snake (section II.B), every part, as a graph over the lateral axis.

Energy (in reference pixels, see :mod:`.params`; grey values divided by 255)::

    E = sum_i w1 |y_{i+1} - y_i|^2 + w2 |y_{i+1} - 2 y_i + y_{i-1}|^2     (eq. 1)
      + sum_i k_regional * E_R(v_i)                                        (eq. 3)
      + sum_i u k1 y_i                                                     (balloon, eq. 2)

Reading of the garbled eq. (3): ``E_R(v) = -Dif(v)`` where ``Dif(v) >= 0`` and the
constant ``k`` (taken as 0) where ``Dif(v) < 0``. Minimising ``-Dif`` puts the contour
"in the centre of the dark-bright-dark region", as the text says; the printed equation
lost the minus sign. ``Dif = 2 M_mid - M_up - M_down`` uses region heights in mm
(:class:`~.params.SnakeParams`), and the potential ``P`` is the positive part of
``Dif`` smoothed by a Gaussian of ``smooth_mm`` (so ``E_R = -P``: the smoothing gives
the thin echo a basin of attraction a few tenths of a mm wide).

Scaling, so the paper's numbers keep their meaning on any image: positions and
differences are in reference pixels of 0.1 mm (the paper's "pixels"), whatever the
recording's pixel size, so eq. (1) with w1 = 1, w2 = 2.5 penalises the same shapes on a
0.05 and a 0.15 mm/px image; intensities are grey/255, so ``Dif`` is in [-2, 2] and
does not depend on the gain's absolute scale; k1, k2 multiply unit vectors and are in
``force_unit`` reference pixels per unit time (their ratio is the paper's). The paper
gives no weight for ``E_R``; ``k_regional`` is ours, chosen (with ``tau``) so that the
echo holds the snake against the balloon and the tension of the free parts.

Balloon (eq. 2): ``k1 N + k2 grad P / |grad P|``, both in units of ``force_unit``
reference pixels per unit time, so the paper's 1000:1 ratio of k1 to k2 is kept. The
contour's normal ``N`` points towards the transducer (the snake starts below the bone,
in its shadow, and is inflated upwards until the bone's echo holds it, as in the
paper's initialisation "50 px below" the previous contour). Because the points move
along depth only, the normal push is its depth component, which is the gradient of the
pressure potential ``u k1 y`` in the energy above (the swept area times the pressure).
The ``k2`` term is not the gradient of an energy; it is 1/1000 of the balloon and left
out of the recorded energy.

Minimisation (semi-implicit finite differences): ``(I + tau A) y' = y + tau F(y)``
with ``A`` the pentadiagonal matrix of eq. (1) with free ends (``A = 2 (w1 D1'D1 + w2
D2'D2)``, D1, D2 the first and second difference matrices), Cholesky-factorised once
per frame (:func:`scipy.linalg.cholesky_banded`) and solved in O(n) per iteration.
Each step is capped at ``max_step_px`` and halved until the energy does not increase
(backtracking: the external forces are explicit and would otherwise make the contour
oscillate across a thin echo). Iterations stop when no point moved more than
``stop_px`` reference pixels (the paper's 3 px) or after ``max_iterations`` (300). The
energy is recorded each iteration and never increases.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.linalg import cho_solve_banded, cholesky_banded
from scipy.ndimage import gaussian_filter

from BoneUSRecon.Logic.segmentation.detection import Detection, empty_detection, sample_bilinear
from BoneUSRecon.Logic.segmentation.features import band_means, dif_map, mm_to_px
from BoneUSRecon.Logic.segmentation.params import (
    REFERENCE_PIXEL_MM,
    PosteriorParams,
    SnakeParams,
)
from BoneUSRecon.Logic.segmentation.posterior import posterior_choice

__all__ = ["SnakeRun", "internal_matrix_banded", "snake_potential", "run_snake", "snake_frame"]


@dataclass(frozen=True, eq=False)
class SnakeRun:
    """One minimisation: the final contour and its history.

    Attributes
    ----------
    points_px : ndarray, shape (n, 2)
        Final snake ``(i, j)`` in image pixels (all points, before the posterior choice).
    energies : ndarray, shape (iterations + 1,)
        Total energy before the first and after each iteration.
    displacements_px : ndarray, shape (iterations,)
        Largest point displacement of each iteration, reference pixels.
    iterations : int
    stopped_by : str
        ``"displacement"`` (the paper's 3 px rule) or ``"max_iterations"``.
    """

    points_px: np.ndarray
    energies: np.ndarray
    displacements_px: np.ndarray
    iterations: int
    stopped_by: str


def internal_matrix_banded(n: int, w1: float, w2: float, tau: float) -> np.ndarray:
    """Upper banded form (3, n) of ``I + tau A`` for an open contour with free ends.

    ``A = 2 (w1 D1^T D1 + w2 D2^T D2)`` is the Hessian of eq. (1); D1 (n-1, n) and
    D2 (n-2, n) take differences only inside the contour, which is what free ends mean.
    """
    d1 = np.diff(np.eye(n), axis=0)
    d2 = np.diff(np.eye(n), n=2, axis=0)
    a = np.eye(n) + tau * 2.0 * (w1 * d1.T @ d1 + w2 * d2.T @ d2)
    ab = np.zeros((3, n))
    for k in range(3):
        ab[2 - k, k:] = np.diagonal(a, k)
    return ab


def snake_potential(
    image: np.ndarray, spacing: tuple[float, float], params: SnakeParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """The potential ``P`` (smoothed positive part of Dif, grey/255 units) and its gradient per reference px.

    Returns
    -------
    P, dP_di, dP_dj : ndarray, shape (H, W)
    """
    sx, sy = float(spacing[0]), float(spacing[1])
    img = np.asarray(image, dtype=np.float32) * np.float32(1.0 / 255.0)
    dif = dif_map(
        img, mm_to_px(params.mid_mm, sy), mm_to_px(params.up_mm, sy), mm_to_px(params.down_mm, sy)
    )
    # E_R = -Dif where Dif >= 0 and the constant k = 0 elsewhere; smoothing the clipped
    # map (rather than clipping a smoothed one) gives the bone band a basin of
    # attraction a few sigma wide, so a snake rising from the shadow is caught.
    np.maximum(dif, 0.0, out=dif)
    p = gaussian_filter(dif, (params.smooth_mm / sy, params.smooth_mm / sx), mode="nearest")
    gj, gi = np.gradient(p)
    # Per image pixel -> per reference pixel.
    return p, gi * (REFERENCE_PIXEL_MM / sx), gj * (REFERENCE_PIXEL_MM / sy)


def run_snake(
    image: np.ndarray,
    spacing: tuple[float, float],
    init_row: float,
    params: SnakeParams = SnakeParams(),  # noqa: B008 (frozen dataclass)
    potential: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None,
) -> SnakeRun:
    """Minimise the snake energy from a horizontal line at ``init_row`` (image rows).

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W)
    spacing : (sx, sy)
        mm per column and per row.
    init_row : float
        Row of the initial straight line.
    params : SnakeParams
    potential : tuple, optional
        Pre-computed :func:`snake_potential` (for tests and re-runs).
    """
    p = params
    sx, sy = float(spacing[0]), float(spacing[1])
    h, w = image.shape
    if potential is None:
        potential = snake_potential(image, spacing, p)
    pot, gi, gj = potential
    ry = sy / REFERENCE_PIXEL_MM  # reference px per image row
    n = p.n_points
    # Span the imaged field of view only: scanners pad the sector with black columns,
    # where nothing holds the balloon back and the tension would drag the snake up.
    lo, hi = field_of_view(image)
    margin = min(mm_to_px(p.margin_mm, sx, minimum=0), (hi - lo) // 4)
    cols = np.linspace(lo + margin, hi - margin, n)
    y = np.full(n, float(np.clip(init_row, 0, h - 1)) * ry)  # reference px
    y_max = (h - 1) * ry
    ab = cholesky_banded(internal_matrix_banded(n, p.w1, p.w2, p.tau))
    balloon = p.force_unit * p.k1
    kdir = p.force_unit * p.k2

    def sample(yy: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        ij = np.column_stack([cols, yy / ry])
        return sample_bilinear(pot, ij), sample_bilinear(gi, ij), sample_bilinear(gj, ij)

    def energy(yy: np.ndarray, pv: np.ndarray) -> float:
        e_int = p.w1 * np.sum(np.diff(yy) ** 2) + p.w2 * np.sum(np.diff(yy, 2) ** 2)
        e_reg = -p.k_regional * np.sum(pv)
        return float(e_int + e_reg + balloon * np.sum(yy))

    pv, pgi, pgj = sample(y)
    energies = [energy(y, pv)]
    disp: list[float] = []
    stopped = "max_iterations"
    for it in range(p.max_iterations):
        norm = np.hypot(pgi, pgj)
        unit_j = np.divide(pgj, norm, out=np.zeros_like(pgj), where=norm > 0)
        force = p.k_regional * pgj + kdir * unit_j - balloon
        y_new = cho_solve_banded((ab, False), y + p.tau * force)
        # Cap the step (as skimage's max_px_move): a thin echo must not be jumped over.
        step = np.clip(y_new - y, -p.max_step_px, p.max_step_px)
        # Backtracking: the explicit external step can overshoot the echo and make the
        # contour oscillate; halve it until the energy goes down (at most 6 times).
        for _ in range(7):
            y_try = np.clip(y + step, 0.0, y_max)
            pv_t, pgi_t, pgj_t = sample(y_try)
            e_try = energy(y_try, pv_t)
            if e_try <= energies[-1]:
                break
            step *= 0.5
        else:
            y_try, pv_t, pgi_t, pgj_t, e_try = y, pv, pgi, pgj, energies[-1]
        d = float(np.max(np.abs(y_try - y)))
        y, pv, pgi, pgj = y_try, pv_t, pgi_t, pgj_t
        energies.append(e_try)
        disp.append(d)
        if it + 1 >= p.min_iterations and d < p.stop_px:
            stopped = "displacement"
            break
    return SnakeRun(
        points_px=np.column_stack([cols, y / ry]),
        energies=np.asarray(energies),
        displacements_px=np.asarray(disp),
        iterations=len(disp),
        stopped_by=stopped,
    )


def field_of_view(image: np.ndarray, threshold: int = 8) -> tuple[int, int]:
    """First and last columns holding image data (column maximum above ``threshold``)."""
    cols = np.flatnonzero(np.asarray(image).max(axis=0) > threshold)
    if cols.size < 2:
        return 0, image.shape[1] - 1
    return int(cols[0]), int(cols[-1])


def initial_row(
    image_height: int, sy: float, params: SnakeParams, previous_px: np.ndarray | None
) -> float:
    """The paper's initialisation rule, in image rows.

    First frame (or after a frame with no kept points): half the image height. Next
    frames: ``init_below_px`` reference px (50 px = 5 mm) below the previous frame's
    *deepest* kept point ("minimal height" of the paper, whose y axis points up; the
    line must start below the whole previous bone contour so the balloon lifts it onto
    the bone), clamped to the image.
    """
    if previous_px is None or len(previous_px) == 0:
        return (image_height - 1) / 2.0
    below = params.init_below_px * REFERENCE_PIXEL_MM / sy
    return float(min(np.max(previous_px[:, 1]) + below, image_height - 1))


def _in_shadow(image: np.ndarray, points_px: np.ndarray, spacing: tuple[float, float]) -> bool:
    """True for a contour inside a shadow: faint, and hardly brighter above than below.

    The region 1.5-3 mm above is < 1.5x as bright as 1-5 mm below, and the contour's
    grey level is < 2.5x the median of the frame's non-black pixels.
    """
    sy = float(spacing[1])
    w = image.shape[1]
    i = np.clip(np.rint(points_px[:, 0]).astype(np.intp), 0, w - 1)
    j = np.rint(points_px[:, 1]).astype(np.intp)
    above = band_means(image, i, j, -3.0, -1.5, sy)
    below = band_means(image, i, j, 1.0, 5.0, sy)
    ok = np.isfinite(above) & np.isfinite(below)
    if not ok.any():
        return False
    shadow_above = np.median(above[ok]) < 1.5 * max(np.median(below[ok]), 1.0)
    # And a faint echo: a reverberation is at most ~2x the frame's typical grey level,
    # bone 3.5-4.5x in the simulator and >= 4.5x on the real L14 recording, whose
    # shadow right under the bone is as bright as the tissue above it.
    lit = image[image > 4]
    typical = float(np.median(lit)) if lit.size else 1.0
    echo = float(np.median(sample_bilinear(image, points_px)))
    return bool(shadow_above and echo < 2.5 * max(typical, 1.0))


def snake_frame(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: SnakeParams = SnakeParams(),  # noqa: B008 (frozen dataclass)
    posterior: PosteriorParams = PosteriorParams(),  # noqa: B008 (frozen dataclass)
    prior_px: np.ndarray | None = None,
) -> Detection:
    """Segment one frame with the paper's snake and posterior choice.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W)
    spacing : (sx, sy)
        mm per column and per row.
    prior_px : ndarray, shape (K, 2), optional
        The previous frame's kept points (initialisation rule).
    """
    h = image.shape[0]
    init = initial_row(h, float(spacing[1]), params, prior_px)
    potential = snake_potential(image, spacing, params)
    run = run_snake(image, spacing, init, params, potential)
    intensity = sample_bilinear(image, run.points_px)
    keep = posterior_choice(run.points_px, intensity, spacing, posterior)
    # The balloon only lifts: a line started above the bone rises to the skin. Then
    # (or when nothing passed the posterior choice) start again from the bottom of the
    # image, as the hip-bone snake of the paper's ref. [4] did.
    top = 0.05 * h
    if (not keep.any() or np.median(run.points_px[keep, 1]) < top) and init < h - 1:
        init = float(h - 1)
        run = run_snake(image, spacing, init, params, potential)
        intensity = sample_bilinear(image, run.points_px)
        keep = posterior_choice(run.points_px, intensity, spacing, posterior)
    # Caught in the shadow: real and simulated shadows are grey and hold reverberation
    # copies of the bone echo 2-6 mm under it, which hold a snake rising from below.
    # A contour with shadow above it as well as below (the region above it hardly
    # brighter than the one below) is such a copy: restart the rise just above it
    # (ours; at most ``max_restarts`` times).
    restarts = 0
    while (
        keep.any()
        and restarts < params.max_restarts
        and _in_shadow(image, run.points_px[keep], spacing)
    ):
        restarts += 1
        init = float(np.min(run.points_px[keep, 1])) - params.restart_above_mm / float(spacing[1])
        if init <= top:
            break
        run = run_snake(image, spacing, init, params, potential)
        intensity = sample_bilinear(image, run.points_px)
        keep = posterior_choice(run.points_px, intensity, spacing, posterior)
    extras = {
        "restarts": restarts,
        "iterations": run.iterations,
        "stopped_by": run.stopped_by,
        "energies": run.energies,
        "init_row": init,
    }
    if not keep.any():
        return empty_detection(reason="no snake point passed the posterior choice", **extras)
    return Detection(run.points_px[keep], intensity[keep], extras)

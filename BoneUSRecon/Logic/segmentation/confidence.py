"""Ultrasound confidence maps (Karamalis et al. 2012) and the confidence drop across a line.

A confidence map gives, per pixel, the probability that a random walk started there
reaches the transducer (the top row, confidence 1) before the bottom of the image
(confidence 0) on an 8-connected graph whose edge weights fall with the intensity
difference between neighbours (Karamalis, Wein, Klein, Navab: "Ultrasound confidence
maps using random walks", Medical Image Analysis 16(6), 2012). Sound that has crossed a
strong reflector (bone: impedance about twice soft tissue's) carries little of the
transducer's signal, and the walk from under it to the top must cross the
reflector's steep edges: the confidence collapses under bone, while a walk from the
tissue under a thin fascia reaches the top around or through a line as short and as
faint as a fascia is.

The graph (the paper's form): intensities ``c = I exp(-alpha l)`` (``l`` the depth over
the image depth: Beer-Lambert attenuation, so differences deep in the image weigh
less), edge weight ``exp(-beta (|c_i - c_j| / s + g))`` with ``s`` the 99th percentile
of ``|c_i - c_j|`` over the frame's edges (ratios above 1 clipped), ``g = 0`` for
vertical edges, ``gamma`` for horizontal and ``sqrt(2) gamma`` for diagonal ones (the
beam runs along depth: a walk sideways is penalised), plus ``1e-6`` so the graph stays
connected. The authors' reference code differs in details: it weights the image by
``1 - exp(-alpha l)``, normalises the differences by their range (min to max) and
again after adding ``gamma`` (to diagonals too); a percentile is not set by one
saturated spot, and either way the scale is a level of the frame itself, so the map
does not depend on gain or grey scale. The Dirichlet problem ``L_UU x = -L_US x_S`` is
solved with a banded Cholesky factor (LAPACK ``pbsv``; nodes numbered across the image
first, so the band is the image width + 1): on the coarse grid used here (0.5 mm axial
x 1.5 mm lateral) it is 3-8x faster than SciPy's sparse LU (SuperLU, COLAMD or minimum
degree ordering), measured on the grids of 480 x 640 frames. The grid is coarse
because the solve costs ``n w^2``.

Measured (issue 10, item 5, 2026-11-29; tables in ``Testing/benchmarks/README.md``,
section "Features measured: confidence maps, phase symmetry"):

* **Behaviour** (``Testing/test_segmentation_features.py``): down a uniform medium the
  confidence falls monotonically; across a bright reflector with a shadow under it the
  log confidence falls by ~9 (orders of magnitude), across a thin fascia line with
  tissue beneath by ~1.3, through plain tissue over the same depths by ~0.8.
* **Cost**: 7-10 ms per 480 x 640 frame for the map (a 120 x 64 grid at 0.15 mm/px),
  9-12 ms with the drop (:func:`confidence_drop`); switched on, ``segment_sweep`` went
  from 23 / 32 to 52 / 52 ms per frame (clavicle standard / tibia hard, CPU, one core:
  the changed evidence also yields more candidates). The budget is 33 ms.
* **As shadow evidence** (``ShadowPathParams.confidence_weight``, the shadow z-score
  becomes ``(1 - k) shadow_z + k z(drop)``): mean frame recall over 30 simulated
  sweeps 0.84 -> 0.79 (k = 0.25) / 0.72 (k = 0.5), wrong share 0.01 -> 0.03 / 0.07;
  the real L14 recording 1.00 -> 0.57 and its cadaver augmentation 0.95 -> 0.00 (0.57
  wrong). As the gate's larger term (``max(shadow_z, z(drop))``): 0.84 -> 0.60. As a
  candidate-level factor on the strength (``1 + 0.25 z``, clipped to 0.5-1.5; not kept
  in the code): 0.84 -> 0.83, ulna grey shadow seed 7 0.55 -> 0.17 (0.47 wrong).

Why it does not help here: the map is a function of the same grey-level gradients the
shadow z-score already measures, integrated along the way to the transducer. Under a
grey shadow (0.65 of the tissue beside it) the walk crosses the faint near cortex
easily and the confidence collapses only under the bright far cortex or a
reverberation band, so it favours exactly the look-alikes the first-reflector rules
of :mod:`.candidates` are there to refuse (radius / clavicle grey shadow: confidence
drop 0.03-0.07 under the bone, 3.1-3.5 under the other candidates, medians in log);
on the real L14 the bone's interior is barely darker than the tissue beside it, so
its drop is no larger than a fascia's. Its cost alone exceeds the frame budget's
headroom. Kept selectable (``confidence_weight`` > 0), off by default.
"""

from __future__ import annotations

import numpy as np
from scipy.linalg import get_lapack_funcs

from BoneUSRecon.Logic.segmentation.features import column_window_mean
from BoneUSRecon.Logic.segmentation.params import ShadowPathParams

__all__ = ["confidence_map", "coarse_log_confidence", "confidence_drop"]

_PBSV = get_lapack_funcs(("pbsv",), (np.zeros(1),))[0]


def confidence_map(
    image: np.ndarray,
    alpha: float = 2.0,
    beta: float = 90.0,
    gamma: float = 0.05,
    norm_percentile: float = 99.0,
) -> np.ndarray:
    """Karamalis' confidence map of an image (rows = depth, the transducer at row 0).

    Parameters
    ----------
    image : ndarray, shape (h, w)
        Grey values in any unit (only ratios of differences enter), ``h >= 3``.
    alpha : float
        Attenuation coefficient over the normalised depth (paper: 2).
    beta : float
        Weight of the normalised intensity difference in the edge weights (paper: 90).
    gamma : float
        Penalty on horizontal edges, in units of the normalised difference (paper: 0.05).
    norm_percentile : float
        Percentile of the edge differences that normalises them (the reference code's
        maximum is the 100th).

    Returns
    -------
    ndarray, shape (h, w), float64
        Confidence in [0, 1]: 1 on the top row, 0 on the bottom row.
    """
    img = np.asarray(image, dtype=np.float64)
    h, w = img.shape
    if h < 3 or w < 1:
        raise ValueError(f"confidence_map needs at least 3 rows and 1 column, got {img.shape}")
    depth = np.linspace(0.0, 1.0, h)[:, None]
    c = img * np.exp(-alpha * depth)
    dv = np.abs(c[1:] - c[:-1])  # (r, c) - (r + 1, c)
    dh = np.abs(c[:, 1:] - c[:, :-1])  # (r, c) - (r, c + 1)
    d1 = np.abs(c[1:, 1:] - c[:-1, :-1])  # (r, c) - (r + 1, c + 1)
    d2 = np.abs(c[1:, :-1] - c[:-1, 1:])  # (r, c + 1) - (r + 1, c)
    allv = np.concatenate([dv.ravel(), dh.ravel(), d1.ravel(), d2.ravel()])
    scale = float(np.percentile(allv, norm_percentile)) if allv.size else 0.0
    scale = max(scale, 1e-12)

    def weight(d: np.ndarray, g: float) -> np.ndarray:
        d = np.minimum(d * (1.0 / scale), 1.0)  # as normalised by the maximum, at most 1
        return np.exp(-beta * (d + g)) + 1e-6

    wv = weight(dv, 0.0)
    wh = weight(dh, gamma)
    wd1 = weight(d1, np.sqrt(2.0) * gamma)
    wd2 = weight(d2, np.sqrt(2.0) * gamma)
    deg = np.zeros((h, w))
    deg[1:] += wv
    deg[:-1] += wv
    deg[:, 1:] += wh
    deg[:, :-1] += wh
    deg[1:, 1:] += wd1
    deg[:-1, :-1] += wd1
    deg[1:, :-1] += wd2
    deg[:-1, 1:] += wd2
    # Unknowns: rows 1 .. h-2, numbered across the image first (node (r, c) is
    # (r - 1) w + c): the matrix is banded with w + 1 super-diagonals. Upper band
    # storage: ab[kd + i - j, j] = A[i, j] for i <= j.
    m = h - 2
    if m == 0:
        return np.vstack([np.ones(w), np.zeros(w)])
    kd = w + 1
    n = m * w
    ab = np.zeros((kd + 1, n))
    ab[kd] = deg[1:-1].ravel()
    if w > 1:
        t = ab[kd - 1].reshape(m, w)  # (r, c - 1) - (r, c): horizontal
        t[:, 1:] = -wh[1:-1]
        t = ab[kd - w + 1].reshape(m, w)  # (r - 1, c + 1) - (r, c): offset w - 1
        t[1:, :-1] = -wd2[1:-1]
        t = ab[0].reshape(m, w)  # (r - 1, c - 1) - (r, c): offset w + 1
        t[1:, 1:] = -wd1[1:-1]
    t = ab[kd - w].reshape(m, w)  # (r - 1, c) - (r, c): vertical, offset w
    t[1:] = -wv[1:-1]
    # Right-hand side: the weights to the top row (confidence 1); the bottom row is 0.
    rhs = np.zeros((m, w))
    rhs[0] += wv[0]
    if w > 1:
        rhs[0, 1:] += wd1[0]
        rhs[0, :-1] += wd2[0]
    _, x, info = _PBSV(ab, rhs.ravel(), lower=0, overwrite_ab=1, overwrite_b=1)
    if info != 0:  # pragma: no cover (the graph Laplacian with a seeded row is SPD)
        raise np.linalg.LinAlgError(f"confidence map: banded Cholesky failed (info {info})")
    out = np.empty((h, w))
    out[0] = 1.0
    out[-1] = 0.0
    out[1:-1] = np.clip(x.reshape(m, w), 0.0, 1.0)
    return out


def coarse_log_confidence(
    work: np.ndarray,
    dx: float,
    dy: float,
    grid_mm: tuple[float, float] = (1.5, 0.5),
    alpha: float = 2.0,
    beta: float = 90.0,
    gamma: float = 0.05,
) -> np.ndarray:
    """``log`` of the confidence map of a working image, solved on a coarse grid.

    The working image (pixels ``dx`` x ``dy`` mm) is block-averaged to about
    ``grid_mm`` (lateral, axial) mm, the map solved there (:func:`confidence_map`) and
    brought back to the working grid by repeating each coarse pixel (the last blocks
    extended to the image edge). Returns shape ``work.shape``, float32.
    """
    h, w = work.shape
    kx = max(1, int(round(grid_mm[0] / dx)))
    ky = max(1, int(round(grid_mm[1] / dy)))
    hh, ww = max(3, h // ky), max(1, w // kx)
    ky = max(1, h // hh)
    kx = max(1, w // ww)
    coarse = work[: hh * ky, : ww * kx].reshape(hh, ky, ww, kx).mean(axis=(1, 3))
    conf = confidence_map(coarse, alpha, beta, gamma)
    logc = np.log(np.maximum(conf, 1e-6)).astype(np.float32)
    ri = np.minimum(np.arange(h) // ky, hh - 1)
    ci = np.minimum(np.arange(w) // kx, ww - 1)
    return logc[ri[:, None], ci[None, :]]


def confidence_drop(
    work: np.ndarray,
    dx: float,
    dy: float,
    usable: np.ndarray,
    above: tuple[int, int],
    below: tuple[int, int],
    params: ShadowPathParams,
) -> np.ndarray:
    """Drop of the log confidence across each working pixel, against the row's typical drop.

    ``mean log C`` over rows ``j + above[0] .. j + above[1]`` less the same over rows
    ``j + below[0] .. j + below[1]``, per pixel ``(j, i)``, less the median of that drop
    over the usable columns of row ``j`` (confidence falls with depth everywhere; what
    matters is whether it falls more here than beside, at the same depths). Positive
    where the confidence collapses under the pixel, as under bone.

    Returns
    -------
    ndarray, shape work.shape, float32
    """
    p = params
    logc = coarse_log_confidence(
        work,
        dx,
        dy,
        p.confidence_grid_mm,
        p.confidence_alpha,
        p.confidence_beta,
        p.confidence_gamma,
    )
    h = work.shape[0]
    csum = np.zeros((h + 1, work.shape[1]), np.float32)
    np.cumsum(logc, axis=0, out=csum[1:])
    j = np.arange(h)
    drop = column_window_mean(csum, j + above[0], j + above[1])
    drop -= column_window_mean(csum, j + below[0], j + below[1])
    cols = usable if usable.any() else np.ones(work.shape[1], bool)
    drop -= np.median(drop[:, cols], axis=1).astype(np.float32)[:, None]
    return drop

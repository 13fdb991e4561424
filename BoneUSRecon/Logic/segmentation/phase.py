"""Local phase symmetry along depth (Hacihaliloglu et al.), as bone echo evidence.

Phase symmetry (Kovesi's measure) is 1 on the centre of a bright, symmetric line and
near 0 elsewhere, whatever the line's contrast: it depends on the local phase of a
band-pass signal, not on its amplitude. Hacihaliloglu et al. (2009) use its 2-D form
to enhance bone surfaces. Here it is computed along depth only, per column, with
log-Gabor filters at a few wavelengths (:func:`phase_symmetry_depth`: one FFT along
depth, ~20x cheaper than ``phasepack.phasesym`` on the working image, which costs
33-60 ms per 480 x 640 frame, over the frame budget; bone echoes face the beam).

Two uses were measured (figures in ``Testing/benchmarks/README.md``, section
"Features measured: confidence maps, phase symmetry"):

* in place of the echo log-ratio (``ShadowPathParams.phase_symmetry``): recall
  collapsed (speckle lines are as symmetric as a bone echo, and a contrast-free
  measure cannot tell a 1.3x echo from a 1.05x one); dropped, kept selectable;
* as an additional term multiplying the score (``ShadowPathParams.phase_weight``,
  :func:`phase_factor`), weights 0.1, 0.25, 0.5: mean recall over 30 simulated sweeps
  0.844 -> 0.836 / 0.835 / 0.821, wrong share 0.009 -> 0.009 / 0.004 / 0.004; it helps
  the hard humerus (0.82 -> 0.88 at 0.25) and tightens the kept points, but breaks
  rows at every weight: the ulna and clavicle under a grey shadow (seed 13 0.65 ->
  0.47, seed 7 0.85 -> 0.62 at 0.25) and the real L14 cadaver augmentation (0.95 ->
  0.86). A contrast-free line measure likely rates sharp reverberation copies as highly
  as the faint near cortex. It also costs 4-5 ms per 480 x 640 frame, most of the
  30 frames/s headroom. Off by default, selectable.
"""

from __future__ import annotations

import numpy as np

__all__ = ["phase_symmetry_depth", "phase_factor"]


def phase_symmetry_depth(
    work: np.ndarray, dy: float, wavelengths_mm: tuple[float, ...], sigma_onf: float = 0.55
) -> np.ndarray:
    """Bright-line phase symmetry along depth (Kovesi's measure, 1-D log-Gabor filters).

    Per column, for each wavelength the analytic signal ``e + i o`` of a log-Gabor band
    pass along depth; the symmetry ``sum max(e - |o|, 0) / sum sqrt(e^2 + o^2)`` is 1 on
    the centre of a bright line and near 0 elsewhere, whatever the line's contrast.

    Parameters
    ----------
    work : ndarray, shape (h, w)
        Image, rows along depth.
    dy : float
        Row spacing, mm.
    wavelengths_mm : tuple of float
        Centre wavelengths of the log-Gabor filters, mm.
    sigma_onf : float
        Bandwidth of the filters (ratio of the Gaussian's sigma to the centre frequency
        on a log scale; 0.55 is about two octaves, Kovesi's usual choice).

    Returns
    -------
    ndarray, shape (h, w), float32, in [0, 1]
    """
    h = work.shape[0]
    spec = np.fft.fft(work - work.mean(axis=0, keepdims=True), axis=0)
    f = np.fft.fftfreq(h, d=dy)
    pos = f > 0  # one-sided filter: the inverse transform is the analytic signal
    num = np.zeros(work.shape, np.float32)
    den = np.full(work.shape, 1e-6, np.float32)
    lg = np.log(sigma_onf)
    for wl in wavelengths_mm:
        g = np.zeros(h)
        g[pos] = 2.0 * np.exp(-(np.log(f[pos] * wl) ** 2) / (2 * lg * lg))
        a = np.fft.ifft(spec * g[:, None], axis=0)
        e, o = a.real.astype(np.float32), a.imag.astype(np.float32)
        num += np.maximum(e - np.abs(o), 0)
        den += np.sqrt(e * e + o * o)
    return num / den


def phase_factor(ps: np.ndarray, valid: np.ndarray, weight: float) -> np.ndarray:
    """Score factor ``1 - k + k min(1, PS / PS_90)`` from a phase symmetry map ``ps``.

    ``PS_90`` is the 90th percentile of ``ps`` over the ``valid`` pixels: the level of a
    clear line in this frame (a level of the frame itself; symmetry is contrast-free
    anyway, so the same percentile means the same on any recording). A pixel on a
    symmetric line keeps its score, one off any line keeps ``1 - k`` of it.
    """
    v = ps[valid]
    ref = float(np.percentile(v[::3], 90)) if v.size >= 10 else 1.0
    k = np.float32(weight)
    out = np.minimum(ps / np.float32(max(ref, 1e-3)), np.float32(1.0))
    out *= k
    out += np.float32(1.0) - k
    return out

"""B-mode image formation: speckle, soft-tissue layers, specular bone echo and shadow.

The chain, per frame, vectorised over a chunk of frames:

1. Echogenicity map of the soft tissue (amplitude std of the scatterers): gel above
   the skin, a bright skin line, hypoechoic fat, muscle with a lognormal texture and
   sparse bright fibre septa.
2. Fully developed speckle: complex Gaussian scatterers times the echogenicity,
   convolved with a Gaussian point-spread function (axial ``psf_axial_mm``, lateral
   ``psf_lateral_mm``) by FFT (:func:`scipy.fft.fft2`), zero-padded against wrap-around.
3. Specular interfaces, added coherently (as complex lines with their own phase):
   fascia lines (bright, thin, no shadow: the distractors) and the bone echo, centred
   on the true bone row of each column with amplitude ``bone_amplitude *
   (cos(incidence) ** specular_exponent + diffuse_fraction * cos(incidence))``, a
   cortical tail below (``bone_tail``, ``bone_tail_mm``: the echo is ~0.5-1 mm thick,
   all below the surface; its *peak* is the true surface), lateral roughness and
   occasional dropouts (``dropouts_per_cm``).
4. Acoustic shadow: everything deeper than the bone surface is multiplied by
   ``shadow_transmission`` (laterally blurred by the beam width); the shadow is grey,
   not black, as on real recordings, and holds faint reverberation copies of the bone
   echo (``reverb_amplitude`` every ``reverb_mm``).
With the ``hard`` realism preset (:mod:`.hard`) a :class:`~.hard.HardScene` adds, in
steps 1 and 3: the no-contact gap and the vessel's lumen and enhancement to the
echogenicity; the far cortex, the fascia off the bone, the skin line over the gap with
its reverberation copies, the vessel's walls and ring-down as specular lines.

5. Depth attenuation left over after TGC, electronic noise, envelope (``abs``), log
   compression over ``dynamic_range_db`` to 8 bits.

The layer depths are smooth functions of the reference position, so neighbouring
frames see the same anatomy.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
from scipy import fft as sfft
from scipy.ndimage import gaussian_filter1d, maximum_filter1d

from BoneUSRecon.Logic.progress import ProgressCallback, report
from BoneUSRecon.Logic.simulation import corruption as corr
from BoneUSRecon.Logic.simulation.params import SimulationParams

if TYPE_CHECKING:
    from BoneUSRecon.Logic.simulation.hard import HardScene

__all__ = ["SmoothField", "TissueLayers", "tissue_layers", "render_frames"]

# Frames rendered at once: bounds memory (~1 MB of complex64 per 256 x 320 frame and
# a few temporaries) while keeping the FFTs batched.
_CHUNK = 16


class SmoothField:
    """A smooth random scalar field ``f(x, y)`` (sum of plane waves), std ~ ``amplitude``.

    Parameters
    ----------
    rng : numpy Generator
    amplitude : float
        Standard deviation of the field (mm or unitless).
    wavelengths : (float, float)
        Range of the plane waves' wavelengths (mm).
    n_terms : int
    """

    def __init__(
        self,
        rng: np.random.Generator,
        amplitude: float,
        wavelengths: tuple[float, float] = (15.0, 60.0),
        n_terms: int = 5,
    ) -> None:
        ang = rng.uniform(0, np.pi, n_terms)
        lam = rng.uniform(*wavelengths, n_terms)
        self.kx = 2 * np.pi / lam * np.cos(ang)
        self.ky = 2 * np.pi / lam * np.sin(ang)
        self.phase = rng.uniform(0, 2 * np.pi, n_terms)
        self.amp = amplitude * np.sqrt(2.0 / n_terms)

    def __call__(self, x: np.ndarray, y: np.ndarray) -> np.ndarray:
        arg = x[..., None] * self.kx + y[..., None] * self.ky + self.phase
        return self.amp * np.sin(arg).sum(-1)


@dataclass(frozen=True, eq=False)
class TissueLayers:
    """Depths (mm) of the soft-tissue interfaces per frame and (padded) column, shape (N, Wp)."""

    #: Lower edge of the bright skin line (dermis).
    skin: np.ndarray
    #: Superficial fascia between fat and muscle.
    fascia1: np.ndarray
    #: Intermuscular fascia, NaN where there is no room above the bone.
    fascia2: np.ndarray
    #: Deep fascia at bone level beside the bone (hidden by the shadow under it).
    deep: np.ndarray
    #: Relative brightness along each fascia line (0 where it fades out).
    strength1: np.ndarray
    strength2: np.ndarray
    strength_deep: np.ndarray


def tissue_layers(
    image_to_reference: np.ndarray,
    top_j: np.ndarray,
    params: SimulationParams,
    rng: np.random.Generator,
    pad: int,
) -> TissueLayers:
    """Soft-tissue interface depths for every frame and column (including ``pad`` columns each side)."""
    m = np.asarray(image_to_reference, float)
    n, w = top_j.shape
    sp = float(params.spacing_mm)
    cols = np.arange(-pad, w + pad, dtype=float)
    # Reference position of each column's top pixel: the anatomy is a function of it.
    xy = m[:, None, :2, 3] + cols[None, :, None] * m[:, None, :2, 0]
    x, y = xy[..., 0], xy[..., 1]
    top_mm = np.pad(top_j * sp, ((0, 0), (pad, pad)), constant_values=np.nan)
    bone_depth = float(params.height) * sp
    top_min = np.where(
        np.isfinite(top_j).any(1),
        np.nanmin(np.where(np.isfinite(top_j), top_j, np.inf), 1) * sp,
        bone_depth,
    )[:, None]

    skin = 1.2 + SmoothField(rng, 0.2)(x, y)
    fascia1 = np.clip(
        0.4 * top_min + SmoothField(rng, 0.8, (20, 80))(x, y),
        skin + 0.6,
        np.maximum(top_min - 1.2, skin + 0.6),
    )
    room = top_min - fascia1
    fascia2 = fascia1 + 0.55 * room + SmoothField(rng, 1.2, (20, 80))(x, y)
    fascia2 = np.where(np.isfinite(top_mm), np.minimum(fascia2, top_mm - 2.0), fascia2)
    fascia2 = np.where((room > 4.0) & (fascia2 > fascia1 + 1.0), fascia2, np.nan)
    deep = top_min + 3.5 + SmoothField(rng, 1.5, (25, 80))(x, y)

    def strength(mean: float) -> np.ndarray:
        # Fascia lines are patchy: bright in places, gone in others.
        return np.clip(mean + 0.5 * SmoothField(rng, 1.0, (8, 30))(x, y), 0.0, 1.3)

    return TissueLayers(
        skin=skin,
        fascia1=fascia1,
        fascia2=fascia2,
        deep=deep,
        strength1=strength(0.8),
        strength2=strength(0.7),
        strength_deep=strength(0.6),
    )


def _psf_transfer(
    shape: tuple[int, int], sig_ax: float, sig_lat: float
) -> tuple[np.ndarray, float]:
    fy = sfft.fftfreq(shape[0])[:, None]
    fx = sfft.fftfreq(shape[1])[None, :]
    h = np.exp(-2 * np.pi**2 * (sig_ax**2 * fy**2 + sig_lat**2 * fx**2)).astype(np.float32)
    # Parseval: white unit-variance noise filtered by h has variance mean(h^2).
    return h, float(1.0 / np.sqrt(np.mean(h.astype(np.float64) ** 2)))


def _add_band(
    field: np.ndarray,
    centre: np.ndarray,
    amp: np.ndarray,
    profile: Callable[[np.ndarray], np.ndarray],
    up: float,
    down: float,
) -> None:
    """Add ``amp * profile(j - centre)`` to ``field`` in place, only on the rows it touches.

    Specular lines are a few pixels thick: drawing them on a band of rows
    ``[centre - up, centre + down]`` per column instead of the whole image is ~20x
    cheaper. ``field`` (n, H, W) complex; ``centre`` (n, W) rows (non-finite: no line);
    ``amp`` (n, W) complex.
    """
    n, h, w = field.shape
    offs = np.arange(-int(np.ceil(up)), int(np.ceil(down)) + 2)
    ok_c = np.isfinite(centre) & (amp != 0)
    c = np.where(ok_c, centre, 0.0)
    rows = np.floor(c)[..., None] + offs  # (n, W, B)
    ok = ok_c[..., None] & (rows >= 0) & (rows < h)
    ni, wi, bi = np.nonzero(ok)
    r = rows[ni, wi, bi]
    field[ni, r.astype(np.intp), wi] += amp[ni, wi] * profile(r - c[ni, wi])


def render_frames(
    image_to_reference: np.ndarray,
    top_j: np.ndarray,
    cos_incidence: np.ndarray,
    params: SimulationParams,
    corrupted: dict[int, str],
    progress: ProgressCallback | None = None,
    tissue_top_j: np.ndarray | None = None,
    scene: HardScene | None = None,
) -> np.ndarray:
    """Render all frames of a sweep.

    Parameters
    ----------
    image_to_reference : ndarray (N, 4, 4)
    top_j, cos_incidence : ndarray (N, W)
        From :func:`BoneUSRecon.Logic.simulation.sections.bone_sections`.
    params : SimulationParams
    corrupted : dict
        ``{frame: kind}`` of frames to corrupt.
    progress : callable, optional
    tissue_top_j : ndarray (N, W), optional
        Bone rows the soft-tissue layers are laid over (default ``top_j``): the
        target bone's, so a neighbouring bone does not move the fascia.
    scene : HardScene, optional
        The hard realism conditions to draw (see :mod:`.hard`).

    Returns
    -------
    ndarray of uint8, shape (N, H, W)
    """
    ip = params.imaging
    n, w = top_j.shape
    h = int(params.height)
    sp = float(params.spacing_mm)
    seed = int(params.seed)
    sig_ax = max(ip.psf_axial_mm / sp, ip.psf_min_px)
    sig_lat = max(ip.psf_lateral_mm / sp, ip.psf_min_px)
    sig_line = max(ip.bone_line_mm / sp, ip.psf_min_px)
    sig_fascia = max(0.15 / sp, ip.psf_min_px)
    pad = int(np.ceil(4 * max(sig_ax, sig_lat))) + 2
    hp, wp = h + 2 * pad, w + 2 * pad
    transfer, norm = _psf_transfer((hp, wp), sig_ax, sig_lat)

    layers = tissue_layers(
        image_to_reference,
        top_j if tissue_top_j is None else tissue_top_j,
        params,
        np.random.default_rng([seed, 2]),
        pad,
    )
    z_pad = ((np.arange(hp) - pad) * sp).astype(np.float32)[None, :, None]
    rows = np.arange(h, dtype=np.float32)[None, :, None]
    z_cm = np.arange(h) * sp / 10.0
    loss_db = (1 - ip.tgc_compensation) * 2 * ip.attenuation_db_cm_mhz * ip.frequency_mhz * z_cm
    gain = (10 ** (-loss_db / 20)).astype(np.float32)[None, :, None]
    floor_db = ip.display_max_db - ip.dynamic_range_db
    tex_sigma = 1.0 / sp  # muscle texture correlation ~1 mm

    present_all = np.isfinite(top_j)
    # Row where the shadow starts: the bone row, carried to the columns beside the bone
    # (nearest bone column) so that the blurred shadow edge spreads outwards too.
    top_filled = np.full(top_j.shape, np.inf, np.float32)
    cols = np.arange(top_j.shape[1])
    for k in np.flatnonzero(present_all.any(1)):
        have = np.flatnonzero(present_all[k])
        nearest = have[np.clip(np.searchsorted(have, cols), 0, have.size - 1)]
        left = have[np.clip(np.searchsorted(have, cols) - 1, 0, have.size - 1)]
        nearest = np.where(np.abs(left - cols) < np.abs(nearest - cols), left, nearest)
        top_filled[k] = top_j[k, nearest]
    # Shadow only where the beam hits bone; edges blurred by the beam width, which
    # grows below the bone (the beam diverges past its focus): blend two blurs by depth.
    lat_near = gaussian_filter1d(present_all.astype(np.float32), sig_lat, axis=1)
    lat_far = gaussian_filter1d(present_all.astype(np.float32), 4 * sig_lat, axis=1)
    cos_c = np.clip(cos_incidence, 0, 1)
    if scene is None:
        strength = cos_c**ip.specular_exponent + ip.diffuse_fraction * cos_c
    else:
        strength = scene.strength
    bone_amp = (ip.bone_amplitude * strength * present_all).astype(np.float32)
    tail_tau = ip.bone_tail_mm / sp  # cortical reverberation: the line's soft lower edge
    reverb_px = ip.reverb_mm / sp
    sig_drop = 0.8 / sp  # width (sigma) of an echo dropout

    # Muscle texture: white noise low-passed by FFT (cheaper than a spatial filter of
    # this ~1 mm width), normalised to unit std.
    tex_transfer, tex_norm = _psf_transfer((hp, wp), tex_sigma, tex_sigma)
    tex_transfer = tex_transfer[:, : wp // 2 + 1]
    # Sparse bright fibre septa in muscle: short lateral streaks ~1.2 mm long.
    n_septa = max(1, int(0.0015 * hp * wp))
    septa_len = max(1, int(round(1.2 / sp)))

    out = np.empty((n, h, w), np.uint8)
    for c0 in range(0, n, _CHUNK):
        ks = np.arange(c0, min(n, c0 + _CHUNK))
        nc = ks.size
        noise = np.empty((nc, hp, wp), np.complex64)
        tex = np.empty((nc, hp, wp), np.float32)
        septa = np.zeros((nc, hp * wp), bool)
        floor = np.empty((nc, h, w), np.complex64)
        phases = np.empty((nc, 4, w), np.complex64)
        rough = np.empty((nc, w), np.float32)
        frame_rngs = []
        for a, k in enumerate(ks):
            # One generator per frame: a frame's pixels do not depend on the chunking.
            r = np.random.default_rng([seed, 3, int(k)])
            noise[a].real = r.standard_normal((hp, wp), np.float32)
            noise[a].imag = r.standard_normal((hp, wp), np.float32)
            tex[a] = r.standard_normal((hp, wp), np.float32)
            septa[a, r.integers(0, hp * wp, n_septa)] = True
            floor[a].real = r.standard_normal((h, w), np.float32)
            floor[a].imag = r.standard_normal((h, w), np.float32)
            # Slowly varying phases of the specular lines and roughness of the bone.
            phases[a] = np.exp(
                1j * (r.uniform(0, 2 * np.pi, (4, 1)) + np.cumsum(r.normal(0, 0.15, (4, w)), 1))
            )
            rough[a] = gaussian_filter1d(r.standard_normal(w), 3 * sig_lat)
            frame_rngs.append(r)
        dropout = np.ones((nc, w), np.float32)
        for a in range(nc):
            # Drawn after everything else of the frame so that the other draws (and the
            # corruption below) are as before; a frame's dropouts follow its own seed.
            r = frame_rngs[a]
            n_drop = r.poisson(ip.dropouts_per_cm * w * sp / 10.0)
            for ic in r.uniform(0, w, n_drop):
                dropout[a] *= 1.0 - 0.7 * np.exp(-0.5 * ((cols - ic) / sig_drop) ** 2).astype(
                    np.float32
                )
        noise *= np.float32(np.sqrt(0.5))
        rough = 1 + 0.25 * rough / np.maximum(rough.std(1, keepdims=True), 1e-6)

        # 1. echogenicity
        skin = layers.skin[ks][:, None, :].astype(np.float32)
        f1 = layers.fascia1[ks][:, None, :].astype(np.float32)
        echo = np.where(
            z_pad < skin,
            np.float32(ip.skin_amplitude),
            np.where(z_pad < f1, np.float32(ip.fat_amplitude), np.float32(1.0)),
        )
        echo[:, :pad, :] = 0.0  # coupling gel above the skin
        tex = sfft.irfft2(
            sfft.rfft2(tex, axes=(1, 2), workers=-1) * tex_transfer,
            s=(hp, wp),
            axes=(1, 2),
            workers=-1,
        )
        tex *= np.float32(tex_norm)
        muscle = z_pad >= f1
        echo *= np.exp(np.where(muscle, np.float32(0.35), np.float32(0.15)) * tex)
        streaks = maximum_filter1d(septa.reshape(nc, hp, wp), septa_len, axis=2)
        echo[muscle & streaks] *= 3.0
        if scene is not None:
            _scene_echogenicity(echo, scene, ks, pad, sp, params)

        # 2. speckle by FFT convolution with the PSF
        noise *= echo
        spec = sfft.fft2(noise, axes=(1, 2), workers=-1)
        spec *= transfer
        speck_full = sfft.ifft2(spec, axes=(1, 2), workers=-1, overwrite_x=True)
        speckle = speck_full[:, pad : pad + h, pad : pad + w] * np.float32(norm)
        del spec, speck_full, noise, echo, tex

        # 3. fascia lines (specular, no shadow)
        sl = slice(pad, pad + w)
        field = speckle.copy()

        def gauss(sigma: float) -> Callable[[np.ndarray], np.ndarray]:
            return lambda d: np.exp(-0.5 * (d / sigma) ** 2)

        for idx, (depth, strength) in enumerate(
            (
                (layers.fascia1, layers.strength1),
                (layers.fascia2, layers.strength2),
                (layers.deep, layers.strength_deep),
            )
        ):
            amp = strength[ks][:, sl] * ip.fascia_amplitude * phases[:, idx]
            _add_band(
                field, depth[ks][:, sl] / sp, amp, gauss(sig_fascia), 4 * sig_fascia, 4 * sig_fascia
            )

        # 4. shadow under the bone (a linear ramp just below the bone line), then the
        # bone echo itself: a Gaussian core on the true surface row and a cortical tail.
        dj = rows - top_filled[ks][:, None, :]
        ramp = np.clip((dj - 2 * sig_line) / max(sig_line, 1.0) + 0.5, 0.0, 1.0)
        far = np.clip(dj * np.float32(sp / 15.0), 0.0, 1.0)  # full divergence 15 mm below
        lat = lat_near[ks][:, None, :] + far * (lat_far[ks] - lat_near[ks])[:, None, :]
        field *= 1.0 - np.float32(1.0 - ip.shadow_transmission) * ramp * lat
        del dj, ramp, far, lat

        def bone_profile(d: np.ndarray) -> np.ndarray:
            core = np.exp(-0.5 * (d / sig_line) ** 2)
            tail = ip.bone_tail * (1 - core) * np.exp(-np.clip(d, 0, None) / tail_tau)
            return core + np.where(d > 0, tail, 0.0)

        bone = np.zeros_like(field)
        amp_k = bone_amp[ks] * rough * dropout
        _add_band(
            bone,
            top_j[ks],
            amp_k * phases[:, 3],
            bone_profile,
            4 * sig_line,
            4 * sig_line + 6 * tail_tau,
        )
        field += bone
        # Reverberations inside the shadow: blurred, weaker copies of the bone echo
        # further down (sound bouncing between the bone and the layers above it).
        if ip.reverb_amplitude > 0:
            sig_rev = 2.0 * sig_line
            for m in range(1, ip.reverb_copies + 1):
                amp_r = (
                    (ip.reverb_amplitude * ip.reverb_decay ** (m - 1))
                    * amp_k
                    * np.conj(phases[:, 3])
                )
                _add_band(
                    field,
                    top_j[ks] + m * reverb_px,
                    amp_r,
                    gauss(sig_rev),
                    4 * sig_rev,
                    4 * sig_rev,
                )
        if scene is not None:
            _scene_lines(field, scene, ks, amp_k, phases, sig_line, sig_fascia, sp, params)

        # corrupted frames (rare: a Python loop over them is fine)
        for a, k in enumerate(ks):
            kind = corrupted.get(int(k))
            if kind is None:
                continue
            r = frame_rngs[a]
            if kind == "shadow_clutter":
                field[a] = corr.shadow_clutter(field[a], speckle[a], top_j[k], bone[a], sp, r)
            elif kind == "false_echo":
                skin_px = float(np.mean(layers.skin[k])) / sp
                field[a] = corr.false_echo(
                    field[a], top_j[k], skin_px, ip.bone_amplitude, sig_line, sp, r
                )
            elif kind == "contact_loss":
                field[a] = corr.contact_loss((h, w), speckle[a], sp, r)
            else:  # pragma: no cover - kinds come from CORRUPTION_KINDS
                raise ValueError(f"unknown corruption kind {kind!r}")

        # 5. gain, noise, envelope, log compression
        field *= gain
        field += np.float32(ip.noise_floor * np.sqrt(0.5)) * floor
        env = np.abs(field)
        db = 20 * np.log10(np.maximum(env, 1e-6))
        out[ks] = np.clip(np.rint((db - floor_db) * (255.0 / ip.dynamic_range_db)), 0, 255).astype(
            np.uint8
        )
        report(progress, "imaging", int(ks[-1]) + 1, n)
    return out


def _scene_echogenicity(
    echo: np.ndarray,
    scene: HardScene,
    ks: np.ndarray,
    pad: int,
    sp: float,
    params: SimulationParams,
) -> None:
    """The hard scene's changes to the echogenicity (padded rows and columns), in place."""
    h = params.hard
    nc, hp, wp = echo.shape
    rows = (np.arange(hp, dtype=np.float32) - pad)[None, :, None]
    if scene.gap_j is not None:
        # No contact: nothing above the curved skin, dimmed tissue below it.
        g = np.pad(scene.gap_j[ks], ((0, 0), (pad, pad)), mode="edge")[:, None, :].astype(
            np.float32
        )
        gap = np.isfinite(g)
        gf = np.where(gap, g, np.float32(-1e9))
        echo *= np.where(
            rows < gf,
            np.float32(0.0),
            np.where(gap, np.float32(h.gap_transmission), np.float32(1.0)),
        )
    if scene.vessel_ij is not None:
        r = np.float32(scene.vessel_r)
        cols = (np.arange(wp, dtype=np.float32) - pad)[None, None, :]
        ci = scene.vessel_ij[ks, 0].astype(np.float32)[:, None, None]
        cj = scene.vessel_ij[ks, 1].astype(np.float32)[:, None, None]
        dx, dy = cols - ci, rows - cj
        echo[dx**2 + dy**2 < r**2] *= 0.03  # blood: anechoic
        # Posterior enhancement: less attenuation through the lumen brightens the tissue below.
        back = np.sqrt(np.clip(r**2 - dx**2, 0, None))
        across = np.clip(1.0 - (dx / r) ** 2, 0.0, 1.0)
        below = np.clip((dy - back) * np.float32(sp / h.vessel_enhancement_mm), 0.0, None)
        boost = 1.0 + (h.vessel_enhancement - 1.0) * across * np.exp(-below) * (dy > back)
        echo *= boost.astype(np.float32)


def _scene_lines(
    field: np.ndarray,
    scene: HardScene,
    ks: np.ndarray,
    amp_k: np.ndarray,
    phases: np.ndarray,
    sig_line: float,
    sig_fascia: float,
    sp: float,
    params: SimulationParams,
) -> None:
    """The hard scene's specular lines, added to the complex field in place."""
    h = params.hard
    nc, hh, w = field.shape

    def gauss(sigma: float) -> Callable[[np.ndarray], np.ndarray]:
        return lambda d: np.exp(-0.5 * (d / sigma) ** 2)

    g_line = gauss(sig_line)
    if scene.far_j is not None:
        amp = h.far_cortex * amp_k * np.conj(phases[:, 2])
        _add_band(field, scene.far_j[ks], amp, gauss(1.5 * sig_line), 6 * sig_line, 6 * sig_line)
    if scene.fascia_j is not None and scene.fascia_amp is not None:
        amp = params.imaging.bone_amplitude * scene.fascia_amp[ks] * phases[:, 1]
        _add_band(field, scene.fascia_j[ks], amp, gauss(sig_fascia), 4 * sig_fascia, 4 * sig_fascia)
    if scene.gap_j is not None:
        g = scene.gap_j[ks]
        on = np.isfinite(g)
        for m in range(1, h.gap_copies + 2):
            # The skin line itself (m = 1), then its copies at 2, 3, ... times its depth:
            # sound bouncing between the probe face and the skin.
            amp = np.where(on, h.gap_amplitude * h.gap_decay ** (m - 1), 0.0) * phases[:, m % 4]
            _add_band(field, m * g, amp, g_line, 4 * sig_line, 4 * sig_line)
    if scene.vessel_ij is not None:
        r = scene.vessel_r
        cols = np.arange(w, dtype=float)[None, :]
        dx = cols - scene.vessel_ij[ks, 0][:, None]
        half = np.sqrt(np.clip(r**2 - dx**2, 0, None))
        wall = np.abs(dx) < 0.9 * r
        cj = scene.vessel_ij[ks, 1][:, None]
        # Walls: specular where the beam meets them square (top and bottom of the lumen).
        face = np.where(wall, np.sqrt(np.clip(1 - (dx / r) ** 2, 0, 1)), 0.0)
        _add_band(
            field,
            np.where(wall, cj - half, np.nan),
            h.ringdown_amplitude * face * phases[:, 0],
            g_line,
            4 * sig_line,
            4 * sig_line,
        )
        for m in range(h.ringdown_copies + 1):
            amp = h.ringdown_amplitude * h.ringdown_decay**m * face * phases[:, (m + 1) % 4]
            row = cj + half + m * h.ringdown_mm / sp
            _add_band(field, np.where(wall, row, np.nan), amp, g_line, 4 * sig_line, 4 * sig_line)

"""Parameters of the phantom simulator (frozen dataclasses, every field documented)."""

from __future__ import annotations

from dataclasses import dataclass, field

# BONES and the reference sweep's defaults live in the import-free names.py (the CLI's
# parsers list them at start-up).
from BoneUSRecon.Logic.simulation.names import (
    BONES,
    CORRUPTION_KINDS,
    DEFAULT_BONE,
    DEFAULT_FRAMES,
    DEFAULT_HEIGHT,
    DEFAULT_SEED,
    DEFAULT_SPACING_MM,
    DEFAULT_WIDTH,
)

__all__ = ["BONES", "CORRUPTION_KINDS", "ImagingParams", "SimulationParams"]


@dataclass(frozen=True)
class ImagingParams:
    """Image formation. Amplitudes are relative to the RMS echo of muscle (= 1)."""

    #: Transmit frequency (MHz): the paper's 7.5 MHz linear probe.
    frequency_mhz: float = 7.5
    #: Axial PSF sigma (mm): ~1.5 wavelengths pulse at 7.5 MHz -> FWHM ~0.3 mm.
    psf_axial_mm: float = 0.13
    #: Lateral PSF sigma (mm): F-number ~2 beam at 7.5 MHz -> FWHM ~0.7 mm.
    psf_lateral_mm: float = 0.3
    #: Smallest PSF sigma in pixels: speckle is never finer than the pixel grid (scan conversion).
    psf_min_px: float = 0.6
    #: Soft-tissue attenuation (dB/cm/MHz), textbook value.
    attenuation_db_cm_mhz: float = 0.5
    #: Fraction of the round-trip attenuation the TGC compensates (unitless).
    tgc_compensation: float = 0.8
    #: Displayed dynamic range of the log compression (dB), typical MSK preset.
    dynamic_range_db: float = 50.0
    #: Echo level shown as white (dB re the muscle RMS echo): sets the overall gain so
    #: muscle is dark grey (~70) and bone near white, as on a scanner's MSK preset
    #: (compare the real L14 recording in ../shared/data/plus: tissue mostly < 90).
    display_max_db: float = 33.0
    #: Echo amplitude of the skin line (dermis).
    skin_amplitude: float = 3.0
    #: Echo amplitude of subcutaneous fat (hypoechoic).
    fat_amplitude: float = 0.35
    #: Peak amplitude of a fascia line (bright, thin, no shadow: the distractor).
    fascia_amplitude: float = 6.0
    #: Peak amplitude of the bone echo at normal incidence (the brightest thing).
    bone_amplitude: float = 16.0
    #: Exponent of cos(incidence) in the bone echo: specular reflection fades fast
    #: off-normal. 3 (was 2): on the real L14 recording the flanks of the bone at
    #: ~55-60 degrees are ~10-15 dB weaker than its top (grey ~100 against ~210).
    specular_exponent: float = 3.0
    #: Diffuse part of the bone echo (fraction of bone_amplitude, times cos(incidence)):
    #: rough cortex still returns a little echo off-normal, so the sides of the bone show dimly.
    diffuse_fraction: float = 0.12
    #: Axial sigma of the bone line (mm): a bit thicker than the PSF (cortical reverberation).
    #: The peak of this Gaussian core lies exactly on the true surface: the simulator's
    #: truth is "the surface is the peak of the echo", as the segmenters assume.
    bone_line_mm: float = 0.18
    #: Amplitude of the echo's tail below the surface, relative to its peak: the bright
    #: band of real bone is ~0.5-1 mm thick, all of it *below* the surface (cortical
    #: reverberation), so the echo is asymmetric: sharp top, soft bottom.
    bone_tail: float = 0.45
    #: Decay length (mm) of that tail.
    bone_tail_mm: float = 0.4
    #: Amplitude transmitted into the acoustic shadow below bone. 0.22 (was 0.03, an
    #: almost black shadow): on the real L14 recording the shadow is grey, its speckle
    #: at 15-40 % of the tissue's grey level (side lobes, multiple reflections).
    shadow_transmission: float = 0.22
    #: Amplitude of reverberation copies of the bone echo inside the shadow, relative to
    #: the echo (the first at ``reverb_mm`` below, the second at twice that, half as
    #: strong): the faint bands seen under real bone.
    reverb_amplitude: float = 0.07
    #: Spacing of the reverberation copies (mm).
    reverb_mm: float = 3.0
    #: Expected number of dropouts of the bone echo per cm of bone line: short stretches
    #: (sigma ~0.8 mm) where the echo falls to ~30 % (roughness, a tendon or vessel
    #: in the way), as real bone lines are not uniformly bright.
    dropouts_per_cm: float = 0.25
    #: Electronic noise floor (amplitude): the faint grain in shadows.
    noise_floor: float = 0.15
    #: Bone points with cos(incidence) below this are not part of the visible contour.
    visible_cos: float = 0.5


@dataclass(frozen=True)
class SimulationParams:
    """One simulated freehand sweep over one bone.

    Defaults give the issue's reference sweep: 150 frames of 256 x 320 pixels at
    0.15 mm (a 38 x 48 mm field of view, usual for a 7.5 MHz linear probe).
    """

    #: Which bone (one of :data:`BONES`).
    bone: str = DEFAULT_BONE
    #: Number of frames (the paper: 50 to 250 images per sweep).
    n_frames: int = DEFAULT_FRAMES
    #: Image width in pixels (columns, lateral).
    width: int = DEFAULT_WIDTH
    #: Image height in pixels (rows, depth).
    height: int = DEFAULT_HEIGHT
    #: Pixel spacing (mm), the same along columns and rows.
    spacing_mm: float = DEFAULT_SPACING_MM
    #: Fraction of frames corrupted (clutter in shadow, false echo, contact loss); the
    #: paper saw ~10 % bad frames on real forearms.
    corrupted_fraction: float = 0.0
    #: Fraction of frames flagged invalid (tracking lost: TransformStatus INVALID).
    invalid_fraction: float = 0.0
    #: Random seed: everything random (motion, tissue, speckle, corruption, gold) follows it.
    seed: int = DEFAULT_SEED
    #: Sweep from the far end of the bone back to the near end.
    reverse: bool = False
    #: Standard deviation of each probe tilt angle (degrees): freehand slices are not parallel.
    tilt_deg: float = 4.0
    #: Standard deviation of the probe's lateral wander off the bone (mm).
    lateral_jitter_mm: float = 1.5
    #: Standard deviation of the probe pressure variation, i.e. of the bone depth (mm).
    depth_jitter_mm: float = 0.7
    #: Relative standard deviation of the sweep speed (unitless): uneven hand speed.
    speed_variation: float = 0.4
    #: Frame rate (Hz), for the timestamps.
    frame_rate_hz: float = 20.0
    #: Length left unswept at each end of the bone segment (mm).
    sweep_margin_mm: float = 10.0
    #: Show the forearm's other bone beside the target (radius <-> ulna), as a
    #: transverse forearm scan does: a second bone echo with its own shadow at the
    #: side of the image. It is not part of the truth, the gold points or the contours.
    neighbour: bool = True
    #: Width (pixels) of the black margin left and right of the imaged area, as in a
    #: scan-converted recording (the real L14 sweep: 176 columns of 820 on the left).
    #: No echo there and no bone in the true contours; 0 (default) images every column.
    black_margin_px: int = 0
    #: Number of digitised gold-standard points (the paper: 1145).
    gold_points: int = 1145
    #: Standard deviation of the digitiser noise, per axis (mm).
    gold_noise_mm: float = 0.2
    #: Image formation parameters.
    imaging: ImagingParams = field(default_factory=ImagingParams)

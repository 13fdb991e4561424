"""Parameters of the phantom simulator (frozen dataclasses, every field documented)."""

from __future__ import annotations

from dataclasses import dataclass, field

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.params_check import check_fields

# BONES and the reference sweep's defaults live in the package's import-free __init__
# (the CLI's parsers list them at start-up).
from BoneUSRecon.Logic.simulation import (
    BONES,
    CORRUPTION_KINDS,
    DEFAULT_BONE,
    DEFAULT_FRAMES,
    DEFAULT_HEIGHT,
    DEFAULT_SEED,
    DEFAULT_SPACING_MM,
    DEFAULT_WIDTH,
    GOLD_REGIONS,
    HARD_CONDITIONS,
    REALISMS,
)

__all__ = [
    "BONES",
    "CORRUPTION_KINDS",
    "GOLD_REGIONS",
    "HARD_CONDITIONS",
    "REALISMS",
    "HardParams",
    "ImagingParams",
    "SimulationParams",
]


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
    #: off-normal. 3: on the real L14 recording the flanks of the bone at
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
    #: Amplitude transmitted into the acoustic shadow below bone. 0.22: on the real
    #: L14 recording the shadow is grey (not black), its speckle
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
    #: Number of reverberation copies of the bone echo in the shadow (the m-th at
    #: ``m * reverb_mm``, amplitude ``reverb_amplitude * reverb_decay ** (m - 1)``).
    reverb_copies: int = 2
    #: Amplitude ratio of successive reverberation copies; 0.5 (the second half as
    #: strong as the first) in version 2.
    reverb_decay: float = 0.5

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=(
                "frequency_mhz",
                "psf_axial_mm",
                "psf_lateral_mm",
                "psf_min_px",
                "dynamic_range_db",
                "bone_line_mm",
                "bone_tail_mm",
                "reverb_mm",
            ),
            non_negative=(
                "attenuation_db_cm_mhz",
                "skin_amplitude",
                "fat_amplitude",
                "fascia_amplitude",
                "bone_amplitude",
                "specular_exponent",
                "diffuse_fraction",
                "bone_tail",
                "shadow_transmission",
                "reverb_amplitude",
                "dropouts_per_cm",
                "noise_floor",
                "reverb_copies",
                "reverb_decay",
            ),
            within={"tgc_compensation": "[0, 1]", "visible_cos": "[0, 1]"},
        )


@dataclass(frozen=True)
class HardParams:
    """Levels of the ``hard`` realism preset (issue 10), measured on a real tracked cadaver
    sweep of a lower leg (linear probe, 216 frames 475 x 405 at 0.108 mm; grey 0-255,
    medians) unless said otherwise.

    Amplitudes are relative to the RMS echo of muscle (= 1), as in :class:`ImagingParams`.
    Grey-level ratios (what the cadaver gives) come out of the log compression: the
    amplitudes below are chosen so that the simulated images measure as the cadaver
    does, and ``Testing/test_simulation_hard.py`` measures them with
    :func:`BoneUSRecon.Logic.simulation.levels.echo_levels`.
    """

    # -- low_contrast: the bone echo only ~1.2-1.35x the grey of the tissue above it
    #: Displayed maximum (dB re the muscle echo): 21 dB (standard 33) makes muscle mid-grey
    #: (~110), as on the cadaver's scanner preset, where tissue above bone is ~100-120.
    display_max_db: float = 21.0
    #: Peak amplitude of the bone echo at normal incidence: 2.6 (standard 16) gives an echo
    #: at ~1.3x the grey of the tissue 1-3 mm above it (cadaver 1.35x; issue's target
    #: 1.2-1.35x; the L14 recording 2.7x, the standard simulator ~1.4x at grey 240).
    bone_amplitude: float = 2.6
    #: Fascia amplitude with ``low_contrast``: fascia as bright as the bone echo.
    fascia_amplitude: float = 2.6

    # -- grey_shadow: 0.4 of the echo, 0.65 of the tissue beside it at the same depth
    #: Amplitude transmitted into the shadow: 0.12 with the reverberation and far-cortex
    #: echoes below gives, on the low-contrast display, a shadow ~0.66 of the grey of the
    #: tissue beside it at the same depth (cadaver 0.65) and ~0.43 of the echo (cadaver
    #: 0.40). The grey is the display's doing: on the standard display (``grey_shadow``
    #: without ``low_contrast``) the same amplitudes give a shadow ~0.8 of the tissue beside.
    shadow_transmission: float = 0.12
    #: Reverberation copies of the bone echo in the shadow: amplitude of the first
    #: (relative to the echo), spacing (mm), number and decay: the equally spaced grey
    #: bands under the cadaver's bone.
    reverb_amplitude: float = 0.25
    reverb_mm: float = 2.5
    reverb_copies: int = 4
    reverb_decay: float = 0.75
    #: Echo of the far (deep) cortex of the bone, relative to the near echo: the curved
    #: echoes seen deep in the cadaver's shadow.
    far_cortex: float = 0.45

    # -- crest: a triangular crest proximally, an oval distally
    #: Fractions of the bone's length where the crest begins to blend into the oval and
    #: where the oval is complete (see :func:`.bones.crest_shape`).
    crest_range: tuple[float, float] = (0.4, 0.6)
    #: Exponent of cos(incidence) of the echo on the crest: 0.5, a rough cortex still
    #: bright on flanks of 60-70 degrees (the cadaver: ~6 mm of flank steeper than 45
    #: degrees visible per frame). On the oval part the standard exponent (3): its echo is
    #: strong only on the side facing the probe.
    crest_exponent: float = 0.5
    #: Lowest relative echo strength ``cos ** p + diffuse * cos`` of a visible contour
    #: point (with ``visible_cos``): where the oval's side has faded, it is not "seen".
    visible_strength: float = 0.35
    #: cos(incidence) of the steepest visible bone: 0.34 = 70 degrees (issue 10: follow
    #: the flanks to at least 70 degrees).
    visible_cos: float = 0.34

    # -- fascia: a bright line running off the bone at its level, tissue beneath
    #: Where the fascia leaves the bone: this far (mm) below the bone's top, on its flank.
    fascia_attach_mm: float = 1.5
    #: Lateral length of the fascia (mm) and its slope (depth gained per mm outwards).
    fascia_length_mm: float = 14.0
    fascia_slope: float = 0.08
    #: Fascia amplitude relative to the bone echo's peak (1: as bright as the bone).
    fascia_strength: float = 1.1

    # -- skin_gap: no probe contact at one image edge
    #: Share of the image width at one edge where the skin curves away from the probe.
    gap_fraction: float = 0.22
    #: Depth (mm) the skin line reaches at the image edge.
    gap_depth_mm: float = 6.0
    #: Amplitude of the skin line over the gap, and of its reverberation copies (at 2, 3,
    #: ... times its depth: equally spaced), each ``gap_decay`` of the previous.
    gap_amplitude: float = 4.0
    gap_copies: int = 3
    gap_decay: float = 0.65
    #: Amplitude transmitted into the tissue under the gap (poor coupling).
    gap_transmission: float = 0.4

    # -- vessel: a dark round lumen with posterior enhancement and ring-down
    #: Lumen radius (mm): an artery or vein of the calf, 2-3 mm.
    vessel_radius_mm: float = 2.5
    #: Depth of the vessel's centre below the bone's top (mm) and its gap to the bone (mm).
    vessel_depth_mm: float = 1.5
    vessel_gap_mm: float = 3.0
    #: Posterior enhancement: tissue below the lumen is this much brighter (amplitude),
    #: fading over ``vessel_enhancement_mm``.
    vessel_enhancement: float = 1.8
    vessel_enhancement_mm: float = 10.0
    #: Ring-down under the back wall: copies every ``ringdown_mm``, each ``ringdown_decay``
    #: of the previous, the first at ``ringdown_amplitude`` (relative to muscle).
    ringdown_amplitude: float = 2.0
    ringdown_mm: float = 0.9
    ringdown_copies: int = 4
    ringdown_decay: float = 0.7

    # -- depth_ramp: the bone's depth along the sweep
    #: Skin-to-bone depth (mm) at the start and the end of the sweep: the cadaver's 25 -> 5 mm.
    depth_mm: tuple[float, float] = (25.0, 5.0)

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=(
                "reverb_mm",
                "fascia_length_mm",
                "gap_depth_mm",
                "vessel_radius_mm",
                "vessel_enhancement_mm",
                "ringdown_mm",
                "depth_mm",
            ),
            non_negative=(
                "bone_amplitude",
                "fascia_amplitude",
                "shadow_transmission",
                "reverb_amplitude",
                "reverb_copies",
                "reverb_decay",
                "far_cortex",
                "crest_exponent",
                "fascia_attach_mm",
                "fascia_strength",
                "gap_amplitude",
                "gap_copies",
                "gap_decay",
                "gap_transmission",
                "vessel_gap_mm",
                "vessel_enhancement",
                "ringdown_amplitude",
                "ringdown_copies",
                "ringdown_decay",
            ),
            within={
                "crest_range": "[0, 1]",
                "visible_strength": "[0, 1]",
                "visible_cos": "[0, 1]",
                "gap_fraction": "[0, 0.5]",
            },
        )


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
    #: Least skin-to-bone-top distance (mm) the probe's pressure leaves: the depth with
    #: its jitter is clamped here. The skin alone is 1-2 mm thick (the hard preset draws
    #: its line at 1.2 mm) and the subcutis over a subcutaneous bone compresses to a few
    #: mm, not to nothing; without the floor a 2 mm pressure jitter on the hard
    #: preset's 5 mm end put the bone's top 1.0 mm under the probe, above the skin line
    #: (issue 10's cadaver leg: 5 mm at its shallowest).
    min_depth_mm: float = 3.0
    #: Relative standard deviation of the sweep speed (unitless): uneven hand speed.
    speed_variation: float = 0.4
    #: Frame rate (Hz), for the timestamps.
    frame_rate_hz: float = 20.0
    #: Length left unswept at each end of the bone segment (mm).
    sweep_margin_mm: float = 10.0
    #: Frames at the start and at the end of the sweep that show no bone ``(first,
    #: last)``: the sweep runs past the bone's end, or the probe has slid off it. Those
    #: frames are rendered without any bone echo, shadow, reverberation or far cortex
    #: (nor the neighbouring bone); the soft tissue, fascia, skin gap and vessel stay as
    #: they would be, and their true contours are empty, so a segmentation keeping them
    #: counts as wrong (:attr:`.scoring.FrameScore.wrong`). Real sweeps start or end
    #: beyond the bone (issue 10's sweep ends); ``sweep_margin_mm`` cannot produce that,
    #: as every frame then shows bone. At least 2 frames must keep the bone.
    bone_free_frames: tuple[int, int] = (0, 0)
    #: Show the forearm's other bone beside the target (radius <-> ulna), as a
    #: transverse forearm scan does: a second bone echo with its own shadow at the
    #: side of the image. It is not part of the truth, the gold points or the contours.
    #: A tibia shows its fibula only when ``neighbour_mm`` is given (see there).
    neighbour: bool = True
    #: Axis-to-axis distance of that other bone (mm; None: :data:`.bones.NEIGHBOURS`'
    #: 26 mm, mid-shaft, where a 48-51 mm wide image catches only its edge). The two
    #: come to 15-20 mm of each other toward the wrist, where both show whole and the
    #: segmentation must tell the bone swept from its neighbour (:func:`.segmentation.
    #: track.central_track`). For a tibia, a number shows the fibula that far lateral
    #: (its top 15 mm deeper than the tibia's; 20-35 mm in issue 10's lower-leg
    #: sweeps); None (default) shows no fibula, as every tibia sweep simulated before
    #: the fibula existed (they stay byte-identical). Other bones have no neighbour.
    neighbour_mm: float | None = None
    #: Width (pixels) of the black margin left and right of the imaged area, as in a
    #: scan-converted recording (the real L14 sweep: 176 columns of 820 on the left).
    #: No echo there and no bone in the true contours; 0 (default) images every column.
    black_margin_px: int = 0
    #: Number of digitised gold-standard points (the paper: 1145).
    gold_points: int = 1145
    #: Standard deviation of the digitiser noise, per axis (mm).
    gold_noise_mm: float = 0.2
    #: Where the gold points are digitised (one of :data:`GOLD_REGIONS`). ``imaged``
    #: (default): the bone the sweep imaged, between the planes of the first and last
    #: frames that showed bone; the paper digitised the bone where it was scanned, and
    #: the simulator's image is a plane with no elevational thickness, so nothing beyond
    #: the end planes is imaged. ``swept`` (before issue 11's follow-up): the whole axis
    #: range those frames' sections touch; with the probe yawed a few degrees across a
    #: wide bone that reaches up to ~4 mm beyond an end plane on one side (3-4 % of the
    #: points on a 150-frame tibia or humerus), bone no frame imaged.
    gold_region: str = "imaged"
    #: Image formation parameters.
    imaging: ImagingParams = field(default_factory=ImagingParams)
    #: Realism preset (one of :data:`REALISMS`): ``standard`` (default, simulator
    #: version 2) or ``hard`` (the levels of a real cadaver sweep, issue 10; the
    #: conditions of ``hard_conditions`` with the levels of ``hard``).
    realism: str = "standard"
    #: With ``realism="hard"``: which of :data:`HARD_CONDITIONS` apply (default all).
    hard_conditions: tuple[str, ...] = HARD_CONDITIONS
    #: Levels of the hard conditions.
    hard: HardParams = field(default_factory=HardParams)

    def __post_init__(self) -> None:
        check_fields(
            self,
            non_negative=(
                "seed",
                "tilt_deg",
                "lateral_jitter_mm",
                "depth_jitter_mm",
                "min_depth_mm",
                "speed_variation",
                "sweep_margin_mm",
                "bone_free_frames",
            ),
            positive=("frame_rate_hz",),
        )
        # The messages the CLI shows for its options (--frames, --size, --corrupt, ...).
        if self.bone not in BONES:
            raise BoneUSReconError(f"unknown bone {self.bone!r}; choose one of {', '.join(BONES)}")
        if self.gold_region not in GOLD_REGIONS:
            raise BoneUSReconError(
                f"gold_region: unknown region {self.gold_region!r}; use one of {', '.join(GOLD_REGIONS)}"
            )
        if self.realism not in REALISMS:
            raise BoneUSReconError(
                f"realism: unknown preset {self.realism!r}; use one of {', '.join(REALISMS)}"
            )
        bad = [c for c in self.hard_conditions if c not in HARD_CONDITIONS]
        if bad:
            raise BoneUSReconError(
                f"hard_conditions: unknown condition {bad[0]!r}; use some of {', '.join(HARD_CONDITIONS)}"
            )
        if self.n_frames < 2:
            raise BoneUSReconError(f"need at least 2 frames, got {self.n_frames}")
        if self.neighbour_mm is not None and not self.neighbour_mm > 0:
            raise BoneUSReconError(
                f"SimulationParams.neighbour_mm must be > 0 (or None), got {self.neighbour_mm!r}"
            )
        if sum(self.bone_free_frames) > self.n_frames - 2:
            raise BoneUSReconError(
                f"SimulationParams.bone_free_frames: {self.bone_free_frames} leaves fewer than "
                f"2 of {self.n_frames} frames showing bone"
            )
        if self.width < 16 or self.height < 16:
            raise BoneUSReconError(
                f"images must be at least 16 x 16 pixels, got {self.height} x {self.width}"
            )
        if not self.spacing_mm > 0:
            raise BoneUSReconError(
                f"pixel spacing must be a positive number of mm, got {self.spacing_mm}"
            )
        for name in ("corrupted_fraction", "invalid_fraction"):
            v = getattr(self, name)
            if not (0.0 <= v <= 1.0):
                raise BoneUSReconError(f"{name.replace('_', ' ')} must be between 0 and 1, got {v}")
        if self.gold_points < 0 or self.gold_noise_mm < 0:
            raise BoneUSReconError("gold points and gold noise must not be negative")

    def has(self, condition: str) -> bool:
        """Whether the hard ``condition`` applies (``realism="hard"`` and listed)."""
        return self.realism == "hard" and condition in self.hard_conditions

"""Parameters of the segmenters, the posterior choice and the frame rejection.

Every length is in millimetres or in *reference pixels* (see
:data:`REFERENCE_PIXEL_MM`), never in image pixels, so that a 0.05 mm/px and a
0.15 mm/px recording of the same anatomy are segmented the same way.

How the paper's numbers are read
--------------------------------
The paper (section II.B) states its sizes in pixels of its own images without giving
their size; a 7.5 MHz probe at the depths of the forearm gives about 0.1 mm/px, so one
paper pixel is taken as one reference pixel of 0.1 mm. "50 px below", "3 px" and
"10 px" thus become 5 mm, 0.3 mm and 1 mm on any image.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import SEGMENTER_NAMES

__all__ = [
    "REFERENCE_PIXEL_MM",
    "SEGMENTER_NAMES",
    "SnakeParams",
    "PosteriorParams",
    "ShadowPathParams",
    "RejectionParams",
    "SegmentationParams",
]

#: Size (mm) of one "pixel" of the paper. All pixel-valued parameters below are in
#: these reference pixels and are converted with the image's own spacing.
REFERENCE_PIXEL_MM = 0.1


@dataclass(frozen=True)
class SnakeParams:
    """The paper's open active contour (section II.B, eqs. 1-3).

    The snake is a graph over the lateral axis: its 100 points keep their column and
    move along the depth axis (the bone contours of the paper's figures are graphs over
    the probe's lateral axis; letting points slide laterally makes an open snake with
    tension shrink). Positions, derivatives and forces are in reference pixels.
    Intensities are the 8-bit grey values divided by 255, so ``Dif`` lies in [-2, 2].
    """

    n_points: int = 100
    """Number of snake points (paper: "the number of points in the snake is 100")."""
    w1: float = 1.0
    """Tension weight on ``|v'|^2`` per point index, reference px (paper: w1 = 1)."""
    w2: float = 2.5
    """Rigidity weight on ``|v''|^2`` per point index, reference px (paper: w2 = 2.5)."""
    k1: float = 500.0
    """Balloon pressure along the normal, in ``force_unit`` (paper: k1 = 500)."""
    k2: float = 0.5
    """Weight of the unit potential-gradient ``grad P/|grad P|``, in ``force_unit`` (paper: k2 = 0.5)."""
    force_unit: float = 1e-2
    """Reference px per unit time per unit of k1, k2 (ours: keeps the paper's k1:k2 = 1000:1; balloon = 5 px per unit time)."""
    k_regional: float = 600.0
    """Weight of the regional energy ``-P`` (ours: the paper gives none; tuned so the echo holds the snake against balloon and tension)."""
    tau: float = 3.0
    """Time step of ``(I + tau A) y' = y + tau F`` (ours: the balloon alone then moves a point 15 px, capped at max_step_px, so the 3 px rule means "held")."""
    mid_mm: float = 0.6
    """Height of the bright band ``M_mid`` centred on the point, mm (Fig. 1; ours: typical bone echo thickness)."""
    up_mm: float = 1.5
    """Height of the region above the band ``M_up``, mm (Fig. 1; ours)."""
    down_mm: float = 3.0
    """Height of the shadow region below the band ``M_down``, mm (Fig. 1; ours)."""
    smooth_mm: float = 0.3
    """Gaussian sigma of the potential ``P`` (positive part of Dif), mm (ours: the bone band's basin of attraction)."""
    max_step_px: float = 5.0
    """Largest move of a point in one iteration, reference px (ours, as skimage's max_px_move)."""
    stop_px: float = 3.0
    """Stop when no point moved more than this many reference px in one iteration (paper: 3 px)."""
    max_iterations: int = 300
    """Iteration cap (paper: "typically set to 300")."""
    min_iterations: int = 3
    """Iterations always done before the stopping rule is tested (ours: lets the balloon start)."""
    init_below_px: float = 50.0
    """Next frame starts this many reference px below the previous contour's deepest kept point (paper: 50 px)."""
    margin_mm: float = 0.5
    """Lateral margin left free at each image side, mm (ours: avoids the edge columns)."""
    max_restarts: int = 3
    """Times the rise is restarted above a contour caught inside the shadow (a reverberation), ours."""
    restart_above_mm: float = 1.0
    """A restart begins this far above the caught contour's highest point, mm (ours)."""


@dataclass(frozen=True)
class PosteriorParams:
    """The paper's posterior choice of the snake points (section II.B, end)."""

    k_intensity: float = 0.005
    """Keep points with intensity > I_mean + k_intensity * I_var (paper: 0.005; 8-bit grey values)."""
    neighbour_px: float = 10.0
    """Points closer than this are connected, reference px (paper: 10 px = 1 mm)."""


@dataclass(frozen=True)
class ShadowPathParams:
    """The default segmenter: a shadow-aware bone map and an optimal path across columns.

    The bone is a bright band with an acoustic shadow under it. The score of a pixel is
    the paper's ``Dif`` contrast gated by how dark the region below is relative to the
    band (attenuation-aware: a ratio, not a difference, so deep bones with weaker echoes
    still score). Dynamic programming then finds the best path over the columns of a
    down-sampled score image with a smoothness penalty and a "no bone" state, and the
    path is refined to sub-pixel depth on the full-resolution image.
    """

    work_mm: float = 0.25
    """Target pixel size of the down-sampled working image, mm (ours: the sub-pixel step restores full resolution; sets the speed)."""
    mid_mm: float = 0.6
    """Height of the bright band, mm (as the snake's M_mid)."""
    up_mm: float = 1.5
    """Height of the region above the band, mm."""
    down_mm: float = 3.0
    """Height of the shadow region right below the band, mm."""
    shadow_mm: float = 6.0
    """Depth of the region (below the band) whose darkness gates the score, mm (ours)."""
    gate_ratio: float = 0.6
    """Shadow/echo intensity ratio at which the shadow gate reaches 0 (ours: tissue under a layer is >= 60 % as bright)."""
    min_score: float = 0.14
    """Score (Dif in [0, 2] times the shadow gate) a pixel needs to pay off over "no bone" (ours: low enough that the weak oblique flank echoes of the real L14 recording (score 0.1-0.3, the top of the arc 0.4-0.6) stay on the path; was 0.3, which kept only the top 6-17 mm)."""
    strong_score: float = 0.3
    """Score of a "strong" column (ours: the former min_score; the top of real and simulated bone scores 0.4-1, a bright tissue layer with tissue under it < 0.25)."""
    strong_mm: float = 2.0
    """A contour needs at least this many mm of strong columns (ours: hysteresis, see min_score)."""
    slope_penalty: float = 0.08
    """Cost per (mm of depth change per mm of lateral step)^2 between neighbouring columns (ours: small, so steep flanks are not cut off)."""
    max_slope: float = 2.2
    """Largest depth change per lateral mm the path may take (ours: ~65 degrees, the flanks of a round bone just before their echo fades; 3.0 let the path climb onto the neighbouring forearm bone in the simulator)."""
    near_field_mm: float = 2.0
    """Rows shallower than this are never bone, mm (ours: gel, skin line and lens reverberation; the shallowest simulated bone, the clavicle, lies >= 3 mm deep, and real bone under skin and periosteum is deeper)."""
    fov_grey: float = 4.0
    """Grey level (0..255) below which a pixel counts as black, for finding the imaged field of view (ours: scan-converted images are exactly 0 outside it)."""
    fov_fraction: float = 0.25
    """A column is inside the field of view when more than this fraction of its pixels are above ``fov_grey`` (ours)."""
    fov_margin_mm: float = 0.5
    """Columns this close to the edge of the field of view are ignored too, mm (ours: block averaging mixes them with the black margin)."""
    switch_cost: float = 0.3
    """Cost of entering or leaving the "no bone" state (ours: tuned on simulated bones and the shared real recording)."""
    merge_gap_mm: float = 3.0
    """Bone runs separated by a gap shorter than this (and a depth step < merge_step_mm) are one contour (ours)."""
    merge_step_mm: float = 1.5
    """Largest depth step across a merged gap, mm (ours)."""
    temporal_sigma_mm: float = 4.0
    """Width of the prior around the previous accepted contour's depth, mm (ours)."""
    temporal_weight: float = 0.25
    """Strength of that prior: scores far from the previous contour are scaled by 1 - weight (ours)."""
    refine_mm: float = 0.4
    """Half-height of the window searched at full resolution around the path, mm (ours)."""
    refine_sigma_mm: float = 0.15
    """Gaussian sigma along depth of the full-resolution profile before the peak fit, mm (ours)."""
    surface_offset_mm: float = 0.0
    """Added to the echo's peak depth to give the surface depth, mm (ours: the peak of the echo is the surface)."""


@dataclass(frozen=True)
class RejectionParams:
    """Per-frame confidence and rejection of implausible contours (ours; the paper had none)."""

    min_length_mm: float = 3.0
    """Contours shorter than this laterally are rejected ("contour too short")."""
    min_points: int = 5
    """Contours with fewer points are rejected."""
    max_shadow_ratio: float = 0.45
    """Reject when the mean shadow intensity (1-5 mm below) exceeds this fraction of the echo's ("no acoustic shadow")."""
    min_contrast: float = 0.12
    """Reject when the mean Dif (grey/255 units) along the contour is below this ("low contrast")."""
    jump_mm: float = 1.5
    """Reject when the contour's median depth difference from the neighbouring frames' prediction exceeds this, mm (ours: a false echo lies >= 1.5 mm above the bone)."""
    point_jump_mm: float = 1.0
    """Points of a kept frame farther than this (mm, depth) from the neighbouring frames' prediction are dropped (ours)."""
    extend_mm: float = 2.0
    """A contour may extend this far (mm) laterally beyond its neighbours' and still be compared; farther points are unsupported (ours)."""
    jump_window: int = 3
    """Number of frames on each side used for the neighbour median."""
    min_confidence: float = 0.0
    """Frames whose confidence is below this are rejected as well (0 disables)."""


@dataclass(frozen=True)
class SegmentationParams:
    """Everything :func:`~BoneUSRecon.Logic.segmentation.segment_sweep` needs."""

    method: str = "shadowpath"
    """Segmenter name, a key of ``SEGMENTERS`` (default: "shadowpath", the more accurate one; "snake" is the paper's)."""
    snake: SnakeParams = field(default_factory=SnakeParams)
    """The paper's snake."""
    posterior: PosteriorParams = field(default_factory=PosteriorParams)
    """The paper's posterior choice (used by the snake)."""
    shadowpath: ShadowPathParams = field(default_factory=ShadowPathParams)
    """The default segmenter."""
    rejection: RejectionParams = field(default_factory=RejectionParams)
    """Confidence and rejection, applied to every segmenter's output."""

    def __post_init__(self) -> None:
        if self.method not in SEGMENTER_NAMES:
            raise BoneUSReconError(
                f"unknown segmenter {self.method!r}; use one of {', '.join(sorted(SEGMENTER_NAMES))}"
            )

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
from BoneUSRecon.Logic.params_check import check_fields
from BoneUSRecon.Logic.segmentation import SEGMENTER_NAMES

__all__ = [
    "REFERENCE_PIXEL_MM",
    "SEGMENTER_NAMES",
    "SnakeParams",
    "PosteriorParams",
    "FlankParams",
    "SettleParams",
    "RimParams",
    "ShadowPathParams",
    "RejectionParams",
    "RecoveryParams",
    "EndsParams",
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

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=(
                "force_unit",
                "tau",
                "mid_mm",
                "up_mm",
                "down_mm",
                "max_step_px",
                "max_iterations",
            ),
            non_negative=(
                "stop_px",
                "w1",
                "w2",
                "k1",
                "k2",
                "k_regional",
                "smooth_mm",
                "min_iterations",
                "init_below_px",
                "margin_mm",
                "max_restarts",
                "restart_above_mm",
            ),
            within={"n_points": "[3, 100000]"},
        )


@dataclass(frozen=True)
class PosteriorParams:
    """The paper's posterior choice of the snake points (section II.B, end)."""

    k_intensity: float = 0.005
    """Keep points with intensity > I_mean + k_intensity * I_var (paper: 0.005; 8-bit grey values)."""
    neighbour_px: float = 10.0
    """Points closer than this are connected, reference px (paper: 10 px = 1 mm)."""

    def __post_init__(self) -> None:
        check_fields(self, positive=("neighbour_px",))


@dataclass(frozen=True)
class FlankParams:
    """Following a contour down the bone's flanks (:mod:`.flanks`), past where the path stops.

    Lengths in mm; every level is relative to this frame's own speckle (see
    :func:`~BoneUSRecon.Logic.segmentation.flanks.extend_flanks`): no grey level enters.
    """

    enabled: bool = True
    """Extend the candidates' flanks (off: the contours of the optimal path alone)."""
    min_start_deg: float = 20.0
    """An end is extended only when the contour already descends outward at least this steeply there, degrees (ours: a flat end is the path's own decision, and a layer running off the bone at its level is flat; a convex bone's flank only steepens outward)."""
    retreat_mm: float = 1.0
    """The trace starts this far (arc length) inside the contour's end and replaces its last part where it reaches at least as far (ours: the path's last columns on a steep flank are its least certain, and a tail that slid onto a layer is re-traced on the bone)."""
    restart_deg: float = 45.0
    """Where the contour's end is steeper than this, the trace starts farther back (up to ``restart_mm`` more), at the first point not so steep, degrees (ours: 97 % of the gold points the surface missed lay on flanks steeper than 45 degrees, where one depth per column samples a flank ever more sparsely and the path's last columns drift off it)."""
    restart_mm: float = 3.0
    """How much farther back than ``retreat_mm`` a trace may start, mm of arc."""
    fit_mm: float = 2.0
    """Length of contour inside the start from which the outward direction and the curvature are taken, mm (ours: ~8 working pixels; long enough to average the per-column jitter, short against a bone's radius of curvature)."""
    step_mm: float = 0.4
    """Arc-length step of the trace, mm (a little over one working pixel of 0.25-0.3 mm)."""
    max_mm: float = 6.0
    """Longest trace, mm of arc (issue 10's cadaver crest: ~6 mm of flank steeper than 45 degrees)."""
    band_mm: float = 0.9
    """Half-width of the search band across the extrapolated arc, mm (a curvature misjudged by 0.1 /mm departs 0.8 mm from it over 4 mm)."""
    offset_mm: float = 0.2
    """Spacing of the samples across the band, mm (under a working pixel; the full-resolution refinement does the rest). With ``step_mm`` it bounds the ridge's turn per step down from the arc: atan(0.2 / 0.4), 27 degrees (never up: a convex flank only steepens)."""
    outside_mm: tuple[float, float] = (0.75, 1.75)
    """Window outward of a sample (on the tissue side of the flank) that its echo is compared with, mm from the sample (past the echo's lateral blur, ~0.3 mm sigma)."""
    shadow_z: float = 1.0
    """Shadow z-score under a sample along the beam (:mod:`.evidence`) at which its echo counts double, robust z units (ours: ``ShadowPathParams.shadow_z_full``, one spread darker than the tissue beside it; no shadow, no bonus)."""
    null_mm: float = 2.75
    """Centre of the null band: the same search, the same width, this far outward of the arc in the tissue beside the flank, mm (clear of the band and the echo's blur)."""
    run_mm: float = 1.5
    """Length over which the ridge and null evidence are averaged along the trace before the stop rule, mm (ours: four steps, five or six working pixels: one grain of speckle does not stop or carry a trace; on humerus 17, 60 frames, kept points beyond 0.5 mm of the bone: 1.7 % at 0.9 mm, 1.5 % at 1.5 mm, with ``stop_z`` 2)."""
    gap_mm: float = 0.9
    """The trace stops where its evidence stays under the stop level for this long, mm (a short dropout of the echo, as on real cortex, is bridged)."""
    stop_z: float = 4.0
    """The trace continues while its averaged ridge evidence exceeds the null band's median by this many of the null's robust spreads (robust z units, as :mod:`.evidence`; ours: at 3 the traces added a few points off the bone where a fascia crosses the flank or under a grey shadow, on the hard simulated tibia 6 of 70 and 10 of 116 added points farther than 0.5 mm; at 4, 2 of 55 and 5 of 63)."""
    max_deg: float = 88.0
    """Steepest direction the trace may take, degrees below the lateral axis (a beam from above cannot see under the bone)."""
    max_curvature: float = 0.5
    """Largest curvature the extrapolated arc takes from the contour, 1/mm (a radius of 2 mm: the tightest bone edge expected; more is the jitter of the contour)."""
    refine_mm: float = 0.3
    """Half-length of the full-resolution profile across the trace on which each point's echo peak is fitted, mm."""

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=(
                "fit_mm",
                "step_mm",
                "max_mm",
                "band_mm",
                "offset_mm",
                "outside_mm",
                "shadow_z",
                "null_mm",
                "run_mm",
                "refine_mm",
            ),
            non_negative=("retreat_mm", "restart_mm", "gap_mm", "stop_z", "max_curvature"),
            within={"min_start_deg": "[0, 90)", "restart_deg": "(0, 90]", "max_deg": "(0, 90]"},
        )
        if not self.outside_mm[1] > self.outside_mm[0]:
            raise BoneUSReconError(
                f"FlankParams.outside_mm must be increasing, got {self.outside_mm!r}"
            )
        if not self.null_mm > 2 * self.band_mm:
            raise BoneUSReconError(
                f"FlankParams.null_mm must be > 2 band_mm (the null band clear of the search band), got {self.null_mm!r}"
            )


@dataclass(frozen=True)
class RimParams:
    """Following a contour's ends round the bone's outline in polar coordinates (:mod:`.rim`).

    Lengths in mm; the stop level is a share of the contour's own echo in the frame (no
    grey level enters).
    """

    enabled: bool = True
    """Follow the contours' ends on from where :mod:`.flanks` left them (off: they stay)."""
    candidates: int = 5
    """Only the strongest this many candidates of a frame (not reverberation copies) are followed (ours: on the hard simulated humerus and tibia, seed 53 at 475 x 405, the kept contour was the third to fifth strongest in 18 of 80 frames, the third in 12: layers over a faint bone are stronger; with 3, on the humerus, tibia and radius of that seed the true contour steeper than 60 degrees covered within 0.5 mm went from 0.48 to 0.58, the surface's gold distance 0.45 -> 0.40 mm. From 3 to 5, session 31: that coverage on 13 hard sweeps 0.577 -> 0.593, unseen 0.593 -> 0.603; gold mean on unseen seeds 109/113 0.222 -> 0.219 mm, 127/131 0.227 -> 0.226, two bones in view 0.223 -> 0.212; recall, wrong share and the L14 recording unchanged; ~1.4 ms per frame more at 475 x 405)."""
    min_points: int = 12
    """Contours with fewer points are not followed (a circle fit needs an arc)."""
    max_start_deg: float = 20.0
    """Of a contour with a bright echo over a shadow (the echo stronger than the shadow's contrast), only ends whose last ``fit_mm`` descends outward less steeply than this are followed, degrees (ours: ``FlankParams.min_start_deg``: an end that descends is the arc tracer's, and its stop rule ended it; following those on too took fasciae touching the flank on the standard simulated sweeps). A faint echo's ends all are, and those of a contour with no shadow."""
    fit_mm: float = 2.0
    """Length of contour at an end over which its slope is measured, mm (as ``FlankParams.fit_mm``); an end with less contour than this before the contour's first break (``join_mm``) is not followed."""
    join_mm: float = 2.0
    """Consecutive contour points farther apart than this are not joined, mm (the paper's posterior choice: 10 reference pixels, 1 mm). An end cut off from the contour by such a break is a piece apart (a layer beside the bone that the path stepped onto: on the standard simulated clavicle, seed 0, frame 9, a trace from such a piece ran on along the layer 3 mm off the bone), and its own direction is no outline's."""
    radius_mm: tuple[float, float] = (2.0, 40.0)
    """Radii of the fitted circle accepted, mm (a clavicle's 5 mm to a tibia's broad face; a flatter fit is a layer)."""
    step_mm: float = 0.3
    """Arc-length step at the end's radius, mm (about a working pixel)."""
    band_mm: float = 5.0
    """Half-width of the radial band searched about the end's radius, mm (a crest departs from its fitted circle by a few mm; a broad bone's flank more: the circle fitted to a contour that stops at its shoulder follows the bone's other, tighter side, and the L14 forearm's right flank lies up to 4.4 mm outside it (frame 9); ours, session 53: at 3 the trace met the band's edge and turned back in frames 9, 12, 15 and 19, at 5 it follows the flank; reconstruction from the reference: recording 0.246 -> 0.247 mm, grey-shadow copy 0.265 -> 0.252, cadaver copy 1.030 -> 0.767, look-alikes copy 0.288 -> 0.261; the simulated harness's gold means (five seed pairs, bone-free ends) within 0.0006 mm, recall and wrong share unchanged)."""
    offset_mm: float = 0.1
    """Spacing of the radial samples, mm."""
    max_step_mm: float = 0.2
    """Largest change of radius per step, mm: the outline may depart from the fitted circle's tangent by up to ~34 degrees (a crest's or a humerus's flank runs straight on where a circle fitted to its top turns down: at 0.1, ~18 degrees, the traces stopped a few mm down such flanks; ours, with ``max_deg`` 110 and ``min_descent_deg`` 10, on the hard simulated humerus, tibia and radius of seeds 53 and 59 at 475 x 405 the true contour steeper than 60 degrees covered within 0.5 mm went from 0.39 / 0.42 to 0.48 / 0.54, the surface's mean gold distance from 0.66 / 0.55 to 0.45 / 0.42 mm, the share of kept points over 1 mm from the bone (3D) 3.1 / 2.8 % -> 3.0 / 2.7 %)."""
    min_descent_deg: float = 10.0
    """Where the radius grows faster than one radial sample per step (the outline running flatter than the fitted circle), the outline so implied must still descend at least this, degrees below the horizontal (a bone's outline descends outward from its apex; a fascia leaving it at its level runs on nearly level: on the hard simulated tibia with fascia, seed 5, ``max_step_mm`` 0.2 without this limit followed flat ends on along the fascia, 37 % of the added points over 0.5 mm from the bone, up to 4.8 mm; with it at 10 to 30 degrees 15 %, up to 0.62 mm; ours: 10, at 20 the hard sweeps of seed 59 were 0.06 mm further from their gold, the L14 recording 0.03 mm from its reference)."""
    outside_mm: tuple[float, float] = (0.75, 1.75)
    """Window out along the ray that a sample's echo is compared with, mm (as ``FlankParams.outside_mm``)."""
    part_window_share: float = 0.3
    """Near the image's or field of view's edge a sample is measured on the part of its windows (``outside_mm`` out and in) inside it, where each holds at least this share of its samples; 1: only whole windows (ours: with whole windows every trace stopped ``outside_mm[1]`` short of the field's edge: on the L14 recording, whose bone runs into the left edge, every contour ended 1.7 mm inside it; 0.3 of the window is 0.3 mm of tissue past the echo's blur, a grain of speckle or two)."""
    run_mm: float = 1.5
    """Arc over which the echo is averaged, mm (as ``FlankParams.run_mm``)."""
    inside: bool = True
    """The echo is also measured against the window as far inward (the smaller of the two counts): a line, not a step."""
    edge_mm: float = 0.8
    """Windows either side of a sample for the edge measure, mm: the log ratio of the mean grey over this length outward to the mean as far inward, taken where it beats the line's (a steep flank whose echo has faded is the edge between the tissue and the bone's shadow; ours: about the echo's own thickness plus a speckle grain, so the edge is located within it). 0: the line alone."""
    keep: float = 0.3
    """The trace continues while its echo is at least this share of the contour's own (log ratios; ours: on the L14 forearm the flank's echo is 0.5-1.0 of the top's)."""
    gap_mm: float = 1.2
    """A shorter dropout under the level is bridged, mm (``FlankParams.gap_mm`` is 0.9; ours: where the path stopped on a faded stretch the trace's first steps are that stretch: on the L14 recording's cadaver-level copy, frame 18, the right end's first 0.9 mm was under the level and 10 mm of flank over it followed; at 1.2 mm the recording's reconstruction went from 0.352 to 0.333 mm from its reference, the hard simulated sweeps' unchanged within 0.01 mm)."""
    fade_mm: float = 3.6
    """A longer stretch under ``keep`` is bridged too, up to this length, mm, where the echo only faded there (every step of it above the null level: still a line, fainter than speckle's best) and returns after it, held at least as long as the stretch (0: no such bridge). A real bone's echo dims where its outline turns (the L14 forearm's right shoulder: 2.1 mm at 0.27-0.29 of the contour's own echo, then 0.8 down the flank, in frames 9-11 and 15) and the flank past it was lost. Ours: 2.4 bridges the recording's shoulder, 3.6 also the cadaver copy's; the reconstruction 0.270 -> 0.246 mm from the reference, the cadaver copy 1.202 -> 1.030, the look-alikes copy 0.299 -> 0.288; on 520 simulated sweeps (``bench_sweeps.py`` groups, five seed pairs, and bone-free ends) every set's gold mean within 0.0007 mm, recall and wrong share unchanged. A stretch with a step at speckle level is a line that ended: between two bones side by side the trace crossed the gap onto the other's flank when only the length was asked (hard radius 14 mm, seed 179: the surface 0.224 -> 0.308 mm)."""
    null_mm: float = 10.0
    """The null band: the same search this far out along the rays, in the tissue beside the bone, mm; at least ``2 band_mm``, so the null band starts where the search band ends (the bone's own flank is no null; farther out more of it leaves a small image: at 12 the 26 mm tall phantom of ``test_segmentation_rim.py`` kept under ten null steps and no trace)."""
    stop_z: float = 0.0
    """The trace's echo must also beat the null's median by this many of its robust spreads (pooled over the frame's traces: what speckle and the tissue's layers give with the same search)."""
    max_mm: float = 15.0
    """Longest trace, mm of arc at the end's radius (the L14 forearm's right flank: 10-20 mm from the shoulder; bounds the work on a flat fit's large radius)."""
    max_deg: float = 110.0
    """Furthest direction followed, degrees from the beam's up direction about the fitted circle. It bounds the search, not the outline's slope (``max_slope_deg``, ``edge_slope_deg`` end the trace by its own descent): a circle fitted to a bone's top lies inside the bone and is smaller than it where the flanks run straight (a crest, a humerus's section narrowing upward), so the flank's points lie at directions past 90 degrees from its centre (ours: at 80, before the slope limits existed the guard against following the shadow's side below the widest point, traces on the hard simulated humerus stopped at 70 degrees about a 5.7 mm circle with 6 mm of flank to go; see ``max_step_mm`` for the figures)."""
    max_slope_deg: float = 85.0
    """The trace ends before its first point descending steeper than this over ``slope_mm``, degrees (past the bone's widest point a beam from above sees nothing; ours: the L14 forearm's echo band runs to ~80 degrees; on the standard simulated clavicle, seed 0, traces ran on down the ring's side past the widest point, 1-2 mm off the bone; 90: no limit)."""
    edge_slope_deg: float = 75.0
    """As ``max_slope_deg`` for points the edge measure placed (no echo), degrees (past the bone's widest point the edge of its shadow runs straight down; ours: issue 10's 70 degrees with a margin; at 80 the traces ran on down the shadow's side on the standard simulated radius, seed 1, 1-2 mm off the bone)."""
    slope_mm: float = 1.2
    """Length of contour and trace over which the descent is measured, mm (a few speckle grains)."""
    min_steps: int = 3
    """Shorter traces are dropped."""
    refine_mm: float = 0.3
    """Half-length of the full-resolution profile along the ray on which each point's echo peak is fitted, mm."""

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=(
                "radius_mm",
                "step_mm",
                "band_mm",
                "offset_mm",
                "max_step_mm",
                "outside_mm",
                "run_mm",
                "refine_mm",
                "slope_mm",
                "join_mm",
            ),
            non_negative=(
                "keep",
                "edge_mm",
                "gap_mm",
                "fade_mm",
                "candidates",
                "min_points",
                "min_steps",
                "null_mm",
                "stop_z",
            ),
            within={
                "max_deg": "(0, 180]",
                "max_slope_deg": "(0, 90]",
                "edge_slope_deg": "(0, 90]",
                "min_descent_deg": "[0, 90)",
                "part_window_share": "(0, 1]",
            },
        )
        for name in ("radius_mm", "outside_mm"):
            lo, hi = getattr(self, name)
            if not hi > lo:
                raise BoneUSReconError(f"RimParams.{name} must be increasing, got {(lo, hi)!r}")
        if self.edge_mm > self.outside_mm[1]:
            raise BoneUSReconError(
                f"RimParams.edge_mm must not exceed outside_mm[1] ({self.outside_mm[1]}), "
                f"got {self.edge_mm!r}"
            )
        if self.null_mm < 2 * self.band_mm:
            raise BoneUSReconError(
                f"RimParams.null_mm must be >= 2 band_mm ({2 * self.band_mm:g}: the null band "
                f"clear of the search band), got {self.null_mm!r}"
            )


@dataclass(frozen=True)
class SettleParams:
    """Moving a contour that runs on a layer just over the bone down onto it (:mod:`.settle`).

    Lengths in mm; the level is in robust z units of this frame's own shadow-onset
    spread (no grey level enters).
    """

    enabled: bool = True
    """Settle the candidates (off: the contours of the optimal path as refined)."""
    depth_mm: float = 3.0
    """Deepest the bone is sought under a contour point, mm (ours: on hard simulated sweeps 68 % of the kept points farther than 0.5 mm from the bone lay 0.5-3 mm over it, 2 % deeper)."""
    own_mm: float = 0.6
    """A point's own onset is the best within this depth under it, mm (a bright echo's onset lies up to ~0.5 mm under its peak: the window above it then holds the echo)."""
    window_mm: tuple[float, float] = (0.3, 1.2)
    """Windows above and below a pixel along the beam for the onset, mm from it (from, to): past the echo's axial blur, short enough to fit between a layer and the bone 1 mm under it."""
    run_mm: float = 1.5
    """Length of contour over which the onsets are averaged before the decision, mm (a layer over the bone runs for mm; one grain of speckle does not)."""
    gain_z: float = 1.5
    """A point moves when the averaged onset at its best depth beats its own by this many robust spreads (ours, hard simulated sweeps seed 7: at 1.5, 411 of 484 moved points came >0.2 mm nearer the bone and 50 went >0.2 mm farther; at 2, 240 / 20 of 269; at 3, 67 / 2 of 69)."""

    shadow_z: float = 0.5
    """Least shadow z-score under the new point (:mod:`.evidence`, averaged alike), robust z units (ours: between the evidence's zero and full levels; the hard simulated sweeps' grey shadow, 0.65 of the tissue beside it as on the cadaver, scores 0.6-0.9 under a faint top; a phantom bone that passes sound, brighter inside than the tissue beside it as the L14 forearm, scores below 0 and nothing moves)."""

    gap_ratio: float = 1.0
    """Between the point and the new one the darkest working pixel must be at most this times the tissue level at its depth (averaged alike; ours: soft tissue lies between a layer and the bone, a thick echo is bright through)."""

    echo_ratio: float = 1.0
    """The new point's echo must be brighter than this times the tissue level at its depth (averaged alike; ours: an echo is brighter than the typical tissue, the inside of a bone that passes sound is not)."""

    thin_mm: float = 1.2
    """The line a point is on must end within this depth under it (a working pixel no brighter than the tissue level there), mm (ours: a fascia is a thin line, blurred to ~1 mm along the beam on the hard simulated sweeps, where 0.6 mm blocked 163 moves onto the bone on six sweeps and 1.2 mm 60; the L14 forearm's cortex is a band ~1 mm thick over a bone that passes sound, 1-1.5 mm along the beam on its flanks, and its top is the surface: with no such test its flank points went 2-3 mm into it; none moves up to 1.5 mm)."""

    max_slope_deg: float = 45.0
    """Only where the contour (averaged over ``run_mm``) is at most this steep, degrees (ours: along the beam, under a steep flank lies the bone's inside, where a fascia touching the flank or the inside of a bone that passes sound is met before any layer; the layers over the bone found on the hard simulated sweeps cap tops and shoulders)."""

    own_max_z: float = 1.0
    """A point moves only while its own onset (averaged alike) is at most this, robust z units (ours: a point with the shadow starting under it is on the bone, whatever lies deeper; on the standard simulated sweeps, whose grey shadow holds reverberation copies of the bone's echo, points of the bone were otherwise moved onto the copy 3 mm down, and a false echo over the bone accepted; at 0.5 two hard sweeps each lost a frame, radius 13 frame 27 and ulna 29 frame 37)."""

    def __post_init__(self) -> None:
        check_fields(
            self, positive=("depth_mm", "run_mm", "window_mm"), non_negative=("own_mm", "gain_z")
        )
        if not self.window_mm[1] > self.window_mm[0]:
            raise BoneUSReconError(
                f"SettleParams.window_mm must be increasing, got {self.window_mm!r}"
            )
        if not self.depth_mm > self.own_mm:
            raise BoneUSReconError(
                f"SettleParams.depth_mm must exceed own_mm, got {self.depth_mm!r}"
            )


@dataclass(frozen=True)
class ShadowPathParams:
    """The default segmenter: contrast-adaptive bone evidence and optimal paths across columns.

    Every level is relative (see :mod:`.evidence`): grey values enter only as ratios
    between regions of the same frame, and those ratios only in units of their own
    spread over the frame (robust z-scores). A score of ``null_z`` thus means "this
    many times what speckle produces by chance", whatever the probe, gain, depth or
    tissue; no absolute grey level decides bone / no bone.
    """

    work_mm: float = 0.25
    """Target pixel size of the down-sampled working image, mm (ours: the sub-pixel step restores full resolution; sets the speed)."""
    phase_symmetry: bool = False
    """Echo evidence from 1-D log-Gabor phase symmetry along depth instead of the band/above log-ratio (:func:`.phase.phase_symmetry_depth`; measured and dropped, see :mod:`.phase`)."""
    phase_wavelengths_mm: tuple[float, ...] = (0.6, 1.2, 2.4)
    """Log-Gabor wavelengths of the phase symmetry, mm."""
    phase_weight: float = 0.0
    """Phase symmetry as an additional echo term: the score is multiplied by ``1 - k + k min(1, PS / PS_90)`` with ``k`` this weight and ``PS_90`` the frame's 90th percentile of the symmetry (0: off; measured and left off, see :mod:`.phase`)."""
    confidence_weight: float = 0.0
    """Weight of the confidence-map drop (Karamalis random walk, :mod:`.confidence`) in the shadow z-score, ``(1 - k) shadow_z + k confidence_z`` (0: off, the map is not computed; measured and left off, see :mod:`.confidence`)."""
    confidence_grid_mm: tuple[float, float] = (1.5, 0.5)
    """Lateral and axial pixel size of the grid the confidence map is solved on, mm (its cost grows as n w^2)."""
    confidence_alpha: float = 2.0
    """Attenuation coefficient of the confidence map over the normalised depth (Karamalis et al. 2012: 2)."""
    confidence_beta: float = 90.0
    """Weight of the normalised intensity difference in the confidence map's edge weights (Karamalis et al. 2012: 90)."""
    confidence_gamma: float = 0.05
    """Horizontal penalty of the confidence map, in units of the normalised difference (Karamalis et al. 2012: 0.05)."""
    mid_mm: float = 0.4
    """Height of the bright band, mm (ours: a thin real cortical echo; a thicker band dilutes a low-contrast echo of 1.3x the tissue above it)."""
    up_mm: float = 1.5
    """Height of the region right above the band that the echo must outshine, mm."""
    shadow_gap_mm: float = 1.5
    """Rows skipped under the band before the shadow windows, mm (the echo's tail: real cortical echoes are 0.5-1 mm thick, all below the surface)."""
    shadow_mm: float = 5.0
    """Bottom of the near shadow window below the band, mm."""
    near_shadow: bool = True
    """Also require the near window (``shadow_gap_mm`` .. ``shadow_mm``) to be shadow (the worse of the two counts)."""
    far_shadow_mm: float = 12.0
    """Bottom of the long shadow window, mm (shadow depth: a vessel lumen or a gap between fasciae is dark for a few mm only)."""
    cover_gap_mm: float = 1.0
    """Top of the cover window above the band, mm (above the echo's own blur)."""
    cover_mm: float = 5.0
    """Bottom-most extent of the cover window above the band, mm."""
    cover_ratio: float = 0.5
    """The cover (tissue above) must be at least this fraction of the tissue level at its depth (a ratio: gel, air and blood are anechoic, soft tissue is not)."""
    cover_min_mm: float = 0.5
    """Least height of the cover window inside the image for the cover to be judged, mm."""
    tissue_percentile: float = 60.0
    """Percentile over the columns giving the tissue level at each depth (ours: bone and shadow fill fewer than 30 % of the columns at most depths, a thin echo barely counts)."""
    shadow_z_zero: float = -1.0
    """Shadow z-score at which the shadow gate closes, robust z units (ours: half a spread brighter than the tissue at that depth: tissue, not shadow, beneath)."""
    shadow_z_full: float = 1.0
    """Shadow z-score at which the shadow gate is fully open, robust z units (ours: one spread darker than the tissue beside it; a grey shadow 0.65 of the tissue, or the L14 bone whose interior is barely darker, still opens it partly and the echo carries the score)."""
    shadow_gate_max: float = 2.0
    """Past ``shadow_z_full`` the gate keeps rising, at the same slope, up to this factor (2: reached at a shadow z of 3 with the defaults), so a shadow far darker than the tissue beside it counts for more than a marginal one (ours, session 46: a bone stops sound, soft tissue does not, so a deep shadow is the bone's surest sign; with the gate capped at 1 a faint echo over a black shadow, echo 1.2x the tissue above on a hard simulated clavicle, scored under a brighter layer with tissue beneath and the sweep was tracked on the layer, recall 0.03, wrong 0.90; at 2: recall 0.93, wrong 0. With ``shadow_gate_width_mm`` 1, the lead's 88 harness sweeps: gold 0.2445 -> 0.2093 mm, recall 0.991 -> 0.996, wrong share 0.0003 -> 0; the L14 recording's cadaver copy 1.416 -> 1.175 mm, the recording 0.270 -> 0.268, its grey-shadow copy 0.245 -> 0.268; 1 keeps the gate as it was. Figures: ``Testing/benchmarks/README.md``, session 46)."""
    shadow_gate_width_mm: float = 1.0
    """The gate rises past 1 on the lowest shadow z-score within this many mm to either side of the pixel, mm (ours, session 46: a bone's shadow is as wide as the bone, a speckle window's dark tail is a column or two; with the pixel's own z a speckle path at the track's depth was kept in a frame with no bone (``Testing/test_segmentation_cli.py``'s frame 3). Over the lead's 88 harness sweeps, +-0.5 / 1 mm (1 chosen): gold 0.2241 / 0.2093 mm, recall 0.994 / 0.996, the true contour covered 0.937 / 0.942; the pixel's own z: 0.2170, 0.994, 0.934)."""
    shadow_percentile: float = 80.0
    """Percentile over the columns giving the tissue level the shadow windows are compared with (ours: tissue beside a bone whose shadow covers up to 80 % of the width)."""
    null_dark_fraction: float = 0.0
    """A pixel whose band or the window above it is darker than this fraction of the tissue level beside at its depth (``shadow_percentile``) lies near the display's floor and is left out of the echo and shadow z-scores' nulls (:func:`.evidence._null_pixels`; 0: every valid pixel, the default). Measured at 0.25 with ``shadow_z_zero`` -0.8 (``Testing/benchmarks/README.md``, sessions 27 and 28): a darker, cleaner shadow no longer weakens the bone (``bench_levels.py`` at 160 x 128: display 9 dB darker, recall 0.81 -> 0.97; less electronic noise 0.84 -> 0.98), the L14 cadaver-level copy 1.62 -> 0.97 mm, unseen harness sweeps' gold 0.236 -> 0.226 mm. Not the default: on a black shadow (the standard simulator) the nulls lose a quarter of the frame, every z-score grows ~1.25x, and speckle and layers past the bone's shoulder clear the path's null level: twice the pixels over it, 4-5x the path groups, segmentation 38-80 % slower at 480 x 640 (21-25 frames/s), kept points' 95th percentile 0.09 -> 0.39 mm on a standard ulna."""
    null_min_share: float = 0.3
    """Least share of the valid pixels the nulls are estimated on; below it (a frame mostly shadow) every valid pixel is used (ours)."""
    shadow_null_tolerance: float = 0.25
    """The shadow z-score's centre is the frame's median unless that lies more than this many spreads above the centre of the lower tail (the tissue's; :func:`.evidence._shadow_scale`), robust z units (ours: clean frames lie within 0.03-0.1 spreads of it, frames whose bone's shadow fills half the image 0.4-0.6; at 0.25 the lead's harness, seeds 53, 59, 71 and 73, changed in 3 sweeps of 78, all for the better: hard radius seed 71 at 160 x 128 recall 0.85 -> 0.97; at 0 in 18, two of them with a wrong frame; at 0.5 the radius was not helped)."""
    null_z: float = 0.8
    """Score (robust z units) a column needs to pay off over "no bone" in the path (ours: 1.5 x the speckle spread; see :mod:`.evidence`)."""
    max_z: float = 8.0
    """Cap on a pixel's score (ours: one very bright spot cannot outweigh a long contour)."""
    slope_penalty: float = 0.05
    """Cost per (mm of depth change per lateral mm)^2 between neighbouring columns, in score units (ours: small, so steep flanks are kept)."""
    max_slope: float = 3.0
    """Largest depth change per lateral mm of the path (tan 72 degrees; past the path's reach a flank is followed by ``flanks``)."""
    settle: SettleParams = field(default_factory=SettleParams)
    """Moving each candidate that runs on a layer just over the bone down onto it, before its flanks are followed (:mod:`.settle`)."""
    flanks: FlankParams = field(default_factory=FlankParams)
    """Following each candidate down the bone's flanks, past where one depth per column holds (:mod:`.flanks`)."""
    rim: RimParams = field(default_factory=RimParams)
    """Following the ends the flanks tracer left, flat ones included, round the outline in polar coordinates (:mod:`.rim`)."""
    near_field_mm: float = 2.0
    """Rows shallower than this are never bone, mm (gel, skin line and lens reverberation)."""
    contact_mm: float = 4.0
    """Depth below the near field over which a column's contact with the skin is judged, mm."""
    contact_dark_fraction: float = 0.7
    """A column with more than this share of those rows darker than half the tissue level at their depth has no contact (ours)."""
    gap_shade: bool = True
    """Withhold from the shadow the shade a partial no-contact gap at an edge of the field casts on the columns under it (:func:`.evidence._edge_gap`; issue 10: a fascia under the skin gap of the hard simulator scored as bone: ulna seed 29 at 0.3 mm, recall 0.78 -> 0.95, wrong share 0.15 -> 0.025)."""
    gap_probe_mm: float = 3.0
    """Depth below the near field over which a column is judged to lie under a gap, mm (ours: the gel or air wedge under a skin curving away from the probe; deeper than the skin line's own blur)."""
    gap_dark_fraction: float = 0.3
    """A column is under a gap when the share of those rows darker than half the tissue level at their depth exceeds the frame's typical column's share (median over the usable columns) by at least this (ours: the contact rule's criterion, for a column only partly uncoupled; an uncoupled column, more than ``contact_dark_fraction`` dark, has no contact at all; measured against the typical column since speckle and a hypoechoic layer under the skin darken every column's rows, see :func:`.evidence._edge_gap`)."""
    gap_min_mm: float = 1.0
    """Least width of a run of such columns from an edge of the usable field, mm (ours: four working pixels; narrower runs are dark speckle, as on the L14 recording)."""
    gap_margin_mm: float = 3.0
    """The gap's columns are extended this far inward, mm (ours: the skin curves back to contact over a few mm and its shade spreads under the contact point; the simulator's gap tapers as the square of the distance from its inner end)."""
    fov_grey: float = 4.0
    """Grey level (0..255) below which a pixel counts as black, for finding the imaged field of view (instrument fact: scan-converted images are exactly 0 outside it)."""
    fov_fraction: float = 0.25
    """A column is inside the field of view when more than this fraction of its pixels are above ``fov_grey``."""
    fov_margin_mm: float = 0.5
    """Columns this close to the edge of the field of view are ignored too, mm (block averaging mixes them with the black margin)."""
    switch_cost: float = 1.0
    """Cost of entering or leaving the "no bone" state, score x mm (ours: a run must gather this much evidence above null to exist)."""
    merge_gap_mm: float = 3.0
    """Bone runs separated by a gap shorter than this (and a depth step < merge_step_mm) are one contour, mm (an echo dropout)."""
    merge_step_mm: float = 1.5
    """Largest depth step across a merged gap, mm."""
    min_length_mm: float = 2.0
    """Shortest candidate contour, mm laterally (ours: shorter runs are speckle)."""
    n_passes: int = 3
    """Optimal-path passes per frame; each pass suppresses what the previous ones found (ours: bone, fascia, reverberation)."""
    max_candidates: int = 5
    """Largest number of candidate contours kept per frame."""
    dome_mm: float = 0.5
    """A piece of a path besides its strongest is offered as a candidate of its own when both its ends lie at least this much deeper than its apex, mm (a second bone the path ran on to, :func:`.candidates._separate_domes`; ours: a forearm bone's visible arc falls 1-3 mm from its top to its ends, a layer off the bone's shoulder is flat or falls one way)."""
    suppress_mm: float = 1.5
    """Half-height of the band suppressed around a found contour before the next pass, mm."""
    kink_slope: float = 0.6
    """Outward descent (depth mm per lateral mm, ~31 degrees) from which a turn to less than a third of it ends the bone (convexity, see candidates.convex_part)."""
    kink_mm: float = 1.5
    """Lateral window over which those slopes are measured, mm."""
    shoulder_slope: float = 0.15
    """Least outward descent (depth mm per lateral mm, ~8.5 degrees) over ``kink_mm`` inside a point from which a turn to less than half of it over ``2 kink_mm`` outward, with less of a shadow step under the part beyond, is a layer leaving the bone's shoulder (see candidates._shoulder_cut)."""
    shoulder_min_mm: float = 8.0
    """Least lateral extent of the part beyond a shoulder turn for it to be cut as a layer, mm (a fascia running off the bone runs on for many mm; a shorter gentle stretch beyond a turn may be the bone's own relief, or a layer the flank trace cannot yet follow the wall under. Measured: at 0 / 3 / 5 / 8 mm, real L14 flank coverage 0.56 / 0.58 / 0.60 / 0.61 (0.61 without the cut: the radius' 5-7 mm plateau before its flank was cut); hard sweeps seeds 5, 7, 29: kept 1-3 mm off 6 / 7 / 12 / 13 frames (18 without); reconstruction gold mean, seeds 5 and 7, 0.3 mm / 0.108 mm, with the first form of the excursion rule: 0.880 / 0.951 mm at 5, 0.818 / 0.907 at 8, 0.835 / 0.925 without the cut; see Testing/benchmarks/README.md, branch shoulder)."""
    shoulder_short_mm: float = 3.0
    """Least lateral extent of a shorter layer (under ``shoulder_min_mm``) beyond a shoulder turn off the apex's sides for it to be cut, mm, where the bone's shadow is clear under the part inside (``shoulder_short_step``), the part kept is at least ``shoulder_min_mm`` wide and the part beyond never rises over the turn by ``shoulder_slope`` over ``kink_mm`` (ours: twice ``kink_mm``, the turn's own outward window; see candidates._shoulder_cut. Measured, hard sweeps, seeds 5 and 7 at 0.3 mm / seed 53 at 0.108 mm, humerus, tibia, radius: kept points over 1 mm from the bone in 3D 0.046 -> 0.032 / 0.030 -> 0.028, flank coverage kept; see Testing/benchmarks/README.md, branch fascia)."""
    shoulder_short_step: float = 0.3
    """Least median underside step (candidates._underside_step: the log ratio of the grey over the contour to that under it, each relative to the tissue at its depth) under the part inside a turn for a shorter layer beyond it to be cut (0.3: the bone's shadow at most ~0.74 of the tissue over it, the cadaver's 0.65 passes; a bone that passes sound, the L14 forearm, has 0.02-0.25 under most of its turns and keeps ``shoulder_min_mm``. Measured at 0.2 / 0.3 / 0.45: L14 reconstruction 0.359 / 0.352 / 0.352 mm from the reference, kept points over 1 mm from the bone on the hard 0.3 mm sweeps, seeds 5 and 7, 0.032 / 0.032 / 0.034)."""
    shoulder_step_ratio: float = 0.25
    """The part beyond such a turn is a layer when the step from the tissue over it to what lies under it (candidates._underside_step) is, on median, under this fraction of the step under the part inside (a ratio of the contour's own values: shadow under the bone's wall, tissue or the bone's echo under a layer; ours: hard sweeps seeds 5, 7, 29, both geometries, kept 1-3 mm off 18 -> 10 / 6 / 6 frames at 0 / 0.25 / 0.5, flank coverage 0.794 -> 0.796 / 0.787 / 0.779)."""
    climb_mm: float = 1.0
    """A contour's side that went down a flank and then climbs back by more than this past its deepest point is cut there, mm (:func:`.candidates._cut_climbing_ends`: it ran on up onto a bone beside it, the fibula 10 mm under the tibia's top, the radius beside an ulna; 0: off. Ours: twice the ~0.5 mm the path's and the rim's points wander about a flank. Measured: harness seeds 109/113, 52 sweeps, wrong 0.001 -> 0, gold 0.216 -> 0.215 mm; Testing/benchmarks/README.md, branch fibula)."""
    valley_mm: float = 0.5
    """A contour is split where it dips deeper than this below its shallowest point on each side of the dip, with less than a third of the shadow on one side than on the other, mm (ours: a layer meeting the bone's flank and climbing away, tissue beneath it; a groove in the bone has the shadow on both sides and stays whole; 0.5 mm is five times the refined contour's jitter)."""
    beneath_ratio: float = 0.8
    """A candidate with an echo at least this fraction of its own grey level under it let the sound through: not bone (a ratio; bone returns far less from beneath it)."""
    reverb_tolerance: float = 0.12
    """Relative tolerance of the reverberation rules (depth ratio 2 or equal spacing), ours."""
    series_min_mm: float = 1.0
    """Least spacing of a reverberation series, mm (closer lines are one echo's thickness)."""
    series_trough_ratio: float = 0.7
    """Between consecutive lines of a reverberation series the grey is below this fraction of the tissue level at that depth (a ratio: shadow, not tissue, between copies)."""
    copy_echo_ratio: float = 1.5
    """A line is no copy of a series' top if its echo z-score exceeds the top's by more than this factor (a ratio: a copy returns less sound than its reflector, though over the shadow it may stand out up to ~1.4x more, measured on the simulated far cortex; the L14 bone under muscle layers stands out 3x more than the layers)."""
    series_extend_deg: float = 45.0
    """Steepest descent at which a series' top made over a copy's columns is followed on past them along its own echo, degrees (:func:`.candidates._extend_top`; a copy spans only the part of the reflector its sound came back from). Past it the flank tracer (:mod:`.flanks`) takes over with its stop rule measured on the frame's speckle. Measured: harness grey group, seeds 173/179, 10 sweeps: without the extension coverage 0.924, gold 0.189 mm; at 45 degrees 0.959, 0.172 mm, p95 of the kept points 0.54 -> 0.44 mm; at 60 the trace ran on down the simulated bone's ring past the imaged flank, p95 1.35 mm."""
    under_ratio: float = 0.8
    """A candidate under another lies in its shadow when the region between them comes back at less than this fraction of the frame's typical tissue-to-level ratio (geometric mean; a ratio: the cadaver's grey shadow is 0.65 of the tissue beside it)."""
    lumen_ratio: float = 0.5
    """A vessel's lumen is no shadow: a round region darker than this fraction of the tissue level at its depth, closed on every side, with tissue beside it and brighter tissue than the typical right under it (posterior enhancement), is read as tissue by the tests of what lies in a shadow (:func:`.candidates._without_lumens`; 0: off). Ours: blood returns almost nothing, and half the tissue level lies well under the cadaver's grey shadow (0.65 of the tissue beside it), so a grey shadow's speckle seldom forms such a region. Measured (session 49): the L14 grey-shadow copy with a vessel 1 mm over the bone, recall 0 -> 1.00; the harness's 352 sweeps of seeds 173-919 unchanged but one (gold 0.210 -> 0.208 mm); ~1 ms per 480 x 640 frame."""
    lumen_mm: tuple[float, float] = (1.5, 10.0)
    """Least and largest height and width of a lumen, mm (a limb's arteries and veins: 2-10 mm across; less is speckle)."""
    refine_mm: float = 0.4
    """Half-height of the window searched at full resolution around the path, mm."""
    refine_sigma_mm: float = 0.15
    """Gaussian sigma along depth of the full-resolution profile before the peak fit, mm."""
    surface_offset_mm: float = 0.0
    """Added to the echo's peak depth to give the surface depth, mm (the peak of the echo is the surface)."""

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=(
                "work_mm",
                "phase_wavelengths_mm",
                "confidence_grid_mm",
                "confidence_beta",
                "mid_mm",
                "up_mm",
                "shadow_mm",
                "far_shadow_mm",
                "cover_mm",
                "max_z",
                "max_slope",
                "contact_mm",
                "gap_probe_mm",
                "min_length_mm",
                "n_passes",
                "max_candidates",
                "dome_mm",
                "suppress_mm",
                "kink_mm",
                "valley_mm",
                "refine_mm",
                "kink_slope",
                "shoulder_slope",
                "series_min_mm",
                "series_trough_ratio",
                "under_ratio",
                "copy_echo_ratio",
                "lumen_mm",
            ),
            non_negative=(
                "shadow_gap_mm",
                "shadow_gate_width_mm",
                "cover_gap_mm",
                "cover_ratio",
                "shadow_null_tolerance",
                "null_z",
                "slope_penalty",
                "near_field_mm",
                "switch_cost",
                "merge_gap_mm",
                "merge_step_mm",
                "beneath_ratio",
                "shoulder_step_ratio",
                "shoulder_min_mm",
                "shoulder_short_mm",
                "shoulder_short_step",
                "climb_mm",
                "reverb_tolerance",
                "refine_sigma_mm",
                "cover_min_mm",
                "fov_margin_mm",
                "gap_min_mm",
                "gap_margin_mm",
                "confidence_alpha",
                "confidence_gamma",
                "lumen_ratio",
            ),
            within={
                "tissue_percentile": "(0, 100)",
                "shadow_percentile": "(0, 100)",
                "contact_dark_fraction": "[0, 1]",
                "null_dark_fraction": "[0, 1)",
                "null_min_share": "[0, 1]",
                "gap_dark_fraction": "(0, 1]",
                "phase_weight": "[0, 1]",
                "confidence_weight": "[0, 1]",
                "fov_grey": "[0, 255]",
                "fov_fraction": "[0, 1)",
                "series_extend_deg": "(0, 90)",
            },
        )
        if not self.shadow_z_full > self.shadow_z_zero:
            raise BoneUSReconError(
                f"ShadowPathParams.shadow_z_full must be > shadow_z_zero, got {self.shadow_z_full!r}"
            )
        if not self.shadow_gate_max >= 1.0:
            raise BoneUSReconError(
                f"ShadowPathParams.shadow_gate_max must be at least 1, got {self.shadow_gate_max!r}"
            )


@dataclass(frozen=True)
class RejectionParams:
    """Choice of one bone track over the whole sweep (ours; the paper had none).

    Continuity is measured in 3D: a candidate contour of one frame is projected into
    the plane of a later frame through both poses, and its in-plane distance to a
    candidate there is compared with a tolerance that grows with the out-of-plane
    distance between them (mm along the sweep, not frame ranks) and, being a distance
    to the other contour (not a depth at a column), it allows steep flanks to shift
    sideways. Strength is relative to the sweep's own typical best candidate.
    """

    tolerance_mm: float = 1.0
    """In-plane distance between the contours of neighbouring frames that costs one unit, at zero distance along the sweep, mm (issue 10: real bone moves 0.23 mm median, 1.5 mm max between frames)."""
    tolerance_per_mm: float = 0.4
    """Growth of that tolerance per mm between the frames along the sweep (a bone surface inclined by up to ~30 degrees to the sweep)."""
    max_deviation: float = 3.5
    """Contours farther apart than this many tolerances are never linked."""
    typical_deviation: float = 0.2
    """The frame-to-frame deviation, in tolerances, the tolerance is made for; a sweep whose own deviates more (``min_tolerance_scale`` times or more) gets both terms of the tolerance scaled up so that it deviates this much (:func:`.track.tolerance_scale`; 0: never scaled). A sweep's deviation: the median over consecutive frames of the least deviation between their contours, base tolerances. Measured (all candidates of each frame): exact poses 0.11-0.16 over the 20 hard sweeps of seeds 173/179, an unsteady hand (tilt 12 degrees) 0.15-0.27; a tracker's noise per frame adds to every pair: 0.5 mm / 0.2 degrees 0.17-0.26, 1 mm / 0.4 degrees (an electromagnetic tracker's level) 0.23-0.42, where the bone's track broke at one frame in seven (recall 0.855; scaled: 0.945). A tolerance fixed larger for every sweep cost the exact ones accuracy (1.5 mm: gold 0.245 -> 0.277 mm over 88 sweeps)."""
    min_tolerance_scale: float = 1.5
    """A smaller scale is not applied: the tolerance stands (ours: with exact poses an unsteady hand, tilting 12 degrees, makes its sweep deviate up to 1.37 typical deviations, 0.15-0.27 over the 20 such sweeps of seeds 173-607; scaled by 1.25 there, one sweep's end frames changed and its gold went 0.51 -> 1.17 mm; from 1.5 on, only sweeps whose poses carry a tracker's noise are scaled)."""
    pose_jitter_mm: float = 0.6
    """The tolerance is scaled only where the poses jitter: the median distance of a frame's image origin from the midpoint of its two neighbours' at least this, mm (a tracker's noise moves each frame's pose on its own; a hand's path runs smooth between frames). Ours: the shared recordings, optically tracked, 0.15 (L14) and 0.23 mm (the spine phantom, whose cross-section changes fast between frames: its contours deviate 2.5 typical deviations, and scaled there the track kept more frames on other structures, wrong share 0.41 -> 0.53); the simulated sweeps 0.48 with exact poses (the simulator's tremor between frames 2-3 mm apart; at 0.4 the paper's snake, whose contours deviate more than the bone does, was scaled on them and kept more frames on other structures), 0.9 and 1.7 with 0.5 and 1 mm of noise per frame."""
    max_tolerance_scale: float = 3.0
    """The tolerance is scaled up by at most this factor (ours: at 3 a link within ``max_deviation`` reaches 10.5 mm plus the slope's share, the gap between a bone's top and its far cortex)."""
    max_skip: int = 8
    """A track may skip this many frames between two of its contours."""
    min_overlap_share: float = 0.3
    """Contours of two frames are linked only if they overlap laterally over at least this share of the shorter one (ours: a partial contour of the bone overlaps a full one completely; side-by-side structures barely)."""
    max_step_mm: float = 3.0
    """Contours of two frames are not linked when one lies wholly under the other (nine in ten of their common columns) by a median of more than this plus ``step_per_mm`` per mm between them along the sweep, mm (ours; issue 10: real bone moves <= 1.5 mm at a column between frames). The growth of the tolerance along the sweep is for a surface inclined to the sweep; a contour of the same extent a step under the track is the far cortex or a reverberation band in the bone's shadow (or the bone over those): on the small bones under a grey shadow, a skip link 4 frames (18 mm) long let the track drop 7.2 mm onto the far cortex at a cost of 0.75 (clavicle seed 5, wrong 0.30 -> 0.00)."""
    step_per_mm: float = 0.15
    """Growth of ``max_step_mm`` per mm between the frames along the sweep: the whole contour's depth drift along a bone (issue 10's cadaver: 0.23 mm median per 1.4 mm frame; a sparse sweep of 4 frames 30-80 mm apart over a clavicle steps 3.8-6.4 mm between them)."""
    min_track_frames: int = 3
    """A track must link at least this many frames (or all frames with candidates, if fewer): a line in one or two frames can be speckle, a bone continues."""
    miss_cost: float = 0.3
    """Cost of a skipped frame, in units of the sweep's typical best candidate strength (ours)."""
    beneath_factor: float = 0.1
    """Value of a candidate that is no first interface (an echo as bright under it: sound went through it; or it lies in a shadow: far cortex), relative to its strength (ours: 0.3 let a far cortex in the shadow of a faint near cortex carry the track on the hard tibia, recall 0.42 -> 0.70 at 0.1)."""
    strength_cap: float = 2.0
    """A candidate's strength counts up to this many typical strengths (one bright look-alike cannot buy a detour)."""
    min_length_mm: float = 1.5
    """Tracked contours shorter than this laterally are rejected ("contour too short"; ours: continuity with the track already vouches for a short piece of the bone)."""
    min_points: int = 5
    """Tracked contours with fewer points are rejected ("contour too short")."""
    lane_offcentre: float = 0.4
    """When at least three of the chosen track's contours lie farther than this share of the field of view's half-width from its middle, a track avoiding their columns is sought, and taken if it lies nearer the middle in their frames (``lane_gain``) and is a bone track too (``lane_frames``, ``lane_value``); 1 or more: never (:func:`.track.central_track`; ours: the operator keeps the bone swept in the middle of the image, where it stays in view, and a neighbouring bone shows toward an edge: the radius 18-27 mm beside a centred ulna lies 0.56-0.81 of the half-width off the middle of 51-96 mm wide simulated images; the L14 recording's bone 0.23 on median, 0.38 at most)."""
    lane_gain: float = 0.25
    """The more central track must lie nearer the middle by at least this share of the half-width, on median over the frames of the contours off the middle (ours: the centred ulna lies within 0.1 of the middle, its neighbour 0.56 or more off it)."""
    lane_frames: float = 0.5
    """The more central track must link at least this share of the chosen track's frames, and of the frames of its contours off the middle (ours: a bone continues through the sweep; a look-alike in the middle, a vessel or a fascia, comes and goes)."""
    lane_value: float = 0.3
    """The more central track's summed node value must be at least this share of the chosen track's (ours: the ulna's evidence 0.6-0.8 of the bigger radius's beside it; a fascia's, with tissue and no shadow under it, a tenth)."""
    one_lane: bool = True
    """Keep the track to one bone: where two of its contours two frames apart share no column (it crossed to a neighbouring bone over a contour joining them), choose it again without the lanes of its shorter stretches, and take that if it links as many frames (:func:`.track._one_lane`; ours: a bone cannot leave its own columns within two frames of a sweep)."""
    extend_ends: bool = True
    """Carry the chosen track on past its ends through nodes in its lane, a frame left off past an end costing ``miss_cost`` as one inside does (:func:`.track._extend_ends`; ours, session 38: the unsteady-hand hard tibia s229 left frames 0-5 off though their candidates lay on the bone in a chain within the link tolerance; see Testing/benchmarks/README.md)."""
    bone_points: tuple[tuple[float, float, float], ...] = ()
    """The user's bone points, reference mm (``ImageToReference``'s output: a markup placed on the bone in the reconstructed volume or a slice of it): the track must follow the bone through them, whatever ``lane_*`` prefers (:mod:`.bone_point`; empty: none). Points on one bone: the bone to follow where two are in view."""
    point_plane_mm: float = 5.0
    """A bone point's frames are those whose image plane passes within this distance of it, mm (ours: the simulated forearm sweeps at the cadaver's geometry have frames 1.8-2.6 mm apart, and a hard sweep's frame may miss the bone's top; at 3 mm a point on an ulna or radius swept near the image's edge had one or two frames, none showing the top, and was lost (seed 127, ``bench_sweeps.py --off-centre``); at 5 mm the bone was followed. Issue 10's cadaver sweep, 1.4 mm apart: seven frames. A bone's top moves in plane by at most ``tolerance_per_mm`` per mm along the sweep, 2 mm over 5 mm: within ``point_contour_mm``)."""
    point_contour_mm: float = 3.0
    """In a bone point's frames only candidates whose contour passes within this in-plane distance of the point (projected into the frame) may be on the track, mm (ours: a click on the bone's echo band, 1-2 mm thick on the L14 recording, and ``point_plane_mm``'s slope; on the simulated forearms with the neighbour 18 mm beside, the neighbour's contour lies 9-14 mm from the swept bone on median, 3 mm at its nearest flank end: a point on a bone's top is well clear of the other)."""
    trim_beyond: bool = True
    """Cut a track contour's level run past the reach of the track frames on either side (:mod:`.reach`; ours, session 35: a layer leaving the bone's top at its level, which no turn of the contour marks. Over 166 simulated sweeps at both geometries, seeds 173-199, every harness group with two new ones (unsteady hand, corrupted frames): wrong-structure share 0.0039 -> 0.0030, recall 0.9903 -> 0.9906, gold 0.2528 -> 0.2530 mm; the two frames it was made for (hard ulna s197 frame 21, 3.6 mm off; hard radius with the ulna 18 mm beside, s173 frame 13, 7.1 mm) on the bone; the L14 recording and its copies unchanged)."""
    beyond_margin_mm: float = 2.0
    """Points more than this past the neighbours' outermost lateral reach are judged, mm (ours: a few speckle grains; the ends of neighbouring contours on the bone vary by about this much)."""
    beyond_level_mm: float = 1.0
    """... and cut when, to their 80th percentile, they lie no deeper than this under the contour's depth at the reach's edge, mm (ours: past its widest point a bone only descends; a flank 3 mm past the reach at 20 degrees descends 1.1 mm; the 80th percentile: a flank tracer may bend a layer's last points down)."""
    beyond_min_mm: float = 3.0
    """... and run on for at least this far past the margin, mm (ours: a broad flat shoulder a frame sees 1 mm further than its neighbours, as on the L14 recording's cadaver-level copy, is kept; the layers cut on the simulated sweeps ran 4-18 mm)."""

    beyond_climb_mm: float = 1.0
    """... or, past the margin too, cut from the bottom of a valley when the contour, going outward from its top inside the reach, climbs back by at least this over the deepest point before it, onto a top at least ``beyond_min_mm`` across, mm (0: off; :mod:`.reach`; as ``ShadowPathParams.climb_mm``: past its widest point a bone's outline only descends, and 1 mm is twice the valley a grain over the top makes, ``valley_mm``. Ours, session 36: the hard radius with the ulna 14 mm beside, s173 frame 28, ran from the radius over the valley onto the ulna's top, which climbed 1.6 mm over the valley 4-11 mm past the neighbours' reach; see Testing/benchmarks/README.md)."""

    at_rest_mm: float = 0.2
    """A frame whose image corners all lie within this of the last frame that moved is one the probe recorded at rest: it is not tracked, it takes that frame's contour (``extras["at_rest_of"]``), and the surface is fitted from the frames that moved, mm (0: off; :func:`~BoneUSRecon.Logic.sweep.frames_at_rest`). Ours, session 44: a track is a longest path over frames, so sixty copies of a held frame gave its candidates sixty times their value and a look-alike there carried the whole track off the bone (a hard ulna held 2 s at the end of its sweep: every frame 6-16 mm off, gold 15.3 mm), and sixty rows at one position weighed the fit (0.03-0.06 mm). 0.2 mm: an optical tracker's jitter (0.05-0.25 mm RMS) mostly under it, the L14 recording's closest frames (0.29 mm at a corner) and the simulated sweeps' (0.87 mm) over it; a probe moving slower than 0.2 mm per frame keeps a frame every 0.2 mm."""

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=(
                "tolerance_mm",
                "max_deviation",
                "max_step_mm",
                "min_track_frames",
                "point_plane_mm",
                "point_contour_mm",
            ),
            non_negative=(
                "tolerance_per_mm",
                "typical_deviation",
                "pose_jitter_mm",
                "step_per_mm",
                "max_skip",
                "miss_cost",
                "beneath_factor",
                "strength_cap",
                "min_length_mm",
                "min_points",
                "lane_offcentre",
                "lane_gain",
                "beyond_margin_mm",
                "beyond_level_mm",
                "beyond_min_mm",
                "beyond_climb_mm",
                "at_rest_mm",
            ),
            within={
                "min_overlap_share": "[0, 1]",
                "lane_frames": "[0, 1]",
                "lane_value": "[0, 1]",
                "min_tolerance_scale": "[1, 10]",
                "max_tolerance_scale": "[1, 10]",
            },
        )


@dataclass(frozen=True)
class RecoveryParams:
    """Frames off the bone track searched again inside the band the track allows (ours; :mod:`.recovery`).

    The per-frame step finds the bone on each frame's own evidence; where the faint top
    scores as low as the speckle around it, or the bone is offered only as a piece that
    meets its neighbours' end to end, the track skips the frame. The track's own
    contours then say where to look. Measured at the cadaver's geometry (hard realism,
    five bones, 40 frames): mean frame recall 0.785 -> 0.920 (seed 5), 0.824 -> 0.915
    (seed 7), 0.800 -> 0.908 (seeds 29 and 31, unseen), wrong share unchanged
    (``Testing/benchmarks/README.md``, "Track-guided recovery").
    """

    enabled: bool = True
    """Search the frames off the track (the shadowpath segmenter only; the paper's snake has none of this)."""
    min_share: float = 0.5
    """The contour found must span at least this share of the columns the neighbouring track contours span in the frame (ours: a run through speckle in the band is short)."""
    max_offset: float = 0.5
    """The contour found must lie, on median, within this share of the wider neighbouring track contour's link tolerance (the band's half-width when it was measured; the band is now the nearer one's, :func:`.recovery.guided_candidate`) of the depth the track's neighbouring contours give (ours: on 82 frames recovered on the bone, median 0.12, p95 0.40, max 0.74; a false echo over the bone and layers crossing the band, 0.60-0.68)."""
    contact_level: float = 0.6
    """A frame whose tissue level (:meth:`.evidence.EvidenceMaps.frame_level`) is under this share of the sweep's median frame's is not searched: the probe is off the skin there, and what the band holds is the lens's reverberation over the noise floor, where a search vouched for by the neighbours finds a path through the noise at the bone's depth (:func:`.recovery.recover_frame`; ours: contact-loss frames of 10 hard sweeps at 475 x 405 read 0.49-0.50, the other frames 0.73-1.07; the L14 recording's frames 0.91-1.04, the Spine phantom's 0.82-1.14; 0: every frame searched)."""
    both_sides: bool = True
    """Search only frames with a track frame on each side within ``max_skip + 1`` frames (offline and live, ``EndsParams.search_past_ends`` searches past the track's ends as False does, the ends cut judging what is found; ours: past the track's ends only one side vouches, and beyond the last frame showing bone there is nothing to find; measured with the bone removed from the last 10 of 40 frames, 24 hard sweeps: searching with one side recovered bone-free frames in 7 sweeps, for +0.017 mean recall on sweeps showing bone throughout)."""

    recheck: bool = True
    """Also search track frames whose contour strays from their neighbours' interpolation, and replace a contour the search finds agreeing with them (:func:`.recovery.recheck_frame`; ours, class A of "Weakest sweeps and guided recovery" in ``Testing/benchmarks/README.md``)."""
    min_stray: float = 0.25
    """A track frame is searched again when its contour lies, on median, at least this share of the nearer neighbouring track frame's link tolerance off the depth the track frames on both sides interpolate (ours: contours on the bone, seeds 13 and 31, p90 0.16, p95 0.21; a cap over a faint top 0.28-0.82)."""
    max_stray_ratio: float = 0.5
    """The guided contour replaces the frame's only if its stray is at most this share of the frame's own, and it is at least as wide (ours, seeds 13 and 31, 16 straying track frames: the four replaced 1.07-1.73 -> 0.05-0.53 mm and 0.53 -> 0.10 mm at ratios 0.21-0.46; the others 0.64-1.36, among them a frame on the bone beside a capped one, 0.18 mm, whose guided contour followed the cap to 0.70 mm at 0.94)."""

    def __post_init__(self) -> None:
        check_fields(
            self,
            within={"min_share": "[0, 1]", "max_stray_ratio": "[0, 1]", "contact_level": "[0, 1]"},
            positive=("max_offset",),
            non_negative=("min_stray",),
        )


@dataclass(frozen=True)
class EndsParams:
    """The track's ends cut back where the frames show no bone shadow (ours; :mod:`.ends`).

    A sweep may start or end past the bone, where the track carries on through a
    fascia at the bone's level or the skin over a no-contact gap. Under bone the tissue
    a few mm below the contour is darker than the tissue above it (its shadow starts
    there); under those look-alikes it is much less so. The step is judged against the
    track's own typical frame, never against a grey level.
    """

    enabled: bool = True
    """Cut the track's bone-free ends (any segmenter)."""
    under_gap_mm: float = 2.5
    """The band under the contour starts this far below it, mm: past the bone's bright band (the simulator's echo tail decays over 0.4 mm; the real L14 recording's cortex is a band 1-2 mm thick)."""
    above_gap_mm: float = 1.0
    """The band above the contour ends this far above it, mm (past the echo's blur upwards)."""
    band_mm: float = 5.0
    """Thickness of the bands under and above the contour, mm (the shadow's reverberation bands are 2.5-3 mm apart: a band spans at least one period)."""
    near_field_mm: float = 2.0
    """The band above starts no shallower than this, mm (the skin line and the probe's near field: ``ShadowPathParams.near_field_mm``)."""
    cover_reach_mm: float = 16.0
    """The band's mean is read against the brightest ``band_mm`` band up to this far over the contour (medians along the contour), not only the band right over it: a muscle lying on the bone (1-10 mm over it: the pronator quadratus on the distal radius and ulna) darkens that band, and where it covers only one end of the sweep the frames there read weak against the track's typical frame (ours, session 51: the L14 recording and its copies with a muscle at 0.5-0.7 over the first 40 % or the last half of the sweep, recall 0.48-0.90 -> 1.00; 0 or under ``above_gap_mm + 2 band_mm``: the band above only, as before; see :func:`.ends.shadow_step`)."""
    column_mm: float = 0.5
    """One contour column in this many mm is measured (speed: a median over columns needs no more; the speckle is ~0.3-0.7 mm wide)."""
    trough_mm: float = 1.0
    """The band under the contour is also read at its darkest layer this thick, mm, on the profile along the contour (the shadow between reverberation copies; :func:`.ends.trough_step`; 0: not read, the band's mean alone as before session 48)."""
    min_ratio: float = 0.5
    """A frame whose step (the band's mean) is below this share of the track's typical step counts as weak (ours: on the tracks of 30 hard sweeps with bone-free ends, 920 frames on the bone and 49 bone-free frames kept, 0.5 cut 48 of the 49 and no frame on the bone, 0.4 cut 35; the real L14 recording's frames step 0.41-1.6 of its median, nothing cut)."""
    trough_ratio: float = 0.6
    """The same for the darkest layer (``trough_mm``); a frame is as weak as both readings find it, the lesser of the two weaknesses (ours, session 48, offline on tracks segmented with the cut off: 160 hard sweeps with bone-free ends, 64 bone-free frames and 5,341 on the bone, and 24 sweeps of the grey, small and motion groups of six seed pairs, 4,065 on the bone; the band's mean alone left 1 bone-free frame and cut 3 + 6 on the bone, the 6 the grey clavicle s811's last frames under a darker muscle layer; the darkest layer alone at 0.6 left none and cut 0 + 5, at 0.5 left 24; both, 1 and 0 + 1; the real L14 recording's frames read 0.70-1.22 of its median, nothing cut)."""
    strong_weight: float = 1.0
    """A frame at or above ``min_ratio`` counts this many times its margin against a cut, a weak one once its margin for it (ours: at 3, which guards a weak stretch of the bone next to a strong end frame better, bone-free frames kept on 96 hard sweeps 4 of 624, at 1 1 of 624, the same frames on the bone; past a bone's end a layer may step 0.6-0.7 of the typical frame in the frames farthest from the bone)."""
    search_past_ends: bool = True
    """With the cut on, the track-guided recovery (:mod:`.recovery`, offline and live) also searches the frames past the track's ends, guided by one side (as ``RecoveryParams.both_sides`` False): the cut judges what it finds there (ours: on 96 hard sweeps with 3 or 10 bone-free frames at an end, mean recall 0.941 -> 0.962, bone-free frames kept 1 of 624 either way; without the cut the one-sided search kept bone-free frames in 7 of 24 sweeps)."""
    max_cut_share: float = 0.5
    """Never cut more than this share of the track's frames: the typical step is the track's median, so it stands for the bone only while most of the track is on it."""
    choose_again: bool = True
    """Once frames are cut, choose the track again with them ruled out, then cut the new track's ends (:func:`.ends.cut_ends_and_choose_again`; offline and live, the first track before recovery too). Ours: the track's choice in the frames kept is not to be bought with frames judged bone-free (hard tibia, seed 5, last 10 frames bone-free: recall 0.93 -> 1.00, wrong share 0.025 -> 0; see Testing/benchmarks/README.md, branch track5)."""

    def __post_init__(self) -> None:
        check_fields(
            self,
            positive=("band_mm", "column_mm", "min_ratio", "trough_ratio"),
            non_negative=(
                "under_gap_mm",
                "above_gap_mm",
                "near_field_mm",
                "cover_reach_mm",
                "strong_weight",
                "trough_mm",
            ),
            within={"max_cut_share": "[0, 1]"},
        )


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
    """The sweep-level choice of one bone track, applied to every segmenter's candidates."""
    recovery: RecoveryParams = field(default_factory=RecoveryParams)
    """Frames off the track searched again inside the band the track allows (shadowpath)."""
    ends: EndsParams = field(default_factory=EndsParams)
    """The track's ends cut back where the frames show no bone shadow (sweeps past a bone's end)."""

    def __post_init__(self) -> None:
        check_fields(self)
        if self.method not in SEGMENTER_NAMES:
            raise BoneUSReconError(
                f"unknown segmenter {self.method!r}; use one of {', '.join(sorted(SEGMENTER_NAMES))}"
            )

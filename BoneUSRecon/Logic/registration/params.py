"""Parameters of the registration: one frozen dataclass, every value documented."""

from __future__ import annotations

from dataclasses import dataclass

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.params_check import check_fields

__all__ = ["INIT_METHODS", "RegistrationParams"]


#: Initial alignments :func:`register` knows.
INIT_METHODS = ("identity", "landmarks", "search")


@dataclass(frozen=True)
class RegistrationParams:
    """Parameters of :func:`register` (mm, degrees, shares in 0..1).

    Attributes
    ----------
    init : {"identity", "landmarks", "search"}
        Initial alignment. ``"identity"``: the given ``init`` matrix (default the
        identity), for a sweep already roughly (within ~15 mm / 15 deg) in the model's
        frame, e.g. after a tracked pointer touched the bone. ``"landmarks"``: the
        least-squares fit of >= 3 paired points. ``"search"``: principal axes of source
        and model with their ambiguities tried (see :func:`register`).
    max_distance_mm : float
        Correspondences farther than this from the model are ignored at the start
        (mm). 25: a 15 mm / 15 deg start moves points of a 60 mm patch by up to ~23 mm.
    min_distance_mm : float
        The distance gate shrinks with the residual scale (10 scales) but never below
        this (mm). 2: a few times the ~0.3 mm accuracy of a reconstructed surface, so a
        good point is never cut.
    noise_floor_mm : float
        Floor on the robust residual scale (mm): residuals below it count as exact. 0.1:
        below the ~0.2 mm error of our reconstructions (Testing/benchmarks/README.md).
    robust : {"tukey", "huber", "none"}
        Weights of the point-to-plane residuals (Tukey's biweight gives gross outliers
        weight 0; :mod:`.robust`).
    max_iterations : int
        ICP iterations at most. 100: from 15 mm / 15 deg away the point-to-plane steps
        converge in 10-30 (measured on the simulated sweeps).
    tolerance_mm : float
        Stop when an iteration moves no source point by more than this (mm).
    max_source_points : int
        Source points used by the iterations (a deterministic random subset; the final
        figures use all points). 2500: the transform's precision saturates far below
        (measured: the same target error with 4000), and an iteration stays ~10 ms.
    damping : float
        Levenberg damping of the 6x6 step, relative to its largest eigenvalue. 1e-6
        keeps an unconstrained direction (a cylinder's axis) from drifting in each
        step while leaving constrained ones untouched.
    min_overlap : float
        Below this share of source points near the model (at the start, or as inliers
        at the end) the inputs do not overlap: an error, not a transform. 0.2.
    min_inlier_share : float
        Below this share of inliers the result is flagged unreliable. 0.6: a good
        registration of our reconstructions keeps > 90 %.
    max_rms_mm : float
        Above this inlier residual RMS (mm) the result is flagged unreliable: the
        shapes do not match (wrong bone, wrong side, a wrong local optimum). 1.0.
    max_sliding_mm : float
        A degree of freedom whose sliding range (see the module docstring) exceeds this
        (mm) is weakly constrained; the result is then flagged unreliable. Also the
        distance beyond which two alignments count as different. 2.0: the target error
        a trusted registration must meet (issue 14).
    search_offsets_mm : float
        ``"search"``: step of the positions tried along the model's long axis (mm).
    search_rolls : int
        ``"search"``: rotations about the long axis tried (evenly spaced).
    max_normal_angle_deg : float
        A source point pairs only with model points whose normal is within this angle
        of its own (degrees): 60, well beyond the 15 deg of a poor start, well short of
        the 180 deg of the far side of a thin bone.
    patch_normal_angle_deg : float
        The same for a source without normals, whose points all take the patch's mean
        normal (:func:`patch_normal`; degrees). 80: the top of a shaft seen by a
        sweep has normals up to ~70 deg from its mean; the far side is beyond 110.
    start_rolls_deg, start_shifts_mm : tuple of float
        Besides the initial alignment, ICP also starts rolled by +- each angle about
        the source's long axis and shifted by +- each distance along it (every
        combination; see :func:`.icp.local_starts`): the local optima of a patch of a shaft.
        15 deg and 10 mm: 9 starts, plus 2 lifted and lowered by each distance along
        the patch's normal (a start below a thin bone meets its far side first); the
        best is kept, and a distinct one fitting about as well flags the result as
        ambiguous.
    coarse_iterations : int
        ICP iterations per start on a subset before the best is refined.
    coarse_points : int
        Size of that subset. 300: enough to rank basins apart by their residual
        (they differ by millimetres), cheap enough for 9 starts.
    """

    init: str = "identity"
    max_distance_mm: float = 25.0
    min_distance_mm: float = 2.0
    noise_floor_mm: float = 0.1
    robust: str = "tukey"
    max_iterations: int = 100
    tolerance_mm: float = 1e-4
    max_source_points: int = 2500
    damping: float = 1e-6
    min_overlap: float = 0.2
    min_inlier_share: float = 0.6
    max_rms_mm: float = 1.0
    max_sliding_mm: float = 2.0
    search_offsets_mm: float = 10.0
    search_rolls: int = 8
    max_normal_angle_deg: float = 60.0
    patch_normal_angle_deg: float = 80.0
    start_rolls_deg: tuple[float, ...] = (15.0,)
    start_shifts_mm: tuple[float, ...] = (10.0,)
    coarse_iterations: int = 12
    coarse_points: int = 300

    def __post_init__(self) -> None:
        # The float fields' coercion already refuses inf and NaN.
        check_fields(
            self,
            choices={"init": INIT_METHODS, "robust": ("tukey", "huber", "none")},
            positive=(
                "max_distance_mm",
                "min_distance_mm",
                "noise_floor_mm",
                "tolerance_mm",
                "max_rms_mm",
                "max_sliding_mm",
                "search_offsets_mm",
                "max_normal_angle_deg",
                "patch_normal_angle_deg",
                "start_rolls_deg",
                "start_shifts_mm",
            ),
            within={
                "min_overlap": "[0, 1]",
                "min_inlier_share": "[0, 1]",
                "max_iterations": "[1, inf)",
                "search_rolls": "[1, inf)",
                "coarse_iterations": "[1, inf)",
                "max_source_points": "[50, inf)",
                "coarse_points": "[50, inf)",
                "damping": "[0, 1)",
            },
        )
        if self.min_distance_mm > self.max_distance_mm:
            raise BoneUSReconError(
                f"RegistrationParams.min_distance_mm ({self.min_distance_mm}) exceeds max_distance_mm ({self.max_distance_mm})"
            )

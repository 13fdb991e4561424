# The public API of BoneUSRecon.Logic.segmentation, as in BoneUSRecon/Logic/__init__.pyi:
# type checkers read it, and lazy_loader.attach_stub (in __init__.py) imports each name
# from here on first use. Only `from .module import name` lines, and the constant
# defined in __init__.py itself.
from .candidates import BoneCandidate, FrameCandidates, frame_candidates
from .detection import Detection
from .driver import (
    SEGMENTERS,
    contours_from_track,
    frame_candidates_for,
    segment_frame,
    segment_sweep,
)
from .ends import cut_bone_free_ends, shadow_step
from .evidence import bone_evidence
from .params import (
    REFERENCE_PIXEL_MM,
    EndsParams,
    PosteriorParams,
    RecoveryParams,
    RejectionParams,
    SegmentationParams,
    ShadowPathParams,
    SnakeParams,
)
from .polydata import points_polydata
from .recovery import recover_frames
from .result import FrameContour, SegmentationPoints, SegmentationResult
from .track import TrackChoice, select_bone_track

SEGMENTER_NAMES: tuple[str, ...]

__all__ = [
    "SEGMENTERS",
    "SEGMENTER_NAMES",
    "REFERENCE_PIXEL_MM",
    "SegmentationParams",
    "SnakeParams",
    "PosteriorParams",
    "ShadowPathParams",
    "RejectionParams",
    "RecoveryParams",
    "EndsParams",
    "shadow_step",
    "cut_bone_free_ends",
    "FrameContour",
    "SegmentationResult",
    "SegmentationPoints",
    "Detection",
    "segment_frame",
    "segment_sweep",
    "frame_candidates_for",
    "contours_from_track",
    "frame_candidates",
    "FrameCandidates",
    "BoneCandidate",
    "select_bone_track",
    "recover_frames",
    "TrackChoice",
    "bone_evidence",
    "points_polydata",
]

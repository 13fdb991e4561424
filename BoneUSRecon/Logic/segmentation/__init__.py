"""Bone contour segmentation (paper step B), per frame and per sweep.

Two segmenters, selectable by name in :data:`SEGMENTERS`:

* ``"shadowpath"`` (default): shadow-gated contrast map and a dynamic-programming
  optimal path across columns with a no-bone state, sub-pixel peak refinement and a
  temporal prior (:mod:`.shadowpath`).
* ``"snake"``: the paper's open active contour with balloon and regional energies and
  its posterior choice of points (:mod:`.snake`, :mod:`.posterior`).

Every segmenter's output goes through the same confidence and rejection checks
(:mod:`.rejection`); rejected frames are reported and never reach the surface fit.
"""

from BoneUSRecon.Logic.segmentation.detection import Detection
from BoneUSRecon.Logic.segmentation.driver import SEGMENTERS, segment_frame, segment_sweep
from BoneUSRecon.Logic.segmentation.params import (
    REFERENCE_PIXEL_MM,
    PosteriorParams,
    RejectionParams,
    SegmentationParams,
    ShadowPathParams,
    SnakeParams,
)
from BoneUSRecon.Logic.segmentation.polydata import points_polydata
from BoneUSRecon.Logic.segmentation.result import FrameContour, SegmentationResult

__all__ = [
    "SEGMENTERS",
    "REFERENCE_PIXEL_MM",
    "SegmentationParams",
    "SnakeParams",
    "PosteriorParams",
    "ShadowPathParams",
    "RejectionParams",
    "FrameContour",
    "SegmentationResult",
    "Detection",
    "segment_frame",
    "segment_sweep",
    "points_polydata",
]

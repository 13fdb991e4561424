"""Bone contour segmentation (paper step B), per frame and per sweep.

Two segmenters, selectable by name in :data:`SEGMENTERS`:

* ``"shadowpath"`` (default): shadow-gated contrast map and a dynamic-programming
  optimal path across columns with a no-bone state, sub-pixel peak refinement and a
  temporal prior (:mod:`.shadowpath`).
* ``"snake"``: the paper's open active contour with balloon and regional energies and
  its posterior choice of points (:mod:`.snake`, :mod:`.posterior`).

Every segmenter's output goes through the same confidence and rejection checks
(:mod:`.rejection`); rejected frames are reported and never reach the surface fit.

Measured (``Testing/benchmarks/bench_segmentation.py``: 60-frame 256x320 simulated
sweeps at 0.15 mm/px of each of the five bones with 10 % corrupted frames; distances of
the kept points to the true bone surface, all bones pooled):

============  ========  ========  =========  ====================================
segmenter     median    p95       > 2 mm     corrupted frames rejected / harmless
============  ========  ========  =========  ====================================
shadowpath    0.011 mm  0.039 mm  0 %        33-83 % / 100 %
snake         0.120 mm  0.301 mm  0 %        67-83 % / 100 %
============  ========  ========  =========  ====================================

("harmless": rejected, or kept with its points on the bone, e.g. the bone found under
a false echo.) shadowpath runs at ~10 ms per 480x640 frame on one core, 50-130x
faster than ``skimage.segmentation.active_contour`` (100 points, 300 iterations, free
ends) on the same frames; the paper's snake is ~10-15x faster than skimage's. Hence
shadowpath is the default.
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

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
sweeps at 0.15 mm/px of each of the five bones with 10 % corrupted frames, simulator
version 2 (grey shadow with reverberation, thick echo, weak flanks, dropouts);
distances of the kept points to the true bone surface, all bones pooled):

============  ========  ========  =========  ====================================
segmenter     median    p95       > 2 mm     corrupted frames rejected / harmless
============  ========  ========  =========  ====================================
shadowpath    0.030 mm  0.072 mm  0.30 %     33-83 % / 100 %
snake         0.150 mm  0.390 mm  1.67 %     67-83 % / 100 %
============  ========  ========  =========  ====================================

("harmless": rejected, or kept with its points on the bone, e.g. the bone found under
a false echo.) On the version-1 simulator (black shadow, thin echo) shadowpath had
0.011 / 0.039 mm and the snake 0.120 / 0.301 mm. The paper's snake, rising from
below, is caught by the reverberations in a grey shadow (the paper's own failure
mode, "noise on the acoustic shadow": 0.227 / 12.2 mm, 24 % of points > 2 mm)
unless restarted above a faint contour with shadow on both sides, as it now is.

On the real L14 recording (``Testing/benchmarks/bench_real.py``) shadowpath accepts
21/21 frames with contours of 16.7-25.1 mm (median 20.8 mm; 6-17 mm before the
flank-friendly defaults), and mirrored, +-30 % gain, speckled, 0.15 mm and cropped
copies give the same contour within 0.004-0.04 mm (median). The steep lower flanks
(beyond ~60 degrees, echo barely above the tissue) are still not traced.

shadowpath runs at ~9 ms per 480x640 frame on one core (segmenter alone; ~15 ms with
the rejection checks), 30-60x faster than ``skimage.segmentation.active_contour``
(100 points, 300 iterations, free ends) on the same frames. Hence it is the default.
"""

from __future__ import annotations

from BoneUSRecon.Logic._lazy import lazy_attributes

#: Names of the segmenters, the default first: the keys of :data:`SEGMENTERS`. Here,
#: importing nothing, so that the CLI's parsers list them at start-up;
#: :class:`SegmentationParams` checks a name against them.
SEGMENTER_NAMES = ("shadowpath", "snake")

# The rest is imported lazily (PEP 562), as in BoneUSRecon.Logic: the segmenters load
# numpy, scipy and VTK, and even params.py (its frozen dataclasses) costs ~14 ms.
_LAZY = {
    "SEGMENTERS": "driver",
    "segment_frame": "driver",
    "segment_sweep": "driver",
    "frame_candidate": "driver",
    "select_contours": "driver",
    "Detection": "detection",
    "REFERENCE_PIXEL_MM": "params",
    "SegmentationParams": "params",
    "SnakeParams": "params",
    "PosteriorParams": "params",
    "ShadowPathParams": "params",
    "RejectionParams": "params",
    "points_polydata": "polydata",
    "FrameContour": "result",
    "SegmentationResult": "result",
}

__all__ = [
    "SEGMENTERS",
    "SEGMENTER_NAMES",
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
    "frame_candidate",
    "select_contours",
    "points_polydata",
]

__getattr__, __dir__ = lazy_attributes(__name__, _LAZY, __all__)

"""Bone contour segmentation (paper step B): candidates per frame, one track per sweep.

Two steps, both public, so that a live reconstruction can run the first as frames
arrive and the second on the frames so far:

* per frame (pure, cacheable): :func:`frame_candidates_for` (any segmenter) or
  :func:`frame_candidates` (the default's): up to five candidate contours with their
  evidence (:mod:`.candidates`, :mod:`.evidence`);
* per sweep: :func:`select_bone_track` chooses one candidate or none per frame by a
  dynamic programme over the frames, continuity measured in 3D through the poses
  (:mod:`.track`); :func:`contours_from_track` packs the choice as
  :class:`FrameContour` objects with their rejection reason (one category) and detail.

:func:`segment_sweep` runs both. Segmenters, selectable by name in :data:`SEGMENTERS`:

* ``"shadowpath"`` (default): contrast-adaptive evidence (every level from the frame
  itself: per-depth tissue levels, robust z-scores; echo against the tissue above it,
  shadow against the tissue at the same depth beside it, soft tissue above) and
  repeated optimal paths across columns; look-alikes (skin over a no-contact gap,
  reverberation copies and series, fascia, vessels, the far cortex and anything else
  in a shadow: bone is the first strong reflector) handled by the rules of
  :mod:`.candidates`.
* ``"snake"``: the paper's open active contour with balloon and regional energies and
  its posterior choice of points (:mod:`.snake`, :mod:`.posterior`); its contour is the
  frame's one candidate, scored on the same evidence and chosen by the same track.

Features from the field measured and left off by default (selectable in
:class:`ShadowPathParams`): ultrasound confidence maps (:mod:`.confidence`, Karamalis'
random walk) and local phase symmetry (:mod:`.phase`, Hacihaliloglu); each module's
docstring says what was measured and why it is off. Measured figures (frame recall,
wrong frames, distances on simulated and real sweeps) and the features tried and
dropped are in ``Testing/benchmarks/README.md``.
"""

from __future__ import annotations

import lazy_loader

#: Names of the segmenters, the default first: the keys of :data:`SEGMENTERS` (the one
#: list; ``driver`` checks its table against it). Defined here, importing nothing, so
#: that the CLI's parsers list them at start-up; :class:`SegmentationParams` checks a
#: name against them.
SEGMENTER_NAMES = ("shadowpath", "snake")

# The rest is imported on first use, from the names listed in ``__init__.pyi`` (as in
# BoneUSRecon.Logic): the segmenters load numpy, SciPy and VTK.
__getattr__, _, _lazy_names = lazy_loader.attach_stub(__name__, __file__)
__all__ = ["SEGMENTER_NAMES", *_lazy_names]


def __dir__() -> list[str]:
    return __all__

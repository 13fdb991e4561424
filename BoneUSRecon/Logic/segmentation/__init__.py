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
  reverberation copies, fascia, vessels) handled by the rules of :mod:`.candidates`.
* ``"snake"``: the paper's open active contour with balloon and regional energies and
  its posterior choice of points (:mod:`.snake`, :mod:`.posterior`); its contour is the
  frame's one candidate, scored on the same evidence and chosen by the same track.

Measured (issue 10; ``Testing/benchmarks/bench_segmentation.py --table-only``, tables
in ``Testing/benchmarks/README.md``): standard simulated sweeps, frame recall
1.00, no wrong-structure frame, kept points 0.03 mm median; every hard condition
alone but the grey shadow, recall 0.80-1.00 and no wrong frame; the full
``realism="hard"`` sweeps, recall 0.35-0.93 (the previous segmenter found no bone), no
wrong frame on radius, ulna and clavicle but 45 % on tibia and humerus, where the
track follows the far cortex or a reverberation band under the grey shadow (the open
problem, with the real L14 recording compressed to a 1.3x echo). The real L14 as
recorded: 21/21 frames on the bone, 0.040 mm median from its reference contours.

Features tried (measured, frame recall on hard sweeps): local phase symmetry along
depth (own 1-D log-Gabor filters, Hacihaliloglu's measure; 2-D ``phasepack.phasesym``
costs 33-60 ms on the working image alone, over the frame budget) instead of the
echo log-ratio: tibia/radius hard 0.50/0.53 -> 0.00/0.00, standard 1.00/0.95 ->
0.57/0.62: dropped (``ShadowPathParams.phase_symmetry`` off). Lateral smoothing of the
working image (0.4 mm): standard clavicle recall 0.97 -> 0.60: dropped. Shadow depth
(a long window to 12 mm beside the near one): kept, it is what separates a vessel
lumen or a gap between fasciae from a bone's shadow. Karamalis' confidence maps were
not tried (a sparse random-walk solve per frame does not fit 30 frames/s).
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

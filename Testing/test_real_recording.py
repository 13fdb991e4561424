"""The default segmenter on the one real recording, and on augmentations of it.

The PLUS recording shipped in Resources/SampleData (21 frames of 820 x 616 at 0.085 mm, a scan-converted
linear probe with black margins beside the image) shows a round bone whose shadow is
grey, with weaker oblique flanks. There is no ground truth, so:

* on the recording itself the contour must be long (the flanks, not only the top of
  the arc), bright, inside the imaged field of view, and found in every frame;
* on augmented copies (mirrored, gain +-30 %, extra speckle, 0.15 mm pixels, cropped,
  under a curvilinear probe's sector, and all at once) the contour must stay on the
  same bone: compared in reference mm
  with the contour of the original, through poses kept consistent by
  :mod:`BoneUSRecon.Logic.simulation.augment`.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REAL_MHA, REAL_XML  # Resources/SampleData, in the repository

from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.simulation import augment


@pytest.fixture(scope="module")
def real():
    from BoneUSRecon.Logic.sequence_io import read_sweep

    sw = read_sweep(REAL_MHA, calibration=REAL_XML)
    return sw, segment_sweep(sw)


def test_real_contours_cover_the_flanks_inside_the_field_of_view(real):
    sw, r = real
    assert len(r.accepted) == sw.n_frames == 21
    sx = float(sw.spacing_mm[0])
    extent = np.array([np.ptp(c.points_px[:, 0]) * sx for c in r.accepted])
    # Measured 13.3-27.5 mm per frame, median 19.1 (the contrast-adaptive segmenter of
    # issue 10 with the flat ends followed round the outline, rim.py; 13.3-19.7, median
    # 17.4 before it; the previous segmenter, tuned on this recording, reached 16.7-25.1).
    assert np.median(extent) >= 16.0 and extent.min() >= 12.0
    # Imaged columns: where the frames are not black (176-642 here).
    lit = np.flatnonzero(np.asarray(sw.frames).max(axis=(0, 1)) > 0)
    for c in r.accepted:
        assert c.points_px[:, 0].min() >= lit[0] and c.points_px[:, 0].max() <= lit[-1]
        # On the bright echo, and a smooth curve (no jumps onto other layers): steps
        # along the contour measured 0.38-0.46 mm at p95 and 1.71 mm at most (its flanks
        # are followed to ~70 degrees, so steps are measured along it, not per column).
        assert np.median(c.intensity) >= 120
        step = np.hypot(*np.diff(c.points_px, axis=0).T) * sx
        assert np.percentile(step, 95) < 0.75 and step.max() < 2.5
    # Neighbouring frames agree (the probe moves smoothly): median depth steps < 1 mm.
    depth = np.array([np.median(c.points_mm(sw)[:, 2]) for c in r.accepted])
    assert np.median(np.abs(np.diff(depth))) < 1.0


@pytest.mark.parametrize("name", list(augment.RECORDING_AUGMENTATIONS))
def test_augmented_recording_gives_the_same_bone(real, name):
    sw, r = real
    aug = augment.RECORDING_AUGMENTATIONS[name](sw)
    r2 = segment_sweep(aug)
    d, cover, beyond = augment.contour_agreement(sw, r, aug, r2)
    # 21/21 on every copy but the 0.15 mm one (19/21: in two frames the track keeps a
    # piece of the bone shorter than 1.5 mm, rejected as too short).
    assert len(r2.accepted) >= 19
    # On the same curve where both contours are (measured medians 0.004-0.03 mm).
    assert np.median(d) <= 0.1
    assert np.percentile(d, 95) <= 0.5
    assert np.mean(d > 2.0) <= 0.01
    # As much of it: most of the original contour is found again, and little found
    # beyond its ends. Measured: cover median 0.87-1.00, beyond median 0.02-0.04 and at
    # most 0.55 of a frame's points: the flank followed 10-20 mm round the outline
    # (rim.py) stops a few mm earlier or later on a copy (the 'all' copy's cover 0.874,
    # the 0.15 mm copy's beyond 0.55 in one frame; 0.9 and 0.5 before the rim). The
    # sector copy (top row 70 % of the width) hides part of the flanks: cover 0.886;
    # 0.806 before its black outside was told from a probe edge off the skin.
    assert np.median(cover) >= 0.85
    assert np.median(beyond) <= 0.1 and beyond.max() <= 0.6


def test_flip_maps_pixels_to_the_same_millimetres(real):
    sw, _ = real
    f = augment.flip_lateral(sw)
    ij = np.array([[10.0, 20.0], [400.0, 300.0]])
    ij_f = np.column_stack([sw.width - 1 - ij[:, 0], ij[:, 1]])
    assert np.allclose(sw.to_reference(3, ij), f.to_reference(3, ij_f))
    assert np.array_equal(f.frames[3][:, ::-1], sw.frames[3])

"""A linear field inside a black screen: a frame grabber's capture or a loose clip rectangle.

Black bands over and under the image over its whole width are outside the field
(:func:`.evidence.outside_field`): not a probe edge off the skin (the contact test read
the band's rows as uncoupled in every column, and no frame kept a contour), not a bone's
shadow (a line framing the image had the band under it for one), and the near field
starts under the band (:mod:`.ends`' shadow step). Labels, a grey-scale bar, a depth
ruler and a focus marker in the margins make no band and no sector. The real recording
so captured keeps its bone: ``test_real_recording`` (the ``screen`` augmentation).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import small_simulation
from test_segmentation_sector import P, _work

from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.segmentation.evidence import field_rows, outside_field, outside_sector
from BoneUSRecon.Logic.simulation import augment


@pytest.fixture(scope="module")
def radius():
    return small_simulation(bone="radius", seed=241, realism="hard")


def test_the_bands_over_and_under_a_captured_field_are_outside(radius):
    sw = radius.sweep
    sp = (float(sw.spacing_mm[0]), float(sw.spacing_mm[1]))
    cap = augment.screen_capture(sw, (6.0, 10.0, 8.0, 12.0))
    for k in (5, 20):
        work, dx, dy = _work(np.asarray(cap.frames[k]), sp)
        h = work.shape[0]
        # The focus marker (a few columns at mid-depth beside the image) made the
        # field a sector; the field's own columns do not.
        assert outside_sector(work, dx, dy, P) is None
        out = outside_field(work, dx, dy, P)
        assert out is not None
        first, end = field_rows(out, h)
        # The field's rows: 6 mm of band over it (the frame line 2 pixels over the
        # image is within a working row or two), 8 mm under it.
        assert abs(first * dy - 6.0) <= 1.0 and abs((h - end) * dy - 8.0) <= 1.0
        # Nothing outside the bands: the field's rows hold no outside pixel.
        assert not out[first:end].any()
    # A sector so captured: its black corners and the band under it.
    work, dx, dy = _work(np.asarray(augment.screen_capture(augment.sector(sw, 0.6)).frames[5]), sp)
    out = outside_field(work, dx, dy, P)
    first, end = field_rows(out, work.shape[0])
    assert outside_sector(work, dx, dy, P) is not None
    assert abs((work.shape[0] - end) * dy - 8.0) <= 1.0 and out[first:end].any()
    # The sweep itself (its field reaching the frame's edges) has no band.
    work, dx, dy = _work(np.asarray(sw.frames[20]), sp)
    assert outside_field(work, dx, dy, P) is None


@pytest.mark.parametrize("sector", [None, 0.6])
def test_a_captured_sweep_keeps_its_bone(radius, sector):
    # Before: no band, the contact test took every column for uncoupled (6 mm of black
    # over the field) or the frame line under the field for the bone (the band under
    # it a perfect shadow): on the hard small sweeps of seed 241, recall 0.00-0.08 and
    # 78-100 % of the frames on that line, 22 mm off. A curvilinear probe's sector so
    # captured: its own outside and the band under it.
    sw = radius.sweep if sector is None else augment.sector(radius.sweep, sector)
    cap = augment.screen_capture(sw)
    r = segment_sweep(cap)
    on = off = 0
    for c in r.accepted:
        d = np.median(radius.distance_to_truth(cap.to_reference(c.frame, c.points_px)))
        on += d < 1.0
        off += d > 3.0
    assert on >= 0.95 * radius.sweep.n_frames and off == 0


def test_a_black_band_only_under_the_probe_edge_is_no_band(radius):
    # A probe edge off the skin: the near rows of a third of the columns are black. The
    # columns in contact start at the top: no band, and those columns stay uncoupled.
    sw = radius.sweep
    sp = (float(sw.spacing_mm[0]), float(sw.spacing_mm[1]))
    image = np.array(sw.frames[20])
    image[: int(round(4.0 / sp[1])), : image.shape[1] // 3] = 0
    work, dx, dy = _work(image, sp)
    assert outside_field(work, dx, dy, P) is None

"""A curvilinear probe's sector-shaped field of view (black outside the sector).

The near rows of the columns at a sector's sides are black: not a probe edge off the
skin (:func:`.evidence._contact`, :func:`.evidence._edge_gap`) and not dark tissue
(the tissue levels). :func:`.evidence.outside_sector` finds the outside from the
scanner's exact black and the field's shape; a linear image's black padding, even
with a dark floor reaching it (the L14 recording), is no sector. The real recording
under a sector keeps its bone: ``test_real_recording`` (the ``sector`` augmentation).
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import REAL_MHA, REAL_XML, small_simulation

from BoneUSRecon.Logic.segmentation.evidence import (
    _inside_percentiles,
    bone_evidence,
    field_of_view,
    outside_sector,
    working_image,
)
from BoneUSRecon.Logic.segmentation.params import ShadowPathParams
from BoneUSRecon.Logic.simulation import augment
from BoneUSRecon.Logic.sweep import pixel_spacing

P = ShadowPathParams()


def _work(image: np.ndarray, spacing: tuple[float, float]) -> tuple[np.ndarray, float, float]:
    work, _, fx, fy = working_image(image, spacing, P.work_mm)
    return work, fx * spacing[0], fy * spacing[1]


@pytest.fixture(scope="module")
def humerus():
    return small_simulation(bone="humerus", n_frames=6, seed=1, realism="hard")


def test_a_sector_field_keeps_its_columns_in_contact(humerus):
    """Under a sector whose top row keeps half the width, the columns at its sides
    (black over their near rows) stay usable: before, 89 of the 160 columns were
    judged off the skin (of ~134 inside the field) and the flanks there were lost."""
    sw = humerus.sweep
    sec = augment.sector(sw, 0.5)
    sp = (float(sw.spacing_mm[0]), float(sw.spacing_mm[1]))
    for k in (2, 4):
        image = np.asarray(sec.frames[k])
        work, dx, dy = _work(image, sp)
        out = outside_sector(work, dx, dy, P)
        assert out is not None
        # The outside is the black the sector left (but for the few pixels along its
        # slanted sides that the working grid's blocks half fill), and all of it above
        # the imaged rows.
        black = work <= P.fov_grey / 255.0
        assert np.mean(black[out]) >= 0.97
        assert out[0].sum() >= 0.4 * work.shape[1] and not out[-1, 10:-10].any()
        ev = bone_evidence(image, sp)
        fov = field_of_view(work, dx, P)
        assert ev.usable.sum() >= 0.95 * fov.sum()
        # The tissue level of the rows under the skin, read inside the sector, is the
        # linear frame's (within 10 %; black counted, it fell with the rows' black share).
        lin = bone_evidence(np.asarray(sw.frames[k]), sp)
        h = lin.tissue.size
        rows = slice(int(0.1 * h), int(0.4 * h))
        assert np.median(ev.tissue[rows] / lin.tissue[rows]) == pytest.approx(1.0, abs=0.1)


def test_a_depth_ruler_in_the_margin_does_not_hide_the_sector(humerus):
    """Dots of a depth ruler (0.3 mm, every 5 mm) in the black margin and a label in a
    top corner: the sector is still found, the columns under the label aside."""
    sw = humerus.sweep
    sp = (float(sw.spacing_mm[0]), float(sw.spacing_mm[1]))
    image = np.asarray(augment.sector(sw, 0.5).frames[2]).copy()
    plain = bone_evidence(image, sp).usable.sum()
    step = int(round(5.0 / sp[1]))
    for r in range(0, image.shape[0], step):
        image[r : r + 1, 3:4] = 220
    image[1:3, -12:-2] = 200
    assert bone_evidence(image, sp).usable.sum() >= plain - 3


def test_black_padding_and_a_dark_floor_are_no_sector(humerus):
    """The L14 recording: black columns beside the image, its dark deep rows reaching
    them; hard simulated frames with a probe edge off the skin: no sector."""
    from BoneUSRecon.Logic.sequence_io import read_sweep

    sw = read_sweep(REAL_MHA, calibration=REAL_XML)
    sp = pixel_spacing(sw.image_to_reference)
    for k in (0, 10, 20):
        work, dx, dy = _work(np.asarray(sw.frames[k]), (float(sp[k, 0]), float(sp[k, 1])))
        assert outside_sector(work, dx, dy, P) is None
    hs = humerus.sweep
    for k in range(hs.n_frames):
        work, dx, dy = _work(np.asarray(hs.frames[k]), (float(hs.spacing_mm[0]),) * 2)
        assert outside_sector(work, dx, dy, P) is None


def test_inside_percentiles_are_numpys_over_the_inside():
    rng = np.random.default_rng(0)
    rows = rng.uniform(0.1, 1.0, (7, 50)).astype(np.float32)
    n_out = np.array([0, 3, 10, 49, 50, 20, 0])
    for r, k in enumerate(n_out):
        rows[r, :k] = 0.0  # the outside's black sorts first
    srt = np.sort(rows, axis=1)
    got = _inside_percentiles(srt, n_out, (60.0, 80.0))
    for r, k in enumerate(n_out):
        if k == 50:  # nothing inside: a nearest row's values (rows 3 and 5)
            assert np.allclose(got[:, r], got[:, 3]) or np.allclose(got[:, r], got[:, 5])
            continue
        want = np.percentile(rows[r, k:], (60.0, 80.0))
        assert np.allclose(got[:, r], want, atol=1e-6)

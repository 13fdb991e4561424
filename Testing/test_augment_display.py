"""Display-chain augmentations: another scanner's curve, depth gain, smoothing and noise.

The segmenter's hold on them is checked on the real L14 recording in
``test_real_recording.py`` (they are in ``augment.RECORDING_AUGMENTATIONS``); here,
what each does to the pixels, and that it leaves the field's black and the poses alone.
"""

from __future__ import annotations

import numpy as np
import pytest

from BoneUSRecon.Logic.simulation import augment
from BoneUSRecon.Logic.sweep import Sweep


@pytest.fixture(scope="module")
def sweep() -> Sweep:
    rng = np.random.default_rng(0)
    frames = rng.integers(1, 256, (3, 40, 30)).astype(np.uint8)
    frames[:, :, :4] = 0  # black outside the field, as scan conversion writes it
    m = np.tile(np.diag([0.2, 0.1, 1.0, 1.0]), (3, 1, 1))
    m[:, 2, 3] = np.arange(3)
    return Sweep(
        frames=frames, image_to_reference=m, timestamps=np.arange(3.0), valid=np.ones(3, bool)
    )


ALL = {
    "curve": lambda s: augment.display_curve(s, 0.6),
    "gain": lambda s: augment.depth_gain(s, 1.3, 0.6),
    "smooth": lambda s: augment.smooth(s, 0.3),
    "noise": lambda s: augment.add_noise(s, 12.0),
}


@pytest.mark.parametrize("name", list(ALL))
def test_display_augmentations_keep_the_black_and_the_poses(sweep, name):
    out = ALL[name](sweep)
    assert out.frames.dtype == np.uint8 and out.frames.shape == sweep.frames.shape
    assert (out.frames[:, :, :4] == 0).all()
    assert np.array_equal(out.image_to_reference, sweep.image_to_reference)
    assert not np.array_equal(out.frames, sweep.frames)


def test_display_curve_maps_each_grey(sweep):
    out = augment.display_curve(sweep, 1.6).frames.astype(float)
    g = sweep.frames.astype(float)
    assert np.abs(out - np.rint(255 * (g / 255) ** 1.6)).max() <= 1
    assert (out[g == 255] == 255).all()
    with pytest.raises(ValueError, match="gamma"):
        augment.display_curve(sweep, 0.0)


def test_depth_gain_runs_from_the_top_to_the_bottom_row(sweep):
    flat = sweep.replace(frames=np.where(sweep.frames > 0, 100, 0).astype(np.uint8))
    out = augment.depth_gain(flat, 1.3, 0.6).frames[0, :, 10]
    assert out[0] == 130 and out[-1] == 60
    assert (np.diff(out.astype(int)) <= 0).all()


def test_smoothing_lowers_the_speckle_and_noise_adds_its_std(sweep):
    inside = sweep.frames[:, :, 8:-4].astype(float)
    smoothed = augment.smooth(sweep, 0.3).frames[:, :, 8:-4].astype(float)
    assert smoothed.std() < 0.5 * inside.std()
    flat = sweep.replace(frames=np.where(sweep.frames > 0, 128, 0).astype(np.uint8))
    noisy = augment.add_noise(flat, 12.0).frames[:, :, 4:].astype(float)
    assert noisy.std() == pytest.approx(12.0, rel=0.1)
    assert noisy.mean() == pytest.approx(128.0, abs=1.0)

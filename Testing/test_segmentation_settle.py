"""Settle (issue 10): a contour running on a layer just over the bone is moved onto it.

Ground truth two ways: a frame drawn here with a known flat bone (its echo, a grey
shadow under it) and a brighter layer ``gap`` mm over it, with and without the shadow
(a phantom bone that passes sound, as the L14 recording's); and the project's
simulator (the hard preset: fascia converging on the bone, faint tops), whose true
surface is known analytically.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import small_simulation
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import SegmentationParams, segment_sweep
from BoneUSRecon.Logic.segmentation.evidence import bone_evidence
from BoneUSRecon.Logic.segmentation.params import SettleParams, ShadowPathParams
from BoneUSRecon.Logic.segmentation.settle import settle_points

SPACING = 0.1  # mm per pixel
BONE_MM, H, W = 15.0, 260, 240  # the bone's top 15 mm deep; a 26 x 24 mm frame
LEFT, RIGHT = 40, 200  # the bone's columns


def layer_frame(seed: int, *, gap_mm: float = 1.0, shadow: float = 0.45) -> np.ndarray:
    """A flat bone ``BONE_MM`` deep (echo 3x the tissue) under a layer ``gap_mm`` over it
    (echo 4x: brighter than the bone), speckle blurred by a point spread function,
    log-compressed to 50 dB; everything under the bone returns ``shadow`` of the tissue
    (1.0: a phantom that passes sound)."""
    rng = np.random.default_rng(seed)
    z = np.arange(H)[:, None] * SPACING
    speckle = gaussian_filter(rng.rayleigh(1.0, (H, W)), (1.0, 2.0))
    speckle /= speckle.mean()
    cols = np.zeros(W, bool)
    cols[LEFT:RIGHT] = True
    amp = speckle * np.where((z > BONE_MM) & cols, shadow, 1.0)
    line = lambda depth, a: a * np.exp(-0.5 * ((z - depth) / 0.12) ** 2) * cols  # noqa: E731
    amp += line(BONE_MM, 3.0) + line(BONE_MM - gap_mm, 4.0)
    db = 20 * np.log10(amp + 1e-3)
    return np.clip(255 * (db + 30) / 50, 0, 255).astype(np.uint8)


def contour_at(depth_mm: float) -> np.ndarray:
    i = np.arange(LEFT + 10, RIGHT - 10, 3, dtype=float)
    return np.column_stack([i, np.full(i.size, depth_mm / SPACING)])


def settled(image: np.ndarray, contour: np.ndarray) -> np.ndarray:
    ev = bone_evidence(image, (SPACING, SPACING), ShadowPathParams())
    return settle_points(ev, [contour], (SPACING, SPACING))[0]


@pytest.mark.parametrize("gap_mm", [0.8, 1.5, 2.5])
@pytest.mark.parametrize("seed", [0, 1])
def test_layer_over_the_bone_settles_onto_the_bone(seed, gap_mm):
    img = layer_frame(seed, gap_mm=gap_mm)
    c = contour_at(BONE_MM - gap_mm)
    out = settled(img, c)
    err = np.abs(out[:, 1] * SPACING - BONE_MM)
    assert np.mean(err <= 0.25) >= 0.9, np.round(np.quantile(err, [0.5, 0.9]), 2)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_contour_on_the_bone_stays(seed):
    # Under the bone lie its shadow, its own echo's tail and nothing brighter: no
    # deeper onset beats the bone's own.
    img = layer_frame(seed, gap_mm=1.0)
    c = contour_at(BONE_MM)
    assert settled(img, c) is c


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_no_shadow_nothing_moves(seed):
    # A phantom bone that passes sound (the L14 recording): no onset, nothing to go by.
    img = layer_frame(seed, gap_mm=1.0, shadow=1.0)
    c = contour_at(BONE_MM - 1.0)
    assert settled(img, c) is c


def test_disabled_or_short_contours_are_returned_as_given():
    img = layer_frame(0)
    ev = bone_evidence(img, (SPACING, SPACING), ShadowPathParams())
    c = contour_at(BONE_MM - 1.0)
    short = c[:2]
    out = settle_points(ev, [c, short], (SPACING, SPACING), SettleParams(enabled=False))
    assert out[0] is c and out[1] is short
    assert settle_points(ev, [short], (SPACING, SPACING))[0] is short


@pytest.mark.parametrize(
    "kw",
    [dict(window_mm=(1.0, 0.5)), dict(depth_mm=0.5, own_mm=0.6), dict(gain_z=-1.0), dict(run_mm=0)],
)
def test_bad_parameters_are_refused(kw):
    with pytest.raises(BoneUSReconError, match="SettleParams"):
        SettleParams(**kw)

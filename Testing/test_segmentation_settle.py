"""Settle (issue 10): a contour running on a layer just over the bone is moved onto it.

Ground truth two ways: a frame drawn here with a known flat bone (its echo, a grey
shadow under it) and a brighter layer ``gap`` mm over it, with and without the shadow
(a phantom bone that passes sound, as the L14 recording's); and the project's
simulator (the hard preset: fascia converging on the bone, faint tops), whose true
surface is known analytically.
"""

from __future__ import annotations

import numpy as np
import pytest
from conftest import small_simulation
from scipy.ndimage import gaussian_filter
from scipy.spatial import cKDTree

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import SegmentationParams, segment_sweep
from BoneUSRecon.Logic.segmentation.evidence import bone_evidence
from BoneUSRecon.Logic.segmentation.params import RimParams, SettleParams, ShadowPathParams
from BoneUSRecon.Logic.segmentation.settle import settle_points
from BoneUSRecon.Logic.simulation.scoring import score_simulation

SPACING = 0.1  # mm per pixel
BONE_MM, H, W = 15.0, 260, 240  # the bone's top 15 mm deep; a 26 x 24 mm frame
LEFT, RIGHT = 40, 200  # the bone's columns


def layer_frame(
    seed: int,
    *,
    gap_mm: float | None = 1.0,
    shadow: float = 0.45,
    band_mm: float = 0.0,
    inside_mm: float | None = None,
) -> np.ndarray:
    """A flat bone ``BONE_MM`` deep (echo 3x the tissue) under a layer ``gap_mm`` over it
    (echo 4x: brighter than the bone; None: no layer), speckle blurred by a point spread
    function, log-compressed to 50 dB; everything under the bone returns ``shadow`` of
    the tissue (above 1: a phantom bone that passes sound and echoes inside, as the L14
    forearm's). ``band_mm``: the bone's echo is a band this thick (the L14 cortex);
    ``inside_mm``: an echo this far under the bone's top, inside it."""
    rng = np.random.default_rng(seed)
    z = np.arange(H)[:, None] * SPACING
    speckle = gaussian_filter(rng.rayleigh(1.0, (H, W)), (1.0, 2.0))
    speckle /= speckle.mean()
    cols = np.zeros(W, bool)
    cols[LEFT:RIGHT] = True
    amp = speckle * np.where((z > BONE_MM + band_mm) & cols, shadow, 1.0)

    def line(depth: float, a: float, thick: float = 0.0) -> np.ndarray:
        dz = np.maximum(np.abs(z - depth - thick / 2) - thick / 2, 0.0)
        return a * np.exp(-0.5 * (dz / 0.12) ** 2) * cols

    amp += line(BONE_MM, 3.0, band_mm)
    if gap_mm is not None:
        amp += line(BONE_MM - gap_mm, 4.0)
    if inside_mm is not None:
        amp += line(BONE_MM + inside_mm, 2.0)
    db = 20 * np.log10(amp + 1e-3)
    return np.clip(255 * (db + 30) / 50, 0, 255).astype(np.uint8)


def contour_at(depth_mm: float) -> np.ndarray:
    i = np.arange(LEFT + 10, RIGHT - 10, 3, dtype=float)
    return np.column_stack([i, np.full(i.size, depth_mm / SPACING)])


def settled(image: np.ndarray, contour: np.ndarray) -> np.ndarray:
    ev = bone_evidence(image, (SPACING, SPACING), ShadowPathParams())
    return settle_points(ev, [contour], (SPACING, SPACING))[0]


@pytest.mark.parametrize("gap_mm", [1.0, 1.2, 1.5])
@pytest.mark.parametrize("seed", [0, 1])
def test_layer_over_the_bone_settles_onto_the_bone(seed, gap_mm):
    # Measured on this frame (seeds 0-3): gaps of 1.0-1.5 mm settle whole; 0.8 mm and
    # 2.0-2.5 mm are left where they are (at 0.8 the bone's onset reaches into the
    # layer's own window; at 2 mm and more the layer's own onset over this smooth
    # speckle, whose mean is ~0.92 of the tissue level the window above is capped at,
    # exceeds SettleParams.own_max_z). The guard keeps the bone's own points off its
    # reverberation copies; the hard simulated sweep below measures what it costs.
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
def test_a_bone_that_passes_sound_moves_nothing(seed):
    # A phantom bone brighter inside than the tissue beside it (the L14 forearm's 1.67x):
    # no shadow under the lower line, so nothing says it is the bone.
    img = layer_frame(seed, gap_mm=1.0, shadow=1.3)
    c = contour_at(BONE_MM - 1.0)
    assert settled(img, c) is c


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_the_top_of_a_thick_echo_band_stays(seed):
    # The L14 cortex: a band ~1.2 mm thick over a shadow, an echo inside the bone 0.6 mm
    # under the band. Its top is the surface: the onset under the band and the echo
    # inside must not pull it 1.8 mm into the bone (only the thin-line test stops it
    # here; on the recording's flanks points went 2-3 mm in without it).
    img = layer_frame(seed, gap_mm=None, band_mm=1.2, inside_mm=1.8)
    c = contour_at(BONE_MM)
    assert settled(img, c) is c


def test_settle_brings_a_hard_sweep_nearer_the_bone():
    # Hard simulated radius (seed 7): fascia converging on the shoulders, faint tops.
    # Measured: kept points > 0.5 mm from the true visible contour 17.2 % -> 15.6 %,
    # mean 0.258 -> 0.244 mm; recall 1.00 both, no wrong frame. With the rim off in
    # both runs: it follows the flanks on past the simulator's visible contour (70
    # degrees), whose points count here as off it whatever settle does.
    sim = small_simulation(bone="radius", seed=7, realism="hard")
    rows = []
    for enabled in (False, True):
        params = SegmentationParams(
            shadowpath=ShadowPathParams(
                settle=SettleParams(enabled=enabled), rim=RimParams(enabled=False)
            )
        )
        res = segment_sweep(sim.sweep, params)
        d = []
        for f, truth in enumerate(sim.true_contours_px):
            kept = res.contours[f].points_px
            if truth is None or kept is None or len(kept) == 0:
                continue
            tree = cKDTree(np.asarray(truth) * 0.3)
            d.append(tree.query(np.asarray(kept) * 0.3)[0])
        d = np.concatenate(d)
        sc = score_simulation(res, sim)
        rows.append((np.mean(d > 0.5), d.mean(), sc.recall, sc.wrong_share))
    (off0, mean0, rec0, wrong0), (off1, mean1, rec1, wrong1) = rows
    assert off1 <= off0 - 0.01, rows
    assert mean1 <= mean0 - 0.008, rows
    assert rec1 >= rec0 and wrong1 <= wrong0, rows


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

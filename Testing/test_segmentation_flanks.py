"""Flanks (issue 10 item 4, issue 11): contours followed down a bone's steep flanks.

Ground truth two ways: a frame drawn here with an exactly known round bone (its echo
fading with the angle of incidence as specular reflection does, a shadow under it, a
fascia touching its flank, a far cortex and a reverberation in its shadow), and the
project's simulator (the hard preset's fascia running off the bone), whose true surface
is known analytically.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import small_simulation
from scipy.ndimage import gaussian_filter

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import SegmentationParams, segment_sweep
from BoneUSRecon.Logic.segmentation.candidates import frame_candidates
from BoneUSRecon.Logic.segmentation.params import FlankParams, RimParams, ShadowPathParams

SPACING = 0.1  # mm per pixel
RADIUS, DEPTH = 7.0, 12.0  # the bone: a circle of 7 mm radius, centre 12 mm deep


def round_bone_frame(
    seed: int, *, fascia: bool = False, far_cortex: bool = False, h: int = 260, w: int = 320
) -> np.ndarray:
    """A frame of a round bone with a specular echo (amplitude cos^3 + 0.1 of the incidence).

    Speckle is Rayleigh amplitude blurred by a point spread function, log-compressed to
    50 dB; the bone's upper half echoes, everything under it (the bone and its shadow)
    returns 0.3 of the tissue. ``fascia``: a bright line touching the right flank at 55
    degrees and running off it laterally, nearly flat (a layer meeting the bone).
    ``far_cortex``: the bone's far wall 60 % down the shadow and a reverberation copy of
    the near echo 3 mm under it, both in the shadow.
    """
    rng = np.random.default_rng(seed)
    z, x = np.mgrid[0:h, 0:w] * SPACING
    cx = w * SPACING / 2
    speckle = gaussian_filter(rng.rayleigh(1.0, (h, w)), (1.0, 2.0))
    speckle /= speckle.mean()
    d = np.hypot(x - cx, z - DEPTH)
    under = (d < RADIUS) | ((np.abs(x - cx) < RADIUS) & (z > DEPTH))
    amp = speckle * np.where(under, 0.3, 1.0)
    cos_inc = np.cos(np.clip(np.arctan2(np.abs(x - cx), DEPTH - z), 0, np.pi / 2))
    upper = z <= DEPTH
    amp += 12.0 * (cos_inc**3 + 0.1) * np.exp(-0.5 * ((d - RADIUS) / 0.15) ** 2) * upper
    if fascia:
        zf = DEPTH - RADIUS * np.cos(np.radians(55)) + 0.05 * (x - cx)
        on = x > cx + RADIUS * np.sin(np.radians(40))
        amp += 5.0 * np.exp(-0.5 * ((z - zf) / 0.12) ** 2) * on
    if far_cortex:
        amp += 3.0 * np.exp(-0.5 * ((d - 0.6 * RADIUS) / 0.15) ** 2) * ~upper * under
        amp += 1.2 * cos_inc**3 * np.exp(-0.5 * ((d - RADIUS - 3.0) / 0.15) ** 2) * under
    db = 20 * np.log10(amp + 1e-3)
    return np.clip(255 * (db + 30) / 50, 0, 255).astype(np.uint8)


def chosen_points_mm(image: np.ndarray, enabled: bool = True) -> np.ndarray:
    # ``enabled=False``: the path alone, the rim (which follows every end on) off too.
    params = ShadowPathParams(flanks=FlankParams(enabled=enabled), rim=RimParams(enabled=enabled))
    fc = frame_candidates(image, (SPACING, SPACING), params)
    assert fc.usable, "no candidate"
    return fc.usable[0].points_px * SPACING


def reach_deg(pts: np.ndarray, w: int = 320) -> tuple[float, float, np.ndarray]:
    """Steepest slope (degrees) reached on the bone (within 0.3 mm of it) left and right,
    and each point's distance to the circle (mm)."""
    cx = w * SPACING / 2
    dev = np.abs(np.hypot(pts[:, 0] - cx, pts[:, 1] - DEPTH) - RADIUS)
    slope = np.degrees(np.arctan2(np.abs(pts[:, 0] - cx), DEPTH - pts[:, 1]))
    on = dev <= 0.3
    left = slope[on & (pts[:, 0] < cx)]
    right = slope[on & (pts[:, 0] > cx)]
    return (left.max() if left.size else 0.0), (right.max() if right.size else 0.0), dev


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_flank_followed_past_a_fascia_to_70_degrees(seed: int) -> None:
    """Both flanks reach 70 degrees on the bone; no point on the fascia meeting the flank.

    The path alone stops where the fascia meets the right flank (~56 degrees there, its
    convexity cut ends the bone at the turn onto the layer).
    """
    pts = chosen_points_mm(round_bone_frame(seed, fascia=True))
    left, right, dev = reach_deg(pts)
    assert left >= 70.0 and right >= 70.0, (left, right)
    assert dev.max() <= 0.4, dev.max()  # all on the bone: none on the fascia


def test_path_alone_stops_at_the_fascia() -> None:
    """The same frame without flank following: the right flank ends where the fascia meets it
    (so the test above measures the flanks, not an easy frame)."""
    _, right, _ = reach_deg(chosen_points_mm(round_bone_frame(0, fascia=True), enabled=False))
    assert right < 65.0, right


@pytest.mark.parametrize("seed", [3, 4])
def test_flank_stays_on_the_bone_over_far_cortex_and_reverberation(seed: int) -> None:
    """A far cortex and a reverberation copy in the shadow: the contour follows the near
    surface to 80 degrees (the path alone: 75-79) and never turns under the bone nor into
    the shadow."""
    pts = chosen_points_mm(round_bone_frame(seed, far_cortex=True))
    left, right, dev = reach_deg(pts)
    assert left >= 80.0 and right >= 80.0, (left, right)
    assert dev.max() <= 0.4, dev.max()
    assert pts[:, 1].max() <= DEPTH + 0.5  # nothing below the bone's widest point


def added_distances(sim, with_step, without_step) -> np.ndarray:
    """Distances to the true bone (mm) of the kept points one segmentation has and the
    other has not (frame by frame)."""
    added = [np.empty(0)]
    for a, b in zip(with_step.contours, without_step.contours, strict=True):
        if not a.accepted:
            continue
        p = a.points_px
        q = b.points_px if b.accepted and len(b.points_px) else np.empty((0, 2))
        new = (
            np.ones(len(p), bool)
            if not len(q)
            else np.sqrt(((p[:, None] - q[None]) ** 2).sum(-1)).min(1) > 1e-6
        )
        if new.any():
            added.append(sim.distance_to_truth(a.points_mm(sim.sweep)[new]))
    return np.concatenate(added)


def test_flanks_add_no_point_off_the_bone_where_a_fascia_runs_off_it() -> None:
    """Simulated hard sweep with a fascia running off the bone at its level (as bright as
    the bone, tissue beneath): the points the flank following adds lie on the true bone.

    The arc tracer alone (the rim, which follows every end on from where this tracer
    left it, is off in both runs: its own test is in ``test_segmentation_rim.py``)."""
    sim = small_simulation(
        bone="tibia", n_frames=20, seed=5, realism="hard", hard_conditions=("fascia",)
    )
    no_rim = SegmentationParams().shadowpath
    base = SegmentationParams(
        shadowpath=dataclasses.replace(no_rim, rim=dataclasses.replace(no_rim.rim, enabled=False))
    )
    off = dataclasses.replace(
        base, shadowpath=dataclasses.replace(base.shadowpath, flanks=FlankParams(enabled=False))
    )
    d = added_distances(sim, segment_sweep(sim.sweep, base), segment_sweep(sim.sweep, off))
    assert d.size >= 20  # the flanks did add points here
    assert np.mean(d > 0.5) <= 0.05 and d.max() <= 1.0, (np.mean(d > 0.5), d.max())


@pytest.mark.parametrize(
    ("changes", "says"),
    [
        ({"outside_mm": (1.5, 0.5)}, "outside_mm must be increasing"),
        ({"null_mm": 1.0}, "null_mm must be > 2 band_mm"),
        ({"step_mm": 0.0}, "FlankParams.step_mm must be > 0"),
        ({"max_deg": 95.0}, "FlankParams.max_deg must lie in"),
        ({"stop_z": -1.0}, "FlankParams.stop_z must be >= 0"),
    ],
)
def test_bad_flank_params_refused(changes: dict, says: str) -> None:
    with pytest.raises(BoneUSReconError, match=says):
        FlankParams(**changes)


def test_stop_level_ignores_windows_touching_the_image_edge() -> None:
    """The stop level is what speckle gives beside the flank: null windows averaging an
    invalid sample (a null band leaving the image) must not set it, even when they are a
    third of the pool (they sat at ~-250 against valid values of a few tenths)."""
    from BoneUSRecon.Logic.segmentation.flanks import _BAD, _stop_level

    rng = np.random.default_rng(0)
    clean = rng.normal(0.1, 0.3, 40)
    n_run = 4
    touched = (_BAD + (n_run - 1) * rng.normal(0.1, 0.3, 20)) / n_run
    whole = np.full(10, _BAD)
    level = _stop_level(np.concatenate([clean, touched, whole]), n_run, 4.0)
    assert level == pytest.approx(_stop_level(clean, n_run, 4.0))
    assert 0.5 < level < 3.0, level
    assert _stop_level(np.concatenate([clean[:9], touched, whole]), n_run, 4.0) is None

"""Frame-level scoring (issue 10, item 7) against constructed inputs with known answers."""

from __future__ import annotations

import numpy as np
import pytest

from BoneUSRecon.Logic.segmentation import SegmentationParams
from BoneUSRecon.Logic.segmentation.result import FrameContour, SegmentationResult
from BoneUSRecon.Logic.simulation import SimulationParams, simulate
from BoneUSRecon.Logic.simulation.scoring import (
    contour_slopes_deg,
    densify_px,
    polyline_distance,
    score_frames,
    score_reference,
    score_simulation,
)


def _line(z: float, x0: float = 0.0, x1: float = 10.0, n: int = 11) -> np.ndarray:
    x = np.linspace(x0, x1, n)
    return np.column_stack([x, np.zeros(n), np.full(n, z)])


def test_score_frames_known_answers() -> None:
    # Truth: the plane z = 0, seen as the segment x in [0, 10] in frames 0-3; frame 4 shows no bone.
    truth = {k: _line(0.0) for k in range(4)}
    kept = {
        0: _line(0.0, 0.0, 5.0, 6),  # on the bone, covers half of it
        1: _line(2.0),  # 2 mm off: neither on the bone nor a wrong structure
        2: _line(5.0),  # 5 mm off: a wrong structure
        # frame 3: nothing kept
        4: _line(0.5),  # kept where no bone is shown: wrong
    }
    slopes = {k: np.r_[np.zeros(10), 50.0] for k in range(4)}
    sc = score_frames(kept, truth, list(range(5)), lambda k, p: np.abs(p[:, 2]), slopes)
    f = sc.frames
    assert [x.median_mm for x in f[:3]] == [0.0, 2.0, 5.0] and np.isnan(f[3].median_mm)
    assert [x.on_bone for x in f] == [True, False, False, False, False]
    assert [x.wrong for x in f] == [False, False, True, False, True]
    assert sc.frames_with_bone == 4 and sc.kept == 4
    assert sc.recall == pytest.approx(1 / 4) and sc.wrong_share == pytest.approx(2 / 5)
    # Frame 0 covers x in [0, 5] (+1 mm reach): 7 of the 11 true points.
    assert (
        f[0].coverage == pytest.approx(7 / 11) and f[3].coverage == 0.0 and np.isnan(f[4].coverage)
    )
    # The 50-degree point (x = 10) is not reached by frame 0; frame 1 is 2 mm off: reaches nothing.
    assert (
        f[0].steepest_deg == 0.0 and np.isnan(f[1].steepest_deg) and f[0].true_steepest_deg == 50.0
    )
    s = sc.summary()
    d = np.concatenate([np.zeros(6), np.full(11, 2.0), np.full(11, 5.0), np.full(11, 0.5)])
    assert s["median_mm"] == pytest.approx(np.median(d)) and s["over_2mm"] == pytest.approx(11 / 39)
    assert s["p95_mm"] == pytest.approx(np.percentile(d, 95))


def test_contour_slopes_and_polyline_distance() -> None:
    # A flat top then a 45-degree and a vertical flank.
    p = np.array(
        [[0.0, 0.0], [1.0, 0.0], [2.0, 0.0], [3.0, 1.0], [4.0, 2.0], [4.0, 3.0], [4.0, 4.0]]
    )
    sl = contour_slopes_deg(p)
    assert (
        sl[:2] == pytest.approx([0.0, 0.0])
        and sl[3] == pytest.approx(45.0)
        and sl[-1] == pytest.approx(90.0)
    )
    poly = np.array([[0.0, 0.0], [10.0, 0.0], [10.0, 10.0]])
    q = np.array([[5.0, 3.0], [12.0, 5.0], [-4.0, 3.0], [10.0, 10.0]])
    assert polyline_distance(q, poly) == pytest.approx([3.0, 2.0, 5.0, 0.0])
    d = densify_px(np.array([[2.0, 10.0], [6.0, 14.0]]))
    assert d[:, 0] == pytest.approx([2, 3, 4, 5, 6]) and d[:, 1] == pytest.approx(
        [10, 11, 12, 13, 14]
    )


def _result(contours: dict[int, np.ndarray], n: int) -> SegmentationResult:
    cs = tuple(
        FrameContour(
            k,
            contours.get(k, np.empty((0, 2))),
            np.zeros(len(contours.get(k, []))),
            1.0,
            k in contours,
        )
        for k in range(n)
    )
    return SegmentationResult(contours=cs, method="test", params=SegmentationParams())


@pytest.fixture(scope="module")
def sim():
    return simulate(
        SimulationParams(bone="radius", n_frames=10, width=96, height=96, spacing_mm=0.4, seed=2)
    )


def test_score_simulation_perfect_shifted_and_missing(sim) -> None:
    n = sim.sweep.n_frames
    truth = {k: c for k, c in enumerate(sim.true_contours_px) if len(c)}
    perfect = score_simulation(_result(truth, n), sim).summary()
    assert perfect["recall"] == 1.0 and perfect["wrong_share"] == 0.0
    assert perfect["median_mm"] < 0.01 and perfect["coverage"] == 1.0
    assert perfect["steepest_deg"] == pytest.approx(perfect["true_steepest_deg"])
    # 5 mm deeper (12.5 rows of 0.4 mm) in every other frame, nothing in frame 1.
    sp = float(sim.sweep.spacing_mm[1])
    moved = {k: c + [0.0, 5.0 / sp] if k % 2 == 0 else c for k, c in truth.items() if k != 1}
    sc = score_simulation(_result(moved, n), sim)
    odd = [k for k in range(n) if k % 2 == 1 and k != 1]
    assert sc.recall == pytest.approx(len(odd) / n)
    assert sc.wrong_share == pytest.approx(len(range(0, n, 2)) / n)
    # Against reference contours (the truth itself, sparsely sampled), the same answers.
    sparse = {
        k: c[::7] if (len(c) - 1) % 7 == 0 else np.vstack([c[::7], c[-1:]])
        for k, c in truth.items()
    }
    ref = score_reference(_result(moved, n), sim.sweep, sparse)
    assert ref.recall == pytest.approx(sc.recall) and ref.wrong_share == pytest.approx(
        sc.wrong_share
    )


def test_far_cortex_is_not_the_imaged_bone(sim) -> None:
    # The bone's far side lies on the true surface too (distance ~0), but it is not the
    # surface the probe images: a segmenter caught on it is on a wrong structure.
    from BoneUSRecon.Logic.simulation.sections import bone_sections

    n, w = sim.sweep.n_frames, sim.sweep.width
    sec = bone_sections(sim.geometry, sim.path.image_to_reference, sim.path.s, w, far=True)
    far = {}
    for k in range(n):
        i = np.flatnonzero(np.isfinite(sec.bottom_j[k]) & (sec.bottom_j[k] < sim.sweep.height - 1))
        if i.size >= 3 and len(sim.true_contours_px[k]):
            far[k] = np.column_stack([i, sec.bottom_j[k, i]])
    assert len(far) >= n // 2
    k0 = next(iter(far))
    assert sim.distance_to_truth(sim.sweep.to_reference(k0, far[k0])).max() < 0.01
    sc = score_simulation(_result(far, n), sim)
    assert sc.recall == 0.0 and sc.wrong_share == pytest.approx(len(far) / n)

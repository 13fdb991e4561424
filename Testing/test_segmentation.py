"""Segmentation: the paper's snake, the default shadowpath, the sweep-level track.

Accuracy is measured in millimetres against ground truth: the simulator's true bone
surface (``Simulation.distance_to_truth``) and, for the pixel-size tests, a small
analytic frame whose bone echo depth is known exactly.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from vtkmodules.util import numpy_support

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import (
    SEGMENTERS,
    SegmentationParams,
    SnakeParams,
    points_polydata,
    segment_frame,
    segment_sweep,
)
from BoneUSRecon.Logic.segmentation.candidates import frame_candidates
from BoneUSRecon.Logic.segmentation.posterior import posterior_choice
from BoneUSRecon.Logic.segmentation.snake import internal_matrix_banded, run_snake
from BoneUSRecon.Logic.sweep import Sweep
from BoneUSRecon.Logic.vtkio import polydata_points


# -- a small analytic frame: bone echo at a known depth (mm) -------------------------
def analytic_frame(
    spacing: float,
    *,
    width_mm: float = 16.0,
    height_mm: float = 12.8,
    seed: int = 0,
    depth_mm: float = 7.0,
    bone: bool = True,
) -> tuple[np.ndarray, np.ndarray]:
    """Speckled tissue, a Gaussian bone echo on ``depth(x)``, dark shadow below.

    Returns the uint8 frame and the true echo depth (mm) per column.
    """
    rng = np.random.default_rng(seed)
    w, h = int(round(width_mm / spacing)), int(round(height_mm / spacing))
    x = np.arange(w) * spacing
    y = (np.arange(h) * spacing)[:, None]
    surf = depth_mm + 1.5 * np.sin(x / width_mm * np.pi * 1.3)
    img = 70 * rng.rayleigh(1.0, (h, w)) * np.exp(-0.05 * y)
    img += 40 * np.exp(-0.5 * ((y - 3) / 0.1) ** 2) * rng.rayleigh(1, (h, w))  # fascia
    if bone:
        d = y - surf[None, :]
        img = np.where(d > 0, img * np.exp(-d / 0.4) * 0.1 + 3 * rng.rayleigh(1, (h, w)), img)
        img += 200 * np.exp(-0.5 * (d / 0.15) ** 2) * (0.7 + 0.3 * rng.rayleigh(1, (h, w)))
    return np.clip(img, 0, 255).astype(np.uint8), surf


def analytic_sweep(n: int = 12, spacing: float = 0.1, *, no_bone=(), black=False) -> Sweep:
    frames, mats = [], []
    for k in range(n):
        img, _ = analytic_frame(spacing, seed=k, depth_mm=6 + 0.03 * k, bone=k not in no_bone)
        frames.append(np.zeros_like(img) if black else img)
        m = np.eye(4)
        m[0, 0] = m[1, 1] = spacing
        m[2, 3] = 0.5 * k
        mats.append(m)
    return Sweep(np.stack(frames), np.stack(mats), np.arange(n) * 0.05, np.ones(n, bool))


def depth_error_mm(points_px: np.ndarray, surf: np.ndarray, spacing: float) -> np.ndarray:
    i, j = points_px[:, 0], points_px[:, 1]
    return j * spacing - np.interp(i, np.arange(surf.size), surf)


# -- the paper's snake ---------------------------------------------------------------
def test_internal_matrix_is_the_free_end_pentadiagonal():
    n, w1, w2, tau = 9, 1.0, 2.5, 3.0
    ab = internal_matrix_banded(n, w1, w2, tau)
    dense = np.diag(ab[2]) + np.diag(ab[1, 1:], 1) + np.diag(ab[1, 1:], -1)
    dense += np.diag(ab[0, 2:], 2) + np.diag(ab[0, 2:], -2)
    d1 = np.diff(np.eye(n), axis=0)
    d2 = np.diff(np.eye(n), n=2, axis=0)
    np.testing.assert_allclose(dense, np.eye(n) + 2 * tau * (w1 * d1.T @ d1 + w2 * d2.T @ d2))
    # Free ends: a translated contour has no internal energy, so rows sum to 1.
    np.testing.assert_allclose(dense.sum(1), 1.0)
    # The energy of eq. (1) is y^T A y / 2 with A the Hessian.
    y = np.random.default_rng(0).normal(size=n)
    a = (dense - np.eye(n)) / tau
    e = w1 * np.sum(np.diff(y) ** 2) + w2 * np.sum(np.diff(y, 2) ** 2)
    assert y @ a @ y / 2 == pytest.approx(e)


def test_snake_energy_decreases_and_stops_by_the_3px_rule():
    s = 0.1
    img, surf = analytic_frame(s)
    run = run_snake(img, (s, s), init_row=img.shape[0] - 1)
    e = run.energies
    assert e.size == run.iterations + 1
    assert e[-1] < e[0] - 100
    # Monotone up to round-off of the bilinear sampling.
    assert np.all(np.diff(e) <= 1e-6 * np.abs(e[:-1]).max())
    # Stopped by the paper's rule: the last iteration moved < 3 px, none before did.
    assert run.stopped_by == "displacement"
    assert run.displacements_px[-1] < 3.0
    assert np.all(run.displacements_px[SnakeParams().min_iterations - 1 : -1] >= 3.0)
    assert run.iterations < 300
    # It found the bone.
    err = depth_error_mm(run.points_px, surf, s)
    assert abs(np.median(err)) < 0.2


def test_snake_iteration_cap():
    s = 0.1
    img, _ = analytic_frame(s)
    run = run_snake(img, (s, s), img.shape[0] - 1, SnakeParams(stop_px=0.0, max_iterations=25))
    assert run.iterations == 25 and run.stopped_by == "max_iterations"


def test_posterior_choice_threshold_and_longest_run():
    # 12 points 0.6 mm apart; bright points 1-4 and 7-8 (a gap of 3 points = 1.8 mm).
    val = np.array([10, 200, 210, 205, 220, 10, 10, 230, 240, 10, 10, 10.0])
    for s in (0.05, 0.15):  # same physical layout at two pixel sizes
        pts = np.column_stack([np.arange(12) * 0.6 / s, np.zeros(12)])
        keep = posterior_choice(pts, val, (s, s))
        assert np.flatnonzero(keep).tolist() == [1, 2, 3, 4]
    # Threshold is I_mean + 0.005 I_var.
    thr = val.mean() + 0.005 * val.var()
    assert not (val[[1, 2, 3, 4]] <= thr).any()


@pytest.mark.parametrize("method", sorted(SEGMENTERS))
def test_pixel_size_invariance(method):
    """The same anatomy at 0.05 and 0.15 mm/px gives the same contour in mm."""
    params = SegmentationParams(method=method)
    res = {}
    for s in (0.05, 0.15):
        img, surf = analytic_frame(s, seed=3)
        det = segment_frame(img, (s, s), params)
        err = depth_error_mm(det.points_px, surf, s)
        res[s] = (np.median(err), np.ptp(det.points_px[:, 0]) * s, det)
    assert abs(res[0.05][0] - res[0.15][0]) < 0.1
    if method == "shadowpath":
        assert abs(res[0.05][1] - res[0.15][1]) < 1.0  # lateral extent, mm
    else:
        # The posterior choice's extent depends on speckle, not on the pixel size; the
        # snake's depth and its number of iterations must not.
        it = [res[s][2].extras["iterations"] for s in (0.05, 0.15)]
        assert abs(it[0] - it[1]) <= max(3, 0.25 * max(it))


def test_shadowpath_subpixel_accuracy_on_analytic_frames():
    for s in (0.05, 0.1, 0.15):
        img, surf = analytic_frame(s, seed=7)
        det = segment_frame(img, (s, s))
        err = depth_error_mm(det.points_px, surf, s)
        assert np.median(np.abs(err)) < 0.08, s
        assert np.percentile(np.abs(err), 95) < 0.15, s
        assert np.ptp(det.points_px[:, 0]) * s > 14.0  # the whole bone, edge to edge


# -- sweep driver, rejection, outputs --------------------------------------------------
def test_sweep_rejects_frames_without_bone_and_keeps_the_rest():
    sw = analytic_sweep(12, no_bone=(4, 9))
    r = segment_sweep(sw)
    assert [c.frame for c in r.contours] == list(range(12))
    assert set(r.rejected) == {4, 9}
    assert all(c.confidence > 0.5 for c in r.accepted)
    pts, frame, inten, conf = r.points_mm(sw)
    named = r.points_mm(sw)
    assert named.xyz is not pts and np.array_equal(named.xyz, pts)
    assert np.array_equal(named.frame, frame) and np.array_equal(named.confidence, conf)
    assert pts.shape == (r.n_points, 3) and set(frame) == set(range(12)) - {4, 9}
    assert inten.min() > 100 and conf.min() > 0.5
    per_frame = r.contours_mm(sw)
    assert [f for f, _ in per_frame] == sorted(set(range(12)) - {4, 9})
    # Points are ordered along the contour (increasing column = increasing x here).
    assert all(np.all(np.diff(p[:, 0]) > 0) for _, p in per_frame)


def test_invalid_frames_are_not_segmented():
    sw = analytic_sweep(6)
    valid = np.ones(6, bool)
    valid[2] = False
    r = segment_sweep(sw.replace(valid=valid))
    assert [c.frame for c in r.contours] == [0, 1, 3, 4, 5]


def test_points_polydata_arrays():
    sw = analytic_sweep(5)
    r = segment_sweep(sw)
    pd = points_polydata(r, sw)
    assert pd.GetNumberOfPoints() == r.n_points
    np.testing.assert_allclose(polydata_points(pd), r.points_mm(sw).xyz)
    for name in ("Frame", "Intensity", "Confidence"):
        assert pd.GetPointData().GetArray(name) is not None
    frames = numpy_support.vtk_to_numpy(pd.GetPointData().GetArray("Frame"))
    assert set(frames.tolist()) == set(range(5))


@pytest.mark.parametrize("kind", ["black", "noise"])
def test_no_bone_anywhere_raises(kind):
    if kind == "black":
        sw = analytic_sweep(5, black=True)
    else:
        rng = np.random.default_rng(0)
        base = analytic_sweep(5)
        sw = base.replace(frames=rng.integers(0, 256, base.frames.shape, dtype=np.uint8))
    for method in SEGMENTERS:
        with pytest.raises(BoneUSReconError, match="no bone contour found in any frame"):
            segment_sweep(sw, SegmentationParams(method=method))


def test_unknown_segmenter():
    with pytest.raises(BoneUSReconError, match="unknown segmenter"):
        segment_sweep(analytic_sweep(2), dataclasses.replace(SegmentationParams(), method="x"))


def test_jump_rejection():
    """A frame whose only bone-like line sits 4 mm shallower than its neighbours is off the track."""
    sw = analytic_sweep(12)
    frames = np.array(sw.frames)
    img, _ = analytic_frame(0.1, seed=99, depth_mm=2.0)
    frames[6] = img
    r = segment_sweep(sw.replace(frames=frames))
    assert set(r.rejected) == {6}
    # One category, the value elsewhere (summary keys carry no numbers).
    assert r.rejected[6] == "jump from neighbouring frames"
    c6 = next(c for c in r.contours if c.frame == 6)
    assert "mm" in c6.detail
    assert r.summary()["rejection_reasons"] == {"jump from neighbouring frames": 1}


def test_optimal_path_follows_ridge_and_leaves_where_no_bone():
    from BoneUSRecon.Logic.segmentation.candidates import _optimal_path

    h, w = 30, 40
    gain = np.full((h, w), -0.1)
    rows = (10 + 4 * np.sin(np.arange(w) / 6)).round().astype(int)
    cols = np.arange(8, 30)
    gain[rows[cols], cols] = 1.0
    steps = np.arange(-2, 3)
    path = _optimal_path(gain, 0.05 * steps**2, 0.5)
    assert np.all(path[cols] == rows[cols])
    assert np.all(path[:6] == -1) and np.all(path[32:] == -1)
    # A one-column speck is not worth two switches.
    gain2 = np.full((h, w), -0.1)
    gain2[5, 20] = 0.8
    assert np.all(_optimal_path(gain2, 0.05 * steps**2, 0.5) == -1)


@pytest.mark.parametrize("method", sorted(SEGMENTERS))
def test_segment_frame_never_crashes_on_odd_images(method):
    """Random sizes, constant, saturated and noisy frames: valid output or nothing."""
    from hypothesis import HealthCheck, given, settings
    from hypothesis import strategies as st

    @settings(max_examples=25, deadline=None, suppress_health_check=list(HealthCheck))
    @given(
        h=st.integers(4, 90),
        w=st.integers(4, 90),
        kind=st.sampled_from(["zeros", "full", "noise", "rows"]),
        spacing=st.floats(0.03, 0.6),
        seed=st.integers(0, 1000),
    )
    def check(h, w, kind, spacing, seed):
        rng = np.random.default_rng(seed)
        img = {
            "zeros": np.zeros((h, w), np.uint8),
            "full": np.full((h, w), 255, np.uint8),
            "noise": rng.integers(0, 256, (h, w), dtype=np.uint8),
            "rows": np.repeat(rng.integers(0, 256, (h, 1), dtype=np.uint8), w, axis=1),
        }[kind]
        det = segment_frame(img, (spacing, spacing), SegmentationParams(method=method))
        pts = det.points_px
        assert pts.ndim == 2 and pts.shape[1] == 2 and det.intensity.shape == (pts.shape[0],)
        if pts.shape[0]:
            assert np.all(np.isfinite(pts))
            assert np.all(np.diff(pts[:, 0]) > 0)
            assert pts[:, 0].min() >= -0.5 and pts[:, 0].max() <= w - 0.5
            assert pts[:, 1].min() >= -0.5 and pts[:, 1].max() <= h - 0.5

    check()


def test_field_of_view_columns():
    """Black columns (and 0.5 mm next to them) are outside; a dark shadow column is not."""
    from BoneUSRecon.Logic.segmentation.evidence import field_of_view
    from BoneUSRecon.Logic.segmentation.params import ShadowPathParams

    rng = np.random.default_rng(0)
    work = rng.uniform(0.1, 0.4, (80, 60)).astype(np.float32)
    work[40:, 25:35] = 0.01  # a deep, nearly black shadow: still imaged
    work[:, :10] = 0.0
    work[:, 52:] = 0.0
    inside = field_of_view(work, 0.25, ShadowPathParams())
    # 0.5 mm at 0.25 mm per column: two more columns each side are dropped.
    assert np.array_equal(np.flatnonzero(inside), np.arange(12, 50))
    assert field_of_view(np.full((20, 30), 0.3, np.float32), 0.25, ShadowPathParams()).all()


# -- look-alikes and the sweep-level track ---------------------------------------------
def _speckle(h: int, w: int, seed: int) -> np.ndarray:
    return 60.0 * np.random.default_rng(seed).rayleigh(1.0, (h, w))


def test_probe_reverberation_copy_is_never_chosen():
    """A line at depth d over a shadow with its copy at 2 d: the copy is a reverberation."""
    s = 0.1
    h, w = 200, 160
    img = _speckle(h, w, 1)
    cols = slice(20, 140)
    img[50:, cols] *= 0.15  # shadow under the line at 5 mm
    img[49:52, cols] = 230  # the line (5 mm)
    img[99:102, cols] = 120  # its probe-face copy at 10 mm, fainter, inside the shadow
    fc = frame_candidates(np.clip(img, 0, 255).astype(np.uint8), (s, s))
    depth = [float(np.median(c.points_px[:, 1])) * s for c in fc.candidates]
    assert fc.usable and abs(np.median(fc.usable[0].points_px[:, 1]) * s - 5.0) < 0.3
    for c, d in zip(fc.candidates, depth, strict=True):
        if abs(d - 10.0) < 0.5:
            assert c.reverberation


def test_fascia_with_tissue_beneath_is_valued_below_the_bone_under_it():
    """A bright fascia over the bone lets the sound through: the bone under it wins."""
    s = 0.1
    img, surf = analytic_frame(s, seed=4, depth_mm=6.5)
    img = img.astype(float)
    img[38:41, :] = np.maximum(img[38:41, :], 235)  # a bright fascia at 4 mm, tissue under it
    fc = frame_candidates(np.clip(img, 0, 255).astype(np.uint8), (s, s))
    best = max(fc.usable, key=lambda c: c.strength * (0.3 if c.echo_beneath else 1.0))
    err = depth_error_mm(best.points_px, surf, s)
    assert np.median(np.abs(err)) < 0.2


def test_a_layer_climbing_off_the_bone_above_its_top_does_not_cut_the_bone_away():
    """A fascia leaving a round bone's flank and climbing above its top (clavicle, issue 10).

    The path runs bone then fascia; the fascia's high point is the shallowest of the
    contour, so the convexity cut around it kept the fascia and dropped the bone. Each
    convex piece is weighed on its own evidence: the bone (with the shadow) is kept.
    """
    s = 0.1
    h, w = 200, 240
    x = np.arange(w) * s
    y = (np.arange(h) * s)[:, None]
    on = np.abs(x - 10.0) < 4.6  # a bone of radius 5 mm, top at 6 mm, shadow beneath
    bone = np.where(on, 11.0 - np.sqrt(np.clip(25.0 - (x - 10.0) ** 2, 0, None)), np.inf)
    attach = 11.0 - np.sqrt(25.0 - 3.5**2)
    fascia = np.where((x >= 13.5) & (x <= 19.0), attach - (x - 13.5) * 0.7, np.inf)
    for seed in (0, 1):
        img = _speckle(h, w, seed)
        d = y - bone[None, :]
        img = np.where(d > 0.2, img * 0.15, img)
        img += 200 * np.exp(-0.5 * (d / 0.15) ** 2)
        img += 200 * np.exp(-0.5 * ((y - fascia[None, :]) / 0.15) ** 2)  # tissue beneath
        fc = frame_candidates(np.clip(img, 0, 255).astype(np.uint8), (s, s))
        pts = fc.usable[0].points_px
        i = np.clip(np.rint(pts[:, 0]).astype(int), 0, w - 1)
        assert np.mean(np.abs(pts[:, 1] * s - bone[i]) < 0.3) >= 0.9
        assert np.ptp(pts[:, 0]) * s >= 0.8 * 9.2  # most of the bone's 9.2 mm width


def _synthetic_track_input(n: int, spacing_mm: float, jumps: dict[int, float]):
    """Frames ``spacing_mm`` apart along z, each with the true contour (depth 6 mm) and,
    in frames of ``jumps``, a stronger look-alike that many mm shallower."""
    from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate, FrameCandidates

    s = 0.1
    i = np.arange(20.0, 140.0, 2.0)
    frames, poses = [], []
    for k in range(n):
        true = np.column_stack([i, np.full(i.size, 60.0)])
        cands = [BoneCandidate(true, np.full(i.size, 200.0), 10.0, 3.0, 2.0)]
        if k in jumps:
            fake = np.column_stack([i, np.full(i.size, 60.0 - jumps[k] / s)])
            cands.insert(0, BoneCandidate(fake, np.full(i.size, 220.0), 14.0, 3.0, 2.0))
        frames.append(FrameCandidates(tuple(cands), (s, s)))
        m = np.eye(4)
        m[0, 0] = m[1, 1] = s
        m[2, 3] = spacing_mm * k
        poses.append(m)
    return frames, np.stack(poses)


def test_track_takes_the_continuous_bone_over_a_stronger_look_alike():
    from BoneUSRecon.Logic.segmentation.track import select_bone_track

    frames, poses = _synthetic_track_input(12, 1.4, {4: 3.7, 5: 3.7, 9: 4.0})
    ch = select_bone_track(frames, poses)
    # Frames 4, 5 and 9 hold the look-alike first (index 0): the bone is index 1 there.
    assert [int(c) for c in ch.chosen] == [1 if k in (4, 5, 9) else 0 for k in range(12)]
    assert not any(ch.reason)


def test_track_neighbours_are_by_distance_along_the_sweep():
    """The tolerance grows with the distance between frames: a bone 2 mm deeper 12 mm
    further along is continuous, 4 mm deeper 1.4 mm further along is a jump."""
    from BoneUSRecon.Logic.segmentation.candidates import FrameCandidates
    from BoneUSRecon.Logic.segmentation.track import select_bone_track

    frames, poses = _synthetic_track_input(8, 1.4, {})
    # Frames 4-7 lie 12 mm further and their bone is 2 mm deeper (a sparse stretch).
    for k in range(4, 8):
        c = frames[k].candidates[0]
        deeper = dataclasses.replace(c, points_px=c.points_px + [0.0, 20.0])
        frames[k] = FrameCandidates((deeper,), frames[k].spacing)
        poses[k][2, 3] += 12.0
    ch = select_bone_track(frames, poses)
    assert (ch.chosen == 0).all()
    # A 4 mm step between frames 1.4 mm apart (a fascia): the track keeps one side only.
    frames2, poses2 = _synthetic_track_input(8, 1.4, {})
    for k in range(5, 8):
        c = frames2[k].candidates[0]
        frames2[k] = FrameCandidates(
            (dataclasses.replace(c, points_px=c.points_px + [0.0, 40.0]),), frames2[k].spacing
        )
    ch2 = select_bone_track(frames2, poses2)
    assert (ch2.chosen[:5] == 0).all() and (ch2.chosen[5:] == -1).all()
    assert set(ch2.reason[5:]) == {"jump from neighbouring frames"}


@pytest.mark.parametrize(
    ("cls", "field", "value"),
    [
        ("ShadowPathParams", "work_mm", 0.0),
        ("ShadowPathParams", "shadow_z_full", -2.0),
        ("ShadowPathParams", "tissue_percentile", 100.0),
        ("RejectionParams", "tolerance_mm", -1.0),
        ("RejectionParams", "max_skip", -1),
    ],
)
def test_parameters_are_checked_at_the_door(cls, field, value):
    from BoneUSRecon.Logic.segmentation import params

    with pytest.raises(BoneUSReconError, match=field):
        getattr(params, cls)(**{field: value})


def _dome_with_climbing_layer(jitter_px: float = 0.0) -> np.ndarray:
    """A contour as the path draws it over clavicle seed 31, frame 60 (0.15 mm pixels):
    a fascia descending onto the bone's left flank (columns 58-146, rows 35 -> 47), then
    the bone's dome (top at row 39, column 174; row 61 at column 218)."""
    i = np.arange(58.0, 219.0, 2.0)
    j = np.where(
        i <= 146,
        35.0 + (i - 58.0) * 12.0 / 88.0,
        39.0
        + 22.0
        * ((i - 174.0) / 44.0) ** 2
        * np.where(i < 174, 8.0 / 22.0 * (44.0 / 28.0) ** 2, 1.0),
    )
    j = j + np.random.default_rng(0).normal(0.0, jitter_px, i.size)
    return np.column_stack([i, j])


def test_contour_split_where_a_layer_meets_the_bone_in_a_valley():
    """A layer meeting the bone's flank and climbing away from it forms a valley with the
    dome: two structures. The old convexity cut alone kept both as one piece (the flank
    there is too shallow for its kink rule)."""
    from BoneUSRecon.Logic.segmentation.candidates import _convex_pieces
    from BoneUSRecon.Logic.segmentation.params import ShadowPathParams

    pts = _dome_with_climbing_layer()
    x = pts[:, 0]
    # The bone's shadow under the dome, tissue under the layer (shadow z-scores).
    shadow = np.where(x > 146, 2.5, 0.3)
    pieces = _convex_pieces(pts, (0.15, 0.15), ShadowPathParams(), 5, shadow)
    # No piece spans both structures; one is the dome, from the valley to the end.
    assert not any(m[x < 120].any() and m[x > 170].any() for m in pieces)
    dome = [m for m in pieces if m[x > 170].any()]
    assert len(dome) == 1 and x[dome[0]].min() >= 140 and x[dome[0]].max() == x.max()


def test_a_dome_with_speckle_jitter_is_not_split():
    """The split needs a dip deeper than ``valley_mm`` on both sides: the refined
    contour's jitter (0.1 px here, 0.3 px at worst) never makes one."""
    from BoneUSRecon.Logic.segmentation.candidates import _valley_runs

    i = np.arange(0.0, 160.0, 2.0)
    for sd in (0.1, 0.3):
        j = 40.0 + 0.004 * (i - 80.0) ** 2 + np.random.default_rng(1).normal(0.0, sd, i.size)
        pts = np.column_stack([i, j])
        assert len(_valley_runs(pts, (0.15, 0.15), 0.5, np.full(i.size, 2.0))) == 1


def test_a_groove_in_the_bone_is_not_split():
    """A groove in the bone (two crests, the bone's shadow under both): one contour."""
    from BoneUSRecon.Logic.segmentation.candidates import _valley_runs

    i = np.arange(0.0, 160.0, 2.0)
    j = 40.0 + 6.0 * np.exp(-0.5 * ((i - 80.0) / 12.0) ** 2) + 0.002 * (i - 80.0) ** 2
    pts = np.column_stack([i, j])
    assert len(_valley_runs(pts, (0.15, 0.15), 0.5, np.full(i.size, 2.0))) == 1
    # The same shape with tissue, not shadow, under one side: a layer meets the bone.
    assert len(_valley_runs(pts, (0.15, 0.15), 0.5, np.where(i < 80, 0.2, 2.0))) == 2


@pytest.mark.parametrize("n", [3, 4])
def test_a_handful_of_scattered_frames_is_judged_frame_by_frame(sim_factory, n) -> None:
    """3 or 4 frames over a whole sweep (80 x 64 at 0.6 mm, ~15 mm apart): the bone's
    candidates do not link, but two speckle pieces of two frames did, so no path
    linked ``min_track_frames`` frames and every frame was rejected as a jump (the
    demo's "too few frames to fit" stopped at "no bone contour found"). Each frame
    is judged alone: every one kept on the bone. (The chance link appears with the
    nulls over the tissue's pixels, ``null_dark_fraction``: the speckle pieces become
    candidates.)"""
    from BoneUSRecon.Logic.segmentation import ShadowPathParams
    from BoneUSRecon.Logic.simulation import DEFAULT_BONE, DEFAULT_SEED
    from BoneUSRecon.Logic.simulation.scoring import score_simulation

    sim = sim_factory(
        bone=DEFAULT_BONE, seed=DEFAULT_SEED, n_frames=n, width=80, height=64, spacing_mm=0.6
    )
    p = SegmentationParams(shadowpath=ShadowPathParams(null_dark_fraction=0.25))
    s = score_simulation(segment_sweep(sim.sweep, p), sim)
    assert s.recall == 1.0 and s.wrong_share == 0.0

"""Sweep ends past the bone (issue 10): the simulator's bone-free frames, and the track's
ends cut back where the frames show no bone shadow (:mod:`.segmentation.ends`).

Ground truth from the simulator: ``bone_free_frames`` renders the first / last frames
without the bone and leaves their true contours empty, so a kept frame there is wrong.
"""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import small_simulation

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import EndsParams, SegmentationParams, segment_sweep
from BoneUSRecon.Logic.segmentation.ends import (
    bone_free_ends,
    cut_ends_and_choose_again,
    shadow_step,
    shadow_steps,
    trough_step,
)
from BoneUSRecon.Logic.segmentation.track import REASONS, TrackChoice
from BoneUSRecon.Logic.simulation import SimulationParams
from BoneUSRecon.Logic.simulation.scoring import score_simulation

OFF = SegmentationParams(ends=EndsParams(enabled=False))


def _free_end(bone: str = "tibia", seed: int = 5, free=(0, 10)):
    return small_simulation(bone=bone, realism="hard", seed=seed, bone_free_frames=free)


# -- the simulator ------------------------------------------------------------------


def test_bone_free_frames_show_no_bone_and_leave_the_rest_unchanged():
    with_bone = small_simulation(bone="tibia", realism="hard", seed=5)
    sim = _free_end(free=(3, 10))
    n = sim.sweep.n_frames
    free = [*range(3), *range(n - 10, n)]
    for k in range(n):
        if k in free:
            assert sim.true_contours_px[k].shape == (0, 2)
            assert not np.isfinite(sim.sections.top_j[k]).any()
        else:
            np.testing.assert_array_equal(sim.true_contours_px[k], with_bone.true_contours_px[k])
            np.testing.assert_array_equal(sim.sweep.frames[k], with_bone.sweep.frames[k])
    # No shadow where the bone was: under its true contour (2-8 mm down) the grey is
    # that of the tissue at those depths across the frame, where with the bone it is
    # the shadow's (hard preset, grey display: ~0.8 of the rows' mean grey).
    sp = sim.params.spacing_mm
    for k in free:
        c = with_bone.true_contours_px[k]
        top = float(np.median(c[:, 1]))
        rows = slice(int(top + 2 / sp), min(int(top + 8 / sp), sim.params.height))
        cols = slice(int(c[:, 0].min()), int(c[:, 0].max()) + 1)

        ratio = [
            img[rows, cols].astype(float).mean() / img[rows].astype(float).mean()
            for img in (with_bone.sweep.frames[k], sim.sweep.frames[k])
        ]
        # Measured: 0.77-0.85 with the bone, 1.02-1.09 without.
        assert ratio[0] < 0.9
        assert 0.95 < ratio[1] < 1.15
    # The gold points stay on the bone the sweep imaged: between the frames showing it.
    assert sim.swept_range_mm[1] - sim.swept_range_mm[0] < (
        with_bone.swept_range_mm[1] - with_bone.swept_range_mm[0]
    )


@pytest.mark.parametrize(
    ("free", "match"),
    [((-1, 0), "bone_free_frames"), ((20, 19), "bone_free_frames"), ((1.5, 0), "integer")],
)
def test_bone_free_frames_are_validated(free, match):
    with pytest.raises(BoneUSReconError, match=match):
        SimulationParams(n_frames=40, bone_free_frames=free)


def test_a_kept_bone_free_frame_counts_as_wrong():
    sim = _free_end()
    r = segment_sweep(sim.sweep, OFF)
    score = score_simulation(r, sim)
    kept_free = [f for f in score.frames if f.kept and not f.shows_bone]
    # Measured: the plain track keeps all 10 (a fascia over the skin gap's shade).
    assert len(kept_free) >= 5
    assert all(f.wrong for f in kept_free)
    assert score.frames_with_bone == 30


# -- the rule -----------------------------------------------------------------------


@pytest.mark.parametrize(("bone", "seed"), [("tibia", 5), ("humerus", 5)])
def test_track_ends_cut_where_the_frames_show_no_bone(bone, seed):
    sim = _free_end(bone, seed)
    before, after = segment_sweep(sim.sweep, OFF), segment_sweep(sim.sweep)
    s0, s1 = score_simulation(before, sim), score_simulation(after, sim)
    free = set(range(30, 40))
    kept_before = free & {c.frame for c in before.accepted}
    assert len(kept_before) >= 5
    # Measured: tibia 10 -> 0 (frame 30, next to the bone, steps 0.66 of the track's
    # typical: kept until the track was chosen again without the frames cut), humerus
    # 10 -> 0.
    assert len(free & {c.frame for c in after.accepted}) <= 1
    # No frame on the bone lost; the tibia gains frames 28-29 (0.93 -> 1.00), which the
    # track went round for the fascia over the bone-free frames (see the test below).
    assert s1.recall >= s0.recall >= 0.85
    assert np.median(s1.distances) < 0.3
    cut = {c.frame for c in after.contours if c.reason == REASONS["noshadow"]}
    # Each bone-free frame the plain track kept is cut, or left off the track chosen
    # again without the frames cut (rejected as a jump). Measured: tibia 9 cut and
    # frame 30 a jump, humerus 6 cut; since the skin gap is found whole
    # (evidence._edge_gap), the fascia over its shade links less well: tibia 0 cut and
    # 9 jumps and 1 no bone found, humerus 6 cut, 3 jumps and 1 no bone found; no
    # bone-free frame kept either way.
    jumps = {c.frame for c in after.contours if c.reason == REASONS["jump"]}
    assert len((cut | jumps) & kept_before) >= len(kept_before) - 1
    # Only frames past the bone's end, and frames kept off the bone, are cut.
    for k in cut - free:
        c = before.contours[k]
        assert np.median(sim.distance_to_truth(c.points_mm(sim.sweep))) > 1.0
    assert all("typical" in after.contours[k].detail for k in cut)


def test_the_track_is_chosen_again_without_the_frames_cut():
    """Hard tibia, seed 5, the last 10 frames bone-free (bench_segmentation's "tibia
    hard end-free"): a fascia leaves the bone's right shoulder and runs on over the
    bone-free frames. In frames 28-29 the strongest candidate lies on the bone, cut off
    at the shoulder (``shoulder_short_mm``), so it does not link to the fascia alone in
    frame 30; the track went round them to the fascia of frames 30-39, and recovery,
    guided by that track, put the fascia into them. The ends cut took frames 31-39
    off but not the bend. Chosen again without the frames cut, the track keeps the
    bone in every frame showing it, and no bone-free frame."""
    sim = _free_end()
    once = SegmentationParams(ends=EndsParams(choose_again=False))
    s0 = score_simulation(segment_sweep(sim.sweep, once), sim)
    r1 = segment_sweep(sim.sweep)
    s1 = score_simulation(r1, sim)
    med0 = {f.frame: f.median_mm for f in s0.frames}
    # Measured without the choice again: 2.56 and 1.41 mm (the fascia), and frame 30
    # (bone-free) kept on the fascia's continuation.
    assert med0[28] > 1.0 and med0[29] > 1.0
    assert s0.wrong_share > 0
    # With it: every frame showing bone kept on it (median < 1 mm; measured 0.03-0.5
    # mm), no bone-free frame kept; frames 28-29 keep their own bone candidate.
    assert s1.recall == 1.0 and s1.wrong_share == 0.0
    assert all(f.median_mm < 0.3 for f in s1.frames if f.frame in (28, 29))
    assert not any(r1.contours[k].extras.get("recovered") for k in (28, 29))


def test_cut_ends_and_choose_again_solves_once_without_the_frames_cut():
    """The rule alone, on a made-up track of 12 frames whose last 3 step weakly: they
    are cut, the track is chosen again once with them ruled out (their reason and
    detail kept), and that track's ends cut in turn; with ``choose_again`` off, the
    plain cut."""
    n = 12
    chosen = np.zeros(n, dtype=np.intp)
    track = TrackChoice(chosen, np.ones(n), [""] * n, [""] * n)
    step = np.full(n, -0.6)
    step[-3:] = -0.05
    calls = []

    def solve(ex):
        calls.append(dict(ex))
        ch = chosen.copy()
        ch[list(ex)] = -1
        ch[0] = -1  # the new track leaves frame 0 (to see that it is the one returned)
        reason = [ex[f][0] if f in ex else "" for f in range(n)]
        reason[0] = REASONS["jump"]
        return TrackChoice(ch, np.ones(n), reason, [ex[f][1] if f in ex else "" for f in range(n)])

    def steps(ch):
        return step[ch.chosen >= 0]

    got = cut_ends_and_choose_again(track, solve, steps)
    assert len(calls) == 1 and set(calls[0]) == {9, 10, 11}
    assert all(calls[0][f][0] == REASONS["noshadow"] for f in (9, 10, 11))
    assert got.chosen[0] == -1 and (got.chosen[1:9] == 0).all() and (got.chosen[9:] < 0).all()
    assert got.reason[9:] == [REASONS["noshadow"]] * 3 and "typical" in got.detail[10]
    plain = cut_ends_and_choose_again(track, solve, steps, EndsParams(choose_again=False))
    assert len(calls) == 1 and plain.chosen[0] == 0 and (plain.chosen[9:] < 0).all()
    # Nothing cut: nothing chosen again.
    step[:] = -0.6
    assert cut_ends_and_choose_again(track, solve, steps) is not None and len(calls) == 1


def test_sweeps_showing_bone_throughout_keep_every_frame():
    """Nothing is cut where every frame shows bone (hard and standard)."""
    for sim in (
        small_simulation(bone="tibia", realism="hard", seed=7),
        small_simulation(bone="radius", realism="hard", seed=7),
        small_simulation(bone="clavicle", seed=0),
    ):
        before, after = segment_sweep(sim.sweep, OFF), segment_sweep(sim.sweep)
        on = {c.frame for c in before.accepted}
        off = on - {c.frame for c in after.accepted}
        # Any frame cut was not on the bone (median over 1 mm: the recall criterion).
        for k in off:
            c = before.contours[k]
            assert np.median(sim.distance_to_truth(c.points_mm(sim.sweep))) > 1.0
        assert score_simulation(after, sim).recall == score_simulation(before, sim).recall


def test_shadow_step_tells_a_shadow_from_a_layer_over_tissue():
    """A bright line with a shadow under it steps down; the same line over tissue does not."""
    rng = np.random.default_rng(0)
    h, w, sp = 120, 100, 0.2
    tissue = rng.rayleigh(60.0, (h, w))
    line = np.full(w, 50.0)
    pts = np.column_stack([np.arange(20, 80, dtype=float), line[20:80]])
    layer = tissue.copy()
    layer[49:52, 20:80] = 200.0
    bone = layer.copy()
    bone[52:, 20:80] *= 0.4  # the shadow: 0.4 of the tissue's amplitude
    img = {k: np.clip(v, 0, 255).astype(np.uint8) for k, v in (("layer", layer), ("bone", bone))}
    shade = tissue.copy()
    shade[:, 20:80] *= 0.4
    shade[49:52, 20:80] = 200.0
    img["shade"] = np.clip(shade, 0, 255).astype(np.uint8)
    # The band's mean, then its darkest layer (a plain shadow's darkest millimetre is
    # its level less the speckle's residue).
    for step, off in ((shadow_step, 0.0), (trough_step, -0.1)):
        s_bone = step(img["bone"], pts, (sp, sp))
        assert s_bone == pytest.approx(np.log(0.4) + off, abs=0.1)
        assert abs(step(img["layer"], pts, (sp, sp))) < 0.2 * abs(s_bone)
        # A shade cast from above (the whole column darker): no step either.
        assert abs(step(img["shade"], pts, (sp, sp))) < 0.2 * abs(s_bone)
        assert np.isnan(step(img["bone"], np.empty((0, 2)), (sp, sp)))
    both = shadow_steps(img["bone"], pts, (sp, sp))
    assert both.shape == (2,) and both[0] == shadow_step(img["bone"], pts, (sp, sp))
    assert np.isnan(trough_step(img["bone"], pts, (sp, sp), EndsParams(trough_mm=0.0)))


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_reverberating_shadow_under_darker_muscle_steps_like_the_bone(seed):
    """A shadow at 0.4 of the tissue holding five fading reverberation copies 2.5 mm
    apart, under a muscle layer at 0.8 of the tissue's level: the band's mean steps
    0.28-0.36 of the same bone's under plain tissue with a plain shadow (weak at
    ``min_ratio`` 0.5: the grey clavicle s811's last six frames were cut so), the
    darkest layer 0.72-0.80 (not weak at ``trough_ratio`` 0.6), and a frame is only as
    weak as both readings find it."""
    rng = np.random.default_rng(seed)
    h, w, sp = 160, 100, 0.2
    tissue = rng.rayleigh(60.0, (h, w))
    pts = np.column_stack([np.arange(20, 80, dtype=float), np.full(60, 50.0)])

    def frame(above: float, copies: bool) -> np.ndarray:
        img = tissue.copy()
        img[52:, 20:80] *= 0.4
        if copies:
            for m in range(1, 6):
                r = 50 + int(round(m * 2.5 / sp))
                img[r - 1 : r + 2, 20:80] += 150 * 0.85**m
        img[49:52, 20:80] = 200.0
        img[20:47, 20:80] *= above
        return np.clip(img, 0, 255).astype(np.uint8)

    p = EndsParams()
    ref = shadow_steps(frame(1.0, False), pts, (sp, sp))
    got = shadow_steps(frame(0.8, True), pts, (sp, sp))
    assert got[0] / ref[0] < p.min_ratio
    assert got[1] / ref[1] >= p.trough_ratio
    # Twelve frames of the plain bone, the last three like this one: not cut.
    steps = np.array([ref] * 9 + [got] * 3)
    assert not bone_free_ends(steps, p).any()
    assert bone_free_ends(steps[:, 0], p)[-3:].all()  # by the band's mean alone


def test_a_muscle_on_the_bone_is_looked_past_a_thin_line_is_not():
    """The band's mean reads the shadow against the brightest 5 mm band up to
    ``cover_reach_mm`` over the contour (medians along it): a muscle at 0.6 of the
    tissue's amplitude filling 1-10 mm over the bone leaves the step the plain bone's
    (read against the band right over it alone, a third of it: weak at ``min_ratio``);
    a layer over tissue with a thin bright line 12 mm over it, or under a plain cover,
    still steps nothing."""
    rng = np.random.default_rng(3)
    h, w, sp = 200, 100, 0.2
    tissue = rng.rayleigh(60.0, (h, w))
    j0 = 120  # the contour's row: 24 mm deep, the bands reach 16 mm over it
    pts = np.column_stack([np.arange(20, 80, dtype=float), np.full(60, float(j0))])

    def frame(muscle: float, shadow: bool, line: bool = False) -> np.ndarray:
        img = tissue.copy()
        if shadow:
            img[j0 + 2 :, 20:80] *= 0.4
        img[j0 - 1 : j0 + 2, 20:80] = 200.0
        img[j0 - 50 : j0 - 5, 20:80] *= muscle  # 1-10 mm over the contour
        if line:
            img[j0 - 61 : j0 - 59, 20:80] = 220.0  # a fascia 12 mm up: 0.4 mm thick
        return np.clip(img, 0, 255).astype(np.uint8)

    p = EndsParams()
    plain = shadow_step(frame(1.0, True), pts, (sp, sp))
    assert plain == pytest.approx(np.log(0.4), abs=0.1)
    under_muscle = shadow_step(frame(0.6, True), pts, (sp, sp))
    assert under_muscle / plain >= 0.8
    alone = shadow_step(frame(0.6, True), pts, (sp, sp), EndsParams(cover_reach_mm=0.0))
    assert alone / plain < p.min_ratio  # the band right over it only: weak
    # The trough reading is not lifted (a frame is spared when either reading is not
    # weak: one lifted reading is enough for the muscle, and keeps the cut's other eye).
    assert trough_step(frame(0.6, True), pts, (sp, sp)) == trough_step(
        frame(0.6, True), pts, (sp, sp), EndsParams(cover_reach_mm=0.0)
    )
    for img in (frame(1.0, False, line=True), frame(1.0, False)):
        assert abs(shadow_step(img, pts, (sp, sp))) < 0.2 * abs(plain)
    # Too near the image's top for the bands over it: the band right over it alone.
    high = np.column_stack([pts[:, 0], np.full(60, 40.0)])
    img = frame(1.0, True)
    assert shadow_step(img, high, (sp, sp)) == shadow_step(
        img, high, (sp, sp), EndsParams(cover_reach_mm=0.0)
    )


def test_bone_free_ends_cuts_weak_runs_at_the_ends_only():
    p = EndsParams()
    w = p.min_ratio
    typical = -0.6
    steps = np.full(30, typical)
    steps[-6:] = 0.2 * typical  # a run past the bone's end
    steps[12] = 0.0  # one weak frame inside the track: both sides vouch for it
    cut = bone_free_ends(steps, p)
    assert cut[-6:].all() and not cut[:-6].any()
    # A stray fair frame inside the weak run does not save the run beyond it.
    steps[-3] = (w + 0.1) * typical
    assert bone_free_ends(steps, p)[-6:].all()
    # A weak frame next to the end frame, itself like the bone, is not cut; nor are
    # two weak frames beyond a strong one; a weak end frame alone is.
    one = np.full(30, typical)
    one[1] = (w - 0.15) * typical
    assert not bone_free_ends(one, p).any()
    one[2] = (w - 0.15) * typical
    assert not bone_free_ends(one, p).any()
    one[0] = (w - 0.15) * typical
    assert bone_free_ends(one, p)[:3].all()
    # No shadow on the track at all: nothing to judge against.
    assert not bone_free_ends(np.full(30, 0.1), p).any()
    # Never more than max_cut_share of the track.
    half = np.full(10, typical)
    half[:6] = 0.0
    assert bone_free_ends(half, dataclasses.replace(p, max_cut_share=0.5)).sum() <= 5


def test_an_end_no_weaker_than_the_bone_inside_the_track_is_kept():
    """The bar is the recording's own: two end frames a little under ``min_ratio`` are
    cut on a track whose other frames all step alike, not on one where a frame inside
    reads weaker still (the bone's steps stray that far here: S clavicle grey s113,
    by the band's mean, ``min_ratio`` 0.5, frames 0-1 at 0.43 and 0.41 of typical, frame
    34 at 0.29, all on the bone; here relative to ``min_ratio``). A run past the bone's
    end, weak throughout, is cut on either track."""
    p = EndsParams()
    w = p.min_ratio
    typical = -0.7
    steps = np.full(40, typical)
    steps[:2] = (w - 0.08) * typical
    assert bone_free_ends(steps, p)[:2].all()
    steps[34] = (w - 0.21) * typical
    assert not bone_free_ends(steps, p).any()
    steps[:5] = (w - 0.2) * typical  # five frames past the end: 5 x 0.2 against 0.21
    assert bone_free_ends(steps, p)[:5].all() and bone_free_ends(steps, p).sum() == 5


def test_ends_params_are_validated():
    with pytest.raises(BoneUSReconError, match="EndsParams.band_mm"):
        EndsParams(band_mm=0)
    with pytest.raises(BoneUSReconError, match="EndsParams.max_cut_share"):
        EndsParams(max_cut_share=1.5)


def test_cli_simulate_bone_free(tmp_path, capsys):
    import json

    from BoneUSRecon.cli import main

    out = tmp_path / "ends"
    rc = main(
        ["simulate", "radius", str(out), "--frames", "8", "--width", "64", "--height", "96",
         "--spacing", "0.4", "--bone-free", "2,3", "--json"]
    )  # fmt: skip
    assert rc == 0
    capsys.readouterr()
    saved = json.loads((out / "simulation.json").read_text())
    assert saved["parameters"]["bone_free_frames"] == [2, 3]
    assert saved["frames_with_visible_bone"] == 3


def test_bone_free_ends_with_both_readings():
    """A frame is as weak as both readings find it; a reading not taken (``trough_mm``
    0: NaN throughout) leaves the other alone; one that finds no shadow on the track
    leaves nothing to judge against."""
    p = EndsParams()
    mean = np.full(20, -0.6)
    trough = np.full(20, -2.0)
    mean[-4:] = 0.1 * -0.6  # weak by the band's mean ...
    both = np.column_stack([mean, trough])
    assert bone_free_ends(mean, p)[-4:].all()
    assert not bone_free_ends(both, p).any()  # ... not by its darkest layer
    both[-4:, 1] = 0.2 * -2.0  # weak by both: cut
    assert bone_free_ends(both, p)[-4:].all() and bone_free_ends(both, p).sum() == 4
    unread = np.column_stack([mean, np.full(20, np.nan)])
    assert (bone_free_ends(unread, p) == bone_free_ends(mean, p)).all()
    flat = np.column_stack([mean, np.full(20, 0.1)])
    assert not bone_free_ends(flat, p).any()

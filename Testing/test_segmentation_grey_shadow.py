"""Bone under a grey shadow with reverberation bands and a far cortex (issue 10, seg2).

Each rule of ``candidates`` that keeps the track on the near cortex has a test with
ground truth: the reverberation series (equally spaced, fading copies over dark troughs
under the reflector), the first-reflector rule (a line in the shadow of a shallower
one is no first interface), and the controls that must not fire (parallel fasciae with
tissue between them; a fascia with tissue beneath over the bone; a dark muscle lying on
the bone).
"""

from __future__ import annotations

import numpy as np
import pytest

from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.segmentation.candidates import frame_candidates
from BoneUSRecon.Logic.segmentation.params import ShadowPathParams
from BoneUSRecon.Logic.simulation.scoring import score_simulation

S = 0.1  # mm per pixel of the synthetic frames


def _speckle(h: int, w: int, seed: int) -> np.ndarray:
    return 60.0 * np.random.default_rng(seed).rayleigh(1.0, (h, w))


def _line(y: np.ndarray, depth: np.ndarray, amp: float, sigma: float = 0.12) -> np.ndarray:
    return amp * np.exp(-0.5 * ((y - depth[None, :]) / sigma) ** 2)


def banded_bone_frame(
    seed: int, *, depth_mm: float = 6.0, band_mm: float = 2.2, far_mm: float = 9.0
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """A gently curved bone echo over a grey shadow (~0.5 of the tissue) holding four
    fading reverberation bands every ``band_mm`` and the far cortex ``far_mm`` deeper
    (brighter than the deepest bands, dimmer than the echo).

    Returns the frame (uint8), the true echo depth (mm) per column and the mask of the
    bone's columns.
    """
    h, w = 260, 200
    x = np.arange(w) * S
    y = (np.arange(h) * S)[:, None]
    on = np.abs(x - 10.0) < 7.0
    surf = depth_mm + 0.02 * (x - 10.0) ** 2
    img = _speckle(h, w, seed)
    d = y - surf[None, :]
    shadow = on[None, :] & (d > 0.3)
    img = np.where(shadow, 0.35 * img, img)
    img += np.where(on[None, :], _line(y, surf, 190.0), 0.0)
    for m in range(1, 5):
        img += np.where(shadow, _line(y, surf + m * band_mm, 120.0 * 0.8 ** (m - 1), 0.2), 0.0)
    img += np.where(shadow, _line(y, surf + far_mm, 110.0, 0.15), 0.0)
    return np.clip(img, 0, 255).astype(np.uint8), surf, on


def _depth(c) -> float:
    return float(np.median(c.points_px[:, 1])) * S


def _value(c) -> float:
    """A candidate's value to the track (its strength, less if no first interface)."""
    return c.strength * (0.1 if c.echo_beneath else 1.0)


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_reverberation_bands_and_far_cortex_lose_to_the_near_cortex(seed):
    img, surf, on = banded_bone_frame(seed)
    fc = frame_candidates(img, (S, S))
    best = max(fc.usable, key=_value)
    i = np.clip(np.rint(best.points_px[:, 0]).astype(int), 0, img.shape[1] - 1)
    err = np.abs(best.points_px[:, 1] * S - surf[i])
    assert np.median(err) < 0.15
    for c in fc.candidates:
        dd = _depth(c) - float(np.median(surf[on]))
        if dd > 1.0:
            # Under the near cortex: a copy (never chosen) or no first interface.
            assert c.reverberation or c.echo_beneath, (round(dd, 2), c.strength)


@pytest.mark.parametrize("ratio", [0.7, 0.55])
def test_a_bone_under_a_dark_muscle_is_a_first_interface(ratio):
    """A hypoechoic muscle lying on the bone (``ratio`` of the tissue's grey, tissue of
    the usual level beside it and over it) is no shadow: no candidate casts it, and the
    bone under it (a bright line over a grey shadow) is the first interface. A rule
    that judged a shadow from the region over a line alone, against the frame's
    typical tissue ("in a shadow whatever cast it", session 50), flagged such a bone:
    with grey shadows no level tells a dark muscle from a shadow."""
    h, w = 260, 400
    x = np.arange(w) * S
    y = (np.arange(h) * S)[:, None]
    on = np.abs(x - 20.0) < 5.0  # the bone, tissue beside it
    surf = 14.0 + 0.03 * (x - 20.0) ** 2
    img = _speckle(h, w, 5)
    over = surf[None, :] - y  # mm over the bone
    muscle = (np.abs(x - 20.0) < 7.0)[None, :] & (over > 1.0) & (over < 9.0)
    img = np.where(muscle, ratio * img, img)
    img = np.where(on[None, :] & (over < -0.3), 0.45 * img, img)  # the bone's grey shadow
    img += np.where(on[None, :], _line(y, surf, 150.0), 0.0)
    fc = frame_candidates(np.clip(img, 0, 255).astype(np.uint8), (S, S))
    bone = [c for c in fc.usable if abs(_depth(c) - 14.2) < 0.5]
    assert bone and not any(c.echo_beneath for c in bone)
    best = max(fc.usable, key=_value)
    assert abs(_depth(best) - 14.2) < 0.5, (_depth(best), best.strength)


def test_parallel_fasciae_with_tissue_between_are_no_reverberation_series():
    """Three equally spaced, fading bright layers with tissue (not shadow) between them
    over a bone: none is a copy, and the bone under them is not in a shadow."""
    h, w = 260, 200
    y = (np.arange(h) * S)[:, None]
    bone = np.full(w, 14.0)
    img = _speckle(h, w, 7)
    img = np.where(y > bone[None, :] + 0.3, 0.15 * img, img)
    img += _line(y, bone, 200.0)
    for m, amp in enumerate((170.0, 140.0, 110.0)):
        img += _line(y, np.full(w, 4.0 + 2.5 * m), amp)
    fc = frame_candidates(np.clip(img, 0, 255).astype(np.uint8), (S, S))
    assert not any(c.reverberation for c in fc.candidates)
    best = max(fc.usable, key=_value)
    assert abs(_depth(best) - 14.0) < 0.2
    assert not best.echo_beneath


@pytest.mark.parametrize("seed", [1, 7])
def test_grey_shadow_sweep_keeps_the_near_cortex(sim_factory, seed):
    """The simulated grey shadow (0.4 of the echo, 0.65 of the tissue beside, four
    reverberation bands and the far cortex) alone on a small tibia sweep: the track
    stays on the near cortex (before: recall 0.00, 97 % of frames on a band or the far
    cortex 7 mm deeper; measured now 0.95-0.97, none wrong, median 0.03 mm)."""
    sim = sim_factory(bone="tibia", seed=seed, realism="hard", hard_conditions=("grey_shadow",))
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] >= 0.9
    assert s["wrong_share"] <= 0.02
    assert s["median_mm"] <= 0.3


def test_a_bone_wider_than_a_bright_fascia_over_dark_muscle_is_not_in_its_shadow():
    """A fascia brighter than the bone, over hypoechoic muscle (darker than the tissue
    beside it) that ends above the bone: the bone reaches beyond the fascia's columns,
    so it lies in no shadow of the fascia (a shadow is as wide as its reflector)."""
    h, w = 200, 200
    x = np.arange(w) * S
    y = (np.arange(h) * S)[:, None]
    img = _speckle(h, w, 11)
    under = (np.abs(x - 10.0) < 4.0)[None, :]
    img = np.where(under & (y > 4.3) & (y < 9.5), 0.55 * img, img)  # muscle belly
    img += np.where(under, _line(y, np.full(w, 4.0), 230.0), 0.0)  # the fascia
    bone = (np.abs(x - 10.0) < 8.5)[None, :]
    img = np.where(bone & (y > 10.3), 0.2 * img, img)
    img += np.where(bone, _line(y, np.full(w, 10.0), 170.0), 0.0)
    fc = frame_candidates(np.clip(img, 0, 255).astype(np.uint8), (S, S))
    at_bone = [c for c in fc.usable if abs(_depth(c) - 10.0) < 0.3]
    assert at_bone and not any(c.echo_beneath for c in at_bone)
    assert abs(_depth(max(fc.usable, key=_value)) - 10.0) < 0.3


def test_small_bone_far_cortex_under_its_bands_is_not_the_track(sim_factory):
    """A small bone (radius) under the grey shadow: the far cortex lies where the last
    reverberation band falls and is brighter than the bands, with the darkest shadow
    beneath it; its shape is not the near cortex's. The series is seen from it
    loosely, confirmed from the near cortex's own profile, and the far cortex is no
    longer the track (before: recall 0.00, 100 % of frames on it; measured now
    0.45-0.53 recall, 5 % wrong, on seeds 1, 5, 7, 13)."""
    sim = sim_factory(bone="radius", seed=1, realism="hard", hard_conditions=("grey_shadow",))
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["wrong_share"] <= 0.15
    assert s["recall"] >= 0.4
    assert s["median_mm"] <= 0.3


def test_small_bone_series_top_and_no_step_onto_the_far_cortex(sim_factory):
    """The clavicle under the grey shadow (seed 5, the bench's sweep: 40 frames 4.5 mm
    apart). A series' top with no piece above the null level keeps its most echoing
    piece, not its shortest; and the track does not step 7 mm down onto the far cortex
    over a 4-frame skip link (18 mm), which the out-of-plane tolerance (1 + 0.4 x 18 mm)
    alone allowed (``max_step_mm`` + ``step_per_mm`` x 18 = 5.8 mm; without it: recall 0.47, 30 % of frames on the far cortex;
    with it 0.62, none; before both 0.57, none). Since seg5's series tops (traced
    along the echo, read along the far cortex's mirror image) the near cortex carries
    the track here with or without the step rule (0.88, none): the ablation no longer
    fails, so only the outcome is asserted, tighter."""
    sim = sim_factory(
        bone="clavicle", seed=5, n_frames=40, realism="hard", hard_conditions=("grey_shadow",)
    )
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["wrong_share"] <= 0.02
    assert s["recall"] >= 0.85
    assert s["median_mm"] <= 0.3


def _offered(sim, params: ShadowPathParams | None = None) -> int:
    """Frames with a usable candidate lying on the true contour (median < 1 mm), not
    marked as no first interface: what the track can choose from (``params``: the
    segmenter's, default if None)."""
    from BoneUSRecon.Logic.simulation.scoring import polyline_distance
    from BoneUSRecon.Logic.sweep import pixel_spacing

    sw = sim.sweep
    sp = pixel_spacing(sw.image_to_reference)
    n = 0
    for k in range(sw.n_frames):
        tc = sim.true_contours_px[k]
        if not len(tc):
            continue
        fc = frame_candidates(np.asarray(sw.frames[k]), tuple(sp[k]), params or ShadowPathParams())
        for c in fc.usable:
            d = polyline_distance(c.points_px * sp[k], tc * sp[k])
            if c.strength > 0 and not c.echo_beneath and np.median(d) < 1.0:
                n += 1
                break
    return n


def test_far_cortex_read_along_its_mirror_image_offers_the_near_cortex(sim_factory, monkeypatch):
    """The ulna under the grey shadow (seed 5): in many frames the passes find only the
    far cortex, a bowl, while the near cortex and its copies are domes. Read along the
    far cortex's own shape the copies blur; along its mirror image they are parallel
    lines and the series' top (the near cortex) is found: offered in 38 frames, 32
    without the mirror."""
    from BoneUSRecon.Logic.segmentation import candidates

    sim = sim_factory(bone="ulna", seed=5, realism="hard", hard_conditions=("grey_shadow",))
    assert _offered(sim) >= 36
    monkeypatch.setattr(candidates, "_curves_down", lambda rows: False)  # the rule off
    assert _offered(sim) <= 33


def test_series_top_traced_along_its_echo(sim_factory):
    """The clavicle under the grey shadow (seed 5): the series' top, built from another
    line's shape moved up and traced as a path along the echo with shadow under it
    (``candidates._trace_band``), lies on the bone in 37 frames (36 before session 29's
    series rules). Per-column maxima in the band, which hopped onto a layer over the
    bone or the first copy at the flanks, gave 33 then; with those rules they give 39
    here and 334 against 324 frames over nine grey sweeps (recall 0.988 against 0.987
    on fifteen), so the trace is kept as the principled form, not for a measured gain
    (``Testing/benchmarks/README.md``, session 29)."""
    sim = sim_factory(bone="clavicle", seed=5, realism="hard", hard_conditions=("grey_shadow",))
    assert _offered(sim) >= 36


def test_a_far_cortex_reaching_beyond_the_near_cortex_does_not_flag_it(sim_factory):
    """The clavicle under the grey shadow (seed 5), frames 21 and 22, with the z-scores'
    nulls over the tissue (``null_dark_fraction`` 0.25, ``shadow_z_zero`` -0.8; an
    option, off by default): the far cortex's pass runs on past the bone along the
    tissue beside it (columns 26-83 and 56-124 under a series' top over 53-93 and
    30-96), so it lies under the top over 31 of its 58 and 41 of its 69 columns. In
    the top's shadow over their common columns, it is no sign that sound went through
    the top (``_mark_echo_beneath``); it flagged the near cortex as no first interface
    in both frames, and the near cortex was offered in 30 frames of the sweep, 34 with
    the rule. With the default nulls the far cortex stays under the top: the rule
    changes nothing there."""
    from BoneUSRecon.Logic.simulation.scoring import polyline_distance
    from BoneUSRecon.Logic.sweep import pixel_spacing

    tissue_null = ShadowPathParams(null_dark_fraction=0.25, shadow_z_zero=-0.8)
    sim = sim_factory(bone="clavicle", seed=5, realism="hard", hard_conditions=("grey_shadow",))
    sw = sim.sweep
    sp = pixel_spacing(sw.image_to_reference)
    for k in (21, 22):
        tc = sim.true_contours_px[k]
        fc = frame_candidates(np.asarray(sw.frames[k]), tuple(sp[k]), tissue_null)
        on = [
            c
            for c in fc.usable
            if np.median(polyline_distance(c.points_px * sp[k], tc * sp[k])) < 0.5
        ]
        assert on and not any(c.echo_beneath for c in on), k
    assert _offered(sim, tissue_null) >= 32  # 34 before session 29's series rules


@pytest.mark.parametrize(
    ("bone", "seed", "least"),
    [
        ("ulna", 5, 0.9),
        ("radius", 7, 0.95),
        ("clavicle", 5, 0.9),
        ("ulna", 13, 0.95),
        ("clavicle", 13, 0.9),
    ],
)
def test_small_bones_under_the_grey_shadow_keep_the_near_cortex(sim_factory, bone, seed, least):
    """Frame recall on the small bones under the grey shadow alone (issue 10, seg5):
    ulna seed 5 0.60 -> 0.95, radius seed 7 0.75 -> 0.93, clavicle seed 5 0.62 -> 0.88,
    ulna seed 13 0.65 -> 0.97, clavicle seed 13 0.60 / 5 % wrong -> 0.88 / none (a fascia
    over the shallow bone, equally spaced with the bone and its copies, was taken as the
    series' top until its first trough had to be shadow), kept points on the bone. With
    the track-guided recovery (session 20): 0.925, 1.00, 0.95, 0.975, 0.925 (clavicle
    seeds 5 and 13 gain 0.05 each; the others unchanged). With the rim's edge measure
    (session 24): clavicle seed 5 0.925."""
    sim = sim_factory(bone=bone, seed=seed, realism="hard", hard_conditions=("grey_shadow",))
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] >= least
    assert s["wrong_share"] <= 0.02
    assert s["median_mm"] <= 0.1


def _dome_covered(sim, frames) -> float:
    """Mean share of the true contour's columns spanned by the widest usable candidate
    lying on it (points within 1 mm of the true contour, median < 1 mm)."""
    from BoneUSRecon.Logic.simulation.scoring import polyline_distance
    from BoneUSRecon.Logic.sweep import pixel_spacing

    sw = sim.sweep
    sp = pixel_spacing(sw.image_to_reference)
    out = []
    for k in frames:
        tc = sim.true_contours_px[k]
        best = 0.0
        for c in frame_candidates(np.asarray(sw.frames[k]), tuple(sp[k])).usable:
            d = polyline_distance(c.points_px * sp[k], tc * sp[k])
            if c.strength > 0 and not c.echo_beneath and np.median(d) < 1.0:
                x = c.points_px[d < 1.0, 0]
                best = max(best, float(np.mean((tc[:, 0] >= x.min()) & (tc[:, 0] <= x.max()))))
        out.append(best)
    return float(np.mean(out))


def test_pieces_over_one_shadow_are_one_near_cortex(sim_factory, monkeypatch):
    """A faint near cortex whose pass contour steps ~1 mm at its flank is split there
    by the convex cut, and only the piece with the larger sum was offered. Pieces over
    one shadow (the far cortex lying under them) are one reflector and are joined.

    The example was the hard tibia seed 5 (frame 24: 98 % of the true contour's
    columns with the rule, 57 % without). Since pixel counts ignore the pixel size's
    last bit (``features.ceil_px``) and layers off the shoulder are cut in more cases
    (session 28), that frame's own pass finds the dome whole (96 % without the rule):
    the premise was lost there. The hard tibia seed 1
    (0.3 mm, 160 x 128) still needs the rule: in frame 24 the near cortex, a faint
    dome over the far cortex 20 mm deeper, is offered whole with it (columns 17-124,
    100 % of the true contour's span) and as a piece without it (columns 41-67, 33 %);
    over frames 20-39 the widest candidate on the bone spans 80 % with the rule, 70 %
    without (frames 20, 21, 24, 30 gain 0.4-0.7; frame 25 loses 0.19) with the nulls
    over tissue (``null_dark_fraction`` 0.25); with the default nulls 76 % and 68 %,
    frame 24 the same. Since the rim searches +-5 mm about its circle (session 53) it
    recovers part of the flank either way: over frames 20-39 0.84 with the rule, 0.77
    without; frame 24 1.00 and 0.33.
    """
    from BoneUSRecon.Logic.segmentation import candidates

    sim = sim_factory(bone="tibia", seed=1, realism="hard")
    frames = range(20, 40)
    with_all = _dome_covered(sim, frames)
    assert with_all >= 0.75
    with_rule = _dome_covered(sim, [24])
    assert with_rule >= 0.9
    monkeypatch.setattr(candidates, "_shadowed_span", lambda c, cands: None)  # the rule off
    assert _dome_covered(sim, [24]) <= with_rule - 0.5
    assert _dome_covered(sim, frames) <= with_all - 0.05


def test_shadow_centre_is_the_tissue_s_when_shadow_fills_most_of_the_frame() -> None:
    """The shadow z-score's centre: the frame's median while shadow is a minority; the
    lower tail's centre, less ``tolerance`` spreads, once shadow fills most of it (the
    median then lies in the shadow and a bone's shadow scores as ordinary)."""
    from BoneUSRecon.Logic.segmentation.evidence import _robust_scale, _shadow_scale

    rng = np.random.default_rng(0)
    tissue = rng.normal(0.1, 0.1, 40_000)
    valid = np.ones(100_000, bool)
    # 60 % shadow (log-ratio 0.6: 0.55 of the tissue beside it).
    mixed = np.concatenate([tissue, rng.normal(0.6, 0.15, 60_000)])
    med, spread = _robust_scale(mixed, valid)
    centre, spread2 = _shadow_scale(mixed, valid, 0.25)
    assert spread2 == spread and med > 0.4  # the median is in the shadow
    # Towards the tissue's 0.1 (measured 0.33: the tail holds some shadow, and the
    # tolerance is kept), from a median of 0.46.
    assert centre < 0.35
    # A bone's shadow of 0.6 then scores 0.74 spreads (the gate at 0.87), against 0.40
    # from the median (0.70).
    assert (0.6 - centre) / spread > 0.7 and (0.6 - med) / spread < 0.45
    # 15 % shadow: the median is the tissue's and is kept as it is.
    clean = np.concatenate([tissue, rng.normal(0.6, 0.15, 7_000)])
    ok = np.ones(clean.size, bool)
    assert _shadow_scale(clean, ok, 0.25) == _robust_scale(clean, ok)


def test_a_shallow_bone_whose_shadow_fills_the_frame_is_kept(sim_factory) -> None:
    """Hard radius, seed 71 (160 x 128 at 0.3 mm): the bone rises from 24 to 5 mm under
    the skin and its shadow fills most of the last frames. With the frame's median as
    the shadow z-score's centre, its bone scored 0.4 spreads of shadow at 6 mm against
    2.4 at 24 mm (the same log-ratio, 0.5-0.65), no candidate lay on it in frames 32 and
    36-38, and recall was 0.85; centred on the tissue, 0.975 (frame 10 missed)."""
    sim = sim_factory(bone="radius", seed=71, realism="hard")
    s = score_simulation(segment_sweep(sim.sweep), sim)
    assert s.recall >= 0.95 and s.wrong_share == 0.0
    sy = float(sim.sweep.spacing_mm[1])
    shallow = [
        f
        for f in s.frames
        if f.shows_bone and sim.true_contours_px[f.frame][:, 1].min() * sy < 10.0
    ]
    assert len(shallow) >= 8 and all(f.on_bone for f in shallow)


@pytest.mark.parametrize(("bone", "least"), [("tibia", 0.9), ("radius", 0.95)])
def test_strong_reverberation_keeps_the_near_cortex(sim_factory, bone, least):
    """Reverberation 0.45 (the hard preset's 0.35 moved up, ``bench_levels.py``), seed
    101: toward the sweep's shallow end the near cortex has five bright copies under
    it and the passes find only the far cortex, 19-26 mm deep. Read along its mirror
    image up to the near field (not only ``far_shadow_mm`` over it, where two copies
    showed) the series is found and its top is the near cortex; a line under the
    series is no copy, so its bright echo does not veto the top (``copy_echo_ratio``).
    Recall tibia 0.65 -> 0.925, radius 0.675 -> 0.975; nothing kept off the bone. On
    the radius a layer 2.8 mm over the bone passed for the top with two speckle-level
    "copies" over a long spacing, the bone's own echo between it and the first: a copy
    is the brightest return since its reflector (0.875 without that rule)."""
    from dataclasses import replace

    from BoneUSRecon.Logic.simulation import HardParams

    sim = sim_factory(
        bone=bone, seed=101, realism="hard", hard=replace(HardParams(), reverb_amplitude=0.45)
    )
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] >= least and s["wrong_share"] == 0.0, (s["recall"], s["wrong_share"])


def test_a_shallow_near_cortex_over_its_copies_is_kept(sim_factory):
    """The clavicle under the grey shadow, seed 109: in the last frames the near cortex
    lies 3.9 mm deep over bright copies and the far cortex was the frames' only
    candidate (frames 37-39 rejected as jumps, recall 0.925). The series' chain from
    the top ran on past its third copy onto the far cortex (brighter than the copy over
    it), which failed the whole chain: the longest valid run from the top is taken. Its
    1.5-3 mm over the top is skin and gel (the near field), not the tissue over a
    reflector: the rows in the near field are not judged. Recall 1.00."""
    sim = sim_factory(bone="clavicle", seed=109, realism="hard", hard_conditions=("grey_shadow",))
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] == 1.0 and s["wrong_share"] == 0.0, (s["recall"], s["wrong_share"])


@pytest.mark.parametrize("seed", [5, 7])
def test_series_top_made_over_a_copy_reaches_past_its_columns(sim_factory, monkeypatch, seed):
    """The tibia under the grey shadow (20 frames): the passes take the first copy under
    the dome (its shadow beneath is darker than the reflector's), which spans only the
    middle of the bone, so the series' top made over its columns stopped short of the
    flanks (``candidates._extend_top`` off: coverage of the true contour 0.906 and
    0.854). Followed on along its own echo with the series' trough under it, it
    reaches them (0.999 and 0.914) without leaving the bone (p95 of the kept points
    0.10 and 0.09 mm). Seed 7 was 0.937 until session 50: in its frame 10 a piece over
    the bone's left half (x 58-88 of 55-126) is the strongest candidate, and the rule
    that judged a shadow from the grey over a line alone flagged that piece, on the
    bone, as lying in one; without it the track keeps the piece there. Since the rim
    searches +-5 mm about its circle (session 53) it takes part of the flanks either
    way: without the extension 0.911 and 0.854, with it 0.999 and 0.917."""
    from BoneUSRecon.Logic.segmentation import candidates

    sim = sim_factory(
        bone="tibia", seed=seed, n_frames=20, realism="hard", hard_conditions=("grey_shadow",)
    )
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] >= 0.95 and s["wrong_share"] == 0
    assert s["coverage"] >= 0.9
    assert s["p95_mm"] <= 0.2
    monkeypatch.setattr(candidates, "_extend_top", lambda ev, lr, cols, rows, *a: (cols, rows))
    without = score_simulation(segment_sweep(sim.sweep), sim).summary()["coverage"]
    assert without <= s["coverage"] - 0.05, (without, s["coverage"])


def test_a_top_traced_onto_a_line_found_already_is_that_line(sim_factory):
    """The tibia with a vessel (seed 5), frame 14: read from the vessel's ring-down, a
    series' top made over the copy's columns ran on the bone over its left half and
    1-4 mm over its right half; followed on along its echo it lay over the whole bone
    and put it in its shadow (echo_beneath), and the track took the top: coverage 0.62.
    Traced onto the bone over half its columns, the top is the bone itself."""
    from BoneUSRecon.Logic.simulation.scoring import polyline_distance

    sim = sim_factory(bone="tibia", seed=5, realism="hard", hard_conditions=("vessel",))
    sw = sim.sweep
    tc = sim.true_contours_px[14]
    fc = frame_candidates(np.asarray(sw.frames[14]), tuple(sw.spacing_mm))
    s = np.asarray(sw.spacing_mm, float)
    on = [c for c in fc.usable if np.median(polyline_distance(c.points_px * s, tc * s)) < 0.3]
    assert on and not any(c.echo_beneath for c in on)
    frame = score_simulation(segment_sweep(sw), sim).frames[14]
    assert frame.on_bone and frame.coverage >= 0.9


def test_series_top_read_at_its_echo_crest_a_row_under_the_traced_row():
    """The strict series (``_series``) from a top whose traced row lies a row over its
    echo's crest (0.86, the crest 0.90): that crest is the top's own echo, not a line
    between it and its first copy brighter than the copy. A line two rows or more
    under the top, as bright, still is one (tissue between: no series)."""
    from BoneUSRecon.Logic.segmentation.candidates import _profile_peaks, _series

    reach = 40

    def profile(extra: int | None) -> np.ndarray:
        v = np.full(reach + 40, 0.0)
        v[reach - 25 : reach - 1] = 0.02 * np.cos(np.arange(24))  # tissue over the top
        v[reach], v[reach + 1] = 0.86, 0.90
        for k, (q, amp) in enumerate(((9, 0.52), (17, 0.50), (26, 0.51), (34, 0.44))):
            lo = 2 if k == 0 else 1
            v[reach + q - (8 - lo) : reach + q] = -1.5 - 0.5 * k  # shadow between copies
            v[reach + q] = amp
        if extra is not None:
            v[reach + extra] = 0.90
        return v

    dark, min_px = float(np.log(0.7)), 3
    members = _series(_profile_peaks(profile(None), reach), reach, min_px, dark, 0.12, strict=True)
    assert members[:4] == [0, 9, 17, 26]
    # Control: a line as bright as the crest three rows under the top.
    spoilt = _series(_profile_peaks(profile(3), reach), reach, min_px, dark, 0.12, strict=True)
    assert spoilt == [0]


def test_grey_humerus_series_top_under_a_darker_muscle_layer(sim_factory):
    """The humerus under the grey shadow (seed 709), frames 32 and 33: the bone's echo
    is weak (its own evidence 4.1 against 18-26 for the copies 7-9 mm under it), so
    only the series makes it the strongest candidate. In both frames the traced top lay
    a row over its echo's crest (0.86 and 0.93; the crest 0.90 and 1.07), read as a line
    between it and its first copy (0.52, 0.59); in frame 32 the tissue 1.5-3 mm over the
    bone is also a darker layer (0.78 of the frame's level), read as a shadow over a far
    cortex, although the troughs between the copies are 3 to 200 times darker. Before:
    the copies were no series, and the track took a fascia leaving the crest in frame 32
    (1.96 mm off) and lost frame 31."""
    from BoneUSRecon.Logic.simulation.scoring import polyline_distance

    sim = sim_factory(bone="humerus", seed=709, realism="hard", hard_conditions=("grey_shadow",))
    sp = tuple(float(v) for v in sim.sweep.spacing_mm)
    mm = np.asarray(sp)
    for k in (32, 33):
        fc = frame_candidates(np.asarray(sim.sweep.frames[k]), sp)
        best = max(fc.usable, key=_value)
        d = polyline_distance(best.points_px * mm, sim.true_contours_px[k] * mm)
        assert np.median(d) < 0.2, k
        top = float(np.median(best.points_px[:, 1])) * sp[1]
        deep = [c for c in fc.candidates if np.median(c.points_px[:, 1]) * sp[1] - top > 5.0]
        assert deep and all(c.reverberation or c.echo_beneath for c in deep), k
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] == 1.0
    assert s["wrong_share"] == 0.0


def test_a_layer_one_spacing_over_the_bone_is_not_the_series_top(sim_factory):
    """The radius under the grey shadow (seed 701), frame 31: a faint layer
    lies 2.6 mm over the bone, one spacing of the reverberation series under it. Read
    along the far cortex's mirror image, the series' shallowest confirmed top was that
    layer (echo z 1.0), the bone its "first copy", so the layer inherited the stack's
    strength and the track took it (2.6 mm off; frame 32 likewise). A copy returns less
    than its reflector: where the next member down is a confirmed top too, with more
    echo, it is the reflector. Recall 0.95 -> 1.00."""
    from BoneUSRecon.Logic.simulation.scoring import polyline_distance

    sim = sim_factory(bone="radius", seed=701, realism="hard", hard_conditions=("grey_shadow",))
    sp = tuple(float(v) for v in sim.sweep.spacing_mm)
    mm = np.asarray(sp)
    fc = frame_candidates(np.asarray(sim.sweep.frames[31]), sp)
    best = max(fc.usable, key=_value)
    d = polyline_distance(best.points_px * mm, sim.true_contours_px[31] * mm)
    assert np.median(d) < 0.2  # measured 0.03 (2.58 before)
    s = score_simulation(segment_sweep(sim.sweep), sim).summary()
    assert s["recall"] == 1.0
    assert s["wrong_share"] == 0.0

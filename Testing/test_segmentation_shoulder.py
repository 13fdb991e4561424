"""The bone's top and shoulder: narrow excursions over the dome, a layer running off the shoulder.

``candidates._fill_excursions`` drops a hop of the path onto a grain or a short layer just
over the bone (it made a false apex that split the dome); ``candidates._shoulder_cut``
cuts a layer running off the bone's shoulder (gentler than ``kink_slope``, tissue under
it). Checked on drawn contours against their known shape (mm) and on small simulated
hard sweeps against the true surface (frame recall, flank coverage).
"""

from __future__ import annotations

import dataclasses
from types import SimpleNamespace

import numpy as np
import pytest
from conftest import CADAVER, small_simulation

from BoneUSRecon.Logic.evaluation import evaluate_surface
from BoneUSRecon.Logic.segmentation import SegmentationParams, segment_sweep
from BoneUSRecon.Logic.segmentation import candidates as cand_mod
from BoneUSRecon.Logic.segmentation.candidates import (
    BoneCandidate,
    _convex_pieces,
    _fill_excursions,
    _shoulder_cut,
    frame_candidates,
)
from BoneUSRecon.Logic.segmentation.params import (
    RecoveryParams,
    RimParams,
    SettleParams,
    ShadowPathParams,
)
from BoneUSRecon.Logic.simulation.scoring import score_simulation

SP = (0.15, 0.15)  # mm per pixel of the drawn contours
R = 8.0  # dome radius, mm
TOP = 10.0  # apex depth, mm


def _dome(x_mm: np.ndarray) -> np.ndarray:
    """Depth (mm) of a circular dome of radius R with its apex at x = 0, depth TOP."""
    return TOP + R - np.sqrt(R**2 - x_mm**2)


def _px(x_mm: np.ndarray, z_mm: np.ndarray) -> np.ndarray:
    return np.column_stack([x_mm / SP[0] + 100.0, z_mm / SP[1]])


def test_a_narrow_excursion_over_the_dome_is_dropped_and_the_dome_stays_whole() -> None:
    """A hop of 1.5 mm over 1.2 mm of the dome beside its apex: its points go, every
    point of the dome stays, and the convex cut then keeps the whole dome as one piece
    (with the hop, the hop is the apex and the dome is cut into pieces around it)."""
    x = np.arange(-6.0, 6.0 + 1e-9, SP[0])
    z = _dome(x)
    hop = (x >= -1.5) & (x <= -0.3)
    z_hop = np.where(hop, z - 1.5, z)
    pts = _px(x, z_hop)
    keep = _fill_excursions(pts, SP, ShadowPathParams())[0]
    assert not keep[hop].any()
    assert keep[~hop].mean() >= 0.97  # at most the hop's foot besides it
    assert np.abs(pts[keep, 1] * SP[1] - _dome(x[keep])).max() < 1e-9  # all on the dome
    pieces = _convex_pieces(pts[keep], SP, ShadowPathParams(), 5)
    assert pieces[0].mean() >= 0.95  # the piece around the apex: nearly all of it
    # Without dropping it, the piece around the apex is the hop itself (the failure).
    raw = _convex_pieces(pts, SP, ShadowPathParams(), 5)
    assert raw[0].sum() <= hop.sum() + 4


def test_a_grain_at_the_apex_lower_than_an_excursion_does_not_cut_the_dome() -> None:
    """Two columns 0.35 mm over the dome's apex (a speckle grain, under ``valley_mm``,
    so no excursion to drop): the dome's descent past them is measured over at least
    half of ``kink_mm``, and the convex cut keeps the whole 12 mm dome; a fascia leaving
    a 45-degree flank at its level is still cut off. (On the hard simulated tibia, seed
    113, frame 15, such a grain made the two steps down off it a "flank" and left 3 mm
    of a 20 mm top.)"""
    p = ShadowPathParams()
    x = np.arange(-6.0, 6.0 + 1e-9, SP[0])
    z = _dome(x)
    grain = np.abs(x) <= 0.5 * SP[0] + 1e-9
    grain |= np.roll(grain, 1)
    pts = _px(x, np.where(grain, z - 0.35, z))
    assert _fill_excursions(pts, SP, p)[0].all()  # too low for an excursion
    assert cand_mod.convex_part(pts, SP, p).all()
    # A flank of 45 degrees (3 mm of it) then a layer running on flat: cut at the turn.
    z_layer = TOP + np.clip(np.abs(x) - 1.0, 0.0, 3.0)
    keep = cand_mod.convex_part(_px(x, z_layer), SP, p)
    assert keep[np.abs(x) <= 3.5].all() and not keep[np.abs(x) >= 4.5].any()


@pytest.mark.parametrize("shape", ["crest", "dome with jitter", "sharp dome"])
def test_the_bone_own_top_is_no_excursion(shape: str) -> None:
    """A crest (5 mm flat top, 45-degree flanks), a dome with 0.05 mm of jitter and a
    tight dome of radius 3 mm keep every point."""
    rng = np.random.default_rng(3)
    x = np.arange(-6.0, 6.0 + 1e-9, SP[0])
    if shape == "crest":
        z = TOP + np.maximum(np.abs(x) - 2.5, 0.0)
    elif shape == "dome with jitter":
        z = _dome(x) + rng.normal(0.0, 0.05, x.size)
    else:
        x = np.arange(-2.8, 2.8 + 1e-9, SP[0])
        z = TOP + 3.0 - np.sqrt(9.0 - x**2)
    assert _fill_excursions(_px(x, z), SP, ShadowPathParams())[0].all()


def _dome_and_layer(
    layer_mm: float, under_layer: float, under_dome: float = 0.5
) -> tuple[np.ndarray, np.ndarray, int]:
    """A dome from x = -6 to its shoulder at x = 2.5 (descending 0.33 there, gentler than
    kink_slope), then a layer running on outward at a 0.05 slope for ``layer_mm``.

    Returns the points, the underside step per point (``under_dome`` under the dome, 0.5:
    shadow; ``under_layer`` under the layer) and the index of the last dome point.
    """
    rng = np.random.default_rng(5)
    xd = np.arange(-6.0, 2.5 + 1e-9, SP[0])
    xl = np.arange(2.5 + SP[0], 2.5 + layer_mm + 1e-9, SP[0])
    z = np.r_[_dome(xd), _dome(2.5) + 0.05 * (xl - 2.5)]
    step = np.r_[np.full(xd.size, under_dome), np.full(xl.size, under_layer)]
    step = step + rng.normal(0.0, 0.1, step.size)
    return _px(np.r_[xd, xl], z), step, xd.size - 1


def test_a_layer_running_off_the_shoulder_is_cut_at_the_shoulder() -> None:
    """Tissue (step 0) under a 10 mm layer running off the dome's shoulder: the layer is
    cut, the dome kept to within 0.5 mm of the shoulder, every point kept on the dome."""
    pts, step, last = _dome_and_layer(10.0, 0.0)
    keep = _shoulder_cut(pts, SP, step, ShadowPathParams())
    assert not keep[last + 1 :].any()
    assert keep[: last + 1].sum() >= last + 1 - round(0.5 / SP[0])
    x = (pts[keep, 0] - 100.0) * SP[0]
    assert np.abs(pts[keep, 1] * SP[1] - _dome(x)).max() < 1e-9
    # The convex cut alone keeps the layer (its turn is gentler than kink_slope).
    assert _convex_pieces(pts, SP, ShadowPathParams(), 5)[0][last + 1 :].all()


@pytest.mark.parametrize(
    ("layer_mm", "under", "under_dome", "why"),
    [
        (10.0, 0.5, 0.5, "shadow under it: the bone's own plateau"),
        (
            6.0,
            0.0,
            0.15,
            "shorter than shoulder_min_mm over a faint shadow (a bone that passes sound, "
            "the L14 forearm): may be the bone's relief",
        ),
    ],
)
def test_a_gentle_stretch_of_bone_is_not_cut(
    layer_mm: float, under: float, under_dome: float, why: str
) -> None:
    pts, step, _ = _dome_and_layer(layer_mm, under, under_dome)
    assert _shoulder_cut(pts, SP, step, ShadowPathParams()).all(), why


def test_a_short_layer_off_a_shadowed_shoulder_is_cut() -> None:
    """6 mm of layer (under shoulder_min_mm) off a dome with a clear shadow under it
    (step 0.5, over shoulder_short_step) and tissue under the layer: the layer is cut at
    the shoulder, the dome kept. Without a clear shadow under the dome (above), or with
    the part kept narrower than shoulder_min_mm, it stays whole."""
    pts, step, last = _dome_and_layer(6.0, 0.0)
    keep = _shoulder_cut(pts, SP, step, ShadowPathParams())
    assert not keep[last + 1 :].any()
    assert keep[: last + 1].sum() >= last + 1 - round(0.5 / SP[0])
    # The same layer off only 5 mm of dome (x from -2.5): too little kept to cut.
    x0 = round(3.5 / SP[0])
    assert _shoulder_cut(pts[x0:], SP, step[x0:], ShadowPathParams()).all()
    # The rule's own floor restores the old behaviour.
    old = ShadowPathParams(shoulder_short_mm=ShadowPathParams().shoulder_min_mm)
    assert _shoulder_cut(pts, SP, step, old).all()


def test_a_short_descending_part_beyond_a_turn_is_not_cut() -> None:
    """A wall flattening to a part that still descends (0.3 mm per mm, 17 degrees, over
    5 mm) is no level layer: the short cut leaves it, however clear the shadow inside
    (hard tibia, seed 5 with its first quarter bone-free, frame 24: the left flank near a
    vessel, descending 23 degrees, was cut as a short layer and the track then kept the
    fascia alone in frames 25, 28, 29). The same part running level is cut."""
    rng = np.random.default_rng(3)
    xd = np.arange(-6.0, 5.0 + 1e-9, SP[0])
    xl = np.arange(5.0 + SP[0], 10.0 + 1e-9, SP[0])
    step = np.r_[np.full(xd.size, 0.5), np.full(xl.size, 0.0)] + rng.normal(
        0, 0.1, xd.size + xl.size
    )
    for slope, cut in ((0.3, False), (0.02, True)):
        z = np.r_[_dome(xd), _dome(5.0) + slope * (xl - 5.0)]
        keep = _shoulder_cut(_px(np.r_[xd, xl], z), SP, step, ShadowPathParams())
        assert (not keep[xd.size + 1 :].any()) if cut else keep.all(), (slope, keep.sum())


def test_a_plain_dome_is_not_cut() -> None:
    x = np.arange(-6.0, 6.0 + 1e-9, SP[0])
    step = np.full(x.size, 0.5)
    step[np.abs(x) > 4] = 0.05  # the shadow fading at the sides changes nothing
    assert _shoulder_cut(_px(x, _dome(x)), SP, step, ShadowPathParams()).all()


def test_shoulder_layer_cut_on_a_hard_sweep() -> None:
    """Radius, hard realism (a fascia running off the bone at its level): frames 36 and
    38 kept a contour leaving the bone's shoulder along the fascia (over 1 mm off on
    median); with the cut they lie on the bone (under 0.3 mm), the sweep's recall rises
    0.925 -> 0.975, and no frame is kept on a wrong structure.

    Seed 1. Humerus seed 5 (frame 21, 1.66 mm without the cut) was used until pixel
    counts became immune to the pixel size's last bit (``features.ceil_px``) and layers
    leaving the shoulder were cut in more cases (session 28): 0.13 mm without the cut
    since. Scanned (hard, seeds 0-39 humerus, 0-19 tibia and radius; a frame over 1 mm
    without the cut and under 0.3 mm with it): radius 1 (frames 36, 38), radius 0
    (24), humerus 18 (33), tibia 5 (27), tibia 18 (29)."""
    sim = small_simulation(bone="radius", seed=1, realism="hard")
    # The rule measured on its own: settled candidates (settle.py) and the flat ends
    # followed (rim.py) change the contours' ends.
    bare = ShadowPathParams(settle=SettleParams(enabled=False), rim=RimParams(enabled=False))
    with_cut = score_simulation(segment_sweep(sim.sweep, SegmentationParams(shadowpath=bare)), sim)
    off = SegmentationParams(shadowpath=dataclasses.replace(bare, shoulder_slope=100.0))
    without = score_simulation(segment_sweep(sim.sweep, off), sim)
    # Frame 36 without the cut: 2.3 mm until session 34, 0.54 since a grain at an apex
    # no longer makes a flank for convex_part (the layer then shorter); frame 38 4.1 mm.
    assert without.frames[38].median_mm > 1.0  # the layer kept with the bone
    for k in (36, 38):
        assert with_cut.frames[k].median_mm < 0.3
    s, s0 = with_cut.summary(), without.summary()
    assert s["recall"] >= 0.95 and s["recall"] > s0["recall"], (s["recall"], s0["recall"])
    assert s["wrong_share"] == 0.0
    assert s["median_mm"] <= 0.1


def test_excursions_dropped_on_a_hard_sweep(monkeypatch: pytest.MonkeyPatch) -> None:
    """Radius, hard realism: with the hops over the bone dropped the domes are offered
    whole, so the kept contours cover more of the true contour (flank coverage) and
    still lie on the bone.

    Seed 2 (coverage 0.715 -> 0.779, recall 0.975 -> 1.000 with the rule, every rule on;
    0.672 -> 0.782 before pieces over one shadow were joined). Seed 5 was
    used until the gap and ends rules were merged: with all rules on its gain fell to
    0.73 -> 0.76 and dropping the hops loses frame 37 (no usable candidate left, and the
    guided search between track frames 36 and 39 finds nothing; kept at 0.12 mm
    without the rule): recall 0.975 -> 0.950, reported to the lead. Since the shadow's
    z-score is centred on the tissue (``shadow_null_tolerance``): 0.808 -> 0.849 with
    the rule (more of the domes found whole without it)."""
    sim = small_simulation(bone="radius", seed=2, realism="hard")
    # The track's straying frames not searched again (RecoveryParams.recheck): that
    # step repairs some of the same frames without the rule (coverage without it 0.715
    # -> 0.736), and this test measures the rule.
    params = SegmentationParams(recovery=RecoveryParams(recheck=False))
    s = score_simulation(segment_sweep(sim.sweep, params), sim).summary()
    monkeypatch.setattr(
        cand_mod, "_fill_excursions", lambda pts, sp, p: (np.ones(len(pts), bool), pts)
    )
    s0 = score_simulation(segment_sweep(sim.sweep, params), sim).summary()
    assert s["coverage"] >= s0["coverage"] + 0.03, (s["coverage"], s0["coverage"])
    assert s["recall"] >= s0["recall"] and s["wrong_share"] == 0.0
    assert s["median_mm"] <= 0.1


def test_an_excursion_where_a_layer_meets_the_dome_does_not_let_the_layer_through() -> None:
    """Clean clavicle, seed 0, frame 13: a layer runs in from the left and hops onto a
    grain before meeting the dome. Dropping the hop must not hide the layer's turn from
    the convex cut (the cut is made on the contour with the hop filled in): every kept
    point within 0.35 mm of the bone (1.6 mm of layer kept when the hop left a gap)."""
    sim = small_simulation(seed=0)
    r = segment_sweep(sim.sweep)
    d = sim.distance_to_truth(r.contours[13].points_mm(sim.sweep))
    assert d.size >= 30 and d.max() <= 0.35, d.max()


def _layer_onto_the_wall() -> tuple[np.ndarray, np.ndarray, int]:
    """A path along a layer that rises gently towards the dome (0.1 mm per mm over 10 mm,
    tissue under it: step 0) and climbs the dome's wall from x = -4 to its end at x = -1.5
    (shadow under it: step 0.5): the contour's shallowest point is its end, on the wall.

    Returns the points, the underside step per point and the index of the first wall point.
    """
    rng = np.random.default_rng(7)
    xl = np.arange(-14.0, -4.0, SP[0])
    xw = np.arange(-4.0, -1.5 + 1e-9, SP[0])
    z = np.r_[_dome(-4.0) + 0.1 * (-4.0 - xl), _dome(xw)]
    step = np.r_[np.zeros(xl.size), np.full(xw.size, 0.5)] + rng.normal(0.0, 0.1, z.size)
    return _px(np.r_[xl, xw], z), step, xl.size


def test_a_layer_whose_path_climbs_onto_the_wall_at_its_end_is_cut() -> None:
    """The path ran along the layer and stopped on the bone's wall (radius, hard, seed
    43, frame 33): the apex of the middle of the contour lies on the layer, so only the
    contour's end, its shallowest point, shows the turn. The layer is cut, the wall kept
    (within 0.5 mm of where it starts), every kept point on the dome."""
    pts, step, first = _layer_onto_the_wall()
    keep = _shoulder_cut(pts, SP, step, ShadowPathParams())
    half = round(0.5 / SP[0])
    assert not keep[: first - half].any()
    assert keep[first + half :].all()
    x = (pts[keep, 0] - 100.0) * SP[0]
    assert np.abs(pts[keep, 1] * SP[1] - _dome(x)).max() < 0.05 + 1e-9


@pytest.mark.parametrize(
    ("under_dome", "under_layer"),
    [(0.5, -0.3), (0.0, 0.3)],
    ids=["shadow under the dome", "grey shadow: the underside says nothing"],
)
def test_a_layer_climbed_onto_at_an_end_over_the_bone_does_not_cut_the_bone(
    under_dome: float, under_layer: float
) -> None:
    """The other way round: a dome whose path climbs at its right end onto a layer 1 mm
    over the apex for 1.5 mm. The end is the contour's shallowest point, but the dome beyond it
    rises back over its foot (no layer falling away from a wall), and with the bone's
    shadow under the dome the underside ratio refuses as well: the dome is kept whole
    (the layer itself is cut from the dome's apex when the underside tells, as before)."""
    rng = np.random.default_rng(11)
    xd = np.arange(-6.0, 4.0 + 1e-9, SP[0])
    xl = np.arange(4.0 + SP[0], 5.5 + 1e-9, SP[0])  # short: the dome holds the apex
    z = np.r_[_dome(xd), np.full(xl.size, TOP - 1.0)]
    step = np.r_[np.full(xd.size, under_dome), np.full(xl.size, under_layer)]
    step = step + rng.normal(0.0, 0.1, z.size)
    keep = _shoulder_cut(_px(np.r_[xd, xl], z), SP, step, ShadowPathParams())
    assert keep[: xd.size].all()


def test_track_stays_on_the_bone_past_a_layer_off_its_shoulder() -> None:
    """Radius, hard realism, seed 43: from frame 33 the track left the bone for a fascia
    running off its left shoulder (4-10 mm off from frame 34 on; recall 0.82, wrong share
    0.15): the only shallow contours of frames 37 and 39 ran along the fascia and climbed
    the bone's wall at their ends, and with frames 33-34 linked the fascia into one
    chain. Cut at the wall, the track stays on the bone: frames 35-39 within 0.5 mm of
    it (33 and 34 stay 1.5-2.3 mm off: 33's cut is refused by the underside ratio, 34 is
    recovered along its neighbours), nothing kept on a wrong structure.

    Frame 32 holds the fascia over part of its length too (median 0.41 mm from the bone
    before the rim's ``max_step_mm`` 0.2): the rim followed that fascia's end on down
    the no-contact reverberations at the image's edge, 1.2 mm (recall 0.95 -> 0.925).
    With the shoulder cut on guided candidates too (:mod:`.recovery`, branch fascia)
    frames 32 and 33 lie on the bone (in-plane medians 0.33 and 0.24 mm; 33 recovered)
    and 34, a fascia 1.5 mm off, is left out: recall 0.975."""
    sim = small_simulation(bone="radius", seed=43, realism="hard")
    sc = score_simulation(segment_sweep(sim.sweep), sim)
    s = sc.summary()
    assert s["wrong_share"] == 0.0 and s["recall"] >= 0.95, (s["recall"], s["wrong_share"])
    late = {f.frame: f.median_mm for f in sc.frames if f.frame >= 35 and f.kept}
    assert len(late) == 5 and max(late.values()) < 0.5, late


def test_a_fascia_running_level_off_the_crest_is_not_kept() -> None:
    """Tibia, hard realism, seed 5: in frames 24-35 a fascia leaves the bone's right
    shoulder at its level and the path ran on along it 4-7 mm (shorter than
    shoulder_min_mm) while the bone turns down; the rim then followed the fascia's end.
    With the shorter layer cut where the bone's shadow is clear (shoulder_short_step),
    the rim follows the bone's flank instead: of the kept points of frames 24-35, 148 of
    941 lay over 1 mm from the true surface (3D), 38 of 1001 with the cut; every frame
    kept, recall 0.975 as before."""
    sim = small_simulation(bone="tibia", seed=5, realism="hard")
    res = segment_sweep(sim.sweep)
    truth = sim.truth_polydata()
    far, n = 0, 0
    for c in res.contours[24:36]:
        assert c.accepted, c.frame
        d = np.asarray(evaluate_surface(truth, c.points_mm(sim.sweep)).distances)
        far, n = far + int((d > 1.0).sum()), n + d.size
    assert far / n < 0.06, (far, n)
    assert score_simulation(res, sim).summary()["recall"] >= 0.975


def test_a_short_layer_hopped_onto_over_the_shoulder_is_cut() -> None:
    """The path hops up from the bone's shoulder onto a layer crossing it over the
    apex's level and runs on 4 mm, tissue under the layer and shadow under the bone
    (standard clavicle seed 1 with corrupted frames, frame 13, under the nulls over
    tissue: 0.9 mm up, 4 mm on, the layer's end as high as the apex). The layer rises
    over the turn, which kept it whole before; by a hop, it is cut at the turn (where
    the descent first reaches shoulder_slope), and the bone inside it is kept."""
    xd = np.arange(-14.0, 2.5 + 1e-9, SP[0])
    xl = np.arange(2.5 + SP[0], 6.5 + 1e-9, SP[0])
    # A crest descending ever more steeply to the right, gently to the left (the apex
    # stays in the middle 60 % of the span, where _apex looks).
    zd = TOP + np.where(xd > 0, 0.3, 0.05) * xd**2
    z = np.r_[zd, np.full(xl.size, TOP - 0.3)]
    step = np.r_[np.full(xd.size, 0.5), np.zeros(xl.size)]
    keep = _shoulder_cut(_px(np.r_[xd, xl], z), SP, step, ShadowPathParams())
    assert not keep[xd.size :].any()
    assert keep[: xd.size][xd <= 0.5].all()


def _cand(pts: np.ndarray, **kw: object) -> BoneCandidate:
    return BoneCandidate(pts, np.full(pts.shape[0], 100.0), 1.0, 1.5, 1.0, **kw)


def test_a_layer_left_beyond_the_settled_wall_is_dropped() -> None:
    """The settle moved the points over the dome's wall (x 2.5-3.5 mm) 1.5 mm down onto
    it; the layer's points beyond stay 1-2 mm over the wall's foot: they cannot be the
    convex bone and go, the settled wall stays. One settled point inside the dome
    (its outer side coming back down to it) drops nothing."""
    p = ShadowPathParams()
    x = np.arange(-6.0, 7.0 + 1e-9, SP[0])
    layer = _dome(2.5) + 0.05 * (x - 2.5)
    z0 = np.where(x <= 2.5, _dome(np.minimum(x, 2.5)), layer)
    wall = (x > 2.5) & (x <= 3.5)
    z1 = np.where(wall, layer + 1.5, z0)
    before, after = _cand(_px(x, z0)), _cand(_px(x, z1))
    got = cand_mod._past_the_settled_wall(before, after, SP, p, 5)
    assert got.points_px.shape[0] == int((x <= 3.5).sum())
    assert np.array_equal(got.points_px, after.points_px[x <= 3.5])
    # One point of the dome settled 1 mm down (x = -2): nothing dropped.
    z2 = z0.copy()
    z2[np.argmin(np.abs(x + 2.0))] += 1.0
    one = _cand(_px(x, z2))
    assert cand_mod._past_the_settled_wall(before, one, SP, p, 5) is one


def test_a_layer_branching_off_the_bone_contour_is_flagged() -> None:
    """A piece rooted on the whole bone's shoulder (x 3 mm) and running on level over
    the wall's descent (2 mm per mm from x 4 mm) (tibia hard seed 5, frame 24, under the nulls over tissue) is flagged
    ``echo_beneath``; the whole bone, its own apex piece (on it at every column) and a
    far cortex under it are not."""
    p = ShadowPathParams()
    ev = SimpleNamespace(fx=1, fy=1)
    xb = np.arange(-6.0, 6.0 + 1e-9, SP[0])
    wall = np.where(xb <= 4.0, _dome(np.minimum(xb, 4.0)), _dome(4.0) + 2.0 * (xb - 4.0))
    bone = _cand(_px(xb, wall))
    xa = np.arange(3.0, 6.0 + 1e-9, SP[0])
    layer = _cand(_px(xa, np.full(xa.size, _dome(3.0))))
    xt = np.arange(-2.0, 2.0 + 1e-9, SP[0])
    apex = _cand(_px(xt, _dome(xt)))
    far = _cand(_px(xt, _dome(xt) + 8.0))
    cands = [bone, layer, apex, far]
    got = cand_mod._mark_branches(cands, [c.points_px for c in cands], ev, SP, p)
    assert [c.echo_beneath for c in got] == [False, True, False, False]


def test_every_candidate_keeps_points_of_its_own_path():
    """Hard humerus at the cadaver's geometry swept by an unsteady hand
    (``bench_sweeps.py --groups motion``), seed 197, frame 12: a rim trace climbed over
    the contour it started from, and the climbing-end cut then kept the trace alone (32
    rim points, none of the path's). The track compares the path's points and stopped
    on it with a traceback; such a candidate is now dropped, and the sweep segments."""
    # bench_sweeps.MOTION: tilt 12 degrees, 4 mm lateral and 2 mm depth jitter, speed
    # varying by 0.8.
    motion = {"tilt_deg": 12.0, "lateral_jitter_mm": 4.0, "depth_jitter_mm": 2.0}
    sim = small_simulation(
        bone="humerus", seed=197, realism="hard", speed_variation=0.8, **motion, **CADAVER
    )
    sp = tuple(sim.sweep.spacing_mm)
    fc = frame_candidates(sim.sweep.frames[12], sp, ShadowPathParams())
    assert fc.candidates and all(c.core_px.shape[0] > 0 for c in fc.candidates)
    result = segment_sweep(sim.sweep)
    assert result.contours[12].accepted

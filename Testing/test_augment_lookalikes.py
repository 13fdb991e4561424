"""Look-alikes drawn into a recording (issue 10, item 2), and the segmenter holding on them.

:func:`augment.no_contact` (a skin line over a no-contact gap at an image edge, with its
reverberation copies), :func:`augment.add_fascia` (a fascia leaving the bone's flank at
its level), :func:`augment.add_vessel` (a vessel with dark lumen, walls, enhancement
and ring-down over the bone) and :func:`augment.add_muscle` (a hypoechoic muscle lying on
the bone, under its fascia or not): each is checked on a small simulated sweep (where it is
drawn, at the grey levels the recording itself gives), then on the shared L14 recording
and on its cadaver-level copy (:func:`augment.harden` with the reference contours),
scored against the reference contours of ``Testing/data``: the simulator's look-alikes
on real texture.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest
from conftest import REAL_MHA, REAL_XML

from BoneUSRecon.Logic.segmentation import segment_sweep
from BoneUSRecon.Logic.simulation import SimulationParams, augment, echo_levels, simulate
from BoneUSRecon.Logic.simulation.scoring import read_reference_csv, score_reference

DATA = Path(__file__).resolve().parent / "data"
MARGIN = 8  # black columns each side of the simulated frames


@pytest.fixture(scope="module")
def sim():
    return simulate(
        SimulationParams(
            bone="tibia",
            n_frames=8,
            width=160,
            height=128,
            spacing_mm=0.3,
            seed=3,
            black_margin_px=MARGIN,
        )
    )


def _contours(sim) -> dict[int, np.ndarray]:
    return {k: c for k, c in enumerate(sim.true_contours_px) if len(c) >= 3}


def _unchanged_geometry(before, after) -> None:
    assert after.frames.shape == before.frames.shape and after.frames.dtype == np.uint8
    assert np.array_equal(after.image_to_reference, before.image_to_reference)
    assert after.frames[:, :, :MARGIN].max() == 0 and after.frames[:, :, -MARGIN:].max() == 0


def _drawn(sim, draw, *args, **kwargs) -> tuple[np.ndarray, np.ndarray]:
    """``draw(sim.sweep, *args, **kwargs)`` with its input untouched and the geometry
    unchanged; the frames' greys before and after, as floats."""
    before = np.array(sim.sweep.frames)
    out = draw(sim.sweep, *args, **kwargs)
    assert np.array_equal(sim.sweep.frames, before)  # the input is not touched
    _unchanged_geometry(sim.sweep, out)
    return before.astype(float), out.frames.astype(float)


@pytest.mark.parametrize("side", [1, -1])
def test_no_contact_draws_a_dark_gap_a_bright_skin_line_and_its_copies(sim, side) -> None:
    f, g = _drawn(sim, augment.no_contact, side=side, depth_mm=6.0, copies=2, transmission=0.4)
    sp = 0.3
    w = f.shape[2]
    edge = w - 1 - MARGIN if side > 0 else MARGIN  # the outermost imaged column
    other = slice(MARGIN, MARGIN + 40) if side > 0 else slice(w - MARGIN - 40, w - MARGIN)
    # In contact (the other side of the image): nothing changes.
    assert np.array_equal(g[:, :, other], f[:, :, other])
    skin = (1.2 + 6.0) / sp  # rows under the probe face at the edge column (top row 0)
    floor = np.percentile(f[:, :, MARGIN:-MARGIN], 2)
    for k in range(f.shape[0]):
        bright = np.percentile(f[k][:, MARGIN:-MARGIN], 99.9)
        col = g[k, :, edge]
        # The gap returns nothing but the recording's own floor (textured).
        assert np.median(col[2 : int(skin) - 4]) <= 2 * floor + 1
        # The skin line, as bright as the frame's brightest echo (texture: +-25 %), and
        # its first copy at twice its depth, 0.65 of it.
        near = col[int(skin) - 2 : int(skin) + 3].max()
        copy = col[int(2 * skin) - 2 : int(2 * skin) + 3].max()
        assert 0.5 * bright <= near <= 255
        assert 0.3 * bright <= copy < near + 40
    # Under the skin, away from its lines, the tissue is dimmed to the transmission.
    rows = slice(int(skin) + 4, int(2 * skin) - 4)
    ratio = g[:, rows, edge].mean() / max(f[:, rows, edge].mean(), 1.0)
    assert 0.3 <= ratio <= 0.55, ratio


def test_fascia_leaves_the_flank_at_the_bone_level_as_bright_as_its_echo(sim) -> None:
    cont = _contours(sim)
    sp = 0.3
    f, g = _drawn(sim, augment.add_fascia, cont, side=1, slope=0.08, length_mm=10.0)
    checked = 0
    for k, c in cont.items():
        c = c[np.argsort(c[:, 0])]
        top, apex = c[:, 1].min(), c[np.argmin(c[:, 1]), 0]
        outward = c[c[:, 0] > apex]
        hit = outward[outward[:, 1] >= top + 1.5 / sp]
        if not len(hit):
            continue
        i0, j0 = hit[0]
        i = int(round(i0 + 4.0 / sp))  # 4 mm along the fascia
        if i >= f.shape[2] - MARGIN:
            continue
        j = j0 + (i - i0) * 0.08
        grey = echo_levels(f[k][None], [c], sp)["echo"]
        got = g[k, int(j) - 3 : int(j) + 4, i].max()
        assert got >= 0.6 * grey, (k, got, grey)
        # Nothing drawn on the other side of the top.
        assert np.array_equal(g[k, :, : int(apex) - 2], f[k, :, : int(apex) - 2])
        checked += 1
    assert checked >= 4


def test_vessel_over_the_bone_dark_lumen_enhancement_and_no_room_no_vessel(sim) -> None:
    cont = _contours(sim)
    sp = 0.3
    f, g = _drawn(sim, augment.add_vessel, cont, lateral_mm=0.0, gap_mm=3.0, radius_mm=2.5)
    floor = np.percentile(f[:, :, MARGIN:-MARGIN], 2)
    drawn = 0
    for k, c in cont.items():
        c = c[np.argsort(c[:, 0])]
        ci = c[np.argmin(c[:, 1]), 0]
        jb = np.interp(ci, c[:, 0], c[:, 1])
        cj = jb - (3.0 + 2.5) / sp
        if cj - 2.5 / sp < 1.0 / sp:
            assert np.array_equal(g[k], f[k])  # no room above this frame's bone
            continue
        r = int(1.0 / sp)
        lumen = g[k, int(cj) - r : int(cj) + r + 1, int(ci) - r : int(ci) + r + 1]
        assert np.median(lumen) <= 2 * floor + 1
        # Posterior enhancement: the tissue between the lumen and the bone brightens.
        rows = slice(int(cj + 2.5 / sp) + 2, int(jb - 1.0 / sp))
        cols = slice(int(ci) - r, int(ci) + r + 1)
        assert g[k, rows, cols].mean() > 1.05 * f[k, rows, cols].mean()
        drawn += 1
    assert drawn >= 4
    # A bone right under the probe face leaves no room: that frame is left as it was.
    shallow = {0: np.column_stack([np.arange(40.0, 120.0), np.full(80, 3.0)])}
    same = augment.add_vessel(sim.sweep, shallow)
    assert np.array_equal(same.frames, sim.sweep.frames)


def test_muscle_darkens_a_band_over_the_bone_and_nothing_beside_it(sim) -> None:
    cont = _contours(sim)
    sp = 0.3
    f, g = _drawn(sim, augment.add_muscle, cont, ratio=0.6, gap_mm=1.0, thickness_mm=6.0)
    w = f.shape[2]
    checked = 0
    for k, c in cont.items():
        c = c[np.argsort(c[:, 0])]
        cols = np.arange(int(c[0, 0]) + 2, int(c[-1, 0]) - 1)
        bone = np.interp(cols, c[:, 0], c[:, 1])
        # Inside the band (2-6 mm over the bone): the recording's grey times the ratio,
        # its texture kept (a muscle is speckle at a lower level, not a floor).
        band = [
            (int(round(b - m / sp)), i)
            for i, b in zip(cols, bone, strict=True)
            for m in (2.0, 4.0, 6.0)
        ]
        band = [(j, i) for j, i in band if j >= 0]
        if len(band) < 20:
            continue
        jj, ii = np.array(band).T
        assert abs(g[k, jj, ii].sum() / f[k, jj, ii].sum() - 0.6) < 0.03
        assert g[k, jj, ii].std() > 0.3 * f[k, jj, ii].std()
        # The bone and what lies under it are untouched, as is the tissue more than
        # 5 mm (+ the 1 mm edge) beside the contour's ends.
        under = [
            (int(round(b + m / sp)), i) for i, b in zip(cols, bone, strict=True) for m in (0.0, 2.0)
        ]
        under = [(j, i) for j, i in under if j < f.shape[1]]
        ju, iu = np.array(under).T
        assert np.array_equal(g[k, ju, iu], f[k, ju, iu])
        far = int(c[-1, 0] + 6.5 / sp)
        if far < w:
            assert np.array_equal(g[k, :, far:], f[k, :, far:])
        checked += 1
    assert checked >= 4
    # With its fascia: a line along the band's top at the frame's bone echo grey.
    lined = augment.add_muscle(sim.sweep, cont, ratio=0.6, thickness_mm=6.0, fascia=1.0)
    g = lined.frames.astype(float)
    for k, c in list(cont.items())[:3]:
        c = c[np.argsort(c[:, 0])]
        i = int(np.median(c[:, 0]))
        top = np.interp(i, c[:, 0], c[:, 1]) - 7.0 / sp
        if top < 3:
            continue
        grey = echo_levels(f[k][None], [c], sp)["echo"]
        assert g[k, int(top) - 2 : int(top) + 3, i].max() >= 0.5 * grey
    # Over one end of the sweep only: the frames past it as they were, those in it as
    # over the whole sweep (the texture is drawn for every frame alike).
    n = sim.sweep.n_frames
    whole = augment.add_muscle(sim.sweep, cont, ratio=0.6)
    end = augment.add_muscle(sim.sweep, cont, ratio=0.6, along=(0.0, 0.4))
    drawn = [k for k in cont if k < 0.4 * n]
    assert drawn and any(k >= 0.4 * n for k in cont)
    for k in range(n):
        want = whole.frames[k] if k < 0.4 * n else sim.sweep.frames[k]
        assert np.array_equal(end.frames[k], want)
    with pytest.raises(ValueError, match="along"):
        augment.add_muscle(sim.sweep, cont, along=(0.5, 0.5))


@pytest.mark.parametrize("bone", ["radius", "ulna", "humerus", "clavicle"])
def test_a_bone_under_a_bright_fascia_over_a_dark_muscle_holds(bone) -> None:
    """A muscle at 0.6 of the tissue's grey, 6 mm thick, under a fascia 1.5 times the
    bone's echo, over the whole of a hard sweep: a bright arch over a dark band in every
    frame, the bone under it dimmer than the arch. The bone under the arch is no far
    cortex (it is a dome) and no copy, so the sound reached it through the arch: it
    does not lie in the arch's shadow (``candidates._mark_echo_beneath``). Before (the
    band read as the arch's shadow, the bone as lying in it): recall 0-0.15, wrong
    0.6-1.0 on seeds 3 and 7 for these bones; after, 1.00 and 0. (The tibia stays open:
    its bone and the arch both unflagged, the arch the stronger.)"""
    from BoneUSRecon.Logic.simulation.scoring import score_simulation

    s = simulate(
        SimulationParams(
            bone=bone, n_frames=20, width=160, height=128, spacing_mm=0.3, seed=3, realism="hard"
        )
    )
    sw = augment.add_muscle(s.sweep, _contours(s), ratio=0.6, thickness_mm=6.0, fascia=1.5)
    sc = score_simulation(segment_sweep(sw), dataclasses.replace(s, sweep=sw)).summary()
    assert sc["recall"] >= 0.95 and sc["wrong_share"] == 0.0, sc


def test_a_lumen_is_read_as_tissue_a_shadow_is_not() -> None:
    """`candidates._without_lumens` on a log-ratio map (0 = tissue at its depth)."""
    from types import SimpleNamespace

    from BoneUSRecon.Logic.segmentation.candidates import _without_lumens
    from BoneUSRecon.Logic.segmentation.params import ShadowPathParams

    d = 0.25  # mm per working pixel
    h, w = 160, 200
    lr = np.zeros((h, w), np.float32)
    rows, cols = np.mgrid[0:h, 0:w]
    lumen = (rows - 40) ** 2 + (cols - 40) ** 2 < 10**2  # 5 mm across
    lr[lumen] = -3.0
    lr[50:55, 30:51] = 0.4  # the back wall and the enhancement under it
    no_enh = (rows - 40) ** 2 + (cols - 150) ** 2 < 10**2  # the same without enhancement
    lr[no_enh] = -3.0
    lr[100:, 60:100] = -3.0  # a shadow: from a bone down to the image's bottom
    lr[80:90, 110:190] = -3.0  # a dark band 20 mm wide between two copies
    lr[90:94, 110:190] = 0.5
    ev = SimpleNamespace(field_top=0, usable=np.ones(w, bool), dx=d, dy=d)
    p = ShadowPathParams()
    out = _without_lumens(lr, ev, p)
    assert np.all(out[lumen] == 0.0)
    keep = ~lumen
    assert np.array_equal(out[keep], lr[keep])  # shadow, band, lumen without enhancement
    assert _without_lumens(lr, ev, ShadowPathParams(lumen_ratio=0.0)) is lr  # off
    # A lumen open to an unusable column (an uncoupled edge) is no lumen either.
    ev.usable[25:35] = False
    assert np.array_equal(_without_lumens(lr, ev, p), lr)


# -- The segmenter on the real recording with the look-alikes drawn in ---------------------


@pytest.fixture(scope="module")
def real():
    from BoneUSRecon.Logic.sequence_io import read_sweep

    sw = read_sweep(REAL_MHA, calibration=REAL_XML)
    ref = read_reference_csv(DATA / "L14_reference.csv")
    bases = {
        "recording": sw,
        "cadaver": augment.harden(sw, bone_contours=ref),
        "grey-shadow": augment.HARD_AUGMENTATIONS["grey-shadow"](sw),
    }
    return bases, ref


SINGLE = [n for n in augment.LOOKALIKE_AUGMENTATIONS if n != "lookalikes"]
HOLDS = [(n, b) for n in SINGLE for b in ("recording", "grey-shadow", "cadaver")] + [
    ("lookalikes", "recording"),
    ("lookalikes", "grey-shadow"),
]


@pytest.mark.parametrize(("name", "base"), HOLDS)
def test_segmenter_holds_on_real_texture_with_a_lookalike(real, name, base) -> None:
    bases, ref = real
    sw = augment.LOOKALIKE_AUGMENTATIONS[name](bases[base], ref)
    s = score_reference(segment_sweep(sw), sw, ref).summary()
    # Measured (session 49): every frame kept and on the bone (recall 1.00, wrong 0) in
    # all ten cases; kept points' median 0.048-0.054 mm on the recording and its
    # grey-shadow copy, 0.096-0.121 on the cadaver copy; > 2 mm at most 0.6 % (the
    # cadaver copy with the gap on the left, where the flank runs under the skin's copies).
    # The muscle rows (session 50): 1.00 / 0 on all three, medians 0.050-0.053 and
    # 0.103-0.116 mm; before the grey over a line alone stopped counting as a shadow,
    # the grey-shadow copy's were recall 0 (wrong 0.48 and 0.86).
    assert s["recall"] >= 0.95, s
    assert s["wrong_share"] == 0.0, s
    assert s["median_mm"] <= 0.2, s
    assert s["over_2mm"] <= 0.02, s


@pytest.mark.xfail(
    strict=True,
    reason="open (session 49): on the cadaver copy the vessel over the bone's top and the "
    "no-contact gap together let a layer at the vessel's depth, 8-9 mm over the bone, carry "
    "the track (recall 0, 15 of 21 frames kept on it, the bone's last 6 rejected as jumps): "
    "in frames 0-6 it is the strongest candidate (14-16 against the bone's 3.5-5, or no "
    "bone candidate); either alone the bone holds; see Testing/benchmarks/README.md, "
    "session 49",
)
def test_segmenter_on_the_cadaver_copy_with_every_lookalike(real) -> None:
    bases, ref = real
    sw = augment.LOOKALIKE_AUGMENTATIONS["lookalikes"](bases["cadaver"], ref)
    s = score_reference(segment_sweep(sw), sw, ref).summary()
    assert s["recall"] >= 0.95 and s["wrong_share"] == 0.0, s


def test_the_near_field_is_no_cover_over_a_superficial_layer(real) -> None:
    """The cadaver copy's frame 16: a layer 3-4 mm under the probe face, the bright near
    field over it. Judged against that "cover", the plain tissue between the layer and
    the bone (0.94 of the tissue level) read as the layer's shadow and the bone as lying
    in it (``echo_beneath``, valued at a tenth on the track). The near field is gel, skin
    and lens echoes, not tissue the sound crossed: it is no cover."""
    from scipy.spatial import cKDTree

    from BoneUSRecon.Logic.segmentation.candidates import frame_candidates
    from BoneUSRecon.Logic.segmentation.params import ShadowPathParams

    bases, ref = real
    sw = bases["cadaver"]
    fc = frame_candidates(np.asarray(sw.frames[16]), sw.spacing_mm, ShadowPathParams())
    t = cKDTree(ref[16])
    on_bone = [
        c for c in fc.candidates if np.median(t.query(c.points_px)[0]) * sw.spacing_mm[0] < 1.0
    ]
    assert on_bone and not any(c.echo_beneath for c in on_bone)


def test_a_side_other_than_either_edge_is_refused(sim) -> None:
    with pytest.raises(ValueError, match="side must be 1"):
        augment.no_contact(sim.sweep, side=0)
    with pytest.raises(ValueError, match="side must be 1"):
        augment.add_fascia(sim.sweep, _contours(sim), side=2)

"""The phantom simulator: geometry, motion, images, corruption, gold points, files, CLI.

Everything is checked against the simulator's own analytic truth in millimetres or
against what an image must show (bright bone line on the true surface, dark shadow).
"""

from __future__ import annotations

import json

import numpy as np
import pytest
from conftest import CADAVER, small_simulation
from hypothesis import given, settings
from hypothesis import strategies as st
from vtkmodules.vtkCommonCore import reference
from vtkmodules.vtkCommonDataModel import vtkStaticCellLocator

from BoneUSRecon.cli import main
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.simulation import (
    BONE_SPECS,
    BONES,
    CORRUPTION_KINDS,
    BoneGeometry,
    SimulationParams,
    sample_gold,
    simulate,
    write_simulation,
)
from BoneUSRecon.Logic.sweep import frame_planes

TINY = {"n_frames": 6, "width": 64, "height": 64, "spacing_mm": 0.6}


# -- determinism -----------------------------------------------------------------------
def test_same_seed_same_everything_other_seed_differs() -> None:
    a = simulate(SimulationParams(bone="ulna", seed=7, corrupted_fraction=0.5, **TINY))
    b = simulate(SimulationParams(bone="ulna", seed=7, corrupted_fraction=0.5, **TINY))
    c = simulate(SimulationParams(bone="ulna", seed=8, corrupted_fraction=0.5, **TINY))
    assert np.array_equal(a.sweep.frames, b.sweep.frames)
    assert np.array_equal(a.sweep.image_to_reference, b.sweep.image_to_reference)
    assert np.array_equal(a.sweep.timestamps, b.sweep.timestamps)
    assert np.array_equal(a.gold, b.gold)
    assert a.corruption_kinds == b.corruption_kinds
    assert all(
        np.array_equal(x, y) for x, y in zip(a.true_contours_px, b.true_contours_px, strict=True)
    )
    assert not np.array_equal(a.sweep.frames, c.sweep.frames)
    assert not np.allclose(a.sweep.image_to_reference, c.sweep.image_to_reference)
    assert not np.allclose(a.gold, c.gold)


# -- geometry ----------------------------------------------------------------------------
def _mesh_section_extents(verts: np.ndarray, x: float) -> tuple[float, float]:
    ring = verts[np.abs(verts[:, 0] - x) < 0.3]
    return float(np.ptp(ring[:, 1])), float(np.ptp(ring[:, 2]))


# Expected (width, height) ranges of the shaft (mm) and depth under the skin (mm).
SIZES = {
    "radius": ((12, 20), (9, 13), (5, 15)),
    "ulna": ((11, 17), (9, 15), (5, 15)),
    "tibia": ((24, 31), (18, 24), (10, 16)),
    "humerus": ((20, 24), (18, 21), (16, 24)),
    "clavicle": ((11, 16), (7, 13), (3, 8)),
}


@pytest.mark.parametrize("bone", BONES)
def test_bone_sizes_on_the_truth_mesh(bone: str) -> None:
    geom = BoneGeometry(BONE_SPECS[bone])
    verts, faces = geom.mesh()
    assert faces.max() < len(verts)
    assert 60 <= geom.length <= 150
    (wlo, whi), (hlo, hhi), _ = SIZES[bone]
    for x in np.linspace(-0.4, 0.4, 9) * geom.length:
        w, h = _mesh_section_extents(verts, x)
        # The twisted ellipse's extents lie between its two diameters.
        assert wlo - 1 <= w <= whi + 1, (bone, x, w)
        assert hlo - 1 <= h <= whi + 1, (bone, x, h)
    a, b = geom.semi_axes(np.linspace(0, geom.length, 50))
    assert wlo <= 2 * a.min() and 2 * a.max() <= whi
    assert hlo <= 2 * b.min() and 2 * b.max() <= hhi


@pytest.mark.parametrize("bone", BONES)
def test_bone_depth_under_the_probe(bone: str, sim_factory) -> None:
    sim = sim_factory(bone=bone, n_frames=8)
    _, _, (dlo, dhi) = SIZES[bone]
    sp = sim.params.spacing_mm
    tops = [c[:, 1].min() * sp for c in sim.true_contours_px if len(c)]
    assert len(tops) == 8
    assert dlo <= np.median(tops) <= dhi
    assert dlo - 2 <= min(tops) and max(tops) <= dhi + 2


@pytest.mark.parametrize("floor", [3.0, 0.0])
def test_probe_pressure_never_brings_the_bone_above_the_floor(floor: float) -> None:
    # An unsteady hand pressing hard (3 mm depth jitter, 12 degrees of tilt) at the
    # hard preset's shallow end: the bone's nearest point in any image stays
    # min_depth_mm under the probe. Without the floor it rose to 1.6 mm (seed 1),
    # above the preset's skin line at 1.2 mm plus the tissue a probe cannot squeeze out.
    sim = simulate(
        SimulationParams(
            bone="radius",
            seed=1,
            realism="hard",
            n_frames=16,
            width=96,
            height=96,
            spacing_mm=0.4,
            tilt_deg=12.0,
            lateral_jitter_mm=4.0,
            depth_jitter_mm=3.0,
            min_depth_mm=floor,
        )
    )
    nearest = min(c[:, 1].min() * 0.4 for c in sim.true_contours_px if len(c))
    if floor > 0:
        assert nearest == pytest.approx(floor, abs=0.01)
    else:
        assert nearest < 2.0


def _axis_lateral_curvature(geom: BoneGeometry) -> np.ndarray:
    # Ring centroids of the mesh (rings of 192 vertices, uniform in phi) = axis points.
    verts, _ = geom.mesh(ds=2.0, n_around=192)
    centres = verts.reshape(-1, 192, 3).mean(1)[2:-2]
    xs, cy = centres[:, 0], centres[:, 1]
    return np.gradient(np.gradient(cy, xs), xs)


def test_clavicle_is_s_shaped_and_radius_is_bowed() -> None:
    k = _axis_lateral_curvature(BoneGeometry(BONE_SPECS["clavicle"]))
    strong = k[np.abs(k) > 0.3 * np.abs(k).max()]
    # S-shape: lateral curvature of both signs, each strong (> 1/150 mm).
    assert strong.max() > 1 / 150 and strong.min() < -1 / 150
    k = _axis_lateral_curvature(BoneGeometry(BONE_SPECS["radius"]))
    strong = k[np.abs(k) > 0.3 * np.abs(k).max()]
    assert np.all(np.sign(strong) == np.sign(strong[0]))  # one bow


def test_truth_mesh_is_closed_around_and_outward() -> None:
    geom = BoneGeometry(BONE_SPECS["humerus"])
    v, f = geom.mesh()
    n = np.cross(v[f[:, 1]] - v[f[:, 0]], v[f[:, 2]] - v[f[:, 0]])
    centre = v[f].mean(1)
    # Outward: away from the axis point at the same x.
    s = centre[:, 0] + geom.length / 2
    radial = centre - geom.axis(s)
    assert np.all(np.einsum("ij,ij->i", n, radial) > 0)


def test_distance_to_truth_exact_and_matches_the_mesh(sim_small) -> None:
    geom = sim_small.geometry
    rng = np.random.default_rng(3)
    s = rng.uniform(5, geom.length - 5, 4000)
    phi = rng.uniform(0, 2 * np.pi, 4000)
    d = rng.uniform(-1.5, 6.0, 4000)
    q = geom.surface(s, phi) + d[:, None] * geom.normals(s, phi)
    dist = sim_small.distance_to_truth(q)
    assert np.abs(dist - np.abs(d)).max() < 1e-5

    # Independent check on the written mesh with VTK's locator.
    pd = sim_small.truth_polydata()
    loc = vtkStaticCellLocator()
    loc.SetDataSet(pd)
    loc.BuildLocator()
    closest = [0.0, 0.0, 0.0]
    cid, sid, dd = reference(0), reference(0), reference(0.0)
    vtk_d = []
    for p in q[:300]:
        loc.FindClosestPoint(p.tolist(), closest, cid, sid, dd)
        vtk_d.append(np.sqrt(float(dd)))
    assert np.abs(np.array(vtk_d) - dist[:300]).max() < 0.01


@settings(max_examples=25, deadline=None)
@given(
    bone=st.sampled_from(BONES),
    s=st.floats(0.02, 0.98),
    phi=st.floats(0, 2 * np.pi),
    d=st.floats(-1.0, 8.0),
)
def test_distance_to_truth_property(bone: str, s: float, phi: float, d: float) -> None:
    # A point d mm along the outward normal is |d| from the surface (inside: while
    # |d| is below the smallest radius of curvature, > 3 mm for every bone).
    geom = BoneGeometry(BONE_SPECS[bone])
    s_mm = s * geom.length
    p = geom.surface(s_mm, phi) + d * geom.normals(s_mm, phi)
    assert abs(geom.distance(p[None])[0] - abs(d)) < 1e-6


def test_contours_mm_skip_frames_without_bone(sim_small_corrupted) -> None:
    sim = sim_small_corrupted
    got = dict(sim.contours_mm())
    lost = [k for k, v in sim.corruption_kinds.items() if v == "contact_loss"]
    assert lost and not set(lost) & set(got)
    assert len(got) == sim.sweep.n_frames - len(lost)
    assert all(sim.distance_to_truth(p).max() < 0.01 for p in got.values())


# -- probe motion ---------------------------------------------------------------------------
def test_poses_follow_the_bone_with_freehand_jitter(sim_small) -> None:
    sw, p = sim_small.sweep, sim_small.params
    m = sw.image_to_reference
    assert np.allclose(sw.spacing_mm, p.spacing_mm)
    origin, axes, normal = frame_planes(m)
    # Columns and rows orthogonal; rows go down into the body.
    assert np.abs(np.einsum("ni,ni->n", axes[:, :, 0], axes[:, :, 1])).max() < 1e-9
    assert np.all(axes[:, 2, 1] < -0.95)
    # Slices are not parallel: several degrees of tilt between frames.
    mean_n = normal.mean(0) / np.linalg.norm(normal.mean(0))
    ang = np.degrees(np.arccos(np.clip(np.abs(normal @ mean_n), 0, 1)))
    assert ang.std() > 1.5 and ang.max() > 3.0
    consecutive = np.degrees(
        np.arccos(np.clip(np.abs(np.einsum("ni,ni->n", normal[1:], normal[:-1])), 0, 1))
    )
    assert np.all(consecutive > 0.01)
    assert sim_small.path.angles_deg.std(0).min() > 0.3 * p.tilt_deg / 2
    # Frames march along the bone (x) with uneven steps.
    centre = sw.corners_mm(np.arange(sw.n_frames)).mean(1)
    steps = np.diff(centre[:, 0])
    assert np.all(steps > 0)
    assert steps.std() / steps.mean() > 0.1
    # Lateral wander around the bone, bone kept in view.
    assert 0.3 < sim_small.path.lateral_mm.std() < 4.0
    assert all(len(c) > 10 for c in sim_small.true_contours_px)
    # Timestamps increase at ~the frame rate.
    dt = np.diff(sw.timestamps)
    assert np.all(dt > 0) and abs(np.median(dt) - 1 / p.frame_rate_hz) < 0.01


def test_reverse_sweeps_the_other_way(sim_factory) -> None:
    sw = sim_factory(reverse=True, n_frames=10).sweep
    centre = sw.corners_mm(np.arange(sw.n_frames)).mean(1)
    assert np.all(np.diff(centre[:, 0]) < 0)


# -- images ---------------------------------------------------------------------------------
def _band_means(
    frame: np.ndarray, contour: np.ndarray, offset_px: float, half: int = 1
) -> np.ndarray:
    i = contour[:, 0].astype(int)
    j = np.rint(contour[:, 1] + offset_px).astype(int)
    rows = np.clip(j[:, None] + np.arange(-half, half + 1), 0, frame.shape[0] - 1)
    return frame[rows, i[:, None]].mean(1)


def test_true_contours_lie_on_the_bright_bone_line(sim_small) -> None:
    sw = sim_small.sweep
    sp = sim_small.params.spacing_mm
    line, shadow, above, tail, peak_off = [], [], [], [], []
    for k, c in enumerate(sim_small.true_contours_px):
        assert c.ndim == 2 and c.shape[1] == 2 and len(c) > 10
        assert np.all(np.diff(c[:, 0]) > 0)  # ordered by increasing i
        f = sw.frames[k].astype(float)
        line.append(_band_means(f, c, 0.0).mean())
        shadow.append(_band_means(f, c, 2.0 / sp).mean())
        tail.append(_band_means(f, c, 0.6 / sp).mean())
        above.append(_band_means(f, c, -1.5 / sp).mean())
        # The brightest row near the contour is the contour row itself.
        i = c[:, 0].astype(int)
        win = np.clip(np.rint(c[:, 1]).astype(int)[:, None] + np.arange(-4, 5), 0, sw.height - 1)
        best = win[np.arange(len(i)), np.argmax(f[win, i[:, None]], axis=1)]
        peak_off.append(np.median(best - c[:, 1]))
        # The contour in mm lies on the true surface.
        assert sim_small.distance_to_truth(sim_small.contour_mm(k)).max() < 0.01
    line, shadow, above, tail = map(np.array, (line, shadow, above, tail))
    assert line.min() > 130 and line.mean() > 150
    # The shadow (2 mm under the surface) is grey, not black, as on real recordings:
    # on average 15-50 % of the tissue above, and well under the echo.
    assert np.all(line > 3 * shadow)
    assert 0.15 < shadow.mean() / above.mean() < 0.5
    # The echo is thick below the surface (cortical tail), not above it: 0.6 mm under
    # the surface is still brighter than the shadow; the peak is on the surface.
    assert np.all(tail > shadow + 10)
    assert np.all(line > above + 40)  # soft tissue above is mid-grey
    assert np.abs(np.array(peak_off)).max() <= 1.0


def test_soft_tissue_has_speckle_and_fascia(sim_small) -> None:
    f = sim_small.sweep.frames[10].astype(float)
    sp = sim_small.params.spacing_mm
    c = sim_small.true_contours_px[10]
    # Beside the bone, below the fascia: muscle speckle, mid grey, strongly fluctuating.
    cols = np.setdiff1d(np.arange(f.shape[1]), np.arange(int(c[0, 0]) - 15, int(c[-1, 0]) + 15))
    muscle = f[int(12 / sp) : int(30 / sp)][:, cols]
    assert 50 < muscle.mean() < 140
    assert muscle.std() / muscle.mean() > 0.3
    # Fascia: bright rows above the bone that are not bone (no shadow beneath).
    top = int(c[:, 1].min())
    assert np.percentile(f[int(1.5 / sp) : top - 2], 99.5) > 150


def test_forearm_scan_shows_the_other_bone_beside_the_target(sim_factory) -> None:
    with_n = sim_factory(bone="radius", n_frames=6)
    without = sim_factory(bone="radius", n_frames=6, neighbour=False)
    assert with_n.neighbour is not None and without.neighbour is None
    assert with_n.neighbour.spec.name == "ulna"
    # Same truth, gold and contours: the neighbour is only a distractor in the image.
    assert np.array_equal(with_n.gold, without.gold)
    assert all(
        np.array_equal(a, b)
        for a, b in zip(with_n.true_contours_px, without.true_contours_px, strict=True)
    )
    h = with_n.sweep.height
    for k in range(6):
        a = with_n.sweep.frames[k].astype(float)
        b = without.sweep.frames[k].astype(float)
        cols = np.flatnonzero(np.abs(a - b).max(0) > 0)
        target = np.flatnonzero(np.isfinite(with_n.sections.top_j[k]))
        assert cols.size > 5
        # Only beside the target bone (shadow edges blur by a few pixels)...
        assert np.intersect1d(cols, target[3:-3]).size == 0
        # ...a bright bone echo over a dark shadow.
        other = cols[np.abs(a - b)[:, cols].max(0) > 100]
        assert a[:, other].max() > 160  # (the edge of the ulna: oblique, so not the brightest)
        assert a[h // 2 :, other].mean() < 0.5 * b[h // 2 :, other].mean()


# -- gold points ----------------------------------------------------------------------------
def test_gold_points_on_the_imaged_upper_surface(sim_small) -> None:
    gold = sim_small.gold
    assert gold.shape == (1145, 3)
    s, phi, foot, d = sim_small.geometry.closest_points(gold)
    # Isotropic 0.2 mm noise per axis: its normal component is N(0, 0.2).
    rms = np.sqrt(np.mean(d**2))
    assert 0.17 < rms < 0.23
    assert d.max() < 1.2
    up = sim_small.geometry.normals(s, phi)[:, 2]
    # Drawn where up >= visible_cos (0.5); the digitiser noise moves the nearest foot
    # point a little round the clavicle's tight flat side (seed 0: lowest 0.399).
    assert np.all(up > 0.35)
    lo, hi = sim_small.swept_range_mm
    assert lo - 0.5 <= s.min() and s.max() <= hi + 0.5
    # Spread over the swept length, not clustered.
    assert (s.max() - s.min()) > 0.8 * (hi - lo)


def test_gold_points_stay_inside_a_narrow_field_of_view(sim_factory) -> None:
    # A 9 mm wide image over a 25-30 mm wide tibia: gold only where it was imaged.
    def lateral(sim):  # gold's lateral position across the bone (mm from the axis)
        s, _, foot, _ = sim.geometry.closest_points(sim.gold)
        _, e_lat, _ = sim.geometry.frame(s)
        return np.einsum("ki,ki->k", foot - sim.geometry.axis(s), e_lat)

    narrow = sim_factory(bone="tibia", width=30, n_frames=20)
    wide = sim_factory(bone="tibia", n_frames=20)
    assert len(narrow.gold) == len(wide.gold) == 1145
    ln, lw = lateral(narrow), lateral(wide)
    half_fov = 0.5 * 30 * narrow.params.spacing_mm
    assert np.abs(ln).max() < half_fov + 3 * narrow.params.lateral_jitter_mm
    assert np.ptp(np.percentile(ln, [1, 99])) < 0.6 * np.ptp(np.percentile(lw, [1, 99]))


def _beyond_end_planes(sim, points: np.ndarray) -> np.ndarray:
    """How far (mm) each point lies beyond the nearer end plane (< 0: between them)."""
    m = sim.sweep.image_to_reference
    seen = [k for k, c in enumerate(sim.true_contours_px) if len(c)]
    centre = m[seen, :3, 3].mean(axis=0)
    out = np.full(len(points), -np.inf)
    for k in (seen[0], seen[-1]):
        n = np.cross(m[k, :3, 0], m[k, :3, 1])
        n /= np.linalg.norm(n)
        side = np.sign((centre - m[k, :3, 3]) @ n)
        out = np.maximum(out, -side * ((points - m[k, :3, 3]) @ n))
    return out


def test_gold_points_lie_between_the_end_frames_planes(sim_factory) -> None:
    # A wide bone with the probe yawed: the end frames' sections span several mm of
    # the axis, but only bone between the first and last image planes was imaged.
    sim = sim_factory(bone="tibia", n_frames=20, seed=13, gold_noise_mm=0.0)
    assert sim.params.gold_region == "imaged"
    assert np.array_equal(sample_gold(sim), sim.gold)  # the same generator
    assert len(sim.gold) == 1145
    assert _beyond_end_planes(sim, sim.gold).max() <= 1e-9
    # The old definition (the whole axis range the sections touch) goes past them.
    swept = sample_gold(sim, "swept")
    beyond = _beyond_end_planes(sim, swept)
    assert beyond.max() > 1.0 and (beyond > 0).sum() > 10
    with pytest.raises(ValueError, match="gold_region"):
        SimulationParams(gold_region="everywhere")


def test_surface_from_true_contours_covers_the_imaged_gold():
    # From true contours the surface covers the imaged gold (tibia, 20 frames: 99.9 %
    # within 1 mm); the swept definition's points beyond the end planes are ~2 mm
    # away (as on the 150-frame tibia, seed 13: 24 of its 25 points missed by 1 mm).
    from BoneUSRecon.Logic.evaluation import evaluate_surface
    from BoneUSRecon.Logic.pipeline import ReconstructionParams, surface_from_contours

    sim = small_simulation(bone="tibia", n_frames=20, seed=13)
    _, _, surf = surface_from_contours(sim.contours_mm(), sim.sweep, ReconstructionParams())
    imaged = evaluate_surface(surf, sim.gold)
    swept_gold = sample_gold(sim, "swept")
    swept = evaluate_surface(surf, swept_gold)
    assert imaged.within_1 >= 0.995 and imaged.mean < 0.2
    far = _beyond_end_planes(sim, swept_gold) > 1.5
    assert far.sum() > 10 and np.median(swept.distances[far]) > 0.8


# -- corruption -----------------------------------------------------------------------------
def test_corrupted_frames_are_recorded_and_do_what_they_say(
    sim_small_corrupted, sim_factory
) -> None:
    sim = sim_small_corrupted
    clean = sim_factory(seed=1)  # same sweep without corruption
    n = sim.sweep.n_frames
    assert len(sim.corrupted) == round(0.1 * n)
    assert set(sim.corruption_kinds) == {int(k) for k in sim.corrupted}
    assert set(sim.corruption_kinds.values()) == set(CORRUPTION_KINDS)
    assert np.array_equal(sim.sweep.image_to_reference, clean.sweep.image_to_reference)
    sp = sim.params.spacing_mm
    for k in range(n):
        a = sim.sweep.frames[k].astype(float)
        b = clean.sweep.frames[k].astype(float)
        kind = sim.corruption_kinds.get(k)
        if kind is None:
            assert np.array_equal(a, b)
            continue
        c = clean.true_contours_px[k]
        i = c[:, 0].astype(int)
        top = int(np.floor(c[:, 1].min()))
        if kind == "contact_loss":
            assert len(sim.true_contours_px[k]) == 0
            assert a.mean() < 0.5 * b.mean()
            assert _band_means(a, c, 0.0).mean() < 60  # no bone line
        elif kind == "shadow_clutter":
            assert np.array_equal(sim.true_contours_px[k], c)
            below = _band_means(a, c, 4.0 / sp, half=int(3 / sp))
            below_clean = _band_means(b, c, 4.0 / sp, half=int(3 / sp))
            assert below.mean() > below_clean.mean() + 25
        elif kind == "false_echo":
            assert np.array_equal(sim.true_contours_px[k], c)
            diff = a[: top - 1, i[0] : i[-1] + 1] - b[: top - 1, i[0] : i[-1] + 1]
            assert diff.max() > 80  # a new bright echo above the bone...
            assert (diff < -40).mean() > 0.02  # ...with its shadow


def test_invalid_fraction_flags_frames(sim_factory) -> None:
    sw = sim_factory(n_frames=10, invalid_fraction=0.2, seed=2).sweep
    assert sw.n_valid == 8
    assert set(sw.invalid_reasons) == set(np.flatnonzero(~sw.valid).tolist())


@pytest.mark.parametrize(
    ("change", "message"),
    [
        ({"bone": "femur"}, "unknown bone"),
        ({"n_frames": -1}, "at least 2 frames"),
        ({"spacing_mm": 0.0}, "spacing"),
        ({"corrupted_fraction": 1.5}, "between 0 and 1"),
        ({"bone": "humerus", "height": 64, "spacing_mm": 0.15}, "mm deep"),
    ],
)
def test_bad_parameters_raise(change: dict, message: str) -> None:
    with pytest.raises(BoneUSReconError, match=message):
        simulate(SimulationParams(**{**TINY, **change}))


# -- files ------------------------------------------------------------------------------------
def test_written_files_round_trip(tmp_path, sim_factory) -> None:
    from BoneUSRecon.Logic.sequence_io import read_sweep
    from BoneUSRecon.Logic.vtkio import polydata_points, read_points, read_polydata

    sim = sim_factory(n_frames=12, corrupted_fraction=0.25, invalid_fraction=0.25, seed=4)
    paths = write_simulation(sim, tmp_path / "out" / "deeper")
    assert {p.name for p in paths.values()} == {
        "sweep.mha",
        "truth.vtp",
        "gold.csv",
        "simulation.json",
    }
    sw = read_sweep(paths["sweep"])
    assert np.array_equal(np.asarray(sw.frames), sim.sweep.frames)
    v = sim.sweep.valid  # the reader does not keep poses of frames flagged INVALID
    assert np.allclose(sw.image_to_reference[v], sim.sweep.image_to_reference[v], atol=1e-9)
    assert np.allclose(sw.timestamps, sim.sweep.timestamps, atol=1e-6)
    assert np.array_equal(sw.valid, sim.sweep.valid)
    truth = read_polydata(paths["truth"])
    assert truth.GetNumberOfCells() == len(sim.truth_faces)
    assert np.allclose(polydata_points(truth), sim.truth_vertices)
    gold = read_points(paths["gold"])
    assert paths["gold"].read_text().splitlines()[0] == "x,y,z"
    assert np.allclose(gold, sim.gold, atol=1e-5)
    info = json.loads(paths["json"].read_text())
    assert info["seed"] == 4 and info["parameters"]["bone"] == "clavicle"
    assert info["corrupted_frames"] == [int(k) for k in sim.corrupted]
    assert {int(k): v for k, v in info["corruption_kinds"].items()} == sim.corruption_kinds
    assert info["invalid_frames"] == np.flatnonzero(~sim.sweep.valid).tolist()
    assert "simulator_version" in info
    # Nothing else (no temporary files) left in the folder.
    assert sorted(p.name for p in paths["sweep"].parent.iterdir()) == sorted(
        p.name for p in paths.values()
    )


# -- CLI ---------------------------------------------------------------------------------------
def test_cli_simulate_writes_and_reports(tmp_path, capsys) -> None:
    out = tmp_path / "sim"
    rc = main(
        [
            "simulate",
            "radius",
            str(out),
            "--frames",
            "5",
            "--width",
            "64",
            "--height",
            "64",
            "--spacing",
            "0.6",
            "--corrupt",
            "0.4",
            "--seed",
            "3",
            "--reverse",
            "--json",
        ]
    )
    assert rc == 0
    info = json.loads(capsys.readouterr().out)
    assert info["frames"] == 5 and info["bone"] == "radius" and len(info["corrupted_frames"]) == 2
    for name in ("sweep.mha", "truth.vtp", "gold.csv", "simulation.json"):
        assert (out / name).stat().st_size > 0
    saved = json.loads((out / "simulation.json").read_text())
    assert saved["parameters"]["reverse"] is True and saved["neighbour"]["bone"] == "ulna"
    rc = main(
        [
            "simulate",
            "radius",
            str(tmp_path / "alone"),
            "--frames",
            "3",
            "--width",
            "64",
            "--height",
            "64",
            "--spacing",
            "0.6",
            "--no-neighbour",
            "-q",
        ]
    )
    assert rc == 0 and "Simulated radius sweep" in capsys.readouterr().out
    assert json.loads((tmp_path / "alone" / "simulation.json").read_text())["neighbour"] is None
    rc = main(
        ["simulate", "ulna", str(tmp_path / "near"), "--frames", "3", "--size", "64x64"]
        + ["--spacing", "0.6", "--neighbour-mm", "18", "-q"]
    )
    assert rc == 0
    saved = json.loads((tmp_path / "near" / "simulation.json").read_text())
    assert saved["neighbour"]["bone"] == "radius" and saved["neighbour"]["offset_mm"][1] == 18.0


@pytest.mark.parametrize(
    ("args", "message"),
    [
        (["femur"], "unknown bone 'femur'"),
        (["ulna", "--frames", "-4"], "at least 2 frames"),
        (["ulna", "--corrupt", "2"], "between 0 and 1"),
        (["ulna", "--spacing", "-0.1"], "spacing"),
        (["ulna", "--neighbour-mm", "0"], "neighbour_mm must be > 0"),
        (["humerus", "--neighbour-mm", "20"], "no bone beside the humerus"),
        (["tibia", "--neighbour-mm", "12"], "at least 18 mm"),
    ],
)
def test_cli_bad_input_one_line_exit_2(tmp_path, capsys, args: list[str], message: str) -> None:
    out = tmp_path / "never"
    rc = main(["simulate", args[0], str(out), *args[1:]])
    err = capsys.readouterr().err
    assert rc == 2
    assert err.count("\n") == 1 and err.startswith("bone-us-recon: error:") and message in err
    assert not out.exists()


def test_cli_output_folder_that_cannot_be_created(tmp_path, capsys) -> None:
    blocker = tmp_path / "a_file"
    blocker.write_text("x")
    rc = main(["simulate", "ulna", str(blocker / "sub"), "--frames", "3"])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and str(blocker) in err
    rc = main(["simulate", "ulna", str(blocker), "--frames", "3"])
    assert rc == 2 and "not a folder" in capsys.readouterr().err


def test_the_true_surface_reaches_as_far_as_the_frames_show_it() -> None:
    """An unsteady hand (tilt 12 degrees, 4 mm lateral jitter) near the sweep's start:
    frame 0's plane meets the bone's surface before the segment's start (s < 0), where
    the surface's formula still holds and the frame is drawn from it. Its true contour
    lies on the true surface; measured against ``[0, L]`` only, it lay mm off (the end
    ring), and the frame scores counted a contour on the bone there as wrong."""
    sim = small_simulation(
        bone="radius",
        seed=1,
        realism="hard",
        n_frames=12,
        tilt_deg=12.0,
        lateral_jitter_mm=4.0,
        depth_jitter_mm=2.0,
        speed_variation=0.8,
        **CADAVER,
    )
    assert sim.sections.s_range[0, 0] < 0.0  # the premise
    first = sim.contour_mm(0)
    assert np.median(sim.geometry.distance(first)) > 1.0  # to [0, L]: the end ring
    for k in range(sim.sweep.n_frames):
        if len(sim.true_contours_px[k]):
            assert sim.distance_to_truth(sim.contour_mm(k)).max() < 1e-3

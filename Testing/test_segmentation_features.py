"""Features of issue 10 item 5: confidence maps (Karamalis) and phase symmetry.

Known behaviour of each feature on images built for it, the confidence map against a
plain sparse solve of the same random-walk problem, and the optional evidence terms
switched on over a simulated sweep.
"""

from __future__ import annotations

import numpy as np
import pytest
import scipy.sparse as sp
from conftest import small_simulation
from scipy.sparse.linalg import spsolve

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation import ShadowPathParams, bone_evidence
from BoneUSRecon.Logic.segmentation.confidence import confidence_map
from BoneUSRecon.Logic.segmentation.phase import phase_symmetry_depth

H, W = 120, 60


def _tissue(rng: np.random.Generator) -> np.ndarray:
    return 0.4 + 0.1 * rng.standard_normal((H, W))


def _sparse_reference(img: np.ndarray, alpha=2.0, beta=90.0, gamma=0.05, pct=99.0) -> np.ndarray:
    """The random-walk problem assembled edge by edge and solved by SciPy's sparse LU."""
    h, w = img.shape
    c = img * np.exp(-alpha * np.linspace(0, 1, h))[:, None]
    idx = np.arange(h * w).reshape(h, w)
    edges = []
    for di, dj, g in [(1, 0, 0.0), (0, 1, gamma), (1, 1, 2**0.5 * gamma), (1, -1, 2**0.5 * gamma)]:
        c0, c1 = max(0, -dj), w - max(0, dj)
        a = idx[0 : h - di, c0:c1].ravel()
        b = idx[di:h, c0 + dj : c1 + dj].ravel()
        edges.append((a, b, np.abs(c.ravel()[a] - c.ravel()[b]), g))
    s = np.percentile(np.concatenate([e[2] for e in edges]), pct)
    rows = np.concatenate([e[0] for e in edges])
    cols = np.concatenate([e[1] for e in edges])
    vals = np.concatenate([np.exp(-beta * (np.minimum(e[2] / s, 1) + e[3])) + 1e-6 for e in edges])
    wm = sp.coo_matrix((vals, (rows, cols)), shape=(h * w, h * w)).tocsr()
    wm = wm + wm.T
    lap = (sp.diags(np.asarray(wm.sum(axis=1)).ravel()) - wm).tocsr()
    u = idx[1:-1].ravel()
    x = spsolve(lap[u][:, u].tocsc(), -(lap[u][:, idx[0]] @ np.ones(w)))
    out = np.zeros((h, w))
    out[0] = 1.0
    out[1:-1] = x.reshape(h - 2, w)
    return out


@pytest.mark.parametrize("shape", [(12, 1), (15, 2), (30, 17)])
def test_confidence_map_solves_the_random_walk(shape: tuple[int, int]) -> None:
    img = np.random.default_rng(1).random(shape)
    np.testing.assert_allclose(confidence_map(img), _sparse_reference(img), atol=1e-9)


def test_confidence_decays_monotonically_down_a_uniform_medium() -> None:
    conf = confidence_map(np.full((H, W), 0.4))
    assert np.all(np.diff(conf, axis=0) < 0)
    assert conf[0].min() == 1.0 and conf[-1].max() == 0.0
    # No reflector: the same in every column.
    assert np.ptp(conf, axis=1).max() < 1e-5


def test_confidence_collapses_under_a_bright_reflector_not_under_a_fascia() -> None:
    rng = np.random.default_rng(0)
    bone = _tissue(rng)
    bone[50:53, 15:45] = 1.0  # cortical echo over columns 15-44
    bone[53:, 15:45] = 0.05 + 0.02 * rng.random((H - 53, 30))  # its shadow
    fascia = _tissue(rng)
    fascia[50:51, 15:45] = 1.0  # a thin bright line, tissue beneath
    drops = {}
    for name, img in (("bone", bone), ("fascia", fascia), ("tissue", _tissue(rng))):
        logc = np.log(np.maximum(confidence_map(img), 1e-9))
        drops[name] = logc[46, 30] - logc[58, 30]  # 4 rows above to 8 rows under the line
    # Under bone the confidence falls by orders of magnitude; under the fascia about as
    # much as through plain tissue over the same depths.
    assert drops["bone"] > 5.0
    assert drops["fascia"] < 2.0 * drops["tissue"]
    assert drops["bone"] > 4.0 * drops["fascia"]


def test_confidence_map_rejects_too_few_rows() -> None:
    with pytest.raises(ValueError, match="at least 3 rows"):
        confidence_map(np.ones((2, 5)))


def test_phase_symmetry_peaks_on_a_line_whatever_its_contrast() -> None:
    rng = np.random.default_rng(2)
    dy = 0.25
    z = np.arange(H) * dy
    for contrast in (0.3, 3.0):
        img = 0.4 + 0.02 * rng.standard_normal((H, W))
        img += contrast * np.exp(-0.5 * ((z - 15.0) / 0.3) ** 2)[:, None]
        ps = phase_symmetry_depth(img, dy, (0.6, 1.2, 2.4))
        # The line is at row 60: the row of the highest median symmetry over the columns
        # (one speckle bump may be as symmetric as the line in one column: the measure
        # ignores amplitude, which is why it did not replace the echo log-ratio).
        assert abs(int(np.median(ps, axis=1).argmax()) - 60) <= 1
        assert np.median(ps[60]) > 0.8
        assert np.median(ps[30]) < 0.5  # 7.5 mm away: no line


def test_optional_terms_validated_and_off_by_default() -> None:
    p = ShadowPathParams()
    assert p.confidence_weight == 0.0 and p.phase_weight == 0.0
    for field in ("confidence_weight", "phase_weight"):
        with pytest.raises(BoneUSReconError, match=field):
            ShadowPathParams(**{field: 1.5})


def test_confidence_term_keeps_bone_shadow_and_opens_no_fascia() -> None:
    """Switched on, the confidence drop adds to the bone's shadow evidence, not a fascia's."""
    from BoneUSRecon.Logic.sweep import pixel_spacing

    sim = small_simulation(
        bone="tibia", n_frames=6, seed=5, realism="hard", hard_conditions=("fascia",)
    )
    spacing = pixel_spacing(sim.sweep.image_to_reference)
    on = ShadowPathParams(confidence_weight=1.0)
    bone_z = []
    for k in range(6):
        tc = sim.true_contours_px[k]
        if tc.shape[0] == 0:
            continue
        ev = bone_evidence(sim.sweep.frames[k], tuple(spacing[k]), on)
        i = np.clip(((tc[:, 0] + 0.5) / ev.fx - 0.5).round().astype(int), 0, ev.work.shape[1] - 1)
        j = np.clip(((tc[:, 1] + 0.5) / ev.fy - 0.5).round().astype(int), 0, ev.work.shape[0] - 1)
        bone_z.append(np.median(ev.shadow_z[j, i]))
    assert bone_z and np.median(bone_z) > 1.0  # the confidence collapses under the bone


@pytest.mark.parametrize("switch", [{"confidence_weight": 0.5}, {"phase_weight": 0.25}])
def test_switched_on_terms_still_segment_a_standard_sweep(switch: dict) -> None:
    """Each optional term, switched on, keeps the standard tibia on the bone (figures in
    Testing/benchmarks/README.md: 1.00 recall there with either)."""
    from BoneUSRecon.Logic.segmentation import SegmentationParams, segment_sweep
    from BoneUSRecon.Logic.simulation.scoring import score_simulation

    sim = small_simulation(bone="tibia", n_frames=12, seed=5)
    res = segment_sweep(sim.sweep, SegmentationParams(shadowpath=ShadowPathParams(**switch)))
    s = score_simulation(res, sim).summary()
    assert s["recall"] >= 0.9 and s["wrong_share"] == 0.0
    assert s["median_mm"] <= 0.1

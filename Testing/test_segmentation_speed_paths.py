"""The fast code paths of the segmenter give exactly what the plain ones give.

The speed-ups of branches ``segspeed`` (optimal path column loop, window means on row
slices, median of three) and ``speed`` (optimal paths of several frames in one column
loop, each with its own costs; cached window plans, one-partition medians of large even counts, percentiles and
medians of sorted rows, the track's pair tests from its boxes) must not change a single
candidate: each is compared here, value for value, with the straightforward computation
it replaces, on inputs built to hit its edge cases (ties, clipped windows, long no-bone
stretches).
"""

from __future__ import annotations

import numpy as np
import pytest
from numpy.lib.stride_tricks import sliding_window_view
from scipy.ndimage import median_filter

from BoneUSRecon.Logic.segmentation import track
from BoneUSRecon.Logic.segmentation.candidates import (
    _optimal_path,
    _optimal_paths,
    _underside_profile,
    convex_part,
    frame_candidates,
    frame_candidates_many,
)
from BoneUSRecon.Logic.segmentation.evidence import EvidenceMaps, _window_mean, bone_evidence
from BoneUSRecon.Logic.segmentation.features import (
    _ONE_KTH_FROM,
    column_window_mean,
    median1d,
    sorted_row_medians,
    sorted_row_percentiles,
)
from BoneUSRecon.Logic.segmentation.params import RejectionParams, ShadowPathParams
from BoneUSRecon.Logic.segmentation.rim import (
    _beam_edge,
    _beam_pixels,
    _beam_rows,
    _column_sums,
    _edge_ratio,
    _radius_paths,
)
from BoneUSRecon.Logic.segmentation.sampling import bilinear_at
from BoneUSRecon.Logic.segmentation.settle import onset_z
from BoneUSRecon.Logic.segmentation.track import (
    _in_plane_deviation,
    _links,
    _links_many,
    _project,
    _stepped,
)
from BoneUSRecon.Logic.simulation import SimulationParams, simulate
from BoneUSRecon.Logic.sweep import pixel_spacing


def _plain_optimal_path(gain: np.ndarray, shift_cost: np.ndarray, switch: float) -> np.ndarray:
    """The optimal path as it was computed before the speed-up (every column in full)."""
    h, w = gain.shape
    n = shift_cost.size
    d = n // 2
    score = np.full((w, h + 2 * d), -np.inf)
    score[:, d : d + h] = gain.T
    win = sliding_window_view(score, n, axis=1).transpose(0, 2, 1)
    null_before = np.zeros(w)
    null_back = np.full(w, -1, dtype=np.intp)
    null = 0.0
    for c in range(1, w):
        prev = score[c - 1, d : d + h]
        cand = np.vstack([win[c - 1] - shift_cost[:, None], np.full((1, h), null - switch)])
        null_before[c] = null
        jb = int(prev.argmax())
        if prev[jb] - switch > null:
            null = prev[jb] - switch
            null_back[c] = jb
        score[c, d : d + h] += cand.max(axis=0)
    path = np.full(w, -1, dtype=np.intp)
    last = score[w - 1, d : d + h]
    jb = int(last.argmax())
    state = jb if last[jb] > null else -1
    for c in range(w - 1, -1, -1):
        path[c] = state
        if c == 0:
            break
        if state >= 0:
            v = score[c - 1, state : state + n] - shift_cost
            k = int(v.argmax())
            state = -1 if null_before[c] - switch > v[k] else state + k - d
        else:
            state = int(null_back[c])
    return path


def test_optimal_path_matches_plain_loop() -> None:
    rng = np.random.default_rng(3)
    steps = np.arange(-3, 4)
    with_bone = 0
    for trial in range(300):
        h, w = int(rng.integers(3, 40)), int(rng.integers(2, 60))
        # Coarse values make ties; long negative stretches take the no-bone shortcut.
        gain = np.round(rng.normal(-0.4, 1.0, (h, w)) * 4) / 4
        gain[:, rng.random(w) < 0.4] = -1.0
        gain = gain.astype(np.float32)
        cost = 0.05 * (steps * rng.uniform(0.5, 2.0)) ** 2 * 0.3
        switch = float(rng.choice([0.5, 1.0, 2.0]))
        fast = _optimal_path(gain.copy(), cost, switch)
        plain = _plain_optimal_path(gain.copy(), cost, switch)
        assert np.array_equal(fast, plain), trial
        with_bone += bool((fast >= 0).any() and (fast < 0).any())
    assert with_bone >= 100  # the trials exercise paths that enter and leave bone


def test_optimal_path_no_bone_shortcut_matches_plain_loop() -> None:
    # Where the columns' best gains sum to at most half the switch cost the no-bone
    # score never rises and _optimal_path skips its bookkeeping (the band traces of the
    # series' tops, switch 1e6): the same paths as the plain loop, at the shortcut's
    # edge too (sums just under and over half the switch).
    rng = np.random.default_rng(4)
    steps = np.arange(-2, 3)
    taken = 0
    for trial in range(300):
        h, w = int(rng.integers(2, 30)), int(rng.integers(2, 40))
        gain = (np.round(rng.normal(0.0, 1.0, (h, w)) * 4) / 4).astype(np.float32)
        cost = 0.05 * steps.astype(float) ** 2
        best = float(np.maximum(gain.max(axis=0), 0.0).sum())
        switch = 1e6 if trial % 3 == 0 else 2.0 * best * float(rng.choice([0.9, 1.0, 1.1]))
        switch = max(switch, 1e-3)
        taken += best <= 0.5 * switch
        fast = _optimal_path(gain.copy(), cost, switch)
        plain = _plain_optimal_path(gain.copy(), cost, switch)
        assert np.array_equal(fast, plain), trial
    assert 100 <= taken < 300  # both sides of the shortcut exercised


def test_optimal_paths_batch_matches_plain_loop() -> None:
    # Several gains of different sizes solved together: each path as if alone.
    rng = np.random.default_rng(9)
    steps = np.arange(-3, 4)
    with_bone = 0
    for trial in range(60):
        cost = 0.05 * (steps * rng.uniform(0.5, 2.0)) ** 2 * 0.3
        switch = float(rng.choice([0.5, 1.0, 2.0]))
        gains = []
        for _ in range(int(rng.integers(2, 7))):
            h, w = int(rng.integers(1, 40)), int(rng.integers(1, 60))
            gain = np.round(rng.normal(-0.4, 1.0, (h, w)) * 4) / 4
            gain[:, rng.random(w) < 0.4] = -1.0
            gains.append(gain.astype(np.float32))
        batch = _optimal_paths([g.copy() for g in gains], cost, switch)
        for g, path in zip(gains, batch, strict=True):
            assert np.array_equal(path, _plain_optimal_path(g.copy(), cost, switch)), trial
            with_bone += bool((path >= 0).any() and (path < 0).any())
    assert with_bone >= 60


def test_optimal_paths_with_own_costs_match_plain_loop() -> None:
    # Gains solved together, each with its own shift costs (frames whose spacings differ,
    # if only in the last bits): each path as if alone with its costs.
    rng = np.random.default_rng(11)
    steps = np.arange(-2, 3)
    with_bone = 0
    scratch: dict = {}
    for trial in range(60):
        switch = float(rng.choice([0.5, 1.0, 2.0]))
        gains, costs = [], []
        for _ in range(int(rng.integers(2, 7))):
            h, w = int(rng.integers(1, 40)), int(rng.integers(1, 60))
            gain = np.round(rng.normal(-0.4, 1.0, (h, w)) * 4) / 4
            gain[:, rng.random(w) < 0.4] = -1.0
            gains.append(gain.astype(np.float32))
            # Costs far apart (other paths) or a hair apart (the same spacing from poses);
            # every third trial, of different sizes (3, 5 or 7 shifts).
            scale = rng.uniform(0.5, 2.0) if trial % 2 else 1.0 + 1e-15 * rng.integers(0, 3)
            st = np.arange(-(k := int(rng.integers(1, 4))), k + 1) if trial % 3 == 0 else steps
            costs.append(0.05 * (st * scale) ** 2 * 0.3)
        # One scratch for all trials: its scores' array reused, larger or smaller.
        batch = _optimal_paths([g.copy() for g in gains], costs, switch, scratch)
        for g, c, path in zip(gains, costs, batch, strict=True):
            assert np.array_equal(path, _plain_optimal_path(g.copy(), c, switch)), trial
            assert np.array_equal(path, _optimal_path(g.copy(), c, switch)), trial
            with_bone += bool((path >= 0).any() and (path < 0).any())
    assert with_bone >= 40


def test_optimal_paths_shifts_in_pairs_match_plain_loop() -> None:
    # Branch speed3 (session 26): each column takes the better of shifts -k and +k, then
    # subtracts their one cost. As in a batch of the pipeline: 9 and 7 shifts mixed
    # (one shift count padded with +inf), many exact ties (quarter steps), exact zeros
    # of both signs in the gains, long no-bone stretches, and one scratch for all trials.
    rng = np.random.default_rng(17)
    scratch: dict = {}
    with_bone = 0
    for trial in range(40):
        switch = float(rng.choice([0.5, 1.0]))
        gains, costs = [], []
        for _ in range(int(rng.integers(3, 9))):
            h, w = int(rng.integers(2, 30)), int(rng.integers(2, 50))
            gain = np.round(rng.normal(-0.3, 1.0, (h, w)) * 4) / 4
            gain[:, rng.random(w) < 0.3] = -1.0
            gain[rng.random((h, w)) < 0.05] = -0.0
            gains.append(gain.astype(np.float32))
            k = int(rng.choice([3, 4]))
            costs.append(0.015 * np.arange(-k, k + 1) ** 2.0)
        batch = _optimal_paths([g.copy() for g in gains], costs, switch, scratch)
        for g, c, path in zip(gains, costs, batch, strict=True):
            assert np.array_equal(path, _plain_optimal_path(g.copy(), c, switch)), trial
            with_bone += bool((path >= 0).any() and (path < 0).any())
    assert with_bone >= 60
    # Costs that differ between -k and +k cannot be paired, and no shift is taken at its
    # score itself: other costs are refused.
    for cost in ([0.1, 0.0, 0.2], [0.1, 0.05, 0.1]):
        with pytest.raises(ValueError, match="symmetric"):
            _optimal_paths([np.zeros((3, 4), np.float32)] * 2, np.array(cost), 1.0)


def test_underside_profile_matches_plain_median() -> None:
    # Branch speed3 (session 26): the shifted contour's values gathered by flat index.
    # Against the plain 2-D index and np.median, on contours running off the image's
    # top and bottom (clipped rows, NaN where most columns are outside), with and
    # without ``only``, over and under 48 columns (every n-th column).
    rng = np.random.default_rng(26)
    for trial in range(200):
        h, w = int(rng.integers(5, 60)), int(rng.integers(3, 120))
        lr = rng.normal(size=(h, w)).astype(np.float32)
        cols = np.sort(rng.choice(w, int(rng.integers(1, w + 1)), replace=False))
        rows = rng.integers(-3, h + 3, cols.size).clip(0, h - 1)
        reach = int(rng.integers(1, 12))
        only = rng.choice(w, int(rng.integers(1, w + 1)), replace=False) if trial % 2 else None
        c = {"cols": cols, "rows": rows}
        fast = _underside_profile(lr, c, reach, only)
        # Plain: the same columns, each shifted row read by a 2-D index, np.median.
        m = np.isin(cols, only) if only is not None else np.ones(cols.size, bool)
        pc, pr = cols[m], rows[m]
        if pc.size > 48:
            step = int(np.ceil(pc.size / 48))
            pc, pr = pc[::step], pr[::step]
        plain = np.full(2 * reach + 1, np.nan)
        for i, k in enumerate(range(-reach, reach + 1)):
            if pc.size and 2 * ((pr + k >= 0) & (pr + k < h)).sum() >= pc.size:
                vals = lr[np.clip(pr + k, 0, h - 1), pc]
                # The upper median of the sorted values, as the partition at size // 2.
                plain[i] = float(np.sort(vals)[pc.size // 2])
        assert np.array_equal(fast, plain, equal_nan=True), trial


def _plain_bilinear_at(a: np.ndarray, x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """sampling.bilinear_at as it was before branch speed3 (each neighbour by indexing)."""
    h, w = a.shape
    x = np.clip(x, 0, w - 1.000001)
    y = np.clip(y, 0, h - 1.000001)
    x0, y0 = x.astype(np.intp), y.astype(np.intp)
    x -= x0
    y -= y0
    i = y0 * w + x0
    flat = a.ravel()
    v00, v01, v10, v11 = flat[i], flat[i + 1], flat[i + w], flat[i + w + 1]
    if flat.dtype.kind != "f":
        v00, v01, v10, v11 = (c.astype(np.float32) for c in (v00, v01, v10, v11))
    top = v01 - v00
    top *= x
    top += v00
    bot = v11 - v10
    bot *= x
    bot += v10
    bot -= top
    bot *= y
    bot += top
    return bot


def test_bilinear_at_matches_plain_indexing() -> None:
    # Grey (uint8) and float images, points inside, on the last row and column and
    # outside (clamped), of 1-D and 2-D shapes.
    rng = np.random.default_rng(6)
    for trial in range(100):
        h, w = int(rng.integers(2, 30)), int(rng.integers(2, 30))
        a = rng.integers(0, 256, (h, w)).astype(np.uint8)
        a = a if trial % 2 else (a / 255.0).astype(np.float32)
        shape = (int(rng.integers(1, 40)),) if trial % 3 else (5, int(rng.integers(1, 9)))
        x = rng.uniform(-2.0, w + 1.0, shape)
        y = rng.uniform(-2.0, h + 1.0, shape)
        x.flat[0], y.flat[0] = w - 1.0, h - 1.0
        fast = bilinear_at(a, x.copy(), y.copy())
        assert fast.dtype == np.float32
        assert np.array_equal(fast, _plain_bilinear_at(a, x.copy(), y.copy())), trial


def test_frame_candidates_many_matches_one_by_one() -> None:
    # Frames with bone, an empty frame and one too small: the same candidates as alone.
    sim = simulate(SimulationParams(n_frames=5, width=160, height=128, seed=3))
    images = [sim.sweep.frames[k] for k in range(5)]
    images += [np.zeros((128, 160), np.uint8), np.zeros((4, 4), np.uint8)]
    sp = pixel_spacing(sim.sweep.image_to_reference)
    # Spacings a hair apart (as from poses): the paths are still solved together.
    spacings = [(float(sp[0, 0]) * (1 + 1e-16 * k), float(sp[0, 1])) for k in range(len(images))]
    many = frame_candidates_many(images, spacings)
    assert sum(len(fc.candidates) for fc in many) >= 5
    for img, s, got in zip(images, spacings, many, strict=True):
        want = frame_candidates(img, s)
        assert (got.reason, got.spacing, got.extras) == (want.reason, want.spacing, want.extras)
        assert len(got.candidates) == len(want.candidates)
        for a, b in zip(got.candidates, want.candidates, strict=True):
            assert np.array_equal(a.points_px, b.points_px)
            assert np.array_equal(a.intensity, b.intensity)
            assert (a.strength, a.echo_z, a.shadow_z) == (b.strength, b.echo_z, b.shadow_z)
            assert (a.reverberation, a.echo_beneath) == (b.reverberation, b.echo_beneath)


def test_window_mean_matches_gathered_rows() -> None:
    rng = np.random.default_rng(4)
    # Two images per size and widths 5 and 1 (the per-row references): the cached index
    # plan of a size and offsets is reused on new data.
    for h, width in ((1, 5), (4, 5), (23, 5), (23, 1), (4, 5), (23, 5)):
        x = rng.random((h, width)).astype(np.float32)
        csum = np.zeros((h + 1, width), np.float32)
        np.cumsum(x, axis=0, out=csum[1:])
        j = np.arange(h)
        for a in range(-h - 2, h + 3):
            for b in range(-h - 2, h + 3):
                assert np.array_equal(
                    _window_mean(csum, a, b), column_window_mean(csum, j + a, j + b)
                ), (h, a, b)


def test_median1d_matches_numpy_median() -> None:
    # Both paths of median1d (two-kth partition below _ONE_KTH_FROM values, one
    # partition and a maximum from there on), even and odd counts, ties, dtypes.
    rng = np.random.default_rng(6)
    sizes = [1, 2, 3, 10, 41, _ONE_KTH_FROM - 2, _ONE_KTH_FROM, _ONE_KTH_FROM + 1, 5000]
    for n in sizes:
        for dtype in (np.float32, np.float64, np.int64):
            for values in (rng.normal(size=n), np.round(rng.normal(size=n) * 2)):
                a = values.astype(dtype)
                got = median1d(a)
                assert got == float(np.median(a)), (n, dtype)
                assert np.array_equal(a, values.astype(dtype))  # input left as it was


def test_median_of_three_is_median_filter() -> None:
    # The formula used by candidates._refine for the usual 3-column lateral median.
    rng = np.random.default_rng(5)
    for n in (3, 4, 9, 200):
        j = np.round(rng.normal(0, 3, n))  # repeated values
        pj = np.concatenate((j[:1], j, j[-1:]))
        a, b, c = pj[:-2], pj[1:-1], pj[2:]
        m = np.maximum(np.minimum(a, b), np.minimum(np.maximum(a, b), c))
        assert np.array_equal(m, median_filter(j, size=3, mode="nearest"))


def _plain_stepped(a: np.ndarray, b_mm: np.ndarray, max_step_mm: float) -> bool:
    """track._stepped as it was before branch ``speed`` (shares by ``mean``)."""
    lo, hi = a[:, 0].min(), a[:, 0].max()
    bi = b_mm[(b_mm[:, 0] >= lo) & (b_mm[:, 0] <= hi)]
    if bi.shape[0] == 0:
        return False
    o = np.argsort(a[:, 0])
    step = bi[:, 1] - np.interp(bi[:, 0], a[o, 0], a[o, 1])
    return bool(
        abs(np.median(step)) > max_step_mm and max((step > 0).mean(), (step < 0).mean()) >= 0.9
    )


def test_track_pair_shortcuts_match_plain() -> None:
    # _links hands the pair tests its boxes' extents and a's lateral order; the
    # results must be those computed from the contours alone (and _stepped's shares
    # by counting those of the plain means), on contours that overlap partly, lie
    # a step under one another, or have repeated lateral positions.
    rng = np.random.default_rng(7)
    hits = 0
    for trial in range(400):
        ka, kb = int(rng.integers(2, 60)), int(rng.integers(1, 60))
        ax = np.sort(rng.uniform(0, 20, ka)) if trial % 3 else np.round(rng.uniform(0, 20, ka))
        a = np.column_stack([ax, rng.normal(10, 0.5, ka), rng.uniform(0, 3, ka)])
        bx = rng.uniform(-5, 25, kb)
        b = np.column_stack([bx, rng.normal(10 + rng.choice([0.0, 2.0, 5.0]), 0.5, kb)])
        a_x = (float(a[:, 0].min()), float(a[:, 0].max()))
        b_x = (float(b[:, 0].min()), float(b[:, 0].max()))
        plain = _in_plane_deviation(a, b)
        fast = _in_plane_deviation(a, b, a_x=a_x, b_x=b_x)
        assert np.array_equal(np.array(plain), np.array(fast)), trial
        o = np.argsort(a[:, 0])
        for step in (0.5, 1.5, 3.0):
            want = _plain_stepped(a, b, step)
            assert _stepped(a, b, step) == want, trial
            assert _stepped(a, b, step, a_x=a_x, a_sorted=(a[o, 0], a[o, 1])) == want, trial
            hits += want
    assert hits >= 50  # the trials exercise stepped pairs too


def _plain_links(a_ref, plane, b_nodes, p):  # type: ignore[no-untyped-def]
    """track._links as it was before branch ``speed``'s session 24: pair by pair."""
    a = _project(a_ref, *plane)
    out = []
    for i, (b, _) in enumerate(b_nodes):
        d, share, z = _in_plane_deviation(a, b)
        if share < p.min_overlap_share or not np.isfinite(d):
            continue
        tol = p.tolerance_mm + p.tolerance_per_mm * z
        if d > p.max_deviation * tol:
            continue
        if _plain_stepped(a, b, p.max_step_mm + p.step_per_mm * z):
            continue
        out.append((i, d / tol))
    return out


def test_links_of_many_contours_match_pair_by_pair() -> None:
    # _links_many measures all pairs of contours together (padded, masked medians):
    # the same edges, in the same order, with the same deviations as one pair at a time,
    # on contours of different sizes that overlap partly, lie a step under one another,
    # lie apart, have even and odd numbers of points beside each other, repeated
    # lateral positions; also in chunks smaller than the pairs (the memory bound).
    rng = np.random.default_rng(12)
    p = RejectionParams()
    edges = stepped = 0
    for trial in range(150):
        q, _ = np.linalg.qr(rng.normal(size=(3, 3)))
        plane = (rng.normal(0, 5, 3), q[:, :2].copy(), q[:, 2].copy())
        b_nodes = []
        for _ in range(int(rng.integers(1, 6))):
            kb = int(rng.integers(1, 40))
            bx = np.sort(rng.uniform(0, 20, kb))
            b = np.column_stack([bx, rng.normal(10 + rng.choice([0.0, 1.0, 5.0]), 0.3, kb)])
            box = (float(bx.min()), float(bx.max()), float(b[:, 1].min()), float(b[:, 1].max()))
            b_nodes.append((b, box))
        a_refs = []
        for _ in range(int(rng.integers(0, 7))):
            ka = int(rng.integers(1, 40))
            ax = rng.uniform(-5, 25, ka) if trial % 3 else np.round(rng.uniform(0, 20, ka))
            loc = np.column_stack([ax, rng.normal(10 + rng.choice([0.0, 4.0]), 0.3, ka)])
            # Back to reference mm through the plane, a little out of it.
            off = rng.uniform(0, 3, ka)
            a_refs.append(plane[0] + loc @ plane[1].T + off[:, None] * plane[2])
        want = [_plain_links(a, plane, b_nodes, p) for a in a_refs]
        assert _links_many(a_refs, plane, b_nodes, p) == want, trial
        assert [_links(a, plane, b_nodes, p) for a in a_refs] == want, trial
        if trial % 10 == 0:
            old, track._PAIR_CHUNK = track._PAIR_CHUNK, 40 * 40 * 2
            try:
                assert _links_many(a_refs, plane, b_nodes, p) == want, trial
            finally:
                track._PAIR_CHUNK = old
        edges += sum(len(w) for w in want)
        stepped += sum(
            _plain_stepped(_project(a, *plane), b, p.max_step_mm)
            for a in a_refs
            for b, _ in b_nodes
        )
    assert edges >= 100 and stepped >= 20  # both outcomes exercised


def _plain_radius_paths(e: np.ndarray, start: int, ms: int) -> np.ndarray:
    """rim's Viterbi as it was before branch ``speed``'s session 24 (stacked views)."""
    n_tr, n_step, nb = e.shape
    acc = np.full((n_tr, nb + 2 * ms), -np.inf)
    acc[:, ms + start] = e[:, 0, start]
    back = np.zeros((n_step, n_tr, nb), np.int8)
    rows_, cols_ = np.arange(n_tr)[:, None], np.arange(nb)[None, :]
    for t in range(1, n_step):
        views = np.stack([acc[:, ms + k : ms + k + nb] for k in range(-ms, ms + 1)])
        k = views.argmax(axis=0)
        new = views[k, rows_, cols_]
        new += e[:, t]
        acc[:, ms : ms + nb] = new
        back[t] = k - ms
    path = np.empty((n_tr, n_step), np.intp)
    path[:, -1] = acc[:, ms : ms + nb].argmax(axis=1)
    tt = np.arange(n_tr)
    for t in range(n_step - 1, 0, -1):
        path[:, t - 1] = path[:, t] + back[t, tt, path[:, t]]
    return path


def test_rim_radius_paths_match_stacked_views() -> None:
    # Coarse scores (ties between moves) and the rim's "outside" value -1e3 in runs.
    # (Branch speed2, session 25: the traces in one run, no moves stored.)
    rng = np.random.default_rng(13)
    for trial in range(600):
        n_tr, n_step, nb = (
            int(rng.integers(1, 9)),
            int(rng.integers(1, 40)),
            int(rng.integers(1, 50)),
        )
        e = np.round(rng.normal(0, 1, (n_tr, n_step, nb)) * 2) / 2
        e[rng.random(e.shape) < 0.1] = -1e3
        e[rng.random(e.shape) < 0.05] = -0.0  # ties of signed zeros
        ms, start = int(rng.integers(1, 4)), int(rng.integers(0, nb))
        assert np.array_equal(_radius_paths(e, start, ms), _plain_radius_paths(e, start, ms)), trial


def _plain_beam_edge(work, level, wi, wj, rows, dark, gap=0.0):  # type: ignore[no-untyped-def]
    """rim's edge along the beam as it was before branch ``speed2`` (session 25): the
    column sums of the whole working image, every point on its own."""
    h, w = work.shape
    cu = np.zeros((h + 1, w))
    np.cumsum(np.minimum(work, level[:, None]), axis=0, out=cu[1:])
    cw = np.zeros((h + 1, w))
    np.cumsum(work, axis=0, out=cw[1:])
    k, o = max(1, int(round(rows))), int(round(gap))
    col = np.rint(np.clip(wi, 0, w - 1)).astype(np.intp)
    row = np.rint(np.clip(wj, 0, h - 1)).astype(np.intp)
    a0, a1 = np.clip(row - o - k, 0, h), np.clip(row - o, 0, h)
    b0, b1 = np.minimum(row + 1 + o, h), np.minimum(row + 1 + o + k, h)
    na, nb = np.maximum(a1 - a0, 1), np.maximum(b1 - b0, 1)
    cap = (cu[a1, col] - cu[a0, col]) / na
    raw = (cw[a1, col] - cw[a0, col]) / na
    below = (cw[b1, col] - cw[b0, col]) / nb
    return _edge_ratio(raw, cap, below, dark)


def test_rim_beam_edge_per_pixel_matches_every_point() -> None:
    # Points inside, on and outside the image (clipped to its edge), many on one pixel;
    # windows clipped at the top and bottom; the sums cut at the deepest window.
    rng = np.random.default_rng(25)
    for trial in range(60):
        h, w = int(rng.integers(8, 90)), int(rng.integers(3, 120))
        work = rng.gamma(2.0, 0.1, (h, w)).astype(np.float32)
        work[rng.random((h, w)) < 0.05] = 0.0
        level = np.float32(rng.uniform(0.1, 0.4, h))
        ev = EvidenceMaps(
            work, work, 2, 2, 0.3, 0.3, np.ones(w, bool), level, work, work, work, level, 0.0
        )
        shape = tuple(int(v) for v in rng.integers(1, 12, 3))
        wi = rng.uniform(-3, w + 2, shape)
        wj = rng.uniform(-3, rng.uniform(0, h + 2), shape)
        row, col, at = _beam_pixels((h, w), wi, wj)
        assert row.size == np.unique(row * w + col).size
        windows = [(float(rng.uniform(0, 6)), float(rng.uniform(0, 4))) for _ in range(2)]
        reach = max(sum(_beam_rows(*win)) for win in windows)
        sums, at_col = _column_sums(ev, col, min(h, int(row.max()) + 1 + reach))
        for rows, gap in windows:
            fast = _beam_edge(sums, row, at_col, h, rows, 0.02, gap)[at]
            plain = _plain_beam_edge(work, level, wi, wj, rows, 0.02, gap)
            assert fast.shape == shape and np.array_equal(fast, plain), trial


def test_onset_on_some_columns_matches_the_whole_width() -> None:
    # settle's onset on the points' columns only (branch speed2, session 25): the column
    # sums of those and of the scale's sample only; the same values as over every column.
    sim = simulate(SimulationParams(bone="tibia", seed=3, realism="hard", n_frames=2))
    rng = np.random.default_rng(4)
    for image in sim.sweep.frames:
        ev = bone_evidence(np.asarray(image), (0.3, 0.3), ShadowPathParams())
        assert ev is not None
        h, w = ev.work.shape
        for rows in ((0, h), (5, 40), (h - 9, h + 3)):
            whole = onset_z(ev, (0.3, 1.2), rows)
            for size in (1, 7, w):
                cols = np.sort(rng.choice(w, size, replace=False))
                assert np.array_equal(onset_z(ev, (0.3, 1.2), rows, cols=cols), whole[:, cols])


def _plain_convex_part(points_px, spacing, p):  # type: ignore[no-untyped-def]
    """candidates.convex_part as it was before branch ``speed2`` (session 25): index
    arrays for each side, every quantity gathered by them; with the inward window's
    span asked as the outward one's, or a drop of valley_mm (session 34: a grain over
    the top is no flank)."""
    n = points_px.shape[0]
    keep = np.ones(n, bool)
    if n < 6:
        return keep
    x = points_px[:, 0] * float(spacing[0])
    z = points_px[:, 1] * float(spacing[1])
    span = x.max() - x.min()
    mid = (x >= x.min() + 0.2 * span) & (x <= x.max() - 0.2 * span)
    top = int(np.flatnonzero(mid)[np.argmin(z[mid])]) if mid.any() else int(np.argmin(z))
    for side in (-1, 1):
        idx = np.arange(top, -1, -1) if side < 0 else np.arange(top, n)
        if idx.size < 4:
            continue
        xo, zo = np.abs(x[idx] - x[top]), z[idx]
        k = np.arange(1, xo.size - 1)
        lo = np.searchsorted(xo, xo[k] - p.kink_mm, side="left")
        hi = np.searchsorted(xo, xo[k] + p.kink_mm, side="right") - 1
        s_in = (zo[k] - zo[lo]) / np.maximum(xo[k] - xo[lo], 1e-6)
        s_out = (zo[hi] - zo[k]) / np.maximum(xo[hi] - xo[k], 1e-6)
        ok = (k - lo >= 1) & (hi - k >= 1) & (xo[hi] - xo[k] >= 0.5 * p.kink_mm)
        ok &= (xo[k] - xo[lo] >= 0.5 * p.kink_mm) | (zo[k] - zo[lo] >= p.valley_mm)
        cut = np.flatnonzero(ok & (s_in >= p.kink_slope) & (s_out < s_in / 3.0))
        if cut.size:
            keep[idx[k[cut[0]] + 1 :]] = False
    return keep


def test_convex_part_matches_index_arrays() -> None:
    # Domes, walks and short contours; most are cut on one side or both.
    rng = np.random.default_rng(25)
    p = ShadowPathParams()
    cut = 0
    for trial in range(1500):
        n = int(rng.integers(1, 150))
        cols = np.sort(rng.choice(400, n, replace=False)).astype(float)
        rows = 100 + np.cumsum(rng.normal(0, rng.uniform(0.5, 8), n))
        if trial % 3 == 0:
            rows = 100 + 0.02 * (cols - cols.mean()) ** 2 + rng.normal(0, 1, n)
        pts = np.column_stack([cols, rows])
        fast = convex_part(pts, (0.15, 0.12), p)
        assert np.array_equal(fast, _plain_convex_part(pts, (0.15, 0.12), p)), trial
        cut += not fast.all()
    assert cut > 500


def test_one_sorted_row_percentile_matches_numpy_1d() -> None:
    # candidates._is_copy reads its 90th percentile (float64) from one sorted row:
    # np.percentile's 1-D value. (Not float32: 1-D np.percentile interpolates a float32
    # array in float32, the rows' version in float64; the evidence baseline, float32,
    # keeps np.percentile.)
    rng = np.random.default_rng(14)
    for trial in range(400):
        n = int(rng.integers(1, 200))
        x = rng.gamma(2.0, 0.3, n)
        if trial % 3 == 0:
            x = np.round(x * 4) / 4
        for q in (75.0, 90.0):
            want = np.percentile(x, q)
            got = sorted_row_percentiles(np.sort(x)[None, :], (q,))[0, 0]
            assert got.dtype == want.dtype and got == want, (trial, q)


def test_sorted_row_statistics_match_numpy() -> None:
    # The tissue level's percentiles and the baseline's row medians, read from rows
    # sorted once, against numpy on the same sorted rows (both dtypes, ties, the ends).
    rng = np.random.default_rng(8)
    qs = [(60.0, 80.0), (50.0,), (0.0, 100.0), (33.3, 97.5), (12.5, 87.5, 99.9)]
    for trial in range(600):
        h, n = int(rng.integers(1, 30)), int(rng.integers(1, 130))
        x = rng.gamma(2.0, 0.2, (h, n)).astype(np.float32 if trial % 2 else np.float64)
        if trial % 3 == 0:
            x = np.round(x * 4) / 4
        s = np.sort(x, axis=1)
        q = qs[trial % len(qs)]
        want = np.percentile(s.copy(), q, axis=1)
        got = sorted_row_percentiles(s, q)
        assert got.dtype == want.dtype and np.array_equal(got, want), (trial, q)
        med = np.median(s, axis=1)
        got_med = sorted_row_medians(s)
        assert got_med.dtype == med.dtype and np.array_equal(got_med, med), trial


def _plain_segment_sweep(sweep, params):  # type: ignore[no-untyped-def]
    """segment_sweep as it was before branch ``speed`` (session 21): the whole track
    chosen again after recovery, every searched frame's evidence computed again."""
    from BoneUSRecon.Logic.segmentation.driver import contours_from_track
    from BoneUSRecon.Logic.segmentation.ends import cut_bone_free_ends
    from BoneUSRecon.Logic.segmentation.recovery import recover_frames, settings
    from BoneUSRecon.Logic.segmentation.track import select_bone_track

    idx = sweep.valid_indices
    sp = pixel_spacing(sweep.image_to_reference)
    spacings = [(float(sp[k, 0]), float(sp[k, 1])) for k in idx]
    frames = frame_candidates_many([sweep.frames[k] for k in idx], spacings, params.shadowpath)
    poses = sweep.image_to_reference[idx]
    choice = select_bone_track(frames, poses, params.rejection)
    frames, searched = recover_frames(
        frames,
        choice,
        poses,
        lambda n: sweep.frames[int(idx[n])],
        params.shadowpath,
        params.rejection,
        settings(params),
    )
    if searched:
        choice = select_bone_track(frames, poses, params.rejection)
    choice = cut_bone_free_ends(frames, choice, lambda ns: (sweep.frames[k] for k in idx[ns]))
    return contours_from_track(idx, frames, choice, params), searched


def test_segment_sweep_track_and_kept_evidence_match_plain(monkeypatch) -> None:  # type: ignore[no-untyped-def]
    # segment_sweep chooses the track with IncrementalTrack (links made once, only the
    # guided candidates linked after recovery) and hands the recovery the evidence maps
    # kept from the per-frame step (when all of them fit EVIDENCE_CACHE_BYTES): the
    # same contours, decisions and details as the plain flow, with and without kept
    # evidence; kept, recovery computes none again.
    import BoneUSRecon.Logic.segmentation.driver as driver
    import BoneUSRecon.Logic.segmentation.recovery as recovery
    from BoneUSRecon.Logic.segmentation import SegmentationParams, segment_sweep

    # Hard tibia (grey shadow) with bone-free ends: the first track leaves frames for
    # recovery to search (past its ends too), and the ends cut has frames to judge.
    # Seed 2 since session 34 (seed 7's track then had a frame the recheck of straying
    # track frames replaces, a step this plain flow does not take).
    sim = simulate(
        SimulationParams(
            bone="tibia",
            realism="hard",
            seed=2,
            n_frames=40,
            width=160,
            height=128,
            spacing_mm=0.3,
            bone_free_frames=(3, 10),
        )
    )
    params = SegmentationParams()
    want, searched = _plain_segment_sweep(sim.sweep, params)
    assert len(searched) >= 1  # recovery found candidates in frames off the first track
    computed = []
    real = recovery.bone_evidence

    def counting(*args, **kwargs):  # type: ignore[no-untyped-def]
        computed.append(1)
        return real(*args, **kwargs)

    monkeypatch.setattr(recovery, "bone_evidence", counting)
    idx = sim.sweep.valid_indices
    sp = pixel_spacing(sim.sweep.image_to_reference)[idx[0]]
    whole = idx.size * real(sim.sweep.frames[idx[0]], (float(sp[0]), float(sp[1]))).nbytes
    # Kept when all of the sweep's maps fit, else none (a long sweep's peak memory).
    for room, computed_again in (
        (driver.EVIDENCE_CACHE_BYTES, False),
        (whole, False),
        (whole - 1, True),
        (0, True),
    ):
        monkeypatch.setattr(driver, "EVIDENCE_CACHE_BYTES", room)
        computed.clear()
        got = segment_sweep(sim.sweep, params).contours
        assert bool(computed) == computed_again
        assert len(got) == len(want)
        for a, b in zip(got, want, strict=True):
            assert np.array_equal(a.points_px, b.points_px)
            assert np.array_equal(a.intensity, b.intensity)
            assert (a.frame, a.accepted, a.reason, a.detail, a.confidence) == (
                b.frame,
                b.accepted,
                b.reason,
                b.detail,
                b.confidence,
            )
            assert a.extras == b.extras

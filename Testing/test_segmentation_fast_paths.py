"""Fast paths written for speed (session 53) give exactly what the plain calls give.

Each helper replaces a library call or a cumulative sum on a hot path of the segmenter
(``bench_segment_cpu.py``); its docstring names the call it stands for. Checked here on
random inputs, edge sizes and NaN included, against that call itself.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import minimum_filter1d
from test_segmentation_speed_paths import _plain_convex_part

from BoneUSRecon.Logic.segmentation.candidates import _runs, convex_part
from BoneUSRecon.Logic.segmentation.evidence import field_tops
from BoneUSRecon.Logic.segmentation.features import row_minimum_filter
from BoneUSRecon.Logic.segmentation.params import ShadowPathParams


@pytest.mark.parametrize("dtype", [np.float32, np.float64, np.int16])
def test_row_minimum_filter_is_scipys_filter(dtype):
    rng = np.random.default_rng(0)
    for _ in range(300):
        h, w = (int(v) for v in rng.integers(1, (12, 60)))
        size = int(rng.integers(1, 2 * w + 4))
        a = (rng.normal(size=(h, w)) * 50).astype(dtype)
        want = minimum_filter1d(a, size, axis=1, mode="nearest")
        got = row_minimum_filter(a, size)
        assert got.dtype == want.dtype and np.array_equal(got, want), (h, w, size)


def test_row_minimum_filter_with_nan_is_scipys_filter():
    rng = np.random.default_rng(1)
    a = rng.normal(size=(8, 40))
    a[3, 7] = np.nan
    for size in (3, 9, 31):
        want = minimum_filter1d(a, size, axis=1, mode="nearest")
        assert np.array_equal(row_minimum_filter(a, size), want, equal_nan=True)


def test_runs_are_nps_split():
    rng = np.random.default_rng(2)
    for _ in range(300):
        idx = np.flatnonzero(rng.random(int(rng.integers(1, 80))) < rng.random())
        want = np.split(idx, np.flatnonzero(np.diff(idx) > 1) + 1)
        got = _runs(idx)
        assert len(got) == len(want) and all(
            np.array_equal(a, b) for a, b in zip(got, want, strict=True)
        )


def test_field_tops_of_a_boolean_mask_are_the_cumulative_sums():
    # The boolean path (ANDs of halves) against the integer path (counts on a sum).
    rng = np.random.default_rng(3)
    for _ in range(200):
        h, w = (int(v) for v in rng.integers((2, 1), (60, 30)))
        dy = float(rng.uniform(0.05, 0.6))
        mask = rng.random((h, w)) < rng.uniform(0.3, 1.0)
        got, want = field_tops(mask, dy), field_tops(mask.astype(np.uint8), dy)
        assert (got is None and want is None) or np.array_equal(got, want), (h, w, dy)


def test_convex_part_is_the_per_side_loop():
    # Both sides measured on one concatenation against each side on its own (the plain
    # index-array version of test_segmentation_speed_paths): domes, crests with layers
    # running off them, flat runs, ties on a pixel grid, edge sizes.
    rng = np.random.default_rng(4)
    p = ShadowPathParams()
    cut = 0
    for trial in range(600):
        n = int(rng.integers(1, 160))
        sx, sy = (float(v) for v in rng.uniform(0.05, 0.4, 2))
        cols = np.sort(rng.choice(np.arange(4 * n + 8), n, replace=False)).astype(float)
        t = np.linspace(-1.0, 1.0, n)
        rows = rng.uniform(5, 60) * t**2 * rng.choice([-1.0, 1.0, 0.0]) + rng.normal(0, 1, n)
        if trial % 3 == 0:  # a layer leaving the dome at one side: a turn to cut
            k = int(rng.integers(0, n)) if n else 0
            rows[k:] = rows[k] if n else rows[k:]
        if trial % 4 == 0:
            rows = np.round(rows)  # ties on the pixel grid
        pts = np.column_stack([cols, rows + 100.0])
        want = _plain_convex_part(pts, (sx, sy), p)
        got = convex_part(pts, (sx, sy), p)
        assert np.array_equal(got, want), trial
        cut += int(not want.all())
    assert cut >= 100  # turns found, on both sides


def test_array_idioms_are_the_numpy_functions():
    # The hot paths' stand-ins (session 53, second round): a 1-D mask's nonzero for
    # np.flatnonzero, the array methods for np.argmin / np.argmax / np.searchsorted,
    # slices for np.diff, np.concatenate for np.r_, and the padded mask's changes for
    # np.diff of np.r_[False, mask, False] (_fill_excursions' excursions).
    rng = np.random.default_rng(5)
    for _ in range(300):
        n = int(rng.integers(0, 50))
        mask = rng.random(n) < rng.random()
        idx = np.flatnonzero(rng.random(n + 1) < 0.6)
        x = np.round(rng.normal(size=n) * 4) / 4  # ties
        assert np.array_equal(mask.nonzero()[0], np.flatnonzero(mask))
        assert np.array_equal(idx[1:] - idx[:-1], np.diff(idx))
        pad = np.zeros(n + 2, bool)
        pad[1:-1] = mask
        want = np.flatnonzero(np.diff(np.r_[False, mask, False]))
        assert np.array_equal((pad[1:] != pad[:-1]).nonzero()[0], want)
        got = np.concatenate(([0], idx + 1)), np.concatenate((idx, [n]))
        for a, b in zip(got, (np.r_[0, idx + 1], np.r_[idx, n]), strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b)
        if n:
            assert x.argmin() == np.argmin(x) and x.argmax() == np.argmax(x)
            xs = np.sort(x)
            for side in ("left", "right"):
                v = xs + rng.choice([-0.25, 0.0, 0.25], n)
                assert np.array_equal(xs.searchsorted(v, side), np.searchsorted(xs, v, side))

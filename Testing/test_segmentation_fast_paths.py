"""Fast paths written for speed (session 53) give exactly what the plain calls give.

Each helper replaces a library call or a cumulative sum on a hot path of the segmenter
(``bench_segment_cpu.py``); its docstring names the call it stands for. Checked here on
random inputs, edge sizes and NaN included, against that call itself.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy.ndimage import minimum_filter1d

from BoneUSRecon.Logic.segmentation.candidates import _runs
from BoneUSRecon.Logic.segmentation.evidence import field_tops
from BoneUSRecon.Logic.segmentation.features import row_minimum_filter


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

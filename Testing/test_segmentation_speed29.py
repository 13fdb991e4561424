"""Branch ``speed29``'s fast paths give exactly what the code they replace gave.

Each speed-up of the default segmenter in this branch (percentiles and medians read
from sorted samples, grey pairs summed as 16-bit words, cumulative sums row by row, the
gap's shade subtracted on slices, the rim's paths of several frames in one loop) is
compared here, value for value, with the plain computation it replaced, on inputs
built to hit its edge cases (ties, signed zeros, odd widths, views, runs of columns).
The whole pipeline's contours are compared with the branch's base by
``Testing/benchmarks/bench_segment_cpu.py --against`` (README, branch speed29).
"""

from __future__ import annotations

import numpy as np

from BoneUSRecon.Logic.segmentation.evidence import _withhold_gap_shade, working_image
from BoneUSRecon.Logic.segmentation.features import (
    column_cumsum,
    mm_to_px,
    sorted_percentile,
    sorted_row_medians,
)
from BoneUSRecon.Logic.segmentation.params import ShadowPathParams
from BoneUSRecon.Logic.segmentation.rim import RadiusPaths, _radius_paths, radius_paths_many


def test_sorted_percentile_matches_numpy_with_a_python_q() -> None:
    # A Python q makes numpy interpolate in the array's dtype (float32 stays float32):
    # the evidence baseline's 75th percentile of float32 row medians.
    rng = np.random.default_rng(29)
    for trial in range(1500):
        n = int(rng.integers(1, 260))
        x = rng.gamma(2.0, 0.3, n).astype(np.float32 if trial % 2 else np.float64)
        if trial % 3 == 0:
            x = np.round(x * 4) / 4  # ties
        if trial % 5 == 0:
            x = np.log(x + 1e-3)  # negative values
        s = np.sort(x)
        for q in (75, 75.0, 10.0, 25, 0, 100, 50, 33.3, 99.9):
            assert sorted_percentile(s, q) == float(np.percentile(x, q)), (trial, q)


def test_column_cumsum_matches_numpy_cumsum() -> None:
    rng = np.random.default_rng(30)
    for trial in range(40):
        h, w = int(rng.integers(1, 60)), int(rng.integers(1, 50))
        a = rng.gamma(2.0, 0.2, (h, w)).astype(np.float32 if trial % 2 else np.float64)
        want = np.zeros((h + 1, w), a.dtype)
        np.cumsum(a, axis=0, out=want[1:])
        got = column_cumsum(a)
        assert got.dtype == want.dtype and np.array_equal(got, want), trial


def _plain_working_image(image, spacing, work_mm):  # type: ignore[no-untyped-def]
    """working_image as it was before branch speed29: strided uint8 reads, as float32."""
    fx, fy = mm_to_px(work_mm, spacing[0]), mm_to_px(work_mm, spacing[1])
    img = np.asarray(image)
    w, h = img.shape[1] // fx, img.shape[0] // fy
    colmean = img[:, 0 : w * fx : fx].astype(np.float32)
    for q in range(1, fx):
        colmean += img[:, q : w * fx : fx]
    colmean *= np.float32(1.0 / (255.0 * fx))
    work = colmean[0 : h * fy : fy].copy()
    for q in range(1, fy):
        work += colmean[q : h * fy : fy]
    work *= np.float32(1.0 / fy)
    return work, colmean, fx, fy


def test_working_image_pair_sums_match_strided_reads() -> None:
    # Even and odd widths, pairs from 0 to 510 (every uint16 carry), a view cut out of a
    # wider image (rows not contiguous), a float image, 1-3 pixels per working pixel.
    rng = np.random.default_rng(31)
    for trial in range(60):
        h, w = int(rng.integers(8, 70)), int(rng.integers(4, 90))
        img = rng.integers(0, 256, (h, w + 7), dtype=np.uint8)
        img[:, ::5] = 255
        img = img[:, 3 : 3 + w] if trial % 3 == 0 else np.ascontiguousarray(img[:, :w])
        if trial % 7 == 0:
            img = img.astype(np.float64)
        sp = float(rng.choice([0.1, 0.15, 0.2, 0.3]))
        got = working_image(img, (sp, sp), 0.25)
        want = _plain_working_image(img, (sp, sp), 0.25)
        assert got[2:] == want[2:]
        for a, b in zip(got[:2], want[:2], strict=True):
            assert a.dtype == b.dtype and np.array_equal(a, b), trial


def _plain_withhold(shadow_z, csum, usable, gap, above_off, scale, dy, p):  # type: ignore[no-untyped-def]
    """_withhold_gap_shade as it was before branch speed29 (a fancy-index subtraction)."""
    h, _ = shadow_z.shape
    nf = mm_to_px(p.near_field_mm, dy, minimum=0)
    end = np.clip(np.arange(h) + above_off, nf, h)
    n = (end - nf).astype(np.float32)
    ok = n >= 1
    ref = usable & ~gap
    if not ok.any() or not ref.any():
        return
    rows = np.flatnonzero(ok)
    above = csum[end[rows]]
    above -= csum[nf]
    above *= (1.0 / n[rows])[:, None]
    rc = np.flatnonzero(ref)
    rc = rc[::2] if rc.size >= 40 else rc
    gc = np.flatnonzero(gap)
    typical = sorted_row_medians(np.sort(above[:, rc], axis=1))
    above = above[:, gc]
    shade = np.log((typical[:, None] + 1e-3) / (above + 1e-3))
    np.maximum(shade, 0, out=shade)
    shade /= scale
    shadow_z[rows[:, None], gc[None, :]] -= shade.astype(shadow_z.dtype)


def test_gap_shade_on_slices_matches_fancy_index() -> None:
    # The gap at one edge, at both (two runs), or scattered columns; windows reaching
    # above the image.
    rng = np.random.default_rng(32)
    p = ShadowPathParams()
    for trial in range(60):
        h, w = int(rng.integers(10, 80)), int(rng.integers(45, 120))
        work = rng.gamma(2.0, 0.1, (h, w)).astype(np.float32)
        csum = column_cumsum(work)
        usable = np.ones(w, bool)
        usable[: int(rng.integers(0, 4))] = False
        gap = np.zeros(w, bool)
        kind = trial % 3
        if kind in (0, 1):
            gap[usable.argmax() : usable.argmax() + int(rng.integers(1, 15))] = True
        if kind == 1:
            gap[w - int(rng.integers(1, 15)) :] = True
        if kind == 2:
            gap[rng.random(w) < 0.2] = True
        gap &= usable
        if not gap.any():
            continue
        z = rng.normal(0.0, 1.0, (h, w)).astype(np.float32)
        want, got = z.copy(), z.copy()
        args = (csum, usable, gap, int(rng.integers(-12, 0)), 0.3, 0.3, p)
        _plain_withhold(want, *args)
        _withhold_gap_shade(got, *args)
        assert np.array_equal(got, want), trial


def test_rim_paths_of_several_frames_match_one_by_one() -> None:
    # Requests of different steps and reaches, with and without an outward limit, ties
    # and signed zeros: each request's paths as it has them alone.
    rng = np.random.default_rng(33)
    for trial in range(80):
        asks = []
        for _ in range(int(rng.integers(1, 7))):
            n_tr = 2 * int(rng.integers(1, 5))
            n_step = int(rng.choice([5, 12, 12, 12]))
            nb = int(rng.choice([9, 9, 13]))
            ms = int(rng.choice([1, 2, 2]))
            e = np.round(rng.normal(0, 1, (n_tr, n_step, nb)) * 2) / 2
            e[rng.random(e.shape) < 0.1] = -1e3
            e[rng.random(e.shape) < 0.05] = -0.0
            up = None
            if rng.random() < 0.6:
                up = rng.integers(1, ms + 1, (n_tr, n_step)).astype(np.intp)
            asks.append(RadiusPaths(e, int(rng.integers(0, nb)), ms, up))
        got = radius_paths_many(asks)
        for a, path in zip(asks, got, strict=True):
            assert np.array_equal(path, _radius_paths(*a)), trial

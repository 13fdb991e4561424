"""Tensor-product least-squares B-spline surface (paper II.D): exactness, oracles, robustness."""

from __future__ import annotations

import numpy as np
import pytest
from scipy.interpolate import LSQBivariateSpline, make_lsq_spline

from BoneUSRecon.Logic.bspline import (
    BSplineSurface,
    FitParams,
    averaging_knots,
    distinct_params,
    fewer_control_points,
    fit_curve,
    fit_surface,
)
from BoneUSRecon.Logic.errors import BoneUSReconError


def known_surface(m=40, n=15, e=None, f=None, seed=0, p=2, q=2):
    # The default control net is FitParams's, so the tests below fit with its default.
    e0, f0 = FitParams().n_control_points
    e, f = e0 if e is None else e, f0 if f is None else f
    rng = np.random.default_rng(seed)
    u = np.r_[0.0, np.sort(rng.uniform(0, 1, m - 2)), 1.0]
    v = np.linspace(0, 1, n)
    ku, kv = averaging_knots(u, e, p), averaging_knots(v, f, q)
    ctrl = rng.normal(scale=10.0, size=(e, f, 3))
    surf = BSplineSurface(ctrl, ku, kv, (p, q))
    return surf, u, v, surf.evaluate(u, v), rng


def test_averaging_knots_are_clamped_and_average_the_data():
    u = np.linspace(0, 1, 11)
    k = averaging_knots(u, 5, 2)
    assert k.size == 5 + 2 + 1
    assert np.all(k[:3] == 0) and np.all(k[-3:] == 1)
    # NURBS Book 9.69: d = 11/3, interior knots at ub[2] + 2/3 (ub[3]-ub[2]) etc.
    d = 11 / 3
    i = int(d)
    assert np.isclose(k[3], (1 - (d - i)) * u[i - 1] + (d - i) * u[i])
    assert np.all(np.diff(k) >= 0)


def test_rows_at_one_position_are_one_position_for_the_knots():
    # Ten rows at the first row's parameter (a probe held still): the knots are those of
    # the distinct positions, and the surface is still recovered (the system was singular).
    surf, u, v, pts, _ = known_surface(seed=5)
    held = np.r_[np.zeros(10), u]
    assert np.allclose(distinct_params(held, 1e-9), u)
    assert np.array_equal(averaging_knots(held, 15, 2), averaging_knots(u, 15, 2))
    # Neighbours closer than the tolerance are merged by run, not in pairs.
    assert np.allclose(distinct_params(np.array([0, 0.4, 0.8, 2.0]), 0.5), [0.4, 2.0])
    grid = np.concatenate([np.repeat(pts[:1], 10, axis=0), pts])
    for method in ("direct", "separable"):
        fit = fit_surface(grid, FitParams(robust="none", smoothing=0.0, method=method), u=held, v=v)
        assert np.abs(fit.surface.control_points - surf.control_points).max() < 1e-8


@pytest.mark.parametrize("method", ["direct", "separable"])
@pytest.mark.parametrize("degree", [(1, 1), (2, 2), (3, 2)])
def test_known_surface_recovered_to_round_off(method, degree):
    surf, u, v, pts, _ = known_surface(p=degree[0], q=degree[1])
    fit = fit_surface(
        pts, FitParams(degree=degree, method=method, robust="none", smoothing=0.0), u=u, v=v
    )
    assert np.abs(fit.surface.control_points - surf.control_points).max() < 1e-9
    assert fit.rms_mm < 1e-10
    # evaluate agrees with scipy's own tensor-product evaluator
    uu, vv = np.meshgrid(np.linspace(0, 1, 7), np.linspace(0, 1, 5), indexing="ij")
    ours = fit.surface.evaluate(uu[:, 0], vv[0])
    for k, s in enumerate(fit.surface.to_scipy()):
        assert np.allclose(s(np.stack([uu, vv], -1)), ours[..., k], atol=1e-10)


def test_known_surface_recovered_with_missing_entries():
    surf, u, v, pts, rng = known_surface(seed=3)
    pts = pts.copy()
    pts[rng.random(pts.shape[:2]) < 0.25] = np.nan
    pts[10:13] = np.nan  # three whole slices missing (rejected frames)
    fit = fit_surface(pts, FitParams(robust="none", smoothing=0.0), u=u, v=v)
    assert np.abs(fit.surface.control_points - surf.control_points).max() < 1e-8
    assert np.isnan(fit.residuals[10:13]).all() and (fit.weights[10:13] == 0).all()


def test_direct_fit_matches_fitpack_weighted_lsq_oracle():
    # Noisy data, random per-point weights, 10% missing: the exact weighted LSQ problem.
    surf, u, v, pts, rng = known_surface(seed=5)
    noisy = pts + rng.normal(scale=0.2, size=pts.shape)
    noisy[rng.random(pts.shape[:2]) < 0.1] = np.nan
    w = rng.uniform(0.2, 1.0, pts.shape[:2])
    fit = fit_surface(noisy, FitParams(robust="none", smoothing=0.0), u=u, v=v, weights=w)
    uu, vv = np.meshgrid(u, v, indexing="ij")
    ok = np.isfinite(noisy).all(-1)
    ku, kv = fit.surface.knots_u, fit.surface.knots_v
    ours = fit.surface.evaluate(u, v)
    for k in range(3):
        # FITPACK minimises sum (w_i r_i)^2, so it gets sqrt of our weights.
        oracle = LSQBivariateSpline(
            uu[ok],
            vv[ok],
            noisy[ok][:, k],
            ku[3:-3],
            kv[3:-3],
            w=np.sqrt(w[ok]),
            kx=2,
            ky=2,
            bbox=[0, 1, 0, 1],
        )
        assert np.abs(oracle(u, v) - ours[..., k]).max() < 1e-9


def test_separable_equals_direct_for_complete_grid_and_separable_weights():
    surf, u, v, pts, rng = known_surface(seed=7)
    noisy = pts + rng.normal(scale=0.3, size=pts.shape)
    w = np.outer(rng.uniform(0.3, 1, u.size), rng.uniform(0.3, 1, v.size))  # a_i b_j
    d = fit_surface(noisy, FitParams(robust="none", smoothing=0.0), u=u, v=v, weights=w)
    s = fit_surface(
        noisy, FitParams(method="separable", robust="none", smoothing=0.0), u=u, v=v, weights=w
    )
    assert np.abs(d.surface.control_points - s.surface.control_points).max() < 1e-9


def test_fit_curve_matches_scipy_make_lsq_spline():
    rng = np.random.default_rng(2)
    x = np.sort(rng.uniform(0, 1, 30))
    x[0], x[-1] = 0, 1
    y = np.sin(4 * x)[:, None, None] + rng.normal(scale=0.05, size=(30, 1, 1))
    w = rng.uniform(0.5, 1, (30, 1))
    t = averaging_knots(x, 8, 3)
    ours = fit_curve(x, y, w, t, 3)[:, 0, 0]
    oracle = make_lsq_spline(x, y[:, 0, 0], t, k=3, w=np.sqrt(w[:, 0]))
    assert np.allclose(ours, oracle.c, atol=1e-10)


def test_robust_fit_ignores_false_frames_and_outlier_points():
    # A gently curved "bone top" sampled on a 60 x 15 grid, 0.1 mm noise.
    rng = np.random.default_rng(11)
    m, n = 60, 15
    s = np.linspace(0, 80, m)
    a = np.linspace(-1.1, 1.1, n)
    ss, aa = np.meshgrid(s, a, indexing="ij")
    r = 6 + 0.5 * np.sin(ss / 15)
    truth = np.stack([ss, r * np.sin(aa) + 2 * np.sin(ss / 25), r * np.cos(aa)], -1)
    pts = truth + rng.normal(scale=0.1, size=truth.shape)
    bad_frames = [7, 8, 30, 45, 52, 53]
    pts[bad_frames, :, 2] -= 5.0  # whole false contours, 5 mm too deep
    pts[rng.random((m, n)) < 0.03, 1] += 3.0  # scattered single-point outliers
    plain = fit_surface(pts, FitParams(robust="none"), u=s, v=a)
    robust = fit_surface(pts, FitParams(), u=s, v=a)
    good = np.setdiff1d(np.arange(m), bad_frames)
    err_plain = np.linalg.norm(plain.surface.evaluate(plain.u, plain.v) - truth, axis=-1)[good]
    err_rob = np.linalg.norm(robust.surface.evaluate(robust.u, robust.v) - truth, axis=-1)[good]
    assert err_plain.mean() > 0.3  # least squares is bent by the false frames
    assert err_rob.mean() < 0.12  # robust fit stays at the noise level
    assert np.all(robust.frame_weights[bad_frames] == 0)
    assert robust.frame_weights[good].min() > 0.5
    assert robust.n_outliers >= len(bad_frames) * n


@pytest.mark.parametrize(
    "kwargs, match",
    [
        ({"degree": (0, 2)}, r"FitParams.degree must be at least 1, got \(0, 2\)"),
        ({"n_control_points": (2, 5)}, "too few for degree"),
        ({"method": "magic"}, "FitParams.method must be one of direct, separable, got 'magic'"),
        ({"robust": "cauchy"}, "FitParams.robust must be one of tukey, huber, none"),
        ({"thin_weight": -1.0}, "thin_weight must be >= 0, got -1.0"),
        ({"thin_share": 0.0}, r"thin_share must lie in \(0, 1\], got 0.0"),
    ],
)
def test_bad_parameters_refused(kwargs, match):
    with pytest.raises(BoneUSReconError, match=match):
        FitParams(**kwargs)


def test_more_control_points_than_data_refused():
    _, u, v, pts, _ = known_surface(m=12, n=6, e=5, f=3)
    with pytest.raises(BoneUSReconError, match="too few valid grid points for 20 x 5"):
        fit_surface(pts, FitParams(n_control_points=(20, 5), fewer_if_short=False))
    sparse = np.full_like(pts, np.nan)
    sparse[:, :2] = pts[:, :2]  # only 2 rays hit anywhere
    with pytest.raises(BoneUSReconError, match="2 rays"):
        fit_surface(sparse, FitParams(n_control_points=(5, 3)))


def test_unsupported_control_points_refused_without_smoothing_and_held_with_it():
    _, u, v, pts, _ = known_surface(m=40, n=15, seed=4)
    holed = pts.copy()
    holed[14:26] = np.nan  # a long gap: some control points have no data under them
    with pytest.raises(BoneUSReconError, match="do not determine"):
        fit_surface(holed, FitParams(robust="none", smoothing=0.0, thin_weight=0.0), u=u, v=v)
    ok = np.isfinite(holed).all(-1)
    for params in (FitParams(robust="none", thin_weight=0.0), FitParams(robust="none")):
        # held by the tiny smoothing, or by the thin-data penalty (no bias on the data)
        fit = fit_surface(holed, params, u=u, v=v)
        assert np.abs(fit.surface.evaluate(u, v)[ok] - pts[ok]).max() < 1e-3


def test_separable_with_missing_entries_is_close_but_not_exact():
    # The paper's two-stage scheme cannot honour per-point weights exactly (module
    # docstring); with 15% missing entries it stays within ~1e-4 of the data's scale.
    surf, u, v, pts, rng = known_surface(seed=3)
    pts = pts.copy()
    pts[rng.random(pts.shape[:2]) < 0.15] = np.nan
    truth = surf.evaluate(u, v)
    err = {}
    for method in ("direct", "separable"):
        fit = fit_surface(pts, FitParams(method=method, robust="none"), u=u, v=v)
        err[method] = np.abs(fit.surface.evaluate(u, v) - truth).max()
    scale = np.abs(truth).max()
    assert err["direct"] < 1e-6 * scale
    assert 1e-6 * scale < err["separable"] < 1e-3 * scale


def test_row_medians_match_nanmedian_and_robust_weights_shape():
    import warnings

    from BoneUSRecon.Logic.robust import robust_weights
    from BoneUSRecon.Logic.robust import row_medians as _row_medians

    rng = np.random.default_rng(0)
    a = rng.uniform(0, 1, (50, 15))
    a[rng.random(a.shape) < 0.3] = np.nan
    a[3] = np.nan  # an empty row -> 0
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        ref = np.nan_to_num(np.nanmedian(a, axis=1))
    assert np.allclose(_row_medians(a), ref)
    r = np.array([0.0, 1.0, 4.685, 10.0])
    t = robust_weights(r, 1.0, "tukey")
    assert t[0] == 1.0 and 0 < t[1] < 1 and t[2] == 0 and t[3] == 0
    h = robust_weights(r, 1.0, "huber")
    assert h[0] == 1.0 and np.isclose(h[3], 0.1345)


def test_fit_is_equivariant_under_rigid_motion():
    from scipy.spatial.transform import Rotation

    surf, u, v, pts, rng = known_surface(seed=9)
    noisy = pts + rng.normal(scale=0.3, size=pts.shape)
    noisy[rng.random(pts.shape[:2]) < 0.1] = np.nan
    noisy[4, :, 2] += 8.0  # one false frame, so the robust weights are exercised too
    rot = Rotation.from_euler("zyx", [30, 10, -70], degrees=True).as_matrix()
    shift = np.array([5.0, -3.0, 100.0])
    a = fit_surface(noisy, FitParams(), u=u, v=v)
    b = fit_surface(noisy @ rot.T + shift, FitParams(), u=u, v=v)
    assert np.allclose(
        a.surface.control_points @ rot.T + shift, b.surface.control_points, atol=1e-6
    )
    assert np.allclose(a.weights, b.weights, atol=1e-9)
    assert a.frame_weights[4] == 0


def test_thin_penalty_changes_nothing_on_a_complete_grid():
    # every direction of the control net is determined: plain least squares, exactly
    surf, u, v, pts, rng = known_surface(seed=5)
    noisy = pts + rng.normal(scale=0.2, size=pts.shape)
    a = fit_surface(noisy, FitParams(robust="none", thin_weight=0.0, smoothing=0.0), u=u, v=v)
    b = fit_surface(noisy, FitParams(robust="none", thin_weight=1.0, smoothing=0.0), u=u, v=v)
    assert np.allclose(a.surface.control_points, b.surface.control_points, atol=1e-9)


def test_robust_weights_judge_offsets_along_the_normal_not_within_the_surface():
    """Correct slices met off their nominal parameters are kept; a false one is not.

    A half-cylinder (radius 8 mm) sampled by rays: in slices 9 and 15 the rays hit the
    bone 6 degrees further round than their nominal angle (a tilted slice, a centre a
    little off), so those points lie on the surface but 0.8 mm from ``S(u_i, v_j)``;
    slice 21 is 1.5 mm above the bone (a false contour). Judged by the full offset the
    two correct slices were rejected too.
    """
    m, n, radius = 30, 15, 8.0
    x = np.linspace(0.0, 60.0, m)
    theta = np.deg2rad(np.linspace(-50.0, 50.0, n))
    hit = np.repeat(theta[None], m, axis=0)
    hit[[9, 15]] += np.deg2rad(6.0)
    rad = np.full((m, 1), radius)
    rad[21] += 1.5
    grid = np.stack(
        [np.repeat(x[:, None], n, axis=1), rad * np.sin(hit), rad * np.cos(hit)], axis=-1
    )
    fit = fit_surface(grid, FitParams(), u=x, v=theta)
    assert np.flatnonzero(fit.frame_weights <= 0).tolist() == [21]
    assert fit.frame_weights[[9, 15]].min() > 0.5
    # The surface stays on the true cylinder (points on it are within a few hundredths).
    s = fit.surface.evaluate(np.linspace(0.05, 0.95, 40), np.linspace(0.05, 0.95, 20))
    assert np.abs(np.hypot(s[..., 1], s[..., 2]) - radius).max() < 0.05


def test_fit_runs_on_one_blas_thread_and_gives_the_threads_back():
    # fit_surface limits BLAS to one thread while it runs (speed on small matrices, and
    # the same bits in a batch worker and a single run: test_batch compares them bit for
    # bit) and restores the process's own limits afterwards.
    from threadpoolctl import threadpool_info

    import BoneUSRecon.Logic.bspline as bspline

    seen = []
    real = bspline.thin_basis

    def spy(*args, **kwargs):
        seen.append({lib["filepath"]: lib["num_threads"] for lib in threadpool_info()})
        return real(*args, **kwargs)

    before = {lib["filepath"]: lib["num_threads"] for lib in threadpool_info()}
    surf, u, v, pts, rng = known_surface(seed=5)
    pts = pts.copy()
    pts[:, :3] = np.nan  # a thin side: the thin-data basis is used
    bspline.thin_basis = spy
    try:
        fit_surface(pts, FitParams(), u=u, v=v)
    finally:
        bspline.thin_basis = real
    assert seen and all(set(s.values()) == {1} for s in seen)
    assert {lib["filepath"]: lib["num_threads"] for lib in threadpool_info()} == before


def test_a_short_grid_is_fitted_with_fewer_control_points():
    # 12 slices cannot carry 20 control points along: half the slices are fitted (the
    # 6 rays carry the 5 around), and a surface in the spline space is still recovered.
    uu, vv = np.meshgrid(np.linspace(0, 30, 12), np.linspace(-1, 1, 6), indexing="ij")
    grid = np.stack([uu, 5 * vv, 2 - vv**2 + 0.01 * uu**2], axis=-1)
    fit = fit_surface(grid, FitParams(n_control_points=(20, 5)), u=uu[:, 0], v=vv[0])
    assert fit.n_control_points == (6, 5)
    assert fit.rms_mm < 1e-6
    # What fewer_control_points does: a count the grid holds stays; below degree + 1
    # it is left as asked (for the fit's refusal); fewer along while points run short.
    assert fewer_control_points((40, 24, 900), (2, 2), (15, 6)) == (15, 6)
    assert fewer_control_points((11, 21, 76), (2, 2), (15, 6)) == (5, 6)
    assert fewer_control_points((4, 24, 80), (2, 2), (15, 6)) == (3, 6)
    assert fewer_control_points((2, 24, 40), (2, 2), (15, 6)) == (15, 6)
    assert fewer_control_points((30, 4, 20), (2, 2), (15, 6)) == (5, 4)
    assert fewer_control_points((30, 2, 60), (2, 2), (15, 6)) == (15, 6)

"""Robust point-to-plane ICP, its starts and their ranking (internal to the package).

Why not a library ICP: small_gicp (fast C++ point-to-plane and GICP) estimates normals
from neighbouring points and rejects outliers only by a hard distance cut; Open3D is a
large dependency with the same hard cut. The model here has exact mesh normals, the
robust weights, the normal-compatible matches and the normal matrix are what the
accuracy and the quality figures need, and the only heavy part (nearest neighbours) is
scipy's C kd-tree, so the loop is a page of numpy and a 6x6 solve per iteration.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BoneUSRecon.Logic.registration.geometry import (
    principal_axes,
    rotation_matrix,
    transform_points,
)
from BoneUSRecon.Logic.registration.model import BoneModel
from BoneUSRecon.Logic.registration.params import RegistrationParams
from BoneUSRecon.Logic.robust import mad_scale, robust_weights

__all__ = ["IcpState", "Cloud", "match", "icp", "search_starts", "local_starts", "score", "best_of"]


@dataclass
class IcpState:
    matrix: np.ndarray
    iterations: int = 0
    converged: bool = False
    scale: float = 1.0
    gate: float = 1.0


@dataclass(frozen=True, eq=False)
class Cloud:
    """Source points with unit normals and the angle a model normal may differ by."""

    points: np.ndarray
    normals: np.ndarray
    max_angle_deg: float

    def subset(self, k: int) -> Cloud:
        """A deterministic random subset of at most ``k`` points."""
        if len(self.points) <= k:
            return self
        idx = np.sort(np.random.default_rng(0).choice(len(self.points), size=k, replace=False))
        return Cloud(self.points[idx], self.normals[idx], self.max_angle_deg)

    def flipped(self) -> Cloud:
        return Cloud(self.points, -self.normals, self.max_angle_deg)


#: Largest rotation (rad, ~3 deg) and translation (mm) of one ICP step.
MAX_STEP_RAD = 0.05
MAX_STEP_MM = 3.0

#: Nearest model points considered per source point: the nearest one that faces the
#: same way and is not on the border is used.
K_NEAREST = 4


def match(
    model: BoneModel, m: np.ndarray, src: Cloud, gate: float, params: RegistrationParams
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Correspondences at pose ``m``: (moved points, mask into them, residuals, normals).

    A source point pairs with the nearest model point within ``gate`` that is not on
    the model's open border and, when the source has normals, whose normal is within
    ``src.max_angle_deg`` of the source's: a patch pushed inside a thin bone would
    otherwise pair with the far side of the bone and flip onto it.
    """
    p = transform_points(m, src.points)
    d, idx = model.tree.query(p, k=K_NEAREST, distance_upper_bound=gate)
    good = np.isfinite(d)
    jj = np.where(good, idx, 0)
    good &= ~model.border[jj]
    ns = src.normals @ m[:3, :3].T
    cosang = np.einsum("kj,kij->ki", ns, model.normals[jj])
    good &= cosang >= np.cos(np.radians(src.max_angle_deg))
    ok = good.any(axis=1)
    first = np.argmax(good, axis=1)
    j = jj[np.arange(len(p)), first][ok]
    n = model.normals[j]
    r = np.einsum("ij,ij->i", p[ok] - model.points[j], n)
    return p, ok, r, n


def robust_residual_weights(r: np.ndarray, params: RegistrationParams) -> tuple[np.ndarray, float]:
    scale = mad_scale(r, params.noise_floor_mm)
    if params.robust == "none":
        return np.ones_like(r), scale
    return robust_weights(r, scale, params.robust), scale


def icp(
    src: Cloud,
    model: BoneModel,
    init: np.ndarray,
    params: RegistrationParams,
    *,
    max_iterations: int | None = None,
    tolerance_mm: float | None = None,
) -> IcpState:
    """Robust point-to-plane ICP from ``init``; returns the final state."""
    tol = params.tolerance_mm if tolerance_mm is None else tolerance_mm
    st = IcpState(matrix=np.array(init, float), gate=params.max_distance_mm)
    pts = src.points
    radius = float(np.sqrt(np.mean(np.sum((pts - pts.mean(0)) ** 2, axis=1)))) or 1.0
    n_iter = params.max_iterations if max_iterations is None else max_iterations
    for it in range(n_iter):
        m = st.matrix
        p, ok, r, n = match(model, m, src, st.gate, params)
        if ok.sum() < 6:
            break
        w, scale = robust_residual_weights(r, params)
        st.scale = scale
        q = p[ok]
        c = np.average(q, axis=0, weights=w) if w.sum() > 0 else q.mean(0)
        jac = np.hstack([np.cross(q - c, n), n])  # d r / d (omega, t), about c
        a = jac.T @ (w[:, None] * jac)
        b = -jac.T @ (w * r)
        lam = params.damping * max(float(np.linalg.eigvalsh(a)[-1]), 1e-12)
        x = np.linalg.solve(a + lam * np.eye(6), b)
        # Trust region: a step from few or one-sided matches can be wild (a patch then
        # tumbles onto the far side of the bone, where its turned normals match again).
        x *= min(
            1.0,
            MAX_STEP_RAD / max(float(np.linalg.norm(x[:3])), 1e-300),
            MAX_STEP_MM / max(float(np.linalg.norm(x[3:])), 1e-300),
        )
        dr = rotation_matrix(x[:3])
        step = np.eye(4)
        step[:3, :3] = dr
        step[:3, 3] = c - dr @ c + x[3:]
        st.matrix = step @ m
        st.iterations = it + 1
        # The gate follows the residual scale: wide while far, tight once aligned.
        st.gate = float(
            np.clip(10.0 * 4.685 * scale, params.min_distance_mm, params.max_distance_mm)
        )
        if np.linalg.norm(x[:3]) * radius + np.linalg.norm(x[3:]) < tol:
            st.converged = True
            break
    return st


def search_starts(
    src: np.ndarray, model: BoneModel, params: RegistrationParams
) -> list[np.ndarray]:
    """Candidate initial transforms from the principal axes, with their ambiguities.

    The source (a patch of one bone) and the model (the whole bone) share a long axis,
    not a centroid nor the two short axes: try both signs of the long axis, rolls about
    it, and positions along the model's length.
    """
    cs, axs, _ = principal_axes(src)
    cm, axm, svm = principal_axes(model.vertices)
    half = np.ptp(model.vertices @ axm[0]) / 2
    len_s = np.ptp(src @ axs[0])
    span = max(half - len_s / 2, 0.0)
    offsets = np.arange(-span, span + 1e-9, params.search_offsets_mm) if span > 0 else np.zeros(1)
    out = []
    for sign in (1.0, -1.0):
        for k in range(params.search_rolls):
            roll = rotation_matrix(axm[0] * (2 * np.pi * k / params.search_rolls))
            a_s = np.array([sign * axs[0], sign * axs[1], axs[2]])  # right-handed either way
            r = roll @ axm.T @ a_s
            for off in offsets:
                m = np.eye(4)
                m[:3, :3] = r
                m[:3, 3] = cm + axm[0] * off - r @ cs
                out.append(m)
    return out


def local_starts(src: np.ndarray, m0: np.ndarray, params: RegistrationParams) -> list[np.ndarray]:
    """Starts around ``m0``: rolls about and shifts along the source's long axis.

    Point-to-plane ICP on a patch of a long bone has local optima exactly there (the
    patch rolls around the shaft or slides along it, measured: from 10 mm / 10 deg away
    about half of the single starts end 4-8 mm off with a 1.6 mm residual); a grid of
    starts 15 deg / 10 mm apart covers the 15 mm / 15 deg the initialisation promises;
    two more start 10 mm above and below (the patch normal), see below.
    """
    c, axes, _ = principal_axes(src)
    ct = transform_points(m0, c[None])[0]
    a = m0[:3, :3] @ axes[0]
    up = m0[:3, :3] @ axes[2]
    out = []
    for roll in (0.0, *params.start_rolls_deg, *(-r for r in params.start_rolls_deg)):
        for shift in (0.0, *params.start_shifts_mm, *(-x for x in params.start_shifts_mm)):
            if roll == 0.0 and shift == 0.0:
                continue
            r = rotation_matrix(a * np.radians(roll))
            m = np.eye(4)
            m[:3, :3] = r
            m[:3, 3] = ct - r @ ct + a * shift
            out.append(m @ m0)
    # Lifted and lowered by the start's reach: a patch started more than the bone's
    # thickness below (or above) its place meets the wrong side of the bone first.
    for lift in (*params.start_shifts_mm, *(-x for x in params.start_shifts_mm)):
        m = np.eye(4)
        m[:3, 3] = up * lift
        out.append(m @ m0)
    return out


def score(src: Cloud, model: BoneModel, m: np.ndarray, params: RegistrationParams) -> float:
    """Mean truncated squared point-to-plane residual (mm^2): unmatched points count as
    the truncation, so a pose that leaves part of the source off the model pays for it."""
    tau = params.min_distance_mm
    _, ok, r, _ = match(model, m, src, tau, params)
    e = np.full(len(src.points), tau**2)
    e[ok] = np.minimum(r**2, tau**2)
    return float(e.mean())


def best_of(
    src: Cloud,
    model: BoneModel,
    starts: list[tuple[np.ndarray, bool]],
    params: RegistrationParams,
) -> tuple[IcpState, bool, tuple[float, float, float] | None]:
    """ICP from the best of ``starts``, and a distinct alternative fitting about as well.

    Each start (a matrix, and whether the source's normals are flipped: a patch normal
    has no known side) runs a short ICP on a subset of ``coarse_points``, ranked by
    :func:`score`; the best is refined on ``src``. The best-ranked start that ended
    more than ``max_sliding_mm`` away runs on (on the subset): if it stays that far
    with a residual within a factor 2 of the best's (floored at the noise), the surface
    matches in two places and the answer is ambiguous. Returns ``(state, flipped,
    None)`` or ``(state, flipped, (distance mm, alternative RMS, best RMS))``.
    """
    sides = {False: src.subset(params.coarse_points)}
    sides[True] = sides[False].flipped()
    pts = sides[False].points
    ranked = []
    for m, flip in starts:
        # Ranking needs the basin, not the last micron: a looser tolerance.
        c = sides[flip]
        stc = icp(c, model, m, params, max_iterations=params.coarse_iterations, tolerance_mm=0.01)
        ranked.append((score(c, model, stc.matrix, params), stc.matrix, flip))
    ranked.sort(key=lambda t: t[0])
    b_flip = ranked[0][2]
    best = icp(src.flipped() if b_flip else src, model, ranked[0][1], params)
    b_score = score(sides[b_flip], model, best.matrix, params)
    floor = params.noise_floor_mm**2

    def apart(m: np.ndarray) -> float:
        d = transform_points(m, pts) - transform_points(best.matrix, pts)
        return float(np.median(np.linalg.norm(d, axis=1)))

    for sc, m, flip in ranked[1:]:
        if sc > 2.0 * max(b_score, floor) + floor:
            break
        if apart(m) <= params.max_sliding_mm:
            continue
        other = icp(sides[flip], model, m, params, max_iterations=2 * params.coarse_iterations)
        a_score = score(sides[flip], model, other.matrix, params)
        dist = apart(other.matrix)
        if dist > params.max_sliding_mm and a_score <= 2.0 * max(b_score, floor):
            if a_score < b_score:  # the alternative is the better one: refine it instead
                best = icp(src.flipped() if flip else src, model, other.matrix, params)
                a_score, b_score, b_flip = b_score, a_score, flip
            return best, b_flip, (dist, float(np.sqrt(a_score)), float(np.sqrt(b_score)))
        break
    return best, b_flip, None

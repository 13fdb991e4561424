"""Quality figures at the final pose: residuals, inliers, and the constraint analysis."""

from __future__ import annotations

from typing import Any

import numpy as np

from BoneUSRecon.Logic.registration.geometry import principal_axes
from BoneUSRecon.Logic.registration.icp import Cloud, IcpState, match, robust_residual_weights
from BoneUSRecon.Logic.registration.model import BoneModel
from BoneUSRecon.Logic.registration.params import RegistrationParams

__all__ = ["quality", "unreliable_reasons", "describe_direction"]


def describe_direction(
    v: np.ndarray, radius: float, long_axis: np.ndarray, centre: np.ndarray
) -> str:
    """One eigen-direction ``(omega * radius, t)`` of the normal matrix in words."""
    rot, tr = v[:3], v[3:]
    if rot @ rot >= tr @ tr:
        ax = rot / np.linalg.norm(rot)
        if abs(ax @ long_axis) > np.cos(np.radians(25)):
            return "rotation about the bone's long axis"
        return f"rotation about the axis ({ax[0]:+.2f}, {ax[1]:+.2f}, {ax[2]:+.2f}) through ({centre[0]:.1f}, {centre[1]:.1f}, {centre[2]:.1f}) mm"
    d = tr / np.linalg.norm(tr)
    if abs(d @ long_axis) > np.cos(np.radians(25)):
        return "translation along the bone's long axis"
    return f"translation along ({d[0]:+.2f}, {d[1]:+.2f}, {d[2]:+.2f})"


def quality(
    cloud: Cloud, model: BoneModel, st: IcpState, params: RegistrationParams
) -> dict[str, Any]:
    """Residuals, inliers and the constraint analysis at the final transform (all points)."""
    src = cloud.points
    gate = float(np.clip(10.0 * 4.685 * st.scale, params.min_distance_mm, params.max_distance_mm))
    p, ok, r, n = match(model, st.matrix, cloud, gate, params)
    w, scale = (
        robust_residual_weights(r, params) if r.size else (np.zeros(0), params.noise_floor_mm)
    )
    inl = w > 0
    res = np.abs(r[inl])
    n_in = int(inl.sum())
    out: dict[str, Any] = {
        "n_inliers": n_in,
        "inlier_share": n_in / max(len(src), 1),
        "rms_mm": float(np.sqrt(np.mean(res**2))) if n_in else float("nan"),
        "median_mm": float(np.median(res)) if n_in else float("nan"),
        "p95_mm": float(np.percentile(res, 95)) if n_in else float("nan"),
    }
    # The source's own long axis, in target coordinates (where the analysis is done).
    _, axes, _ = principal_axes(src)
    long_axis = st.matrix[:3, :3] @ axes[0]
    out["long_axis"] = axes[0]
    if n_in < 6:
        out.update(
            eigenvalues=np.zeros(6),
            condition=float("inf"),
            sliding_mm=np.full(6, np.inf),
            directions=("all six degrees of freedom",) * 6,
        )
        return out
    q, nn, ww = p[ok][inl], n[inl], w[inl]
    c = np.average(q, axis=0, weights=ww)
    radius = float(np.sqrt(np.average(np.sum((q - c) ** 2, axis=1), weights=ww)))
    jac = np.hstack([np.cross(q - c, nn) / radius, nn])
    a = jac.T @ (ww[:, None] * jac) / ww.sum()
    evals, evecs = np.linalg.eigh(a)
    evals = np.maximum(evals, 0.0)
    # The residual a weak direction must overcome: the observed scatter, floored.
    sigma = max(out["rms_mm"], params.noise_floor_mm)
    with np.errstate(divide="ignore"):
        sliding = np.where(evals > 0, sigma / np.sqrt(evals), np.inf)
    dirs = tuple(describe_direction(evecs[:, k], radius, long_axis, c) for k in range(6))
    out.update(
        eigenvalues=evals,
        condition=float(evals[-1] / evals[0]) if evals[0] > 0 else float("inf"),
        sliding_mm=sliding,
        directions=dirs,
    )
    return out


def unreliable_reasons(q: dict[str, Any], st: IcpState, params: RegistrationParams) -> list[str]:
    reasons = []
    for k in np.argsort(q["sliding_mm"])[::-1]:
        s = q["sliding_mm"][k]
        if s > params.max_sliding_mm:
            what = (
                "unconstrained"
                if s > 20 * params.max_sliding_mm
                else f"weakly constrained (slides {s:.1f} mm)"
            )
            reasons.append(
                f"{q['directions'][k]} is {what}: the imaged surface lacks features in that direction"
            )
    if q["inlier_share"] < params.min_inlier_share:
        reasons.append(
            f"only {100 * q['inlier_share']:.0f}% of the source points fit the model "
            f"(at least {100 * params.min_inlier_share:.0f}% expected)"
        )
    if not q["rms_mm"] <= params.max_rms_mm:
        reasons.append(
            f"residual RMS {q['rms_mm']:.2f} mm exceeds {params.max_rms_mm:g} mm: the shapes do not match well"
        )
    if not st.converged:
        reasons.append(f"ICP did not converge in {st.iterations} iterations")
    return reasons

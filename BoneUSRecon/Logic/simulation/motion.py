"""Freehand probe motion over a bone: one ``ImageToReference`` pose per frame.

The operator drags the probe along the bone, keeping it roughly across the bone and
the bone roughly in the middle of the image (the paper's acquisition protocol), with
what a hand adds: uneven speed, tilts of several degrees about all three axes (so the
slices are not parallel), lateral wander and varying pressure (depth). Each of these
is a smooth random signal (hand motion is low-frequency) plus a little tremor.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.ndimage import gaussian_filter1d
from scipy.spatial.transform import Rotation

from BoneUSRecon.Logic.simulation.bones import UP, BoneGeometry
from BoneUSRecon.Logic.simulation.params import SimulationParams
from BoneUSRecon.Logic.simulation.sections import bone_sections

__all__ = ["ProbePath", "probe_path", "smooth_noise"]


@dataclass(frozen=True, eq=False)
class ProbePath:
    """Where the probe was for each frame."""

    #: Pixel ``(i, j, 0, 1)`` -> reference mm, shape (N, 4, 4).
    image_to_reference: np.ndarray
    #: Bone axis parameter under the probe centre (mm), shape (N,).
    s: np.ndarray
    #: Seconds, shape (N,).
    timestamps: np.ndarray
    #: Yaw (about the vertical), elevational tilt (about the lateral axis) and rock
    #: (about the beam's normal) of each frame (degrees), shape (N, 3).
    angles_deg: np.ndarray
    #: Lateral offset of the probe centre from the bone axis (mm), shape (N,).
    lateral_mm: np.ndarray
    #: Skin-to-bone-top distance under the probe centre (mm), shape (N,).
    depth_mm: np.ndarray


def smooth_noise(rng: np.random.Generator, n: int, correlation: float) -> np.ndarray:
    """Zero-mean, unit-std random signal of length ``n`` correlated over ``correlation`` samples."""
    pad = int(4 * correlation) + 1
    x = gaussian_filter1d(rng.standard_normal(n + 2 * pad), max(correlation, 1e-6))[pad:-pad]
    x = x - x.mean()
    sd = x.std()
    return x / sd if sd > 0 else x


def probe_path(geom: BoneGeometry, params: SimulationParams, rng: np.random.Generator) -> ProbePath:
    """Simulate the probe poses of one sweep.

    Parameters
    ----------
    geom : BoneGeometry
    params : SimulationParams
        Uses ``n_frames, width, height, spacing_mm, reverse, tilt_deg,
        lateral_jitter_mm, depth_jitter_mm, min_depth_mm, speed_variation, frame_rate_hz,
        sweep_margin_mm``.
    rng : numpy Generator

    Returns
    -------
    ProbePath
    """
    n = params.n_frames
    sx = sy = float(params.spacing_mm)
    # Hand motion changes over ~1/8 of the sweep; tremor is frame to frame.
    corr = max(1.0, n / 8.0)

    def jitter(std: float, tremor: float = 0.15) -> np.ndarray:
        return std * (
            np.sqrt(1 - tremor**2) * smooth_noise(rng, n, corr) + tremor * rng.standard_normal(n)
        )

    # Uneven speed: positive speed profile, integrated to positions along the bone.
    speed = np.clip(1.0 + params.speed_variation * smooth_noise(rng, n, corr), 0.25, None)
    pos = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]))])
    pos /= pos[-1] if n > 1 else 1.0
    s0, s1 = params.sweep_margin_mm, geom.length - params.sweep_margin_mm
    s = s0 + (s1 - s0) * pos
    if params.reverse:
        s = s[::-1].copy()

    yaw, tilt, rock = jitter(params.tilt_deg), jitter(params.tilt_deg), jitter(params.tilt_deg / 2)
    lateral = jitter(params.lateral_jitter_mm)
    depth = geom.spec.depth_mm + jitter(params.depth_jitter_mm, tremor=0.3)
    if params.has("depth_ramp"):
        # The hard preset: the bone rises from deep to shallow along the sweep (the
        # cadaver leg's 25 -> 5 mm), plus the same pressure jitter.
        d0, d1 = params.hard.depth_mm
        depth = depth - geom.spec.depth_mm + d0 + (d1 - d0) * pos

    # Nominal frame: image plane across the bone's horizontal direction, columns
    # lateral, rows straight down. The operator follows the bone's curve in the
    # horizontal plane (the S of a clavicle), not its small vertical bow.
    t = geom.axis_derivative(s)
    t[:, 2] = 0.0
    t /= np.linalg.norm(t, axis=1, keepdims=True)
    lat = np.cross(UP, t)
    down = np.tile(-UP, (n, 1))
    # Probe face centre: above the bone axis, at the bone top plus the depth.
    centre = geom.axis(s) + lateral[:, None] * lat
    centre[:, 2] = geom.top_height(s) + depth

    # Tilts applied about the probe face centre: yaw about the vertical, elevational
    # tilt about the lateral axis, rock about the sweep direction.
    rots = (
        Rotation.from_rotvec(np.deg2rad(yaw)[:, None] * UP)
        * Rotation.from_rotvec(np.deg2rad(tilt)[:, None] * lat)
        * Rotation.from_rotvec(np.deg2rad(rock)[:, None] * t)
    )
    ex = rots.apply(lat)
    ey = rots.apply(down)
    ez = np.cross(ex, ey)
    origin = centre - ((params.width - 1) / 2.0) * sx * ex

    m = np.zeros((n, 4, 4))
    m[:, :3, 0] = sx * ex
    m[:, :3, 1] = sy * ey
    # Third column: unit normal scaled like the pixels, so the matrix is a similarity.
    m[:, :3, 2] = 0.5 * (sx + sy) * ez
    m[:, :3, 3] = origin
    m[:, 3, 3] = 1.0
    # Pressure compresses the tissue over the bone only so far: where the bone comes
    # nearer the probe face than ``min_depth_mm`` anywhere in the image (tilted, rocked
    # or off to one side, the bone's top under the face's centre is not its nearest
    # point), the probe is lifted along its beam by the difference. A shift along the
    # beam moves every section point by the same depth, so one pass is exact.
    # (No floor, no sections: they cost as much as the frames' own.)
    if params.min_depth_mm > 0:
        top_j = bone_sections(geom, m, s, int(params.width)).top_j
        seen = np.isfinite(top_j).any(axis=1)
        nearest = np.full(n, np.inf)
        nearest[seen] = np.nanmin(top_j[seen], axis=1) * sy
        lift = np.clip(params.min_depth_mm - nearest, 0.0, None)
        m[:, :3, 3] -= lift[:, None] * ey
        depth = depth + lift
    # Frame clock: a fixed frame rate with a little acquisition jitter.
    dt = 1.0 / params.frame_rate_hz
    ts = np.arange(n) * dt + rng.uniform(-0.05, 0.05, n) * dt
    return ProbePath(
        image_to_reference=m,
        s=s,
        timestamps=ts - ts[0],
        angles_deg=np.column_stack([yaw, tilt, rock]),
        lateral_mm=lateral,
        depth_mm=depth,
    )

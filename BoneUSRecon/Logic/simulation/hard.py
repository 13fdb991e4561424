"""The ``hard`` realism preset: what a real cadaver sweep shows and our simulator did not.

Issue 10 measured a real tracked cadaver sweep of a lower leg (grey 0-255, medians)
and found images unlike the standard simulator's. ``SimulationParams(realism="hard")``
reproduces each condition, switchable one by one (``hard_conditions``), with the levels
of :class:`~.params.HardParams` (each documented with the real value it comes from):

* ``low_contrast``: the bone echo is a thin line only ~1.3x the grey of the tissue just
  above it (cadaver 1.35x), on mid-grey tissue.
* ``grey_shadow``: the shadow is mid-grey, ~0.4 of the echo and ~0.65 of the tissue
  beside it at the same depth, filled with speckle, equally spaced reverberation bands
  and the echo of the far cortex.
* ``crest``: the bone is a triangular crest (a ~5 mm flat top, flanks at ~60 degrees)
  over the first part of the segment, an oval further on whose echo is strong only on
  the side facing the probe (:func:`.bones.crest_shape`); the visible contour runs
  down the crest's flanks to 70 degrees.
* ``fascia``: a bright line leaving the bone's flank at the bone's level and running
  outwards, with tissue (not shadow) beneath: a bone look-alike. It ends where it
  meets a neighbouring bone's surface (never runs into or under it).
* ``skin_gap``: at one image edge the skin curves away from the probe over a dark
  no-contact gap, with equally spaced bright reverberation copies of the skin line below.
* ``vessel``: a dark round lumen beside the bone with bright walls, posterior
  enhancement and ring-down.
* ``depth_ramp``: the bone's depth goes from 25 to 5 mm along the sweep.

The ground truth is unchanged in kind: the true surface (with the crest) is exact,
and the true contour per frame is the visible part of the bone, never the fascia,
skin, vessel or reverberations.
"""

from __future__ import annotations

from dataclasses import dataclass, replace
from typing import Any

import numpy as np

from BoneUSRecon.Logic.simulation.bones import NEIGHBOURS, BoneGeometry
from BoneUSRecon.Logic.simulation.motion import ProbePath, smooth_noise
from BoneUSRecon.Logic.simulation.params import SimulationParams
from BoneUSRecon.Logic.simulation.sections import BoneSections

__all__ = ["HardScene", "effective_params", "crest_of", "echo_strength", "hard_scene"]


def effective_params(params: SimulationParams) -> SimulationParams:
    """``params`` with the imaging levels of its hard conditions (unchanged if standard)."""
    if params.realism != "hard":
        return params
    h, ip = params.hard, params.imaging
    changes: dict[str, Any] = {}
    if params.has("low_contrast"):
        changes.update(
            display_max_db=h.display_max_db,
            bone_amplitude=h.bone_amplitude,
            fascia_amplitude=h.fascia_amplitude,
        )
    if params.has("grey_shadow"):
        changes.update(
            shadow_transmission=h.shadow_transmission,
            reverb_amplitude=h.reverb_amplitude,
            reverb_mm=h.reverb_mm,
            reverb_copies=h.reverb_copies,
            reverb_decay=h.reverb_decay,
        )
    if params.has("crest"):
        changes.update(visible_cos=h.visible_cos)
    return replace(params, imaging=replace(ip, **changes)) if changes else params


def crest_of(params: SimulationParams) -> tuple[float, float] | None:
    """The ``crest`` argument of :class:`.bones.BoneGeometry` for ``params``."""
    return tuple(params.hard.crest_range) if params.has("crest") else None  # type: ignore[return-value]


def echo_strength(
    params: SimulationParams, geom: BoneGeometry, s: np.ndarray, cos_incidence: np.ndarray
) -> np.ndarray:
    """Relative bone echo ``cos ** p + diffuse * cos`` per frame and column, (N, W).

    ``p`` is the standard specular exponent on an oval and ``crest_exponent`` on a
    crest (blended by the crest weight at each frame's position ``s``).
    """
    ip = params.imaging
    c = np.clip(cos_incidence, 0.0, 1.0)
    w = geom.crest_weight(s)[:, None] if params.has("crest") else 0.0
    p = ip.specular_exponent + (params.hard.crest_exponent - ip.specular_exponent) * w
    return c**p + ip.diffuse_fraction * c


@dataclass(frozen=True, eq=False)
class HardScene:
    """What the hard conditions draw in each frame, in pixels; None for a condition that is off.

    All arrays are (N, W) per frame and column, NaN where there is nothing.
    """

    #: Relative bone echo per frame and column (see :func:`echo_strength`).
    strength: np.ndarray
    #: Row of the far cortex (``grey_shadow``).
    far_j: np.ndarray | None = None
    #: Row and amplitude of the fascia running off the bone (``fascia``), ending where
    #: it meets a neighbouring bone.
    fascia_j: np.ndarray | None = None
    fascia_amp: np.ndarray | None = None
    #: Row of the skin line over the no-contact gap (``skin_gap``).
    gap_j: np.ndarray | None = None
    #: Vessel centre ``(i, j)`` per frame (N, 2) and its radius (pixels) (``vessel``).
    vessel_ij: np.ndarray | None = None
    vessel_r: float = 0.0


def _vessel_side(params: SimulationParams, rng: np.random.Generator) -> float:
    """Lateral side (+1 / -1, along +y) of the vessel: away from a neighbouring bone.

    Only a neighbour shown by default moves it (the forearm's). A tibia's fibula,
    shown on request, leaves the draw as it was, so that a tibia sweep with the
    fibula is the same sweep plus the fibula (the look-alikes unchanged): what the
    fibula costs is measured alone. The vessel may then lie on the fibula's side, as
    the anterior tibial vessels do (on the interosseous membrane between the two).
    """
    pair = NEIGHBOURS.get(params.bone)
    if params.neighbour and pair is not None and pair.by_default:
        return -float(np.sign(pair.lateral_mm))
    return float(rng.choice([-1.0, 1.0]))


def _fascia_end(rows: np.ndarray, run: np.ndarray, bone_top: np.ndarray) -> float:
    """How far (columns) a fascia runs before it first meets another bone.

    A fascia is a sheet of connective tissue between muscles; where its run reaches a
    bone it ends on the bone's surface (it inserts into the periosteum): it cannot
    pass through the bone, and under the bone it would lie in the bone's acoustic
    shadow, where the bone has reflected or absorbed most of the sound and nothing
    comes back as bright as over tissue. The fascia line is drawn after the shadows
    (:func:`.imaging.render_frames`), so drawn on it would read as bright under the
    bone as beside it: a line a real image never shows, which a segmenter could
    follow from one bone onto the other. Over the bone, above its surface (tissue
    between), a fascia runs on.

    Parameters
    ----------
    rows : ndarray (W,)
        The fascia's row per column, NaN off its run.
    run : ndarray (W,)
        Each column's distance along the run from where the fascia leaves its bone
        (columns, increasing outwards; negative behind it).
    bone_top : ndarray (W,)
        The other bone's surface row per column, NaN where the beam misses it.

    Returns
    -------
    float
        The run at the first column where the fascia lies on or below the other
        bone's surface (in it or under it), ``inf`` if it never does.
    """
    with np.errstate(invalid="ignore"):
        into = (rows >= bone_top) & (run >= 0)
    return float(run[into].min()) if into.any() else np.inf


def hard_scene(
    params: SimulationParams,
    geom: BoneGeometry,
    path: ProbePath,
    sections: BoneSections,
    rng: np.random.Generator,
    other_top_j: np.ndarray | None = None,
) -> HardScene:
    """Lay out the hard conditions of every frame.

    Parameters
    ----------
    params : SimulationParams
        As from :func:`effective_params`.
    geom : BoneGeometry
        The swept bone.
    path : ProbePath
    sections : BoneSections
        The swept bone's sections (the fascia and vessel are laid out beside it).
    rng : numpy.random.Generator
    other_top_j : ndarray (N, W), optional
        Row of a neighbouring bone's surface per frame and column (NaN where the beam
        misses it or it is not shown): the fascia ends where it meets it
        (:func:`_fascia_end`).

    Returns
    -------
    HardScene
    """
    h = params.hard
    n, w = sections.top_j.shape
    sp = float(params.spacing_mm)
    cols = np.arange(w, dtype=float)
    strength = echo_strength(params, geom, path.s, sections.cos_incidence)
    side = _vessel_side(params, rng)
    # Image columns point along +y or -y depending on the pose: the fascia goes to the
    # side opposite the vessel, in image terms.
    col_dir = np.sign(path.image_to_reference[:, 1, 0])
    col_dir[col_dir == 0] = 1.0
    out: dict[str, object] = {"strength": strength}

    if params.has("grey_shadow") and sections.bottom_j is not None:
        far = np.where(np.isfinite(sections.top_j), sections.bottom_j, np.nan)
        out["far_j"] = np.where((far >= 0) & (far < params.height), far, np.nan)

    if params.has("fascia"):
        fj = np.full((n, w), np.nan)
        fa = np.zeros((n, w))
        wiggle = smooth_noise(rng, n, max(1.0, n / 6))
        for k in range(n):
            top = sections.top_j[k]
            have = np.flatnonzero(np.isfinite(top))
            if have.size < 3:
                continue
            d = -side * col_dir[k]  # the fascia leaves on the side away from the vessel
            jtop = float(np.nanmin(top))
            flank = have if d > 0 else have[::-1]
            # The first column past the top (going outwards) where the flank is attach_mm deep.
            apex = int(have[np.argmin(top[have])])
            beyond = flank[(flank - apex) * d > 0]
            hit = beyond[top[beyond] >= jtop + h.fascia_attach_mm / sp]
            if hit.size == 0:
                continue
            i0 = float(hit[0])
            run = (cols - i0) * d
            on = (run >= 0) & (run <= h.fascia_length_mm / sp)
            fj[k, on] = top[int(i0)] + run[on] * (h.fascia_slope + 0.02 * wiggle[k])
            # Fades in over 1 mm at the bone and out over its last 3 mm.
            fa[k, on] = np.clip(run[on] * sp / 1.0, 0.3, 1.0) * np.clip(
                (h.fascia_length_mm - run[on] * sp) / 3.0, 0.0, 1.0
            )
            if other_top_j is not None:
                # No fascia in or under the neighbouring bone: it ends on its surface.
                cut = on & (run >= _fascia_end(fj[k], run, other_top_j[k]))
                fj[k, cut] = np.nan
                fa[k, cut] = 0.0
        out["fascia_j"] = fj
        out["fascia_amp"] = fa * h.fascia_strength

    if params.has("skin_gap"):
        gap_side = float(rng.choice([-1.0, 1.0]))
        frac = h.gap_fraction * (1.0 + 0.15 * smooth_noise(rng, n, max(1.0, n / 6)))
        edge_w = np.clip(frac, 0.05, 0.45) * (w - 1)
        u = (
            (cols[None, :] - (w - 1 - edge_w[:, None]))
            if gap_side > 0
            else (edge_w[:, None] - cols[None, :])
        )
        u = u / edge_w[:, None]
        skin_mm = 1.2 + h.gap_depth_mm * np.clip(u, 0.0, 1.0) ** 2
        out["gap_j"] = np.where(u > 0, skin_mm / sp, np.nan)

    if params.has("vessel"):
        # A straight-ish vessel beside the bone, along it: centre at the bone's lateral
        # edge (at the vessel's height) plus a gap, vessel_depth_mm below the bone's top.
        a, b = geom.semi_axes(path.s)
        top_z = geom.top_height(path.s)
        centre_axis = geom.axis(path.s)
        z = top_z - h.vessel_depth_mm
        half = a * np.sqrt(np.clip(1 - ((z - centre_axis[:, 2]) / b) ** 2, 0.0, 1.0))
        lat = centre_axis[:, 1] + side * (half + h.vessel_gap_mm + h.vessel_radius_mm)
        p = np.column_stack([centre_axis[:, 0], lat, z, np.ones(n)])
        # Where the vessel crosses each image plane, in pixels (the plane is nearly
        # across the bone: the point at the frame's axis position is within a fraction
        # of a mm of it, and the vessel is not part of the truth).
        inv = np.linalg.inv(path.image_to_reference)
        ij = np.einsum("nab,nb->na", inv, p)[:, :2]
        out["vessel_ij"] = ij
        out["vessel_r"] = h.vessel_radius_mm / sp
    return HardScene(**out)  # type: ignore[arg-type]

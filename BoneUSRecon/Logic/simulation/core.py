"""The simulator's entry points: :func:`simulate` and :func:`write_simulation`."""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, replace
from pathlib import Path
from typing import Any

import numpy as np
from vtkmodules.util import numpy_support
from vtkmodules.vtkCommonCore import vtkPoints
from vtkmodules.vtkCommonDataModel import vtkCellArray, vtkPolyData

from BoneUSRecon import __version__
from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import atomic_path, can_create_file_in
from BoneUSRecon.Logic.progress import ProgressCallback, report
from BoneUSRecon.Logic.simulation.bones import (
    BONE_SPECS,
    NEIGHBOURS,
    UP,
    BoneGeometry,
    bone_spec,
    shows_neighbour,
)
from BoneUSRecon.Logic.simulation.corruption import choose_corrupted
from BoneUSRecon.Logic.simulation.hard import HardScene, crest_of, effective_params, hard_scene
from BoneUSRecon.Logic.simulation.hard import echo_strength as hard_echo_strength
from BoneUSRecon.Logic.simulation.imaging import render_frames
from BoneUSRecon.Logic.simulation.motion import ProbePath, probe_path
from BoneUSRecon.Logic.simulation.params import BONES, SimulationParams
from BoneUSRecon.Logic.simulation.sections import BoneSections, bone_sections, visible_contours
from BoneUSRecon.Logic.sweep import Sweep

__all__ = [
    "Simulation",
    "simulate",
    "write_simulation",
    "check_params",
    "sample_gold",
    "check_output_dir",
    "simulation_info",
]

#: Version of the simulation model, written to ``simulation.json``; bump when the
#: images or geometry for a given seed change.
SIMULATOR_VERSION = 3


@dataclass(frozen=True, eq=False)
class Simulation:
    """A simulated sweep with its ground truth.

    Attributes
    ----------
    sweep : Sweep
        The tracked sweep (``valid`` all True unless ``invalid_fraction > 0``).
    params : SimulationParams
    truth_vertices : ndarray (V, 3)
        Dense triangulation of the true bone surface (mm, reference frame); within
        0.003 mm of the analytic surface.
    truth_faces : ndarray (F, 3)
        Triangles (vertex indices, outward-oriented).
    gold : ndarray (K, 3)
        Digitised points on the imaged upper bone surface, with ``gold_noise_mm`` noise
        (over ``params.gold_region``; :func:`sample_gold` gives the other definition).
    corrupted : ndarray of int
        Indices of the corrupted frames, increasing.
    corruption_kinds : dict[int, str]
        Kind of each corrupted frame (see :mod:`.corruption`).
    true_contours_px : list of ndarray (K, 2)
        Per frame, the visible bone contour in pixels ``(i, j)``, ordered by increasing
        ``i``; empty ``(0, 2)`` when no bone is in view.
    geometry : BoneGeometry
        The analytic bone (exact distances, normals).
    path : ProbePath
        The probe motion (axis parameter, tilts, lateral offset, depth per frame).
    sections : BoneSections
        Bone row and incidence cosine per frame and column (also outside the visible part).
    swept_range_mm : (float, float)
        Range of the bone axis parameter the sweep imaged.
    neighbour : BoneGeometry or None
        The other bone shown beside the target (:data:`.bones.NEIGHBOURS`: the other
        forearm bone, or the fibula beside a tibia when ``params.neighbour_mm`` asks
        for it); a distractor, not in the truth, the gold points or the contours.
    hard_scene : HardScene or None
        With ``realism="hard"``: where the hard conditions were drawn, in pixels per
        frame (fascia, no-contact gap, vessel, far cortex; see :mod:`.hard`): the
        look-alikes a segmenter must not take for bone. None at standard realism.
    """

    sweep: Sweep
    params: SimulationParams
    truth_vertices: np.ndarray
    truth_faces: np.ndarray
    gold: np.ndarray
    corrupted: np.ndarray
    corruption_kinds: dict[int, str]
    true_contours_px: list[np.ndarray]
    geometry: BoneGeometry
    path: ProbePath
    sections: BoneSections
    swept_range_mm: tuple[float, float]
    neighbour: BoneGeometry | None = None
    hard_scene: HardScene | None = None

    def truth_polydata(self) -> vtkPolyData:
        """The true bone surface as triangles with outward point ``Normals``."""
        pd = vtkPolyData()
        pts = vtkPoints()
        pts.SetData(
            numpy_support.numpy_to_vtk(np.ascontiguousarray(self.truth_vertices, float), deep=True)
        )
        pd.SetPoints(pts)
        f = self.truth_faces
        offsets = np.arange(0, 3 * len(f) + 1, 3, dtype=np.int64)
        cells = vtkCellArray()
        cells.SetData(
            numpy_support.numpy_to_vtkIdTypeArray(offsets, deep=True),
            numpy_support.numpy_to_vtkIdTypeArray(
                np.ascontiguousarray(f, np.int64).reshape(-1), deep=True
            ),
        )
        pd.SetPolys(cells)
        s, phi = self.geometry.mesh_params(*_MESH)
        nrm = self.geometry.normals(s[:, None], phi[None, :]).reshape(-1, 3)
        arr = numpy_support.numpy_to_vtk(np.ascontiguousarray(nrm), deep=True)
        arr.SetName("Normals")
        pd.GetPointData().SetNormals(arr)
        return pd

    def bone_model_polydata(self, n_triangles: int | None = None) -> vtkPolyData:
        """The whole simulated bone segment as a closed triangle mesh (mm, reference frame).

        A stand-in for a bone model segmented from CT, whose pose is known: the
        registration's ground truth. ``n_triangles`` sets its size (about that many
        triangles, see :meth:`BoneGeometry.closed_mesh_params`); default: the truth
        mesh's resolution (0.5 mm along, 192 around).
        """
        from BoneUSRecon.Logic.vtkio import triangles_to_polydata

        g = self.geometry
        res = _MESH if n_triangles is None else g.closed_mesh_params(int(n_triangles))
        return triangles_to_polydata(*g.closed_mesh(*res))

    def distance_to_truth(self, points: np.ndarray) -> np.ndarray:
        """Unsigned distance (mm) from each point ``(K, 3)`` to the true bone surface.

        Exact projection onto the analytic surface (Newton), accurate to ~1e-6 mm, over
        the stretch of it the frames show: a frame tilted near the sweep's end may
        image the surface past the segment's ``[0, L]`` (the unsteady-hand radius s179,
        frame 0: ``s`` from -11.5 to -4.9 mm), and a contour on that bone is on it, not
        5 mm from the segment's end ring.
        """
        g = self.geometry
        s_range = self.sections.s_range
        finite = s_range[np.isfinite(s_range).all(axis=1)]
        lo = min(0.0, float(finite[:, 0].min())) if finite.size else 0.0
        hi = max(g.length, float(finite[:, 1].max())) if finite.size else g.length
        return g.distance(np.asarray(points, float).reshape(-1, 3), s_limits=(lo, hi))

    def contour_mm(self, frame: int) -> np.ndarray:
        """The true visible contour of ``frame`` in reference mm, shape (K, 3)."""
        return self.sweep.to_reference(frame, self.true_contours_px[frame])

    def true_profile(self, frame: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The bone under every column of ``frame`` that meets it, visible or not.

        Returns
        -------
        points_px : ndarray (K, 2)
            ``(i, j)``: the column and the (sub-pixel) row of the first bone surface its
            beam meets, ordered by ``i`` (the target bone only).
        slope_deg : ndarray (K,)
            In-plane slope of that surface (degrees from the image's lateral axis).
        visible : ndarray of bool (K,)
            Whether the point is part of the true visible contour (``true_contours_px``).
        """
        from BoneUSRecon.Logic.simulation.scoring import contour_slopes_deg

        j = self.sections.top_j[frame]
        i = np.flatnonzero(
            np.isfinite(j)
            & (np.nan_to_num(j, nan=-1.0) >= 0)
            & (np.nan_to_num(j, nan=-1.0) <= self.sweep.height - 1)
        )
        pts = np.column_stack([i.astype(float), j[i]]) if i.size else np.empty((0, 2))
        sx, sy = (float(v) for v in self.sweep.spacing_mm)
        visible = np.isin(i, self.true_contours_px[frame][:, 0].astype(int))
        return pts, contour_slopes_deg(pts * [sx, sy]), visible

    def contours_mm(self) -> list[tuple[int, np.ndarray]]:
        """``(frame, (K, 3) mm)`` for every valid frame with a visible bone, in frame order.

        The same form as ``SegmentationResult.contours_mm``: a perfect segmentation.
        """
        return [
            (k, self.contour_mm(k))
            for k in range(self.sweep.n_frames)
            if self.sweep.valid[k] and len(self.true_contours_px[k])
        ]


# (ds mm, points around) of the truth mesh: see BoneGeometry.mesh for the error bound.
_MESH = (0.5, 192)

#: Limits that keep an absurd request from eating the machine: the simulated sweep is
#: held in memory (uint8), and image formation needs ~130 bytes per pixel of one frame
#: (complex64 speckle fields), 0.5 GB at 2048 x 2048.
MAX_IMAGE_SIDE = 2048
MAX_SWEEP_BYTES = 4_000_000_000


def check_params(params: SimulationParams) -> None:
    """Raise :class:`BoneUSReconError` for parameters the simulator cannot honour."""
    p = params
    if p.bone not in BONES:
        raise BoneUSReconError(f"unknown bone {p.bone!r}; choose one of {', '.join(BONES)}")
    if int(p.n_frames) < 2:
        raise BoneUSReconError(f"need at least 2 frames, got {p.n_frames}")
    if int(p.width) < 16 or int(p.height) < 16:
        raise BoneUSReconError(
            f"images must be at least 16 x 16 pixels, got {p.height} x {p.width}"
        )
    if int(p.width) > MAX_IMAGE_SIDE or int(p.height) > MAX_IMAGE_SIDE:
        raise BoneUSReconError(
            f"images must be at most {MAX_IMAGE_SIDE} pixels per side, got {p.height} x {p.width}"
        )
    if int(p.n_frames) * int(p.width) * int(p.height) > MAX_SWEEP_BYTES:
        raise BoneUSReconError(
            f"{p.n_frames} frames of {p.height} x {p.width} pixels would need "
            f"{int(p.n_frames) * int(p.width) * int(p.height) / 1e9:.1f} GB in memory; "
            f"the simulator holds at most {MAX_SWEEP_BYTES / 1e9:g} GB"
        )
    if not (np.isfinite(p.spacing_mm) and p.spacing_mm > 0):
        raise BoneUSReconError(f"pixel spacing must be a positive number of mm, got {p.spacing_mm}")
    for name in ("corrupted_fraction", "invalid_fraction"):
        v = getattr(p, name)
        if not (0.0 <= v <= 1.0):
            raise BoneUSReconError(f"{name.replace('_', ' ')} must be between 0 and 1, got {v}")
    if not (0 <= int(p.black_margin_px) and 2 * int(p.black_margin_px) <= int(p.width) - 16):
        raise BoneUSReconError(
            f"black margins of {p.black_margin_px} px leave less than 16 imaged columns of {p.width}"
        )
    if p.gold_points < 0 or p.gold_noise_mm < 0:
        raise BoneUSReconError("gold points and gold noise must not be negative")
    if p.neighbour_mm is not None:
        pair = NEIGHBOURS.get(p.bone)
        if pair is None:
            raise BoneUSReconError(
                f"neighbour_mm: the simulator shows no bone beside the {p.bone} "
                f"(only beside the {', '.join(NEIGHBOURS)}); got {p.neighbour_mm:g} mm"
            )
        if p.neighbour_mm < pair.min_lateral_mm:
            raise BoneUSReconError(
                f"neighbour_mm: the {pair.bone} must lie at least {pair.min_lateral_mm:g} mm "
                f"from the {p.bone} (nearer, the two bones would cut into each other); "
                f"got {p.neighbour_mm:g} mm"
            )
    spec = BONE_SPECS[p.bone]
    if 2 * p.sweep_margin_mm >= spec.length_mm:
        raise BoneUSReconError(
            f"sweep margin {p.sweep_margin_mm} mm leaves nothing of the {spec.length_mm} mm {p.bone} to sweep"
        )
    depth = max(p.hard.depth_mm) if p.has("depth_ramp") else spec.depth_mm
    need = depth + 3 * p.depth_jitter_mm + 4.0
    have = p.height * p.spacing_mm
    if need > have:
        raise BoneUSReconError(
            f"the image is {have:.1f} mm deep but the {p.bone} lies {depth:g} mm under the skin "
            f"(needs about {need:.0f} mm to show it and its shadow); raise the image height or the pixel spacing"
        )


def _end_planes(path: ProbePath, contours: list[np.ndarray]) -> np.ndarray | None:
    """The first and last frames that showed bone as planes ``(2, 4)``: unit normal and offset.

    Each normal points into the sweep (towards the mean centre of those frames), so a
    point ``x`` is on the imaged side of both when ``x @ n + c >= 0`` for each. None
    when fewer than two frames showed bone.
    """
    seen = np.flatnonzero([len(c) > 0 for c in contours])
    if seen.size < 2:
        return None
    m = path.image_to_reference
    inner = m[seen, :3, 3].mean(axis=0)
    planes = np.empty((2, 4))
    for row, k in enumerate((seen[0], seen[-1])):
        n = np.cross(m[k, :3, 0], m[k, :3, 1])
        n /= np.linalg.norm(n)
        c = -float(n @ m[k, :3, 3])
        if n @ inner + c < 0:
            n, c = -n, -c
        planes[row] = (*n, c)
    return planes


def _sample_gold(
    geom: BoneGeometry,
    s_range: tuple[float, float],
    path: ProbePath,
    params: SimulationParams,
    contours: list[np.ndarray],
    rng: np.random.Generator,
    faded: bool = False,
) -> np.ndarray:
    """Uniform-by-area points on the imaged upper surface, plus isotropic noise.

    The imaged upper surface: within the swept range, facing up (``normal . up >=
    visible_cos``, and with ``realism="hard"`` an echo strength of at least
    ``HardParams.visible_strength``: the same rules as the visible contours, what the
    probe sees and a digitiser reaches from above; ``faded`` drops the strength rule,
    for the whole upper surface, as a CT bone model's gold would be) and inside the
    field of view of the frame nearest along the bone (a narrow image does not show
    the whole width of a tibia).
    With ``gold_region="imaged"`` also between the planes of the first and last frames
    that showed bone (``contours``): the image is a plane, so bone beyond them was not
    imaged; ``"swept"`` keeps the whole axis range (see ``SimulationParams.gold_region``).
    """
    k = int(params.gold_points)
    if k == 0:
        return np.empty((0, 3))
    s = np.linspace(*s_range, max(int((s_range[1] - s_range[0]) / 0.25), 2))
    phi = np.linspace(0, 2 * np.pi, 720, endpoint=False)
    S, PH = np.meshgrid(s, phi, indexing="ij")
    P, Ps, Pp = geom.derivatives(s[:, None], phi[None, :])
    cr = np.cross(Pp, Ps)
    area = np.linalg.norm(cr, axis=-1)
    up = (cr @ UP) / area
    # Field of view of the nearest frame (by axis parameter) for every grid point.
    order = np.argsort(path.s)
    pos = np.clip(np.searchsorted(path.s[order], s), 1, len(order) - 1)
    lo, hi = order[pos - 1], order[pos]
    near = np.where(np.abs(path.s[lo] - s) <= np.abs(path.s[hi] - s), lo, hi)
    m = path.image_to_reference[near]  # (n_s, 4, 4)
    d = P - m[:, None, :3, 3]
    i = (
        np.einsum("smk,sk->sm", d, m[:, :3, 0])
        / np.einsum("sk,sk->s", m[:, :3, 0], m[:, :3, 0])[:, None]
    )
    j = (
        np.einsum("smk,sk->sm", d, m[:, :3, 1])
        / np.einsum("sk,sk->s", m[:, :3, 1], m[:, :3, 1])[:, None]
    )
    margin = int(params.black_margin_px)
    seen = (i >= margin) & (i <= params.width - 1 - margin) & (j >= 0) & (j <= params.height - 1)
    planes = _end_planes(path, contours) if params.gold_region == "imaged" else None

    def imaged(x: np.ndarray) -> np.ndarray:
        if planes is None:
            return np.ones(x.shape[:-1], bool)
        return np.all(x @ planes[:, :3].T + planes[:, 3] >= 0, axis=-1)

    visible = up >= params.imaging.visible_cos
    if params.realism == "hard" and not faded:
        # The hard preset's contours also need the echo strength (the oval's faded
        # sides are in no frame): the same rule here, or the gold holds bone no frame
        # shows (session 40: the far gold of hard sweeps lay 1-2 mm past every contour).
        visible &= hard_echo_strength(params, geom, s, up) >= params.hard.visible_strength
    w = np.where(visible & seen & imaged(P), area, 0.0).reshape(-1)
    if w.sum() <= 0:
        return np.empty((0, 3))
    ds, dphi = s[1] - s[0], phi[1] - phi[0]
    # The jitter within a grid cell can carry a point up to half a cell past an end
    # plane: such draws are replaced (with "swept" the first draw is kept whole, as
    # before the region was introduced, so its points are unchanged for a given seed).
    got: list[np.ndarray] = []
    n_got = 0
    while n_got < k:
        cell = rng.choice(w.size, size=k, p=w / w.sum())
        ss = np.clip(S.reshape(-1)[cell] + rng.uniform(-0.5, 0.5, k) * ds, *s_range)
        pp = PH.reshape(-1)[cell] + rng.uniform(-0.5, 0.5, k) * dphi
        pts = geom.surface(ss, pp)
        pts = pts[imaged(pts)]
        got.append(pts)
        n_got += len(pts)
    pts = np.concatenate(got)[:k]
    return pts + rng.normal(0.0, params.gold_noise_mm, pts.shape)


def sample_gold(sim: Simulation, region: str | None = None, *, faded: bool = False) -> np.ndarray:
    """The gold points of ``sim`` digitised over ``region`` (``"imaged"`` or ``"swept"``).

    Same generator as :func:`simulate`, so ``sample_gold(sim)`` equals ``sim.gold``;
    a benchmark reports both definitions with ``sample_gold(sim, "swept")``. With
    ``faded=True`` (hard preset) the gold also covers the bone whose echo has faded
    below ``HardParams.visible_strength``, which no frame shows: what a method that
    extrapolates down the flanks is measured against.
    """
    params = effective_params(replace(sim.params, gold_region=region or sim.params.gold_region))
    return _sample_gold(
        sim.geometry,
        sim.swept_range_mm,
        sim.path,
        params,
        sim.true_contours_px,
        np.random.default_rng([int(params.seed), 5]),
        faded=faded,
    )


def _bone_free_mask(params: SimulationParams) -> np.ndarray:
    """Which frames show no bone (``params.bone_free_frames`` at the start and the end)."""
    n = int(params.n_frames)
    first, last = (int(v) for v in params.bone_free_frames)
    free = np.zeros(n, bool)
    free[:first] = True
    free[n - last :] = last > 0
    return free


def _neighbour(geom: BoneGeometry, params: SimulationParams) -> BoneGeometry | None:
    """The other bone beside the target (:data:`.bones.NEIGHBOURS`), or None.

    Its axis lies the pair's lateral distance (or ``params.neighbour_mm``, on the
    pair's side) from the target's, and its top the pair's ``deeper_mm`` below the
    target's top, both mid-segment; with the target's nominal skin written out, as
    before the pairs had their own depth offsets, so the forearm's bones lie where
    they always did, to the last bit.
    """
    if not shows_neighbour(params.bone, params.neighbour, params.neighbour_mm):
        return None
    pair = NEIGHBOURS[params.bone]
    dy = pair.lateral_mm
    if params.neighbour_mm is not None:
        dy = float(np.copysign(params.neighbour_mm, dy))
    spec2 = bone_spec(pair.bone)
    plain = BoneGeometry(spec2)
    depth = geom.spec.depth_mm
    skin = float(geom.top_height(geom.length / 2)[0]) + depth
    dz = skin - (depth + pair.deeper_mm) - float(plain.top_height(plain.length / 2)[0])
    return BoneGeometry(spec2, offset=(0.0, dy, dz))


def simulate(
    params: SimulationParams | None = None, progress: ProgressCallback | None = None
) -> Simulation:
    """Simulate a tracked freehand sweep over a bone, with its ground truth.

    Deterministic for a given ``params`` (including ``seed``): each random component
    (motion, tissue, speckle per frame, corruption, gold, validity) has its own
    generator seeded from ``(seed, component)``.

    Parameters
    ----------
    params : SimulationParams, optional
        Defaults to ``SimulationParams()`` (clavicle, 150 frames of 256 x 320 at 0.15 mm).
    progress : callable, optional
        Called as ``progress(stage, done, total)``.

    Returns
    -------
    Simulation

    Raises
    ------
    BoneUSReconError
        Parameters out of range (unknown bone, fewer than 2 frames, an image too
        shallow to show the bone, ...).

    Examples
    --------
    >>> sim = simulate(SimulationParams(bone="radius", n_frames=10, width=64, height=64, spacing_mm=0.6))
    >>> sim.sweep.frames.shape
    (10, 64, 64)
    """
    asked = SimulationParams() if params is None else params
    check_params(asked)
    # The hard realism preset's imaging levels (the same params when standard).
    params = effective_params(asked)
    seed = int(params.seed)
    geom = BoneGeometry(BONE_SPECS[params.bone], crest=crest_of(params))
    report(progress, "geometry", 0, 3)
    path = probe_path(geom, params, np.random.default_rng([seed, 1]))
    hard = params.realism == "hard"
    sections = bone_sections(geom, path.image_to_reference, path.s, int(params.width), far=hard)
    top_j, cos_inc = sections.top_j, sections.cos_incidence
    other = _neighbour(geom, params)
    # Frames past the bone's end show no bone (neither bone is rendered there).
    free = _bone_free_mask(params)
    other_top = None
    if other is not None:
        # The image shows whichever bone each beam meets first (they never overlap).
        s2 = path.s - geom.length / 2 + other.length / 2  # same x as the probe
        sec2 = bone_sections(other, path.image_to_reference, s2, int(params.width))
        use2 = np.isfinite(sec2.top_j) & ~(top_j <= sec2.top_j)
        top_j = np.where(use2, sec2.top_j, top_j)
        cos_inc = np.where(use2, sec2.cos_incidence, cos_inc)
        # Where the hard scene's fascia meets the neighbour, it ends.
        other_top = np.where(free[:, None], np.nan, sec2.top_j)
    report(progress, "geometry", 1, 3)
    kinds = choose_corrupted(
        int(params.n_frames), float(params.corrupted_fraction), np.random.default_rng([seed, 4])
    )
    scene = (
        hard_scene(params, geom, path, sections, np.random.default_rng([seed, 7]), other_top)
        if hard
        else None
    )
    if scene is not None and other is not None:
        # The neighbouring bone's echo keeps the standard angle law.
        ip = params.imaging
        c2 = np.clip(cos_inc, 0, 1)
        both = np.where(use2, c2**ip.specular_exponent + ip.diffuse_fraction * c2, scene.strength)
        scene = replace(scene, strength=both)
    # Frames past the bone's end: no bone is rendered there (the tissue layers, fascia,
    # skin gap and vessel were laid out above from the bone's sections and stay).
    if free.any():
        top_j = np.where(free[:, None], np.nan, top_j)
        cos_inc = np.where(free[:, None], 0.0, cos_inc)
        if scene is not None and scene.far_j is not None:
            scene = replace(scene, far_j=np.where(free[:, None], np.nan, scene.far_j))
    frames = render_frames(
        path.image_to_reference,
        top_j,
        cos_inc,
        params,
        kinds,
        progress,
        tissue_top_j=sections.top_j,
        scene=scene,
    )
    hidden = {k for k, v in kinds.items() if v == "contact_loss"}
    strength = (
        None if scene is None else hard_echo_strength(params, geom, path.s, sections.cos_incidence)
    )
    contours = visible_contours(
        sections,
        int(params.height),
        params.imaging.visible_cos,
        hidden,
        strength=strength,
        min_strength=params.hard.visible_strength,
    )
    if free.any():
        contours = [np.empty((0, 2)) if free[k] else c for k, c in enumerate(contours)]
        nan = np.where(free[:, None], np.nan, 0.0)
        sections = replace(
            sections,
            top_j=sections.top_j + nan,
            cos_incidence=np.where(free[:, None], 0.0, sections.cos_incidence),
            bottom_j=None if sections.bottom_j is None else sections.bottom_j + nan,
        )
    m = int(params.black_margin_px)
    if m > 0:
        # Scan-converted frames are exactly black outside the imaged area: no bone seen there.
        frames[:, :, :m] = 0
        frames[:, :, frames.shape[2] - m :] = 0
        contours = [c[(c[:, 0] >= m) & (c[:, 0] < frames.shape[2] - m)] for c in contours]

    # The part of the bone the sweep imaged: between the extreme sections that showed bone.
    seen = np.array([c.shape[0] > 0 for c in contours])
    sr = sections.s_range[seen] if seen.any() else sections.s_range
    swept = (float(max(sr.min(), 0.0)), float(min(sr.max(), geom.length)))
    gold = _sample_gold(geom, swept, path, params, contours, np.random.default_rng([seed, 5]))
    report(progress, "geometry", 2, 3)
    verts, faces = geom.mesh(*_MESH)

    n = int(params.n_frames)
    valid = np.ones(n, bool)
    reasons: dict[int, str] = {}
    n_bad = int(round(params.invalid_fraction * n))
    if n_bad:
        bad = np.random.default_rng([seed, 6]).choice(n, size=n_bad, replace=False)
        valid[bad] = False
        reasons = {
            int(k): "ImageToReference status INVALID (simulated tracking loss)" for k in sorted(bad)
        }
    sweep = Sweep(
        frames=frames,
        image_to_reference=path.image_to_reference,
        timestamps=path.timestamps,
        valid=valid,
        source=None,
        transform_name="ImageToReference",
        invalid_reasons=reasons,
        metadata={
            "simulated": True,
            "bone": params.bone,
            "seed": seed,
            "UltrasoundImageOrientation": "MF",
        },
    )
    report(progress, "geometry", 3, 3)
    return Simulation(
        sweep=sweep,
        params=asked,
        truth_vertices=verts,
        truth_faces=faces,
        gold=gold,
        corrupted=np.array(sorted(kinds), dtype=int),
        corruption_kinds=dict(kinds),
        true_contours_px=contours,
        geometry=geom,
        path=path,
        sections=sections,
        swept_range_mm=swept,
        neighbour=other,
        hard_scene=scene,
    )


def simulation_info(sim: Simulation) -> dict[str, Any]:
    """The JSON-able description written to ``simulation.json``."""
    spec = sim.geometry.spec
    a, b = sim.geometry.semi_axes(np.linspace(*sim.swept_range_mm, 50))
    return {
        "simulator_version": SIMULATOR_VERSION,
        "package_version": __version__,
        "seed": int(sim.params.seed),
        "parameters": asdict(sim.params),
        "bone": {
            **asdict(spec),
            "swept_range_mm": list(sim.swept_range_mm),
            "width_range_mm": [float(2 * a.min()), float(2 * a.max())],
            "height_range_mm": [float(2 * b.min()), float(2 * b.max())],
        },
        "frames": sim.sweep.n_frames,
        "spacing_mm": [float(v) for v in sim.sweep.spacing_mm],
        "corrupted_frames": [int(k) for k in sim.corrupted],
        "corruption_kinds": {str(k): v for k, v in sim.corruption_kinds.items()},
        "invalid_frames": [int(k) for k in np.flatnonzero(~sim.sweep.valid)],
        "neighbour": None
        if sim.neighbour is None
        else {
            "bone": sim.neighbour.spec.name,
            "offset_mm": [float(v) for v in sim.neighbour.offset],
        },
        "frames_with_visible_bone": int(sum(c.shape[0] > 0 for c in sim.true_contours_px)),
        "gold_points": int(sim.gold.shape[0]),
        "reference_frame": "x along the bone, y lateral, z up (towards the skin); mm",
    }


def check_output_dir(outdir: str | os.PathLike[str]) -> Path:
    """Check, before any work, that ``outdir`` is a folder or can be created as one.

    Raises
    ------
    BoneUSReconError
        The path is a file, lies under a file, or its nearest existing parent folder
        is not writable.
    """
    out = Path(outdir)
    if out.exists():
        if not out.is_dir():
            raise BoneUSReconError("output path exists and is not a folder", out)
        probe = out
    else:
        probe = out.absolute().parent
        while not probe.exists():
            probe = probe.parent
        if not probe.is_dir():
            raise BoneUSReconError(
                f"cannot create the output folder: {str(probe)!r} is not a folder", out
            )
    if not can_create_file_in(probe):
        raise BoneUSReconError(f"cannot write in {str(probe)!r}", out)
    return out


def write_simulation(
    sim: Simulation, outdir: str | os.PathLike[str], progress: ProgressCallback | None = None
) -> dict[str, Path]:
    """Write ``sweep.mha``, ``truth.vtp``, ``gold.csv`` and ``simulation.json`` to ``outdir``.

    The folder is created if needed; every file is written atomically.

    Returns
    -------
    dict
        ``{"sweep", "truth", "gold", "json"}`` -> written paths.

    Raises
    ------
    BoneUSReconError
        The folder cannot be created or written.
    """
    from BoneUSRecon.Logic.sequence_io import write_sweep
    from BoneUSRecon.Logic.vtkio import write_points_csv, write_polydata

    out = check_output_dir(outdir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except FileExistsError:
        raise BoneUSReconError("output path exists and is not a folder", out) from None
    except OSError as exc:
        raise BoneUSReconError(
            f"cannot create the output folder ({exc.strerror or exc})", out
        ) from None
    paths = {
        "sweep": out / "sweep.mha",
        "truth": out / "truth.vtp",
        "gold": out / "gold.csv",
        "json": out / "simulation.json",
    }
    report(progress, "writing", 0, 4)
    write_sweep(sim.sweep, paths["sweep"])
    report(progress, "writing", 1, 4)
    write_polydata(sim.truth_polydata(), paths["truth"])
    report(progress, "writing", 2, 4)
    write_points_csv(sim.gold, paths["gold"])
    report(progress, "writing", 3, 4)
    with atomic_path(paths["json"]) as tmp:
        tmp.write_text(json.dumps(simulation_info(sim), indent=2) + "\n", encoding="utf-8")
    report(progress, "writing", 4, 4)
    return paths

"""Bone geometry: each bone is a smooth generalised cylinder with an analytic surface.

Reference frame (mm): ``x`` runs along the bone, ``y`` is lateral, ``z`` points up,
towards the skin and the probe. The bone's centre axis is a smooth curve
``c(s) = (s - L/2, y(s), z(s))`` for arc parameter ``s`` in ``[0, L]`` (``s`` is the
``x`` coordinate shifted by ``L/2``, not the arc length). The cross-section at ``s`` is
an ellipse with semi-axes ``a(s)`` (lateral) and ``b(s)`` (vertical), rotated by a
twist angle ``theta(s)`` in the plane normal to the axis::

    P(s, phi) = c(s) + u' e_lat(s) + w' e_up(s),
    (u', w') = R(theta(s)) (a(s) cos phi, b(s) sin phi)

so ``phi = pi/2`` is the top of the bone (facing the probe) when there is no twist.

A bone may also have a *crest* (the ``hard`` realism preset, issue 10): over the
first part of the segment ``(cos phi, sin phi)`` is replaced by a rounded triangle
``(X(phi), Z(phi))`` (:func:`crest_shape`: a flat top ~0.5 of the half-width, flanks
at ~60 degrees, as the anterior crest of a tibia), blending into the ellipse further
along (``crest_weight``): proximally a crest, distally an oval, as on the real
cadaver leg. The crest is a smoothed Fourier series, so the surface stays smooth and
convex and the exact distance below still holds.
Everything is a sum of sines: the surface is infinitely smooth, which lets
:meth:`BoneGeometry.closest_points` project points onto it by Newton's method to
~1e-6 mm, far better than the < 0.01 mm the tests need, instead of relying on a mesh.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.spatial import cKDTree

__all__ = [
    "BoneSpec",
    "BONE_SPECS",
    "NEIGHBOUR_SPECS",
    "Neighbour",
    "NEIGHBOURS",
    "bone_spec",
    "shows_neighbour",
    "BoneGeometry",
    "crest_shape",
]

UP = np.array([0.0, 0.0, 1.0])


@dataclass(frozen=True)
class BoneSpec:
    """Shape and placement of the imaged segment of one bone.

    Sizes are typical adult values of the bone shafts (anatomy atlases and the
    ultrasound literature), rounded; they are meant to be realistic, not a model of
    one person.
    """

    name: str
    #: Length of the simulated segment along ``x`` (mm); the sweep covers it minus margins.
    length_mm: float
    #: Lateral diameter ``2a`` at ``s = 0`` and ``s = L`` (mm), linearly interpolated.
    width_mm: tuple[float, float]
    #: Vertical diameter ``2b`` (along the beam) at ``s = 0`` and ``s = L`` (mm).
    height_mm: tuple[float, float]
    #: Skin-to-bone-top distance under the probe (mm), before the operator's jitter.
    depth_mm: float
    #: Amplitude of the axis' lateral curvature (mm): a bow or an S.
    lateral_bow_mm: float
    #: Periods of the lateral curve over the segment: 0.5 is a C-shaped bow, 1.0 an S.
    lateral_periods: float
    #: Amplitude of the axis' vertical bow (mm).
    vertical_bow_mm: float
    #: Total twist of the cross-section over the segment (degrees).
    twist_deg: float
    #: Relative amplitude of the slow undulation of both diameters (unitless).
    undulation: float


#: The five bones of the paper (its introduction), all imaged from above.
BONE_SPECS: dict[str, BoneSpec] = {
    # Radius shaft: ~14 mm wide proximally, widening to ~19 mm towards the wrist;
    # lateral bow of a few mm; 5-15 mm under the skin of the forearm.
    "radius": BoneSpec("radius", 110.0, (14.0, 19.0), (10.0, 12.0), 8.0, 3.0, 0.5, 1.5, 20.0, 0.05),
    # Ulna: thicker proximally (~16 mm) tapering to ~12 mm; subcutaneous border.
    "ulna": BoneSpec("ulna", 110.0, (16.0, 12.0), (14.0, 10.0), 6.0, 2.5, 0.5, 1.0, 15.0, 0.05),
    # Tibia shaft: 25-30 mm wide, ~20-22 mm deep; under ~12 mm of soft tissue here.
    "tibia": BoneSpec("tibia", 150.0, (25.0, 30.0), (20.0, 22.0), 12.0, 2.0, 0.5, 2.0, 15.0, 0.04),
    # Humerus shaft: ~22 mm; under biceps/brachialis, ~20 mm deep.
    "humerus": BoneSpec(
        "humerus", 140.0, (21.0, 23.0), (19.0, 20.0), 20.0, 2.0, 0.5, 1.5, 15.0, 0.04
    ),
    # Clavicle: S-shaped in the horizontal plane (one full period over ~130 mm, ~9 mm
    # amplitude), round medially (15 mm) and flat laterally (12 x 8 mm), subcutaneous.
    "clavicle": BoneSpec(
        "clavicle", 130.0, (15.0, 12.0), (12.0, 8.0), 5.0, 9.0, 1.0, 2.0, 35.0, 0.06
    ),
}


#: Bones the simulator shows only beside a swept bone, never sweeps (not in
#: :data:`BONE_SPECS`, so not in the CLI's choice of bones).
NEIGHBOUR_SPECS: dict[str, BoneSpec] = {
    # Fibula shaft: a slender bone with a rounded-triangular section, ~10-15 mm across
    # mid-shaft (Gray's Anatomy, 41st ed., ch. 83: "long and slender"; CT morphometry of
    # adult fibulae gives mid-shaft diameters of ~11-14 mm, the antero-posterior one
    # the larger), narrowest in its lower third. It lies posterolateral to the tibia,
    # under the peroneal and posterior muscles: on a transverse scan over the tibia's
    # anterior face its top is 10-25 mm deeper than the tibia's (issue 10's lower-leg
    # sweeps), hence the large depth here (only the depth offset of
    # :data:`NEIGHBOURS` places it). Here 13 -> 11 mm wide and 14 -> 12 mm high (an
    # oval; the section's three borders are left out), a slight bow, little twist. As
    # long as the tibia's segment, so every probe position finds it beside the tibia.
    "fibula": BoneSpec(
        "fibula", 150.0, (13.0, 11.0), (14.0, 12.0), 27.0, 1.5, 0.5, 1.0, 10.0, 0.04
    ),
}


def bone_spec(name: str) -> BoneSpec:
    """The :class:`BoneSpec` of a swept bone or of a neighbour-only bone ``name``."""
    return BONE_SPECS[name] if name in BONE_SPECS else NEIGHBOUR_SPECS[name]


@dataclass(frozen=True)
class Neighbour:
    """The other bone a transverse scan shows beside a swept bone, and where it lies.

    Each pair states its own lateral and depth offsets: the forearm's two bones lie
    side by side at about the same depth, the fibula lies well deeper than the tibia.
    """

    #: The neighbouring bone (a key of :data:`BONE_SPECS` or :data:`NEIGHBOUR_SPECS`).
    bone: str
    #: Axis-to-axis distance along +y (mm; its sign is the side).
    lateral_mm: float
    #: How far the neighbour's top lies below the swept bone's top, mid-segment (mm).
    deeper_mm: float
    #: Shown by default (``SimulationParams.neighbour`` True); when False, only when
    #: ``SimulationParams.neighbour_mm`` asks for it (so that sweeps made before the
    #: pair existed stay byte-identical).
    by_default: bool = True
    #: Smallest lateral distance a sweep may ask for (``neighbour_mm``, mm): nearer,
    #: the two simulated bones would cut into each other (0: not checked).
    min_lateral_mm: float = 0.0


#: The other bone a transverse scan shows beside the target (along +y).
#:
#: * Forearm: the radius and ulna lie side by side, ~26 mm apart axis to axis
#:   mid-shaft, so a 48 mm wide image catches the edge of the other one. The
#:   neighbour's top lies 2 mm under its own nominal depth (:attr:`BoneSpec.depth_mm`)
#:   below the swept bone's skin (the rule before the pairs had their own offsets):
#:   beside a radius (8 mm deep) the ulna's top (6 + 2 mm) is level with the radius's,
#:   beside an ulna (6 mm) the radius's (8 + 2 mm) is 4 mm deeper.
#: * Lower leg: the fibula lies posterolateral to the tibia. Over the tibia's
#:   anterior face a 40-50 mm wide image shows it 20-35 mm lateral to the tibia's
#:   middle and 10-25 mm deeper than the tibia's top (issue 10's lower-leg sweeps):
#:   28 mm (its medial half in a 51 mm wide image) and 15 mm deeper here. Not shown
#:   by default: a tibia sweep shows the fibula only when ``neighbour_mm`` is given,
#:   so every tibia sweep simulated before the fibula existed is unchanged. At 18 mm
#:   the two surfaces come within ~1 mm of each other (their smallest gap over the
#:   segment, standard and crest-shaped tibia); at 16 mm they cut into each other,
#:   hence ``min_lateral_mm``. (The forearm pair is not checked, as before: its
#:   bones meet below ~16 mm.)
NEIGHBOURS: dict[str, Neighbour] = {
    "radius": Neighbour("ulna", -26.0, 6.0 + 2.0 - 8.0),
    "ulna": Neighbour("radius", 26.0, 8.0 + 2.0 - 6.0),
    "tibia": Neighbour("fibula", 28.0, 15.0, by_default=False, min_lateral_mm=18.0),
}


def shows_neighbour(bone: str, neighbour: bool, neighbour_mm: float | None) -> bool:
    """Whether a sweep of ``bone`` shows its neighbour (see :class:`Neighbour`)."""
    pair = NEIGHBOURS.get(bone)
    return bool(neighbour) and pair is not None and (pair.by_default or neighbour_mm is not None)


#: Corners of the crest cross-section (units of the semi-axes ``a``, ``b``; counter-
#: clockwise from the top): a flat top of +-0.28 a (~7 mm wide on a tibia, ~5 mm once
#: the corners are rounded), flanks falling 1.3 b over 0.52 a (~62 degrees on a tibia,
#: the cadaver's crest: "about 5 mm flat, 6 mm of flank steeper than 45 degrees"),
#: a broad posterior side.
_CREST_CORNERS = ((0.36, 1.0), (-0.36, 1.0), (-0.8, -0.3), (-0.5, -0.95), (0.5, -0.95), (0.8, -0.3))
#: Harmonics of the crest's Fourier series and the Gaussian taper of their weights:
#: 24 harmonics tapered at 6 keep the outline convex (no Gibbs ripples) with corners
#: rounded over ~1-2 mm.
_CREST_HARMONICS, _CREST_TAPER = 24, 6.0
_CREST_CACHE: list[tuple[np.ndarray, np.ndarray]] = []


def crest_shape() -> tuple[np.ndarray, np.ndarray]:
    """Complex Fourier coefficients ``(cx, cz)`` of the unit crest cross-section.

    ``X(phi) = Re(sum_k cx[k] exp(i k phi))`` (and ``Z`` likewise) runs counter-clockwise
    round the rounded triangle of ``_CREST_CORNERS`` at constant speed, with
    ``phi = pi/2`` at the middle of the flat top (as the ellipse's top).
    """
    if not _CREST_CACHE:
        v = np.array(_CREST_CORNERS, float)
        v = np.vstack([v, v[:1]])
        seg = np.linalg.norm(np.diff(v, axis=0), axis=1)
        arc = np.r_[0.0, np.cumsum(seg)]
        m = 4096
        u = np.linspace(0.0, arc[-1], m, endpoint=False)
        x, z = np.interp(u, arc, v[:, 0]), np.interp(u, arc, v[:, 1])
        top = int(np.argmin(np.hypot(x, z - 1.0)))
        # Shift the parameter so phi = pi/2 falls at the middle of the flat top.
        t = 2 * np.pi * (u - u[top]) / arc[-1] + np.pi / 2
        k = np.arange(_CREST_HARMONICS + 1)
        basis = np.exp(-1j * np.outer(k, t)) * (2.0 / m)
        taper = np.exp(-((k / _CREST_TAPER) ** 2))
        cx, cz = basis @ x * taper, basis @ z * taper
        cx[0] /= 2
        cz[0] /= 2
        _CREST_CACHE.append((cx, cz))
    return _CREST_CACHE[0]


def _fourier(c: np.ndarray, phi: np.ndarray, order: int) -> np.ndarray:
    """``d^order/dphi^order Re(sum_k c[k] exp(i k phi))``, shape ``phi.shape``.

    Evaluated once per distinct angle (the sections and the gold grid broadcast one
    row of angles over many planes), by Horner's scheme in ``exp(i phi)``.
    """
    phi = np.asarray(phi, float)
    uniq, inv = np.unique(phi, return_inverse=True)
    k = np.arange(c.size)
    coef = (1j * k) ** order * c
    z = np.exp(1j * uniq)
    acc = np.full(uniq.shape, coef[-1], complex)
    for ck in coef[-2::-1]:
        acc = acc * z + ck
    return np.real(acc)[inv.reshape(phi.shape)]


class BoneGeometry:
    """The analytic surface of one bone (see the module docstring for the formula).

    Parameters
    ----------
    spec : BoneSpec
    offset : (3,) array-like, optional
        Translation of the whole bone (mm), for a neighbouring bone.
    crest : (float, float), optional
        Give the bone a crest (see :func:`crest_shape`) up to the fraction ``crest[0]``
        of its length, blending into its ellipse by ``crest[1]``; None (default): an
        elliptic cross-section everywhere.
    """

    # Finite-difference step in s for the surface derivatives (mm). The surface is a
    # sum of sines, so central differences are accurate to ~h^2 * |P'''| ~ 1e-8 mm.
    _HS = 1e-3

    def __init__(
        self,
        spec: BoneSpec,
        offset: np.ndarray | tuple[float, float, float] = (0.0, 0.0, 0.0),
        crest: tuple[float, float] | None = None,
    ) -> None:
        self.spec = spec
        self.crest = None if crest is None else (float(crest[0]), float(crest[1]))
        self.offset = np.asarray(offset, float).reshape(3)
        self.length = float(spec.length_mm)
        self._tree: cKDTree | None = None
        self._tree_params: np.ndarray | None = None

    # -- the analytic description ------------------------------------------------------
    def axis(self, s: np.ndarray) -> np.ndarray:
        """Centre axis ``c(s)``, shape ``s.shape + (3,)``."""
        s = np.asarray(s, float)
        sp, L = self.spec, self.length
        x = s - L / 2
        y = sp.lateral_bow_mm * np.sin(2 * np.pi * sp.lateral_periods * s / L)
        z = sp.vertical_bow_mm * np.sin(np.pi * s / L)
        return np.stack([x, y, z], axis=-1) + self.offset

    def axis_derivative(self, s: np.ndarray) -> np.ndarray:
        """``dc/ds``, shape ``s.shape + (3,)``."""
        s = np.asarray(s, float)
        sp, L = self.spec, self.length
        k = 2 * np.pi * sp.lateral_periods / L
        dy = sp.lateral_bow_mm * k * np.cos(k * s)
        dz = sp.vertical_bow_mm * (np.pi / L) * np.cos(np.pi * s / L)
        return np.stack([np.ones_like(s), dy, dz], axis=-1)

    def frame(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Unit tangent, lateral and up vectors of the cross-section plane at ``s``.

        ``e_lat = up x t`` normalised and ``e_up = t x e_lat``: smooth because the axis
        never turns vertical.
        """
        t = self.axis_derivative(s)
        t = t / np.linalg.norm(t, axis=-1, keepdims=True)
        e_lat = np.cross(UP, t)
        e_lat /= np.linalg.norm(e_lat, axis=-1, keepdims=True)
        e_up = np.cross(t, e_lat)
        return t, e_lat, e_up

    def semi_axes(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Semi-axes ``a(s)`` (lateral) and ``b(s)`` (vertical), mm."""
        s = np.asarray(s, float)
        sp, L = self.spec, self.length
        f = s / L
        w = (sp.width_mm[0] + (sp.width_mm[1] - sp.width_mm[0]) * f) / 2
        h = (sp.height_mm[0] + (sp.height_mm[1] - sp.height_mm[0]) * f) / 2
        a = w * (1 + sp.undulation * np.sin(2 * np.pi * 1.5 * f + 0.7))
        b = h * (1 + sp.undulation * np.sin(2 * np.pi * 1.2 * f + 2.1))
        return a, b

    def twist(self, s: np.ndarray) -> np.ndarray:
        """Twist angle of the cross-section (rad), zero at mid-segment."""
        return np.deg2rad(self.spec.twist_deg) * (np.asarray(s, float) / self.length - 0.5)

    def section_basis(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """``c(s), U(s), V(s)`` such that ``P(s, phi) = c + cos(phi) U + sin(phi) V``.

        ``U = a (cos(theta) e_lat + sin(theta) e_up)`` and
        ``V = b (-sin(theta) e_lat + cos(theta) e_up)``: the twisted ellipse's semi-axes.
        """
        s = np.asarray(s, float)
        c = self.axis(s)
        _, e_lat, e_up = self.frame(s)
        a, b = self.semi_axes(s)
        th = self.twist(s)
        ct, st = np.cos(th)[..., None], np.sin(th)[..., None]
        U = a[..., None] * (ct * e_lat + st * e_up)
        V = b[..., None] * (-st * e_lat + ct * e_up)
        return c, U, V

    def crest_weight(self, s: np.ndarray) -> np.ndarray:
        """Weight of the crest in the cross-section at ``s`` (1: crest, 0: ellipse)."""
        s = np.asarray(s, float)
        if self.crest is None:
            return np.zeros_like(s)
        f0, f1 = self.crest
        u = np.clip((s / self.length - f0) / max(f1 - f0, 1e-9), 0.0, 1.0)
        return 0.5 * (1.0 + np.cos(np.pi * u))

    def _shape(
        self, s: np.ndarray, phi: np.ndarray, order: int = 0
    ) -> tuple[np.ndarray, np.ndarray]:
        """``(X, Z)`` of the cross-section (``(cos, sin)`` blended with the crest), or their
        ``order``-th derivative in ``phi``."""
        ex = np.real(
            1j**order * np.exp(1j * phi)
        )  # d^order of (cos, sin) = Re, Im of i^order e^{i phi}
        ez = np.imag(1j**order * np.exp(1j * phi))
        if self.crest is None:
            return ex, ez
        w = self.crest_weight(s)
        cx, cz = crest_shape()
        return ex + w * (_fourier(cx, phi, order) - ex), ez + w * (_fourier(cz, phi, order) - ez)

    def surface(self, s: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Surface points ``P(s, phi)``, shape ``broadcast(s, phi).shape + (3,)``."""
        # The basis depends on s only: with s (n, 1) and phi (1, m) it is computed n times.
        s, phi = np.asarray(s, float), np.asarray(phi, float)
        c, U, V = self.section_basis(s)
        if self.crest is not None:
            x, z = self._shape(s, phi)
            return c + x[..., None] * U + z[..., None] * V
        return c + np.cos(phi)[..., None] * U + np.sin(phi)[..., None] * V

    def _derivatives_crest(
        self, s: np.ndarray, phi: np.ndarray, second: bool
    ) -> tuple[np.ndarray, ...]:
        """:meth:`derivatives` of a bone with a crest: exact in ``phi``, central differences
        of the whole point in ``s`` (the crest weight depends on ``s`` too)."""
        hs = self._HS

        def at(sv: np.ndarray, order: int) -> np.ndarray:
            c, U, V = self.section_basis(sv)
            x, z = self._shape(sv, phi, order)
            return (c if order == 0 else 0.0) + x[..., None] * U + z[..., None] * V

        P, Pp = at(s, 0), at(s, 1)
        Pplus, Pminus = at(s + hs, 0), at(s - hs, 0)
        Ps = (Pplus - Pminus) / (2 * hs)
        if not second:
            return P, Ps, Pp
        Pss = (Pplus - 2 * P + Pminus) / hs**2
        Psph = (at(s + hs, 1) - at(s - hs, 1)) / (2 * hs)
        return P, Ps, Pp, Pss, Psph, at(s, 2)

    def derivatives(
        self, s: np.ndarray, phi: np.ndarray, second: bool = False
    ) -> tuple[np.ndarray, ...]:
        """``P, P_s, P_phi`` (and ``P_ss, P_sphi, P_phiphi`` if ``second``).

        Derivatives in ``phi`` are exact; those in ``s`` are central differences of the
        section basis (accurate to ~1e-8 mm: everything is a sum of sines).
        """
        hs = self._HS
        s, phi = np.asarray(s, float), np.asarray(phi, float)
        if self.crest is not None:
            return self._derivatives_crest(s, phi, second)
        c0, U0, V0 = self.section_basis(s)
        cp, Up, Vp = self.section_basis(s + hs)
        cm, Um, Vm = self.section_basis(s - hs)
        cph, sph = np.cos(phi)[..., None], np.sin(phi)[..., None]
        P = c0 + cph * U0 + sph * V0
        Pp = -sph * U0 + cph * V0
        d1 = [(x1 - x2) / (2 * hs) for x1, x2 in ((cp, cm), (Up, Um), (Vp, Vm))]
        Ps = d1[0] + cph * d1[1] + sph * d1[2]
        if not second:
            return P, Ps, Pp
        d2 = [
            (x1 - 2 * x0 + x2) / hs**2 for x1, x0, x2 in ((cp, c0, cm), (Up, U0, Um), (Vp, V0, Vm))
        ]
        Pss = d2[0] + cph * d2[1] + sph * d2[2]
        Psph = -sph * d1[1] + cph * d1[2]
        Pphph = -(cph * U0 + sph * V0)
        return P, Ps, Pp, Pss, Psph, Pphph

    def normals(self, s: np.ndarray, phi: np.ndarray) -> np.ndarray:
        """Outward unit normals ``P_phi x P_s`` normalised."""
        _, Ps, Pp = self.derivatives(s, phi)
        n = np.cross(Pp, Ps)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def top_height(self, s: np.ndarray | float, n_phi: int = 720) -> np.ndarray:
        """Height ``z`` of the highest surface point of the cross-section at ``s`` (mm)."""
        s = np.atleast_1d(np.asarray(s, float))
        phi = np.linspace(0, 2 * np.pi, n_phi, endpoint=False)
        z = self.surface(s[:, None], phi[None, :])[..., 2]
        return z.max(axis=1)

    # -- mesh ------------------------------------------------------------------------
    def mesh_params(self, ds: float = 0.5, n_around: int = 192) -> tuple[np.ndarray, np.ndarray]:
        """The ``(s, phi)`` grid of :meth:`mesh`: ``s`` (n_s,) and ``phi`` (n_around,)."""
        n_s = int(np.ceil(self.length / ds)) + 1
        return (
            np.linspace(0.0, self.length, n_s),
            np.linspace(0.0, 2 * np.pi, n_around, endpoint=False),
        )

    def mesh(self, ds: float = 0.5, n_around: int = 192) -> tuple[np.ndarray, np.ndarray]:
        """Triangulated open tube over ``s`` in ``[0, L]``, outward-oriented.

        With the defaults the chord error (distance between a triangle and the analytic
        surface) is below 0.003 mm for every bone: around, ``r (1 - cos(pi/192))`` with
        the largest radius of curvature of the sections (~20 mm); along, the axis and
        the diameters bend over tens of mm, so 0.5 mm steps are flat to ~1e-4 mm.

        Returns
        -------
        vertices : ndarray, shape (n_s * n_around, 3)
            Ring by ring: vertex ``r * n_around + q`` is ``P(s_r, phi_q)``.
        faces : ndarray of int64, shape (2 * (n_s - 1) * n_around, 3)
        """
        s, phi = self.mesh_params(ds, n_around)
        verts = self.surface(s[:, None], phi[None, :]).reshape(-1, 3)
        n_s, m = s.size, phi.size
        i, j = np.meshgrid(np.arange(n_s - 1), np.arange(m), indexing="ij")
        a = i * m + j
        b = i * m + (j + 1) % m
        c = (i + 1) * m + j
        d = (i + 1) * m + (j + 1) % m
        # (a, b, c): edges along phi then along s -> normal P_phi x P_s, outward.
        faces = np.concatenate(
            [np.stack([a, b, c], -1).reshape(-1, 3), np.stack([b, d, c], -1).reshape(-1, 3)]
        )
        return verts, faces.astype(np.int64)

    def closed_mesh(self, ds: float = 0.5, n_around: int = 192) -> tuple[np.ndarray, np.ndarray]:
        """The whole simulated bone segment as a closed, outward-oriented triangle mesh (mm).

        :meth:`mesh`'s tube capped at ``s = 0`` and ``s = L`` by a fan around the axis
        point, so every edge is shared by exactly two triangles: what a bone model
        segmented from CT looks like to a registration (a watertight surface), here
        with a known position. ``2 * (n_s - 1) * n_around + 2 * n_around`` triangles
        (``n_s = ceil(L / ds) + 1``); :meth:`closed_mesh_params` picks ``ds`` for a
        triangle budget.

        Returns
        -------
        vertices : ndarray, shape (n_s * n_around + 2, 3)
            The tube's vertices, then the two cap centres.
        faces : ndarray of int64, shape (F, 3)
        """
        verts, faces = self.mesh(ds, n_around)
        n_v = verts.shape[0]
        centres = self.axis(np.array([0.0, self.length]))
        j = np.arange(n_around)
        jn = (j + 1) % n_around
        last = n_v - n_around
        # Tube triangles (a, b, c) run along phi then along s with an outward normal;
        # at s = 0 the outside is -t, so the fan goes (centre, next, this) there.
        cap0 = np.stack([np.full(n_around, n_v), jn, j], -1)
        cap1 = np.stack([np.full(n_around, n_v + 1), last + j, last + jn], -1)
        return np.vstack([verts, centres]), np.vstack([faces, cap0, cap1]).astype(np.int64)

    def closed_mesh_params(self, n_triangles: int, n_around: int = 192) -> tuple[float, int]:
        """``(ds, n_around)`` for :meth:`closed_mesh` with about ``n_triangles`` triangles.

        ``n_around`` is lowered (never below 24) for small budgets, so that rings stay
        more than ~10 along the bone; ``ds`` then follows from
        ``2 n_around (n_s - 1) + 2 n_around`` triangles.
        """
        if n_triangles < 200:
            raise ValueError(f"n_triangles must be at least 200, got {n_triangles}")
        m = int(max(24, min(n_around, n_triangles // 20)))
        n_s = max(2, int(round((n_triangles - 2 * m) / (2 * m))) + 1)
        # Slightly above L / (n_s - 1), so that mesh_params' ceil gives n_s rings.
        return self.length / (n_s - 1) * (1 + 1e-12), m

    # -- closest points -------------------------------------------------------------------
    def _seed_tree(self) -> tuple[cKDTree, np.ndarray]:
        if self._tree is None:
            s, phi = self.mesh_params(ds=0.5, n_around=180)
            S, PH = np.meshgrid(s, phi, indexing="ij")
            self._tree = cKDTree(self.surface(S, PH).reshape(-1, 3))
            self._tree_params = np.column_stack([S.reshape(-1), PH.reshape(-1)])
        assert self._tree_params is not None
        return self._tree, self._tree_params

    def closest_points(
        self,
        points: np.ndarray,
        iterations: int = 10,
        s_limits: tuple[float, float] | None = None,
    ) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Project points onto the surface (vectorised Newton on ``(s, phi)``).

        Starts from the nearest vertex of a 0.5 mm x 2 deg grid (kd-tree), then runs
        Newton steps on ``f = |P(s, phi) - q|^2 / 2`` with the exact Hessian, falling
        back to Gauss-Newton where the Hessian is not positive definite (points deep
        inside the bone). Stops when every step is below 1e-9 mm. ``s`` is clamped to
        ``s_limits`` (default ``[0, L]``): beyond them the distance is to the tube's end
        ring.

        Parameters
        ----------
        points : ndarray, shape (K, 3)
        iterations : int
            Newton steps at most (one more per 2 mm the limits reach past ``[0, L]``).
        s_limits : (float, float), optional
            The range of ``s`` the surface is taken over (the surface's formula holds
            past ``[0, L]``, and a tilted image plane near a sweep's end shows it there:
            :meth:`.core.Simulation.distance_to_truth`).

        Returns
        -------
        s, phi : ndarray, shape (K,)
        foot : ndarray, shape (K, 3)
            Closest surface points.
        distance : ndarray, shape (K,)
            Unsigned distances (mm).
        """
        q = np.asarray(points, float).reshape(-1, 3)
        if q.shape[0] == 0:
            e = np.empty(0)
            return e, e, np.empty((0, 3)), e
        lo, hi = (0.0, self.length) if s_limits is None else s_limits
        # The seeds lie in [0, L] and a step moves s by 2 mm at most: steps to reach
        # the limits' far ends too.
        iterations += int(np.ceil(max(-lo, hi - self.length, 0.0) / 2.0))
        tree, params = self._seed_tree()
        _, idx = tree.query(q)
        s = params[idx, 0].copy()
        phi = params[idx, 1].copy()
        for _ in range(iterations):
            P, Ps, Pp, Pss, Psp, Ppp = self.derivatives(s, phi, second=True)
            r = P - q
            gs = np.einsum("ki,ki->k", Ps, r)
            gp = np.einsum("ki,ki->k", Pp, r)
            jss = np.einsum("ki,ki->k", Ps, Ps)
            jsp = np.einsum("ki,ki->k", Ps, Pp)
            jpp = np.einsum("ki,ki->k", Pp, Pp)
            hss = jss + np.einsum("ki,ki->k", Pss, r)
            hsp = jsp + np.einsum("ki,ki->k", Psp, r)
            hpp = jpp + np.einsum("ki,ki->k", Ppp, r)
            det = hss * hpp - hsp**2
            bad = (det <= 1e-12) | (hss <= 0)
            hss = np.where(bad, jss, hss)
            hsp = np.where(bad, jsp, hsp)
            hpp = np.where(bad, jpp, hpp)
            det = hss * hpp - hsp**2
            ds = -(hpp * gs - hsp * gp) / det
            dp = -(-hsp * gs + hss * gp) / det
            # Trust region: never jump further than the seed grid's cell size allows.
            s = np.clip(s + np.clip(ds, -2.0, 2.0), lo, hi)
            phi = phi + np.clip(dp, -0.3, 0.3)
            if max(np.abs(ds).max(), np.abs(dp).max() * 30.0) < 1e-9:
                break  # converged everywhere (quadratic convergence: usually 3-4 steps)
        foot = self.surface(s, phi)
        return s, np.mod(phi, 2 * np.pi), foot, np.linalg.norm(foot - q, axis=1)

    def distance(
        self, points: np.ndarray, s_limits: tuple[float, float] | None = None
    ) -> np.ndarray:
        """Unsigned distance (mm) from each point ``(K, 3)`` to the surface
        (``s_limits``: as :meth:`closest_points`)."""
        return self.closest_points(points, s_limits=s_limits)[3]

    # -- plane sections -------------------------------------------------------------------
    def plane_section(
        self,
        origin: np.ndarray,
        normal: np.ndarray,
        s_guess: np.ndarray,
        phi: np.ndarray,
        iterations: int = 8,
    ) -> tuple[np.ndarray, np.ndarray]:
        """Intersect planes with the surface, one ``s`` per ``(plane, phi)``.

        Solves ``n . (P(s, phi) - o) = 0`` for ``s`` by Newton's method; the planes must
        be roughly perpendicular to the axis (true for a probe sweeping across the bone).

        Parameters
        ----------
        origin, normal : ndarray, shape (N, 3)
        s_guess : ndarray, shape (N,)
        phi : ndarray, shape (M,)

        Returns
        -------
        s : ndarray, shape (N, M)
        points : ndarray, shape (N, M, 3)
        """
        o = np.asarray(origin, float)[:, None, :]
        n = np.asarray(normal, float)[:, None, :]
        s = np.broadcast_to(np.asarray(s_guess, float)[:, None], (o.shape[0], phi.size)).copy()
        ph = np.broadcast_to(phi[None, :], s.shape)
        cph, sph = np.cos(ph)[..., None], np.sin(ph)[..., None]
        hs = self._HS
        for _ in range(iterations):
            if self.crest is not None:
                f0 = np.sum(n * (self.surface(s, ph) - o), axis=-1)
                step = f0 * hs / (np.sum(n * (self.surface(s + hs, ph) - o), axis=-1) - f0)
                s = s - step
                if np.abs(step).max() < 1e-7:
                    break
                continue
            # Newton on s with a forward difference: two basis evaluations per step.
            c0, U0, V0 = self.section_basis(s)
            c1, U1, V1 = self.section_basis(s + hs)
            f0 = np.sum(n * (c0 + cph * U0 + sph * V0 - o), axis=-1)
            f1 = np.sum(n * (c1 + cph * U1 + sph * V1 - o), axis=-1)
            step = f0 * hs / (f1 - f0)
            s = s - step
            if np.abs(step).max() < 1e-7:
                break
        return s, self.surface(s, ph)

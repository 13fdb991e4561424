"""Where each image plane cuts the bone: the true bone line in pixels.

For every frame the plane of the image is intersected with the analytic bone surface
(:meth:`BoneGeometry.plane_section`), the section is mapped to pixel coordinates, and
its upper arc (the part whose surface normal faces the beam) gives, for every image
column, the row of the first bone surface met by the beam and the cosine of the angle
of incidence there. The image formation draws the bone echo exactly on that row, so
the contours reported here are the true answer for a segmenter.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from BoneUSRecon.Logic.simulation.bones import BoneGeometry

__all__ = ["BoneSections", "bone_sections", "visible_contours"]


@dataclass(frozen=True, eq=False)
class BoneSections:
    """Bone surface met by each column's beam, per frame."""

    #: Row (sub-pixel) of the bone surface per column, NaN where the beam misses the
    #: bone, shape (N, W).
    top_j: np.ndarray
    #: cos(angle between the beam and the surface normal), 0 where no bone, shape (N, W).
    cos_incidence: np.ndarray
    #: Range of the axis parameter ``s`` each section spans (mm), shape (N, 2).
    s_range: np.ndarray
    #: Row of the far (deep) bone surface per column, NaN where the beam misses the
    #: bone, shape (N, W); only when asked for (``far=True``), else None.
    bottom_j: np.ndarray | None = None


def bone_sections(
    geom: BoneGeometry,
    image_to_reference: np.ndarray,
    s_guess: np.ndarray,
    width: int,
    n_phi: int = 720,
    far: bool = False,
) -> BoneSections:
    """Intersect every frame's plane with the bone.

    Parameters
    ----------
    geom : BoneGeometry
    image_to_reference : ndarray, shape (N, 4, 4)
    s_guess : ndarray, shape (N,)
        Axis parameter near each plane (where the probe is).
    width : int
        Image columns.
    n_phi : int
        Samples around the section; 720 (0.5 degree, < 0.1 mm apart) keeps the linear
        interpolation between them within ~1e-4 mm of the true curve.
    far : bool
        Also find the far surface (the lower arc) per column: ``bottom_j``.

    Returns
    -------
    BoneSections
    """
    m = np.asarray(image_to_reference, float)
    n = m.shape[0]
    ex, ey, origin = m[:, :3, 0], m[:, :3, 1], m[:, :3, 3]
    sx2 = np.einsum("ni,ni->n", ex, ex)
    sy2 = np.einsum("ni,ni->n", ey, ey)
    normal = np.cross(ex, ey)
    normal /= np.linalg.norm(normal, axis=1, keepdims=True)
    beam = ey / np.sqrt(sy2)[:, None]

    phi = np.linspace(0.0, 2 * np.pi, n_phi, endpoint=False)
    s, pts = geom.plane_section(origin, normal, s_guess, phi)
    nrm = geom.normals(s, np.broadcast_to(phi, s.shape))
    d = pts - origin[:, None, :]
    i_px = np.einsum("nmk,nk->nm", d, ex) / sx2[:, None]
    j_px = np.einsum("nmk,nk->nm", d, ey) / sy2[:, None]
    cos = -np.einsum("nmk,nk->nm", nrm, beam)

    top = np.full((n, width), np.nan)
    cosw = np.zeros((n, width))
    bottom = np.full((n, width), np.nan) if far else None
    cols = np.arange(width, dtype=float)
    for k in range(n):
        up = cos[k] > 0
        if not up.any():
            continue
        # Roll so the upper arc (contiguous: the section is convex) starts at index 0.
        start = int(np.flatnonzero(up & ~np.roll(up, 1))[0]) if not up.all() else 0
        order = np.roll(np.arange(n_phi), -start)
        arc = order[up[order]]
        ii, jj, cc = i_px[k, arc], j_px[k, arc], cos[k, arc]
        srt = np.argsort(ii)
        ii, jj, cc = ii[srt], jj[srt], cc[srt]
        inside = (cols >= ii[0]) & (cols <= ii[-1])
        top[k, inside] = np.interp(cols[inside], ii, jj)
        cosw[k, inside] = np.interp(cols[inside], ii, cc)
        if bottom is not None and not up.all():
            low = order[~up[order]]
            il, jl = i_px[k, low], j_px[k, low]
            srt = np.argsort(il)
            il, jl = il[srt], jl[srt]
            inside = (cols >= il[0]) & (cols <= il[-1])
            bottom[k, inside] = np.interp(cols[inside], il, jl)
    return BoneSections(
        top_j=top,
        cos_incidence=cosw,
        s_range=np.column_stack([s.min(1), s.max(1)]),
        bottom_j=bottom,
    )


def visible_contours(
    sections: BoneSections,
    height: int,
    visible_cos: float,
    hidden: set[int] | None = None,
    strength: np.ndarray | None = None,
    min_strength: float = 0.0,
) -> list[np.ndarray]:
    """The visible bone contour of each frame, in pixels ``(i, j)`` ordered by ``i``.

    A column is part of the visible contour when its beam meets the bone inside the
    image with ``cos(incidence) >= visible_cos`` (an oblique bone surface sends its
    specular echo away from the probe and is not seen) and, if ``strength`` (N, W) is
    given, a relative echo strength of at least ``min_strength``. Frames in ``hidden``
    (probe contact lost) have an empty contour.

    Returns
    -------
    list of ndarray, each of shape (K, 2)
    """
    out = []
    hidden = hidden or set()
    for k in range(sections.top_j.shape[0]):
        j = sections.top_j[k]
        ok = np.isfinite(j) & (sections.cos_incidence[k] >= visible_cos)
        if strength is not None:
            ok &= strength[k] >= min_strength
        ok &= (np.nan_to_num(j, nan=-1.0) >= 0) & (np.nan_to_num(j, nan=-1.0) <= height - 1)
        if k in hidden:
            ok[:] = False
        i = np.flatnonzero(ok).astype(float)
        out.append(np.column_stack([i, j[ok]]) if i.size else np.empty((0, 2)))
    return out

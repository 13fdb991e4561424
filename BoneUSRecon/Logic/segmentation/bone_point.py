"""The bone the user points at: "bone points" make the track follow that bone.

Where two bones are in view (the radius beside the ulna, the fibula beside the tibia,
15-30 mm apart), the track follows the one near the middle of the image
(:func:`.track.central_track`). A user who swept the bone off-centre, or who wants the
other one, places a point on it (a markup fiducial on the bone in the reconstructed
volume or a slice of it; reference mm, the coordinates ``ImageToReference`` maps
pixels into): ``RejectionParams.bone_points``.

* A point's frames are those whose image plane passes within
  ``RejectionParams.point_plane_mm`` of it.
* In those frames only candidates whose contour passes within ``point_contour_mm`` of
  the point (projected into the frame's plane, in-plane distance) may be on the track;
  a frame of the point without such a candidate is rejected as "no contour at the bone
  point" (the distance of its nearest contour is its detail).
* The track must pass through the allowed candidates: the default track where it
  already does, else the best over those through the most of them, kept to the pointed
  bone away from the points by the lane rules measured from the points' own image
  column (:func:`.track.pointed_track`).
* A point with no candidate near it in any of its frames is taken to the nearest
  frame before them and the nearest after them that has one, up to the track's
  reach and as far along the sweep as the bone's top may drift by at most
  ``point_contour_mm`` (:func:`_frames_beyond`): those frames are the point's too.
  A bone's faint top may be no candidate in a few frames while its far cortex, 10 mm
  under it, is (small off-centre forearm sweeps near their end, where the bone lies
  6-7 mm deep): the point was left out and the track followed the other bone.
* A point with no candidate near it in any of those frames (the bone missed there, or
  the point placed off it) is left out, and the track chosen as without it:
  :func:`point_warnings` says so in the segmentation's summary. Refusing the whole
  sweep would lose a surface the default rules may well get right; following the
  nearest contour would follow whatever lies nearest, maybe the other bone.

A point that lies farther than ``point_plane_mm`` from every frame's plane, or whose
projection falls outside every image, is an error (:func:`check_bone_points`): it is
not on this sweep (the wrong sweep, or the wrong coordinates).

Points all on one bone: two points on two bones whose frames overlap rule out
every candidate of the frames they share.

Live (:class:`~BoneUSRecon.Logic.live.LiveReconstructor`, the same incremental track):
a point takes effect once frames pass near it, and is judged against the frames
received so far. A refit during the scan says nothing of a point off those frames
(the probe may not have reached it yet) and warns of a point they reach but no
contour does (:func:`point_warnings`, as offline). The final refit (the scan over)
reports a point off the whole sweep as a warning with the batch error's sentence
(:func:`off_sweep_points`), not as an error: offline the sweep file can be run again
with the point corrected, while a live scan cannot be given again, and its surface,
built as without the point (a point off the sweep rules out no candidate), is worth
keeping.
"""

from __future__ import annotations

from collections.abc import Collection, Sequence
from pathlib import Path

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.segmentation.candidates import FrameCandidates
from BoneUSRecon.Logic.segmentation.params import RejectionParams
from BoneUSRecon.Logic.sweep import frame_planes

__all__ = [
    "OFF_POINT",
    "check_bone_points",
    "off_sweep_points",
    "point_marks",
    "point_warnings",
]

#: Rejection reason of a frame of a bone point with no candidate near the point.
OFF_POINT = "no contour at the bone point"


def _in_planes(points: np.ndarray, poses: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each point in each frame's plane: lateral, depth and |out of plane| mm, (N, P) each."""
    origin, axes, normal = frame_planes(poses)
    rel = points[None, :, :] - origin[:, None, :]
    lateral = np.einsum("npk,nk->np", rel, axes[:, :, 0])
    depth = np.einsum("npk,nk->np", rel, axes[:, :, 1])
    return lateral, depth, np.abs(np.einsum("npk,nk->np", rel, normal))


def _label(points: np.ndarray, q: int) -> str:
    x, y, z = points[q]
    return f"bone point {q + 1} ({x:.1f}, {y:.1f}, {z:.1f} mm)"


def off_sweep_points(
    image_to_reference: np.ndarray,
    shape: tuple[int, int],
    params: RejectionParams,
) -> dict[int, str]:
    """The bone points that are not on the sweep, each with why (one sentence).

    Parameters
    ----------
    image_to_reference : ndarray, shape (N, 4, 4)
        The poses of the frames.
    shape : (int, int)
        The frames' ``(height, width)`` in pixels.
    params : RejectionParams
        Its ``bone_points`` and ``point_plane_mm``.

    Returns
    -------
    dict of int to str
        Index of the point in ``params.bone_points`` -> why it is not on the sweep: it
        lies farther than ``point_plane_mm`` from every frame's plane, or its
        projection into every frame that near lies outside the image. Empty when all
        are on it (or there are none).
    """
    if not params.bone_points:
        return {}
    pts = np.asarray(params.bone_points, dtype=float).reshape(-1, 3)
    poses = np.asarray(image_to_reference, dtype=float).reshape(-1, 4, 4)
    if poses.shape[0] == 0:
        return {q: f"{_label(pts, q)}: no frame to place it in" for q in range(pts.shape[0])}
    lateral, depth, z = _in_planes(pts, poses)
    sx = np.linalg.norm(poses[:, :3, 0], axis=1)[:, None]
    sy = np.linalg.norm(poses[:, :3, 1], axis=1)[:, None]
    h, w = shape
    inside = (lateral >= 0) & (lateral <= (w - 1) * sx) & (depth >= 0) & (depth <= (h - 1) * sy)
    near = z <= params.point_plane_mm
    out: dict[int, str] = {}
    for q in range(pts.shape[0]):
        if not near[:, q].any():
            out[q] = (
                f"{_label(pts, q)} lies {z[:, q].min():.1f} mm from the nearest frame's plane "
                f"(at most {params.point_plane_mm:g} mm): it is not on this sweep"
            )
        elif not (near[:, q] & inside[:, q]).any():
            out[q] = (
                f"{_label(pts, q)} lies outside the image of every frame within "
                f"{params.point_plane_mm:g} mm of it: it is not on this sweep"
            )
    return out


def check_bone_points(
    image_to_reference: np.ndarray,
    shape: tuple[int, int],
    params: RejectionParams,
    source: str | Path | None = None,
) -> None:
    """Refuse bone points that are not on the sweep (:func:`off_sweep_points`).

    Parameters
    ----------
    image_to_reference : ndarray, shape (N, 4, 4)
        The poses of the frames to segment.
    shape : (int, int)
        The frames' ``(height, width)`` in pixels.
    params : RejectionParams
        Its ``bone_points`` and ``point_plane_mm``.
    source : path, optional
        The sweep's file, named in the error.

    Raises
    ------
    BoneUSReconError
        The first point farther than ``point_plane_mm`` from every frame's plane, or
        whose projection into every frame that near lies outside the image.
    """
    off = off_sweep_points(image_to_reference, shape, params)
    if off:
        raise BoneUSReconError(off[min(off)], source)


def _contour_distance(fc: FrameCandidates, c: int, lateral: float, depth: float) -> float:
    """In-plane distance (mm) from ``(lateral, depth)`` mm to candidate ``c``'s contour."""
    pts = fc.candidates[c].points_px
    if pts.shape[0] == 0:
        return np.inf
    d = pts * np.asarray(fc.spacing, dtype=float) - (lateral, depth)
    return float(np.sqrt((d * d).sum(axis=1).min()))


def _frames_beyond(
    frames: Sequence[FrameCandidates],
    nodes: Sequence[tuple[int, int]],
    lateral: np.ndarray,
    depth: np.ndarray,
    z: np.ndarray,
    q: int,
    near_plane: np.ndarray,
    params: RejectionParams,
) -> dict[int, dict[int, float]]:
    """For a point none of whose frames has a candidate near it: the nearest frame
    before them and the nearest after them that has one (none, one or two frames),
    each with its candidates' distances to the point (node index -> mm).

    A frame is looked for up to ``max_skip + 1`` frames beyond the point's (the track's
    own reach), whose plane lies within ``point_plane_mm + point_contour_mm /
    tolerance_per_mm`` of the point: past its frames the bone's top drifts in plane by
    up to ``tolerance_per_mm`` per mm along the sweep (the track's link tolerance), so
    a contour still within ``point_contour_mm`` of the point that far is on the bone
    the point is on (12.5 mm with the defaults).
    """
    p = params
    reach_mm = (
        p.point_plane_mm + p.point_contour_mm / p.tolerance_per_mm
        if p.tolerance_per_mm > 0
        else np.inf
    )
    own = np.flatnonzero(near_plane[:, q])
    by_frame: dict[int, list[int]] = {}
    for k, (f, _) in enumerate(nodes):
        by_frame.setdefault(f, []).append(k)
    out: dict[int, dict[int, float]] = {}
    for side in (
        range(int(own[0]) - 1, max(-1, int(own[0]) - p.max_skip - 2), -1),
        range(int(own[-1]) + 1, min(z.shape[0], int(own[-1]) + p.max_skip + 2)),
    ):
        for f in side:
            if z[f, q] > reach_mm or f not in by_frame:
                continue
            d = {
                k: _contour_distance(frames[f], nodes[k][1], lateral[f, q], depth[f, q])
                for k in by_frame[f]
            }
            if min(d.values()) <= p.point_contour_mm:
                out[f] = d
                break
    return out


def point_marks(
    frames: Sequence[FrameCandidates],
    poses: np.ndarray,
    nodes: Sequence[tuple[int, int]],
    params: RejectionParams,
) -> tuple[np.ndarray, dict[int, tuple[str, str]]]:
    """What the bone points say of each node of the track.

    Parameters
    ----------
    frames : sequence of FrameCandidates
    poses : ndarray, shape (N, 4, 4)
    nodes : sequence of (frame, candidate)
        The track's nodes.
    params : RejectionParams

    Returns
    -------
    mark : ndarray of int8, shape (len(nodes),)
        1: a candidate near a point, in its frame (the track is to pass through such
        nodes); -1: another candidate of such a frame (ruled out); 0: the points say
        nothing of it. A point with no candidate near it in any of its frames has
        the nearest frames beyond them that have one (:func:`_frames_beyond`) as
        frames too; points with none even there are left out (all 0: the track as
        without them).
    off : dict of int to (str, str)
        Frames of a point kept in which no candidate is near it: :data:`OFF_POINT`
        and the distance of the nearest one.
    """
    mark = np.zeros(len(nodes), dtype=np.int8)
    if not params.bone_points or not nodes:
        return mark, {}
    pts = np.asarray(params.bone_points, dtype=float).reshape(-1, 3)
    lateral, depth, z = _in_planes(pts, np.asarray(poses, dtype=float).reshape(-1, 4, 4))
    near_plane = z <= params.point_plane_mm
    dist = np.full((len(nodes), pts.shape[0]), np.inf)
    for k, (f, c) in enumerate(nodes):
        for q in np.flatnonzero(near_plane[f]).tolist():
            dist[k, q] = _contour_distance(frames[f], c, lateral[f, q], depth[f, q])
    near = dist <= params.point_contour_mm
    for q in np.flatnonzero(~near.any(axis=0) & near_plane.any(axis=0)).tolist():
        for f, d in _frames_beyond(frames, nodes, lateral, depth, z, q, near_plane, params).items():
            near_plane[f, q] = True
            for k, mm in d.items():
                dist[k, q] = mm
    near = dist <= params.point_contour_mm
    kept = near.any(axis=0)  # the points with a candidate near them somewhere
    if not kept.any():
        return mark, {}
    node_frames = np.array([f for f, _ in nodes])
    pointed = near_plane[node_frames][:, kept].any(axis=1)
    mark[pointed] = -1
    mark[near[:, kept].any(axis=1)] = 1
    off: dict[int, tuple[str, str]] = {}
    for f in np.unique(node_frames[pointed]).tolist():
        ks = np.flatnonzero(node_frames == f)
        if (mark[ks] == 1).any():
            continue
        q_near = np.flatnonzero(near_plane[f] & kept)
        d = dist[np.ix_(ks, q_near)]
        row, col = np.unravel_index(int(np.argmin(d)), d.shape)
        off[f] = (OFF_POINT, f"{d[row, col]:.1f} mm from bone point {int(q_near[col]) + 1}")
    return mark, off


def point_warnings(
    contours_mm: Sequence[tuple[int, np.ndarray]],
    image_to_reference: np.ndarray,
    params: RejectionParams,
    *,
    skip: Collection[int] = (),
) -> tuple[str, ...]:
    """Bone points the final track does not reach, one sentence each.

    Parameters
    ----------
    contours_mm : sequence of (frame, ndarray (K, 3))
        The accepted contours, reference mm, with the index of their frame in
        ``image_to_reference``.
    image_to_reference : ndarray, shape (N, 4, 4)
        The poses of the sweep's frames.
    params : RejectionParams
    skip : collection of int
        Indices of points in ``params.bone_points`` not to judge (e.g. those
        :func:`off_sweep_points` already reports).

    Returns
    -------
    tuple of str
        In point order; empty when every point has an accepted contour within
        ``point_contour_mm`` in one of its frames (in-plane distance).
    """
    if not params.bone_points:
        return ()
    pts = np.asarray(params.bone_points, dtype=float).reshape(-1, 3)
    poses = np.asarray(image_to_reference, dtype=float).reshape(-1, 4, 4)
    _, _, off_plane = _in_planes(pts, poses)
    out = []
    for q in range(pts.shape[0]):
        if q in skip:
            continue
        best = np.inf
        for f, xyz in contours_mm:
            z = off_plane[f, q]
            if z > params.point_plane_mm or xyz.shape[0] == 0:
                continue
            # The contour lies in the frame's plane: its in-plane distance to the
            # point's projection is the 3D distance with the out-of-plane part taken off.
            d2 = float(((xyz - pts[q]) ** 2).sum(axis=1).min()) - z * z
            best = min(best, float(np.sqrt(max(d2, 0.0))))
        if not best <= params.point_contour_mm:
            nearest = "none in its frames" if not np.isfinite(best) else f"nearest {best:.1f} mm"
            out.append(
                f"{_label(pts, q)}: no accepted contour within {params.point_contour_mm:g} mm "
                f"of it ({nearest}): the track does not follow the bone there"
            )
    return tuple(out)

"""The registration's entry points: :func:`register` and :func:`register_polydata`."""

from __future__ import annotations

import os
import time
from typing import Any

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.registration.geometry import (
    check_units,
    landmark_transform,
    patch_normal,
    transform_points,
)
from BoneUSRecon.Logic.registration.icp import Cloud, best_of, local_starts, search_starts
from BoneUSRecon.Logic.registration.model import BoneModel, model_from_polydata
from BoneUSRecon.Logic.registration.params import RegistrationParams
from BoneUSRecon.Logic.registration.quality import quality, unreliable_reasons
from BoneUSRecon.Logic.registration.result import Registration

__all__ = ["register", "register_polydata", "register_reconstruction", "towards_probe"]


def register(
    source: np.ndarray,
    model: BoneModel,
    params: RegistrationParams | None = None,
    *,
    source_normals: np.ndarray | None = None,
    towards_probe: np.ndarray | None = None,
    init: np.ndarray | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    source_path: str | os.PathLike[str] | None = None,
    model_path: str | os.PathLike[str] | None = None,
) -> Registration:
    """Rigidly register ``source`` points to a bone ``model``.

    Parameters
    ----------
    source : ndarray (K, 3)
        The reconstructed surface's vertices or the segmented points (mm, SOURCE frame).
    model : BoneModel
        From :func:`bone_model` / :func:`model_from_polydata` (mm, TARGET frame).
    params : RegistrationParams, optional
        Default ``RegistrationParams()``.
    source_normals : ndarray (K, 3), optional
        Outward normals of the source (a reconstructed surface has them, pointing to
        the probe); matched within ``max_normal_angle_deg``.
    towards_probe : ndarray (K, 3), optional
        For points without normals (segmented points): the direction from each point
        towards the probe that saw it (:func:`towards_probe`). The imaged bone faces
        the probe, so this stands for the normal, within ``patch_normal_angle_deg``.
        Without either, the source is taken as a patch seen from one side: its
        :func:`patch_normal` stands for every point's, and both sides are tried
        (slower, and from 15 mm / 15 deg away 2 of 10 clavicle trials took the wrong
        side, flagged).
    init : ndarray (4, 4), optional
        Initial SOURCE -> TARGET matrix for ``init="identity"`` (default the identity).
    landmarks : (ndarray (K, 3), ndarray (K, 3)), optional
        Paired source and target landmarks; required by ``init="landmarks"`` (and
        then used instead of ``init``).
    source_path, model_path : path-like, optional
        Named in errors.

    Returns
    -------
    Registration

    Raises
    ------
    BoneUSReconError
        Too few or non-finite source points, a unit mismatch (:func:`check_units`),
        bad landmarks, or inputs that do not overlap (fewer than ``min_overlap`` of
        the source points near the model at the start or fitting it at the end: a
        clear failure instead of a silent wrong transform).
    """
    t0 = time.perf_counter()
    params = RegistrationParams() if params is None else params
    src = np.asarray(source, float).reshape(-1, 3)
    if src.shape[0] < 6:
        raise BoneUSReconError(f"need at least 6 source points, got {src.shape[0]}", source_path)
    if not np.isfinite(src).all():
        raise BoneUSReconError("source points contain NaN or infinity", source_path)
    check_units(src, model, source_path, model_path)
    oriented = source_normals is not None or towards_probe is not None
    if oriented:
        given = source_normals if source_normals is not None else towards_probe
        nrm = np.asarray(given, float).reshape(-1, 3)
        if nrm.shape != src.shape:
            raise BoneUSReconError(f"{len(nrm)} source normals for {len(src)} points", source_path)
        length = np.linalg.norm(nrm, axis=1)
        good = np.isfinite(length) & (length > 0)
        nrm = np.where(good[:, None], nrm / np.where(good, length, 1.0)[:, None], 0.0)
    else:
        nrm = np.broadcast_to(patch_normal(src), src.shape)
    # Exact normals, or a direction the surface faces only roughly (patch, probe).
    angle = (
        params.max_normal_angle_deg if source_normals is not None else params.patch_normal_angle_deg
    )
    cloud = Cloud(src, np.ascontiguousarray(nrm), angle)
    sub = cloud.subset(params.max_source_points)
    lm_rms = None
    method = "landmarks" if landmarks is not None else params.init
    if method == "landmarks":
        if landmarks is None:
            raise BoneUSReconError("init='landmarks' needs paired source and target landmarks")
        m0, lm_rms = landmark_transform(*landmarks)
    elif method == "search":
        m0 = np.eye(4)
    else:
        m0 = np.eye(4) if init is None else np.asarray(init, float)
        if m0.shape != (4, 4) or not np.isfinite(m0).all():
            raise BoneUSReconError(
                f"the initial transform must be a finite 4x4 matrix, got shape {m0.shape}"
            )
        if (
            not np.allclose(m0[:3, :3] @ m0[:3, :3].T, np.eye(3), atol=1e-4)
            or np.linalg.det(m0[:3, :3]) < 0
        ):
            raise BoneUSReconError(
                "the initial transform is not rigid (a rotation and a translation)"
            )
    if method == "search":
        mats = search_starts(sub.points, model, params)
    else:
        # Overlap at the start: a start far from the model is refused, not "registered".
        d0, _ = model.tree.query(
            transform_points(m0, sub.points), distance_upper_bound=params.max_distance_mm
        )
        near0 = float(np.isfinite(d0).mean())
        if near0 < params.min_overlap:
            raise BoneUSReconError(
                f"the source and the model do not overlap: only {100 * near0:.0f}% of the source points lie "
                f"within {params.max_distance_mm:g} mm of the model at the initial alignment (give paired "
                "landmarks or an initial matrix, or use the global search)",
                source_path,
            )
        mats = [m0, *local_starts(sub.points, m0, params)]
    # A patch normal has no known side: every start is tried with both.
    starts = [(m, flip) for m in mats for flip in ((False,) if oriented else (False, True))]
    st, flipped, alt = best_of(sub, model, starts, params)
    q = quality(cloud.flipped() if flipped else cloud, model, st, params)
    if q["inlier_share"] < params.min_overlap:
        raise BoneUSReconError(
            f"registration failed: only {100 * q['inlier_share']:.0f}% of the source points fit the model "
            f"at the end (at least {100 * params.min_overlap:.0f}% needed); the inputs do not overlap or "
            "the initial alignment is too far off",
            source_path,
        )
    reasons = unreliable_reasons(q, st, params)
    if alt is not None:
        reasons.append(
            f"another alignment {alt[0]:.1f} mm away (median over the source points) fits about as well "
            f"(residual {alt[1]:.2f} against {alt[2]:.2f} mm): the imaged surface matches the model in two places"
        )
    return Registration(
        matrix=st.matrix,
        initial=m0,
        rms_mm=q["rms_mm"],
        median_mm=q["median_mm"],
        p95_mm=q["p95_mm"],
        inlier_share=q["inlier_share"],
        n_source=int(src.shape[0]),
        n_inliers=q["n_inliers"],
        iterations=st.iterations,
        converged=st.converged,
        eigenvalues=q["eigenvalues"],
        condition=q["condition"],
        sliding_mm=q["sliding_mm"],
        directions=q["directions"],
        reliable=not reasons,
        reasons=tuple(reasons),
        landmark_rms_mm=lm_rms,
        long_axis=q["long_axis"],
        seconds=time.perf_counter() - t0,
    )


def register_polydata(
    source: Any,
    target: Any,
    params: RegistrationParams | None = None,
    *,
    init: np.ndarray | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    source_path: str | os.PathLike[str] | None = None,
    target_path: str | os.PathLike[str] | None = None,
) -> Registration:
    """:func:`register` on ``vtkPolyData``: the source's points (a surface or a point
    cloud; its point ``Normals`` used when present) to the target's triangles. See
    :func:`register` for the arguments."""
    from vtkmodules.util import numpy_support

    from BoneUSRecon.Logic.vtkio import polydata_points

    model = model_from_polydata(target, target_path)
    pts = polydata_points(source)
    if pts.shape[0] == 0:
        raise BoneUSReconError("the source has no points", source_path)
    arr = source.GetPointData().GetNormals()
    normals = numpy_support.vtk_to_numpy(arr).astype(float) if arr is not None else None
    return register(
        pts,
        model,
        params,
        source_normals=normals,
        init=init,
        landmarks=landmarks,
        source_path=source_path,
        model_path=target_path,
    )


def towards_probe(points: Any, image_to_reference: np.ndarray) -> np.ndarray:
    """Unit direction from each segmented point towards the probe that imaged it.

    Parameters
    ----------
    points : vtkPolyData
        Segmented points with their ``Frame`` point array (as
        :attr:`Reconstruction.points`).
    image_to_reference : ndarray (N, 4, 4)
        The sweep's poses. The image's row axis ``j`` points down the beam, away from
        the transducer (PLUS ``MF``, as every :class:`Sweep` is stored), so the probe
        is at ``-j``.

    Returns
    -------
    ndarray (K, 3)
    """
    from vtkmodules.util import numpy_support

    arr = points.GetPointData().GetArray("Frame")
    if arr is None:
        raise BoneUSReconError("the segmented points have no Frame array")
    frames = numpy_support.vtk_to_numpy(arr).astype(np.int64)
    down = np.asarray(image_to_reference, float)[frames, :3, 1]
    return -down / np.linalg.norm(down, axis=1, keepdims=True)


def register_reconstruction(
    recon: Any,
    model: BoneModel,
    params: RegistrationParams | None = None,
    *,
    init: np.ndarray | None = None,
    landmarks: tuple[np.ndarray, np.ndarray] | None = None,
    model_path: str | os.PathLike[str] | None = None,
) -> Registration:
    """Register a :class:`Reconstruction`'s segmented points to ``model``.

    The segmented points, not the fitted surface: they lie on the imaged bone, while the
    smooth surface between contours carries a small shape error that a shaft, weakly
    held along its axis, turns into axial sliding (measured on a simulated 200-frame
    radius sweep: target error 0.07 mm from the points against 0.59 mm from the
    surface). Each point faces the probe that saw it (:func:`towards_probe`), which
    settles which side of the bone it is on.
    """
    from BoneUSRecon.Logic.vtkio import polydata_points

    return register(
        polydata_points(recon.points),
        model,
        params,
        towards_probe=towards_probe(recon.points, recon.sweep.image_to_reference),
        init=init,
        landmarks=landmarks,
        source_path=recon.sweep.source,
        model_path=model_path,
    )

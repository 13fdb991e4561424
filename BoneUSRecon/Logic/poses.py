"""Per-frame poses from a sequence header's transforms, and PLUS calibration XML.

Choosing the pose
-----------------
The pose of frame ``k`` is ``ImageToReference``: taken directly when the file has
``ImageToReferenceTransform``, otherwise composed along the chain of available
transforms, normally ``inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe``.
``ImageToProbe`` (the probe calibration, which carries the mm/pixel scale) comes from
``calibration=`` (a PLUS device-set XML; it wins when given, the user asked for it),
else from a per-frame or global ``ImageToProbeTransform`` header field.
``transform="ImageToTracker"`` (any ``ImageTo<X>``) picks another target frame;
``transform="ProbeToTracker"`` (any ``<A>To<B>``) means "the pose given by that
transform": ``ProbeToTracker * ImageToProbe``.

The chain is the shortest path from ``Image`` to the target frame in the graph whose
edges are the available transforms (:func:`find_chain`); a link may be used inverted.
"""

from __future__ import annotations

import os
import xml.etree.ElementTree as ET
from collections import defaultdict, deque
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from BoneUSRecon.Logic.errors import BoneUSReconError
from BoneUSRecon.Logic.fileio import check_input_file
from BoneUSRecon.Logic.metaio import TRANSFORM_NAME_RE, MetaHeader

__all__ = [
    "read_calibration",
    "sweep_transforms",
    "find_chain",
    "split_transform_name",
    "chain_text",
]


def _parse_matrix(text: str, what: str, path: Path) -> np.ndarray:
    parts = text.split()
    if len(parts) != 16:
        raise BoneUSReconError(f"{what}: expected 16 numbers, got {len(parts)}", path)
    try:
        vals = [float(p) for p in parts]
    except ValueError:
        raise BoneUSReconError(f"{what}: non-numeric value in {text[:60]!r}", path) from None
    return np.array(vals, dtype=np.float64).reshape(4, 4)


@dataclass
class _Link:
    """One transform ``From -> To`` per frame, with per-frame problems."""

    name: str
    matrices: np.ndarray  # (N, 4, 4), identity where unusable
    problem: list[str]  # per frame, "" if usable
    source: str  # "frames", "header", "calibration"


def _frame_link(hdr: MetaHeader, name: str) -> _Link:
    n = hdr.n_frames
    mats = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    problem = [f"{name} missing"] * n
    values = hdr.frame_fields.get(name + "Transform", {})
    statuses = hdr.frame_fields.get(name + "TransformStatus", {})
    for k, text in values.items():
        if k >= n:
            continue
        m = _parse_matrix(text, f"Seq_Frame{k:04d}_{name}Transform", hdr.path)
        status = statuses.get(k, "OK")
        if status.upper() != "OK":
            problem[k] = f"{name} status {status}"
        elif not np.all(np.isfinite(m)):
            problem[k] = f"{name} has NaN or infinite values"
        else:
            mats[k] = m
            problem[k] = ""
    return _Link(name, mats, problem, "frames")


def _const_link(name: str, m: np.ndarray, n: int, source: str) -> _Link:
    mats = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    if np.all(np.isfinite(m)):
        mats[:] = m
        problem = [""] * n
    else:
        problem = [f"{name} has NaN or infinite values"] * n
    return _Link(name, mats, problem, source)


def _invert(link: _Link) -> _Link:
    m = link.matrices
    det = np.linalg.det(m)
    scale = np.abs(m[:, :3, :3]).max(axis=(1, 2)) ** 3
    bad = ~(np.abs(det) > 1e-12 * np.maximum(scale, 1e-300))
    problem = list(link.problem)
    safe = m.copy()
    for k in np.flatnonzero(bad):
        if not problem[k]:
            problem[k] = f"{link.name} is singular"
        safe[k] = np.eye(4)
    inv = np.linalg.inv(safe)
    a, b = TRANSFORM_NAME_RE.match(link.name).groups()  # type: ignore[union-attr]
    return _Link(f"{b}To{a}", inv, problem, link.source)


def split_transform_name(name: str) -> tuple[str, str] | None:
    """The ``(From, To)`` frames of a transform name, or None if it is not one.

    Examples
    --------
    >>> split_transform_name("ProbeToTrackerTransform")
    ('Probe', 'Tracker')
    >>> split_transform_name("ImageToReference")
    ('Image', 'Reference')
    >>> split_transform_name("Timestamp") is None
    True
    """
    if name.endswith("Transform"):
        name = name[: -len("Transform")]
    m = TRANSFORM_NAME_RE.match(name)
    return (m.group(1), m.group(2)) if m else None


def find_chain(
    edges: dict[str, tuple[str, str]], start: str, goal: str
) -> list[tuple[str, bool]] | None:
    """Shortest chain of transforms from frame ``start`` to ``goal``.

    Parameters
    ----------
    edges : dict
        Transform name -> ``(From, To)`` frames.
    start, goal : str
        Frame names.

    Returns
    -------
    list of (str, bool) or None
        ``(name, inverted)`` applied in order, or None when no chain exists.

    Examples
    --------
    >>> edges = {"ProbeToTracker": ("Probe", "Tracker"), "ImageToProbe": ("Image", "Probe"),
    ...          "ReferenceToTracker": ("Reference", "Tracker")}
    >>> steps = find_chain(edges, "Image", "Reference")
    >>> steps
    [('ImageToProbe', False), ('ProbeToTracker', False), ('ReferenceToTracker', True)]
    >>> chain_text(steps)
    'inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe'
    >>> find_chain(edges, "Image", "Stylus") is None
    True
    """
    adj: dict[str, list[tuple[str, str, bool]]] = defaultdict(list)
    for name, (a, b) in edges.items():
        adj[a].append((b, name, False))
        adj[b].append((a, name, True))
    prev: dict[str, tuple[str, str, bool]] = {}
    seen = {start}
    queue = deque([start])
    while queue:
        node = queue.popleft()
        if node == goal:
            break
        # Prefer forward use of a transform over inverting one (PLUS names transforms
        # so that the chain to the reference is mostly forward); ties by name, so the
        # choice never depends on header order.
        for nxt, name, inverted in sorted(adj[node], key=lambda t: (t[2], t[1])):
            if nxt not in seen:
                seen.add(nxt)
                prev[nxt] = (node, name, inverted)
                queue.append(nxt)
    if goal not in seen:
        return None
    steps: list[tuple[str, bool]] = []
    node = goal
    while node != start:
        p, name, inverted = prev[node]
        steps.append((name, inverted))
        node = p
    return steps[::-1]


def chain_text(steps: list[tuple[str, bool]]) -> str:
    """The chain from :func:`find_chain` as a product of matrices (rightmost first)."""
    return " * ".join(f"inv({n})" if inv else n for n, inv in reversed(steps))


def sweep_transforms(
    hdr: MetaHeader,
    *,
    calibration: str | os.PathLike[str] | None = None,
    transform: str | None = None,
) -> tuple[np.ndarray, list[str], str]:
    """Compose the per-frame ``ImageToReference`` (or the named target) pose.

    Parameters
    ----------
    hdr : MetaHeader
    calibration : path-like, optional
        PLUS device-set XML with the ``Image -> Probe`` calibration.
    transform : str, optional
        Target pose name (see module docstring). Default ``ImageToReference``.

    Returns
    -------
    matrices : ndarray, shape (N, 4, 4)
        Pixel ``(i, j, 0, 1)`` -> target frame mm; identity where unusable.
    problems : list of str
        Per frame, why it cannot be used ("" if it can).
    name : str
        The chain used, e.g. ``"inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe"``.
    """
    path = hdr.path
    edges: dict[str, tuple[str, str]] = {}
    sources: dict[str, str] = {}
    for key in hdr.frame_fields:
        if key.endswith("Transform"):
            ab = split_transform_name(key)
            if ab:
                edges[key[: -len("Transform")]] = ab
                sources[key[: -len("Transform")]] = "frames"
    for key in hdr.fields:
        if key.endswith("Transform"):
            ab = split_transform_name(key)
            if ab and key[: -len("Transform")] not in edges:
                edges[key[: -len("Transform")]] = ab
                sources[key[: -len("Transform")]] = "header"
    file_edges = sorted(edges)
    calib: np.ndarray | None = None
    if calibration is not None:
        calib = read_calibration(calibration)
        edges["ImageToProbe"] = ("Image", "Probe")
        sources["ImageToProbe"] = "calibration"

    have = ", ".join(sorted(edges)) or "none"
    if transform is None:
        target_name = "ImageToReference"
    else:
        target_name = (
            transform[: -len("Transform")] if transform.endswith("Transform") else transform
        )
    ab = split_transform_name(target_name)
    if ab is None:
        raise BoneUSReconError(
            f"the pose {transform!r} is not a transform name like ImageToReference",
            path,
            parameter="transform",
        )
    a, b = ab
    if a == b:
        raise BoneUSReconError(
            f"the pose {transform!r} maps a frame to itself", path, parameter="transform"
        )
    if a == "Image":
        steps = find_chain(edges, "Image", b)
    elif target_name in edges:
        # The image must reach frame A without the named transform itself, otherwise
        # "StylusToTracker" would be reached by going out and back along it.
        others = {k: v for k, v in edges.items() if k != target_name}
        head = find_chain(others, "Image", a)
        steps = None if head is None else head + [(target_name, False)]
    else:
        raise BoneUSReconError(f"the file has no {target_name} transform (it has: {have})", path)
    if steps is None and not file_edges:
        # A plain image stack: no calibration can give it poses.
        raise BoneUSReconError(
            "no transforms in the file: it is a plain image (a 3D volume or a stack of "
            "frames), not a tracked sweep; a PLUS sequence records a pose per frame "
            "(e.g. ProbeToTrackerTransform, ImageToReferenceTransform)",
            path,
        )
    if steps is None:
        if target_name == "ImageToReference":
            missing = [
                t
                for t in ("ReferenceToTracker", "ProbeToTracker", "ImageToProbe")
                if t not in edges
            ]
            # The calibration only helps when it is the one missing link.
            calibration_helps = missing == ["ImageToProbe"]
            hint = "; give a calibration (ImageToProbe) file" if calibration_helps else ""
            raise BoneUSReconError(
                "no usable transform: no ImageToReferenceTransform and cannot compose "
                "inv(ReferenceToTracker) * ProbeToTracker * ImageToProbe: missing "
                f"{', '.join(missing) or 'a link'}; the file has: {have}{hint}",
                path,
                parameter="calibration" if calibration_helps else None,
            )
        goal = b if a == "Image" else a
        raise BoneUSReconError(
            f"no usable transform: no chain of transforms from Image to {goal} for "
            f"{target_name}; the file has: {have}",
            path,
        )

    # Overflow in absurd (e.g. 1e300) matrices just makes those frames invalid.
    with np.errstate(all="ignore"):
        return _compose(hdr, steps, sources, calib)


def _compose(
    hdr: MetaHeader,
    steps: list[tuple[str, bool]],
    sources: dict[str, str],
    calib: np.ndarray | None,
) -> tuple[np.ndarray, list[str], str]:
    """Multiply the chain's links per frame and check each composed pose."""
    path, n = hdr.path, hdr.n_frames
    total = np.broadcast_to(np.eye(4), (n, 4, 4)).copy()
    problems = [""] * n
    for name, inverted in steps:
        if sources[name] == "frames":
            link = _frame_link(hdr, name)
        elif sources[name] == "calibration":
            assert calib is not None
            link = _const_link(name, calib, n, "calibration")
        else:
            link = _const_link(
                name,
                _parse_matrix(hdr.fields[name + "Transform"], name + "Transform", path),
                n,
                "header",
            )
        if inverted:
            link = _invert(link)
        total = link.matrices @ total
        problems = [p or q for p, q in zip(problems, link.problem, strict=True)]

    # Frame-level checks on the composed pose: finite, affine, non-degenerate plane.
    finite = np.all(np.isfinite(total), axis=(1, 2))
    safe = np.where(finite[:, None, None], total, np.eye(4))
    affine_k = np.all(np.abs(safe[:, 3, :] - [0, 0, 0, 1]) <= 1e-6, axis=1)
    c0, c1 = safe[:, :3, 0], safe[:, :3, 1]
    n0, n1 = np.linalg.norm(c0, axis=1), np.linalg.norm(c1, axis=1)
    cross = np.linalg.norm(np.cross(c0, c1), axis=1)
    degenerate = ~(cross > 1e-9 * n0 * n1) | ~(n0 > 0) | ~(n1 > 0)
    for k in range(n):
        if problems[k]:
            continue
        if not finite[k]:
            problems[k] = "pose has NaN or infinite values"
        elif not affine_k[k]:
            problems[k] = "pose is not an affine transform (last row is not 0 0 0 1)"
        elif degenerate[k]:
            problems[k] = "pose is singular (image axes collapse)"
    total[np.array([bool(p) for p in problems], dtype=bool)] = np.eye(4)
    name = chain_text(steps)
    return total, problems, name


def read_calibration(
    xml_path: str | os.PathLike[str], *, from_frame: str = "Image", to_frame: str = "Probe"
) -> np.ndarray:
    """Read a transform from a PLUS device-set configuration XML.

    Looks for ``<CoordinateDefinitions><Transform From=.. To=.. Matrix=".."/>``; the
    reverse transform (``From=to_frame To=from_frame``) is inverted if that is what
    the file holds.

    Parameters
    ----------
    xml_path : path-like
    from_frame, to_frame : str
        Coordinate frame names, default ``Image`` -> ``Probe`` (the probe calibration).

    Returns
    -------
    ndarray, shape (4, 4)

    Raises
    ------
    BoneUSReconError
        Missing file, not XML, no such transform, bad or singular matrix.
    """
    p = check_input_file(xml_path)
    try:
        root = ET.parse(p).getroot()
    except ET.ParseError as exc:
        raise BoneUSReconError(f"not a valid XML file: {exc}", p) from None
    what = f'<Transform From="{from_frame}" To="{to_frame}">'
    for el in root.iter("Transform"):
        a, b = el.get("From"), el.get("To")
        if (a, b) not in ((from_frame, to_frame), (to_frame, from_frame)):
            continue
        text = el.get("Matrix")
        if text is None:
            raise BoneUSReconError(f"{what} has no Matrix attribute", p)
        m = _parse_matrix(text, f"{what} Matrix", p)
        if not np.all(np.isfinite(m)):
            raise BoneUSReconError(f"{what} Matrix has NaN or infinite values", p)
        if abs(np.linalg.det(m)) < 1e-12 * max(np.abs(m[:3, :3]).max(), 1e-300) ** 3:
            raise BoneUSReconError(f"{what} Matrix is singular", p)
        return m if a == from_frame else np.linalg.inv(m)
    raise BoneUSReconError(f"no {what} in the file's <CoordinateDefinitions>", p)

"""The bone track of :mod:`.track`, built as frames arrive (live reconstruction).

:func:`~.track.select_bone_track` links every pair of frames up to ``max_skip + 1``
apart (projections and point-to-contour distances: nearly all of its time) and then
runs its dynamic programme. Over a live session that repeats the same links at every
refit. :class:`IncrementalTrack` links each new frame to its predecessors once, when it
arrives, and keeps the links; a refit runs only the programme over the stored links
(a few milliseconds for hundreds of frames) and the backtrack.

The links cannot be scored once and for all: a node's value is its strength relative
to the typical strength of all frames so far, which moves as frames arrive. Links are
therefore stored as the deviation alone (geometry, independent of the other frames),
and the values and the forward pass are recomputed at each :meth:`IncrementalTrack.solve`,
in the same order and with the same arithmetic as :func:`~.track.select_bone_track`: the
same track, bit for bit (``Testing/test_live.py`` checks it on simulated sweeps,
hard ones included). Every per-frame and per-pair step is a function of :mod:`.track`,
shared with the batch version, so a change of scoring there applies to both.

When frames are dropped (:meth:`IncrementalTrack.keep`, e.g. a live session thinning
its frames to stay within memory), frames that were more than ``max_skip + 1`` apart
may become neighbours: their links are owed and are made either in spare time
(:meth:`IncrementalTrack.work`) or at the next :meth:`IncrementalTrack.solve`.
"""

from __future__ import annotations

import time
from collections.abc import Iterable
from dataclasses import dataclass, field

import numpy as np

from BoneUSRecon.Logic.segmentation.candidates import FrameCandidates
from BoneUSRecon.Logic.segmentation.params import RejectionParams
from BoneUSRecon.Logic.segmentation.track import (
    TrackChoice,
    _finish,
    _frame_reason,
    _is_node,
    _links,
    _node_points,
    _node_value,
    _typical_strength,
)
from BoneUSRecon.Logic.sweep import frame_planes

__all__ = ["IncrementalTrack"]


@dataclass(eq=False)
class _TrackFrame:
    """One frame's nodes, their geometry, and its links from earlier frames."""

    uid: int
    candidates: FrameCandidates
    pose: np.ndarray
    plane: tuple[np.ndarray, np.ndarray, np.ndarray]
    reason: str
    nodes: list[int]  # candidate indices that are nodes, in candidate order
    ref: list[np.ndarray]  # each node's sampled contour, reference mm
    b_nodes: list[tuple[np.ndarray, tuple[float, float, float, float]]]
    #: Predecessor uid -> ``(its node, this frame's node, deviation)``, in the order
    #: :func:`~.track.select_bone_track` visits them.
    links: dict[int, list[tuple[int, int, float]]] = field(default_factory=dict)


class IncrementalTrack:
    """:func:`~.track.select_bone_track` over frames given one at a time.

    Parameters
    ----------
    params : RejectionParams

    Examples
    --------
    >>> from BoneUSRecon.Logic.segmentation import frame_candidates_for
    >>> from BoneUSRecon.Logic.segmentation.track import select_bone_track
    >>> from BoneUSRecon.Logic.simulation import SimulationParams, simulate
    >>> sim = simulate(SimulationParams(n_frames=20, width=120, height=96, spacing_mm=0.4))
    >>> sw, track = sim.sweep, IncrementalTrack()
    >>> frames = [frame_candidates_for(image, (0.4, 0.4)) for _, image in sw.iter_frames()]
    >>> for fc, pose in zip(frames, sw.image_to_reference):
    ...     track.add(fc, pose)
    >>> bool((track.solve().chosen == select_bone_track(frames, sw.image_to_reference).chosen).all())
    True
    """

    def __init__(
        self,
        params: RejectionParams = RejectionParams(),  # noqa: B008 (frozen dataclass)
    ) -> None:
        self.params = params
        self._frames: list[_TrackFrame] = []
        self._next_uid = 0
        #: ``(frame uid, predecessor uid)`` pairs still to link (after :meth:`keep`).
        self._owed: list[tuple[int, int]] = []
        #: Rejection details from earlier solves (see :func:`~.track._finish`).
        self._details: dict[tuple[int, int, int, int], str] = {}

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def owed(self) -> int:
        """Pairs of frames still to link (made by :meth:`work` or :meth:`solve`)."""
        return len(self._owed)

    def add(self, candidates: FrameCandidates, pose: np.ndarray) -> None:
        """Append the next frame (in acquisition order) and link it to its predecessors.

        Parameters
        ----------
        candidates : FrameCandidates
        pose : ndarray, shape (4, 4)
            ``ImageToReference``.
        """
        m = np.asarray(pose, dtype=float).reshape(4, 4)
        origin, axes, normal = frame_planes(m)
        nodes = [c for c, cand in enumerate(candidates.candidates) if _is_node(cand)]
        geometry = [_node_points(candidates.candidates[c], candidates.spacing, m) for c in nodes]
        fr = _TrackFrame(
            uid=self._next_uid,
            candidates=candidates,
            pose=m,
            plane=(origin[0], axes[0], normal[0]),
            reason=_frame_reason(candidates),
            nodes=nodes,
            ref=[gm[0] for gm in geometry],
            b_nodes=[gm[1:] for gm in geometry],
        )
        self._next_uid += 1
        self._frames.append(fr)
        g = len(self._frames) - 1
        for f in range(max(0, g - self.params.max_skip - 1), g):
            self._link(self._frames[f], fr)

    def _link(self, a: _TrackFrame, b: _TrackFrame) -> None:
        """Store the links from frame a's nodes to the later frame b's (none if either has none)."""
        out: list[tuple[int, int, float]] = []
        if a.nodes and b.nodes:
            for ia, a_ref in enumerate(a.ref):
                out.extend(
                    (ia, ib, dev) for ib, dev in _links(a_ref, b.plane, b.b_nodes, self.params)
                )
        b.links[a.uid] = out

    def keep(self, positions: Iterable[int]) -> None:
        """Keep only the frames at these positions (ascending); the others are forgotten.

        Frames that become neighbours are linked later (:meth:`work`, :meth:`solve`).
        """
        idx = sorted(set(int(i) for i in positions))
        if idx and not 0 <= idx[0] <= idx[-1] < len(self._frames):
            raise IndexError(f"positions out of range 0..{len(self._frames) - 1}")
        self._frames = [self._frames[i] for i in idx]
        kept = {fr.uid for fr in self._frames}
        self._details = {}  # positions change: details name frames by position
        self._owed = []
        for g, fr in enumerate(self._frames):
            fr.links = {u: v for u, v in fr.links.items() if u in kept}
            for f in range(max(0, g - self.params.max_skip - 1), g):
                if self._frames[f].uid not in fr.links:
                    self._owed.append((fr.uid, self._frames[f].uid))

    def work(self, budget_s: float) -> int:
        """Make owed links for up to ``budget_s`` seconds of this thread's CPU time.

        Returns
        -------
        int
            Pairs linked.
        """
        if not self._owed:
            return 0
        by_uid = {fr.uid: fr for fr in self._frames}
        t0 = time.thread_time()
        done = 0
        while self._owed and (done == 0 or time.thread_time() - t0 < budget_s):
            g_uid, f_uid = self._owed.pop()
            g, f = by_uid.get(g_uid), by_uid.get(f_uid)
            if g is not None and f is not None and f_uid not in g.links:
                self._link(f, g)
            done += 1
        return done

    def solve(self) -> TrackChoice:
        """The track over the frames kept, as :func:`~.track.select_bone_track` chooses it."""
        p = self.params
        self.work(np.inf)
        frames = self._frames
        n = len(frames)
        reason = [fr.reason for fr in frames]
        nodes = [(f, c) for f, fr in enumerate(frames) for c in fr.nodes]
        if not nodes:
            return TrackChoice(np.full(n, -1, dtype=np.intp), np.zeros(n), reason, [""] * n)
        if len(self._details) > 8 * n:
            self._details.clear()  # choices that changed long ago
        fcs = [fr.candidates for fr in frames]
        typical = _typical_strength(fcs)
        value_arr = np.array([_node_value(fcs[f].candidates[c], typical, p) for f, c in nodes])
        # The forward pass on Python floats (the same IEEE arithmetic as the batch
        # version's numpy scalars, ~10x faster per edge); edges in the batch order.
        value = value_arr.tolist()
        score = list(value)
        back = [-1] * len(nodes)
        link_dev = [0.0] * len(nodes)
        base = np.cumsum([0] + [len(fr.nodes) for fr in frames]).tolist()
        for g, fr in enumerate(frames):
            if not fr.nodes:
                continue
            bg = base[g]
            for f in range(max(0, g - p.max_skip - 1), g):
                edges = fr.links.get(frames[f].uid)
                if not edges:
                    continue
                bf = base[f]
                gap_cost = p.miss_cost * (g - f - 1)
                for ia, ib, dev in edges:
                    ka, kb = bf + ia, bg + ib
                    s = score[ka] - dev**2 - gap_cost + value[kb]
                    if s > score[kb]:
                        score[kb], back[kb], link_dev[kb] = s, ka, dev
        poses = np.stack([fr.pose for fr in frames])
        return _finish(
            fcs,
            poses,
            nodes,
            value_arr,
            np.array(score),
            np.array(back, dtype=np.intp),
            np.array(link_dev),
            reason,
            p,
            keys=[fr.uid for fr in frames],
            details=self._details,
        )

    def memory_bytes(self) -> int:
        """Approximate bytes held for the nodes' geometry and the links."""
        total = 0
        for fr in self._frames:
            total += sum(r.nbytes for r in fr.ref) + sum(b.nbytes + 64 for b, _ in fr.b_nodes)
            total += sum(48 * len(v) + 64 for v in fr.links.values()) + 400
        return total

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

A second solve may add one candidate to some frames (:meth:`IncrementalTrack.solve` with
``extra``: the guided candidates of :mod:`.recovery`, the last candidate of their frame
as offline). Only the extra nodes are linked, to the frames within ``max_skip + 1`` on
either side; those links are kept while the extra candidate is the same object, and the
stored state is not changed (the next plain solve is the track without them).

The link tolerance is scaled to the frames' own deviation as the batch track scales it
(:func:`~.track.tolerance_scale`): each frame's least deviation to the one before it is
measured once, with the base tolerance, when it arrives; where the scale over the frames
so far changes (rarely: it moves in quarters), every link is made again with the new one
(:meth:`IncrementalTrack.rescale`, run by each solve).

When frames are dropped (:meth:`IncrementalTrack.keep`, e.g. a live session thinning
its frames to stay within memory), frames that were more than ``max_skip + 1`` apart
may become neighbours: their links are owed and are made either in spare time
(:meth:`IncrementalTrack.work`) or at the next :meth:`IncrementalTrack.solve`.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field, replace

import numpy as np

from BoneUSRecon.Logic.segmentation.candidates import BoneCandidate, FrameCandidates
from BoneUSRecon.Logic.segmentation.params import RejectionParams
from BoneUSRecon.Logic.segmentation.track import (
    Plane,
    PlaneNode,
    TrackChoice,
    _finish,
    _frame_reason,
    _is_node,
    _links,
    _links_many,
    _node_points,
    _node_value,
    _pair_deviation,
    _typical_strength,
    pointed_track,
    pose_jitter,
    scaled_tolerance,
    tolerance_scale,
)
from BoneUSRecon.Logic.sweep import frame_planes

__all__ = ["IncrementalTrack"]


@dataclass(eq=False)
class _TrackFrame:
    """One frame's nodes, their geometry, and its links from earlier frames."""

    uid: int
    candidates: FrameCandidates
    pose: np.ndarray
    plane: Plane
    reason: str
    nodes: list[int]  # candidate indices that are nodes, in candidate order
    ref: list[np.ndarray]  # each node's sampled contour, reference mm
    b_nodes: list[PlaneNode]
    #: Predecessor uid -> ``(its node, this frame's node, deviation)``, in the order
    #: :func:`~.track.select_bone_track` visits them.
    links: dict[int, list[tuple[int, int, float]]] = field(default_factory=dict)
    #: ``(the frame before it, the least deviation to it in base tolerances)``
    #: (:func:`~.track.tolerance_scale`); None until measured.
    near: tuple[int, float] | None = None


@dataclass(eq=False)
class _Extra:
    """An extra candidate of one frame (:meth:`IncrementalTrack.solve`) and its links,
    kept while the same candidate object is given again."""

    cand: BoneCandidate
    #: Stands for the frame in the rejection details' keys (the frame with this
    #: candidate is another frame than the one without): negative, never a uid.
    key: int
    candidates: FrameCandidates  # the frame's candidates with ``cand`` last
    reason: str
    node: bool
    ref: np.ndarray | None
    b_node: PlaneNode | None
    #: Predecessor uid -> ``(its node, deviation)`` to this candidate.
    into: dict[int, list[tuple[int, float]]] = field(default_factory=dict)
    #: Successor uid -> ``(its node, deviation)`` from this candidate.
    out: dict[int, list[tuple[int, float]]] = field(default_factory=dict)
    #: Successor uid -> ``(its extra candidate, deviations)`` from this one to that one.
    pair: dict[int, tuple[BoneCandidate, list[float]]] = field(default_factory=dict)


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
        #: The tolerance's scale for the frames so far and the parameters it gives
        #: (:func:`~.track.tolerance_scale`): the links are made with these.
        self._scale = 1.0
        self._p = params
        self._frames: list[_TrackFrame] = []
        self._next_uid = 0
        #: ``(frame uid, predecessor uid)`` pairs still to link (after :meth:`keep`).
        self._owed: list[tuple[int, int]] = []
        #: Rejection details from earlier solves (see :func:`~.track._finish`).
        self._details: dict[tuple[int, int, int, int], str] = {}
        #: Frame uid -> its latest extra candidate and that candidate's links.
        self._extra: dict[int, _Extra] = {}
        self._next_key = -1

    def __len__(self) -> int:
        return len(self._frames)

    @property
    def uids(self) -> list[int]:
        """A number per kept frame, unique within the session (stable across :meth:`keep`)."""
        return [fr.uid for fr in self._frames]

    @property
    def rejection(self) -> RejectionParams:
        """The parameters the track is chosen with: ``params`` with the link tolerance
        scaled to the frames' own deviation (as of the last :meth:`solve` or
        :meth:`rescale`); what the steps after the track use (recovery, the reach)."""
        return self._p

    @property
    def scale(self) -> float:
        """The link tolerance's scale (:meth:`rescale`; 1: as ``params`` give it)."""
        return self._scale

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
        self._link(self._frames[max(0, g - self.params.max_skip - 1) : g], fr)
        if g:
            a = self._frames[g - 1]
            if self._p is self.params:
                # Linked with the base tolerances: the least deviation to the frame
                # before is among the links just made (the same edges :meth:`_measure`
                # makes; one search, not two).
                devs = [dev for _, _, dev in fr.links[a.uid]]
                fr.near = (a.uid, min(devs) if devs else np.inf)
            else:
                self._measure(a, fr)

    def _measure(self, a: _TrackFrame, b: _TrackFrame) -> None:
        """Frame b's least deviation to a, the frame before it (base tolerances)."""
        dev = (
            _pair_deviation(a.ref, b.plane, b.b_nodes, self.params)
            if a.nodes and b.nodes
            else np.inf
        )
        b.near = (a.uid, dev)

    def rescale(self) -> float:
        """Scale the link tolerance to the frames kept (:func:`~.track.tolerance_scale`);
        where the scale changes, every link is made again with it. Returns the scale."""
        for g in range(1, len(self._frames)):
            a, b = self._frames[g - 1], self._frames[g]
            if b.near is None or b.near[0] != a.uid:
                self._measure(a, b)
        scale = tolerance_scale(
            [fr.near[1] for fr in self._frames[1:] if fr.near],
            self.params,
            pose_jitter(np.array([fr.plane[0] for fr in self._frames]).reshape(-1, 3)),
        )
        if scale != self._scale:
            self._scale, self._p = scale, scaled_tolerance(self.params, scale)
            # The links and everything made with them, made again.
            self._owed, self._details, self._extra = [], {}, {}
            for g, fr in enumerate(self._frames):
                fr.links = {}
                self._link(self._frames[max(0, g - self.params.max_skip - 1) : g], fr)
        return scale

    def _link(self, preds: list[_TrackFrame], b: _TrackFrame) -> None:
        """Store the links from each earlier frame's nodes to frame b's (none if either
        has none), all made together (:func:`~.track._links_many`)."""
        linked = [a for a in preds if a.nodes] if b.nodes else []
        refs = [a_ref for a in linked for a_ref in a.ref]
        edges = iter(_links_many(refs, b.plane, b.b_nodes, self._p))
        for a in preds:
            out: list[tuple[int, int, float]] = []
            if a.nodes and b.nodes:
                for ia in range(len(a.ref)):
                    out.extend((ia, ib, dev) for ib, dev in next(edges))
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
        self._extra = {u: e for u, e in self._extra.items() if u in kept}
        for e in self._extra.values():
            e.into = {u: v for u, v in e.into.items() if u in kept}
            e.out = {u: v for u, v in e.out.items() if u in kept}
            e.pair = {u: v for u, v in e.pair.items() if u in kept}
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
                self._link([f], g)
            done += 1
        return done

    def _extras(self, extra: Mapping[int, BoneCandidate] | None) -> list[_Extra | None]:
        """Per kept frame, its extra candidate with its geometry (made once per candidate)."""
        out: list[_Extra | None] = [None] * len(self._frames)
        for pos, cand in (extra or {}).items():
            f = int(pos)
            if not 0 <= f < len(self._frames):
                raise IndexError(f"extra candidate for position {f}, not in 0..{len(self) - 1}")
            fr = self._frames[f]
            e = self._extra.get(fr.uid)
            if e is None or e.cand is not cand:
                # As :func:`~.recovery.with_candidate` (offline) extends the frame.
                fc = replace(fr.candidates, candidates=(*fr.candidates.candidates, cand), reason="")
                node = _is_node(cand)
                gm = _node_points(cand, fc.spacing, fr.pose) if node else None
                e = _Extra(
                    cand,
                    self._next_key,
                    fc,
                    _frame_reason(fc),
                    node,
                    gm[0] if gm is not None else None,
                    gm[1:] if gm is not None else None,
                )
                self._next_key -= 1
                self._extra[fr.uid] = e
            out[f] = e
        return out

    def _extra_edges(
        self, a: _TrackFrame, ea: _Extra | None, b: _TrackFrame, eb: _Extra | None
    ) -> tuple[list[tuple[int, float]], list[tuple[int, float]], list[float]]:
        """Links of the extra nodes between frame a and the later frame b: a's nodes to
        b's extra, a's extra to b's nodes, a's extra to b's extra (made once, kept)."""
        p = self._p
        into: list[tuple[int, float]] = []
        out: list[tuple[int, float]] = []
        both: list[float] = []
        if eb is not None and eb.node:
            got = eb.into.get(a.uid)
            if got is None:
                assert eb.b_node is not None
                got = [
                    (ia, dev)
                    for ia, links in enumerate(_links_many(a.ref, b.plane, [eb.b_node], p))
                    for _, dev in links
                ]
                eb.into[a.uid] = got
            into = got
        if ea is not None and ea.node:
            assert ea.ref is not None
            got = ea.out.get(b.uid)
            if got is None:
                got = _links(ea.ref, b.plane, b.b_nodes, p) if b.nodes else []
                ea.out[b.uid] = got
            out = got
            if eb is not None and eb.node:
                kept = ea.pair.get(b.uid)
                if kept is None or kept[0] is not eb.cand:
                    assert eb.b_node is not None
                    kept = (eb.cand, [dev for _, dev in _links(ea.ref, b.plane, [eb.b_node], p)])
                    ea.pair[b.uid] = kept
                both = kept[1]
        return into, out, both

    def solve(
        self,
        extra: Mapping[int, BoneCandidate] | None = None,
        explain: bool = True,
        exclude: Mapping[int, tuple[str, str]] | None = None,
    ) -> TrackChoice:
        """The track over the frames kept, as :func:`~.track.select_bone_track` chooses it.

        Parameters
        ----------
        extra : mapping of int to BoneCandidate, optional
            Position of a kept frame -> one more candidate for it, as if appended to
            its candidates (the guided candidates of :mod:`.recovery`). The choice is
            :func:`~.track.select_bone_track` over the frames so extended; an index
            equal to a frame's number of candidates names its extra candidate. The
            frames kept are not changed: a later solve without ``extra`` is the plain
            track again.
        explain : bool
            False: the choice only, without the rejection details (the distance from
            each frame off the track to it, the slow part of a solve on a sweep with
            many such frames); live recovery needs only the choice of its first solve.
        exclude : mapping of int to (str, str), optional
            Positions of kept frames that may not be on the track, each with the
            rejection reason and detail it keeps, as :func:`~.track.select_bone_track`'s
            ``exclude`` (the frames the ends cut judged bone-free).

        Returns
        -------
        TrackChoice
        """
        self.work(np.inf)
        self.rescale()
        p = self._p
        frames = self._frames
        n = len(frames)
        ext = self._extras(extra)
        fcs = [
            fr.candidates if e is None else e.candidates for fr, e in zip(frames, ext, strict=True)
        ]
        reason = [fr.reason if e is None else e.reason for fr, e in zip(frames, ext, strict=True)]
        detail = [""] * n
        exclude = exclude or {}
        for f, (r, d) in exclude.items():
            reason[f], detail[f] = r, d
        # Each frame's nodes: its own, then its extra candidate (its last candidate);
        # none for an excluded frame.
        n_base = [0 if f in exclude else len(fr.nodes) for f, fr in enumerate(frames)]
        has_extra = [e is not None and e.node and f not in exclude for f, e in enumerate(ext)]
        nodes = [
            (f, c)
            for f, (fr, e) in enumerate(zip(frames, ext, strict=True))
            if f not in exclude
            for c in (fr.nodes + [len(fr.candidates.candidates)] if has_extra[f] else fr.nodes)
        ]
        if not nodes:
            return TrackChoice(np.full(n, -1, dtype=np.intp), np.zeros(n), reason, detail)
        if len(self._details) > 8 * n:
            self._details.clear()  # choices that changed long ago
        typical = _typical_strength(fcs)
        value_arr = np.array([_node_value(fcs[f].candidates[c], typical, p) for f, c in nodes])
        count = [nb + (1 if x else 0) for nb, x in zip(n_base, has_extra, strict=True)]
        base = np.cumsum([0] + count).tolist()

        def forward(values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
            # On Python floats (the same IEEE arithmetic as the batch version's numpy
            # scalars, ~10x faster per edge); edges in the batch order.
            value = values.tolist()
            score = list(value)
            back = [-1] * len(nodes)
            link_dev = [0.0] * len(nodes)
            for g, fr in enumerate(frames):
                if not count[g]:
                    continue
                bg, eg = base[g], ext[g]
                for f in range(max(0, g - p.max_skip - 1), g):
                    if not count[f]:
                        continue  # no nodes (its stored links, if any, name none)
                    fa, ef = frames[f], ext[f]
                    bf = base[f]
                    gap_cost = p.miss_cost * (g - f - 1)
                    edges = fr.links.get(fa.uid)
                    if edges:
                        for ia, ib, dev in edges:
                            ka, kb = bf + ia, bg + ib
                            s = score[ka] - dev**2 - gap_cost + value[kb]
                            if s > score[kb]:
                                score[kb], back[kb], link_dev[kb] = s, ka, dev
                    if eg is None and ef is None:
                        continue
                    # The extra nodes' edges. Only the order of the edges into one node
                    # matters (a node's predecessors' scores are final): the batch
                    # version visits them by the predecessor's node, the extra one last.
                    into, out, both = self._extra_edges(fa, ef, fr, eg)
                    xf, xg = bf + n_base[f], bg + n_base[g]  # the extra nodes' indices
                    for ka, kb, dev in (
                        *((bf + ia, xg, dev) for ia, dev in into),
                        *((xf, bg + ib, dev) for ib, dev in out),
                        *((xf, xg, dev) for dev in both),
                    ):
                        s = score[ka] - dev**2 - gap_cost + value[kb]
                        if s > score[kb]:
                            score[kb], back[kb], link_dev[kb] = s, ka, dev
            return np.array(score), np.array(back, dtype=np.intp), np.array(link_dev)

        poses = np.stack([fr.pose for fr in frames])
        value_arr, (score_arr, back_arr, dev_arr), path = pointed_track(
            fcs, poses, nodes, value_arr, forward, p, reason, detail
        )
        return _finish(
            fcs,
            poses,
            nodes,
            value_arr,
            score_arr,
            back_arr,
            dev_arr,
            reason,
            p,
            keys=[fr.uid if e is None else e.key for fr, e in zip(frames, ext, strict=True)],
            details=self._details,
            explain=explain,
            detail=detail,
            path=path,
        )

    def memory_bytes(self) -> int:
        """Approximate bytes held for the nodes' geometry and the links."""
        total = 0
        for fr in self._frames:
            total += sum(r.nbytes for r in fr.ref) + sum(b.nbytes + 64 for b, _ in fr.b_nodes)
            total += sum(48 * len(v) + 64 for v in fr.links.values()) + 400
        for e in self._extra.values():
            if e.ref is not None and e.b_node is not None:
                total += e.ref.nbytes + e.b_node[0].nbytes
            n_links = sum(len(v) for v in (*e.into.values(), *e.out.values()))
            n_links += sum(len(v) for _, v in e.pair.values())
            total += 40 * n_links + 64 * (len(e.into) + len(e.out) + len(e.pair)) + 400
        return total

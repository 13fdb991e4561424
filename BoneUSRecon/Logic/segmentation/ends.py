"""Sweep-level step: the track's ends cut back where the frames show no bone shadow.

A real sweep may start or end past a bone's end, or where the probe has slid off it;
those frames show no bone, yet the track (:mod:`.track`) carries on through whatever
continues the bone in 3D there: a fascia leaving the bone at its level, or the skin
line over a no-contact gap at the image edge, whose shade passes for a shadow in the
per-frame evidence. Measured on 96 hard simulated sweeps of 40 frames with the first
or last 3 or 10 frames bone-free (``SimulationParams.bone_free_frames``; seeds 5, 7,
29, both geometries), the track kept 65 of 624 bone-free frames, in 10 sweeps; with
this cut 1, recall unchanged (0.941), and with the one-sided recovery past the track's
ends that the cut makes safe (``EndsParams.search_past_ends``) recall 0.962.

What tells the bone from those look-alikes is where the dark begins. Bone casts its
shadow from the contour down: a few mm under the contour the tissue is darker than the
tissue just above it. A fascia over tissue has tissue beneath it (no step), and the
shade of a no-contact gap is cast from the skin above, so the column is dark above
the contour as well as under it (little step). :func:`shadow_step` measures that step
per frame: the median over the contour's columns of ``log(grey under) - log(grey
above)``, in bands ``band_mm`` thick starting ``under_gap_mm`` under the contour (past
the bone's bright band) and ``above_gap_mm`` above it. :func:`trough_step` reads the
same bands on the profile along the contour (per row offset, the median log grey over
its columns): the darkest ``trough_mm`` layer of the band under it less the band above's
mean. A grey shadow filled with reverberation copies every 2-3 mm (the band spans at
least one period) is dark between them, and the band's mean is then not much darker
than a hypoechoic muscle over the bone: the grey clavicle s811 (seeds no session had
run) lost its last 6 frames so, on the bone under a muscle layer at 0.78 of the
tissue's level, stepping 0.36 to -0.3 of the track's typical frame (gold 1.33 mm); its
darkest layer read 0.58-1.03. The darkest layer has its own blind side: the tissue under
a layer has darker layers too, and a bone's darkest layer varies with where its copies
fall (the grey clavicle s919's last frames read 0.49-0.68 of typical by it, 0.37-1.0 by
the mean). A frame is as weak as both readings find it (:func:`bone_free_ends`; measured
in ``Testing/benchmarks/README.md``, session 48).

A muscle lying on the bone (the pronator quadratus over the distal 4-6 cm of the radius
and ulna, the brachialis on the humerus) fills the band above with tissue darker than
the rest, and where it covers one end of the sweep only, those frames step less than
the track's typical frame by both readings and were cut as bone-free (the L14 recording
and its copies with a muscle at 0.5-0.7 over the first 40 % or the last half: recall
0.48-0.90, every frame cut on the bone). So the band's mean is read against the
brightest ``band_mm`` band up to ``cover_reach_mm`` over the contour, not only the band
right over it (:func:`_cover_lift`; medians along the contour, so a thin bright line in
a band moves it little, a muscle filling it does). Only that reading is lifted: a frame
is spared when either reading finds it no weaker than the track's, so one lifted reading
is enough for the bone under a muscle, and the darkest layer still judges a layer past
the bone's end under tissue that is brighter higher up (the hard simulator's tissue
gets brighter over some layers: lifting both readings kept bone-free frames in 1 more
of 80 sweeps, lifting the mean alone in none).

:func:`bone_free_ends` judges the step of each track frame against the track's own
typical step (the median over its frames): the weakness of a frame is ``min_ratio -
step / typical``. From each end of the track, the run of frames cut is the one whose
weakness, summed, is greatest, if it is positive (a one-sided change point, CUSUM-like),
a frame that looks like the bone counting ``strong_weight`` times its margin: a lone
weak frame among the bone's, or a weak stretch of the bone next to a strong end frame,
is not cut; a run of look-alikes with a stray fair frame in it is. The run must also
weigh more than the weakest stretch between the two ends' runs (the largest summed
weakness of a run there): how far the bone's own steps stray is the recording's, and a
weak end no weaker than the bone shows inside the track is the bone. Frames inside the
track are never cut (both sides vouch for them).

Why it generalises: no grey level is read as such. The step is a difference of log
greys in the same columns (a ratio: the same under any gain or display curve), and it
is judged against the recording's own bone, the track's median frame: whatever the
shadow's floor (the L14 recording's near-black, the cadaver's 0.65 of the tissue
beside) and whatever lies above the bone, a frame showing that bone steps like the
track's other frames, and one past its end, over tissue or in a shade from above,
much less. Tried and not kept: the step less the same step in the columns beside the
contour (tissue at the same depths): on the real L14 recording the tissue beside the
bone at its depth is darker than its shadow, and the frames' ratios spread 0.2-1.8.
Measured in ``Testing/benchmarks/README.md``, "Bone-free sweep ends (branch ends)".

**The track chosen again without the frames cut** (:func:`cut_ends_and_choose_again`).
The track is one longest path: every frame it passes adds its value, so a layer that
carries on past the bone's end adds value in every bone-free frame it crosses, and the
path bends to reach it. In the last frames showing bone the bone's contour may not link
to that layer (cut off at the shoulder, where the layer leaves the bone: no lateral
overlap with the layer alone beyond), while a contour of the layer itself, or a short
piece at the shoulder with the layer's root, does. The track then skips those frames'
bone contours, however strong, for the layer, and the ends cut afterwards removes the
bone-free frames but not the bend they caused (hard tibia, seed 5, last 10 frames
bone-free, frames 28-29: their strongest candidates lay on the bone, 0.05 and 0.16 mm;
the track went round them to the fascia of frames 30-39, and recovery, guided by that
track, put the fascia into them, 2.6 and 1.4 mm off). So once frames are cut, the track
is chosen again with them ruled out (no node of theirs; their reason kept), and the new
track's ends cut as before. It generalises: it asks nothing new of the images, only
that the track's choice in the frames kept not be bought with frames the same sweep's
evidence judged to show no bone ("one decision over the sweep", :mod:`.track`, made
with what that decision already knows). Once: a second choice could erode a weak end
of the bone against a track grown more bone-like (the cut is relative to the track's
median); the new track's ends are cut as before. The first track is cut and chosen
again too (offline and live), before recovery searches the frames off it
(:mod:`.recovery`): the guided search takes its band from the track's contours next to
a frame, and those should not lead into frames judged bone-free.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable, Mapping, Sequence

import numpy as np

from BoneUSRecon.Logic.segmentation.candidates import FrameCandidates
from BoneUSRecon.Logic.segmentation.evidence import field_tops
from BoneUSRecon.Logic.segmentation.features import median1d
from BoneUSRecon.Logic.segmentation.params import EndsParams, ShadowPathParams
from BoneUSRecon.Logic.segmentation.track import REASONS, TrackChoice

__all__ = [
    "shadow_step",
    "trough_step",
    "shadow_steps",
    "steps_array",
    "unmeasured",
    "READINGS",
    "candidate_steps",
    "bone_free_ends",
    "cut_ends_at_steps",
    "cut_bone_free_ends",
    "cut_ends_and_choose_again",
]

# log(grey + 1) of every uint8 grey: one table lookup instead of a log per pixel.
_LOG = np.log(np.arange(256, dtype=float) + 1.0)
#: The scanner's black (:attr:`ShadowPathParams.fov_grey`): a band of it over the whole
#: field is outside the image, and the near field starts under it.
_BLACK = ShadowPathParams().fov_grey


def _band_means(cum: np.ndarray, r0: np.ndarray, r1: np.ndarray) -> np.ndarray:
    """Per column ``k``, the mean of rows ``[r0[k], r1[k])`` from its cumulative sum
    ``cum[:, k]`` (``(n + 1, K)``, row 0 zero); NaN where the band is empty."""
    n = cum.shape[0] - 1
    a = np.clip(np.round(r0).astype(np.intp), 0, n)
    b = np.clip(np.round(r1).astype(np.intp), 0, n)
    k = np.arange(a.size)
    return np.where(b > a, (cum[b, k] - cum[a, k]) / np.maximum(b - a, 1), np.nan)


def _field_top(img: np.ndarray, cols: np.ndarray, sy: float) -> float:
    """The imaged field's top row over ``cols``: the median over them of the first row
    starting 1 mm of pixels over the scanner's black (0 where the image starts at the
    frame's top; under a black band over the image, a screen capture's, the band's
    depth; a label's glyphs in the band, under 1 mm tall, are passed over)."""
    lit = img[:, cols] > _BLACK
    if lit[: max(1, int(round(1.0 / sy)))].all():  # the usual frame: imaged from row 0
        return 0.0
    tops = field_tops(lit, sy)
    if tops is None:
        return 0.0
    return float(np.median(np.where(tops < lit.shape[0], tops, 0)))


def _columns(
    image: np.ndarray, points_px: np.ndarray, spacing: tuple[float, float], column_mm: float
) -> tuple[np.ndarray, np.ndarray, np.ndarray, float]:
    """The image, and the columns ``i`` and rows ``j`` of a contour's points one every
    ~``column_mm``, and the row spacing (what both readings of the step measure on)."""
    img = np.asarray(image)
    sx, sy = float(spacing[0]), float(spacing[1])
    pts = points_px[:: max(1, int(round(column_mm / max(sx, 1e-6))))]
    i = np.clip(np.round(pts[:, 0]).astype(np.intp), 0, img.shape[1] - 1)
    return img, i, np.asarray(pts[:, 1], dtype=float), sy


def _row_medians(
    img: np.ndarray, i: np.ndarray, j: np.ndarray, offs: np.ndarray, top: float, partial: bool
) -> np.ndarray:
    """The profile along a contour: per row offset ``offs`` from its rows ``j`` (over its
    columns ``i``), the median log grey over the columns. NaN where the row lies outside
    the field (above ``top``, or past the image) over any column, or with ``partial``
    over more than half of them (then the median of the columns inside)."""
    h = img.shape[0]
    rows = np.round(j[None, :] + offs[:, None]).astype(np.intp)
    inside = (rows >= top) & (rows < h)
    vals = _LOG[img[np.clip(rows, 0, h - 1), i[None, :]]]
    # np.median where the row lies inside over all the columns, the usual row
    # (nanmedian is ~10x slower).
    prof = np.full(offs.size, np.nan)
    n_in = np.count_nonzero(inside, axis=1)
    whole = n_in == i.size
    if whole.any():
        prof[whole] = np.median(vals[whole], axis=1)
    if partial:
        part = ~whole & (n_in >= 0.5 * i.size)
        # The median of each such row's columns inside: np.nanmedian's values (its
        # masked-array path costs ~0.3 ms a call on these few tens of rows).
        for r in np.flatnonzero(part).tolist():
            prof[r] = median1d(vals[r][inside[r]])
    return prof


def _cover_lift(
    img: np.ndarray, i: np.ndarray, j: np.ndarray, sy: float, top: float, params: EndsParams
) -> float:
    """How much brighter (log grey) the tissue higher over a contour is than the band
    right over it (:attr:`EndsParams.cover_reach_mm`): on the profile along the contour
    (:func:`_row_medians`), the greatest median of a ``band_mm`` band stacked over the
    band above, up to ``cover_reach_mm`` over the contour and wholly under the near
    field, less the band above's median; 0 when none is brighter or the band above is
    not wholly in the field. Medians: a thin bright line (a fascia, the skin's copies)
    in a band moves them little, a darker muscle filling it does."""
    band = max(1, int(round(params.band_mm / sy)))
    # The bands wholly within the reach (16 mm: three, 1-16 mm over the contour).
    n = int(np.floor((params.cover_reach_mm - params.above_gap_mm) / params.band_mm + 1e-9))
    if n < 2:
        return 0.0
    a1 = int(round(params.above_gap_mm / sy))
    prof = _row_medians(img, i, j, np.arange(-(a1 + n * band), -a1), top, partial=False)
    # Band k (0: the band above) is the k-th block of rows counted up from the contour.
    meds = [prof[prof.size - (k + 1) * band : prof.size - k * band] for k in range(n)]
    if not np.isfinite(meds[0]).all():
        return 0.0
    base = float(np.median(meds[0]))
    higher = [float(np.median(m)) - base for m in meds[1:] if np.isfinite(m).all()]
    return max([0.0, *higher])


def shadow_step(
    image: np.ndarray,
    points_px: np.ndarray,
    spacing: tuple[float, float],
    params: EndsParams = EndsParams(),  # noqa: B008 (frozen dataclass)
) -> float:
    """How much darker the tissue under a contour is than the tissue above it (log grey).

    Parameters
    ----------
    image : ndarray (H, W) uint8
    points_px : ndarray (K, 2)
        The contour's ``(i, j)`` = (column, row), sub-pixel.
    spacing : (float, float)
        Pixel spacing (mm) along columns and rows.
    params : EndsParams

    Returns
    -------
    float
        Median over the contour's columns (one every ~``column_mm``) of the mean log
        grey in ``[under_gap_mm, under_gap_mm + band_mm]`` under the contour less that
        in ``[above_gap_mm, above_gap_mm + band_mm]`` above it (not above
        ``near_field_mm`` under the imaged field's top: under a black band over the
        contour's columns, as :func:`.evidence.outside_field`), less how much brighter
        the tissue higher over it is (:func:`_cover_lift`, up to ``cover_reach_mm``: a
        muscle on the bone is looked past): negative under bone (its shadow starts at
        the contour), near zero under a layer over tissue or in a shade cast from
        above. NaN when no band fits in the image.
    """
    if points_px.shape[0] == 0:
        return float("nan")
    img, i, j, sy = _columns(image, points_px, spacing, params.column_mm)
    h = img.shape[0]
    band = params.band_mm / sy
    under0 = j + params.under_gap_mm / sy
    above1 = j - params.above_gap_mm / sy
    top = _field_top(img, i, sy) + params.near_field_mm / sy
    above0 = np.maximum(above1 - band, top)
    # Only the rows the bands reach, cumulated once per column.
    r0 = int(max(0, np.floor(above0.min())))
    r1 = int(min(h, np.ceil((under0 + band).max()) + 1))
    if r1 - r0 < 2:
        return float("nan")
    cum = np.zeros((r1 - r0 + 1, i.size))
    np.cumsum(_LOG[img[r0:r1, i]], axis=0, out=cum[1:])
    d = _band_means(cum, under0 - r0, under0 + band - r0) - _band_means(
        cum, above0 - r0, above1 - r0
    )
    d = d[np.isfinite(d)]
    if not d.size:
        return float("nan")
    return float(np.median(d)) - _cover_lift(img, i, j, sy, top, params)


def trough_step(
    image: np.ndarray,
    points_px: np.ndarray,
    spacing: tuple[float, float],
    params: EndsParams = EndsParams(),  # noqa: B008 (frozen dataclass)
) -> float:
    """:func:`shadow_step`'s bands read on the profile along the contour (per row offset,
    the median log grey over its columns, one every ~``column_mm``): the darkest
    ``trough_mm`` layer of the band under it less the mean of the band above. NaN when
    ``trough_mm`` is 0 or no layer fits in the image."""
    if points_px.shape[0] == 0 or not params.trough_mm > 0:
        return float("nan")
    img, i, j, sy = _columns(image, points_px, spacing, params.column_mm)
    a1 = int(round(params.above_gap_mm / sy))
    u0 = int(round(params.under_gap_mm / sy))
    band = max(1, int(round(params.band_mm / sy)))
    offs = np.arange(-(a1 + band), u0 + band + 1)
    top = _field_top(img, i, sy) + params.near_field_mm / sy
    # A row offset counts where it lies in the image over at least half the columns.
    prof = _row_medians(img, i, j, offs, top, partial=True)
    above = prof[: band + 1]
    above = above[np.isfinite(above)]
    k = max(1, int(round(params.trough_mm / sy)))
    under = prof[offs >= u0]
    if above.size == 0 or under.size < k:
        return float("nan")
    layers = np.convolve(under, np.full(k, 1.0 / k), mode="valid")  # NaN where it is out
    layers = layers[np.isfinite(layers)]
    if layers.size == 0:
        return float("nan")
    return float(layers.min() - above.mean())


#: Readings of a contour's shadow step (:func:`shadow_steps`): the band's mean, its
#: darkest layer.
READINGS = 2


def steps_array(rows: Iterable[np.ndarray]) -> np.ndarray:
    """Contours' :func:`shadow_steps` as one ``(n, READINGS)`` array (n may be 0)."""
    return np.array(list(rows), dtype=float).reshape(-1, READINGS)


def unmeasured() -> np.ndarray:
    """The steps of a contour not measured (a copy, or the cut off): NaN each reading."""
    return np.full(READINGS, np.nan)


def shadow_steps(
    image: np.ndarray,
    points_px: np.ndarray,
    spacing: tuple[float, float],
    params: EndsParams = EndsParams(),  # noqa: B008 (frozen dataclass)
) -> np.ndarray:
    """Both readings of a contour's step, ``[shadow_step, trough_step]`` (shape (2,)):
    what :func:`bone_free_ends` judges a track frame by."""
    return np.array(
        [
            shadow_step(image, points_px, spacing, params),
            trough_step(image, points_px, spacing, params),
        ]
    )


def _weakness(steps: np.ndarray, ratio: float) -> np.ndarray | None:
    """``ratio - step / typical`` per frame (0 where not measured; None: no shadow on the
    track, or too few frames measured, to judge against)."""
    ok = np.isfinite(steps)
    if ok.sum() < 3:
        return None
    typical = float(np.median(steps[ok]))
    if not typical < 0:
        return None
    return np.where(ok, ratio - steps / typical, 0.0)


def bone_free_ends(steps: np.ndarray, params: EndsParams = EndsParams()) -> np.ndarray:  # noqa: B008
    """Which of a track's frames (in sweep order) to cut at its two ends.

    Parameters
    ----------
    steps : ndarray (T,) or (T, 2)
        Of each track frame, in sweep order (NaN: not measured): :func:`shadow_step`,
        or both readings (:func:`shadow_steps`).
    params : EndsParams

    Returns
    -------
    ndarray of bool (T,)
        True for the frames cut: at each end, the run whose summed weakness is
        greatest, when that sum is positive and greater than the largest summed
        weakness of any run of the frames between the two ends' runs (the bone's own
        weakest stretch); never more than ``max_cut_share`` of the track. A frame's
        weakness is ``min_ratio - step / typical`` (``typical`` the track's median
        step); with both readings, the lesser of that and ``trough_ratio -
        trough / typical trough``: a frame is as weak as both find it.
    """
    steps = np.asarray(steps, dtype=float)
    t = steps.shape[0]
    cut = np.zeros(t, bool)
    if t < 3:
        return cut
    cols = steps.reshape(t, -1)
    ratios = (params.min_ratio, params.trough_ratio)
    found = []
    for k in range(cols.shape[1]):
        if not np.isfinite(cols[:, k]).any():
            continue  # not read (``trough_mm`` 0)
        w = _weakness(cols[:, k], ratios[k])
        if w is None:
            return cut  # the track's own frames cast no shadow: nothing to judge against
        found.append(w)
    if not found:
        return cut
    # A frame not measured weighs nothing either way; a frame that looks like the
    # bone weighs ``strong_weight`` times more than a weak one: the bone's own frames
    # vary (a real recording's 0.4-1.6 of its median), a run past its end is weak
    # throughout.
    weak = np.minimum.reduce(found)
    weak = np.where(weak < 0, params.strong_weight * weak, weak)
    most = int(np.floor(params.max_cut_share * t))
    # Each end's candidate run: the one whose summed weakness is greatest.
    runs = []
    for order in (np.arange(t), np.arange(t)[::-1]):  # from the first frame, the last
        s = np.cumsum(weak[order])[:most]
        n = int(np.argmax(s)) + 1 if s.size and s.max() > 0 else 0
        runs.append((order[:n], float(s[n - 1]) if n else 0.0))
    # The bar a run must clear: the weakest stretch of the bone itself, the largest
    # summed weakness of a run between the two (both neighbours vouch for it). How far
    # the bone's own steps stray depends on the recording: reverberation copies in a
    # grey shadow move the under-band's grey with the copies' phase (S clavicle grey
    # s113: frames 0-1, on the bone, at 0.43 and 0.41 of typical were cut, summed
    # weakness 0.16, while frame 34, inside the track and on the bone too, read 0.29
    # alone, 0.21). A run past the bone's end is weak throughout and sums more.
    bar = _largest_run_sum(weak[runs[0][0].size : t - runs[1][0].size])
    for frames, total in runs:
        if frames.size and total > bar:
            cut[frames] = True
    if cut.sum() > most:  # both ends at once: keep the larger share of the track
        return np.zeros(t, bool)
    return cut


def _largest_run_sum(x: np.ndarray) -> float:
    """The largest sum of a run of consecutive values of ``x`` (0 for none, or all
    negative): the maximum subarray sum, from cumulative sums (vectorised Kadane)."""
    if x.size == 0:
        return 0.0
    c = np.concatenate(([0.0], np.cumsum(x)))
    return float(max(0.0, np.max(c - np.minimum.accumulate(c))))


def candidate_steps(
    image: np.ndarray,
    fc: FrameCandidates,
    params: EndsParams = EndsParams(),  # noqa: B008 (frozen dataclass)
) -> np.ndarray:
    """:func:`shadow_steps` of each of a frame's candidates the track may choose, shape
    ``(n, 2)`` (NaN for a reverberation copy, and for all with the cut off).

    A live session measures them as the frame arrives, while it has the pixels: the
    step depends only on the frame and the candidate, and the track may choose any
    usable candidate at a later refit, when the pixels may be gone (~1 ms per frame of
    480x640 with ~5 candidates, against ~30 ms for making them).
    """
    return steps_array(
        shadow_steps(image, c.points_px, fc.spacing, params)
        if params.enabled and not c.reverberation
        else unmeasured()
        for c in fc.candidates
    )


def cut_ends_at_steps(
    choice: TrackChoice,
    steps: np.ndarray,
    params: EndsParams = EndsParams(),  # noqa: B008 (frozen dataclass)
) -> TrackChoice:
    """``choice`` with its bone-free ends taken off, given the :func:`shadow_steps` (or
    the :func:`shadow_step`) of each track frame's chosen candidate (``steps``, in the order of
    ``flatnonzero(choice.chosen >= 0)``); see :func:`cut_bone_free_ends`.
    """
    on = np.flatnonzero(choice.chosen >= 0)
    steps = np.asarray(steps, dtype=float)
    if not params.enabled or on.size < 3:
        return choice
    cut = bone_free_ends(steps, params)
    if not cut.any():
        return choice
    cols = steps.reshape(on.size, -1)
    typical = [np.median(c[np.isfinite(c)]) if np.isfinite(c).any() else np.nan for c in cols.T]
    rel = cols / np.asarray(typical)
    chosen = choice.chosen.copy()
    conf = choice.confidence.copy()
    reason, detail = list(choice.reason), list(choice.detail)
    for n, r in zip(on[cut], rel[cut], strict=True):
        chosen[n], conf[n] = -1, 0.0
        reason[n] = REASONS["noshadow"]
        detail[n] = f"step {r[0]:.2f} of the track's typical" + (
            f" (its darkest layer {r[1]:.2f})" if r.size > 1 and np.isfinite(r[1]) else ""
        )
    return TrackChoice(chosen, conf, reason, detail)


def cut_bone_free_ends(
    frames: Sequence[FrameCandidates],
    choice: TrackChoice,
    images: Callable[[np.ndarray], Iterable[np.ndarray]],
    params: EndsParams = EndsParams(),  # noqa: B008 (frozen dataclass)
) -> TrackChoice:
    """``choice`` with the track's bone-free ends taken off (:func:`bone_free_ends`).

    ``images(ns)`` yields the images of the frames at positions ``ns`` of ``frames``,
    in that order (a sweep's ``iter_frames``, which keeps a memory-mapped sweep's pages
    from piling up). Frames cut are rejected with the reason "no bone shadow under it"
    and their step relative to the track's typical one in the detail.
    """
    if not params.enabled:
        return choice
    on = np.flatnonzero(choice.chosen >= 0)
    if on.size < 3:
        return choice
    steps = steps_array(
        shadow_steps(
            image, frames[n].candidates[int(choice.chosen[n])].points_px, frames[n].spacing, params
        )
        for n, image in zip(on.tolist(), images(on), strict=True)
    )
    return cut_ends_at_steps(choice, steps, params)


def cut_ends_and_choose_again(
    choice: TrackChoice,
    solve: Callable[[Mapping[int, tuple[str, str]]], TrackChoice],
    steps: Callable[[TrackChoice], np.ndarray],
    params: EndsParams = EndsParams(),  # noqa: B008 (frozen dataclass)
) -> TrackChoice:
    """``choice`` with its bone-free ends cut, the track chosen again without the frames
    cut, and that track's bone-free ends cut (see the module docstring).

    Parameters
    ----------
    choice : TrackChoice
    solve : callable
        ``solve(exclude)``: the track chosen over the same frames with the frames of
        ``exclude`` (position -> (reason, detail)) ruled out
        (:func:`~.track.select_bone_track`'s or
        :meth:`~.track_incremental.IncrementalTrack.solve`'s ``exclude``).
    steps : callable
        ``steps(choice)``: the :func:`shadow_step` of each track frame's chosen
        candidate, in the order of ``flatnonzero(choice.chosen >= 0)``.
    params : EndsParams

    Returns
    -------
    TrackChoice
    """
    if not params.enabled:
        return choice
    cut = cut_ends_at_steps(choice, steps(choice), params)
    gone = np.flatnonzero((cut.chosen < 0) & (choice.chosen >= 0)).tolist()
    if not gone or not params.choose_again:
        return cut
    again = solve({n: (cut.reason[n], cut.detail[n]) for n in gone})
    return cut_ends_at_steps(again, steps(again), params)

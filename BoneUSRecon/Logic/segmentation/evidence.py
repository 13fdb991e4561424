"""Contrast-adaptive bone evidence of one frame: every level comes from the frame itself.

A bone echo is a bright line *relative to what surrounds it*, with an acoustic shadow
*relative to the tissue at the same depth beside it*. Real recordings differ by an
order of magnitude in absolute terms (bone echo 1.35x the tissue above it on a cadaver
leg, 2.7x on the L14 forearm, 3x in the simulator; shadow 0.65 of the tissue beside it
on the cadaver, 0.2 in the simulator), so no absolute grey level can decide bone / no
bone. Here every quantity is a log-ratio between two regions of the same frame, and
every log-ratio is then measured in units of its own spread over the frame (a robust
z-score: 1.4826 x the median absolute deviation). The spread is what speckle alone
produces with this probe, this gain and these region sizes, so "2 units" means "twice
what speckle does by chance" on any recording; that is why the levels generalise.

Per working pixel (rows = candidate echo centre, columns = the lateral position):

* **tissue level** ``T(row)``: a percentile of the grey values of the usable columns at
  that depth, smoothed over ~1 mm of depth (per-depth tissue statistics: gain, TGC and
  attenuation change it with depth, so it is measured per row). Two references come
  from it, robust to a bone or the skin line spanning most of the width: for the
  shadow windows the 80th percentile (tissue beside a shadow covering up to 80 % of
  the columns); for the echo band and the cover the 60th percentile's minimum within
  +-1 mm of depth (a thin line spanning the width raises only its own rows).
* **echo** ``log(M_mid / max(M_up, T_echo(row)))``: the band brighter than both the
  tissue right above it and the typical tissue at its depth.
* **shadow** ``min(log(T_near / M_near), log(T_far / M_far))``: the region under the
  band darker than the tissue *at the same depth* (not than the echo: a grey shadow
  0.4 of the echo is still 0.65 of the tissue beside it), over a near window
  (``shadow_gap_mm`` .. ``shadow_mm``: the shadow starts right under the surface, so a
  line mm above the bone, with tissue beneath, is not it) and a long one (down to
  ``far_shadow_mm``: the shadow depth; bone stops sound to the bottom of the image, a
  vessel lumen or a gap between fasciae is dark for a few mm only, with brighter
  tissue (posterior enhancement, ring-down) under it).
* **cover** ``M_cover / T_cover``: soft tissue above the band (1-5 mm above, the part of
  that window inside the image), compared with the tissue at those depths. Bone
  always lies under soft tissue; the skin line over a no-contact gap, the lens
  reverberations of an uncoupled probe, and the posterior wall of a vessel have
  anechoic gel, air or lumen above them. Pixels whose cover is darker than
  ``cover_ratio`` of the tissue there score 0.

The shadow's z-score is centred on the tissue, not on the frame: the median of the
frame's shadow log-ratio is the tissue's only while shadow fills a minority of the
pixels. A bone 5-8 mm under the skin (the cadaver sweep's depth went 25 -> 5 mm) casts
its shadow over half the frame and more, and the median moves into it: on a hard
simulated radius (seed 71, 160 x 128) the bone's own shadow log-ratio stayed 0.48-0.65
from 24 mm deep to 5 mm, its z-score fell from 2.4 to 0.4, and the shallow frames lost
their bone. A shadow only adds values above the tissue's, so the lower tail (10th and
25th percentiles, a normal null) is the tissue's; where the median lies more than
``shadow_null_tolerance`` spreads above the centre so estimated, the centre moves down
by the excess (:func:`_shadow_scale`; clean frames are unchanged).

The score is the echo z-score (positive part) times a shadow gate rising from 0 at
``shadow_z_zero`` (the region below brighter than the tissue at its depth: a fascia or
tendon, a bright line with tissue beneath) to 1 at ``shadow_z_full`` (clearly darker),
and on at the same slope to ``shadow_gate_max`` (2, at a shadow z of 3, where the
shadow holds over ``shadow_gate_width_mm`` to either side): soft tissue does not stop
sound, so a shadow far darker than the tissue beside it is the surest sign of bone, and
a faint echo over it must not lose to a brighter layer over tissue. With the gate flat
from 1 on, a hard simulated clavicle whose echo was 1.2x the tissue above, over a black
shadow (z 4-5), scored 0-1.4 along its top against 1-1.6 for a layer under the skin
with a barely darker band beneath (z ~0.5), and the sweep's track took the layer
(recall 0.03, 90 % of frames wrong); at 2 it holds (recall 0.93, no frame wrong). In z
units of the frame's own spread, like every level here.

Columns outside the imaged field of view (black margins of scan-converted images) and
columns without probe contact (dark from the near field down, as an uncoupled probe
edge is) score 0. Columns under a *partial* no-contact gap at an edge of the field
(the skin curving away from the probe over gel or air: dark over part of the first mm
under the near field) keep their place, but the shade the gap casts on them (their
darkness above the band relative to the columns in contact) is not credited to a
line under it as its shadow (``gap_shade``, :func:`_edge_gap`). Black bands over and
under the field across its whole width (a frame grabber's capture of the scanner's
screen, a loose clip rectangle) are outside it (:func:`outside_field`): the near field
starts under the band, and a score's windows lie within the field's rows.

Optional terms, off by default (measured and not kept; the figures in their modules and
in ``Testing/benchmarks/README.md``): Karamalis' confidence drop mixed into the shadow
z-score (``confidence_weight``, :mod:`.confidence`) and phase symmetry along depth as a
factor on the score (``phase_weight``, :mod:`.phase`). Features tried, kept and dropped:
``Testing/benchmarks/README.md``.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.ndimage import gaussian_filter1d, minimum_filter1d

from BoneUSRecon.Logic.segmentation.confidence import confidence_drop
from BoneUSRecon.Logic.segmentation.features import (
    ceil_px,
    column_cumsum,
    median1d,
    mm_to_px,
    row_minimum_filter,
    sorted_percentile,
    sorted_row_medians,
    sorted_row_percentiles,
)
from BoneUSRecon.Logic.segmentation.params import ShadowPathParams
from BoneUSRecon.Logic.segmentation.phase import phase_factor, phase_symmetry_depth

__all__ = [
    "EvidenceMaps",
    "working_image",
    "field_of_view",
    "outside_sector",
    "outside_field",
    "field_rows",
    "field_tops",
    "tissue_level",
    "bone_evidence",
]

_EPS = np.float32(1e-3)  # grey/255: guards log(0) in black regions (no decision rests on it)


@dataclass(frozen=True, eq=False)
class EvidenceMaps:
    """Bone evidence of one frame on the working grid.

    Attributes
    ----------
    work : ndarray, shape (h, w)
        Block-averaged frame, grey/255.
    colmean : ndarray, shape (H, w)
        Column-block averages at full depth resolution (for sub-pixel refinement).
    fx, fy : int
        Block size (image columns and rows per working pixel).
    dx, dy : float
        Working pixel size, mm.
    usable : ndarray of bool, shape (w,)
        Columns inside the field of view and in contact.
    tissue : ndarray, shape (h,)
        Tissue level per working row, grey/255.
    echo_z, shadow_z : ndarray, shape (h, w)
        Robust z-scores of the echo and shadow log-ratios.
    score : ndarray, shape (h, w)
        ``sqrt(echo_z+ * shadow_z+)`` where scoring is allowed, else 0.
    tissue_beside : ndarray, shape (h,)
        The level the shadow windows are compared with (``shadow_percentile`` per row:
        the tissue beside a shadow that covers most of the width), grey/255.
    log_tissue_ratio : float
        Where plain tissue lies against ``tissue_beside``, in log: the upper quartile
        over rows of the per-row median of ``log(work / tissue_beside)`` (rows mostly
        tissue; speckle's median sits below a high percentile). The baseline of
        ratios measured against ``tissue_beside``.
    fov : ndarray of bool, shape (w,), or None
        Columns inside the imaged field of view (``usable`` without the contact test;
        None: not recorded, as ``usable``).
    field_top : int
        The imaged field's first row (:func:`outside_field`: under a black band over
        the whole width; 0 without one). The near field is measured from it.
    """

    work: np.ndarray
    colmean: np.ndarray
    fx: int
    fy: int
    dx: float
    dy: float
    usable: np.ndarray
    tissue: np.ndarray
    echo_z: np.ndarray
    shadow_z: np.ndarray
    score: np.ndarray
    tissue_beside: np.ndarray
    log_tissue_ratio: float
    fov: np.ndarray | None = None
    field_top: int = 0

    def frame_level(self) -> float:
        """The frame's tissue level: the median of :attr:`tissue` over the rows from 15
        to 50 % of the depth (grey/255).

        Below the skin line and the lens's reverberation bands, above the depths where
        a bone's shadow fills much of the width: the soft tissue's backscatter. With the
        probe off the skin none comes back and the level falls to the noise floor; a
        frame is judged against its own sweep's frames (:attr:`.params.RecoveryParams.contact_level`),
        never against a grey level.
        """
        h = self.tissue.shape[0]
        return float(np.median(self.tissue[int(0.15 * h) : max(int(0.5 * h), int(0.15 * h) + 1)]))

    def work_index(self, points_px: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """The working pixel nearest to each image point ``(i, j)``: its rows and
        columns, clipped to the working image (a block's centre lies at image pixel
        ``(index + 0.5) * f - 0.5``)."""
        pts = np.asarray(points_px, float)
        h, w = self.score.shape
        col = np.clip(np.rint((pts[:, 0] + 0.5) / self.fx - 0.5).astype(np.intp), 0, w - 1)
        row = np.clip(np.rint((pts[:, 1] + 0.5) / self.fy - 0.5).astype(np.intp), 0, h - 1)
        return row, col

    @property
    def nbytes(self) -> int:
        """Bytes held by the maps (~1.8 MB for a 480x640 frame at 0.15 mm per pixel)."""
        return sum(a.nbytes for a in vars(self).values() if isinstance(a, np.ndarray))


def working_image(
    image: np.ndarray, spacing: tuple[float, float], work_mm: float
) -> tuple[np.ndarray, np.ndarray, int, int]:
    """Block-average ``image`` to pixels of about ``work_mm``: ``(work, colmean, fx, fy)``.

    Averaging (not sub-sampling) also averages out speckle; strided slice sums are
    several times faster than ``reshape(...).mean`` on uint8.
    """
    fx = mm_to_px(work_mm, float(spacing[0]))
    fy = mm_to_px(work_mm, float(spacing[1]))
    img = np.asarray(image)
    w = img.shape[1] // fx
    h = img.shape[0] // fy
    if fx == 2 and img.dtype == np.uint8 and img.strides[1] == 1 and img.ndim == 2:
        # Pairs of grey values read as one 16-bit word each and summed as integers
        # (exact, as their float32 sum is: the same values; ~3x faster than two strided
        # uint8 reads, converted and added).
        pair = img[:, : w * fx].view(np.uint16)
        both = pair >> 8
        both += pair & 0xFF
        colmean = both.astype(np.float32)
    else:
        colmean = img[:, 0 : w * fx : fx].astype(np.float32)
        for q in range(1, fx):
            colmean += img[:, q : w * fx : fx]
    colmean *= np.float32(1.0 / (255.0 * fx))
    work = colmean[0 : h * fy : fy].copy()
    for q in range(1, fy):
        work += colmean[q : h * fy : fy]
    work *= np.float32(1.0 / fy)
    return work, colmean, fx, fy


def field_of_view(
    work: np.ndarray, dx: float, params: ShadowPathParams, imaged: np.ndarray | None = None
) -> np.ndarray:
    """Columns of a working image (values 0..1) inside the imaged field of view, shape (w,).

    A column is inside when more than ``fov_fraction`` of its pixels are brighter than
    ``fov_grey`` (scan-converted images are exactly black outside the imaged area: an
    instrument fact, not a tissue level); the inside is then shrunk by
    ``fov_margin_mm`` on each side of every outside run (the edge columns are averaged
    with the black margin). ``imaged``: ``work`` over ``fov_grey`` if the caller has it.
    """
    p = params
    if imaged is None:
        imaged = work > np.float32(p.fov_grey / 255.0)
    inside = imaged.mean(axis=0) > p.fov_fraction
    k = int(round(p.fov_margin_mm / dx))
    if k > 0 and not inside.all():
        pad = np.pad(inside, k, mode="edge")
        inside = sliding_window_view(pad, 2 * k + 1).all(axis=1)
    return inside


def outside_sector(
    work: np.ndarray,
    dx: float,
    dy: float,
    params: ShadowPathParams,
    imaged: np.ndarray | None = None,
) -> np.ndarray | None:
    """Pixels of a working image outside a sector-shaped field of view, shape (h, w),
    or None when the field is no sector (a linear probe).

    A curvilinear (or steered, trapezoidal) probe's scan-converted image is a sector:
    black (at or under ``fov_grey``, an instrument fact as for :func:`field_of_view`)
    over the near rows of the columns at its sides, imaged below. The column rule
    cannot see it: such a column is black over its near rows only, which
    :func:`_contact` and :func:`_edge_gap` read as a probe edge off the skin and the
    tissue levels of those rows as darker tissue (a hard simulated humerus under a
    sector keeping half the top row, 475 x 405: 131 of 237 columns usable against ~203
    inside the field, surface 0.39 mm from gold against 0.27 in the linear field).

    Each column is imaged from the first row that starts 1 mm of pixels over the
    black; the rows above are the outside. The field is a sector when the columns at
    either end of the imaged ones start at least a quarter of the image deep (a
    sector's sides reach its top only at its apex). Why it generalises: it reads only
    the scanner's exact black and the field's shape, no tissue level; a depth ruler's
    dots or a text line under 1 mm tall in the margin are passed over (a taller label
    keeps its columns as before); a linear image's black padding (whole columns, the
    column rule's), its dark floor or a shadow reaching the padding deep down (the L14
    recording), a stand-off's black rows over the whole width or a no-contact patch at
    a near corner make no sector. ``imaged``: ``work`` over ``fov_grey`` if the caller
    has it (:func:`field_of_view`'s mask).
    """
    if imaged is None:
        imaged = work > np.float32(params.fov_grey / 255.0)
    return _sector_outside(field_tops(imaged, dy), _field_columns(imaged, params), work.shape[0])


def _sector_outside(top: np.ndarray | None, field: np.ndarray, h: int) -> np.ndarray | None:
    """:func:`outside_sector` from the mask's :func:`field_tops` ``top`` and its
    :func:`_field_columns` ``field`` (``h`` rows): :func:`outside_field` reads both
    too, and makes them once."""
    if top is None:
        return None
    cols = np.flatnonzero((top < h) & field)
    if cols.size < 2 or max(top[cols[0]], top[cols[-1]]) < h // 4:
        return None
    return np.arange(h)[:, None] < top[None, :]


def _field_columns(imaged: np.ndarray, params: ShadowPathParams) -> np.ndarray:
    """The widest run of columns more than ``fov_fraction`` imaged, shape (w,): the
    image itself, not a grey-scale bar, a ruler or a marker drawn beside it (a focus
    marker's few columns at mid-depth made a linear field a sector)."""
    inside = imaged.mean(axis=0) > params.fov_fraction
    edges = np.diff(np.r_[0, inside.astype(np.int8), 0])
    starts, ends = np.flatnonzero(edges == 1), np.flatnonzero(edges == -1)
    out = np.zeros_like(inside)
    if starts.size:
        k = int(np.argmax(ends - starts))
        out[starts[k] : ends[k]] = True
    return out


def field_tops(imaged: np.ndarray, dy: float) -> np.ndarray | None:
    """Per column of a mask of imaged pixels (over the scanner's black), shape (h, w),
    the first row starting 1 mm of them (h: none); None when it is under 1 mm tall
    (``dy``: its row spacing, mm). A depth ruler's dots or a label's glyphs under 1 mm
    tall start no field."""
    h = imaged.shape[0]
    run = max(1, int(round(1.0 / dy)))
    if h <= run:
        return None
    if imaged.dtype == bool:
        # starts[r]: rows r .. r + run - 1 all imaged, as runs of 1, 2, 4, ... rows each
        # the AND of two runs of half its length, then the window as two overlapping
        # runs: the same mask as counting them on a cumulative sum, without a sum down
        # the columns (~6x faster at a working image's 240 x 320).
        runs, span = imaged, 1
        while 2 * span <= run:
            runs = runs[:-span] & runs[span:]
            span *= 2
        starts = runs[: h - run + 1] & runs[run - span : h - span + 1]
    else:
        cs = np.zeros((h + 1, imaged.shape[1]), np.int32)
        np.cumsum(imaged, axis=0, out=cs[1:])
        starts = (cs[run:] - cs[:-run]) == run  # (h - run + 1, w)
    return np.where(starts.any(axis=0), np.argmax(starts, axis=0), h)


#: Share of the imaged columns that must start at one depth (within 1 mm of their
#: median start) for a black band over a linear field (:func:`outside_field`).
_BAND_FLAT_SHARE = 0.6
#: A row under the field is in a band when this share of the field's columns are exactly
#: 0 there (:func:`outside_field`: a screen's black; a bone's shadow reaching the frame's
#: bottom over the whole width, as black as the scanner's floor, still holds its noise:
#: the analytic frames of ``test_segmentation.py`` lost their bone to a band read as
#: the top band is, their shadows under ``fov_grey``).
_UNDER_ZERO_SHARE = 0.9


def outside_field(
    work: np.ndarray,
    dx: float,
    dy: float,
    params: ShadowPathParams,
    imaged: np.ndarray | None = None,
) -> np.ndarray | None:
    """Pixels of a working image outside its imaged field, shape (h, w), or None (none).

    A sector's black outside (:func:`outside_sector`) and any band under it, or black
    bands over the whole width above and under a linear field: a frame grabber's screen capture, a loose
    clip rectangle, a scanner drawing its image lower. A band is neither dark tissue
    nor a probe edge off the skin nor a bone's shadow, yet the contact test read the
    band's rows (2-6 mm under the frame's top) as uncoupled in every column (the L14
    recording with 6 mm more of black over it kept no frame), and a line drawn along
    the field's bottom edge (a screen's frame round the image) had the band under it
    for a perfect shadow (17 of its 21 frames kept that line, 25 mm under the bone).

    A band is flat: most imaged columns (``_BAND_FLAT_SHARE``) start (or end) within
    1 mm of their median start (end), at least 1 mm from the frame's edge; the band
    reaches to it. Labels, a grey-scale bar or a depth ruler in the margins are a
    minority of the columns and lie in the band or beside the field. The band under
    the field is held to more, since a bone's shadow spanning the width may be as dark
    and its edge as flat: its rows, at least 1 mm of them, are exactly 0 over nearly
    all the field's columns (``_UNDER_ZERO_SHARE``: a screen's black; a shadow keeps
    the scanner's noise in it). Why it generalises: it reads only the scanner's exact black (``fov_grey``, an
    instrument fact) and the field's shape, as the sector rule does. A probe edge off
    the skin is no band: the columns in contact start at the top.
    """
    if imaged is None:
        imaged = work > np.float32(params.fov_grey / 255.0)
    h, w = work.shape
    # The column tops and the field's columns, made once for the sector and band rules.
    tops = field_tops(imaged, dy)
    field = _field_columns(imaged, params)
    sector = _sector_outside(tops, field, h)
    run = max(1, int(round(1.0 / dy)))
    if not field.any():
        return sector

    def band_depth(tops: np.ndarray | None) -> int:
        # Rows of a flat black band from the frame's edge (0: none).
        if tops is None:
            return 0
        cols = tops[(tops < h) & field]
        if cols.size < 2:
            return 0
        depth = float(np.median(cols))
        if depth < run or np.mean(np.abs(cols - depth) <= run) < _BAND_FLAT_SHARE:
            return 0
        return int(depth)

    # Over a sector, its own outside holds any band over it.
    above = band_depth(tops) if sector is None else 0
    # Under the field: the last rows exactly 0 over nearly all its columns.
    zero = (work[:, field] == 0).mean(axis=1) >= _UNDER_ZERO_SHARE
    under = int(np.argmin(zero[::-1])) if not zero.all() else 0
    under = under if under >= run else 0
    if not above and not under:
        return sector
    band = np.zeros((h, w), bool) if sector is None else sector.copy()
    band[:above] = True
    band[h - under :] = True
    return band


def field_rows(outside: np.ndarray | None, h: int) -> tuple[int, int]:
    """The rows ``[first, end)`` of the imaged field: those not wholly outside it at
    the frame's top and bottom (:func:`outside_field`'s bands; the whole frame if None)."""
    if outside is None:
        return 0, h
    inside = np.flatnonzero(~outside.all(axis=1))
    if inside.size == 0:
        return 0, h
    return int(inside[0]), int(inside[-1]) + 1


def tissue_level(
    work: np.ndarray,
    columns: np.ndarray,
    percentile: float | tuple[float, ...],
    dy: float,
    outside: np.ndarray | None = None,
) -> np.ndarray:
    """Tissue grey level per row: a percentile over ``columns``, smoothed over ~1 mm of depth.

    Several percentiles at once (one partition of the rows) give shape ``(n, h)``.
    ``outside``: pixels outside a sector-shaped field (:func:`outside_sector`), left
    out of their rows' percentiles.
    """
    # Half the columns suffice for a percentile (from 40 on): every other one of the
    # selected columns, gathered once.
    cols = np.flatnonzero(columns) if columns.any() else np.arange(work.shape[1])
    pick = cols[::2] if cols.size >= 40 else cols
    sel = work[:, pick]
    # Sorting the rows first: the same order statistics, so the same percentiles, and a
    # row-wise sort is several times faster than numpy's per-row selection at these sizes.
    # np.percentile's values read from the sorted rows (no re-partition).
    srt = np.sort(sel, axis=1)
    qs = percentile if isinstance(percentile, tuple) else (percentile,)
    if outside is None:
        t = sorted_row_percentiles(srt, qs)
    else:
        t = _inside_percentiles(srt, outside[:, pick].sum(axis=1), qs)
    t = (t if isinstance(percentile, tuple) else t[0]).astype(np.float32)
    t = gaussian_filter1d(t, max(0.5, 1.0 / dy), axis=-1, mode="nearest")
    # Relative floor (a fraction of the frame's own typical tissue level): deep rows of
    # a dark image must not turn a ratio into a division by ~0.
    # (np.median's values from the rows sorted: ~10x cheaper on these two short rows.)
    med = sorted_row_medians(np.sort(t, axis=-1).reshape(-1, t.shape[-1]))
    med = np.maximum(med.reshape(t.shape[:-1] + (1,)), _EPS)
    return np.maximum(t, np.float32(0.05) * med.astype(np.float32))


def _inside_percentiles(srt: np.ndarray, n_out: np.ndarray, q: tuple[float, ...]) -> np.ndarray:
    """Percentiles ``q`` of sorted rows without their first ``n_out`` values (the black
    outside a sector sorts first), shape ``(len(q), h)``; numpy's "linear" rule. A row
    with nothing inside takes the nearest row's values that has (0 if none has)."""
    h, n = srt.shape
    m = n - n_out  # values inside, per row
    has = m > 0
    pos = n_out[None, :] + (np.asarray(q, float)[:, None] / 100.0) * np.maximum(m - 1, 0)[None, :]
    i0 = np.clip(np.floor(pos).astype(np.intp), 0, n - 1)
    i1 = np.minimum(i0 + 1, n - 1)
    g = pos - i0
    rows = np.arange(h)[None, :]
    out = srt[rows, i0] + (srt[rows, i1] - srt[rows, i0]) * g
    if not has.all():
        if not has.any():
            return np.zeros_like(out)
        # Each row's nearest row with values inside (outside_sector's empty rows are
        # the top ones: their nearest is the first row imaged).
        near = np.flatnonzero(has)
        out = out[:, near[np.abs(np.arange(h)[:, None] - near[None, :]).argmin(axis=1)]]
    return out


@functools.lru_cache(maxsize=64)
def _window_plan(
    h: int, a_off: int, b_off: int, dtype: str
) -> tuple[int, int, np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """What :func:`_window_mean` needs besides the data, for ``h`` rows and these offsets.

    Every frame of a sweep has the same size and window offsets, so the clipped index
    arrays and the divisor are built once (they cost more than the window sums at
    working-image sizes). Returns ``(lo, hi, edge, a_edge, b_edge, divisor)``: rows
    ``lo:hi`` are plain slices, rows ``edge`` are gathered at their clipped ends, and
    ``divisor`` (h, 1) holds the window lengths (at least 1) in ``dtype``. Read-only.
    """
    j = np.arange(h)
    a = np.clip(j + a_off, 0, h)
    b = np.clip(j + b_off, 0, h)
    lo = max(0, -a_off, -b_off)
    hi = min(h, h - a_off + 1, h - b_off + 1)
    if hi > lo:
        edge = np.r_[0:lo, hi:h]
    else:
        lo = hi = 0
        edge = j
    div = np.maximum(b - a, 1).astype(dtype)[:, None]
    out = (lo, hi, edge, a[edge], b[edge], div)
    for arr in out[2:]:
        arr.flags.writeable = False  # shared between calls
    return out


def _window_mean(csum: np.ndarray, a_off: int, b_off: int) -> np.ndarray:
    """``column_window_mean(csum, j + a_off, j + b_off)`` for rows ``j = 0 .. H-1``.

    The same values, computed on row slices where neither end is clipped (no gathered
    copies of the cumulative sum: the windows of bone_evidence are fixed offsets), with
    the index arrays of the clipped rows cached per size and offsets (:func:`_window_plan`).
    """
    h = csum.shape[0] - 1
    lo, hi, edge, a_edge, b_edge, div = _window_plan(h, a_off, b_off, csum.dtype.str)
    out = np.empty((h, csum.shape[1]), csum.dtype)
    # Rows whose window ends both lie in 0..h: plain slices.
    if hi > lo:
        np.subtract(csum[lo + b_off : hi + b_off], csum[lo + a_off : hi + a_off], out=out[lo:hi])
    if edge.size:
        out[edge] = csum[b_edge] - csum[a_edge]
    out /= div
    return out


def _robust_scale(x: np.ndarray, valid: np.ndarray) -> tuple[float, float] | None:
    """Median of ``x`` over ``valid`` and 1.4826 x its median absolute deviation (the
    spread, at least 1e-3); None when fewer than 10 pixels are sampled."""
    # Every 3rd valid pixel is plenty for a median (and 3x faster on the hot path).
    return _scale_of(x[valid][::3])


def _scale_of(v: np.ndarray) -> tuple[float, float] | None:
    """:func:`_robust_scale` of an already gathered sample ``v``."""
    if v.size < 10:
        return None
    med = median1d(v)
    return med, max(median1d(np.abs(v - med)) * 1.4826, 1e-3)


def _null_pixels(valid: np.ndarray, dark: np.ndarray | None, min_share: float) -> np.ndarray:
    """The pixels the z-scores' nulls are estimated on: ``valid`` ones not ``dark``.

    The null is what speckle in tissue gives. Near the display's floor (a shadow with
    little electronic noise, a low gain) the grey is a small number and its log ratios
    fluctuate the more, the darker it is, so a null taken over the whole frame widens
    as the shadow darkens: on hard simulated sweeps with less electronic noise (the
    shadow 0.54 of the tissue beside it instead of 0.65) or a display 9 dB darker, the
    echo and shadow spreads grew 1.6-2x, every z-score in the frame shrank by as much,
    and a near cortex 5-8 mm deep fell under the path's null level: recall 0.82 and
    0.81 (475 x 405 and 160 x 128), the easier image read worse than the preset's.
    ``dark`` marks pixels whose band or the window above it is under
    ``null_dark_fraction`` of the tissue beside at their depth (None: the option is
    off, the default). At a quarter a grey shadow (the cadaver's 0.65) stays in the
    null and the preset's frames at 475 x 405 keep 99.9 % of their pixels (the L14
    recording, dark speckle, 87-91 %). Both levels are the frame's own, so no grey
    level decides. When fewer than ``min_share`` of the valid pixels remain (a frame
    mostly black), all are used.
    """
    if dark is None:
        return valid
    null = valid & ~dark
    return null if null.sum() >= min_share * valid.sum() else valid


#: Standard normal quantiles of the shadow null's lower tail (10th and 25th percentiles).
_Z10, _Z25 = -1.2815516, -0.6744898


def _shadow_scale(
    log_s: np.ndarray, valid: np.ndarray, tolerance: float
) -> tuple[float, float] | None:
    """Centre and spread of the shadow log-ratio's null (the tissue), robust to a shadow
    filling most of the frame (see the module docstring): :func:`_shadow_scale_of` of
    the sample :func:`_robust_scale` takes (every third ``valid`` pixel)."""
    return _shadow_scale_of(log_s[valid][::3], tolerance)


def _shadow_scale_of(v: np.ndarray, tolerance: float) -> tuple[float, float] | None:
    """:func:`_shadow_scale` of an already gathered sample ``v`` of the shadow
    log-ratio (bone_evidence gathers it once for both z-scores).

    The spread is :func:`_robust_scale`'s. The centre is the median, moved down by as
    much as it lies over ``tolerance`` spreads above the centre of a normal fitted to
    the lower tail (the 10th and 25th percentiles), where no shadow reaches.
    """
    # ``v``: the sample _robust_scale takes (every third null pixel). Sorted once: the
    # same statistics (of the same values) as np.percentile's, whose partition at
    # several ranks costs ~6x a sort.
    v = np.sort(v)
    ms = _scale_of(v)
    if ms is None:
        return None
    med, spread = ms
    q10, q25 = sorted_row_percentiles(v[None, :], (10.0, 25.0))[:, 0]
    sigma = (q25 - q10) / (_Z25 - _Z10)
    centre = float(q25 - _Z25 * sigma)
    return med - max(0.0, med - centre - tolerance * spread), spread


def _robust_z(
    x: np.ndarray, valid: np.ndarray, ms: tuple[float, float] | None = None
) -> np.ndarray:
    """``x`` over 1.4826 x its median absolute deviation about the median (over ``valid``;
    ``ms``: that median and spread, when already computed by :func:`_robust_scale`)."""
    ms = _robust_scale(x, valid) if ms is None else ms
    if ms is None:
        return np.zeros_like(x)
    return (x - np.float32(ms[0])) / np.float32(ms[1])


def _dark_share(
    work: np.ndarray,
    tissue: np.ndarray,
    dy: float,
    near_field_mm: float,
    depth_mm: float,
    outside: np.ndarray | None = None,
) -> np.ndarray | None:
    """Per column, the share of the rows ``depth_mm`` under the near field darker than
    half the tissue level at their depth (None: fewer than 2 such rows in the image).
    ``outside``: pixels outside the field (:func:`outside_field`), not counted (a
    column with none of those rows inside: share 0, nothing says it is off the skin)."""
    h = work.shape[0]
    # From the imaged field's top (a black band over it is outside the field).
    a = field_rows(outside, h)[0] + mm_to_px(near_field_mm, dy, minimum=0)
    b = min(h, a + mm_to_px(depth_mm, dy))
    if b - a < 2:
        return None
    dark = work[a:b] < 0.5 * tissue[a:b, None]
    if outside is None:
        return dark.mean(axis=0)
    ins = ~outside[a:b]
    n = ins.sum(axis=0)
    return np.where(n > 0, (dark & ins).sum(axis=0) / np.maximum(n, 1), 0.0)


def _contact(
    work: np.ndarray,
    tissue: np.ndarray,
    dy: float,
    p: ShadowPathParams,
    outside: np.ndarray | None = None,
) -> np.ndarray:
    """Columns in contact: not dark from the near field down (an uncoupled probe edge is)."""
    # Share of the near rows darker than half the tissue level at their depth: an
    # uncoupled column is dark except for thin, equally spaced lens reverberations.
    dark = _dark_share(work, tissue, dy, p.near_field_mm, p.contact_mm, outside)
    if dark is None:
        return np.ones(work.shape[1], bool)
    return dark < p.contact_dark_fraction


def _edge_gap(
    work: np.ndarray,
    tissue: np.ndarray,
    usable: np.ndarray,
    dx: float,
    dy: float,
    p: ShadowPathParams,
    outside: np.ndarray | None = None,
) -> np.ndarray:
    """Columns under a partial no-contact gap at an edge of the usable field, shape (w,).

    Where the skin curves away from the probe at one end of its face, gel or air lies
    between them: the column is dark under the near field (darker than half the tissue
    level at its depth, as :func:`_contact` judges an uncoupled column) over part of the
    first ``gap_probe_mm``, not all of it, and the tissue under the skin line gets less
    sound (shade that no structure below casts). Such a column is *dark* when the
    share of those rows that are dark exceeds the frame's typical column's (the median
    over the usable columns) by at least ``gap_dark_fraction``. A gap is a run of dark
    columns from the first or last usable column inward, measured with tolerance: a
    stretch of columns that are not dark and narrower than ``gap_min_mm`` does not end
    it (nor, at the edge, start it late), and the run holds at least ``gap_min_mm`` of
    dark columns. It is extended ``gap_margin_mm`` inward from its last dark column
    (the skin returns to contact gradually).

    Why the tolerance: over a gap the darkness is intermittent along the width.
    Speckle in the gel's dim echo straddles the half-tissue level, the skin line
    climbs through the probed rows as the gap thins, and its reverberation copies
    cross them; a column there may read not dark. Ending the run at the first such
    column cut the gap short (hard clavicle seed 83 at 0.108 mm, frame 18: 10 of its
    57 working columns; a fascia over the rest took its shade as a bone's shadow).
    ``gap_min_mm`` is the one scale on both sides: a dark run narrower than it is
    speckle (no gap), and an interruption narrower than it is speckle too (no end of
    the gap).

    Why the typical column: a tolerant run also bridges the dark pixels speckle and a
    hypoechoic layer under the skin (subcutaneous fat, as in the simulator's standard
    scene) put in every column; with a fixed share the run crossed much of the frame
    where no gap was. Measured against the simulator (its gap's columns): hard sweeps,
    seeds 79 and 83, both sizes (800 frames): share of the gap's columns found 0.28 ->
    0.59, frames with the gap found 0.57 -> 0.98, no column flagged beyond the gap;
    hard clavicle seed 83 at 0.108 mm, the columns with more than ``gap_dark_fraction``
    of the probed rows above the skin: 0.46 -> 0.999 found. Sweeps without a gap
    (standard scene: humerus, radius seed 0, clavicle seed 79 at 0.3 mm, tibia seed 0
    at 0.108 mm; tibia seed 0 with a depth ramp only), frames with a gap flagged: 71
    -> 16 of 200 (with the fixed share and the tolerance: 161). On the L14 recording
    and the spine phantom no frame has a gap, as before. Every level is the frame's
    own (the tissue level per depth, the typical column's share), so the rule reads no
    absolute grey; a dark structure inside the field (a vessel, a bone's shadow) does
    not touch the field's edge under the near field.
    """
    w = work.shape[1]
    gap = np.zeros(w, bool)
    cols = np.flatnonzero(usable)
    if not p.gap_shade or cols.size < 2:
        return gap
    share = _dark_share(work, tissue, dy, p.near_field_mm, p.gap_probe_mm, outside)
    if share is None:
        return gap
    # Beyond the frame's typical column: speckle and a hypoechoic layer spanning the
    # width (subcutaneous fat) darken every column's rows, a gap only its own.
    typical = median1d(share[usable])
    dark = (share >= p.gap_dark_fraction + typical) & usable
    least = max(1, ceil_px(p.gap_min_mm / dx))
    margin = int(round(p.gap_margin_mm / dx))
    for edge, step in ((int(cols[0]), 1), (int(cols[-1]), -1)):
        # The dark columns from this edge inward, by their distance from the edge.
        idx = np.flatnonzero(dark[edge::step] if step > 0 else dark[edge::-1])
        # The run starts within ``least`` of the edge and goes on while the stretches
        # between dark columns are narrower than ``least`` (index steps of at most it).
        if idx.size < least or idx[0] >= least:
            continue
        brk = np.flatnonzero(idx[1:] - idx[:-1] > least)
        n = int(brk[0]) + 1 if brk.size else idx.size
        if n < least:  # fewer than gap_min_mm of dark columns: speckle
            continue
        end = edge + step * (int(idx[n - 1]) + margin)
        lo, hi = sorted((edge, min(max(end, 0), w - 1)))
        gap[lo : hi + 1] = True
    return gap & usable


def _withhold_gap_shade(
    shadow_z: np.ndarray,
    csum: np.ndarray,
    usable: np.ndarray,
    gap: np.ndarray,
    above_off: int,
    scale: float,
    dy: float,
    p: ShadowPathParams,
    first: int = 0,
) -> None:
    """Take from ``shadow_z`` (in place), in the ``gap`` columns, the shade cast from above.

    ``first``: the imaged field's first row (:func:`field_rows`).

    Under a partial no-contact gap (:func:`_edge_gap`) a column is dark from the skin
    line down: a layer there has darker tissue under it than the tissue at its depth,
    as a bone would, but the shade was there above it already. For each row (a band
    centre) the column's mean from the near field down to the cover window's top
    (``above_off`` rows from the row) is compared with the median of that mean over the
    columns in full contact (usable, not gap): ``log(median / mean)``, the darkness of
    the column above the band relative to the typical column at those depths. Its
    positive part is the shade the band did not cast, and is not credited to it as
    shadow: it is taken from the shadow log-ratio, i.e. from the z-score in units of
    ``scale`` (the spread the z-score was computed with; the other columns' z-scores
    stay as they are). Only the gap's columns: elsewhere a column darker above the
    band is anatomy (measured: on the L14 recording the column over the bone is darker
    than typical; applied everywhere, L14 grey-shadow recall 1.00 -> 0.86).

    Why it generalises: both levels are means of the same frame at the same depths, a
    ratio (gain, TGC and probe cancel), and the correction is in the frame's own spread.
    """
    h, w = shadow_z.shape
    nf = first + mm_to_px(p.near_field_mm, dy, minimum=0)
    end = np.clip(np.arange(h) + above_off, nf, h)
    n = (end - nf).astype(np.float32)
    ok = n >= 1
    if not ok.any():
        return
    ref = usable & ~gap
    if not ref.any():
        return
    rows = np.flatnonzero(ok)
    # Column means over the rows above the band (cumulative sums: one subtraction);
    # every other reference column suffices for a median (as in tissue_level).
    above = csum[end[rows]]
    above -= csum[nf]
    above *= (1.0 / n[rows])[:, None]
    rc = np.flatnonzero(ref)
    rc = rc[::2] if rc.size >= 40 else rc
    gc = np.flatnonzero(gap)
    if gc.size == 0:
        return
    typical = sorted_row_medians(np.sort(above[:, rc], axis=1))
    above = above[:, gc]
    shade = np.log((typical[:, None] + _EPS) / (above + _EPS))
    np.maximum(shade, 0, out=shade)
    shade /= scale
    shade = shade.astype(shadow_z.dtype)
    # The rows are a run (``end`` rises with the row) and the gap's columns one or two
    # runs (from the field's edges): subtracted on slices, not by fancy index (the same
    # values).
    r = slice(int(rows[0]), int(rows[-1]) + 1) if rows[-1] - rows[0] == rows.size - 1 else rows
    cut = [0, *(np.flatnonzero(gc[1:] - gc[:-1] != 1) + 1).tolist(), gc.size]
    for a, b in zip(cut[:-1], cut[1:], strict=True):
        c = slice(int(gc[a]), int(gc[b - 1]) + 1)
        if isinstance(r, slice):
            shadow_z[r, c] -= shade[:, a:b]
        else:
            shadow_z[r[:, None], np.arange(c.start, c.stop)[None, :]] -= shade[:, a:b]


def shadow_gate(shadow_z: np.ndarray, zero: float, full: float, top: float = 1.0) -> np.ndarray:
    """The shadow gate: 0 at or under the shadow z-score ``zero``, rising linearly to 1
    at ``full`` and on at the same slope up to ``top`` (1: flat from ``full`` on; float32,
    as the score)."""
    lo, hi = np.float32(zero), np.float32(full)
    gate = shadow_z - lo
    gate /= hi - lo
    np.clip(gate, 0, np.float32(top), out=gate)
    return gate


def bone_evidence(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
) -> EvidenceMaps | None:
    """Evidence maps of one frame (see the module docstring); None if the image is too small."""
    p = params
    sx, sy = float(spacing[0]), float(spacing[1])
    work, colmean, fx, fy = working_image(image, spacing, p.work_mm)
    h, w = work.shape
    if w < 3 or h < 8:
        return None
    dx, dy = fx * sx, fy * sy
    imaged = work > np.float32(p.fov_grey / 255.0)  # over the scanner's black
    fov = field_of_view(work, dx, p, imaged)
    # A sector's black outside (curvilinear probe), or a black band over and under a
    # captured field, is neither dark tissue nor a probe edge off the skin nor a shadow:
    # left out of the levels, the contact and gap tests and the nulls.
    outside = outside_field(work, dx, dy, p, imaged)
    # Both references from one partition of the rows; again over the usable columns
    # only if contact removed some.
    pct = (p.tissue_percentile, p.shadow_percentile)
    tissue, t_shadow = tissue_level(work, fov, pct, dy, outside)
    usable = fov & _contact(work, tissue, dy, p, outside)
    if usable.any() and not np.array_equal(usable, fov):
        tissue, t_shadow = tissue_level(work, usable, pct, dy, outside)

    mid = mm_to_px(p.mid_mm, dy)
    up = mm_to_px(p.up_mm, dy)
    gap = mm_to_px(p.shadow_gap_mm, dy, minimum=0)
    near = mm_to_px(p.shadow_mm, dy)
    far = mm_to_px(p.far_shadow_mm, dy)
    cov_a = mm_to_px(p.cover_gap_mm, dy, minimum=0)
    cov_b = mm_to_px(p.cover_mm, dy)
    csum = column_cumsum(work)
    # Two references from the same statistics, robust to a bone (or the skin line)
    # spanning most of the width: for the shadow windows a high percentile (tissue
    # beside a shadow that covers up to 80 % of the columns), for the echo band the
    # lowest tissue level within +-1 mm of depth (a thin line spanning the width
    # raises its own rows' percentile, not its neighbours').
    tsum = np.zeros((h + 1, 1), dtype=np.float32)
    np.cumsum(t_shadow, out=tsum[1:, 0])
    t_echo = minimum_filter1d(tissue, 2 * mm_to_px(1.0, dy) + 1, mode="nearest")
    esum = np.zeros((h + 1, 1), dtype=np.float32)
    np.cumsum(t_echo, out=esum[1:, 0])
    j = np.arange(h)
    t0 = -(mid // 2)  # window offsets from the row: band top and bottom
    b0 = t0 + mid
    top = j + t0
    bot = j + b0
    m_mid = _window_mean(csum, t0, b0)
    m_up = _window_mean(csum, t0 - up, t0)
    # Pixels near the display's floor (band or the tissue above it far darker than the
    # tissue beside at their depth): left out of the z-scores' nulls (_null_pixels).
    dark = None
    if p.null_dark_fraction > 0:
        lvl = np.float32(p.null_dark_fraction) * t_shadow[:, None]
        dark = (m_mid < lvl) | (m_up < lvl)
    m_far = _window_mean(csum, b0 + gap, b0 + far)
    cov_top = top - cov_b
    m_cov = _window_mean(csum, t0 - cov_b, t0 - cov_a)
    # The references' windows are fixed offsets from each row too: _window_mean gives
    # column_window_mean's values (Testing/test_segmentation_speed_paths.py).
    t_far = _window_mean(tsum, b0 + gap, b0 + far)
    t_cov = _window_mean(esum, t0 - cov_b, t0 - cov_a)
    t_mid = t_echo[:, None]

    # In place where an operand is not needed again (the same operations in the same
    # dtype as the plain expressions: the same values, fewer temporaries).
    if p.phase_symmetry:
        log_e = phase_symmetry_depth(work, dy, p.phase_wavelengths_mm) * np.float32(m_mid > t_mid)
    else:
        den = np.maximum(m_up, t_mid, out=m_up)
        den += _EPS
        log_e = m_mid + _EPS
        log_e /= den
        np.log(log_e, out=log_e)
    m_far += _EPS
    log_s = np.divide(t_far + _EPS, m_far, out=m_far)
    np.log(log_s, out=log_s)
    if p.near_shadow:
        # The shadow starts right under the surface: the near window localises it (a
        # line mm above the bone has tissue, then the shadow, beneath it).
        m_sh = _window_mean(csum, b0 + gap, b0 + near)
        t_sh = _window_mean(tsum, b0 + gap, b0 + near)
        m_sh += _EPS
        np.divide(t_sh + _EPS, m_sh, out=m_sh)
        np.minimum(log_s, np.log(m_sh, out=m_sh), out=log_s)

    # Where the score may be: shadow windows mostly inside the image, a region above
    # inside the image and below the near field (gel, skin line, lens reverberation).
    # The field's rows, not the frame's: black bands over and under it are no image.
    first, end = field_rows(outside, h)
    inside = np.clip(end - (bot + gap), 0, near) / near
    nf = mm_to_px(p.near_field_mm, dy, minimum=0)
    rows_ok = (inside >= 0.5) & (top - up >= first) & (j >= first + nf)
    valid = rows_ok[:, None] & usable[None, :]
    if outside is not None:
        valid &= ~outside
    # Both z-scores' nulls over the tissue's pixels, with null_dark_fraction set not
    # the black ones (_null_pixels; by default every valid pixel).
    null = _null_pixels(valid, dark, p.null_min_share)
    # Both nulls on the sample _robust_scale takes (every third null pixel), its
    # positions found once.
    pick = np.flatnonzero(null)[::3]
    echo_z = _robust_z(log_e, valid, _scale_of(log_e.ravel().take(pick)))
    shadow_ms = _shadow_scale_of(log_s.ravel().take(pick), p.shadow_null_tolerance)
    shadow_z = _robust_z(log_s, valid, shadow_ms)
    gap_cols = _edge_gap(work, tissue, usable, dx, dy, p, outside)
    if gap_cols.any() and (ms := shadow_ms) is not None:
        # In the spread's units of the frame's shadow log-ratio as it is: the rule
        # changes the gap's columns only, not the scale every other column is read in.
        _withhold_gap_shade(shadow_z, csum, usable, gap_cols, t0 - cov_a, ms[1], dy, p, first)
    if p.confidence_weight > 0:
        # Optional (off by default; measured in .confidence): Karamalis' confidence
        # drop across the band, combined with the shadow z-score.
        drop = confidence_drop(work, dx, dy, usable, (t0 - up, t0), (b0 + gap, b0 + near), p)
        k = np.float32(p.confidence_weight)
        shadow_z *= np.float32(1.0) - k
        shadow_z += k * _robust_z(drop, valid)
    # Soft tissue above (see module docstring): the cover is judged against the tissue
    # at its own depth, over the part of its window inside the image; only where less
    # than ``cover_min_mm`` of it is (a line right under the image top) is there no
    # judgement.
    cov_rows = np.clip(top - cov_a, 0, h) - np.clip(cov_top, 0, h)
    judged = (cov_rows * dy >= p.cover_min_mm)[:, None]
    covered = (m_cov >= p.cover_ratio * t_cov) | ~judged
    # Shadow gate: 0 where the region below is brighter than the tissue at its depth
    # (tissue, not shadow, under a fascia), 1 where it is clearly darker, and up to
    # shadow_gate_max where it is far darker (a faint echo over a deep shadow).
    gate = shadow_gate(shadow_z, p.shadow_z_zero, p.shadow_z_full)
    if p.shadow_gate_max > 1:
        # Past 1 on the shadow held over +-shadow_gate_width_mm beside the pixel (its
        # lowest z there): a bone's shadow is as wide as the bone, a speckle window's
        # dark tail is not (one column's tail carried a speckle path through a frame
        # with no bone at the track's depth; see ShadowPathParams.shadow_gate_width_mm).
        half = mm_to_px(p.shadow_gate_width_mm, dx, minimum=0)
        wide = row_minimum_filter(shadow_z, 2 * half + 1)
        lo, hi = p.shadow_z_full, 2 * p.shadow_z_full - p.shadow_z_zero
        gate += shadow_gate(wide, lo, hi, p.shadow_gate_max - 1)
    score = np.maximum(echo_z, 0)
    score *= gate
    if p.phase_weight > 0:
        # Optional (off by default; measured in .phase): phase symmetry along depth as
        # an additional echo term.
        ps = phase_symmetry_depth(work, dy, p.phase_wavelengths_mm)
        score *= phase_factor(ps, valid, p.phase_weight)
    score *= valid & covered
    np.minimum(score, np.float32(p.max_z), out=score)
    sub = work[nf::2][:, usable][:, ::2]
    # Plain tissue against the level beside: the per-row median ratio of the rows
    # that are mostly tissue (the upper quartile of rows: shadow and bone fill the
    # others' medians with dark).
    base = np.log(sub + _EPS, out=sub)
    base -= np.log(t_shadow[nf::2, None] + _EPS)
    if base.size:  # rows sorted first: the same medians, faster (see tissue_level)
        base.sort(axis=1)
        base = sorted_percentile(np.sort(sorted_row_medians(base)), 75)
    else:
        base = 0.0
    return EvidenceMaps(
        work,
        colmean,
        fx,
        fy,
        dx,
        dy,
        usable,
        tissue,
        echo_z,
        shadow_z,
        score.astype(np.float32, copy=False),
        t_shadow,
        base,
        fov,
        first,
    )

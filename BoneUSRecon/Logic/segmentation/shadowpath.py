"""The default segmenter: shadow-aware bone score and an optimal path across columns.

Steps (all vectorised over rows; the only Python loops run over the ~100-300 columns
of the working image):

1. Average the frame into a working image of about ``work_mm`` pixels (speckle is
   averaged out, and the cost no longer depends on the recording's resolution).
2. Score every working pixel with the paper's contrast ``Dif = 2 M_mid - M_up -
   M_down`` (only its positive part) times a shadow gate ``1 - M_shadow / M_mid``
   (scaled so a shadow at ``gate_ratio`` of the echo counts for nothing). The gate is a ratio,
   so it does not depend on the gain or on attenuation with depth: a bone echo is
   bright *relative to what lies under it*, whereas tissue layers have tissue under
   them.
3. Dynamic programming over the columns finds the path maximising the summed score
   minus ``min_score`` per mm, minus a quadratic slope penalty, with a "no bone" state
   that costs ``switch_cost`` to enter or leave: columns without bone are not forced
   onto a contour.
4. Runs of bone columns separated by short gaps are merged; the best-scoring group
   with at least ``strong_mm`` of columns scoring ``strong_score`` is kept (one bone
   per sweep, as in the paper). This hysteresis lets weak echoes continue a contour
   (the oblique flanks of real bone) without letting them start one.
5. Sub-pixel depth: along each kept column, the Gaussian-smoothed full-resolution
   profile's peak near the path, by a parabolic fit through the three samples around
   the maximum.

A temporal prior from the previous accepted contour (a broad Gaussian in depth)
down-weights, but never forbids, echoes far from where the bone was.
"""

from __future__ import annotations

import numpy as np
from numpy.lib.stride_tricks import sliding_window_view
from scipy.ndimage import gaussian_filter1d, median_filter

from BoneUSRecon.Logic.segmentation.detection import Detection, empty_detection, sample_bilinear
from BoneUSRecon.Logic.segmentation.features import column_window_mean, mm_to_px
from BoneUSRecon.Logic.segmentation.params import ShadowPathParams

__all__ = ["shadowpath_frame", "bone_score", "field_of_view"]

_NULL = np.int8(-128)  # back-pointer meaning "came from the no-bone state"


def bone_score(work: np.ndarray, dy: float, params: ShadowPathParams) -> np.ndarray:
    """Shadow-gated regional contrast of a working image (values 0..1), shape (h, w).

    Parameters
    ----------
    work : ndarray, shape (h, w), float32 in [0, 1]
    dy : float
        Working pixel height in mm.
    """
    p = params
    h = work.shape[0]
    mid = mm_to_px(p.mid_mm, dy)
    up = mm_to_px(p.up_mm, dy)
    down = mm_to_px(p.down_mm, dy)
    shadow = mm_to_px(p.shadow_mm, dy)
    csum = np.zeros((h + 1, work.shape[1]), dtype=np.float32)
    np.cumsum(work, axis=0, out=csum[1:])
    j = np.arange(h)
    top = j - mid // 2
    bot = top + mid
    m_mid = column_window_mean(csum, top, bot)
    m_up = column_window_mean(csum, top - up, top)
    m_down = column_window_mean(csum, bot, bot + down)
    m_sh = column_window_mean(csum, bot, bot + shadow)
    dif = 2.0 * m_mid - m_up - m_down
    gate = 1.0 - (m_sh / (m_mid + 0.02)) / p.gate_ratio
    # Where most of the shadow region is outside the image there is no evidence of a
    # shadow: no score (otherwise the image's bottom rows would look like bone).
    inside = np.clip(h - bot, 0, shadow) / shadow
    # Likewise at the top: a band whose region above is cut by the image edge, or in
    # the near field (coupling gel, skin line, lens reverberation: no bone lies
    # there), is not scored; the dark gel above the bright skin line would look like
    # an echo with nothing above it.
    near = mm_to_px(p.near_field_mm, dy, minimum=0)
    ok = (inside >= 0.5) & (top - up >= 0) & (j >= near)
    gate *= ok[:, None]
    np.clip(gate, 0.0, 1.0, out=gate)
    np.maximum(dif, 0.0, out=dif)
    return dif * gate


def field_of_view(work: np.ndarray, dx: float, params: ShadowPathParams) -> np.ndarray:
    """Columns of a working image (values 0..1) inside the imaged field of view, shape (w,).

    A column is inside when more than ``fov_fraction`` of its pixels are brighter than
    ``fov_grey``; the inside is then shrunk by ``fov_margin_mm`` on each side of every
    outside run (the edge columns are averaged with the black margin).
    """
    p = params
    inside = (work > p.fov_grey / 255.0).mean(axis=0) > p.fov_fraction
    k = int(round(p.fov_margin_mm / dx))
    if k > 0 and not inside.all():
        # Erosion by k columns (binary, 1-D): a column stays inside only if all its
        # neighbours within k are inside; the image borders do not erode.
        pad = np.pad(inside, k, mode="edge")
        win = sliding_window_view(pad, 2 * k + 1)
        inside = win.all(axis=1)
    return inside


def _temporal_factor(
    h: int, w: int, fx: int, fy: int, dy: float, prior_px: np.ndarray, p: ShadowPathParams
) -> np.ndarray:
    """Multiplicative prior (h, w) around the previous contour's depth."""
    ci = (np.arange(w) + 0.5) * fx - 0.5
    order = np.argsort(prior_px[:, 0])
    pi, pj = prior_px[order, 0], prior_px[order, 1]
    # Outside the previous contour's lateral span, extend its end depths (np.interp).
    depth_rows = (np.interp(ci, pi, pj) + 0.5) / fy - 0.5
    # float32 throughout: this is a full working-image map, computed every frame.
    rows = np.arange(h, dtype=np.float32)[:, None]
    z = (rows - depth_rows.astype(np.float32)[None, :]) * np.float32(dy / p.temporal_sigma_mm)
    wgt = np.float32(p.temporal_weight)
    return (1.0 - wgt) + wgt * np.exp(np.float32(-0.5) * z * z)


def _optimal_path(gain: np.ndarray, shift_cost: np.ndarray, switch: float) -> np.ndarray:
    """Best path through ``gain`` (h, w) with a no-bone state; rows per column, -1 = no bone."""
    h, w = gain.shape
    n_shift = shift_cost.size
    d = n_shift // 2
    back = np.empty((w, h), dtype=np.int8)
    null_back = np.full(w, -1, dtype=np.intp)
    acc = gain[:, 0].astype(np.float64)
    null = 0.0
    padded = np.full(h + 2 * d, -np.inf)
    # One strided view of the padded buffer, made once: win[j, k] = padded[j + k],
    # i.e. the previous column's score at row j + k - d.
    win = sliding_window_view(padded, n_shift)
    cand = np.empty((h, n_shift))
    rows = np.arange(h)
    shift_code = (np.arange(n_shift) - d).astype(np.int8)
    for c in range(1, w):
        padded[d : d + h] = acc
        np.subtract(win, shift_cost, out=cand)
        k = cand.argmax(axis=1)
        best = cand[rows, k]
        from_null = null - switch
        use_null = from_null > best
        code = shift_code[k]
        code[use_null] = _NULL
        back[c] = code
        jb = int(acc.argmax())
        from_bone = acc[jb] - switch
        if from_bone > null:
            null, null_back[c] = from_bone, jb
        best[use_null] = from_null
        acc = best + gain[:, c]
    path = np.full(w, -1, dtype=np.intp)
    jb = int(acc.argmax())
    state = jb if acc[jb] > null else -1
    for c in range(w - 1, -1, -1):
        path[c] = state
        if c == 0:
            break
        if state >= 0:
            step = back[c, state]
            state = -1 if step == _NULL else state + int(step)
        else:
            state = int(null_back[c])
    return path


def _best_group(
    path: np.ndarray,
    gain: np.ndarray,
    score: np.ndarray,
    dx: float,
    dy: float,
    p: ShadowPathParams,
) -> np.ndarray:
    """Columns of the best group of bone runs (short gaps with small steps merged)."""
    cols = np.flatnonzero(path >= 0)
    if cols.size == 0:
        return cols
    breaks = np.flatnonzero(np.diff(cols) > 1)
    starts = np.r_[0, breaks + 1]
    ends = np.r_[breaks, cols.size - 1]
    groups: list[list[int]] = [[0]]
    for r in range(1, starts.size):
        a, b = cols[ends[r - 1]], cols[starts[r]]
        gap_mm = (b - a - 1) * dx
        step_mm = abs(path[b] - path[a]) * dy
        if gap_mm <= p.merge_gap_mm and step_mm <= p.merge_step_mm:
            groups[-1].append(r)
        else:
            groups.append([r])
    best, best_score = cols[:0], -np.inf
    for g in groups:
        sel = np.concatenate([cols[starts[r] : ends[r] + 1] for r in g])
        # Hysteresis: weak echoes may continue a contour (the oblique flanks of real
        # bone), but a contour needs some strong evidence to exist at all.
        if (score[path[sel], sel] >= p.strong_score).sum() * dx < p.strong_mm:
            continue
        s = float(gain[path[sel], sel].sum())
        if s > best_score:
            best, best_score = sel, s
    return best


def shadowpath_frame(
    image: np.ndarray,
    spacing: tuple[float, float],
    params: ShadowPathParams = ShadowPathParams(),  # noqa: B008 (frozen dataclass)
    prior_px: np.ndarray | None = None,
) -> Detection:
    """Find the bone contour of one frame.

    Parameters
    ----------
    image : ndarray of uint8, shape (H, W)
    spacing : (sx, sy)
        mm per column and per row.
    params : ShadowPathParams
    prior_px : ndarray, shape (K, 2), optional
        Previous accepted contour ``(i, j)`` for the temporal prior.

    Returns
    -------
    Detection
        One point per working column of the kept bone, ``(i, j)`` sub-pixel.
    """
    p = params
    sx, sy = float(spacing[0]), float(spacing[1])
    hh_full, ww_full = image.shape
    fx = mm_to_px(p.work_mm, sx)
    fy = mm_to_px(p.work_mm, sy)
    w = ww_full // fx
    h = hh_full // fy
    if w < 3 or h < 8:
        return empty_detection(reason="image too small")
    dx, dy = fx * sx, fy * sy
    # Column-averaged image at full depth resolution: reused for the sub-pixel step.
    # (Strided slice sums: several times faster than reshape(...).mean on uint8.)
    img = np.asarray(image)
    colmean = img[:, 0 : w * fx : fx].astype(np.float32)
    for q in range(1, fx):
        colmean += img[:, q : w * fx : fx]
    colmean *= np.float32(1.0 / (255.0 * fx))
    work = colmean[0 : h * fy : fy].copy()
    for q in range(1, fy):
        work += colmean[q : h * fy : fy]
    work *= np.float32(1.0 / fy)
    score = bone_score(work, dy, p)
    # Scan-converted recordings (the real L14 sweep) have black margins beside the
    # imaged sector or rectangle: no bone can be found there, nor right at its edge.
    outside = ~field_of_view(work, dx, p)
    if outside.all():
        return empty_detection(reason="no imaged field of view")
    score[:, outside] = 0.0
    if prior_px is not None and len(prior_px) >= 2 and p.temporal_weight > 0:
        score = score * _temporal_factor(h, w, fx, fy, dy, np.asarray(prior_px), p)
    gain = (score - p.min_score) * dx
    n_shift = max(1, int(np.ceil(p.max_slope * dx / dy)))
    steps = np.arange(-n_shift, n_shift + 1)
    shift_cost = p.slope_penalty * (steps * dy / dx) ** 2 * dx
    # Only the box holding positive gains matters: outside its columns "no bone" is
    # optimal, and rows beyond it (plus a margin for the slope) cannot help a path.
    # On typical frames this cuts the dynamic programme by 3-5x.
    pos = gain > 0
    if not pos.any():
        return empty_detection(reason="no bone found")
    rr = np.flatnonzero(pos.any(axis=1))
    cc = np.flatnonzero(pos.any(axis=0))
    r0, r1 = max(0, rr[0] - 2 * n_shift), min(h, rr[-1] + 1 + 2 * n_shift)
    c0, c1 = cc[0], cc[-1] + 1
    path = np.full(w, -1, dtype=np.intp)
    sub = _optimal_path(gain[r0:r1, c0:c1], shift_cost, p.switch_cost)
    path[c0:c1] = np.where(sub >= 0, sub + r0, -1)
    cols = _best_group(path, gain, score, dx, dy, p)
    if cols.size == 0:
        return empty_detection(reason="no bone found")

    # Sub-pixel refinement on the full-resolution depth profile of each kept column.
    centre = (path[cols] + 0.5) * fy - 0.5
    half = mm_to_px(p.refine_mm, sy)
    sig = p.refine_sigma_mm / sy
    pad = int(np.ceil(3 * sig)) if sig >= 0.5 else 0
    off = np.arange(-half - pad - 1, half + pad + 2)
    rows = np.clip(np.rint(centre).astype(np.intp)[:, None] + off[None, :], 0, hh_full - 1)
    prof = colmean[rows, cols[:, None]]
    if pad:
        prof = gaussian_filter1d(prof, sig, axis=1, mode="nearest")
    core = slice(pad + 1, pad + 2 * half + 2)
    k = prof[:, core].argmax(axis=1) + pad + 1
    r = np.arange(cols.size)
    y0, y1, y2 = prof[r, k - 1], prof[r, k], prof[r, k + 1]
    denom = y0 - 2 * y1 + y2
    frac = np.where(denom < 0, 0.5 * (y0 - y2) / np.where(denom < 0, denom, -1.0), 0.0)
    j = rows[r, k] + np.clip(frac, -0.5, 0.5) + p.surface_offset_mm / sy
    # Lateral median over ~0.6 mm: removes single-column speckle jumps.
    size = max(1, int(round(0.6 / dx)) | 1)
    if size > 1 and j.size >= size:
        j = median_filter(j, size=size, mode="nearest")
    i = (cols + 0.5) * fx - 0.5
    pts = np.column_stack([i, j])
    intensity = sample_bilinear(image, pts)
    return Detection(pts, intensity, {"work_px": (fx, fy)})

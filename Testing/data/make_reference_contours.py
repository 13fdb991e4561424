"""Make the reference bone contours of the two shared PLUS recordings (see README.md).

A careful path per frame, then corrections by hand after looking at every overlay:

1. Bone-likeness per pixel: the grey (Gaussian, 1 px) minus the mean grey 0.5-4 mm
   below it (a bright line over a darker band), in a window of columns and rows set
   by hand per recording (where the bone is, from looking at the frames).
2. The best path across those columns by dynamic programming (at most ``max_step``
   rows per column, a small penalty per row of step): one row per column.
3. The ends are trimmed where the smoothed bone-likeness falls below a share of the
   path's median (the flanks fade out); per-frame hand edits (``EDITS``) then set
   the column range or pin rows where the path left the bone.

Run: ``python Testing/data/make_reference_contours.py [--overlays DIR]``; writes
``Testing/data/<name>_reference.csv`` (frame, i, j: pixel column and row, every
``STEP`` columns) and, with ``--overlays``, one PNG per frame to look at.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.ndimage import binary_closing, gaussian_filter, label, uniform_filter1d

HERE = Path(__file__).resolve().parent
PLUS = HERE.parents[2] / "shared" / "data" / "plus"

#: Per recording: file, calibration, column window, row window, max step (rows per
#: column), end-trim share; chosen by looking at the frames.
RECORDINGS = {
    "L14": dict(
        mha="BoneUltrasound_L14.igs.mha",
        xml="BoneUltrasound_L14_config.xml",
        cols=(178, 640),
        rows=(240, 560),
        max_step=4,
        trim=0.2,
        unimodal=True,
        score="ridge",
    ),
    "SpinePhantom": dict(
        mha="SpinePhantomFreehand.igs.mha",
        xml="PlusDeviceSet_SpinePhantomFreehandReconstructionOnly.xml",
        cols=(190, 628),
        rows=(80, 480),
        max_step=4,
        trim=0.35,
        unimodal=False,
        score="shadow",
        shadowed=0.5,
    ),
}

#: Hand edits after looking at the overlays: {recording: {frame: edit}}; ``"cols": (c0,
#: c1)`` keeps only those columns of the path, ``"through": [(i, j), ...]`` makes it pass
#: within 3 rows of those pixels (read off a zoomed overlay with a pixel ruler).
EDITS: dict[str, dict[int, dict]] = {
    "L14": {
        # The right flank is fainter here: the path left it at the shoulder.
        2: {"through": [(469, 335), (494, 385), (506, 410)], "cols": (0, 519)},
        3: {"through": [(472, 335), (503, 385), (516, 410)], "cols": (0, 525)},
        8: {"through": [(462, 325), (492, 375), (512, 410)], "cols": (0, 516)},
        9: {"through": [(468, 325), (498, 375), (518, 410)], "cols": (0, 520)},
        # The left flank fades towards the image edge; the right side of 19-20 has a
        # fascia leaving the shoulder sideways, which the path followed.
        17: {"through": [(237, 315), (215, 340), (197, 365)], "cols": (0, 585)},
        18: {"through": [(240, 315), (219, 340), (200, 365)], "cols": (0, 560)},
        19: {
            "through": [
                (240, 315),
                (219, 340),
                (200, 365),
                (525, 335),
                (547, 360),
                (566, 385),
                (587, 410),
            ],
            "cols": (0, 590),
        },
        20: {"through": [(544, 335), (559, 360), (581, 385), (600, 410)], "cols": (0, 602)},
    },
    "SpinePhantom": {
        # A bright, thick lamina with its shadow below: its top edge, set by hand (the
        # shadow test looks too close below a 3-4 mm thick echo).
        4: {"through": [(370, 243), (420, 238), (460, 243)], "cols": (345, 480), "hand": True},
        5: {"through": [(385, 245), (430, 240), (470, 245)], "cols": (360, 490), "hand": True},
        6: {"through": [(390, 250), (430, 240), (465, 238)], "cols": (365, 480), "hand": True},
        7: {"through": [(380, 262), (430, 245), (480, 238)], "cols": (360, 505), "hand": True},
        # No reference: a ring-shaped echo (3) or two laminae beside a faint process (9-11)
        # that I could not trace with confidence.
        3: {"skip": True},
        9: {"skip": True},
        10: {"skip": True},
        11: {"skip": True},
    },
}

#: Columns between stored points.
STEP = 4


def _bone_score(img: np.ndarray, sp: float, kind: str = "shadow") -> np.ndarray:
    """``shadow``: bright over dark, the grey (Gaussian, 1 px) minus the mean grey 0.5-4
    mm below; ``ridge``: a bright ridge, the grey minus its 2 mm neighbourhood's mean
    (follows steep flanks, whose shadow is beside rather than below them)."""
    g = gaussian_filter(img.astype(np.float32), 1.0)
    if kind == "ridge":
        from scipy.ndimage import uniform_filter

        return g - uniform_filter(g, max(3, int(round(2.0 / sp))))
    n0, n1 = int(round(0.5 / sp)), int(round(4.0 / sp))
    box = uniform_filter1d(g, n1 - n0 + 1, axis=0, mode="nearest")
    below = np.empty_like(box)
    shift = n0 + (n1 - n0 + 1) // 2
    below[:-shift] = box[shift:]
    below[-shift:] = box[-1:]
    return g - below


def _dp(score: np.ndarray, steps: np.ndarray, start: int | None = None) -> np.ndarray:
    """Best path (one row per column) through ``score`` with the allowed row ``steps``
    per column (penalty 0.5 per row), optionally starting at row ``start``."""
    h, w = score.shape
    acc = score[:, 0].copy()
    if start is not None:
        acc[:] = -np.inf
        acc[start] = score[start, 0]
    back = np.zeros((h, w), np.int32)
    penalty = 0.5 * np.abs(steps)
    for c in range(1, w):
        cand = np.full((steps.size, h), -np.inf, np.float32)
        for q, d in enumerate(steps):
            lo, hi = max(0, -d), min(h, h - d)
            cand[q, lo:hi] = acc[lo + d : hi + d] - penalty[q]
        best = cand.argmax(0)
        back[:, c] = np.arange(h) + steps[best]
        acc = cand[best, np.arange(h)] + score[:, c]
    path = np.empty(w, np.int32)
    path[-1] = int(acc.argmax())
    for c in range(w - 1, 0, -1):
        path[c - 1] = back[path[c], c]
    return path


def bone_path(
    img: np.ndarray,
    sp: float,
    cols: tuple[int, int],
    rows: tuple[int, int],
    max_step: int,
    unimodal: bool = False,
    through: list[tuple[int, int]] | None = None,
    kind: str = "shadow",
) -> tuple[np.ndarray, np.ndarray]:
    """Rows of the best bright-over-dark path across ``cols`` (one per column), by DP,
    and the bone-likeness along it. ``unimodal``: an arc, rising to its brightest point
    then falling (a round bone: the path cannot climb onto a fascia beside it)."""
    score = _bone_score(img, sp, kind)[rows[0] : rows[1], cols[0] : cols[1]]
    for i, j in through or []:
        pinned = score[:, i - cols[0]].copy()
        score[:, i - cols[0]] = -1e4
        score[j - rows[0] - 3 : j - rows[0] + 4, i - cols[0]] = pinned[
            j - rows[0] - 3 : j - rows[0] + 4
        ]
    steps = np.arange(-max_step, max_step + 1)
    path = _dp(score, steps)
    if unimodal:
        # The apex: the strongest bright-over-dark stretch (1.5 mm wide) in the window;
        # from there the path may only go down (a step d means the previous column's
        # row is d rows lower: d <= 0 going away from the apex).
        # (found on the bright-over-dark score: a fascia is a ridge too, but has no shadow)
        bone = _bone_score(img, sp)[rows[0] : rows[1], cols[0] : cols[1]]
        sm = uniform_filter1d(bone, max(3, int(round(1.5 / sp))), axis=1, mode="nearest")
        r0, a = np.unravel_index(int(sm.argmax()), sm.shape)
        right = _dp(score[:, a:], steps[steps <= 0], start=int(r0))
        left = _dp(score[:, : a + 1][:, ::-1], steps[steps <= 0], start=int(r0))[::-1]
        path = np.r_[left[:-1], right]
        s = score[path, np.arange(path.size)]
        # The foot of each flank: going out from the apex, once the path has been
        # steeper than 45 degrees, it ends where it turns flatter than 20 degrees
        # over 1 mm (the tissue line at the foot of the bone, not the bone). Not with
        # hand-set points: there the hand sets the ends (``cols``).
        n = max(2, int(round(1.0 / sp)))
        slope = np.abs(path[n:] - path[:-n]) / n  # rise per column over 1 mm, at column c + n/2
        keep = np.ones(path.size, bool)
        for side in (1, -1) if not through else ():
            idx = np.arange(a, path.size - n) if side > 0 else np.arange(a - n, -1, -1)
            steep = False
            for c in idx:
                steep |= slope[c] > 1.0
                if steep and slope[c] < np.tan(np.radians(20)):
                    cut = c + n // 2
                    if side > 0:
                        keep[cut + 1 :] = False
                    else:
                        keep[:cut] = False
                    break
        return path + rows[0], np.where(keep, s, -np.inf)
    return path + rows[0], score[path, np.arange(path.size)]


def reference(name: str) -> tuple[object, dict[int, np.ndarray]]:
    """The recording (a Sweep) and its reference contour per frame ``(K, 2)`` pixels."""
    from BoneUSRecon.Logic.sequence_io import read_sweep

    cfg = RECORDINGS[name]
    sw = read_sweep(PLUS / cfg["mha"], calibration=PLUS / cfg["xml"])
    sp = float(np.mean(sw.spacing_mm))
    out = {}
    for k in range(sw.n_frames):
        edit = EDITS[name].get(k, {})
        j, s = bone_path(
            np.asarray(sw.frames[k]),
            sp,
            cfg["cols"],
            cfg["rows"],
            cfg["max_step"],
            cfg["unimodal"],
            edit.get("through"),
            cfg["score"],
        )
        i = np.arange(cfg["cols"][0], cfg["cols"][1])
        valid = np.isfinite(s)
        sm = uniform_filter1d(np.where(valid, s, 0.0), max(3, int(round(1.0 / sp))), mode="nearest")
        good = valid & (sm > 0)
        on = (
            np.flatnonzero(valid & (sm >= cfg["trim"] * np.median(sm[good])))
            if good.any()
            else np.arange(0)
        )
        keep = np.zeros(i.size, bool)
        if on.size:
            keep[on[0] : on[-1] + 1] = True
        if edit.get("skip"):
            continue
        if cfg.get("shadowed") and not edit.get("hand"):
            # Only where a shadow lies beneath: the mean grey 1-8 mm below the path
            # under ``shadowed`` of the frame's median grey at those depths; the
            # longest such run (gaps up to 1 mm bridged).
            img = np.asarray(sw.frames[k], np.float32)
            med = np.median(img[:, cfg["cols"][0] : cfg["cols"][1]], axis=1)
            n0, n1 = int(round(1.0 / sp)), int(round(8.0 / sp))
            dark = np.zeros(i.size, bool)
            for q, (c, r) in enumerate(zip(i, j, strict=True)):
                rr = np.arange(r + n0, min(r + n1, img.shape[0]))
                dark[q] = rr.size > 0 and img[rr, c].mean() < cfg["shadowed"] * max(
                    np.mean(med[rr]), 1.0
                )
            dark = binary_closing(dark, np.ones(int(round(1.0 / sp)) | 1, bool))
            lab, nlab = label(dark)
            if nlab:
                keep &= lab == 1 + int(np.argmax(np.bincount(lab.ravel())[1:]))
            else:
                keep[:] = False
        if "cols" in edit:
            keep &= (i >= edit["cols"][0]) & (i <= edit["cols"][1])
        ii, jj = i[keep], j[keep]
        sel = np.r_[np.arange(0, ii.size - 1, STEP), ii.size - 1] if ii.size else np.arange(0)
        out[k] = np.column_stack([ii[sel], jj[sel]]).astype(float)
    return sw, out


def write_csv(path: Path, contours: dict[int, np.ndarray]) -> None:
    rows = ["frame,i,j"] + [f"{k},{int(i)},{int(j)}" for k, c in contours.items() for i, j in c]
    path.write_text("\n".join(rows) + "\n", encoding="utf-8")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--overlays", type=Path)
    ap.add_argument("--only", choices=list(RECORDINGS))
    args = ap.parse_args()
    for name in RECORDINGS:
        if args.only and name != args.only:
            continue
        sw, ref = reference(name)
        write_csv(HERE / f"{name}_reference.csv", ref)
        if args.overlays:
            from PIL import Image

            args.overlays.mkdir(parents=True, exist_ok=True)
            for k, c in ref.items():
                img = np.stack([np.asarray(sw.frames[k])] * 3, -1)
                ii = np.arange(c[0, 0], c[-1, 0] + 1).astype(int) if len(c) else np.arange(0)
                jj = np.rint(np.interp(ii, c[:, 0], c[:, 1])).astype(int) if len(c) else ii
                img[np.clip(jj + 6, 0, img.shape[0] - 1), ii] = (255, 0, 0)
                img[np.clip(jj - 6, 0, img.shape[0] - 1), ii] = (0, 255, 0)
                Image.fromarray(img).save(args.overlays / f"{name}_{k:02d}.png")


if __name__ == "__main__":
    main()

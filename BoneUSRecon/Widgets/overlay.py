"""PNG overlays of segmented contours on B-mode frames (Pillow only, no VTK rendering).

Used by ``bone-us-recon segment --overlay`` and by the report for its contour figures.
Accepted contours are drawn in green with their points; rejected frames get their
contour in red (if any) and the rejection reason written on a banner.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

import numpy as np
from PIL import Image, ImageDraw

from BoneUSRecon.Logic.fileio import atomic_path

__all__ = ["overlay_image", "write_overlay", "write_overlays"]

GREEN = (40, 230, 60)
RED = (255, 50, 40)
YELLOW = (255, 220, 0)


def overlay_image(
    frame: np.ndarray,
    points_px: np.ndarray | None = None,
    *,
    accepted: bool = True,
    label: str = "",
    truth_px: np.ndarray | None = None,
    scale: int = 1,
) -> Image.Image:
    """One frame as an RGB image with its contour drawn.

    Parameters
    ----------
    frame : ndarray of uint8, shape (H, W)
    points_px : ndarray, shape (K, 2), optional
        Contour ``(i, j)`` in pixels.
    accepted : bool
        Green contour when True, red when the frame was rejected.
    label : str
        Text for the top banner (e.g. "frame 12" or the rejection reason).
    truth_px : ndarray, shape (M, 2), optional
        A reference contour drawn in yellow (e.g. the simulator's truth).
    scale : int
        Integer up-sampling for small frames (nearest neighbour).
    """
    img = Image.fromarray(np.ascontiguousarray(frame, dtype=np.uint8), mode="L").convert("RGB")
    if scale > 1:
        img = img.resize((img.width * scale, img.height * scale), Image.Resampling.NEAREST)
    draw = ImageDraw.Draw(img)
    # Lines about 1/300 of the image wide, so they stay visible on large frames.
    lw = max(scale, round(img.width / 300))

    def xy(p: np.ndarray) -> list[tuple[float, float]]:
        q = (np.asarray(p, float) + 0.5) * scale - 0.5
        return [(float(a), float(b)) for a, b in q]

    if truth_px is not None and len(truth_px) > 1:
        draw.line(xy(truth_px), fill=YELLOW, width=max(1, lw // 2))
    if points_px is not None and len(points_px):
        colour = GREEN if accepted else RED
        pts = xy(points_px)
        if len(pts) > 1:
            # Break the line where the contour has a gap (no bone between).
            gaps = np.flatnonzero(np.diff(np.asarray(points_px)[:, 0]) > 3 * _step(points_px))
            for seg in np.split(np.arange(len(pts)), gaps + 1):
                if seg.size > 1:
                    draw.line([pts[s] for s in seg], fill=colour, width=lw)
        r = max(1.0, lw * 0.75)
        for x, y in pts[:: max(1, len(pts) // 60)]:
            draw.ellipse((x - r, y - r, x + r, y + r), outline=colour)
    if label:
        colour = (255, 255, 255) if accepted else RED
        draw.rectangle((0, 0, img.width, 12), fill=(0, 0, 0))
        draw.text((2, 0), label, fill=colour)
    return img


def _step(points_px: np.ndarray) -> float:
    d = np.diff(np.asarray(points_px)[:, 0])
    return float(np.median(d)) if d.size else 1.0


def write_overlay(image: Image.Image, path: str | os.PathLike[str]) -> Path:
    """Save ``image`` as PNG atomically."""
    with atomic_path(path) as tmp:
        image.save(tmp, format="PNG")
    return Path(path)


def write_overlays(
    frames: np.ndarray,
    contours: Iterable,
    outdir: str | os.PathLike[str],
    *,
    every: int = 1,
    truth_px: list[np.ndarray] | None = None,
) -> list[Path]:
    """Write ``frame_NNNN.png`` for every ``every``-th contour (rejected ones always).

    Parameters
    ----------
    frames : ndarray, shape (N, H, W)
        The sweep's frames.
    contours : iterable of FrameContour
    outdir : path-like
        Created if missing.
    every : int
        Write one accepted frame in ``every`` (rejected frames are always written).
    truth_px : list of ndarray, optional
        Per frame (indexed by frame number) reference contours drawn in yellow.
    """
    out = Path(outdir)
    out.mkdir(parents=True, exist_ok=True)
    written = []
    for n, c in enumerate(contours):
        if c.accepted and n % max(1, every):
            continue
        label = f"frame {c.frame}  conf {c.confidence:.2f}"
        if not c.accepted:
            label = f"frame {c.frame} REJECTED: {c.reason}"
        frame = np.asarray(frames[c.frame])
        scale = 2 if frame.shape[1] < 400 else 1
        truth = truth_px[c.frame] if truth_px is not None else None
        img = overlay_image(
            frame, c.points_px, accepted=c.accepted, label=label, truth_px=truth, scale=scale
        )
        written.append(write_overlay(img, out / f"frame_{c.frame:04d}.png"))
    return written

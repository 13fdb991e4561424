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
from PIL import Image, ImageDraw, ImageFont

from BoneUSRecon.Logic.fileio import atomic_path

__all__ = ["overlay_image", "write_overlay", "write_overlays", "label_font_size", "label_lines"]

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
        size = label_font_size(img.width)
        font = _font(size)
        line_h = size + 3
        # The banner never covers more than a third of the image (tiny frames).
        max_lines = max(1, min(3, (img.height // 3) // line_h))
        lines = label_lines(label, img.width - 2 * _PAD, size, max_lines=max_lines)
        draw.rectangle((0, 0, img.width, 4 + line_h * len(lines)), fill=(0, 0, 0))
        for k, line in enumerate(lines):
            draw.text((_PAD, 2 + k * line_h), line, fill=colour, font=font)
    return img


_PAD = 4  # pixels between the banner's text and the image edge


def label_font_size(width: int) -> int:
    """Banner font size (pixels) for an image ``width`` pixels wide.

    A 26th of the width: the report shows frames about 320 pixels wide whatever
    their size, so an 820-pixel frame's label (31 px) still reads at about 12 px
    there; never below 12 px, so small frames' labels stay legible at full size.
    """
    return max(12, round(width / 26))


def _font(size: int) -> ImageFont.FreeTypeFont | ImageFont.ImageFont:
    # Pillow >= 10.1 ships a scalable default font; older ones only the 11 px bitmap.
    try:
        return ImageFont.load_default(size=size)
    except TypeError:  # pragma: no cover - old Pillow
        return ImageFont.load_default()


def label_lines(label: str, width: int, size: int, max_lines: int = 3) -> list[str]:
    """``label`` broken into lines no wider than ``width`` pixels in the banner font.

    Long rejection reasons wrap instead of running off a small frame; past
    ``max_lines`` the last line ends with an ellipsis (the full reason is in the
    summary and the report's caption).
    """
    font = _font(size)
    words = label.split()
    lines: list[str] = []
    for word in words:
        trial = f"{lines[-1]} {word}" if lines else word
        if lines and font.getlength(trial) <= width:
            lines[-1] = trial
        else:
            lines.append(word)
    if len(lines) > max_lines:
        last = " ".join(lines[max_lines - 1 :])
        while last and font.getlength(last + "...") > width:
            last = last[:-1]
        lines = lines[: max_lines - 1] + [last.rstrip() + "..."]
    # A single word wider than the image (rare): cut it to fit.
    out = []
    for line in lines:
        while len(line) > 1 and font.getlength(line) > width:
            line = line[:-1]
        out.append(line)
    return out


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

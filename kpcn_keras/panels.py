"""The side-by-side PNGs of denoised frames: tonemapped panels in a row, each captioned.

:func:`panels_png` is ``kpcn denoise --png``'s (Pillow, full resolution, a block of rows tonemapped at a time);
:func:`side_by_side_png` is the reports' and figures' (matplotlib). Both tonemap with ``prep.colour.tonemap``.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np

from prep.files import atomic_path, pyplot, save_png

PNG_ROWS = 256  # rows of a panel tonemapped at a time


def side_by_side_png(path: str | Path, panels: list[tuple[str, np.ndarray]], title: str = "") -> Path:
    """Tonemapped panels in a row with their captions (``prep.colour.tonemap``), drawn by matplotlib (the
    report figures)."""
    plt = pyplot()

    from prep.colour import tonemap

    h, w = panels[0][1].shape[:2]
    scale = 4.0 / max(h, w)
    fig, axes = plt.subplots(1, len(panels), figsize=(len(panels) * w * scale, h * scale + 0.8), squeeze=False)
    for ax, (caption, image) in zip(axes[0], panels):
        ax.imshow(tonemap(image), interpolation="nearest")
        ax.set_title(caption, fontsize=9)
        ax.axis("off")
    if title:
        fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    return save_png(fig, path)


def panels_png(path: str | Path, panels: list[tuple[str, np.ndarray]], title: str = "") -> Path:
    """The side-by-side PNG of ``kpcn denoise``: tonemapped panels at full resolution in a row, each captioned
    above, the title on top; written atomically. Pillow only: matplotlib's figure, layout and resampling
    cost about 120 ms a frame at 256x256 for the same picture."""
    from PIL import Image, ImageDraw

    from prep.colour import tonemap

    h, w = panels[0][1].shape[:2]
    gap, line = 4, 14
    top = line * (2 if title else 1)
    canvas = np.full((top + h, len(panels) * (w + gap) - gap, 3), 255, np.uint8)
    for i, (_, image) in enumerate(panels):
        x = i * (w + gap)
        for y in range(0, h, PNG_ROWS):  # the float64 tonemap of a whole frame is 24 bytes a pixel at a time
            rows = slice(y, y + PNG_ROWS)
            canvas[top + y : top + y + PNG_ROWS, x : x + w] = np.round(tonemap(image[rows]) * 255.0).astype(np.uint8)
    picture = Image.fromarray(canvas)
    draw = ImageDraw.Draw(picture)
    if title:
        draw.text((2, 1), title, fill=(0, 0, 0))
    for i, (caption, _) in enumerate(panels):
        draw.text((i * (w + gap) + 2, top - line + 1), caption, fill=(0, 0, 0))
    path = Path(path)
    with atomic_path(path) as tmp:
        picture.save(tmp, format="PNG", compress_level=1)  # speed over a few percent of size
    return path

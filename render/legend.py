"""Class legends and captions drawn onto rendered images (PIL).

A legend lists, in label order, a colour swatch and the name of every class that appears in the image; the
empty class never appears. It sits in the image's bottom-left corner on a light panel, so that it reads on
any background.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np

from fruxel.classes import ClassTable

from .compat import default_font

SWATCH = 12
"""Side of a colour swatch, pixels (before scaling with the image size)."""
PAD = 4
"""Gap between swatch, text and panel edge, pixels (before scaling)."""


def present_labels(*label_arrays: Any) -> list[int]:
    """Sorted non-zero labels that occur in any of the given integer arrays (any shapes)."""
    seen: set[int] = set()
    for a in label_arrays:
        arr = np.asarray(a)
        if arr.size:
            seen.update(int(v) for v in np.unique(arr) if v != 0)
    return sorted(seen)


def _scale(image_height: int) -> float:
    # Legends stay legible on thumbnails and do not dwarf large renders: 1x at 480 rows, within [0.75, 2].
    return float(min(2.0, max(0.75, image_height / 480.0)))


def draw_legend(image: Any, classes: ClassTable, labels: Iterable[int]) -> np.ndarray:
    """A copy of ``image`` with a legend of ``labels`` in its bottom-left corner.

    Args:
        image: ``(h, w, 3)`` uint8 RGB.
        classes: names and colours of the labels.
        labels: the classes to list (non-zero labels below ``len(classes)``); none gives the image unchanged.

    Returns:
        ``(h, w, 3)`` uint8 RGB.
    """
    from PIL import Image, ImageDraw

    labels = [int(c) for c in labels if 0 < int(c) < len(classes)]
    img = Image.fromarray(np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[..., :3]))
    if not labels:
        return np.asarray(img).copy()
    s = _scale(img.height)
    sw, pad = max(6, round(SWATCH * s)), max(2, round(PAD * s))
    font = default_font(max(8, round(11 * s)))
    draw = ImageDraw.Draw(img, "RGBA")
    names = [classes.names[c] for c in labels]
    text_w = max(draw.textbbox((0, 0), n, font=font)[2] for n in names)
    row = sw + pad
    panel_w = pad + sw + pad + text_w + pad
    panel_h = pad + row * len(labels)
    x0, y0 = pad, img.height - pad - panel_h
    draw.rectangle([x0, y0, x0 + panel_w, y0 + panel_h], fill=(255, 255, 255, 200), outline=(90, 90, 90, 255))
    for r, (c, name) in enumerate(zip(labels, names, strict=True)):
        y = y0 + pad + r * row
        draw.rectangle([x0 + pad, y, x0 + pad + sw - 1, y + sw - 1], fill=tuple(classes.colours[c]) + (255,),
                       outline=(60, 60, 60, 255))
        draw.text((x0 + 2 * pad + sw, y + sw / 2), name, fill=(20, 20, 20, 255), font=font, anchor="lm")
    return np.asarray(img).copy()


def draw_caption(image: Any, text: str) -> np.ndarray:
    """A copy of ``image`` (``(h, w, 3)`` uint8 RGB) with one line of ``text`` in its top-left corner."""
    from PIL import Image, ImageDraw

    img = Image.fromarray(np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[..., :3]))
    s = _scale(img.height)
    pad = max(2, round(PAD * s))
    font = default_font(max(8, round(11 * s)))
    draw = ImageDraw.Draw(img, "RGBA")
    box = draw.textbbox((2 * pad, 2 * pad), text, font=font)
    draw.rectangle([box[0] - pad, box[1] - pad, box[2] + pad, box[3] + pad], fill=(255, 255, 255, 200))
    draw.text((2 * pad, 2 * pad), text, fill=(20, 20, 20, 255), font=font)
    return np.asarray(img).copy()

"""Class legends and captions drawn onto rendered images (PIL).

A legend lists, in label order, a colour swatch and the name of every class that appears in the image; the
empty class never appears. It sits on a light panel, so that it reads on any background, in the corner where it
hides the least of the picture (bottom-left when that is free). Text is DejaVu Sans
(:func:`fruxel.render.compat.default_font`).
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from fruxel.classes import ClassTable

from .compat import default_font

SWATCH = 12
"""Side of a colour swatch, pixels (before scaling with the image size)."""
PAD = 4
"""Gap between swatch, text and panel edge, pixels (before scaling)."""


_CHUNK = 1 << 22
"""Labels counted at once by :func:`present_labels` (bounds its temporary memory on huge images)."""


def present_labels(*label_arrays: Any) -> list[int]:
    """Sorted non-zero labels that occur in any of the given integer arrays (any shapes, labels >= 0).

    Counted in chunks (linear time, bounded memory), since a ray cast of a large image has 10^8 labels.
    """
    seen: set[int] = set()
    for a in label_arrays:
        flat = np.asarray(a).reshape(-1)
        for start in range(0, flat.size, _CHUNK):
            counts = np.bincount(flat[start:start + _CHUNK].astype(np.intp, copy=False))
            seen.update(int(v) for v in np.flatnonzero(counts) if v != 0)
    return sorted(seen)


def _scale(image_height: int) -> float:
    # Legends stay legible on thumbnails and do not dwarf large renders: 1x at 480 rows, within [0.75, 2].
    return float(min(2.0, max(0.75, image_height / 480.0)))


def _draw_on(image: np.ndarray, box: tuple[int, int, int, int], draw: Any) -> np.ndarray:
    """A copy of ``image`` (``(h, w, 3)`` uint8) where ``draw(ImageDraw, x0, y0)`` drew into ``box`` = ``(x0, y0,
    x1, y1)`` (clipped to the image); only that corner goes through PIL, so large images cost one copy."""
    from PIL import Image, ImageDraw

    h, w = image.shape[:2]
    x0, y0 = max(0, box[0]), max(0, box[1])
    x1, y1 = min(w, box[2]), min(h, box[3])
    out = np.array(image, dtype=np.uint8, copy=True)
    if x1 <= x0 or y1 <= y0:
        return out
    crop = Image.fromarray(np.ascontiguousarray(out[y0:y1, x0:x1]))
    draw(ImageDraw.Draw(crop, "RGBA"), -x0, -y0)
    out[y0:y1, x0:x1] = np.asarray(crop)
    return out


CORNERS = ("bottom-left", "bottom-right", "top-left", "top-right")
"""Where a legend may go, in order of preference."""


def _panel(image_height: int, classes: ClassTable, labels: list[int]) -> tuple[int, int, int, int, Any]:
    """Width, height, swatch side and padding of a legend panel for images ``image_height`` rows high, and its
    font."""
    from PIL import Image, ImageDraw

    s = _scale(image_height)
    sw, pad = max(6, round(SWATCH * s)), max(2, round(PAD * s))
    font = default_font(max(8, round(11 * s)))
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    text_w = max(measure.textbbox((0, 0), classes.names[c], font=font, anchor="lm")[2] for c in labels)
    return pad + sw + pad + text_w + pad, pad + (sw + pad) * len(labels), sw, pad, font


def _origin(corner: str, shape: tuple[int, ...], width: int, height: int, gap: int) -> tuple[int, int]:
    h, w = shape[:2]
    x = gap if corner.endswith("left") else max(gap, w - gap - width)
    y = gap if corner.startswith("top") else max(gap, h - gap - height)
    return x, y


def _labels(classes: ClassTable, labels: Iterable[int]) -> list[int]:
    return [int(c) for c in labels if 0 < int(c) < len(classes)]


def legend_corner(images: Sequence[Any], classes: ClassTable, labels: Iterable[int],
                  background: tuple[int, int, int] = (255, 255, 255)) -> str:
    """The corner (:data:`CORNERS`) where a legend of ``labels`` hides the fewest pixels other than
    ``background`` over all ``images`` (``(h, w, 3)`` uint8, one size): one corner for every frame of a video,
    so that the legend stays put; the first in :data:`CORNERS` on ties."""
    labels = _labels(classes, labels)
    if not labels or not images:
        return CORNERS[0]
    shape = np.asarray(images[0]).shape
    width, height, _, pad, _ = _panel(shape[0], classes, labels)
    bg = np.asarray(background, dtype=np.uint8)
    counts = []
    for corner in CORNERS:
        x, y = _origin(corner, shape, width, height, pad)
        counts.append(sum(int(np.count_nonzero(np.any(np.asarray(im)[y:y + height + 1, x:x + width + 1, :3] != bg,
                                                                   axis=-1))) for im in images))
    return CORNERS[int(np.argmin(counts))]


def draw_legend(image: Any, classes: ClassTable, labels: Iterable[int],
                background: tuple[int, int, int] = (255, 255, 255), corner: str | None = None) -> np.ndarray:
    """A copy of ``image`` with a legend of ``labels`` in one of its corners.

    Args:
        image: ``(h, w, 3)`` uint8 RGB.
        classes: names and colours of the labels.
        labels: the classes to list (non-zero labels below ``len(classes)``); none gives the image unchanged.
        background: the picture's background colour.
        corner: one of :data:`CORNERS`; None picks the one where the legend hides the least of the picture
            (:func:`legend_corner`), so that it does not cover the model or the frustum's edges where it can
            help it.

    Returns:
        ``(h, w, 3)`` uint8 RGB.
    """
    img = np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[..., :3])
    labels = _labels(classes, labels)
    if not labels:
        return img.copy()
    if corner is None:
        corner = legend_corner([img], classes, labels, background)
    if corner not in CORNERS:
        raise ValueError(f"corner must be one of {CORNERS}, got {corner!r}")
    panel_w, panel_h, sw, pad, font = _panel(img.shape[0], classes, labels)
    x0, y0 = _origin(corner, img.shape, panel_w, panel_h, pad)

    def draw(d: Any, dx: int, dy: int) -> None:
        d.rectangle([x0 + dx, y0 + dy, x0 + dx + panel_w, y0 + dy + panel_h], fill=(255, 255, 255, 200),
                    outline=(90, 90, 90, 255))
        for r, c in enumerate(labels):
            y = y0 + dy + pad + r * (sw + pad)
            d.rectangle([x0 + dx + pad, y, x0 + dx + pad + sw - 1, y + sw - 1], fill=tuple(classes.colours[c]) + (255,),
                        outline=(60, 60, 60, 255))
            d.text((x0 + dx + 2 * pad + sw, y + sw / 2), classes.names[c], fill=(20, 20, 20, 255), font=font,
                   anchor="lm")

    return _draw_on(img, (x0, y0, x0 + panel_w + 1, y0 + panel_h + 1), draw)


def wrap_text(text: str, width: int, font: Any, measure: Any = None) -> list[str]:
    """``text`` in lines no wider than ``width`` pixels in ``font``, broken at spaces; a word wider than that is
    cut and ends in an ellipsis.

    Args:
        text: the text.
        width: the widest line, pixels.
        font: a PIL font (:func:`fruxel.render.compat.default_font`).
        measure: a PIL ``ImageDraw`` to measure with (None: made here).

    Returns:
        The lines (one empty line for empty text).
    """
    if measure is None:
        from PIL import Image, ImageDraw

        measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    lines: list[str] = []
    for word in text.split():
        joined = f"{lines[-1]} {word}" if lines else word
        if lines and measure.textlength(joined, font=font) <= width:
            lines[-1] = joined
            continue
        if measure.textlength(word, font=font) > width:
            while len(word) > 1 and measure.textlength(word + "\u2026", font=font) > width:
                word = word[:-1]
            word += "\u2026"
        lines.append(word)
    return lines or [""]


def draw_caption(image: Any, text: str, font_size: int | None = None) -> np.ndarray:
    """A copy of ``image`` (``(h, w, 3)`` uint8 RGB) with one line of ``text`` in its top-left corner, in
    ``font_size`` pixels (None: scaled with the image's height, as legends are)."""
    from PIL import Image, ImageDraw

    img = np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[..., :3])
    s = _scale(img.shape[0]) if font_size is None else font_size / 11
    pad = max(2, round(PAD * s))
    font = default_font(max(8, round(11 * s)))
    box = ImageDraw.Draw(Image.new("RGB", (1, 1))).textbbox((2 * pad, 2 * pad), text, font=font)

    def draw(d: Any, dx: int, dy: int) -> None:
        d.rectangle([box[0] - pad + dx, box[1] - pad + dy, box[2] + pad + dx, box[3] + pad + dy],
                    fill=(255, 255, 255, 200))
        d.text((2 * pad + dx, 2 * pad + dy), text, fill=(20, 20, 20, 255), font=font)

    return _draw_on(img, (box[0] - pad, box[1] - pad, box[2] + pad + 1, box[3] + pad + 1), draw)


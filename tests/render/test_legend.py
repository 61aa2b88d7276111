"""Tests of fruxel.render.legend: swatches of the present classes only, placed where they hide the least, captions
in a font with real spaces."""

from __future__ import annotations

import numpy as np

from fruxel import DEFAULT_CLASSES
from fruxel.render.compat import default_font
from fruxel.render.legend import CORNERS, draw_caption, draw_legend, legend_corner, present_labels

PALETTE = DEFAULT_CLASSES.palette()


def has_colour(img: np.ndarray, c: int) -> bool:
    return bool(np.any(np.all(img == PALETTE[c], axis=-1)))


def test_present_labels() -> None:
    assert present_labels(np.array([[0, 3], [3, 1]]), np.array([5, 0])) == [1, 3, 5]
    assert present_labels(np.zeros((2, 2), int)) == []


def test_legend_lists_only_present_classes() -> None:
    blank = np.full((240, 320, 3), 255, np.uint8)
    img = draw_legend(blank, DEFAULT_CLASSES, [2, 4])
    assert img.shape == blank.shape and img.dtype == np.uint8
    assert has_colour(img, 2) and has_colour(img, 4)
    assert not any(has_colour(img, c) for c in (1, 3, 5, 6))
    # The legend sits in the bottom-left corner.
    changed = np.any(img != 255, axis=-1)
    rows, cols = np.nonzero(changed)
    assert rows.min() > 240 // 2 and cols.max() < 320 // 2


def test_legend_without_labels_and_caption() -> None:
    blank = np.full((60, 80, 3), 255, np.uint8)
    assert np.array_equal(draw_legend(blank, DEFAULT_CLASSES, []), blank)
    assert np.array_equal(draw_legend(blank, DEFAULT_CLASSES, [0]), blank)
    cap = draw_caption(blank, "mesh")
    assert np.any(cap[:20] != 255) and np.all(cap[40:] == 255)


def _legend_box(img: np.ndarray, blank: np.ndarray) -> tuple[int, int, int, int]:
    rows, cols = np.nonzero(np.any(img != blank, axis=-1))
    return rows.min(), rows.max(), cols.min(), cols.max()


def test_legend_moves_away_from_the_picture() -> None:
    """The legend goes to the corner where it covers the fewest pixels of the picture: here the bottom-left
    corner holds lines (like the frustum's apex), so it goes bottom-right."""
    pic = np.full((240, 320, 3), 255, np.uint8)
    pic[150:240, 0:120] = 40
    img = draw_legend(pic, DEFAULT_CLASSES, [1, 2, 3])
    r0, r1, c0, c1 = _legend_box(img, pic)
    assert r0 > 120 and c0 > 160
    assert np.array_equal(img[150:240, 0:120], pic[150:240, 0:120])
    assert legend_corner([pic], DEFAULT_CLASSES, [1, 2, 3]) == "bottom-right"
    # Over several frames one corner serves them all: the one freest over the whole sequence.
    other = np.full_like(pic, 255)
    other[150:240, 200:320] = 40
    other[0:100, 0:100] = 40
    assert legend_corner([pic, other, other], DEFAULT_CLASSES, [1]) == "top-right"
    for corner in CORNERS:
        r0, r1, c0, c1 = _legend_box(draw_legend(np.full_like(pic, 255), DEFAULT_CLASSES, [4], corner=corner),
                                     np.full_like(pic, 255))
        assert (r0 < 120) == corner.startswith("top") and (c0 < 160) == corner.endswith("left")


def test_captions_keep_their_spaces() -> None:
    """Captions use DejaVu Sans (shipped with matplotlib): a space is a space, not the two pixels of Pillow's
    default font that made "1232 triangles" read as "1232triangles"."""
    font = default_font(11)
    assert font.getname()[0] == "DejaVu Sans"
    assert font.getlength("1232 triangles") - font.getlength("1232triangles") >= 3
    blank = np.full((40, 200, 3), 255, np.uint8)
    spaced, joined = draw_caption(blank, "mesh  1232 triangles"), draw_caption(blank, "mesh1232triangles")
    assert _legend_box(spaced, blank)[3] - _legend_box(joined, blank)[3] >= 6

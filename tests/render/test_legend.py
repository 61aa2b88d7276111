"""Tests of fruxel.render.legend: swatches of the present classes only, captions."""

from __future__ import annotations

import numpy as np

from fruxel import DEFAULT_CLASSES
from fruxel.render.legend import draw_caption, draw_legend, present_labels

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

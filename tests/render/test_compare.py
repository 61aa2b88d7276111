"""Comparison pictures (fruxel.render.compare) and the video files of fruxel.render.images: panels where they
belong, legends that wrap and cover nothing, GIFs that keep class colours exact in every frame, MP4s from
generators."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fruxel import DEFAULT_CLASSES
from fruxel.render.compare import GAP, Layout, compose, fit_height, legend_strip
from fruxel.render.images import save_video

PALETTE = DEFAULT_CLASSES.palette()


def panel(h: int, w: int, colour: tuple[int, int, int]) -> np.ndarray:
    return np.full((h, w, 3), colour, np.uint8)


def test_compose_places_columns_left_to_right_with_a_legend_below() -> None:
    a, b, c = panel(40, 30, (200, 0, 0)), panel(40, 50, (0, 200, 0)), panel(40, 50, (0, 0, 200))
    pic = compose([[a], [b, c]], ["red", "green and blue"], DEFAULT_CLASSES, [1, 2], title="a title")
    assert pic.shape[1] == GAP + 30 + GAP + 50 + GAP
    red = np.argwhere(np.all(pic == (200, 0, 0), axis=-1))
    green = np.argwhere(np.all(pic == (0, 200, 0), axis=-1))
    blue = np.argwhere(np.all(pic == (0, 0, 200), axis=-1))
    assert len(red) == 40 * 30 and len(green) == 40 * 50 and len(blue) == 40 * 50
    assert red[:, 1].max() < green[:, 1].min()  # columns side by side
    assert green[:, 0].max() < blue[:, 0].min()  # panels of a column stacked
    assert red[:, 0].min() == green[:, 0].min()  # columns top-aligned
    # The legend's swatches (wall, floor) lie below every panel.
    for c in (1, 2):
        swatch = np.argwhere(np.all(pic == PALETTE[c], axis=-1))
        assert len(swatch) > 20 and swatch[:, 0].min() > blue[:, 0].max()
    assert not np.any(np.all(pic == PALETTE[3], axis=-1))  # window is not listed


def test_compose_without_legend_and_title_is_tight() -> None:
    pic = compose([[panel(30, 30, (9, 9, 9))]], [""], DEFAULT_CLASSES, [1], legend=False)
    rows = np.flatnonzero(np.any(np.all(pic == (9, 9, 9), axis=-1), axis=1))
    assert pic.shape[0] - rows.max() - 1 == GAP


def test_legend_strip_wraps_to_its_width() -> None:
    wide = legend_strip(1000, DEFAULT_CLASSES, range(1, 7))
    narrow = legend_strip(150, DEFAULT_CLASSES, range(1, 7))
    assert wide.shape[1] == 1000 and narrow.shape[1] == 150
    assert narrow.shape[0] >= 3 * wide.shape[0] - 4
    for c in range(1, 7):
        assert np.any(np.all(narrow == PALETTE[c], axis=-1))
    assert legend_strip(100, DEFAULT_CLASSES, []).shape == (0, 100, 3)


def test_fit_height_keeps_the_aspect() -> None:
    assert fit_height(panel(100, 200, (1, 2, 3)), 50).shape == (50, 100, 3)
    assert fit_height(panel(10, 15, (1, 2, 3)), 30).shape == (30, 45, 3)


def test_gif_keeps_given_colours_exact_in_every_frame(tmp_path: Path) -> None:
    """A palette per frame drifted class colours (a legend swatch changed colour from frame to frame) and merged
    small ones away; the GIF's one palette holds the given colours exactly."""
    rng = np.random.default_rng(0)
    frames = []
    for _ in range(5):
        f = rng.integers(0, 256, (60, 80, 3), dtype=np.uint8)  # a noisy photo panel
        f[:, 60:] = 255  # white background
        for c in range(1, 7):
            f[2 + 8 * c:8 + 8 * c, 70:76] = PALETTE[c]  # legend swatches, 36 pixels each
        frames.append(f)
    path = tmp_path / "v.gif"
    save_video(path, iter(frames), 10, ".gif", [(255, 255, 255), *PALETTE[1:]])
    with Image.open(path) as gif:
        assert gif.n_frames == 5
        for i in range(5):
            gif.seek(i)
            got = np.asarray(gif.convert("RGB"))
            # Dithering carries the noise's error a pixel or two into the white; beyond, every pixel is exact.
            assert np.array_equal(got[:, 63:], frames[i][:, 63:])


def test_mp4_from_a_generator(tmp_path: Path) -> None:
    import imageio.v2 as imageio

    def frames():
        for i in range(4):
            yield panel(31, 45, (60 * i, 100, 100))  # odd sizes: padded to even for H.264

    save_video(tmp_path / "v.mp4", frames(), 8, ".mp4")
    got = imageio.mimread(tmp_path / "v.mp4", format="FFMPEG")
    assert len(got) == 4 and got[0].shape[:2] == (32, 46)
    assert abs(int(got[3][10, 10, 0]) - 180) < 8


@pytest.mark.parametrize("suffix", [".gif", ".mp4"])
def test_no_frames_is_an_error(tmp_path: Path, suffix: str) -> None:
    from fruxel.render import RenderError

    with pytest.raises(RenderError, match="no frames"):
        save_video(tmp_path / f"v{suffix}", iter([]), 10, suffix)


def test_layout_fill_is_compose_and_keeps_its_template() -> None:
    rng = np.random.default_rng(3)
    cols = [[rng.integers(0, 256, (40, 30, 3), dtype=np.uint8)],
            [rng.integers(0, 256, (40, 50, 3), dtype=np.uint8), rng.integers(0, 256, (20, 50, 4), dtype=np.uint8)]]
    heads, title = ["one", "two with a heading long enough to wrap"], "a title over both"
    layout = Layout([[p.shape[:2] for p in c] for c in cols], heads, DEFAULT_CLASSES, [1, 2, 5], title=title)
    before = layout.template.copy()
    first = layout.fill(cols)
    assert np.array_equal(first, compose(cols, heads, DEFAULT_CLASSES, [1, 2, 5], title=title))
    other = [[cols[0][0] // 2], [cols[1][0] // 3, cols[1][1] // 4]]
    second = layout.fill(other)
    assert np.array_equal(second, compose(other, heads, DEFAULT_CLASSES, [1, 2, 5], title=title))
    assert np.array_equal(layout.template, before) and not np.array_equal(first, second)


@pytest.mark.parametrize("cols, match", [([[panel(40, 30, (1, 1, 1))]], "2 columns"),
                                         ([[panel(40, 30, (1, 1, 1))], []], "1 panels"),
                                         ([[panel(40, 31, (1, 1, 1))], [panel(40, 50, (1, 1, 1))]], "40x30")])
def test_layout_refuses_panels_it_was_not_made_for(cols, match) -> None:
    layout = Layout([[(40, 30)], [(40, 50)]], ["a", "b"], DEFAULT_CLASSES, [1])
    with pytest.raises(ValueError, match=match):
        layout.fill(cols)

"""fruxel.train.predict.frame_image: a photo brought to a grid camera's view, at any size."""

from __future__ import annotations

import math
import tracemalloc

import numpy as np
import pytest
from PIL import Image

from fruxel.grid import FruxelGrid
from fruxel.train.predict import PAD_VALUE, frame_image

GRID = FruxelGrid(width=64, height=64, depth=64, z_near=0.5, z_far=8.0, hfov=60.0)


def smooth_photo(h: int, w: int) -> np.ndarray:
    y, x = np.mgrid[0:h, 0:w]
    return np.stack([x * 255 // max(1, w - 1), y * 255 // max(1, h - 1), (x + y) % 256], axis=-1).astype(np.uint8)


def test_same_view_is_a_plain_resize() -> None:
    photo = smooth_photo(512, 512)
    expected = np.asarray(Image.fromarray(photo).resize((128, 128), Image.BOX))
    assert np.array_equal(frame_image(photo, GRID, (128, 128)), expected)
    assert frame_image(photo, GRID, (300, 300)).shape == (300, 300, 3)


def test_wider_photo_is_cropped_to_the_grids_view() -> None:
    """A 90-degree photo: the grid's 60 degrees are its middle tan(30)/tan(45) = 57.7 % of the columns."""
    photo = smooth_photo(400, 400)
    out = frame_image(photo, GRID, (64, 64), hfov=90.0)
    cols = round(400 * math.tan(math.radians(30)))
    x0 = (400 - cols) // 2
    expected = np.asarray(Image.fromarray(photo[x0:x0 + cols, x0:x0 + cols]).resize((64, 64), Image.BOX))
    assert np.array_equal(out, expected)


def test_narrow_photo_is_padded_about_the_centre_without_a_huge_frame() -> None:
    """A 1-degree photo covers a few pixels in the middle of the grid's view; the frame it would need at the
    photo's own resolution (63,000 pixels a side, 12 GB) is never allocated."""
    photo = np.full((480, 640, 3), 200, np.uint8)
    tracemalloc.start()
    try:
        out = frame_image(photo, GRID, (128, 128), hfov=1.0)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 10_000_000
    inside = np.argwhere(np.all(out == 200, axis=-1))
    assert len(inside) > 0 and np.all(np.abs(inside - 63.5) < 3)
    assert np.count_nonzero(np.all(out == PAD_VALUE, axis=-1)) > 128 * 128 - 10


def test_pad_fit_keeps_the_whole_photo() -> None:
    photo = np.full((100, 200, 3), 30, np.uint8)
    out = frame_image(photo, GRID, (64, 64), fit="pad")
    rows = np.flatnonzero(np.all(out == 30, axis=(1, 2)))
    assert rows.min() == 16 and rows.max() == 47
    assert np.all(out[:15] == PAD_VALUE) and np.all(out[49:] == PAD_VALUE)


@pytest.mark.parametrize("hfov", [0.0, -5.0, 180.0, float("nan"), float("inf")])
def test_impossible_field_of_view_is_refused(hfov: float) -> None:
    with pytest.raises(ValueError, match="hfov"):
        frame_image(smooth_photo(8, 8), GRID, (8, 8), hfov=hfov)


def test_crop_fit_keeps_a_narrower_field_of_view() -> None:
    """A square 40-degree photo on the 60-degree square grid fills the middle tan(20)/tan(30) = 63 % of the view
    whether the aspect is cropped or padded (crop fit once took the whole photo for 60 degrees)."""
    photo = np.full((512, 512, 3), 200, np.uint8)
    share = math.tan(math.radians(20)) / math.tan(math.radians(30))
    for fit in ("crop", "pad"):
        out = frame_image(photo, GRID, (100, 100), hfov=40.0, fit=fit)
        cols = np.flatnonzero(np.all(out[50] == 200, axis=-1))
        assert abs(len(cols) - 100 * share) <= 1.5, (fit, len(cols))


@pytest.mark.parametrize("fit", ["crop", "pad"])
def test_given_field_of_view_keeps_the_geometry_whatever_the_fit(fit: str) -> None:
    """A 4:3 photo at the grid's 60 degrees fills every column and the middle 3/4 of the rows; enlarging it to lose
    the grey bands would show the model a narrower field of view than it takes the image for. Continuous in the
    field of view: no jump where the photo's crosses the grid's."""
    photo = np.full((480, 640, 3), 200, np.uint8)
    outs = [frame_image(photo, GRID, (64, 64), hfov=h, fit=fit).astype(int) for h in (59.9, 60.0, 60.1)]
    rows = np.flatnonzero(np.all(outs[1] == 200, axis=(1, 2)))
    assert rows.min() == 8 and rows.max() == 55
    assert np.all(outs[1][:8] == PAD_VALUE) and np.all(outs[1][56:] == PAD_VALUE)
    assert np.abs(outs[0] - outs[1]).mean() < 2.0 and np.abs(outs[1] - outs[2]).mean() < 2.0


@pytest.mark.parametrize(("h", "w", "hfov", "fit"), [
    (300, 300, None, "crop"), (120, 240, None, "pad"), (240, 120, None, "pad"), (120, 240, None, "crop"),
    (200, 200, 40.0, "crop"), (90, 300, 45.0, "crop"), (300, 300, 90.0, "crop")])
def test_coverage_is_where_the_framed_photo_is_not_padding(h: int, w: int, hfov: float | None, fit: str) -> None:
    """Each grid column is covered exactly when the framed image at its centre ray shows the photo, not the grey:
    the framed image is made at 4 x 4 pixels a column, so the column's centre is a pixel corner whose four pixels
    all lie on one side of a padding edge that falls on a column boundary or between."""
    from fruxel.train.predict import frame_coverage

    photo = np.full((h, w, 3), 255 - PAD_VALUE if PAD_VALUE < 128 else 0, np.uint8)
    framed = frame_image(photo, GRID, (GRID.height * 4, GRID.width * 4), hfov, fit)
    grey = (framed == PAD_VALUE).all(-1)
    centre = grey[1::4, 1::4] & grey[2::4, 2::4] & grey[1::4, 2::4] & grey[2::4, 1::4]
    photo_there = ~grey[1::4, 1::4] & ~grey[2::4, 2::4] & ~grey[1::4, 2::4] & ~grey[2::4, 1::4]
    covered = frame_coverage(photo.shape, GRID, hfov, fit)
    assert covered.shape == (GRID.height, GRID.width)
    assert not (covered & centre).any() and not (~covered & photo_there).any()
    padded = hfov == 40.0 or (fit == "pad" and h != w) or (hfov == 45.0)
    assert covered.all() != padded


def test_uncovered_columns_are_left_empty() -> None:
    import torch

    from fruxel.train.predict import empty_uncovered

    torch.manual_seed(0)
    logits = torch.randn(2, 7, 8, 4, 5).half()
    before = logits.clone()
    covered = np.ones((4, 5), bool)
    covered[0] = covered[:, 4] = False
    out = empty_uncovered(logits, covered)
    assert out is logits
    mask = torch.from_numpy(covered)
    labels = out.float().argmax(-4)
    assert (labels[..., ~mask] == 0).all()
    torch.testing.assert_close(out[..., mask], before[..., mask])
    assert torch.isfinite(out).all()
    assert empty_uncovered(before.clone(), np.ones((4, 5), bool)).equal(before)

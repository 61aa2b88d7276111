"""prepare_image maps a photo onto the grid's own camera by its field of view, or by aspect alone."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fruxel.train.config import preset
from fruxel.train.predict import PAD_VALUE, prepare_image

CONFIG = preset("tiny").model  # 32^3 grid, 60 degrees, 64 x 64 input


def ramp(h: int, w: int) -> np.ndarray:
    """An (h, w, 3) photo whose red channel is its column index and green its row index (both < 256)."""
    img = np.zeros((h, w, 3), np.uint8)
    img[..., 0] = np.arange(w)[None, :]
    img[..., 1] = np.arange(h)[:, None]
    return img


def test_wider_field_of_view_keeps_the_grid_s_central_columns() -> None:
    # tan(hfov / 2) = 2 tan(30 deg): the grid's view is the photo's central half, in both directions.
    hfov = math.degrees(2 * math.atan(2 * math.tan(math.radians(30.0))))
    out = prepare_image(ramp(200, 200), CONFIG, hfov=hfov)
    assert out.shape == (64, 64, 3)
    assert abs(int(out[32, 0, 0]) - 50) <= 2 and abs(int(out[32, -1, 0]) - 149) <= 2
    assert abs(int(out[0, 32, 1]) - 50) <= 2 and abs(int(out[-1, 32, 1]) - 149) <= 2


def test_narrower_field_of_view_is_padded_around_the_photo() -> None:
    # tan(hfov / 2) = tan(30 deg) / 2: the photo fills the grid's central half; the rest is grey.
    hfov = math.degrees(2 * math.atan(0.5 * math.tan(math.radians(30.0))))
    out = prepare_image(ramp(100, 100) + 1, CONFIG, hfov=hfov)
    assert (out[:, :10] == PAD_VALUE).all() and (out[:, -10:] == PAD_VALUE).all()
    assert (out[:10] == PAD_VALUE).all()
    assert out[32, 16:48, 0].min() < 20 and out[32, 16:48, 0].max() > 80


@pytest.mark.parametrize("fit", ["crop", "pad"])
def test_aspect_without_field_of_view(fit: str) -> None:
    out = prepare_image(ramp(100, 200), CONFIG, fit=fit)
    if fit == "crop":  # the central 100 x 100 square: columns 50..149
        assert abs(int(out[32, 0, 0]) - 50) <= 2 and abs(int(out[32, -1, 0]) - 149) <= 2
        assert not (out == PAD_VALUE).all(axis=2).any()
    else:  # the whole photo, grey above and below
        assert abs(int(out[32, 0, 0]) - 0) <= 2 and abs(int(out[32, -1, 0]) - 199) <= 2
        assert (out[:10] == PAD_VALUE).all() and (out[-10:] == PAD_VALUE).all()

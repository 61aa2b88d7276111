"""Framing: a photo of any size and field of view brought onto the view of a fruxel grid's own camera.

SSZ sees the grid's own camera (conventions section 8): an image of ``2^k W x 2^k H`` pixels whose horizontal field of
view is the grid's. A photo of another size and field of view is mapped onto it geometrically, about the
optical centre (the photo's centre):

* with its field of view given (``hfov``), geometry decides: a wider photo is cropped to the grid's view, a
  narrower one is padded (the model sees :data:`PAD_VALUE` grey where the photo has nothing), in both directions;
  ``fit`` plays no part, since enlarging the photo to fill the frame would change the field of view the model sees;
* without it, the photo is taken as the grid's view and only its aspect is brought to ``H / W``: crop
  (``fit="crop"``, default) or pad (``fit="pad"``) rows or columns, centred;
* then it is resized to the model's image size (area averaging when shrinking).

:func:`frame_coverage` tells which grid columns the framed photo covers. The commands frame photos with these
(:mod:`fruxel.train.predict`), and the simulator frames the images of its cameras of other fields of view with
them too (:mod:`fruxel.train.sim.cameras`), so that training sees what prediction sees. numpy and Pillow only.

Images are ``(h, w, 3)`` uint8 RGB arrays (rows down, columns right).
"""

from __future__ import annotations

import math

import numpy as np

from fruxel.grid import FruxelGrid

PAD_VALUE = 128
"""Grey (uint8) the model sees where the photo has nothing."""

def frame_image(img: np.ndarray, grid: FruxelGrid, size: tuple[int, int], hfov: float | None = None,
                fit: str = "crop") -> np.ndarray:
    """A photo framed to the view of a grid's own camera (see the module docstring), at any size: the model's
    input (:func:`prepare_image`) or a picture of what the model sees.

    Only the photo's part inside the frame is resized, then placed on :data:`PAD_VALUE` grey: a photo whose field of
    view is far narrower than the grid's (a frame many times the photo's size) costs no more memory than the result.

    Args:
        img: ``(h, w, 3)`` uint8 RGB.
        grid: the grid whose camera's view the photo is brought to.
        size: ``(height, width)`` of the result in pixels, in the grid's aspect ``H / W``.
        hfov: the photo's horizontal field of view, degrees (None: the grid's own).
        fit: ``"crop"`` or ``"pad"``, how the aspect is matched when ``hfov`` is None.

    Returns:
        ``(height, width, 3)`` uint8 RGB.

    Raises:
        ValueError: a wrong array, field of view or fit.
    """
    from PIL import Image

    if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be an (h, w, 3) uint8 array, got {getattr(img, 'dtype', type(img))} "
                         f"{getattr(img, 'shape', '')}")
    if fit not in ("crop", "pad"):
        raise ValueError(f"fit must be 'crop' or 'pad', got {fit!r}")
    if hfov is not None and not (math.isfinite(hfov) and 0.0 < hfov < 180.0):
        raise ValueError(f"--hfov must be in (0, 180) degrees, got {hfov!r}")
    h, w = img.shape[:2]
    rows, cols, sy, sx, dy, dx, ch, cw = _frame(h, w, grid, hfov, fit)
    out_h, out_w = size
    part = Image.fromarray(np.ascontiguousarray(img[sy:sy + ch, sx:sx + cw]))
    resample = Image.BOX if rows >= out_h else Image.BILINEAR
    if (ch, cw) == (rows, cols):
        return np.asarray(part.resize((out_w, out_h), resample), dtype=np.uint8)
    out = np.full((out_h, out_w, 3), PAD_VALUE, dtype=np.uint8)
    # Where the part lands, at least one pixel (a photo narrower than one output pixel still shows), centred.
    (y0, y1), (x0, x1) = (_span(d, c, n, m) for d, c, n, m in ((dy, ch, rows, out_h), (dx, cw, cols, out_w)))
    out[y0:y1, x0:x1] = np.asarray(part.resize((x1 - x0, y1 - y0), resample), dtype=np.uint8)
    return out


def _frame(h: int, w: int, grid: FruxelGrid, hfov: float | None, fit: str
           ) -> tuple[int, int, int, int, int, int, int, int]:
    """Where an ``h x w`` photo lies in the grid's view (:func:`frame_image`): the frame's ``rows, cols`` in photo
    pixels; the first photo row and column inside it ``sy, sx``; where they land in the frame ``dy, dx``; and the
    size of the photo's part inside it ``ch, cw``."""
    # Pixels per unit of x/z of the photo; the grid's view spans u in [-tu, tu].
    f = w / (2.0 * math.tan(math.radians(hfov if hfov is not None else grid.hfov) / 2.0))
    cols = max(1, round(2.0 * grid.tu * f))
    if hfov is None:
        # The photo is the grid's view (cols == w): the frame is the largest centred region of the grid's aspect
        # inside the photo (crop) or the smallest one around it (pad).
        aspect_cols = max(1, round(h * grid.width / grid.height))
        cols = min(cols, aspect_cols) if fit == "crop" else max(cols, aspect_cols)
    rows = max(1, round(cols * grid.height / grid.width))
    # The frame (rows x cols photo pixels) centred on the photo: the photo's part inside it, and where it lands.
    sy, sx = max(0, (h - rows) // 2), max(0, (w - cols) // 2)
    dy, dx = max(0, (rows - h) // 2), max(0, (cols - w) // 2)
    return rows, cols, sy, sx, dy, dx, min(h, rows), min(w, cols)


def frame_coverage(shape: tuple[int, ...], grid: FruxelGrid, hfov: float | None = None, fit: str = "crop"
                   ) -> np.ndarray:
    """Which grid columns the photo covers once framed (:func:`frame_image`): those whose centre ray passes
    through the photo rather than through the grey padding around it.

    Args:
        shape: the photo's ``(h, w, ...)``.
        grid: the grid.
        hfov, fit: as :func:`frame_image` takes them.

    Returns:
        ``(H, W)`` bool, grid frame (row j down, column i right); all True when nothing is padded.
    """
    h, w = int(shape[0]), int(shape[1])
    rows, cols, _, _, dy, dx, ch, cw = _frame(h, w, grid, hfov, fit)
    y = (np.arange(grid.height) + 0.5) * rows / grid.height  # each column's centre ray, frame pixels
    x = (np.arange(grid.width) + 0.5) * cols / grid.width
    return ((y >= dy) & (y < dy + ch))[:, None] & ((x >= dx) & (x < dx + cw))[None, :]


def _span(offset: int, length: int, frame: int, size: int) -> tuple[int, int]:
    """Output pixels ``[a, b)`` of ``size`` that hold frame pixels ``[offset, offset + length)`` of ``frame``:
    their own span rounded, or the one pixel nearest its centre when that span rounds to nothing."""
    a, b = round(offset * size / frame), round((offset + length) * size / frame)
    if b > a:
        return a, b
    a = min(size - 1, max(0, int((offset + length / 2) * size / frame)))
    return a, a + 1



"""The picture of examples: per sample, the image | truth and prediction seen from the grid's own camera |
truth and prediction ray-cast from a novel pose, with a class legend below."""

from __future__ import annotations

import os
from typing import Any

import numpy as np

from fruxel.classes import ClassTable
from fruxel.grid import FruxelGrid
from fruxel.io import atomic_path

HEADINGS = ("image", "truth, own view", "prediction, own view", "truth, novel view", "prediction, novel view")
"""Column headings of the sheet."""


def example_sheet(samples: list[dict[str, Any]], grid: FruxelGrid, classes: ClassTable, path: str | os.PathLike[str],
                  *, title: str = "", tile: int = 192, backend: str | None = None) -> None:
    """Write the examples PNG.

    Args:
        samples: dicts of ``image`` ``(3, h, w)`` float in [0, 1] and ``labels`` / ``pred`` ``(D, H, W)`` uint8
            (torch CPU tensors or numpy), as :func:`fruxel.train.eval.evaluate.evaluate` keeps them.
        grid, classes: their grid and class table.
        path: the PNG.
        title: a line above the rows.
        tile: width of each picture, pixels.
        backend: kernel backend of the ray casts.
    """
    import torch
    from PIL import Image, ImageDraw

    from fruxel.render.compat import default_font
    from fruxel.render.legend import draw_legend, wrap_text
    from fruxel.render.raycast import raycast_image

    from .metrics import first_surface

    palette = np.asarray(classes.palette(), dtype=np.uint8)
    th = max(1, round(tile * grid.height / grid.width))
    rows = []
    present: set[int] = set()
    for s in samples:
        img = (np.clip(np.asarray(s["image"]).transpose(1, 2, 0), 0, 1) * 255).round().astype(np.uint8)
        tiles = [np.asarray(Image.fromarray(img).resize((tile, th), Image.BILINEAR))]
        vols = [np.ascontiguousarray(np.asarray(s[k]), dtype=np.uint8) for k in ("labels", "pred")]
        for vol in vols:
            present |= {int(v) for v in np.unique(vol)}
            surf = first_surface(torch.from_numpy(vol[None]))[0].numpy()
            tiles.append(np.asarray(Image.fromarray(palette[surf]).resize((tile, th), Image.NEAREST)))
        novel = view_of(vols[0], grid, tile, th)
        tiles += [raycast_image(vol, grid, novel, palette, backend=backend)[0] for vol in vols]
        rows.append(np.concatenate(tiles, axis=1))
    sheet = np.concatenate(rows, axis=0) if rows else np.full((th, tile * len(HEADINGS), 3), 255, np.uint8)
    # The legend gets a column of its own, so that it covers no picture.
    key = draw_legend(np.full((min(sheet.shape[0], 240), 130, 3), 255, np.uint8), classes, sorted(present - {0}))
    font = default_font(13)
    line = 18
    # A long title (several camera settings, say) wraps rather than runs off the sheet.
    titles = wrap_text(title, sheet.shape[1] + key.shape[1] - 8, font) if title else []
    top = line * (len(titles) + 1)
    canvas = Image.new("RGB", (sheet.shape[1] + key.shape[1], sheet.shape[0] + top), (255, 255, 255))
    canvas.paste(Image.fromarray(sheet), (0, top))
    canvas.paste(Image.fromarray(key), (sheet.shape[1], canvas.height - key.shape[0]))
    draw = ImageDraw.Draw(canvas)
    for k, text in enumerate(titles):
        draw.text((4, 2 + k * line), text, fill=(0, 0, 0), font=font)
    for i, h in enumerate(HEADINGS):
        draw.text((i * tile + 4, top - line + 2), h, fill=(0, 0, 0), font=font)
    with atomic_path(path) as tmp:
        canvas.save(tmp, format="PNG")


def view_of(labels: np.ndarray, grid: FruxelGrid, width: int, height: int, azimuth: float = 35.0,
            elevation: float = 30.0) -> Any:
    """A camera looking at the occupied cells of ``labels`` ``(D, H, W)`` from above one side, framed on their
    bounding box (the whole grid when none is occupied).

    Args:
        labels: the volume to frame, grid frame.
        grid: its grid.
        width, height: image size, pixels.
        azimuth, elevation: degrees, as for :func:`fruxel.camera.orbit_direction`.
    """
    import math

    from fruxel.camera import Camera, orbit_direction

    k, j, i = np.nonzero(labels)
    if len(k):
        pts = grid.cell_to_point(k, j, i)
        lo, hi = pts.min(axis=0), pts.max(axis=0)
    else:
        lo, hi = grid.bounds()
    centre = (lo + hi) / 2.0
    radius = 0.5 * float(np.linalg.norm(hi - lo)) + 1e-3
    hfov = 50.0
    fit = radius / math.sin(math.radians(hfov * min(1.0, height / width) / 2.0))
    eye = centre + fit * orbit_direction(math.radians(azimuth), math.radians(elevation))
    return Camera.look_at(eye, centre, width=width, height=height, hfov=hfov)

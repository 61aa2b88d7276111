"""Comparison pictures: panels in titled columns above one class legend, so that a photo, the model predicted
from it and the ground truth can be read side by side.

:func:`compose` lays out any panels (``fruxel-render`` on a photo); :class:`Layout` draws the same frame once and
fills it with new panels (the live robot demo's video frames);
:class:`PhotoComparison` draws the pictures of ``fruxel-render PHOTO``: the photo (and, with mesh and ray cast,
the prediction seen from the photo's own camera under it), then a column per model (the prediction, the truth
when there is one), each shown as a mesh, a ray cast or both, from one viewing camera. The legend sits in a strip
of its own below the panels, so that it covers none of them, and lists every class either model holds.

Images are ``(h, w, 3)`` uint8 RGB arrays.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.classes import ClassTable

from .compat import default_font
from .frames import FrameRenderer
from .legend import wrap_text

GAP = 8
"""Pixels between panels and around the picture."""
BACKGROUND = (255, 255, 255)
"""Colour of the picture around the panels (the renderers' background)."""
TEXT = (20, 20, 20)
"""Colour of titles, headings and legend names."""


def _font_size(panel_height: int) -> int:
    # Readable on 192-pixel video panels and not shouting on 512-pixel ones.
    return int(np.clip(round(panel_height / 24), 12, 18))


def caption_size(panel_height: int) -> int:
    """Text height in pixels of the captions on panels ``panel_height`` rows high (a little below the headings')."""
    return _font_size(panel_height) - 1


def fit_height(image: Any, height: int) -> np.ndarray:
    """``image`` (``(h, w, 3)`` uint8) scaled to ``height`` rows, its aspect kept (area averaging when shrinking,
    bilinear when enlarging)."""
    from PIL import Image

    img = np.ascontiguousarray(np.asarray(image, dtype=np.uint8)[..., :3])
    h, w = img.shape[:2]
    if h == height:
        return img
    width = max(1, round(w * height / h))
    resample = Image.BOX if height < h else Image.BILINEAR
    return np.asarray(Image.fromarray(img).resize((width, height), resample), dtype=np.uint8)


def legend_strip(width: int, classes: ClassTable, labels: Iterable[int], font_size: int = 13) -> np.ndarray:
    """A legend as a strip: a colour swatch and the name of each class in ``labels``, left to right, on as many
    rows as ``width`` needs.

    Args:
        width: the strip's width, pixels.
        classes: names and colours.
        labels: the classes to list (non-zero labels below ``len(classes)``, in label order).
        font_size: text height, pixels.

    Returns:
        ``(h, width, 3)`` uint8 on :data:`BACKGROUND`; ``h`` is 0 when there is no class to list.
    """
    from PIL import Image, ImageDraw

    shown = sorted({int(c) for c in labels if 0 < int(c) < len(classes)})
    font = default_font(font_size)
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    sw, pad = font_size, max(4, font_size // 2)
    items = [(c, sw + pad // 2 + int(np.ceil(measure.textlength(classes.names[c], font=font)))) for c in shown]
    rows: list[list[tuple[int, int]]] = [[]]
    x = GAP
    for c, w in items:
        if rows[-1] and x + w > width - GAP:
            rows.append([])
            x = GAP
        rows[-1].append((c, w))
        x += w + 2 * pad
    rows = [r for r in rows if r]
    line = sw + pad
    strip = Image.new("RGB", (width, len(rows) * line + (pad if rows else 0)), BACKGROUND)
    draw = ImageDraw.Draw(strip)
    for r, row in enumerate(rows):
        x, y = GAP, pad // 2 + r * line
        for c, w in row:
            draw.rectangle([x, y, x + sw - 1, y + sw - 1], fill=tuple(int(v) for v in classes.colours[c]),
                           outline=(60, 60, 60))
            draw.text((x + sw + pad // 2, y + sw / 2), classes.names[c], fill=TEXT, font=font, anchor="lm")
            x += w + 2 * pad
    return np.asarray(strip, dtype=np.uint8)


def compose(columns: Sequence[Sequence[np.ndarray]], headings: Sequence[str], classes: ClassTable,
            labels: Iterable[int], *, title: str | None = None, legend: bool = True) -> np.ndarray:
    """Panels in columns, a heading over each column, an optional title above them and a legend strip below.

    Args:
        columns: per column, its panels from top to bottom (``(h, w, 3)`` uint8; the panels of one column share
            a width, columns may differ).
        headings: one line over each column (wrapped to the column's width when longer).
        classes: class names and colours for the legend.
        labels: the classes the legend lists.
        title: text above everything (wrapped to the picture's width); None for none.
        legend: False leaves the legend out.

    Returns:
        ``(h, w, 3)`` uint8 RGB on :data:`BACKGROUND`.
    """
    sizes = [[(int(p.shape[0]), int(p.shape[1])) for p in col] for col in columns]
    return Layout(sizes, headings, classes, labels, title=title, legend=legend).fill(columns)


class Layout:
    """The frame of a :func:`compose` picture (title, headings, legend strip), drawn once for panels of given
    sizes and then filled with new panels as often as wanted: a video's frames keep their layout, and drawing its
    text every frame took a noticeable share of the live robot demo's frame (PIL renders each glyph again).

    Args:
        sizes: per column, the ``(height, width)`` of each of its panels, top to bottom.
        headings, classes, labels, title, legend: as :func:`compose`.
    """

    def __init__(self, sizes: Sequence[Sequence[tuple[int, int]]], headings: Sequence[str], classes: ClassTable,
                 labels: Iterable[int], *, title: str | None = None, legend: bool = True) -> None:
        from PIL import Image, ImageDraw

        if len(headings) != len(sizes):
            raise ValueError(f"{len(sizes)} columns but {len(headings)} headings")
        self.sizes = [[(int(h), int(w)) for h, w in col] for col in sizes]
        panel_h = max(h for col in self.sizes for h, _ in col)
        size = _font_size(panel_h)
        font, bold = default_font(size), default_font(size + 1)
        measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
        line = round(size * 1.35)
        widths = [max(w for _, w in col) for col in self.sizes]
        width = GAP + sum(w + GAP for w in widths)
        title_lines = wrap_text(title, width - 2 * GAP, font, measure) if title else []
        heads = [wrap_text(h, w, bold, measure) for h, w in zip(headings, widths, strict=True)]
        head_h = max(len(h) for h in heads) * line
        body_h = max(sum(h for h, _ in col) + GAP * (len(col) - 1) for col in self.sizes)
        strip = legend_strip(width, classes, labels, size) if legend else np.zeros((0, width, 3), np.uint8)
        top = GAP + len(title_lines) * line + (GAP // 2 if title_lines else 0)
        height = top + head_h + body_h + GAP + strip.shape[0] + (GAP // 2 if strip.shape[0] else 0)
        canvas = Image.new("RGB", (width, height), BACKGROUND)
        draw = ImageDraw.Draw(canvas)
        for i, text in enumerate(title_lines):
            draw.text((GAP, GAP + i * line), text, fill=TEXT, font=font)
        self.origins: list[list[tuple[int, int]]] = []
        """Per column, the ``(y, x)`` of each panel's top-left corner in the picture."""
        x = GAP
        for col, w, head in zip(self.sizes, widths, heads, strict=True):
            for i, text in enumerate(head):
                draw.text((x + 2, top + i * line), text, fill=TEXT, font=bold)
            y = top + head_h
            self.origins.append([])
            for h, _ in col:
                self.origins[-1].append((y, x))
                y += h + GAP
            x += w + GAP
        self.template = np.asarray(canvas, dtype=np.uint8).copy()
        """``(h, w, 3)`` uint8: the picture without its panels."""
        if strip.shape[0]:
            y0 = top + head_h + body_h + GAP
            self.template[y0:y0 + strip.shape[0]] = strip

    def fill(self, columns: Sequence[Sequence[np.ndarray]]) -> np.ndarray:
        """A new picture: the template with ``columns``' panels (``(h, w, 3)`` or ``(h, w, 4)`` uint8, of the sizes
        the layout was made for) in their places.

        Raises:
            ValueError: a column or panel that does not match the layout.
        """
        if len(columns) != len(self.sizes):
            raise ValueError(f"the layout has {len(self.sizes)} columns, got {len(columns)}")
        out = self.template.copy()
        for c, (col, sizes, origins) in enumerate(zip(columns, self.sizes, self.origins, strict=True)):
            if len(col) != len(sizes):
                raise ValueError(f"column {c} of the layout has {len(sizes)} panels, got {len(col)}")
            for panel, (h, w), (y, x) in zip(col, sizes, origins, strict=True):
                if tuple(panel.shape[:2]) != (h, w):
                    raise ValueError(f"a panel of column {c} is {panel.shape[0]}x{panel.shape[1]}, the layout's "
                                     f"{h}x{w}")
                out[y:y + h, x:x + w] = panel[..., :3]
        return out


def _labels_of(frames: FrameRenderer) -> set[int]:
    from .frames import volume_labels

    labels = volume_labels(frames.inp.volume, frames.inp, frames.opts.threshold)
    return {int(c) for c in np.flatnonzero(np.bincount(labels.reshape(-1), minlength=1)) if c != 0}


class PhotoComparison:
    """The pictures of ``fruxel-render PHOTO``: the photo beside the model predicted from it and, when given, the
    ground truth, from one viewing camera per picture (see the module docstring).

    Args:
        photo: the photo framed to the grid camera's view (``fruxel.train.predict.frame_image``), ``(h, w, 3)``
            uint8 at any resolution: it is scaled to the panels' height.
        prediction: frames of the predicted model (logits or labels); its options (mode, shell, meshing,
            backend) apply to the truth too.
        truth: frames of the ground truth on the same grid, or None.
        title: a line above the picture (what was predicted, how, and how well).
        headings: headings of the photo, prediction and truth columns.
    """

    def __init__(self, photo: np.ndarray, prediction: FrameRenderer, truth: FrameRenderer | None, *,
                 title: str | None = None,
                 headings: tuple[str, str, str] = ("photo", "SSZ prediction", "ground truth")) -> None:
        self.photo = np.ascontiguousarray(np.asarray(photo, dtype=np.uint8)[..., :3])
        self.prediction = prediction
        self.truth = truth
        self.title = title
        self.headings = headings
        self._own: dict[int, np.ndarray] = {}

    @property
    def models(self) -> list[FrameRenderer]:
        """The frames of the models shown, prediction first."""
        return [self.prediction] + ([self.truth] if self.truth is not None else [])

    def model_points(self) -> np.ndarray | None:
        """Corners of the occupied cells of every model shown, ``(N, 3)`` float64 grid frame (what a view must
        show); None when all are empty."""
        pts = [p for p in (m.model_points() for m in self.models) if p is not None]
        return np.concatenate(pts) if pts else None

    def labels(self) -> list[int]:
        """The classes any of the models holds (the legend's)."""
        return sorted(set().union(*(_labels_of(m) for m in self.models)))

    def _own_view(self, height: int) -> np.ndarray:
        """The prediction ray-cast from the photo's camera (the grid's own, scaled to ``height`` rows), captioned."""
        if height not in self._own:
            from .legend import draw_caption
            from .raycast import RaycastStyle, raycast_image

            grid, opts = self.prediction.inp.grid, self.prediction.opts
            cam = grid.camera().scaled(height / grid.height)
            img, _ = raycast_image(self.prediction.inp.volume, grid, cam, self.prediction.inp.classes.palette(),
                                   backend=opts.backend, device=opts.device, threshold=opts.threshold,
                                   style=RaycastStyle(shading=opts.shading, fog=opts.fog))
            self._own[height] = draw_caption(img, "SSZ seen from the photo's camera", caption_size(height))
        return self._own[height]

    def _model_column(self, frames: FrameRenderer, camera: Camera) -> list[np.ndarray]:
        from .legend import draw_caption

        mode = frames.opts.mode
        panels = []
        if mode in ("mesh", "both"):
            img, _ = frames.mesh_image(camera)
            panels.append(draw_caption(img, frames.mesh_caption(), caption_size(camera.height)))
        if mode in ("raycast", "both"):
            img, _ = frames.raycast_image(camera)
            panels.append(draw_caption(img, frames.raycast_caption(), caption_size(camera.height)))
        return panels

    def image(self, camera: Camera, labels: Sequence[int] | None = None) -> np.ndarray:
        """The picture for one viewing camera: ``(h, w, 3)`` uint8.

        Args:
            camera: the viewing camera of the model panels (their size is its image size).
            labels: the legend's classes; None for :meth:`labels`.
        """
        h = camera.height
        photo = [fit_height(self.photo, h)]
        if self.prediction.opts.mode == "both":
            photo.append(self._own_view(h))
        columns = [photo] + [self._model_column(m, camera) for m in self.models]
        headings = list(self.headings[:len(columns)])
        legend = self.prediction.opts.legend
        return compose(columns, headings, self.prediction.inp.classes, self.labels() if labels is None else labels,
                       title=self.title, legend=legend)

    def images(self, cameras: Iterable[Camera]) -> list[np.ndarray]:
        """The pictures of a sequence of views (an orbit), with one legend for all."""
        labels = self.labels()
        return [self.image(cam, labels) for cam in cameras]

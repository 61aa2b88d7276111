"""Prediction: any photo -> the image SSZ expects -> logits of a fruxel model.

SSZ sees the grid's own camera (SPEC section 8): an image of ``2^k W x 2^k H`` pixels whose horizontal field of
view is the grid's. A photo of another size and field of view is mapped onto it geometrically, about the
optical centre (the photo's centre):

* with its field of view given (``hfov``), geometry decides: a wider photo is cropped to the grid's view, a
  narrower one is padded (the model sees grey where the photo has nothing), in both directions;
* without it, the photo is taken as the grid's view and only its aspect is brought to ``H / W``: crop
  (``fit="crop"``, default) or pad (``fit="pad"``) rows or columns, centred;
* then it is resized to the model's image size (area averaging when shrinking).

Images are ``(h, w, 3)`` uint8 RGB arrays (rows down, columns right) until :func:`to_tensor`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterable, Iterator, Sequence

import numpy as np
import torch

from fruxel.errors import FruxelError

from .config import ModelConfig

PAD_VALUE = 128
"""Grey (uint8) the model sees where the photo has nothing."""
MAX_IMAGE_PIXELS = 1 << 28
"""Largest photo accepted, in pixels (a decompression-bomb bound)."""
MAX_FRAME_GROWTH = 16
"""A photo whose frame (the grid's view at the photo's scale) would hold more than this many times its pixels (and
the model image's) is framed at the model's scale instead (see :func:`prepare_image`)."""


class ImageError(FruxelError, ValueError):
    """An image that cannot be used; the message names the file and the problem."""


def load_image(path: str | os.PathLike[str]) -> np.ndarray:
    """A PNG, JPEG or other Pillow-readable photo as ``(h, w, 3)`` uint8 RGB, turned upright by its EXIF
    orientation; grey and alpha images become RGB (alpha over white would invent colours: it is dropped).

    Raises:
        ImageError: a missing or unreadable file, or one over :data:`MAX_IMAGE_PIXELS`.
    """
    from PIL import Image, ImageOps, UnidentifiedImageError

    p = os.fsdecode(path)
    if not os.path.exists(p):
        raise ImageError(f"{p}: no such file")
    if not os.path.isfile(p):
        raise ImageError(f"{p}: not a regular file")
    try:
        with Image.open(p) as im:
            if im.width * im.height > MAX_IMAGE_PIXELS:
                raise ImageError(f"{p}: {im.width}x{im.height} pixels is more than {MAX_IMAGE_PIXELS}")
            im = ImageOps.exif_transpose(im)
            rgb = np.asarray(im.convert("RGB"), dtype=np.uint8)
    except ImageError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as e:
        raise ImageError(f"{p}: not a readable image ({type(e).__name__}: {e})") from None
    if rgb.ndim != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ImageError(f"{p}: empty image")
    return np.ascontiguousarray(rgb)


def _crop_or_pad(img: np.ndarray, rows: int, cols: int) -> np.ndarray:
    """Centre ``img`` in a ``rows x cols`` frame: crop where it is larger, pad with :data:`PAD_VALUE` where
    smaller."""
    h, w = img.shape[:2]
    out = np.full((rows, cols, 3), PAD_VALUE, dtype=np.uint8)
    sy, sx = max(0, (h - rows) // 2), max(0, (w - cols) // 2)
    dy, dx = max(0, (rows - h) // 2), max(0, (cols - w) // 2)
    ch, cw = min(h, rows), min(w, cols)
    out[dy:dy + ch, dx:dx + cw] = img[sy:sy + ch, sx:sx + cw]
    return out


def prepare_image(img: np.ndarray, config: ModelConfig, hfov: float | None = None, fit: str = "crop"
                  ) -> np.ndarray:
    """A photo as the model's input image (see the module docstring).

    Args:
        img: ``(h, w, 3)`` uint8 RGB.
        config: the model's architecture (grid and image size).
        hfov: the photo's horizontal field of view, degrees; None takes the photo's width (crop) or its whole
            frame (pad) as the grid's view.
        fit: ``"crop"`` or ``"pad"``, how the aspect is matched when ``hfov`` is None.

    Returns:
        ``(2^k H, 2^k W, 3)`` uint8 RGB.

    Raises:
        ValueError: a wrong array, field of view or fit.
    """
    from PIL import Image

    if not isinstance(img, np.ndarray) or img.dtype != np.uint8 or img.ndim != 3 or img.shape[2] != 3:
        raise ValueError(f"image must be an (h, w, 3) uint8 array, got {getattr(img, 'dtype', type(img))} "
                         f"{getattr(img, 'shape', '')}")
    if fit not in ("crop", "pad"):
        raise ValueError(f"fit must be 'crop' or 'pad', got {fit!r}")
    grid = config.grid
    if hfov is not None and not (math.isfinite(hfov) and 0.0 < hfov < 180.0):
        raise ValueError(f"--hfov must be in (0, 180) degrees, got {hfov!r}")
    h, w = img.shape[:2]
    if hfov is None:
        # The photo is taken as the grid's view: the largest centred region of the grid's aspect (crop), or the
        # smallest frame of that aspect around the whole photo (pad).
        wide = w * grid.height >= h * grid.width
        if (fit == "crop") == wide:
            rows, cols = h, max(1, round(h * grid.width / grid.height))
        else:
            rows, cols = max(1, round(w * grid.height / grid.width)), w
    else:
        # Geometry decides: the grid's view spans x/z in [-tu, tu] and y/z in [-tv, tv]; the photo's focal length
        # in pixels follows from its field of view (square pixels). Outside the photo is padded, beyond the
        # grid's view cropped; ``fit`` plays no part.
        f = w / (2.0 * math.tan(math.radians(hfov) / 2.0))
        cols, rows = max(1, round(2.0 * grid.tu * f)), max(1, round(2.0 * grid.tv * f))
    out_h, out_w = config.image_size
    if rows * cols > MAX_FRAME_GROWTH * max(h * w, out_h * out_w):
        # A photo far narrower than the grid's view (a long lens): padding it at its own scale would need a huge
        # frame (1 degree of a 4000-pixel photo in a 60 degree grid: 264000^2 pixels), so it is shrunk to the
        # model's scale first and padded there: the same picture up to resampling.
        s = out_w / cols
        img = np.asarray(Image.fromarray(img).resize((max(1, round(w * s)), max(1, round(h * s))), Image.BOX))
        rows, cols = out_h, out_w
    framed = _crop_or_pad(img, rows, cols)
    resample = Image.BOX if rows >= out_h else Image.BILINEAR
    return np.asarray(Image.fromarray(framed).resize((out_w, out_h), resample), dtype=np.uint8)


def to_tensor(images: Sequence[np.ndarray], device: torch.device | str = "cpu") -> torch.Tensor:
    """``(h, w, 3)`` uint8 images of one size -> ``(B, 3, h, w)`` float32 in [0, 1] on ``device``."""
    t = torch.from_numpy(np.stack(images)).to(device)
    return t.permute(0, 3, 1, 2).float().div_(255.0).contiguous()


class Predictor:
    """Batched prediction with a trained generator.

    Args:
        generator: the model, in eval mode.
        config: its architecture.
        device: where to predict.
        batch: images per forward pass.
    """

    def __init__(self, generator: torch.nn.Module, config: ModelConfig, device: torch.device | str = "cpu",
                 batch: int = 8) -> None:
        self.device = torch.device(device)
        self.generator = generator.to(self.device).eval()
        self.config = config
        self.batch = max(1, int(batch))

    @torch.no_grad()
    def logits(self, images: torch.Tensor) -> torch.Tensor:
        """``(B, 3, h, w)`` float images -> ``(B, C, D, H, W)`` float32 logits (bfloat16 compute on CUDA)."""
        cuda = self.device.type == "cuda"
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=cuda):
            return self.generator(images.to(self.device)).logits.float()

    def predict(self, images: Iterable[np.ndarray]) -> Iterator[torch.Tensor]:
        """Logits ``(C, D, H, W)`` float32 of each prepared image (:func:`prepare_image`), in order."""
        pending: list[np.ndarray] = []
        for img in images:
            pending.append(img)
            if len(pending) == self.batch:
                yield from self.logits(to_tensor(pending, self.device))
                pending = []
        if pending:
            yield from self.logits(to_tensor(pending, self.device))


def default_model() -> str:
    """Path of the SSZ model shipped with fruxel (64^3 from 128^2), loaded when no checkpoint is given."""
    return str(os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", "ssz64.safetensors"))


def load_predictor(path: str | None = None, device: str | None = None, batch: int = 8) -> Predictor:
    """A :class:`Predictor` of a shipped model or training checkpoint (the shipped default when ``path`` is
    None), on ``device`` (CUDA when present)."""
    from .export import load_generator

    dev = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    gen, config, _ = load_generator(path or default_model(), device=dev)
    return Predictor(gen, config, dev, batch)



"""Prediction: any photo -> the image SSZ expects -> logits of a fruxel model.

SSZ sees the grid's own camera (conventions section 8): an image of ``2^k W x 2^k H`` pixels whose horizontal field of
view is the grid's. A photo of another size and field of view is mapped onto it geometrically, about the
optical centre (the photo's centre):

* with its field of view given (``hfov``), geometry decides: a wider photo is cropped to the grid's view, a
  narrower one is padded (the model sees grey where the photo has nothing), in both directions; ``fit`` plays no
  part, since enlarging the photo to fill the frame would change the field of view the model sees;
* without it, the photo is taken as the grid's view and only its aspect is brought to ``H / W``: crop
  (``fit="crop"``, default) or pad (``fit="pad"``) rows or columns, centred;
* then it is resized to the model's image size (area averaging when shrinking).

Grid columns whose centre ray falls on the padding rather than on the photo (:func:`frame_coverage`) are left
empty in the prediction (:func:`empty_uncovered`): the model sees grey there, and what it makes of it is not in
the photo.

Images are ``(h, w, 3)`` uint8 RGB arrays (rows down, columns right) until :func:`to_tensor`.
"""

from __future__ import annotations

import math
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

import numpy as np
import torch

from fruxel.errors import FruxelError
from fruxel.grid import FruxelGrid

from .models.registry import ModelConfig
from .rules import NO_RULES, InferenceRules, predict_logits

PAD_VALUE = 128
"""Grey (uint8) the model sees where the photo has nothing."""
MAX_IMAGE_PIXELS = 1 << 28
"""Largest photo accepted, in pixels (a decompression-bomb bound)."""


class ImageError(FruxelError, ValueError):
    """An image that cannot be used; the message names the file and the problem."""


def load_image(path: str | os.PathLike[str]) -> np.ndarray:
    """A PNG, JPEG or other Pillow-readable photo as ``(h, w, 3)`` uint8 RGB, turned upright by its EXIF
    orientation; grey and alpha images become RGB (alpha over white would invent colours: it is dropped). Grey of
    16 bits (PNG, TIFF) is scaled to 8 (``v / 257``), 32-bit float grey (TIFF) in [0, 1] by 255.

    Raises:
        ImageError: a missing or unreadable file, one over :data:`MAX_IMAGE_PIXELS`, or one whose pixels have no
            range to scale by (32-bit integers, floats outside [0, 1] or not finite).
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
            rgb = _as_rgb(im, p)
    except ImageError:
        raise
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as e:
        raise ImageError(f"{p}: not a readable image ({type(e).__name__}: {e})") from None
    if rgb.ndim != 3 or rgb.shape[0] < 1 or rgb.shape[1] < 1:
        raise ImageError(f"{p}: empty image")
    return np.ascontiguousarray(rgb)


def _as_rgb(im: Any, p: str) -> np.ndarray:
    """A Pillow image as ``(h, w, 3)`` uint8 RGB. Pillow's own conversion clips wide grey to 8 bits, which turns a
    16-bit PNG white and a float TIFF black; those are scaled here instead."""
    mode = im.mode
    # Pillow before 10 opened 16-bit grey PNGs as 32-bit "I"; a TIFF's "I" is a true 32-bit integer.
    if mode.startswith("I;16") or (mode == "I" and im.format == "PNG"):
        grey = np.rint(np.asarray(im, dtype=np.float32) / 257.0)
    elif mode == "F":
        v = np.asarray(im, dtype=np.float32)
        lo, hi = (float(v.min()), float(v.max())) if v.size else (0.0, 0.0)
        if not (np.isfinite(lo) and np.isfinite(hi) and 0.0 <= lo and hi <= 1.0):
            raise ImageError(f"{p}: 32-bit float pixels from {lo:g} to {hi:g}; fruxel reads float photos in [0, 1] "
                             "(or save it with 8 or 16 bits a channel)")
        grey = np.rint(v * 255.0)
    elif mode.startswith("I"):
        raise ImageError(f"{p}: 32-bit integer pixels have no range to scale them by; save the photo with 8 or 16 "
                         "bits a channel")
    else:
        return np.asarray(im.convert("RGB"), dtype=np.uint8)
    return np.repeat(np.clip(grey, 0, 255).astype(np.uint8)[..., None], 3, axis=2)


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


UNCOVERED_LOGIT = -1.0e4
"""The occupied classes' logit in a column the photo does not cover (:func:`empty_uncovered`): far below any the
network gives, within float16's range (stored logits are float16)."""


def empty_uncovered(logits: torch.Tensor, coverage: np.ndarray) -> torch.Tensor:
    """Leave the columns the photo does not cover empty (in place): their occupied classes' logits become
    :data:`UNCOVERED_LOGIT` and the empty class's 0. The model sees grey there, and what it makes of grey (a
    floor going on, a cabinet) is not in the photo.

    Args:
        logits: ``(..., C, D, H, W)`` float logits, channel 0 = empty, grid frame.
        coverage: ``(H, W)`` bool of :func:`frame_coverage`.

    Returns:
        ``logits``.
    """
    if coverage.all():
        return logits
    gone = torch.from_numpy(~np.asarray(coverage, dtype=bool)).to(logits.device)
    logits[..., 1:, :, gone] = UNCOVERED_LOGIT
    logits[..., 0, :, gone] = 0.0
    return logits


def _span(offset: int, length: int, frame: int, size: int) -> tuple[int, int]:
    """Output pixels ``[a, b)`` of ``size`` that hold frame pixels ``[offset, offset + length)`` of ``frame``:
    their own span rounded, or the one pixel nearest its centre when that span rounds to nothing."""
    a, b = round(offset * size / frame), round((offset + length) * size / frame)
    if b > a:
        return a, b
    a = min(size - 1, max(0, int((offset + length / 2) * size / frame)))
    return a, a + 1


def prepare_image(img: np.ndarray, config: ModelConfig, hfov: float | None = None, fit: str = "crop"
                  ) -> np.ndarray:
    """A photo as the model's input image (see the module docstring): :func:`frame_image` at the model's image
    size.

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
    return frame_image(img, config.grid, config.image_size, hfov, fit)


def to_tensor(images: Sequence[np.ndarray], device: torch.device | str = "cpu") -> torch.Tensor:
    """``(h, w, 3)`` uint8 images of one size -> ``(B, 3, h, w)`` float32 in [0, 1] on ``device``."""
    t = torch.from_numpy(np.stack(images)).to(device)
    return t.permute(0, 3, 1, 2).float().div_(255.0).contiguous()


PRECISIONS = ("bfloat16", "autocast")
"""How a :class:`Predictor` holds the network on CUDA: weights stored in bfloat16 (the default: no casts per call;
the batch norms' statistics are rounded to bfloat16), or float32 weights under bfloat16 autocast (every call casts
each weight again). How closely the two agree is measured in docs/experiments.md."""


class Predictor:
    """Batched prediction with a trained network and its inference rules (:func:`fruxel.train.rules.predict_logits`).

    On CUDA each input shape's forward pass (the network and the rules together) is captured once as a CUDA graph
    and replayed: at batch 1 the eager pass is bound by launching its kernels from Python, which the live robot
    demo pays every frame. With ``compile`` the captured pass is Inductor's (fused kernels; it takes a while to
    compile). Timings are in BENCHMARKS.md. Work that follows the logits (a shell, a ray cast) can join the same
    graph through :meth:`run`.

    Args:
        network: the model, in eval mode (moved to ``device``, and to bfloat16 with that precision, in place).
        config: its architecture.
        device: where to predict.
        batch: images per forward pass.
        graphs: replay CUDA graphs on CUDA (False: always the eager pass).
        compile: on CUDA, run the forward pass through ``torch.compile`` (Inductor, without its own CUDA graphs:
            the graphs here capture the compiled pass). Ignored on the CPU.
        precision: one of :data:`PRECISIONS`, on CUDA (the CPU predicts in float32).
        rules: the inference rules applied after the network (the model file's own: :func:`load_predictor`).

    Raises:
        ValueError: an unknown precision.
    """

    MAX_GRAPHS = 4
    """Captures kept at once (a batched run needs two: the full batches and the last one)."""

    def __init__(self, network: torch.nn.Module, config: ModelConfig, device: torch.device | str = "cpu",
                 batch: int = 8, graphs: bool = True, compile: bool = False, precision: str = "bfloat16",
                 rules: InferenceRules = NO_RULES) -> None:
        if precision not in PRECISIONS:
            raise ValueError(f"precision must be one of {', '.join(PRECISIONS)}, got {precision!r}")
        self.device = torch.device(device)
        cuda = self.device.type == "cuda"
        self.precision = precision if cuda else "float32"
        self.network = network.to(self.device).eval()
        if self.precision == "bfloat16":
            self.network.to(torch.bfloat16)
        self.config = config
        self.rules = rules
        self.batch = max(1, int(batch))
        self.graphs = bool(graphs) and cuda
        self.compiled = bool(compile) and cuda
        self._pass = torch.compile(self._eager) if self.compiled else self._eager
        self._graphs: dict[tuple[Any, ...], tuple[Any, torch.Tensor, Any]] = {}

    def _eager(self, images: torch.Tensor) -> torch.Tensor:
        if self.precision == "bfloat16":
            return predict_logits(self.network, images.to(torch.bfloat16), self.rules).float()
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "autocast"):
            return predict_logits(self.network, images, self.rules).float()

    def _forward(self, images: torch.Tensor, then: Callable[[torch.Tensor], Any] | None = None) -> Any:
        logits = self._pass(images)
        return logits if then is None else then(logits)

    @property
    def captured(self) -> int:
        """CUDA graphs held now, one per input shape and ``then`` (at most :attr:`MAX_GRAPHS`)."""
        return len(self._graphs)

    @torch.no_grad()
    def logits(self, images: torch.Tensor) -> torch.Tensor:
        """``(B, 3, h, w)`` float images -> ``(B, C, D, H, W)`` float32 logits under the rules (bfloat16 compute on
        CUDA)."""
        out = self.run(images)
        # A graph writes the same buffer on every replay: a caller keeps its own copy.
        return out.clone() if self.graphs else out

    @torch.no_grad()
    def run(self, images: torch.Tensor, then: Callable[[torch.Tensor], Any] | None = None) -> Any:
        """``then(logits)`` of a batch (the logits themselves without ``then``); on CUDA with graphs the forward
        pass and ``then`` are captured together, once per input shape and ``then``, and replayed.

        Args:
            images: ``(B, 3, h, w)`` float RGB in [0, 1].
            then: work on the ``(B, C, D, H, W)`` float32 logits that returns tensors (e.g. a ``kernels.shell``
                and ``kernels.first_hit`` of torch CUDA tensors). To be captured it must never wait for the GPU
                (no ``.item()``, no copy to the host, no size that depends on the data).

        Returns:
            What ``then`` returns. Replayed, these are the graph's own buffers: the next call with the same shape
            and ``then`` overwrites them (copy what you keep).
        """
        images = images.to(self.device)
        if not self.graphs:
            return self._forward(images, then)
        key = (tuple(images.shape), images.dtype, then)
        entry = self._graphs.get(key)
        if entry is None:
            entry = self._capture(images, then)
            if len(self._graphs) >= self.MAX_GRAPHS:
                self._graphs.pop(next(iter(self._graphs)))
            self._graphs[key] = entry
        graph, static_in, static_out = entry
        static_in.copy_(images)
        graph.replay()
        return static_out

    def _capture(self, images: torch.Tensor, then: Callable[[torch.Tensor], Any] | None
                 ) -> tuple[Any, torch.Tensor, Any]:
        static_in = images.clone()
        side = torch.cuda.Stream(self.device)
        side.wait_stream(torch.cuda.current_stream(self.device))
        with torch.cuda.stream(side):
            # Warm-up off the capture: Inductor compiles, cuDNN chooses its algorithms, Warp loads its modules and
            # the allocator settles.
            for _ in range(3 if self.compiled else 2):
                self._forward(static_in, then)
        torch.cuda.current_stream(self.device).wait_stream(side)
        graph = torch.cuda.CUDAGraph()
        with torch.cuda.graph(graph):
            static_out = self._forward(static_in, then)
        return graph, static_in, static_out

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


def share_cpu(threads: int | None = None) -> int:
    """Set torch's CPU threads for prediction: ``threads``, or half the usable cores (at least 1), leaving the rest
    to what runs beside the model (rendering, kernels, a simulator). torch's own default, a thread per core,
    stalls whenever another process takes a core, since its threads wait for each other at every operation
    (BENCHMARKS.md has the measurement).

    Returns:
        The number of threads set.
    """
    if threads is None:
        cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else (os.cpu_count() or 1)
        threads = max(1, cores // 2)
    torch.set_num_threads(int(threads))
    return int(threads)


def load_predictor(path: str | None = None, device: str | None = None, batch: int = 8, graphs: bool = True,
                   compile: bool = False, precision: str = "bfloat16", rules: InferenceRules | None = None
                   ) -> Predictor:
    """A :class:`Predictor` of a shipped model or training checkpoint, a file or a shipped model's name
    (:func:`fruxel.train.model_files.model_path`; the shipped default when ``path`` is None), on ``device`` (CUDA
    when present), with the file's inference rules unless ``rules`` are given; ``graphs``, ``compile`` and
    ``precision`` as :class:`Predictor`'s."""
    from .model_files import load_model

    dev = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    m = load_model(path, device=dev)
    return Predictor(m.network, m.config, dev, batch, graphs, compile, precision,
                     m.rules if rules is None else rules)

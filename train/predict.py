"""Prediction: any photo -> the image SSZ expects -> logits of a fruxel model.

SSZ sees the grid's own camera (conventions section 8). A photo of another size and field of view is brought onto that
view by :func:`frame_image` (:mod:`.framing`: cropped or padded about its centre by its field of view, or by its
aspect when the field of view is not given, then resized to the model's image size).

Grid columns whose centre ray falls on the padding rather than on the photo (:func:`frame_coverage`) are left
empty in the prediction (:func:`empty_uncovered`): the model sees grey there, and what it makes of it is not in
the photo.

Images are ``(h, w, 3)`` uint8 RGB arrays (rows down, columns right) until :func:`to_tensor`.
"""

from __future__ import annotations

import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from typing import Any

import numpy as np
import torch

from fruxel.errors import FruxelError

# The framing of photos lives in .framing (numpy and Pillow only, for the simulator too); the commands import it
# from here.
from .framing import PAD_VALUE as PAD_VALUE
from .framing import frame_coverage as frame_coverage
from .framing import frame_image as frame_image
from .models.registry import ModelConfig
from .rules import NO_RULES, InferenceRules, predict_logits

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

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

import math
import os
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fruxel.errors import ConfigError, FruxelError

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


FOCAL_35MM_BOUNDS = (8.0, 400.0)
"""Plausible 35 mm-equivalent focal lengths, millimetres (a 132-degree fisheye to a long telephoto): an EXIF value
outside them is taken for a mistake and ignored (:func:`exif_focal_35mm`)."""
FILM_WIDTH_MM = 36.0
"""The long side of 35 mm film, millimetres: ``hfov = 2 atan(36 / (2 f35))`` across a landscape photo."""


def exif_focal_35mm(path: str | os.PathLike[str]) -> tuple[float | None, str | None]:
    """The photo's 35 mm-equivalent focal length from its EXIF (``FocalLengthIn35mmFilm``, tag 0xA405 of the Exif
    IFD), millimetres.

    Returns:
        ``(focal, None)``; ``(None, None)`` when the file has none (or no EXIF); ``(None, why)`` when it has one
        outside :data:`FOCAL_35MM_BOUNDS` or unreadable, ``why`` a sentence to warn with.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(os.fsdecode(path)) as im:
            value = im.getexif().get_ifd(0x8769).get(0xA405)
    except (UnidentifiedImageError, OSError, ValueError, SyntaxError):
        return None, None
    if value is None:
        return None, None
    try:
        f = float(value)
    except (TypeError, ValueError):
        return None, f"its EXIF 35 mm focal length {value!r} is not a number"
    lo, hi = FOCAL_35MM_BOUNDS
    if not (math.isfinite(f) and lo <= f <= hi):
        return None, f"its EXIF 35 mm focal length {f:g} mm is outside {lo:g}-{hi:g} mm"
    return f, None


def hfov_from_focal_35mm(focal: float, width: int, height: int) -> float:
    """Horizontal field of view, degrees, of an upright ``width x height`` photo with 35 mm-equivalent focal length
    ``focal`` mm: its long side spans the film's 36 mm, so ``2 atan(36 / (2 f))`` across a landscape photo and
    ``2 atan(36 w / h / (2 f))`` across a portrait one."""
    across = FILM_WIDTH_MM * width / max(width, height)
    return math.degrees(2.0 * math.atan(across / (2.0 * focal)))


def centre_intrinsics(img: np.ndarray, intrinsics: Sequence[float]) -> tuple[np.ndarray, float]:
    """A photo of pinhole intrinsics ``(fx, fy, cx, cy)`` (pixels) as one that :func:`frame_image` takes with a
    field of view: its rows stretched by ``fx / fy`` (square pixels), then cropped to the largest window centred
    on the principal point (so nothing outside the photo is made up).

    Args:
        img: ``(h, w, 3)`` uint8 RGB.
        intrinsics: ``fx, fy > 0``; ``(cx, cy)`` inside the photo.

    Returns:
        ``(image (h', w', 3) uint8, hfov degrees)`` of the centred photo.

    Raises:
        ValueError: intrinsics that are not four finite numbers, a focal length <= 0, or a principal point that
            leaves no window of a pixel around it.
    """
    from PIL import Image

    fx, fy, cx, cy = (float(v) for v in intrinsics)
    h, w = img.shape[:2]
    if not all(math.isfinite(v) for v in (fx, fy, cx, cy)) or min(fx, fy) <= 0:
        raise ValueError(f"intrinsics must be finite with fx, fy > 0, got {fx:g},{fy:g},{cx:g},{cy:g}")
    if fx != fy:
        rows = max(1, round(h * fx / fy))
        img = np.asarray(Image.fromarray(img).resize((w, rows), Image.BILINEAR), dtype=np.uint8)
        cy, h = cy * rows / h, rows
    half_w, half_h = min(cx, w - cx), min(cy, h - cy)
    if half_w < 0.5 or half_h < 0.5:
        raise ValueError(f"the principal point ({cx:g}, {cy:g}) must lie inside the {w}x{h} photo, away from its "
                         "edges")
    x0, y0 = round(cx - half_w), round(cy - half_h)
    x1, y1 = max(x0 + 1, round(cx + half_w)), max(y0 + 1, round(cy + half_h))
    return np.ascontiguousarray(img[y0:y1, x0:x1]), math.degrees(2.0 * math.atan((x1 - x0) / (2.0 * fx)))


@dataclass(frozen=True)
class CameraPrior:
    """What is known of a photo's camera besides the image, for a model that reads it
    (``SSZConfig.camera_inputs``). Angles follow the simulator's cameras (:mod:`fruxel.train.sim.cameras`): pitch
    positive looking down, roll positive clockwise as seen from behind the camera (its right side down). None is
    unknown. The gravity direction needs the pitch (a roll alone is taken with pitch 0 too; the roll defaults to
    0, a level camera, when only the pitch is given); a height means something only along gravity, so a height
    without pitch or roll is refused.

    Raises:
        ConfigError: on construction, a value that is not finite or outside its bounds, or a height without an
            angle (the message names the field).
    """

    pitch: float | None = None
    """Degrees, in (-90, 90), positive looking down."""
    roll: float | None = None
    """Degrees, in (-90, 90), positive clockwise as seen from behind the camera."""
    height: float | None = None
    """Height of the optical centre above the floor, metres, in (0, 10]."""

    def __post_init__(self) -> None:
        for name, lo, hi in (("pitch", -90.0, 90.0), ("roll", -90.0, 90.0), ("height", 0.0, 10.0)):
            v = getattr(self, name)
            if v is None:
                continue
            ok = isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) and lo < v and (
                v <= hi if name == "height" else v < hi)
            if not ok:
                bounds = "(0, 10] metres" if name == "height" else f"({lo:g}, {hi:g}) degrees"
                raise ConfigError(f"camera {name} must be a number in {bounds}, got {v!r}")
            object.__setattr__(self, name, float(v))
        if self.height is not None and not self.knows_gravity:
            raise ConfigError("camera height needs the pitch (or roll): a model reads the height along gravity")

    @property
    def knows_gravity(self) -> bool:
        """Whether the gravity direction is known (a pitch or a roll given)."""
        return self.pitch is not None or self.roll is not None

    def gravity(self) -> np.ndarray | None:
        """``(3,)`` float64 unit gravity direction in the camera frame (OpenCV axes), or None when unknown: the
        simulator's own pose of a camera at this pitch and roll (:func:`fruxel.train.sim.robot.camera_poses`,
        :func:`fruxel.train.sim.cameras.roll_poses`, :func:`~fruxel.train.sim.cameras.gravity_in_camera`)."""
        if not self.knows_gravity:
            return None
        from .sim.cameras import gravity_in_camera, roll_poses
        from .sim.robot import CameraMount, camera_poses

        pose = camera_poses(np.zeros((1, 2)), np.zeros(1), CameraMount(tilt=self.pitch or 0.0))
        return gravity_in_camera(roll_poses(pose, self.roll or 0.0)[0])

    def camera_input(self, batch: int, device: torch.device | str = "cpu") -> Any:
        """The :class:`~fruxel.train.models.conditioning.CameraInput` of ``batch`` photos of this camera."""
        from .models.conditioning import CameraInput

        g = self.gravity()
        known = [[g is not None, self.height is not None]] * batch
        return CameraInput.of(np.tile(np.zeros(3) if g is None else g, (batch, 1)),
                              np.full(batch, self.height or 0.0), known, device)


UNKNOWN_CAMERA = CameraPrior()
"""Nothing known of the camera: a photo alone."""


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
        camera: what is known of the photos' camera, for a model that reads it (``config.reads_camera``; other
            models ignore it); None: nothing known. Fixed for the predictor's life (the CUDA graphs hold it).

    Raises:
        ValueError: an unknown precision.
    """

    MAX_GRAPHS = 4
    """Captures kept at once (a batched run needs two: the full batches and the last one)."""

    def __init__(self, network: torch.nn.Module, config: ModelConfig, device: torch.device | str = "cpu",
                 batch: int = 8, graphs: bool = True, compile: bool = False, precision: str = "bfloat16",
                 rules: InferenceRules = NO_RULES, camera: CameraPrior | None = None) -> None:
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
        self.camera = camera if camera is not None else UNKNOWN_CAMERA
        self._cameras: dict[int, Any] = {}
        self._pass = torch.compile(self._eager) if self.compiled else self._eager
        self._graphs: dict[tuple[Any, ...], tuple[Any, torch.Tensor, Any]] = {}

    def _camera_input(self, batch: int) -> Any:
        """The network's camera input for ``batch`` photos (made once per batch size, on the device, outside any
        graph capture), or None for a model that reads no camera."""
        if not self.config.reads_camera:
            return None
        if batch not in self._cameras:
            self._cameras[batch] = self.camera.camera_input(batch, self.device)
        return self._cameras[batch]

    def _eager(self, images: torch.Tensor, camera: Any = None) -> torch.Tensor:
        if self.precision == "bfloat16":
            return predict_logits(self.network, images.to(torch.bfloat16), self.rules, camera=camera).float()
        with torch.autocast(self.device.type, dtype=torch.bfloat16, enabled=self.precision == "autocast"):
            return predict_logits(self.network, images, self.rules, camera=camera).float()

    def _forward(self, images: torch.Tensor, then: Callable[[torch.Tensor], Any] | None = None) -> Any:
        logits = self._pass(images, self._camera_input(images.shape[0]))
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
        self._camera_input(images.shape[0])  # made before a capture: a graph cannot copy from the host
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
                   compile: bool = False, precision: str = "bfloat16", rules: InferenceRules | None = None,
                   camera: CameraPrior | None = None) -> Predictor:
    """A :class:`Predictor` of a shipped model or training checkpoint, a file or a shipped model's name
    (:func:`fruxel.train.model_files.model_path`; the shipped default when ``path`` is None), on ``device`` (CUDA
    when present), with the file's inference rules unless ``rules`` are given; ``graphs``, ``compile``,
    ``precision`` and ``camera`` (what is known of the photos' camera) as :class:`Predictor`'s."""
    from .model_files import load_model

    dev = torch.device(device or ("cuda" if torch.cuda.is_available() else "cpu"))
    m = load_model(path, device=dev)
    return Predictor(m.network, m.config, dev, batch, graphs, compile, precision,
                     m.rules if rules is None else rules, camera)

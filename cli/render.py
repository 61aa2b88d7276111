"""``fruxel-render``: show a fruxel model as a trapezoid mesh (pyrender) or a ray-cast image, or run Table 1.

Usage::

    fruxel-render [MODEL] [--backend {warp,opencl}] [--device cpu|cuda[:N]] [--mode {mesh,raycast,both}]
                  [--shell {none,own,poses,view}] [--mesh {full,culled,greedy}] [--size WxH] [--camera JSON]
                  [--grid N|WxHxD [--z-near Z] [--z-far Z] [--hfov DEG]] [--out DIR] [--orbit N [--video {gif,mp4}]]
                  [--export FILE.glb|FILE.ply] [--view] [--benchmark]
                  [PHOTO options: --checkpoint FILE --truth FILE.npz --fit crop|pad --intrinsics FX,FY,CX,CY
                   --pitch DEG --roll DEG --height M]

MODEL (default: the bundled sample room, ``fruxel.data.SAMPLE_ROOM``) is one of

* a photo (``.png``, ``.jpg``, ``.webp``, ``.bmp``, ``.tif``, ``.gif``, or any file that starts like one): SSZ
  predicts its model (``--checkpoint``, default ``ssz64-any``, :func:`fruxel.train.predict.load_predictor`), after
  the photo is brought to the view of the model's grid camera (``--hfov``: the photo's horizontal field of view, else
  ``--intrinsics``, else its EXIF 35 mm focal length, else the grid's; ``--fit``: how its aspect is matched,
  :func:`fruxel.train.predict.frame_image`; :func:`fruxel.cli.common.photo_view`), and with what is known of its
  camera (``--pitch``, ``--roll``, ``--height``) for a model that reads it. The picture then shows the photo, the
  predicted model and, with ``--truth FILE.npz`` (a fruxel model on the same grid, its classes among the model's,
  matched by name), the ground truth, each as the mesh, the ray cast or both
  (:class:`fruxel.render.compare.PhotoComparison`), from one view fitted to what the models hold, and the own-view
  first-hit accuracy against the truth in its title. ``--orbit``, ``--export``, ``--view`` and ``--benchmark`` work on
  the prediction;

* a fruxel model file ``.npz`` (:func:`fruxel.load`);
* a logits file ``.npz`` (:func:`fruxel.save_logits`, :func:`fruxel.load_logits`): logits ``(C, D, H, W)`` with
  their grid and classes, the format predictions are written in;
* a bare logits tensor ``(C, D, H, W)`` or ``(1, C, D, H, W)`` (NCDHW, channel 0 = empty) saved as ``.npy``
  (read with ``allow_pickle=False``) or ``.pt`` (``torch.load(weights_only=True)``). A bare tensor needs its
  grid, from (first found) ``--grid WxHxD`` (with ``--z-near``, ``--z-far`` and ``--hfov``, whose defaults are
  the simulator's grid), a ``.pt`` dict ``{"logits": tensor, "grid": {...}}``, or a JSON sidecar beside the
  file (``X.npy`` + ``X.json``) holding a grid dict (:meth:`fruxel.FruxelGrid.to_dict`) or ``{"grid": {...},
  "classes": {...}}``. Classes come from the ``.pt`` dict's or the sidecar's ``"classes"``
  (:meth:`fruxel.ClassTable.to_dict`), else the default classes (cut or extended to C).

What is drawn is described in :mod:`fruxel.render.frames`: shell sources (``--shell``), meshing (``--mesh``),
the default oblique view and orbits (``--orbit N``: one turn, into a GIF, or an MP4 with ``imageio-ffmpeg``).
The viewing camera is ``--camera`` (a :meth:`fruxel.Camera.to_json` text, or a file holding one; its own image
size wins over ``--size``), else the default view.

Outputs go to ``--out`` (default ``out/``): ``NAME_mesh.png``, ``NAME_raycast.png``, ``NAME_both.png`` (mesh
and ray cast side by side) or ``NAME_MODE_orbit.gif|mp4``, written atomically; NAME is the model file's (or the
photo's) stem.
Every path written is printed. Errors are one line ``fruxel-render: error: ...`` on stderr with exit status 2
(:func:`fruxel.cli.common.run`); what needs no model is checked before any work (:func:`check_render_inputs`: the
photo's header, ``--camera``, the output files, and whether a model file's grid can be drawn in the memory
available, :data:`RENDER_BYTES_PER_CELL`). ``--view`` opens pyrender's interactive Viewer instead (it needs a display).
"""

from __future__ import annotations

import argparse
import json
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fruxel.errors import FruxelError

from .common import (
    OneLineParser,
    UsageError,
    add_camera_options,
    add_grid_options,
    camera_prior,
    check_output_file,
    check_output_folder,
    check_photo,
    config_option,
    config_values,
    device_name,
    grid_from_args,
    grid_options_given,
    image_size,
    note_unread_camera,
    one_line,
    path_name,
    photo_view,
    positive_int,
    run,
    unit_fraction,
    write_outputs,
)

if TYPE_CHECKING:
    from fruxel import Camera, ClassTable, FruxelGrid
    from fruxel.render.frames import RenderInput
    from fruxel.render.table1 import Table1Config

PROG = "fruxel-render"
BACKENDS = ("warp", "opencl")
FITS = ("crop", "pad")
"""How a photo's aspect is matched to the grid's (:func:`fruxel.train.predict.frame_image`); the first is the
default."""
PHOTO_SIZE = (480, 360)
"""Size ``(width, height)`` in pixels of each model panel of a photo's picture."""
PHOTO_DISPLAY = 512
"""Width in pixels at which the photo is framed to the grid's view for its panel (scaled to the panels' height)."""
VIDEO_FORMATS = ("gif", "mp4")
VIDEO_FORMATS_DEFAULT = "gif"


class InputError(FruxelError, ValueError):
    """A MODEL or ``--camera`` file that cannot be used, or an option value that does not fit it."""


# ---------------------------------------------------------------------------------------------------- parsing
def _default_grid() -> FruxelGrid:
    from fruxel.train.sim.config import DEFAULT_GRID

    return DEFAULT_GRID


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (no heavy imports: ``--help`` must be instant)."""
    from fruxel.render.frames import DEFAULT_SIZE, MESHINGS, MODES, SHELLS, RenderOptions
    from fruxel.render.table1 import Table1Config

    p = OneLineParser(
        prog=PROG,
        description="Render a fruxel model: a trapezoid mesh of what the camera sees (pyrender), a ray-cast image "
        "(first_hit), or both; or measure Table 1 (--benchmark).",
        epilog="MODEL may be a .npz fruxel model or logits file (fruxel.save_logits), or a bare logits tensor "
        "(C,D,H,W) in .npy/.pt, which takes its grid from --grid, a .pt dict {'logits', 'grid'} or a JSON sidecar "
        "X.json beside X.npy. Default view: "
        "oblique, 30 deg right and 35 deg above the grid camera's side, fitted to the model's occupied cells (to "
        "the frustum with --frustum or when the model is empty).",
    )
    p.add_argument("model", nargs="?", metavar="MODEL",
                   help="model or logits .npz, a logits tensor .npy/.pt, or a photo (.png, .jpg, ...) to predict a "
                   "model from (default: the sample room)")
    config_option(p, RenderOptions, "backend", choices=BACKENDS)
    config_option(p, RenderOptions, "device", type=device_name, metavar="cpu|cuda[:N]")
    config_option(p, RenderOptions, "mode", choices=MODES)
    config_option(p, RenderOptions, "shell", choices=SHELLS,
                  help="cells to show: none (all), own (what the grid camera sees), poses (M cameras around the "
                  "grid), view (what the viewer sees); default: own for the mesh, none for the ray cast")
    config_option(p, RenderOptions, "poses", type=positive_int, metavar="M")
    config_option(p, RenderOptions, "meshing", "--mesh", choices=MESHINGS)
    config_option(p, RenderOptions, "shading", choices=("lit", "flat"))
    config_option(p, RenderOptions, "fog")
    config_option(p, RenderOptions, "legend")
    config_option(p, RenderOptions, "frustum")
    config_option(p, RenderOptions, "threshold", type=unit_fraction, metavar="T")
    p.add_argument("--size", type=image_size, default=None, metavar="WxH",
                   help=f"image size in pixels (default: {DEFAULT_SIZE[0]}x{DEFAULT_SIZE[1]}, or --camera's; for a "
                   f"photo, each model panel's, default {PHOTO_SIZE[0]}x{PHOTO_SIZE[1]}); up to "
                   "2^28 pixels, large images drawn in tiles at about 8 bytes a pixel of memory (16000x16000: 2-3 GB)")
    p.add_argument("--camera", default=None, metavar="JSON", help="viewing camera: Camera JSON text or a file")
    add_grid_options(p, _default_grid(), size_default=False,
                     what="of a bare logits tensor; with --benchmark, N for an N^3 room",
                     hfov_help="for a photo MODEL, the photo's horizontal field of view (default: the model grid's)")
    p.add_argument("--out", type=path_name, default=None, metavar="DIR|FILE",
                   help=f"output folder (default {DEFAULT_OUT}/), or the file itself when it ends in an image or "
                   "video suffix (.png, .jpg, ...; .gif, .mp4 with --orbit)")
    p.add_argument("--orbit", type=positive_int, default=None, metavar="N",
                   help="render an N-frame orbit around the model into a video")
    p.add_argument("--video", choices=VIDEO_FORMATS, default=None,
                   help=f"orbit format when --out is a folder (default {VIDEO_FORMATS_DEFAULT}; mp4 needs "
                   "imageio-ffmpeg)")
    p.add_argument("--fps", type=positive_int, default=12, help="orbit frames per second (default 12)")
    p.add_argument("--export", type=path_name, default=None, metavar="FILE",
                   help="also write the mesh to FILE.glb (glTF's frame, +Y up, as glTF viewers expect) or FILE.ply "
                   "(the grid frame: OpenCV axes, y down; with face labels)")
    p.add_argument("--view", action="store_true", help="open pyrender's interactive Viewer (needs a display)")
    ph = p.add_argument_group("a photo MODEL (predicted with SSZ)")
    ph.add_argument("--checkpoint", type=Path, default=None, metavar="FILE",
                    help="the SSZ model: a shipped .safetensors file, a training checkpoint, or a model shipped with "
                    "fruxel by name: ssz64-any (the default: 64^3 cells from 256x256 images from any camera; give "
                    "--pitch, --roll, --height when known), ssz64 (64^3 cells, the robot's mount) or ssz128 (ssz64 "
                    "at 128^3 cells from 512x512)")
    ph.add_argument("--truth", type=Path, default=None, metavar="FILE.npz",
                    help="the photo's ground truth, a fruxel model on the prediction's grid whose classes are among "
                    "the model's (matched by name): adds its column and the own-view first-hit accuracy")
    ph.add_argument("--fit", choices=FITS, default=None,
                    help="without --hfov, how a photo of another aspect than the grid's is matched: crop (default; a "
                    "centred crop of the grid's aspect) or pad (grey bands); with --hfov geometry alone decides")
    add_camera_options(ph, hfov=False)
    b = p.add_argument_group("Table 1 (--benchmark)")
    b.add_argument("--benchmark", action="store_true", help="measure Table 1 (per-frame model updates)")
    config_option(b, Table1Config, "frames", type=positive_int)
    b.add_argument("--backends", default=None, metavar="LIST",
                   help="ray-cast rows, comma-separated, e.g. warp,opencl or warp-cuda (default: "
                   f"{','.join(Table1Config.raycast_backends)})")
    return p


# ---------------------------------------------------------------------------------------------------- input
LOGITS_DTYPES = ("float16", "float32", "float64")
"""dtypes of a bare logits tensor (numpy or torch), as the kernels take them."""
MAX_CAMERA_BYTES = 1 << 20
"""Largest ``--camera`` file read: a camera's JSON is a few hundred bytes."""


def _named(source: str, what: str | None, make: Any, value: Any) -> Any:
    """``make(value)``, with any fruxel error re-raised as one line naming ``source`` (and ``what``)."""
    try:
        return make(value)
    except FruxelError as e:
        raise InputError(f"{source}: {what + ': ' if what else ''}{e}") from None


def _classes_for(n_channels: int, given: Any, source: str) -> ClassTable:
    from fruxel import DEFAULT_CLASSES, ClassTable

    if given is not None:
        table = _named(source, "classes", ClassTable.from_dict, given)
        if len(table) != n_channels:
            raise InputError(f"{source}: the class table has {len(table)} classes but the logits have {n_channels} "
                             "channels")
        return table
    if n_channels <= len(DEFAULT_CLASSES):
        return ClassTable(DEFAULT_CLASSES.names[:n_channels], DEFAULT_CLASSES.colours[:n_channels])
    extra = [f"class {c}" for c in range(len(DEFAULT_CLASSES), n_channels)]
    return DEFAULT_CLASSES.extended(*extra)


def _read_sidecar(path: Path) -> tuple[Any, Any, str]:
    """The grid and classes dicts of ``X.json`` beside ``X.npy`` (None where missing) and the sidecar's name."""
    side = path.with_suffix(".json")
    if not side.is_file():
        return None, None, str(side)
    try:
        meta = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise InputError(f"{side}: cannot read the grid sidecar: {one_line(e)}") from None
    if isinstance(meta, dict) and "grid" in meta:
        return meta["grid"], meta.get("classes"), str(side)
    return meta, None, str(side)


def _torch_problem(e: BaseException) -> str:
    """Why ``torch.load(weights_only=True)`` refused a file, in fruxel's words."""
    import pickle

    text = re.sub(r"\x1b\[[0-9;]*m", "", str(e))
    if isinstance(e, pickle.UnpicklingError) or "weights only load failed" in text.lower():
        # torch's own message goes on to suggest weights_only=False, which would run the file's code.
        return ("refused: it holds Python objects that only unpickling could load, and fruxel never unpickles a "
                "file; save a tensor, or a dict of tensors and plain values")
    first = text.strip().splitlines()[0] if text.strip() else type(e).__name__
    return f"cannot read it ({first})"


def _load_tensor(path: Path) -> tuple[Any, Any, Any]:
    """The logits of a ``.npy`` / ``.pt`` file and the grid / classes dicts a ``.pt`` dict carries."""
    if path.suffix.lower() == ".npy":
        import numpy as np

        try:
            return np.load(path, allow_pickle=False), None, None
        except (OSError, ValueError, EOFError) as e:
            raise InputError(f"{path}: cannot read logits: {one_line(e)}") from None
    try:
        import torch
    except ImportError:
        raise InputError(f"{path}: reading .pt files needs torch: pip install 'fruxel[train]'") from None
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for a damaged or unsafe file
        problem = _torch_problem(e)
        raise InputError(f"{path}: {problem}") from None
    grid = classes = None
    if isinstance(obj, dict):
        if "logits" not in obj:
            raise InputError(f"{path}: holds a dict without 'logits' (keys: {sorted(map(str, obj))})")
        obj, grid, classes = obj["logits"], obj.get("grid"), obj.get("classes")
        what = "its 'logits' entry is"
    else:
        what = "holds"
    if not isinstance(obj, torch.Tensor):
        raise InputError(f"{path}: {what} a {type(obj).__name__}, expected a logits tensor (C, D, H, W), alone or "
                         "as a dict {'logits': tensor, 'grid': {...}, 'classes': {...}}")
    return obj, grid, classes


def load_input(model: str | None, grid: FruxelGrid | None = None) -> RenderInput:
    """Read MODEL (see the module docstring).

    Args:
        model: the file name, None for the sample room.
        grid: the grid of a bare logits tensor (``--grid``), None to take it from the file or its sidecar.

    Raises:
        FruxelFileError: a missing or invalid ``.npz`` model or logits file.
        InputError: a missing, unreadable or misshapen tensor file, no grid for it, or an invalid grid or class
            table in it; the message names the file.
        UsageError: ``grid`` for a file that carries its own.
    """
    import numpy as np

    import fruxel
    from fruxel.io import file_kind, load_logits
    from fruxel.render.frames import RenderInput
    from fruxel.render.shading import to_numpy

    if model is None:
        from fruxel.data import SAMPLE_ROOM

        m = fruxel.load(SAMPLE_ROOM)
        return RenderInput(np.ascontiguousarray(m.labels), m.grid, m.classes, SAMPLE_ROOM.stem)
    path = Path(model)
    suffix = path.suffix.lower()
    if suffix not in MODEL_SUFFIXES:
        raise InputError(f"{path}: unknown model file type: expected .npz (model or logits file), .npy / .pt "
                         "(logits tensor) or a photo (.png, .jpg, ...)")
    if suffix == ".npz":
        if grid is not None:
            raise UsageError(f"--grid describes a bare logits tensor (.npy / .pt); {path} carries its grid")
        if file_kind(path) == "logits":
            lf = load_logits(path)
            return RenderInput(lf.logits[None], lf.grid, lf.classes, path.stem)
        m = fruxel.load(path)
        return RenderInput(np.ascontiguousarray(m.labels), m.grid, m.classes, path.stem)
    if not path.is_file():
        raise InputError(f"{path}: {'is a folder, not a file' if path.is_dir() else 'no such file'}")
    tensor, grid_dict, classes_dict = _load_tensor(path)
    side_grid, side_classes, side = _read_sidecar(path)
    if grid is None:
        if grid_dict is not None:
            grid = _named(str(path), "grid", fruxel.FruxelGrid.from_dict, grid_dict)
        elif side_grid is not None:
            grid = _named(side, "grid", fruxel.FruxelGrid.from_dict, side_grid)
        else:
            raise InputError(f"{path}: a bare tensor needs its grid: give --grid WxHxD (with --z-near, --z-far, "
                             f"--hfov) or a sidecar {side}")
    shape = tuple(int(s) for s in tensor.shape)
    if len(shape) == 4:
        tensor = tensor[None]
    elif not (len(shape) == 5 and shape[0] == 1):
        raise InputError(f"{path}: logits must have shape (C, D, H, W) or (1, C, D, H, W), got {shape}")
    kind = str(tensor.dtype).removeprefix("torch.")
    if kind not in LOGITS_DTYPES:
        raise InputError(f"{path}: logits must be float16, float32 or float64, got dtype {kind}")
    if tuple(tensor.shape[2:]) != grid.shape:
        raise InputError(f"{path}: logits have (D, H, W) = {tuple(tensor.shape[2:])} but the grid has {grid.shape}")
    if not np.all(np.isfinite(to_numpy(tensor))):
        raise InputError(f"{path}: the logits contain NaN or infinite values")
    if classes_dict is not None:
        classes = _classes_for(int(tensor.shape[1]), classes_dict, str(path))
    else:
        classes = _classes_for(int(tensor.shape[1]), side_classes, side)
    return RenderInput(tensor, grid, classes, path.stem)


MODEL_SUFFIXES = (".npz", ".npy", ".pt", ".pth")
"""Suffixes (lower case) of model, logits and tensor files."""
PHOTO_SUFFIXES = (".png", ".jpg", ".jpeg", ".webp", ".bmp", ".tif", ".tiff", ".gif")
"""Suffixes (lower case) of photos."""
PHOTO_MAGIC = (b"\x89PNG\r\n\x1a\n", b"\xff\xd8\xff", b"GIF87a", b"GIF89a", b"BM", b"II*\x00", b"MM\x00*")
"""First bytes of PNG, JPEG, GIF, BMP and TIFF files (WebP: ``RIFF????WEBP``)."""


def is_photo(model: str | None) -> bool:
    """True when MODEL names a photo: a photo suffix (:data:`PHOTO_SUFFIXES`), or a file of another suffix (not a
    model's) that starts like an image (:data:`PHOTO_MAGIC`)."""
    if model is None:
        return False
    path = Path(model)
    suffix = path.suffix.lower()
    if suffix in MODEL_SUFFIXES:
        return False
    if suffix in PHOTO_SUFFIXES:
        return True
    try:
        with open(path, "rb") as f:
            head = f.read(16)
    except OSError:
        return False
    return head.startswith(PHOTO_MAGIC) or (head[:4] == b"RIFF" and head[8:12] == b"WEBP")


@dataclass(frozen=True)
class Photo:
    """A photo MODEL after prediction: what its picture shows besides the predicted model."""

    framed: Any
    """``(h, w, 3)`` uint8 RGB: the photo framed to the view of the grid's camera, :data:`PHOTO_DISPLAY` wide."""
    truth: RenderInput | None
    """The ``--truth`` model, or None."""
    title: str
    """The picture's title: the photo, the model, where and how fast it predicted, and the own-view accuracy."""


def _check_photo_options(args: argparse.Namespace, photo: bool) -> None:
    """Refuse options that do not fit a photo MODEL, or photo options without one."""
    import math

    if not photo:
        given = [flag for flag, v in (("--checkpoint", args.checkpoint), ("--truth", args.truth),
                                      ("--fit", args.fit), ("--pitch", args.pitch), ("--roll", args.roll),
                                      ("--height", args.height), ("--intrinsics", args.intrinsics))
                 if v is not None]
        if given:
            raise UsageError(f"{', '.join(given)}: only for a photo MODEL (.png, .jpg, ...)")
        return
    grid = [g for g in grid_options_given(args) if g != "--hfov"]
    if grid:
        raise UsageError(f"{', '.join(grid)}: the grid options describe a bare logits tensor; a photo is predicted "
                         "on the SSZ model's own grid")
    if args.hfov is not None and not (math.isfinite(args.hfov) and 0.0 < args.hfov < 180.0):
        raise UsageError(f"--hfov {args.hfov:g}: a photo's horizontal field of view must be in (0, 180) degrees")


def _describe_grid(g: FruxelGrid) -> str:
    return f"{g.width}x{g.height}x{g.depth} cells, {g.z_near:g}-{g.z_far:g} m, {g.hfov:g} degrees"


def _own_view_accuracy(pred: Any, truth: Any) -> float | None:
    """Own-view first-hit accuracy (conventions section 9), percent: ``(1, C, D, H, W)`` logits against ``(D, H, W)``
    labels; None when the truth's own view hits nothing."""
    import numpy as np
    import torch

    from fruxel.train.eval.metrics import first_surface

    p = first_surface(torch.as_tensor(pred).argmax(dim=1).cpu())[0]
    t = first_surface(torch.from_numpy(np.array(truth, dtype=np.int64))[None])[0]
    hit = t != 0
    return 100.0 * float(((p == t) & hit).sum()) / float(hit.sum()) if bool(hit.any()) else None


def load_photo(args: argparse.Namespace) -> tuple[RenderInput, Photo]:
    """Predict the model of a photo MODEL (see the module docstring).

    Returns:
        The prediction (logits ``(1, C, D, H, W)`` float32, on the prediction's device) and the photo's
        :class:`Photo`.

    Raises:
        ImageError: an unreadable photo. ModelFileError: an unusable ``--checkpoint``. FruxelFileError,
        InputError: an unusable ``--truth``. UsageError: options that do not fit a photo.
    """
    import time

    import numpy as np

    import fruxel
    from fruxel.classes import ClassTableError
    from fruxel.render.frames import RenderInput
    from fruxel.train.model_files import model_path
    from fruxel.train.predict import (
        empty_uncovered,
        frame_coverage,
        frame_image,
        load_image,
        load_predictor,
        share_cpu,
        to_tensor,
    )

    _check_photo_options(args, True)
    prior = camera_prior(args)
    path = Path(args.model)
    image = load_image(path)
    truth = None
    if args.truth is not None:
        t = fruxel.load(args.truth)
        truth = RenderInput(np.ascontiguousarray(t.labels), t.grid, t.classes, args.truth.stem)
    checkpoint = model_path(args.checkpoint)
    predictor = load_predictor(checkpoint, device=args.device, batch=1, camera=prior)
    note_unread_camera(args, predictor.config, PROG)
    if predictor.device.type == "cpu":
        share_cpu()
    grid, classes = predictor.config.grid, predictor.config.classes
    if truth is not None:
        if truth.grid != grid:
            raise InputError(f"--truth {args.truth}: its grid ({_describe_grid(truth.grid)}) is not the model's "
                             f"({_describe_grid(grid)})")
        try:  # a truth of fewer classes (the flat world's, say) is compared by class name
            lut = truth.classes.indices_in(classes)
        except ClassTableError:
            raise InputError(f"--truth {args.truth}: its classes ({', '.join(truth.classes.names)}) are not all among "
                             f"the model's ({', '.join(classes.names)})") from None
        truth = RenderInput(lut[truth.volume].astype(np.uint8), grid, classes, truth.name)
    fit = args.fit or FITS[0]
    image, view = photo_view(path, image, args, PROG, grid.hfov)
    x = to_tensor([frame_image(image, grid, predictor.config.image_size, view, fit)], predictor.device)
    # The first call sets up the backend's kernels (seconds on a loaded CPU); the time shown is the second's.
    predictor.logits(x)
    t0 = time.perf_counter()
    logits = predictor.logits(x)
    if predictor.device.type == "cuda":
        import torch

        torch.cuda.synchronize(predictor.device)  # the time is the prediction's, not its launch's
    ms = 1000.0 * (time.perf_counter() - t0)
    logits = empty_uncovered(logits, frame_coverage(image.shape, grid, view, fit))
    height = round(PHOTO_DISPLAY * grid.height / grid.width)
    framed = frame_image(image, grid, (height, PHOTO_DISPLAY), view, fit)
    hfov = view if view is not None else grid.hfov
    title = (f"{path.name} ({image.shape[1]}x{image.shape[0]}, {hfov:g}\N{DEGREE SIGN}) \N{RIGHTWARDS ARROW} SSZ "
             f"{Path(checkpoint).name} ({grid.width}x{grid.height}x{grid.depth} cells, {grid.z_near:g}-"
             f"{grid.z_far:g} m), predicted on {predictor.device.type} in {ms:.0f} ms")
    if truth is not None:
        acc = _own_view_accuracy(logits, truth.volume)
        if acc is not None:
            title += f"; own-view first-hit accuracy against {args.truth.name}: {acc:.1f} %"
    return RenderInput(logits, grid, classes, path.stem), Photo(framed, truth, title)


def load_source(args: argparse.Namespace) -> tuple[RenderInput, Photo | None]:
    """MODEL as :func:`load_input` reads it, or a photo's prediction (:func:`load_photo`)."""
    if is_photo(args.model):
        return load_photo(args)
    _check_photo_options(args, False)
    return load_input(args.model, _input_grid(args)), None


def _read_camera_file(text: str) -> str:
    path = Path(text)
    source = f"--camera {text}"
    try:
        with open(path, "rb") as f:
            raw = f.read(MAX_CAMERA_BYTES + 1)
    except FileNotFoundError:
        raise InputError(f"{source}: no such file") from None
    except IsADirectoryError:
        raise InputError(f"{source}: is a folder, not a camera file") from None
    except OSError as e:
        raise InputError(f"{source}: cannot read it ({e.strerror or e})") from None
    if len(raw) > MAX_CAMERA_BYTES:
        raise InputError(f"{source}: not a camera file (larger than {MAX_CAMERA_BYTES} bytes)")
    try:
        return raw.decode("utf-8")
    except UnicodeDecodeError:
        raise InputError(f"{source}: not a camera file (binary data, not JSON text)") from None


def viewing_camera(text: str | None, grid: FruxelGrid, size: tuple[int, int] | None) -> Camera:
    """The camera of ``--camera`` (:func:`read_camera`) or :func:`fruxel.render.frames.default_camera` at ``size``.

    Raises:
        InputError: an unreadable file or an invalid camera, naming ``--camera`` and the file.
        UsageError: ``size`` given and other than the camera's own image size.
    """
    from fruxel.render.frames import DEFAULT_SIZE, default_camera

    cam = read_camera(text, size)
    if cam is None:
        w, h = size or DEFAULT_SIZE
        return default_camera(grid, w, h)
    return cam


def read_camera(text: str | None, size: tuple[int, int] | None) -> Camera | None:
    """The camera of ``--camera``, None without one: read before any work, as it needs no model.

    ``text`` is a :meth:`fruxel.Camera.to_json` text when it starts with ``{``, else the name of a file holding
    one (so that a missing file says so rather than "malformed JSON").

    Raises:
        InputError: an unreadable file or an invalid camera, naming ``--camera`` and the file.
        UsageError: ``size`` given and other than the camera's own image size.
    """
    from fruxel import Camera

    if text is None:
        return None
    if text.lstrip().startswith("{"):
        source = "--camera (JSON text)"
    else:
        source = f"--camera {text}"
        text = _read_camera_file(text)
    cam = _named(source, None, Camera.from_json, text)
    if size is not None and tuple(size) != (cam.width, cam.height):
        raise UsageError(f"--size {size[0]}x{size[1]} and {source}: the camera sets the image size "
                         f"({cam.width}x{cam.height}); leave out --size")
    return cam


# ---------------------------------------------------------------------------------------------------- render
def _render_options(args: argparse.Namespace) -> Any:
    from fruxel.render.frames import RenderOptions

    return RenderOptions(**config_values(args, RenderOptions))


def _input_grid(args: argparse.Namespace) -> FruxelGrid | None:
    return grid_from_args(args, _default_grid(), size_default=False)


DEFAULT_OUT = Path("out")
"""Output folder when ``--out`` is not given."""


def output_path(args: argparse.Namespace, name: str) -> Path:
    """The image or video file to write (checked before anything is rendered).

    ``--out`` ending in an image suffix (``.png``, ``.jpg``, ...: :data:`fruxel.render.images.IMAGE_FORMATS`) or a
    video suffix (``.gif``, ``.mp4``) is that file; anything else is a folder, which gets ``NAME_MODE.png`` or,
    with ``--orbit``, ``NAME_MODE_orbit.gif|mp4`` (``--video``).

    Raises:
        UsageError: an image for ``--orbit``, a video without it, or ``--video`` against ``--out``'s suffix.
        RenderError: MP4 without ``imageio-ffmpeg``.
    """
    from fruxel.render.images import IMAGE_FORMATS, VIDEO_FORMATS, check_video_writer

    out = args.out if args.out is not None else DEFAULT_OUT
    suffix = out.suffix.lower()
    if args.orbit is None:
        if args.video is not None:
            raise UsageError("--video is the format of an --orbit video")
        if suffix in VIDEO_FORMATS:
            raise UsageError(f"--out {out} is a video: add --orbit N, or name an image (.png) or a folder")
        return out if suffix in IMAGE_FORMATS else out / f"{name}_{args.mode}.png"
    if suffix in IMAGE_FORMATS:
        raise UsageError(f"--orbit writes a video: --out {out} must end in .gif or .mp4, or be a folder")
    if suffix in VIDEO_FORMATS:
        if args.video is not None and f".{args.video}" != suffix:
            raise UsageError(f"--video {args.video} and --out {out} ask for different formats; give one of them")
        target = out
    else:
        target = out / f"{name}_{args.mode}_orbit.{args.video or VIDEO_FORMATS_DEFAULT}"
    check_video_writer(target)
    return target


RENDER_BYTES_PER_CELL = 6
"""Memory a picture takes per cell of the model's grid, bytes (an estimate: the padded labels, the shell and the
mesh's work arrays; 5.5 measured for the mesh of a 1024 x 1024 x 512 room, 1.6 for its ray cast), on top of the
volume itself (a logits file's logits and their probabilities)."""


def model_name(model: str | None) -> str:
    """NAME of the output files of MODEL: the file's (or photo's) stem, ``sample_room`` for the sample room."""
    if model is None:
        from fruxel.data import SAMPLE_ROOM

        return SAMPLE_ROOM.stem
    return Path(model).stem


def _check_model_memory(model: str | None) -> None:
    """Refuse a model or logits file whose grid is too large to render in the memory available, from its header,
    before anything is read (a 4 MB file of zeros can declare billions of cells)."""
    if model is None or Path(model).suffix.lower() != ".npz" or not Path(model).is_file():
        return  # the sample room is small; other files are reported by the reader
    from fruxel.io import MemoryLimitError, check_memory, read_header

    kind, grid, classes = read_header(model)
    cells = grid.width * grid.height * grid.depth
    # A logits file's volume: its float logits (up to 4 bytes) and their float32 probabilities, per class.
    volume = cells * len(classes) * 8 if kind == "logits" else cells
    try:
        check_memory(volume + RENDER_BYTES_PER_CELL * cells,
                     f"its {grid.width}x{grid.height}x{grid.depth} cells ({cells / 1e9:.2g} billion) to render")
    except MemoryLimitError as e:
        raise InputError(f"{model}: {e}") from None


def check_render_inputs(args: argparse.Namespace) -> tuple[Camera | None, Path | None]:
    """Every check that needs no model, before any work (no photo predicted, no model read): options that do not
    go together, the photo's header, ``--camera``, the output files, and whether the model's grid fits in memory.

    Returns:
        The ``--camera`` camera (None without one) and the image or video file to write (None with ``--view``).

    Raises:
        UsageError, InputError, PhotoError, OutputError: see :func:`run_render`.
    """
    if args.export is not None and args.export.suffix.lower() not in (".glb", ".ply"):
        raise UsageError(f"--export writes .glb or .ply, got {str(args.export)!r}")
    if args.view:
        given = [flag for flag, v in (("--out", args.out), ("--orbit", args.orbit), ("--export", args.export),
                                      ("--video", args.video)) if v is not None]
        if given:
            raise UsageError(f"--view shows the model in a window and writes no file: leave out {', '.join(given)}")
    photo = is_photo(args.model)
    _check_photo_options(args, photo)
    if photo:
        check_photo(args.model)
    else:
        _input_grid(args)  # --z-near, --z-far or --hfov without --grid, an impossible grid
        _check_model_memory(args.model)
    camera = read_camera(args.camera, args.size)
    target = None
    if not args.view:
        target = output_path(args, model_name(args.model))
        check_output_file(target, "--out")
    if args.export is not None:
        check_output_file(args.export, "--export")
    return camera, target


def run_render(args: argparse.Namespace) -> list[Path]:
    """Render as asked and write the outputs, all of them or none (:func:`fruxel.cli.common.write_outputs`);
    returns the files written (none for ``--view``)."""
    from fruxel.render.frames import FrameRenderer, open_viewer, orbit
    from fruxel.render.images import image_format, save_image, save_video

    given_camera, target = check_render_inputs(args)
    inp, photo = load_source(args)
    opts = _render_options(args)
    frames = FrameRenderer(inp, opts)
    empty = not inp.any_occupied(opts.threshold)
    if empty:
        # Not an error (an untrained or thresholded model can be empty), but a blank picture needs a reason.
        rule = f" at --threshold {opts.threshold:g}" if inp.is_scores and opts.threshold is not None else ""
        print(f"{PROG}: note: {inp.name}: every cell is empty{rule}; the picture shows no model", file=sys.stderr)
    pictures: Any = frames
    from fruxel.render.frames import DEFAULT_SIZE, default_camera

    if photo is not None:
        from fruxel.render.compare import PhotoComparison

        truth = FrameRenderer(photo.truth, opts) if photo.truth is not None else None
        pictures = PhotoComparison(photo.framed, frames, truth, title=photo.title,
                                   headings=("photo, in the model's view", "SSZ prediction", "ground truth"))
    # Views fit what the models hold: the grid's far end is mostly empty, and a model of a near wall filled a tenth
    # of a view fitted to the frustum, in its corner. A still view with --frustum drawn fits the frustum.
    points = pictures.model_points() if given_camera is None or args.orbit is not None else None
    size = args.size or (DEFAULT_SIZE if photo is None else PHOTO_SIZE)
    camera = given_camera or default_camera(inp.grid, *size, points=None if photo is None and opts.frustum else points)
    if target is None:
        open_viewer(inp, opts, camera)
        return []
    outputs: list[tuple[Path, Any]] = []
    if args.orbit is not None:
        from tqdm import tqdm

        cams = orbit(inp.grid, camera, args.orbit, points=points)
        # stderr, like the error lines; the bar disappears when done so scripts see only the written paths.
        images = pictures.images(tqdm(cams, desc="orbit", unit="frame", leave=False, disable=None))
        keep = [(255, 255, 255), *inp.classes.palette()[1:]]

        def encode(frames: Any) -> Any:
            # The frames are drawn; encoding them (a GIF's palette mapping) is the other long part.
            return tqdm(frames, total=len(images), desc="encode", unit="frame", leave=False, disable=None)

        outputs.append((target, lambda tmp: save_video(tmp, images, args.fps, target.suffix, keep, encode)))
    else:
        image, fmt = pictures.image(camera), image_format(target)
        if empty and photo is None and args.mode != "both":
            # "both" (and the photo comparison) caption their panels already, the mesh's with "0 triangles".
            from fruxel.render.legend import draw_caption

            image = draw_caption(image, f"{inp.name}: every cell is empty")
        outputs.append((target, lambda tmp: save_image(tmp, image, fmt)))
    if args.export is not None:
        from fruxel.mesh import encode_mesh

        data = encode_mesh(frames.mesh_for(camera), args.export.suffix)
        outputs.append((args.export, lambda tmp: tmp.write_bytes(data)))
    return write_outputs(outputs)


# ---------------------------------------------------------------------------------------------------- Table 1
def config_from_args(args: argparse.Namespace) -> Table1Config:
    """A :class:`fruxel.render.table1.Table1Config` from ``fruxel-render --benchmark``'s or
    ``benchmarks/table1.py``'s options (``--size``, ``--frames``, ``--grid N``, ``--backend``, ``--device``,
    ``--backends``)."""
    from fruxel.render.table1 import Table1Config

    kw: dict[str, Any] = {}
    if getattr(args, "size", None) is not None:
        kw["size"] = tuple(args.size)
    if getattr(args, "frames", None) is not None:
        kw["frames"] = int(args.frames)
    extra = [g for g in grid_options_given(args) if g != "--grid"]
    if extra:
        raise UsageError(f"{', '.join(extra)} do not apply to --benchmark: its room's grid is fixed, --grid N sets "
                         "its size")
    grid = getattr(args, "grid", None)
    if grid is not None:
        if len(set(grid)) != 1:
            raise UsageError(f"--benchmark measures an N^3 room: --grid N, got {'x'.join(map(str, grid))}")
        kw["n"] = int(grid[0])
    for name in ("backend", "device"):
        if getattr(args, name, None) is not None:
            kw[name] = getattr(args, name)
    if getattr(args, "backends", None):
        from fruxel.kernels.registry import split_name

        names = tuple(b.strip() for b in args.backends.split(",") if b.strip())
        # A misspelt name fails here, before minutes of measuring; an installed-but-unusable one still becomes an
        # "unavailable" row (as OpenCL does on a GPU machine without it).
        for b in names:
            split_name(b)
        kw["raycast_backends"] = names
    return Table1Config(**kw)


def _benchmark(args: argparse.Namespace) -> list[Path]:
    """``fruxel-render --benchmark``: run Table 1, print it, record the results in ``--out``."""
    from fruxel import labels_from_scores
    from fruxel.io import atomic_write
    from fruxel.render.shading import to_numpy
    from fruxel.render.table1 import format_table, machine_tag, markdown_section, record, run, verdicts

    cfg = config_from_args(args)
    from fruxel.render.images import IMAGE_FORMATS, VIDEO_FORMATS

    out = args.out if args.out is not None else DEFAULT_OUT
    if out.suffix.lower() in (*IMAGE_FORMATS, *VIDEO_FORMATS):
        raise UsageError(f"--benchmark writes several files (table1.json, table1.png, table1.md): --out {out} must "
                         "be a folder")
    check_output_folder(out, "--out")
    if is_photo(args.model):
        check_photo(args.model)
    model = None
    if args.model is not None:
        # Scores are turned into labels once, before timing.
        inp = load_photo(args)[0] if is_photo(args.model) else load_input(args.model)
        labels = labels_from_scores(to_numpy(inp.volume)[0], axis=0) if inp.is_scores else inp.volume
        model = (labels, inp.grid, inp.classes)
    result = run(cfg, model)
    print()
    print(format_table(result))
    for v in verdicts(result):
        print(f"  {v}")
    written = record(result, out, None)
    md = out / "table1.md"
    with atomic_write(md, "w") as f:
        f.write(markdown_section({machine_tag(result.machine): result}, "table1.png"))
    written.append(md)
    return written


# ---------------------------------------------------------------------------------------------------- entry
def _main(args: argparse.Namespace) -> int:
    written = _benchmark(args) if args.benchmark else run_render(args)
    for path in written:
        print(path)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``fruxel-render``; returns the exit status (0, 2 for bad input, 130 when interrupted)."""
    return run(_main, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

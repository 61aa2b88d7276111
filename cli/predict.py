"""``fruxel-predict``: fruxel models from photos with a trained SSZ model.

Usage::

    fruxel-predict IMAGE... [--checkpoint FILE] [--out DIR] [--fit crop|pad] [--hfov DEG | --intrinsics FX,FY,CX,CY]
                   [--pitch DEG] [--roll DEG] [--height M] [--batch N] [--logits] [--device cpu|cuda[:N]] [-q]

IMAGE is any PNG, JPEG or other image Pillow reads (16-bit grey and 32-bit float grey in [0, 1] included), of any
size a camera gives: at least 16 pixels on its shorter side and at most 8 times as long as wide
(:func:`fruxel.cli.common.check_photo`; smaller or thinner pictures are refused). Each is mapped onto the model's
own camera (:func:`fruxel.train.predict.prepare_image`): with a field of view it is cropped or padded to the grid's
view about the centre, by geometry alone; without one the photo is taken as the grid's view and its aspect matched
by a centred crop (``--fit crop``, default) or grey padding (``--fit pad``); then it is resized to the model's image
size. The field of view is ``--hfov``, else ``--intrinsics`` (the photo cropped about its principal point to
square pixels), else the photo's EXIF 35 mm-equivalent focal length (``2 atan(36 / (2 f))`` across a landscape
photo; a value outside 8-400 mm is ignored with a warning line), else none. ``--pitch``, ``--roll`` and
``--height`` tell a model that reads the camera (``SSZConfig.camera_inputs``) which way is down and how high the
camera is (:class:`fruxel.train.predict.CameraPrior`); other models ignore them. Grid columns whose centre ray
falls on grey padding are left empty: the photo says nothing of them. The model (``--checkpoint``: a shipped
``.safetensors`` file, a training checkpoint ``.pt`` or a shipped model's name, ``ssz64``, ``ssz128`` or ``ssz64-any``
(the one that reads the camera); default the
model shipped with fruxel, ``ssz64-any``) predicts the images in batches of ``--batch``.

For an image ``NAME.EXT`` it writes into ``--out`` (default ``out/``)

* ``NAME.npz``, a fruxel model file (:func:`fruxel.save`): the argmax labels on the model's grid with its classes;
* with ``--logits``, ``NAME.logits.npz`` too, a logits file (:func:`fruxel.save_logits`): the logits
  ``(C, D, H, W)`` in float16.

The labels are the argmax of the logits as stored (float16), so both files show the same model; ``fruxel-render``
reads either. An image's files are written together, atomically; every path written is printed. The output
folder and each photo's format and size are checked before the model loads, every photo is read before it runs,
and two images that would write the same file are refused. Errors are one line ``fruxel-predict: error: ...`` with
exit status 2 (:func:`fruxel.cli.common.run`).
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from .common import (
    OneLineParser,
    UsageError,
    add_camera_options,
    add_model_options,
    camera_prior,
    check_output_folder,
    check_photo,
    note_unread_camera,
    path_name,
    photo_view,
    positive_int,
    run,
    torch_device,
    write_outputs,
)

PROG = "fruxel-predict"
DEFAULT_OUT = Path("out")
"""Output folder when ``--out`` is not given."""
MODEL_SUFFIX = ".npz"
"""Suffix of the fruxel model file written per image."""
LOGITS_SUFFIX = ".logits.npz"
"""Suffix of the logits file written per image with ``--logits``."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``fruxel-predict`` (standard library only: ``--help`` is instant)."""
    p = OneLineParser(
        prog=PROG,
        description="Predict a semantic fruxel model from each photo with a trained SSZ model; writes NAME.npz "
        "(fruxel model: argmax labels) and, with --logits, NAME.logits.npz per image, both readable by "
        "fruxel-render.",
    )
    p.add_argument("images", nargs="+", metavar="IMAGE", help="photos: PNG, JPEG or anything Pillow reads, any size")
    add_model_options(p)
    p.add_argument("--out", type=path_name, default=DEFAULT_OUT, metavar="DIR",
                   help=f"output folder (default {DEFAULT_OUT}/)")
    p.add_argument("--fit", choices=("crop", "pad"), default="crop",
                   help="without --hfov: match the model's aspect by a centred crop or by grey padding (default crop)")
    add_camera_options(p)
    p.add_argument("--batch", type=positive_int, default=8, metavar="N", help="images per forward pass (default 8)")
    p.add_argument("--compile", action="store_true",
                   help="on CUDA, compile the forward pass first (torch.compile, about half a minute): worth it for "
                   "many images")
    p.add_argument("--logits", action="store_true",
                   help="also write NAME.logits.npz, the logits (C, D, H, W) in float16")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bars, no list of files written")
    return p


def output_names(images: Sequence[str], out: Path, logits: bool) -> list[list[Path]]:
    """The files each image writes: ``[out/NAME.npz]`` (and ``out/NAME.logits.npz``), NAME its file's stem.

    Raises:
        UsageError: two images that would write the same file (``a/x.png`` and ``b/x.jpg``; ``x.png`` and
            ``x.logits.png`` with ``--logits``).
    """
    owner: dict[Path, str] = {}
    result = []
    for image in images:
        stem = Path(image).stem
        files = [out / f"{stem}{MODEL_SUFFIX}"] + ([out / f"{stem}{LOGITS_SUFFIX}"] if logits else [])
        for f in files:
            if f in owner:
                raise UsageError(f"{owner[f]} and {image} would both write {f}; rename one, or predict them in two "
                                 "runs with different --out folders")
            owner[f] = image
        result.append(files)
    return result


def _progress(items: Any, total: int, desc: str, quiet: bool) -> Any:
    from tqdm import tqdm

    # stderr, like the error lines; the bar disappears when done so scripts see only the written paths.
    return tqdm(items, total=total, desc=desc, unit="image", disable=True if quiet else None, leave=False,
                dynamic_ncols=True)


def _writers(logits: Any, grid: Any, classes: Any, files: list[Path]) -> list[tuple[Path, Any]]:
    """The writers of one image's files, from its ``(C, D, H, W)`` float32 logits."""
    import numpy as np

    from fruxel import FruxelModel, labels_from_scores, save, save_logits

    # float16 holds +-65504; a larger logit would become infinite, which a logits file refuses.
    half = np.clip(logits, -65504.0, 65504.0).astype(np.float16)
    # Labels from the stored float16 logits, so the model file and the logits file show the same cells.
    model = FruxelModel(labels_from_scores(half, axis=0), grid, classes)
    out = [(files[0], lambda tmp: save(tmp, model))]
    if len(files) > 1:
        out.append((files[1], lambda tmp: save_logits(tmp, half, grid, classes)))
    return out


def _main(args: argparse.Namespace) -> int:
    # Everything that can be checked is checked before the model loads: the output folder, the photos' headers
    # (format and size), the device.
    if args.out.exists() and not args.out.is_dir():
        raise UsageError(f"--out {args.out} is a file; --out is the folder the predictions go to")
    if not args.out.exists() and args.out.suffix.lower() == ".npz":  # a file name meant, not a folder to make
        raise UsageError(f"--out {args.out}: --out is the folder the predictions go to, as NAME.npz for each image; "
                         f"give a folder")
    check_output_folder(args.out, "--out")
    targets = output_names(args.images, args.out, args.logits)
    for path in args.images:
        check_photo(path)
    prior = camera_prior(args)
    device = str(torch_device(args.device))

    from fruxel.train.predict import (
        ImageError,
        empty_uncovered,
        frame_coverage,
        load_image,
        load_predictor,
        prepare_image,
    )

    predictor = load_predictor(args.checkpoint, device=device, batch=args.batch, compile=args.compile, camera=prior)
    config = predictor.config
    note_unread_camera(args, config, PROG)
    # Every image is read and checked before the model runs; what is kept is its small model-sized version.
    prepared, coverage = [], []
    grid, classes = config.grid, config.classes
    for path in _progress(args.images, len(args.images), "read", args.quiet):
        try:
            image, hfov = photo_view(path, load_image(path), args, PROG, grid.hfov)
            prepared.append(prepare_image(image, config, hfov=hfov, fit=args.fit))
        except ImageError:
            raise
        except ValueError as e:
            raise ImageError(f"{path}: {e}") from None
        coverage.append(frame_coverage(image.shape, grid, hfov, args.fit))
    predictions = _progress(predictor.predict(prepared), len(prepared), "predict", args.quiet)
    for logits, covered, files in zip(predictions, coverage, targets, strict=True):
        logits = empty_uncovered(logits, covered)
        written = write_outputs(_writers(logits.cpu().numpy(), grid, classes, files))
        if not args.quiet:
            for p in written:
                print(p)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``fruxel-predict`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    return run(_main, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

"""``fruxel-sim``: make simulated data sets and preview samples.

    fruxel-sim generate --out DIR [--samples N | --split train=15000,test=1000] [--image 512] [--grid 128]
                        [--workers K] [--seed S] [--shard-size 64] [--backend warp]
    fruxel-sim preview --out sheet.png [--seed S] [--split train] [--index I] [--count N] [--image 256]

``generate`` writes shards and a manifest (:mod:`.writer`); it resumes an interrupted run in the same folder and
refuses a folder made with other settings. ``preview`` writes a contact sheet: per sample the robot camera's
image, the own-view ground-truth labels in the class colours, and a ray-cast render of the ground-truth volume
from a second camera beside the robot's, with a class legend.

Errors print one line on stderr and exit with status 2 (130 when interrupted). Heavy modules are imported inside
the commands, so ``--help`` is instant.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from typing import Any

from fruxel.cli import OneLineParser, non_negative_int, positive_int

PROG = "fruxel-sim"


def _grid_size(text: str) -> tuple[int, int, int]:
    """``"128"`` -> (128, 128, 128); ``"160x120x128"`` -> (W, H, D)."""
    parts = text.lower().split("x")
    try:
        values = [int(p) for p in parts]
    except ValueError:
        values = []
    if len(values) == 1:
        values *= 3
    if len(values) != 3 or min(values) < 1:
        raise argparse.ArgumentTypeError(f"--grid takes N or WxHxD with positive integers, got {text!r}")
    return values[0], values[1], values[2]


def _config_options(p: argparse.ArgumentParser, image: int, grid: str) -> None:
    p.add_argument("--image", type=positive_int, default=image, metavar="S",
                   help=f"image width in pixels; the height is S*H/W (default {image})")
    p.add_argument("--grid", type=_grid_size, default=_grid_size(grid), metavar="N|WxHxD",
                   help=f"grid size in cells (default {grid})")
    p.add_argument("--hfov", type=float, default=60.0, help="horizontal field of view, degrees (default 60)")
    p.add_argument("--z-near", type=float, default=0.5, help="grid near plane, metres (default 0.5)")
    p.add_argument("--z-far", type=float, default=8.0, help="grid far plane, metres (default 8)")
    p.add_argument("--samples-per-scene", type=positive_int, default=16, metavar="N",
                   help="samples per room and robot trajectory (default 16)")
    p.add_argument("--no-augment", action="store_true", help="render without appearance augmentation")
    p.add_argument("--seed", type=non_negative_int, default=0, help="base seed (default 0)")
    p.add_argument("--backend", default="warp", choices=("warp", "warp-cpu", "warp-cuda"),
                   help="fruxelize backend (default warp: CUDA when present, else CPU)")


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``fruxel-sim``."""
    # Subcommand parsers are made with the same class, so they give one-line errors too.
    parser = OneLineParser(prog=PROG, description="Simulated training data for fruxel: rooms, a mobile "
                                     "robot's camera images and ground-truth fruxel labels.")
    sub = parser.add_subparsers(dest="command", required=True, metavar="COMMAND")

    g = sub.add_parser("generate", help="write a data set: compressed shards plus manifest.json",
                       description="Write a data set folder: shards {split}-NNNNN.npz and manifest.json. "
                       "Deterministic per seed; an interrupted run resumes in the same folder.")
    g.add_argument("--out", required=True, metavar="DIR", help="data set folder (created if missing)")
    g.add_argument("--samples", type=positive_int, metavar="N",
                   help="total samples, divided 15:1 into train and test (default: the --split sizes)")
    g.add_argument("--split", default=None, metavar="NAME=N,...",
                   help="samples per split (default train=15000,test=1000, the paper's)")
    g.add_argument("--shard-size", type=positive_int, default=64, metavar="N", help="samples per shard (default 64)")
    g.add_argument("--workers", type=positive_int, default=1, metavar="K", help="worker processes (default 1)")
    g.add_argument("--device", default=None, help="Warp device for fruxelize, e.g. cpu, cuda:0 (default: automatic)")
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    _config_options(g, 512, "128")

    v = sub.add_parser("preview", help="write a contact sheet PNG of a few samples",
                       description="Contact sheet: camera image | own-view ground-truth labels | ray-cast render of "
                       "the ground truth from a second pose, with a class legend.")
    v.add_argument("--out", required=True, metavar="PNG", help="the PNG to write")
    v.add_argument("--split", default="train", help="split name (seeds differ per split; default train)")
    v.add_argument("--index", type=non_negative_int, default=0, help="first sample index (default 0)")
    v.add_argument("--count", type=positive_int, default=1, help="samples, one row each (default 1)")
    v.add_argument("--raycast-backend", default=None,
                   help="first_hit backend for the second view (default: the best available)")
    _config_options(v, 256, "128")
    return parser


def _config(args: argparse.Namespace, splits: Any, shard_size: int = 64) -> Any:
    from fruxel.grid import FruxelGrid

    from .config import AugmentConfig, ImageConfig, SimConfig

    w, h, d = args.grid
    grid = FruxelGrid(width=w, height=h, depth=d, z_near=args.z_near, z_far=args.z_far, hfov=args.hfov)
    image = ImageConfig(size=args.image, augment=AugmentConfig(enabled=not args.no_augment))
    return SimConfig(grid=grid, image=image, samples_per_scene=args.samples_per_scene, shard_size=shard_size,
                     splits=splits)


def _generate(args: argparse.Namespace) -> int:
    from .config import PAPER_SPLITS, ConfigError, parse_splits, scale_splits
    from .writer import generate

    splits = parse_splits(args.split) if args.split is not None else PAPER_SPLITS
    if args.samples is not None:
        if args.split is None:
            splits = scale_splits(args.samples)
        elif sum(n for _, n in splits) != args.samples:
            raise ConfigError(f"--samples {args.samples} does not match --split {args.split!r} "
                              f"({sum(n for _, n in splits)} samples); give one of them")
    config = _config(args, splits, args.shard_size)
    manifest = generate(args.out, config, args.seed, workers=args.workers, backend=args.backend, device=args.device,
                        progress=not args.quiet)
    if not args.quiet:
        sizes = ", ".join(f"{name} {n}" for name, n in config.splits)
        print(f"{PROG}: {args.out}: {sizes} samples in {len(manifest.hashes)} shards "
              f"({config.image_width}x{config.image_height} images, {_grid_text(config)} grid), seed {args.seed}")
    return 0


def _grid_text(config: Any) -> str:
    g = config.grid
    return f"{g.width}x{g.height}x{g.depth}"


def _preview(args: argparse.Namespace) -> int:
    import numpy as np
    from PIL import Image

    from fruxel.io import atomic_write
    from fruxel.kernels import first_hit
    from fruxel.shading import shade_hits

    from .images import contact_sheet, second_camera
    from .sample import SampleMaker

    config = _config(args, ((args.split, args.index + args.count),))
    classes = config.classes
    palette = classes.palette()
    grid = config.grid
    rows, titles = [], []
    with SampleMaker(config, args.seed, backend=args.backend) as maker:
        for i in range(args.index, args.index + args.count):
            s = maker.make(args.split, i)
            own = first_hit(s.labels, grid, grid.camera(), backend=args.raycast_backend)
            cam = second_camera(own.depth, config, config.image_width)
            hits = first_hit(s.labels, grid, cam, backend=args.raycast_backend)
            shaded = shade_hits(np.asarray(hits.label), np.asarray(hits.normal), np.asarray(hits.depth), palette,
                                cam.rotation, fog=(grid.z_near, 2.0 * grid.z_far))
            rows.append({
                "camera image": s.image,
                "ground truth, own view": classes.colour_of(np.asarray(own.label)),
                "ground truth, second pose": shaded,
            })
            titles.append(f"{args.split} sample {i} (room {s.scene}, frame {s.frame}), seed {args.seed}, "
                          f"grid {_grid_text(config)}")
    sheet = contact_sheet(rows, classes.names, palette, titles)
    with atomic_write(args.out) as f:
        Image.fromarray(sheet).save(f, format="PNG")
    print(f"{PROG}: wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")
    return 0


def _expected_errors() -> tuple[type[BaseException], ...]:
    from fruxel.camera import CameraError
    from fruxel.classes import ClassTableError
    from fruxel.grid import GridError
    from fruxel.kernels import BackendError, BackendUnavailable, VolumeError

    from .config import ConfigError
    from .robot import TrajectoryError
    from .scene import SceneError
    from .shards import DatasetError

    return (ConfigError, DatasetError, GridError, CameraError, ClassTableError, SceneError, TrajectoryError,
            BackendError, BackendUnavailable, VolumeError, OSError)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``fruxel-sim`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    args = build_parser().parse_args(argv)
    run = {"generate": _generate, "preview": _preview}[args.command]
    expected = _expected_errors()
    try:
        return run(args)
    except KeyboardInterrupt:
        print(f"{PROG}: interrupted", file=sys.stderr)
        return 130
    except expected as e:
        print(f"{PROG}: error: {e}", file=sys.stderr)
        return 2


if __name__ == "__main__":
    sys.exit(main())

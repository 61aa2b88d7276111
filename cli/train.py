"""``fruxel-train``: train SSZ, the image-to-fruxel network (conventions section 8).

    fruxel-train --preset tiny --out runs/tiny                 # 32^3 from 64^2, a laptop CPU
    fruxel-train --config my.json --out runs/x --device cuda   # a preset with fields overridden (JSON)
    fruxel-train --resume --out runs/x [--steps N] [--time-limit S] [--workers K]
    fruxel-train --preset ssz64 --print-config > my.json       # the full config, to start a file from
    torchrun --nproc_per_node 8 -m fruxel.cli.train --preset ssz64 --out runs/ssz64

A config file is a JSON object that starts from a preset (``"preset": "ssz64"``, default the built-in defaults)
and overrides any fields, nested as :class:`fruxel.train.config.TrainConfig` nests them::

    {"preset": "tiny", "optim": {"lr": 0.001}, "run": {"steps": 5000}, "data": {"workers": 2}}

``--steps``, ``--batch-size``, ``--workers``, ``--time-limit`` and ``--data DIR`` (shards written by
``fruxel-sim generate``, or a data folder of your own labelled photos with a ``dataset.json``: docs/your-data.md)
override the config's values. To fine-tune a model on your data, start from it with ``"run": {"init": FILE}``.
The run folder gets the checkpoint ``last.pt``, the shipped model ``model.safetensors``, ``config.json``,
``metrics.csv``, ``curves.png`` and ``examples.png`` (:mod:`fruxel.train.engine.trainer`). ``--resume`` continues
``RUN_DIR/last.pt`` with the run's own config; only ``--steps``, ``--time-limit`` and ``--workers`` may change.
Ctrl-C writes a checkpoint, then exits with status 130.

Under ``torchrun`` every process runs this command; each trains on its own part of the data (DDP), and rank 0
writes the files and prints. Errors print one line on stderr and exit with status 2
(:func:`fruxel.cli.common.run`). Heavy modules are imported inside :func:`_main`, so ``--help`` is instant.
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from collections.abc import Sequence
from typing import Any

from fruxel.train.config import PRESETS

from .common import (
    OneLineParser,
    UsageError,
    check_output_folder,
    device_name,
    non_negative_int,
    path_name,
    positive_int,
    run,
    torch_device,
)

PROG = "fruxel-train"


def _seconds(text: str) -> float:
    try:
        v = float(text)
    except ValueError:
        v = -1.0
    if not v >= 0.0 or v == float("inf"):
        raise argparse.ArgumentTypeError(f"expected a number of seconds >= 0, got {text!r}")
    return v


def _preset_name(text: str) -> str:
    from fruxel.train.config import REPLACED_PRESETS

    if text in REPLACED_PRESETS:
        raise argparse.ArgumentTypeError(f"preset {text!r} was replaced by {REPLACED_PRESETS[text]!r}")
    if text not in PRESETS:
        raise argparse.ArgumentTypeError(f"unknown preset {text!r}; choose one of {', '.join(PRESETS)}")
    return text


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``fruxel-train``."""
    p = OneLineParser(prog=PROG, description="Train SSZ (one image -> a semantic fruxel model) on the streaming "
                      "simulator or a data set of shards. Under torchrun, every process trains on its own part of "
                      "the data (DDP) and rank 0 writes the run folder.")
    what = p.add_mutually_exclusive_group()
    what.add_argument("--config", metavar="FILE",
                      help="JSON config: a preset (\"preset\": NAME) with any fields overridden")
    what.add_argument("--preset", type=_preset_name, metavar="{" + ",".join(PRESETS) + "}",
                      help="a named config: tiny (32^3 from 64^2, a CPU), ssz64 and ssz128 (the shipped models' "
                      "architectures: 64^3 from 256^2, 128^3 from 512^2, the latter fine-tuned from ssz64), ssz64-any "
                      "(ssz64 reading the camera, on the furnished rooms from any camera)")
    p.add_argument("--out", type=path_name, metavar="RUN_DIR",
                   help="the run folder: checkpoints, shipped model, metrics, curves, examples (created)")
    p.add_argument("--overwrite", action="store_true",
                   help="a new run may replace the run RUN_DIR holds (without it, that is refused)")
    p.add_argument("--resume", action="store_true",
                   help="continue RUN_DIR/last.pt with the run's own config (--steps, --time-limit and --workers "
                   "may change)")
    p.add_argument("--device", type=device_name, default=None,
                   help="cpu, cuda or cuda:N (default: CUDA when present; under torchrun each process takes GPU "
                   "LOCAL_RANK)")
    o = p.add_argument_group("overrides of the config")
    o.add_argument("--steps", type=positive_int, metavar="N", help="run.steps: optimiser steps of the whole run")
    o.add_argument("--batch-size", type=positive_int, metavar="N",
                   help="run.batch_size: global batch (divided among the torchrun processes)")
    o.add_argument("--workers", type=non_negative_int, metavar="K",
                   help="data.workers: simulator or reader processes per training process (0: in the process)")
    o.add_argument("--data", type=path_name, metavar="DIR",
                   help="train on the data set folder DIR (fruxel-sim generate; data.source = shards) or on the "
                   "data folder of labelled photos DIR (with a dataset.json: yours, or fruxel-sim export; "
                   "data.source = folder) instead of streaming; sets data.root = DIR")
    o.add_argument("--time-limit", type=_seconds, metavar="S",
                   help="run.time_limit: checkpoint and stop after S seconds (0: none); continue with --resume")
    p.add_argument("--print-config", action="store_true",
                   help="print the full resolved config as JSON and exit (a file to start a config from)")
    p.add_argument("-q", "--quiet", action="store_true", help="no progress bar or summary")
    return p


def _read_config(path: str) -> Any:
    from fruxel.train.config import ConfigError, TrainConfig

    with open(path, encoding="utf-8") as f:
        try:
            text = f.read()
        except UnicodeDecodeError as e:
            raise ConfigError(f"{path}: not a text file ({e.reason})") from None
    try:
        return TrainConfig.from_json(text)
    except ConfigError as e:
        raise ConfigError(f"{path}: {e}") from None


def _changes(args: argparse.Namespace) -> dict[str, dict[str, Any]]:
    """The overrides given on the command line, nested as in a config file."""
    changes: dict[str, dict[str, Any]] = {}
    for dest, part, key in (("steps", "run", "steps"), ("batch_size", "run", "batch_size"),
                            ("time_limit", "run", "time_limit"), ("workers", "data", "workers")):
        if getattr(args, dest) is not None:
            changes.setdefault(part, {})[key] = getattr(args, dest)
    if args.data is not None:
        from fruxel.train.folder import is_folder_set

        source = "folder" if is_folder_set(args.data) else "shards"
        changes.setdefault("data", {}).update(source=source, root=str(args.data))
    return changes


def _config(args: argparse.Namespace) -> Any:
    """The experiment of a new run: the file or preset with the command line's overrides."""
    from fruxel.train.config import override, preset

    if args.config is not None:
        config = _read_config(args.config)
    elif args.preset is not None:
        config = preset(args.preset)
    else:
        raise UsageError("give --config FILE or --preset NAME for a new run, or --resume to continue one")
    return override(config, _changes(args), "")


def _main_rank() -> bool:
    return int(os.environ.get("RANK", "0")) == 0


def _summary(out: str, config: Any, result: Any) -> str:
    rate = result.samples / result.seconds if result.seconds > 0 else 0.0
    parts = [f"{PROG}: {out}: step {result.step} of {config.run.steps}, {result.samples} samples in "
             f"{result.seconds:.1f} s ({rate:.1f} samples/s)"]
    if result.interrupted:
        parts[0] += " - stopped by the time limit; continue with --resume"
    if result.losses:
        terms = ", ".join(f"{k} {v:.4g}" for k, v in result.losses.items() if k != "total")
        parts.append(f"loss {result.losses.get('total', float('nan')):.4g} ({terms})")
    m = result.metrics
    if m:
        def pct(key: str) -> str:
            return "n/a" if m.get(key) is None else f"{m[key]:.1f} %"

        depth = "n/a" if m.get("depth_error") is None else f"{m['depth_error']:.3f} m"
        parts.append(f"held-out ({m.get('samples', '?')} samples): mIoU {pct('miou')}, completion IoU "
                     f"{pct('completion_iou')}, own-view accuracy {pct('own_view_accuracy')}, novel-view accuracy "
                     f"{pct('novel_view_accuracy')}, depth error {depth}")
    return "; ".join(parts)


def _main(args: argparse.Namespace) -> int:
    if args.resume:
        given = [flag for flag, v in (("--config", args.config), ("--preset", args.preset),
                                      ("--batch-size", args.batch_size), ("--data", args.data)) if v is not None]
        given += ["--overwrite"] if args.overwrite else []
        if given:
            raise UsageError(f"{', '.join(given)} cannot be given with --resume: a run continues with its own "
                             "config (only --steps, --time-limit and --workers may change)")
        if args.out is None:
            raise UsageError("--resume needs --out RUN_DIR, the run to continue")
    elif args.out is None and not args.print_config:
        raise UsageError("--out RUN_DIR is required: the folder the run writes")

    overrides = {k: v for k, v in (("steps", args.steps), ("time_limit", args.time_limit),
                                   ("workers", args.workers)) if v is not None}
    if args.print_config:
        if args.resume:
            from fruxel.train.engine.checkpoint import LATEST, read_checkpoint
            from fruxel.train.engine.trainer import override_settings

            config = override_settings(read_checkpoint(os.path.join(args.out, LATEST)).config, overrides)
        else:
            config = _config(args)
        print(json.dumps(config.to_dict(), indent=2))
        return 0

    from fruxel.train.engine import distributed
    from fruxel.train.engine.checkpoint import LATEST
    from fruxel.train.engine.trainer import Trainer

    # What can be checked is checked before the run folder is made and the model built.
    if args.device is not None:
        torch_device(args.device)
    config = None if args.resume else _config(args)
    check_output_folder(args.out, "--out")
    show = not args.quiet and _main_rank()
    trainer = None
    try:
        trainer = Trainer(config, args.out, resume=args.resume, device=args.device, progress=show,
                          overrides=overrides if args.resume else None, overwrite=args.overwrite)
        result = trainer.fit()
    except KeyboardInterrupt:
        if _main_rank():
            path = os.path.join(args.out, LATEST)
            if trainer is not None and trainer.saved_step is not None:
                print(f"{PROG}: checkpoint of step {trainer.saved_step} written to {path}; continue with "
                      f"{PROG} --resume --out {args.out}", file=sys.stderr)
            elif args.resume:
                print(f"{PROG}: interrupted before the first step; {path} is unchanged", file=sys.stderr)
            else:
                print(f"{PROG}: interrupted before the first step; no checkpoint written", file=sys.stderr)
        raise
    finally:
        distributed.teardown()
    if show:
        line = _summary(args.out, trainer.config, result)
        if args.resume and trainer.saved_step is None:
            line += f"; nothing left to train (give --steps more than {result.step} to train longer)"
        print(line)
    return 0


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``fruxel-train`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    return run(_main, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

"""``fruxel-calibrate``: choose a trained model's inference rules on training-split samples and write the model
with them.

    fruxel-calibrate runs/x/model.safetensors --out runs/x/calibrated.safetensors --fill --first-hit-label
    fruxel-calibrate MODEL --data data/set --split train --out CALIBRATED.safetensors
    fruxel-calibrate MODEL --seed 100 --samples 2048 --device cuda --workers 14 --fill --first-hit-label
        --flip-average --out CALIBRATED.safetensors
    fruxel-calibrate MODEL --test-set any-camera [--assets DIR] --out CALIBRATED.safetensors

Predicts ``--samples`` samples of ``--split`` (default ``train``: never the test split the model is evaluated on;
without ``--data``, the simulator's split streamed with data seed ``--seed``, so that calibration can draw rooms no
training run drew; with ``--test-set NAME``, the split of a held-out test set's stream (by default ``any-camera``
for a model that labels the furnished rooms' classes: :func:`fruxel.train.sim.testsets.default_test_set`),
:data:`fruxel.train.sim.testsets.TEST_SETS`, whose rooms of the ``train`` split training never drew either) once,
counts mIoU, completion IoU, own-view and novel-view first-hit accuracy (the novel views
unless ``--no-novel``) at every ``--offsets`` value added to the empty logit (with ``--fill``: and
``fill_columns`` after it at every ``--thresholds`` value; with ``--first-hit-label``, ``first_hit_label`` last in
every pair; with ``--flip-average``, every prediction the average of the image's and its mirror image's), prints
the table, picks the rules by :func:`fruxel.train.eval.calibrate.choose_rules` and writes the model's weights
unchanged with those rules (:class:`fruxel.train.rules.InferenceRules`, the ``rules`` of its metadata), the sweep
recorded in its ``training`` metadata under ``calibration``.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Sequence
from typing import Any

from .common import (
    OneLineParser,
    UsageError,
    add_test_set_options,
    check_test_set_options,
    data_source,
    device_name,
    non_negative_int,
    positive_int,
    run,
    streamed_source,
)

PROG = "fruxel-calibrate"
DEFAULT_OFFSETS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0)
"""Empty-logit offsets tried by default."""
DEFAULT_THRESHOLDS = (0.5, 0.6, 0.7, 0.8, 0.9)
"""``fill_threshold`` values tried by default with ``--fill``."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser of ``fruxel-calibrate``."""
    p = OneLineParser(prog=PROG, description="Choose a trained model's inference rules on training-split samples "
                      "and write the model with them (weights unchanged).")
    p.add_argument("model", help="trained model: a .safetensors file, a training checkpoint or a shipped model's name")
    p.add_argument("--out", required=True, help="calibrated model file to write (.safetensors)")
    p.add_argument("--data", default=None, help="data set folder (fruxel-sim generate) or data folder of labelled "
                   "photos (docs/your-data.md) holding --split (default: "
                   "stream the simulator's --split with data seed --seed)")
    p.add_argument("--split", default="train", help="split to calibrate on (default train)")
    add_test_set_options(p)
    p.add_argument("--seed", type=non_negative_int, default=None, metavar="S",
                   help="data seed of streamed samples (without --data; default 0)")
    p.add_argument("--workers", type=non_negative_int, default=0, metavar="K",
                   help="worker processes that make or read the samples (default 0: this process)")
    p.add_argument("--device", type=device_name, default="cpu", metavar="cpu|cuda[:N]",
                   help="where the model runs (default cpu)")
    p.add_argument("--samples", type=positive_int, default=512, help="samples of the split (default 512)")
    p.add_argument("--offsets", type=float, nargs="+", default=list(DEFAULT_OFFSETS),
                   help="empty-logit offsets to try; 0 is always added")
    p.add_argument("--fill", action="store_true", help="use fill_columns and calibrate its threshold")
    p.add_argument("--thresholds", type=float, nargs="+", default=list(DEFAULT_THRESHOLDS),
                   help="with --fill: fill_threshold values to try, in (0, 1]; the model's own is always added")
    p.add_argument("--first-hit-label", action="store_true",
                   help="use first_hit_label (after the other rules, in every pair)")
    p.add_argument("--flip-average", action="store_true",
                   help="use flip_average (the image and its mirror image averaged first)")
    p.add_argument("--no-novel", dest="novel", action="store_false",
                   help="leave the novel views out of the sweep and of the choice (faster)")
    p.add_argument("--backend", default=None, help="kernel backend of the novel views (default: the best available)")
    p.add_argument("--batch", type=positive_int, default=16, help="samples per batch (default 16)")
    return p


def _check(args: argparse.Namespace) -> None:
    """Refuse what does not go together, before any model is loaded."""
    if not all(math.isfinite(o) for o in args.offsets):
        raise UsageError("--offsets must be finite numbers")
    if not all(0.0 < t <= 1.0 for t in args.thresholds):  # NaN fails too
        raise UsageError("--thresholds must be numbers in (0, 1]")
    if not args.out.endswith(".safetensors"):
        raise UsageError(f"--out {args.out}: must end in .safetensors")
    if args.data is not None and args.seed is not None:
        raise UsageError("--seed picks streamed samples; a data set (--data) has its own")
    check_test_set_options(args)


def _samples(args: argparse.Namespace, config: Any) -> tuple[Any, int]:
    """``(source, count)``: where the samples come from and how many there are, checked against the model
    (:func:`fruxel.cli.common.streamed_source`)."""
    from fruxel.train.samples import split_size

    if args.data is None:
        return streamed_source(args, config), args.samples
    source = data_source(args.data, config)
    return source, min(args.samples, split_size(source, config, args.split))


def _table(summaries: dict[tuple[float, float], dict[str, Any]], best: tuple[float, float], fill: bool,
           novel: bool) -> str:
    """The sweep as a Markdown table, the chosen rules marked."""
    from fruxel.train.eval.calibrate import rules_score

    lines = ["| empty offset | fill threshold | mIoU | completion IoU | own view % | novel view % | sum |",
             "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for r, s in summaries.items():
        mark = " (chosen)" if r == best else ""
        t = f"{r[1]:.2f}" if fill else "-"
        nv = f"{s['novel_view_accuracy']:.2f}" if novel else "-"
        lines.append(f"| {r[0]:+.2f}{mark} | {t} | {s['miou']:.2f} | {s['completion_iou']:.2f} | "
                     f"{s['own_view_accuracy']:.2f} | {nv} | {rules_score(s):.2f} |")
    return "\n".join(lines)


def _main(args: argparse.Namespace) -> None:
    from tqdm import tqdm

    from fruxel.train.engine.data import to_device
    from fruxel.train.eval.calibrate import choose_rules, rules_of, sweep_rules
    from fruxel.train.model_files import load_model, save_model
    from fruxel.train.rules import InferenceRules
    from fruxel.train.samples import split_batches

    from .common import torch_device

    _check(args)
    device = torch_device(args.device)
    m = load_model(args.model)
    base = InferenceRules(flip_average=args.flip_average, fill_columns=args.fill,
                          fill_threshold=m.rules.fill_threshold, first_hit_label=args.first_hit_label)
    source, count = _samples(args, m.config)
    offsets = sorted({0.0, *map(float, args.offsets)})
    thresholds = sorted({base.fill_threshold, *map(float, args.thresholds)})

    def images(pairs):  # noqa: ANN001, ANN202
        with tqdm(total=count, desc="calibrate", unit="sample", leave=False, disable=None) as bar:
            for image, labels, *camera in pairs:
                yield *to_device({"image": image, "labels": labels}, device), *camera
                bar.update(len(labels))

    # A model that reads the camera is calibrated with the pose the samples record (as fruxel-eval's default).
    pairs = split_batches(source, m.config, args.split, count, args.batch, workers=args.workers,
                          camera=m.config.reads_camera)
    accs = sweep_rules(m.network.to(device), images(pairs), offsets, thresholds, m.config.num_classes, base=base,
                       device=device, grid=m.config.grid if args.novel else None, backend=args.backend)
    summaries = {r: a.summary() for r, a in accs.items()}
    best = choose_rules(summaries, (0.0, base.fill_threshold))
    rules = rules_of(base, best)
    print(f"{count} samples of {source.describe()} split {args.split}; rules swept: {base}")
    print(_table(summaries, best, args.fill, args.novel))
    sweep = {(f"{r[0]:g}/{r[1]:g}" if args.fill else f"{r[0]:g}"):
             {k: round(s[k], 3) for k in ("miou", "completion_iou", "own_view_accuracy", "novel_view_accuracy")
              if s[k] is not None} for r, s in summaries.items()}
    stream = f"stream:seed={source.seed}" + (f",test-set={source.test_set}" if source.test_set else "")
    calibration = {"data": args.data or stream, "split": args.split, "samples": count,
                   "rules": rules.to_dict(), "sweep": sweep}
    # Stored as the file stored them: the weights written back are the weights read.
    save_model(args.out, m.network.cpu(), m.config, rules, {**m.training, "calibration": calibration}, half=m.half)
    print(f"wrote {args.out}: {rules}")


def main(argv: Sequence[str] | None = None) -> int:
    """Run ``fruxel-calibrate`` with ``argv`` (default ``sys.argv[1:]``); returns the exit status."""
    return run(_main, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

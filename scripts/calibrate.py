"""Choose a trained SSZ's inference rules on training-split samples and write the calibrated model file.

    python scripts/calibrate.py MODEL.safetensors --data data/eval64 --out CALIBRATED.safetensors [--fill]
    python scripts/calibrate.py MODEL.safetensors --seed 100 --samples 2048 --device cuda --workers 14 --fill
        --first-hit-label --out CALIBRATED.safetensors

Predicts ``--samples`` samples of the data set's ``--split`` (default ``train``: never the test split the model is
evaluated on; without ``--data``, the simulator's ``--split`` streamed with data seed ``--seed``, so that the
calibration can draw rooms no training run drew) once, counts mIoU, completion IoU, own-view and novel-view
first-hit accuracy (the novel views unless ``--no-novel``) at every ``--offsets`` value added to the empty logit
(with ``--fill``: and ``fill_columns`` after it at every ``--thresholds`` value; with ``--first-hit-label``,
``first_hit_label`` last in every pair; with ``--flip-average``, every prediction the average of the image's and
its mirror image's), prints the table, picks the rules by
:func:`fruxel.train.eval.calibrate.choose_rules` and writes the model with ``empty_offset`` (and ``fill_columns``,
``fill_threshold``, ``first_hit_label``, ``flip_average``) set, the sweep recorded in its ``training`` metadata
under ``calibration``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence

from fruxel.cli.common import OneLineParser, UsageError, device_name, non_negative_int, run, torch_device

DEFAULT_OFFSETS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0)
DEFAULT_THRESHOLDS = (0.5, 0.6, 0.7, 0.8, 0.9)


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="calibrate.py", description=__doc__.split("\n\n")[0])
    p.add_argument("model", help="trained model (.safetensors or checkpoint)")
    p.add_argument("--data", default=None, help="data set folder (fruxel-sim generate) holding --split (default: "
                   "stream the simulator's --split with data seed --seed)")
    p.add_argument("--split", default="train", help="split to calibrate on (default train)")
    p.add_argument("--seed", type=non_negative_int, default=None, metavar="S",
                   help="data seed of streamed samples (without --data; default 0)")
    p.add_argument("--workers", type=non_negative_int, default=0, metavar="K",
                   help="worker processes that make or read the samples (default 0: this process)")
    p.add_argument("--device", type=device_name, default="cpu", metavar="cpu|cuda[:N]",
                   help="where the model runs (default cpu)")
    p.add_argument("--samples", type=int, default=512, help="samples of the split (default 512)")
    p.add_argument("--offsets", type=float, nargs="+", default=list(DEFAULT_OFFSETS),
                   help="empty-logit offsets to try; 0 is always added")
    p.add_argument("--fill", action="store_true", help="set fill_columns and calibrate with it")
    p.add_argument("--thresholds", type=float, nargs="+", default=list(DEFAULT_THRESHOLDS),
                   help="with --fill: fill_threshold values to try, in (0, 1]; the model's own is always added")
    p.add_argument("--first-hit-label", action="store_true",
                   help="set first_hit_label and calibrate with it (after the other rules, in every pair)")
    p.add_argument("--flip-average", action="store_true",
                   help="set flip_average and calibrate with it (the image and its mirror image averaged first)")
    p.add_argument("--no-novel", dest="novel", action="store_false",
                   help="leave the novel views out of the sweep and of the choice (faster)")
    p.add_argument("--backend", default=None, help="kernel backend of the novel views (default: the best available)")
    p.add_argument("--batch", type=int, default=16, help="samples per batch")
    p.add_argument("--out", required=True, help="calibrated model file to write (.safetensors)")
    return p


def _main(args: argparse.Namespace) -> None:
    import math

    from tqdm import tqdm

    from fruxel.train.config import ConfigError
    from fruxel.train.eval.calibrate import choose_rules, rules_score, sweep_rules
    from fruxel.train.eval.samples import EvalData, batches, data_set_manifest, split_size
    from fruxel.train.export import load_generator, save_shipped

    if args.samples < 1 or args.batch < 1:
        raise UsageError("--samples and --batch must be >= 1")
    if not all(math.isfinite(o) for o in args.offsets):
        raise UsageError("--offsets must be finite numbers")
    if not all(0.0 < t <= 1.0 for t in args.thresholds):  # NaN fails too
        raise UsageError("--thresholds must be numbers in (0, 1]")
    if not args.out.endswith(".safetensors"):
        raise UsageError(f"--out {args.out}: must end in .safetensors")
    if args.data is not None and args.seed is not None:
        raise UsageError("--seed picks streamed samples; a data set (--data) has its own")
    device = torch_device(args.device)
    generator, config, training = load_generator(args.model)
    try:  # the model's own check: fill_columns needs the column depth head
        dataclasses.replace(config, fill_columns=bool(args.fill)).check()
    except ConfigError as e:
        raise UsageError(f"{args.model}: --fill: {e}") from None
    if args.data is not None:
        manifest = data_set_manifest(args.data, config)
        data = EvalData(source="shards", root=args.data, seed=manifest.seed)
        count = min(args.samples, split_size(data, config, args.split))
    else:
        data = EvalData(source="stream", seed=args.seed or 0)
        count = args.samples
    offsets = sorted({0.0, *map(float, args.offsets)})
    thresholds = sorted({config.fill_threshold, *map(float, args.thresholds)})

    def images(pairs):  # noqa: ANN001, ANN202
        with tqdm(total=count, desc="calibrate", unit="sample", leave=False, disable=None) as bar:
            for image, labels in pairs:
                yield image.permute(0, 3, 1, 2).float() / 255, labels
                bar.update(len(labels))

    generator.flip_average = bool(args.flip_average)
    generator.to(device)
    pairs = batches(data, config, args.split, count, args.batch, workers=args.workers)
    accs = sweep_rules(generator, images(pairs), offsets, thresholds, config.num_classes, fill=args.fill,
                       device=device, grid=config.grid if args.novel else None, backend=args.backend,
                       first_hit=args.first_hit_label)
    summaries = {r: a.summary() for r, a in accs.items()}
    offset, threshold = best = choose_rules(summaries, (0.0, config.fill_threshold))
    source = args.data or f"the simulator (data seed {data.seed})"
    print(f"{count} samples of {source} split {args.split}, fill_columns {args.fill}, "
          f"first_hit_label {args.first_hit_label}, flip_average {args.flip_average}")
    print("| empty offset | fill threshold | mIoU | completion IoU | own view % | novel view % | sum |\n"
          "| ---: | ---: | ---: | ---: | ---: | ---: | ---: |")
    for r, s in summaries.items():
        mark = " (chosen)" if r == best else ""
        t = f"{r[1]:.2f}" if args.fill else "-"
        novel = f"{s['novel_view_accuracy']:.2f}" if args.novel else "-"
        print(f"| {r[0]:+.2f}{mark} | {t} | {s['miou']:.2f} | {s['completion_iou']:.2f} | "
              f"{s['own_view_accuracy']:.2f} | {novel} | {rules_score(s):.2f} |")
    calibrated = dataclasses.replace(config, empty_offset=offset, fill_columns=bool(args.fill),
                                     fill_threshold=threshold, first_hit_label=bool(args.first_hit_label),
                                     flip_average=bool(args.flip_average))
    generator.cpu()
    sweep = {(f"{r[0]:g}/{r[1]:g}" if args.fill else f"{r[0]:g}"):
             {k: round(s[k], 3) for k in ("miou", "completion_iou", "own_view_accuracy", "novel_view_accuracy")
              if s[k] is not None} for r, s in summaries.items()}
    training = {**training, "calibration": {"data": args.data or f"stream:seed={data.seed}", "split": args.split,
                                            "samples": count, "fill_columns": bool(args.fill),
                                            "first_hit_label": bool(args.first_hit_label),
                                            "flip_average": bool(args.flip_average), "empty_offset": offset,
                                            **({"fill_threshold": threshold} if args.fill else {}), "sweep": sweep}}
    save_shipped(args.out, generator, calibrated, training, half=True)
    print(f"wrote {args.out}: empty_offset {offset:g}, fill_columns {args.fill}"
          + (f", fill_threshold {threshold:g}" if args.fill else "") + f", first_hit_label {args.first_hit_label}"
          + f", flip_average {args.flip_average}")


def main(argv: Sequence[str] | None = None) -> int:
    return run(_main, _parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

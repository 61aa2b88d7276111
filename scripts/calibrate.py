"""Choose a trained SSZ's empty-logit offset on training-split samples and write the calibrated model file.

    python scripts/calibrate.py MODEL.safetensors --data data/eval64 --out CALIBRATED.safetensors [--fill]

Predicts ``--samples`` samples of the data set's ``--split`` (default ``train``: never the test split the model is
evaluated on) once, counts mIoU, completion IoU and own-view first-hit accuracy at every ``--offsets`` value added
to the empty logit (with ``fill_columns`` after it when ``--fill``), prints the table, picks the offset by
:func:`fruxel.train.eval.calibrate.choose_offset` and writes the model with ``empty_offset`` (and
``fill_columns``) set, the sweep recorded in its ``training`` metadata under ``calibration``.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Sequence

from fruxel.cli.common import OneLineParser, UsageError, run

DEFAULT_OFFSETS = (0.0, 0.25, 0.5, 0.75, 1.0, 1.5, 2.0, 2.5, 3.0, 4.0)


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="calibrate.py", description=__doc__.split("\n\n")[0])
    p.add_argument("model", help="trained model (.safetensors or checkpoint)")
    p.add_argument("--data", required=True, help="data set folder (fruxel-sim generate) holding --split")
    p.add_argument("--split", default="train", help="split to calibrate on (default train)")
    p.add_argument("--samples", type=int, default=512, help="samples of the split (default 512)")
    p.add_argument("--offsets", type=float, nargs="+", default=list(DEFAULT_OFFSETS),
                   help="empty-logit offsets to try; 0 is always added")
    p.add_argument("--fill", action="store_true", help="set fill_columns and calibrate with it")
    p.add_argument("--batch", type=int, default=16, help="samples per batch")
    p.add_argument("--out", required=True, help="calibrated model file to write (.safetensors)")
    return p


def _main(args: argparse.Namespace) -> None:
    import math

    import torch
    from tqdm import tqdm

    from fruxel.train.config import ConfigError
    from fruxel.train.eval.calibrate import choose_offset, sweep_offsets
    from fruxel.train.eval.samples import EvalData, batches, data_set_manifest, split_size
    from fruxel.train.export import load_generator, save_shipped

    if args.samples < 1 or args.batch < 1:
        raise UsageError("--samples and --batch must be >= 1")
    if not all(math.isfinite(o) for o in args.offsets):
        raise UsageError("--offsets must be finite numbers")
    if not args.out.endswith(".safetensors"):
        raise UsageError(f"--out {args.out}: must end in .safetensors")
    generator, config, training = load_generator(args.model)
    try:  # the model's own check: fill_columns needs the column depth head
        dataclasses.replace(config, fill_columns=bool(args.fill)).check()
    except ConfigError as e:
        raise UsageError(f"{args.model}: --fill: {e}") from None
    manifest = data_set_manifest(args.data, config)
    data = EvalData(source="shards", root=args.data, seed=manifest.seed)
    count = min(args.samples, split_size(data, config, args.split))
    offsets = sorted({0.0, *map(float, args.offsets)})

    def images(pairs):  # noqa: ANN001, ANN202
        with tqdm(total=count, desc="calibrate", unit="sample", leave=False, disable=None) as bar:
            for image, labels in pairs:
                yield image.permute(0, 3, 1, 2).float() / 255, labels
                bar.update(len(labels))

    accs = sweep_offsets(generator, images(batches(data, config, args.split, count, args.batch)), offsets,
                         config.num_classes, fill=args.fill, device=torch.device("cpu"))
    summaries = {o: a.summary() for o, a in accs.items()}
    best = choose_offset(summaries)
    print(f"{count} samples of {args.data} split {args.split}, fill_columns {args.fill}")
    print("| empty offset | mIoU | completion IoU | own view % |\n| ---: | ---: | ---: | ---: |")
    for o, s in summaries.items():
        mark = " (chosen)" if o == best else ""
        print(f"| {o:+.2f}{mark} | {s['miou']:.2f} | {s['completion_iou']:.2f} | {s['own_view_accuracy']:.2f} |")
    calibrated = dataclasses.replace(config, empty_offset=best, fill_columns=bool(args.fill))
    generator.empty_offset, generator.fill_columns = best, bool(args.fill)
    sweep = {f"{o:g}": {k: round(s[k], 3) for k in ("miou", "completion_iou", "own_view_accuracy")}
             for o, s in summaries.items()}
    training = {**training, "calibration": {"data": args.data, "split": args.split, "samples": count,
                                            "fill_columns": bool(args.fill), "empty_offset": best, "sweep": sweep}}
    save_shipped(args.out, generator, calibrated, training, half=True)
    print(f"wrote {args.out}: empty_offset {best:g}, fill_columns {args.fill}")


def main(argv: Sequence[str] | None = None) -> int:
    return run(_main, _parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

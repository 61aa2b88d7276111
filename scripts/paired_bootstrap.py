"""How sure an mIoU difference is: models compared on the same held-out samples, resampled by room.

    python scripts/paired_bootstrap.py MODEL MODEL [MODEL ...] [--test-set any-camera] [--samples 256]
        [--camera-known gravity,height] [--raw] [--rounds 2000]

The samples are fruxel-eval's (the same stream, seed 0, augmented, and its sample cache: run after a `fruxel-eval`
of the same test set and count). A streamed test set's consecutive samples share one room (16 a room: 256 samples
are 16 rooms), so they are not independent: the bootstrap draws *rooms* with replacement, the same draw for every
model (paired), and recomputes each model's mIoU from the summed confusion counts of the rooms drawn, as
fruxel-eval computes it (mean over the classes present in the drawn truth). Printed: each model's mIoU with its 95 %
interval, the spread of its per-room mIoU, and each model's difference from the first one with its 95 % interval
and the share of draws in which it is above zero. An analysis for the experiments log, not a metric of the
product's reports.
"""

from __future__ import annotations

import argparse
import sys
import warnings

import numpy as np


def room_samples() -> int:
    """Consecutive samples of one room in fruxel-eval's streamed test sets (its ``SampleSource``'s default)."""
    from fruxel.train.samples import SampleSource

    return int(SampleSource.samples_per_scene)


def room_confusions(pairs, classes: int, per_room: int) -> np.ndarray:
    """``(rooms, C, C)`` int64 confusion counts ``[true, predicted]`` per room from ``(prediction, truth)`` label
    volumes ``(B, D, H, W)`` (batches in sample order; sample ``n`` is in room ``n // per_room``)."""
    import torch

    from fruxel.train.eval.metrics import confusion

    rooms: list[np.ndarray] = []
    n = 0
    for pred, truth in pairs:
        for b in range(pred.shape[0]):
            if n % per_room == 0:
                rooms.append(np.zeros((classes, classes), dtype=np.int64))
            rooms[-1] += confusion(torch.from_numpy(pred[b]), torch.from_numpy(truth[b]), classes).numpy()
            n += 1
    return np.stack(rooms)


def miou(conf: np.ndarray) -> np.ndarray:
    """mIoU in percent over the classes present in the truth (class 0, empty, left out), as fruxel-eval's, of
    confusion counts ``(..., C, C)``; NaN where no class is present."""
    tp = np.diagonal(conf, axis1=-2, axis2=-1).astype(np.float64)
    true, pred = conf.sum(axis=-1), conf.sum(axis=-2)
    with np.errstate(invalid="ignore", divide="ignore"):
        iou = tp / (true + pred - tp)
    present = true > 0
    iou = np.where(present, iou, np.nan)[..., 1:]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)  # a room with no class present: NaN, said in the docstring
        return 100.0 * np.nanmean(iou, axis=-1)


def bootstrap(confs: np.ndarray, rounds: int, seed: int = 0) -> np.ndarray:
    """``(rounds, models)`` mIoU of room draws with replacement, the same draws for every model.

    Args:
        confs: ``(models, rooms, C, C)`` int64 per-room confusion counts.
        rounds: draws.
        seed: the draws' seed.
    """
    rng = np.random.default_rng(seed)
    rooms = confs.shape[1]
    out = np.empty((rounds, confs.shape[0]))
    for r in range(rounds):
        counts = np.bincount(rng.integers(0, rooms, rooms), minlength=rooms)
        out[r] = miou(np.tensordot(counts, confs, axes=([0], [1])))
    return out


def _main(args: argparse.Namespace) -> int:
    import os

    sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
    from depth_tolerance import held_out_predictions

    per_room = room_samples()
    confs = []
    for model in args.model:
        names, pairs = held_out_predictions(model, args.test_set, args.samples, args.batch, args.camera_known,
                                            raw=args.raw, device=args.device)
        confs.append(room_confusions(pairs, len(names), per_room))
    confs = np.stack(confs)
    whole = miou(confs.sum(axis=1))
    draws = bootstrap(confs, args.rounds)
    rooms = miou(confs)
    print(f"{confs.shape[1]} rooms of {per_room} samples, {args.rounds} paired draws of rooms")
    for m, model in enumerate(args.model):
        lo, hi = np.percentile(draws[:, m], [2.5, 97.5])
        print(f"{model}: mIoU {whole[m]:.2f} [{lo:.2f}, {hi:.2f}]; per room {np.nanmin(rooms[m]):.1f} to "
              f"{np.nanmax(rooms[m]):.1f}")
    for m in range(1, len(args.model)):
        d = draws[:, m] - draws[:, 0]
        lo, hi = np.percentile(d, [2.5, 97.5])
        print(f"{args.model[m]} - {args.model[0]}: {whole[m] - whole[0]:+.2f} [{lo:+.2f}, {hi:+.2f}], above zero in "
              f"{100.0 * float((d > 0).mean()):.0f} % of draws")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv``, print the comparison; bad input is one error line and status 2 (fruxel's commands' runner)."""
    from fruxel.cli.common import OneLineParser, UsageError, run

    p = OneLineParser(prog="paired_bootstrap.py", description=__doc__.split("\n\n")[0])
    p.add_argument("model", nargs="+", help="shipped models' names, .safetensors files or training checkpoints")
    p.add_argument("--test-set", default="any-camera")
    p.add_argument("--samples", type=int, default=256)
    p.add_argument("--camera-known", default="gravity,height", help="pieces of the camera told (empty: none)")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--raw", action="store_true", help="the networks alone, without their files' inference rules")
    p.add_argument("--rounds", type=int, default=2000)
    p.add_argument("--device", default="cpu", help="where the networks run (cpu, cuda)")

    def checked(args: argparse.Namespace) -> int:
        if len(args.model) < 2:
            raise UsageError("give two models or more: the first is the one the others are compared with")
        if args.rounds < 100:
            raise UsageError(f"--rounds must be at least 100, got {args.rounds}")
        n = room_samples()
        if args.samples < 2 * n or args.samples % n:
            raise UsageError(f"--samples must be a multiple of {n} (whole rooms), at least two rooms; got "
                             f"{args.samples}")
        from fruxel.train.model_files import read_model_file

        for model in args.model:  # every file read before the first model's slow predictions
            read_model_file(model)
        return _main(args)

    return run(checked, p, argv)


if __name__ == "__main__":
    sys.exit(main())

"""How near a model's wrong cells are: per-class IoU on held-out samples where a cell's class counts as found when
the other volume has that class within ``r`` depth slices along the same column (``r = 0`` is the usual IoU).

    python scripts/depth_tolerance.py MODEL [--test-set any-camera] [--samples 256] [--camera-known gravity,height]

The samples are fruxel-eval's (the same stream, seed 0, augmented, and its sample cache: run after a `fruxel-eval`
of the same test set and count, nothing is simulated again). With ``r`` slices of tolerance a predicted cell of
class c is right when the truth has c within ``r`` slices of it in depth, and a true cell is found when the
prediction has c within ``r`` slices; the IoU is then ``1 / (1/precision + 1/recall - 1)``, which for ``r = 0`` is
``TP / (TP + FP + FN)``. Then, for the cells that one slice of tolerance leaves wrong, what they are: true cells
not found that the prediction leaves empty, and that lie behind the first occupied cell of their column (hidden
from the camera); predicted cells not right where the truth is empty. An analysis for the experiments log, not a
metric of the product's reports.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Iterator

import numpy as np

TOLERANCES = (0, 1, 2)
"""Depth slices of tolerance reported."""


def widen(mask: np.ndarray, r: int) -> np.ndarray:
    """``mask`` ``(B, D, H, W)`` bool, true also within ``r`` slices along D of a true cell."""
    out = mask.copy()
    for s in range(1, r + 1):
        out[:, s:] |= mask[:, :-s]
        out[:, :-s] |= mask[:, s:]
    return out


def tolerant_counts(pred: np.ndarray, truth: np.ndarray, classes: int, r: int) -> np.ndarray:
    """``(classes, 4)`` int64 counts per class of ``(B, D, H, W)`` label volumes: predicted cells, true cells,
    predicted cells with the class within ``r`` slices in the truth, true cells with it within ``r`` in the
    prediction (row 0, empty, stays zero)."""
    out = np.zeros((classes, 4), dtype=np.int64)
    for c in range(1, classes):
        p, t = pred == c, truth == c
        out[c] = p.sum(), t.sum(), (p & widen(t, r)).sum(), (t & widen(p, r)).sum()
    return out


def error_counts(pred: np.ndarray, truth: np.ndarray, classes: int, r: int = 1) -> np.ndarray:
    """``(classes, 5)`` int64 counts per class of what ``r`` slices of tolerance leave wrong: true cells not found,
    of which predicted empty, of which hidden (behind their column's first occupied cell); predicted cells not
    right, of which empty in the truth."""
    occupied = truth != 0
    first = occupied.argmax(axis=1)[:, None]
    hidden = np.arange(truth.shape[1])[None, :, None, None] > first
    out = np.zeros((classes, 5), dtype=np.int64)
    for c in range(1, classes):
        p, t = pred == c, truth == c
        missed, wrong = t & ~widen(p, r), p & ~widen(t, r)
        out[c] = missed.sum(), (missed & (pred == 0)).sum(), (missed & hidden).sum(), wrong.sum(), \
            (wrong & ~occupied).sum()
    return out


def tolerant_iou(counts: np.ndarray) -> np.ndarray:
    """Per-class IoU (percent; NaN for a class in neither volume) from :func:`tolerant_counts`."""
    pred, true, right, found = (counts[:, k].astype(np.float64) for k in range(4))
    with np.errstate(invalid="ignore", divide="ignore"):
        precision, recall = right / pred, found / true
        iou = np.where((precision > 0) & (recall > 0), 1.0 / (1.0 / precision + 1.0 / recall - 1.0), 0.0)
    return 100.0 * np.where((pred + true) > 0, iou, np.nan)


def held_out_predictions(model: str, test_set: str, samples: int, batch: int, camera_known: str, raw: bool = False,
                         device: str = "cpu") -> tuple[tuple[str, ...], Iterator[tuple[np.ndarray, np.ndarray]]]:
    """The model's class names and its ``(prediction, truth)`` label volumes ``(B, D, H, W)`` uint8, batch by batch,
    on fruxel-eval's held-out samples of ``test_set`` (its sample cache), with the pieces of the camera in
    ``camera_known`` (comma-separated; empty: none) told to a model that reads the camera; ``raw``: the network
    alone, without the file's inference rules; ``device``: where the network runs (``cpu``, ``cuda``)."""
    import torch

    from fruxel.train.engine.data import to_device
    from fruxel.train.eval.evaluate import model_predict
    from fruxel.train.eval.sample_cache import cached_split_batches
    from fruxel.train.model_files import load_model
    from fruxel.train.rules import NO_RULES
    from fruxel.train.samples import SampleSource

    m = load_model(model, device=device)
    known = [k for k in camera_known.split(",") if k] if m.config.reads_camera else None
    predict = model_predict(m.network, NO_RULES if raw else m.rules, camera_known=known)
    source = SampleSource(seed=0, assets="", test_set=test_set, augment=True)

    def pairs() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        with torch.no_grad():
            for image, labels, record in cached_split_batches(source, m.config, "test", samples, batch,
                                                              device=device, camera=True):
                x, _ = to_device({"image": image, "labels": labels}, torch.device(device))
                yield predict(x, labels, record).cpu().numpy(), labels.cpu().numpy()

    return tuple(m.config.classes.names), pairs()


def add_arguments(p: argparse.ArgumentParser) -> None:
    """The model and sample arguments both analysis scripts take."""
    p.add_argument("model", help="a shipped model's name, a .safetensors file or a training checkpoint")
    p.add_argument("--test-set", default="any-camera")
    p.add_argument("--samples", type=int, default=256)
    p.add_argument("--camera-known", default="gravity,height", help="pieces of the camera told (empty: none)")
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--device", default="cpu", help="where the network runs (cpu, cuda)")


def _main(args: argparse.Namespace) -> int:
    names, pairs = held_out_predictions(args.model, args.test_set, args.samples, args.batch, args.camera_known,
                                        device=args.device)
    counts = {r: np.zeros((len(names), 4), dtype=np.int64) for r in TOLERANCES}
    errors = np.zeros((len(names), 5), dtype=np.int64)
    for pred, truth in pairs:
        for r in TOLERANCES:
            counts[r] += tolerant_counts(pred, truth, len(names), r)
        errors += error_counts(pred, truth, len(names))
    for r in TOLERANCES:
        iou = tolerant_iou(counts[r])
        present = counts[r][:, 1] > 0
        print(f"within {r} slice(s): mIoU {np.nanmean(iou[present]):.1f} | "
              + " ".join(f"{names[c]} {iou[c]:.1f}" for c in range(1, len(names))))
    print("wrong within 1 slice (% of the class's true cells not found: predicted empty, hidden | % of its "
          "predicted cells not right: empty in the truth):")
    with np.errstate(invalid="ignore", divide="ignore"):
        share = 100.0 * errors[:, [1, 2, 4]] / errors[:, [0, 0, 3]]
    print(" | ".join(f"{names[c]} {share[c, 0]:.0f}, {share[c, 1]:.0f} | {share[c, 2]:.0f}"
                     for c in range(1, len(names))))
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv``, print the tables; bad input is one error line and status 2 (fruxel's commands' runner)."""
    from fruxel.cli.common import OneLineParser, run

    p = OneLineParser(prog="depth_tolerance.py", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    return run(_main, p, argv)


if __name__ == "__main__":
    sys.exit(main())

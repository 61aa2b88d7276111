"""The most a rule that fixes the depth of what the camera sees could give: mIoU on held-out samples when each
column's predicted content is shifted along the column so that its first occupied cell lies where the truth's does
(an oracle: the truth hands over the depth a pose-given geometric rule would have to find).

    python scripts/depth_snap.py MODEL [--test-set any-camera] [--samples 256] [--classes wall] [--within 2]

A column moves when the first occupied cells of prediction and truth are both of ``--classes`` (all classes when
not given) and at most ``--within`` slices apart (0: any distance): its first run (the first cell and the cells of
its class right behind it) moves, the rest of the column stays; with ``--carry`` the whole column moves. The
samples are fruxel-eval's (run after a `fruxel-eval` of the same test set and count: its sample cache, nothing
simulated again), the pose told. An analysis for the experiments log, not a metric of the product's reports.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from depth_tolerance import tolerant_counts, tolerant_iou  # noqa: E402


def shift_columns(volume: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``volume`` ``(B, D, H, W)`` with column ``(b, j, i)`` moved ``delta[b, j, i]`` slices along D (positive:
    farther); slices moved in from outside are 0 (empty)."""
    k = np.arange(volume.shape[1])[None, :, None, None] - delta[:, None]
    inside = (k >= 0) & (k < volume.shape[1])
    return np.where(inside, np.take_along_axis(volume, np.clip(k, 0, volume.shape[1] - 1), axis=1), 0)


def move_first_runs(volume: np.ndarray, delta: np.ndarray) -> np.ndarray:
    """``volume`` ``(B, D, H, W)`` with only each column's first run (its first occupied cell and the cells of the
    same class right behind it: the surface the camera sees, as deep as it goes) moved ``delta`` slices along D;
    it overwrites what it lands on and leaves empty where it was."""
    k = np.arange(volume.shape[1])[None, :, None, None]
    first = (volume != 0).argmax(axis=1)[:, None]
    cls = np.take_along_axis(volume, first, axis=1)
    after = k >= first
    ends = np.where((after & (volume != cls)).any(axis=1, keepdims=True),
                    (after & (volume != cls)).argmax(axis=1)[:, None], volume.shape[1])
    run = after & (k < ends) & (cls != 0)
    moved = shift_columns(np.where(run, volume, 0), delta)
    return np.where(moved != 0, moved, np.where(run, 0, volume))


def snap_shifts(pred: np.ndarray, truth: np.ndarray, classes: list[int], within: int) -> np.ndarray:
    """``(B, H, W)`` int64: per column, the shift that puts the prediction's first occupied cell on the truth's,
    where both are occupied, both first cells are of ``classes`` and at most ``within`` slices apart (0: any); 0
    elsewhere. ``pred``, ``truth``: ``(B, D, H, W)`` labels."""
    occupied_p, occupied_t = pred != 0, truth != 0
    kp, kt = occupied_p.argmax(axis=1), occupied_t.argmax(axis=1)
    cp = np.take_along_axis(pred, kp[:, None], axis=1)[:, 0]
    ct = np.take_along_axis(truth, kt[:, None], axis=1)[:, 0]
    move = occupied_p.any(axis=1) & occupied_t.any(axis=1) & np.isin(cp, classes) & np.isin(ct, classes)
    if within > 0:
        move &= np.abs(kt - kp) <= within
    return np.where(move, kt - kp, 0).astype(np.int64)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("model", help="a shipped model's name, a .safetensors file or a training checkpoint")
    p.add_argument("--test-set", default="any-camera")
    p.add_argument("--samples", type=int, default=256)
    p.add_argument("--classes", default="", help="comma-separated class names whose first cells move (default all)")
    p.add_argument("--within", type=int, default=2, help="slices a first cell may move (0: any)")
    p.add_argument("--carry", action="store_true", help="move the whole column, not its first run only")
    p.add_argument("--batch", type=int, default=16)
    args = p.parse_args(argv)
    import torch

    from fruxel.train.engine.data import to_device
    from fruxel.train.eval.evaluate import model_predict
    from fruxel.train.eval.sample_cache import cached_split_batches
    from fruxel.train.model_files import load_model
    from fruxel.train.samples import SampleSource

    m = load_model(args.model, device="cpu")
    names = m.config.classes.names
    unknown = [c for c in args.classes.split(",") if c and c not in names]
    if unknown:
        sys.exit(f"depth_snap: --classes {args.classes}: not classes of the model ({', '.join(names[1:])})")
    classes = [names.index(c) for c in args.classes.split(",") if c] or list(range(1, len(names)))
    predict = model_predict(m.network, m.rules, camera_known=["gravity", "height"] if m.config.reads_camera else None)
    counts = {k: np.zeros((len(names), 4), dtype=np.int64) for k in ("model", "snapped")}
    moved = columns = 0
    source = SampleSource(seed=0, assets="", test_set=args.test_set, augment=True)
    with torch.no_grad():
        for image, labels, record in cached_split_batches(source, m.config, "test", args.samples, args.batch,
                                                          device="cpu", camera=True):
            x, _ = to_device({"image": image, "labels": labels}, torch.device("cpu"))
            pred, truth = predict(x, labels, record).numpy(), labels.numpy()
            shift = snap_shifts(pred, truth, classes, args.within)
            moved, columns = moved + int((shift != 0).sum()), columns + int((pred != 0).any(axis=1).sum())
            counts["model"] += tolerant_counts(pred, truth, len(names), 0)
            snapped = shift_columns(pred, shift) if args.carry else move_first_runs(pred, shift)
            counts["snapped"] += tolerant_counts(snapped, truth, len(names), 0)
    for key, c in counts.items():
        iou = tolerant_iou(c)
        print(f"{key}: mIoU {np.nanmean(iou[c[:, 1] > 0]):.2f} | "
              + " ".join(f"{names[k]} {iou[k]:.1f}" for k in range(1, len(names))))
    print(f"columns moved: {moved} of {columns} occupied ({100.0 * moved / max(columns, 1):.1f} %)")
    return 0


if __name__ == "__main__":
    sys.exit(main())

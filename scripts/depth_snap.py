"""The most a rule that fixes the depth of what the camera sees could give: mIoU on held-out samples when each
column's predicted content is shifted along the column so that its first occupied cell lies where the truth's does
(an oracle: the truth hands over the depth a pose-given geometric rule would have to find).

    python scripts/depth_snap.py MODEL [--test-set any-camera] [--samples 256] [--classes wall] [--within 2]
        [--camera-known gravity,height]

A column moves when the first occupied cells of prediction and truth are both of ``--classes`` (all classes when
not given) and at most ``--within`` slices apart (0: any distance): its first run (the first cell and the cells of
its class right behind it) moves, the rest of the column stays; with ``--carry`` the whole column moves. The
samples are fruxel-eval's (run after a `fruxel-eval` of the same test set and count: its sample cache, nothing
simulated again), the pose told unless ``--camera-known`` says otherwise. An analysis for the experiments log,
not a metric of the product's reports.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from depth_tolerance import add_arguments, held_out_predictions, tolerant_counts, tolerant_iou  # noqa: E402


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


def _main(args: argparse.Namespace) -> int:
    from fruxel.cli.common import UsageError

    names, pairs = held_out_predictions(args.model, args.test_set, args.samples, args.batch, args.camera_known,
                                        device=args.device)
    unknown = [c for c in args.classes.split(",") if c and c not in names]
    if unknown:
        raise UsageError(f"--classes {args.classes}: not classes of the model ({', '.join(names[1:])})")
    classes = [names.index(c) for c in args.classes.split(",") if c] or list(range(1, len(names)))
    counts = {k: np.zeros((len(names), 4), dtype=np.int64) for k in ("model", "snapped")}
    moved = columns = 0
    for pred, truth in pairs:
        shift = snap_shifts(pred, truth, classes, args.within)
        moved, columns = moved + int((shift != 0).sum()), columns + int((pred != 0).any(axis=1).sum())
        snapped = shift_columns(pred, shift) if args.carry else move_first_runs(pred, shift)
        counts["model"] += tolerant_counts(pred, truth, len(names), 0)
        counts["snapped"] += tolerant_counts(snapped, truth, len(names), 0)
    for key, c in counts.items():
        iou = tolerant_iou(c)
        print(f"{key}: mIoU {np.nanmean(iou[c[:, 1] > 0]):.2f} | "
              + " ".join(f"{names[k]} {iou[k]:.1f}" for k in range(1, len(names))))
    print(f"columns moved: {moved} of {columns} occupied ({100.0 * moved / max(columns, 1):.1f} %)")
    return 0


def main(argv: list[str] | None = None) -> int:
    """Parse ``argv``, print the scores; bad input is one error line and status 2 (fruxel's commands' runner)."""
    from fruxel.cli.common import OneLineParser, run

    p = OneLineParser(prog="depth_snap.py", description=__doc__.split("\n\n")[0])
    add_arguments(p)
    p.add_argument("--classes", default="", help="comma-separated class names whose first cells move (default all)")
    p.add_argument("--within", type=int, default=2, help="slices a first cell may move (0: any)")
    p.add_argument("--carry", action="store_true", help="move the whole column, not its first run only")
    return run(_main, p, argv)


if __name__ == "__main__":
    sys.exit(main())

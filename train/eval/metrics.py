"""Evaluation metrics of conventions section 9 as pure functions of predicted and ground-truth label volumes.

Counts are accumulated over every cell (or pixel) of every sample together, never averaged per sample: an
:class:`Accumulator` adds batches up and :meth:`Accumulator.summary` turns the counts into the metrics.

Volumes are ``(B, D, H, W)`` integer labels in the grid frame (0 = empty); predictions are the argmax of the
logits.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np
import torch


def confusion(pred: torch.Tensor, target: torch.Tensor, classes: int) -> torch.Tensor:
    """Confusion counts ``M[t, p]``: cells with true class ``t`` predicted as ``p``.

    Args:
        pred, target: integer label tensors of one shape, values in ``[0, classes)``.
        classes: C.

    Returns:
        ``(C, C)`` int64, on the inputs' device.
    """
    idx = target.reshape(-1).long() * classes + pred.reshape(-1).long()
    return torch.bincount(idx, minlength=classes * classes).reshape(classes, classes)


def iou_per_class(conf: np.ndarray) -> np.ndarray:
    """``TP / (TP + FP + FN)`` per class from a confusion matrix (NaN where the class is nowhere)."""
    conf = np.asarray(conf, dtype=np.float64)
    tp = np.diag(conf)
    denom = conf.sum(0) + conf.sum(1) - tp
    with np.errstate(invalid="ignore", divide="ignore"):
        return np.where(denom > 0, tp / denom, np.nan)


def completion_iou(conf: np.ndarray) -> float:
    """IoU of occupied (label != 0) against empty, from a confusion matrix."""
    conf = np.asarray(conf, dtype=np.float64)
    tp = conf[1:, 1:].sum()
    fp = conf[0, 1:].sum()
    fn = conf[1:, 0].sum()
    return float(tp / (tp + fp + fn)) if tp + fp + fn > 0 else float("nan")


def first_surface(labels: torch.Tensor) -> torch.Tensor:
    """Label of each column's first occupied cell (0 for an empty column): the first hits of the grid's own
    camera at native resolution (conventions section 4).

    Args:
        labels: ``(B, D, H, W)`` integer labels.

    Returns:
        ``(B, H, W)`` int64.
    """
    occupied = labels != 0
    first = occupied.to(torch.uint8).argmax(dim=1, keepdim=True)
    return labels.gather(1, first).squeeze(1).long() * occupied.any(dim=1)


@dataclass
class Accumulator:
    """Running counts of every metric of conventions section 9 over batches.

    Args:
        classes: C.
    """

    classes: int
    """C."""
    conf: np.ndarray = field(init=False)
    """``(C, C)`` int64 cell confusion counts ``[true, predicted]``."""
    own_hits: int = 0
    """Own-view pixels where the ground truth hits."""
    own_correct: int = 0
    """... of which the prediction's first hit has the same label."""
    novel_pixels: int = 0
    """Novel-view pixels where the prediction or the truth hits."""
    novel_correct: int = 0
    """... of which the labels agree (a miss is label 0)."""
    depth_pixels: int = 0
    """Novel-view pixels where both hit."""
    depth_abs_sum: float = 0.0
    """Sum of the absolute depth differences over those pixels, metres."""
    samples: int = 0
    """Samples counted."""

    def __post_init__(self) -> None:
        self.conf = np.zeros((self.classes, self.classes), dtype=np.int64)

    def add_volumes(self, pred: torch.Tensor, target: torch.Tensor) -> None:
        """Count cells and own-view first hits of a batch of ``(B, D, H, W)`` volumes."""
        self.conf += confusion(pred, target, self.classes).cpu().numpy()
        p = first_surface(pred)
        t = first_surface(target)
        hit = t != 0
        self.own_hits += int(hit.sum())
        self.own_correct += int(((p == t) & hit).sum())
        self.samples += int(pred.shape[0])

    def add_views(self, pred_label: Any, pred_depth: Any, true_label: Any, true_depth: Any) -> None:
        """Count the pixels of novel views: ``first_hit`` labels and depths of the prediction and the truth.

        Args:
            pred_label, true_label: ``(..., h, w)`` integer first-hit labels (0 = miss).
            pred_depth, true_depth: same shape, depths in metres (0 on a miss).
        """
        pl, tl = np.asarray(pred_label), np.asarray(true_label)
        pd, td = np.asarray(pred_depth, dtype=np.float64), np.asarray(true_depth, dtype=np.float64)
        either = (pl != 0) | (tl != 0)
        both = (pl != 0) & (tl != 0)
        self.novel_pixels += int(either.sum())
        self.novel_correct += int(((pl == tl) & either).sum())
        self.depth_pixels += int(both.sum())
        self.depth_abs_sum += float(np.abs(pd - td)[both].sum())

    def merge(self, other: Accumulator) -> None:
        """Add another accumulator's counts (e.g. from another distributed rank)."""
        self.conf += other.conf
        for name in ("own_hits", "own_correct", "novel_pixels", "novel_correct", "depth_pixels", "depth_abs_sum",
                     "samples"):
            setattr(self, name, getattr(self, name) + getattr(other, name))

    def summary(self, names: tuple[str, ...] | None = None) -> dict[str, Any]:
        """The metrics: ``iou`` per class name (percent; None for a class absent from both), ``miou`` over the
        classes present in the ground truth, ``completion_iou``, ``own_view_accuracy``, ``novel_view_accuracy``
        (percent) and ``depth_error`` (metres); a metric with nothing to count is None."""
        names = names or tuple(str(c) for c in range(self.classes))
        iou = iou_per_class(self.conf)
        present = self.conf.sum(1) > 0
        present[0] = False
        per_class = {names[c]: (None if np.isnan(iou[c]) else 100.0 * float(iou[c])) for c in range(1, self.classes)}
        miou = 100.0 * float(np.nanmean(iou[present])) if present.any() else None
        comp = completion_iou(self.conf)

        def pct(a: int, b: int) -> float | None:
            return 100.0 * a / b if b else None

        return {
            "samples": self.samples,
            "miou": miou,
            "iou": per_class,
            "completion_iou": None if np.isnan(comp) else 100.0 * comp,
            "own_view_accuracy": pct(self.own_correct, self.own_hits),
            "novel_view_accuracy": pct(self.novel_correct, self.novel_pixels),
            "depth_error": self.depth_abs_sum / self.depth_pixels if self.depth_pixels else None,
        }

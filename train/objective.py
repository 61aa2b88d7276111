"""The network's training objective: per-cell class-weighted cross-entropy, a soft Jaccard (IoU) term,
the image-side heads' cross-entropies (column surface depth and class), the shell-aware losses and the
adversarial term, each switchable and weighted by :class:`~fruxel.train.config.LossConfig`.

Targets come from the ground-truth label volume alone: a column's first occupied cell is what the grid's own
camera sees of it (conventions section 4, ``shell`` from the grid's own camera), so the own-view truth is derived here,
on the training device, and never read from elsewhere.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import TYPE_CHECKING

import numpy as np
import torch
import torch.nn.functional as F

from .config import LossConfig
from .rules import first_hit_log_probs

if TYPE_CHECKING:
    from .losses import ShellLoss
    from .models.registry import ModelOutput


def class_frequencies(label_batches: Iterable[torch.Tensor], classes: int) -> np.ndarray:
    """Share of cells of each class over some label volumes.

    Args:
        label_batches: integer label tensors of any shape (``(B, D, H, W)`` batches), values in ``[0, classes)``.
        classes: C.

    Returns:
        ``(C,)`` float64 frequencies summing to 1.
    """
    counts = np.zeros(classes, dtype=np.float64)
    for labels in label_batches:
        counts += torch.bincount(labels.reshape(-1).long().cpu(), minlength=classes)[:classes].double().numpy()
    total = counts.sum()
    if total <= 0:
        raise ValueError("no cells to count class frequencies from")
    return counts / total


def class_weights(frequencies: np.ndarray, power: float) -> np.ndarray:
    """Cross-entropy weights ``f_c^-power``, normalised so that their mean over the cells (weighted by ``f``) is 1.

    A class never seen gets the largest weight of the seen ones (it cannot affect the normaliser).

    Args:
        frequencies: ``(C,)`` class frequencies.
        power: 0 (all weights 1) to 1 (inverse frequency).

    Returns:
        ``(C,)`` float32 weights.
    """
    f = np.asarray(frequencies, dtype=np.float64)
    seen = f > 0
    w = np.ones_like(f)
    w[seen] = f[seen] ** -power
    w[~seen] = w[seen].max() if seen.any() else 1.0
    w /= float((w * f).sum())
    return w.astype(np.float32)


def surface_targets(labels: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """Each column's first occupied slice and its label: what the grid's own camera sees.

    Args:
        labels: ``(B, D, H, W)`` integer labels, grid frame.

    Returns:
        ``(depth_bin, label)``, each ``(B, H, W)`` int64: the first occupied slice ``k`` (``D`` when the column is
        empty) and its label (0 when empty).
    """
    occupied = labels != 0
    any_hit = occupied.any(dim=1)
    # argmax returns the first maximum: the first occupied slice.
    first = occupied.to(torch.uint8).argmax(dim=1)
    depth_bin = torch.where(any_hit, first, labels.shape[1]).long()
    label = labels.gather(1, first.unsqueeze(1)).squeeze(1).long() * any_hit
    return depth_bin, label


def soft_iou_loss(probs: torch.Tensor, labels: torch.Tensor) -> torch.Tensor:
    """``1 - mean_c IoU_c`` with soft counts, over the classes 1..C-1 present in ``labels`` (none: 0).

    ``IoU_c = sum(p_c [y = c]) / (sum(p_c) + sum([y = c]) - sum(p_c [y = c]))``, summed over the whole batch as
    conventions section 9 counts the metric.

    Args:
        probs: ``(B, C, D, H, W)`` float class probabilities.
        labels: ``(B, D, H, W)`` integer labels.
    """
    c = probs.shape[1]
    onehot = F.one_hot(labels.long(), c).movedim(-1, 1).to(probs.dtype)
    dims = (0, 2, 3, 4)
    inter = (probs * onehot).sum(dims)[1:]
    psum = probs.sum(dims)[1:]
    ysum = onehot.sum(dims)[1:]
    present = ysum > 0
    if not bool(present.any()):
        return probs.sum() * 0.0
    iou = inter / (psum + ysum - inter).clamp_min(1e-6)
    return 1.0 - iou[present].mean()


class SSZObjective:
    """The network's loss terms for one batch (the adversarial term is added by the engine, which owns the
    discriminator). It reads the output contract (:class:`~fruxel.train.models.registry.ModelOutput`): the
    ``depth`` and ``surface`` terms count when the network has those heads.

    Args:
        config: weights and switches.
        weights: ``(C,)`` class weights of the cross-entropy (:func:`class_weights`), on the training device.
        shell_loss: a :class:`fruxel.train.losses.ShellLoss`, or None when ``config.shell`` is off.
    """

    def __init__(self, config: LossConfig, weights: torch.Tensor, shell_loss: ShellLoss | None = None) -> None:
        self.config = config
        self.weights = weights
        self.shell_loss = shell_loss

    def __call__(self, out: ModelOutput, labels: torch.Tensor) -> dict[str, torch.Tensor]:
        """The weighted terms and their total.

        Args:
            out: the network's output.
            labels: ``(B, D, H, W)`` integer ground-truth labels (uint8 is fine), on the logits' device.

        Returns:
            ``{"total": ..., "ce": ..., "iou": ..., "depth": ..., "surface": ..., "first_hit": ..., "shell": ...}``
            scalar tensors (unweighted terms; ``total`` is the weighted sum); absent terms are left out.
        """
        c = self.config
        logits = out.logits.float()
        target = labels.long()
        terms: dict[str, torch.Tensor] = {}
        total = logits.new_zeros(())
        if c.ce:
            terms["ce"] = F.cross_entropy(logits, target, weight=self.weights)
            total = total + c.ce * terms["ce"]
        if c.iou:
            terms["iou"] = soft_iou_loss(torch.softmax(logits, dim=1), target)
            total = total + c.iou * terms["iou"]
        depth = c.depth and out.depth_logits is not None
        surface = c.surface and out.surface_logits is not None
        if depth or surface or c.first_hit:
            depth_bin, first_label = surface_targets(target)
            if depth:
                terms["depth"] = F.cross_entropy(out.depth_logits, depth_bin)
                total = total + c.depth * terms["depth"]
            if surface:
                terms["surface"] = F.cross_entropy(out.surface_logits, first_label)
                total = total + c.surface * terms["surface"]
            if c.first_hit:
                terms["first_hit"] = F.nll_loss(first_hit_log_probs(logits), first_label)
                total = total + c.first_hit * terms["first_hit"]
        if self.shell_loss is not None:
            terms["shell"] = self.shell_loss(logits, labels).total
            total = total + c.shell_weight * terms["shell"]
        terms["total"] = total
        return terms

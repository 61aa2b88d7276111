"""The two baselines of conventions section 9, evaluated as predictions on the same samples as a model.

* **Per-cell prior**: every cell gets its most frequent label over training samples (:class:`CellPrior`): the
  best one can do knowing where things usually are, without looking at the image.
* **Visible-surface oracle**: the ground truth's own-view shell alone (:func:`oracle_prediction`), i.e. the first
  occupied cell of each column with its true label and nothing behind it: a perfect depth and segmentation network
  that completes nothing.

Volumes are ``(B, D, H, W)`` integer labels in the grid frame, indexed ``[b, k, j, i]``, 0 = empty.
"""

from __future__ import annotations

from typing import Any

import numpy as np
import torch

from fruxel.errors import FruxelError
from fruxel.grid import FruxelGrid


class BaselineError(FruxelError, ValueError):
    """Labels a baseline cannot use (another grid, labels outside the class table, no samples counted)."""


class CellPrior:
    """Per-cell label counts over training samples, and their mode.

    The counts are one ``(D*H*W, C)`` uint32 array (28 bytes a cell for the seven default classes: 7.3 MB at
    64^3, 59 MB at 128^3), filled one class at a time so that no ``(B, D*H*W, C)`` one-hot array is ever made.

    Args:
        shape: ``(D, H, W)`` of the volumes.
        classes: C.
    """

    def __init__(self, shape: tuple[int, int, int], classes: int) -> None:
        self.shape = tuple(int(s) for s in shape)
        """``(D, H, W)``."""
        self.classes = int(classes)
        """C."""
        self.counts = np.zeros((int(np.prod(self.shape)), self.classes), dtype=np.uint32)
        """``(D*H*W, C)`` uint32: samples in which cell ``(k * H + j) * W + i`` held class ``c``."""
        self.samples = 0
        """Samples counted."""

    def add(self, labels: Any) -> None:
        """Count a batch of training labels.

        Args:
            labels: ``(B, D, H, W)`` or ``(D, H, W)`` integer labels, numpy or torch (any device; counted on the
                host).

        Raises:
            BaselineError: another shape, a non-integer dtype, or labels outside ``[0, C)``.
        """
        lab = labels.detach().cpu().numpy() if isinstance(labels, torch.Tensor) else np.asarray(labels)
        if lab.ndim == 3:
            lab = lab[None]
        if lab.ndim != 4 or tuple(lab.shape[1:]) != self.shape:
            raise BaselineError(f"labels of shape {lab.shape} do not fit the prior's (B, D, H, W) = (B, *{self.shape})")
        if lab.dtype.kind not in "iu":
            raise BaselineError(f"labels must be integers, got dtype {lab.dtype}")
        if lab.size and (int(lab.min()) < 0 or int(lab.max()) >= self.classes):
            raise BaselineError(f"labels must be in [0, {self.classes}), got range [{lab.min()}, {lab.max()}]")
        flat = lab.reshape(len(lab), -1)
        for c in range(self.classes):
            # One class at a time: a (B, D*H*W) bool temporary and a (D*H*W,) sum, whatever C is.
            self.counts[:, c] += (flat == c).sum(axis=0, dtype=np.uint32)
        self.samples += len(lab)

    def mode(self) -> np.ndarray:
        """Each cell's most frequent label; a tie goes to the lowest class id (empty before any object).

        Returns:
            ``(D, H, W)`` uint8.

        Raises:
            BaselineError: no sample counted yet.
        """
        if not self.samples:
            raise BaselineError("the per-cell prior has no training samples counted")
        return self.counts.argmax(axis=1).astype(np.uint8).reshape(self.shape)


def prior_prediction(prior: torch.Tensor, batch: int) -> torch.Tensor:
    """The per-cell prior as the prediction for every sample of a batch.

    Args:
        prior: ``(D, H, W)`` uint8, :meth:`CellPrior.mode` as a tensor on the evaluation device.
        batch: B.

    Returns:
        ``(B, D, H, W)`` uint8, a broadcast view of ``prior`` (no copy).
    """
    return prior.unsqueeze(0).expand(batch, *prior.shape)


def oracle_prediction(labels: Any, grid: FruxelGrid, backend: str | None = None) -> Any:
    """The visible-surface oracle: the ground truth's shell from the grid's own camera.

    Args:
        labels: ``(B, D, H, W)`` ground-truth integer labels (numpy or torch, CPU or CUDA).
        grid: their grid.
        backend: kernel backend (None: the best available).

    Returns:
        Labels of the same shape, dtype, kind and device: each column's first occupied cell keeps its label,
        every other cell is 0.
    """
    from fruxel.kernels import shell

    return shell(labels, grid, [grid.camera()], backend=backend)

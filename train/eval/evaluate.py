"""Evaluating a generator on samples: predictions, the metrics of SPEC section 9 and a picture of examples."""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

import numpy as np
import torch

from fruxel.classes import ClassTable
from fruxel.grid import FruxelGrid

from .metrics import Accumulator


def novel_cameras(grid: FruxelGrid) -> list[Any]:
    """The novel views of SPEC section 9: ``orbit_cameras(grid, 4)`` at the grid's own width and height."""
    from fruxel.kernels import orbit_cameras

    return orbit_cameras(grid, 4, width=grid.width, height=grid.height)


def count_views(acc: Accumulator, pred: torch.Tensor, target: torch.Tensor, grid: FruxelGrid,
                cameras: list[Any], backend: str | None = None) -> None:
    """Add the novel-view counts of a batch: ``first_hit`` of prediction and truth from each camera.

    Args:
        acc: the accumulator.
        pred, target: ``(B, D, H, W)`` uint8 labels (CPU or CUDA; kernels run where the data is).
        grid: their grid.
        cameras: the viewing cameras.
        backend: kernel backend (None: the best available).
    """
    from fruxel import kernels

    for cam in cameras:
        hp = kernels.first_hit(pred, grid, cam, backend=backend)
        ht = kernels.first_hit(target, grid, cam, backend=backend)
        acc.add_views(_host(hp.label), _host(hp.depth), _host(ht.label), _host(ht.depth))


def _host(x: Any) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


@torch.no_grad()
def evaluate(generator: torch.nn.Module, batches: Iterable[tuple[torch.Tensor, torch.Tensor]], grid: FruxelGrid,
             classes: ClassTable, *, device: torch.device, novel: bool = True, backend: str | None = None,
             autocast: bool = False, keep: int = 0) -> tuple[Accumulator, list[dict[str, Any]]]:
    """Run the generator over batches and count every metric.

    Args:
        generator: the model (switched to eval mode for the call, then back).
        batches: ``(image, labels)`` pairs: ``(B, 3, h, w)`` float in [0, 1] and ``(B, D, H, W)`` integer labels,
            on any device.
        grid, classes: the grid and class table of the labels.
        device: where to predict.
        novel: also count the novel-view metrics (two ``first_hit`` per camera and batch).
        backend: kernel backend for the novel views.
        autocast: predict under bfloat16 autocast (CUDA).
        keep: how many samples to keep for :func:`fruxel.train.eval.visual.example_sheet` (first ones).

    Returns:
        ``(accumulator, kept)``: kept samples as dicts of ``image`` (3, h, w) float, ``labels`` and ``pred``
        (D, H, W) uint8, all on the CPU.
    """
    was_training = generator.training
    generator.eval()
    acc = Accumulator(len(classes.names))
    cams = novel_cameras(grid) if novel else []
    kept: list[dict[str, Any]] = []
    try:
        for image, labels in batches:
            image = image.to(device, non_blocking=True)
            labels = labels.to(device, non_blocking=True)
            with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast):
                logits = generator(image).logits
            pred = logits.argmax(dim=1).to(torch.uint8)
            target = labels.to(torch.uint8)
            acc.add_volumes(pred, target)
            if cams:
                count_views(acc, pred, target, grid, cams, backend)
            for b in range(min(keep - len(kept), len(pred))):
                kept.append({"image": image[b].float().cpu(), "labels": target[b].cpu(), "pred": pred[b].cpu()})
    finally:
        generator.train(was_training)
    return acc, kept

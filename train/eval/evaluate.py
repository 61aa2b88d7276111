"""Evaluating a generator on samples: predictions, the metrics of conventions section 9 and a picture of examples."""

from __future__ import annotations

from collections.abc import Callable, Collection, Iterable, Mapping
from typing import Any

import numpy as np
import torch

from fruxel.classes import ClassTable
from fruxel.grid import FruxelGrid

from ..models.conditioning import CameraInput
from ..rules import InferenceRules, predict_logits
from .by_camera import CameraBinned
from .metrics import Accumulator


def spread(count: int, n: int) -> list[int]:
    """Positions of ``n`` examples spread evenly over ``count`` samples, first and last included (fewer when
    ``count < n``; none for ``n = 0``): consecutive samples share a room, so the first few would show one."""
    return np.unique(np.linspace(0, count - 1, min(n, count)).round().astype(int)).tolist() if count > 0 else []


def novel_cameras(grid: FruxelGrid) -> list[Any]:
    """The novel views of conventions section 9: ``orbit_cameras(grid, 4)`` at the grid's own width and height."""
    from fruxel.kernels import orbit_cameras

    return orbit_cameras(grid, 4, width=grid.width, height=grid.height)


def count_views(acc: Accumulator, pred: torch.Tensor, target: torch.Tensor, grid: FruxelGrid,
                cameras: list[Any], backend: str | None = None, target_hits: list[Any] | None = None) -> None:
    """Add the novel-view counts of a batch: ``first_hit`` of prediction and truth from each camera.

    Args:
        acc: the accumulator.
        pred, target: ``(B, D, H, W)`` uint8 labels (CPU or CUDA; kernels run where the data is).
        grid: their grid.
        cameras: the viewing cameras.
        backend: kernel backend (None: the best available).
        target_hits: the truth's ``first_hit`` per camera when already computed (several predictions of one
            batch), else None.
    """
    from fruxel import kernels

    for c, cam in enumerate(cameras):
        hp = kernels.first_hit(pred, grid, cam, backend=backend)
        ht = target_hits[c] if target_hits is not None else kernels.first_hit(target, grid, cam, backend=backend)
        acc.add_views(_host(hp.label), _host(hp.depth), _host(ht.label), _host(ht.depth))


def _host(x: Any) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


Predict = Callable[..., torch.Tensor]
"""A prediction rule: ``(image (B, 3, h, w) float, truth (B, D, H, W) uint8) -> (B, D, H, W)`` integer labels on
the truth's device. The truth is given only so that baselines built from it (the visible-surface oracle) and from
its shape (the per-cell prior) can be evaluated like a network. A rule with a true ``reads_camera`` attribute
(:func:`model_predict` of a network that reads the camera) is called with the batch's camera record third (None
when the batches carry none)."""


def model_predict(network: torch.nn.Module, rules: InferenceRules, autocast: bool = False,
                  camera_known: Collection[str] | None = None) -> Predict:
    """The prediction rule of a network and its inference rules: the argmax of its logits under the rules
    (:func:`fruxel.train.rules.predict_logits`; bfloat16 autocast on CUDA with ``autocast``).

    Args:
        network, rules, autocast: as above.
        camera_known: for a network that reads the camera, the pieces of each sample's recorded camera it is told
            (a subset of :data:`fruxel.train.models.conditioning.KNOWN`; empty: pose unknown); None for a network
            that reads none.
    """

    def predict(image: torch.Tensor, _: torch.Tensor, record: Mapping[str, Any] | None = None) -> torch.Tensor:
        camera = None
        if camera_known is not None:
            camera = (CameraInput.unknown(len(image), image.device) if record is None
                      else CameraInput.from_record(record, camera_known, image.device))
        with torch.autocast(image.device.type, dtype=torch.bfloat16, enabled=autocast):
            logits = predict_logits(network, image, rules, camera=camera)
        return logits.argmax(dim=1).to(torch.uint8)

    predict.reads_camera = camera_known is not None  # type: ignore[attr-defined]
    return predict


@torch.no_grad()
def evaluate_predictions(predictors: Mapping[str, Predict], batches: Iterable[tuple[torch.Tensor, torch.Tensor]],
                         grid: FruxelGrid, classes: ClassTable, *, device: torch.device, novel: bool = True,
                         backend: str | None = None, keep: int | Collection[int] = 0,
                         by_camera: Mapping[str, CameraBinned] | None = None
                         ) -> tuple[dict[str, Accumulator], list[dict[str, Any]]]:
    """Count every metric of several prediction rules on the same samples, in one pass over them.

    Args:
        predictors: the rules by name (e.g. the model and the baselines of :mod:`.baselines`).
        batches: ``(image, labels)`` pairs: ``(B, 3, h, w)`` float in [0, 1] and ``(B, D, H, W)`` integer labels,
            on any device; or ``(image, labels, camera)`` with the batch's camera record (for rules that read it).
        grid, classes: the grid and class table of the labels.
        device: where to predict and count.
        novel: also count the novel-view metrics (two ``first_hit`` per camera, batch and rule).
        backend: kernel backend for the novel views.
        keep: samples to keep for :func:`fruxel.train.eval.visual.example_sheet`: a number (the first ones) or the
            positions of the samples in the order of ``batches``.
        by_camera: counts per camera bin of some of the rules, by rule name, added to in place (the batches must
            carry their camera record).

    Returns:
        ``(accumulators by name, kept)``: kept samples in order, as dicts of ``image`` (3, h, w) float, ``labels``
        and ``pred`` (D, H, W) uint8 (``pred``: the first rule's prediction), all on the CPU.

    Raises:
        ValueError: ``by_camera`` with batches that carry no camera record.
    """
    accs = {name: Accumulator(len(classes.names)) for name in predictors}
    cams = novel_cameras(grid) if novel else []
    wanted = set(range(keep)) if isinstance(keep, int) else {int(k) for k in keep}
    kept: list[dict[str, Any]] = []
    seen = 0
    for batch in batches:
        image, labels = batch[0], batch[1]
        record = batch[2] if len(batch) > 2 else None
        image = image.to(device, non_blocking=True)
        target = labels.to(device, non_blocking=True).to(torch.uint8)
        first = None
        for name, predict in predictors.items():
            if getattr(predict, "reads_camera", False):
                pred = predict(image, target, record).to(torch.uint8)
            else:
                pred = predict(image, target).to(torch.uint8)
            first = pred if first is None else first
            accs[name].add_volumes(pred, target)
            if by_camera and name in by_camera:
                if record is None:
                    raise ValueError("counting by camera needs batches that carry their camera record")
                by_camera[name].add(pred, target, record)
            if cams:
                count_views(accs[name], pred, target, grid, cams, backend)
        for b in range(len(target)):
            if seen + b in wanted:
                kept.append({"image": image[b].float().cpu(), "labels": target[b].cpu(),
                             "pred": first[b].cpu() if first is not None else target[b].cpu()})
        seen += len(target)
    return accs, kept


@torch.no_grad()
def evaluate(network: torch.nn.Module, rules: InferenceRules, batches: Iterable[tuple[torch.Tensor, torch.Tensor]],
             grid: FruxelGrid, classes: ClassTable, *, device: torch.device, novel: bool = True,
             backend: str | None = None, autocast: bool = False, keep: int = 0,
             camera_known: Collection[str] | None = None) -> tuple[Accumulator, list[dict[str, Any]]]:
    """Run a network under its inference rules over batches and count every metric.

    Args:
        network: the model (switched to eval mode for the call, then back).
        rules: its inference rules (:data:`fruxel.train.rules.NO_RULES` for the network's raw argmax).
        batches: ``(image, labels)`` pairs: ``(B, 3, h, w)`` float in [0, 1] and ``(B, D, H, W)`` integer labels,
            on any device, or ``(image, labels, camera)`` triples (the camera record, for a network that reads it).
        grid, classes: the grid and class table of the labels.
        device: where to predict.
        novel: also count the novel-view metrics (two ``first_hit`` per camera and batch).
        backend: kernel backend for the novel views.
        autocast: predict under bfloat16 autocast (CUDA).
        keep: how many samples to keep for :func:`fruxel.train.eval.visual.example_sheet` (first ones).
        camera_known: the camera pieces a network that reads the camera is told (:func:`model_predict`).

    Returns:
        ``(accumulator, kept)``: kept samples as dicts of ``image`` (3, h, w) float, ``labels`` and ``pred``
        (D, H, W) uint8, all on the CPU.
    """
    was_training = network.training
    network.eval()
    try:
        predict = model_predict(network, rules, autocast, camera_known)
        accs, kept = evaluate_predictions({"model": predict}, batches, grid, classes,
                                          device=device, novel=novel, backend=backend, keep=keep)
    finally:
        network.train(was_training)
    return accs["model"], kept

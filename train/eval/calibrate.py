"""Choosing a trained model's inference rules (:class:`fruxel.train.rules.InferenceRules`: the empty-logit offset
and the ``fill_columns`` threshold) on training-split samples (``fruxel-calibrate``).

The class-weighted cross-entropy that trains SSZ down-weights the empty class (most of the cells), so the argmax of
its logits calls cells occupied more readily than the cell-count metrics reward. After training, a constant added
to every cell's empty logit moves that threshold. With ``fill_columns``, a column that the volume leaves empty gets
a surface when the depth head's "no surface" probability is below ``fill_threshold``: a higher threshold gives the
own view a surface in more of the columns the network is unsure of (a plain wall close to the camera), at the price
of surfaces where the truth has none. Both are chosen here on samples of the training split (never the test split
the model is evaluated on), with the rules applied exactly as :func:`fruxel.train.rules.predict_logits` applies
them.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Iterable, Iterator, Sequence
from typing import Any

import torch

from fruxel.errors import ConfigError

from ..models.conditioning import CameraInput
from ..models.registry import run_network
from ..rules import InferenceRules, filled_empty_logits, first_hit_classes, mirror_average
from .metrics import Accumulator

Rules = tuple[float, float]
"""``(empty_offset, fill_threshold)``."""


@torch.no_grad()
def sweep_rules(network: torch.nn.Module, batches: Iterable[tuple[torch.Tensor, torch.Tensor]],
                offsets: Sequence[float], thresholds: Sequence[float], classes: int, *, base: InferenceRules,
                device: torch.device, grid: Any = None, backend: str | None = None) -> dict[Rules, Accumulator]:
    """Metrics (cell IoUs, completion, own view; novel views with ``grid``) of a network's predictions under each
    pair of rules.

    Args:
        network: the network (in eval mode for the sweep, then back).
        batches: ``(images (B, 3, h, w) float in [0, 1], labels (B, D, H, W) integer)`` pairs, or triples with the
            batch's camera record third: a network that reads the camera is then told the recorded pose.
        offsets: the offsets to try, added to every cell's empty logit (channel 0).
        thresholds: the ``fill_threshold`` values to try with each offset, in (0, 1] (ignored without
            ``base.fill_columns``).
        classes: C, classes including empty.
        base: the rules swept: its ``flip_average``, ``fill_columns`` and ``first_hit_label`` hold in every pair,
            its ``fill_threshold`` is the one of every pair without ``fill_columns``.
        device: where to predict and count.
        grid: the labels' grid: also count the novel views of :func:`~.evaluate.novel_cameras` (None: not).
        backend: kernel backend of the novel views.

    Returns:
        An accumulator per ``(offset, threshold)``.
    """
    from fruxel import kernels

    from .evaluate import count_views, novel_cameras

    cams = novel_cameras(grid) if grid is not None else []
    ts = [float(t) for t in thresholds] if base.fill_columns else [base.fill_threshold]
    accs = {(float(o), t): Accumulator(classes) for o in offsets for t in ts}
    training = network.training
    network.eval()
    try:
        for image, labels, *record in batches:
            image = image.to(device)
            camera = CameraInput.from_record(record[0], device=device) if record else None
            out = (mirror_average(network, image, device.type != "cpu", camera) if base.flip_average
                   else run_network(network, image, camera))
            if base.fill_columns and out.depth_logits is None:
                raise ConfigError("rules.fill_columns needs a network with a column depth head")
            logits = out.logits.float()
            target = labels.to(device).to(torch.uint8)
            best = first_hit_classes(logits) if base.first_hit_label else None
            truth_hits = [kernels.first_hit(target, grid, cam, backend=backend) for cam in cams]
            for (o, t), pred in swept_predictions(logits, out.depth_logits, list(accs), base.fill_columns, best):
                acc = accs[(o, t)]
                acc.add_volumes(pred, target)
                if cams:
                    count_views(acc, pred, target, grid, cams, backend, truth_hits)
    finally:
        network.train(training)
    return accs


def swept_predictions(logits: torch.Tensor, depth_logits: torch.Tensor | None, pairs: Sequence[Rules], fill: bool,
                      best: torch.Tensor | None) -> Iterator[tuple[Rules, torch.Tensor]]:
    """Each pair's prediction, ``argmax`` of :func:`~fruxel.train.rules.first_hit_label` (with ``best``) of
    :func:`~fruxel.train.rules.shift_and_fill` of ``logits``, the same labels computed on per-cell maxima.

    The rules change only a cell's empty logit (the offset, the filled cell) and the class of a column's first
    occupied cell (``best``), so a cell's class follows from its empty logit against its best occupied logit: the
    occupied classes' maximum, argmax and log-sum-exp are taken once a batch instead of once a pair.

    Args:
        logits: ``(B, C, D, H, W)`` float logits (channel 0 = empty), grid frame.
        depth_logits: ``(B, D + 1, H, W)`` column depth logits (with ``fill``).
        pairs: the ``(empty_offset, fill_threshold)`` pairs.
        fill: apply ``fill_columns`` with each pair's threshold.
        best: ``(B, H, W)`` int64 :func:`~fruxel.train.rules.first_hit_classes` for ``first_hit_label``; None: off.

    Yields:
        ``((empty_offset, fill_threshold), labels (B, D, H, W) uint8)`` per pair, in order.
    """
    empty0, occupied = logits[:, 0], logits[:, 1:]
    top = occupied.amax(dim=1)
    label = occupied.argmax(dim=1) + 1  # the first best on ties, as argmax across every channel takes it
    if fill:  # fill_columns' per-cell quantities, computed as it computes them
        no_surface = torch.softmax(depth_logits.float(), dim=1)[:, -1]
        lse = torch.logsumexp(occupied.float(), dim=1)
    for o, t in pairs:
        empty = empty0 + o if o else empty0
        if fill:
            empty = filled_empty_logits(empty, top, lse, no_surface, t)
        occ = top > empty  # a tie goes to empty, as argmax takes the first channel
        pred = torch.where(occ, label, 0)
        if best is not None:
            first = occ.to(torch.uint8).argmax(dim=1, keepdim=True)
            hit = occ.any(dim=1, keepdim=True)
            pred.scatter_(1, first, torch.where(hit, best.unsqueeze(1), pred.gather(1, first)))
        yield (o, t), pred.to(torch.uint8)


def rules_of(base: InferenceRules, chosen: Rules) -> InferenceRules:
    """``base`` with the chosen ``(empty_offset, fill_threshold)``."""
    return dataclasses.replace(base, empty_offset=chosen[0], fill_threshold=chosen[1])


def rules_score(summary: dict[str, Any]) -> float:
    """What :func:`choose_rules` maximises: mIoU + completion IoU + own-view first-hit accuracy (the three metrics
    the project sets targets for) + novel-view first-hit accuracy when it was counted, in points, weighted equally.

    Novel views matter because the rules can trade them away: chosen on the first three alone, they once bought
    those three points with more novel-view points lost (docs/experiments.md)."""
    novel = summary.get("novel_view_accuracy")
    return (summary["miou"] + summary["completion_iou"] + summary["own_view_accuracy"]
            + (novel if novel is not None else 0.0))


def choose_rules(summaries: dict[Rules, dict[str, Any]], default: Rules) -> Rules:
    """The rules with the largest :func:`rules_score` (ties: the ones nearest ``default``).

    Args:
        summaries: :meth:`Accumulator.summary` per ``(offset, threshold)``; must include ``default``.
        default: the model as trained, e.g. ``(0.0, 0.5)``.

    Raises:
        ValueError: ``default`` is not among them.
    """
    if default not in summaries:
        raise ValueError(f"the sweep must include the model as trained (offset {default[0]:g}, threshold "
                         f"{default[1]:g})")
    return max(summaries, key=lambda r: (round(rules_score(summaries[r]), 9),
                                         -abs(r[0] - default[0]) - abs(r[1] - default[1])))

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
from collections.abc import Iterable, Sequence
from typing import Any

import torch

from fruxel.errors import ConfigError

from ..models.conditioning import CameraInput
from ..models.registry import run_network
from ..rules import InferenceRules, first_hit_classes, first_hit_label, mirror_average, shift_and_fill
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
            for (o, t), acc in accs.items():
                shifted = shift_and_fill(logits, out.depth_logits, empty_offset=o, fill=base.fill_columns,
                                         fill_threshold=t)
                if best is not None:
                    shifted = first_hit_label(shifted, None, best=best)
                pred = shifted.argmax(1).to(torch.uint8)
                acc.add_volumes(pred, target)
                if cams:
                    count_views(acc, pred, target, grid, cams, backend, truth_hits)
    finally:
        network.train(training)
    return accs


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

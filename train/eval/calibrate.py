"""Choosing a trained model's empty-logit offset (``ModelConfig.empty_offset``) on training-split samples.

The class-weighted cross-entropy that trains SSZ down-weights the empty class (about 97 % of the cells at 64^3),
so the argmax of its logits calls cells occupied more readily than the cell-count metrics reward. After training,
a constant added to every cell's empty logit moves that threshold; it is chosen here on samples of the training
split (never the test split the model is evaluated on), with the model's ``fill_columns`` rule applied after the
shift exactly as the model applies it at inference.
"""

from __future__ import annotations

from collections.abc import Iterable, Sequence
from typing import Any

import torch

from .metrics import Accumulator

OWN_VIEW_TOLERANCE = 0.5
"""An offset may lower the own-view first-hit accuracy by at most this many points against offset 0."""


@torch.no_grad()
def sweep_offsets(generator: Any, batches: Iterable[tuple[torch.Tensor, torch.Tensor]], offsets: Sequence[float],
                  classes: int, *, fill: bool, device: torch.device) -> dict[float, Accumulator]:
    """Volume metrics (cell IoUs, completion, own view) of the generator's predictions at each empty-logit offset.

    Args:
        generator: an :class:`~fruxel.train.models.generator.SSZGenerator`; its own inference rules are switched
            off for the sweep and restored after it.
        batches: ``(images (B, 3, h, w) float in [0, 1], labels (B, D, H, W) integer)`` pairs.
        offsets: the offsets to try, added to every cell's empty logit (channel 0).
        classes: C, classes including empty.
        fill: apply :func:`~fruxel.train.models.generator.fill_columns` after each shift.
        device: where to predict and count.

    Returns:
        An accumulator per offset (no novel views).
    """
    from ..models.generator import inference_rules

    accs = {float(o): Accumulator(classes) for o in offsets}
    rules = (generator.training, generator.empty_offset, generator.fill_columns)
    generator.eval()
    generator.empty_offset, generator.fill_columns = 0.0, False
    try:
        for image, labels in batches:
            out = generator(image.to(device))
            logits = out.logits.float()
            target = labels.to(device).to(torch.uint8)
            for o, acc in accs.items():
                shifted = inference_rules(logits, out.depth_logits, empty_offset=o, fill=fill)
                acc.add_volumes(shifted.argmax(1).to(torch.uint8), target)
    finally:
        generator.train(rules[0])
        generator.empty_offset, generator.fill_columns = rules[1], rules[2]
    return accs


def choose_offset(summaries: dict[float, dict[str, Any]], tolerance: float = OWN_VIEW_TOLERANCE) -> float:
    """The offset with the largest mIoU + completion IoU among those whose own-view first-hit accuracy is within
    ``tolerance`` points of offset 0's (ties: the offset nearest 0).

    Args:
        summaries: :meth:`Accumulator.summary` per offset; must include 0.

    Raises:
        ValueError: no offset 0 among them.
    """
    if 0.0 not in summaries:
        raise ValueError("the offsets must include 0 (the model as trained)")
    floor = summaries[0.0]["own_view_accuracy"] - tolerance
    allowed = [o for o, s in summaries.items() if s["own_view_accuracy"] >= floor]
    return max(allowed, key=lambda o: (summaries[o]["miou"] + summaries[o]["completion_iou"], -abs(o)))

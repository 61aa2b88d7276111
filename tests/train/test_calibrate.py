"""Choosing the inference rules after training (fruxel.train.eval.calibrate)."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch

from fruxel.train.eval.calibrate import choose_rules, rules_of, rules_score, sweep_rules
from fruxel.train.eval.evaluate import evaluate
from fruxel.train.rules import InferenceRules

from .test_blocks import small_config


def _summary(miou: float, completion: float, own: float) -> dict[str, float]:
    return {"miou": miou, "completion_iou": completion, "own_view_accuracy": own}


def test_choose_rules_takes_the_best_sum_of_the_three_targets() -> None:
    s = {(0.0, 0.5): _summary(50, 55, 90), (0.5, 0.5): _summary(51, 56, 89.8), (1.0, 0.5): _summary(52, 57, 87.0),
         (0.5, 0.7): _summary(50.8, 55.7, 91.0), (-0.5, 0.5): _summary(49, 54, 91)}
    assert rules_score(s[(0.5, 0.7)]) == pytest.approx(197.5)
    assert rules_score({**s[(0.5, 0.7)], "novel_view_accuracy": 80.0}) == pytest.approx(277.5)
    assert rules_score({**s[(0.5, 0.7)], "novel_view_accuracy": None}) == pytest.approx(197.5)
    # Counted novel views take part in the choice: (0.5, 0.7) loses them.
    novel = {r: {**v, "novel_view_accuracy": 70.0 if r == (0.5, 0.7) else 80.0} for r, v in s.items()}
    assert choose_rules(novel, (0.0, 0.5)) == (0.5, 0.5)
    # (1.0, 0.5) has the best IoUs but loses 3 points of own view; (0.5, 0.7) trades 0.5 IoU points for 1.2 own view.
    assert choose_rules(s, (0.0, 0.5)) == (0.5, 0.7)
    del s[(0.5, 0.7)]
    assert choose_rules(s, (0.0, 0.5)) == (0.5, 0.5)
    tie = {(0.0, 0.5): _summary(50, 55, 90), (0.5, 0.5): _summary(50, 55, 90), (0.0, 0.6): _summary(50, 55, 90)}
    assert choose_rules(tie, (0.0, 0.5)) == (0.0, 0.5)  # ties: the model as trained
    assert choose_rules(tie, (0.0, 0.6)) == (0.0, 0.6)
    with pytest.raises(ValueError, match="must include the model as trained"):
        choose_rules({(0.5, 0.5): _summary(50, 55, 90)}, (0.0, 0.5))


def test_sweep_counts_what_the_calibrated_model_predicts() -> None:
    """Each pair's counts equal those of the network evaluated under the rules with that ``empty_offset`` and
    ``fill_threshold``; the network comes back in the mode it was in."""
    cfg = small_config()
    torch.manual_seed(3)
    net = cfg.build()
    with torch.no_grad():  # a prediction with some occupied cells at every offset tried
        net.head.bias[0] -= 1.0
        # The depth head's "no surface" near 0.7 (bias ln(0.7 D / 0.3) against D slices at about 0): threshold 0.5
        # fills few columns and 0.9 most.
        net.depth_head.weight.mul_(0.05)
        net.depth_head.bias.zero_()
        net.depth_head.bias[-1] = math.log(0.7 * 16 / 0.3)
    net.train()
    images = torch.rand(4, 3, 32, 32)
    labels = (torch.rand(4, 16, 16, 16) < 0.1).to(torch.uint8) * torch.randint(1, 7, (4, 16, 16, 16),
                                                                               dtype=torch.uint8)
    pairs = [(images[:2], labels[:2]), (images[2:], labels[2:])]
    cpu = torch.device("cpu")
    fill = InferenceRules(fill_columns=True, fill_threshold=0.6)
    accs = sweep_rules(net, pairs, [0.0, 1.5], [0.5, 0.9], 7, base=fill, device=cpu, grid=cfg.grid)
    assert set(accs) == {(0.0, 0.5), (0.0, 0.9), (1.5, 0.5), (1.5, 0.9)} and net.training
    occupied = {}
    for chosen, got in accs.items():
        acc, _ = evaluate(net, rules_of(fill, chosen), pairs, cfg.grid, cfg.classes, device=cpu)
        assert (acc.conf == got.conf).all() and acc.own_correct == got.own_correct
        assert got.novel_pixels > 0 and (acc.novel_pixels, acc.novel_correct, acc.depth_pixels) == (
            got.novel_pixels, got.novel_correct, got.depth_pixels)
        occupied[chosen] = int(acc.conf[:, 1:].sum())
    assert occupied[(1.5, 0.5)] < occupied[(0.0, 0.5)]  # the offset does move the decision
    assert occupied[(1.5, 0.9)] > occupied[(1.5, 0.5)]  # and the threshold fills more columns
    # With first_hit_label and flip_average, on weights whose occupied classes vary from cell to cell.
    with torch.no_grad():  # about 30 % of the cells occupied, their classes varying from cell to cell
        net.head.weight.normal_(0.0, 3.0)
        net.head.bias.zero_()
        net.head.bias[0] = 3.0
    for extra in ({"first_hit_label": True}, {"first_hit_label": True, "flip_average": True}):
        base = dataclasses.replace(fill, **extra)
        labelled = sweep_rules(net, pairs, [0.0, 1.5], [0.9], 7, base=base, device=cpu)
        acc, _ = evaluate(net, rules_of(base, (1.5, 0.9)), pairs, cfg.grid, cfg.classes, device=cpu)
        got = labelled[(1.5, 0.9)]
        assert (acc.conf == got.conf).all() and acc.own_correct == got.own_correct
    unlabelled = sweep_rules(net, pairs, [1.5], [0.9], 7, base=fill, device=cpu)
    assert not (labelled[(1.5, 0.9)].conf == unlabelled[(1.5, 0.9)].conf).all()  # the rules change some cells
    plain = sweep_rules(net, pairs, [0.0], [0.5, 0.9], 7, base=InferenceRules(fill_threshold=0.6), device=cpu)
    assert set(plain) == {(0.0, 0.6)}  # without fill_columns the threshold is not swept
    assert plain[(0.0, 0.6)].novel_pixels == 0  # and without a grid no novel views are counted


@pytest.mark.parametrize("fill", [False, True])
@pytest.mark.parametrize("first_hit", [False, True])
def test_swept_predictions_are_the_rules_argmax_ties_included(fill: bool, first_hit: bool) -> None:
    """Each pair's labels equal the argmax of the rules applied to the whole logits, on integer logits where the
    empty logit often ties the best occupied one and occupied classes tie each other (the argmax takes the first)."""
    from fruxel.train.eval.calibrate import swept_predictions
    from fruxel.train.rules import first_hit_classes, first_hit_label, shift_and_fill

    torch.manual_seed(5)
    logits = torch.randint(-2, 3, (2, 5, 12, 6, 7)).float()
    depth = torch.randn(2, 13, 6, 7)
    best = first_hit_classes(logits) if first_hit else None
    pairs = [(0.0, 0.5), (1.0, 0.5), (0.0, 0.9), (-1.0, 0.9)]
    got = dict(swept_predictions(logits, depth, pairs, fill, best))
    assert list(got) == pairs
    for o, t in pairs:
        x = shift_and_fill(logits, depth, empty_offset=o, fill=fill, fill_threshold=t)
        if first_hit:
            x = first_hit_label(x, None, best=best)
        assert torch.equal(got[(o, t)], x.argmax(1).to(torch.uint8)), (o, t)

"""Inference rules (fruxel.train.rules): each rule against a column-by-column reference, their order, the mirror
average, and the stored settings."""

from __future__ import annotations

import dataclasses
import itertools
import math

import pytest
import torch

from fruxel.errors import ConfigError
from fruxel.train.rules import (
    DEFAULT_FILL_THRESHOLD,
    NO_RULES,
    InferenceRules,
    apply_rules,
    fill_columns,
    first_hit_classes,
    first_hit_label,
    first_hit_log_probs,
    mirror_average,
    predict_logits,
    shift_and_fill,
)

from .test_blocks import small_config


def _network(seed: int) -> torch.nn.Module:
    """A small SSZ in eval mode, every cell empty and every column with a surface by its depth head, so that the
    rules have something to do."""
    torch.manual_seed(seed)
    net = small_config().build().eval()
    with torch.no_grad():
        net.head.bias[0] += 5.0
        net.depth_head.bias[-1] -= 10.0
    return net


# ------------------------------------------------------------------------------------------------ fill_columns
def _fill_reference(logits: torch.Tensor, depth_logits: torch.Tensor,
                    threshold: float = DEFAULT_FILL_THRESHOLD) -> torch.Tensor:
    """Predicted labels after the rule, column by column: (B, D, H, W) int64."""
    labels = logits.argmax(1)
    none = torch.softmax(depth_logits.double(), dim=1)[:, -1]
    b_, _, h_, w_ = labels.shape
    for b in range(b_):
        for y in range(h_):
            for x in range(w_):
                column = logits[b, :, :, y, x].double()  # (C, D)
                if (labels[b, :, y, x] > 0).any() or none[b, y, x] >= threshold:
                    continue
                k = int((1 - torch.softmax(column, dim=0)[0]).argmax())
                labels[b, k, y, x] = int(column[1:, k].argmax()) + 1
    return labels


@pytest.mark.parametrize("threshold", [DEFAULT_FILL_THRESHOLD, 0.85])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_fill_columns_gives_a_surface_to_the_columns_the_head_sees_one_in(dtype: torch.dtype,
                                                                         threshold: float) -> None:
    torch.manual_seed(1)
    logits = torch.randn(2, 5, 6, 4, 3) * 30  # large logits: bfloat16 spacing there is 0.25 to 1
    logits[:, 0] += 60.0  # most columns empty
    logits[0, 0, 2, 1, 1] = -100.0  # one column already has a surface
    depth_logits = torch.randn(2, 7, 4, 3) * 3
    depth_logits[:, -1] += 2.5  # "no surface" from 0.0003 to 0.96: both thresholds tried decide columns
    logits = logits.to(dtype)
    out = fill_columns(logits, depth_logits, threshold=threshold)
    assert out.dtype == dtype and out.shape == logits.shape
    torch.testing.assert_close(out[:, 1:], logits[:, 1:], rtol=0, atol=0)
    expected = _fill_reference(logits.float(), depth_logits, threshold)
    assert torch.equal(out.argmax(1), expected)
    before = (logits.argmax(1) > 0).any(1)
    after = (out.argmax(1) > 0).any(1)
    none = torch.softmax(depth_logits, 1)[:, -1]
    head_sees = none < threshold
    assert torch.equal(after, before | head_sees) and not torch.equal(after, before)
    # The draw has columns between the two thresholds tried, so the threshold decides some columns.
    assert ((none >= DEFAULT_FILL_THRESHOLD) & (none < 0.85) & ~before).any()
    # Only filled columns change, each in one cell.
    changed = (out != logits).any(1)  # (B, D, H, W)
    assert torch.equal(changed.sum(1), (after & ~before).long())


@pytest.mark.parametrize("offset", [0.0, 0.7])
def test_predict_logits_shifts_then_fills(offset: float) -> None:
    net = _network(0)
    image = torch.rand(2, 3, 32, 32)
    rules = InferenceRules(fill_columns=True, empty_offset=offset, fill_threshold=0.9)
    with torch.no_grad():
        ref = net(image)
        out = predict_logits(net, image, rules)
        shifted = ref.logits.clone()
        shifted[:, 0] += offset
        torch.testing.assert_close(out, fill_columns(shifted, ref.depth_logits, threshold=0.9))
        assert (ref.logits.argmax(1) == 0).all() and ((out.argmax(1) > 0).sum(1) == 1).all()
        torch.testing.assert_close(predict_logits(net, image, NO_RULES), ref.logits)  # no rule: the network


# --------------------------------------------------------------------------------------------- first_hit_label
def _first_hit_reference(logits: torch.Tensor) -> torch.Tensor:
    """``P(first hit = c)`` per column by enumerating every labelling of the column: (B, C, H, W) float64."""
    p = torch.softmax(logits.double(), dim=1)
    b_, c_, d_, h_, w_ = p.shape
    out = torch.zeros(b_, c_, h_, w_, dtype=torch.float64)
    for b, y, x in itertools.product(range(b_), range(h_), range(w_)):
        for seq in itertools.product(range(c_), repeat=d_):
            first = next((c for c in seq if c), 0)
            out[b, first, y, x] += math.prod(float(p[b, c, k, y, x]) for k, c in enumerate(seq))
    return out


def test_first_hit_log_probs_is_the_columns_first_hit_distribution() -> None:
    torch.manual_seed(2)
    logits = torch.randn(2, 3, 4, 2, 3) * 2.5
    logits[0, 0, 0, 0, 0] = -80.0  # a cell surely occupied: the cells behind it can never be the first hit
    got = first_hit_log_probs(logits)
    assert got.shape == (2, 3, 2, 3) and got.dtype == torch.float32
    torch.testing.assert_close(got.exp().double(), _first_hit_reference(logits), rtol=1e-5, atol=1e-6)
    shifted = logits.clone()
    shifted[:, 0] += 1.3
    torch.testing.assert_close(first_hit_log_probs(logits, 1.3), first_hit_log_probs(shifted))
    assert torch.isfinite(got).all()


def test_first_hit_label_names_the_board_the_cells_share() -> None:
    """A board spread over three cells, each 40 % furniture and 60 % empty, in front of a wall: the argmax shows
    the wall, the column's first hit is furniture with probability 1 - 0.6^3 = 0.78; only that cell changes."""
    c, d = 5, 6
    logits = torch.full((1, c, d, 2, 2), -20.0)
    logits[:, 0] = 0.0  # empty everywhere ...
    logits[0, 4, 1:4, 0, 0] = math.log(0.4 / 0.6)  # ... but column (0, 0): furniture 40 % in slices 1-3
    logits[0, 0, 5, 0, 0] = -20.0
    logits[0, 1, 5, 0, 0] = 5.0  # a wall in slice 5
    logits[0, 1, 2, 1, 1] = 3.0  # column (1, 1): a wall in slice 2, nothing else
    logits[0, 3, 4, 1, 1] = 9.0  # and a window behind it, which the first hit never is
    torch.testing.assert_close(first_hit_log_probs(logits)[0, 4, 0, 0].exp(), torch.tensor(1 - 0.6 ** 3))
    assert int(logits[0, :, 5, 0, 0].argmax()) == 1
    out = first_hit_label(logits, logits)
    labels, before = out.argmax(1), logits.argmax(1)
    assert int(labels[0, 5, 0, 0]) == 4  # the wall's cell now shows the board ...
    changed = (labels != before).nonzero().tolist()
    assert changed == [[0, 5, 0, 0]]  # ... and nothing else changed: columns without a hit stay empty
    torch.testing.assert_close(out[:, :, :5], logits[:, :, :5], rtol=0, atol=0)
    # After other rules, the first occupied cell of the ruled logits is relabelled (bfloat16 keeps the margin).
    ruled = logits.clone()
    ruled[0, 0, 3, 0, 0] = -30.0  # say a rule made slice 3 the first occupied cell, as furniture
    ruled[0, 1, 3, 0, 0] = 2.0  # ... with wall slightly ahead of furniture there
    out = first_hit_label(ruled.bfloat16(), logits)
    assert out.dtype == torch.bfloat16 and int(out.argmax(1)[0, 3, 0, 0]) == 4
    best = first_hit_classes(logits)
    assert best.shape == (1, 2, 2) and int(best[0, 0, 0]) == 4 and int(best[0, 1, 1]) == 1
    torch.testing.assert_close(first_hit_label(ruled, None, best=best), first_hit_label(ruled, logits))


def test_first_hit_label_comes_after_the_other_rules() -> None:
    net = _network(4)
    image = torch.rand(2, 3, 32, 32)
    ruled = InferenceRules(fill_columns=True, empty_offset=0.5, fill_threshold=0.9)
    with torch.no_grad():
        raw = net(image)
        before = predict_logits(net, image, ruled)
        out = predict_logits(net, image, dataclasses.replace(ruled, first_hit_label=True))
        torch.testing.assert_close(out, first_hit_label(before, raw.logits))
        torch.testing.assert_close(out, apply_rules(raw.logits, raw.depth_logits,
                                                    dataclasses.replace(ruled, first_hit_label=True)))


# ------------------------------------------------------------------------------------------------------ flip_average
def test_flip_average_averages_the_image_and_its_mirror_before_the_rules() -> None:
    torch.manual_seed(5)
    net = small_config().build().eval()
    image = torch.rand(2, 3, 32, 32)
    rules = InferenceRules(fill_columns=True, empty_offset=0.5, fill_threshold=0.9, first_hit_label=True)
    flipped = dataclasses.replace(rules, flip_average=True)
    with torch.no_grad():
        a, m = net(image), net(image.flip(-1))
        # The mirror's outputs mirrored back along W (the last axis), then averaged.
        raw = (a.logits + m.logits.flip(-1)) / 2
        depth = (a.depth_logits + m.depth_logits.flip(-1)) / 2
        avg = mirror_average(net, image, batched=False)
        torch.testing.assert_close(avg.depth_logits, depth)
        torch.testing.assert_close(avg.surface_logits, (a.surface_logits + m.surface_logits.flip(-1)) / 2)
        torch.testing.assert_close(avg.logits, raw)
        out = predict_logits(net, image, flipped)
        want = first_hit_label(shift_and_fill(raw, depth, empty_offset=0.5, fill=True, fill_threshold=0.9), raw)
        torch.testing.assert_close(out, want)
        assert not torch.allclose(out, predict_logits(net, image, rules), atol=1e-3)  # the mirror changes it
        # The average is mirror-symmetric: the mirror image's prediction is the prediction mirrored.
        torch.testing.assert_close(predict_logits(net, image.flip(-1), flipped), out.flip(-1))
        # One batch of both images (the GPU's way) gives what two passes (the CPU's) give.
        one = mirror_average(net, image, batched=True)
        for k, v in vars(avg).items():
            torch.testing.assert_close(getattr(one, k), v)
        torch.testing.assert_close(predict_logits(net, image, flipped, batched_flip=True), out)


# ------------------------------------------------------------------------------------------------------ settings
def test_rules_round_trip_and_check_themselves() -> None:
    rules = InferenceRules(flip_average=True, empty_offset=0.5, fill_columns=True, fill_threshold=0.9,
                           first_hit_label=True)
    assert InferenceRules.from_dict(rules.to_dict()) == rules
    assert InferenceRules.from_dict({}) == NO_RULES and NO_RULES.fill_threshold == DEFAULT_FILL_THRESHOLD
    with pytest.raises(ConfigError, match="rules.empty_offset must be a finite number"):
        InferenceRules(empty_offset=math.inf)
    for bad in (0.0, 1.5, math.nan):
        with pytest.raises(ConfigError, match=r"rules.fill_threshold must be in \(0, 1\]"):
            InferenceRules(fill_threshold=bad)
    with pytest.raises(ConfigError, match="unknown config key 'rules.fill'"):
        InferenceRules.from_dict({"fill": True})
    with pytest.raises(ConfigError, match="rules.flip_average must be true or false"):
        InferenceRules.from_dict({"flip_average": 1})


def test_fill_columns_needs_the_column_depth_head() -> None:
    logits = torch.zeros(1, 3, 2, 2, 2)
    with pytest.raises(ValueError, match="column depth head"):
        apply_rules(logits, None, InferenceRules(fill_columns=True))
    torch.testing.assert_close(apply_rules(logits, None, InferenceRules(empty_offset=1.0))[:, 0], logits[:, 0] + 1)

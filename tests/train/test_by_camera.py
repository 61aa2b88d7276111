"""Metrics per camera bin (issue 39's chart): samples land in the bins their recorded height and pitch name, a bin's
counts are those of its samples as the report's Accumulator counts them, and the bins add up to the whole."""

from __future__ import annotations

import math

import numpy as np
import pytest

torch = pytest.importorskip("torch")

from fruxel.classes import DEFAULT_CLASSES  # noqa: E402
from fruxel.errors import ConfigError  # noqa: E402
from fruxel.grid import FruxelGrid  # noqa: E402
from fruxel.train.eval.by_camera import (  # noqa: E402
    HEIGHT_EDGES,
    PITCH_EDGES,
    CameraBinned,
    CameraBins,
    bin_index,
    by_camera_section,
)
from fruxel.train.eval.evaluate import evaluate_predictions  # noqa: E402
from fruxel.train.eval.metrics import Accumulator  # noqa: E402

GRID = FruxelGrid(width=8, height=6, depth=5, z_near=0.5, z_far=4.0, hfov=60.0)
C = len(DEFAULT_CLASSES.names)
NAMES = tuple(DEFAULT_CLASSES.names)


def volumes(n: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``(pred, truth)``: ``(n, D, H, W)`` uint8 labels, the prediction a noisy copy of the truth (so that the bins'
    metrics differ from one another)."""
    g = torch.Generator().manual_seed(seed)
    truth = torch.randint(0, C, (n, *GRID.shape), generator=g, dtype=torch.uint8)
    truth[torch.rand(truth.shape, generator=g) < 0.5] = 0
    noise = torch.randint(0, C, truth.shape, generator=g, dtype=torch.uint8)
    pred = torch.where(torch.rand(truth.shape, generator=g) < 0.3 * torch.arange(1, n + 1).view(-1, 1, 1, 1) / n,
                       noise, truth)
    return pred, truth


def test_default_edges_are_the_issues_bins() -> None:
    assert HEIGHT_EDGES == (0.3, 0.5, 0.7, 0.9, 1.1, 1.3, 1.5, 1.7, 1.9)
    assert PITCH_EDGES == (-20.0, -10.0, 0.0, 10.0, 20.0, 30.0, 40.0)


def test_values_fall_into_their_bins() -> None:
    heights = [0.29, 0.3, 0.49, 0.5, 0.7000001, 1.2, 1.8999, 1.9, 1.95, math.nan]
    assert bin_index(heights, HEIGHT_EDGES).tolist() == [-1, 0, 0, 1, 2, 4, 7, 7, 8, -2]
    pitches = torch.tensor([-25.0, -20.0, -0.1, 0.0, 9.99, 10.0, 39.0, 40.0, 41.0], dtype=torch.float64)
    assert bin_index(pitches, PITCH_EDGES).tolist() == [-1, 0, 1, 2, 2, 3, 5, 5, 6]


@pytest.mark.parametrize("edges", [(1.0,), (1.0, 0.5), (0.0, math.nan), (0.0, 0.0, 1.0), [0.0, 1.0], (0.0, True)])
def test_bad_edges_are_refused_naming_the_axis(edges: object) -> None:
    with pytest.raises(ConfigError, match="height bin edges"):
        CameraBins(height=edges)  # type: ignore[arg-type]
    with pytest.raises(ConfigError, match="pitch bin edges"):
        CameraBins(pitch=edges)  # type: ignore[arg-type]


def test_each_bin_counts_its_own_samples_and_the_bins_add_up() -> None:
    pred, truth = volumes(7)
    record = {"height": torch.tensor([0.35, 1.0, 1.05, 0.2, math.nan, 1.85, 0.36], dtype=torch.float64),
              "pitch": torch.tensor([5.0, 5.0, -15.0, 35.0, 20.0, 50.0, 5.0], dtype=torch.float64)}
    binned = CameraBinned(C, CameraBins())
    # In two batches, as evaluation feeds it.
    binned.add(pred[:4], truth[:4], {k: v[:4] for k, v in record.items()})
    binned.add(pred[4:], truth[4:], {k: v[4:] for k, v in record.items()})
    want = {"height": {0: [0, 6], 3: [1, 2], 7: [5]}, "pitch": {0: [2], 2: [0, 1, 6], 4: [4], 5: [3]}}
    whole = Accumulator(C)
    whole.add_volumes(pred, truth)
    for axis, bins in want.items():
        summed = Accumulator(C)
        for b, acc in enumerate(binned.accs[axis]):
            alone = Accumulator(C)
            if b in bins:
                alone.add_volumes(pred[bins[b]], truth[bins[b]])
            assert acc.samples == len(bins.get(b, [])), (axis, b)
            assert np.array_equal(acc.conf, alone.conf) and acc.own_hits == alone.own_hits, (axis, b)
            assert acc.own_correct == alone.own_correct, (axis, b)
            summed.merge(acc)
        assert summed.samples == sum(map(len, bins.values()))
    assert binned.outside["height"] == {"below": 1, "above": 0, "unrecorded": 1}
    assert binned.outside["pitch"] == {"below": 0, "above": 1, "unrecorded": 0}
    # The bins of both axes hold different samples, so their metrics differ from bin to bin.
    section = by_camera_section({"model": binned}, NAMES, None)
    assert section["height"]["samples"] == [2, 0, 0, 2, 0, 0, 0, 1]
    assert section["pitch"]["samples"] == [1, 0, 3, 0, 1, 1]
    miou = section["height"]["miou"]["model"]
    assert miou[1] is None and len({round(v, 6) for v in miou if v is not None}) == 3


def test_one_bin_of_everything_gives_the_reports_numbers() -> None:
    """Through evaluate_predictions with two rules: when every sample falls into one bin, that bin's mIoU and
    own-view accuracy are the overall ones of the same rule; with the default bins the bins' confusion matrices add
    up to the overall one."""
    pred, truth = volumes(6, seed=1)
    image = torch.zeros(6, 3, 12, 16)
    record = {"height": torch.tensor([0.4, 0.6, 0.8, 1.2, 1.4, 1.8], dtype=torch.float64),
              "pitch": torch.tensor([-15.0, -5.0, 5.0, 15.0, 25.0, 35.0], dtype=torch.float64)}
    rules = {"model": lambda img, t: pred, "oracle": lambda img, t: t}
    batches = [(image, truth, record)]
    one = {k: CameraBinned(C, CameraBins(height=(0.0, 2.0), pitch=(-90.0, 90.0))) for k in rules}
    accs, _ = evaluate_predictions(rules, batches, GRID, DEFAULT_CLASSES, device=torch.device("cpu"), novel=False,
                                   by_camera=one)
    section = by_camera_section(one, NAMES, "chart.png")
    assert section["chart"] == "chart.png"
    for rule, acc in accs.items():
        overall = acc.summary(NAMES)
        for axis in ("height", "pitch"):
            assert section[axis]["samples"] == [6]
            assert section[axis]["miou"][rule] == [pytest.approx(overall["miou"], rel=1e-12)]
            assert section[axis]["own_view_accuracy"][rule] == [overall["own_view_accuracy"]]
            assert section[axis]["confusion"][rule] == [acc.conf.tolist()]
    assert section["height"]["own_view_accuracy"]["oracle"] == [100.0]
    spread = {"model": CameraBinned(C, CameraBins())}
    evaluate_predictions({"model": rules["model"]}, batches, GRID, DEFAULT_CLASSES, device=torch.device("cpu"),
                         novel=False, by_camera=spread)
    section = by_camera_section(spread, NAMES, None)
    for axis in ("height", "pitch"):
        assert sum(section[axis]["samples"]) == 6
        assert np.sum(section[axis]["confusion"]["model"], axis=0).tolist() == accs["model"].conf.tolist()
        assert sum(section[axis]["own_hits"]["model"]) == accs["model"].own_hits
    assert section["height"]["samples"] == [1, 1, 1, 0, 1, 1, 0, 1]
    assert section["pitch"]["samples"] == [1, 1, 1, 1, 1, 1]


def test_binning_without_camera_records_is_refused() -> None:
    pred, truth = volumes(2)
    with pytest.raises(ValueError, match="camera record"):
        evaluate_predictions({"model": lambda img, t: pred}, [(torch.zeros(2, 3, 12, 16), truth)], GRID,
                             DEFAULT_CLASSES, device=torch.device("cpu"), novel=False,
                             by_camera={"model": CameraBinned(C, CameraBins())})

"""Evaluation: the metrics of conventions section 9 on small hand-computed cases, the two baselines on hand-made
volumes, one pass of several prediction rules, and the report built from their counts."""

from __future__ import annotations

import json

import numpy as np
import pytest

from fruxel import kernels
from fruxel.classes import DEFAULT_CLASSES, ClassTable
from fruxel.grid import FruxelGrid

torch = pytest.importorskip("torch")

from fruxel.train.eval.baselines import (  # noqa: E402 - needs torch
    BaselineError,
    CellPrior,
    oracle_prediction,
    prior_prediction,
)
from fruxel.train.eval.evaluate import evaluate_predictions, spread  # noqa: E402
from fruxel.train.eval.metrics import (  # noqa: E402
    Accumulator,
    completion_iou,
    confusion,
    first_surface,
    iou_per_class,
)
from fruxel.train.eval.report import build_report, markdown_report  # noqa: E402

BACKENDS = kernels.available_backends()


def vol(*slices: list[int]) -> torch.Tensor:
    """A ``(1, D, 1, W)`` label volume from its D slices, each a row of W labels (one row of columns, H = 1)."""
    return torch.tensor([[[row] for row in slices]], dtype=torch.uint8)


# ---------------------------------------------------------------------------------------------------- metrics
# Truth and prediction on a 2-slice, 3-column volume (C = 4): columns i0, i1, i2, slices k0 (front), k1 (back).
TRUTH = vol([1, 0, 0],
            [2, 2, 0])
PRED = vol([1, 3, 0],
           [0, 2, 3])


def test_confusion_counts_true_against_predicted() -> None:
    conf = confusion(PRED, TRUTH, 4).numpy()
    want = np.zeros((4, 4), np.int64)
    want[1, 1] = 1          # k0 i0
    want[0, 3] = 2          # k0 i1, k1 i2: empty predicted as 3
    want[0, 0] = 1          # k0 i2
    want[2, 0] = 1          # k1 i0: 2 missed
    want[2, 2] = 1          # k1 i1
    np.testing.assert_array_equal(conf, want)


def test_iou_miou_and_completion_by_hand() -> None:
    acc = Accumulator(4)
    acc.add_volumes(PRED, TRUTH)
    iou = iou_per_class(acc.conf)
    # class 1: TP 1, FP 0, FN 0; class 2: TP 1, FN 1 -> 1/2; class 3: TP 0, FP 2 -> 0; empty: TP 1, FP 1, FN 2 -> 1/4
    np.testing.assert_allclose(iou, [0.25, 1.0, 0.5, 0.0])
    s = acc.summary(("empty", "a", "b", "c"))
    assert s["iou"] == pytest.approx({"a": 100.0, "b": 50.0, "c": 0.0})
    # mIoU over the classes present in the truth (a and b), not over c, which only the prediction has.
    assert s["miou"] == pytest.approx(75.0)
    # occupied: TP = k0 i0, k1 i1; FP = k0 i1, k1 i2; FN = k1 i0 -> 2 / 5
    assert completion_iou(acc.conf) == pytest.approx(0.4)
    assert s["completion_iou"] == pytest.approx(40.0)


def test_own_view_accuracy_counts_columns_where_the_truth_hits() -> None:
    np.testing.assert_array_equal(first_surface(TRUTH).numpy(), [[[1, 2, 0]]])
    np.testing.assert_array_equal(first_surface(PRED).numpy(), [[[1, 3, 3]]])
    acc = Accumulator(4)
    acc.add_volumes(PRED, TRUTH)
    # Truth hits in i0 and i1; the prediction agrees in i0 only. i2 (a miss in the truth) does not count.
    assert (acc.own_hits, acc.own_correct) == (2, 1)
    assert acc.summary()["own_view_accuracy"] == pytest.approx(50.0)


def test_novel_view_accuracy_and_depth_error_by_hand() -> None:
    acc = Accumulator(4)
    pred_label = np.array([[1, 0], [2, 3], [0, 0]])
    true_label = np.array([[1, 2], [0, 3], [0, 0]])
    pred_depth = np.array([[1.0, 0.0], [2.0, 4.0], [0.0, 0.0]])
    true_depth = np.array([[1.5, 3.0], [0.0, 3.0], [0.0, 0.0]])
    acc.add_views(pred_label, pred_depth, true_label, true_depth)
    # Either hits in 4 pixels (both misses in the last row do not count); labels agree in 2 of them.
    assert (acc.novel_pixels, acc.novel_correct) == (4, 2)
    # Both hit in 2 pixels: |1 - 1.5| and |4 - 3|.
    assert acc.depth_pixels == 2 and acc.depth_abs_sum == pytest.approx(1.5)
    s = acc.summary()
    assert s["novel_view_accuracy"] == pytest.approx(50.0) and s["depth_error"] == pytest.approx(0.75)


def test_counts_pool_every_cell_of_every_sample() -> None:
    """IoU over the whole split, not the mean of per-sample IoUs (which would be 50 % here)."""
    acc = Accumulator(2)
    acc.add_volumes(vol([1, 0, 0, 0]), vol([1, 0, 0, 0]))        # IoU 1 alone
    acc.add_volumes(vol([0, 0, 0, 0]), vol([1, 1, 1, 0]))        # IoU 0 alone
    assert acc.summary()["iou"]["1"] == pytest.approx(25.0)
    assert acc.samples == 2


def test_nothing_to_count_is_none() -> None:
    s = Accumulator(3).summary()
    assert s["miou"] is None and s["own_view_accuracy"] is None and s["depth_error"] is None
    assert s["iou"] == {"1": None, "2": None}


# ---------------------------------------------------------------------------------------------------- baselines
def test_cell_prior_is_the_per_cell_mode() -> None:
    a = np.array([[[0, 1], [2, 3]]], np.uint8)     # (D=1, H=2, W=2)
    b = np.array([[[1, 1], [2, 0]]], np.uint8)
    c = np.array([[[1, 0], [0, 3]]], np.uint8)
    prior = CellPrior((1, 2, 2), 4)
    prior.add(np.stack([a, b]))                    # a batch
    prior.add(torch.from_numpy(c))                 # a single volume, as a tensor
    assert prior.samples == 3
    np.testing.assert_array_equal(prior.counts[0], [1, 2, 0, 0])   # cell (0, 0, 0): 0, 1, 1
    np.testing.assert_array_equal(prior.counts[2], [1, 0, 2, 0])
    # (0,0,0): 1 twice; (0,0,1): 1 twice; (0,1,0): 2 twice; (0,1,1): 3 twice
    np.testing.assert_array_equal(prior.mode(), [[[1, 1], [2, 3]]])
    assert prior.mode().dtype == np.uint8


def test_cell_prior_ties_go_to_the_lower_class() -> None:
    prior = CellPrior((1, 1, 2), 3)
    prior.add(np.array([[[2, 1]]], np.uint8))
    prior.add(np.array([[[1, 0]]], np.uint8))
    np.testing.assert_array_equal(prior.mode(), [[[1, 0]]])


def test_cell_prior_refuses_what_it_cannot_count() -> None:
    prior = CellPrior((1, 2, 2), 3)
    with pytest.raises(BaselineError, match="no training samples"):
        prior.mode()
    with pytest.raises(BaselineError, match="shape"):
        prior.add(np.zeros((1, 2, 3), np.uint8))
    with pytest.raises(BaselineError, match=r"\[0, 3\)"):
        prior.add(np.full((1, 2, 2), 3, np.uint8))
    with pytest.raises(BaselineError, match="integers"):
        prior.add(np.zeros((1, 2, 2), np.float32))
    assert prior.samples == 0 and not prior.counts.any()


def test_prior_prediction_repeats_the_mode_for_every_sample() -> None:
    mode = torch.tensor([[[1, 0], [2, 3]]], dtype=torch.uint8)
    p = prior_prediction(mode, 3)
    assert p.shape == (3, 1, 2, 2)
    assert all(torch.equal(p[b], mode) for b in range(3))


@pytest.mark.parametrize("backend", BACKENDS)
def test_oracle_keeps_each_columns_first_occupied_cell(backend: str) -> None:
    grid = FruxelGrid(width=3, height=2, depth=4, z_near=0.5, z_far=4.0, hfov=60.0)
    truth = np.zeros((2, 4, 2, 3), np.uint8)      # (B, D, H, W)
    truth[0, 1, 0, 0] = 1
    truth[0, 3, 0, 0] = 2                          # behind the wall of the same column: dropped
    truth[0, 0, 1, 2] = 4
    truth[0, 1:, 1, 2] = 3                         # a solid column: only its front cell stays
    truth[1, 2, 0, 1] = 5
    truth[1, 3, 1, 1] = 6
    want = np.zeros_like(truth)
    for b, j, i in np.ndindex(2, 2, 3):
        occupied = np.nonzero(truth[b, :, j, i])[0]
        if len(occupied):
            want[b, occupied[0], j, i] = truth[b, occupied[0], j, i]
    assert want[0, 1, 0, 0] == 1 and want[0, 3, 0, 0] == 0 and want[0, 0, 1, 2] == 4 and want[0, 1:, 1, 2].sum() == 0
    got = oracle_prediction(torch.from_numpy(truth), grid, backend)
    assert isinstance(got, torch.Tensor) and got.dtype == torch.uint8
    np.testing.assert_array_equal(got.numpy(), want)
    # As a prediction its own view is perfect, and it completes nothing behind the surface.
    acc = Accumulator(7)
    acc.add_volumes(got, torch.from_numpy(truth))
    assert acc.summary()["own_view_accuracy"] == 100.0
    assert acc.conf[2, 0] == 1 and acc.conf[3, 0] == 3      # the cells behind a front cell are missed


# ---------------------------------------------------------------------------------------------------- evaluation
def test_one_pass_counts_every_rule_on_the_same_samples() -> None:
    grid = FruxelGrid(width=3, height=1, depth=2, z_near=0.5, z_far=4.0, hfov=60.0)
    truths = [TRUTH, vol([0, 0, 1], [2, 0, 0]), vol([3, 3, 0], [0, 0, 0])]
    images = [torch.full((1, 3, 4, 12), float(n) / 10) for n in range(3)]
    seen: list[int] = []

    def shifted(image: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
        seen.append(len(truth))
        return torch.roll(truth, 1, dims=-1)

    def empty(image: torch.Tensor, truth: torch.Tensor) -> torch.Tensor:
        return torch.zeros_like(truth)

    batches = [(torch.cat(images[:2]), torch.cat(truths[:2])), (images[2], truths[2])]
    accs, kept = evaluate_predictions({"shifted": shifted, "empty": empty}, batches, grid, DEFAULT_CLASSES,
                                      device=torch.device("cpu"), novel=True, keep=[0, 2])
    assert seen == [2, 1]
    want = {"shifted": Accumulator(7), "empty": Accumulator(7)}
    for t in truths:
        for name, pred in (("shifted", torch.roll(t, 1, dims=-1)), ("empty", torch.zeros_like(t))):
            want[name].add_volumes(pred, t)
    for name in want:
        np.testing.assert_array_equal(accs[name].conf, want[name].conf)
        assert (accs[name].own_hits, accs[name].own_correct) == (want[name].own_hits, want[name].own_correct)
        assert accs[name].samples == 3
    # Novel views were counted: an empty prediction agrees with the truth nowhere the truth is seen.
    assert accs["empty"].novel_pixels > 0 and accs["empty"].novel_correct == 0 and accs["empty"].depth_pixels == 0
    assert len(kept) == 2
    assert torch.equal(kept[0]["labels"], truths[0][0]) and torch.equal(kept[1]["labels"], truths[2][0])
    assert torch.equal(kept[1]["pred"], torch.roll(truths[2], 1, dims=-1)[0])
    assert torch.allclose(kept[1]["image"], images[2][0])


# ---------------------------------------------------------------------------------------------------- report
def test_report_holds_the_accumulators_numbers() -> None:
    model, oracle = Accumulator(4), Accumulator(4)
    model.add_volumes(PRED, TRUTH)
    oracle.add_volumes(first_surface_volume(TRUTH), TRUTH)
    model.add_views(np.array([1, 0]), np.array([2.0, 0.0]), np.array([1, 1]), np.array([2.5, 3.0]))
    classes = ClassTable(names=("empty", "a", "b", "c"), colours=DEFAULT_CLASSES.colours[:4])
    report = build_report({"model": model, "oracle": oracle}, classes, model={
        "file": "m.safetensors", "grid": FruxelGrid(width=3, height=1, depth=2, z_near=0.5, z_far=4.0,
                                                     hfov=60.0).to_dict(), "image_size": [4, 12],
        "training": {"step": 7}}, data={"source": "hand-made", "split": "test", "samples": 1},
        prior=None, machine={"cpu": "test"}, command="fruxel-eval --samples 1", seconds=1.234)
    text = json.dumps(report)
    back = json.loads(text)
    assert back["results"]["model"]["miou"] == pytest.approx(75.0)
    assert back["results"]["model"]["confusion"] == model.conf.tolist()
    assert back["results"]["model"]["novel_view_accuracy"] == pytest.approx(50.0)
    assert back["results"]["model"]["depth_error"] == pytest.approx(0.5)
    assert back["results"]["oracle"]["own_view_accuracy"] == pytest.approx(100.0)
    assert back["class_share"]["b"] == pytest.approx(100 * 2 / 6)
    assert "prior" not in back["results"] and "prior" not in back["definitions"]
    md = markdown_report(back)
    lines = md.splitlines()
    # The oracle keeps k0 i0 (a) and k1 i1 (b): a 100 %, b 50 %, like the model, but it predicts no c and
    # completes 2 of the 3 occupied cells with no false ones (the model: 2 of 5).
    assert "| mIoU (%) | 75.0 | 75.0 |" in lines
    assert "| completion IoU (%) | 40.0 | 66.7 |" in lines
    assert "| own-view first-hit accuracy (%) | 50.0 | 100.0 |" in lines
    assert "| novel-view first-hit accuracy (%) | 50.0 | n/a |" in lines
    assert "| a | 16.67 | 100.0 | 100.0 |" in lines
    assert "| b | 33.33 | 50.0 | 50.0 |" in lines
    assert "| novel-view depth error (m) | 0.500 | n/a |" in lines
    assert "| c | 0.00 | 0.0 | n/a |" in lines
    assert "`fruxel-eval --samples 1`" in md and "m.safetensors" in md and "step 7" in md


def first_surface_volume(labels: torch.Tensor) -> torch.Tensor:
    """Each column's first occupied cell, everything else empty (the oracle, computed here without kernels)."""
    occupied = labels != 0
    first = occupied.to(torch.uint8).argmax(dim=1, keepdim=True)
    keep = torch.zeros_like(occupied).scatter_(1, first, True) & occupied
    return labels * keep


def test_report_names_the_inference_rules() -> None:
    from fruxel.train.eval.report import rules_text

    assert rules_text({"fill_columns": True, "empty_offset": 2.0}) == "empty logit +2, fill_columns"
    assert (rules_text({"fill_columns": True, "empty_offset": 3.0, "fill_threshold": 0.7})
            == "empty logit +3, fill_columns (threshold 0.7)")
    assert rules_text({"fill_columns": False, "empty_offset": 0.0, "fill_threshold": 0.7}) == "none (plain argmax)"
    assert rules_text({"fill_columns": False, "empty_offset": -0.5}) == "empty logit -0.5"
    assert rules_text({"fill_columns": False, "empty_offset": 0.0}) == "none (plain argmax)"
    assert (rules_text({"fill_columns": True, "empty_offset": 1.0, "fill_threshold": 0.8, "first_hit_label": True})
            == "empty logit +1, fill_columns (threshold 0.8), first_hit_label")
    assert rules_text({"fill_columns": False, "empty_offset": 0.0, "first_hit_label": False}) == "none (plain argmax)"
    assert (rules_text({"flip_average": True, "fill_columns": True, "empty_offset": 1.0, "fill_threshold": 0.8})
            == "flip_average, empty logit +1, fill_columns (threshold 0.8)")


def test_examples_are_spread_over_the_samples() -> None:
    """Sixteen samples share a room: the examples of a 256-sample evaluation come from four rooms, not one."""
    shown = spread(256, 4)
    assert shown == [0, 85, 170, 255]
    assert len({i // 16 for i in shown}) == 4
    assert spread(3, 4) == [0, 1, 2] and spread(1, 4) == [0]
    assert spread(0, 4) == [] and spread(10, 0) == []


def test_a_camera_model_is_named_with_what_it_was_told_even_under_one_setting() -> None:
    """A report of a model that reads the camera names the setting of every model row, one setting or several; a
    report of a model that reads none (``camera_known`` None, or absent in older reports) names it ``model``."""
    from fruxel.train.eval.report import rule_names

    one = {"results": {"model": {}, "oracle": {}}, "data": {"camera_known": ["gravity", "height"]}}
    several = {"results": {"model": {}, "model@none": {}}, "data": {"camera_known": ["gravity"]}}
    assert rule_names(one)["model"] == "model, camera known: gravity,height"
    assert list(rule_names(several).values()) == ["model, camera known: gravity", "model, camera known: none"]
    for data in ({"camera_known": None}, {}):
        assert rule_names({"results": {"model": {}, "oracle": {}}, "data": data})["model"] == "model"

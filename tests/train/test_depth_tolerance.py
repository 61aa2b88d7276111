"""scripts/depth_tolerance.py: IoU that forgives a class found a few depth slices away."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from fruxel.train.eval.metrics import confusion, iou_per_class

from .conftest import load_script, slab_volumes

ROOT = Path(__file__).resolve().parents[2]


@pytest.fixture(scope="module")
def tol():
    return load_script("depth_tolerance")


def _volumes(seed: int) -> tuple[np.ndarray, np.random.Generator]:
    """A surface two slices thick in each column of ``(2, 12, 5, 6)`` volumes, and the generator."""
    return slab_volumes(seed, 12, (2, 9), 2)


def test_no_tolerance_is_the_usual_iou(tol) -> None:
    truth, rng = _volumes(0)
    pred = np.where(rng.random(truth.shape) < 0.3, rng.integers(0, 4, truth.shape), truth).astype(np.uint8)
    expected = 100 * iou_per_class(confusion(torch.from_numpy(pred), torch.from_numpy(truth), 4).numpy())
    got = tol.tolerant_iou(tol.tolerant_counts(pred, truth, 4, 0))
    np.testing.assert_allclose(got[1:], expected[1:])


def test_a_prediction_one_slice_deeper_is_right_within_one_slice(tol) -> None:
    truth, _ = _volumes(1)
    pred = np.zeros_like(truth)
    pred[:, 1:] = truth[:, :-1]
    exact = tol.tolerant_iou(tol.tolerant_counts(pred, truth, 4, 0))
    within = tol.tolerant_iou(tol.tolerant_counts(pred, truth, 4, 1))
    assert (exact[1:] < 50).all()
    np.testing.assert_allclose(within[1:], 100.0)


def test_a_class_in_neither_volume_is_nan_and_a_missed_one_zero(tol) -> None:
    truth, _ = _volumes(2)
    pred = np.where(truth == 2, 0, truth).astype(np.uint8)
    iou = tol.tolerant_iou(tol.tolerant_counts(pred, truth, 5, 1))
    assert iou[2] == 0.0 and np.isnan(iou[4]) and iou[1] == 100.0


@pytest.mark.slow
def test_it_reads_a_model_on_fruxel_evals_samples(tol, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                  capsys: pytest.CaptureFixture[str], tiny_pack: Path) -> None:
    """The tiny camera-aware model (the paper's six classes) on four streamed samples of the robot's test set: a line
    per tolerance, IoU not falling with it, then what stays wrong; the samples kept in fruxel-eval's cache."""
    monkeypatch.setenv("FRUXEL_ASSETS", str(tiny_pack))
    monkeypatch.setenv("FRUXEL_CACHE_DIR", str(tmp_path))
    model = ROOT / "tests" / "data" / "camera_tiny" / "model.safetensors"
    assert tol.main([str(model), "--test-set", "robot", "--samples", "4", "--batch", "4"]) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert len(lines) == 5 and lines[3].startswith("wrong within 1 slice") and lines[4].startswith("wall ")
    lines = lines[:3]
    assert [ln.split(":")[0] for ln in lines] == [f"within {r} slice(s)" for r in (0, 1, 2)]
    mious = [float(ln.split("mIoU ")[1].split()[0]) for ln in lines]
    assert mious == sorted(mious)
    assert list((tmp_path / "samples").glob("*.npz"))  # fruxel-eval's cache, for the next look


def test_what_stays_wrong_is_told_apart(tol) -> None:
    """One column: a wall at slices 3 to 5 (4 and 5 hidden behind 3); the prediction has only its front slice and a
    false wall in free space at slice 8."""
    truth = np.zeros((1, 12, 1, 1), dtype=np.uint8)
    truth[0, 3:6, 0, 0] = 1
    pred = np.zeros_like(truth)
    pred[0, 3, 0, 0] = 1
    pred[0, 8, 0, 0] = 1
    counts = tol.error_counts(pred, truth, 2, r=0)
    # true 4 and 5 not found, both predicted empty, both behind the first occupied cell; predicted 8 not right, empty
    assert counts[1].tolist() == [2, 2, 2, 1, 1]
    assert tol.error_counts(pred, truth, 2, r=1)[1].tolist() == [1, 1, 1, 1, 1]


@pytest.fixture(scope="module")
def snap():
    return load_script("depth_snap")


def test_snapping_puts_each_first_cell_on_the_truths_and_carries_the_column(snap) -> None:
    """scripts/depth_snap.py: a column whose first cell is one slice short moves one slice back with what lies
    behind it; one of another class, or too far, stays; a shifted-out slice leaves empty behind it."""
    truth = np.zeros((1, 8, 1, 3), dtype=np.uint8)
    pred = np.zeros_like(truth)
    truth[0, 4:6, 0, 0], pred[0, 3:5, 0, 0], pred[0, 6, 0, 0] = 1, 1, 2  # near miss, with a cell behind
    truth[0, 4, 0, 1], pred[0, 3, 0, 1] = 1, 2  # classes differ
    truth[0, 7, 0, 2], pred[0, 2, 0, 2] = 1, 1  # five slices apart
    shift = snap.snap_shifts(pred, truth, [1], within=2)
    assert shift.tolist() == [[[1, 0, 0]]]
    out = snap.shift_columns(pred, shift)
    assert out[0, :, 0, 0].tolist() == [0, 0, 0, 0, 1, 1, 0, 2]
    assert (out[0, :, 0, 1:] == pred[0, :, 0, 1:]).all()
    assert snap.snap_shifts(pred, truth, [1], within=0)[0, 0, 2] == 5
    far = snap.shift_columns(pred, np.full((1, 1, 3), 4))[0, :, 0, 0]
    assert far.tolist() == [0, 0, 0, 0, 0, 0, 0, 1]  # its first cell at the far end, the rest shifted out


def test_moving_a_first_run_leaves_the_rest_of_its_column(snap) -> None:
    """Only the surface moves: the first cell and its class's cells right behind it; a cell of another class
    behind them stays, and one the run lands on is overwritten."""
    col = np.zeros((1, 8, 1, 1), dtype=np.uint8)
    col[0, 2:4, 0, 0], col[0, 4, 0, 0], col[0, 6, 0, 0] = 1, 2, 1
    out = snap.move_first_runs(col, np.array([[[2]]]))[0, :, 0, 0]
    assert out.tolist() == [0, 0, 0, 0, 1, 1, 1, 0]  # run 2-3 moved to 4-5 over the 2; the 1 at 6 stays
    assert snap.move_first_runs(col, np.array([[[-1]]]))[0, :, 0, 0].tolist() == [0, 1, 1, 0, 2, 0, 1, 0]
    empty = np.zeros((1, 8, 1, 1), dtype=np.uint8)
    assert not snap.move_first_runs(empty, np.array([[[3]]])).any()

"""scripts/paired_bootstrap.py: mIoU differences with intervals from draws of whole rooms, paired across models."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fruxel.train.eval.metrics import Accumulator

from .conftest import load_script, slab_volumes


@pytest.fixture(scope="module")
def pb():
    return load_script("paired_bootstrap")


def _noisy(truth: np.ndarray, share: float, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return np.where(rng.random(truth.shape) < share, rng.integers(0, 4, truth.shape), truth).astype(np.uint8)


def test_the_rooms_counts_give_fruxel_evals_miou(pb) -> None:
    truth, _ = slab_volumes(0, 12, (2, 9), 2)  # (2, 12, 5, 6), classes 1..3
    truth = np.concatenate([truth, truth[:, :, ::-1]])  # 4 samples
    pred = _noisy(truth, 0.3, 1)
    rooms = pb.room_confusions([(pred[:3], truth[:3]), (pred[3:], truth[3:])], 4, per_room=2)
    assert rooms.shape == (2, 4, 4)
    acc = Accumulator(4)
    acc.add_volumes(torch.from_numpy(pred), torch.from_numpy(truth))
    assert pb.miou(rooms.sum(axis=0)) == pytest.approx(acc.summary()["miou"])


def test_a_better_model_is_above_zero_in_every_draw_and_a_copy_in_none(pb) -> None:
    truth, _ = slab_volumes(2, 12, (2, 9), 2)
    rooms = [np.stack([pb.room_confusions([(_noisy(truth, share, 10 * r + k), truth)], 4, per_room=2)[0]
                       for r in range(8)]) for k, share in enumerate((0.4, 0.1))]
    confs = np.stack([rooms[0], rooms[1], rooms[0]])  # worse, better, the worse again
    draws = pb.bootstrap(confs, rounds=200, seed=3)
    assert draws.shape == (200, 3)
    assert (draws[:, 1] > draws[:, 0]).all()
    assert (draws[:, 2] == draws[:, 0]).all()
    lo, hi = np.percentile(draws[:, 0], [2.5, 97.5])
    assert lo <= pb.miou(confs[0].sum(axis=0)) <= hi


def test_bad_arguments_are_one_line(pb, capsys: pytest.CaptureFixture[str]) -> None:
    assert pb.main(["ssz64-any"]) == 2
    assert pb.main(["ssz64-any", "ssz64-any", "--samples", "40"]) == 2
    assert pb.main(["ssz64-any", "no-such-model.safetensors", "--samples", "32"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 3 and "two models" in err[0] and "multiple of 16" in err[1] and "no-such-model" in err[2]

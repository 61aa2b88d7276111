"""scripts/thickness_oracle.py: the IoU that the walls' unseen thickness leaves a reader that knows all else."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import torch

from fruxel.train.eval.metrics import confusion, iou_per_class

from .conftest import load_script


@pytest.fixture(scope="module")
def oracle():
    return load_script("thickness_oracle")


def test_counts_give_the_usual_iou(oracle) -> None:
    """Per-class IoU from the counts the script takes from depth_tolerance (no tolerance) equals the product's
    confusion-matrix IoU on random volumes; a class in neither volume is NaN."""
    rng = np.random.default_rng(3)
    truth = rng.integers(0, 4, size=(2, 6, 5, 4)).astype(np.uint8)
    pred = np.where(rng.random(truth.shape) < 0.3, rng.integers(0, 4, size=truth.shape), truth).astype(np.uint8)
    ours = oracle.tolerant_iou(oracle.tolerant_counts(pred, truth, 5, 0))
    ref = iou_per_class(confusion(torch.from_numpy(pred).long(), torch.from_numpy(truth).long(), 5).numpy())
    assert np.allclose(ours[1:4], 100.0 * ref[1:4])
    assert np.isnan(ours[4]) and np.isnan(ours[0])


def test_a_thicker_wall_costs_its_extra_cells(oracle) -> None:
    """A wall of 2 slices guessed as 3: IoU 2/3; guessed right: 100."""
    truth = np.zeros((1, 8, 2, 2), dtype=np.uint8)
    truth[:, 4:6] = 1
    guess = np.zeros_like(truth)
    guess[:, 4:7] = 1
    assert oracle.tolerant_iou(oracle.tolerant_counts(guess, truth, 2, 0))[1] == pytest.approx(200.0 / 3.0)
    assert oracle.tolerant_iou(oracle.tolerant_counts(truth, truth, 2, 0))[1] == 100.0


def test_the_config_changes_only_the_walls_thickness(oracle) -> None:
    """The wrapped sim_config collapses the home world's wall thickness range and leaves the rest as it was."""
    from fruxel.train import samples
    from fruxel.train.config import preset

    model = preset("ssz64-any").model
    source = samples.SampleSource(seed=0, assets="", test_set="any-camera", augment=True)
    before = samples.sim_config(model, source, (("test", 4),))
    after = oracle.with_wall_thickness(samples.sim_config, 0.2)(model, source, (("test", 4),))
    assert before.home.wall_thickness_range != (0.2, 0.2)
    assert after.home.wall_thickness_range == (0.2, 0.2)
    assert after.replace(home=before.home) == before


@pytest.mark.slow
def test_it_compares_the_same_rooms_with_other_walls(oracle, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                     capsys: pytest.CaptureFixture[str], tiny_pack: Path) -> None:
    """One streamed sample of the any-camera set, made twice: the floor and ceiling stay nearly as they were (the same
    room and camera; only their slabs' rims under the walls move), the walls change."""
    monkeypatch.setenv("FRUXEL_ASSETS", str(tiny_pack))
    monkeypatch.setenv("FRUXEL_CACHE_DIR", str(tmp_path))
    assert oracle.main(["--samples", "1", "--thickness", "0.6"]) == 0
    line = capsys.readouterr().out.strip().splitlines()[-1]
    scores = dict(zip(line.split("| ")[1].split()[::2], line.split("| ")[1].split()[1::2], strict=True))
    assert float(scores["wall"]) < 80.0
    assert float(scores["floor"]) > 80.0 and float(scores["ceiling"]) > 80.0

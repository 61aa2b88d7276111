"""Choosing the empty-logit offset after training (train/eval/calibrate.py, scripts/calibrate.py)."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
from pathlib import Path

import pytest
import torch

from fruxel.grid import FruxelGrid
from fruxel.train.config import ModelConfig, TrainConfig
from fruxel.train.engine.trainer import sim_config
from fruxel.train.eval.calibrate import choose_offset, sweep_offsets
from fruxel.train.eval.evaluate import evaluate
from fruxel.train.export import build_generator, read_weights, save_shipped
from fruxel.train.sim.writer import generate


def _summary(miou: float, completion: float, own: float) -> dict[str, float]:
    return {"miou": miou, "completion_iou": completion, "own_view_accuracy": own}


def test_choose_offset_takes_the_best_iou_within_the_own_view_tolerance() -> None:
    s = {0.0: _summary(50, 55, 90), 0.5: _summary(51, 56, 89.8), 1.0: _summary(52, 57, 89.0),
         -0.5: _summary(49, 54, 91)}
    assert choose_offset(s) == 0.5  # 1.0 is better on IoU but costs a point of own view
    assert choose_offset(s, tolerance=2.0) == 1.0
    assert choose_offset({0.0: _summary(50, 55, 90), 0.5: _summary(50, 55, 90)}) == 0.0  # ties: nearest 0
    with pytest.raises(ValueError, match="must include 0"):
        choose_offset({0.5: _summary(50, 55, 90)})


def _tiny() -> ModelConfig:
    grid = FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0)
    return ModelConfig(grid=grid, levels=3, stem=8, encoder=(8, 8, 8), encoder_blocks=(1, 1, 1), topdown=(8, 8, 8),
                       decoder=(8, 8, 8), decoder_blocks=(1, 1, 1))


def test_sweep_counts_what_the_calibrated_model_predicts(tmp_path: Path) -> None:
    """Each offset's counts equal those of the model built with that ``empty_offset`` (and ``fill_columns``), and
    the sweep leaves the generator's own rules as they were."""
    cfg = _tiny()
    torch.manual_seed(3)
    gen = build_generator(dataclasses.replace(cfg, fill_columns=True, empty_offset=0.3))
    with torch.no_grad():  # a prediction with some occupied cells at every offset tried
        gen.head.bias[0] -= 2.0
    gen.train()
    images = torch.rand(4, 3, 32, 32)
    labels = (torch.rand(4, 16, 16, 16) < 0.1).to(torch.uint8) * torch.randint(1, 7, (4, 16, 16, 16),
                                                                               dtype=torch.uint8)
    pairs = [(images[:2], labels[:2]), (images[2:], labels[2:])]
    accs = sweep_offsets(gen, pairs, [0.0, 1.5], 7, fill=True, device=torch.device("cpu"))
    assert gen.training and gen.empty_offset == 0.3 and gen.fill_columns
    sums = {}
    for offset in (0.0, 1.5):
        other = build_generator(dataclasses.replace(cfg, fill_columns=True, empty_offset=offset))
        other.load_state_dict(gen.state_dict())
        acc, _ = evaluate(other, pairs, cfg.grid, cfg.classes, device=torch.device("cpu"), novel=False)
        assert (acc.conf == accs[offset].conf).all() and acc.own_correct == accs[offset].own_correct
        sums[offset] = int(acc.conf[1:, 1:].sum())
    assert sums[1.5] < sums[0.0]  # the offset does move the decision


def test_calibrate_script_writes_the_chosen_offset(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    spec = importlib.util.spec_from_file_location("calibrate", Path(__file__).parents[2] / "scripts" / "calibrate.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    main = script.main

    cfg = _tiny()
    data = tmp_path / "data"
    sim = dataclasses.replace(sim_config(TrainConfig(model=cfg)), splits=(("train", 4),), shard_size=4)
    generate(str(data), sim, 0, progress=False)
    torch.manual_seed(0)
    model = tmp_path / "m.safetensors"
    save_shipped(model, build_generator(cfg), cfg, {"steps": 7}, half=False)
    out = tmp_path / "cal.safetensors"
    assert main([str(model), "--data", str(data), "--samples", "4", "--offsets", "0.5", "--fill", "--batch", "2",
                 "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    _, written, training = read_weights(out)
    assert written.fill_columns and written.empty_offset in (0.0, 0.5)
    assert f"empty_offset {written.empty_offset:g}" in printed and "(chosen)" in printed
    cal = training["calibration"]
    assert training["steps"] == 7 and cal["samples"] == 4 and set(cal["sweep"]) == {"0", "0.5"}
    json.dumps(training)
    assert main([str(model), "--data", str(data), "--out", str(tmp_path / "x.bin")]) == 2
    assert "must end in .safetensors" in capsys.readouterr().err

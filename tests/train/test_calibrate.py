"""Choosing the inference rules after training (train/eval/calibrate.py, scripts/calibrate.py)."""

from __future__ import annotations

import dataclasses
import importlib.util
import json
import math
from pathlib import Path

import pytest
import torch

from fruxel.grid import FruxelGrid
from fruxel.train.config import ModelConfig, TrainConfig
from fruxel.train.engine.trainer import sim_config
from fruxel.train.eval.calibrate import choose_rules, rules_score, sweep_rules
from fruxel.train.eval.evaluate import evaluate
from fruxel.train.export import build_generator, read_weights, save_shipped
from fruxel.train.sim.writer import generate


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


def _tiny() -> ModelConfig:
    grid = FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0)
    return ModelConfig(grid=grid, levels=3, stem=8, encoder=(8, 8, 8), encoder_blocks=(1, 1, 1), topdown=(8, 8, 8),
                       decoder=(8, 8, 8), decoder_blocks=(1, 1, 1))


def test_sweep_counts_what_the_calibrated_model_predicts(tmp_path: Path) -> None:
    """Each pair's counts equal those of the model built with that ``empty_offset`` and ``fill_threshold`` (and
    ``fill_columns``), and the sweep leaves the generator's own rules as they were."""
    cfg = _tiny()
    torch.manual_seed(3)
    gen = build_generator(dataclasses.replace(cfg, fill_columns=True, empty_offset=0.3, fill_threshold=0.6))
    with torch.no_grad():  # a prediction with some occupied cells at every offset tried
        gen.head.bias[0] -= 1.0
        # The depth head's "no surface" near 0.7 (bias ln(0.7 D / 0.3) against D slices at about 0): threshold 0.5
        # fills few columns and 0.9 most.
        gen.depth_head.weight.mul_(0.05)
        gen.depth_head.bias.zero_()
        gen.depth_head.bias[-1] = math.log(0.7 * 16 / 0.3)
    gen.train()
    images = torch.rand(4, 3, 32, 32)
    labels = (torch.rand(4, 16, 16, 16) < 0.1).to(torch.uint8) * torch.randint(1, 7, (4, 16, 16, 16),
                                                                               dtype=torch.uint8)
    pairs = [(images[:2], labels[:2]), (images[2:], labels[2:])]
    accs = sweep_rules(gen, pairs, [0.0, 1.5], [0.5, 0.9], 7, fill=True, device=torch.device("cpu"), grid=cfg.grid)
    assert set(accs) == {(0.0, 0.5), (0.0, 0.9), (1.5, 0.5), (1.5, 0.9)}
    assert gen.training and gen.empty_offset == 0.3 and gen.fill_columns and gen.fill_threshold == 0.6
    occupied = {}
    for offset, threshold in accs:
        other = build_generator(dataclasses.replace(cfg, fill_columns=True, empty_offset=offset,
                                                    fill_threshold=threshold))
        other.load_state_dict(gen.state_dict())
        acc, _ = evaluate(other, pairs, cfg.grid, cfg.classes, device=torch.device("cpu"))
        got = accs[(offset, threshold)]
        assert (acc.conf == got.conf).all() and acc.own_correct == got.own_correct
        assert got.novel_pixels > 0 and (acc.novel_pixels, acc.novel_correct, acc.depth_pixels) == (
            got.novel_pixels, got.novel_correct, got.depth_pixels)
        occupied[(offset, threshold)] = int(acc.conf[:, 1:].sum())
    assert occupied[(1.5, 0.5)] < occupied[(0.0, 0.5)]  # the offset does move the decision
    assert occupied[(1.5, 0.9)] > occupied[(1.5, 0.5)]  # and the threshold fills more columns
    # With first_hit_label, on weights whose occupied classes vary from cell to cell.
    varied = build_generator(cfg)
    varied.load_state_dict(gen.state_dict())
    with torch.no_grad():  # about 30 % of the cells occupied, their classes varying from cell to cell
        varied.head.weight.normal_(0.0, 3.0)
        varied.head.bias.zero_()
        varied.head.bias[0] = 3.0
    labelled = sweep_rules(varied, pairs, [0.0, 1.5], [0.9], 7, fill=True, device=torch.device("cpu"),
                           first_hit=True)
    unlabelled = sweep_rules(varied, pairs, [1.5], [0.9], 7, fill=True, device=torch.device("cpu"))
    assert not varied.first_hit_label
    other = build_generator(dataclasses.replace(cfg, fill_columns=True, empty_offset=1.5, fill_threshold=0.9,
                                                first_hit_label=True))
    other.load_state_dict(varied.state_dict())
    acc, _ = evaluate(other, pairs, cfg.grid, cfg.classes, device=torch.device("cpu"))
    got = labelled[(1.5, 0.9)]
    assert (acc.conf == got.conf).all() and acc.own_correct == got.own_correct
    assert not (got.conf == unlabelled[(1.5, 0.9)].conf).all()  # the rule changes some first cells' classes
    plain = sweep_rules(gen, pairs, [0.0], [0.5, 0.9], 7, fill=False, device=torch.device("cpu"))
    assert set(plain) == {(0.0, 0.6)}  # without fill_columns the threshold is not swept
    assert plain[(0.0, 0.6)].novel_pixels == 0  # and without a grid no novel views are counted


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
    assert main([str(model), "--data", str(data), "--samples", "4", "--offsets", "0.5", "--fill", "--thresholds",
                 "0.9", "--batch", "2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    _, written, training = read_weights(out)
    assert written.fill_columns and written.empty_offset in (0.0, 0.5) and written.fill_threshold in (0.5, 0.9)
    assert f"empty_offset {written.empty_offset:g}" in printed and "(chosen)" in printed
    assert f"fill_threshold {written.fill_threshold:g}" in printed and "novel view %" in printed
    cal = training["calibration"]
    assert all("novel_view_accuracy" in v for v in cal["sweep"].values())
    assert training["steps"] == 7 and cal["samples"] == 4 and set(cal["sweep"]) == {"0/0.5", "0/0.9", "0.5/0.5",
                                                                                      "0.5/0.9"}
    assert cal["fill_threshold"] == written.fill_threshold
    json.dumps(training)
    assert main([str(model), "--data", str(data), "--samples", "4", "--offsets", "0.5", "--batch", "2", "--no-novel",
                 "--out", str(tmp_path / "plain.safetensors")]) == 0
    _, written, training = read_weights(tmp_path / "plain.safetensors")
    assert not written.fill_columns and set(training["calibration"]["sweep"]) == {"0", "0.5"}
    assert not any("novel_view_accuracy" in v for v in training["calibration"]["sweep"].values())
    capsys.readouterr()
    # Streamed samples (no --data) of a data seed, with first_hit_label.
    assert main([str(model), "--seed", "3", "--samples", "2", "--offsets", "0.5", "--fill", "--thresholds", "0.9",
                 "--first-hit-label", "--no-novel", "--batch", "2", "--out", str(tmp_path / "fh.safetensors")]) == 0
    assert "the simulator (data seed 3)" in capsys.readouterr().out
    _, written, training = read_weights(tmp_path / "fh.safetensors")
    assert written.first_hit_label and written.fill_columns
    cal = training["calibration"]
    assert cal["first_hit_label"] and cal["data"] == "stream:seed=3" and cal["samples"] == 2
    assert not written.flip_average and not cal["flip_average"]
    # With flip_average: the sweep is of the mirrored average (other numbers than without), and the model keeps it.
    assert main([str(model), "--seed", "3", "--samples", "2", "--offsets", "0.5", "--fill", "--thresholds", "0.9",
                 "--first-hit-label", "--flip-average", "--no-novel", "--batch", "2",
                 "--out", str(tmp_path / "flip.safetensors")]) == 0
    assert "flip_average True" in capsys.readouterr().out
    _, flipped, flip_training = read_weights(tmp_path / "flip.safetensors")
    assert flipped.flip_average and flip_training["calibration"]["flip_average"]
    assert flip_training["calibration"]["sweep"] != cal["sweep"]
    assert main([str(model), "--data", str(data), "--seed", "3", "--out", str(out)]) == 2
    err = capsys.readouterr().err
    assert "--seed picks streamed samples" in err and len(err.strip().splitlines()) == 1
    assert main([str(model), "--data", str(data), "--out", str(tmp_path / "x.bin")]) == 2
    assert "must end in .safetensors" in capsys.readouterr().err
    for bad in ("0", "1.5", "nan"):
        assert main([str(model), "--data", str(data), "--fill", "--thresholds", bad, "--out", str(out)]) == 2
        err = capsys.readouterr().err
        assert "--thresholds must be numbers in (0, 1]" in err and len(err.strip().splitlines()) == 1

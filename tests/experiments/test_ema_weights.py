"""The weight-average experiment: a real (16^3) training run through it writes ``ema.safetensors`` beside the
trained model, the average of the parameters over the steps, which a resumed run continues."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
import torch

from fruxel.train.model_files import read_model_file

from .conftest import load_experiment

ema = load_experiment("ema_weights")

CONFIG = {
    "preset": "tiny", "name": "ema-test",
    "model": {"grid": {"width": 16, "height": 16, "depth": 16}, "levels": 3, "stem": 8, "encoder": [8, 12, 16],
              "encoder_blocks": [1, 1, 1], "topdown": [8, 12, 16], "decoder": [4, 8, 12],
              "decoder_blocks": [1, 1, 1]},
    "data": {"world": "flat", "camera": "robot", "workers": 0, "samples_per_scene": 4, "train_samples": 64,
             "test_samples": 4, "eval_samples": 0, "frequency_samples": 4, "replay": 0},
    "optim": {"lr": 0.01, "warmup": 1},
    "run": {"steps": 3, "batch_size": 2, "log_every": 1, "eval_every": 0, "checkpoint_every": 0,
            "tensorboard": False},
}


def _train(tmp_path: Path, out: Path, decay: float, *extra: str) -> tuple[dict, dict, dict]:
    cfg = tmp_path / "config.json"
    cfg.write_text(json.dumps(CONFIG))
    args = ["--config", str(cfg)] if "--resume" not in extra else []
    assert ema.main(["--decay", str(decay), "--", *args, "--out", str(out), "--device", "cpu", "-q", *extra]) == 0
    model, average = read_model_file(out / "model.safetensors"), read_model_file(out / ema.EMA_FILE)
    return model.state, average.state, average.training


def _params(state: dict) -> list[str]:
    return [k for k, v in state.items() if v.is_floating_point() and "running" not in k]


def test_a_short_memory_average_is_the_trained_model_and_a_long_one_is_not(tmp_path: Path) -> None:
    model, average, meta = _train(tmp_path, tmp_path / "short", 1e-6)
    assert meta["step"] == 3 and meta["ema_decay"] == 1e-6
    for k in _params(model):
        # Both files store float16: one unit in the last place apart at most.
        torch.testing.assert_close(average[k].float(), model[k].float(), rtol=2e-3, atol=1e-6)
    model, average, _ = _train(tmp_path, tmp_path / "long", 1.0 - 1e-7)
    moved = [k for k in _params(model) if not torch.equal(model[k], average[k])]
    assert len(moved) > len(_params(model)) // 2


def test_a_resumed_run_continues_the_average(tmp_path: Path) -> None:
    out = tmp_path / "run"
    _, first, _ = _train(tmp_path, out, 0.5)
    model, average, meta = _train(tmp_path, out, 0.5, "--resume", "--steps", "5")
    assert meta["step"] == 5
    k = max(_params(model), key=lambda k: (model[k].float() - first[k].float()).abs().max())
    # Two more steps of a half-life of one step: the average moved from where the first run left it.
    assert not torch.equal(average[k], first[k])


def test_a_bad_decay_is_refused_in_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        ema.main(["--decay", "1.5", "--", "--preset", "tiny"])
    assert e.value.code == 2
    assert "--decay must be in (0, 1)" in capsys.readouterr().err

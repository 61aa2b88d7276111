"""fruxel-calibrate: the rules chosen on training-split samples, written under the model file's rules key with
the weights unchanged; one line for each bad option."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from fruxel.cli.calibrate import main  # noqa: E402
from fruxel.train.model_files import read_model_file, save_model  # noqa: E402
from fruxel.train.samples import SampleSource, sim_config  # noqa: E402
from fruxel.train.sim.writer import generate  # noqa: E402

from .conftest import small_model_config  # noqa: E402


@pytest.mark.slow
def test_calibrate_writes_the_chosen_rules(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cfg = small_model_config()
    data = tmp_path / "data"
    sim = dataclasses.replace(sim_config(cfg, SampleSource(), (("train", 4),)), shard_size=4)
    generate(str(data), sim, 0, progress=False)
    torch.manual_seed(0)
    model = tmp_path / "m.safetensors"
    save_model(model, cfg.build(), cfg, training={"steps": 7}, half=False)
    weights = read_model_file(model).state
    out = tmp_path / "cal.safetensors"
    assert main([str(model), "--data", str(data), "--samples", "4", "--offsets", "0.5", "--fill", "--thresholds",
                 "0.9", "--batch", "2", "--out", str(out)]) == 0
    printed = capsys.readouterr().out
    written = read_model_file(out)
    rules = written.rules
    assert rules.fill_columns and rules.empty_offset in (0.0, 0.5) and rules.fill_threshold in (0.5, 0.9)
    assert all(torch.equal(written.state[k], v) for k, v in weights.items()) and written.config == cfg
    assert f"wrote {out}: {rules}" in printed and "(chosen)" in printed and "novel view %" in printed
    cal = written.training["calibration"]
    assert all("novel_view_accuracy" in v for v in cal["sweep"].values())
    assert written.training["steps"] == 7 and cal["samples"] == 4
    assert set(cal["sweep"]) == {"0/0.5", "0/0.9", "0.5/0.5", "0.5/0.9"} and cal["rules"] == rules.to_dict()
    json.dumps(written.training)
    assert main([str(model), "--data", str(data), "--samples", "4", "--offsets", "0.5", "--batch", "2", "--no-novel",
                 "--out", str(tmp_path / "plain.safetensors")]) == 0
    written = read_model_file(tmp_path / "plain.safetensors")
    assert not written.rules.fill_columns and set(written.training["calibration"]["sweep"]) == {"0", "0.5"}
    assert not any("novel_view_accuracy" in v for v in written.training["calibration"]["sweep"].values())
    capsys.readouterr()
    # Streamed samples (no --data) of a data seed, with first_hit_label.
    assert main([str(model), "--seed", "3", "--samples", "2", "--offsets", "0.5", "--fill", "--thresholds", "0.9",
                 "--first-hit-label", "--no-novel", "--batch", "2", "--out", str(tmp_path / "fh.safetensors")]) == 0
    assert "simulator stream, seed 3" in capsys.readouterr().out
    fh = read_model_file(tmp_path / "fh.safetensors")
    assert fh.rules.first_hit_label and fh.rules.fill_columns and not fh.rules.flip_average
    cal = fh.training["calibration"]
    assert cal["data"] == "stream:seed=3" and cal["samples"] == 2
    # With flip_average: the sweep is of the mirrored average (other numbers than without), and the model keeps it.
    assert main([str(model), "--seed", "3", "--samples", "2", "--offsets", "0.5", "--fill", "--thresholds", "0.9",
                 "--first-hit-label", "--flip-average", "--no-novel", "--batch", "2",
                 "--out", str(tmp_path / "flip.safetensors")]) == 0
    flipped = read_model_file(tmp_path / "flip.safetensors")
    assert flipped.rules.flip_average and flipped.training["calibration"]["sweep"] != cal["sweep"]
    capsys.readouterr()


@pytest.mark.parametrize(("argv", "words"), [
    (["--seed", "3"], "--seed picks streamed samples"),
    (["--out", "x.bin"], "must end in .safetensors"),
    (["--fill", "--thresholds", "0"], "--thresholds must be numbers in (0, 1]"),
    (["--fill", "--thresholds", "1.5"], "--thresholds must be numbers in (0, 1]"),
    (["--fill", "--thresholds", "nan"], "--thresholds must be numbers in (0, 1]"),
    (["--offsets", "inf"], "--offsets must be finite numbers"),
    (["--test-set", "robot"], "--test-set robot streams the test set's samples; a data set (--data) has its own"),
    (["--assets", "pack"], "--assets names the asset pack of a --test-set"),
])
def test_bad_options_give_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
                                   words: str) -> None:
    out = ["--out", str(tmp_path / "c.safetensors")] if "--out" not in argv else []
    assert main(["ssz64", "--data", str(tmp_path), *argv, *out]) == 2
    err = capsys.readouterr().err
    assert words in err and len(err.strip().splitlines()) == 1 and "Traceback" not in err


def test_calibrate_on_a_test_set_stream(home_model: Path, tiny_pack: Path, tmp_path: Path,
                                        capsys: pytest.CaptureFixture[str]) -> None:
    """--test-set: the set's stream (here the furnished rooms from any camera, from the pack --assets names), said
    in the output and recorded in the calibration; a room-world set for a model without its classes is one line."""
    out = tmp_path / "cal.safetensors"
    assert main([str(home_model), "--test-set", "any-camera", "--assets", str(tiny_pack), "--samples", "2",
                 "--offsets", "0.5", "--no-novel", "--batch", "2", "--out", str(out)]) == 0
    assert "test set any-camera split train" in capsys.readouterr().out
    assert read_model_file(out).training["calibration"]["data"] == "stream:seed=0,test-set=any-camera"
    assert main(["ssz64", "--test-set", "any-camera", "--out", str(tmp_path / "no.safetensors")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "ceiling, object" in err[0] and not (tmp_path / "no.safetensors").exists()

"""``fruxel-eval --by-camera`` (issue 39's chart): mIoU and own-view accuracy per bin of camera height and pitch in
report.json, report.md and by_camera.png; a model that reads the camera evaluated under several ``--camera-known``
settings on the same samples, a curve each; bad values give one error line naming the option."""

from __future__ import annotations

import dataclasses
import json
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from fruxel.cli import eval as eval_cli

from .conftest import SMALL_GRID, small_model_config, widened_generator
from .test_eval import BATCH
from .test_predict import error_line

torch = pytest.importorskip("torch")

from fruxel.train.eval.by_camera import HEIGHT_EDGES, PITCH_EDGES, bin_index  # noqa: E402


@pytest.fixture(scope="module")
def camera_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small architecture reading the camera, with the furnished rooms' classes, as a shipped file."""
    from fruxel.classes import HOME_CLASSES
    from fruxel.train.model_files import save_model

    config = dataclasses.replace(small_model_config(HOME_CLASSES), camera_inputs=True)
    path = tmp_path_factory.mktemp("cam") / "cam.safetensors"
    save_model(path, widened_generator(config), config, half=False)
    return path


def evaluate(model: Path, out: Path, *extra: str) -> dict[str, Any]:
    argv = ["--checkpoint", str(model), "--batch", str(BATCH), "--prior-samples", "0", "--examples", "0",
            "--device", "cpu", "--out", str(out), "-q", *extra]
    assert eval_cli.main(argv) == 0
    return json.loads((out / "report.json").read_text())


def check_chart(path: Path) -> None:
    """A two-panel picture with coloured lines (not a blank or grey-only image)."""
    img = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert img.shape[1] > 1.8 * img.shape[0] > 600, img.shape
    coloured = (img.max(-1) - img.min(-1)) > 80
    left, right = coloured[:, : img.shape[1] // 2], coloured[:, img.shape[1] // 2:]
    assert left.sum() > 40 and right.sum() > 40, "a panel has no coloured line or marker"


@pytest.fixture(scope="module")
def any_camera_data(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data set of 8 test samples of the flat world, each from a random camera (a room each)."""
    from fruxel.train.sim.cameras import ANY_CAMERA
    from fruxel.train.sim.config import ImageConfig, SimConfig
    from fruxel.train.sim.writer import generate

    out = tmp_path_factory.mktemp("data") / "any"
    config = SimConfig(grid=SMALL_GRID, image=ImageConfig(size=64), samples_per_scene=1, shard_size=4,
                       splits=(("test", 8),), camera=ANY_CAMERA)
    generate(str(out), config, 3, progress=False)
    return out


def test_samples_are_binned_by_their_recorded_camera(shipped_model: Path, any_camera_data: Path,
                                                     tmp_path: Path) -> None:
    """Samples of random cameras spread over the bins: each bin holds the samples whose recorded height (pitch)
    lies in it, the bins' confusion matrices add up to the report's, and report.md and the chart show them."""
    from fruxel.train.sim.dataset import ShardDataset

    out = tmp_path / "report"
    report = evaluate(shipped_model, out, "--data", str(any_camera_data), "--by-camera")
    tests = [ShardDataset(str(any_camera_data), "test").sample(i) for i in range(8)]
    section = report["by_camera"]
    assert section["chart"] == "by_camera.png"
    assert sorted(p.name for p in out.iterdir()) == ["by_camera.png", "report.json", "report.md"]
    whole = np.array(report["results"]["model"]["confusion"])
    for axis, edges in (("height", HEIGHT_EDGES), ("pitch", PITCH_EDGES)):
        part = section[axis]
        assert part["edges"] == list(edges) and list(part["miou"]) == ["model"]
        idx = bin_index([float(s.camera_arrays()[axis]) for s in tests], edges)
        assert (idx >= 0).all() and (idx < len(edges) - 1).all()  # the test set's cameras lie inside the bins
        assert len(set(idx.tolist())) >= 3, f"the random cameras should spread over the {axis} bins"
        assert part["samples"] == np.bincount(idx, minlength=len(edges) - 1).tolist()
        assert part["outside"] == {"below": 0, "above": 0, "unrecorded": 0}
        assert np.sum(part["confusion"]["model"], axis=0).tolist() == whole.tolist()
        assert sum(part["own_hits"]["model"]) == report["results"]["model"]["counts"]["own_hits"]
        full = [i for i, n in enumerate(part["samples"]) if n]
        assert all(part["miou"]["model"][i] is not None for i in full)
        assert all(part["miou"]["model"][i] is None for i in range(len(edges) - 1) if i not in full)
    md = (out / "report.md").read_text()
    assert "## By camera" in md and "![by camera](by_camera.png)" in md
    assert f"| 0.3..0.5 | {section['height']['samples'][0]} |" in md
    check_chart(out / "by_camera.png")


def test_a_model_of_one_mount_falls_into_one_bin_equal_to_the_whole(shipped_model: Path, tmp_path: Path,
                                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """The robot's mount (one height, one pitch): every sample in one bin, whose numbers are the report's; a model
    that reads no camera gives one curve, and its results are those of a run without --by-camera."""
    out = tmp_path / "report"
    report = evaluate(shipped_model, out, "--samples", "3", "--by-camera")
    plain = evaluate(shipped_model, tmp_path / "plain", "--samples", "3")
    assert plain["by_camera"] is None and report["results"] == plain["results"]
    assert not (tmp_path / "plain" / "by_camera.png").exists()
    model = report["results"]["model"]
    for axis in ("height", "pitch"):
        part = report["by_camera"][axis]
        assert sorted(part["samples"])[-1] == 3 and sum(part["samples"]) == 3
        b = part["samples"].index(3)
        assert part["miou"] == {"model": [model["miou"] if i == b else None for i in range(len(part["samples"]))]}
        assert part["own_view_accuracy"]["model"][b] == model["own_view_accuracy"]
        assert part["confusion"]["model"][b] == model["confusion"]
    check_chart(out / "by_camera.png")
    # Printed: the report's files, the chart among them.
    assert eval_cli.main(["--checkpoint", str(shipped_model), "--samples", "1", "--prior-samples", "0", "--examples",
                          "0", "--device", "cpu", "--out", str(tmp_path / "printed"), "--by-camera"]) == 0
    assert capsys.readouterr().out.splitlines()[1:] == [str(tmp_path / "printed" / n) for n in
                                                         ("report.md", "report.json", "by_camera.png")]


def test_pose_given_and_unknown_in_one_run(camera_model: Path, tmp_path: Path) -> None:
    """A model that reads the camera under two settings: two results and two curves on the same samples, each the
    same as a run under that setting alone."""
    out = tmp_path / "both"
    args = ("--test-set", "robot", "--samples", "2", "--by-camera")
    both = evaluate(camera_model, out, *args, "--camera-known", "gravity,height", "--camera-known", "none")
    given = evaluate(camera_model, tmp_path / "given", *args)
    unknown = evaluate(camera_model, tmp_path / "unknown", *args, "--camera-known", "none")
    assert list(both["results"]) == ["model", "model@none", "oracle"]
    assert both["data"]["camera_known"] == ["gravity", "height"] == given["data"]["camera_known"]
    assert unknown["data"]["camera_known"] == []
    assert both["results"]["model"] == given["results"]["model"]
    assert both["results"]["model@none"] == unknown["results"]["model"]
    assert both["results"]["model"]["confusion"] != both["results"]["model@none"]["confusion"], \
        "telling the pose should change the prediction"
    for axis in ("height", "pitch"):
        miou = both["by_camera"][axis]["miou"]
        assert miou == {"model": given["by_camera"][axis]["miou"]["model"],
                        "model@none": unknown["by_camera"][axis]["miou"]["model"]}
    md = (out / "report.md").read_text()
    assert "model, camera known: gravity,height" in md and "model, camera known: none" in md
    assert "mIoU, model, camera known: none" in md.split("## By camera")[1]
    check_chart(out / "by_camera.png")


@pytest.mark.parametrize("argv, words", [
    (["--camera-known", "none", "--camera-known", "none"], "--camera-known none is given twice"),
    (["--camera-known", "height"], "--camera-known"),
    (["--camera-known", "gravity,none"], "--camera-known"),
    (["--by-camera=yes"], "--by-camera"),
])
def test_bad_values_give_one_line_naming_the_option(argv: list[str], words: str, shipped_model: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    try:
        rc = eval_cli.main(["--checkpoint", str(shipped_model), "--samples", "1", "--out", str(out), *argv])
    except SystemExit as e:  # argparse's own usage errors
        rc = e.code
    assert rc == 2 and words in error_line(capsys, "fruxel-eval")
    assert not out.exists()


def test_several_settings_for_a_model_without_camera_are_refused(shipped_model: Path, tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "out"
    assert eval_cli.main(["--checkpoint", str(shipped_model), "--samples", "1", "--out", str(out), "--camera-known",
                          "gravity", "--camera-known", "none"]) == 2
    line = error_line(capsys, "fruxel-eval")
    assert "--camera-known" in line and "reads no camera" in line and str(shipped_model) in line
    assert not out.exists()


def test_help_names_the_bins_of_the_code() -> None:
    """--help writes the bins without importing torch: they must be the ones the code counts."""
    for axis, edges in (("height", HEIGHT_EDGES), ("pitch", PITCH_EDGES)):
        first, last, step, _ = eval_cli.BIN_EDGES[axis]
        assert np.allclose(edges, np.arange(first, last + step / 2, step))

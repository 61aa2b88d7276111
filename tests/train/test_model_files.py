"""Model files (fruxel.train.model_files): the shipped models are what the presets build, files of version 1 still
read (their rules moved out of the model config), and a file that used a removed setting is refused in one line."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

torch = pytest.importorskip("torch")

from fruxel.train.config import preset  # noqa: E402
from fruxel.train.legacy import REMOVED_MODEL_KEYS, RULE_KEYS  # noqa: E402
from fruxel.train.model_files import (  # noqa: E402
    LEGACY_FORMAT,
    ModelFileError,
    load_model,
    read_model_file,
    save_model,
)
from fruxel.train.models.registry import model_config_to_dict  # noqa: E402
from fruxel.train.rules import NO_RULES, InferenceRules  # noqa: E402

from .test_blocks import small_config  # noqa: E402


@pytest.mark.parametrize("name", ["ssz64", "ssz128", "ssz64-any"])
def test_the_presets_rebuild_the_shipped_models(name: str) -> None:
    """``fruxel-train --preset NAME`` trains the shipped model's architecture and image size: the same config, and
    a network whose every tensor has the shipped file's name and shape."""
    shipped = read_model_file(name)
    built = preset(name).model
    assert built == shipped.config and built.image_size == shipped.config.image_size
    state = built.build().state_dict()
    assert {k: tuple(v.shape) for k, v in state.items()} == {k: tuple(v.shape) for k, v in shipped.state.items()}


def test_the_camera_aware_preset_is_ssz64_reading_the_camera_on_the_furnished_rooms() -> None:
    """``ssz64-any`` (issue 39's training) is the shipped ssz64's architecture and image size with camera inputs,
    the furnished rooms' classes, streamed from the furnished rooms with any camera; tiny reads the camera too."""
    import dataclasses

    from fruxel.classes import HOME_CLASSES

    any_cam, ssz64 = preset("ssz64-any"), preset("ssz64")
    assert any_cam.model == dataclasses.replace(ssz64.model, camera_inputs=True, classes=HOME_CLASSES)
    assert any_cam.model.reads_camera and preset("tiny").model.reads_camera and not ssz64.model.reads_camera
    assert (any_cam.data.world, any_cam.data.camera) == ("home", "any")
    # 32 frames a room: the room's set-up shared by twice the samples (docs/experiments.md, round 3); a fifth of
    # the rooms the robot's flat world from its mount
    assert any_cam.data == dataclasses.replace(ssz64.data, world="home", camera="any", samples_per_scene=32,
                                               mix_set="robot", mix_share=0.2)


def _legacy_file(path: Path, model: dict, rules: dict) -> None:
    """A file as fruxel wrote shipped models before version 2: the rules inside the model config, the
    discriminator's channels too."""
    from safetensors.torch import save_file

    torch.manual_seed(0)
    net = small_config().build()
    meta = {"format": LEGACY_FORMAT, "version": "1", "training": json.dumps({"steps": 3}),
            "model": json.dumps({**model, **rules, "discriminator": [8]})}
    save_file({k: v.contiguous() for k, v in net.state_dict().items()}, str(path), metadata=meta)


def test_a_version_1_file_reads_with_its_rules(tmp_path: Path) -> None:
    model = {k: v for k, v in model_config_to_dict(small_config()).items() if k != "architecture"}
    old = {"surface_fusion": True, "lift": "depth", "fine_depth": 0, "group_width": 1}  # the values every net has
    rules = InferenceRules(flip_average=True, empty_offset=0.5, fill_columns=True, fill_threshold=0.9,
                           first_hit_label=True)
    path = tmp_path / "old.safetensors"
    _legacy_file(path, {**model, **old}, rules.to_dict())
    loaded = load_model(path)
    assert loaded.config == small_config() and loaded.rules == rules and loaded.training == {"steps": 3}
    # Written again, it is a version 2 file with the same weights, config and rules.
    save_model(tmp_path / "new.safetensors", loaded.network, loaded.config, loaded.rules, loaded.training, half=False)
    again = read_model_file(tmp_path / "new.safetensors")
    assert (again.config, again.rules) == (loaded.config, loaded.rules)
    assert all(torch.equal(again.state[k], v) for k, v in read_model_file(path).state.items())
    assert set(RULE_KEYS) == set(rules.to_dict())


@pytest.mark.parametrize(("key", "value"), [("fine_depth", 8), ("lift", "copy"), ("surface_fusion", False),
                                            ("group_width", 16), ("refine_scale", 1)])
def test_a_version_1_file_that_used_a_removed_setting_is_refused(tmp_path: Path, key: str, value: object) -> None:
    assert key in REMOVED_MODEL_KEYS
    model = {k: v for k, v in model_config_to_dict(small_config()).items() if k != "architecture"}
    path = tmp_path / "lever.safetensors"
    _legacy_file(path, {**model, key: value}, {})
    with pytest.raises(ModelFileError, match=rf"^{path}: bad model metadata: .*model\.{key} = .* was removed"):
        read_model_file(path)


def test_a_file_without_rules_has_none(tmp_path: Path) -> None:
    cfg = small_config()
    path = tmp_path / "plain.safetensors"
    save_model(path, cfg.build(), cfg)
    f = read_model_file(path)
    assert f.rules == NO_RULES and f.config == cfg
    assert load_model(path).half and not load_model(path).network.training

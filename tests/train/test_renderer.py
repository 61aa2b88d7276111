"""The simulator's renderer seam: the protocol, the registry, a config naming its renderer, and a second renderer
added by writing one class and registering it."""

from __future__ import annotations

import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fruxel.grid import FruxelGrid
from fruxel.kernels import first_hit
from fruxel.kernels.fruxelize import fruxelize
from fruxel.train.sim.config import ConfigError, ImageConfig, SimConfig
from fruxel.train.sim.images import SceneRenderer
from fruxel.train.sim.manifest import MANIFEST
from fruxel.train.sim.renderer import (
    DEFAULT_RENDERER,
    RENDERERS,
    Renderer,
    make_renderer,
    register_renderer,
    renderer_factory,
    renderer_names,
)
from fruxel.train.sim.sample import SampleMaker
from fruxel.train.sim.shards import DatasetError, ShardReader, shard_specs
from fruxel.train.sim.writer import generate

GRID = FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0)
SEED = 3


class LabelRenderer:
    """A second renderer: every pixel in the class colour of the first solid on its ray (class 0's colour where
    there is none), found by ``fruxelize`` on a grid with one column per pixel and ``first_hit`` down the columns.
    No lighting and no augmentation: the generator's ``rng`` is not used."""

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        g = config.grid
        self.grid = FruxelGrid(width=config.image_width, height=config.image_height, depth=g.depth,
                               z_near=g.z_near, z_far=g.z_far, hfov=g.hfov)
        self.scene: Any = None
        self.meshes: Any = None

    def set_scene(self, scene: Any) -> None:
        if scene is not self.scene:
            self.scene, self.meshes = scene, scene.mesh_set()

    def render(self, pose: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        if self.meshes is None:
            raise RuntimeError("LabelRenderer.render() needs a room: call set_scene() first")
        labels = fruxelize(self.meshes, self.grid, pose)
        return self.config.classes.colour_of(np.asarray(first_hit(labels, self.grid, self.grid.camera()).label))

    def close(self) -> None:
        self.scene = self.meshes = None


@pytest.fixture
def labels_renderer() -> Iterator[str]:
    """``LabelRenderer`` registered as ``"labels"`` for one test."""
    register_renderer("labels", LabelRenderer)
    yield "labels"
    RENDERERS.pop("labels")


def _config(renderer: str = DEFAULT_RENDERER) -> SimConfig:
    return SimConfig(grid=GRID, image=ImageConfig(size=16), samples_per_scene=2, shard_size=2,
                     splits=(("train", 4), ("test", 2)), renderer=renderer)


def test_a_second_renderer_is_one_class_and_one_registration(labels_renderer: str) -> None:
    """The samples of a config naming the label renderer have its images, and the same labels and poses as with
    the default renderer: the renderer decides the image and nothing else."""
    assert labels_renderer in renderer_names() and DEFAULT_RENDERER in renderer_names()
    config = _config(labels_renderer)
    assert isinstance(make_renderer(config), LabelRenderer)
    assert isinstance(LabelRenderer(config), Renderer)
    with SampleMaker(config, SEED) as maker:
        drawn = [maker.make("train", i) for i in range(4)]
    with SampleMaker(_config(), SEED) as maker:
        lit = [maker.make("train", i) for i in range(4)]
    for s, t in zip(drawn, lit, strict=True):
        # With S = W the image's own grid is the sample's grid: the image is the own-view truth in class colours.
        own = np.asarray(first_hit(s.labels, GRID, GRID.camera()).label)
        assert len(np.unique(own)) >= 3
        np.testing.assert_array_equal(s.image, config.classes.colour_of(own))
        assert s.labels.tobytes() == t.labels.tobytes() and s.pose.tobytes() == t.pose.tobytes()
        assert s.image.shape == t.image.shape and s.image.tobytes() != t.image.tobytes()


def test_a_data_set_records_its_renderer(labels_renderer: str, tmp_path: Path) -> None:
    """Spawned generator workers make the registered renderer's images; the manifest names the renderer, and a
    folder made with one renderer refuses another."""
    out = tmp_path / "labels"
    config = _config(labels_renderer)
    generate(str(out), config, SEED, workers=2, progress=False)
    recorded = json.loads((out / MANIFEST).read_text())["config"]
    assert recorded["renderer"] == labels_renderer and SimConfig.from_dict(recorded) == config
    for spec in shard_specs(config):
        with ShardReader(str(out / spec.file), spec, config, SEED) as reader:
            for s in reader.samples():
                own = np.asarray(first_hit(s.labels, GRID, GRID.camera()).label)
                np.testing.assert_array_equal(s.image, config.classes.colour_of(own))
    with pytest.raises(DatasetError, match="differs in: renderer"):
        generate(str(out), _config(), SEED, progress=False)


def test_the_default_renderer_keeps_configs_and_digests_of_data_sets_made_before() -> None:
    """A config of the default renderer serialises as before renderers had names (no key, so the same digest in
    manifests and shards), and a recorded config without the key reads as the default."""
    config = _config()
    d = config.to_dict()
    assert "renderer" not in d and config.renderer == DEFAULT_RENDERER == "pyrender"
    assert SimConfig.from_dict(d) == config
    assert isinstance(make_renderer(config), SceneRenderer) and isinstance(SceneRenderer(config), Renderer)


class DeviceRenderer(LabelRenderer):
    """The label renderer with a ``device`` argument, which it records in :attr:`made_on`."""

    made_on: list[str | None] = []

    def __init__(self, config: SimConfig, device: str | None = None) -> None:
        super().__init__(config)
        self.device = device
        DeviceRenderer.made_on.append(device)


def test_a_renderer_taking_a_device_gets_the_sample_makers(labels_renderer: str) -> None:
    """A factory with a ``device`` argument is handed the device its process computes on (each training rank's
    data workers draw on their own GPU), and one without it is made from the config alone."""
    register_renderer("device-labels", DeviceRenderer)
    try:
        config = _config("device-labels")
        assert make_renderer(config, "cpu").device == "cpu"
        assert make_renderer(config).device is None
        assert isinstance(make_renderer(_config(labels_renderer), "cpu"), LabelRenderer)
        DeviceRenderer.made_on.clear()
        with SampleMaker(config, SEED, device="cpu") as maker:
            maker.make("train", 0)
        assert DeviceRenderer.made_on == ["cpu"]
    finally:
        RENDERERS.pop("device-labels")


def test_registry_errors(labels_renderer: str) -> None:
    named = _config(labels_renderer)
    assert named.digest() != _config().digest()
    with pytest.raises(ConfigError,
                       match=r"unknown renderer 'nope'; renderers are \['labels', 'pyrender', 'raytrace'\]"):
        _config("nope")
    with pytest.raises(ConfigError, match="unknown renderer 'nope'"):
        SimConfig.from_dict({**named.to_dict(), "renderer": "nope"})
    with pytest.raises(ConfigError, match="registered already"):
        register_renderer("pyrender", LabelRenderer)
    with pytest.raises(ConfigError, match="renderer name"):
        register_renderer("Flat Colours", LabelRenderer)
    with pytest.raises(ConfigError, match="callable or a 'module:attribute' path"):
        register_renderer("broken", 42)  # type: ignore[arg-type]
    register_renderer("missing", "fruxel.train.sim.no_such_module:Renderer")
    try:
        with pytest.raises(ConfigError, match="renderer 'missing' .* cannot be imported"):
            renderer_factory("missing")
    finally:
        RENDERERS.pop("missing")
    assert renderer_factory(DEFAULT_RENDERER) is SceneRenderer

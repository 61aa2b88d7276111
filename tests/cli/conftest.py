"""Fixtures of the command tests: a small SSZ model in both file forms (shipped safetensors, training checkpoint)."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from fruxel.grid import FruxelGrid

SMALL_GRID = FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0)
"""The grid of the test model: 16^3 cells, from 64 x 64 images."""


def small_model_config(classes: Any = None) -> Any:
    """A :class:`fruxel.train.models.ssz.SSZConfig`: a 16^3-from-64^2 SSZ architecture with a few thousand weights
    (a forward pass takes milliseconds), of ``classes`` (default :data:`fruxel.classes.DEFAULT_CLASSES`)."""
    from fruxel.classes import DEFAULT_CLASSES
    from fruxel.train.models.ssz import SSZConfig

    return SSZConfig(grid=SMALL_GRID, classes=classes or DEFAULT_CLASSES, image_scale=2, levels=3, stem=4,
                     encoder=(8, 8, 8), encoder_blocks=(1, 1, 1), encoder_expand=2, topdown=(8, 8, 8),
                     decoder=(4, 4, 4), decoder_blocks=(1, 1, 1))


def widened_generator(config: Any) -> Any:
    """A generator of ``config``, freshly initialised, with a widened output layer so that its argmax holds several
    classes (a fresh model predicts almost only empty cells)."""
    torch = pytest.importorskip("torch")
    torch.manual_seed(0)
    gen = config.build().eval()
    torch.manual_seed(0)  # the head's draw does not depend on how many weights came before it
    with torch.no_grad():
        gen.head.weight.normal_(0.0, 8.0)
        gen.head.bias.zero_()
        gen.head.bias[0] = 6.0
    return gen


@pytest.fixture(scope="session")
def small_generator() -> Any:
    """``(generator, config)``: :func:`widened_generator` of :func:`small_model_config`."""
    config = small_model_config()
    return widened_generator(config), config


@pytest.fixture(scope="session")
def shipped_model(small_generator: Any, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small model as a shipped file (float32 weights, so that it predicts exactly as the checkpoint form)."""
    from fruxel.train.model_files import save_model

    gen, config = small_generator
    path = tmp_path_factory.mktemp("models") / "small.safetensors"
    save_model(path, gen, config, training={"step": 0, "note": "fresh"}, half=False)
    return path


@pytest.fixture(scope="session")
def home_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small architecture with the furnished rooms' classes (:data:`fruxel.classes.HOME_CLASSES`) as a shipped
    file: :func:`widened_generator`, float32."""
    from fruxel.classes import HOME_CLASSES
    from fruxel.train.model_files import save_model

    config = small_model_config(HOME_CLASSES)
    path = tmp_path_factory.mktemp("models") / "home.safetensors"
    save_model(path, widened_generator(config), config, training={"step": 0, "note": "fresh"}, half=False)
    return path


@pytest.fixture(scope="session")
def checkpoint_model(small_generator: Any, tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The small model as a training checkpoint (``.pt``, written by the engine's own writer)."""
    from fruxel.train.config import DataConfig, TrainConfig
    from fruxel.train.engine.checkpoint import save_checkpoint

    gen, config = small_generator
    path = tmp_path_factory.mktemp("models") / "small.pt"
    save_checkpoint(path, {"step": 0, "samples": 0, "generator": gen.state_dict()},
                    TrainConfig(name="small", model=config, data=DataConfig(world="flat")))
    return path


@pytest.fixture(autouse=True)
def cache_folder(tmp_path_factory: pytest.TempPathFactory, monkeypatch: pytest.MonkeyPatch) -> Path:
    """A cache folder of each test's own (``FRUXEL_CACHE_DIR``): no test reads what another cached, and nothing is
    written into the user's ~/.cache."""
    folder = tmp_path_factory.mktemp("cache")
    monkeypatch.setenv("FRUXEL_CACHE_DIR", str(folder))
    return folder

"""The experiment configs kept in configs/ stay valid as the config schema evolves."""

from __future__ import annotations

from pathlib import Path

import pytest

from fruxel.train.config import TrainConfig

CONFIGS = sorted((Path(__file__).parents[2] / "configs").rglob("*.json"))


def test_there_are_configs() -> None:
    assert len(CONFIGS) >= 6


@pytest.mark.parametrize("path", CONFIGS, ids=lambda p: str(p.relative_to(p.parents[1])))
def test_config_file_reads(path: Path) -> None:
    config = TrainConfig.from_json(path.read_text())
    assert path.stem in config.name  # the run folder names say which file made them

"""Fixtures shared by the simulator's tests."""

from __future__ import annotations

from pathlib import Path

import pytest

ASSETPACK_SOURCES = Path(__file__).resolve().parents[1] / "data" / "assetpack_sources"
"""The tiny, committed asset-pack sources (tests/data/assetpack_sources)."""


@pytest.fixture(scope="session")
def tiny_pack(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny asset pack the real builder makes from :data:`ASSETPACK_SOURCES` (no network), once per session."""
    from fruxel.train.sim.assetpack.build import build_pack

    out = tmp_path_factory.mktemp("pack") / "pack"
    build_pack(ASSETPACK_SOURCES, out)
    return out

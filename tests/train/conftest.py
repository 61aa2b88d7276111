"""Fixtures shared by the tests of fruxel.train: the tiny asset pack built from the committed sources."""

from __future__ import annotations

from pathlib import Path

import pytest

ASSETPACK_SOURCES = Path(__file__).resolve().parents[1] / "data" / "assetpack_sources"
"""The tiny committed sources of the asset pack (scripts/make_assetpack_fixture.py)."""


@pytest.fixture(scope="session")
def tiny_pack(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny asset pack, built once per session by the real builder from :data:`ASSETPACK_SOURCES` (no network);
    tests that change it work on a copy."""
    from fruxel.train.sim.assetpack.build import build_pack

    out = tmp_path_factory.mktemp("pack") / "pack"
    build_pack(ASSETPACK_SOURCES, out)
    return out


@pytest.fixture(scope="session")
def pack_dir(tiny_pack: Path) -> Path:
    """:func:`tiny_pack` (the name the renderer's and the pack's tests use)."""
    return tiny_pack

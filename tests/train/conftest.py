"""Fixtures shared by the tests of fruxel.train: the tiny asset pack (``tiny_pack``, tests/conftest.py) under the
name the renderer's and the pack's tests use."""

from __future__ import annotations

from pathlib import Path

import pytest


@pytest.fixture(scope="session")
def pack_dir(tiny_pack: Path) -> Path:
    """The tiny asset pack (the name the renderer's and the pack's tests use)."""
    return tiny_pack

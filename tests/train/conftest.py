"""Fixtures and helpers shared by the tests of fruxel.train: the tiny asset pack (``tiny_pack``, tests/conftest.py)
under the name the renderer's and the pack's tests use, and :func:`load_script` for the tests of scripts/."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import pytest

SCRIPTS = Path(__file__).resolve().parents[2] / "scripts"


def load_script(name: str) -> ModuleType:
    """``scripts/NAME.py`` as a module (the scripts are no package), registered in ``sys.modules`` as NAME so that
    its dataclasses and the scripts that import it find it."""
    spec = importlib.util.spec_from_file_location(name, SCRIPTS / f"{name}.py")
    module = importlib.util.module_from_spec(spec)
    sys.modules[name] = module
    spec.loader.exec_module(module)
    return module


@pytest.fixture(scope="session")
def pack_dir(tiny_pack: Path) -> Path:
    """The tiny asset pack (the name the renderer's and the pack's tests use)."""
    return tiny_pack

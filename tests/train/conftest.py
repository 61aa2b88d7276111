"""Fixtures and helpers shared by the tests of fruxel.train: the tiny asset pack (``tiny_pack``, tests/conftest.py)
under the name the renderer's and the pack's tests use, and :func:`load_script` for the tests of scripts/."""

from __future__ import annotations

import importlib.util
import sys
from pathlib import Path
from types import ModuleType

import numpy as np
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


def slab_volumes(seed: int, depth: int, first: tuple[int, int], thick: int) -> tuple[np.ndarray, np.random.Generator]:
    """``(2, depth, 5, 6)`` uint8 label volumes with one slab of class 1-3, ``thick`` slices, in each column,
    starting at a slice drawn from ``[first[0], first[1])``; and the generator, for more draws of the same test."""
    rng = np.random.default_rng(seed)
    truth = np.zeros((2, depth, 5, 6), dtype=np.uint8)
    for b in range(2):
        for j in range(5):
            for i in range(6):
                k = rng.integers(*first)
                truth[b, k:k + thick, j, i] = rng.integers(1, 4)
    return truth, rng

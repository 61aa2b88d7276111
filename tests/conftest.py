"""Session-wide test settings (headless OpenGL and quiet Warp, set before any test imports pyrender or warp) and
fixtures shared by the test folders (the tiny asset pack, torch on one thread)."""

import os
from collections.abc import Iterator
from pathlib import Path

import pytest

# pyrender picks its OpenGL platform at import time; tests never have a display.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("PYGLET_HEADLESS", "true")

ASSETPACK_SOURCES = Path(__file__).resolve().parent / "data" / "assetpack_sources"
"""The tiny committed sources of the asset pack (scripts/make_assetpack_fixture.py)."""


@pytest.fixture(scope="session", autouse=True)
def session_cache_folder(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Path]:
    """fruxel's cache folder (``FRUXEL_CACHE_DIR``: the decoded textures of :mod:`fruxel.train.sim.assetpack.derived`,
    priors) in the session's temporary folder, so that tests never read or fill the user's ``~/.cache``; spawned
    workers inherit it."""
    folder = tmp_path_factory.mktemp("fruxel-cache")
    old = os.environ.get("FRUXEL_CACHE_DIR")
    os.environ["FRUXEL_CACHE_DIR"] = str(folder)
    yield folder
    if old is None:
        os.environ.pop("FRUXEL_CACHE_DIR", None)
    else:
        os.environ["FRUXEL_CACHE_DIR"] = old


@pytest.fixture
def torch_one_thread() -> Iterator[None]:
    """Run torch on one thread for the test: on two cores shared with other processes, torch's two OpenMP threads
    waited for each other up to 50 times longer than one thread took for a whole training step of a tiny SSZ."""
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)


@pytest.fixture(scope="session")
def tiny_pack(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The tiny asset pack, built once per session by the real builder from :data:`ASSETPACK_SOURCES` (no network);
    tests that change it work on a copy."""
    from fruxel.train.sim.assetpack.build import build_pack

    out = tmp_path_factory.mktemp("pack") / "pack"
    build_pack(ASSETPACK_SOURCES, out)
    return out

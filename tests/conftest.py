"""Session-wide test settings (headless OpenGL and quiet Warp, set before any test imports pyrender or warp) and
fixtures shared by the test folders."""

import os
from collections.abc import Iterator

import pytest

# pyrender picks its OpenGL platform at import time; tests never have a display.
os.environ.setdefault("PYOPENGL_PLATFORM", "egl")
os.environ.setdefault("PYGLET_HEADLESS", "true")


@pytest.fixture
def torch_one_thread() -> Iterator[None]:
    """Run torch on one thread for the test: on two cores shared with other processes, torch's two OpenMP threads
    waited for each other up to 50 times longer than one thread took for a whole training step of a tiny SSZ."""
    torch = pytest.importorskip("torch")
    threads = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(threads)

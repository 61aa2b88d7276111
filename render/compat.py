"""Small compatibility shims for third-party packages: pyrender, applied before it is imported, and the text font.

pyrender 0.1.45 (the last release) refers to ``np.infty``, which NumPy 2 removed, and picks its OpenGL platform
from ``PYOPENGL_PLATFORM`` at import time. Every import of pyrender in fruxel goes through :func:`import_pyrender`
(the renderer, the simulator's camera images), so importing a fruxel module never loads pyrender by itself.
"""

from __future__ import annotations

import functools
import importlib.util
import os
from typing import Any

import numpy as np


def prepare_pyrender(headless: bool | None = None) -> None:
    """Make ``import pyrender`` work with NumPy 2 and choose the OpenGL platform.

    Args:
        headless: True selects EGL (offscreen, no display needed: Mesa here, NVIDIA on GPU machines); False keeps
            the default window platform; None (default) selects EGL when no ``DISPLAY`` is set. A
            ``PYOPENGL_PLATFORM`` the user set is always kept.
    """
    if not hasattr(np, "infty"):
        # Same value NumPy 1 had under this name; pyrender only reads it.
        setattr(np, "infty", np.inf)  # noqa: B010 - a plain assignment trips the NumPy 2 lint
    if headless is None:
        headless = not os.environ.get("DISPLAY")
    if headless:
        os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def import_pyrender(headless: bool = True) -> Any:
    """``pyrender``, imported after the NumPy 2 / EGL shim (:func:`prepare_pyrender`).

    Args:
        headless: select EGL unless the user set ``PYOPENGL_PLATFORM``; False for the interactive Viewer.
    """
    prepare_pyrender(headless=headless)
    import pyrender

    return pyrender


@functools.cache
def _dejavu() -> str | None:
    """The path of DejaVu Sans as matplotlib ships it (found without importing matplotlib), or None."""
    spec = importlib.util.find_spec("matplotlib")
    for folder in (spec.submodule_search_locations or []) if spec is not None else []:
        path = os.path.join(folder, "mpl-data", "fonts", "ttf", "DejaVuSans.ttf")
        if os.path.isfile(path):
            return path
    return None


def default_font(size: int) -> Any:
    """The font of every caption and legend fruxel draws: DejaVu Sans at ``size`` pixels.

    DejaVu ships with matplotlib (a dependency of the ``render`` and ``train`` extras). Pillow's own default font
    (the fallback where matplotlib is missing) gives a space two pixels at caption sizes, so that "1232
    triangles" reads as "1232triangles".
    """
    from PIL import ImageFont

    path = _dejavu()
    if path is not None:
        return ImageFont.truetype(path, size)
    try:
        return ImageFont.load_default(size=size)
    except TypeError:
        return ImageFont.load_default()

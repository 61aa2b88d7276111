"""fruxel.render: show fruxel models, as trapezoid meshes in pyrender or as ray-cast images.

* :mod:`fruxel.render.scene` — pyrender scenes: the OpenCV-to-pyrender camera conversion, mesh upload,
  offscreen (EGL) renderers kept per image size.
* :mod:`fruxel.render.raycast` — ``first_hit`` from the viewing camera, shaded per pixel (no mesh).
* :mod:`fruxel.render.shading` — the one shading formula of ray casts and lit meshes.
* :mod:`fruxel.render.legend` — class legends and captions on images.
* :mod:`fruxel.render.frames` — what ``fruxel-render`` draws: options, default and orbit views, and the frame
  renderer that turns a model and a camera into an image.
* :mod:`fruxel.render.images` — image and video files (PNG, JPEG, GIF, MP4), written atomically.
* :mod:`fruxel.render.markdown` — one section of a Markdown report rewritten.
* :mod:`fruxel.render.table1` — the visualisation benchmark (Table 1 of the paper, per-frame model updates).

Importing this package imports neither pyrender nor torch nor a kernel backend; each is loaded when first used.
"""

from __future__ import annotations

import importlib
from typing import Any

from fruxel.errors import FruxelError

__all__ = ["MeshStyle", "MeshView", "RaycastStyle", "RenderError", "raycast_image", "render_mesh"]


class RenderError(FruxelError, ValueError):
    """Raised for a display request that cannot be met: an image too large for the renderer, an output format
    whose writer is missing, no display for the interactive viewer."""


_LAZY = {
    "MeshStyle": ".scene",
    "MeshView": ".scene",
    "render_mesh": ".scene",
    "RaycastStyle": ".shading",
    "raycast_image": ".raycast",
}


def __getattr__(name: str) -> Any:
    if name in _LAZY:
        return getattr(importlib.import_module(_LAZY[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")

"""Shading of ray-cast hits into an image: class colour, Lambert term from the entry-face normal, depth fog.

Numpy only, so both the renderer and the simulator's previews use it. Inputs are the fields of
``fruxel.kernels.Hits`` for one image, as numpy arrays.
"""

from __future__ import annotations

from typing import Any

import numpy as np

DEFAULT_BACKGROUND = (255, 255, 255)
"""RGB of pixels whose ray missed."""
DEFAULT_LIGHT = (-0.4, -0.7, -0.6)
"""Direction towards the light (OpenCV axes: above-left-behind the viewer when given in the camera frame)."""
DEFAULT_AMBIENT = 0.35
"""Share of a colour lit regardless of orientation."""


def shade_hits(
    label: Any,
    normal: Any,
    depth: Any,
    palette: Any,
    camera_rotation: Any | None = None,
    *,
    light: Any = DEFAULT_LIGHT,
    ambient: float = DEFAULT_AMBIENT,
    fog: tuple[float, float] | None = None,
    background: tuple[int, int, int] = DEFAULT_BACKGROUND,
) -> np.ndarray:
    """Shade one ray-cast image.

    Args:
        label: ``(h, w)`` integer class labels, 0 = miss.
        normal: ``(h, w, 3)`` float unit entry-face normals, grid frame, facing the camera.
        depth: ``(h, w)`` float depth of the hit in the viewing camera, metres.
        palette: ``(C, 3)`` uint8 class colours; labels index it.
        camera_rotation: ``(3, 3)`` camera-to-grid rotation. When given, ``light`` is a direction in the camera
            frame (a head light that follows the viewer); when None, ``light`` is in the grid frame.
        light: ``(3,)`` direction *towards* the light (normalised here), in the frame given above. The default
            comes from above-left-behind the viewer (OpenCV axes: -y is up, -z is towards the viewer).
        ambient: share of the colour that is lit regardless of orientation, in [0, 1].
        fog: ``(near, far)`` metres: colours blend linearly into the background from ``near`` to ``far``; None
            for no fog.
        background: RGB of missed pixels and of full fog.

    Returns:
        ``(h, w, 3)`` uint8 RGB image.

    Raises:
        ValueError: mismatched shapes, a label outside the palette, or ambient outside [0, 1].
    """
    label = np.asarray(label)
    normal = np.asarray(normal, dtype=np.float64)
    depth = np.asarray(depth, dtype=np.float64)
    pal = np.asarray(palette, dtype=np.uint8)
    if label.ndim != 2 or normal.shape != label.shape + (3,) or depth.shape != label.shape:
        raise ValueError(f"expected label (h, w), normal (h, w, 3), depth (h, w); got {label.shape}, "
                         f"{normal.shape}, {depth.shape}")
    if pal.ndim != 2 or pal.shape[1] != 3:
        raise ValueError(f"palette must be (C, 3), got {pal.shape}")
    if label.size and (label.min() < 0 or label.max() >= len(pal)):
        raise ValueError(f"labels must lie in [0, {len(pal)}), got [{label.min()}, {label.max()}]")
    if not 0.0 <= ambient <= 1.0:
        raise ValueError(f"ambient must be in [0, 1], got {ambient}")
    ldir = np.asarray(light, dtype=np.float64).reshape(3)
    if camera_rotation is not None:
        ldir = np.asarray(camera_rotation, dtype=np.float64) @ ldir
    ldir = ldir / max(np.linalg.norm(ldir), 1e-12)
    lambert = np.clip(normal @ ldir, 0.0, 1.0)
    intensity = ambient + (1.0 - ambient) * lambert
    colour = pal[label].astype(np.float64) * intensity[..., None]
    bg = np.asarray(background, dtype=np.float64)
    if fog is not None:
        near, far = fog
        f = np.clip((depth - near) / max(far - near, 1e-12), 0.0, 1.0)[..., None]
        colour = colour * (1.0 - f) + bg * f
    hit = label != 0
    out = np.where(hit[..., None], colour, bg)
    return np.clip(np.rint(out), 0, 255).astype(np.uint8)

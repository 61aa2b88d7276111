"""Ray-cast images of fruxel volumes: ``first_hit`` from the viewing camera, then shading per pixel.

No mesh is built, so a volume that changes every frame (a network's live output) costs one kernel launch and
one shading pass per image. The volume may be labels ``(D, H, W)`` or logits ``(1, C, D, H, W)``, numpy or
torch, on the CPU or CUDA; the kernel reads it where it is (no argmax on the host first).

Shading is :func:`fruxel.render.shading.shade`: class colour times ``ambient + (1 - ambient) * max(0, n . l)``
with ``n`` the entry-face normal and ``l`` a head light given in the camera frame, then optional linear depth fog
into the background, in float32 on the hits' own device (numpy, or torch on CUDA).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from .shading import DEFAULT_STYLE, RaycastStyle, fog_range, shade, to_numpy

__all__ = ["RaycastStyle", "first_hits", "raycast_image", "shade", "to_numpy"]


def first_hits(
    volume: Any,
    grid: FruxelGrid,
    camera: Camera,
    *,
    backend: str | None = None,
    device: str | None = None,
    threshold: float | None = None,
) -> Any:
    """``fruxel.kernels.first_hit`` for one image: a :class:`fruxel.kernels.Hits` without batch axis.

    Args:
        volume: labels ``(D, H, W)`` or scores ``(1, C, D, H, W)`` (a batch of one), numpy or torch.
        grid, camera: the volume's grid and the viewing camera.
        backend, device, threshold: as for ``first_hit``.

    Returns:
        Hits with ``(h, w)`` label / cell / depth and ``(h, w, 3)`` normal, in the volume's kind of array and on
        its device.
    """
    from fruxel import kernels

    hits = kernels.first_hit(volume, grid, camera, backend=backend, device=device, threshold=threshold)
    if hits.label.ndim == 3:
        hits = type(hits)(label=hits.label[0], cell=hits.cell[0], depth=hits.depth[0], normal=hits.normal[0])
    return hits


MAX_TILE_PIXELS = 1 << 22
"""Most pixels ray cast at once; a larger image is cast in bands of rows (:func:`raycast_image`), so that the
hits of one band (about 30 bytes a pixel) bound the memory, not the image's size."""


def raycast_image(
    volume: Any,
    grid: FruxelGrid,
    camera: Camera,
    palette: Any,
    *,
    backend: str | None = None,
    device: str | None = None,
    threshold: float | None = None,
    style: RaycastStyle = DEFAULT_STYLE,
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast one image of a volume.

    An image of more than :data:`MAX_TILE_PIXELS` pixels is cast in bands of rows, each with the principal point
    moved to its place (the same rays), and shaded with the fog range of the whole image (found in a first pass
    over the bands when fog is on). Memory is then the result, 7 bytes a pixel, plus one band's hits.

    Args:
        volume: labels ``(D, H, W)`` or scores ``(1, C, D, H, W)``, numpy or torch (see :func:`first_hits`).
        grid: the volume's grid.
        camera: the viewing camera (any pose).
        palette: ``(C, 3)`` uint8 class colours.
        backend, device, threshold: as for ``fruxel.kernels.first_hit``.
        style: shading (see :class:`RaycastStyle`).

    Returns:
        image: ``(h, w, 3)`` uint8 RGB.
        labels: ``(h, w)`` int32 label of each pixel's first hit, 0 on a miss.
    """
    def cast(cam: Camera) -> Any:
        return first_hits(volume, grid, cam, backend=backend, device=device, threshold=threshold)

    if camera.width * camera.height <= MAX_TILE_PIXELS:
        hits = cast(camera)
        return shade(hits, camera, palette, style), to_numpy(hits.label).astype(np.int32, copy=False)
    rows = max(1, MAX_TILE_PIXELS // camera.width)
    bands = [Camera(camera.fx, camera.fy, camera.cx, camera.cy - y0, camera.width, min(rows, camera.height - y0),
                    camera.pose) for y0 in range(0, camera.height, rows)]
    fog = None
    if style.fog:
        near, far = np.inf, -np.inf
        for band in bands:
            hits = cast(band)
            depth = to_numpy(hits.depth)[to_numpy(hits.label) != 0]
            if depth.size:
                near, far = min(near, float(depth.min())), max(far, float(depth.max()))
        fog = fog_range(np.array([near, far]), np.array([True, True])) if near <= far else None
    image = np.empty((camera.height, camera.width, 3), dtype=np.uint8)
    labels = np.empty((camera.height, camera.width), dtype=np.int32)
    for y0, band in zip(range(0, camera.height, rows), bands, strict=True):
        hits = cast(band)
        image[y0:y0 + band.height] = shade(hits, band, palette, style, fog=fog)
        labels[y0:y0 + band.height] = to_numpy(hits.label)
    return image, labels

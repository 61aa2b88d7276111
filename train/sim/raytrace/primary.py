"""Camera rays: each pixel's samples follow their rays through glass to the first opaque surface and record its
material (:func:`trace_primary_kernel`).

Camera: the robot camera of ``SimConfig.image_camera()``, OpenCV axes, pinhole. Sample ``k`` of pixel ``(x, y)``
goes through image point ``(x + a, y + b)`` with ``(a, b)`` in ``[0, 1)^2`` from a per-pixel rotated additive
recurrence (:func:`~.surfaces.stratified`), so the samples of a pixel cover exactly the square ``[x, x + 1) x
[y, y + 1)`` that :meth:`fruxel.Camera.project` maps to it, and the image lines up with the grid.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fruxel.kernels.wp.runtime import warp

from .buffers import Buffers, RayBuffers
from .surfaces import SceneData, stratified, surface_at, trace

wp = warp()
wp.set_module_options({"enable_backward": False})

ALPHA_X = wp.constant(0.7548776662466927)
ALPHA_Y = wp.constant(0.5698402909980532)
"""The R2 sequence's steps (Roberts 2018): evenly spread sample positions within a pixel."""


@wp.kernel
def trace_primary_kernel(
    scene: SceneData,
    rot: wp.mat33,
    origin: wp.vec3,
    intrinsics: wp.vec4,
    ambient: wp.vec3,
    width: int,
    spp: int,
    seed: int,
    rays: RayBuffers,
):
    """One thread follows camera ray ``k`` of pixel ``(x, y)`` and fills entry ``(y * W + x) * spp + k`` of
    ``rays`` (:class:`~.buffers.RayBuffers`: flag, pos, normal, geometric, view, albedo, rough_metal, through,
    front, depth).

    Launch dims ``(H, W, spp)``. ``rot`` / ``origin``: camera-to-world rotation and centre (OpenCV axes, world
    frame z up, metres); ``intrinsics``: ``(fx, fy, cx, cy)`` pixels; ``ambient``: the ambient radiance (what
    glass reflects); ``seed``: the image's seed of this kernel (one random stream per pixel).
    """
    y, x, k = wp.tid()
    pixel = y * width + x
    r = wp.rand_init(seed, pixel)
    a = stratified(wp.randf(r), k, ALPHA_X)
    b = stratified(wp.randf(r), k, ALPHA_Y)
    cam = wp.vec3((float(x) + a - intrinsics[2]) / intrinsics[0], (float(y) + b - intrinsics[3]) / intrinsics[1],
                  1.0)
    d = wp.normalize(rot * cam)
    i = pixel * spp + k
    hit = trace(scene, origin, d, ambient)
    rays.through[i] = hit.through
    rays.depth[i] = hit.t
    rays.view[i] = -d
    if hit.kind == 0:
        rays.flag[i] = 0
        rays.front[i] = hit.front
        return
    s = surface_at(scene, hit, d, 1.0 / intrinsics[0])
    rays.pos[i] = hit.pos
    rays.normal[i] = s.normal
    rays.geometric[i] = s.geometric
    rays.albedo[i] = s.albedo
    rays.rough_metal[i] = wp.vec2(s.roughness, s.metallic)
    if s.emitter != 0:
        rays.flag[i] = 2
        rays.front[i] = hit.front + wp.cw_mul(hit.through, s.emitted)
    else:
        rays.flag[i] = 1
        rays.front[i] = hit.front


def trace_primary(scene: Any, buffers: Buffers, pose: np.ndarray, intrinsics: tuple[float, float, float, float],
                  ambient: np.ndarray, seed: int, device: str) -> None:
    """Launch :func:`trace_primary_kernel` for one image.

    Args:
        scene: the room's ``SceneData``.
        buffers: the image's buffers.
        pose: ``(4, 4)`` float64 camera-to-world, OpenCV axes.
        intrinsics: ``(fx, fy, cx, cy)``, pixels.
        ambient: ``(3,)`` ambient radiance.
        seed: the kernel's seed, in [0, 2^31).
        device: Warp device.
    """
    rot = wp.mat33(*np.asarray(pose[:3, :3], dtype=np.float32).ravel())
    wp.launch(trace_primary_kernel, dim=(buffers.height, buffers.width, buffers.spp), device=device,
              inputs=[scene, rot, wp.vec3(*np.asarray(pose[:3, 3], dtype=np.float32)), wp.vec4(*intrinsics),
                      wp.vec3(*np.asarray(ambient, dtype=np.float32)), buffers.width, buffers.spp, int(seed),
                      buffers.rays])

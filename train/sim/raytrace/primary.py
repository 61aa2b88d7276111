"""Camera rays: each pixel's samples follow their rays through glass to the first opaque surface and record its
material (:func:`trace_primary_kernel`); pixels on an edge get more samples (:func:`find_edges_kernel`).

Camera: the robot camera of ``SimConfig.image_camera()``, OpenCV axes, pinhole. Sample ``k`` of pixel ``(x, y)``
goes through image point ``(x + a, y + b)`` with ``(a, b)`` in ``[0, 1)^2`` from a per-pixel rotated additive
recurrence (:func:`~.surfaces.stratified`), so the samples of a pixel cover exactly the square ``[x, x + 1) x
[y, y + 1)`` that :meth:`fruxel.Camera.project` maps to it, and the image lines up with the grid.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fruxel.kernels.wp.runtime import warp

from .buffers import Buffers, PixelBuffers, RayBuffers
from .surfaces import R2_1, R2_2, SceneData, stratified, surface_at, trace

wp = warp()
wp.set_module_options({"enable_backward": False})


@wp.kernel
def trace_primary_kernel(
    scene: SceneData,
    rot: wp.mat33,
    origin: wp.vec3,
    intrinsics: wp.vec4,
    ambient: wp.vec3,
    width: int,
    slots: int,
    first: int,
    edges_only: int,
    seed: int,
    rays: RayBuffers,
    pixels: PixelBuffers,
):
    """One thread follows camera ray ``k = first + c`` of pixel ``(x, y)`` and fills entry ``(y * W + x) * S + k``
    of ``rays`` (:class:`~.buffers.RayBuffers`: flag, material, pos, normal, geometric, view, albedo, rough_metal,
    through, front, depth); with ``edges_only`` set, a pixel off the edges (``pixels.edge`` 0) gets flag -1 there.

    Launch dims ``(H, W, C)``. ``rot`` / ``origin``: camera-to-world rotation and centre (OpenCV axes, world frame
    z up, metres); ``intrinsics``: ``(fx, fy, cx, cy)`` pixels; ``ambient``: the ambient radiance (what glass
    reflects); ``slots``: S, ray slots per pixel; ``seed``: the image's seed of this kernel (one random stream per
    pixel, so sample ``k`` sits where it would with any ``first``).
    """
    y, x, c = wp.tid()
    pixel = y * width + x
    k = first + c
    i = pixel * slots + k
    if edges_only != 0 and pixels.edge[pixel] == 0:
        rays.flag[i] = -1
        rays.material[i] = -1
        return
    r = wp.rand_init(seed, pixel)
    a = stratified(wp.randf(r), k, R2_1)
    b = stratified(wp.randf(r), k, R2_2)
    cam = wp.vec3((float(x) + a - intrinsics[2]) / intrinsics[0], (float(y) + b - intrinsics[3]) / intrinsics[1],
                  1.0)
    d = wp.normalize(rot * cam)
    hit = trace(scene, origin, d, ambient)
    rays.through[i] = hit.through
    rays.depth[i] = hit.t
    rays.view[i] = -d
    rays.material[i] = hit.material
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


@wp.func
def _differ(rays: RayBuffers, i: int, j: int) -> bool:
    """Whether rays ``i`` and ``j`` found different surfaces: another kind or material, a depth more than 1 cm +
    2 % apart, or normals more than about 25 degrees apart."""
    if rays.flag[i] != rays.flag[j] or rays.material[i] != rays.material[j]:
        return True
    if rays.flag[i] == 0:
        return False
    d = rays.depth[i]
    return wp.abs(rays.depth[j] - d) > 0.01 + 0.02 * d or wp.dot(rays.normal[i], rays.normal[j]) < 0.9


@wp.kernel
def find_edges_kernel(width: int, height: int, slots: int, samples: int, rays: RayBuffers, pixels: PixelBuffers):
    """One thread decides whether pixel ``(x, y)`` is on an edge: its first ``samples`` rays, or its first ray and
    that of a 4-neighbour, found different surfaces. Writes ``pixels.edge[y * W + x]`` (int32 0/1).

    Launch dims ``(H, W)``; ``slots``: S, ray slots per pixel.
    """
    y, x = wp.tid()
    pixel = y * width + x
    i0 = pixel * slots
    edge = int(0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    for k in range(1, samples):
        if _differ(rays, i0, i0 + k):
            edge = 1
    if x > 0 and _differ(rays, i0, i0 - slots):
        edge = 1
    if x + 1 < width and _differ(rays, i0, i0 + slots):
        edge = 1
    if y > 0 and _differ(rays, i0, i0 - width * slots):
        edge = 1
    if y + 1 < height and _differ(rays, i0, i0 + width * slots):
        edge = 1
    pixels.edge[pixel] = edge


def trace_primary(scene: Any, buffers: Buffers, pose: np.ndarray, intrinsics: tuple[float, float, float, float],
                  ambient: np.ndarray, seed: int, samples: int, device: str) -> None:
    """Launch the camera rays of one image: ``samples`` per pixel, then, if ``buffers`` has more slots, the edge
    samples at the pixels :func:`find_edges_kernel` puts on an edge.

    Args:
        scene: the room's ``SceneData``.
        buffers: the image's buffers (``buffers.spp`` slots per pixel, at least ``samples``).
        pose: ``(4, 4)`` float64 camera-to-world, OpenCV axes.
        intrinsics: ``(fx, fy, cx, cy)``, pixels.
        ambient: ``(3,)`` ambient radiance.
        seed: the kernel's seed, in [0, 2^31).
        samples: camera rays of every pixel.
        device: Warp device.
    """
    rot = wp.mat33(*np.asarray(pose[:3, :3], dtype=np.float32).ravel())
    h, w, slots = buffers.height, buffers.width, buffers.spp
    common = [scene, rot, wp.vec3(*np.asarray(pose[:3, 3], dtype=np.float32)), wp.vec4(*intrinsics),
              wp.vec3(*np.asarray(ambient, dtype=np.float32)), w, slots]
    wp.launch(trace_primary_kernel, dim=(h, w, samples), device=device,
              inputs=[*common, 0, 0, int(seed), buffers.rays, buffers.pixels])
    if slots > samples:
        wp.launch(find_edges_kernel, dim=(h, w), device=device,
                  inputs=[w, h, slots, samples, buffers.rays, buffers.pixels])
        wp.launch(trace_primary_kernel, dim=(h, w, slots - samples), device=device,
                  inputs=[*common, samples, 1, int(seed), buffers.rays, buffers.pixels])

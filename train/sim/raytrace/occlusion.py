"""Ambient occlusion: how much of the room's ambient light reaches each camera ray's surface
(:func:`trace_occlusion_kernel`).

Each of ``ao_samples`` rays leaves the surface in a cosine-weighted direction about its shading normal (stratified
over the pixel's samples) and goes at most ``ao_distance``; a ray stopped after ``t`` lets ``t / ao_distance`` of
the ambient light through, so that a surface darkens its neighbour the more the closer it is (a concave corner,
the floor under a table) while an open wall keeps all of it. Glass and emitters do not stop the rays.
"""

from __future__ import annotations

from typing import Any

from fruxel.kernels.wp.runtime import warp

from .buffers import Buffers, RayBuffers
from .surfaces import SceneData, cosine_direction, open_distance, stratified

wp = warp()
wp.set_module_options({"enable_backward": False})

ALPHA_1 = wp.constant(0.7548776662466927)
ALPHA_2 = wp.constant(0.5698402909980532)
AO_OFFSET = wp.constant(5.0e-4)
"""Metres an occlusion ray starts off its surface, along the face normal."""


@wp.kernel
def trace_occlusion_kernel(scene: SceneData, width: int, spp: int, ao_samples: int, distance: float, seed: int,
                           rays: RayBuffers):
    """One thread measures the ambient occlusion of camera ray ``k`` of pixel ``(x, y)``: ``rays.ao`` (float in
    [0, 1], 1 = open) at entry ``(y * W + x) * spp + k``; 1 where the ray found no lit surface.

    Launch dims ``(H, W, spp)``. Reads ``rays`` flag, pos, normal, geometric (world frame); ``ao_samples`` rays
    of length ``distance`` metres; ``seed``: this kernel's seed (one random stream per pixel).
    """
    y, x, k = wp.tid()
    pixel = y * width + x
    i = pixel * spp + k
    if rays.flag[i] != 1 or ao_samples == 0:
        rays.ao[i] = 1.0
        return
    p = rays.pos[i]
    n = rays.normal[i]
    g = rays.geometric[i]
    r = wp.rand_init(seed, pixel)
    rot1 = wp.randf(r)
    rot2 = wp.randf(r)
    open_sum = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    for a in range(ao_samples):
        j = k * ao_samples + a
        d = cosine_direction(n, stratified(rot1, j, ALPHA_1), stratified(rot2, j, ALPHA_2))
        below = wp.dot(d, g)
        if below < 0.01:
            # A normal-mapped normal tilts the lobe below the face: mirror such directions back above it.
            d = wp.normalize(d + (0.02 - 2.0 * below) * g)
        open_sum += open_distance(scene, p + AO_OFFSET * g, d, distance) / distance
    rays.ao[i] = open_sum / float(ao_samples)


def trace_occlusion(scene: Any, buffers: Buffers, ao_samples: int, distance: float, seed: int, device: str) -> None:
    """Launch :func:`trace_occlusion_kernel` for one image (after :func:`.primary.trace_primary`)."""
    wp.launch(trace_occlusion_kernel, dim=(buffers.height, buffers.width, buffers.spp), device=device,
              inputs=[scene, buffers.width, buffers.spp, int(ao_samples), float(distance), int(seed), buffers.rays])

"""Ambient and window rays: how much of the room's ambient light reaches each camera ray's surface (ambient
occlusion), and the light it receives through the windows (:func:`trace_ambient_kernel`).

Each of ``ao_samples`` ambient rays leaves the surface in a cosine-weighted direction about its shading normal
(stratified over the pixel's samples); stopped by a surface after ``t`` (glass and emitters do not stop it), it
lets ``min(t / ao_distance, 1)`` of the ambient light through, so that a surface darkens its neighbour the more the
closer it is (a concave corner, the floor under a table) while an open wall keeps all of it.

Each of ``window_samples`` window rays goes to a random point of the glass (the windows as portals, sampled by
area); unless anything stands in between (an opaque surface, or nearer glass: each direction counts only the first
glass it meets, so the two sides of a pane count once), the radiance of the portal (the mean of what shines behind
it, the outdoor view or the sky, through the rest of the glass, measured once per room:
:func:`.ambient.measure_portals`) times ``cos cos' A / d^2`` (``A``: all the glass's area; ``d`` at least 22 cm) is
the window's irradiance. A window thus
lights the floor and walls in front of it, more the nearer, and furniture casts soft shadows away from it. (Rays
sent in random directions rarely find a window: its light came out as speckle.) Light of emitters not behind glass
(a lamp shade, an open sky) is part of the ambient light (:mod:`.ambient`).
"""

from __future__ import annotations

from typing import Any

from fruxel.kernels.wp.runtime import warp

from .buffers import Buffers, RayBuffers
from .surfaces import R2_1, R2_2, SceneData, cosine_direction, open_distance, stratified

wp = warp()
wp.set_module_options({"enable_backward": False})

AO_OFFSET = wp.constant(5.0e-4)
"""Metres an ambient ray starts off its surface, along the face normal."""


@wp.struct
class PortalPoint:
    """A point on a window (portal): which portal, where, and the window's unit normal there."""

    index: int
    point: wp.vec3
    normal: wp.vec3


@wp.func
def sample_portal(scene: SceneData, r1: float, r2: float, r3: float) -> PortalPoint:
    """A point uniformly distributed over the area of all portals, from three uniform numbers."""
    lo = int(0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    hi = scene.portals.shape[0] - 1
    while lo < hi:
        mid = (lo + hi) // 2
        if scene.portal_cdf[mid] < r1:
            lo = mid + 1
        else:
            hi = mid
    face = scene.portals[lo]
    su = wp.sqrt(r2)
    out = PortalPoint()
    out.index = lo
    out.point = wp.mesh_eval_position(scene.mesh, face, 1.0 - su, r3 * su)
    out.normal = wp.mesh_eval_face_normal(scene.mesh, face)
    return out


@wp.kernel
def trace_ambient_kernel(scene: SceneData, width: int, spp: int, ao_samples: int, window_samples: int,
                         distance: float, seed: int, rays: RayBuffers):
    """One thread sends the ambient and window rays of camera ray ``k`` of pixel ``(x, y)`` (entry ``(y * W + x) *
    spp + k``): ``rays.ao`` (float in [0, 1], 1 = open) and ``rays.sky`` (vec3, irradiance through the windows); 1
    and 0 where the ray found no lit surface.

    Launch dims ``(H, W, spp)``. Reads ``rays`` flag, pos, normal, geometric (world frame) and the scene's portals;
    ``ao_samples`` ambient rays of ``distance`` metres; ``window_samples`` rays to random points of the windows;
    ``seed``: this kernel's seed (one random stream per pixel).
    """
    y, x, k = wp.tid()
    pixel = y * width + x
    i = pixel * spp + k
    rays.sky[i] = wp.vec3(0.0, 0.0, 0.0)
    rays.ao[i] = 1.0
    if rays.flag[i] != 1:
        return
    p = rays.pos[i]
    n = rays.normal[i]
    g = rays.geometric[i]
    start = p + AO_OFFSET * g
    r = wp.rand_init(seed, pixel)
    rot1 = wp.randf(r)
    rot2 = wp.randf(r)
    if ao_samples > 0:
        open_sum = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
        for a in range(ao_samples):
            j = k * ao_samples + a
            d = cosine_direction(n, stratified(rot1, j, R2_1), stratified(rot2, j, R2_2))
            below = wp.dot(d, g)
            if below < 0.01:
                # A normal-mapped normal tilts the lobe below the face: mirror such directions back above it.
                d = wp.normalize(d + (0.02 - 2.0 * below) * g)
            open_sum += open_distance(scene, start, d, distance) / distance
        rays.ao[i] = open_sum / float(ao_samples)
    if window_samples == 0 or scene.portal_area <= 0.0:
        return
    rot3 = wp.randf(r)
    sky = wp.vec3(0.0, 0.0, 0.0)
    for a in range(window_samples):
        j = k * window_samples + a
        q = sample_portal(scene, stratified(rot3, j, R2_1), wp.randf(r), wp.randf(r))
        w = q.point - start
        d2 = wp.dot(w, w)
        dist = wp.sqrt(d2)
        w = w / dist
        cos_p = wp.dot(n, w)
        if cos_p <= 0.0 or wp.dot(g, w) <= 0.0:
            continue
        if wp.mesh_query_ray_anyhit(scene.mesh, start, w, dist - 1.0e-3):
            # Something stands between: an opaque surface, or glass nearer on the same ray (the room side of a
            # pane hides its outdoor side): each direction counts the first glass it meets, so a window of two
            # panes counts once.
            continue
        cos_g = wp.abs(wp.dot(q.normal, w))
        sky += scene.portal_radiance[q.index] * (cos_p * cos_g * scene.portal_area
                                                 / (wp.max(d2, 0.05) * float(window_samples)))
    rays.sky[i] = sky


def trace_ambient(scene: Any, buffers: Buffers, ao_samples: int, window_samples: int, distance: float, seed: int,
                  device: str) -> None:
    """Launch :func:`trace_ambient_kernel` for one image (after :func:`.primary.trace_primary`)."""
    wp.launch(trace_ambient_kernel, dim=(buffers.height, buffers.width, buffers.spp), device=device,
              inputs=[scene, buffers.width, buffers.spp, int(ao_samples), int(window_samples), float(distance),
                      int(seed), buffers.rays])

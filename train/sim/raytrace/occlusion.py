"""Ambient and window rays: how much of the room's ambient light reaches each camera ray's surface (ambient
occlusion), and the light it receives from what shines by itself: the outdoor view through the windows, the sky,
an emitting lamp shade (:func:`trace_ambient_kernel`).

Each of ``ao_samples`` ambient rays leaves the surface in a cosine-weighted direction about its shading normal
(stratified over the pixel's samples) and follows it through glass (:func:`~.surfaces.trace`):

* stopped by a surface after ``t``, it lets ``min(t / ao_distance, 1)`` of the ambient light through, so that a
  surface darkens its neighbour the more the closer it is (a concave corner, the floor under a table) while an open
  wall keeps all of it;
* reaching an emitter or leaving the scene, it brings that radiance: with cosine-weighted rays, ``pi`` times their
  mean radiance is the irradiance from emitters and sky.

Light through glass comes by the window rays instead (when the scene has glass and ``window_samples`` > 0): each
goes to a random point of the glass (the windows as portals, sampled by area) and on through it; what shines
behind, times ``cos cos' A / d^2`` (``A``: all the glass's area; ``d`` at least 22 cm), is the window's irradiance.
A window thus lights the floor and walls in front of it, more the nearer, and furniture casts soft shadows away
from it, with far less noise than ambient rays that rarely find a window.
"""

from __future__ import annotations

from typing import Any

from fruxel.kernels.wp.runtime import warp

from .buffers import Buffers, RayBuffers
from .surfaces import PI, Hit, SceneData, cosine_direction, stratified, surface_at, trace

wp = warp()
wp.set_module_options({"enable_backward": False})

ALPHA_1 = wp.constant(0.7548776662466927)
ALPHA_2 = wp.constant(0.5698402909980532)
AO_OFFSET = wp.constant(5.0e-4)
"""Metres an ambient ray starts off its surface, along the face normal."""
EMITTER_ANGLE = wp.constant(0.05)
"""Radians of the footprint an ambient ray reads an emitter's image with (a blurred view of it)."""


@wp.struct
class PortalPoint:
    """A point on a window (portal): where, and the window's unit normal there."""

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
    out.point = wp.mesh_eval_position(scene.mesh, face, 1.0 - su, r3 * su)
    out.normal = wp.mesh_eval_face_normal(scene.mesh, face)
    return out


@wp.func
def seen_light(scene: SceneData, hit: Hit, d: wp.vec3) -> wp.vec3:
    """The radiance a ray brings from what shines by itself: the emitter it ended on, or the sky (with what the
    glass on the way adds); 0 when it ended on a surface that does not shine."""
    if hit.kind == 0:
        return hit.front
    s = surface_at(scene, hit, d, EMITTER_ANGLE)
    if s.emitter == 0:
        return wp.vec3(0.0, 0.0, 0.0)
    return hit.front + wp.cw_mul(hit.through, s.emitted)


@wp.kernel
def trace_ambient_kernel(scene: SceneData, width: int, spp: int, ao_samples: int, window_samples: int,
                         distance: float, seed: int, rays: RayBuffers):
    """One thread sends the ambient and window rays of camera ray ``k`` of pixel ``(x, y)`` (entry ``(y * W + x) *
    spp + k``): ``rays.ao`` (float in [0, 1], 1 = open) and ``rays.sky`` (vec3, irradiance from emitters and sky);
    1 and 0 where the ray found no lit surface.

    Launch dims ``(H, W, spp)``. Reads ``rays`` flag, pos, normal, geometric (world frame) and the scene's portals;
    ``ao_samples`` ambient rays, occlusion measured over ``distance`` metres; ``window_samples`` rays to random
    points of the windows; ``seed``: this kernel's seed (one random stream per pixel).
    """
    y, x, k = wp.tid()
    pixel = y * width + x
    i = pixel * spp + k
    rays.sky[i] = wp.vec3(0.0, 0.0, 0.0)
    if rays.flag[i] != 1:
        rays.ao[i] = 1.0
        return
    p = rays.pos[i]
    n = rays.normal[i]
    g = rays.geometric[i]
    start = p + AO_OFFSET * g
    r = wp.rand_init(seed, pixel)
    rot1 = wp.randf(r)
    rot2 = wp.randf(r)
    portals = window_samples > 0 and scene.portal_area > 0.0
    open_sum = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    sky = wp.vec3(0.0, 0.0, 0.0)
    for a in range(ao_samples):
        j = k * ao_samples + a
        d = cosine_direction(n, stratified(rot1, j, ALPHA_1), stratified(rot2, j, ALPHA_2))
        below = wp.dot(d, g)
        if below < 0.01:
            # A normal-mapped normal tilts the lobe below the face: mirror such directions back above it.
            d = wp.normalize(d + (0.02 - 2.0 * below) * g)
        hit = trace(scene, start, d, wp.vec3(0.0, 0.0, 0.0))
        light = seen_light(scene, hit, d)
        if wp.length_sq(light) > 0.0:
            if not (portals and hit.glass > 0):  # light through a window comes by the window rays
                sky += light * (PI / float(ao_samples))
        elif hit.kind == 1:
            open_sum += wp.min(hit.t / distance, 1.0)
            continue
        open_sum += 1.0
    rays.ao[i] = wp.where(ao_samples > 0, open_sum / float(wp.max(ao_samples, 1)), 1.0)
    if portals:
        rot3 = wp.randf(r)
        for a in range(window_samples):
            j = k * window_samples + a
            q = sample_portal(scene, stratified(rot3, j, ALPHA_1), wp.randf(r), wp.randf(r))
            w = q.point - start
            d2 = wp.dot(w, w)
            dist = wp.sqrt(d2)
            w = w / dist
            cos_p = wp.dot(n, w)
            if cos_p <= 0.0 or wp.dot(g, w) <= 0.0:
                continue
            hit = trace(scene, start, w, wp.vec3(0.0, 0.0, 0.0))
            if hit.glass == 0 or hit.t < dist - 1.0e-3:
                continue  # something opaque stands between the surface and that point of the window
            cos_g = wp.abs(wp.dot(q.normal, w))
            sky += seen_light(scene, hit, w) * (cos_p * cos_g * scene.portal_area / (wp.max(d2, 0.05)
                                                                                     * float(window_samples)))
    rays.sky[i] = sky


def trace_ambient(scene: Any, buffers: Buffers, ao_samples: int, window_samples: int, distance: float, seed: int,
                  device: str) -> None:
    """Launch :func:`trace_ambient_kernel` for one image (after :func:`.primary.trace_primary`)."""
    wp.launch(trace_ambient_kernel, dim=(buffers.height, buffers.width, buffers.spp), device=device,
              inputs=[scene, buffers.width, buffers.spp, int(ao_samples), int(window_samples), float(distance),
                      int(seed), buffers.rays])

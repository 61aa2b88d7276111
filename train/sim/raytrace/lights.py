"""Direct light: every light's irradiance at each camera ray's surface, through soft shadows
(:func:`shade_lights_kernel`), and the device function that samples a light (:func:`sample_light`).

Lights (:class:`~fruxel.train.sim.scene.Light`; intensity times colour is ``LightData.radiance``)
    * directional (the sun): irradiance ``radiance`` from the direction opposite to the one it shines, jittered
      within its angular radius;
    * point: ``radiance / d^2`` from a random point of a ball of its radius;
    * spot: a point light times ``smoothstep(cos outer, cos inner, cos angle)`` about the direction it shines.

Soft shadows: each of a ray's ``shadow_samples`` shadow rays goes to another random point of the light
(stratified over the pixel's samples), through glass (:func:`~.surfaces.transmittance`). The irradiance's falloff
uses the light's centre; the specular highlight is that of the centre direction with the roughness widened by the
light's apparent size (no sparkle of single samples on glossy surfaces).
"""

from __future__ import annotations

from typing import Any

from fruxel.kernels.wp.runtime import warp

from .buffers import Buffers, RayBuffers
from .surfaces import (
    FAR,
    R2_1,
    R2_2,
    LightData,
    SceneData,
    cone_direction,
    ggx_specular,
    specular_f0,
    sphere_direction,
    stratified,
    transmittance,
)

wp = warp()
wp.set_module_options({"enable_backward": False})

SHADOW_OFFSET = wp.constant(5.0e-4)
"""Metres a shadow ray starts off its surface, along the face normal."""


@wp.struct
class LightSample:
    """One sample of a light seen from a point: unit direction to the sampled point and to the light's centre,
    distance to the sampled point (far for the sun), irradiance on a surface facing the light (no shadow), and the
    light's apparent radius (radians)."""

    direction: wp.vec3
    centre: wp.vec3
    distance: float
    irradiance: wp.vec3
    spread: float


@wp.func
def sample_light(light: LightData, p: wp.vec3, r1: float, r2: float) -> LightSample:
    """Sample ``light`` from world point ``p`` with two uniform numbers (module docstring)."""
    s = LightSample()
    if light.kind == 0:
        s.centre = -light.direction
        s.direction = s.centre
        if light.radius > 0.0:
            s.direction = cone_direction(s.centre, wp.cos(light.radius), r1, r2)
        s.distance = FAR
        s.irradiance = light.radiance
        s.spread = light.radius
        return s
    c = light.position - p
    dc = wp.max(wp.length(c), 1.0e-4)
    s.centre = c / dc
    w = light.position + light.radius * sphere_direction(r1, r2) - p
    dist = wp.max(wp.length(w), 1.0e-4)
    s.direction = w / dist
    s.distance = dist
    falloff = 1.0 / wp.max(dc * dc, 1.0e-2)
    if light.kind == 2:
        cos_a = wp.dot(-s.centre, light.direction)
        if light.cos_inner - light.cos_outer > 1.0e-5:
            falloff = falloff * wp.smoothstep(light.cos_outer, light.cos_inner, cos_a)
        elif cos_a < light.cos_outer:
            falloff = 0.0
    s.irradiance = light.radiance * falloff
    s.spread = light.radius / dc
    return s


@wp.func
def direct_light(scene: SceneData, light: LightData, p: wp.vec3, n: wp.vec3, g: wp.vec3, r1: float,
                 r2: float) -> wp.vec4:
    """Irradiance ``(r, g, b)`` from one sample of ``light`` at ``p`` (shading normal ``n``, face normal ``g``, both
    unit and facing the viewer), shadow included, and in ``w`` the cosine of the light's centre (0 when it is
    behind)."""
    s = sample_light(light, p, r1, r2)
    n_l = wp.dot(n, s.direction)
    if n_l <= 0.0 or wp.dot(g, s.direction) <= 0.0 or wp.max(s.irradiance) <= 0.0:
        return wp.vec4(0.0, 0.0, 0.0, 0.0)
    vis = wp.vec3(1.0, 1.0, 1.0)
    if light.shadows != 0:
        vis = transmittance(scene, p + SHADOW_OFFSET * g, s.direction, s.distance - 1.0e-3)
    e = wp.cw_mul(s.irradiance, vis) * n_l
    return wp.vec4(e[0], e[1], e[2], wp.max(wp.dot(n, s.centre), 0.0))


@wp.kernel
def shade_lights_kernel(scene: SceneData, width: int, spp: int, shadow_samples: int, seed: int,
                        rays: RayBuffers):
    """One thread sums the light reaching camera ray ``k`` of pixel ``(x, y)``'s surface: ``rays.diffuse`` (the
    lights' irradiance, vec3) and ``rays.specular`` (their reflected specular radiance, vec3) at entry
    ``(y * W + x) * spp + k``; zero where the ray found no lit surface.

    Launch dims ``(H, W, spp)``. Reads ``rays`` flag, pos, normal, geometric, view, albedo, rough_metal (world
    frame); ``scene.lights`` ``(L,)``; ``shadow_samples`` shadow rays per light; ``seed``: this kernel's seed
    (one random stream per pixel, two numbers per light).
    """
    y, x, k = wp.tid()
    pixel = y * width + x
    i = pixel * spp + k
    diffuse = wp.vec3(0.0, 0.0, 0.0)
    specular = wp.vec3(0.0, 0.0, 0.0)
    if rays.flag[i] != 1:
        rays.diffuse[i] = diffuse
        rays.specular[i] = specular
        return
    p = rays.pos[i]
    n = rays.normal[i]
    g = rays.geometric[i]
    v = rays.view[i]
    rm = rays.rough_metal[i]
    f0 = specular_f0(rays.albedo[i], rm[1])
    alpha = rm[0] * rm[0]
    r = wp.rand_init(seed, pixel)
    scale = 1.0 / float(shadow_samples)
    for li in range(scene.lights.shape[0]):
        light = scene.lights[li]
        rot1 = wp.randf(r)
        rot2 = wp.randf(r)
        for s in range(shadow_samples):
            j = k * shadow_samples + s
            e = direct_light(scene, light, p, n, g, stratified(rot1, j, R2_1), stratified(rot2, j, R2_2))
            irr = wp.vec3(e[0], e[1], e[2]) * scale
            diffuse += irr
            if e[3] > 0.0:
                ls = sample_light(light, p, 0.5, 0.5)
                wide = wp.min(1.0, alpha + 0.5 * ls.spread)
                specular += wp.cw_mul(ggx_specular(n, v, ls.centre, wide, f0), irr)
    rays.diffuse[i] = diffuse
    rays.specular[i] = specular


def shade_lights(scene: Any, buffers: Buffers, shadow_samples: int, seed: int, device: str) -> None:
    """Launch :func:`shade_lights_kernel` for one image (after :func:`.primary.trace_primary`)."""
    wp.launch(shade_lights_kernel, dim=(buffers.height, buffers.width, buffers.spp), device=device,
              inputs=[scene, buffers.width, buffers.spp, int(shadow_samples), int(seed), buffers.rays])

"""From camera rays to pixels: each ray's light split into its diffuse albedo and lighting
(:func:`split_light_kernel`), then every ray's lighting smoothed over the rays of neighbouring pixels that saw the
same surface, multiplied back with its albedo and averaged over the pixel (:func:`filter_light_kernel`), giving the
image's linear radiance.

A ray's radiance is ``kd * light + add``: ``kd = through (1 - metallic) albedo``, ``light = (E_lights + E_ambient
ao + E_sky) / pi`` (the diffuse lighting, which a few shadow, ambient and window rays make noisy) and ``add =
through (specular + ambient specular) + front`` (reflections, emitters, glass, sky). The filter replaces each
ray's ``light`` by the weighted mean of the ``light`` of the rays of the ``(2 r + 1)^2`` pixels around it (all
their samples), weighted by a Gaussian of the pixel distance, the depth difference relative to depth and the 8th
power of the normals' cosine: rays on another surface (across an edge, a silhouette) get no weight, so a lit
chair's edge takes no light from the dark wall behind it, and the texture in ``kd`` stays sharp.
"""

from __future__ import annotations

import numpy as np

from fruxel.kernels.wp.runtime import warp

from .buffers import Buffers, PixelBuffers, RayBuffers
from .surfaces import PI, ambient_specular, specular_f0

wp = warp()
wp.set_module_options({"enable_backward": False})


@wp.kernel
def split_light_kernel(width: int, spp: int, ambient: wp.vec3, rays: RayBuffers):
    """One thread splits camera ray ``k`` of pixel ``(x, y)`` (entry ``(y * W + x) * spp + k``, ``spp`` ray slots per
    pixel) into ``rays.kd``, ``rays.light`` and ``rays.add`` (vec3, linear; module docstring); ``kd`` and ``light``
    are 0 where the ray found no lit surface, all three where there is no ray (flag -1).

    Launch dims ``(H, W, spp)``. ``ambient``: the ambient irradiance (vec3, this sample's); reads ``rays`` flag,
    normal, view, albedo, rough_metal, through, front, diffuse, specular, ao, sky.
    """
    y, x, k = wp.tid()
    i = (y * width + x) * spp + k
    add = wp.vec3(0.0, 0.0, 0.0)
    if rays.flag[i] >= 0:
        add = rays.front[i]
    kd = wp.vec3(0.0, 0.0, 0.0)
    light = wp.vec3(0.0, 0.0, 0.0)
    if rays.flag[i] == 1:
        through = rays.through[i]
        rm = rays.rough_metal[i]
        a = rays.albedo[i]
        ao = rays.ao[i]
        kd = wp.cw_mul(through, a) * (1.0 - rm[1])
        light = (rays.diffuse[i] + ambient * ao + rays.sky[i]) / PI
        n_v = wp.max(wp.dot(rays.normal[i], rays.view[i]), 0.0)
        env = wp.cw_mul(ambient_specular(specular_f0(a, rm[1]), n_v, rm[0]), ambient) * (ao / PI)
        add += wp.cw_mul(through, rays.specular[i] + env)
    rays.kd[i] = kd
    rays.light[i] = light
    rays.add[i] = add


@wp.kernel
def filter_light_kernel(width: int, height: int, spp: int, radius: int, rays: RayBuffers, pixels: PixelBuffers):
    """One thread writes pixel ``(x, y)``'s radiance ``pixels.radiance[y * W + x]`` (vec3, linear): the mean over its
    rays (those with flag >= 0) of ``kd`` times the filtered ``light`` plus ``add`` (module docstring).

    Launch dims ``(H, W)``. ``spp``: ray slots per pixel; ``radius``: the filter's half width in pixels (0: no
    filter). Reads ``rays`` flag, kd, light, add, normal, depth.
    """
    y, x = wp.tid()
    base = (y * width + x) * spp
    sigma2 = 2.0 * (0.5 * float(radius) + 0.5) * (0.5 * float(radius) + 0.5)
    out = wp.vec3(0.0, 0.0, 0.0)
    count = int(0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    for k in range(spp):
        i = base + k
        if rays.flag[i] < 0:
            continue
        count += 1
        out += rays.add[i]
        if rays.flag[i] != 1:
            continue
        light = rays.light[i]
        if radius > 0:
            n = rays.normal[i]
            depth = rays.depth[i]
            tolerance = 0.01 + 0.03 * depth
            total = wp.vec3(0.0, 0.0, 0.0)
            weight = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
            for dy in range(-radius, radius + 1):
                for dx in range(-radius, radius + 1):
                    yy = y + dy
                    xx = x + dx
                    if yy < 0 or yy >= height or xx < 0 or xx >= width:
                        continue
                    spatial = -float(dx * dx + dy * dy) / sigma2
                    for j in range(spp):
                        q = (yy * width + xx) * spp + j
                        if rays.flag[q] != 1:
                            continue
                        c = wp.max(wp.dot(n, rays.normal[q]), 0.0)
                        c2 = c * c
                        c4 = c2 * c2
                        w = wp.exp(spatial - wp.abs(rays.depth[q] - depth) / tolerance) * c4 * c4
                        total += w * rays.light[q]
                        weight += w
            if weight > 0.0:
                light = total / weight
        out += wp.cw_mul(rays.kd[i], light)
    pixels.radiance[y * width + x] = out / float(wp.max(count, 1))


def resolve(buffers: Buffers, ambient: np.ndarray, radius: int, device: str) -> None:
    """Launch the two kernels for one image (after the primary, lighting and occlusion kernels)."""
    wp.launch(split_light_kernel, dim=(buffers.height, buffers.width, buffers.spp), device=device,
              inputs=[buffers.width, buffers.spp, wp.vec3(*np.asarray(ambient, dtype=np.float32)), buffers.rays])
    wp.launch(filter_light_kernel, dim=(buffers.height, buffers.width), device=device,
              inputs=[buffers.width, buffers.height, buffers.spp, int(radius), buffers.rays, buffers.pixels])

"""From camera rays to pixels: the samples of each pixel combined (:func:`combine_samples_kernel`), then the
diffuse lighting smoothed by an edge-aware filter and multiplied back with the albedo
(:func:`filter_lighting_kernel`), giving the image's linear radiance.

Per ray, the radiance is ``through * ((1 - metallic) albedo / pi * (E_lights + E_ambient ao) + specular)
+ front``. The pixel keeps the diffuse part apart, as ``albedo`` (the mean of ``through (1 - metallic) albedo``)
times ``light`` (the mean diffuse radiance over it): a few shadow and occlusion rays make ``light`` noisy, and the
filter averages it over the ``(2 r + 1)^2`` neighbours on the same surface (weights: a Gaussian of the pixel
distance, the depth difference relative to depth, and the 8th power of the normals' cosine), while the texture in
``albedo`` stays sharp.
"""

from __future__ import annotations

import numpy as np

from fruxel.kernels.wp.runtime import warp

from .buffers import Buffers, PixelBuffers, RayBuffers
from .surfaces import PI, ambient_specular, specular_f0

wp = warp()
wp.set_module_options({"enable_backward": False})


@wp.kernel
def combine_samples_kernel(width: int, spp: int, ambient: wp.vec3, rays: RayBuffers, pixels: PixelBuffers):
    """One thread combines the ``spp`` camera rays of pixel ``(x, y)`` into entry ``y * W + x`` of ``pixels``
    albedo, light, add (vec3, linear), normal (vec3, world frame; 0 where the samples saw different surfaces or
    no lit one) and depth (metres).

    Launch dims ``(H, W)``. ``ambient``: the ambient irradiance (vec3, per sample); reads every ``rays`` buffer.
    """
    y, x = wp.tid()
    pixel = y * width + x
    albedo = wp.vec3(0.0, 0.0, 0.0)
    diffuse = wp.vec3(0.0, 0.0, 0.0)
    add = wp.vec3(0.0, 0.0, 0.0)
    for k in range(spp):
        i = pixel * spp + k
        add += rays.front[i]
        if rays.flag[i] == 1:
            through = rays.through[i]
            rm = rays.rough_metal[i]
            a = rays.albedo[i]
            kd = wp.cw_mul(through, a) * (1.0 - rm[1])
            e = rays.diffuse[i] + ambient * rays.ao[i]
            albedo += kd
            diffuse += wp.cw_mul(kd, e) / PI
            n_v = wp.max(wp.dot(rays.normal[i], rays.view[i]), 0.0)
            env = wp.cw_mul(ambient_specular(specular_f0(a, rm[1]), n_v, rm[0]), ambient) * (rays.ao[i] / PI)
            add += wp.cw_mul(through, rays.specular[i] + env)
    inv = 1.0 / float(spp)
    albedo = albedo * inv
    light = wp.vec3(0.0, 0.0, 0.0)
    for c in range(3):
        if albedo[c] > 1.0e-5:
            light[c] = diffuse[c] * inv / albedo[c]
    pixels.albedo[pixel] = albedo
    pixels.light[pixel] = light
    pixels.add[pixel] = add * inv
    i0 = pixel * spp
    n0 = rays.normal[i0]
    d0 = rays.depth[i0]
    same = rays.flag[i0] == 1
    for k in range(1, spp):
        i = i0 + k
        if rays.flag[i] != 1 or wp.dot(rays.normal[i], n0) < 0.9 or wp.abs(rays.depth[i] - d0) > 0.01 + 0.03 * d0:
            same = False
    # A pixel whose samples saw different surfaces (an edge) keeps its own light and lends none: its light is a
    # mixture that belongs to neither side.
    pixels.normal[pixel] = wp.where(same, n0, wp.vec3(0.0, 0.0, 0.0))
    pixels.depth[pixel] = d0


@wp.kernel
def filter_lighting_kernel(width: int, height: int, radius: int, pixels: PixelBuffers):
    """One thread writes pixel ``(x, y)``'s radiance (vec3, linear): its albedo times its neighbours' filtered
    light, plus its added radiance (module docstring).

    Launch dims ``(H, W)``. ``radius``: the filter's half width in pixels (0: no filter). Reads ``pixels`` albedo,
    light, add, normal, depth; writes ``pixels.radiance``.
    """
    y, x = wp.tid()
    p = y * width + x
    albedo = pixels.albedo[p]
    light = pixels.light[p]
    n = pixels.normal[p]
    if radius > 0 and wp.length_sq(n) > 0.0:
        depth = pixels.depth[p]
        tolerance = 0.01 + 0.03 * depth
        sigma2 = 2.0 * (0.5 * float(radius) + 0.5) * (0.5 * float(radius) + 0.5)
        total = wp.vec3(0.0, 0.0, 0.0)
        weight = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                yy = y + dy
                xx = x + dx
                if yy < 0 or yy >= height or xx < 0 or xx >= width:
                    continue
                q = yy * width + xx
                c = wp.max(wp.dot(n, pixels.normal[q]), 0.0)
                c2 = c * c
                c4 = c2 * c2
                w = wp.exp(-float(dx * dx + dy * dy) / sigma2 - wp.abs(pixels.depth[q] - depth) / tolerance)
                w = w * c4 * c4
                total += w * pixels.light[q]
                weight += w
        if weight > 0.0:
            light = total / weight
    pixels.radiance[p] = wp.cw_mul(albedo, light) + pixels.add[p]


def resolve(buffers: Buffers, ambient: np.ndarray, radius: int, device: str) -> None:
    """Launch the two kernels for one image (after the primary, lighting and occlusion kernels)."""
    dim = (buffers.height, buffers.width)
    wp.launch(combine_samples_kernel, dim=dim, device=device,
              inputs=[buffers.width, buffers.spp, wp.vec3(*np.asarray(ambient, dtype=np.float32)), buffers.rays,
                      buffers.pixels])
    wp.launch(filter_lighting_kernel, dim=dim, device=device,
              inputs=[buffers.width, buffers.height, int(radius), buffers.pixels])

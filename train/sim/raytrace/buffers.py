"""The device buffers one image is computed in, kept by the renderer between images of one size (every kernel
overwrites what it writes, so nothing passes from one image to the next).

Per camera ray (``N = H * W * S`` entries, ``S`` = samples per pixel plus edge samples; ray ``(y * W + x) * S + k``
is sample ``k`` of pixel ``(x, y)``): :class:`RayBuffers`, written by :func:`.primary.trace_primary_kernel` and read
by the lighting, occlusion and resolving kernels. Per pixel (``H * W``): :class:`PixelBuffers`.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

from fruxel.kernels.wp.runtime import warp

wp = warp()


@wp.struct
class RayBuffers:
    """What each camera ray found (world frame); arrays of ``N`` entries."""

    flag: wp.array(dtype=wp.int32)
    """-1: no ray (an edge sample of a pixel off the edges); 0: no opaque surface (sky); 1: a lit surface; 2: an
    emitter (its light is in ``front``)."""
    material: wp.array(dtype=wp.int32)
    """The opaque surface's material row (-1: none)."""
    pos: wp.array(dtype=wp.vec3)
    """The opaque hit point, metres."""
    normal: wp.array(dtype=wp.vec3)
    """Unit shading normal there (smoothed, normal-mapped), facing the camera."""
    geometric: wp.array(dtype=wp.vec3)
    """Unit face normal there, facing the camera."""
    view: wp.array(dtype=wp.vec3)
    """Unit direction from the hit back along the ray."""
    albedo: wp.array(dtype=wp.vec3)
    """Linear albedo (texture times colour)."""
    rough_metal: wp.array(dtype=wp.vec2)
    """Roughness and metalness."""
    through: wp.array(dtype=wp.vec3)
    """What the glass on the way lets through (1 without glass)."""
    front: wp.array(dtype=wp.vec3)
    """Radiance added on the way: glass reflections, emitters, the sky."""
    depth: wp.array(dtype=wp.float32)
    """Distance along the ray to the opaque hit (or far), metres."""
    diffuse: wp.array(dtype=wp.vec3)
    """Irradiance from the lights (shadows included), per unit albedo times pi (lighting kernel)."""
    specular: wp.array(dtype=wp.vec3)
    """Specular radiance reflected from the lights (lighting kernel)."""
    ao: wp.array(dtype=wp.float32)
    """Unoccluded share of the ambient light, in [0, 1] (:mod:`.occlusion`)."""
    sky: wp.array(dtype=wp.vec3)
    """Irradiance from emitters and sky reaching the surface (:mod:`.occlusion`)."""
    kd: wp.array(dtype=wp.vec3)
    """Diffuse albedo times the glass in front (:mod:`.resolve`)."""
    light: wp.array(dtype=wp.vec3)
    """Diffuse lighting, lights and ambient, over pi (:mod:`.resolve`)."""
    add: wp.array(dtype=wp.vec3)
    """Radiance besides ``kd * light``: reflections, emitters, glass, sky (:mod:`.resolve`)."""


@wp.struct
class PixelBuffers:
    """Per pixel (``H * W`` entries, pixel ``y * W + x``)."""

    edge: wp.array(dtype=wp.int32)
    """1 where the pixel is on an edge and takes the edge samples (:func:`.primary.find_edges_kernel`)."""
    radiance: wp.array(dtype=wp.vec3)
    """The rendered linear radiance (:mod:`.resolve`)."""
    blurred: wp.array(dtype=wp.vec3)
    """The radiance through the lens blur."""
    meter: wp.array(dtype=wp.float32)
    """Per image row, the sum of log luminance (auto-exposure); entry ``H`` the exposure factor."""
    image: wp.array(dtype=wp.vec3ub)
    """The developed 8-bit sRGB image."""


@dataclass
class Buffers:
    """The two structs for one image size, on one device."""

    height: int
    width: int
    spp: int
    """Ray slots per pixel: samples per pixel plus edge samples."""
    rays: Any
    pixels: Any


def allocate(height: int, width: int, spp: int, device: str) -> Buffers:
    """Buffers for ``height x width`` images with ``spp`` ray slots per pixel on ``device``."""
    n, p = height * width * spp, height * width
    rays = RayBuffers()
    for name, dtype in (("flag", wp.int32), ("material", wp.int32), ("pos", wp.vec3), ("normal", wp.vec3),
                        ("geometric", wp.vec3), ("view", wp.vec3), ("albedo", wp.vec3), ("rough_metal", wp.vec2),
                        ("through", wp.vec3), ("front", wp.vec3), ("depth", wp.float32), ("diffuse", wp.vec3),
                        ("specular", wp.vec3), ("ao", wp.float32), ("sky", wp.vec3), ("kd", wp.vec3),
                        ("light", wp.vec3), ("add", wp.vec3)):
        setattr(rays, name, wp.zeros(n, dtype=dtype, device=device))
    pixels = PixelBuffers()
    for name, dtype in (("edge", wp.int32), ("radiance", wp.vec3), ("blurred", wp.vec3),
                        ("image", wp.vec3ub)):
        setattr(pixels, name, wp.zeros(p, dtype=dtype, device=device))
    pixels.meter = wp.zeros(height + 1, dtype=wp.float32, device=device)
    return Buffers(height, width, spp, rays, pixels)

"""The room's ambient light: an estimate of its indirect (bounced) light, made once per room by probe rays
(:func:`probe_room_kernel`, :func:`estimate_ambient`); and the radiance of each window pane, what shines behind it
(:func:`measure_portals_kernel`), which the window rays of :mod:`.occlusion` bring in.

In a closed room whose surfaces have mean albedo ``rho`` and receive mean direct irradiance ``E_d``, light that
keeps bouncing adds the irradiance ``E_a = (mean(rho E_d) + pi mean(L_e)) / (1 - mean(rho))`` everywhere (the
radiosity of a uniform enclosure; ``L_e``: what the room sees that shines by itself, the outdoor view through its
windows, the sky, a lamp shade). When the window rays bring the light behind glass to each surface directly
(:mod:`.occlusion`), only its reflections are ambient: for that part ``pi mean(L_e)`` becomes ``mean(rho) pi
mean(L_e)``. The
means are taken over the surfaces that probe rays see from points above the room's free floor
(:attr:`~fruxel.train.sim.scene.Scene.free_space`), at two heights, in uniform directions: a sunlit patch on the
floor, a dark corner and a window count as much as they cover. ``E_a`` is coloured (a red room's ambient light is
red) and is what the ambient-occlusion rays shade; each sample scales it by a random factor.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fruxel.kernels.wp.runtime import warp

from .lights import direct_light
from .surfaces import (
    PI,
    RAY_EPS,
    SceneData,
    cosine_direction,
    glass_tint,
    schlick,
    seen_light,
    sphere_direction,
    surface_at,
    trace,
)

wp = warp()
wp.set_module_options({"enable_backward": False})

PROBE_ORIGINS = 8
"""Points the probe rays start from."""
PROBE_RAYS = 512
"""Rays per point."""
PORTAL_RAYS = 64
"""Probe rays per side of each portal (glass face) measuring what shines behind it."""
MAX_ALBEDO = 0.8
"""The mean albedo is capped here: the estimate grows as ``1 / (1 - rho)``."""


@wp.kernel
def probe_room_kernel(scene: SceneData, origins: wp.array(dtype=wp.vec3), rays_per_origin: int, seed: int,
                      reflected: wp.array(dtype=wp.vec3), albedo: wp.array(dtype=wp.vec3),
                      emitted: wp.array(dtype=wp.vec3), windows: wp.array(dtype=wp.vec3)):
    """One thread follows probe ray ``r`` of origin ``o`` (entry ``o * R + r``) and records what it sees: the
    albedo times the direct irradiance of its surface (``reflected``), the albedo (``albedo``) and the radiance
    of what shines by itself, seen through glass (``windows``) or not (``emitted``), all vec3, linear, zero where
    they do not apply.

    Launch dims ``(O * R,)``. ``origins`` ``(O,)`` world points; ``seed``: the room's probe seed.
    """
    tid = wp.tid()
    o = tid // rays_per_origin
    r = wp.rand_init(seed, tid)
    d = sphere_direction(wp.randf(r), wp.randf(r))
    hit = trace(scene, origins[o], d, wp.vec3(0.0, 0.0, 0.0))
    zero = wp.vec3(0.0, 0.0, 0.0)
    reflected[tid] = zero
    albedo[tid] = zero
    shine = hit.front
    if hit.kind == 1:
        s = surface_at(scene, hit, d, 0.05)
        if s.emitter != 0:
            shine = hit.front + wp.cw_mul(hit.through, s.emitted)
    emitted[tid] = wp.where(hit.glass == 0, shine, zero)
    windows[tid] = wp.where(hit.glass > 0, shine, zero)
    if hit.kind == 0:
        return
    s = surface_at(scene, hit, d, 0.05)
    if s.emitter != 0:
        return
    e = wp.vec3(0.0, 0.0, 0.0)
    for li in range(scene.lights.shape[0]):
        c = direct_light(scene, scene.lights[li], hit.pos, s.normal, s.geometric, wp.randf(r), wp.randf(r))
        e += wp.vec3(c[0], c[1], c[2])
    a = wp.cw_mul(hit.through, s.albedo) * (1.0 - s.metallic)
    albedo[tid] = a
    reflected[tid] = wp.cw_mul(a, e)


@wp.kernel
def measure_portals_kernel(scene: SceneData, rays_per_side: int, seed: int, radiance: wp.array(dtype=wp.vec3)):
    """One thread sends probe ray ``r`` from the centre of portal ``p`` to side ``s`` of it (0: along its normal,
    1: against it), cosine-weighted, through the glass; writes what shines there, times what the portal's own glass
    lets through (vec3, linear, 0 for a surface that does not shine), to entry ``(p * 2 + s) * R + r`` of
    ``radiance``.

    Launch dims ``(P, 2, R)``; ``scene.portals`` ``(P,)`` the glass faces; ``seed``: the room's.
    """
    p, side, r = wp.tid()
    face = scene.portals[p]
    normal = wp.mesh_eval_face_normal(scene.mesh, face) * wp.where(side == 0, 1.0, -1.0)
    rng = wp.rand_init(seed, (p * 2 + side) * rays_per_side + r)
    d = cosine_direction(normal, wp.randf(rng), wp.randf(rng))
    start = wp.mesh_eval_position(scene.mesh, face, 0.3333333, 0.3333333) + RAY_EPS * normal
    hit = trace(scene, start, d, wp.vec3(0.0, 0.0, 0.0))
    # What comes through the pane itself too (the probe starts past it).
    mat = scene.materials[scene.face_material[face]]
    own = glass_tint(mat.color) * ((1.0 - mat.opacity) * (1.0 - schlick(0.04, wp.dot(normal, d))))
    radiance[(p * 2 + side) * rays_per_side + r] = wp.cw_mul(own, seen_light(scene, hit, d))


def measure_portals(data: Any, portals: int, seed: int, device: str) -> np.ndarray:
    """The radiance each portal (glass face) lets into the room: ``(P, 3)`` float32, per portal the mean radiance of
    what shines on its brighter side (the outdoor side; the room side sees mostly surfaces that do not shine)."""
    if portals == 0:
        return np.zeros((0, 3), dtype=np.float32)
    out = wp.zeros(portals * 2 * PORTAL_RAYS, dtype=wp.vec3, device=device)
    wp.launch(measure_portals_kernel, dim=(portals, 2, PORTAL_RAYS), device=device,
              inputs=[data, PORTAL_RAYS, int(seed) & 0x7FFFFFFF, out])
    sides = out.numpy().astype(np.float64).reshape(portals, 2, PORTAL_RAYS, 3).mean(axis=2)
    brighter = sides.sum(axis=2).argmax(axis=1)
    return sides[np.arange(portals), brighter].astype(np.float32)


def probe_origins(scene: Any) -> np.ndarray:
    """``(PROBE_ORIGINS, 3)`` float32 world points above the room's free floor, at 40 % and 75 % of its height:
    free cells evenly spread over the free ones in cell order (the room's centre when none is free)."""
    size = np.asarray(scene.room_size, dtype=np.float64)
    heights = (0.4 * size[2], 0.75 * size[2])
    per_height = PROBE_ORIGINS // len(heights)
    free = scene.free_space
    centres = free.cell_centres()[~free.occupied] if free.occupied.size else np.zeros((0, 2))
    if len(centres) == 0:
        xy = np.repeat(size[None, :2] / 2, per_height, axis=0)
    else:
        xy = centres[np.linspace(0, len(centres) - 1, per_height).round().astype(int)]
    pts = [np.array([px, py, h]) for h in heights for px, py in xy]
    return np.asarray(pts, dtype=np.float32)


def estimate_ambient(scene: Any, data: Any, seed: int, windows_direct: bool, device: str) -> np.ndarray:
    """The room's ambient irradiance ``E_a`` (module docstring): ``(3,)`` float64, linear RGB.

    Args:
        scene: the :class:`~fruxel.train.sim.scene.Scene` (its free floor places the probes).
        data: its ``SceneData`` on ``device``.
        seed: the probe rays' seed (the room's, so that every image of a room has the same ambient light).
        windows_direct: whether the images take the light through glass directly (window rays,
            :mod:`.occlusion`): then only its reflections are ambient light (module docstring).
        device: Warp device.
    """
    origins = probe_origins(scene)
    n = len(origins) * PROBE_RAYS
    out = [wp.zeros(n, dtype=wp.vec3, device=device) for _ in range(4)]
    wp.launch(probe_room_kernel, dim=n, device=device,
              inputs=[data, wp.array(origins, dtype=wp.vec3, device=device), PROBE_RAYS, int(seed) & 0x7FFFFFFF,
                      *out])
    reflected, albedo, emitted, windows = (a.numpy().astype(np.float64).mean(axis=0) for a in out)
    rho = np.minimum(albedo, MAX_ALBEDO)
    shine = emitted + windows * (rho if windows_direct else 1.0)
    return (reflected + float(PI) * shine) / (1.0 - rho)

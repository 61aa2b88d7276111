"""Shading normals at the corners of a room's faces, smoothed across curved surfaces and kept sharp at edges
(:func:`smooth_normals_kernel`).

Per corner: the sum of the area-weighted normals of the faces around its vertex that lie within ``smooth_angle``
of this face's normal (a face further off is across an edge, not part of the curve), normalised. A box keeps its
faces' normals (its faces meet at 90 degrees); a decimated sofa or statue looks smooth. Faces share a vertex where
they share its index (objects never do: their vertices are numbered apart).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fruxel.kernels.wp.runtime import warp

wp = warp()
wp.set_module_options({"enable_backward": False})


@wp.func
def _face_cross(points: wp.array(dtype=wp.vec3), faces: wp.array(dtype=wp.int32), f: int) -> wp.vec3:
    """Twice the area times the unit normal of face ``f`` (counter-clockwise winding)."""
    a = points[faces[3 * f]]
    return wp.cross(points[faces[3 * f + 1]] - a, points[faces[3 * f + 2]] - a)


@wp.kernel
def smooth_normals_kernel(points: wp.array(dtype=wp.vec3), faces: wp.array(dtype=wp.int32),
                          ring_start: wp.array(dtype=wp.int32), ring_faces: wp.array(dtype=wp.int32),
                          cos_max: float, normals: wp.array(dtype=wp.vec3)):
    """One thread computes the shading normal of corner ``c`` (corner ``c % 3`` of face ``c // 3``):
    ``normals[c]`` (unit vec3, world frame, outward).

    Launch dims ``(3 F,)``. ``points`` ``(V,)`` vec3 world frame; ``faces`` ``(3 F,)`` int32 vertex indices;
    ``ring_start`` ``(V + 1,)`` and ``ring_faces`` ``(3 F,)`` int32: the faces around vertex ``v`` are
    ``ring_faces[ring_start[v]:ring_start[v + 1]]``, in face order; ``cos_max``: cosine of the smoothing angle
    (above 1: no smoothing).
    """
    c = wp.tid()
    own = _face_cross(points, faces, c // 3)
    length = wp.length(own)
    unit = wp.vec3(0.0, 0.0, 1.0)
    if length > 0.0:
        unit = own / length
    if cos_max > 1.0:
        normals[c] = unit
        return
    v = faces[c]
    total = wp.vec3(0.0, 0.0, 0.0)
    for r in range(ring_start[v], ring_start[v + 1]):
        other = _face_cross(points, faces, ring_faces[r])
        n = wp.length(other)
        if n > 0.0 and wp.dot(other, unit) >= cos_max * n:
            total += other
    n = wp.length(total)
    if n > 0.0:
        unit = total / n
    normals[c] = unit


def corner_normals(points: Any, faces: np.ndarray, smooth_angle: float, device: str) -> Any:
    """Launch :func:`smooth_normals_kernel`.

    Args:
        points: ``(V,)`` ``wp.vec3`` array on ``device``, world frame.
        faces: ``(F, 3)`` int32 vertex indices.
        smooth_angle: degrees in [0, 90); 0 gives every corner its face's normal.
        device: Warp device.

    Returns:
        ``(3 F,)`` ``wp.vec3`` array of unit outward normals, corner ``3 f + k`` of face ``f``.
    """
    corners = np.ascontiguousarray(faces, dtype=np.int32).ravel()
    order = np.argsort(corners, kind="stable")
    counts = np.bincount(corners, minlength=points.shape[0])
    start = np.concatenate([[0], np.cumsum(counts)]).astype(np.int32)
    out = wp.empty(len(corners), dtype=wp.vec3, device=device)
    cos_max = math.cos(math.radians(smooth_angle)) if smooth_angle > 0 else 2.0
    wp.launch(smooth_normals_kernel, dim=len(corners), device=device,
              inputs=[points, wp.array(corners, dtype=wp.int32, device=device),
                      wp.array(start, dtype=wp.int32, device=device),
                      wp.array((order // 3).astype(np.int32), dtype=wp.int32, device=device), float(cos_max), out])
    return out

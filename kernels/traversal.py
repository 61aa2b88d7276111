"""The ray traversal every backend implements, and the constants they share.

This module is the single definition of the algorithm; the Warp kernels, the OpenCL source and the test
reference implement exactly these steps, and take the constants below as arguments (OpenCL gets them as
``-D`` build options), never as copies.

Ray
    Pixel ``(x, y)`` of a camera with pose ``[R | c]`` (camera-to-grid) has origin ``o = c`` and direction
    ``d = R @ ((x + 0.5 - cx) / fx, (y + 0.5 - cy) / fy, 1)``, unnormalised, so the ray parameter ``t`` is the
    depth in the viewing camera. All work is in the grid frame.

1. Clip (Cyrus-Beck) to the frustum, the intersection of six half-spaces ``n . p + c >= 0``::

       left   (1, 0, -u_0)   c = 0         right  (-1, 0, u_W)   c = 0
       top    (0, 1, -v_0)   c = 0         bottom (0, -1, v_H)   c = 0
       near   (0, 0, 1)      c = -z_near   far    (0, 0, -1)     c = z_far

   Start with ``[t_lo, t_hi] = [0, inf)``. For each plane in the order above, ``a = n . d``, ``b = n . o + c``:
   ``a == 0``: miss if ``b < 0``, else no constraint; ``a > 0``: ``t_lo = max(t_lo, -b / a)``, remembering the
   plane when it raises t_lo (strictly); ``a < 0``: ``t_hi = min(t_hi, -b / a)``. Miss when ``t_lo >= t_hi``.
   The left and right half-spaces already imply z >= 0, and near clips the apex region, so the six describe the
   frustum exactly and rays through the apex or from behind it need no special case.

2. Entry cell at ``p = o + t_lo d``: ``k = floor((p_z - z_near) / dz)``, ``i = floor((p_x / p_z - u_0) / du)``,
   ``j = floor((p_y / p_z - v_0) / dv)``, each clamped to its range. The index of the entry plane's family is
   set exactly instead (left: i = 0, right: i = W - 1, top: j = 0, bottom: j = H - 1, near: k = 0,
   far: k = D - 1). A camera inside the frustum (no entry plane) starts in the cell containing it.

3. Step signs, constant along the ray because ``u(t) = x(t) / z(t)`` is monotone where z > 0:
   ``s_i = sign(d_x o_z - d_z o_x)``, ``s_j = sign(d_y o_z - d_z o_y)``, ``s_k = sign(d_z)``. A zero sign means
   that family is never crossed (next crossing at +inf).

4. Next crossing of each family: the boundary ahead is ``ib = i + (s_i > 0)`` (likewise jb, kb);
   ``t_u = (u_ib o_z - o_x) / (d_x - u_ib d_z)``, ``t_v = (v_jb o_z - o_y) / (d_y - v_jb d_z)``,
   ``t_z = (z_kb - o_z) / d_z``. Boundaries are computed from their index (``u_ib = -tu + ib * du``), never
   accumulated. A u-boundary counts as ahead only when ``s_i (d_x - u_ib d_z) > 0`` (likewise for v), else its
   crossing is +inf: the plane ``x = u z`` continues behind the apex (z < 0), and a ray from a camera behind
   the apex meets it there at a t that would otherwise look like a crossing ahead.

5. Loop, at most ``W + H + D + 3`` times: if the current cell is occupied, it is the hit: ``depth = t_entry``
   (``t_lo`` for the first cell), ``normal`` = the entry face's. Otherwise take the family with the smallest
   next crossing, ties broken in the order u, v, z (``FAMILY_U < FAMILY_V < FAMILY_Z``); if that crossing is
   ``>= t_hi`` or the stepped index leaves its range, the ray misses. Else step that index by its sign, set
   ``t_entry`` to the crossing, and recompute that family's next crossing.

Entry-face normal (grid frame, unit, facing the camera, i.e. ``dot(n, d) < 0``)
    u-plane at ``u``: ``-s_i (1, 0, -u) / |(1, 0, -u)|``; v-plane: ``-s_j (0, 1, -v) / |.|``; z-plane:
    ``(0, 0, -s_k)``. Entering through a clip plane: minus that plane's unit normal (the same formulas). A camera
    inside an occupied cell hits it at ``t = 0`` with normal ``-d / |d|``.

Empty-space skipping
    Backends may skip empty space in whole boxes of cells: any box of indices (``i0 <= i < i1``, likewise j, k)
    that holds the current cell and no occupied one. Its boundaries are cell planes, so the box is itself a
    trapezoid cell. Skipping must give the same hits as the plain loop above: find the crossing ``t_exit``
    where the ray leaves the box (each family's far boundary by step 4's formula; the first of them, ties u, v,
    z), step that family into the next cell as the plain loop would, and put every other family past all of its
    crossings below ``t_exit`` (at ``t_exit`` too for families before the exiting one in the tie order), then
    continue. Warp takes its boxes from a coarse occupancy pyramid of ``BLOCK``-cell cubes and advances each
    family crossing by crossing (at most ``BLOCK`` per family); OpenCL takes them from a chessboard distance field
    over small groups of cells (the cube of empty groups around the current one) and puts each family where the
    exit point lies, verified against the crossings on either side. Both rely on a family's crossings growing
    with the boundary index, as they do wherever consecutive crossings differ by more than float32 rounding.
    Results may differ from the plain loop only for rays that pass exactly through a cell edge.

Precision
    Kernels compute in float32. Backends and the float64 test reference agree on labels and cells except for
    rays passing within float32 rounding of a cell edge or corner; depths agree to float32 rounding.
"""

from __future__ import annotations

from functools import lru_cache

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

FAMILY_U = 0
"""Plane family x = u z (column boundaries); also the first in the tie order."""
FAMILY_V = 1
"""Plane family y = v z (row boundaries)."""
FAMILY_Z = 2
"""Plane family z = const (slice boundaries)."""

BLOCK = 4
"""Edge of a coarse pyramid block, in cells, along each axis (the last block of an axis may be partial)."""


def max_steps(grid: FruxelGrid) -> int:
    """Upper bound on DDA iterations for one ray: every step moves one index monotonically."""
    return grid.width + grid.height + grid.depth + 3


def grid_params(grid: FruxelGrid) -> np.ndarray:
    """Grid constants for the kernels: ``(8,)`` float32 ``(u_0, v_0, du, dv, z_near, dz, z_far, 0)``.

    ``u_W`` and ``v_H`` are ``-u_0`` and ``-v_0`` (the grid is symmetric about its axis).
    """
    return np.array([-grid.tu, -grid.tv, grid.du, grid.dv, grid.z_near, grid.dz, grid.z_far, 0.0], dtype=np.float32)


def camera_params(camera: Camera) -> np.ndarray:
    """Camera constants for the kernels: ``(16,)`` float32.

    Layout: ``(fx, fy, cx, cy, r00, r01, r02, r10, r11, r12, r20, r21, r22, ox, oy, oz)``: intrinsics, the
    camera-to-grid rotation row by row, and the optical centre in the grid frame.
    """
    return np.concatenate(
        [[camera.fx, camera.fy, camera.cx, camera.cy], camera.rotation.reshape(-1), camera.position]
    ).astype(np.float32)


def is_own_view(camera: Camera, grid: FruxelGrid) -> bool:
    """True when ``camera`` is the grid's own camera at native resolution (identity pose, same intrinsics), for
    which ``shell`` takes the column fast path: pixel (i, j) then looks straight down column (j, i)."""
    if camera.width != grid.width or camera.height != grid.height:  # before the cached lookup, which hashes the grid
        return False
    own = _own_intrinsics(grid)
    for value, ref in zip((camera.fx, camera.fy, camera.cx, camera.cy), own, strict=True):
        if abs(value - ref) > 1e-9 * abs(ref) + 1e-8:  # np.allclose(rtol=1e-9), written out: it is on every call
            return False
    return bool(np.all(np.abs(np.asarray(camera.pose) - _EYE4) <= _POSE_TOLERANCE))


_EYE4 = np.eye(4)
_POSE_TOLERANCE = 1e-12 + 1e-5 * _EYE4
"""np.allclose(pose, eye(4), atol=1e-12) per entry: 1e-12 plus the default relative 1e-5 on the diagonal."""


@lru_cache(maxsize=64)
def _own_intrinsics(grid: FruxelGrid) -> tuple[float, float, float, float]:
    """``(fx, fy, cx, cy)`` of the grid's own camera (whose image is ``grid.width`` x ``grid.height``)."""
    own = grid.camera()
    return own.fx, own.fy, own.cx, own.cy

"""Warp functions for the ray traversal of :mod:`fruxel.kernels.traversal`, shared by every Warp kernel that walks
rays: ``first_hit`` and ``shell`` (:func:`trace_ray`) and ``soft_first_hit``'s forward and backward walks.

Each function implements one numbered step of ``traversal.py`` and says which. Everything is float32 and in the
grid frame (OpenCV axes, metres); the ray parameter ``t`` is depth in the viewing camera because the camera-frame
direction has z = 1.

The walk is written once, as pieces every walk uses: :func:`clip_ray` (step 1), :func:`start_walk` (steps 2-4: entry
cell, step signs, per-ray coefficients and first crossings on a level), :func:`pick_step` and :func:`take_step`
(step 5's choice and step, on a level of boxes), and, for the backward walk of ``soft_first_hit``,
:func:`step_back` (a step undone). :func:`trace_ray` walks cells, blocks and super-blocks with them;
``soft_first_hit``'s forward walk takes every cell (level 0) and records the stepped families, which its backward
walk undoes. So all of them visit the same cells at the same crossings, bit for bit.

Empty-space skipping (the "Empty-space skipping" paragraph of traversal.py) uses a two-level occupancy pyramid:
blocks of ``BLOCK`` cells and super-blocks of ``SUPER`` blocks along each axis (index space; the last box of an
axis may be partial). :func:`trace_ray` walks one level at a time, cells, blocks or super-blocks, each exactly as
step 5 walks cells: the next crossing of each family is the far side of the current box, ties in the order u, v,
z. Box boundaries are cell boundaries with the same index, and every crossing comes from one expression
(:func:`ray_crossing`), so a boundary's crossing is bit-identical on every level: a coarse walk meets the boundaries
of its level in exactly the order, ties included, in which the plain cell loop would.

The walk keeps one cell index per family. A step on any level moves the stepped family to the first cell of the
next box, which is where the plain loop stands at that crossing. The other families may lag inside their current
boxes (the plain loop would have crossed some of their finer planes meanwhile, all inside empty boxes); on the way
down through a crossing ``(t, f)`` into an occupied box, each family but ``f`` is advanced past the finer
crossings that the plain loop takes before ``(t, f)`` (``t_g < t``, or ``t_g == t`` and ``g`` before ``f`` in the
tie order), at most ``BLOCK - 1`` of them per level, without leaving the box. On the cell level the state is then
the plain loop's, so the hits are the same.
"""

from __future__ import annotations

import ctypes
import math
from functools import lru_cache
from typing import Any

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from .. import traversal
from .arrays import Packed
from .runtime import warp

wp = warp()

# ``@wp.func`` forced inline (CUDA ``__forceinline__``): the walk's helpers take the grid struct by value, which a
# call that is not inlined would copy on every step. Warp before inline hints leaves it to the compilers.
try:
    inline_func = wp.func(inline=True)
except TypeError:
    inline_func = wp.func

BLOCK = wp.constant(traversal.BLOCK)
if traversal.BLOCK & (traversal.BLOCK - 1):
    raise ImportError(f"the Warp walk shifts by log2(BLOCK): BLOCK must be a power of two, got {traversal.BLOCK}")
BLOCK_SHIFT = wp.constant(traversal.BLOCK.bit_length() - 1)
SUPER_BLOCKS = traversal.BLOCK
"""Edge of a super-block (the pyramid's second level), in blocks: ``BLOCK * SUPER_BLOCKS`` cells. Equal to BLOCK,
so that every level has the same number of children per parent along an axis."""
SUPER = wp.constant(SUPER_BLOCKS)
SUPER_SHIFT = wp.constant((traversal.BLOCK * SUPER_BLOCKS).bit_length() - 1)
PARENT_SHIFT = wp.constant(BLOCK_SHIFT)
"""log2 of the children per parent box along an axis, the same for cells in blocks and blocks in super-blocks."""
LEVEL_SUPERS = wp.constant(2)
"""The walk's levels: 0 cells, 1 blocks, 2 super-blocks."""
FAMILY_U = wp.constant(traversal.FAMILY_U)
FAMILY_V = wp.constant(traversal.FAMILY_V)
FAMILY_Z = wp.constant(traversal.FAMILY_Z)
NO_FAMILY = wp.constant(-1)
"""Entry face of a ray that starts inside the frustum (no clip plane crossed)."""

# Clip planes in the order of step 1; PLANE_NONE: the ray starts inside the frustum.
PLANE_NONE = wp.constant(-1)
PLANE_LEFT = wp.constant(0)
PLANE_RIGHT = wp.constant(1)
PLANE_TOP = wp.constant(2)
PLANE_BOTTOM = wp.constant(3)
PLANE_NEAR = wp.constant(4)
PLANE_FAR = wp.constant(5)

TRACE_BLOCK_DIM = 128
"""CUDA threads per block of the kernels that walk rays (their state takes many registers)."""

# Largest cell count per batch item: cell indices are int32 inside the kernels.
MAX_CELLS = 2**31 - 1
MAX_LAUNCH = 2**31 - 1
"""Most threads of one one-dimensional launch (thread indices are int32); larger batches take several launches."""


@wp.struct
class GridInfo:
    """Grid constants for the kernels (from :func:`fruxel.kernels.traversal.grid_params`), passed by value."""

    u0: wp.float32
    """``u_0 = -tu``, the left boundary of u = x / z (``u_W = -u_0``)."""
    v0: wp.float32
    """``v_0 = -tv``, the top boundary of v = y / z (``v_H = -v_0``)."""
    du: wp.float32
    """Column width in u."""
    dv: wp.float32
    """Row height in v."""
    z_near: wp.float32
    """Near plane, metres."""
    dz: wp.float32
    """Slice thickness, metres."""
    z_far: wp.float32
    """Far plane, metres."""
    width: wp.int32
    """W, cells along i (u)."""
    height: wp.int32
    """H, cells along j (v)."""
    depth: wp.int32
    """D, cells along k (z)."""
    blocks_u: wp.int32
    """Pyramid blocks along i, ``ceil(W / BLOCK)``."""
    blocks_v: wp.int32
    """Pyramid blocks along j, ``ceil(H / BLOCK)``."""
    supers_u: wp.int32
    """Super-blocks along i, ``ceil(blocks_u / SUPER)``."""
    supers_v: wp.int32
    """Super-blocks along j, ``ceil(blocks_v / SUPER)``."""
    supers_offset: wp.int32
    """Where the super-block flags start in a pyramid row: the number of blocks, ``bd * bh * bw``."""


@wp.struct
class CameraInfo:
    """Viewing camera constants (from :func:`fruxel.kernels.traversal.camera_params`), passed by value."""

    fx: wp.float32
    fy: wp.float32
    cx: wp.float32
    cy: wp.float32
    rotation: wp.mat33
    """Camera-to-grid rotation."""
    origin: wp.vec3
    """Optical centre, grid frame."""
    width: wp.int32
    """Image width, pixels."""
    height: wp.int32
    """Image height, pixels."""


if (CameraInfo.ctype.width.offset, CameraInfo.ctype.height.offset) != (64, 68):
    raise ImportError("CameraInfo must lay out camera_params' 16 float32 first, then width and height")


def blocks(n: int) -> int:
    """Number of pyramid blocks covering ``n`` cells along one axis (the last one may be partial)."""
    return -(-n // traversal.BLOCK)


def supers(n: int) -> int:
    """Number of super-blocks covering ``n`` cells along one axis."""
    return -(-blocks(n) // SUPER_BLOCKS)


@lru_cache(maxsize=64)
def pyramid_size(grid: FruxelGrid) -> int:
    """Flags per batch item in the pyramid: blocks then super-blocks, ``bd * bh * bw + sd * sh * sw``."""
    return math.prod(pyramid_shape(grid)) + math.prod(supers_shape(grid))


def pyramid_shape(grid: FruxelGrid) -> tuple[int, int, int]:
    """First pyramid level ``(bd, bh, bw) = (ceil(D / BLOCK), ceil(H / BLOCK), ceil(W / BLOCK))``."""
    return blocks(grid.depth), blocks(grid.height), blocks(grid.width)


def supers_shape(grid: FruxelGrid) -> tuple[int, int, int]:
    """Second pyramid level ``(sd, sh, sw) = (ceil(bd / SUPER), ceil(bh / SUPER), ceil(bw / SUPER))``."""
    return supers(grid.depth), supers(grid.height), supers(grid.width)


@lru_cache(maxsize=64)
def grid_info(grid: FruxelGrid) -> GridInfo:
    """The :class:`GridInfo` of ``grid`` (cached: grids are immutable and hashable; the struct is never mutated).

    Raises:
        ValueError: a grid of more than ``MAX_CELLS`` cells, beyond the kernels' int32 cell indices.
    """
    if grid.n_cells > MAX_CELLS:
        raise ValueError(f"the Warp kernels take grids of at most {MAX_CELLS} cells, got {grid.n_cells}")
    p = traversal.grid_params(grid)
    g = GridInfo()
    g.u0, g.v0, g.du, g.dv, g.z_near, g.dz, g.z_far = (float(x) for x in p[:7])
    g.width, g.height, g.depth = grid.width, grid.height, grid.depth
    g.blocks_v, g.blocks_u = blocks(grid.height), blocks(grid.width)
    g.supers_u, g.supers_v = supers(grid.width), supers(grid.height)
    g.supers_offset = math.prod(pyramid_shape(grid))
    return g


def camera_arg(camera: Camera) -> Packed:
    """``camera``'s :class:`CameraInfo` as a launch argument, packed directly: the struct's layout is
    :func:`~fruxel.kernels.traversal.camera_params` (16 float32) followed by width and height (int32)."""
    c = CameraInfo.ctype()
    p = traversal.camera_params(camera)
    ctypes.memmove(ctypes.addressof(c), p.ctypes.data, p.nbytes)
    c.width, c.height = camera.width, camera.height
    return Packed(c)


# ---------------------------------------------------------------------------------------------- ray
@inline_func
def pixel_ray(cam: CameraInfo, x: int, y: int) -> wp.vec3:
    """Direction of pixel ``(x, y)``'s ray in the grid frame, unnormalised (camera-frame z = 1); its origin is
    ``cam.origin``."""
    dc = wp.vec3((float(x) + 0.5 - cam.cx) / cam.fx, (float(y) + 0.5 - cam.cy) / cam.fy, 1.0)
    return cam.rotation @ dc


# ---------------------------------------------------------------------------------------------- step 1: clip
@inline_func
def clip_half_space(a: float, b: float, t_lo: float, t_hi: float, plane: int, which: int):
    """Step 1 for one half-space ``n . p + c >= 0`` with ``a = n . d``, ``b = n . o + c``.

    Returns:
        The updated ``(t_lo, t_hi, plane)``; ``plane`` becomes ``which`` when this half-space raises ``t_lo``
        strictly. A ray parallel to the plane and outside gets ``t_hi = -inf`` (a miss).
    """
    t = -b / a
    raise_lo = a > 0.0 and t > t_lo
    t_hi = wp.where(a < 0.0, wp.min(t_hi, t), wp.where(a == 0.0 and b < 0.0, -wp.inf, t_hi))
    return wp.where(raise_lo, t, t_lo), t_hi, wp.where(raise_lo, which, plane)


@inline_func
def clip_ray(g: GridInfo, o: wp.vec3, d: wp.vec3):
    """Step 1: clip the ray ``o + t d`` (t >= 0) to the frustum.

    Returns:
        ``(t_lo, t_hi, plane)``: the parameter interval inside the frustum and the clip plane the ray enters
        through (``PLANE_NONE`` when it starts inside). The ray misses when ``t_lo >= t_hi``.
    """
    t_lo = wp.float32(0.0)
    t_hi = float(wp.inf)
    plane = int(PLANE_NONE)
    # left (1, 0, -u_0), right (-1, 0, u_W), top (0, 1, -v_0), bottom (0, -1, v_H), u_W = -u_0, v_H = -v_0
    t_lo, t_hi, plane = clip_half_space(d[0] - g.u0 * d[2], o[0] - g.u0 * o[2], t_lo, t_hi, plane, PLANE_LEFT)
    t_lo, t_hi, plane = clip_half_space(-d[0] - g.u0 * d[2], -o[0] - g.u0 * o[2], t_lo, t_hi, plane, PLANE_RIGHT)
    t_lo, t_hi, plane = clip_half_space(d[1] - g.v0 * d[2], o[1] - g.v0 * o[2], t_lo, t_hi, plane, PLANE_TOP)
    t_lo, t_hi, plane = clip_half_space(-d[1] - g.v0 * d[2], -o[1] - g.v0 * o[2], t_lo, t_hi, plane, PLANE_BOTTOM)
    # near (0, 0, 1) with c = -z_near, far (0, 0, -1) with c = z_far
    t_lo, t_hi, plane = clip_half_space(d[2], o[2] - g.z_near, t_lo, t_hi, plane, PLANE_NEAR)
    t_lo, t_hi, plane = clip_half_space(-d[2], g.z_far - o[2], t_lo, t_hi, plane, PLANE_FAR)
    return t_lo, t_hi, plane


# ---------------------------------------------------------------------------------------------- step 2: entry
@inline_func
def floor_index(x: float, n: int) -> int:
    """``floor(x)`` clamped to ``[0, n - 1]``; NaN gives 0."""
    return int(wp.clamp(wp.floor(x), 0.0, float(n - 1)))


@inline_func
def entry_cell(g: GridInfo, o: wp.vec3, d: wp.vec3, t: float, plane: int):
    """Step 2: the cell ``(i, j, k)`` the ray enters at parameter ``t`` through clip plane ``plane``; the entry
    plane's own index is set exactly.

    Returns:
        ``(i, j, k)``, three ints.
    """
    p = o + t * d
    i = floor_index((p[0] / p[2] - g.u0) / g.du, g.width)
    j = floor_index((p[1] / p[2] - g.v0) / g.dv, g.height)
    k = floor_index((p[2] - g.z_near) / g.dz, g.depth)
    i = wp.where(plane == PLANE_LEFT, 0, wp.where(plane == PLANE_RIGHT, g.width - 1, i))
    j = wp.where(plane == PLANE_TOP, 0, wp.where(plane == PLANE_BOTTOM, g.height - 1, j))
    k = wp.where(plane == PLANE_NEAR, 0, wp.where(plane == PLANE_FAR, g.depth - 1, k))
    return i, j, k


@inline_func
def entry_face(g: GridInfo, plane: int):
    """The entry face of clip plane ``plane`` as ``(family, boundary index, sign)`` for :func:`face_normal`:
    minus the plane's unit normal is the fine-plane normal of that boundary crossed with that sign."""
    if plane == PLANE_LEFT:
        return FAMILY_U, 0, 1
    if plane == PLANE_RIGHT:
        return FAMILY_U, g.width, -1
    if plane == PLANE_TOP:
        return FAMILY_V, 0, 1
    if plane == PLANE_BOTTOM:
        return FAMILY_V, g.height, -1
    if plane == PLANE_NEAR:
        return FAMILY_Z, 0, 1
    if plane == PLANE_FAR:
        return FAMILY_Z, g.depth, -1
    return NO_FAMILY, 0, 0


# ---------------------------------------------------------------------------------------------- step 3: signs
@inline_func
def sign_of(x: float) -> int:
    """-1, 0 or 1."""
    if x > 0.0:
        return 1
    if x < 0.0:
        return -1
    return 0


@inline_func
def step_signs(o: wp.vec3, d: wp.vec3):
    """Step 3: ``(s_i, s_j, s_k)``, three ints -1, 0 or 1, constant along the ray; 0 means that family is never
    crossed."""
    return sign_of(d[0] * o[2] - d[2] * o[0]), sign_of(d[1] * o[2] - d[2] * o[1]), sign_of(d[2])


# ---------------------------------------------------------------------------------------------- step 4: crossings
@inline_func
def select(family: int, a: Any, b: Any, c: Any):
    """``a``, ``b`` or ``c`` for family u, v or z, without a branch (selects keep the walk free of divergence)."""
    return wp.where(family == FAMILY_U, a, wp.where(family == FAMILY_V, b, c))


@inline_func
def ray_coefficients(g: GridInfo, o: wp.vec3, d: wp.vec3):
    """Step 4's per-ray coefficients (:func:`ray_crossing`) for the families u, v, z (components 0, 1, 2).

    u and v: the plane ``a = w z`` (a = x or y), ``w = w_0 + boundary dw``, is crossed at
    ``t = (w o_z - o_a) / (d_a - w d_z)``; expanded in ``boundary``, ``na = u_0 o_z - o_x``, ``nb = du o_z``,
    ``da = d_x - u_0 d_z``, ``db = -du d_z`` for u, likewise for v. z: ``t = (w - o_z) / d_z``, the same expression
    with ``o_z``, ``d_z`` replaced by 1, 0, which is exact: ``na = z_near - o_z``, ``nb = dz``, ``da = d_z``,
    ``db = 0``. Boundaries come from their index, never accumulated. A walk computes these once per ray; a crossing
    then costs two multiply-adds and one division.

    Returns:
        ``(na, nb, da, db)``, four vec3.
    """
    na = wp.vec3(g.u0 * o[2] - o[0], g.v0 * o[2] - o[1], g.z_near - o[2])
    nb = wp.vec3(g.du * o[2], g.dv * o[2], g.dz)
    da = wp.vec3(d[0] - g.u0 * d[2], d[1] - g.v0 * d[2], d[2])
    db = wp.vec3(-(g.du * d[2]), -(g.dv * d[2]), 0.0)
    return na, nb, da, db


@inline_func
def ray_crossing(na: wp.vec3, nb: wp.vec3, da: wp.vec3, db: wp.vec3, family: int, boundary: int, s: int) -> float:
    """Step 4 from per-ray coefficients (:func:`ray_coefficients`): ``t`` where the ray crosses plane ``boundary``
    of ``family`` moving with sign ``s``; +inf where it never does.

    The crossing exists only where the ray approaches the plane, ``s * den > 0``: for u and v, ``a - w z`` is
    linear in t and must change sign in the direction of motion, else the root lies behind the apex (the ray's u
    converges short of the plane). Every crossing of every Warp walk comes from this one expression, so a plane's
    crossing is bit-identical on every level of the block walk and in ``soft_first_hit``'s walks alike."""
    b = float(boundary)
    num = select(family, na[0], na[1], na[2]) + b * select(family, nb[0], nb[1], nb[2])
    den = select(family, da[0], da[1], da[2]) + b * select(family, db[0], db[1], db[2])
    return wp.where(float(s) * den > 0.0, num / den, wp.inf)


@inline_func
def boundary_behind(index: int, s: int) -> int:
    """The boundary a ray moving with sign ``s`` crossed to enter cell ``index``."""
    return wp.where(s > 0, index, index + 1)


@inline_func
def pick_family(tu: float, tv: float, tz: float) -> int:
    """Step 5: the family with the smallest next crossing, ties in the order u, v, z."""
    return wp.where(tu <= wp.min(tv, tz), FAMILY_U, wp.where(tv <= tz, FAMILY_V, FAMILY_Z))


@inline_func
def set_family(f: int, index: int, t_next: float, i: int, j: int, k: int, cu: float, cv: float, cz: float):
    """The walk's per-family state ``(i, j, k, cu, cv, cz)`` with family ``f``'s cell index set to ``index`` and its
    next crossing to ``t_next`` (selects, no branch: the rays of a warp step different families)."""
    return (
        wp.where(f == FAMILY_U, index, i),
        wp.where(f == FAMILY_V, index, j),
        wp.where(f == FAMILY_Z, index, k),
        wp.where(f == FAMILY_U, t_next, cu),
        wp.where(f == FAMILY_V, t_next, cv),
        wp.where(f == FAMILY_Z, t_next, cz),
    )


@inline_func
def precedes(t_a: float, family_a: int, t_b: float, family_b: int) -> bool:
    """Whether the plain loop takes crossing ``(t_a, family_a)`` before ``(t_b, family_b)``."""
    return t_a < t_b or (t_a == t_b and family_a < family_b)


@inline_func
def box_boundary(index: int, s: int, shift: int, n: int) -> int:
    """The cell boundary in front of the box (``2^shift`` cells per box, ``n`` cells on the axis) that holds cell
    ``index``, moving with sign ``s``; shift 0 gives step 4's boundary ahead of a cell, ``index + (s > 0)``."""
    return wp.where(s > 0, wp.min(((index >> shift) + 1) << shift, n), (index >> shift) << shift)


@inline_func
def next_box(index: int, s: int, shift: int) -> int:
    """The first cell a ray moving with sign ``s`` enters in the box after the one holding cell ``index``."""
    return wp.where(s > 0, ((index >> shift) + 1) << shift, ((index >> shift) << shift) - 1)


@inline_func
def last_in_box(index: int, s: int, shift: int, n: int) -> int:
    """The last cell, moving with sign ``s``, of the box (``2^shift`` cells) that holds cell ``index``."""
    return wp.where(s > 0, wp.min(((index >> shift) + 1) << shift, n) - 1, (index >> shift) << shift)


@inline_func
def level_shift(level: int) -> int:
    """log2 of a level's box edge in cells: 0 for cells, then blocks, then super-blocks."""
    return wp.where(level == 0, 0, wp.where(level == 1, BLOCK_SHIFT, SUPER_SHIFT))


@inline_func
def box_flag(
    labels: wp.array2d(dtype=wp.uint8),
    pyramid: wp.array2d(dtype=wp.uint8),
    b: int,
    g: GridInfo,
    level: int,
    i: int,
    j: int,
    k: int,
) -> int:
    """The label of cell ``(k, j, i)`` (level 0), or the flag of the block (1) or super-block (2) holding it;
    nonzero where occupied. One expression for every level, both arrays read (no branch: the rays of a warp stand
    on different levels)."""
    shift = level_shift(level)
    nv = wp.where(level == 1, g.blocks_v, g.supers_v)
    nu = wp.where(level == 1, g.blocks_u, g.supers_u)
    flat = wp.where(level == 2, g.supers_offset, 0) + ((k >> shift) * nv + (j >> shift)) * nu + (i >> shift)
    cell = int(labels[b, (k * g.height + j) * g.width + i])
    box = int(pyramid[b, wp.where(level == 0, 0, flat)])
    return wp.where(level == 0, cell, box)


@inline_func
def catch_up(
    na: wp.vec3,
    nb: wp.vec3,
    da: wp.vec3,
    db: wp.vec3,
    family: int,
    index: int,
    s: int,
    shift: int,
    n: int,
    t_next: float,
    t: float,
    f: int,
):
    """Advance one family on a level (boxes of ``2^shift`` cells; ``index`` a cell of the current box, ``t_next``
    the crossing of its far side) past every crossing of that level the plain loop takes before crossing
    ``(t, f)``, without leaving the parent box (``2^(shift + 2)`` cells) just entered. The stepped family itself
    (``family == f``) and a walk that has not stepped yet (``f < 0``) stay: the loop runs no iteration for them, so
    every family's call is unconditional (no branch around it).

    Returns:
        The new ``(index, t_next)``: the first cell of the box reached (or ``index`` unchanged), and its crossing.
    """
    last = wp.where(f >= 0 and f != family, last_in_box(index, s, shift + PARENT_SHIFT, n) >> shift, index >> shift)
    while (index >> shift) != last and precedes(t_next, family, t, f):
        index = next_box(index, s, shift)
        t_next = ray_crossing(na, nb, da, db, family, box_boundary(index, s, shift, n), s)
    return index, t_next


# ---------------------------------------------------------------------------------------------- the walk
# Every Warp walk is made of these pieces: trace_ray (cells, blocks, super-blocks, forwards) and soft_first_hit's
# forward (every cell, forwards) and backward (every cell, backwards through its step tape). Written once, they
# give the walks the same cells at the same crossings, bit for bit.
@inline_func
def box_crossings(
    na: wp.vec3, nb: wp.vec3, da: wp.vec3, db: wp.vec3, g: GridInfo, shift: int, si: int, sj: int, sk: int, i: int,
    j: int, k: int
):
    """Step 4 on a level of boxes of ``2^shift`` cells (0: cells): each family's next crossing, the far side of
    the box holding cell ``(i, j, k)``.

    Returns:
        ``(cu, cv, cz)``.
    """
    cu = ray_crossing(na, nb, da, db, FAMILY_U, box_boundary(i, si, shift, g.width), si)
    cv = ray_crossing(na, nb, da, db, FAMILY_V, box_boundary(j, sj, shift, g.height), sj)
    cz = ray_crossing(na, nb, da, db, FAMILY_Z, box_boundary(k, sk, shift, g.depth), sk)
    return cu, cv, cz


@inline_func
def start_walk(g: GridInfo, o: wp.vec3, d: wp.vec3, t_lo: float, plane: int, shift: int):
    """Steps 2-4 for a ray clipped by :func:`clip_ray` (``t_lo < t_hi``, entering through ``plane``): the walk's
    start on the level of boxes of ``2^shift`` cells.

    Returns:
        ``(i, j, k, si, sj, sk, na, nb, da, db, cu, cv, cz)``: the entry cell, the step signs, the per-ray
        coefficients of :func:`ray_coefficients` and each family's next crossing (:func:`box_crossings`).
    """
    i, j, k = entry_cell(g, o, d, t_lo, plane)
    si, sj, sk = step_signs(o, d)
    na, nb, da, db = ray_coefficients(g, o, d)
    cu, cv, cz = box_crossings(na, nb, da, db, g, shift, si, sj, sk, i, j, k)
    return i, j, k, si, sj, sk, na, nb, da, db, cu, cv, cz


@inline_func
def pick_step(
    g: GridInfo, shift: int, si: int, sj: int, sk: int, i: int, j: int, k: int, cu: float, cv: float, cz: float
):
    """Step 5's choice, on a level of boxes of ``2^shift`` cells: the next step of the walk standing in cell
    ``(i, j, k)`` of its current box, with next crossings ``cu, cv, cz``.

    The stepped family's values are picked with selects, not a branch per family: the rays of a warp step
    different families, and three branches would run one after another.

    Returns:
        ``(f, t, sf, nf, old, new)``: the family with the nearest crossing (ties in the order u, v, z), that
        crossing, the family's sign and cell count, and its cell index before the step and after it (the first
        cell of the next box). The walk ends instead where ``t >= t_hi`` (past the clipped segment) or ``new``
        leaves ``[0, nf)``: the caller tests that in its ``if``. (Returned from here as a bool, the test made
        :func:`trace_ray` compile to other code than the code measured on the H100; see PERF_NOTES.md.)
    """
    f = pick_family(cu, cv, cz)
    t = wp.min(cu, wp.min(cv, cz))  # select(f, cu, cv, cz), without waiting for f
    sf = select(f, si, sj, sk)
    nf = select(f, g.width, g.height, g.depth)
    old = select(f, i, j, k)
    return f, t, sf, nf, old, next_box(old, sf, shift)


@inline_func
def take_step(
    na: wp.vec3, nb: wp.vec3, da: wp.vec3, db: wp.vec3, shift: int, f: int, sf: int, nf: int, new: int, i: int, j: int,
    k: int, cu: float, cv: float, cz: float
):
    """Step 5's step, as :func:`pick_step` chose it: family ``f``'s cell index becomes ``new`` and its next
    crossing the far side of ``new``'s box.

    Returns:
        The walk's new ``(i, j, k, cu, cv, cz)``.
    """
    t_next = ray_crossing(na, nb, da, db, f, box_boundary(new, sf, shift, nf), sf)
    return set_family(f, new, t_next, i, j, k, cu, cv, cz)


@inline_func
def entered_through(f: int, si: int, sj: int, sk: int, i: int, j: int, k: int):
    """The face through which a walk's step of family ``f`` entered cell ``(i, j, k)``.

    Returns:
        ``(boundary, sf)``: the crossed plane's index in family ``f`` and the family's step sign.
    """
    sf = select(f, si, sj, sk)
    return boundary_behind(select(f, i, j, k), sf), sf


@inline_func
def step_back(
    na: wp.vec3, nb: wp.vec3, da: wp.vec3, db: wp.vec3, f: int, si: int, sj: int, sk: int, i: int, j: int, k: int
):
    """Undo a cell step of family ``f`` that entered cell ``(i, j, k)``: where the walk entered the cell, and the
    cell it came from (the walk backwards through a step tape, each crossing the same expression as forwards).

    Returns:
        ``(t, i, j, k)``: the crossing at which the step entered cell ``(i, j, k)``, and the cell before it.
    """
    boundary, sf = entered_through(f, si, sj, sk, i, j, k)
    t = ray_crossing(na, nb, da, db, f, boundary, sf)
    return t, wp.where(f == FAMILY_U, i - sf, i), wp.where(f == FAMILY_V, j - sf, j), wp.where(f == FAMILY_Z, k - sf, k)


# ---------------------------------------------------------------------------------------------- step 5: the loop
@inline_func
def trace_ray(
    labels: wp.array2d(dtype=wp.uint8),
    pyramid: wp.array2d(dtype=wp.uint8),
    b: int,
    g: GridInfo,
    o: wp.vec3,
    d: wp.vec3,
):
    """Steps 1-5 with empty-space skipping: the first occupied cell along the ray ``o + t d`` in batch item ``b``.

    One walk on three levels (cells, blocks, super-blocks), with one state per family: the cell index ``i, j, k``
    and the next crossing ``cu, cv, cz`` of the far side of the current box on the current level. Crossings come
    from the ray's coefficients (:func:`ray_coefficients`), computed once. A step on a
    level moves the stepped family's cell index to the first cell of the next box, which is where the plain loop
    stands at that crossing; the other families' cell indices lie in their current boxes but may lag inside them,
    until a descent catches them up (see the module docstring). After each step the walk goes up while the step
    entered an empty parent box, and down (catching up) while the current box is occupied; on the cell level an
    occupied cell is the hit. Every walk ends: each step moves one index one way, and leaving the index range or
    the clipped segment is a miss.

    Args:
        labels: ``(B, D * H * W)`` uint8 labels, flat cell index ``(k * H + j) * W + i``; 0 = empty.
        pyramid: ``(B, bd * bh * bw + sd * sh * sw)`` uint8: block flags (:func:`pyramid_shape`, flat
            ``(bk * bh + bj) * bw + bi``), then super-block flags (:func:`supers_shape`, flat likewise) from
            ``g.supers_offset``; nonzero where the box holds an occupied cell.
        b: batch item.
        g: the grid.
        o: ray origin, grid frame.
        d: ray direction, grid frame, unnormalised.

    Returns:
        ``(cell, t, family, boundary, sign)``: the flat index of the hit cell (-1 on a miss), the ``t`` where the
        ray enters it, and its entry face for :func:`face_normal` (``NO_FAMILY`` when the ray starts inside it).
        The entry face is the last step's crossing, read off at the end rather than kept up to date in the loop:
        descents never move the stepped family's index.
    """
    t_lo, t_hi, plane = clip_ray(g, o, d)
    if t_lo >= t_hi:
        return wp.int32(-1), wp.float32(0.0), int(NO_FAMILY), wp.int32(0), wp.int32(0)
    # Start on the super-block level; the first pass of the loop descends as far as the boxes are occupied.
    i, j, k, si, sj, sk, na, nb, da, db, cu, cv, cz = start_walk(g, o, d, t_lo, plane, SUPER_SHIFT)
    level = int(LEVEL_SUPERS)
    shift = int(SUPER_SHIFT)
    t = t_lo
    f = int(NO_FAMILY)
    cell = wp.int32(-1)
    while True:
        if box_flag(labels, pyramid, b, g, level, i, j, k) != 0:
            if level == 0:
                cell = (k * g.height + j) * g.width + i
                break
            # Down one level at the last crossing (t, f): the stepped family stands at its box's first cell,
            # the others catch up inside the box just entered. Then look at the new box again.
            level -= 1
            shift = level_shift(level)
            cu, cv, cz = box_crossings(na, nb, da, db, g, shift, si, sj, sk, i, j, k)
            i, cu = catch_up(na, nb, da, db, FAMILY_U, i, si, shift, g.width, cu, t, f)
            j, cv = catch_up(na, nb, da, db, FAMILY_V, j, sj, shift, g.height, cv, t, f)
            k, cz = catch_up(na, nb, da, db, FAMILY_Z, k, sk, shift, g.depth, cz, t, f)
            continue

        # One step on the current level: across an empty box, or (level 0) to the next cell.
        f, t, sf, nf, old, new = pick_step(g, shift, si, sj, sk, i, j, k, cu, cv, cz)
        if t >= t_hi or new < 0 or new >= nf:
            break
        i, j, k, cu, cv, cz = take_step(na, nb, da, db, shift, f, sf, nf, new, i, j, k, cu, cv, cz)
        # Up while the step entered an empty parent box (a parent that did not change is still occupied).
        while level < LEVEL_SUPERS:
            up = level_shift(level + 1)
            parent_occupied = box_flag(labels, pyramid, b, g, level + 1, i, j, k) != 0
            if (old >> up) == (new >> up) or parent_occupied:
                break
            level += 1
            shift = up
            cu, cv, cz = box_crossings(na, nb, da, db, g, shift, si, sj, sk, i, j, k)
    if f < 0:
        ef, eb, es = entry_face(g, plane)
        return cell, t_lo, ef, eb, es
    eb, es = entered_through(f, si, sj, sk, i, j, k)
    return cell, t, f, eb, es


@inline_func
def face_normal(g: GridInfo, family: int, boundary: int, s: int, d: wp.vec3) -> wp.vec3:
    """Unit normal of an entry face, grid frame, facing the camera (``dot(n, d) < 0``).

    u-plane ``u``: ``-s (1, 0, -u) / |.|``; v-plane: ``-s (0, 1, -v) / |.|``; z-plane: ``(0, 0, -s)``; a ray that
    starts inside its hit cell (``NO_FAMILY``): ``-d / |d|``.
    """
    if family == FAMILY_U:
        w = g.u0 + float(boundary) * g.du
        return -float(s) * wp.normalize(wp.vec3(1.0, 0.0, -w))
    if family == FAMILY_V:
        w = g.v0 + float(boundary) * g.dv
        return -float(s) * wp.normalize(wp.vec3(0.0, 1.0, -w))
    if family == FAMILY_Z:
        return wp.vec3(0.0, 0.0, -float(s))
    return -wp.normalize(d)

"""Warp kernels of ``fruxelize``: mark cell centres with the latest mesh whose solid contains them, then label each
cell by that mesh.

The algorithm, the inside rules and the priority are documented in :mod:`fruxel.kernels.fruxelize`; this module
uploads the parts built there and runs a marking kernel, then :func:`resolve_labels_kernel`. Both marking kernels
walk one part along one column with :func:`mark_part_column`: on a GPU :func:`mark_part_columns_kernel`, one thread
a (part, column) pair, since at 64^3 one thread a column is 4,096 threads, too few to fill a GPU, and a column's
parts are independent (the atomic maximum keeps the latest mesh whatever order they are walked in); on the CPU,
where Warp runs threads one after another, :func:`mark_columns_kernel`, one thread a column looping over the parts
of the meshes its ray meets. Works on Warp's CPU and CUDA devices.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from ..fruxelize import MAX_CROSSINGS, MeshParts
from .runtime import resolve_device, warp

wp = warp()
wp.set_module_options({"enable_backward": False})

_Crossings = wp.types.vector(length=MAX_CROSSINGS, dtype=wp.float32)

# Three unit directions with no two components equal and none along an axis: the parity vote must not run
# along the faces or edges of axis-aligned boxes, which is where a single parity ray is most often wrong.
VOTE_DIR_A = wp.constant(wp.vec3(0.26726124, 0.53452248, 0.80178373))
VOTE_DIR_B = wp.constant(wp.vec3(-0.71066905, 0.16929599, 0.68282553))
VOTE_DIR_C = wp.constant(wp.vec3(0.40114076, -0.89136752, 0.21110468))
BIG = wp.constant(1.0e30)
MAX_HITS = wp.constant(MAX_CROSSINGS)


@wp.func
def slab_interval(o: wp.vec3, d: wp.vec3, lo: wp.vec3, hi: wp.vec3) -> wp.vec2:
    """Parameter interval ``(t0, t1)`` of the line ``o + t d`` inside the box ``[lo, hi]``; ``t0 > t1`` when the
    line misses it. ``t`` ranges over the whole line, negative values included."""
    t0 = float(-BIG)
    t1 = float(BIG)
    for a in range(3):
        if wp.abs(d[a]) < 1.0e-20:
            if o[a] < lo[a] or o[a] > hi[a]:
                return wp.vec2(1.0, -1.0)
        else:
            ta = (lo[a] - o[a]) / d[a]
            tb = (hi[a] - o[a]) / d[a]
            t0 = wp.max(t0, wp.min(ta, tb))
            t1 = wp.min(t1, wp.max(ta, tb))
    return wp.vec2(t0, t1)


@wp.func
def parity_inside(mesh: wp.uint64, root: int, p: wp.vec3) -> bool:
    """Majority vote of crossing parity along three skew directions from ``p``, confined to one BVH group."""
    votes = int(0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    votes += wp.mesh_query_ray_count_intersections(mesh, p, VOTE_DIR_A, root) % 2
    votes += wp.mesh_query_ray_count_intersections(mesh, p, VOTE_DIR_B, root) % 2
    votes += wp.mesh_query_ray_count_intersections(mesh, p, VOTE_DIR_C, root) % 2
    return votes >= 2


@wp.func
def winding_inside(mesh: wp.uint64, p: wp.vec3) -> bool:
    """Generalised winding number of an open part at ``p`` is >= 1/2 (the mesh has winding-number support)."""
    q = wp.mesh_query_point_sign_winding_number(mesh, p, 1.0e6, 2.0, 0.5)
    return q.result and q.sign < 0.0


@wp.struct
class Parts:
    """A :class:`WarpMeshSet`'s parts and meshes as the marking kernels read them (world frame)."""

    closed_mesh: wp.uint64
    """The grouped BVH of every closed part (group = part index); 0 when there is none."""
    open_meshes: wp.array(dtype=wp.uint64)
    """``(O,)`` ids of the open parts' meshes (built with winding-number support)."""
    kind: wp.array(dtype=wp.int32)
    """``(P,)`` 0 closed, 1 open."""
    ref: wp.array(dtype=wp.int32)
    """``(P,)`` the part's group in ``closed_mesh`` or its index in ``open_meshes``."""
    rank: wp.array(dtype=wp.int32)
    """``(P,)`` its mesh's index + 1."""
    lo: wp.array(dtype=wp.vec3)
    """``(P,)`` padded box corner, low."""
    hi: wp.array(dtype=wp.vec3)
    """``(P,)`` padded box corner, high."""
    mesh_first_part: wp.array(dtype=wp.int32)
    """``(M + 1,)`` mesh ``m``'s parts are ``mesh_first_part[m]:mesh_first_part[m + 1]``."""
    mesh_lo: wp.array(dtype=wp.vec3)
    """``(M,)`` padded box corner of each mesh, low."""
    mesh_hi: wp.array(dtype=wp.vec3)
    """``(M,)`` padded box corner of each mesh, high."""


@wp.struct
class Columns:
    """The grid's column rays: column ``(j, i)``'s centre ray is ``origin + t R (u0 + (i + 1/2) du, v0 + (j + 1/2)
    dv, 1)``, world frame, and its cell ``k``'s centre lies at ``t = zc0 + k dz``."""

    rot: wp.mat33
    """Grid-camera-to-world rotation ``R``."""
    origin: wp.vec3
    """Grid camera centre, world frame."""
    u0: float
    """``-tu``: the grid's left edge on the image plane z = 1."""
    du: float
    """Column width on that plane."""
    v0: float
    """``-tv``: its top edge."""
    dv: float
    """Row height."""
    zc0: float
    """Depth of the first cell centre, ``z_near + dz / 2``."""
    dz: float
    """Slice thickness."""
    depth: int
    """Cells a column (D)."""


@wp.func
def column_ray(c: Columns, j: int, i: int) -> wp.vec3:
    """World-frame direction ``R (u_c, v_c, 1)`` of grid column ``(j, i)``'s centre ray (``t`` is its depth)."""
    return c.rot * wp.vec3(c.u0 + (float(i) + 0.5) * c.du, c.v0 + (float(j) + 0.5) * c.dv, 1.0)


@wp.func
def first_cell(c: Columns, t: float) -> int:
    """The first cell whose centre lies at depth ``t`` or beyond (may be ``depth``: none)."""
    return int(wp.ceil(wp.clamp((t - c.zc0) / c.dz, -1.0, float(c.depth))))


@wp.func
def last_cell(c: Columns, t: float) -> int:
    """The last cell whose centre lies at depth ``t`` or before (may be -1: none)."""
    return int(wp.floor(wp.clamp((t - c.zc0) / c.dz, -1.0, float(c.depth))))


@wp.func
def mark_open_piece(mesh: wp.uint64, c: Columns, d: wp.vec3, ka: int, kb: int, lazy: int, rank: int,
                    ranks: wp.array3d(dtype=wp.int32), j: int, i: int):
    """Mark centres ``ka..kb`` of column ``(j, i)`` (direction ``d``) inside an open part (by its winding number)
    with ``rank``.

    With ``lazy`` set, the centres lie on one piece of the ray between two consecutive crossings of the part's
    surface, where the winding number is smooth: when it falls on the same side of 1/2 at the first, middle and
    last centre, the whole piece takes that side; otherwise every centre is evaluated.
    """
    if lazy != 0 and kb - ka >= 2:
        a = winding_inside(mesh, c.origin + (c.zc0 + float(ka) * c.dz) * d)
        b = winding_inside(mesh, c.origin + (c.zc0 + float((ka + kb) // 2) * c.dz) * d)
        e = winding_inside(mesh, c.origin + (c.zc0 + float(kb) * c.dz) * d)
        if a == b and b == e:
            if a:
                for k in range(ka, kb + 1):
                    wp.atomic_max(ranks, k, j, i, rank)
            return
    for k in range(ka, kb + 1):
        if winding_inside(mesh, c.origin + (c.zc0 + float(k) * c.dz) * d):
            wp.atomic_max(ranks, k, j, i, rank)


@wp.func
def mark_open_part(mesh: wp.uint64, c: Columns, d: wp.vec3, t_lo: float, t_hi: float, k0: int, k1: int,
                   ts: _Crossings, n: int, overflow: int, rank: int, ranks: wp.array3d(dtype=wp.int32), j: int,
                   i: int):
    """Mark the centres ``k0..k1`` of column ``(j, i)`` inside an open part, piece by piece between its ``n``
    crossings ``ts`` of the ray within ``[t_lo, t_hi]`` (every centre evaluated when the walk overflowed)."""
    if overflow != 0:
        mark_open_piece(mesh, c, d, k0, k1, 0, rank, ranks, j, i)
        return
    ta = t_lo
    for mm in range(n + 1):
        tb = t_hi
        if mm < n:
            tb = ts[mm]
        ka = wp.max(k0, first_cell(c, ta))
        kb = wp.min(k1, last_cell(c, tb))
        if ka <= kb:
            mark_open_piece(mesh, c, d, ka, kb, 1, rank, ranks, j, i)
        ta = tb


@wp.func
def mark_closed_part(mesh: wp.uint64, root: int, c: Columns, d: wp.vec3, k0: int, k1: int, ts: _Crossings,
                     ws: _Crossings, n: int, total: float, overflow: int, rank: int,
                     ranks: wp.array3d(dtype=wp.int32), fallbacks: wp.array(dtype=wp.int32), j: int, i: int):
    """Mark the centres ``k0..k1`` of column ``(j, i)`` inside a closed part from its ``n`` crossings ``ts`` with
    signs ``ws`` (summing to ``total``): inside where the crossings before a centre sum to non-zero. A walk that
    overflowed or does not sum to zero (a part that is not watertight along this ray) falls back to the parity vote
    at each centre, counted in ``fallbacks[0]``."""
    if overflow != 0 or total != 0.0:
        wp.atomic_add(fallbacks, 0, 1)
        for k in range(k0, k1 + 1):
            if parity_inside(mesh, root, c.origin + (c.zc0 + float(k) * c.dz) * d):
                wp.atomic_max(ranks, k, j, i, rank)
        return
    w = float(0.0)  # noqa: UP018 - Warp: a variable a loop mutates is declared dynamic
    mi = int(0)  # noqa: UP018
    for k in range(k0, k1 + 1):
        tc = c.zc0 + float(k) * c.dz
        while mi < n and ts[mi] < tc:
            w += ws[mi]
            mi += 1
        if w != 0.0:
            wp.atomic_max(ranks, k, j, i, rank)


@wp.func
def mark_part_column(parts: Parts, p: int, rank: int, c: Columns, d: wp.vec3, ranks: wp.array3d(dtype=wp.int32),
                     fallbacks: wp.array(dtype=wp.int32), j: int, i: int):
    """Raise the cells of column ``(j, i)`` (direction ``d``) whose centres lie inside part ``p`` to ``rank`` (an
    atomic maximum), walking the part's crossings of the ray; count a closed part's fall back to the parity vote in
    ``fallbacks[0]``. Arrays as :func:`mark_part_columns_kernel`'s."""
    seg = slab_interval(c.origin, d, parts.lo[p], parts.hi[p])
    t_lo = seg[0]
    t_hi = seg[1]
    if t_lo > t_hi:
        return
    k0 = wp.max(0, first_cell(c, t_lo))
    k1 = wp.min(c.depth - 1, last_cell(c, t_hi))
    if k0 > k1:
        return
    kind = parts.kind[p]
    mesh = parts.closed_mesh
    root = int(-1)  # noqa: UP018 - Warp: declared dynamic, reassigned below
    if kind == 1:
        mesh = parts.open_meshes[parts.ref[p]]
    else:
        root = wp.mesh_get_group_root(parts.closed_mesh, parts.ref[p])
    # The walk starts on the padded box, outside the part, where the winding number is 0. Hits closer than eps to
    # the previous one are the same crossing reported by two triangles sharing an edge.
    eps = 1.0e-5 * (1.0 + wp.max(wp.abs(t_lo), wp.abs(t_hi)))
    ts = _Crossings()
    ws = _Crossings()
    n = int(0)  # noqa: UP018 - Warp: a variable a loop mutates is declared dynamic
    total = float(0.0)  # noqa: UP018
    t = t_lo
    overflow = int(0)  # noqa: UP018
    while t < t_hi:
        q = wp.mesh_query_ray(mesh, c.origin + t * d, d, t_hi - t, root)
        if not q.result:
            break
        if n == MAX_HITS:
            overflow = 1
            break
        ts[n] = t + q.t
        ws[n] = wp.where(q.sign > 0.0, 1.0, -1.0)
        total += ws[n]
        n += 1
        t = t + q.t + eps
    if kind == 1:
        mark_open_part(mesh, c, d, t_lo, t_hi, k0, k1, ts, n, overflow, rank, ranks, j, i)
    elif n > 0:
        mark_closed_part(mesh, root, c, d, k0, k1, ts, ws, n, total, overflow, rank, ranks, fallbacks, j, i)


@wp.kernel
def mark_part_columns_kernel(parts: Parts, c: Columns, ranks: wp.array3d(dtype=wp.int32),
                             fallbacks: wp.array(dtype=wp.int32)):
    """One thread marks the cells of grid column ``(j, i)`` whose centres lie inside part ``p`` (the GPU's kernel).

    Launch dims ``(P, H, W)``. Inputs: ``parts`` (:class:`Parts`, world frame), ``c`` the grid's column rays
    (:class:`Columns`). Output: ``ranks`` ``(D, H, W)`` int32, zero on entry, each marked cell raised to the part's
    rank (its mesh's index + 1); ``fallbacks`` ``(1,)`` int32, atomically counts (column, closed part) pairs that
    used the parity vote.
    """
    p, j, i = wp.tid()
    mark_part_column(parts, p, parts.rank[p], c, column_ray(c, j, i), ranks, fallbacks, j, i)


@wp.kernel
def mark_columns_kernel(parts: Parts, c: Columns, ranks: wp.array3d(dtype=wp.int32),
                        fallbacks: wp.array(dtype=wp.int32)):
    """One thread marks the cells of grid column ``(j, i)`` inside every part (the CPU's kernel).

    Launch dims ``(H, W)``. Inputs and outputs as :func:`mark_part_columns_kernel`'s; a mesh whose padded box the
    column's ray misses (``parts.mesh_lo`` / ``mesh_hi``) is skipped with all its parts.
    """
    j, i = wp.tid()
    d = column_ray(c, j, i)
    for m in range(parts.mesh_lo.shape[0]):
        box = slab_interval(c.origin, d, parts.mesh_lo[m], parts.mesh_hi[m])
        if box[0] > box[1] or box[1] < c.zc0 or box[0] > c.zc0 + float(c.depth - 1) * c.dz:
            continue
        for p in range(parts.mesh_first_part[m], parts.mesh_first_part[m + 1]):
            mark_part_column(parts, p, m + 1, c, d, ranks, fallbacks, j, i)


@wp.kernel
def resolve_labels_kernel(
    ranks: wp.array3d(dtype=wp.int32),
    mesh_label: wp.array(dtype=wp.int32),
    labels: wp.array3d(dtype=wp.uint8),
):
    """One thread labels cell ``(k, j, i)`` with the label of the latest mesh that holds its centre.

    Launch dims ``(D, H, W)``. Inputs: ``ranks`` ``(D, H, W)`` int32 (:func:`mark_part_columns_kernel`: a mesh's
    index + 1, 0 where none), ``mesh_label`` ``(M,)`` int32. Output: ``labels`` ``(D, H, W)`` uint8, 0 where no
    mesh holds the centre.
    """
    k, j, i = wp.tid()
    r = ranks[k, j, i]
    if r > 0:
        labels[k, j, i] = wp.uint8(mesh_label[r - 1])


@dataclass
class WarpMeshSet:
    """A :class:`fruxel.kernels.fruxelize.MeshParts` uploaded to one Warp device."""

    device: str
    """Warp device string, e.g. ``"cpu"`` or ``"cuda:0"``."""
    closed: Any
    """``wp.Mesh`` of every closed part, grouped by part (None when there is none)."""
    opened: list[Any]
    """``wp.Mesh`` per open part, with winding-number support; kept here so that their ids stay valid."""
    parts: Any
    """The kernels' :class:`Parts`."""
    mesh_label: Any
    """``(M,)`` int32 ``wp.array``: each mesh's label (0 for a mesh without parts)."""


def build_mesh_set(parts: MeshParts, device: str | None) -> WarpMeshSet:
    """Upload ``parts`` to ``device`` (None: CUDA when present, else the CPU) and build the BVHs."""
    dev = resolve_device(device)

    def vec3s(a: np.ndarray) -> Any:
        return wp.array(np.ascontiguousarray(a, dtype=np.float32).reshape(-1, 3), dtype=wp.vec3, device=dev)

    def ints(a: np.ndarray) -> Any:
        return wp.array(np.ascontiguousarray(a, dtype=np.int32).reshape(-1), dtype=wp.int32, device=dev)

    closed = None
    if len(parts.closed_faces):
        closed = wp.Mesh(points=vec3s(parts.closed_vertices), indices=ints(parts.closed_faces),
                         groups=ints(parts.closed_group), bvh_constructor="median" if dev == "cpu" else None)
    opened = [wp.Mesh(points=vec3s(v), indices=ints(f), support_winding_number=True) for v, f in parts.open_meshes]
    first = np.asarray(parts.mesh_first_part, dtype=np.int64)
    n_meshes = len(first) - 1
    # Every part of a mesh carries the mesh's label; a mesh without parts labels nothing.
    mesh_label = np.zeros(n_meshes, dtype=np.int32)
    has = first[1:] > first[:-1]
    mesh_label[has] = np.asarray(parts.part_label)[first[:-1][has]]
    ps = Parts()
    ps.closed_mesh = wp.uint64(closed.id if closed is not None else 0)
    ps.open_meshes = wp.array(np.array([m.id for m in opened], dtype=np.uint64), dtype=wp.uint64, device=dev)
    ps.kind, ps.ref = ints(parts.part_kind), ints(parts.part_ref)
    ps.rank = ints(np.repeat(np.arange(1, n_meshes + 1), np.diff(first)))
    ps.lo, ps.hi = vec3s(parts.part_lo), vec3s(parts.part_hi)
    ps.mesh_first_part = ints(parts.mesh_first_part)
    ps.mesh_lo, ps.mesh_hi = vec3s(parts.mesh_lo), vec3s(parts.mesh_hi)
    return WarpMeshSet(device=dev, closed=closed, opened=opened, parts=ps, mesh_label=ints(mesh_label))


def columns_of(grid: Any, pose: np.ndarray) -> Any:
    """The :class:`Columns` of ``grid`` at camera-to-world ``pose`` ``(4, 4)`` (float32, as the kernels read it)."""
    c = Columns()
    c.rot = wp.mat33(*np.asarray(pose[:3, :3], dtype=np.float32).reshape(-1))
    c.origin = wp.vec3(*np.asarray(pose[:3, 3], dtype=np.float32))
    c.u0, c.du, c.v0, c.dv = float(-grid.tu), float(grid.du), float(-grid.tv), float(grid.dv)
    # In float32, as the kernels once added it on the device: the centres' depths stay those of earlier labels.
    c.zc0 = float(np.float32(grid.z_near) + np.float32(0.5) * np.float32(grid.dz))
    c.dz, c.depth = float(grid.dz), int(grid.depth)
    return c


def fruxelize(mesh_set: WarpMeshSet, grid: Any, pose: np.ndarray, pairs: bool | None = None) -> tuple[np.ndarray, int]:
    """Run the device's marking kernel (:func:`mark_part_columns_kernel` on CUDA, :func:`mark_columns_kernel` on the
    CPU) and :func:`resolve_labels_kernel` for one grid pose.

    Args:
        mesh_set: the uploaded meshes.
        grid: the :class:`fruxel.FruxelGrid`.
        pose: ``(4, 4)`` float64 validated grid-camera-to-world transform.
        pairs: one thread a (part, column) pair (True) or a column (False); None: pairs on CUDA only.

    Returns:
        labels ``(D, H, W)`` uint8 numpy, and the number of (column, closed part) pairs that fell back to the
        parity vote.
    """
    dev = mesh_set.device
    pairs = dev.startswith("cuda") if pairs is None else pairs
    labels = wp.zeros(grid.shape, dtype=wp.uint8, device=dev)
    ranks = wp.zeros(grid.shape, dtype=wp.int32, device=dev)
    fallbacks = wp.zeros(1, dtype=wp.int32, device=dev)
    n_parts = mesh_set.parts.kind.shape[0]
    if n_parts:
        kernel, dim = ((mark_part_columns_kernel, (n_parts, grid.height, grid.width)) if pairs
                       else (mark_columns_kernel, (grid.height, grid.width)))
        wp.launch(kernel, dim=dim, inputs=[mesh_set.parts, columns_of(grid, pose)], outputs=[ranks, fallbacks],
                  device=dev)
        wp.launch(resolve_labels_kernel, dim=grid.shape, inputs=[ranks, mesh_set.mesh_label], outputs=[labels],
                  device=dev)
    # .numpy() synchronises with the device: the labels are the result, the counter only a diagnostic.
    return labels.numpy(), int(fallbacks.numpy()[0])

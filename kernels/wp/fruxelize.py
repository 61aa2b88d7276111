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


@wp.func
def mark_open_piece(
    mesh: wp.uint64,
    origin: wp.vec3,
    d: wp.vec3,
    zc0: float,
    dz: float,
    ka: int,
    kb: int,
    lazy: int,
    rank: int,
    ranks: wp.array3d(dtype=wp.int32),
    j: int,
    i: int,
):
    """Mark centres ``ka..kb`` of column ``(j, i)`` inside an open part (by its winding number) with ``rank``.

    With ``lazy`` set, the centres lie on one piece of the ray between two consecutive crossings of the part's
    surface, where the winding number is smooth: when it falls on the same side of 1/2 at the first, middle and
    last centre, the whole piece takes that side; otherwise every centre is evaluated.
    """
    if lazy != 0 and kb - ka >= 2:
        a = winding_inside(mesh, origin + (zc0 + float(ka) * dz) * d)
        b = winding_inside(mesh, origin + (zc0 + float((ka + kb) // 2) * dz) * d)
        c = winding_inside(mesh, origin + (zc0 + float(kb) * dz) * d)
        if a == b and b == c:
            if a:
                for k in range(ka, kb + 1):
                    wp.atomic_max(ranks, k, j, i, rank)
            return
    for k in range(ka, kb + 1):
        if winding_inside(mesh, origin + (zc0 + float(k) * dz) * d):
            wp.atomic_max(ranks, k, j, i, rank)


@wp.func
def mark_part_column(
    closed_mesh: wp.uint64,
    open_meshes: wp.array(dtype=wp.uint64),
    part_kind: wp.array(dtype=wp.int32),
    part_ref: wp.array(dtype=wp.int32),
    part_lo: wp.array(dtype=wp.vec3),
    part_hi: wp.array(dtype=wp.vec3),
    p: int,
    rank: int,
    origin: wp.vec3,
    d: wp.vec3,
    zc0: float,
    dz: float,
    depth: int,
    ranks: wp.array3d(dtype=wp.int32),
    fallbacks: wp.array(dtype=wp.int32),
    j: int,
    i: int,
):
    """Raise the cells of column ``(j, i)`` (ray ``origin + t d``, world frame) whose centres lie inside part ``p``
    to ``rank`` (an atomic maximum), walking the part's crossings; count a closed part's fall back to the parity
    vote in ``fallbacks[0]``. Arrays as :func:`mark_part_columns_kernel`'s."""
    seg = slab_interval(origin, d, part_lo[p], part_hi[p])
    t_lo = seg[0]
    t_hi = seg[1]
    if t_lo > t_hi:
        return
    k0 = wp.max(0, int(wp.ceil(wp.clamp((t_lo - zc0) / dz, -1.0, float(depth)))))
    k1 = wp.min(depth - 1, int(wp.floor(wp.clamp((t_hi - zc0) / dz, -1.0, float(depth)))))
    if k0 > k1:
        return
    kind = part_kind[p]
    mesh = closed_mesh
    root = int(-1)  # noqa: UP018 - Warp: declared dynamic, reassigned below
    if kind == 1:
        mesh = open_meshes[part_ref[p]]
    else:
        root = wp.mesh_get_group_root(closed_mesh, part_ref[p])
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
        q = wp.mesh_query_ray(mesh, origin + t * d, d, t_hi - t, root)
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
        if overflow != 0:
            mark_open_piece(mesh, origin, d, zc0, dz, k0, k1, 0, rank, ranks, j, i)
            return
        ta = t_lo
        for mm in range(n + 1):
            tb = t_hi
            if mm < n:
                tb = ts[mm]
            ka = wp.max(k0, int(wp.ceil(wp.clamp((ta - zc0) / dz, -1.0, float(depth)))))
            kb = wp.min(k1, int(wp.floor(wp.clamp((tb - zc0) / dz, -1.0, float(depth)))))
            if ka <= kb:
                mark_open_piece(mesh, origin, d, zc0, dz, ka, kb, 1, rank, ranks, j, i)
            ta = tb
        return
    if n == 0:
        return
    if overflow != 0 or total != 0.0:
        wp.atomic_add(fallbacks, 0, 1)
        for k in range(k0, k1 + 1):
            c = origin + (zc0 + float(k) * dz) * d
            if parity_inside(closed_mesh, root, c):
                wp.atomic_max(ranks, k, j, i, rank)
        return
    w = float(0.0)  # noqa: UP018
    mi = int(0)  # noqa: UP018
    for k in range(k0, k1 + 1):
        tc = zc0 + float(k) * dz
        while mi < n and ts[mi] < tc:
            w += ws[mi]
            mi += 1
        if w != 0.0:
            wp.atomic_max(ranks, k, j, i, rank)


@wp.func
def column_ray(rot: wp.mat33, u0: float, du: float, v0: float, dv: float, j: int, i: int) -> wp.vec3:
    """World-frame direction ``R (u_c, v_c, 1)`` of grid column ``(j, i)``'s centre ray (``t`` is its depth)."""
    return rot * wp.vec3(u0 + (float(i) + 0.5) * du, v0 + (float(j) + 0.5) * dv, 1.0)


@wp.kernel
def mark_part_columns_kernel(
    closed_mesh: wp.uint64,
    open_meshes: wp.array(dtype=wp.uint64),
    part_kind: wp.array(dtype=wp.int32),
    part_ref: wp.array(dtype=wp.int32),
    part_rank: wp.array(dtype=wp.int32),
    part_lo: wp.array(dtype=wp.vec3),
    part_hi: wp.array(dtype=wp.vec3),
    rot: wp.mat33,
    origin: wp.vec3,
    u0: float,
    du: float,
    v0: float,
    dv: float,
    z_near: float,
    dz: float,
    depth: int,
    ranks: wp.array3d(dtype=wp.int32),
    fallbacks: wp.array(dtype=wp.int32),
):
    """One thread marks the cells of grid column ``(j, i)`` whose centres lie inside part ``p`` (the GPU's kernel).

    Launch dims ``(P, H, W)``. Inputs: ``closed_mesh`` the grouped BVH of every closed part (group = part index),
    ``open_meshes`` ``(O,)`` ids of the open parts' meshes (built with winding-number support); part arrays
    ``(P,)`` (kind 0 closed / 1 open, ref = group or open index, rank = its mesh's index + 1, padded box corners
    ``vec3``, world frame); ``rot`` / ``origin`` the grid camera's camera-to-world rotation and centre; grid
    constants (``u0 = -tu``, ``v0 = -tv``). Output: ``ranks`` ``(D, H, W)`` int32, zero on entry, each marked cell
    raised to the part's rank; ``fallbacks`` ``(1,)`` int32, atomically counts (column, closed part) pairs that
    used the parity vote.
    """
    p, j, i = wp.tid()
    d = column_ray(rot, u0, du, v0, dv, j, i)
    mark_part_column(closed_mesh, open_meshes, part_kind, part_ref, part_lo, part_hi, p, part_rank[p], origin, d,
                     z_near + 0.5 * dz, dz, depth, ranks, fallbacks, j, i)


@wp.kernel
def mark_columns_kernel(
    closed_mesh: wp.uint64,
    open_meshes: wp.array(dtype=wp.uint64),
    part_kind: wp.array(dtype=wp.int32),
    part_ref: wp.array(dtype=wp.int32),
    part_lo: wp.array(dtype=wp.vec3),
    part_hi: wp.array(dtype=wp.vec3),
    mesh_first_part: wp.array(dtype=wp.int32),
    mesh_lo: wp.array(dtype=wp.vec3),
    mesh_hi: wp.array(dtype=wp.vec3),
    rot: wp.mat33,
    origin: wp.vec3,
    u0: float,
    du: float,
    v0: float,
    dv: float,
    z_near: float,
    dz: float,
    depth: int,
    ranks: wp.array3d(dtype=wp.int32),
    fallbacks: wp.array(dtype=wp.int32),
):
    """One thread marks the cells of grid column ``(j, i)`` inside every part (the CPU's kernel).

    Launch dims ``(H, W)``. Inputs as :func:`mark_part_columns_kernel`'s but for the ranks, which are the meshes'
    indices + 1, and the meshes' arrays: ``mesh_first_part`` ``(M + 1,)`` int32 (mesh ``m``'s parts are
    ``mesh_first_part[m]:mesh_first_part[m + 1]``), ``mesh_lo`` / ``mesh_hi`` ``(M,)`` padded boxes, world frame,
    which skip a mesh whose box the column's ray misses. Outputs as :func:`mark_part_columns_kernel`'s.
    """
    j, i = wp.tid()
    d = column_ray(rot, u0, du, v0, dv, j, i)
    zc0 = z_near + 0.5 * dz
    for m in range(mesh_lo.shape[0]):
        box = slab_interval(origin, d, mesh_lo[m], mesh_hi[m])
        if box[0] > box[1] or box[1] < zc0 or box[0] > zc0 + float(depth - 1) * dz:
            continue
        for p in range(mesh_first_part[m], mesh_first_part[m + 1]):
            mark_part_column(closed_mesh, open_meshes, part_kind, part_ref, part_lo, part_hi, p, m + 1, origin, d,
                             zc0, dz, depth, ranks, fallbacks, j, i)


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
    arrays: dict[str, Any]
    """The kernel's part and mesh arrays (``wp.array``), keyed by parameter name."""


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
    ids = np.array([m.id for m in opened], dtype=np.uint64)
    first = np.asarray(parts.mesh_first_part, dtype=np.int64)
    n_meshes = len(first) - 1
    # Every part of a mesh carries the mesh's label; a mesh without parts labels nothing.
    mesh_label = np.zeros(n_meshes, dtype=np.int32)
    has = first[1:] > first[:-1]
    mesh_label[has] = np.asarray(parts.part_label)[first[:-1][has]]
    arrays = {
        "open_meshes": wp.array(ids, dtype=wp.uint64, device=dev),
        "part_kind": ints(parts.part_kind),
        "part_ref": ints(parts.part_ref),
        "part_rank": ints(np.repeat(np.arange(1, n_meshes + 1), np.diff(first))),
        "part_lo": vec3s(parts.part_lo),
        "part_hi": vec3s(parts.part_hi),
        "mesh_first_part": ints(parts.mesh_first_part),
        "mesh_lo": vec3s(parts.mesh_lo),
        "mesh_hi": vec3s(parts.mesh_hi),
        "mesh_label": ints(mesh_label),
    }
    return WarpMeshSet(device=dev, closed=closed, opened=opened, arrays=arrays)


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
    a = mesh_set.arrays
    n_parts = a["part_kind"].shape[0]
    camera = [wp.mat33(*np.asarray(pose[:3, :3], dtype=np.float32).reshape(-1)),
              wp.vec3(*np.asarray(pose[:3, 3], dtype=np.float32)),
              float(-grid.tu), float(grid.du), float(-grid.tv), float(grid.dv), float(grid.z_near), float(grid.dz),
              int(grid.depth)]
    closed = wp.uint64(mesh_set.closed.id if mesh_set.closed is not None else 0)
    if n_parts and pairs:
        wp.launch(mark_part_columns_kernel, dim=(n_parts, grid.height, grid.width),
                  inputs=[closed, a["open_meshes"], a["part_kind"], a["part_ref"], a["part_rank"], a["part_lo"],
                          a["part_hi"], *camera],
                  outputs=[ranks, fallbacks], device=dev)
    elif n_parts:
        wp.launch(mark_columns_kernel, dim=(grid.height, grid.width),
                  inputs=[closed, a["open_meshes"], a["part_kind"], a["part_ref"], a["part_lo"], a["part_hi"],
                          a["mesh_first_part"], a["mesh_lo"], a["mesh_hi"], *camera],
                  outputs=[ranks, fallbacks], device=dev)
    if n_parts:
        wp.launch(resolve_labels_kernel, dim=grid.shape, inputs=[ranks, a["mesh_label"]], outputs=[labels],
                  device=dev)
    # .numpy() synchronises with the device: the labels are the result, the counter only a diagnostic.
    return labels.numpy(), int(fallbacks.numpy()[0])

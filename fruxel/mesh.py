"""Trapezoid meshing of fruxel label volumes (conventions section 6): full, face-culled and greedy triangle meshes.

All three modes build the mesh from the grid's lattice points (:meth:`FruxelGrid.corner_points`), so a vertex
at boundary indices ``(kb, jb, ib)`` has the same float32 coordinates in every mesh and every mode. Every
face of every mode lies on one of the grid's planes (``x = u_i z``, ``y = v_j z`` or ``z = z_k``), and each
quad's four corners lie on that plane, so two triangles per quad reproduce the cell faces exactly.

Modes:

- ``"full"``: every occupied cell is an independent closed hexahedron, 8 vertices and 12 triangles, no
  vertices shared between cells (the paper's display mesh).
- ``"culled"``: only the faces between an occupied cell and an empty cell or the outside of the grid. Faces
  between two occupied cells are dropped even when their classes differ: the surface shown is the boundary
  of the occupied set, and a face between two solids of different classes is never visible from outside.
  Vertices are shared through their lattice point, one copy per class (vertex key = (lattice point, class))
  so that per-vertex colours do not bleed between classes. Seen as a point set the surface is closed: with
  vertices identified by position every edge has as many faces running one way as the other (an edge where
  two occupied cells touch only along that edge has four faces, two each way).
- ``"greedy"``: the culled faces, merged into larger rectangles per plane, class and facing direction. On
  each plane, the faces of one class form a 2D grid in index space; maximal runs along one axis are merged
  across consecutive rows when they span the same columns with the same class, which covers exactly the
  same faces. The rectangles' corners are lattice points, so the merged quads are exact, but they create
  T-junctions: the mesh covers the same surface with no gaps in area, while its edges no longer match up
  one to one. Its signed volume (divergence theorem) still equals the occupied volume.

Winding is counter-clockwise seen from outside the occupied region, so face normals point outwards and the
signed volume is positive.

Cost: after one pass over the grid that finds the occupied cells, ``"culled"`` and ``"greedy"`` look only at
those cells and their boundary faces, and ``"full"`` only at the occupied cells, so a sparse volume (a VMS
shell keeps a few % of the cells) meshes in time proportional to its size, not to the grid's.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .grid import FruxelGrid
from .io import atomic_write

if TYPE_CHECKING:
    import trimesh

MODES = ("full", "culled", "greedy")
EXPORT_FORMATS = (".ply", ".glb")

# Above this many possible keys (lattice points, or (class, point) pairs) the vertex de-duplication sorts its
# keys instead of marking them in a dense table, so memory stays proportional to the mesh, not the lattice.
_DENSE_KEY_LIMIT = 2**25
# The dense table is also skipped when the key space is this many times larger than the number of keys: its
# cost follows the key space (allocation, page faults, a scan for the marks), a sort's only the mesh.
_DENSE_KEY_RATIO = 16
# Boundary faces are found from the occupied cells' neighbours while fewer than 1 / this of the (padded) grid's
# cells are occupied, and from whole-grid masks above that: six gathers per occupied cell cost about as much as
# six boolean passes over the grid at that density.
_SPARSE_FACES_FACTOR = 6
# Sorted de-duplication packs key and position into one int64; beyond this many bits it falls back to
# np.unique.
_SORT_KEY_BITS = 63


@dataclass(frozen=True, eq=False)
class TriMesh:
    """A triangle mesh in the grid frame with per-vertex colours and per-face class labels.

    Attributes:
        vertices: ``(V, 3)`` float32, grid frame (OpenCV axes), metres.
        faces: ``(F, 3)`` int32 vertex indices, counter-clockwise seen from outside (normals point out).
        colors: ``(V, 4)`` uint8 RGBA per vertex (alpha 255).
        labels: ``(F,)`` uint8 class of each face (never 0).
    """

    vertices: np.ndarray
    faces: np.ndarray
    colors: np.ndarray
    labels: np.ndarray

    @property
    def n_vertices(self) -> int:
        """Number of vertices V."""
        return int(self.vertices.shape[0])

    @property
    def n_faces(self) -> int:
        """Number of triangles F."""
        return int(self.faces.shape[0])


def _empty_mesh() -> TriMesh:
    return TriMesh(
        vertices=np.zeros((0, 3), np.float32),
        faces=np.zeros((0, 3), np.int32),
        colors=np.zeros((0, 4), np.uint8),
        labels=np.zeros((0,), np.uint8),
    )


def _check_inputs(labels: Any, grid: FruxelGrid, palette: Any, mode: str) -> tuple[np.ndarray, np.ndarray]:
    if mode not in MODES:
        raise ValueError(f"mode must be one of {MODES}, got {mode!r}")
    lab = np.asarray(labels)
    if lab.dtype.kind not in "iu":
        raise ValueError(f"labels must be an integer array, got dtype {lab.dtype}")
    if lab.shape != grid.shape:
        raise ValueError(f"labels must have the grid's shape (D, H, W) = {grid.shape}, got {lab.shape}")
    pal = np.asarray(palette)
    if pal.ndim != 2 or pal.shape[1] not in (3, 4) or pal.shape[0] < 1:
        raise ValueError(f"palette must have shape (C, 3) or (C, 4), got {pal.shape}")
    if pal.dtype != np.uint8:
        raise ValueError(f"palette must be uint8, got dtype {pal.dtype}")
    if pal.shape[0] > 256:
        raise ValueError(f"at most 256 classes fit the uint8 face labels, palette has {pal.shape[0]}")
    rgba = np.full((pal.shape[0], 4), 255, np.uint8)
    rgba[:, : pal.shape[1]] = pal
    if lab.size:
        lo, hi = int(lab.min()), int(lab.max())
        if lo < 0 or hi >= pal.shape[0]:
            raise ValueError(f"labels must lie in [0, {pal.shape[0]}) (palette size), got range [{lo}, {hi}]")
    # Labels below 256 are held as uint8 so the per-face passes move a quarter or an eighth of the bytes.
    return lab.astype(np.uint8, copy=False), rgba


def _quad_corners(axis: int, sign: int) -> np.ndarray:
    """Corner codes of the face of a cell on side ``sign`` of xyz axis ``axis``: ``(4,)`` int64.

    A corner code has bit 0 for x (i), bit 1 for y (j), bit 2 for z (k), as in :meth:`FruxelGrid.cell_corners`.
    With ``(axis, b, c)`` a cyclic permutation of (x, y, z), ``e_b x e_c = e_axis``, so walking the quad
    (0,0), (1,0), (1,1), (0,1) in (b, c) turns counter-clockwise about +axis; the -axis face walks it backwards.
    The map from index space to the grid frame has a positive Jacobian (``z^2 > 0``) and keeps each face's
    corners in convex position, so the orientation carries over to the triangles in metres.
    """
    b, c = (axis + 1) % 3, (axis + 2) % 3
    if sign > 0:
        bs, cs = (0, 1, 1, 0), (0, 0, 1, 1)
    else:
        bs, cs = (0, 0, 1, 1), (0, 1, 1, 0)
    base = (1 << axis) if sign > 0 else 0
    return np.array([base + (x << b) + (y << c) for x, y in zip(bs, cs, strict=True)], dtype=np.int64)


# Two triangles per quad, (q0, q1, q2) and (q0, q2, q3), keep the quad's winding.
_QUAD_TRIS = np.array([[0, 1, 2], [0, 2, 3]], dtype=np.int64)

# The six face directions as (xyz axis, sign).
_DIRECTIONS = tuple((axis, sign) for axis in range(3) for sign in (-1, 1))

# Triangles of one hexahedron as corner codes: (12, 3).
_HEX_TRIS = np.concatenate([_quad_corners(a, s)[_QUAD_TRIS] for a, s in _DIRECTIONS])


def _divmod(a: np.ndarray, b: int) -> tuple[np.ndarray, np.ndarray]:
    """``np.divmod(a, b)`` for a non-negative integer array and a positive scalar.

    NumPy's floor_divide by a scalar divides with a precomputed multiply and shift, several times faster than
    the divmod ufunc, which divides element by element in hardware.
    """
    q = a // b
    return q, a - q * b


def _lattice_points(grid: FruxelGrid, lattice_ids: np.ndarray) -> np.ndarray:
    """Coordinates of lattice points by flat lattice id ``(kb * (H+1) + jb) * (W+1) + ib``: ``(n, 3)`` float32."""
    jw = grid.width + 1
    kb, rem = _divmod(lattice_ids, (grid.height + 1) * jw)
    jb, ib = _divmod(rem, jw)
    return grid.corner_points(kb, jb, ib).astype(np.float32)


def _slab_tables(grid: FruxelGrid, k0: int, k1: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Coordinates of the lattice points on the boundary slices ``k0 <= kb < k1``, one table per coordinate.

    A lattice point is ``(u_ib z_kb, v_jb z_kb, z_kb)``, so its x depends only on ``(kb, ib)``, its y on
    ``(kb, jb)`` and its z on ``kb``: three small tables hold the whole slab, where one table of points would be
    as large as the lattice. The entries come elementwise from :meth:`FruxelGrid.corner_points`, so a vertex
    gathered from them is bit-identical to evaluating its lattice point directly.

    Returns:
        x: ``(k1 - k0, W + 1)`` float32, grid frame, metres.
        y: ``(k1 - k0, H + 1)`` float32.
        z: ``(k1 - k0,)`` float32.
    """
    kb = np.arange(k0, k1)[:, None]
    xz = grid.corner_points(kb, 0, np.arange(grid.width + 1)[None, :]).astype(np.float32)
    y = grid.corner_points(kb, np.arange(grid.height + 1)[None, :], 0)[..., 1].astype(np.float32)
    return np.ascontiguousarray(xz[..., 0]), y, np.ascontiguousarray(xz[:, 0, 2])


def _full(lab: np.ndarray, grid: FruxelGrid, rgba: np.ndarray) -> TriMesh:
    _, H, W = lab.shape
    H1, W1 = H + 1, W + 1
    flat = lab.reshape(-1)
    # nonzero of a bool mask is several times faster than of uint8, and flat indices skip a 3D unravel.
    cells = np.flatnonzero(flat != 0)
    n = cells.size
    if 8 * n > np.iinfo(np.int32).max:
        raise ValueError(f"{n} occupied cells need more vertices than int32 face indices can address")
    cls = flat[cells]
    kk, rem = _divmod(cells, H * W)
    jj, ii = _divmod(rem, W)
    # Cells come in ascending flat order, so their slices run from kk[0] to kk[-1].
    k0 = int(kk[0])
    x, y, z = _slab_tables(grid, k0, int(kk[-1]) + 2)
    kr = kk - k0
    # vertices[m, cz, cy, cx] is corner c = 4 cz + 2 cy + cx of cell m. Its x depends on (cz, cx) only, y on
    # (cz, cy) and z on cz: gather 4 + 4 + 2 values per cell and let broadcasting spread them over the corners.
    vertices = np.empty((n, 2, 2, 2, 3), np.float32)
    xk = (kr * W1 + ii)[:, None] + np.array([0, 1, W1, W1 + 1])
    vertices[..., 0] = x.reshape(-1).take(xk).reshape(n, 2, 1, 2)
    yk = (kr * H1 + jj)[:, None] + np.array([0, 1, H1, H1 + 1])
    vertices[..., 1] = y.reshape(-1).take(yk).reshape(n, 2, 2, 1)
    vertices[..., 2] = z.take(kr[:, None] + np.array([0, 1])).reshape(n, 2, 1, 1)
    faces = (np.arange(n, dtype=np.int32)[:, None, None] * 8 + _HEX_TRIS.astype(np.int32)[None]).reshape(-1, 3)
    colors = np.repeat(rgba[cls], 8, axis=0)
    return TriMesh(vertices=vertices.reshape(-1, 3), faces=faces, colors=colors, labels=np.repeat(cls, 12))


def _padded_strides(shape: tuple[int, ...]) -> tuple[int, int, int]:
    """Flat index steps of one cell along array axes (k, j, i) in the padded layout of :func:`_boundary_faces`."""
    _, H, W = shape
    return (H + 1) * (W + 1), W + 1, 1


def _boundary_faces(lab: np.ndarray) -> tuple[np.ndarray, list[np.ndarray]]:
    """The labels in a zero-padded flat layout, and the boundary faces on each side of the occupied cells.

    Layout: cell ``(k, j, i)`` sits at ``((k + 1) * (H+1) + j) * (W+1) + i`` of a ``(D + 2, H + 1, W + 1)``
    array, with one empty slab before and after and the lattice's extra row and column empty. Every neighbour of
    a cell across a face is then inside the array and reads 0 outside the grid (a step back from ``i = 0`` lands
    on the previous row's empty last column), so no pass needs bounds checks, and the lattice id of a cell's
    corner 0 is its index minus ``(H+1) * (W+1)``, with no unravelling.

    Args:
        lab: ``(D, H, W)`` uint8 labels.

    Returns:
        flat: ``((D + 2) * (H + 1) * (W + 1),)`` uint8 padded labels, flattened.
        faces: per direction of ``_DIRECTIONS``, ``(n_d,)`` int64 padded flat indices, ascending, of the
            occupied cells whose neighbour across that face is empty or outside the grid.
    """
    D, H, W = lab.shape
    pad = np.zeros((D + 2, H + 1, W + 1), np.uint8)
    pad[1:-1, :H, :W] = lab
    flat = pad.reshape(-1)
    occ = flat != 0
    cells = np.flatnonzero(occ)
    strides = _padded_strides(lab.shape)
    offsets = [sign * strides[2 - axis] for axis, sign in _DIRECTIONS]
    if cells.size * _SPARSE_FACES_FACTOR < flat.size:
        # Sparse volumes (VMS shells): look up the neighbours of the occupied cells only, so the cost follows
        # their number rather than the grid's.
        return flat, [cells[flat[cells + off] == 0] for off in offsets]
    # Dense volumes: shifted whole-grid masks stream through memory faster than per-cell gathers. The occupied
    # cells all lie in slabs 1..D, whose neighbours stay inside the array.
    s = strides[0]
    inner = occ[s : s + D * s]
    empty = ~occ
    return flat, [np.flatnonzero(inner & empty[s + off : s + D * s + off]) + s for off in offsets]


def _culled_quads(
    flat: np.ndarray, faces: list[np.ndarray], shape: tuple[int, ...]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Every boundary face as a quad of lattice ids.

    Args:
        flat: padded labels of :func:`_boundary_faces`.
        faces: boundary faces per direction, from :func:`_boundary_faces`.
        shape: ``(D, H, W)`` of the label volume.

    Returns:
        quads: per direction, ``(n, 4)`` int64 flat lattice ids ``(kb * (H+1) + jb) * (W+1) + ib`` of the
            face's corners, in winding order.
        classes: per direction, ``(n,)`` uint8 class of each face.
    """
    _, H, W = shape
    H1, W1 = H + 1, W + 1
    c = np.arange(8)
    corner_offset = (c >> 2) * (H1 * W1) + ((c >> 1) & 1) * W1 + (c & 1)
    quads, classes = [], []
    for (axis, sign), f in zip(_DIRECTIONS, faces, strict=True):
        quads.append((f - H1 * W1)[:, None] + corner_offset[_quad_corners(axis, sign)][None, :])
        classes.append(flat[f])
    return quads, classes


def _rectangles(
    flat: np.ndarray, faces: np.ndarray, axis: int, sign: int, shape: tuple[int, ...]
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximal rectangles of equal-class faces on the planes of one direction, in index space.

    Works on the face list alone: whether a face's neighbour along the run axis is a face of the same class is
    read from the padded labels, so no pass touches the whole grid.

    Args:
        flat: padded labels of :func:`_boundary_faces`.
        faces: ``(n,)`` int64 padded flat indices of the boundary faces of this direction, ascending.
        axis: xyz axis of the faces' normal (0: x / i, 1: y / j, 2: z / k).
        sign: side of the cell the faces are on, -1 or +1 along that axis.
        shape: ``(D, H, W)`` of the label volume.

    Returns:
        cell_lo: ``(m, 3)`` int64 ``(k, j, i)`` of each rectangle's first cell.
        cell_hi: ``(m, 3)`` int64 ``(k, j, i)`` of each rectangle's last cell (inclusive).
        cls: ``(m,)`` uint8 class of each rectangle.
    """
    D, H, W = shape
    W1 = W + 1
    strides = _padded_strides(shape)
    arr_axis = 2 - axis
    # Runs go along the last remaining array axis (i, or j on the u-planes) and are merged across the other
    # one, which is where walls and floors seen by the camera extend in long bands.
    row_axis, col_axis = (a for a in range(3) if a != arr_axis)
    n_rows, n_cols = shape[row_axis], shape[col_axis]
    normal, step = sign * strides[arr_axis], strides[col_axis]
    cls = flat[faces]

    def continued(offset: int) -> np.ndarray:
        """True where the cell ``offset`` along the run axis has a face on this side with the same class."""
        nb = faces + offset
        same = flat[nb] == cls
        # Across the normal only from occupied neighbours: those are inside the grid, so the second step stays
        # inside the padded array even from the grid's first slice.
        idx = np.flatnonzero(same)
        same[idx] = flat[nb[idx] + normal] == 0
        return same

    starts = faces[~continued(-step)]
    ends = faces[~continued(step)]
    k, j, i = _unravel_padded(starts, shape)
    if col_axis == 2:
        # Runs along i lie within one row of the flat order, so starts and ends alternate and pair up as they are.
        ps, rs = (k, j) if arr_axis == 0 else (j, k)
        cs, ce, run_cls = i, ends % W1, flat[starts]
    else:
        # Runs along j cross the flat order (cells of other columns i come between theirs): sort starts and ends
        # by (plane i, row k, column j) so that they pair up; the class rides in the low byte of the start key.
        ke, je, ie = _unravel_padded(ends, shape)
        ce = np.sort((ie * D + ke) * H + je) % H
        t, run_cls = _divmod(np.sort(((i * D + k) * H + j) * 256 + flat[starts]), 256)
        t, cs = _divmod(t, H)
        ps, rs = _divmod(t, D)
    # A run continues the rectangle of the row before when that row has a run on the same plane with the same
    # span and class: sort the runs by (plane, span, class, row) and look at neighbours. The key holds all of
    # them, so sorting the keys themselves (no argsort) is enough.
    key, rs = _divmod(np.sort((((ps * n_cols + cs) * n_cols + ce) * 256 + run_cls) * n_rows + rs), n_rows)
    first = np.ones(key.size, dtype=bool)
    first[1:] = (key[1:] != key[:-1]) | (rs[1:] != rs[:-1] + 1)
    heads = np.flatnonzero(first)
    last = np.empty_like(heads)
    last[:-1] = heads[1:] - 1
    last[-1:] = key.size - 1
    t, rect_cls = _divmod(key[heads], 256)
    t, ce = _divmod(t, n_cols)
    ps, cs = _divmod(t, n_cols)
    lo_t = np.stack([ps, rs[heads], cs], axis=-1)
    hi_t = np.stack([ps, rs[last], ce], axis=-1)
    inv = np.argsort((arr_axis, row_axis, col_axis))
    return lo_t[:, inv], hi_t[:, inv], rect_cls.astype(np.uint8)


def _unravel_padded(p: np.ndarray, shape: tuple[int, ...]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cell indices ``(k, j, i)`` of padded flat indices (:func:`_boundary_faces`): three ``(n,)`` int64 arrays."""
    _, H, W = shape
    k, rem = _divmod(p, (H + 1) * (W + 1))
    j, i = _divmod(rem, W + 1)
    return k - 1, j, i


def _greedy_quads(
    flat: np.ndarray, faces: list[np.ndarray], shape: tuple[int, ...]
) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Boundary faces merged into rectangles, as quads of lattice ids (see :func:`_culled_quads`)."""
    _, H, W = shape
    H1, W1 = H + 1, W + 1
    quads, classes = [], []
    for (axis, sign), f in zip(_DIRECTIONS, faces, strict=True):
        lo, hi, cls = _rectangles(flat, f, axis, sign, shape)
        # Boundary indices (kb, jb, ib) of each rectangle's two extreme lattice corners; the face plane sits
        # on the far side of the cell for a + face.
        blo, bhi = lo.copy(), hi + 1
        arr_axis = 2 - axis
        plane = lo[:, arr_axis] + (1 if sign > 0 else 0)
        blo[:, arr_axis] = plane
        bhi[:, arr_axis] = plane
        ids_lo = (blo[:, 0] * H1 + blo[:, 1]) * W1 + blo[:, 2]
        step = ((bhi[:, 0] - blo[:, 0]) * H1 * W1, (bhi[:, 1] - blo[:, 1]) * W1, bhi[:, 2] - blo[:, 2])
        # Corner code bit b selects the far boundary along xyz axis b, i.e. array axis 2 - b.
        codes = _quad_corners(axis, sign)
        corners = [ids_lo + sum(step[2 - b] * ((code >> b) & 1) for b in range(3)) for code in codes]
        quads.append(np.stack(corners, axis=-1))
        classes.append(cls)
    return quads, classes


def _vertex_ids(keys: np.ndarray, n_keys: int) -> tuple[np.ndarray, np.ndarray]:
    """Distinct vertex keys and each corner's index among them.

    Args:
        keys: ``(m,)`` int64 key of every quad corner, in ``[0, n_keys)``.
        n_keys: size of the key space.

    Returns:
        uniq: ``(V,)`` int64 distinct keys, ascending.
        vid: ``(m,)`` int32 index of each key in ``uniq``.
    """
    m = keys.size
    if n_keys <= _DENSE_KEY_LIMIT and n_keys <= _DENSE_KEY_RATIO * m:
        mark = np.zeros(n_keys, dtype=bool)
        mark[keys] = True
        uniq = np.flatnonzero(mark)
        remap = np.empty(n_keys, dtype=np.int32)
        remap[uniq] = np.arange(uniq.size, dtype=np.int32)
        return uniq, remap[keys]
    bits = max(int(m - 1).bit_length(), 1)
    if int(n_keys - 1).bit_length() + bits > _SORT_KEY_BITS:
        uniq, vid = np.unique(keys, return_inverse=True)
        return uniq, vid.reshape(-1).astype(np.int32)
    # Each key carries its position in the low bits, so one plain sort (much faster than an argsort) both
    # orders the keys and says where each came from.
    packed = np.sort((keys << bits) | np.arange(m))
    skeys = packed >> bits
    new = np.ones(m, dtype=bool)
    np.not_equal(skeys[1:], skeys[:-1], out=new[1:])
    vid = np.empty(m, dtype=np.int32)
    vid[packed & ((1 << bits) - 1)] = np.cumsum(new, dtype=np.int32) - 1
    return skeys[new], vid


def _surface(lab: np.ndarray, grid: FruxelGrid, rgba: np.ndarray, merge: bool) -> TriMesh:
    flat, faces = _boundary_faces(lab)
    quads, quad_cls = (_greedy_quads if merge else _culled_quads)(flat, faces, lab.shape)
    quad_ids = np.concatenate(quads)
    qcls = np.concatenate(quad_cls)
    n_lattice = (grid.depth + 1) * (grid.height + 1) * (grid.width + 1)
    # One vertex per (class, lattice point): classes are numbered densely among those present so the key
    # space is only as large as it needs to be.
    present = np.flatnonzero(np.bincount(qcls, minlength=rgba.shape[0]))
    dense = np.zeros(rgba.shape[0], np.int64)
    dense[present] = np.arange(present.size)
    # Lattice points first, then (class, point) among the points used: the second key space is only as large
    # as the mesh, where (class, lattice point) keys would span classes x lattice. Ranks keep the lattice
    # order, so the vertices come out sorted by (class, lattice id) either way.
    lat, lat_vid = _vertex_ids(quad_ids.reshape(-1), n_lattice)
    keys = (dense[qcls][:, None] * lat.size + lat_vid.reshape(-1, 4)).reshape(-1)
    uniq, vid = _vertex_ids(keys, present.size * lat.size)
    vcls, vrank = _divmod(uniq, lat.size)
    vertices = _lattice_points(grid, lat[vrank])
    colors = rgba[present[vcls]]
    faces = vid.reshape(-1, 4)[:, _QUAD_TRIS].reshape(-1, 3)
    return TriMesh(vertices=vertices, faces=faces, colors=colors, labels=np.repeat(qcls, 2))


def mesh_labels(labels: Any, grid: FruxelGrid, palette: Any, mode: str = "full") -> TriMesh:
    """Triangle mesh of the occupied cells of a label volume.

    Args:
        labels: ``(D, H, W)`` integer class per cell (0 = empty), the grid's shape.
        grid: the volume's :class:`FruxelGrid`.
        palette: ``(C, 3)`` (or ``(C, 4)`` with alpha) uint8 colour per class; every label must be < C.
        mode: ``"full"`` (a closed hexahedron per occupied cell), ``"culled"`` (only faces between occupied
            and empty or outside) or ``"greedy"`` (culled faces merged into rectangles); see the module
            docstring.

    Returns:
        The mesh in the grid frame, metres. Empty arrays when no cell is occupied.

    Raises:
        ValueError: an unknown mode, labels of the wrong shape or dtype or out of the palette's range, a
            palette of the wrong shape or dtype, or a full mesh too large for int32 indices (over 268M cells).
    """
    lab, rgba = _check_inputs(labels, grid, palette, mode)
    if not np.any(lab):
        return _empty_mesh()
    if mode == "full":
        return _full(lab, grid, rgba)
    return _surface(lab, grid, rgba, merge=mode == "greedy")


def to_trimesh(mesh: TriMesh) -> trimesh.Trimesh:
    """The mesh as a :class:`trimesh.Trimesh` (not processed: vertices and faces stay as they are).

    Vertex colours are kept; face labels go into ``face_attributes["label"]``.
    """
    import trimesh

    tm = trimesh.Trimesh(
        vertices=mesh.vertices, faces=mesh.faces, vertex_colors=mesh.colors, process=False, validate=False
    )
    tm.face_attributes["label"] = mesh.labels
    return tm


GLTF_FROM_GRID = np.diag([1.0, -1.0, -1.0])
"""Rotation from the grid frame (OpenCV: y down, z forward) to glTF's (+Y up, the default camera looking down
-Z): 180 degrees about x. It keeps handedness, so faces keep their winding and outward normals."""


def encode_mesh(mesh: TriMesh, suffix: str) -> bytes:
    """The bytes of a mesh file of type ``suffix`` (:data:`EXPORT_FORMATS`), in that format's frame.

    - ``.ply`` (binary, with the face labels as the uchar face property ``label``): the grid frame as it is
      (OpenCV axes: x right, y down, z forward, metres), like every fruxel array.
    - ``.glb``: glTF's frame, which every glTF viewer assumes: +Y up. Vertices are turned 180 degrees about x
      (:data:`GLTF_FROM_GRID`: ``(x, y, z) -> (x, -y, -z)``), so a room stands upright and the grid camera's view
      is glTF's default view down -Z. glTF has no place for face labels.

    Raises:
        ValueError: an unsupported suffix.
    """
    suffix = suffix.lower()
    if suffix not in EXPORT_FORMATS:
        raise ValueError(f"mesh export supports {EXPORT_FORMATS}, got {suffix!r}")
    tm = to_trimesh(mesh)
    if suffix == ".ply":
        return tm.export(file_type="ply", encoding="binary")
    # Negation is exact in float32, so the glTF vertices are the lattice points with two signs flipped.
    tm.vertices = mesh.vertices * GLTF_FROM_GRID.diagonal().astype(np.float32)
    return tm.export(file_type="glb")


def export_mesh(mesh: TriMesh, path: str | os.PathLike[str]) -> Path:
    """Write a mesh to ``.ply`` (binary) or ``.glb`` with its vertex colours, atomically, in the format's frame.

    PLY keeps the grid frame (OpenCV axes, y down) and the face labels; GLB is in glTF's +Y-up frame (the grid
    frame turned 180 degrees about x), see :func:`encode_mesh`.

    The file is written atomically (:func:`fruxel.io.atomic_write`: a temporary file in the same folder, synced
    and moved into place), so a reader never sees a partial file and a failed write leaves any earlier file
    untouched.

    Args:
        mesh: the mesh to write.
        path: destination; its suffix picks the format.

    Returns:
        The destination path.

    Raises:
        ValueError: an unsupported suffix.
    """
    dest = Path(path)
    if dest.suffix.lower() not in EXPORT_FORMATS:
        raise ValueError(f"mesh export supports {EXPORT_FORMATS}, got {dest.name!r}")
    data = encode_mesh(mesh, dest.suffix)
    with atomic_write(dest) as f:
        f.write(data)
    return dest

"""Trapezoid meshing of fruxel label volumes (SPEC section 6): full, face-culled and greedy triangle meshes.

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
"""

from __future__ import annotations

import os
import secrets
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from .grid import FruxelGrid

if TYPE_CHECKING:
    import trimesh

MODES = ("full", "culled", "greedy")
EXPORT_FORMATS = (".ply", ".glb")

# Above this many (class, lattice point) keys the vertex de-duplication sorts its keys instead of marking
# them in a dense table, so memory stays proportional to the mesh rather than to classes x lattice.
_DENSE_KEY_LIMIT = 2**25


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


def _lattice_points(grid: FruxelGrid, lattice_ids: np.ndarray) -> np.ndarray:
    """Coordinates of lattice points by flat lattice id ``(kb * (H+1) + jb) * (W+1) + ib``: ``(n, 3)`` float32."""
    jw = grid.width + 1
    kb, rem = np.divmod(lattice_ids, (grid.height + 1) * jw)
    jb, ib = np.divmod(rem, jw)
    return grid.corner_points(kb, jb, ib).astype(np.float32)


def _full(lab: np.ndarray, grid: FruxelGrid, rgba: np.ndarray) -> TriMesh:
    H1, W1 = grid.height + 1, grid.width + 1
    kk, jj, ii = np.nonzero(lab)
    n = kk.size
    if 8 * n > np.iinfo(np.int32).max:
        raise ValueError(f"{n} occupied cells need more vertices than int32 face indices can address")
    cls = lab[kk, jj, ii]
    c = np.arange(8)
    corner_offset = (c >> 2) * (H1 * W1) + ((c >> 1) & 1) * W1 + (c & 1)
    base = (kk * H1 + jj) * W1 + ii
    corner_ids = (base[:, None] + corner_offset[None, :]).reshape(-1)
    # Corners are gathered from one table of the lattice points they can touch, which costs far less than
    # evaluating corner_points 8 times per cell; the values are the same, since each point depends only on
    # its own boundary indices.
    k0, k1 = int(kk.min()), int(kk.max()) + 2
    sub = grid.corner_points(
        np.arange(k0, k1)[:, None, None], np.arange(H1)[None, :, None], np.arange(W1)[None, None, :]
    ).astype(np.float32).reshape(-1, 3)
    vertices = np.take(sub, corner_ids - k0 * H1 * W1, axis=0)
    faces = (np.arange(n, dtype=np.int32)[:, None, None] * 8 + _HEX_TRIS.astype(np.int32)[None]).reshape(-1, 3)
    colors = np.repeat(rgba[cls], 8, axis=0)
    return TriMesh(vertices=vertices, faces=faces, colors=colors, labels=np.repeat(cls, 12))


def _face_masks(lab: np.ndarray) -> list[np.ndarray]:
    """Boundary faces on each side of every cell, per direction of ``_DIRECTIONS``.

    Returns:
        Six ``(D, H, W)`` bool arrays: True where the cell is occupied and its neighbour across that face is
        empty or outside the grid.
    """
    occ = np.zeros(tuple(n + 2 for n in lab.shape), dtype=bool)
    occ[1:-1, 1:-1, 1:-1] = lab != 0
    inner = occ[1:-1, 1:-1, 1:-1]
    out = []
    for axis, sign in _DIRECTIONS:
        arr_axis = 2 - axis
        sl = [slice(1, -1)] * 3
        sl[arr_axis] = slice(2, None) if sign > 0 else slice(0, -2)
        out.append(inner & ~occ[tuple(sl)])
    return out


def _culled_quads(lab: np.ndarray, masks: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Every boundary face as a quad of lattice ids.

    Returns:
        quads: per direction, ``(n, 4)`` int64 flat lattice ids ``(kb * (H+1) + jb) * (W+1) + ib`` of the
            face's corners, in winding order.
        classes: per direction, ``(n,)`` uint8 class of each face.
    """
    _, H, W = lab.shape
    H1, W1 = H + 1, W + 1
    c = np.arange(8)
    corner_offset = (c >> 2) * (H1 * W1) + ((c >> 1) & 1) * W1 + (c & 1)
    flat_lab = lab.reshape(-1)
    quads, classes = [], []
    for (axis, sign), mask in zip(_DIRECTIONS, masks, strict=True):
        f = np.flatnonzero(mask)
        k, rem = np.divmod(f, H * W)
        # Lattice id of the cell's corner 0, from its flat cell index without unravelling i.
        base = f + k * (H + W + 1) + rem // W
        quads.append(base[:, None] + corner_offset[_quad_corners(axis, sign)][None, :])
        classes.append(flat_lab[f])
    return quads, classes


def _rectangles(face_lab: np.ndarray, axis: int) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Maximal rectangles of equal-class faces on the planes of one direction, in index space.

    Args:
        face_lab: ``(D, H, W)`` uint8 class of the boundary face of each cell on that side, 0 for none.
        axis: xyz axis of the faces' normal (0: x / i, 1: y / j, 2: z / k).

    Returns:
        cell_lo: ``(n, 3)`` int64 ``(k, j, i)`` of each rectangle's first cell.
        cell_hi: ``(n, 3)`` int64 ``(k, j, i)`` of each rectangle's last cell (inclusive).
        cls: ``(n,)`` uint8 class of each rectangle.
    """
    arr_axis = 2 - axis
    # Runs go along the last remaining array axis (i, or j on the u-planes) and are merged across the other
    # one, which is where walls and floors seen by the camera extend in long bands.
    rest = [a for a in range(3) if a != arr_axis]
    perm = (arr_axis, rest[0], rest[1])
    g = np.ascontiguousarray(np.transpose(face_lab, perm))
    _, n_rows, n_cols = g.shape
    nz = g != 0
    start = nz.copy()
    start[:, :, 1:] &= g[:, :, 1:] != g[:, :, :-1]
    end = nz
    end[:, :, :-1] &= g[:, :, :-1] != g[:, :, 1:]
    # Starts and ends pair up in C order, since every run has exactly one of each and runs do not nest.
    fs = np.flatnonzero(start)
    ce = np.flatnonzero(end) % n_cols
    ps, rem = np.divmod(fs, n_rows * n_cols)
    rs, cs = np.divmod(rem, n_cols)
    cls = g.reshape(-1)[fs]
    # A run continues the rectangle of the row before when that row has a run on the same plane with the
    # same span and class: sort the runs by (plane, span, class, row) and look at neighbours.
    key = ((ps * n_cols + cs) * n_cols + ce) * 256 + cls
    order = np.argsort(key * n_rows + rs, kind="stable")
    key, rs_sorted = key[order], rs[order]
    first = np.ones(order.size, dtype=bool)
    first[1:] = (key[1:] != key[:-1]) | (rs_sorted[1:] != rs_sorted[:-1] + 1)
    heads = np.flatnonzero(first)
    last = np.append(heads[1:], order.size) - 1
    o = order[heads]
    lo_t = np.stack([ps[o], rs[o], cs[o]], axis=-1)
    hi_t = np.stack([ps[o], rs_sorted[last], ce[o]], axis=-1)
    inv = np.argsort(perm)
    return lo_t[:, inv], hi_t[:, inv], cls[o]


def _greedy_quads(lab: np.ndarray, masks: list[np.ndarray]) -> tuple[list[np.ndarray], list[np.ndarray]]:
    """Boundary faces merged into rectangles, as quads of lattice ids (see :func:`_culled_quads`)."""
    _, H, W = lab.shape
    H1, W1 = H + 1, W + 1
    quads, classes = [], []
    for (axis, sign), mask in zip(_DIRECTIONS, masks, strict=True):
        lo, hi, cls = _rectangles(lab * mask, axis)
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


def _surface(lab: np.ndarray, grid: FruxelGrid, rgba: np.ndarray, merge: bool) -> TriMesh:
    masks = _face_masks(lab)
    quads, quad_cls = (_greedy_quads if merge else _culled_quads)(lab, masks)
    quad_ids = np.concatenate(quads)
    qcls = np.concatenate(quad_cls)
    n_lattice = (grid.depth + 1) * (grid.height + 1) * (grid.width + 1)
    # One vertex per (class, lattice point): classes are numbered densely among those present so the key
    # space is only as large as it needs to be.
    present = np.flatnonzero(np.bincount(qcls, minlength=rgba.shape[0]))
    dense = np.zeros(rgba.shape[0], np.int64)
    dense[present] = np.arange(present.size)
    keys = (dense[qcls][:, None] * n_lattice + quad_ids).reshape(-1)
    n_keys = present.size * n_lattice
    if n_keys <= _DENSE_KEY_LIMIT:
        mark = np.zeros(n_keys, dtype=bool)
        mark[keys] = True
        uniq = np.flatnonzero(mark)
        remap = np.empty(n_keys, dtype=np.int32)
        remap[uniq] = np.arange(uniq.size, dtype=np.int32)
        vid = remap[keys]
    else:
        uniq, vid = np.unique(keys, return_inverse=True)
        vid = vid.astype(np.int32)
    vcls, vlat = np.divmod(uniq, n_lattice)
    vertices = _lattice_points(grid, vlat)
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


def export_mesh(mesh: TriMesh, path: str | os.PathLike[str]) -> Path:
    """Write a mesh to ``.ply`` (binary) or ``.glb`` with its vertex colours, atomically.

    PLY also keeps the face labels, as the uchar face property ``label``; glTF has no place for them.

    The file is written to a temporary file in the same folder and moved into place, so a reader never sees
    a partial file and a failed write leaves any earlier file untouched.

    Args:
        mesh: the mesh to write.
        path: destination; its suffix picks the format.

    Returns:
        The destination path.

    Raises:
        ValueError: an unsupported suffix.
    """
    dest = Path(path)
    suffix = dest.suffix.lower()
    if suffix not in EXPORT_FORMATS:
        raise ValueError(f"mesh export supports {EXPORT_FORMATS}, got {dest.name!r}")
    tm = to_trimesh(mesh)
    if suffix == ".ply":
        data = tm.export(file_type="ply", encoding="binary")
    else:
        data = tm.export(file_type="glb")
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    while True:
        tmp = dest.parent / f".{dest.name}.{secrets.token_hex(6)}.tmp"
        try:
            # Mode 0o666 lets the umask decide the permissions, as for any newly created file (mkstemp's 0o600
            # would leave exported meshes private).
            fd = os.open(tmp, flags, 0o666)
            break
        except FileExistsError:
            continue
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
        os.replace(tmp, dest)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return dest

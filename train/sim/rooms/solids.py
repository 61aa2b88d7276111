"""The solid a pack mesh is labelled by: the mesh itself when it is closed, else its surface filled into a solid.

Why: ``fruxelize`` labels a cell by the solid that contains its centre (conventions, "fruxelize"). Most pack meshes
(Sweet Home 3D's furniture) are not closed: a wardrobe is a hollow box of panels, open at the back or the bottom,
its faces wound every which way, so its inside (a winding number over 0.5) came out as scattered cells, a lattice
of furniture in front of the wall the truth then saw through it. A piece of furniture is labelled by the volume it
takes: its surface voxelised at :data:`PITCH`, closed by one voxel (the gaps between panels), its enclosed cavities
filled, then every horizontal section's holes filled (a sofa or a cabinet open at the bottom encloses its inside in
each section), and the voxels' outer faces as a closed triangle mesh. The solid is the surface thickened by half a
voxel at most; what is thin stays thin (a chair's legs, a shelf's boards). Images are drawn from the mesh itself.

A prop's solid is made once per machine (:mod:`..assetpack.derived`, named by the mesh file's SHA-256) and kept on
the :class:`~.library.Prop`; :func:`fruxel.train.sim.rooms.home.make_home` places it with the prop.
"""

from __future__ import annotations

import numpy as np

PITCH = 0.03
"""Voxel side of a filled solid, metres: well under a 64^3 grid's cells at the rooms' distances (5-12 cm), so the
label follows the surface to about a cell."""


def is_closed(vertices: np.ndarray, faces: np.ndarray) -> bool:
    """Whether ``fruxelize`` takes the mesh as closed solids (every part closed: :func:`fruxel.kernels.fruxelize.
    prepare_meshes`), so that it needs no filling."""
    from fruxel.kernels.fruxelize import prepare_meshes

    return bool((prepare_meshes([(vertices, faces, 1)]).part_kind == 0).all())


def surface_voxels(vertices: np.ndarray, faces: np.ndarray, pitch: float, origin: np.ndarray,
                   shape: tuple[int, int, int]) -> np.ndarray:
    """``shape`` bool grid, True where the surface passes through a voxel (voxel ``(i, j, k)`` spans ``origin +
    pitch * [i, i + 1)`` along x, and so on): each triangle sampled at most half a voxel apart."""
    occ = np.zeros(shape, dtype=bool)
    tri = vertices[faces]
    longest = np.max(np.linalg.norm(tri - tri[:, [1, 2, 0]], axis=2), axis=1)
    steps = np.maximum(1, np.ceil(longest / (pitch / 2))).astype(np.int64)
    for n in np.unique(steps):
        i, j = np.meshgrid(np.arange(n + 1), np.arange(n + 1), indexing="ij")
        keep = i + j <= n
        u, v = i[keep] / n, j[keep] / n
        t = tri[steps == n]
        pts = t[:, None, 0] + u[None, :, None] * (t[:, None, 1] - t[:, None, 0]) + \
            v[None, :, None] * (t[:, None, 2] - t[:, None, 0])
        idx = np.clip(np.floor((pts.reshape(-1, 3) - origin) / pitch).astype(np.int64), 0, np.array(shape) - 1)
        occ[idx[:, 0], idx[:, 1], idx[:, 2]] = True
    return occ


def filled_voxels(vertices: np.ndarray, faces: np.ndarray, pitch: float = PITCH) -> tuple[np.ndarray, np.ndarray]:
    """The filled solid as voxels (module docstring): ``(occupancy (X, Y, Z) bool, origin (3,) float64)``; voxel
    ``(i, j, k)`` spans ``origin + pitch * [i, i + 1)`` along x (z up: sections are ``[:, :, k]``)."""
    from scipy import ndimage

    lo, hi = vertices.min(axis=0), vertices.max(axis=0)
    pad = 3  # room for the closing's dilation and erosion, and an outside around the solid
    origin = lo - pad * pitch
    shape = tuple(int(s) for s in np.ceil((hi - lo) / pitch).astype(np.int64) + 2 * pad + 1)
    occ = surface_voxels(vertices, faces, pitch, origin, shape)
    cube = np.ones((3, 3, 3), dtype=bool)
    occ = ndimage.binary_fill_holes(ndimage.binary_dilation(occ, cube))
    for k in range(occ.shape[2]):
        occ[:, :, k] = ndimage.binary_fill_holes(occ[:, :, k])
    return ndimage.binary_erosion(occ, cube, border_value=0), origin


def voxel_mesh(occ: np.ndarray, origin: np.ndarray, pitch: float) -> tuple[np.ndarray, np.ndarray]:
    """The outer faces of occupied voxels as a closed triangle mesh with outward normals: ``(vertices (V, 3)
    float64, faces (F, 3) int64)``, two triangles per face, vertices shared on the voxel corners' lattice."""
    p = np.pad(occ, 1)
    nx, ny, nz = p.shape
    corner = (ny + 1) * (nz + 1), nz + 1, 1
    quads = []
    for axis in range(3):
        for step in (1, -1):
            # a face of voxel c towards c + step along axis, where c is occupied and its neighbour is not
            here = p & ~np.roll(p, -step, axis=axis)
            cells = np.argwhere(here)
            if not len(cells):
                continue
            base = cells + (np.eye(3, dtype=np.int64)[axis] if step == 1 else 0)
            a, b = [ax for ax in range(3) if ax != axis]
            ea, eb = np.eye(3, dtype=np.int64)[a], np.eye(3, dtype=np.int64)[b]
            ring = [base, base + ea, base + ea + eb, base + eb]
            # counter-clockwise seen from +axis when ea x eb = +axis; the face's normal points along step
            if (np.cross(ea, eb)[axis] > 0) != (step == 1):
                ring = ring[::-1]
            quads.append(np.stack([r @ np.array(corner) for r in ring], axis=1))
    if not quads:
        return np.zeros((0, 3)), np.zeros((0, 3), dtype=np.int64)
    q = np.concatenate(quads)
    tris = np.concatenate([q[:, [0, 1, 2]], q[:, [0, 2, 3]]])
    used, local = np.unique(tris, return_inverse=True)
    ijk = np.stack([used // corner[0], used % corner[0] // corner[1], used % corner[1]], axis=1)
    return origin + (ijk - 1) * pitch, local.reshape(-1, 3).astype(np.int64)


def filled_solid(vertices: np.ndarray, faces: np.ndarray, pitch: float = PITCH) -> tuple[np.ndarray, np.ndarray]:
    """The solid a mesh that is not closed is labelled by (module docstring): ``(vertices (V, 3) float64, faces
    (F, 3) int64)``, a closed mesh with outward normals in the mesh's own frame, metres.

    Args:
        vertices: ``(V, 3)`` float vertices, metres.
        faces: ``(F, 3)`` int triangles.
        pitch: voxel side, metres.
    """
    occ, origin = filled_voxels(np.asarray(vertices, dtype=np.float64), np.asarray(faces, dtype=np.int64), pitch)
    return voxel_mesh(occ, origin, pitch)


def affine_map(source: np.ndarray, target: np.ndarray) -> np.ndarray | None:
    """The affine map that takes ``source`` vertices onto ``target`` (a placed prop: rotated, moved, lifted, scaled
    or squashed), as a ``(4, 3)`` float64 matrix for ``[x, y, z, 1] @ M``; None when the vertices differ in number
    or no affine map fits them to a micrometre (the piece was built from more than the prop)."""
    if source.shape != target.shape or len(source) < 4:
        return None
    a = np.column_stack([source, np.ones(len(source))])
    m, *_ = np.linalg.lstsq(a, target, rcond=None)
    return m if np.abs(a @ m - target).max() <= 1e-6 else None


THICKENED_LABELS = ("door", "window", "furniture", "sculpture", "object")
"""Classes whose thin upright parts get a label slab of at least ``HomeConfig.label_thickness`` (not the room's
own wall, floor and ceiling, which are thick, nor anything lying flat: a rug, a table top)."""


def thicken_slabs(vertices: np.ndarray, faces: np.ndarray, minimum: float) -> np.ndarray:
    """``vertices`` with every upright slab thinner than ``minimum`` stretched to ``minimum`` about its middle.

    A door leaf, a painting or a pane is a few centimetres thick; seen from in front, a grid's cells are deeper
    than that (a 64^3 grid's slices are 12 cm deep), so few cell centres fell inside it and its truth came out as
    stripes of the wall behind it. Each connected part of the mesh (vertices joined by faces) whose thinnest
    principal axis is nearly horizontal (within 30 degrees) and spans less than ``minimum`` is scaled along that
    axis alone; other parts keep their vertices.

    Args:
        vertices: ``(V, 3)`` float64, world frame (z up), metres.
        faces: ``(F, 3)`` int64.
        minimum: the thinnest slab, metres.

    Returns:
        ``(V, 3)`` float64, a new array.
    """
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    v = np.array(vertices, dtype=np.float64)
    if not len(faces):
        return v
    e = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]]])
    graph = coo_matrix((np.ones(len(e)), (e[:, 0], e[:, 1])), shape=(len(v), len(v)))
    n, part = connected_components(graph, directed=False)
    # Per part at once (the parts' vertices sorted together, reduced by segment): the box centre, the covariance's
    # eigenvectors, the extent along the thinnest one.
    order = np.argsort(part, kind="stable")
    starts = np.flatnonzero(np.r_[True, np.diff(part[order]) != 0])
    vs = v[order]
    centre = (np.minimum.reduceat(vs, starts) + np.maximum.reduceat(vs, starts)) / 2
    d = v - centre[part]
    count = np.bincount(part, minlength=n).astype(np.float64)
    mean = np.stack([np.bincount(part, d[:, a], n) for a in range(3)], axis=1) / count[:, None]
    cov = np.stack([np.stack([np.bincount(part, d[:, a] * d[:, b], n) for b in range(3)], axis=1)
                    for a in range(3)], axis=1) / count[:, None, None] - mean[:, :, None] * mean[:, None, :]
    thin = np.linalg.eigh(cov)[1][:, :, 0]  # (n, 3): eigenvectors come in columns, smallest eigenvalue first
    t = np.einsum("ij,ij->i", d, thin[part])
    ts = t[order]
    tlo, thi = np.minimum.reduceat(ts, starts), np.maximum.reduceat(ts, starts)
    extent = thi - tlo
    stretch = (count > 3) & (extent > 0.0) & (extent < minimum) & (np.abs(thin[:, 2]) < 0.5)
    factor = np.where(stretch, minimum / np.where(extent > 0, extent, 1.0) - 1.0, 0.0)
    mid = (tlo + thi) / 2
    return v + ((t - mid[part]) * factor[part])[:, None] * thin[part]

"""Where small things can stand on a piece of furniture: the support surfaces of a mesh, and fitting items on them.

Frame: the mesh's own (canonical) frame of :mod:`fruxel.train.sim.assets`: metres, z up, front towards -y.

Each level is eroded by one cell (a cell keeps the smallest free height of its 3 x 3 neighbourhood): a panel that
stands on the surface between two cell centres has no horizontal face there and would not be seen from above.

A *support level* is the set of cells of a horizontal grid (:data:`CELL` metres) where the mesh has an upward,
horizontal face at one height: a table top, a shelf board, a cabinet's top. Each cell records the free height
above the surface there: up to the mesh's next surface above the cell (the shelf board above), and only as long as
nothing of the mesh stands in front of the cell (towards -y), so that things put there are seen and reachable and
never shut inside a cabinet. The levels of a mesh are computed once per process (:class:`~.library.Library`
caches them) by rasterising the mesh's faces twice: seen from above (heights) and from the front (depths).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

CELL = 0.02
"""Cell size of the support grids, metres."""
UP = 0.9
"""A face is an upward support when the z component of its unit normal is at least this."""
MIN_CELLS = 20
"""Smallest support level kept, in cells (0.008 m^2)."""
TOP_ROOM = 1.0
"""Free height recorded above a surface with nothing of the mesh above it, metres."""


@dataclass(eq=False)
class Level:
    """One support surface of a mesh (module docstring); cell ``(r, c)`` is centred at
    ``(x0 + (c + 1/2) CELL, y0 + (r + 1/2) CELL)``."""

    z: float
    """Height of the surface, metres (mesh frame)."""
    x0: float
    """x of the grid's lower edge, metres."""
    y0: float
    """y of the grid's lower edge, metres."""
    room: np.ndarray
    """``(ny, nx)`` float32 free height above each cell, metres; 0 where the level has no surface."""
    used: np.ndarray = field(default_factory=lambda: np.zeros((0, 0), dtype=bool))
    """``(ny, nx)`` bool cells taken by items already placed (a per-room copy, see :meth:`fresh`)."""

    @property
    def area(self) -> float:
        """Surface area, square metres."""
        return float(np.count_nonzero(self.room > 0)) * CELL * CELL

    def fresh(self) -> Level:
        """A copy for one room: the same surface with nothing placed on it (the cached level stays clean)."""
        return Level(self.z, self.x0, self.y0, self.room, np.zeros(self.room.shape, dtype=bool))

    def fit(self, rng: np.random.Generator, width: float, depth: float, height: float,
            margin: float = CELL) -> tuple[float, float] | None:
        """A random free spot for an axis-aligned item of ``width x depth`` (x, y) and ``height``, marked used.

        Returns:
            The item's centre ``(x, y)`` in the mesh frame, or None when no spot has the room.
        """
        if self.used.shape != self.room.shape:
            self.used = np.zeros(self.room.shape, dtype=bool)
        kw, kd = int(np.ceil(width / CELL)), int(np.ceil(depth / CELL))
        ny, nx = self.room.shape
        if kw > nx or kd > ny or kw < 1 or kd < 1:
            return None
        bad = (self.room < height) | self.used
        s = np.zeros((ny + 1, nx + 1), dtype=np.int32)
        s[1:, 1:] = np.cumsum(np.cumsum(bad, axis=0), axis=1)
        windows = s[kd:, kw:] - s[:-kd, kw:] - s[kd:, :-kw] + s[:-kd, :-kw]
        rows, cols = np.nonzero(windows == 0)
        if len(rows) == 0:
            return None
        k = int(rng.integers(len(rows)))
        r, c = int(rows[k]), int(cols[k])
        m = int(np.ceil(margin / CELL))
        self.used[max(r - m, 0):r + kd + m, max(c - m, 0):c + kw + m] = True
        return self.x0 + (c + kw / 2) * CELL, self.y0 + (r + kd / 2) * CELL

    def free_run(self, height: float) -> tuple[np.ndarray, np.ndarray]:
        """Cells with at least ``height`` of room and not used: ``(rows, cols)`` int arrays."""
        if self.used.shape != self.room.shape:
            self.used = np.zeros(self.room.shape, dtype=bool)
        return np.nonzero((self.room >= height) & ~self.used)


def _rasterise(p: np.ndarray, depth: np.ndarray, lo: np.ndarray, shape: tuple[int, int]
               ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Cells whose centres the 2D triangles cover, with the depth interpolated there.

    Args:
        p: ``(F, 3, 2)`` triangle corners in the grid's two axes, metres.
        depth: ``(F, 3)`` the third coordinate at the corners.
        lo: ``(2,)`` the grid's lower edge.
        shape: ``(n0, n1)`` cells along the two axes.

    Returns:
        Flat cell index ``i0 * n1 + i1``, interpolated depth and triangle index per covered cell centre.
    """
    g = (p - lo) / CELL - 0.5
    first = np.clip(np.ceil(g.min(axis=1) - 1e-9), 0, None).astype(np.int64)
    last = np.minimum(np.floor(g.max(axis=1) + 1e-9).astype(np.int64), np.array(shape) - 1)
    n = np.maximum(last - first + 1, 0)
    count = n[:, 0] * n[:, 1]
    tri = np.repeat(np.arange(len(p)), count)
    if len(tri) == 0:
        return np.zeros(0, np.int64), np.zeros(0), np.zeros(0, np.int64)
    k = np.arange(len(tri)) - np.repeat(np.cumsum(count) - count, count)
    i0 = first[tri, 0] + k // n[tri, 1]
    i1 = first[tri, 1] + k % n[tri, 1]
    c = np.stack([i0, i1], axis=1).astype(np.float64)
    a, b, e = g[tri, 0], g[tri, 1], g[tri, 2]
    v0, v1, v2 = b - a, e - a, c - a
    den = v0[:, 0] * v1[:, 1] - v1[:, 0] * v0[:, 1]
    with np.errstate(divide="ignore", invalid="ignore"):
        s = (v2[:, 0] * v1[:, 1] - v1[:, 0] * v2[:, 1]) / den
        t = (v0[:, 0] * v2[:, 1] - v2[:, 0] * v0[:, 1]) / den
    inside = (np.abs(den) > 1e-12) & (s >= -1e-6) & (t >= -1e-6) & (s + t <= 1 + 1e-6)
    d = depth[tri]
    z = d[:, 0] + s * (d[:, 1] - d[:, 0]) + t * (d[:, 2] - d[:, 0])
    return (i0 * shape[1] + i1)[inside], z[inside], tri[inside]


def support_levels(vertices: np.ndarray, faces: np.ndarray) -> tuple[Level, ...]:
    """The support levels of a mesh (module docstring), lowest first.

    Args:
        vertices: ``(V, 3)`` float, metres, mesh frame.
        faces: ``(F, 3)`` int, outward (counter-clockwise seen from outside).
    """
    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    tri = v[f]
    normal = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    length = np.linalg.norm(normal, axis=1)
    ok = length > 1e-12
    tri, normal = tri[ok], normal[ok] / length[ok, None]
    lo, hi = v.min(axis=0) - CELL, v.max(axis=0) + CELL
    nx, ny, nz = (int(np.ceil((hi[k] - lo[k]) / CELL)) for k in range(3))
    # Seen from above: every surface height over each (y, x) cell, and which of them are upward supports.
    flat = np.abs(normal[:, 2]) > 1e-6
    cells, z, t = _rasterise(tri[flat][:, :, [1, 0]], tri[flat][:, :, 2], lo[[1, 0]], (ny, nx))
    up = (normal[flat][t, 2] >= UP)
    # Seen from the front: the frontmost (smallest y) surface over each (x, z) cell.
    side = np.abs(normal[:, 1]) > 1e-6
    fc, fy, _ = _rasterise(tri[side][:, :, [0, 2]], tri[side][:, :, 1], lo[[0, 2]], (nx, nz))
    front = np.full(nx * nz, np.inf)
    np.minimum.at(front, fc, fy)
    front = front.reshape(nx, nz)
    order = np.lexsort((z, cells))
    key = cells[order] * 100.0 + (z[order] - lo[2])
    sc, sz = cells[up], z[up]
    nxt = np.searchsorted(key, sc * 100.0 + (sz - lo[2]) + 0.004)
    above = np.where((nxt < len(key)) & (cells[order][np.minimum(nxt, len(key) - 1)] == sc),
                     z[order][np.minimum(nxt, len(key) - 1)] - sz, TOP_ROOM)
    return _levels(sc, sz, np.minimum(above, TOP_ROOM), front, lo, (ny, nx, nz))


def _levels(cells: np.ndarray, z: np.ndarray, above: np.ndarray, front: np.ndarray, lo: np.ndarray,
            shape: tuple[int, int, int]) -> tuple[Level, ...]:
    """Group support cells into levels by height and limit each cell's room by what stands in front of it."""
    ny, nx, nz = shape
    out = []
    bins = np.round(z / 0.01).astype(np.int64)
    groups: list[list[int]] = []
    # Heights within a centimetre of each other are one surface (a board's faces after decimation); things
    # stand where it is highest, so they neither sink into it nor float above it.
    for b in np.unique(bins):
        if groups and b - groups[-1][0] <= 1:
            groups[-1].append(int(b))
        else:
            groups.append([int(b)])
    for group in groups:
        sel = np.isin(bins, group)
        if np.count_nonzero(sel) < MIN_CELLS:
            continue
        level_z = float(z[sel].max())
        sel &= z >= level_z - 0.004
        c, room = cells[sel], above[sel]
        r, col = c // nx, c % nx
        # Open towards the front: the frontmost surface over this x column, from just above the level up to the
        # item's top, must lie behind the cell (else a cabinet door or a rail would hide and enclose the item).
        k0 = int(np.floor((level_z - lo[2]) / CELL)) + 1
        cell_y = lo[1] + (r + 0.5) * CELL
        cols = front[col, k0:]
        blocked = cols < (cell_y[:, None] - CELL)
        if blocked.shape[1] == 0:
            blocked = np.zeros((len(c), 1), dtype=bool)
        free = np.where(blocked.any(axis=1), lo[2] + (k0 + blocked.argmax(axis=1)) * CELL - level_z, np.inf)
        room = np.minimum(room, free)
        grid = np.zeros((ny, nx), dtype=np.float32)
        np.maximum.at(grid, (r, col), room.astype(np.float32))
        # A vertical panel standing on the surface between two cell centres is not seen from above: each cell
        # keeps the smallest room of its neighbourhood, so things stay a cell clear of every edge.
        pad = np.pad(grid, 1)
        grid = np.min([pad[i:i + ny, j:j + nx] for i in range(3) for j in range(3)], axis=0)
        if np.count_nonzero(grid >= 0.04) < MIN_CELLS:
            continue
        if out and abs(out[-1].z - level_z) < 0.015:
            continue
        out.append(Level(level_z, float(lo[0]), float(lo[1]), grid))
    return tuple(out)

"""Build the bundled sample room: a small procedural fruxel model.

``python scripts/make_sample.py`` writes it (a maintainer's command: the core holds no command-line code). The
result is deterministic: every cell is labelled by testing its centre against simple solids (boxes, cylinders, a
sphere) in the grid frame, with no randomness.

The scene, in the grid camera's frame (OpenCV axes: x right, y down, z forward; metres). The camera stands
1 m above the floor, looking horizontally into a 4 m wide room:

- floor (class ``floor``): the slab 1.0 <= y <= 1.25;
- walls (``wall``): the back wall 5.55 <= z <= 5.9 and the side walls at |x| in [2.0, 2.3], up to the top of
  the frustum (no ceiling, so an oblique view sees inside);
- a window opening in the back wall, with a recessed pane (``window``);
- a door opening in the back wall, with a recessed door leaf (``door``);
- a table (top and four legs) and a cabinet by the left wall (``furniture``), a cylindrical pedestal
  (``furniture``) carrying a sphere (``sculpture``).

The bundled file is ``sample_room.npz`` (:func:`fruxel.save`). Its picture, ``sample_room.png``, needs pyrender,
which the numpy-only core does not import: ``python scripts/make_sample_picture.py`` draws it.
"""

from __future__ import annotations

import numpy as np

from fruxel.classes import DEFAULT_CLASSES
from fruxel.grid import FruxelGrid
from fruxel.model import FruxelModel

GRID = FruxelGrid(width=64, height=48, depth=64, z_near=0.5, z_far=6.0, hfov=60.0)
"""Grid of the sample room: 64 x 48 x 64 cells, z from 0.5 to 6 m, 60 degree horizontal field of view."""

# Generous bounds for solids that should reach the edge of the frustum: the frustum at z_far spans
# |x| <= 3.47 m and |y| <= 2.6 m.
FAR = 10.0


def _box(p: np.ndarray, lo: tuple[float, float, float], hi: tuple[float, float, float]) -> np.ndarray:
    """Points inside an axis-aligned box: ``p`` ``(..., 3)`` grid frame -> ``(...)`` bool."""
    return np.all((p >= np.asarray(lo)) & (p <= np.asarray(hi)), axis=-1)


def _cylinder_y(
    p: np.ndarray, centre_xz: tuple[float, float], radius: float, y_range: tuple[float, float]
) -> np.ndarray:
    """Points inside a vertical (y-axis) cylinder: ``(...)`` bool."""
    dx, dz = p[..., 0] - centre_xz[0], p[..., 2] - centre_xz[1]
    return (dx * dx + dz * dz <= radius * radius) & (p[..., 1] >= y_range[0]) & (p[..., 1] <= y_range[1])


def _sphere(p: np.ndarray, centre: tuple[float, float, float], radius: float) -> np.ndarray:
    """Points inside a sphere: ``(...)`` bool."""
    return np.sum((p - np.asarray(centre)) ** 2, axis=-1) <= radius * radius


def room_labels(grid: FruxelGrid = GRID) -> np.ndarray:
    """Labels of the sample room on ``grid``: ``(D, H, W)`` uint8, :data:`DEFAULT_CLASSES` ids.

    Solids are painted in order, later ones over earlier ones, so openings are cut after the walls.
    """
    ids = {name: i for i, name in enumerate(DEFAULT_CLASSES.names)}
    p = grid.cell_centres()
    lab = np.zeros(grid.shape, np.uint8)

    lab[_box(p, (-FAR, 1.0, -FAR), (FAR, 1.25, FAR))] = ids["floor"]
    walls = (
        _box(p, (-FAR, -FAR, 5.55), (FAR, 1.25, 5.9))
        | _box(p, (-2.3, -FAR, -FAR), (-2.0, 1.25, 5.9))
        | _box(p, (2.0, -FAR, -FAR), (2.3, 1.25, 5.9))
    )
    lab[walls] = ids["wall"]

    window_hole = _box(p, (-1.6, -1.2, 5.5), (-0.3, 0.0, 5.95))
    lab[window_hole] = 0
    lab[window_hole & _box(p, (-FAR, -FAR, 5.68), (FAR, FAR, 5.82))] = ids["window"]
    door_hole = _box(p, (0.7, -1.1, 5.5), (1.6, 1.0, 5.95))
    lab[door_hole] = 0
    lab[door_hole & _box(p, (-FAR, -FAR, 5.62), (FAR, FAR, 5.78))] = ids["door"]

    table = _box(p, (-0.1, 0.2, 3.7), (1.3, 0.3, 4.5))
    for x0 in (-0.05, 1.1):
        for z0 in (3.75, 4.3):
            table |= _box(p, (x0, 0.3, z0), (x0 + 0.14, 1.0, z0 + 0.14))
    cabinet = _box(p, (-2.0, 0.15, 3.9), (-1.5, 1.0, 5.0))
    pedestal = _cylinder_y(p, (-0.8, 3.3), 0.2, (0.2, 1.0))
    lab[table | cabinet | pedestal] = ids["furniture"]
    lab[_sphere(p, (-0.8, -0.08, 3.3), 0.28)] = ids["sculpture"]
    return lab


def sample_model() -> FruxelModel:
    """The sample room as a :class:`FruxelModel` on :data:`GRID` with :data:`DEFAULT_CLASSES`."""
    return FruxelModel(room_labels(GRID), GRID, DEFAULT_CLASSES)

"""Procedural room models for benchmarks and demos: a room-like N^3 fruxel model and an oblique view of it.

The benchmarks (``benchmarks/``) and ``fruxel-render --benchmark`` (Table 1) all measure on these.

:func:`room_volume` paints, in the grid frame (OpenCV axes: x right, y down, z forward, metres), the sample
room's structure (:func:`fruxel.data.make_sample.room_labels`: floor, three walls, a window and a door with
their panes, a table, a cabinet, a pedestal and a small sculpture), then a sculpture blob (overlapping spheres)
and seeded furniture blocks resting on the floor until the requested fraction of cells is occupied. The result
depends only on ``(n, occupancy, seed)``.

Labels are :data:`fruxel.classes.DEFAULT_CLASSES` ids: 0 empty, 1 wall, 2 floor, 3 window, 4 furniture,
5 door, 6 sculpture.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from fruxel.camera import Camera, look_at_grid, orbit_direction
from fruxel.classes import DEFAULT_CLASSES
from fruxel.data.make_sample import room_labels
from fruxel.grid import FruxelGrid

Z_NEAR, Z_FAR, HFOV = 0.5, 6.0, 60.0
"""Grid of every room volume: depth range in metres and horizontal field of view in degrees."""
FLOOR_Y = 1.0
"""Top of the floor slab (y grows downwards), metres."""

_IDS = {name: i for i, name in enumerate(DEFAULT_CLASSES.names)}


def room_grid(n: int = 128) -> FruxelGrid:
    """The ``n x n x n`` grid of :func:`room_volume`."""
    return FruxelGrid(width=n, height=n, depth=n, z_near=Z_NEAR, z_far=Z_FAR, hfov=HFOV)


def _slices(grid: FruxelGrid, z_lo: float, z_hi: float) -> slice:
    """The slices whose cell centres can lie in ``[z_lo, z_hi]``."""
    zc = grid.z_near + (np.arange(grid.depth) + 0.5) * grid.dz
    k = np.flatnonzero((zc >= z_lo) & (zc <= z_hi))
    return slice(int(k[0]), int(k[-1]) + 1) if k.size else slice(0, 0)


def room_volume(n: int = 128, occupancy: float = 0.25, seed: int = 0) -> tuple[np.ndarray, FruxelGrid]:
    """A room-like ``n^3`` model with about ``occupancy`` of its cells occupied.

    Args:
        n: cells along each axis.
        occupancy: target fraction of occupied cells; the result has at least this (up to one furniture
            block more), or the structure's own occupancy where that is already higher.
        seed: seed of the sculpture and furniture placement.

    Returns:
        labels: ``(n, n, n)`` uint8 ``(D, H, W)``.
        grid: its :class:`FruxelGrid` (:func:`room_grid`).
    """
    grid = room_grid(n)
    rng = np.random.default_rng(seed)
    lab = room_labels(grid)
    centres = grid.cell_centres()
    target = int(math.ceil(occupancy * lab.size))

    # A sculpture blob: overlapping spheres around a point on the floor, left of centre.
    blob_c = np.array([rng.uniform(-1.4, -0.6), FLOOR_Y - 0.45, rng.uniform(2.2, 3.0)])
    for _ in range(6):
        c = blob_c + rng.normal(size=3) * [0.18, 0.15, 0.18]
        r = rng.uniform(0.15, 0.3)
        ks = _slices(grid, c[2] - r, c[2] + r)
        inside = np.sum((centres[ks] - c) ** 2, axis=-1) <= r * r
        sub = lab[ks]
        sub[inside & (sub == 0)] = _IDS["sculpture"]

    occupied = int(np.count_nonzero(lab))
    while occupied < target:
        # Furniture blocks: boxes standing on the floor, from low crates to tall shelves.
        cx, cz = rng.uniform(-2.0, 2.0), rng.uniform(1.0, 5.5)
        hx, hz = rng.uniform(0.1, 0.6), rng.uniform(0.1, 0.6)
        top = FLOOR_Y - rng.uniform(0.2, 2.0)
        ks = _slices(grid, cz - hz, cz + hz)
        p = centres[ks]
        solid = (np.abs(p[..., 0] - cx) <= hx) & (np.abs(p[..., 2] - cz) <= hz) & (p[..., 1] >= top)
        solid &= p[..., 1] <= FLOOR_Y
        sub = lab[ks]
        new = solid & (sub == 0)
        sub[new] = _IDS["furniture"]
        occupied += int(np.count_nonzero(new))
    return lab, grid


def oblique_camera(grid: FruxelGrid, size: int | tuple[int, int] = 512, hfov: float = 60.0) -> Camera:
    """A camera above, right of and in front of the grid, looking down at its centre at an angle.

    The eye is 0.85 diagonals of the frustum's bounding box from its centre, at 35 degrees azimuth and 30
    degrees elevation (grid frame, as :func:`fruxel.kernels.orbit_cameras` counts them): with the default 60
    degree field of view the whole frustum is just in view and fills most of a square image, and no image axis
    is parallel to a plane family, so rays cross all three families obliquely.

    Args:
        grid: the grid looked at.
        size: image side in pixels, or ``(width, height)``.
        hfov: horizontal field of view, degrees.
    """
    width, height = (size, size) if isinstance(size, (int, np.integer)) else (int(size[0]), int(size[1]))
    box = grid.bounds()
    r = 0.85 * float(np.linalg.norm(box[1] - box[0]))
    direction = orbit_direction(math.radians(35.0), math.radians(30.0))
    return look_at_grid(grid, direction, distance=r, width=width, height=height, hfov=hfov)


def describe(labels: np.ndarray) -> dict[str, Any]:
    """Occupied cells and the count per class of a label volume, for benchmark reports."""
    counts = np.bincount(labels.reshape(-1), minlength=len(DEFAULT_CLASSES.names))
    return {
        "occupied": int(labels.size - counts[0]),
        "occupancy": float(1.0 - counts[0] / labels.size),
        "classes": {name: int(c) for name, c in zip(DEFAULT_CLASSES.names, counts, strict=False) if c},
    }

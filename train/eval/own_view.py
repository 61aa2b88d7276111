"""Where own-view first-hit errors come from: the truth against what the camera actually sees.

The ground truth labels a cell by the solid that contains its *centre* (SPEC section 4, ``fruxelize``); the own
view's first hit is a column's first occupied cell. A camera, and so a network reading its image, sees the first
*surface* along the column instead. The two disagree where a solid along the column's centre ray contains no cell
centre (a board thinner than a cell's depth, 0.12 m at 64^3 over 0.5-8 m: the truth shows the wall behind it, or
a lattice of the board's cells where it happens to cross centres), and where the camera is closer than ``z_near``
to a surface (the image shows that surface; the truth starts behind it). :func:`visible_surface` casts each
column's centre ray against the scene's labelled meshes, and :class:`OwnViewBreakdown` splits the truth's own-view
pixels into

* ``clean``: the first surface seen lies in ``[z_near, z_far]`` and carries the truth's label,
* ``aliased``: it lies in that range but carries another label than the truth's first occupied cell,
* ``near``: the camera is closer than ``z_near`` to the first surface it sees,
* ``far``: the first surface seen lies beyond ``z_far``, or nothing is hit (the truth still hits: a rare grazing
  case),

and counts a prediction's own-view accuracy in each (``scripts/own_view_errors.py``). :func:`surface_extent` splits
the clean pixels further by how deep the first solid is along the ray: under a slice, whether the truth keeps it
depends on where within the slice it lies.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fruxel.grid import FruxelGrid

CATEGORIES = ("clean", "aliased", "near", "far")
"""The kinds of own-view pixel, in the order of :attr:`OwnViewBreakdown.hits`."""


class JoinedMeshes:
    """Labelled meshes joined into one mesh for many :func:`visible_surface` calls (the ray queries' acceleration
    structure is built with the first call and kept, as ``fruxelize``'s ``MeshSet`` keeps its upload).

    Args:
        meshes: ``(vertices (V, 3) float, faces (F, 3) int, label)`` per solid, world frame, metres (the input of
            ``fruxelize``, e.g. ``Scene.labelled_meshes()``).
    """

    def __init__(self, meshes: Sequence[tuple[np.ndarray, np.ndarray, int]]) -> None:
        import trimesh

        verts = [np.asarray(v, dtype=np.float64) for v, _, _ in meshes]
        start = np.cumsum([0] + [len(v) for v in verts[:-1]])
        faces = np.concatenate([np.asarray(f, dtype=np.int64) + s for (_, f, _), s in zip(meshes, start, strict=True)])
        self.mesh = trimesh.Trimesh(np.concatenate(verts), faces, process=False)
        """The joined mesh."""
        self.face_label = np.concatenate([np.full(len(f), int(lab), dtype=np.int64) for _, f, lab in meshes])
        """``(F,)`` int64 label of each face of :attr:`mesh`."""


def visible_surface(meshes: JoinedMeshes | Sequence[tuple[np.ndarray, np.ndarray, int]], grid: FruxelGrid,
                    pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first surface along each grid column's centre ray, as a camera sees it.

    Args:
        meshes: a :class:`JoinedMeshes` (faster for many poses of one scene), or the labelled meshes it takes.
        grid: the grid.
        pose: ``(4, 4)`` grid-camera-to-world transform, OpenCV axes.

    Returns:
        ``(labels (H, W) int64, depth (H, W) float64)``: the label of the first mesh surface hit and its depth along
        the camera's z axis in metres (from the optical centre, not from ``z_near``); 0 and ``inf`` where the ray
        hits nothing.
    """
    joined = meshes if isinstance(meshes, JoinedMeshes) else JoinedMeshes(meshes)
    pose = np.asarray(pose, dtype=np.float64)
    dirs = _centre_rays(grid, pose)
    origins = np.repeat(pose[None, :3, 3], len(dirs), axis=0)
    tri, ray, loc = _first_crossing(joined, origins, dirs)
    labels = np.zeros(len(dirs), dtype=np.int64)
    depth = np.full(len(dirs), np.inf)
    labels[ray] = joined.face_label[tri]
    depth[ray] = (loc - origins[ray]) @ pose[:3, 2]
    return labels.reshape(grid.height, grid.width), depth.reshape(grid.height, grid.width)


def surface_extent(meshes: JoinedMeshes, grid: FruxelGrid, pose: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """How deep, along each column's centre ray, the solid behind the first surface of :func:`visible_surface`
    reaches: the depth of the next surface the ray crosses (the solid's back face, for the closed, separate solids
    of a simulated room) minus the first surface's.

    A solid thinner than a slice (``grid.dz``) along the ray holds a cell centre or not depending on where, within
    a slice, it lies: whether the truth keeps it is a matter of centimetres that the image barely shows.

    Args:
        meshes: the scene's :class:`JoinedMeshes`.
        grid: the grid.
        pose: ``(4, 4)`` grid-camera-to-world transform, OpenCV axes.
        depth: ``(H, W)`` float64 first-surface depths of :func:`visible_surface` (``inf``: nothing hit).

    Returns:
        ``(H, W)`` float64 extent along the camera's z axis in metres; ``inf`` where nothing is hit, or where the
        ray finds no surface behind the first one.
    """
    h, w = grid.height, grid.width
    pose = np.asarray(pose, dtype=np.float64)
    start = np.asarray(depth, dtype=np.float64).reshape(-1)
    hit = np.isfinite(start)
    extent = np.full(h * w, np.inf)
    if not hit.any():
        return extent.reshape(h, w)
    # From just behind the first surface: the ray is inside the solid, and its first crossing is the way out.
    eps = 1e-4
    dirs = _centre_rays(grid, pose)[hit]
    origins = pose[None, :3, 3] + dirs * (start[hit, None] + eps)
    _, ray, loc = _first_crossing(meshes, origins, dirs)
    rows = np.flatnonzero(hit)[ray]
    extent[rows] = (loc - origins[ray]) @ pose[:3, 2] + eps
    return extent.reshape(h, w)


def _centre_rays(grid: FruxelGrid, pose: np.ndarray) -> np.ndarray:
    """``(H * W, 3)`` float64 world-frame directions of the columns' centre rays, row-major, scaled to z = 1 in
    the camera frame (so that a ray parameter is a depth)."""
    j, i = np.meshgrid(np.arange(grid.height), np.arange(grid.width), indexing="ij")
    d = grid.cell_to_point(np.zeros_like(j), j, i).reshape(-1, 3)
    return (d / d[:, 2:3]) @ pose[:3, :3].T


def _first_crossing(meshes: JoinedMeshes, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                      np.ndarray]:
    """The first crossing of each ray with the joined mesh: ``(face (K,), ray (K,), location (K, 3))`` for the K
    rays that cross it (trimesh's ``intersects_id`` without multiple hits)."""
    return meshes.mesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)


@dataclass
class OwnViewBreakdown:
    """Own-view pixels where the truth hits, by :data:`CATEGORIES`, and how many a prediction gets right in each."""

    hits: np.ndarray = field(default_factory=lambda: np.zeros(len(CATEGORIES), dtype=np.int64))
    """Pixels per category."""
    correct: np.ndarray = field(default_factory=lambda: np.zeros(len(CATEGORIES), dtype=np.int64))
    """... of which the prediction's first hit has the truth's label."""
    thin_hits: int = 0
    """``clean`` pixels whose first solid is thinner than a slice along the ray (counted when
    :meth:`add` gets ``seen_extent``)."""
    thin_correct: int = 0
    """... of which the prediction's first hit has the truth's label."""
    extents: int = 0
    """Views counted with ``seen_extent``."""

    def add(self, pred: np.ndarray, truth: np.ndarray, seen_label: np.ndarray, seen_depth: np.ndarray,
            grid: FruxelGrid, seen_extent: np.ndarray | None = None) -> None:
        """Count one view.

        Args:
            pred, truth: ``(H, W)`` integer labels of each column's first occupied cell (0 = none), e.g.
                :func:`fruxel.train.eval.metrics.first_surface` of the prediction and of the truth.
            seen_label, seen_depth: :func:`visible_surface` of the same view.
            grid: the grid.
            seen_extent: ``(H, W)`` :func:`surface_extent` of the same view, to split the clean pixels into thin
                (first solid under ``grid.dz`` deep along the ray) and the rest; None: not split.
        """
        hit = truth != 0
        in_range = (seen_depth >= grid.z_near) & (seen_depth <= grid.z_far)
        kinds = (in_range & (seen_label == truth), in_range & (seen_label != truth), seen_depth < grid.z_near,
                 seen_depth > grid.z_far)
        ok = pred == truth
        for c, m in enumerate(kinds):
            self.hits[c] += int((hit & m).sum())
            self.correct[c] += int((hit & m & ok).sum())
        if seen_extent is not None:
            thin = hit & kinds[0] & (seen_extent < grid.dz)
            self.thin_hits += int(thin.sum())
            self.thin_correct += int((thin & ok).sum())
            self.extents += 1

    def summary(self) -> dict[str, Any]:
        """Per category: its share of the truth's own-view pixels and the prediction's accuracy there (percent,
        None for an empty category); ``accuracy``: over all of them; ``lost``: points of that accuracy lost in each
        category. With extents counted, ``clean_thin`` and ``clean_thick`` split the clean pixels the same way."""
        total = int(self.hits.sum())

        def part(n: int, k: int) -> dict[str, float | None]:
            return {"share": 100.0 * n / total if total else None, "accuracy": 100.0 * k / n if n else None,
                    "lost": 100.0 * (n - k) / total if total else None}

        out: dict[str, Any] = {"pixels": total,
                               "accuracy": 100.0 * int(self.correct.sum()) / total if total else None}
        for c, name in enumerate(CATEGORIES):
            n, k = int(self.hits[c]), int(self.correct[c])
            out[name] = part(n, k)
        if self.extents:
            n, k = int(self.hits[0]), int(self.correct[0])
            out["clean_thin"] = part(self.thin_hits, self.thin_correct)
            out["clean_thick"] = part(n - self.thin_hits, k - self.thin_correct)
        return out

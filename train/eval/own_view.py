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

and counts a prediction's own-view accuracy in each (``scripts/own_view_errors.py``).
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
    h, w = grid.height, grid.width
    j, i = np.meshgrid(np.arange(h), np.arange(w), indexing="ij")
    d = grid.cell_to_point(np.zeros_like(j), j, i).reshape(-1, 3)
    d = d / d[:, 2:3]  # z = 1: the ray parameter is the depth
    pose = np.asarray(pose, dtype=np.float64)
    origins = np.repeat(pose[None, :3, 3], len(d), axis=0)
    dirs = d @ pose[:3, :3].T
    tri, ray, loc = joined.mesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)
    labels = np.zeros(len(d), dtype=np.int64)
    depth = np.full(len(d), np.inf)
    labels[ray] = joined.face_label[tri]
    depth[ray] = (loc - origins[ray]) @ pose[:3, 2]
    return labels.reshape(h, w), depth.reshape(h, w)


@dataclass
class OwnViewBreakdown:
    """Own-view pixels where the truth hits, by :data:`CATEGORIES`, and how many a prediction gets right in each."""

    hits: np.ndarray = field(default_factory=lambda: np.zeros(len(CATEGORIES), dtype=np.int64))
    """Pixels per category."""
    correct: np.ndarray = field(default_factory=lambda: np.zeros(len(CATEGORIES), dtype=np.int64))
    """... of which the prediction's first hit has the truth's label."""

    def add(self, pred: np.ndarray, truth: np.ndarray, seen_label: np.ndarray, seen_depth: np.ndarray,
            grid: FruxelGrid) -> None:
        """Count one view.

        Args:
            pred, truth: ``(H, W)`` integer labels of each column's first occupied cell (0 = none), e.g.
                :func:`fruxel.train.eval.metrics.first_surface` of the prediction and of the truth.
            seen_label, seen_depth: :func:`visible_surface` of the same view.
            grid: the grid.
        """
        hit = truth != 0
        in_range = (seen_depth >= grid.z_near) & (seen_depth <= grid.z_far)
        kinds = (in_range & (seen_label == truth), in_range & (seen_label != truth), seen_depth < grid.z_near,
                 seen_depth > grid.z_far)
        ok = pred == truth
        for c, m in enumerate(kinds):
            self.hits[c] += int((hit & m).sum())
            self.correct[c] += int((hit & m & ok).sum())

    def summary(self) -> dict[str, Any]:
        """Per category: its share of the truth's own-view pixels and the prediction's accuracy there (percent,
        None for an empty category); ``accuracy``: over all of them; ``lost``: points of that accuracy lost in each
        category."""
        total = int(self.hits.sum())
        out: dict[str, Any] = {"pixels": total,
                               "accuracy": 100.0 * int(self.correct.sum()) / total if total else None}
        for c, name in enumerate(CATEGORIES):
            n, k = int(self.hits[c]), int(self.correct[c])
            out[name] = {"share": 100.0 * n / total if total else None, "accuracy": 100.0 * k / n if n else None,
                         "lost": 100.0 * (n - k) / total if total else None}
        return out

"""first_hit against an independent ray caster: trimesh's ray-triangle intersector on the ``full`` trapezoid mesh.

The full mesh has one closed hexahedron (8 vertices, 12 triangles) per occupied cell, in the order of
``np.nonzero(labels)`` (see :func:`fruxel.mesh.mesh_labels`), so the first triangle a ray hits names its cell
(``face // 12``) and label. The mesh has float32 vertices and the intersector works in float64 with its own
tolerances, so the two may differ only where a ray passes next to a cell edge.
"""

from __future__ import annotations

from functools import cache

import numpy as np
import pytest

pytest.importorskip("trimesh")
pytest.importorskip("rtree")

from fruxel.camera import Camera  # noqa: E402
from fruxel.grid import FruxelGrid  # noqa: E402
from fruxel.kernels import orbit_cameras  # noqa: E402

from .conftest import BACKENDS, first_hit, hits_numpy, random_camera, random_labels  # noqa: E402
from .reference import edge_distance  # noqa: E402

MIN_AGREEMENT = 0.999
EDGE_DISTANCE = 1e-3
"""Cell units: how close to a cell edge a disagreement with the mesh oracle must be."""

GRID = FruxelGrid(12, 10, 9, z_near=0.5, z_far=3.5, hfov=70.0)
VIEW_KINDS = ("front", "beside", "far_side", "above", "behind_apex", "inside")


@cache
def _scene() -> tuple[np.ndarray, list[Camera]]:
    rng = np.random.default_rng(300)
    labels = random_labels(rng, GRID, 0.25)
    cams = []
    for kind in VIEW_KINDS:
        cam = random_camera(rng, GRID, kind, labels, size=(64, 48))
        k, j, i = GRID.point_to_cell(cam.position)
        if k >= 0 and labels[k, j, i]:
            # From inside a closed hexahedron the mesh is seen from its back; the kernels hit at t = 0.
            continue
        cams.append(cam)
    cams.append(orbit_cameras(GRID, 1, width=64, height=48)[0])
    return labels, cams


@cache
def _oracle(view: int) -> dict[str, np.ndarray]:
    """Per pixel of view ``view``: ``cell`` (-1 on a miss), ``label``, ``t`` and the hit ``point``."""
    import trimesh
    from trimesh.ray.ray_triangle import RayMeshIntersector

    from fruxel.classes import DEFAULT_CLASSES
    from fruxel.mesh import mesh_labels

    labels, cams = _scene()
    cam = cams[view]
    mesh = mesh_labels(labels, GRID, DEFAULT_CLASSES.palette(), mode="full")
    tm = trimesh.Trimesh(vertices=mesh.vertices.astype(np.float64), faces=mesh.faces, process=False, validate=False)
    o, d = cam.rays()
    h, w = o.shape[:2]
    tri, ray, loc = RayMeshIntersector(tm).intersects_id(
        o.reshape(-1, 3), d.reshape(-1, 3), multiple_hits=False, return_locations=True)
    cells = np.flatnonzero(labels)
    out = {"cell": np.full(h * w, -1, np.int64), "label": np.zeros(h * w, np.int32), "t": np.zeros(h * w),
           "point": np.zeros((h * w, 3))}
    dd = d.reshape(-1, 3)
    out["cell"][ray] = cells[tri // 12]
    out["label"][ray] = mesh.labels[tri]
    out["point"][ray] = loc
    out["t"][ray] = np.einsum("ij,ij->i", loc - o.reshape(-1, 3)[ray], dd[ray]) / np.einsum("ij,ij->i", dd[ray],
                                                                                             dd[ray])
    return {k: v.reshape((h, w) + v.shape[1:]) for k, v in out.items()}


def test_oracle_mesh_order_matches_cells() -> None:
    """The full mesh's hexahedron n is the n-th occupied cell: its 8 vertices are that cell's corners."""
    from fruxel.classes import DEFAULT_CLASSES
    from fruxel.mesh import mesh_labels

    labels, _ = _scene()
    mesh = mesh_labels(labels, GRID, DEFAULT_CLASSES.palette(), mode="full")
    k, j, i = np.nonzero(labels)
    corners = GRID.cell_corners(k, j, i).astype(np.float32)
    verts = mesh.vertices[mesh.faces.reshape(-1, 12, 3)].reshape(len(k), -1, 3)
    for n in range(0, len(k), max(1, len(k) // 25)):
        assert {tuple(v) for v in verts[n]} == {tuple(c) for c in corners[n]}
    np.testing.assert_array_equal(mesh.labels.reshape(-1, 12)[:, 0], labels[k, j, i])


@pytest.mark.parametrize("backend", BACKENDS)
def test_first_hit_agrees_with_mesh_ray_caster(backend: str) -> None:
    labels, cams = _scene()
    total = agree = hits = 0
    for view, cam in enumerate(cams):
        oracle = _oracle(view)
        got = hits_numpy(first_hit(backend, labels, GRID, cam))
        same = (got["cell"] == oracle["cell"]) & (got["label"] == oracle["label"])
        total += same.size
        agree += int(same.sum())
        hits += int((oracle["cell"] >= 0).sum())
        o, d = cam.rays()
        for y, x in zip(*np.nonzero(~same), strict=True):
            points = []
            if oracle["cell"][y, x] >= 0:
                points.append(oracle["point"][y, x])
            if got["cell"][y, x] >= 0:
                points.append(o[y, x] + float(got["depth"][y, x]) * d[y, x])
            dist = edge_distance(GRID, np.array(points)).min()
            assert dist <= EDGE_DISTANCE, (
                f"view {view} pixel ({y}, {x}): cell {got['cell'][y, x]} vs mesh {oracle['cell'][y, x]}, "
                f"{dist:.2e} cell units from the nearest edge")
        both = same & (oracle["cell"] >= 0)
        np.testing.assert_allclose(got["depth"][both], oracle["t"][both], rtol=1e-4, atol=1e-5)
    assert agree >= MIN_AGREEMENT * total, f"only {agree} of {total} pixels agree with the mesh oracle"
    assert hits > 0.3 * total

"""fruxelize: labels against independent point-in-solid tests at the cell centres.

References: trimesh's ``contains`` (ray tests, run per watertight component, since it is not meant for
overlapping or touching pieces in one mesh) for closed meshes, and an exact numpy generalised winding number
(Van Oosterom-Strackee solid angles) for open ones. Agreement must be at least 99.5 %, and every disagreement
must lie within float32 rounding of a surface.
"""

from __future__ import annotations

import numpy as np
import pytest

from fruxel.camera import Camera, CameraError
from fruxel.grid import FruxelGrid
from fruxel.kernels import BackendError, fruxelize
from fruxel.kernels.fruxelize import MAX_CROSSINGS, MeshError, MeshSet, prepare_meshes

trimesh = pytest.importorskip("trimesh")
pytest.importorskip("warp")

SURFACE_TOL = 1e-4
"""Metres: a centre this close to a surface may fall on either side after float32 rounding."""


def _pose(eye, target) -> np.ndarray:
    """Grid-camera-to-world pose looking from ``eye`` at ``target`` with world z up."""
    return Camera.look_at(eye, target, up=(0.0, 0.0, 1.0)).pose.copy()


def _world_centres(grid: FruxelGrid, pose: np.ndarray) -> np.ndarray:
    return grid.cell_centres().reshape(-1, 3) @ pose[:3, :3].T + pose[:3, 3]


def _contains(mesh, points: np.ndarray) -> np.ndarray:
    """Union of trimesh ``contains`` over the watertight components (bounding-box culled)."""
    out = np.zeros(len(points), dtype=bool)
    for comp in mesh.split(only_watertight=False):
        lo, hi = comp.bounds
        sel = np.flatnonzero(np.all((points >= lo - 1e-9) & (points <= hi + 1e-9), axis=1))
        if len(sel):
            out[sel[comp.contains(points[sel])]] = True
    return out


def _surface_distance(meshes, points: np.ndarray) -> np.ndarray:
    d = np.full(len(points), np.inf)
    if len(points) == 0:
        return d
    for m in meshes:
        _, dist, _ = trimesh.proximity.closest_point(m, points)
        d = np.minimum(d, dist)
    return d


def _winding_numbers(vertices: np.ndarray, faces: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Exact generalised winding number of each point (Van Oosterom-Strackee), ``(N,)`` float64."""
    tri = vertices[faces]
    out = np.zeros(len(points))
    for start in range(0, len(points), 2048):
        p = points[start:start + 2048]
        a, b, c = (tri[None, :, k, :] - p[:, None, :] for k in range(3))
        la, lb, lc = (np.linalg.norm(x, axis=-1) for x in (a, b, c))
        det = np.einsum("...i,...i->...", a, np.cross(b, c))
        den = (la * lb * lc + np.einsum("...i,...i->...", a, b) * lc + np.einsum("...i,...i->...", b, c) * la
               + np.einsum("...i,...i->...", c, a) * lb)
        out[start:start + 2048] = (2.0 * np.arctan2(det, den)).sum(axis=1) / (4.0 * np.pi)
    return out


def _check(labels: np.ndarray, ref: np.ndarray, meshes, centres: np.ndarray) -> None:
    bad = np.flatnonzero(labels.reshape(-1) != ref)
    assert 1.0 - len(bad) / ref.size >= 0.995, f"{len(bad)} of {ref.size} cells disagree"
    if len(bad):
        dist = _surface_distance(meshes, centres[bad])
        assert dist.max() < SURFACE_TOL, f"a disagreeing cell centre lies {dist.max():.3g} m from every surface"


@pytest.fixture(scope="module")
def grid() -> FruxelGrid:
    return FruxelGrid(width=40, height=30, depth=48, z_near=0.4, z_far=7.0, hfov=70.0)


def _solids(rng: np.random.Generator) -> list:
    out = []
    for _ in range(3):
        b = trimesh.creation.box(extents=rng.uniform(0.4, 1.5, 3))
        b.apply_transform(trimesh.transformations.random_rotation_matrix(rng.uniform(size=3)))
        b.apply_translation(rng.uniform([2.0, -1.5, -1.0], [5.0, 1.5, 1.0]))
        out.append(b)
    s = trimesh.creation.icosphere(subdivisions=2, radius=rng.uniform(0.4, 0.9))
    s.apply_translation(rng.uniform([2.0, -1.0, -0.5], [4.5, 1.0, 0.5]))
    out.append(s)
    c = trimesh.creation.cylinder(radius=0.3, height=1.5, sections=24)
    c.apply_translation(rng.uniform([2.0, -1.0, -0.5], [4.5, 1.0, 0.5]))
    out.append(c)
    return out


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_matches_contains_with_later_winning(grid: FruxelGrid, seed: int) -> None:
    rng = np.random.default_rng(seed)
    solids = _solids(rng)
    labels_of = [4, 6, 1, 3, 5]
    pose = _pose(rng.uniform(-0.3, 0.3, 3), [4.0, 0.0, 0.0] + rng.uniform(-0.5, 0.5, 3))
    labels = fruxelize([(m.vertices, m.faces, lab) for m, lab in zip(solids, labels_of, strict=True)], grid, pose)
    assert labels.shape == grid.shape and labels.dtype == np.uint8
    centres = _world_centres(grid, pose)
    ref = np.zeros(len(centres), dtype=np.uint8)
    for m, lab in zip(solids, labels_of, strict=True):
        ref[_contains(m, centres)] = lab
    assert len(np.unique(ref)) >= 4, "the test scene should show several labels"
    _check(labels, ref, solids, centres)


def test_touching_and_overlapping_pieces_in_one_mesh(grid: FruxelGrid) -> None:
    """A table: top and legs touch along whole faces, a handle overlaps the top; one mesh, one label."""
    top = trimesh.creation.box(bounds=[[2.0, -0.6, -0.2], [3.2, 0.6, -0.16]])
    legs = [trimesh.creation.box(bounds=[[x, y, -0.9], [x + 0.06, y + 0.06, -0.2]])
            for x in (2.05, 3.09) for y in (-0.55, 0.49)]
    knob = trimesh.creation.box(bounds=[[2.5, -0.1, -0.25], [2.7, 0.1, -0.1]])
    table = trimesh.util.concatenate([top, *legs, knob])
    pose = _pose([0.0, 0.1, 0.3], [2.6, 0.0, -0.4])
    labels, fallbacks = fruxelize([(table, 4)], grid, pose, return_fallbacks=True)
    centres = _world_centres(grid, pose)
    ref = np.where(_contains(table, centres), 4, 0)
    assert ref.sum() > 0
    _check(labels, ref, [table], centres)
    assert fallbacks == 0
    assert prepare_meshes([(table, 4)]).n_parts == 6


def test_inverted_mesh_is_still_solid(grid: FruxelGrid) -> None:
    box = trimesh.creation.box(bounds=[[2.0, -0.5, -0.5], [3.0, 0.5, 0.5]])
    pose = _pose([0.0, 0.0, 0.0], [2.5, 0.0, 0.0])
    a = fruxelize([(box.vertices, box.faces, 3)], grid, pose)
    b = fruxelize([(box.vertices, box.faces[:, ::-1], 3)], grid, pose)
    assert a.any()
    np.testing.assert_array_equal(a, b)


def test_open_mesh_uses_the_winding_number(grid: FruxelGrid) -> None:
    """A box with its top missing, and a bowl-like half sphere: inside is winding number >= 1/2."""
    box = trimesh.creation.box(bounds=[[2.0, -0.6, -0.6], [3.2, 0.6, 0.6]])
    keep = box.face_normals[:, 2] < 0.5
    open_box = trimesh.Trimesh(box.vertices, box.faces[keep], process=False)
    sphere = trimesh.creation.icosphere(subdivisions=3, radius=0.5)
    bowl = trimesh.Trimesh(sphere.vertices, sphere.faces[sphere.triangles_center[:, 1] < 0.2], process=False)
    bowl.apply_translation([4.0, 0.0, 0.2])
    assert not open_box.is_watertight and not bowl.is_watertight
    pose = _pose([0.0, -0.4, 1.2], [3.0, 0.0, 0.0])
    meshes = [(open_box.vertices, open_box.faces, 4), (bowl.vertices, bowl.faces, 6)]
    parts = prepare_meshes(meshes)
    assert list(parts.part_kind) == [1, 1]
    labels = fruxelize(meshes, grid, pose)
    centres = _world_centres(grid, pose)
    ref = np.zeros(len(centres), dtype=np.uint8)
    wn = {}
    for m, lab in ((open_box, 4), (bowl, 6)):
        lo, hi = m.bounds
        sel = np.flatnonzero(np.all((centres >= lo) & (centres <= hi), axis=1))
        wn[lab] = np.zeros(len(centres))
        wn[lab][sel] = _winding_numbers(m.vertices, m.faces, centres[sel])
        ref[wn[lab] >= 0.5] = lab
    assert (ref == 4).sum() > 50 and (ref == 6).sum() > 10
    bad = np.flatnonzero(labels.reshape(-1) != ref)
    assert 1.0 - len(bad) / ref.size >= 0.995
    # Warp evaluates far triangles by a dipole expansion: only centres near the threshold may differ.
    near = np.minimum(np.abs(wn[4][bad] - 0.5), np.abs(wn[6][bad] - 0.5)) < 0.05
    close = _surface_distance([open_box, bowl], centres[bad]) < SURFACE_TOL
    assert np.all(near | close)


def test_many_crossings_fall_back_to_the_parity_vote(grid: FruxelGrid) -> None:
    """One closed comb with more than MAX_CROSSINGS faces along the view: the walk overflows, the per-centre
    vote must still give the solid."""
    from fruxel.train.sim.scene import slab_with_holes

    n_slots = MAX_CROSSINGS // 2 + 4
    pitch = 0.12
    holes = [(0.05 + k * pitch, 0.1, 0.05 + k * pitch + pitch / 2, 0.9) for k in range(n_slots)]
    v, f = slab_with_holes(0.1 + n_slots * pitch, 1.0, 0.6, holes)
    comb = trimesh.Trimesh(v, f, process=False)
    assert comb.is_watertight and comb.body_count == 1
    # Stand the comb so that the teeth cross the optical axis (+x): slab x -> world x, slab z -> world y.
    comb.apply_transform([[1, 0, 0, 1.0], [0, 0, 1, -0.5], [0, -1, 0, 0.3], [0, 0, 0, 1]])
    pose = _pose([0.0, 0.0, 0.0], [3.0, 0.0, 0.0])
    labels, fallbacks = fruxelize([(comb, 1)], grid, pose, return_fallbacks=True)
    assert fallbacks > 0
    centres = _world_centres(grid, pose)
    ref = np.where(_contains(comb, centres), 1, 0)
    assert ref.sum() > 100
    _check(labels, ref, [comb], centres)


def test_priority_is_list_order(grid: FruxelGrid) -> None:
    a = trimesh.creation.box(bounds=[[2.0, -0.5, -0.5], [3.0, 0.5, 0.5]])
    b = trimesh.creation.box(bounds=[[2.5, -0.2, -0.2], [3.5, 0.2, 0.2]])
    pose = _pose([0.0, 0.0, 0.0], [2.5, 0.0, 0.0])
    ab = fruxelize([(a, 1), (b, 5)], grid, pose)
    ba = fruxelize([(b, 5), (a, 1)], grid, pose)
    centres = _world_centres(grid, pose).reshape(*grid.shape, 3)
    both = _contains(a, centres.reshape(-1, 3)) & _contains(b, centres.reshape(-1, 3))
    both = both.reshape(grid.shape)
    assert both.sum() > 10
    assert np.all(ab[both] == 5) and np.all(ba[both] == 1)
    carve = fruxelize([(a, 1), (b, 0)], grid, pose)
    assert np.all(carve[both] == 0) and carve.any()


def test_mesh_set_is_reusable_and_accepts_scene_objects(grid: FruxelGrid) -> None:
    from fruxel.train.sim import make_scene, random_trajectory

    scene = make_scene(3)
    traj = random_trajectory(scene, 3, seed=3, steps_per_frame=5)
    mesh_set = MeshSet(scene.objects)
    for pose in traj.poses:
        np.testing.assert_array_equal(fruxelize(mesh_set, grid, pose), fruxelize(scene.labelled_meshes(), grid, pose))


def test_scene_ground_truth_matches_contains() -> None:
    from fruxel.train.sim import make_scene, random_trajectory

    grid = FruxelGrid(width=48, height=36, depth=40, z_near=0.3, z_far=7.0, hfov=70.0)
    rng = np.random.default_rng(7)
    for seed in (0, 1):
        scene = make_scene(seed)
        pose = random_trajectory(scene, 4, seed=seed, steps_per_frame=3).poses[-1]
        labels = fruxelize(scene.objects, grid, pose).reshape(-1)
        centres = _world_centres(grid, pose)
        idx = rng.choice(len(centres), 4000, replace=False)
        ref = np.zeros(len(idx), dtype=np.uint8)
        for o in scene.objects:
            ref[_contains(o.mesh, centres[idx])] = o.label
        assert len(np.unique(ref)) >= 3
        _check(labels[idx], ref, [o.mesh for o in scene.objects], centres[idx])


def test_the_gpus_kernel_of_part_column_pairs_labels_as_the_cpus_of_columns(grid: FruxelGrid) -> None:
    """On a GPU fruxelize runs one thread a (part, column) pair, on the CPU one a column; both run here on Warp's CPU
    device and label every cell alike: closed and open parts, overlaps won by the later mesh, a mesh of label 0
    carving, and a simulator room; the parity vote's count too."""
    import importlib

    from fruxel.train.sim import make_scene, random_trajectory

    wpf = importlib.import_module("fruxel.kernels.wp.fruxelize")
    rng = np.random.default_rng(3)
    solids = _solids(rng)
    opened = trimesh.creation.box(extents=(1.2, 1.0, 0.8)).apply_translation((3.5, 0.0, 0.0))
    opened = trimesh.Trimesh(opened.vertices, opened.faces[:-2], process=False)
    carve = trimesh.creation.box(extents=(0.6, 0.6, 0.6)).apply_translation((3.4, 0.1, 0.0))
    pose = _pose((0.0, 0.0, 0.2), (4.0, 0.0, 0.0))
    scene = make_scene(2)
    cases = [([(m, 1 + k % 5) for k, m in enumerate(solids)] + [(opened, 6), (carve, 0)], grid, pose),
             (scene.objects, grid, random_trajectory(scene, 4, seed=2, steps_per_frame=3).poses[-1])]
    for meshes, g, p in cases:
        native = MeshSet(meshes, device="cpu").native
        by_pairs, pair_falls = wpf.fruxelize(native, g, p, pairs=True)
        by_columns, column_falls = wpf.fruxelize(native, g, p, pairs=False)
        assert len(np.unique(by_columns)) >= 3
        np.testing.assert_array_equal(by_pairs, by_columns)
        assert pair_falls == column_falls


def test_bad_input_is_refused(grid: FruxelGrid) -> None:
    box = trimesh.creation.box()
    pose = np.eye(4)
    with pytest.raises(MeshError):
        fruxelize([(box.vertices[:, :2], box.faces, 1)], grid, pose)
    with pytest.raises(MeshError):
        fruxelize([(box.vertices, box.faces + 100, 1)], grid, pose)
    with pytest.raises(MeshError):
        fruxelize([(box.vertices, box.faces, 256)], grid, pose)
    with pytest.raises(MeshError):
        fruxelize([(np.full((3, 3), np.nan), [[0, 1, 2]], 1)], grid, pose)
    with pytest.raises(MeshError):
        fruxelize([box], grid, pose)
    with pytest.raises(CameraError):
        fruxelize([(box, 1)], grid, np.diag([2.0, 1.0, 1.0, 1.0]))
    with pytest.raises(BackendError):
        fruxelize([(box, 1)], grid, pose, backend="opencl")
    assert not fruxelize([], grid, pose).any()


def _parts_arrays(parts) -> list[np.ndarray]:
    out = [np.asarray(getattr(parts, name)) for name in (
        "closed_vertices", "closed_faces", "closed_group", "part_kind", "part_ref", "part_label", "part_lo", "part_hi",
        "mesh_first_part", "mesh_lo", "mesh_hi")]
    return out + [a for pair in parts.open_meshes for a in pair]


def test_a_mesh_met_again_is_split_as_the_first_time(monkeypatch: pytest.MonkeyPatch) -> None:
    """Meshes with the faces of one met before (a furniture model in another room, moved) reuse its split plan: the
    parts are those of a process that never saw it, closed and open pieces alike, and the shared plan is
    read-only."""
    import importlib

    fz = importlib.import_module("fruxel.kernels.fruxelize")
    touching = trimesh.util.concatenate([trimesh.creation.box(extents=(1, 1, 1)),
                                         trimesh.creation.box(extents=(1, 1, 1)).apply_translation((1, 0, 0))])
    box = trimesh.creation.box(extents=(2, 1, 0.1))
    faces = np.asarray(box.faces).copy()
    faces[-2:] = faces[-2:, ::-1]  # two faces wound the other way: open, with as many faces as the closed box
    flipped = trimesh.Trimesh(box.vertices, faces, process=False)
    scene = [(touching, 2), (box, 4), (flipped, 5), (trimesh.creation.icosphere(subdivisions=1), 3)]

    def moved(offset: float) -> list:
        return [(m.copy().apply_translation((offset, 2 * offset, 0)), label) for m, label in scene]

    monkeypatch.setattr(fz, "_plans", type(fz._plans)())
    prepare_meshes(moved(0.0))
    assert len(fz._plans) >= 3
    cached = prepare_meshes(moved(1.5))
    monkeypatch.setattr(fz, "_plans", type(fz._plans)())
    fresh = prepare_meshes(moved(1.5))
    assert cached.part_kind.tolist() == [0, 0, 0, 1, 0]
    for a, b in zip(_parts_arrays(cached), _parts_arrays(fresh), strict=True):
        np.testing.assert_array_equal(a, b)
    plan = next(iter(fz._plans.values()))
    with pytest.raises(ValueError, match="read-only"):
        plan.open_faces[...] = 0


def test_the_split_plans_kept_are_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    import importlib

    fz = importlib.import_module("fruxel.kernels.fruxelize")
    monkeypatch.setattr(fz, "_plans", type(fz._plans)())
    monkeypatch.setattr(fz, "SPLIT_PLANS", 3)
    box = trimesh.creation.box()
    for n in range(5):
        prepare_meshes([(np.asarray(box.vertices), np.roll(np.asarray(box.faces), n, axis=0), 1)])
    assert len(fz._plans) == 3


def test_part_bounds_are_those_of_each_parts_faces() -> None:
    """A part's bounds come from its own vertices (grouped by part in the split plan): equal to the bounds of its
    faces' corners, with the parts' vertices interleaved in the mesh and a vertex no face uses lying far out."""
    from fruxel.kernels.fruxelize import _pad, prepare_meshes

    rng = np.random.default_rng(3)
    boxes = [trimesh.creation.box(extents=rng.uniform(0.2, 1.0, 3)).apply_translation(rng.uniform(-3, 3, 3))
             for _ in range(4)]
    v = np.concatenate([b.vertices for b in boxes] + [[[50.0, 50.0, 50.0]]])
    f = np.concatenate([b.faces + 8 * k for k, b in enumerate(boxes)])
    perm = rng.permutation(len(v) - 1)  # shuffle the boxes' vertices together; the stray one stays last
    inv = np.empty_like(perm)
    inv[perm] = np.arange(len(perm))
    v = np.concatenate([v[:-1][perm], v[-1:]])
    f = inv[f]
    parts = prepare_meshes([(v, f, 1)])
    assert len(parts.part_lo) == 4 and (parts.part_kind == 0).all()
    tri = parts.closed_vertices[parts.closed_faces]
    for p in range(4):
        mine = tri[parts.closed_group == p].reshape(-1, 3)
        lo, hi = _pad(mine.min(axis=0, keepdims=True), mine.max(axis=0, keepdims=True))  # the walk's margin
        np.testing.assert_array_equal(parts.part_lo[p], lo[0])
        np.testing.assert_array_equal(parts.part_hi[p], hi[0])

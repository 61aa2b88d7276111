"""The solids the furnished rooms' pieces are labelled by (fruxel.train.sim.rooms.solids): pack meshes that are
not closed are filled, thin upright slabs thickened, and the labels of a room follow them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import trimesh

from fruxel.grid import FruxelGrid
from fruxel.kernels.fruxelize import fruxelize
from fruxel.train.sim.rooms import solids


def _hollow_cabinet() -> tuple[np.ndarray, np.ndarray]:
    """A 0.8 x 0.5 x 1.0 m box of single faces, open at the bottom, every other face wound the wrong way (as
    Sweet Home 3D's meshes come): its winding number inside is about 0, so it labelled nothing inside."""
    box = trimesh.creation.box((0.8, 0.5, 1.0))
    box.apply_translation((0.0, 0.0, 0.5))
    faces = box.faces[box.face_normals[:, 2] > -0.5].copy()
    faces[::2] = faces[::2, ::-1]
    return np.asarray(box.vertices, dtype=np.float64), faces.astype(np.int64)


def _grid_facing(centre_distance: float) -> tuple[FruxelGrid, np.ndarray]:
    """A 16^3 grid whose camera stands ``centre_distance`` m in front of the origin, looking along +y (world z up)."""
    grid = FruxelGrid(16, 16, 16, 0.5, 4.0, 60.0)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, 1.0], [0.0, -1.0, 0.0]])  # x right, y down = -z, z fwd = +y
    pose[:3, 3] = (0.0, -centre_distance, 0.5)
    return grid, pose


def test_a_voxel_is_a_closed_box_with_outward_faces() -> None:
    v, f = solids.voxel_mesh(np.ones((1, 1, 1), dtype=bool), np.array([1.0, 2.0, 3.0]), 0.1)
    mesh = trimesh.Trimesh(v, f, process=False)
    assert len(f) == 12 and mesh.is_watertight and mesh.is_winding_consistent
    assert mesh.volume == pytest.approx(1e-3) and np.allclose(v.min(axis=0), [1.0, 2.0, 3.0])


def test_a_hollow_cabinet_is_filled_and_labels_its_inside() -> None:
    v, f = _hollow_cabinet()
    assert not solids.is_closed(v, f)
    sv, sf = solids.filled_solid(v, f)
    filled = trimesh.Trimesh(sv, sf, process=False)
    assert filled.is_watertight and 0.4 <= filled.volume <= 0.4 * 1.3  # the box, grown by half a voxel at most
    grid, pose = _grid_facing(2.0)
    raw = fruxelize([(v, f, 3)], grid, pose)
    solid = fruxelize([(sv, sf, 3)], grid, pose)
    # cells whose centres lie well inside the cabinet (its middle third in every direction)
    centres = grid.cell_centres() @ pose[:3, :3].T + pose[:3, 3]
    inside = (np.abs(centres[..., 0]) < 0.13) & (np.abs(centres[..., 1]) < 0.08) & \
        (np.abs(centres[..., 2] - 0.5) < 0.16)
    assert inside.sum() >= 2
    assert (solid[inside] == 3).all() and (raw[inside] == 3).mean() < 0.5


@pytest.mark.parametrize("thin_axis, changed", [(1, True), (2, False)])
def test_thin_upright_slabs_are_thickened_and_flat_ones_are_not(thin_axis: int, changed: bool) -> None:
    size = np.array([0.9, 0.9, 0.9])
    size[thin_axis] = 0.03
    box = trimesh.creation.box(size)
    other = trimesh.creation.box((0.3, 0.3, 0.3))
    other.apply_translation((2.0, 0.0, 0.0))
    both = trimesh.util.concatenate([box, other])
    v = solids.thicken_slabs(both.vertices, both.faces, 0.12)
    n = len(box.vertices)
    extent = np.ptp(v[:n], axis=0)
    assert extent[thin_axis] == pytest.approx(0.12 if changed else 0.03)
    assert np.allclose(v[:n].mean(axis=0), box.vertices.mean(axis=0))  # about its middle
    assert np.array_equal(v[n:], both.vertices[n:])  # a part that is not thin keeps its vertices


def test_affine_map_recovers_a_placement_and_refuses_what_is_not_one() -> None:
    rng = np.random.default_rng(0)
    src = rng.uniform(-1, 1, (50, 3))
    yaw = 0.7
    r = np.array([[np.cos(yaw), -np.sin(yaw), 0.0], [np.sin(yaw), np.cos(yaw), 0.0], [0.0, 0.0, 1.0]])
    dst = (src * [1.1, 1.1, 0.8]) @ r.T + [3.0, -2.0, 0.4]
    m = solids.affine_map(src, dst)
    assert m is not None and np.allclose(np.column_stack([src, np.ones(50)]) @ m, dst)
    assert solids.affine_map(src, dst[:-1]) is None
    bent = dst.copy()
    bent[:, 2] += 0.1 * src[:, 0] ** 2
    assert solids.affine_map(src, bent) is None


def test_a_furnished_room_labels_its_pieces_by_their_solids(pack_dir: Path, tmp_path: Path,
                                                              monkeypatch: pytest.MonkeyPatch) -> None:
    """Every piece of a room made from a pack mesh that is not closed is labelled by a solid that is; the room's
    labelled meshes are those solids; the solids are kept once per machine and read back the same."""
    from fruxel.classes import HOME_CLASSES
    from fruxel.train.sim.rooms import HomeConfig, make_home
    from fruxel.train.sim.rooms.library import Library, library

    monkeypatch.setenv("FRUXEL_CACHE_DIR", str(tmp_path))
    scene = make_home(3, HomeConfig(), HOME_CLASSES, assets=str(pack_dir), split="train")
    lib = library(str(pack_dir))
    open_pack = [o for o in scene.objects if o.asset and o.solid and lib.solid(o.asset) is not None]
    assert open_pack, "the tiny pack's room has no piece from an open mesh"
    for o in open_pack:
        # the prop's solid, placed as the piece (not the piece's own mesh, thickened or not)
        assert o.label_mesh is not None and np.array_equal(o.label_mesh[1], lib.solid(o.asset)[1]), o.name
        # a solid: its faces enclose a positive volume (wound outwards), whatever the pack mesh's winding was
        tri = o.label_mesh[0][o.label_mesh[1]]
        assert np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() / 6 > 1e-4
    meshes = scene.labelled_meshes()
    by_name = [o for o in scene.objects if o.solid]
    assert all(np.array_equal(m[0], o.label_mesh[0]) for m, o in zip(meshes, by_name, strict=True)
               if o.label_mesh is not None)
    fresh = Library(Path(pack_dir))  # the process's library may hold its solids already: a new one makes them
    kept = fresh.solid(open_pack[0].asset)
    assert kept is not None and list((tmp_path / "pack").glob("solid-*-v.npy"))
    assert all(np.array_equal(a, b) for a, b in zip(kept, lib.solid(open_pack[0].asset), strict=True))
    again = make_home(3, HomeConfig(), HOME_CLASSES, assets=str(pack_dir), split="train")
    assert all(np.array_equal(a.label_mesh[0], b.label_mesh[0]) for a, b in zip(scene.objects, again.objects,
                                                                               strict=True)
               if a.label_mesh is not None)


def test_a_home_config_recorded_before_the_solids_makes_the_rooms_it_made(pack_dir: Path) -> None:
    """A data set's config written before the label solids (no ``filled_solids``, no ``label_thickness`` in its
    ``home``) reads as labelling every mesh as it is, so that its missing shards are made as its others were."""
    from fruxel.classes import HOME_CLASSES
    from fruxel.train.sim.config import SimConfig
    from fruxel.train.sim.rooms import HomeConfig, make_home

    config = SimConfig(world="home", renderer="raytrace", classes=HOME_CLASSES, assets=str(pack_dir))
    d = config.to_dict()
    d["home"] = {k: v for k, v in d.get("home", _plain_home()).items()
                 if k not in ("filled_solids", "label_thickness")}
    old = SimConfig.from_dict(d).home
    assert old.filled_solids is False and old.label_thickness == 0.0
    assert HomeConfig().filled_solids is True and HomeConfig().label_thickness == pytest.approx(0.12)
    scene = make_home(3, old, HOME_CLASSES, assets=str(pack_dir), split="train")
    assert all(o.label_mesh is None for o in scene.objects)


def _plain_home() -> dict:
    from fruxel.train.sim.config import _plain
    from fruxel.train.sim.rooms import HomeConfig

    return _plain(HomeConfig())

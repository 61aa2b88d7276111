"""Procedural rooms and the asset importers."""

from __future__ import annotations

import zipfile
from pathlib import Path

import numpy as np
import pytest

from fruxel.classes import DEFAULT_CLASSES, ClassTable
from fruxel.train.sim import (
    CLASS_NAMES,
    AssetError,
    RoomConfig,
    SceneError,
    load_asset_folder,
    load_sh3f,
    make_scene,
)
from fruxel.train.sim.assets import parse_properties
from fruxel.train.sim.scene import slab_with_holes

trimesh = pytest.importorskip("trimesh")

WALL, FLOOR, WINDOW, FURNITURE, DOOR, SCULPTURE = (DEFAULT_CLASSES.index(n) for n in CLASS_NAMES)


def _same(a, b) -> None:
    assert [o.name for o in a.objects] == [o.name for o in b.objects]
    for x, y in zip(a.objects, b.objects, strict=True):
        np.testing.assert_array_equal(x.mesh.vertices, y.mesh.vertices)
        np.testing.assert_array_equal(x.mesh.faces, y.mesh.faces)
        assert (x.label, x.color, x.metallic, x.roughness) == (y.label, y.color, y.metallic, y.roughness)
    np.testing.assert_array_equal(a.room_size, b.room_size)
    np.testing.assert_array_equal(a.free_space.occupied, b.free_space.occupied)
    for la, lb in zip(a.lights, b.lights, strict=True):
        np.testing.assert_array_equal(la.pose, lb.pose)
        assert (la.kind, la.color, la.intensity) == (lb.kind, lb.color, lb.intensity)


def test_same_seed_same_scene() -> None:
    _same(make_scene(11), make_scene(11))
    a, b = make_scene(11), make_scene(12)
    assert not np.array_equal(a.room_size, b.room_size)


@pytest.mark.parametrize("seed", range(6))
def test_rooms_are_closed_labelled_solids(seed: int) -> None:
    scene = make_scene(seed)
    labels = [o.label for o in scene.objects]
    assert labels.count(FLOOR) == 1 and labels.count(WALL) == 4
    assert WINDOW in labels and DOOR in labels and FURNITURE in labels
    assert set(labels) <= {WALL, FLOOR, WINDOW, FURNITURE, DOOR, SCULPTURE}
    assert len({o.name for o in scene.objects}) == len(scene.objects)
    order = [FLOOR, WALL, WINDOW, DOOR, FURNITURE, SCULPTURE]
    assert [order.index(v) for v in labels] == sorted(order.index(v) for v in labels), "priority order"
    lx, ly, lz = scene.room_size
    for o in scene.objects:
        m = o.mesh
        assert m.is_watertight and m.is_winding_consistent, o.name
        for body in m.split(only_watertight=False):
            assert body.volume > 0, f"{o.name}: a piece has inward normals"
        assert len(o.color) == 4 and all(0.0 <= c <= 1.0 for c in o.color)
        assert 0.0 <= o.metallic <= 1.0 and 0.0 <= o.roughness <= 1.0
        if o.label in (FURNITURE, SCULPTURE):
            lo, hi = m.bounds
            assert lo[0] >= 0 and lo[1] >= 0 and hi[0] <= lx and hi[1] <= ly and lo[2] >= -1e-9, o.name
            assert hi[2] <= lz
    for light in scene.lights:
        assert light.kind in ("directional", "point") and light.intensity > 0
        np.testing.assert_allclose(light.pose[:3, :3] @ light.pose[:3, :3].T, np.eye(3), atol=1e-12)


def test_openings_are_real_holes_filled_by_their_objects() -> None:
    scene = make_scene(5, RoomConfig(windows=(2, 2), doors=(1, 1)))
    walls = [o.mesh for o in scene.objects if o.label == WALL]
    by_name = {o.name: o for o in scene.objects}
    openings = [n[:-len("_frame")] for n in by_name if n.endswith("_frame")]
    assert len(openings) == 3
    rng = np.random.default_rng(0)
    for name in openings:
        frame = by_name[f"{name}_frame"]
        filler = by_name.get(f"{name}_glass") or by_name[f"{name}_leaf"]
        assert frame.label == filler.label == (WINDOW if name.startswith("window") else DOOR)
        lo, hi = filler.mesh.bounds
        # Points inside the glass or leaf: in the filler's solid and in no wall, so the wall has a real hole.
        pts = lo + (hi - lo) * rng.uniform(0.05, 0.95, size=(200, 3))
        assert filler.mesh.contains(pts).all()
        assert not any(w.contains(pts).any() for w in walls)
        assert not frame.mesh.contains(pts).any()
        # Around the frame along the wall there is wall; across the wall (room side, outside) there is none.
        lo, hi = frame.mesh.bounds
        mid = (lo + hi) / 2
        side = np.array([[lo[0] - 0.05, mid[1], mid[2]], [hi[0] + 0.05, mid[1], mid[2]],
                         [mid[0], lo[1] - 0.05, mid[2]], [mid[0], hi[1] + 0.05, mid[2]]])
        assert np.sum(np.any([w.contains(side) for w in walls], axis=0)) == 2
        assert frame.mesh.contains(np.array([[mid[0], mid[1], hi[2] - 0.01]]))[0]


def test_slab_with_holes_is_a_closed_manifold() -> None:
    v, f = slab_with_holes(3.0, 2.5, 0.2, [(0.5, 0.0, 1.4, 2.1), (1.8, 0.9, 2.7, 2.0)])
    m = trimesh.Trimesh(v, f, process=True)
    assert m.is_watertight and m.is_winding_consistent and m.volume > 0
    expect = 0.2 * (3.0 * 2.5 - 0.9 * 2.1 - 0.9 * 1.1)
    assert m.volume == pytest.approx(expect, rel=1e-9)
    assert m.euler_number == 2 - 2 * 1  # one through-hole (the door notch reaches the border and is none)


def test_labels_are_the_class_tables_ids() -> None:
    # Another order, an extra class and a ceiling class of its own: the same solids, labelled by class name.
    table = ClassTable.from_names(("floor", "ceiling", "door", "wall", "sculpture", "window", "plant", "furniture"))
    cfg = RoomConfig(ceiling=True, sculptures=(1, 2))
    default = make_scene(5, cfg)
    other = make_scene(5, RoomConfig(ceiling=True, sculptures=(1, 2), ceiling_class="ceiling"), table)
    assert default.classes == DEFAULT_CLASSES and other.classes == table
    assert [o.name for o in other.objects] == [o.name for o in default.objects]
    for a, b in zip(default.objects, other.objects, strict=True):
        np.testing.assert_array_equal(a.mesh.vertices, b.mesh.vertices)
        want = "ceiling" if a.name == "ceiling" else DEFAULT_CLASSES.names[a.label]
        assert table.names[b.label] == want, a.name
    assert {table.names[o.label] for o in other.objects} >= {*CLASS_NAMES, "ceiling"}
    with pytest.raises(SceneError, match=r"lacks the simulator's classes \['window', 'furniture', 'door'"):
        make_scene(1, classes=ClassTable.from_names(("wall", "floor", "sculpture")))
    with pytest.raises(SceneError, match="'ceiling'"):
        make_scene(1, RoomConfig(ceiling=True, ceiling_class="ceiling"))


def test_config_counts_and_validation() -> None:
    cfg = RoomConfig(length_range=(7.0, 7.0), width_range=(6.0, 6.0), windows=(3, 3), doors=(2, 2),
                     furniture=(0, 0), sculptures=(2, 2), ceiling=True, furniture_kinds=("chair",))
    scene = make_scene(3, cfg)
    names = [o.name for o in scene.objects]
    assert sum(n.endswith("_glass") for n in names) == 3
    assert sum(n.endswith("_leaf") for n in names) == 2
    assert sum(o.label == SCULPTURE for o in scene.objects) == 2
    assert "ceiling" in names and not any(o.label == FURNITURE for o in scene.objects)
    np.testing.assert_allclose(scene.room_size[:2], [7.0, 6.0])
    chairs = make_scene(4, RoomConfig(furniture=(4, 4), furniture_kinds=("chair",)))
    assert all(o.name.startswith("chair") for o in chairs.objects if o.label == FURNITURE)
    with pytest.raises(SceneError):
        RoomConfig(length_range=(5.0, 4.0))
    with pytest.raises(SceneError):
        RoomConfig(furniture_kinds=("bed",))
    with pytest.raises(SceneError):
        RoomConfig(windows=(-1, 2))


# ---------------------------------------------------------------------------------------------- assets
def _write_obj(path: Path, mesh) -> None:
    lines = [f"v {x:.6f} {y:.6f} {z:.6f}" for x, y, z in mesh.vertices]
    lines += [f"f {a + 1} {b + 1} {c + 1}" for a, b, c in mesh.faces]
    path.write_text("\n".join(lines) + "\n")


def test_asset_folder(tmp_path: Path) -> None:
    (tmp_path / "furniture").mkdir()
    (tmp_path / "sculptures").mkdir()
    (tmp_path / "window").mkdir()
    _write_obj(tmp_path / "furniture" / "crate.obj", trimesh.creation.box(extents=[0.6, 0.4, 0.5]))
    trimesh.creation.icosphere(1, 0.3).export(tmp_path / "sculptures" / "ball.ply")
    trimesh.creation.box(extents=[1.0, 0.1, 1.0]).export(tmp_path / "window" / "pane.off")
    (tmp_path / "furniture" / "notes.txt").write_text("not a mesh")
    lib = load_asset_folder(tmp_path)
    assert sorted((a.kind, a.name) for a in lib.assets) == [
        ("furniture", "crate"), ("sculpture", "ball"), ("window", "pane")]
    crate = lib.of_kind("furniture")[0]
    lo, hi = crate.mesh.bounds
    np.testing.assert_allclose(lo, [-0.3, -0.2, 0.0], atol=1e-6)
    np.testing.assert_allclose(hi, [0.3, 0.2, 0.5], atol=1e-6)

    cfg = RoomConfig(asset_dir=str(tmp_path), asset_probability=1.0, furniture=(3, 3), sculptures=(1, 1),
                     windows=(1, 1))
    scene = make_scene(2, cfg)
    names = [o.name for o in scene.objects]
    assert any(n.startswith("crate_") for n in names) and "window_0" in names
    assert any(o.label == SCULPTURE for o in scene.objects)
    _same(scene, make_scene(2, RoomConfig(assets=lib, asset_probability=1.0, furniture=(3, 3),
                                          sculptures=(1, 1), windows=(1, 1))))
    with pytest.raises(AssetError):
        load_asset_folder(tmp_path / "missing")
    (tmp_path / "furniture" / "broken.obj").write_text("v 0 0 0\n")
    with pytest.raises(AssetError, match="broken.obj"):
        load_asset_folder(tmp_path)


CATALOG = """\
# Tiny test library
id=test.lib
name=Test \\
    library
id#1=test#chair
name#1=Stool \\u00e9
category#1=Living room
model#1=/models/stool.obj
width#1=40
depth#1=30
height#1=45
doorOrWindow#1=false
id#2=test#window
name#2=Small window
category#2=Doors and windows
model#2=models/win.obj
width#2=100
depth#2=10
height#2=120
doorOrWindow#2=true
modelRotation#2=1 0 0 0 0 1 0 -1 0
id#3 = test#door
name#3 : Front door
category#3=Doors and windows
model#3=models/door.obj
width#3=90
depth#3=5
height#3=210
doorOrWindow#3=true
"""


def _sh3f(path: Path, catalog: str = CATALOG, extra: dict[str, str] | None = None) -> Path:
    stool = trimesh.creation.box(extents=[2.0, 3.0, 4.0])  # y up in Sweet Home 3D: height 3
    win = trimesh.creation.box(extents=[1.0, 0.2, 1.5])  # z up: the rotation turns it y up
    door = trimesh.creation.box(extents=[1.0, 2.0, 0.1])
    with zipfile.ZipFile(path, "w") as zf:
        zf.writestr("PluginFurnitureCatalog.properties", catalog)
        for name, m in (("stool", stool), ("win", win), ("door", door)):
            text = "mtllib mat.mtl\n" + "\n".join(f"v {x} {y} {z}" for x, y, z in m.vertices) + "\n"
            text += "\n".join(f"f {a + 1} {b + 1} {c + 1}" for a, b, c in m.faces) + "\n"
            zf.writestr(f"models/{name}.obj", text)
        zf.writestr("models/mat.mtl", "newmtl m\nKd 0.5 0.5 0.5\n")
        for k, v in (extra or {}).items():
            zf.writestr(k, v)
    return path


def test_sh3f_import(tmp_path: Path) -> None:
    lib = load_sh3f(_sh3f(tmp_path / "lib.sh3f"))
    by_kind = {a.kind: a for a in lib.assets}
    assert sorted(by_kind) == ["door", "furniture", "window"]
    stool = by_kind["furniture"]
    assert stool.name == "Stool" and stool.category == "Living room"
    # Catalog sizes are centimetres: width along x, depth along y, height along z (z up).
    np.testing.assert_allclose(stool.mesh.extents, [0.40, 0.30, 0.45], rtol=1e-9)
    np.testing.assert_allclose(stool.mesh.bounds[0], [-0.2, -0.15, 0.0], atol=1e-12)
    np.testing.assert_allclose(by_kind["window"].mesh.extents, [1.0, 0.1, 1.2], rtol=1e-9)
    np.testing.assert_allclose(by_kind["door"].mesh.extents, [0.9, 0.05, 2.1], rtol=1e-9)
    scene = make_scene(1, RoomConfig(sh3f_files=(str(tmp_path / "lib.sh3f"),), asset_probability=1.0,
                                     windows=(1, 1), doors=(1, 1), furniture=(2, 2)))
    names = [o.name for o in scene.objects]
    assert "window_0" in names and "door_0" in names and any(n.startswith("Stool") for n in names)
    window = next(o for o in scene.objects if o.name == "window_0")
    assert window.label == WINDOW and window.mesh.is_watertight


def test_sh3f_errors(tmp_path: Path) -> None:
    (tmp_path / "plain.sh3f").write_text("not a zip")
    with pytest.raises(AssetError, match="zip"):
        load_sh3f(tmp_path / "plain.sh3f")
    with zipfile.ZipFile(tmp_path / "nocat.sh3f", "w") as zf:
        zf.writestr("models/a.obj", "v 0 0 0\n")
    with pytest.raises(AssetError, match="PluginFurnitureCatalog"):
        load_sh3f(tmp_path / "nocat.sh3f")
    bad = CATALOG.replace("model#1=/models/stool.obj", "model#1=../../etc/passwd")
    with pytest.raises(AssetError, match="not in the archive"):
        load_sh3f(_sh3f(tmp_path / "escape.sh3f", bad))


def test_properties_parser() -> None:
    props = parse_properties(CATALOG + "key\\ with\\ space = a\\tb\\\\\n! comment\nlast:value \n")
    assert props["name"] == "Test library"
    assert props["name#1"] == "Stool \u00e9"
    assert props["id#3"] == "test#door" and props["name#3"] == "Front door"
    assert props["key with space"] == "a\tb\\"
    assert props["last"] == "value "

"""The furnished rooms (train/sim/rooms, the "home" world) on the tiny asset pack the real builder makes from the
committed sources: labels, support, overlaps, context, the asset split, determinism, the robot, materials, config."""

from __future__ import annotations

import hashlib
import math
import re
from pathlib import Path

import numpy as np
import pytest

from fruxel.classes import DEFAULT_CLASSES, HOME_CLASSES
from fruxel.errors import ConfigError
from fruxel.grid import FruxelGrid
from fruxel.train.sim.assetpack import AssetPack
from fruxel.train.sim.config import SimConfig, TrajectoryConfig
from fruxel.train.sim.robot import random_trajectory
from fruxel.train.sim.rooms import ASSETS_ENV, HomeConfig, MaterialConfig, library, make_home, resolve_pack
from fruxel.train.sim.rooms.materials import PLAUSIBLE, MaterialSampler
from fruxel.train.sim.rooms.procedural import bookcase, cabinet, table
from fruxel.train.sim.rooms.supports import CELL, support_levels
from fruxel.train.sim.scene import SceneError

STRUCTURE = re.compile(r"^(floor|ceiling|wall_\d|hall_|baseboard|crown|window_|door_)")
"""Names of the shell's objects (module docstring of train/sim/rooms/shell.py)."""
SEEDS = range(10)


@pytest.fixture(scope="module")
def rooms(tiny_pack: Path) -> list:
    return [make_home(s, assets=tiny_pack) for s in SEEDS]


def _digest(scene) -> str:
    h = hashlib.sha256()
    for o in scene.objects:
        h.update(o.name.encode())
        for a in (np.asarray(o.mesh.vertices), np.asarray(o.mesh.faces), o.parts):
            h.update(np.ascontiguousarray(a).tobytes())
        h.update(repr((o.label, o.color, o.materials, o.solid, o.asset)).encode())
    for light in scene.lights:
        h.update(repr((light.kind, light.color, light.intensity, light.cone, light.radius)).encode())
        h.update(light.pose.tobytes())
    h.update(scene.free_space.occupied.tobytes() + scene.room_size.tobytes() + repr(scene.ambient).encode())
    return h.hexdigest()


def test_same_seed_same_scene_bytes(tiny_pack: Path, rooms: list) -> None:
    again = make_home(SEEDS[3], assets=tiny_pack)
    assert _digest(again) == _digest(rooms[3])
    assert _digest(rooms[3]) != _digest(rooms[4])


# ---------------------------------------------------------------------------------------------- labels
def _down_grid(scene, cells: int = 128, slices: int = 200) -> tuple[FruxelGrid, np.ndarray]:
    """A grid seen from far above the room, looking straight down, covering the interior from floor to ceiling."""
    lx, ly, lz = scene.room_size
    height = 40.0
    near = height - lz - 0.02
    hfov = math.degrees(2 * math.atan((max(lx, ly) + 0.2) / 2 / near))
    grid = FruxelGrid(width=cells, height=cells, depth=slices, z_near=near, z_far=height + 0.02, hfov=hfov)
    pose = np.eye(4)
    pose[:3, :3] = np.array([[1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]])
    pose[:3, 3] = [lx / 2, ly / 2, height]
    return grid, pose


def _view(eye: list[float], yaw: float, pitch_up: float) -> np.ndarray:
    """Camera-to-world pose, OpenCV axes, looking along ``yaw`` tilted up by ``pitch_up`` radians."""
    f = np.array([math.cos(yaw) * math.cos(pitch_up), math.sin(yaw) * math.cos(pitch_up), math.sin(pitch_up)])
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, np.cross(f, x), f, eye
    return pose


def test_ceilings_and_objects_are_labelled(rooms: list) -> None:
    from fruxel.kernels import fruxelize

    grid = FruxelGrid(width=48, height=48, depth=64, z_near=0.3, z_far=8.0, hfov=70.0)
    ceiling, obj = HOME_CLASSES.index("ceiling"), HOME_CLASSES.index("object")
    for scene in rooms[:3]:
        assert scene.classes == HOME_CLASSES
        # Look up at the wall behind a picture or a curtain, from 2.5 m in front of it.
        target = next(o for o in scene.objects if o.name.startswith(("painting", "poster", "curtain")))
        c = np.asarray(target.mesh.vertices).mean(axis=0)
        lx, ly, _ = scene.room_size
        inward = np.array([lx / 2, ly / 2]) - c[:2]
        inward /= np.linalg.norm(inward)
        eye = [*(c[:2] + inward * 2.5), 1.2]
        pose = _view(eye, math.atan2(-inward[1], -inward[0]), math.radians(25))
        labels = np.asarray(fruxelize(scene.labelled_meshes(), grid, pose, backend="warp-cpu"))
        found = set(np.unique(labels).tolist())
        assert {ceiling, obj, HOME_CLASSES.index("wall")} <= found, (target.name, found)


def test_the_home_world_needs_its_classes(tiny_pack: Path) -> None:
    with pytest.raises(SceneError, match=r"lacks the furnished rooms' classes \['ceiling', 'object'\]"):
        make_home(0, assets=tiny_pack, classes=DEFAULT_CLASSES)
    with pytest.raises(ConfigError, match="use fruxel.classes.HOME_CLASSES"):
        SimConfig(world="home")
    # Another table with the names in other places labels the same solids by name.
    shuffled = HOME_CLASSES.from_names(("object", "floor", "ceiling", "door", "wall", "window", "sculpture",
                                        "furniture"))
    a, b = make_home(1, assets=tiny_pack), make_home(1, assets=tiny_pack, classes=shuffled)
    assert [HOME_CLASSES.names[o.label] for o in a.objects] == [shuffled.names[o.label] for o in b.objects]


# ---------------------------------------------------------------------------------------------- placement
def _heights_at(v: np.ndarray, f: np.ndarray, xy: np.ndarray) -> list[np.ndarray]:
    """For each point ``(N, 2)``, the heights where a vertical line through it meets the mesh's triangles."""
    tri = v[f]
    a, b, c = tri[:, 0], tri[:, 1], tri[:, 2]
    out = []
    for p in xy:
        e0, e1, e2 = b[:, :2] - a[:, :2], c[:, :2] - a[:, :2], p - a[:, :2]
        den = e0[:, 0] * e1[:, 1] - e1[:, 0] * e0[:, 1]
        ok = np.abs(den) > 1e-12
        s = np.where(ok, (e2[:, 0] * e1[:, 1] - e1[:, 0] * e2[:, 1]) / np.where(ok, den, 1), -1)
        t = np.where(ok, (e0[:, 0] * e2[:, 1] - e2[:, 0] * e0[:, 1]) / np.where(ok, den, 1), -1)
        hit = ok & (s >= -1e-6) & (t >= -1e-6) & (s + t <= 1 + 1e-6)
        out.append(a[hit, 2] + s[hit] * (b[hit, 2] - a[hit, 2]) + t[hit] * (c[hit, 2] - a[hit, 2]))
    return out


def _rests(o, scene, others) -> bool:
    """Whether an object stands on the floor, hangs from the ceiling, touches a wall, or rests on another solid
    (a vertical line through one of its lowest points meets another solid's surface right below it)."""
    v = np.asarray(o.mesh.vertices)
    lx, ly, lz = scene.room_size
    low, top = v[:, 2].min(), v[:, 2].max()
    to_wall = np.min(np.abs(np.stack([v[:, 0], lx - v[:, 0], v[:, 1], ly - v[:, 1]])))
    if low < 0.002 or top > lz - 0.002 or to_wall < 0.002:
        return True
    # Points of what it stands on: the centres of its lowest faces and points along its lowest edges.
    tri = v[np.asarray(o.mesh.faces)]
    a, b = tri, np.roll(tri, -1, axis=1)
    edges = (a[:, :, 2] < low + 0.003) & (b[:, :, 2] < low + 0.003)
    steps = np.linspace(0.0, 1.0, 5)[:, None, None]
    along = (a[edges][None] + steps * (b[edges] - a[edges])[None]).reshape(-1, 3)
    faces = tri[np.all(tri[:, :, 2] < low + 0.003, axis=1)].mean(axis=1)
    feet = np.concatenate([along, faces, v[v[:, 2] < low + 0.003]])[:, :2]
    feet = feet[:: max(1, len(feet) // 80)]
    for other in others:
        ov = np.asarray(other.mesh.vertices)
        lo, hi = ov[:, :2].min(axis=0), ov[:, :2].max(axis=0)
        near = feet[np.all((feet >= lo) & (feet <= hi), axis=1)]
        if len(near) and any(np.any((z > low - 0.012) & (z < low + 0.002))
                             for z in _heights_at(ov, np.asarray(other.mesh.faces), near)):
            return True
    return False


def test_nothing_floats(rooms: list) -> None:
    for scene in rooms:
        solids = [o for o in scene.objects if o.solid]
        checked = [o for o in solids if not STRUCTURE.match(o.name)]
        assert len(checked) > 8
        floating = [o.name for o in checked if not _rests(o, scene, [s for s in solids if s is not o])]
        assert not floating, (scene.seed, floating)


def test_no_two_solids_overlap(rooms: list) -> None:
    """Each solid gets its own label; fruxelize lets the later mesh win, so a cell inside two solids gets another
    label when the order is reversed. Cells of about 4 x 4 x 1.5 cm."""
    from fruxel.kernels import fruxelize

    for scene in rooms[:4]:
        solids = [o for o in scene.objects if o.solid]
        assert len(solids) < 255
        meshes = [(np.asarray(o.mesh.vertices), np.asarray(o.mesh.faces), k + 1) for k, o in enumerate(solids)]
        grid, pose = _down_grid(scene)
        a = np.asarray(fruxelize(meshes, grid, pose, backend="warp-cpu"))
        b = np.asarray(fruxelize(meshes[::-1], grid, pose, backend="warp-cpu"))
        both = (a != b) & (a > 0) & (b > 0)
        cell = (grid.z_near + grid.z_far) / 2 * 2 * grid.tu / grid.width
        volume = cell * cell * (grid.z_far - grid.z_near) / grid.depth
        pairs: dict[tuple[str, str], int] = {}
        for x, y in zip(a[both], b[both], strict=True):
            key = tuple(sorted((solids[x - 1].name, solids[y - 1].name)))
            pairs[key] = pairs.get(key, 0) + 1
        big = {k: round(n * volume * 1e3, 2) for k, n in pairs.items() if n * volume > 2e-4}
        assert not big, (scene.seed, big, "litres")
        assert int(np.count_nonzero(a)) > 10_000


def _near(a: np.ndarray, b: np.ndarray) -> float:
    """Smallest horizontal distance from points ``a`` to the bounding rectangle of points ``b`` (tables stand
    square to the walls, within a few degrees)."""
    lo, hi = b[:, :2].min(axis=0), b[:, :2].max(axis=0)
    d = np.maximum(np.maximum(lo - a[:, :2], a[:, :2] - hi), 0.0)
    return float(np.sqrt((d ** 2).sum(axis=1)).min())


def test_beds_and_sofas_touch_a_wall_and_chairs_stand_at_tables(tiny_pack: Path) -> None:
    seen = {"bed": 0, "sofa": 0, "chair": 0}
    for seed in range(6):
        for kind in ("bedroom", "living", "dining", "office"):
            scene = make_home(seed, HomeConfig(room_types=(kind,)), assets=tiny_pack)
            lx, ly, _ = scene.room_size
            tables = [np.asarray(o.mesh.vertices) for o in scene.objects
                      if re.match(r"(dining_table|small_table|desk)_", o.name)]
            for o in scene.objects:
                v = np.asarray(o.mesh.vertices)
                role = re.sub(r"_\d+$", "", o.name)
                if role in ("bed", "sofa"):
                    gap = np.min(np.abs(np.stack([v[:, 0], lx - v[:, 0], v[:, 1], ly - v[:, 1]])))
                    assert gap < 0.06, (seed, kind, o.name, gap)
                    seen[role] += 1
                if role == "chair":
                    assert tables and min(_near(v, t) for t in tables) < 0.3, (seed, kind, o.name)
                    seen[role] += 1
    assert min(seen.values()) > 0, seen


def test_a_robot_can_drive_through_the_rooms(rooms: list) -> None:
    kwargs = TrajectoryConfig(steps_per_frame=5).kwargs()
    for scene in rooms:
        traj = random_trajectory(scene, 16, scene.seed, **kwargs)
        assert traj.poses.shape == (16, 4, 4)
        xy = traj.states.position
        assert not scene.free_space.collides(xy, kwargs["radius"]).any()
        assert scene.free_space.occupied.mean() > 0.05


# ---------------------------------------------------------------------------------------------- assets
def _assets_of(scene) -> set[str]:
    ids = {o.asset for o in scene.objects if o.asset is not None}
    for o in scene.objects:
        ids |= {i for m in o.materials for i in (m.texture, m.image) if i is not None}
    return ids


def test_train_rooms_use_train_assets_and_test_rooms_the_chosen_split(tiny_pack: Path, rooms: list) -> None:
    pack = AssetPack(tiny_pack)
    used = set().union(*(_assets_of(s) for s in rooms))
    assert {pack.entry(i).split for i in used} == {"train"}
    assert any(pack.entry(i).kind == "mesh" for i in used) and any(pack.entry(i).kind == "image" for i in used)
    held_out = set().union(*(_assets_of(make_home(s, assets=tiny_pack, split="test")) for s in SEEDS))
    assert held_out and {pack.entry(i).split for i in held_out} == {"test"}
    seen = set().union(*(_assets_of(make_home(s, HomeConfig(test_assets="train"), assets=tiny_pack, split="test"))
                         for s in SEEDS))
    assert {pack.entry(i).split for i in seen} == {"train"}


def test_materials_do_not_tell_the_class(tiny_pack: Path, rooms: list) -> None:
    pack = AssetPack(tiny_pack)
    categories = set(pack.categories("texture", "train"))
    by_class: dict[str, set[str]] = {}
    for scene in rooms:
        for o in scene.objects:
            name = scene.classes.names[o.label]
            by_class.setdefault(name, set()).update(pack.entry(m.texture).category for m in o.materials
                                                    if m.texture is not None)
    assert len(categories) >= 3
    assert by_class["wall"] == categories and by_class["furniture"] == categories and by_class["floor"] >= {"wood"}
    # With no preference for plausible pairings, a wall and a table top draw categories alike.
    lib = library(tiny_pack)
    counts = {}
    for role in ("wall", "wood"):
        sampler = MaterialSampler(np.random.default_rng(0), MaterialConfig(plausibility=0.0, plain=0.0), lib, "train")
        drawn = [sampler.category(role) for _ in range(3000)]
        counts[role] = np.array([drawn.count(c) for c in sorted(categories)]) / len(drawn)
    assert np.abs(counts["wall"] - counts["wood"]).max() < 0.05
    assert np.abs(counts["wall"] - 1 / len(categories)).max() < 0.05
    assert set(PLAUSIBLE["wall"]) & set(PLAUSIBLE["wood"]) >= {"wood", "stone"}


# ---------------------------------------------------------------------------------------------- supports
def test_support_surfaces_of_a_table_a_bookcase_and_a_closed_cabinet() -> None:
    rng = np.random.default_rng(0)
    t = table(rng, 1.2, 0.8, 0.75)
    levels = support_levels(t.vertices, t.faces)
    # The whole top but a band of one cell along its edges (supports.py: levels are eroded by a cell).
    assert [round(lv.z, 2) for lv in levels] == [0.75]
    assert (1.2 - 2 * CELL) * (0.8 - 2 * CELL) * 0.95 < levels[0].area < 1.2 * 0.8
    b = bookcase(rng, 1.0, 0.3, 1.8)
    shelves = support_levels(b.vertices, b.faces)
    assert len(shelves) >= 4 and all(0.2 < lv.room.max() < 0.5 for lv in shelves[:-1])
    c = cabinet(np.random.default_rng(3), 0.8, 0.5, 0.9)
    # Inside the closed carcass nothing can stand: only the top is a support.
    assert [round(lv.z, 2) for lv in support_levels(c.vertices, c.faces)] == [0.9]


# ---------------------------------------------------------------------------------------------- config
def test_home_config_checks_itself_and_round_trips(tiny_pack: Path) -> None:
    with pytest.raises(ConfigError, match=r"home\.doors must be integers"):
        HomeConfig(doors=(2, 1))
    with pytest.raises(ConfigError, match=r"home\.test_assets must be one of"):
        HomeConfig(test_assets="val")
    with pytest.raises(ConfigError, match=r"home\.materials\.plausibility must be a number in \[0, 1\]"):
        HomeConfig(materials=MaterialConfig(plausibility=1.5))
    with pytest.raises(ConfigError, match=r"home\.room_types must be distinct names"):
        HomeConfig(room_types=("garage",))
    flat = SimConfig()
    assert not {"world", "home", "assets"} & set(flat.to_dict())
    home = SimConfig(world="home", classes=HOME_CLASSES, assets=str(tiny_pack),
                     home=HomeConfig(test_assets="train", materials=MaterialConfig(plausibility=0.2)))
    d = home.to_dict()
    assert d["world"] == "home" and d["home"]["materials"]["plausibility"] == 0.2 and d["assets"] == str(tiny_pack)
    assert SimConfig.from_dict(d) == home and SimConfig.from_dict(d).digest() == home.digest() != flat.digest()
    assert HomeConfig().asset_split("train") == "train" and HomeConfig().asset_split("test") == "test"
    assert HomeConfig(test_assets="train").asset_split("eval") == "train"


def test_the_pack_is_found_or_named_in_one_line(tiny_pack: Path, tmp_path: Path,
                                               monkeypatch: pytest.MonkeyPatch) -> None:
    assert resolve_pack(tiny_pack) == tiny_pack
    monkeypatch.setenv(ASSETS_ENV, str(tiny_pack))
    assert resolve_pack(None) == tiny_pack
    monkeypatch.setenv(ASSETS_ENV, str(tmp_path / "nowhere"))
    with pytest.raises(ConfigError, match=r"nowhere: no asset pack there \(\$FRUXEL_ASSETS\); build it with "
                                          r"`make assets`") as e:
        resolve_pack(None)
    assert "\n" not in str(e.value)


def test_sample_maker_draws_home_rooms(tiny_pack: Path) -> None:
    from fruxel.train.sim.config import ImageConfig
    from fruxel.train.sim.sample import SampleMaker

    config = SimConfig(world="home", classes=HOME_CLASSES, assets=str(tiny_pack), samples_per_scene=2,
                       grid=FruxelGrid(32, 32, 32, 0.5, 8.0, 60.0), image=ImageConfig(size=32),
                       splits=(("train", 4), ("test", 2)))
    with SampleMaker(config, 0, backend="warp-cpu") as maker:
        scene, _ = maker.scene_of("train", 0)
        assert scene.classes == HOME_CLASSES and any(o.name == "ceiling" for o in scene.objects)
        sample = maker.make("test", 1)
        assert sample.image.shape == (32, 32, 3) and sample.labels.max() < len(HOME_CLASSES)

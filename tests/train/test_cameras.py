"""Any camera (issue 38, item 1): the camera config and its draws, the robot's mount giving today's bytes, images
framed onto the grid's view lining up with the labels, and the camera record in samples, shards and batches.

Real simulator, real pyrender (llvmpipe), real Warp on the CPU; tiny grids and images so that the file runs in
well under a minute on two cores.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import shutil
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid
from fruxel.kernels import first_hit
from fruxel.kernels.fruxelize import fruxelize
from fruxel.train.framing import PAD_VALUE
from fruxel.train.sim import cameras, testsets
from fruxel.train.sim.cameras import ANY_CAMERA, CAMERA_KEYS, ROBOT_CAMERA, CameraConfig, CameraRecord
from fruxel.train.sim.config import AugmentConfig, ConfigError, ImageConfig, SimConfig
from fruxel.train.sim.images import SceneRenderer
from fruxel.train.sim.manifest import MANIFEST, Manifest
from fruxel.train.sim.renderer import RENDERERS, register_renderer
from fruxel.train.sim.sample import SampleMaker
from fruxel.train.sim.scene import FreeSpace, Scene, SceneObject, boxes
from fruxel.train.sim.shards import DatasetError, ShardReader, encode_shard, shard_specs
from fruxel.train.sim.writer import generate

trimesh = pytest.importorskip("trimesh")
torch = pytest.importorskip("torch")
from fruxel.train.samples import Batches, BlockPlan, BlockStream  # noqa: E402 - needs torch
from fruxel.train.sim.dataset import ShardDataset  # noqa: E402 - needs torch

REFERENCE = Path(__file__).resolve().parents[1] / "data" / "robot_mount"
"""Samples made before the camera work (``make_reference.py`` there says how)."""

GRID = FruxelGrid(width=32, height=32, depth=32, z_near=0.5, z_far=8.0, hfov=60.0)
ANY = SimConfig(grid=GRID, image=ImageConfig(size=32), samples_per_scene=3, shard_size=3,
                splits=(("train", 12), ("test", 3)), camera=ANY_CAMERA)
"""Any camera at one image pixel per grid column (S = W), three frames per room."""
SEED = 5


def _gravity(pose: np.ndarray) -> np.ndarray:
    """World down (-z) in the camera frame of a camera-to-world pose, computed here from the matrix alone."""
    return np.asarray(pose)[:3, :3].T @ np.array([0.0, 0.0, -1.0])


def _angles(pose: np.ndarray) -> tuple[float, float, float]:
    """(height above the floor z = 0, pitch down, roll) of a pose, degrees, from its matrix alone."""
    g = _gravity(pose)
    return float(pose[2, 3]), math.degrees(math.asin(g[2])), math.degrees(math.atan2(g[0], g[1]))


# ---------------------------------------------------------------------------------------------------- config
def test_camera_config_checks_its_ranges() -> None:
    assert CameraConfig(height=(1.2, 1.2)).height == (1.2, 1.2)  # a degenerate range is a fixed value
    assert CameraConfig(pitch=[-5, 5]).pitch == (-5.0, 5.0)
    for field, bad in (("height", (0.0, 1.0)), ("height", (1.0, 10.5)), ("pitch", (10.0, 5.0)),
                       ("pitch", (-90.0, 0.0)), ("roll", (0.0, float("nan"))), ("hfov", (50.0, 180.0)),
                       ("hfov", (0.0, 60.0)), ("roll", (1.0,)), ("hfov", "wide")):
        with pytest.raises(ConfigError, match=f"camera.{field} must be"):
            CameraConfig(**{field: bad})
    with pytest.raises(ConfigError, match="camera must be a CameraConfig"):
        ANY.replace(camera="any")
    with pytest.raises(ConfigError, match=r"camera.hfov 170 degrees would render \d+x\d+ pixels"):
        SimConfig(image=ImageConfig(size=2048), camera=CameraConfig(hfov=(60.0, 170.0)))
    assert cameras.camera_named("any") == ANY_CAMERA and cameras.camera_named("robot") == ROBOT_CAMERA
    with pytest.raises(ConfigError, match=r"unknown camera 'phone'; cameras are \['robot', 'any'\]"):
        cameras.camera_named("phone")


def test_robot_camera_keeps_the_configs_and_digests_of_data_sets_made_before() -> None:
    """Configs recorded before cameras varied read as the robot camera and keep their digests; another camera is
    recorded, round-trips and changes the digest."""
    manifest = json.loads((REFERENCE / "dataset_v2" / MANIFEST).read_text())
    old = SimConfig.from_dict(manifest["config"])
    assert old.camera == ROBOT_CAMERA and "camera" not in old.to_dict()
    assert old.digest() == manifest["config_sha256"]
    d = ANY.to_dict()
    assert d["camera"] == {"height": [0.3, 1.9], "pitch": [-20.0, 40.0], "roll": [-10.0, 10.0], "hfov": [50.0, 80.0],
                           "aim": 120.0}
    assert SimConfig.from_dict(json.loads(json.dumps(d))) == ANY
    # A camera recorded before frames were aimed reads as one that looks along the robot's heading.
    before = SimConfig.from_dict({**d, "camera": {k: v for k, v in d["camera"].items() if k != "aim"}})
    assert before.camera.aim is None and before.camera.height == ANY_CAMERA.height
    assert ANY.digest() != ANY.replace(camera=ROBOT_CAMERA).digest()
    with pytest.raises(ConfigError, match="camera.pitch must be"):
        SimConfig.from_dict({**d, "camera": {**d["camera"], "pitch": [50.0, 40.0]}})


# ---------------------------------------------------------------------------------------------------- draws
def test_draws_cover_their_ranges_uniformly() -> None:
    config = ANY.replace(image=ImageConfig(size=256))
    mounts = [cameras.draw_mount(config, seed) for seed in range(4000)]
    for name in ("height", "pitch", "roll", "hfov"):
        lo, hi = getattr(ANY_CAMERA, name)
        v = np.array([getattr(m, name) for m in mounts])
        assert v.min() >= lo and v.max() <= hi, name
        # Uniform: each quarter of the range holds about a quarter of the draws (4000 draws: 25 % +- 2.7 % at 4 sigma).
        share = np.histogram(v, bins=4, range=(lo, hi))[0] / len(v)
        assert np.all(np.abs(share - 0.25) < 0.03), (name, share)
    # The field of view is one of whole-pixel widths: it renders at the network image's focal length.
    for m in mounts[:50]:
        w, _ = cameras.render_size(config, m.hfov)
        assert m.hfov == pytest.approx(math.degrees(2 * math.atan(w / (2 * config.image_camera().fx))), abs=1e-9)
    robot = cameras.draw_mount(ANY.replace(camera=ROBOT_CAMERA), 3)
    assert robot == cameras.robot_mount(ANY) == cameras.Mount(1.0, 10.0, 0.0, 60.0)


def test_samples_record_their_camera_and_it_agrees_with_the_pose() -> None:
    """Each room draws one camera, fixed over its frames; the record's height, pitch, roll and gravity are what the
    pose says, its intrinsics the render's; the drive is the robot's whatever the camera."""
    with SampleMaker(ANY, SEED) as maker:
        samples = [maker.make("train", i) for i in range(12)]
    with SampleMaker(ANY.replace(camera=ROBOT_CAMERA), SEED) as maker:
        robot = [maker.make("train", i) for i in range(12)]
    mounts = set()
    for s, r in zip(samples, robot, strict=True):
        c = s.camera
        mounts.add((s.scene, c.height, c.pitch, c.roll, c.hfov))
        for name in ("height", "pitch", "roll"):
            lo, hi = getattr(ANY_CAMERA, name)
            assert lo <= getattr(c, name) <= hi
        assert 50.0 <= c.hfov <= 80.0
        height, pitch, roll = _angles(s.pose)
        assert (height, pitch, roll) == pytest.approx((c.height, c.pitch, c.roll), abs=1e-9)
        g = _gravity(s.pose)
        assert np.linalg.norm(c.gravity) == pytest.approx(1.0, abs=1e-12)
        np.testing.assert_allclose(c.gravity, g, atol=1e-12)
        fx, fy, cx, cy = c.intrinsics
        w, h = c.image_size
        assert fx == fy == ANY.image_camera().fx and (cx, cy) == (w / 2, h / 2) and w == h
        assert math.degrees(2 * math.atan(w / (2 * fx))) == pytest.approx(c.hfov, abs=1e-9)
        # The robot drives the same path: only the mount's height and the camera's rotation differ.
        np.testing.assert_array_equal(s.pose[:2, 3], r.pose[:2, 3])
        assert s.image.shape == (32, 32, 3) and s.coverage.shape == (32, 32) and s.coverage.dtype == bool
        assert s.coverage.all() == (c.hfov >= 60.0)
    assert len(mounts) == 4 and len({m[1:] for m in mounts}) == 4  # one camera per room, a new one per room


def test_positive_roll_turns_the_camera_clockwise() -> None:
    """Right side down, and the horizon rising to the right in the image."""
    cfg = ANY.replace(camera=CameraConfig(height=(1.0, 1.0), pitch=(0.0, 0.0), roll=(8.0, 8.0)))
    with SampleMaker(cfg, SEED) as maker:
        s = maker.make("train", 0)
    pose = s.pose
    assert pose[2, 0] < 0  # the camera's x axis (image right) points below the horizontal
    cam = Camera.from_hfov(100, 100, 60.0, pose)
    ahead = pose[:3, 2] * np.array([1.0, 1.0, 0.0])
    ahead /= np.linalg.norm(ahead)
    side = np.cross(ahead, [0.0, 0.0, 1.0])  # level, to the camera's right
    # Two far points at the camera's height: on the horizon.
    left, right = cam.project(pose[:3, 3] + 50 * ahead - 10 * side), cam.project(pose[:3, 3] + 50 * ahead + 10 * side)
    assert right[0] > left[0] and right[1] < left[1]
    assert s.camera.roll == 8.0 and _angles(pose)[2] == pytest.approx(8.0)


# ---------------------------------------------------------------------------------------------------- bytes
def _sha(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


@pytest.mark.parametrize("fixed", [False, True], ids=["robot-camera", "fixed-ranges-at-the-robot-mount"])
def test_robot_mount_gives_the_bytes_made_before(fixed: bool) -> None:
    """The samples of the reference configs, made by the code before the camera work, again: with the robot camera,
    and with ranges fixed at the robot's values (which draw, frame and record, but change nothing)."""
    from fruxel.render.scene import gl_renderer_name

    ref = json.loads((REFERENCE / "samples.json").read_text())
    same_machine = gl_renderer_name() == ref["gl_renderer"] and np.__version__ == ref["numpy"]
    checked = 0
    for name, entry in ref["configs"].items():
        config = SimConfig.from_dict(entry["config"])
        if fixed:
            m = config.trajectory.mount
            config = config.replace(camera=CameraConfig(height=(m.height,) * 2, pitch=(m.tilt,) * 2, roll=(0.0, 0.0),
                                                        hfov=(config.grid.hfov,) * 2))
        with SampleMaker(config, entry["seed"], backend="warp-cpu") as maker:
            for row in entry["samples"]:
                s = maker.make(row["split"], row["index"])
                assert _sha(s.labels) == row["labels"], (name, row["index"])
                if same_machine:
                    assert (_sha(s.image), _sha(s.pose)) == (row["image"], row["pose"]), (name, row["index"])
                else:  # another OpenGL driver or numpy build: images and the last bits of poses may differ
                    np.testing.assert_allclose(s.pose, row["pose_values"], rtol=0, atol=1e-12)
                assert s.camera == cameras.camera_record(config, cameras.robot_mount(config), s.pose)
                checked += 1
    assert checked == 17


# ---------------------------------------------------------------------------------------------------- framing
@pytest.mark.parametrize("grid", [GRID, FruxelGrid(32, 24, 16, 0.5, 8.0, 70.0)], ids=["square", "32x24"])
@pytest.mark.parametrize("size", [32, 64])
def test_framing_moves_whole_pixels(grid: FruxelGrid, size: int) -> None:
    """The framed render is the render cropped or padded about its centre, pixel for pixel: nothing resampled."""
    config = SimConfig(grid=grid, image=ImageConfig(size=size), camera=ANY_CAMERA)
    rng = np.random.default_rng(0)
    seen = set()
    for hfov in np.linspace(30.0, 100.0, 71):
        hfov = cameras.render_hfov(config, float(hfov))
        w, h = cameras.render_size(config, hfov)
        render = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
        framed = cameras.frame_render(config, render, hfov)
        s, s_h = config.image_width, config.image_height
        expected = np.full((s_h, s, 3), PAD_VALUE, np.uint8)
        dy, dx = (s_h - h) // 2, (s - w) // 2
        if w >= s:
            expected[:] = render[-dy:-dy + s_h if dy else None, -dx:-dx + s if dx else None]
        else:
            expected[dy:dy + h, dx:dx + w] = render
        np.testing.assert_array_equal(framed, expected, err_msg=f"{hfov} degrees, {w}x{h}")
        cover = cameras.coverage(config, hfov)
        # At S = W (one pixel per column) a column is covered exactly where its pixel is not padding.
        if s == grid.width:
            np.testing.assert_array_equal(cover, ~(expected == PAD_VALUE).all(-1) | (w >= s))
        seen.add(w < s)
    assert seen == {True, False}


COLOURS = {1: (0.9, 0.1, 0.1, 1.0), 2: (0.1, 0.9, 0.1, 1.0), 4: (0.1, 0.1, 0.9, 1.0)}
BOX = ([2.2, -1.2, 0.3], [3.0, 0.4, 1.1])
"""The box (label 4), world min and max corners, metres."""


def _box_scene() -> Scene:
    """A floor (2), a back wall (1) and a box (4) in flat colours, lit by ambient light only."""
    parts = {2: ([-1.0, -6.0, -0.3], [9.0, 6.0, 0.0]), 1: ([7.0, -6.0, 0.0], [7.3, 6.0, 3.0]), 4: BOX}
    objects = []
    for label, (lo, hi) in parts.items():
        v, f = boxes([lo], [hi])
        objects.append(SceneObject(f"obj{label}", label, trimesh.Trimesh(v, f, process=False), COLOURS[label],
                                   0.0, 1.0))
    return Scene(tuple(objects), np.array([7.0, 12.0, 3.0]), (), FreeSpace(np.zeros((2, 2), bool), np.zeros(2), 1.0),
                 0)


def _column_hits_box(grid: FruxelGrid, pose: np.ndarray) -> np.ndarray:
    """``(H, W)`` bool: whether each column's centre ray meets the box before the back of the grid, by the slab
    method in float64 (the geometry, apart from the renderer and fruxelize)."""
    u = -grid.tu + (np.arange(grid.width) + 0.5) * 2 * grid.tu / grid.width
    v = -grid.tv + (np.arange(grid.height) + 0.5) * 2 * grid.tv / grid.height
    d = np.stack(np.broadcast_arrays(u[None, :], v[:, None], 1.0), -1) @ pose[:3, :3].T
    with np.errstate(divide="ignore"):
        t0 = (np.array(BOX[0]) - pose[:3, 3]) / d
        t1 = (np.array(BOX[1]) - pose[:3, 3]) / d
    near, far = np.minimum(t0, t1).max(-1), np.maximum(t0, t1).min(-1)
    return (near <= far) & (far > grid.z_near) & (near < grid.z_far)


def _box_pose() -> np.ndarray:
    """Camera 1.3 m above the floor at the origin, looking along +x, pitched 15 degrees down and rolled 7."""
    level = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.3], [0.0, 0.0, 0.0, 1.0]])
    c, s = math.cos(math.radians(15.0)), math.sin(math.radians(15.0))
    pitch = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, c, s, 0.0], [0.0, -s, c, 0.0], [0.0, 0.0, 0.0, 1.0]])
    return cameras.roll_poses(level @ pitch, 7.0)


def test_a_box_lands_where_it_should() -> None:
    """A box seen at a known pitched and rolled pose by cameras of 45, 60 and 80 degrees, framed onto a 60 degree
    grid: the framed images are the grid view's pixel for pixel where they cover it (grey elsewhere), and their
    box pixels, fruxelize's own view of the box and the box's geometry are the same grid columns."""
    grid = FruxelGrid(width=48, height=48, depth=192, z_near=0.5, z_far=8.0, hfov=60.0)
    pose = _box_pose()
    assert _angles(pose) == pytest.approx((1.3, 15.0, 7.0))
    scene = _box_scene()
    framed = {}
    for hfov in (45.0, 60.0, 80.0):
        config = SimConfig(grid=grid, image=ImageConfig(size=48, background=(1.0, 1.0, 1.0),
                                                        augment=AugmentConfig(enabled=False, ambient=(1.0, 1.0))),
                           camera=CameraConfig(hfov=(hfov, hfov)))
        mount = cameras.draw_mount(config, 0)
        camera = cameras.render_camera(config, mount.hfov)
        with SceneRenderer(config) as r:
            r.set_scene(scene)
            render = r.render(pose, None, camera=camera)
        assert render.shape == (camera.height, camera.width, 3) and abs(mount.hfov - hfov) < 1.0
        assert (camera.width > 48) == (hfov > 60.0) and (camera.width < 48) == (hfov < 60.0)
        framed[hfov] = cameras.frame_render(config, render, mount.hfov), cameras.coverage(config, mount.hfov)
    grid_view = framed[60.0][0]
    for hfov in (45.0, 80.0):
        image, cover = framed[hfov]
        np.testing.assert_array_equal(image[cover], grid_view[cover])
        assert (image[~cover] == PAD_VALUE).all() and cover.all() == (hfov > 60.0)
    narrow_cover = framed[45.0][1]
    assert 0.5 < narrow_cover.mean() < 0.9
    # The grid view's pixels by nearest flat colour (pyrender writes through a 1/2.2 gamma); edge pixels are blends.
    refs = 255.0 * np.array([[1.0, 1.0, 1.0]] + [COLOURS[k][:3] for k in (1, 2, 4)]) ** (1 / 2.2)
    dist = np.linalg.norm(grid_view[:, :, None, :].astype(float) - refs[None, None], axis=-1)
    pixel_label, pure = np.array([0, 1, 2, 4])[dist.argmin(-1)], dist.min(-1) < 30
    own = np.asarray(first_hit(fruxelize(scene.objects, grid, pose), grid, grid.camera()).label)
    geometry = _column_hits_box(grid, pose)
    assert 150 < geometry.sum() < 0.5 * geometry.size and pure.mean() > 0.9
    assert ((pixel_label == 4) == geometry)[pure].all()
    assert ((pixel_label == own) | ~pure).mean() > 0.99
    # fruxelize samples cell centres 4 cm apart: only columns on the box's outline, grazing its edges, may differ.
    outline = np.zeros_like(geometry)
    for axis in (0, 1):
        for step in (1, -1):
            outline |= geometry != np.roll(geometry, step, axis=axis)
    wrong = (own == 4) != geometry
    assert not (wrong & ~outline).any() and wrong.sum() <= 0.1 * outline.sum(), (wrong.sum(), outline.sum())
    # Shifted by one column, image and geometry disagree along the outline: the test sees misalignment.
    assert ((np.roll(pixel_label == 4, 1, axis=1) != geometry) & pure).sum() > 10
    # Where the narrow camera saw nothing, the labels keep the truth: the box goes on there.
    assert ((own == 4) & ~narrow_cover).any()


class CameraLabelRenderer:
    """A renderer of class colours for any camera: each pixel in the colour of the first solid on its ray, found by
    ``fruxelize`` on a grid with one column per pixel of the camera asked for, and ``first_hit`` down the columns."""

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        self.scene: Any = None
        self.meshes: Any = None

    def set_scene(self, scene: Any) -> None:
        if scene is not self.scene:
            self.scene, self.meshes = scene, scene.mesh_set()

    def render(self, pose: np.ndarray, rng: Any, camera: Camera | None = None) -> np.ndarray:
        cam = self.config.image_camera() if camera is None else camera
        g = self.config.grid
        hfov = math.degrees(2 * math.atan(cam.width / (2 * cam.fx)))
        grid = FruxelGrid(width=cam.width, height=cam.height, depth=g.depth, z_near=g.z_near, z_far=g.z_far, hfov=hfov)
        view = first_hit(fruxelize(self.meshes, grid, pose), grid, grid.camera())
        return self.config.classes.colour_of(np.asarray(view.label))

    def close(self) -> None:
        self.scene = self.meshes = None


class GridOnlyRenderer(CameraLabelRenderer):
    """The same, for the grid's view only: a renderer of the protocol without the camera argument."""

    def render(self, pose: np.ndarray, rng: Any) -> np.ndarray:  # type: ignore[override]
        return super().render(pose, rng)


class WrongSizeRenderer(CameraLabelRenderer):
    """A renderer that takes cameras but draws the grid's view whatever it is asked for."""

    def render(self, pose: np.ndarray, rng: Any, camera: Camera | None = None) -> np.ndarray:
        return super().render(pose, rng)


@pytest.fixture
def label_renderers() -> Iterator[None]:
    for name, cls in (("camera-labels", CameraLabelRenderer), ("grid-labels", GridOnlyRenderer),
                      ("wrong-size", WrongSizeRenderer)):
        register_renderer(name, cls)
    yield
    for name in ("camera-labels", "grid-labels", "wrong-size"):
        RENDERERS.pop(name)


def test_sample_images_and_labels_line_up_in_real_rooms(label_renderers: None) -> None:
    """Samples of real rooms with any camera, drawn in class colours: on every column the image covers, the framed
    image is the labels' own view; elsewhere it is grey, and the labels keep the room."""
    config = ANY.replace(renderer="camera-labels")
    covered = uncovered = 0
    with SampleMaker(config, SEED) as maker:
        for i in range(0, 12, 3):
            s = maker.make("train", i)
            own = config.classes.colour_of(np.asarray(first_hit(s.labels, GRID, GRID.camera()).label))
            cover = s.coverage
            agree = (s.image == own).all(-1)
            assert agree[cover].mean() > 0.995, (i, s.camera.hfov, agree[cover].mean())
            assert (s.image[~cover] == PAD_VALUE).all()
            covered += int(cover.sum())
            uncovered += int((~cover).sum()) if (own[~cover] != config.classes.colour_of(np.zeros(1, int))).any() else 0
    assert covered > 0 and uncovered > 0  # some camera was narrower than the grid, and the labels went on there


def test_a_renderer_without_the_camera_argument_serves_the_grid_view_only(label_renderers: None) -> None:
    with SampleMaker(ANY.replace(renderer="grid-labels", camera=ROBOT_CAMERA), SEED) as maker:
        maker.make("train", 0)
    fixed = CameraConfig(height=(0.5, 1.5), pitch=(0.0, 30.0), hfov=(60.0, 60.0))
    with SampleMaker(ANY.replace(renderer="grid-labels", camera=fixed), SEED) as maker:
        assert maker.make("train", 0).camera.hfov == 60.0
    with SampleMaker(ANY.replace(renderer="grid-labels"), SEED) as maker, pytest.raises(
            ConfigError, match="renderer 'grid-labels' draws only the grid's view"):
        for i in range(0, 12, 3):
            maker.make("train", i)
    # A render of another size than the camera asked for would be resampled by the framing: refused.
    with SampleMaker(ANY.replace(renderer="wrong-size"), SEED) as maker, pytest.raises(
            RuntimeError, match=r"renderer 'wrong-size' returned uint8 \(32, 32, 3\) for a \d+x\d+ camera"):
        for i in range(0, 12, 3):
            maker.make("train", i)


# ---------------------------------------------------------------------------------------------------- shards
@pytest.fixture(scope="module")
def any_data_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("any")
    generate(str(out), ANY, SEED, progress=False)
    return out


def test_shards_record_the_camera(any_data_set: Path, tmp_path: Path) -> None:
    """Shards hold each sample's record (the same as the maker's, bit for bit); a second run, with two spawned
    workers, writes the same bytes."""
    with SampleMaker(ANY, SEED) as maker:
        made = [maker.make("test", i) for i in range(3)]
    spec = [s for s in shard_specs(ANY) if s.split == "test"][0]
    with ShardReader(str(any_data_set / spec.file), spec, ANY, SEED) as reader:
        meta = reader.meta
        read = reader.samples()
    assert meta["version"] == 3 and [e["camera"] for e in meta["samples"]] == [s.camera.to_dict() for s in made]
    for a, b in zip(made, read, strict=True):
        assert a.camera == b.camera
        np.testing.assert_array_equal(a.coverage, b.coverage)
        assert a.image.tobytes() == b.image.tobytes() and a.pose.tobytes() == b.pose.tobytes()
    again = tmp_path / "again"
    generate(str(again), ANY, SEED, workers=2, progress=False)
    for f in sorted(any_data_set.iterdir()):
        assert (again / f.name).read_bytes() == f.read_bytes(), f.name


def test_a_damaged_camera_record_is_refused(tmp_path: Path) -> None:
    spec = shard_specs(ANY)[0]
    with SampleMaker(ANY, SEED) as maker:
        samples = [maker.make(spec.split, i) for i in spec.indices]
    for change, problem in (({"image_size": (7, 7)}, "not those of its field of view"),
                            ({"gravity": (0.0, 2.0, 0.0)}, "not a unit vector"),
                            ({"pitch": float("nan")}, "pitch must be 1 finite numbers")):
        bad = [dataclasses.replace(s, camera=dataclasses.replace(s.camera, **change)) if k == 1 else s
               for k, s in enumerate(samples)]
        path = tmp_path / spec.file
        path.write_bytes(encode_shard(spec, ANY, SEED, bad))
        with pytest.raises(DatasetError, match=f"meta entry 1: .*{problem}"):
            ShardReader(str(path), spec, ANY, SEED)


def test_old_shards_still_read_as_the_robot_mount(tmp_path: Path) -> None:
    """A data set of format 2, made before the camera work: read with the robot mount's record, its samples are
    the robot camera's of today; the generator reads it but does not add to it."""
    old = REFERENCE / "dataset_v2"
    ds = ShardDataset(old, "train")
    assert ds.manifest.version == 2 and len(ds) == 3
    config = ds.config
    with SampleMaker(config, ds.manifest.seed, backend="warp-cpu") as maker:
        for i in range(3):
            s, fresh = ds.sample(i), maker.make("train", i)
            assert s.camera == fresh.camera == cameras.camera_record(config, cameras.robot_mount(config), s.pose)
            assert s.coverage.all() and s.camera.height == 1.0 and s.camera.pitch == 10.0
            assert s.labels.tobytes() == fresh.labels.tobytes()
            np.testing.assert_allclose(s.pose, fresh.pose, rtol=0, atol=1e-12)
    item = ds[1]
    assert sorted(item["camera"]) == sorted(CAMERA_KEYS) and float(item["camera"]["pitch"]) == 10.0
    ds.close()
    assert Manifest.load(str(old / MANIFEST)).to_json() == (old / MANIFEST).read_text()
    copy = tmp_path / "old"
    shutil.copytree(old, copy)
    with pytest.raises(DatasetError, match="format version 2, made by an older fruxel; it stays readable"):
        generate(str(copy), config, ds.manifest.seed, progress=False)


# ---------------------------------------------------------------------------------------------------- batches
def _batches(workers: int, position: tuple[int, int] = (0, 0), source: str = "stream", root: str = "") -> Batches:
    plan = BlockPlan(0, 12, ANY.samples_per_scene, None)

    def factory(block: int, skip: int) -> BlockStream:
        return BlockStream(plan, source, "train", sim_config=ANY, seed=SEED, root=root, first_block=block, skip=skip,
                           device="cpu", stop_block=4)

    return Batches(factory, 5, workers, position=position)


def _all(batches: Batches) -> list[dict[str, Any]]:
    try:
        return list(batches)
    finally:
        batches.close()


def test_batches_carry_the_camera_and_resume(any_data_set: Path) -> None:
    """Batches of 5 over rooms of 3: the camera dictionary follows its samples across block boundaries, from the
    stream and from the shards alike, and a resumed run continues with the same cameras."""
    with SampleMaker(ANY, SEED) as maker:
        made = [maker.make("train", i) for i in range(12)]
    whole = _all(_batches(0))
    assert [len(b["index"]) for b in whole] == [5, 5, 2]
    cam = {k: torch.cat([b["camera"][k] for b in whole]) for k in CAMERA_KEYS}
    shapes = {"intrinsics": (12, 4), "image_size": (12, 2), "pose": (12, 4, 4), "height": (12,), "gravity": (12, 3),
              "pitch": (12,), "roll": (12,), "hfov": (12,), "coverage": (12, 32, 32)}
    for k, shape in shapes.items():
        assert tuple(cam[k].shape) == shape, k
        want = np.stack([s.camera_arrays()[k] for s in made])
        assert cam[k].numpy().dtype == want.dtype and np.array_equal(cam[k].numpy(), want), k
    assert cam["coverage"].dtype == torch.bool and cam["image_size"].dtype == torch.int64
    shards = _all(_batches(0, source="shards", root=str(any_data_set)))
    for a, b in zip(whole, shards, strict=True):
        for k in CAMERA_KEYS:
            assert torch.equal(a["camera"][k], b["camera"][k]), k
    # Resume after the first batch (block 1, 2 of its 3 samples used): the rest is what an uninterrupted run saw.
    first = _batches(0)
    next(first)
    position = first.position
    first.close()
    assert position == (1, 2)
    rest = _all(_batches(0, position=position))
    for k in CAMERA_KEYS:
        assert torch.equal(torch.cat([b["camera"][k] for b in rest]), cam[k][5:]), k


def test_spawned_data_workers_carry_the_camera() -> None:
    one, two = _all(_batches(0)), _all(_batches(2))
    assert len(one) == len(two)
    for a, b in zip(one, two, strict=True):
        assert torch.equal(a["image"], b["image"]) and torch.equal(a["labels"], b["labels"])
        for k in CAMERA_KEYS:
            assert torch.equal(a["camera"][k], b["camera"][k]), k


def test_record_round_trip_and_checks() -> None:
    r = CameraRecord((40.0, 40.0, 20.0, 20.0), (40, 40), 1.2, (0.0, math.cos(0.2), math.sin(0.2)), 11.46, 0.0, 53.1)
    assert CameraRecord.from_dict(json.loads(json.dumps(r.to_dict()))) == r
    with pytest.raises(ValueError, match="exactly the keys"):
        CameraRecord.from_dict({**r.to_dict(), "extra": 1})
    with pytest.raises(ValueError, match="image_size must be two positive integers"):
        CameraRecord.from_dict({**r.to_dict(), "image_size": [40.5, 40]})


def test_training_streams_the_furnished_rooms_from_any_camera_by_default() -> None:
    """fruxel-train's streamed samples are, unless a config says otherwise, the furnished rooms from any camera drawn
    by the world's own renderer (the ray tracer); the old style stays one setting away."""
    from fruxel.train.config import DataConfig, preset
    from fruxel.train.samples import SampleSource, sim_config

    data = DataConfig()
    assert (data.world, data.camera, data.renderer) == ("home", "any", "")
    config = sim_config(preset("ssz64-any").model, SampleSource.of(data), (("train", 4),))
    assert config.world == "home" and config.camera == ANY_CAMERA and config.renderer == "raytrace"
    old = sim_config(preset("ssz64").model, SampleSource.of(dataclasses.replace(data, world="flat", camera="robot")),
                     (("train", 4),))
    assert old.world == "flat" and old.camera == ROBOT_CAMERA and old.renderer == "pyrender"


# ---------------------------------------------------------------------------------------------------- test sets
def test_test_sets_camera_side() -> None:
    assert list(testsets.TEST_SETS) == ["any-camera", "any-camera-test-assets", "robot"]
    base = ANY.replace(camera=ROBOT_CAMERA, splits=(("test", 32),))
    robot = testsets.test_set("robot").config(base)
    # The robot set is the base config itself: the samples of earlier reports, bit for bit.
    assert robot == base and robot.digest() == base.digest()
    for name in ("any-camera", "any-camera-test-assets"):
        s = testsets.test_set(name)
        assert s.camera == ANY_CAMERA and s.world == "home"
        cams = s.config(base, camera_only=True)
        assert cams == base.replace(camera=ANY_CAMERA)
        with pytest.raises(ConfigError, match=f"test set '{name}': world 'home' labels"):
            s.config(base)  # the flat world's six classes have no ceiling or object
    assert testsets.test_set("any-camera").assets == "train" and testsets.test_set("any-camera-test-assets").assets \
        == "test"
    with pytest.raises(ConfigError, match="unknown test set 'hand-held'"):
        testsets.test_set("hand-held")


def test_test_sets_world_and_assets(tiny_pack: Path) -> None:
    """The room-world sets draw furnished rooms with the ray tracer, their test rooms furnished from the set's asset
    split only (checked on the rooms their sample maker makes); the robot set is the flat world of its renderer."""
    from fruxel.classes import HOME_CLASSES
    from fruxel.train.sim.assetpack import AssetPack
    from fruxel.train.sim.sample import make_room

    base = ANY.replace(splits=(("test", 32),), classes=HOME_CLASSES, world="home", renderer="raytrace",
                       assets=str(tiny_pack))
    a, b, r = (testsets.test_set(n).config(base) for n in ("any-camera", "any-camera-test-assets", "robot"))
    assert (a.world, b.world, r.world) == ("home", "home", "flat")
    assert (a.renderer, b.renderer, r.renderer) == ("raytrace", "raytrace", "pyrender")
    assert (a.camera, b.camera, r.camera) == (ANY_CAMERA, ANY_CAMERA, ROBOT_CAMERA)
    assert a.replace(home=b.home) == b and a.digest() != b.digest()
    pack = AssetPack(tiny_pack)
    for config, split in ((a, "train"), (b, "test")):
        used: set[str] = set()
        for seed in range(3):
            scene = make_room(config, seed, "test")
            used |= {o.asset for o in scene.objects if o.asset is not None}
            used |= {i for o in scene.objects for m in o.materials for i in (m.texture, m.image) if i is not None}
        assert used and {pack.entry(i).split for i in used} == {split}
    # Training rooms keep the training assets whatever the set.
    train_scene = make_room(b, 0, "train")
    assert {pack.entry(o.asset).split for o in train_scene.objects if o.asset is not None} == {"train"}


def test_streamed_samples_take_the_source_camera() -> None:
    """The training stream's simulator config takes its cameras from the sample source, by name."""
    from fruxel.train.models.ssz import SSZConfig
    from fruxel.train.samples import DataError, SampleSource, sim_config

    model = SSZConfig(grid=FruxelGrid(16, 16, 16, 0.5, 8.0, 60.0), image_scale=2, levels=3, stem=4, encoder=(8, 8, 8),
                      encoder_blocks=(1, 1, 1), encoder_expand=2, topdown=(8, 8, 8), decoder=(4, 4, 4),
                      decoder_blocks=(1, 1, 1))
    assert sim_config(model, SampleSource(), (("train", 4),)).camera == ROBOT_CAMERA
    source = SampleSource(camera="any")
    assert sim_config(model, source, (("train", 4),)).camera == ANY_CAMERA and "any camera" in source.describe()
    with pytest.raises(DataError, match="sample source camera must be one of robot, any, got 'phone'"):
        SampleSource(camera="phone")


def test_any_camera_looks_towards_the_room_within_its_aim() -> None:
    """ANY_CAMERA aims every frame from the robot's position towards the room's middle within +- aim / 2 (a person
    pointing a camera at the room); the headings differ from frame to frame; the robot camera looks along its
    drive, not at the middle."""
    def off_centre(samples: list, sizes: dict) -> np.ndarray:
        out = []
        for s in samples:
            fwd = s.pose[:3, 2]
            to_mid = sizes[s.scene][:2] / 2 - s.pose[:2, 3]
            # the heading: the optical axis's horizontal direction (the roll turns the image about that axis)
            a = math.degrees(math.atan2(fwd[1], fwd[0]) - math.atan2(to_mid[1], to_mid[0]))
            out.append((a + 180.0) % 360.0 - 180.0)
        return np.array(out)

    results = {}
    more = ANY.replace(splits=(("train", 48),), samples_per_scene=8)
    for name, config in (("any", more), ("robot", more.replace(camera=ROBOT_CAMERA))):
        with SampleMaker(config, SEED) as maker:
            samples = [maker.make("train", i) for i in range(48)]
            sizes = {s.scene: np.asarray(maker.scene_of("train", s.index)[0].room_size) for s in samples}
        results[name] = off_centre(samples, sizes)
    assert np.abs(results["any"]).max() <= ANY_CAMERA.aim / 2 + 1e-6
    assert np.std(results["any"]) > 5.0
    assert np.abs(results["robot"]).max() > ANY_CAMERA.aim / 2 + 10.0

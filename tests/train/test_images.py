"""Camera images of simulated rooms: alignment with the grid, determinism, augmentation, the contact sheet."""

from __future__ import annotations

import numpy as np
import pytest

from fruxel.grid import FruxelGrid
from fruxel.kernels import first_hit
from fruxel.kernels.fruxelize import fruxelize
from fruxel.train.sim.config import AugmentConfig, ImageConfig, SimConfig, augment_rng
from fruxel.train.sim.images import SceneRenderer, contact_sheet, second_camera
from fruxel.train.sim.scene import FreeSpace, Scene, SceneObject, boxes, make_scene

trimesh = pytest.importorskip("trimesh")

GRID = FruxelGrid(width=32, height=24, depth=32, z_near=0.5, z_far=8.0, hfov=70.0)

# Camera at (0, 0, 1) looking along +x, level: OpenCV x right = world -y, y down = world -z, z forward = world +x.
POSE = np.array([[0.0, 0.0, 1.0, 0.0], [-1.0, 0.0, 0.0, 0.0], [0.0, -1.0, 0.0, 1.0], [0.0, 0.0, 0.0, 1.0]])

COLOURS = {1: (0.9, 0.1, 0.1, 1.0), 2: (0.1, 0.9, 0.1, 1.0), 4: (0.1, 0.1, 0.9, 1.0)}


def _box_scene() -> Scene:
    """A floor, a back wall and a box on the floor, in three flat colours, lit by ambient light only."""
    parts = {
        2: ([-1.0, -4.0, -0.1], [8.0, 4.0, 0.0]),
        1: ([6.0, -4.0, 0.0], [6.3, 4.0, 3.0]),
        4: ([2.5, -0.3, 0.0], [3.5, 1.2, 1.4]),
    }
    objects = []
    for label, (lo, hi) in parts.items():
        v, f = boxes([lo], [hi])
        objects.append(SceneObject(f"obj{label}", label, trimesh.Trimesh(v, f, process=False), COLOURS[label],
                                   0.0, 1.0))
    free = FreeSpace(np.zeros((2, 2), dtype=bool), np.zeros(2), 1.0)
    return Scene(tuple(objects), np.array([6.0, 8.0, 3.0]), (), free, 0)


def _config(size: int, **augment: object) -> SimConfig:
    return SimConfig(grid=GRID, image=ImageConfig(size=size, background=(1.0, 1.0, 1.0),
                                                  augment=AugmentConfig(**augment)))


def test_image_lines_up_with_the_grid() -> None:
    # With ambient light 1 and no lamps each object shows in its own flat colour, so every pixel can be classified
    # and compared with the own-view ground truth. At S = W pixel (x, y) looks down column (y, x) exactly; thin
    # slices keep the ground truth's cell-centre rule from moving object edges by more than a few columns.
    grid = FruxelGrid(width=32, height=24, depth=256, z_near=0.5, z_far=8.0, hfov=70.0)
    cfg = _config(32, enabled=False, ambient=(1.0, 1.0)).replace(grid=grid)
    scene = _box_scene()
    with SceneRenderer(cfg) as r:
        r.set_scene(scene)
        img = r.render(POSE)
    assert img.shape == (24, 32, 3) and img.dtype == np.uint8
    view = np.asarray(first_hit(fruxelize(scene.objects, grid, POSE), grid, grid.camera()).label)
    # pyrender writes its linear shading through a 1/2.2 gamma.
    refs = 255.0 * np.array([[1.0, 1.0, 1.0]] + [COLOURS[k][:3] for k in (1, 2, 4)]) ** (1 / 2.2)
    dist = np.linalg.norm(img[:, :, None, :].astype(float) - refs[None, None], axis=-1)
    pixel_label = np.array([0, 1, 2, 4])[dist.argmin(axis=-1)]
    # Pixels on an edge are blends (the renderer antialiases): only pixels of one flat colour are compared.
    pure = dist.min(axis=-1) < 30
    assert {0, 1, 2, 4} == set(np.unique(view).tolist())
    assert pure.mean() > 0.85
    agree = (pixel_label == view)[pure].mean()
    assert agree > 0.99, agree
    # An image one pixel off would disagree along every edge: the test can see misalignment.
    for axis in (0, 1):
        assert (np.roll(pixel_label, 1, axis=axis) == view)[pure].mean() < 0.97


def test_same_inputs_same_bytes_in_fresh_renderers() -> None:
    cfg = SimConfig(grid=FruxelGrid(16, 16, 16, 0.5, 8.0, 60.0), image=ImageConfig(size=96))
    scene = make_scene(3)
    pose = np.array(POSE)
    pose[:3, 3] = [scene.room_size[0] / 2, scene.room_size[1] / 2, 1.0]
    images, keep = [], []
    for k in range(3):
        # pyrender orders nodes by address; live clutter moves the new scene's nodes elsewhere in memory (drawn in
        # another order, the same scene gave other bytes in a few pixels).
        keep.append([object() for _ in range(997 * k + 13)])
        with SceneRenderer(cfg) as r:
            r.set_scene(make_scene(3))
            images.append(r.render(pose, augment_rng(0, "train", 5)))
    assert images[0].tobytes() == images[1].tobytes() == images[2].tobytes()
    with SceneRenderer(cfg) as r:
        r.set_scene(scene)
        other = r.render(pose, augment_rng(0, "train", 6))
        plain = r.render(pose, None)
    assert other.tobytes() != images[0].tobytes() and plain.tobytes() != images[0].tobytes()


def test_augmentation_off_ignores_the_generator() -> None:
    cfg = _config(32, enabled=False)
    with SceneRenderer(cfg) as r:
        r.set_scene(_box_scene())
        a = r.render(POSE, np.random.default_rng(1))
        b = r.render(POSE, None)
    np.testing.assert_array_equal(a, b)


NEUTRAL = {"light_intensity": (1.0, 1.0), "light_tint": 0.0, "ambient": (0.5, 0.5), "object_colour": 0.0,
           "exposure": (0.0, 0.0), "white_balance": 0.0, "saturation": (1.0, 1.0), "gamma": (1.0, 1.0),
           "noise": (0.0, 0.0)}
"""Augmentation ranges of one value each that change nothing: every draw is the same whatever the generator."""


def test_camera_response() -> None:
    """The image-space steps of the augmentation: one stop of exposure doubles every channel value (clipped at
    255), and pixel noise moves values a little, around the same image; the scene is drawn the same each time."""

    def image(**augment: object) -> np.ndarray:
        with SceneRenderer(_config(32, **{**NEUTRAL, **augment})) as r:
            r.set_scene(_box_scene())
            return r.render(POSE, np.random.default_rng(0))

    base = image()
    brighter = image(exposure=(1.0, 1.0))
    np.testing.assert_array_equal(brighter, np.minimum(2 * base.astype(int), 255))
    assert (base < 128).any() and (base > 128).any()
    noisy = image(noise=(0.05, 0.05))
    assert noisy.dtype == np.uint8 and 0 < np.abs(noisy.astype(int) - base).mean() < 20


def test_second_camera_and_contact_sheet() -> None:
    cfg = _config(32)
    depth = np.full((24, 32), 3.0, np.float32)
    cam = second_camera(depth, cfg, 40)
    assert (cam.width, cam.height) == (40, 30)
    # It looks at the point 3 m down the robot camera's axis from beside and above it (grid frame, y down).
    x, y, d = cam.project([0.0, 0.0, 3.0])
    assert abs(x - 20.0) < 1e-6 and abs(y - 15.0) < 1e-6 and d > 0
    assert cam.position[0] > 0 and cam.position[1] < 0
    palette = cfg.classes.palette()
    rows = [{"a": np.zeros((24, 32, 3), np.uint8), "b": np.full((12, 16, 3), 200, np.uint8)}]
    sheet = contact_sheet(rows, cfg.classes.names, palette, ["row"])
    assert sheet.dtype == np.uint8 and sheet.ndim == 3 and sheet.shape[1] >= 32 + 32
    flat = sheet.reshape(-1, 3)
    for c in range(1, len(palette)):
        assert (flat == palette[c]).all(axis=1).any(), cfg.classes.names[c]

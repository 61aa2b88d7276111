"""One sample of the simulator and the code that makes it.

Sample
    One camera view (:class:`Sample`): the RGB image, the ground-truth labels of the grid aligned with that
    camera, the camera pose, what the sample records about its camera (:class:`.cameras.CameraRecord`, and the grid
    columns the image covers) and where the sample came from. Each room's trajectory draws its camera from
    ``SimConfig.camera`` (:mod:`.cameras`: the robot's own mount by default); a camera of another field of view than
    the grid's renders at its own and is framed onto the grid's view, as the commands frame a photo. Sample
    ``i`` of a split is a pure function of the config, the base seed, the split and ``i`` (seed rule in
    :mod:`.config`); :class:`SampleMaker` computes it, reusing the room, its robot trajectory, its uploaded
    meshes and the renderer for consecutive samples of one room.

Own-view truth
    The labels are the one source of ground truth. What the grid's own camera sees of them (per pixel the label
    and depth of its column's first occupied cell) is ``fruxel.kernels.first_hit(labels, grid, grid.camera())``,
    computed where it is needed, on the training device (:class:`fruxel.train.losses.ShellLoss` does, and hands
    it out as ``ShellTargets.own_view``), like the first hits of every other view. Samples do not carry a second
    copy of it: a stored image could disagree with the kernel's (by a float32 rounding of the depth, or a bug),
    and computing it in numpy on the host cost more per sample than ``fruxelize`` on a GPU (the ``own_view``
    and ``fruxelize`` stages of the simulator's profile in BENCHMARKS.md).

Samples are written to shard files by :mod:`.shards` and :mod:`.writer` and read back by :mod:`.dataset`; training
streams them, or reads the shards, through :mod:`fruxel.train.samples`.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from . import cameras
from .cameras import CameraRecord, Mount
from .config import ConfigError, SimConfig, augment_rng, camera_seed, scene_seed, trajectory_seed
from .renderer import Renderer, make_renderer, takes_camera

MAX_ROOM_ATTEMPTS = 16
"""Rooms tried for one scene index before giving up, when the robot finds no free floor (see the seed rule)."""

FIELDS = ("image", "labels", "pose")
"""The arrays of a sample (attributes of :class:`Sample`), in the order shards store them."""


@dataclass(frozen=True, eq=False)
class Sample:
    """One training sample: a camera image, the ground truth of the grid aligned with the camera, and the camera."""

    split: str
    """Name of the split the sample belongs to."""
    index: int
    """Index of the sample in its split."""
    scene: int
    """Room index in the split, ``index // samples_per_scene``."""
    frame: int
    """Frame of the room's robot trajectory, ``index % samples_per_scene``."""
    scene_seed: int
    """The seed the room was made from (``make_scene(scene_seed, config.room)``)."""
    image: np.ndarray
    """``(S * H / W, S, 3)`` uint8 RGB image of the grid's view: the camera's own render, framed onto the grid's
    view when its field of view is another (grey where the camera saw nothing, :mod:`.cameras`)."""
    labels: np.ndarray
    """``(D, H, W)`` uint8 ground-truth labels of the grid (0 = empty), indexed ``[k, j, i]``; the one source of
    truth, own view included (see the module docstring)."""
    pose: np.ndarray
    """``(4, 4)`` float64 camera-to-world transform of the camera (= the grid's pose), world frame z up, OpenCV
    camera axes."""
    camera: CameraRecord
    """The camera's intrinsics, image size, height above the floor, gravity direction, pitch, roll and field of
    view (:mod:`.cameras`)."""
    coverage: np.ndarray
    """``(H, W)`` bool, grid frame: the grid columns the image covers (:func:`fruxel.train.framing.frame_coverage`
    of the framed render; all True for a camera as wide as the grid's or wider). The labels of the others are the
    full truth all the same (:mod:`.cameras` says why)."""

    def arrays(self) -> dict[str, np.ndarray]:
        """The arrays keyed by :data:`FIELDS`."""
        return {name: getattr(self, name) for name in FIELDS}

    def camera_arrays(self) -> dict[str, np.ndarray]:
        """The camera as arrays keyed by :data:`.cameras.CAMERA_KEYS` (the ``camera`` of a batch, per sample)."""
        return {**self.camera.arrays(), "pose": self.pose, "coverage": self.coverage}


def field_specs(config: SimConfig) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """dtype and shape of every per-sample member for ``config``."""
    g = config.grid
    return {
        "image": (np.dtype(np.uint8), (config.image_height, config.image_width, 3)),
        "labels": (np.dtype(np.uint8), g.shape),
        "pose": (np.dtype(np.float64), (4, 4)),
    }


@dataclass
class _Room:
    """One room with its trajectory and uploaded meshes, kept while consecutive samples use it."""

    key: tuple[str, int]
    """``(split, scene index)``."""
    scene: Any
    """The :class:`fruxel.train.sim.scene.Scene`."""
    poses: np.ndarray
    """``(samples_per_scene, 4, 4)`` float64 camera-to-world poses of the robot trajectory's camera (its roll
    included), world frame z up, OpenCV camera axes."""
    mesh_set: Any
    """The room's solids uploaded for ``fruxelize`` (:class:`fruxel.kernels.fruxelize.MeshSet`)."""
    seed: int
    """The seed the room was made from."""
    mount: Mount
    """The camera the trajectory drew."""
    coverage: np.ndarray
    """``(H, W)`` bool: the grid columns the camera's framed image covers."""


def make_room(config: SimConfig, seed: int, split: str) -> Any:
    """The room of ``config.world`` made from ``seed`` for data split ``split``: a flat room
    (:func:`.scene.make_scene`) or a furnished one (:func:`.rooms.make_home`, whose assets come from the pack split
    that ``config.home`` gives ``split``)."""
    if config.world == "home":
        from .rooms import make_home

        return make_home(seed, config.home, config.classes, assets=config.assets, split=split)
    from .scene import make_scene

    return make_scene(seed, config.room, config.classes)


STAGES = ("scene", "trajectory", "upload", "render", "fruxelize")
"""Stages :class:`SampleMaker` times (seconds accumulate in ``SampleMaker.timings``)."""


class SampleMaker:
    """Computes samples from ``(config, seed, split, index)``; one per process (it owns the renderer that
    ``config.renderer`` names, :mod:`.renderer`, e.g. an OpenGL context).

    Consecutive indices of one room reuse the room, its trajectory, the meshes uploaded for ``fruxelize`` and the
    renderer's scene, so asking for samples in index order is fastest.

    Args:
        config: the generator settings.
        seed: the base seed, >= 0.
        backend: ``fruxelize`` backend (``"warp"``, ``"warp-cpu"``, ``"warp-cuda"``); results do not depend on it.
        device: Warp device, or None (CUDA when present, else the CPU).
    """

    def __init__(self, config: SimConfig, seed: int, *, backend: str | None = "warp",
                 device: str | None = None) -> None:
        self.config = config
        """The generator settings."""
        self.seed = int(seed)
        """The base seed."""
        self.backend = backend
        """The ``fruxelize`` backend."""
        self.device = device
        """The Warp device, or None."""
        self.timings: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        """Seconds spent per stage of :data:`STAGES` since construction (for profiling)."""
        self._room: _Room | None = None
        self._renderer: Renderer | None = None

    def _load_room(self, split: str, scene: int) -> _Room:
        if self._room is not None and self._room.key == (split, scene):
            return self._room

        from .robot import TrajectoryError, random_trajectory

        cfg = self.config
        for attempt in range(MAX_ROOM_ATTEMPTS):
            t0 = time.perf_counter()
            s_seed = scene_seed(self.seed, split, scene, attempt)
            room = make_room(cfg, s_seed, split)
            t1 = time.perf_counter()
            self.timings["scene"] += t1 - t0
            mount = cameras.draw_mount(cfg, camera_seed(self.seed, split, scene))
            kwargs = {**cfg.trajectory.kwargs(), "mount": mount.robot_mount(cfg.trajectory.mount.offset)}
            try:
                traj = random_trajectory(room, cfg.samples_per_scene, trajectory_seed(self.seed, split, scene, attempt),
                                         **kwargs)
            except TrajectoryError:
                self.timings["trajectory"] += time.perf_counter() - t1
                continue
            t2 = time.perf_counter()
            self.timings["trajectory"] += t2 - t1
            self._room = None
            mesh_set = room.mesh_set(backend=self.backend, device=self.device)
            self.timings["upload"] += time.perf_counter() - t2
            poses = np.asarray(traj.poses, dtype=np.float64)
            if cfg.camera.aim is not None:
                poses = cameras.aim_poses(poses, np.asarray(room.room_size, dtype=np.float64)[:2] / 2, mount,
                                          cfg.camera.aim, camera_seed(self.seed, split, scene))
            poses = cameras.roll_poses(poses, mount.roll)
            self._room = _Room((split, scene), room, poses, mesh_set, s_seed, mount,
                               cameras.coverage(cfg, mount.hfov))
            return self._room
        raise RuntimeError(f"split {split!r} scene {scene}: no room among {MAX_ROOM_ATTEMPTS} attempts had free "
                           "floor for the robot; loosen config.room or config.trajectory")

    def scene_of(self, split: str, index: int) -> tuple[Any, np.ndarray]:
        """The room of sample ``index`` of ``split`` and its camera pose, without rendering or labelling it.

        Returns:
            ``(Scene, pose (4, 4) float64)``: the pose is the sample's ``pose``.

        Raises:
            ConfigError: an unknown split or an index outside it.
        """
        room, frame = self._locate(split, index)
        return room.scene, room.poses[frame].copy()

    def _locate(self, split: str, index: int) -> tuple[_Room, int]:
        """The loaded room of sample ``index`` and its frame; ConfigError for an index outside the split."""
        n = self.config.split_samples(split)
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < n:
            raise ConfigError(f"sample index {index!r} is outside split {split!r} of {n} samples")
        scene, frame = divmod(int(index), self.config.samples_per_scene)
        return self._load_room(split, scene), frame

    def make(self, split: str, index: int) -> Sample:
        """Sample ``index`` of ``split``.

        Raises:
            ConfigError: an unknown split or an index outside it.
        """
        return self.make_with_render(split, index)[0]

    def make_with_render(self, split: str, index: int) -> tuple[Sample, np.ndarray]:
        """Sample ``index`` of ``split`` and its camera's render before framing: ``(h, w, 3)`` uint8 RGB of
        ``sample.camera`` (its intrinsics and image size; the sample's ``image`` itself when the camera is not
        framed). A photo with those intrinsics, framed as the commands frame photos, is the sample's image (what
        ``fruxel-sim export`` writes).

        Raises:
            ConfigError: an unknown split or an index outside it.
        """
        from fruxel.kernels.fruxelize import fruxelize

        room, frame = self._locate(split, index)
        index, scene, pose = int(index), room.key[1], room.poses[frame]
        t0 = time.perf_counter()
        render, image = self._render(room, pose, augment_rng(self.seed, split, index))
        t1 = time.perf_counter()
        labels = np.ascontiguousarray(fruxelize(room.mesh_set, self.config.grid, pose, backend=self.backend),
                                      dtype=np.uint8)
        t2 = time.perf_counter()
        self.timings["render"] += t1 - t0
        self.timings["fruxelize"] += t2 - t1
        record = cameras.camera_record(self.config, room.mount, pose)
        sample = Sample(split, index, scene, frame, room.seed, image, labels, pose.copy(), record,
                        room.coverage.copy())
        return sample, render

    def _render(self, room: _Room, pose: np.ndarray, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
        """``(render, image)``: the render of the room's camera at its own field of view, and the sample's image,
        that render framed onto the network's view (:mod:`.cameras`); the same array twice when the camera is the
        network's own.

        Raises:
            ConfigError: a camera of another field of view for a renderer that draws only the network's view.
        """
        cfg = self.config
        if self._renderer is None:
            self._renderer = make_renderer(cfg, self.device)
        self._renderer.set_scene(room.scene)
        if not cameras.is_framed(cfg, room.mount.hfov):
            image = self._renderer.render(pose, rng)
            return image, image
        if not takes_camera(self._renderer):
            raise ConfigError(f"renderer {cfg.renderer!r} draws only the grid's view (its render() takes no camera), "
                              f"but the config's camera draws other fields of view ({room.mount.hfov:.4g} degrees); "
                              "use a fixed camera.hfov equal to the grid's, or a renderer that takes cameras")
        camera = cameras.render_camera(cfg, room.mount.hfov)
        render = self._renderer.render(pose, rng, camera=camera)
        if getattr(render, "shape", None) != (camera.height, camera.width, 3) or render.dtype != np.uint8:
            # Framing would resample an image of the wrong size without a word.
            raise RuntimeError(f"renderer {cfg.renderer!r} returned {getattr(render, 'dtype', type(render))} "
                               f"{getattr(render, 'shape', '')} for a {camera.width}x{camera.height} camera; "
                               f"expected ({camera.height}, {camera.width}, 3) uint8")
        return render, cameras.frame_render(cfg, render, room.mount.hfov)

    def close(self) -> None:
        """Free the renderer (its OpenGL context, say) and the current room (idempotent)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self._room = None

    def __enter__(self) -> SampleMaker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()

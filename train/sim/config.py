"""Typed settings of the data set generator, their JSON form and the per-sample seed rule.

Everything that decides a sample's *content* lives in :class:`SimConfig` (grid, image, augmentation, rooms,
robot trajectories, scenes per trajectory, class table, renderer) together with the split sizes and the shard size; the
base seed is given separately. A data set's manifest records ``SimConfig.to_dict()`` and the seed, and a
generator asked to resume refuses a folder made with anything else. How samples are computed (``backend``,
``device``, number of workers) is not part of it: every backend gives the same labels (conventions section 4).

Image and grid
    The image is taken by the robot camera with the grid's horizontal field of view: ``S`` pixels wide and
    ``S * H / W`` high (``S x S`` for the usual square grids), ``fx = fy = S / (2 tan(hfov / 2))``, principal
    point at the image centre. It is the grid's own camera scaled by ``S / W``, so the image and the grid share
    the optical centre and the frustum's side planes: grid column ``(j, i)`` is seen by the ``S / W`` x ``S / W``
    block of pixels around image point ``((i + 1/2) S / W, (j + 1/2) S / W)``. ``S * H / W`` must be an integer.
    A camera of another field of view (``camera``, :mod:`.cameras`) renders at its own and is framed onto this
    image, as the commands frame a photo; the grid stays aligned with it (the grid's pose is the camera's pose).

Seeds (sample ``i`` of split ``s`` with base seed ``b``; ``k(s) = crc32(s)``, ``n = samples_per_scene``)
    scene ``c = i // n``, frame ``f = i % n``; the room is ``make_scene(scene_seed)`` with
    ``scene_seed = SeedSequence([b, k(s), c, 0]).generate_state(2, uint32)`` read as one uint64; the robot's
    trajectory through it comes from ``SeedSequence([b, k(s), c, 1])`` (always ``n`` frames, so a sample does
    not depend on the split size), and the image augmentation of sample ``i`` from
    ``SeedSequence([b, k(s), i, 2])``; the camera of room ``c`` (``camera``, :mod:`.cameras`) is drawn from
    ``SeedSequence([b, k(s), c, 3])``. A room with no free floor for the robot (rare) is replaced by the next
    attempt ``a = 1, 2, ...``, whose seeds append ``a`` to the first two sequences above (the camera stays).
    Sample ``i`` is therefore a pure function of ``(config, b, s, i)``: shards, streaming and any number of workers
    give the same samples.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
import math
import zlib
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.classes import DEFAULT_CLASSES, ClassTable, ClassTableError
from fruxel.errors import ConfigError
from fruxel.grid import FruxelGrid, GridError

from .cameras import ROBOT_CAMERA, CameraConfig, check_camera
from .checks import check_range
from .raytrace.config import RaytraceConfig
from .renderer import DEFAULT_RENDERER, check_renderer
from .robot import CameraMount, RobotParams
from .rooms.config import HomeConfig
from .scene import RoomConfig, SceneError

CONFIG_VERSION = 1
"""Version of the generator's sample recipe; bumped whenever the same config and seed would give other bytes."""

PAPER_SPLITS: tuple[tuple[str, int], ...] = (("train", 15000), ("test", 1000))
"""The paper's data set: 15k training and 1k test samples."""

WORLDS = ("flat", "home")
"""What the rooms look like (:attr:`SimConfig.world`): ``flat`` (:func:`.scene.make_scene`, flat-coloured box
furniture, the robot's first data sets) or ``home`` (:func:`.rooms.make_home`, furnished rooms from the asset
pack)."""

DEFAULT_WORLD = "flat"
"""The world of every data set made before there were two, and of a config that names none."""
WORLD_RENDERERS = {"flat": "pyrender", "home": "raytrace"}
"""The renderer each world is drawn with unless another is named: the flat world's flat-shaded OpenGL, the furnished
rooms' ray tracer (textures, soft shadows, a camera response)."""

MAX_SPLIT_SAMPLES = 10**9
"""Largest number of samples one split may have: a sanity bound that catches typos such as an extra digit."""


@dataclass(frozen=True)
class AugmentConfig:
    """Random appearance changes of the rendered image, drawn per sample from the sample's augmentation seed.

    Lighting, object colours and saturation change the scene before it is drawn; exposure, white balance, gamma
    and noise act on the RGB image the renderer returns, in [0, 1], in that order.
    """

    enabled: bool = True
    """False renders the scene as generated (light, colours and camera response unchanged)."""
    light_intensity: tuple[float, float] = (0.5, 1.6)
    """Range of the factor each light's intensity is multiplied by (one draw per light)."""
    light_tint: float = 0.12
    """Largest change of each light's colour channels (an added uniform offset in [-t, t], then clipped)."""
    ambient: tuple[float, float] = (0.03, 0.2)
    """Range of pyrender's ambient light level (grey), which keeps unlit faces from being black."""
    object_colour: float = 0.05
    """Largest change of each object's base colour channels (uniform in [-c, c], then clipped to [0, 1])."""
    exposure: tuple[float, float] = (-0.6, 0.6)
    """Range of the exposure change in stops: the image is multiplied by ``2 ** ev``."""
    white_balance: float = 0.08
    """Largest relative change of each channel's gain (uniform factor in [1 - w, 1 + w])."""
    saturation: tuple[float, float] = (0.75, 1.25)
    """Range of the saturation factor of object and background colours (blend with their grey value; 1 keeps
    them)."""
    gamma: tuple[float, float] = (0.8, 1.25)
    """Range of the gamma exponent applied to the [0, 1] image (1 = unchanged)."""
    noise: tuple[float, float] = (0.0, 0.015)
    """Range of the standard deviation of additive Gaussian pixel noise, in [0, 1] units."""

    def __post_init__(self) -> None:
        check_range("light_intensity", self.light_intensity, 0.0)
        check_range("ambient", self.ambient, 0.0, 1.0)
        check_range("exposure", self.exposure, -8.0, 8.0)
        check_range("saturation", self.saturation, 0.0)
        check_range("gamma", self.gamma, 1e-3)
        check_range("noise", self.noise, 0.0, 1.0)
        for name in ("light_tint", "object_colour", "white_balance"):
            v = getattr(self, name)
            if not 0.0 <= float(v) <= 1.0:
                raise ConfigError(f"{name} must be in [0, 1], got {v!r}")


@dataclass(frozen=True)
class ImageConfig:
    """The robot camera's image (see the module docstring for how it relates to the grid)."""

    size: int = 512
    """S: image width in pixels (the paper uses 512); the height is ``S * H / W``."""
    clip_near: float = 0.02
    """Near clip plane of the renderer, metres: keeps the camera close to a wall from cutting into it."""
    clip_far: float = 100.0
    """Far clip plane of the renderer, metres: beyond any room."""
    background: tuple[float, float, float] = (0.72, 0.82, 0.93)
    """RGB in [0, 1] seen through openings (nothing is outside a room): a pale sky."""
    light_scale: float = 0.3
    """Factor on every light intensity of the scene before augmentation: the scene's intensities (pyrender
    units) burn out near walls at 1; 0.3 gives mid-grey walls with highlights only near the lamps."""
    augment: AugmentConfig = field(default_factory=AugmentConfig)
    """Appearance augmentation."""

    def __post_init__(self) -> None:
        if isinstance(self.size, bool) or not isinstance(self.size, (int, np.integer)) or not 1 <= self.size <= 8192:
            raise ConfigError(f"image size must be an integer in [1, 8192], got {self.size!r}")
        if not 0 < self.light_scale < math.inf:
            raise ConfigError(f"light_scale must be a positive number, got {self.light_scale!r}")
        if not 0 < self.clip_near < self.clip_far:
            raise ConfigError(f"image clip planes must satisfy 0 < near < far, got {self.clip_near}, {self.clip_far}")
        if len(self.background) != 3 or not all(0.0 <= float(c) <= 1.0 for c in self.background):
            raise ConfigError(f"background must be RGB in [0, 1], got {self.background!r}")


@dataclass(frozen=True)
class TrajectoryConfig:
    """How the robot drives through a room: the arguments of :func:`fruxel.train.sim.robot.random_trajectory`."""

    robot: RobotParams = field(default_factory=RobotParams)
    """Robot dynamics (conventions section 7)."""
    mount: CameraMount = field(default_factory=CameraMount)
    """Where the camera rides on the robot; its ``hfov`` is set to the grid's by :class:`SimConfig`."""
    radius: float = 0.25
    """Robot footprint radius, metres."""
    margin: float = 0.05
    """Extra clearance the planner keeps from obstacles, metres."""
    steps_per_frame: int = 5
    """Simulation steps (of ``robot.dt``) between two samples of one trajectory: 0.5 s at the defaults, so
    consecutive samples of a room differ by a few dozen centimetres or degrees rather than being near copies."""
    speed_range: tuple[float, float] = (0.2, 0.6)
    """Cruising speeds drawn, m/s."""
    max_turn_rate: float = 0.6
    """Largest turn rate while driving, rad/s."""
    segment_seconds: tuple[float, float] = (0.8, 3.0)
    """Duration range of one random command segment, seconds."""

    def __post_init__(self) -> None:
        if not (self.radius > 0 and self.margin >= 0 and self.max_turn_rate >= 0):
            raise ConfigError("trajectory needs radius > 0, margin >= 0 and max_turn_rate >= 0")
        if isinstance(self.steps_per_frame, bool) or not isinstance(self.steps_per_frame, (int, np.integer)) \
                or self.steps_per_frame < 1:
            raise ConfigError(f"steps_per_frame must be a positive integer, got {self.steps_per_frame!r}")
        check_range("speed_range", self.speed_range, 0.0)
        check_range("segment_seconds", self.segment_seconds, 0.0)

    def kwargs(self) -> dict[str, Any]:
        """Keyword arguments of ``random_trajectory`` (everything but the scene, frame count and seed)."""
        return {"params": self.robot, "mount": self.mount, "radius": self.radius, "margin": self.margin,
                "steps_per_frame": self.steps_per_frame, "speed_range": self.speed_range,
                "max_turn_rate": self.max_turn_rate, "segment_seconds": self.segment_seconds}


DEFAULT_GRID = FruxelGrid(width=128, height=128, depth=128, z_near=0.5, z_far=8.0, hfov=60.0)
"""The paper's grid: 128^3 cells, 0.5 to 8 m, 60 degrees across."""


@dataclass(frozen=True)
class SimConfig:
    """Everything that decides the samples of a data set, except the base seed (see the module docstring)."""

    grid: FruxelGrid = DEFAULT_GRID
    """The fruxel grid of every sample, aligned with its camera (the grid's pose is the camera's)."""
    image: ImageConfig = field(default_factory=ImageConfig)
    """The camera image."""
    room: RoomConfig = field(default_factory=RoomConfig)
    """Ranges the room generator draws from; a loaded ``assets`` library is refused (it cannot be recorded)."""
    trajectory: TrajectoryConfig = field(default_factory=TrajectoryConfig)
    """Robot and camera mount (the robot's own camera; ``camera`` says which cameras the samples take)."""
    classes: ClassTable = DEFAULT_CLASSES
    """Class table of the labels (stored with the data set); it must name the simulator's classes
    (:data:`.scene.CLASS_NAMES`, and ``room.ceiling_class`` with a ceiling), whose ids it gives."""
    samples_per_scene: int = 16
    """n: consecutive samples that share one room and one robot trajectory (frames 0..n-1)."""
    shard_size: int = 64
    """Samples per shard file (the last shard of a split may hold fewer)."""
    splits: tuple[tuple[str, int], ...] = PAPER_SPLITS
    """``(name, samples)`` per split, in file order; names are lower-case letters, digits, '_' or '-'."""
    renderer: str = DEFAULT_RENDERER
    """The renderer that draws the camera images, by its name in the registry of :mod:`fruxel.train.sim.renderer`
    (which says how to add one); ``pyrender`` is offscreen OpenGL with PBR materials, ``raytrace`` the ray-traced
    renderer of :mod:`.raytrace`."""
    raytrace: RaytraceConfig = field(default_factory=RaytraceConfig)
    """Settings of the ``raytrace`` renderer (sampling, camera response); other renderers ignore them."""
    camera: CameraConfig = ROBOT_CAMERA
    """The camera each trajectory draws (:mod:`.cameras`): its height, pitch, roll and field of view. The default,
    :data:`~.cameras.ROBOT_CAMERA`, is the robot's own mount (``trajectory.mount``, the grid's field of view)."""
    world: str = DEFAULT_WORLD
    """Which room generator makes the rooms (:data:`WORLDS`): ``flat`` uses :attr:`room`, ``home`` uses
    :attr:`home` and the asset pack (its classes must include ``ceiling`` and ``object``: :data:`fruxel.classes.
    HOME_CLASSES`)."""
    home: HomeConfig = field(default_factory=HomeConfig)
    """Ranges the furnished rooms draw from (the ``home`` world), the material sampling, and which pack split
    test rooms draw their assets from."""
    assets: str | None = None
    """The asset pack folder of the ``home`` world and of the ``raytrace`` renderer's textures; None: the
    ``FRUXEL_ASSETS`` environment variable, else the repository's ``assets/pack`` (:func:`fruxel.train.sim.rooms.
    resolve_pack`; ``make assets`` builds it). The pack is named by its folder: ``make assets`` gives the same pack
    from the same pinned sources on any machine."""

    def __post_init__(self) -> None:
        check_renderer(self.renderer)
        if not isinstance(self.raytrace, RaytraceConfig):
            raise ConfigError(f"raytrace must be a RaytraceConfig, got {type(self.raytrace).__name__}")
        if not isinstance(self.camera, CameraConfig):
            raise ConfigError(f"camera must be a CameraConfig, got {type(self.camera).__name__}")
        self._check_world()
        if not isinstance(self.grid, FruxelGrid):
            raise ConfigError(f"grid must be a FruxelGrid, got {type(self.grid).__name__}")
        if (self.image.size * self.grid.height) % self.grid.width:
            raise ConfigError(
                f"image size {self.image.size} times grid height {self.grid.height} must be a multiple of the grid "
                f"width {self.grid.width}, so that the image covers exactly the grid's frustum"
            )
        try:
            self.room.class_ids(self.classes)
        except SceneError as e:
            raise ConfigError(str(e)) from None
        if self.room.assets is not None:
            raise ConfigError("room.assets (a loaded library) cannot be recorded in a manifest; use room.asset_dir "
                              "or room.sh3f_files")
        for name in ("samples_per_scene", "shard_size"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < 1:
                raise ConfigError(f"{name} must be a positive integer, got {v!r}")
        object.__setattr__(self, "splits", check_splits(self.splits))
        if self.trajectory.mount.hfov != self.grid.hfov:
            # The grid's field of view is the camera's; a different number in the mount would only mislead.
            mount = dataclasses.replace(self.trajectory.mount, hfov=self.grid.hfov)
            object.__setattr__(self, "trajectory", dataclasses.replace(self.trajectory, mount=mount))
        check_camera(self)

    def _check_world(self) -> None:
        if self.world not in WORLDS:
            raise ConfigError(f"world must be one of {', '.join(WORLDS)}, got {self.world!r}")
        if not isinstance(self.home, HomeConfig):
            raise ConfigError(f"home must be a HomeConfig, got {type(self.home).__name__}")
        if self.assets is not None and (not isinstance(self.assets, str) or not self.assets):
            raise ConfigError(f"assets must be a folder name or None, got {self.assets!r}")
        if self.world == "home":
            from .rooms import CLASS_NAMES

            missing = [n for n in CLASS_NAMES if n not in self.classes.names]
            if missing:
                raise ConfigError(f"world 'home' labels {list(CLASS_NAMES)}; the class table lacks {missing}: use "
                                  "fruxel.classes.HOME_CLASSES")

    # ------------------------------------------------------------------ derived
    @property
    def image_width(self) -> int:
        """Image width in pixels, S."""
        return int(self.image.size)

    @property
    def image_height(self) -> int:
        """Image height in pixels, ``S * H / W``."""
        return self.image.size * self.grid.height // self.grid.width

    def image_camera(self, pose: Any = None) -> Camera:
        """The network image's camera: the grid's own camera scaled by ``S / W`` (the robot camera's, and the view
        every other camera's render is framed onto, :mod:`.cameras`).

        Args:
            pose: ``(4, 4)`` camera-to-world transform (OpenCV axes), identity when None.
        """
        f = self.image_width / (2.0 * self.grid.tu)
        return Camera(fx=f, fy=f, cx=self.image_width / 2.0, cy=self.image_height / 2.0, width=self.image_width,
                      height=self.image_height, pose=np.eye(4) if pose is None else pose)

    def split_samples(self, split: str) -> int:
        """Number of samples of ``split``. Raises ``ConfigError`` for an unknown split."""
        for name, n in self.splits:
            if name == split:
                return n
        raise ConfigError(f"no split named {split!r}; splits are {[s for s, _ in self.splits]}")

    def replace(self, **changes: Any) -> SimConfig:
        """A copy with some fields changed (``dataclasses.replace``)."""
        return dataclasses.replace(self, **changes)

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dictionary of every field (tuples become lists), with ``"version"``:
        :data:`CONFIG_VERSION`.

        ``"renderer"``, ``"camera"``, ``"world"``, ``"home"`` and ``"assets"`` are left out when they are the
        defaults (``home`` is written whenever the world is ``home``), and ``"raytrace"`` unless the ``raytrace``
        renderer draws or its settings are not the defaults: data sets made before renderers, cameras and worlds had
        names record none of them, and their configs keep their digests (:meth:`digest`, in every manifest and
        shard).
        """
        out = {
            "version": CONFIG_VERSION,
            "grid": self.grid.to_dict(),
            "image": _plain(self.image),
            "room": _plain(self.room),
            "trajectory": _plain(self.trajectory),
            "classes": self.classes.to_dict(),
            "samples_per_scene": int(self.samples_per_scene),
            "shard_size": int(self.shard_size),
            "splits": [[name, int(n)] for name, n in self.splits],
        }
        if self.renderer != DEFAULT_RENDERER:
            out["renderer"] = self.renderer
        if self.renderer == "raytrace" or self.raytrace != RaytraceConfig():
            out["raytrace"] = _plain(self.raytrace)
        if self.camera != ROBOT_CAMERA:
            out["camera"] = _plain(self.camera)
        if self.world != DEFAULT_WORLD:
            out["world"] = self.world
        if self.world != DEFAULT_WORLD or self.home != HomeConfig():
            out["home"] = _plain(self.home)
        if self.assets is not None:
            out["assets"] = self.assets
        return out

    @classmethod
    def from_dict(cls, d: Any) -> SimConfig:
        """Inverse of :meth:`to_dict`.

        Raises:
            ConfigError: not a dictionary, missing or unexpected keys at any level, a different
                :data:`CONFIG_VERSION`, or invalid values.
        """
        if not isinstance(d, Mapping):
            raise ConfigError(f"config must be a JSON object, got {type(d).__name__}")
        names = ("version", "grid", "image", "room", "trajectory", "classes", "samples_per_scene", "shard_size",
                 "splits")
        _expect_keys("config", d, names, optional=("renderer", "raytrace", "camera", "world", "home", "assets"))
        if d["version"] != CONFIG_VERSION:
            raise ConfigError(f"config version {d['version']!r} is not this generator's version {CONFIG_VERSION}")
        try:
            grid = FruxelGrid.from_dict(d["grid"])
            classes = ClassTable.from_dict(d["classes"])
            splits = d["splits"]
            if not isinstance(splits, list) or not all(isinstance(s, list) and len(s) == 2 for s in splits):
                raise ConfigError("config 'splits' must be a list of [name, samples] pairs")
            return cls(
                grid=grid,
                image=_from_plain(ImageConfig, d["image"], "image"),
                room=_from_plain(RoomConfig, d["room"], "room"),
                trajectory=_from_plain(TrajectoryConfig, d["trajectory"], "trajectory"),
                classes=classes,
                samples_per_scene=d["samples_per_scene"],
                shard_size=d["shard_size"],
                splits=tuple((s[0], s[1]) for s in splits),
                renderer=d.get("renderer", DEFAULT_RENDERER),
                camera=_from_plain(CameraConfig, d["camera"], "camera") if "camera" in d else ROBOT_CAMERA,
                world=d.get("world", DEFAULT_WORLD),
                home=_from_plain(HomeConfig, d["home"], "home") if "home" in d else HomeConfig(),
                assets=d.get("assets"),
                raytrace=_from_plain(RaytraceConfig, d["raytrace"], "raytrace") if "raytrace" in d
                else RaytraceConfig(),
            )
        except (GridError, ClassTableError, SceneError, TypeError) as e:
            raise ConfigError(f"invalid config: {e}") from None

    def digest(self) -> str:
        """SHA-256 (hex) of the canonical JSON of :meth:`to_dict`: equal configs, equal digests."""
        text = json.dumps(self.to_dict(), sort_keys=True, separators=(",", ":"))
        return hashlib.sha256(text.encode("utf-8")).hexdigest()


def _plain(obj: Any) -> Any:
    """Dataclasses, tuples and numpy scalars as plain JSON values (dataclasses become dictionaries)."""
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: _plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [_plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return [_plain(v) for v in obj.tolist()]
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.floating):
        return float(obj)
    return obj


def _expect_keys(what: str, d: Mapping[str, Any], names: Sequence[str], optional: Sequence[str] = ()) -> None:
    missing = [n for n in names if n not in d]
    extra = sorted(str(k) for k in d if k not in names and k not in optional)
    if missing or extra:
        raise ConfigError(f"{what}: missing keys {missing}, unexpected keys {extra}")


def _from_plain(cls: type, d: Any, what: str) -> Any:
    """Rebuild dataclass ``cls`` from :func:`_plain` output: nested dataclass fields recurse, lists become
    tuples (every sequence field of the generator's configs is a tuple)."""
    if not isinstance(d, Mapping):
        raise ConfigError(f"{what} must be a JSON object, got {type(d).__name__}")
    fields = {f.name: f for f in dataclasses.fields(cls)}
    # A field added after data sets were written is absent from their manifests: it reads as what those data sets
    # were made with (the class's RECORDED_BEFORE), not as today's default.
    before = dict(getattr(cls, "RECORDED_BEFORE", {}))
    _expect_keys(what, d, [n for n in fields if n not in before], optional=tuple(before))
    kwargs = {n: v for n, v in before.items() if n not in d}
    for name, value in d.items():
        default = _field_default(fields[name])
        if dataclasses.is_dataclass(default) and not isinstance(default, type):
            kwargs[name] = _from_plain(type(default), value, f"{what}.{name}")
        else:
            kwargs[name] = _tuples(value)
    return cls(**kwargs)


def _field_default(f: dataclasses.Field) -> Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:
        return f.default_factory()
    return None


def _tuples(value: Any) -> Any:
    if isinstance(value, list):
        return tuple(_tuples(v) for v in value)
    return value


# ---------------------------------------------------------------------------------------------------- splits
def check_splits(splits: Any) -> tuple[tuple[str, int], ...]:
    """Validate ``(name, samples)`` pairs; returns them as a tuple of tuples.

    Raises:
        ConfigError: no split, a repeated or malformed name, or a sample count that is not a positive integer.
    """
    try:
        pairs = [(name, n) for name, n in splits]
    except (TypeError, ValueError):
        raise ConfigError(f"splits must be (name, samples) pairs, got {splits!r}") from None
    if not pairs:
        raise ConfigError("at least one split is needed")
    out = []
    for name, n in pairs:
        if not isinstance(name, str) or not name or len(name) > 32 or not all(
                c.islower() or c.isdigit() or c in "_-" for c in name) or not name[0].isalnum():
            raise ConfigError(f"split name must be 1-32 lower-case letters, digits, '_' or '-', got {name!r}")
        if isinstance(n, bool) or not isinstance(n, (int, np.integer)) or not 1 <= n <= MAX_SPLIT_SAMPLES:
            raise ConfigError(f"split {name!r} must have a positive integer number of samples, got {n!r}")
        out.append((name, int(n)))
    names = [name for name, _ in out]
    if len(set(names)) != len(names):
        raise ConfigError(f"split names must be unique, got {names}")
    return tuple(out)


def parse_splits(text: str) -> tuple[tuple[str, int], ...]:
    """``"train=15000,test=1000"`` -> ``(("train", 15000), ("test", 1000))``.

    Raises:
        ConfigError: malformed text (the message quotes it).
    """
    pairs = []
    for part in text.split(","):
        name, sep, count = part.strip().partition("=")
        if not sep:
            raise ConfigError(f"split {part.strip()!r} must be NAME=SAMPLES (in {text!r})")
        try:
            n = int(count)
        except ValueError:
            raise ConfigError(f"split {name.strip()!r} has a non-integer sample count {count!r}") from None
        pairs.append((name.strip(), n))
    return check_splits(pairs)


def scale_splits(total: int, splits: Sequence[tuple[str, int]] = PAPER_SPLITS) -> tuple[tuple[str, int], ...]:
    """``total`` samples divided in the proportions of ``splits`` (largest remainders; every split gets >= 1).

    ``scale_splits(16000)`` is the paper's ``train=15000, test=1000``.

    Raises:
        ConfigError: ``total`` smaller than the number of splits.
    """
    base = check_splits(splits)
    if isinstance(total, bool) or not isinstance(total, (int, np.integer)) or total < len(base):
        raise ConfigError(f"--samples must be an integer >= {len(base)} (one per split), got {total!r}")
    weights = np.array([n for _, n in base], dtype=np.float64)
    exact = weights / weights.sum() * total
    counts = np.maximum(np.floor(exact).astype(np.int64), 1)
    while counts.sum() > total:
        counts[int(np.argmax(counts))] -= 1
    order = np.argsort(-(exact - np.floor(exact)), kind="stable")
    k = 0
    while counts.sum() < total:
        counts[order[k % len(order)]] += 1
        k += 1
    return tuple((name, int(c)) for (name, _), c in zip(base, counts, strict=True))


# ---------------------------------------------------------------------------------------------------- seeds
def split_key(split: str) -> int:
    """``crc32`` of the split name: the split's entry in every seed sequence (stable across runs and platforms)."""
    return zlib.crc32(split.encode("utf-8"))


def _check_seed(seed: Any) -> int:
    if isinstance(seed, bool) or not isinstance(seed, (int, np.integer)) or seed < 0:
        raise ConfigError(f"seed must be a non-negative integer, got {seed!r}")
    return int(seed)


def _uint64(entropy: list[int]) -> int:
    words = np.random.SeedSequence(entropy).generate_state(2, np.uint32)
    return int(words[0]) | (int(words[1]) << 32)


def scene_seed(seed: int, split: str, scene: int, attempt: int = 0) -> int:
    """Seed of ``make_scene`` for scene ``scene`` of ``split`` (a uint64 as a Python int).

    ``attempt`` > 0 gives the seeds of the rooms tried after one with no free floor for the robot.
    """
    entropy = [_check_seed(seed), split_key(split), int(scene), 0]
    return _uint64(entropy + ([int(attempt)] if attempt else []))


def trajectory_seed(seed: int, split: str, scene: int, attempt: int = 0) -> int:
    """Seed of the robot trajectory through scene ``scene`` of ``split`` (a uint64 as a Python int)."""
    entropy = [_check_seed(seed), split_key(split), int(scene), 1]
    return _uint64(entropy + ([int(attempt)] if attempt else []))


def camera_seed(seed: int, split: str, scene: int) -> np.random.SeedSequence:
    """Seed of the camera drawn for scene ``scene`` of ``split`` (:func:`.cameras.draw_mount`); the same for every
    attempt at the room, so that a replaced room keeps the camera."""
    return np.random.SeedSequence([_check_seed(seed), split_key(split), int(scene), 3])


def augment_rng(seed: int, split: str, index: int) -> np.random.Generator:
    """The random generator of sample ``index``'s image augmentation."""
    return np.random.default_rng(np.random.SeedSequence([_check_seed(seed), split_key(split), int(index), 2]))

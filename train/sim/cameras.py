"""The simulator's cameras: the camera each trajectory draws, its image framed onto the grid's view, and what every
sample records about it (conventions section 7).

Config
    :class:`CameraConfig` (``SimConfig.camera``) gives ranges ``(low, high)`` of the camera's height above the
    floor, pitch, roll and horizontal field of view, drawn uniformly once per trajectory (room) and fixed while the
    robot drives; a range with ``low == high`` is a fixed value, and None is the robot's own: the height and tilt
    of ``TrajectoryConfig.mount``, a level camera (roll 0) and the grid's field of view. :data:`ROBOT_CAMERA` (every
    field None) is the robot's fixed mount; it gives exactly the samples the simulator made before cameras varied,
    and follows the robot's mount and the grid if they change. :data:`ANY_CAMERA` is any camera: 0.3 to 1.9 m above
    the floor, pitch -20 to +40 degrees, roll within +-10 degrees, 50 to 80 degrees across. :data:`CAMERAS` names
    them.

Angles (degrees)
    Pitch is positive looking down. Roll turns the camera about its optical axis, positive clockwise as seen from
    behind the camera: its right side goes down, and the horizon in its image rises to the right. The pose is the
    robot's (heading, then pitch about the camera's x axis), turned by the roll about the camera's z axis, so the
    gravity direction in the camera frame (OpenCV axes: x right, y down, z forward) is
    ``g = (sin r cos p, cos r cos p, sin p)``: ``p = asin(g_z)``, ``r = atan2(g_x, g_y)``.

Draw
    From the trajectory's camera seed (:func:`.config.camera_seed`), apart from the room's and the drive's seeds: the
    room and the drive are the same whatever the camera. Four uniform numbers ``u`` in [0, 1) are drawn in the order
    height, pitch, roll, field of view (whether or not a field is None), and each value is ``low + (high - low) u``.
    The field of view is then rounded to whole pixels of the render (below; steps of 2 pixels, kept inside the range
    where a step allows); that rounded value is the one used and recorded. With ``CameraConfig.aim`` each frame's
    heading is then drawn too, from a stream of its own (:func:`aim_poses`).

Rendering and framing
    The grid stays the model's grid, aligned with the camera (the grid's pose is the camera's pose). The camera
    renders at its own field of view with the focal length of the network's image, ``f = S / (2 tan(hfov_grid /
    2))`` pixels (:meth:`SimConfig.image_camera <.config.SimConfig.image_camera>`): ``w = 2 f tan(hfov / 2)`` pixels
    across, rounded to the parity of ``S``, ``h`` likewise from ``w H / W`` to the parity of ``S H / W``, principal
    point in the middle (:func:`render_camera`). :func:`fruxel.train.framing.frame_image` frames the render onto the
    grid's view at the network's image size with the field of view ``2 atan(w / (2 f))``, exactly as the commands
    frame a photo given ``--hfov``: a wider camera's render is cropped about its centre, a narrower one's padded
    with grey. The render has the network image's pixel density, so the framing moves whole pixels and resamples
    nothing: no detail is lost or made up. A field of view that rounds to ``S`` pixels renders the network image
    itself (the robot's case), with no framing.

Coverage and labels
    :func:`fruxel.train.framing.frame_coverage` gives the grid columns the image covers (all of them for a camera as
    wide as the grid's or wider). The labels of the columns it does not cover stay the full truth of the grid
    (``fruxelize`` of the room, as everywhere): the room is there whether the camera saw it or not, and labels
    emptied to fit the image would teach that grey padding means empty space, which no photo's padding does. What
    to do with those columns (leave them out of a loss or a metric, or learn to complete them) is the training's
    choice, which the recorded coverage makes possible; prediction leaves them empty
    (:func:`fruxel.train.predict.empty_uncovered`).

Record
    :class:`CameraRecord`, per sample: the rendered camera's intrinsics and image size, its height above the floor,
    the gravity direction in the camera frame, and the mount's pitch, roll and field of view. The sample's pose
    (camera-to-world, which is also the grid's) and coverage complete it in the ``camera`` of a batch
    (:data:`CAMERA_KEYS`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar

import numpy as np

from fruxel.camera import Camera
from fruxel.errors import ConfigError

from .robot import CameraMount

if TYPE_CHECKING:
    from .config import SimConfig

FLOOR_Z = 0.0
"""World z of the floor's top (every simulated room's floor: :mod:`.scene`), metres: heights are measured from it."""
MAX_RENDER_SIDE = 8192
"""Largest side of a camera's render, pixels (the largest image size a config allows)."""

_LIMITS = {"height": (0.0, 10.0), "pitch": (-90.0, 90.0), "roll": (-90.0, 90.0), "hfov": (0.0, 180.0)}
"""Per field of :class:`CameraConfig`: the open bounds of its ranges (the height's upper one, 10 m, included)."""


@dataclass(frozen=True)
class CameraConfig:
    """The camera each trajectory draws (module docstring): ranges ``(low, high)`` drawn uniformly once per
    trajectory; ``low == high`` is a fixed value; None is the robot's own.

    Raises:
        ConfigError: on construction, a range that is not a pair of finite numbers with ``low <= high`` inside its
            field's bounds (the message names the field).
    """

    height: tuple[float, float] | None = None
    """Height of the optical centre above the floor, metres, in (0, 10]; None: the robot mount's height
    (``TrajectoryConfig.mount.height``)."""
    pitch: tuple[float, float] | None = None
    """Pitch, degrees, positive looking down, in (-90, 90); None: the robot mount's tilt."""
    roll: tuple[float, float] | None = None
    """Roll about the optical axis, degrees, positive clockwise as seen from behind the camera (its right side
    down), in (-90, 90); None: 0, a level camera."""
    hfov: tuple[float, float] | None = None
    """Horizontal field of view, degrees, in (0, 180), rounded to whole pixels of the render; None: the grid's. The
    render's size grows with it (``SimConfig`` refuses a render side over :data:`MAX_RENDER_SIDE`)."""
    aim: float | None = None
    """Where each frame looks, in the horizontal plane: None, along the robot's heading (its own mount); a number
    in [0, 180] degrees, from the robot's position towards the middle of the room, turned by a uniform angle within
    +- ``aim`` / 2 (:func:`aim_poses`): a person points a camera at the room, where a robot's camera driving along
    a wall sees the wall from close by."""

    RECORDED_BEFORE: ClassVar[dict[str, Any]] = {"aim": None}
    """Fields added after data sets were recorded, with what those data sets were made with (``aim``: the heading)."""

    def __post_init__(self) -> None:
        if self.aim is not None and (isinstance(self.aim, bool) or not isinstance(self.aim, (int, float)) or
                                     not 0.0 <= float(self.aim) <= 180.0):
            raise ConfigError(f"camera.aim must be None or a number of degrees in [0, 180], got {self.aim!r}")
        for name, (lo_bound, hi_bound) in _LIMITS.items():
            value = getattr(self, name)
            if value is None:
                continue
            try:
                lo, hi = (float(v) for v in value)
            except (TypeError, ValueError):
                raise ConfigError(f"camera.{name} must be a (low, high) pair of numbers or None, got {value!r}"
                                  ) from None
            top_ok = hi <= hi_bound if name == "height" else hi < hi_bound
            if not (math.isfinite(lo) and math.isfinite(hi) and lo_bound < lo <= hi and top_ok):
                bounds = "(0, 10] m" if name == "height" else f"({lo_bound:g}, {hi_bound:g}) degrees"
                raise ConfigError(f"camera.{name} must be a range low <= high inside {bounds}, got {value!r}")
            object.__setattr__(self, name, (lo, hi))


ROBOT_CAMERA = CameraConfig()
"""The robot's fixed mount (``TrajectoryConfig.mount``, level, the grid's field of view): today's samples."""
ANY_CAMERA = CameraConfig(height=(0.3, 1.9), pitch=(-20.0, 40.0), roll=(-10.0, 10.0), hfov=(50.0, 80.0),
                          aim=120.0)
"""Any camera (issue 38): 0.3 to 1.9 m above the floor, pitch -20 to +40 degrees, roll within +-10, 50 to 80
degrees across, looking towards the room's middle within +-60 degrees."""
CAMERAS: dict[str, CameraConfig] = {"robot": ROBOT_CAMERA, "any": ANY_CAMERA}
"""The named camera configs (``fruxel-sim --camera NAME``)."""


def camera_named(name: str) -> CameraConfig:
    """The camera config called ``name`` in :data:`CAMERAS`.

    Raises:
        ConfigError: no such name (the message lists them).
    """
    if name not in CAMERAS:
        raise ConfigError(f"unknown camera {name!r}; cameras are {list(CAMERAS)}")
    return CAMERAS[name]


@dataclass(frozen=True)
class Mount:
    """One trajectory's camera, as drawn (degrees, metres)."""

    height: float
    """Height of the optical centre above the floor, metres."""
    pitch: float
    """Pitch, degrees, positive looking down."""
    roll: float
    """Roll, degrees, positive clockwise as seen from behind the camera."""
    hfov: float
    """Horizontal field of view of the render, degrees, rounded to its whole pixels (:func:`render_camera`)."""

    def robot_mount(self, offset: tuple[float, float]) -> CameraMount:
        """The robot's :class:`~.robot.CameraMount` with this height, pitch and field of view, at ``offset``
        (``(forward, left)`` metres in the robot frame); the roll is :func:`roll_poses`'s."""
        return CameraMount(height=self.height, tilt=self.pitch, offset=offset, hfov=self.hfov)


# ---------------------------------------------------------------------------------------------------- render
def _render_focal(config: SimConfig) -> float:
    """Focal length of every render, pixels: the network image's (``SimConfig.image_camera().fx``)."""
    return config.image_width / (2.0 * config.grid.tu)


def render_size(config: SimConfig, hfov: float) -> tuple[int, int]:
    """``(width, height)`` in pixels of the render of a camera ``hfov`` degrees across (module docstring): the
    network image's focal length, each side rounded to the parity of the network image's, so that framing moves
    whole pixels."""
    f = _render_focal(config)
    s, s_h = config.image_width, config.image_height
    w = s + 2 * round((2.0 * f * math.tan(math.radians(hfov) / 2.0) - s) / 2.0)
    h = s_h + 2 * round((w * config.grid.height / config.grid.width - s_h) / 2.0)
    return w, h


def _width_hfov(config: SimConfig, w: int) -> float:
    """The field of view of a render ``w`` pixels wide, degrees: exactly the grid's at the network image's width."""
    if w == config.image_width:
        return float(config.grid.hfov)
    return math.degrees(2.0 * math.atan(w / (2.0 * _render_focal(config))))


def render_hfov(config: SimConfig, hfov: float, bounds: tuple[float, float] | None = None) -> float:
    """The field of view a camera ``hfov`` degrees across renders with: ``2 atan(w / (2 f))`` of its whole-pixel
    width (:func:`render_size`), or exactly the grid's when that width is the network image's.

    Args:
        config: the simulator config.
        hfov: degrees.
        bounds: ``(low, high)`` degrees the result should keep to: a width whose field of view rounds outside them
            moves one step (2 pixels) inwards when the step lands inside (small images have coarse steps).
    """
    w, _ = render_size(config, hfov)
    if bounds is not None:
        lo, hi = bounds
        if _width_hfov(config, w) < lo and _width_hfov(config, w + 2) <= hi:
            w += 2
        elif _width_hfov(config, w) > hi and w > 2 and _width_hfov(config, w - 2) >= lo:
            w -= 2
    return _width_hfov(config, w)


def render_camera(config: SimConfig, hfov: float, pose: Any = None) -> Camera:
    """The camera a field of view of ``hfov`` degrees renders with (module docstring): ``fx = fy`` the network
    image's, principal point in the middle of :func:`render_size`; :meth:`SimConfig.image_camera` itself when the
    size is the network image's.

    Args:
        config: the simulator config (grid and image size).
        hfov: degrees, in (0, 180).
        pose: ``(4, 4)`` camera-to-world transform (OpenCV axes), identity when None.
    """
    w, h = render_size(config, hfov)
    if (w, h) == (config.image_width, config.image_height):
        return config.image_camera(pose)
    f = _render_focal(config)
    return Camera(fx=f, fy=f, cx=w / 2.0, cy=h / 2.0, width=w, height=h, pose=np.eye(4) if pose is None else pose)


def is_framed(config: SimConfig, hfov: float) -> bool:
    """Whether a camera of ``hfov`` degrees renders something other than the network image (which then needs
    framing, and a renderer that draws other cameras)."""
    return render_size(config, hfov) != (config.image_width, config.image_height)


def only_grid_view(config: SimConfig) -> bool:
    """Whether every camera ``config`` draws renders the network image itself (no framing)."""
    r = config.camera.hfov
    return r is None or not (is_framed(config, r[0]) or is_framed(config, r[1]))


def check_camera(config: SimConfig) -> None:
    """Check that the cameras of ``config`` can be rendered: every field of view of its range gives a render of 1
    to :data:`MAX_RENDER_SIDE` pixels a side.

    Raises:
        ConfigError: naming ``camera.hfov`` and the size it would need.
    """
    if config.camera.hfov is None:
        return
    for hfov in config.camera.hfov:
        w, h = render_size(config, hfov)
        if not (1 <= min(w, h) and max(w, h) <= MAX_RENDER_SIDE):
            raise ConfigError(f"camera.hfov {hfov:g} degrees would render {w}x{h} pixels at this image size "
                              f"({config.image_width}); a side must be 1 to {MAX_RENDER_SIDE}")


def frame_render(config: SimConfig, render: np.ndarray, hfov: float) -> np.ndarray:
    """A camera's render framed onto the grid's view at the network image's size (module docstring).

    Args:
        config: the simulator config.
        render: ``(h, w, 3)`` uint8 RGB of :func:`render_camera` for ``hfov``.
        hfov: the render's field of view, degrees (:func:`render_hfov`).

    Returns:
        ``(S * H / W, S, 3)`` uint8 RGB.
    """
    from fruxel.train.framing import frame_image

    return frame_image(render, config.grid, (config.image_height, config.image_width), hfov=hfov)


def coverage(config: SimConfig, hfov: float) -> np.ndarray:
    """``(H, W)`` bool, grid frame: the grid columns a camera of ``hfov`` degrees covers once framed
    (:func:`fruxel.train.framing.frame_coverage` of its render); all True when it is not framed."""
    from fruxel.train.framing import frame_coverage

    if not is_framed(config, hfov):
        return np.ones((config.grid.height, config.grid.width), dtype=bool)
    w, h = render_size(config, hfov)
    return frame_coverage((h, w), config.grid, hfov=hfov)


# ---------------------------------------------------------------------------------------------------- mounts
def draw_mount(config: SimConfig, seed: int) -> Mount:
    """The camera of one trajectory, drawn from ``config.camera`` with ``default_rng(seed)`` (module docstring)."""
    cam, robot = config.camera, config.trajectory.mount
    u = np.random.default_rng(seed).random(4)

    def pick(r: tuple[float, float] | None, fallback: float, k: int) -> float:
        # lo + (hi - lo) u is exactly lo for a degenerate range.
        return float(fallback) if r is None else float(r[0] + (r[1] - r[0]) * u[k])

    hfov = render_hfov(config, pick(cam.hfov, config.grid.hfov, 3), cam.hfov)
    return Mount(height=pick(cam.height, robot.height, 0), pitch=pick(cam.pitch, robot.tilt, 1),
                 roll=pick(cam.roll, 0.0, 2), hfov=hfov)


def roll_poses(poses: np.ndarray, roll: float) -> np.ndarray:
    """Camera-to-world poses turned by ``roll`` degrees about their optical axis (module docstring).

    Args:
        poses: ``(..., 4, 4)`` float64 camera-to-world, OpenCV axes.
        roll: degrees, positive clockwise as seen from behind the camera.

    Returns:
        ``(..., 4, 4)`` float64; ``poses`` itself when ``roll`` is 0.
    """
    if roll == 0.0:
        return poses
    c, s = math.cos(math.radians(roll)), math.sin(math.radians(roll))
    out = np.array(poses, dtype=np.float64)
    out[..., :3, :3] = out[..., :3, :3] @ np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
    return out


def aim_poses(poses: np.ndarray, centre: Any, mount: Mount, aim: float, seed: Any) -> np.ndarray:
    """The frames of a trajectory turned to look towards the room (:attr:`CameraConfig.aim`), before the roll.

    Each frame keeps its camera's position, height and pitch; its heading becomes the direction from the camera
    to ``centre`` plus ``(u - 0.5) aim`` degrees, ``u`` the frame's uniform number from the camera seed's child
    stream with spawn key 1 (one per frame, in order: apart from the mount's four draws, module docstring).

    Args:
        poses: ``(N, 4, 4)`` float64 camera-to-world, OpenCV axes, world frame z up, of the level-rolled robot camera.
        centre: ``(2,)`` world xy the cameras look towards, metres (the room's middle).
        mount: the trajectory's camera (its height and pitch).
        aim: the spread, degrees.
        seed: the trajectory's camera seed (:func:`.config.camera_seed`: a ``SeedSequence``, or an int).

    Returns:
        ``(N, 4, 4)`` float64 camera-to-world poses.
    """
    from .robot import CameraMount, camera_poses

    pos = np.asarray(poses, dtype=np.float64)[:, :2, 3]
    parent = seed if isinstance(seed, np.random.SeedSequence) else np.random.SeedSequence(int(seed))
    u = np.random.default_rng(np.random.SeedSequence(parent.entropy, spawn_key=(*parent.spawn_key, 1))
                              ).random(len(pos))
    to_centre = np.asarray(centre, dtype=np.float64).reshape(1, 2) - pos
    theta = np.arctan2(to_centre[:, 1], to_centre[:, 0]) + np.radians((u - 0.5) * float(aim))
    return camera_poses(pos, theta, CameraMount(height=mount.height, tilt=mount.pitch, offset=(0.0, 0.0),
                                                hfov=mount.hfov))


def gravity_in_camera(pose: Any) -> np.ndarray:
    """``(3,)`` float64 unit vector: the direction of gravity (world ``-z``) in the camera frame of a
    camera-to-world ``pose`` (OpenCV axes)."""
    g = -np.asarray(pose, dtype=np.float64)[2, :3]
    return g / np.linalg.norm(g)


def pose_angles(pose: Any) -> tuple[float, float, float]:
    """``(height above the floor in metres, pitch, roll in degrees)`` of a camera-to-world ``pose``, computed back
    from it and the floor plane (module docstring); what a sample's record says, up to rounding."""
    g = gravity_in_camera(pose)
    height = float(np.asarray(pose, dtype=np.float64)[2, 3] - FLOOR_Z)
    return height, math.degrees(math.asin(max(-1.0, min(1.0, g[2])))), math.degrees(math.atan2(g[0], g[1]))


# ---------------------------------------------------------------------------------------------------- records
CAMERA_KEYS = ("intrinsics", "image_size", "pose", "height", "gravity", "pitch", "roll", "hfov", "coverage")
"""The ``camera`` of a batch, per sample (batch shapes lead with ``B``):

* ``intrinsics`` ``(4,)`` float64: ``fx, fy, cx, cy`` of the rendered camera, pixels of its render;
* ``image_size`` ``(2,)`` int64: the render's ``width, height``, pixels;
* ``pose`` ``(4, 4)`` float64: camera-to-world, OpenCV axes, world frame z up, metres (the grid's pose too);
* ``height`` ``()`` float64: the optical centre's height above the floor, metres;
* ``gravity`` ``(3,)`` float64: unit direction of gravity in the camera frame (OpenCV axes);
* ``pitch``, ``roll``, ``hfov`` ``()`` float64: the mount's, degrees (module docstring);
* ``coverage`` ``(H, W)`` bool, grid frame: the grid columns the framed image covers.
"""


@dataclass(frozen=True)
class CameraRecord:
    """What a sample records about its camera (module docstring; :data:`CAMERA_KEYS` less the pose and coverage,
    which the sample holds as arrays)."""

    intrinsics: tuple[float, float, float, float]
    """``(fx, fy, cx, cy)`` of the rendered camera, pixels of its render."""
    image_size: tuple[int, int]
    """``(width, height)`` of the render, pixels."""
    height: float
    """Height of the optical centre above the floor, metres."""
    gravity: tuple[float, float, float]
    """Unit direction of gravity in the camera frame (OpenCV axes)."""
    pitch: float
    """Degrees, positive looking down."""
    roll: float
    """Degrees, positive clockwise as seen from behind the camera."""
    hfov: float
    """Horizontal field of view of the render, degrees."""

    def to_dict(self) -> dict[str, Any]:
        """Plain JSON (floats round-trip exactly)."""
        return {"intrinsics": list(self.intrinsics), "image_size": list(self.image_size), "height": self.height,
                "gravity": list(self.gravity), "pitch": self.pitch, "roll": self.roll, "hfov": self.hfov}

    @classmethod
    def from_dict(cls, d: Any) -> CameraRecord:
        """Inverse of :meth:`to_dict`, checked.

        Raises:
            ValueError: missing or extra keys, wrong types, non-finite values, non-positive focal lengths or
                sizes, a gravity vector that is not a unit vector, a field of view outside (0, 180).
        """
        names = ("intrinsics", "image_size", "height", "gravity", "pitch", "roll", "hfov")
        if not isinstance(d, dict) or sorted(d) != sorted(names):
            raise ValueError(f"a camera record needs exactly the keys {list(names)}")
        intr, size, grav = (_numbers(d[k], n, k) for k, n in (("intrinsics", 4), ("image_size", 2), ("gravity", 3)))
        scalars = [_numbers([d[k]], 1, k)[0] for k in ("height", "pitch", "roll", "hfov")]
        if not all(isinstance(v, int) and not isinstance(v, bool) and v > 0 for v in d["image_size"]):
            raise ValueError(f"camera image_size must be two positive integers, got {d['image_size']!r}")
        if min(intr[:2]) <= 0 or not 0 < scalars[3] < 180 or abs(math.hypot(*grav) - 1.0) > 1e-9:
            raise ValueError("camera record has a non-positive focal length, a field of view outside (0, 180) or a "
                             "gravity direction that is not a unit vector")
        return cls(tuple(intr), (int(size[0]), int(size[1])), scalars[0], tuple(grav), *scalars[1:])

    def arrays(self) -> dict[str, np.ndarray]:
        """The record as arrays keyed as in :data:`CAMERA_KEYS` (dtypes and shapes there)."""
        return {"intrinsics": np.array(self.intrinsics, dtype=np.float64),
                "image_size": np.array(self.image_size, dtype=np.int64),
                "height": np.float64(self.height), "gravity": np.array(self.gravity, dtype=np.float64),
                "pitch": np.float64(self.pitch), "roll": np.float64(self.roll), "hfov": np.float64(self.hfov)}


def _numbers(value: Any, n: int, name: str) -> list[float]:
    if not isinstance(value, list) or len(value) != n or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        raise ValueError(f"camera {name} must be {n} finite numbers, got {value!r}")
    return [float(v) for v in value]


def camera_record(config: SimConfig, mount: Mount, pose: Any) -> CameraRecord:
    """The record of a sample taken by ``mount``'s camera at camera-to-world ``pose`` (module docstring)."""
    cam = render_camera(config, mount.hfov)
    g = gravity_in_camera(pose)
    return CameraRecord((cam.fx, cam.fy, cam.cx, cam.cy), (cam.width, cam.height), float(mount.height),
                        (float(g[0]), float(g[1]), float(g[2])), float(mount.pitch), float(mount.roll),
                        float(mount.hfov))


def robot_mount(config: SimConfig) -> Mount:
    """The robot's own mount (:data:`ROBOT_CAMERA`'s camera) for ``config``: what data sets made before cameras
    varied were taken with."""
    m = config.trajectory.mount
    return Mount(height=float(m.height), pitch=float(m.tilt), roll=0.0, hfov=float(config.grid.hfov))

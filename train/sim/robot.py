"""The paper's mobile robot (conventions section 7): wheel commands in, one camera pose per frame out.

Dynamics
    Longitudinal motion ``X' = A X + B u`` with ``X = (x1, x2)`` (displacement along the path, speed),
    ``A = [[0, 1], [0, -a]]``, ``B = [0, b]``, ``a = b_friction / m``, ``b = 1 / m``. The input is the mean of
    the two wheel commands after clipping each to ``[-u_max, u_max]``. Commands are held constant over each
    step (zero-order hold), and the step is integrated exactly with the closed-form discretisation

        e = exp(-a dt)
        x2' = e x2 + (b u / a)(1 - e)
        x1' = x1 + x2 (1 - e) / a + (b u / a)(dt - (1 - e) / a)

    (the limit ``a -> 0`` is used when there is no friction), so a constant input reproduces
    ``x2(t) = (b u / a)(1 - exp(-a t))`` to rounding. Heading: ``theta(t + dt) = theta(t) + (u_r - u_l) / 50 *
    2 pi * dt`` (clipped commands; ``heading_gain = 2 pi / 50`` by default). Position on the floor: each step
    moves by its displacement ``x1' - x1`` along the heading held during the step, ``theta(t)``.

Frames
    World: right-handed, metres, z up (see :mod:`.scene`). The heading ``theta`` is measured from the world +x
    axis towards +y. The robot's frame has x forward, y left, z up, origin on the floor at its centre.
    Camera poses are camera-to-world 4x4 matrices with OpenCV axes (x right, y down, z forward): usable as
    ``fruxel.Camera(..., pose=T)`` and as the grid pose of ``fruxelize``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from fruxel.errors import FruxelError

if TYPE_CHECKING:
    from .scene import FreeSpace, Scene


class TrajectoryError(FruxelError, RuntimeError):
    """Raised when no collision-free trajectory can be made (no free start, a scripted path that collides)."""


@dataclass(frozen=True)
class RobotParams:
    """Physical parameters of the robot and the simulation step."""

    mass: float = 20.0
    """m, kg."""
    b_friction: float = 50.0
    """Viscous friction coefficient, N s / m: the steady speed for input u is ``u / b_friction``."""
    dt: float = 0.1
    """Simulation step, seconds (one frame per step unless a trajectory asks for more steps per frame)."""
    u_max: float = 100.0
    """Wheel command limit: each command is clipped to ``[-u_max, u_max]``."""
    heading_gain: float = 2.0 * math.pi / 50.0
    """Heading rate per unit of ``u_r - u_l``, rad/s (conventions section 7: ``2 pi / 50``)."""

    def __post_init__(self) -> None:
        if not (self.mass > 0 and self.b_friction >= 0 and self.dt > 0 and self.u_max > 0):
            raise ValueError("RobotParams needs mass > 0, b_friction >= 0, dt > 0 and u_max > 0")

    @property
    def a(self) -> float:
        """``b_friction / m``, 1/s."""
        return self.b_friction / self.mass

    @property
    def b(self) -> float:
        """``1 / m``, 1/kg."""
        return 1.0 / self.mass

    def discretisation(self) -> tuple[np.ndarray, np.ndarray]:
        """Exact zero-order-hold discretisation of one step: ``X' = Ad X + Bd u``.

        Returns:
            Ad ``(2, 2)`` and Bd ``(2,)`` float64.
        """
        a, b, dt = self.a, self.b, self.dt
        if a * dt < 1e-12:
            return np.array([[1.0, dt], [0.0, 1.0]]), np.array([b * dt * dt / 2.0, b * dt])
        g = -math.expm1(-a * dt) / a  # (1 - e^{-a dt}) / a, accurate for small a dt
        return np.array([[1.0, g], [0.0, 1.0 - a * g]]), np.array([b * (dt - g) / a, b * g])


@dataclass(frozen=True)
class CameraMount:
    """Where the camera rides on the robot."""

    height: float = 1.0
    """Height of the optical centre above the floor, metres."""
    tilt: float = 10.0
    """Pitch in degrees, positive looking down."""
    offset: tuple[float, float] = (0.1, 0.0)
    """Position of the optical centre in the robot frame, ``(forward, left)`` metres."""
    hfov: float = 60.0
    """Horizontal field of view of the camera, degrees (for building the ``fruxel.Camera`` / grid)."""


@dataclass(frozen=True, eq=False)
class RobotStates:
    """The robot at each of N = T + 1 instants (the initial state and after each of T steps)."""

    t: np.ndarray
    """``(N,)`` float64 time, seconds."""
    x1: np.ndarray
    """``(N,)`` float64 displacement along the path, metres (signed: reversing decreases it)."""
    x2: np.ndarray
    """``(N,)`` float64 longitudinal speed, m/s."""
    theta: np.ndarray
    """``(N,)`` float64 heading, radians from world +x towards +y (not wrapped)."""
    position: np.ndarray
    """``(N, 2)`` float64 world xy of the robot's centre, metres."""
    commands: np.ndarray
    """``(T, 2)`` float64 clipped wheel commands ``(u_r, u_l)`` applied from state n to n + 1."""

    def __len__(self) -> int:
        return int(self.t.shape[0])


@dataclass(frozen=True, eq=False)
class Trajectory:
    """Camera poses of the frames of one robot run, with the states they came from."""

    poses: np.ndarray
    """``(N, 4, 4)`` float64 camera-to-world transforms, OpenCV axes, one per frame."""
    states: RobotStates
    """The robot at every simulation step."""
    frame_steps: np.ndarray
    """``(N,)`` int64: frame n shows ``states`` index ``frame_steps[n]``."""
    mount: CameraMount
    """The camera mount used."""
    params: RobotParams
    """The robot parameters used."""


def clip_commands(commands: Any, params: RobotParams) -> np.ndarray:
    """Wheel commands ``(T, 2)`` ``(u_r, u_l)`` clipped to ``[-u_max, u_max]``, float64.

    Raises:
        ValueError: wrong shape or non-finite values.
    """
    c = np.asarray(commands, dtype=np.float64)
    if c.ndim != 2 or c.shape[1] != 2:
        raise ValueError(f"commands must have shape (T, 2) as (u_r, u_l), got {c.shape}")
    if not np.all(np.isfinite(c)):
        raise ValueError("commands contain NaN or infinite values")
    return np.clip(c, -params.u_max, params.u_max)


def simulate(
    commands: Any,
    params: RobotParams | None = None,
    x0: float = 0.0,
    v0: float = 0.0,
    theta0: float = 0.0,
    pos0: Any = (0.0, 0.0),
) -> RobotStates:
    """Run the robot model over a sequence of wheel commands (see the module docstring).

    Args:
        commands: ``(T, 2)`` wheel commands ``(u_r, u_l)``, held for ``dt`` each; clipped to the limit.
        params: robot parameters (defaults when None).
        x0: initial displacement, metres.
        v0: initial speed, m/s.
        theta0: initial heading, radians.
        pos0: initial world xy, metres.

    Returns:
        The T + 1 states.
    """
    p = params if params is not None else RobotParams()
    c = clip_commands(commands, p)
    n = len(c)
    ad, bd = p.discretisation()
    u = c.mean(axis=1)
    x = np.empty((n + 1, 2))
    x[0] = (x0, v0)
    for k in range(n):
        x[k + 1] = ad @ x[k] + bd * u[k]
    theta = theta0 + np.concatenate([[0.0], np.cumsum((c[:, 0] - c[:, 1]) * p.heading_gain * p.dt)])
    step = np.diff(x[:, 0])
    pos = np.empty((n + 1, 2))
    pos[0] = np.asarray(pos0, dtype=np.float64).reshape(2)
    pos[1:] = pos[0] + np.cumsum(step[:, None] * np.stack([np.cos(theta[:-1]), np.sin(theta[:-1])], axis=1), axis=0)
    return RobotStates(np.arange(n + 1) * p.dt, x[:, 0].copy(), x[:, 1].copy(), theta, pos, c)


def camera_poses(position: Any, theta: Any, mount: CameraMount) -> np.ndarray:
    """Camera-to-world poses of a camera on the robot.

    Args:
        position: ``(N, 2)`` robot world xy, metres.
        theta: ``(N,)`` headings, radians.
        mount: the camera mount.

    Returns:
        ``(N, 4, 4)`` float64 camera-to-world, OpenCV axes: z along the heading pitched down by ``tilt``, x to
        the robot's right, y down in the image.
    """
    pos = np.asarray(position, dtype=np.float64).reshape(-1, 2)
    th = np.asarray(theta, dtype=np.float64).reshape(-1)
    ct, st = np.cos(th), np.sin(th)
    tilt = math.radians(mount.tilt)
    fwd = np.stack([ct * math.cos(tilt), st * math.cos(tilt), np.full_like(ct, -math.sin(tilt))], axis=1)
    right = np.stack([st, -ct, np.zeros_like(ct)], axis=1)
    down = np.cross(fwd, right)
    out = np.zeros((len(pos), 4, 4))
    out[:, :3, 0], out[:, :3, 1], out[:, :3, 2] = right, down, fwd
    f, left = mount.offset
    out[:, 0, 3] = pos[:, 0] + f * ct - left * st
    out[:, 1, 3] = pos[:, 1] + f * st + left * ct
    out[:, 2, 3] = mount.height
    out[:, 3, 3] = 1.0
    return out


def constant_commands(u_r: float, u_l: float, n: int) -> np.ndarray:
    """``(n, 2)`` float64 commands holding ``(u_r, u_l)``."""
    return np.tile(np.array([[u_r, u_l]], dtype=np.float64), (int(n), 1))


def segment_commands(segments: Any, dt: float) -> np.ndarray:
    """Scripted commands from segments ``[(u_r, u_l, seconds), ...]``: ``(T, 2)`` float64, each segment held for
    ``round(seconds / dt)`` steps."""
    rows = [constant_commands(ur, ul, round(s / dt)) for ur, ul, s in segments]
    return np.concatenate(rows) if rows else np.zeros((0, 2))


def _frames(states: RobotStates, mount: CameraMount, params: RobotParams, steps_per_frame: int) -> Trajectory:
    idx = np.arange(0, len(states), steps_per_frame, dtype=np.int64)
    poses = camera_poses(states.position[idx], states.theta[idx], mount)
    return Trajectory(poses, states, idx, mount, params)


def _path_points(p: np.ndarray, heading: float, length: float, spacing: float) -> np.ndarray:
    """Points every ``spacing`` metres (ends included) on the segment from ``p`` of signed ``length``."""
    n = int(math.ceil(abs(length) / spacing)) + 1
    s = np.linspace(0.0, length, n)
    return p + s[:, None] * np.array([math.cos(heading), math.sin(heading)])


def trajectory_from_commands(
    commands: Any,
    params: RobotParams | None = None,
    mount: CameraMount | None = None,
    *,
    x0: float = 0.0,
    v0: float = 0.0,
    theta0: float = 0.0,
    pos0: Any = (0.0, 0.0),
    steps_per_frame: int = 1,
    scene: Scene | None = None,
    radius: float = 0.25,
) -> Trajectory:
    """Camera poses for scripted wheel commands.

    Args:
        commands: ``(T, 2)`` ``(u_r, u_l)``.
        params, mount: robot and mount (defaults when None).
        x0, v0, theta0, pos0: the initial state (see :func:`simulate`).
        steps_per_frame: a frame every this many steps (frame 0 is the initial state).
        scene: when given, every step's path is checked against ``scene.free_space`` for a disk of ``radius``.
        radius: the robot's footprint radius, metres.

    Raises:
        TrajectoryError: the path leaves the free space (the message gives the step).
    """
    p = params if params is not None else RobotParams()
    m = mount if mount is not None else CameraMount()
    states = simulate(commands, p, x0, v0, theta0, pos0)
    if scene is not None:
        fs = scene.free_space
        for k in range(len(states) - 1):
            pts = _path_points(states.position[k], states.theta[k], states.x1[k + 1] - states.x1[k],
                               fs.resolution / 2)
            if fs.collides(pts, radius).any():
                raise TrajectoryError(f"scripted path collides at step {k} (t = {states.t[k]:.2f} s)")
    return _frames(states, m, p, steps_per_frame)


def random_trajectory(
    scene: Scene,
    n_frames: int,
    seed: int,
    params: RobotParams | None = None,
    mount: CameraMount | None = None,
    *,
    radius: float = 0.25,
    margin: float = 0.05,
    steps_per_frame: int = 1,
    speed_range: tuple[float, float] = (0.2, 0.6),
    max_turn_rate: float = 0.6,
    segment_seconds: tuple[float, float] = (0.8, 3.0),
    max_retries: int = 20,
    start: tuple[float, float, float] | None = None,
) -> Trajectory:
    """A collision-free random drive through ``scene``.

    The robot starts at rest on a random free cell (or at ``start = (x, y, theta)``) and drives segments of
    random wheel commands: forward at a speed drawn from ``speed_range`` while turning at most
    ``max_turn_rate``. Before each step the planner checks that the step *and the stop that would follow it*
    (both wheels at 0: a straight glide of ``x2 / a``) keep a disk of ``radius + margin`` in free space. When a
    command fails, it tries up to ``max_retries`` others (turns in place first, then new random segments), and
    otherwise stops. Stopping is always safe, because the glide it follows was checked one step earlier, so
    the drive never collides.

    Args:
        scene: the room; its ``free_space`` is the obstacle map.
        n_frames: number of frames (camera poses) wanted, >= 1.
        seed: seeds ``numpy.random.default_rng``; the same inputs give the same trajectory.
        params, mount: robot and camera mount (defaults when None).
        radius: footprint radius, metres. margin: extra clearance kept by the planner, metres.
        steps_per_frame: simulation steps between frames.
        speed_range: cruising speeds drawn, m/s.
        max_turn_rate: largest turn rate while driving, rad/s.
        segment_seconds: duration range of one command segment, seconds.
        max_retries: alternative commands tried when the current one would collide.
        start: fixed start pose ``(x, y, theta)``; None draws one.

    Returns:
        The :class:`Trajectory`: ``n_frames`` poses; ``states`` has ``(n_frames - 1) * steps_per_frame + 1``
        entries.

    Raises:
        TrajectoryError: no free start cell for the footprint, or a given start that collides.
    """
    p = params if params is not None else RobotParams()
    m = mount if mount is not None else CameraMount()
    if n_frames < 1 or steps_per_frame < 1:
        raise ValueError("n_frames and steps_per_frame must be >= 1")
    rng = np.random.default_rng(seed)
    pos, theta = _start_pose(scene, rng, radius, margin, start)
    driver = _RandomDriver(p, scene.free_space, radius + margin, rng, speed_range, max_turn_rate, segment_seconds,
                           pos.copy(), theta)
    commands = driver.commands((n_frames - 1) * steps_per_frame, max_retries)
    # The states come from simulate() itself, so that a trajectory is exactly the model's response to its
    # commands; the planner's own stepping differs from it only by rounding, far inside the margin.
    states = simulate(commands, p, 0.0, 0.0, theta, pos)
    return _frames(states, m, p, steps_per_frame)


def _start_pose(scene: Scene, rng: np.random.Generator, radius: float, margin: float,
                start: tuple[float, float, float] | None) -> tuple[np.ndarray, float]:
    """The drive's start: ``start``, checked, or a random free cell centre and heading drawn from ``rng``.

    Returns:
        ``(position (2,) float64 world xy, heading radians)``.

    Raises:
        TrajectoryError: no free cell for a disk of ``radius + margin``, or a ``start`` that collides.
    """
    fs = scene.free_space
    clear = radius + margin
    if start is not None:
        pos = np.array(start[:2], dtype=np.float64)
        if fs.collides(pos, clear):
            raise TrajectoryError(f"start {tuple(start)} collides in scene {scene.seed}")
        return pos, float(start[2])
    cand = fs.cell_centres()[fs.free_centres(clear)]
    if len(cand) == 0:
        raise TrajectoryError(f"scene {scene.seed}: no free cell for a robot of radius {radius} m "
                              f"(+ {margin} m margin)")
    pos = cand[int(rng.integers(len(cand)))].copy()
    return pos, float(rng.uniform(-math.pi, math.pi))


@dataclass
class _RandomDriver:
    """The planner of :func:`random_trajectory`: the robot's state as it drives, and the random commands it tries.

    Every draw comes from :attr:`rng` in the order of :meth:`commands`, so the same seed gives the same drive.
    """

    params: RobotParams
    """Robot dynamics."""
    free: FreeSpace
    """The room's obstacle map."""
    clear: float
    """Radius of the disk kept in free space (footprint plus margin), metres."""
    rng: np.random.Generator
    """The drive's random generator."""
    speed_range: tuple[float, float]
    """Cruising speeds drawn, m/s."""
    max_turn_rate: float
    """Largest turn rate while cruising, rad/s."""
    segment_seconds: tuple[float, float]
    """Duration range of one cruising segment, seconds."""
    pos: np.ndarray
    """``(2,)`` float64 world xy of the robot now, metres."""
    theta: float
    """Heading now, radians from world +x towards +y."""
    x: np.ndarray = field(default_factory=lambda: np.zeros(2))
    """``(2,)`` float64 longitudinal state now: displacement (m) and speed (m/s)."""

    def __post_init__(self) -> None:
        self._ad, self._bd = self.params.discretisation()

    def cruise(self) -> tuple[np.ndarray, int]:
        """A random cruising segment: wheel commands ``(2,)`` and the steps to hold them."""
        p, rng = self.params, self.rng
        v = rng.uniform(*self.speed_range)
        w = rng.uniform(-self.max_turn_rate, self.max_turn_rate)
        return _wheels(v * p.b_friction, w, p), int(round(rng.uniform(*self.segment_seconds) / p.dt))

    def spin(self) -> tuple[np.ndarray, int]:
        """A random turn in place: wheel commands ``(2,)`` and the steps to hold them."""
        p, rng = self.params, self.rng
        w = rng.choice([-1.0, 1.0]) * rng.uniform(0.4, 1.0)
        return _wheels(0.0, w, p), int(round(rng.uniform(0.5, 2.0) / p.dt))

    def safe(self, cmd: np.ndarray) -> bool:
        """Whether one step of ``cmd`` and the glide to a stop after it keep the disk in free space."""
        p, x = self.params, self.x
        c = np.clip(cmd, -p.u_max, p.u_max)
        nx = self._ad @ x + self._bd * c.mean()
        th2 = self.theta + (c[0] - c[1]) * p.heading_gain * p.dt
        p2 = self.pos + (nx[0] - x[0]) * np.array([math.cos(self.theta), math.sin(self.theta)])
        glide = nx[1] / p.a if p.a > 0 else (np.inf if nx[1] != 0 else 0.0)
        if not np.isfinite(glide):
            return False
        spacing = self.free.resolution / 2
        pts = np.concatenate([_path_points(self.pos, self.theta, nx[0] - x[0], spacing),
                              _path_points(p2, th2, glide, spacing)])
        return not self.free.collides(pts, self.clear).any()

    def step(self, cmd: np.ndarray) -> np.ndarray:
        """Drive one step of ``cmd``; returns the clipped command ``(2,)``."""
        p = self.params
        c = np.clip(cmd, -p.u_max, p.u_max)
        x_next = self._ad @ self.x + self._bd * c.mean()
        self.pos = self.pos + (x_next[0] - self.x[0]) * np.array([math.cos(self.theta), math.sin(self.theta)])
        self.theta = self.theta + (c[0] - c[1]) * p.heading_gain * p.dt
        self.x = x_next
        return c

    def commands(self, n_steps: int, max_retries: int) -> np.ndarray:
        """Drive ``n_steps`` steps (see :func:`random_trajectory`); returns the ``(n_steps, 2)`` clipped wheel
        commands ``(u_r, u_l)``."""
        cmd, left = self.cruise()
        out = np.zeros((n_steps, 2))
        for k in range(n_steps):
            if left <= 0:
                cmd, left = self.cruise()
            tries = 0
            while not self.safe(cmd) and tries < max_retries:
                cmd, left = self.spin() if tries < max_retries // 2 else self.cruise()
                tries += 1
            if tries == max_retries and not self.safe(cmd):
                cmd, left = np.zeros(2), 1
            out[k] = self.step(cmd)
            left -= 1
        return out


def _wheels(u_mean: float, turn_rate: float, p: RobotParams) -> np.ndarray:
    """Wheel commands ``(u_r, u_l)`` giving the longitudinal input ``u_mean`` and the turn rate (rad/s)."""
    diff = turn_rate / p.heading_gain
    return np.array([u_mean + diff / 2.0, u_mean - diff / 2.0])

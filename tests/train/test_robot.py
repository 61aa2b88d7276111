"""The mobile robot: closed-form response, heading rule, clipping, camera mount, collision-free trajectories."""

from __future__ import annotations

import math

import numpy as np
import pytest

from fruxel.camera import Camera, check_pose
from fruxel.train.sim import (
    CameraMount,
    FreeSpace,
    RobotParams,
    TrajectoryError,
    camera_poses,
    constant_commands,
    make_scene,
    random_trajectory,
    segment_commands,
    simulate,
    trajectory_from_commands,
)


@pytest.mark.parametrize(("mass", "b_friction", "dt"), [(20.0, 50.0, 0.1), (3.0, 7.5, 0.02), (50.0, 5.0, 0.5)])
def test_constant_input_matches_the_closed_form(mass: float, b_friction: float, dt: float) -> None:
    p = RobotParams(mass=mass, b_friction=b_friction, dt=dt)
    u = 37.0
    states = simulate(constant_commands(u, u, 200), p)
    a, b, t = b_friction / mass, 1.0 / mass, states.t
    x2 = (b * u / a) * (1.0 - np.exp(-a * t))
    x1 = (b * u / a) * (t - (1.0 - np.exp(-a * t)) / a)
    np.testing.assert_allclose(states.x2, x2, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(states.x1, x1, rtol=1e-9, atol=1e-12)
    np.testing.assert_array_equal(states.theta, 0.0)
    np.testing.assert_allclose(states.position[:, 0], x1, rtol=1e-9, atol=1e-12)
    np.testing.assert_allclose(states.position[:, 1], 0.0, atol=1e-12)


def test_initial_state_and_heading_rule() -> None:
    p = RobotParams()
    u_r, u_l, n = 30.0, 20.0, 50
    theta0, pos0, v0, x0 = 0.7, (1.0, -2.0), 0.3, 0.5
    states = simulate(constant_commands(u_r, u_l, n), p, x0=x0, v0=v0, theta0=theta0, pos0=pos0)
    k = np.arange(n + 1)
    np.testing.assert_allclose(states.theta, theta0 + k * (u_r - u_l) / 50.0 * 2.0 * math.pi * p.dt, rtol=1e-12)
    a, b, u = p.a, p.b, (u_r + u_l) / 2
    t = states.t
    x2 = v0 * np.exp(-a * t) + (b * u / a) * (1.0 - np.exp(-a * t))
    x1 = x0 + v0 * (1.0 - np.exp(-a * t)) / a + (b * u / a) * (t - (1.0 - np.exp(-a * t)) / a)
    np.testing.assert_allclose(states.x2, x2, rtol=1e-9)
    np.testing.assert_allclose(states.x1, x1, rtol=1e-9)
    np.testing.assert_allclose(states.position[0], pos0)
    step = np.diff(states.position, axis=0)
    expect = np.diff(states.x1)[:, None] * np.stack([np.cos(states.theta[:-1]), np.sin(states.theta[:-1])], axis=1)
    np.testing.assert_allclose(step, expect, rtol=1e-12, atol=1e-15)


def test_no_friction_is_the_limit() -> None:
    p = RobotParams(mass=10.0, b_friction=0.0, dt=0.1)
    states = simulate(constant_commands(5.0, 5.0, 30), p)
    np.testing.assert_allclose(states.x2, 0.5 * states.t, rtol=1e-12)
    np.testing.assert_allclose(states.x1, 0.25 * states.t**2, rtol=1e-12, atol=1e-15)


def test_commands_are_clipped() -> None:
    p = RobotParams()
    wild = np.array([[150.0, -300.0], [1e6, 99.0], [-101.0, -100.5]])
    states = simulate(wild, p)
    np.testing.assert_array_equal(states.commands, [[100.0, -100.0], [100.0, 99.0], [-100.0, -100.0]])
    ref = simulate(np.clip(wild, -100, 100), p)
    np.testing.assert_array_equal(states.x1, ref.x1)
    np.testing.assert_array_equal(states.theta, ref.theta)
    with pytest.raises(ValueError):
        simulate(np.zeros((3, 3)), p)
    with pytest.raises(ValueError):
        simulate([[np.nan, 0.0]], p)


def test_camera_pose_follows_the_mount() -> None:
    mount = CameraMount(height=1.2, tilt=15.0, offset=(0.2, 0.05), hfov=70.0)
    theta = np.array([0.0, math.pi / 2, 2.0])
    pos = np.array([[1.0, 2.0], [3.0, 1.0], [0.0, 0.0]])
    poses = camera_poses(pos, theta, mount)
    for T, th, p in zip(poses, theta, pos, strict=True):
        check_pose(T)
        fwd = np.array([math.cos(th), math.sin(th)])
        left = np.array([-math.sin(th), math.cos(th)])
        np.testing.assert_allclose(T[:2, 3], p + 0.2 * fwd + 0.05 * left, atol=1e-12)
        assert T[2, 3] == pytest.approx(1.2)
        z = T[:3, 2]
        assert math.degrees(math.asin(-z[2])) == pytest.approx(15.0)
        np.testing.assert_allclose(z[:2] / np.linalg.norm(z[:2]), fwd, atol=1e-12)
        assert T[2, 1] < 0  # image y (down) points down in the world
        np.testing.assert_allclose(T[:3, 0], [math.sin(th), -math.cos(th), 0.0], atol=1e-12)
        cam = Camera.from_hfov(64, 48, mount.hfov, pose=T)
        ahead = np.r_[T[:2, 3] + 3.0 * fwd, 1.2 - 3.0 * math.tan(math.radians(15.0))]
        x, y, d = cam.project(ahead)
        assert d > 0 and x == pytest.approx(32.0) and y == pytest.approx(24.0)
        x, y, _ = cam.project(ahead + [0.0, 0.0, 0.5])
        assert y < 24.0  # higher in the world is higher in the image


def _brute_collides(fs: FreeSpace, xy: np.ndarray, radius: float) -> np.ndarray:
    """Independent check: distance from each point to every occupied cell square, and to the map's outside."""
    centres = fs.cell_centres()[fs.occupied]
    h = fs.resolution / 2
    out = np.zeros(len(xy), dtype=bool)
    ny, nx = fs.occupied.shape
    lo = fs.origin
    hi = fs.origin + fs.resolution * np.array([nx, ny])
    for n, p in enumerate(xy):
        dx = np.maximum(np.abs(p[0] - centres[:, 0]) - h, 0.0)
        dy = np.maximum(np.abs(p[1] - centres[:, 1]) - h, 0.0)
        inside_map = np.all(p - radius >= lo) and np.all(p + radius <= hi)
        out[n] = bool(np.any(dx * dx + dy * dy < radius * radius)) or not inside_map
    return out


@pytest.mark.parametrize("seed", [0, 4])
def test_random_trajectories_never_collide(seed: int) -> None:
    scene = make_scene(seed)
    radius = 0.25
    traj = random_trajectory(scene, 60, seed=seed, radius=radius, steps_per_frame=2)
    assert traj.poses.shape == (60, 4, 4)
    assert len(traj.states) == 119
    np.testing.assert_array_equal(traj.frame_steps, np.arange(0, 119, 2))
    pos = traj.states.position
    assert not _brute_collides(scene.free_space, pos, radius).any()
    # Between steps the robot moves in a straight line: check points along every step too.
    seg = np.linspace(0.0, 1.0, 5)[:, None, None]
    mids = (pos[:-1] + seg * (pos[1:] - pos[:-1])).reshape(-1, 2)
    assert not _brute_collides(scene.free_space, mids, radius).any()
    travelled = np.abs(np.diff(traj.states.x1)).sum()
    assert travelled > 1.0, "the robot should explore, not stand still"
    again = random_trajectory(scene, 60, seed=seed, radius=radius, steps_per_frame=2)
    np.testing.assert_array_equal(traj.poses, again.poses)
    ref = simulate(traj.states.commands, traj.params, theta0=traj.states.theta[0], pos0=traj.states.position[0])
    np.testing.assert_array_equal(ref.position, traj.states.position)
    np.testing.assert_array_equal(traj.poses, camera_poses(pos[traj.frame_steps], traj.states.theta[traj.frame_steps],
                                                           traj.mount))
    assert np.all(np.abs(traj.states.commands) <= 100.0)


def test_free_space_covers_the_obstacles() -> None:
    scene = make_scene(2)
    fs = scene.free_space
    for o in scene.objects:
        if o.label in (4, 6):
            v = np.asarray(o.mesh.vertices)[:, :2]
            cells = np.floor((v - fs.origin) / fs.resolution).astype(int)
            assert fs.occupied[cells[:, 1], cells[:, 0]].all(), o.name
    lx, ly, _ = scene.room_size
    assert fs.collides([lx + 0.1, ly / 2], 0.01) and fs.collides([-0.1, ly / 2], 0.01)
    np.testing.assert_array_equal(fs.collides(np.array([[lx / 2, -5.0], [lx / 2, 50.0]]), 0.1), [True, True])


def test_scripted_trajectories() -> None:
    p = RobotParams()
    cmds = segment_commands([(20.0, 20.0, 1.0), (5.0, -5.0, 0.5), (20.0, 20.0, 0.5)], p.dt)
    assert cmds.shape == (20, 2)
    scene = make_scene(1)
    traj = random_trajectory(scene, 1, seed=0)
    x, y = traj.states.position[0]
    th = traj.states.theta[0]
    ok = trajectory_from_commands(constant_commands(0.0, 0.0, 5), p, pos0=(x, y), theta0=th, scene=scene)
    assert ok.poses.shape == (6, 4, 4)
    with pytest.raises(TrajectoryError):
        trajectory_from_commands(constant_commands(100.0, 100.0, 200), p, pos0=(x, y), theta0=th, scene=scene)


def test_no_room_for_the_robot_is_a_clear_error() -> None:
    scene = make_scene(1)
    full = FreeSpace(np.ones_like(scene.free_space.occupied), scene.free_space.origin, scene.free_space.resolution)
    blocked = type(scene)(scene.objects, scene.room_size, scene.lights, full, scene.seed)
    with pytest.raises(TrajectoryError, match="no free cell"):
        random_trajectory(blocked, 5, seed=0)
    with pytest.raises(TrajectoryError):
        random_trajectory(scene, 5, seed=0, start=(-1.0, -1.0, 0.0))


def test_free_centres_is_collides_at_cell_centres() -> None:
    fs = make_scene(6).free_space
    centres = fs.cell_centres().reshape(-1, 2)
    for radius in (0.0, 0.12, 0.3):
        np.testing.assert_array_equal(fs.free_centres(radius).reshape(-1), ~fs.collides(centres, radius))

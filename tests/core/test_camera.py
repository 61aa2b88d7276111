"""Viewing cameras (conventions section 3): look_at, intrinsics, rays, projection, OpenGL pose, validation, JSON."""

from __future__ import annotations

import math

import numpy as np
import pytest
from hypothesis import assume, given, settings
from hypothesis import strategies as st

from fruxel.camera import OPENCV_TO_OPENGL, Camera, CameraError, check_pose
from fruxel.grid import FruxelGrid

FAST = settings(max_examples=60, deadline=None)

coords = st.floats(-20.0, 20.0)
vectors = st.tuples(coords, coords, coords).map(np.array)


def _rotation(axis: np.ndarray, angle: float) -> np.ndarray:
    a = axis / np.linalg.norm(axis)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(angle) * k + (1 - math.cos(angle)) * k @ k


@st.composite
def poses(draw: st.DrawFn) -> np.ndarray:
    axis = draw(vectors)
    assume(np.linalg.norm(axis) > 1e-3)
    pose = np.eye(4)
    pose[:3, :3] = _rotation(axis, draw(st.floats(-math.pi, math.pi)))
    pose[:3, 3] = draw(vectors)
    return pose


@st.composite
def cameras(draw: st.DrawFn) -> Camera:
    w, h = draw(st.integers(1, 64)), draw(st.integers(1, 64))
    return Camera(
        fx=draw(st.floats(10.0, 2000.0)),
        fy=draw(st.floats(10.0, 2000.0)),
        cx=draw(st.floats(-10.0, w + 10.0)),
        cy=draw(st.floats(-10.0, h + 10.0)),
        width=w,
        height=h,
        pose=draw(poses()),
    )


def _is_rigid(pose: np.ndarray) -> bool:
    r = pose[:3, :3]
    return (np.allclose(r.T @ r, np.eye(3), atol=1e-9) and abs(np.linalg.det(r) - 1) < 1e-9
            and np.array_equal(pose[3], [0, 0, 0, 1]))


# ---------------------------------------------------------------------------------------------------- look_at
@FAST
@given(vectors, vectors, vectors)
def test_look_at_points_the_optical_axis_at_the_target_with_up_up(eye, target, up) -> None:
    fwd = target - eye
    assume(np.linalg.norm(fwd) > 1e-3 and np.linalg.norm(up) > 1e-3)
    up_perp = up - (up @ fwd) / (fwd @ fwd) * fwd
    assume(np.linalg.norm(up_perp) > 1e-3 * np.linalg.norm(up))
    cam = Camera.look_at(eye, target, up=up, width=64, height=48, hfov=70.0)
    assert _is_rigid(cam.pose)
    np.testing.assert_allclose(cam.position, eye, atol=1e-12)
    np.testing.assert_allclose(cam.rotation[:, 2], fwd / np.linalg.norm(fwd), atol=1e-9)
    # Image up is camera -y (OpenCV): it must be the part of `up` across the viewing direction.
    np.testing.assert_allclose(-cam.rotation[:, 1], up_perp / np.linalg.norm(up_perp), atol=1e-6)
    x, y, depth = cam.project(target)
    assert (x, y) == (pytest.approx(cam.cx, abs=1e-6), pytest.approx(cam.cy, abs=1e-6))
    assert depth == pytest.approx(np.linalg.norm(fwd), rel=1e-9)
    # A point above the target along `up` appears higher (smaller row) in the image.
    assert cam.project(target + 0.1 * up_perp / np.linalg.norm(up_perp))[1] < cam.cy


def test_look_at_down_the_z_axis_is_the_identity() -> None:
    cam = Camera.look_at((0, 0, 0), (0, 0, 5), up=(0, -1, 0), width=32, height=16, hfov=90.0)
    np.testing.assert_allclose(cam.pose, np.eye(4), atol=1e-15)
    assert cam.fx == pytest.approx(16.0) and cam.fy == pytest.approx(16.0)
    assert (cam.cx, cam.cy) == (16.0, 8.0)


@pytest.mark.parametrize(
    "eye, target, up",
    [
        ((1, 2, 3), (1, 2, 3), (0, -1, 0)),
        ((0, 0, 0), (0, 5, 0), (0, -1, 0)),
        ((0, 0, 0), (0, 0, 1), (0, 0, 0)),
        ((0, 0, np.nan), (0, 0, 1), (0, -1, 0)),
        ((0, 0, 0), (np.inf, 0, 1), (0, -1, 0)),
    ],
)
def test_look_at_refuses_degenerate_input(eye, target, up) -> None:
    with pytest.raises(CameraError):
        Camera.look_at(eye, target, up=up)


# ------------------------------------------------------------------------------------------------ intrinsics and rays
@FAST
@given(st.integers(1, 200), st.integers(1, 200), st.floats(1.0, 179.0))
def test_from_hfov_spans_the_field_of_view(w: int, h: int, hfov: float) -> None:
    cam = Camera.from_hfov(w, h, hfov)
    assert cam.fx == cam.fy and (cam.cx, cam.cy) == (w / 2, h / 2)
    span = math.atan((w - cam.cx) / cam.fx) + math.atan(cam.cx / cam.fx)
    assert math.degrees(span) == pytest.approx(hfov, rel=1e-9)
    np.testing.assert_array_equal(cam.pose, np.eye(4))


@pytest.mark.parametrize("hfov", [0.0, 180.0, -10.0, 200.0])
def test_from_hfov_refuses_impossible_angles(hfov: float) -> None:
    with pytest.raises(CameraError):
        Camera.from_hfov(64, 48, hfov)


@FAST
@given(cameras(), st.data())
def test_ray_directions_follow_the_spec_in_both_frames(cam: Camera, data: st.DataObject) -> None:
    x = data.draw(st.integers(0, cam.width - 1))
    y = data.draw(st.integers(0, cam.height - 1))
    dc = cam.ray_directions_camera()
    assert dc.shape == (cam.height, cam.width, 3)
    np.testing.assert_allclose(dc[y, x], [(x + 0.5 - cam.cx) / cam.fx, (y + 0.5 - cam.cy) / cam.fy, 1.0], rtol=1e-14)
    assert np.all(dc[..., 2] == 1.0)
    origins, dirs = cam.rays()
    np.testing.assert_array_equal(origins[y, x], cam.pose[:3, 3])
    np.testing.assert_allclose(dirs[y, x], cam.pose[:3, :3] @ dc[y, x], atol=1e-12)


@FAST
@given(cameras(), st.data())
def test_project_inverts_rays(cam: Camera, data: st.DataObject) -> None:
    x = data.draw(st.integers(0, cam.width - 1))
    y = data.draw(st.integers(0, cam.height - 1))
    t = data.draw(st.floats(0.05, 100.0))
    origins, dirs = cam.rays()
    p = origins[y, x] + t * dirs[y, x]
    np.testing.assert_allclose(cam.project(p), [x + 0.5, y + 0.5, t], rtol=1e-7, atol=1e-7)
    assert cam.project(np.stack([p, p])).shape == (2, 3)


def test_point_behind_the_camera_has_negative_depth() -> None:
    cam = Camera.look_at((0, 0, 0), (1, 0, 0), up=(0, -1, 0), width=8, height=8)
    assert cam.project([-3.0, 0.0, 0.0])[2] == pytest.approx(-3.0)


def test_intrinsic_matrix_projects_like_project() -> None:
    cam = Camera(fx=300.0, fy=280.0, cx=161.0, cy=119.5, width=320, height=240)
    p = np.array([0.3, -0.2, 2.5])
    h = cam.K @ p
    np.testing.assert_allclose(cam.project(p)[:2], h[:2] / h[2])


# ---------------------------------------------------------------------------------------------------- OpenGL
@FAST
@given(cameras())
def test_opengl_pose_flips_y_and_z(cam: Camera) -> None:
    gl = cam.opengl_pose()
    np.testing.assert_array_equal(gl, cam.pose @ np.diag([1.0, -1.0, -1.0, 1.0]))
    np.testing.assert_array_equal(OPENCV_TO_OPENGL, np.diag([1.0, -1.0, -1.0, 1.0]))
    # OpenGL looks down its -z and has y up: the same optical axis and the opposite of OpenCV's y.
    np.testing.assert_array_equal(-gl[:3, 2], cam.pose[:3, 2])
    np.testing.assert_array_equal(-gl[:3, 1], cam.pose[:3, 1])
    assert _is_rigid(gl)


# ---------------------------------------------------------------------------------------------------- validation
def _scaled() -> np.ndarray:
    return np.diag([2.0, 2.0, 2.0, 1.0])


def _reflection() -> np.ndarray:
    return np.diag([1.0, 1.0, -1.0, 1.0])


def _shear() -> np.ndarray:
    p = np.eye(4)
    p[0, 1] = 0.2
    return p


def _bottom_row() -> np.ndarray:
    p = np.eye(4)
    p[3, 0] = 1.0
    return p


def _nan_pose() -> np.ndarray:
    p = np.eye(4)
    p[1, 3] = np.nan
    return p


@pytest.mark.parametrize(
    "pose", [_scaled(), _reflection(), _shear(), _bottom_row(), _nan_pose(), np.eye(3), "pose", np.eye(4)[:3]]
)
def test_non_rigid_or_malformed_poses_are_refused(pose) -> None:
    with pytest.raises(CameraError):
        Camera(fx=100.0, fy=100.0, cx=32.0, cy=24.0, width=64, height=48, pose=pose)
    with pytest.raises(CameraError):
        check_pose(pose)


@pytest.mark.parametrize(
    "change",
    [
        {"width": 0},
        {"height": 0},
        {"width": -5},
        {"width": 2.5},
        {"height": True},
        {"fx": 0.0},
        {"fy": -1.0},
        {"fx": float("nan")},
        {"cx": float("inf")},
        {"cy": "centre"},
        {"width": 2**15, "height": 2**14},
    ],
)
def test_impossible_intrinsics_are_refused(change: dict) -> None:
    good = dict(fx=100.0, fy=100.0, cx=32.0, cy=24.0, width=64, height=48)
    with pytest.raises(CameraError):
        Camera(**{**good, **change})


def test_pose_is_copied_and_read_only() -> None:
    pose = np.eye(4)
    cam = Camera(fx=1.0, fy=1.0, cx=0.5, cy=0.5, width=1, height=1, pose=pose)
    pose[0, 3] = 5.0
    assert cam.position[0] == 0.0
    with pytest.raises(ValueError):
        cam.pose[0, 3] = 1.0


# ---------------------------------------------------------------------------------------------------- JSON and helpers
@FAST
@given(cameras())
def test_json_round_trip(cam: Camera) -> None:
    again = Camera.from_json(cam.to_json())
    assert again == cam and hash(again) == hash(cam)
    np.testing.assert_array_equal(again.pose, cam.pose)


@pytest.mark.parametrize("text", ["{", "[]", '{"fx": 1}'])
def test_malformed_camera_json_is_refused(text: str) -> None:
    with pytest.raises(CameraError):
        Camera.from_json(text)


def test_with_pose_and_scaled_keep_the_view() -> None:
    cam = Camera.look_at((1.0, -0.5, 0.0), (0.0, 0.0, 4.0), width=40, height=30, hfov=50.0)
    moved = cam.with_pose(np.eye(4))
    assert (moved.fx, moved.cx, moved.width) == (cam.fx, cam.cx, cam.width)
    np.testing.assert_array_equal(moved.pose, np.eye(4))
    big = cam.scaled(2.0)
    assert (big.width, big.height) == (80, 60)
    p = np.array([0.2, 0.1, 3.0])
    # Doubling the resolution doubles continuous pixel coordinates and keeps the depth.
    np.testing.assert_allclose(big.project(p), cam.project(p) * [2.0, 2.0, 1.0], rtol=1e-12)


def test_orbit_direction_axes_and_broadcast() -> None:
    """Azimuth 0 looks from -z (the grid's own side), +90 degrees from +x; elevation 90 degrees from above (-y)."""
    from fruxel.camera import orbit_direction

    np.testing.assert_allclose(orbit_direction(0.0, 0.0), [0.0, 0.0, -1.0], atol=1e-15)
    np.testing.assert_allclose(orbit_direction(np.pi / 2, 0.0), [1.0, 0.0, 0.0], atol=1e-15)
    np.testing.assert_allclose(orbit_direction(0.3, np.pi / 2), [0.0, -1.0, 0.0], atol=1e-15)
    d = orbit_direction(np.linspace(-3, 3, 7), 0.4)
    assert d.shape == (7, 3)
    np.testing.assert_allclose(np.linalg.norm(d, axis=-1), 1.0, rtol=1e-15)
    np.testing.assert_allclose(d[:, 1], -np.sin(0.4))


# ---------------------------------------------------------------------------------------------------- look_at_grid
FRAME_GRID = FruxelGrid(width=40, height=30, depth=50, z_near=0.3, z_far=7.0, hfov=75.0)


@pytest.mark.parametrize("seed", range(6))
def test_look_at_grid_fits_the_points_tightly(seed: int) -> None:
    """With no distance, every point lands inside the image less the margin, and one touches it (the fit is the
    smallest distance); with centre=True the points' image is centred as well."""
    from fruxel.camera import look_at_grid, orbit_direction

    rng = np.random.default_rng(seed)
    d = orbit_direction(rng.uniform(-np.pi, np.pi), rng.uniform(-1.2, 1.2))
    points = FRAME_GRID.cell_corners(rng.integers(0, 50, 5), rng.integers(0, 30, 5), rng.integers(0, 40, 5))
    points = points.reshape(-1, 3)
    for pts, centre in ((None, False), (points, False), (points, True)):
        cam = look_at_grid(FRAME_GRID, d, points=pts, width=64, height=48, hfov=55.0, margin=0.05, centre=centre)
        p = cam.project(FRAME_GRID.frustum_corners() if pts is None else pts)
        lo, hi = np.array([3.2, 2.4]), np.array([64 - 3.2, 48 - 2.4])
        assert np.all(p[:, 2] > 0) and np.all(p[:, :2] >= lo - 1e-6) and np.all(p[:, :2] <= hi + 1e-6)
        slack = np.minimum(p[:, :2] - lo, hi - p[:, :2]).min()
        assert slack < 1e-6
        if centre:
            mid = 0.5 * (p[:, :2].min(axis=0) + p[:, :2].max(axis=0))
            np.testing.assert_allclose(mid, [32.0, 24.0], atol=0.5)
        else:
            target = FRAME_GRID.centre()
            np.testing.assert_allclose(cam.project(target)[:2], [32.0, 24.0], atol=1e-9)
        # The view is along -direction whatever was fitted.
        np.testing.assert_allclose(cam.rotation[:, 2], -d, atol=1e-12)


def test_look_at_grid_at_a_distance_and_from_above() -> None:
    from fruxel.camera import look_at_grid

    target = np.array([0.5, 0.2, 3.0])
    cam = look_at_grid(FRAME_GRID, [0.0, 0.0, -2.0], distance=4.0, target=target, width=20, height=10)
    np.testing.assert_allclose(cam.position, target + [0.0, 0.0, -4.0], atol=1e-12)
    np.testing.assert_allclose(cam.project(target), [10.0, 5.0, 4.0], atol=1e-9)
    # Image up is the grid's up (-y): a point above the target is above the image centre.
    assert cam.project(target + [0.0, -0.1, 0.0])[1] < 5.0
    top = look_at_grid(FRAME_GRID, [0.0, -1.0, 0.0], distance=3.0)
    np.testing.assert_allclose(top.rotation[:, 2], [0.0, 1.0, 0.0], atol=1e-12)


@pytest.mark.parametrize("kwargs", [{"direction": [0.0, 0.0, 0.0]}, {"direction": [np.nan, 0.0, 1.0]},
                                    {"distance": -1.0}, {"distance": np.inf}, {"margin": 0.5},
                                    {"points": np.zeros((0, 3))}])
def test_look_at_grid_refuses_impossible_input(kwargs: dict) -> None:
    from fruxel.camera import look_at_grid

    args = {"direction": [0.0, -0.5, -1.0], **kwargs}
    with pytest.raises(CameraError):
        look_at_grid(FRAME_GRID, args.pop("direction"), **args)

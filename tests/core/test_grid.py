"""FruxelGrid geometry (conventions section 1): planes, cells, centres, corners, volumes, validation, JSON."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fruxel.grid import MAX_CELLS, FruxelGrid, GridError

FAST = settings(max_examples=60, deadline=None)


@st.composite
def grids(draw: st.DrawFn, max_size: int = 24) -> FruxelGrid:
    z_near = draw(st.floats(0.01, 10.0))
    return FruxelGrid(
        width=draw(st.integers(1, max_size)),
        height=draw(st.integers(1, max_size)),
        depth=draw(st.integers(1, max_size)),
        z_near=z_near,
        z_far=z_near + draw(st.floats(0.01, 50.0)),
        hfov=draw(st.floats(1.0, 170.0)),
    )


@st.composite
def grid_and_cell(draw: st.DrawFn) -> tuple[FruxelGrid, int, int, int]:
    g = draw(grids())
    return g, draw(st.integers(0, g.depth - 1)), draw(st.integers(0, g.height - 1)), draw(st.integers(0, g.width - 1))


# ---------------------------------------------------------------------------------------------------- planes
@FAST
@given(grids())
def test_plane_boundaries_follow_the_spec(g: FruxelGrid) -> None:
    tu = math.tan(math.radians(g.hfov) / 2)
    tv = tu * g.height / g.width
    u, v, z = g.u_bounds(), g.v_bounds(), g.z_bounds()
    assert u.shape == (g.width + 1,) and v.shape == (g.height + 1,) and z.shape == (g.depth + 1,)
    np.testing.assert_allclose(u, [-tu + i * 2 * tu / g.width for i in range(g.width + 1)], rtol=0, atol=1e-12 * tu)
    np.testing.assert_allclose(v, [-tv + j * 2 * tv / g.height for j in range(g.height + 1)], rtol=0, atol=1e-12 * tv)
    np.testing.assert_allclose(z, [g.z_near + k * (g.z_far - g.z_near) / g.depth for k in range(g.depth + 1)],
                               rtol=1e-13)
    assert z[0] == g.z_near and u[0] == -tu and v[0] == -tv
    assert np.all(np.diff(u) > 0) and np.all(np.diff(v) > 0) and np.all(np.diff(z) > 0)
    assert g.shape == (g.depth, g.height, g.width) and g.n_cells == g.depth * g.height * g.width


def test_square_pixels_and_known_planes() -> None:
    g = FruxelGrid(width=4, height=2, depth=3, z_near=1.0, z_far=4.0, hfov=90.0)
    np.testing.assert_allclose(g.u_bounds(), [-1.0, -0.5, 0.0, 0.5, 1.0], atol=1e-15)
    np.testing.assert_allclose(g.v_bounds(), [-0.5, 0.0, 0.5], atol=1e-15)
    np.testing.assert_allclose(g.z_bounds(), [1.0, 2.0, 3.0, 4.0])
    assert g.du == pytest.approx(g.dv)


# ---------------------------------------------------------------------------------------------------- corners
@FAST
@given(grid_and_cell())
def test_neighbouring_cells_share_corners_bit_identically(gc: tuple[FruxelGrid, int, int, int]) -> None:
    g, k, j, i = gc
    corners = g.cell_corners(k, j, i)
    assert corners.shape == (8, 3)
    c = np.arange(8)
    # Corner bit 0 steps i, bit 1 steps j, bit 2 steps k (grid.py's documented corner order).
    for axis, bit, (kk, jj, ii) in ((2, 1, (k, j, i + 1)), (1, 2, (k, j + 1, i)), (0, 4, (k + 1, j, i))):
        if (kk, jj, ii)[axis] >= g.shape[axis]:
            continue
        other = g.cell_corners(kk, jj, ii)
        high = c[(c & bit) != 0]
        assert np.array_equal(corners[high], other[high - bit]), f"shared face along axis {axis} differs"


@FAST
@given(grid_and_cell())
def test_corners_lie_on_the_cell_planes(gc: tuple[FruxelGrid, int, int, int]) -> None:
    g, k, j, i = gc
    corners = g.cell_corners(k, j, i)
    u, v, z = g.u_bounds(), g.v_bounds(), g.z_bounds()
    for c in range(8):
        x, y, zz = corners[c]
        assert zz == pytest.approx(z[k + (c >> 2)], rel=1e-12)
        assert x / zz == pytest.approx(u[i + (c & 1)], rel=1e-9, abs=1e-12)
        assert y / zz == pytest.approx(v[j + ((c >> 1) & 1)], rel=1e-9, abs=1e-12)


# ---------------------------------------------------------------------------------------------------- points and cells
@FAST
@given(grid_and_cell())
def test_cell_to_point_to_cell_round_trip(gc: tuple[FruxelGrid, int, int, int]) -> None:
    g, k, j, i = gc
    p = g.cell_to_point(k, j, i)
    assert p.shape == (3,)
    assert g.point_to_cell(p).tolist() == [k, j, i]
    # The centre is the middle of the cell's three parameter ranges (grid.py's documented definition).
    u, v, z = g.u_bounds(), g.v_bounds(), g.z_bounds()
    zc = (z[k] + z[k + 1]) / 2
    np.testing.assert_allclose(p, [(u[i] + u[i + 1]) / 2 * zc, (v[j] + v[j + 1]) / 2 * zc, zc],
                               rtol=1e-12, atol=1e-12 * zc)


def test_all_centres_round_trip_and_match_cell_centres() -> None:
    g = FruxelGrid(width=7, height=5, depth=6, z_near=0.3, z_far=9.0, hfov=120.0)
    centres = g.cell_centres()
    assert centres.shape == (6, 5, 7, 3) and centres.dtype == np.float64
    k, j, i = np.meshgrid(np.arange(6), np.arange(5), np.arange(7), indexing="ij")
    np.testing.assert_array_equal(g.point_to_cell(centres), np.stack([k, j, i], axis=-1))
    np.testing.assert_array_equal(centres[2, 3, 4], g.cell_to_point(2, 3, 4))


@FAST
@given(grid_and_cell(), st.tuples(*[st.floats(0.001, 0.999)] * 3))
def test_random_points_inside_a_cell_map_back_to_it(gc: tuple[FruxelGrid, int, int, int], f: tuple) -> None:
    g, k, j, i = gc
    u = g.u_bounds()[i] + f[0] * g.du
    v = g.v_bounds()[j] + f[1] * g.dv
    z = g.z_bounds()[k] + f[2] * g.dz
    assert g.point_to_cell([u * z, v * z, z]).tolist() == [k, j, i]


def test_points_outside_the_frustum_give_minus_one() -> None:
    g = FruxelGrid(width=4, height=4, depth=4, z_near=1.0, z_far=5.0, hfov=90.0)
    outside = [
        [0.0, 0.0, 0.99],  # in front of the near plane
        [0.0, 0.0, 5.0],  # on the far plane: slices are half-open
        [0.0, 0.0, -2.0],  # behind the camera
        [3.1, 0.0, 3.0],  # right of u = 1
        [0.0, -3.1, 3.0],  # above v = -1
        [np.nan, 0.0, 2.0],
        [0.0, 0.0, np.inf],
    ]
    np.testing.assert_array_equal(g.point_to_cell(outside), -np.ones((len(outside), 3), dtype=np.int64))
    assert g.point_to_cell([0.0, 0.0, 1.0]).tolist() == [0, 2, 2]  # the near plane itself is inside slice 0
    assert g.point_to_cell(np.zeros((2, 5, 3))).shape == (2, 5, 3)
    with pytest.raises(GridError):
        g.point_to_cell(np.zeros((4, 2)))


@FAST
@given(grids(), st.data())
def test_flat_index_follows_the_spec_and_inverts(g: FruxelGrid, data: st.DataObject) -> None:
    k = np.array(data.draw(st.lists(st.integers(0, g.depth - 1), min_size=1, max_size=8)))
    j = np.array(data.draw(st.lists(st.integers(0, g.height - 1), min_size=len(k), max_size=len(k))))
    i = np.array(data.draw(st.lists(st.integers(0, g.width - 1), min_size=len(k), max_size=len(k))))
    flat = g.flat_index(k, j, i)
    assert flat.dtype == np.int64
    np.testing.assert_array_equal(flat, np.ravel_multi_index((k, j, i), g.shape))
    for a, b in zip(g.unflatten(flat), (k, j, i), strict=True):
        np.testing.assert_array_equal(a, b)


def test_index_validation() -> None:
    g = FruxelGrid(width=3, height=2, depth=4, z_near=1.0, z_far=2.0, hfov=60.0)
    for bad in ((4, 0, 0), (0, 2, 0), (0, 0, 3), (-1, 0, 0)):
        with pytest.raises(GridError, match="out of range"):
            g.cell_to_point(*bad)
    with pytest.raises(GridError, match="integer"):
        g.cell_to_point(0.5, 0, 0)
    with pytest.raises(GridError):
        g.unflatten(g.n_cells)


# ---------------------------------------------------------------------------------------------------- the own camera
@FAST
@given(grids(max_size=16), st.data())
def test_own_camera_centre_ray_passes_through_every_cell_centre_of_its_column(
    g: FruxelGrid, data: st.DataObject
) -> None:
    j = data.draw(st.integers(0, g.height - 1))
    i = data.draw(st.integers(0, g.width - 1))
    cam = g.camera()
    assert (cam.width, cam.height) == (g.width, g.height)
    origins, dirs = cam.rays()
    assert dirs.shape == (g.height, g.width, 3)
    np.testing.assert_array_equal(origins[j, i], [0.0, 0.0, 0.0])
    d = dirs[j, i]
    centres = g.cell_to_point(np.arange(g.depth), j, i)
    cross = np.cross(d, centres)
    scale = np.linalg.norm(d) * np.linalg.norm(centres, axis=-1)
    assert np.all(np.linalg.norm(cross, axis=-1) <= 1e-12 * scale)
    # Same direction, not the opposite one, and every centre maps back to this column.
    assert np.all(centres @ d > 0)
    np.testing.assert_array_equal(g.point_to_cell(centres)[:, 1:], np.tile([j, i], (g.depth, 1)))


# ---------------------------------------------------------------------------------------------------- volumes
@FAST
@given(grids())
def test_cell_volumes_sum_to_the_frustum_volume(g: FruxelGrid) -> None:
    tu = math.tan(math.radians(g.hfov) / 2)
    tv = tu * g.height / g.width
    frustum = (2 * tu) * (2 * tv) * (g.z_far**3 - g.z_near**3) / 3
    vol = g.cell_volumes()
    assert vol.shape == g.shape and np.all(vol > 0)
    assert vol.sum() == pytest.approx(frustum, rel=1e-9)


def _polyhedron_volume(corners: np.ndarray) -> float:
    # Divergence theorem over the six planar quadrilateral faces, each split into two triangles; corner order
    # as in grid.py (bit 0: i, bit 1: j, bit 2: k). Independent of the closed form used by the grid.
    faces = [(0, 2, 3, 1), (4, 5, 7, 6), (0, 1, 5, 4), (2, 6, 7, 3), (0, 4, 6, 2), (1, 3, 7, 5)]
    total = 0.0
    for a, b, c, d in faces:
        for tri in ((a, b, c), (a, c, d)):
            p, q, r = corners[list(tri)]
            total += np.dot(p, np.cross(q, r)) / 6.0
    return abs(total)


@FAST
@given(grid_and_cell())
def test_cell_volume_matches_its_polyhedron(gc: tuple[FruxelGrid, int, int, int]) -> None:
    g, k, j, i = gc
    assert g.cell_volumes()[k, j, i] == pytest.approx(_polyhedron_volume(g.cell_corners(k, j, i)), rel=1e-7)


def test_bounds_contain_every_corner() -> None:
    g = FruxelGrid(width=5, height=3, depth=4, z_near=0.5, z_far=6.0, hfov=100.0)
    k, j, i = np.meshgrid(np.arange(4), np.arange(3), np.arange(5), indexing="ij")
    corners = g.cell_corners(k, j, i).reshape(-1, 3)
    lo, hi = g.bounds()
    assert np.all(corners >= lo - 1e-12) and np.all(corners <= hi + 1e-12)
    np.testing.assert_allclose([corners.min(axis=0), corners.max(axis=0)], [lo, hi])


# ---------------------------------------------------------------------------------------------------- validation
GOOD = dict(width=4, height=3, depth=2, z_near=0.5, z_far=3.0, hfov=60.0)


@pytest.mark.parametrize(
    "change",
    [
        {"z_near": 0.0},
        {"z_near": -1.0},
        {"z_far": 0.5},
        {"z_far": 0.4},
        {"hfov": 0.0},
        {"hfov": 180.0},
        {"hfov": -30.0},
        {"hfov": float("nan")},
        {"z_near": float("nan")},
        {"z_far": float("inf")},
        {"width": 0},
        {"height": -2},
        {"depth": 2.5},
        {"width": "4"},
        {"width": True},
        {"width": None},
        {"hfov": "wide"},
        {"width": 2**12, "height": 2**12, "depth": 2**11 + 1},
    ],
)
def test_impossible_parameters_are_refused(change: dict) -> None:
    with pytest.raises(GridError):
        FruxelGrid(**{**GOOD, **change})


def test_integral_floats_and_numpy_numbers_are_accepted() -> None:
    g = FruxelGrid(width=4.0, height=np.int32(3), depth=np.uint8(2), z_near=np.float32(0.5), z_far=3, hfov=60)
    assert g == FruxelGrid(**GOOD)
    assert isinstance(g.width, int) and isinstance(g.z_far, float)
    assert g.n_cells <= MAX_CELLS


# ---------------------------------------------------------------------------------------------------- JSON
@FAST
@given(grids())
def test_json_round_trip_is_exact(g: FruxelGrid) -> None:
    again = FruxelGrid.from_json(g.to_json())
    assert again == g and hash(again) == hash(g)
    assert FruxelGrid.from_dict(json.loads(json.dumps(g.to_dict()))) == g


@pytest.mark.parametrize(
    "text",
    [
        "{not json",
        "[1, 2, 3]",
        json.dumps({k: v for k, v in GOOD.items() if k != "hfov"}),
        json.dumps({**GOOD, "extra": 1}),
        json.dumps({**GOOD, "z_near": -1}),
    ],
)
def test_malformed_grid_json_is_refused(text: str) -> None:
    with pytest.raises(GridError):
        FruxelGrid.from_json(text)

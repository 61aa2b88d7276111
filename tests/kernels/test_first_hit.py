"""first_hit on every backend: agreement with the float64 reference, hard viewpoints, watertightness, batches,
scores and array kinds (conventions sections 2-4)."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid
from fruxel.kernels import first_hit as _kernels_first_hit
from fruxel.kernels import shell as _kernels_shell

from .conftest import (
    BACKENDS,
    CAMERA_KINDS,
    REAL_BACKENDS,
    assert_agree,
    assert_bounds,
    first_hit,
    hits_numpy,
    lattice_camera,
    random_camera,
    random_grid,
    random_intrinsics_camera,
    random_labels,
    region_of_cells,
    scores_from_labels,
)
from .reference import near_edge, ref_first_hit, ref_labels_from_scores

SEEDS = range(10)


# ---------------------------------------------------------------------------------------------- random scenes


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", SEEDS)
def test_random_views_agree_with_reference(backend: str, seed: int) -> None:
    """Random volume, non-square grid, random intrinsics; every kind of viewpoint in turn."""
    rng = np.random.default_rng(seed)
    grid = random_grid(rng)
    labels = random_labels(rng, grid)
    for n, kind in enumerate(CAMERA_KINDS):
        if (n + seed) % 2:
            continue
        cam = random_camera(rng, grid, kind, labels)
        hits = first_hit(backend, labels, grid, cam)
        what = f"seed {seed} {kind}"
        assert_agree(hits, labels, grid, cam, what=what)
        assert_bounds(hits, labels, grid, cam, what=what)
        got = hits_numpy(hits)
        if kind == "away":
            assert np.all(got["cell"] == -1), f"{what}: a camera looking away hit something"
        if kind == "inside_occupied":
            k, j, i = grid.point_to_cell(cam.position)
            assert np.all(got["cell"] == (k * grid.height + j) * grid.width + i), f"{what}: not the camera's cell"
            assert np.all(got["depth"] == 0), f"{what}: depth inside an occupied cell"
            _, d = cam.rays()
            np.testing.assert_allclose(got["normal"], -d / np.linalg.norm(d, axis=-1, keepdims=True), atol=1e-5)


@pytest.mark.parametrize("backend", BACKENDS)
@settings(max_examples=8, deadline=None, derandomize=True)
@given(
    seed=st.integers(0, 2**32 - 1),
    occupancy=st.floats(0.05, 0.4),
    kind=st.sampled_from(CAMERA_KINDS[:-1]),
)
def test_property_agreement(backend: str, seed: int, occupancy: float, kind: str) -> None:
    rng = np.random.default_rng(seed)
    grid = random_grid(rng, small=True)
    labels = random_labels(rng, grid, occupancy)
    if not labels.any():
        labels[0, 0, 0] = 1
    cam = random_camera(rng, grid, kind, labels, size=(24, 18))
    hits = first_hit(backend, labels, grid, cam)
    assert_agree(hits, labels, grid, cam, what=f"{kind} {seed}")
    assert_bounds(hits, labels, grid, cam, what=f"{kind} {seed}")


@pytest.mark.skipif(len(REAL_BACKENDS) < 2, reason="needs two backends")
@pytest.mark.parametrize("seed", range(4))
def test_backends_agree_with_each_other(seed: int) -> None:
    rng = np.random.default_rng(100 + seed)
    grid = random_grid(rng)
    labels = random_labels(rng, grid)
    for kind in CAMERA_KINDS:
        cam = random_camera(rng, grid, kind, labels)
        res = {b: hits_numpy(first_hit(b, labels, grid, cam)) for b in REAL_BACKENDS}
        for a, b in itertools.combinations(REAL_BACKENDS, 2):
            mism = (res[a]["cell"] != res[b]["cell"]) | (res[a]["label"] != res[b]["label"])
            if mism.any():
                until = np.maximum(res[a]["depth"], res[b]["depth"]).astype(np.float64) * 1.001
                flag = near_edge(grid, cam, 1e-4, until=np.where(until > 0, until, np.inf))
                assert not (mism & ~flag).any(), f"{a} and {b} differ away from edges ({kind}, seed {seed})"
                assert mism.sum() <= 0.005 * mism.size
            same = ~mism & (res[a]["cell"] >= 0)
            np.testing.assert_allclose(res[a]["depth"][same], res[b]["depth"][same], rtol=1e-5, atol=1e-6)


# ---------------------------------------------------------------------------------------------- hard viewpoints


def _hard_cameras(grid: FruxelGrid, rng: np.random.Generator) -> dict[str, Camera]:
    """Cameras whose rays run along planes, parallel to axes, or through the apex region."""
    c = grid.centre()
    zk = grid.z_bounds()
    uk = grid.u_bounds()
    cams = {}
    # Looking along +x: grid direction (1, b, -a); column x + 0.5 == cx has d_z = 0 exactly, and the row with
    # y + 0.5 == cy has d_y = 0; the eye sits exactly on slice plane z_2, so that column grazes it.
    side = np.eye(4)
    side[:3, :3] = [[0, 0, 1], [0, 1, 0], [-1, 0, 0]]
    side[:3, 3] = [c[0] - 3 * grid.bounds()[1][0], 0.37 * c[1], zk[2]]
    cams["d_z=0 along slice plane"] = Camera(fx=30.0, fy=25.0, cx=16.5, cy=11.5, width=33, height=23, pose=side)
    # Looking along +z from beside the axis: the column with x + 0.5 == cx has d_x = 0 (rays parallel to the
    # plane x = 0, crossing u-planes only through o_x / z), the row with y + 0.5 == cy has d_y = 0.
    fwd = np.eye(4)
    fwd[:3, 3] = [0.3 * grid.bounds()[1][0], -0.2 * grid.bounds()[1][1], 0.5 * grid.z_near]
    cams["d_x=0 forward"] = Camera(fx=28.0, fy=33.0, cx=12.5, cy=9.5, width=31, height=21, pose=fwd)
    # Camera on the plane x = u_3 z, aiming along it: rays of column cx lie in that plane.
    z0 = 0.5 * (zk[0] + zk[1])
    eye = np.array([uk[3] * z0, 0.1 * c[1], z0])
    along = np.array([uk[3], 0.0, 1.0]) / math.hypot(uk[3], 1.0)
    pose = Camera.look_at(eye, eye + along, up=(0, -1, 0)).pose
    cams["grazing u-plane"] = Camera(fx=26.0, fy=26.0, cx=13.5, cy=10.0, width=27, height=21, pose=pose)
    # Behind the apex on the axis, looking forward: rays cross the optical axis before entering.
    back = np.eye(4)
    back[:3, 3] = [0.0, 0.0, -2.0 * grid.z_near]
    cams["behind apex forward"] = Camera(fx=20.0, fy=23.0, cx=15.3, cy=10.7, width=30, height=22, pose=back)
    # At the apex itself with a tilted pose: every ray starts on every u- and v-plane's common line.
    tilt = Camera.look_at([0.0, 0.0, 0.0], c + rng.normal(size=3) * 0.1, up=(0, -1, 0)).pose
    cams["at apex tilted"] = random_intrinsics_camera(rng, tilt, (30, 24))
    # On a lattice corner inside the grid, looking across the grid.
    corner = grid.corner_points(2, 1, 2)
    cams["on lattice corner"] = random_intrinsics_camera(rng, Camera.look_at(corner, c + [0.3, 0.2, 0.5]).pose)
    # Grazing the frustum's left face from outside, nearly parallel to it.
    z1 = grid.z_far * 1.2
    left = np.array([uk[0] * z1 - 1e-9, 0.0, z1])
    cams["grazing left face"] = Camera.from_hfov(
        25, 19, 20.0, Camera.look_at(left, left * 0.1 + [0, 0.02 * z1, 0], up=(0, -1, 0)).pose)
    return cams


HARD_CASES = ("d_z=0 along slice plane", "d_x=0 forward", "grazing u-plane", "behind apex forward",
              "at apex tilted", "on lattice corner", "grazing left face")


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", HARD_CASES)
def test_hard_viewpoints(backend: str, case: str) -> None:
    """Degenerate rays: reference agreement away from edges, and the per-cell clipping bounds everywhere."""
    rng = np.random.default_rng(7)
    grid = FruxelGrid(11, 9, 10, z_near=0.4, z_far=3.2, hfov=75.0)
    labels = random_labels(rng, grid, 0.2)
    cam = _hard_cameras(grid, rng)[case]
    hits = first_hit(backend, labels, grid, cam)
    assert_agree(hits, labels, grid, cam, max_fraction=None, what=case)
    assert_bounds(hits, labels, grid, cam, what=case)


def test_hard_viewpoints_are_hard() -> None:
    """The hard cameras really have the degenerate rays they are named for (guards against silent drift)."""
    rng = np.random.default_rng(7)
    grid = FruxelGrid(11, 9, 10, z_near=0.4, z_far=3.2, hfov=75.0)
    cams = _hard_cameras(grid, rng)
    _, d = cams["d_z=0 along slice plane"].rays()
    assert np.any(d[..., 2] == 0) and np.any((d[..., 2] == 0) & (d[..., 1] == 0))
    assert cams["d_z=0 along slice plane"].position[2] == grid.z_bounds()[2]
    _, d = cams["d_x=0 forward"].rays()
    assert np.any(d[..., 0] == 0)
    assert np.all(cams["at apex tilted"].position == 0)
    labels = np.ones(grid.shape, np.uint8)
    assert (ref_first_hit(labels, grid, cams["behind apex forward"])["cell"] >= 0).mean() > 0.5
    assert near_edge(grid, cams["grazing u-plane"], 1e-4).any()


# ---------------------------------------------------------------------------------------------- watertightness


def _lattice_eyes(grid: FruxelGrid) -> list[tuple[np.ndarray, int]]:
    """Eyes and target slices for :func:`lattice_camera`: apex, behind it, inside, beside, beyond the far plane."""
    b = grid.bounds()
    zk = grid.z_bounds()
    return [
        (np.zeros(3), grid.depth // 2),
        (np.array([0.03, -0.02, -0.7]), 1),
        (np.array([0.4 * b[1][0], 0.2 * b[1][1], zk[1] + 0.3 * grid.dz]), grid.depth - 1),
        (np.array([1.7 * b[1][0], -0.3 * b[1][1], 0.5 * zk[0]]), grid.depth // 2 + 1),
        (np.array([-0.1 * b[1][0], 0.25 * b[1][1], 1.3 * grid.z_far]), 2),
        (grid.corner_points(1, 2, 2), grid.depth),
    ]


def _outside_views(rng: np.random.Generator, grid: FruxelGrid, target: np.ndarray, n: int,
                   keep_out: tuple[float, ...]) -> list[Camera]:
    """Random cameras outside the parameter box ``keep_out``, looking at points around ``target``."""
    cams = []
    r = float(np.linalg.norm(grid.bounds()[1] - grid.bounds()[0]))
    while len(cams) < n:
        eye = target + rng.normal(size=3) * rng.uniform(0.3, 1.2) * r
        u_lo, u_hi, v_lo, v_hi, z_lo, z_hi = keep_out
        if eye[2] > 0 and u_lo <= eye[0] / eye[2] <= u_hi and v_lo <= eye[1] / eye[2] <= v_hi and \
                z_lo <= eye[2] <= z_hi:
            continue
        aim = target + rng.normal(size=3) * 0.05 * r
        cams.append(random_intrinsics_camera(rng, Camera.look_at(eye, aim).pose, (33, 27)))
    return cams


@pytest.mark.parametrize("backend", BACKENDS)
def test_watertight_box(backend: str) -> None:
    """A solid box of cells stops every ray through its interior, including rays along its inner edges."""
    rng = np.random.default_rng(11)
    grid = FruxelGrid(8, 7, 6, z_near=0.5, z_far=2.5, hfov=70.0)
    labels = np.zeros(grid.shape, np.uint8)
    labels[1:5, 1:6, 2:7] = rng.integers(1, 7, size=(4, 5, 5))
    region = region_of_cells(grid, 1, 5, 1, 6, 2, 7)
    cams = [lattice_camera(grid, e, k) for e, k in _lattice_eyes(grid)]
    cams += _outside_views(rng, grid, grid.cell_to_point(3, 3, 4), 8, region)
    for n, cam in enumerate(cams):
        hits = first_hit(backend, labels, grid, cam)
        assert_bounds(hits, labels, grid, cam, regions=[region], what=f"box view {n}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_watertight_sphere(backend: str) -> None:
    """A solid ball of cells seen from outside: no ray through an occupied cell's interior gets through."""
    rng = np.random.default_rng(12)
    grid = FruxelGrid(10, 9, 8, z_near=0.6, z_far=3.0, hfov=65.0)
    centre = grid.cell_to_point(4, 4, 5)
    radius = 2.6 * grid.cell_extent()[4].max()
    labels = (np.linalg.norm(grid.cell_centres() - centre, axis=-1) < radius).astype(np.uint8)
    labels *= rng.integers(1, 7, size=grid.shape).astype(np.uint8)
    assert labels.sum() > 20
    cams = [lattice_camera(grid, e, k) for e, k in _lattice_eyes(grid)]
    far = (-grid.tu, grid.tu, -grid.tv, grid.tv, grid.z_near, grid.z_far)
    cams += _outside_views(rng, grid, centre, 8, far)
    for n, cam in enumerate(cams):
        hits = first_hit(backend, labels, grid, cam)
        assert_bounds(hits, labels, grid, cam, what=f"sphere view {n}")


@pytest.mark.parametrize("backend", BACKENDS)
def test_wall_stops_every_ray(backend: str) -> None:
    """A fully occupied slice stops every ray that reaches it, from either side, along edges too."""
    rng = np.random.default_rng(13)
    grid = FruxelGrid(9, 6, 7, z_near=0.5, z_far=2.6, hfov=80.0)
    k0 = 3
    labels = np.zeros(grid.shape, np.uint8)
    labels[k0] = rng.integers(1, 7, size=grid.shape[1:])
    region = region_of_cells(grid, k0, k0 + 1, 0, grid.height, 0, grid.width)
    cams = [lattice_camera(grid, e, k) for e, k in _lattice_eyes(grid)]
    cams += [lattice_camera(grid, np.array([0.0, 0.0, 0.0]), k0), lattice_camera(grid, np.zeros(3), k0 + 1)]
    cams += _outside_views(rng, grid, grid.cell_to_point(k0, 3, 4), 6, region)
    reached = 0
    for n, cam in enumerate(cams):
        hits = first_hit(backend, labels, grid, cam)
        assert_bounds(hits, labels, grid, cam, regions=[region], what=f"wall view {n}")
        got = hits_numpy(hits)
        reached += int((got["cell"] >= 0).sum())
        # Rays from the apex lie on u- and v-planes at once; each must stop in slice k0. The outermost ones run
        # along the frustum's faces, where missing is as right as hitting.
        if np.all(cam.position == 0):
            inner = got["cell"][1:-1, 1:-1]
            k = inner // (grid.height * grid.width)
            assert np.all(inner >= 0) and np.all(k == k0), f"wall view {n}: apex ray not stopped at k0"
    assert reached > 1000


def test_lattice_camera_hits_lattice_points() -> None:
    """The lattice cameras used above do aim at lattice points (so the watertight tests test edges)."""
    grid = FruxelGrid(8, 7, 6, z_near=0.5, z_far=2.5, hfov=70.0)
    for eye, k in _lattice_eyes(grid):
        cam = lattice_camera(grid, eye, k)
        o, d = cam.rays()
        t = (grid.z_bounds()[k] - o[..., 2]) / d[..., 2]
        p = o + t[..., None] * d
        corners = grid.corner_points(k, np.arange(grid.height + 1)[:, None], np.arange(grid.width + 1)[None, :])
        assert np.all(t > 0)
        assert np.max(np.abs(np.sort(p.reshape(-1, 3), axis=0) - np.sort(corners.reshape(-1, 3), axis=0))) < 1e-12


def test_near_edge_is_selective() -> None:
    """The excuse for float32 differences covers rays along edges and few others."""
    rng = np.random.default_rng(17)
    grid = FruxelGrid(10, 8, 9, z_near=0.5, z_far=3.0, hfov=70.0)
    assert near_edge(grid, lattice_camera(grid, np.zeros(3), 4), 1e-4)[1:-1, 1:-1].all()
    for kind in ("front", "beside", "far_side"):
        cam = random_camera(rng, grid, kind, size=(60, 45))
        assert near_edge(grid, cam, 1e-4).mean() < 0.03
    # One-pixel cameras aimed past the edge of u_3 and v_2, mid-slice, at a given offset in cell units.
    zk = grid.z_bounds()[4] + 0.5 * grid.dz
    for offset, flagged in ((1e-6, True), (3e-5, True), (1e-2, False)):
        target = np.array([(grid.u_bounds()[3] + offset * grid.du) * zk, grid.v_bounds()[2] * zk, zk])
        cam = Camera.look_at(np.array([1.3, -0.9, 0.2]), target, width=1, height=1)
        assert bool(near_edge(grid, cam, 1e-4)[0, 0]) is flagged, offset


# ---------------------------------------------------------------------------------------------- batches, scores


@pytest.mark.parametrize("backend", BACKENDS)
def test_batched_equals_items(backend: str) -> None:
    rng = np.random.default_rng(21)
    grid = random_grid(rng)
    labels = np.stack([random_labels(rng, grid) for _ in range(3)])
    cam = random_camera(rng, grid, "front")
    batch = hits_numpy(first_hit(backend, labels, grid, cam))
    assert batch["label"].shape == (3, cam.height, cam.width)
    assert batch["normal"].shape == (3, cam.height, cam.width, 3)
    for b in range(3):
        one = hits_numpy(first_hit(backend, labels[b], grid, cam))
        for f in one:
            np.testing.assert_array_equal(batch[f][b], one[f], err_msg=f"item {b} field {f}")
    # The items differ, so equality above is not trivially true.
    assert not np.array_equal(batch["cell"][0], batch["cell"][1])


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
@pytest.mark.parametrize("probs", [False, True], ids=["logits", "probs"])
def test_scores_give_their_argmax_labels(backend: str, dtype: type, probs: bool) -> None:
    rng = np.random.default_rng(31)
    grid = random_grid(rng, small=True)
    labels = np.stack([random_labels(rng, grid) for _ in range(2)])
    scores = scores_from_labels(rng, labels, 7, dtype, probs)
    np.testing.assert_array_equal(ref_labels_from_scores(scores), labels)
    cam = random_camera(rng, grid, "front", size=(32, 24))
    want = hits_numpy(first_hit(backend, labels, grid, cam))
    got = hits_numpy(first_hit(backend, scores, grid, cam, probs=probs))
    np.testing.assert_array_equal(got["label"], want["label"])
    np.testing.assert_array_equal(got["cell"], want["cell"])
    np.testing.assert_allclose(got["depth"], want["depth"], rtol=1e-6, atol=0)
    np.testing.assert_allclose(got["normal"], want["normal"], atol=1e-6)
    assert (want["cell"] >= 0).mean() > 0.2


def _threshold_scores(rng: np.random.Generator, shape: tuple[int, ...], channels: int, threshold: float,
                      probs: bool) -> np.ndarray:
    """Scores ``(B, C, D, H, W)`` whose ``1 - p(empty)`` stays at least 0.02 from ``threshold`` and whose
    non-empty argmax is unique by a margin, as logits or probabilities (float32)."""
    p_occ = rng.uniform(0.0, 1.0, size=shape)
    p_occ = np.where(np.abs(p_occ - threshold) < 0.02, np.clip(p_occ + 0.05, 0, 1), p_occ)
    p_occ[..., 0, 0, 0] = 1.0
    w = rng.random(size=(shape[0], channels - 1) + shape[1:]) + 0.1
    best = rng.integers(0, channels - 1, size=(shape[0], 1) + shape[1:])
    np.put_along_axis(w, best, w.max(axis=1, keepdims=True) + 1.0, axis=1)
    w /= w.sum(axis=1, keepdims=True)
    p = np.concatenate([(1 - p_occ)[:, None], p_occ[:, None] * w], axis=1)
    if probs:
        return p.astype(np.float32)
    return np.log(np.maximum(p, 1e-30)).astype(np.float32)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("probs", [False, True], ids=["logits", "probs"])
@pytest.mark.parametrize("threshold", [0.3, 0.75, 1.0])
def test_threshold_rule(backend: str, probs: bool, threshold: float) -> None:
    """With a threshold a cell is occupied when ``1 - p(empty) >= threshold``; its label is the best non-empty
    class. Compared with first_hit on the labels that rule gives, computed independently in float64."""
    rng = np.random.default_rng(41)
    grid = random_grid(rng, small=True)
    scores = _threshold_scores(rng, (2,) + grid.shape, 5, threshold, probs)
    labels = ref_labels_from_scores(scores, threshold, probs)
    argmax_labels = ref_labels_from_scores(scores)
    assert labels.any() and not np.array_equal(labels != 0, argmax_labels != 0)
    cam = random_camera(rng, grid, "front", size=(32, 24))
    got = hits_numpy(first_hit(backend, scores, grid, cam, threshold=threshold, probs=probs))
    want = hits_numpy(first_hit(backend, labels.astype(np.uint8), grid, cam))
    np.testing.assert_array_equal(got["cell"], want["cell"])
    np.testing.assert_array_equal(got["label"], want["label"])


@pytest.mark.parametrize("backend", BACKENDS)
def test_threshold_below_float32_resolution_of_one(backend: str) -> None:
    """A logit threshold far below float32's resolution near 1: occupancy ``1 - p(empty)`` about 7.6e-10 must
    still pass a threshold of 1e-10 in float32 arithmetic (a kernel that forms ``1 - p(empty)`` by subtraction
    rounds it to 0 and misses every cell)."""
    grid = FruxelGrid(6, 5, 4, z_near=0.5, z_far=3.0, hfov=60.0)
    scores = np.zeros((1, 2, *grid.shape), np.float32)
    scores[:, 1] = -21.0
    hits = hits_numpy(first_hit(backend, scores, grid, grid.camera(), threshold=1e-10))
    assert np.all(hits["cell"] == np.arange(grid.height * grid.width).reshape(grid.height, grid.width))
    assert np.all(hits["label"] == 1)


# ---------------------------------------------------------------------------------------------- array kinds


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("in_dtype", [np.uint8, np.int16, np.int32, np.int64, np.bool_])
def test_numpy_in_numpy_out(backend: str, in_dtype: type) -> None:
    rng = np.random.default_rng(51)
    grid = random_grid(rng, small=True)
    labels = random_labels(rng, grid, 0.3)
    vol = (labels != 0) if in_dtype is np.bool_ else labels.astype(in_dtype)
    cam = random_camera(rng, grid, "front", size=(20, 14))
    hits = first_hit(backend, vol, grid, cam)
    for f, dt, shape in (("label", np.int32, (14, 20)), ("cell", np.int64, (14, 20)),
                         ("depth", np.float32, (14, 20)), ("normal", np.float32, (14, 20, 3))):
        v = getattr(hits, f)
        assert isinstance(v, np.ndarray), f"{f} is {type(v)}"
        assert v.dtype == dt and v.shape == shape, f"{f}: {v.dtype} {v.shape}"
    assert_agree(hits, vol.astype(np.int64), grid, cam, what=str(in_dtype))
    if in_dtype is np.bool_:
        assert set(np.unique(hits.label)) <= {0, 1}


@pytest.mark.parametrize("backend", BACKENDS)
def test_torch_in_torch_out(backend: str) -> None:
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(61)
    grid = random_grid(rng, small=True)
    labels = np.stack([random_labels(rng, grid, 0.3) for _ in range(2)])
    cam = random_camera(rng, grid, "front", size=(20, 14))
    want = hits_numpy(first_hit(backend, labels, grid, cam))
    scores = scores_from_labels(rng, labels, 7, np.float32)
    vols = (torch.from_numpy(labels), torch.from_numpy(labels.astype(np.int64)), torch.from_numpy(scores),
            torch.from_numpy(scores).to(torch.bfloat16))
    for vol in vols:
        hits = first_hit(backend, vol, grid, cam)
        for f, dt in (("label", torch.int32), ("cell", torch.int64), ("depth", torch.float32),
                      ("normal", torch.float32)):
            v = getattr(hits, f)
            assert isinstance(v, torch.Tensor) and v.device.type == "cpu", f"{f}: {type(v)}"
            assert v.dtype == dt, f"{f}: {v.dtype}"
            np.testing.assert_array_equal(v.numpy(), want[f], err_msg=f"{f} from {vol.dtype}")


@pytest.mark.gpu
@pytest.mark.skipif("warp-cuda" not in REAL_BACKENDS, reason="needs Warp on a CUDA device")
def test_cuda_tensor_in_cuda_tensor_out() -> None:
    """A CUDA tensor stays on its device (backend chosen by default), with the reference's values.

    Compared with the numpy reference rather than warp-cpu: GPU machines may carry a Warp without its CPU
    compiler.
    """
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(71)
    grid = random_grid(rng)
    labels = np.stack([random_labels(rng, grid) for _ in range(2)])
    cam = random_camera(rng, grid, "front", size=(48, 36))
    hits = _kernels_first_hit(torch.from_numpy(labels).cuda(), grid, cam)
    assert hits.cell.is_cuda and hits.depth.dtype == torch.float32
    got = hits_numpy(hits)
    for b in range(len(labels)):
        assert_agree({k: v[b] for k, v in got.items()}, labels[b], grid, cam, what=f"item {b}")
    kept = _kernels_shell(torch.from_numpy(labels).cuda(), grid, [cam])
    assert kept.is_cuda
    kept = kept.cpu().numpy()
    assert np.all((kept == 0) | (kept == labels))
    for b in range(len(labels)):
        # The shell keeps every first hit: the reference sees through it what CUDA saw in the full volume.
        assert_agree({k: v[b] for k, v in got.items()}, kept[b], grid, cam, what=f"shell item {b}")

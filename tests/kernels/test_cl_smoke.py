"""Quick checks of the OpenCL backend on its own (the cross-backend suite is test_first_hit.py / test_shell.py).

The oracle here is deliberately independent of kernels/traversal.py: dense float64 sampling along every ray,
which finds the first occupied cell without any plane-crossing arithmetic. Sampling can step over a sliver
of a cell that a ray only grazes, and float32 may take the other cell at an edge, so the checks are one-sided
where they must be (the kernel may find an earlier, grazed cell; its answer must still be an occupied cell the
ray enters at the reported depth) and allow a small share of cell disagreements, all at cell edges.
"""

from __future__ import annotations

import importlib

import numpy as np
import pytest

from fruxel.camera import Camera, CameraError
from fruxel.grid import FruxelGrid
from fruxel.kernels import EMPTY_LOGIT, VolumeError

cl = pytest.importorskip("fruxel.kernels.cl")
if not cl.is_available():  # pragma: no cover - only without an OpenCL device
    pytest.skip(f"no OpenCL device: {cl.unavailable_reason()}", allow_module_level=True)
occupancy = importlib.import_module("fruxel.kernels.cl.occupancy")

GRID = FruxelGrid(width=13, height=11, depth=15, z_near=0.4, z_far=3.0, hfov=70.0)


def _scene(grid: FruxelGrid, seed: int) -> np.ndarray:
    """A few random boxes of labels 1..6 and scattered single cells: ``(D, H, W)`` uint8."""
    rng = np.random.default_rng(seed)
    lab = np.zeros(grid.shape, np.uint8)
    dims = np.array(grid.shape)
    for _ in range(5):
        lo = rng.integers(0, dims)
        size = rng.integers(1, np.maximum(2, dims // 3))
        lab[lo[0]:lo[0] + size[0], lo[1]:lo[1] + size[1], lo[2]:lo[2] + size[2]] = rng.integers(1, 7)
    lab[rng.random(grid.shape) < 0.01] = 5
    return lab


def _cameras(grid: FruxelGrid) -> list[Camera]:
    """Outside front-left-above, behind the apex, inside the frustum, looking back at it, and the own view."""
    c = grid.centre()
    return [
        Camera.look_at(c + np.array([-2.0, -1.5, -2.5]), c, width=40, height=32),
        Camera.look_at(np.array([0.1, -0.05, -1.0]), c + np.array([0.2, 0.1, 0.0]), width=36, height=30, hfov=50),
        Camera.look_at(c + np.array([0.05, 0.02, -0.3]), c + np.array([0.5, 0.3, 1.0]), width=30, height=30, hfov=90),
        Camera.look_at(c + np.array([0.3, 0.2, 3.0]), c, width=32, height=28),
        grid.camera(),
    ]


def _param_coords(grid: FruxelGrid, p: np.ndarray) -> np.ndarray:
    """Continuous ``(fk, fj, fi)`` of grid-frame points ``(..., 3)``: integers are cell planes."""
    with np.errstate(divide="ignore", invalid="ignore"):
        fi = (p[..., 0] / p[..., 2] + grid.tu) / grid.du
        fj = (p[..., 1] / p[..., 2] + grid.tv) / grid.dv
    fk = (p[..., 2] - grid.z_near) / grid.dz
    return np.stack([fk, fj, fi], axis=-1)


def _brute_first_hit(lab: np.ndarray, grid: FruxelGrid, cam: Camera, step: float) -> tuple[np.ndarray, ...]:
    """First occupied sample along each ray, sampled every ``step`` in t (depth) from 0 to past the far plane.

    Returns ``(h, w)`` arrays: flat cell index (-1 none) and t of that sample (inf none).
    """
    o, d = cam.rays()
    o, d = o.reshape(-1, 3), d.reshape(-1, 3)
    t_max = np.linalg.norm(cam.position - grid.centre()) + np.linalg.norm(grid.bounds()[1] - grid.bounds()[0])
    ts = np.arange(step / 2, t_max, step)
    cell = np.full(len(o), -1, np.int64)
    t_hit = np.full(len(o), np.inf)
    dims = np.array(grid.shape)
    for chunk in np.array_split(np.arange(len(ts)), max(1, len(ts) // 400)):
        p = o[:, None, :] + ts[None, chunk, None] * d[:, None, :]
        f = _param_coords(grid, p)
        inside = (p[..., 2] > 0) & np.all((f >= 0) & (f < dims), axis=-1)
        idx = np.where(inside[..., None], np.floor(np.nan_to_num(f)), 0).astype(np.int64)
        occ = inside & (lab[idx[..., 0], idx[..., 1], idx[..., 2]] != 0)
        first = np.argmax(occ, axis=1)
        new = occ.any(axis=1) & (cell < 0)
        k, j, i = (idx[new, first[new], a] for a in range(3))
        cell[new] = (k * grid.height + j) * grid.width + i
        t_hit[new] = ts[chunk][first[new]]
    return cell.reshape(cam.height, cam.width), t_hit.reshape(cam.height, cam.width)


@pytest.mark.parametrize("seed", [0, 1])
def test_first_hit_matches_dense_sampling(seed: int) -> None:
    lab = _scene(GRID, seed)
    step = 2e-3
    for cam in _cameras(GRID):
        hits = cl.first_hit(lab, GRID, cam)
        cell, t_b = _brute_first_hit(lab, GRID, cam, step)
        o, d = cam.rays()
        hit = hits.cell >= 0
        assert hits.label.dtype == np.int32 and hits.cell.dtype == np.int64
        assert hits.depth.dtype == np.float32 and hits.normal.shape == (cam.height, cam.width, 3)
        # Every sampled hit is found, no later than the sample (the kernel may find a grazed cell first).
        assert np.all(hit[cell >= 0])
        assert np.all(hits.depth[cell >= 0] <= t_b[cell >= 0] + 1e-5 * (1 + t_b[cell >= 0]))
        # Misses and hits carry the documented fill values and labels.
        assert np.all(hits.label[~hit] == 0) and np.all(hits.depth[~hit] == 0) and np.all(hits.normal[~hit] == 0)
        flat = lab.reshape(-1)
        assert np.all(hits.label[hit] == flat[hits.cell[hit]]) and np.all(flat[hits.cell[hit]] != 0)
        # The reported entry point lies in (the closure of) the reported cell.
        p = o[hit] + hits.depth[hit, None].astype(np.float64) * d[hit]
        k, j, i = GRID.unflatten(hits.cell[hit])
        f = _param_coords(GRID, p)
        lo = np.stack([k, j, i], axis=-1)
        assert np.all((f >= lo - 1e-3) & (f <= lo + 1 + 1e-3))
        # Same cell as the sampling, except for rays through edges or grazing slivers (a small share).
        both = hit & (cell >= 0)
        assert np.mean(hits.cell[both] != cell[both]) <= 0.02
        # Normals: unit, facing the camera.
        n = hits.normal[hit].astype(np.float64)
        assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
        assert np.all(np.einsum("ij,ij->i", n, d[hit]) < 0)


@pytest.mark.parametrize("width", [37, 64])
def test_skipping_is_exactly_the_plain_loop(monkeypatch: pytest.MonkeyPatch, width: int) -> None:
    """The field's distances only skip: without them (every iteration a plain step), with short jumps and with the
    default ones, every output is bit-identical. Width 64 takes the field's vector path, 37 its general one."""
    grid = FruxelGrid(width=width, height=21, depth=45, z_near=0.3, z_far=6.0, hfov=80.0)
    lab = _scene(grid, 7)
    lab[:, :, 30:] = 0
    cams = _cameras(grid)[:4]
    results = {}
    for cap in (0, 2, occupancy.DIST_CAP):
        monkeypatch.setattr(occupancy, "DIST_CAP", cap)
        results[cap] = [cl.first_hit(lab, grid, cam) for cam in cams]
        shells = cl.shell(lab, grid, cams)
        if cap == 0:
            plain_shell = shells
        np.testing.assert_array_equal(shells, plain_shell)
    for cap in (2, occupancy.DIST_CAP):
        for a, b in zip(results[0], results[cap], strict=True):
            for name in ("label", "cell", "depth", "normal"):
                np.testing.assert_array_equal(getattr(a, name), getattr(b, name))


@pytest.mark.parametrize(("shape", "wide"), [((45, 21, 64), False), ((9, 13, 37), False), ((4, 3, 2), False),
                                           ((45, 21, 64), True)])
def test_field_is_the_chessboard_distance_and_the_masks(monkeypatch: pytest.MonkeyPatch,
                                                        shape: tuple[int, int, int], wide: bool) -> None:
    """The walk's field (occupancy.build_field) against scipy's chessboard distance transform of the occupied 2 x 2
    x 2 groups, capped, and each group's mask against its cells; two batch items (the vector path for width 64, the
    general one otherwise). Cells at the grid's far corners and edges check that the field's padding reads as
    empty to the passes. ``wide``: the passes with 64-bit offsets (used from 2^31 elements)."""
    ndimage = pytest.importorskip("scipy.ndimage")
    import pyopencl

    from fruxel.kernels.cl.runtime import get_runtime
    from fruxel.kernels.inputs import inspect_volume

    if wide:
        monkeypatch.setattr(occupancy, "PASS_WIDE_FROM", 0)
    d, h, w = shape
    grid = FruxelGrid(width=w, height=h, depth=d, z_near=0.3, z_far=6.0, hfov=80.0)
    rng = np.random.default_rng(3)
    lab = np.zeros((2, *grid.shape), np.uint8)
    lab[0][rng.random(grid.shape) < 0.002] = 4
    lab[0, d // 2, h // 3, w // 3] = 1
    lab[1, -1, -1, -1] = 2
    lab[1, 0, 0, :] = 3
    rt = get_runtime(None)
    with rt.lock:
        vol = occupancy.labels_from_host(rt, lab, inspect_volume(lab, grid), grid)
        raw = np.empty(occupancy.field_elements(grid, 2), np.uint16)
        pyopencl.enqueue_copy(rt.queue, raw, vol.field)
    gd = occupancy.field_layout(grid)
    field = raw.reshape(2, gd[2], gd[1], gd[0])
    gw = -(-w // 2)
    for b in range(2):
        cells = np.zeros((gd[2] * 2, (gd[1] - 1) * 2, gw * 2), bool)
        cells[:d, :h, :w] = lab[b] != 0
        # (z, y, x) in the group flattened is 4 z + 2 y + x: the mask's bit of that cell
        weights = 1 << np.arange(8)
        bits = cells.reshape(gd[2], 2, gd[1] - 1, 2, gw, 2).transpose(0, 2, 4, 1, 3, 5).reshape(gd[2], gd[1] - 1, gw, 8)
        mask = (bits * weights).sum(-1)
        occ = mask != 0
        want = ndimage.distance_transform_cdt(~occ, metric="chessboard") if occ.any() else np.full(occ.shape, 999)
        got = field[b, :, :-1, :gw]
        np.testing.assert_array_equal(got >> 8, np.minimum(want, occupancy.DIST_CAP))
        # the mask's bits of cells past the grid are free (never read): compare those of cells inside it
        inside = np.zeros(cells.shape, bool)
        inside[:d, :h, :w] = True
        ibits = inside.reshape(gd[2], 2, gd[1] - 1, 2, gw, 2).transpose(0, 2, 4, 1, 3, 5).reshape(gd[2], gd[1] - 1,
                                                                                                 gw, 8)
        valid = (ibits * weights).sum(-1)
        np.testing.assert_array_equal(got & valid, mask)


def test_both_walk_widths_agree(monkeypatch: pytest.MonkeyPatch) -> None:
    """The walk traces 16 rays per work-item where the compiler targets AVX-512 and 8 elsewhere: both give the same
    bits. Only the narrower width is tried besides the native one (a wider one is what PoCL 3.0 mishandles)."""
    from fruxel.kernels.cl.runtime import get_runtime

    rt = get_runtime(None)
    if rt.lanes == 8:
        pytest.skip("the device's native width is the narrower one")
    grid = FruxelGrid(width=37, height=22, depth=45, z_near=0.3, z_far=6.0, hfov=80.0)
    lab = _scene(grid, 9)
    cams = _cameras(grid)
    native = [cl.first_hit(lab, grid, cam) for cam in cams]
    native_shell = cl.shell(lab, grid, cams)
    monkeypatch.setattr(rt, "lanes", 8)
    for cam, a in zip(cams, native, strict=True):
        b = cl.first_hit(lab, grid, cam)
        for name in ("label", "cell", "depth", "normal"):
            np.testing.assert_array_equal(getattr(a, name), getattr(b, name))
    np.testing.assert_array_equal(cl.shell(lab, grid, cams), native_shell)


def test_shell_is_the_union_of_first_hits() -> None:
    lab = np.stack([_scene(GRID, 3), _scene(GRID, 4)]).astype(np.int16)
    cams = _cameras(GRID)
    out = cl.shell(lab, GRID, cams)
    assert out.dtype == lab.dtype and out.shape == lab.shape
    for b in range(2):
        keep = np.zeros(GRID.n_cells, bool)
        for cam in cams:
            c = cl.first_hit(lab[b], GRID, cam).cell
            keep[c[c >= 0]] = True
        np.testing.assert_array_equal(out[b], np.where(keep.reshape(GRID.shape), lab[b], 0))


def test_own_view_shell_keeps_the_first_cell_of_each_column() -> None:
    lab = _scene(GRID, 5)
    out = cl.shell(lab, GRID, GRID.camera())
    occ = lab != 0
    first = np.argmax(occ, axis=0)
    keep = (np.arange(GRID.depth)[:, None, None] == first[None]) & occ.any(axis=0)[None]
    np.testing.assert_array_equal(out, np.where(keep, lab, 0))


@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
@pytest.mark.parametrize(("threshold", "probs"), [(None, False), (0.4, False), (0.4, True)])
def test_scores(dtype: type, threshold: float | None, probs: bool) -> None:
    rng = np.random.default_rng(0)
    logits = rng.normal(size=(2, 4, *GRID.shape))
    logits[:, 0] += 1.5
    scores = np.exp(logits) / np.exp(logits).sum(axis=1, keepdims=True) if probs else logits
    scores = scores.astype(dtype)
    s = scores.astype(np.float64)
    if threshold is None:
        occ = np.argmax(s, axis=1) != 0
    else:
        p0 = s[:, 0] if probs else np.exp(s[:, 0]) / np.exp(s).sum(axis=1)
        occ = 1 - p0 >= threshold
    labels = np.where(occ, 1 + np.argmax(s[:, 1:], axis=1), 0)
    own = GRID.camera()
    hits = cl.first_hit(scores, GRID, own, threshold=threshold, probs=probs)
    for b in range(2):
        np.testing.assert_array_equal(hits.label[b], cl.first_hit(labels[b], GRID, own).label)
    out = cl.shell(scores, GRID, own, threshold=threshold, probs=probs)
    kept = cl.shell(labels, GRID, own) != 0
    empty = np.array([1.0, 0, 0, 0] if probs else [0.0] + [EMPTY_LOGIT] * 3, dtype)[None, :, None, None, None]
    assert out.dtype == scores.dtype
    np.testing.assert_array_equal(out, np.where(kept[:, None], scores, empty))


def test_torch_in_torch_out() -> None:
    torch = pytest.importorskip("torch")
    lab = _scene(GRID, 2)
    cam = _cameras(GRID)[0]
    ref = cl.first_hit(lab, GRID, cam)
    hits = cl.first_hit(torch.from_numpy(lab.astype(np.int64)), GRID, cam)
    assert isinstance(hits.cell, torch.Tensor) and hits.cell.shape == (cam.height, cam.width)
    np.testing.assert_array_equal(hits.cell.numpy(), ref.cell)
    logits = torch.randn(1, 3, *GRID.shape, dtype=torch.bfloat16)
    out = cl.shell(logits, GRID, [cam, GRID.camera()])
    assert out.dtype == torch.bfloat16 and out.shape == logits.shape


def test_bad_input_raises_before_device_work(monkeypatch: pytest.MonkeyPatch) -> None:
    def no_device(*_: object) -> None:
        raise AssertionError("device work started before validation")

    for name in ("first_hit", "shell"):
        monkeypatch.setattr(importlib.import_module(f"fruxel.kernels.cl.{name}"), "get_runtime", no_device)
    lab = _scene(GRID, 0)
    cam = GRID.camera()
    with pytest.raises(VolumeError, match="shape"):
        cl.first_hit(lab[:-1], GRID, cam)
    with pytest.raises(VolumeError, match="dtype"):
        cl.first_hit(lab.astype(np.complex64), GRID, cam)
    with pytest.raises(VolumeError, match="NaN"):
        bad = np.zeros((1, 2, *GRID.shape), np.float32)
        bad[0, 1, 3, 4, 5] = np.nan
        cl.shell(bad, GRID, cam)
    with pytest.raises(VolumeError, match="threshold"):
        cl.first_hit(lab, GRID, cam, threshold=0.5)
    with pytest.raises(VolumeError, match="camera"):
        cl.shell(lab, GRID, [])
    with pytest.raises(VolumeError, match="channels"):
        cl.first_hit(np.zeros((1, 300, *GRID.shape), np.float16), GRID, cam)
    pose = np.eye(4)
    pose[0, 0] = 2.0
    with pytest.raises(CameraError):
        Camera(fx=10, fy=10, cx=5, cy=5, width=10, height=10, pose=pose)


def test_device_names() -> None:
    assert cl.resolve_device(None) is None
    assert cl.resolve_device("cpu") == "cpu"
    assert cl.resolve_device("cuda:0") in ("gpu", "cpu")
    assert not cl.cuda_available()
    with pytest.raises(ValueError, match="device"):
        cl.resolve_device("tpu")

"""Quick checks of the Warp backend against an independent brute force (dense float64 sampling along each ray),
plus array kinds, batches, scores, the shell's paths and input errors.

The cross-backend suite (test_first_hit.py, test_shell.py) checks the backends against the traversal reference;
this file stands alone: its oracle shares no code with any traversal. It runs on the Warp CPU device and, where
present, on CUDA.
"""

from __future__ import annotations

import numpy as np
import pytest

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid
from fruxel.kernels import EMPTY_LOGIT, VolumeError, first_hit, orbit_cameras, shell
from fruxel.kernels.registry import BackendError

pytest.importorskip("warp")
torch = pytest.importorskip("torch")

from fruxel.kernels.wp.runtime import warp  # noqa: E402 - after the skips: needs warp

wp = warp()
DEVICES = [d for d, ok in (("cpu", wp.is_cpu_available()), ("cuda", wp.get_cuda_device_count() > 0)) if ok]
"""Warp devices that can run kernels here (Warp without its CPU compiler runs CUDA only)."""

GRID = FruxelGrid(width=14, height=10, depth=16, z_near=0.5, z_far=3.0, hfov=60.0)
STEP = 1e-3
"""Sampling step of the brute force along t (metres of camera depth; the smallest cell is ~0.05 m)."""
SLACK = 3
"""Samples of slack around the brute force's answer: a ray may graze a cell for less than a step."""


def scene(seed: int = 0) -> np.ndarray:
    """A ``(D, H, W)`` uint8 volume: a floor, a back wall and a few boxes, labels 1..5."""
    rng = np.random.default_rng(seed)
    d, h, w = GRID.shape
    lab = np.zeros(GRID.shape, np.uint8)
    lab[:, h - 2 :, :] = 2
    lab[d - 2 :, :, :] = 1
    for label in range(3, 6):
        k, j, i = rng.integers(2, d - 5), rng.integers(2, h - 5), rng.integers(1, w - 5)
        lab[k : k + rng.integers(2, 5), j : j + rng.integers(2, 4), i : i + rng.integers(2, 5)] = label
    return lab


def cameras() -> list[Camera]:
    """Views from outside (two orbit poses, one from behind the apex) and one from inside the frustum."""
    c = GRID.centre()
    return [
        *orbit_cameras(GRID, 2, width=24, height=18),
        Camera.look_at([0.3, -0.2, -0.8], c, width=20, height=16),
        Camera.look_at(c + [0.1, -0.3, -0.4], c + [0.4, 0.6, 1.0], width=20, height=16, hfov=90.0),
    ]


def brute_force(lab: np.ndarray, cam: Camera) -> np.ndarray:
    """Occupancy along every pixel's ray, sampled every ``STEP`` from t = 0 to past the far corner.

    Returns:
        ``(R, S)`` bool: sample s of pixel r (row-major) lies in an occupied cell.
    """
    o, d = cam.rays()
    far = float(np.linalg.norm(GRID.bounds() - cam.position, axis=1).max()) * 2.0
    t = np.arange(0.0, far, STEP)
    kji = GRID.point_to_cell(o.reshape(-1, 1, 3) + t[None, :, None] * d.reshape(-1, 1, 3))
    inside = kji[..., 0] >= 0
    flat = (kji[..., 0] * GRID.height + kji[..., 1]) * GRID.width + kji[..., 2]
    return inside & (lab.reshape(-1)[np.where(inside, flat, 0)] != 0)


def check_hits(hits: dict[str, np.ndarray], lab: np.ndarray, cam: Camera) -> None:
    """The kernel's hits agree with the brute force: nothing occupied before the hit, the ray in the hit cell just
    past the hit depth (up to rounding at cell edges), a miss only where the ray meets no occupied cell (up to
    ``SLACK`` samples), and the hit's label and normal consistent."""
    occ = brute_force(lab, cam)
    cell = hits["cell"].reshape(-1)
    depth = hits["depth"].reshape(-1).astype(np.float64)
    label = hits["label"].reshape(-1)
    normal = hits["normal"].reshape(-1, 3).astype(np.float64)
    d = cam.rays()[1].reshape(-1, 3)
    hit = cell >= 0
    for r in np.flatnonzero(~hit):
        assert occ[r].sum() <= SLACK, f"pixel {r}: a miss, but the ray crosses occupied cells"
        assert label[r] == 0 and depth[r] == 0 and not normal[r].any()
    o = cam.position
    for r in np.flatnonzero(hit):
        s = int(round(depth[r] / STEP))
        assert not occ[r, : max(0, s - SLACK)].any(), f"pixel {r}: occupied cells before the hit at t={depth[r]}"
        # Just past the entry point the ray is in the hit cell, up to rounding at the cell's edges.
        p = o + (depth[r] + 0.5 * STEP) * d[r]
        f = np.array([(p[2] - GRID.z_near) / GRID.dz, (p[1] / p[2] + GRID.tv) / GRID.dv,
                      (p[0] / p[2] + GRID.tu) / GRID.du])
        kji = np.array(np.unravel_index(cell[r], GRID.shape))
        outside = np.maximum(kji - f, f - (kji + 1)).max()
        assert outside < 0.05, f"pixel {r}: at t={depth[r]} the ray is {outside} cells away from cell {cell[r]}"
        assert label[r] == lab.reshape(-1)[cell[r]] != 0
    n = normal[hit]
    np.testing.assert_allclose(np.linalg.norm(n, axis=1), 1.0, atol=1e-5)
    assert np.all(np.einsum("ij,ij->i", n, d[hit]) < 0), "normals must face the camera"


def np_hits(h: object) -> dict[str, np.ndarray]:
    return {f: np.asarray(getattr(h, f).cpu() if hasattr(getattr(h, f), "cpu") else getattr(h, f))
            for f in ("label", "cell", "depth", "normal")}


@pytest.mark.parametrize("device", DEVICES)
def test_first_hit_matches_brute_force(device: str) -> None:
    lab = scene()
    for cam in [*cameras(), GRID.camera()]:
        h = first_hit(lab, GRID, cam, backend="warp", device=device)
        assert h.label.dtype == np.int32 and h.cell.dtype == np.int64 and h.depth.dtype == np.float32
        assert h.label.shape == (cam.height, cam.width) and h.normal.shape == (cam.height, cam.width, 3)
        check_hits(np_hits(h), lab, cam)


@pytest.mark.parametrize("device", DEVICES)
def test_prepared_launches_follow_buffers_shapes_and_evictions(device: str, monkeypatch: pytest.MonkeyPatch) -> None:
    # Prepared launch commands keep their descriptors between calls: every call must still read its own volume
    # and write its own outputs, across image sizes (new commands) and with a cache of one command (evictions).
    from fruxel.kernels.wp import arrays

    vols = [scene(seed) for seed in range(3)]
    cams = [cameras()[0], cameras()[2]]  # 24 x 18 and 20 x 16: different launch dimensions
    assert (cams[0].width, cams[0].height) != (cams[1].width, cams[1].height)
    fresh = {(v, c): np_hits(first_hit(vols[v], GRID, cams[c], backend="warp", device=device))
             for v in range(3) for c in range(2)}
    for cache_size in (arrays._COMMAND_CACHE_SIZE, 1):
        monkeypatch.setattr(arrays, "_COMMAND_CACHE_SIZE", cache_size)
        arrays.prepared_launches().clear()
        for v, c in [(0, 0), (1, 1), (2, 0), (0, 1), (1, 0), (2, 1)]:
            got = np_hits(first_hit(vols[v], GRID, cams[c], backend="warp", device=device))
            for name, ref in fresh[(v, c)].items():
                np.testing.assert_array_equal(got[name], ref, err_msg=f"{name} of volume {v}, camera {c}")
    assert len(arrays.prepared_launches()) <= 1


@pytest.mark.parametrize("device", DEVICES)
def test_torch_batches_and_scores(device: str) -> None:
    """Torch in, torch out on the caller's device; a batch equals its items; scores equal their labels."""
    labs = np.stack([scene(0), scene(1)])
    cam = cameras()[0]
    tl = torch.from_numpy(labs).to(torch.int64)
    tl = tl.to(device) if device == "cuda" else tl
    hb = first_hit(tl, GRID, cam, backend="warp", device=device)
    assert isinstance(hb.cell, torch.Tensor) and hb.cell.device == tl.device and hb.cell.dtype == torch.int64
    assert hb.label.shape == (2, cam.height, cam.width) and hb.normal.shape == (2, cam.height, cam.width, 3)
    for b in range(2):
        hu = np_hits(first_hit(labs[b], GRID, cam, backend="warp", device=device))
        for f, v in np_hits(hb).items():
            np.testing.assert_array_equal(v[b], hu[f], err_msg=f)

    # Scores whose argmax is the label, and probabilities thresholded to the same occupancy.
    rng = np.random.default_rng(5)
    logits = rng.normal(size=(2, 6, *GRID.shape)).astype(np.float32)
    logits += 8.0 * np.moveaxis(np.eye(6, dtype=np.float32)[labs], -1, 1)
    e = np.exp(logits - logits.max(1, keepdims=True))
    probs = (e / e.sum(1, keepdims=True)).astype(np.float64)
    ref = np_hits(hb)
    for vol, kw in ((logits, {}), (logits.astype(np.float16), {}), (probs, {"threshold": 0.5, "probs": True})):
        got = np_hits(first_hit(vol, GRID, cam, backend="warp", device=device, **kw))
        for f in ("label", "cell"):
            np.testing.assert_array_equal(got[f], ref[f], err_msg=f"{vol.dtype} {kw} {f}")


@pytest.mark.parametrize("device", DEVICES)
def test_shell_paths(device: str) -> None:
    """The own-view fast path keeps each column's first occupied cell; the general path keeps exactly the first hits
    of every pixel; mixed lists take the union; scores keep or become the canonical empty cell."""
    labs = np.stack([scene(0), scene(2)])
    own = GRID.camera()
    cams = cameras()[:2]
    occ = labs != 0
    first = np.argmax(occ, axis=1)
    want_own = np.where((np.arange(GRID.depth)[None, :, None, None] == first[:, None]) & occ.any(1)[:, None], labs, 0)
    np.testing.assert_array_equal(shell(labs, GRID, own, backend="warp", device=device), want_own)

    keep = np.zeros(labs.shape, bool)
    for b in range(2):
        for cam in cams:
            c = np_hits(first_hit(labs[b], GRID, cam, backend="warp", device=device))["cell"]
            keep[b].reshape(-1)[c[c >= 0]] = True
    want = np.where(keep, labs, 0)
    np.testing.assert_array_equal(shell(labs, GRID, cams, backend="warp", device=device), want)
    mixed = shell(labs.astype(np.int16), GRID, [own, *cams], backend="warp", device=device)
    assert mixed.dtype == np.int16
    np.testing.assert_array_equal(mixed, np.where(keep | (want_own != 0), labs, 0))

    rng = np.random.default_rng(3)
    logits = torch.from_numpy(rng.normal(size=(2, 4, *GRID.shape)).astype(np.float32))
    logits[:, 0] -= 3.0 * torch.from_numpy(labs != 0).float() - 1.5
    logits = logits.to(device) if device == "cuda" else logits
    occ_s = (logits.argmax(1) != 0).cpu().numpy()
    for cam_list, path in (([own], "own view"), (cams, "general")):
        out = shell(logits, GRID, cam_list, backend="warp", device=device)
        assert isinstance(out, torch.Tensor) and out.device == logits.device and out.dtype == logits.dtype
        kept = shell(torch.from_numpy(occ_s.astype(np.uint8)), GRID, cam_list, backend="warp", device=device) != 0
        kept = kept.numpy()
        o, x = out.cpu().numpy(), logits.cpu().numpy()
        np.testing.assert_array_equal(np.moveaxis(o, 1, -1)[kept], np.moveaxis(x, 1, -1)[kept], err_msg=path)
        removed = np.moveaxis(o, 1, -1)[~kept]
        assert np.all(removed[:, 0] == 0) and np.all(removed[:, 1:] == np.float32(EMPTY_LOGIT)), path
    probs = torch.softmax(logits.double(), 1)
    out = shell(probs, GRID, own, backend="warp", device=device, threshold=0.5, probs=True).cpu().numpy()
    removed = np.moveaxis(out, 1, -1)[np.moveaxis(out, 1, -1)[..., 0] == 1.0]
    assert removed.size and np.all(removed[:, 1:] == 0)


@pytest.mark.parametrize("device", DEVICES)
def test_centre_out_rows_are_a_permutation(device: str) -> None:
    """The trace kernel's row order visits every row once, middle first, for odd and even heights."""
    from fruxel.kernels.wp.first_hit import centre_out

    @wp.kernel
    def rows_kernel(h: int, out: wp.array(dtype=wp.int32)):
        r = wp.tid()
        out[r] = centre_out(r, h)

    for h in (1, 2, 3, 8, 17, 512):
        out = wp.zeros(h, dtype=wp.int32, device=device)
        wp.launch(rows_kernel, (h,), [h, out], device=device)
        rows = out.numpy()
        assert sorted(rows.tolist()) == list(range(h)), h
        assert rows[0] == h // 2 and np.all(np.diff(np.abs(rows - (h - 1) / 2)) >= 0), h


@pytest.mark.parametrize("device", DEVICES)
def test_batches_split_across_launches(device: str, monkeypatch: pytest.MonkeyPatch) -> None:
    """A batch too large for one launch of int32 thread indices runs as several (here: one item per launch, as
    if each image had 2^31 pixels) and gives what one launch gives."""
    from fruxel.kernels.wp import traverse

    vols = np.stack([scene(seed) for seed in range(3)])
    cam = cameras()[0]
    whole = np_hits(first_hit(vols, GRID, cam, backend="warp", device=device))
    monkeypatch.setattr(traverse, "MAX_LAUNCH", cam.width * cam.height + 1)
    split = np_hits(first_hit(vols, GRID, cam, backend="warp", device=device))
    for name, ref in whole.items():
        np.testing.assert_array_equal(split[name], ref, err_msg=name)
    assert (whole["cell"][0] != whole["cell"][2]).any()


@pytest.mark.parametrize("device", DEVICES)
def test_pyramid_word_path_equals_byte_path(device: str) -> None:
    """The pyramid read four cells per word (the CUDA path when W % 4 == 0) flags exactly what the byte path
    flags, partial blocks and super-blocks included; layouts the word path cannot read fall back to bytes."""
    from fruxel.kernels.wp import occupancy
    from fruxel.kernels.wp.arrays import Workspace, compute_device
    from fruxel.kernels.wp.traverse import grid_info, pyramid_size

    grid = FruxelGrid(width=20, height=18, depth=37, z_near=0.5, z_far=3.0, hfov=60.0)
    rng = np.random.default_rng(3)
    vol = (rng.random((2, *grid.shape)) < 0.002).astype(np.uint8) * rng.integers(1, 5, (2, *grid.shape), np.uint8)
    vol[1, 36, 17, 19] = 3  # the last cell: the partial last block and super-block of every axis
    t = torch.from_numpy(vol).to("cuda" if device == "cuda" else "cpu")
    ws = Workspace.like(t, compute_device(t, device))
    labels = ws.input(t, shape=(2, grid.n_cells), dtype=wp.uint8)
    g = grid_info(grid)
    byte = ws.empty((2, pyramid_size(grid)), wp.uint8, zero=True)
    ws.launch(occupancy.build_pyramid_kernel, (2, grid.depth, grid.height, g.blocks_u), [labels, g, 1, byte])
    words = occupancy.label_words(labels, grid)
    assert words is not None and words.shape == (2 * grid.n_cells // 4,)
    word = ws.empty((2, pyramid_size(grid)), wp.uint8, zero=True)
    ws.launch(occupancy.build_pyramid_words_kernel, words.shape, [words, g, word])
    want, got = byte.native.cpu().numpy(), word.native.cpu().numpy()
    assert 0 < want.sum() < want.size
    np.testing.assert_array_equal(got, want)
    # W % 4 != 0, or labels one byte off a word boundary: no word view.
    odd = ws.input(torch.zeros(GRID.shape, dtype=torch.uint8, device=t.device), shape=(1, GRID.n_cells),
                   dtype=wp.uint8)
    assert occupancy.label_words(odd, GRID) is None
    flat = t.reshape(-1)[1 : 1 + grid.n_cells]
    shifted = ws.input(flat, shape=(1, grid.n_cells), dtype=wp.uint8)
    assert shifted.ptr % 4 == 1 and occupancy.label_words(shifted, grid) is None
    if device == "cpu":  # numpy labels (Warp holds a numpy caller's data on CUDA): the byte path
        as_numpy = Workspace.like(vol, "cpu").input(vol, shape=(2, grid.n_cells), dtype=wp.uint8)
        assert isinstance(as_numpy.native, np.ndarray) and occupancy.label_words(as_numpy, grid) is None


def test_bad_input_raises_before_work() -> None:
    lab = scene()
    cam = cameras()[0]
    bad = [
        (lab[:, :, :-1], {}),  # wrong shape
        (lab.astype(np.complex64), {}),  # wrong dtype
        (lab.astype(np.int32) * 300, {}),  # labels beyond uint8
        (np.full((1, 3, *GRID.shape), np.nan, np.float32), {}),  # NaN scores
        (np.zeros((1, 3, *GRID.shape), np.float32), {"threshold": 1.5}),  # threshold outside (0, 1]
        (lab, {"threshold": 0.5}),  # threshold on labels
    ]
    for vol, kw in bad:
        with pytest.raises(VolumeError):
            first_hit(vol, GRID, cam, backend="warp", **kw)
    with pytest.raises(VolumeError):
        shell(lab, GRID, [], backend="warp")
    with pytest.raises(VolumeError):
        first_hit(lab, GRID, [cam, cam], backend="warp")
    with pytest.raises(BackendError):
        first_hit(lab, GRID, cam, backend="warp", device="tpu")

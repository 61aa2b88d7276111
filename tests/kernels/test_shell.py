"""shell (VMS) on every backend: a subset of the volume that keeps every camera's first hits, the own-view column
rule, scores, batches, array kinds, and the orbit poses it is built from (conventions section 4)."""

from __future__ import annotations

import numpy as np
import pytest

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid
from fruxel.kernels import EMPTY_LOGIT, orbit_cameras

from .conftest import (
    BACKENDS,
    EDGE_TOL,
    first_hit,
    hits_numpy,
    random_camera,
    random_grid,
    random_labels,
    scores_from_labels,
    shell,
    to_numpy,
)
from .reference import near_edge, ref_first_hit, ref_labels_from_scores, ref_own_view_shell, ref_shell


def _views(rng: np.random.Generator, grid: FruxelGrid, labels: np.ndarray) -> list[Camera]:
    cams = [random_camera(rng, grid, kind, labels) for kind in ("front", "beside", "inside", "behind_apex")]
    return cams + orbit_cameras(grid, 2, width=36, height=28)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("seed", range(3))
def test_shell_keeps_exactly_the_first_hits(backend: str, seed: int) -> None:
    """The shell is a subset of the volume with the same labels, every camera sees the same first hits in it,
    and it keeps a cell exactly when some pixel's first hit is that cell (up to rays through cell edges)."""
    rng = np.random.default_rng(200 + seed)
    grid = random_grid(rng)
    labels = random_labels(rng, grid)
    cams = _views(rng, grid, labels)
    kept = shell(backend, labels, grid, cams)
    assert isinstance(kept, np.ndarray) and kept.dtype == labels.dtype and kept.shape == labels.shape
    assert np.all((kept == 0) | (kept == labels)), "shell changed a label"
    assert 0 < np.count_nonzero(kept) < np.count_nonzero(labels)

    seen = np.zeros(grid.n_cells, bool)
    robust = np.zeros(grid.n_cells, bool)
    for n, cam in enumerate(cams):
        full = hits_numpy(first_hit(backend, labels, grid, cam))
        thin = hits_numpy(first_hit(backend, kept, grid, cam))
        seen[full["cell"][full["cell"] >= 0]] = True
        ref = ref_first_hit(labels, grid, cam)
        flag = near_edge(grid, cam, EDGE_TOL, until=np.where(ref["cell"] >= 0, ref["depth"], np.inf))
        robust[ref["cell"][(ref["cell"] >= 0) & ~flag]] = True
        mism = (full["cell"] != thin["cell"]) | (full["label"] != thin["label"])
        assert not (mism & ~flag).any(), f"view {n}: first hits through the shell differ away from edges"
        assert mism.sum() <= 0.005 * mism.size
        same = ~mism & (full["cell"] >= 0)
        np.testing.assert_allclose(thin["depth"][same], full["depth"][same], rtol=1e-6, atol=1e-7)
    kept_set = kept.reshape(-1) != 0
    assert np.all(kept_set[robust]), "a cell that is a pixel's first hit (away from edges) was removed"
    extra = kept_set & ~seen
    assert not extra.any(), f"{extra.sum()} kept cells are no pixel's first hit"


@pytest.mark.parametrize("backend", BACKENDS)
def test_shell_matches_reference_shell(backend: str) -> None:
    """The shell keeps every cell the reference keeps through a ray away from edges, and differs from the
    reference's shell by no more cells than there are rays near edges."""
    rng = np.random.default_rng(210)
    grid = random_grid(rng, small=True)
    labels = random_labels(rng, grid, 0.3)
    cams = [random_camera(rng, grid, kind, labels, size=(24, 18)) for kind in ("front", "far_side", "above")]
    kept = shell(backend, labels, grid, cams).reshape(-1) != 0
    want = ref_shell(labels, grid, cams).reshape(-1) != 0
    robust = np.zeros(grid.n_cells, bool)
    n_flagged = 0
    for cam in cams:
        ref = ref_first_hit(labels, grid, cam)
        flag = near_edge(grid, cam, EDGE_TOL, until=np.where(ref["cell"] >= 0, ref["depth"], np.inf))
        robust[ref["cell"][(ref["cell"] >= 0) & ~flag]] = True
        n_flagged += int(flag.sum())
    assert robust.sum() > 10
    assert np.all(kept[robust]), "a cell some ray hits away from edges was removed"
    assert np.count_nonzero(kept != want) <= n_flagged


@pytest.mark.parametrize("backend", BACKENDS)
def test_own_view_shell_is_first_cell_per_column(backend: str) -> None:
    """From the grid's own camera the shell is the first occupied cell of each column (fast path), and the
    general traversal with a camera that is the own camera up to a tiny pose change gives the same."""
    rng = np.random.default_rng(220)
    grid = FruxelGrid(13, 10, 12, z_near=0.5, z_far=4.0, hfov=70.0)
    labels = np.stack([random_labels(rng, grid, occ) for occ in (0.05, 0.2, 0.4)])
    labels[1, :, 2, 3] = 0  # an empty column
    want = ref_own_view_shell(labels)
    own = grid.camera()
    np.testing.assert_array_equal(shell(backend, labels, grid, own), want)
    nudged = np.eye(4)
    nudged[:3, 3] = [1e-7, -1e-7, -1e-6]
    general = own.with_pose(nudged)
    np.testing.assert_array_equal(shell(backend, labels, grid, general), want)
    for b in range(3):
        np.testing.assert_array_equal(shell(backend, labels[b], grid, [own]), want[b])


def test_reference_own_view_shell_agrees_with_traversal() -> None:
    """The two reference routes (column argmax, and traversal from the own camera) agree."""
    rng = np.random.default_rng(221)
    for _ in range(3):
        grid = random_grid(rng)
        labels = random_labels(rng, grid)
        np.testing.assert_array_equal(ref_shell(labels, grid, [grid.camera()]), ref_own_view_shell(labels))


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("dtype", [np.float16, np.float32, np.float64])
@pytest.mark.parametrize("probs", [False, True], ids=["logits", "probs"])
def test_shell_of_scores(backend: str, dtype: type, probs: bool) -> None:
    """Scores keep their values in kept cells; removed cells become the canonical empty cell."""
    rng = np.random.default_rng(230)
    grid = random_grid(rng, small=True)
    labels = np.stack([random_labels(rng, grid, 0.3) for _ in range(2)])
    scores = scores_from_labels(rng, labels, 7, dtype, probs)
    cams = [grid.camera(), random_camera(rng, grid, "beside", size=(24, 18))]
    want_labels = shell(backend, labels, grid, cams)
    out = shell(backend, scores, grid, cams, probs=probs)
    assert isinstance(out, np.ndarray) and out.dtype == scores.dtype and out.shape == scores.shape
    np.testing.assert_array_equal(ref_labels_from_scores(out), want_labels)
    keep = np.broadcast_to((want_labels != 0)[:, None], scores.shape)
    np.testing.assert_array_equal(out[keep], scores[keep])
    removed = np.moveaxis(out, 1, -1)[(want_labels == 0)]
    assert removed.shape[0] > 0
    if probs:
        np.testing.assert_array_equal(removed[:, 0], 1)
        np.testing.assert_array_equal(removed[:, 1:], 0)
    else:
        np.testing.assert_array_equal(removed[:, 0], 0)
        np.testing.assert_array_equal(removed[:, 1:], dtype(EMPTY_LOGIT))
        z = removed.astype(np.float32)
        e = np.exp(z - z.max(axis=-1, keepdims=True))
        assert np.all(e[:, 0] / e.sum(axis=-1) == 1), "p(empty) of a removed cell is not 1 in float32"


@pytest.mark.parametrize("backend", BACKENDS)
def test_shell_of_scores_with_threshold(backend: str) -> None:
    rng = np.random.default_rng(240)
    grid = random_grid(rng, small=True)
    labels = random_labels(rng, grid, 0.3)[None]
    scores = scores_from_labels(rng, labels, 7, np.float32)
    threshold = 0.2
    thr_labels = ref_labels_from_scores(scores, threshold).astype(np.uint8)
    assert np.count_nonzero(thr_labels) > np.count_nonzero(labels)
    cam = random_camera(rng, grid, "front", size=(24, 18))
    out = shell(backend, scores, grid, [cam], threshold=threshold)
    want = shell(backend, thr_labels, grid, [cam])
    np.testing.assert_array_equal(np.moveaxis(out, 1, -1)[want != 0], np.moveaxis(scores, 1, -1)[want != 0])
    assert np.all(np.argmax(out, axis=1)[want == 0] == 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_shell_batched_equals_items(backend: str) -> None:
    rng = np.random.default_rng(250)
    grid = random_grid(rng)
    labels = np.stack([random_labels(rng, grid) for _ in range(3)])
    cams = [random_camera(rng, grid, k, size=(24, 18)) for k in ("front", "far_side")]
    batch = shell(backend, labels, grid, cams)
    for b in range(3):
        np.testing.assert_array_equal(batch[b], shell(backend, labels[b], grid, cams), err_msg=f"item {b}")
    assert not np.array_equal(batch[0], batch[1])


@pytest.mark.parametrize("backend", BACKENDS)
def test_shell_torch_in_torch_out(backend: str) -> None:
    torch = pytest.importorskip("torch")
    rng = np.random.default_rng(260)
    grid = random_grid(rng, small=True)
    labels = random_labels(rng, grid, 0.3)[None]
    scores = scores_from_labels(rng, labels, 7, np.float32)
    cams = [grid.camera(), random_camera(rng, grid, "front", size=(20, 16))]
    for vol in (labels, scores):
        want = shell(backend, vol, grid, cams)
        got = shell(backend, torch.from_numpy(vol), grid, cams)
        assert isinstance(got, torch.Tensor) and got.device.type == "cpu"
        assert got.dtype == torch.from_numpy(vol).dtype and tuple(got.shape) == vol.shape
        np.testing.assert_array_equal(to_numpy(got), want)
    bf16 = shell(backend, torch.from_numpy(scores).to(torch.bfloat16), grid, cams)
    assert isinstance(bf16, torch.Tensor) and bf16.dtype == torch.bfloat16 and tuple(bf16.shape) == scores.shape
    np.testing.assert_array_equal(ref_labels_from_scores(bf16.float().numpy()), shell(backend, labels, grid, cams))


@pytest.mark.parametrize("layout", ["orbit", "sphere"])
@pytest.mark.parametrize("m", [1, 6, 9])
def test_orbit_cameras_look_at_the_grid_and_see_all_of_it(layout: str, m: int) -> None:
    """With the default radius and field of view (square images), every camera sees all 8 grid corners."""
    grid = FruxelGrid(20, 14, 16, z_near=0.4, z_far=5.0, hfov=80.0)
    cams = orbit_cameras(grid, m, layout=layout, width=64, height=64)
    assert len(cams) == m
    centre = grid.centre()
    corners = grid.corner_points(
        np.array([0, 0, 0, 0, 1, 1, 1, 1]) * grid.depth, np.array([0, 0, 1, 1] * 2) * grid.height,
        np.array([0, 1] * 4) * grid.width,
    )
    positions = []
    for cam in cams:
        c = cam.project(centre)
        assert c[2] > 0
        np.testing.assert_allclose(c[:2], [cam.cx, cam.cy], atol=1e-6)
        p = cam.project(corners)
        assert np.all(p[:, 2] > 0), "a grid corner is behind the camera"
        assert np.all((p[:, 0] >= 0) & (p[:, 0] <= cam.width) & (p[:, 1] >= 0) & (p[:, 1] <= cam.height)), (
            "a grid corner is outside the image")
        positions.append(cam.position)
    assert len({tuple(np.round(p, 9)) for p in positions}) == m

"""Shared helpers of the kernel tests: the backend list, dispatch, random scenes and cameras, and the checks.

Tests are parametrised over :data:`BACKENDS`: every name of :func:`fruxel.kernels.available_backends` (ids are
those names, usable directly as ``backend=``) plus ``"reference"``, a test-only pseudo-backend that wraps the
numpy reference of :mod:`.reference` in the kernels' calling convention (validation, batches, scores, torch in
and out). Running the suite against the reference alone checks the reference against the independent oracles
(per-cell clipping, the triangle-mesh ray caster) before any backend exists.

A backend whose operation module cannot be imported yet is skipped with the import error as the reason.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np
import pytest

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid
from fruxel.kernels import EMPTY_LOGIT, Hits, available_backends
from fruxel.kernels import first_hit as _kernels_first_hit
from fruxel.kernels import shell as _kernels_shell
from fruxel.kernels.inputs import check_cameras, inspect_volume, is_torch
from fruxel.kernels.registry import get_backend, split_name

from .reference import (
    brute_first_hit_bounds,
    cell_param_bounds,
    clip_param_box,
    near_edge,
    ref_first_hit,
    ref_labels_from_scores,
)

REFERENCE = "reference"
"""Name of the test-only numpy pseudo-backend."""


def _real_backends() -> list[str]:
    # A half-written backend may raise anything on import; the suite must still collect.
    try:
        return list(available_backends())
    except Exception:  # noqa: BLE001
        return []


REAL_BACKENDS = _real_backends()
"""Backends found by the registry, fastest first."""
BACKENDS = REAL_BACKENDS + [REFERENCE]
"""What the tests are parametrised over."""

EDGE_TOL = 1e-4
"""Cell units: pixels whose ray passes this close to a cell edge may legitimately differ from the reference."""
MAX_EDGE_FRACTION = 0.005
"""At most this fraction of a random view's pixels may differ from the reference (all of them near edges)."""
DEPTH_RTOL, DEPTH_ATOL = 1e-4, 1e-5
NORMAL_ATOL = 1e-3


# ---------------------------------------------------------------------------------------------- dispatch


def _require(backend: str, op: str) -> None:
    base, _ = split_name(backend)
    try:
        getattr(get_backend(base), op)
    except (ImportError, AttributeError) as e:
        pytest.skip(f"{backend}.{op} is not importable yet: {e}")


def first_hit(backend: str, volume: Any, grid: FruxelGrid, camera: Camera, **kw: Any) -> Hits:
    """``fruxel.kernels.first_hit`` on ``backend``, or the reference pseudo-backend."""
    if backend == REFERENCE:
        return reference_first_hit(volume, grid, camera, **kw)
    _require(backend, "first_hit")
    return _kernels_first_hit(volume, grid, camera, backend=backend, **kw)


def shell(backend: str, volume: Any, grid: FruxelGrid, cameras: Any, **kw: Any) -> Any:
    """``fruxel.kernels.shell`` on ``backend``, or the reference pseudo-backend."""
    if backend == REFERENCE:
        return reference_shell(volume, grid, cameras, **kw)
    _require(backend, "shell")
    return _kernels_shell(volume, grid, cameras, backend=backend, **kw)


def to_numpy(x: Any) -> np.ndarray:
    """A numpy copy of a numpy array or torch tensor (bfloat16, which numpy lacks, as float32)."""
    if is_torch(x):
        x = x.detach().cpu()
        return (x.float() if str(x.dtype) == "torch.bfloat16" else x).numpy()
    return np.asarray(x)


def hits_numpy(h: Hits) -> dict[str, np.ndarray]:
    """The four fields of :class:`Hits` as numpy arrays."""
    return {f: to_numpy(getattr(h, f)) for f in ("label", "cell", "depth", "normal")}


def _volume_labels(volume: Any, threshold: float | None, probs: bool, is_scores: bool) -> np.ndarray:
    arr = to_numpy(volume)
    if is_scores:
        return ref_labels_from_scores(arr, threshold, probs)
    return arr.astype(np.int64)


def reference_first_hit(
    volume: Any, grid: FruxelGrid, camera: Camera, *, threshold: float | None = None, probs: bool = False
) -> Hits:
    """The reference in the kernels' calling convention (see :func:`fruxel.kernels.first_hit`)."""
    spec = inspect_volume(volume, grid, threshold, probs)
    (camera,) = check_cameras(camera)
    lab = _volume_labels(volume, threshold, probs, spec.is_scores)
    if not spec.batched:
        lab = lab[None]
    res = [ref_first_hit(x, grid, camera) for x in lab]
    out = {
        "label": np.stack([r["label"] for r in res]).astype(np.int32),
        "cell": np.stack([r["cell"] for r in res]).astype(np.int64),
        "depth": np.stack([r["depth"] for r in res]).astype(np.float32),
        "normal": np.stack([r["normal"] for r in res]).astype(np.float32),
    }
    if not spec.batched:
        out = {k: v[0] for k, v in out.items()}
    if spec.kind == "torch":
        import torch

        out = {k: torch.from_numpy(np.ascontiguousarray(v)) for k, v in out.items()}
    return Hits(**out)


def reference_shell(
    volume: Any, grid: FruxelGrid, cameras: Any, *, threshold: float | None = None, probs: bool = False
) -> Any:
    """The reference shell in the kernels' calling convention (see :func:`fruxel.kernels.shell`)."""
    spec = inspect_volume(volume, grid, threshold, probs)
    cams = check_cameras(cameras)
    lab = _volume_labels(volume, threshold, probs, spec.is_scores)
    if lab.ndim == 3:
        lab = lab[None]
    keep = np.zeros(lab.shape, bool)
    for b in range(lab.shape[0]):
        for cam in cams:
            c = ref_first_hit(lab[b], grid, cam)["cell"]
            keep[b].reshape(-1)[c[c >= 0]] = True
    arr = to_numpy(volume).copy()
    if spec.is_scores:
        removed = np.broadcast_to(~keep[:, None], arr.shape)
        empty = np.zeros(arr.shape[1], arr.dtype)
        empty[0] = 1 if probs else 0
        empty[1:] = 0 if probs else EMPTY_LOGIT
        arr = np.where(removed, empty[None, :, None, None, None], arr)
    else:
        arr = np.where(keep.reshape(arr.shape), arr, 0).astype(arr.dtype)
    if spec.kind == "torch":
        import torch

        return torch.from_numpy(np.ascontiguousarray(arr)).to(volume.dtype)
    return arr


# ---------------------------------------------------------------------------------------------- scenes


def random_grid(rng: np.random.Generator, small: bool = False) -> FruxelGrid:
    """A grid with W != H and random depth range and field of view."""
    lo, hi = (3, 9) if small else (5, 17)
    w = int(rng.integers(lo, hi))
    h = int(rng.integers(lo, hi))
    while h == w:
        h = int(rng.integers(lo, hi))
    d = int(rng.integers(lo, hi))
    z_near = float(rng.uniform(0.2, 1.5))
    return FruxelGrid(w, h, d, z_near=z_near, z_far=z_near + float(rng.uniform(1.0, 6.0)),
                      hfov=float(rng.uniform(25.0, 130.0)))


def random_labels(rng: np.random.Generator, grid: FruxelGrid, occupancy: float | None = None) -> np.ndarray:
    """``(D, H, W)`` uint8 labels 1..6 at random cells, occupancy 5-40% unless given."""
    occ = float(rng.uniform(0.05, 0.4)) if occupancy is None else occupancy
    lab = rng.integers(1, 7, size=grid.shape).astype(np.uint8)
    lab[rng.random(grid.shape) >= occ] = 0
    return lab


def random_intrinsics_camera(rng: np.random.Generator, pose: np.ndarray, size: tuple[int, int] = (40, 30),
                             hfov: float | None = None) -> Camera:
    """A camera with ``fx != fy`` and an off-centre principal point (``size`` is ``(width, height)``)."""
    w, h = size
    hf = float(rng.uniform(35.0, 100.0)) if hfov is None else hfov
    f = w / (2 * math.tan(math.radians(hf) / 2))
    return Camera(fx=f * float(rng.uniform(0.85, 1.15)), fy=f * float(rng.uniform(0.85, 1.15)),
                  cx=w / 2 + float(rng.uniform(-0.2, 0.2)) * w, cy=h / 2 + float(rng.uniform(-0.2, 0.2)) * h,
                  width=w, height=h, pose=pose)


def _point_in_cell(rng: np.random.Generator, grid: FruxelGrid, k: int, j: int, i: int) -> np.ndarray:
    """A random point well inside cell (k, j, i) (parameters 0.2..0.8 of the cell), grid frame."""
    a, b, c = rng.uniform(0.2, 0.8, 3)
    z = grid.z_near + (k + a) * grid.dz
    return np.array([(-grid.tu + (i + b) * grid.du) * z, (-grid.tv + (j + c) * grid.dv) * z, z])


def random_point_in_frustum(rng: np.random.Generator, grid: FruxelGrid) -> np.ndarray:
    """A random point well inside some cell of the grid."""
    return _point_in_cell(rng, grid, *(int(rng.integers(n)) for n in grid.shape))


CAMERA_KINDS = ("front", "inside", "inside_occupied", "behind_apex", "beside", "far_side", "above", "away")
"""Kinds of random viewpoint; ``away`` looks away from the grid, so every ray misses."""


def random_camera(rng: np.random.Generator, grid: FruxelGrid, kind: str, labels: np.ndarray | None = None,
                  size: tuple[int, int] = (40, 30)) -> Camera:
    """A random camera of one of :data:`CAMERA_KINDS`, with random intrinsics (``fx != fy``, off-centre)."""
    c = grid.centre()
    ext = grid.bounds()[1] - grid.bounds()[0]
    r = float(np.linalg.norm(ext))
    target = random_point_in_frustum(rng, grid)
    if kind == "front":
        eye = c + np.array([rng.uniform(-0.5, 0.5) * ext[0], rng.uniform(-0.5, 0.5) * ext[1], 0.0])
        eye[2] = float(rng.uniform(-0.5, 0.6)) * grid.z_near
    elif kind == "inside":
        eye = random_point_in_frustum(rng, grid)
    elif kind == "inside_occupied":
        occ = np.argwhere(labels != 0)
        eye = _point_in_cell(rng, grid, *occ[rng.integers(len(occ))])
    elif kind == "behind_apex":
        eye = np.array([rng.uniform(-0.2, 0.2), rng.uniform(-0.2, 0.2), -rng.uniform(0.2, 2.0)]) * r
        target = c + rng.normal(size=3) * 0.2 * r
    elif kind == "beside":
        side = np.array([rng.choice([-1.0, 1.0]), rng.uniform(-0.3, 0.3), 0.0])
        eye = c + side * (0.6 + rng.uniform(0, 1)) * r
        eye[2] = c[2] + rng.uniform(-0.3, 0.3) * ext[2]
        target = c - side * r + rng.normal(size=3) * 0.1 * r
    elif kind == "far_side":
        eye = c + np.array([rng.uniform(-0.3, 0.3), rng.uniform(-0.3, 0.3), rng.uniform(0.7, 1.5)]) * r
    elif kind == "above":
        eye = c + np.array([rng.uniform(-0.3, 0.3), -rng.uniform(0.7, 1.5), rng.uniform(-0.3, 0.3)]) * r
    elif kind == "away":
        out = rng.normal(size=3)
        out /= np.linalg.norm(out)
        eye = c + out * 1.6 * r
        target = eye + out
    else:
        raise ValueError(kind)
    up = (0.0, -1.0, 0.0) if kind != "above" else (0.0, 0.0, 1.0)
    pose = Camera.look_at(eye, target, up=up).pose
    # A little roll, so that image rows are not parallel to the grid's rows.
    roll = float(rng.uniform(-0.3, 0.3))
    rz = np.array([[math.cos(roll), -math.sin(roll), 0], [math.sin(roll), math.cos(roll), 0], [0, 0, 1]])
    pose = pose.copy()
    pose[:3, :3] = pose[:3, :3] @ rz
    hfov = 50.0 if kind == "away" else None
    return random_intrinsics_camera(rng, pose, size, hfov)


def lattice_camera(grid: FruxelGrid, eye: Any, k: int) -> Camera:
    """A camera at ``eye`` whose ``(W + 1) x (H + 1)`` pixel rays pass through the lattice points of plane z_k.

    Pixel ``(x, y)`` aims at the corner ``(u_i z_k, v_j z_k, z_k)`` with ``j = y`` and ``i = x`` (looking along
    +z, ``eye`` in front of the plane) or ``i = W - x`` (looking along -z, rotated 180 degrees about y). From
    the apex every ray lies in a u-plane and a v-plane at once, i.e. runs along a cell edge.
    """
    eye = np.asarray(eye, dtype=np.float64)
    zk = grid.z_bounds()[k]
    sz = 1.0 if eye[2] < zk else -1.0
    t = (zk - eye[2]) / sz
    i = np.arange(grid.width + 1) if sz > 0 else grid.width - np.arange(grid.width + 1)
    a = (grid.u_bounds()[i] * zk - eye[0]) / (t * sz)
    b = (grid.v_bounds() * zk - eye[1]) / t
    fx, fy = 1.0 / (a[1] - a[0]), 1.0 / (b[1] - b[0])
    pose = np.eye(4)
    pose[:3, :3] = np.diag([sz, 1.0, sz])
    pose[:3, 3] = eye
    return Camera(fx=fx, fy=fy, cx=0.5 - a[0] * fx, cy=0.5 - b[0] * fy, width=grid.width + 1,
                  height=grid.height + 1, pose=pose)


def scores_from_labels(rng: np.random.Generator, labels: np.ndarray, channels: int, dtype: Any,
                       probs: bool = False) -> np.ndarray:
    """Random ``(B, C, D, H, W)`` scores whose argmax is ``labels`` ``(B, D, H, W)`` by a margin.

    Logits are normal noise with the labelled channel raised 2 above the others' maximum, so the argmax is the
    same in float16; probabilities are their softmax, computed in float64 and then cast.
    """
    noise = rng.normal(size=(labels.shape[0], channels) + labels.shape[1:])
    top = noise.max(axis=1)
    np.put_along_axis(noise, labels[:, None].astype(np.int64), (top + 2.0)[:, None], axis=1)
    if probs:
        e = np.exp(noise - noise.max(axis=1, keepdims=True))
        noise = e / e.sum(axis=1, keepdims=True)
    return noise.astype(dtype)


# ---------------------------------------------------------------------------------------------- checks


def assert_agree(hits: Hits | dict, labels: np.ndarray, grid: FruxelGrid, camera: Camera,
                 max_fraction: float | None = MAX_EDGE_FRACTION, what: str = "") -> None:
    """A backend's first hits equal the reference's, up to rays near cell edges.

    Labels and cells must be equal on every pixel not flagged by :func:`near_edge` (``EDGE_TOL``); flagged
    differences may be at most ``max_fraction`` of the pixels (None: any number, for views built to run along
    edges). Where cells agree, depths agree to ``DEPTH_RTOL``/``DEPTH_ATOL`` and, away from edges, normals to
    ``NORMAL_ATOL``. Misses have depth 0 and a zero normal.
    """
    got = hits_numpy(hits) if isinstance(hits, Hits) else hits
    ref = ref_first_hit(labels, grid, camera)
    mism = (got["label"] != ref["label"]) | (got["cell"] != ref["cell"])
    until = np.where(ref["cell"] >= 0, ref["depth"], np.inf)
    flag = near_edge(grid, camera, EDGE_TOL, until=until) if mism.any() else np.zeros(mism.shape, bool)
    bad = mism & ~flag
    if bad.any():
        ys, xs = np.nonzero(bad)
        ex = [(int(y), int(x), int(ref["cell"][y, x]), int(got["cell"][y, x]), float(ref["depth"][y, x]),
               float(got["depth"][y, x])) for y, x in zip(ys[:5], xs[:5], strict=True)]
        raise AssertionError(f"{what}: {bad.sum()} of {bad.size} pixels differ from the reference away from cell "
                             f"edges; (y, x, ref cell, cell, ref depth, depth): {ex}; camera {camera!r}")
    if max_fraction is not None:
        assert mism.sum() <= max_fraction * mism.size, (
            f"{what}: {mism.sum()} of {mism.size} pixels (all near edges) differ from the reference")
    same = ~mism & (ref["cell"] >= 0)
    np.testing.assert_allclose(got["depth"][same], ref["depth"][same], rtol=DEPTH_RTOL, atol=DEPTH_ATOL,
                               err_msg=f"{what}: depth")
    if not flag.any():
        flag = near_edge(grid, camera, EDGE_TOL, until=until)
    ok = same & ~flag
    np.testing.assert_allclose(got["normal"][ok], ref["normal"][ok], atol=NORMAL_ATOL, err_msg=f"{what}: normal")
    miss = got["cell"] < 0
    assert np.all(got["depth"][miss] == 0) and np.all(got["normal"][miss] == 0), f"{what}: miss not zeroed"
    assert np.all(got["label"][miss] == 0), f"{what}: label on a miss"
    assert_hit_normals(got, camera, what)


def assert_hit_normals(got: dict, camera: Camera, what: str = "") -> None:
    """Normals of hits are unit vectors facing the camera: ``|n| = 1`` and ``dot(n, ray) < 0``."""
    hit = got["cell"] >= 0
    _, d = camera.rays()
    n = got["normal"][hit].astype(np.float64)
    np.testing.assert_allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-4, err_msg=f"{what}: normal not unit")
    dots = np.einsum("ij,ij->i", n, d[hit] / np.linalg.norm(d[hit], axis=-1, keepdims=True))
    assert np.all(dots < 1e-6), f"{what}: {np.sum(dots >= 1e-6)} normals face away from the camera"


def assert_bounds(hits: Hits | dict, labels: np.ndarray, grid: FruxelGrid, camera: Camera,
                  regions: list[tuple[float, ...]] | None = None, margin: float = 1e-3, what: str = "") -> None:
    """First hits are consistent with clipping every ray against every occupied cell (no DDA involved).

    Per pixel: a ray through the interior of an occupied cell (shrunk by ``margin`` cell units), or of one of
    the convex ``regions`` (parameter boxes ``(u_lo, u_hi, v_lo, v_hi, z_lo, z_hi)`` known to be solid, shrunk
    likewise), must hit no later than it enters there: nothing leaks through edges or corners. A hit must be an
    occupied cell that the ray touches, entered no earlier than the ray meets any occupied cell (grown by
    ``margin``), with that cell's label.
    """
    got = hits_numpy(hits) if isinstance(hits, Hits) else hits
    b = brute_first_hit_bounds(labels, grid, camera, margin)
    t_must = b["t_must"]
    if regions:
        o, d = camera.rays()
        for reg in regions:
            lo = np.array(reg, dtype=np.float64)
            span = np.array([grid.du, grid.du, grid.dv, grid.dv, grid.dz, grid.dz]) * margin
            shrunk = lo + span * np.array([1, -1, 1, -1, 1, -1])
            t_in, t_out = clip_param_box(o, d, *shrunk)
            t_must = np.minimum(t_must, np.where(t_in < t_out, t_in, np.inf))
    depth = got["depth"].astype(np.float64)
    hit = got["cell"] >= 0
    eps = DEPTH_RTOL * np.abs(depth) + DEPTH_ATOL
    leak = np.isfinite(t_must) & (~hit | (depth > t_must + eps))
    if leak.any():
        ys, xs = np.nonzero(leak)
        raise AssertionError(f"{what}: {leak.sum()} rays pass occupied space without a hit (or hit too late), e.g. "
                             f"pixel (y, x) = ({ys[0]}, {xs[0]}): must hit by t = {t_must[ys[0], xs[0]]}, got cell "
                             f"{got['cell'][ys[0], xs[0]]} at {depth[ys[0], xs[0]]}; camera {camera!r}")
    early = hit & (depth < b["t_may"] - eps)
    assert not early.any(), f"{what}: {early.sum()} hits before the ray meets any occupied cell"
    flat = labels.reshape(-1)
    cells = got["cell"][hit]
    assert np.all(flat[cells] != 0), f"{what}: a hit on an empty cell"
    np.testing.assert_array_equal(got["label"][hit], flat[cells].astype(np.int32), err_msg=f"{what}: hit label")
    col = np.searchsorted(b["cells"], cells)
    touch = b["touch"][hit, col]
    t_touch = b["t_touch"][hit, col]
    wrong = ~touch | (t_touch > depth[hit] + eps[hit])
    assert not wrong.any(), f"{what}: {wrong.sum()} hit cells that the ray does not enter at the hit depth"


def region_of_cells(grid: FruxelGrid, k0: int, k1: int, j0: int, j1: int, i0: int, i1: int) -> tuple[float, ...]:
    """Parameter box of the block of cells ``k0 <= k < k1`` (etc.), for ``assert_bounds(regions=...)``."""
    cells = np.array([[k0, j0, i0], [k1 - 1, j1 - 1, i1 - 1]])
    u_lo, u_hi, v_lo, v_hi, z_lo, z_hi = cell_param_bounds(grid, cells, 0.0)
    return (u_lo[0], u_hi[1], v_lo[0], v_hi[1], z_lo[0], z_hi[1])

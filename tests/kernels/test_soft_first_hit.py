"""soft_first_hit on every backend: exact gradients (gradcheck in float64), the own view against a pure-torch
cumprod reference, backends against each other, occupancies of exactly 0 and 1, the hard limit ``first_hit``,
bfloat16 / no_grad, camera groups and input errors (conventions section 4)."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid
from fruxel.kernels import VolumeError, soft_first_hit
from fruxel.kernels.soft import (
    SoftHits,
    own_view_entry_depths,
    soft_first_hit_groups,
    soft_first_hit_occ,
    soft_first_hit_own_view_torch,
)

from .conftest import REAL_BACKENDS, first_hit, random_camera, random_labels, to_numpy

pytestmark = pytest.mark.skipif(not REAL_BACKENDS, reason="no kernel backend is available")

GRID = FruxelGrid(width=6, height=5, depth=4, z_near=0.5, z_far=3.0, hfov=60.0)
"""Small grid of the gradient checks: its own view is 6 x 5 pixels, like the novel view."""
C = 3
"""Classes of the tests (channel 0 = empty); every test uses this one count, so Warp builds one module per
scalar type."""


def _novel(grid: FruxelGrid, size: tuple[int, int] = (6, 5)) -> Camera:
    """An oblique view from above and to the side, seeing the grid's front and side faces."""
    eye = grid.centre() + np.array([1.0, -0.8, -3.0])
    return Camera.look_at(eye, grid.centre(), width=size[0], height=size[1], hfov=50.0)


def _outputs(h: SoftHits) -> tuple[torch.Tensor, ...]:
    return h.classes, h.depth, h.depth_sum


def _checked(h: SoftHits) -> tuple[torch.Tensor, ...]:
    """The outputs gradcheck differentiates: ``depth`` depends on every kernel output (``depth_sum`` and the hit
    probability), ``classes`` on the class sums and the miss probability."""
    return h.classes, h.depth


def _weighted(outs: tuple[torch.Tensor, ...], weights: tuple[torch.Tensor, ...]) -> torch.Tensor:
    return sum((o * w).sum() for o, w in zip(outs, weights, strict=True))


def _onehot_probs(labels: np.ndarray, dtype: torch.dtype = torch.float64) -> torch.Tensor:
    """``(B, C, D, H, W)`` probabilities exactly 0 or 1 from labels ``(B, D, H, W)``."""
    return torch.from_numpy(np.moveaxis(np.eye(C)[labels], -1, 1)).to(dtype)


@pytest.mark.parametrize("backend", REAL_BACKENDS)
def test_gradcheck_float64(backend: str, poisoned_allocations: None) -> None:
    torch.manual_seed(0)
    logits = torch.randn(1, C, *GRID.shape, dtype=torch.float64, requires_grad=True)
    cams = [GRID.camera(), _novel(GRID)]
    # Rays that share a cell add into it in a thread-dependent order (OpenCL): allow rounding-level differences.
    assert torch.autograd.gradcheck(lambda x: _checked(soft_first_hit(x, GRID, cams, backend=backend)), (logits,),
                                    nondet_tol=1e-12)


@pytest.mark.parametrize("backend", REAL_BACKENDS)
def test_gradcheck_occupancy_float64(backend: str) -> None:
    torch.manual_seed(1)
    occ = (0.05 + 0.9 * torch.rand(1, *GRID.shape, dtype=torch.float64)).requires_grad_()
    cls = torch.softmax(torch.randn(1, C - 1, *GRID.shape, dtype=torch.float64), 1).requires_grad_()
    inside = Camera.look_at(GRID.centre() + np.array([0.1, 0.0, -0.3]), GRID.centre() + np.array([0.3, 0.2, 2.0]),
                            width=6, height=5, hfov=70.0)
    assert torch.autograd.gradcheck(
        lambda o, c: _checked(soft_first_hit_occ(o, c, GRID, [inside, _novel(GRID)], backend=backend)), (occ, cls),
        nondet_tol=1e-12)


@pytest.mark.parametrize("backend", REAL_BACKENDS)
@pytest.mark.parametrize("dtype", [torch.float64, torch.float32])
def test_own_view_equals_torch_cumprod(backend: str, dtype: torch.dtype) -> None:
    grid = FruxelGrid(width=7, height=5, depth=9, z_near=0.4, z_far=4.0, hfov=75.0)
    torch.manual_seed(2)
    logits = (3.0 * torch.randn(2, C, *grid.shape, dtype=dtype)).requires_grad_()
    got = soft_first_hit(logits, grid, grid.camera(), backend=backend)
    ref = soft_first_hit_own_view_torch(logits, grid)
    tol = {"atol": 1e-12, "rtol": 1e-12} if dtype == torch.float64 else {"atol": 2e-6, "rtol": 1e-5}
    if dtype == torch.float64 and "cuda" in backend:
        # Measured on an H100: float64 outputs drift from torch's cumprod by up to 9e-10 relative and gradients by
        # up to 3e-10 absolute (CPU backends agree to 1e-12). Not yet explained; see the kernel benchmark notes.
        tol = {"atol": 1e-9, "rtol": 5e-9}
    for name in ("classes", "depth", "miss", "depth_sum"):
        torch.testing.assert_close(getattr(got, name), getattr(ref, name), **tol, msg=name)
    weights = tuple(torch.randn_like(o) for o in _outputs(got))
    (g_got,) = torch.autograd.grad(_weighted(_outputs(got), weights), logits)
    (g_ref,) = torch.autograd.grad(_weighted(_outputs(ref), weights), logits)
    torch.testing.assert_close(g_got, g_ref, **tol)


@pytest.mark.skipif(not any(b.startswith("warp") for b in REAL_BACKENDS), reason="needs the Warp backend")
def test_own_view_column_kernels_equal_the_general_walk(monkeypatch: pytest.MonkeyPatch) -> None:
    # Warp runs the grid's own view on column kernels; they must visit the general walk's cells at its depths.
    backend = next(b for b in REAL_BACKENDS if b.startswith("warp"))
    torch.manual_seed(8)
    logits = 3.0 * torch.randn(2, C, *GRID.shape, dtype=torch.float64)
    logits[0, 0, 2:] -= 40.0  # saturated cells: some columns stop early
    results = []
    for columns in (True, False):
        if not columns:
            monkeypatch.setattr("fruxel.kernels.traversal.is_own_view", lambda camera, grid: False)
        x = logits.clone().requires_grad_()
        h = soft_first_hit(x, GRID, GRID.camera(), backend=backend)
        weights = tuple(torch.randn_like(o, generator=torch.Generator().manual_seed(9)) for o in _outputs(h))
        (g,) = torch.autograd.grad(_weighted(_outputs(h), weights), x)
        results.append((h, g))
    (h_col, g_col), (h_gen, g_gen) = results
    for name in ("classes", "depth", "depth_sum"):
        torch.testing.assert_close(getattr(h_col, name), getattr(h_gen, name), atol=0, rtol=0, msg=name)
    torch.testing.assert_close(g_col, g_gen, atol=1e-14, rtol=1e-12)


@pytest.mark.parametrize("backend", REAL_BACKENDS)
def test_tiny_upstream_gradients_are_kept(backend: str) -> None:
    # A ray whose only upstream gradient is tiny (its square underflows float32) still sends it back.
    torch.manual_seed(10)
    logits = torch.randn(1, C, *GRID.shape)
    cams = [GRID.camera(), _novel(GRID)]
    grads = []
    for scale in (1.0, 1e-25):
        x = logits.clone().requires_grad_()
        (g,) = torch.autograd.grad(scale * soft_first_hit(x, GRID, cams, backend=backend).classes[:, :, 1].sum(), x)
        grads.append(g.double() / scale)
    assert grads[0].abs().max() > 0
    torch.testing.assert_close(grads[1], grads[0], rtol=1e-4, atol=1e-6 * grads[0].abs().max().item())


def test_own_view_entry_depths() -> None:
    t = own_view_entry_depths(GRID)
    np.testing.assert_allclose(t, GRID.z_bounds()[:-1], rtol=1e-6)
    assert t.dtype == np.float32 and t[0] == np.float32(GRID.z_near)


@pytest.mark.skipif(len(REAL_BACKENDS) < 2, reason="needs two backends")
def test_backends_agree() -> None:
    rng = np.random.default_rng(3)
    grid = FruxelGrid(width=9, height=7, depth=8, z_near=0.5, z_far=4.0, hfov=70.0)
    labels = np.stack([random_labels(rng, grid, 0.15) for _ in range(2)])
    cams = [random_camera(rng, grid, kind, labels[0], size=(12, 10))
            for kind in ("front", "beside", "inside", "behind_apex", "far_side")]
    logits = torch.from_numpy(2.0 * rng.normal(size=(2, C, *grid.shape))).float()
    results = {}
    for backend in REAL_BACKENDS:
        x = logits.clone().requires_grad_()
        h = soft_first_hit(x, grid, cams, backend=backend)
        weights = tuple(torch.ones_like(o) for o in _outputs(h))
        (g,) = torch.autograd.grad(_weighted(_outputs(h), weights), x)
        results[backend] = (h, g)
    (h0, g0), *others = results.values()
    for h, g in others:
        for name in ("classes", "depth", "miss", "depth_sum"):
            torch.testing.assert_close(getattr(h, name), getattr(h0, name), atol=1e-5, rtol=1e-5, msg=name)
        torch.testing.assert_close(g, g0, atol=1e-4, rtol=1e-4)


@pytest.fixture
def poisoned_allocations(monkeypatch: pytest.MonkeyPatch) -> None:
    """``torch.empty_like`` returns NaN-filled tensors, so that a kernel that must write every element of an
    uninitialised output (the own view's store-mode backward) cannot pass by finding zeros there."""
    real = torch.empty_like

    def poisoned(t: torch.Tensor, **kwargs: object) -> torch.Tensor:
        out = real(t, **kwargs)
        return out.fill_(float("nan")) if out.dtype.is_floating_point else out

    monkeypatch.setattr(torch, "empty_like", poisoned)


@pytest.mark.parametrize("backend", REAL_BACKENDS)
def test_exact_zero_one_is_first_hit_with_finite_gradients(backend: str, poisoned_allocations: None) -> None:
    rng = np.random.default_rng(4)
    grid = FruxelGrid(width=8, height=6, depth=7, z_near=0.5, z_far=4.0, hfov=65.0)
    labels = np.stack([random_labels(rng, grid, 0.2) % C for _ in range(2)]).astype(np.uint8)
    cams = [grid.camera()] + [random_camera(rng, grid, kind, labels[0], size=(8, 6))
                              for kind in ("front", "beside", "inside")]
    probs = _onehot_probs(labels).requires_grad_()
    soft = soft_first_hit(probs, grid, cams, backend=backend, probs=True)
    for n, cam in enumerate(cams):
        hard = first_hit(backend, labels, grid, cam)
        lab, depth = to_numpy(hard.label), to_numpy(hard.depth)
        np.testing.assert_array_equal(to_numpy(soft.classes[:, n]), np.moveaxis(np.eye(C)[lab], -1, 1))
        hit = lab > 0
        np.testing.assert_array_equal(to_numpy(soft.depth[:, n])[hit], depth[hit])
        assert np.all(to_numpy(soft.depth[:, n])[~hit] == 0)
    weights = tuple(torch.randn_like(o) for o in _outputs(soft))
    (g,) = torch.autograd.grad(_weighted(_outputs(soft), weights), probs)
    assert torch.isfinite(g).all()
    # The own view alone (its backward writes every cell, zeros included): behind a column's first occupied cell
    # the transmittance is exactly 0, and so is every gradient there.
    own = soft_first_hit(probs, grid, grid.camera(), backend=backend, probs=True)
    (g_own,) = torch.autograd.grad(_weighted(_outputs(own), tuple(w[:, :1] for w in weights)), probs)
    first = np.argmax(labels > 0, axis=1)  # (B, H, W): the first occupied slice of each column (0 if none)
    behind = np.arange(grid.depth)[None, :, None, None] > first[:, None]
    behind &= (labels > 0).any(axis=1)[:, None]
    assert behind.any()
    assert torch.all(g_own.permute(0, 2, 3, 4, 1)[torch.from_numpy(behind)] == 0)
    # The same through the occupancy interface, with o and its class distribution at the ends of [0, 1].
    occ = (torch.from_numpy(labels) > 0).double().requires_grad_()
    cls = probs.detach()[:, 1:].clone().requires_grad_()
    soft = soft_first_hit_occ(occ, cls, grid, cams, backend=backend)
    grads = torch.autograd.grad(_weighted(_outputs(soft), weights), (occ, cls))
    assert all(torch.isfinite(x).all() for x in grads)
    assert all(torch.isfinite(o).all() for o in _outputs(soft))


@pytest.mark.parametrize("backend", REAL_BACKENDS)
def test_tends_to_first_hit(backend: str) -> None:
    rng = np.random.default_rng(5)
    grid = FruxelGrid(width=8, height=6, depth=7, z_near=0.5, z_far=4.0, hfov=65.0)
    labels = (random_labels(rng, grid, 0.2) % C)[None].astype(np.uint8)
    cams = [random_camera(rng, grid, kind, labels[0], size=(8, 6)) for kind in ("front", "above")]
    hard = [first_hit(backend, labels, grid, cam) for cam in cams]
    onehot = np.stack([np.moveaxis(np.eye(C)[to_numpy(h.label)], -1, 1) for h in hard], axis=1)
    hit = np.stack([to_numpy(h.label) > 0 for h in hard], axis=1)
    depth = np.stack([to_numpy(h.depth) for h in hard], axis=1)
    errors = []
    for scale in (4.0, 8.0, 16.0, 32.0):
        logits = torch.from_numpy(scale * np.moveaxis(np.eye(C)[labels], -1, 1))
        soft = soft_first_hit(logits, grid, cams, backend=backend)
        err = np.abs(to_numpy(soft.classes) - onehot).max()
        derr = np.abs(to_numpy(soft.depth) - depth)[hit].max()
        errors.append((err, derr))
    errs = np.array(errors)
    assert np.all(np.diff(errs[:, 0]) < 0), errs
    assert errs[-1, 0] < 1e-9 and errs[-1, 1] < 1e-6, errs


@pytest.mark.parametrize("backend", REAL_BACKENDS)
def test_bfloat16_and_no_grad(backend: str) -> None:
    torch.manual_seed(6)
    cams = [GRID.camera(), _novel(GRID)]
    logits = torch.randn(2, C, *GRID.shape).to(torch.bfloat16).requires_grad_()
    soft = soft_first_hit(logits, GRID, cams, backend=backend)
    assert soft.classes.dtype == torch.float32
    ref = soft_first_hit(logits.detach().float(), GRID, cams, backend=backend)
    torch.testing.assert_close(soft.classes, ref.classes)
    soft.classes.sum().backward()
    assert logits.grad is not None and logits.grad.dtype == torch.bfloat16
    with torch.no_grad():
        quiet = soft_first_hit(logits, GRID, cams, backend=backend)
    assert quiet.classes.grad_fn is None
    torch.testing.assert_close(quiet.classes, ref.classes)


@pytest.mark.parametrize("backend", REAL_BACKENDS)
def test_batch_camera_groups_and_kinds(backend: str) -> None:
    torch.manual_seed(7)
    logits = torch.randn(2, C, *GRID.shape, dtype=torch.float64)
    own, big = GRID.camera(), _novel(GRID, (9, 7))
    together = soft_first_hit(logits, GRID, [own, _novel(GRID)], backend=backend)
    for b in range(2):
        alone = soft_first_hit(logits[b:b + 1], GRID, _novel(GRID), backend=backend)
        torch.testing.assert_close(together.classes[b:b + 1, 1:], alone.classes, atol=1e-14, rtol=0)
    torch.testing.assert_close(together.classes.sum(2), torch.ones(2, 2, 5, 6, dtype=torch.float64))
    x = logits.clone().requires_grad_()
    g_own, g_big = soft_first_hit_groups(x, GRID, [own, [big]], backend=backend)
    assert g_own.classes.shape == (2, 1, C, 5, 6) and g_big.classes.shape == (2, 1, C, 7, 9)
    (g_joint,) = torch.autograd.grad(g_own.depth.sum() + g_big.depth.sum(), x)
    (g_a,) = torch.autograd.grad(soft_first_hit(x, GRID, own, backend=backend).depth.sum(), x)
    (g_b,) = torch.autograd.grad(soft_first_hit(x, GRID, big, backend=backend).depth.sum(), x)
    torch.testing.assert_close(g_joint, g_a + g_b, atol=1e-12, rtol=1e-12)
    # The own view twice, in a group after a novel view: the first own view writes every cell's gradient, the
    # second adds to it, and the novel view's gradient is added on top (whatever the order of the cameras).
    h_big, h_own = soft_first_hit_groups(x, GRID, [big, [own, own]], backend=backend)
    (g_twice,) = torch.autograd.grad(h_big.depth.sum() + h_own.depth.sum(), x)
    torch.testing.assert_close(g_twice, 2.0 * g_a + g_b, atol=1e-12, rtol=1e-12)
    out = soft_first_hit(logits.numpy(), GRID, own, backend=backend)
    assert isinstance(out.classes, np.ndarray)
    np.testing.assert_allclose(out.classes, together.classes[:, :1].numpy(), atol=1e-14)


def test_input_errors() -> None:
    logits = torch.zeros(1, C, *GRID.shape)
    with pytest.raises(VolumeError, match="image size"):
        soft_first_hit(logits, GRID, [GRID.camera(), _novel(GRID, (9, 7))])
    with pytest.raises(VolumeError, match="shape"):
        soft_first_hit(torch.zeros(1, C, 3, 3, 3), GRID, GRID.camera())
    with pytest.raises(VolumeError, match="C >= 2"):
        soft_first_hit(torch.zeros(1, 1, *GRID.shape), GRID, GRID.camera())
    with pytest.raises(VolumeError, match="float"):
        soft_first_hit(torch.zeros(1, C, *GRID.shape, dtype=torch.int64), GRID, GRID.camera())
    with pytest.raises(VolumeError, match="camera"):
        soft_first_hit(logits, GRID, [])
    with pytest.raises(VolumeError, match="class_probs"):
        soft_first_hit_occ(torch.zeros(1, *GRID.shape), torch.zeros(1, C - 1, 2, 2, 2), GRID, GRID.camera())


@pytest.mark.parametrize("backend", REAL_BACKENDS)
def test_unusual_numpy_layouts(backend: str) -> None:
    """numpy scores with negative strides, the other byte order or long double give the plain float64 result;
    a non-float array is refused with a VolumeError (torch itself takes none of these)."""
    logits = np.random.default_rng(3).normal(size=(1, C, *GRID.shape))
    want = soft_first_hit(logits, GRID, GRID.camera(), backend=backend).classes
    flipped = np.ascontiguousarray(logits[..., ::-1])[..., ::-1]
    assert flipped.strides[-1] < 0
    for odd in (flipped, logits.astype(np.longdouble), logits.astype(">f8")):
        got = soft_first_hit(odd, GRID, GRID.camera(), backend=backend).classes
        np.testing.assert_allclose(got, want, rtol=1e-12, atol=1e-15)
    with pytest.raises(VolumeError, match="float"):
        soft_first_hit(logits.astype(object), GRID, GRID.camera(), backend=backend)

"""Shell-aware losses: their values on hand-built inputs, the voxel cross-entropy's weighting, seeded novel poses
(checkpointed, per rank), the own-view truth, and a real optimisation of free logits towards a ground-truth volume
that must bring every term down."""

from __future__ import annotations

import dataclasses
import io
from typing import Any

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from fruxel.errors import ConfigError
from fruxel.grid import FruxelGrid
from fruxel.kernels import available_backends, first_hit, soft_first_hit
from fruxel.kernels.soft import SoftHits
from fruxel.train.losses import (
    ShellLoss,
    ShellLossConfig,
    depth_l1,
    group_by_size,
    random_poses,
    shell_cross_entropy,
    visible_weighted_voxel_ce,
)

BACKENDS = available_backends()
C = 3
"""Classes of the tests (channel 0 = empty), as in tests/kernels/test_soft_first_hit.py (one Warp module)."""


def _soft(classes: torch.Tensor, depth: torch.Tensor) -> SoftHits:
    hit = classes[:, :, 1:].sum(2)
    return SoftHits(classes=classes, depth=depth, miss=classes[:, :, 0], depth_sum=depth * hit)


def test_shell_cross_entropy_value() -> None:
    classes = torch.tensor([[0.7, 0.1], [0.2, 0.1], [0.1, 0.8]]).reshape(1, 1, 3, 1, 2)
    labels = torch.tensor([0, 2]).reshape(1, 1, 1, 2)
    soft = _soft(classes, torch.zeros(1, 1, 1, 2))
    got = shell_cross_entropy(soft, labels, eps=0.0)
    torch.testing.assert_close(got, -(torch.log(torch.tensor(0.7)) + torch.log(torch.tensor(0.8))) / 2)
    masked = shell_cross_entropy(soft, labels, eps=0.0, mask=torch.tensor([[[[False, True]]]]))
    torch.testing.assert_close(masked, -torch.log(torch.tensor(0.8)))
    torch.testing.assert_close(shell_cross_entropy(soft, labels, eps=0.0, reduction="sum"), 2 * got)
    # A confidently wrong pixel stays finite, with a gradient.
    p = torch.tensor([1.0, 0.0, 0.0]).reshape(1, 1, 3, 1, 1).requires_grad_()
    loss = shell_cross_entropy(_soft(p, torch.zeros(1, 1, 1, 1)), torch.tensor([[[[1]]]]))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(p.grad).all() and p.grad[0, 0, 1] < 0


def test_depth_l1_counts_ground_truth_hits_only() -> None:
    classes = torch.full((1, 1, C, 1, 3), 1.0 / C)
    soft = _soft(classes, torch.tensor([1.0, 2.0, 3.0]).reshape(1, 1, 1, 3))
    target = torch.tensor([1.5, 0.0, 2.0]).reshape(1, 1, 1, 3)
    mask = torch.tensor([True, False, True]).reshape(1, 1, 1, 3)
    torch.testing.assert_close(depth_l1(soft, target, mask), torch.tensor(0.75))
    torch.testing.assert_close(depth_l1(soft, target, mask, scale=0.5), torch.tensor(0.375))
    torch.testing.assert_close(depth_l1(soft, target, mask, reduction="sum"), torch.tensor(1.5))
    assert depth_l1(soft, target, torch.zeros_like(mask)) == 0


def test_visible_weighted_voxel_ce() -> None:
    torch.manual_seed(0)
    logits = torch.randn(2, C, 3, 4, 5)
    labels = torch.randint(0, C, (2, 3, 4, 5))
    shell = torch.rand(2, 3, 4, 5) < 0.3
    ce = F.cross_entropy(logits, labels, reduction="none")
    w = torch.where(shell, 2.0, 0.25)
    expect = (w * ce).sum() / w.sum()
    got = visible_weighted_voxel_ce(logits, labels, shell, weight_visible=2.0, weight_other=0.25)
    torch.testing.assert_close(got, expect)
    from_log = visible_weighted_voxel_ce(torch.log_softmax(logits, 1), labels, shell, weight_visible=2.0,
                                         weight_other=0.25, log_probs=True)
    torch.testing.assert_close(from_log, expect)
    only_shell = visible_weighted_voxel_ce(logits, labels, shell, weight_visible=1.0, weight_other=0.0)
    torch.testing.assert_close(only_shell, ce[shell].mean())


def test_random_poses_are_seeded_and_look_at_the_grid() -> None:
    grid = FruxelGrid(width=8, height=6, depth=7, z_near=0.5, z_far=4.0, hfov=60.0)
    a = random_poses(grid, 3, np.random.default_rng(1), width=16, height=12)
    b = random_poses(grid, 3, np.random.default_rng(1), width=16, height=12)
    assert [c.to_json() for c in a] == [c.to_json() for c in b]
    for cam in a:
        x, y, depth = cam.project(grid.centre())
        assert depth > 0 and abs(x - 8) < 1e-6 and abs(y - 6) < 1e-6
    groups = group_by_size([grid.camera(), *a, grid.camera()])
    assert [len(g) for g in groups] == [2, 3]


def _room(grid: FruxelGrid) -> np.ndarray:
    """``(D, H, W)`` labels: a floor (class 2) and a box (class 1) standing on it."""
    lab = np.zeros(grid.shape, np.uint8)
    lab[:, -2:, :] = 2
    lab[3:6, 3:-2, 2:6] = 1
    return lab


def _two_rooms() -> tuple[FruxelGrid, torch.Tensor]:
    """A small grid and a batch of two label volumes: :func:`_room` and its mirror image."""
    grid = FruxelGrid(width=10, height=8, depth=9, z_near=0.5, z_far=4.0, hfov=60.0)
    return grid, torch.from_numpy(np.stack([_room(grid), np.flip(_room(grid), axis=2).copy()]))


def _random_logits(grid: FruxelGrid, seed: int) -> torch.Tensor:
    """``(2, C, D, H, W)`` float64 standard-normal logits from ``torch.manual_seed(seed)``."""
    torch.manual_seed(seed)
    return torch.randn(2, C, *grid.shape, dtype=torch.float64)


def _optimise(grid: FruxelGrid, labels: torch.Tensor, config: ShellLossConfig, steps: int) -> tuple[Any, ...]:
    """Adam on free logits (seeded) against ``labels``; returns the logits, the loss, the first call's terms and
    the cameras of that first call."""
    torch.manual_seed(0)
    logits = torch.randn(labels.shape[0], C, *grid.shape, requires_grad=True)
    loss = ShellLoss(grid, config)
    fixed = loss.cameras()
    opt = torch.optim.Adam([logits], lr=0.2)
    first = None
    for _ in range(steps):
        terms = loss(logits, labels)
        opt.zero_grad()
        terms.total.backward()
        opt.step()
        first = first or terms
    return logits.detach(), loss, first, fixed


@pytest.mark.skipif(not BACKENDS, reason="no kernel backend is available")
def test_shell_terms_alone_train_the_visible_surface() -> None:
    # Without the voxel term every gradient comes from soft_first_hit's backward pass: a wrong one fails here.
    grid, labels = _two_rooms()
    config = ShellLossConfig(novel_views=2, novel_size=(16, 12), seed=3, weight_voxel=0.0)
    logits, loss, first, fixed = _optimise(grid, labels, config, 25)
    final = loss(logits, labels, fixed)
    assert final.shell_ce < 0.05 * first.shell_ce.item()
    assert final.depth < 0.2 * first.depth.item()
    pred = logits.argmax(1).to(torch.uint8)
    for cam in fixed:
        agree = (first_hit(pred, grid, cam).label == first_hit(labels, grid, cam).label).double().mean()
        assert agree > 0.97, (cam, agree)
    assert len(final.cameras) == 3 and final.cameras[0] == grid.camera()


@pytest.mark.skipif(not BACKENDS, reason="no kernel backend is available")
def test_optimisation_brings_every_term_down() -> None:
    grid = FruxelGrid(width=10, height=8, depth=9, z_near=0.5, z_far=4.0, hfov=60.0)
    labels = torch.from_numpy(_room(grid)[None])
    config = ShellLossConfig(novel_views=1, novel_size=(16, 12), seed=4)
    logits, loss, first, fixed = _optimise(grid, labels, config, 15)
    final = loss(logits, labels, fixed)
    assert final.total < 0.3 * first.total.item()
    for name in ("shell_ce", "depth", "voxel"):
        assert getattr(final, name) < 0.5 * getattr(first, name).item(), name


@pytest.mark.skipif(not BACKENDS, reason="no kernel backend is available")
def test_shell_loss_terms_equal_the_loss_functions() -> None:
    # ShellLoss pools every camera group's pixels and normalises once; its terms must be the public losses',
    # summed over the groups and normalised over all of them, and its total their weighted sum.
    grid, labels = _two_rooms()
    logits = _random_logits(grid, 5)
    config = ShellLossConfig(novel_views=2, novel_size=(16, 12), seed=6, weight_visible=2.0, weight_other=0.25,
                             weight_shell=0.5, weight_depth=3.0, weight_voxel=0.7)
    loss = ShellLoss(grid, config)
    cams = loss.cameras()
    terms = loss(logits, labels, cams)
    targets = loss.targets(labels, cams)
    pairs = list(zip([soft_first_hit(logits, grid, g) for g in group_by_size(cams)], targets.groups, strict=True))
    pixels = sum(t[0].numel() for _, t in pairs)
    hits = sum(int(t[2].sum()) for _, t in pairs)
    ce = sum(shell_cross_entropy(h, t[0], eps=config.eps, reduction="sum") for h, t in pairs) / pixels
    depth = sum(depth_l1(h, t[1], t[2], reduction="sum") for h, t in pairs) / hits / (grid.z_far - grid.z_near)
    voxel = visible_weighted_voxel_ce(logits, labels, targets.shell_mask, weight_visible=2.0, weight_other=0.25)
    torch.testing.assert_close(terms.shell_ce, ce)
    torch.testing.assert_close(terms.depth, depth)
    torch.testing.assert_close(terms.voxel, voxel)
    torch.testing.assert_close(terms.total, 0.5 * ce + 3.0 * depth + 0.7 * voxel)


@pytest.mark.skipif(not BACKENDS, reason="no kernel backend is available")
def test_own_view_term_is_the_own_columns_first_hit_cross_entropy() -> None:
    # The own camera's pixel (x, y) looks down column (y, x): its expected first-hit class is, along the column,
    # sum_d p_c(d) prod_{d' < d} p_0(d') (channel 0: the product over every cell, a miss). A reference of its own.
    grid, labels = _two_rooms()
    logits = _random_logits(grid, 7)
    base = ShellLossConfig(novel_views=2, novel_size=(16, 12), seed=8, weight_shell=0.5, weight_voxel=0.7)
    plain = ShellLoss(grid, base)
    cams = plain.cameras()
    weighted = ShellLoss(grid, dataclasses.replace(base, weight_own_view=2.5))(logits, labels, cams)
    terms = plain(logits, labels, cams)
    assert terms.own_view is None
    p = torch.softmax(logits, dim=1)
    before = torch.cumprod(torch.cat([torch.ones_like(p[:, :1, :1]), p[:, :1, :-1]], dim=2), dim=2)
    expected = (p * before).sum(2)  # (B, C, H, W): first occupied cell's class
    expected[:, 0] = p[:, 0].prod(1)
    truth = torch.from_numpy(np.asarray(first_hit(labels, grid, grid.camera()).label)).long()
    ref = -torch.log(expected.gather(1, truth.unsqueeze(1)) + base.eps).mean()
    torch.testing.assert_close(weighted.own_view, ref)
    torch.testing.assert_close(weighted.total, terms.total + 2.5 * ref)
    # Without the own camera there is nothing to weight: the settings refuse the weight.
    with pytest.raises(ConfigError, match="weight_own_view needs loss.shell_losses.own_view"):
        dataclasses.replace(base, own_view=False, weight_own_view=2.5)
    novel_only = ShellLoss(grid, dataclasses.replace(base, own_view=False))
    assert novel_only(logits, labels, novel_only.cameras()).own_view is None


def test_loss_arguments_are_checked() -> None:
    soft = _soft(torch.full((1, 1, C, 1, 2), 1.0 / C), torch.ones(1, 1, 1, 2))
    labels = torch.zeros(1, 1, 1, 2, dtype=torch.long)
    with pytest.raises(ValueError, match="reduction"):
        shell_cross_entropy(soft, labels, reduction="none")
    with pytest.raises(ValueError, match="bool"):
        shell_cross_entropy(soft, labels, mask=torch.ones(1, 1, 1, 2))
    with pytest.raises(ValueError, match="bool"):
        depth_l1(soft, torch.ones(1, 1, 1, 2), torch.ones(1, 1, 1, 2, dtype=torch.uint8))
    with pytest.raises(ValueError, match="reduction"):
        depth_l1(soft, torch.ones(1, 1, 1, 2), torch.ones(1, 1, 1, 2, dtype=torch.bool), reduction="max")
    # A masked-out pixel whose probability is exactly 0 (eps 0) counts for nothing, gradient included.
    p = torch.tensor([0.0, 1.0, 0.0, 0.5, 0.5, 0.0]).reshape(1, 1, C, 1, 2).requires_grad_()
    loss = shell_cross_entropy(_soft(p, torch.ones(1, 1, 1, 2)), torch.tensor([[[[1, 0]]]]), eps=0.0,
                               mask=torch.tensor([[[[False, True]]]]))
    loss.backward()
    assert torch.isfinite(loss) and torch.isfinite(p.grad).all() and torch.all(p.grad[..., 0] == 0)


@pytest.mark.parametrize("backend", BACKENDS)
def test_own_view_truth_is_the_first_occupied_cell(backend: str) -> None:
    # The one source of own-view truth (labels -> first_hit) is what the data sets' users get from ShellTargets:
    # per column the label of its first occupied cell and that cell's near plane z_k, 0 for an empty column.
    grid = FruxelGrid(width=7, height=5, depth=9, z_near=0.5, z_far=5.0, hfov=60.0)
    rng = np.random.default_rng(0)
    labels = ((rng.uniform(size=(2, *grid.shape)) < 0.15) * rng.integers(1, C, size=(2, *grid.shape))).astype(np.uint8)
    labels[0, :, 0, 0] = 0
    loss = ShellLoss(grid, ShellLossConfig(novel_views=1, novel_size=(16, 12), backend=backend))
    novel, own = loss.cameras()[1], grid.camera()
    shifted = np.eye(4)
    shifted[0, 3] = 0.1
    beside = own.with_pose(shifted)
    # The own view is found wherever it is among the cameras, also behind another camera of its size.
    for cams in ([own, novel], [novel, own], [novel, beside, own]):
        lab, depth, hit = loss.targets(torch.from_numpy(labels), cams).own_view
        assert lab.shape == depth.shape == hit.shape == (2, 5, 7) and depth.dtype == torch.float32
        zb = grid.z_bounds()
        for b, j, i in np.ndindex(2, 5, 7):
            ks = np.flatnonzero(labels[b, :, j, i])
            if len(ks) == 0:
                assert lab[b, j, i] == 0 and depth[b, j, i] == 0 and not hit[b, j, i]
            else:
                assert lab[b, j, i] == labels[b, ks[0], j, i] and hit[b, j, i]
                assert float(depth[b, j, i]) == pytest.approx(zb[ks[0]], rel=1e-6)
    assert loss.targets(torch.from_numpy(labels), [novel]).own_view is None


def test_novel_poses_are_checkpointed_and_differ_per_rank() -> None:
    grid = FruxelGrid(width=8, height=6, depth=7, z_near=0.5, z_far=4.0, hfov=60.0)
    config = ShellLossConfig(novel_views=2, novel_size=(16, 12), seed=11)

    def poses(loss: ShellLoss, n: int) -> list[str]:
        return [c.to_json() for _ in range(n) for c in loss.cameras()[1:]]

    a = ShellLoss(grid, config)
    first = poses(a, 2)
    assert len(set(first)) == 4, "every draw must give new poses"
    state = a.state_dict()
    following = poses(a, 3)
    # Through a checkpoint as a training loop writes it: torch.save, torch.load(weights_only=True).
    buf = io.BytesIO()
    torch.save({"shell_loss": state}, buf)
    buf.seek(0)
    loaded = torch.load(buf, weights_only=True)["shell_loss"]
    b = ShellLoss(grid, config)
    b.load_state_dict(loaded)
    assert poses(b, 3) == following
    # Other ranks draw other poses from the same state, each rank its own stream; the own view stays first.
    r1 = ShellLoss(grid, config, rank=1)
    assert r1.cameras()[0] == grid.camera()
    r1.load_state_dict(loaded)
    on_rank_1 = poses(r1, 3)
    assert set(on_rank_1).isdisjoint(following)
    fresh = ShellLoss(grid, config, rank=1)
    poses(fresh, 2)
    assert poses(fresh, 3) == on_rank_1 and fresh.state_dict() == r1.state_dict() == a.state_dict()
    assert set(poses(ShellLoss(grid, config, rank=2), 2)).isdisjoint(poses(ShellLoss(grid, config, rank=1), 2))
    # Another seed, another stream; a state of another seed is refused.
    other = ShellLoss(grid, ShellLossConfig(novel_views=2, novel_size=(16, 12), seed=12))
    assert set(poses(other, 2)).isdisjoint(first)
    with pytest.raises(ValueError, match="seed 11"):
        other.load_state_dict(state)
    with pytest.raises(ValueError, match="keys"):
        b.load_state_dict({"draws": 1})
    with pytest.raises(ValueError, match="'draws' must be a non-negative integer"):
        b.load_state_dict({"draws": -1, "seed": 11})
    with pytest.raises(ValueError, match="rank"):
        ShellLoss(grid, config, rank=-1)
    with pytest.raises(ValueError, match="seed"):
        ShellLoss(grid, ShellLossConfig(seed=-3))

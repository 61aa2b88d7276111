"""Shell-aware losses: losses on what a camera will see of a predicted fruxel volume, free of any network.

Every loss takes the network's output as plain tensors, so any training loop can use them:

* :func:`shell_cross_entropy`: cross-entropy of ``soft_first_hit``'s expected class distribution (channel 0 =
  miss) against the ``first_hit`` labels of the ground truth from the same cameras;
* :func:`depth_l1`: L1 between the expected first-hit depth (given a hit) and the ground-truth first-hit depth,
  on the pixels where the ground truth hits;
* :func:`visible_weighted_voxel_ce`: per-cell cross-entropy, weighted up on the ground truth's
  visible shell (:func:`fruxel.kernels.shell`) and down elsewhere;
* :class:`ShellLoss`: the three together from the grid's own view plus K random novel poses per batch, with the
  ground-truth side (``first_hit``, ``shell``, no gradient) computed on the fly.

Frames: volumes are NCDHW in the grid frame (conventions sections 1-2); images are ``(B, N, h, w)`` per camera; depths
are metres along each viewing camera's z.

Ground truth has one source, the label volume: what any camera sees of it, the grid's own camera included, is
``first_hit`` of the labels (the own view's is each column's first occupied cell, its depth the cell's near plane
``z_k``). :meth:`ShellLoss.targets` computes it on the labels' device and hands the own view's out as
:attr:`ShellTargets.own_view`, for metrics that need it; the simulator's samples do not store a copy.
"""

from __future__ import annotations

import functools
import math
import operator
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

import fruxel.kernels as fk
from fruxel.camera import Camera, look_at_grid, orbit_direction
from fruxel.grid import FruxelGrid
from fruxel.kernels.soft import SoftHits, soft_first_hit_groups

from .config import ShellLossConfig

__all__ = ["ShellLoss", "ShellLossConfig", "ShellLossTerms", "ShellTargets", "depth_l1", "random_poses",
           "shell_cross_entropy", "visible_weighted_voxel_ce"]


# ---------------------------------------------------------------------------------------------- losses
def shell_cross_entropy(soft: SoftHits, target_labels: torch.Tensor, *, eps: float = 1e-6,
                        mask: torch.Tensor | None = None, reduction: str = "mean") -> torch.Tensor:
    """Cross-entropy of the expected first-hit class distribution against first-hit labels.

    Args:
        soft: :class:`~fruxel.kernels.soft.SoftHits` of the prediction, ``classes`` ``(B, N, C, h, w)``.
        target_labels: ``(B, N, h, w)`` integer ``first_hit`` labels of the ground truth from the same cameras
            (0 = miss), values in ``[0, C)``.
        eps: added to the probability before the log, so that a confidently wrong pixel keeps a finite loss and a
            gradient (``-log(p + eps) <= -log(eps)``).
        mask: optional ``(B, N, h, w)`` bool, the pixels that count (all when None).
        reduction: ``"mean"`` over the counted pixels (0 when none count), or ``"sum"`` (to pool several calls,
            e.g. camera groups of different image sizes, before one division).

    Returns:
        Scalar tensor: the mean (or sum) of ``-log(p[label] + eps)`` over the counted pixels.

    Raises:
        ValueError: a mask that is not bool, or an unknown reduction.
    """
    _check_reduction(reduction)
    q = soft.classes.gather(2, target_labels.long().unsqueeze(2)) + eps
    if mask is not None:
        _check_mask(mask, "mask")
        # Masked pixels get log(1) = 0 before the log, not after it: a p of 0 there (with eps 0) would otherwise
        # send NaN back through the log.
        q = torch.where(mask.unsqueeze(2), q, 1.0)
    total = -torch.log(q).sum()
    if reduction == "sum":
        return total
    return total / (target_labels.numel() if mask is None else mask.sum().clamp_min(1))


def _check_reduction(reduction: str) -> None:
    if reduction not in ("mean", "sum"):
        raise ValueError(f"reduction must be 'mean' or 'sum', got {reduction!r}")


def _check_count(value: object, name: str) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or value < 0:
        raise ValueError(f"{name} must be a non-negative integer, got {value!r}")


def _check_mask(mask: torch.Tensor, name: str) -> None:
    if mask.dtype != torch.bool:
        raise ValueError(f"{name} must be a bool tensor, got {mask.dtype}")


def depth_l1(soft: SoftHits, target_depth: torch.Tensor, target_hit_mask: torch.Tensor, *,
             scale: float = 1.0, reduction: str = "mean") -> torch.Tensor:
    """L1 between the expected first-hit depth given a hit and the ground-truth first-hit depth.

    ``soft.depth`` is ``sum_m w_m t_m / sum_m w_m``: it says where the surface is, independently of how likely a
    hit is (which :func:`shell_cross_entropy` trains), and its gradient with respect to the logits stays bounded
    where the hit probability is small.

    Args:
        soft: :class:`~fruxel.kernels.soft.SoftHits` of the prediction, ``depth`` ``(B, N, h, w)``.
        target_depth: ``(B, N, h, w)`` ground-truth ``first_hit`` depth, metres (viewing camera z).
        target_hit_mask: ``(B, N, h, w)`` bool, pixels where the ground truth hits; only these count.
        scale: factor on the absolute error, e.g. ``1 / (z_far - z_near)`` for a unit-free loss.
        reduction: ``"mean"`` over the ground truth's hits (0 when there are none), or ``"sum"``.

    Returns:
        Scalar tensor: ``scale * mean |depth - target_depth|`` over the ground-truth hits (or the sum).

    Raises:
        ValueError: a mask that is not bool, or an unknown reduction.
    """
    _check_reduction(reduction)
    _check_mask(target_hit_mask, "target_hit_mask")
    err = torch.where(target_hit_mask, (soft.depth - target_depth.to(soft.depth.dtype)).abs(), 0.0).sum()
    if reduction != "sum":
        err = err / target_hit_mask.sum().clamp_min(1)
    return err * scale if scale != 1.0 else err


def visible_weighted_voxel_ce(scores: torch.Tensor, target_labels: torch.Tensor, shell_mask: torch.Tensor, *,
                              weight_visible: float = 1.0, weight_other: float = 0.1,
                              log_probs: bool = False) -> torch.Tensor:
    """Per-cell cross-entropy with a weight per cell from the ground truth's visible shell.

    Args:
        scores: ``(B, C, D, H, W)`` logits (or log-probabilities with ``log_probs=True``), channel 0 = empty.
        target_labels: ``(B, D, H, W)`` integer ground-truth labels in ``[0, C)``.
        shell_mask: ``(B, D, H, W)`` bool, cells of the ground truth's shell (``fruxel.kernels.shell(...) != 0``).
        weight_visible: weight of a shell cell.
        weight_other: weight of every other cell (empty space and hidden interiors).
        log_probs: ``scores`` are log-probabilities already (saves a second log-softmax).

    Returns:
        Scalar tensor: ``sum(weight * ce) / sum(weight)``.
    """
    s = scores if scores.dtype in (torch.float32, torch.float64) else scores.float()
    target = target_labels.long()
    ce = F.nll_loss(s, target, reduction="none") if log_probs else F.cross_entropy(s, target, reduction="none")
    w = torch.where(shell_mask, weight_visible, weight_other).to(ce.dtype)
    return (w * ce).sum() / w.sum().clamp_min(torch.finfo(ce.dtype).tiny)


# ---------------------------------------------------------------------------------------------- poses
def random_poses(grid: FruxelGrid, k: int, generator: np.random.Generator, *, width: int = 128, height: int = 128,
                 hfov: float = 60.0, azimuth: tuple[float, float] = (-60.0, 60.0),
                 elevation: tuple[float, float] = (5.0, 40.0),
                 distance: tuple[float, float] = (0.9, 1.3)) -> list[Camera]:
    """K random viewing cameras around the grid, each looking at the centre of its bounding box.

    Angles follow :func:`fruxel.kernels.orbit_cameras`: azimuth 0 is the grid's own viewing side (the camera
    stands towards -z), elevation lifts the camera towards -y (up). The distance is a factor on the orbit's
    default radius, 1.2 times the bounding box's diagonal.

    Args:
        grid: the grid to look at.
        k: number of cameras, >= 0.
        generator: numpy random generator (seeded by the caller).
        width, height, hfov: image size in pixels and horizontal field of view in degrees.
        azimuth, elevation: ranges in degrees, drawn uniformly.
        distance: range of the radius factor, drawn uniformly.

    Returns:
        k cameras with ``(4, 4)`` camera-to-grid poses.
    """
    box = grid.bounds()
    radius = 1.2 * float(np.linalg.norm(box[1] - box[0]))
    cams = []
    for _ in range(k):
        az = math.radians(generator.uniform(*azimuth))
        el = math.radians(generator.uniform(*elevation))
        r = radius * generator.uniform(*distance)
        cams.append(look_at_grid(grid, orbit_direction(az, el), distance=r, width=width, height=height, hfov=hfov))
    return cams


def group_by_size(cameras: list[Camera]) -> list[list[Camera]]:
    """Cameras grouped by image size, in order of first appearance (one ``soft_first_hit`` group per size)."""
    groups: dict[tuple[int, int], list[Camera]] = {}
    for c in cameras:
        groups.setdefault((c.width, c.height), []).append(c)
    return list(groups.values())


# ---------------------------------------------------------------------------------------------- combined
@dataclass(frozen=True)
class ShellLossTerms:
    """What :class:`ShellLoss` computed for one batch."""

    total: torch.Tensor
    """Scalar: the weighted sum of the three terms."""
    shell_ce: torch.Tensor
    """Scalar: :func:`shell_cross_entropy`, mean over every pixel of every camera."""
    depth: torch.Tensor
    """Scalar: :func:`depth_l1` over the ground truth's hits of every camera, unit-free."""
    voxel: torch.Tensor
    """Scalar: :func:`visible_weighted_voxel_ce`."""
    cameras: list[Camera]
    """The cameras used, own view first."""
    own_view: torch.Tensor | None = None
    """Scalar: the shell cross-entropy over the own view's pixels alone (computed when
    :attr:`ShellLossConfig.weight_own_view` is not 0 and the own camera is among the cameras), else None."""


@dataclass(frozen=True)
class ShellTargets:
    """The ground-truth side of :class:`ShellLoss` for one batch and set of cameras (no gradient), with the
    normalisations that depend only on it computed once."""

    groups: list[tuple[torch.Tensor, torch.Tensor, torch.Tensor]]
    """Per camera group (:func:`group_by_size`): ``first_hit`` labels ``(B, N, h, w)`` int64, depths
    ``(B, N, h, w)`` float32 (metres along each viewing camera's z) and hit mask ``(B, N, h, w)`` bool of the
    ground truth."""
    shell_mask: torch.Tensor
    """``(B, D, H, W)`` bool: the ground truth's shell from every camera."""
    depth_norm: torch.Tensor
    """0-dim float32: the depth L1's factor, ``1 / ((z_far - z_near) * max(1, ground-truth hits))``."""
    voxel_weight: torch.Tensor
    """``(B, D, H, W)`` float32: the voxel cross-entropy's per-cell weights divided by their sum."""
    voxel_labels: torch.Tensor
    """``(B, D, H, W)`` int64: the ground-truth labels as the voxel cross-entropy takes them."""
    depth_flat: torch.Tensor
    """``(sum of B * N * h * w over the groups,)`` float32: every group's ground-truth depths, flattened and
    concatenated in group order."""
    hit_flat: torch.Tensor
    """``(sum of B * N * h * w over the groups,)`` bool: every group's ground-truth hit mask, like ``depth_flat``."""
    own_index: tuple[int, int] | None = None
    """Where the grid's own camera is among the cameras: ``(camera group, camera within the group)``, or None."""

    @property
    def own_view(self) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor] | None:
        """The grid's own camera (when it is among the cameras): its ``first_hit`` labels ``(B, H, W)`` int64,
        depths ``(B, H, W)`` float32 (the near plane ``z_k`` of each column's first occupied cell, 0 on a miss) and
        hit mask ``(B, H, W)`` bool, views of the group tensors above: the own-view truth, from the labels like
        every view's."""
        if self.own_index is None:
            return None
        g, n = self.own_index
        lab, depth, hit = self.groups[g]
        return lab[:, n], depth[:, n], hit[:, n]

    @property
    def pixels(self) -> int:
        """Pixels of every camera together (the shell cross-entropy's mean)."""
        return self.hit_flat.numel()


class ShellLoss:
    """Shell-aware losses of predicted logits against a ground-truth label volume, from the grid's own view plus
    K random novel poses per call (seeded; new poses at every call).

    Novel poses: draw ``n`` (the n-th call of :meth:`cameras`, counted from 0 in :attr:`draws`) of rank ``r``
    takes its poses from ``numpy.random.default_rng(SeedSequence(config.seed, spawn_key=(r, n)))``, so they
    differ between distributed ranks and between draws, and depend on nothing else: the generator's whole state
    is the counter. :meth:`state_dict` / :meth:`load_state_dict` checkpoint it; restoring gives the same next
    poses. The rank is not part of the state: ranks that draw equally often (one call per training step) share
    it, so a checkpoint written by rank 0 restores every rank to its own stream.

    Args:
        grid: the volumes' grid.
        config: settings; defaults of :class:`ShellLossConfig` when None.
        rank: this process's distributed rank (``torch.distributed.get_rank()``), >= 0; 0 without distribution.

    Raises:
        ValueError: a negative or non-integer seed or rank.
    """

    def __init__(self, grid: FruxelGrid, config: ShellLossConfig | None = None, *, rank: int = 0) -> None:
        self.grid = grid
        """The volumes' grid."""
        self.config = config or ShellLossConfig()
        """The settings."""
        _check_count(self.config.seed, "ShellLossConfig.seed")
        _check_count(rank, "rank")
        self.rank = int(rank)
        """The distributed rank mixed into the novel poses' seed."""
        self.draws = 0
        """Novel-pose draws made so far (calls of :meth:`cameras`): the generator's state."""

    def pose_generator(self, draw: int) -> np.random.Generator:
        """The numpy generator of novel-pose draw ``draw`` on this rank (see the class docstring)."""
        return np.random.default_rng(np.random.SeedSequence(self.config.seed, spawn_key=(self.rank, draw)))

    def cameras(self) -> list[Camera]:
        """The cameras of the next batch: the own view (if configured) and K newly drawn novel poses; advances
        :attr:`draws`."""
        c = self.config
        cams = [self.grid.camera()] if c.own_view else []
        w, h = c.novel_size
        hfov = self.grid.hfov if c.novel_hfov is None else c.novel_hfov
        cams += random_poses(self.grid, c.novel_views, self.pose_generator(self.draws), width=w, height=h,
                             hfov=hfov, azimuth=c.azimuth, elevation=c.elevation, distance=c.distance)
        if not cams:
            raise ValueError("ShellLoss needs the own view or at least one novel view")
        self.draws += 1
        return cams

    def state_dict(self) -> dict[str, int]:
        """The novel poses' generator state, ``{"seed": int, "draws": int}``: plain ints, for a training checkpoint
        (``torch.save``, read back with ``torch.load(weights_only=True)``) or JSON."""
        return {"seed": int(self.config.seed), "draws": int(self.draws)}

    def load_state_dict(self, state: dict[str, int]) -> None:
        """Restore :meth:`state_dict`'s state: the next :meth:`cameras` gives what it gave after the state was taken
        (on this rank).

        Raises:
            ValueError: not such a state, or one taken with another seed (the run's config changed).
        """
        if not isinstance(state, dict) or sorted(state) != ["draws", "seed"]:
            keys = sorted(map(str, state)) if isinstance(state, dict) else type(state).__name__
            raise ValueError(f"ShellLoss state must be a dict with keys 'draws' and 'seed', got {keys}")
        _check_count(state["seed"], "ShellLoss state 'seed'")
        _check_count(state["draws"], "ShellLoss state 'draws'")
        if state["seed"] != self.config.seed:
            raise ValueError(f"ShellLoss state was taken with seed {state['seed']}, this ShellLoss has seed "
                             f"{self.config.seed}")
        self.draws = int(state["draws"])

    def targets(self, labels: torch.Tensor, cameras: list[Camera]) -> ShellTargets:
        """The ground-truth side (no gradient): ``first_hit`` of the labels per camera group and their ``shell``
        (see :class:`ShellTargets`)."""
        c = self.config
        out = []
        with torch.no_grad():
            for group in group_by_size(cameras):
                hits = [fk.first_hit(labels, self.grid, cam, backend=c.backend, device=c.device) for cam in group]
                lab = torch.stack([torch.as_tensor(h.label) for h in hits], dim=1).long()
                depth = torch.stack([torch.as_tensor(h.depth) for h in hits], dim=1)
                out.append((lab, depth, lab > 0))
            mask = torch.as_tensor(fk.shell(labels, self.grid, cameras, backend=c.backend, device=c.device)) != 0
            hit_count = sum(t[2].sum() for t in out).clamp_min(1)
            depth_norm = 1.0 / ((self.grid.z_far - self.grid.z_near) * hit_count)
            weight = torch.where(mask, c.weight_visible, c.weight_other)
            weight = weight / weight.sum().clamp_min(torch.finfo(weight.dtype).tiny)
            depth_flat = torch.cat([t[1].reshape(-1) for t in out])
            hit_flat = torch.cat([t[2].reshape(-1) for t in out])
        own = self.grid.camera()
        own_index = next(((g, n) for g, group in enumerate(group_by_size(cameras)) for n, cam in enumerate(group)
                          if cam == own), None)
        return ShellTargets(out, mask, depth_norm, weight, labels.long(), depth_flat, hit_flat, own_index)

    def __call__(self, logits: torch.Tensor, labels: torch.Tensor,
                 cameras: list[Camera] | None = None) -> ShellLossTerms:
        """The three losses and their weighted total for one batch: :meth:`targets` then :meth:`losses`.

        Args:
            logits: ``(B, C, D, H, W)`` predicted logits (any float dtype; bfloat16 is computed in float32), on the
                CPU or CUDA; gradients flow back to them.
            labels: ``(B, D, H, W)`` integer ground-truth labels in ``[0, C)`` (uint8 is cheapest), same device.
            cameras: the viewing cameras; None draws them with :meth:`cameras`.

        Returns:
            :class:`ShellLossTerms`.
        """
        cams = self.cameras() if cameras is None else list(cameras)
        return self.losses(logits, cams, self.targets(labels, cams))

    def losses(self, logits: torch.Tensor, cameras: list[Camera], targets: ShellTargets) -> ShellLossTerms:
        """The differentiable part, from ground-truth targets computed beforehand (e.g. by a data loader).

        Every device operation counts (on a GPU each costs its launch), so the terms are summed over the camera
        groups and normalised once, with the factors of :class:`ShellTargets`.

        Args:
            logits: as for :meth:`__call__`.
            cameras: the cameras :meth:`targets` was given.
            targets: what :meth:`targets` returned for the batch's labels and ``cameras`` (they carry the labels
                the voxel cross-entropy needs).

        Returns:
            :class:`ShellLossTerms`.
        """
        c = self.config
        s = logits if logits.dtype in (torch.float32, torch.float64) else logits.float()
        # One log-softmax serves both the voxel cross-entropy and, exponentiated, the kernels' probabilities.
        log_p = torch.log_softmax(s, dim=1)
        soft = soft_first_hit_groups(log_p.exp(), self.grid, group_by_size(cameras), backend=c.backend,
                                     device=c.device, probs=True)
        # Every group's pixels in one vector per quantity, so that each operation runs once for all groups.
        p_label = torch.cat([h.classes.gather(2, t[0].unsqueeze(2)).reshape(-1)
                             for h, t in zip(soft, targets.groups, strict=True)])
        shell_ce = torch.log(p_label + c.eps).sum() * (-1.0 / targets.pixels)
        pred_depth = torch.cat([h.depth.reshape(-1) for h in soft])
        err = torch.where(targets.hit_flat, (pred_depth - targets.depth_flat.to(pred_depth.dtype)).abs(), 0.0)
        depth = err.sum() * targets.depth_norm
        voxel = (F.nll_loss(log_p, targets.voxel_labels, reduction="none") * targets.voxel_weight).sum()
        weighted = [(c.weight_shell, shell_ce), (c.weight_depth, depth), (c.weight_voxel, voxel)]
        own_ce = None
        if c.weight_own_view and targets.own_index is not None:
            g, n = targets.own_index
            p_own = soft[g].classes[:, n].gather(1, targets.own_view[0].unsqueeze(1))
            own_ce = -torch.log(p_own + c.eps).mean()
            weighted.append((c.weight_own_view, own_ce))
        # reduce, not sum(): adding to 0 would cost one more device operation; unit weights cost none.
        total = functools.reduce(operator.add, (x if w == 1.0 else w * x for w, x in weighted))
        return ShellLossTerms(total=total, shell_ce=shell_ce, depth=depth, voxel=voxel, cameras=list(cameras),
                              own_view=own_ce)

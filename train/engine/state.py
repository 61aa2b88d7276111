"""A training run's state: the models, optimisers, schedule, data position, counters and random states, with the
checkpoint layout that saves and restores it (:mod:`.checkpoint` writes and reads the file)."""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import torch
from torch import nn

from fruxel.errors import FruxelError

from ..config import TrainConfig
from .checkpoint import rng_state, set_rng_state
from .data import ReplayBuffer


class TrainingError(FruxelError, RuntimeError):
    """A run that cannot start or continue (bad data folder, nothing to resume, a config that does not fit, a
    checkpoint that cannot be written)."""


@dataclass
class TrainingState:
    """Everything a checkpoint holds and a resumed run restores (:meth:`state_dict`, :meth:`load_state_dict`)."""

    config: TrainConfig
    """The run's config."""
    network: nn.Module
    """The network being trained (unwrapped: no DDP, no compilation)."""
    optimizer: torch.optim.Optimizer
    """AdamW over the network's parameters."""
    scheduler: torch.optim.lr_scheduler.LambdaLR
    """Warm-up and cosine decay (:func:`lr_factor`)."""
    discriminator: nn.Module | None = None
    """The 3D PatchGAN, with ``loss.adversarial``."""
    d_optimizer: torch.optim.Optimizer | None = None
    """Its Adam optimiser."""
    shell: Any = None
    """The shell-aware losses (:class:`fruxel.train.losses.ShellLoss`, whose novel poses are state), or None."""
    replay: ReplayBuffer | None = None
    """The replay buffer (its draws' generator is state; its samples are not saved), or None."""
    class_weights: torch.Tensor | None = None
    """``(C,)`` float32 cross-entropy class weights, counted on the first training batches (None until then)."""
    step: int = 0
    """Optimiser steps done."""
    samples: int = 0
    """Training samples drawn, all ranks."""
    elapsed: float = 0.0
    """Seconds of training steps (evaluation excluded)."""
    position: tuple[int, int] = (0, 0)
    """The data position of the next unused batch, ``(block, used)`` (:class:`fruxel.train.samples.Batches`)."""
    summary: dict[str, Any] = field(default_factory=dict)
    """The last evaluation's summary."""
    losses: dict[str, float] = field(default_factory=dict)
    """The last logged training losses."""

    def state_dict(self) -> dict[str, Any]:
        """The checkpoint's contents (:mod:`.checkpoint` adds the format and the config)."""
        return {
            "step": self.step,
            "samples": self.samples,
            "elapsed": self.elapsed,
            "generator": self.network.state_dict(),
            "discriminator": self.discriminator.state_dict() if self.discriminator is not None else None,
            "optimizer": self.optimizer.state_dict(),
            "d_optimizer": self.d_optimizer.state_dict() if self.d_optimizer is not None else None,
            "scheduler": self.scheduler.state_dict(),
            "data": {"position": list(self.position)},
            "class_weights": self.class_weights.detach().cpu(),
            "rng": rng_state(),
            "shell_poses": self.shell.state_dict() if self.shell is not None else None,
            "replay": self.replay.state_dict() if self.replay is not None else None,
            "summary": self.summary,
            "losses": self.losses,
        }

    def load_counters(self, state: dict[str, Any], device: torch.device) -> None:
        """Restore the counters, data position, class weights and last results of :meth:`state_dict` (what the
        data stream needs before the models are restored)."""
        self.step, self.samples, self.elapsed = int(state["step"]), int(state["samples"]), float(state["elapsed"])
        self.position = tuple(int(v) for v in state["data"]["position"])
        self.class_weights = state["class_weights"].to(device)
        self.summary = dict(state.get("summary") or {})
        self.losses = dict(state.get("losses") or {})

    def load_models(self, state: dict[str, Any]) -> None:
        """Restore the models, optimisers, schedule, poses, replay draws and random states of :meth:`state_dict`."""
        self.network.load_state_dict(state["generator"])
        self.optimizer.load_state_dict(state["optimizer"])
        self.scheduler.load_state_dict(state["scheduler"])
        if self.discriminator is not None and state.get("discriminator") is not None:
            self.discriminator.load_state_dict(state["discriminator"])
            self.d_optimizer.load_state_dict(state["d_optimizer"])
        if self.shell is not None and state.get("shell_poses"):
            self.shell.load_state_dict(state["shell_poses"])
        if self.replay is not None and state.get("replay"):
            self.replay.load_state_dict(state["replay"])
        set_rng_state(state["rng"])


def lr_factor(config: TrainConfig) -> Callable[[int], float]:
    """The learning rate's factor at each step: linear warm-up from 0, then a cosine down to ``optim.min_lr``."""
    o, steps = config.optim, config.run.steps

    def factor(step: int) -> float:
        if step < o.warmup:
            return (step + 1) / o.warmup
        t = min(1.0, (step - o.warmup) / max(1, steps - o.warmup))
        return o.min_lr + (1.0 - o.min_lr) * 0.5 * (1.0 + math.cos(math.pi * t))

    return factor


def _param_groups(model: nn.Module, weight_decay: float) -> list[dict[str, Any]]:
    """Weight decay on weights, not on norms and biases."""
    decay, plain = [], []
    for p in model.parameters():
        (decay if p.ndim > 1 else plain).append(p)
    return [{"params": decay, "weight_decay": weight_decay}, {"params": plain, "weight_decay": 0.0}]


def new_state(config: TrainConfig, network: nn.Module, device: torch.device, rank: int) -> TrainingState:
    """A fresh state around ``network`` (already initialised and on ``device``): its optimiser and schedule, and
    the discriminator, shell losses and replay buffer the config asks for."""
    from ..losses import ShellLoss
    from ..models.discriminator import PatchDiscriminator3d

    c, cuda = config, device.type == "cuda"
    # fused: one kernel for every parameter on CUDA (the per-tensor loop costs a launch per tensor).
    opt = torch.optim.AdamW(_param_groups(network, c.optim.weight_decay), lr=c.optim.lr,
                            betas=tuple(c.optim.betas), fused=cuda)
    state = TrainingState(c, network, opt, torch.optim.lr_scheduler.LambdaLR(opt, lr_factor(c)))
    if c.loss.adversarial:
        state.discriminator = PatchDiscriminator3d(c.model.num_classes, c.loss.discriminator).to(device)
        state.d_optimizer = torch.optim.Adam(state.discriminator.parameters(), lr=c.loss.discriminator_lr,
                                             betas=(0.5, 0.999))
    if c.loss.shell:
        state.shell = ShellLoss(c.model.grid, c.loss.shell_losses, rank=rank)
    if c.data.replay:
        state.replay = ReplayBuffer(c.data.replay, (*c.model.image_size, 3), c.model.grid.shape, device,
                                    c.run.seed * 7919 + rank)
    return state

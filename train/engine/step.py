"""One training step: forward, the objective, backward, the optimiser, then the discriminator's own step."""

from __future__ import annotations

import time
from dataclasses import dataclass, field

import torch
import torch.nn.functional as F
from torch import nn

from ..config import LossConfig
from ..models.conditioning import CameraInput
from ..models.discriminator import hinge_d_loss, hinge_g_loss
from ..models.registry import run_network
from ..objective import SSZObjective
from .state import TrainingState


def adversarial_weight(loss: LossConfig, step: int) -> float:
    """The generator's adversarial weight at ``step``: 0 before ``adversarial_start``, then a linear ramp."""
    if not loss.adversarial or step < loss.adversarial_start:
        return 0.0
    ramp = max(1, loss.adversarial_ramp)
    return loss.adversarial_weight * min(1.0, (step - loss.adversarial_start + 1) / ramp)


@dataclass
class PhaseTimer:
    """Seconds spent per phase of the steps after the first ``warm`` ones, for benchmarks (``enabled``: every phase
    boundary waits for the device, so steps get slower).

    Phases: ``data``, ``forward``, ``loss``, ``backward``, ``optimizer``, ``discriminator``; ``steps`` counts the
    steps timed.
    """

    enabled: bool = False
    """Time at all."""
    warm: int = 20
    """Steps left out (start-up, autotuning, compilation)."""
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    """The training device (synchronised at each boundary)."""
    seconds: dict[str, float] = field(default_factory=dict)
    """The sums."""
    _last: float = 0.0

    def tick(self, step: int, phase: str | None) -> None:
        """Add the time since the last tick to ``phase`` (None starts a step)."""
        if not self.enabled or step < self.warm:
            return
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)  # a phase ends when its kernels have run
        now = time.perf_counter()
        if phase is None:
            self.seconds["steps"] = self.seconds.get("steps", 0.0) + 1.0
        else:
            self.seconds[phase] = self.seconds.get(phase, 0.0) + now - self._last
        self._last = now


@dataclass
class Step:
    """The plain step of a run: what it needs besides the state.

    Attributes:
        model: the network as trained (wrapped by DDP and ``torch.compile`` where the run asks).
        d_model: the discriminator as trained (DDP-wrapped under distribution), or None.
        objective: the loss terms.
        autocast: bfloat16 autocast (CUDA with ``run.precision = "bf16"``).
        timer: the phase timer.
        graphs: ``model`` replays CUDA graphs (``run.cuda_graphs``): each step tells them that a new step begins, so
            the graphs may reuse the memory of the last step's outputs.
    """

    model: nn.Module
    d_model: nn.Module | None
    objective: SSZObjective
    autocast: bool
    timer: PhaseTimer
    graphs: bool = False

    def __call__(self, state: TrainingState, image: torch.Tensor, labels: torch.Tensor,
                 camera: CameraInput | None = None) -> dict[str, torch.Tensor]:
        """Train one batch at ``state.step`` (the caller advances the counters).

        Args:
            state: the run's state (network, optimisers, discriminator).
            image: ``(B, 3, h, w)`` float RGB in [0, 1] on the training device.
            labels: ``(B, D, H, W)`` uint8 labels, grid frame, same device.
            camera: what the network is told of the batch's cameras (a network that reads them), else None.

        Returns:
            The loss terms, detached scalar tensors (``total`` and each term).
        """
        c, step, tick = state.config, state.step, self.timer.tick
        kind = image.device.type
        adv_w = adversarial_weight(c.loss, step)
        if self.graphs:
            torch.compiler.cudagraph_mark_step_begin()
        state.optimizer.zero_grad(set_to_none=True)
        with torch.autocast(kind, dtype=torch.bfloat16, enabled=self.autocast):
            out = run_network(self.model, image, camera)
            tick(step, "forward")
            terms = self.objective(out, labels)
            tick(step, "loss")
            if adv_w > 0:
                d_plain = state.discriminator
                d_plain.requires_grad_(False)
                fake = d_plain(torch.softmax(out.logits.float(), dim=1), image)
                terms["adversarial"] = hinge_g_loss(fake)
                terms["total"] = terms["total"] + adv_w * terms["adversarial"]
                d_plain.requires_grad_(True)
        terms["total"].backward()
        tick(step, "backward")
        if c.optim.grad_clip:
            torch.nn.utils.clip_grad_norm_(state.network.parameters(), c.optim.grad_clip)
        state.optimizer.step()
        state.scheduler.step()
        tick(step, "optimizer")
        if state.discriminator is not None and step >= c.loss.adversarial_start:
            state.d_optimizer.zero_grad(set_to_none=True)
            with torch.autocast(kind, dtype=torch.bfloat16, enabled=self.autocast):
                real_p = F.one_hot(labels.long(), c.model.num_classes).movedim(-1, 1).float()
                fake_p = torch.softmax(out.logits.detach().float(), dim=1)
                d_loss = hinge_d_loss(self.d_model(real_p, image), self.d_model(fake_p, image))
            d_loss.backward()
            state.d_optimizer.step()
            terms["discriminator"] = d_loss
            tick(step, "discriminator")
        return {k: v.detach() for k, v in terms.items()}

"""Experiment (issue 39): an exponential moving average of the weights, kept beside a training run.

Not in the product: a research lever that extends it from outside (the trainer's callbacks), until a shipped model
uses it. Run fruxel-train through this module::

    python experiments/ema_weights.py [--decay 0.999] -- FRUXEL-TRAIN ARGS...

Besides what fruxel-train writes, the run folder gets ``ema.safetensors``: the network whose parameters are the
average ``a <- decay * a + (1 - decay) * p`` over the steps (``p`` the trained parameters after each step; the
batch-norm statistics are the trained network's own), written with every checkpoint, in the shipped format, so
that ``fruxel-eval --checkpoint RUN/ema.safetensors`` reads it against ``RUN/model.safetensors`` from the same run.
A resumed run continues the average that ``ema.safetensors`` holds (the file is written whenever ``last.pt`` is).
"""

from __future__ import annotations

import argparse
import os
import sys
from typing import Any

import torch

from fruxel.train.engine.callbacks import Callback

EMA_FILE = "ema.safetensors"
"""The average's file in the run folder."""


class WeightAverage(Callback):
    """The trainer callback that keeps and writes the average (module docstring).

    Args:
        decay: the average's weight on its past, in (0, 1).
    """

    def __init__(self, decay: float) -> None:
        self.decay = decay
        self.shadow: dict[str, torch.Tensor] = {}
        """The averaged parameters by name, float32, on the network's device."""

    def on_start(self, trainer: Any) -> None:
        from fruxel.train.model_files import read_model_file

        self._params = dict(trainer.state.network.named_parameters())
        self.shadow = {k: p.detach().float().clone() for k, p in self._params.items()}
        path = trainer.folder.file(EMA_FILE)
        if trainer.resumed and os.path.exists(path):
            for k, v in read_model_file(path).state.items():
                if k in self.shadow:
                    self.shadow[k] = v.to(self.shadow[k].device, torch.float32)
        self._pairs = ([self.shadow[k] for k in self._params], [p.detach() for p in self._params.values()])

    def on_step(self, trainer: Any, terms: dict[str, torch.Tensor]) -> None:
        with torch.no_grad():
            torch._foreach_lerp_(self._pairs[0], [p.float() for p in self._pairs[1]], 1.0 - self.decay)
        every, step = trainer.config.run.checkpoint_every, trainer.state.step
        if every and step % every == 0 and step < trainer.config.run.steps:
            self.save(trainer)

    def on_stop(self, trainer: Any, interrupted: bool) -> None:
        self.save(trainer)

    def save(self, trainer: Any) -> None:
        """Write ``ema.safetensors``: the trained network with the averaged parameters (its buffers its own)."""
        if not trainer.dist.main:
            return
        import copy

        from fruxel.train.model_files import save_model

        net = copy.deepcopy(trainer.state.network)
        with torch.no_grad():
            for k, p in net.named_parameters():
                p.copy_(self.shadow[k].to(p.dtype))
        s = trainer.state
        meta = {"step": s.step, "samples": s.samples, "ema_decay": self.decay, "config": trainer.config.name}
        save_model(trainer.folder.file(EMA_FILE), net, trainer.config.model, training=meta)


def main(argv: list[str]) -> int:
    """Parse ``--decay``, add the callback to every Trainer, run fruxel-train with the rest."""
    p = argparse.ArgumentParser(prog="ema_weights.py")
    p.add_argument("--decay", type=float, default=0.999)
    p.add_argument("rest", nargs=argparse.REMAINDER)
    a = p.parse_args(argv)
    if not 0.0 < a.decay < 1.0:
        p.error(f"--decay must be in (0, 1), got {a.decay}")
    from fruxel.cli import train as train_cli
    from fruxel.train.engine import trainer as trainer_mod

    init = trainer_mod.Trainer.__init__

    def with_average(self: Any, *args: Any, **kw: Any) -> None:
        init(self, *args, **kw)
        # Before the checkpoints' callback, so that a checkpoint's ema.safetensors is of the same step.
        self.callbacks.insert(self.callbacks.index(self.checkpoints), WeightAverage(a.decay))

    trainer_mod.Trainer.__init__ = with_average
    rest = a.rest[1:] if a.rest[:1] == ["--"] else a.rest
    return train_cli.main(rest)


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

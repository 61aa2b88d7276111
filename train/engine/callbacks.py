"""What happens around the training steps, as callbacks of :class:`~.trainer.Trainer`: the metric log and progress
bar, the periodic evaluation, checkpoints, the time limit, and the check that CUDA graphs replay the network.

A callback sees the trainer at four points (:class:`Callback`): before the first step, after each step, when the
run stops (its last step, the time limit or Ctrl-C) and after everything (``on_close``, also after an error). Only
rank 0 writes files; every rank calls the callbacks, so that collective operations (the mean of the logged losses,
the barrier after an evaluation) meet.

What the run folder says always agrees with its checkpoint: metric rows, curves and the examples picture are
committed when a checkpoint is written, and rows logged after the last checkpoint are dropped again when a
checkpoint cannot be written (a full disk) or on resume.
"""

from __future__ import annotations

import math
import os
import sys
import time
from typing import TYPE_CHECKING, Any

import torch

from . import distributed
from .checkpoint import LATEST, save_checkpoint
from .logbook import CURVES, Logbook, plot_curves
from .run_folder import EXAMPLES, SHIPPED
from .state import TrainingError

if TYPE_CHECKING:
    from .trainer import Trainer


class Callback:
    """Hooks around the steps; each does nothing unless overridden."""

    def on_start(self, trainer: Trainer) -> None:
        """Before the first step (after a resume's state is restored)."""

    def on_step(self, trainer: Trainer, terms: dict[str, torch.Tensor]) -> None:
        """After each step, ``trainer.state.step`` counting it; ``terms`` are the step's detached losses."""

    def on_stop(self, trainer: Trainer, interrupted: bool) -> None:
        """The run stops: after its last step or the time limit (``interrupted`` False), or on Ctrl-C (True)."""

    def on_close(self, trainer: Trainer) -> None:
        """After everything, also after an error."""


class MetricLog(Callback):
    """Every ``run.log_every`` steps: the mean losses, samples per second and learning rate into ``metrics.csv``
    (and TensorBoard), and the progress bar; the curves when a checkpoint commits the rows."""

    def __init__(self, progress: bool) -> None:
        self.progress = progress
        self.book: Logbook | None = None
        self.bar: Any = None
        self.rates: list[float] = []
        """Samples per second of each logged window."""
        self._sums: dict[str, torch.Tensor] = {}
        self._window = (0, 0.0, 0)

    def on_start(self, trainer: Trainer) -> None:
        from tqdm import tqdm

        s, c = trainer.state, trainer.config
        if trainer.dist.main:
            self.book = Logbook(trainer.folder.path, resume_step=s.step if trainer.resumed else None,
                                tensorboard=c.run.tensorboard)
        self.bar = tqdm(total=c.run.steps, initial=s.step, disable=not self.progress, unit="step",
                        dynamic_ncols=True)
        self._window = (0, time.perf_counter(), 0)

    def on_step(self, trainer: Trainer, terms: dict[str, torch.Tensor]) -> None:
        for k, v in terms.items():
            self._sums[k] = self._sums[k] + v if k in self._sums else v
        steps, start, samples = self._window
        self._window = (steps + 1, start, samples + trainer.config.run.batch_size)
        self.bar.update(1)
        step = trainer.state.step
        if step % trainer.config.run.log_every == 0 or step == trainer.config.run.steps:
            self.flush(trainer)

    def flush(self, trainer: Trainer, agree: bool = True) -> None:
        """Log the window's means (after a resume within a window, over fewer than ``log_every`` steps).

        Args:
            agree: average the losses over the ranks (a collective: every rank must flush at the same step).
                False after Ctrl-C, which each rank meets at its own step: rank 0's own means are logged.
        """
        steps, start, samples = self._window
        if not steps:
            return
        values = {f"loss/{k}": float(v) / steps for k, v in self._sums.items()}
        if agree:
            values = distributed.mean_scalars(trainer.dist, values)
        trainer.state.losses = {k.split("/", 1)[1]: v for k, v in values.items()}
        now = time.perf_counter()
        values["samples_per_s"] = samples / max(now - start, 1e-9)
        self.rates.append(values["samples_per_s"])
        values["lr"] = trainer.state.scheduler.get_last_lr()[0]
        self._sums, self._window = {}, (0, now, 0)
        if self.book is not None:
            self.book.log(trainer.state.step, values)
        self.bar.set_postfix(loss=f"{values['loss/total']:.3f}", sps=f"{values['samples_per_s']:.0f}")

    def log(self, step: int, values: dict[str, float]) -> None:
        """Add a row of other values (an evaluation's)."""
        if self.book is not None:
            self.book.log(step, values)

    def commit(self, trainer: Trainer) -> None:
        """The rows so far belong to the checkpoint just written: keep them, and draw the curves."""
        if self.book is not None:
            self.book.commit()
            plot_curves(self.book.rows, trainer.folder.file(CURVES), title=trainer.config.name)

    def rollback(self) -> None:
        """Drop the rows logged since the last checkpoint."""
        if self.book is not None:
            self.book.rollback()

    def on_stop(self, trainer: Trainer, interrupted: bool) -> None:
        self.bar.close()

    def on_close(self, trainer: Trainer) -> None:
        if self.bar is not None:
            self.bar.close()
        if self.book is not None:
            self.book.close()


class Evaluation(Callback):
    """Every ``run.eval_every`` steps and when the run ends (not on Ctrl-C): the metrics on ``data.eval_samples``
    test samples (rank 0; the network's raw argmax, no inference rules: those are chosen after training,
    ``fruxel-calibrate``), logged, and a sheet of examples, drawn when the next checkpoint commits."""

    def __init__(self, log: MetricLog, enabled: bool) -> None:
        self.log = log
        self.enabled = enabled
        self.pending: tuple[list[dict[str, Any]], str] | None = None
        """The examples and title of the last evaluation not yet drawn."""
        self._set: tuple[torch.Tensor, torch.Tensor] | None = None

    def on_step(self, trainer: Trainer, terms: dict[str, torch.Tensor]) -> None:
        every, step = trainer.config.run.eval_every, trainer.state.step
        if every and step % every == 0 and step < trainer.config.run.steps:
            self.evaluate(trainer)

    def on_stop(self, trainer: Trainer, interrupted: bool) -> None:
        if not interrupted:
            # Also after a time-limit stop: each chunk of a run that trains in time slices ends with its metrics.
            self.evaluate(trainer)

    def evaluate(self, trainer: Trainer) -> None:
        """Evaluate now (rank 0), then wait for every rank."""
        if trainer.dist.main and self.enabled:
            t = time.perf_counter()
            summary = self._evaluate(trainer)
            trainer.state.summary = summary
            self.log.log(trainer.state.step,
                         {f"eval/{k}": v for k, v in summary.items() if isinstance(v, float)}
                         | {f"eval/iou_{k}": v for k, v in summary["iou"].items() if v is not None}
                         | {"eval/seconds": time.perf_counter() - t})
        distributed.barrier(trainer.dist)

    def _evaluate(self, trainer: Trainer) -> dict[str, Any]:
        from ..eval.evaluate import evaluate, spread
        from ..models.conditioning import KNOWN
        from ..rules import NO_RULES
        from ..samples import SampleSource, load_split
        from .data import to_device

        c, dev = trainer.config, trainer.dist.device
        reads = c.model.reads_camera
        if self._set is None:
            self._set = load_split(SampleSource.of(c.data), c.model, "test", c.data.eval_samples,
                                   workers=c.data.workers, device="cuda" if dev.type == "cuda" else "cpu",
                                   camera=reads)
        images, labels = self._set[:2]
        bs = max(1, c.run.batch_size // trainer.dist.world)
        # A network that reads the camera is evaluated with the pose the test set records (pose given).
        batches = (to_device({"image": images[i:i + bs], "labels": labels[i:i + bs]}, dev)
                   + (({k: v[i:i + bs] for k, v in self._set[2].items()},) if reads else ())
                   for i in range(0, len(images), bs))
        acc, kept = evaluate(trainer.state.network, NO_RULES, batches, c.model.grid, c.model.classes, device=dev,
                             autocast=trainer.autocast, keep=spread(len(images), 4),
                             camera_known=KNOWN if reads else None)
        summary = acc.summary(c.model.classes.names)
        self.pending = (kept, f"{c.name}, step {trainer.state.step}: held-out rooms, mIoU {summary['miou']:.1f}")
        return summary

    def commit(self, trainer: Trainer) -> None:
        """Draw the last evaluation's examples (a checkpoint at or after it was just written)."""
        from ..eval.visual import example_sheet

        if self.pending is not None:
            kept, title = self.pending
            c = trainer.config
            example_sheet(kept, c.model.grid, c.model.classes, trainer.folder.file(EXAMPLES), title=title)
            self.pending = None


class Checkpoints(Callback):
    """Every ``run.checkpoint_every`` steps, when the run stops (Ctrl-C included): the checkpoint ``last.pt`` and
    the shipped form ``model.safetensors`` (rank 0), then the logs committed to it (:class:`MetricLog`,
    :class:`Evaluation`)."""

    def __init__(self, log: MetricLog, evaluation: Evaluation) -> None:
        self.log = log
        self.evaluation = evaluation
        self.saved_step: int | None = None
        """The step of the last checkpoint written (None before the first)."""

    def on_step(self, trainer: Trainer, terms: dict[str, torch.Tensor]) -> None:
        every, step = trainer.config.run.checkpoint_every, trainer.state.step
        if every and step % every == 0 and step < trainer.config.run.steps:
            self.save(trainer)

    def on_stop(self, trainer: Trainer, interrupted: bool) -> None:
        self.log.flush(trainer, agree=not interrupted)
        self.save(trainer)

    def save(self, trainer: Trainer) -> None:
        """Write the checkpoint of the state now, then commit the logs to it.

        Raises:
            TrainingError: the checkpoint could not be written (the logs are rolled back to the last one).
        """
        if not trainer.dist.main:
            return
        from ..model_files import save_model

        s, c = trainer.state, trainer.config
        checkpoint = trainer.folder.file(LATEST)
        try:
            save_checkpoint(checkpoint, trainer.checkpoint_state(), c)
            summary = {**s.summary, "step": s.step, "samples": s.samples, "seconds": round(s.elapsed, 1),
                       "config": c.name}
            save_model(trainer.folder.file(SHIPPED), s.network, c.model, training=summary)
        except (OSError, RuntimeError) as e:
            # torch.save reports a failed write as a RuntimeError ("file write failed"); both mean the same here.
            self.log.rollback()
            what = os.strerror(e.errno) if isinstance(e, OSError) and e.errno else str(e).splitlines()[0]
            kept = f"step {self.saved_step}" if self.saved_step is not None else "the checkpoint it had"
            raise TrainingError(f"{checkpoint}: could not write the checkpoint of step {s.step} ({what}); the run "
                                f"folder keeps {kept}") from None
        self.saved_step = s.step
        self.log.commit(trainer)
        self.evaluation.commit(trainer)


class TimeLimit(Callback):
    """Stops the run after ``run.time_limit`` seconds (checkpointed and evaluated as at its end).

    Under DDP the ranks decide together, every :attr:`AGREE_EVERY` steps: each rank's clock started a little apart,
    and a rank that stopped alone left the others waiting in their next all-reduce (a two-GPU run hung at the end of
    its time slice)."""

    AGREE_EVERY = 10
    """Steps between the ranks' joint decisions (one tiny all-reduce each); a run stops at most this late."""

    def on_start(self, trainer: Trainer) -> None:
        limit = trainer.config.run.time_limit
        self.stop_at = time.perf_counter() + limit if limit else math.inf

    def on_step(self, trainer: Trainer, terms: dict[str, torch.Tensor]) -> None:
        over = time.perf_counter() > self.stop_at
        if trainer.dist.distributed:
            if trainer.state.step % self.AGREE_EVERY:
                return
            over = distributed.any_rank(trainer.dist, over)
        if over:
            trainer.stop = True


def graph_skips() -> int:
    """Graphs that ``torch.compile`` compiled in this process for CUDA graphs but runs without them (each forward
    and backward graph counts once; on the CPU every one is skipped)."""
    from torch._dynamo.utils import counters

    return int(counters["inductor"]["cudagraph_skips"])


class GraphCheck(Callback):
    """After the first step of a run that replays CUDA graphs (:attr:`Trainer.graphs`): how many of the network's
    compiled graphs ``torch.compile`` runs without them (a CPU tensor among the inputs, an operation graphs cannot
    hold), and, on rank 0, one warning line when there are any. Such steps are slower, not wrong."""

    def __init__(self) -> None:
        self.skips = 0
        """Graphs run without CUDA graphs, counted after the first step (0 when the run replays none)."""
        self._before: int | None = None

    def on_start(self, trainer: Trainer) -> None:
        if trainer.graphs:
            self._before = graph_skips()  # the count is the process's: other runs in it may have added to it

    def on_step(self, trainer: Trainer, terms: dict[str, torch.Tensor]) -> None:
        if self._before is None:
            return
        self.skips, self._before = graph_skips() - self._before, None
        if self.skips and trainer.dist.main:
            print(f"run.cuda_graphs: torch.compile runs {self.skips} of the network's graphs without CUDA graphs, so "
                  "the steps are slower (TORCH_LOGS=cudagraphs says why)", file=sys.stderr)

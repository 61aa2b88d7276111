"""The SSZ training engine: one loop for a laptop CPU, one GPU and ``torchrun`` over many.

A run lives in a folder::

    run_dir/config.json        the full experiment config (also inside every checkpoint)
    run_dir/last.pt            the newest checkpoint (atomic; ``--resume`` continues from it)
    run_dir/model.safetensors  the shipped form of the newest generator (float16, config in the metadata)
    run_dir/metrics.csv        losses, learning rate, samples/s and evaluations per step
    run_dir/curves.png         training curves
    run_dir/examples.png       image | own view truth, prediction | novel view truth, prediction
    run_dir/tensorboard/       when TensorBoard is installed

Resuming restores the models, optimisers, scheduler, step, data position and every random generator, so on the
CPU the resumed run computes the same losses as one that never stopped (a replay buffer, whose samples are not
saved, refills from the stream instead). Ctrl-C, a ``time_limit`` or the end of the run write a checkpoint.
"""

from __future__ import annotations

import dataclasses
import math
import os
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import torch
import torch.nn.functional as F

from fruxel.errors import FruxelError
from fruxel.io import atomic_write
from fruxel.kernels.fpmode import flush_denormals

from ..config import TrainConfig, override
from ..export import build_discriminator, build_generator, save_shipped
from ..models.blocks import channels_last
from ..models.discriminator import hinge_d_loss, hinge_g_loss
from ..objective import SSZObjective, class_frequencies, class_weights
from . import distributed
from .checkpoint import LATEST, read_checkpoint, rng_state, save_checkpoint, set_rng_state
from .data import BlockPlan, BlockStream, ReplayBuffer, rank_range, to_device
from .logbook import CURVES, Logbook, plot_curves

SHIPPED = "model.safetensors"
"""File name of the shipped model in a run folder."""
EXAMPLES = "examples.png"
"""File name of the examples picture in a run folder."""
CONFIG = "config.json"
"""File name of the config in a run folder."""


class TrainingError(FruxelError, RuntimeError):
    """A run that cannot start or continue (bad data folder, nothing to resume, a config that does not fit)."""


@dataclass
class TrainResult:
    """What :func:`train` did."""

    step: int
    """Steps done in total (including those before a resume)."""
    samples: int
    """Training samples drawn in total (all ranks)."""
    seconds: float
    """Wall time of training steps in total (including before a resume), evaluation excluded."""
    interrupted: bool
    """True when Ctrl-C or the time limit stopped the run before its last step."""
    metrics: dict[str, Any]
    """The last evaluation's summary (empty when none ran)."""
    timings: dict[str, float]
    """With ``profile``: seconds spent per phase of the steps (``data``, ``forward``, ``shell``, ``backward``,
    ``optimizer``, ``discriminator``) after the first ``warm`` steps, and ``steps`` timed; else empty."""
    peak_memory: int
    """Peak bytes allocated on the CUDA device (0 on the CPU)."""
    losses: dict[str, float] = dataclasses.field(default_factory=dict)
    """The last logged training losses (mean over the last ``log_every`` steps): ``total``, ``ce``, ..."""


RESUME_SETTINGS = {"steps": "run", "time_limit": "run", "log_every": "run", "eval_every": "run",
                   "checkpoint_every": "run", "tensorboard": "run", "workers": "data"}
"""The settings :class:`Trainer`'s ``overrides`` may change, by name, and the part of the config each is in."""


def override_settings(config: TrainConfig, overrides: dict[str, Any]) -> TrainConfig:
    """``config`` with the settings of :data:`RESUME_SETTINGS` named in ``overrides`` changed.

    Raises:
        TrainingError: a setting that cannot be changed on resume.
        ConfigError: an impossible value.
    """
    changes: dict[str, dict[str, Any]] = {}
    for key, value in overrides.items():
        part = RESUME_SETTINGS.get(key)
        if part is None:
            raise TrainingError(f"{key!r} cannot be changed on resume; these can: {', '.join(RESUME_SETTINGS)}")
        changes.setdefault(part, {})[key] = value
    return override(config, changes, "").check()


def sim_config(config: TrainConfig) -> Any:
    """The simulator settings that make this experiment's samples (streaming)."""
    from fruxel.train.sim.config import AugmentConfig, ImageConfig, SimConfig

    m, d = config.model, config.data
    return SimConfig(grid=m.grid, image=ImageConfig(size=m.image_size[1], augment=AugmentConfig(enabled=d.augment)),
                     classes=m.classes, samples_per_scene=d.samples_per_scene,
                     splits=(("train", d.train_samples), ("test", d.test_samples)))


def _data_source(config: TrainConfig) -> tuple[Any, int, int]:
    """``(sim config or None, train samples, test samples)``, checking a shard folder against the model."""
    d, m = config.data, config.model
    if d.source == "stream":
        return sim_config(config), d.train_samples, d.test_samples
    from fruxel.train.sim.dataset import ShardDataset

    try:
        ds = ShardDataset(d.root, "train", verify=False)
    except ValueError as e:
        raise TrainingError(str(e)) from None
    sc = ds.config
    if sc.grid.shape != m.grid.shape or (sc.image_height, sc.image_width) != m.image_size:
        raise TrainingError(f"{d.root}: data set grid {sc.grid.shape} / image {sc.image_width} px does not fit the "
                            f"model's grid {m.grid.shape} / image {m.image_size[1]} px")
    try:
        test = sc.split_samples("test")
    except ValueError:
        test = 0
    return None, sc.split_samples("train"), test


def _schedule(config: TrainConfig) -> Callable[[int], float]:
    o, steps = config.optim, config.run.steps

    def factor(step: int) -> float:
        if step < o.warmup:
            return (step + 1) / o.warmup
        t = min(1.0, (step - o.warmup) / max(1, steps - o.warmup))
        return o.min_lr + (1.0 - o.min_lr) * 0.5 * (1.0 + math.cos(math.pi * t))

    return factor


def _param_groups(model: torch.nn.Module, weight_decay: float) -> list[dict[str, Any]]:
    decay, plain = [], []
    # Frozen parameters (ModelConfig.refine_frozen) are left out: they never get a gradient.
    for p in (p for p in model.parameters() if p.requires_grad):
        (decay if p.ndim > 1 else plain).append(p)
    return [{"params": decay, "weight_decay": weight_decay}, {"params": plain, "weight_decay": 0.0}]


def _adversarial_weight(config: TrainConfig, step: int) -> float:
    loss = config.loss
    if not loss.adversarial or step < loss.adversarial_start:
        return 0.0
    ramp = max(1, loss.adversarial_ramp)
    return loss.adversarial_weight * min(1.0, (step - loss.adversarial_start + 1) / ramp)


def load_eval_set(config: TrainConfig, count: int, workers: int = 0, device: str | None = None
                  ) -> tuple[torch.Tensor, torch.Tensor]:
    """The first ``count`` samples of the test split: ``(images (N, h, w, 3) uint8, labels (N, D, H, W) uint8)``.

    The test split's rooms come from seeds the training split never uses (the split name enters every seed).
    """
    from .data import Batches

    sim, _, n_test = _data_source(config)
    count = min(count, n_test)
    if count <= 0:
        raise TrainingError("the data has no test split to evaluate on")
    plan = BlockPlan(0, count, config.data.samples_per_scene, None)
    first, last = plan.rooms

    def factory(block: int, skip: int) -> BlockStream:
        # The stream ends after the blocks of ``count`` samples: the workers make nothing that is not used.
        return BlockStream(plan, config.data.source, "test", sim_config=sim, seed=config.data.seed,
                           root=config.data.root, first_block=block, skip=skip, device=device,
                           stop_block=last - first)

    batches = Batches(factory, count, min(workers, math.ceil(count / config.data.samples_per_scene)))
    try:
        b = next(batches)
    finally:
        batches.close()
    return b["image"], b["labels"]


class Trainer:
    """One run (see the module docstring); :meth:`fit` trains it.

    Args:
        config: the experiment (ignored on resume, where the checkpoint's config is used; may be None then).
        run_dir: the run's folder (created).
        resume: continue from ``run_dir/last.pt``.
        device: ``"cpu"``, ``"cuda"`` or None (CUDA when present).
        progress: show a progress bar (rank 0).
        overrides: settings to change, by name, e.g. ``{"time_limit": 540.0}``; on resume only those of
            :data:`RESUME_SETTINGS` (the others would make the continuation differ from the run it continues).
        profile: time the phases of every step after the first ``warm`` ones (synchronises the device at each
            phase boundary, so steps are slower; for benchmarks).
        warm: steps left out of the profile (start-up, autotuning, compilation).
        evaluation: evaluate (periodically and at the end); off for throughput measurements.
    """

    def __init__(self, config: TrainConfig | None, run_dir: str, *, resume: bool = False, device: str | None = None,
                 progress: bool = True, overrides: dict[str, Any] | None = None, profile: bool = False,
                 warm: int = 20, evaluation: bool = True) -> None:
        self.evaluation = evaluation
        self.profile = profile
        self.warm = warm
        self.timings: dict[str, float] = {}
        self.rates: list[float] = []
        self.run_dir = os.fsdecode(run_dir)
        self.saved_step: int | None = None
        """The step of the last checkpoint this trainer wrote (None before the first)."""
        self.ckpt = None
        if resume:
            path = os.path.join(self.run_dir, LATEST)
            if not os.path.exists(path):
                raise TrainingError(f"{path}: no checkpoint to resume from")
            self.ckpt = read_checkpoint(path)
            config = self.ckpt.config
        if config is None:
            raise TrainingError("a new run needs a config")
        if overrides:
            config = override_settings(config, overrides)
        self.config = config.check()
        self.dist = distributed.setup(device)
        self.progress = progress and self.dist.main
        os.makedirs(self.run_dir, exist_ok=True)

    # ------------------------------------------------------------------ set-up
    def _start_from(self, path: str) -> None:
        """Load ``run.init``'s generator weights into the fresh generator (see :class:`RunConfig`)."""
        from ..export import read_weights

        state, _, _ = read_weights(path)
        own = self.generator.state_dict()
        foreign = sorted(k for k in state if k not in own)
        reshaped = sorted(k for k in state if k in own and state[k].shape != own[k].shape)
        if foreign or reshaped:
            what = [f"{len(foreign)} it does not have ({', '.join(foreign[:3])})"] if foreign else []
            what += [f"{len(reshaped)} of another shape ({', '.join(reshaped[:3])})"] if reshaped else []
            raise TrainingError(f"{path}: run.init does not fit the model config: parameters {'; '.join(what)}")
        self.generator.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()}, strict=False)
        fresh = sorted(k for k in own if k not in state)
        if fresh and self.progress:
            print(f"run.init {path}: kept the fresh initialisation of {', '.join(fresh)}", file=sys.stderr)

    def _build(self) -> None:
        c, dev = self.config, self.dist.device
        cuda = dev.type == "cuda"
        if not cuda:
            if c.data.workers and "OMP_NUM_THREADS" not in os.environ:
                # The simulator's workers take cores too; more compute threads than free cores made CPU steps many
                # times slower (oversubscribed thread pools spin and wait on each other).
                cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
                torch.set_num_threads(max(1, cores - c.data.workers))
        torch.manual_seed(c.run.seed)
        self.generator = build_generator(c.model, checkpointing=c.run.checkpointing)
        if c.run.init and self.ckpt is None:
            self._start_from(c.run.init)
        self.generator = self.generator.to(dev)
        self.discriminator = build_discriminator(c.model).to(dev) if c.loss.adversarial else None
        self.channels_last = cuda and c.run.channels_last
        if self.channels_last:
            self.generator = channels_last(self.generator)
        # fused: one kernel for every parameter on CUDA (the per-tensor loop cost 13 ms a step on the H100).
        self.opt = torch.optim.AdamW(_param_groups(self.generator, c.optim.weight_decay), lr=c.optim.lr,
                                     betas=tuple(c.optim.betas), fused=cuda)
        self.sched = torch.optim.lr_scheduler.LambdaLR(self.opt, _schedule(c))
        self.d_opt = None
        if self.discriminator is not None:
            self.d_opt = torch.optim.Adam(self.discriminator.parameters(), lr=c.loss.discriminator_lr,
                                          betas=(0.5, 0.999))
        self.model = self.generator
        self.d_model = self.discriminator
        if self.dist.distributed:
            from torch.nn.parallel import DistributedDataParallel as DDP

            ids = [dev.index] if cuda else None
            self.model = DDP(self.generator, device_ids=ids)
            if self.discriminator is not None:
                self.d_model = DDP(self.discriminator, device_ids=ids)
        if c.run.compile:
            self.model = torch.compile(self.model)
        self.autocast = cuda and c.run.precision == "bf16"
        self.shell = None
        if c.loss.shell:
            from ..losses import ShellLoss, ShellLossConfig

            n = c.loss.shell_view_size
            self.shell = ShellLoss(c.model.grid, ShellLossConfig(
                novel_views=c.loss.shell_views, novel_size=(n, n), novel_hfov=c.model.grid.hfov, seed=c.run.seed,
                weight_own_view=c.loss.shell_own_view),
                rank=self.dist.rank)

    def _batches(self, position: tuple[int, int]) -> Any:
        from .data import Batches

        c, d = self.config, self.dist
        sim, n_train, _ = _data_source(c)
        try:
            lo, hi = rank_range(n_train, c.data.samples_per_scene, d.rank, d.world)
        except ValueError as e:
            where = c.data.root if c.data.source == "shards" else "data.train_samples"
            raise TrainingError(f"{where}: training split: {e}") from None
        plan = BlockPlan(lo, hi, c.data.samples_per_scene, None if c.data.source == "stream" else c.run.seed)
        per_rank = c.run.batch_size // d.world
        if c.data.replay:
            per_rank = max(1, math.ceil(per_rank / c.data.reuse))
        cuda_index = d.device.index if d.device.type == "cuda" else None
        sim_device = f"cuda:{cuda_index}" if cuda_index is not None else "cpu"

        def factory(block: int, skip: int) -> BlockStream:
            return BlockStream(plan, c.data.source, "train", sim_config=sim, seed=c.data.seed, root=c.data.root,
                               first_block=block, skip=skip, device=sim_device)

        return Batches(factory, per_rank, c.data.workers, pin=d.device.type == "cuda", position=position)

    # ------------------------------------------------------------------ state
    def _state(self, step: int, samples: int, seconds: float, position: tuple[int, int], weights: torch.Tensor,
               summary: dict[str, Any], losses: dict[str, float]) -> dict[str, Any]:
        return {
            "step": step,
            "samples": samples,
            "elapsed": seconds,
            "generator": self.generator.state_dict(),
            "discriminator": self.discriminator.state_dict() if self.discriminator is not None else None,
            "optimizer": self.opt.state_dict(),
            "d_optimizer": self.d_opt.state_dict() if self.d_opt is not None else None,
            "scheduler": self.sched.state_dict(),
            "data": {"position": list(position)},
            "class_weights": weights.detach().cpu(),
            "rng": rng_state(),
            "shell_poses": self.shell.state_dict() if self.shell is not None else None,
            "replay": self.replay.state_dict() if self.replay is not None else None,
            "summary": summary,
            "losses": losses,
        }

    def _restore(self, state: dict[str, Any]) -> None:
        self.generator.load_state_dict(state["generator"])
        self.opt.load_state_dict(state["optimizer"])
        self.sched.load_state_dict(state["scheduler"])
        if self.discriminator is not None and state.get("discriminator") is not None:
            self.discriminator.load_state_dict(state["discriminator"])
            self.d_opt.load_state_dict(state["d_optimizer"])
        if self.shell is not None and state.get("shell_poses"):
            self.shell.load_state_dict(state["shell_poses"])
        if self.replay is not None and state.get("replay"):
            self.replay.load_state_dict(state["replay"])
        set_rng_state(state["rng"])

    def _save(self, state: dict[str, Any]) -> None:
        if not self.dist.main:
            return
        save_checkpoint(os.path.join(self.run_dir, LATEST), state, self.config)
        self.saved_step = int(state["step"])
        summary = dict(state["summary"])
        summary.update(step=state["step"], samples=state["samples"], seconds=round(state["elapsed"], 1),
                       config=self.config.name)
        save_shipped(os.path.join(self.run_dir, SHIPPED), self.generator, self.config.model, summary)

    # ------------------------------------------------------------------ evaluation
    def _evaluate(self, step: int) -> dict[str, Any]:
        from ..eval.evaluate import evaluate
        from ..eval.visual import example_sheet

        c = self.config
        if self._eval_set is None:
            self._eval_set = load_eval_set(c, c.data.eval_samples, c.data.workers,
                                           "cuda" if self.dist.device.type == "cuda" else "cpu")
        images, labels = self._eval_set
        bs = max(1, c.run.batch_size // self.dist.world)
        batches = ((images[i:i + bs].permute(0, 3, 1, 2).float() / 255.0, labels[i:i + bs])
                   for i in range(0, len(images), bs))
        acc, kept = evaluate(self.generator, batches, c.model.grid, c.model.classes, device=self.dist.device,
                             autocast=self.autocast, keep=4)
        summary = acc.summary(c.model.classes.names)
        example_sheet(kept, c.model.grid, c.model.classes, os.path.join(self.run_dir, EXAMPLES),
                      title=f"{c.name}, step {step}: held-out rooms, mIoU {summary['miou']:.1f}")
        return summary

    # ------------------------------------------------------------------ the loop
    def fit(self) -> TrainResult:
        """Train to ``run.steps`` (or until Ctrl-C / the time limit) and return what happened.

        A run resumed at or after ``run.steps`` returns at once, with what its checkpoint says.

        Raises:
            KeyboardInterrupt: after saving a checkpoint, so that the caller exits like an interrupted program.
        """
        threads = torch.get_num_threads()
        # Zero-initialised residual projections make denormal floats early in training, which x86 cores handle in
        # microcode: flushing them to zero halved the tiny preset's CPU step time. Both the mode and the thread
        # count are process-wide, so they are put back for the caller.
        try:
            with flush_denormals(self.dist.device.type != "cuda"):
                return self._fit()
        finally:
            torch.set_num_threads(threads)

    def _fit(self) -> TrainResult:
        from tqdm import tqdm

        c, d = self.config, self.dist
        if self.ckpt is not None and int(self.ckpt.state["step"]) >= c.run.steps:
            st = self.ckpt.state
            return TrainResult(step=int(st["step"]), samples=int(st["samples"]), seconds=float(st["elapsed"]),
                               interrupted=False, metrics=dict(st.get("summary") or {}), timings={}, peak_memory=0,
                               losses=dict(st.get("losses") or {}))
        self._build()
        self._eval_set = None
        per_rank = c.run.batch_size // d.world
        if per_rank * d.world != c.run.batch_size:
            raise TrainingError(f"run.batch_size {c.run.batch_size} is not divisible by {d.world} ranks")
        if d.main:
            with atomic_write(os.path.join(self.run_dir, CONFIG), "w") as f:
                f.write(c.to_json() + "\n")
        self.replay = None
        if c.data.replay:
            m = c.model
            self.replay = ReplayBuffer(c.data.replay, (*m.image_size, 3), m.grid.shape, d.device,
                                       c.run.seed * 7919 + d.rank)
        step, samples, elapsed, position = 0, 0, 0.0, (0, 0)
        weights = None
        last_summary: dict[str, Any] = {}
        last_losses: dict[str, float] = {}
        if self.ckpt is not None:
            st = self.ckpt.state
            step, samples, elapsed = int(st["step"]), int(st["samples"]), float(st["elapsed"])
            position = tuple(int(v) for v in st["data"]["position"])
            weights = st["class_weights"].to(d.device)
            last_summary = dict(st.get("summary") or {})
            last_losses = dict(st.get("losses") or {})
        batches = self._batches(position)
        # Batches drawn ahead of their step, each with the data position before it: a checkpoint taken while some
        # are still unused records the position of the first of them, so that a resumed run draws them again.
        prefetched: list[tuple[tuple[int, int], dict[str, torch.Tensor]]] = []
        if weights is None:
            # Class frequencies from the first training batches, which are then trained on as usual.
            need = math.ceil(c.data.frequency_samples / max(1, batches.batch))
            for _ in range(need):
                prefetched.append((batches.position, next(batches)))
            counts = torch.as_tensor(class_frequencies([b["labels"] for _, b in prefetched], c.model.num_classes))
            if d.distributed:
                counts = counts.to(d.device)
                torch.distributed.all_reduce(counts)
                counts = counts.cpu() / d.world
            weights = torch.from_numpy(class_weights(counts.numpy(), c.loss.class_weight_power)).to(d.device)
        if self.ckpt is not None:
            self._restore(self.ckpt.state)
        objective = SSZObjective(c.loss, weights, self.shell, grid=c.model.grid)
        log = Logbook(self.run_dir, resume_step=step if self.ckpt is not None else None,
                      tensorboard=c.run.tensorboard) if d.main else None
        bar = tqdm(total=c.run.steps, initial=step, disable=not self.progress, unit="step", dynamic_ncols=True)
        sums: dict[str, torch.Tensor] = {}
        window_steps, window_start, window_samples = 0, time.perf_counter(), 0
        t_start = time.perf_counter()
        stop_at = t_start + c.run.time_limit if c.run.time_limit else math.inf
        interrupted = False

        def state() -> dict[str, Any]:
            position = prefetched[0][0] if prefetched else batches.position
            return self._state(step, samples, elapsed + time.perf_counter() - t_start, position, weights,
                               last_summary, last_losses)

        try:
            while step < c.run.steps:
                self._tick(step, None)
                host = prefetched.pop(0)[1] if prefetched else None
                if self.replay is not None:
                    if step == 0 or self.replay.filled < per_rank:
                        while self.replay.filled < per_rank:
                            self.replay.add(host if host is not None else next(batches))
                            host = None
                    else:
                        self.replay.add(host if host is not None else next(batches))
                    dev_batch = self.replay.draw(per_rank)
                    image, labels = to_device(dev_batch, d.device, self.channels_last)
                    surface_depth = dev_batch.get("surface_depth")
                else:
                    host = host if host is not None else next(batches)
                    image, labels = to_device(host, d.device, self.channels_last)
                    surface_depth = host.get("surface_depth")
                    if surface_depth is not None:
                        surface_depth = surface_depth.to(d.device, non_blocking=True)
                self._tick(step, "data")
                terms = self._step(step, image, labels, objective, surface_depth)
                for k, v in terms.items():
                    sums[k] = sums[k] + v if k in sums else v
                step += 1
                samples += c.run.batch_size
                window_steps += 1
                window_samples += c.run.batch_size
                bar.update(1)
                if step % c.run.log_every == 0 or step == c.run.steps:
                    # The mean over the steps summed (after a resume within a window, fewer than log_every).
                    values = {f"loss/{k}": float(v) / window_steps for k, v in sums.items()}
                    values = distributed.mean_scalars(d, values)
                    last_losses = {k.split("/", 1)[1]: v for k, v in values.items()}
                    now = time.perf_counter()
                    values["samples_per_s"] = window_samples / max(now - window_start, 1e-9)
                    self.rates.append(values["samples_per_s"])
                    values["lr"] = self.sched.get_last_lr()[0]
                    window_steps, window_start, window_samples, sums = 0, now, 0, {}
                    if log is not None:
                        log.log(step, values)
                    bar.set_postfix(loss=f"{values['loss/total']:.3f}", sps=f"{values['samples_per_s']:.0f}")
                if c.run.eval_every and step % c.run.eval_every == 0 and step < c.run.steps:
                    last_summary = self._eval_and_log(step, log)
                if c.run.checkpoint_every and step % c.run.checkpoint_every == 0 and step < c.run.steps:
                    self._save(state())
                if time.perf_counter() > stop_at:
                    interrupted = step < c.run.steps
                    break
        except KeyboardInterrupt:
            bar.close()
            final = state()
            # The data workers are stopped and waited for before the checkpoint is written (on Ctrl-C they exit
            # too): a worker dying as it exits must not break the write.
            batches.close()
            self._save(final)
            if log is not None:
                log.close()
            raise
        except BaseException:
            batches.close()
            raise
        bar.close()
        final = state()
        # The training data's workers (renderers, GPU contexts) are gone before the evaluation starts its own.
        batches.close()
        # Also after a time-limit stop: each chunk of a run that trains in time slices ends with its metrics.
        last_summary = final["summary"] = self._eval_and_log(step, log)
        self._save(final)
        if log is not None:
            plot_curves(log.rows, os.path.join(self.run_dir, CURVES), title=c.name)
            log.close()
        peak = torch.cuda.max_memory_allocated(d.device) if d.device.type == "cuda" else 0
        return TrainResult(step=step, samples=samples, seconds=final["elapsed"], interrupted=interrupted,
                           metrics=last_summary, timings=dict(self.timings), peak_memory=int(peak),
                           losses=last_losses)

    def _tick(self, step: int, phase: str | None) -> None:
        """With ``profile``: add the time since the last tick to ``phase`` (None starts a step)."""
        if not self.profile or step < self.warm:
            return
        if self.dist.device.type == "cuda":
            torch.cuda.synchronize(self.dist.device)  # a phase ends when its kernels have run
        now = time.perf_counter()
        if phase is None:
            self.timings["steps"] = self.timings.get("steps", 0.0) + 1.0
        else:
            self.timings[phase] = self.timings.get(phase, 0.0) + now - self._t_phase
        self._t_phase = now

    def _eval_and_log(self, step: int, log: Logbook | None) -> dict[str, Any]:
        summary: dict[str, Any] = {}
        if self.dist.main and self.evaluation:
            t = time.perf_counter()
            summary = self._evaluate(step)
            if log is not None:
                log.log(step, {f"eval/{k}": v for k, v in summary.items() if isinstance(v, float)} |
                        {f"eval/iou_{k}": v for k, v in summary["iou"].items() if v is not None} |
                        {"eval/seconds": time.perf_counter() - t})
                plot_curves(log.rows, os.path.join(self.run_dir, CURVES), title=self.config.name)
        distributed.barrier(self.dist)
        return summary

    def _step(self, step: int, image: torch.Tensor, labels: torch.Tensor, objective: SSZObjective,
              surface_depth: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
        c = self.config
        adv_w = _adversarial_weight(c, step)
        self.opt.zero_grad(set_to_none=True)
        with torch.autocast(self.dist.device.type, dtype=torch.bfloat16, enabled=self.autocast):
            out = self.model(image)
            self._tick(step, "forward")
            terms = objective(out, labels, surface_depth)
            self._tick(step, "loss")
            if adv_w > 0:
                d_plain = self.discriminator
                d_plain.requires_grad_(False)
                fake = d_plain(torch.softmax(out.logits.float(), dim=1), image)
                terms["adversarial"] = hinge_g_loss(fake)
                terms["total"] = terms["total"] + adv_w * terms["adversarial"]
                d_plain.requires_grad_(True)
        terms["total"].backward()
        self._tick(step, "backward")
        if c.optim.grad_clip:
            torch.nn.utils.clip_grad_norm_(self.generator.parameters(), c.optim.grad_clip)
        self.opt.step()
        self.sched.step()
        self._tick(step, "optimizer")
        if self.discriminator is not None and step >= c.loss.adversarial_start:
            self.d_opt.zero_grad(set_to_none=True)
            with torch.autocast(self.dist.device.type, dtype=torch.bfloat16, enabled=self.autocast):
                real_p = F.one_hot(labels.long(), c.model.num_classes).movedim(-1, 1).float()
                fake_p = torch.softmax(out.logits.detach().float(), dim=1)
                d_loss = hinge_d_loss(self.d_model(real_p, image), self.d_model(fake_p, image))
            d_loss.backward()
            self.d_opt.step()
            terms["discriminator"] = d_loss
            self._tick(step, "discriminator")
        return {k: v.detach() for k, v in terms.items()}


def train(config: TrainConfig, run_dir: str, *, resume: bool = False, device: str | None = None,
          progress: bool = True, overrides: dict[str, Any] | None = None, profile: bool = False) -> TrainResult:
    """Train (or continue) one run; see :class:`Trainer`."""
    try:
        trainer = Trainer(config, run_dir, resume=resume, device=device, progress=progress, overrides=overrides,
                          profile=profile)
        return trainer.fit()
    finally:
        distributed.teardown()



"""The training engine: one loop for a laptop CPU, one GPU and ``torchrun`` over many.

A run lives in a folder (:mod:`.run_folder`). :class:`Trainer` builds the run's state (:mod:`.state`), feeds the
plain step (:mod:`.step`) with batches of the data module (:mod:`fruxel.train.samples`), and hands the rest to its
callbacks (:mod:`.callbacks`): the metric log, the periodic evaluation, checkpoints and the time limit.

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
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fruxel.kernels.fpmode import flush_denormals

from ..config import TrainConfig, override
from . import distributed
from .callbacks import Callback, Checkpoints, Evaluation, GraphCheck, MetricLog, TimeLimit
from .checkpoint import LATEST, Checkpoint, read_checkpoint
from .data import camera_with_dropout, to_device
from .run_folder import CONFIG, RunFolder
from .state import TrainingError, TrainingState, new_state
from .step import PhaseTimer, Step

__all__ = ["RESUME_SETTINGS", "TrainResult", "Trainer", "TrainingError", "override_settings", "train"]


@dataclass
class TrainResult:
    """What :meth:`Trainer.fit` did."""

    step: int
    """Steps done in total (including those before a resume)."""
    samples: int
    """Training samples drawn in total (all ranks)."""
    seconds: float
    """Wall time of training steps in total (including before a resume), evaluation excluded."""
    interrupted: bool
    """True when the time limit stopped the run before its last step."""
    metrics: dict[str, Any]
    """The last evaluation's summary (empty when none ran)."""
    timings: dict[str, float]
    """With ``profile``: seconds spent per phase of the steps (:class:`~.step.PhaseTimer`); else empty."""
    peak_memory: int
    """Peak bytes allocated on the CUDA device (0 on the CPU)."""
    losses: dict[str, float] = dataclasses.field(default_factory=dict)
    """The last logged training losses (mean over the last ``log_every`` steps): ``total``, ``ce``, ..."""
    data_seconds: float = 0.0
    """Seconds this process waited for its batches in this call (host batches, the replay buffer and the copy to
    the device; what the steps' compute did not hide)."""
    graph_skips: int = 0
    """With CUDA graphs (:attr:`Trainer.graphs`): the network's compiled graphs run without them
    (:class:`~.callbacks.GraphCheck`); 0 otherwise."""


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
    return override(config, changes, "")


class Trainer:
    """One run; :meth:`fit` trains it.

    Args:
        config: the run's config (ignored on resume, where the checkpoint's config is used; may be None then).
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
        overwrite: a new run may replace the run its folder holds (else that is refused).

    Raises:
        TrainingError: nothing to resume, a folder that holds a run, another process training there.
    """

    def __init__(self, config: TrainConfig | None, run_dir: str | os.PathLike[str], *, resume: bool = False,
                 device: str | None = None, progress: bool = True, overrides: dict[str, Any] | None = None,
                 profile: bool = False, warm: int = 20, evaluation: bool = True, overwrite: bool = False) -> None:
        self.folder = RunFolder(run_dir)
        """The run's folder."""
        self.folder.check(resume=resume, overwrite=overwrite)
        self.resumed = resume
        """Whether this run continues a checkpoint."""
        self._overwrite = overwrite
        self._ckpt: Checkpoint | None = read_checkpoint(self.folder.file(LATEST)) if resume else None
        config = self._ckpt.config if self._ckpt is not None else config
        if config is None:
            raise TrainingError("a new run needs a config")
        self.config = override_settings(config, overrides) if overrides else config
        """The run's config."""
        from ..samples import SampleSource, split_size, train_split_size

        # data.eval_samples 0 turns the evaluation off: asked for no test samples, it would fail only once training
        # had ended, before the last checkpoint was written.
        evaluation = evaluation and self.config.data.eval_samples > 0
        # A data set that does not fit, or lacks the test split the evaluation reads, is refused before anything is
        # written (not after training, when the evaluation first reads it).
        source = SampleSource.of(self.config.data)
        train_split_size(source, self.config.model, self.config.data.train_samples)
        if evaluation:
            split_size(source, self.config.model, "test")
        self.dist = distributed.setup(device)
        """This process's place in the run (device, rank, world)."""
        self.progress = progress and self.dist.main
        self.timer = PhaseTimer(profile, warm, self.dist.device)
        self.log = MetricLog(self.progress)
        evaluator = Evaluation(self.log, evaluation)
        self.checkpoints = Checkpoints(self.log, evaluator)
        self.graph_check = GraphCheck()
        self.callbacks: list[Callback] = [self.log, evaluator, self.checkpoints, TimeLimit(), self.graph_check]
        """Called in this order at each point (:class:`~.callbacks.Callback`)."""
        self.state: TrainingState | None = None
        """The run's state, built by :meth:`fit`."""
        self.stop = False
        """Set by a callback to end the run after the current step."""
        self.autocast = self.dist.device.type == "cuda" and self.config.run.precision == "bf16"
        """Whether steps and evaluations run under bfloat16 autocast."""
        run = self.config.run
        self.graphs = run.compile and run.cuda_graphs and self.dist.device.type == "cuda"
        """Whether the steps replay the compiled network as CUDA graphs (``run.cuda_graphs``)."""

    @property
    def saved_step(self) -> int | None:
        """The step of the last checkpoint this trainer wrote (None before the first)."""
        return self.checkpoints.saved_step

    @property
    def rates(self) -> list[float]:
        """Samples per second of each logged window."""
        return self.log.rates

    # ------------------------------------------------------------------ set-up
    def build(self) -> tuple[TrainingState, Step]:
        """The run's state, fresh or as the checkpoint left it but for the models (:meth:`fit` restores those after
        counting the class weights), and the step around it (the network as the run trains it,
        :func:`training_module`); :meth:`fit` calls it."""
        c, dev = self.config, self.dist.device
        if dev.type != "cuda" and c.data.workers and "OMP_NUM_THREADS" not in os.environ:
            # The simulator's workers take cores too; more compute threads than free cores made CPU steps many
            # times slower (oversubscribed thread pools spin and wait on each other).
            cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count() or 1
            torch.set_num_threads(max(1, cores - c.data.workers))
        torch.manual_seed(c.run.seed)
        network = c.model.build(checkpointing=c.run.checkpointing)
        if c.run.init and self._ckpt is None:
            self._start_from(network, c.run.init)
        state = new_state(c, network.to(dev), dev, self.dist.rank)
        if self._ckpt is not None:
            state.load_counters(self._ckpt.state, dev)
        model = network
        if dev.type == "cuda" and c.run.channels_last:
            from ..models.blocks import channels_last

            model = channels_last(network)
        ids = [dev.index] if dev.type == "cuda" else None
        model = training_module(model, compile=c.run.compile, graphs=self.graphs, ddp=self.dist.distributed,
                                device_ids=ids)
        d_model = state.discriminator
        if self.dist.distributed and d_model is not None:
            d_model = _ddp(d_model, ids)
        return state, Step(model, d_model, None, self.autocast, self.timer, graphs=self.graphs)

    def _start_from(self, network: torch.nn.Module, path: str) -> None:
        """Load ``run.init``'s network weights into the fresh network (see :class:`~fruxel.train.config.RunConfig`)."""
        from ..model_files import read_model_file

        init = read_model_file(path)
        theirs_names, own_names = list(init.config.classes.names), list(self.config.model.classes.names)
        if theirs_names != own_names and len(theirs_names) == len(own_names):
            # Same shapes: which parameters hold one entry per class cannot be told, so none could be mapped.
            raise TrainingError(f"{path}: run.init has {len(theirs_names)} other classes than the model config's "
                                f"({', '.join(theirs_names)}); as many classes must have the same names in order")
        own = network.state_dict()
        state = {k: v for k, v in init.state.items() if k in own}
        foreign = sorted(k for k in init.state if k not in own)
        reshaped = sorted(k for k in state if state[k].shape != own[k].shape)
        mapped = {k: _by_class(state[k], own[k], theirs_names, own_names) for k in reshaped}
        unfit = [k for k, v in mapped.items() if v is None]
        if foreign or unfit:
            what = [f"{len(foreign)} it does not have ({', '.join(foreign[:3])})"] if foreign else []
            what += [f"{len(unfit)} of another shape ({', '.join(unfit[:3])})"] if unfit else []
            raise TrainingError(f"{path}: run.init does not fit the model config: parameters {'; '.join(what)}")
        state.update(mapped)
        network.load_state_dict({k: v.to(own[k].dtype) for k, v in state.items()}, strict=False)
        fresh = sorted(k for k in own if k not in state)
        new_classes = [n for n in own_names if n not in theirs_names]
        if self.progress and (fresh or (reshaped and new_classes)):
            kept = ([", ".join(fresh)] if fresh else []) + ([f"the classes {', '.join(new_classes)}"]
                                                            if reshaped and new_classes else [])
            print(f"run.init {path}: kept the fresh initialisation of {'; '.join(kept)}", file=sys.stderr)

    def _sim_device(self) -> str:
        """The Warp device a streamed simulator's workers draw on: the rank's CUDA device, else the CPU."""
        d = self.dist.device
        return f"cuda:{d.index}" if d.type == "cuda" and d.index is not None else "cpu"

    def _batches(self) -> Any:
        """The rank's training batches from the state's data position."""
        from ..samples import SampleSource, gpu_sharing_hint, train_split_size, training_batches

        c, d, s = self.config, self.dist, self.state
        source = SampleSource.of(c.data)
        per_rank = c.run.batch_size // d.world
        if c.data.replay:
            per_rank = max(1, math.ceil(per_rank / c.data.reuse))
        sim_device = self._sim_device()
        hint = gpu_sharing_hint(source, c.data.workers, sim_device)
        if hint and self.progress and d.rank == 0:
            print(hint, file=sys.stderr)
        return training_batches(source, c.model, train_split_size(source, c.model, c.data.train_samples),
                                batch=per_rank, workers=c.data.workers, rank=d.rank, world=d.world,
                                position=s.position, shuffle_seed=c.run.seed, pin=d.device.type == "cuda",
                                device=sim_device)

    def _class_weights(self, batches: Any) -> None:
        """Count the class frequencies on the first training batches (kept in :attr:`_prefetched`, trained on as
        usual) and set the state's cross-entropy weights, averaged over the ranks."""
        from ..objective import class_frequencies, class_weights

        c, d = self.config, self.dist
        for _ in range(math.ceil(c.data.frequency_samples / max(1, batches.batch))):
            self._prefetched.append((batches.position, next(batches)))
        counts = torch.as_tensor(class_frequencies([b["labels"] for _, b in self._prefetched], c.model.num_classes))
        if d.distributed:
            counts = counts.to(d.device)
            torch.distributed.all_reduce(counts)
            counts = counts.cpu() / d.world
        self.state.class_weights = torch.from_numpy(class_weights(counts.numpy(), c.loss.class_weight_power)).to(
            d.device)

    def checkpoint_state(self) -> dict[str, Any]:
        """The state to checkpoint now: batches drawn ahead of their step are drawn again by a resumed run, so the
        data position is that of the first of them."""
        s = self.state
        s.position = self._prefetched[0][0] if self._prefetched else self._stream.position
        return s.state_dict()

    # ------------------------------------------------------------------ the loop
    def fit(self) -> TrainResult:
        """Train to ``run.steps`` (or until Ctrl-C / the time limit) and return what happened.

        A run resumed at or after ``run.steps`` returns at once, with what its checkpoint says.

        Raises:
            KeyboardInterrupt: after saving a checkpoint, so that the caller exits like an interrupted program.
            TrainingError: see the class; a checkpoint that could not be written.
        """
        if self._ckpt is not None and int(self._ckpt.state["step"]) >= self.config.run.steps:
            st = self._ckpt.state
            return TrainResult(step=int(st["step"]), samples=int(st["samples"]), seconds=float(st["elapsed"]),
                               interrupted=False, metrics=dict(st.get("summary") or {}), timings={}, peak_memory=0,
                               losses=dict(st.get("losses") or {}))
        threads = torch.get_num_threads()
        # Zero-initialised residual projections make denormal floats early in training, which x86 cores handle in
        # microcode: flushing them to zero speeds CPU steps up. Both the mode and the thread count are
        # process-wide, so they are put back for the caller.
        try:
            with flush_denormals(self.dist.device.type != "cuda"):
                return self._fit()
        finally:
            torch.set_num_threads(threads)
            self.folder.release()

    def _fit(self) -> TrainResult:
        from ..samples import SampleSource, check_mps_clients

        c, d = self.config, self.dist
        if c.run.batch_size % d.world:
            raise TrainingError(f"run.batch_size {c.run.batch_size} is not divisible by {d.world} ranks")
        check_mps_clients(SampleSource.of(c.data), c.data.workers, self._sim_device())
        if d.main:
            self.folder.claim(resume=self.resumed, overwrite=self._overwrite)
        self.state, step = self.build()
        # Batches drawn ahead of their step, each with the data position before it (see checkpoint_state).
        self._prefetched: list[tuple[tuple[int, int], dict[str, torch.Tensor]]] = []
        self._data_total = 0.0
        self._stream = self._batches()
        try:
            if self.state.class_weights is None:
                self._class_weights(self._stream)
            if self._ckpt is not None:
                self.state.load_models(self._ckpt.state)
            from ..objective import SSZObjective

            step.objective = SSZObjective(c.loss, self.state.class_weights, self.state.shell)
            if d.main:
                from fruxel.io import atomic_write

                with atomic_write(self.folder.file(CONFIG), "w") as f:
                    f.write(c.to_json() + "\n")
            for cb in self.callbacks:
                cb.on_start(self)
            interrupted = self._loop(step)
        finally:
            self._stream.close()
            for cb in self.callbacks:
                cb.on_close(self)
        peak = torch.cuda.max_memory_allocated(d.device) if d.device.type == "cuda" else 0
        s = self.state
        return TrainResult(step=s.step, samples=s.samples, seconds=s.elapsed, interrupted=interrupted,
                           metrics=s.summary, timings=dict(self.timer.seconds), peak_memory=int(peak),
                           losses=s.losses, data_seconds=self._data_total, graph_skips=self.graph_check.skips)

    def _loop(self, step: Step) -> bool:
        """The steps, then the callbacks' ``on_stop``; returns whether the time limit cut the run short."""
        c, s = self.config, self.state
        try:
            for image, labels, camera in self._feed():
                t = time.perf_counter()
                terms = step(s, image, labels, camera)
                s.step += 1
                s.samples += c.run.batch_size
                s.elapsed += time.perf_counter() - t + self._data_seconds
                for cb in self.callbacks:
                    cb.on_step(self, terms)
                if self.stop:
                    break
        except KeyboardInterrupt:
            # The data workers are stopped and waited for before the checkpoint is written (on Ctrl-C they exit
            # too): a worker dying as it exits must not break the write.
            self._stream.close()
            for cb in self.callbacks:
                cb.on_stop(self, interrupted=True)
            raise
        # The training data's workers (renderers, GPU contexts) are gone before the evaluation starts its own.
        self._stream.close()
        for cb in self.callbacks:
            cb.on_stop(self, interrupted=False)
        return s.step < c.run.steps

    def _feed(self) -> Iterator[tuple[torch.Tensor, torch.Tensor, Any]]:
        """The batches of the steps to come, on the training device (through the replay buffer when there is one),
        with what the network is told of their cameras (None for a network that reads none); ``_data_seconds`` is
        the time the last one took."""
        c, s, dev = self.config, self.state, self.dist.device
        per_rank = c.run.batch_size // self.dist.world
        channels_last = dev.type == "cuda" and c.run.channels_last
        while s.step < c.run.steps:
            t = time.perf_counter()
            self.timer.tick(s.step, None)
            host = self._prefetched.pop(0)[1] if self._prefetched else None
            if s.replay is not None:
                if s.step == 0 or s.replay.filled < per_rank:
                    # The ring is filled before the first draw (and after a resume, whose ring starts empty).
                    while s.replay.filled < per_rank:
                        s.replay.add(host if host is not None else next(self._stream))
                        host = None
                else:
                    s.replay.add(host if host is not None else next(self._stream))
                batch = s.replay.draw(per_rank)
            else:
                batch = host if host is not None else next(self._stream)
            image, labels = to_device(batch, dev, channels_last)
            camera = None
            if c.model.reads_camera:
                # Drawn from the run's seed, the step and the rank: a resumed run withholds the same pieces.
                rng = np.random.default_rng((c.run.seed, s.step, self.dist.rank))
                camera = camera_with_dropout(batch["camera"], c.data.camera_dropout, rng, dev)
            self.timer.tick(s.step, "data")
            self._data_seconds = time.perf_counter() - t
            self._data_total += self._data_seconds
            yield image, labels, camera


def train(config: TrainConfig, run_dir: str, *, resume: bool = False, device: str | None = None,
          progress: bool = True, overrides: dict[str, Any] | None = None, profile: bool = False,
          overwrite: bool = False) -> TrainResult:
    """Train (or continue) one run; see :class:`Trainer`."""
    try:
        trainer = Trainer(config, run_dir, resume=resume, device=device, progress=progress, overrides=overrides,
                          profile=profile, overwrite=overwrite)
        return trainer.fit()
    finally:
        distributed.teardown()


def training_module(model: torch.nn.Module, *, compile: bool, graphs: bool, ddp: bool,
                    device_ids: list[int] | None = None) -> torch.nn.Module:
    """``model`` as a run trains it: compiled (``run.compile``; its passes replayed as CUDA graphs with ``graphs``),
    then, with ``ddp``, wrapped by DistributedDataParallel on ``device_ids`` (None on the CPU).

    Compiled before DDP wraps it, every rank runs the graph one GPU runs: one graph, which CUDA graphs replay whole.
    Compiling the DDP-wrapped network instead split it at DDP's buckets, and two GPUs scaled worse that way
    (BENCHMARKS.md "Multi-GPU training").
    """
    if compile:
        model = torch.compile(model, mode="reduce-overhead" if graphs else None)
    return _ddp(model, device_ids) if ddp else model


def _ddp(module: torch.nn.Module, device_ids: list[int] | None) -> torch.nn.Module:
    """``module`` in DistributedDataParallel without the sync of its buffers before each forward pass.

    That sync (of batch norm's running statistics) is a collective where every forward waits for the slowest rank.
    Training normalises with each batch's own statistics anyway; the running ones (evaluation's) are rank 0's,
    which the checkpoints hold. torch 2.13 names the switch ``forward_sync_buffers`` (still syncing once at the
    start); earlier versions ``broadcast_buffers``.
    """
    import inspect

    from torch.nn.parallel import DistributedDataParallel as DDP

    names = inspect.signature(DDP.__init__).parameters
    off = {"forward_sync_buffers": False} if "forward_sync_buffers" in names else {"broadcast_buffers": False}
    return DDP(module, device_ids=device_ids, **off)


def _by_class(theirs: torch.Tensor, own: torch.Tensor, their_names: Sequence[str],
              own_names: Sequence[str]) -> torch.Tensor | None:
    """``theirs`` (a parameter of a model with other classes) laid out for this model's classes, or None.

    Each dimension that differs must hold one entry per class (followed by any number of other entries, as many in
    both): each class this model shares by name with the init model takes that class's entries, a new class keeps
    ``own``'s fresh values and the trailing entries follow the classes. Any other difference gives None.

    Args:
        theirs: the init model's parameter, any shape and dtype.
        own: the fresh parameter of this model, of the same rank.
        their_names: the init model's class names (its class order).
        own_names: this model's class names.

    Returns:
        A tensor of ``own``'s shape and ``theirs``'s dtype, or None when the shapes differ otherwise.
    """
    n_theirs, n_own = len(their_names), len(own_names)
    their_names, own_names = list(their_names), list(own_names)
    if theirs.dim() != own.dim():
        return None
    src: list[torch.Tensor] = []
    dst: list[torch.Tensor] = []
    for a, b in zip(theirs.shape, own.shape, strict=True):
        pairs = [(i, i) for i in range(a)]
        if a != b:
            extra = a - n_theirs
            if extra < 0 or b - n_own != extra:
                return None
            pairs = [(their_names.index(n), i) for i, n in enumerate(own_names) if n in their_names]
            pairs += [(n_theirs + j, n_own + j) for j in range(extra)]
        # Index tensors shaped to broadcast as an outer product (numpy's ix_) over all dimensions.
        shape = [1] * theirs.dim()
        shape[len(src)] = -1
        src.append(torch.tensor([p[0] for p in pairs], dtype=torch.long).reshape(shape))
        dst.append(torch.tensor([p[1] for p in pairs], dtype=torch.long).reshape(shape))
    out = own.detach().clone().to(theirs.dtype)
    out[tuple(dst)] = theirs[tuple(src)]
    return out

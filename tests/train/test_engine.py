"""The SSZ training engine on the CPU: overfitting, checkpoints, exact resume, Ctrl-C, DDP, teardown.

Everything trains a 16^3 SSZ from 32^2 images with three levels and narrow layers, a few samples a batch and a
few steps, with the simulator streaming in this process (``data.workers = 0``) or a small shard data set made by
``fruxel.train.sim.writer.generate``; the file takes well under two minutes on two cores.
"""

from __future__ import annotations

import csv
import dataclasses
import os
import socket
import sys
import time
import warnings
from pathlib import Path
from typing import Any

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("torch_one_thread")

from fruxel.classes import DEFAULT_CLASSES, HOME_CLASSES  # noqa: E402
from fruxel.train.config import TrainConfig, override  # noqa: E402
from fruxel.train.engine.callbacks import TimeLimit  # noqa: E402
from fruxel.train.engine.checkpoint import (  # noqa: E402
    FORMAT,
    LATEST,
    CheckpointError,
    read_checkpoint,
    rng_state,
    save_checkpoint,
)
from fruxel.train.engine.run_folder import SHIPPED  # noqa: E402
from fruxel.train.engine.step import PhaseTimer  # noqa: E402
from fruxel.train.engine.trainer import Trainer, TrainingError  # noqa: E402
from fruxel.train.eval.evaluate import evaluate  # noqa: E402
from fruxel.train.model_files import load_model, read_model_file, save_model  # noqa: E402
from fruxel.train.objective import SSZObjective, class_frequencies, class_weights  # noqa: E402
from fruxel.train.rules import NO_RULES  # noqa: E402
from fruxel.train.samples import Batches, BlockPlan, BlockStream, SampleSource  # noqa: E402
from fruxel.train.samples import sim_config as make_sim_config  # noqa: E402
from fruxel.train.sim.writer import generate  # noqa: E402

TINY: dict[str, Any] = {
    "preset": "tiny", "name": "engine-test",
    "model": {"grid": {"width": 16, "height": 16, "depth": 16}, "levels": 3, "stem": 8, "encoder": [8, 12, 16],
              "encoder_blocks": [1, 1, 1], "topdown": [8, 12, 16], "decoder": [4, 8, 12],
              "decoder_blocks": [1, 1, 1]},
    "loss": {"discriminator": [8]},
    "data": {"world": "flat", "camera": "robot", "workers": 0, "samples_per_scene": 4, "train_samples": 64,
             "test_samples": 4, "eval_samples": 4,
             "frequency_samples": 4},
    "optim": {"warmup": 2},
    "run": {"steps": 8, "batch_size": 2, "log_every": 1, "eval_every": 0, "checkpoint_every": 0,
            "tensorboard": False},
}
"""A 16^3 SSZ from 32^2 images that trains a step in about a tenth of a second on one core."""


def tiny(changes: dict[str, Any] | None = None) -> TrainConfig:
    """:data:`TINY` with ``changes`` (nested as in a config file)."""
    base = override(TrainConfig.from_dict(TINY), {"model": {"classes": DEFAULT_CLASSES.to_dict()}}, "")
    return override(base, changes or {}, "")


def sim_config(config: TrainConfig) -> Any:
    """The simulator settings of a config's streamed samples."""
    d = config.data
    return make_sim_config(config.model, SampleSource.of(d), (("train", d.train_samples), ("test", d.test_samples)))


@pytest.fixture(scope="module")
def shards(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A data set of :data:`TINY`'s grid and images: 16 training samples (4 rooms of 4), 4 test samples."""
    out = tmp_path_factory.mktemp("shards")
    sim = dataclasses.replace(sim_config(tiny()), splits=(("train", 16), ("test", 4)), shard_size=4)
    generate(str(out), sim, 0, progress=False)
    return out


def _rows(run: Path) -> dict[int, dict[str, str]]:
    """The training rows of a run's metrics.csv by step: losses and learning rate."""
    with open(run / "metrics.csv", newline="") as f:
        return {int(r["step"]): {k: v for k, v in r.items() if k.startswith("loss/") or k == "lr"}
                for r in csv.DictReader(f) if r.get("loss/total")}


def _interrupt_at(monkeypatch: pytest.MonkeyPatch, at: int) -> None:
    """Make the next Trainer raise KeyboardInterrupt (as Ctrl-C does) when step ``at`` starts."""
    tick = PhaseTimer.tick

    def interrupting(self: PhaseTimer, step: int, phase: str | None) -> None:
        if phase is None and step == at:
            raise KeyboardInterrupt
        tick(self, step, phase)

    monkeypatch.setattr(PhaseTimer, "tick", interrupting)


def _assert_same_tensors(a: Any, b: Any, where: str = "") -> None:
    """Nested dicts / lists of tensors and plain values are identical (tensors bit for bit)."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor) and a.dtype == b.dtype and torch.equal(a, b), where
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), where
        for k in a:
            _assert_same_tensors(a[k], b[k], f"{where}.{k}")
    elif isinstance(a, (list, tuple)):
        assert isinstance(b, (list, tuple)) and len(a) == len(b), where
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            _assert_same_tensors(x, y, f"{where}[{i}]")
    else:
        assert a == b, where


def _batch(config: TrainConfig, root: Path | None, count: int, split: str = "train"
           ) -> tuple[torch.Tensor, torch.Tensor]:
    """The first ``count`` samples of a split: images ``(N, 3, h, w)`` float in [0, 1], labels ``(N, D, H, W)``
    uint8."""
    if root is not None:
        from fruxel.train.sim.dataset import ShardDataset

        ds = ShardDataset(root, split)
        samples = [ds.sample(i) for i in range(count)]
        ds.close()
    else:
        from fruxel.train.sim.sample import SampleMaker

        with SampleMaker(sim_config(config), config.data.seed) as maker:
            samples = [maker.make(split, i) for i in range(count)]
    image = torch.from_numpy(np.stack([s.image for s in samples])).permute(0, 3, 1, 2).float() / 255.0
    return image, torch.from_numpy(np.stack([s.labels for s in samples]))


# ---------------------------------------------------------------------------------------------- learning
@pytest.mark.slow
def test_overfits_one_fixed_batch(tmp_path: Path) -> None:
    """The engine, trained on one room of two samples (every batch is the same two), drives the loss far below its
    start, and the own-view first-hit accuracy of conventions section 9 on those samples rises well above the untrained
    network's."""
    config = tiny({"data": {"train_samples": 2, "samples_per_scene": 2, "frequency_samples": 2},
                   "optim": {"lr": 0.01, "warmup": 5}, "run": {"steps": 100, "batch_size": 2}})
    image, labels = _batch(config, None, 2)
    grid, classes = config.model.grid, config.model.classes

    def accuracy(generator: torch.nn.Module) -> float:
        acc, _ = evaluate(generator, NO_RULES, [(image, labels)], grid, classes, device=torch.device("cpu"),
                          novel=False)
        return acc.summary(classes.names)["own_view_accuracy"]

    torch.manual_seed(config.run.seed)  # the initialisation the trainer starts from
    before = accuracy(config.model.build())
    result = Trainer(config, tmp_path, device="cpu", progress=False, evaluation=False).fit()
    assert result.step == 100 and result.samples == 200
    losses = [float(r["loss/total"]) for r in _rows(tmp_path).values()]
    assert len(losses) == 100
    first, last = np.mean(losses[:3]), np.mean(losses[-3:])
    assert last < 0.3 * first, (first, last)
    after = accuracy(load_model(tmp_path / LATEST).network)
    assert after > before + 10.0 and after > 50.0, (before, after)


# ---------------------------------------------------------------------------------------------- checkpoints
def test_checkpoint_round_trip(tmp_path: Path) -> None:
    """A checkpoint reads back with the same tensors (models, optimiser moments, random states) and config."""
    config = tiny()
    torch.manual_seed(0)
    gen = config.model.build()
    opt = torch.optim.AdamW(gen.parameters(), lr=1e-3)
    image, labels = torch.rand(2, 3, 32, 32), torch.randint(0, 7, (2, 16, 16, 16), dtype=torch.uint8)
    weights = torch.from_numpy(class_weights(class_frequencies([labels], 7), 0.5))
    SSZObjective(config.loss, weights)(gen(image), labels)["total"].backward()
    opt.step()
    state = {"step": 7, "samples": 14, "elapsed": 1.5, "generator": gen.state_dict(), "optimizer": opt.state_dict(),
             "data": {"position": [3, 1]}, "class_weights": weights, "rng": rng_state(),
             "summary": {"miou": 12.5, "iou": {"wall": None}}, "losses": {"total": 2.0}}
    path = tmp_path / LATEST
    save_checkpoint(path, state, config)
    assert sorted(p.name for p in tmp_path.iterdir()) == [LATEST]  # no temporary file left
    ck = read_checkpoint(path)
    assert ck.config == config
    _assert_same_tensors({k: ck.state[k] for k in state}, state)
    assert ck.state["format"] == FORMAT
    # The generator the checkpoint holds loads for prediction, with the same weights.
    loaded = load_model(path)
    assert loaded.config == config.model and loaded.rules == NO_RULES
    _assert_same_tensors(loaded.network.state_dict(), gen.state_dict())


class _Trap:
    """Unpickling this creates the file ``path`` (what a hostile checkpoint could do with any callable)."""

    def __init__(self, path: str) -> None:
        self.path = path

    def __reduce__(self) -> tuple[Any, ...]:
        return (open, (self.path, "w"))


def test_checkpoint_holding_a_pickled_object_is_refused_without_running_it(tmp_path: Path) -> None:
    marker = tmp_path / "pwned"
    path = tmp_path / LATEST
    torch.save({"format": FORMAT, "version": 1, "config": tiny().to_json(), "step": 1, "generator": {},
                "payload": _Trap(str(marker))}, path)
    with pytest.raises(CheckpointError, match="refused") as e:
        read_checkpoint(path)
    assert str(path) in str(e.value) and "weights_only=False" not in str(e.value)
    with pytest.raises(CheckpointError, match="refused"):
        load_model(path)
    with pytest.raises(CheckpointError, match="refused"):
        Trainer(None, tmp_path, resume=True, device="cpu")
    assert not marker.exists()


# ---------------------------------------------------------------------------------------------- resume
@pytest.mark.slow
@pytest.mark.parametrize("source", ["shards", "stream"])
def test_resume_equals_an_uninterrupted_run(tmp_path: Path, shards: Path, monkeypatch: pytest.MonkeyPatch,
                                            source: str) -> None:
    """8 steps in one go against 4 steps, Ctrl-C, and 4 resumed: the same losses at every step and bit-identical
    weights and optimiser state at the end (data position, random states, optimiser and schedule restored).

    Batches of 3 from rooms of 4 samples cross room boundaries; 15 samples for the class frequencies are 5
    batches drawn before the first step, so the interruption at step 4 falls while one is still unused; the shards'
    16 training samples run out after 5 steps, so the resumed run goes on in the second epoch's order. The
    streaming run evaluates every 3 steps, which must not disturb training either.
    """
    changes = {"data": {"frequency_samples": 15}, "run": {"batch_size": 3}}
    if source == "shards":
        changes["data"].update(source="shards", root=str(shards))
    else:
        changes["run"]["eval_every"] = 3
    config = tiny(changes)
    evaluation = source == "stream"

    whole = tmp_path / "whole"
    Trainer(config, whole, device="cpu", progress=False, evaluation=evaluation).fit()

    parts = tmp_path / "parts"
    with monkeypatch.context() as m:
        _interrupt_at(m, 4)
        with pytest.raises(KeyboardInterrupt):
            Trainer(config, parts, device="cpu", progress=False, evaluation=evaluation).fit()
    assert read_checkpoint(parts / LATEST).state["step"] == 4
    resumed = Trainer(None, parts, resume=True, device="cpu", progress=False, evaluation=evaluation).fit()
    assert resumed.step == 8 and resumed.samples == 24

    a, b = _rows(whole), _rows(parts)
    assert sorted(a) == sorted(b) == list(range(1, 9))
    assert a == b
    sa, sb = read_checkpoint(whole / LATEST).state, read_checkpoint(parts / LATEST).state
    for key in ("generator", "optimizer", "scheduler", "data", "class_weights", "rng", "step", "samples"):
        _assert_same_tensors(sa[key], sb[key], key)


@pytest.mark.slow
def test_a_run_resumes_on_more_ranks(tmp_path: Path, shards: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A run started in one process goes on under two DDP ranks (a lent machine with more GPUs): the global batch
    is split between them, the step count and samples go on from the checkpoint, and the checkpoint it writes
    resumes again in one process."""
    config = tiny({"data": {"source": "shards", "root": str(shards)}, "run": {"steps": 6, "batch_size": 4}})
    with monkeypatch.context() as m:
        _interrupt_at(m, 2)
        with pytest.raises(KeyboardInterrupt):
            Trainer(config, tmp_path, device="cpu", progress=False, evaluation=False).fit()
    before = read_checkpoint(tmp_path / LATEST).state
    assert before["step"] == 2
    torch.multiprocessing.spawn(_resume_rank, args=(2, _free_port(), str(tmp_path)), nprocs=2, join=True)
    assert (tmp_path / "resumed.txt").read_text().split() == ["4", "16"]
    after = read_checkpoint(tmp_path / LATEST).state
    assert after["step"] == 4 and after["samples"] == 16
    assert any(not torch.equal(a, b) for a, b in zip(before["generator"].values(), after["generator"].values(),
                                                      strict=True))
    assert Trainer(None, tmp_path, resume=True, device="cpu", progress=False, evaluation=False,
                   overrides={"steps": 5}).fit().step == 5


@pytest.mark.slow
def test_ctrl_c_before_the_loop_and_resuming_a_finished_run(tmp_path: Path, shards: Path,
                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """Ctrl-C at step 0 still leaves a checkpoint (the class weights it needs included); a run resumed at its
    last step returns at once; settings that would change the run are refused on resume."""
    config = tiny({"data": {"source": "shards", "root": str(shards)}, "run": {"steps": 2}})
    with monkeypatch.context() as m:
        _interrupt_at(m, 0)
        with pytest.raises(KeyboardInterrupt):
            Trainer(config, tmp_path, device="cpu", progress=False, evaluation=False).fit()
    st = read_checkpoint(tmp_path / LATEST).state
    assert st["step"] == 0 and st["data"]["position"] == [0, 0] and st["class_weights"].shape == (7,)
    assert Trainer(None, tmp_path, resume=True, device="cpu", progress=False, evaluation=False).fit().step == 2
    stamp = (tmp_path / LATEST).stat().st_mtime_ns
    again = Trainer(None, tmp_path, resume=True, device="cpu", progress=False).fit()
    assert again.step == 2 and again.losses and (tmp_path / LATEST).stat().st_mtime_ns == stamp
    with pytest.raises(TrainingError, match="batch_size"):
        Trainer(None, tmp_path, resume=True, device="cpu", overrides={"batch_size": 4})


# ---------------------------------------------------------------------------------------------- DDP
def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def _end_rank() -> None:
    """End a spawned rank's process once its results are written, skipping the interpreter's teardown: torch 2.13
    aborts there now and then ("terminate called without an active exception", SIGABRT, after the work was done;
    once in CI's slow tests here, as in the data workers, :func:`fruxel.train.samples._init_worker`), which failed
    the test of a rank that had done everything right."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


def _ddp_rank(rank: int, world: int, port: int, config_json: str, batch_file: str, out: str) -> None:
    """One process of :func:`test_ddp_gradients_match_one_process`: the engine's own set-up (``torchrun``'s
    environment, gloo, DDP around the generator), then the gradients of this rank's half of the batch, averaged
    by DDP's all-reduce."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    from torch.nn.parallel import DistributedDataParallel

    from fruxel.train.engine import distributed

    config = TrainConfig.from_json(config_json)
    trainer = Trainer(config, out, device="cpu", progress=False)
    state, step = trainer.build()
    assert isinstance(step.model, DistributedDataParallel) and trainer.dist.world == world
    # No buffer sync before each forward (a wait for the slowest rank); the attribute's name is torch's older one.
    assert step.model.broadcast_buffers is False
    batch = torch.load(batch_file, weights_only=True)
    per = len(batch["image"]) // world
    half = slice(rank * per, (rank + 1) * per)
    grads = {}
    for mode, objective in _objectives(config, batch["weights"]).items():
        state.network.train(mode == "train")
        state.network.zero_grad(set_to_none=True)
        objective(step.model(batch["image"][half]), batch["labels"][half])["total"].backward()
        grads[mode] = {n: p.grad.clone() for n, p in state.network.named_parameters()}
    torch.save(grads, os.path.join(out, f"grads{rank}.pt"))
    distributed.teardown()
    _end_rank()


def _resume_rank(rank: int, world: int, port: int, out: str) -> None:
    """One process of :func:`test_a_run_resumes_on_more_ranks`: the engine under ``torchrun``'s environment (gloo),
    resuming the run in ``out``; rank 0 writes what it did."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    result = Trainer(None, out, resume=True, device="cpu", progress=False, evaluation=False,
                     overrides={"steps": 4}).fit()
    if rank == 0:
        Path(out, "resumed.txt").write_text(f"{result.step} {result.samples}")
    _end_rank()


def _time_limit_rank(rank: int, world: int, port: int, out: str, config_json: str) -> None:
    """One process of :func:`test_ranks_stop_together_at_a_time_limit`: rank 0's time limit is over when the loop
    starts, rank 1's far off (clocks that started apart, exaggerated); each writes the step it stopped at."""
    os.environ.update(MASTER_ADDR="127.0.0.1", MASTER_PORT=str(port), RANK=str(rank), WORLD_SIZE=str(world),
                      LOCAL_RANK=str(rank))
    torch.set_num_threads(1)
    config = override(TrainConfig.from_json(config_json), {"run": {"time_limit": 1e-6 if rank == 0 else 1e6}}, "")
    from fruxel.train.engine import distributed

    try:
        result = Trainer(config, out, device="cpu", progress=False, evaluation=False).fit()
    finally:
        distributed.teardown()
    Path(out, f"stopped{rank}.txt").write_text(f"{result.step} {int(result.interrupted)}")
    _end_rank()


@pytest.mark.slow
def test_ranks_stop_together_at_a_time_limit(tmp_path: Path, shards: Path) -> None:
    """A time limit that one rank reaches before the other stops every rank at the same step, with the checkpoint
    of that step (a rank stopping alone left the other waiting in its next all-reduce: the run hung)."""
    config = tiny({"data": {"source": "shards", "root": str(shards)}, "run": {"steps": 40, "batch_size": 4}})
    ctx = torch.multiprocessing.start_processes(_time_limit_rank, args=(2, _free_port(), str(tmp_path),
                                                                          config.to_json()),
                                                nprocs=2, join=False, start_method="spawn")
    deadline = time.monotonic() + 120
    while not ctx.join(timeout=5):
        if time.monotonic() > deadline:
            for p in ctx.processes:
                p.kill()
            pytest.fail("the ranks did not finish within 120 s (one waits for the other)")
    every = TimeLimit.AGREE_EVERY
    assert [(tmp_path / f"stopped{r}.txt").read_text() for r in range(2)] == [f"{every} 1"] * 2
    assert read_checkpoint(tmp_path / LATEST).state["step"] == every


def _objectives(config: TrainConfig, weights: torch.Tensor) -> dict[str, SSZObjective]:
    """``eval``: batch norm on its running statistics and only per-cell / per-column mean terms with equal class
    weights, so the loss of a batch is the mean of its halves' losses. ``train``: the full objective as trained."""
    plain = dataclasses.replace(config.loss, iou=0.0)
    return {"eval": SSZObjective(plain, torch.ones_like(weights)), "train": SSZObjective(config.loss, weights)}


@pytest.mark.slow
def test_ddp_gradients_match_one_process(tmp_path: Path, shards: Path) -> None:
    """DDP on 2 gloo processes, each with half of a fixed batch of 4, gives the gradients one process computes.

    DDP averages the ranks' gradients, each taken of the loss of that rank's half. Two comparisons follow:

    * ``eval``: with batch norm (in the 2D encoder) on its running statistics and a loss that is a mean over
      cells and columns of equal weight, the mean of the halves' losses is the loss of the whole batch, so DDP
      must give exactly the one-process gradient of the whole batch of 4.
    * ``train``: as training runs, batch norm normalises each rank's half with that half's own statistics (DDP does
      not synchronise them) and the class-weighted cross-entropy and soft IoU are ratios over the batch, so the
      whole-batch gradient is not what DDP computes. What it must compute is the mean of the two halves'
      gradients, each half through batch norm on its own; one process computes that by running the halves
      separately.
    """
    config = tiny({"data": {"source": "shards", "root": str(shards)}, "run": {"batch_size": 4}})
    image, labels = _batch(config, shards, 4)
    weights = torch.from_numpy(class_weights(class_frequencies([labels], 7), 0.5))
    batch_file = tmp_path / "batch.pt"
    torch.save({"image": image, "labels": labels, "weights": weights}, batch_file)
    torch.multiprocessing.spawn(_ddp_rank, args=(2, _free_port(), config.to_json(), str(batch_file), str(tmp_path)),
                                nprocs=2, join=True)
    ranks = [torch.load(tmp_path / f"grads{r}.pt", weights_only=True) for r in range(2)]

    torch.manual_seed(config.run.seed)  # the initialisation every rank starts from
    gen = config.model.build()
    objectives = _objectives(config, weights)
    expected = {}
    gen.eval()
    objectives["eval"](gen(image), labels)["total"].backward()
    expected["eval"] = {n: p.grad.clone() for n, p in gen.named_parameters()}
    gen.train()
    gen.zero_grad(set_to_none=True)
    for half in (slice(0, 2), slice(2, 4)):
        (objectives["train"](gen(image[half]), labels[half])["total"] / 2).backward()
    expected["train"] = {n: p.grad.clone() for n, p in gen.named_parameters()}

    for mode, want in expected.items():
        scale = max(float(g.abs().max()) for g in want.values())
        assert scale > 0
        for name, g in want.items():
            for r in range(2):
                torch.testing.assert_close(ranks[r][mode][name], g, rtol=1e-4, atol=1e-6 * scale,
                                           msg=lambda m, mode=mode, name=name, r=r: f"{mode} {name} rank {r}: {m}")


# ---------------------------------------------------------------------------------------------- data workers
def test_streams_close_their_reader(shards: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """A block stream frees its sample maker (OpenGL context, Warp meshes) or shard files when its iteration ends
    and when it is dropped early, not at the interpreter's exit."""
    from fruxel.train.sim import dataset, sample

    closed: list[str] = []
    monkeypatch.setattr(sample.SampleMaker, "close", lambda self: closed.append("maker"))
    monkeypatch.setattr(dataset.ShardDataset, "close", lambda self: closed.append("shards"))
    plan = BlockPlan(0, 8, 4, None)
    blocks = list(BlockStream(plan, "shards", "train", root=str(shards), stop_block=2))
    assert [int(b["block"]) for b in blocks] == [0, 1] and closed == ["shards"]
    it = iter(BlockStream(plan, "stream", "train", sim_config=sim_config(tiny()), stop_block=None))
    assert len(next(it)["index"]) == 4
    it.close()
    assert closed == ["shards", "maker"]


class _MarkedStream(torch.utils.data.IterableDataset):
    """Blocks of one zero sample; when its iteration is finalised (in the worker) it writes ``marker``, then,
    with ``abort``, kills its process with SIGABRT as it exits."""

    def __init__(self, marker: str, abort: bool) -> None:
        super().__init__()
        self.marker = marker
        self.abort = abort

    def __iter__(self) -> Any:
        if self.abort:
            import atexit

            atexit.register(os.abort)
        q = 0
        try:
            while True:
                yield {"image": np.zeros((1, 2, 2, 3), np.uint8), "labels": np.zeros((1, 2, 2, 2), np.uint8),
                       "index": np.asarray([q]), "block": np.int64(q)}
                q += 1
        finally:
            Path(self.marker).write_text("closed")


@pytest.mark.slow
@pytest.mark.parametrize("abort", [False, True])
def test_batches_close_waits_for_the_workers(tmp_path: Path, abort: bool) -> None:
    """``Batches.close`` stops the workers and waits for them: the worker's stream is finalised before it returns.
    A worker that dies from a signal as it exits (the data no longer needed) gives one warning naming the signal,
    never an exception (torch's SIGCHLD handler raises one when it sees the death first, a race)."""
    # A clean worker could die as its interpreter tore down (torch aborts there now and then: SIGABRT in 3 of 8
    # runs of a bare stream before the workers learnt to skip the teardown), so the clean case runs three times.
    for attempt in range(1 if abort else 3):
        marker = tmp_path / f"closed{attempt}"
        batches = Batches(lambda block, skip, m=str(marker): _MarkedStream(m, abort), 2, 1)
        assert next(batches)["index"].tolist() == [0, 1]
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            batches.close()
        assert marker.read_text() == "closed"
        # Only this warning is the subject: others that shutting a process pool down may raise (a ResourceWarning
        # for a pipe, say) are not.
        messages = [str(w.message) for w in caught if "data workers" in str(w.message)]
        if abort:  # an exit handler registered after the worker's start runs before the skip, and aborts
            assert len(messages) == 1 and "SIGABRT" in messages[0], messages
        else:
            assert messages == [], messages
        batches.close()  # idempotent


@pytest.mark.slow
def test_run_folder_after_a_run_with_evaluation(tmp_path: Path, shards: Path) -> None:
    """A short run with evaluation writes every file of the run folder, and the shipped model loads."""
    config = tiny({"data": {"source": "shards", "root": str(shards)}, "run": {"steps": 2}})
    result = Trainer(config, tmp_path, device="cpu", progress=False).fit()
    names = {p.name for p in tmp_path.iterdir()}
    assert {LATEST, SHIPPED, "config.json", "metrics.csv", "curves.png", "examples.png"} <= names
    assert TrainConfig.from_json((tmp_path / "config.json").read_text()) == config
    assert result.metrics["samples"] == 4 and 0.0 <= result.metrics["own_view_accuracy"] <= 100.0
    assert set(result.losses) >= {"total", "ce", "iou"}
    shipped = load_model(tmp_path / SHIPPED)
    assert shipped.config == config.model and shipped.training["step"] == 2 and shipped.rules == NO_RULES


def test_a_run_asked_for_no_test_samples_trains_without_evaluation(tmp_path: Path) -> None:
    """``data.eval_samples`` 0 turns the evaluation off: the run ends with its checkpoint and model written (it used
    to train, then fail in its last evaluation before the checkpoint, with "no test split to evaluate on")."""
    config = tiny({"data": {"eval_samples": 0}, "run": {"steps": 2}})
    result = Trainer(config, tmp_path, device="cpu", progress=False).fit()
    assert result.step == 2 and not result.metrics
    assert {LATEST, SHIPPED} <= {p.name for p in tmp_path.iterdir()}
    assert "eval/miou" not in (tmp_path / "metrics.csv").read_text()


@pytest.mark.slow
def test_fit_restores_the_callers_floating_point_mode_and_threads(tmp_path: Path, shards: Path) -> None:
    """Training on the CPU flushes denormals and sets its thread count for itself only: both are process-wide, and
    other code (hypothesis, for one) refuses to run with denormals flushed."""
    threads = torch.get_num_threads()
    config = tiny({"data": {"source": "shards", "root": str(shards), "workers": 1}, "run": {"steps": 1}})
    Trainer(config, tmp_path, device="cpu", progress=False).fit()
    assert (torch.tensor([1e-39], dtype=torch.float32) * 2.0).item() != 0.0
    assert torch.get_num_threads() == threads


def test_run_init_starts_from_a_model_file_and_keeps_new_layers_fresh(tmp_path: Path, shards: Path,
                                                                      capsys: pytest.CaptureFixture[str]) -> None:
    """Fine-tuning: a model without the detail branch starts a run of a model with it; every weight the file has
    is taken, the branch (which it lacks) keeps its fresh initialisation, its zero-started last BatchNorm included,
    and a file that does not fit stops the run."""
    plain = tiny()
    torch.manual_seed(5)
    source = plain.model.build()
    with torch.no_grad():
        for p in source.parameters():
            p.add_(torch.randn_like(p))
    path = tmp_path / "plain.safetensors"
    save_model(path, source, plain.model, half=False)
    detailed = tiny({"model": {"detail_branch": 4}, "run": {"init": str(path)}})
    state, _ = Trainer(detailed, tmp_path / "run", device="cpu").build()
    got, want = state.network.state_dict(), source.state_dict()
    fresh = sorted(k for k in got if k not in want)
    assert fresh and all(k.startswith("detail_branch.") for k in fresh), fresh
    _assert_same_tensors({k: got[k] for k in want}, want)
    last = f"detail_branch.{len(state.network.detail_branch) - 1}.weight"
    assert not got[last].any()
    assert f"kept the fresh initialisation of {', '.join(fresh)}" in capsys.readouterr().err
    # Another grid: the weights do not fit.
    other = tiny({"model": {"grid": {"width": 32, "height": 32, "depth": 32}}})
    save_model(path, other.model.build(), other.model)
    trainer = Trainer(tiny({"run": {"init": str(path)}}), tmp_path / "run2", device="cpu")
    with pytest.raises(TrainingError, match=r"plain\.safetensors: run.init does not fit the model config: "
                                            r"parameters \d+ of another shape"):
        trainer.build()


def test_run_init_from_a_model_of_other_classes_takes_each_shared_class_by_name(tmp_path: Path) -> None:
    """Fine-tuning to a class table that grew (the shipped ssz64's seven classes -> the furnished rooms' nine): the
    class-indexed rows of the heads are taken by class name (the order may differ), a new class keeps its fresh
    rows, entries after the classes follow them; every other weight is taken as it is."""
    names = ["empty", "floor", "wall", "window", "furniture", "door", "sculpture"]  # two swapped, two missing
    colours = [[0, 0, 0], [1, 1, 1], [2, 2, 2], [3, 3, 3], [4, 4, 4], [5, 5, 5], [6, 6, 6]]
    fewer = tiny({"model": {"classes": {"names": names, "colours": colours}}})
    torch.manual_seed(5)
    source = fewer.model.build()
    path = tmp_path / "fewer.safetensors"
    save_model(path, source, fewer.model, half=False)
    config = tiny({"model": {"classes": HOME_CLASSES.to_dict()}, "run": {"init": str(path)}})
    state, _ = Trainer(config, tmp_path / "run", device="cpu", progress=False).build()
    torch.manual_seed(config.run.seed)
    fresh = config.model.build().state_dict()
    got, want = state.network.state_dict(), source.state_dict()
    own_names = list(config.model.classes.names)
    reshaped = [k for k in want if want[k].shape != got[k].shape]
    assert "head.weight" in reshaped and "head.bias" in reshaped, reshaped
    def source_index(i: int) -> int | None:  # this model's entry i of a class dimension, in the file
        if i >= len(own_names):
            return len(names) + i - len(own_names)
        return names.index(own_names[i]) if own_names[i] in names else None

    for key in reshaped:
        theirs, own, new = want[key].numpy(), got[key].numpy(), fresh[key].numpy()
        for index in np.ndindex(own.shape):
            mapped = [source_index(i) if a != b else i for i, a, b in zip(index, theirs.shape, own.shape, strict=True)]
            expected = new[index] if None in mapped else theirs[tuple(mapped)]
            assert own[index] == expected, (key, index)
    kept = [k for k in want if k not in reshaped]
    _assert_same_tensors({k: got[k] for k in kept}, {k: want[k] for k in kept})
    # As many classes in another order: which rows are per class cannot be told from the shapes, so it stops.
    swapped = tiny({"model": {"classes": {"names": names, "colours": colours}}})
    save_model(path, swapped.model.build(), swapped.model, half=False)
    with pytest.raises(TrainingError, match="as many classes must have the same names in order"):
        Trainer(tiny({"run": {"init": str(path)}}), tmp_path / "run3", device="cpu", progress=False).build()


def test_shell_losses_settings_reach_the_shell_loss(tmp_path: Path, shards: Path) -> None:
    data = {"source": "shards", "root": str(shards)}
    config = tiny({"data": data, "loss": {"shell": True, "shell_losses": {"weight_own_view": 1.5, "seed": 3}}})
    state, _ = Trainer(config, tmp_path, device="cpu").build()
    assert state.shell is not None and state.shell.config == config.loss.shell_losses
    assert state.shell.config.weight_own_view == 1.5 and state.shell.config.own_view


def test_first_hit_term_is_the_own_views_first_hit_cross_entropy() -> None:
    """``loss.first_hit``: the mean over the columns of ``-log P(first hit = the truth's first label)``, with a
    gradient to the logits; it matches the shell-aware losses' own-view term, which gets there through kernels."""
    from fruxel.train.config import ConfigError, LossConfig
    from fruxel.train.losses import ShellLoss, ShellLossConfig
    from fruxel.train.models.registry import ModelOutput
    from fruxel.train.rules import first_hit_log_probs

    config = tiny()
    torch.manual_seed(5)
    labels = (torch.rand(2, 16, 16, 16) < 0.08).to(torch.uint8) * torch.randint(1, 7, (2, 16, 16, 16),
                                                                                dtype=torch.uint8)
    logits = (torch.randn(2, 7, 16, 16, 16) * 2).requires_grad_()
    out = ModelOutput(logits=logits)
    only = LossConfig(ce=0.0, iou=0.0, depth=0.0, surface=0.0, first_hit=2.0)
    terms = SSZObjective(only, torch.ones(7))(out, labels)
    first = (labels != 0).to(torch.uint8).argmax(1, keepdim=True)
    seen = labels.long().gather(1, first).squeeze(1) * (labels != 0).any(1)
    expected = -first_hit_log_probs(logits.detach()).gather(1, seen.unsqueeze(1)).mean()
    torch.testing.assert_close(terms["first_hit"], expected)
    torch.testing.assert_close(terms["total"], 2.0 * expected)
    terms["total"].backward()
    assert logits.grad is not None and logits.grad.abs().sum() > 0
    shell = ShellLoss(config.model.grid, ShellLossConfig(novel_views=0, weight_own_view=1.0, eps=0.0))
    own = shell(logits.detach(), labels).own_view
    torch.testing.assert_close(own, expected, rtol=1e-4, atol=1e-5)
    assert "first_hit" not in SSZObjective(dataclasses.replace(only, first_hit=0.0, ce=1.0), torch.ones(7))(out, labels)
    for bad in (-1.0, float("nan")):
        with pytest.raises(ConfigError, match="loss.first_hit"):
            LossConfig(first_hit=bad)


def test_a_shipped_file_whose_header_length_starts_with_0x80_is_not_taken_for_a_pickle(tmp_path: Path) -> None:
    """A safetensors header of 128 + 256 k bytes starts the file with 0x80, pickle's protocol byte: the shipped
    model of 2026-11-25 had one, and read as "not a fruxel SSZ checkpoint"."""
    config = tiny().model
    gen = config.build()
    path = tmp_path / "m.safetensors"
    for pad in range(300):
        save_model(path, gen, config, training={"note": "x" * pad}, half=False)
        if path.read_bytes()[:1] == b"\x80":
            break
    assert path.read_bytes()[:1] == b"\x80"
    f = read_model_file(path)
    assert f.config == config and f.training["note"] == "x" * pad and set(f.state) == set(gen.state_dict())
    assert not load_model(path).network.training


def test_an_empty_or_truncated_checkpoint_is_one_error_naming_it(tmp_path: Path) -> None:
    path = tmp_path / LATEST
    path.write_bytes(b"")
    with pytest.raises(CheckpointError, match=r"last\.pt: not a readable checkpoint \(.*empty file\)"):
        read_checkpoint(path)
    save_checkpoint(path, {"step": 1, "generator": {}}, tiny())
    path.write_bytes(path.read_bytes()[:100])
    with pytest.raises(CheckpointError, match=r"last\.pt: not a readable checkpoint"):
        read_checkpoint(path)


@pytest.mark.parametrize("mps", [True, False])
def test_a_cuda_device_that_cannot_be_used_is_one_line_that_says_what_to_do(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch, mps: bool) -> None:
    """CUDA refuses the device (seen on a lent GPU after a killed run had left the CUDA MPS server unusable): the
    set-up raises one TrainingError naming the device and, where MPS runs, how to restart it. The refusal itself is
    CUDA's, which a machine without a GPU cannot give, so it is injected where torch would raise it."""
    import torch

    from fruxel.train.engine import distributed

    def refuse(dev: Any) -> None:
        raise RuntimeError("CUDA error: CUDA-capable device(s) is/are busy or unavailable\nCUDA kernel errors might "
                           "be asynchronously reported at some other API call")

    monkeypatch.setattr(torch.cuda, "set_device", refuse)
    monkeypatch.setenv("CUDA_MPS_PIPE_DIRECTORY", str(tmp_path))
    for name in ("WORLD_SIZE", "RANK", "LOCAL_RANK"):
        monkeypatch.delenv(name, raising=False)
    if mps:
        (tmp_path / "control").write_text("")
    with pytest.raises(TrainingError) as e:
        distributed.setup("cuda")
    message = str(e.value)
    assert message.startswith("cuda:0: CUDA cannot use this device (CUDA-capable device(s) is/are busy or unavailable)")
    assert "\n" not in message
    assert ("nvidia-cuda-mps-control -d" in message and str(tmp_path) in message) == mps
    assert ("exclusive mode" in message) != mps


def test_ranks_wait_for_each_other_longer_than_nccls_default(monkeypatch: pytest.MonkeyPatch) -> None:
    """The process group is made with a timeout above NCCL's 10 minutes: the first all-reduce waits for every rank's
    compilation, which on a loaded host ended minutes apart. The group itself is torch's; what the engine asks of it
    is recorded here."""
    import datetime

    import torch.distributed as dist

    from fruxel.train.engine import distributed

    asked: dict[str, Any] = {}
    monkeypatch.setattr(dist, "is_initialized", lambda: False)
    monkeypatch.setattr(dist, "init_process_group", lambda backend, **kw: asked.update(backend=backend, **kw))
    monkeypatch.setenv("WORLD_SIZE", "2")
    monkeypatch.setenv("RANK", "1")
    monkeypatch.setenv("LOCAL_RANK", "1")
    d = distributed.setup("cpu")
    assert (d.rank, d.world, asked["backend"], asked["rank"], asked["world_size"]) == (1, 2, "gloo", 1, 2)
    assert asked["timeout"] >= datetime.timedelta(minutes=30)


def test_the_network_is_compiled_before_ddp_wraps_it(tmp_path: Path) -> None:
    """Every rank runs the graph one GPU runs: DDP wraps the compiled network. Compiling the DDP wrapper instead
    lets DDPOptimizer split the graph at DDP's buckets, which two GPUs ran slower (issue 37)."""
    import torch.distributed as dist
    from torch._dynamo.eval_frame import OptimizedModule
    from torch.nn.parallel import DistributedDataParallel

    from fruxel.train.engine.trainer import training_module

    net = torch.nn.Linear(3, 2)
    dist.init_process_group("gloo", store=dist.FileStore(str(tmp_path / "store"), 1), rank=0, world_size=1)
    try:
        wrapped = training_module(net, compile=True, graphs=False, ddp=True)
        assert isinstance(wrapped, DistributedDataParallel) and isinstance(wrapped.module, OptimizedModule)
        assert wrapped.module._orig_mod is net
        assert training_module(net, compile=False, graphs=False, ddp=False) is net
    finally:
        dist.destroy_process_group()


def test_cuda_graphs_are_a_cuda_option(tmp_path: Path) -> None:
    """``run.cuda_graphs`` is on by default; on the CPU the compiled step does not mark CUDA graph steps."""
    config = tiny({"run": {"compile": True}})
    assert config.run.cuda_graphs
    state, step = Trainer(config, tmp_path / "run", device="cpu", progress=False).build()
    assert step.graphs is False and step.model._orig_mod is state.network


def test_a_run_whose_graphs_run_without_cuda_graphs_says_so_once(tmp_path: Path,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The check after a run's first step counts the compiled graphs that run without CUDA graphs and warns once.
    On the CPU, ``torch.compile``'s reduce-overhead mode runs every graph so, which stands in here for a GPU run
    whose graph cannot be captured (CI has no GPU); the trainer is told it replays graphs, as on CUDA."""
    trainer = Trainer(tiny({"run": {"compile": True}}), tmp_path / "run", device="cpu", progress=False)
    assert trainer.graphs is False  # a CPU run: nothing to check
    trainer.graphs = True
    check = trainer.graph_check
    check.on_start(trainer)
    double = torch.compile(lambda x: (2.0 * x).sum(), mode="reduce-overhead")
    double(torch.ones(3))
    for _ in range(3):
        check.on_step(trainer, {})
    assert check.skips == 1
    err = capsys.readouterr().err
    assert err.count("run.cuda_graphs: torch.compile runs 1 of the network's graphs without CUDA graphs") == 1

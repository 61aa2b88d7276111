"""Training data for the engine: blocks of consecutive samples (whole simulated rooms) made by the simulator or
read from shards in DataLoader workers, re-batched in a fixed order, optionally mixed through a replay buffer on
the training device.

Order and resuming
    A rank's samples form a sequence of *blocks*, block ``q`` being one room's samples (``samples_per_scene``
    consecutive indices, clipped to the rank's range). Streaming takes the rooms in index order; shards take each
    epoch's rooms in a permutation seeded by the run. Worker ``w`` of ``K`` makes blocks ``q = w, w + K, ...``; the
    DataLoader returns its workers' results round-robin, so the main process receives blocks in the order
    ``q = 0, 1, 2, ...`` whatever ``K`` is. A batch is the next ``batch`` samples of that sequence, and the
    position ``(next block, samples of it already used)`` is all a checkpoint needs to continue with exactly the
    samples an uninterrupted run would have seen.

Ranks
    Rank ``r`` of ``n`` owns the room-aligned index range :func:`rank_range` of the split: disjoint ranges, so no
    two ranks ever train on the same sample.

Arrays
    Blocks and batches hold ``image`` ``(N, h, w, 3)`` uint8 RGB (image rows and columns, the grid camera's
    image), ``labels`` ``(N, D, H, W)`` uint8 (grid frame) and ``index`` ``(N,)`` int64; they stay uint8 until
    the training device (:func:`to_device`), where images become ``(N, 3, h, w)`` float in [0, 1].
"""

from __future__ import annotations

import atexit
import math
import os
import signal
import sys
import warnings
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, IterableDataset, get_worker_info


def rank_range(samples: int, samples_per_scene: int, rank: int, world: int) -> tuple[int, int]:
    """The index range ``[lo, hi)`` of rank ``rank`` of ``world`` in a split of ``samples`` samples: whole rooms,
    disjoint between ranks, together the whole split.

    Raises:
        ValueError: fewer rooms than ranks.
    """
    rooms = math.ceil(samples / samples_per_scene)
    if rooms < world:
        raise ValueError(f"{rooms} rooms ({samples} samples) cannot be divided among {world} ranks")
    a = rooms * rank // world
    b = rooms * (rank + 1) // world
    return a * samples_per_scene, min(samples, b * samples_per_scene)


@dataclass(frozen=True)
class BlockPlan:
    """Which samples block ``q`` of a rank holds (see the module docstring)."""

    lo: int
    """First index of the rank's range."""
    hi: int
    """One past the last index of the rank's range."""
    samples_per_scene: int
    """Samples per room."""
    shuffle_seed: int | None
    """None: rooms in index order (streaming, one pass). Otherwise each epoch permutes the rooms with
    ``default_rng([shuffle_seed, epoch])`` (shards)."""

    @property
    def rooms(self) -> tuple[int, int]:
        """First room and one past the last room of the range."""
        n = self.samples_per_scene
        return self.lo // n, (self.hi - 1) // n + 1

    def block(self, q: int) -> range:
        """The indices of block ``q`` (any ``q >= 0``; the range repeats in epochs)."""
        first, last = self.rooms
        count = last - first
        epoch, pos = divmod(q, count)
        if self.shuffle_seed is None:
            room = first + pos
        else:
            room = first + int(np.random.default_rng([self.shuffle_seed, epoch]).permutation(count)[pos])
        n = self.samples_per_scene
        return range(max(self.lo, room * n), min(self.hi, (room + 1) * n))


class BlockStream(IterableDataset):
    """Blocks of samples from ``first_block`` on, each worker making its share (see the module docstring).

    Args:
        plan: the rank's blocks.
        source: ``"stream"`` (a :class:`~fruxel.train.sim.shards.SampleMaker` per worker) or ``"shards"``.
        split: the split's name.
        sim_config: the simulator config (streaming).
        seed: the simulator's base seed (streaming).
        root: the data set folder (shards).
        first_block: the block to start with.
        skip: samples of the first block to leave out (already used before a resume).
        device: Warp device of the simulator's ``fruxelize`` (None: CUDA when present).
        stop_block: the block to stop before (None: endless, the range repeating in epochs). A loader that needs a
            known number of samples (the evaluation set) stops there, so its workers make nothing more.
    """

    def __init__(self, plan: BlockPlan, source: str, split: str, *, sim_config: Any = None, seed: int = 0,
                 root: str = "", first_block: int = 0, skip: int = 0, device: str | None = None,
                 stop_block: int | None = None) -> None:
        super().__init__()
        self.plan = plan
        self.source = source
        self.split = split
        self.sim_config = sim_config
        self.seed = seed
        self.root = root
        self.first_block = first_block
        self.skip = skip
        self.device = device
        self.stop_block = stop_block

    def _reader(self) -> tuple[Callable[[int], Any], Callable[[], None]]:
        """``(read, close)``: sample ``i`` of the split (simulated or read from shards), and the closing of what
        reading holds."""
        if self.source == "stream":
            from fruxel.train.sim.sample import SampleMaker

            maker = SampleMaker(self.sim_config, self.seed, backend="warp", device=self.device)
            return (lambda i: maker.make(self.split, i)), maker.close
        from fruxel.train.sim.dataset import ShardDataset

        ds = ShardDataset(self.root, self.split)
        return ds.sample, ds.close

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        info = get_worker_info()
        worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
        read, close = self._reader()
        q = self.first_block + worker
        # What reading holds (the renderer's OpenGL context and Warp meshes, or open shard files) is freed when the
        # iteration ends or the generator is dropped; in a DataLoader worker, when its loop returns, before the
        # interpreter exits. Left to the exit, the EGL and CUDA contexts are torn down in whatever order the
        # interpreter's clean-up takes (the suspected cause of workers aborting after training on the H100).
        try:
            while self.stop_block is None or q < self.stop_block:
                idx = self.plan.block(q)
                if q == self.first_block:
                    idx = idx[self.skip:]
                samples = [read(i) for i in idx]
                block = {
                    "image": np.stack([s.image for s in samples]),
                    "labels": np.stack([np.asarray(s.labels, dtype=np.uint8) for s in samples]),
                    "index": np.asarray([s.index for s in samples], dtype=np.int64),
                    "block": np.int64(q),
                }
                # Simulated samples carry each column's rendered surface depth (the fine depth head's target);
                # samples read from shards do not.
                if samples and all(s.surface_depth is not None for s in samples):
                    block["surface_depth"] = np.stack([s.surface_depth for s in samples])
                yield block
                q += workers
        finally:
            close()


def _init_worker(_: int) -> None:
    """Set up a DataLoader worker process: one llvmpipe thread each when there are several, and an exit that skips
    the interpreter's teardown."""
    info = get_worker_info()
    if info is not None and info.num_workers > 1:
        # Each worker renders with one llvmpipe thread (the workers already use the cores); read when the
        # renderer's context is made. NVIDIA's EGL ignores it.
        os.environ.setdefault("LP_NUM_THREADS", "1")
    # A spawned worker ends through sys.exit, so C++ destructors run as its interpreter tears down, and one of torch's
    # aborts there now and then ("terminate called without an active exception", SIGABRT; a bare IterableDataset of
    # zeros in 3 of 8 runs on torch 2.13). Exit handlers run last-registered first: the handlers of what the stream
    # imports later still run, then this ends the process, skipping those of what was imported before (torch's) and
    # the teardown. The worker's loop has returned and its stream is finalised by then (Batches.close), and the
    # process's contexts (EGL, CUDA) are released by the kernel.
    atexit.register(_exit_now)


def _exit_now() -> None:
    """End this process with status 0 at once, with Python's own output flushed."""
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(0)


BATCH_KEYS = ("image", "labels", "index", "surface_depth")
"""What a batch of :class:`Batches` holds (``surface_depth`` only when the stream has it)."""


class Batches:
    """Fixed-size batches of a rank's block sequence, resumable at a position.

    Args:
        stream_factory: called with ``(first_block, skip)``; returns a :class:`BlockStream`.
        batch: samples per batch.
        workers: DataLoader worker processes (0: blocks are made in this process).
        pin: pin batches in page-locked memory (for CUDA).
        position: ``(next block, samples of it already used)`` to start from.
    """

    def __init__(self, stream_factory: Any, batch: int, workers: int, *, pin: bool = False,
                 position: tuple[int, int] = (0, 0)) -> None:
        self.batch = batch
        block, used = position
        ds = stream_factory(block, used)
        # A generator of its own: each iter() of a DataLoader draws a base seed from its generator, which would
        # otherwise be torch's global one, whose state a checkpoint restores (a resumed run draws once more).
        kwargs: dict[str, Any] = {"batch_size": None, "num_workers": workers, "pin_memory": pin,
                                  "generator": torch.Generator().manual_seed(0)}
        if workers:
            kwargs.update(multiprocessing_context="spawn", prefetch_factor=4, persistent_workers=False,
                          worker_init_fn=_init_worker)
        self._loader = DataLoader(ds, **kwargs)
        self._it: Iterator[dict[str, Any]] | None = None
        self._start = (block, used)
        self._next = (block, used)
        self._buf: dict[str, Any] | None = None
        self._block = block
        self._offset = 0
        self._base = 0

    @property
    def position(self) -> tuple[int, int]:
        """``(block, used)``: where the next batch starts (a checkpoint stores this)."""
        if self._buf is not None:
            return self._block, self._base + self._offset
        return self._next

    def __next__(self) -> dict[str, torch.Tensor]:
        if self._it is None:
            self._it = iter(self._loader)
        parts: list[dict[str, torch.Tensor]] = []
        need = self.batch
        while need:
            if self._buf is None:
                self._buf = next(self._it)
                self._block = int(self._buf["block"])
                self._offset = 0
                # The stream's first block comes without the samples used before a resume.
                self._base = self._start[1] if self._block == self._start[0] else 0
            n = len(self._buf["index"])
            take = min(n - self._offset, need)
            sl = slice(self._offset, self._offset + take)
            parts.append({k: torch.as_tensor(self._buf[k][sl]) for k in BATCH_KEYS if k in self._buf})
            self._offset += take
            need -= take
            if self._offset == n:
                self._next = (self._block + 1, 0)
                self._buf = None
        return {k: torch.cat([p[k] for p in parts]) if len(parts) > 1 else parts[0][k] for k in parts[0]}

    def __iter__(self) -> Batches:
        return self

    def close(self) -> None:
        """Stop the workers and wait until they have exited (idempotent).

        A worker that a signal ends as it exits (its data no longer needed) gives one warning naming the signal,
        not an error.
        """
        it, self._it = self._it, None
        self._loader = None  # type: ignore[assignment]
        # The DataLoader's iterator shuts its workers down when garbage-collected, and an error raised there (its
        # SIGCHLD handler's "DataLoader worker (pid N) is killed by signal", when a worker dies while it exits)
        # was printed as an ignored exception with a traceback. Shut down here instead, where it can be caught;
        # whether the handler sees the death at all is a race, so the exit codes are read once all have ended.
        shutdown = getattr(it, "_shutdown_workers", None)
        if shutdown is None:
            return
        try:
            shutdown()
        except RuntimeError as e:
            if not str(e).startswith("DataLoader worker"):
                raise
        ended = [f"pid {w.pid} by {_signal_name(-w.exitcode)}" for w in getattr(it, "_workers", ())
                 if w.exitcode is not None and w.exitcode < 0]
        if ended:
            warnings.warn(f"data workers ended by a signal as they stopped, after their last batch was used: "
                          f"{', '.join(ended)}", RuntimeWarning, stacklevel=2)


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"


def to_device(batch: dict[str, torch.Tensor], device: torch.device, channels_last: bool = False
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(image, labels)`` on ``device``: image ``(B, 3, h, w)`` float32 in [0, 1], labels ``(B, D, H, W)`` uint8.

    The uint8 arrays cross to the device as they are (a quarter of float32's bytes for images, an eighth of int64's
    for labels); the conversion happens there.
    """
    img = batch["image"].to(device, non_blocking=True).permute(0, 3, 1, 2).float().div_(255.0)
    if channels_last:
        img = img.contiguous(memory_format=torch.channels_last)
    else:
        img = img.contiguous()
    return img, batch["labels"].to(device, non_blocking=True)


class ReplayBuffer:
    """A ring of recent samples on the training device from which batches are drawn uniformly.

    Each :meth:`step` adds ``fresh`` new samples (replacing the oldest once full) and draws a batch from every
    sample held, so each sample is used about ``batch / fresh`` times while it stays in the buffer.

    Args:
        capacity: samples held.
        image_shape: ``(h, w, 3)``.
        grid_shape: ``(D, H, W)``.
        device: where the ring lives.
        seed: seed of the draws (its state is part of :meth:`state_dict`).
    """

    def __init__(self, capacity: int, image_shape: tuple[int, ...], grid_shape: tuple[int, ...],
                 device: torch.device, seed: int) -> None:
        self.capacity = capacity
        self.images = torch.empty((capacity, *image_shape), dtype=torch.uint8, device=device)
        self.labels = torch.empty((capacity, *grid_shape), dtype=torch.uint8, device=device)
        self.surface_depth: torch.Tensor | None = None
        """``(capacity, H, W)`` float32 rendered surface depths, made on the first batch that has them."""
        self.filled = 0
        self.head = 0
        self.generator = torch.Generator().manual_seed(seed)

    def add(self, batch: dict[str, torch.Tensor]) -> None:
        """Insert a batch of host samples (``image``, ``labels`` uint8; ``surface_depth`` float32 if the stream
        has it, then in every batch)."""
        n = len(batch["image"])
        slots = (torch.arange(n) + self.head) % self.capacity
        dev = self.images.device
        self.images[slots.to(dev)] = batch["image"].to(dev, non_blocking=True)
        self.labels[slots.to(dev)] = batch["labels"].to(dev, non_blocking=True)
        depth = batch.get("surface_depth")
        if depth is not None and self.surface_depth is None and not self.filled:
            self.surface_depth = torch.empty((self.capacity, *depth.shape[1:]), dtype=torch.float32, device=dev)
        if (depth is None) != (self.surface_depth is None):
            raise ValueError("a replay buffer's batches must all have surface_depth or all lack it")
        if depth is not None:
            self.surface_depth[slots.to(dev)] = depth.to(dev, torch.float32, non_blocking=True)
        self.head = (self.head + n) % self.capacity
        self.filled = min(self.capacity, self.filled + n)

    def draw(self, batch: int) -> dict[str, torch.Tensor]:
        """A batch drawn uniformly (with replacement) from the samples held, on the buffer's device."""
        idx = torch.randint(0, self.filled, (batch,), generator=self.generator).to(self.images.device)
        out = {"image": self.images[idx], "labels": self.labels[idx]}
        if self.surface_depth is not None:
            out["surface_depth"] = self.surface_depth[idx]
        return out

    def state_dict(self) -> dict[str, Any]:
        """The draw generator's state (the samples themselves are not saved: a resumed run refills the ring)."""
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.generator.set_state(state["generator"])

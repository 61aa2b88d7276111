"""torch data sets of simulated samples: read from shards (:class:`ShardDataset`) or made on the fly in the
DataLoader's workers (:class:`StreamingDataset`). The same config and seed give the same samples either way.

Items are dictionaries of tensors (:func:`sample_tensors`):

    ``image``       ``(3, S * H / W, S)`` float32 RGB in [0, 1] (the stored uint8 divided by 255), CHW
    ``labels``      ``(D, H, W)`` uint8 ground-truth labels of the grid (0 = empty), indexed ``[k, j, i]``
    ``pose``        ``(4, 4)`` float64 camera-to-world of the robot camera (world frame z up, OpenCV axes)
    ``K``           ``(3, 3)`` float64 image intrinsics (the grid's own camera is ``K`` scaled by ``W / S``)
    ``index``       ``()`` int64 sample index in the split

Labels stay uint8, as stored, until the device: an int64 copy would cost eight times the memory and bandwidth in
the workers, the DataLoader's queues and pinned memory (16 MiB instead of 2 MiB per 128^3 sample). The kernels
take uint8 volumes as they are; a training step converts with ``.long()`` on the device where a loss needs it.

Own-view truth (the label and depth of each column's first occupied cell) is not an item: it is
``fruxel.kernels.first_hit(labels, grid, grid.camera())`` on the device, which :class:`fruxel.train.losses.ShellLoss`
computes with the other views' truth and returns as ``ShellTargets.own_view`` (see :mod:`.sample`).

Streaming is for machines where a data set cannot be copied in: each DataLoader worker builds its own
:class:`SampleMaker` (renderer, Warp meshes) and makes a contiguous, room-aligned part of the split's index range.
Workers must be started with ``spawn`` (an OpenGL or CUDA context does not survive ``fork``);
:func:`streaming_loader` sets that up.

Distributed training: every rank streams its own equal, disjoint share of the indices,
``StreamingDataset(config, split, seed, rank=rank, world_size=world_size)`` (:func:`rank_range`), and
``StreamingDataset.batches`` says how many batches each rank's loader yields. A :class:`ShardDataset` is map-style:
give its DataLoader a ``torch.utils.data.DistributedSampler``.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from collections.abc import Iterator
from typing import Any

import numpy as np
import torch
from torch.utils.data import DataLoader, Dataset, IterableDataset, get_worker_info

from .config import ConfigError, SimConfig
from .manifest import MANIFEST, Manifest
from .sample import Sample, SampleMaker
from .shards import DatasetError, ShardReader


def sample_tensors(sample: Sample, config: SimConfig) -> dict[str, torch.Tensor]:
    """The tensors of one sample (layout in the module docstring). The uint8 labels share memory with the sample's
    array where it is contiguous and writable (no copy)."""
    img = torch.from_numpy(np.ascontiguousarray(sample.image.transpose(2, 0, 1)))
    return {
        "image": img.to(torch.float32).div_(255.0),
        "labels": torch.from_numpy(np.require(sample.labels, np.uint8, "CW")),
        "pose": torch.from_numpy(np.array(sample.pose, dtype=np.float64)),
        "K": torch.from_numpy(config.image_camera().K),
        "index": torch.tensor(sample.index, dtype=torch.int64),
    }


class ShardDataset(Dataset):
    """Map-style data set over the shards of one split of a data set folder.

    The manifest is read and checked on construction; a shard is checked (SHA-256 against the manifest, members,
    meta) the first time a process reads from it, then kept open (at most ``max_open`` per process) and read one
    sample at a time, so random access inflates only the sample asked for.

    Args:
        root: the data set folder (with ``manifest.json``).
        split: the split's name, e.g. ``"train"``.
        verify: check each shard's SHA-256 when first opened (reads the file once more).
        max_open: shard files kept open per process.

    Raises:
        DatasetError: no or a bad manifest, an unknown split, or a data set that is not complete yet.
    """

    def __init__(self, root: str | os.PathLike[str], split: str = "train", *, verify: bool = True,
                 max_open: int = 8) -> None:
        self.root = os.fsdecode(root)
        """The data set folder."""
        self.manifest = Manifest.load(os.path.join(self.root, MANIFEST))
        """The data set's manifest."""
        self.config: SimConfig = self.manifest.config
        """The settings the samples were made with."""
        self.split = split
        """The split served."""
        try:
            self._n = self.config.split_samples(split)
        except ConfigError as e:
            raise DatasetError(os.path.join(self.root, MANIFEST), str(e)) from None
        self._shards = self.manifest.shards(split)
        missing = [s.file for s in self._shards if self.manifest.hashes[s.file] is None]
        if missing:
            raise DatasetError(self.root, f"data set is incomplete: {len(missing)} of {len(self._shards)} shards of "
                                          f"split {split!r} are not written yet (first: {missing[0]}); run "
                                          "fruxel-sim generate again with the same arguments to finish it")
        self.verify = verify
        """Whether shards are checked against their SHA-256 when first opened."""
        self.max_open = max(1, int(max_open))
        """Shard files kept open per process."""
        self._readers: OrderedDict[int, ShardReader] = OrderedDict()
        self._pid = os.getpid()

    def __len__(self) -> int:
        return self._n

    def _reader(self, shard: int) -> ShardReader:
        if self._pid != os.getpid():
            # A forked DataLoader worker must not share the parent's file offsets: start afresh.
            self._readers = OrderedDict()
            self._pid = os.getpid()
        reader = self._readers.get(shard)
        if reader is None:
            spec = self._shards[shard]
            sha = self.manifest.hashes[spec.file] if self.verify else None
            reader = ShardReader(os.path.join(self.root, spec.file), spec, self.config, self.manifest.seed, sha)
            self._readers[shard] = reader
            while len(self._readers) > self.max_open:
                self._readers.popitem(last=False)[1].close()
        else:
            self._readers.move_to_end(shard)
        return reader

    def sample(self, index: int) -> Sample:
        """Sample ``index`` as numpy arrays (:class:`Sample`)."""
        if isinstance(index, torch.Tensor):
            index = int(index)
        if not -self._n <= index < self._n:
            raise IndexError(f"index {index} out of range for split {self.split!r} of {self._n} samples")
        index %= self._n
        shard, j = divmod(index, self.config.shard_size)
        return self._reader(shard).sample(j)

    def __getitem__(self, index: int) -> dict[str, torch.Tensor]:
        return sample_tensors(self.sample(index), self.config)

    def close(self) -> None:
        """Close the open shard files."""
        for reader in self._readers.values():
            reader.close()
        self._readers.clear()

    def __getstate__(self) -> dict[str, Any]:
        state = self.__dict__.copy()
        state["_readers"] = OrderedDict()
        return state


def worker_range(start: int, stop: int, samples_per_scene: int, worker: int, workers: int) -> range:
    """The indices of ``start .. stop - 1`` that worker ``worker`` of ``workers`` makes: a contiguous run of whole
    rooms (clipped to the range at its ends), so that every room is built by one worker only.

    Args:
        start, stop: the index range.
        samples_per_scene: samples per room; room ``c`` holds indices ``c * n .. (c + 1) * n - 1``.
        worker, workers: this worker's number and the number of workers.
    """
    if stop <= start:
        return range(start, start)
    first_room = start // samples_per_scene
    rooms = (stop - 1) // samples_per_scene + 1 - first_room
    a = first_room + rooms * worker // workers
    b = first_room + rooms * (worker + 1) // workers
    lo = max(start, a * samples_per_scene)
    return range(lo, max(lo, min(stop, b * samples_per_scene)))


def rank_range(start: int, samples: int, rank: int, world_size: int) -> range:
    """The indices of ``start .. start + samples - 1`` that distributed rank ``rank`` of ``world_size`` takes: the
    rank-th of ``world_size`` contiguous runs of ``samples // world_size`` indices each.

    Every rank gets as many samples as every other, so that ranks run the same number of steps (a rank with one
    batch more would wait forever in its gradient all-reduce); the last ``samples % world_size`` indices are left
    out, as ``DistributedSampler(drop_last=True)`` does. Runs are not room-aligned: a room that straddles two
    ranks is built by both (a few milliseconds), which keeps the shares equal.

    Raises:
        ValueError: a rank outside ``0 .. world_size - 1``, or a negative start or count.
    """
    if not 0 <= rank < world_size:
        raise ValueError(f"rank must be in 0 .. world_size - 1, got rank {rank!r} of world_size {world_size!r}")
    if start < 0 or samples < 0:
        raise ValueError(f"start and samples must be >= 0, got {start!r} and {samples!r}")
    n = samples // world_size
    return range(start + rank * n, start + (rank + 1) * n)


class StreamingDataset(IterableDataset):
    """Samples of one split made on the fly, identical to the shards the generator writes for the same seed.

    The data set makes the indices ``start .. start + samples - 1``, or with ``world_size`` > 1 this rank's equal
    share of them (:func:`rank_range`; the shares of all ranks are disjoint). Each DataLoader worker (or the main
    process, without workers) makes a contiguous, room-aligned part of those in order (:func:`worker_range`), with
    its own :class:`SampleMaker`, and batches its part on its own: see :meth:`batches` for how many batches that
    gives. Use ``spawn`` workers (:func:`streaming_loader`).

    Args:
        config: the generator settings.
        split: the split's name.
        seed: the base seed.
        samples: how many samples to make (all ranks together); None: the split's size in ``config.splits``.
        start: index of the first sample.
        rank, world_size: this process's distributed rank and the number of ranks
            (``torch.distributed.get_rank()``, ``get_world_size()``); 0 and 1 without distribution.
        backend, device: ``fruxelize`` backend and Warp device (see :class:`SampleMaker`); None for the device
            takes CUDA when present.

    Raises:
        ConfigError: an unknown split or a range outside it. ValueError: a rank outside the world.
    """

    def __init__(self, config: SimConfig, split: str = "train", seed: int = 0, *, samples: int | None = None,
                 start: int = 0, rank: int = 0, world_size: int = 1, backend: str | None = "warp",
                 device: str | None = None) -> None:
        super().__init__()
        n = config.split_samples(split)
        samples = n - start if samples is None else samples
        if start < 0 or samples < 0 or start + samples > n:
            raise ConfigError(f"samples {start}..{start + samples - 1} are outside split {split!r} of {n} samples")
        part = rank_range(start, samples, rank, world_size)
        start, samples = part.start, len(part)
        self.config = config
        """The generator settings."""
        self.split = split
        """The split made."""
        self.seed = int(seed)
        """The base seed."""
        self.start = int(start)
        """Index of the first sample (of this rank's share)."""
        self.samples = int(samples)
        """Number of samples (of this rank's share)."""
        self.backend = backend
        """``fruxelize`` backend."""
        self.device = device
        """Warp device, or None."""
        self._maker: SampleMaker | None = None

    def __len__(self) -> int:
        return self.samples

    def __getstate__(self) -> dict[str, Any]:
        # Each worker builds its own maker: an OpenGL or CUDA context cannot be pickled or shared.
        state = self.__dict__.copy()
        state["_maker"] = None
        return state

    def indices(self) -> range:
        """The indices this process makes: all of them, or this DataLoader worker's part."""
        info = get_worker_info()
        worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
        return self.worker_indices(worker, workers)

    def worker_indices(self, worker: int, workers: int) -> range:
        """The indices DataLoader worker ``worker`` of ``workers`` makes (:func:`worker_range`)."""
        return worker_range(self.start, self.start + self.samples, self.config.samples_per_scene, worker, workers)

    def batches(self, batch_size: int, workers: int, drop_last: bool = False) -> int:
        """The number of batches a DataLoader with ``workers`` workers (0: none) yields per epoch.

        Each worker batches its own part, so up to one partial batch per worker: the number can exceed
        ``ceil(len(self) / batch_size)`` (the DataLoader's ``len``), and differ between ranks whose shares are split
        differently by room boundaries. It depends only on the arguments, so every rank can compute every rank's
        count and a training loop can run the smallest of them in every rank.
        """
        if isinstance(batch_size, bool) or not isinstance(batch_size, int) or batch_size < 1:
            raise ValueError(f"batch_size must be a positive integer, got {batch_size!r}")
        parts = [len(self.worker_indices(w, max(1, workers))) for w in range(max(1, workers))]
        return sum(n // batch_size if drop_last else -(-n // batch_size) for n in parts)

    def samples_numpy(self) -> Iterator[Sample]:
        """This process's samples as numpy :class:`Sample` objects, in index order."""
        idx = self.indices()
        if not len(idx):
            return
        # Kept between epochs (persistent DataLoader workers): renderer, EGL and Warp start once per process.
        if self._maker is None:
            self._maker = SampleMaker(self.config, self.seed, backend=self.backend, device=self.device)
        for i in idx:
            yield self._maker.make(self.split, i)

    def close(self) -> None:
        """Free this process's renderer and meshes (idempotent; iterating again makes new ones)."""
        if self._maker is not None:
            self._maker.close()
            self._maker = None

    def __iter__(self) -> Iterator[dict[str, torch.Tensor]]:
        for sample in self.samples_numpy():
            yield sample_tensors(sample, self.config)


def _single_thread_llvmpipe(_: int) -> None:
    # Runs in each worker before its renderer exists; Mesa reads the variable when it creates the context.
    os.environ.setdefault("LP_NUM_THREADS", "1")


def streaming_loader(dataset: StreamingDataset, batch_size: int, workers: int, **kwargs: Any) -> DataLoader:
    """A DataLoader over a :class:`StreamingDataset` with ``spawn`` workers.

    Workers are persistent by default, so that their start-up (about 13 s for 16 workers on the H100 machine:
    imports, EGL, CUDA and Warp) is paid once rather than every epoch; each epoch then makes the same samples.
    With ``workers`` > 1 each worker renders with one llvmpipe thread (``LP_NUM_THREADS=1`` unless set), since the
    workers already use the cores; NVIDIA's EGL ignores the variable.

    Args:
        dataset: the streaming data set.
        batch_size: samples per batch.
        workers: DataLoader worker processes (0 makes samples in the calling process).
        **kwargs: passed to ``DataLoader`` (e.g. ``pin_memory``, ``prefetch_factor``).
    """
    if workers > 0:
        kwargs.setdefault("multiprocessing_context", "spawn")
        kwargs.setdefault("persistent_workers", True)
        if workers > 1:
            kwargs.setdefault("worker_init_fn", _single_thread_llvmpipe)
    return DataLoader(dataset, batch_size=batch_size, num_workers=workers, **kwargs)

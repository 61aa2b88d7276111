"""Reading a simulator data set with torch: :class:`ShardDataset`, one split of a data set folder, sample by sample.

Items are dictionaries of tensors (:func:`sample_tensors`):

    ``image``       ``(3, S * H / W, S)`` float32 RGB in [0, 1] (the stored uint8 divided by 255), CHW
    ``labels``      ``(D, H, W)`` uint8 ground-truth labels of the grid (0 = empty), indexed ``[k, j, i]``
    ``pose``        ``(4, 4)`` float64 camera-to-world of the camera (world frame z up, OpenCV axes)
    ``K``           ``(3, 3)`` float64 intrinsics of ``image``, the grid's view (the grid's own camera is ``K``
                    scaled by ``W / S``)
    ``camera``      the sample's camera: a dictionary of tensors keyed by :data:`.cameras.CAMERA_KEYS` (its
                    rendered camera's intrinsics and size, pose, height above the floor, gravity direction,
                    pitch, roll, field of view, and the grid columns ``image`` covers), shapes and dtypes there
    ``index``       ``()`` int64 sample index in the split

Labels stay uint8, as stored, until the device: an int64 copy would cost eight times the memory and bandwidth in
the workers, the DataLoader's queues and pinned memory (16 MiB instead of 2 MiB per 128^3 sample). The kernels
take uint8 volumes as they are; a training step converts with ``.long()`` on the device where a loss needs it.

Own-view truth (the label and depth of each column's first occupied cell) is not an item: it is
``fruxel.kernels.first_hit(labels, grid, grid.camera())`` on the device, which :class:`fruxel.train.losses.ShellLoss`
computes with the other views' truth and returns as ``ShellTargets.own_view`` (see :mod:`.sample`).

Training reads shards, or makes samples on the fly, through one path: the engine's blocks of whole rooms
(:class:`fruxel.train.samples.BlockStream`, batched by :class:`fruxel.train.samples.Batches`), which read
shards with :meth:`ShardDataset.sample` and simulate with :class:`.sample.SampleMaker`; the same config and seed
give the same samples either way.
"""

from __future__ import annotations

import os
from collections import OrderedDict
from typing import Any

import numpy as np
import torch
from torch.utils.data import Dataset

from .config import ConfigError, SimConfig
from .manifest import MANIFEST, Manifest
from .sample import Sample
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
        "camera": {k: torch.from_numpy(np.array(v)) for k, v in sample.camera_arrays().items()},
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
            reader = ShardReader(os.path.join(self.root, spec.file), spec, self.config, self.manifest.seed, sha,
                                 version=self.manifest.version)
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

"""Samples for a model: split S of a source (the simulator's stream, a data set folder of shards, or a data folder of
labelled photos, :mod:`fruxel.train.folder`) made or read for model M, in batches. The one data path of training,
evaluation, calibration and the demos.

Order and resuming
    A rank's samples form a sequence of *blocks*, block ``q`` being one room's samples (``samples_per_scene``
    consecutive indices, clipped to the rank's range). Streaming takes the rooms in index order; shards take each
    epoch's rooms in a permutation seeded by the run; a data folder's samples are independent photos, each a block
    of its own, permuted likewise. Worker ``w`` of ``K`` makes blocks ``q = w, w + K, ...``; the
    DataLoader returns its workers' results round-robin, so the main process receives blocks in the order
    ``q = 0, 1, 2, ...`` whatever ``K`` is. A batch is the next ``batch`` samples of that sequence, and the
    position ``(next block, samples of it already used)`` is all a checkpoint needs to continue with exactly the
    samples an uninterrupted run would have seen.

Mixed rooms
    A stream may make a share of its training rooms as another kind (``data.mix_set``: a test set's camera, world
    and renderer on the training split); :func:`mixed_room` picks them by each room's own draw, so the order and
    resuming above hold unchanged.

Ranks
    Rank ``r`` of ``n`` owns the room-aligned index range :func:`rank_range` of the split: disjoint ranges, so no
    two ranks ever train on the same sample.

Arrays
    Blocks and batches hold ``image`` ``(N, h, w, 3)`` uint8 RGB (image rows and columns, the grid camera's
    image), ``labels`` ``(N, D, H, W)`` uint8 (grid frame), ``index`` ``(N,)`` int64, and ``camera``, a dictionary
    of each sample's camera (:data:`fruxel.train.sim.cameras.CAMERA_KEYS`):

    ============== ================ ======= ==========================================================================
    key            shape            dtype   what, in which frame
    ============== ================ ======= ==========================================================================
    ``intrinsics`` ``(N, 4)``       float64 ``fx, fy, cx, cy`` of the rendered camera, pixels of its own render
    ``image_size`` ``(N, 2)``       int64   ``width, height`` of that render, pixels
    ``pose``       ``(N, 4, 4)``    float64 camera-to-world (= the grid's pose), OpenCV axes, world z up, metres
    ``height``     ``(N,)``         float64 optical centre above the floor, metres
    ``gravity``    ``(N, 3)``       float64 unit direction of gravity in the camera frame (x right, y down, z ahead)
    ``pitch``      ``(N,)``         float64 degrees, positive looking down
    ``roll``       ``(N,)``         float64 degrees, positive clockwise as seen from behind the camera
    ``hfov``       ``(N,)``         float64 the camera's horizontal field of view, degrees
    ``coverage``   ``(N, H, W)``    bool    grid frame: the columns ``image`` covers (not grey padding)
    ============== ================ ======= ==========================================================================

    A data folder's samples give NaN where their camera file does not say (:mod:`fruxel.train.folder`): the pose,
    the gravity direction with pitch and roll, the height.

    ``image`` is always the grid's view: a camera of another field of view is framed onto it as the commands frame a
    photo (:mod:`fruxel.train.sim.cameras`); ``labels`` are the full truth, covered columns or not. Images and
    labels stay uint8 until the training device (:func:`fruxel.train.engine.data.to_device`), where images become
    ``(N, 3, h, w)`` float in [0, 1]; the camera stays on the host until a network takes it.
"""

from __future__ import annotations

import atexit
import dataclasses
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

from fruxel.errors import ConfigError, FruxelError
from fruxel.kernels.wp.runtime import cuda_wait, set_cuda_wait

from .config import DATA_SOURCES, DataConfig
from .folder import grid_words
from .models.registry import ModelConfig


class DataError(FruxelError, ValueError):
    """Samples that cannot be had for a model: a data set folder that is missing, foreign, of another grid, image
    size or class table, or without the split asked for; a corrupt shard found by a worker."""


@dataclass(frozen=True)
class SampleSource:
    """Where samples come from."""

    source: str = "stream"
    """``"stream"``: made by the simulator for the model's grid and image size; ``"shards"``: a data set folder;
    ``"folder"``: a data folder of labelled photos (:mod:`fruxel.train.folder`)."""
    root: str = ""
    """The data set folder (``source = "shards"``) or data folder (``source = "folder"``)."""
    seed: int = 0
    """The simulator's base seed (streaming; a data set has its own)."""
    augment: bool = True
    """Appearance augmentation of streamed images (a data set has its own setting)."""
    samples_per_scene: int = DataConfig.samples_per_scene
    """Consecutive samples per room (streaming; a data set has its own)."""
    camera: str = "robot"
    """The cameras streamed samples take, by name (:data:`fruxel.train.sim.cameras.CAMERAS`: ``"robot"``, the
    robot's own mount, or ``"any"``); a data set has its own."""
    world: str = "flat"
    """The simulator's world of streamed samples (:data:`fruxel.train.sim.config.WORLDS`); a data set has its own."""
    renderer: str = ""
    """The renderer of streamed samples; "" takes the world's own (:data:`fruxel.train.sim.config.WORLD_RENDERERS`)."""
    assets: str = ""
    """The asset pack folder of the home world ("": the default one, :func:`fruxel.train.sim.rooms.resolve_pack`)."""
    test_set: str = ""
    """A held-out test set (:data:`fruxel.train.sim.testsets.TEST_SETS`) whose config streamed samples take: its
    camera, world, renderer and asset split replace the source's own; "" for none."""
    mix_set: str = ""
    """A test set whose camera, world and renderer ``mix_share`` of the streamed training rooms take
    (:attr:`~fruxel.train.config.DataConfig.mix_set`); "" for none."""
    mix_share: float = 0.0
    """The share of streamed training rooms made as ``mix_set``'s, in [0, 1)."""

    def __post_init__(self) -> None:
        from fruxel.train.sim.cameras import CAMERAS
        from fruxel.train.sim.testsets import TEST_SETS

        if self.source not in DATA_SOURCES:
            raise DataError(f"sample source must be one of {', '.join(DATA_SOURCES)}, got {self.source!r}")
        if self.camera not in CAMERAS:
            raise DataError(f"sample source camera must be one of {', '.join(CAMERAS)}, got {self.camera!r}")
        if self.test_set and (self.test_set not in TEST_SETS or self.source != "stream"):
            raise DataError(f"sample source test set must be one of {', '.join(TEST_SETS)} and streamed, got "
                            f"{self.test_set!r} ({self.source})")

    @classmethod
    def of(cls, data: DataConfig) -> SampleSource:
        """The source a training run's :class:`~fruxel.train.config.DataConfig` describes."""
        return cls(data.source, data.root, data.seed, data.augment, data.samples_per_scene, data.camera, data.world,
                   data.renderer, data.assets, mix_set=data.mix_set, mix_share=data.mix_share)

    def describe(self) -> str:
        """The source in words, e.g. ``"simulator stream, seed 0, augmented"``."""
        if self.source == "shards":
            return f"data set {self.root}"
        if self.source == "folder":
            return f"data folder {self.root}"
        if self.test_set:
            what = f", test set {self.test_set}"
        else:
            what = ("" if self.camera == "robot" else f", {self.camera} camera") + \
                ("" if self.world == "flat" else f", {self.world} world")
        if self.mix_share > 0:
            what += f", {self.mix_share:.0%} of its training rooms as test set {self.mix_set}'s"
        return (f"simulator stream, seed {self.seed}, {self.samples_per_scene} samples per room, "
                f"{'augmented' if self.augment else 'no augmentation'}{what}")


def sim_config(model: ModelConfig, source: SampleSource, splits: tuple[tuple[str, int], ...]) -> Any:
    """The simulator settings that make ``model``'s samples from a streamed ``source``: its grid, class table and
    image size, the source's rooms, camera and augmentation, and ``splits`` (a streamed sample depends on the seed, the
    split's name and its index, never on the split's size); with a test set, that config turned into the test set's
    (:meth:`fruxel.train.sim.testsets.EvaluationSet.config`).

    Raises:
        ConfigError: a test set of the room world for a model whose classes lack ``ceiling`` and ``object``.
    """
    from fruxel.train.sim.cameras import camera_named
    from fruxel.train.sim.config import WORLD_RENDERERS, AugmentConfig, ImageConfig, SimConfig
    from fruxel.train.sim.testsets import TEST_SETS

    config = SimConfig(grid=model.grid, classes=model.classes, samples_per_scene=source.samples_per_scene,
                       image=ImageConfig(size=model.image_size[1], augment=AugmentConfig(enabled=source.augment)),
                       splits=splits, camera=camera_named(source.camera), world=source.world,
                       renderer=source.renderer or WORLD_RENDERERS[source.world], assets=source.assets or None)
    return TEST_SETS[source.test_set].config(config) if source.test_set else config


def check_data_set(root: str, model: ModelConfig) -> Any:
    """The manifest of a data set folder, checked against a model.

    Returns:
        The data set's :class:`fruxel.train.sim.manifest.Manifest` (``.config``: its simulator config, ``.seed``).

    Raises:
        DataError: no data set there (or a broken manifest), or its grid (size and frustum), image size or
            class table differ from the model's.
    """
    from fruxel.train.sim.manifest import MANIFEST, Manifest
    from fruxel.train.sim.shards import DatasetError

    path = os.path.join(root, MANIFEST)
    if not os.path.isdir(root):
        raise DataError(f"{root}: {'no such folder' if not os.path.exists(root) else 'not a folder'}")
    if not os.path.isfile(path):
        raise DataError(f"{root}: not a data set folder (no {MANIFEST}; make one with fruxel-sim generate)")
    try:
        manifest = Manifest.load(path)
    except DatasetError as e:
        raise DataError(str(e)) from None
    sc = manifest.config
    problems = []
    if sc.grid != model.grid:
        problems.append(f"grid {grid_words(sc.grid)} (the model's: {grid_words(model.grid)})")
    if (sc.image_height, sc.image_width) != model.image_size:
        problems.append(f"images {sc.image_width}x{sc.image_height} (the model's: {model.image_size[1]}x"
                        f"{model.image_size[0]})")
    if sc.classes != model.classes:
        problems.append(f"classes {list(sc.classes.names)} (the model's: {list(model.classes.names)})")
    if problems:
        raise DataError(f"{root}: the data set does not fit the model: {'; '.join(problems)}")
    return manifest


def check_folder_set(root: str, model: ModelConfig) -> Any:
    """A data folder of labelled photos (:mod:`fruxel.train.folder`), checked whole against a model.

    Returns:
        Its :class:`fruxel.train.folder.FolderSet`.

    Raises:
        DataError: see :func:`fruxel.train.folder.check_folder` (one line naming the file).
    """
    from .folder import FolderError, check_folder

    try:
        return check_folder(root, model.grid, model.classes.names)
    except FolderError as e:
        raise DataError(str(e)) from None


def split_size(source: SampleSource, model: ModelConfig, split: str) -> int | None:
    """Samples in ``split`` of a data set or data folder (None for the stream, which has any number).

    Raises:
        DataError: see :func:`check_data_set` and :func:`check_folder_set`; a split the data set does not have.
    """
    if source.source == "folder":
        splits = check_folder_set(source.root, model).splits
        if split not in splits:
            raise DataError(f"{source.root}: the data folder has no split {split!r} (its splits: "
                            f"{', '.join(splits)})")
        return len(splits[split])
    if source.source != "shards":
        _check_stream(source, model, split)
        return None
    from fruxel.train.sim.dataset import ShardDataset
    from fruxel.train.sim.shards import DatasetError

    sc = check_data_set(source.root, model).config
    names = [name for name, _ in sc.splits]
    if split not in names:
        raise DataError(f"{source.root}: the data set has no split {split!r} (its splits: {', '.join(names)})")
    try:
        # Refuses a split whose shards are not all written yet.
        ShardDataset(source.root, split, verify=False)
    except DatasetError as e:
        raise DataError(str(e)) from None
    return sc.split_samples(split)


def _check_stream(source: SampleSource, model: ModelConfig, split: str) -> None:
    """Refuse a streamed ``split`` whose rooms need an asset pack that is not there (or whose workers are told an
    unknown way to wait for CUDA), in this process: the workers that would make the samples find it only after they
    start, each in its own traceback.

    Raises:
        ConfigError: see :func:`sim_config`; no asset pack where ``data.assets`` (or ``$FRUXEL_ASSETS``, or the
            repository's ``assets/pack``) points.
        BackendError: an unknown ``$FRUXEL_CUDA_WAIT`` (the workers' :func:`set_cuda_wait`).
    """
    from fruxel.train.sim.rooms import check_pack

    check_pack(sim_config(model, source, ((split, 1),)), option="data.assets")
    if source.mix_share > 0 and split == "train":
        check_pack(sim_config(model, _mixed_in(source), ((split, 1),)), option="data.assets")
    cuda_wait()


def _mixed_in(source: SampleSource) -> SampleSource:
    """The source of the rooms a stream mixes in: ``source`` as its ``mix_set``'s (camera, world, renderer)."""
    return dataclasses.replace(source, test_set=source.mix_set, mix_set="", mix_share=0.0)


MIX_DRAW = 0x6D6978
"""A constant of the mix's random draws (:func:`mixed_room`), apart from every other draw of the simulator's."""


def mixed_room(seed: int, room: int, share: float) -> bool:
    """Whether streamed training room ``room`` (of base seed ``seed``) is made as the mix's
    (:attr:`~fruxel.train.config.DataConfig.mix_share`): a draw of its own per room, so the same rooms whatever the
    workers, ranks or resumes."""
    return share > 0 and bool(np.random.default_rng([MIX_DRAW, seed, room]).random() < share)


def split_batches(source: SampleSource, model: ModelConfig, split: str, count: int, batch: int, *, workers: int = 0,
                  device: str | None = None, camera: bool = False) -> Iterator[tuple[Any, ...]]:
    """The first ``count`` samples of ``split`` in batches of ``batch`` (the last one smaller).

    Args:
        source: where the samples come from.
        model: the model's architecture (grid, image size and classes of streamed samples).
        split: e.g. ``"test"``.
        count: samples, >= 1 (at most the split's size for a data set).
        batch: samples per batch.
        workers: DataLoader worker processes that make or read the samples (0: this process).
        device: Warp device of the simulator's ``fruxelize`` (None: CUDA when present).
        camera: also yield each batch's camera record (for a network that reads the camera).

    Yields:
        ``(images (B, h, w, 3) uint8, labels (B, D, H, W) uint8)`` CPU tensors, with ``camera`` a third item: the
        batch's camera record, a dictionary of CPU tensors (module docstring).

    Raises:
        DataError: see :func:`check_data_set`; a corrupt shard.
    """
    spp, reading = _reading(source, model, ((split, count),))
    plan = BlockPlan(0, count, spp, None)

    def factory(block: int, skip: int) -> BlockStream:
        # The stream ends after the blocks of ``count`` samples: the workers make nothing that is not used.
        return BlockStream(plan, source.source, split, **reading, first_block=block, skip=skip, device=device,
                           stop_block=plan.rooms[1] - plan.rooms[0])

    loader = Batches(factory, batch, min(workers, math.ceil(count / spp)))
    try:
        done = 0
        while done < count:
            b = next(loader)
            take = min(count - done, len(b["index"]))
            if camera:
                yield b["image"][:take], b["labels"][:take], {k: v[:take] for k, v in b["camera"].items()}
            else:
                yield b["image"][:take], b["labels"][:take]
            done += take
    finally:
        loader.close()


def load_split(source: SampleSource, model: ModelConfig, split: str, count: int, *, workers: int = 0,
               device: str | None = None, camera: bool = False) -> tuple[Any, ...]:
    """The first ``count`` samples of ``split`` at once (a training run's evaluation set): ``(images (N, h, w, 3)
    uint8, labels (N, D, H, W) uint8)``, N = ``count`` or the split's size if smaller; with ``camera``, their camera
    record (a dictionary of tensors) third.

    Raises:
        DataError: no such split, or an empty one; see :func:`split_batches`.
    """
    size = split_size(source, model, split)
    count = count if size is None else min(count, size)
    if count <= 0:
        raise DataError(f"{source.describe()}: no {split} split to evaluate on")
    parts = list(zip(*split_batches(source, model, split, count, count, workers=workers, device=device,
                                    camera=camera), strict=True))
    out: tuple[Any, ...] = (torch.cat(parts[0]), torch.cat(parts[1]))
    if camera:
        out += ({k: torch.cat([torch.as_tensor(c[k]) for c in parts[2]]) for k in parts[2][0]},)
    return out


def training_batches(source: SampleSource, model: ModelConfig, samples: int, *, batch: int, workers: int,
                     rank: int = 0, world: int = 1, position: tuple[int, int] = (0, 0), shuffle_seed: int = 0,
                     pin: bool = False, device: str | None = None) -> Batches:
    """The endless, resumable batches of a rank's part of the train split (see the module docstring).

    Args:
        source: where the samples come from.
        model: the model (grid, image size and classes of streamed samples).
        samples: the train split's size (:func:`train_split_size`).
        batch: samples per batch (the rank's share of the global batch).
        workers: DataLoader worker processes.
        rank, world: this process's distributed rank and the number of ranks.
        position: ``(block, used)`` to start from (a checkpoint's).
        shuffle_seed: seed of the per-epoch room order of a data set (streaming takes rooms in order).
        pin: pin batches in page-locked memory (for CUDA).
        device: Warp device of the simulator's ``fruxelize``.

    Raises:
        DataError: fewer rooms than ranks.
    """
    spp, reading = _reading(source, model, (("train", samples),))
    if source.source == "stream" and source.mix_share > 0:
        reading["mix"] = (sim_config(model, _mixed_in(source), (("train", samples),)), source.mix_share)
    try:
        lo, hi = rank_range(samples, spp, rank, world)
    except ValueError as e:
        where = "data.train_samples" if source.source == "stream" else source.root
        raise DataError(f"{where}: training split: {e}") from None
    plan = BlockPlan(lo, hi, spp, None if source.source == "stream" else shuffle_seed)

    def factory(block: int, skip: int) -> BlockStream:
        return BlockStream(plan, source.source, "train", **reading, first_block=block, skip=skip, device=device)

    return Batches(factory, batch, workers, pin=pin, position=position)


MPS_PIPE_DEFAULT = "/tmp/nvidia-mps"
"""Where CUDA's Multi-Process Service keeps its control pipe unless ``$CUDA_MPS_PIPE_DIRECTORY`` says otherwise."""


def mps_pipe() -> str:
    """The folder of CUDA MPS's control pipe (``$CUDA_MPS_PIPE_DIRECTORY``, else :data:`MPS_PIPE_DEFAULT`)."""
    return os.environ.get("CUDA_MPS_PIPE_DIRECTORY") or MPS_PIPE_DEFAULT


def mps_running() -> bool:
    """Whether CUDA MPS's control daemon runs on this machine (its control pipe stands in :func:`mps_pipe`)."""
    return os.path.exists(os.path.join(mps_pipe(), "control"))


MPS_CLIENTS = 48
"""CUDA processes one GPU serves under MPS (Volta and later): on the one-GPU H200 machine 48 simulator workers
streamed and 60 failed to get a CUDA context (BENCHMARKS.md, "## Simulator", h200-w48-room32)."""


def check_mps_clients(source: SampleSource, workers: int, device: str | None) -> None:
    """Refuse more streamed-simulator workers on one CUDA device than CUDA MPS serves beside the training process.

    Args:
        source: the training data.
        workers: DataLoader workers of the rank.
        device: the Warp device the workers draw on (``"cuda:N"`` or ``"cpu"``).

    Raises:
        ConfigError: MPS runs and the workers and the training process are more than :data:`MPS_CLIENTS` (the
            workers would fail to get a CUDA context after their start-up).
    """
    if source.source != "stream" or not str(device or "").startswith("cuda") or not mps_running():
        return
    if workers + 1 > MPS_CLIENTS:
        raise ConfigError(f"data.workers {workers}: with CUDA MPS on, one GPU serves at most {MPS_CLIENTS} processes, "
                          f"and the {workers} simulator workers on {device} and the training process are "
                          f"{workers + 1}; use at most {MPS_CLIENTS - 1} workers a GPU")


def gpu_sharing_hint(source: SampleSource, workers: int, device: str | None) -> str | None:
    """A one-line hint when several simulator workers will share one GPU without CUDA's Multi-Process Service, else
    None.

    Each data worker of a streamed simulator is a process with its own CUDA context; without MPS the GPU runs one
    context at a time and the workers wait for each other's time slices: the furnished rooms streamed several times
    faster with MPS on (BENCHMARKS.md, "## Simulator", both rows). MPS is a per-machine daemon
    (``nvidia-cuda-mps-control -d``) that lets their kernels run side by side; fruxel does not start it.

    Args:
        source: the training data.
        workers: DataLoader workers of the rank.
        device: the Warp device the workers draw on (``"cuda:N"`` or ``"cpu"``).
    """
    if source.source != "stream" or workers < 2 or not str(device or "").startswith("cuda"):
        return None
    pipe = mps_pipe()
    if mps_running():
        return None
    return (f"note: {workers} simulator workers share {device} without CUDA MPS (no control pipe in {pipe}); "
            "`nvidia-cuda-mps-control -d` before training lets them run side by side (BENCHMARKS.md, Simulator)")


def _reading(source: SampleSource, model: ModelConfig, splits: tuple[tuple[str, int], ...]
             ) -> tuple[int, dict[str, Any]]:
    """``(samples per block, BlockStream's reading arguments)`` of a source: a data set's own samples per room; one
    sample a block for a data folder, whose samples are independent photos; the stream's, with its simulator config
    of ``splits``."""
    if source.source == "shards":
        return check_data_set(source.root, model).config.samples_per_scene, {"root": source.root}
    if source.source == "folder":
        return 1, {"root": source.root, "folder": check_folder_set(source.root, model),
                   "image_size": model.image_size}
    return source.samples_per_scene, {"sim_config": sim_config(model, source, splits), "seed": source.seed}


def train_split_size(source: SampleSource, model: ModelConfig, streamed: int) -> int:
    """Samples of the train split: ``streamed`` for the stream, the data set's own for shards.

    Raises:
        DataError: see :func:`split_size`.
    """
    size = split_size(source, model, "train")
    return streamed if size is None else size


def _worker_error(e: BaseException) -> BaseException:
    """A fruxel error raised in a DataLoader worker (a corrupt shard, a missing asset) with its own one-line message.

    The DataLoader re-raises a worker's exception as ``X("Caught X in DataLoader worker process N ... Original
    Traceback ... module.X: message")``, or as a ``RuntimeError`` of that text when ``X`` cannot be rebuilt from it
    alone, as fruxel's errors with a file and a problem cannot (those become one :class:`DataError`). Anything else
    (a bug) is returned as it was, traceback and all.
    """
    text = str(e)
    last = text.strip().splitlines()[-1] if text.strip() else ""
    kind, _, message = last.partition(": ")
    if not (text.startswith("Caught ") and "DataLoader worker" in text and kind.startswith("fruxel.") and message):
        return e
    if isinstance(e, FruxelError) and type(e).__name__ == kind.rpartition(".")[2]:
        try:
            return type(e)(message)
        except TypeError:
            pass
    return DataError(message)


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
        source: ``"stream"`` (a :class:`~fruxel.train.sim.shards.SampleMaker` per worker), ``"shards"`` or
            ``"folder"``.
        split: the split's name.
        sim_config: the simulator config (streaming).
        seed: the simulator's base seed (streaming).
        root: the data set folder (shards) or data folder.
        folder: the checked data folder (:class:`fruxel.train.folder.FolderSet`; ``source = "folder"``).
        image_size: ``(height, width)`` the data folder's photos are framed to (the model's image size).
        first_block: the block to start with.
        skip: samples of the first block to leave out (already used before a resume).
        device: Warp device of the simulator's ``fruxelize`` (None: CUDA when present).
        stop_block: the block to stop before (None: endless, the range repeating in epochs). A loader that needs a
            known number of samples (the evaluation set) stops there, so its workers make nothing more.
        mix: ``(simulator config, share)``: the rooms that :func:`mixed_room` picks are made with that config instead
            (streaming; :attr:`~fruxel.train.config.DataConfig.mix_set`); None: none.
    """

    def __init__(self, plan: BlockPlan, source: str, split: str, *, sim_config: Any = None, seed: int = 0,
                 root: str = "", folder: Any = None, image_size: tuple[int, int] = (0, 0), first_block: int = 0,
                 skip: int = 0, device: str | None = None, stop_block: int | None = None,
                 mix: tuple[Any, float] | None = None) -> None:
        super().__init__()
        self.plan = plan
        self.source = source
        self.split = split
        self.sim_config = sim_config
        self.seed = seed
        self.root = root
        self.folder = folder
        self.image_size = image_size
        self.first_block = first_block
        self.skip = skip
        self.device = device
        self.stop_block = stop_block
        self.mix = mix

    def _reader(self, sim_config: Any = None) -> tuple[Callable[[int], Any], Callable[[], None]]:
        """``(read, close)``: sample ``i`` of the split (simulated, with ``sim_config`` if given, else the stream's
        own; read from shards or from a data folder), and the closing of what reading holds."""
        if self.source == "folder":
            return (lambda i: self.folder.sample(self.split, i, self.image_size)), (lambda: None)
        if self.source == "stream":
            from fruxel.train.sim.sample import SampleMaker

            maker = SampleMaker(sim_config or self.sim_config, self.seed, backend="warp", device=self.device)
            return (lambda i: maker.make(self.split, i)), maker.close
        from fruxel.train.sim.dataset import ShardDataset

        ds = ShardDataset(self.root, self.split)
        return ds.sample, ds.close

    def _start_stream(self) -> None:
        """Set up this process for the simulator, before a renderer makes its contexts."""
        if get_worker_info() is not None:
            # How a worker waits for its GPU ($FRUXEL_CUDA_WAIT), set before its renderer makes the CUDA context;
            # not in a process that also trains (no workers), whose context is torch's.
            set_cuda_wait()
        if self.device is not None and self.device.startswith("cuda:"):
            # An EGL renderer draws on the GPU this stream's kernels use, not on GPU 0 for every rank's workers
            # (pyrender reads EGL_DEVICE_ID when it makes its context, after this).
            os.environ["EGL_DEVICE_ID"] = self.device.split(":", 1)[1]

    def _block_reader(self, block: range, readers: dict[bool, tuple[Callable[[int], Any], Callable[[], None]]]
                      ) -> Callable[[int], Any]:
        """The reader of a block (its whole index range): the mix's when :func:`mixed_room` picks its room (made at
        its first room and kept in ``readers``), else the stream's own (``readers[False]``)."""
        room = block.start // self.plan.samples_per_scene
        mixed = self.mix is not None and mixed_room(self.seed, room, self.mix[1])
        if mixed and True not in readers:
            readers[True] = self._reader(self.mix[0])
        return readers[mixed][0]

    def __iter__(self) -> Iterator[dict[str, np.ndarray]]:
        info = get_worker_info()
        worker, workers = (0, 1) if info is None else (info.id, info.num_workers)
        if self.source == "stream":
            self._start_stream()
        readers = {False: self._reader()}

        def close() -> None:
            for _, shut in readers.values():
                shut()

        q = self.first_block + worker
        # What reading holds (the renderer's OpenGL context and Warp meshes, or open shard files) is freed when the
        # iteration ends or the generator is dropped; in a DataLoader worker, when its loop returns, before the
        # interpreter exits. Left to the exit, the EGL and CUDA contexts are torn down in whatever order the
        # interpreter's clean-up takes (the suspected cause of workers aborting after training on the H100).
        try:
            while self.stop_block is None or q < self.stop_block:
                idx = self.plan.block(q)
                read = self._block_reader(idx, readers)
                if q == self.first_block:
                    idx = idx[self.skip:]
                samples = [read(i) for i in idx]
                cams = [s.camera_arrays() for s in samples]
                block = {
                    "image": np.stack([s.image for s in samples]),
                    "labels": np.stack([np.asarray(s.labels, dtype=np.uint8) for s in samples]),
                    "index": np.asarray([s.index for s in samples], dtype=np.int64),
                    "camera": {k: np.stack([c[k] for c in cams]) for k in cams[0]},
                    "block": np.int64(q),
                }
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


BATCH_KEYS = ("image", "labels", "index", "camera")
"""What a batch of :class:`Batches` holds (``camera`` a dictionary of tensors; the module docstring)."""


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

    def __next__(self) -> dict[str, Any]:
        """The next batch: ``batch`` samples, fewer only at the end of a stream with a last block.

        Raises:
            StopIteration: that stream has ended.
        """
        if self._it is None:
            self._it = iter(self._loader)
        parts: list[dict[str, Any]] = []
        need = self.batch
        while need:
            if self._buf is None:
                try:
                    nxt = next(self._it, None)
                except Exception as e:  # noqa: BLE001 - a worker's error, cleaned up when it is fruxel's own
                    raise _worker_error(e) from None
                if nxt is None:  # a stream with a last block (stop_block) has ended
                    if not parts:
                        raise StopIteration
                    break
                self._buf = nxt
                self._block = int(self._buf["block"])
                self._offset = 0
                # The stream's first block comes without the samples used before a resume.
                self._base = self._start[1] if self._block == self._start[0] else 0
            n = len(self._buf["index"])
            take = min(n - self._offset, need)
            sl = slice(self._offset, self._offset + take)
            parts.append({k: _take(self._buf[k], sl) for k in BATCH_KEYS if k in self._buf})
            self._offset += take
            need -= take
            if self._offset == n:
                self._next = (self._block + 1, 0)
                self._buf = None
        return _join(parts)

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


def _take(value: Any, sl: slice) -> Any:
    """Rows ``sl`` of a block's array, or of every array of a dictionary of them, as tensors."""
    if isinstance(value, dict):
        return {k: _take(v, sl) for k, v in value.items()}
    return torch.as_tensor(value[sl])


def _join(parts: list[Any]) -> Any:
    """The parts of one batch (tensors, or dictionaries of them alike) concatenated along the first axis."""
    if isinstance(parts[0], dict):
        return {k: _join([p[k] for p in parts]) for k in parts[0]}
    return torch.cat(parts) if len(parts) > 1 else parts[0]


def _signal_name(number: int) -> str:
    try:
        return signal.Signals(number).name
    except ValueError:
        return f"signal {number}"

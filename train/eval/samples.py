"""Samples to evaluate a model on: a split of a data set folder (``fruxel-sim generate``) or the simulator's stream
made for the model's grid and image size, read in batches by the training engine's loaders.

Batches are ``(images (B, h, w, 3) uint8 RGB, labels (B, D, H, W) uint8)`` host tensors: the grid camera's image
and the grid-frame labels, in index order from sample 0 of the split.
"""

from __future__ import annotations

import math
import os
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import torch

from fruxel.errors import FruxelError

from ..config import DataConfig, ModelConfig, TrainConfig


class EvalDataError(FruxelError, ValueError):
    """A data set that cannot be evaluated on: missing, foreign, of another grid, image size or class table, or
    without the split asked for."""


@dataclass(frozen=True)
class EvalData:
    """Where evaluation samples come from."""

    source: str = "stream"
    """``"stream"``: made by the simulator for the model's grid and image size; ``"shards"``: a data set folder."""
    root: str = ""
    """The data set folder (``source = "shards"``)."""
    seed: int = 0
    """The simulator's base seed (streaming; a data set has its own)."""
    augment: bool = True
    """Appearance augmentation of streamed images (a data set has its own setting)."""
    samples_per_scene: int = DataConfig.samples_per_scene
    """Consecutive samples per room (streaming; a data set has its own)."""

    def describe(self) -> str:
        """The source in words, e.g. ``"simulator stream, seed 0, augmented"``."""
        if self.source == "shards":
            return f"data set {self.root}"
        return (f"simulator stream, seed {self.seed}, {self.samples_per_scene} samples per room, "
                f"{'augmented' if self.augment else 'no augmentation'}")


def data_set_manifest(root: str, model: ModelConfig) -> Any:
    """The manifest of a data set folder, checked against a model.

    Returns:
        The data set's :class:`fruxel.train.sim.manifest.Manifest` (``.config``: its simulator config, ``.seed``).

    Raises:
        EvalDataError: no data set there (or a broken manifest), or its grid (size and frustum), image size or
            class table differ from the model's.
    """
    from fruxel.train.sim.manifest import MANIFEST, Manifest
    from fruxel.train.sim.shards import DatasetError

    path = os.path.join(root, MANIFEST)
    if not os.path.isdir(root):
        raise EvalDataError(f"{root}: {'no such folder' if not os.path.exists(root) else 'not a folder'}")
    if not os.path.isfile(path):
        raise EvalDataError(f"{root}: not a data set folder (no {MANIFEST}; make one with fruxel-sim generate)")
    try:
        manifest = Manifest.load(path)
    except DatasetError as e:
        raise EvalDataError(str(e)) from None
    sc = manifest.config
    g, m = sc.grid, model.grid
    problems = []
    if g != m:
        problems.append(f"grid {g.width}x{g.height}x{g.depth} z {g.z_near:g}..{g.z_far:g} m hfov {g.hfov:g} (the "
                        f"model's: {m.width}x{m.height}x{m.depth} z {m.z_near:g}..{m.z_far:g} m hfov {m.hfov:g})")
    if (sc.image_height, sc.image_width) != model.image_size:
        problems.append(f"images {sc.image_width}x{sc.image_height} (the model's: {model.image_size[1]}x"
                        f"{model.image_size[0]})")
    if sc.classes != model.classes:
        problems.append(f"classes {list(sc.classes.names)} (the model's: {list(model.classes.names)})")
    if problems:
        raise EvalDataError(f"{root}: the data set does not fit the model: {'; '.join(problems)}")
    return manifest


def split_size(data: EvalData, model: ModelConfig, split: str) -> int | None:
    """Samples in ``split`` of a data set (None for the stream, which has any number).

    Raises:
        EvalDataError: see :func:`data_set_manifest`; a split the data set does not have.
    """
    if data.source != "shards":
        return None
    from fruxel.train.sim.dataset import ShardDataset
    from fruxel.train.sim.shards import DatasetError

    sc = data_set_manifest(data.root, model).config
    names = [name for name, _ in sc.splits]
    if split not in names:
        raise EvalDataError(f"{data.root}: the data set has no split {split!r} (its splits: {', '.join(names)})")
    try:
        # Refuses a split whose shards are not all written yet.
        ShardDataset(data.root, split, verify=False)
    except DatasetError as e:
        raise EvalDataError(str(e)) from None
    return sc.split_samples(split)


def batches(data: EvalData, model: ModelConfig, split: str, count: int, batch: int, *, workers: int = 0,
            device: str | None = None) -> Iterator[tuple[torch.Tensor, torch.Tensor]]:
    """The first ``count`` samples of ``split`` in batches of ``batch`` (the last one smaller).

    Args:
        data: the source.
        model: the model's architecture (grid, image size and classes of streamed samples).
        split: e.g. ``"test"``.
        count: samples, >= 1 (at most the split's size for a data set).
        batch: samples per batch.
        workers: DataLoader worker processes that make or read the samples (0: this process).
        device: Warp device of the simulator's ``fruxelize`` (None: CUDA when present).

    Yields:
        ``(images (B, h, w, 3) uint8, labels (B, D, H, W) uint8)`` CPU tensors.
    """
    from ..engine.data import Batches, BlockPlan, BlockStream
    from ..engine.trainer import sim_config

    if data.source == "shards":
        spp = data_set_manifest(data.root, model).config.samples_per_scene
        sim = None
    else:
        spp = data.samples_per_scene
        config = TrainConfig(model=model, data=DataConfig(seed=data.seed, augment=data.augment, samples_per_scene=spp))
        # A streamed sample depends on the seed, the split's name and its index, never on the split's size.
        sim = sim_config(config).replace(splits=((split, count),))
    plan = BlockPlan(0, count, spp, None)

    def factory(block: int, skip: int) -> Any:
        return BlockStream(plan, data.source, split, sim_config=sim, seed=data.seed, root=data.root,
                           first_block=block, skip=skip, device=device)

    # The stream of blocks is endless (it starts over after the last room); a last batch that is not full is cut
    # to size, at the cost of making at most batch - 1 samples for nothing.
    loader = Batches(factory, batch, min(workers, math.ceil(count / spp)))
    try:
        done = 0
        while done < count:
            try:
                b = next(loader)
            except RuntimeError as e:
                raise _worker_error(e) from None
            take = min(count - done, len(b["index"]))
            yield b["image"][:take], b["labels"][:take]
            done += take
    finally:
        loader.close()


def _worker_error(e: RuntimeError) -> BaseException:
    """A fruxel error raised in a DataLoader worker (a corrupt shard, say) as one :class:`EvalDataError`.

    The DataLoader re-raises a worker's exception as ``RuntimeError("Caught X in DataLoader worker process N ...
    Original Traceback ... module.X: message")`` when ``X`` cannot be rebuilt from that text alone, as fruxel's
    errors with a file and a problem cannot. Anything else (a bug) is returned as it was, traceback and all.
    """
    text = str(e)
    last = text.strip().splitlines()[-1] if text.strip() else ""
    kind, _, message = last.partition(": ")
    if text.startswith("Caught ") and "DataLoader worker" in text and kind.startswith("fruxel.") and message:
        return EvalDataError(message)
    return e

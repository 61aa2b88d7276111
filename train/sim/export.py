"""The simulator's samples written as a data folder of labelled photos (:mod:`fruxel.train.folder`), behind
``fruxel-sim export``: an example of the format for users, and data for its tests.

Sample ``i`` of split ``S`` becomes ``S/NNNNNN.png`` (the camera's render before framing: a photo of its own size
and field of view, lossless), ``S/NNNNNN.json`` (its intrinsics, camera-to-world pose and height above the floor)
and ``S/NNNNNN.npy`` (the labels); ``dataset.json`` lists the splits. Read back with the model's grid and image
size, each gives the simulator's sample: the same framed image, labels and camera.

The folder is written whole under a temporary name beside ``out`` and renamed into place at the end, so a killed
export leaves nothing under ``out``; an existing ``out`` is refused unless ``overwrite`` (and then only a data folder
or an empty folder is replaced).
"""

from __future__ import annotations

import json
import os
import shutil
import tempfile
from typing import Any

import numpy as np

from ..folder import DATASET_JSON, FolderError, dataset_json, is_folder_set
from .config import SimConfig
from .sample import Sample, SampleMaker


def sample_files(sample: Sample, render: np.ndarray) -> tuple[np.ndarray, dict[str, Any], np.ndarray]:
    """``(photo (h, w, 3) uint8, camera file content, labels (D, H, W) uint8)`` of a simulator sample and its
    render (:meth:`.sample.SampleMaker.make_with_render`); the camera's gravity, pitch and roll follow from the
    pose."""
    camera = {"intrinsics": list(sample.camera.intrinsics), "pose": np.asarray(sample.pose).tolist(),
              "height": sample.camera.height}
    return render, camera, np.ascontiguousarray(sample.labels, dtype=np.uint8)


def export_folder(out: str | os.PathLike[str], config: SimConfig, seed: int, *, overwrite: bool = False,
                  backend: str | None = "warp", device: str | None = None, progress: bool = True) -> dict[str, Any]:
    """Write ``config``'s splits as a data folder.

    Args:
        out: the folder to make.
        config: the simulator config (grid, classes, cameras, rooms, splits).
        seed: the simulator's base seed.
        overwrite: replace an existing data folder (or empty folder) at ``out``.
        backend, device: ``fruxelize``'s (:class:`.sample.SampleMaker`).
        progress: a tqdm bar of the samples on stderr.

    Returns:
        The ``dataset.json`` written.

    Raises:
        FolderError: ``out`` exists (without ``overwrite``), or is something other than a data folder or an empty
            folder.
    """
    from tqdm import tqdm

    from fruxel.io import durable_rename

    out = os.path.abspath(os.fsdecode(out))
    check_target(out, overwrite)
    parent = os.path.dirname(out)
    os.makedirs(parent, exist_ok=True)
    tmp = tempfile.mkdtemp(prefix=f".{os.path.basename(out)}.", suffix=".tmp", dir=parent)
    try:
        splits = {}
        total = sum(n for _, n in config.splits)
        with SampleMaker(config, seed, backend=backend, device=device) as maker, \
                tqdm(total=total, unit="sample", desc="fruxel-sim export", disable=not progress) as bar:
            for split, n in config.splits:
                os.makedirs(os.path.join(tmp, split))
                splits[split] = [f"{split}/{i:06d}" for i in range(n)]
                for i, stem in enumerate(splits[split]):
                    _write_sample(os.path.join(tmp, *stem.split("/")), *sample_files(*maker.make_with_render(split, i)))
                    bar.update(1)
        d = dataset_json(config.grid, config.classes.names, splits)
        with open(os.path.join(tmp, DATASET_JSON), "w", encoding="utf-8") as f:
            json.dump(d, f, indent=1)
            f.write("\n")
        old = _set_aside(out, parent)
        try:
            durable_rename(tmp, out)
        except BaseException:
            if old is not None:
                os.rename(old, out)
            raise
        if old is not None:
            shutil.rmtree(old)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return d


def check_target(out: str, overwrite: bool) -> None:
    """Refuse an existing ``out`` without ``overwrite``, and anything but a data folder or empty folder with it."""
    if not os.path.lexists(out):
        return
    if not overwrite:
        raise FolderError(f"{out}: already exists (pass --overwrite to replace it)")
    if not os.path.isdir(out) or os.path.islink(out) or (os.listdir(out) and not is_folder_set(out)):
        raise FolderError(f"{out}: not a data folder (no {DATASET_JSON}) or empty folder; refusing to replace it")


def _set_aside(out: str, parent: str) -> str | None:
    """Move an existing ``out`` to a temporary name beside it (removed once the new folder is in place)."""
    if not os.path.lexists(out):
        return None
    old = tempfile.mkdtemp(prefix=f".{os.path.basename(out)}.", suffix=".old", dir=parent)
    os.rmdir(old)
    os.rename(out, old)
    return old


def _write_sample(base: str, photo: np.ndarray, camera: dict[str, Any], labels: np.ndarray) -> None:
    """The three files of one sample: ``base.png``, ``base.json``, ``base.npy`` (module docstring)."""
    from PIL import Image

    Image.fromarray(np.ascontiguousarray(photo)).save(base + ".png", format="PNG")
    with open(base + ".json", "w", encoding="utf-8") as f:
        json.dump(camera, f)
    np.save(base + ".npy", labels, allow_pickle=False)

"""Streamed evaluation samples kept on disk: a second evaluation of the same test samples reads them back.

Simulating a test set takes minutes on a CPU (the furnished rooms are ray-traced), and every checkpoint of a run, or
every arm of an experiment, is evaluated on the same samples. :func:`cached_split_batches` yields exactly what
:func:`fruxel.train.samples.split_batches` yields for a stream, and the first time writes the samples to
``$FRUXEL_CACHE_DIR/samples/<key>.npz`` (:func:`fruxel.io.cache_folder`), named by a hash of everything that makes
them (:func:`stream_key`: the simulator's settings and seed, the asset pack's manifest and fruxel's own code), the
split, the count, whether camera records travel and the Warp device of the simulator (a CUDA ray tracer may round
otherwise than the CPU's). A file that cannot be read, or holds other shapes, is ignored and made again.
"""

from __future__ import annotations

import hashlib
import importlib.util
import json
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import numpy as np
import torch

MAX_BYTES = 2 << 30
"""Samples of more bytes than this (images and labels together) are streamed without a cache: they are held in
memory until written."""


def code_digest() -> str:
    """SHA-256 of the sources that make and count the samples (fruxel's core, kernels and training packages):
    derived data made by other code is not read back."""
    digest = hashlib.sha256()
    for name in ("fruxel", "fruxel.kernels", "fruxel.train"):
        spec = importlib.util.find_spec(name)
        root = Path(next(iter(spec.submodule_search_locations))) if spec and spec.submodule_search_locations else None
        if root is None:
            continue
        for f in sorted(p for p in root.rglob("*") if p.suffix in (".py", ".cl", ".h") and p.is_file()):
            rel = f.relative_to(root)
            if name == "fruxel" and len(rel.parts) > 1 and rel.parts[0] != "data":
                continue  # the other packages, which an installed wheel nests in fruxel/, are hashed as themselves
            digest.update(f"{name}/{rel.as_posix()}\0".encode())
            digest.update(f.read_bytes())
    return digest.hexdigest()


def stream_key(source: Any, model: Any, splits: tuple[tuple[str, int], ...]) -> dict[str, Any]:
    """What makes a stream's samples, for a cache key: the simulator's settings and seed, fruxel's code
    (:func:`code_digest`) and, for the furnished rooms, the asset pack's manifest (a pack built again from other
    sources draws other rooms).

    Args:
        source: a streamed :class:`fruxel.train.samples.SampleSource`.
        model: the model's config (grid, image size and classes of the samples).
        splits: ``(name, count)`` of the splits the samples are drawn from.
    """
    from fruxel.train.samples import sim_config

    config = sim_config(model, source, splits)
    key: dict[str, Any] = {"stream": config.to_dict(), "seed": source.seed, "code": code_digest()}
    pack = pack_digest(config)
    if pack is not None:
        key["pack"] = pack
    return key


def pack_digest(config: Any) -> str | None:
    """SHA-256 (hex) of the asset pack's ``manifest.json`` that a simulator config's furnished rooms are drawn from
    (the manifest holds every file's SHA-256, so the digest names the pack's bytes), None for the flat world, which
    reads no pack.

    Args:
        config: a :class:`fruxel.train.sim.config.SimConfig`.
    """
    if config.world != "home":
        return None
    from fruxel.train.sim.rooms.library import resolve_pack

    return hashlib.sha256((resolve_pack(config.assets) / "manifest.json").read_bytes()).hexdigest()


def samples_cache_path(source: Any, model: Any, split: str, count: int, *, camera: bool, device: str | None) -> Path:
    """Where :func:`cached_split_batches` keeps the ``count`` streamed samples of ``split``.

    Args:
        source: a streamed :class:`fruxel.train.samples.SampleSource`.
        model: the model's config (grid, image size and classes of the samples).
        split: e.g. ``"test"``.
        count: samples.
        camera: whether the camera records are kept too.
        device: the simulator's Warp device (None: CUDA when present).
    """
    from fruxel.io import cache_folder

    key = {**stream_key(source, model, ((split, count),)), "split": split, "count": count, "camera": camera,
           "device": _warp_device(device)}
    name = hashlib.sha256(json.dumps(key, sort_keys=True, default=str).encode()).hexdigest()[:32]
    return cache_folder() / "samples" / f"{name}.npz"


def _warp_device(device: str | None) -> str:
    """``"cpu"`` or ``"cuda"``: the kind of device the simulator's kernels run on."""
    if device is not None:
        return "cuda" if device.startswith("cuda") else "cpu"
    return "cuda" if torch.cuda.is_available() else "cpu"


def cached_split_batches(source: Any, model: Any, split: str, count: int, batch: int, *, workers: int = 0,
                         device: str | None = None, camera: bool = False) -> Iterator[tuple[Any, ...]]:
    """:func:`fruxel.train.samples.split_batches`, read from the cache when the same samples were streamed before
    and written to it when not (a data set or folder is read as it is: it is on disk already).

    Yields:
        ``(images (B, h, w, 3) uint8, labels (B, D, H, W) uint8[, camera])`` CPU tensors, as ``split_batches``.
    """
    from fruxel.train.samples import split_batches

    h, w = model.image_size
    size = count * (h * w * 3 + model.grid.depth * model.grid.height * model.grid.width)
    if source.source != "stream" or size > MAX_BYTES:
        yield from split_batches(source, model, split, count, batch, workers=workers, device=device, camera=camera)
        return
    path = samples_cache_path(source, model, split, count, camera=camera, device=device)
    cached = _read(path, count, (h, w), (model.grid.depth, model.grid.height, model.grid.width), camera)
    if cached is not None:
        for i in range(0, count, batch):
            yield tuple(_rows(part, i, i + batch) for part in cached)
        return
    kept: list[tuple[Any, ...]] = []
    for b in split_batches(source, model, split, count, batch, workers=workers, device=device, camera=camera):
        kept.append(b)
        yield b
    _write(path, kept, camera)


def _rows(part: Any, start: int, stop: int) -> Any:
    """Rows ``start:stop`` of a tensor, or of each tensor of a camera record."""
    return {k: v[start:stop] for k, v in part.items()} if isinstance(part, dict) else part[start:stop]


def _read(path: Path, count: int, image: tuple[int, int], grid: tuple[int, int, int],
          camera: bool) -> tuple[Any, ...] | None:
    """The cached ``(images, labels[, camera])`` at ``path`` as CPU tensors, or None (none there, unreadable, other
    shapes)."""
    try:
        with np.load(path, allow_pickle=False) as f:
            arrays = {k: f[k] for k in f.files}
    except (OSError, ValueError, KeyError, EOFError):
        return None
    images, labels = arrays.pop("images", None), arrays.pop("labels", None)
    if (images is None or labels is None or images.shape != (count, *image, 3) or labels.shape != (count, *grid)
            or images.dtype != np.uint8 or labels.dtype != np.uint8):
        return None
    record = {k[len("camera."):]: torch.from_numpy(v) for k, v in arrays.items() if k.startswith("camera.")}
    if camera and (not record or any(len(v) != count for v in record.values())):
        return None
    out = (torch.from_numpy(images), torch.from_numpy(labels))
    return (*out, record) if camera else out


def _write(path: Path, batches: list[tuple[Any, ...]], camera: bool) -> None:
    """Write the streamed ``batches`` to ``path`` atomically (a cache: a folder that cannot be written is left)."""
    from fruxel.io import atomic_path

    arrays = {"images": torch.cat([b[0] for b in batches]).numpy(),
              "labels": torch.cat([b[1] for b in batches]).numpy()}
    if camera:
        for k in batches[0][2]:
            arrays[f"camera.{k}"] = torch.cat([b[2][k] for b in batches]).numpy()
    try:
        path.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(path) as tmp:
            np.savez_compressed(tmp, **arrays)
    except OSError:
        pass

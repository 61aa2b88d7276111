"""Writing a simulator data set folder: the resumable, parallel generator behind ``fruxel-sim generate``.

:func:`generate` makes the shards (:mod:`.shards`) of every split with :class:`.sample.SampleMaker`, in this
process or in spawned workers, and records each finished shard in the manifest (:mod:`.manifest`). Writes are
atomic (:func:`fruxel.io.atomic_write`: temporary file beside the target, fsync, rename), so a killed run leaves
complete shards, a consistent manifest and temporary files that the next run deletes before it makes what is
missing.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import re
from collections.abc import Callable, Iterator
from typing import Any

from fruxel.io import atomic_write, file_sha256
from fruxel.kernels.wp.runtime import cuda_wait, set_cuda_wait

from .config import ConfigError, SimConfig
from .manifest import MANIFEST, Manifest
from .renderer import RENDERERS, register_renderer
from .sample import SampleMaker
from .shards import VERSION, DatasetError, ShardReader, ShardSpec, check_shard_sha256, encode_shard

# The temporary files fruxel.io.atomic_write leaves beside a shard or the manifest when a run is killed.
_SHARD_RE = re.compile(r"^\.([a-z0-9][a-z0-9_-]*-\d{5,}\.npz|manifest\.json)\.[0-9a-f]{12}\.tmp$")


def _make_shard(maker: SampleMaker, spec: ShardSpec, out: str, tick: Callable[[], None]) -> str:
    samples = []
    for i in spec.indices:
        samples.append(maker.make(spec.split, i))
        tick()
    data = encode_shard(spec, maker.config, maker.seed, samples)
    with atomic_write(os.path.join(out, spec.file)) as f:
        f.write(data)
    return hashlib.sha256(data).hexdigest()


_WORKER: dict[str, Any] = {}


def _worker_init(config: SimConfig, seed: int, backend: str | None, device: str | None, counter: Any,
                 renderer: Any) -> None:
    # The workers already fill the cores: one llvmpipe thread each avoids oversubscription (NVIDIA ignores it).
    os.environ.setdefault("LP_NUM_THREADS", "1")
    set_cuda_wait()  # how the worker waits for its GPU ($FRUXEL_CUDA_WAIT): the workers share the host's cores
    # A renderer registered at run time in the parent is not registered in a fresh spawned process.
    if config.renderer not in RENDERERS:
        register_renderer(config.renderer, renderer)
    _WORKER["maker"] = SampleMaker(config, seed, backend=backend, device=device)
    _WORKER["counter"] = counter


def _worker_tick() -> None:
    counter = _WORKER["counter"]
    with counter.get_lock():
        counter.value += 1


def _worker_shard(spec: ShardSpec, out: str) -> tuple[ShardSpec, str]:
    return spec, _make_shard(_WORKER["maker"], spec, out, _worker_tick)


def _check_existing(out: str, manifest: Manifest) -> list[ShardSpec]:
    """Shards still to make; records shards written after the last manifest update (a killed run)."""
    todo = []
    for spec in manifest.shards():
        path = os.path.join(out, spec.file)
        sha = manifest.hashes[spec.file]
        if os.path.lexists(path):
            if sha is not None:
                check_shard_sha256(path, sha, "delete it to have it remade")
                continue
            with ShardReader(path, spec, manifest.config, manifest.seed) as reader:
                reader.samples()
            manifest.hashes[spec.file] = file_sha256(path)
            continue
        manifest.hashes[spec.file] = None
        todo.append(spec)
    return todo


def _remove_temporaries(out: str) -> None:
    for name in os.listdir(out):
        if _SHARD_RE.match(name):
            with contextlib.suppress(OSError):
                os.remove(os.path.join(out, name))


def generate(
    out: str,
    config: SimConfig,
    seed: int,
    *,
    workers: int = 1,
    backend: str | None = "warp",
    device: str | None = None,
    progress: bool = True,
    callback: Callable[[int, int], None] | None = None,
) -> Manifest:
    """Make (or finish) a data set folder: shards plus manifest, deterministic per seed and resumable.

    A folder with a manifest must have been started with the same config and seed; its complete shards are
    checked against their SHA-256 and skipped, a shard written after the manifest's last update is checked in
    full and recorded, leftover temporary files are deleted, and the missing shards are made. The manifest is
    rewritten (atomically) after every finished shard.

    Args:
        out: the folder (created if missing).
        config: the generator settings.
        seed: the base seed, >= 0.
        workers: processes making shards in parallel (``spawn`` start method: each owns a renderer, e.g. an
            OpenGL context); 1 makes them in this process.
        backend, device: ``fruxelize`` backend and Warp device (see :class:`SampleMaker`).
        progress: show a tqdm progress bar (samples) on stderr.
        callback: called in this process as ``callback(done, total)`` (samples) whenever progress is shown, e.g.
            for logging or benchmarks.

    Returns:
        The final manifest.

    Raises:
        DatasetError: a folder made with other settings, a bad manifest, or a corrupt or foreign shard.
        ConfigError: bad settings.
        BackendError: an unknown ``$FRUXEL_CUDA_WAIT``.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"workers must be a positive integer, got {workers!r}")
    cuda_wait()  # an unknown $FRUXEL_CUDA_WAIT is refused here, not in each worker
    out = os.fsdecode(out)
    manifest, mpath = _open_folder(out, config, seed)
    _remove_temporaries(out)
    todo = _check_existing(out, manifest)
    manifest.complete = not todo
    manifest.save(mpath)
    total = sum(n for _, n in config.splits)

    def finished(spec: ShardSpec, sha: str) -> None:
        manifest.hashes[spec.file] = sha
        manifest.save(mpath)

    with _progress(total, total - sum(s.count for s in todo), progress, callback) as advance:
        if workers == 1 or len(todo) <= 1:
            with SampleMaker(config, seed, backend=backend, device=device) as maker:
                for spec in todo:
                    finished(spec, _make_shard(maker, spec, out, lambda: advance(1)))
        elif todo:
            _generate_parallel(todo, out, config, seed, workers, backend, device, advance, finished)
    manifest.complete = True
    manifest.save(mpath)
    return manifest


def _open_folder(out: str, config: SimConfig, seed: int) -> tuple[Manifest, str]:
    """The data set folder ``out`` (created if missing) and its manifest: the one there, which must record
    ``config`` and ``seed``, or a new one (not saved yet).

    Returns:
        ``(manifest, path of manifest.json)``.

    Raises:
        DatasetError: ``out`` is a file, a bad manifest, or one of other settings (the message names them).
    """
    if os.path.exists(out) and not os.path.isdir(out):
        raise DatasetError(out, "the output exists and is not a folder")
    os.makedirs(out, exist_ok=True)
    mpath = os.path.join(out, MANIFEST)
    if not os.path.exists(mpath):
        return Manifest(config, seed), mpath
    manifest = Manifest.load(mpath)
    if manifest.version != VERSION:
        raise DatasetError(mpath, f"this folder holds a data set of format version {manifest.version}, made by an "
                                  f"older fruxel; it stays readable, but new shards (version {VERSION}) are not added "
                                  "to it: use another --out")
    if manifest.config.digest() != config.digest() or manifest.seed != seed:
        ours, theirs = config.to_dict(), manifest.config.to_dict()
        diff = [k for k in dict.fromkeys([*ours, *theirs]) if ours.get(k) != theirs.get(k)]
        if manifest.seed != seed:
            diff.append("seed")
        raise DatasetError(mpath, f"this folder holds a data set made with other settings (differs in: "
                                  f"{', '.join(diff)}); use another --out, or delete the folder to start over")
    return manifest, mpath


@contextlib.contextmanager
def _progress(total: int, done: int, show: bool, callback: Callable[[int, int], None] | None
              ) -> Iterator[Callable[[int], None]]:
    """A tqdm bar of ``total`` samples starting at ``done`` (hidden unless ``show``); yields ``advance(n)``,
    which moves it on by ``n`` samples and calls ``callback(done, total)`` when n > 0."""
    from tqdm import tqdm

    with tqdm(total=total, initial=done, unit="sample", desc="fruxel-sim generate", disable=not show,
              dynamic_ncols=True, smoothing=0.1) as bar:
        counted = [done]

        def advance(n: int) -> None:
            bar.update(n)
            counted[0] += n
            if callback is not None and n:
                callback(counted[0], total)

        yield advance


def _generate_parallel(todo: list[ShardSpec], out: str, config: SimConfig, seed: int, workers: int,
                       backend: str | None, device: str | None, advance: Callable[[int], None],
                       finished: Callable[[ShardSpec, str], None]) -> None:
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = mp.get_context("spawn")
    counter = ctx.Value("q", 0)
    shown = 0
    ex = ProcessPoolExecutor(max_workers=min(workers, len(todo)), mp_context=ctx, initializer=_worker_init,
                             initargs=(config, seed, backend, device, counter, RENDERERS[config.renderer]))
    try:
        pending = {ex.submit(_worker_shard, spec, out) for spec in todo}
        while pending:
            done, pending = wait(pending, timeout=0.25, return_when=FIRST_COMPLETED)
            value = counter.value
            advance(value - shown)
            shown = value
            for fut in done:
                finished(*fut.result())
    except BaseException:
        # Stop the shards in flight too: their results would be thrown away, and a worker stuck on a broken
        # room would otherwise keep the interpreter from exiting.
        procs = list(getattr(ex, "_processes", {}).values())
        ex.shutdown(wait=False, cancel_futures=True)
        for p in procs:
            if p.is_alive():
                p.terminate()
        raise
    ex.shutdown(wait=True)

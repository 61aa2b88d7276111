"""Samples of the simulator and their files: making sample ``i``, shard files, the manifest, and the resumable
parallel generator behind ``fruxel-sim generate``.

Sample
    One robot camera view (:class:`Sample`): the RGB image, the ground-truth labels of the grid aligned with that
    camera, the grid's own-view depth and label images, the camera pose and where the sample came from. Sample
    ``i`` of a split is a pure function of the config, the base seed, the split and ``i`` (seed rule in
    :mod:`.config`); :class:`SampleMaker` computes it, reusing the room, its robot trajectory, its uploaded
    meshes and the renderer for consecutive samples of one room.

Data set folder (format version 1)
    ``manifest.json``, and per split ``ceil(samples / shard_size)`` shards ``{split}-{n:05d}.npz``; shard ``n``
    holds samples ``n * shard_size ..`` of its split (the last one fewer). The manifest is a JSON object::

        {"format": "fruxel-sim", "version": 1, "complete": bool, "seed": int, "config_sha256": hex,
         "grid": FruxelGrid.to_dict(), "classes": ClassTable.to_dict(),
         "image": {"width": S, "height": S * H / W},
         "intrinsics": {"image": {fx, fy, cx, cy, width, height}, "grid": {...the grid's own camera...}},
         "seeds": "the seed rule in words", "samples_per_scene": n, "shard_size": N,
         "splits": {name: {"samples": int, "shards": [{"file", "start", "count", "sha256": hex or null}]}},
         "config": SimConfig.to_dict()}

    ``sha256`` is the SHA-256 of a complete shard file, null until the shard is written.

Shard file
    An ``.npz`` (zip) read without pickle. Member ``meta`` is a 0-d unicode JSON string
    ``{"format": "fruxel-sim-shard", "version": 1, "config_sha256", "seed", "split", "shard", "start", "count",
    "samples": [{"index", "scene", "frame", "scene_seed"}, ...]}``; sample ``j`` (``0 <= j < count``, index
    ``start + j``) is stored as the members ``image_{j:05d}`` ``(S * H / W, S, 3)`` uint8 RGB,
    ``labels_{j:05d}`` ``(D, H, W)`` uint8, ``view_depth_{j:05d}`` ``(H, W)`` float32 metres,
    ``view_label_{j:05d}`` ``(H, W)`` uint8 and ``pose_{j:05d}`` ``(4, 4)`` float64 camera-to-world (world frame
    z up, OpenCV camera axes). One member per sample and field lets a map-style data set read one sample without
    inflating the whole shard. Members are deflate-compressed with fixed zip timestamps, so the same samples
    give the same file bytes (with the same zlib). The samples themselves are bit-identical for the same config
    and seed on the same machine, OpenGL driver and library versions (what the tests check); images made with
    another driver (llvmpipe here, NVIDIA on a GPU machine) can differ in the last bits of some pixels, and poses
    computed by another numpy build in the last bits of some entries.

Writes are atomic (:func:`fruxel.io.atomic_write`: temporary file beside the target, fsync, rename). Reads are
strict: the file's SHA-256 must match the manifest, the members must be exactly the expected ones, and every npy
header is checked (dtype, shape, size) before any data is read (:func:`fruxel.io.read_npy_member`); any problem
raises one :class:`DatasetError` naming the file.
"""

from __future__ import annotations

import contextlib
import hashlib
import io
import json
import math
import os
import re
import time
import zipfile
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass, field
from typing import IO, Any

import numpy as np
import numpy.lib.format as npy_format

from fruxel.errors import FruxelError
from fruxel.io import (
    ArchiveError,
    atomic_write,
    describe_read_error,
    open_archive,
    read_json_member,
    read_npy_member,
)

from .config import ConfigError, SimConfig, augment_rng, scene_seed, trajectory_seed

FORMAT = "fruxel-sim"
"""``format`` of a data set manifest."""
SHARD_FORMAT = "fruxel-sim-shard"
"""``format`` in a shard's meta."""
VERSION = 1
"""Version of the manifest and shard layout."""
MANIFEST = "manifest.json"
"""File name of the manifest in a data set folder."""
COMPRESS_LEVEL = 1
"""zlib level of the shard members: label volumes are mostly runs that level 1 already packs tightly, and images
barely compress at any level, while higher levels cost several times the time (measured in bench_sim.py)."""
MAX_ROOM_ATTEMPTS = 16
"""Rooms tried for one scene index before giving up, when the robot finds no free floor (see the seed rule)."""
MAX_META_CHARS = 1 << 24
"""Longest shard meta JSON accepted, in characters."""

FIELDS = ("image", "labels", "view_depth", "view_label", "pose")
"""Per-sample members of a shard, in file order."""

SEED_RULE = (
    "sample i of split s (k = crc32(s), n = samples_per_scene): scene c = i // n, frame f = i % n; "
    "room = make_scene(SeedSequence([seed, k, c, 0]).generate_state(2, uint32) as uint64); "
    "trajectory = random_trajectory(room, n, seed from SeedSequence([seed, k, c, 1])); "
    "augmentation rng = default_rng(SeedSequence([seed, k, i, 2])); a room without free floor is replaced by "
    "attempt a = 1, 2, ..., with a appended to the first two sequences"
)
"""The seed rule in words, recorded in every manifest (the code is in :mod:`.config`)."""

# The temporary files fruxel.io.atomic_write leaves beside a shard or the manifest when a run is killed.
_SHARD_RE = re.compile(r"^\.([a-z0-9][a-z0-9_-]*-\d{5,}\.npz|manifest\.json)\.[0-9a-f]{12}\.tmp$")


class DatasetError(FruxelError, ValueError):
    """A data set file that cannot be used: a corrupt or foreign shard, a bad manifest, a folder made with other
    settings, or an incomplete data set. The message names the file and the problem; :attr:`path` and
    :attr:`problem` hold them."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        """The file (or folder) concerned."""
        self.problem = problem
        """What is wrong, in words."""

    def __reduce__(self) -> tuple[Any, ...]:
        # Errors raised in generator workers cross back to the parent by pickle.
        return (type(self), (self.path, self.problem))


# ---------------------------------------------------------------------------------------------------- samples
@dataclass(frozen=True, eq=False)
class Sample:
    """One training sample: a robot camera image and the ground truth of the grid aligned with it."""

    split: str
    """Name of the split the sample belongs to."""
    index: int
    """Index of the sample in its split."""
    scene: int
    """Room index in the split, ``index // samples_per_scene``."""
    frame: int
    """Frame of the room's robot trajectory, ``index % samples_per_scene``."""
    scene_seed: int
    """The seed the room was made from (``make_scene(scene_seed, config.room)``)."""
    image: np.ndarray
    """``(S * H / W, S, 3)`` uint8 RGB image of the robot camera."""
    labels: np.ndarray
    """``(D, H, W)`` uint8 ground-truth labels of the grid (0 = empty), indexed ``[k, j, i]``."""
    view_depth: np.ndarray
    """``(H, W)`` float32 depth (metres along the camera's z) of each column's first occupied cell, 0 = none."""
    view_label: np.ndarray
    """``(H, W)`` uint8 label of each column's first occupied cell, 0 = none."""
    pose: np.ndarray
    """``(4, 4)`` float64 camera-to-world transform of the robot camera (= the grid's pose), world frame z up,
    OpenCV camera axes."""

    def arrays(self) -> dict[str, np.ndarray]:
        """The five arrays keyed by :data:`FIELDS`."""
        return {name: getattr(self, name) for name in FIELDS}


def field_specs(config: SimConfig) -> dict[str, tuple[np.dtype, tuple[int, ...]]]:
    """dtype and shape of every per-sample member for ``config``."""
    g = config.grid
    return {
        "image": (np.dtype(np.uint8), (config.image_height, config.image_width, 3)),
        "labels": (np.dtype(np.uint8), g.shape),
        "view_depth": (np.dtype(np.float32), (g.height, g.width)),
        "view_label": (np.dtype(np.uint8), (g.height, g.width)),
        "pose": (np.dtype(np.float64), (4, 4)),
    }


@dataclass
class _Room:
    """One room with its trajectory and uploaded meshes, kept while consecutive samples use it."""

    key: tuple[str, int]
    """``(split, scene index)``."""
    scene: Any
    """The :class:`fruxel.train.sim.scene.Scene`."""
    poses: np.ndarray
    """``(samples_per_scene, 4, 4)`` float64 camera-to-world poses of the robot trajectory, world frame z up,
    OpenCV camera axes."""
    mesh_set: Any
    """The room's solids uploaded for ``fruxelize`` (:class:`fruxel.kernels.fruxelize.MeshSet`)."""
    seed: int
    """The seed the room was made from."""


STAGES = ("scene", "trajectory", "upload", "render", "fruxelize", "own_view")
"""Stages :class:`SampleMaker` times (seconds accumulate in ``SampleMaker.timings``)."""


class SampleMaker:
    """Computes samples from ``(config, seed, split, index)``; one per process (it owns an OpenGL context).

    Consecutive indices of one room reuse the room, its trajectory, the meshes uploaded for ``fruxelize`` and the
    renderer's scene, so asking for samples in index order is fastest.

    Args:
        config: the generator settings.
        seed: the base seed, >= 0.
        backend: ``fruxelize`` backend (``"warp"``, ``"warp-cpu"``, ``"warp-cuda"``); results do not depend on it.
        device: Warp device, or None (CUDA when present, else the CPU).
    """

    def __init__(self, config: SimConfig, seed: int, *, backend: str | None = "warp",
                 device: str | None = None) -> None:
        self.config = config
        """The generator settings."""
        self.seed = int(seed)
        """The base seed."""
        self.backend = backend
        """The ``fruxelize`` backend."""
        self.device = device
        """The Warp device, or None."""
        self.timings: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        """Seconds spent per stage of :data:`STAGES` since construction (for profiling)."""
        self._room: _Room | None = None
        self._renderer: Any = None

    def _load_room(self, split: str, scene: int) -> _Room:
        if self._room is not None and self._room.key == (split, scene):
            return self._room

        from .robot import TrajectoryError, random_trajectory
        from .scene import make_scene

        cfg = self.config
        for attempt in range(MAX_ROOM_ATTEMPTS):
            t0 = time.perf_counter()
            s_seed = scene_seed(self.seed, split, scene, attempt)
            room = make_scene(s_seed, cfg.room)
            t1 = time.perf_counter()
            self.timings["scene"] += t1 - t0
            try:
                traj = random_trajectory(room, cfg.samples_per_scene, trajectory_seed(self.seed, split, scene, attempt),
                                         **cfg.trajectory.kwargs())
            except TrajectoryError:
                self.timings["trajectory"] += time.perf_counter() - t1
                continue
            t2 = time.perf_counter()
            self.timings["trajectory"] += t2 - t1
            self._room = None
            mesh_set = room.mesh_set(backend=self.backend, device=self.device)
            self.timings["upload"] += time.perf_counter() - t2
            self._room = _Room((split, scene), room, np.asarray(traj.poses, dtype=np.float64), mesh_set, s_seed)
            return self._room
        raise RuntimeError(f"split {split!r} scene {scene}: no room among {MAX_ROOM_ATTEMPTS} attempts had free "
                           "floor for the robot; loosen config.room or config.trajectory")

    def make(self, split: str, index: int) -> Sample:
        """Sample ``index`` of ``split``.

        Raises:
            ConfigError: an unknown split or an index outside it.
        """
        from fruxel.kernels.fruxelize import fruxelize, own_view_truth

        n = self.config.split_samples(split)
        if isinstance(index, bool) or not isinstance(index, (int, np.integer)) or not 0 <= index < n:
            raise ConfigError(f"sample index {index!r} is outside split {split!r} of {n} samples")
        index = int(index)
        scene, frame = divmod(index, self.config.samples_per_scene)
        room = self._load_room(split, scene)
        pose = room.poses[frame]
        t0 = time.perf_counter()
        if self._renderer is None:
            from .images import SceneRenderer

            self._renderer = SceneRenderer(self.config)
        self._renderer.set_scene(room.scene)
        image = self._renderer.render(pose, augment_rng(self.seed, split, index))
        t1 = time.perf_counter()
        labels = np.ascontiguousarray(fruxelize(room.mesh_set, self.config.grid, pose, backend=self.backend),
                                      dtype=np.uint8)
        t2 = time.perf_counter()
        depth, label = own_view_truth(labels, self.config.grid)
        t3 = time.perf_counter()
        self.timings["render"] += t1 - t0
        self.timings["fruxelize"] += t2 - t1
        self.timings["own_view"] += t3 - t2
        return Sample(split, index, scene, frame, room.seed, image, labels, depth.astype(np.float32),
                      label.astype(np.uint8), pose.copy())

    def close(self) -> None:
        """Free the renderer's OpenGL context and the current room (idempotent)."""
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        self._room = None

    def __enter__(self) -> SampleMaker:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------------- layout
@dataclass(frozen=True)
class ShardSpec:
    """Where one shard sits in its split."""

    split: str
    """Split name."""
    number: int
    """Shard number n within the split."""
    start: int
    """Index of the shard's first sample in the split."""
    count: int
    """Number of samples in the shard."""

    @property
    def file(self) -> str:
        """File name, ``{split}-{n:05d}.npz``."""
        return f"{self.split}-{self.number:05d}.npz"

    @property
    def indices(self) -> range:
        """Sample indices of the shard."""
        return range(self.start, self.start + self.count)


def shard_specs(config: SimConfig) -> list[ShardSpec]:
    """All shards of a data set, split by split in ``config.splits`` order."""
    out = []
    for split, n in config.splits:
        for k in range(math.ceil(n / config.shard_size)):
            start = k * config.shard_size
            out.append(ShardSpec(split, k, start, min(config.shard_size, n - start)))
    return out


# ---------------------------------------------------------------------------------------------------- writing
def _put(zf: zipfile.ZipFile, key: str, array: np.ndarray) -> None:
    buf = io.BytesIO()
    # np.require keeps a 0-d array 0-d (np.ascontiguousarray would make it 1-d).
    npy_format.write_array(buf, np.require(array, requirements="C"), allow_pickle=False)
    # A fixed timestamp and attributes make the archive a function of its contents alone.
    info = zipfile.ZipInfo(f"{key}.npy", date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_DEFLATED
    info.external_attr = 0o644 << 16
    zf.writestr(info, buf.getvalue(), compresslevel=COMPRESS_LEVEL)


def _shard_meta(spec: ShardSpec, config: SimConfig, seed: int, samples: Sequence[Sample]) -> dict[str, Any]:
    return {
        "format": SHARD_FORMAT, "version": VERSION, "config_sha256": config.digest(), "seed": int(seed),
        "split": spec.split, "shard": spec.number, "start": spec.start, "count": spec.count,
        "samples": [{"index": s.index, "scene": s.scene, "frame": s.frame, "scene_seed": s.scene_seed}
                    for s in samples],
    }


def encode_shard(spec: ShardSpec, config: SimConfig, seed: int, samples: Sequence[Sample]) -> bytes:
    """The bytes of a shard file (layout in the module docstring).

    Raises:
        ValueError: samples that are not exactly the shard's, or arrays of the wrong dtype or shape.
    """
    if [s.index for s in samples] != list(spec.indices) or any(s.split != spec.split for s in samples):
        raise ValueError(f"shard {spec.file} needs samples {spec.start}..{spec.start + spec.count - 1} of "
                         f"{spec.split!r}")
    specs = field_specs(config)
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", allowZip64=True) as zf:
        _put(zf, "meta", np.array(json.dumps(_shard_meta(spec, config, seed, samples)), dtype=np.str_))
        for j, s in enumerate(samples):
            for name in FIELDS:
                a = getattr(s, name)
                dtype, shape = specs[name]
                if a.dtype != dtype or a.shape != shape:
                    raise ValueError(f"sample {s.index} {name}: expected {shape} {dtype}, got {a.shape} {a.dtype}")
                _put(zf, f"{name}_{j:05d}", a)
    return buf.getvalue()


def file_sha256(path: str) -> str:
    """SHA-256 (hex) of a file's bytes."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


# ---------------------------------------------------------------------------------------------------- reading
@contextlib.contextmanager
def _reading(path: str) -> Iterator[None]:
    """Turn every failure inside into one :class:`DatasetError` for ``path``, with no chained traceback."""
    try:
        yield
        return
    except DatasetError:
        raise
    except Exception as e:
        problem = describe_read_error(e)
    raise DatasetError(path, f"corrupt or foreign shard: {problem}") from None


def check_shard_sha256(path: str, sha256: str, advice: str) -> None:
    """Compare the shard at ``path`` with the manifest's SHA-256.

    Raises:
        DatasetError: the digests differ (``advice`` says what to do), or the file cannot be read.
    """
    with _reading(path):
        actual = file_sha256(path)
    if actual != sha256:
        raise DatasetError(path, "corrupt or foreign shard: its SHA-256 differs from the manifest's (the file was "
                                 f"damaged, truncated or replaced); {advice}")


class ShardReader:
    """Strict reader of one shard file; samples are read one at a time.

    Opening checks the SHA-256 (when given), the member names and the meta; :meth:`sample` checks each member's
    npy header before reading its data. Not shareable across processes: open one per process.

    Args:
        path: the shard file.
        spec: which shard it must be.
        config: the data set's settings (dtypes and shapes, the config digest).
        seed: the data set's base seed.
        sha256: the expected SHA-256 (hex) from the manifest, or None to skip the check.

    Raises:
        DatasetError: a missing, unreadable, corrupt or foreign file (the message names it).
    """

    def __init__(self, path: str, spec: ShardSpec, config: SimConfig, seed: int, sha256: str | None = None) -> None:
        self.path = os.fsdecode(path)
        """The shard file."""
        self.spec = spec
        """The shard's place in its split."""
        self.config = config
        """The data set's settings."""
        self._specs = field_specs(config)
        self._file: IO[bytes] | None = None
        self._zip: zipfile.ZipFile | None = None
        self.meta: dict[str, Any] = {}
        """The shard's meta JSON."""
        if not os.path.isfile(self.path):
            raise DatasetError(self.path, "missing shard (no such file)" if not os.path.exists(self.path)
                               else "not a regular file")
        if sha256 is not None:
            check_shard_sha256(self.path, sha256, "delete it and run fruxel-sim generate again to remake it")
        try:
            with _reading(self.path):
                self._open(seed)
        except BaseException:
            self.close()
            raise

    def _open(self, seed: int) -> None:
        self._file = open(self.path, "rb")
        self._zip = open_archive(self._file)
        names = self._zip.namelist()
        expected = ["meta.npy"] + [f"{n}_{j:05d}.npy" for j in range(self.spec.count) for n in FIELDS]
        if len(names) != len(set(names)) or set(names) != set(expected):
            missing = sorted(set(expected) - set(names))[:4]
            extra = sorted(set(names) - set(expected))[:4]
            raise ArchiveError(f"wrong members (missing {missing}, unexpected {extra}; "
                               f"{len(names)} members, expected {len(expected)})")
        self.meta = self._read_meta()
        want = _shard_meta(self.spec, self.config, seed, [])
        for key in ("format", "version", "config_sha256", "seed", "split", "shard", "start", "count"):
            if self.meta.get(key) != want[key]:
                raise ArchiveError(f"meta {key} is {self.meta.get(key)!r}, expected {want[key]!r} (a shard of another "
                                   "data set, split or version)")
        entries = self.meta.get("samples")
        sps = self.config.samples_per_scene
        if not isinstance(entries, list) or len(entries) != self.spec.count:
            raise ArchiveError("meta 'samples' must list one entry per sample")
        for j, e in enumerate(entries):
            index = self.spec.start + j
            ok = isinstance(e, dict) and sorted(e) == ["frame", "index", "scene", "scene_seed"] and all(
                isinstance(v, int) and not isinstance(v, bool) for v in e.values())
            if not ok or (e["index"], e["scene"], e["frame"]) != (index, *divmod(index, sps)):
                raise ArchiveError(f"meta entry {j} does not describe sample {index}")

    def _read_meta(self) -> dict[str, Any]:
        assert self._zip is not None
        meta = read_json_member(self._zip, "meta", MAX_META_CHARS)
        if not isinstance(meta, dict):
            raise ArchiveError("meta must be a JSON object")
        return meta

    def sample(self, j: int) -> Sample:
        """Sample ``j`` of the shard (index ``start + j``).

        Raises:
            IndexError: ``j`` outside the shard. DatasetError: a damaged member.
        """
        if not 0 <= j < self.spec.count:
            raise IndexError(f"shard {self.spec.file} has {self.spec.count} samples, asked for {j}")
        if self._zip is None:
            raise DatasetError(self.path, "shard reader is closed")
        arrays = {}
        with _reading(self.path):
            for name in FIELDS:
                dtype, shape = self._specs[name]
                arrays[name] = read_npy_member(self._zip, f"{name}_{j:05d}.npy", dtype, shape)
            n_classes = len(self.config.classes)
            for name in ("labels", "view_label"):
                if arrays[name].size and int(arrays[name].max()) >= n_classes:
                    raise ArchiveError(f"member '{name}_{j:05d}' has labels outside the {n_classes} classes")
            if not np.all(np.isfinite(arrays["view_depth"])) or not np.all(np.isfinite(arrays["pose"])):
                raise ArchiveError(f"sample {j} has non-finite depth or pose values")
        e = self.meta["samples"][j]
        return Sample(self.spec.split, e["index"], e["scene"], e["frame"], e["scene_seed"], **arrays)

    def samples(self) -> list[Sample]:
        """Every sample of the shard, in order."""
        return [self.sample(j) for j in range(self.spec.count)]

    def close(self) -> None:
        """Close the file (idempotent)."""
        if self._zip is not None:
            self._zip.close()
            self._zip = None
        if self._file is not None:
            self._file.close()
            self._file = None

    def __enter__(self) -> ShardReader:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


# ---------------------------------------------------------------------------------------------------- manifest
@dataclass
class Manifest:
    """The index of a data set folder (JSON layout in the module docstring)."""

    config: SimConfig
    """The settings every sample was made with."""
    seed: int
    """The base seed."""
    hashes: dict[str, str | None] = field(default_factory=dict)
    """SHA-256 (hex) of each complete shard by file name; None for shards not written yet."""
    complete: bool = False
    """True once every shard is written and recorded."""

    def __post_init__(self) -> None:
        for spec in shard_specs(self.config):
            self.hashes.setdefault(spec.file, None)

    def shards(self, split: str | None = None) -> list[ShardSpec]:
        """The shards of one split, or of all splits in order."""
        return [s for s in shard_specs(self.config) if split is None or s.split == split]

    def to_dict(self) -> dict[str, Any]:
        """The manifest as a plain JSON object."""
        cfg = self.config
        grid_cam = cfg.grid.camera()
        img_cam = cfg.image_camera()

        def intr(c: Any) -> dict[str, Any]:
            return {"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height}

        return {
            "format": FORMAT,
            "version": VERSION,
            "complete": bool(self.complete),
            "seed": int(self.seed),
            "config_sha256": cfg.digest(),
            "grid": cfg.grid.to_dict(),
            "classes": cfg.classes.to_dict(),
            "image": {"width": cfg.image_width, "height": cfg.image_height},
            "intrinsics": {"image": intr(img_cam), "grid": intr(grid_cam)},
            "seeds": SEED_RULE,
            "samples_per_scene": cfg.samples_per_scene,
            "shard_size": cfg.shard_size,
            "splits": {
                split: {"samples": n, "shards": [
                    {"file": s.file, "start": s.start, "count": s.count, "sha256": self.hashes[s.file]}
                    for s in self.shards(split)]}
                for split, n in cfg.splits
            },
            "config": cfg.to_dict(),
        }

    def to_json(self) -> str:
        """The manifest's JSON text (stable: the same manifest gives the same text)."""
        return json.dumps(self.to_dict(), indent=1) + "\n"

    def save(self, path: str) -> None:
        """Write the manifest atomically."""
        with atomic_write(path) as f:
            f.write(self.to_json().encode("utf-8"))

    @classmethod
    def load(cls, path: str) -> Manifest:
        """Read and check a manifest: every field must be what its config and seed imply.

        Raises:
            DatasetError: a missing, unreadable or malformed manifest, another format or version, or fields that
                contradict its config (the message names the file).
        """
        path = os.fsdecode(path)
        try:
            with open(path, "rb") as f:
                raw = f.read(64 << 20)
        except FileNotFoundError:
            raise DatasetError(path, "no data set manifest here (no such file)") from None
        except OSError as e:
            raise DatasetError(path, f"cannot read the manifest ({e.strerror or e})") from None
        try:
            d = json.loads(raw.decode("utf-8"))
        except (UnicodeDecodeError, ValueError) as e:
            raise DatasetError(path, f"manifest is not valid JSON ({e})") from None
        if not isinstance(d, dict) or d.get("format") != FORMAT:
            fmt = d.get("format") if isinstance(d, dict) else None
            raise DatasetError(path, f"not a fruxel-sim manifest (format {fmt!r})")
        if d.get("version") != VERSION:
            raise DatasetError(path, f"manifest version {d.get('version')!r}; this fruxel reads version {VERSION}")
        try:
            config = SimConfig.from_dict(d.get("config"))
        except ConfigError as e:
            raise DatasetError(path, f"manifest has an invalid config: {e}") from None
        seed = d.get("seed")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise DatasetError(path, f"manifest seed must be a non-negative integer, got {seed!r}")
        out = cls(config, seed)
        try:
            for split, _ in config.splits:
                for entry in d["splits"][split]["shards"]:
                    sha = entry["sha256"]
                    if entry["file"] not in out.hashes:
                        raise DatasetError(path, f"manifest lists an unexpected shard {entry['file']!r}")
                    if sha is not None and not (isinstance(sha, str) and re.fullmatch(r"[0-9a-f]{64}", sha)):
                        raise DatasetError(path, f"manifest has a malformed sha256 for {entry['file']!r}")
                    out.hashes[entry["file"]] = sha
        except (KeyError, TypeError):
            raise DatasetError(path, "manifest 'splits' is malformed") from None
        out.complete = d.get("complete") is True
        expected = json.loads(out.to_json())
        expected["complete"] = d.get("complete")
        if d != expected:
            diff = sorted(k for k in set(d) | set(expected) if d.get(k) != expected.get(k))
            raise DatasetError(path, f"manifest fields contradict its config and seed: {diff}")
        if out.complete and any(v is None for v in out.hashes.values()):
            raise DatasetError(path, "manifest says complete but some shards have no sha256")
        return out


# ---------------------------------------------------------------------------------------------------- generate
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


def _worker_init(config: SimConfig, seed: int, backend: str | None, device: str | None, counter: Any) -> None:
    # The workers already fill the cores: one llvmpipe thread each avoids oversubscription (NVIDIA ignores it).
    os.environ.setdefault("LP_NUM_THREADS", "1")
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
        workers: processes making shards in parallel (``spawn`` start method: each owns an OpenGL context); 1
            makes them in this process.
        backend, device: ``fruxelize`` backend and Warp device (see :class:`SampleMaker`).
        progress: show a tqdm progress bar (samples) on stderr.
        callback: called in this process as ``callback(done, total)`` (samples) whenever progress is shown, e.g.
            for logging or benchmarks.

    Returns:
        The final manifest.

    Raises:
        DatasetError: a folder made with other settings, a bad manifest, or a corrupt or foreign shard.
        ConfigError: bad settings.
    """
    if isinstance(workers, bool) or not isinstance(workers, int) or workers < 1:
        raise ConfigError(f"workers must be a positive integer, got {workers!r}")
    out = os.fsdecode(out)
    if os.path.exists(out) and not os.path.isdir(out):
        raise DatasetError(out, "the output exists and is not a folder")
    os.makedirs(out, exist_ok=True)
    mpath = os.path.join(out, MANIFEST)
    if os.path.exists(mpath):
        manifest = Manifest.load(mpath)
        if manifest.config.digest() != config.digest() or manifest.seed != seed:
            diff = [k for k, v in config.to_dict().items() if manifest.config.to_dict()[k] != v]
            if manifest.seed != seed:
                diff.append("seed")
            raise DatasetError(mpath, f"this folder holds a data set made with other settings (differs in: "
                                      f"{', '.join(diff)}); use another --out, or delete the folder to start over")
    else:
        manifest = Manifest(config, seed)
    _remove_temporaries(out)
    todo = _check_existing(out, manifest)
    manifest.complete = not todo
    manifest.save(mpath)
    total = sum(n for _, n in config.splits)
    done = total - sum(s.count for s in todo)

    from tqdm import tqdm

    with tqdm(total=total, initial=done, unit="sample", desc="fruxel-sim generate", disable=not progress,
              dynamic_ncols=True, smoothing=0.1) as bar:
        counted = [done]

        def advance(n: int) -> None:
            bar.update(n)
            counted[0] += n
            if callback is not None and n:
                callback(counted[0], total)

        def finished(spec: ShardSpec, sha: str) -> None:
            manifest.hashes[spec.file] = sha
            manifest.save(mpath)

        if workers == 1 or len(todo) <= 1:
            with SampleMaker(config, seed, backend=backend, device=device) as maker:
                for spec in todo:
                    finished(spec, _make_shard(maker, spec, out, lambda: advance(1)))
        elif todo:
            _generate_parallel(todo, out, config, seed, workers, backend, device, advance, finished)
    manifest.complete = True
    manifest.save(mpath)
    return manifest


def _generate_parallel(todo: list[ShardSpec], out: str, config: SimConfig, seed: int, workers: int,
                       backend: str | None, device: str | None, advance: Callable[[int], None],
                       finished: Callable[[ShardSpec, str], None]) -> None:
    import multiprocessing as mp
    from concurrent.futures import FIRST_COMPLETED, ProcessPoolExecutor, wait

    ctx = mp.get_context("spawn")
    counter = ctx.Value("q", 0)
    shown = 0
    ex = ProcessPoolExecutor(max_workers=min(workers, len(todo)), mp_context=ctx, initializer=_worker_init,
                             initargs=(config, seed, backend, device, counter))
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

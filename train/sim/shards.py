"""Shard files of a simulator data set: where each shard sits in its split, the file format, and the strict reader.

Shard file
    An ``.npz`` (zip) read without pickle. Member ``meta`` is a 0-d unicode JSON string
    ``{"format": "fruxel-sim-shard", "version": 3, "config_sha256", "seed", "split", "shard", "start", "count",
    "samples": [{"index", "scene", "frame", "scene_seed", "camera"}, ...]}``, where ``camera`` is the sample's
    camera record (:meth:`.cameras.CameraRecord.to_dict`: ``intrinsics`` ``[fx, fy, cx, cy]`` and ``image_size``
    ``[width, height]`` of the rendered camera, ``height`` above the floor in metres, ``gravity`` ``[x, y, z]`` in
    the camera frame, ``pitch``, ``roll`` and ``hfov`` in degrees; JSON floats round-trip exactly). Sample ``j``
    (``0 <= j < count``, index ``start + j``) is stored as the members ``image_{j:05d}`` ``(S * H / W, S, 3)``
    uint8 RGB, ``labels_{j:05d}`` ``(D, H, W)`` uint8 and ``pose_{j:05d}`` ``(4, 4)`` float64 camera-to-world
    (world frame z up, OpenCV camera axes). One member per sample and field lets a map-style data set read one
    sample without inflating the whole shard. The grid columns the image covers are not stored: they follow from
    the record and the config (:func:`.cameras.coverage`), and are computed when a sample is read. Members are
    deflate-compressed with fixed zip timestamps, so the same samples give the same file bytes (with the same
    zlib). The samples themselves are bit-identical for the same config and seed on the same machine, OpenGL
    driver and library versions (what the tests check); images made with another driver (llvmpipe here, NVIDIA on
    a GPU machine) can differ in the last bits of some pixels, and poses computed by another numpy build in the
    last bits of some entries.

Version 2 (data sets made before cameras varied) is the same without ``camera``; its samples were all taken by
the robot's own mount, and are read with the record that mount gives (:func:`.cameras.robot_mount`), exactly what
this version records for it.

The data set folder that holds the shards, and its manifest, are described in :mod:`.manifest`. Reads are
strict: the file's SHA-256 must match the manifest, the members must be exactly the expected ones, and every npy
header is checked (dtype, shape, size) before any data is read (:func:`fruxel.io.read_npy_member`); any problem
raises one :class:`DatasetError` naming the file.
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import os
import zipfile
from collections.abc import Iterator, Sequence
from dataclasses import dataclass
from typing import IO, Any

import numpy as np
import numpy.lib.format as npy_format

from fruxel.errors import FruxelError
from fruxel.io import (
    ArchiveError,
    describe_read_error,
    file_sha256,
    open_archive,
    read_json_member,
    read_npy_member,
)

from . import cameras
from .cameras import ROBOT_CAMERA, CameraRecord
from .config import SimConfig
from .sample import FIELDS, Sample, field_specs

SHARD_FORMAT = "fruxel-sim-shard"
"""``format`` in a shard's meta."""
VERSION = 3
"""Version of the manifest and shard layout, written. Version 3 added each sample's camera record; version 1 also
stored each sample's own-view depth and label images (``view_depth_*``, ``view_label_*``), which are now
``first_hit`` of the labels (see :mod:`.sample`)."""
READ_VERSIONS = (2, 3)
"""Versions read (version 2 as the robot's mount, module docstring)."""
COMPRESS_LEVEL = 1
"""zlib level of the shard members: label volumes are mostly runs that level 1 already packs tightly, and images
barely compress at any level, while higher levels take longer (the ``encode`` stage of the simulator's profile,
``benchmarks/bench_sim.py``, results in BENCHMARKS.md)."""
MAX_META_CHARS = 1 << 24
"""Longest shard meta JSON accepted, in characters."""


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


def _shard_meta(spec: ShardSpec, config: SimConfig, seed: int, samples: Sequence[Sample], version: int = VERSION
                ) -> dict[str, Any]:
    return {
        "format": SHARD_FORMAT, "version": version, "config_sha256": config.digest(), "seed": int(seed),
        "split": spec.split, "shard": spec.number, "start": spec.start, "count": spec.count,
        "samples": [{"index": s.index, "scene": s.scene, "frame": s.frame, "scene_seed": s.scene_seed,
                     "camera": s.camera.to_dict()} for s in samples],
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
        version: the data set's format version (its manifest's, one of :data:`READ_VERSIONS`).

    Raises:
        DatasetError: a missing, unreadable, corrupt or foreign file (the message names it).
    """

    def __init__(self, path: str, spec: ShardSpec, config: SimConfig, seed: int, sha256: str | None = None,
                 version: int = VERSION) -> None:
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
        self.version = version
        """The shard's format version."""
        self._records: list[CameraRecord] = []
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
        want = _shard_meta(self.spec, self.config, seed, [], self.version)
        for key in ("format", "version", "config_sha256", "seed", "split", "shard", "start", "count"):
            if self.meta.get(key) != want[key]:
                raise ArchiveError(f"meta {key} is {self.meta.get(key)!r}, expected {want[key]!r} (a shard of another "
                                   "data set, split or version)")
        if self.version not in READ_VERSIONS or (self.version < 3 and self.config.camera != ROBOT_CAMERA):
            raise ArchiveError(f"format version {self.version} cannot hold this config's samples")
        entries = self.meta.get("samples")
        sps = self.config.samples_per_scene
        if not isinstance(entries, list) or len(entries) != self.spec.count:
            raise ArchiveError("meta 'samples' must list one entry per sample")
        keys = ["frame", "index", "scene", "scene_seed"] + (["camera"] if self.version >= 3 else [])
        for j, e in enumerate(entries):
            index = self.spec.start + j
            ok = isinstance(e, dict) and sorted(e) == sorted(keys) and all(
                isinstance(e[k], int) and not isinstance(e[k], bool) for k in keys if k != "camera")
            if not ok or (e["index"], e["scene"], e["frame"]) != (index, *divmod(index, sps)):
                raise ArchiveError(f"meta entry {j} does not describe sample {index}")
            if self.version >= 3:
                self._records.append(self._record(j, e["camera"]))

    def _record(self, j: int, d: Any) -> CameraRecord:
        """The camera record of meta entry ``j``, checked against the config (the render its field of view gives)."""
        try:
            record = CameraRecord.from_dict(d)
        except ValueError as e:
            raise ArchiveError(f"meta entry {j}: {e}") from None
        cam = cameras.render_camera(self.config, record.hfov)
        if record.image_size != (cam.width, cam.height) or not np.allclose(
                record.intrinsics, (cam.fx, cam.fy, cam.cx, cam.cy), rtol=1e-9, atol=0.0):
            raise ArchiveError(f"meta entry {j}: its camera's intrinsics and image size are not those of its field of "
                               f"view ({record.hfov:g} degrees) in this data set's config")
        return record

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
            if arrays["labels"].size and int(arrays["labels"].max()) >= n_classes:
                raise ArchiveError(f"member 'labels_{j:05d}' has labels outside the {n_classes} classes")
            if not np.all(np.isfinite(arrays["pose"])):
                raise ArchiveError(f"sample {j} has non-finite pose values")
        e = self.meta["samples"][j]
        if self._records:
            record = self._records[j]
        else:
            record = cameras.camera_record(self.config, cameras.robot_mount(self.config), arrays["pose"])
        return Sample(self.spec.split, e["index"], e["scene"], e["frame"], e["scene_seed"], **arrays, camera=record,
                      coverage=cameras.coverage(self.config, record.hfov))

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

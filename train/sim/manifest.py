"""The manifest of a simulator data set folder: what the folder holds, how it was made, and which shards are done.

Data set folder (format version 3)
    ``manifest.json``, and per split ``ceil(samples / shard_size)`` shards ``{split}-{n:05d}.npz`` (format in
    :mod:`.shards`); shard ``n`` holds samples ``n * shard_size ..`` of its split (the last one fewer). The manifest
    is a JSON object::

        {"format": "fruxel-sim", "version": 3, "complete": bool, "seed": int, "config_sha256": hex,
         "grid": FruxelGrid.to_dict(), "classes": ClassTable.to_dict(),
         "image": {"width": S, "height": S * H / W},
         "intrinsics": {"image": {fx, fy, cx, cy, width, height}, "grid": {...the grid's own camera...}},
         "seeds": "the seed rule in words", "samples_per_scene": n, "shard_size": N,
         "splits": {name: {"samples": int, "shards": [{"file", "start", "count", "sha256": hex or null}]}},
         "config": SimConfig.to_dict()}

    ``sha256`` is the SHA-256 of a complete shard file, null until the shard is written. ``intrinsics.image`` is
    the network image's camera, the view every sample's image shows; each sample's own camera is in its shard
    (:mod:`.shards`).

    Version 2 folders (made before cameras varied; their shards hold no camera record) are read as they are, with
    their own seed rule (:data:`SEED_RULE_V2`); the generator does not add version 3 shards to them.

Writes are atomic (:func:`fruxel.io.atomic_write`: temporary file beside the target, fsync, rename); reading checks
every field against what the recorded config and seed imply, and any problem raises one :class:`DatasetError`
naming the file.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass, field
from typing import Any

from fruxel.io import atomic_write

from .cameras import ROBOT_CAMERA
from .config import ConfigError, SimConfig
from .shards import READ_VERSIONS, VERSION, DatasetError, ShardSpec, shard_specs

FORMAT = "fruxel-sim"
"""``format`` of a data set manifest."""
MANIFEST = "manifest.json"
"""File name of the manifest in a data set folder."""
SEED_RULE_V2 = (
    "sample i of split s (k = crc32(s), n = samples_per_scene): scene c = i // n, frame f = i % n; "
    "room = make_scene(SeedSequence([seed, k, c, 0]).generate_state(2, uint32) as uint64); "
    "trajectory = random_trajectory(room, n, seed from SeedSequence([seed, k, c, 1])); "
    "augmentation rng = default_rng(SeedSequence([seed, k, i, 2])); a room without free floor is replaced by "
    "attempt a = 1, 2, ..., with a appended to the first two sequences"
)
"""The seed rule in words of version 2 manifests."""
SEED_RULE = SEED_RULE_V2 + (
    "; the camera of scene c is drawn from default_rng(SeedSequence([seed, k, c, 3])) (config.camera: uniform "
    "draws in the order height, pitch, roll, hfov), the same for every attempt"
)
"""The seed rule in words, recorded in every manifest (the code is in :mod:`.config` and :mod:`.cameras`)."""


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
    version: int = VERSION
    """The folder's format version (:data:`.shards.READ_VERSIONS`; what this fruxel writes: :data:`.shards.VERSION`)."""

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
            "version": self.version,
            "complete": bool(self.complete),
            "seed": int(self.seed),
            "config_sha256": cfg.digest(),
            "grid": cfg.grid.to_dict(),
            "classes": cfg.classes.to_dict(),
            "image": {"width": cfg.image_width, "height": cfg.image_height},
            "intrinsics": {"image": intr(img_cam), "grid": intr(grid_cam)},
            "seeds": SEED_RULE if self.version >= 3 else SEED_RULE_V2,
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
        version = d.get("version")
        if isinstance(version, bool) or version not in READ_VERSIONS:
            raise DatasetError(path, f"manifest version {version!r}; this fruxel reads versions "
                                     f"{', '.join(map(str, READ_VERSIONS))} (make the data set again with this fruxel, "
                                     "into a new folder)")
        try:
            config = SimConfig.from_dict(d.get("config"))
        except ConfigError as e:
            raise DatasetError(path, f"manifest has an invalid config: {e}") from None
        seed = d.get("seed")
        if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
            raise DatasetError(path, f"manifest seed must be a non-negative integer, got {seed!r}")
        if version < 3 and config.camera != ROBOT_CAMERA:
            raise DatasetError(path, f"a version {version} manifest cannot hold a camera other than the robot's")
        out = cls(config, seed, version=version)
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

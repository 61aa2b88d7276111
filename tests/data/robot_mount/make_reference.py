"""The robot mount's reference samples: what the simulator made before cameras other than the robot's existed.

Run once, at commit 0bb6701 (before the camera record and shard format version 3), from the worktree root:

    PYOPENGL_PLATFORM=egl .venv/bin/python tests/data/robot_mount/make_reference.py

It wrote

* ``samples.json``: for each of three small configs (``CONFIGS``), the SHA-256 of every sample's image, labels and
  pose bytes, the poses themselves, and the machine's OpenGL renderer and numpy version (image bytes can differ
  between OpenGL drivers, pose bits between numpy builds; see :mod:`fruxel.train.sim.shards`);
* ``dataset_v2/``: a complete data set folder of format version 2 (the last shards without a camera record), which
  ``tests/train/test_cameras.py`` reads with today's code.

Later code writes version 3 shards, so the folder cannot be remade by it; ``samples.json`` can be checked by it
(``tests/train/test_cameras.py`` does, with the robot camera).
"""

from __future__ import annotations

import hashlib
import json
import shutil
from pathlib import Path

import numpy as np

from fruxel.grid import FruxelGrid
from fruxel.render.scene import gl_renderer_name
from fruxel.train.sim.config import AugmentConfig, ImageConfig, SimConfig
from fruxel.train.sim.sample import SampleMaker
from fruxel.train.sim.writer import generate

HERE = Path(__file__).resolve().parent

CONFIGS = {
    # The data set tests' tiny config: 16^3 grid, 64 x 64 images, augmented.
    "tiny": (SimConfig(grid=FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0),
                       image=ImageConfig(size=64), samples_per_scene=3, shard_size=2,
                       splits=(("train", 6), ("test", 2))), 7),
    # A non-square grid of another field of view, without augmentation.
    "wide": (SimConfig(grid=FruxelGrid(width=32, height=24, depth=16, z_near=0.3, z_far=6.0, hfov=70.0),
                       image=ImageConfig(size=64, augment=AugmentConfig(enabled=False)), samples_per_scene=2,
                       shard_size=4, splits=(("train", 4),)), 3),
    # The shipped model's grid (64^3, 128 x 128 images), augmented.
    "ssz64": (SimConfig(grid=FruxelGrid(width=64, height=64, depth=64, z_near=0.5, z_far=8.0, hfov=60.0),
                        image=ImageConfig(size=128), samples_per_scene=16, shard_size=4,
                        splits=(("train", 3), ("test", 2))), 0),
}
"""Name -> (config, seed)."""


def _sha(a: np.ndarray) -> str:
    return hashlib.sha256(np.ascontiguousarray(a).tobytes()).hexdigest()


def main() -> None:
    out = {"gl_renderer": None, "numpy": np.__version__, "configs": {}}
    for name, (config, seed) in CONFIGS.items():
        rows = []
        with SampleMaker(config, seed, backend="warp-cpu") as maker:
            for split, n in config.splits:
                for i in range(n):
                    s = maker.make(split, i)
                    rows.append({"split": split, "index": i, "image": _sha(s.image), "labels": _sha(s.labels),
                                 "pose": _sha(s.pose), "pose_values": s.pose.tolist()})
        out["configs"][name] = {"config": config.to_dict(), "seed": seed, "samples": rows}
    out["gl_renderer"] = gl_renderer_name()
    (HERE / "samples.json").write_text(json.dumps(out, indent=1) + "\n")
    folder = HERE / "dataset_v2"
    if folder.exists():
        shutil.rmtree(folder)
    config, seed = CONFIGS["tiny"]
    generate(str(folder), config.replace(splits=(("train", 3), ("test", 2))), seed, backend="warp-cpu",
             progress=False)


if __name__ == "__main__":
    main()

"""Write the bundled photo and its ground truth: ``fruxel/data/photo.png`` and ``fruxel/data/photo_truth.npz``.

Run ``python scripts/make_photo.py [--out-dir DIR] [--index I]``. The photo is sample :data:`INDEX` of the
simulator's *test* split (rooms from seeds the training split never uses) with the robot model ssz64's grid (64^3,
0.5-8 m, 60 degrees) and class table, the training's base seed (0) and samples per room (16), and the seed
rule of :mod:`fruxel.train.sim.config` (its augmentation included): the room and the robot pose the shipped
model was evaluated on, its camera image rendered at 512 x 512, larger than the 64^3 model's input (that model reads
the photo reduced by area averaging, as any photo). The truth is the sample's 64^3 labels
as a fruxel model file; ``photo_truth128.npz`` holds its 128^3 labels, the truth of the 128^3 model
(``train/data/ssz128.safetensors``), which reads the photo at its own size.

Sample 43 was chosen because its camera sees every class (wall, floor, window, furniture, door and a sculpture),
after looking at the own-view class counts of 58 test samples, with the first shipped model, whose own-view
first-hit accuracy on it was close to its mean over the test split: a typical photo, not the best one
(docs/experiments.md). ``make demo`` gives the default model's own-view accuracy on it in its picture's title;
docs/model.md gives the model's accuracy over the test split.

The labels are exact on any machine (``fruxelize`` is deterministic); the image bytes are those of Mesa's
llvmpipe (another OpenGL driver can round the shading differently, by about one grey level).
``tests/train/test_photo.py`` checks that the bundled files are this sample.
"""

from __future__ import annotations

import argparse
from pathlib import Path
from typing import Any

SPLIT = "test"
"""The simulator split of the photo: held-out rooms."""
INDEX = 43
"""The sample of the split (room ``43 // 16 = 2``, frame 11 of its robot trajectory)."""
SEED = 0
"""Base seed of the simulator (``DataConfig.seed`` of the shipped model's training)."""
SAMPLES_PER_SCENE = 16
"""Samples per room (``DataConfig.samples_per_scene`` of the shipped model's training)."""
TEST_SAMPLES = 1000
"""Size of the test split (``DataConfig.test_samples``)."""
IMAGE_SIZE = 512
"""Width and height of the bundled photo, pixels."""


def photo_config(model_file: str | Path | None = None) -> Any:
    """The simulator settings of the photo: a shipped model's grid and classes (those of the robot's model, whose
    flat world the photo is from, unless ``model_file`` is given), a 512-pixel image."""
    from fruxel.train.model_files import ROBOT_MODEL, read_model_file, shipped_model
    from fruxel.train.sim.config import ImageConfig, SimConfig

    model = read_model_file(model_file if model_file is not None else shipped_model(ROBOT_MODEL)).config
    return SimConfig(grid=model.grid, image=ImageConfig(size=IMAGE_SIZE), classes=model.classes,
                     samples_per_scene=SAMPLES_PER_SCENE, splits=(("train", 10_000_000), (SPLIT, TEST_SAMPLES)))


def photo_sample(index: int = INDEX, config: Any = None) -> Any:
    """The :class:`fruxel.train.sim.sample.Sample` of the bundled photo (or of another test sample), with the
    labels on the grid of ``config`` (a :func:`photo_config`; default: the robot's model's)."""
    from fruxel.train.sim.sample import SampleMaker

    with SampleMaker(config if config is not None else photo_config(), SEED) as maker:
        return maker.make(SPLIT, index)


def main(argv: list[str] | None = None) -> int:
    from PIL import Image

    from fruxel.data import PHOTO, PHOTO_TRUTH, PHOTO_TRUTH_128
    from fruxel.io import atomic_path, save
    from fruxel.model import FruxelModel
    from fruxel.train.model_files import shipped_model

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=PHOTO.parent,
                        help="folder of photo.png, photo_truth.npz and photo_truth128.npz")
    parser.add_argument("--index", type=int, default=INDEX, help=f"sample of the test split (default {INDEX})")
    args = parser.parse_args(argv)
    cfg = photo_config()
    sample = photo_sample(args.index, cfg)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    png, npz = args.out_dir / PHOTO.name, args.out_dir / PHOTO_TRUTH.name
    with atomic_path(png) as tmp:
        Image.fromarray(sample.image).save(tmp, format="PNG", optimize=True)
    model = FruxelModel(sample.labels, cfg.grid, cfg.classes)
    save(npz, model)
    print(f"{png}: {png.stat().st_size} bytes, {sample.image.shape[1]}x{sample.image.shape[0]} pixels")
    print(f"{npz}: {npz.stat().st_size} bytes, split {SPLIT!r} sample {sample.index} (room {sample.scene}, frame "
          f"{sample.frame}, room seed {sample.scene_seed})")
    for name, n in zip(model.classes.names, model.counts().tolist(), strict=False):
        print(f"  {name:10s} {n}")
    # The same room and pose on the 128^3 model's grid: the truth of fruxel-render --checkpoint ssz128.
    cfg128 = photo_config(shipped_model("ssz128"))
    fine = photo_sample(args.index, cfg128)
    npz128 = args.out_dir / PHOTO_TRUTH_128.name
    save(npz128, FruxelModel(fine.labels, cfg128.grid, cfg.classes))
    print(f"{npz128}: {npz128.stat().st_size} bytes, the same sample on a {fine.labels.shape[0]}^3 grid")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

"""What the walls' unseen thickness costs a perfect reader: per-class IoU of a test set's truth against the truth of
the same samples with every wall as thick as one value.

    python scripts/thickness_oracle.py [--test-set any-camera] [--samples 256] [--thickness 0.21]

From inside a room a wall's thickness cannot be seen (a door's jamb shows it, from some poses), yet the labels count
the wall's cells through it: a 64^3 grid over 0.5-8 m has slices 0.117 m deep and the home world's walls are 0.12 to
0.3 m thick. This script labels the rooms and camera poses of fruxel-eval's held-out samples of ``--test-set`` (the same
stream, seed 0) twice: as they are, and with ``home.wall_thickness_range`` collapsed to ``--thickness`` (the room
generator still draws the thickness, so every later draw is the same: the same furniture and objects in the same
places), both from the first room's camera pose. The second truth is what a reader that knew everything except the
walls' thickness, and guessed ``--thickness``, would answer; its IoU against the first is that reader's score, the
ceiling that the unseen thickness alone leaves any model. The halls behind doors, the window frames set in the
walls and the floor and ceiling slabs' rims under the walls move with the walls' faces, so they count too. An
analysis for the experiments log, not a metric of the product's reports.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from depth_tolerance import tolerant_counts, tolerant_iou  # noqa: E402

GRID = 64
"""The grid of the samples (the camera-aware model's, 64^3)."""


def with_wall_thickness(make_config: Callable[..., Any], thickness: float) -> Callable[..., Any]:
    """``make_config`` (:func:`fruxel.train.samples.sim_config`) whose configs have every wall ``thickness`` metres
    thick (``home.wall_thickness_range`` collapsed to one value)."""

    def made(*args: Any, **kwargs: Any) -> Any:
        config = make_config(*args, **kwargs)
        home = dataclasses.replace(config.home, wall_thickness_range=(thickness, thickness))
        return config.replace(home=home)

    return made


def label_pairs(test_set: str, samples: int, thickness: float) -> tuple[tuple[str, ...],
                                                                        Iterator[tuple[np.ndarray, np.ndarray]]]:
    """The class names and, per sample, the ``(D, H, W)`` uint8 truth of fruxel-eval's first ``samples`` test
    samples of ``test_set`` and the truth of the same room with every wall ``thickness`` metres thick, both seen
    from the sample's own camera pose (the robot's drive may take another path in the other room: the pose is the
    first one's)."""
    from fruxel.kernels.fruxelize import fruxelize
    from fruxel.train import samples as sample_module
    from fruxel.train.model_files import load_model
    from fruxel.train.sim.sample import SampleMaker

    model = load_model("ssz64-any", device="cpu").config
    if model.grid.depth != GRID:
        raise SystemExit(f"thickness_oracle: ssz64-any's grid is {model.grid.depth}^3, not {GRID}^3")
    source = sample_module.SampleSource(seed=0, assets="", test_set=test_set, augment=True)
    drawn = sample_module.sim_config(model, source, (("test", samples),))
    guessed = with_wall_thickness(sample_module.sim_config, thickness)(model, source, (("test", samples),))

    def pairs() -> Iterator[tuple[np.ndarray, np.ndarray]]:
        rooms: dict[int, tuple[Any, Any]] = {}
        with SampleMaker(drawn, 0, backend="warp-cpu") as a, SampleMaker(guessed, 0, backend="warp-cpu") as b:
            for i in range(samples):
                (room_a, pose), (room_b, _) = a.scene_of("test", i), b.scene_of("test", i)
                key = i // drawn.samples_per_scene
                if key not in rooms:  # one room's meshes at a time
                    rooms = {key: (room_a.mesh_set(backend="warp-cpu"), room_b.mesh_set(backend="warp-cpu"))}
                sets = rooms[key]
                yield tuple(np.asarray(fruxelize(m, drawn.grid, pose, backend="warp-cpu"), dtype=np.uint8)
                            for m in sets)

    return tuple(model.classes.names), pairs()


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--test-set", default="any-camera")
    p.add_argument("--samples", type=int, default=256)
    p.add_argument("--thickness", type=float, default=0.21,
                   help="the walls' thickness of the guess, metres (default: the middle of the home world's range)")
    args = p.parse_args(argv)
    from tqdm import tqdm

    from fruxel.train.sim.testsets import TEST_SETS

    if not 0.08 <= args.thickness <= 0.6:
        raise SystemExit(f"thickness_oracle: --thickness must lie in [0.08, 0.6] m, got {args.thickness}")
    if args.samples < 1 or args.test_set not in TEST_SETS or TEST_SETS[args.test_set].world != "home":
        raise SystemExit(f"thickness_oracle: --samples must be >= 1 and --test-set one of the furnished rooms' "
                         f"{[n for n, t in TEST_SETS.items() if t.world == 'home']}")
    names, pairs = label_pairs(args.test_set, args.samples, args.thickness)
    counts = np.zeros((len(names), 4), dtype=np.int64)
    for truth, guess in tqdm(pairs, total=args.samples, desc="thickness_oracle", unit="sample"):
        counts += tolerant_counts(guess, truth, len(names), 0)  # no tolerance: the usual IoU's counts
    scores = tolerant_iou(counts)
    present = counts[:, 1] > 0
    print(f"walls {args.thickness:g} m thick against the drawn thickness, {args.samples} samples of {args.test_set}: "
          f"mIoU {np.nanmean(scores[present]):.1f} | "
          + " ".join(f"{names[c]} {scores[c]:.1f}" for c in range(1, len(names))))
    return 0


if __name__ == "__main__":
    sys.exit(main())

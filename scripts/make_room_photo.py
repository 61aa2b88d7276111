"""Write the bundled furnished-room photo, its ground truth and its credits: ``fruxel/data/room.png``,
``fruxel/data/room_truth.npz`` and ``fruxel/data/room_credits.md``, the first picture of ``make demo``.

    python scripts/make_room_photo.py [--assets assets/pack] [--out-dir fruxel/data]

The photo is sample :data:`INDEX` of the ``any-camera`` test set's test split (seed 0: the held-out rooms
``fruxel-eval`` streams), made for the default model's grid and classes (``ssz64-any``: 64^3 cells, 0.5-8 m, 60
degrees, the furnished rooms' classes) with a 512 x 512 image, as ``scripts/testset_sheet.py --committable-only``
makes its sheets: the room is furnished from the pack's committable assets alone, whose licences let a picture of
them be committed (``room_credits.md`` lists the ones the room holds), so it holds other things than the same test
room in ``fruxel-eval``, which draws from every asset. The camera (any height, pitch, roll and field of view of the
set) is printed as the ``--pitch``, ``--roll`` and ``--height`` that ``make demo`` tells the model; the image is
already framed to the grid's 60 degrees (grey where a narrower camera saw nothing).

Sample 51 (room 3, frame 3) was chosen after looking at frame 3 of the test split's first 12 rooms: its truth holds
six classes (wall, floor, window, furniture, ceiling, object), seen from a hand-held height; it looks like a
lived-in room, and the default model's own-view first-hit accuracy on it, told its camera, was near that model's
mean over the test set: a typical photo, not the best one. The labels are exact on any machine; the image is the ray
tracer's on Warp's CPU device (the script and its test make it there, on any machine).
``tests/train/test_room_photo.py`` checks that the bundled files are this sample and that the Makefile tells its
camera.
"""

from __future__ import annotations

import argparse
import sys
import tempfile
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

TEST_SET = "any-camera"
"""The held-out test set of the photo (``fruxel.train.sim.testsets.TEST_SETS``)."""
INDEX = 51
"""The sample of the set's test split."""
SEED = 0
"""The base seed of the stream (``fruxel-eval``'s default)."""
IMAGE_SIZE = 512
"""Width and height of the bundled photo, pixels."""


def room_sample(pack: Path) -> tuple[Any, Any, set[str]]:
    """The photo's :class:`fruxel.train.sim.sample.Sample`, furnished from the committable assets of ``pack``, the
    simulator config that made it (its grid and classes are the truth's) and the ids of the pack assets its room
    holds."""
    from testset_sheet import committable_pack, room_assets, set_config

    from fruxel.train.sim.sample import SampleMaker

    with tempfile.TemporaryDirectory() as tmp:
        committable = committable_pack(pack, Path(tmp) / "pack")
        shape = argparse.Namespace(grid=64, image=IMAGE_SIZE, count=INDEX + 1)  # rooms: the split holds INDEX
        config = set_config(TEST_SET, shape, committable)
        with SampleMaker(config, SEED, device="cpu") as maker:
            sample = maker.make("test", INDEX)
            scene, _ = maker.scene_of("test", INDEX)
    return sample, config, room_assets(scene)


def camera_flags(sample: Any) -> list[str]:
    """The ``fruxel-render`` options that tell a model the sample's camera: pitch and roll to 0.1 degree, height to
    a centimetre."""
    c = sample.camera
    return ["--pitch", f"{c.pitch:.1f}", "--roll", f"{c.roll:.1f}", "--height", f"{c.height:.2f}"]


def main(argv: list[str] | None = None) -> int:
    """Write the three files into ``--out-dir``, atomically, and print the camera's flags."""
    from PIL import Image
    from raytrace_sheet import credits_table

    from fruxel.data import ROOM_CREDITS, ROOM_PHOTO, ROOM_TRUTH
    from fruxel.io import atomic_path, save
    from fruxel.model import FruxelModel
    from fruxel.train.sim.rooms.library import resolve_pack

    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--assets", type=Path, default=None,
                        help="the asset pack (default: $FRUXEL_ASSETS, else assets/pack)")
    parser.add_argument("--out-dir", type=Path, default=ROOM_PHOTO.parent, help="folder of the three files")
    args = parser.parse_args(argv)
    pack = resolve_pack(args.assets, option="--assets")
    sample, config, used = room_sample(pack)
    args.out_dir.mkdir(parents=True, exist_ok=True)
    png, npz, credits = (args.out_dir / p.name for p in (ROOM_PHOTO, ROOM_TRUTH, ROOM_CREDITS))
    with atomic_path(png) as tmp:
        Image.fromarray(sample.image).save(tmp, format="PNG", optimize=True)
    save(npz, FruxelModel(sample.labels, config.grid, config.classes))
    with atomic_path(credits) as tmp:
        Path(tmp).write_text(credits_table(pack, used))
    print(f"{png}: {png.stat().st_size} bytes; {npz}; {credits}: {len(used)} assets")
    print("camera: " + " ".join(camera_flags(sample)))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

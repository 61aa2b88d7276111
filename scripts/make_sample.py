"""Write the bundled sample room, ``fruxel/data/sample_room.npz`` (:func:`fruxel.data.make_sample.sample_model`).

Run ``python scripts/make_sample.py [--out-dir DIR]``, then ``python scripts/make_sample_picture.py`` for its
picture. The model is deterministic; ``tests/core/test_mesh.py`` checks that the bundled file is up to date.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from fruxel.data import SAMPLE_ROOM
from fruxel.data.make_sample import sample_model
from fruxel.io import save


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out-dir", type=Path, default=SAMPLE_ROOM.parent, help="folder of sample_room.npz")
    args = parser.parse_args(argv)
    model = sample_model()
    args.out_dir.mkdir(parents=True, exist_ok=True)
    npz = args.out_dir / SAMPLE_ROOM.name
    save(npz, model)
    print(f"{npz}: {npz.stat().st_size} bytes, {model.n_occupied} occupied cells")
    for name, n in zip(model.classes.names, model.counts().tolist(), strict=False):
        print(f"  {name:10s} {n}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

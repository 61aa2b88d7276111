"""One contact sheet per held-out test set (``train/sim/testsets.py``), to look at what a model is evaluated on: N
samples of the test split, one room each, as ``fruxel-sim preview --test-set NAME`` draws them (its camera image, the
ground truth's first-hit labels from the sample's own camera in the class colours, and a ray-cast render of the
truth from a second pose).

    python scripts/testset_sheet.py --assets assets/pack --committable-only --out-dir docs/testsets
        [--credits docs/testsets/credits.md] [--count 6] [--image 256] [--grid 64] [--seed 0] [--sets a,b]
        [--photos ../shared/real_photos [--compare-out out/testsets-vs-photos.png]]

Writes ``{out-dir}/{set}.png`` for each set. The samples are those ``fruxel-eval --test-set NAME`` streams for a
model of ``--grid`` cells from ``--image`` pixels with the furnished rooms' classes (``HOME_CLASSES``), seed
``--seed``: the test split's rooms ``0, 1, ..., N - 1`` (their first frames). ``--committable-only`` furnishes the
rooms from a copy of the pack that holds only the assets whose licence lets pictures of them be committed (for
sheets that go into docs/; ``--credits`` lists the assets they show). ``--photos DIR`` also writes a comparison
sheet (``--compare-out``) of the sets' camera images above the photos of ``DIR`` resized to the same height: never
for the repository, whose licence the photos do not share.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png")
"""The files of ``--photos`` that are photos."""


def committable_pack(pack: Path, out: Path) -> Path:
    """A pack folder at ``out`` holding the committable assets of ``pack`` alone (their files linked, not copied),
    each in its split."""
    from fruxel.train.sim.assetpack.manifest import BUILDER_NAME, MANIFEST_NAME, manifest_bytes, parse_manifest

    manifest = pack / MANIFEST_NAME
    entries = [e for e in parse_manifest(manifest.read_bytes(), str(manifest)) if e.committable]
    for e in entries:
        for name in e.files.values():
            (out / name).parent.mkdir(parents=True, exist_ok=True)
            (out / name).symlink_to((pack / name).resolve())
    (out / MANIFEST_NAME).write_bytes(manifest_bytes(entries))
    if (pack / BUILDER_NAME).is_file():  # else the copy is refused as its pack would be, in one line
        (out / BUILDER_NAME).write_bytes((pack / BUILDER_NAME).read_bytes())
    return out


def set_config(name: str, args: argparse.Namespace, assets: Path) -> Any:
    """The simulator config of test set ``name`` for the sheets' model (grid, image size, home classes)."""
    from fruxel.classes import HOME_CLASSES
    from fruxel.grid import FruxelGrid
    from fruxel.train.sim.config import ImageConfig, SimConfig
    from fruxel.train.sim.testsets import TEST_SETS

    grid = FruxelGrid(args.grid, args.grid, args.grid, 0.5, 8.0, 60.0)
    base = SimConfig(grid=grid, image=ImageConfig(size=args.image), classes=HOME_CLASSES, assets=str(assets))
    return TEST_SETS[name].config(base.replace(splits=(("test", args.count * base.samples_per_scene),)))


def set_sheet(name: str, config: Any, count: int, seed: int, used: set[str]) -> tuple[np.ndarray, list[Any]]:
    """The sheet of one test set, as ``fruxel-sim preview --test-set NAME --count N --step S`` draws it (S the samples
    a room: the first frame of each of the test split's first ``count`` rooms), and its samples; the pack assets
    their rooms show are added to ``used``."""
    from fruxel.train.sim.images import preview_sheet
    from fruxel.train.sim.sample import SampleMaker

    indices = range(0, count * config.samples_per_scene, config.samples_per_scene)
    with SampleMaker(config, seed) as maker:
        sheet, samples = preview_sheet(maker, config, "test", indices, seed, what=f"test set {name}: ")
        for index in indices:
            used.update(room_assets(maker.scene_of("test", index)[0]))
    return sheet, samples


def room_assets(scene: Any) -> set[str]:
    """The ids of the pack assets a room holds: its objects' meshes and their materials' textures and images."""
    used = {o.asset for o in scene.objects if o.asset}
    return used | {a for o in scene.objects for m in o.materials for a in (m.texture, m.image) if a}


def comparison_sheet(images: dict[str, list[np.ndarray]], photos: Path) -> np.ndarray:
    """The sets' camera images, a row each, above the photos of ``photos`` scaled to the images' height, in rows
    as wide as the images' rows."""
    from PIL import Image

    from fruxel.train.predict import load_image
    from fruxel.train.sim.images import contact_sheet

    rows = [{f"{name} {k}": img for k, img in enumerate(imgs)} for name, imgs in images.items()]
    titles = [f"test set {name}" for name in images]
    files = sorted(p for p in photos.iterdir() if p.suffix.lower() in PHOTO_SUFFIXES)
    if not files:
        raise SystemExit(f"testset_sheet: {photos}: no photos ({', '.join(PHOTO_SUFFIXES)})")
    height = next(iter(images.values()))[0].shape[0]
    width = max(sum(img.shape[1] for img in row.values()) for row in rows)
    row: dict[str, np.ndarray] = {}
    for f in files:
        photo = Image.fromarray(load_image(f))
        scaled = np.asarray(photo.resize((round(photo.width * height / photo.height), height), Image.LANCZOS))
        if row and sum(p.shape[1] for p in row.values()) + scaled.shape[1] > width:
            rows.append(row)
            row = {}
        row[f.name] = scaled
    rows.append(row)
    titles += [f"photos of {photos} (not the project's licence: never commit this sheet)"] * (len(rows) - len(titles))
    return contact_sheet(rows, ("",), np.zeros((1, 3), np.uint8), titles)


def committable_path(path: Path) -> bool:
    """Whether git would pick ``path`` up in this repository (inside it and not ignored): no place for a picture of
    photos whose licence is not the project's."""
    repo = Path(__file__).resolve().parents[1]
    try:
        path.resolve().relative_to(repo)
    except ValueError:
        return False
    try:
        ignored = subprocess.run(["git", "-C", str(repo), "check-ignore", "-q", str(path.resolve())]).returncode == 0
    except OSError:
        return True  # no git to ask: inside the repository counts as committable
    return not ignored


def main(argv: list[str] | None = None) -> int:
    from fruxel.train.sim.testsets import TEST_SETS

    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--assets", type=Path, required=True, help="the asset pack folder (make assets)")
    p.add_argument("--out-dir", type=Path, required=True, help="folder of the sheets, {set}.png")
    p.add_argument("--sets", default=",".join(TEST_SETS), help="test sets, comma-separated (default: all)")
    p.add_argument("--count", type=int, default=6, help="samples per set (default 6)")
    p.add_argument("--image", type=int, default=256, help="image size in pixels (default 256)")
    p.add_argument("--grid", type=int, default=64, help="grid cells a side (default 64)")
    p.add_argument("--seed", type=int, default=0, help="base seed (default 0)")
    p.add_argument("--committable-only", action="store_true", help="only assets that may be committed")
    p.add_argument("--credits", type=Path, help="write a Markdown table of the shown assets' licences and credits")
    p.add_argument("--photos", type=Path, help="a folder of photos to compare with, by eye")
    p.add_argument("--compare-out", type=Path, default=Path("out/testsets-vs-photos.png"),
                   help="the comparison sheet with --photos (default out/testsets-vs-photos.png)")
    args = p.parse_args(argv)
    names = args.sets.split(",")
    unknown = [n for n in names if n not in TEST_SETS]
    if unknown:
        p.error(f"--sets: unknown test sets {unknown} (known: {list(TEST_SETS)})")
    if not (args.assets / "manifest.json").is_file():
        p.error(f"--assets {args.assets}: no asset pack there (build it with `make assets`)")
    if min(args.count, args.image, args.grid) < 1:
        p.error("--count, --image and --grid must be positive")
    if args.photos is not None and not args.photos.is_dir():
        p.error(f"--photos {args.photos}: not a folder")
    if args.photos is not None and committable_path(args.compare_out):
        p.error(f"--compare-out {args.compare_out}: git would commit it; the photos' licence is not the project's "
                "(write it under out/, which git ignores)")
    with tempfile.TemporaryDirectory() as tmp:
        pack = committable_pack(args.assets, Path(tmp)) if args.committable_only else args.assets
        write_sheets(args, names, pack)
    return 0


def write_sheets(args: argparse.Namespace, names: list[str], pack: Path) -> None:
    """Make the samples of every set and write the sheets (and the credits and the comparison, where asked)."""
    from raytrace_sheet import credits_table

    from fruxel.render.images import write_image

    used: set[str] = set()
    images = {}
    args.out_dir.mkdir(parents=True, exist_ok=True)
    for name in names:
        config = set_config(name, args, pack)
        sheet, samples = set_sheet(name, config, args.count, args.seed, used)
        images[name] = [s.image for s in samples]
        out = write_image(args.out_dir / f"{name}.png", sheet)
        print(f"testset_sheet: wrote {out}")
    if args.credits:
        args.credits.write_text(credits_table(pack, used))
        print(f"testset_sheet: wrote {args.credits}")
    if args.photos:
        args.compare_out.parent.mkdir(parents=True, exist_ok=True)
        print(f"testset_sheet: wrote {write_image(args.compare_out, comparison_sheet(images, args.photos))}")


if __name__ == "__main__":
    sys.exit(main())

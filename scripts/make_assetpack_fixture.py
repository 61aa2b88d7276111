"""Make the tiny asset-pack sources the tests build from (tests/data/assetpack_sources/), from the real cache.

    python scripts/make_assetpack_fixture.py [--cache assets/cache] [--out tests/data/assetpack_sources]

Only committable content (CC0, MIT, public domain), trimmed so the whole folder stays far below 1 MB: four
CC0 models of Sweet Home 3D's BlendSwap-CC-0 library (a chair, shelves, a desk lamp and a phone whose catalog
entry has a modelRotation) in a trimmed .sh3f with the package's copyright file, and a few textures and photos
of Miniworld (MIT), robosuite (MIT) and scikit-image (CC0 / public domain) downscaled to 64-128 pixels. The tree
mirrors the cache's layout, so the tests run the real builder on it (fruxel.train.sim.assetpack.build_pack).
"""

from __future__ import annotations

import argparse
import io
import re
import shutil
import zipfile
from pathlib import Path

from PIL import Image

SH3F = "usr/share/sweethome3d/furniture/BlendSwap-CC-0.sh3f"
MODELS = (15, 39, 70, 79)
"""Catalog entries kept: desk lamp, shelves, Apple iPhone (modelRotation), chair."""
IMAGES = {
    "pypi/miniworld-2.1.0": ["miniworld/textures/brick_wall_1.png", "miniworld/textures/wood_planks_1.png",
                             "miniworld/textures/portraits/alessandro_allori1.png"],
    "pypi/robosuite-1.5.2": ["robosuite/models/assets/textures/light-wood.png",
                             "robosuite/models/assets/textures/white-plaster.png"],
    "pypi/scikit-image-0.26.0": ["skimage/data/brick.png", "skimage/data/rocket.jpg", "skimage/data/coffee.png"],
}
"""Files kept per package tree, downscaled."""


def _zip_write(zf: zipfile.ZipFile, name: str, data: bytes) -> None:
    info = zipfile.ZipInfo(name, date_time=(1980, 1, 1, 0, 0, 0))
    info.compress_type = zipfile.ZIP_DEFLATED
    zf.writestr(info, data, compresslevel=9)


def _trim_sh3f(src: Path, dest: Path) -> None:
    with zipfile.ZipFile(src) as zf:
        catalog = zf.read("PluginFurnitureCatalog.properties").decode("utf-8")
        keep_lines, folders = [], set()
        for line in catalog.splitlines():
            m = re.match(r"[A-Za-z]+#(\d+)=", line)
            if m is None or int(m.group(1)) in MODELS:
                keep_lines.append(line)
            if m is not None and int(m.group(1)) in MODELS and line.startswith("model#"):
                folders.add(line.split("=", 1)[1].lstrip("/").rsplit("/", 1)[0] + "/")
        names = sorted(n for n in zf.namelist() if any(n.startswith(f) for f in folders) and not n.endswith("/"))
        dest.parent.mkdir(parents=True, exist_ok=True)
        with zipfile.ZipFile(dest, "w") as out:
            _zip_write(out, "PluginFurnitureCatalog.properties", ("\n".join(keep_lines) + "\n").encode("utf-8"))
            for n in names:
                _zip_write(out, n, zf.read(n))


def _small_image(src: Path, dest: Path, side: int) -> None:
    dest.parent.mkdir(parents=True, exist_ok=True)
    with Image.open(src) as im:
        im = im.convert("RGB")
        im.thumbnail((side, side), Image.Resampling.LANCZOS)
        buf = io.BytesIO()
        im.save(buf, format="JPEG" if dest.suffix == ".jpg" else "PNG", **({"quality": 85}
                                                                          if dest.suffix == ".jpg" else {}))
    dest.write_bytes(buf.getvalue())


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--cache", type=Path, default=Path("assets/cache"))
    p.add_argument("--out", type=Path, default=Path("tests/data/assetpack_sources"))
    args = p.parse_args()
    sh3d = args.cache / "debian/sweethome3d-furniture-1.8-1"
    out_sh3d = args.out / "debian/sweethome3d-furniture-1.8-1"
    if args.out.exists():
        shutil.rmtree(args.out)
    _trim_sh3f(sh3d / SH3F, out_sh3d / SH3F)
    copyright_rel = "usr/share/doc/sweethome3d-furniture/copyright"
    (out_sh3d / copyright_rel).parent.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(sh3d / copyright_rel, out_sh3d / copyright_rel)
    for tree, files in IMAGES.items():
        for rel in files:
            _small_image(args.cache / tree / rel, args.out / tree / rel, 128 if "rocket" in rel else 64)
    total = sum(f.stat().st_size for f in args.out.rglob("*") if f.is_file())
    print(f"wrote {args.out}: {total} bytes")


if __name__ == "__main__":
    main()

"""A sheet of photos and what models read in them: per photo, the photo in the models' view and each model's
own-view labels (the first occupied cell of every column of its fruxel model: what its camera sees of it).

    python scripts/photo_sheet.py ../shared/real_photos --model ssz64 --model runs/any/model.safetensors \
        --out out/photos.png [--pitch 10 --height 1.4]

For looking at real photos by eye whenever the simulator or a model changes (never for choosing anything: the
photos are not held-out data of any split). Each model reads every photo with the camera it is told of: by default
nothing (pose unknown), else ``--pitch`` / ``--roll`` / ``--height`` for all of them, as ``fruxel-predict`` takes
them; the photo is framed as the grid's view at its own width (the centre crop of ``fruxel-predict --fit crop``).
The sheet's photos are the inputs' pixels: keep a sheet of photos whose licence forbids redistribution out of the
repository.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Any

import numpy as np

PHOTO_SUFFIXES = (".jpg", ".jpeg", ".png", ".webp")


def photos_of(paths: list[str]) -> list[Path]:
    """The photo files named, folders expanded (sorted); exits with one line when there are none."""
    out: list[Path] = []
    for p in map(Path, paths):
        out += sorted(f for f in p.iterdir() if f.suffix.lower() in PHOTO_SUFFIXES) if p.is_dir() else [p]
    missing = [str(p) for p in out if not p.is_file()]
    if missing or not out:
        sys.exit(f"photo_sheet: {missing[0] if missing else ' '.join(paths)}: no such photo")
    return out


def read_photos(model: str, photos: list[Path], camera: dict[str, float | None],
                size: int) -> tuple[list[list[np.ndarray]], Any]:
    """Per photo ``[framed photo, own-view labels coloured]``, each ``(size, size, 3)`` uint8, for ``model``; and
    the model's class table."""
    import torch
    from PIL import Image

    from fruxel.train.eval.metrics import first_surface
    from fruxel.train.predict import CameraPrior, load_image, load_predictor, prepare_image

    predictor = load_predictor(model, device="cpu", camera=CameraPrior(**camera))
    cfg = predictor.config
    colours = np.asarray(cfg.classes.colours, dtype=np.uint8)
    out = []
    for p in photos:
        image = prepare_image(load_image(p), cfg)
        with torch.no_grad():
            (logits,) = predictor.predict([image])
        labels = first_surface(logits.argmax(0)[None])[0].numpy()
        out.append([np.asarray(Image.fromarray(a).resize((size, size), resample))
                    for a, resample in ((image, Image.BILINEAR), (colours[labels], Image.NEAREST))])
    return out, cfg.classes


def main(argv: list[str] | None = None) -> None:
    from fruxel.cli.common import OneLineParser

    p = OneLineParser(prog="photo_sheet.py", description=__doc__.split("\n\n")[0])
    p.add_argument("photos", nargs="+", help="photo files or folders of them")
    p.add_argument("--model", action="append", default=None, help="a model file or shipped name (repeatable; "
                   "default ssz64)")
    p.add_argument("--pitch", type=float, default=None)
    p.add_argument("--roll", type=float, default=None)
    p.add_argument("--height", type=float, default=None)
    p.add_argument("--size", type=int, default=192, help="side of each panel in pixels (default 192)")
    p.add_argument("--out", default="out/photo_sheet.png")
    args = p.parse_args(argv)
    if args.size < 32:
        p.error(f"--size must be at least 32 pixels, got {args.size}")
    from PIL import Image

    from fruxel.errors import FruxelError
    from fruxel.io import atomic_write
    from fruxel.render.legend import draw_caption, draw_legend

    photos = photos_of(args.photos)
    models = args.model or ["ssz64"]
    camera = {"pitch": args.pitch, "roll": args.roll, "height": args.height}
    try:
        read = [read_photos(m, photos, camera, args.size) for m in models]
    except FruxelError as e:
        sys.exit(f"photo_sheet: {e}")
    panels = [r[0] for r in read]
    classes = max((r[1] for r in read), key=lambda c: len(c.names))
    rows = [np.concatenate([panels[0][i][0]] + [panels[k][i][1] for k in range(len(models))], axis=1)
            for i in range(len(photos))]
    rows.append(draw_legend(np.full((args.size // 2, rows[0].shape[1], 3), 255, np.uint8), classes,
                            range(1, len(classes.names)), corner="top-left"))
    sheet = np.concatenate(rows, axis=0)
    told = ", ".join(f"{k} {v:g}" for k, v in camera.items() if v is not None) or "pose unknown"
    for k, name in enumerate([f"photo ({told})", *models]):
        strip = draw_caption(sheet[:args.size, k * args.size:(k + 1) * args.size],
                             Path(name).parent.name if name.endswith(".safetensors") else name)
        sheet[:args.size, k * args.size:(k + 1) * args.size] = strip
    out = Path(args.out)
    out.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(out, "wb") as f:
        Image.fromarray(sheet).save(f, format="PNG")
    print(out)


if __name__ == "__main__":
    main()

"""Contact sheets of an asset pack, to look at: its textures (albedo beside normal map) and a few of its meshes
rendered offscreen with pyrender (orthographic, seen from the front, -y, and a little above, all at one scale
per sheet row so that sizes compare; a 1 m bar stands beside each).

    python scripts/assetpack_sheets.py assets/pack --textures out/textures.png --meshes out/meshes.png
        [--committable-only] [--tile 72] [--per-category 6] [--mesh-ids ID ...]

``--committable-only`` draws only assets whose licence allows committing them (for sheets that go into docs/).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np


def _caption(img: np.ndarray, lines: list[str], size: int = 11) -> np.ndarray:
    from PIL import Image, ImageDraw

    from fruxel.render.compat import default_font

    h = (size + 3) * len(lines) + 2
    out = Image.new("RGB", (img.shape[1], img.shape[0] + h), "white")
    out.paste(Image.fromarray(img), (0, 0))
    d = ImageDraw.Draw(out)
    for k, line in enumerate(lines):
        d.text((2, img.shape[0] + 1 + k * (size + 3)), line, fill="black", font=default_font(size))
    return np.asarray(out)


def _grid(tiles: list[np.ndarray], cols: int) -> np.ndarray:
    h = max(t.shape[0] for t in tiles)
    w = max(t.shape[1] for t in tiles)
    rows = (len(tiles) + cols - 1) // cols
    sheet = np.full((rows * h, cols * w, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, cols)
        sheet[r * h:r * h + t.shape[0], c * w:c * w + t.shape[1]] = t
    return sheet


def texture_sheet(pack, tile: int, per_category: int, committable_only: bool, drawn: list) -> np.ndarray:
    from PIL import Image

    tiles = []
    for cat in pack.categories("texture"):
        entries = [e for e in pack.select("texture", cat) if e.committable or not committable_only]
        for e in entries[:: max(1, len(entries) // per_category)][:per_category]:
            t = pack.texture(e)
            drawn.append(e)
            a = np.asarray(Image.fromarray(t.albedo).resize((tile, tile)))
            n = np.asarray(Image.fromarray(np.round((t.normal + 1) * 127.5).astype(np.uint8)).resize((tile, tile)))
            pair = np.concatenate([a, np.full((tile, 2, 3), 255, np.uint8), n], axis=1)
            tiles.append(_caption(pair, [f"{cat} ({e.split}) {e.size_m[0]:.2g} m", e.id.split("/")[0] + " "
                                         + e.licence]))
    return _grid(tiles, 8)


def _render(mesh, size: int, extent: float) -> np.ndarray:
    from fruxel.render.compat import import_pyrender

    pyrender = import_pyrender()
    import trimesh

    scene = pyrender.Scene(bg_color=[1.0, 1.0, 1.0, 1.0], ambient_light=[0.35, 0.35, 0.35])
    tm = mesh.to_trimesh()
    scene.add(pyrender.Mesh.from_trimesh(tm, smooth=False))
    # A 1 m bar beside the model, and the floor line z = 0.
    bar = trimesh.creation.box(extents=(0.03, 0.03, 1.0))
    bar.apply_translation((-extent * 0.45, 0, 0.5))
    bar.visual.face_colors = (220, 40, 40, 255)
    scene.add(pyrender.Mesh.from_trimesh(bar, smooth=False))
    floor = trimesh.creation.box(extents=(extent, 0.02, 0.005))
    floor.visual.face_colors = (60, 60, 60, 255)
    scene.add(pyrender.Mesh.from_trimesh(floor, smooth=False))
    # Camera in front (-y), 15 degrees above, looking at the middle of the frame.
    a = np.radians(15)
    pose = np.eye(4)
    # Columns: camera x (right) = +x, y (up) and z (backwards, pyrender looks along -z) tilted by a.
    pose[:3, :3] = np.array([[1, 0, 0], [0, np.sin(a), -np.cos(a)], [0, np.cos(a), np.sin(a)]])
    centre = np.array([0, 0, extent * 0.42])
    pose[:3, 3] = centre + pose[:3, 2] * 10
    cam = pyrender.OrthographicCamera(xmag=extent / 2, ymag=extent / 2, znear=0.1, zfar=30)
    scene.add(cam, pose=pose)
    scene.add(pyrender.DirectionalLight(intensity=3.0), pose=pose)
    r = pyrender.OffscreenRenderer(size, size)
    try:
        color, _ = r.render(scene)
    finally:
        r.delete()
    return np.asarray(color[..., :3])


def mesh_sheet(pack, ids: list[str], size: int, committable_only: bool, drawn: list) -> np.ndarray:
    tiles = []
    for i in ids:
        e = pack.entry(i)
        if committable_only and not e.committable:
            continue
        m = pack.mesh(e)
        drawn.append(e)
        extent = 2.4 if m.size_m.max() <= 2.2 else float(m.size_m.max()) * 1.1
        x, y, z = m.size_m
        img = _render(m, size, extent)
        tiles.append(_caption(img, [f"{e.category}: {e.name}"[:30], f"{x:.2f} x {y:.2f} x {z:.2f} m, {e.split}",
                                    f"view {extent:.1f} m wide, bar 1 m"]))
    return _grid(tiles, 6)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("pack", type=Path)
    p.add_argument("--textures", type=Path)
    p.add_argument("--meshes", type=Path)
    p.add_argument("--mesh-ids", nargs="*", default=None)
    p.add_argument("--committable-only", action="store_true")
    p.add_argument("--tile", type=int, default=72)
    p.add_argument("--per-category", type=int, default=6)
    p.add_argument("--credits", type=Path, help="write a Markdown table of the drawn assets' licences and credits")
    args = p.parse_args(argv)

    from fruxel.render.images import write_image
    from fruxel.train.sim.assetpack import AssetPack

    pack = AssetPack(args.pack)
    drawn: list = []
    if args.textures:
        write_image(args.textures, texture_sheet(pack, args.tile, args.per_category, args.committable_only, drawn))
        print(f"wrote {args.textures}")
    if args.meshes:
        ids = args.mesh_ids or [e.id for cat in pack.categories("mesh") for e in pack.select("mesh", cat)[:1]]
        write_image(args.meshes, mesh_sheet(pack, ids, 200, args.committable_only, drawn))
        print(f"wrote {args.meshes}")
    if args.credits:
        rows = ["| asset | source | licence | credit |", "| --- | --- | --- | --- |"]
        rows += [f"| {e.id} | {e.source.package} {e.source.version} | {e.licence} | {e.credit} |" for e in drawn]
        args.credits.write_text("\n".join(rows) + "\n")
        print(f"wrote {args.credits}")
    return 0


if __name__ == "__main__":
    sys.exit(main())

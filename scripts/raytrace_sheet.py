"""A contact sheet of the ray-traced renderer, to look at: flat rooms dressed with the asset pack (the stand-in
of :mod:`fruxel.train.sim.raytrace.dressing`), each seen from a camera of its own (height 0.3-1.9 m, pitch -20 to
40 degrees down, roll within 10 degrees, at a point of the robot's trajectory), drawn without and with a camera
response drawn for the sample.

    python scripts/raytrace_sheet.py assets/pack --out out/raytrace.png [--rooms 8] [--size 256] [--seed 0]
        [--committable-only] [--credits out/credits.md] [--photos ../shared/real_photos] [--columns 2]

``--committable-only`` dresses with assets whose licence allows committing them (for sheets that go into docs/);
``--photos`` adds a last row of photos from a folder, centre-cropped to the same size, to compare by eye (never
for docs/: their licence is not the project's).
"""

from __future__ import annotations

import argparse
import math
from pathlib import Path

import numpy as np


def mount_pose(pose: np.ndarray, height: float, pitch: float, roll: float) -> np.ndarray:
    """A camera-to-world pose (OpenCV axes) at ``pose``'s floor position and heading, ``height`` metres up,
    pitched ``pitch`` degrees down and rolled ``roll`` degrees."""
    forward = pose[:3, 2]
    yaw = math.atan2(forward[1], forward[0])
    p, r = math.radians(pitch), math.radians(roll)
    z = np.array([math.cos(yaw) * math.cos(p), math.sin(yaw) * math.cos(p), -math.sin(p)])
    x = np.cross(z, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    y = np.cross(z, x)
    x, y = math.cos(r) * x + math.sin(r) * y, -math.sin(r) * x + math.cos(r) * y
    out = np.eye(4)
    out[:3, 0], out[:3, 1], out[:3, 2] = x, y, z
    out[:3, 3] = [pose[0, 3], pose[1, 3], height]
    return out


def render_rooms(pack_dir: str, rooms: int, size: int, seed: int, committable: bool,
                 used: set[str]) -> list[np.ndarray]:
    """Per room, its image without and with the camera response side by side, ``(size, 2 size, 3)`` uint8; the ids
    of the pack assets the rooms' materials name are added to ``used``."""
    from fruxel.grid import FruxelGrid
    from fruxel.train.sim.config import ImageConfig, SimConfig
    from fruxel.train.sim.raytrace import RaytraceConfig
    from fruxel.train.sim.raytrace.dressing import dress_scene
    from fruxel.train.sim.raytrace.renderer import RaytraceRenderer, open_pack
    from fruxel.train.sim.robot import TrajectoryError, random_trajectory
    from fruxel.train.sim.scene import RoomConfig, make_scene

    config = SimConfig(grid=FruxelGrid(64, 64, 64, 0.5, 8.0, 60.0), image=ImageConfig(size=size),
                       renderer="raytrace", room=RoomConfig(ceiling=True), assets=pack_dir, raytrace=RaytraceConfig())
    pack = open_pack(pack_dir)
    renderer = RaytraceRenderer(config)
    out, room = [], seed
    while len(out) < rooms:
        rng = np.random.default_rng([seed, room])
        scene = dress_scene(make_scene(room, config.room, config.classes), pack, room, committable=committable)
        try:
            poses = random_trajectory(scene, 4, room, **config.trajectory.kwargs()).poses
        except TrajectoryError:
            room += 1
            continue
        pose = mount_pose(poses[int(rng.integers(4))], rng.uniform(0.3, 1.9), rng.uniform(-20, 40),
                          rng.uniform(-10, 10))
        used.update(a for o in scene.objects for m in o.materials for a in (m.texture, m.image) if a is not None)
        renderer.set_scene(scene)
        plain = renderer.render(pose, None)
        out.append(np.concatenate([plain, renderer.render(pose, rng)], axis=1))
        room += 1
    renderer.close()
    return out


def photo_row(folder: Path, size: int, count: int) -> list[np.ndarray]:
    """Up to ``count`` pairs of photos from ``folder``, centre-cropped to ``size^2``."""
    from PIL import Image

    tiles = []
    for path in sorted(folder.glob("*.jpg"))[:2 * count]:
        with Image.open(path) as im:
            im = im.convert("RGB")
            s = size / min(im.size)
            im = im.resize((round(im.width * s), round(im.height * s)), Image.BILINEAR)
            left, top = (im.width - size) // 2, (im.height - size) // 2
            tiles.append(np.asarray(im.crop((left, top, left + size, top + size))))
    return [np.concatenate(tiles[i:i + 2], axis=1) for i in range(0, len(tiles) - 1, 2)]


def sheet(tiles: list[np.ndarray], columns: int, pad: int = 4) -> np.ndarray:
    """Tiles (all the same shape) in rows of ``columns`` on white."""
    h, w = tiles[0].shape[:2]
    rows = (len(tiles) + columns - 1) // columns
    out = np.full((rows * (h + pad) + pad, columns * (w + pad) + pad, 3), 255, np.uint8)
    for i, t in enumerate(tiles):
        r, c = divmod(i, columns)
        out[pad + r * (h + pad):pad + r * (h + pad) + h, pad + c * (w + pad):pad + c * (w + pad) + w] = t
    return out


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("pack", help="the asset pack folder (make assets)")
    p.add_argument("--out", type=Path, required=True, help="PNG to write")
    p.add_argument("--rooms", type=int, default=8)
    p.add_argument("--size", type=int, default=256)
    p.add_argument("--seed", type=int, default=0, help="first room's seed")
    p.add_argument("--columns", type=int, default=2, help="pairs per row")
    p.add_argument("--committable-only", action="store_true", help="only assets that may be committed")
    p.add_argument("--photos", type=Path, default=None, help="a folder of photos for a last row, to compare")
    p.add_argument("--credits", type=Path, help="write a Markdown table of the pack assets' licences and credits")
    args = p.parse_args(argv)
    from fruxel.render.images import write_image

    used: set[str] = set()
    tiles = render_rooms(args.pack, args.rooms, args.size, args.seed, args.committable_only, used)
    if args.photos is not None:
        tiles += photo_row(args.photos, args.size, args.columns)
    write_image(args.out, sheet(tiles, args.columns))
    print(f"raytrace_sheet: wrote {args.out}")
    if args.credits:
        args.credits.write_text(credits_table(args.pack, used))
        print(f"raytrace_sheet: wrote {args.credits}")
    return 0


def credits_table(pack_dir: str | Path, used: set[str]) -> str:
    """A Markdown table of the licence and credit of each pack asset in ``used`` (ids), sorted by id."""
    from fruxel.train.sim.assetpack import AssetPack

    pack = AssetPack(pack_dir, verify=False)
    rows = ["| asset | source | licence | credit |", "| --- | --- | --- | --- |"]
    rows += [f"| {e.id} | {e.source.package} {e.source.version} | {e.licence} | {e.credit} |"
             for e in (pack.entry(i) for i in sorted(used))]
    return "\n".join(rows) + "\n"


if __name__ == "__main__":
    raise SystemExit(main())

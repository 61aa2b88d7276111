"""Contact sheet of furnished rooms (the simulator's "home" world), to look at them: per room a plan seen from
above (ceiling left out) and views from cameras at several heights and pitches, drawn by pyrender with the rooms'
materials (textures tiled at metric scale by box projection, pictures stretched once, the scene's lights with
shadow maps, the ambient colour) and, with --labels, beside each view its visible solids in the class colours.

    python scripts/home_sheet.py --out sheet.png [--rooms 4] [--seed 0] [--split train] [--assets assets/pack]
                                 [--types living,bedroom] [--labels]

This is a look at layout and materials, not the training renderer (train/sim/images.py is the flat one, the
photoreal one lives behind the renderer seam).
"""

from __future__ import annotations

import argparse
import math
import os
from pathlib import Path

import numpy as np

os.environ.setdefault("PYOPENGL_PLATFORM", "egl")


def _uv(tri: np.ndarray, tile: float) -> np.ndarray:
    """Box projection: each face takes the two world axes most parallel to it, in tiles of ``tile`` metres."""
    n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    axis = np.argmax(np.abs(n), axis=1)
    pick = np.array([[1, 2], [0, 2], [0, 1]])[axis]
    p = tri.reshape(-1, 3)
    idx = np.repeat(pick, 3, axis=0)
    return np.take_along_axis(p, idx, axis=1) / tile


def _picture_uv(tri: np.ndarray) -> np.ndarray:
    """An image stretched once over the part: planar projection on its largest face's plane, v up."""
    p = tri.reshape(-1, 3)
    ext = p.max(axis=0) - p.min(axis=0)
    h_axis = 0 if ext[0] >= ext[1] else 1
    u = (p[:, h_axis] - p[:, h_axis].min()) / max(ext[h_axis], 1e-9)
    v = (p[:, 2] - p[:, 2].min()) / max(ext[2], 1e-9)
    n = np.cross(tri[0, 1] - tri[0, 0], tri[0, 2] - tri[0, 0])
    # Seen from the side the face looks to, u must run left to right.
    if (h_axis == 0 and n[1] > 0) or (h_axis == 1 and n[0] < 0):
        u = 1 - u
    return np.stack([u, v], 1)


def build_scene(scene, lib, pr, with_ceiling: bool = True):
    """A pyrender scene of a furnished room with its materials and lights."""
    ps = pr.Scene(bg_color=(0.75, 0.82, 0.9, 1.0), ambient_light=np.array(scene.ambient or (0.1,) * 3) * 4.0)
    textures: dict[str, object] = {}

    def tex(kind: str, ident: str):
        if ident not in textures:
            e = lib.pack.entry(ident)
            from fruxel.train.sim.assetpack.pack import read_rgb

            textures[ident] = pr.Texture(source=read_rgb(lib.root / e.files[kind]), source_channels="RGB")
        return textures[ident]

    for o in scene.objects:
        if o.name == "ceiling" and not with_ceiling:
            continue
        v, f = np.asarray(o.mesh.vertices), np.asarray(o.mesh.faces)
        parts = o.parts if o.parts is not None else np.zeros(len(f), dtype=np.int32)
        prims = []
        for k, m in enumerate(o.materials):
            sel = parts == k
            if not sel.any():
                continue
            tri = v[f[sel]]
            n = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
            n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
            kw = {}
            if m.texture is not None:
                kw["baseColorTexture"] = tex("albedo", m.texture)
                uv = _uv(tri, m.tile_m)
            elif m.image is not None:
                kw["baseColorTexture"] = tex("image", m.image)
                uv = _picture_uv(tri)
            else:
                uv = np.zeros((len(tri) * 3, 2))
            colour = np.array([*m.color, m.opacity])
            if m.emission > 0:
                kw["emissiveFactor"] = np.array(m.color) * min(m.emission, 1.0)
                if "baseColorTexture" in kw:
                    kw["emissiveTexture"] = kw["baseColorTexture"]
            mat = pr.MetallicRoughnessMaterial(baseColorFactor=colour, metallicFactor=m.metallic,
                                               roughnessFactor=m.roughness, doubleSided=True,
                                               alphaMode="BLEND" if m.opacity < 1 else "OPAQUE", **kw)
            prims.append(pr.Primitive(positions=tri.reshape(-1, 3), normals=np.repeat(n, 3, axis=0),
                                      texcoord_0=uv, material=mat))
        if prims:
            ps.add(pr.Mesh(prims), name=o.name)
    for light in scene.lights:
        c = np.array(light.color)
        if light.kind == "directional":
            ps.add(pr.DirectionalLight(color=c, intensity=light.intensity * 1.0), pose=light.pose)
        elif light.kind == "spot":
            ps.add(pr.SpotLight(color=c, intensity=light.intensity * 1.5, innerConeAngle=light.cone[0],
                                outerConeAngle=light.cone[1]), pose=light.pose)
        else:
            ps.add(pr.PointLight(color=c, intensity=light.intensity * 1.5), pose=light.pose)
    return ps


def label_scene(scene, pr):
    """The room's solids in their class colours (drawn unlit), the drawn-only surfaces left out."""
    ps = pr.Scene(bg_color=(0.0, 0.0, 0.0, 1.0), ambient_light=np.ones(3))
    palette = scene.classes.palette() / 255.0
    for o in scene.objects:
        if not o.solid:
            continue
        mat = pr.MetallicRoughnessMaterial(baseColorFactor=(*palette[o.label], 1.0), doubleSided=True)
        ps.add(pr.Mesh.from_trimesh(o.mesh, material=mat, smooth=False))
    return ps


def look(eye: np.ndarray, yaw: float, pitch_down: float) -> np.ndarray:
    """OpenGL camera-to-world pose at ``eye`` looking along ``yaw`` (from +x towards +y), pitched down."""
    f = np.array([math.cos(yaw) * math.cos(pitch_down), math.sin(yaw) * math.cos(pitch_down), -math.sin(pitch_down)])
    x = np.cross(f, [0.0, 0.0, 1.0])
    x /= np.linalg.norm(x)
    up = np.cross(x, f)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, up, -f, eye
    return pose


def _views(scene, rng: np.random.Generator, n: int) -> list[tuple[np.ndarray, float, float]]:
    free = scene.free_space.free_centres(0.3)
    centres = scene.free_space.cell_centres()[free]
    lx, ly, _ = scene.room_size
    heights, pitches = [0.45, 1.0, 1.5, 1.85], [-5.0, 10.0, 25.0, 40.0]
    out = []
    for k in range(n):
        p = centres[rng.integers(len(centres))] if len(centres) else np.array([lx / 2, ly / 2])
        target = np.array([rng.uniform(0.2, 0.8) * lx, rng.uniform(0.2, 0.8) * ly])
        d = target - p
        if np.linalg.norm(d) < 1.0:
            d = np.array([lx / 2, ly / 2]) - p + 1e-3
        out.append((np.array([p[0], p[1], heights[k % 4]]), math.atan2(d[1], d[0]), math.radians(pitches[k % 4])))
    return out


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--rooms", type=int, default=4)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--split", default="train")
    p.add_argument("--assets", default=None)
    p.add_argument("--views", type=int, default=4)
    p.add_argument("--size", type=int, default=320)
    p.add_argument("--types", default=None, help="room types, comma-separated, one room each in turn")
    p.add_argument("--labels", action="store_true", help="beside each view, its visible solids in class colours")
    args = p.parse_args()

    from PIL import Image, ImageDraw

    from fruxel.render.compat import import_pyrender
    from fruxel.train.sim.rooms import HomeConfig, library, make_home
    from fruxel.train.sim.rooms.home import describe

    pr = import_pyrender()
    lib = library(args.assets)
    w, hgt = args.size, args.size * 3 // 4
    renderer = pr.OffscreenRenderer(w, hgt)
    rows = []
    for r in range(args.rooms):
        seed = args.seed + r
        config = HomeConfig()
        if args.types:
            types = args.types.split(",")
            config = HomeConfig(room_types=(types[r % len(types)],))
        scene = make_home(seed, config, assets=lib, split=args.split)
        rng = np.random.default_rng(seed)
        tiles = [_plan(scene, lib, pr, renderer, w, hgt)]
        ps, ls = build_scene(scene, lib, pr), label_scene(scene, pr)
        cam = pr.PerspectiveCamera(yfov=math.radians(52), aspectRatio=w / hgt)
        node, label_node = ps.add(cam, pose=np.eye(4)), ls.add(cam, pose=np.eye(4))
        for eye, yaw, pitch in _views(scene, rng, args.views):
            ps.set_pose(node, look(eye, yaw, pitch))
            ls.set_pose(label_node, look(eye, yaw, pitch))
            colour, _ = renderer.render(ps, flags=pr.RenderFlags.SHADOWS_DIRECTIONAL | pr.RenderFlags.SHADOWS_SPOT)
            tile = Image.fromarray(colour)
            ImageDraw.Draw(tile).text((4, 4), f"h {eye[2]:.2f} m, pitch {math.degrees(pitch):.0f}", fill="white")
            tiles.append(np.asarray(tile))
            if args.labels:
                labels, _ = renderer.render(ls, flags=pr.RenderFlags.FLAT)
                tiles.append(labels)
        row = Image.fromarray(np.concatenate(tiles, axis=1))
        ImageDraw.Draw(row).text((4, hgt - 14), f"seed {seed}: {describe(scene)}"[:120], fill="yellow")
        rows.append(np.asarray(row))
    Image.fromarray(np.concatenate(rows, axis=0)).save(args.out)
    print(f"wrote {args.out}")


def _plan(scene, lib, pr, renderer, w: int, hgt: int) -> np.ndarray:
    """The room seen from straight above, its ceiling left out."""
    ps = build_scene(scene, lib, pr, with_ceiling=False)
    ps.add(pr.DirectionalLight(intensity=2.0), pose=look(np.zeros(3), 0.0, math.radians(89.9)))
    lx, ly, _ = scene.room_size
    mag = max(lx / 2 * hgt / w, ly / 2) + 0.4
    cam = pr.OrthographicCamera(xmag=mag * w / hgt, ymag=mag)
    pose = np.eye(4)
    pose[:3, 3] = [lx / 2, ly / 2, 20.0]
    ps.add(cam, pose=pose)
    colour, _ = renderer.render(ps)
    return colour


if __name__ == "__main__":
    main()

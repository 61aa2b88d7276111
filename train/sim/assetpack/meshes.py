"""Meshes for the asset pack: OBJ files with their material groups, OFF scans, decimation, canonical frame.

Sweet Home 3D models are OBJ files whose ``usemtl`` groups become the mesh's parts (one material each, so a
renderer can give every part its own material); :func:`read_obj` reads them with their MTL colours. Decimation
(:func:`decimate`) runs part by part with quadric edge collapse (``fast_simplification``), so parts keep their
faces apart, and spreads a face budget over the parts by their size. Everything here works in the canonical frame
of :mod:`fruxel.train.sim.assets` (metres, z up, footprint centred, standing on z = 0, front towards -y).
"""

from __future__ import annotations

import io
import posixpath
from collections.abc import Callable
from dataclasses import dataclass
from typing import IO

import numpy as np

from .manifest import AssetPackError

DEFAULT_COLOR = (200, 200, 200, 255)
"""Colour of a part whose material is missing or has no diffuse colour."""


@dataclass
class RawMesh:
    """A mesh on its way into the pack."""

    vertices: np.ndarray
    """``(V, 3)`` float64, metres, canonical frame."""
    faces: np.ndarray
    """``(F, 3)`` int64."""
    face_parts: np.ndarray
    """``(F,)`` int64 part index per face."""
    part_names: list[str]
    """``P`` material names."""
    part_colors: np.ndarray
    """``(P, 4)`` uint8 sRGB colour and opacity."""
    elevation_m: float = 0.0
    """Height above the floor the model is usually placed at (Sweet Home 3D's ``elevation``), metres."""


@dataclass
class _Material:
    color: tuple[int, int, int, int] = DEFAULT_COLOR
    texture: str | None = None


def _parse_mtl(text: str) -> dict[str, _Material]:
    out: dict[str, _Material] = {}
    cur: _Material | None = None
    for line in text.splitlines():
        tok = line.split()
        if not tok:
            continue
        key = tok[0]
        try:
            if key == "newmtl" and len(tok) > 1:
                cur = out.setdefault(" ".join(tok[1:]), _Material())
            elif cur is None:
                continue
            elif key == "Kd" and len(tok) >= 4:
                rgb = [int(round(min(max(float(x), 0.0), 1.0) * 255)) for x in tok[1:4]]
                cur.color = (rgb[0], rgb[1], rgb[2], cur.color[3])
            elif key in ("d", "Tr") and len(tok) >= 2:
                a = float(tok[1]) if key == "d" else 1.0 - float(tok[1])
                cur.color = (*cur.color[:3], int(round(min(max(a, 0.0), 1.0) * 255)))
            elif key == "map_Kd" and len(tok) > 1:
                cur.texture = tok[-1]
        except ValueError:
            continue  # a malformed material line keeps the defaults: colours are hints, not geometry
    return out


def _mean_color(data: bytes) -> tuple[int, int, int] | None:
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            im.draft("RGB", (64, 64))
            small = np.asarray(im.convert("RGB").resize((16, 16)), dtype=np.float64)
    except (OSError, ValueError, SyntaxError):
        return None
    m = small.reshape(-1, 3).mean(axis=0)
    return int(round(m[0])), int(round(m[1])), int(round(m[2]))


def read_obj(data: bytes, resolve: Callable[[str], bytes | None], label: str) -> RawMesh:
    """A Wavefront OBJ mesh with its ``usemtl`` groups as parts, in the file's own frame and units.

    Polygons are split into triangle fans; faces before any ``usemtl`` go to a part named ``default``. A part's
    colour is its texture's mean colour when the MTL names one that ``resolve`` finds, else the diffuse colour
    (``Kd``), with the MTL's opacity (``d`` or ``Tr``).

    Args:
        data: the OBJ file's bytes.
        resolve: reads a file the OBJ names (its MTL, textures) relative to its folder; None when missing.
        label: names the file in errors.

    Raises:
        AssetPackError: no vertices or faces, a malformed number or an index out of range.
    """
    verts: list[list[float]] = []
    tris: list[tuple[int, int, int]] = []
    parts: list[int] = []
    names: dict[str, int] = {}
    cur = -1
    mtl: dict[str, _Material] = {}
    try:
        for line in data.decode("utf-8", errors="replace").splitlines():
            if line.startswith("v "):
                verts.append([float(x) for x in line.split()[1:4]])
            elif line.startswith("f "):
                n = len(verts)
                idx = [int(t.split("/")[0]) for t in line.split()[1:]]
                idx = [i - 1 if i > 0 else n + i for i in idx]
                if cur < 0:
                    cur = names.setdefault("default", len(names))
                for k in range(1, len(idx) - 1):
                    tris.append((idx[0], idx[k], idx[k + 1]))
                    parts.append(cur)
            elif line.startswith("usemtl"):
                cur = names.setdefault(line[6:].strip() or "default", len(names))
            elif line.startswith("mtllib"):
                text = resolve(line[6:].strip())
                if text is not None:
                    mtl.update(_parse_mtl(text.decode("utf-8", errors="replace")))
    except ValueError as e:
        raise AssetPackError(f"{label}: malformed OBJ ({e})") from None
    v = np.asarray(verts, dtype=np.float64).reshape(-1, 3)
    f = np.asarray(tris, dtype=np.int64).reshape(-1, 3)
    if len(v) == 0 or len(f) == 0:
        raise AssetPackError(f"{label}: no vertices or faces")
    if f.min() < 0 or f.max() >= len(v) or not np.all(np.isfinite(v)):
        raise AssetPackError(f"{label}: face index out of range or non-finite vertex")
    colors = []
    for name in names:
        m = mtl.get(name, _Material())
        rgb = m.color[:3]
        if m.texture is not None and (tex := resolve(m.texture)) is not None:
            rgb = _mean_color(tex) or rgb
        colors.append((*rgb, m.color[3]))
    return RawMesh(v, f, np.asarray(parts, dtype=np.int64), list(names), np.asarray(colors, dtype=np.uint8))


def zip_resolver(zf: object, folder: str) -> Callable[[str], bytes | None]:
    """A ``resolve`` for :func:`read_obj`: files relative to ``folder`` inside an open zip archive."""

    def resolve(name: str) -> bytes | None:
        path = posixpath.normpath(posixpath.join(folder, name.replace("\\", "/")))
        try:
            return zf.read(path)  # type: ignore[attr-defined]
        except KeyError:
            return None

    return resolve


_UP = {"z": np.eye(3), "y": np.array([[1.0, 0, 0], [0, 0, -1.0], [0, 1.0, 0]]),
       "-y": np.array([[1.0, 0, 0], [0, 0, 1.0], [0, -1.0, 0]]),
       "x": np.array([[0, 0, -1.0], [0, 1.0, 0], [1.0, 0, 0]])}


def read_off_statue(fileobj: IO[bytes], height_m: float, up: str, label: str) -> RawMesh:
    """A scanned statue from an OFF file: turned so that ``up`` points along +z, scaled to ``height_m``, in the
    canonical frame, one part named ``statue``.

    Raises:
        AssetPackError: an unreadable file or an unknown ``up``.
    """
    import trimesh

    from fruxel.train.sim.assets import canonical_mesh

    if up not in _UP:
        raise AssetPackError(f"{label}: unknown up axis {up!r}")
    try:
        m = trimesh.load(fileobj, file_type="off", process=False, force="mesh")
    except Exception as e:  # noqa: BLE001 - trimesh raises many kinds of errors for bad files
        raise AssetPackError(f"{label}: cannot read OFF ({type(e).__name__}: {e})") from None
    v = np.asarray(m.vertices, dtype=np.float64) @ _UP[up].T
    v = v * (height_m / max(np.ptp(v[:, 2]), 1e-12))
    c = canonical_mesh(v, m.faces)
    f = np.asarray(c.faces, dtype=np.int64)
    return RawMesh(np.asarray(c.vertices), f, np.zeros(len(f), dtype=np.int64), ["statue"],
                   np.array([DEFAULT_COLOR], dtype=np.uint8))


def _compact(v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    used, inv = np.unique(f.ravel(), return_inverse=True)
    return v[used], inv.reshape(-1, 3)


def decimate(mesh: RawMesh, max_faces: int) -> RawMesh:
    """The mesh with at most about ``max_faces`` faces, each part simplified on its own.

    Each part keeps a share of the budget in proportion to its faces (at least its own count up to 12, so small
    parts like handles survive); parts are simplified by quadric edge collapse and their vertices are not shared.
    Degenerate faces (two equal corners) are dropped. Deterministic.

    Args:
        mesh: the mesh, metres.
        max_faces: the face budget.
    """
    import fast_simplification

    f_all = mesh.faces[(mesh.faces[:, 0] != mesh.faces[:, 1]) & (mesh.faces[:, 1] != mesh.faces[:, 2])
                       & (mesh.faces[:, 0] != mesh.faces[:, 2])]
    p_all = mesh.face_parts[(mesh.faces[:, 0] != mesh.faces[:, 1]) & (mesh.faces[:, 1] != mesh.faces[:, 2])
                            & (mesh.faces[:, 0] != mesh.faces[:, 2])]
    total = len(f_all)
    vs, fs, ps = [], [], []
    offset = 0
    for p in range(len(mesh.part_names)):
        f = f_all[p_all == p]
        if len(f) == 0:
            continue
        v, f = _compact(mesh.vertices, f)
        target = max(min(len(f), 12), int(round(len(f) * max_faces / total)))
        if target < len(f) and len(f) > 12:
            v32, f32 = fast_simplification.simplify(v.astype(np.float32), f.astype(np.int32),
                                                    target_reduction=1.0 - target / len(f))
            if len(f32) > 0:
                v, f = np.asarray(v32, dtype=np.float64), np.asarray(f32, dtype=np.int64)
        vs.append(v)
        fs.append(f + offset)
        ps.append(np.full(len(f), p, dtype=np.int64))
        offset += len(v)
    if not fs:
        raise AssetPackError("mesh has no faces left")
    used = sorted(set(np.concatenate(ps).tolist()))
    remap = np.full(len(mesh.part_names), -1, dtype=np.int64)
    remap[used] = np.arange(len(used))
    return RawMesh(np.concatenate(vs), np.concatenate(fs), remap[np.concatenate(ps)],
                   [mesh.part_names[i] for i in used], mesh.part_colors[used], mesh.elevation_m)

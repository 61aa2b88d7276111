"""A room as the flat arrays the ray tracer uploads: every triangle of every object in one list, each with its
material, a material table and the lights. numpy only (:mod:`.renderer` uploads them).

Materials
    Each object's :attr:`~fruxel.train.sim.scene.SceneObject.materials` (or, when it has none, one material made
    from its flat ``color``, ``metallic`` and ``roughness``, the colour read as sRGB) becomes one row of the table
    per (object, material); ``parts`` gives each face its row. A row's ``mode`` says how its colour varies:

    * 0, plain: the material's colour;
    * 1, texture: a pack texture tiled in world space by box projection at metric scale (:data:`TEXTURE`);
    * 2, image: a pack image stretched once over the part, by a planar projection onto the plane of the part's
      largest face (:func:`image_frame`).

World-space box projection (mode 1)
    A face takes the two world axes most parallel to it, chosen by the largest component ``a`` of its outward
    normal ``n`` (sign ``s``): ``a = x``: ``(u, v) = (s y, z)``; ``a = y``: ``(-s x, z)``; ``a = z``: ``(s x, y)``,
    in tiles (``u / tile width + offset``). The tangent ``dp/du`` and bitangent ``dp/dv`` then satisfy ``T x B =
    n``, so the texture reads unmirrored from outside and its normal map (x along u, y along v) bends the right
    way. Each row gets a fixed offset of its tiles (from a CRC of the object's name), so that objects sharing a
    texture do not share its seams.
"""

from __future__ import annotations

import math
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

import numpy as np

from fruxel.errors import FruxelError

PLAIN, TEXTURE, IMAGE = 0, 1, 2
"""Material modes (module docstring)."""
LIGHT_KINDS = {"directional": 0, "point": 1, "spot": 2}
"""Light kinds as the kernels number them."""

MATERIAL_FIELDS = ("color", "roughness", "metallic", "opacity", "emission", "mode", "albedo_layer", "normal_layer",
                   "scale", "offset", "origin", "axis_u", "axis_v", "axis_n")
"""The columns of :attr:`SceneArrays.materials`, the fields of the kernels' ``MaterialData``."""
LIGHT_FIELDS = ("kind", "radiance", "position", "direction", "cos_inner", "cos_outer", "radius", "shadows")
"""The columns of :attr:`SceneArrays.lights`, the fields of the kernels' ``LightData``."""


class SceneArraysError(FruxelError, ValueError):
    """A scene the ray tracer cannot draw (the message names the object)."""


@dataclass
class SceneArrays:
    """One room, flattened (world frame, z up, metres)."""

    vertices: np.ndarray
    """``(V, 3)`` float32, every object's vertices, object after object."""
    faces: np.ndarray
    """``(F, 3)`` int32 vertex indices into :attr:`vertices`, counter-clockwise seen from outside."""
    face_material: np.ndarray
    """``(F,)`` int32: each face's row of :attr:`materials`."""
    materials: dict[str, np.ndarray]
    """Columns by :data:`MATERIAL_FIELDS`, ``M`` rows: ``color`` ``(M, 3)`` float32 linear RGB; ``roughness``,
    ``metallic``, ``opacity``, ``emission`` ``(M,)`` float32; ``mode`` ``(M,)`` int32 (module docstring);
    ``albedo_layer``, ``normal_layer`` ``(M,)`` int32 texture layers (-1: none); ``scale`` ``(M, 2)`` float32
    tiles per metre along u and v (mode 1) or the reciprocal of the image's extent (mode 2); ``offset``
    ``(M, 2)`` float32 tile offset; ``origin``, ``axis_u``, ``axis_v``, ``axis_n`` ``(M, 3)`` float32 the image
    plane's corner and unit axes (mode 2; ``u`` right, ``v`` up, ``n`` its normal, world frame)."""
    lights: dict[str, np.ndarray]
    """Columns by :data:`LIGHT_FIELDS`, ``L`` rows: ``kind`` ``(L,)`` int32 (:data:`LIGHT_KINDS`); ``radiance``
    ``(L, 3)`` float32 colour times intensity; ``position`` ``(L, 3)``; ``direction`` ``(L, 3)`` the unit
    direction the light shines (its pose's -z axis); ``cos_inner``, ``cos_outer`` ``(L,)`` a spot's cone;
    ``radius`` ``(L,)`` metres (radians for a directional light); ``shadows`` ``(L,)`` int32 0/1."""
    objects: np.ndarray
    """``(F,)`` int32: each face's object index in the scene (for masks in tests and tools)."""
    portals: np.ndarray
    """``(P,)`` int32: the faces of glass (opacity < 1): the windows the light of what lies behind comes through."""
    portal_cdf: np.ndarray
    """``(P,)`` float32: the portals' cumulative share of their total area (the last is 1), for sampling by area."""
    portal_area: float
    """The portals' total area, square metres (0: none)."""


LayerLookup = Callable[[str, str], int]
"""``lookup(role, asset_id) -> layer``: the device texture layer of a pack asset, ``role`` one of ``"albedo"``,
``"normal"`` (textures) and ``"image"``."""


def srgb_to_linear(c: Any) -> np.ndarray:
    """sRGB values in [0, 1] to linear (the exact piecewise curve)."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def build_scene_arrays(scene: Any, layers: LayerLookup, tile_aspect: Callable[[str], float]) -> SceneArrays:
    """Flatten ``scene`` (a :class:`~fruxel.train.sim.scene.Scene`).

    Args:
        scene: the room.
        layers: the texture layer of each pack asset the materials name (see :data:`LayerLookup`).
        tile_aspect: a pack texture's tile height over its width (from its ``size_m``), asked after its layers.

    Raises:
        SceneArraysError: an object without faces, or ``parts`` that do not index its materials.
    """
    verts, faces, face_mat, objects = [], [], [], []
    rows: list[dict[str, Any]] = []
    n_v = 0
    for k, obj in enumerate(scene.objects):
        v = np.asarray(obj.mesh.vertices, dtype=np.float64)
        f = np.asarray(obj.mesh.faces, dtype=np.int64)
        if f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
            raise SceneArraysError(f"object {obj.name!r}: a mesh of triangles is needed, got faces {f.shape}")
        mats = tuple(obj.materials) or (_flat_material(obj),)
        parts = np.zeros(len(f), dtype=np.int64) if obj.parts is None else np.asarray(obj.parts)
        if parts.shape != (len(f),) or parts.min() < 0 or parts.max() >= len(mats):
            raise SceneArraysError(f"object {obj.name!r}: parts must be ({len(f)},) indices of its {len(mats)} "
                                   f"materials, got shape {parts.shape}")
        for m, mat in enumerate(mats):
            rows.append(_material_row(obj.name, m, mat, v, f[parts == m], layers, tile_aspect))
        face_mat.append(parts + len(rows) - len(mats))
        verts.append(v)
        faces.append(f + n_v)
        objects.append(np.full(len(f), k, dtype=np.int32))
        n_v += len(v)
    if not faces:
        raise SceneArraysError("the scene has no objects to draw")
    all_v, all_f = np.concatenate(verts), np.concatenate(faces)
    face_row = np.concatenate(face_mat)
    opacity = np.asarray([r["opacity"] for r in rows], dtype=np.float64)
    portals = np.nonzero(opacity[face_row] < 1.0)[0]
    tri = all_v[all_f[portals]]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    total = float(area.sum())
    return SceneArrays(
        vertices=np.ascontiguousarray(all_v, dtype=np.float32),
        faces=np.ascontiguousarray(all_f, dtype=np.int32),
        face_material=np.ascontiguousarray(face_row, dtype=np.int32),
        materials={name: np.asarray([r[name] for r in rows]) for name in MATERIAL_FIELDS},
        lights=light_columns(scene.lights),
        objects=np.concatenate(objects),
        portals=portals.astype(np.int32),
        portal_cdf=(np.cumsum(area) / total if total > 0 else np.zeros(0)).astype(np.float32),
        portal_area=total,
    )


def _flat_material(obj: Any) -> Any:
    from ..scene import Material

    rgba = np.asarray(obj.color, dtype=np.float64)
    return Material(color=tuple(float(c) for c in srgb_to_linear(rgba[:3])), roughness=float(obj.roughness),
                    metallic=float(obj.metallic), opacity=float(rgba[3]) if len(rgba) > 3 else 1.0)


def _material_row(name: str, index: int, mat: Any, v: np.ndarray, part_faces: np.ndarray, layers: LayerLookup,
                  tile_aspect: Callable[[str], float]) -> dict[str, Any]:
    """One row of the material table (columns :data:`MATERIAL_FIELDS`)."""
    row: dict[str, Any] = {
        "color": np.clip(np.asarray(mat.color, dtype=np.float32), 0.0, 1.0),
        "roughness": np.float32(np.clip(mat.roughness, 0.0, 1.0)),
        "metallic": np.float32(np.clip(mat.metallic, 0.0, 1.0)),
        "opacity": np.float32(np.clip(mat.opacity, 0.0, 1.0)),
        "emission": np.float32(max(float(mat.emission), 0.0)),
        "mode": np.int32(PLAIN), "albedo_layer": np.int32(-1), "normal_layer": np.int32(-1),
        "scale": np.ones(2, np.float32),
        "offset": tile_offset(name, index),
        "origin": np.zeros(3, np.float32), "axis_u": np.zeros(3, np.float32), "axis_v": np.zeros(3, np.float32),
        "axis_n": np.zeros(3, np.float32),
    }
    if mat.image is not None and len(part_faces):
        origin, axis_u, axis_v, axis_n, extent = image_frame(v, part_faces)
        row.update(mode=np.int32(IMAGE), albedo_layer=np.int32(layers("image", mat.image)), origin=origin,
                   axis_u=axis_u, axis_v=axis_v, axis_n=axis_n, scale=(1.0 / extent).astype(np.float32))
    elif mat.texture is not None:
        if not mat.tile_m > 0:
            raise SceneArraysError(f"object {name!r}: material {index} has tile_m {mat.tile_m!r}, must be > 0")
        albedo, normal = layers("albedo", mat.texture), layers("normal", mat.texture)
        height = mat.tile_m * tile_aspect(mat.texture)
        row.update(mode=np.int32(TEXTURE), albedo_layer=np.int32(albedo), normal_layer=np.int32(normal),
                   scale=np.array([1.0 / mat.tile_m, 1.0 / height], np.float32))
    return row


def tile_offset(name: str, index: int) -> np.ndarray:
    """``(2,)`` float32 in [0, 1): the tile offset of material ``index`` of object ``name`` (module docstring)."""
    crc = zlib.crc32(f"{name}/{index}".encode())
    return np.array([(crc & 0xFFFF) / 65536.0, (crc >> 16) / 65536.0], np.float32)


def image_frame(v: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, ...]:
    """The plane an image is stretched over: that of the part's largest face, spanned by the part's extent.

    ``u`` is horizontal (``z x n``, or world x on a level face) and ``v = n x u`` (so ``u x v = n``): the image
    stands upright read from the side ``n`` points to; the kernels mirror ``u`` for a ray from the other side, so
    it reads the same from either side.

    Args:
        v: ``(V, 3)`` float64 vertices, world frame.
        faces: ``(K, 3)`` int64 the part's faces (K >= 1).

    Returns:
        ``origin (3,)``, unit ``axis_u``, ``axis_v``, ``axis_n`` ``(3,)`` float32 and the extent ``(2,)`` float64
        (metres along u and v, at least 1 mm): image point ``(s, t)`` in [0, 1]^2 (t up) lies at ``origin + s
        extent_u axis_u + t extent_v axis_v``.
    """
    tri = v[faces]
    cross = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    n = cross[int(np.argmax(np.linalg.norm(cross, axis=1)))]
    n = n / max(np.linalg.norm(n), 1e-12)
    u = np.cross([0.0, 0.0, 1.0], n)
    if np.linalg.norm(u) < 1e-6:
        u = np.array([1.0, 0.0, 0.0]) - n * n[0]
    u /= np.linalg.norm(u)
    w = np.cross(n, u)
    pts = v[np.unique(faces)]
    su, sv = pts @ u, pts @ w
    extent = np.maximum([su.max() - su.min(), sv.max() - sv.min()], 1e-3)
    origin = su.min() * u + sv.min() * w + float(np.mean(pts @ n)) * n
    return (origin.astype(np.float32), u.astype(np.float32), w.astype(np.float32), n.astype(np.float32), extent)


def light_columns(lights: Any) -> dict[str, np.ndarray]:
    """The lights of a scene as the columns :data:`LIGHT_FIELDS` (see :attr:`SceneArrays.lights`).

    Raises:
        SceneArraysError: an unknown kind or a pose that is not ``(4, 4)``.
    """
    rows = []
    for n, light in enumerate(lights):
        if light.kind not in LIGHT_KINDS:
            raise SceneArraysError(f"light {n}: unknown kind {light.kind!r} (one of {list(LIGHT_KINDS)})")
        pose = np.asarray(light.pose, dtype=np.float64)
        if pose.shape != (4, 4) or not np.all(np.isfinite(pose)):
            raise SceneArraysError(f"light {n}: pose must be a finite (4, 4) matrix, got shape {pose.shape}")
        axis = -pose[:3, 2] / max(np.linalg.norm(pose[:3, 2]), 1e-12)
        inner, outer = (float(c) for c in light.cone)
        rows.append({
            "kind": LIGHT_KINDS[light.kind],
            "radiance": np.asarray(light.color, dtype=np.float64) * float(light.intensity),
            "position": pose[:3, 3], "direction": axis,
            "cos_inner": math.cos(min(inner, outer)), "cos_outer": math.cos(max(inner, outer)),
            "radius": max(float(light.radius), 0.0), "shadows": int(bool(light.shadows)),
        })
    shapes = {"kind": (np.int32, ()), "radiance": (np.float32, (3,)), "position": (np.float32, (3,)),
              "direction": (np.float32, (3,)), "cos_inner": (np.float32, ()), "cos_outer": (np.float32, ()),
              "radius": (np.float32, ()), "shadows": (np.int32, ())}
    return {name: np.asarray([r[name] for r in rows], dtype=dt).reshape(len(rows), *shape)
            for name, (dt, shape) in shapes.items()}

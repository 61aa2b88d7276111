"""A stand-in dressing for the old flat rooms: pack materials, glass, an outdoor view behind every window and soft
lights, so that the ray-traced renderer can be tested, benchmarked and looked at before the room generator
assigns materials itself. Not the room generator: it places nothing and labels nothing (the outdoor views are
drawn, never labelled).

Every group of objects (objects whose names differ only by their numbers: the four walls, the chairs, the door
frames) gets one material: a random pack texture of a random category (walls and ceilings: of :data:`PALE` with
probability 0.7; other objects: independent of the class), its tile at the
pack's size times 0.7-1.4, a pale random tint, random roughness, metal for a metal texture with probability 0.7.
Window glass becomes clear glass, and behind each window stands an emissive plane with a pack outdoor image, 1.5 m
out, 8 m by 5 m. Point lights get a radius of 2-8 cm and become spot lights pointing down with probability 0.3; the
sun gets an angular radius of 0.5-2 degrees.
"""

from __future__ import annotations

import dataclasses
import math
import re
from typing import Any

import numpy as np

from ..scene import Light, Material, Scene, SceneObject

PALE = ("concrete", "paint", "plaster", "wallpaper")
"""Categories walls and ceilings take with probability 0.7 (most rooms' walls are pale)."""
OUTDOOR_DISTANCE = 1.5
"""Metres from a window's glass to its outdoor view."""
OUTDOOR_SIZE = (8.0, 5.0)
"""Width and height of an outdoor view, metres."""


def dress_scene(scene: Scene, pack: Any, seed: int, split: str = "train", committable: bool = False) -> Scene:
    """``scene`` with pack materials, glass, outdoor views and soft lights (module docstring).

    Args:
        scene: a room of :func:`~fruxel.train.sim.scene.make_scene`.
        pack: the :class:`~fruxel.train.sim.assetpack.AssetPack` to draw textures and images from.
        seed: the dressing's random seed.
        split: the pack split to draw from (``"train"`` or ``"test"``).
        committable: draw only assets whose licence lets them be committed (for pictures that go into docs/).

    Returns:
        A new scene: the same solids in the same order (so the same labels), with materials, then one non-solid
        outdoor view per window.
    """
    rng = np.random.default_rng(seed)

    def entries(kind: str, category: str | None = None, of_split: str | None = split) -> list[Any]:
        return [e for e in pack.select(kind, category, of_split) if e.committable or not committable]

    textures = entries("texture")
    categories = sorted({e.category for e in textures})
    outdoor = entries("image", "outdoor") or entries("image", "outdoor", None)
    groups: dict[str, Material] = {}
    objects, views = [], []
    for obj in scene.objects:
        if obj.name.endswith("_glass"):
            glass = Material(color=(0.9, 0.95, 1.0), roughness=0.05, opacity=0.12)
            objects.append(dataclasses.replace(obj, materials=(glass,), parts=None))
            if outdoor:
                image = outdoor[int(rng.integers(len(outdoor)))]
                views.append(_outdoor_view(obj, scene, image.id, _sun(scene) * rng.uniform(0.5, 1.3)))
            continue
        key = re.sub(r"_\d+", "", obj.name)
        if key not in groups:
            pale = key in ("wall", "ceiling") and rng.uniform() < 0.7
            groups[key] = _random_material(rng, textures, [c for c in PALE if c in categories] if pale
                                           else categories)
        objects.append(dataclasses.replace(obj, materials=(groups[key],), parts=None))
    return dataclasses.replace(scene, objects=tuple(objects + views), lights=_soft_lights(scene.lights, rng))


def _random_material(rng: np.random.Generator, textures: list[Any], categories: list[str]) -> Material:
    category = categories[int(rng.integers(len(categories)))]
    choices = [e for e in textures if e.category == category]
    entry = choices[int(rng.integers(len(choices)))]
    tint = 1.0 - rng.uniform(0.0, 0.2) * rng.uniform(0.0, 1.0, size=3)
    metal = category == "metal" and rng.uniform() < 0.7
    return Material(color=tuple(float(c) for c in tint), texture=entry.id,
                    tile_m=float(entry.size_m[0] * rng.uniform(0.7, 1.4)), roughness=float(rng.uniform(0.35, 0.95)),
                    metallic=float(rng.uniform(0.7, 1.0)) if metal else 0.0)


def _sun(scene: Scene) -> float:
    """The scene's directional light intensity (1 without one)."""
    suns = [light.intensity for light in scene.lights if light.kind == "directional"]
    return float(max(suns)) if suns else 1.0


def _outdoor_view(glass: SceneObject, scene: Scene, image_id: str, emission: float) -> SceneObject:
    """An emissive rectangle with ``image_id`` behind the window whose glass is ``glass``, facing the room."""
    v = np.asarray(glass.mesh.vertices, dtype=np.float64)
    lo, hi = v.min(axis=0), v.max(axis=0)
    centre = (lo + hi) / 2
    axis = 0 if hi[0] - lo[0] < hi[1] - lo[1] else 1
    out = 1.0 if centre[axis] > float(scene.room_size[axis]) / 2 else -1.0
    plane = centre.copy()
    plane[axis] += out * (OUTDOOR_DISTANCE + (hi[axis] - lo[axis]) / 2)
    along = np.zeros(3)
    along[1 - axis] = 1.0
    w, h = OUTDOOR_SIZE
    corners = np.array([plane + sa * w / 2 * along + np.array([0.0, 0.0, sz * h / 2])
                        for sa, sz in ((-1, -1), (1, -1), (1, 1), (-1, 1))])
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    normal = np.cross(corners[1] - corners[0], corners[2] - corners[0])
    if normal[axis] * out > 0:  # make it face the room
        faces = faces[:, ::-1]
    import trimesh

    mesh = trimesh.Trimesh(corners, faces, process=False)
    material = Material(color=(1.0, 1.0, 1.0), image=image_id, roughness=1.0, emission=float(emission))
    return SceneObject(f"{glass.name}_outdoor", 0, mesh, (1.0, 1.0, 1.0, 1.0), 0.0, 1.0, materials=(material,),
                       solid=False)


def _soft_lights(lights: tuple[Light, ...], rng: np.random.Generator) -> tuple[Light, ...]:
    out = []
    for light in lights:
        if light.kind == "directional":
            out.append(dataclasses.replace(light, radius=math.radians(rng.uniform(0.5, 2.0))))
            continue
        radius, spot = rng.uniform(0.02, 0.08), rng.uniform() < 0.3
        if not spot:
            out.append(dataclasses.replace(light, radius=radius))
            continue
        pose = np.asarray(light.pose, dtype=np.float64).copy()
        pose[:3, :3] = np.eye(3)  # local -z is world -z: shining down
        cone = (math.radians(rng.uniform(20, 35)), math.radians(rng.uniform(40, 60)))
        out.append(dataclasses.replace(light, kind="spot", pose=pose, cone=cone, radius=radius,
                                       intensity=light.intensity * 2.0))
    return tuple(out)

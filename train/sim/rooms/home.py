"""``make_home``: one furnished room from a seed (the simulator's ``"home"`` world).

Steps, in this order (every random draw comes from ``numpy.random.default_rng(seed)`` in this order, so the same
seed, config, class table and asset pack give the same scene, bit for bit):

1. the room type (:data:`.config.ROOM_TYPES`), the interior size and the wall thickness;
2. the openings and the shell (:mod:`.shell`): floor, ceiling, walls, baseboards, crown, windows, doors, halls;
3. radiators and curtains at the windows (:mod:`.decor`);
4. the furniture by room type, the extras, floor plants and lamps, sculptures (:mod:`.furnish`);
5. rugs (raising what stands on them), ceiling fixtures, what stands on the furniture, what hangs on the walls
   (:mod:`.decor`);
6. the lights and the ambient colour (:mod:`.lights`);
7. the scene: objects in ``fruxelize`` priority order (:data:`.draft.LAYERS`: structure, trim, windows, doors,
   rugs, furniture, sculptures, objects, then the drawn-only views), each labelled by its class name's index in
   the given class table, and the robot's free-space map from the footprints of the solids that stand on the
   floor (furniture, sculptures, floor plants and lamps, open door leaves, floor-length curtains, radiators; not
   rugs, not what stands on furniture or hangs on walls and ceiling).

Every surface's material is drawn by :mod:`.materials`, independently of its class.
"""

from __future__ import annotations

import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from typing import Any

import numpy as np

from fruxel.classes import HOME_CLASSES, ClassTable

from ..scene import Scene, SceneError, SceneObject, _free_space, _make_mesh, _walls
from . import decor, furnish, shell
from .config import HomeConfig
from .draft import LAYERS, Home, Piece, flat_colour
from .library import Library, library
from .lights import lights as room_lights
from .materials import MaterialSampler

CLASS_NAMES = ("wall", "floor", "window", "furniture", "door", "sculpture", "ceiling", "object")
"""The classes a furnished room labels its solids with, by name; the scene's class table must hold each."""

STAGES = ("shell", "windows", "furniture", "rugs", "dressing", "walls", "lights", "objects", "free_space")
"""Stages :func:`make_home` times (seconds add up in the ``timings`` dictionary it is given)."""


def class_ids(classes: ClassTable) -> dict[str, int]:
    """The label of each class a furnished room draws, ``"empty"`` (for drawn-only surfaces) included.

    Raises:
        SceneError: ``classes`` lacks one of :data:`CLASS_NAMES`.
    """
    missing = [n for n in CLASS_NAMES if n not in classes.names]
    if missing:
        raise SceneError(f"the class table lacks the furnished rooms' classes {missing} (it has "
                         f"{list(classes.names)}); use fruxel.classes.HOME_CLASSES")
    return {n: classes.index(n) for n in ("empty", *CLASS_NAMES)}


@contextmanager
def _stage(timings: dict[str, float] | None, name: str) -> Iterator[None]:
    t0 = time.perf_counter()
    yield
    if timings is not None:
        timings[name] = timings.get(name, 0.0) + time.perf_counter() - t0


def make_home(seed: int, config: HomeConfig | None = None, classes: ClassTable = HOME_CLASSES, *,
              assets: str | os.PathLike[str] | Library | None = None, split: str = "train",
              timings: dict[str, float] | None = None) -> Scene:
    """A furnished room (module docstring).

    Args:
        seed: any integer; the only source of randomness.
        config: the ranges drawn from (None: ``HomeConfig()``).
        classes: the class table whose ids label the solids.
        assets: the asset pack: a folder (:func:`.library.resolve_pack` finds one when None) or a loaded library.
        split: the data split the room belongs to; with ``config.test_assets`` it decides which pack split the
            room's meshes, textures and pictures come from (:meth:`HomeConfig.asset_split`).
        timings: a dictionary the seconds of each stage of :data:`STAGES` are added to, or None.

    Returns:
        The :class:`fruxel.train.sim.scene.Scene` (world frame z up, metres, interior ``[0, Lx] x [0, Ly] x
        [0, Lz]``), with ``Scene.ambient`` set.

    Raises:
        SceneError: a class table without the furnished rooms' classes.
        ConfigError: no asset pack where it was looked for. AssetPackError: a malformed pack.
    """
    cfg = config if config is not None else HomeConfig()
    ids = class_ids(classes)
    lib = assets if isinstance(assets, Library) else library(assets)
    asset_split = cfg.asset_split(split)
    rng = np.random.default_rng(seed)
    with _stage(timings, "shell"):
        room_type = cfg.room_types[int(rng.integers(len(cfg.room_types)))]
        lx, ly, lz, tw = (float(rng.uniform(*r)) for r in (cfg.length_range, cfg.width_range, cfg.height_range,
                                                          cfg.wall_thickness_range))
        h = Home(rng, cfg, lib, asset_split, lx, ly, lz, tw, _walls(lx, ly, tw),
                 MaterialSampler(rng, cfg.materials, lib, asset_split))
        shell.openings(h)
        shell.build(h)
    with _stage(timings, "windows"):
        decor.radiators(h)
        decor.curtains(h)
    with _stage(timings, "furniture"):
        furnish.furnish(h, room_type)
    with _stage(timings, "rugs"):
        decor.rugs(h)
        decor.ceiling_lamps(h)
    with _stage(timings, "dressing"):
        decor.dress(h)
    with _stage(timings, "walls"):
        decor.wall_art(h)
    with _stage(timings, "lights"):
        lights, ambient = room_lights(h)
    with _stage(timings, "objects"):
        pieces = sorted(h.pieces, key=lambda p: LAYERS.index(p.layer))
        label_meshes = _label_meshes(pieces, lib, cfg.label_thickness, cfg.filled_solids)
        objects = tuple(_object(p, ids, lib, m) for p, m in zip(pieces, label_meshes, strict=True))
    with _stage(timings, "free_space"):
        free = _free_space(lx, ly, [p.slot.fp for p in h.pieces if _blocks(p)], cfg.free_space_resolution)
    return Scene(objects, np.array([lx, ly, lz]), tuple(lights), free, int(seed), classes, ambient=ambient)


def _blocks(p: Piece) -> bool:
    """Whether a piece is in the robot's way: a solid standing on (or reaching down to) the floor."""
    return p.solid and p.slot is not None and p.layer != "rug" and p.mount not in ("support", "ceiling") \
        and p.slot.z0 < 0.3


def _object(p: Piece, ids: dict[str, int], lib: Library, label_mesh: tuple[np.ndarray, np.ndarray] | None
            ) -> SceneObject:
    counts = np.bincount(p.parts, minlength=len(p.materials))
    main = p.materials[int(np.argmax(counts))]
    return SceneObject(p.name, ids[p.label], _make_mesh(p.vertices, p.faces), flat_colour(p, lib),
                       float(main.metallic), float(main.roughness), tuple(p.materials),
                       np.ascontiguousarray(p.parts, dtype=np.int32), p.solid,
                       p.prop.asset if p.prop is not None else None, label_mesh)


def _label_meshes(pieces: list[Piece], lib: Library, thickness: float, filled: bool = True
                  ) -> list[tuple[np.ndarray, np.ndarray] | None]:
    """Per piece, the solid it is labelled by when it is not its mesh (:mod:`.solids`), or None.

    With ``filled``, a piece made from a pack mesh that is not closed is labelled by the mesh's filled solid, placed
    as the piece is (the affine map from the pack mesh to the piece's vertices: rotation, position, lift, scale; a
    piece that is more than its prop, a statue on a pedestal, keeps its mesh); then the thin upright parts of doors,
    windows, furniture, sculptures and objects are thickened to ``thickness`` (0: none), all pieces in one call.
    """
    from .solids import THICKENED_LABELS, affine_map, thicken_slabs

    bases: list[tuple[np.ndarray, np.ndarray, bool]] = []
    for p in pieces:
        v, f = np.asarray(p.vertices, dtype=np.float64), np.asarray(p.faces, dtype=np.int64)
        is_filled = False
        if filled and p.solid and p.prop is not None and p.prop.asset:
            solid = lib.solid(p.prop.asset)
            m = None if solid is None else affine_map(lib.prop(p.prop.asset).vertices, v)
            if m is not None:
                v, f, is_filled = np.column_stack([solid[0], np.ones(len(solid[0]))]) @ m, solid[1], True
        bases.append((v, f, is_filled))
    thin = [k for k, p in enumerate(pieces) if p.solid and p.label in THICKENED_LABELS]
    out: list[tuple[np.ndarray, np.ndarray] | None] = [(v, f) if is_filled else None for v, f, is_filled in bases]
    if thin:
        offsets = np.cumsum([0] + [len(bases[k][0]) for k in thin])
        stacked = thicken_slabs(np.concatenate([bases[k][0] for k in thin]),
                                np.concatenate([bases[k][1] + o for k, o in zip(thin, offsets, strict=False)]),
                                thickness)
        for k, a, b in zip(thin, offsets[:-1], offsets[1:], strict=True):
            v = stacked[a:b]
            if bases[k][2] or not np.array_equal(v, bases[k][0]):
                out[k] = (v, bases[k][1])
    return out


def describe(scene: Scene) -> dict[str, Any]:
    """Counts of a room's objects per class name and its size (for logs and tests)."""
    names = scene.classes.names
    out: dict[str, Any] = {"size": [round(float(v), 2) for v in scene.room_size], "lights": len(scene.lights)}
    for o in scene.objects:
        key = names[o.label] if o.solid else "drawn only"
        out[key] = out.get(key, 0) + 1
    return out


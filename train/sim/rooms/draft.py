"""A furnished room while it is being made: its pieces, the space they take and the checks that keep them apart.

Space (:class:`Slot`)
    Every placed piece takes a *slot*: the rotated rectangle of its footprint on the floor (world xy) and the
    height range ``[z0, z1]`` it fills. Two slots collide when their rectangles, grown by ``HomeConfig.min_gap``,
    overlap *and* their height ranges overlap, so a painting hangs above a sofa and a pendant above a table, but
    two chairs never interpenetrate. Doors keep the floor in front of them free (a keep-out slot as deep as the
    leaf is wide, up to 2.2 m high), windows keep their height range free in front of the glass, so tall furniture
    never blocks them while a low sideboard may stand under a sill.

Walls
    The four walls of :func:`fruxel.train.sim.scene._walls` (wall frame: x along the inner face, y outwards through
    the wall, z up; walls 0 and 2 run along world x and cover the corners). Wall ``k``'s interior spans
    :meth:`Home.inner` along its x. A piece stands *against* a wall with its back (+y of its canonical frame)
    towards it, in front of the baseboard.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from ..scene import Material, _Footprint, _overlap, _Wall
from .config import HomeConfig
from .library import Library, Prop
from .materials import MaterialSampler, linear_to_srgb
from .supports import Level

SUPPORT_ROLES = frozenset({"dining_table", "small_table", "coffee_table", "side_table", "nightstand", "desk",
                           "dresser", "shelf", "cabinet", "tv_unit", "kitchen_upper", "worktop", "piano",
                           "fireplace", "wardrobe"})
"""Roles whose tops and shelves get things put on them (not beds, seats or appliances)."""

LAYERS = ("structure", "trim", "window", "door", "rug", "furniture", "sculpture", "object", "view")
"""``fruxelize`` priority of the pieces (later wins where solids touch), by layer: the scene's object order."""


@dataclass
class Slot:
    """Space a piece takes (module docstring)."""

    fp: _Footprint
    """Rotated rectangle on the floor, world xy."""
    z0: float
    """Lowest height filled, metres."""
    z1: float
    """Highest height filled, metres."""
    kind: str = "piece"
    """``piece`` (furniture and things on the floor), ``fixed`` (a piece rugs keep away from: kitchen runs,
    radiators, curtains), ``keepout`` (in front of a door), ``window`` (in front of the glass), ``leaf`` (an open
    door leaf, inside its door's keep-out) or ``rug``."""
    box: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    """``(xmin, ymin, xmax, ymax)`` of :attr:`fp`, world (filled on creation): a fast first test."""

    def __post_init__(self) -> None:
        xs, ys = zip(*self.fp.corners().tolist(), strict=True)
        self.box = (min(xs), min(ys), max(xs), max(ys))

    def meets(self, other: Slot, gap: float) -> bool:
        """Whether the two slots collide (module docstring)."""
        if not (self.z0 < other.z1 and other.z0 < self.z1):
            return False
        a, b = self.box, other.box
        if a[0] > b[2] + gap or b[0] > a[2] + gap or a[1] > b[3] + gap or b[1] > a[3] + gap:
            return False
        return _overlap(self.fp, other.fp, gap)


@dataclass(eq=False)
class Piece:
    """One object of the room, with what the generator still needs to know about it."""

    name: str
    """Unique name in the room (role and number: ``bed_0``, ``window_1_glass``)."""
    label: str
    """Class name it is labelled as (``wall``, ``floor``, ``ceiling``, ``window``, ``door``, ``furniture``,
    ``sculpture``, ``object``)."""
    vertices: np.ndarray
    """``(V, 3)`` float64 world frame, metres."""
    faces: np.ndarray
    """``(F, 3)`` int64."""
    parts: np.ndarray
    """``(F,)`` int32 material index of each face."""
    materials: list[Material]
    """Its materials."""
    layer: str
    """One of :data:`LAYERS`."""
    mount: str = "structure"
    """How it is held: ``structure`` (floor, walls, ceiling, openings), ``floor``, ``rug``, ``wall``, ``ceiling``,
    ``support`` (stands on another piece)."""
    slot: Slot | None = None
    """The space it takes (None for structure)."""
    solid: bool = True
    """False: drawn only (the outdoor view)."""
    role: str = ""
    """Its role (:data:`fruxel.train.sim.rooms.library.ROLES` or a structure name)."""
    prop: Prop | None = None
    """The mesh it was made from, if any."""
    pose: tuple[float, float, float, float] = (0.0, 0.0, 0.0, 0.0)
    """``(x, y, z, yaw)``: where the prop's canonical frame sits in the world."""
    levels: list[Level] = field(default_factory=list)
    """Its support surfaces for this room (fresh copies), when things may stand on it."""
    wants: list[str] = field(default_factory=list)
    """Roles to put on it first when it is dressed (a lamp on a nightstand, a TV on a TV unit)."""


@dataclass(eq=False)
class Home:
    """The room being made (module docstring). Every random draw comes from :attr:`rng`, in the generator's order."""

    rng: np.random.Generator
    """The room's generator."""
    cfg: HomeConfig
    """The settings."""
    lib: Library
    """The asset pack."""
    split: str
    """The asset split drawn from."""
    lx: float
    """Interior length along x, metres."""
    ly: float
    """Interior width along y, metres."""
    lz: float
    """Interior height, metres."""
    tw: float
    """Wall thickness, metres."""
    walls: list[_Wall]
    """The four walls."""
    sampler: MaterialSampler
    """The room's material sampler."""
    pieces: list[Piece] = field(default_factory=list)
    """Everything made so far."""
    slots: list[Slot] = field(default_factory=list)
    """Space taken (module docstring)."""
    baseboard: float = 0.0
    """Thickness of the baseboards (0: none), metres."""
    baseboard_height: float = 0.0
    """Height of the baseboards (0: none), metres."""
    counts: dict[str, int] = field(default_factory=dict)
    """Pieces named so far per role."""
    lights: list[Any] = field(default_factory=list)
    """Light fixtures that may be lit: ``(kind, position (3,), piece)`` tuples (:mod:`.lights`)."""
    doors: list[Any] = field(default_factory=list)
    """The doors made (:mod:`.shell`)."""
    windows: list[Any] = field(default_factory=list)
    """The windows made (:mod:`.shell`)."""
    rug_spots: list[Any] = field(default_factory=list)
    """Rugs the furniture groups ask for: ``(centre (2,), yaw, width, depth)`` (:mod:`.decor` lays them)."""
    pendants: list[Any] = field(default_factory=list)
    """World xy where a pendant light belongs (above a dining table)."""
    small_sculptures: list[Any] = field(default_factory=list)
    """Small statues left for furniture tops: ``(prop, role, scale)``."""

    # -------------------------------------------------------------------------------------------- naming
    def name(self, role: str) -> str:
        """A fresh name for a piece of ``role``: ``role_N``."""
        n = self.counts.get(role, 0)
        self.counts[role] = n + 1
        return f"{role}_{n}"

    # -------------------------------------------------------------------------------------------- space
    def inner(self, k: int) -> tuple[float, float]:
        """The range of wall ``k``'s x that faces the interior."""
        return (self.tw, self.tw + self.lx) if k % 2 == 0 else (0.0, self.ly)

    def inside(self, fp: _Footprint, margin: float = 0.005) -> bool:
        """Whether the rectangle lies in the interior (``margin`` from the walls' inner faces)."""
        c = fp.corners().tolist()
        return (min(min(x, y) for x, y in c) >= margin and max(x for x, _ in c) <= self.lx - margin
                and max(y for _, y in c) <= self.ly - margin)

    def fits(self, fp: _Footprint, z0: float, z1: float, gap: float | None = None, wall_margin: float = 0.005,
             ignore: tuple[str, ...] = ("rug",), skip: Slot | None = None) -> bool:
        """Whether a piece filling ``fp`` from ``z0`` to ``z1`` is inside the room and clear of every slot but
        those of the kinds in ``ignore`` and ``skip`` (the support a thing stands on)."""
        g = self.cfg.min_gap if gap is None else gap
        if z1 > self.lz + 1e-6:
            return False
        # Low pieces keep clear of the baseboards too.
        margin = max(wall_margin, self.baseboard + 0.003) if z0 < self.baseboard_height else wall_margin
        if not self.inside(fp, margin):
            return False
        probe = Slot(fp, z0, z1)
        return not any(s.kind not in ignore and s is not skip and probe.meets(s, g) for s in self.slots)

    def against(self, k: int, s: float, width: float, depth: float, gap: float = 0.01
                ) -> tuple[np.ndarray, float, _Footprint]:
        """Pose of a piece with its back to wall ``k`` at ``s`` along it (in front of the baseboard).

        Returns:
            Centre ``(2,)`` world xy, yaw (the canonical frame's rotation) and the footprint rectangle.
        """
        wall = self.walls[k]
        yaw = math.atan2(wall.normal[1], wall.normal[0]) - math.pi / 2
        centre = wall.start + s * wall.along - wall.normal * (self.baseboard + gap + depth / 2)
        return centre, yaw, _Footprint(float(centre[0]), float(centre[1]), width / 2, depth / 2, yaw)

    # -------------------------------------------------------------------------------------------- materials
    def dress(self, prop: Prop, body: str, shared: dict[Any, Material] | None = None
              ) -> tuple[np.ndarray, list[Material]]:
        """Materials for a prop's parts (:mod:`.materials`): parts of one role and one source colour share one.

        Args:
            prop: the mesh.
            body: the role of parts whose names say nothing.
            shared: materials already drawn for a set of equal pieces (chairs of one table), by part key; filled.

        Returns:
            ``(F,)`` int32 material index per face, and the materials.
        """
        cache = {} if shared is None else shared
        index: dict[Any, int] = {}
        mats: list[Material] = []
        remap = np.zeros(len(prop.part_roles), dtype=np.int32)
        for p in np.unique(prop.parts):
            role = prop.part_roles[p] or body
            colour = prop.part_colours[p]
            if role == "any" and self.rng.uniform() < self.cfg.materials.source_colour:
                role = "keep"
            key = (role, tuple(np.round(colour, 2)) if role in ("keep", "any") else p if role == "glass" else None)
            if key not in cache:
                cache[key] = self.sampler.draw(role, colour)
            if key not in index:
                index[key] = len(mats)
                mats.append(cache[key])
            remap[p] = index[key]
        return remap[prop.parts], mats

    # -------------------------------------------------------------------------------------------- pieces
    def add(self, piece: Piece) -> Piece:
        """Record a piece (and its slot)."""
        self.pieces.append(piece)
        if piece.slot is not None:
            self.slots.append(piece.slot)
        return piece

    def add_box_piece(self, role: str, label: str, layer: str, parts: Sequence[tuple[np.ndarray, np.ndarray]],
                      materials: Sequence[Material], name: str | None = None, mount: str = "structure",
                      slot: Slot | None = None) -> Piece:
        """A piece from meshes already in the world frame, one material per mesh of ``parts``."""
        vs, fs, ps, n = [], [], [], 0
        for k, (v, f) in enumerate(parts):
            vs.append(np.asarray(v, dtype=np.float64))
            fs.append(np.asarray(f, dtype=np.int64) + n)
            ps.append(np.full(len(f), k, dtype=np.int32))
            n += len(v)
        return self.add(Piece(name or self.name(role), label, np.concatenate(vs), np.concatenate(fs),
                              np.concatenate(ps), list(materials), layer, mount, slot, role=role))

    def place(self, prop: Prop, role: str, label: str, layer: str, x: float, y: float, z: float, yaw: float,
              mount: str, body: str, shared: dict[Any, Material] | None = None, slot: Slot | None = None) -> Piece:
        """Put a prop into the room: its canonical frame rotated by ``yaw`` about z and moved to ``(x, y, z)``."""
        c, s = math.cos(yaw), math.sin(yaw)
        r = np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])
        v = prop.vertices @ r.T + np.array([x, y, z])
        parts, mats = self.dress(prop, body, shared)
        levels = [lv.fresh() for lv in prop.levels()] if mount in ("floor", "rug", "wall") and \
            role in SUPPORT_ROLES else []
        return self.add(Piece(self.name(role), label, v, prop.faces, parts, mats, layer, mount, slot, role=role,
                              prop=prop, pose=(x, y, z, yaw), levels=levels))


def footprint_of(prop: Prop, x: float, y: float, yaw: float, grow: float = 0.0) -> _Footprint:
    """The rotated rectangle a prop covers on the floor at ``(x, y)`` turned by ``yaw``."""
    size = prop.size
    return _Footprint(float(x), float(y), float(size[0] / 2 + grow), float(size[1] / 2 + grow), float(yaw))


def flat_colour(piece: Piece, lib: Library) -> tuple[float, float, float, float]:
    """The colour the flat renderer draws a piece in: its most used material's tint times its texture's mean
    colour, sRGB, with the material's opacity."""
    counts = np.bincount(piece.parts, minlength=len(piece.materials))
    m = piece.materials[int(np.argmax(counts))]
    colour = np.asarray(m.color, dtype=np.float64)
    if m.texture is not None:
        colour = colour * lib.texture_colour(m.texture)
    elif m.image is not None:
        colour = colour * 0.5
    srgb = linear_to_srgb(colour)
    return (float(srgb[0]), float(srgb[1]), float(srgb[2]), float(m.opacity))

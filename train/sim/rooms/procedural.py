"""Pieces built from boxes, cylinders and spheres, for the roles a pack split has no mesh for (a tiny test pack, a
held-out split without floor lamps) or when ``HomeConfig.procedural`` asks for one.

Each builder returns a :class:`~.library.Prop` in the canonical frame (metres, z up, footprint centred on the
origin, standing on z = 0, front towards -y), made of closed, outward components that touch but do not overlap
(statues and foliage excepted: their pieces overlap, which ``fruxelize``'s non-zero rule makes one solid), with a
material role per part (:mod:`.materials`). Sizes are real-world ones drawn per piece.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np

from ..scene import _sculpture, boxes
from .library import Prop
from .materials import srgb_to_linear


class _Parts:
    """Components collected per part, turned into a :class:`Prop`."""

    def __init__(self, roles: tuple[str, ...], colours: tuple[tuple[float, float, float], ...] | None = None
                 ) -> None:
        self.roles = roles
        self.colours = colours or tuple((0.6, 0.6, 0.6) for _ in roles)
        self.pieces: list[tuple[np.ndarray, np.ndarray, int]] = []

    def box(self, lo: list[float], hi: list[float], part: int) -> None:
        v, f = boxes([lo], [hi])
        self.pieces.append((v, f, part))

    def mesh(self, v: np.ndarray, f: np.ndarray, part: int) -> None:
        self.pieces.append((np.asarray(v, dtype=np.float64), np.asarray(f, dtype=np.int64), part))

    def cylinder(self, radius: float, z0: float, z1: float, part: int, x: float = 0.0, y: float = 0.0,
                 sections: int = 16, top_radius: float | None = None) -> None:
        """A closed (truncated) cone along z: radius at z0, ``top_radius`` (default the same) at z1."""
        a = np.linspace(0.0, 2 * math.pi, sections, endpoint=False)
        r1 = radius if top_radius is None else top_radius
        ring0 = np.stack([x + radius * np.cos(a), y + radius * np.sin(a), np.full(sections, z0)], 1)
        ring1 = np.stack([x + r1 * np.cos(a), y + r1 * np.sin(a), np.full(sections, z1)], 1)
        v = np.concatenate([ring0, ring1, [[x, y, z0], [x, y, z1]]])
        i = np.arange(sections)
        j = (i + 1) % sections
        c0, c1 = 2 * sections, 2 * sections + 1
        f = np.concatenate([np.stack([i, j, j + sections], 1), np.stack([i, j + sections, i + sections], 1),
                            np.stack([np.full(sections, c0), j, i], 1),
                            np.stack([np.full(sections, c1), i + sections, j + sections], 1)])
        self.mesh(v, f, part)

    def sphere(self, centre: list[float], radius: np.ndarray | float, part: int) -> None:
        import trimesh

        s = trimesh.creation.icosphere(subdivisions=1)
        self.mesh(np.asarray(s.vertices) * radius + np.asarray(centre), np.asarray(s.faces), part)

    def prop(self, name: str) -> Prop:
        vs, fs, ps, n = [], [], [], 0
        for v, f, part in self.pieces:
            vs.append(v)
            fs.append(f + n)
            ps.append(np.full(len(f), part, dtype=np.int32))
            n += len(v)
        v = np.concatenate(vs)
        lo, hi = v.min(axis=0), v.max(axis=0)
        v = v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
        roles = tuple(None if r == "body" else r for r in self.roles)
        return Prop(name, None, v, np.concatenate(fs), np.concatenate(ps), roles,
                    srgb_to_linear(np.asarray(self.colours, dtype=np.float64)))


def _legs(b: _Parts, w: float, d: float, h: float, leg: float, inset: float, part: int) -> None:
    for sx in (-1, 1):
        for sy in (-1, 1):
            x, y = sx * (w / 2 - inset - leg / 2), sy * (d / 2 - inset - leg / 2)
            b.box([x - leg / 2, y - leg / 2, 0.0], [x + leg / 2, y + leg / 2, h], part)


def table(rng: np.random.Generator, w: float, d: float, h: float) -> Prop:
    """Four legs and a top."""
    b = _Parts(("wood", "wood"))
    top = rng.uniform(0.025, 0.05)
    b.box([-w / 2, -d / 2, h - top], [w / 2, d / 2, h], 0)
    _legs(b, w, d, h - top, rng.uniform(0.035, 0.07), rng.uniform(0.02, 0.08), 1)
    return b.prop("table")


def chair(rng: np.random.Generator) -> Prop:
    """Seat, back and four legs; the back towards +y."""
    b = _Parts(("wood", "soft"))
    s, sh, bh = rng.uniform(0.4, 0.5), rng.uniform(0.43, 0.48), rng.uniform(0.35, 0.5)
    st, bt = 0.04, rng.uniform(0.025, 0.04)
    b.box([-s / 2, -s / 2, sh - st], [s / 2, s / 2, sh], 1)
    b.box([-s / 2, s / 2 - bt, sh], [s / 2, s / 2, sh + bh], 0)
    _legs(b, s, s, sh - st, rng.uniform(0.03, 0.045), 0.01, 0)
    return b.prop("chair")


def sofa(rng: np.random.Generator, w: float | None = None) -> Prop:
    """Base, back, arms, seat cushions and feet; the back towards +y."""
    b = _Parts(("soft", "soft", "wood"))
    w = rng.uniform(1.6, 2.3) if w is None else w
    d, foot = rng.uniform(0.8, 0.95), rng.uniform(0.04, 0.12)
    base, seat, back = foot + rng.uniform(0.15, 0.22), rng.uniform(0.4, 0.47), rng.uniform(0.75, 0.9)
    arm, armh, bt = rng.uniform(0.1, 0.22), rng.uniform(0.55, 0.68), rng.uniform(0.15, 0.25)
    b.box([-w / 2, -d / 2, foot], [w / 2, d / 2, base], 0)
    b.box([-w / 2, d / 2 - bt, base], [w / 2, d / 2, back], 0)
    b.box([-w / 2, -d / 2, base], [-w / 2 + arm, d / 2 - bt, armh], 0)
    b.box([w / 2 - arm, -d / 2, base], [w / 2, d / 2 - bt, armh], 0)
    n = max(1, int(round((w - 2 * arm) / rng.uniform(0.5, 0.75))))
    xs = np.linspace(-w / 2 + arm, w / 2 - arm, n + 1)
    for a, c in zip(xs[:-1], xs[1:], strict=True):
        b.box([a + 0.004, -d / 2 + 0.01, base], [c - 0.004, d / 2 - bt, seat], 1)
    _legs(b, w, d, foot, 0.05, 0.04, 2)
    return b.prop("sofa")


def bed(rng: np.random.Generator) -> Prop:
    """Frame, mattress, duvet, pillows and a headboard at +y."""
    b = _Parts(("wood", "soft", "soft", "soft"))
    w, length = rng.choice([0.9, 1.2, 1.4, 1.6, 1.8]) + 0.06, rng.uniform(2.0, 2.2)
    frame, mat = rng.uniform(0.2, 0.35), rng.uniform(0.16, 0.26)
    head, ht = frame + mat + rng.uniform(0.35, 0.8), rng.uniform(0.04, 0.08)
    b.box([-w / 2, -length / 2, 0.0], [w / 2, length / 2 - ht, frame], 0)
    b.box([-w / 2, length / 2 - ht, 0.0], [w / 2, length / 2, head], 0)
    b.box([-w / 2 + 0.02, -length / 2 + 0.02, frame], [w / 2 - 0.02, length / 2 - ht, frame + mat], 1)
    top = frame + mat
    cover = rng.uniform(0.55, 0.8) * (length - ht)
    b.box([-w / 2 + 0.01, -length / 2 + 0.01, top], [w / 2 - 0.01, -length / 2 + cover, top + 0.05], 2)
    n = 1 if w < 1.2 else 2
    pw = (w - 0.1) / n
    for k in range(n):
        x0 = -w / 2 + 0.05 + k * pw
        b.box([x0 + 0.02, length / 2 - ht - 0.45, top], [x0 + pw - 0.02, length / 2 - ht - 0.05, top + 0.12], 3)
    return b.prop("bed")


def cabinet(rng: np.random.Generator, w: float, d: float, h: float, name: str = "cabinet") -> Prop:
    """A closed carcass on a plinth with door or drawer fronts and handles; the front at -y."""
    b = _Parts(("wood", "wood", "metal"))
    plinth = rng.uniform(0.0, 0.1)
    if plinth > 0.03:
        b.box([-w / 2 + 0.03, -d / 2 + 0.05, 0.0], [w / 2 - 0.03, d / 2 - 0.02, plinth], 0)
    else:
        plinth = 0.0
    b.box([-w / 2, -d / 2 + 0.02, plinth], [w / 2, d / 2, h], 0)
    drawers = h < 1.1 and rng.uniform() < 0.5
    cols = max(1, int(round(w / rng.uniform(0.4, 0.6))))
    rows = max(1, int(round((h - plinth) / rng.uniform(0.2, 0.3)))) if drawers else 1
    xs, zs = np.linspace(-w / 2, w / 2, cols + 1), np.linspace(plinth, h, rows + 1)
    for a, c in zip(xs[:-1], xs[1:], strict=True):
        for z0, z1 in zip(zs[:-1], zs[1:], strict=True):
            b.box([a + 0.003, -d / 2, z0 + 0.003], [c - 0.003, -d / 2 + 0.02, z1 - 0.003], 1)
            if drawers:
                hx, hz = (a + c) / 2 - 0.05, (z0 + z1) / 2 - 0.01
                b.box([hx, -d / 2 - 0.025, hz], [hx + 0.1, -d / 2, hz + 0.02], 2)
            else:
                hx = c - 0.05 if (a + c) / 2 < 0 or cols == 1 else a + 0.03
                hz = min(z1 - 0.25, 1.05) if z1 - z0 > 0.6 else (z0 + z1) / 2 - 0.05
                b.box([hx, -d / 2 - 0.025, hz], [hx + 0.02, -d / 2, hz + 0.1], 2)
    return b.prop(name)


def bookcase(rng: np.random.Generator, w: float, d: float, h: float) -> Prop:
    """Open shelves: sides, back, top and boards, open at -y."""
    b = _Parts(("wood", "wood"))
    pt, bk = rng.uniform(0.018, 0.03), 0.01
    b.box([-w / 2, -d / 2, 0.0], [-w / 2 + pt, d / 2, h], 0)
    b.box([w / 2 - pt, -d / 2, 0.0], [w / 2, d / 2, h], 0)
    b.box([-w / 2 + pt, d / 2 - bk, 0.0], [w / 2 - pt, d / 2, h], 1)
    n = max(2, int(round(h / rng.uniform(0.3, 0.4))))
    for z in np.linspace(0.0, h - pt, n + 1):
        b.box([-w / 2 + pt, -d / 2, z], [w / 2 - pt, d / 2 - bk, z + pt], 0)
    return b.prop("bookcase")


def tv(rng: np.random.Generator) -> Prop:
    """A flat screen on a foot."""
    b = _Parts(("keep", "metal"), ((0.02, 0.02, 0.025), (0.2, 0.2, 0.2)))
    w = rng.uniform(0.6, 1.3)
    sh, foot = w * 9 / 16, rng.uniform(0.05, 0.12)
    b.box([-0.12, -0.1, 0.0], [0.12, 0.1, 0.02], 1)
    b.box([-0.03, -0.01, 0.02], [0.03, 0.02, foot], 1)
    b.box([-w / 2, -0.025, foot], [w / 2, 0.02, foot + sh], 0)
    return b.prop("tv")


def radiator(rng: np.random.Generator, w: float) -> Prop:
    """Vertical fins between two rails."""
    b = _Parts(("metal",))
    h, d = rng.uniform(0.4, 0.8), rng.uniform(0.06, 0.12)
    n = max(3, int(w / 0.06))
    fin = w / n
    for k in range(n):
        x0 = -w / 2 + k * fin
        b.box([x0 + 0.006, -d / 2, 0.0], [x0 + fin - 0.006, d / 2, h], 0)
    return b.prop("radiator")


def lamp(rng: np.random.Generator, kind: str) -> Prop:
    """A floor lamp (base, pole, shade), a table lamp (foot, shade) or a ceiling fixture (flush disc or pendant)."""
    b = _Parts(("metal", "soft"), ((0.3, 0.3, 0.3), (0.95, 0.92, 0.85)))
    if kind == "floor_lamp":
        h, r = rng.uniform(1.3, 1.8), rng.uniform(0.15, 0.25)
        b.cylinder(rng.uniform(0.12, 0.2), 0.0, 0.03, 0)
        b.cylinder(0.012, 0.03, h - 0.25, 0, sections=8)
        b.cylinder(r, h - 0.25, h, 1, top_radius=r * rng.uniform(0.6, 1.0))
    elif kind == "table_lamp":
        h, r = rng.uniform(0.3, 0.6), rng.uniform(0.1, 0.2)
        b.cylinder(rng.uniform(0.05, 0.09), 0.0, h * 0.6, 0, top_radius=0.02)
        b.cylinder(r, h * 0.6, h, 1, top_radius=r * rng.uniform(0.55, 1.0))
    elif rng.uniform() < 0.5:
        b.cylinder(rng.uniform(0.12, 0.3), 0.0, rng.uniform(0.04, 0.1), 1, sections=20)
    else:
        drop, r = rng.uniform(0.3, 0.9), rng.uniform(0.12, 0.3)
        b.cylinder(r, 0.0, rng.uniform(0.15, 0.3), 1, top_radius=0.04)
        top = b.pieces[-1][0][:, 2].max()
        b.cylinder(0.006, top, top + drop, 0, sections=6)
    return b.prop(kind)


def plant(rng: np.random.Generator, height: float) -> Prop:
    """A pot and a crown of foliage (overlapping spheres)."""
    green = tuple(float(c) for c in np.clip([rng.uniform(0.1, 0.3), rng.uniform(0.35, 0.6), rng.uniform(0.1, 0.25)],
                                            0, 1))
    b = _Parts(("any", "keep"), ((0.6, 0.6, 0.6), green))
    pr, ph = height * rng.uniform(0.12, 0.22), height * rng.uniform(0.2, 0.35)
    b.cylinder(pr, 0.0, ph, 0, top_radius=pr * rng.uniform(1.0, 1.3))
    crown = height - ph
    for _ in range(int(rng.integers(3, 7))):
        r = crown * rng.uniform(0.18, 0.3)
        c = [rng.uniform(-0.5, 0.5) * pr, rng.uniform(-0.5, 0.5) * pr, ph + rng.uniform(r, crown - r)]
        b.sphere(c, r * rng.uniform(0.8, 1.2, size=3), 1)
    return b.prop("plant")


def rug(rng: np.random.Generator, w: float, d: float, t: float) -> Prop:
    """A flat box."""
    b = _Parts(("rug",))
    b.box([-w / 2, -d / 2, 0.0], [w / 2, d / 2, t], 0)
    return b.prop("rug")


def clutter(rng: np.random.Generator, big: bool = False) -> Prop:
    """A box, a bottle or a vase."""
    b = _Parts(("any",))
    s = rng.uniform(0.3, 0.7) if big else rng.uniform(0.05, 0.25)
    k = rng.integers(3)
    if k == 0:
        w, d, h = s * rng.uniform(0.5, 1.2, size=3)
        b.box([-w / 2, -d / 2, 0.0], [w / 2, d / 2, h], 0)
    elif k == 1:
        r = s * rng.uniform(0.15, 0.3)
        b.cylinder(r, 0.0, s * 0.7, 0)
        b.cylinder(r * 0.35, s * 0.7, s, 0)
    else:
        r = s * rng.uniform(0.2, 0.35)
        b.cylinder(r * 0.6, 0.0, s * 0.15, 0)
        b.cylinder(r, s * 0.15, s * 0.75, 0, top_radius=r * 0.4)
        b.cylinder(r * 0.4, s * 0.75, s, 0, top_radius=r * 0.6)
    return b.prop("clutter")


def statue(rng: np.random.Generator) -> Prop:
    """A figure or a stack of shapes (the flat rooms' procedural sculpture, its pedestal included)."""
    v, f = _sculpture(rng)
    b = _Parts(("stone",))
    b.mesh(v, f, 0)
    return b.prop("statue")


def _sized(lo: float, hi: float) -> Callable[[np.random.Generator], float]:
    return lambda rng: float(rng.uniform(lo, hi))


BUILDERS: dict[str, Callable[[np.random.Generator], Prop]] = {
    "bed": bed,
    "sofa": sofa,
    "armchair": lambda rng: sofa(rng, float(rng.uniform(0.75, 1.0))),
    "chair": chair,
    "stool": chair,
    "dining_table": lambda rng: table(rng, rng.uniform(1.2, 2.0), rng.uniform(0.8, 1.0), rng.uniform(0.72, 0.78)),
    "small_table": lambda rng: table(rng, rng.uniform(0.7, 1.1), rng.uniform(0.6, 0.9), rng.uniform(0.72, 0.78)),
    "coffee_table": lambda rng: table(rng, rng.uniform(0.8, 1.3), rng.uniform(0.45, 0.7), rng.uniform(0.35, 0.5)),
    "side_table": lambda rng: table(rng, rng.uniform(0.35, 0.55), rng.uniform(0.35, 0.55), rng.uniform(0.45, 0.65)),
    "desk": lambda rng: table(rng, rng.uniform(1.0, 1.6), rng.uniform(0.55, 0.8), rng.uniform(0.72, 0.77)),
    "nightstand": lambda rng: cabinet(rng, rng.uniform(0.4, 0.55), rng.uniform(0.35, 0.45), rng.uniform(0.45, 0.65),
                                      "nightstand"),
    "dresser": lambda rng: cabinet(rng, rng.uniform(0.8, 1.5), rng.uniform(0.4, 0.55), rng.uniform(0.7, 1.0),
                                   "dresser"),
    "tv_unit": lambda rng: cabinet(rng, rng.uniform(1.0, 1.8), rng.uniform(0.35, 0.5), rng.uniform(0.4, 0.6),
                                   "tv unit"),
    "cabinet": lambda rng: cabinet(rng, rng.uniform(0.5, 1.2), rng.uniform(0.35, 0.6), rng.uniform(0.7, 1.9)),
    "wardrobe": lambda rng: cabinet(rng, rng.uniform(0.9, 2.0), rng.uniform(0.55, 0.65), rng.uniform(1.9, 2.3),
                                    "wardrobe"),
    "kitchen_lower": lambda rng: cabinet(rng, rng.choice([0.4, 0.6, 0.8]), 0.6, 0.9, "lower cabinet"),
    "kitchen_upper": lambda rng: cabinet(rng, rng.choice([0.4, 0.6, 0.8]), rng.uniform(0.3, 0.35), 0.7,
                                         "upper cabinet"),
    "kitchen_tall": lambda rng: cabinet(rng, 0.6, 0.6, rng.uniform(1.8, 2.1), "tall cabinet"),
    "appliance": lambda rng: cabinet(rng, 0.6, 0.6, 0.85, "appliance"),
    "shelf": lambda rng: bookcase(rng, rng.uniform(0.6, 1.4), rng.uniform(0.25, 0.4), rng.uniform(1.0, 2.1)),
    "tv": tv,
    "radiator": lambda rng: radiator(rng, float(rng.uniform(0.5, 1.2))),
    "floor_lamp": lambda rng: lamp(rng, "floor_lamp"),
    "table_lamp": lambda rng: lamp(rng, "table_lamp"),
    "ceiling_lamp": lambda rng: lamp(rng, "ceiling_lamp"),
    "floor_plant": lambda rng: plant(rng, float(rng.uniform(0.6, 1.6))),
    "small_plant": lambda rng: plant(rng, float(rng.uniform(0.15, 0.45))),
    "clutter": clutter,
    "floor_clutter": lambda rng: clutter(rng, big=True),
    "statue": statue,
    "figure": statue,
}
"""A builder per role that has one (roles without one are left out when the pack has no mesh for them)."""

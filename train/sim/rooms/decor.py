"""Decoration and clutter: radiators and curtains at the windows, rugs, ceiling fixtures, what stands on the
furniture (lamps, TVs, books, plants, small statues, clutter) and what hangs on the walls (paintings, posters,
clocks, wall lamps). Everything here is labelled ``object`` except small statues (``sculpture``) and radiators
(``furniture``, the pack's label for appliances).

Where each thing goes
    * Radiators stand against the wall under a window whose sill leaves room; curtains hang from a rod above a
      window (pleated panels, drawn to the sides or partly closed, down to the floor or to below the sill).
    * Rugs lie on the floor where a group asked for one (under a coffee table, the foot of a bed, a dining table)
      or anywhere free; they keep away from doors, curtains and fixed pieces. Every piece standing on the floor
      over a rug is then raised by the rug's thickness, so it rests on the rug.
    * Ceiling fixtures hang from the ceiling, a pendant over a dining table first; elsewhere their lowest point
      stays above 2 m so that a camera carried through the room never runs into one.
    * Support surfaces (:mod:`.supports`) of furniture get, first, what a piece wants (a lamp on a nightstand, a TV
      on a TV unit, a computer on a desk), then books in rows on bookcase shelves, then small things at a density
      drawn from ``HomeConfig.clutter``: clutter, small plants, picture frames, books lying in stacks, small
      statues. Each rests on the surface, inside it, with its own room above it, and clear of everything else.
    * Paintings (framed or not) and posters hang flat on the walls between 0.9 m and the ceiling, at eye height or
      above the furniture in front of them, never over a window, a door or tall furniture.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np

from ..scene import _Footprint, _overlap, boxes, slab_with_holes
from .draft import Home, Piece, Slot, footprint_of
from .furnish import _front, along_wall, prop_for, stand
from .procedural import rug
from .shell import Window


# ---------------------------------------------------------------------------------------------- windows
def radiators(h: Home) -> None:
    """A radiator under a window with ``HomeConfig.radiator``'s chance, where the sill is high enough."""
    rng = h.rng
    for w in h.windows:
        if rng.uniform() >= h.cfg.radiator or w.z0 - w.sill < 0.55:
            continue
        prop = prop_for(h, "radiator")
        if prop is None or prop.size[0] > w.width + 0.2:
            continue
        # Hung on the wall above the baseboard, as radiators are.
        z = max(rng.uniform(0.06, 0.15), h.baseboard_height + 0.01)
        if z + prop.size[2] > w.z0 - w.sill - 0.06:
            continue
        along_wall(h, prop, "radiator", k=w.wall, s=w.x0 + w.width / 2, tries=1, z=z, mount="wall", kind="fixed")


def curtains(h: Home) -> None:
    """Curtains at windows with ``HomeConfig.curtains``'s chance (module docstring)."""
    for w in h.windows:
        if h.rng.uniform() < h.cfg.curtains:
            _curtain(h, w)


def _curtain(h: Home, w: Window) -> None:
    rng, wall = h.rng, h.walls[w.wall]
    top_room = h.lz - 0.04 - (0.12 if any(p.name == "crown" for p in h.pieces) else 0.0)
    rod_z = min(w.z1 + rng.uniform(0.06, 0.25), top_room - 0.03)
    dist = rng.uniform(0.12, 0.18)  # in front of the sill, which sticks out up to 6 cm
    lo, hi = h.inner(w.wall)
    x0 = max(w.x0 - rng.uniform(0.1, 0.35), lo + 0.05)
    x1 = min(w.x0 + w.width + rng.uniform(0.1, 0.35), hi - 0.05)
    floor_length = w.z0 <= 0.0 or rng.uniform() < 0.6
    bottom = rng.uniform(0.005, 0.02) if floor_length else max(w.z0 - w.sill - rng.uniform(0.05, 0.2), 0.3)
    amp, period, t = rng.uniform(0.015, 0.04), rng.uniform(0.08, 0.16), rng.uniform(0.008, 0.015)
    span = x1 - x0
    closed = rng.uniform() < 0.15
    width = span / 2 - 0.01 if closed else rng.uniform(0.15, 0.35) * span
    panels = [(x0, x0 + width), (x1 - width, x1)] if rng.uniform() < 0.75 else \
        [(x0, x0 + width) if rng.uniform() < 0.5 else (x1 - width, x1)]
    parts_fabric = [_pleated(a, b, -dist, amp, period, t, bottom, rod_z - 0.02, rng.uniform(0, 2 * math.pi))
                    for a, b in panels]
    lo_b = [[x0, -dist - 0.012, rod_z - 0.012], [x0 + 0.02, -dist, rod_z + 0.005], [x1 - 0.04, -dist, rod_z + 0.005]]
    hi_b = [[x1, -dist + 0.012, rod_z + 0.012], [x0 + 0.04, 0.0, rod_z + 0.025], [x1 - 0.02, 0.0, rod_z + 0.025]]
    rod = boxes(lo_b, hi_b)
    # The slot covers the fabric and the rod; the brackets behind them reach the wall above the window.
    c = wall.to_world(np.array([[(x0 + x1) / 2, -dist, 0.0]]))[0]
    fp = _Footprint(c[0], c[1], span / 2, amp + t / 2 + 0.015, math.atan2(wall.along[1], wall.along[0]))
    if not h.fits(fp, bottom, rod_z + 0.03, gap=0.0, ignore=("rug", "window")):
        return
    world = [(wall.to_world(v), f) for v, f in parts_fabric] + [(wall.to_world(rod[0]), rod[1])]
    fabric, metal = h.sampler.draw("soft"), h.sampler.draw("metal" if rng.uniform() < 0.6 else "wood")
    piece = h.add_box_piece("curtain", "object", "object", world, [fabric] * len(parts_fabric) + [metal],
                            mount="wall", slot=Slot(fp, bottom, rod_z + 0.03, "fixed"))
    piece.parts = np.where(piece.parts < len(parts_fabric), 0, 1).astype(np.int32)
    piece.materials = [fabric, metal]


def _pleated(x0: float, x1: float, y0: float, amp: float, period: float, t: float, z0: float, z1: float,
             phase: float) -> tuple[np.ndarray, np.ndarray]:
    """A closed, outward pleated curtain panel: a wavy strip (centre line ``y0 + amp sin(...)``, ``t`` thick)
    from ``x0`` to ``x1`` extruded from ``z0`` to ``z1``, in a wall frame."""
    n = max(2, int(math.ceil((x1 - x0) / (period / 8)))) + 1
    xs = np.linspace(x0, x1, n)
    yc = y0 + amp * np.sin(2 * math.pi * (xs - x0) / period + phase)
    v = np.concatenate([np.stack([xs, yc + dy, np.full(n, z)], 1) for z in (z0, z1) for dy in (-t / 2, t / 2)])

    def idx(s: np.ndarray, back: int, top: int) -> np.ndarray:
        return top * 2 * n + back * n + s

    s = np.arange(n - 1)
    quads = [  # (a, b, c, d) counter-clockwise seen from outside
        (idx(s, 0, 0), idx(s + 1, 0, 0), idx(s + 1, 0, 1), idx(s, 0, 1)),    # front, -y
        (idx(s, 1, 0), idx(s, 1, 1), idx(s + 1, 1, 1), idx(s + 1, 1, 0)),    # back, +y
        (idx(s, 0, 0), idx(s, 1, 0), idx(s + 1, 1, 0), idx(s + 1, 0, 0)),    # bottom, -z
        (idx(s, 0, 1), idx(s + 1, 0, 1), idx(s + 1, 1, 1), idx(s, 1, 1)),    # top, +z
    ]
    e0, e1 = np.array([0]), np.array([n - 1])
    quads += [(idx(e0, 0, 0), idx(e0, 0, 1), idx(e0, 1, 1), idx(e0, 1, 0)),  # end at x0, -x
              (idx(e1, 0, 0), idx(e1, 1, 0), idx(e1, 1, 1), idx(e1, 0, 1))]  # end at x1, +x
    f = np.concatenate([np.concatenate([np.stack([a, b, c], 1), np.stack([a, c, d], 1)]) for a, b, c, d in quads])
    return v, f


# ---------------------------------------------------------------------------------------------- rugs
def rugs(h: Home) -> None:
    """Lay the rugs the groups asked for, then free ones up to ``HomeConfig.rugs``, and raise what stands on
    them: a piece whose feet are over a rug stands on it; a rug that would cut into anything else that comes
    down that low (a bedspread, a base) is taken away again."""
    rng = h.rng
    laid: list[Piece] = []
    n = int(rng.integers(h.cfg.rugs[0], h.cfg.rugs[1] + 1))
    for centre, yaw, w, d in h.rug_spots:
        if len(laid) < n:
            laid += _lay(h, [(float(centre[0]), float(centre[1]), yaw)], w, d, allow_pack=False)
    for _ in range(n - len(laid)):
        w, d = rng.uniform(0.8, 2.4), rng.uniform(0.6, 1.8)
        spots = [(rng.uniform(0.0, h.lx), rng.uniform(0.0, h.ly), float(rng.choice([0.0, math.pi / 2])))
                 for _ in range(h.cfg.placement_tries)]
        laid += _lay(h, spots, w, d, allow_pack=True)
    lifts: dict[int, float] = {}
    for r in laid:
        feet, clash = [], False
        for p in h.pieces:
            if p.mount != "floor" or p.slot is None or not _overlap(p.slot.fp, r.slot.fp, -0.01):
                continue
            if _below(p, r.slot.fp, p.slot.z0 + 0.003):
                feet.append(id(p))
            elif _below(p, r.slot.fp, p.slot.z0 + (r.slot.z1 - r.slot.z0) + 0.002):
                clash = True
        if clash:
            h.pieces.remove(r)
            h.slots.remove(r.slot)
            continue
        for k in feet:
            lifts[k] = max(lifts.get(k, 0.0), r.slot.z1)
    for p in h.pieces:
        lift = lifts.get(id(p), 0.0)
        if lift > 0:
            p.vertices = p.vertices + [0.0, 0.0, lift]
            p.slot.z0, p.slot.z1 = p.slot.z0 + lift, p.slot.z1 + lift
            p.pose = (p.pose[0], p.pose[1], p.pose[2] + lift, p.pose[3])
            p.mount = "rug"


def _below(p: Piece, fp: _Footprint, z: float) -> bool:
    """Whether any part of the piece below height ``z`` lies over the rectangle ``fp`` (5 mm inside its edges):
    each face is clipped to ``z`` and the floor projection of what is left is tested against the rectangle by
    separating axes (the rectangle's two, and the face's three edge normals)."""
    tri = p.vertices[p.faces]
    tri = tri[tri[:, :, 2].min(axis=1) < z]
    if len(tri) == 0:
        return False
    a, b = tri, np.roll(tri, -1, axis=1)
    za, zb = a[:, :, 2] - z, b[:, :, 2] - z
    cross = za * zb < 0
    t = np.where(cross, za / np.where(cross, za - zb, 1.0), 0.0)
    pts = np.concatenate([a, a + (b - a) * t[..., None]], axis=1)[:, :, :2]
    keep = np.concatenate([za <= 0, cross], axis=1)
    # Points not kept repeat a kept one, which changes no projection's extent.
    first = pts[np.arange(len(pts)), np.argmax(keep, axis=1)]
    pts = np.where(keep[..., None], pts, first[:, None, :])
    ax = fp.axes()
    q = (pts - np.array([fp.cx, fp.cy])) @ ax.T  # (T, 6, 2) in the rectangle's frame
    half = np.array([fp.hx - 0.005, fp.hy - 0.005])
    apart = np.any(q.min(axis=1) > half, axis=1) | np.any(q.max(axis=1) < -half, axis=1)
    for k in range(3):
        edge = (tri[:, (k + 1) % 3, :2] - tri[:, k, :2]) @ ax.T
        n = np.stack([-edge[:, 1], edge[:, 0]], axis=1)
        proj = np.einsum("tij,tj->ti", q, n)
        reach = np.abs(n) @ half
        apart |= (proj.min(axis=1) > reach) | (proj.max(axis=1) < -reach)
    return bool(np.any(~apart))


def _lay(h: Home, spots: list[tuple[float, float, float]], w: float, d: float, allow_pack: bool) -> list[Piece]:
    """A rug at the first free spot of ``spots`` (free of doors, curtains, fixed pieces and other rugs; furniture
    may stand on it): a pack rug, or a box with a carpet or fabric texture stretched once over it."""
    rng = h.rng
    t = rng.uniform(*h.cfg.rug_thickness)
    prop = prop_for(h, "rug") if allow_pack and rng.uniform() < 0.5 else None
    if prop is None or prop.asset is None:
        prop = rug(rng, min(w, h.lx - 0.2), min(d, h.ly - 0.2), t)
    for x, y, yaw in spots:
        fp = footprint_of(prop, x, y, yaw)
        top = float(prop.size[2])
        probe = Slot(fp, 0.0, top)
        if not h.inside(fp, h.baseboard + 0.01) or any(s.kind != "piece" and probe.meets(s, 0.02) for s in h.slots):
            continue
        piece = stand(h, prop, "rug", x, y, yaw, mount="floor", kind="rug", check=False)
        piece.mount, piece.layer = "rug", "rug"
        if prop.asset is None:
            piece.materials = [_whole(h, m, float(prop.size[0])) for m in piece.materials]
        return [piece]
    return []


def _whole(h: Home, m: Any, width: float) -> Any:
    """A carpet texture is a whole rug's design: stretch it once over the rug's width."""
    if m.texture is not None and h.lib.pack.entry(m.texture).category == "carpet":
        return dataclasses.replace(m, tile_m=width)
    return m


# ---------------------------------------------------------------------------------------------- ceiling
def ceiling_lamps(h: Home) -> None:
    """Ceiling fixtures (module docstring), each a light the room may switch on (:mod:`.lights`)."""
    rng = h.rng
    n = int(rng.integers(h.cfg.ceiling_lamps[0], h.cfg.ceiling_lamps[1] + 1))
    spots = [(p, True) for p in h.pendants]
    for k in range(n):
        prop = prop_for(h, "ceiling_lamp")
        if prop is None:
            continue
        pendant = k < len(spots)
        size = prop.size
        if not pendant and h.lz - size[2] < 2.0:
            continue
        for _ in range(h.cfg.placement_tries):
            if pendant:
                x, y = spots[k][0]
            else:
                x, y = rng.uniform(0.25 * h.lx, 0.75 * h.lx), rng.uniform(0.25 * h.ly, 0.75 * h.ly)
            z = h.lz - float(size[2])
            piece = stand(h, prop, "ceiling_lamp", float(x), float(y), float(rng.choice([0.0, math.pi / 2])), z=z,
                          mount="ceiling", gap=0.02)
            if piece is not None:
                h.lights.append(("ceiling", np.array([x, y, z - 0.03]), piece))
                break
            if pendant:
                break


# ---------------------------------------------------------------------------------------------- supports
_ON_TOP = ("clutter", "clutter", "clutter", "clutter", "small_plant", "books", "clutter", "small_plant")
"""What a free spot on a support draws from, uniformly."""


def dress(h: Home) -> None:
    """Put what belongs on every support surface (module docstring)."""
    rng = h.rng
    for piece in list(h.pieces):
        if not piece.levels:
            continue
        shelf = piece.role == "shelf"
        usable = [lv for lv in piece.levels if lv.z >= (0.05 if shelf else 0.25)]
        if not usable:
            continue
        top = max(usable, key=lambda lv: (lv.room.max() >= 0.5, lv.z))
        for want in piece.wants:
            put_on(h, piece, [top], want)
        if shelf:
            _books(h, piece, usable)
        density = rng.uniform(*h.cfg.clutter)
        for lv in usable:
            for _ in range(int(density * lv.area / 0.06 + rng.uniform())):
                if h.small_sculptures and rng.uniform() < 0.3:
                    prop, role, scale = h.small_sculptures.pop()
                    put_on(h, piece, [lv], role, prop, scale)
                    continue
                what = _ON_TOP[int(rng.integers(len(_ON_TOP)))]
                if what == "books":
                    _stack(h, piece, lv)
                else:
                    put_on(h, piece, [lv], what)


def put_on(h: Home, piece: Piece, levels: list[Any], role: str, prop: Any = None, scale: float = 1.0
           ) -> Piece | None:
    """Stand a prop of ``role`` on one of ``levels`` of ``piece`` (turned to face the room, or any way for small
    things), if one has a free spot with the room for it."""
    rng = h.rng
    prop = prop if prop is not None else prop_for(h, role)
    if prop is None:
        return None
    if scale != 1.0:
        prop = dataclasses.replace(prop, vertices=prop.vertices * scale, _levels=None)
    facing = role in ("tv", "computer", "table_lamp", "statue", "figure")
    rel = rng.uniform(-0.15, 0.15) if facing else float(rng.choice([0.0, 0.0, math.pi, math.pi / 2, -math.pi / 2])) \
        + rng.uniform(-0.3, 0.3)
    sx, sy, sz = (float(v) for v in prop.size)
    c, s = abs(math.cos(rel)), abs(math.sin(rel))
    bw, bd = c * sx + s * sy, s * sx + c * sy
    x, y, z, yaw = piece.pose
    for lv in levels:
        spot = lv.fit(rng, bw, bd, sz + 0.01)
        if spot is None:
            continue
        cy, sy_ = math.cos(yaw), math.sin(yaw)
        wx, wy = x + cy * spot[0] - sy_ * spot[1], y + sy_ * spot[0] + cy * spot[1]
        wz = z + lv.z + 0.0005
        fp = footprint_of(prop, wx, wy, yaw + rel)
        if wz + sz > h.lz - 0.02 or not h.fits(fp, wz, wz + sz, gap=0.0, wall_margin=0.0, skip=piece.slot):
            continue
        item = stand(h, prop, role, wx, wy, yaw + rel, z=wz, mount="support", check=False)
        if role == "table_lamp":
            h.lights.append(("lamp", np.array([wx, wy, wz + 0.75 * sz]), item))
        return item
    return None


def _books(h: Home, piece: Piece, levels: list[Any]) -> None:
    """Rows of upright books on a bookcase's shelves, filling a share ``HomeConfig.books`` of each row."""
    rng = h.rng
    fill = rng.uniform(*h.cfg.books)
    for lv in levels:
        if rng.uniform() > 0.85:
            continue
        rows, cols = lv.free_run(0.14)
        if len(cols) == 0:
            continue
        c0, c1 = int(cols.min()), int(cols.max())
        start = c0 + int(rng.uniform(0.0, 1.0 - fill) * (c1 - c0))
        _row(h, piece, lv, start, start + int(fill * (c1 - c0 + 1)))


def _row(h: Home, piece: Piece, lv: Any, c_start: int, c_end: int) -> None:
    """Books standing side by side on one shelf from column ``c_start`` to ``c_end`` (grid of ``lv``), each as
    high and deep as the shelf allows over all the cells it covers (and below the ceiling), spines at the front."""
    from .supports import CELL

    rng = h.rng
    lo, hi, which = [], [], []
    x, x_end = lv.x0 + c_start * CELL, lv.x0 + c_end * CELL
    ceiling = h.lz - (piece.pose[2] + lv.z) - 0.02
    tones = int(rng.integers(2, 6))
    while x < x_end:
        t = rng.uniform(0.015, 0.06)
        c0, c1 = int((x - lv.x0) / CELL), int(math.ceil((x + t - lv.x0) / CELL))
        ok = np.all((lv.room[:, c0:c1] >= 0.14) & ~lv.used[:, c0:c1], axis=1) if c1 <= lv.room.shape[1] else []
        r = np.nonzero(ok)[0]
        # The rows from the front-most free one backwards, as long as they stay free.
        run = r[:int(np.argmax(np.diff(np.r_[r, -9]) != 1)) + 1] if len(r) else r
        if len(run) < 5 or x + t > x_end:
            x += t
            continue
        front, back = lv.y0 + run[0] * CELL, lv.y0 + (run[-1] + 1) * CELL
        room = min(float(lv.room[run[0]:run[-1] + 1, c0:c1].min()) - 0.01, ceiling)
        height = min(rng.uniform(0.6, 0.95) * room, rng.uniform(0.15, 0.32))
        depth = min(back - front - 0.01, rng.uniform(0.12, 0.25))
        inset = rng.uniform(0.0, min(0.03, back - front - 0.01 - depth))
        if height >= 0.1:
            lo.append([x, front + inset, lv.z + 0.0005])
            hi.append([x + t - 0.001, front + inset + depth, lv.z + 0.0005 + height])
            which.append(int(rng.integers(tones)))
        x += t + rng.uniform(0.0, 0.003)
    if lo:
        _book_piece(h, piece, lo, hi, which, tones)
        lv.used[:, c_start:c_end + 1] = True


def _stack(h: Home, piece: Piece, lv: Any) -> None:
    """A few books lying on each other on a free spot of ``lv``."""
    rng = h.rng
    w, d = rng.uniform(0.15, 0.3), rng.uniform(0.12, 0.22)
    n = int(rng.integers(2, 7))
    ts = rng.uniform(0.015, 0.05, size=n)
    if piece.pose[2] + lv.z + ts.sum() > h.lz - 0.02:
        return
    spot = lv.fit(rng, w + 0.02, d + 0.02, float(ts.sum()) + 0.01)
    if spot is None:
        return
    lo, hi, z = [], [], lv.z + 0.0005
    for k in range(n):
        dx, dy, sw, sd = rng.uniform(-0.01, 0.01), rng.uniform(-0.01, 0.01), w * rng.uniform(0.85, 1.0), \
            d * rng.uniform(0.85, 1.0)
        lo.append([spot[0] + dx - sw / 2, spot[1] + dy - sd / 2, z])
        hi.append([spot[0] + dx + sw / 2, spot[1] + dy + sd / 2, z + ts[k] - 0.0005])
        z += ts[k]
    _book_piece(h, piece, lo, hi, list(rng.integers(0, 3, size=n)), 3)


def _book_piece(h: Home, piece: Piece, lo: list[list[float]], hi: list[list[float]], which: list[int], tones: int
                ) -> None:
    """Books given as boxes in ``piece``'s frame, as one object with a few materials."""
    v, f = boxes(np.array(lo), np.array(hi))
    x, y, z, yaw = piece.pose
    c, s = math.cos(yaw), math.sin(yaw)
    world = np.stack([x + c * v[:, 0] - s * v[:, 1], y + s * v[:, 0] + c * v[:, 1], z + v[:, 2]], 1)
    mats = [h.sampler.draw("soft" if h.rng.uniform() < 0.5 else "any") for _ in range(tones)]
    parts = np.repeat(np.asarray(which, dtype=np.int32), 12)
    lo_w, hi_w = world[:, :2].min(axis=0), world[:, :2].max(axis=0)
    fp = _Footprint(*((lo_w + hi_w) / 2), *((hi_w - lo_w) / 2), 0.0)
    h.add(Piece(h.name("books"), "object", world, f, parts, mats, "object", "support",
                Slot(fp, float(world[:, 2].min()), float(world[:, 2].max()), "piece"), role="books"))


# ---------------------------------------------------------------------------------------------- walls
def wall_art(h: Home) -> None:
    """Paintings and posters on the walls (module docstring), then maybe a clock and a wall lamp."""
    rng = h.rng
    for _ in range(int(rng.integers(h.cfg.wall_art[0], h.cfg.wall_art[1] + 1))):
        _picture(h, "painting" if rng.uniform() < 0.7 else "poster")
    for role, chance, z in (("wall_clock", 0.2, (1.6, 2.0)), ("wall_lamp", 0.25, (1.5, 1.9))):
        if rng.uniform() < chance:
            prop = prop_for(h, role)
            height = rng.uniform(*z)
            if prop is None or height + prop.size[2] > h.lz - 0.15:
                continue
            got = along_wall(h, prop, role, z=height, mount="wall", tries=10)
            if got is not None and role == "wall_lamp":
                x, y, _, yaw = got[0].pose
                h.lights.append(("lamp", np.array([x, y, height + prop.size[2] / 2]) + np.r_[_front(yaw) * 0.1, 0],
                                 got[0]))


def _picture(h: Home, kind: str) -> None:
    rng = h.rng
    ids = h.lib.image_ids(kind, h.split)
    pick = rng.uniform()
    width = rng.uniform(0.3, 1.1) if kind == "painting" else rng.uniform(0.35, 0.7)
    framed = kind == "painting" and rng.uniform() < 0.7
    fw, depth = rng.uniform(0.02, 0.07), rng.uniform(0.015, 0.035) if kind == "painting" else 0.006
    if not ids:
        return
    image = ids[min(int(pick * len(ids)), len(ids) - 1)]
    iw, ih = h.lib.image_size(image)
    height = width * ih / iw
    if height > 1.1:
        width, height = width * 1.1 / height, 1.1
    v, f, parts, outer = _canvas(width, height, framed, fw, depth, rng.uniform(0.0, 0.015))
    top_limit = h.lz - 0.15
    for _ in range(h.cfg.placement_tries):
        k = int(rng.integers(4))
        lo, hi = h.inner(k)
        s, zc = rng.uniform(lo + outer[0] / 2, hi - outer[0] / 2), rng.uniform(1.25, 1.75)
        z0 = min(max(zc - outer[2] / 2, 0.9), top_limit - outer[2])
        if z0 < 0.9 or hi - lo < outer[0]:
            continue
        centre, yaw, fp = h.against(k, s, outer[0], outer[1], -h.baseboard)
        if not h.fits(fp, z0, z0 + outer[2], gap=0.05, wall_margin=-0.001):
            continue
        c, sn = math.cos(yaw), math.sin(yaw)
        world = np.stack([centre[0] + c * v[:, 0] - sn * v[:, 1], centre[1] + sn * v[:, 0] + c * v[:, 1],
                          z0 + v[:, 2]], 1)
        mats = [h.sampler.picture(image), h.sampler.draw("any"), h.sampler.draw("trim")]
        h.add(Piece(h.name(kind), "object", world, f, parts, mats, "object", "wall",
                    Slot(fp, z0, z0 + outer[2], "piece"), role=kind))
        return


def _canvas(w: float, hgt: float, framed: bool, fw: float, depth: float, proud: float
            ) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[float, float, float]]:
    """A canvas box (its front face, -y, is part 0 and shows the picture; its other faces part 1) in a frame ring
    (part 2), back at y = +D/2, bottom at z = 0, centred on x.

    Returns:
        Vertices, faces, parts and the outer size ``(width, depth D, height)``.
    """
    outer_w, outer_h = (w + 2 * fw, hgt + 2 * fw) if framed else (w, hgt)
    fd = depth + proud if framed else depth
    back = fd / 2
    b = fw if framed else 0.0
    v, f = boxes([[-w / 2, back - depth, b]], [[w / 2, back, b + hgt]])
    parts = np.ones(len(f), dtype=np.int32)
    parts[4:6] = 0  # the faces of corners with the y bit clear: the -y side (see scene.boxes)
    if framed:
        rv, rf = slab_with_holes(outer_w, outer_h, fd, [(fw, fw, outer_w - fw, outer_h - fw)])
        rv = rv + [-outer_w / 2, back - fd, 0.0]
        f = np.concatenate([f, rf + len(v)])
        v = np.concatenate([v, rv])
        parts = np.concatenate([parts, np.full(len(rf), 2, dtype=np.int32)])
    return v, f, parts, (outer_w, fd, outer_h)

"""The room's shell: floor, ceiling, walls with real openings, baseboards and crown moulding, windows with their
frames, sills, glass and outdoor view, doors with linings, casings, leaves and handles, and a hall behind each door.

Frames: world (z up, metres, interior ``[0, Lx] x [0, Ly] x [0, Lz]``) and each wall's own frame (x along its inner
face, y outwards through it, z up; :class:`fruxel.train.sim.scene._Wall`). Every part is a closed box or a slab
with holes (:func:`fruxel.train.sim.scene.slab_with_holes`); parts touch along faces and never overlap.

Classes (by name): floor slab ``floor``; ceiling slab ``ceiling``; walls, baseboards and crown moulding ``wall``;
window frame, mullions, sill and panes ``window``; door lining, casings, leaves and handles ``door``; the hall's
floor, walls and ceiling ``floor``, ``wall``, ``ceiling``. The outdoor picture behind each window is drawn only
(``solid`` False): never labelled, never an obstacle.

Doors: at most one per wall, so each has its own hall (a short corridor as deep as ``HomeConfig.hall_depth``,
with its own materials, seen through an open door instead of the empty world). An open leaf swings into the room
about its hinge by up to 90 degrees; the floor in front of every door (as deep as the leaf is wide) is kept free
of furniture, so a leaf never meets a piece.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from ..scene import _Footprint, boxes, slab_with_holes
from .draft import Home, Slot

CORNER = 0.3
"""Openings keep this far from the room's inner corners, metres."""
GAP = 0.35
"""Smallest wall between two openings, metres."""


@dataclass
class Door:
    """A door opening and what fills it (wall frame)."""

    wall: int
    """Wall index."""
    x0: float
    """Opening's start along the wall, metres."""
    width: float
    """Opening width, metres."""
    height: float
    """Opening height, metres."""
    casing: float = 0.07
    """Casing width around the opening on the wall faces, metres."""
    hall: tuple[float, float] = (0.0, 0.0)
    """Range along the wall that the hall behind the door takes, its walls included (set by :func:`build`)."""
    hall_depth: float = 0.0
    """How far the hall reaches out from the wall's outer face, its back wall included, metres."""


@dataclass
class Window:
    """A window opening (wall frame)."""

    wall: int
    """Wall index."""
    x0: float
    """Opening's start along the wall, metres."""
    width: float
    """Opening width, metres."""
    z0: float
    """Sill height (top of the sill; 0 for a French window), metres."""
    z1: float
    """Top of the opening, metres."""
    sill: float = 0.0
    """Thickness of the sill below ``z0`` (0: none), metres."""


def openings(h: Home) -> None:
    """Draw the doors and windows and record their openings on the walls (fewer where the walls are full)."""
    rng, cfg = h.rng, h.cfg
    for _ in range(int(rng.integers(cfg.doors[0], cfg.doors[1] + 1))):
        double = rng.uniform() < cfg.double_door
        w = rng.uniform(1.3, 1.7) if double else rng.uniform(0.78, 0.98)
        height = min(rng.uniform(2.0, 2.2), h.lz - 0.3)
        free = [k for k in range(4) if not any(d.wall == k for d in h.doors)]
        spot = _place(h, free, w, 0.12)
        if spot is not None:
            h.walls[spot[0]].openings.append(("door", spot[1], 0.0, spot[1] + w, height))
            h.doors.append(Door(spot[0], spot[1], w, height, float(rng.uniform(0.05, 0.09))))
    for _ in range(int(rng.integers(cfg.windows[0], cfg.windows[1] + 1))):
        french = rng.uniform() < cfg.french_window
        w = rng.uniform(0.8, 1.8) if french else rng.uniform(0.6, 2.2)
        top = min(rng.uniform(1.95, 2.4), h.lz - 0.22)
        z0 = 0.0 if french else float(np.clip(top - rng.uniform(0.8, 1.6), 0.35, top - 0.5))
        sill = 0.0 if french else float(rng.uniform(0.02, 0.04))
        spot = _place(h, list(range(4)), w, 0.0)
        if spot is not None:
            h.walls[spot[0]].openings.append(("window", spot[1], z0 - sill, spot[1] + w, top))
            h.windows.append(Window(spot[0], spot[1], w, z0, top, sill))


def _place(h: Home, walls: list[int], w: float, casing: float) -> tuple[int, float] | None:
    rng = h.rng
    for _ in range(h.cfg.placement_tries):
        pick, where = rng.uniform(), rng.uniform()
        if not walls:
            return None
        k = walls[min(int(pick * len(walls)), len(walls) - 1)]
        lo, hi = h.inner(k)
        lo, hi = lo + CORNER + casing, hi - CORNER - casing - w
        if hi < lo:
            continue
        x0 = lo + where * (hi - lo)
        if all(x0 + w + GAP + casing <= a or x0 >= b + GAP + casing for _, a, _, b, _ in h.walls[k].openings):
            return k, float(x0)
    return None


def build(h: Home) -> None:
    """The floor, ceiling, walls, trim, windows, doors and halls of the room (after :func:`openings`)."""
    rng, cfg, lx, ly, lz, tw = h.rng, h.cfg, h.lx, h.ly, h.lz, h.tw
    ft = cfg.slab_thickness
    s = h.sampler
    h.add_box_piece("floor", "floor", "structure", [boxes([[-tw, -tw, -ft]], [[lx + tw, ly + tw, 0.0]])],
                    [s.draw("floor")], name="floor")
    h.add_box_piece("ceiling", "ceiling", "structure", [boxes([[-tw, -tw, lz]], [[lx + tw, ly + tw, lz + ft]])],
                    [s.draw("ceiling")], name="ceiling")
    main = s.draw("wall")
    accent = int(rng.integers(4)) if rng.uniform() < 0.2 else -1
    other = s.draw("wall")
    for k, wall in enumerate(h.walls):
        holes = [(a, z0, b, z1) for _, a, z0, b, z1 in wall.openings]
        v, f = slab_with_holes(wall.length, lz, tw, holes)
        h.add_box_piece("wall", "wall", "structure", [(wall.to_world(v), f)], [other if k == accent else main],
                        name=f"wall_{k}")
    _trim(h)
    for d in h.doors:
        _door(h, d)
        _hall(h, d)
    for w in h.windows:
        _window(h, w)


def _trim(h: Home) -> None:
    """Baseboards along the bottom of the walls (interrupted by doors and French windows) and a crown moulding
    along the top; each wall's pieces stop short of the corner where the wall along x runs through."""
    rng, cfg = h.rng, h.cfg
    base, crown = rng.uniform() < cfg.baseboard, rng.uniform() < cfg.crown
    bh, bt = rng.uniform(0.06, 0.15), rng.uniform(0.01, 0.022)
    ch, cd = rng.uniform(0.04, 0.1), rng.uniform(0.02, 0.05)
    material = h.sampler.draw("trim")
    if base:
        h.baseboard, h.baseboard_height = float(bt), float(bh)
        cuts = {k: [] for k in range(4)}
        for d in h.doors:
            cuts[d.wall].append((d.x0 - d.casing, d.x0 + d.width + d.casing))
        for w in h.windows:
            if w.z0 <= 0.0:
                cuts[w.wall].append((w.x0, w.x0 + w.width))
        h.add_box_piece("baseboard", "wall", "trim", [_run(h, cuts, bt, 0.0, bh)], [material], name="baseboard")
    if crown:
        h.add_box_piece("crown", "wall", "trim", [_run(h, {k: [] for k in range(4)}, cd, h.lz - ch, h.lz)],
                        [material], name="crown")
        # Tall pieces against a wall must stay below the moulding.
        for k, wall in enumerate(h.walls):
            a, b = h.inner(k)
            c = wall.to_world(np.array([[(a + b) / 2, -cd / 2, 0.0]]))[0]
            yaw = math.atan2(wall.along[1], wall.along[0])
            h.slots.append(Slot(_Footprint(c[0], c[1], (b - a) / 2, cd / 2, yaw), h.lz - ch, h.lz, "fixed"))


def _run(h: Home, cuts: dict[int, list[tuple[float, float]]], depth: float, z0: float, z1: float
         ) -> tuple[np.ndarray, np.ndarray]:
    """Boxes along every wall's inner face, ``depth`` into the room, from ``z0`` to ``z1``, skipping ``cuts``."""
    lo_all, hi_all = [], []
    for k, wall in enumerate(h.walls):
        a, b = h.inner(k)
        if k % 2 == 1:
            a, b = a + depth, b - depth
        segments = [(a, b)]
        for c0, c1 in sorted(cuts[k]):
            segments = [p for s0, s1 in segments for p in ((s0, min(s1, c0)), (max(s0, c1), s1)) if p[1] - p[0] > 0.01]
        for s0, s1 in segments:
            corners = wall.to_world(np.array([[s0, -depth, z0], [s1, 0.0, z1]]))
            lo_all.append(corners.min(axis=0))
            hi_all.append(corners.max(axis=0))
    return boxes(np.array(lo_all).reshape(-1, 3), np.array(hi_all).reshape(-1, 3))


def _local_boxes(wall, lo: list[list[float]], hi: list[list[float]]) -> tuple[np.ndarray, np.ndarray]:
    """Axis-aligned boxes given in a wall's frame, in the world (walls are axis-aligned, so they stay boxes)."""
    v, f = boxes(np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64))
    return _flip_if_mirrored(wall, wall.to_world(v), f)


def _flip_if_mirrored(wall, v: np.ndarray, f: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # A wall frame is a proper rotation (along x normal = up), so windings stay outward; kept as a check.
    a = np.array([wall.along[0], wall.along[1], 0.0])
    n = np.array([wall.normal[0], wall.normal[1], 0.0])
    return (v, f) if np.cross(a, n)[2] > 0 else (v, f[:, ::-1])


def _window(h: Home, w: Window) -> None:
    """Frame and mullions, panes, the sill and the outdoor view of one window."""
    rng, tw, wall = h.rng, h.tw, h.walls[w.wall]
    fd = rng.uniform(0.05, min(0.12, tw - 0.02))
    yf = tw - fd - rng.uniform(0.0, 0.4) * (tw - fd)
    fw = rng.uniform(0.04, 0.08)
    height = w.z1 - w.z0
    v, f = slab_with_holes(w.width, height, fd, [(fw, fw, w.width - fw, height - fw)])
    parts = [(v + [w.x0, yf, w.z0], f)]
    xs, zs = _mullions(rng, w.width - 2 * fw, height - 2 * fw)
    bars_lo, bars_hi, panes_lo, panes_hi = [], [], [], []
    gd = fd * rng.uniform(0.6, 0.9)
    gy = yf + (fd - gd) / 2
    x_in, z_in = w.x0 + fw, w.z0 + fw
    for i, (a, b) in enumerate(zip(xs[:-1], xs[1:], strict=True)):
        if i > 0:
            bars_lo.append([x_in + a[0], yf, z_in])
            bars_hi.append([x_in + a[1], yf + fd, z_in + zs[-1][1]])
        for j, (c, e) in enumerate(zip(zs[:-1], zs[1:], strict=True)):
            if j > 0:
                bars_lo.append([x_in + a[1], yf, z_in + c[0]])
                bars_hi.append([x_in + b[0], yf + fd, z_in + c[1]])
            panes_lo.append([x_in + a[1], gy, z_in + c[1]])
            panes_hi.append([x_in + b[0], gy + gd, z_in + e[0]])
    if bars_lo:
        parts.append(boxes(bars_lo, bars_hi))
    v, f = _concat_local(parts)
    frame = h.sampler.draw("trim")
    n = h.windows.index(w)
    h.add_box_piece("window", "window", "window", [(wall.to_world(v), f)], [frame], name=f"window_{n}_frame")
    h.add_box_piece("window", "window", "window", [_local_boxes(wall, panes_lo, panes_hi)], [h.sampler.draw("glass")],
                    name=f"window_{n}_glass")
    if w.sill > 0:
        p, e = rng.uniform(0.02, 0.06), rng.uniform(0.02, 0.08)
        lo = [[w.x0, -p, w.z0 - w.sill], [w.x0 - e, -p, w.z0 - w.sill], [w.x0 + w.width, -p, w.z0 - w.sill]]
        hi = [[w.x0 + w.width, tw, w.z0], [w.x0, 0.0, w.z0], [w.x0 + w.width + e, 0.0, w.z0]]
        h.add_box_piece("window", "window", "window", [_local_boxes(wall, lo, hi)], [h.sampler.draw("trim")],
                        name=f"window_{n}_sill")
    # Tall furniture must not stand in front of the glass; what is lower than the sill may.
    depth = 0.15
    c = wall.to_world(np.array([[w.x0 + w.width / 2, -depth / 2, 0.0]]))[0]
    yaw = math.atan2(wall.along[1], wall.along[0])
    h.slots.append(Slot(_Footprint(c[0], c[1], w.width / 2 + 0.08, depth / 2, yaw), max(w.z0 - w.sill - 0.02, 0.0),
                        w.z1, "window"))
    _view(h, w, n)


def _mullions(rng: np.random.Generator, width: float, height: float
              ) -> tuple[list[tuple[float, float]], list[tuple[float, float]]]:
    """Bar positions inside a frame: ``(start, end)`` of each bar along x and z, the frame's inner edges included
    as zero-width bars at both ends."""
    nv = 0 if width < 0.7 else int(rng.choice([0, 1, 1, 2, 3])) if width > 1.5 else int(rng.choice([0, 1, 1]))
    nh = int(rng.choice([0, 0, 1, 2])) if height > 1.0 else 0
    bw = rng.uniform(0.03, 0.06)
    xs = [(0.0, 0.0)] + [(c - bw / 2, c + bw / 2) for c in np.linspace(0, width, nv + 2)[1:-1]] + [(width, width)]
    # Transoms a third of the height or more apart, so that no pane is thinner than its bars.
    cuts = [rng.uniform(0.55, 0.8)] if nh == 1 else [rng.uniform(0.25, 0.4), rng.uniform(0.65, 0.8)] if nh else []
    zs = [(0.0, 0.0)] + [(height * c - bw / 2, height * c + bw / 2) for c in cuts] + [(height, height)]
    return xs, zs


def _concat_local(parts: list[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, n = [], [], 0
    for v, f in parts:
        vs.append(np.asarray(v, dtype=np.float64))
        fs.append(np.asarray(f) + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def _view(h: Home, w: Window, n: int) -> None:
    """The outdoor picture on a plane behind the window, facing the room, wide enough to fill the opening from
    most of the room (clipped to the wall's outer extent and away from halls on the same wall)."""
    rng, tw, wall = h.rng, h.tw, h.walls[w.wall]
    ids = h.lib.image_ids("outdoor", h.split)
    pick, d, spread, lift = rng.uniform(), rng.uniform(*h.cfg.outdoor_distance), rng.uniform(1.2, 2.0), \
        rng.uniform(-0.3, 0.2)
    if not ids:
        return
    image = ids[min(int(pick * len(ids)), len(ids) - 1)]
    iw, ih = h.lib.image_size(image)
    outer = (0.0, h.lx + 2 * tw) if w.wall % 2 == 0 else (-tw, h.ly + tw)
    xa, xb = max(w.x0 - d * spread, outer[0]), min(w.x0 + w.width + d * spread, outer[1])
    for door in h.doors:
        if door.wall == w.wall:
            ha, hb = door.hall
            if d < door.hall_depth + 0.3:
                xa, xb = (xa, min(xb, ha - 0.01)) if ha > w.x0 else (max(xa, hb + 0.01), xb)
    height = max((xb - xa) * ih / iw, (w.z1 - w.z0) + 2 * d * 0.8)
    zc = (w.z0 + w.z1) / 2 + lift * (w.z1 - w.z0)
    y = tw + d
    v = np.array([[xa, y, zc - height / 2], [xb, y, zc - height / 2], [xb, y, zc + height / 2],
                  [xa, y, zc + height / 2]])
    f = np.array([[0, 1, 2], [0, 2, 3]])
    piece = h.add_box_piece("view", "empty", "view", [(wall.to_world(v), f)],
                            [h.sampler.picture(image, emission=float(rng.uniform(0.8, 1.6)))],
                            name=f"window_{n}_view")
    piece.solid = False


def _door(h: Home, d: Door) -> None:
    """Lining and casings (label door), the leaves and their handles, and the floor kept free in front."""
    rng, tw, wall = h.rng, h.tw, h.walls[d.wall]
    jt, ct, cw = rng.uniform(0.02, 0.035), rng.uniform(0.01, 0.022), d.casing
    x0, x1, top = d.x0, d.x0 + d.width, d.height
    lo = [[x0, 0.0, 0.0], [x1 - jt, 0.0, 0.0], [x0 + jt, 0.0, top - jt]]
    hi = [[x0 + jt, tw, top], [x1, tw, top], [x1 - jt, tw, top]]
    for y0, y1 in ((-ct, 0.0), (tw, tw + ct)):
        lo += [[x0 - cw, y0, 0.0], [x1 - jt, y0, 0.0], [x0 + jt, y0, top - jt]]
        hi += [[x0 + jt, y1, top + cw], [x1 + cw, y1, top + cw], [x1 - jt, y1, top + cw]]
    n = h.doors.index(d)
    h.add_box_piece("door", "door", "door", [_local_boxes(wall, lo, hi)], [h.sampler.draw("trim")],
                    name=f"door_{n}_frame")
    is_open = rng.uniform() < h.cfg.open_door
    double = d.width > 1.2
    clear = d.width - 2 * jt
    lw = clear / 2 - 0.005 if double else clear - 0.006
    lt, lh = rng.uniform(0.035, 0.045), top - jt - 0.011
    yl = rng.uniform(0.0, max(tw - lt, 0.0) * 0.3)
    leaf_mat, handle_mat = h.sampler.draw("door"), h.sampler.draw("metal")
    panels = rng.uniform() < 0.5
    hinges = [(x0 + jt + 0.003, 1.0), (x1 - jt - 0.003, -1.0)] if double else \
        [((x0 + jt + 0.003, 1.0) if rng.uniform() < 0.5 else (x1 - jt - 0.003, -1.0))]
    for k, (xh, sigma) in enumerate(hinges):
        angle = math.radians(rng.uniform(*h.cfg.door_angle)) if is_open else 0.0
        leaf, handle = _leaf(rng, lw, lt, lh, panels)
        parts = []
        for v, f in (leaf, handle):
            # Leaf frame (u from the hinge along the leaf, v across it from the room side, z up) to the wall frame,
            # turned about the hinge into the room.
            phi = -sigma * angle
            dx, dy = sigma * v[:, 0], v[:, 1]
            local = np.stack([xh + dx * math.cos(phi) - dy * math.sin(phi),
                              yl + dx * math.sin(phi) + dy * math.cos(phi), v[:, 2] + 0.008], axis=1)
            fw = f if sigma > 0 else f[:, ::-1]
            parts.append((wall.to_world(local), fw))
        piece = h.add_box_piece("door", "door", "door", parts, [leaf_mat, handle_mat], name=f"door_{n}_leaf_{k}")
        piece.slot = Slot(_rect(piece.vertices), 0.0, top, "leaf")
    depth = max(h.cfg.door_clearance, lw + 0.15)
    c = wall.to_world(np.array([[x0 + d.width / 2, -depth / 2, 0.0]]))[0]
    yaw = math.atan2(wall.along[1], wall.along[0])
    h.slots.append(Slot(_Footprint(c[0], c[1], d.width / 2 + cw + 0.05, depth / 2, yaw), 0.0, 2.3, "keepout"))


def _leaf(rng: np.random.Generator, lw: float, lt: float, lh: float, panels: bool
          ) -> tuple[tuple[np.ndarray, np.ndarray], tuple[np.ndarray, np.ndarray]]:
    """A leaf (with raised panels on both faces, maybe) and its two lever handles, in the leaf frame (u along the
    leaf from the hinge, v across from the room side, z up from the leaf's bottom)."""
    lo, hi = [[0.0, 0.0, 0.0]], [[lw, lt, lh]]
    if panels:
        rows, m, p = int(rng.integers(1, 4)), rng.uniform(0.08, 0.12), 0.006
        zs = np.linspace(m, lh - m, rows + 1)
        for z0, z1 in zip(zs[:-1], zs[1:], strict=True):
            for v0, v1 in ((-p, 0.0), (lt, lt + p)):
                lo.append([m, v0, z0 + 0.04])
                hi.append([lw - 0.13, v1, z1 - 0.04])
    leaf = boxes(lo, hi)
    hz, u = rng.uniform(0.95, 1.05), lw - rng.uniform(0.055, 0.075)
    lo, hi = [], []
    for side in (-1.0, 1.0):
        face = 0.0 if side < 0 else lt
        lo += [[u - 0.025, min(face, face + 0.012 * side), hz - 0.04],
               [u - 0.008, min(face + 0.012 * side, face + 0.055 * side), hz - 0.008],
               [u - 0.13, min(face + 0.055 * side, face + 0.075 * side), hz - 0.01]]
        hi += [[u + 0.025, max(face, face + 0.012 * side), hz + 0.04],
               [u + 0.008, max(face + 0.012 * side, face + 0.055 * side), hz + 0.008],
               [u + 0.008, max(face + 0.055 * side, face + 0.075 * side), hz + 0.01]]
    return leaf, boxes(lo, hi)


def _rect(v: np.ndarray) -> _Footprint:
    """The smallest rectangle, among orientations every 5 degrees, around points' floor projections."""
    xy = v[:, :2]
    best = None
    for deg in range(0, 90, 5):
        a = math.radians(deg)
        ax = np.array([[math.cos(a), math.sin(a)], [-math.sin(a), math.cos(a)]])
        p = xy @ ax.T
        lo, hi = p.min(axis=0), p.max(axis=0)
        area = float(np.prod(hi - lo))
        if best is None or area < best[0]:
            c = ((lo + hi) / 2) @ ax
            best = (area, _Footprint(float(c[0]), float(c[1]), float((hi - lo)[0] / 2), float((hi - lo)[1] / 2), a))
    return best[1]


def _hall(h: Home, d: Door) -> None:
    """A short corridor behind the door: floor, ceiling and three walls, with materials of their own."""
    rng, tw, lz, wall = h.rng, h.tw, h.lz, h.walls[d.wall]
    ht, depth = rng.uniform(0.1, 0.15), rng.uniform(*h.cfg.hall_depth)
    outer = (0.0, h.lx + 2 * tw) if d.wall % 2 == 0 else (-tw, h.ly + tw)
    xa = max(d.x0 - d.casing - rng.uniform(0.1, 1.5), outer[0] + ht)
    xb = min(d.x0 + d.width + d.casing + rng.uniform(0.1, 1.5), outer[1] - ht)
    d.hall, d.hall_depth = (xa - ht, xb + ht), depth + ht
    ft = h.cfg.slab_thickness
    y0, y1 = tw, tw + depth
    s = h.sampler
    h.add_box_piece("hall", "floor", "structure", [_local_boxes(wall, [[xa - ht, y0, -ft]], [[xb + ht, y1 + ht, 0.0]])],
                    [s.draw("floor")], name=f"hall_{h.doors.index(d)}_floor")
    h.add_box_piece("hall", "ceiling", "structure",
                    [_local_boxes(wall, [[xa - ht, y0, lz]], [[xb + ht, y1 + ht, lz + ft]])], [s.draw("ceiling")],
                    name=f"hall_{h.doors.index(d)}_ceiling")
    lo = [[xa - ht, y0, 0.0], [xb, y0, 0.0], [xa - ht, y1, 0.0]]
    hi = [[xa, y1, lz], [xb + ht, y1, lz], [xb + ht, y1 + ht, lz]]
    h.add_box_piece("hall", "wall", "structure", [_local_boxes(wall, lo, hi)], [s.draw("wall")],
                    name=f"hall_{h.doors.index(d)}_walls")

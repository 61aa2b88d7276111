"""Furniture placed by context: what a room type holds, and where each piece goes relative to the walls and to
the pieces it belongs with.

Room types (:data:`PLANS`; each entry is tried with its chance, in order, so the main group comes first)

* ``living``: a sofa against a wall, a coffee table in front of it, armchairs at the table's ends facing it, a
  side table at the sofa's end, a TV unit against the opposite wall facing the sofa; shelves, cabinets;
* ``bedroom``: a bed with its head against a wall, nightstands on either side of the head (with lamps), a
  wardrobe, a dresser, maybe a desk with its chair;
* ``dining``: a table with chairs around it (facing it, a gap from its edge), a sideboard, shelves;
* ``office``: desks against walls with chairs at them, bookcases, cabinets, an armchair;
* ``kitchen``: a run of lower cabinets and appliances along a wall under one worktop, a tall unit or fridge at its
  end, upper cabinets above (not over windows), and a small table with chairs;
* ``studio``: a bed, a sofa group, a small table with chairs, a desk.

Then ``HomeConfig.extra_furniture`` more storage, seats and floor clutter, and the sculptures (on the floor, on a
pedestal, or small ones left for the furniture's tops). Pieces against walls stand with their back (the canonical
+y) to the wall, in front of the baseboard; everything stands on the floor (z = 0; :mod:`.decor` raises what
stands on a rug by the rug's thickness). A piece is left out when none of ``HomeConfig.placement_tries`` spots is
free (:class:`.draft.Home.fits`).

Meshes come from the pack (:mod:`.library`'s roles) in the room's asset split; a role the split lacks, or a piece
``HomeConfig.procedural`` picks, is built from boxes (:mod:`.procedural`). Labels: the pack's label of the mesh
(``furniture`` for furniture, appliances and kitchen units, ``object`` for TVs, lamps, plants and clutter,
``sculpture`` for statues, people and animals), or the role's for built pieces (:data:`ROLE_LABEL`).
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from ..scene import Material, boxes
from .draft import Home, Piece, Slot, footprint_of
from .library import ROLES, Prop
from .procedural import BUILDERS, _Parts

ROLE_LABEL: dict[str, str] = {
    **dict.fromkeys(("tv", "computer", "floor_lamp", "table_lamp", "ceiling_lamp", "wall_lamp", "floor_plant",
                     "small_plant", "rug", "clutter", "floor_clutter", "wall_clock"), "object"),
    **dict.fromkeys(("statue", "figure"), "sculpture"),
}
"""Class name of each role's built pieces; roles not listed are ``furniture``."""

PLANS: dict[str, tuple[tuple[str, float], ...]] = {
    "living": (("sofa_group", 1.0), ("storage:shelf", 0.8), ("storage:cabinet", 0.5), ("storage:dresser", 0.4),
               ("armchair", 0.3), ("piano", 0.1), ("fireplace", 0.2), ("desk", 0.2), ("small_dining", 0.25)),
    "bedroom": (("bed", 1.0), ("storage:wardrobe", 0.8), ("storage:dresser", 0.6), ("desk", 0.35),
                ("armchair", 0.35), ("storage:shelf", 0.4)),
    "dining": (("dining", 1.0), ("storage:dresser", 0.8), ("storage:shelf", 0.5), ("storage:cabinet", 0.5),
               ("armchair", 0.2)),
    "office": (("desk", 1.0), ("desk", 0.4), ("storage:shelf", 0.9), ("storage:shelf", 0.6),
               ("storage:cabinet", 0.6), ("armchair", 0.5), ("sofa_group", 0.15)),
    "kitchen": (("kitchen", 1.0), ("small_dining", 0.8), ("storage:cabinet", 0.4), ("storage:shelf", 0.3)),
    "studio": (("bed", 0.9), ("sofa_group", 0.7), ("small_dining", 0.6), ("desk", 0.5), ("storage:shelf", 0.6),
               ("storage:wardrobe", 0.5)),
}
"""What each room type places (module docstring): ``(group, chance)`` in order."""

EXTRAS = ("storage:shelf", "storage:cabinet", "armchair", "storage:dresser", "floor_clutter", "side_table")
"""What ``HomeConfig.extra_furniture`` draws from, uniformly."""


def prop_for(h: Home, role: str) -> Prop | None:
    """A mesh for ``role``: one of the pack's in the room's split, or a built one (module docstring); None when
    neither exists. Always draws the same two numbers first, so a missing role does not shift later draws."""
    coin, pick = h.rng.uniform(), h.rng.uniform()
    ids = h.lib.role_ids(role, h.split)
    if ids and coin >= h.cfg.procedural:
        return h.lib.prop(ids[min(int(pick * len(ids)), len(ids) - 1)])
    builder = BUILDERS.get(role)
    return builder(h.rng) if builder is not None else None


def label_of(h: Home, prop: Prop, role: str) -> str:
    """The class a prop of ``role`` is labelled as."""
    if prop.asset is not None:
        return h.lib.pack.entry(prop.asset).label
    return ROLE_LABEL.get(role, "furniture")


def stand(h: Home, prop: Prop, role: str, x: float, y: float, yaw: float, *, z: float = 0.0, mount: str = "floor",
          kind: str = "piece", shared: dict[Any, Material] | None = None, check: bool = True,
          gap: float | None = None, wall_margin: float = 0.005) -> Piece | None:
    """Put ``prop`` at ``(x, y, z)`` turned by ``yaw``, if its slot is free (or ``check`` is False)."""
    fp = footprint_of(prop, x, y, yaw)
    top = z + float(prop.size[2])
    if check and not h.fits(fp, z, top, gap, wall_margin=wall_margin):
        return None
    label = label_of(h, prop, role)
    layer = label if label in ("furniture", "sculpture", "object") else "furniture"
    body = ROLES[role].body if role in ROLES else "wood"
    return h.place(prop, role, label, layer, x, y, z, yaw, mount, body, shared, Slot(fp, z, top, kind))


def along_wall(h: Home, prop: Prop, role: str, k: int | None = None, s: float | None = None, tries: int | None = None,
               z: float = 0.0, mount: str = "floor", kind: str = "piece", shared: dict[Any, Material] | None = None,
               gap: float | None = None) -> tuple[Piece, int, float] | None:
    """Put ``prop`` with its back to a wall (wall ``k`` at ``s`` when given, else random ones). Things hung on the
    wall above the baseboard touch the wall; things standing on the floor stand a little in front of the baseboard.

    Returns:
        The piece, its wall and its position along the wall, or None when no try was free.
    """
    rng = h.rng
    size = prop.size
    hung = mount == "wall" and z >= h.baseboard_height
    for _ in range(tries or h.cfg.placement_tries):
        kk = int(rng.integers(4)) if k is None else k
        lo, hi = h.inner(kk)
        where, drawn = rng.uniform(), rng.uniform(0.005, 0.03)
        back = drawn if gap is None else gap
        if hi - lo < size[0] + 0.02:
            continue
        ss = lo + size[0] / 2 + 0.01 + where * (hi - lo - size[0] - 0.02) if s is None else s
        centre, yaw, _ = h.against(kk, ss, float(size[0]), float(size[1]), -h.baseboard if hung else back)
        piece = stand(h, prop, role, float(centre[0]), float(centre[1]), yaw, z=z, mount=mount, kind=kind,
                      shared=shared, wall_margin=-0.001 if hung else 0.005)
        if piece is not None:
            return piece, kk, float(ss)
    return None


def _front(yaw: float) -> np.ndarray:
    """World direction of a piece's front (canonical -y) at ``yaw``."""
    return np.array([math.sin(yaw), -math.cos(yaw)])


def _right(yaw: float) -> np.ndarray:
    """World direction of a piece's canonical +x at ``yaw``."""
    return np.array([math.cos(yaw), math.sin(yaw)])


def furnish(h: Home, room_type: str) -> None:
    """Place the room type's groups, the extras and the sculptures (module docstring)."""
    rng = h.rng
    for group, chance in PLANS[room_type]:
        if rng.uniform() < chance:
            _group(h, group)
    for _ in range(int(rng.integers(h.cfg.extra_furniture[0], h.cfg.extra_furniture[1] + 1))):
        _group(h, EXTRAS[int(rng.integers(len(EXTRAS)))])
    for _ in range(int(rng.integers(h.cfg.plants[0], h.cfg.plants[1] + 1))):
        _corner_piece(h, "floor_plant")
    if rng.uniform() < 0.6:
        _corner_piece(h, "floor_lamp")
    for _ in range(int(rng.integers(h.cfg.sculptures[0], h.cfg.sculptures[1] + 1))):
        _sculpture(h)


def _group(h: Home, group: str) -> None:
    if group.startswith("storage:"):
        role = group.split(":", 1)[1]
        found = _against_wall(h, role)
        if found is not None and role == "dresser" and h.rng.uniform() < 0.5:
            found[1][0].wants.append("table_lamp")
        return
    {"sofa_group": _sofa_group, "bed": _bed, "dining": _dining, "small_dining": lambda x: _dining(x, small=True),
     "desk": _desk, "kitchen": _kitchen, "armchair": _free_seat,
     "piano": lambda x: _simple(x, "piano"), "fireplace": lambda x: _simple(x, "fireplace"),
     "floor_clutter": lambda x: _corner_piece(x, "floor_clutter"),
     "side_table": lambda x: _simple(x, "side_table")}[group](h)


def _against_wall(h: Home, role: str) -> tuple[Prop, tuple[Piece, int, float]] | None:
    """A prop for ``role`` with its back to a wall (:func:`along_wall`): ``(prop, (piece, wall, position))``, or
    None when the pack has none or no wall has room."""
    prop = prop_for(h, role)
    placed = along_wall(h, prop, role) if prop is not None else None
    return (prop, placed) if placed is not None else None


def _simple(h: Home, role: str) -> Piece | None:
    found = _against_wall(h, role)
    return found[1][0] if found else None


def _bed(h: Home) -> None:
    """A bed with its head to a wall, nightstands beside the head, maybe a rug under its foot half."""
    rng = h.rng
    found = _against_wall(h, "bed")
    if found is None:
        return
    prop, (bed, k, s) = found
    width = float(prop.size[0])
    for side in (-1.0, 1.0):
        if rng.uniform() < 0.8:
            ns = prop_for(h, "nightstand")
            if ns is None:
                continue
            s2 = s + side * (width / 2 + rng.uniform(0.03, 0.12) + ns.size[0] / 2)
            got = along_wall(h, ns, "nightstand", k=k, s=s2, tries=1)
            if got is not None and rng.uniform() < 0.8:
                got[0].wants.append("table_lamp")
    if rng.uniform() < 0.4:
        x, y, _, yaw = bed.pose
        c = np.array([x, y]) + _front(yaw) * prop.size[1] * rng.uniform(0.15, 0.4)
        h.rug_spots.append((c, yaw, width + rng.uniform(0.4, 1.2), prop.size[1] * rng.uniform(0.5, 0.8)))


def _sofa_group(h: Home) -> None:
    """A sofa against a wall, a coffee table in front, armchairs facing the table, a side table, a TV unit
    against the opposite wall facing the sofa, and a rug under the table."""
    rng = h.rng
    found = _against_wall(h, "sofa")
    if found is None:
        return
    prop, (sofa, k, s) = found
    x, y, _, yaw = sofa.pose
    centre, front, right = np.array([x, y]), _front(yaw), _right(yaw)
    table_at = centre + front * (prop.size[1] / 2 + 0.85)
    ct = prop_for(h, "coffee_table") if rng.uniform() < 0.85 else None
    width = 1.0
    if ct is not None:
        table_at = centre + front * (prop.size[1] / 2 + rng.uniform(0.3, 0.5) + ct.size[1] / 2)
        if stand(h, ct, "coffee_table", *table_at, yaw) is not None:
            width = float(ct.size[0])
            if rng.uniform() < 0.6:
                h.rug_spots.append((table_at, yaw, width + rng.uniform(0.6, 1.4), ct.size[1] + rng.uniform(0.8, 1.4)))
    for side in rng.permutation([-1.0, 1.0])[:int(rng.choice([0, 1, 1, 2]))]:
        ac = prop_for(h, "armchair")
        if ac is not None:
            at = table_at + right * side * (width / 2 + rng.uniform(0.25, 0.5) + ac.size[1] / 2)
            stand(h, ac, "armchair", *at, yaw - side * math.pi / 2 + rng.uniform(-0.2, 0.2))
    if rng.uniform() < 0.5:
        st = prop_for(h, "side_table")
        side = 1.0 if rng.uniform() < 0.5 else -1.0
        if st is not None:
            got = along_wall(h, st, "side_table", k=k, s=s + side * (prop.size[0] / 2 + 0.05 + st.size[0] / 2),
                             tries=1)
            if got is not None:
                got[0].wants.append("table_lamp")
    if rng.uniform() < 0.7:
        unit = prop_for(h, "tv_unit")
        opposite = (k + 2) % 4
        w = h.walls[opposite]
        s_opp = float(np.dot(centre - w.start, w.along))
        if unit is not None:
            got = along_wall(h, unit, "tv_unit", k=opposite, s=s_opp + rng.uniform(-0.3, 0.3), tries=1)
            got = got or along_wall(h, unit, "tv_unit", k=opposite, tries=5)
            if got is not None:
                got[0].wants.append("tv")


def _dining(h: Home, small: bool = False) -> None:
    """A table (free-standing, or against a wall when small) with chairs around it facing it."""
    rng = h.rng
    chair = prop_for(h, "chair")
    table = None
    for role in ("small_table",) if small else ("dining_table", "small_table"):
        prop = prop_for(h, role)
        if prop is None or chair is None:
            continue
        cd = float(max(chair.size[0], chair.size[1]))
        for _ in range(h.cfg.placement_tries):
            yaw = float(rng.choice([0.0, math.pi / 2])) + rng.uniform(-0.04, 0.04)
            x, y = rng.uniform(0.0, h.lx), rng.uniform(0.0, h.ly)
            # Room for the chairs around it first.
            if h.fits(footprint_of(prop, x, y, yaw, grow=cd + 0.05), 0.0, 1.2):
                table = stand(h, prop, role, x, y, yaw)
                if table is not None:
                    break
        if table is not None:
            break
    if table is None:
        return
    table.wants.append("small_plant" if rng.uniform() < 0.5 else "clutter")
    _chairs_around(h, table, prop, chair)
    x, y, _, yaw = table.pose
    if rng.uniform() < 0.5:
        h.pendants.append(np.array([x, y]))
    if rng.uniform() < 0.3:
        h.rug_spots.append((np.array([x, y]), yaw, prop.size[0] + 2 * cd + rng.uniform(0.2, 0.8),
                            prop.size[1] + 2 * cd + rng.uniform(0.2, 0.8)))


def _chairs_around(h: Home, table: Piece, prop: Prop, chair: Prop) -> None:
    """Chairs along the table's long sides (and ends, when it is long), each facing the table."""
    rng = h.rng
    x, y, _, yaw = table.pose
    w, d = float(prop.size[0]), float(prop.size[1])
    cd = float(chair.size[1])
    shared: dict[Any, Material] = {}
    spots = []
    n = max(1, int((w - 0.1) / rng.uniform(0.55, 0.7)))
    for side in (-1.0, 1.0):
        for xi in (np.linspace(-w / 2, w / 2, n + 2)[1:-1] if n > 1 else [0.0]):
            # A chair on the table's +y side faces -y (its canonical front): yaw as the table's.
            spots.append((xi, side * (d / 2 + rng.uniform(0.02, 0.12) + cd / 2), yaw if side > 0 else yaw + math.pi))
    if w > 1.3 and rng.uniform() < 0.5:
        for side in (-1.0, 1.0):
            spots.append((side * (w / 2 + rng.uniform(0.02, 0.12) + cd / 2), 0.0, yaw - side * math.pi / 2))
    for lx, ly, cyaw in spots:
        if rng.uniform() < 0.15:
            continue
        c, s = math.cos(yaw), math.sin(yaw)
        at = (x + c * lx - s * ly, y + s * lx + c * ly)
        stand(h, chair, "chair", *at, cyaw + rng.uniform(-0.15, 0.15), shared=shared)


def _desk(h: Home) -> None:
    """A desk against a wall with a chair at it, facing it."""
    rng = h.rng
    found = _against_wall(h, "desk")
    if found is None:
        return
    prop, (desk, _, _) = found
    desk.wants.append("computer" if rng.uniform() < 0.5 else "table_lamp")
    chair = prop_for(h, "chair")
    if chair is not None:
        x, y, _, yaw = desk.pose
        at = np.array([x, y]) + _front(yaw) * (prop.size[1] / 2 + rng.uniform(0.03, 0.15) + chair.size[1] / 2)
        stand(h, chair, "chair", *at, yaw + math.pi + rng.uniform(-0.3, 0.3))


def _free_seat(h: Home, role: str = "armchair") -> None:
    """A seat turned towards the room's middle, somewhere free."""
    rng = h.rng
    prop = prop_for(h, role)
    if prop is None:
        return
    for _ in range(h.cfg.placement_tries):
        x, y = rng.uniform(0.0, h.lx), rng.uniform(0.0, h.ly)
        to_mid = np.array([h.lx / 2 - x, h.ly / 2 - y])
        yaw = math.atan2(to_mid[0], -to_mid[1]) + rng.uniform(-0.5, 0.5)
        if stand(h, prop, role, x, y, yaw) is not None:
            return


def _corner_piece(h: Home, role: str) -> None:
    """A piece against a wall near one of its ends (a plant or a lamp in a corner), else anywhere along it."""
    rng = h.rng
    prop = prop_for(h, role)
    if prop is None:
        return
    for _ in range(h.cfg.placement_tries):
        k = int(rng.integers(4))
        lo, hi = h.inner(k)
        near, off = rng.uniform(), rng.uniform(0.0, 0.4)
        half = float(prop.size[0]) / 2 + 0.03
        s = lo + half + off if near < 0.5 else hi - half - off
        if along_wall(h, prop, role, k=k, s=s, tries=1) is not None:
            return
    along_wall(h, prop, role)


KITCHEN_GAP = 0.01
"""Gap between a kitchen run's backs and the baseboard, metres: the units and their worktop line up at the back."""


def _kitchen(h: Home) -> None:
    """A run of lower units and appliances along a wall under a worktop, a tall unit at its start, and upper
    cabinets above the lower units (module docstring); the walls are tried in random order until a run of two
    units or more stands."""
    for k in h.rng.permutation(4):
        if _kitchen_run(h, int(k)) >= 2:
            return


def _kitchen_run(h: Home, k: int) -> int:
    """The kitchen along wall ``k``, from one of its ends; spots a door, a French window or furniture takes are
    stepped over. Returns the number of units placed."""
    rng = h.rng
    lo, hi = h.inner(k)
    end = min(hi, lo + rng.uniform(2.0, 4.5))
    cursor, placed = lo + 0.01, 0
    if rng.uniform() < 0.6:
        tall = prop_for(h, "kitchen_tall")
        if tall is not None and along_wall(h, tall, "kitchen_tall", k=k, s=cursor + tall.size[0] / 2, tries=1,
                                           kind="fixed", gap=KITCHEN_GAP) is not None:
            cursor += float(tall.size[0]) + 0.01
            placed += 1
    run: list[Piece] = []
    shared: dict[Any, Material] = {}
    while cursor < end - 0.3:
        # Under the worktop only cabinets; an appliance (with its own top, its console) ends the worktop.
        role = "appliance" if rng.uniform() < 0.2 else "kitchen_lower"
        unit = prop_for(h, role)
        if unit is None or cursor + unit.size[0] > end:
            break
        got = along_wall(h, unit, role, k=k, s=cursor + unit.size[0] / 2, tries=1, kind="fixed",
                         shared=shared if role == "kitchen_lower" else None, gap=KITCHEN_GAP)
        if got is None or role == "appliance" or not _flat_top(unit):
            _worktop(h, run, k)
            run = []
            cursor += float(unit.size[0]) + 0.01 if got is not None else 0.1
            placed += got is not None
            continue
        run.append(got[0])
        placed += 1
        cursor += float(unit.size[0]) + 0.005
    _worktop(h, run, k)
    return placed


def _flat_top(prop: Prop) -> bool:
    """Whether a unit's top is one flat surface at its full height covering most of it (a worktop can rest on
    it; a sink's faucet or a back rail would stand in the worktop)."""
    size = prop.size
    return any(lv.z > size[2] - 0.01 and lv.area > 0.4 * size[0] * size[1] for lv in prop.levels())


def _worktop(h: Home, run: list[Piece], k: int) -> None:
    """One worktop over a row of lower units, and upper cabinets above them where the wall is free."""
    if not run:
        return
    rng = h.rng
    wall = h.walls[k]
    ss = [float(np.dot(np.array(p.pose[:2]) - wall.start, wall.along)) for p in run]
    half = [float(p.prop.size[0]) / 2 for p in run]
    a, b = min(s - w for s, w in zip(ss, half, strict=True)), max(s + w for s, w in zip(ss, half, strict=True))
    depth = max(float(p.prop.size[1]) for p in run) + 0.03
    top = max(float(p.vertices[:, 2].max()) for p in run)
    for p in run:
        # One counter height: lower units are stretched up to the tallest (a few centimetres at most).
        z0, z1 = p.slot.z0, float(p.vertices[:, 2].max())
        if z1 < top:
            p.vertices = np.column_stack([p.vertices[:, :2], z0 + (p.vertices[:, 2] - z0) * (top - z0) / (z1 - z0)])
            p.slot.z1 = top
    top += 0.002
    t = rng.uniform(0.025, 0.045)
    b_ = _Parts(("stone" if rng.uniform() < 0.5 else "wood",))
    b_.box([-(b - a) / 2, -depth / 2, 0.0], [(b - a) / 2, depth / 2, t], 0)
    worktop = b_.prop("worktop")
    got = along_wall(h, worktop, "worktop", k=k, s=(a + b) / 2, tries=1, z=top, mount="floor", kind="fixed",
                     gap=KITCHEN_GAP)
    if got is not None:
        got[0].mount = "support"
    shared: dict[Any, Material] = {}
    z = top + t + rng.uniform(0.45, 0.65)
    for s in ss:
        if rng.uniform() < 0.7:
            upper = prop_for(h, "kitchen_upper")
            if upper is not None and z + upper.size[2] < h.lz - 0.05:
                along_wall(h, upper, "kitchen_upper", k=k, s=s, tries=1, z=z, mount="wall", kind="fixed",
                           shared=shared)


def _sculpture(h: Home) -> None:
    """A statue (or, with ``HomeConfig.sculpture_figures``, an animal figurine) on the floor or on a pedestal; a
    small one may instead wait for a piece of furniture's top (:mod:`.decor`)."""
    rng = h.rng
    role = "figure" if rng.uniform() < h.cfg.sculpture_figures else "statue"
    prop = prop_for(h, role)
    if prop is None:
        return
    scale = rng.uniform(0.8, 1.25) if role == "statue" else 1.0
    size = prop.size * scale
    on_pedestal = size[2] < 0.9 and rng.uniform() < 0.7
    if size[2] < 0.6 and not on_pedestal and rng.uniform() < 0.6:
        h.small_sculptures.append((prop, role, scale))
        return
    prop = _pedestal(rng, prop, scale) if on_pedestal else _scaled(prop, scale)
    if rng.uniform() < 0.5 and along_wall(h, prop, role) is not None:
        return
    for _ in range(h.cfg.placement_tries):
        if stand(h, prop, role, rng.uniform(0.0, h.lx), rng.uniform(0.0, h.ly), rng.uniform(0, 2 * math.pi)):
            return


def _scaled(prop: Prop, scale: float) -> Prop:
    if scale == 1.0:
        return prop
    return Prop(prop.name, prop.asset, prop.vertices * scale, prop.faces, prop.parts, prop.part_roles,
                prop.part_colours, prop.elevation)


def _pedestal(rng: np.random.Generator, prop: Prop, scale: float) -> Prop:
    """The statue scaled and standing on a box or column pedestal; the pedestal is another part of the same
    piece (it belongs to the sculpture, as in the flat rooms)."""
    v = prop.vertices * scale
    foot = float(max(v[:, 0].max() - v[:, 0].min(), v[:, 1].max() - v[:, 1].min()))
    ph, pw = rng.uniform(0.6, 1.1), foot * rng.uniform(0.75, 1.0) + 0.08
    pv, pf = boxes([[-pw / 2, -pw / 2, 0.0]], [[pw / 2, pw / 2, ph]])
    parts = np.concatenate([prop.parts, np.full(len(pf), len(prop.part_roles), dtype=np.int32)])
    return Prop(prop.name, prop.asset, np.concatenate([v + [0.0, 0.0, ph], pv]),
                np.concatenate([prop.faces, pf + len(v)]), parts, (*prop.part_roles, "stone"),
                np.concatenate([prop.part_colours, [[0.7, 0.7, 0.7]]]), prop.elevation)

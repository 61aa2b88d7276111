"""Procedural rooms for the simulator: walls with real openings, windows, doors, furniture, sculptures, lights.

World frame
    Right-handed, metres, **z up**. The room's interior is the box ``[0, Lx] x [0, Ly] x [0, Lz]``
    (``room_size = (Lx, Ly, Lz)``): the top of the floor slab is the plane z = 0 and the interior's corner at
    the origin. Walls stand outside the interior on the floor slab, from z = 0 to z = Lz.

Solids
    Every object is a closed, consistently wound (outward normals) triangle mesh, or a set of such components
    in one mesh, so that :func:`fruxel.kernels.fruxelize` can label the solid containing each cell centre
    exactly: the floor is a slab, walls are slabs extruded around their openings (a wall with a window has a
    real hole, which the window's frame and glass fill), furniture is built from boxes, sculptures from spheres,
    capsules, cylinders, cones, tori and boxes. Asset meshes (:mod:`.assets`) are used as they are and may be
    open; fruxelize then applies its winding-number rule.

Order
    ``Scene.objects`` lists floor, (ceiling,) walls, windows, doors, furniture, sculptures. ``fruxelize`` lets
    later meshes win where solids overlap, so openings' fillers take precedence over walls.

Labels
    Every solid is labelled by class *name* (:data:`CLASS_NAMES`, and ``RoomConfig.ceiling_class``); its id is
    that name's index in the class table ``make_scene`` is given (the data set's ``SimConfig.classes``), so a
    table with other ids or more classes labels the same solids accordingly. Nothing here assumes the default
    table's ids.

Everything random comes from ``numpy.random.default_rng(seed)``: the same seed and config give the same scene,
bit for bit. Nothing is cached between calls.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from fruxel.classes import DEFAULT_CLASSES, ClassTable
from fruxel.errors import ConfigError

if TYPE_CHECKING:
    import trimesh

    from .assets import AssetLibrary

CLASS_NAMES = ("wall", "floor", "window", "furniture", "door", "sculpture")
"""The classes the generator labels its solids with, by name; a scene's class table must hold each of them."""

FURNITURE_KINDS = ("table", "chair", "shelf", "cabinet", "sofa")
"""Procedural furniture types."""


SceneError = ConfigError
"""An impossible room configuration: the project's one :class:`~fruxel.errors.ConfigError` (this name is kept for
the callers that catch it)."""


# ---------------------------------------------------------------------------------------------- data types
@dataclass(frozen=True)
class Material:
    """How a surface looks to a photoreal renderer, drawn independently of the surface's class.

    Textures and images are assets of the asset pack (:mod:`.assetpack`), named by id. A texture tiles the surface
    at metric scale by a world-space box projection (each face takes the two world axes most parallel to it, so a
    wall's bricks keep their size whatever the wall's extent); an image is stretched once over the part instead (a
    painting's canvas, the outdoor view behind a window).
    """

    color: tuple[float, float, float] = (0.8, 0.8, 0.8)
    """Linear RGB in [0, 1]: the base colour, multiplied with the texture or image when there is one."""
    texture: str | None = None
    """Id of a pack texture (albedo and normal map), or None for the plain colour."""
    tile_m: float = 1.0
    """Metres one tile of the texture spans (the pack's ``size_m`` for the texture, times a random scale)."""
    image: str | None = None
    """Id of a pack image stretched once over the part (planar projection onto its largest face's plane), or None."""
    roughness: float = 0.6
    """Microfacet roughness in [0, 1]."""
    metallic: float = 0.0
    """Metalness in [0, 1]."""
    opacity: float = 1.0
    """In (0, 1]: below 1 the surface is glass, and a ray goes on through it."""
    emission: float = 0.0
    """>= 0: the surface shines with its own colour (times this) besides what it reflects: the outdoor view, a
    lamp's shade."""


@dataclass(frozen=True, eq=False)
class SceneObject:
    """One labelled solid of a scene (or, with ``solid`` False, a surface that is drawn and never labelled)."""

    name: str
    """Unique name within the scene, e.g. ``"wall_2"``, ``"window_0_glass"``, ``"chair_3"``."""
    label: int
    """Class id in the scene's class table (:attr:`Scene.classes`) of the solid's class (module docstring)."""
    mesh: trimesh.Trimesh
    """Triangle mesh in the world frame, metres; closed with outward normals unless it came from an asset."""
    color: tuple[float, float, float, float]
    """Base colour RGBA in [0, 1]; alpha < 1 means a transparent material (window glass). The flat renderer's
    material; a photoreal renderer uses ``materials`` when there are any."""
    metallic: float
    """PBR metallic factor in [0, 1] (the flat renderer's)."""
    roughness: float
    """PBR roughness factor in [0, 1] (the flat renderer's)."""
    materials: tuple[Material, ...] = ()
    """The materials of the object's parts for a photoreal renderer (empty: one made from ``color``, ``metallic``
    and ``roughness``)."""
    parts: np.ndarray | None = None
    """``(F,)`` int32, per face of ``mesh``, the index of its material in ``materials`` (None: every face takes
    material 0)."""
    solid: bool = True
    """False for a surface that is drawn but is not a solid of the room (the outdoor view behind a window): never
    labelled, never in the robot's way."""
    asset: str | None = None
    """Id of the asset pack mesh the object was made from (None: built by the generator); its materials name their
    own textures and images."""
    label_mesh: tuple[np.ndarray, np.ndarray] | None = None
    """The solid the object is labelled by when it is not ``mesh``: ``(vertices (V, 3) float64 world frame,
    metres, faces (F, 3) int64)``, closed (a pack mesh that is not closed, filled: :mod:`.rooms.solids`); None:
    ``mesh`` itself."""


@dataclass(frozen=True, eq=False)
class Light:
    """A light source, in pyrender's conventions."""

    kind: str
    """``"directional"``, ``"point"`` or ``"spot"``."""
    color: tuple[float, float, float]
    """RGB in [0, 1]."""
    intensity: float
    """Directional: lux (W/m^2 in pyrender's units); point and spot: candela."""
    pose: np.ndarray
    """``(4, 4)`` float64 light-to-world transform; a directional or spot light shines along its local -z axis, a
    point or spot light sits at the translation."""
    cone: tuple[float, float] = (0.0, math.pi / 4)
    """A spot light's inner and outer cone half-angles, radians (full intensity inside the inner one, none
    outside the outer one)."""
    radius: float = 0.0
    """Size of the light, metres (a point or spot light's radius; for a directional light, the angular radius of
    the sun in radians): soft shadows where a photoreal renderer samples it; 0 is a hard point."""
    shadows: bool = True
    """Whether the light casts shadows where the renderer draws them."""


@dataclass(frozen=True, eq=False)
class FreeSpace:
    """2D occupancy map of the floor for the robot planner.

    Cell ``(r, c)`` (row r along y, column c along x) is the square ``[x0 + c s, x0 + (c + 1) s) x
    [y0 + r s, y0 + (r + 1) s)`` with ``(x0, y0) = origin`` and ``s = resolution``. A cell is occupied when the
    square intersects a wall (anything outside the room's interior) or the footprint of an object standing in
    the room (furniture, sculpture): the footprint is the rotated bounding rectangle of the object's
    projection on the floor, so the map is conservative. Points outside the map count as occupied.
    """

    occupied: np.ndarray
    """``(ny, nx)`` bool, True where the robot may not be."""
    origin: np.ndarray
    """``(2,)`` float64 world xy of the map's lower-left corner (cell (0, 0)'s minimum corner), metres."""
    resolution: float
    """Cell size in metres."""

    def cell_centres(self) -> np.ndarray:
        """World xy of every cell centre: ``(ny, nx, 2)`` float64."""
        ny, nx = self.occupied.shape
        xs = self.origin[0] + (np.arange(nx) + 0.5) * self.resolution
        ys = self.origin[1] + (np.arange(ny) + 0.5) * self.resolution
        gx, gy = np.meshgrid(xs, ys)
        return np.stack([gx, gy], axis=-1)

    def free_centres(self, radius: float) -> np.ndarray:
        """Which cell centres are collision-free positions for a disk of ``radius``: ``(ny, nx)`` bool.

        The same test as :meth:`collides` at every cell centre, computed as a dilation of the occupied cells.
        """
        s = self.resolution
        ny, nx = self.occupied.shape
        w = int(math.ceil(radius / s)) + 1
        blocked = np.ones((ny + 2 * w, nx + 2 * w), dtype=bool)
        blocked[w:w + ny, w:w + nx] = self.occupied
        out = np.zeros((ny, nx), dtype=bool)
        for dr in range(-w, w + 1):
            for dc in range(-w, w + 1):
                gx, gy = max(abs(dc) * s - s / 2, 0.0), max(abs(dr) * s - s / 2, 0.0)
                if gx * gx + gy * gy < radius * radius:
                    out |= blocked[w + dr:w + dr + ny, w + dc:w + dc + nx]
        return ~out

    def collides(self, xy: Any, radius: float) -> np.ndarray:
        """Whether a disk of ``radius`` centred at each point overlaps an occupied cell (or leaves the map).

        Args:
            xy: ``(N, 2)`` or ``(2,)`` world xy, metres.
            radius: disk radius, metres, >= 0.

        Returns:
            ``(N,)`` (or scalar) bool: True where the open disk meets an occupied cell's closed square.
        """
        p = np.asarray(xy, dtype=np.float64)
        single = p.ndim == 1
        p = p.reshape(-1, 2)
        s = self.resolution
        ny, nx = self.occupied.shape
        w = int(math.ceil(radius / s)) + 1
        off = np.arange(-w, w + 1)
        col0 = np.floor((p[:, 0] - self.origin[0]) / s).astype(np.int64)
        row0 = np.floor((p[:, 1] - self.origin[1]) / s).astype(np.int64)
        cols = col0[:, None, None] + off[None, None, :]
        rows = row0[:, None, None] + off[None, :, None]
        cx = self.origin[0] + (cols + 0.5) * s
        cy = self.origin[1] + (rows + 0.5) * s
        dx = np.maximum(np.abs(p[:, 0, None, None] - cx) - s / 2, 0.0)
        dy = np.maximum(np.abs(p[:, 1, None, None] - cy) - s / 2, 0.0)
        near = dx * dx + dy * dy < radius * radius
        inside = (cols >= 0) & (cols < nx) & (rows >= 0) & (rows < ny)
        rr, cc = np.broadcast_to(rows, near.shape), np.broadcast_to(cols, near.shape)
        occ = np.ones(near.shape, dtype=bool)
        occ[inside] = self.occupied[rr[inside], cc[inside]]
        out = (near & occ).any(axis=(1, 2))
        return bool(out[0]) if single else out


@dataclass(frozen=True, eq=False)
class Scene:
    """A generated room."""

    objects: tuple[SceneObject, ...]
    """Labelled solids in fruxelize priority order (later wins): floor, walls, windows, doors, furniture,
    sculptures."""
    room_size: np.ndarray
    """``(3,)`` float64 interior size ``(Lx, Ly, Lz)`` in metres; the interior is ``[0, Lx] x [0, Ly] x [0, Lz]``."""
    lights: tuple[Light, ...]
    """Light sources (one directional, some point lights below the ceiling)."""
    free_space: FreeSpace
    """Floor occupancy map for the robot."""
    seed: int
    """The seed the scene was made from."""
    classes: ClassTable = DEFAULT_CLASSES
    """The class table the objects' labels index."""
    ambient: tuple[float, float, float] | None = None
    """Linear RGB of the diffuse light the sky and the room's walls give everywhere (a photoreal renderer's
    ambient or sky term), or None: the renderer's own (the flat renderer's augmentation draws its ambient level)."""

    def labelled_meshes(self) -> list[tuple[np.ndarray, np.ndarray, int]]:
        """``(vertices (V, 3) float64, faces (F, 3) int64, label)`` per solid object, world frame, in priority order:
        the input of :func:`fruxel.kernels.fruxelize`; an object's ``label_mesh`` where it has one."""
        return [(*(o.label_mesh if o.label_mesh is not None else (np.asarray(o.mesh.vertices),
                                                                     np.asarray(o.mesh.faces))), o.label)
                for o in self.objects if o.solid]

    def mesh_set(self, backend: str | None = None, device: str | None = None) -> Any:
        """The scene uploaded once for many :func:`fruxel.kernels.fruxelize` calls (a user-held
        :class:`fruxel.kernels.fruxelize.MeshSet`; ``backend``, ``device`` as for it)."""
        from fruxel.kernels.fruxelize import MeshSet

        return MeshSet(self.labelled_meshes(), backend=backend, device=device)


@dataclass(frozen=True)
class RoomConfig:
    """Ranges the room generator draws from. Ranges are ``(low, high)``, inclusive for counts."""

    length_range: tuple[float, float] = (4.0, 8.0)
    """Interior size along x, metres."""
    width_range: tuple[float, float] = (3.5, 7.0)
    """Interior size along y, metres."""
    height_range: tuple[float, float] = (2.4, 3.2)
    """Interior height (floor to wall top), metres."""
    wall_thickness_range: tuple[float, float] = (0.1, 0.25)
    """Wall thickness, metres."""
    floor_thickness: float = 0.1
    """Thickness of the floor slab below z = 0, metres."""
    windows: tuple[int, int] = (1, 3)
    """Number of windows (fewer when the walls have no room left)."""
    doors: tuple[int, int] = (1, 2)
    """Number of doors (fewer when the walls have no room left)."""
    furniture: tuple[int, int] = (3, 8)
    """Number of furniture pieces (fewer when the floor is full)."""
    sculptures: tuple[int, int] = (0, 2)
    """Number of sculptures (fewer when the floor is full)."""
    furniture_kinds: tuple[str, ...] = FURNITURE_KINDS
    """Procedural furniture types to draw from (a subset of :data:`FURNITURE_KINDS`)."""
    point_lights: tuple[int, int] = (1, 3)
    """Number of point lights below the ceiling."""
    ceiling: bool = False
    """Add a ceiling slab on the walls, labelled ``ceiling_class``."""
    ceiling_class: str = "wall"
    """Class name (in the scene's class table) of the ceiling, when there is one; the default classes have no
    ceiling, so it counts as wall."""
    min_gap: float = 0.1
    """Smallest distance kept between the footprints of objects standing in the room, metres."""
    door_clearance: float = 1.0
    """Depth of the area kept free in front of (inside) each door, metres."""
    free_space_resolution: float = 0.05
    """Cell size of the free-space map, metres."""
    asset_dir: str | None = None
    """Folder of asset meshes, one sub-folder per class (see :func:`.assets.load_asset_folder`); loaded per call."""
    sh3f_files: tuple[str, ...] = ()
    """Sweet Home 3D furniture libraries (``.sh3f``) to import; loaded per call."""
    assets: AssetLibrary | None = None
    """An asset library loaded once by the caller (used together with the two options above)."""
    asset_probability: float = 0.5
    """Chance that a furniture piece, sculpture, door or window is an asset, when the library has one."""
    placement_tries: int = 40
    """Random placements tried per object before it is left out."""

    def __post_init__(self) -> None:
        for name in ("length_range", "width_range", "height_range", "wall_thickness_range"):
            lo, hi = getattr(self, name)
            if not 0 < lo <= hi:
                raise SceneError(f"{name} must satisfy 0 < low <= high, got {(lo, hi)}")
        for name in ("windows", "doors", "furniture", "sculptures", "point_lights"):
            lo, hi = getattr(self, name)
            if not 0 <= lo <= hi:
                raise SceneError(f"{name} must satisfy 0 <= low <= high, got {(lo, hi)}")
        if self.length_range[0] < 2.0 or self.width_range[0] < 2.0 or self.height_range[0] < 2.2:
            raise SceneError("rooms must be at least 2 m x 2 m and 2.2 m high")
        unknown = set(self.furniture_kinds) - set(FURNITURE_KINDS)
        if unknown or not self.furniture_kinds:
            raise SceneError(f"furniture_kinds must be a non-empty subset of {FURNITURE_KINDS}, got {unknown}")
        if self.free_space_resolution <= 0 or self.floor_thickness <= 0:
            raise SceneError("free_space_resolution and floor_thickness must be > 0")
        if not isinstance(self.ceiling_class, str) or not self.ceiling_class:
            raise SceneError(f"ceiling_class must be a class name, got {self.ceiling_class!r}")

    def class_ids(self, classes: ClassTable) -> dict[str, int]:
        """The label of each class the generator draws (:data:`CLASS_NAMES`, and the ceiling's class when there is
        a ceiling): its index in ``classes``.

        Raises:
            SceneError: ``classes`` lacks one of them.
        """
        names = (*CLASS_NAMES, self.ceiling_class) if self.ceiling else CLASS_NAMES
        missing = [n for n in dict.fromkeys(names) if n not in classes.names]
        if missing:
            raise SceneError(f"the class table lacks the simulator's classes {missing} (it has "
                             f"{list(classes.names)}); add them, e.g. with ClassTable.extended")
        return {n: classes.index(n) for n in names}


# ---------------------------------------------------------------------------------------------- mesh helpers
_BOX_FACES = np.array(
    [[0, 2, 1], [1, 2, 3], [4, 5, 6], [5, 7, 6], [0, 1, 4], [1, 5, 4],
     [2, 6, 3], [3, 6, 7], [0, 4, 2], [2, 4, 6], [1, 3, 5], [3, 7, 5]],
    dtype=np.int64,
)
"""Outward, counter-clockwise faces of a box whose corner ``c`` has x, y, z from bits 0, 1, 2 of c."""
_CORNER_BITS = np.array([[(c >> b) & 1 for b in range(3)] for c in range(8)], dtype=bool)


def boxes(lo: Any, hi: Any) -> tuple[np.ndarray, np.ndarray]:
    """Closed meshes of N axis-aligned boxes, one component each.

    Args:
        lo, hi: ``(N, 3)`` float corners (any frame).

    Returns:
        vertices ``(8N, 3)`` float64 and faces ``(12N, 3)`` int64, outward normals.
    """
    lo = np.asarray(lo, dtype=np.float64).reshape(-1, 3)
    hi = np.asarray(hi, dtype=np.float64).reshape(-1, 3)
    v = np.where(_CORNER_BITS[None], hi[:, None, :], lo[:, None, :]).reshape(-1, 3)
    f = (_BOX_FACES[None] + 8 * np.arange(len(lo))[:, None, None]).reshape(-1, 3)
    return v, f


def slab_with_holes(length: float, height: float, thickness: float, holes: Sequence[Sequence[float]]
                    ) -> tuple[np.ndarray, np.ndarray]:
    """A closed slab ``[0, length] x [0, thickness] x [0, height]`` with rectangular through-holes along y.

    The face-on profile is cut into the grid of all hole edges; every solid grid cell gives two triangles on
    each big face and a side quad towards each empty or outside neighbour, so the mesh is watertight and
    manifold with no T-junctions (holes may touch the slab's border, e.g. a door opening reaching the floor).

    Args:
        length, height, thickness: slab size along x, z and y, metres.
        holes: ``(x0, z0, x1, z1)`` rectangles, pairwise disjoint (touching at most along an edge with the slab
            border).

    Returns:
        vertices ``(V, 3)`` float64 and faces ``(F, 3)`` int64 in the slab frame, outward normals.
    """
    h = np.asarray(holes, dtype=np.float64).reshape(-1, 4)
    xs = np.unique(np.concatenate([[0.0, length], h[:, 0], h[:, 2]]).clip(0.0, length))
    zs = np.unique(np.concatenate([[0.0, height], h[:, 1], h[:, 3]]).clip(0.0, height))
    na, nb = len(xs) - 1, len(zs) - 1
    xm, zm = (xs[:-1] + xs[1:]) / 2, (zs[:-1] + zs[1:]) / 2
    solid = np.ones((na, nb), dtype=bool)
    for x0, z0, x1, z1 in h:
        solid &= ~(((xm > x0) & (xm < x1))[:, None] & ((zm > z0) & (zm < z1))[None, :])
    pad = np.zeros((na + 2, nb + 2), dtype=bool)
    pad[1:-1, 1:-1] = solid
    nz1 = nb + 1
    gx, gz = np.meshgrid(xs, zs, indexing="ij")
    front = np.stack([gx, np.zeros_like(gx), gz], axis=-1).reshape(-1, 3)
    back = front.copy()
    back[:, 1] = thickness
    verts = np.concatenate([front, back])
    off = len(front)

    def fi(a: np.ndarray, b: np.ndarray) -> np.ndarray:
        return a * nz1 + b

    a, b = np.nonzero(solid)
    f00, f10, f11, f01 = fi(a, b), fi(a + 1, b), fi(a + 1, b + 1), fi(a, b + 1)
    tris = [
        np.stack([f00, f10, f11], 1), np.stack([f00, f11, f01], 1),
        np.stack([f00, f11, f10], 1) + off, np.stack([f00, f01, f11], 1) + off,
    ]
    left = ~pad[a, b + 1]
    al, bl = a[left], b[left]
    tris += [np.stack([fi(al, bl), fi(al, bl + 1), fi(al, bl + 1) + off], 1),
             np.stack([fi(al, bl), fi(al, bl + 1) + off, fi(al, bl) + off], 1)]
    right = ~pad[a + 2, b + 1]
    ar, br = a[right] + 1, b[right]
    tris += [np.stack([fi(ar, br), fi(ar, br + 1) + off, fi(ar, br + 1)], 1),
             np.stack([fi(ar, br), fi(ar, br) + off, fi(ar, br + 1) + off], 1)]
    bottom = ~pad[a + 1, b]
    ab, bb = a[bottom], b[bottom]
    tris += [np.stack([fi(ab, bb), fi(ab, bb) + off, fi(ab + 1, bb) + off], 1),
             np.stack([fi(ab, bb), fi(ab + 1, bb) + off, fi(ab + 1, bb)], 1)]
    top = ~pad[a + 1, b + 2]
    at, bt = a[top], b[top] + 1
    tris += [np.stack([fi(at, bt), fi(at + 1, bt) + off, fi(at, bt) + off], 1),
             np.stack([fi(at, bt), fi(at + 1, bt), fi(at + 1, bt) + off], 1)]
    faces = np.concatenate(tris)
    used, inv = np.unique(faces, return_inverse=True)
    return verts[used], inv.reshape(-1, 3)


def _concat(parts: Sequence[tuple[np.ndarray, np.ndarray]]) -> tuple[np.ndarray, np.ndarray]:
    vs, fs, n = [], [], 0
    for v, f in parts:
        vs.append(v)
        fs.append(f + n)
        n += len(v)
    return np.concatenate(vs), np.concatenate(fs)


def _rot_z(yaw: float) -> np.ndarray:
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def _rot_xyz(rx: float, ry: float, rz: float) -> np.ndarray:
    cx, sx, cy, sy = math.cos(rx), math.sin(rx), math.cos(ry), math.sin(ry)
    rxm = np.array([[1.0, 0.0, 0.0], [0.0, cx, -sx], [0.0, sx, cx]])
    rym = np.array([[cy, 0.0, sy], [0.0, 1.0, 0.0], [-sy, 0.0, cy]])
    return _rot_z(rz) @ rym @ rxm


def _make_mesh(v: np.ndarray, f: np.ndarray) -> trimesh.Trimesh:
    import trimesh

    return trimesh.Trimesh(vertices=v, faces=f, process=False)


# ---------------------------------------------------------------------------------------------- materials
def _hsv(h: float, s: float, v: float, a: float = 1.0) -> tuple[float, float, float, float]:
    import colorsys

    r, g, b = colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0))
    return (float(r), float(g), float(b), float(a))


def _wall_colour(rng: np.random.Generator) -> tuple[float, float, float, float]:
    return _hsv(rng.uniform(), rng.uniform(0.0, 0.25), rng.uniform(0.7, 0.97))


def _floor_colour(rng: np.random.Generator) -> tuple[float, float, float, float]:
    if rng.uniform() < 0.6:
        return _hsv(rng.uniform(0.05, 0.11), rng.uniform(0.35, 0.7), rng.uniform(0.35, 0.8))
    return _hsv(rng.uniform(), rng.uniform(0.0, 0.15), rng.uniform(0.3, 0.85))


def _furniture_colour(rng: np.random.Generator) -> tuple[float, float, float, float]:
    if rng.uniform() < 0.5:
        return _hsv(rng.uniform(0.04, 0.12), rng.uniform(0.3, 0.8), rng.uniform(0.25, 0.85))
    return _hsv(rng.uniform(), rng.uniform(0.0, 0.9), rng.uniform(0.15, 0.95))


# ---------------------------------------------------------------------------------------------- furniture
# Builders return boxes in the piece's own frame: z up, origin at the centre of its footprint on the floor,
# front towards -y and back towards +y (the side that goes against a wall).
def _table(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    low = rng.uniform() < 0.25
    w, d = rng.uniform(0.8, 1.8), rng.uniform(0.6, 1.0)
    if low:
        w, d = w * 0.7, d * 0.7
    h = rng.uniform(0.38, 0.5) if low else rng.uniform(0.7, 0.78)
    tt, leg, inset = rng.uniform(0.03, 0.05), rng.uniform(0.04, 0.07), rng.uniform(0.03, 0.08)
    lx, ly = w / 2 - inset - leg / 2, d / 2 - inset - leg / 2
    cx = np.array([-lx, lx, -lx, lx])
    cy = np.array([-ly, -ly, ly, ly])
    lo = [[-w / 2, -d / 2, h - tt]] + [[x - leg / 2, y - leg / 2, 0.0] for x, y in zip(cx, cy, strict=True)]
    hi = [[w / 2, d / 2, h]] + [[x + leg / 2, y + leg / 2, h - tt] for x, y in zip(cx, cy, strict=True)]
    return np.array(lo), np.array(hi)


def _chair(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    s, sh, st = rng.uniform(0.4, 0.5), rng.uniform(0.42, 0.48), 0.04
    leg, bh, bt = rng.uniform(0.03, 0.045), rng.uniform(0.35, 0.5), rng.uniform(0.025, 0.04)
    e = s / 2 - 0.01 - leg / 2
    lo = [[-s / 2, -s / 2, sh - st], [-s / 2, s / 2 - bt, sh]]
    hi = [[s / 2, s / 2, sh], [s / 2, s / 2, sh + bh]]
    for x in (-e, e):
        for y in (-e, e):
            lo.append([x - leg / 2, y - leg / 2, 0.0])
            hi.append([x + leg / 2, y + leg / 2, sh - st])
    return np.array(lo), np.array(hi)


def _shelf(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    w, d, h = rng.uniform(0.6, 1.2), rng.uniform(0.25, 0.4), rng.uniform(1.0, 2.0)
    pt, bk = 0.02, 0.01
    n = int(rng.integers(2, 6))
    lo = [[-w / 2, -d / 2, 0.0], [w / 2 - pt, -d / 2, 0.0], [-w / 2 + pt, d / 2 - bk, 0.0]]
    hi = [[-w / 2 + pt, d / 2, h], [w / 2, d / 2, h], [w / 2 - pt, d / 2, h]]
    for z in np.linspace(0.05, h - pt, n + 1):
        lo.append([-w / 2 + pt, -d / 2, z])
        hi.append([w / 2 - pt, d / 2 - bk, z + pt])
    return np.array(lo), np.array(hi)


def _cabinet(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    w, d, h = rng.uniform(0.5, 1.2), rng.uniform(0.4, 0.6), rng.uniform(0.6, 1.0)
    n = int(rng.integers(1, 4))
    lo = [[-w / 2, -d / 2 + 0.02, 0.06], [-w / 2 + 0.03, -d / 2 + 0.06, 0.0]]
    hi = [[w / 2, d / 2, h], [w / 2 - 0.03, d / 2 - 0.03, 0.06]]
    xs = np.linspace(-w / 2, w / 2, n + 1)
    for a, b in zip(xs[:-1], xs[1:], strict=True):
        lo.append([a + 0.005, -d / 2, 0.07])
        hi.append([b - 0.005, -d / 2 + 0.02, h - 0.01])
        hx = b - 0.06 if n == 1 or a < 0 else a + 0.04
        lo.append([hx, -d / 2 - 0.03, h - 0.2])
        hi.append([hx + 0.02, -d / 2 + 0.005, h - 0.08])
    return np.array(lo), np.array(hi)


def _sofa(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    w, d = rng.uniform(1.5, 2.3), rng.uniform(0.8, 1.0)
    sh, bh, ah = rng.uniform(0.4, 0.46), rng.uniform(0.75, 0.9), rng.uniform(0.55, 0.65)
    aw, bt, foot = rng.uniform(0.12, 0.25), rng.uniform(0.15, 0.25), 0.08
    n = int(rng.integers(1, 4))
    lo = [[-w / 2, -d / 2, foot], [-w / 2, d / 2 - bt, 0.25], [-w / 2, -d / 2, 0.25], [w / 2 - aw, -d / 2, 0.25]]
    hi = [[w / 2, d / 2, 0.25], [w / 2, d / 2, bh], [-w / 2 + aw, d / 2 - bt, ah], [w / 2, d / 2 - bt, ah]]
    xs = np.linspace(-w / 2 + aw, w / 2 - aw, n + 1)
    for a, b in zip(xs[:-1], xs[1:], strict=True):
        lo.append([a + 0.005, -d / 2 + 0.01, 0.25])
        hi.append([b - 0.005, d / 2 - bt, sh])
    for x in (-w / 2 + 0.05, w / 2 - 0.1):
        for y in (-d / 2 + 0.05, d / 2 - 0.1):
            lo.append([x, y, 0.0])
            hi.append([x + 0.05, y + 0.05, foot])
    return np.array(lo), np.array(hi)


_BUILDERS: dict[str, Callable[[np.random.Generator], tuple[np.ndarray, np.ndarray]]] = {
    "table": _table, "chair": _chair, "shelf": _shelf, "cabinet": _cabinet, "sofa": _sofa,
}
_AGAINST_WALL = {"table": 0.3, "chair": 0.15, "shelf": 0.95, "cabinet": 0.9, "sofa": 0.8}
"""Chance that a piece of each kind is placed with its back to a wall."""


# ---------------------------------------------------------------------------------------------- sculptures
def _sculpture(rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """A statue on a pedestal, in its own frame (z up, footprint centred on the origin): a union of closed
    primitives (the pieces overlap; fruxelize's non-zero rule makes the union solid)."""
    import trimesh

    pieces: list[tuple[np.ndarray, np.ndarray]] = []
    pw, ph = rng.uniform(0.3, 0.6), rng.uniform(0.3, 1.0)
    if rng.uniform() < 0.5:
        pieces.append(boxes([[-pw / 2, -pw / 2, 0.0]], [[pw / 2, pw / 2, ph]]))
    else:
        c = trimesh.creation.cylinder(radius=pw / 2, height=ph, sections=20)
        pieces.append((c.vertices + [0.0, 0.0, ph / 2], c.faces))
    room = min(2.3 - ph, 1.2)
    s = rng.uniform(0.5, 1.0) * room

    def place(m: Any, pos: Sequence[float], rot: np.ndarray) -> None:
        pieces.append((np.asarray(m.vertices) @ rot.T + np.asarray(pos), np.asarray(m.faces)))

    if rng.uniform() < 0.5:
        r = s * rng.uniform(0.1, 0.16)
        body_h = s * rng.uniform(0.45, 0.6)
        lean = rng.uniform(-0.2, 0.2, size=2)
        place(trimesh.creation.capsule(height=body_h, radius=r, count=[10, 10]),
              [0.0, 0.0, ph + r + body_h / 2], _rot_xyz(lean[0], lean[1], 0.0))
        head = s * rng.uniform(0.08, 0.12)
        place(trimesh.creation.uv_sphere(radius=head, count=[12, 12]), [0.0, 0.0, ph + 2 * r + body_h + head * 0.8],
              np.eye(3))
        for side in (-1.0, 1.0):
            if rng.uniform() < 0.8:
                ang = rng.uniform(0.3, 2.2)
                arm = trimesh.creation.capsule(height=s * rng.uniform(0.25, 0.4), radius=r * 0.35, count=[8, 8])
                place(arm, [side * r * 1.1, 0.0, ph + r + body_h * 0.8], _rot_xyz(0.0, side * ang, rng.uniform(-1, 1)))
    else:
        z = ph
        for _ in range(int(rng.integers(2, 5))):
            kind = rng.integers(0, 4)
            size = s * rng.uniform(0.15, 0.35)
            rot = _rot_xyz(*rng.uniform(-0.4, 0.4, size=2), rng.uniform(0, math.pi))
            if kind == 0:
                m = trimesh.creation.box(extents=size * rng.uniform(0.6, 1.4, size=3))
            elif kind == 1:
                m = trimesh.creation.uv_sphere(radius=size / 2, count=[12, 12])
            elif kind == 2:
                m = trimesh.creation.cone(radius=size / 2, height=size, sections=16)
                m = m.copy()
                m.vertices[:, 2] -= size / 2
            else:
                m = trimesh.creation.torus(major_radius=size / 2, minor_radius=size / 8, major_sections=20,
                                           minor_sections=10)
            place(m, [0.0, 0.0, z + size * 0.45], rot)
            z += size * 0.8
    v, f = _concat(pieces)
    return v, f


# ---------------------------------------------------------------------------------------------- placement
@dataclass
class _Footprint:
    """Rotated rectangle on the floor (world xy, metres)."""

    cx: float
    """Centre x."""
    cy: float
    """Centre y."""
    hx: float
    """Half extent along the rectangle's own x axis."""
    hy: float
    """Half extent along its own y axis."""
    yaw: float
    """Angle of its x axis from world +x towards +y, radians."""

    def axes(self) -> np.ndarray:
        """``(2, 2)``: rows are the rectangle's x and y axes in world xy."""
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        return np.array([[c, s], [-s, c]])

    def corners(self) -> np.ndarray:
        """``(4, 2)`` world xy corners, counter-clockwise."""
        # Scalars, not 2x2 arrays: room furnishing asks for corners thousands of times a room.
        c, s = math.cos(self.yaw), math.sin(self.yaw)
        xx, xy, yx, yy = self.hx * c, self.hx * s, -self.hy * s, self.hy * c
        return np.array([[self.cx - xx - yx, self.cy - xy - yy], [self.cx + xx - yx, self.cy + xy - yy],
                         [self.cx + xx + yx, self.cy + xy + yy], [self.cx - xx + yx, self.cy - xy + yy]])


def _overlap(a: _Footprint, b: _Footprint, gap: float) -> bool:
    """Separating-axis test of two rotated rectangles, each grown by ``gap / 2``."""
    # Scalars, not numpy: the furnishing's slot checks call this thousands of times a room.
    dx, dy = b.cx - a.cx, b.cy - a.cy
    ca, sa, cb, sb = math.cos(a.yaw), math.sin(a.yaw), math.cos(b.yaw), math.sin(b.yaw)
    ahx, ahy, bhx, bhy = a.hx + gap / 2, a.hy + gap / 2, b.hx + gap / 2, b.hy + gap / 2
    for ux, uy in ((ca, sa), (-sa, ca), (cb, sb), (-sb, cb)):
        ra = ahx * abs(ca * ux + sa * uy) + ahy * abs(-sa * ux + ca * uy)
        rb = bhx * abs(cb * ux + sb * uy) + bhy * abs(-sb * ux + cb * uy)
        if abs(dx * ux + dy * uy) > ra + rb:
            return False
    return True


@dataclass
class _Wall:
    """One wall, in its own frame: x along the inner face, y through the wall (outwards), z up."""

    start: np.ndarray
    """``(2,)`` world xy of the wall frame's origin, on the inner face's line."""
    along: np.ndarray
    """``(2,)`` unit world direction of the wall's x axis."""
    normal: np.ndarray
    """``(2,)`` unit outward normal (the wall's y axis); ``along x normal`` points up, so the frame is right-handed."""
    length: float
    """Length of the slab along x, metres (walls along world x also cover the corners)."""
    usable: tuple[float, float]
    """Range of x where openings may go (clear of the corners)."""
    openings: list[tuple[str, float, float, float, float]] = field(default_factory=list)
    """``(kind, x0, z0, x1, z1)`` of each door or window opening, wall frame."""

    def to_world(self, local: np.ndarray) -> np.ndarray:
        """Wall-local points (x along, y outwards, z up) to world."""
        o = np.array([self.start[0], self.start[1], 0.0])
        ax = np.array([self.along[0], self.along[1], 0.0])
        ay = np.array([self.normal[0], self.normal[1], 0.0])
        return o + local[:, :1] * ax + local[:, 1:2] * ay + local[:, 2:3] * np.array([0.0, 0.0, 1.0])


def _walls(lx: float, ly: float, tw: float) -> list[_Wall]:
    """The four walls; the two along x also cover the corners, so walls touch but do not overlap."""
    m = 0.25  # openings keep this far from the inner corners
    a = np.array
    return [
        _Wall(a([lx + tw, 0.0]), a([-1.0, 0.0]), a([0.0, -1.0]), lx + 2 * tw, (tw + m, tw + lx - m)),
        _Wall(a([lx, ly]), a([0.0, -1.0]), a([1.0, 0.0]), ly, (m, ly - m)),
        _Wall(a([-tw, ly]), a([1.0, 0.0]), a([0.0, 1.0]), lx + 2 * tw, (tw + m, tw + lx - m)),
        _Wall(a([0.0, 0.0]), a([0.0, 1.0]), a([-1.0, 0.0]), ly, (m, ly - m)),
    ]


def _place_opening(rng: np.random.Generator, walls: list[_Wall], kind: str, w: float, z0: float, z1: float,
                   tries: int) -> tuple[_Wall, float] | None:
    for _ in range(tries):
        wall = walls[int(rng.integers(len(walls)))]
        lo, hi = wall.usable
        if hi - lo < w:
            continue
        x0 = rng.uniform(lo, hi - w)
        if all(x0 + w + 0.2 <= a or x0 >= b + 0.2 for _, a, _, b, _ in wall.openings):
            wall.openings.append((kind, x0, z0, x0 + w, z1))
            return wall, x0
    return None


# ---------------------------------------------------------------------------------------------- the generator
@dataclass
class _Draft:
    """A room being generated: its random generator, settings and sizes, and what is made so far.

    Every random draw of a room comes from :attr:`rng`, in the order of :func:`make_scene`'s steps: a step moved,
    or a draw added, gives other rooms for the same seeds.
    """

    rng: np.random.Generator
    """The room's one random generator, ``numpy.random.default_rng(seed)``."""
    cfg: RoomConfig
    """The ranges drawn from."""
    ids: dict[str, int]
    """Label of each class name drawn (:meth:`RoomConfig.class_ids`)."""
    library: AssetLibrary | None
    """Assets to draw from, or None."""
    lx: float
    """Interior length along x, metres."""
    ly: float
    """Interior width along y, metres."""
    lz: float
    """Interior height, metres."""
    tw: float
    """Wall thickness, metres."""
    objects: list[SceneObject] = field(default_factory=list)
    """The solids made so far, in priority order."""
    footprints: list[_Footprint] = field(default_factory=list)
    """Floor footprints of the objects standing in the room (furniture, sculptures)."""
    keep_out: list[_Footprint] = field(default_factory=list)
    """Floor areas no standing object may take (in front of the doors)."""

    def add(self, name: str, label: int, v: np.ndarray, f: np.ndarray, color: tuple[float, ...], metallic: float,
            roughness: float) -> None:
        """Append a solid: vertices ``(V, 3)`` and faces ``(F, 3)`` in the world frame, its look."""
        self.objects.append(SceneObject(name, label, _make_mesh(v, f), tuple(float(c) for c in color),
                                        float(metallic), float(roughness)))

    def place(self, walls: list[_Wall], v: np.ndarray, against_wall: float) -> np.ndarray | None:
        """Find a free spot on the floor for an object and record its footprint.

        Args:
            walls: the room's walls.
            v: ``(V, 3)`` vertices of the object in its own frame (z up, its back towards +y).
            against_wall: chance that each try puts its back to a random wall rather than anywhere.

        Returns:
            The ``(V, 3)`` world vertices of the placed object, or None when no try of
            ``cfg.placement_tries`` fits (inside the room, clear of other footprints and the doors' areas).
        """
        rng, cfg = self.rng, self.cfg
        lo, hi = v[:, :2].min(axis=0), v[:, :2].max(axis=0)
        off, half = (lo + hi) / 2, (hi - lo) / 2
        for _ in range(cfg.placement_tries):
            if rng.uniform() < against_wall:
                wall = walls[int(rng.integers(4))]
                yaw = math.atan2(wall.normal[1], wall.normal[0]) - math.pi / 2
                s = rng.uniform(0.0, wall.length)
                # The piece's back (+y in its frame) faces the wall, 2 cm in front of the inner face.
                centre = wall.start + s * wall.along - wall.normal * (half[1] + 0.02)
            else:
                yaw = rng.uniform(0.0, 2 * math.pi)
                centre = np.array([rng.uniform(0.0, self.lx), rng.uniform(0.0, self.ly)])
            fp = _Footprint(float(centre[0]), float(centre[1]), float(half[0]), float(half[1]), float(yaw))
            corners = fp.corners()
            if corners.min() < 0.01 or np.any(corners.max(axis=0) > np.array([self.lx, self.ly]) - 0.01):
                continue
            if any(_overlap(fp, o, cfg.min_gap) for o in self.footprints + self.keep_out):
                continue
            self.footprints.append(fp)
            r = _rot_z(yaw)
            return (v - np.array([off[0], off[1], 0.0])) @ r.T + np.array([centre[0], centre[1], 0.0])
        return None


_Door = tuple[_Wall, float, float, float]
"""A door's opening: ``(wall, x0, width, height)``, wall frame, metres."""
_Window = tuple[_Wall, float, float, float, float]
"""A window's opening: ``(wall, x0, width, z0, z1)``, wall frame, metres."""


def make_scene(seed: int, config: RoomConfig | None = None, classes: ClassTable = DEFAULT_CLASSES) -> Scene:
    """Generate a room from a seed.

    Args:
        seed: any integer; the only source of randomness (``numpy.random.default_rng(seed)``).
        config: the ranges to draw from; None uses ``RoomConfig()``.
        classes: the class table whose ids label the solids (see the module docstring); the same seed and config
            give the same solids with any table.

    Returns:
        The :class:`Scene`; see the module docstring for the world frame, the object order and the labels.

    Raises:
        SceneError: an impossible configuration, or a class table without the simulator's classes.
        assets.AssetError: an unreadable asset folder or library.
    """
    cfg = config if config is not None else RoomConfig()
    ids = cfg.class_ids(classes)
    rng = np.random.default_rng(seed)
    library = _load_library(cfg)
    lx, ly, lz = (rng.uniform(*r) for r in (cfg.length_range, cfg.width_range, cfg.height_range))
    room = _Draft(rng, cfg, ids, library, lx, ly, lz, rng.uniform(*cfg.wall_thickness_range))
    _add_floor(room)
    walls = _walls(lx, ly, room.tw)
    doors = _door_openings(room, walls)
    windows = _window_openings(room, walls)
    _add_walls(room, walls)
    frame_colour = _hsv(rng.uniform(), rng.uniform(0.0, 0.2), rng.uniform(0.3, 0.95))
    _add_windows(room, windows, frame_colour)
    handles = _add_doors(room, doors, frame_colour)
    room.keep_out = _door_areas(doors, cfg.door_clearance)
    _add_furniture(room, walls)
    _add_sculptures(room, walls)
    lights = _lights(rng, lx, ly, lz, cfg)
    free = _free_space(lx, ly, room.footprints + handles, cfg.free_space_resolution)
    return Scene(tuple(room.objects), np.array([lx, ly, lz]), tuple(lights), free, int(seed), classes)


def _add_floor(room: _Draft) -> None:
    """The floor slab under the interior and the walls, and the ceiling slab on the walls when asked for."""
    rng, tw, ft = room.rng, room.tw, room.cfg.floor_thickness
    lx, ly, lz = room.lx, room.ly, room.lz
    room.add("floor", room.ids["floor"], *boxes([[-tw, -tw, -ft]], [[lx + tw, ly + tw, 0.0]]), _floor_colour(rng),
             0.0, rng.uniform(0.4, 0.9))
    if room.cfg.ceiling:
        room.add("ceiling", room.ids[room.cfg.ceiling_class], *boxes([[-tw, -tw, lz]], [[lx + tw, ly + tw, lz + ft]]),
                 _hsv(0.0, 0.0, rng.uniform(0.85, 0.98)), 0.0, 0.9)


def _door_openings(room: _Draft, walls: list[_Wall]) -> list[_Door]:
    """Draw the doors and cut their openings into ``walls`` (fewer doors when the walls have no room left)."""
    rng, cfg = room.rng, room.cfg
    doors = []
    for _ in range(int(rng.integers(cfg.doors[0], cfg.doors[1] + 1))):
        w, h = rng.uniform(0.8, 1.0), min(rng.uniform(2.0, 2.15), room.lz - 0.15)
        placed = _place_opening(rng, walls, "door", w, 0.0, h, cfg.placement_tries)
        if placed is not None:
            doors.append((placed[0], placed[1], w, h))
    return doors


def _window_openings(room: _Draft, walls: list[_Wall]) -> list[_Window]:
    """Draw the windows and cut their openings into ``walls`` (fewer windows when the walls have no room left)."""
    rng, cfg = room.rng, room.cfg
    windows = []
    for _ in range(int(rng.integers(cfg.windows[0], cfg.windows[1] + 1))):
        w = rng.uniform(0.6, 1.6)
        z0 = rng.uniform(0.7, 1.0)
        z1 = min(z0 + rng.uniform(0.9, 1.4), room.lz - 0.2)
        placed = _place_opening(rng, walls, "window", w, z0, z1, cfg.placement_tries)
        if placed is not None:
            windows.append((placed[0], placed[1], w, z0, z1))
    return windows


def _add_walls(room: _Draft, walls: list[_Wall]) -> None:
    """The four wall slabs, with holes where the openings are, in one colour."""
    wall_colour = _wall_colour(room.rng)
    for n, wall in enumerate(walls):
        holes = [(a, z0, b, z1) for _, a, z0, b, z1 in wall.openings]
        v, f = slab_with_holes(wall.length, room.lz, room.tw, holes)
        room.add(f"wall_{n}", room.ids["wall"], wall.to_world(v), f, wall_colour, 0.0, room.rng.uniform(0.6, 0.95))


def _add_windows(room: _Draft, windows: list[_Window], frame_colour: tuple[float, ...]) -> None:
    """Fill each window opening: an asset, or a frame with its glass."""
    rng, tw, label = room.rng, room.tw, room.ids["window"]
    for n, (wall, x0, w, z0, z1) in enumerate(windows):
        fw, depth = rng.uniform(0.04, 0.08), tw * rng.uniform(0.5, 0.9)
        y0 = (tw - depth) / 2
        asset = _pick(rng, room.library, "window", room.cfg.asset_probability)
        if asset is not None:
            v, f = _fit_asset(asset, [x0, y0, z0], [x0 + w, y0 + depth, z1])
            room.add(f"window_{n}", label, wall.to_world(v), f, frame_colour, 0.0, 0.5)
            continue
        v, f = slab_with_holes(w, z1 - z0, depth, [(fw, fw, w - fw, z1 - z0 - fw)])
        room.add(f"window_{n}_frame", label, wall.to_world(v + [x0, y0, z0]), f, frame_colour, 0.0, 0.5)
        # The glass fills nearly the frame's depth (double glazing): a pane a few millimetres thin would hold
        # almost no cell centre, and the ground truth of the opening would be stripes of window in empty space.
        gv, gf = boxes([[x0 + fw, y0 + 0.005, z0 + fw]], [[x0 + w - fw, y0 + depth - 0.005, z1 - fw]])
        room.add(f"window_{n}_glass", label, wall.to_world(gv), gf, (0.75, 0.87, 0.95, 0.3), 0.0, 0.05)


def _add_doors(room: _Draft, doors: list[_Door], frame_colour: tuple[float, ...]) -> list[_Footprint]:
    """Fill each door opening: an asset, or a frame, a leaf and a handle.

    Returns:
        The floor footprints of the handles, which may stick out of a thin wall into the room.
    """
    rng, tw, label = room.rng, room.tw, room.ids["door"]
    handles = []
    for n, (wall, x0, w, h) in enumerate(doors):
        fw, depth = rng.uniform(0.04, 0.07), tw * rng.uniform(0.6, 0.95)
        y0 = (tw - depth) / 2
        wood = _hsv(rng.uniform(0.04, 0.1), rng.uniform(0.3, 0.7), rng.uniform(0.25, 0.85))
        asset = _pick(rng, room.library, "door", room.cfg.asset_probability)
        if asset is not None:
            v, f = _fit_asset(asset, [x0, y0, 0.0], [x0 + w, y0 + depth, h])
            room.add(f"door_{n}", label, wall.to_world(v), f, wood, 0.0, 0.6)
            continue
        v, f = slab_with_holes(w, h, depth, [(fw, 0.0, w - fw, h - fw)])
        room.add(f"door_{n}_frame", label, wall.to_world(v + [x0, y0, 0.0]), f, frame_colour, 0.0, 0.5)
        lt = max(depth * rng.uniform(0.5, 0.8), 0.04)
        lv, lf = boxes([[x0 + fw, tw / 2 - lt / 2, 0.0]], [[x0 + w - fw, tw / 2 + lt / 2, h - fw]])
        room.add(f"door_{n}_leaf", label, wall.to_world(lv), lf, wood, 0.0, rng.uniform(0.4, 0.8))
        hx = x0 + w - fw - 0.1 if rng.uniform() < 0.5 else x0 + fw + 0.06
        hv, hf = boxes([[hx, tw / 2 - lt / 2 - 0.06, 0.95]], [[hx + 0.04, tw / 2 + lt / 2 + 0.06, 1.05]])
        room.add(f"door_{n}_handle", label, wall.to_world(hv), hf, (0.8, 0.8, 0.78, 1.0), 1.0, 0.3)
        # A handle may stick out of a thin wall into the room: the robot must not drive into it.
        hw = wall.to_world(hv)
        hlo, hhi = hw[:, :2].min(axis=0), hw[:, :2].max(axis=0)
        handles.append(_Footprint(*((hlo + hhi) / 2), *((hhi - hlo) / 2), 0.0))
    return handles


def _door_areas(doors: list[_Door], clearance: float) -> list[_Footprint]:
    """The floor area kept free in front of (inside) each door: ``clearance`` deep, 10 cm wider each side."""
    areas = []
    for wall, x0, w, _ in doors:
        c = wall.to_world(np.array([[x0 + w / 2, -clearance / 2, 0.0]]))[0]
        yaw = math.atan2(wall.along[1], wall.along[0])
        areas.append(_Footprint(c[0], c[1], w / 2 + 0.1, clearance / 2, yaw))
    return areas


def _add_furniture(room: _Draft, walls: list[_Wall]) -> None:
    """Draw and place the furniture pieces (assets or procedural kinds); a piece with no free spot is left out."""
    rng, cfg = room.rng, room.cfg
    kinds = list(cfg.furniture_kinds)
    for n in range(int(rng.integers(cfg.furniture[0], cfg.furniture[1] + 1))):
        asset = _pick(rng, room.library, "furniture", cfg.asset_probability)
        if asset is not None:
            v, f = np.asarray(asset.mesh.vertices, dtype=np.float64), np.asarray(asset.mesh.faces)
            kind, wall_p = asset.name, 0.5
        else:
            kind = kinds[int(rng.integers(len(kinds)))]
            v, f = boxes(*_BUILDERS[kind](rng))
            wall_p = _AGAINST_WALL[kind]
        colour = _furniture_colour(rng)
        metallic, roughness = (rng.uniform(0.6, 1.0), rng.uniform(0.2, 0.5)) if rng.uniform() < 0.1 else (
            0.0, rng.uniform(0.4, 0.95))
        placed = room.place(walls, v, wall_p)
        if placed is not None:
            room.add(f"{kind}_{n}", room.ids["furniture"], placed, f, colour, metallic, roughness)


def _add_sculptures(room: _Draft, walls: list[_Wall]) -> None:
    """Draw and place the sculptures (assets or procedural statues), bronze or stone; one with no free spot is
    left out."""
    rng, cfg = room.rng, room.cfg
    for n in range(int(rng.integers(cfg.sculptures[0], cfg.sculptures[1] + 1))):
        asset = _pick(rng, room.library, "sculpture", cfg.asset_probability)
        if asset is not None:
            v, f = np.asarray(asset.mesh.vertices, dtype=np.float64), np.asarray(asset.mesh.faces)
        else:
            v, f = _sculpture(rng)
        if rng.uniform() < 0.5:
            colour, metallic, roughness = _hsv(rng.uniform(0.05, 0.12), 0.6, rng.uniform(0.3, 0.6)), 0.9, 0.35
        else:
            colour, metallic, roughness = _hsv(rng.uniform(), rng.uniform(0, 0.1), rng.uniform(0.55, 0.95)), 0.0, 0.8
        placed = room.place(walls, v, 0.2)
        if placed is not None:
            room.add(f"sculpture_{n}", room.ids["sculpture"], placed, f, colour, metallic, roughness)


def _lights(rng: np.random.Generator, lx: float, ly: float, lz: float, cfg: RoomConfig) -> list[Light]:
    out = []
    az, el = rng.uniform(0, 2 * math.pi), rng.uniform(0.5, 1.3)
    direction = -np.array([math.cos(el) * math.cos(az), math.cos(el) * math.sin(az), math.sin(el)])
    # pyrender's directional light shines along its local -z axis.
    zz = -direction / np.linalg.norm(direction)
    x = np.cross([0.0, 0.0, 1.0], zz)
    x /= np.linalg.norm(x)
    pose = np.eye(4)
    pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, np.cross(zz, x), zz
    warm = rng.uniform(0.0, 0.15)
    out.append(Light("directional", (1.0, 1.0 - warm / 2, 1.0 - warm), float(rng.uniform(1.5, 4.0)), pose))
    for _ in range(int(rng.integers(cfg.point_lights[0], cfg.point_lights[1] + 1))):
        p = np.eye(4)
        p[:3, 3] = [rng.uniform(0.2, lx - 0.2), rng.uniform(0.2, ly - 0.2), lz - rng.uniform(0.15, 0.4)]
        warm = rng.uniform(0.0, 0.3)
        out.append(Light("point", (1.0, 1.0 - warm / 3, 1.0 - warm), float(rng.uniform(5.0, 25.0)), p))
    return out


def _free_space(lx: float, ly: float, footprints: list[_Footprint], res: float) -> FreeSpace:
    """Rasterise the room into cells of ``res``: occupied outside the interior and where a cell's square meets
    a footprint (exact square-vs-rotated-rectangle separating-axis test)."""
    nx, ny = int(math.ceil(lx / res)) + 2, int(math.ceil(ly / res)) + 2
    origin = np.array([-res, -res])
    xs = origin[0] + (np.arange(nx) + 0.5) * res
    ys = origin[1] + (np.arange(ny) + 0.5) * res
    h = res / 2
    inside_x = (xs - h >= 0.0) & (xs + h <= lx)
    inside_y = (ys - h >= 0.0) & (ys + h <= ly)
    occ = ~(inside_y[:, None] & inside_x[None, :])
    for fp in footprints:
        ax = fp.axes()
        ex = fp.hx * abs(ax[0, 0]) + fp.hy * abs(ax[1, 0])
        ey = fp.hx * abs(ax[0, 1]) + fp.hy * abs(ax[1, 1])
        c0, c1 = np.searchsorted(xs, [fp.cx - ex - res, fp.cx + ex + res])
        r0, r1 = np.searchsorted(ys, [fp.cy - ey - res, fp.cy + ey + res])
        if c1 <= c0 or r1 <= r0:
            continue
        dx = xs[c0:c1][None, :] - fp.cx
        dy = ys[r0:r1][:, None] - fp.cy
        hit = (np.abs(dx) <= h + ex) & (np.abs(dy) <= h + ey)
        for k, half in ((0, fp.hx), (1, fp.hy)):
            proj = dx * ax[k, 0] + dy * ax[k, 1]
            hit &= np.abs(proj) <= half + h * (abs(ax[k, 0]) + abs(ax[k, 1]))
        occ[r0:r1, c0:c1] |= hit
    return FreeSpace(occ, origin, float(res))


# ---------------------------------------------------------------------------------------------- assets
def _load_library(cfg: RoomConfig) -> AssetLibrary | None:
    if cfg.assets is None and cfg.asset_dir is None and not cfg.sh3f_files:
        return None
    from .assets import AssetLibrary, load_asset_folder, load_sh3f

    lib = cfg.assets if cfg.assets is not None else AssetLibrary(())
    if cfg.asset_dir is not None:
        lib = lib.merged(load_asset_folder(cfg.asset_dir))
    for path in cfg.sh3f_files:
        lib = lib.merged(load_sh3f(path))
    return lib


def _pick(rng: np.random.Generator, library: AssetLibrary | None, kind: str, probability: float) -> Any:
    """An asset of ``kind`` with the given chance, else None. Draws from ``rng`` whether or not there is a
    library, so that adding assets of one class does not reshuffle the rest of the scene."""
    coin, idx = rng.uniform(), rng.uniform()
    if library is None:
        return None
    items = library.of_kind(kind)
    if not items or coin >= probability:
        return None
    return items[min(int(idx * len(items)), len(items) - 1)]


def _fit_asset(asset: Any, lo: Sequence[float], hi: Sequence[float]) -> tuple[np.ndarray, np.ndarray]:
    """Scale an asset (its own frame: x width, y depth, z height) into the box ``[lo, hi]`` of wall-local
    coordinates (x along the wall, y through it, z up)."""
    v = np.asarray(asset.mesh.vertices, dtype=np.float64)
    vmin, vmax = v.min(axis=0), v.max(axis=0)
    size = np.maximum(vmax - vmin, 1e-9)
    lo, hi = np.asarray(lo, dtype=np.float64), np.asarray(hi, dtype=np.float64)
    return lo + (v - vmin) / size * (hi - lo), np.asarray(asset.mesh.faces)

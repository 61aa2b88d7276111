"""The asset pack as the room generator uses it: found once, loaded once per process, queried by *role*.

Where the pack is (:func:`resolve_pack`)
    An explicit folder (``SimConfig.assets``), else the ``FRUXEL_ASSETS`` environment variable, else the
    repository's ``assets/pack`` (what ``make assets`` builds). A folder that is not there is one error line
    naming it and saying to run ``make assets``.

Caching
    :func:`library` keeps one :class:`Library` per pack folder and process: the checked manifest, every decoded
    mesh (as a :class:`Prop`, with its support surfaces computed on first use), each texture's mean colour and each
    image's size. Rooms after the first cost no file reads; a data worker holds at most the whole pack (tens of
    MiB). Nothing cached depends on a room's random draws, so the cache never changes a room.

Roles
    A role (:data:`ROLES`) is what a piece is for in a room: ``bed``, ``dining_table``, ``nightstand``, ``tv``,
    ``table_lamp``, ``clutter`` ... Each names the pack categories it takes meshes from and the sizes, elevations and
    names that qualify (a nightstand is a cabinet at most 0.75 m high, a coffee table a table below 0.56 m), so
    that a bedside table never becomes a wardrobe. :meth:`Library.props` lists a role's meshes in one asset split.
"""

from __future__ import annotations

import os
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from fruxel.errors import ConfigError

from ..assetpack import AssetPack, AssetPackError
from ..assetpack.pack import read_rgb
from .materials import part_role, srgb_to_linear
from .supports import Level, support_levels

ASSETS_ENV = "FRUXEL_ASSETS"
"""Environment variable naming the asset pack folder when the config names none."""

REPOSITORY_PACK = Path(__file__).resolve().parents[3] / "assets" / "pack"
"""The pack ``make assets`` builds in the repository (``assets/pack``)."""


def resolve_pack(path: str | os.PathLike[str] | None, *, option: str = "SimConfig.assets") -> Path:
    """The asset pack folder (module docstring): ``path``, else ``$FRUXEL_ASSETS``, else the repository's.

    Args:
        path: the folder the config names, or None.
        option: what names ``path`` to the user (``"--assets"`` in a command), for the message.

    Raises:
        ConfigError: the folder does not exist or has no ``manifest.json`` (one line: where it looked, and
            ``make assets``).
    """
    if path is not None and str(path):
        root, where = Path(path), option
    elif os.environ.get(ASSETS_ENV):
        root, where = Path(os.environ[ASSETS_ENV]), f"${ASSETS_ENV}"
    else:
        root, where = REPOSITORY_PACK, "the repository's default"
    if not (root / "manifest.json").is_file():
        raise ConfigError(f"{root}: no asset pack there ({where}); build it with `make assets` (or set "
                          f"{ASSETS_ENV} / {option} to a pack folder)")
    return root


def check_pack(config: Any, *, option: str = "SimConfig.assets") -> None:
    """Check, before any slow work, that the asset pack a simulator config needs is there: the ``home`` world
    furnishes its rooms from it; other configs need none.

    Args:
        config: the :class:`~fruxel.train.sim.config.SimConfig`.
        option: what names ``config.assets`` to the user, for the message (:func:`resolve_pack`).

    Raises:
        ConfigError: no pack in the folder (one line naming it, where it came from and ``make assets``).
    """
    if config.world == "home":
        resolve_pack(config.assets, option=option)


@dataclass(frozen=True)
class Role:
    """Which pack meshes can play one role in a room (module docstring)."""

    categories: tuple[str, ...]
    """Pack mesh categories drawn from."""
    height: tuple[float, float] = (0.0, 10.0)
    """Range of the mesh's height, metres."""
    width: tuple[float, float] = (0.0, 10.0)
    """Range of its larger footprint side, metres."""
    depth: tuple[float, float] = (0.0, 10.0)
    """Range of its smaller footprint side, metres."""
    elevation: tuple[float, float] = (0.0, 0.05)
    """Range of its usual height above the floor (Sweet Home 3D's elevation), metres."""
    include: str = ""
    """Regular expression the lower-case name must match (empty: any)."""
    exclude: str = ""
    """Regular expression the lower-case name must not match (empty: none)."""
    body: str = "wood"
    """Material role of parts whose names say nothing (:mod:`.materials`)."""


_SEATS = r"bench|wheelchair|workbench|abdominal|high chair|children|child|class seat|piano"
ROLES: dict[str, Role] = {
    "bed": Role(("bed",), (0.3, 1.5), (1.7, 2.4), (0.8, 2.2), exclude=r"air mattress|hospital|crib|baby",
                body="soft"),
    "sofa": Role(("sofa",), (0.6, 1.1), (1.4, 3.0), (0.6, 1.2), exclude=r"opened", body="soft"),
    "armchair": Role(("armchair",), (0.6, 1.1), (0.5, 1.15), (0.45, 1.0), exclude=r"ottoman|puff", body="soft"),
    "chair": Role(("chair",), (0.72, 1.16), (0.35, 0.7), (0.3, 0.7), exclude=_SEATS + r"|stool|bar"),
    "stool": Role(("chair",), (0.4, 1.1), (0.25, 0.6), (0.25, 0.6), include=r"stool|bar"),
    "dining_table": Role(("table",), (0.7, 0.8), (0.9, 2.4), (0.6, 1.3),
                         exclude=r"pool|tennis|football|fan|tablet|changing|bar|children|trestle"),
    "small_table": Role(("table",), (0.7, 0.8), (0.6, 1.25), (0.5, 1.25),
                        exclude=r"pool|tennis|football|fan|tablet|changing|bar|children"),
    "coffee_table": Role(("table",), (0.3, 0.56), (0.6, 1.5), (0.4, 1.0), exclude=r"football|children|fan"),
    "side_table": Role(("table", "cabinet"), (0.4, 0.7), (0.3, 0.7), (0.3, 0.7),
                       exclude=r"locker|safe|filing|fan|tablet|upper"),
    "nightstand": Role(("cabinet",), (0.35, 0.75), (0.3, 0.7), (0.3, 0.65), exclude=r"locker|safe|filing|upper"),
    "desk": Role(("desk", "table"), (0.7, 0.8), (1.0, 2.0), (0.5, 0.95),
                 exclude=r"technical|dressing|pool|tennis|football|fan|tablet|changing|round|glass|bar|children"),
    "wardrobe": Role(("cabinet",), (1.4, 2.4), (0.6, 2.3), (0.3, 0.7), include=r"wardrobe|high cabinet|cupboard"),
    "dresser": Role(("cabinet",), (0.5, 1.2), (0.6, 1.8), (0.3, 0.7),
                    include=r"chest|dresser|drawer|lower cabinet|sideboard|vanity", exclude=r"corner|sink|double"),
    "shelf": Role(("shelf",), (0.7, 2.3), (0.4, 3.0), (0.2, 0.6)),
    "cabinet": Role(("cabinet",), (0.5, 2.3), (0.4, 2.2), (0.3, 0.7),
                    exclude=r"sink|vanity|corner|locker|safe|upper|clothes rack|trunck"),
    "tv_unit": Role(("cabinet", "table"), (0.35, 0.85), (0.9, 2.0), (0.3, 0.75),
                    include=r"chest|dresser|lower cabinet|coffee|table$|sideboard", exclude=r"corner|sink|upper"),
    "tv": Role(("tv",), (0.3, 0.8), (0.4, 1.3), (0.05, 0.55), include=r"tv|television",
               exclude=r"stand|cabinet|remote|wall", body="any"),
    "computer": Role(("tv",), (0.3, 0.6), (0.3, 0.6), (0.2, 0.55), include=r"imac|monitor|computer", body="any"),
    "kitchen_lower": Role(("cabinet",), (0.8, 0.95), (0.4, 1.1), (0.5, 0.7),
                          include=r"lower cabinet|drawers cabinet|sink cabinet", exclude=r"corner"),
    "kitchen_upper": Role(("cabinet",), (0.5, 0.8), (0.3, 1.1), (0.25, 0.45), (1.2, 2.0), exclude=r"corner"),
    "kitchen_tall": Role(("appliance", "cabinet"), (1.2, 2.2), (0.5, 1.0), (0.5, 0.95),
                         include=r"fridge|refrigerator|freezer|high cabinet", body="metal"),
    "appliance": Role(("appliance",), (0.72, 0.95), (0.5, 1.1), (0.45, 0.8),
                      include=r"oven|stove|washing|dryer|dish", exclude=r"small|microwave|propane", body="metal"),
    "radiator": Role(("appliance",), (0.3, 0.9), (0.4, 2.2), (0.05, 0.45), (0.0, 0.2), include=r"radiator",
                     body="metal"),
    "piano": Role(("furniture",), (1.0, 1.5), (1.2, 1.6), (0.4, 0.7), include=r"piano"),
    "fireplace": Role(("furniture",), (0.9, 1.3), (1.0, 1.4), (0.3, 0.5), include=r"fireplace", body="stone"),
    "floor_lamp": Role(("lamp",), (1.0, 2.0), (0.15, 0.7), (0.15, 0.7), body="metal"),
    "table_lamp": Role(("lamp",), (0.25, 0.8), (0.1, 0.5), (0.1, 0.5), body="metal"),
    "ceiling_lamp": Role(("lamp",), (0.03, 1.0), (0.1, 1.4), (0.1, 1.4), (1.2, 2.6),
                         include=r"hanging|pendant|ceiling|chandelier|fluorescent", body="metal"),
    # At most 26 cm out from the wall: a camera carried through the room keeps 30 cm from the walls.
    "wall_lamp": Role(("lamp",), (0.05, 0.6), (0.05, 0.5), (0.03, 0.26), (1.2, 2.2), include=r"wall", body="metal"),
    "floor_plant": Role(("plant",), (0.5, 2.0), (0.2, 1.2), (0.2, 1.2), exclude=r"christmas", body="any"),
    "small_plant": Role(("plant",), (0.08, 0.6), (0.08, 0.5), (0.08, 0.5), exclude=r"christmas", body="any"),
    "rug": Role(("rug",), (0.0, 0.07), (0.5, 3.0), (0.3, 2.6), body="rug"),
    "clutter": Role(("clutter", "wall_decor"), (0.03, 0.45), (0.05, 0.45), (0.02, 0.4),
                    exclude=r"cuckoo|white board|hanger|towel rack|coathanger|paper towel|tool|shovel|saw|hammer",
                    body="any"),
    "floor_clutter": Role(("clutter",), (0.3, 1.3), (0.25, 1.0), (0.15, 0.8),
                          exclude=r"treadmill|bike|ladder|hanging|hanger|jacket|suit|trousers|skirt|rack|mixer|"
                                  r"coffee|helmet|cone|extinguisher|aquarium|fan",
                          body="any"),
    "wall_clock": Role(("wall_decor",), (0.2, 0.8), (0.15, 0.5), (0.03, 0.25), (0.5, 2.0), body="any"),
    "statue": Role(("statue",), body="stone"),
    # Scanned figurines of animals; the pack's people and its animal models (a cat, a dog, a horse) are not
    # statues, and a person labelled sculpture would teach the network that people are.
    "figure": Role(("animal",), (0.2, 1.2), (0.1, 1.3), exclude=r"horse|cat|dog|chicken|rabbit", body="stone"),
}
"""Every role the generator fills from the pack (module docstring)."""


@dataclass(eq=False)
class Prop:
    """A mesh ready to place, in the canonical frame (z up, metres, footprint centred, on z = 0, front -y)."""

    name: str
    """Display name (the pack's, or the builder's for procedural pieces)."""
    asset: str | None
    """Pack asset id, or None for a procedural piece."""
    vertices: np.ndarray
    """``(V, 3)`` float64 metres."""
    faces: np.ndarray
    """``(F, 3)`` int64."""
    parts: np.ndarray
    """``(F,)`` int32: each face's part."""
    part_roles: tuple[str | None, ...]
    """Material role of each part (None: the piece's own role decides)."""
    part_colours: np.ndarray
    """``(P, 3)`` float64 linear RGB of each part (the source's colour)."""
    elevation: float = 0.0
    """Usual height above the floor, metres."""
    _levels: tuple[Level, ...] | None = field(default=None, repr=False)
    size: np.ndarray = field(init=False, repr=False)
    """``(3,)`` float64 extent along x, y, z, metres (computed once)."""

    def __post_init__(self) -> None:
        self.size = self.vertices.max(axis=0) - self.vertices.min(axis=0)

    def levels(self) -> tuple[Level, ...]:
        """Support surfaces (:mod:`.supports`), computed on first use and kept."""
        if self._levels is None:
            self._levels = support_levels(self.vertices, self.faces)
        return self._levels


class Library:
    """One asset pack, decoded lazily and kept (module docstring).

    Args:
        root: the pack folder (already resolved).

    Raises:
        AssetPackError: a malformed pack (one line naming the file).
    """

    def __init__(self, root: Path) -> None:
        self.root = root
        self.pack = AssetPack(root)
        self._props: dict[str, Prop] = {}
        self._role_ids: dict[tuple[str, str], tuple[str, ...]] = {}
        self._textures: dict[tuple[str, str], tuple[str, ...]] = {}
        self._colours: dict[str, np.ndarray] = {}
        self._image_sizes: dict[str, tuple[int, int]] = {}
        self._solids: dict[str, tuple[np.ndarray, np.ndarray] | None] = {}

    # -------------------------------------------------------------------------------------------- meshes
    def role_ids(self, role: str, split: str) -> tuple[str, ...]:
        """Ids of the pack meshes that can play ``role`` in ``split`` (:data:`ROLES`), in id order."""
        key = (role, split)
        if key not in self._role_ids:
            r = ROLES[role]
            ids = []
            for cat in r.categories:
                for e in self.pack.select("mesh", cat, split):
                    if _qualifies(r, e.name.lower(), np.asarray(e.size_m), float(e.info.get("elevation_m", 0.0))):
                        ids.append(e.id)
            self._role_ids[key] = tuple(sorted(ids))
        return self._role_ids[key]

    def prop(self, asset_id: str) -> Prop:
        """The decoded mesh ``asset_id`` as a :class:`Prop` (kept: treat its arrays as read-only)."""
        if asset_id not in self._props:
            m = self.pack.mesh(asset_id)
            v = np.asarray(m.vertices, dtype=np.float64)
            colours = srgb_to_linear(m.part_colors[:, :3] / 255.0)
            roles = tuple(part_role(n, int(c[3])) for n, c in zip(m.part_names, m.part_colors, strict=True))
            self._props[asset_id] = Prop(m.entry.name, asset_id, v, np.asarray(m.faces, dtype=np.int64),
                                         np.asarray(m.face_parts, dtype=np.int32), roles, colours,
                                         float(m.entry.info.get("elevation_m", 0.0)))
        return self._props[asset_id]

    def solid(self, asset_id: str) -> tuple[np.ndarray, np.ndarray] | None:
        """The solid the mesh ``asset_id`` is labelled by in its canonical frame (:mod:`.solids`): ``(vertices
        (V, 3) float64, faces (F, 3) int64)`` of its filled surface, made once per machine; None when the mesh is
        closed and labels as it is."""
        if asset_id not in self._solids:
            from ..assetpack.derived import code_digest, derived_arrays
            from . import solids

            prop = self.prop(asset_id)
            if solids.is_closed(prop.vertices, prop.faces):
                self._solids[asset_id] = None
            else:
                made: dict[str, np.ndarray] = {}

                def part(key: str) -> np.ndarray:
                    if not made:
                        made["v"], made["f"] = solids.filled_solid(prop.vertices, prop.faces)
                    return made[key]

                name = f"solid-{self.pack.entry(asset_id).sha256['mesh'][:32]}-{solids.PITCH}-" \
                       f"{code_digest(solids.__name__)}"
                v = derived_arrays().get(f"{name}-v", (-1, 3), np.float64, lambda: part("v"))
                f = derived_arrays().get(f"{name}-f", (-1, 3), np.int64, lambda: part("f"))
                self._solids[asset_id] = (v, f)
        return self._solids[asset_id]

    # -------------------------------------------------------------------------------------------- textures
    def texture_categories(self, split: str) -> list[str]:
        """The texture categories that ``split`` has, sorted."""
        return sorted(self.pack.categories("texture", split))

    def texture_ids(self, category: str, split: str) -> tuple[str, ...]:
        """Ids of the textures of ``category`` in ``split``, in id order."""
        key = (category, split)
        if key not in self._textures:
            self._textures[key] = tuple(e.id for e in self.pack.select("texture", category, split))
        return self._textures[key]

    def texture_size(self, texture_id: str) -> float:
        """Metres one tile of the texture spans along its width (the pack's ``size_m[0]``)."""
        return float(self.pack.entry(texture_id).size_m[0])

    def texture_colour(self, texture_id: str) -> np.ndarray:
        """``(3,)`` float64 mean linear RGB of the texture's albedo (decoded once)."""
        if texture_id not in self._colours:
            from ..assetpack.derived import code_digest, derived_arrays

            e = self.pack.entry(texture_id)

            def compute() -> np.ndarray:
                albedo = read_rgb(self.root / e.files["albedo"])
                return srgb_to_linear(albedo.reshape(-1, 3) / 255.0).mean(axis=0)

            name = f"colour-{e.sha256['albedo'][:32]}-{code_digest(__name__)}"
            self._colours[texture_id] = derived_arrays().get(name, (3,), np.float64, compute)
        return self._colours[texture_id]

    # -------------------------------------------------------------------------------------------- images
    def image_ids(self, category: str, split: str) -> tuple[str, ...]:
        """Ids of the pack images of ``category`` (outdoor, painting, poster) in ``split``."""
        key = (f"image:{category}", split)
        if key not in self._textures:
            self._textures[key] = tuple(e.id for e in self.pack.select("image", category, split))
        return self._textures[key]

    def image_size(self, image_id: str) -> tuple[int, int]:
        """``(width, height)`` of a pack image in pixels (its header only is read)."""
        if image_id not in self._image_sizes:
            from PIL import Image as PILImage

            path = self.root / self.pack.entry(image_id).files["image"]
            try:
                with PILImage.open(path) as im:
                    self._image_sizes[image_id] = (int(im.width), int(im.height))
            except OSError as e:
                raise AssetPackError(f"{path}: not a readable image ({e})") from None
        return self._image_sizes[image_id]


def _qualifies(r: Role, name: str, size: np.ndarray, elevation: float) -> bool:
    wide, deep = max(size[0], size[1]), min(size[0], size[1])
    checks = (r.height[0] <= size[2] <= r.height[1], r.width[0] <= wide <= r.width[1],
              r.depth[0] <= deep <= r.depth[1], r.elevation[0] <= elevation <= r.elevation[1],
              not r.include or re.search(r.include, name) is not None,
              not r.exclude or re.search(r.exclude, name) is None)
    return all(checks)


_LIBRARIES: dict[str, Library] = {}


def library(path: str | os.PathLike[str] | None = None) -> Library:
    """The process's :class:`Library` of the pack :func:`resolve_pack` finds for ``path`` (opened on first use).

    Raises:
        ConfigError: no pack there. AssetPackError: a malformed pack.
    """
    root = resolve_pack(path)
    key = str(root.resolve())
    if key not in _LIBRARIES:
        _LIBRARIES[key] = Library(root)
    return _LIBRARIES[key]


def describe(lib: Library, split: str) -> dict[str, Any]:
    """How many pack meshes each role has in ``split`` (for checking a pack against the generator)."""
    return {role: len(lib.role_ids(role, split)) for role in ROLES}

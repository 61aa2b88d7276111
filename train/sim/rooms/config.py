"""Settings of the furnished rooms (the ``"home"`` world): :class:`HomeConfig` and its :class:`MaterialConfig`.

Every field is a plain number, range, string or tuple, so that a config is written to JSON and read back exactly
(:meth:`fruxel.train.sim.config.SimConfig.to_dict`); each dataclass checks itself when made and raises
:class:`fruxel.errors.ConfigError` naming the field. Ranges are ``(low, high)``: counts inclusive, lengths in metres,
angles in degrees.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any, ClassVar

from fruxel.errors import ConfigError

from ..checks import check_range

ROOM_TYPES = ("living", "bedroom", "dining", "office", "kitchen", "studio")
"""What a room is furnished as (:mod:`.furnish` says which pieces each type places)."""

ASSET_SPLITS = ("train", "test")
"""The asset pack's splits (:mod:`fruxel.train.sim.assetpack.manifest`)."""

TRAIN_SPLIT = "train"
"""The data split whose rooms always draw the pack's train assets."""


def _range(name: str, value: Any, low: float, high: float) -> None:
    check_range(f"home.{name}", value, low, high)


def _count_range(name: str, value: Any, high: int = 1000) -> None:
    try:
        lo, hi = value
    except (TypeError, ValueError):
        raise ConfigError(f"home.{name} must be a (low, high) pair of integers, got {value!r}") from None
    if not all(isinstance(v, int) and not isinstance(v, bool) for v in (lo, hi)) or not 0 <= lo <= hi <= high:
        raise ConfigError(f"home.{name} must be integers with 0 <= low <= high <= {high}, got {value!r}")


def _probability(name: str, value: Any) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not 0.0 <= value <= 1.0:
        raise ConfigError(f"home.{name} must be a number in [0, 1], got {value!r}")


@dataclass(frozen=True)
class MaterialConfig:
    """How surfaces draw their materials from the pack's textures (:mod:`.materials` documents the sampling).

    A surface has a *role* (wall, floor, wood part, upholstery, metal part, ...); its material category (plaster,
    wood, fabric, ...) is drawn from a mixture of the uniform distribution over every category the pack has and
    the role's table of plausible categories, so that no category belongs to one class.
    """

    plausibility: float = 0.8
    """In [0, 1]: weight of the role's plausible categories in the mixture (0: every surface draws its category
    uniformly, whatever it is; 1: only plausible pairings, a wall is never leather)."""
    plain: float = 0.08
    """Chance that a surface has no texture at all, only its tint (a smooth painted or lacquered surface)."""
    tile_scale: tuple[float, float] = (0.7, 1.5)
    """Range of the factor on the pack's metric tile size (``Material.tile_m = size_m * factor``)."""
    saturation: tuple[float, float] = (0.0, 0.3)
    """Range of the tint's saturation on light, neutral textures (plaster, paint, concrete, fabric, metal)."""
    value: tuple[float, float] = (0.55, 1.0)
    """Range of the tint's value (brightness) on every texture."""
    vivid: float = 0.12
    """Chance of a vivid tint (saturation 0.4 to 0.8) on a neutral texture: coloured paint and fabric."""
    source_colour: float = 0.35
    """Chance that a part of a pack mesh whose role is not fixed (plastic, clutter, unnamed parts) keeps its
    model's own colour as tint; foliage, skin and screens always do."""
    roughness_jitter: float = 0.1
    """Largest change of a material category's roughness range ends, either way."""

    def __post_init__(self) -> None:
        for name in ("plausibility", "plain", "vivid", "source_colour", "roughness_jitter"):
            _probability(f"materials.{name}", getattr(self, name))
        _range("materials.tile_scale", self.tile_scale, 0.05, 20.0)
        _range("materials.saturation", self.saturation, 0.0, 1.0)
        _range("materials.value", self.value, 0.0, 1.0)


@dataclass(frozen=True)
class HomeConfig:
    """Ranges the furnished-room generator (:func:`fruxel.train.sim.rooms.make_home`) draws from."""

    room_types: tuple[str, ...] = ROOM_TYPES
    """The room types drawn from, uniformly (a subset of :data:`ROOM_TYPES`)."""
    length_range: tuple[float, float] = (3.0, 6.5)
    """Interior size along x, metres."""
    width_range: tuple[float, float] = (2.8, 5.5)
    """Interior size along y, metres."""
    height_range: tuple[float, float] = (2.4, 3.2)
    """Interior height (floor to ceiling), metres."""
    wall_thickness_range: tuple[float, float] = (0.12, 0.3)
    """Wall thickness, metres (windows and doors sit in it)."""
    slab_thickness: float = 0.12
    """Thickness of the floor slab below z = 0 and of the ceiling slab above the interior, metres."""
    doors: tuple[int, int] = (1, 2)
    """Number of doors, at most one per wall (fewer where the walls have no room left)."""
    double_door: float = 0.15
    """Chance that a door has two leaves."""
    open_door: float = 0.6
    """Chance that a door's leaves are open; an open leaf swings into the room."""
    door_angle: tuple[float, float] = (10.0, 85.0)
    """Range of an open leaf's angle from its closed position, degrees (at most 85: a leaf opened flat would touch
    the casing)."""
    hall_depth: tuple[float, float] = (1.0, 2.5)
    """Depth of the hall behind each door (its floor, walls and ceiling, seen through an open door), metres."""
    windows: tuple[int, int] = (1, 3)
    """Number of windows (fewer where the walls have no room left)."""
    french_window: float = 0.15
    """Chance that a window reaches down to the floor."""
    outdoor_distance: tuple[float, float] = (0.6, 2.5)
    """Distance of the outdoor picture behind a window from the wall's outer face, metres."""
    curtains: float = 0.55
    """Chance that a window has curtains."""
    baseboard: float = 0.85
    """Chance that the walls have baseboards."""
    crown: float = 0.25
    """Chance of a crown moulding along the top of the walls."""
    radiator: float = 0.35
    """Chance that a window with room below it has a radiator under it."""
    extra_furniture: tuple[int, int] = (2, 5)
    """Additional pieces (storage, armchairs, plants, lamps) placed after the room type's own."""
    procedural: float = 0.05
    """Chance that a piece is built from boxes rather than taken from the pack even when the pack has one for its
    role. Roles the pack's split lacks are always built (the held-out split has a fifth of the meshes); this share
    puts built pieces into training rooms too, so that they are not a look only test rooms have."""
    sculptures: tuple[int, int] = (0, 2)
    """Number of sculptures (on the floor, on a pedestal, or small ones on furniture)."""
    sculpture_figures: float = 0.2
    """Chance that a sculpture is one of the pack's scanned animal figurines rather than a scanned statue."""
    rugs: tuple[int, int] = (0, 2)
    """Number of rugs (under the main group's furniture, or free on the floor)."""
    rug_thickness: tuple[float, float] = (0.008, 0.025)
    """Rug thickness, metres; furniture standing on a rug is raised by it."""
    filled_solids: bool = True
    """Label a pack mesh that is not closed by its filled solid (:mod:`.solids`); False: by the mesh itself, whose
    inside (a winding number over 0.5) is scattered cells for most of them (what data sets made before had)."""
    label_thickness: float = 0.12
    """Thinnest upright slab in the labels, metres: a door leaf, a painting, a pane or another thin upright part of
    a door, window, furniture, sculpture or object is labelled as a slab this thick about its middle
    (:func:`.solids.thicken_slabs`; images show it as it is); 0: none. The default is the depth of a 64^3 grid's
    slices over 0.5-8 m, so that every column that sees it finds a cell centre inside it."""
    wall_art: tuple[int, int] = (2, 7)
    """Number of paintings and posters on the walls."""
    plants: tuple[int, int] = (1, 3)
    """Number of plants standing on the floor (small ones on furniture come with the clutter)."""
    ceiling_lamps: tuple[int, int] = (1, 2)
    """Number of ceiling fixtures (flush, pendant or track lights)."""
    clutter: tuple[float, float] = (0.3, 0.9)
    """Range of the share of each support surface's free spots that gets small things (clutter, lamps, plants,
    frames, books)."""
    books: tuple[float, float] = (0.4, 0.95)
    """Range of the share of a bookcase's shelf length filled with books."""
    lights: tuple[int, int] = (1, 4)
    """Number of lights that are on: sun through a window, ceiling fixtures, lamps."""
    sun: float = 0.6
    """Chance that the sun shines through a window, when the room has one."""
    min_gap: float = 0.04
    """Smallest gap between the footprints of two pieces, metres."""
    door_clearance: float = 0.9
    """Smallest depth of the floor area kept free in front of each door, metres (at least the leaf's width)."""
    placement_tries: int = 30
    """Random positions tried per piece before it is left out."""
    free_space_resolution: float = 0.05
    """Cell size of the robot's free-space map, metres."""
    test_assets: str = "test"
    """The pack split that rooms of data splits other than ``train`` draw their meshes, textures and pictures
    from: ``"test"`` (held-out assets training never sees) or ``"train"``. Rooms of the ``train`` split always
    draw train assets."""
    materials: MaterialConfig = field(default_factory=MaterialConfig)
    """How surfaces draw their materials."""

    RECORDED_BEFORE: ClassVar[dict[str, Any]] = {"filled_solids": False, "label_thickness": 0.0}
    """Fields added after data sets were recorded, with what those data sets were made with (pack meshes labelled
    as they are, no slab thickened)."""

    def __post_init__(self) -> None:
        if isinstance(self.room_types, str) or not self.room_types or \
                not set(self.room_types) <= set(ROOM_TYPES) or len(set(self.room_types)) != len(self.room_types):
            raise ConfigError(f"home.room_types must be distinct names among {ROOM_TYPES}, got {self.room_types!r}")
        _range("length_range", self.length_range, 2.5, 30.0)
        _range("width_range", self.width_range, 2.5, 30.0)
        _range("height_range", self.height_range, 2.3, 6.0)
        _range("wall_thickness_range", self.wall_thickness_range, 0.08, 0.6)
        for name in ("door_angle",):
            _range(name, getattr(self, name), 0.0, 85.0)
        for name in ("hall_depth", "outdoor_distance"):
            _range(name, getattr(self, name), 0.3, 20.0)
        _range("rug_thickness", self.rug_thickness, 0.003, 0.06)
        _range("clutter", self.clutter, 0.0, 1.0)
        _range("books", self.books, 0.0, 1.0)
        for name in ("doors", "windows", "extra_furniture", "sculptures", "rugs", "wall_art", "plants",
                     "ceiling_lamps", "lights"):
            _count_range(name, getattr(self, name))
        if self.lights[0] < 1:
            raise ConfigError(f"home.lights must light the room: low >= 1, got {self.lights!r}")
        for name in ("double_door", "open_door", "french_window", "curtains", "baseboard", "crown", "radiator",
                     "procedural", "sculpture_figures", "sun"):
            _probability(name, getattr(self, name))
        if not isinstance(self.filled_solids, bool):
            raise ConfigError(f"home.filled_solids must be true or false, got {self.filled_solids!r}")
        for name in ("slab_thickness", "min_gap", "door_clearance", "free_space_resolution", "label_thickness"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, float)) or not 0.0 <= v < 10.0 or \
                    (v == 0 and name not in ("min_gap", "label_thickness")):
                raise ConfigError(f"home.{name} must be a length in metres, > 0 and < 10, got {v!r}")
        if isinstance(self.placement_tries, bool) or not isinstance(self.placement_tries, int) or \
                not 1 <= self.placement_tries <= 10_000:
            raise ConfigError(f"home.placement_tries must be an integer in [1, 10000], got {self.placement_tries!r}")
        if self.test_assets not in ASSET_SPLITS:
            raise ConfigError(f"home.test_assets must be one of {ASSET_SPLITS}, got {self.test_assets!r}")
        if not isinstance(self.materials, MaterialConfig):
            raise ConfigError(f"home.materials must be a MaterialConfig, got {type(self.materials).__name__}")

    def asset_split(self, split: str) -> str:
        """The pack split that rooms of data split ``split`` draw their assets from (see :attr:`test_assets`)."""
        return TRAIN_SPLIT if split == TRAIN_SPLIT else self.test_assets

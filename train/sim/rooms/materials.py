"""Materials of the furnished rooms: every surface draws its own from the pack's textures, independently of its
class.

Sampling (one :class:`MaterialSampler` per room, drawing from the room's generator)

1. Each surface has a *role* (:data:`PLAUSIBLE`'s keys): what kind of surface it is physically, not which class it
   is labelled as. Walls, halls and the ceiling are ``wall`` or ``ceiling``, the floor ``floor``; baseboards,
   window and door frames ``trim``; door leaves ``door``; furniture bodies, shelves and tables ``wood``;
   upholstery, bedding and curtains ``soft``; handles, legs and lamp parts ``metal``; rugs ``rug``; statues and
   pedestals ``stone``; clutter, books and unnamed parts ``any``. A pack mesh's parts get their role from their
   material names (:func:`part_role`: "chrome" is metal, "fabric" soft, "glass" glass, ...), else from the piece.
2. The material category (plaster, paint, wallpaper, brick, tile, concrete, stone, marble, wood, carpet, fabric,
   leather, metal: the categories the pack's split has) is drawn from the mixture
   ``(1 - p) * uniform + p * PLAUSIBLE[role]`` with ``p = MaterialConfig.plausibility``: every category has a
   chance on every surface (a sofa may be wood, a wall leather), plausible ones more. With
   ``MaterialConfig.plain`` the surface gets no texture, only its tint.
3. The texture is drawn uniformly from the category in the room's asset split; ``tile_m`` is the texture's metric
   size (the pack's ``size_m``) times a factor in ``MaterialConfig.tile_scale``.
4. The tint (``Material.color``, linear RGB, multiplied with the texture) is near white on textures that carry
   their own colour (wood, brick, tile, ...), a random hue of saturation ``MaterialConfig.saturation`` on light,
   neutral ones (plaster, paint, concrete, fabric, metal; vivid with ``MaterialConfig.vivid``), always with value
   in ``MaterialConfig.value``. Roughness is drawn from the category's range (:data:`ROUGHNESS`, ends moved by up
   to ``MaterialConfig.roughness_jitter``); metalness is high for metal and 0 otherwise.

Special roles: ``glass`` (window panes, glass parts: a light tint, opacity 0.15 to 0.4, smooth), ``keep`` (a pack
part whose own colour matters: foliage, skin, screens; its source colour as tint on a plain or subtle texture),
and pictures (:meth:`MaterialSampler.picture`: an image stretched once, for paintings, posters and the outdoor
view).
"""

from __future__ import annotations

import colorsys
import re
from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from ..scene import Material
from .config import MaterialConfig

if TYPE_CHECKING:
    from .library import Library

PLAUSIBLE: dict[str, dict[str, float]] = {
    "wall": {"plaster": 4, "paint": 4, "wallpaper": 2, "brick": 1, "concrete": 1, "wood": 0.6, "tile": 0.5,
             "stone": 0.4, "marble": 0.2},
    "ceiling": {"plaster": 5, "paint": 5, "concrete": 1, "wood": 0.5},
    "floor": {"wood": 6, "tile": 2.5, "concrete": 1, "stone": 1, "marble": 1},
    "trim": {"paint": 4, "wood": 4, "plaster": 1, "metal": 0.5, "marble": 0.3},
    "door": {"wood": 6, "paint": 3, "metal": 0.5, "plaster": 0.3},
    "wood": {"wood": 8, "paint": 1.5, "metal": 1, "marble": 0.6, "leather": 0.3, "concrete": 0.3, "stone": 0.3},
    "soft": {"fabric": 6, "leather": 2, "wallpaper": 0.3},
    "metal": {"metal": 7, "paint": 1, "wood": 0.5},
    "rug": {"carpet": 6, "fabric": 3},
    "stone": {"marble": 3, "stone": 3, "metal": 2, "concrete": 1.5, "plaster": 1.5, "wood": 1},
    "any": {"paint": 2, "metal": 1.5, "wood": 1.5, "fabric": 1, "plaster": 0.5, "leather": 0.5, "marble": 0.3},
}
"""Plausible material categories per role, with relative weights (module docstring, step 2)."""

ROLES = (*PLAUSIBLE, "glass", "keep")
"""Every role a surface can have."""

ROUGHNESS: dict[str, tuple[float, float]] = {
    "plaster": (0.75, 0.95), "paint": (0.35, 0.85), "wallpaper": (0.6, 0.9), "brick": (0.75, 0.95),
    "concrete": (0.6, 0.95), "tile": (0.1, 0.4), "stone": (0.5, 0.9), "marble": (0.05, 0.3), "wood": (0.3, 0.75),
    "carpet": (0.85, 1.0), "fabric": (0.75, 1.0), "leather": (0.35, 0.65), "metal": (0.15, 0.5),
}
"""Roughness range per material category (module docstring, step 4); other categories take (0.3, 0.9)."""

COLOURED = frozenset({"wood", "brick", "tile", "stone", "marble", "carpet", "leather", "wallpaper"})
"""Categories whose textures carry their own colour: tinted only slightly."""

_PART_RULES = (
    ("glass", r"glass|vidro|cristal|transparent|crystal|window ?pane|mirror|lens"),
    ("keep", r"leaf|leave|stem|branch|stalk|plant|flower|petal|pollen|soil|grass|trunk|skin|hair|eye|iris|"
             r"cornea|teeth|gum|lip|screen|display|led|label|book|page|paper|fruit|food"),
    ("metal", r"metal|chrome|steel|alu|inox|brass|gold|silver|iron|cromo|copper|handle|knob|hinge|gond|nickel"),
    ("soft", r"fabric|cloth|textile|cushion|pillow|mattress|matress|sheet|blanket|duvet|seat|couch|sofa|leather|"
             r"cosin|towel|curtain|velvet|linen|wool|upholster|plaid"),
    ("wood", r"wood|oak|pine|madera|ash|venge|teak|walnut|beech|maple|cherry|birch|plank|board|tabletop|worktop"),
    ("stone", r"marble|granite|stone|ceramic|porcelain"),
)
"""(role, regular expression on the lower-case part name), first match wins (:func:`part_role`)."""


def part_role(name: str, opacity: int) -> str | None:
    """The role a pack mesh's part has by its material name (None: the piece decides).

    Args:
        name: the part's material name from the source.
        opacity: its alpha, 0-255; a see-through part is glass whatever its name.
    """
    if opacity < 250:
        return "glass"
    low = name.lower()
    return next((role for role, pat in _PART_RULES if re.search(pat, low)), None)


def srgb_to_linear(c: np.ndarray) -> np.ndarray:
    """sRGB values in [0, 1] to linear RGB (the IEC 61966-2-1 curve)."""
    c = np.asarray(c, dtype=np.float64)
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4)


def linear_to_srgb(c: np.ndarray) -> np.ndarray:
    """Linear RGB in [0, 1] to sRGB values."""
    c = np.clip(np.asarray(c, dtype=np.float64), 0.0, 1.0)
    return np.where(c <= 0.0031308, c * 12.92, 1.055 * c ** (1 / 2.4) - 0.055)


def _hsv(h: float, s: float, v: float) -> np.ndarray:
    return np.array(colorsys.hsv_to_rgb(h % 1.0, min(max(s, 0.0), 1.0), min(max(v, 0.0), 1.0)))


class MaterialSampler:
    """Draws the materials of one room (module docstring).

    Args:
        rng: the room's random generator (every draw comes from it, in call order).
        config: the sampling settings.
        library: the asset pack's textures and images.
        split: the pack split the room draws from.
    """

    def __init__(self, rng: np.random.Generator, config: MaterialConfig, library: Library, split: str) -> None:
        self.rng = rng
        self.config = config
        self.library = library
        self.split = split
        self.categories = tuple(library.texture_categories(split))
        """The pack split's texture categories, sorted."""

    def category(self, role: str) -> str | None:
        """A material category for a surface of ``role`` (None when the pack split has no textures)."""
        if not self.categories:
            self.rng.uniform()
            return None
        table = PLAUSIBLE.get(role, PLAUSIBLE["any"])
        plausible = np.array([table.get(c, 0.0) for c in self.categories])
        n = len(self.categories)
        p = self.config.plausibility
        weights = np.full(n, (1.0 - p) / n)
        if plausible.sum() > 0:
            weights += p * plausible / plausible.sum()
        else:
            weights += p / n
        return self.categories[int(np.searchsorted(np.cumsum(weights) / weights.sum(), self.rng.uniform()))]

    def draw(self, role: str, source: Sequence[float] | None = None) -> Material:
        """A material for a surface of ``role`` (one of :data:`ROLES`).

        Args:
            role: the surface's role.
            source: for ``keep``, the part's own linear RGB colour.
        """
        rng, cfg = self.rng, self.config
        if role == "glass":
            tint = _hsv(rng.uniform(0.45, 0.62), rng.uniform(0.0, 0.15), rng.uniform(0.85, 1.0))
            return Material(tuple(float(c) for c in tint), roughness=float(rng.uniform(0.0, 0.1)),
                            opacity=float(rng.uniform(0.15, 0.4)))
        if role == "keep":
            colour = np.asarray(source if source is not None else (0.6, 0.6, 0.6), dtype=np.float64)
            jitter = rng.uniform(0.85, 1.1)
            texture = self._texture("paint" if "paint" in self.categories else None) if rng.uniform() < 0.5 else None
            tint = tuple(float(c) for c in np.clip(colour * jitter, 0.0, 1.0))
            return Material(tint, texture[0] if texture else None, texture[1] if texture else 1.0,
                            roughness=float(rng.uniform(0.3, 0.8)))
        category = self.category(role)
        plain = rng.uniform() < cfg.plain
        texture = None if plain else self._texture(category)
        tint = self._tint(category)
        lo, hi = ROUGHNESS.get(category or "", (0.3, 0.9))
        j = cfg.roughness_jitter
        rough = float(np.clip(rng.uniform(lo - j, hi + j), 0.02, 1.0))
        metal = float(rng.uniform(0.6, 1.0)) if category == "metal" else 0.0
        return Material(tuple(float(c) for c in tint), texture[0] if texture else None,
                        texture[1] if texture else 1.0, roughness=rough, metallic=metal)

    def _texture(self, category: str | None) -> tuple[str, float] | None:
        """A texture id of ``category`` and its tile size, or None (no category). Draws twice either way."""
        pick, scale = self.rng.uniform(), self.rng.uniform(*self.config.tile_scale)
        if category is None:
            return None
        ids = self.library.texture_ids(category, self.split)
        if not ids:
            return None
        tid = ids[min(int(pick * len(ids)), len(ids) - 1)]
        return tid, float(self.library.texture_size(tid) * scale)

    def _tint(self, category: str | None) -> np.ndarray:
        rng, cfg = self.rng, self.config
        hue, vivid, sat, val = rng.uniform(), rng.uniform() < cfg.vivid, rng.uniform(*cfg.saturation), \
            rng.uniform(*cfg.value)
        if category in COLOURED:
            sat = sat * 0.4
        elif vivid:
            sat = rng.uniform(0.4, 0.8)
        return srgb_to_linear(_hsv(hue, sat, val))

    def picture(self, image: str, emission: float = 0.0) -> Material:
        """A pack image stretched once over a surface: a painting's canvas, a poster, the view out of a window."""
        rng = self.rng
        shade = float(rng.uniform(0.85, 1.0))
        return Material((shade, shade, shade), image=image, roughness=float(rng.uniform(0.4, 0.9)),
                        emission=float(emission))

"""Semantic classes: names and display colours of the labels of a fruxel model (conventions section 2).

Label ``c`` of a model means class ``names[c]``; class 0 is always ``"empty"``. Labels are uint8 on disk, so a
table holds at most 256 classes. A table is stored with every model and data set, so users may define their
own classes; :data:`DEFAULT_CLASSES` is the project's default set.

Default palette (RGB, uint8), chosen from the Tableau 10 / 20 colours, which are distinct on screen and in
greyscale print and keep the semantic hints a viewer expects (floor greenish, window cyan, door brown):

    ===  =========  ===============  =========================================================
    id   name       RGB              why
    ===  =========  ===============  =========================================================
    0    empty      (0, 0, 0)        never drawn; black where a colour is needed (background)
    1    wall       (174, 199, 232)  light blue: large, calm surfaces that should not dominate
    2    floor      (152, 223, 138)  light green
    3    window     (23, 190, 207)   cyan, glass
    4    furniture  (255, 127, 14)   orange, stands out against walls and floor
    5    door       (140, 86, 75)    brown, wood
    6    sculpture  (148, 103, 189)  purple
    ===  =========  ===============  =========================================================

:data:`HOME_CLASSES` appends the two classes of the simulator's furnished rooms (conventions section 2), so files
with the default table stay readable:

    ===  =========  ===============  =========================================================
    7    ceiling    (219, 219, 141)  pale olive: large and calm like the walls, yet told apart from them
    8    object     (227, 119, 194)  pink: clutter and decoration (paintings, plants, lamps, rugs, books)
    ===  =========  ===============  =========================================================

Classes added without a colour get the next unused colour of :data:`EXTRA_COLOURS`, then generated hues.
"""

from __future__ import annotations

import colorsys
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from .errors import FruxelError

MAX_CLASSES = 256
"""Labels are stored as uint8, so a class table holds at most 256 classes (ids 0..255)."""

MAX_NAME_LENGTH = 256
"""Longest class name accepted, in characters; keeps file metadata small."""

EMPTY = "empty"
"""Name of class 0, which every table starts with."""

Colour = tuple[int, int, int]

DEFAULT_NAMES: tuple[str, ...] = ("empty", "wall", "floor", "window", "furniture", "door", "sculpture")
"""The default class names, in label order (conventions section 2)."""

DEFAULT_COLOURS: tuple[Colour, ...] = (
    (0, 0, 0),
    (174, 199, 232),
    (152, 223, 138),
    (23, 190, 207),
    (255, 127, 14),
    (140, 86, 75),
    (148, 103, 189),
)
"""RGB uint8 colours of :data:`DEFAULT_NAMES` (see the module docstring)."""

EXTRA_COLOURS: tuple[Colour, ...] = (
    (214, 39, 40),
    (31, 119, 180),
    (44, 160, 44),
    (227, 119, 194),
    (188, 189, 34),
    (255, 187, 120),
    (255, 152, 150),
    (197, 176, 213),
    (196, 156, 148),
    (247, 182, 210),
    (219, 219, 141),
    (158, 218, 229),
    (127, 127, 127),
)
"""Colours handed out, in order, to classes created without one (the rest of Tableau 20)."""


class ClassTableError(FruxelError, ValueError):
    """Raised for an invalid class table (names, colours, sizes) or a label outside the table."""


def _check_colour(index: int, colour: Any) -> Colour:
    try:
        values = tuple(colour)
    except TypeError:
        raise ClassTableError(f"colour of class {index} must be an RGB triple, got {colour!r}") from None
    if len(values) != 3:
        raise ClassTableError(f"colour of class {index} must have 3 components, got {colour!r}")
    out = []
    for v in values:
        if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or not 0 <= v <= 255:
            raise ClassTableError(f"colour of class {index} must hold integers in [0, 255], got {colour!r}")
        out.append(int(v))
    return (out[0], out[1], out[2])


def _generated_colour(n: int) -> Colour:
    # Golden-ratio hue steps spread any number of extra classes around the colour wheel without repeats.
    hue = (0.13 + n * 0.618033988749895) % 1.0
    r, g, b = colorsys.hsv_to_rgb(hue, 0.55, 0.9)
    return (round(r * 255), round(g * 255), round(b * 255))


def auto_colours(n: int, taken: Iterable[Colour] = ()) -> tuple[Colour, ...]:
    """``n`` distinct RGB colours not in ``taken``: :data:`EXTRA_COLOURS` first, then generated hues.

    Args:
        n: number of colours wanted, >= 0.
        taken: colours already in use, to skip.

    Returns:
        ``n`` RGB triples of ints in [0, 255].
    """
    used = set(taken)
    out: list[Colour] = []
    candidates = iter(EXTRA_COLOURS)
    generated = 0
    while len(out) < n:
        colour = next(candidates, None)
        if colour is None:
            colour = _generated_colour(generated)
            generated += 1
        if colour not in used:
            used.add(colour)
            out.append(colour)
    return tuple(out)


@dataclass(frozen=True)
class ClassTable:
    """Names and display colours of the semantic classes; label ``c`` is class ``names[c]``.

    Immutable and hashable; validated on construction (lists are accepted and stored as tuples).

    Raises:
        ClassTableError: no classes or more than :data:`MAX_CLASSES`, class 0 not named ``"empty"``, names
            that are empty, not strings, too long or repeated, or colours that are not one RGB triple of
            integers in [0, 255] per class.
    """

    names: tuple[str, ...]
    """Class names in label order; ``names[0] == "empty"``; unique, non-empty strings."""
    colours: tuple[Colour, ...]
    """One ``(r, g, b)`` triple of ints in [0, 255] per class, same order as ``names``."""

    def __post_init__(self) -> None:
        if isinstance(self.names, str) or not isinstance(self.names, Sequence):
            raise ClassTableError(f"class names must be a sequence of strings, got {type(self.names).__name__}")
        names = tuple(self.names)
        if not 1 <= len(names) <= MAX_CLASSES:
            raise ClassTableError(f"a class table holds 1 to {MAX_CLASSES} classes, got {len(names)}")
        for c, name in enumerate(names):
            if not isinstance(name, str) or not name or len(name) > MAX_NAME_LENGTH:
                raise ClassTableError(
                    f"class {c} name must be a non-empty string of at most {MAX_NAME_LENGTH} characters, got {name!r}"
                )
        if names[0] != EMPTY:
            raise ClassTableError(f"class 0 must be named {EMPTY!r}, got {names[0]!r}")
        if len(set(names)) != len(names):
            dupes = sorted({n for n in names if names.count(n) > 1})
            raise ClassTableError(f"class names must be unique, repeated: {dupes}")
        if isinstance(self.colours, (str, bytes)) or not isinstance(self.colours, (Sequence, np.ndarray)):
            raise ClassTableError(f"colours must be a sequence of RGB triples, got {type(self.colours).__name__}")
        if len(self.colours) != len(names):
            raise ClassTableError(f"got {len(names)} class names but {len(self.colours)} colours")
        colours = tuple(_check_colour(c, col) for c, col in enumerate(self.colours))
        object.__setattr__(self, "names", names)
        object.__setattr__(self, "colours", colours)

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_names(cls, names: Sequence[str], colours: Sequence[Any] | None = None) -> ClassTable:
        """A table from names, with ``"empty"`` prepended if missing and colours filled in where not given.

        Args:
            names: class names in label order, with or without the leading ``"empty"``.
            colours: RGB triples for the first ``len(colours)`` classes of the resulting table (``"empty"``
                included); the rest get :func:`auto_colours`.
        """
        names = tuple(names)
        if not names or names[0] != EMPTY:
            names = (EMPTY, *names)
        given = [] if colours is None else list(colours)
        if len(given) > len(names):
            raise ClassTableError(f"got {len(names)} class names but {len(given)} colours")
        if not given:
            given = [DEFAULT_COLOURS[0]]
        checked = [_check_colour(c, col) for c, col in enumerate(given)]
        return cls(names, (*checked, *auto_colours(len(names) - len(checked), checked)))

    def extended(self, *names: str, colours: Sequence[Any] | None = None) -> ClassTable:
        """This table with classes appended (new ids ``len(self) ..``), colours given or automatic.

        Args:
            *names: names of the new classes.
            colours: RGB triples for the first ``len(colours)`` new classes; the rest get :func:`auto_colours`.
        """
        given = [] if colours is None else [_check_colour(len(self) + c, col) for c, col in enumerate(colours)]
        if len(given) > len(names):
            raise ClassTableError(f"got {len(names)} new class names but {len(given)} colours")
        extra = auto_colours(len(names) - len(given), (*self.colours, *given))
        return ClassTable((*self.names, *names), (*self.colours, *given, *extra))

    # ------------------------------------------------------------------ queries
    def __len__(self) -> int:
        return len(self.names)

    @property
    def n_classes(self) -> int:
        """Number of classes C, ``"empty"`` included."""
        return len(self.names)

    def index(self, name: str) -> int:
        """Label id of the class called ``name``. Raises ``ClassTableError`` when there is none."""
        try:
            return self.names.index(name)
        except ValueError:
            raise ClassTableError(f"no class named {name!r}; classes are {list(self.names)}") from None

    def indices_in(self, other: ClassTable) -> np.ndarray:
        """Each of this table's classes' label id in ``other``, by name: ``(C,)`` int64, so that a label volume of
        this table is ``indices_in(other)[labels]`` in ``other``'s (a truth of fewer classes against a model of
        more). Raises ``ClassTableError`` naming the classes ``other`` lacks."""
        missing = [n for n in self.names if n not in other.names]
        if missing:
            raise ClassTableError(f"no class named {', '.join(map(repr, missing))} among {list(other.names)}")
        return np.array([other.names.index(n) for n in self.names], dtype=np.int64)

    def palette(self) -> np.ndarray:
        """Colours of all classes: ``(C, 3)`` uint8 RGB, row ``c`` for label ``c``. A new array each call."""
        return np.array(self.colours, dtype=np.uint8).reshape(len(self), 3)

    def colour_of(self, labels: Any) -> np.ndarray:
        """Colours of labels: ``(..., 3)`` uint8 RGB for integer labels of any shape ``(...)``.

        Raises:
            ClassTableError: non-integer labels, or a label outside ``[0, C)``.
        """
        lab = np.asarray(labels)
        if lab.dtype.kind not in "iu":
            raise ClassTableError(f"labels must be integers, got dtype {lab.dtype}")
        if lab.size and (lab.min() < 0 or lab.max() >= len(self)):
            raise ClassTableError(f"labels must be in [0, {len(self)}), got range [{lab.min()}, {lab.max()}]")
        return self.palette()[lab]

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dictionary: ``{"names": [str, ...], "colours": [[r, g, b], ...]}``."""
        return {"names": list(self.names), "colours": [list(c) for c in self.colours]}

    @classmethod
    def from_dict(cls, d: Any) -> ClassTable:
        """Inverse of :meth:`to_dict`. Raises ``ClassTableError`` on missing, extra or invalid keys."""
        if not isinstance(d, dict):
            raise ClassTableError(f"classes must be a JSON object, got {type(d).__name__}")
        keys = ("names", "colours")
        missing = [k for k in keys if k not in d]
        extra = sorted(str(k) for k in set(d) - set(keys))
        if missing or extra:
            raise ClassTableError(f"classes keys: missing {missing}, unexpected {extra}")
        if not isinstance(d["names"], list) or not isinstance(d["colours"], list):
            raise ClassTableError("classes 'names' and 'colours' must be JSON lists")
        return cls(tuple(d["names"]), tuple(d["colours"]))


DEFAULT_CLASSES = ClassTable(DEFAULT_NAMES, DEFAULT_COLOURS)
"""``0 empty, 1 wall, 2 floor, 3 window, 4 furniture, 5 door, 6 sculpture`` with the default palette."""

HOME_NAMES: tuple[str, ...] = ("ceiling", "object")
"""The classes the furnished rooms add after the default ones (conventions section 2), in label order."""

HOME_CLASSES = DEFAULT_CLASSES.extended(*HOME_NAMES, colours=((219, 219, 141), (227, 119, 194)))
"""The default table with ``7 ceiling, 8 object`` appended: the class table of the simulator's furnished rooms."""

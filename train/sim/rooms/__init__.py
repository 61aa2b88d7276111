"""Furnished rooms: the simulator's ``"home"`` world (``SimConfig.world``).

Rooms like rooms: a ceiling, walls with real openings, baseboards, windows with frames, sills, glass and an outdoor
picture behind them, doors with linings, casings, handles and halls, some open; furniture from the asset pack's
Sweet Home 3D meshes placed by context (beds and sofas against walls, nightstands beside beds, chairs at tables and
desks), scanned statues, rugs, paintings and posters, curtains, plants, lamps, books on shelves and small clutter
on the furniture; one to four lights of varied kind and colour; every surface a material drawn from the pack's
textures independently of its class. Labels by class name from :data:`fruxel.classes.HOME_CLASSES` (the default
seven and ``ceiling``, ``object``).

* :mod:`.config` — :class:`HomeConfig` (and :class:`MaterialConfig`), what the rooms draw from;
* :mod:`.home` — :func:`make_home`, the generator and the order of its steps;
* :mod:`.shell` — floor, ceiling, walls, trim, windows, doors and halls;
* :mod:`.furnish` — furniture by room type and context; :mod:`.decor` — curtains, rugs, lamps, books, clutter,
  pictures; :mod:`.lights` — the lights;
* :mod:`.library` — the asset pack found and cached per process, meshes by role; :mod:`.procedural` — built
  stand-ins for roles a pack split lacks; :mod:`.supports` — where things can stand on furniture;
  :mod:`.materials` — the material sampling; :mod:`.draft` — the room while it is made, and its space checks.
"""

from __future__ import annotations

from .config import ROOM_TYPES, HomeConfig, MaterialConfig
from .home import CLASS_NAMES, STAGES, make_home
from .library import ASSETS_ENV, check_pack, library, resolve_pack

__all__ = ["ASSETS_ENV", "CLASS_NAMES", "ROOM_TYPES", "STAGES", "HomeConfig", "MaterialConfig", "check_pack",
           "library", "make_home", "resolve_pack"]

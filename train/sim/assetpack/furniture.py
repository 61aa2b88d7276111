"""Sweet Home 3D libraries as pack candidates: which models are taken, their furniture kind, licence and credit.

The catalog of each ``.sh3f`` is read with :func:`fruxel.train.sim.assets.read_sh3f_catalog` and every model is
turned into the canonical frame with :func:`fruxel.train.sim.assets.sh3d_to_canonical` (``modelRotation``, the
catalog's size, z up, front towards -y), keeping its ``usemtl`` groups as parts (:func:`.meshes.read_obj`).

Kinds come from the model's English name (first matching rule of :data:`KIND_RULES`); catalog categories
``Vehicles``, ``Exterior`` and ``Staircases`` are not taken, nor names in :data:`SKIP_NAMES`. Licences come
from the package's Debian copyright file (``Files: <Library>/*``); credits from each model's ``creator#N`` and
the library's LICENSE file.
"""

from __future__ import annotations

import re
import zipfile
from pathlib import Path
from typing import Any

import numpy as np

from .licences import CopyrightParagraph, lookup_copyright, spdx
from .manifest import AssetPackError, SourceRef
from .sources import Candidate, Package, _slug

FURNITURE_DIR = "usr/share/sweethome3d/furniture"
"""Where the package keeps its ``.sh3f`` libraries."""

SKIP_CATEGORIES = ("Vehicles", "Exterior", "Staircases")
"""Catalog categories not taken (not indoor)."""

SKIP_NAMES = re.compile(r"contemporary living room|elevator|shutter|fence|railing|shipping container|chimney|"
                        r"furnace|bill \d|parking|lamppost|street|park light|porch|outdoor|flashlight|"
                        r"mower|pallet|punching|air conditioning|plug|switch|socket|intercom|smoke detector|"
                        r"rj45|antenna|table tennis bat|keys|ring$|glove|cap$|watch|comb|lip stick|pencil|"
                        r"text marker|scissors|stapler|ruler|screwdriver|pliers|fork$|spoon|knife$", re.I)
"""Names not taken: whole rooms, outdoor items and things too small to matter in a room-sized grid."""

KIND_RULES = (
    (r"bedside|night ?stand", "cabinet"), (r"\bbed\b|crib|futon$|mattress|cradle", "bed"),
    (r"sofa|couch|futon couch", "sofa"), (r"armchair|ottoman|puff", "armchair"),
    (r"chair|stool|bench|seat", "chair"),
    (r"desk lamp|lamp|light|chandelier|lantern", "lamp"),
    (r"\bdesk\b|dressing table|technical table", "desk"),
    (r"\btv\b|television|screen|imac|monitor", "tv"),
    (r"table", "table"),
    (r"bookcase|shelves|shelf", "shelf"),
    (r"cabinet|cupboard|wardrobe|dresser|chest$|drawers|locker|sideboard|vanity|safe$|clothes rack|trunck",
     "cabinet"),
    (r"fridge|refrigerator|freezer|oven|cooker|stove|washing machine|dryer|dish ?washer|hood|boiler|water heater|"
     r"radiator|microwave|water cooler|cooktop", "appliance"),
    (r"bath|toilet|washbasin|basin|bidet|urinal|shower|lavatory|sink", "sanitary"),
    (r"piano|fireplace|island", "furniture"),
    (r"plant|ficus|yucca|tulips|orchid|lily|bamboo|bonsai|cactus|flowers|spathiphyllum|christmas tree", "plant"),
    (r"rug|carpet|bathmat|doormat|tatami", "rug"),
    (r"curtain|blind", "curtain"),
    (r"frame|clock|calendar|white board", "wall_decor"),
)
"""(regular expression on the lower-case name, kind), first match wins; anything else indoor is ``clutter``."""

LABEL = {"bed": "furniture", "sofa": "furniture", "armchair": "furniture", "chair": "furniture",
         "table": "furniture", "desk": "furniture", "shelf": "furniture", "cabinet": "furniture",
         "appliance": "furniture", "sanitary": "furniture", "furniture": "furniture", "lamp": "object",
         "plant": "object", "rug": "object", "curtain": "object", "wall_decor": "object", "tv": "object",
         "clutter": "object", "door": "door", "window": "window", "person": "sculpture", "animal": "sculpture",
         "statue": "sculpture"}
"""The class each kind is drawn as."""

LIBRARY_CREDIT = {
    "BlendSwap-CC-0": "{creator} (Blend Swap), Sweet Home 3D library BlendSwap-CC-0",
    "BlendSwap-CC-BY": "{creator} (Blend Swap), Sweet Home 3D library BlendSwap-CC-BY",
    "KatorLegaz": "Andrew Kator & Jennifer Legaz",
    "Reallusion": "Reallusion (http://www.reallusion.com)",
    "Scopia": "{scopia}",
}
"""Credit text per library; ``{creator}`` is the model's ``creator#N``."""

SCOPIA_ETEKS = "Emmanuel PUYBARET / eTeks and Scopia Visual Interfaces Systems, s.l. (http://www.scopia.es)"
SCOPIA_ONLY = "Scopia Visual Interfaces Systems, s.l. (http://www.scopia.es)"

MODEL_TEXTURES = {
    ("BlendSwap-CC-BY", "blendswap-cc-by/sofa3/dark-brown_leather.jpg"): "leather",
    ("BlendSwap-CC-BY", "blendswap-cc-by/wheelchair/Leather0056_2_S.jpg"): "leather",
    ("BlendSwap-CC-0", "blendswap-cc-0/couch2/Fabric_011_COLOR.jpg"): "fabric",
    ("BlendSwap-CC-BY", "blendswap-cc-by/cornerSofa/Fabric_04.jpg"): "fabric",
    ("BlendSwap-CC-BY", "blendswap-cc-by/plaidChair/cloth-texture-19.jpg"): "fabric",
    ("BlendSwap-CC-0", "blendswap-cc-0/tableWithTablecloth/red_checked.jpg"): "fabric",
    ("BlendSwap-CC-0", "blendswap-cc-0/lowerCabinet/marble_14.jpg"): "marble",
    ("BlendSwap-CC-BY", "blendswap-cc-by/fountain/white-marble.jpg"): "marble",
    ("BlendSwap-CC-0", "blendswap-cc-0/upperCabinet/american_oak.jpg"): "wood",
    ("BlendSwap-CC-0", "blendswap-cc-0/oakTable/oak.jpg"): "wood",
    ("BlendSwap-CC-0", "blendswap-cc-0/table/Wood_013_COLOR.jpg"): "wood",
    ("BlendSwap-CC-BY", "blendswap-cc-by/kitchenChair/Wood_plancks_003_COLOR.jpg"): "wood",
    ("BlendSwap-CC-0", "blendswap-cc-0/rangeHood/Metal009_2K_Color.jpg"): "metal",
    ("KatorLegaz", "katorlegaz/oriental-rug/rug.jpg"): "carpet",
}
"""Material photos inside the libraries taken as textures -> material."""

FACE_BUDGET = {"furniture": 3000, "door": 2000, "window": 2000, "sculpture": 6000, "object": 1200}
"""Faces kept per mesh, by label (clutter and decoration are small in a room-sized grid)."""


def kind_of(name: str, catalog_kind: str) -> str:
    """The pack kind of a Sweet Home 3D model from its name and :func:`fruxel.train.sim.assets` class."""
    if catalog_kind in ("door", "window"):
        return catalog_kind
    low = name.lower()
    return next((k for pat, k in KIND_RULES if re.search(pat, low)), "clutter")


def _scopia_models(zf: zipfile.ZipFile) -> set[str]:
    try:
        text = zf.read("LICENSE.TXT").decode("utf-8", errors="replace")
    except KeyError:
        return set()
    return {line[2:].strip() for line in text.splitlines() if line.startswith("- ")}


def _credit(library: str, item: Any, scopia_eteks: set[str]) -> str:
    creator = item.props.get("creator", "").strip() or library
    folder = item.member.split("/")[-2] if item.member.count("/") >= 2 else ""
    scopia = SCOPIA_ETEKS if folder in scopia_eteks else SCOPIA_ONLY
    return LIBRARY_CREDIT.get(library, "{creator}").format(creator=creator, scopia=scopia)


def _mesh_reader(path: Path, item: Any, label: str) -> Any:
    def read() -> Any:
        from fruxel.train.sim.assets import sh3d_to_canonical

        from .meshes import decimate, read_obj, zip_resolver

        with zipfile.ZipFile(path) as zf:
            folder = item.member.rsplit("/", 1)[0] if "/" in item.member else ""
            raw = read_obj(zf.read(item.member), zip_resolver(zf, folder), f"{path}:{item.member}")
        raw.vertices = sh3d_to_canonical(raw.vertices, item)
        try:
            raw.elevation_m = max(float(item.props.get("elevation", 0) or 0), 0.0) / 100.0
        except ValueError:
            raw.elevation_m = 0.0
        return decimate(raw, FACE_BUDGET[label])

    return read


def sh3d_candidates(tree: Path, pkg: Package, paras: list[CopyrightParagraph]) -> list[Candidate]:
    """Candidates (meshes and material textures) of every ``.sh3f`` library in the package tree.

    Raises:
        AssetPackError: an unreadable library or catalog, or a library its copyright file does not cover.
    """
    from fruxel.train.sim.assets import AssetError, read_sh3f_catalog

    from .sources import _texture

    out: list[Candidate] = []
    for path in sorted((tree / FURNITURE_DIR).glob("*.sh3f")):
        library = path.stem
        try:
            para = lookup_copyright(paras, f"{library}/model.obj")
        except KeyError:
            raise AssetPackError(f"{path}: the package's copyright file has no paragraph for {library}/*") from None
        licence = spdx(para.licence)
        rel = str(path.relative_to(tree))
        try:
            with zipfile.ZipFile(path) as zf:
                items = read_sh3f_catalog(zf, str(path))
                scopia_eteks = _scopia_models(zf) if library == "Scopia" else set()
                members = set(zf.namelist())
        except (OSError, zipfile.BadZipFile) as e:
            raise AssetPackError(f"{path}: not a readable .sh3f library ({e})") from None
        except AssetError as e:
            raise AssetPackError(str(e)) from None
        for item in items:
            if item.category in SKIP_CATEGORIES or SKIP_NAMES.search(item.name):
                continue
            if not item.member.lower().endswith(".obj"):
                continue
            kind = "person" if item.category == "Characters" else kind_of(item.name, item.kind)
            if item.category == "Characters" and re.search(r"dog|cat|horse|rabbit|chicken|bulldog", item.name, re.I):
                kind = "animal"
            label = LABEL[kind]
            model = item.member.rsplit("/", 2)[-2] if item.member.count("/") >= 1 else item.member
            asset_id = f"sh3d/{_slug(library)}/{_slug(model)}-{item.index}"
            size = np.nan_to_num(item.size_cm, nan=0.0)
            out.append(Candidate(asset_id, "mesh", kind, SourceRef(pkg.registry, pkg.name, pkg.version,
                                                                      f"{rel}:{item.member}"),
                                 licence, _credit(library, item, scopia_eteks), _mesh_reader(path, item, label),
                                 label=label, name=item.name,
                                 note="size from the catalog (width, depth, height)" if size.all() else ""))
        for (lib, member), cat in sorted(MODEL_TEXTURES.items()):
            if lib != library or member not in members:
                continue
            owner = next((i for i in items if i.member.rsplit("/", 1)[0] == member.rsplit("/", 1)[0]), None)
            credit = _credit(library, owner, scopia_eteks) if owner is not None else library
            stem = member.rsplit("/", 1)[-1].rsplit(".", 1)[0]
            asset_id = f"sh3d/{_slug(library)}/texture-{_slug(member.split('/')[-2])}-{_slug(stem)}"
            cand = _texture(pkg, tree, rel, cat, licence, credit, asset_id)
            cand.source = SourceRef(pkg.registry, pkg.name, pkg.version, f"{rel}:{member}")

            def read(path: Path = path, member: str = member) -> tuple[bytes, None]:
                with zipfile.ZipFile(path) as zf:
                    return zf.read(member), None

            cand.read = read
            out.append(cand)
    return out

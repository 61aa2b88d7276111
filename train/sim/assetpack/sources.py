"""What the asset pack is built from: the pinned source packages, what is taken from each, and its licence.

Every source is a Debian or PyPI package at a pinned version, fetched without root (:mod:`.fetch`) and unpacked
under ``CACHE/<registry>/<name>-<version>/``. Each licence was checked by hand against the package's own files;
:func:`collect` re-reads the machine-readable ones (Debian copyright files, wallpaper metadata) on every build, so
an entry's licence is the one its package states for that very file.

Sources, what is taken, and where the licence was checked:

- debian ``sweethome3d-furniture`` 1.8-1: five Sweet Home 3D libraries (furniture, doors, windows, people) and
  a few of their material photos (leather, fabric, marble, rug). ``usr/share/doc/sweethome3d-furniture/copyright``:
  BlendSwap-CC-0 CC0, BlendSwap-CC-BY and Scopia CC-BY-3.0, KatorLegaz and Reallusion CC-BY-3.0-US; credits
  from each model's ``creator#N`` and the libraries' LICENSE files.
- debian ``libcgal-demo`` 5.5.1-2: scanned statues from ``data.tar.gz``. ``libcgal-dev``'s copyright: files
  without their own notice are CC0-1.0. The scans' origins are not named there and several well-known ones are
  research-only (Stanford's armadillo, bunny and dragon; the deformation-transfer camel and elephant): those are
  left out, the rest is kept set-up only.
- debian ``ufoai-textures`` 2.5-2: material textures with normal maps, and pictures. Per file from its DEP-5
  copyright (mostly GPL-2+, some CC-BY-3.0 or public domain).
- debian ``mate-backgrounds`` 1.26.0-1: outdoor photos and close-ups. Per file from its DEP-5 copyright: GPL-2+.
- debian ``plasma-workspace-wallpapers`` 5.27.5-2: outdoor photos and prints. Each wallpaper's
  ``metadata.json`` (LGPL-3.0 or CC-BY-SA-4.0, with its author).
- pypi ``miniworld`` 2.1.0: material textures and public-domain portrait paintings. The repository's LICENSE and
  README say MIT (the wheel's metadata says Apache; both allow committing).
- pypi ``robosuite`` 1.5.2: material textures. ``dist-info/licenses/LICENSE``: MIT.
- pypi ``scikit-image`` 0.26.0: a brick texture and photos, CC0 or public domain as
  ``skimage/data/_fetchers.py`` states per image.

Rejected: gnome-backgrounds 43.1 (abstract vector art, no photos), ukui-wallpapers (abstract, CC-BY-SA, nothing
the pack needs), the CGAL scans named above (research-only licences), Sweet Home 3D's vehicles, outdoor
objects and staircases (not indoor), and textures of food, logos, doors and outdoor ground (not wall, floor or
furniture materials).
"""

from __future__ import annotations

import io
import json
import posixpath
import re
import tarfile
import zipfile
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from .licences import committable, lookup_copyright, parse_debian_copyright, spdx
from .manifest import AssetPackError, SourceRef


@dataclass(frozen=True)
class Package:
    """A pinned source package."""

    registry: str
    """``debian`` or ``pypi``."""
    name: str
    """The package name."""
    version: str
    """The exact version fetched (Debian: with its epoch, e.g. ``4:5.27.5-2``)."""

    @property
    def folder(self) -> str:
        """Its unpacked tree under the cache: ``<registry>/<name>-<version>`` (no epoch)."""
        return f"{self.registry}/{self.name}-{self.version.split(':')[-1]}"


SH3D = Package("debian", "sweethome3d-furniture", "1.8-1")
CGAL_DATA = Package("debian", "libcgal-demo", "5.5.1-2")
CGAL_DOC = Package("debian", "libcgal-dev", "5.5.1-2")
UFOAI = Package("debian", "ufoai-textures", "2.5-2")
MATE = Package("debian", "mate-backgrounds", "1.26.0-1")
PLASMA = Package("debian", "plasma-workspace-wallpapers", "4:5.27.5-2")
MINIWORLD = Package("pypi", "miniworld", "2.1.0")
ROBOSUITE = Package("pypi", "robosuite", "1.5.2")
SKIMAGE = Package("pypi", "scikit-image", "0.26.0")
PACKAGES = (SH3D, CGAL_DATA, CGAL_DOC, UFOAI, MATE, PLASMA, MINIWORLD, ROBOSUITE, SKIMAGE)
"""Every source package, in the order they are read."""

TEXTURE_SIZE_M = {"plaster": 1.0, "paint": 1.0, "wallpaper": 0.53, "brick": 1.0, "tile": 0.6, "wood": 1.0,
                  "carpet": 1.0, "fabric": 0.4, "leather": 0.4, "metal": 0.5, "concrete": 2.0, "stone": 1.0,
                  "marble": 1.0}
"""Metres covered by one tile of a texture of each material, where the source gives no size: estimates of a
typical photo texture's field of view (a wallpaper's pattern repeats over its 0.53 m roll width)."""

RELIEF_M = {"plaster": 0.002, "paint": 0.0005, "wallpaper": 0.0005, "brick": 0.008, "tile": 0.002, "wood": 0.001,
            "carpet": 0.004, "fabric": 0.002, "leather": 0.001, "metal": 0.0005, "concrete": 0.003, "stone": 0.008,
            "marble": 0.0005}
"""Height range (metres) given to a texture's luminance when its normal map is derived (no map in the source)."""


@dataclass
class Candidate:
    """One asset to build: what it is, where it comes from, its licence, and how to read its source data."""

    id: str
    """The asset id (see :mod:`.manifest`)."""
    kind: str
    """``texture``, ``mesh`` or ``image``."""
    category: str
    """Material, furniture kind or image use."""
    source: SourceRef
    """Where it comes from."""
    licence: str
    """SPDX id."""
    credit: str
    """Author / copyright text."""
    read: Callable[[], Any]
    """Reads the source data: texture ``(albedo bytes, normal bytes or None)``, image ``bytes``, mesh a
    :class:`fruxel.train.sim.assetpack.meshes.RawMesh`."""
    label: str = ""
    """Meshes: the class it is drawn as."""
    name: str = ""
    """Display name."""
    note: str = ""
    """Free text for the manifest."""
    setup_only: bool = False
    """Keep it out of commits even if its licence would allow them (uncertain provenance)."""
    size_m: tuple[float, ...] | None = None
    """Textures: metres per tile (width; the height follows the aspect ratio)."""
    info: dict[str, Any] = field(default_factory=dict)
    """Extra numbers for the manifest."""

    @property
    def committable(self) -> bool:
        """Whether the built asset may be committed."""
        return committable(self.licence) and not self.setup_only


def _slug(text: str) -> str:
    return re.sub(r"[^a-z0-9_.-]+", "-", text.lower()).strip("-.") or "x"


def _ref(pkg: Package, path: str) -> SourceRef:
    return SourceRef(pkg.registry, pkg.name, pkg.version, path)


def _file_reader(path: Path) -> Callable[[], bytes]:
    return lambda: path.read_bytes()


def _texture(pkg: Package, tree: Path, rel: str, category: str, licence: str, credit: str, asset_id: str,
             normal_rel: str | None = None, note: str = "", size_m: float | None = None) -> Candidate:
    normal = tree / normal_rel if normal_rel else None

    def read() -> tuple[bytes, bytes | None]:
        return (tree / rel).read_bytes(), normal.read_bytes() if normal is not None else None

    size = size_m if size_m is not None else TEXTURE_SIZE_M[category]
    why = "size: the material's typical tile (an estimate)" if size_m is None else "size: measured from the photo"
    return Candidate(asset_id, "texture", category, _ref(pkg, rel), licence, credit, read, name=Path(rel).stem,
                     note="; ".join(x for x in (note, why) if x), size_m=(size,))


# ---------------------------------------------------------------------------------------------------- PyPI
MINIWORLD_TEXTURES = {
    "brick_wall_1": "brick", "cinder_blocks_1": "brick", "ceiling_tile_noborder_1": "plaster",
    "ceiling_tiles_1": "tile", "concrete_1": "concrete", "concrete_2": "concrete", "concrete_3": "concrete",
    "concrete_4": "concrete", "concrete_tiles_1": "tile", "drywall_1": "paint", "floor_tiles_bw_1": "tile",
    "floor_tiles_white": "tile", "marble_1": "marble", "metal_grill_1": "metal", "metal_grill_2": "metal",
    "stucco_1": "plaster", "white_1": "paint", "wood_1": "wood", "wood_2": "wood", "wood_planks_1": "wood",
}
"""Miniworld texture (file stem) -> material; the rest are doors, food, ground, water or logos."""

MINIWORLD_CREDIT = "Miniworld (Maxime Chevalier-Boisvert, Farama Foundation)"

ROBOSUITE_TEXTURES = {
    "blue-wood": "wood", "dark-wood": "wood", "gray-woodgrain": "wood", "green-wood": "wood", "light-wood": "wood",
    "red-wood": "wood", "wood-tiles": "wood", "wood-varnished-panels": "wood", "brass-ambra": "metal",
    "metal": "metal", "steel-brushed": "metal", "steel-scratched": "metal", "clay": "plaster",
    "cream-plaster": "plaster", "gray-plaster": "plaster", "light-gray-plaster": "plaster",
    "pink-plaster": "plaster", "white-plaster": "plaster", "yellow-plaster": "plaster", "ceramic": "paint",
    "gray-felt": "fabric", "light-gray-floor-tile": "tile", "white-bricks": "brick",
}
"""robosuite texture (file stem) -> material; the rest are food, cans, dirt and glass."""

SKIMAGE_FILES = {
    # file: (kind, category, licence, credit) as skimage/data/_fetchers.py states them
    "brick.png": ("texture", "brick", "CC0-1.0", "scikit-image data: Bricks25 from CC0Textures"),
    "rocket.jpg": ("image", "outdoor", "LicenseRef-public-domain", "SpaceX, released into the public domain "
                   "(scikit-image data)"),
    "astronaut.png": ("image", "poster", "LicenseRef-public-domain", "NASA, photograph of Eileen Collins "
                      "(scikit-image data)"),
    "coffee.png": ("image", "poster", "CC0-1.0", "Rachel Michetti, courtesy of Pikolo Espresso Bar (scikit-image "
                   "data)"),
    "chelsea.png": ("image", "poster", "CC0-1.0", "Stefan van der Walt (scikit-image data)"),
    "hubble_deep_field.jpg": ("image", "poster", "LicenseRef-public-domain", "NASA / ESA Hubble (scikit-image "
                              "data)"),
}
"""scikit-image data files taken, with the licence each one's docstring states."""


def _miniworld(tree: Path) -> list[Candidate]:
    out = []
    base = "miniworld/textures"
    for stem, cat in sorted(MINIWORLD_TEXTURES.items()):
        rel = f"{base}/{stem}.png"
        if (tree / rel).is_file():
            out.append(_texture(MINIWORLD, tree, rel, cat, "MIT", MINIWORLD_CREDIT, f"miniworld/{_slug(stem)}"))
    portraits = tree / base / "portraits"
    for p in sorted(portraits.glob("*.png")) if portraits.is_dir() else []:
        painter = re.sub(r"\d+$", "", p.stem).replace("_", " ").title()
        out.append(Candidate(f"miniworld/portrait/{_slug(p.stem)}", "image", "painting",
                             _ref(MINIWORLD, f"{base}/portraits/{p.name}"), "MIT",
                             f"painting by {painter} (public-domain artwork), from {MINIWORLD_CREDIT}",
                             _file_reader(p), name=p.stem))
    return out


def _robosuite(tree: Path) -> list[Candidate]:
    base = "robosuite/models/assets/textures"
    credit = "robosuite (Stanford Vision and Learning Lab, UT Robot Perception and Learning Lab)"
    return [_texture(ROBOSUITE, tree, f"{base}/{stem}.png", cat, "MIT", credit, f"robosuite/{_slug(stem)}")
            for stem, cat in sorted(ROBOSUITE_TEXTURES.items()) if (tree / base / f"{stem}.png").is_file()]


def _skimage(tree: Path) -> list[Candidate]:
    out = []
    for name, (kind, cat, licence, credit) in sorted(SKIMAGE_FILES.items()):
        rel = f"skimage/data/{name}"
        if not (tree / rel).is_file():
            continue
        asset_id = f"skimage/{_slug(Path(name).stem)}"
        if kind == "texture":
            out.append(_texture(SKIMAGE, tree, rel, cat, licence, credit, asset_id))
        else:
            out.append(Candidate(asset_id, kind, cat, _ref(SKIMAGE, rel), licence, credit, _file_reader(tree / rel),
                                 name=Path(name).stem))
    return out


# ---------------------------------------------------------------------------------------------------- Debian
def _debian_copyright(tree: Path, pkg: Package) -> list:
    path = tree / "usr/share/doc" / pkg.name / "copyright"
    try:
        return parse_debian_copyright(path.read_text(encoding="utf-8", errors="replace"))
    except OSError as e:
        raise AssetPackError(f"{path}: cannot read the package's copyright file ({e.strerror or e})") from None


UFOAI_RULES = (
    (r"tex_buildings/carpet\d+", "carpet"), (r"tex_mattn/carpet\d+", "carpet"),
    (r"tex_material/s?wood\d+", "wood"), (r"tex_ctp1/woodb?_[a-z]*_?\d+", "wood"), (r"tex_mattn/wood\d+", "wood"),
    (r"tex_buildings/floor_wood01", "wood"), (r"tex_misc/laminate001", "wood"),
    (r"tex_material/metall?\d+a?", "metal"), (r"tex_ctp1/metal_[a-z]_\d+", "metal"),
    (r"tex_ctp1/bricks_[a-z]_\d+", "brick"), (r"tex_mattn/wall_bricks\d+", "brick"),
    (r"tex_buildings/wall_brick01", "brick"),
    (r"tex_buildings/tile\d+", "tile"), (r"tex_ctp1/tiles_[a-z]_\d+", "tile"),
    (r"tex_buildings/wallpaper\d+", "wallpaper"), (r"tex_ctp1/wallpaper_[a-z]+_\d+", "wallpaper"),
    (r"tex_furniture/textil\d+", "fabric"), (r"tex_furniture/couch_[a-z]", "fabric"),
    (r"tex_furniture/seat\d+", "fabric"),
    (r"tex_buildings/concrete\d+", "concrete"), (r"tex_ctp1/concrete_[a-z]_\d+", "concrete"),
    (r"tex_trak/trak4_plaster[\w-]*", "plaster"), (r"tex_ctp1/marble_m_1", "marble"),
    (r"tex_mattn/stone00\d", "stone"),
)
"""UFO:AI texture paths (under ``textures/``, no suffix) -> material."""

UFOAI_EXCLUDE = frozenset()
"""UFO:AI textures the rules match but that are not usable materials (seen on the contact sheet)."""

UFOAI_PICTURES = (r"tex_pics/(art|landsc|asia|dragon)[\w-]*", "painting")
"""UFO:AI pictures taken as paintings."""


def _ufoai(tree: Path) -> list[Candidate]:
    pk3_rel = "usr/share/games/ufoai/base/0textures.pk3"
    paras = _debian_copyright(tree, UFOAI)
    pk3 = tree / pk3_rel
    if not pk3.is_file():
        return []
    with zipfile.ZipFile(pk3) as zf:
        names = sorted(n for n in zf.namelist() if not n.endswith("/"))
    stems = {posixpath.splitext(n)[0]: n for n in names}
    out = []
    for stem, member in sorted(stems.items()):
        key = stem.removeprefix("textures/")
        if re.search(r"_(nm|sm|gm|rm|hm)$", key):
            continue  # a normal, specular or glow map of another texture
        cat = next((c for pat, c in UFOAI_RULES if re.fullmatch(pat, key)), None)
        if cat is None and re.fullmatch(UFOAI_PICTURES[0], key):
            cat = UFOAI_PICTURES[1]
        if cat is None or key in UFOAI_EXCLUDE:
            continue
        para = lookup_copyright(paras, f"base/{member}")
        licence, credit = spdx(para.licence), para.copyright or "The UFO:AI Team"
        normal = stems.get(f"{stem}_nm")

        def read(member: str = member, normal: str | None = normal, picture: bool = cat == "painting") -> Any:
            with zipfile.ZipFile(pk3) as z:
                return z.read(member) if picture else (z.read(member), z.read(normal) if normal else None)

        ref = _ref(UFOAI, f"{pk3_rel}:{member}")
        asset_id = f"ufoai/{_slug(key.removeprefix('tex_'))}"
        if cat == "painting":
            out.append(Candidate(asset_id, "image", cat, ref, licence, credit, read, name=Path(key).name))
        else:
            out.append(Candidate(asset_id, "texture", cat, ref, licence, credit, read, name=Path(key).name,
                                 note="size: the material's typical tile (an estimate)",
                                 size_m=(TEXTURE_SIZE_M[cat],), info={"normal": "source" if normal else "derived"}))
    return out


MATE_IMAGES = {"nature/Dune.jpg": "outdoor", "nature/Storm.jpg": "outdoor", "nature/GreenMeadow.jpg": "poster",
               "nature/FreshFlower.jpg": "poster", "nature/LadyBird.jpg": "poster", "nature/RainDrops.jpg": "poster",
               "nature/YellowFlower.jpg": "poster", "nature/TwoWings.jpg": "poster", "nature/Aqua.jpg": "poster",
               "nature/Garden.jpg": "poster", "nature/Blinds.jpg": "poster"}
"""MATE backgrounds taken (path under ``usr/share/backgrounds/mate/``) -> image use."""

PLASMA_IMAGES = {"BytheWater": "outdoor", "ColdRipple": "outdoor", "DarkestHour": "outdoor",
                 "EveningGlow": "outdoor", "Kite": "outdoor", "Path": "outdoor", "summer_1am": "outdoor",
                 "Autumn": "painting", "FallenLeaf": "poster", "OneStandsOut": "poster", "PastelHills": "poster",
                 "Grey": "poster"}
"""Plasma wallpapers taken -> image use."""


def _mate(tree: Path) -> list[Candidate]:
    paras = _debian_copyright(tree, MATE)
    out = []
    for rel, cat in sorted(MATE_IMAGES.items()):
        path = tree / "usr/share/backgrounds/mate" / rel
        if not path.is_file():
            continue
        para = lookup_copyright(paras, rel)
        out.append(Candidate(f"mate/{_slug(Path(rel).stem)}", "image", cat,
                             _ref(MATE, str(path.relative_to(tree))), spdx(para.licence), para.copyright,
                             _file_reader(path), name=Path(rel).stem))
    return out


def _plasma(tree: Path) -> list[Candidate]:
    out = []
    for name, cat in sorted(PLASMA_IMAGES.items()):
        folder = tree / "usr/share/wallpapers" / name
        meta_path = folder / "metadata.json"
        if not meta_path.is_file():
            continue
        meta = json.loads(meta_path.read_text(encoding="utf-8"))["KPlugin"]
        images = sorted((folder / "contents/images").glob("1920x1080.*")) or sorted(
            (folder / "contents/images").iterdir())
        authors = ", ".join(a.get("Name", "") for a in meta.get("Authors", []))
        out.append(Candidate(f"plasma/{_slug(name)}", "image", cat, _ref(PLASMA, str(images[0].relative_to(tree))),
                             spdx(meta["License"]), f"{authors} (KDE Plasma wallpaper '{meta.get('Name', name)}')",
                             _file_reader(images[0]), name=name,
                             note="licence from the wallpaper's metadata.json (the package's copyright file says "
                             "GPL-2+ for all)"))
    return out


CGAL_STATUES = {"nefertiti": "statue", "lion": "statue", "lion-head": "statue", "man": "statue",
                "mannequin-devil": "statue", "head": "statue", "bull": "animal", "elk": "animal", "bear": "animal",
                "triceratops": "animal", "dino": "animal", "cow": "animal", "pig": "animal"}
"""CGAL data meshes taken as sculptures (stem -> category)."""

CGAL_REJECTED = ("armadillo", "bunny00", "ChineseDragon-10kv", "elephant", "camel", "homer", "kitten")
"""Scans left out: research-only or non-free origins (Stanford, deformation-transfer data, a cartoon character)."""

CGAL_HEIGHT_M = {"nefertiti": 0.5, "lion": 1.0, "lion-head": 0.6, "man": 1.75, "mannequin-devil": 0.5,
                 "head": 0.45, "bull": 0.8, "elk": 0.9, "bear": 0.8, "triceratops": 0.5, "dino": 0.5, "cow": 0.6,
                 "pig": 0.4}
"""Height given to each statue (metres): the scans have no unit."""

CGAL_UP = {"man": "z", "mannequin-devil": "z"}
"""Each scan's up axis where it is not ``y`` (seen on renders of the scan turned by each candidate axis: with
``y`` the man and the devil's head lay on their backs, with ``z`` the Nefertiti face lay face up)."""


def _cgal(tree: Path, doc_tree: Path) -> list[Candidate]:
    from .furniture import FACE_BUDGET
    from .meshes import decimate, read_off_statue

    paras_text = (doc_tree / "usr/share/doc/libcgal-dev/copyright")
    if not paras_text.is_file():
        raise AssetPackError(f"{paras_text}: missing (libcgal-dev's copyright file states the data's licence)")
    if "licensed under the Creative Commons CC0 1.0 license" not in " ".join(paras_text.read_text().split()):
        raise AssetPackError(f"{paras_text}: no longer states CC0 for files without a notice; review the statues")
    archive = tree / "usr/share/doc/libcgal-dev/data.tar.gz"
    if not archive.is_file():
        return []
    out = []
    with tarfile.open(archive) as tf:
        members = {Path(m.name).stem: m.name for m in tf.getmembers() if m.name.startswith("data/meshes/")
                   and m.name.endswith(".off")}
    for stem, cat in sorted(CGAL_STATUES.items()):
        if stem not in members:
            continue
        member = members[stem]

        def read(member: str = member, stem: str = stem) -> Any:
            with tarfile.open(archive) as t:
                data = t.extractfile(member).read()
            raw = read_off_statue(io.BytesIO(data), CGAL_HEIGHT_M[stem], CGAL_UP.get(stem, "y"),
                                  f"{archive}:{member}")
            return decimate(raw, FACE_BUDGET["sculpture"])

        out.append(Candidate(f"cgal/{_slug(stem)}", "mesh", cat,
                             _ref(CGAL_DATA, f"usr/share/doc/libcgal-dev/data.tar.gz:{member}"), "CC0-1.0",
                             "CGAL project (data of libcgal-demo)", read, label="sculpture", name=stem,
                             setup_only=True,
                             note="CC0 by libcgal-dev's copyright (files without a notice); the scan's origin is not "
                             "named, so kept set-up only; height chosen (no unit in the scan)"))
    return out


def _sh3d(tree: Path) -> list[Candidate]:
    from .furniture import sh3d_candidates

    paras = _debian_copyright(tree, SH3D)
    return sh3d_candidates(tree, SH3D, paras)


def collect(cache: Path, packages: tuple[Package, ...] = PACKAGES) -> list[Candidate]:
    """Every candidate asset of the unpacked ``packages`` under ``cache``, sorted by id.

    Packages whose tree is absent are skipped (:func:`fruxel.train.sim.assetpack.fetch.fetch_all` fetches them
    first; the tests build from a small tree that holds a few).

    Raises:
        AssetPackError: a package's licence statement is missing or changed, or two candidates share an id.
    """
    readers: dict[Package, Callable[[Path], list[Candidate]]] = {
        SH3D: _sh3d, CGAL_DATA: lambda t: _cgal(t, cache / CGAL_DOC.folder), UFOAI: _ufoai, MATE: _mate,
        PLASMA: _plasma, MINIWORLD: _miniworld, ROBOSUITE: _robosuite, SKIMAGE: _skimage,
    }
    out: list[Candidate] = []
    for pkg in packages:
        tree = cache / pkg.folder
        if pkg in readers and tree.is_dir():
            out.extend(readers[pkg](tree))
    ids: dict[str, Candidate] = {}
    for c in out:
        if c.id in ids:
            raise AssetPackError(f"two assets get the id {c.id!r}: {ids[c.id].source.path} and {c.source.path}")
        ids[c.id] = c
    return sorted(out, key=lambda c: c.id)

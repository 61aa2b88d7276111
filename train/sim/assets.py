"""Optional real assets for the room generator: a folder of meshes per class, and Sweet Home 3D libraries.

Assets are never required; :func:`fruxel.train.sim.scene.make_scene` draws procedural objects when there are
none. Every asset is stored in one canonical frame: **z up, metres, the footprint's bounding box centred on the
origin, standing on z = 0, front towards -y** (its back goes against a wall). Doors and windows are later
stretched to fill their opening (x along the wall, y through it, z up).

Folder layout (:func:`load_asset_folder`)::

    root/
      furniture/   *.obj *.off *.ply *.glb *.gltf *.stl
      sculpture/   ...
      door/        ...
      window/      ...

(plural folder names are accepted too). Files are read with trimesh; a file that holds a scene is flattened
into one mesh with its node transforms applied. Meshes are taken to be in metres with z up unless told
otherwise (``up="y"`` for the common OBJ convention).

Sweet Home 3D (:func:`load_sh3f`): a ``.sh3f`` file is a zip of models plus ``PluginFurnitureCatalog.properties``,
a Java properties file with indexed keys ``id#N``, ``name#N``, ``category#N``, ``model#N`` (the model's path in
the zip), ``width#N`` / ``depth#N`` / ``height#N`` (centimetres), ``doorOrWindow#N`` and ``modelRotation#N``
(nine numbers, a row-major 3x3 matrix applied to the model first). Sweet Home 3D models are y up with their
front towards +z; after the rotation the model is scaled to width x height x depth along its x, y, z axes and
turned into the canonical frame by ``(x, y, z) -> (x, -z, y)``. Doors and windows go to the ``window`` class when
their name says window, hatch or skylight, else to ``door``; everything else is furniture, except names or
categories that say statue, sculpture or bust. :func:`read_sh3f_catalog` and :func:`sh3d_to_canonical` are the
two halves of that import, shared with the asset pack's builder (:mod:`fruxel.train.sim.assetpack`), which reads
the models with their material groups.
"""

from __future__ import annotations

import io
import posixpath
import re
import zipfile
from collections.abc import Iterable
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np

from fruxel.errors import FruxelError

if TYPE_CHECKING:
    import trimesh

KINDS = ("furniture", "sculpture", "door", "window")
"""Asset classes, named after the class table's names."""

MESH_SUFFIXES = (".obj", ".off", ".ply", ".glb", ".gltf", ".stl")
"""File types read from an asset folder."""

MAX_ARCHIVE_BYTES = 512 * 2**20
"""Largest total uncompressed size of a ``.sh3f`` archive read; larger ones are refused (zip bombs)."""

CATALOG_NAME = "PluginFurnitureCatalog.properties"
"""The catalog's file name inside a ``.sh3f`` zip."""


class AssetError(FruxelError, ValueError):
    """Raised for an unreadable asset folder, mesh file or furniture library; the message names the file."""


@dataclass(frozen=True, eq=False)
class Asset:
    """One mesh of the library, in the canonical frame (see the module docstring)."""

    name: str
    """Display name (the file stem, or the catalog's ``name#N``), made safe for object names."""
    kind: str
    """One of :data:`KINDS`."""
    mesh: trimesh.Trimesh
    """Triangle mesh, canonical frame, metres."""
    category: str = ""
    """The catalog category (Sweet Home 3D) or the folder name."""
    source: str = ""
    """Where it came from: a file path, or ``library.sh3f:model/path.obj``."""


@dataclass(frozen=True, eq=False)
class AssetLibrary:
    """An immutable collection of assets, loaded once and handed to ``RoomConfig.assets``."""

    assets: tuple[Asset, ...]
    """All assets, in load order (the order make_scene indexes them in)."""

    def of_kind(self, kind: str) -> tuple[Asset, ...]:
        """The assets of one class, in load order."""
        return tuple(a for a in self.assets if a.kind == kind)

    def merged(self, other: AssetLibrary) -> AssetLibrary:
        """This library's assets followed by ``other``'s."""
        return AssetLibrary(self.assets + other.assets)

    def __len__(self) -> int:
        return len(self.assets)


def _safe_name(text: str) -> str:
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", text).strip("_") or "asset"


def canonical_mesh(vertices: Any, faces: Any) -> trimesh.Trimesh:
    """A mesh moved so that its xy bounding box is centred on the origin and its lowest point is at z = 0.

    Args:
        vertices: ``(V, 3)`` float, already z up and in metres.
        faces: ``(F, 3)`` int.

    Raises:
        AssetError: an empty or non-finite mesh.
    """
    import trimesh

    v = np.asarray(vertices, dtype=np.float64)
    f = np.asarray(faces, dtype=np.int64)
    if v.ndim != 2 or v.shape[1] != 3 or len(v) == 0 or f.ndim != 2 or f.shape[1] != 3 or len(f) == 0:
        raise AssetError(f"mesh is empty or malformed: vertices {v.shape}, faces {f.shape}")
    if not np.all(np.isfinite(v)):
        raise AssetError("mesh has NaN or infinite vertices")
    lo, hi = v.min(axis=0), v.max(axis=0)
    shift = np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])
    return trimesh.Trimesh(vertices=v - shift, faces=f, process=False)


def _load_mesh(source: Any, file_type: str | None = None, resolver: Any = None, label: str = "") -> Any:
    """Read a mesh file (or file object) with trimesh, flattening scenes into one mesh."""
    import trimesh

    try:
        loaded = trimesh.load(source, file_type=file_type, force="mesh", resolver=resolver, process=False)
    except Exception as e:  # noqa: BLE001 - trimesh raises many kinds of errors for bad files
        raise AssetError(f"{label}: cannot read mesh ({type(e).__name__}: {e})") from None
    if not isinstance(loaded, trimesh.Trimesh) or len(loaded.faces) == 0:
        raise AssetError(f"{label}: no triangles found")
    return loaded


_Y_UP_TO_Z_UP = np.array([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])
"""Maps a y-up frame with the front towards +z onto z up with the front towards -y: (x, y, z) -> (x, -z, y)."""


def load_asset_folder(root: str | Path, *, up: str = "z", scale: float = 1.0) -> AssetLibrary:
    """Load every mesh of ``root/<class>/`` (see the module docstring).

    Args:
        root: the folder.
        up: the files' up axis, ``"z"`` or ``"y"`` (y up with the front towards +z).
        scale: factor to metres (0.01 for centimetres).

    Raises:
        AssetError: a missing folder, an unknown ``up``, or an unreadable mesh file.
    """
    base = Path(root)
    if not base.is_dir():
        raise AssetError(f"{base}: asset folder not found")
    if up not in ("z", "y"):
        raise AssetError(f"up must be 'z' or 'y', got {up!r}")
    out = []
    for kind in KINDS:
        for folder in (base / kind, base / f"{kind}s"):
            if not folder.is_dir():
                continue
            for path in sorted(folder.iterdir()):
                if path.suffix.lower() not in MESH_SUFFIXES:
                    continue
                m = _load_mesh(str(path), label=str(path))
                v = np.asarray(m.vertices, dtype=np.float64) * scale
                if up == "y":
                    v = v @ _Y_UP_TO_Z_UP.T
                out.append(Asset(_safe_name(path.stem), kind, canonical_mesh(v, m.faces), folder.name, str(path)))
    return AssetLibrary(tuple(out))


def parse_properties(text: str) -> dict[str, str]:
    """Parse a Java ``.properties`` file: ``key=value``, ``key: value`` or ``key value`` lines, ``#`` and ``!``
    comments, backslash line continuations, and the escapes ``\\t \\n \\r \\f \\uXXXX`` and ``\\<char>``.

    Returns:
        Keys to values, later duplicates winning.
    """
    lines = text.splitlines()
    out: dict[str, str] = {}
    i = 0
    while i < len(lines):
        line = lines[i].lstrip()
        i += 1
        if not line or line[0] in "#!":
            continue
        while _ends_with_continuation(line) and i < len(lines):
            line = line[:-1] + lines[i].lstrip()
            i += 1
        if _ends_with_continuation(line):
            line = line[:-1]
        key, value = _split_property(line)
        out[_unescape(key)] = _unescape(value)
    return out


def _ends_with_continuation(line: str) -> bool:
    n = len(line) - len(line.rstrip("\\"))
    return n % 2 == 1


def _split_property(line: str) -> tuple[str, str]:
    j = 0
    while j < len(line):
        c = line[j]
        if c == "\\":
            j += 2
            continue
        if c in "=: \t\f":
            break
        j += 1
    key = line[:j]
    rest = line[j:].lstrip(" \t\f")
    if rest[:1] in ("=", ":"):
        rest = rest[1:].lstrip(" \t\f")
    return key, rest


_ESCAPES = {"t": "\t", "n": "\n", "r": "\r", "f": "\f"}


def _unescape(s: str) -> str:
    out = []
    j = 0
    while j < len(s):
        c = s[j]
        if c != "\\" or j + 1 >= len(s):
            out.append(c)
            j += 1
            continue
        n = s[j + 1]
        if n == "u" and re.fullmatch(r"[0-9A-Fa-f]{4}", s[j + 2:j + 6] or ""):
            out.append(chr(int(s[j + 2:j + 6], 16)))
            j += 6
        else:
            out.append(_ESCAPES.get(n, n))
            j += 2
    return "".join(out)


def _classify(name: str, category: str, door_or_window: bool) -> str:
    text = f"{name} {category}".lower()
    if door_or_window:
        # By name only: Sweet Home 3D's stock category is "Doors and windows" for both.
        return "window" if any(w in name.lower() for w in ("window", "hatch", "skylight")) else "door"
    if any(w in text for w in ("statue", "sculpture", "bust")):
        return "sculpture"
    return "furniture"


def _number(props: dict[str, str], key: str, label: str) -> float | None:
    if key not in props:
        return None
    try:
        return float(props[key])
    except ValueError:
        raise AssetError(f"{label}: {key} is not a number: {props[key]!r}") from None


class _ZipResolver:
    """Resolves the files an OBJ names (its MTL, textures) relative to its folder inside the zip."""

    def __init__(self, zf: zipfile.ZipFile, folder: str) -> None:
        self.zf = zf
        self.folder = folder

    def get(self, name: str) -> bytes:
        path = posixpath.normpath(posixpath.join(self.folder, name.replace("\\", "/")))
        try:
            return self.zf.read(path)
        except KeyError:
            raise FileNotFoundError(name) from None

    def keys(self) -> Iterable[str]:
        return self.zf.namelist()

    def write(self, name: str, data: Any) -> None:
        raise OSError("read-only archive")


@dataclass(frozen=True)
class CatalogItem:
    """One entry ``#N`` of a Sweet Home 3D catalog (``PluginFurnitureCatalog.properties``)."""

    index: int
    """The entry's number ``N``."""
    name: str
    """``name#N`` (the model file's stem when missing)."""
    category: str
    """``category#N`` (may be empty)."""
    member: str
    """The model's path inside the zip, normalised (checked to be in the archive)."""
    kind: str
    """One of :data:`KINDS`, from the name, category and ``doorOrWindow#N``."""
    rotation: np.ndarray | None
    """``modelRotation#N``: ``(3, 3)`` float64, row-major, applied to the model's vertices first; None if absent."""
    size_cm: np.ndarray
    """``(3,)`` float64: ``width#N``, ``height#N``, ``depth#N`` in centimetres (NaN where missing or not positive),
    along the model's x, y, z after the rotation."""
    props: dict[str, str]
    """Every ``key#N`` of this entry, without the ``#N`` (e.g. ``creator``, ``elevation``)."""


def read_sh3f_catalog(zf: zipfile.ZipFile, label: str) -> list[CatalogItem]:
    """The entries of an open ``.sh3f`` archive's catalog, in index order.

    Args:
        zf: the open archive.
        label: what error messages call the archive (its path).

    Raises:
        AssetError: an archive larger than :data:`MAX_ARCHIVE_BYTES`, no catalog, an entry without a model, a model
            path missing from the zip or leaving it, an unsupported model type, or a malformed number or rotation;
            the message names the entry.
    """
    if sum(i.file_size for i in zf.infolist()) > MAX_ARCHIVE_BYTES:
        raise AssetError(f"{label}: archive unpacks to more than {MAX_ARCHIVE_BYTES} bytes")
    names = zf.namelist()
    catalog = next((n for n in names if posixpath.basename(n) == CATALOG_NAME), None)
    if catalog is None:
        raise AssetError(f"{label}: no {CATALOG_NAME} in the archive")
    props = parse_properties(zf.read(catalog).decode("utf-8", errors="replace"))
    indices = sorted({int(m.group(1)) for k in props if (m := re.fullmatch(r"(?:id|model)#(\d+)", k))})
    members = set(names)
    out = []
    for n in indices:
        item_label = f"{label}: item #{n}"
        model = props.get(f"model#{n}")
        if not model:
            raise AssetError(f"{item_label}: no model#{n}")
        member = posixpath.normpath(model.replace("\\", "/").lstrip("/"))
        if member.startswith("..") or member not in members:
            raise AssetError(f"{item_label}: model {model!r} is not in the archive")
        if posixpath.splitext(member)[1].lower() not in MESH_SUFFIXES:
            raise AssetError(f"{item_label}: model {model!r} has an unsupported type")
        rot = None
        if props.get(f"modelRotation#{n}"):
            text = props[f"modelRotation#{n}"]
            try:
                rot = np.array([float(x) for x in text.split()], dtype=np.float64).reshape(3, 3)
            except ValueError:
                raise AssetError(f"{item_label}: modelRotation#{n} is not nine numbers: {text!r}") from None
        size = np.array([_number(props, f"{k}#{n}", item_label) or np.nan for k in ("width", "height", "depth")])
        size[~(size > 0)] = np.nan
        name = props.get(f"name#{n}", posixpath.splitext(posixpath.basename(member))[0])
        category = props.get(f"category#{n}", "")
        dw = props.get(f"doorOrWindow#{n}", "false").strip().lower() == "true"
        own = {k[: -len(f"#{n}")]: v for k, v in props.items() if k.endswith(f"#{n}")}
        out.append(CatalogItem(n, name, category, member, _classify(name, category, dw), rot, size, own))
    return out


def sh3d_to_canonical(vertices: Any, item: CatalogItem) -> np.ndarray:
    """A Sweet Home 3D model's vertices in the canonical frame (see the module docstring): rotated by the item's
    ``modelRotation``, scaled to its catalog size, turned z up with the front towards -y, then footprint-centred
    and standing on z = 0 (:func:`canonical_mesh`'s shift).

    Args:
        vertices: ``(V, 3)`` float, the model file's vertices (Sweet Home 3D frame: y up, front towards +z).
        item: the model's catalog entry.

    Returns:
        ``(V, 3)`` float64, metres, canonical frame.
    """
    v = np.asarray(vertices, dtype=np.float64)
    if item.rotation is not None:
        v = v @ item.rotation.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    ext = np.maximum(hi - lo, 1e-12)
    # Missing sizes keep the model's own extent, taken to be in centimetres like the catalog's.
    target = np.where(np.isfinite(item.size_cm), item.size_cm, ext) / 100.0
    v = ((v - lo) / ext * target) @ _Y_UP_TO_Z_UP.T
    lo, hi = v.min(axis=0), v.max(axis=0)
    return v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]])


def load_sh3f(path: str | Path) -> AssetLibrary:
    """Import a Sweet Home 3D furniture library (see the module docstring).

    Raises:
        AssetError: not a zip, no catalog, an archive larger than :data:`MAX_ARCHIVE_BYTES`, a model path
            missing from the zip or leaving it, or an unreadable model; the message names the entry.
    """
    src = Path(path)
    try:
        zf = zipfile.ZipFile(src)
    except (OSError, zipfile.BadZipFile) as e:
        raise AssetError(f"{src}: not a readable .sh3f (zip) file: {e}") from None
    with zf:
        out = []
        for item in read_sh3f_catalog(zf, str(src)):
            label = f"{src}: item #{item.index} {item.member}"
            suffix = posixpath.splitext(item.member)[1].lower().lstrip(".")
            resolver = _ZipResolver(zf, posixpath.dirname(item.member))
            m = _load_mesh(io.BytesIO(zf.read(item.member)), file_type=suffix, resolver=resolver, label=label)
            v = sh3d_to_canonical(m.vertices, item)
            out.append(Asset(_safe_name(item.name), item.kind, canonical_mesh(v, m.faces), item.category,
                             f"{src}:{item.member}"))
    return AssetLibrary(tuple(out))

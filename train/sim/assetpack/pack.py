"""Reading an asset pack: :class:`AssetPack` checks a pack folder and answers queries with typed records.

A pack folder (built by :func:`fruxel.train.sim.assetpack.build.build_pack`)::

    pack/
      manifest.json                 # every asset: files, split, source, licence (manifest.py)
      builder.txt                   # the digest of the code that built it (manifest.builder_digest); a pack
                                    # of other code is refused: it may hold other bytes for the same sources
      textures/ID.jpg               # albedo, sRGB, RGB JPEG
      textures/ID.normal.jpg        # tangent-space normal map, RGB JPEG (see Texture.normal)
      meshes/ID.npz                 # vertices, faces, parts (see Mesh), written without pickle
      images/ID.jpg                 # outdoor views and pictures, sRGB, RGB JPEG

Mesh file (``.npz``, every member a plain npy array; read strictly, never with pickle):

- ``vertices``: ``(V, 3)`` ``<f4``, metres, the canonical frame of :mod:`fruxel.train.sim.assets`: z up, the
  footprint's bounding box centred on the origin, standing on z = 0, front towards -y;
- ``faces``: ``(F, 3)`` ``<i4``, vertex indices, counter-clockwise seen from outside where the source was;
- ``face_parts``: ``(F,)`` ``<u2``, each face's part (the source's material group);
- ``part_names``: ``(P,)`` ``<U`` unicode, the material names;
- ``part_colors``: ``(P, 4)`` ``|u1``, each part's sRGB colour and opacity (the material's diffuse colour, or its
  texture's mean colour; alpha 255 = opaque).

Usage::

    pack = AssetPack("assets/pack")                       # checks the builder, the manifest, every file's SHA-256
    for tex in pack.textures(category="brick", split="train"):
        tex.albedo, tex.normal, tex.size_m                # (H, W, 3) uint8, (H, W, 3) float32, (2,) metres
    beds = pack.meshes(category="bed", split="test")      # Mesh records
    views = pack.images(category="outdoor")
    pack.categories("mesh")                               # {"bed": 12, ...}
"""

from __future__ import annotations

import io
import os
import zipfile
from collections import Counter
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from fruxel.io import ArchiveError, describe_read_error, file_sha256, open_archive, open_npy_member

from .manifest import (
    BUILDER_NAME,
    FOLDERS,
    KINDS,
    MANIFEST_NAME,
    SPLITS,
    AssetPackError,
    Entry,
    builder_digest,
    parse_manifest,
)

if TYPE_CHECKING:
    import trimesh

MESH_MEMBERS = ("vertices", "faces", "face_parts", "part_names", "part_colors")
"""The npy members of a mesh file."""
MAX_MESH_FACES = 1 << 22
"""Largest face or vertex count a mesh file may announce (read strictly: a bigger header is refused unread)."""
MAX_IMAGE_PIXELS = 1 << 24
"""Largest image accepted (width x height)."""


@dataclass(frozen=True, eq=False)
class Texture:
    """A tileable material texture."""

    entry: Entry
    """Its manifest entry (id, category, split, licence, ...)."""
    albedo: np.ndarray
    """``(H, W, 3)`` uint8, sRGB base colour; row 0 is the tile's top (+v), column 0 its left (-u)."""
    normal: np.ndarray
    """``(H, W, 3)`` float32 unit vectors, tangent space of the tile: x along the image's columns (right), y up the
    image (towards row 0), z out of the surface (stored as RGB ``(n + 1) / 2``, OpenGL convention)."""

    @property
    def size_m(self) -> np.ndarray:
        """``(2,)`` float64: metres covered by one tile along its width and its height."""
        return np.asarray(self.entry.size_m, dtype=np.float64)


@dataclass(frozen=True, eq=False)
class Mesh:
    """A furniture, door, window or statue mesh in the canonical frame (see the module docstring)."""

    entry: Entry
    """Its manifest entry; ``entry.label`` is the class it is drawn as."""
    vertices: np.ndarray
    """``(V, 3)`` float32, metres: z up, footprint centred on the origin, standing on z = 0, front towards -y."""
    faces: np.ndarray
    """``(F, 3)`` int32 vertex indices."""
    face_parts: np.ndarray
    """``(F,)`` int32: each face's part, an index into :attr:`part_names` and :attr:`part_colors`."""
    part_names: tuple[str, ...]
    """``P`` material names from the source."""
    part_colors: np.ndarray
    """``(P, 4)`` uint8: sRGB colour and opacity of each part."""

    @property
    def size_m(self) -> np.ndarray:
        """``(3,)`` float64: the extent along x, y, z in metres (the real-world size)."""
        return np.asarray(self.entry.size_m, dtype=np.float64)

    def to_trimesh(self) -> trimesh.Trimesh:
        """The mesh as a ``trimesh.Trimesh`` with per-face colours from the parts (not processed or merged)."""
        import trimesh

        return trimesh.Trimesh(vertices=self.vertices, faces=self.faces,
                               face_colors=self.part_colors[self.face_parts], process=False)


@dataclass(frozen=True, eq=False)
class Image:
    """An image: an outdoor view for behind windows, or a painting or poster."""

    entry: Entry
    """Its manifest entry (category ``outdoor``, ``painting`` or ``poster``)."""
    pixels: np.ndarray
    """``(H, W, 3)`` uint8, sRGB; row 0 is the top."""


class AssetPack:
    """A checked asset pack folder (layout in the module docstring).

    Opening reads ``manifest.json`` and checks it (schema, allowed licences, unique ids and files), then checks
    that every file it lists exists with its size and SHA-256, and that the folder holds no file the manifest
    does not list. Asset files are decoded when queried.

    Args:
        root: the pack folder.
        verify: check every file's SHA-256 on opening (a fraction of a second for a full pack); sizes and presence
            are always checked.

    Raises:
        AssetPackError: a missing folder or manifest, a malformed manifest, a missing, changed or unlisted file;
            one line naming the file.
    """

    def __init__(self, root: str | os.PathLike[str], *, verify: bool = True) -> None:
        self.root = Path(root)
        """The pack folder."""
        manifest = self.root / MANIFEST_NAME
        if not self.root.is_dir():
            raise AssetPackError(f"{self.root}: asset pack folder not found")
        try:
            data = manifest.read_bytes()
        except OSError as e:
            raise AssetPackError(f"{manifest}: cannot read the manifest ({e.strerror or e})") from None
        self.entries: tuple[Entry, ...] = tuple(parse_manifest(data, str(manifest)))
        """Every asset, in manifest (id) order."""
        self._by_id = {e.id: e for e in self.entries}
        self._check_builder()
        self._check_files(verify)

    def _check_builder(self) -> None:
        """Refuse a pack built by other pack-building code than this fruxel's (:func:`.manifest.builder_digest`)."""
        stamp = self.root / BUILDER_NAME
        try:
            theirs = stamp.read_text(encoding="ascii").strip()
        except (OSError, UnicodeDecodeError):
            theirs = None
        ours = builder_digest()
        if theirs != ours:
            what = f"built by pack code {theirs}" if theirs else "built before packs named the code that built them"
            raise AssetPackError(f"{stamp}: {what}, not by this fruxel's ({ours}); its rooms could differ: build it "
                                 "again (make assets, or fruxel-sim assets --replace)")

    def _check_files(self, verify: bool) -> None:
        listed = {p for e in self.entries for p in e.files.values()}
        for folder in FOLDERS.values():
            d = self.root / folder
            if not d.is_dir():
                continue
            for p in sorted(d.iterdir()):
                rel = f"{folder}/{p.name}"
                if rel not in listed:
                    raise AssetPackError(f"{p}: file not listed in {MANIFEST_NAME} (foreign or left over)")
        for p in sorted(self.root.iterdir()):
            if p.name not in (MANIFEST_NAME, BUILDER_NAME) and p.name not in FOLDERS.values():
                raise AssetPackError(f"{p}: unexpected entry in an asset pack folder")
        for e in self.entries:
            total = 0
            for role, rel in e.files.items():
                path = self.root / rel
                if not path.is_file():
                    raise AssetPackError(f"{path}: missing (asset {e.id!r}, {role})")
                total += path.stat().st_size
                if verify and file_sha256(path) != e.sha256[role]:
                    raise AssetPackError(f"{path}: corrupt or changed (SHA-256 differs from {MANIFEST_NAME}, "
                                         f"asset {e.id!r})")
            if total != e.bytes:
                raise AssetPackError(f"{self.root / next(iter(e.files.values()))}: asset {e.id!r} has {total} "
                                     f"bytes of files, {MANIFEST_NAME} says {e.bytes}")

    # ------------------------------------------------------------------------------------------------ queries
    def select(self, kind: str, category: str | None = None, split: str | None = None,
               label: str | None = None) -> tuple[Entry, ...]:
        """The entries of one kind, optionally of one category, split and (meshes) label, in id order.

        Raises:
            AssetPackError: an unknown kind or split.
        """
        if kind not in KINDS:
            raise AssetPackError(f"unknown asset kind {kind!r} (one of {KINDS})")
        if split is not None and split not in SPLITS:
            raise AssetPackError(f"unknown split {split!r} (one of {SPLITS})")
        return tuple(e for e in self.entries if e.kind == kind and (category is None or e.category == category)
                     and (split is None or e.split == split) and (label is None or e.label == label))

    def categories(self, kind: str, split: str | None = None) -> dict[str, int]:
        """Category -> number of assets of ``kind`` (in ``split``, if given), sorted by category."""
        return dict(sorted(Counter(e.category for e in self.select(kind, split=split)).items()))

    def entry(self, asset_id: str) -> Entry:
        """The entry with this id.

        Raises:
            AssetPackError: no such asset.
        """
        try:
            return self._by_id[asset_id]
        except KeyError:
            raise AssetPackError(f"{self.root}: no asset {asset_id!r}") from None

    def textures(self, category: str | None = None, split: str | None = None) -> list[Texture]:
        """The textures of ``category`` in ``split`` (None: all), decoded."""
        return [self.texture(e) for e in self.select("texture", category, split)]

    def meshes(self, category: str | None = None, split: str | None = None,
               label: str | None = None) -> list[Mesh]:
        """The meshes of ``category`` (furniture kind) in ``split``, optionally of one ``label``, decoded."""
        return [self.mesh(e) for e in self.select("mesh", category, split, label)]

    def images(self, category: str | None = None, split: str | None = None) -> list[Image]:
        """The images of ``category`` (``outdoor``, ``painting``, ``poster``) in ``split``, decoded."""
        return [self.image(e) for e in self.select("image", category, split)]

    # ------------------------------------------------------------------------------------------------ loading
    def _of(self, item: Entry | str, kind: str) -> Entry:
        e = self.entry(item) if isinstance(item, str) else item
        if e.kind != kind:
            raise AssetPackError(f"{self.root}: asset {e.id!r} is a {e.kind}, not a {kind}")
        return e

    def texture(self, item: Entry | str) -> Texture:
        """One texture, by entry or id.

        Raises:
            AssetPackError: not a texture, or a file that does not decode (naming it).
        """
        e = self._of(item, "texture")
        albedo = read_rgb(self.root / e.files["albedo"])
        rgb = read_rgb(self.root / e.files["normal"])
        if rgb.shape != albedo.shape:
            raise AssetPackError(f"{self.root / e.files['normal']}: normal map is {rgb.shape[1]}x{rgb.shape[0]}, "
                                 f"its albedo {albedo.shape[1]}x{albedo.shape[0]}")
        n = rgb.astype(np.float32) / 127.5 - 1.0
        n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-6)
        return Texture(e, albedo, n)

    def mesh(self, item: Entry | str) -> Mesh:
        """One mesh, by entry or id.

        Raises:
            AssetPackError: not a mesh, or a file that is not a valid mesh file (naming it).
        """
        e = self._of(item, "mesh")
        v, f, parts, names, colors = read_mesh_file(self.root / e.files["mesh"])
        return Mesh(e, v, f, parts, names, colors)

    def image(self, item: Entry | str) -> Image:
        """One image, by entry or id.

        Raises:
            AssetPackError: not an image, or a file that does not decode (naming it).
        """
        e = self._of(item, "image")
        return Image(e, read_rgb(self.root / e.files["image"]))

    def __len__(self) -> int:
        return len(self.entries)

    def __iter__(self) -> Iterator[Entry]:
        return iter(self.entries)


def read_rgb(path: Path) -> np.ndarray:
    """An image file as ``(H, W, 3)`` uint8 RGB.

    Raises:
        AssetPackError: unreadable, not an image, truncated or larger than :data:`MAX_IMAGE_PIXELS`.
    """
    from PIL import Image as PILImage

    try:
        with PILImage.open(path) as im:
            if im.width * im.height > MAX_IMAGE_PIXELS:
                raise AssetPackError(f"{path}: image of {im.width}x{im.height} pixels is too large")
            im.load()
            return np.asarray(im.convert("RGB"), dtype=np.uint8)
    except AssetPackError:
        raise
    except (OSError, ValueError, SyntaxError) as e:
        problem = f"{type(e).__name__}: {e}"
    raise AssetPackError(f"{path}: not a readable image ({problem})")


def _mesh_members(zf: zipfile.ZipFile) -> dict[str, np.ndarray]:
    names = sorted(zf.namelist())
    want = sorted(f"{m}.npy" for m in MESH_MEMBERS)
    if names != want:
        raise ArchiveError(f"members {names}, expected {want}")
    out = {}
    for m in MESH_MEMBERS:
        with open_npy_member(zf, f"{m}.npy") as a:
            if any(s > MAX_MESH_FACES * 4 for s in a.shape) or a.fortran_order:
                raise ArchiveError(f"member {m!r} has shape {a.shape} (too large or Fortran order)")
            out[m] = a.read_array()
    return out


def read_mesh_file(path: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, tuple[str, ...], np.ndarray]:
    """Read and check a mesh file (layout in the module docstring), without pickle.

    Returns:
        ``vertices`` ``(V, 3)`` float32, ``faces`` ``(F, 3)`` int32, ``face_parts`` ``(F,)`` int32, ``part_names``
        (``P`` strings) and ``part_colors`` ``(P, 4)`` uint8.

    Raises:
        AssetPackError: not a mesh file, wrong members, dtypes or shapes, indices out of range, or non-finite
            vertices; naming the file.
    """
    try:
        with open(path, "rb") as fh, open_archive(fh) as zf:
            a = _mesh_members(zf)
    except Exception as e:  # noqa: BLE001 - a damaged archive raises zipfile's, zlib's or struct's errors
        raise AssetPackError(f"{path}: not a valid mesh file ({describe_read_error(e)})") from None
    v, f, fp, names, colors = (a[m] for m in MESH_MEMBERS)
    checks = [
        (v.dtype == np.dtype("<f4") and v.ndim == 2 and v.shape[1] == 3 and len(v) > 0, "vertices must be (V, 3) <f4"),
        (f.dtype == np.dtype("<i4") and f.ndim == 2 and f.shape[1] == 3 and len(f) > 0, "faces must be (F, 3) <i4"),
        (fp.dtype == np.dtype("<u2") and fp.shape == (len(f),), "face_parts must be (F,) <u2"),
        (names.dtype.kind == "U" and names.ndim == 1 and len(names) > 0, "part_names must be (P,) unicode"),
        (colors.dtype == np.uint8 and colors.shape == (len(names), 4), "part_colors must be (P, 4) uint8"),
    ]
    for ok, problem in checks:
        if not ok:
            raise AssetPackError(f"{path}: {problem}")
    if not np.all(np.isfinite(v)):
        raise AssetPackError(f"{path}: vertices hold NaN or infinite values")
    if f.min() < 0 or f.max() >= len(v) or fp.max() >= len(names):
        raise AssetPackError(f"{path}: face or part indices out of range")
    return (np.ascontiguousarray(v), np.ascontiguousarray(f), fp.astype(np.int32),
            tuple(str(x) for x in names), np.ascontiguousarray(colors))


def mesh_file_bytes(vertices: np.ndarray, faces: np.ndarray, face_parts: np.ndarray, part_names: Iterable[str],
                    part_colors: np.ndarray) -> bytes:
    """A mesh file's bytes (layout in the module docstring), deterministic: fixed member order and time stamps.

    Args:
        vertices: ``(V, 3)`` float, metres, canonical frame.
        faces: ``(F, 3)`` int.
        face_parts: ``(F,)`` int, below 65536.
        part_names: ``P`` non-empty strings.
        part_colors: ``(P, 4)`` uint8.
    """
    import numpy.lib.format as npy_format

    part_names = list(part_names)
    arrays = {
        "vertices": np.ascontiguousarray(vertices, dtype="<f4"),
        "faces": np.ascontiguousarray(faces, dtype="<i4"),
        "face_parts": np.ascontiguousarray(face_parts, dtype="<u2"),
        "part_names": np.array(list(part_names), dtype=np.str_).astype(f"<U{max(1, *map(len, part_names))}"),
        "part_colors": np.ascontiguousarray(part_colors, dtype=np.uint8),
    }
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as zf:
        for name in MESH_MEMBERS:
            member = io.BytesIO()
            npy_format.write_array(member, arrays[name], allow_pickle=False)
            info = zipfile.ZipInfo(f"{name}.npy", date_time=(1980, 1, 1, 0, 0, 0))
            info.compress_type = zipfile.ZIP_DEFLATED
            zf.writestr(info, member.getvalue(), compresslevel=9)
    return buf.getvalue()

"""The asset pack's manifest (``manifest.json``): one entry per asset, its files, split, source and licence.

Layout of ``manifest.json`` (format ``fruxel-assetpack``, version 1)::

    {"format": "fruxel-assetpack", "version": 1,
     "licences": {"CC0-1.0": {"url": "...", "committable": true}, ...},     # every licence the entries use
     "assets": [ENTRY, ...]}                                                 # sorted by id

    ENTRY = {
      "id": "sh3d/blendswap-cc-0/armchair",    # unique; lower-case letters, digits, '_', '-', '.', '/'
      "kind": "texture" | "mesh" | "image",
      "category": "armchair",                  # texture: material (brick, wood, ...); mesh: furniture kind (bed,
                                               # chair, door, statue, ...); image: outdoor | painting | poster
      "label": "furniture",                    # meshes: the class it is drawn as (furniture, door, window,
                                               # sculpture, object); "" for textures and images
      "name": "Armchair",                      # display name from the source
      "split": "train" | "test",
      "files": {"albedo": "textures/....jpg", "normal": "textures/....normal.jpg"}   # texture
             | {"mesh": "meshes/....npz"} | {"image": "images/....jpg"},
      "sha256": {ROLE: hex digest of that file},
      "bytes": 12345,                          # the files' total size
      "size_m": [w, h] | [x, y, z] | null,     # texture: metres per tile along its width and height;
                                               # mesh: its extent along x, y, z; image: null
      "source": {"registry": "debian" | "pypi", "package": "...", "version": "...",
                 "path": "path/in/the/package[:member/inside/an/archive]"},
      "licence": "CC-BY-3.0",                  # SPDX id (LicenseRef-public-domain for public-domain works)
      "credit": "...",                         # author / copyright text as the licence asks
      "committable": false,                    # true only for CC0, CC-BY, MIT, BSD, Apache, public domain
      "note": "...",                           # why a permissive asset is set-up only, where the size is from, ...
      "info": {...}                            # kind-specific numbers: mesh {"faces", "vertices", "parts",
                                               # "elevation_m"}, texture {"normal": "source" | "derived"}
    }

The split is by asset id (:func:`assign_splits`): within each (kind, category) the ids are ordered by their
SHA-256 and the first ``round(test_fraction * n)`` (at least one where the group has two or more) are the test
split, so test rooms use textures, meshes and images that training never sees.
"""

from __future__ import annotations

import functools
import hashlib
import json
import re
from collections import defaultdict
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from fruxel.errors import FruxelError

from .licences import ALLOWED, COMMITTABLE

FORMAT_NAME = "fruxel-assetpack"
"""Value of the manifest's ``format``."""
FORMAT_VERSION = 1
"""The manifest version this module writes and reads."""
MANIFEST_NAME = "manifest.json"
"""The manifest's file name in a pack folder."""
BUILDER_NAME = "builder.txt"
"""The file of a pack folder that names the code that built it (:func:`builder_digest`), beside the manifest."""
BUILDER_MODULES = ("build", "fetch", "furniture", "licences", "manifest", "meshes", "sources", "textures")
"""The modules of this package whose code decides a pack's bytes (the reader and the per-machine derived arrays
do not)."""
KINDS = ("texture", "mesh", "image")
"""Asset kinds."""
SPLITS = ("train", "test")
"""Split names."""
ROLES = {"texture": ("albedo", "normal"), "mesh": ("mesh",), "image": ("image",)}
"""The files each kind has, by role."""
FOLDERS = {"texture": "textures", "mesh": "meshes", "image": "images"}
"""The pack sub-folder of each kind's files."""
LABELS = ("furniture", "door", "window", "sculpture", "object")
"""The classes a mesh may be drawn as (names of the simulator's class table)."""
REGISTRIES = ("debian", "pypi", "repository")
"""Where a source package comes from (``repository``: files the fruxel repository itself holds)."""

_ID = re.compile(r"[a-z0-9][a-z0-9_.-]*(/[a-z0-9][a-z0-9_.-]*)*")
_FILE = re.compile(r"[a-z0-9][a-z0-9_.-]*")
_SHA = re.compile(r"[0-9a-f]{64}")


class AssetPackError(FruxelError, ValueError):
    """A pack, manifest or asset file that is missing, malformed, corrupt or not allowed, or a build that cannot
    go on; the message names the file (or the source) and the problem."""


@dataclass(frozen=True)
class SourceRef:
    """Where an asset came from."""

    registry: str
    """One of :data:`REGISTRIES`."""
    package: str
    """The package's name (``sweethome3d-furniture``, ``miniworld``)."""
    version: str
    """The package's version (``1.8-1``, ``2.1.0``)."""
    path: str
    """The file inside the package; ``ARCHIVE:MEMBER`` for a file inside an archive the package holds."""


@dataclass(frozen=True)
class Entry:
    """One asset of the manifest (see the module docstring for each field's meaning)."""

    id: str
    """Unique id, also the split's hash key."""
    kind: str
    """One of :data:`KINDS`."""
    category: str
    """Material, furniture kind or image use."""
    split: str
    """One of :data:`SPLITS`."""
    files: dict[str, str]
    """Role -> path relative to the pack folder."""
    sha256: dict[str, str]
    """Role -> SHA-256 of that file (hex)."""
    bytes: int
    """Total size of the files."""
    size_m: tuple[float, ...] | None
    """Texture: metres per tile (width, height); mesh: extent (x, y, z) in metres; image: None."""
    source: SourceRef
    """Where it came from."""
    licence: str
    """SPDX id, one of :data:`fruxel.train.sim.assetpack.licences.ALLOWED`."""
    credit: str
    """Author / copyright text as the licence asks."""
    committable: bool
    """Whether the asset may be committed and shipped (a :data:`COMMITTABLE` licence and a certain provenance)."""
    label: str = ""
    """Meshes: the class it is drawn as (one of :data:`LABELS`); empty for other kinds."""
    name: str = ""
    """Display name from the source."""
    note: str = ""
    """Free text: why a permissive asset is set-up only, where a size comes from."""
    info: dict[str, Any] = field(default_factory=dict)
    """Kind-specific numbers (mesh: faces, vertices, parts, elevation_m; texture: normal)."""

    def to_dict(self) -> dict[str, Any]:
        """The entry as the manifest writes it."""
        return {
            "id": self.id, "kind": self.kind, "category": self.category, "label": self.label, "name": self.name,
            "split": self.split, "files": dict(sorted(self.files.items())),
            "sha256": dict(sorted(self.sha256.items())), "bytes": self.bytes,
            "size_m": None if self.size_m is None else [round(float(x), 6) for x in self.size_m],
            "source": {"registry": self.source.registry, "package": self.source.package,
                       "version": self.source.version, "path": self.source.path},
            "licence": self.licence, "credit": self.credit, "committable": self.committable, "note": self.note,
            "info": dict(sorted(self.info.items())),
        }


def split_key(asset_id: str) -> bytes:
    """The sort key of an asset id for :func:`assign_splits`: its SHA-256 digest."""
    return hashlib.sha256(asset_id.encode("utf-8")).digest()


def assign_splits(groups: Iterable[tuple[tuple[str, str], str]], test_fraction: float) -> dict[str, str]:
    """Assign each asset to ``train`` or ``test``, deterministically from the ids alone.

    Args:
        groups: ``((kind, category), id)`` pairs.
        test_fraction: share of each group that goes to the test split, in [0, 1).

    Returns:
        Id -> split. Within each group the ids ordered by :func:`split_key` take ``test`` for the first
        ``round(test_fraction * n)``, at least one where the group has two or more assets and the fraction is
        positive; the rest ``train``.
    """
    by_group: dict[tuple[str, str], list[str]] = defaultdict(list)
    for g, i in groups:
        by_group[g].append(i)
    out = {}
    for ids in by_group.values():
        ids = sorted(ids, key=split_key)
        n_test = round(test_fraction * len(ids))
        if test_fraction > 0 and len(ids) >= 2:
            n_test = min(max(n_test, 1), len(ids) - 1)
        for k, i in enumerate(ids):
            out[i] = "test" if k < n_test else "train"
    return out


@functools.cache
def builder_digest() -> str:
    """A digest (16 hex digits) of the pack-building code, :data:`BUILDER_MODULES`' source files.

    A pack holds it in :data:`BUILDER_NAME`, and :class:`~.pack.AssetPack` opens only a pack of the same digest:
    a pack built by other code may hold other bytes for the same sources (a scan turned upright, say), and so draw
    other rooms, other test sets included, while its manifest still checks. Any change to those files asks for the
    pack to be built again (a minute or two), which is the price of never reading a stale one. Read once a process.
    """
    from pathlib import Path

    digest = hashlib.sha256()
    here = Path(__file__).resolve().parent
    for name in BUILDER_MODULES:
        digest.update(f"{name}\0".encode())
        digest.update((here / f"{name}.py").read_bytes())
    return digest.hexdigest()[:16]


def manifest_dict(entries: Iterable[Entry]) -> dict[str, Any]:
    """The manifest object of ``entries`` (sorted by id), with the table of the licences they use."""
    ordered = sorted(entries, key=lambda e: e.id)
    used = sorted({e.licence for e in ordered})
    licences = {k: {"url": ALLOWED[k], "committable": k in COMMITTABLE} for k in used}
    return {"format": FORMAT_NAME, "version": FORMAT_VERSION, "licences": licences,
            "assets": [e.to_dict() for e in ordered]}


def manifest_bytes(entries: Iterable[Entry]) -> bytes:
    """``manifest.json``'s bytes: :func:`manifest_dict` as indented, key-ordered UTF-8 JSON (deterministic)."""
    return (json.dumps(manifest_dict(entries), indent=1, ensure_ascii=False) + "\n").encode("utf-8")


# ---------------------------------------------------------------------------------------------------- reading
def _need(cond: bool, where: str, problem: str) -> None:
    if not cond:
        raise AssetPackError(f"{where}: {problem}")


def _str(d: dict[str, Any], key: str, where: str, *, empty: bool = False) -> str:
    v = d.get(key)
    _need(isinstance(v, str) and (empty or v != ""), where, f"{key!r} must be a{'' if empty else ' non-empty'} "
          f"string, got {v!r}")
    return v


def _size(v: Any, kind: str, where: str) -> tuple[float, ...] | None:
    n = {"texture": 2, "mesh": 3, "image": 0}[kind]
    if n == 0:
        _need(v is None, where, f"size_m of an image must be null, got {v!r}")
        return None
    ok = isinstance(v, list) and len(v) == n and all(isinstance(x, (int, float)) and 0 < x < 1e3 for x in v)
    _need(ok, where, f"size_m must be {n} positive numbers (metres), got {v!r}")
    return tuple(float(x) for x in v)


def _files(d: dict[str, Any], kind: str, asset_id: str, where: str) -> tuple[dict[str, str], dict[str, str]]:
    files, sha = d.get("files"), d.get("sha256")
    roles = ROLES[kind]
    _need(isinstance(files, dict) and sorted(files) == sorted(roles), where,
          f"files must have exactly the roles {list(roles)}, got {files!r}")
    _need(isinstance(sha, dict) and sorted(sha) == sorted(roles), where,
          f"sha256 must have exactly the roles {list(roles)}, got {sha!r}")
    for role in roles:
        path = files[role]
        ok = isinstance(path, str) and path.count("/") == 1 and path.split("/")[0] == FOLDERS[kind] \
            and _FILE.fullmatch(path.split("/")[1]) is not None
        _need(ok, where, f"file {path!r} ({role}) is not a plain file name under {FOLDERS[kind]}/")
        _need(isinstance(sha[role], str) and _SHA.fullmatch(sha[role]) is not None, where,
              f"sha256 of {role} is not 64 hex digits: {sha[role]!r}")
    return dict(files), dict(sha)


def _entry(d: Any, where: str) -> Entry:
    _need(isinstance(d, dict), where, "an asset entry must be an object")
    asset_id = _str(d, "id", where)
    _need(_ID.fullmatch(asset_id) is not None, where, f"id {asset_id!r} has characters outside [a-z0-9_.-/]")
    where = f"{where} {asset_id!r}"
    kind = _str(d, "kind", where)
    _need(kind in KINDS, where, f"kind must be one of {KINDS}, got {kind!r}")
    split = _str(d, "split", where)
    _need(split in SPLITS, where, f"split must be one of {SPLITS}, got {split!r}")
    label = _str(d, "label", where, empty=True)
    _need(label in LABELS if kind == "mesh" else label == "", where,
          f"label must be one of {LABELS} for a mesh and empty otherwise, got {label!r}")
    files, sha = _files(d, kind, asset_id, where)
    nbytes = d.get("bytes")
    _need(isinstance(nbytes, int) and not isinstance(nbytes, bool) and nbytes > 0, where,
          f"bytes must be a positive integer, got {nbytes!r}")
    src = d.get("source")
    _need(isinstance(src, dict), where, "source must be an object")
    source = SourceRef(*(_str(src, k, f"{where} source") for k in ("registry", "package", "version", "path")))
    _need(source.registry in REGISTRIES, where, f"source registry must be one of {REGISTRIES}")
    licence = _str(d, "licence", where)
    _need(licence in ALLOWED, where, f"licence {licence!r} is not allowed in a pack (allowed: {sorted(ALLOWED)})")
    commit = d.get("committable")
    _need(isinstance(commit, bool), where, "committable must be true or false")
    _need(not commit or licence in COMMITTABLE, where, f"committable is true but {licence} is set-up only")
    credit = _str(d, "credit", where)
    info = d.get("info", {})
    _need(isinstance(info, dict), where, "info must be an object")
    return Entry(asset_id, kind, _str(d, "category", where), split, files, sha, nbytes,
                 _size(d.get("size_m"), kind, where), source, licence, credit, commit, label,
                 _str(d, "name", where, empty=True), _str(d, "note", where, empty=True), info)


def parse_manifest(data: bytes, where: str) -> list[Entry]:
    """The entries of a ``manifest.json``, checked (the module docstring's schema).

    Args:
        data: the file's bytes.
        where: the file's name, for messages.

    Raises:
        AssetPackError: not JSON, another format or version, a malformed entry, a licence not allowed, a
            duplicate id or file; the message names the file and the entry.
    """
    try:
        doc = json.loads(data.decode("utf-8"))
    except (UnicodeDecodeError, json.JSONDecodeError) as e:
        raise AssetPackError(f"{where}: not a JSON manifest ({e})") from None
    _need(isinstance(doc, dict), where, "the manifest must be a JSON object")
    _need(doc.get("format") == FORMAT_NAME, where, f"format must be {FORMAT_NAME!r}, got {doc.get('format')!r}")
    _need(doc.get("version") == FORMAT_VERSION, where,
          f"version {doc.get('version')!r} is not supported (this fruxel reads version {FORMAT_VERSION})")
    assets = doc.get("assets")
    _need(isinstance(assets, list), where, "assets must be a list")
    entries = [_entry(a, f"{where}: asset {i}") for i, a in enumerate(assets)]
    seen_ids: set[str] = set()
    seen_files: set[str] = set()
    for e in entries:
        _need(e.id not in seen_ids, where, f"asset id {e.id!r} appears twice")
        seen_ids.add(e.id)
        for path in e.files.values():
            _need(path not in seen_files, where, f"file {path!r} belongs to two assets (second: {e.id!r})")
            seen_files.add(path)
    return entries


def summary_lines(entries: Iterable[Entry]) -> list[str]:
    """A pack's counts as text lines: per kind and category the train/test counts and bytes, per licence the
    asset count and whether it may be committed, and the total size."""
    entries = list(entries)
    rows: dict[tuple[str, str], list[int]] = defaultdict(lambda: [0, 0, 0])
    for e in entries:
        r = rows[(e.kind, e.category)]
        r[0 if e.split == "train" else 1] += 1
        r[2] += e.bytes
    lines = [f"{'kind':8} {'category':12} {'train':>6} {'test':>5} {'KiB':>8}"]
    for kind in KINDS:
        for (k, cat), (tr, te, nb) in sorted(rows.items()):
            if k == kind:
                lines.append(f"{k:8} {cat:12} {tr:6d} {te:5d} {nb / 1024:8.0f}")
    per_kind = {k: sum(1 for e in entries if e.kind == k) for k in KINDS}
    lines.append("total: " + ", ".join(f"{n} {k}{'es' if k == 'mesh' else 's'}" for k, n in per_kind.items())
                 + f"; {sum(e.bytes for e in entries) / 2**20:.1f} MiB of asset files")
    lic: dict[str, int] = defaultdict(int)
    for e in entries:
        lic[e.licence] += 1
    lines.append("licences: " + ", ".join(f"{k} {n} ({'committable' if k in COMMITTABLE else 'set-up only'})"
                                          for k, n in sorted(lic.items())))
    lines.append(f"committable assets: {sum(e.committable for e in entries)} of {len(entries)}")
    return lines

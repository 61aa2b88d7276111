"""Building an asset pack from the unpacked source packages (:func:`build_pack`).

Steps: collect the candidates (:func:`.sources.collect`), process each one (textures downscaled with a normal map,
meshes decimated part by part, images downscaled; all JPEG or deterministic npz), assign the train/test split
by id (:func:`.manifest.assign_splits`), check the total size against the budget, and write the pack folder
atomically (a hidden folder beside it, renamed at the end). The same sources and config give the same bytes.
"""

from __future__ import annotations

import hashlib
import os
import shutil
import tempfile
from collections import Counter
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np

from .manifest import (
    BUILDER_NAME,
    FOLDERS,
    MANIFEST_NAME,
    ROLES,
    AssetPackError,
    Entry,
    assign_splits,
    builder_digest,
    manifest_bytes,
)
from .sources import PACKAGES, RELIEF_M, Candidate, Package, collect

MIB = 2**20


@dataclass(frozen=True)
class PackConfig:
    """How a pack is built."""

    texture_size: int = 256
    """Longest side of a texture and its normal map, pixels."""
    outdoor_size: int = 768
    """Longest side of an outdoor view (seen through a window, often large in the image), pixels."""
    picture_size: int = 320
    """Longest side of a painting or poster, pixels."""
    jpeg_quality: int = 85
    """JPEG quality of albedos and images."""
    normal_quality: int = 90
    """JPEG quality of normal maps (smooth fields, artefacts show as bumps)."""
    test_fraction: float = 0.2
    """Share of each (kind, category) in the test split."""
    max_bytes: int = 48 * MIB
    """Largest pack allowed (its files and manifest), bytes: it travels to a GPU machine with a 64 MiB limit."""
    min_mesh_extent_m: float = 0.05
    """Meshes whose largest extent is below this (metres) are left out: too small for a room-sized grid."""


@dataclass
class _Built:
    cand: Candidate
    files: dict[str, bytes]
    size_m: tuple[float, ...] | None
    info: dict[str, Any]


def _file_name(asset_id: str, role: str, suffix: str) -> str:
    base = asset_id.replace("/", ".")
    return f"{base}.{role}{suffix}" if role == "normal" else f"{base}{suffix}"


def _texture(c: Candidate, config: PackConfig) -> _Built:
    from .textures import decode_rgb, derive_normal, downscale, jpeg_bytes, normal_from_source

    albedo_bytes, normal_bytes = c.read()
    albedo = downscale(decode_rgb(albedo_bytes, c.source.path), config.texture_size)
    h, w = albedo.shape[:2]
    width_m = float(c.size_m[0]) if c.size_m else 1.0
    if normal_bytes is not None:
        normal = normal_from_source(decode_rgb(normal_bytes, c.source.path + " (normal map)"), (h, w))
        how = "source"
    else:
        normal = derive_normal(albedo, width_m, RELIEF_M.get(c.category, 0.002))
        how = "derived from luminance"
    files = {"albedo": jpeg_bytes(albedo, config.jpeg_quality), "normal": jpeg_bytes(normal, config.normal_quality)}
    return _Built(c, files, (width_m, width_m * h / w), {**c.info, "normal": how, "pixels": [w, h]})


def _image(c: Candidate, config: PackConfig) -> _Built:
    from .textures import decode_rgb, downscale, jpeg_bytes

    side = config.outdoor_size if c.category == "outdoor" else config.picture_size
    rgb = downscale(decode_rgb(c.read(), c.source.path), side)
    return _Built(c, {"image": jpeg_bytes(rgb, config.jpeg_quality)}, None, {"pixels": [rgb.shape[1], rgb.shape[0]]})


def _mesh(c: Candidate, config: PackConfig) -> _Built | None:
    from .pack import mesh_file_bytes

    raw = c.read()
    # Decimation moves the hull a little: centre the footprint and stand it on z = 0 again, in float32 as stored.
    v = raw.vertices.astype(np.float32)
    lo, hi = v.min(axis=0), v.max(axis=0)
    raw.vertices = v - np.array([(lo[0] + hi[0]) / 2, (lo[1] + hi[1]) / 2, lo[2]], dtype=np.float32)
    ext = raw.vertices.max(axis=0) - raw.vertices.min(axis=0)
    if ext.max() < config.min_mesh_extent_m:
        return None
    data = mesh_file_bytes(raw.vertices, raw.faces, raw.face_parts, raw.part_names, raw.part_colors)
    info = {"faces": len(raw.faces), "vertices": len(raw.vertices), "parts": len(raw.part_names),
            "elevation_m": round(float(raw.elevation_m), 4)}
    return _Built(c, {"mesh": data}, tuple(float(x) for x in ext), info)


def process(c: Candidate, config: PackConfig) -> _Built | None:
    """Turn one candidate into its pack files (None: left out, e.g. a mesh too small).

    Raises:
        AssetPackError: unreadable source data, naming it.
    """
    return {"texture": _texture, "image": _image, "mesh": _mesh}[c.kind](c, config)


def _entries(built: list[_Built], config: PackConfig) -> tuple[list[Entry], dict[str, bytes]]:
    splits = assign_splits((((b.cand.kind, b.cand.category), b.cand.id) for b in built), config.test_fraction)
    entries, blobs = [], {}
    for b in built:
        c = b.cand
        suffix = {"albedo": ".jpg", "normal": ".jpg", "mesh": ".npz", "image": ".jpg"}
        files = {role: f"{FOLDERS[c.kind]}/{_file_name(c.id, role, suffix[role])}" for role in ROLES[c.kind]}
        sha = {role: hashlib.sha256(b.files[role]).hexdigest() for role in ROLES[c.kind]}
        for role, path in files.items():
            blobs[path] = b.files[role]
        entries.append(Entry(c.id, c.kind, c.category, splits[c.id], files, sha,
                             sum(len(b.files[r]) for r in ROLES[c.kind]), b.size_m, c.source, c.licence, c.credit,
                             c.committable, c.label, c.name, c.note, b.info))
    return entries, blobs


def _check_size(entries: list[Entry], manifest: bytes, config: PackConfig) -> None:
    total = sum(e.bytes for e in entries) + len(manifest)
    if total > config.max_bytes:
        by = Counter()
        for e in entries:
            by[f"{e.kind} {e.category}"] += e.bytes
        top = ", ".join(f"{k} {v / MIB:.1f} MiB" for k, v in by.most_common(4))
        raise AssetPackError(f"the pack would take {total / MIB:.1f} MiB, over the {config.max_bytes / MIB:.1f} MiB "
                             f"budget (largest: {top}); lower the sizes or face budgets")


def _write(out: Path, blobs: dict[str, bytes], manifest: bytes, replace: bool) -> None:
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", dir=out.parent))
    try:
        for folder in FOLDERS.values():
            (tmp / folder).mkdir()
        for rel, data in sorted(blobs.items()):
            (tmp / rel).write_bytes(data)
        (tmp / MANIFEST_NAME).write_bytes(manifest)
        (tmp / BUILDER_NAME).write_text(builder_digest() + "\n", encoding="ascii")
        for p in tmp.rglob("*"):
            if p.is_file():
                with open(p, "rb") as f:
                    os.fsync(f.fileno())
        old = None
        if out.exists():
            if not replace:
                raise AssetPackError(f"{out}: already exists (pass --replace to rebuild it)")
            old = out.with_name(f".{out.name}.old")
            shutil.rmtree(old, ignore_errors=True)
            out.rename(old)
        tmp.rename(out)
        if old is not None:
            shutil.rmtree(old, ignore_errors=True)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise


def build_pack(cache: str | os.PathLike[str], out: str | os.PathLike[str], config: PackConfig = PackConfig(), *,
               packages: tuple[Package, ...] = PACKAGES, replace: bool = False, progress: bool = False,
               workers: int = 1) -> list[Entry]:
    """Build a pack folder from the unpacked source packages under ``cache``.

    Args:
        cache: the cache folder with each package's tree (:mod:`.fetch`).
        out: the pack folder to write.
        config: sizes, qualities, split and budget.
        packages: the packages to read (absent trees are skipped).
        replace: replace an existing ``out``; otherwise an existing folder is an error, found before any work.
        progress: show a progress bar (tqdm, on stderr).
        workers: processes that convert assets (fork; 1 = in this process).

    Returns:
        The manifest's entries, in id order.

    Raises:
        AssetPackError: ``out`` exists without ``replace``, no candidates, unreadable sources, or a pack over
            ``config.max_bytes``; the message names the file or the budget.
    """
    cache, out = Path(cache), Path(out)
    if out.exists() and not replace:
        raise AssetPackError(f"{out}: already exists (pass --replace to rebuild it)")
    if not cache.is_dir():
        raise AssetPackError(f"{cache}: source cache folder not found")
    candidates = collect(cache, packages)
    if not candidates:
        raise AssetPackError(f"{cache}: no source package found (expected e.g. {packages[0].folder}/)")
    built = _process_all(candidates, config, progress, workers)
    entries, blobs = _entries(built, config)
    manifest = manifest_bytes(entries)
    _check_size(entries, manifest, config)
    _write(out, blobs, manifest, replace)
    return sorted(entries, key=lambda e: e.id)


_WORK: list[Candidate] = []


def _process_index(args: tuple[int, PackConfig]) -> tuple[dict[str, bytes], Any, dict[str, Any]] | None:
    b = process(_WORK[args[0]], args[1])
    # The candidate stays behind: its reader is a closure, which cannot travel back.
    return None if b is None else (b.files, b.size_m, b.info)


def _process_all(candidates: list[Candidate], config: PackConfig, progress: bool, workers: int) -> list[_Built]:
    from tqdm import tqdm

    bar = tqdm(total=len(candidates), desc="assets", unit="asset", disable=not progress)
    out: list[_Built | None] = []
    try:
        if workers > 1:
            import multiprocessing as mp

            # Candidates hold closures (their readers), which fork inherits and pickle cannot carry.
            _WORK[:] = candidates
            with mp.get_context("fork").Pool(workers) as pool:
                jobs = [(i, config) for i in range(len(candidates))]
                for c, r in zip(candidates, pool.imap(_process_index, jobs, chunksize=4), strict=True):
                    out.append(None if r is None else _Built(c, *r))
                    bar.update()
        else:
            for c in candidates:
                out.append(process(c, config))
                bar.update()
    finally:
        _WORK.clear()
        bar.close()
    return [b for b in out if b is not None]

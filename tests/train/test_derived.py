"""The asset pack's derived arrays (decoded texture layers, mean colours), kept once per machine and read by every
process (fruxel.train.sim.assetpack.derived)."""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np
import pytest


def _counting(value: np.ndarray) -> tuple[list[int], object]:
    calls: list[int] = []

    def compute() -> np.ndarray:
        calls.append(1)
        return value

    return calls, compute


def test_an_array_is_made_once_and_read_back_by_another_process_s_instance(tmp_path: Path) -> None:
    from fruxel.train.sim.assetpack.derived import DerivedArrays

    value = np.arange(12, dtype=np.uint8).reshape(3, 4)
    calls, compute = _counting(value)
    first = DerivedArrays(tmp_path).get("a-123", (3, 4), np.uint8, compute)
    again = DerivedArrays(tmp_path).get("a-123", (3, 4), np.uint8, compute)
    assert calls == [1] and (tmp_path / "a-123.npy").is_file()
    assert np.array_equal(first, value) and np.array_equal(again, value) and again.dtype == np.uint8


@pytest.mark.parametrize("damage", ["garbage", "other shape", "other dtype"])
def test_a_damaged_or_mismatched_file_is_made_again(tmp_path: Path, damage: str) -> None:
    from fruxel.train.sim.assetpack.derived import DerivedArrays

    path = tmp_path / "b.npy"
    if damage == "garbage":
        path.write_bytes(b"\x93NUMPY not really")
    else:
        np.save(path, np.zeros((2, 2) if damage == "other shape" else (3, 4), np.float32 if damage == "other dtype"
                               else np.uint8))
    value = np.full((3, 4), 7, dtype=np.uint8)
    calls, compute = _counting(value)
    got = DerivedArrays(tmp_path).get("b", (3, 4), np.uint8, compute)
    assert calls == [1] and np.array_equal(got, value)
    assert np.array_equal(np.load(path, allow_pickle=False), value)  # repaired


def test_an_unwritable_folder_warns_once_and_still_gives_the_arrays(tmp_path: Path) -> None:
    from fruxel.train.sim.assetpack.derived import DerivedArrays

    blocker = tmp_path / "not-a-folder"
    blocker.write_text("a file where the cache folder should be")
    cache = DerivedArrays(blocker / "pack")
    value = np.ones(5)
    with pytest.warns(RuntimeWarning, match="not-a-folder"):
        assert np.array_equal(cache.get("c", (5,), np.float64, lambda: value), value)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert np.array_equal(cache.get("d", (5,), np.float64, lambda: 2 * value), 2 * value)
    assert cache.folder is None


def test_a_computed_array_of_the_wrong_shape_is_refused(tmp_path: Path) -> None:
    from fruxel.train.sim.assetpack.derived import DerivedArrays

    with pytest.raises(ValueError, match="shape"):
        DerivedArrays(tmp_path).get("e", (4,), np.uint8, lambda: np.zeros(3))


def test_texture_layers_come_from_the_cache_folder_and_equal_a_fresh_decode(pack_dir: Path, tmp_path: Path,
                                                                           monkeypatch: pytest.MonkeyPatch) -> None:
    """The layers a renderer uploads are those the texture decodes to; the files are named by the source files'
    SHA-256, and a second process's layers are read from them (a planted file is what it uploads)."""
    from fruxel.train.sim.assetpack import AssetPack
    from fruxel.train.sim.raytrace.textures import TextureLayers, albedo_texels, layer_stride, normal_texels

    monkeypatch.setenv("FRUXEL_CACHE_DIR", str(tmp_path))
    pack = AssetPack(pack_dir)
    texture = next(e for e in pack if e.kind == "texture")
    layers = TextureLayers(pack, 16, "cpu")
    a, n = layers.layer("albedo", texture.id), layers.layer("normal", texture.id)
    stride = layer_stride(16)
    decoded = pack.texture(texture.id)
    assert np.array_equal(layers.albedo.numpy()[a * stride:(a + 1) * stride], albedo_texels(decoded.albedo, 16))
    assert np.array_equal(layers.normal.numpy()[n * stride:(n + 1) * stride], normal_texels(decoded.normal, 16))
    files = sorted(p.name for p in (tmp_path / "pack").iterdir())
    assert len(files) == 2 and all(texture.sha256[r][:32] in f for r, f in zip(("albedo", "normal"), files,
                                                                                 strict=True))
    albedo_file = tmp_path / "pack" / files[0]
    np.save(albedo_file, np.full((stride, 4), 9, dtype=np.uint8))
    other = TextureLayers(pack, 16, "cpu")
    k = other.layer("albedo", texture.id)
    assert (other.albedo.numpy()[k * stride:(k + 1) * stride] == 9).all()


def test_mean_texture_colours_are_kept_too(pack_dir: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    from fruxel.train.sim.rooms.library import Library

    monkeypatch.setenv("FRUXEL_CACHE_DIR", str(tmp_path))
    lib = Library(pack_dir)
    texture = next(e for e in lib.pack if e.kind == "texture")
    colour = lib.texture_colour(texture.id)
    assert colour.shape == (3,) and (0 < colour).all() and (colour < 1).all()
    kept = list((tmp_path / "pack").glob(f"colour-{texture.sha256['albedo'][:32]}-*.npy"))
    assert len(kept) == 1 and np.array_equal(np.load(kept[0], allow_pickle=False), colour)

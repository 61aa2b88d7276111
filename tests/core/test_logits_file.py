"""Logits files (conventions section 8, fruxel.io.save_logits / load_logits): round trips, and malformed files refused
with one error naming the file, as for model files."""

from __future__ import annotations

import io
import json
import os
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.lib.format as npy_format
import pytest

import fruxel
from fruxel.classes import DEFAULT_CLASSES, ClassTable
from fruxel.grid import FruxelGrid
from fruxel.io import FruxelFileError, LogitsFile, load_logits, save_logits
from fruxel.model import FruxelModel, ModelError

GRID = FruxelGrid(width=5, height=4, depth=3, z_near=0.25, z_far=7.5, hfov=73.5)
C = len(DEFAULT_CLASSES)


def _logits(dtype: type = np.float32, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).normal(0.0, 2.0, (C, *GRID.shape)).astype(dtype)


def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    npy_format.write_array(buf, array, allow_pickle=True)
    return buf.getvalue()


def _meta(**change: object) -> bytes:
    meta = {"format": "fruxel-logits", "version": 1, "grid": GRID.to_dict(), "classes": DEFAULT_CLASSES.to_dict()}
    meta.update(change)
    return _npy(np.array(json.dumps(meta)))


def _zip(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w") as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


# ---------------------------------------------------------------------------------------------------- round trips
@pytest.mark.parametrize("dtype", [np.float16, np.float32])
def test_round_trip(tmp_path: Path, dtype: type) -> None:
    classes = DEFAULT_CLASSES.extended("plant")
    lg = np.random.default_rng(1).normal(size=(len(classes), *GRID.shape)).astype(dtype)
    path = tmp_path / "pred.npz"
    fruxel.save_logits(path, lg, GRID, classes)
    got = fruxel.load_logits(path)
    assert isinstance(got, LogitsFile) and got.grid == GRID and got.classes == classes
    assert got.logits.dtype == dtype and got.logits.flags.c_contiguous and got.logits.flags.writeable
    np.testing.assert_array_equal(got.logits, lg)
    np.testing.assert_array_equal(got.labels(), fruxel.labels_from_scores(lg, axis=0))
    assert got.to_model(threshold=0.5) == FruxelModel(fruxel.labels_from_scores(lg, 0.5, axis=0), GRID, classes)
    # A plain npz that numpy reads without pickle.
    with np.load(path, allow_pickle=False) as npz:
        assert sorted(npz.files) == ["logits", "meta"]
        assert json.loads(str(npz["meta"]))["format"] == "fruxel-logits"
    assert os.listdir(tmp_path) == ["pred.npz"]


def test_other_byte_order_and_fortran_order_are_read(tmp_path: Path) -> None:
    lg = _logits()
    path = _zip(tmp_path / "be.npz", {"logits.npy": _npy(np.asfortranarray(lg.astype(">f4"))), "meta.npy": _meta()})
    got = load_logits(path)
    assert got.logits.dtype == np.dtype(np.float32) and got.logits.flags.c_contiguous
    np.testing.assert_array_equal(got.logits, lg)


def test_torch_tensors_are_saved(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    lg = _logits()
    save_logits(tmp_path / "t.npz", torch.from_numpy(lg), GRID, DEFAULT_CLASSES)
    np.testing.assert_array_equal(load_logits(tmp_path / "t.npz").logits, lg)


@pytest.mark.parametrize(("logits", "grid", "classes", "words"), [
    (_logits(np.float64), GRID, DEFAULT_CLASSES, "float16 or float32"),
    (_logits()[None], GRID, DEFAULT_CLASSES, "shape"),
    (_logits()[:5], GRID, DEFAULT_CLASSES, "7 classes"),
    (np.where(np.arange(C * 60).reshape(C, 3, 4, 5) == 7, np.nan, _logits()).astype(np.float32), GRID,
     DEFAULT_CLASSES, "NaN"),
    (_logits(), GRID.to_dict(), DEFAULT_CLASSES, "FruxelGrid"),
    (_logits(), GRID, DEFAULT_CLASSES.names, "ClassTable"),
    ("abc", GRID, DEFAULT_CLASSES, "float16 or float32"),
])
def test_save_refuses_bad_logits(tmp_path: Path, logits: object, grid: object, classes: object, words: str) -> None:
    with pytest.raises(ModelError, match=words):
        save_logits(tmp_path / "x.npz", logits, grid, classes)  # type: ignore[arg-type]
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------------------------------------------- malformed
def _header_only(shape: tuple, descr: str) -> bytes:
    buf = io.BytesIO()
    npy_format.write_array_header_1_0(buf, {"descr": descr, "fortran_order": False, "shape": shape})
    return buf.getvalue()


MALFORMED: dict[str, tuple[Callable[[Path], Path], str]] = {
    "missing": (lambda p: p, "no such file"),
    "folder": (lambda p: (p.mkdir(), p)[1], "directory"),
    "garbage": (lambda p: (p.write_bytes(b"not a zip"), p)[1], "not an npz"),
    "a model file": (lambda p: (fruxel.save(p, FruxelModel(np.zeros(GRID.shape, np.uint8), GRID)), p)[1],
                     "fruxel.load reads it"),
    "no meta": (lambda p: _zip(p, {"logits.npy": _npy(_logits())}), "missing ['meta']"),
    "extra member": (lambda p: _zip(p, {"logits.npy": _npy(_logits()), "meta.npy": _meta(), "x.npy": _npy(
        np.zeros(1))}), "unexpected"),
    "object array": (lambda p: _zip(p, {"logits.npy": _npy(np.array([{"a": 1}], dtype=object)), "meta.npy": _meta()}),
                     "pickle"),
    "int logits": (lambda p: _zip(p, {"logits.npy": _npy(_logits().astype(np.int32)), "meta.npy": _meta()}),
                   "float16 or float32"),
    "float64 logits": (lambda p: _zip(p, {"logits.npy": _npy(_logits(np.float64)), "meta.npy": _meta()}),
                       "float16 or float32"),
    "3-d logits": (lambda p: _zip(p, {"logits.npy": _npy(_logits()[0]), "meta.npy": _meta()}), "expected 4"),
    "wrong channels": (lambda p: _zip(p, {"logits.npy": _npy(_logits()[:3]), "meta.npy": _meta()}), "7 classes"),
    "wrong grid": (lambda p: _zip(p, {"logits.npy": _npy(_logits()[:, :2]), "meta.npy": _meta()}), "(D, H, W)"),
    "huge header": (lambda p: _zip(p, {"logits.npy": _header_only((C, 2048, 2048, 2048), "<f4"), "meta.npy":
                                       _meta(grid={**GRID.to_dict(), "width": 2048, "height": 2048,
                                                   "depth": 2048})}), "more than the limit"),
    "truncated data": (lambda p: _zip(p, {"logits.npy": _npy(_logits())[:-40], "meta.npy": _meta()}), "bytes"),
    "NaN": (lambda p: _zip(p, {"logits.npy": _npy(np.full((C, *GRID.shape), np.nan, np.float32)),
                               "meta.npy": _meta()}), "NaN"),
    "model format name": (lambda p: _zip(p, {"logits.npy": _npy(_logits()), "meta.npy": _meta(format="fruxel")}),
                          "format"),
    "version 2": (lambda p: _zip(p, {"logits.npy": _npy(_logits()), "meta.npy": _meta(version=2)}), "version"),
    "bad grid": (lambda p: _zip(p, {"logits.npy": _npy(_logits()), "meta.npy": _meta(grid={"width": -1})}), "grid"),
    "bad classes": (lambda p: _zip(p, {"logits.npy": _npy(_logits()), "meta.npy": _meta(classes=[1, 2])}),
                    "classes"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_files_raise_one_error_naming_the_file(tmp_path: Path, case: str) -> None:
    make, words = MALFORMED[case]
    path = make(tmp_path / "bad.npz")
    with pytest.raises(FruxelFileError) as e:
        fruxel.load_logits(path)
    msg = str(e.value)
    assert msg.startswith(f"cannot load logits file {str(path)!r}: ") and "\n" not in msg
    assert words in msg, msg
    assert e.value.__cause__ is None and e.value.__context__ is None


def test_a_logits_file_is_not_a_model(tmp_path: Path) -> None:
    save_logits(tmp_path / "l.npz", _logits(), GRID, DEFAULT_CLASSES)
    with pytest.raises(FruxelFileError, match="fruxel.load_logits reads it"):
        fruxel.load(tmp_path / "l.npz")


def test_class_table_of_the_file_is_kept(tmp_path: Path) -> None:
    classes = ClassTable(("empty", "thing"), ((0, 0, 0), (200, 10, 10)))
    save_logits(tmp_path / "two.npz", _logits()[:2], GRID, classes)
    assert load_logits(tmp_path / "two.npz").classes == classes


def test_file_kind(tmp_path: Path) -> None:
    from fruxel.io import file_kind

    save_logits(tmp_path / "l.npz", _logits(), GRID, DEFAULT_CLASSES)
    fruxel.save(tmp_path / "m.npz", FruxelModel(np.zeros(GRID.shape, np.uint8), GRID))
    (tmp_path / "x.npz").write_bytes(b"junk")
    kinds = [file_kind(tmp_path / n) for n in ("l.npz", "m.npz", "x.npz", "missing.npz")]
    assert kinds == ["logits", "model", None, None]

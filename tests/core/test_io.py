"""Model files (conventions section 5): round trips, atomic writes, and a corpus of malformed files."""

from __future__ import annotations

import io
import json
import os
import re
import traceback
import tracemalloc
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import numpy.lib.format as npy_format
import pytest

import fruxel
import fruxel.io as fio
from fruxel.classes import DEFAULT_CLASSES, ClassTable
from fruxel.grid import FruxelGrid
from fruxel.io import FruxelFileError, load, save
from fruxel.model import FruxelModel

GRID = FruxelGrid(width=5, height=4, depth=3, z_near=0.25, z_far=7.5, hfov=73.5)


def _labels(seed: int = 0, grid: FruxelGrid = GRID, n: int = 7) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, n, grid.shape).astype(np.uint8)


def _model(seed: int = 0) -> FruxelModel:
    return FruxelModel(_labels(seed), GRID)


# ---------------------------------------------------------------------------------------------------- builders
def _npy(array: np.ndarray) -> bytes:
    buf = io.BytesIO()
    npy_format.write_array(buf, array, allow_pickle=True)
    return buf.getvalue()


def _npy_header(shape: tuple, descr: str, version: tuple[int, int] = (1, 0)) -> bytes:
    buf = io.BytesIO()
    d = {"descr": descr, "fortran_order": False, "shape": shape}
    if version == (1, 0):
        npy_format.write_array_header_1_0(buf, d)
    else:
        npy_format.write_array_header_2_0(buf, d)
    return buf.getvalue()


def _meta(*, base_grid: FruxelGrid = GRID, base_classes: ClassTable = DEFAULT_CLASSES, **change) -> dict:
    meta = {"format": "fruxel", "version": 1, "grid": base_grid.to_dict(), "classes": base_classes.to_dict()}
    meta.update(change)
    return meta


def _meta_npy(meta: dict | str) -> bytes:
    return _npy(np.array(meta if isinstance(meta, str) else json.dumps(meta)))


def _zip(path: Path, members: dict[str, bytes], compression: int = zipfile.ZIP_STORED) -> Path:
    with zipfile.ZipFile(path, "w", compression=compression) as zf:
        for name, data in members.items():
            zf.writestr(name, data)
    return path


def _valid_members(labels: np.ndarray | None = None, meta: dict | None = None) -> dict[str, bytes]:
    return {"labels.npy": _npy(_labels() if labels is None else labels), "meta.npy": _meta_npy(meta or _meta())}


# ---------------------------------------------------------------------------------------------------- round trips
def test_round_trip_keeps_labels_grid_and_classes(tmp_path: Path) -> None:
    classes = DEFAULT_CLASSES.extended("café", "plant", colours=[(12, 34, 56)])
    model = FruxelModel(_labels(1, n=len(classes)), GRID, classes)
    path = tmp_path / "scene.npz"
    fruxel.save(path, model)
    again = fruxel.load(str(path))
    assert again == model
    assert again.grid == GRID and again.classes == classes and again.labels.dtype == np.uint8
    np.testing.assert_array_equal(again.labels, model.labels)
    # The file is a plain npz that numpy reads without pickle: uint8 labels and a unicode meta string.
    with np.load(path, allow_pickle=False) as npz:
        assert sorted(npz.files) == ["labels", "meta"]
        assert npz["labels"].dtype == np.uint8 and npz["meta"].dtype.kind == "U" and npz["meta"].shape == ()
        meta = json.loads(str(npz["meta"]))
    assert meta["format"] == "fruxel" and meta["version"] == 1
    assert FruxelGrid.from_dict(meta["grid"]) == GRID and ClassTable.from_dict(meta["classes"]) == classes


def test_other_valid_writers_are_read(tmp_path: Path) -> None:
    # An uncompressed np.savez file, a bytes (UTF-8) meta string and Fortran-ordered labels are all valid.
    labels = _labels(2)
    path = tmp_path / "plain.npz"
    np.savez(path, labels=np.asfortranarray(labels), meta=np.array(json.dumps(_meta()).encode("utf-8")))
    model = load(path)
    np.testing.assert_array_equal(model.labels, labels)
    assert model.labels.flags.c_contiguous


def test_save_replaces_an_existing_file_and_respects_the_umask(tmp_path: Path) -> None:
    path = tmp_path / "scene.npz"
    save(path, _model(0))
    save(path, _model(1))
    assert load(path) == _model(1)
    assert os.listdir(tmp_path) == ["scene.npz"]
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(path).st_mode & 0o777 == 0o666 & ~umask


def test_save_refuses_non_models(tmp_path: Path) -> None:
    with pytest.raises(TypeError):
        save(tmp_path / "x.npz", _labels())
    assert os.listdir(tmp_path) == []


# ---------------------------------------------------------------------------------------------------- atomic writes
def _half_write_then_fail(fileobj, model) -> None:
    fileobj.write(b"PK\x03\x04 half of an archive")
    raise RuntimeError("killed mid-write")


def _fail_replace(src, dst) -> None:
    raise OSError("disk vanished")


@pytest.mark.parametrize(
    "target, replacement",
    [("_write_npz", _half_write_then_fail), ("os.replace", _fail_replace)],
)
def test_a_failed_write_leaves_the_old_file_and_no_litter(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, target: str, replacement: Callable
) -> None:
    path = tmp_path / "scene.npz"
    save(path, _model(0))
    before = path.read_bytes()
    if target == "os.replace":
        monkeypatch.setattr(fio.os, "replace", replacement)
    else:
        monkeypatch.setattr(fio, target, replacement)
    with pytest.raises((RuntimeError, OSError)):
        save(path, _model(1))
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["scene.npz"]
    assert path.read_bytes() == before
    assert load(path) == _model(0)


def test_a_failed_first_write_leaves_nothing(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(fio, "_write_npz", _half_write_then_fail)
    with pytest.raises(RuntimeError):
        save(tmp_path / "new.npz", _model(0))
    assert os.listdir(tmp_path) == []


def test_saving_onto_a_directory_fails_cleanly(tmp_path: Path) -> None:
    (tmp_path / "d.npz").mkdir()
    with pytest.raises(OSError):
        save(tmp_path / "d.npz", _model(0))
    assert os.listdir(tmp_path) == ["d.npz"]


# ---------------------------------------------------------------------------------------------------- public helpers
def _via_file(path: Path, data: bytes, fail: BaseException | None = None) -> None:
    with fio.atomic_write(path) as f:
        f.write(data[: len(data) // 2])
        if fail is not None:
            raise fail
        f.write(data[len(data) // 2 :])


def _via_path(path: Path, data: bytes, fail: BaseException | None = None) -> None:
    with fio.atomic_path(path) as tmp:
        tmp.write_bytes(data[: len(data) // 2])
        if fail is not None:
            raise fail
        tmp.write_bytes(data)


@pytest.mark.parametrize("write", [_via_file, _via_path])
@pytest.mark.parametrize("failure", ["exception", "KeyboardInterrupt", "os.replace"])
def test_atomic_helpers_keep_the_old_file_and_leave_no_litter_on_failure(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, write: Callable, failure: str
) -> None:
    path = tmp_path / "frame.png"
    path.write_bytes(b"old contents")
    fail: BaseException | None = {"exception": RuntimeError("killed mid-write"),
                                  "KeyboardInterrupt": KeyboardInterrupt()}.get(failure)
    if failure == "os.replace":
        monkeypatch.setattr(fio.os, "replace", _fail_replace)
    with pytest.raises((RuntimeError, KeyboardInterrupt, OSError)):
        write(path, b"new contents", fail)
    monkeypatch.undo()
    assert os.listdir(tmp_path) == ["frame.png"]
    assert path.read_bytes() == b"old contents"


@pytest.mark.parametrize("write", [_via_file, _via_path])
def test_atomic_helpers_replace_the_file_on_success(tmp_path: Path, write: Callable) -> None:
    path = tmp_path / "frame.png"
    path.write_bytes(b"old contents")
    write(path, b"new contents")
    assert os.listdir(tmp_path) == ["frame.png"]
    assert path.read_bytes() == b"new contents"
    write(tmp_path / "fresh.png", b"first")
    assert (tmp_path / "fresh.png").read_bytes() == b"first"
    umask = os.umask(0)
    os.umask(umask)
    assert os.stat(tmp_path / "fresh.png").st_mode & 0o777 == 0o666 & ~umask


def test_atomic_path_is_a_hidden_sibling_with_the_target_suffix(tmp_path: Path) -> None:
    path = tmp_path / "orbit.mp4"
    path.write_bytes(b"old")
    with fio.atomic_path(path) as tmp:
        # Writers that pick the format by suffix (PIL, imageio, matplotlib) need the target's own suffix.
        assert tmp.parent == tmp_path and tmp.suffix == ".mp4"
        assert re.fullmatch(r"\.orbit\.mp4\.[0-9a-f]{12}\.tmp\.mp4", tmp.name)
        assert tmp.is_file() and tmp.stat().st_size == 0
        tmp.write_bytes(b"new")
        assert path.read_bytes() == b"old"
    assert path.read_bytes() == b"new" and not tmp.exists()


def test_atomic_write_names_its_temporary_and_writes_text(tmp_path: Path) -> None:
    path = tmp_path / "manifest.json"
    with fio.atomic_write(path, "w") as f:
        (name,) = os.listdir(tmp_path)
        # The simulator's generator removes such leftovers of a killed run by this name.
        assert re.fullmatch(r"\.manifest\.json\.[0-9a-f]{12}\.tmp", name)
        f.write("café\n")
    assert path.read_text(encoding="utf-8") == "café\n"
    with pytest.raises(ValueError, match="mode"), fio.atomic_write(path, "ab"):
        pass
    assert os.listdir(tmp_path) == ["manifest.json"]


def test_atomic_files_replace_all_or_none(tmp_path: Path) -> None:
    a, b = tmp_path / "a.png", tmp_path / "sub" / "b.glb"
    b.parent.mkdir()
    a.write_text("old a")
    with pytest.raises(RuntimeError), fio.atomic_files() as files:
        files.path(a).write_text("new a")
        files.path(b).write_text("new b")
        raise RuntimeError("the second output failed")
    assert a.read_text() == "old a" and not b.exists()
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a.png", "sub"], "no temporary file left"
    with fio.atomic_files() as files:
        ta, tb = files.path(a), files.path(b)
        assert ta.suffix == ".png" and tb.suffix == ".glb" and ta.parent == a.parent and tb.parent == b.parent
        ta.write_text("new a")
        tb.write_text("new b")
        assert a.read_text() == "old a", "nothing is replaced before the block ends"
    assert a.read_text() == "new a" and b.read_text() == "new b"
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["a.png", "b.glb", "sub"]


def test_stale_temporaries_of_a_killed_writer_are_removed(tmp_path: Path) -> None:
    """A writer killed with SIGKILL leaves its temporary file; remove_stale_temporaries removes it (and only
    temporaries of that output), but never a live writer's."""
    import signal
    import subprocess
    import sys
    import time

    target = tmp_path / "orbit.mp4"
    code = ("import sys, time\nfrom fruxel.io import atomic_path\n"
            f"with atomic_path({str(target)!r}) as tmp:\n    print(tmp, flush=True)\n    time.sleep(60)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdout=subprocess.PIPE, text=True)
    killed = Path(proc.stdout.readline().strip())
    assert killed.is_file() and killed.name.startswith(".orbit.mp4.") and killed.suffix == ".mp4"
    assert fio.remove_stale_temporaries(target, min_age=0.0) == [], "a live writer's file stays"
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    proc.stdout.close()
    assert killed.is_file(), "SIGKILL leaves the temporary file behind"
    other = tmp_path / ".orbit.gif.0123456789ab.tmp.gif"
    other.write_bytes(b"another output's")
    young = tmp_path / ".orbit.mp4.0123456789ab.tmp"
    young.write_bytes(b"")
    with fio.atomic_path(target) as live:
        old = time.time() - 3600
        for p in (killed, other, young, live):
            os.utime(p, (old, old))
        young_now = time.time()
        os.utime(young, (young_now, young_now))
        assert fio.remove_stale_temporaries(target) == [str(killed)]
        live.write_bytes(b"done")
    assert target.read_bytes() == b"done"
    assert sorted(p.name for p in tmp_path.iterdir()) == sorted([other.name, young.name, target.name])
    assert fio.remove_stale_temporaries(tmp_path / "missing" / "x.png") == []


def test_read_npy_member_reads_exactly_the_expected_array(tmp_path: Path) -> None:
    pose = np.arange(16, dtype=np.float64).reshape(4, 4)
    path = _zip(tmp_path / "a.npz", {"pose.npy": _npy(pose), "obj.npy": _npy(np.array([{"evil": 1}], dtype=object)),
                                     "cut.npy": _npy(pose)[:-8], "fortran.npy": _npy(np.asfortranarray(pose))})
    with zipfile.ZipFile(path) as zf:
        got = fio.read_npy_member(zf, "pose.npy", np.float64, (4, 4))
        np.testing.assert_array_equal(got, pose)
        assert got.flags.writeable and got.dtype == np.float64
        for name, dtype, shape, problem in [
            ("pose.npy", np.float32, (4, 4), r"member 'pose' is \(4, 4\) float64, expected \(4, 4\) float32"),
            ("pose.npy", np.float64, (16,), "expected"),
            ("fortran.npy", np.float64, (4, 4), "Fortran order"),
            ("obj.npy", np.float64, (1,), "object array"),
            ("cut.npy", np.float64, (4, 4), "truncated"),
        ]:
            # The neutral error: each reader (load, the simulator's shards) words it into its own.
            with pytest.raises(fio.ArchiveError, match=problem) as info:
                fio.read_npy_member(zf, name, dtype, shape)
            assert not isinstance(info.value, FruxelFileError)


# ---------------------------------------------------------------------------------------------------- malformed corpus
def _cut(fraction: float) -> Callable[[Path], Path]:
    def make(path: Path) -> Path:
        save(path, _model(3))
        data = path.read_bytes()
        path.write_bytes(data[: int(len(data) * fraction)])
        return path

    return make


def _flip_label_byte(path: Path) -> Path:
    npy = _npy(_labels(4))
    _zip(path, {"labels.npy": npy, "meta.npy": _meta_npy(_meta())})
    data = bytearray(path.read_bytes())
    at = bytes(data).find(npy) + len(npy) - 5
    data[at] ^= 0xFF
    path.write_bytes(bytes(data))
    return path


def _labels_header_only(shape: tuple, grid: FruxelGrid = GRID) -> Callable[[Path], Path]:
    def make(path: Path) -> Path:
        return _zip(path, {"labels.npy": _npy_header(shape, "|u1"), "meta.npy": _meta_npy(_meta(base_grid=grid))})

    return make


def _members(**members: bytes | Callable[[], bytes]) -> Callable[[Path], Path]:
    def make(path: Path) -> Path:
        return _zip(path, {f"{k}.npy": v() if callable(v) else v for k, v in members.items()})

    return make


def _with_meta(meta: dict | str) -> Callable[[Path], Path]:
    return _members(labels=lambda: _npy(_labels()), meta=lambda: _meta_npy(meta))


def _raw(data: bytes) -> Callable[[Path], Path]:
    def make(path: Path) -> Path:
        path.write_bytes(data)
        return path

    return make


BIG_GRID = FruxelGrid(width=1000, height=1000, depth=1000, z_near=0.5, z_far=8.0, hfov=60.0)
OBJECT_LABELS = np.empty(GRID.shape, dtype=object)
OBJECT_LABELS[...] = 0

MALFORMED: dict[str, tuple[Callable[[Path], Path], str]] = {
    "missing meta": (_members(labels=lambda: _npy(_labels())), "keys.*missing.*meta"),
    "extra key": (_members(labels=lambda: _npy(_labels()), meta=lambda: _meta_npy(_meta()),
                           extra=lambda: _npy(np.zeros(2))), "keys.*unexpected.*extra"),
    "renamed key": (_members(label=lambda: _npy(_labels()), meta=lambda: _meta_npy(_meta())), "keys"),
    "int64 labels": (_members(labels=lambda: _npy(_labels().astype(np.int64)), meta=lambda: _meta_npy(_meta())),
                     "dtype int64"),
    "float labels": (_members(labels=lambda: _npy(_labels().astype(np.float32)), meta=lambda: _meta_npy(_meta())),
                     "dtype float32"),
    "object labels": (_members(labels=lambda: _npy(OBJECT_LABELS), meta=lambda: _meta_npy(_meta())), "object"),
    "object meta": (_members(labels=lambda: _npy(_labels()), meta=lambda: _npy(np.array([_meta()], dtype=object))),
                    "object"),
    "2-d labels": (_members(labels=lambda: _npy(_labels().reshape(12, 5)), meta=lambda: _meta_npy(_meta())),
                   "dimensions"),
    "shape mismatch": (_members(labels=lambda: _npy(_labels().reshape(4, 3, 5)), meta=lambda: _meta_npy(_meta())),
                       "shape"),
    "cut at 10%": (_cut(0.1), "truncated"),
    "cut at 50%": (_cut(0.5), "truncated"),
    "cut at 99%": (_cut(0.99), "truncated"),
    "header claims 10^12 cells": (_labels_header_only((10_000, 10_000, 10_000)), "10{12} cells"),
    "header without data": (_labels_header_only((1000, 1000, 1000), BIG_GRID), "truncated"),
    "trailing data": (_members(labels=lambda: _npy(_labels()) + b"\0\0\0", meta=lambda: _meta_npy(_meta())),
                      "trailing|inconsistent"),
    "bad crc": (_flip_label_byte, "corrupt|CRC"),
    "garbage bytes": (_raw(bytes(range(256)) * 8), "not an npz|zip"),
    "empty file": (_raw(b""), "zip"),
    "npy bad magic": (_members(labels=lambda: b"NOTNUMPY" + bytes(100), meta=lambda: _meta_npy(_meta())), "magic"),
    "npy bad header": (_members(labels=lambda: b"\x93NUMPY\x01\x00\x10\x00{'descr': 12}   \n",
                                meta=lambda: _meta_npy(_meta())), "header"),
    "npy version 3": (_members(labels=lambda: b"\x93NUMPY\x03\x00" + bytes(60), meta=lambda: _meta_npy(_meta())),
                      "version"),
    "meta not JSON": (_with_meta("{'grid': oops"), "JSON"),
    "meta a list": (_with_meta("[1, 2]"), "object"),
    "meta missing grid": (_with_meta({k: v for k, v in _meta().items() if k != "grid"}), "missing.*grid"),
    "meta extra key": (_with_meta(_meta(note="hello")), "unexpected.*note"),
    "wrong format name": (_with_meta(_meta(format="froxel")), "format"),
    "unsupported version": (_with_meta(_meta(version=2)), "unsupported format version 2"),
    "version as text": (_with_meta(_meta(version="1")), "version"),
    "invalid grid": (_with_meta(_meta(grid={**GRID.to_dict(), "z_near": -1.0})), "invalid grid.*z_near"),
    "invalid classes": (_with_meta(_meta(classes={"names": ["wall"], "colours": [[0, 0, 0]]})), "invalid classes"),
    "label out of range": (_members(labels=lambda: _npy(np.full(GRID.shape, 7, np.uint8)),
                                    meta=lambda: _meta_npy(_meta())), "label value 7 is out of range"),
    "huge meta string": (_members(labels=lambda: _npy(_labels()), meta=lambda: _npy_header((), "<U100000000")),
                         "too large"),
    "numeric meta": (_members(labels=lambda: _npy(_labels()), meta=lambda: _npy(np.arange(3))), "dtype"),
    "meta array of strings": (_members(labels=lambda: _npy(_labels()),
                                       meta=lambda: _npy(np.array([json.dumps(_meta())]))), "shape"),
    "meta not UTF-8": (_members(labels=lambda: _npy(_labels()), meta=lambda: _npy(np.array(b"\xff\xfe{}"))), "UTF-8"),
    "directory": (lambda p: (p.mkdir(), p)[1], "directory"),
    "missing file": (lambda p: p, "no such file"),
}


@pytest.mark.parametrize("case", sorted(MALFORMED))
def test_malformed_files_raise_one_clear_error(tmp_path: Path, case: str) -> None:
    make, problem = MALFORMED[case]
    path = make(tmp_path / f"bad {case}.npz")
    with pytest.raises(FruxelFileError) as info:
        load(path)
    err = info.value
    assert isinstance(err, ValueError)
    assert path.name in str(err) and err.path == str(path)
    assert re.search(problem, str(err)), f"{str(err)!r} does not name the problem {problem!r}"
    assert err.__cause__ is None and err.__context__ is None
    text = "".join(traceback.format_exception(err))
    assert "During handling" not in text and "direct cause" not in text


@pytest.mark.parametrize("case", ["header claims 10^12 cells", "header without data", "huge meta string"])
def test_absurd_headers_are_refused_before_allocating(tmp_path: Path, case: str) -> None:
    path = MALFORMED[case][0](tmp_path / "big.npz")
    tracemalloc.start()
    try:
        with pytest.raises(FruxelFileError):
            load(path)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20, f"loading a {case!r} file allocated {peak} bytes"


def _zeros_file(path: Path, grid: FruxelGrid, logits: bool = False) -> Path:
    """A valid model (or logits) file of zeros on ``grid``: a few hundred kB declaring a large volume (zeros never
    written cost no memory until they are)."""
    meta = json.dumps({"format": "fruxel-logits" if logits else "fruxel", "version": 1, "grid": grid.to_dict(),
                       "classes": DEFAULT_CLASSES.to_dict()})
    volume = {"logits": np.zeros((len(DEFAULT_CLASSES), *grid.shape), np.float16)} if logits else \
        {"labels": np.zeros(grid.shape, np.uint8)}
    # Compressed (save_logits stores logits as they are): the file stays small.
    np.savez_compressed(path, **volume, meta=np.array(meta, dtype=np.str_))
    return path


@pytest.mark.skipif(not hasattr(os, "fork") or not os.path.exists("/proc/self/statm"),
                    reason="needs Linux's address-space limit")
@pytest.mark.parametrize("logits", [False, True], ids=["model", "logits"])
def test_a_volume_larger_than_the_memory_left_is_refused_before_reading(tmp_path: Path, logits: bool) -> None:
    """In a process limited to 500 MB (``ulimit -v``), 268 million cells of labels (two copies while loading) or
    of float16 logits are refused with one error naming the file and the memory, having allocated almost nothing;
    a volume that fits loads."""
    import subprocess
    import sys

    big = FruxelGrid(width=1024, height=1024, depth=256 if not logits else 32, z_near=0.5, z_far=8.0, hfov=60.0)
    path = _zeros_file(tmp_path / "big.npz", big, logits)
    small = _zeros_file(tmp_path / "small.npz", GRID, logits)
    reader = "load_logits" if logits else "load"
    code = (f"import resource, sys, tracemalloc\nresource.setrlimit(resource.RLIMIT_AS, ({500 << 20}, {500 << 20}))\n"
            f"import fruxel, fruxel.io as fio\nfio.{reader}(sys.argv[2])\ntracemalloc.start()\n"
            f"try:\n    fio.{reader}(sys.argv[1])\nexcept fruxel.FruxelFileError as e:\n"
            "    print(tracemalloc.get_traced_memory()[1]); print(e)\n")
    out = subprocess.run([sys.executable, "-c", code, str(path), str(small)], capture_output=True, text=True,
                         timeout=300)
    assert out.returncode == 0 and out.stderr == "", out.stderr
    peak, message = out.stdout.splitlines()
    assert int(peak) < 16 * 2**20, f"allocated {peak} bytes before refusing"
    assert str(path) in message and "1024x1024" in message and "of memory, more than the" in message, message


def test_read_header_reads_meta_alone(tmp_path: Path) -> None:
    """The kind, grid and classes of a file without reading its volume: a file declaring 4 billion cells costs
    nothing to ask."""
    save(tmp_path / "m.npz", _model())
    fio.save_logits(tmp_path / "l.npz", np.zeros((7, *GRID.shape), np.float32), GRID, DEFAULT_CLASSES)
    assert fio.read_header(tmp_path / "m.npz") == ("model", GRID, DEFAULT_CLASSES)
    assert fio.read_header(tmp_path / "l.npz") == ("logits", GRID, DEFAULT_CLASSES)
    huge = FruxelGrid(width=2048, height=2048, depth=1024, z_near=0.5, z_far=8.0, hfov=60.0)
    path = MALFORMED["garbage bytes"][0](tmp_path / "g.npz")
    with pytest.raises(FruxelFileError, match="g.npz"):
        fio.read_header(path)
    # A model file whose labels member claims 4 billion cells: only meta is read.
    meta = json.dumps({"format": "fruxel", "version": 1, "grid": huge.to_dict(), "classes": DEFAULT_CLASSES.to_dict()})
    with zipfile.ZipFile(tmp_path / "h.npz", "w") as zf:
        header = io.BytesIO()
        npy_format.write_array_header_1_0(header, {"descr": "|u1", "fortran_order": False, "shape": huge.shape})
        zf.writestr("labels.npy", header.getvalue())
        zf.writestr("meta.npy", _npy(np.array(meta, dtype=np.str_)))
    tracemalloc.start()
    try:
        assert fio.read_header(tmp_path / "h.npz") == ("model", huge, DEFAULT_CLASSES)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 16 * 2**20


def test_every_corpus_file_is_refused_by_the_public_name(tmp_path: Path) -> None:
    # fruxel.load is the documented entry point; it must be the same function with the same error type.
    assert fruxel.load is load and fruxel.save is save and fruxel.FruxelFileError is FruxelFileError
    path = MALFORMED["garbage bytes"][0](tmp_path / "g.npz")
    with pytest.raises(fruxel.FruxelFileError):
        fruxel.load(path)


def test_atomic_path_keeps_the_umask_permissions_when_the_writer_replaces_the_file(tmp_path: Path) -> None:
    """safetensors' save_file writes a new file of mode 0o600 in place of the one it is given; a shipped model
    must still be readable as any other written file."""
    path = tmp_path / "model.safetensors"
    with fio.atomic_path(path) as tmp:
        os.remove(tmp)
        fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        os.write(fd, b"weights")
        os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    assert path.read_bytes() == b"weights"
    assert os.stat(path).st_mode & 0o777 == 0o666 & ~umask

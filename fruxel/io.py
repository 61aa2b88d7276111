"""Model files (SPEC section 5): an ``.npz`` archive read and written without pickle.

Layout, format version 1:

- ``labels``: ``(D, H, W)`` uint8 npy member, the model's labels indexed ``[k, j, i]``.
- ``meta``: 0-d numpy unicode (``<U``) npy member holding one JSON object,
  ``{"format": "fruxel", "version": 1, "grid": FruxelGrid.to_dict(), "classes": ClassTable.to_dict()}``.
  A bytes (``|S``) member holding UTF-8 JSON is read too.

Members are deflate-compressed (label volumes are mostly zeros). :func:`save` writes atomically: a temporary
file in the target's directory, fsync, then ``os.replace``, so a crash leaves the old file or the new one,
never a half-written file under the target's name.

:func:`load` never unpickles and never trusts a size before checking it: it opens the archive with
:mod:`zipfile`, checks the member names, parses each member's npy header (``numpy.lib.format``) and refuses
wrong dtypes, object arrays, wrong shapes or absurd sizes *before* reading any data, cross-checks the label
shape with the grid in ``meta``, then reads exactly the bytes the header announces. Every problem raises one
:class:`FruxelFileError` naming the file and the problem, with no chained traceback.
"""

from __future__ import annotations

import contextlib
import json
import os
import secrets
import zipfile
from typing import IO, Any

import numpy as np
import numpy.lib.format as npy_format

from .classes import ClassTable, ClassTableError
from .grid import MAX_CELLS, FruxelGrid, GridError
from .model import FruxelModel

FORMAT_NAME = "fruxel"
"""Value of ``meta["format"]``."""

FORMAT_VERSION = 1
"""The file format version this module writes and reads."""

MAX_META_CHARS = 1 << 20
"""Longest ``meta`` JSON accepted, in characters: far above any real grid plus 256 class names."""

_MEMBERS = ("labels.npy", "meta.npy")
_META_KEYS = ("format", "version", "grid", "classes")


class FruxelFileError(ValueError):
    """A file that is not a valid fruxel model file (or cannot be read). The message names the file and the
    problem; :attr:`path` and :attr:`problem` hold them separately."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"cannot load fruxel model {path!r}: {problem}")
        self.path = path
        """The file name as given to :func:`load`."""
        self.problem = problem
        """What is wrong with it, in words."""


class _Bad(Exception):
    """Internal: one problem found while reading; becomes a FruxelFileError outside any except block."""


# ---------------------------------------------------------------------------------------------------- save
def _meta_json(model: FruxelModel) -> str:
    return json.dumps(
        {"format": FORMAT_NAME, "version": FORMAT_VERSION, "grid": model.grid.to_dict(),
         "classes": model.classes.to_dict()},
        ensure_ascii=False,
    )


def _write_npz(fileobj: IO[bytes], model: FruxelModel) -> None:
    np.savez_compressed(fileobj, labels=np.ascontiguousarray(model.labels, dtype=np.uint8),
                        meta=np.array(_meta_json(model), dtype=np.str_))


def _fsync_directory(directory: str) -> None:
    # Makes the rename itself durable on POSIX; some platforms cannot open directories, which is harmless.
    try:
        fd = os.open(directory, os.O_RDONLY)
    except OSError:
        return
    try:
        with contextlib.suppress(OSError):
            os.fsync(fd)
    finally:
        os.close(fd)


def save(path: str | os.PathLike[str], model: FruxelModel) -> None:
    """Write ``model`` to ``path`` atomically (format in the module docstring).

    The name is used as given (no ``.npz`` is appended). An existing file is replaced only once the new one is
    complete and synced; on any failure the old file is left as it was and the temporary file is removed.

    Args:
        path: target file name.
        model: the model to write.

    Raises:
        TypeError: ``model`` is not a :class:`FruxelModel`.
        OSError: the file cannot be written (the target is a directory, no permission, disk full).
    """
    if not isinstance(model, FruxelModel):
        raise TypeError(f"save() needs a FruxelModel, got {type(model).__name__}")
    target = os.fsdecode(path)
    directory = os.path.dirname(os.path.abspath(target))
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    while True:
        # Hidden, beside the target (os.replace must not cross file systems), short enough for any name limit.
        tmp = os.path.join(directory, f".{os.path.basename(target)[:120]}.{secrets.token_hex(6)}.tmp")
        try:
            # Mode 0o666 lets the umask decide the permissions, as for any newly created file.
            fd = os.open(tmp, flags, 0o666)
            break
        except FileExistsError:
            continue
    try:
        with os.fdopen(fd, "wb") as f:
            _write_npz(f, model)
            f.flush()
            os.fsync(f.fileno())
        os.replace(tmp, target)
    except BaseException:
        with contextlib.suppress(OSError):
            os.remove(tmp)
        raise
    _fsync_directory(directory)


# ---------------------------------------------------------------------------------------------------- load
def _listing(missing: list[str], extra: list[str]) -> str:
    parts = ([f"missing {missing}"] if missing else []) + ([f"unexpected or repeated {extra}"] if extra else [])
    return ": " + ", ".join(parts)


def _read_header(zf: zipfile.ZipFile, name: str) -> tuple[IO[bytes], tuple[int, ...], bool, np.dtype, int]:
    """Open member ``name`` and parse its npy header; returns the open stream positioned at the data, shape,
    fortran_order, dtype and the header length in bytes."""
    key = name[:-4]
    f = zf.open(name)
    try:
        # Only ValueError means a bad npy member; zip-level errors (bad CRC, truncation) go up to load().
        try:
            version = npy_format.read_magic(f)
        except ValueError:
            raise _Bad(f"member {key!r} is not an npy array (bad magic string)") from None
        if version not in ((1, 0), (2, 0)):
            raise _Bad(f"member {key!r} has unsupported npy format version {version}")
        try:
            if version == (1, 0):
                shape, fortran, dtype = npy_format.read_array_header_1_0(f)
            else:
                shape, fortran, dtype = npy_format.read_array_header_2_0(f)
        except (ValueError, TypeError, SyntaxError) as e:
            problem = f"member {key!r} has a malformed npy header ({e})"
        else:
            return f, tuple(shape), bool(fortran), dtype, f.tell()
        raise _Bad(problem)
    except BaseException:
        f.close()
        raise


def _read_data(f: IO[bytes], key: str, nbytes: int) -> bytes:
    # Reading at most one byte more than announced bounds memory by the header (already checked) and shows
    # both truncated and over-long members; zipfile verifies the CRC when the member ends.
    data = f.read(nbytes + 1)
    if len(data) < nbytes:
        raise _Bad(f"member {key!r} is truncated: {len(data)} of {nbytes} data bytes")
    if len(data) > nbytes or f.read(1):
        raise _Bad(f"member {key!r} has trailing data after its {nbytes} data bytes")
    return data


def _expect_size(info: zipfile.ZipInfo, key: str, header_len: int, nbytes: int) -> None:
    if info.file_size != header_len + nbytes:
        raise _Bad(f"member {key!r} holds {info.file_size} bytes but its header announces {header_len + nbytes} "
                   "(truncated or inconsistent)")


def _read_meta(zf: zipfile.ZipFile) -> tuple[FruxelGrid, ClassTable]:
    f, shape, _, dtype, header_len = _read_header(zf, "meta.npy")
    with f:
        if dtype.hasobject:
            raise _Bad("member 'meta' is an object array (refused: loading it would need pickle)")
        if dtype.kind not in "US" or dtype.fields is not None:
            raise _Bad(f"member 'meta' has dtype {dtype}, expected a unicode string")
        if shape != ():
            raise _Bad(f"member 'meta' has shape {shape}, expected a 0-d string")
        chars = dtype.itemsize // 4 if dtype.kind == "U" else dtype.itemsize
        if chars > MAX_META_CHARS:
            raise _Bad(f"member 'meta' is too large: {chars} characters, limit {MAX_META_CHARS}")
        _expect_size(zf.getinfo("meta.npy"), "meta", header_len, dtype.itemsize)
        raw = _read_data(f, "meta", dtype.itemsize)
    value = np.frombuffer(raw, dtype=dtype, count=1)[0] if dtype.itemsize else dtype.type()
    if dtype.kind == "S":
        try:
            text = bytes(value).decode("utf-8")
        except UnicodeDecodeError:
            raise _Bad("member 'meta' is not valid UTF-8") from None
    else:
        text = str(value)
    try:
        meta = json.loads(text)
    except (ValueError, RecursionError) as e:
        problem = f"meta is not valid JSON ({e})"
    else:
        return _check_meta(meta)
    raise _Bad(problem)


def _check_meta(meta: Any) -> tuple[FruxelGrid, ClassTable]:
    if not isinstance(meta, dict):
        raise _Bad(f"meta must be a JSON object, got {type(meta).__name__}")
    missing = [k for k in _META_KEYS if k not in meta]
    extra = sorted(str(k) for k in set(meta) - set(_META_KEYS))
    if missing or extra:
        raise _Bad(f"wrong meta keys{_listing(missing, extra)}")
    if meta["format"] != FORMAT_NAME:
        raise _Bad(f"meta format is {meta['format']!r}, expected {FORMAT_NAME!r}")
    version = meta["version"]
    if isinstance(version, bool) or not isinstance(version, int):
        raise _Bad(f"meta version must be an integer, got {version!r}")
    if version != FORMAT_VERSION:
        raise _Bad(f"unsupported format version {version} (this fruxel reads version {FORMAT_VERSION})")
    try:
        grid = FruxelGrid.from_dict(meta["grid"])
    except GridError as e:
        problem = f"meta has an invalid grid: {e}"
    else:
        try:
            classes = ClassTable.from_dict(meta["classes"])
        except ClassTableError as e:
            problem = f"meta has invalid classes: {e}"
        else:
            return grid, classes
    raise _Bad(problem)


def _read_labels(zf: zipfile.ZipFile, grid: FruxelGrid, classes: ClassTable) -> np.ndarray:
    f, shape, fortran, dtype, header_len = _read_header(zf, "labels.npy")
    with f:
        if dtype.hasobject:
            raise _Bad("member 'labels' is an object array (refused: loading it would need pickle)")
        if dtype != np.dtype(np.uint8):
            raise _Bad(f"member 'labels' has dtype {dtype}, expected uint8")
        if len(shape) != 3:
            raise _Bad(f"member 'labels' has {len(shape)} dimensions (shape {shape}), expected 3 (D, H, W)")
        n = 1
        for s in shape:
            n *= s
        if n > MAX_CELLS:
            raise _Bad(f"member 'labels' header claims {n} cells (shape {shape}), more than the limit {MAX_CELLS}")
        if shape != grid.shape:
            raise _Bad(f"member 'labels' has shape {shape} but the grid in meta has (D, H, W) = {grid.shape}")
        _expect_size(zf.getinfo("labels.npy"), "labels", header_len, n)
        raw = _read_data(f, "labels", n)
    labels = np.frombuffer(raw, dtype=np.uint8).reshape(shape, order="F" if fortran else "C")
    top = int(labels.max()) if labels.size else 0
    if top >= len(classes):
        raise _Bad(f"label value {top} is out of range for the {len(classes)} classes in meta")
    return labels


def _load(path: str) -> FruxelModel:
    try:
        f = open(path, "rb")
    except FileNotFoundError:
        raise _Bad("no such file") from None
    except IsADirectoryError:
        raise _Bad("it is a directory, not a file") from None
    except OSError as e:
        raise _Bad(f"cannot open it ({e.strerror or e})") from None
    with f:
        if os.path.isdir(path):
            raise _Bad("it is a directory, not a file")
        head = f.read(4)
        f.seek(0)
        try:
            zf = zipfile.ZipFile(f)
        except zipfile.BadZipFile:
            if head == b"PK\x03\x04":
                raise _Bad("truncated or corrupt zip archive (no readable central directory)") from None
            raise _Bad("not an npz file (not a zip archive)") from None
        with zf:
            names = zf.namelist()
            if sorted(names) != sorted(_MEMBERS):
                missing = [m[:-4] for m in _MEMBERS if m not in names]
                extra = sorted({n for n in names if n not in _MEMBERS} | {n for n in names if names.count(n) > 1})
                raise _Bad(f"wrong keys{_listing(missing, extra)}; expected exactly 'labels' and 'meta'")
            grid, classes = _read_meta(zf)
            labels = _read_labels(zf, grid, classes)
    return FruxelModel(labels, grid, classes)


def load(path: str | os.PathLike[str]) -> FruxelModel:
    """Read a model file written by :func:`save` (format in the module docstring), without pickle.

    Args:
        path: the file name.

    Returns:
        The model, with its labels, grid and class table.

    Raises:
        FruxelFileError: the file is missing, unreadable, a directory, or not a valid fruxel model file: not a
            zip archive, truncated, wrong members, an object array, a wrong dtype, ndim or shape, a header
            claiming an absurd size, meta that is not JSON or has a wrong format name, an unsupported
            version, an invalid grid or class table, or labels outside the class table. One error, whose
            message names the file and the problem, with no chained exception.
    """
    name = os.fsdecode(path)
    try:
        return _load(name)
    except _Bad as e:
        problem = str(e)
    except (zipfile.BadZipFile, zipfile.LargeZipFile) as e:
        problem = f"corrupt zip archive ({e})"
    except EOFError:
        problem = "truncated file (unexpected end of data)"
    except MemoryError:
        problem = "not enough memory to read it"
    except OSError as e:
        problem = f"read error ({e.strerror or e})"
    except Exception as e:
        # Anything else a damaged archive can provoke in zipfile or zlib (bad CRC, unknown compression,
        # encryption, struct errors) is still a damaged file, and the caller gets the one documented error.
        problem = f"corrupt file ({type(e).__name__}: {e})"
    raise FruxelFileError(name, problem)

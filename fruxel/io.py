"""Model files (conventions section 5) and logits files (conventions section 8): ``.npz`` archives read and written
without pickle; and the package's atomic writes and strict npy-member reading, which the simulator's shards, mesh export
and the renderer share.

Model file layout, format version 1:

- ``labels``: ``(D, H, W)`` uint8 npy member, the model's labels indexed ``[k, j, i]``.
- ``meta``: 0-d numpy unicode (``<U``) npy member holding one JSON object,
  ``{"format": "fruxel", "version": 1, "grid": FruxelGrid.to_dict(), "classes": ClassTable.to_dict()}``.
  A bytes (``|S``) member holding UTF-8 JSON is read too.

Logits file layout (a network's output for one image, for ``fruxel-render``, predictions and tests), format
version 1:

- ``logits``: ``(C, D, H, W)`` float16 or float32 npy member (NCDHW without the batch axis; channel 0 = empty),
  C-ordered; read in either byte order and returned in the machine's.
- ``meta``: as above, with ``"format": "fruxel-logits"``; ``classes`` has C entries.

Model members are deflate-compressed (label volumes are mostly zeros); logits are stored uncompressed (float
scores hardly compress, and large ones load faster so). :func:`save` and :func:`save_logits` write atomically
(:func:`atomic_write`): a temporary file in the target's directory, fsync, then ``os.replace``, so a crash leaves
the old file or the new one, never a half-written file under the target's name.

:func:`load` and :func:`load_logits` never unpickle and never trust a size before checking it: they open the
archive with :mod:`zipfile`, check the member names, parse each member's npy header (:func:`open_npy_member`)
and refuse wrong dtypes, object arrays, wrong shapes or absurd sizes *before* reading any data, cross-check the
array's shape with the grid and classes in ``meta``, refuse an array larger than the memory available
(:func:`check_memory`: a 4 MB file of zeros can declare 4 GB of labels), then read exactly the bytes the header
announces into the array's own buffer (and refuse NaN or infinite logits). :func:`read_header` reads ``meta``
alone, for a check before the work a file is for. Every problem raises one :class:`FruxelFileError` naming the
file and the problem, with no chained traceback.

Shared helpers (numpy and the standard library only):

- :func:`atomic_write` (a file object) and :func:`atomic_path` (a temporary file name, for writers that need one
  with the right suffix: PIL, imageio, matplotlib) replace a file atomically and durably; :func:`atomic_files`
  replaces several files together, all or none; :func:`remove_stale_temporaries` removes what killed writers
  of a file left behind.
- :func:`open_archive`, :func:`open_npy_member`, :func:`read_npy_member` and :func:`describe_read_error` read
  npz archives strictly; they raise the neutral :class:`ArchiveError`, which each reader turns into its own
  error naming the file (:class:`FruxelFileError` here, ``DatasetError`` in :mod:`fruxel.train.sim.shards`).
"""

from __future__ import annotations

import contextlib
import hashlib
import json
import os
import re
import secrets
import stat
import time
import zipfile
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import IO, Any, TypeVar

import numpy as np
import numpy.lib.format as npy_format

try:
    import fcntl
except ImportError:  # Windows: no flock, see remove_stale_temporaries
    fcntl = None  # type: ignore[assignment]

from .classes import ClassTable, ClassTableError
from .errors import FruxelError
from .grid import MAX_CELLS, FruxelGrid, GridError
from .model import FruxelModel, ModelError, labels_from_scores

FORMAT_NAME = "fruxel"
"""Value of ``meta["format"]``."""

FORMAT_VERSION = 1
"""The file format version this module writes and reads."""

LOGITS_FORMAT_NAME = "fruxel-logits"
"""Value of ``meta["format"]`` in a logits file."""

LOGITS_DTYPES = (np.dtype(np.float16), np.dtype(np.float32))
"""The dtypes of a logits file's ``logits`` (in the machine's byte order; the other order is read too)."""

MAX_LOGITS_BYTES = 1 << 36
"""Largest ``logits`` member accepted, in bytes (64 GiB): a header claiming more is refused before reading."""

MAX_META_CHARS = 1 << 20
"""Longest ``meta`` JSON accepted, in characters: far above any real grid plus 256 class names."""

READ_CHUNK = 1 << 24
"""Bytes read at a time into an array's own buffer (:meth:`NpyMember.read_array`)."""

T = TypeVar("T")

_MEMBERS = ("labels.npy", "meta.npy")
_LOGITS_MEMBERS = ("logits.npy", "meta.npy")
_META_KEYS = ("format", "version", "grid", "classes")


class FruxelFileError(FruxelError, ValueError):
    """A file that is not a valid fruxel model file or logits file (or cannot be read). The message names the
    file and the problem; :attr:`path` and :attr:`problem` hold them separately."""

    def __init__(self, path: str, problem: str, kind: str = "fruxel model") -> None:
        super().__init__(f"cannot load {kind} {path!r}: {problem}")
        self.path = path
        """The file name as given to :func:`load`."""
        self.problem = problem
        """What is wrong with it, in words."""


class ArchiveError(ValueError):
    """One problem found while strictly reading an npz archive (a bad npy header, a truncated member, a wrong
    layout). The message is the problem in words, without the file name: each reader catches this error and
    raises its own, naming the file, outside the ``except`` block (so with no chained traceback)."""


# ---------------------------------------------------------------------------------------------------- atomic writes
STALE_AGE = 5.0
"""Seconds a temporary file must have existed before :func:`remove_stale_temporaries` may take it for a dead
writer's (a live writer holds a lock on it from a moment after creating it)."""


def file_sha256(path: str | os.PathLike[str]) -> str:
    """SHA-256 (hex) of a file's bytes, read in 4 MiB blocks."""
    h = hashlib.sha256()
    with open(path, "rb") as f:
        for block in iter(lambda: f.read(1 << 22), b""):
            h.update(block)
    return h.hexdigest()


CACHE_ENV = "FRUXEL_CACHE_DIR"
"""The environment variable naming the folder of fruxel's caches (:func:`cache_folder`)."""


def cache_folder() -> Path:
    """The folder of fruxel's caches (derived data that is made again when it is missing): ``$FRUXEL_CACHE_DIR``,
    else ``$XDG_CACHE_HOME/fruxel``, else ``~/.cache/fruxel``."""
    if os.environ.get(CACHE_ENV):
        return Path(os.environ[CACHE_ENV])
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "fruxel"


def _temporary_name(target: str, suffix: str) -> str:
    # Beside the target (os.replace must not cross file systems), short enough for any name limit.
    directory = os.path.dirname(os.path.abspath(target))
    return os.path.join(directory, f".{os.path.basename(target)[:120]}.{secrets.token_hex(6)}.tmp{suffix}")


def _hold(fd: int) -> int:
    """A duplicate of ``fd`` holding an exclusive ``flock`` on the file: the mark of a live writer, which the
    kernel drops when the process dies. Close the duplicate to release it. Without ``fcntl`` (Windows) the
    duplicate marks nothing."""
    lock = os.dup(fd)
    if fcntl is not None:
        with contextlib.suppress(OSError):
            fcntl.flock(lock, fcntl.LOCK_EX)
    return lock


def _create_temporary(target: str, suffix: str) -> tuple[str, int, int]:
    """Create a new, empty, hidden file beside ``target``; returns its name, an open write descriptor and the
    descriptor of the writer's lock on it (:func:`_hold`)."""
    flags = os.O_WRONLY | os.O_CREAT | os.O_EXCL | getattr(os, "O_BINARY", 0)
    while True:
        tmp = _temporary_name(target, suffix)
        try:
            # Mode 0o666 lets the umask decide the permissions, as for any newly created file (mkstemp's 0o600
            # would leave written models, meshes and images private).
            fd = os.open(tmp, flags, 0o666)
        except FileExistsError:
            continue
        return tmp, fd, _hold(fd)


def _discard(tmp: str, lock: int) -> None:
    with contextlib.suppress(OSError):
        os.remove(tmp)
    os.close(lock)


def remove_stale_temporaries(path: str | os.PathLike[str], min_age: float = STALE_AGE) -> list[str]:
    """Remove the temporary files that killed writers of ``path`` left beside it.

    :func:`atomic_write`, :func:`atomic_path` and :func:`atomic_files` remove their temporary file on any error,
    but a process killed with ``SIGKILL`` (or a power cut) cannot. Such a file is recognised by its name
    (``.NAME.XXXXXXXXXXXX.tmp`` or ``.NAME.XXXXXXXXXXXX.tmpSUFFIX`` for ``path`` = ``NAME``), and told from a
    live writer's by the lock every writer holds on its temporary file until it is done (``flock``, released by
    the kernel when a process dies). Files younger than ``min_age`` seconds are left alone (a writer takes its
    lock a moment after creating the file). Where ``flock`` is missing, only files older than a day go.

    Args:
        path: the output whose stale temporaries to remove; its folder may be missing.
        min_age: seconds since the last change below which a file is kept.

    Returns:
        The names removed.
    """
    target = os.fsdecode(path)
    directory = os.path.dirname(os.path.abspath(target))
    base = os.path.basename(target)
    pattern = re.compile(rf"\.{re.escape(base[:120])}\.[0-9a-f]{{12}}\.tmp(?:{re.escape(Path(base).suffix)})?")
    try:
        names = os.listdir(directory)
    except OSError:
        return []
    removed = []
    for name in names:
        if not pattern.fullmatch(name):
            continue
        tmp = os.path.join(directory, name)
        try:
            fd = os.open(tmp, os.O_RDONLY | getattr(os, "O_NOFOLLOW", 0))
        except OSError:
            continue
        try:
            st = os.fstat(fd)
            age = time.time() - st.st_mtime
            if not stat.S_ISREG(st.st_mode) or age < (min_age if fcntl is not None else 86400.0):
                continue
            if fcntl is not None:
                try:
                    fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
                except OSError:
                    continue  # a live writer holds it
            os.remove(tmp)
            removed.append(tmp)
        except OSError:
            continue
        finally:
            os.close(fd)
    return removed


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


def _fsync_file(path: str) -> None:
    fd = os.open(path, os.O_RDWR | getattr(os, "O_BINARY", 0))
    try:
        os.fsync(fd)
    finally:
        os.close(fd)


def durable_rename(src: str | os.PathLike[str], dst: str | os.PathLike[str]) -> None:
    """Rename a finished file or folder ``src`` to the free name ``dst`` (same file system), durably: every file
    under ``src`` is fsynced first, then the rename and the folder that holds ``dst``. A folder written whole under
    a temporary name and renamed so appears at once, complete, or not at all.

    Raises:
        OSError: ``dst`` exists as a non-empty folder, or the rename fails.
    """
    src, dst = os.fsdecode(src), os.fsdecode(dst)
    files = [src] if not os.path.isdir(src) else [os.path.join(d, f) for d, _, fs in os.walk(src) for f in fs]
    for path in files:
        _fsync_file(path)
    for d in [d for d, _, _ in os.walk(src)] if os.path.isdir(src) else []:
        _fsync_directory(d)
    os.rename(src, dst)
    _fsync_directory(os.path.dirname(os.path.abspath(dst)))


def _commit(tmp: str, target: str) -> None:
    os.replace(tmp, target)
    _fsync_directory(os.path.dirname(os.path.abspath(target)))


@contextlib.contextmanager
def atomic_write(path: str | os.PathLike[str], mode: str = "wb", *, encoding: str = "utf-8") -> Iterator[IO[Any]]:
    """Replace the file ``path`` atomically with what the ``with`` block writes to the yielded file object.

    The block writes to a new hidden file beside the target, ``.NAME.XXXXXXXXXXXX.tmp`` (12 hex digits); when it
    ends normally the file is flushed and fsynced, renamed onto ``path`` with ``os.replace`` and the folder is
    fsynced, so a reader or a crash sees the old file or the complete new one, never part of one. When the block
    (or the sync or the rename) raises, including ``KeyboardInterrupt``, the temporary file is removed, the old
    file is left as it was and the exception propagates. Only a killed process can leave the temporary file;
    :func:`remove_stale_temporaries` cleans up after one.

    Args:
        path: the file to write; its folder must exist.
        mode: ``"wb"`` (bytes) or ``"w"`` (text).
        encoding: the text encoding of mode ``"w"``; unused for ``"wb"``.

    Yields:
        The open temporary file, in ``mode``.

    Raises:
        ValueError: another mode.
        OSError: the file cannot be written (the target is a directory, no permission, disk full).
    """
    if mode not in ("wb", "w"):
        raise ValueError(f"atomic_write() writes in mode 'wb' or 'w', not {mode!r}")
    target = os.fsdecode(path)
    tmp, fd, lock = _create_temporary(target, "")
    try:
        with os.fdopen(fd, mode, encoding=None if "b" in mode else encoding) as f:
            yield f
            f.flush()
            os.fsync(f.fileno())
        _commit(tmp, target)
    except BaseException:
        _discard(tmp, lock)
        raise
    os.close(lock)


class AtomicFiles:
    """The temporary files of one :func:`atomic_files` block, committed together when it ends."""

    def __init__(self) -> None:
        self._pending: list[tuple[str, str, int, int]] = []

    def path(self, path: str | os.PathLike[str]) -> Path:
        """A new, empty temporary file for the target ``path`` (``.NAME.XXXXXXXXXXXX.tmpSUFFIX`` beside it, with
        its suffix, for writers that pick the format by the name); write it (overwriting it) and close it.

        Raises:
            OSError: it cannot be created (a missing folder, no permission).
        """
        target = os.fsdecode(path)
        tmp, fd, lock = _create_temporary(target, Path(target).suffix)
        mode = stat.S_IMODE(os.fstat(fd).st_mode)
        os.close(fd)
        self._pending.append((tmp, target, lock, mode))
        return Path(tmp)


@contextlib.contextmanager
def atomic_files() -> Iterator[AtomicFiles]:
    """Replace several files together: all of them, or (when anything fails before the renames) none.

    Each :meth:`AtomicFiles.path` gives a temporary file for one target. When the block ends normally every
    temporary file is fsynced, then each is renamed onto its target and the folders are fsynced; when the block,
    a sync or a rename raises (``KeyboardInterrupt`` too), the temporary files not yet renamed are removed and
    the exception propagates. Until the renames nothing under a target's name has changed, so a failed block
    leaves every old file as it was; only a rename failing half way (which a full disk or a permission error
    cannot cause: the data are already written) could leave some targets new and some old.

    Yields:
        The set of pending files.
    """
    files = AtomicFiles()
    pending = files._pending
    try:
        yield files
        for tmp, _, _, mode in pending:
            # A writer may have replaced the file rather than overwritten it (safetensors' save_file does, with
            # mode 0o600): the target gets the permissions the umask gave the file this block created.
            if stat.S_IMODE(os.stat(tmp).st_mode) != mode:
                os.chmod(tmp, mode)
            _fsync_file(tmp)
        while pending:
            tmp, target, lock, _ = pending[0]
            _commit(tmp, target)
            pending.pop(0)
            os.close(lock)
    except BaseException:
        for tmp, _, lock, _ in pending:
            _discard(tmp, lock)
        raise


@contextlib.contextmanager
def atomic_path(path: str | os.PathLike[str]) -> Iterator[Path]:
    """Replace the file ``path`` atomically with the file written to the yielded temporary name.

    For writers that take a file name and pick the format by its suffix (PIL, imageio, matplotlib, trimesh):
    the temporary file is ``.NAME.XXXXXXXXXXXX.tmpSUFFIX`` beside the target, with the target's suffix (e.g.
    ``.room.png.0123456789ab.tmp.png``), created empty before the block runs. When the block ends normally the
    file is fsynced, renamed onto ``path`` and the folder fsynced; when anything raises, including
    ``KeyboardInterrupt``, the temporary file is removed and the old file stays as it was (as for
    :func:`atomic_write`). One file of :func:`atomic_files`.

    Args:
        path: the file to write; its folder must exist.

    Yields:
        The temporary file's path; the block must write it (overwriting the empty file) and close it.

    Raises:
        OSError: the file cannot be written or replaced.
    """
    with atomic_files() as files:
        yield files.path(path)


# ---------------------------------------------------------------------------------------------------- strict reading
def describe_read_error(e: BaseException) -> str:
    """The problem, in words, behind an exception raised while reading an archive strictly.

    Args:
        e: an :class:`ArchiveError` (its message), or anything that zipfile, zlib or the file system raise on a
            damaged or unreadable file.

    Returns:
        E.g. ``"truncated file (unexpected end of data)"`` or ``"corrupt zip archive (Bad CRC-32 ...)"``.
    """
    if isinstance(e, ArchiveError):
        return str(e)
    if isinstance(e, (zipfile.BadZipFile, zipfile.LargeZipFile)):
        return f"corrupt zip archive ({e})"
    if isinstance(e, EOFError):
        return "truncated file (unexpected end of data)"
    if isinstance(e, MemoryError):
        return "not enough memory to read it"
    if isinstance(e, OSError):
        return f"read error ({e.strerror or e})"
    # Anything else a damaged archive can provoke in zipfile or zlib (bad CRC, unknown compression, encryption,
    # struct errors) is still a damaged file.
    return f"corrupt file ({type(e).__name__}: {e})"


def open_archive(fileobj: IO[bytes]) -> zipfile.ZipFile:
    """Open a zip (npz) archive for reading.

    Args:
        fileobj: the file, opened in binary mode at its start; it must stay open while the archive is used.

    Returns:
        The archive.

    Raises:
        ArchiveError: not a zip archive, or one whose central directory is missing (a truncated file).
    """
    head = fileobj.read(4)
    fileobj.seek(0)
    try:
        return zipfile.ZipFile(fileobj)
    except zipfile.BadZipFile:
        if head == b"PK\x03\x04":
            raise ArchiveError("truncated or corrupt zip archive (no readable central directory)") from None
        raise ArchiveError("not an npz file (not a zip archive)") from None


class NpyMember:
    """An npy member of an open archive whose header has been parsed and checked, positioned at its data.

    Made by :func:`open_npy_member`. The caller checks :attr:`dtype` and :attr:`shape` (and any size limit of
    its own) and only then calls :meth:`read` or :meth:`read_array`, which read exactly the bytes the header
    announces; nothing is allocated by size before that. Close it (or use it as a context manager).
    """

    shape: tuple[int, ...]
    """The array shape the header announces."""
    fortran_order: bool
    """Whether the data are in Fortran (column-major) order."""
    dtype: np.dtype
    """The array dtype the header announces (never an object dtype: those are refused on opening)."""
    header_len: int
    """Length of the npy magic string and header, in bytes."""

    def __init__(self, zf: zipfile.ZipFile, name: str) -> None:
        self.key = name[:-4] if name.endswith(".npy") else name
        """The member's name without ``.npy``, as error messages name it."""
        self._info = zf.getinfo(name)
        self._file = zf.open(name)
        try:
            self.shape, self.fortran_order, self.dtype, self.header_len = self._parse()
        except BaseException:
            self._file.close()
            raise

    def _parse(self) -> tuple[tuple[int, ...], bool, np.dtype, int]:
        key, f = self.key, self._file
        # Only ValueError means a bad npy member; zip-level errors (bad CRC, truncation) go up to the reader.
        try:
            version = npy_format.read_magic(f)
        except ValueError:
            raise ArchiveError(f"member {key!r} is not an npy array (bad magic string)") from None
        if version not in ((1, 0), (2, 0)):
            raise ArchiveError(f"member {key!r} has unsupported npy format version {version}")
        try:
            if version == (1, 0):
                shape, fortran, dtype = npy_format.read_array_header_1_0(f)
            else:
                shape, fortran, dtype = npy_format.read_array_header_2_0(f)
        except (ValueError, TypeError, SyntaxError) as e:
            problem = f"member {key!r} has a malformed npy header ({e})"
        else:
            if dtype.hasobject:
                problem = f"member {key!r} is an object array (refused: loading it would need pickle)"
            else:
                return tuple(shape), bool(fortran), dtype, f.tell()
        raise ArchiveError(problem)

    @property
    def nbytes(self) -> int:
        """Data bytes the header announces: the product of :attr:`shape` times the item size (a Python int, so
        an absurd header cannot overflow it)."""
        n = self.dtype.itemsize
        for s in self.shape:
            n *= s
        return n

    def read(self) -> bytes:
        """Exactly the :attr:`nbytes` data bytes, after checking the member's stored size agrees with the header.

        Raises:
            ArchiveError: a truncated member, or one with data beyond (or a stored size other than) what the
                header announces. Damaged compressed data raise zipfile's or zlib's own errors.
        """
        key, nbytes = self.key, self.nbytes
        if self._info.file_size != self.header_len + nbytes:
            raise ArchiveError(f"member {key!r} holds {self._info.file_size} bytes but its header announces "
                               f"{self.header_len + nbytes} (truncated or inconsistent)")
        # Reading at most one byte more than announced bounds memory by the header (already checked) and shows
        # both truncated and over-long members; zipfile verifies the CRC when the member ends.
        data = self._file.read(nbytes + 1)
        if len(data) < nbytes:
            raise ArchiveError(f"member {key!r} is truncated: {len(data)} of {nbytes} data bytes")
        if len(data) > nbytes or self._file.read(1):
            raise ArchiveError(f"member {key!r} has trailing data after its {nbytes} data bytes")
        return data

    def read_array(self) -> np.ndarray:
        """The array of :attr:`shape` and :attr:`dtype` in the member's memory order: new and writable, read into
        its own buffer :data:`READ_CHUNK` bytes at a time, so that memory holds the data once (not the bytes and
        then the array). The checks are :meth:`read`'s. Not for item size 0 (e.g. ``<U0``).

        Raises:
            ArchiveError: as :meth:`read`.
        """
        key, nbytes = self.key, self.nbytes
        if self._info.file_size != self.header_len + nbytes:
            raise ArchiveError(f"member {key!r} holds {self._info.file_size} bytes but its header announces "
                               f"{self.header_len + nbytes} (truncated or inconsistent)")
        buf = np.empty(nbytes, dtype=np.uint8)
        view = memoryview(buf)
        got = 0
        while got < nbytes:
            n = self._file.readinto(view[got:got + READ_CHUNK])
            if not n:
                raise ArchiveError(f"member {key!r} is truncated: {got} of {nbytes} data bytes")
            got += n
        # The end of the member: zipfile verifies its CRC here.
        if self._file.read(1):
            raise ArchiveError(f"member {key!r} has trailing data after its {nbytes} data bytes")
        order = "F" if self.fortran_order else "C"
        return buf.view(self.dtype).reshape(self.shape, order=order)

    def close(self) -> None:
        """Close the member's stream (idempotent)."""
        self._file.close()

    def __enter__(self) -> NpyMember:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def open_npy_member(zf: zipfile.ZipFile, name: str) -> NpyMember:
    """Open the npy member ``name`` of ``zf`` and parse its header, refusing object arrays (no pickle).

    Args:
        zf: the open archive.
        name: the member's name in the archive, e.g. ``"labels.npy"``; it must exist.

    Returns:
        The open member, positioned at its data (see :class:`NpyMember`).

    Raises:
        ArchiveError: not an npy member (bad magic string), an unsupported npy version, a malformed header, or
            an object dtype.
    """
    return NpyMember(zf, name)


def read_npy_member(zf: zipfile.ZipFile, name: str, dtype: np.dtype | type, shape: tuple[int, ...]) -> np.ndarray:
    """Read the npy member ``name`` of ``zf``, which must hold exactly a C-ordered ``shape`` ``dtype`` array.

    The header is checked before any data is read, so a member announcing another (or an absurd) size costs
    nothing.

    Args:
        zf: the open archive.
        name: the member's name in the archive, e.g. ``"pose_00000.npy"``.
        dtype: the dtype required (byte order included).
        shape: the shape required.

    Returns:
        A new, writable ``shape`` array of ``dtype``.

    Raises:
        ArchiveError: an object array, another dtype, shape or memory order, or a truncated or over-long member
            (see :func:`open_npy_member`, :meth:`NpyMember.read`).
    """
    dtype = np.dtype(dtype)
    with open_npy_member(zf, name) as m:
        if m.dtype != dtype or m.shape != tuple(shape) or m.fortran_order:
            raise ArchiveError(f"member {m.key!r} is {m.shape} {m.dtype}{' (Fortran order)' if m.fortran_order else ''}"
                               f", expected {tuple(shape)} {dtype}")
        return m.read_array()


# ---------------------------------------------------------------------------------------------------- memory
def _meminfo_available() -> int | None:
    try:
        with open("/proc/meminfo", encoding="ascii") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    try:
        return os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
    except (AttributeError, OSError, ValueError):
        return None


def _read_number(path: str) -> int | None:
    try:
        with open(path, encoding="ascii") as f:
            text = f.read().strip()
        return int(text) if text.isdigit() else None  # "max": no limit
    except (OSError, ValueError):
        return None


def _cgroup_available() -> int | None:
    """Memory left under this process's control group limit (cgroup v2, else v1), None without a limit."""
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        limit, usage = _read_number(limit_file), _read_number(usage_file)
        if limit is not None and usage is not None and limit < 1 << 60:
            return max(0, limit - usage)
    return None


def _address_space_available() -> int | None:
    """Address space left under this process's ``RLIMIT_AS`` (``ulimit -v``), None without a limit."""
    try:
        import resource

        limit = resource.getrlimit(resource.RLIMIT_AS)[0]
        if limit == resource.RLIM_INFINITY:
            return None
        with open("/proc/self/statm", encoding="ascii") as f:
            used = int(f.read().split()[0]) * os.sysconf("SC_PAGE_SIZE")
        return max(0, limit - used)
    except (ImportError, OSError, ValueError, IndexError, AttributeError):
        return None


def available_memory() -> int | None:
    """Bytes of memory this process can still allocate: the system's estimate of available memory (Linux's
    ``MemAvailable``: free memory plus the caches it can drop), within this process's control group limit and
    address-space limit (``ulimit -v``) where they are set. None where nothing is known (then nothing is refused
    for memory)."""
    known = [m for m in (_meminfo_available(), _cgroup_available(), _address_space_available()) if m is not None]
    return min(known) if known else None


def format_bytes(n: float) -> str:
    """``n`` bytes in words, e.g. ``"4.3 GB"`` (decimal units)."""
    for unit in ("bytes", "kB", "MB", "GB"):
        if abs(n) < 1000 or unit == "GB":
            return f"{n:.0f} {unit}" if unit == "bytes" else f"{n:.1f} {unit}"
        n /= 1000
    return f"{n:.1f} GB"


def check_memory(need: int, what: str) -> None:
    """Refuse work that needs more memory than :func:`available_memory` before anything is allocated.

    Args:
        need: bytes the work needs.
        what: the work, in words, e.g. ``"its (1024, 2048, 2048) labels"``; the message reads "WHAT need(s) ...".

    Raises:
        MemoryLimitError: ``need`` exceeds the memory available.
    """
    have = available_memory()
    if have is not None and need > have:
        raise MemoryLimitError(f"{what} need {format_bytes(need)} of memory, more than the {format_bytes(have)} "
                               "available")


class MemoryLimitError(FruxelError, MemoryError):
    """Work refused because it needs more memory than this machine has available (:func:`check_memory`)."""


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


def save(path: str | os.PathLike[str], model: FruxelModel) -> None:
    """Write ``model`` to ``path`` atomically (format in the module docstring).

    The name is used as given (no ``.npz`` is appended). An existing file is replaced only once the new one is
    complete and synced; on any failure the old file is left as it was and the temporary file is removed
    (:func:`atomic_write`).

    Args:
        path: target file name.
        model: the model to write.

    Raises:
        TypeError: ``model`` is not a :class:`FruxelModel`.
        OSError: the file cannot be written (the target is a directory, no permission, disk full).
    """
    if not isinstance(model, FruxelModel):
        raise TypeError(f"save() needs a FruxelModel, got {type(model).__name__}")
    with atomic_write(path) as f:
        _write_npz(f, model)


# ---------------------------------------------------------------------------------------------------- load
def _listing(missing: list[str], extra: list[str]) -> str:
    parts = ([f"missing {missing}"] if missing else []) + ([f"unexpected or repeated {extra}"] if extra else [])
    return ": " + ", ".join(parts)


def read_json_member(zf: zipfile.ZipFile, name: str, max_chars: int) -> Any:
    """The JSON value stored in member ``name.npy`` as a 0-d string (unicode, or UTF-8 bytes), read without
    pickle and with a size limit checked before anything is read.

    Raises:
        ArchiveError: a member that is not a 0-d string, longer than ``max_chars``, not UTF-8 or not JSON.
    """
    with open_npy_member(zf, f"{name}.npy") as m:
        dtype, shape = m.dtype, m.shape
        if dtype.kind not in "US" or dtype.fields is not None:
            raise ArchiveError(f"member {name!r} has dtype {dtype}, expected a unicode string")
        if shape != ():
            raise ArchiveError(f"member {name!r} has shape {shape}, expected a 0-d string")
        chars = dtype.itemsize // 4 if dtype.kind == "U" else dtype.itemsize
        if chars > max_chars:
            raise ArchiveError(f"member {name!r} is too large: {chars} characters, limit {max_chars}")
        raw = m.read()
    value = np.frombuffer(raw, dtype=dtype, count=1)[0] if dtype.itemsize else dtype.type()
    if dtype.kind == "S":
        try:
            text = bytes(value).decode("utf-8")
        except UnicodeDecodeError:
            raise ArchiveError(f"member {name!r} is not valid UTF-8") from None
    else:
        text = str(value)
    try:
        return json.loads(text)
    except (ValueError, RecursionError) as e:
        problem = f"{name} is not valid JSON ({e})"
    raise ArchiveError(problem)


def _check_meta(meta: Any, format_name: str = FORMAT_NAME) -> tuple[FruxelGrid, ClassTable]:
    if not isinstance(meta, dict):
        raise ArchiveError(f"meta must be a JSON object, got {type(meta).__name__}")
    missing = [k for k in _META_KEYS if k not in meta]
    extra = sorted(str(k) for k in set(meta) - set(_META_KEYS))
    if missing or extra:
        raise ArchiveError(f"wrong meta keys{_listing(missing, extra)}")
    if meta["format"] != format_name:
        raise ArchiveError(f"meta format is {meta['format']!r}, expected {format_name!r}")
    version = meta["version"]
    if isinstance(version, bool) or not isinstance(version, int):
        raise ArchiveError(f"meta version must be an integer, got {version!r}")
    if version != FORMAT_VERSION:
        raise ArchiveError(f"unsupported format version {version} (this fruxel reads version {FORMAT_VERSION})")
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
    raise ArchiveError(problem)


def _read_labels(zf: zipfile.ZipFile, grid: FruxelGrid, classes: ClassTable) -> np.ndarray:
    with open_npy_member(zf, "labels.npy") as m:
        shape = m.shape
        if m.dtype != np.dtype(np.uint8):
            raise ArchiveError(f"member 'labels' has dtype {m.dtype}, expected uint8")
        if len(shape) != 3:
            raise ArchiveError(f"member 'labels' has {len(shape)} dimensions (shape {shape}), expected 3 (D, H, W)")
        cells = m.nbytes  # uint8: one byte per cell
        if cells > MAX_CELLS:
            raise ArchiveError(f"member 'labels' header claims {cells} cells (shape {shape}), more than the "
                               f"limit {MAX_CELLS}")
        if shape != grid.shape:
            raise ArchiveError(f"member 'labels' has shape {shape} but the grid in meta has (D, H, W) = {grid.shape}")
        # Read into a buffer, then copied by FruxelModel: twice the labels at once.
        _check_memory(2 * cells, f"its {grid.width}x{grid.height}x{grid.depth} grid's labels")
        labels = m.read_array()
    top = int(labels.max()) if labels.size else 0
    if top >= len(classes):
        raise ArchiveError(f"label value {top} is out of range for the {len(classes)} classes in meta")
    return labels


def _check_memory(need: int, what: str) -> None:
    """:func:`check_memory` as an :class:`ArchiveError` (the reader names the file)."""
    try:
        check_memory(need, what)
    except MemoryLimitError as e:
        problem = str(e)
    else:
        return
    raise ArchiveError(problem)


def _open_file(path: str) -> IO[bytes]:
    try:
        f = open(path, "rb")
    except FileNotFoundError:
        raise ArchiveError("no such file") from None
    except IsADirectoryError:
        raise ArchiveError("it is a directory, not a file") from None
    except OSError as e:
        raise ArchiveError(f"cannot open it ({e.strerror or e})") from None
    if os.path.isdir(path):
        f.close()
        raise ArchiveError("it is a directory, not a file")
    return f


def _check_members(zf: zipfile.ZipFile, expected: tuple[str, ...]) -> None:
    names = zf.namelist()
    if sorted(names) == sorted(expected):
        return
    # The other kind of fruxel file gets a pointer to its reader rather than a list of keys.
    if sorted(names) == sorted(_LOGITS_MEMBERS):
        raise ArchiveError("it is a logits file, not a model (fruxel.load_logits reads it)")
    if sorted(names) == sorted(_MEMBERS):
        raise ArchiveError("it is a fruxel model file (labels), not logits (fruxel.load reads it)")
    missing = [m[:-4] for m in expected if m not in names]
    extra = sorted({n for n in names if n not in expected} | {n for n in names if names.count(n) > 1})
    wanted = " and ".join(repr(m[:-4]) for m in expected)
    raise ArchiveError(f"wrong keys{_listing(missing, extra)}; expected exactly {wanted}")


def file_kind(path: str | os.PathLike[str]) -> str | None:
    """What a file is, from its archive's member names alone: ``"model"`` (:func:`load`), ``"logits"``
    (:func:`load_logits`), or None for anything else (including a missing or unreadable file, which the
    loaders then report properly). Reads only the zip directory."""
    try:
        with open(path, "rb") as f, open_archive(f) as zf:
            names = sorted(zf.namelist())
    except Exception:  # noqa: BLE001 - any file that cannot be opened as an archive is neither kind
        return None
    return {tuple(sorted(_MEMBERS)): "model", tuple(sorted(_LOGITS_MEMBERS)): "logits"}.get(tuple(names))


def read_header(path: str | os.PathLike[str]) -> tuple[str, FruxelGrid, ClassTable]:
    """What a model or logits file holds, from its meta alone (the labels or logits are not read): to check a
    file before the work it is for.

    Returns:
        ``(kind, grid, classes)``, kind ``"model"`` or ``"logits"`` (:func:`file_kind`).

    Raises:
        FruxelFileError: neither kind of file, or bad meta; the message names the file.
    """
    name = os.fsdecode(path)
    kind = file_kind(name) or "model"
    label = "fruxel model" if kind == "model" else "logits file"
    members, format_name = (_MEMBERS, FORMAT_NAME) if kind == "model" else (_LOGITS_MEMBERS, LOGITS_FORMAT_NAME)
    grid, classes = _read_strictly(name, label, members, format_name, lambda zf, g, c: (g, c))
    return kind, grid, classes


def _read_strictly(path: str | os.PathLike[str], kind: str, members: tuple[str, ...], format_name: str,
                   read: Callable[[zipfile.ZipFile, FruxelGrid, ClassTable], T]) -> T:
    """Open a fruxel archive, check its members and meta, and return ``read(zf, grid, classes)``; any problem
    becomes one :class:`FruxelFileError` naming the file, with no chained exception."""
    name = os.fsdecode(path)
    try:
        with _open_file(name) as f, open_archive(f) as zf:
            _check_members(zf, members)
            grid, classes = _check_meta(read_json_member(zf, "meta", MAX_META_CHARS), format_name)
            return read(zf, grid, classes)
    except Exception as e:
        # Whatever a damaged archive provokes is still a damaged file, and the caller gets the one documented error.
        problem = describe_read_error(e)
    raise FruxelFileError(name, problem, kind)


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
    return _read_strictly(path, "fruxel model", _MEMBERS, FORMAT_NAME,
                          lambda zf, grid, classes: FruxelModel(_read_labels(zf, grid, classes), grid, classes))


# ---------------------------------------------------------------------------------------------------- logits
@dataclass(frozen=True, eq=False)
class LogitsFile:
    """The contents of a logits file (:func:`load_logits`): a network's scores for one image, with their grid and
    classes."""

    logits: np.ndarray
    """``(C, D, H, W)`` float16 or float32, C-contiguous, writable, machine byte order, all finite; channel 0 =
    empty."""
    grid: FruxelGrid
    """The grid of the logits' ``(D, H, W)``."""
    classes: ClassTable
    """The C classes of the channels."""

    def labels(self, threshold: float | None = None) -> np.ndarray:
        """Labels ``(D, H, W)`` uint8 by the occupancy rule of :func:`fruxel.labels_from_scores`."""
        return labels_from_scores(self.logits, threshold=threshold, axis=0)

    def to_model(self, threshold: float | None = None) -> FruxelModel:
        """The :class:`FruxelModel` of :meth:`labels`."""
        return FruxelModel(self.labels(threshold), self.grid, self.classes)


def _as_numpy(x: Any) -> np.ndarray:
    if hasattr(x, "detach") and hasattr(x, "cpu"):
        # A torch tensor (on any device), read without importing torch here.
        x = x.detach().cpu().numpy()
    return np.asarray(x)


def _check_logits(logits: Any, grid: Any, classes: Any) -> np.ndarray:
    if not isinstance(grid, FruxelGrid):
        raise ModelError(f"save_logits() needs a FruxelGrid, got {type(grid).__name__}")
    if not isinstance(classes, ClassTable):
        raise ModelError(f"save_logits() needs a ClassTable, got {type(classes).__name__}")
    try:
        arr = _as_numpy(logits)
    except (TypeError, ValueError, RuntimeError) as e:
        raise ModelError(f"logits must be a numpy array, got {type(logits).__name__} ({e})") from None
    if arr.dtype.newbyteorder("=") not in LOGITS_DTYPES:
        raise ModelError(f"logits must be float16 or float32, got dtype {arr.dtype} (convert with .astype)")
    want = (len(classes), *grid.shape)
    if arr.shape != want:
        raise ModelError(f"logits must have shape (C, D, H, W) = {want} for {len(classes)} classes and the grid's "
                         f"(D, H, W), got {arr.shape}")
    if not np.all(np.isfinite(arr)):
        raise ModelError("logits contain NaN or infinite values")
    return np.ascontiguousarray(arr, dtype=arr.dtype.newbyteorder("="))


def save_logits(path: str | os.PathLike[str], logits: Any, grid: FruxelGrid, classes: ClassTable) -> None:
    """Write a logits file (format in the module docstring) atomically.

    Args:
        path: target file name, used as given (``.npz`` by convention).
        logits: ``(C, D, H, W)`` float16 or float32 scores, channel 0 = empty; a numpy array (or a torch tensor,
            copied to the host). Stored in that dtype.
        grid: the grid of ``(D, H, W)``.
        classes: the C classes of the channels.

    Raises:
        ModelError: not a grid or class table, another dtype, a shape other than ``(len(classes), *grid.shape)``,
            or NaN or infinite values.
        OSError: the file cannot be written.
    """
    arr = _check_logits(logits, grid, classes)
    meta = json.dumps({"format": LOGITS_FORMAT_NAME, "version": FORMAT_VERSION, "grid": grid.to_dict(),
                       "classes": classes.to_dict()}, ensure_ascii=False)
    with atomic_write(path) as f:
        np.savez(f, logits=arr, meta=np.array(meta, dtype=np.str_))


def _read_logits(zf: zipfile.ZipFile, grid: FruxelGrid, classes: ClassTable) -> np.ndarray:
    with open_npy_member(zf, "logits.npy") as m:
        shape, dtype = m.shape, m.dtype
        if dtype.newbyteorder("=") not in LOGITS_DTYPES:
            raise ArchiveError(f"member 'logits' has dtype {dtype}, expected float16 or float32")
        if len(shape) != 4:
            raise ArchiveError(f"member 'logits' has {len(shape)} dimensions (shape {shape}), expected 4 "
                               f"(C, D, H, W)")
        if m.nbytes > MAX_LOGITS_BYTES:
            raise ArchiveError(f"member 'logits' header claims {m.nbytes} bytes (shape {shape}), more than the limit "
                               f"{MAX_LOGITS_BYTES}")
        want = (len(classes), *grid.shape)
        if shape != want:
            raise ArchiveError(f"member 'logits' has shape {shape} but meta's {len(classes)} classes and grid "
                               f"(D, H, W) = {grid.shape} need {want}")
        _check_memory(m.nbytes, f"its {grid.width}x{grid.height}x{grid.depth} grid's {len(classes)} logits a cell")
        logits = m.read_array()
    if not np.all(np.isfinite(logits)):
        raise ArchiveError("the logits contain NaN or infinite values")
    # A writable, C-ordered copy in the machine's byte order (torch.from_numpy and the kernels take it as it is).
    return np.require(logits, dtype=dtype.newbyteorder("="), requirements=["C", "W"])


def load_logits(path: str | os.PathLike[str]) -> LogitsFile:
    """Read a logits file written by :func:`save_logits`, without pickle, as strictly as :func:`load`.

    Args:
        path: the file name.

    Returns:
        The logits ``(C, D, H, W)``, their grid and classes.

    Raises:
        FruxelFileError: the file is missing, unreadable, or not a valid logits file (a model file, wrong members,
            an object array, another dtype, ndim or shape, a header claiming an absurd size, bad meta, NaN or
            infinite values). One error naming the file and the problem.
    """
    return _read_strictly(path, "logits file", _LOGITS_MEMBERS, LOGITS_FORMAT_NAME,
                          lambda zf, grid, classes: LogitsFile(_read_logits(zf, grid, classes), grid, classes))

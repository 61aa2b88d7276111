"""Arrays derived from the asset pack's files (texture layers with their mip levels, a texture's mean colour), made
once per machine and kept as ``.npy`` files that every process of the simulator reads.

Why: decoding a texture and building its mip levels takes tens of milliseconds, and each of the simulator's worker
processes met every texture for the first time on its own: 15 workers of a streamed training decoded the same
textures 15 times, and that was half of a sample's time for minutes (BENCHMARKS.md, "## Simulator"). A file read
from the page cache takes a fraction of a millisecond.

Where: ``cache_folder() / "pack"`` (:func:`fruxel.io.cache_folder`: ``$FRUXEL_CACHE_DIR``, else
``$XDG_CACHE_HOME/fruxel``, else ``~/.cache/fruxel``), one file per array, named by what it is made from: the
SHA-256 of the source file (from the pack's manifest, so that a changed file is a new name and no stale array is
ever read), the parameters, and a digest of the module that computes it (:func:`code_digest`, so that changed code
makes new arrays). Files are written atomically (:func:`fruxel.io.atomic_write`); processes that make the same array
at once write the same bytes. A file that does not read back as the shape and dtype asked for is made again. When
the folder cannot be written the arrays are computed in every process as before, after one warning.
"""

from __future__ import annotations

import hashlib
import sys
import warnings
from collections.abc import Callable
from pathlib import Path

import numpy as np

_DIGESTS: dict[str, str] = {}


def code_digest(module: str) -> str:
    """The first 12 hex digits of the SHA-256 of a module's source file (part of a derived array's name)."""
    if module not in _DIGESTS:
        path = Path(sys.modules[module].__file__ or "")
        _DIGESTS[module] = hashlib.sha256(path.read_bytes()).hexdigest()[:12]
    return _DIGESTS[module]


class DerivedArrays:
    """A folder of derived arrays (module docstring).

    Args:
        folder: where the arrays live; None: ``cache_folder() / "pack"``.
    """

    def __init__(self, folder: str | Path | None = None) -> None:
        from fruxel.io import cache_folder

        self.folder: Path | None = Path(folder) if folder is not None else cache_folder() / "pack"
        """The folder, or None once it proved unwritable (arrays are then computed every time)."""

    def get(self, name: str, shape: tuple[int, ...], dtype: np.dtype | type,
            compute: Callable[[], np.ndarray]) -> np.ndarray:
        """The array called ``name``: read from the folder, else ``compute()``-d and written there.

        Args:
            name: the file name without ``.npy``: everything the array depends on (module docstring).
            shape: the array's shape, -1 where any size goes; a file of another shape or dtype is made again.
            dtype: the array's dtype.
            compute: makes the array (called only when the file is missing or wrong).

        Returns:
            The array, ``shape`` and ``dtype``, C-ordered.
        """
        dtype = np.dtype(dtype)
        path = None if self.folder is None else self.folder / f"{name}.npy"
        if path is not None:
            try:
                a = np.load(path, allow_pickle=False)
                if _fits(a.shape, shape) and a.dtype == dtype:
                    return a
            except (OSError, ValueError, EOFError):
                pass  # missing or damaged: made again below
        a = np.ascontiguousarray(compute(), dtype=dtype)
        if not _fits(a.shape, shape):
            raise ValueError(f"derived array {name!r} was computed with shape {a.shape}, expected {tuple(shape)}")
        if path is not None:
            self._write(path, a)
        return a

    def _write(self, path: Path, a: np.ndarray) -> None:
        from fruxel.io import atomic_write

        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with atomic_write(path) as f:
                np.save(f, a, allow_pickle=False)
        except OSError as e:
            warnings.warn(f"{path.parent}: cannot keep the asset pack's decoded textures there ({e.strerror or e}); "
                          "each process decodes them itself (set FRUXEL_CACHE_DIR to a writable folder)",
                          RuntimeWarning, stacklevel=3)
            self.folder = None


def _fits(shape: tuple[int, ...], wanted: tuple[int, ...]) -> bool:
    """Whether ``shape`` is ``wanted``, where a -1 in ``wanted`` takes any size."""
    return len(shape) == len(wanted) and all(w in (-1, s) for s, w in zip(shape, wanted, strict=True))


_SHARED: dict[str, DerivedArrays] = {}


def derived_arrays() -> DerivedArrays:
    """The process's :class:`DerivedArrays` of the current cache folder (one per folder, made on first use)."""
    from fruxel.io import cache_folder

    key = str(cache_folder() / "pack")
    if key not in _SHARED:
        _SHARED[key] = DerivedArrays(key)
    return _SHARED[key]

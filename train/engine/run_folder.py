"""A run's folder: the files a run writes there, one run at a time (a lock), and never a run overwritten by
accident.

::

    run_dir/config.json        the full training config (also inside every checkpoint)
    run_dir/last.pt            the newest checkpoint (atomic; ``--resume`` continues from it)
    run_dir/model.safetensors  the shipped form of the newest network (float16, config in the metadata)
    run_dir/metrics.csv        losses, learning rate, samples/s and evaluations per step
    run_dir/curves.png         training curves
    run_dir/examples.png       image | own view truth, prediction | novel view truth, prediction
    run_dir/tensorboard/       when TensorBoard is installed
    run_dir/.lock              held (``flock``) by the process training there; names it
"""

from __future__ import annotations

import errno
import os
import shutil

from fruxel.io import remove_stale_temporaries

from .checkpoint import LATEST
from .logbook import CURVES, METRICS
from .state import TrainingError

CONFIG = "config.json"
"""File name of the config in a run folder."""
SHIPPED = "model.safetensors"
"""File name of the shipped model in a run folder."""
EXAMPLES = "examples.png"
"""File name of the examples picture in a run folder."""
TENSORBOARD = "tensorboard"
"""Folder of the TensorBoard event files in a run folder."""
LOCK = ".lock"
"""File name of the lock in a run folder."""
RUN_FILES = (CONFIG, LATEST, SHIPPED, METRICS, CURVES, EXAMPLES)
"""The files a run writes."""


class RunFolder:
    """The folder of one run.

    Args:
        path: the folder (made by :meth:`claim` when missing).
    """

    def __init__(self, path: str | os.PathLike[str]) -> None:
        self.path = os.fsdecode(path)
        """The folder."""
        self._lock: int | None = None

    def file(self, name: str) -> str:
        """The path of ``name`` in the folder."""
        return os.path.join(self.path, name)

    def holds_run(self) -> list[str]:
        """The run files present (empty for a new or empty folder)."""
        return [n for n in RUN_FILES if os.path.exists(self.file(n))]

    def check(self, *, resume: bool, overwrite: bool = False) -> None:
        """Refuse what would lose or mix up runs, before anything is written (every distributed rank calls it).

        Raises:
            TrainingError: ``--resume`` without a checkpoint; a new run into a folder that holds one, unless
                ``overwrite``; a path that is not a folder.
        """
        if os.path.exists(self.path) and not os.path.isdir(self.path):
            raise TrainingError(f"{self.path}: not a folder")
        if resume:
            if not os.path.isfile(self.file(LATEST)):
                raise TrainingError(f"{self.file(LATEST)}: no checkpoint to resume from")
            return
        present = self.holds_run()
        if present and not overwrite:
            raise TrainingError(f"{self.path}: holds a run ({', '.join(present)}); continue it with --resume, replace "
                                "it with --overwrite, or choose another --out")

    def claim(self, *, resume: bool, overwrite: bool = False) -> None:
        """Make the folder, take its lock, then (a new run with ``overwrite``) remove the earlier run's files, and
        remove the temporary files of writers that were killed (rank 0 only).

        Raises:
            TrainingError: another process holds the lock; see :meth:`check`.
        """
        self.check(resume=resume, overwrite=overwrite)
        os.makedirs(self.path, exist_ok=True)
        self._take_lock()
        if not resume and overwrite:
            for name in self.holds_run():
                os.remove(self.file(name))
            shutil.rmtree(self.file(TENSORBOARD), ignore_errors=True)
        for name in RUN_FILES:
            # The lock is held: no other writer is alive here, so every temporary file is stale.
            remove_stale_temporaries(self.file(name), min_age=0.0)

    def _take_lock(self) -> None:
        import fcntl

        fd = os.open(self.file(LOCK), os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError as e:
            holder = os.read(fd, 64).decode("ascii", "replace").strip() or "?"
            os.close(fd)
            if e.errno in (errno.EWOULDBLOCK, errno.EACCES):
                raise TrainingError(f"{self.path}: another run is training here (process {holder}); wait for it to "
                                    "end or choose another --out") from None
            raise
        os.ftruncate(fd, 0)
        os.write(fd, f"{os.getpid()}\n".encode())
        self._lock = fd

    def release(self) -> None:
        """Give the lock back (idempotent). The lock file stays: removing it could let two processes lock two
        different files of one name."""
        if self._lock is not None:
            os.close(self._lock)
            self._lock = None

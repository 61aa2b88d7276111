"""Training checkpoints: one ``.pt`` file per save, written atomically and read without pickle.

A checkpoint is a dict of tensors, numbers, strings, lists and dicts only (``torch.load(weights_only=True)``
refuses anything else, so a file holding a pickled object is rejected without running it)::

    {"format": "fruxel-ssz-checkpoint", "version": 1, "config": TrainConfig JSON text,
     "step": int, "samples": int, "generator": state_dict, "discriminator": state_dict or None,
     "optimizer": ..., "d_optimizer": ... or None, "scheduler": ..., "data": {"position": [block, used]},
     "class_weights": (C,) float32, "rng": {"torch": ..., "cuda": [...]},
     "shell_poses": ..., "replay": ..., "summary": {...}, "losses": {...} (the last logged),
     "elapsed": seconds of training}
"""

from __future__ import annotations

import os
import pickle
import re
import zipfile
from dataclasses import dataclass
from typing import Any

import torch

from fruxel.errors import FruxelError
from fruxel.io import atomic_path

from ..config import ConfigError, TrainConfig

FORMAT = "fruxel-ssz-checkpoint"
"""``format`` of a checkpoint."""
VERSION = 1
"""Version of the checkpoint layout."""
LATEST = "last.pt"
"""File name of the newest checkpoint in a run folder."""


class CheckpointError(FruxelError, ValueError):
    """A checkpoint that cannot be used; the message names the file and the problem."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        """The file."""
        self.problem = problem
        """What is wrong, in words."""


@dataclass
class Checkpoint:
    """A checkpoint as read: its experiment config and the whole dict."""

    config: TrainConfig
    """The experiment the checkpoint belongs to."""
    state: dict[str, Any]
    """Everything saved (layout in the module docstring)."""


def rng_state() -> dict[str, Any]:
    """The states of torch's global generators (CPU and each CUDA device). Every other random draw of a run comes
    from a generator of its own, saved with its owner (shell-loss poses, replay draws); nothing draws from numpy's
    or Python's global generators."""
    return {"torch": torch.get_rng_state(),
            "cuda": list(torch.cuda.get_rng_state_all()) if torch.cuda.is_available() else []}


def set_rng_state(state: dict[str, Any]) -> None:
    """Restore :func:`rng_state`."""
    torch.set_rng_state(state["torch"])
    if torch.cuda.is_available() and state["cuda"]:
        torch.cuda.set_rng_state_all(state["cuda"])


def save_checkpoint(path: str | os.PathLike[str], state: dict[str, Any], config: TrainConfig) -> None:
    """Write a checkpoint atomically (a crash leaves the previous file or the new one, never part of one)."""
    full = {"format": FORMAT, "version": VERSION, "config": config.to_json(), **state}
    with atomic_path(path) as tmp:
        torch.save(full, tmp)


def read_checkpoint(path: str | os.PathLike[str], map_location: str | torch.device = "cpu") -> Checkpoint:
    """Read and check a checkpoint without unpickling anything but tensors and plain containers.

    Raises:
        CheckpointError: a missing or unreadable file, one holding objects (refused, never run), another format
            or version, or a bad config.
    """
    path = os.fsdecode(path)
    if not os.path.isfile(path):
        raise CheckpointError(path, "no such file" if not os.path.exists(path) else "not a regular file")
    try:
        state = torch.load(path, map_location=map_location, weights_only=True)
    except pickle.UnpicklingError as e:
        # torch's message suggests weights_only=False, which would run the file's code: only what was refused is
        # repeated ("Unsupported global: GLOBAL getattr was not an allowed global by default").
        m = re.search(r"WeightsUnpickler error: ([^.\n]*)", str(e))
        what = f" ({m.group(1).strip()})" if m else ""
        raise CheckpointError(path, f"refused: holds something other than tensors and plain data{what}; nothing "
                                    "in it was run") from None
    except (RuntimeError, EOFError, OSError, zipfile.BadZipFile, ValueError) as e:
        first = (str(e).strip().splitlines() or ["empty file" if os.path.getsize(path) == 0 else "no detail"])[0]
        raise CheckpointError(path, f"not a readable checkpoint ({type(e).__name__}: {first})") from None
    if not isinstance(state, dict) or state.get("format") != FORMAT:
        what = repr(state.get("format")) if isinstance(state, dict) else f"a {type(state).__name__}"
        raise CheckpointError(path, f"not a fruxel SSZ checkpoint (format {what})")
    if state.get("version") != VERSION:
        raise CheckpointError(path, f"checkpoint version {state.get('version')!r} is not {VERSION}")
    try:
        config = TrainConfig.from_json(state["config"])
    except (KeyError, TypeError, ConfigError) as e:
        raise CheckpointError(path, f"bad config inside ({e})") from None
    for key in ("step", "generator"):
        if key not in state:
            raise CheckpointError(path, f"missing {key!r}")
    return Checkpoint(config=config, state=state)

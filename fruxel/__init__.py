"""fruxel: semantic fruxel (frustum voxel) models of a scene from one image.

The core package is numpy-only: grid geometry (:class:`FruxelGrid`), viewing cameras (:class:`Camera`), the
model container (:class:`FruxelModel`), files (:func:`save`, :func:`load` for models; :func:`save_logits`,
:func:`load_logits` for a network's logits) and trapezoid meshing. Compute
kernels live in :mod:`fruxel.kernels`, display in :mod:`fruxel.render`, the network and simulator in
:mod:`fruxel.train`; they are imported on demand so that ``import fruxel`` stays light.
"""

from __future__ import annotations

import importlib
from typing import Any

from .camera import Camera, CameraError
from .classes import DEFAULT_CLASSES, HOME_CLASSES, ClassTable, ClassTableError
from .errors import FruxelError
from .grid import FruxelGrid, GridError
from .io import FruxelFileError, LogitsFile, load, load_logits, save, save_logits
from .mesh import TriMesh, export_mesh, mesh_labels
from .model import FruxelModel, ModelError, labels_from_scores

__version__ = "0.1.0"

__all__ = [
    "DEFAULT_CLASSES",
    "HOME_CLASSES",
    "Camera",
    "CameraError",
    "ClassTable",
    "ClassTableError",
    "FruxelError",
    "FruxelFileError",
    "FruxelGrid",
    "FruxelModel",
    "GridError",
    "LogitsFile",
    "ModelError",
    "TriMesh",
    "__version__",
    "export_mesh",
    "labels_from_scores",
    "load",
    "load_logits",
    "mesh_labels",
    "save",
    "save_logits",
]

_SUBMODULES = ("kernels", "render", "train")


def __getattr__(name: str) -> Any:
    # Sub-packages import torch / warp / pyrender; load them only when a user reaches for them.
    if name in _SUBMODULES:
        return importlib.import_module(f"fruxel.{name}")
    raise AttributeError(f"module 'fruxel' has no attribute {name!r}")

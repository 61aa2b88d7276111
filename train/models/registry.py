"""The architecture seam: what every image-to-fruxel network shares, and the registry that builds one by name.

A network architecture is a frozen config dataclass that derives from :class:`ModelConfig`, registered under a
name with :func:`register`. The config holds every setting of the architecture, validates itself once when it is
made (raising :class:`fruxel.errors.ConfigError` naming the key) and builds its network (:meth:`ModelConfig.build`).
A shipped model file names its architecture; loading looks the name up here (:func:`architecture`) and builds the
network from the stored config, so a new architecture needs no change to loading, training, calibration,
evaluation or prediction.

Every network honours one output contract, :class:`ModelOutput`: ``forward(image)`` takes ``(B, 3, h, w)`` float
RGB in [0, 1] of the grid's own camera at the config's :attr:`ModelConfig.image_size` and returns the cells' class
logits, plus the column heads the training objective and the inference rules read when the network has them. A
network whose config :attr:`ModelConfig.reads_camera` also takes ``forward(image, camera)``, what is known of the
camera (:func:`run_network` calls either).

This module imports no torch: configs are read and checked (``fruxel-train --print-config``, a file's metadata)
without loading the network code.
"""

from __future__ import annotations

import dataclasses
from collections.abc import Callable, Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, TypeVar

from fruxel.classes import HOME_CLASSES, ClassTable
from fruxel.errors import ConfigError
from fruxel.grid import FruxelGrid

if TYPE_CHECKING:
    import torch
    from torch import nn


@dataclass
class ModelOutput:
    """What every network's ``forward`` returns (the output contract).

    Attributes are tensors of the grid's shape ``(D, H, W)`` and the config's class table (C classes, 0 = empty), in
    the grid frame (conventions section 1: column ``(j, i)`` is pixel ``(i, j)`` of the grid's own camera).
    """

    logits: torch.Tensor
    """``(B, C, D, H, W)`` class logits of every cell, channel 0 = empty, in the compute dtype."""
    depth_logits: torch.Tensor | None = None
    """``(B, D + 1, H, W)`` float32 logits of each column's first occupied slice (bin D = no surface), or None for a
    network without a column depth head (the objective's ``depth`` term and the ``fill_columns`` rule need it)."""
    surface_logits: torch.Tensor | None = None
    """``(B, C, H, W)`` float32 logits of each column's first-surface class (0 = no surface), or None for a network
    without that head (the objective's ``surface`` term needs it)."""


@dataclass(frozen=True)
class ModelConfig:
    """What every architecture's config holds: the output grid and class table. Subclasses add their settings,
    validate them in :meth:`validate` and build their network in :meth:`build`."""

    NAME: ClassVar[str] = ""
    """The architecture's registry name (set by :func:`register`)."""

    grid: FruxelGrid = FruxelGrid(width=64, height=64, depth=64, z_near=0.5, z_far=8.0, hfov=60.0)
    """The output grid: shape ``(D, H, W)`` and the frustum it spans (the image's camera is the grid's own)."""
    classes: ClassTable = HOME_CLASSES
    """Class table of the output; C = ``len(classes.names)``, class 0 = empty. The default is the simulator's
    furnished rooms' (:data:`fruxel.classes.HOME_CLASSES`: the paper's six, ``ceiling`` and ``object``); the shipped
    ``ssz64`` and ``ssz128`` have the paper's six (:data:`fruxel.classes.DEFAULT_CLASSES`)."""

    def __post_init__(self) -> None:
        self.validate()

    def validate(self) -> None:
        """Raise :class:`~fruxel.errors.ConfigError` (naming ``model.KEY``) for an impossible setting."""
        if not isinstance(self.grid, FruxelGrid):
            raise ConfigError(f"model.grid must be a FruxelGrid, got {type(self.grid).__name__}")
        if not isinstance(self.classes, ClassTable):
            raise ConfigError(f"model.classes must be a ClassTable, got {type(self.classes).__name__}")

    @property
    def architecture(self) -> str:
        """The registry name of this config's architecture."""
        return self.NAME

    @property
    def num_classes(self) -> int:
        """C."""
        return len(self.classes.names)

    @property
    def image_size(self) -> tuple[int, int]:
        """``(height, width)`` of the input image in pixels, in the grid's aspect."""
        raise NotImplementedError

    @property
    def reads_camera(self) -> bool:
        """Whether the network's ``forward(image, camera)`` takes what is known of the camera (a
        :class:`~fruxel.train.models.conditioning.CameraInput`); False: ``forward(image)`` alone, and callers pass no
        camera (:func:`run_network`)."""
        return False

    def build(self, *, checkpointing: bool = False) -> nn.Module:
        """A freshly initialised network of this config (``checkpointing``: recompute activations in the backward
        pass where the architecture supports it)."""
        raise NotImplementedError


def run_network(network: nn.Module, image: torch.Tensor, camera: Any = None) -> Any:
    """``network(image)``, or ``network(image, camera)`` when a camera is given (a network whose config
    :attr:`~ModelConfig.reads_camera`; other architectures' ``forward`` takes the image alone)."""
    return network(image) if camera is None else network(image, camera)


C = TypeVar("C", bound=type[ModelConfig])
_ARCHITECTURES: dict[str, type[ModelConfig]] = {}


def register(name: str) -> Callable[[C], C]:
    """Class decorator: register a :class:`ModelConfig` subclass as architecture ``name``."""

    def add(cls: C) -> C:
        if name in _ARCHITECTURES and _ARCHITECTURES[name] is not cls:
            raise ValueError(f"architecture {name!r} is registered already")
        cls.NAME = name
        _ARCHITECTURES[name] = cls
        return cls

    return add


def architectures() -> tuple[str, ...]:
    """The registered architecture names."""
    _load_builtin()
    return tuple(_ARCHITECTURES)


def architecture(name: str) -> type[ModelConfig]:
    """The config class registered as ``name``.

    Raises:
        ConfigError: no such architecture.
    """
    _load_builtin()
    if name not in _ARCHITECTURES:
        raise ConfigError(f"unknown model.architecture {name!r}; known: {', '.join(_ARCHITECTURES)}")
    return _ARCHITECTURES[name]


def _load_builtin() -> None:
    """Register fruxel's own architectures (imported here, not at the top, so that this module stays a leaf)."""
    from . import ssz  # noqa: F401


def model_config_to_dict(config: ModelConfig) -> dict[str, Any]:
    """Plain-JSON form of a model config, ``{"architecture": NAME, ...fields}``."""
    from ..config import to_plain

    return {"architecture": config.architecture, **to_plain(config)}


def model_config_from_dict(d: Any, base: ModelConfig | None = None, path: str = "model") -> ModelConfig:
    """A model config from JSON data: ``base`` (default: the named architecture's defaults) with the given fields
    overridden; ``"architecture"`` picks the class (default: ``base``'s, else ``"ssz"``).

    Raises:
        ConfigError: an unknown architecture or key, or an impossible value (naming ``path.key``).
    """
    from ..config import override

    if not isinstance(d, Mapping):
        raise ConfigError(f"{path} must be a JSON object, got {type(d).__name__}")
    d = dict(d)
    name = d.pop("architecture", base.architecture if base is not None else "ssz")
    if not isinstance(name, str):
        raise ConfigError(f"{path}.architecture must be a string, got {name!r}")
    cls = architecture(name)
    if base is None or type(base) is not cls:
        # Another architecture starts from its own defaults, keeping the grid and class table.
        shared = {} if base is None else {f.name: getattr(base, f.name) for f in dataclasses.fields(ModelConfig)}
        base = cls(**shared)
    return override(base, d, path)

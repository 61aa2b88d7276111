"""The settings of SSZ, fruxel's image-to-fruxel network (architecture ``"ssz"``), and the network they build.

The network itself is :class:`fruxel.train.models.generator.SSZGenerator` (conventions section 8); this config is
what a shipped ``ssz`` file stores, what ``fruxel-train`` presets set, and the one place its settings are checked.
Per-level tuples run from the grid's resolution (level 0) down.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import TYPE_CHECKING

from fruxel.errors import ConfigError

from .registry import ModelConfig, register

if TYPE_CHECKING:
    from .generator import SSZGenerator

MAX_IMAGE_SCALE = 4
"""Largest ``image_scale``."""
IMAGE_WIDTHS = (16, 1024)
"""Smallest and largest width of the image the network reads, pixels."""


@register("ssz")
@dataclass(frozen=True)
class SSZConfig(ModelConfig):
    """Architecture of the SSZ generator (see :mod:`fruxel.train.models.generator` for the data flow)."""

    image_scale: int = 1
    """k: the stem reads an image ``2^k`` times the grid's width and height (k = 1: 128^2 for a 64^3 grid)."""
    levels: int = 5
    """L: resolution levels; every grid axis must be divisible by ``2^(L-1)`` (``2^L`` with ``refine``)."""
    stem: int = 24
    """Channels of the 2D stem (at half the image resolution)."""
    detail_branch: int = 0
    """Channels of a branch that reads the image at twice the resolution ``image_scale`` gives (0 = none): the
    input image is then ``2^(k+1)`` times the grid, the stem sees it averaged over 2 x 2 pixels, and the branch
    (two stride-2 convolutions around an inverted residual block) adds what only the finer image holds to the
    stem's output: where a board thinner than a cell lies against the column's centre ray. It starts as a zero
    term, so a model fine-tuned (``run.init``) from weights without it starts as that model on the pooled image."""
    encoder: tuple[int, ...] = (32, 48, 96, 160, 224)
    """Channels of the 2D encoder per level."""
    encoder_blocks: tuple[int, ...] = (2, 2, 3, 3, 2)
    """2D inverted residual blocks per level."""
    encoder_expand: int = 4
    """Expansion factor of the 2D inverted residual blocks."""
    topdown: tuple[int, ...] = (48, 64, 96, 128, 160)
    """Channels of the 2D top-down path per level (the image features copied into the 3D levels)."""
    decoder: tuple[int, ...] = (16, 24, 32, 48, 64)
    """Channels of the 3D decoder per level."""
    decoder_blocks: tuple[int, ...] = (1, 1, 1, 2, 2)
    """Volumetric inverted residual blocks per level."""
    expand: int = 2
    """Expansion factor of the 3D decoder's inverted residual blocks."""
    refine: int = 0
    """Channels of a refinement level that doubles the output grid in every axis (0 = none;
    :class:`fruxel.train.models.generator.RefineLevel`). Everything else is then built for ``grid`` halved and
    reads the image averaged over 2 x 2 pixels, so a model trained at that grid (``run.init``) is the network below
    the level, which starts as a zero correction: a fresh level repeats the coarse model's answer on the fine
    cells. The level reads the full image (``image_size``) through a branch of its own."""
    camera_inputs: bool = False
    """Condition the network on what is known of the camera besides the image: the gravity direction in the camera
    frame and the height above the floor, each optional (:mod:`fruxel.train.models.conditioning`). Every decoder
    level (below ``refine``'s) then reads each cell's height above the floor as extra channels. False: the network
    of the shipped ``ssz64`` and ``ssz128``, which reads the image alone."""

    def validate(self) -> None:
        """Raise :class:`~fruxel.errors.ConfigError` (naming ``model.KEY``) for an impossible architecture."""
        super().validate()
        for name in ("levels", "stem", "expand", "encoder_expand"):
            _count(name, getattr(self, name))
        for name in ("detail_branch", "refine"):
            _count(name, getattr(self, name), allow_zero=True)
        if not isinstance(self.camera_inputs, bool):
            raise ConfigError(f"model.camera_inputs must be true or false, got {self.camera_inputs!r}")
        if isinstance(self.image_scale, bool) or not isinstance(self.image_scale, int) \
                or not 0 <= self.image_scale <= MAX_IMAGE_SCALE:
            raise ConfigError(f"model.image_scale must be an integer in [0, {MAX_IMAGE_SCALE}], got "
                              f"{self.image_scale!r}")
        for name in ("encoder", "encoder_blocks", "topdown", "decoder", "decoder_blocks"):
            seq = getattr(self, name)
            if not isinstance(seq, tuple) or len(seq) != self.levels:
                raise ConfigError(f"model.{name} needs one entry per level ({self.levels}), got {seq!r}")
            for v in seq:
                _count(name, v, allow_zero=name.endswith("blocks"))
        f = 2 ** (self.levels - 1 + (1 if self.refine else 0))
        g = self.grid
        if g.width % f or g.height % f or g.depth % f:
            why = "2^levels (levels, then refine)" if self.refine else "2^(levels-1)"
            raise ConfigError(f"model.grid {g.width}x{g.height}x{g.depth} must be divisible by {why} = {f} in every "
                              "axis")
        w = self.image_size[1]
        if not IMAGE_WIDTHS[0] <= w <= IMAGE_WIDTHS[1]:
            raise ConfigError(f"model: image width {w} (grid width x 2^image_scale, doubled by detail_branch) must be "
                              f"in [{IMAGE_WIDTHS[0]}, {IMAGE_WIDTHS[1]}]")

    @property
    def image_size(self) -> tuple[int, int]:
        """``(height, width)`` of the input image in pixels."""
        k = self.image_scale + (1 if self.detail_branch else 0)
        return self.grid.height << k, self.grid.width << k

    @property
    def reads_camera(self) -> bool:
        """Whether the network takes the camera (``camera_inputs``)."""
        return self.camera_inputs

    def build(self, *, checkpointing: bool = False) -> SSZGenerator:
        """A freshly initialised :class:`~fruxel.train.models.generator.SSZGenerator` of this config."""
        from .generator import SSZGenerator

        # The network's keyword arguments are the config's own fields, by name: a setting is written once.
        own = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in ("grid", "classes")}
        g = self.grid
        return SSZGenerator(classes=self.num_classes, grid_shape=(g.depth, g.height, g.width), grid=g,
                            checkpointing=checkpointing, **own)


def _count(name: str, v: object, allow_zero: bool = False) -> None:
    if isinstance(v, bool) or not isinstance(v, int) or v < (0 if allow_zero else 1):
        raise ConfigError(f"model.{name} must be an integer >= {0 if allow_zero else 1}, got {v!r}")

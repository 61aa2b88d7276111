"""Experiment (issue 39): SSZ whose decoder cells also read the image where their floor footprint is seen.

Not in the product: a research lever that extends it from outside (the architecture registry), until a shipped model
uses it. Run the product's commands through this module so that the architecture is registered::

    python experiments/footprint_lift.py train --config CONFIG.json --out RUN_DIR --device cuda
    python experiments/footprint_lift.py eval --checkpoint RUN_DIR/model.safetensors ...

with ``"model": {"architecture": "ssz-footprint", "detail_branch": 24, "camera_inputs": true}`` in the config
(ssz64-any's architecture plus the footprint term) and ``"run": {"init": "ssz64-any"}``: the new term starts at
zero, so training starts from the shipped model's function.

Why: a wall stands on the floor. With gravity and height told, the floor plane is known, so a wall's distance is
where the image row of its base lands on that plane. The product's decoder cell ``(k, j, i)`` reads the image
features of its own column ``(j, i)`` only; what tells it that a wall stands at its depth is the image at the row
where the floor at that depth is seen, which a 3x3x3 decoder reaches only at coarse levels. Here every cell of
every level also reads the top-down image features (bilinear, through a zero-initialised 1x1 convolution) at the
image point of its *footprint*: its centre ``c`` moved down along gravity ``g`` onto the floor,
``f = c + (h + c . (-g)) g`` (camera frame, OpenCV axes), seen at ``(f_x / f_z / tu, f_y / f_z / tv)`` in
grid_sample's normalised image coordinates. Cells whose footprint is behind the camera, outside the image, or
whose gravity or height is unknown read zeros; the convolution's bias, sampled with zero padding, says which.
"""

from __future__ import annotations

import dataclasses
import sys
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn

from fruxel.grid import FruxelGrid
from fruxel.train.models.conditioning import CameraInput
from fruxel.train.models.generator import SSZGenerator
from fruxel.train.models.registry import register
from fruxel.train.models.ssz import SSZConfig

MIN_FRONT = 0.05
"""Metres: a footprint nearer the camera plane than this is not seen (its projection would blow up)."""


@register("ssz-footprint")
@dataclass(frozen=True)
class FootprintSSZConfig(SSZConfig):
    """ssz's architecture with the footprint term (module docstring); needs ``camera_inputs``. Its defaults are
    ssz64-any's architecture."""

    detail_branch: int = 24
    """As ssz's (ssz64-any's value)."""
    camera_inputs: bool = True
    """As ssz's; must be true."""

    def validate(self) -> None:
        """As ssz's, and the camera must be read."""
        super().validate()
        from fruxel.errors import ConfigError

        if not self.camera_inputs or self.refine:
            raise ConfigError("model: ssz-footprint needs camera_inputs true and refine 0")

    def build(self, *, checkpointing: bool = False) -> FootprintGenerator:
        own = {f.name: getattr(self, f.name) for f in dataclasses.fields(self) if f.name not in ("grid", "classes")}
        g = self.grid
        return FootprintGenerator(classes=self.num_classes, grid_shape=(g.depth, g.height, g.width), grid=g,
                                  checkpointing=checkpointing, **own)


class FootprintGenerator(SSZGenerator):
    """SSZGenerator with each Lift's sum extended by the image features seen at the cells' floor footprints."""

    def __init__(self, *, grid: FruxelGrid, topdown: tuple[int, ...], decoder: tuple[int, ...], **kw: object
                 ) -> None:
        super().__init__(grid=grid, topdown=topdown, decoder=decoder, **kw)
        self.tu, self.tv = grid.tu, grid.tv
        self.footprint = nn.ModuleList(nn.Conv2d(topdown[s], decoder[s], 1) for s in range(self.levels))
        for conv in self.footprint:
            nn.init.zeros_(conv.weight)
            nn.init.zeros_(conv.bias)

    def footprint_points(self, camera: CameraInput, level: int) -> tuple[torch.Tensor, torch.Tensor]:
        """Where each cell's floor footprint is seen.

        Returns:
            ``(B, D_s * H_s, W_s, 2)`` float32 grid_sample coordinates (x, y) in [-1, 1] over the image, and
            ``(B, 1, D_s, H_s, W_s)`` float32 1 where the footprint is known and in front of the camera, else 0.
        """
        centres = getattr(self.conditioning, f"centres{level}")  # (1, 3, D, H, W)
        b = len(camera)
        known = camera.known[:, 0].float() * camera.known[:, 1].float()
        g = camera.gravity.float().view(b, 3, 1, 1, 1)
        above = camera.height.float().view(b, 1, 1, 1, 1) - (g * centres).sum(dim=1, keepdim=True)
        f = centres + above * g  # (B, 3, D, H, W)
        z = f[:, 2:3]
        ok = (z > MIN_FRONT).float() * known.view(b, 1, 1, 1, 1)
        zs = torch.where(z > MIN_FRONT, z, torch.ones_like(z))
        xy = torch.cat([f[:, 0:1] / zs / self.tu, f[:, 1:2] / zs / self.tv], dim=1) * ok
        _, _, d, h, w = xy.shape
        return xy.permute(0, 2, 3, 4, 1).reshape(b, d * h, w, 2), ok

    def footprint_features(self, t: torch.Tensor, camera: CameraInput, level: int) -> torch.Tensor:
        """``(B, V_s, D_s, H_s, W_s)``: the level's top-down features ``t`` ``(B, T_s, H_s, W_s)`` through the 1x1
        convolution, seen at the cells' footprints (zeros where not seen)."""
        xy, ok = self.footprint_points(camera, level)
        y = self.footprint[level](t)
        s = F.grid_sample(y.float(), xy, mode="bilinear", padding_mode="zeros", align_corners=False)
        b, c = s.shape[:2]
        return (s.view(b, c, *ok.shape[2:]) * ok).to(t.dtype)

    def _lift(self, level: int, x: torch.Tensor, t: torch.Tensor, depth: torch.Tensor, shape: tuple[int, int, int],
              camera: CameraInput | None) -> torch.Tensor:
        """SSZGenerator's merge, with the footprint term added after it (the Lift's activation first, so that the
        term at zero changes nothing). ``camera`` is never None here: the network reads the camera."""
        x = super()._lift(level, x, t, depth, shape, camera)
        return x + self.footprint_features(t, camera, level).to(x.dtype)


def main(argv: list[str]) -> int:
    """``train ...`` or ``eval ...`` (anything else: another fruxel CLI module's name) with the architecture
    registered."""
    import importlib

    if not argv:
        print("usage: footprint_lift.py {train,eval,predict,calibrate} ARGS...", file=sys.stderr)
        return 2
    return importlib.import_module(f"fruxel.cli.{argv[0]}").main(argv[1:])


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

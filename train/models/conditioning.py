"""What SSZ knows about the camera beyond its image: the gravity direction and the height above the floor, each
possibly unknown, turned into per-cell geometry for the 3D decoder (``SSZConfig.camera_inputs``).

The intrinsics need no input: the image is framed onto the grid's own view (:mod:`fruxel.train.framing`), so every
cell's position in the camera frame is fixed by the grid. With gravity known, a cell's "up" coordinate relative to
the camera is ``c . (-g)`` (``c`` its centre, ``g`` the unit gravity direction in the camera frame, OpenCV axes: x
right, y down, z forward); with the height ``h`` known too, its height above the floor is ``h + c . (-g)``, so the
floor is where that is zero. How far away the floor is then is geometry, not a guess from the image.

:class:`CameraInput` holds the batch's tensors (unknown pieces are zeros with a 0 flag); :class:`CameraConditioning`
turns them into :data:`CAMERA_CHANNELS` per-cell feature channels at each decoder level, which each level's
:class:`~.blocks.Lift` reads. Neither applies a rule of its own: what is known is whatever the caller says (the
training engine drops pieces at random, ``DataConfig.camera_dropout``; evaluation and prediction say what they
know).
"""

from __future__ import annotations

from collections.abc import Collection, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch
from torch import nn

from fruxel.grid import FruxelGrid

CAMERA_CHANNELS = 5
"""Per-cell channels of :meth:`CameraConditioning.forward`: up coordinate, height above the floor, floor side, and
the two flags (gravity known, height known)."""
UP_SCALE = 2.0
"""Metres per unit of the up and height channels (keeps them near [-4, 4] over an 8 m frustum)."""
KNOWN = ("gravity", "height")
"""The camera pieces a model can be told, in the order of :attr:`CameraInput.known`'s columns."""


@dataclass
class CameraInput:
    """A batch's camera pieces as tensors, on the network's device. Unknown pieces are zeros with flag 0.

    A height means something only along gravity: the conditioning treats the height as unknown wherever gravity
    is (whatever its flag says).
    """

    gravity: torch.Tensor
    """``(B, 3)`` float32 unit direction of gravity in the camera frame (OpenCV axes), zeros where unknown."""
    height: torch.Tensor
    """``(B,)`` float32 height of the optical centre above the floor, metres, 0 where unknown."""
    known: torch.Tensor
    """``(B, 2)`` float32 flags 1 (known) or 0: gravity, height (:data:`KNOWN`)."""

    def __len__(self) -> int:
        return int(self.height.shape[0])

    @classmethod
    def unknown(cls, batch: int, device: torch.device | str = "cpu") -> CameraInput:
        """Nothing known, for ``batch`` samples."""
        z = torch.zeros(batch, device=device)
        return cls(torch.zeros(batch, 3, device=device), z, torch.zeros(batch, 2, device=device))

    @classmethod
    def of(cls, gravity: Any, height: Any, known: Any, device: torch.device | str = "cpu") -> CameraInput:
        """From arrays or tensors: ``gravity`` ``(B, 3)``, ``height`` ``(B,)``, ``known`` ``(B, 2)`` 0/1 (any
        numeric dtype). Unknown pieces are zeroed here; a NaN piece (what a data folder's sample that does not give
        it holds, :mod:`fruxel.train.folder`) is unknown whatever ``known`` says."""
        def t(x: Any) -> torch.Tensor:
            return torch.as_tensor(np.asarray(x) if not isinstance(x, torch.Tensor) else x).to(device, torch.float32)

        g, h = t(gravity).reshape(-1, 3), t(height).reshape(-1)
        k = t(known).reshape(-1, 2) * torch.stack([torch.isfinite(g).all(dim=1), torch.isfinite(h)], dim=1)
        zero = g.new_zeros(())
        return cls(torch.where(k[:, :1] > 0, g, zero), torch.where(k[:, 1] > 0, h, zero), k)

    @classmethod
    def from_record(cls, camera: Mapping[str, Any], known: Collection[str] = KNOWN,
                    device: torch.device | str = "cpu") -> CameraInput:
        """From a batch's camera record (``batch["camera"]``: :data:`fruxel.train.sim.cameras.CAMERA_KEYS`), with
        only the pieces named in ``known`` (a subset of :data:`KNOWN`) given.

        Raises:
            ValueError: an unknown piece name.
        """
        bad = sorted(set(known) - set(KNOWN))
        if bad:
            raise ValueError(f"unknown camera pieces {bad}; known are {list(KNOWN)}")
        n = len(camera["height"])
        flags = np.tile(np.array([[p in known for p in KNOWN]], dtype=np.float32), (n, 1))
        return cls.of(camera["gravity"], camera["height"], flags, device)

    def to(self, device: torch.device | str) -> CameraInput:
        """The same on ``device``."""
        return CameraInput(self.gravity.to(device), self.height.to(device), self.known.to(device))

    def mirrored(self) -> CameraInput:
        """The camera of the mirror image (left and right swapped, :func:`fruxel.train.rules.mirror_average`):
        gravity's x component negated (the roll reversed)."""
        return CameraInput(self.gravity * self.gravity.new_tensor([-1.0, 1.0, 1.0]), self.height, self.known)

    def cat(self, other: CameraInput) -> CameraInput:
        """This batch followed by ``other``'s."""
        return CameraInput(torch.cat([self.gravity, other.gravity]), torch.cat([self.height, other.height]),
                           torch.cat([self.known, other.known]))


class CameraConditioning(nn.Module):
    """Per-cell camera features of each decoder level (module docstring).

    Channels (:data:`CAMERA_CHANNELS`), per cell of centre ``c`` (camera frame, metres), ``u = c . (-g)``:

    0. ``u / UP_SCALE`` where gravity is known, else 0;
    1. ``(h + u) / UP_SCALE``, the height above the floor, where gravity and height are known, else 0;
    2. ``tanh((h + u) / dz_s)``, which side of the floor the cell is, sharp at the level's slice thickness
       ``dz_s`` (the decoder's pointwise merge could not make that step from channel 1 alone), else 0;
    3. gravity known (0/1); 4. height known (0/1, and gravity known).

    Args:
        grid: the network's output grid (below a refinement level: the grid halved, same frustum).
        levels: decoder levels; level ``s`` has the grid's cells divided by ``2^s`` per axis.
    """

    def __init__(self, grid: FruxelGrid, levels: int) -> None:
        super().__init__()
        self.levels = levels
        self.bands: list[float] = []
        for s in range(levels):
            g = FruxelGrid(width=grid.width >> s, height=grid.height >> s, depth=grid.depth >> s,
                           z_near=grid.z_near, z_far=grid.z_far, hfov=grid.hfov)
            centres = torch.from_numpy(g.cell_centres()).to(torch.float32).permute(3, 0, 1, 2).unsqueeze(0)
            # Derived from the config's grid, so not stored in the weights: files stay the network's parameters.
            self.register_buffer(f"centres{s}", centres.contiguous(), persistent=False)
            self.bands.append(float(g.dz))

    def forward(self, camera: CameraInput, level: int) -> torch.Tensor:
        """The features of level ``level``.

        Args:
            camera: the batch's camera (B samples, on this module's device).
            level: 0 .. levels - 1.

        Returns:
            ``(B, CAMERA_CHANNELS, D_s, H_s, W_s)`` float32, grid frame.
        """
        centres = getattr(self, f"centres{level}")  # (1, 3, D, H, W)
        b = len(camera)
        kg = camera.known[:, 0].float()
        kh = kg * camera.known[:, 1].float()
        up = -camera.gravity.float() * kg[:, None]
        u = (up.view(b, 3, 1, 1, 1) * centres).sum(dim=1)  # (B, D, H, W)
        above = camera.height.float().view(b, 1, 1, 1) + u
        k_h = kh.view(b, 1, 1, 1)
        shape = u.shape
        return torch.stack([u / UP_SCALE, k_h * above / UP_SCALE, k_h * torch.tanh(above / self.bands[level]),
                            kg.view(b, 1, 1, 1).expand(shape), k_h.expand(shape)], dim=1)

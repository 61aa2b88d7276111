"""Training batches on the training device: the uint8 host batches of :mod:`fruxel.train.samples` moved and
converted there, optionally mixed through a replay buffer that lives there.

Arrays: ``image`` ``(N, h, w, 3)`` uint8 RGB (the grid camera's image) and ``labels`` ``(N, D, H, W)`` uint8 (grid
frame) stay uint8 until the device (:func:`to_device`), where images become ``(N, 3, h, w)`` float in [0, 1]. A
network that reads the camera gets what :func:`camera_with_dropout` leaves of each sample's camera record.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np
import torch

from ..models.conditioning import CameraInput


def camera_with_dropout(camera: Mapping[str, Any], dropout: tuple[float, float], rng: np.random.Generator,
                        device: torch.device | str) -> CameraInput:
    """A batch's camera for a network that reads it, pieces withheld at random (``DataConfig.camera_dropout``).

    Args:
        camera: the batch's camera record (``gravity`` ``(B, 3)``, ``height`` ``(B,)``; arrays or tensors).
        dropout: ``(p_gravity, p_height)``: gravity (and with it the height) withheld with probability
            ``p_gravity``; else the height alone with probability ``p_height``.
        rng: the draws' generator.
        device: where the network runs.

    Returns:
        The :class:`~fruxel.train.models.conditioning.CameraInput`, withheld pieces zero with flag 0.
    """
    n = len(camera["height"])
    keep_g = rng.random(n) >= dropout[0]
    keep_h = keep_g & (rng.random(n) >= dropout[1])
    return CameraInput.of(camera["gravity"], camera["height"], np.stack([keep_g, keep_h], axis=1), device)


def to_device(batch: dict[str, torch.Tensor], device: torch.device, channels_last: bool = False
              ) -> tuple[torch.Tensor, torch.Tensor]:
    """``(image, labels)`` on ``device``: image ``(B, 3, h, w)`` float32 in [0, 1], labels ``(B, D, H, W)`` uint8.

    The uint8 arrays cross to the device as they are (a quarter of float32's bytes for images, an eighth of int64's
    for labels); the conversion happens there.
    """
    img = batch["image"].to(device, non_blocking=True).permute(0, 3, 1, 2).float().div_(255.0)
    if channels_last:
        img = img.contiguous(memory_format=torch.channels_last)
    else:
        img = img.contiguous()
    return img, batch["labels"].to(device, non_blocking=True)


class ReplayBuffer:
    """A ring of recent samples on the training device from which batches are drawn uniformly.

    Each :meth:`add` inserts new samples (replacing the oldest once full) and :meth:`draw` takes a batch from every
    sample held, so with ``reuse`` draws per batch added each sample is used about ``reuse`` times while it stays in
    the buffer.

    Args:
        capacity: samples held.
        image_shape: ``(h, w, 3)``.
        grid_shape: ``(D, H, W)``.
        device: where the ring lives.
        seed: seed of the draws (its state is part of :meth:`state_dict`).
    """

    def __init__(self, capacity: int, image_shape: tuple[int, ...], grid_shape: tuple[int, ...],
                 device: torch.device, seed: int) -> None:
        self.capacity = capacity
        self.images = torch.empty((capacity, *image_shape), dtype=torch.uint8, device=device)
        self.labels = torch.empty((capacity, *grid_shape), dtype=torch.uint8, device=device)
        # The cameras' gravity and height, for a network that reads them (float64 as recorded).
        self.gravity = torch.zeros((capacity, 3), dtype=torch.float64, device=device)
        self.height = torch.zeros((capacity,), dtype=torch.float64, device=device)
        self.filled = 0
        self.head = 0
        self.generator = torch.Generator().manual_seed(seed)

    def add(self, batch: dict[str, torch.Tensor]) -> None:
        """Insert a batch of host samples (``image``, ``labels`` uint8, and ``camera`` when the batch has one)."""
        n = len(batch["image"])
        slots = ((torch.arange(n) + self.head) % self.capacity).to(self.images.device)
        self.images[slots] = batch["image"].to(self.images.device, non_blocking=True)
        self.labels[slots] = batch["labels"].to(self.images.device, non_blocking=True)
        if "camera" in batch:
            for name in ("gravity", "height"):
                value = torch.as_tensor(batch["camera"][name], dtype=torch.float64)
                getattr(self, name)[slots] = value.to(self.images.device, non_blocking=True)
        self.head = (self.head + n) % self.capacity
        self.filled = min(self.capacity, self.filled + n)

    def draw(self, batch: int) -> dict[str, torch.Tensor]:
        """A batch drawn uniformly (with replacement) from the samples held, on the buffer's device (``camera``:
        their ``gravity`` and ``height``)."""
        idx = torch.randint(0, self.filled, (batch,), generator=self.generator).to(self.images.device)
        return {"image": self.images[idx], "labels": self.labels[idx],
                "camera": {"gravity": self.gravity[idx], "height": self.height[idx]}}

    def state_dict(self) -> dict[str, Any]:
        """The draw generator's state (the samples themselves are not saved: a resumed run refills the ring)."""
        return {"generator": self.generator.get_state()}

    def load_state_dict(self, state: dict[str, Any]) -> None:
        """Restore :meth:`state_dict`."""
        self.generator.set_state(state["generator"])

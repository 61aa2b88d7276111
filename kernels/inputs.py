"""Validation of kernel inputs and the result container, shared by every backend.

Backends call :func:`inspect_volume` and :func:`check_cameras` before touching a device, so that bad input
gets one clear error and nothing is written. Array kinds: numpy arrays and torch tensors (CPU or CUDA); torch
is never imported here, tensors are recognised by duck typing.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.errors import FruxelError
from fruxel.grid import FruxelGrid

MAX_LABEL = 255
"""Largest label value a label volume may hold (labels are uint8 on disk and on the device)."""

EMPTY_LOGIT = -1.0e4
"""Logit that ``shell`` writes into the non-empty channels of a removed cell (channel 0 gets 0): finite in
float16, and far enough below 0 that p(empty) rounds to exactly 1."""


class VolumeError(FruxelError, ValueError):
    """Raised for a volume the kernels cannot take: wrong shape or dtype, NaN or infinite scores, labels out of
    range, or a threshold outside (0, 1]."""


def is_torch(x: Any) -> bool:
    """True for a torch tensor (checked by duck typing, without importing torch)."""
    return type(x).__module__.startswith("torch") and hasattr(x, "detach") and hasattr(x, "device")


@dataclass(frozen=True)
class VolumeSpec:
    """What a kernel input is, after validation."""

    kind: str
    """``"numpy"`` or ``"torch"``: the kind of array results are given back as."""
    device: str
    """Where the data lives: ``"cpu"`` or a torch CUDA device string such as ``"cuda:0"``."""
    batched: bool
    """Whether the caller passed a batch axis; results drop it again when not."""
    is_scores: bool
    """True for float logits / probabilities ``(B, C, D, H, W)``, False for integer labels."""
    batch: int
    """B (1 when the input had no batch axis)."""
    channels: int
    """C for scores, 0 for labels."""
    threshold: float | None
    """Occupancy threshold on ``1 - p(empty)``, or None for the argmax rule."""
    probs: bool
    """Scores are probabilities (True) or logits (False, softmax over C gives p)."""


def _dtype_kind(x: Any) -> str:
    """numpy dtype kind letter ('b', 'i', 'u', 'f', ...) of a numpy array or torch tensor."""
    if is_torch(x):
        import torch

        if x.dtype == torch.bool:
            return "b"
        if x.dtype.is_floating_point:
            return "f"
        if x.dtype.is_complex:
            return "c"
        return "u" if x.dtype == torch.uint8 else "i"
    return np.asarray(x).dtype.kind


def _all_finite(volume: Any) -> bool:
    """Whether a float array holds no NaN or infinity, without an element-sized temporary: NaN propagates
    through min and max, and an infinity is the min or the max."""
    if is_torch(volume):
        import torch

        lo, hi = torch.aminmax(volume.detach().reshape(-1))
        return bool(torch.isfinite(lo) & torch.isfinite(hi))  # one host synchronisation, needed for the error
    return bool(np.isfinite(volume.min()) and np.isfinite(volume.max()))


def inspect_volume(volume: Any, grid: FruxelGrid, threshold: float | None = None, probs: bool = False) -> VolumeSpec:
    """Validate a kernel input volume against a grid (conventions section 2).

    Accepted:
        * integer or bool labels ``(D, H, W)`` or ``(B, D, H, W)``, values in [0, 255], 0 = empty;
        * float16/32/64 (or bfloat16 tensors) logits or probabilities ``(B, C, D, H, W)``, C >= 2, finite.

    Args:
        volume: numpy array or torch tensor (CPU or CUDA).
        grid: the grid whose ``(D, H, W)`` the volume must match.
        threshold: occupancy threshold on ``1 - p(empty)`` in (0, 1], or None for the argmax rule. Scores only.
        probs: whether float scores are probabilities rather than logits (matters only with a threshold).

    Raises:
        VolumeError: anything else, naming the problem.
    """
    if not (is_torch(volume) or isinstance(volume, np.ndarray)):
        raise VolumeError(f"volume must be a numpy array or torch tensor, got {type(volume).__name__}")
    shape = tuple(int(s) for s in volume.shape)
    kind = _dtype_kind(volume)
    dhw = grid.shape
    if kind in "biu":
        if len(shape) not in (3, 4) or shape[-3:] != dhw:
            raise VolumeError(f"label volume must have shape {dhw} or (B, *{dhw}), got {shape}")
        if threshold is not None:
            raise VolumeError("threshold applies to float scores, not to integer labels")
        batched = len(shape) == 4
        if 0 in shape:
            raise VolumeError(f"volume is empty: shape {shape}")
        if kind != "b" and str(volume.dtype).removeprefix("torch.") != "uint8":
            # uint8 holds [0, 255] by type: no reduction, and no device synchronisation for CUDA tensors.
            lo, hi = volume.min(), volume.max()
            lo, hi = (lo.item(), hi.item()) if is_torch(volume) else (lo, hi)
            if lo < 0 or hi > MAX_LABEL:
                raise VolumeError(f"labels must lie in [0, {MAX_LABEL}], got values in [{lo}, {hi}]")
        spec_b, spec_c, scores = (shape[0] if batched else 1), 0, False
    elif kind == "f":
        if len(shape) != 5 or shape[-3:] != dhw:
            raise VolumeError(f"float scores must have shape (B, C, *{dhw}) (NCDHW), got {shape}")
        if shape[1] < 2:
            raise VolumeError(f"float scores need at least 2 channels (0 = empty), got C = {shape[1]}")
        if shape[0] == 0:
            raise VolumeError("volume is empty: B = 0")
        finite = _all_finite(volume)
        if not finite:
            raise VolumeError("float scores contain NaN or infinite values")
        if threshold is not None and not (0.0 < float(threshold) <= 1.0):
            raise VolumeError(f"threshold must be in (0, 1], got {threshold}")
        batched, spec_b, spec_c, scores = True, shape[0], shape[1], True
    else:
        raise VolumeError(f"volume dtype must be integer, bool or float, got {volume.dtype}")
    device = str(volume.device) if is_torch(volume) and volume.device.type != "cpu" else "cpu"
    return VolumeSpec(
        kind="torch" if is_torch(volume) else "numpy",
        device=device,
        batched=batched,
        is_scores=scores,
        batch=spec_b,
        channels=spec_c,
        threshold=None if threshold is None else float(threshold),
        probs=bool(probs),
    )


def check_cameras(cameras: Any) -> list[Camera]:
    """A camera or a non-empty sequence of cameras, as a list.

    Raises:
        VolumeError: an empty sequence or something that is not a :class:`fruxel.Camera`.
    """
    if isinstance(cameras, Camera):
        return [cameras]
    # A mapping, a string or any other non-sequence is not a set of cameras (iterating a dict would report its
    # keys' type instead of the dict's).
    if isinstance(cameras, (str, bytes, Mapping)) or not isinstance(cameras, Iterable):
        raise VolumeError(f"expected a fruxel.Camera or a sequence of them, got {type(cameras).__name__}")
    cams = list(cameras)
    if not cams:
        raise VolumeError("at least one camera is needed")
    for n, c in enumerate(cams):
        if not isinstance(c, Camera):
            raise VolumeError(f"expected a fruxel.Camera or a sequence of them, got {type(c).__name__} at index {n}")
    return cams


def empty_scores(spec: VolumeSpec) -> tuple[float, float]:
    """Channel 0 and each of channels 1..C-1 of the canonical empty cell in a score volume: ``(0, EMPTY_LOGIT)``
    for logits, ``(1, 0)`` for probabilities (what ``shell`` writes into removed cells)."""
    return (1.0, 0.0) if spec.probs else (0.0, EMPTY_LOGIT)


def check_camera(camera: Any) -> Camera:
    """The one camera of a call that takes exactly one (``first_hit``), given alone or as a one-item sequence.

    Raises:
        VolumeError: not exactly one :class:`fruxel.Camera`.
    """
    cams = check_cameras(camera)
    if len(cams) != 1:
        raise VolumeError(f"first_hit takes one camera, got {len(cams)}")
    return cams[0]


@dataclass(frozen=True)
class Hits:
    """Per-pixel result of ``first_hit`` (conventions section 4), in the caller's kind of array and on its device.

    Leading axes are ``(B,)`` when the volume had a batch axis, none otherwise; ``h, w`` are the camera's image
    height and width.
    """

    label: Any
    """``(..., h, w)`` int32: label of the first occupied cell, 0 on a miss."""
    cell: Any
    """``(..., h, w)`` int64: flat index ``(k * H + j) * W + i`` of that cell, -1 on a miss."""
    depth: Any
    """``(..., h, w)`` float32: z of the entry point in the viewing camera's frame (= ray parameter t), 0 on a
    miss."""
    normal: Any
    """``(..., h, w, 3)`` float32: unit normal of the entry face in the grid frame, pointing back towards the
    camera (``dot(normal, ray) < 0``); zeros on a miss."""

    @property
    def hit(self) -> Any:
        """``(..., h, w)`` bool: pixels whose ray hit an occupied cell."""
        return self.cell >= 0

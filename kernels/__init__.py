"""fruxel.kernels: ray traversal through fruxel grids, on NVIDIA Warp (CUDA or CPU) and OpenCL.

Operations (conventions section 4), one contract for every backend:

* :func:`first_hit` — per pixel of a viewing camera, the first occupied cell along its ray (exact DDA over the
  three plane families);
* :func:`shell` — the voxel model simplification (VMS): keep only cells that are some pixel's first hit.

Volumes are label volumes ``(D, H, W)`` / ``(B, D, H, W)`` or float logits / probabilities
``(B, C, D, H, W)`` (NCDHW), as numpy arrays or torch tensors on the CPU or CUDA. Results come back in the
caller's kind of array and on its device. ``backend`` is ``"warp"``, ``"opencl"`` or None (the best available,
see :func:`fruxel.kernels.registry.resolve`); ``device`` picks Warp's device (``"cpu"``, ``"cuda"``,
``"cuda:1"``) and follows the data by default.
"""

from __future__ import annotations

from typing import Any

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from .fruxelize import fruxelize
from .inputs import EMPTY_LOGIT, Hits, VolumeError
from .poses import orbit_cameras
from .registry import BackendError, BackendUnavailable, available_backends, get_backend, resolve
from .soft import SoftHits, soft_first_hit

__all__ = [
    "EMPTY_LOGIT",
    "BackendError",
    "BackendUnavailable",
    "Hits",
    "SoftHits",
    "VolumeError",
    "available_backends",
    "first_hit",
    "fruxelize",
    "get_backend",
    "orbit_cameras",
    "shell",
    "soft_first_hit",
]


def first_hit(
    volume: Any,
    grid: FruxelGrid,
    camera: Camera,
    *,
    backend: str | None = None,
    device: str | None = None,
    threshold: float | None = None,
    probs: bool = False,
) -> Hits:
    """First occupied cell along each pixel's ray (conventions section 4).

    Args:
        volume: labels ``(D, H, W)`` / ``(B, D, H, W)`` (integer, 0 = empty) or float scores
            ``(B, C, D, H, W)``; numpy or torch, CPU or CUDA.
        grid: the volume's grid.
        camera: the viewing camera; its pose is camera-to-grid and may put it anywhere, inside or behind the
            frustum too.
        backend: ``"warp"``, ``"opencl"``, an :func:`available_backends` name such as ``"warp-cpu"``, or None.
        device: Warp device, or None to follow the data.
        threshold: for scores, occupied when ``1 - p(empty) >= threshold``; None uses the argmax rule.
        probs: scores are probabilities rather than logits (matters only with ``threshold``).

    Returns:
        :class:`Hits` with ``(B?, h, w)`` label (int32), cell (int64), depth (float32) and
        ``(B?, h, w, 3)`` normal (float32, grid frame).

    Raises:
        VolumeError, fruxel.CameraError: bad input (nothing is computed).
        BackendError, BackendUnavailable: an unknown or missing backend.
    """
    mod, dev = resolve(backend, device, volume)
    return mod.first_hit(volume, grid, camera, device=dev, threshold=threshold, probs=probs)


def shell(
    volume: Any,
    grid: FruxelGrid,
    cameras: Camera | list[Camera],
    *,
    backend: str | None = None,
    device: str | None = None,
    threshold: float | None = None,
    probs: bool = False,
) -> Any:
    """The VMS shell: the volume with every cell that is no pixel's first hit set to empty (conventions section 4).

    Args:
        volume: as for :func:`first_hit`.
        grid: the volume's grid.
        cameras: one camera or a list; the grid's own camera at native resolution takes a fast path (the first
            occupied cell of each column).
        backend, device, threshold, probs: as for :func:`first_hit`.

    Returns:
        An array of the input's shape, dtype, kind and device. Labels keep their value where kept and become 0
        elsewhere. Scores keep their values where kept; elsewhere the cell becomes the canonical empty cell:
        logits ``(0, EMPTY_LOGIT, ..., EMPTY_LOGIT)`` (p(empty) rounds to 1 in every float type), probabilities
        ``(1, 0, ..., 0)``.
    """
    mod, dev = resolve(backend, device, volume)
    return mod.shell(volume, grid, cameras, device=dev, threshold=threshold, probs=probs)

"""OpenCL ``shell``: the VMS simplification (conventions section 4) of a label or score volume.

Per call: labels (and their field) on the device (:mod:`.occupancy`), a zeroed uint8 mask, one traversal
launch per camera marking each pixel's first-hit cell (:file:`shell.cl`'s ``mark_shell_kernel``; the grid's own
camera at native resolution takes ``mark_columns_kernel``, one work-item per column), then one launch that writes the
output from the input, the mask and the canonical empty cell. Nothing is cached across calls but device buffers.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from .. import traversal
from ..inputs import VolumeSpec, check_cameras, empty_scores, inspect_volume
from . import occupancy
from .runtime import Runtime, get_runtime, host_array, source, to_caller

_SOURCE = source(__file__)
_LOCAL_COLUMNS = 16
"""Work-group width of mark_columns_kernel (columns along x)."""
_LOCAL_SELECT = 256
"""Work-group size of write_shell_kernel_* (elements along the cell axis)."""


def shell(
    volume: Any,
    grid: FruxelGrid,
    cameras: Camera | list[Camera],
    *,
    device: str | None = None,
    threshold: float | None = None,
    probs: bool = False,
) -> Any:
    """The VMS shell on OpenCL (see :func:`fruxel.kernels.shell`).

    Args:
        volume: labels ``(D, H, W)`` / ``(B, D, H, W)`` (integer or bool, 0 = empty) or float scores
            ``(B, C, D, H, W)`` (NCDHW, channel 0 = empty); numpy or torch (CPU or CUDA, the latter copied to
            the host and the result copied back).
        grid: the volume's grid.
        cameras: one camera or a non-empty list (poses camera-to-grid).
        device: OpenCL device selector from :func:`.runtime.resolve_device`.
        threshold: occupancy threshold on ``1 - p(empty)`` for scores, or None for the argmax rule.
        probs: the scores are probabilities rather than logits.

    Returns:
        An array of the input's shape, dtype, kind and device: labels keep their value where some pixel's first
        hit is the cell and become 0 elsewhere; scores keep their values there and elsewhere become the
        canonical empty cell, logits ``(0, EMPTY_LOGIT, ..., EMPTY_LOGIT)`` or probabilities ``(1, 0, ..., 0)``.

    Raises:
        VolumeError, fruxel.CameraError: bad input, before any device work.
    """
    spec = inspect_volume(volume, grid, threshold, probs)
    occupancy.check_spec(spec)
    cams = check_cameras(cameras)
    arr = host_array(volume)
    rt = get_runtime(device)
    with rt.lock:
        out = _run(rt, arr, spec, grid, cams)
    return to_caller(out, spec, like=volume)


def empty_bits(spec: VolumeSpec, dtype: np.dtype) -> tuple[Any, Any]:
    """Bit patterns (unsigned integers of ``dtype``'s size) of a removed cell's channel 0 and other channels."""
    e0, e1 = empty_scores(spec) if spec.is_scores else (0, 0)
    bits = np.dtype(f"u{dtype.itemsize}")
    return np.array(e0, dtype).view(bits)[()], np.array(e1, dtype).view(bits)[()]


def _run(rt: Runtime, arr: np.ndarray, spec: VolumeSpec, grid: FruxelGrid, cams: list[Camera]) -> np.ndarray:
    """Enqueue labels, field, one marking launch per camera and the output launch for host volume ``arr``,
    and wait for the result: an array like ``arr`` (same shape and dtype)."""
    own = [traversal.is_own_view(cam, grid) for cam in cams]
    vol = occupancy.labels_from_host(rt, arr, spec, grid, walk=not all(own))
    b, cells = spec.batch, grid.n_cells
    opts = occupancy.trace_options(cells, rt.lanes)
    mask = rt.scratch("shell_mask", b * cells)
    rt.zero(mask, b * cells)
    n = occupancy.cell_counts(grid)
    for cam, own_view in zip(cams, own, strict=True):
        if own_view:
            k = rt.kernel(_SOURCE, "mark_columns_kernel", opts)
            k(rt.queue, (occupancy.round_up(grid.width, _LOCAL_COLUMNS), grid.height, b), (_LOCAL_COLUMNS, 1, 1),
              vol.labels, n, mask)
        else:
            k = rt.kernel(_SOURCE, "mark_shell_kernel", opts)
            k(rt.queue, occupancy.tile_global(cam, b, rt.lanes), (*occupancy.TILE_LOCAL, 1), vol.field,
              *occupancy.trace_args(grid, cam), mask)

    out = np.empty_like(arr)
    data = vol.data if vol.data is not None else rt.input("shell_in", arr)
    dst = rt.output("shell_out", out)
    channels = spec.channels if spec.is_scores else 1
    e0, e1 = empty_bits(spec, arr.dtype)
    k = rt.kernel(_SOURCE, f"write_shell_kernel_{arr.dtype.itemsize}", opts)
    k(rt.queue, (occupancy.round_up(cells, _LOCAL_SELECT), channels, b), (_LOCAL_SELECT, 1, 1), data, mask, dst,
      np.int64(cells), e0, e1)
    # The call's one synchronisation: the result goes to the caller next.
    rt.fetch([(dst, out)])
    return out

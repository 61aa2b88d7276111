"""OpenCL ``first_hit``: the first occupied cell along each pixel's ray (conventions section 4, kernels/traversal.py).

One work-item per tile of 4 x 4 pixels and batch item runs :file:`first_hit.cl`'s walk over the uint8 labels, one
ray per vector lane, with the field of :mod:`.occupancy` for empty-space skipping.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from ..inputs import Hits, VolumeSpec, check_camera, inspect_volume
from . import occupancy
from .runtime import Runtime, get_runtime, host_array, source, to_caller

_SOURCE = source(__file__)


def first_hit(
    volume: Any,
    grid: FruxelGrid,
    camera: Camera,
    *,
    device: str | None = None,
    threshold: float | None = None,
    probs: bool = False,
) -> Hits:
    """First occupied cell along each pixel's ray, on OpenCL (see :func:`fruxel.kernels.first_hit`).

    Args:
        volume: labels ``(D, H, W)`` / ``(B, D, H, W)`` (integer or bool, 0 = empty) or float scores
            ``(B, C, D, H, W)`` (NCDHW, channel 0 = empty); numpy or torch (CPU or CUDA, the latter copied to
            the host and the results copied back).
        grid: the volume's grid.
        camera: the viewing camera (pose camera-to-grid).
        device: OpenCL device selector from :func:`.runtime.resolve_device`.
        threshold: occupancy threshold on ``1 - p(empty)`` for scores, or None for the argmax rule.
        probs: the scores are probabilities rather than logits.

    Returns:
        :class:`Hits` in the caller's kind and device, leading axis B only when the input had one:
        label ``(B?, h, w)`` int32, cell ``(B?, h, w)`` int64 (-1 on a miss), depth ``(B?, h, w)`` float32 (z in
        the viewing camera, 0 on a miss), normal ``(B?, h, w, 3)`` float32 (grid frame, zeros on a miss), where
        ``h, w`` are the camera's image height and width.

    Raises:
        VolumeError, fruxel.CameraError: bad input, before any device work.
    """
    spec = inspect_volume(volume, grid, threshold, probs)
    occupancy.check_spec(spec)
    cam = check_camera(camera)
    arr = host_array(volume)
    rt = get_runtime(device)
    with rt.lock:
        label, cell, depth, normal = _run(rt, arr, spec, grid, cam)
    if not spec.batched:
        label, cell, depth, normal = label[0], cell[0], depth[0], normal[0]
    return Hits(label=to_caller(label, spec), cell=to_caller(cell, spec), depth=to_caller(depth, spec),
                normal=to_caller(normal, spec))


def _run(rt: Runtime, arr: np.ndarray, spec: VolumeSpec, grid: FruxelGrid, cam: Camera) -> tuple[np.ndarray, ...]:
    """Enqueue labels, field and traversal for host volume ``arr`` and wait for the results: label
    ``(B, h, w)`` int32, cell ``(B, h, w)`` int64, depth ``(B, h, w)`` float32, normal ``(B, h, w, 3)`` float32."""
    vol = occupancy.labels_from_host(rt, arr, spec, grid)
    b, h, w = spec.batch, cam.height, cam.width
    label = np.empty((b, h, w), np.int32)
    cell = np.empty((b, h, w), np.int64)
    depth = np.empty((b, h, w), np.float32)
    normal = np.empty((b, h, w, 3), np.float32)
    outs = [(rt.output(name, a), a) for name, a in
            (("hit_label", label), ("hit_cell", cell), ("hit_depth", depth), ("hit_normal", normal))]
    k = rt.kernel(_SOURCE, "trace_first_hit_kernel", occupancy.trace_options(grid.n_cells, rt.lanes))
    k(rt.queue, occupancy.tile_global(cam, b, rt.lanes), (*occupancy.TILE_LOCAL, 1), vol.labels, vol.field,
      *occupancy.trace_args(grid, cam), *(buf for buf, _ in outs))
    # The call's one synchronisation: the results go to the caller next.
    rt.fetch(outs)
    return label, cell, depth, normal

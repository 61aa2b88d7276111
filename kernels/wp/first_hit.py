"""``first_hit`` on Warp: the first occupied cell along each pixel's ray (conventions section 4, kernels/traversal.py).

One call: labels from the volume (one launch for scores, none for uint8 labels), the coarse pyramid (one launch),
then one thread per pixel and batch item walks its ray (:func:`~fruxel.kernels.wp.traverse.trace_ray`).
"""

from __future__ import annotations

from typing import Any

from fruxel.grid import FruxelGrid

from ..inputs import Hits, check_camera, inspect_volume
from . import traverse
from .arrays import Workspace, compute_device
from .occupancy import occupancy
from .runtime import warp
from .traverse import CameraInfo, GridInfo, camera_arg, face_normal, grid_info, pixel_ray, trace_ray

wp = warp()
wp.set_module_options({"enable_backward": False})


@wp.func
def centre_out(rank: int, h: int) -> int:
    """Image row of launch rank ``rank`` of ``h`` rows: the middle row first, then outwards, alternating (a
    permutation of ``0 .. h - 1``).

    The GPU starts blocks in launch order, and a frame takes as long as its slowest warp takes after it starts.
    The rays that walk longest are usually those through the middle of the image, which looks at the grid (on the
    kernel benchmark's view the longest warp alone runs most of the frame), so they are launched first rather
    than when the rows above them are done.
    """
    half = rank >> 1
    return wp.where((rank & 1) != 0, h // 2 - 1 - half, h // 2 + half)


@wp.kernel
def trace_first_hit_kernel(
    labels: wp.array2d(dtype=wp.uint8),
    pyramid: wp.array2d(dtype=wp.uint8),
    grid: GridInfo,
    camera: CameraInfo,
    b0: int,
    label: wp.array3d(dtype=wp.int32),
    cell: wp.array3d(dtype=wp.int64),
    depth: wp.array3d(dtype=wp.float32),
    normal: wp.array3d(dtype=wp.vec3),
):
    """Trace one pixel's ray to its first occupied cell.

    Launch: ``(n * h * w,)``, one thread per pixel of batch items ``b0 .. b0 + n - 1`` (x fastest, so a warp shares
    a row of rays; rows in :func:`centre_out` order). One-dimensional, with the coordinates unravelled here in 32
    bits: Warp unravels multi-dimensional launches with 64-bit divisions, which cost every thread about a hundred
    instructions.

    Args:
        labels: ``(B, N)`` uint8 labels, flat cell index ``(k * H + j) * W + i``, 0 = empty.
        pyramid: ``(B, bd * bh * bw + sd * sh * sw)`` uint8 block and super-block flags.
        grid: the grid.
        camera: the viewing camera (pose camera-to-grid).
        b0: first batch item of this launch.
        label: ``(B, h, w)`` int32 output: the hit cell's label, 0 on a miss.
        cell: ``(B, h, w)`` int64 output: the hit cell's flat index, -1 on a miss.
        depth: ``(B, h, w)`` float32 output: ray parameter (= viewing-camera z) of the entry point, 0 on a miss.
        normal: ``(B, h, w)`` vec3 output: unit entry-face normal, grid frame, facing the camera; zero on a miss.
    """
    tid = wp.tid()
    row = tid // camera.width
    x = tid - row * camera.width
    item = row // camera.height
    y = centre_out(row - item * camera.height, camera.height)
    b = b0 + item
    d = pixel_ray(camera, x, y)
    n, t, family, boundary, s = trace_ray(labels, pyramid, b, grid, camera.origin, d)
    if n < 0:
        label[b, y, x] = 0
        cell[b, y, x] = wp.int64(-1)
        depth[b, y, x] = 0.0
        normal[b, y, x] = wp.vec3(0.0)
    else:
        label[b, y, x] = int(labels[b, n])
        cell[b, y, x] = wp.int64(n)
        depth[b, y, x] = t
        normal[b, y, x] = face_normal(grid, family, boundary, s, d)


def first_hit(
    volume: Any,
    grid: FruxelGrid,
    camera: Any,
    *,
    device: str | None = None,
    threshold: float | None = None,
    probs: bool = False,
) -> Hits:
    """First occupied cell along each pixel's ray; see :func:`fruxel.kernels.first_hit`.

    Args:
        volume: labels ``(D, H, W)`` / ``(B, D, H, W)`` or scores ``(B, C, D, H, W)``; numpy or torch, CPU or CUDA.
            Torch tensors on the compute device are read in place, and the kernels run on torch's current stream.
        grid: the volume's grid.
        camera: one :class:`fruxel.Camera`.
        device: Warp device; None follows the data (a CUDA tensor's device, else CUDA when present, else CPU).
        threshold: occupancy threshold on ``1 - p(empty)`` for scores; None: argmax rule.
        probs: scores are probabilities.

    Returns:
        :class:`~fruxel.kernels.Hits` in the caller's kind of array, on the caller's device; ``(B, h, w)`` fields
        for batched volumes, ``(h, w)`` otherwise.

    Raises:
        VolumeError, fruxel.CameraError: bad input, before any device work.
        BackendError, BackendUnavailable: an unknown or absent device.
    """
    spec = inspect_volume(volume, grid, threshold, probs)
    cam = check_camera(camera)
    g = grid_info(grid)
    ws = Workspace.like(volume, compute_device(volume, device))

    labels, pyramid = occupancy(ws, volume, spec, grid)
    dims = (spec.batch, cam.height, cam.width)
    label = ws.empty(dims, wp.int32)
    cell = ws.empty(dims, wp.int64)
    depth = ws.empty(dims, wp.float32)
    normal = ws.empty(dims, wp.vec3)
    pixels = cam.height * cam.width
    per_launch = max(1, traverse.MAX_LAUNCH // pixels)  # int32 thread indices
    cam_arg = camera_arg(cam)
    for b0 in range(0, spec.batch, per_launch):
        n = min(per_launch, spec.batch - b0)
        ws.launch(
            trace_first_hit_kernel,
            (n * pixels,),
            [labels, pyramid, g, cam_arg, b0, label, cell, depth, normal],
            block_dim=traverse.TRACE_BLOCK_DIM,
        )
    lead = dims if spec.batched else dims[1:]
    return Hits(
        label=ws.result(label, shape=lead),
        cell=ws.result(cell, shape=lead),
        depth=ws.result(depth, shape=lead),
        normal=ws.result(normal, shape=(*lead, 3)),
    )


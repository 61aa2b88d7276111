"""``shell`` on Warp: the voxel model simplification (conventions section 4), keeping only cells that are some pixel's
first hit.

General path: labels and pyramid (see :mod:`.occupancy`), a zeroed uint8 mask ``(B, N)``, one launch per camera
marking every pixel's first-hit cell (:func:`~fruxel.kernels.wp.traverse.trace_ray`, the same walk as
``first_hit``), then one launch writing the output from the mask.

Fast path: the grid's own camera at native resolution (:func:`~fruxel.kernels.traversal.is_own_view`) looks
straight down the columns (its rays pass through the apex, so they cross no u- or v-plane), and its first hits are
the first occupied cell of each column. Alone, it runs as one launch that scans each column and writes the output
directly, reading scores as they are (no label pass, no pyramid, no mask). Beside other cameras it marks the mask
by a column scan instead of a traversal.

Removed cells become the canonical empty cell: label 0; logits ``(0, EMPTY_LOGIT, ..., EMPTY_LOGIT)``;
probabilities ``(1, 0, ..., 0)``.
"""

from __future__ import annotations

from typing import Any

from fruxel.grid import FruxelGrid

from ..inputs import check_cameras, empty_scores, inspect_volume
from ..traversal import is_own_view
from . import traverse
from .arrays import Buffer, Workspace, compute_device
from .occupancy import (
    SCORE_DTYPES,
    build_pyramid,
    label_scores,
    labels_input,
    score_label,
    score_mode,
    scores_input,
)
from .runtime import warp
from .traverse import CameraInfo, GridInfo, camera_arg, grid_info, pixel_ray, trace_ray

wp = warp()
wp.set_module_options({"enable_backward": False})


# ---------------------------------------------------------------------------------------------- own view alone
@wp.kernel
def keep_first_labels_kernel(
    labels: wp.array2d(dtype=wp.uint8),
    grid: GridInfo,
    out: wp.array2d(dtype=wp.uint8),
):
    """Own-view shell of one column of labels: keep its first occupied cell, zero the rest.

    Launch: ``(B, H * W)``, one thread per batch item and column ``j * W + i`` (consecutive threads read
    consecutive cells of a slice).

    Args:
        labels: ``(B, N)`` uint8 labels, flat cell index ``(k * H + j) * W + i``.
        grid: the grid.
        out: ``(B, N)`` uint8 output.
    """
    b, col = wp.tid()
    plane = grid.height * grid.width
    found = wp.bool(False)
    for k in range(grid.depth):
        n = k * plane + col
        lab = labels[b, n]
        if not found and int(lab) != 0:
            found = True
            out[b, n] = lab
        else:
            out[b, n] = wp.uint8(0)


@wp.kernel
def keep_first_scores_kernel(
    scores: wp.array3d(dtype=Any),
    mode: int,
    threshold: wp.float64,
    empty_first: float,
    empty_rest: float,
    grid: GridInfo,
    out: wp.array3d(dtype=Any),
):
    """Own-view shell of one column of scores, occupancy decided on the fly: keep the first occupied cell's
    scores, write the canonical empty cell everywhere else. Scores are read only up to the kept cell.

    Launch: ``(B, H * W)``, one thread per batch item and column ``j * W + i``.

    Args:
        scores: ``(B, C, N)`` float16/32/64 logits or probabilities.
        mode: occupancy rule (``MODE_ARGMAX``, ``MODE_LOGITS``, ``MODE_PROBS`` of :mod:`.occupancy`).
        threshold: threshold on ``1 - p(empty)`` for the threshold modes.
        empty_first: channel 0 of the canonical empty cell (0 for logits, 1 for probabilities).
        empty_rest: channels 1..C-1 of the canonical empty cell (``EMPTY_LOGIT`` for logits, 0 for probabilities).
        grid: the grid.
        out: ``(B, C, N)`` output, the dtype of ``scores``.
    """
    b, col = wp.tid()
    plane = grid.height * grid.width
    first = out.dtype(empty_first)
    rest = out.dtype(empty_rest)
    found = wp.bool(False)
    for k in range(grid.depth):
        n = k * plane + col
        keep = wp.bool(False)
        if not found:
            keep = score_label(scores, b, n, mode, threshold) != 0
            found = keep
        if keep:
            for c in range(scores.shape[1]):
                out[b, c, n] = scores[b, c, n]
        else:
            out[b, 0, n] = first
            for c in range(1, scores.shape[1]):
                out[b, c, n] = rest


# ---------------------------------------------------------------------------------------------- general path
@wp.kernel
def mark_columns_kernel(
    labels: wp.array2d(dtype=wp.uint8),
    grid: GridInfo,
    mask: wp.array2d(dtype=wp.uint8),
):
    """Mark the first occupied cell of one column: the own-view camera's first hit for that pixel.

    Launch: ``(B, H * W)``, one thread per batch item and column ``j * W + i``.

    Args:
        labels: ``(B, N)`` uint8 labels.
        grid: the grid.
        mask: ``(B, N)`` uint8, set to 1 at the column's first occupied cell.
    """
    b, col = wp.tid()
    plane = grid.height * grid.width
    for k in range(grid.depth):
        n = k * plane + col
        if int(labels[b, n]) != 0:
            mask[b, n] = wp.uint8(1)
            break


@wp.kernel
def mark_shell_kernel(
    labels: wp.array2d(dtype=wp.uint8),
    pyramid: wp.array2d(dtype=wp.uint8),
    grid: GridInfo,
    camera: CameraInfo,
    mask: wp.array2d(dtype=wp.uint8),
):
    """Mark the first-hit cell of one pixel's ray (several pixels may mark one cell; they all store 1).

    Launch: ``(B, h, w)``, one thread per batch item and pixel of ``camera``.

    Args:
        labels: ``(B, N)`` uint8 labels.
        pyramid: ``(B, bd * bh * bw + sd * sh * sw)`` uint8 block and super-block flags.
        grid: the grid.
        camera: the viewing camera (pose camera-to-grid).
        mask: ``(B, N)`` uint8, set to 1 at the hit cell.
    """
    b, y, x = wp.tid()
    n, _t, _family, _boundary, _s = trace_ray(
        labels, pyramid, b, grid, camera.origin, pixel_ray(camera, x, y)
    )
    if n >= 0:
        mask[b, n] = wp.uint8(1)


@wp.kernel
def write_shell_labels_kernel(
    labels: wp.array2d(dtype=wp.uint8),
    mask: wp.array2d(dtype=wp.uint8),
    out: wp.array2d(dtype=wp.uint8),
):
    """Write one cell of the label shell: its label where marked, else 0.

    Launch: ``(B, N)``, one thread per cell.

    Args:
        labels: ``(B, N)`` uint8 labels.
        mask: ``(B, N)`` uint8 marks.
        out: ``(B, N)`` uint8 output.
    """
    b, n = wp.tid()
    if int(mask[b, n]) != 0:
        out[b, n] = labels[b, n]
    else:
        out[b, n] = wp.uint8(0)


@wp.kernel
def write_shell_scores_kernel(
    scores: wp.array3d(dtype=Any),
    mask: wp.array2d(dtype=wp.uint8),
    empty_first: float,
    empty_rest: float,
    out: wp.array3d(dtype=Any),
):
    """Write one cell of the score shell: its scores where marked, else the canonical empty cell.

    Launch: ``(B, N)``, one thread per cell.

    Args:
        scores: ``(B, C, N)`` float16/32/64 logits or probabilities.
        mask: ``(B, N)`` uint8 marks.
        empty_first: channel 0 of the canonical empty cell.
        empty_rest: channels 1..C-1 of the canonical empty cell.
        out: ``(B, C, N)`` output, the dtype of ``scores``.
    """
    b, n = wp.tid()
    if int(mask[b, n]) != 0:
        for c in range(scores.shape[1]):
            out[b, c, n] = scores[b, c, n]
    else:
        out[b, 0, n] = out.dtype(empty_first)
        for c in range(1, scores.shape[1]):
            out[b, c, n] = out.dtype(empty_rest)


for _t in SCORE_DTYPES:
    wp.overload(keep_first_scores_kernel, {"scores": wp.array3d(dtype=_t), "out": wp.array3d(dtype=_t)})
    wp.overload(write_shell_scores_kernel, {"scores": wp.array3d(dtype=_t), "out": wp.array3d(dtype=_t)})


# ---------------------------------------------------------------------------------------------- host side
def shell(
    volume: Any,
    grid: FruxelGrid,
    cameras: Any,
    *,
    device: str | None = None,
    threshold: float | None = None,
    probs: bool = False,
) -> Any:
    """The VMS shell; see :func:`fruxel.kernels.shell`.

    Args:
        volume: labels ``(D, H, W)`` / ``(B, D, H, W)`` or scores ``(B, C, D, H, W)``; numpy or torch, CPU or CUDA.
            Torch tensors on the compute device are read in place, and the kernels run on torch's current stream.
        grid: the volume's grid.
        cameras: one :class:`fruxel.Camera` or a non-empty list; the grid's own camera at native resolution takes
            the column fast path.
        device: Warp device; None follows the data.
        threshold: occupancy threshold on ``1 - p(empty)`` for scores; None: argmax rule.
        probs: scores are probabilities (also picks the canonical empty cell).

    Returns:
        An array of the volume's shape, dtype, kind and device.

    Raises:
        VolumeError, fruxel.CameraError: bad input, before any device work.
        BackendError, BackendUnavailable: an unknown or absent device.
    """
    spec = inspect_volume(volume, grid, threshold, probs)
    cams = check_cameras(cameras)
    ws = Workspace.like(volume, compute_device(volume, device))
    own_view = [is_own_view(c, grid) for c in cams]
    own = any(own_view)
    others = [c for c, o in zip(cams, own_view, strict=True) if not o]
    g = grid_info(grid)
    batch, n = spec.batch, grid.n_cells
    columns = (batch, grid.height * grid.width)
    shape = tuple(int(s) for s in volume.shape)

    if spec.is_scores:
        scores = scores_input(ws, volume, spec, grid)
        mode, thr = score_mode(spec.threshold, spec.probs)
        first, rest = empty_scores(spec)
        out = ws.empty(scores.shape, scores.dtype)
        if not others:
            ws.launch(
                keep_first_scores_kernel, columns, [scores, mode, wp.float64(thr), first, rest, g, out]
            )
        else:
            mask = _mark(ws, label_scores(ws, scores, spec), grid, own, others)
            ws.launch(write_shell_scores_kernel, (batch, n), [scores, mask, first, rest, out])
    else:
        labels = labels_input(ws, volume, spec, grid)
        out = ws.empty((batch, n), wp.uint8)
        if not others:
            ws.launch(keep_first_labels_kernel, columns, [labels, g, out])
        else:
            mask = _mark(ws, labels, grid, own, others)
            ws.launch(write_shell_labels_kernel, (batch, n), [labels, mask, out])
    return ws.result(out, shape=shape, dtype=volume.dtype)


def _mark(ws: Workspace, labels: Buffer, grid: FruxelGrid, own: bool, others: list[Any]) -> Buffer:
    """``(B, N)`` uint8 mask of the first-hit cells of every pixel of the own-view camera (when ``own``) and of
    each camera of ``others``."""
    g = grid_info(grid)
    batch = labels.shape[0]
    pyramid = build_pyramid(ws, labels, grid)
    mask = ws.empty(labels.shape, wp.uint8, zero=True)
    if own:
        ws.launch(mark_columns_kernel, (batch, grid.height * grid.width), [labels, g, mask])
    for cam in others:
        args = [labels, pyramid, g, camera_arg(cam), mask]
        ws.launch(mark_shell_kernel, (batch, cam.height, cam.width), args, block_dim=traverse.TRACE_BLOCK_DIM)
    return mask

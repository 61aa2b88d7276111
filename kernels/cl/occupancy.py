"""Occupancy on the OpenCL device: the uint8 label volume the traversal reads, its coarse pyramid, and the
traversal's build options and arguments that depend on it.

Float scores are turned into labels once per call by :file:`occupancy.cl` (SPEC section 2's rule), so the
traversal's inner loop only ever tests a byte. The pyramid (blocks of ``BLOCK`` cells a side from
:mod:`fruxel.kernels.traversal`, and a second level of super-blocks ``BLOCK^2`` cells a side) is rebuilt on every
call from the labels: it is cheap next to the traversal, and no index cache survives a call.

The traversal's source (:file:`first_hit.cl`), build options and arguments live here too: they depend on the
pyramid's levels, and both :mod:`.first_hit` and :mod:`.shell` launch the traversal.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from .. import traversal
from ..inputs import MAX_LABEL, VolumeError, VolumeSpec
from .runtime import Runtime, defines, source

LEVELS = 3
"""Pyramid levels used by the traversal: cells, blocks of ``BLOCK`` cells a side and super-blocks of ``BLOCK^2``
cells a side (1 gives the plain loop, 2 blocks only)."""

LOG_BLOCK = traversal.BLOCK.bit_length() - 1
if 1 << LOG_BLOCK != traversal.BLOCK:  # pragma: no cover - guards a future edit of traversal.BLOCK
    raise ImportError(f"the OpenCL pyramid needs traversal.BLOCK to be a power of two, got {traversal.BLOCK}")

_SOURCE = source(__file__)
TRACE_SOURCE = source(__file__, "first_hit")
"""The traversal source, :file:`first_hit.cl`; :file:`shell.cl` is compiled after it."""

TRACE_LOCAL = (16, 4)
"""Work-group shape of the per-pixel traversal kernels (pixels along x, y): PoCL runs a work-group as one loop,
so a tile of neighbouring rays shares cache lines of the label volume."""
_LOCAL_CELLS = 256
"""Work-group size of label_scores_kernel (PoCL vectorises its straight-line body across work-items)."""
_LOCAL_PYRAMID = 16
"""Work-group width of pyramid (coarse cells along x)."""

_SCORE_TYPES = {np.dtype(np.float16): "SCORE_HALF", np.dtype(np.float32): "SCORE_FLOAT",
                np.dtype(np.float64): "SCORE_DOUBLE"}


def level_shape(grid: FruxelGrid, level: int) -> tuple[int, int, int]:
    """``(D, H, W)`` of pyramid level ``level`` (0 = cells): each axis ``ceil(n / BLOCK^level)``."""
    s = traversal.BLOCK**level
    return tuple(-(-n // s) for n in grid.shape)  # type: ignore[return-value]


@dataclass
class DeviceVolume:
    """A volume ready for the traversal kernels, valid until the call's final synchronisation."""

    labels: Any
    """uint8 ``(B, D, H, W)`` device buffer: 0 = empty, else the label."""
    levels: list[Any]
    """Pyramid buffers: level 1 ``(B, *level_shape(grid, 1))`` uint8, level 2 likewise (a 1-byte dummy when the
    traversal uses fewer levels); empty when not built."""
    data: Any = None
    """A device view of the host array the call was given (after :func:`runtime.host_array`) when one was made
    (float scores, uint8 labels), else None."""
    keep: list[Any] = field(default_factory=list)
    """Host arrays the device may still read; they must outlive the call's kernels."""


def round_up(x: int, m: int) -> int:
    """``x`` rounded up to a multiple of ``m`` (an NDRange padded to whole work-groups)."""
    return -(-x // m) * m


def cell_counts(grid: FruxelGrid) -> np.ndarray:
    """Cells per family as the kernels' int4 argument ``(W, H, D, 1)``."""
    return np.array([grid.width, grid.height, grid.depth, 1], np.int32)


def check_spec(spec: VolumeSpec) -> None:
    """What this backend needs beyond :func:`fruxel.kernels.inputs.inspect_volume`, checked before device work.

    Raises:
        VolumeError: scores with more than ``MAX_LABEL + 1`` channels (their labels would not fit in a byte).
    """
    if spec.is_scores and spec.channels > MAX_LABEL + 1:
        raise VolumeError(f"scores have {spec.channels} channels; at most {MAX_LABEL + 1} classes fit uint8 labels")


def labels_from_host(rt: Runtime, arr: np.ndarray, spec: VolumeSpec, grid: FruxelGrid,
                     pyramid: bool = True) -> DeviceVolume:
    """Put a validated volume on the device as uint8 labels and build its pyramid (all enqueued, no wait).

    Args:
        rt: the device runtime (its lock held by the caller).
        arr: C-contiguous host array: labels ``(D, H, W)`` / ``(B, D, H, W)`` of any integer or bool dtype with
            values in [0, 255], or scores ``(B, C, D, H, W)`` float16/32/64 (see :func:`runtime.host_array`).
        spec: :func:`fruxel.kernels.inputs.inspect_volume`'s description of the volume.
        grid: the volume's grid.
        pyramid: build the pyramid (only the traversal needs it); without, :attr:`DeviceVolume.levels` is empty.

    The caller has checked ``spec`` with :func:`check_spec`.
    """
    b = spec.batch
    cells = grid.n_cells
    keep: list[Any] = []
    if spec.is_scores:
        scores = arr
        if scores.dtype == np.float64 and not rt.has_fp64:
            scores = scores.astype(np.float32)
        keep.append(scores)
        kind = _SCORE_TYPES[scores.dtype]
        mode = 0 if spec.threshold is None else (2 if spec.probs else 1)
        k = rt.kernel(_SOURCE, "label_scores_kernel",
                      defines(**{kind: 1}, NUM_CHANNELS=spec.channels, MODE=mode, BLOCK=traversal.BLOCK))
        real = np.float64 if kind == "SCORE_DOUBLE" else np.float32
        labels = rt.scratch("labels", b * cells)
        data = rt.input("scores", scores)
        k(rt.queue, (round_up(cells, _LOCAL_CELLS), b), (_LOCAL_CELLS, 1), data, labels, np.int64(cells),
          real(spec.threshold or 0.0))
        if scores is not arr:
            data = None
    else:
        if arr.dtype == np.bool_:
            lab = arr.view(np.uint8)
        elif arr.dtype == np.uint8:
            lab = arr
        else:
            lab = arr.astype(np.uint8)  # values were checked to lie in [0, MAX_LABEL]
        keep.append(lab)
        labels = rt.input("labels", lab)
        data = labels if lab is arr else None
    levels = build_pyramid(rt, labels, grid, b) if pyramid else []
    return DeviceVolume(labels=labels, levels=levels, data=data, keep=keep)


def build_pyramid(rt: Runtime, labels: Any, grid: FruxelGrid, batch: int) -> list[Any]:
    """Enqueue the pyramid of a uint8 ``(B, D, H, W)`` label buffer: levels 1 .. LEVELS-1 in pooled buffers,
    padded with 1-byte dummies to two entries (the kernels always take two level buffers)."""
    opts = defines(SCORE_FLOAT=1, NUM_CHANNELS=2, MODE=0, BLOCK=traversal.BLOCK)
    k = rt.kernel(_SOURCE, "build_pyramid_kernel", opts)
    out = []
    fine = labels
    for level in range(1, LEVELS):
        nf = level_shape(grid, level - 1)
        nc = level_shape(grid, level)
        coarse = rt.scratch(f"pyramid{level}", batch * int(np.prod(nc)))
        k(rt.queue, (round_up(nc[2], _LOCAL_PYRAMID), nc[1], nc[0] * batch), (_LOCAL_PYRAMID, 1, 1), fine, coarse,
          np.array([nf[2], nf[1], nf[0], 1], np.int32), np.array([nc[2], nc[1], nc[0], 1], np.int32))
        out.append(coarse)
        fine = coarse
    while len(out) < 2:
        out.append(rt.scratch(f"pyramid{len(out) + 1}", 1))
    return out


def trace_options() -> tuple[str, ...]:
    """``-D`` build options of the traversal, all from :mod:`fruxel.kernels.traversal`."""
    return defines(BLOCK=traversal.BLOCK, LOG_BLOCK=LOG_BLOCK, LEVELS=LEVELS, FAMILY_U=traversal.FAMILY_U,
                   FAMILY_V=traversal.FAMILY_V, FAMILY_Z=traversal.FAMILY_Z)


def trace_args(grid: FruxelGrid, camera: Camera) -> tuple[Any, ...]:
    """The traversal kernels' scalar arguments after the three map buffers: grid (float8), camera (float16),
    cells per family (int4 ``(W, H, D, 1)``), image width and height, and the iteration guard."""
    return (traversal.grid_params(grid), traversal.camera_params(camera),
            cell_counts(grid), np.int32(camera.width),
            np.int32(camera.height), np.int32((LEVELS + 1) * traversal.max_steps(grid)))


def trace_global(camera: Camera, batch: int) -> tuple[int, int, int]:
    """NDRange of the per-pixel kernels: the image rounded up to whole work-groups, times the batch."""
    lx, ly = TRACE_LOCAL
    return (round_up(camera.width, lx), round_up(camera.height, ly), batch)

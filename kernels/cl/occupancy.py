"""Occupancy on the OpenCL device: the uint8 label volume the traversal reads, its field, and the
traversal's build options and arguments that depend on them.

Float scores are turned into labels once per call by :file:`occupancy.cl` (conventions section 2's rule), so the
traversal's inner loop only ever tests a byte. The field (per group of ``GROUP^3`` cells, the chessboard
distance to the nearest group holding an occupied cell, capped at :data:`DIST_CAP`, and which of the group's cells
are occupied) is rebuilt on every call from the labels: it is cheap next to the traversal, and no index cache
survives a call. :file:`walk.h` jumps with it out of empty cubes of groups (kernels/traversal.py, "Empty-space
skipping") and tests cells with it.

The traversal's build options and arguments live here too: they depend on the field's layout, and :mod:`.first_hit`,
:mod:`.shell` and :mod:`.soft_first_hit` all build the traversal.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from .. import traversal
from ..inputs import MAX_LABEL, VolumeError, VolumeSpec
from .runtime import Runtime, defines, source

GROUP_LOG = 1
"""log2 of the edge, in cells, of a group of the field: groups of 2 x 2 x 2 cells, whose 8 cells fit the field's
occupancy mask (the kernels require 1). Groups of 1 cell skip few more iterations on the room but cost eight
times the building, groups of 4 take many more iterations (measured in benchmarks/PERF_NOTES.md)."""
DIST_CAP = 15
"""Largest distance (in groups) the field records: each axis pass looks this far. 0 turns skipping off (every group
reads 0, every iteration is a plain step), which tests use to check that skipping changes nothing."""
TILE = 4
"""Width, in pixels, of the tile of rays one work-item of the first-hit walk traces, one ray per vector lane: 4 x 4
pixels for 16 lanes, 4 x 2 for 8 (:attr:`.runtime.Runtime.lanes`; :file:`walk.h` lays them out for 4)."""
TILE_LOCAL = (16, 1)
"""Work-group shape of the tile kernels, in tiles along x, y: a row of 16 tiles (64 x 4 pixels) per work-group
(square groups measured slower: benchmarks/PERF_NOTES.md)."""
TRACE_LOCAL = (16, 4)
"""Work-group shape of the per-pixel kernels (soft_first_hit), pixels along x, y: PoCL runs a work-group as one
loop, so a tile of neighbouring rays shares cache lines of the volume."""
PASS_WIDE_FROM = 2**31
"""Elements of the passes' buffers from which their offsets are computed in 64 bits (PASS_WIDE; tests lower it)."""
FIELD_GAP = 16
"""Elements after each row of the field (and before the first): the x pass reads them as empty neighbours."""
_FIELD_VECTOR = 16
"""Groups per work-item of the field kernels (one uchar16): rows are padded to a multiple of it."""
_LOCAL_CELLS = 256
"""Work-group size of label_scores_kernel (PoCL vectorises its straight-line body across work-items)."""

if not 0 <= DIST_CAP <= min(FIELD_GAP, 255):  # pragma: no cover - guards a future edit
    raise ImportError(f"DIST_CAP must lie in [0, {min(FIELD_GAP, 255)}], got {DIST_CAP}")

_SOURCE = source(__file__)

_SCORE_TYPES = {np.dtype(np.float16): "SCORE_HALF", np.dtype(np.float32): "SCORE_FLOAT",
                np.dtype(np.float64): "SCORE_DOUBLE"}


def field_layout(grid: FruxelGrid) -> np.ndarray:
    """The distance field's row length, rows per slice and slices, as the kernels' int4 ``gd``:
    ``(GWP + FIELD_GAP, GH + 1, GD, 1)`` with ``GD, GH = ceil((D, H) / GROUP)`` and ``GWP = ceil(W / GROUP)`` rounded
    up to a multiple of 16 (see :file:`occupancy.cl`)."""
    g = 1 << GROUP_LOG
    gwp = round_up(-(-grid.width // g), _FIELD_VECTOR)
    return np.array([gwp + FIELD_GAP, -(-grid.height // g) + 1, -(-grid.depth // g), 1], np.int32)


def field_elements(grid: FruxelGrid, batch: int) -> int:
    """Elements (ushorts) of the walk's fields of ``batch`` volumes: ``(B, GD, GH + 1, GWP + FIELD_GAP)``."""
    gd = field_layout(grid)
    return batch * int(gd[0]) * int(gd[1]) * int(gd[2])


def _pass_lead(gd: np.ndarray) -> int:
    """Elements of the passes' buffers before the first row (and after the last): the z pass's reach, DIST_CAP
    slices, and at least the x pass's, FIELD_GAP."""
    return max(DIST_CAP * int(gd[0]) * int(gd[1]), FIELD_GAP)


@dataclass
class DeviceVolume:
    """A volume ready for the traversal kernels, valid until the call's final synchronisation."""

    labels: Any
    """uint8 ``(B, D, H, W)`` device buffer: 0 = empty, else the label."""
    field: Any = None
    """Its field for the first-hit walk (:func:`build_field`; layout :func:`field_layout`), or None when not
    built."""
    data: Any = None
    """A device view of the host array the call was given (after :func:`runtime.host_array`) when one was made
    (float scores, uint8 labels), else None."""
    keep: list[Any] = dataclasses.field(default_factory=list)
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
                     walk: bool = True) -> DeviceVolume:
    """Put a validated volume on the device as uint8 labels and build its field (all enqueued, no wait).

    Args:
        rt: the device runtime (its lock held by the caller).
        arr: C-contiguous host array: labels ``(D, H, W)`` / ``(B, D, H, W)`` of any integer or bool dtype with
            values in [0, 255], or scores ``(B, C, D, H, W)`` float16/32/64 (see :func:`runtime.host_array`).
        spec: :func:`fruxel.kernels.inputs.inspect_volume`'s description of the volume.
        grid: the volume's grid.
        walk: build the field (only the first-hit walk needs it); without, :attr:`DeviceVolume.field` is None.

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
                      _options(**{kind: 1}, NUM_CHANNELS=spec.channels, MODE=mode))
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
    walk_field = build_field(rt, labels, grid, b) if walk else None
    return DeviceVolume(labels=labels, field=walk_field, data=data, keep=keep)


def _options(**values: int) -> tuple[str, ...]:
    """Build options of :file:`occupancy.cl`: ``values`` (AXIS 1 and PASS_WIDE 0 unless given) and the field's
    constants."""
    return defines(**{"AXIS": 1, "PASS_WIDE": 0, **values}, GROUP_LOG=GROUP_LOG, DIST_CAP=DIST_CAP,
                   FIELD_GAP=FIELD_GAP)


def build_field(rt: Runtime, labels: Any, grid: FruxelGrid, batch: int) -> Any:
    """Enqueue the walk's field of a uint8 ``(B, D, H, W)`` label buffer (:file:`occupancy.cl`): mark the occupied
    groups and their masks, then one distance pass per axis between pooled buffers, the last writing the ushort
    field. Returns the field's buffer (layout :func:`field_layout`, :func:`field_elements` ushorts)."""
    gd = field_layout(grid)
    lead = _pass_lead(gd)
    count = field_elements(grid, batch)
    a, b, masks = (rt.scratch(name, count + 2 * lead) for name in ("field_a", "field_b", "field_masks"))
    field = rt.scratch("field", 2 * count)
    gwp = int(gd[0]) - FIELD_GAP
    groups = (gwp, int(gd[1]), int(gd[2]) * batch)
    # Work-groups of whole rows (PoCL vectorises the work-items of a work-group): the longest that divides GWP.
    local = (next(m for m in (64, 32, 16) if gwp % m == 0), 1, 1)
    n, lead_arg = cell_counts(grid), np.int32(lead)

    def kernel(name: str, axis: int) -> Any:
        return rt.kernel(_SOURCE, name, _options(SCORE_FLOAT=1, NUM_CHANNELS=2, MODE=0, AXIS=axis,
                                                  PASS_WIDE=int(count + 2 * lead >= PASS_WIDE_FROM)))

    # A work-group per row of groups (PoCL's own choice of work-group split the kernel unevenly over its threads).
    row = gwp // _FIELD_VECTOR + 1
    kernel("mark_groups_kernel", 1)(rt.queue, (row, *groups[1:]), (row, 1, 1), labels, a, masks, n, gd, lead_arg)
    kernel("chessboard_x_kernel", 1)(rt.queue, groups, local, a, b, gd, lead_arg)
    kernel("chessboard_yz_kernel", 1)(rt.queue, groups, local, b, a, gd, lead_arg)
    kernel("chessboard_yz_kernel", 2)(rt.queue, groups, local, a, masks, field, gd, lead_arg)
    return field


def ray_options() -> tuple[str, ...]:
    """``-D`` build options of :file:`ray.h`, from :mod:`fruxel.kernels.traversal`."""
    return defines(FAMILY_U=traversal.FAMILY_U, FAMILY_V=traversal.FAMILY_V, FAMILY_Z=traversal.FAMILY_Z)


def trace_options(cells: int, lanes: int) -> tuple[str, ...]:
    """``-D`` build options of the tile walk (:file:`walk.h`, :file:`ray.h`): ``cells`` (per volume) decides
    whether cell offsets need 64 bits, ``lanes`` is the rays per work-item (:attr:`.runtime.Runtime.lanes`)."""
    return ray_options() + defines(LANES=lanes, TILE=TILE, GROUP_LOG=GROUP_LOG, WIDE_INDEX=int(cells >= 2**31))


def trace_args(grid: FruxelGrid, camera: Camera) -> tuple[Any, ...]:
    """The tile kernels' arguments after the labels and field buffers: the field's layout (int4), grid (float8),
    camera (float16), cells per family (int4 ``(W, H, D, 1)``), image width and height, and the iteration guard
    (every iteration moves one family at least one cell on)."""
    return (field_layout(grid), traversal.grid_params(grid), traversal.camera_params(camera), cell_counts(grid),
            np.int32(camera.width), np.int32(camera.height), np.int32(traversal.max_steps(grid)))


def tile_global(camera: Camera, batch: int, lanes: int) -> tuple[int, int, int]:
    """NDRange of the tile kernels: the image's tiles of ``TILE x lanes / TILE`` pixels rounded up to whole
    work-groups, times the batch."""
    lx, ly = TILE_LOCAL
    return (round_up(-(-camera.width // TILE), lx), round_up(-(-camera.height // (lanes // TILE)), ly), batch)


def trace_global(camera: Camera, batch: int) -> tuple[int, int, int]:
    """NDRange of the per-pixel kernels: the image rounded up to whole work-groups, times the batch."""
    lx, ly = TRACE_LOCAL
    return (round_up(camera.width, lx), round_up(camera.height, ly), batch)

"""Occupancy on the device: float scores to uint8 labels (conventions section 2), and the coarse pyramid for empty-space
skipping.

The traversal reads only uint8 labels ``(B, D * H * W)`` (flat cell index ``(k * H + j) * W + i``, 0 = empty) and
the two-level pyramid ``(B, bd * bh * bw + sd * sh * sw)`` uint8: flags of the blocks of
:data:`~fruxel.kernels.traversal.BLOCK` cells (``bd = ceil(D / BLOCK)`` and likewise, flat block index
``(bk * bh + bj) * bw + bi``), then of the super-blocks of ``SUPER`` blocks (from ``GridInfo.supers_offset``);
nonzero where the box holds an occupied cell. Both are built on every call, on the device, from the volume as it
is.

Occupancy rule for scores ``(B, C, D, H, W)`` (channel 0 = empty): without a threshold a cell is occupied when its
argmax is not 0; with one, when ``1 - p(empty) >= threshold``, ``p = softmax(logits)`` or the probabilities as
given. The label of an occupied cell is the argmax over channels ``1..C-1``; ties go to the lowest index.
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fruxel.grid import FruxelGrid

from ..inputs import MAX_LABEL, VolumeError, VolumeSpec
from .arrays import Buffer, Workspace, torch_dtype
from .runtime import warp
from .traverse import BLOCK, SUPER, GridInfo, grid_info, pyramid_size

wp = warp()
wp.set_module_options({"enable_backward": False})

MODE_ARGMAX = wp.constant(0)
"""Occupied when the argmax is not channel 0."""
MODE_LOGITS = wp.constant(1)
"""Occupied when ``1 - softmax(scores)[0] >= threshold``."""
MODE_PROBS = wp.constant(2)
"""Occupied when ``1 - scores[0] >= threshold``."""

SCORE_DTYPES = (wp.float16, wp.float32, wp.float64)
"""Score dtypes the kernels take as they are; others (bfloat16, float8, long double) are converted first."""


@wp.func
def widen(x: wp.float16) -> wp.float32:
    """Arithmetic type of a score: float32 for float16 (exp in half precision loses the threshold)."""
    return wp.float32(x)


@wp.func
def widen(x: wp.float32) -> wp.float32:  # noqa: F811 - Warp overloads functions by argument type
    """Arithmetic type of a score: float32 stays."""
    return x


@wp.func
def widen(x: wp.float64) -> wp.float64:  # noqa: F811 - Warp overloads functions by argument type
    """Arithmetic type of a score: float64 stays."""
    return x


@wp.func
def score_label(scores: wp.array3d(dtype=Any), b: int, n: int, mode: int, threshold: wp.float64) -> int:
    """Label of cell ``n`` of batch item ``b`` from its scores ``(B, C, N)``: 0 when empty, else the argmax over
    channels ``1..C-1`` (ties to the lowest). ``mode`` is ``MODE_ARGMAX``, ``MODE_LOGITS`` or ``MODE_PROBS``."""
    s0 = scores[b, 0, n]
    best = scores[b, 1, n]
    label = wp.int32(1)
    for c in range(2, scores.shape[1]):
        v = scores[b, c, n]
        if v > best:
            best = v
            label = c
    if mode == MODE_ARGMAX:
        if best > s0:
            return label
        return 0
    if mode == MODE_PROBS:
        if wp.float64(1.0) - wp.float64(s0) >= threshold:
            return label
        return 0
    # softmax's 1 - p(empty) = sum_{c >= 1} e_c / sum_c e_c, shifted by the maximum so nothing overflows
    m = wp.max(widen(s0), widen(best))
    rest = type(m)(0.0)
    for c in range(1, scores.shape[1]):
        rest += wp.exp(widen(scores[b, c, n]) - m)
    if wp.float64(rest / (wp.exp(widen(s0) - m) + rest)) >= threshold:
        return label
    return 0


@wp.kernel
def label_scores_kernel(
    scores: wp.array3d(dtype=Any),
    mode: int,
    threshold: wp.float64,
    labels: wp.array2d(dtype=wp.uint8),
):
    """Label one cell from its scores (:func:`score_label`).

    Launch: ``(B, N)``, one thread per cell, ``N = D * H * W``.

    Args:
        scores: ``(B, C, N)`` float16/32/64 logits or probabilities, NCDHW flattened over DHW.
        mode: ``MODE_ARGMAX``, ``MODE_LOGITS`` or ``MODE_PROBS``.
        threshold: threshold on ``1 - p(empty)`` (unused for ``MODE_ARGMAX``).
        labels: ``(B, N)`` uint8 output, 0 = empty.
    """
    b, n = wp.tid()
    labels[b, n] = wp.uint8(score_label(scores, b, n, mode, threshold))


for _t in SCORE_DTYPES:
    wp.overload(label_scores_kernel, {"scores": wp.array3d(dtype=_t)})


@wp.func
def mark_boxes(pyramid: wp.array2d(dtype=wp.uint8), b: int, grid: GridInfo, bk: int, bj: int, bi: int):
    """Flag block ``(bk, bj, bi)`` of batch item ``b`` and its super-block occupied. Flags start at zero and are
    only ever set to 1, so many threads may set one; each is read first, because stores to one address queue up in
    the cache."""
    blk = (bk * grid.blocks_v + bj) * grid.blocks_u + bi
    if pyramid[b, blk] == wp.uint8(0):
        pyramid[b, blk] = wp.uint8(1)
    sup = grid.supers_offset + ((bk // SUPER) * grid.supers_v + bj // SUPER) * grid.supers_u + bi // SUPER
    if pyramid[b, sup] == wp.uint8(0):
        pyramid[b, sup] = wp.uint8(1)


@wp.kernel
def build_pyramid_kernel(
    labels: wp.array2d(dtype=wp.uint8),
    grid: GridInfo,
    span: int,
    pyramid: wp.array2d(dtype=wp.uint8),
):
    """Flag the blocks and super-blocks of ``span`` consecutive block rows (a block row: the up to ``BLOCK`` cells
    of one block in one row ``(k, j)``) that hold an occupied cell. Flags start at zero and are only ever set to 1,
    so the threads of a box may all write it.

    Launch: ``(B, D, H, ceil(bw / span))``, one thread per span of block rows; consecutive threads read
    consecutive cells. Span 1 gives the GPU many threads; on the CPU, one thread per row saves per-thread cost.

    Args:
        labels: ``(B, N)`` uint8 labels, flat cell index ``(k * H + j) * W + i``.
        grid: the grid (sizes, box counts, ``supers_offset``).
        span: block rows per thread.
        pyramid: ``(B, bd * bh * bw + sd * sh * sw)`` uint8, zeroed: block flags at flat index
            ``(bk * bh + bj) * bw + bi``, then super-block flags at ``supers_offset + (qk * sh + qj) * sw + qi``.
    """
    b, k, j, s = wp.tid()
    base = (k * grid.height + j) * grid.width
    bj = j // BLOCK
    bk = k // BLOCK
    for bi in range(s * span, wp.min(s * span + span, grid.blocks_u)):
        occupied = wp.int32(0)
        for i in range(bi * BLOCK, wp.min(bi * BLOCK + BLOCK, grid.width)):
            occupied = occupied | int(labels[b, base + i])
        if occupied != 0:
            mark_boxes(pyramid, b, grid, bk, bj, bi)


@wp.kernel
def build_pyramid_words_kernel(
    words: wp.array(dtype=wp.int32),
    grid: GridInfo,
    pyramid: wp.array2d(dtype=wp.uint8),
):
    """:func:`build_pyramid_kernel` for one block row read as one 32-bit word: ``BLOCK == 4`` cells, ``W`` a
    multiple of 4 and the labels 4-byte aligned, so that every block row is one aligned word (one load instead of
    four; the GPU path).

    Launch: ``(B * D * H * bw,)``, one thread per block row (word). One-dimensional, with the coordinates unravelled
    here in 32 bits: Warp unravels multi-dimensional launches with 64-bit divisions, which would cost this short
    kernel more than its work.

    Args:
        words: ``(B * N / 4,)`` int32, the uint8 labels ``(B, N)`` seen four cells per word.
        grid: the grid (sizes, box counts, ``supers_offset``).
        pyramid: ``(B, bd * bh * bw + sd * sh * sw)`` uint8, zeroed (layout of :func:`build_pyramid_kernel`).
    """
    w = wp.tid()
    if words[w] != 0:
        row = w // grid.blocks_u
        bi = w - row * grid.blocks_u
        slab = row // grid.height
        bj = (row - slab * grid.height) // BLOCK
        b = slab // grid.depth
        bk = (slab - b * grid.depth) // BLOCK
        mark_boxes(pyramid, b, grid, bk, bj, bi)


# ---------------------------------------------------------------------------------------------- host side
def score_mode(threshold: float | None, probs: bool) -> tuple[int, float]:
    """``(mode, threshold)`` kernel arguments for the occupancy rule."""
    if threshold is None:
        return int(MODE_ARGMAX), 0.0
    return (int(MODE_PROBS) if probs else int(MODE_LOGITS)), float(threshold)


def score_dtype(volume: Any) -> Any:
    """Warp dtype the kernels read ``volume``'s scores as: its own for float16/32/64; float32 for torch's other
    float types (bfloat16, float8), float64 for numpy's long double."""
    name = str(volume.dtype).removeprefix("torch.")
    for t in SCORE_DTYPES:
        if name == np.dtype(wp.dtype_to_numpy(t)).name:
            return t
    return wp.float64 if isinstance(volume, np.ndarray) else wp.float32


def scores_input(ws: Workspace, volume: Any, spec: VolumeSpec, grid: FruxelGrid) -> Buffer:
    """Validated float scores as a ``(B, C, N)`` array on the compute device (zero copy where possible).

    Raises:
        VolumeError: more channels than uint8 labels can name.
    """
    if spec.channels > MAX_LABEL + 1:
        raise VolumeError(f"scores have {spec.channels} channels; labels are uint8, so at most {MAX_LABEL + 1}")
    return ws.input(volume, shape=(spec.batch, spec.channels, grid.n_cells), dtype=score_dtype(volume))


def labels_input(ws: Workspace, volume: Any, spec: VolumeSpec, grid: FruxelGrid) -> Buffer:
    """Validated integer / bool labels as ``(B, N)`` uint8 on the compute device (zero copy for uint8)."""
    return ws.input(volume, shape=(spec.batch, grid.n_cells), dtype=wp.uint8)


def label_scores(ws: Workspace, scores: Buffer, spec: VolumeSpec) -> Buffer:
    """``(B, N)`` uint8 labels of ``(B, C, N)`` scores, by the rule of ``spec`` (one launch)."""
    batch, _, n = scores.shape
    labels = ws.empty((batch, n), wp.uint8)
    mode, threshold = score_mode(spec.threshold, spec.probs)
    ws.launch(label_scores_kernel, (batch, n), [scores, mode, wp.float64(threshold), labels])
    return labels


def build_pyramid(ws: Workspace, labels: Buffer, grid: FruxelGrid) -> Buffer:
    """The two-level pyramid ``(B, bd * bh * bw + sd * sh * sw)`` uint8 of ``(B, N)`` uint8 labels (a zeroed
    allocation and one launch)."""
    batch = labels.shape[0]
    g = grid_info(grid)
    pyramid = ws.empty((batch, pyramid_size(grid)), wp.uint8, zero=True)
    words = label_words(labels, grid) if ws.is_cuda else None
    if words is not None:
        ws.launch(build_pyramid_words_kernel, words.shape, [words, g, pyramid])
        return pyramid
    span = 1 if ws.is_cuda else g.blocks_u
    dim = (batch, grid.depth, grid.height, -(-g.blocks_u // span))
    ws.launch(build_pyramid_kernel, dim, [labels, g, span, pyramid])
    return pyramid


def label_words(labels: Buffer, grid: FruxelGrid) -> Buffer | None:
    """``(B, N)`` uint8 labels as ``(B * N / 4,)`` int32 words (no copy) when each block row is one aligned word
    (``BLOCK == 4``, ``W % 4 == 0``, 4-byte aligned data) and the labels are a torch tensor (as they are on CUDA,
    but for numpy callers, whose data Warp holds); else None."""
    native = labels.native
    if BLOCK != 4 or grid.width % 4 or labels.ptr % 4 or isinstance(native, (np.ndarray, wp.array)):
        return None
    view = native.view(torch_dtype(wp.int32)).reshape(-1)
    return Buffer(view, (labels.size // 4,), wp.int32, labels.ptr, labels.device)


def occupancy(ws: Workspace, volume: Any, spec: VolumeSpec, grid: FruxelGrid) -> tuple[Buffer, Buffer]:
    """Labels ``(B, N)`` uint8 and the pyramid of a validated volume, on the compute device."""
    if spec.is_scores:
        labels = label_scores(ws, scores_input(ws, volume, spec, grid), spec)
    else:
        labels = labels_input(ws, volume, spec, grid)
    return labels, build_pyramid(ws, labels, grid)

"""OpenCL backend of ``soft_first_hit``: the forward and backward kernels of :file:`soft_first_hit.cl`.

The algorithm, its backward recursion and the step tape are those of :mod:`fruxel.kernels.wp.soft_first_hit`;
the ray set-up is :file:`ray.h`'s, as :file:`first_hit.cl`'s walk, so both operations visit the same cells. The forward
kernel also finishes each pixel: it writes ``classes`` (the miss probability ``T_M`` in front of the class sums
``acc_c = sum_m T_m p_mc``), ``depth_sum`` and ``depth = depth_sum / hit`` (``hit = sum_{c>=1} acc_c``, 0 where
``hit`` is at most the scalar type's smallest normal number). The backward kernel folds the gradient of ``depth``
into those of ``depth_sum`` and of every ``acc_c`` (the chain rule through ``depth_sum / hit``), then walks the ray
back to front.

Programs are built once per context and per (scalar type, number of classes). Data travels as host arrays: on
PoCL (the CPU) they are used in place through ``USE_HOST_PTR`` buffers, elsewhere copied. Gradients are scattered
with compare-and-swap adds (plain adds for the grid's own view, whose rays own their cells), so float rounding may
differ from run to run where rays share a cell.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from .. import traversal
from . import occupancy
from .runtime import Runtime, cl, defines, get_runtime, source

TAPE_STEPS_PER_WORD = 16
"""Steps per uint32 word of the step tape (2 bits each)."""

_SOURCE = source(__file__)


def torch_device(device: str | None) -> Any:
    """The torch device the kernels' data is staged on: always the CPU (host arrays; zero-copy on PoCL)."""
    import torch

    return torch.device("cpu")


@dataclass(eq=False)
class SavedRays:
    """Per-ray record of a forward pass for the backward pass (device buffers, kept alive by this object)."""

    device: str | None
    """OpenCL device selector of the runtime that ran the forward."""
    state: Any
    """``(R, 4)`` int32 buffer: cells on the ray and ``(i, j, k)`` of the last one."""
    log_t: Any
    """``(R,)`` buffer of the scalar type: log-transmittance after the last non-saturated cell."""
    tape: Any
    """``(R, words)`` uint32 buffer: the step tape."""
    words: int
    """Tape words per ray."""
    cams: list[Camera]
    """The cameras, in slot order."""


def _kernel(rt: Runtime, name: str, real: np.dtype, nc: int) -> Any:
    opts = occupancy.ray_options() + defines(REAL_DOUBLE=int(real == np.float64), NC=nc, SPW=TAPE_STEPS_PER_WORD)
    return rt.kernel(_SOURCE, name, opts)


def _global(cam: Camera, batch: int) -> tuple[tuple[int, int, int], tuple[int, int, int]]:
    return occupancy.trace_global(cam, batch), (*occupancy.TRACE_LOCAL, 1)


def _host(t: Any, real: np.dtype) -> np.ndarray:
    """A torch CPU tensor as a C-contiguous numpy array of ``real`` (no copy when it already is one)."""
    return np.ascontiguousarray(t.detach().numpy(), dtype=real)


def _real(rt: Runtime, t: Any) -> np.dtype:
    import torch

    if t.dtype == torch.float64:
        if not rt.has_fp64:
            raise TypeError(f"OpenCL device {rt.device.name!r} has no float64 (cl_khr_fp64); pass float32 input")
        return np.dtype(np.float64)
    return np.dtype(np.float32)


def forward(probs: Any, grid: FruxelGrid, cameras: list[Camera], *, save: bool,
            device: str | None = None) -> tuple[Any, Any, Any, SavedRays | None]:
    """Run the forward kernel, one launch per camera, and wait for the results.

    Args:
        probs: ``(B, C, D, H, W)`` torch float32/float64 CPU tensor, contiguous: class probabilities by cell
            ``(k, j, i)``, channel 0 = empty.
        grid: the volume's grid.
        cameras: N cameras of one image size ``h x w``.
        save: keep what :func:`backward` needs.
        device: OpenCL device selector (:func:`.runtime.resolve_device`).

    Returns:
        ``(classes, depth, dsum, saved)``: torch CPU tensors of ``probs``' dtype, by pixel ``(y, x)`` of each
        camera: ``classes`` ``(B, N, C, h, w)`` (channel 0 the miss probability ``T_M``, channel ``c >= 1`` the
        class sum ``acc_c``), ``depth`` ``(B, N, h, w)`` (``dsum / hit``, 0 where ``hit`` is at most the smallest
        normal number; metres along the camera's z) and ``dsum`` ``(B, N, h, w)`` (``sum_m w_m t_m``, metres), and
        a :class:`SavedRays` (None without ``save``).
    """
    import torch

    rt = get_runtime(device)
    real = _real(rt, probs)
    b, c = probs.shape[0], probs.shape[1]
    h, w = cameras[0].height, cameras[0].width
    n_cam = len(cameras)
    classes = torch.empty((b, n_cam, c, h, w), dtype=probs.dtype)
    depth = torch.empty((b, n_cam, h, w), dtype=probs.dtype)
    dsum = torch.empty((b, n_cam, h, w), dtype=probs.dtype)
    rays = b * n_cam * h * w
    max_steps = traversal.max_steps(grid)
    words = -(-max_steps // TAPE_STEPS_PER_WORD)
    grid_args = (traversal.grid_params(grid), occupancy.cell_counts(grid))
    with rt.lock:
        k = _kernel(rt, "accumulate_soft_hits_kernel", real, c - 1)
        p_buf = rt.input("soft_probs", _host(probs, real))
        outs = [(rt.output(name, a.numpy()), a.numpy()) for name, a in
                (("soft_classes", classes), ("soft_depth", depth), ("soft_dsum", dsum))]
        if save:
            # Fresh buffers, not the runtime's pool: several forward passes may await their backward at once.
            flags = cl.mem_flags.READ_WRITE
            state = cl.Buffer(rt.context, flags, rays * 16)
            log_t = cl.Buffer(rt.context, flags, rays * real.itemsize)
            tape = cl.Buffer(rt.context, flags, rays * words * 4)
        else:
            state = log_t = tape = rt.scratch("soft_dummy", 16)
        for slot, cam in enumerate(cameras):
            k(rt.queue, *_global(cam, b), p_buf, grid_args[0], traversal.camera_params(cam), grid_args[1],
              np.int32(w), np.int32(h), np.int32(max_steps), np.int32(slot), np.int32(n_cam),
              np.int32(save), np.int32(words), *(buf for buf, _ in outs), state, log_t, tape)
        # Host synchronisation (the call's only one): waits for the kernels, whose results are torch tensors.
        rt.fetch(outs)
    saved = SavedRays(device, state, log_t, tape, words, list(cameras)) if save else None
    return classes, depth, dsum, saved


def backward(probs: Any, grid: FruxelGrid, groups: list[tuple[Any, ...]]) -> Any:
    """Run the backward kernel, one launch per camera of every group, and wait for the gradient.

    Args:
        probs: ``(B, C, D, H, W)`` torch float32/float64 CPU tensor, contiguous: the forward's class probabilities.
        grid: the volume's grid.
        groups: one ``(saved, classes, depth, g_classes, g_depth, g_dsum)`` per camera group of the forward
            call(s), all torch CPU tensors of ``probs``' dtype (the gradients contiguous), by pixel ``(y, x)`` of
            the group's N cameras of one image size ``h x w``: ``saved`` the group's :class:`SavedRays`;
            ``classes`` ``(B, N, C, h, w)`` and ``depth`` ``(B, N, h, w)`` its forward outputs; ``g_classes``
            ``(B, N, C, h, w)``, ``g_depth`` and ``g_dsum`` ``(B, N, h, w)`` the upstream gradients of
            ``classes``, ``depth`` and ``dsum``, each None where that output gets no gradient.

    Returns:
        ``(B, C, D, H, W)`` torch CPU tensor of ``probs``' dtype, by cell ``(k, j, i)``: the gradient of the loss
        with respect to ``probs``, summed over every group.
    """
    import torch

    rt = get_runtime(groups[0][0].device)
    real = _real(rt, probs)
    b, c = probs.shape[0], probs.shape[1]
    # Zero-copy: the kernels add into grad itself; else into a zeroed device buffer copied back at the end.
    grad = (torch.zeros if rt.zero_copy else torch.empty)(probs.shape, dtype=probs.dtype)
    # Host arrays the enqueued commands read: alive until the synchronisation below.
    keep = [_host(probs, real)]
    grid_args = (traversal.grid_params(grid), occupancy.cell_counts(grid))
    with rt.lock:
        k = _kernel(rt, "backpropagate_soft_hits_kernel", real, c - 1)
        p_buf = rt.input("soft_probs", keep[0])
        host = grad.numpy()
        if rt.zero_copy:
            g_buf = cl.Buffer(rt.context, cl.mem_flags.READ_WRITE | cl.mem_flags.USE_HOST_PTR, hostbuf=host)
        else:
            g_buf = rt.scratch("soft_grad", host.nbytes)
            rt.zero(g_buf, host.nbytes)  # what the kernels add into
        for saved, *tensors in groups:
            cams = saved.cams
            h, w = cams[0].height, cams[0].width
            # An upstream gradient of None (an output the loss does not use) is zero.
            pixel_shape = tuple(tensors[1].shape)
            shapes = (None, None, tuple(tensors[0].shape), pixel_shape, pixel_shape)
            arrays = [_host(t, real) if t is not None else np.zeros(shape, real)
                      for t, shape in zip(tensors, shapes, strict=True)]
            keep += arrays
            # The queue is in order: a pooled buffer (not zero-copy) is refilled only after the previous group's
            # kernels have read it.
            bufs = [rt.input(name, a) for name, a in zip(
                ("soft_classes", "soft_depth", "soft_g_classes", "soft_g_depth", "soft_g_dsum"), arrays, strict=True)]
            for slot, cam in enumerate(cams):
                own = traversal.is_own_view(cam, grid)
                k(rt.queue, *_global(cam, b), p_buf, grid_args[0], traversal.camera_params(cam), grid_args[1],
                  np.int32(w), np.int32(h), np.int32(slot), np.int32(len(cams)), np.int32(own),
                  np.int32(saved.words), saved.state, saved.log_t, saved.tape, *bufs, g_buf)
        # Host synchronisation (the call's only one): waits for every group's kernels; the gradient is a torch
        # tensor.
        rt.fetch([(g_buf, host)])
    return grad


def soft_first_hit(scores: Any, grid: FruxelGrid, cameras: Any, *, device: str | None = None,
                   probs: bool = False) -> Any:
    """:func:`fruxel.kernels.soft_first_hit` on this backend (``device``: ``None``, ``"cpu"`` or ``"gpu"``)."""
    from ..soft import soft_first_hit as _public

    return _public(scores, grid, cameras, backend="opencl", device=device, probs=probs)

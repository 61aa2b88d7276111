"""Warp backend of ``soft_first_hit``: expected first hit along every pixel's ray, with its exact backward pass.

One thread per ray (batch item b, pixel p = y * w + x of one camera). Cells are visited in exactly the order of
the DDA of :mod:`fruxel.kernels.traversal` (steps 1-5, plain loop: every cell contributes), using the shared
traversal steps of :mod:`.traverse`. The kernels take each cell's class probabilities ``p_m`` (channel 0 =
empty, as softmax gives them). With occupancy ``o_m = 1 - p_m0``, the non-empty classes renormalised
``q_mc = p_mc / o_m`` and entry depth ``t_m`` (first_hit's depth), the hit weight of cell m is
``w_m = o_m T_m`` with ``T_m = prod_{l<m} (1 - o_l) = prod_{l<m} p_l0``, and the renormalisation cancels::

    acc_c = sum_m w_m q_mc = sum_m T_m p_mc          (c = 1..C-1)
    dsum  = sum_m w_m t_m  = sum_m T_m S_m t_m       (S_m = sum_{c>=1} p_mc, = o_m, exact for tiny o)
    miss  = T_M                                      (M = cells on the ray)

so the forward pass needs no division, and ``T`` is a running product of ``p_0`` that survives ``p_0`` of
exactly 0 (a saturated cell, ``o = 1``) and 1 (``o = 0``). The loop stops early only when ``T`` is 0, where every
later weight is 0 anyway; a ``T`` below the smallest normal number of the scalar type counts as 0 (flushed, as
FTZ arithmetic does), because denormal arithmetic runs about a hundred times slower on CPUs and the weights it
would add are below that smallest normal number.

Backward, also division-free. With upstream gradients ``g_c`` (of acc_c), ``g_d`` (of dsum), ``g_miss`` of one
ray, ``L = sum_m T_m a_m + g_miss T_M`` with ``a_m = sum_c g_c p_mc + g_d t_m S_m``; then::

    dL/dp_mc = T_m (g_c + g_d t_m)                   (c >= 1)
    dL/dp_m0 = T_m R_m,  R_{M-1} = g_miss,  R_{m-1} = a_m + p_m0 R_m

``R_m`` is the loss downstream of cell m per unit of transmittance past it, built back to front. The backward
kernel walks each ray backwards: the forward saves per ray the number of cells, the last cell's indices and
``log T`` after it (the sum of ``log p_m0`` over cells with ``p_m0 > 0``), plus a *step tape* of 2 bits per step
(the plane family crossed to enter each cell). Undoing the steps in reverse visits the forward's cells in
reverse, exactly, with no floating-point decision repeated; ``T_m = exp(log T_{m+1} - log p_m0)`` comes back in
log space, so no ``1 / p_m0`` appears. Where the forward stopped early (``T_{s+1}`` 0 after cell s), the walk
starts at cell s with ``R_s = g_miss``: the cells behind s have zero weight and get zero gradient, as in the
function computed, and ``dL/dp_s0`` treats the ray as ending at s. That entry is the only approximation: softmax
multiplies it by ``p_s0``, and ``T_s p_s0`` is 0 or below the smallest normal number, so no logit gradient moves
by more than that (an occupancy input of exactly 1 gets the derivative of a ray that ends there).

Geometry (ray, clip, crossings) is float32 as in every backend; accumulation is in the kernel's scalar type,
float32 or float64 (one instantiation per scalar type and number of classes, built once per process). Gradients
are scattered with ``wp.atomic_add`` (Warp runs CPU threads one after another, so CPU results are deterministic).
CPU launches run with denormals flushed to zero, as GPUs run (see :func:`_flush_denormals`).
"""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from .. import traversal
from .runtime import warp
from .traverse import (
    CameraInfo,
    GridInfo,
    boundary_ahead,
    boundary_behind,
    camera_info,
    clip_ray,
    crossing,
    entry_cell,
    grid_info,
    pick_family,
    pixel_ray,
    step_signs,
)

wp = warp()

if (traversal.FAMILY_U, traversal.FAMILY_V, traversal.FAMILY_Z) != (0, 1, 2):
    raise ImportError("soft_first_hit keeps per-family state in vector lanes: FAMILY_U, _V, _Z must be 0, 1, 2")

TAPE_STEPS_PER_WORD = 15
"""Steps stored per int32 word of the step tape, 2 bits each (the plane family crossed); 15 keeps the sign bit
clear, so no shift overflows."""


@wp.func
def _scatter(grad: wp.array3d(dtype=Any), b: int, c: int, cell: int, value: Any, exclusive: int):
    """``grad[b, c, cell] += value``: skipped for 0 (most channels of a pixel the loss treats as a miss), plain when
    this launch's rays own their cells, atomic otherwise."""
    if value != type(value)(0.0):
        if exclusive == 1:
            grad[b, c, cell] = grad[b, c, cell] + value
        else:
            wp.atomic_add(grad, b, c, cell, value)


# ---------------------------------------------------------------------------------------------- kernels
@cache
def _kernels(real: Any, nc: int) -> tuple[Any, Any]:
    """Forward and backward kernels for scalar type ``real`` (``wp.float32`` / ``wp.float64``) and ``nc`` classes
    (``C - 1``, channel 0 = empty excluded), in one module of their own: built once per process and device (and
    cached on disk by Warp)."""
    vec_c = wp.types.vector(length=nc, dtype=real)
    module = f"fruxel_soft_first_hit_{nc}_{real.__name__}"
    spw = wp.constant(TAPE_STEPS_PER_WORD)
    tiny = float(np.finfo(np.float64 if real == wp.float64 else np.float32).tiny)

    @wp.kernel(enable_backward=False, module=module)
    def accumulate_soft_hits_kernel(
        probs: wp.array3d(dtype=real),
        g: GridInfo,
        cam: CameraInfo,
        n: int,
        max_steps: int,
        save: int,
        acc: wp.array4d(dtype=real),
        miss: wp.array3d(dtype=real),
        dsum: wp.array3d(dtype=real),
        state: wp.array2d(dtype=wp.int32),
        log_t: wp.array(dtype=real),
        tape: wp.array2d(dtype=wp.int32),
    ):
        """Expected first hit of one ray: thread (b, p) is pixel ``p = y * w + x`` of camera slot n, batch item b.

        Launch dims ``(B, h * w)``, one launch per camera. Input: ``probs`` ``(B, C, D*H*W)`` class probabilities
        by flat cell index ``(k * H + j) * W + i``, channel 0 = empty (clamped to [0, 1]); ``g``, ``cam`` the grid
        and camera constants (by value: no upload); ``max_steps`` :func:`traversal.max_steps`. Outputs (slot n of
        N): ``acc`` ``(B, N, C-1, h*w)``, ``miss`` and ``dsum`` ``(B, N, h*w)``, depth in the viewing camera's z.
        With ``save`` = 1, per ray r = (b * N + n) * h*w + p also ``state[:, r]`` = (cells on the ray, i, j, k of
        the last one), ``log_t[r]`` = sum of ``log p_0`` over them (saturated cells left out) and ``tape[:, r]`` =
        the family of every step, 2 bits each, TAPE_STEPS_PER_WORD per word (ray-minor, so that neighbouring
        threads write neighbouring words); without ``save`` these three are 1-column dummies.
        """
        b, p = wp.tid()
        zero = real(0.0)
        one = real(1.0)
        r = (b * miss.shape[1] + n) * miss.shape[2] + p
        o = cam.origin
        d = pixel_ray(cam, p % cam.width, p // cam.width)
        t_lo, t_hi, plane = clip_ray(g, o, d)
        accv = vec_c()
        ds = zero
        tr = one
        logt = zero
        ncell = int(0)  # noqa: UP018 - Warp: a variable a loop mutates is declared dynamic
        idx = wp.vec3i(0, 0, 0)
        if t_lo < t_hi:
            idx = entry_cell(g, o, d, t_lo, plane)
            s = step_signs(o, d)
            tn = wp.vec3(
                crossing(g, o, d, 0, boundary_ahead(idx[0], s[0]), s[0]),
                crossing(g, o, d, 1, boundary_ahead(idx[1], s[1]), s[1]),
                crossing(g, o, d, 2, boundary_ahead(idx[2], s[2]), s[2]),
            )
            dims = wp.vec3i(g.width, g.height, g.depth)
            t_entry = t_lo
            word = int(0)  # noqa: UP018
            for _it in range(max_steps):
                cell = (idx[2] * g.height + idx[1]) * g.width + idx[0]
                p0 = wp.clamp(probs[b, 0, cell], zero, one)
                occ = zero
                for c in range(wp.static(nc)):
                    pc = probs[b, c + 1, cell]
                    accv[c] = accv[c] + tr * pc
                    occ = occ + pc
                ds = ds + tr * occ * real(t_entry)
                ncell += 1
                if save == 1 and p0 > zero:
                    logt = logt + wp.log(p0)
                tr = tr * p0
                if tr < real(tiny):
                    # Transmittance 0, or below the smallest normal number, where it is flushed to 0 (as FTZ
                    # arithmetic does): every later weight is 0, and the CPU is spared denormal arithmetic, which
                    # costs a hundred times more per operation.
                    tr = zero
                    break
                f = pick_family(tn[0], tn[1], tn[2])
                tf = tn[f]
                if tf >= t_hi:
                    break
                nxt = idx[f] + s[f]
                if nxt < 0 or nxt >= dims[f]:
                    break
                if save == 1:
                    step = ncell - 1
                    word = word | (f << (2 * (step % spw)))
                    if step % spw == spw - 1:
                        tape[step // spw, r] = word
                        word = 0
                idx[f] = nxt
                t_entry = tf
                tn[f] = crossing(g, o, d, f, boundary_ahead(nxt, s[f]), s[f])
            if save == 1 and (ncell - 1) % spw != 0:
                tape[(ncell - 1) // spw, r] = word
        for c in range(wp.static(nc)):
            acc[b, n, c, p] = accv[c]
        dsum[b, n, p] = ds
        miss[b, n, p] = tr
        if save == 1:
            state[0, r] = ncell
            state[1, r] = idx[0]
            state[2, r] = idx[1]
            state[3, r] = idx[2]
            log_t[r] = logt

    @wp.kernel(enable_backward=False, module=module)
    def backpropagate_soft_hits_kernel(
        probs: wp.array3d(dtype=real),
        g: GridInfo,
        cam: CameraInfo,
        n: int,
        exclusive: int,
        state: wp.array2d(dtype=wp.int32),
        log_t: wp.array(dtype=real),
        tape: wp.array2d(dtype=wp.int32),
        g_acc: wp.array4d(dtype=real),
        g_miss: wp.array3d(dtype=real),
        g_dsum: wp.array3d(dtype=real),
        grad: wp.array3d(dtype=real),
    ):
        """Gradients from one ray's outputs into its cells: thread (b, p) as in the forward kernel.

        Launch dims ``(B, h * w)``, one launch per camera. Inputs: the forward kernel's ``probs``, ``g``, ``cam``,
        ``n``, its saved ``state``, ``log_t`` and ``tape``, and the upstream gradients ``g_acc``
        ``(B, N, C-1, h*w)``, ``g_miss`` and ``g_dsum`` ``(B, N, h*w)``. Adds into ``grad`` ``(B, C, D*H*W)``,
        which the caller zeroes: atomically, or with plain adds when ``exclusive`` = 1 (no two rays of this camera
        share a cell: the grid's own view, whose pixels each own a column). The ray's cells are visited last to
        first by undoing the taped steps; the module docstring gives the recursion.
        """
        b, p = wp.tid()
        r = (b * g_miss.shape[1] + n) * g_miss.shape[2] + p
        ncell = state[0, r]
        if ncell == 0:
            return
        zero = real(0.0)
        one = real(1.0)
        ga = vec_c()
        for c in range(wp.static(nc)):
            ga[c] = g_acc[b, n, c, p]
        gm = g_miss[b, n, p]
        gd = g_dsum[b, n, p]
        if wp.length_sq(ga) == zero and gm == zero and gd == zero:
            return  # a pixel the loss ignores: nothing to add
        o = cam.origin
        d = pixel_ray(cam, p % cam.width, p // cam.width)
        t_lo, t_hi, plane = clip_ray(g, o, d)
        s = step_signs(o, d)
        idx = wp.vec3i(state[1, r], state[2, r], state[3, r])
        logt = log_t[r]
        rr = gm
        for back in range(ncell):
            m = ncell - 1 - back
            f = int(0)  # noqa: UP018 - Warp: a variable a loop mutates is declared dynamic
            t = t_lo
            if m > 0:
                step = m - 1
                f = (tape[step // spw, r] >> (2 * (step % spw))) & 3
                t = crossing(g, o, d, f, boundary_behind(idx[f], s[f]), s[f])
            cell = (idx[2] * g.height + idx[1]) * g.width + idx[0]
            p0 = wp.clamp(probs[b, 0, cell], zero, one)
            if p0 > zero:
                logt = logt - wp.log(p0)
            tr = wp.exp(logt)
            gdt = gd * real(t)
            a = zero
            for c in range(wp.static(nc)):
                gc = ga[c] + gdt
                a = a + gc * probs[b, c + 1, cell]
                _scatter(grad, b, c + 1, cell, tr * gc, exclusive)
            _scatter(grad, b, 0, cell, tr * rr, exclusive)
            rr = a + p0 * rr
            if m > 0:
                idx[f] = idx[f] - s[f]

    return accumulate_soft_hits_kernel, backpropagate_soft_hits_kernel


# ---------------------------------------------------------------------------------------------- host side
@dataclass(eq=False)
class SavedRays:
    """Per-ray record of a forward pass that the backward pass walks back; ray r = (b * N + n) * h*w + p."""

    state: Any
    """``(4, R)`` int32 torch tensor: cells on the ray and ``(i, j, k)`` of the last one."""
    log_t: Any
    """``(R,)`` torch tensor of the scalar type: ``log T`` after the last cell, saturated cells left out."""
    tape: Any
    """``(words, R)`` int32 torch tensor: the step tape (see :data:`TAPE_STEPS_PER_WORD`)."""
    cams: list
    """Per camera, its :class:`CameraInfo`."""
    own: list
    """Per camera, whether it is the grid's own view (its rays never share a cell)."""
    size: tuple[int, int]
    """Image ``(h, w)`` of every camera."""


def _stream(t: Any) -> Any:
    """The Warp stream of the caller's current torch CUDA stream, or None on the CPU (launches stay in the
    caller's stream order, with no synchronisation)."""
    if t.device.type != "cuda":
        return None
    import torch

    return wp.stream_from_torch(torch.cuda.current_stream(t.device))


def _warp_device(t: Any) -> str:
    return "cpu" if t.device.type == "cpu" else f"cuda:{t.device.index or 0}"


@contextmanager
def _flush_denormals(cpu: bool) -> Iterator[None]:
    """Run the enclosed CPU launches with denormals flushed to zero (FTZ/DAZ), restoring the caller's mode after.

    Warp runs CPU kernels on the calling thread, so its floating-point mode applies. Near the end of a ray the
    products ``T p`` fall below the smallest normal number, where x86 arithmetic takes a slow microcode assist;
    GPUs flush them anyway. The mode is probed with a denormal
    multiplication (zero when flushing is on) and put back as it was.
    """
    if not cpu:
        yield
        return
    import torch

    was_on = (torch.tensor([1e-39], dtype=torch.float32) * 2.0).item() == 0.0
    if not was_on:
        torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if not was_on:
            torch.set_flush_denormal(False)


def torch_device(device: str) -> Any:
    """The torch device holding the kernels' data for Warp device ``device`` (``"cpu"``, ``"cuda:N"``): the same
    memory, so torch tensors pass to the kernels with no copy."""
    import torch

    return torch.device(device)


def _real(t: Any) -> Any:
    import torch

    if t.dtype == torch.float64:
        return wp.float64
    if t.dtype == torch.float32:
        return wp.float32
    raise TypeError(f"soft_first_hit kernels take float32 or float64 tensors, got {t.dtype}")


def forward(probs: Any, grid: FruxelGrid, cameras: list[Camera], *, save: bool,
            device: str | None = None) -> tuple[Any, ...]:
    """Run the forward kernel: expected first hits of every pixel of every camera.

    Args:
        probs: ``(B, C, D, H, W)`` torch float32/float64, contiguous, on the CPU or a CUDA device: class
            probabilities, channel 0 = empty.
        grid: the volume's grid.
        cameras: N cameras sharing one image size ``h x w`` (checked by the caller).
        save: keep what :func:`backward` needs.
        device: the Warp device; the kernels run where ``probs`` lives, which the caller has made this device.

    Returns:
        ``(acc, miss, dsum, saved)``: ``acc`` ``(B, N, C-1, h, w)`` expected class mass, ``miss`` ``(B, N, h, w)``,
        ``dsum`` ``(B, N, h, w)`` unnormalised expected depth (viewing-camera z), all of ``probs``' dtype and
        device; ``saved`` a :class:`SavedRays`, or None without ``save``. Nothing waits for the kernels: on CUDA
        they run in the caller's torch stream order.
    """
    import torch

    real = _real(probs)
    b, c = probs.shape[0], probs.shape[1]
    h, w = cameras[0].height, cameras[0].width
    n_cam = len(cameras)
    fwd, _ = _kernels(real, c - 1)
    opts = {"dtype": probs.dtype, "device": probs.device}
    acc = torch.empty((b, n_cam, c - 1, h, w), **opts)
    miss = torch.empty((b, n_cam, h, w), **opts)
    dsum = torch.empty((b, n_cam, h, w), **opts)
    rays = b * n_cam * h * w if save else 1
    words = -(-traversal.max_steps(grid) // TAPE_STEPS_PER_WORD) if save else 1
    state = torch.empty((4, rays), dtype=torch.int32, device=probs.device)
    log_t = torch.empty((rays,), **opts)
    tape = torch.empty((words, rays), dtype=torch.int32, device=probs.device)
    cams = [camera_info(cam) for cam in cameras]
    inputs = [
        wp.from_torch(probs.view(b, c, -1), dtype=real), grid_info(grid), None, 0, traversal.max_steps(grid),
        int(save), wp.from_torch(acc.view(b, n_cam, c - 1, h * w), dtype=real),
        wp.from_torch(miss.view(b, n_cam, h * w), dtype=real), wp.from_torch(dsum.view(b, n_cam, h * w), dtype=real),
        wp.from_torch(state, dtype=wp.int32), wp.from_torch(log_t, dtype=real), wp.from_torch(tape, dtype=wp.int32),
    ]
    stream = _stream(probs)
    with _flush_denormals(stream is None):
        for n, cam in enumerate(cams):
            inputs[2], inputs[3] = cam, n
            wp.launch(fwd, dim=(b, h * w), inputs=inputs, device=None if stream else _warp_device(probs),
                      stream=stream)
    own = [traversal.is_own_view(cam, grid) for cam in cameras]
    saved = SavedRays(state, log_t, tape, cams, own, (h, w)) if save else None
    return acc, miss, dsum, saved


def backward(probs: Any, grid: FruxelGrid, saved: SavedRays, g_acc: Any, g_miss: Any, g_dsum: Any,
             out: Any = None) -> Any:
    """Run the backward kernel: the gradient of a loss with respect to ``probs``.

    Args:
        probs: the forward's input (unchanged since).
        grid: the forward's grid.
        saved: the forward's :class:`SavedRays`.
        g_acc: ``(B, N, C-1, h, w)`` upstream gradient of ``acc``; ``g_miss``, ``g_dsum``: ``(B, N, h, w)``, of
            ``miss`` and ``dsum``; contiguous, of ``probs``' dtype and device.
        out: a ``(B, C, D, H, W)`` tensor like ``probs`` to add the gradient into, or None for a new one.

    Returns:
        ``(B, C, D, H, W)`` gradient (``out`` when given), of ``probs``' dtype and device (in stream order, no wait).
    """
    import torch

    real = _real(probs)
    b, c = probs.shape[0], probs.shape[1]
    h, w = saved.size
    n_cam = len(saved.cams)
    _, bwd = _kernels(real, c - 1)
    grad = torch.zeros_like(probs) if out is None else out
    inputs = [
        wp.from_torch(probs.view(b, c, -1), dtype=real), grid_info(grid), None, 0, 0,
        wp.from_torch(saved.state, dtype=wp.int32), wp.from_torch(saved.log_t, dtype=real),
        wp.from_torch(saved.tape, dtype=wp.int32), wp.from_torch(g_acc.view(b, n_cam, c - 1, h * w), dtype=real),
        wp.from_torch(g_miss.view(b, n_cam, h * w), dtype=real),
        wp.from_torch(g_dsum.view(b, n_cam, h * w), dtype=real), wp.from_torch(grad.view(b, c, -1), dtype=real),
    ]
    stream = _stream(probs)
    with _flush_denormals(stream is None):
        for n, (cam, own) in enumerate(zip(saved.cams, saved.own, strict=True)):
            inputs[2], inputs[3], inputs[4] = cam, n, int(own)
            wp.launch(bwd, dim=(b, h * w), inputs=inputs, device=None if stream else _warp_device(probs),
                      stream=stream)
    return grad


def soft_first_hit(scores: Any, grid: FruxelGrid, cameras: Any, *, device: str | None = None,
                   probs: bool = False) -> Any:
    """:func:`fruxel.kernels.soft_first_hit` on this backend (``device``: ``"cpu"``, ``"cuda"``, ``"cuda:N"``)."""
    from ..soft import soft_first_hit as _public

    return _public(scores, grid, cameras, backend="warp", device=device, probs=probs)

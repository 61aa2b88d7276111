"""Warp backend of ``soft_first_hit``: expected first hit along every pixel's ray, with its exact backward pass.

One thread per ray (batch item b, pixel p = y * w + x of one camera). Cells are visited in exactly the order of
the DDA of :mod:`fruxel.kernels.traversal` (steps 1-5, plain loop: every cell contributes), by the walk of
:mod:`.traverse` that ``first_hit`` takes (its start, step choice and step on the cell level, and the step undone
backwards), so the cells and their entry depths are first_hit's bit for bit. The kernels take each cell's class
probabilities ``p_m`` (channel 0 = empty, as softmax gives them). With occupancy ``o_m = 1 - p_m0``, the non-empty
classes renormalised ``q_mc = p_mc / o_m`` and entry depth ``t_m`` (first_hit's depth), the hit weight of cell m is
``w_m = o_m T_m`` with ``T_m = prod_{l<m} (1 - o_l) = prod_{l<m} p_l0``, and the renormalisation cancels::

    acc_c = sum_m w_m q_mc = sum_m T_m p_mc          (c = 1..C-1)
    dsum  = sum_m w_m t_m  = sum_m T_m S_m t_m       (S_m = sum_{c>=1} p_mc, = o_m, exact for tiny o)
    miss  = T_M                                      (M = cells on the ray)

so the forward pass needs no division, and ``T`` is a running product of ``p_0`` that survives ``p_0`` of
exactly 0 (a saturated cell, ``o = 1``) and 1 (``o = 0``). The loop stops early only when ``T`` is 0, where every
later weight is 0 anyway; a ``T`` below the smallest normal number of the scalar type counts as 0 (flushed, as
FTZ arithmetic does), because denormal arithmetic runs about a hundred times slower on CPUs and the weights it
would add are below that smallest normal number. The forward kernel also finishes each pixel: it writes
``classes = (miss, acc_1, ..., acc_{C-1})`` and ``depth = dsum / hit`` with ``hit = sum_c acc_c`` (0 where ``hit``
is below the smallest normal number), so no per-pixel torch operation follows.

Backward, also division-free along the ray. A ray's upstream gradients are ``G_c`` (of classes, ``G_0`` of the
miss), ``G_depth`` and ``G_dsum``. Through ``depth = dsum / hit`` they become ``g_c = G_c + k`` for the class sums
with the common part ``k = -G_depth depth / hit``, and ``g_d = G_dsum + G_depth / hit`` for dsum (``k = 0``,
``g_d = G_dsum`` where depth is the constant 0). With ``L = sum_m T_m a_m + G_0 T_M``,
``a_m = sum_{c>=1} G_c p_mc + u_m S_m`` and ``u_m = k + g_d t_m``::

    dL/dp_mc = T_m (G_c + u_m)                       (c >= 1)
    dL/dp_m0 = T_m R_m,  R_{M-1} = G_0,  R_{m-1} = a_m + p_m0 R_m

``R_m`` is the loss downstream of cell m per unit of transmittance past it, built back to front. The backward
kernel walks each ray backwards: the forward saves per ray the number of cells, the last cell's indices and
``log T`` after it (the sum of ``log p_m0`` over cells with ``p_m0 > 0``), plus a *step tape* of 2 bits per step
(the plane family crossed to enter each cell). Undoing the steps in reverse visits the forward's cells in
reverse, exactly, with no floating-point decision repeated; ``T_m = exp(log T_{m+1} - log p_m0)`` comes back in
log space, so no ``1 / p_m0`` appears. Where the forward stopped early (``T_{s+1}`` 0 after cell s), the walk
starts at cell s with ``R_s = G_0``: the cells behind s have zero weight and get zero gradient, as in the
function computed, and ``dL/dp_s0`` treats the ray as ending at s. That entry is the only approximation: softmax
multiplies it by ``p_s0``, and ``T_s p_s0`` is 0 or below the smallest normal number, so no logit gradient moves
by more than that (an occupancy input of exactly 1 gets the derivative of a ray that ends there).

Gradients of rays that share cells are scattered with ``wp.atomic_add``, and only where nonzero: per cell the
class channels whose ``G_c`` is nonzero (a cross-entropy gives one), ``T_m R_m`` into channel 0, and the part
``T_m u_m`` common to every class channel once into a ``(B, D*H*W)`` buffer that is added to channels 1..C-1 at the
end. The grid's own camera at native resolution takes a fast path (:func:`~fruxel.kernels.traversal.is_own_view`):
pixel (x, y) walks column (y, x) front to back (its ray crosses only z-planes, at the same ``t`` as the general
walk), needs no tape, and owns its cells, so the first own view of a backward pass *stores* every cell's gradient
(zeros behind an early stop) into an uninitialised tensor: no zero fill, no read-modify-write, no atomics.

Geometry (ray, clip, crossings) is float32 as in every backend; accumulation is in the kernel's scalar type,
float32 or float64 (one instance per scalar type and number of classes: its per-cell functions and four kernels,
each made by a cached factory, in one Warp module built once per process; see :func:`kernels`). Warp runs
CPU threads one after another, so CPU results are deterministic; CPU launches run with denormals flushed to zero,
as GPUs run (see :func:`~fruxel.kernels.fpmode.flush_denormals`). Launches go through
:class:`~fruxel.kernels.wp.arrays.Workspace` (torch memory, torch's current CUDA stream, recorded launches), so
nothing waits for the device.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cache
from types import SimpleNamespace
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from .. import traversal
from ..fpmode import flush_denormals
from .arrays import Buffer, Packed, Workspace, device_of
from .runtime import warp
from .traverse import (
    FAMILY_Z,
    CameraInfo,
    GridInfo,
    camera_arg,
    clip_ray,
    grid_info,
    inline_func,
    pick_step,
    pixel_ray,
    ray_coefficients,
    ray_crossing,
    start_walk,
    step_back,
    step_signs,
    take_step,
)

wp = warp()

TAPE_STEPS_PER_WORD = 15
"""Steps stored per int32 word of the step tape, 2 bits each (the plane family crossed); 15 keeps the sign bit
clear, so no shift overflows."""

# Flags of the backward kernels' ``given`` argument: which upstream gradients exist (an output that a loss does not
# use gets none, and costs no zero-filled tensor).
GIVEN_CLASSES = wp.constant(1)
GIVEN_DEPTH = wp.constant(2)
GIVEN_DSUM = wp.constant(4)


# ---------------------------------------------------------------------------------------------- kernels
@inline_func
def column_ray(g: GridInfo, cam: CameraInfo, p: int):
    """The own view's ray down column ``p = j * W + i`` (``cam`` the grid's own camera): where it enters the
    frustum, on slice 0's near face, and its coefficients (:func:`~fruxel.kernels.wp.traverse.ray_coefficients`),
    from which the column kernels take its z-plane crossings.

    Returns:
        ``(t_lo, na, nb, da, db)``.
    """
    o = cam.origin
    d = pixel_ray(cam, p % g.width, p // g.width)
    t_lo, _t_hi, _plane = clip_ray(g, o, d)
    na, nb, da, db = ray_coefficients(g, o, d)
    return t_lo, na, nb, da, db


# One instance per scalar type ``real`` (``wp.float32`` / ``wp.float64``) and number of classes ``nc`` (``C - 1``,
# channel 0 = empty excluded): the per-cell functions (:func:`_cell_funcs`) and four kernels, each made by a cached
# factory of its own, in one Warp module per instance that :func:`kernels` makes complete before its first launch
# (a kernel added to a loaded module would rebuild it). Built once per process and device, cached on disk by Warp.
#
# Warp evaluates a function's annotations with the closure variables its body uses, so a function whose body does
# not use ``real`` or ``vec_c`` annotates those parameters as Any (the same code once specialised).


def _module(real: Any, nc: int) -> str:
    """The Warp module of instance ``(real, nc)``."""
    return f"fruxel_soft_first_hit_{nc}_{real.__name__}"


@cache
def _vectors(real: Any, nc: int) -> tuple[Any, Any]:
    """``(vec_c, vec_p)``: vectors of ``nc`` class values and of all ``nc + 1`` channels, of scalar type ``real``."""
    return wp.types.vector(length=nc, dtype=real), wp.types.vector(length=nc + 1, dtype=real)


def _tiny(real: Any) -> float:
    """The smallest normal number of ``real``: a transmittance or hit probability below it counts as 0."""
    return float(np.finfo(np.float64 if real == wp.float64 else np.float32).tiny)


@cache
def _cell_funcs(real: Any, nc: int) -> SimpleNamespace:
    """The per-cell and per-pixel ``wp.func`` of instance ``(real, nc)`` that the kernels share."""
    vec_c, vec_p = _vectors(real, nc)
    tiny = _tiny(real)

    @wp.func
    def absorb(probs: wp.array3d(dtype=real), b: int, cell: int, t: float, acc: vec_c, ds: real, logt: real,
               tr: real, save: int):
        """One cell of the forward walk: adds its weighted class mass and depth, and multiplies the
        transmittance by ``p_0`` (logged when ``save``). Returns ``(acc, ds, logt, tr)``."""
        out = vec_c(acc)
        p0 = wp.clamp(probs[b, 0, cell], real(0.0), real(1.0))
        occ = real(0.0)
        for c in range(wp.static(nc)):
            pc = probs[b, c + 1, cell]
            out[c] = out[c] + tr * pc
            occ = occ + pc
        lt = logt
        if save == 1 and p0 > real(0.0):
            lt = lt + wp.log(p0)
        return out, ds + tr * occ * real(t), lt, tr * p0

    @wp.func
    def finish_ray(classes: wp.array4d(dtype=real), depth: wp.array3d(dtype=real), dsum: wp.array3d(dtype=real),
                   b: int, n: int, p: int, acc: Any, ds: real, tr: real):
        """Write one pixel's outputs: ``classes = (miss, acc)``, ``dsum`` and ``depth = dsum / hit``."""
        hit = real(0.0)
        for c in range(wp.static(nc)):
            classes[b, n, c + 1, p] = acc[c]
            hit = hit + acc[c]
        classes[b, n, 0, p] = tr
        dsum[b, n, p] = ds
        dep = real(0.0)
        if hit > real(tiny):
            dep = ds / hit
        depth[b, n, p] = dep

    @wp.func
    def save_ray(state: wp.array2d(dtype=wp.int32), log_t: wp.array(dtype=Any), r: int, ncell: int, i: int, j: int,
                 k: int, logt: Any):
        """Keep ray r's end state for the backward pass: cells on the ray, the last one's indices, ``log T``."""
        state[0, r] = ncell
        state[1, r] = i
        state[2, r] = j
        state[3, r] = k
        log_t[r] = logt

    @wp.func
    def ray_gradients(classes: wp.array4d(dtype=real), depth: wp.array3d(dtype=real),
                      g_classes: wp.array4d(dtype=real), g_depth: wp.array3d(dtype=real),
                      g_dsum: wp.array3d(dtype=real), given: int, b: int, n: int, p: int):
        """One ray's upstream gradients through ``depth = dsum / hit``: ``(G_c, G_0, g_d, k)`` (module
        docstring); ``hit`` is summed in the forward's order, so it is the forward's bit for bit. ``given`` flags
        the upstream gradients that exist (:data:`GIVEN_CLASSES`, ``_DEPTH``, ``_DSUM``); the others are 0."""
        gc = vec_c()
        g0 = real(0.0)
        if given & GIVEN_CLASSES != 0:
            g0 = g_classes[b, n, 0, p]
            for c in range(wp.static(nc)):
                gc[c] = g_classes[b, n, c + 1, p]
        gd = real(0.0)
        if given & GIVEN_DSUM != 0:
            gd = g_dsum[b, n, p]
        k = real(0.0)
        if given & GIVEN_DEPTH != 0:
            hit = real(0.0)
            for c in range(wp.static(nc)):
                hit = hit + classes[b, n, c + 1, p]
            if hit > real(tiny):
                gdep = g_depth[b, n, p]
                gd = gd + gdep / hit
                k = -gdep * depth[b, n, p] / hit
        return gc, g0, gd, k

    @wp.func
    def load_cell(probs: wp.array3d(dtype=Any), b: int, cell: int):  # Any: see the note above _module
        """All C probabilities of one cell, channel 0 first."""
        v = vec_p()
        for c in range(wp.static(nc + 1)):
            v[c] = probs[b, c, cell]
        return v

    @wp.func
    def no_gradient(gc: Any, g0: real, gd: real, k: real) -> bool:
        """Whether a ray's upstream gradients are all zero, tested value by value (a sum of squares would
        underflow for tiny gradients and drop them)."""
        quiet = g0 == real(0.0) and gd == real(0.0) and k == real(0.0)
        for c in range(wp.static(nc)):
            quiet = quiet and gc[c] == real(0.0)
        return quiet

    @wp.func
    def cell_gradient(pm: Any, t: float, logt: real, gc: Any, gd: real, k: real):
        """One cell of the backward walk from its probabilities ``pm`` (:func:`load_cell`):
        ``(log T_m, T_m, u_m, a_m, p_m0)`` from ``log T_{m+1}``."""
        p0 = wp.clamp(pm[0], real(0.0), real(1.0))
        lt = logt
        if p0 > real(0.0):
            lt = lt - wp.log(p0)
        u = k + gd * real(t)
        a = real(0.0)
        s = real(0.0)
        for c in range(wp.static(nc)):
            a = a + gc[c] * pm[c + 1]
            s = s + pm[c + 1]
        return lt, wp.exp(lt), u, a + u * s, p0

    return SimpleNamespace(absorb=absorb, finish_ray=finish_ray, save_ray=save_ray, ray_gradients=ray_gradients,
                           load_cell=load_cell, no_gradient=no_gradient, cell_gradient=cell_gradient)


@cache
def _forward_kernel(real: Any, nc: int) -> Any:
    """:func:`accumulate_soft_hits_kernel` of instance ``(real, nc)``: the general forward walk."""
    vec_c, _vec_p = _vectors(real, nc)
    tiny = _tiny(real)
    cells = _cell_funcs(real, nc)
    spw = wp.constant(TAPE_STEPS_PER_WORD)

    @wp.kernel(enable_backward=False, module=_module(real, nc))
    def accumulate_soft_hits_kernel(
        probs: wp.array3d(dtype=real),
        g: GridInfo,
        cam: CameraInfo,
        n: int,
        max_steps: int,
        save: int,
        classes: wp.array4d(dtype=real),
        depth: wp.array3d(dtype=real),
        dsum: wp.array3d(dtype=real),
        state: wp.array2d(dtype=wp.int32),
        log_t: wp.array(dtype=real),
        tape: wp.array2d(dtype=wp.int32),
    ):
        """Expected first hit of one ray: thread (b, p) is pixel ``p = y * w + x`` of camera slot n, batch item b.

        Launch dims ``(B, h * w)``, one launch per camera. Input: ``probs`` ``(B, C, D*H*W)`` class probabilities
        by flat cell index ``(k * H + j) * W + i``, channel 0 = empty (clamped to [0, 1]); ``g``, ``cam`` the grid
        and camera constants (by value: no upload); ``max_steps`` :func:`traversal.max_steps`. Outputs (slot n of
        N): ``classes`` ``(B, N, C, h*w)``, ``depth`` and ``dsum`` ``(B, N, h*w)``, depths in the viewing
        camera's z. With ``save`` = 1, per ray r = (b * N + n) * h*w + p also ``state[:, r]`` = (cells on the ray,
        i, j, k of the last one), ``log_t[r]`` = sum of ``log p_0`` over them (saturated cells left out) and
        ``tape[:, r]`` = the family of every step, 2 bits each, TAPE_STEPS_PER_WORD per word (ray-minor, so that
        neighbouring threads write neighbouring words); without ``save`` these three are 1-column dummies. The
        walk is :func:`~fruxel.kernels.wp.traverse.trace_ray`'s on the cell level (its start, choice and step),
        keeping one index and next crossing per family in scalars (a vector indexed by the family would live in
        local memory).
        """
        b, p = wp.tid()
        r = (b * depth.shape[1] + n) * depth.shape[2] + p
        o = cam.origin
        d = pixel_ray(cam, p % cam.width, p // cam.width)
        t_lo, t_hi, plane = clip_ray(g, o, d)
        acc = vec_c()
        ds = real(0.0)
        tr = real(1.0)
        logt = real(0.0)
        ncell = int(0)  # noqa: UP018 - Warp: a variable a loop mutates is declared dynamic
        iu = int(0)  # noqa: UP018
        iv = int(0)  # noqa: UP018
        iz = int(0)  # noqa: UP018
        if t_lo < t_hi:
            iu, iv, iz, su, sv, sz, na, nb, da, db, cu, cv, cz = start_walk(g, o, d, t_lo, plane, 0)
            t_entry = t_lo
            word = int(0)  # noqa: UP018
            for _it in range(max_steps):
                cell = (iz * g.height + iv) * g.width + iu
                acc, ds, logt, tr = cells.absorb(probs, b, cell, t_entry, acc, ds, logt, tr, save)
                ncell += 1
                if tr < real(tiny):
                    # Transmittance 0, or below the smallest normal number, where it is flushed to 0 (as FTZ
                    # arithmetic does): every later weight is 0, and the CPU is spared denormal arithmetic, which
                    # costs a hundred times more per operation.
                    tr = real(0.0)
                    break
                f, t, sf, nf, _old, nxt = pick_step(g, 0, su, sv, sz, iu, iv, iz, cu, cv, cz)
                if t >= t_hi or nxt < 0 or nxt >= nf:
                    break
                if save == 1:
                    step = ncell - 1
                    word = word | (f << (2 * (step % spw)))
                    if step % spw == spw - 1:
                        tape[step // spw, r] = word
                        word = 0
                iu, iv, iz, cu, cv, cz = take_step(na, nb, da, db, 0, f, sf, nf, nxt, iu, iv, iz, cu, cv, cz)
                t_entry = t
            if save == 1 and (ncell - 1) % spw != 0:
                tape[(ncell - 1) // spw, r] = word
        cells.finish_ray(classes, depth, dsum, b, n, p, acc, ds, tr)
        if save == 1:
            cells.save_ray(state, log_t, r, ncell, iu, iv, iz, logt)

    return accumulate_soft_hits_kernel


@cache
def _forward_own_kernel(real: Any, nc: int) -> Any:
    """:func:`accumulate_own_view_kernel` of instance ``(real, nc)``: the forward walk down the grid's columns."""
    vec_c, _vec_p = _vectors(real, nc)
    tiny = _tiny(real)
    cells = _cell_funcs(real, nc)

    @wp.kernel(enable_backward=False, module=_module(real, nc))
    def accumulate_own_view_kernel(
        probs: wp.array3d(dtype=real),
        g: GridInfo,
        cam: CameraInfo,
        n: int,
        save: int,
        classes: wp.array4d(dtype=real),
        depth: wp.array3d(dtype=real),
        dsum: wp.array3d(dtype=real),
        state: wp.array2d(dtype=wp.int32),
        log_t: wp.array(dtype=real),
    ):
        """:func:`accumulate_soft_hits_kernel` for the grid's own camera: thread (b, p) walks column
        ``p = j * W + i`` from slice 0 (the cells and entry depths of the general walk, which crosses only
        z-planes there); no tape.

        Launch dims ``(B, H * W)``; arrays as for :func:`accumulate_soft_hits_kernel` with ``h * w = H * W``.
        """
        b, p = wp.tid()
        r = (b * depth.shape[1] + n) * depth.shape[2] + p
        t_lo, na, nb, da, db = column_ray(g, cam, p)
        plane_cells = g.height * g.width
        acc = vec_c()
        ds = real(0.0)
        tr = real(1.0)
        logt = real(0.0)
        ncell = int(0)  # noqa: UP018
        t_entry = t_lo
        for k in range(g.depth):
            acc, ds, logt, tr = cells.absorb(probs, b, k * plane_cells + p, t_entry, acc, ds, logt, tr, save)
            ncell += 1
            if tr < real(tiny):
                tr = real(0.0)
                break
            t_entry = ray_crossing(na, nb, da, db, FAMILY_Z, k + 1, 1)
        cells.finish_ray(classes, depth, dsum, b, n, p, acc, ds, tr)
        if save == 1:
            cells.save_ray(state, log_t, r, ncell, p % g.width, p // g.width, ncell - 1, logt)

    return accumulate_own_view_kernel


@cache
def _backward_kernel(real: Any, nc: int) -> Any:
    """:func:`backpropagate_soft_hits_kernel` of instance ``(real, nc)``: the general backward walk."""
    cells = _cell_funcs(real, nc)
    spw = wp.constant(TAPE_STEPS_PER_WORD)

    @wp.kernel(enable_backward=False, module=_module(real, nc))
    def backpropagate_soft_hits_kernel(
        probs: wp.array3d(dtype=real),
        g: GridInfo,
        cam: CameraInfo,
        n: int,
        state: wp.array2d(dtype=wp.int32),
        log_t: wp.array(dtype=real),
        tape: wp.array2d(dtype=wp.int32),
        classes: wp.array4d(dtype=real),
        depth: wp.array3d(dtype=real),
        g_classes: wp.array4d(dtype=real),
        g_depth: wp.array3d(dtype=real),
        g_dsum: wp.array3d(dtype=real),
        given: int,
        grad: wp.array3d(dtype=real),
        common: wp.array2d(dtype=real),
    ):
        """Gradients from one ray's outputs into its cells: thread (b, p) as in the forward kernel.

        Launch dims ``(B, h * w)``, one launch per camera. Inputs: the forward kernel's ``probs``, ``g``, ``cam``,
        ``n``, its saved ``state``, ``log_t`` and ``tape``, its outputs ``classes`` ``(B, N, C, h*w)`` and
        ``depth`` ``(B, N, h*w)``, and the upstream gradients ``g_classes``, ``g_depth``, ``g_dsum`` of the same
        shapes, of which ``given`` flags those that exist (the others are 1-element dummies). Adds atomically,
        nonzero values only, into ``grad`` ``(B, C, D*H*W)`` (channel 0 and the class channels with a nonzero
        ``G_c``) and ``common`` ``(B, D*H*W)`` (the part of every class channel's gradient that does not depend on
        the channel). The ray's cells are visited last to first by undoing the taped steps
        (:func:`~fruxel.kernels.wp.traverse.step_back`); the module docstring gives the recursion.
        """
        b, p = wp.tid()
        r = (b * depth.shape[1] + n) * depth.shape[2] + p
        ncell = state[0, r]
        if ncell == 0:
            return
        gc, g0, gd, k = cells.ray_gradients(classes, depth, g_classes, g_depth, g_dsum, given, b, n, p)
        if cells.no_gradient(gc, g0, gd, k):
            return  # a pixel the loss ignores: nothing to add
        o = cam.origin
        d = pixel_ray(cam, p % cam.width, p // cam.width)
        t_lo, _t_hi, _plane = clip_ray(g, o, d)
        na, nb, da, db = ray_coefficients(g, o, d)
        su, sv, sz = step_signs(o, d)
        iu = state[1, r]
        iv = state[2, r]
        iz = state[3, r]
        logt = log_t[r]
        rr = g0
        # One cell of lookahead: the next cell's loads go out before this cell's atomics, which they could
        # otherwise not pass (the compiler cannot tell that the two arrays do not overlap).
        pm = cells.load_cell(probs, b, (iz * g.height + iv) * g.width + iu)
        for back in range(ncell):
            m = ncell - 1 - back
            cell = (iz * g.height + iv) * g.width + iu
            t = t_lo
            nxt = pm
            if m > 0:
                step = m - 1
                f = (tape[step // spw, r] >> (2 * (step % spw))) & 3
                t, iu, iv, iz = step_back(na, nb, da, db, f, su, sv, sz, iu, iv, iz)
                nxt = cells.load_cell(probs, b, (iz * g.height + iv) * g.width + iu)
            logt, tr, u, a, p0 = cells.cell_gradient(pm, t, logt, gc, gd, k)
            for c in range(wp.static(nc)):
                v = tr * gc[c]
                if v != real(0.0):
                    wp.atomic_add(grad, b, c + 1, cell, v)
            v = tr * u
            if v != real(0.0):
                wp.atomic_add(common, b, cell, v)
            v = tr * rr
            if v != real(0.0):
                wp.atomic_add(grad, b, 0, cell, v)
            rr = a + p0 * rr
            pm = nxt

    return backpropagate_soft_hits_kernel


@cache
def _backward_own_kernel(real: Any, nc: int) -> Any:
    """:func:`backpropagate_own_view_kernel` of instance ``(real, nc)``: the backward walk up the grid's columns."""
    cells = _cell_funcs(real, nc)

    @wp.kernel(enable_backward=False, module=_module(real, nc))
    def backpropagate_own_view_kernel(
        probs: wp.array3d(dtype=real),
        g: GridInfo,
        cam: CameraInfo,
        n: int,
        store: int,
        state: wp.array2d(dtype=wp.int32),
        log_t: wp.array(dtype=real),
        classes: wp.array4d(dtype=real),
        depth: wp.array3d(dtype=real),
        g_classes: wp.array4d(dtype=real),
        g_depth: wp.array3d(dtype=real),
        g_dsum: wp.array3d(dtype=real),
        given: int,
        grad: wp.array3d(dtype=real),
    ):
        """:func:`backpropagate_soft_hits_kernel` for the grid's own camera: thread (b, p) walks column
        ``p = j * W + i`` back to front. Its cells belong to no other ray of the launch, so values are written
        without atomics: with ``store`` = 1 every cell of the column and every channel is *written* (zeros
        behind an early stop and for a ray without gradient), so ``grad`` needs no initialisation; with
        ``store`` = 0 nonzero values are added.

        Launch dims ``(B, H * W)``; arrays as for :func:`backpropagate_soft_hits_kernel` (no ``common``: the
        common part goes straight into every class channel).
        """
        b, p = wp.tid()
        r = (b * depth.shape[1] + n) * depth.shape[2] + p
        ncell = state[0, r]
        plane_cells = g.height * g.width
        gc, g0, gd, k = cells.ray_gradients(classes, depth, g_classes, g_depth, g_dsum, given, b, n, p)
        quiet = cells.no_gradient(gc, g0, gd, k)
        if store == 1:
            first_zero = ncell
            if quiet:
                first_zero = 0
            for kk in range(first_zero, g.depth):
                for c in range(wp.static(nc + 1)):
                    grad[b, c, kk * plane_cells + p] = real(0.0)
        if quiet:
            return
        t_lo, na, nb, da, db = column_ray(g, cam, p)
        logt = log_t[r]
        rr = g0
        # One cell of lookahead, as in backpropagate_soft_hits_kernel: loads before this cell's stores.
        pm = cells.load_cell(probs, b, (ncell - 1) * plane_cells + p)
        for back in range(ncell):
            m = ncell - 1 - back
            cell = m * plane_cells + p
            t = t_lo
            nxt = pm
            if m > 0:
                t = ray_crossing(na, nb, da, db, FAMILY_Z, m, 1)
                nxt = cells.load_cell(probs, b, cell - plane_cells)
            logt, tr, u, a, p0 = cells.cell_gradient(pm, t, logt, gc, gd, k)
            if store == 1:
                for c in range(wp.static(nc)):
                    grad[b, c + 1, cell] = tr * (gc[c] + u)
                grad[b, 0, cell] = tr * rr
            else:
                for c in range(wp.static(nc)):
                    v = tr * (gc[c] + u)
                    if v != real(0.0):
                        grad[b, c + 1, cell] = grad[b, c + 1, cell] + v
                v = tr * rr
                if v != real(0.0):
                    grad[b, 0, cell] = grad[b, 0, cell] + v
            rr = a + p0 * rr
            pm = nxt

    return backpropagate_own_view_kernel


@cache
def kernels(real: Any, nc: int) -> dict[str, Any]:
    """The four kernels of instance ``(real, nc)``, made together so that their Warp module is complete before its
    first launch: ``"forward"``, ``"forward_own"`` (the grid's own view), ``"backward"``, ``"backward_own"``."""
    return {
        "forward": _forward_kernel(real, nc),
        "forward_own": _forward_own_kernel(real, nc),
        "backward": _backward_kernel(real, nc),
        "backward_own": _backward_own_kernel(real, nc),
    }


# ---------------------------------------------------------------------------------------------- host side
@dataclass(eq=False)
class SavedRays:
    """Per-ray record of a forward pass that the backward pass walks back; ray r = (b * N + n) * h*w + p."""

    state: Any
    """``(4, R)`` int32 torch tensor: cells on the ray and ``(i, j, k)`` of the last one."""
    log_t: Any
    """``(R,)`` torch tensor of the scalar type: ``log T`` after the last cell, saturated cells left out."""
    tape: Any
    """``(words, R)`` int32 torch tensor: the step tape (see :data:`TAPE_STEPS_PER_WORD`); one word per ray when
    every camera is an own view (no tape needed)."""
    cams: list[Packed]
    """Per camera, its packed :class:`~fruxel.kernels.wp.traverse.CameraInfo`."""
    own: list[bool]
    """Per camera, whether it is the grid's own view (the column kernels)."""
    size: tuple[int, int]
    """Image ``(h, w)`` of every camera."""


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


def _buffer(t: Any, shape: tuple[int, ...], real: Any, device: str) -> Buffer:
    """A contiguous torch tensor seen as a Warp buffer of ``shape`` (a view, no copy)."""
    return Buffer.of(t.view(shape), real, device)


def forward(probs: Any, grid: FruxelGrid, cameras: list[Camera], *, save: bool,
            device: str | None = None) -> tuple[Any, ...]:
    """Run the forward kernels: expected first hits of every pixel of every camera.

    Args:
        probs: ``(B, C, D, H, W)`` torch float32/float64, contiguous, on the CPU or a CUDA device: class
            probabilities, channel 0 = empty.
        grid: the volume's grid.
        cameras: N cameras sharing one image size ``h x w`` (checked by the caller).
        save: keep what :func:`backward` needs.
        device: the Warp device; the kernels run where ``probs`` lives, which the caller has made this device.

    Returns:
        ``(classes, depth, dsum, saved)``: ``classes`` ``(B, N, C, h, w)`` (channel 0 the miss probability,
        channel c the expected class-c mass), ``depth`` ``(B, N, h, w)`` the expected entry depth given a hit (0
        where no hit is possible), ``dsum`` ``(B, N, h, w)`` its unnormalised form (viewing-camera z), all of
        ``probs``' dtype and device; ``saved`` a :class:`SavedRays`, or None without ``save``. Nothing waits for
        the kernels: on CUDA they run in the caller's torch stream order.
    """
    real = _real(probs)
    dev = device_of(probs)
    ws = Workspace(dev, "torch", dev)
    b, c = probs.shape[0], probs.shape[1]
    h, w = cameras[0].height, cameras[0].width
    n_cam = len(cameras)
    kern = kernels(real, c - 1)
    own = [traversal.is_own_view(cam, grid) for cam in cameras]
    classes = ws.empty((b, n_cam, c, h * w), real)
    depth = ws.empty((b, n_cam, h * w), real)
    dsum = ws.empty((b, n_cam, h * w), real)
    rays = b * n_cam * h * w if save else 1
    steps = traversal.max_steps(grid)
    words = -(-steps // TAPE_STEPS_PER_WORD) if save and not all(own) else 1
    state = ws.empty((4, rays), wp.int32)
    log_t = ws.empty((rays,), real)
    tape = ws.empty((words, rays), wp.int32)
    p = _buffer(probs, (b, c, grid.n_cells), real, dev)
    g = grid_info(grid)
    cams = [camera_arg(cam) for cam in cameras]
    # Warp runs CPU kernels on the calling thread, so the thread's mode applies: near the end of a ray the
    # products T p fall below the smallest normal number.
    with flush_denormals(not ws.is_cuda):
        for n, (cam, is_own) in enumerate(zip(cams, own, strict=True)):
            if is_own:
                ws.launch(kern["forward_own"], (b, h * w),
                          [p, g, cam, n, int(save), classes, depth, dsum, state, log_t])
            else:
                ws.launch(kern["forward"], (b, h * w), [p, g, cam, n, steps, int(save), classes, depth, dsum, state,
                                                           log_t, tape])
    saved = SavedRays(state.native, log_t.native, tape.native, cams, own, (h, w)) if save else None
    return (classes.native.view(b, n_cam, c, h, w), depth.native.view(b, n_cam, h, w),
            dsum.native.view(b, n_cam, h, w), saved)


def backward(probs: Any, grid: FruxelGrid, groups: list[tuple[Any, ...]]) -> Any:
    """Run the backward kernels: the gradient of a loss with respect to ``probs``, over every camera group.

    Own-view cameras go first: the first of them writes every cell (no zero fill); the others add.

    Args:
        probs: the forward's input (unchanged since).
        grid: the forward's grid.
        groups: per camera group of the forward, ``(saved, classes, depth, g_classes, g_depth, g_dsum)``: its
            :class:`SavedRays`, its outputs ``classes`` ``(B, N, C, h, w)`` and ``depth`` ``(B, N, h, w)``, and
            the upstream gradients of ``classes``, ``depth`` and ``dsum`` (contiguous, ``probs``' dtype and
            device; None where that output gets no gradient).

    Returns:
        ``(B, C, D, H, W)`` gradient, of ``probs``' dtype and device (in stream order, no wait).
    """
    import torch

    real = _real(probs)
    dev = device_of(probs)
    ws = Workspace(dev, "torch", dev)
    b, c = probs.shape[0], probs.shape[1]
    kern = kernels(real, c - 1)
    n_cells = grid.n_cells
    launches = [(saved.own[n], gi, n) for gi, (saved, *_rest) in enumerate(groups) for n in range(len(saved.cams))]
    launches.sort(key=lambda x: not x[0])  # own views first (a stable sort keeps the order otherwise)
    store = launches[0][0]
    grad = torch.empty_like(probs) if store else torch.zeros_like(probs)
    gbuf = _buffer(grad, (b, c, n_cells), real, dev)
    common = None
    if not all(own for own, _, _ in launches):
        common = ws.empty((b, n_cells), real, zero=True)
    p = _buffer(probs, (b, c, n_cells), real, dev)
    g = grid_info(grid)
    bufs = []
    dummy = None
    for saved, classes, depth, g_cls, g_depth, g_dsum in groups:
        h, w = saved.size
        n_cam = len(saved.cams)
        hw = h * w
        given = sum(flag for t, flag in ((g_cls, GIVEN_CLASSES), (g_depth, GIVEN_DEPTH), (g_dsum, GIVEN_DSUM))
                    if t is not None)
        if dummy is None and given != GIVEN_CLASSES | GIVEN_DEPTH | GIVEN_DSUM:
            dummy = torch.empty((1,), dtype=probs.dtype, device=probs.device)
        pixels = (b, n_cam, hw)
        bufs.append([
            Buffer.of(saved.state, wp.int32, dev), Buffer.of(saved.log_t, real, dev),
            Buffer.of(saved.tape, wp.int32, dev),
            _buffer(classes, (b, n_cam, c, hw), real, dev),
            _buffer(dummy, (1, 1, 1, 1), real, dev) if g_cls is None else _buffer(g_cls, (b, n_cam, c, hw), real, dev),
            *(_buffer(dummy, (1, 1, 1), real, dev) if t is None else _buffer(t, pixels, real, dev)
              for t in (depth, g_depth, g_dsum)),
            given,
        ])
    # Warp runs CPU kernels on the calling thread, so the thread's mode applies: near the end of a ray the
    # products T p fall below the smallest normal number.
    with flush_denormals(not ws.is_cuda):
        for own, gi, n in launches:
            saved = groups[gi][0]
            h, w = saved.size
            state, log_t, tape, classes, g_cls, depth, g_depth, g_dsum, given = bufs[gi]
            cam = saved.cams[n]
            if own:
                ws.launch(kern["backward_own"], (b, h * w), [p, g, cam, n, int(store), state, log_t, classes,
                                                                depth, g_cls, g_depth, g_dsum, given, gbuf])
                store = False
            else:
                ws.launch(kern["backward"], (b, h * w), [p, g, cam, n, state, log_t, tape, classes, depth, g_cls,
                                                            g_depth, g_dsum, given, gbuf, common])
    if common is not None:
        grad.view(b, c, n_cells)[:, 1:] += common.native.unsqueeze(1)
    return grad


def soft_first_hit(scores: Any, grid: FruxelGrid, cameras: Any, *, device: str | None = None,
                   probs: bool = False) -> Any:
    """:func:`fruxel.kernels.soft_first_hit` on this backend (``device``: ``"cpu"``, ``"cuda"``, ``"cuda:N"``)."""
    from ..soft import soft_first_hit as _public

    return _public(scores, grid, cameras, backend="warp", device=device, probs=probs)

"""``soft_first_hit``: the differentiable counterpart of ``first_hit``, for losses on what a camera will see.

Along each pixel's ray, cells are visited in exactly the DDA order of :mod:`fruxel.kernels.traversal`. Cell m has
occupancy ``o_m = 1 - p_m(empty)``, class probabilities ``q_m(c)`` (the non-empty classes renormalised) and entry
depth ``t_m`` (the viewing camera's z where the ray enters it, as ``first_hit``'s depth). The ray stops at cell m
with probability ``w_m = o_m prod_{l<m} (1 - o_l)``; per pixel this gives

* ``classes[0] = miss = prod_m (1 - o_m)`` and ``classes[c] = sum_m w_m q_m(c)`` for ``c >= 1``: a distribution
  over ``first_hit`` labels (0 = miss) that sums to 1;
* ``depth = sum_m w_m t_m / sum_m w_m``: the expected entry depth *given a hit* (0 where the hit probability is 0),
  and ``depth_sum = sum_m w_m t_m``, its unnormalised form.

The normalised depth keeps "where" apart from "whether" (``classes`` carries the hit probability), so an L1 loss
on it moves the surface, not the hit probability. Its gradient with respect to the logits stays bounded where the
hit probability is small: the ``1 / hit`` of the normalisation meets ``d o / d logit = o (1 - o)`` with
``o_m <= hit / T_m``.

The kernels take the class probabilities ``p`` (channel 0 = empty), in which ``w_m q_m(c) = T_m p_m(c)``: the
renormalisation cancels and neither pass divides (see :mod:`fruxel.kernels.wp.soft_first_hit` for the derivation
of the written backward pass; Warp's automatic differentiation is wrong through loops with a dynamic bound or an
early exit). The softmax is one torch operation outside the kernels, differentiated by torch. The forward kernels
also finish each pixel (``classes``, ``depth``), so that no per-pixel torch operation follows, and the backward
kernels take the upstream gradients of those outputs directly (None for an output a loss does not use).

Every backend module ``soft_first_hit`` has ``forward(probs, grid, cameras, *, save, device=None)`` returning
``(classes, depth, depth_sum, saved)`` and ``backward(probs, grid, groups)`` with one ``(saved, classes, depth,
g_classes, g_depth, g_depth_sum)`` per camera group, returning the gradient with respect to ``probs``.

torch is imported on first use: ``import fruxel.kernels`` does not need it.
"""

from __future__ import annotations

import importlib
from dataclasses import dataclass
from functools import cache
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid

from . import traversal
from .inputs import VolumeError, check_cameras, is_torch
from .registry import resolve


@dataclass(frozen=True)
class SoftHits:
    """Per-pixel expected first hit, batched over B volumes and N cameras (all of one image size ``h x w``).

    Arrays are torch tensors (numpy arrays when the input was numpy), on the input's device, float64 for float64
    input and float32 otherwise. Depths are in metres along the viewing camera's z (= the ray parameter t).
    ``classes`` and ``depth`` are what the backward pass reads back, so a loss must not change them in place
    (autograd then raises); ``miss`` is a view of ``classes``.
    """

    classes: Any
    """``(B, N, C, h, w)``: channel 0 the miss probability, channel ``c >= 1`` the probability that the first hit
    has class c; sums to 1 over C, comparable to ``first_hit`` labels (0 = miss)."""
    depth: Any
    """``(B, N, h, w)``: expected entry depth of the first hit given a hit, ``depth_sum / hit``; 0 where the hit
    probability is 0 (as ``first_hit``'s depth on a miss)."""
    miss: Any
    """``(B, N, h, w)``: probability that the ray passes every cell, ``prod_m (1 - o_m)`` (= ``classes[:, :, 0]``)."""
    depth_sum: Any
    """``(B, N, h, w)``: ``sum_m w_m t_m``, the expected depth with a miss counted as 0."""

    @property
    def hit(self) -> Any:
        """``(B, N, h, w)``: probability of a hit, ``1 - miss``, summed from the class channels (accurate when
        small)."""
        return self.classes[:, :, 1:].sum(2)


# ---------------------------------------------------------------------------------------------- inputs
def _torch() -> Any:
    try:
        import torch
    except ImportError as e:
        raise ImportError(f"soft_first_hit needs torch ({e}); install it with: pip install 'fruxel[train]'") from None
    return torch


def check_same_size(cameras: Any) -> list[Camera]:
    """Cameras as a list, all of one image size.

    Raises:
        VolumeError: no camera, something that is not a camera, or cameras of different image sizes.
    """
    cams = check_cameras(cameras)
    sizes = {(c.width, c.height) for c in cams}
    if len(sizes) > 1:
        raise VolumeError(
            f"soft_first_hit: all cameras of one call must share the image size, got (w, h) {sorted(sizes)}; "
            "call once per size"
        )
    return cams


def _as_tensor(x: Any, name: str) -> Any:
    torch = _torch()
    if isinstance(x, np.ndarray):
        if x.dtype.kind != "f":
            raise VolumeError(f"{name} must be a float array, got {x.dtype}")
        # torch takes neither negative strides, nor the other byte order, nor long double.
        dtype = np.dtype(np.float64) if x.dtype.itemsize > 8 else x.dtype.newbyteorder("=")
        return torch.from_numpy(np.ascontiguousarray(x, dtype=dtype))
    if not is_torch(x):
        raise VolumeError(f"{name} must be a numpy array or torch tensor, got {type(x).__name__}")
    if not x.dtype.is_floating_point:
        raise VolumeError(f"{name} must be a float tensor, got {x.dtype}")
    return x


def _check_scores(s: Any, grid: FruxelGrid, name: str = "scores") -> None:
    dhw = grid.shape
    if not s.dtype.is_floating_point:
        raise VolumeError(f"{name} must be float, got {s.dtype}")
    if s.dim() != 5 or tuple(s.shape[2:]) != dhw or s.shape[1] < 2 or s.shape[0] == 0:
        raise VolumeError(f"{name} must have shape (B, C, *{dhw}) with B >= 1 and C >= 2, got {tuple(s.shape)}")


def scores_to_probs(scores: Any, *, probs: bool = False) -> Any:
    """Class probabilities of scores as the kernels take them: ``softmax`` over C for logits, the scores themselves
    for probabilities; bfloat16 and float16 are computed in float32. A torch operation, differentiated by torch.

    Args:
        scores: ``(B, C, D, H, W)`` torch float tensor, channel 0 = empty.
        probs: the scores are probabilities already.

    Returns:
        ``(B, C, D, H, W)`` float64 for float64 scores, else float32.
    """
    torch = _torch()
    s = scores if scores.dtype in (torch.float32, torch.float64) else scores.float()
    return s if probs else torch.softmax(s, dim=1)


# ---------------------------------------------------------------------------------------------- autograd
@cache
def _function() -> Any:
    """The ``torch.autograd.Function`` around a backend's forward and backward kernels (made on first use)."""
    torch = _torch()
    from torch.autograd.function import once_differentiable

    class SoftFirstHitFunction(torch.autograd.Function):
        """``probs (B, C, D, H, W)`` -> per camera group ``classes (B, N, C, h, w), depth, depth_sum (B, N, h, w)``,
        flattened group after group. One backward pass gathers every group's gradient into one tensor."""

        @staticmethod
        def forward(ctx: Any, probs: Any, impl: Any, device: Any, grid: FruxelGrid, groups: list, save: bool) -> Any:
            outs, saved = [], []
            for cams in groups:
                classes, depth, dsum, rays = impl.forward(probs, grid, cams, save=save, device=device)
                outs += [classes, depth, dsum]
                saved.append(rays)
            ctx.impl, ctx.grid, ctx.rays = impl, grid, saved if save else None
            # Outputs the loss does not use get None, not a zero-filled tensor (one device fill each saved).
            ctx.set_materialize_grads(False)
            if save:
                # The backward kernels read each ray's class sums and depth back (saved as outputs, so that an
                # in-place change to them is caught by autograd's version check).
                ctx.save_for_backward(probs, *(x for g in range(len(groups)) for x in outs[3 * g: 3 * g + 2]))
            return tuple(outs)

        @staticmethod
        @once_differentiable
        def backward(ctx: Any, *grads: Any) -> Any:
            if ctx.rays is None:
                raise RuntimeError("soft_first_hit: backward through a forward pass that saved nothing")
            probs, *outs = ctx.saved_tensors
            groups = []
            for g, rays in enumerate(ctx.rays):
                g_cls, g_depth, g_dsum = (None if x is None else x.to(probs.dtype).contiguous()
                                          for x in grads[3 * g: 3 * g + 3])
                if g_cls is None and g_depth is None and g_dsum is None:
                    continue
                groups.append((rays, outs[2 * g], outs[2 * g + 1], g_cls, g_depth, g_dsum))
            if not groups:
                return None, None, None, None, None, None
            return ctx.impl.backward(probs, ctx.grid, groups), None, None, None, None, None

    return SoftFirstHitFunction


def _hits(classes: Any, depth: Any, dsum: Any, out_device: Any) -> SoftHits:
    """SoftHits from the kernels' outputs, on ``out_device``."""
    if classes.device != out_device:
        classes, depth, dsum = classes.to(out_device), depth.to(out_device), dsum.to(out_device)
    return SoftHits(classes, depth, classes[:, :, 0], dsum)


def _numpy(h: SoftHits) -> SoftHits:
    return SoftHits(*(t.detach().cpu().numpy() for t in (h.classes, h.depth, h.miss, h.depth_sum)))


def _run(p: Any, grid: FruxelGrid, groups: list[list[Camera]], backend: str | None,
         device: str | None) -> list[SoftHits]:
    """The kernels on probabilities ``p`` ``(B, C, D, H, W)`` (float32/64 torch) for each camera group; results
    on ``p``'s device."""
    torch = _torch()
    mod, dev = resolve(backend, device, p)
    impl = importlib.import_module(".soft_first_hit", mod.__name__)
    kp = p.to(impl.torch_device(dev)).contiguous()
    save = torch.is_grad_enabled() and kp.requires_grad
    outs = _function().apply(kp, impl, dev, grid, groups, save)
    return [_hits(*outs[3 * g: 3 * g + 3], p.device) for g in range(len(groups))]


# ---------------------------------------------------------------------------------------------- public
def soft_first_hit(
    scores: Any,
    grid: FruxelGrid,
    cameras: Camera | list[Camera],
    *,
    backend: str | None = None,
    device: str | None = None,
    probs: bool = False,
) -> SoftHits:
    """Differentiable expected first hit of every pixel of every camera (conventions section 4), batched over B and N.

    The occupancy is ``1 - p(empty)`` and the class probabilities are the non-empty classes renormalised; the ray
    stops at cell m with probability ``w_m = o_m prod_{l<m} (1 - o_l)`` (see the module docstring).

    Args:
        scores: ``(B, C, D, H, W)`` logits (or probabilities with ``probs=True``), channel 0 = empty, C >= 2;
            torch float64/float32/bfloat16/float16 on the CPU or CUDA, or numpy.
        grid: the volume's grid.
        cameras: one camera or a list of N cameras sharing one image size ``h x w``; any pose, the grid's own
            camera (``grid.camera()``) included.
        backend: ``"warp"``, ``"opencl"``, an :func:`~fruxel.kernels.available_backends` name such as
            ``"warp-cpu"``, or None (the best available).
        device: Warp device (``"cpu"``, ``"cuda"``, ``"cuda:1"``) or None to follow the data.
        probs: the scores are probabilities (each cell's sum 1).

    Returns:
        :class:`SoftHits` on the input's device: ``classes`` ``(B, N, C, h, w)``, ``depth``, ``miss`` and
        ``depth_sum`` ``(B, N, h, w)``; float64 for float64 scores, else float32 (bfloat16 and float16 are
        computed in float32). torch autograd flows back to ``scores``; under ``torch.no_grad``, or when
        ``scores`` needs no gradient, nothing is kept for a backward pass. Otherwise the forward keeps, per ray,
        its end state (5 words) and, unless every camera of its group is the grid's own view, a step tape of 2 bits
        per step (about ``(W + H + D + 3) / 15`` 32-bit words), besides the outputs ``classes`` and ``depth``.

    Raises:
        VolumeError, fruxel.CameraError: bad shapes, dtypes or cameras (nothing is computed). Values are not
            scanned, which would synchronise with the GPU: NaN scores give NaN results, as in any torch operation.
        BackendError, BackendUnavailable: an unknown or missing backend.
    """
    return soft_first_hit_groups(scores, grid, [cameras], backend=backend, device=device, probs=probs)[0]


def soft_first_hit_groups(
    scores: Any,
    grid: FruxelGrid,
    camera_groups: list[Camera | list[Camera]],
    *,
    backend: str | None = None,
    device: str | None = None,
    probs: bool = False,
) -> list[SoftHits]:
    """:func:`soft_first_hit` for several groups of cameras at once, e.g. the grid's own view (``W x H``) and
    novel views of another image size: one softmax, one kernel launch per camera, one backward pass that adds
    every group's gradient into one tensor.

    Args:
        scores, grid, backend, device, probs: as for :func:`soft_first_hit`.
        camera_groups: a list of groups, each a camera or a list of cameras of one image size (sizes may differ
            between groups).

    Returns:
        One :class:`SoftHits` per group, in order.

    Raises:
        VolumeError, fruxel.CameraError, BackendError, BackendUnavailable: as for :func:`soft_first_hit`.
    """
    numpy_in = isinstance(scores, np.ndarray)
    s = _as_tensor(scores, "scores")
    _check_scores(s, grid)
    if not isinstance(camera_groups, (list, tuple)) or not camera_groups:
        raise VolumeError("camera_groups must be a non-empty list of cameras or camera lists")
    groups = [check_same_size(g) for g in camera_groups]
    hits = _run(scores_to_probs(s, probs=probs), grid, groups, backend, device)
    return [_numpy(h) for h in hits] if numpy_in else hits


def soft_first_hit_occ(
    occupancy: Any,
    class_probs: Any,
    grid: FruxelGrid,
    cameras: Camera | list[Camera],
    *,
    backend: str | None = None,
    device: str | None = None,
) -> SoftHits:
    """:func:`soft_first_hit` from occupancies and class probabilities given separately.

    Args:
        occupancy: ``(B, D, H, W)`` float, ``o = 1 - p(empty)`` in [0, 1], by cell ``(k, j, i)``; torch (CPU or
            CUDA) or numpy.
        class_probs: ``(B, C-1, D, H, W)`` float, each cell's distribution over the non-empty classes 1..C-1.
        grid, cameras, backend, device: as for :func:`soft_first_hit`.

    Returns:
        :class:`SoftHits` as for :func:`soft_first_hit`, differentiable with respect to both inputs (they enter
        the kernels as ``p = (1 - o, o q)``).

    Raises:
        VolumeError, fruxel.CameraError, BackendError, BackendUnavailable: as for :func:`soft_first_hit`.
    """
    torch = _torch()
    numpy_in = isinstance(occupancy, np.ndarray) and isinstance(class_probs, np.ndarray)
    occ = _as_tensor(occupancy, "occupancy")
    cls = _as_tensor(class_probs, "class_probs")
    dhw = grid.shape
    if occ.dim() != 4 or tuple(occ.shape[1:]) != dhw or occ.shape[0] == 0:
        raise VolumeError(f"occupancy must have shape (B, *{dhw}) with B >= 1, got {tuple(occ.shape)}")
    if cls.dim() != 5 or tuple(cls.shape[2:]) != dhw or cls.shape[0] != occ.shape[0] or cls.shape[1] < 1:
        raise VolumeError(
            f"class_probs must have shape ({occ.shape[0]}, C-1, *{dhw}) with C-1 >= 1, got {tuple(cls.shape)}"
        )
    if occ.device != cls.device:
        raise VolumeError(f"occupancy and class_probs are on different devices ({occ.device}, {cls.device})")
    real = torch.float64 if torch.float64 in (occ.dtype, cls.dtype) else torch.float32
    o = occ.to(real).unsqueeze(1)
    p = torch.cat([1.0 - o, o * cls.to(real)], dim=1)
    (hits,) = _run(p, grid, [check_same_size(cameras)], backend, device)
    return _numpy(hits) if numpy_in else hits


def own_view_entry_depths(grid: FruxelGrid) -> np.ndarray:
    """Entry depth of each slice along the grid's own camera rays, ``(D,)`` float32, as the kernels compute it:
    ``z_near`` for the first slice (the near-plane clip), then the slice boundary ``z_near + k dz`` in float32."""
    g = traversal.grid_params(grid)
    return g[4] + np.arange(grid.depth, dtype=np.float32) * g[5]


def soft_first_hit_own_view_torch(scores: Any, grid: FruxelGrid, *, probs: bool = False) -> SoftHits:
    """Pure-torch reference of :func:`soft_first_hit` from the grid's own camera at native resolution.

    Pixel (x, y) of that camera looks straight down column (j, i) = (y, x) through cells k = 0..D-1, so the
    transmittance is an exclusive ``cumprod`` of ``1 - o`` along D, written from the definition (``o`` and ``q``
    explicitly, not the kernels' cancelled form), and torch's autograd gives the gradients. Tests and the benchmark
    use it as the baseline; it needs no backend.

    Args:
        scores: ``(B, C, D, H, W)`` torch float logits (or probabilities with ``probs=True``), channel 0 = empty.
        grid: their grid.
        probs: the scores are probabilities.

    Returns:
        :class:`SoftHits` with N = 1 and ``h, w = H, W``, float64 for float64 scores, else float32.
    """
    torch = _torch()
    _check_scores(scores, grid)
    s = scores if scores.dtype in (torch.float32, torch.float64) else scores.float()
    if probs:
        occ = 1.0 - s[:, 0]
        rest = s[:, 1:]
        total = rest.sum(1, keepdim=True)
        cls = rest / torch.where(total > 0, total, torch.ones_like(total))
    else:
        occ = torch.sigmoid(torch.logsumexp(s[:, 1:], dim=1) - s[:, 0])
        cls = torch.softmax(s[:, 1:], dim=1)
    free = 1.0 - occ
    trans = torch.cumprod(torch.cat([torch.ones_like(free[:, :1]), free[:, :-1]], dim=1), dim=1)
    w = occ * trans
    t = torch.as_tensor(own_view_entry_depths(grid), device=s.device).to(s.dtype)
    acc = (w.unsqueeze(1) * cls).sum(2)
    miss = trans[:, -1] * free[:, -1]
    dsum = (w * t[None, :, None, None]).sum(1)
    hit = acc.sum(1)
    pos = hit > torch.finfo(hit.dtype).tiny
    # Where no hit is possible the ratio is 0/0: divide by 1 there, so that no NaN reaches the backward pass.
    depth = torch.where(pos, dsum / torch.where(pos, hit, torch.ones_like(hit)), torch.zeros_like(dsum))
    classes = torch.cat([miss.unsqueeze(1), acc], dim=1)
    return SoftHits(classes.unsqueeze(1), depth.unsqueeze(1), miss.unsqueeze(1), dsum.unsqueeze(1))

"""Building blocks of SSZ: 2D inverted residual blocks (MobileNetV2), their volumetric counterparts, and the
2D-to-3D lift that puts image features into the depth slices of a fruxel volume.

Tensors are NCHW (2D) and NCDHW (3D, conventions section 2); a 3D block keeps its input's memory format, so a
channels-last-3D input stays channels-last-3D.
"""

from __future__ import annotations

import math

import torch
from torch import nn

LEAK = 0.1
"""Negative slope of the decoder's LeakyReLUs (conventions section 8)."""


def act2d() -> nn.Module:
    """The 2D encoder's activation (ReLU6, as in MobileNetV2: bounded, so bf16 activations never overflow)."""
    return nn.ReLU6(inplace=True)


def act3d() -> nn.Module:
    """The 3D decoder's activation (LeakyReLU, conventions section 8)."""
    return nn.LeakyReLU(LEAK, inplace=True)


class InvertedResidual2d(nn.Module):
    """MobileNetV2 inverted residual block: expand 1x1, depthwise 3x3, project 1x1 (linear), residual.

    The last batch norm's scale starts at zero, so a fresh block is the identity (as the volumetric blocks are): a
    block added to a trained encoder leaves the network's answer as it was until training moves it.

    Args:
        channels: input and output channels.
        expand: expansion factor of the hidden width.
    """

    def __init__(self, channels: int, expand: int) -> None:
        super().__init__()
        hidden = channels * expand
        self.body = nn.Sequential(
            nn.Conv2d(channels, hidden, 1, bias=False), nn.BatchNorm2d(hidden), act2d(),
            nn.Conv2d(hidden, hidden, 3, padding=1, groups=hidden, bias=False), nn.BatchNorm2d(hidden), act2d(),
            nn.Conv2d(hidden, channels, 1, bias=False), nn.BatchNorm2d(channels),
        )
        nn.init.zeros_(self.body[-1].weight)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, channels, h, w)`` -> same shape."""
        return x + self.body(x)


class Down2d(nn.Module):
    """Halves the resolution with a depthwise 3x3 stride-2 convolution, then changes the width with a pointwise
    one (conventions section 8: "downscaled by depthwise and pointwise convolutions").

    Args:
        cin, cout: input and output channels.
    """

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(cin, cin, 3, stride=2, padding=1, groups=cin, bias=False), nn.BatchNorm2d(cin), act2d(),
            nn.Conv2d(cin, cout, 1, bias=False), nn.BatchNorm2d(cout), act2d(),
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, cin, h, w)`` -> ``(B, cout, ceil(h / 2), ceil(w / 2))``."""
        return self.body(x)


class Pointwise3d(nn.Conv3d):
    """A 1x1x1 ``Conv3d`` (the same parameters, initialisation and state-dict keys) computed as a matrix product
    over the channels: ``weight (cout, cin) @ x[b] (cin, D*H*W)`` for each sample, or ``x (B, D, H, W, cin) @
    weight.T`` for a channels-last-3D input, whose output is channels-last-3D too.

    On the H100, cuDNN ran the decoder's 1x1x1 convolutions at 64^3 with layout conversions around them
    (NCDHW <-> NDHWC) and, for their weight gradients, a slow implicit-GEMM kernel: a large share of a training
    step's kernel time (``benchmarks/profile_ssz.py``, BENCHMARKS.md). The same product on cuBLAS runs at memory
    speed, forward and backward, and needs no conversion.

    Args:
        cin, cout: input and output channels.
        bias: add a learnt bias per output channel.
    """

    def __init__(self, cin: int, cout: int, bias: bool = True) -> None:
        super().__init__(cin, cout, 1, bias=bias)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, cin, D, H, W)`` -> ``(B, cout, D, H, W)``, in ``x``'s memory format."""
        b, c, d, h, w = x.shape
        weight = self.weight.view(self.out_channels, c)
        if x.is_contiguous():
            # bmm over the batch with the weight broadcast (stride 0): torch.matmul would fold (B, C, N) into
            # (B * N, C) through a transposed copy of the whole volume, forward and backward.
            y = torch.bmm(weight.expand(b, -1, -1), x.view(b, c, d * h * w))
            if self.bias is not None:
                # In the product's dtype (bfloat16 under autocast), as the convolution adds it.
                y = y + self.bias.to(y.dtype).view(-1, 1)
            return y.view(b, self.out_channels, d, h, w)
        if x.is_contiguous(memory_format=torch.channels_last_3d):
            return nn.functional.linear(x.permute(0, 2, 3, 4, 1), weight, self.bias).permute(0, 4, 1, 2, 3)
        return super().forward(x)


class InvertedResidual3d(nn.Module):
    """Volumetric inverted residual block: expand 1x1x1, depthwise 3x3x3, project 1x1x1, residual.

    No batch normalisation: on the H100 its bfloat16 statistics and backward kernels over 64^3 volumes cost more
    than every convolution of the decoder together (benchmarks/bench_ssz.py). The projection starts at zero, so
    each block starts as the identity and the stack trains stably without it.

    Args:
        channels: input and output channels.
        expand: expansion factor of the hidden width.
        spatial: False leaves the 3x3x3 convolution out (a per-cell block, for the finest level, where the
            neighbourhood comes from the up-convolution below it).
    """

    def __init__(self, channels: int, expand: int, spatial: bool = True) -> None:
        super().__init__()
        hidden = channels * expand
        project = Pointwise3d(hidden, channels)
        nn.init.zeros_(project.weight)
        nn.init.zeros_(project.bias)
        layers: list[nn.Module] = [Pointwise3d(channels, hidden), act3d()]
        if spatial:
            layers += [depthwise_conv3d(hidden), act3d()]
        self.body = nn.Sequential(*layers, project)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, channels, D, H, W)`` -> same shape."""
        return x + self.body(x)


def depthwise_conv3d(channels: int) -> nn.Conv3d:
    """The depthwise 3x3x3 convolution of the decoder's blocks, ``channels`` in and out."""
    return nn.Conv3d(channels, channels, 3, padding=1, groups=channels)


def channels_last(model: nn.Module) -> nn.Module:
    """Store every 5-D weight channels-last-3D and every 4-D weight channels-last (in place); returns ``model``.

    ``Module.to(memory_format=...)`` refuses a model that mixes 2D and 3D convolutions, as SSZ does.
    """
    for p in model.parameters():
        if p.ndim == 5:
            p.data = p.data.contiguous(memory_format=torch.channels_last_3d)
        elif p.ndim == 4:
            p.data = p.data.contiguous(memory_format=torch.channels_last)
    return model


class Up3d(nn.Module):
    """Doubles the resolution of a volume: a depthwise-separable 3D up-convolution, LeakyReLU, pointwise 3D
    convolution (conventions section 8's decoder block).

    The up-convolution is written in its "parity" form: the depthwise 3x3x3 convolution at the *input*
    resolution, then a depthwise transposed convolution of kernel 2 and stride 2, which gives each of the eight
    output parities its own weight per channel. The neighbourhood is gathered where there are eight times fewer
    cells, and the kernel-2 transposed convolution, written as nearest x2 times a periodic weight, is one
    elementwise product (PyTorch's grouped ``ConvTranspose3d`` and depthwise ``Conv3d`` have no fast CUDA kernels:
    pytorch issues 37406 and 47341; the forms measured are in BENCHMARKS.md).

    Args:
        cin, cout: input and output channels.
    """

    def __init__(self, cin: int, cout: int) -> None:
        super().__init__()
        self.up = depthwise_conv3d(cin)
        # Depthwise ConvTranspose3d(kernel 2, stride 2) weights, one per channel and output parity.
        self.parity = nn.Parameter(torch.ones(1, cin, 1, 2, 1, 2, 1, 2))
        self.post = nn.Sequential(act3d(), Pointwise3d(cin, cout), act3d())

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        """``(B, cin, D, H, W)`` -> ``(B, cout, 2D, 2H, 2W)``."""
        y = self.up(x)
        b, c, d, h, w = y.shape
        up = (y[:, :, :, None, :, None, :, None] * self.parity.to(y.dtype)).reshape(b, c, 2 * d, 2 * h, 2 * w)
        if y.is_contiguous(memory_format=torch.channels_last_3d) and not y.is_contiguous():
            up = up.contiguous(memory_format=torch.channels_last_3d)
        return self.post(up)


def coordinates(shape: tuple[int, int, int], device: torch.device, dtype: torch.dtype) -> torch.Tensor:
    """Normalised cell coordinates of a grid level, ``(1, 3, D, H, W)``: channel 0 the slice ``(k + 1/2) / D``,
    1 the row ``(j + 1/2) / H``, 2 the column ``(i + 1/2) / W``, each shifted to [-1/2, 1/2].

    Convolutions are translation invariant; the camera-aligned grid is not (the floor is at the bottom of the
    image, depth grows with k), so the decoder sees where each cell is.
    """
    axes = [(torch.arange(n, device=device, dtype=torch.float32) + 0.5) / n - 0.5 for n in shape]
    k, j, i = torch.meshgrid(*axes, indexing="ij")
    return torch.stack([k, j, i]).unsqueeze(0).to(dtype)


class Lift(nn.Module):
    """2D-to-3D skip of one decoder level: merges the decoder's volume with the image features of the same
    resolution copied into every depth slice (the Z-GAN skip) and with where along each column the visible surface
    lies.

    ``merge([x3d, copy(f2d), depth_features, coordinates])`` is one pointwise convolution over the concatenation;
    it is computed as the sum of a 3D pointwise convolution of ``x3d`` and of the small per-cell features, plus a
    2D pointwise convolution of ``f2d`` broadcast along depth. That is the same function without materialising
    the copy (which would be ``D`` times the image features).

    Depth features per cell (2 channels): the probability that the column's first surface is in this slice (the
    column's distribution, pooled to the level's resolution and scaled so that a column sums to its hit
    probability) and the cumulative probability up to and including it (0 in front of the surface, 1 behind).
    Cells in front of what the camera sees are empty; the cumulative channel says which those are.

    With ``camera`` channels, the camera's per-cell geometry (:class:`~.conditioning.CameraConditioning`: each
    cell's height above the floor where gravity and height are known) joins the sum through one more pointwise
    term; without them the module and its parameters are what they were.

    Args:
        c3d: channels of the decoder's volume (0 at the bottom level, where there is none yet).
        c2d: channels of the image features.
        cout: output channels.
        camera: channels of the camera features (0: the network reads no camera).
    """

    DEPTH_CHANNELS = 2
    """Channels of the depth features (:meth:`~.generator.SSZGenerator.depth_features`)."""

    def __init__(self, c3d: int, c2d: int, cout: int, camera: int = 0) -> None:
        super().__init__()
        self.from_2d = nn.Conv2d(c2d, cout, 1, bias=False)
        self.from_3d = Pointwise3d(c3d, cout, bias=False) if c3d else None
        self.from_coords = Pointwise3d(3, cout, bias=True)
        self.from_depth = Pointwise3d(self.DEPTH_CHANNELS, cout, bias=False)
        self.from_camera = Pointwise3d(camera, cout, bias=False) if camera else None
        self.post = act3d()

    def forward(self, x3d: torch.Tensor | None, f2d: torch.Tensor, depth: torch.Tensor,
                shape: tuple[int, int, int], camera: torch.Tensor | None = None) -> torch.Tensor:
        """Merge one level.

        Args:
            x3d: ``(B, c3d, D, H, W)`` decoder volume, or None at the bottom level.
            f2d: ``(B, c2d, H, W)`` image features of this resolution.
            depth: ``(B, 2, D, H, W)`` depth features.
            shape: ``(D, H, W)`` of this level.
            camera: ``(B, camera, D, H, W)`` camera features when the module has camera channels (else ignored).

        Returns:
            ``(B, cout, D, H, W)``, in ``x3d``'s memory format.
        """
        ref = x3d if x3d is not None else f2d
        # The coordinate term is the same for every sample: computed once, broadcast over the batch.
        y = self.from_coords(coordinates(shape, ref.device, ref.dtype)) + self.from_2d(f2d).unsqueeze(2)
        if self.from_3d is not None:
            # The dense volume first, so that the sum keeps its (channels-last) layout.
            y = self.from_3d(x3d) + y
        elif y.shape[0] != f2d.shape[0]:
            y = y.expand(f2d.shape[0], -1, -1, -1, -1)
        y = y + self.from_depth(depth.to(y.dtype))
        if self.from_camera is not None and camera is not None:
            y = y + self.from_camera(camera.to(y.dtype))
        return self.post(y)


class SurfaceFusion(nn.Module):
    """The image side's own-view answer, written into the volume's logits: a per-cell term added to the decoder's
    logits from each column's first-surface depth distribution and surface class.

    What the grid's own camera sees of a column is its first occupied cell; the image-side heads predict exactly
    that (the slice, as a distribution over the D slices plus "no surface", and the class). The decoder receives
    the depth distribution as a feature (:class:`Lift`) but is free to ignore it: in the first shipped model (no
    fusion) the surface-class head alone named the own view's first hit more often than the volume did
    (docs/experiments.md). This layer gives the heads a direct, learnt say in the logits of every cell, per cell,
    from four log-probabilities:

    * ``log P(in front)``: the column's surface lies behind this slice (or there is none): the cell is empty;
    * ``log P(behind)``: the surface lies in front of this slice: the cell is hidden, anything goes;
    * ``log (P(here) / max over the column's slices)``: 0 at the column's most likely surface slice. A column
      unsure *where* its surface is (a plain wall filling the image) spreads its probability over many slices,
      so that no cell of it is more likely occupied than empty and the argmax leaves the column with no surface
      at all; this field marks the one slice to put it in;
    * ``log P(surface here) + log P(class c | surface)`` for each occupied class c.

    The ``C + 2`` features are mixed into ``C`` logits by 1x1x1 weights that start at zero (``mix`` for all but
    the third, ``mode`` for it), so a new model starts as the decoder alone and learns how far to trust the
    heads. Log-probabilities are floored at ``log(FLOOR)`` so that the term stays bounded.

    Args:
        classes: C, classes including empty (channel 0).
    """

    FLOOR = 1e-4
    """Smallest probability (or ratio to the column's most likely slice) taken into a log feature."""

    def __init__(self, classes: int) -> None:
        super().__init__()
        self.mix = Pointwise3d(classes + 1, classes)
        self.mode = Pointwise3d(1, classes, bias=False)
        for p in (self.mix.weight, self.mix.bias, self.mode.weight):
            nn.init.zeros_(p)

    def _fields(self, depth_logits: torch.Tensor, surface_logits: torch.Tensor
                ) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor, torch.Tensor]:
        """``log P(in front)``, ``log P(behind)``, ``log P(here)``, ``log (P(here) / max P(here))``, each
        ``(B, D, H, W)``, and ``log P(class c | surface)`` for c = 1 .. C-1, ``(B, C-1, H, W)``; float32,
        floored."""
        q = torch.softmax(depth_logits.float(), dim=1)
        here = q[:, :-1]  # (B, D, H, W)
        upto = torch.cumsum(here, dim=1)
        floor = self.FLOOR
        front = torch.log((1.0 - upto).clamp(min=floor))
        behind = torch.log((upto - here).clamp(min=floor))
        # The softmax never gives exactly 0, so the column maximum is positive.
        mode = torch.log((here / here.amax(dim=1, keepdim=True)).clamp(min=floor))
        cls = torch.log_softmax(surface_logits.float(), dim=1)[:, 1:].clamp(min=math.log(floor))
        return front, behind, torch.log(here.clamp(min=floor)), mode, cls

    def features(self, depth_logits: torch.Tensor, surface_logits: torch.Tensor) -> torch.Tensor:
        """The per-cell log features that the weights mix.

        Args:
            depth_logits: ``(B, D + 1, H, W)`` logits of each column's first-surface slice (bin D = no surface).
            surface_logits: ``(B, C, H, W)`` logits of each column's first-surface class (0 = no surface).

        Returns:
            ``(B, C + 2, D, H, W)`` float32: ``log P(in front)``, ``log P(behind)``, ``log (P(here) / max)``, then
            ``log P(here, class c)`` for c = 1 .. C-1.
        """
        front, behind, here, mode, cls = self._fields(depth_logits, surface_logits)
        at = here.unsqueeze(1) + cls.unsqueeze(2)
        return torch.cat([front.unsqueeze(1), behind.unsqueeze(1), mode.unsqueeze(1), at], dim=1)

    def forward(self, depth_logits: torch.Tensor, surface_logits: torch.Tensor) -> torch.Tensor:
        """The 1x1x1 mix of :meth:`features`: the ``(B, C, D, H, W)`` term to add to the decoder's logits, in the
        weights' dtype.

        The mix is linear and ``log P(here, c) = log P(here) + log P(c | surface)``, whose second part is the same
        in every cell of a column; so the term is computed as four per-cell fields weighted per output class plus
        one per-column term broadcast along depth, never materialising the ``C + 2`` features (the same function,
        a small share of the network's kernel time: benchmarks/profile_ssz.py).
        """
        front, behind, here, mode, cls = self._fields(depth_logits, surface_logits)
        dtype = self.mix.weight.dtype
        w = self.mix.weight.view(self.mix.out_channels, -1)  # (C, C + 1)
        column = torch.einsum("oc,bchw->bohw", w[:, 2:].to(dtype), cls.to(dtype))
        column = column + self.mix.bias.to(dtype).view(1, -1, 1, 1)
        view = (1, -1, 1, 1, 1)
        return (w[:, 0].to(dtype).view(view) * front.to(dtype).unsqueeze(1)
                + w[:, 1].to(dtype).view(view) * behind.to(dtype).unsqueeze(1)
                + self.mode.weight.to(dtype).view(view) * mode.to(dtype).unsqueeze(1)
                + w[:, 2:].sum(dim=1).to(dtype).view(view) * here.to(dtype).unsqueeze(1)
                + column.unsqueeze(2))

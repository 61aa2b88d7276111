"""The SSZ generator: one RGB image of the grid's own camera -> logits of a fruxel model (conventions section 8).

Architecture (``L`` = ``levels``; level ``s`` has the grid's resolution divided by ``2^s``)::

    image (B, 3, h, w), w = W * 2^k
      | normalise; stem: 3x3 stride-2 conv, then k-1 depthwise/pointwise halvings        (2D, to H x W)
      |   [with detail_branch the image is twice as large: the stem reads it 2x2-pooled, the branch the image
      |    itself, and their sum goes on]
      | encoder level s = 0 .. L-1: [halving], inverted residual blocks -> e_s          (B, E_s, H_s, W_s)
      | global context: mean over the image, pointwise, added to e_{L-1}
      | top-down path: t_{L-1} = e_{L-1}; t_s = block(up(t_{s+1}) + lateral(e_s))      (B, T_s, H_s, W_s)
      | heads on t_0: column depth distribution (D + 1 bins, the last = no surface) and surface class (C)
      v
    3D decoder, bottom up:
      x_{L-1} = Lift(learned depth lift of t_{L-1}, t_{L-1}, depth features)             (B, V_{L-1}, D_s, H_s, W_s)
      x_s     = blocks(Lift(Up3d(x_{s+1}), t_s, depth features))                         (B, V_s, D_s, H_s, W_s)
      logits  = pointwise(x_0) + SurfaceFusion(depth head, surface head)                 (B, C, D, H, W)
    [refine: RefineLevel doubles the grid from the full image, the network above reading it 2x2-pooled]
    [camera_inputs: each Lift also reads CameraConditioning's per-cell geometry of the camera (B, 5, D_s, H_s, W_s)]

The 2D-to-3D skips copy the image features of each resolution into every depth slice (Z-GAN's skip). A copy
says nothing about *where along the column* something is, and a wall one or two cells thick must land in exactly
the right slice; so the image side also predicts each column's first-surface depth as a distribution over the D
slices (supervised with the ground truth's first occupied cell, as in categorical depth networks), and each
level's skip carries that distribution and its running sum (0 in front of the surface, 1 behind) pooled to the
level's resolution. :class:`~.blocks.SurfaceFusion` lets the heads speak in the output directly: it adds to every
cell's logits a learnt mix of the log-probabilities that the column's surface lies behind, in front of or in this
cell with each class.

This module is the network alone. Its settings are checked by :class:`~.ssz.SSZConfig`, which builds it; what is
applied to its logits at inference (mirror averaging, thresholds, column filling) is :mod:`fruxel.train.rules`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint

from fruxel.grid import FruxelGrid

from .blocks import Down2d, InvertedResidual2d, InvertedResidual3d, Lift, Pointwise3d, SurfaceFusion, Up3d, act2d
from .conditioning import CAMERA_CHANNELS, CameraConditioning, CameraInput
from .registry import ModelOutput

IMAGE_MEAN = (0.485, 0.456, 0.406)
"""Per-channel mean subtracted inside the model (inputs are RGB in [0, 1], conventions section 8)."""
IMAGE_STD = (0.229, 0.224, 0.225)
"""Per-channel standard deviation divided inside the model."""


class SSZGenerator(nn.Module):
    """Image -> fruxel logits (see the module docstring); built by :meth:`fruxel.train.models.ssz.SSZConfig.build`,
    whose fields these arguments are (documented there).

    Args:
        classes: C, number of classes including empty.
        grid_shape: ``(D, H, W)`` of the output.
        image_scale, levels, stem, detail_branch, encoder, encoder_blocks, encoder_expand, topdown, decoder,
            decoder_blocks, expand, refine, camera_inputs: the architecture (:class:`~.ssz.SSZConfig`).
        grid: the output grid (its frustum places the cells for ``camera_inputs``; required with it).
        checkpointing: recompute the 3D decoder's blocks in the backward pass instead of storing their
            activations (less memory, more decoder time).
    """

    def __init__(self, *, classes: int, grid_shape: tuple[int, int, int], image_scale: int, levels: int,
                 stem: int, detail_branch: int, encoder: tuple[int, ...], encoder_blocks: tuple[int, ...],
                 encoder_expand: int, topdown: tuple[int, ...], decoder: tuple[int, ...],
                 decoder_blocks: tuple[int, ...], expand: int, refine: int, camera_inputs: bool = False,
                 grid: FruxelGrid | None = None, checkpointing: bool = False) -> None:
        super().__init__()
        scale = 2 if refine else 1
        self.grid_shape = tuple(grid_shape)
        """``(D, H, W)`` of the output."""
        self.base_shape = tuple(n // scale for n in grid_shape)
        """``(D, H, W)`` of the network below the refinement level (``grid_shape``, halved with ``refine``)."""
        self.image_scale = image_scale
        self.levels = levels
        self.checkpointing = checkpointing
        self.register_buffer("mean", torch.tensor(IMAGE_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGE_STD).view(1, 3, 1, 1), persistent=False)
        self._build_image_side(classes, image_scale, levels, stem, detail_branch, encoder, encoder_blocks,
                               encoder_expand, topdown)
        self.conditioning: CameraConditioning | None = None
        if camera_inputs:
            if grid is None:
                raise ValueError("camera_inputs needs the grid")
            d, h, w = self.base_shape
            self.conditioning = CameraConditioning(
                FruxelGrid(width=w, height=h, depth=d, z_near=grid.z_near, z_far=grid.z_far, hfov=grid.hfov), levels)
        self._build_decoder(classes, levels, topdown, decoder, decoder_blocks, expand)
        self.refine: RefineLevel | None = None
        if refine:
            halvings = image_scale + (1 if detail_branch else 0)
            self.refine = RefineLevel(classes=classes, slices=self.grid_shape[0], channels=refine,
                                      decoder=decoder[0], topdown=topdown[0], halvings=halvings, expand=expand,
                                      encoder_expand=encoder_expand)

    def _build_image_side(self, classes: int, image_scale: int, levels: int, stem: int, detail_branch: int,
                          encoder: tuple[int, ...], encoder_blocks: tuple[int, ...], encoder_expand: int,
                          topdown: tuple[int, ...]) -> None:
        """The stem, the detail branch, the encoder, the top-down path and the column heads."""
        # Stem: image resolution down to the grid's (k halvings); with k = 0 a stride-1 convolution.
        self.stem = nn.Sequential(nn.Conv2d(3, stem, 3, stride=2 if image_scale else 1, padding=1, bias=False),
                                  nn.BatchNorm2d(stem), act2d())
        # The detail branch reads an image twice as large as the stem's, where a column is 4 pixels wide instead of
        # 2: its centre ray then passes between two pixels' centres that lie a quarter of a column apart, so a leg or
        # a board's edge holding the cell centres or not shows in the image. Two stride-2 convolutions bring it to
        # the stem's output resolution; its last BatchNorm starts at zero, so that weights trained without it
        # (``run.init``) start as the model they were on the pooled image.
        self.detail_branch: nn.Module | None = None
        if detail_branch:
            last = nn.BatchNorm2d(stem)
            nn.init.zeros_(last.weight)
            self.detail_branch = nn.Sequential(
                nn.Conv2d(3, detail_branch, 3, stride=2, padding=1, bias=False), nn.BatchNorm2d(detail_branch),
                act2d(), InvertedResidual2d(detail_branch, encoder_expand),
                nn.Conv2d(detail_branch, stem, 3, stride=2 if image_scale else 1, padding=1, bias=False), last)
        self.stem_down = nn.Sequential(*[Down2d(stem, stem) for _ in range(max(image_scale - 1, 0))])
        enc = []
        cin = stem
        for s in range(levels):
            layers: list[nn.Module] = [Down2d(cin, encoder[s])] if s else [
                nn.Conv2d(cin, encoder[s], 1, bias=False), nn.BatchNorm2d(encoder[s]), act2d()]
            layers += [InvertedResidual2d(encoder[s], encoder_expand) for _ in range(encoder_blocks[s])]
            enc.append(nn.Sequential(*layers))
            cin = encoder[s]
        self.encoder = nn.ModuleList(enc)
        self.context = nn.Sequential(nn.Conv2d(encoder[-1], encoder[-1], 1), act2d())
        self.lateral = nn.ModuleList(nn.Conv2d(encoder[s], topdown[s], 1, bias=False) for s in range(levels))
        self.topdown_up = nn.ModuleList(nn.Conv2d(topdown[s + 1], topdown[s], 1, bias=False)
                                        for s in range(levels - 1))
        self.topdown = nn.ModuleList(
            nn.Sequential(nn.BatchNorm2d(topdown[s]), act2d(), InvertedResidual2d(topdown[s], encoder_expand))
            for s in range(levels))
        self.depth_head = nn.Conv2d(topdown[0], self.base_shape[0] + 1, 1)
        self.surface_head = nn.Conv2d(topdown[0], classes, 1)

    def _build_decoder(self, classes: int, levels: int, topdown: tuple[int, ...], decoder: tuple[int, ...],
                       decoder_blocks: tuple[int, ...], expand: int) -> None:
        """The 3D decoder, its lifts and up-convolutions, the output head and the surface fusion."""
        db = self.base_shape[0] // 2 ** (levels - 1)
        self.bottom_lift = nn.Conv2d(topdown[-1], decoder[-1] * db, 1)
        cam = CAMERA_CHANNELS if self.conditioning is not None else 0
        self.lifts = nn.ModuleList(Lift(decoder[s], topdown[s], decoder[s], cam) for s in range(levels))
        self.ups = nn.ModuleList(Up3d(decoder[s + 1], decoder[s]) for s in range(levels - 1))
        # The finest level's blocks work per cell: its neighbourhood comes from the up-convolution into it.
        self.blocks = nn.ModuleList(
            nn.Sequential(*[InvertedResidual3d(decoder[s], expand, spatial=s > 0) for _ in range(decoder_blocks[s])])
            for s in range(levels))
        self.head = Pointwise3d(decoder[0], classes)
        self.fusion = SurfaceFusion(classes)

    # ------------------------------------------------------------------ parts
    def encode(self, image: torch.Tensor) -> list[torch.Tensor]:
        """Top-down image features ``t_s``, ``(B, T_s, H / 2^s, W / 2^s)`` for s = 0 .. L-1 (``H, W`` of
        ``base_shape``; with ``refine`` the image is the 2 x 2-pooled one)."""
        self._check_image(image, self.base_shape)
        x = (image - self.mean.to(image.dtype)) / self.std.to(image.dtype)
        fine = None
        if self.detail_branch is not None:
            fine, x = x, F.avg_pool2d(x, 2)
        s0 = self.stem(x)
        if fine is not None:
            s0 = s0 + self.detail_branch(fine)
        x = self.stem_down(s0)
        feats = []
        for s, stage in enumerate(self.encoder):
            x = stage(x)
            if s == self.levels - 1:
                x = x + self.context(x.mean(dim=(2, 3), keepdim=True))
            feats.append(x)
        t = self.lateral[-1](feats[-1])
        out = [self.topdown[-1](t)]
        for s in range(self.levels - 2, -1, -1):
            up = F.interpolate(self.topdown_up[s](out[0]), scale_factor=2.0, mode="nearest")
            out.insert(0, self.topdown[s](up + self.lateral[s](feats[s])))
        return out

    @property
    def image_size(self) -> tuple[int, int]:
        """``(height, width)`` of the image :meth:`forward` takes."""
        k = self.image_scale + (1 if self.detail_branch is not None else 0) + (1 if self.refine is not None else 0)
        _, h, w = self.base_shape
        return h << k, w << k

    def _check_image(self, image: torch.Tensor, shape: tuple[int, int, int]) -> None:
        """Raise ValueError unless ``image`` is ``(B, 3, H * 2^k, W * 2^k)`` for the grid ``shape`` ``(D, H, W)``
        (``k`` = ``image_scale``, plus one with the detail branch)."""
        _, h, w = shape
        k = self.image_scale + (1 if self.detail_branch is not None else 0)
        if image.ndim != 4 or image.shape[1] != 3 or image.shape[2] != h << k or image.shape[3] != w << k:
            raise ValueError(f"image must be (B, 3, {h << k}, {w << k}), got {tuple(image.shape)}")

    @staticmethod
    def depth_features(depth_logits: torch.Tensor, levels: int) -> list[torch.Tensor]:
        """Per level, ``(B, 2, D_s, H_s, W_s)`` float32: the first-surface probability of each cell and its
        running sum along depth (see :class:`~.blocks.Lift`).

        Args:
            depth_logits: ``(B, D + 1, H, W)``; the last bin (no surface) is dropped after the softmax.
            levels: number of levels.
        """
        p = torch.softmax(depth_logits.float(), dim=1)[:, :-1].unsqueeze(1)  # (B, 1, D, H, W)
        out = []
        for s in range(levels):
            ps = F.avg_pool3d(p, 2**s) * (2**s) if s else p
            out.append(torch.cat([ps, torch.cumsum(ps, dim=2).clamp_(max=1.0)], dim=1))
        return out

    def _run(self, module: nn.Module, *args: torch.Tensor) -> torch.Tensor:
        if self.checkpointing and self.training and torch.is_grad_enabled():
            return checkpoint(module, *args, use_reentrant=False)
        return module(*args)

    def _lift(self, level: int, x: torch.Tensor, t: torch.Tensor, depth: torch.Tensor, shape: tuple[int, int, int],
              camera: CameraInput | None) -> torch.Tensor:
        """Decoder level ``level``'s 2D-to-3D merge (:class:`~.blocks.Lift`) of the volume ``x`` with the level's
        image features ``t`` ``(B, T_s, H_s, W_s)``, depth features and, with ``camera_inputs``, the camera's
        per-cell geometry: ``(B, V_s, D_s, H_s, W_s)``. The seam an architecture derived from this one extends
        (``experiments/footprint_lift.py``)."""
        cond = self.conditioning
        return self.lifts[level](x, t, depth, shape, cond(camera, level) if cond is not None else None)

    # ------------------------------------------------------------------ forward
    def forward(self, image: torch.Tensor, camera: CameraInput | None = None) -> ModelOutput:
        """Predict a batch: the network alone (inference rules are :mod:`fruxel.train.rules`).

        Args:
            image: ``(B, 3, h, w)`` float RGB in [0, 1] (the grid's own camera, :attr:`image_size`).
            camera: what is known of each sample's camera, for a network built with ``camera_inputs`` (None:
                nothing known); a network without it ignores the argument.

        Returns:
            :class:`~.registry.ModelOutput` with all three heads.
        """
        if self.conditioning is not None and camera is None:
            camera = CameraInput.unknown(image.shape[0], image.device)
        if self.refine is None:
            logits, depth_logits, surface_logits = self._predict_base(image, camera)[:3]
            return ModelOutput(logits=logits, depth_logits=depth_logits, surface_logits=surface_logits)
        # The level reads the image twice as large as the network below.
        self._check_image(image, tuple(2 * n for n in self.base_shape))
        # The network below reads the image as it was trained to: averaged over 2 x 2 pixels.
        logits, depth_logits, surface_logits, x0, t0 = self._predict_base(F.avg_pool2d(image, 2), camera)
        normalised = (image - self.mean.to(image.dtype)) / self.std.to(image.dtype)
        logits, depth_logits, surface_logits = self.refine(normalised, logits, depth_logits, surface_logits, x0, t0,
                                                           run=self._run)
        return ModelOutput(logits=logits, depth_logits=depth_logits, surface_logits=surface_logits)

    def _predict_base(self, image: torch.Tensor, camera: CameraInput | None) -> tuple[torch.Tensor, ...]:
        """The network at ``base_shape``: ``(logits, depth_logits, surface_logits)``, then the finest decoder volume
        ``(B, V_0, D, H, W)`` and the finest top-down image features ``(B, T_0, H, W)`` (read by the refinement
        level). ``camera`` is read only with ``camera_inputs``."""
        t = self.encode(image)
        d, h, w = self.base_shape
        depth_logits = self.depth_head(t[0]).float()
        surface_logits = self.surface_head(t[0]).float()
        depth = self.depth_features(depth_logits, self.levels)
        shapes = [(d >> s, h >> s, w >> s) for s in range(self.levels)]
        b = image.shape[0]
        bottom = self.bottom_lift(t[-1])
        ds, hs, ws = shapes[-1]
        x = bottom.reshape(b, -1, ds, hs, ws)
        if self.conditioning is not None and camera is not None:
            camera = camera.to(image.device)
        x = self._lift(self.levels - 1, x, t[-1], depth[-1], shapes[-1], camera)
        x = self._run(self.blocks[-1], x)
        for s in range(self.levels - 2, -1, -1):
            x = self.ups[s](x)
            x = self._lift(s, x, t[s], depth[s], shapes[s], camera)
            x = self._run(self.blocks[s], x)
        logits = self.head(x)
        logits = logits + self.fusion(depth_logits, surface_logits).to(logits.dtype)
        return logits, depth_logits, surface_logits, x, t[0]


def split_depth_logits(depth_logits: torch.Tensor) -> torch.Tensor:
    """A column depth distribution on the grid refined twofold in every axis: each slice's probability shared
    equally by its two halves, "no surface" kept, each column repeated over its 2 x 2 sub-columns.

    Args:
        depth_logits: ``(B, D + 1, H, W)`` float logits (bin D = no surface).

    Returns:
        ``(B, 2 D + 1, 2 H, 2 W)`` float32 log-probabilities.
    """
    log_p = torch.log_softmax(depth_logits.float(), dim=1)
    halves = (log_p[:, :-1] - math.log(2.0)).repeat_interleave(2, dim=1)
    out = torch.cat([halves, log_p[:, -1:]], dim=1)
    return F.interpolate(out, scale_factor=2.0, mode="nearest")


class RefineLevel(nn.Module):
    """A decoder level that doubles a trained network's output grid in every axis (``SSZConfig.refine``).

    The network below predicts the grid halved from the image averaged over 2 x 2 pixels; this level reads the
    full image through a branch of its own (stride-2 convolutions down to the fine grid's columns), joins it with
    the network's finest top-down features repeated 2 x 2, and predicts from that:

    * the column depth distribution on the fine grid (2 D + 1 bins): the coarse one with each slice split in two
      (:func:`split_depth_logits`) plus a correction;
    * the columns' surface class: the coarse one repeated 2 x 2 plus a correction;
    * the logits: the coarse ones repeated 2 x 2 x 2 plus a correction from a volume that is the coarse decoder's
      finest volume, up-convolved (:class:`~.blocks.Up3d`), merged with the image features and the fine depth
      distribution (:class:`~.blocks.Lift`) and passed through a per-cell inverted residual block.

    Every correction starts at zero, so a fresh level repeats the coarse model's answer on the fine cells: a model
    trained at the coarse grid (``run.init``) starts as itself.

    Args:
        classes: C.
        slices: D, the fine grid's depth (the depth head gives D + 1 bins).
        channels: the level's width (image branch, volume).
        decoder: V_0, channels of the coarse decoder's finest volume.
        topdown: T_0, channels of the coarse network's finest top-down features.
        halvings: how many times the full image is halved to the fine grid's width (k of ``image_scale``, plus
            one with the detail branch).
        expand: expansion of the inverted residual blocks (3D).
        encoder_expand: expansion of the inverted residual blocks (2D).
    """

    def __init__(self, *, classes: int, slices: int, channels: int, decoder: int, topdown: int, halvings: int,
                 expand: int, encoder_expand: int) -> None:
        super().__init__()
        r = channels
        self.branch = nn.Sequential(
            nn.Conv2d(3, r, 3, stride=2 if halvings else 1, padding=1, bias=False), nn.BatchNorm2d(r), act2d(),
            InvertedResidual2d(r, encoder_expand), *[Down2d(r, r) for _ in range(max(halvings - 1, 0))])
        self.from_coarse = nn.Conv2d(topdown, r, 1, bias=False)
        self.mix = nn.Sequential(nn.BatchNorm2d(r), act2d(), InvertedResidual2d(r, encoder_expand))
        self.depth_head = nn.Conv2d(r, slices + 1, 1)
        self.surface_head = nn.Conv2d(r, classes, 1)
        self.up = Up3d(decoder, r)
        self.lift = Lift(r, r, r)
        self.block = InvertedResidual3d(r, expand, spatial=False)
        self.head = Pointwise3d(r, classes)
        for m in (self.depth_head, self.surface_head, self.head):
            nn.init.zeros_(m.weight)
            nn.init.zeros_(m.bias)

    def forward(self, image: torch.Tensor, logits: torch.Tensor, depth_logits: torch.Tensor,
                surface_logits: torch.Tensor, x0: torch.Tensor, t0: torch.Tensor, *,
                run: Callable[..., torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Refine one batch (fine grid ``(D, H, W)``, coarse grid ``(D/2, H/2, W/2)``).

        Args:
            image: ``(B, 3, h, w)`` the full image, normalised as the model normalises it.
            logits: ``(B, C, D/2, H/2, W/2)`` the coarse logits.
            depth_logits: ``(B, D/2 + 1, H/2, W/2)`` the coarse column depth logits.
            surface_logits: ``(B, C, H/2, W/2)`` the coarse surface class logits.
            x0: ``(B, V_0, D/2, H/2, W/2)`` the coarse decoder's finest volume.
            t0: ``(B, T_0, H/2, W/2)`` the coarse network's finest top-down features.
            run: how to call the 3D block (the generator's activation checkpointing).

        Returns:
            ``(logits (B, C, D, H, W), depth_logits (B, D + 1, H, W) float32, surface_logits (B, C, H, W)
            float32)``.
        """
        def fine(x: torch.Tensor) -> torch.Tensor:
            """Each coarse cell or column repeated on the fine grid (2 per axis)."""
            return F.interpolate(x, scale_factor=2.0, mode="nearest")

        f = self.mix(self.branch(image) + fine(self.from_coarse(t0)))
        depth_logits = split_depth_logits(depth_logits) + self.depth_head(f).float()
        surface_logits = fine(surface_logits.float()) + self.surface_head(f).float()
        (depth,) = SSZGenerator.depth_features(depth_logits, 1)
        x = self.lift(self.up(x0), f, depth, tuple(2 * n for n in x0.shape[2:]))
        x = run(self.block, x) if run is not None else self.block(x)
        coarse = fine(logits)
        out = coarse + self.head(x).to(coarse.dtype)
        return out, depth_logits, surface_logits

"""The SSZ generator: one RGB image of the grid's own camera -> logits of a fruxel model (SPEC section 8).

Architecture (``L`` = ``config.levels``; level ``s`` has the grid's resolution divided by ``2^s``)::

    image (B, 3, h, w), w = W * 2^k
      | normalise; stem: 3x3 stride-2 conv, then k-1 depthwise/pointwise halvings        (2D, to H x W)
      |   [+ image_branch at w; with detail_branch the image is twice as large, the stem reads it 2x2-pooled and
      |    the branch the image itself]
      | encoder level s = 0 .. L-1: [halving], inverted residual blocks -> e_s          (B, E_s, H_s, W_s)
      | global context: mean over the image, pointwise, added to e_{L-1}
      | top-down path: t_{L-1} = e_{L-1}; t_s = block(up(t_{s+1}) + lateral(e_s))      (B, T_s, H_s, W_s)
      | heads on t_0: column depth distribution (D + 1 bins, the last = no surface) and surface class (C)
      v
    3D decoder, bottom up:
      x_{L-1} = Lift(learned depth lift of t_{L-1}, t_{L-1}, depth features)             (B, V_{L-1}, D_s, H_s, W_s)
      x_s     = blocks(Lift(Up3d(x_{s+1}), t_s, depth features))                         (B, V_s, D_s, H_s, W_s)
      logits  = pointwise(x_0) [+ SurfaceFusion(depth head, surface head)]                (B, C, D, H, W)

The 2D-to-3D skips copy the image features of each resolution into every depth slice (Z-GAN's skip). A copy
says nothing about *where along the column* something is, and a wall one or two cells thick must land in exactly
the right slice; so the image side also predicts each column's first-surface depth as a distribution over the D
slices (supervised with the ground truth's first occupied cell, as in categorical depth networks), and each
level's skip carries that distribution and its running sum (0 in front of the surface, 1 behind) pooled to the
level's resolution. ``lift="copy"`` turns this off (the plain Z-GAN skip) for comparison.

``empty_offset`` and ``fill_columns`` are inference rules on top, in eval mode only. The first shifts every
cell's empty logit (a decision threshold chosen after training); with the second (:func:`fill_columns`) a column
that the volume leaves empty but whose depth head says it has a surface gets one surface cell, where the volume
finds a surface most likely.

``flip_average``, also eval mode only and before those, predicts the image and its mirror image and averages the
two answers, the mirror's mirrored back along W (the grid's own camera is centred, SPEC section 1); ``first_hit_label``
(:func:`first_hit_label`) comes after them.

With ``surface_fusion`` the heads also speak in the output directly: :class:`~.blocks.SurfaceFusion` adds to
every cell's logits a learnt mix of the log-probabilities that the column's surface lies behind, in front of or
in this cell with each class; the own view's first hit is then the heads' answer wherever the decoder is unsure.

Shapes: ``D, H, W`` must be divisible by ``2^(L-1)``; the image must be ``(H * 2^k, W * 2^k)`` with ``k >= 0``
(``k + 1`` with ``detail_branch``).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
import torch.nn.functional as F
from torch import nn
from torch.utils.checkpoint import checkpoint

from ..config import ModelConfig
from .blocks import Down2d, InvertedResidual2d, InvertedResidual3d, Lift, Pointwise3d, SurfaceFusion, Up3d, act2d

IMAGE_MEAN = (0.485, 0.456, 0.406)
"""Per-channel mean subtracted inside the model (inputs are RGB in [0, 1], SPEC section 8)."""
IMAGE_STD = (0.229, 0.224, 0.225)
"""Per-channel standard deviation divided inside the model."""
FILL_SURFACE_PROBABILITY: float = ModelConfig.fill_threshold
"""The default ``threshold`` of :func:`fill_columns`: ``ModelConfig.fill_threshold``'s default."""


@dataclass
class SSZOutput:
    """What :meth:`SSZGenerator.forward` returns."""

    logits: torch.Tensor
    """``(B, C, D, H, W)`` class logits of every cell, channel 0 = empty, in the autocast dtype."""
    depth_logits: torch.Tensor | None
    """``(B, D + 1, H, W)`` float32 logits of each column's first-surface slice (bin D = no surface); None with
    ``lift="copy"``."""
    surface_logits: torch.Tensor
    """``(B, C, H, W)`` float32 logits of each column's first-surface class (0 = no surface)."""
    fine_logits: torch.Tensor | None = None
    """``(B, D * R + 1, H, W)`` float32 logits of each column's first-surface depth in sub-slice bins (``R`` =
    ``fine_depth`` bins per slice, bin ``k * R + r`` is the r-th of slice k; the last = no surface), or None
    without ``fine_depth``."""


class SSZGenerator(nn.Module):
    """Image -> fruxel logits (see the module docstring).

    Args:
        classes: C, number of classes including empty.
        grid_shape: ``(D, H, W)`` of the output.
        image_scale: k: the image is ``2^k`` times the grid's width and height.
        levels: L, resolution levels of the encoder and decoder (the coarsest is the grid over ``2^(L-1)``).
        stem: channels of the stem.
        image_branch: channels of the full-resolution image branch added to the stem's output (0 = none; needs
            ``image_scale >= 1``).
        detail_branch: channels of a branch that reads an image twice as large (``2^(k+1)`` times the grid) while
            the stem reads it averaged over 2 x 2 pixels; its result is added to the stem's output (0 = none).
        encoder: E_s, channels of encoder level s (length L).
        encoder_blocks: inverted residual blocks per encoder level (length L).
        topdown: T_s, channels of the top-down path at level s (length L).
        decoder: V_s, channels of decoder level s (length L).
        decoder_blocks: volumetric inverted residual blocks per decoder level (length L).
        expand: expansion factor of the 3D decoder's inverted residual blocks.
        encoder_expand: expansion factor of the 2D inverted residual blocks.
        lift: ``"depth"`` (skips with the column depth distribution) or ``"copy"`` (the plain Z-GAN skip).
        upsample: :class:`~.blocks.Up3d` mode.
        group_width: channels per group of the decoder's 3x3x3 convolutions (1 = depthwise).
        full_res_spatial: give the finest level's blocks a 3x3x3 convolution too (by default they are per-cell:
            the neighbourhood comes from the up-convolution into that level).
        surface_fusion: add :class:`~.blocks.SurfaceFusion`'s term to the logits (needs ``lift="depth"``).
        fill_columns: in eval mode, pass the logits through :func:`fill_columns` (needs ``lift="depth"``).
        empty_offset: in eval mode, add this to the empty class's logits (before ``fill_columns``).
        fill_threshold: :func:`fill_columns`' ``threshold``, in (0, 1].
        first_hit_label: in eval mode, then :func:`first_hit_label`.
        flip_average: in eval mode, average the network's outputs on the image and on its mirror image (mirrored
            back) before the rules.
        fine_depth: R, sub-slice bins of the fine depth head (0 = none; needs ``lift="depth"``).
        refine: channels of a refinement level that doubles the output grid (0 = none; see
            :class:`RefineLevel`): everything above is then built for ``grid_shape`` halved and reads the image
            averaged over 2 x 2 pixels.
        refine_scale: with ``refine``, 2 (the level doubles the grid, as above) or 1 (the level keeps
            ``grid_shape`` and reads an image twice as large as the network above it, which reads it averaged over
            2 x 2 pixels).
        refine_frozen: with ``refine``, train only the refinement level: the rest is frozen (no gradient, its
            BatchNorm statistics kept in eval mode).
        checkpointing: recompute the 3D decoder's blocks in the backward pass instead of storing their
            activations (less memory, about a third more decoder time).
    """

    def __init__(self, *, classes: int, grid_shape: tuple[int, int, int], image_scale: int, levels: int,
                 stem: int, image_branch: int = 0, detail_branch: int = 0, encoder: tuple[int, ...],
                 encoder_blocks: tuple[int, ...], topdown: tuple[int, ...],
                 decoder: tuple[int, ...], decoder_blocks: tuple[int, ...], expand: int, encoder_expand: int = 4,
                 lift: str = "depth",
                 upsample: str = "parity", group_width: int = 1, full_res_spatial: bool = False,
                 surface_fusion: bool = False, fill_columns: bool = False, empty_offset: float = 0.0,
                 fill_threshold: float = FILL_SURFACE_PROBABILITY, first_hit_label: bool = False,
                 flip_average: bool = False, fine_depth: int = 0, refine: int = 0, refine_scale: int = 2,
                 refine_frozen: bool = False, checkpointing: bool = False) -> None:
        super().__init__()
        for name, seq in (("encoder", encoder), ("encoder_blocks", encoder_blocks), ("topdown", topdown),
                          ("decoder", decoder), ("decoder_blocks", decoder_blocks)):
            if len(seq) != levels:
                raise ValueError(f"{name} needs one entry per level ({levels}), got {len(seq)}")
        if lift not in ("depth", "copy"):
            raise ValueError(f"lift must be 'depth' or 'copy', got {lift!r}")
        for name, on in (("surface_fusion", surface_fusion), ("fill_columns", fill_columns),
                         ("fine_depth", fine_depth), ("refine", refine)):
            if on and lift != "depth":
                raise ValueError(f"{name} needs lift='depth' (the column depth head)")
        if not 0.0 < fill_threshold <= 1.0:
            raise ValueError(f"fill_threshold must be in (0, 1], got {fill_threshold}")
        if refine < 0:
            raise ValueError(f"refine must be >= 0, got {refine}")
        if refine_scale not in (1, 2):
            raise ValueError(f"refine_scale must be 1 or 2, got {refine_scale}")
        if refine and fine_depth:
            raise ValueError("refine and fine_depth cannot be combined (the fine head speaks for the coarse grid)")
        d, h, w = grid_shape
        f = 2 ** (levels - 1)
        scale = refine_scale if refine else 1
        g = f * scale
        if d % g or h % g or w % g:
            raise ValueError(f"grid {w}x{h}x{d} (WxHxD) must be divisible by {g} in every axis (2^(levels-1)"
                             + (", times 2 for refine)" if scale == 2 else ")"))
        self.grid_shape = (d, h, w)
        d, h, w = d // scale, h // scale, w // scale
        self.base_shape = (d, h, w)
        """``(D, H, W)`` of the network below the refinement level (``grid_shape``, halved with ``refine`` at
        ``refine_scale`` 2)."""
        self.classes = classes
        self.image_scale = image_scale
        self.levels = levels
        self.lift = lift
        self.checkpointing = checkpointing
        self.fill_columns = fill_columns
        self.empty_offset = float(empty_offset)
        self.fill_threshold = float(fill_threshold)
        self.first_hit_label = bool(first_hit_label)
        self.flip_average = bool(flip_average)
        self.register_buffer("mean", torch.tensor(IMAGE_MEAN).view(1, 3, 1, 1), persistent=False)
        self.register_buffer("std", torch.tensor(IMAGE_STD).view(1, 3, 1, 1), persistent=False)

        # Stem: image resolution down to the grid's (k halvings); with k = 0 a stride-1 convolution.
        self.stem = nn.Sequential(nn.Conv2d(3, stem, 3, stride=2 if image_scale else 1, padding=1, bias=False),
                                  nn.BatchNorm2d(stem), act2d())
        # The stem halves the image's resolution in its first layer, a strided 3x3 convolution. The branch works at
        # the image's own resolution first, for what is finer than a column: the edges of boards one or two pixels wide
        # and label boundaries inside a column. Its last BatchNorm starts at zero, so that weights trained without
        # it (``run.init``) start as the model they were.
        self.image_branch: nn.Module | None = None
        if image_branch:
            if not image_scale:
                raise ValueError("image_branch needs image_scale >= 1 (an image larger than the grid)")
            last = nn.BatchNorm2d(stem)
            nn.init.zeros_(last.weight)
            self.image_branch = nn.Sequential(
                nn.Conv2d(3, image_branch, 3, padding=1, bias=False), nn.BatchNorm2d(image_branch), act2d(),
                InvertedResidual2d(image_branch, encoder_expand),
                nn.Conv2d(image_branch, stem, 3, stride=2, padding=1, bias=False), last)
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
        self.depth_head = nn.Conv2d(topdown[0], d + 1, 1) if lift == "depth" else None
        self.surface_head = nn.Conv2d(topdown[0], classes, 1)
        # The fine depth head places each column's first surface within a slice (R bins per slice): a board
        # thinner than a slice holds a cell centre or not depending on that, which the slice distribution above
        # cannot say. Its R per-cell probabilities reach the full-resolution level's Lift, whose term for them starts
        # at zero so that weights trained without it (``run.init``) start as the model they were.
        self.fine_depth = int(fine_depth)
        if self.fine_depth < 0:
            raise ValueError(f"fine_depth must be >= 0, got {fine_depth}")
        self.fine_head = nn.Conv2d(topdown[0], d * self.fine_depth + 1, 1) if self.fine_depth else None

        depth_channels = 2 if lift == "depth" else 0
        db = d // f
        self.bottom_lift = nn.Conv2d(topdown[-1], decoder[-1] * db, 1)
        self.lifts = nn.ModuleList(
            Lift(decoder[s], topdown[s], decoder[s], depth_channels, fine_channels=self.fine_depth if s == 0 else 0)
            for s in range(levels))
        self.ups = nn.ModuleList(Up3d(decoder[s + 1], decoder[s], upsample, group_width) for s in range(levels - 1))
        self.blocks = nn.ModuleList(
            nn.Sequential(*[InvertedResidual3d(decoder[s], expand, group_width, spatial=s > 0 or full_res_spatial)
                            for _ in range(decoder_blocks[s])])
            for s in range(levels))
        self.head = Pointwise3d(decoder[0], classes)
        self.fusion = SurfaceFusion(classes) if surface_fusion else None
        self.refine: RefineLevel | None = None
        self.refine_frozen = bool(refine and refine_frozen)
        if refine:
            k = image_scale + (1 if detail_branch else 0)
            self.refine = RefineLevel(classes=classes, slices=self.grid_shape[0], channels=refine, decoder=decoder[0],
                                      topdown=topdown[0], scale=scale, halvings=k + (1 if scale == 1 else 0),
                                      expand=expand, encoder_expand=encoder_expand,
                                      upsample=upsample, group_width=group_width)
        if self.refine_frozen:
            for name, p in self.named_parameters():
                if not name.startswith("refine."):
                    p.requires_grad_(False)
            # Modules are built in training mode and the trainer never calls train(): the frozen network's modes
            # (eval) are set here, or its BatchNorms would train on the fine-tuning batches.
            self.train(self.training)

    def train(self, mode: bool = True) -> SSZGenerator:
        """As :meth:`nn.Module.train`; with ``refine_frozen`` everything but the refinement level stays in eval
        mode, so that the frozen network's BatchNorm statistics are the ones it was trained with."""
        super().train(mode)
        if self.refine_frozen:
            for name, child in self.named_children():
                if name != "refine":
                    child.eval()
        return self

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
        if self.image_branch is not None:
            s0 = s0 + self.image_branch(x)
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

    @staticmethod
    def fine_features(fine_logits: torch.Tensor, bins: int) -> torch.Tensor:
        """``(B, R, D, H, W)`` float32: the probability that the column's first surface lies in sub-slice bin r of
        each cell (R = ``bins``; summed over r, the slice's share of the column's surface).

        Args:
            fine_logits: ``(B, D * R + 1, H, W)``; the last bin (no surface) is dropped after the softmax.
            bins: R, bins per slice.
        """
        p = torch.softmax(fine_logits.float(), dim=1)[:, :-1]
        b, n, h, w = p.shape
        # Contiguous: the Lift's pointwise product then runs as one batched matrix product (Pointwise3d).
        return p.reshape(b, n // bins, bins, h, w).transpose(1, 2).contiguous()

    def _run(self, module: nn.Module, *args: torch.Tensor) -> torch.Tensor:
        if self.checkpointing and self.training and torch.is_grad_enabled():
            return checkpoint(module, *args, use_reentrant=False)
        return module(*args)

    # ------------------------------------------------------------------ forward
    def forward(self, image: torch.Tensor, *, rules: bool = True) -> SSZOutput:
        """Predict a batch.

        Args:
            image: ``(B, 3, H * 2^k, W * 2^k)`` float RGB in [0, 1] (the grid's own camera, scaled).
            rules: in eval mode, apply the inference rules (:meth:`apply_rules`); False gives the network's logits
                (mirror averaged with ``flip_average``) for a caller that applies them itself.

        Returns:
            :class:`SSZOutput`.
        """
        if not self.training and self.flip_average:
            # The mirror's outputs are mirrored back along W, the last axis of every output, and the logits
            # averaged (SPEC section 1: cx = W / 2, so pixel column x and grid column W - 1 - x mirror each other
            # exactly).
            a, m = self._mirror_passes(image, batched=image.device.type != "cpu")
            logits, depth_logits, surface_logits, fine_logits = (
                None if x is None else (x + y.flip(-1)) * 0.5 for x, y in zip(a, m, strict=True))
        else:
            logits, depth_logits, surface_logits, fine_logits = self._predict(image)
        if not self.training and rules:
            logits = self.apply_rules(logits, depth_logits)
        return SSZOutput(logits=logits, depth_logits=depth_logits, surface_logits=surface_logits,
                         fine_logits=fine_logits)

    def apply_rules(self, logits: torch.Tensor, depth_logits: torch.Tensor | None) -> torch.Tensor:
        """This model's eval-mode inference rules on the network's logits: :func:`inference_rules` with its
        ``empty_offset``, ``fill_columns`` and ``fill_threshold``, then :func:`first_hit_label` if it is on.

        Args:
            logits: ``(B, C, D, H, W)`` class logits before the rules (``forward(image, rules=False)``).
            depth_logits: ``(B, D + 1, H, W)`` column depth logits (needed with ``fill_columns``).

        Returns:
            ``(B, C, D, H, W)`` logits, ``logits``' dtype.
        """
        ruled = inference_rules(logits, depth_logits, empty_offset=self.empty_offset, fill=self.fill_columns,
                                fill_threshold=self.fill_threshold)
        return first_hit_label(ruled, logits) if self.first_hit_label else ruled

    def _mirror_passes(self, image: torch.Tensor, *, batched: bool) -> tuple[tuple, tuple]:
        """:meth:`_predict` of the image and of its mirror image (W reversed): as one batch, or (``batched``
        False) one after the other. On 2 CPU cores, image -> logits with the rules took 3.0 times the plain pass
        as one batch of two (cache-bound) and 2.0 times as two passes (benchmarks/bench_ssz.py --parts rules); on a
        GPU one batch is the cheaper."""
        if not batched:
            return self._predict(image), self._predict(image.flip(-1))
        b = image.shape[0]
        both = self._predict(torch.cat([image, image.flip(-1)]))
        return tuple(x if x is None else x[:b] for x in both), tuple(x if x is None else x[b:] for x in both)

    def _predict(self, image: torch.Tensor
                 ) -> tuple[torch.Tensor, torch.Tensor | None, torch.Tensor, torch.Tensor | None]:
        """The network alone, no inference rule: ``(logits, depth_logits, surface_logits, fine_logits)`` of
        :class:`SSZOutput`."""
        if self.refine is None:
            return self._predict_base(image)[:4]
        # The level reads the image twice as large as the network below (for either scale).
        self._check_image(image, tuple(2 * n for n in self.base_shape))
        with torch.set_grad_enabled(torch.is_grad_enabled() and not self.refine_frozen):
            # The network below reads the image as it was trained to: averaged over 2 x 2 pixels.
            logits, depth_logits, surface_logits, _, x0, t0 = self._predict_base(F.avg_pool2d(image, 2))
        normalised = (image - self.mean.to(image.dtype)) / self.std.to(image.dtype)
        logits, depth_logits, surface_logits = self.refine(normalised, logits, depth_logits, surface_logits, x0, t0,
                                                           run=self._run)
        return logits, depth_logits, surface_logits, None

    def _predict_base(self, image: torch.Tensor) -> tuple[torch.Tensor, ...]:
        """The network at ``base_shape``: :meth:`_predict`'s four outputs, then the finest decoder volume
        ``(B, V_0, D, H, W)`` and the finest top-down image features ``(B, T_0, H, W)`` (read by the refinement
        level)."""
        t = self.encode(image)
        d, h, w = self.base_shape
        depth_logits = self.depth_head(t[0]).float() if self.depth_head is not None else None
        surface_logits = self.surface_head(t[0]).float()
        depth = self.depth_features(depth_logits, self.levels) if depth_logits is not None else [None] * self.levels
        fine_logits = self.fine_head(t[0]).float() if self.fine_head is not None else None
        fine = self.fine_features(fine_logits, self.fine_depth) if fine_logits is not None else None
        shapes = [(d >> s, h >> s, w >> s) for s in range(self.levels)]
        b = image.shape[0]
        bottom = self.bottom_lift(t[-1])
        ds, hs, ws = shapes[-1]
        x = bottom.reshape(b, -1, ds, hs, ws)
        x = self.lifts[-1](x, t[-1], depth[-1], shapes[-1], fine if self.levels == 1 else None)
        x = self._run(self.blocks[-1], x)
        for s in range(self.levels - 2, -1, -1):
            x = self.ups[s](x)
            x = self.lifts[s](x, t[s], depth[s], shapes[s], fine if s == 0 else None)
            x = self._run(self.blocks[s], x)
        logits = self.head(x)
        if self.fusion is not None:
            logits = logits + self.fusion(depth_logits, surface_logits).to(logits.dtype)
        return logits, depth_logits, surface_logits, fine_logits, x, t[0]


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
    """A decoder level that doubles a trained network's output grid in every axis (``ModelConfig.refine``), or
    (``scale`` 1) keeps it and reads the image at twice the resolution the network below reads.

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

    With ``scale`` 1 the fine grid is the coarse one: nothing is repeated or split, the decoder's finest volume
    enters the merge as it is, and the per-cell block gets a 3x3x3 convolution (the neighbourhood that the
    up-convolution gives at scale 2).

    Args:
        classes: C.
        slices: D, the fine grid's depth (the depth head gives D + 1 bins).
        scale: 2 (the grid doubled) or 1 (the grid kept).
        channels: the level's width (image branch, volume).
        decoder: V_0, channels of the coarse decoder's finest volume.
        topdown: T_0, channels of the coarse network's finest image features.
        halvings: how many times the full image is halved to the fine grid's width (k of ``image_scale``, plus
            one with the detail branch, plus one at ``scale`` 1).
        expand: expansion of the inverted residual blocks (3D).
        encoder_expand: expansion of the inverted residual blocks (2D).
        upsample: :class:`~.blocks.Up3d` mode.
        group_width: channels per group of the up-convolution's 3x3x3 convolution.
    """

    def __init__(self, *, classes: int, slices: int, channels: int, decoder: int, topdown: int, halvings: int,
                 expand: int, encoder_expand: int, upsample: str, group_width: int, scale: int = 2) -> None:
        super().__init__()
        if halvings < 0:
            raise ValueError(f"halvings must be >= 0, got {halvings}")
        if scale not in (1, 2):
            raise ValueError(f"scale must be 1 or 2, got {scale}")
        self.scale = scale
        r = channels
        self.branch = nn.Sequential(
            nn.Conv2d(3, r, 3, stride=2 if halvings else 1, padding=1, bias=False), nn.BatchNorm2d(r), act2d(),
            InvertedResidual2d(r, encoder_expand), *[Down2d(r, r) for _ in range(max(halvings - 1, 0))])
        self.from_coarse = nn.Conv2d(topdown, r, 1, bias=False)
        self.mix = nn.Sequential(nn.BatchNorm2d(r), act2d(), InvertedResidual2d(r, encoder_expand))
        self.depth_head = nn.Conv2d(r, slices + 1, 1)
        self.surface_head = nn.Conv2d(r, classes, 1)
        self.up = Up3d(decoder, r, upsample, group_width) if scale == 2 else None
        self.lift = Lift(r if scale == 2 else decoder, r, r, depth_channels=2)
        self.block = InvertedResidual3d(r, expand, group_width, spatial=scale == 1)
        self.head = Pointwise3d(r, classes)
        for m in (self.depth_head, self.surface_head, self.head):
            nn.init.zeros_(m.weight)
            nn.init.zeros_(m.bias)

    def forward(self, image: torch.Tensor, logits: torch.Tensor, depth_logits: torch.Tensor,
                surface_logits: torch.Tensor, x0: torch.Tensor, t0: torch.Tensor, *,
                run: Callable[..., torch.Tensor] | None = None) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
        """Refine one batch (fine grid ``(D, H, W)``, coarse grid ``(D/2, H/2, W/2)``; with ``scale`` 1 both are
        ``(D, H, W)``, read the shapes below with it).

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
            """Each coarse cell or column repeated on the fine grid (2 per axis; the identity at scale 1)."""
            return F.interpolate(x, scale_factor=2.0, mode="nearest") if self.scale == 2 else x

        f = self.mix(self.branch(image) + fine(self.from_coarse(t0)))
        depth_logits = (split_depth_logits(depth_logits) if self.scale == 2 else depth_logits.float()) \
            + self.depth_head(f).float()
        surface_logits = fine(surface_logits.float()) + self.surface_head(f).float()
        (depth,) = SSZGenerator.depth_features(depth_logits, 1)
        x = self.up(x0) if self.up is not None else x0
        x = self.lift(x, f, depth, tuple(x.shape[2:]))
        x = run(self.block, x) if run is not None else self.block(x)
        coarse = fine(logits)
        out = coarse + self.head(x).to(coarse.dtype)
        return out, depth_logits, surface_logits


def first_hit_log_probs(logits: torch.Tensor, empty_offset: float = 0.0) -> torch.Tensor:
    """Each column's distribution of the own view's first hit, from the cells' class distributions taken as
    independent: ``P(first hit = c) = sum_k P(cells 0..k-1 empty) P(cell k = c)`` and ``P(miss) = P(all empty)``.

    This is what the grid's own camera sees of the volume in expectation (a column is a pixel of the own view,
    SPEC section 1), the own-view term of the shell-aware losses without their kernels. The training objective's
    ``first_hit`` term is its cross-entropy against the truth's first label; the ``first_hit_label`` inference rule
    takes its argmax over the occupied classes.

    Args:
        logits: ``(B, C, D, H, W)`` class logits (channel 0 = empty), any float dtype, grid frame.
        empty_offset: added to every cell's empty logit first.

    Returns:
        ``(B, C, H, W)`` float32 log-probabilities: channel 0 the column's miss, channel c its first hit being
        class c; they sum to 1 over the channels.
    """
    s = logits.float()
    if empty_offset:
        s = torch.cat([s[:, :1] + empty_offset, s[:, 1:]], dim=1)
    log_p = torch.log_softmax(s, dim=1)
    empty = log_p[:, 0]  # (B, D, H, W)
    through = torch.cumsum(empty, dim=1)  # log P(cells 0..k empty)
    # log P(cells 0..k-1 empty): the exclusive sum, shifted rather than subtracted (a cell surely occupied would
    # subtract a log of 0).
    before = torch.cat([torch.zeros_like(through[:, :1]), through[:, :-1]], dim=1)
    hit = torch.logsumexp(before.unsqueeze(1) + log_p[:, 1:], dim=2)  # (B, C - 1, H, W)
    return torch.cat([through[:, -1:], hit], dim=1)


def first_hit_classes(raw: torch.Tensor) -> torch.Tensor:
    """Each column's most likely first-hit class among the occupied ones, ``argmax_{c >= 1}`` of
    :func:`first_hit_log_probs` of the raw logits ``(B, C, D, H, W)``: ``(B, H, W)`` int64 in ``[1, C)``."""
    return first_hit_log_probs(raw)[:, 1:].argmax(dim=1) + 1


def first_hit_label(logits: torch.Tensor, raw: torch.Tensor | None, *, best: torch.Tensor | None = None
                    ) -> torch.Tensor:
    """Give each column's first occupied cell the class most likely to be the column's first hit.

    The argmax of each cell alone decides where a column's first occupied cell is and what it holds; the own
    camera sees the first hit of the whole column. A board thinner than a cell, which the truth keeps only where it
    crosses a cell centre, is often spread by the decoder over several cells, none of them more likely occupied
    than empty, so the argmax shows the wall behind it; together those cells can still make furniture the likeliest
    first hit. This rule takes the class ``c >= 1`` that maximises ``P(first hit = c)`` of
    :func:`first_hit_log_probs` on the raw logits (the distribution the ``first_hit`` loss trains) and raises its
    logit in the first occupied cell of ``logits`` just above that cell's best, so that the argmax is that class.
    Only that cell's class can change: the volume's occupancy, the cells behind it and every logit of a cell whose
    class stays are untouched, and empty columns stay empty.

    Args:
        logits: ``(B, C, D, H, W)`` logits after the other rules (:func:`inference_rules`), any float dtype, grid
            frame.
        raw: ``(B, C, D, H, W)`` the network's logits before them (the same or another float dtype); None when
            ``best`` is given.
        best: ``(B, H, W)`` int64, :func:`first_hit_classes` of ``raw`` computed beforehand (a sweep over the other
            rules needs it once).

    Returns:
        ``(B, C, D, H, W)`` logits, ``logits``' dtype.
    """
    # A cell is occupied where its argmax is not empty (a tie goes to empty, as argmax takes the first), as in
    # fill_columns; compared through the best occupied logit because an argmax across the channel axis takes
    # 20 ms at 64^3 on 2 cores, the maximum well under 1 ms.
    occupied = logits[:, 1:].amax(dim=1) > logits[:, 0]  # (B, D, H, W)
    first = occupied.to(torch.uint8).argmax(dim=1, keepdim=True)  # (B, 1, H, W): the first occupied slice (0: none)
    if best is None:
        best = first_hit_classes(raw)
    # Only the first occupied cell of each column is read and written: (B, C, 1, H, W) gathered along depth.
    index = first.unsqueeze(1).expand(-1, logits.shape[1], -1, -1, -1)
    cell = logits.gather(2, index)
    change = occupied.any(dim=1, keepdim=True) & (cell.argmax(dim=1) != best.unsqueeze(1))  # (B, 1, H, W)
    mask = F.one_hot(best, logits.shape[1]).permute(0, 3, 1, 2).unsqueeze(2).bool() & change.unsqueeze(1)
    top = cell.amax(dim=1, keepdim=True)
    # Just above the cell's best, by a margin wider than the dtype's spacing at that size (bfloat16 keeps 8 bits).
    return logits.scatter(2, index, torch.where(mask, top + (1.0 + 0.02 * top.abs()), cell))


def inference_rules(logits: torch.Tensor, depth_logits: torch.Tensor | None, *, empty_offset: float,
                    fill: bool, fill_threshold: float = FILL_SURFACE_PROBABILITY) -> torch.Tensor:
    """The eval-mode rules of ``ModelConfig.empty_offset``, ``fill_columns`` and ``fill_threshold`` applied to a
    batch's logits.

    Args:
        logits: ``(B, C, D, H, W)`` class logits (channel 0 = empty), any float dtype.
        depth_logits: ``(B, D + 1, H, W)`` column depth logits (needed with ``fill``).
        empty_offset: added to every cell's empty logit.
        fill: then :func:`fill_columns`.
        fill_threshold: its ``threshold``.

    Returns:
        ``(B, C, D, H, W)`` logits (``logits`` itself when there is nothing to do).
    """
    if fill:
        return fill_columns(logits, depth_logits, empty_offset, fill_threshold)
    if empty_offset:
        return torch.cat([logits[:, :1] + empty_offset, logits[:, 1:]], dim=1)
    return logits


def fill_columns(logits: torch.Tensor, depth_logits: torch.Tensor, empty_offset: float = 0.0,
                 threshold: float = FILL_SURFACE_PROBABILITY) -> torch.Tensor:
    """Give every column that the depth head believes has a surface at least one occupied cell.

    The argmax of a column's logits can leave it empty everywhere while the column depth head is confident that
    the own camera sees a surface there: typically a plain wall close to the camera, whose distance the decoder
    spreads over many slices so that no single cell is more likely occupied than empty, and the predicted model
    shows a hole (5.6 % of the own-view pixels where the truth has a surface, in the first 256 test samples, for
    the model shipped before this rule existed; docs/model.md). For such a column (no cell with ``argmax != 0``,
    and the depth head's probability of "no surface" below ``threshold``) the cell with the largest
    ``P(occupied) = 1 - P(empty)`` has its empty logit lowered just below its best occupied class's, so that it
    becomes that class's surface; every other logit is returned unchanged. Columns that the volume already
    fills, and columns that the head thinks see nothing, are untouched.

    Args:
        logits: ``(B, C, D, H, W)`` class logits (channel 0 = empty), any float dtype, grid frame.
        depth_logits: ``(B, D + 1, H, W)`` float logits of each column's first-surface slice (bin D = no surface).
        empty_offset: added to every cell's empty logit first (``ModelConfig.empty_offset``; the same as calling
            this on the shifted logits, in one pass).
        threshold: fill a column whose "no surface" probability is below this (``ModelConfig.fill_threshold``,
            in (0, 1]; 1 fills every empty column but those where the head is certain of "no surface").

    Returns:
        ``(B, C, D, H, W)`` logits, ``logits``' dtype.
    """
    empty = logits[:, 0] + empty_offset if empty_offset else logits[:, 0]
    occupied = logits[:, 1:]
    top = occupied.amax(dim=1)  # (B, D, H, W): the best occupied class's logit
    no_surface = torch.softmax(depth_logits.float(), dim=1)[:, -1]  # (B, H, W)
    fill = ~(top > empty).any(dim=1) & (no_surface < threshold)
    # log P(occupied) - log P(empty) rises with P(occupied): one log-sum-exp, over the occupied classes only.
    odds = torch.logsumexp(occupied.float(), dim=1) - empty.float()
    cell = torch.zeros_like(empty, dtype=torch.bool).scatter_(1, odds.argmax(dim=1, keepdim=True), fill.unsqueeze(1))
    # Just below the best class, by a margin wider than the dtype's spacing at that size (bfloat16 keeps 8 bits).
    below = top - (1.0 + 0.02 * top.abs())
    return torch.cat([torch.where(cell, below, empty).unsqueeze(1), occupied], dim=1)

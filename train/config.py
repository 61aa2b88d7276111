"""Typed settings of an SSZ experiment: the model, its losses, the data, the optimiser and the run, with named
presets and a JSON form.

A config file (``fruxel-train --config FILE``) is a JSON object that starts from a preset and overrides any
fields, nested as the dataclasses are::

    {"preset": "ssz64", "optim": {"lr": 0.002}, "run": {"steps": 20000}, "loss": {"shell": false}}

Unknown keys, wrong types and impossible values are refused with one :class:`ConfigError` naming the key. The
full config (:meth:`TrainConfig.to_dict`) is saved beside every checkpoint, so a run can always be reproduced.
"""

from __future__ import annotations

import dataclasses
import json
import math
from collections.abc import Mapping
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fruxel.classes import DEFAULT_CLASSES, ClassTable, ClassTableError
from fruxel.errors import ConfigError
from fruxel.grid import FruxelGrid, GridError

CONFIG_VERSION = 1
"""Version of the config's JSON layout."""


# ---------------------------------------------------------------------------------------------------- model
@dataclass(frozen=True)
class ModelConfig:
    """Architecture of the SSZ generator and discriminator (SPEC section 8; see
    :mod:`fruxel.train.models.generator`). Per-level tuples run from the grid's resolution (level 0) down."""

    grid: FruxelGrid = FruxelGrid(width=64, height=64, depth=64, z_near=0.5, z_far=8.0, hfov=60.0)
    """The output grid: shape ``(D, H, W)`` and the frustum it spans (the image's camera is the grid's own)."""
    classes: ClassTable = DEFAULT_CLASSES
    """Class table of the output; C = ``len(classes.names)``, class 0 = empty."""
    image_scale: int = 1
    """k: the input image is ``2^k`` times the grid's width and height (k = 1: 128^2 images for a 64^3 grid)."""
    levels: int = 5
    """L: resolution levels; every grid axis must be divisible by ``2^(L-1)``."""
    stem: int = 24
    """Channels of the 2D stem (at half the image resolution)."""
    image_branch: int = 0
    """Channels of a branch that works at the image's full resolution before the stem's stride-2 convolution and
    adds its result to the stem's output (0 = none; needs ``image_scale >= 1``). It starts as a zero term, so a
    model fine-tuned (``run.init``) from weights without it starts as that model."""
    detail_branch: int = 0
    """Channels of a branch that reads the image at twice the resolution ``image_scale`` gives (0 = none): the
    input image is then ``2^(k+1)`` times the grid, the stem sees it averaged over 2 x 2 pixels, and the branch
    (two stride-2 convolutions around an inverted residual block) adds what only the finer image holds to the
    stem's output: where a board thinner than a cell lies against the column's centre ray. It starts as a zero
    term, so a model fine-tuned (``run.init``) from weights without it starts as that model on the pooled image."""
    encoder: tuple[int, ...] = (32, 48, 96, 160, 224)
    """Channels of the 2D encoder per level."""
    encoder_blocks: tuple[int, ...] = (2, 2, 3, 3, 2)
    """2D inverted residual blocks per level."""
    encoder_expand: int = 4
    """Expansion factor of the 2D inverted residual blocks (2D work is cheap next to the 3D decoder's)."""
    topdown: tuple[int, ...] = (48, 64, 96, 128, 160)
    """Channels of the 2D top-down path per level (the image features copied into the 3D levels)."""
    decoder: tuple[int, ...] = (16, 24, 32, 48, 64)
    """Channels of the 3D decoder per level."""
    decoder_blocks: tuple[int, ...] = (1, 1, 1, 2, 2)
    """Volumetric inverted residual blocks per level."""
    expand: int = 2
    """Expansion factor of the 3D decoder's inverted residual blocks."""
    lift: str = "depth"
    """2D-to-3D skips: ``"depth"`` (image features copied along depth with each column's predicted surface depth
    distribution) or ``"copy"`` (the plain Z-GAN copy)."""
    upsample: str = "parity"
    """3D up-convolution (:class:`fruxel.train.models.blocks.Up3d`): ``"parity"`` (3x3x3 at the coarse level, then
    a depthwise kernel-2 transposed convolution), ``"resize"`` (nearest x2, then 3x3x3) or ``"transpose"``
    (transposed 4x4x4, stride 2); measured in benchmarks/bench_ssz.py."""
    full_res_spatial: bool = False
    """Give the finest level's blocks a 3x3x3 convolution (by default they work per cell)."""
    group_width: int = 1
    """Channels per group of the decoder's 3x3x3 convolutions: 1 is depthwise (SPEC section 8); wider groups run
    on faster GPU kernels (measured in benchmarks/bench_ssz.py)."""
    surface_fusion: bool = False
    """Add the image-side heads' own-view answer to the logits of every cell
    (:class:`fruxel.train.models.blocks.SurfaceFusion`; needs ``lift = "depth"``). On in every preset; off here
    so that a config or model file written before the field existed reads as the model it describes."""
    fill_columns: bool = False
    """At inference (eval mode), give a column that the volume leaves empty one surface cell when the column depth
    head says it has a surface (:func:`fruxel.train.models.generator.fill_columns`; needs ``lift = "depth"``).
    Training is unchanged; off here for the same reason as ``surface_fusion``."""
    empty_offset: float = 0.0
    """At inference (eval mode), added to every cell's empty logit (channel 0) before ``fill_columns``: a
    decision threshold between empty and occupied chosen after training on training-split samples
    (``scripts/calibrate.py``), since the class-weighted cross-entropy that trains the model down-weights the
    empty class. Training is unchanged."""
    fill_threshold: float = 0.5
    """``fill_columns`` fills a column whose depth head gives "no surface" a probability below this, in (0, 1]
    (1 fills every column the volume leaves empty); chosen with ``empty_offset`` by ``scripts/calibrate.py``."""
    first_hit_label: bool = False
    """At inference (eval mode), after ``empty_offset`` and ``fill_columns``: give each column's first occupied
    cell the class most likely to be the column's first hit
    (:func:`fruxel.train.models.generator.first_hit_label`), which is what the grid's own camera shows of it. Where
    a thin board is spread over several cells, none of them alone more likely occupied than empty, the cells
    together can still make it the likeliest first hit. Training is unchanged; off here for the same reason as
    ``surface_fusion``."""
    flip_average: bool = False
    """At inference (eval mode), before the other rules: predict the image and its mirror image (left and right
    swapped; one batch on a GPU, two passes on the CPU) and average the logits, the mirror's mirrored back
    (test-time augmentation; twice the network's work). The grid's own camera is centred (SPEC section 1), so the
    mirror image is the mirrored room seen through the mirrored grid. Training is unchanged; off here for the same
    reason as ``surface_fusion``."""
    fine_depth: int = 0
    """R: bins per slice of a second column depth head (0 = none; needs ``lift = "depth"``), which places each
    column's first *surface* within a slice, supervised with the simulator's rendered depth
    (``loss.fine_depth``). A board thinner than a slice holds a cell centre, and so stays in the truth, or not
    depending on where within the slice it lies; the per-cell probabilities of its R bins reach the finest
    decoder level. The decoder's term for them starts at zero, so a model fine-tuned (``run.init``) from weights
    without the head starts as that model."""
    refine: int = 0
    """Channels of a refinement level that doubles the output grid in every axis (``refine_scale`` 2) or reads an
    image twice as large for the same grid (``refine_scale`` 1) (0 = none;
    :class:`fruxel.train.models.generator.RefineLevel`). Everything else is then built for ``grid`` (halved at
    scale 2) and reads the image averaged over 2 x 2 pixels, so a model trained at that grid (``run.init``) is the
    network below the level, which starts as a zero correction: a fresh level repeats the coarse model's answer on
    the fine cells. The level reads the full image (``image_size``) through a branch of its own."""
    refine_scale: int = 2
    """With ``refine``: 2, the level doubles the output grid in every axis (the network below works at ``grid``
    halved and reads the image averaged over 2 x 2 pixels); 1, the level keeps ``grid`` and only reads an image
    twice as large as the network below does (that network reads it averaged over 2 x 2 pixels): a sharper look at
    the same cells, whose correction starts at zero too, so a model trained at ``grid`` (``run.init``) starts as
    itself. ``image_size`` counts it."""
    refine_frozen: bool = False
    """With ``refine``: train only the refinement level; the network below keeps its weights and BatchNorm
    statistics (no gradient flows into it, so training is the level's cost alone)."""
    discriminator: tuple[int, ...] = (32, 64, 128)
    """Channels of the 3D PatchGAN's stride-2 layers (used only when ``loss.adversarial`` is on)."""

    @property
    def image_size(self) -> tuple[int, int]:
        """``(height, width)`` of the input image in pixels."""
        k = self.image_scale + (1 if self.detail_branch else 0) + (1 if self.refine and self.refine_scale == 1 else 0)
        return self.grid.height << k, self.grid.width << k

    @property
    def num_classes(self) -> int:
        """C."""
        return len(self.classes.names)

    def check(self, path: str = "model") -> None:
        """Raise :class:`ConfigError` for an impossible architecture."""
        _positive_int(f"{path}.levels", self.levels)
        _positive_int(f"{path}.stem", self.stem)
        _positive_int(f"{path}.expand", self.expand)
        _positive_int(f"{path}.encoder_expand", self.encoder_expand)
        _positive_int(f"{path}.group_width", self.group_width)
        _positive_int(f"{path}.image_branch", self.image_branch, allow_zero=True)
        _positive_int(f"{path}.detail_branch", self.detail_branch, allow_zero=True)
        _positive_int(f"{path}.fine_depth", self.fine_depth, allow_zero=True)
        _positive_int(f"{path}.refine", self.refine, allow_zero=True)
        if self.refine and self.lift != "depth":
            raise ConfigError(f"{path}.refine needs {path}.lift = 'depth', got {self.lift!r}")
        if self.refine and self.fine_depth:
            raise ConfigError(f"{path}.refine and {path}.fine_depth cannot be combined")
        if self.refine_frozen and not self.refine:
            raise ConfigError(f"{path}.refine_frozen needs {path}.refine > 0")
        if self.refine_scale not in (1, 2) or isinstance(self.refine_scale, bool):
            raise ConfigError(f"{path}.refine_scale must be 1 or 2, got {self.refine_scale!r}")
        if self.refine_scale != 2 and not self.refine:
            raise ConfigError(f"{path}.refine_scale needs {path}.refine > 0")
        if self.fine_depth and self.lift != "depth":
            raise ConfigError(f"{path}.fine_depth needs {path}.lift = 'depth', got {self.lift!r}")
        if not 0 <= self.image_scale <= 4 or isinstance(self.image_scale, bool):
            raise ConfigError(f"{path}.image_scale must be an integer in [0, 4], got {self.image_scale!r}")
        if self.detail_branch and self.image_scale > 3:
            raise ConfigError(f"{path}.detail_branch doubles the image: it needs {path}.image_scale <= 3, got "
                              f"{self.image_scale}")
        if self.image_branch and not self.image_scale:
            raise ConfigError(f"{path}.image_branch needs {path}.image_scale >= 1 (an image larger than the grid)")
        for name in ("encoder", "encoder_blocks", "topdown", "decoder", "decoder_blocks"):
            seq = getattr(self, name)
            if len(seq) != self.levels:
                raise ConfigError(f"{path}.{name} needs one entry per level ({self.levels}), got {len(seq)}")
            for v in seq:
                _positive_int(f"{path}.{name}", v, allow_zero=name.endswith("blocks"))
        for v in self.discriminator:
            _positive_int(f"{path}.discriminator", v)
        doubled = bool(self.refine and self.refine_scale == 2)
        f = 2 ** (self.levels - 1 + (1 if doubled else 0))
        g = self.grid
        if g.width % f or g.height % f or g.depth % f:
            why = "2^levels (levels, then refine)" if doubled else "2^(levels-1)"
            raise ConfigError(f"{path}.grid {g.width}x{g.height}x{g.depth} must be divisible by {why} = {f} "
                              "in every axis")
        if self.lift not in ("depth", "copy"):
            raise ConfigError(f"{path}.lift must be 'depth' or 'copy', got {self.lift!r}")
        if self.surface_fusion and self.lift != "depth":
            raise ConfigError(f"{path}.surface_fusion needs {path}.lift = 'depth' (the column depth head)")
        if not math.isfinite(self.empty_offset):
            raise ConfigError(f"{path}.empty_offset must be a finite number, got {self.empty_offset}")
        if not (math.isfinite(self.fill_threshold) and 0.0 < self.fill_threshold <= 1.0):
            raise ConfigError(f"{path}.fill_threshold must be in (0, 1], got {self.fill_threshold}")
        if self.fill_columns and self.lift != "depth":
            raise ConfigError(f"{path}.fill_columns needs {path}.lift = 'depth' (the column depth head)")
        if self.upsample not in ("parity", "resize", "transpose"):
            raise ConfigError(f"{path}.upsample must be 'parity', 'resize' or 'transpose', got {self.upsample!r}")
        w = self.grid.width << self.image_scale
        if not 16 <= w <= 1024:
            raise ConfigError(f"{path}: image width {w} (grid width x 2^image_scale) must be in [16, 1024]")


INFERENCE_RULES = ("flip_average", "empty_offset", "fill_columns", "fill_threshold", "first_hit_label")
"""The :class:`ModelConfig` fields that are SSZ's eval-mode inference rules: attributes of the same names on the
generator, read at every call, so a loaded model's rules can be changed in place."""


# ---------------------------------------------------------------------------------------------------- losses

@dataclass(frozen=True)
class LossConfig:
    """Terms of the generator's objective and their weights; every term is a mean, so weights compare."""

    ce: float = 1.0
    """Weight of the class-weighted per-cell cross-entropy."""
    class_weight_power: float = 0.5
    """Class weights of the cross-entropy are ``frequency^-power`` (normalised to a mean of 1 over the cells),
    frequencies counted on the training split: 0 = unweighted, 1 = inverse frequency. Empty, about 97 % of the
    cells at 64^3, is down-weighted by it."""
    iou: float = 1.0
    """Weight of the soft Jaccard loss ``1 - mean_c soft IoU_c`` over the occupied classes, the metric's own
    form (soft IoU with probabilities), counted over the whole batch."""
    depth: float = 0.5
    """Weight of the cross-entropy of the columns' first-surface depth distribution (``lift = "depth"``) against
    the ground truth's first occupied slice (or "no surface")."""
    surface: float = 0.5
    """Weight of the cross-entropy of the columns' first-surface class against the ground truth's."""
    first_hit: float = 0.0
    """Weight of the own view's first-hit cross-entropy: each column's first-hit distribution over "miss" and the
    classes (:func:`fruxel.train.models.generator.first_hit_log_probs`, the cells taken as independent) against
    the truth's first label, mean over the columns. The own-view term of the shell-aware losses computed on the
    columns directly, without their kernels or novel views; what the ``first_hit_label`` rule decodes."""
    fine_depth: float = 0.5
    """Weight of the cross-entropy of the fine depth head (``model.fine_depth``) against the sub-slice bin of the
    surface that the simulator's renderer sees on each column's centre ray (streamed data only; columns whose ray
    grazes an edge, or whose surface is nearer than ``z_near``, are left out)."""
    shell: bool = False
    """Add the shell-aware losses (:class:`fruxel.train.losses.ShellLoss`: own view and random novel views)."""
    shell_weight: float = 0.5
    """Weight of the shell-aware losses' total."""
    shell_views: int = 2
    """Random novel views per batch for the shell-aware losses."""
    shell_view_size: int = 64
    """Width and height of each novel view, pixels."""
    shell_own_view: float = 0.0
    """Weight, inside the shell-aware losses' total, of their cross-entropy over the grid's own view alone
    (:attr:`fruxel.train.losses.ShellLossConfig.weight_own_view`): the own-view first-hit accuracy's own term.
    At 0 the own view is one camera among ``1 + shell_views`` in the shell cross-entropy."""
    adversarial: bool = False
    """Add the adversarial term (conditional 3D PatchGAN, hinge loss)."""
    adversarial_weight: float = 0.05
    """Final weight of the generator's adversarial term."""
    adversarial_start: int = 1000
    """Step at which the adversarial term starts (the discriminator trains from there too)."""
    adversarial_ramp: int = 1000
    """Steps over which the adversarial weight rises linearly from 0 to its final value."""
    discriminator_lr: float = 2e-4
    """Learning rate of the discriminator (Adam, betas 0.5 / 0.999)."""

    def check(self, path: str = "loss") -> None:
        """Raise :class:`ConfigError` for impossible settings."""
        for name in ("ce", "class_weight_power", "iou", "depth", "surface", "first_hit", "fine_depth", "shell_weight",
                     "shell_own_view", "adversarial_weight", "discriminator_lr"):
            _finite_nonneg(f"{path}.{name}", getattr(self, name))
        for name in ("shell_views", "adversarial_start", "adversarial_ramp"):
            _positive_int(f"{path}.{name}", getattr(self, name), allow_zero=True)
        _positive_int(f"{path}.shell_view_size", self.shell_view_size)


# ---------------------------------------------------------------------------------------------------- data
@dataclass(frozen=True)
class DataConfig:
    """Where training and evaluation samples come from."""

    source: str = "stream"
    """``"stream"``: made on the fly by the simulator (:class:`fruxel.train.sim.StreamingDataset`), or
    ``"shards"``: read from a data set folder written by ``fruxel-sim generate`` (``root``)."""
    root: str = ""
    """The data set folder, for ``source = "shards"`` (its grid and image size must match the model)."""
    seed: int = 0
    """Base seed of the simulator's samples (streaming); the test split's rooms come from seeds the training split
    never uses."""
    train_samples: int = 10_000_000
    """Size of the streamed training split (an index range; samples are made only when drawn)."""
    test_samples: int = 1_000
    """Size of the streamed test split."""
    samples_per_scene: int = 16
    """Samples per simulated room (consecutive frames of one robot trajectory)."""
    augment: bool = True
    """Appearance augmentation of the simulator's images."""
    workers: int = 4
    """DataLoader worker processes (per distributed rank); each makes samples with its own renderer."""
    replay: int = 0
    """Samples kept in a replay buffer on the training device (0 = off): each batch draws from the buffer, which
    new samples from the loader replace oldest first. Lets the model train faster than the simulator makes
    samples."""
    reuse: int = 1
    """With a replay buffer: batches drawn per batch of new samples (each sample is used about this many times)."""
    eval_samples: int = 256
    """Test samples used by the periodic evaluation during training."""
    frequency_samples: int = 256
    """Training samples counted for the cross-entropy's class frequencies."""

    def check(self, path: str = "data") -> None:
        """Raise :class:`ConfigError` for impossible settings."""
        if self.source not in ("stream", "shards"):
            raise ConfigError(f"{path}.source must be 'stream' or 'shards', got {self.source!r}")
        if self.source == "shards" and not self.root:
            raise ConfigError(f"{path}.root must name a data set folder when {path}.source is 'shards'")
        for name in ("seed", "workers", "replay", "eval_samples"):
            _positive_int(f"{path}.{name}", getattr(self, name), allow_zero=True)
        for name in ("train_samples", "test_samples", "samples_per_scene", "reuse", "frequency_samples"):
            _positive_int(f"{path}.{name}", getattr(self, name))


# ---------------------------------------------------------------------------------------------------- optimiser
@dataclass(frozen=True)
class OptimConfig:
    """AdamW with linear warm-up and cosine decay."""

    lr: float = 2e-3
    """Peak learning rate."""
    weight_decay: float = 1e-4
    """AdamW weight decay (not applied to norms and biases)."""
    betas: tuple[float, float] = (0.9, 0.999)
    """AdamW betas."""
    warmup: int = 200
    """Steps of linear warm-up from 0."""
    min_lr: float = 0.02
    """Final learning rate of the cosine decay, as a fraction of ``lr``."""
    grad_clip: float = 5.0
    """Largest gradient norm (0 = no clipping)."""

    def check(self, path: str = "optim") -> None:
        """Raise :class:`ConfigError` for impossible settings."""
        for name in ("lr", "weight_decay", "min_lr", "grad_clip"):
            _finite_nonneg(f"{path}.{name}", getattr(self, name))
        if not (len(self.betas) == 2 and all(0.0 <= float(b) < 1.0 for b in self.betas)):
            raise ConfigError(f"{path}.betas must be two numbers in [0, 1), got {self.betas!r}")
        _positive_int(f"{path}.warmup", self.warmup, allow_zero=True)


# ---------------------------------------------------------------------------------------------------- run
@dataclass(frozen=True)
class RunConfig:
    """Length, batch and the machinery of a run."""

    steps: int = 20_000
    """Optimiser steps of the whole run (the schedule's length)."""
    batch_size: int = 32
    """Global batch size (divided among distributed ranks)."""
    seed: int = 0
    """Seed of the model's initialisation, the shell losses' poses and the replay draws."""
    precision: str = "bf16"
    """``"bf16"``: autocast to bfloat16 on CUDA (float32 on the CPU), or ``"fp32"``."""
    channels_last: bool = False
    """Keep activations channels-last (NDHWC) on CUDA. Off by default: with the default up-convolution the
    contiguous layout measured faster on the H100 (benchmarks/bench_ssz.py)."""
    compile: bool = False
    """``torch.compile`` the generator (fuses its elementwise work and cuts its kernel launches: on the H100 the
    ``ssz64`` step went from 71.7 to 55.3 ms, forward + backward at batch 32; benchmarks/profile_ssz.py). On in
    the GPU presets ``ssz64`` and ``paper``; compiling costs about a minute at the start of a run, and on the CPU
    it needs a C++ compiler."""
    checkpointing: bool = False
    """Recompute the 3D decoder's activations in the backward pass (less memory, more time)."""
    log_every: int = 50
    """Steps between metric rows (CSV, TensorBoard) and progress-bar updates."""
    eval_every: int = 2_000
    """Steps between evaluations on ``data.eval_samples`` test samples (0 = only at the end)."""
    checkpoint_every: int = 2_000
    """Steps between checkpoints (one is always written at the end and on Ctrl-C)."""
    time_limit: float = 0.0
    """Seconds after which the run checkpoints and stops (0 = none): for machines lent in time slices."""
    tensorboard: bool = True
    """Also write TensorBoard event files (when TensorBoard is installed)."""
    init: str = ""
    """A model file (shipped ``.safetensors`` or training checkpoint), or a shipped model's name (``ssz64``,
    ``ssz128``), whose generator weights start the run instead of a fresh initialisation ("" = none): fine-tuning.
    Parameters the file lacks (a layer the architecture gained since) keep their fresh initialisation and are named
    at the start; a parameter of another shape, or one the architecture does not have, stops the run. The
    optimiser, schedule and discriminator start afresh."""

    def check(self, path: str = "run") -> None:
        """Raise :class:`ConfigError` for impossible settings."""
        for name in ("steps", "batch_size", "log_every"):
            _positive_int(f"{path}.{name}", getattr(self, name))
        for name in ("seed", "eval_every", "checkpoint_every"):
            _positive_int(f"{path}.{name}", getattr(self, name), allow_zero=True)
        if self.precision not in ("bf16", "fp32"):
            raise ConfigError(f"{path}.precision must be 'bf16' or 'fp32', got {self.precision!r}")
        _finite_nonneg(f"{path}.time_limit", self.time_limit)


@dataclass(frozen=True)
class TrainConfig:
    """One SSZ experiment."""

    name: str = "ssz64"
    """Name of the experiment (the preset it came from unless renamed); shown in reports."""
    model: ModelConfig = field(default_factory=ModelConfig)
    """Architecture."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Objective."""
    data: DataConfig = field(default_factory=DataConfig)
    """Samples."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Optimiser and schedule."""
    run: RunConfig = field(default_factory=RunConfig)
    """Length and machinery."""

    def check(self) -> TrainConfig:
        """Validate every part; returns self. Raises :class:`ConfigError` naming the key."""
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError("name must be a non-empty string")
        self.model.check()
        self.loss.check()
        self.data.check()
        self.optim.check()
        self.run.check()
        if self.model.fine_depth and self.loss.fine_depth and self.data.source != "stream":
            # Only the simulator has the rendered depth the term is trained on; shards keep images and labels alone.
            raise ConfigError("loss.fine_depth needs data.source = 'stream' (shards hold no rendered depth); set "
                              "loss.fine_depth to 0 to train the fine depth head only through the volume")
        return self

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form with ``"version"``."""
        return {"version": CONFIG_VERSION, **to_plain(self)}

    def to_json(self) -> str:
        """:meth:`to_dict` as indented JSON text."""
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, d: Any) -> TrainConfig:
        """A config from JSON data: a preset (key ``"preset"``, default the dataclass defaults) with the given
        fields overridden. Raises :class:`ConfigError` naming the key."""
        if not isinstance(d, Mapping):
            raise ConfigError(f"config must be a JSON object, got {type(d).__name__}")
        d = dict(d)
        version = d.pop("version", CONFIG_VERSION)
        if version != CONFIG_VERSION:
            raise ConfigError(f"config version {version!r} is not this program's version {CONFIG_VERSION}")
        base = preset(d.pop("preset")) if "preset" in d else cls()
        return override(base, d, "").check()

    @classmethod
    def from_json(cls, text: str) -> TrainConfig:
        """Inverse of :meth:`to_json` (also takes partial configs, see :meth:`from_dict`)."""
        try:
            d = json.loads(text)
        except json.JSONDecodeError as e:
            raise ConfigError(f"config is not valid JSON ({e})") from None
        return cls.from_dict(d)


# ---------------------------------------------------------------------------------------------------- presets
def _presets() -> dict[str, TrainConfig]:
    tiny_grid = FruxelGrid(width=32, height=32, depth=32, z_near=0.5, z_far=8.0, hfov=60.0)
    paper_grid = FruxelGrid(width=128, height=128, depth=128, z_near=0.5, z_far=8.0, hfov=60.0)
    return {
        "tiny": TrainConfig(
            name="tiny",
            model=ModelConfig(grid=tiny_grid, levels=4, stem=8, encoder=(16, 24, 32, 48), encoder_blocks=(1, 1, 1, 1),
                              encoder_expand=2, topdown=(16, 24, 32, 48), decoder=(8, 16, 24, 32),
                              decoder_blocks=(1, 1, 1, 1), discriminator=(16, 32), surface_fusion=True),
            data=DataConfig(workers=1, eval_samples=32, frequency_samples=64),
            optim=OptimConfig(warmup=20),
            run=RunConfig(steps=2000, batch_size=8, precision="fp32", channels_last=False, log_every=10,
                          eval_every=500, checkpoint_every=500),
        ),
        "ssz64": TrainConfig(name="ssz64", model=ModelConfig(surface_fusion=True),
                             data=DataConfig(workers=14, replay=4096, reuse=2), run=RunConfig(compile=True)),
        "paper": TrainConfig(
            name="paper",
            model=ModelConfig(grid=paper_grid, image_scale=2, levels=6, stem=16, encoder=(24, 32, 48, 64, 96, 128),
                              encoder_blocks=(1, 1, 2, 2, 2, 2), topdown=(24, 32, 32, 48, 64, 96),
                              decoder=(8, 16, 24, 32, 48, 64), decoder_blocks=(0, 1, 1, 1, 2, 2),
                              discriminator=(16, 32, 64, 128), surface_fusion=True),
            data=DataConfig(workers=14),
            run=RunConfig(batch_size=8, compile=True),
        ),
    }


PRESETS = ("tiny", "ssz64", "paper")
"""Named presets: ``tiny`` (32^3 from 64^2, trains on a laptop CPU), ``ssz64`` (64^3 from 128^2), ``paper``
(the paper's 128^3 from 512^2)."""


def preset(name: str) -> TrainConfig:
    """The preset ``name`` (one of :data:`PRESETS`)."""
    presets = _presets()
    if name not in presets:
        raise ConfigError(f"unknown preset {name!r}; choose one of {list(presets)}")
    return presets[name]


# ---------------------------------------------------------------------------------------------------- JSON form
def to_plain(obj: Any) -> Any:
    """Dataclasses (grids and class tables by their own ``to_dict``), tuples and numpy scalars as plain JSON."""
    if isinstance(obj, (FruxelGrid, ClassTable)):
        return obj.to_dict()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        return {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
    if isinstance(obj, (tuple, list)):
        return [to_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def override(base: Any, changes: Mapping[str, Any], path: str) -> Any:
    """``base`` (a config dataclass) with the fields in ``changes`` replaced, recursing into nested configs.

    Raises:
        ConfigError: an unknown key, or a value of the wrong kind (the message names ``path.key``).
    """
    if not isinstance(changes, Mapping):
        raise ConfigError(f"{path or 'config'} must be a JSON object, got {type(changes).__name__}")
    fields = {f.name: f for f in dataclasses.fields(base)}
    kwargs = {}
    for key, value in changes.items():
        where = f"{path}.{key}" if path else str(key)
        if key not in fields:
            raise ConfigError(f"unknown config key {where!r}; known keys here: {sorted(fields)}")
        current = getattr(base, key)
        try:
            if isinstance(current, FruxelGrid):
                value = FruxelGrid.from_dict({**current.to_dict(), **value} if isinstance(value, Mapping) else value)
            elif isinstance(current, ClassTable):
                value = ClassTable.from_dict(value)
            elif dataclasses.is_dataclass(current):
                value = override(current, value, where)
            else:
                value = _coerce(where, current, value)
        except (GridError, ClassTableError) as e:
            raise ConfigError(f"{where}: {e}") from None
        kwargs[key] = value
    return dataclasses.replace(base, **kwargs)


def _coerce(where: str, current: Any, value: Any) -> Any:
    """``value`` as the kind of ``current`` (the default's type): tuples from lists, floats from integers."""
    if isinstance(current, bool):
        if not isinstance(value, bool):
            raise ConfigError(f"{where} must be true or false, got {value!r}")
        return value
    if isinstance(current, int):
        if isinstance(value, bool) or not isinstance(value, int):
            raise ConfigError(f"{where} must be an integer, got {value!r}")
        return value
    if isinstance(current, float):
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise ConfigError(f"{where} must be a number, got {value!r}")
        return float(value)
    if isinstance(current, str):
        if not isinstance(value, str):
            raise ConfigError(f"{where} must be a string, got {value!r}")
        return value
    if isinstance(current, tuple):
        if not isinstance(value, (list, tuple)):
            raise ConfigError(f"{where} must be a list, got {value!r}")
        kind = type(current[0]) if current else None
        return tuple(_coerce(f"{where}[{i}]", kind(), v) if kind else v for i, v in enumerate(value))
    return value


def _positive_int(name: str, v: Any, allow_zero: bool = False) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (0 if allow_zero else 1):
        raise ConfigError(f"{name} must be an integer >= {0 if allow_zero else 1}, got {v!r}")


def _finite_nonneg(name: str, v: Any) -> None:
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise ConfigError(f"{name} must be a finite number >= 0, got {v!r}")

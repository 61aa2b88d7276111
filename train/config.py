"""Typed settings of a training run: the model, its losses, the data, the optimiser and the run, with named
presets and a JSON form.

A config file (``fruxel-train --config FILE``) is a JSON object that starts from a preset and overrides any
fields, nested as the dataclasses are::

    {"preset": "ssz64", "optim": {"lr": 0.002}, "run": {"steps": 20000}, "loss": {"shell": true}}

Every config dataclass checks itself once, when it is made (``__post_init__``): unknown keys, wrong types and
impossible values are refused with one :class:`~fruxel.errors.ConfigError` naming the key. The full config
(:meth:`TrainConfig.to_dict`) is saved beside every checkpoint, so a run can always be reproduced.

The model section is an architecture's config (:mod:`fruxel.train.models.registry`): ``"architecture"`` names it
(default ``"ssz"``, :class:`~fruxel.train.models.ssz.SSZConfig`) and the other keys are its fields.
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

from .models.registry import ModelConfig, model_config_from_dict
from .models.ssz import SSZConfig

CONFIG_VERSION = 2
"""Version of the config's JSON layout (1: before the model's inference rules left it; read by
:func:`fruxel.train.legacy.upgrade_config`)."""


# ---------------------------------------------------------------------------------------------------- checks
def count(name: str, v: Any, allow_zero: bool = False) -> None:
    """Raise :class:`~fruxel.errors.ConfigError` naming ``name`` unless ``v`` is an integer >= 1 (>= 0 with
    ``allow_zero``)."""
    if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v < (0 if allow_zero else 1):
        raise ConfigError(f"{name} must be an integer >= {0 if allow_zero else 1}, got {v!r}")


def finite_nonneg(name: str, v: Any) -> None:
    """Raise :class:`~fruxel.errors.ConfigError` naming ``name`` unless ``v`` is a finite number >= 0."""
    if isinstance(v, bool) or not isinstance(v, (int, float)) or not math.isfinite(v) or v < 0:
        raise ConfigError(f"{name} must be a finite number >= 0, got {v!r}")


# ---------------------------------------------------------------------------------------------------- losses
@dataclass(frozen=True)
class ShellLossConfig:
    """Settings of :class:`fruxel.train.losses.ShellLoss` (here, beside the other training settings, so that a
    config is read without loading torch)."""

    own_view: bool = True
    """Include the grid's own camera at native resolution (pixel (x, y) looks down column (y, x))."""
    novel_views: int = 2
    """K: random novel poses drawn per batch (shared by the batch's volumes)."""
    novel_size: tuple[int, int] = (128, 128)
    """``(width, height)`` of each novel view, pixels."""
    novel_hfov: float | None = None
    """Horizontal field of view of the novel views, degrees (None: the grid's own)."""
    azimuth: tuple[float, float] = (-60.0, 60.0)
    """Range of the novel views' azimuth, degrees (0 = the grid's own viewing side)."""
    elevation: tuple[float, float] = (5.0, 40.0)
    """Range of the novel views' elevation above the grid's horizontal plane, degrees."""
    distance: tuple[float, float] = (0.9, 1.3)
    """Range of the novel views' distance, as a factor on 1.2 times the grid's bounding-box diagonal."""
    weight_shell: float = 1.0
    """Weight of :func:`shell_cross_entropy` in the total."""
    weight_depth: float = 1.0
    """Weight of :func:`depth_l1` (unit-free: the error is divided by ``z_far - z_near``) in the total."""
    weight_voxel: float = 1.0
    """Weight of :func:`visible_weighted_voxel_ce` in the total."""
    weight_own_view: float = 0.0
    """Weight of the own view's shell cross-entropy on its own in the total (needs ``own_view``). Its pixels also
    count in :func:`shell_cross_entropy`, where they are one camera among ``1 + novel_views``; this term is what
    the own-view first-hit accuracy of conventions section 9 measures, so it can be weighted up separately."""
    weight_visible: float = 1.0
    """Per-cell weight of the ground truth's shell cells in the voxel cross-entropy."""
    weight_other: float = 0.1
    """Per-cell weight of all other cells in the voxel cross-entropy."""
    eps: float = 1e-6
    """Added to the expected class probability in :func:`shell_cross_entropy`."""
    seed: int = 0
    """Base seed (>= 0) of the novel poses: draw n of distributed rank r is a pure function of ``(seed, r, n)``
    (see :class:`ShellLoss`)."""
    backend: str | None = None
    """Kernel backend (``"warp"``, ``"opencl"``, an ``available_backends`` name, or None for the best)."""
    device: str | None = None
    """Warp device, or None to follow the data."""

    def __post_init__(self) -> None:
        where = "loss.shell_losses"
        count(f"{where}.novel_views", self.novel_views, allow_zero=True)
        if len(self.novel_size) != 2:
            raise ConfigError(f"{where}.novel_size must be (width, height), got {self.novel_size!r}")
        for v in self.novel_size:
            count(f"{where}.novel_size", v)
        if self.novel_hfov is not None and not (isinstance(self.novel_hfov, (int, float))
                                                and math.isfinite(self.novel_hfov) and 0 < self.novel_hfov < 180):
            raise ConfigError(f"{where}.novel_hfov must be in (0, 180) degrees or null, got {self.novel_hfov!r}")
        for name in ("azimuth", "elevation", "distance"):
            lo_hi = getattr(self, name)
            if len(lo_hi) != 2 or not all(math.isfinite(v) for v in lo_hi) or lo_hi[0] > lo_hi[1]:
                raise ConfigError(f"{where}.{name} must be a (low, high) range, got {lo_hi!r}")
        for name in ("weight_shell", "weight_depth", "weight_voxel", "weight_own_view", "weight_visible",
                     "weight_other", "eps"):
            finite_nonneg(f"{where}.{name}", getattr(self, name))
        count(f"{where}.seed", self.seed, allow_zero=True)
        if self.weight_own_view and not self.own_view:
            raise ConfigError(f"{where}.weight_own_view needs {where}.own_view")
        if not self.own_view and not self.novel_views:
            raise ConfigError(f"{where} needs the own view or at least one novel view")


@dataclass(frozen=True)
class LossConfig:
    """Terms of the generator's objective and their weights; every term is a mean, so weights compare."""

    ce: float = 1.0
    """Weight of the class-weighted per-cell cross-entropy."""
    class_weight_power: float = 0.5
    """Class weights of the cross-entropy are ``frequency^-power`` (normalised to a mean of 1 over the cells),
    frequencies counted on the training split: 0 = unweighted, 1 = inverse frequency. Empty, most of the cells,
    is down-weighted by it."""
    iou: float = 1.0
    """Weight of the soft Jaccard loss ``1 - mean_c soft IoU_c`` over the occupied classes, the metric's own
    form (soft IoU with probabilities), counted over the whole batch."""
    depth: float = 0.5
    """Weight of the cross-entropy of the columns' first-surface depth distribution against the ground truth's
    first occupied slice (or "no surface"); needs a network with a column depth head."""
    surface: float = 0.5
    """Weight of the cross-entropy of the columns' first-surface class against the ground truth's; needs a network
    with a surface class head."""
    first_hit: float = 0.0
    """Weight of the own view's first-hit cross-entropy: each column's first-hit distribution over "miss" and the
    classes (:func:`fruxel.train.rules.first_hit_log_probs`, the cells taken as independent) against the truth's
    first label, mean over the columns. The own-view term of the shell-aware losses computed on the columns
    directly, without their kernels or novel views; what the ``first_hit_label`` rule decodes."""
    shell: bool = False
    """Add the shell-aware losses (:class:`fruxel.train.losses.ShellLoss`: own view and random novel views)."""
    shell_weight: float = 0.5
    """Weight of the shell-aware losses' total."""
    shell_losses: ShellLossConfig = ShellLossConfig(novel_views=2, novel_size=(64, 64))
    """The shell-aware losses' own settings (views, their poses and size, the terms' weights, the poses' seed)."""
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
    discriminator: tuple[int, ...] = (32, 64, 128)
    """Channels of the 3D PatchGAN's stride-2 layers (:class:`fruxel.train.models.discriminator.
    PatchDiscriminator3d`)."""

    def __post_init__(self) -> None:
        for name in ("ce", "class_weight_power", "iou", "depth", "surface", "first_hit", "shell_weight",
                     "adversarial_weight", "discriminator_lr"):
            finite_nonneg(f"loss.{name}", getattr(self, name))
        for name in ("adversarial_start", "adversarial_ramp"):
            count(f"loss.{name}", getattr(self, name), allow_zero=True)
        if not self.discriminator:
            raise ConfigError("loss.discriminator needs at least one layer")
        for v in self.discriminator:
            count("loss.discriminator", v)
        if not isinstance(self.shell_losses, ShellLossConfig):
            raise ConfigError(f"loss.shell_losses must be an object, got {self.shell_losses!r}")


# ---------------------------------------------------------------------------------------------------- data
DATA_SOURCES = ("stream", "shards", "folder")
"""Where training samples come from (:attr:`DataConfig.source`)."""


@dataclass(frozen=True)
class DataConfig:
    """Where training and evaluation samples come from (:mod:`fruxel.train.samples`)."""

    source: str = "stream"
    """``"stream"``: made on the fly by the simulator; ``"shards"``: read from a data set folder written by
    ``fruxel-sim generate`` (``root``); ``"folder"``: read from a data folder of labelled photos, yours or written
    by ``fruxel-sim export`` (``root``, :mod:`fruxel.train.folder`, docs/your-data.md)."""
    root: str = ""
    """The data set folder, for ``source = "shards"`` (its grid and image size must match the model), or the data
    folder, for ``source = "folder"`` (its grid and classes must match the model)."""
    world: str = "home"
    """The simulator's world of streamed samples (:data:`fruxel.train.sim.config.WORLDS`): ``"home"``, furnished
    rooms from the asset pack (the model's classes must include ``ceiling`` and ``object``), or ``"flat"``, the
    flat-shaded rooms the shipped models learnt."""
    camera: str = "any"
    """The cameras of streamed samples (:data:`fruxel.train.sim.cameras.CAMERAS`): ``"any"``, a mount drawn per
    trajectory, or ``"robot"``, the robot's own."""
    renderer: str = ""
    """The renderer of streamed samples, by its registry name; "" takes the world's own
    (:data:`fruxel.train.sim.config.WORLD_RENDERERS`)."""
    assets: str = ""
    """The asset pack folder of the home world; "" takes the ``FRUXEL_ASSETS`` environment variable, else the
    repository's ``assets/pack`` (``make assets``)."""
    mix_set: str = ""
    """Another kind of room mixed into the stream: a test set's name (:data:`fruxel.train.sim.testsets.TEST_SETS`)
    whose camera, world and renderer a share of the streamed training rooms take (``mix_share``; the training
    split's rooms, never the set's own held-out ones), so that a model for one kind of room keeps another:
    ``"robot"``, the robot's mount in the flat world. "" for none; streaming only."""
    mix_share: float = 0.0
    """The share of streamed training rooms made as ``mix_set``'s, in [0, 1); which rooms is fixed by the seed and
    each room's index, so a resumed or distributed run makes the same ones."""
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
    """Test samples used by the periodic evaluation during training (0: no evaluation; the run then logs its losses
    alone)."""
    frequency_samples: int = 256
    """Training samples counted for the cross-entropy's class frequencies."""
    camera_dropout: tuple[float, float] = (0.3, 0.3)
    """For a model that reads the camera (``model.camera_inputs``): ``(p_gravity, p_height)``, the probability that
    a training sample's gravity direction is withheld from the network (its height then too: a height means
    nothing without gravity), and that its height alone is withheld when gravity is given; each in [0, 1], drawn
    per sample, so that the network learns "unknown" as well as "known" (a phone knows gravity, a photo nothing).
    The default gives 49 % both, 21 % gravity only, 30 % nothing. Models without camera inputs ignore it."""

    def __post_init__(self) -> None:
        from .sim.cameras import CAMERAS
        from .sim.config import WORLDS
        from .sim.renderer import renderer_names

        if self.source not in DATA_SOURCES:
            raise ConfigError(f"data.source must be one of {', '.join(DATA_SOURCES)}, got {self.source!r}")
        for name, value, known in (("world", self.world, WORLDS), ("camera", self.camera, tuple(CAMERAS))):
            if value not in known:
                raise ConfigError(f"data.{name} must be one of {', '.join(known)}, got {value!r}")
        if self.renderer and self.renderer not in renderer_names():
            raise ConfigError(f"data.renderer must be one of {', '.join(renderer_names())} (or empty: the world's "
                              f"own), got {self.renderer!r}")
        if self.source in ("shards", "folder") and not self.root:
            raise ConfigError(f"data.root must name a data set folder when data.source is {self.source!r}")
        for name in ("seed", "workers", "replay", "eval_samples"):
            count(f"data.{name}", getattr(self, name), allow_zero=True)
        for name in ("train_samples", "test_samples", "samples_per_scene", "reuse", "frequency_samples"):
            count(f"data.{name}", getattr(self, name))
        self._check_mix()
        p = self.camera_dropout
        if not (isinstance(p, tuple) and len(p) == 2 and all(
                isinstance(v, (int, float)) and not isinstance(v, bool) and 0.0 <= v <= 1.0 for v in p)):
            raise ConfigError(f"data.camera_dropout must be two probabilities in [0, 1] (gravity, height), got {p!r}")

    def _check_mix(self) -> None:
        from .sim.testsets import TEST_SETS

        if self.mix_set and self.mix_set not in TEST_SETS:
            raise ConfigError(f"data.mix_set must be one of {', '.join(TEST_SETS)} (or empty: none), got "
                              f"{self.mix_set!r}")
        share = self.mix_share
        if isinstance(share, bool) or not isinstance(share, (int, float)) or not 0.0 <= share < 1.0:
            raise ConfigError(f"data.mix_share must be a number in [0, 1), got {share!r}")
        if share > 0 and not self.mix_set:
            raise ConfigError("data.mix_share needs data.mix_set: the test set whose rooms are mixed in")
        if share > 0 and self.source != "stream":
            raise ConfigError(f"data.mix_set mixes streamed rooms only; data.source is {self.source!r}")


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

    def __post_init__(self) -> None:
        for name in ("lr", "weight_decay", "min_lr", "grad_clip"):
            finite_nonneg(f"optim.{name}", getattr(self, name))
        if not (len(self.betas) == 2 and all(0.0 <= float(b) < 1.0 for b in self.betas)):
            raise ConfigError(f"optim.betas must be two numbers in [0, 1), got {self.betas!r}")
        count("optim.warmup", self.warmup, allow_zero=True)


# ---------------------------------------------------------------------------------------------------- run
PRECISIONS = ("bf16", "fp32")
"""Compute precisions of a run (:attr:`RunConfig.precision`)."""


@dataclass(frozen=True)
class RunConfig:
    """Length, batch and the machinery of a run."""

    steps: int = 20_000
    """Optimiser steps of the whole run (the schedule's length)."""
    batch_size: int = 32
    """Global batch size (divided among distributed ranks)."""
    seed: int = 0
    """Seed of the model's initialisation and the replay draws."""
    precision: str = "bf16"
    """``"bf16"``: autocast to bfloat16 on CUDA (float32 on the CPU), or ``"fp32"``."""
    channels_last: bool = False
    """Keep activations channels-last (NDHWC) on CUDA. Off by default: with the default up-convolution the
    contiguous layout measured faster on the H100 (BENCHMARKS.md)."""
    compile: bool = False
    """``torch.compile`` the generator (fuses its elementwise work and cuts its kernel launches; BENCHMARKS.md).
    On in the GPU presets; compiling takes a while at the start of a run, and on the CPU it needs a C++
    compiler."""
    cuda_graphs: bool = True
    """With ``compile`` on CUDA, replay the compiled network's forward and backward passes as CUDA graphs
    (``torch.compile(mode="reduce-overhead")``): the host no longer launches each kernel, which paced the steps on one
    GPU and, under DDP, made every rank wait for the slowest launcher (BENCHMARKS.md "Multi-GPU training"). Off: the
    kernels are launched one by one, as before. Ignored without ``compile`` and on the CPU."""
    checkpointing: bool = False
    """Recompute the 3D decoder's activations in the backward pass (less memory, more time)."""
    log_every: int = 50
    """Steps between metric rows (CSV, TensorBoard) and progress-bar updates."""
    eval_every: int = 2_000
    """Steps between evaluations on ``data.eval_samples`` test samples (0 = only at the end)."""
    checkpoint_every: int = 2_000
    """Steps between checkpoints (one is always written at the end and on Ctrl-C)."""
    time_limit: float = 0.0
    """Seconds of the training loop (from its first step, compilation included) after which the run evaluates,
    checkpoints and stops (0 = none): for machines lent in time slices. Leave room after it for the start-up before
    the loop and the final evaluation and checkpoint. Under DDP the ranks agree on the stop every 10 steps."""
    tensorboard: bool = True
    """Also write TensorBoard event files (when TensorBoard is installed)."""
    init: str = ""
    """A model file (shipped ``.safetensors`` or training checkpoint), or a shipped model's name (``ssz64``,
    ``ssz128``), whose network weights start the run instead of a fresh initialisation ("" = none): fine-tuning.
    Parameters the file lacks (a layer the architecture gained since) keep their fresh initialisation and are named
    at the start. A file with another number of classes gives each class of this model's table that it has (by
    name) its weights, and a new class keeps its fresh ones; as many classes must be the same, in order. Any other
    parameter of another shape, or one the architecture does not have, stops the run. The optimiser, schedule and
    discriminator start afresh."""

    def __post_init__(self) -> None:
        for name in ("steps", "batch_size", "log_every"):
            count(f"run.{name}", getattr(self, name))
        for name in ("seed", "eval_every", "checkpoint_every"):
            count(f"run.{name}", getattr(self, name), allow_zero=True)
        if self.precision not in PRECISIONS:
            raise ConfigError(f"run.precision must be one of {', '.join(PRECISIONS)}, got {self.precision!r}")
        finite_nonneg("run.time_limit", self.time_limit)


# ---------------------------------------------------------------------------------------------------- the whole
@dataclass(frozen=True)
class TrainConfig:
    """One training run."""

    name: str = "ssz64"
    """Name of the experiment (the preset it came from unless renamed); shown in reports."""
    model: ModelConfig = field(default_factory=SSZConfig)
    """Architecture (any registered one; :mod:`fruxel.train.models.registry`)."""
    loss: LossConfig = field(default_factory=LossConfig)
    """Objective."""
    data: DataConfig = field(default_factory=DataConfig)
    """Samples."""
    optim: OptimConfig = field(default_factory=OptimConfig)
    """Optimiser and schedule."""
    run: RunConfig = field(default_factory=RunConfig)
    """Length and machinery."""

    def __post_init__(self) -> None:
        if not isinstance(self.name, str) or not self.name:
            raise ConfigError("name must be a non-empty string")
        for part, kind in (("model", ModelConfig), ("loss", LossConfig), ("data", DataConfig),
                           ("optim", OptimConfig), ("run", RunConfig)):
            if not isinstance(getattr(self, part), kind):
                raise ConfigError(f"{part} must be a {kind.__name__}, got {type(getattr(self, part)).__name__}")
        if self.data.source == "stream" and self.data.world == "home":
            from .sim.rooms import CLASS_NAMES

            missing = [n for n in CLASS_NAMES if n not in self.model.classes.names]
            if missing:
                raise ConfigError(f"data.world 'home' labels {list(CLASS_NAMES)}; model.classes lacks {missing} (use "
                                  "fruxel.classes.HOME_CLASSES, or data.world 'flat')")

    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON form with ``"version"``."""
        return {"version": CONFIG_VERSION, **to_plain(self)}

    def to_json(self) -> str:
        """:meth:`to_dict` as indented JSON text."""
        return json.dumps(self.to_dict(), indent=2)

    @classmethod
    def from_dict(cls, d: Any) -> TrainConfig:
        """A config from JSON data: a preset (key ``"preset"``, default the dataclass defaults) with the given
        fields overridden; a config of version 1 is upgraded first (:func:`fruxel.train.legacy.upgrade_config`).

        Raises:
            ConfigError: naming the key.
        """
        from .legacy import upgrade_config

        if not isinstance(d, Mapping):
            raise ConfigError(f"config must be a JSON object, got {type(d).__name__}")
        d = dict(d)
        version = d.pop("version", CONFIG_VERSION)
        if version == 1:
            d = upgrade_config(d)
        elif version != CONFIG_VERSION:
            raise ConfigError(f"config version {version!r} is not this program's version {CONFIG_VERSION}")
        base = preset(d.pop("preset")) if "preset" in d else cls()
        return override(base, d, "")

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
    grid128 = FruxelGrid(width=128, height=128, depth=128, z_near=0.5, z_far=8.0, hfov=60.0)
    shipped = DataConfig(workers=14, replay=4096, reuse=2, world="flat", camera="robot")
    return {
        "tiny": TrainConfig(
            name="tiny",
            model=SSZConfig(grid=tiny_grid, levels=4, stem=8, encoder=(16, 24, 32, 48), encoder_blocks=(1, 1, 1, 1),
                            encoder_expand=2, topdown=(16, 24, 32, 48), decoder=(8, 16, 24, 32),
                            decoder_blocks=(1, 1, 1, 1), camera_inputs=True),
            loss=LossConfig(discriminator=(16, 32)),
            data=DataConfig(workers=1, eval_samples=32, frequency_samples=64),
            optim=OptimConfig(warmup=20),
            run=RunConfig(steps=2000, batch_size=8, precision="fp32", log_every=10, eval_every=500,
                          checkpoint_every=500),
        ),
        # The shipped ssz64's architecture, image size (256 x 256: the stem reads it 2 x 2-pooled), classes and
        # samples (the flat world from the robot's mount).
        "ssz64": TrainConfig(name="ssz64", model=SSZConfig(detail_branch=24, classes=DEFAULT_CLASSES), data=shipped,
                             run=RunConfig(compile=True)),
        # ssz64's architecture reading the camera (issue 39), for the furnished rooms from any camera: the default
        # model's training. Cameras withheld at random (data.camera_dropout) so that "unknown" works. It starts from
        # the shipped ssz64 (its seven classes by name; ceiling, object and the camera inputs fresh) at half ssz64's
        # learning rate: a lent GPU's half hour a session does not train one from nothing. Its class weights are
        # flatter than the default's (power 0.25, not 0.5): the default's low weight of empty cells bought recall
        # with false surfaces in free space (docs/experiments.md, the class-weighting A/B). 32 frames a room, not
        # 16: the stream's room set-up is shared by twice the samples (about 1.2x the samples a second on one GPU),
        # and the network read new rooms no worse for it (round 3 of the A/B). A fifth of the rooms are the robot's
        # mount in the flat world (data.mix_set): what ssz64 reads, which the rooms from any camera alone unlearnt.
        "ssz64-any": TrainConfig(name="ssz64-any", model=SSZConfig(detail_branch=24, camera_inputs=True),
                                 loss=LossConfig(class_weight_power=0.25),
                                 data=dataclasses.replace(shipped, world="home", camera="any", samples_per_scene=32,
                                                          mix_set="robot", mix_share=0.2),
                                 optim=OptimConfig(lr=1e-3, warmup=300),
                                 run=RunConfig(compile=True, init="ssz64")),
        # The shipped ssz128's: ssz64 below a refinement level, 512 x 512 images, fine-tuned from the shipped ssz64
        # with the whole network training (its last two stages; the level started alone: docs/model.md).
        "ssz128": TrainConfig(
            name="ssz128", model=SSZConfig(grid=grid128, detail_branch=24, refine=16, classes=DEFAULT_CLASSES),
            loss=LossConfig(first_hit=1.0), data=dataclasses.replace(shipped, replay=2048),
            optim=OptimConfig(lr=3e-4, warmup=100),
            run=RunConfig(steps=5000, batch_size=16, compile=True, init="ssz64")),
    }


PRESETS = ("tiny", "ssz64", "ssz128", "ssz64-any")
"""Named presets: ``tiny`` (32^3 from 64^2, reads the camera, trains on a laptop CPU, in the simulator's furnished
rooms from any camera), ``ssz64`` and ``ssz128`` (the shipped models' architectures, image sizes, classes and
samples: 64^3 from 256^2, 128^3 from 512^2, the flat world from the robot's mount), ``ssz64-any`` (ssz64's
architecture reading the camera, the furnished rooms from any camera, their classes: the camera-aware model's
training)."""
REPLACED_PRESETS = {"paper": "ssz128"}
"""Presets that no longer exist, and what replaced them."""


def preset(name: str) -> TrainConfig:
    """The preset ``name`` (one of :data:`PRESETS`)."""
    presets = _presets()
    if name in REPLACED_PRESETS:
        raise ConfigError(f"preset {name!r} was replaced by {REPLACED_PRESETS[name]!r}")
    if name not in presets:
        raise ConfigError(f"unknown preset {name!r}; choose one of {list(presets)}")
    return presets[name]


# ---------------------------------------------------------------------------------------------------- JSON form
def to_plain(obj: Any) -> Any:
    """Dataclasses (grids and class tables by their own ``to_dict``, model configs with their ``architecture``),
    tuples and numpy scalars as plain JSON."""
    if isinstance(obj, (FruxelGrid, ClassTable)):
        return obj.to_dict()
    if dataclasses.is_dataclass(obj) and not isinstance(obj, type):
        plain = {f.name: to_plain(getattr(obj, f.name)) for f in dataclasses.fields(obj)}
        return {"architecture": obj.architecture, **plain} if isinstance(obj, ModelConfig) else plain
    if isinstance(obj, (tuple, list)):
        return [to_plain(v) for v in obj]
    if isinstance(obj, np.generic):
        return obj.item()
    return obj


def override(base: Any, changes: Mapping[str, Any], path: str) -> Any:
    """``base`` (a config dataclass) with the fields in ``changes`` replaced, recursing into nested configs; the
    result checks itself.

    Raises:
        ConfigError: an unknown key, or a value of the wrong kind or impossible (the message names ``path.key``).
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
            if isinstance(current, ModelConfig):
                value = model_config_from_dict(value, current, where)
            elif isinstance(current, FruxelGrid):
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
    try:
        return dataclasses.replace(base, **kwargs)
    except (TypeError, ValueError) as e:
        if isinstance(e, ConfigError):
            raise
        # A dataclass without its own check (a nested settings class) refusing a value.
        raise ConfigError(f"{path or 'config'}: {e}") from None


def _coerce(where: str, current: Any, value: Any) -> Any:
    """``value`` as the kind of ``current`` (the default's type): tuples from lists, floats from integers. A field
    whose default is None takes the value as it is (its dataclass checks it)."""
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

"""Building SSZ from its config, and the two files a trained model lives in (SPEC section 8).

* A **shipped model**: one ``.safetensors`` file of the generator's weights (float16 or float32) whose metadata
  holds ``{"format": "fruxel-ssz", "version": 1, "model": ModelConfig as JSON, "training": summary}``. It loads
  without pickle and without optimiser state.
* A **training checkpoint** (:mod:`fruxel.train.engine.checkpoint`): a dict read with
  ``torch.load(weights_only=True)``, which holds the same generator weights and the whole experiment config.

:func:`load_generator` reads either and returns the generator in eval mode with its :class:`ModelConfig`.
"""

from __future__ import annotations

import json
import os
from typing import Any

import torch

from fruxel.errors import FruxelError
from fruxel.io import atomic_path

from .config import ConfigError, ModelConfig, TrainConfig, override
from .models.discriminator import PatchDiscriminator3d
from .models.generator import SSZGenerator

FORMAT = "fruxel-ssz"
"""``format`` in a shipped model's metadata."""
VERSION = 1
"""Version of the shipped model's metadata layout."""
SHIPPED_MODELS = {"ssz64": "ssz64.safetensors", "ssz128": "ssz128.safetensors"}
"""The models shipped with fruxel (in ``fruxel/train/data/``), by the name that ``--checkpoint`` and ``run.init``
accept in place of a path: ``ssz64`` (64^3 cells from a 256 x 256 image, the default) and ``ssz128`` (128^3 cells
from 512 x 512, the paper's scale; docs/model.md)."""
MAX_TENSORS = 10_000
"""Most tensors a shipped model may hold (a sanity bound against hostile files)."""


class ModelFileError(FruxelError, ValueError):
    """A model file that cannot be used; the message names the file and the problem."""

    def __init__(self, path: str, problem: str) -> None:
        super().__init__(f"{path}: {problem}")
        self.path = path
        """The file."""
        self.problem = problem
        """What is wrong, in words."""


def build_generator(config: ModelConfig, *, checkpointing: bool = False) -> SSZGenerator:
    """A freshly initialised generator of ``config``."""
    g = config.grid
    return SSZGenerator(classes=config.num_classes, grid_shape=(g.depth, g.height, g.width),
                        image_scale=config.image_scale, levels=config.levels, stem=config.stem,
                        image_branch=config.image_branch, detail_branch=config.detail_branch,
                        encoder=config.encoder, encoder_blocks=config.encoder_blocks, topdown=config.topdown,
                        decoder=config.decoder, decoder_blocks=config.decoder_blocks, expand=config.expand,
                        encoder_expand=config.encoder_expand,
                        lift=config.lift, upsample=config.upsample, group_width=config.group_width,
                        full_res_spatial=config.full_res_spatial, surface_fusion=config.surface_fusion,
                        fill_columns=config.fill_columns, empty_offset=config.empty_offset,
                        fill_threshold=config.fill_threshold, first_hit_label=config.first_hit_label,
                        flip_average=config.flip_average, fine_depth=config.fine_depth,
                        refine=config.refine, refine_scale=config.refine_scale,
                        refine_frozen=config.refine_frozen, checkpointing=checkpointing)


def build_discriminator(config: ModelConfig) -> PatchDiscriminator3d:
    """A freshly initialised discriminator of ``config``."""
    return PatchDiscriminator3d(config.num_classes, config.discriminator)


def save_shipped(path: str | os.PathLike[str], generator: torch.nn.Module, config: ModelConfig,
                 training: dict[str, Any] | None = None, *, half: bool = True) -> None:
    """Write the shipped form of a generator atomically.

    Args:
        path: the ``.safetensors`` file.
        generator: the trained generator (its ``state_dict`` is saved; buffers such as batch-norm statistics
            included).
        config: its architecture.
        training: a JSON-able summary of how it was trained (steps, samples seen, GPU time, metrics).
        half: store floating tensors as float16 (halves the file; predictions are made in float32 or bf16).
    """
    from safetensors.torch import save_file

    state = {}
    for k, v in generator.state_dict().items():
        v = v.detach().cpu()
        if half and v.is_floating_point():
            v = v.half()
        state[k] = v.contiguous()
    meta = {"format": FORMAT, "version": str(VERSION),
            "model": json.dumps({k: v for k, v in TrainConfig(model=config).to_dict()["model"].items()}),
            "training": json.dumps(training or {})}
    with atomic_path(path) as tmp:
        save_file(state, str(tmp), metadata=meta)


def _model_config(path: str, d: Any) -> ModelConfig:
    try:
        config = override(ModelConfig(), d, "model")
        config.check()
        return config
    except ConfigError as e:
        raise ModelFileError(path, f"bad model config: {e}") from None


def read_shipped(path: str) -> tuple[dict[str, torch.Tensor], ModelConfig, dict[str, Any]]:
    """The weights, architecture and training summary of a shipped model file, checked.

    Raises:
        ModelFileError: not a safetensors file of this format, or a bad config.
    """
    from safetensors import SafetensorError, safe_open

    try:
        with safe_open(path, framework="pt") as f:
            meta = f.metadata() or {}
            keys = list(f.keys())
            if len(keys) > MAX_TENSORS:
                raise ModelFileError(path, f"holds {len(keys)} tensors, more than {MAX_TENSORS}")
            state = {k: f.get_tensor(k) for k in keys}
    except (SafetensorError, OSError, ValueError) as e:
        if isinstance(e, ModelFileError):
            raise
        raise ModelFileError(path, f"not a readable safetensors file ({e})") from None
    if meta.get("format") != FORMAT:
        raise ModelFileError(path, f"metadata format is {meta.get('format')!r}, not {FORMAT!r}")
    if meta.get("version") != str(VERSION):
        raise ModelFileError(path, f"metadata version {meta.get('version')!r} is not {VERSION}")
    try:
        model = json.loads(meta["model"])
        training = json.loads(meta.get("training", "{}"))
    except (KeyError, json.JSONDecodeError) as e:
        raise ModelFileError(path, f"metadata 'model' is not JSON ({e})") from None
    return state, _model_config(path, model), training


def shipped_model(name: str) -> str:
    """Path of the shipped model ``name`` (a key of :data:`SHIPPED_MODELS`)."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", SHIPPED_MODELS[name])


def model_path(path: str | os.PathLike[str]) -> str:
    """``path`` itself, or the shipped model it names (:data:`SHIPPED_MODELS`) when no such file exists here."""
    path = os.fsdecode(path)
    return shipped_model(path) if path in SHIPPED_MODELS and not os.path.exists(path) else path


def read_weights(path: str | os.PathLike[str]) -> tuple[dict[str, torch.Tensor], ModelConfig, dict[str, Any]]:
    """The generator weights, architecture and training summary of a shipped ``.safetensors`` file or a training
    checkpoint (told apart by their first bytes), read without pickle.

    Args:
        path: the file, or the name of a shipped model (:func:`model_path`).

    Raises:
        ModelFileError: a missing, unreadable or foreign file.
        fruxel.train.engine.checkpoint.CheckpointError: a checkpoint that cannot be read (or holds pickled
            objects).
    """
    path = model_path(path)
    if not os.path.isfile(path):
        if os.path.exists(path):
            raise ModelFileError(path, "not a regular file")
        # A bare word (no folder, no suffix) was most likely meant as a shipped model's name.
        bare = not os.path.dirname(path) and not os.path.splitext(path)[1]
        raise ModelFileError(path, "no such file" + (f", nor a shipped model ({', '.join(SHIPPED_MODELS)})"
                                                     if bare else ""))
    with open(path, "rb") as f:
        head = f.read(9)
    # safetensors: an 8-byte little-endian header length, then the JSON header. Its first byte can be 0x80 (a
    # header of 128 + 256 k bytes), so the JSON's opening brace is checked before the pickle and zip magics.
    safetensors = head[8:9] == b"{" and int.from_bytes(head[:8], "little") < os.path.getsize(path)
    if not safetensors and (head[:2] == b"PK" or head[:1] == b"\x80"):
        if path.lower().endswith(".safetensors"):
            # torch.load reads any file named .safetensors as one, whatever it holds.
            raise ModelFileError(path, "named .safetensors but is a torch.save archive (zip), as a training "
                                       "checkpoint is: give a checkpoint its .pt name" if head[:2] == b"PK" else
                                 "named .safetensors but is a Python pickle, which fruxel never loads")
        from .engine.checkpoint import read_checkpoint

        ckpt = read_checkpoint(path)
        return ckpt.state["generator"], ckpt.config.model, ckpt.state.get("summary", {})
    return read_shipped(path)


def load_generator(path: str | os.PathLike[str], device: str | torch.device = "cpu"
                   ) -> tuple[SSZGenerator, ModelConfig, dict[str, Any]]:
    """A trained generator from a shipped ``.safetensors`` file or a training checkpoint, in eval mode, float32.

    Returns:
        ``(generator, model config, training summary)``.

    Raises:
        ModelFileError: a missing, unreadable or foreign file, weights that do not fit the config, integer weights
            where the model has floating ones, or NaN or infinite weights.
    """
    path = model_path(path)
    state, config, training = read_weights(path)
    gen = build_generator(config)
    own = gen.state_dict()
    for k, v in state.items():
        # load_state_dict would cast integer weights (a quantised file) silently, and NaN would show only as NaN
        # logits much later.
        if k in own and own[k].is_floating_point() and not v.is_floating_point():
            raise ModelFileError(path, f"weight {k} is {str(v.dtype).removeprefix('torch.')}; fruxel reads float16, "
                                       "bfloat16 or float32 weights (not a quantised model)")
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            raise ModelFileError(path, f"weight {k} holds NaN or infinite values (a diverged training run?)")
    try:
        gen.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in state.items()})
    except RuntimeError as e:
        # torch's first line only names the module; the next says what does not fit (it may list many keys).
        lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
        detail = lines[1] if len(lines) > 1 else lines[0] if lines else type(e).__name__
        detail = detail if len(detail) <= 300 else detail[:297] + "..."
        raise ModelFileError(path, f"weights do not fit the model config ({detail})") from None
    return gen.to(device).eval(), config, training

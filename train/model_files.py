"""The files a trained model lives in (conventions section 8), and loading a network from them by its architecture.

* A **shipped model**: one ``.safetensors`` file of the network's weights (float16 or float32) whose metadata
  holds ``{"format": "fruxel-model", "version": "2", "model": the model config as JSON, with its
  "architecture", "rules": the inference rules as JSON, "training": a summary}``. It loads without pickle and
  without optimiser state. Files of version 1 (``"format": "fruxel-ssz"``, the rules inside the model config)
  are read too (:mod:`fruxel.train.legacy`).
* A **training checkpoint** (:mod:`fruxel.train.engine.checkpoint`): a dict read with
  ``torch.load(weights_only=True)``, which holds the same network weights and the whole training config (no
  rules: a model gets them after training, ``fruxel-calibrate``).

:func:`load_model` reads either: it builds the network the file's config names
(:func:`fruxel.train.models.registry.architecture`), loads the weights, and returns it in eval mode with its
config and rules.
"""

from __future__ import annotations

import json
import os
from dataclasses import dataclass, field
from typing import Any

import torch

from fruxel.errors import ConfigError, FruxelError
from fruxel.io import atomic_path

from .models.registry import ModelConfig, model_config_from_dict
from .rules import NO_RULES, InferenceRules

FORMAT = "fruxel-model"
"""``format`` in a shipped model's metadata."""
VERSION = 2
"""Version of the shipped model's metadata layout."""
LEGACY_FORMAT = "fruxel-ssz"
"""``format`` of version 1 files."""
SHIPPED_MODELS = {"ssz64": "ssz64.safetensors", "ssz128": "ssz128.safetensors", "ssz64-any": "ssz64-any.safetensors"}
"""The models shipped with fruxel (in ``fruxel/train/data/``), by the name that ``--checkpoint`` and ``run.init``
accept in place of a path: ``ssz64-any`` (64^3 cells from a 256 x 256 image, trained on furnished rooms from any
camera; it reads the camera's gravity direction and height when told them; the default), ``ssz64`` (64^3 cells,
trained from the robot's own mount in the flat world: the robot's model) and ``ssz128`` (ssz64 at 128^3 cells from
512 x 512, the paper's scale); docs/model.md."""
DEFAULT_MODEL = "ssz64-any"
"""The shipped model used when none is named: the one for a photo from any camera."""
ROBOT_MODEL = "ssz64"
"""The shipped model of the robot's own mount (``fruxel-robot`` and the live demo when none is named): the
specialist, which reads that mount better than :data:`DEFAULT_MODEL` (docs/model.md)."""
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


@dataclass
class ModelFile:
    """What a model file holds."""

    state: dict[str, torch.Tensor]
    """The network's ``state_dict`` as stored (float16 or float32 floats)."""
    config: ModelConfig
    """Its architecture (and grid, class table)."""
    rules: InferenceRules = NO_RULES
    """The inference rules chosen for it (none for a training checkpoint)."""
    training: dict[str, Any] = field(default_factory=dict)
    """How it was trained (a JSON-able summary)."""


@dataclass
class LoadedModel:
    """A network ready to predict, with what belongs to it."""

    network: torch.nn.Module
    """The network, in eval mode, float32 (:class:`~fruxel.train.models.registry.ModelOutput` contract)."""
    config: ModelConfig
    """Its architecture."""
    rules: InferenceRules
    """Its inference rules (:func:`fruxel.train.rules.predict_logits`)."""
    training: dict[str, Any]
    """How it was trained."""
    path: str
    """The file it was read from."""
    half: bool = False
    """Whether the file stores float16 weights (saving with ``half=half`` writes the same weights back)."""


def save_model(path: str | os.PathLike[str], network: torch.nn.Module, config: ModelConfig,
               rules: InferenceRules = NO_RULES, training: dict[str, Any] | None = None, *, half: bool = True) -> None:
    """Write the shipped form of a network atomically.

    Args:
        path: the ``.safetensors`` file.
        network: the trained network (its ``state_dict`` is saved; buffers such as batch-norm statistics
            included).
        config: its architecture.
        rules: its inference rules.
        training: a JSON-able summary of how it was trained (steps, samples seen, GPU time, metrics).
        half: store floating tensors as float16 (halves the file; predictions are made in float32 or bf16).
    """
    from safetensors.torch import save_file

    from .models.registry import model_config_to_dict

    state = {}
    for k, v in network.state_dict().items():
        v = v.detach().cpu()
        if half and v.is_floating_point():
            v = v.half()
        state[k] = v.contiguous()
    meta = {"format": FORMAT, "version": str(VERSION), "model": json.dumps(model_config_to_dict(config)),
            "rules": json.dumps(rules.to_dict()), "training": json.dumps(training or {})}
    with atomic_path(path) as tmp:
        save_file(state, str(tmp), metadata=meta)


def read_shipped(path: str) -> ModelFile:
    """The weights, architecture, rules and training summary of a shipped model file, checked.

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
    kind = (meta.get("format"), meta.get("version"))
    if kind not in ((FORMAT, str(VERSION)), (LEGACY_FORMAT, "1")):
        raise ModelFileError(path, f"metadata format {kind[0]!r} version {kind[1]!r} is not {FORMAT!r} version "
                                   f"{VERSION} (nor {LEGACY_FORMAT!r} version 1)")
    try:
        model = json.loads(meta["model"])
        rules = json.loads(meta.get("rules", "{}"))
        training = json.loads(meta.get("training", "{}"))
    except (KeyError, json.JSONDecodeError) as e:
        raise ModelFileError(path, f"metadata 'model' is not JSON ({e})") from None
    try:
        if kind[0] == LEGACY_FORMAT:
            from .legacy import split_model

            model, rules = split_model(model, path)
            model.pop("discriminator", None)
        return ModelFile(state, model_config_from_dict(model), InferenceRules.from_dict(rules), training)
    except ConfigError as e:
        raise ModelFileError(path, f"bad model metadata: {e}") from None


def shipped_model(name: str) -> str:
    """Path of the shipped model ``name`` (a key of :data:`SHIPPED_MODELS`)."""
    return os.path.join(os.path.dirname(os.path.abspath(__file__)), "data", SHIPPED_MODELS[name])


def model_path(path: str | os.PathLike[str] | None) -> str:
    """``path`` itself, or the shipped model it names (:data:`SHIPPED_MODELS`) when no such file exists here; the
    default model (:data:`DEFAULT_MODEL`) for None."""
    if path is None:
        return shipped_model(DEFAULT_MODEL)
    path = os.fsdecode(path)
    return shipped_model(path) if path in SHIPPED_MODELS and not os.path.exists(path) else path


def read_model_file(path: str | os.PathLike[str] | None) -> ModelFile:
    """The network weights, architecture, rules and training summary of a shipped ``.safetensors`` file or a
    training checkpoint (told apart by their first bytes), read without pickle.

    Args:
        path: the file, or the name of a shipped model (:func:`model_path`); None for the default.

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
        return ModelFile(ckpt.state["generator"], ckpt.config.model, NO_RULES, ckpt.state.get("summary", {}))
    return read_shipped(path)


def load_model(path: str | os.PathLike[str] | None = None, device: str | torch.device = "cpu") -> LoadedModel:
    """A trained network from a shipped ``.safetensors`` file or a training checkpoint (a path, a shipped model's
    name, or None for the default), built by its architecture's name, in eval mode, float32.

    Raises:
        ModelFileError: a missing, unreadable or foreign file, weights that do not fit the config, integer weights
            where the network has floating ones, or NaN or infinite weights.
    """
    path = model_path(path)
    f = read_model_file(path)
    network = f.config.build()
    own = network.state_dict()
    for k, v in f.state.items():
        # load_state_dict would cast integer weights (a quantised file) silently, and NaN would show only as NaN
        # logits much later.
        if k in own and own[k].is_floating_point() and not v.is_floating_point():
            raise ModelFileError(path, f"weight {k} is {str(v.dtype).removeprefix('torch.')}; fruxel reads float16, "
                                       "bfloat16 or float32 weights (not a quantised model)")
        if v.is_floating_point() and not bool(torch.isfinite(v).all()):
            raise ModelFileError(path, f"weight {k} holds NaN or infinite values (a diverged training run?)")
    try:
        network.load_state_dict({k: v.float() if v.is_floating_point() else v for k, v in f.state.items()})
    except RuntimeError as e:
        # torch's first line only names the module; the next says what does not fit (it may list many keys).
        lines = [ln.strip() for ln in str(e).splitlines() if ln.strip()]
        detail = lines[1] if len(lines) > 1 else lines[0] if lines else type(e).__name__
        detail = detail if len(detail) <= 300 else detail[:297] + "..."
        raise ModelFileError(path, f"weights do not fit the model config ({detail})") from None
    half = any(v.dtype == torch.float16 for v in f.state.values())
    return LoadedModel(network.to(device).eval(), f.config, f.rules, f.training, path, half)

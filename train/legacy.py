"""Reading what earlier fruxel versions wrote: training configs of version 1 (inside run folders and checkpoints)
and the model section of shipped model files of version 1.

Version 1 kept the inference rules in the model config and had settings that no shipped model used (research
levers, removed since; their history is in docs/experiments.md). Upgrading moves the rules out and drops each
removed setting that holds the value the network always had; a file that used a removed setting for real is
refused with one :class:`~fruxel.errors.ConfigError` naming it, since no current network computes what it
describes.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

from fruxel.errors import ConfigError

RULE_KEYS = ("flip_average", "empty_offset", "fill_columns", "fill_threshold", "first_hit_label")
"""Version 1 model keys that are inference rules now (:class:`fruxel.train.rules.InferenceRules`)."""
REMOVED_MODEL_KEYS = {"image_branch": 0, "lift": "depth", "upsample": "parity", "full_res_spatial": False,
                      "group_width": 1, "surface_fusion": True, "fine_depth": 0, "refine_scale": 2,
                      "refine_frozen": False}
"""Version 1 model keys that are gone, with the value every current network has."""
OLD_SSZ64_DETAIL_BRANCH = 0
"""``model.detail_branch`` of version 1's ``ssz64`` preset (version 2's rebuilds the shipped model: 24)."""


def split_model(model: Mapping[str, Any], where: str) -> tuple[dict[str, Any], dict[str, Any]]:
    """A version 1 model section as ``(model section of version 2, inference rules)``, the discriminator's
    channels left in the model section under ``"discriminator"`` for the caller to move.

    Args:
        model: the version 1 ``model`` object (partial or complete).
        where: the file or key, for messages.

    Raises:
        ConfigError: a removed setting used with another value than the current network's.
    """
    if not isinstance(model, Mapping):
        raise ConfigError(f"{where}: model must be a JSON object, got {type(model).__name__}")
    out, rules = {}, {}
    for key, value in model.items():
        if key in RULE_KEYS:
            rules[key] = value
        elif key in REMOVED_MODEL_KEYS:
            if value != REMOVED_MODEL_KEYS[key]:
                raise ConfigError(f"{where}: model.{key} = {value!r} was removed from fruxel (no shipped model used "
                                  f"it; docs/experiments.md); only {REMOVED_MODEL_KEYS[key]!r} can be read")
        else:
            out[key] = value
    return out, rules


def upgrade_config(d: Mapping[str, Any]) -> dict[str, Any]:
    """A training config of version 1 (without its ``"version"`` key) as one of version 2.

    Raises:
        ConfigError: see :func:`split_model`; version 1's ``paper`` preset.
    """
    d = {k: dict(v) if isinstance(v, Mapping) else v for k, v in d.items()}
    if d.get("preset") == "paper":
        raise ConfigError("config version 1 preset 'paper' no longer exists (ssz128 is the 128^3 preset now)")
    model, _ = split_model(d.get("model", {}), "config version 1")
    if d.get("preset") == "ssz64":
        model.setdefault("detail_branch", OLD_SSZ64_DETAIL_BRANCH)
    loss = dict(d.get("loss", {}))
    if "discriminator" in model:
        loss["discriminator"] = model.pop("discriminator")
    shell = {}
    for old, new in (("shell_views", "novel_views"), ("shell_own_view", "weight_own_view")):
        if old in loss:
            shell[new] = loss.pop(old)
    if "shell_view_size" in loss:
        n = loss.pop("shell_view_size")
        shell["novel_size"] = [n, n]
    # Version 1 drew the shell losses' poses from run.seed.
    run = d.get("run", {})
    if isinstance(run, Mapping) and "seed" in run:
        shell["seed"] = run["seed"]
    loss.pop("fine_depth", None)
    if shell:
        loss["shell_losses"] = shell
    if model:
        d["model"] = model
    else:
        d.pop("model", None)
    if loss:
        d["loss"] = loss
    return d

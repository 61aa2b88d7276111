"""The refinement level (``SSZConfig.refine``): a decoder level that doubles a trained model's output grid.

A fresh level loaded with the coarse model's weights (``run.init``) repeats the coarse model's answer on the fine
cells; the split of the column depth distribution; the config checks; the shipped file; and a real CPU training
run on top of a coarse model given by ``run.init``.

Everything uses :data:`.test_engine.TINY`'s 16^3 grid from 32^2 images with three levels: with ``refine`` the
network below works at 8^3 from the image averaged to 16^2.
"""

from __future__ import annotations

import copy
import csv
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("torch_one_thread")

import torch.nn.functional as F  # noqa: E402
from torch import nn  # noqa: E402

from fruxel.errors import ConfigError  # noqa: E402
from fruxel.train.config import TrainConfig  # noqa: E402
from fruxel.train.engine.checkpoint import LATEST, read_checkpoint  # noqa: E402
from fruxel.train.engine.run_folder import SHIPPED  # noqa: E402
from fruxel.train.engine.trainer import Trainer  # noqa: E402
from fruxel.train.model_files import load_model, save_model  # noqa: E402
from fruxel.train.models.generator import SSZGenerator, split_depth_logits  # noqa: E402
from fruxel.train.models.ssz import SSZConfig  # noqa: E402

from .test_engine import tiny  # noqa: E402

COARSE = {"grid": {"width": 8, "height": 8, "depth": 8}}
"""Model changes of :func:`.test_engine.tiny` for the coarse model: the grid below a refined 16^3 one."""


def _coarse(changes: dict[str, Any] | None = None) -> TrainConfig:
    return tiny({"model": COARSE | (changes or {})})


def _refined(changes: dict[str, Any] | None = None, **more: Any) -> TrainConfig:
    """:func:`.test_engine.tiny` (16^3 grid) with an 8-channel refinement level and ``changes`` to the model."""
    return tiny({"model": {"refine": 8} | (changes or {}), **more})


def _batch_norms(model: nn.Module) -> dict[str, nn.modules.batchnorm._BatchNorm]:
    return {n: m for n, m in model.named_modules() if isinstance(m, nn.modules.batchnorm._BatchNorm)}


def _woken(model: SSZGenerator, seed: int = 7) -> SSZGenerator:
    """``model`` with every parameter moved off its initialisation (the zero-started heads and projections
    included) and BatchNorm statistics that are not the identity's, so that running a part in the wrong mode, on
    the wrong image or not at all shows in its output; in eval mode."""
    gen = torch.Generator().manual_seed(seed)
    with torch.no_grad():
        for p in model.parameters():
            p.add_(0.1 * torch.randn(p.shape, generator=gen))
        for bn in _batch_norms(model).values():
            bn.running_mean.copy_(0.2 * torch.randn(bn.running_mean.shape, generator=gen))
            bn.running_var.copy_(0.5 + 1.5 * torch.rand(bn.running_var.shape, generator=gen))
    return model.eval()


def _repeat(x: torch.Tensor) -> torch.Tensor:
    """Each cell of ``(B, C, D, H, W)`` repeated 2 x 2 x 2."""
    return x.repeat_interleave(2, 2).repeat_interleave(2, 3).repeat_interleave(2, 4)


# ---------------------------------------------------------------------------------------------- starting point
@pytest.mark.parametrize("detail_branch", [0, 4])
def test_a_fresh_level_on_a_coarse_model_repeats_its_answer(tmp_path: Path, detail_branch: int) -> None:
    """``run.init`` with a model of the grid halved: every weight but the level's is taken, and the refined model
    is the coarse one on the image averaged over 2 x 2 pixels, each cell repeated 2 x 2 x 2, each column's slice
    split in two halves, each column's surface class repeated 2 x 2. Once the level's zero-started heads are not
    zero, each of them changes its output."""
    extra = {"detail_branch": detail_branch} if detail_branch else {}
    coarse_cfg = _coarse(extra)
    torch.manual_seed(3)
    coarse = _woken(coarse_cfg.model.build())
    path = tmp_path / "coarse.safetensors"
    save_model(path, coarse, coarse_cfg.model, half=False)
    config = _refined(extra, run={"init": str(path)})
    assert config.model.image_size == tuple(2 * n for n in coarse_cfg.model.image_size)
    state, _ = Trainer(config, tmp_path / "run", device="cpu", progress=False).build()
    fine = state.network
    assert fine.grid_shape == (16, 16, 16) and fine.base_shape == (8, 8, 8)
    got, want = fine.state_dict(), coarse.state_dict()
    fresh = sorted(k for k in got if k not in want)
    assert fresh and all(k.startswith("refine.") for k in fresh) and not [k for k in want if k not in got]
    for k, v in want.items():
        assert torch.equal(got[k], v), k
    fine.eval()
    image = torch.rand(2, 3, *config.model.image_size)
    with torch.no_grad():
        a = coarse(F.avg_pool2d(image, 2))
        b = fine(image)
    assert b.logits.shape == (2, 7, 16, 16, 16) and b.depth_logits.shape == (2, 17, 16, 16)
    assert b.surface_logits.shape == (2, 7, 16, 16)
    torch.testing.assert_close(b.logits, _repeat(a.logits))
    torch.testing.assert_close(b.depth_logits, split_depth_logits(a.depth_logits))
    torch.testing.assert_close(b.surface_logits, F.interpolate(a.surface_logits, scale_factor=2.0, mode="nearest"))
    # The woken BatchNorms matter: the coarse model in training mode (batch statistics) answers otherwise.
    with torch.no_grad():
        assert (copy.deepcopy(coarse).train()(F.avg_pool2d(image, 2)).logits - a.logits).abs().max() > 1e-2
    # Each correction is wired to its output.
    for head, field in (("head", "logits"), ("depth_head", "depth_logits"), ("surface_head", "surface_logits")):
        with torch.no_grad():
            getattr(fine.refine, head).weight.normal_()
            c = fine(image)
        assert (getattr(c, field) - getattr(b, field)).abs().max() > 1e-3, head


def test_split_depth_logits_halves_each_slice_and_repeats_each_column() -> None:
    torch.manual_seed(0)
    d = 5
    logits = 3.0 * torch.randn(2, d + 1, 3, 4)
    out = split_depth_logits(logits.to(torch.bfloat16))
    assert out.shape == (2, 2 * d + 1, 6, 8) and out.dtype == torch.float32
    out = split_depth_logits(logits)
    p, q = torch.softmax(logits, 1), out.exp()
    torch.testing.assert_close(q.sum(1), torch.ones(2, 6, 8))
    torch.testing.assert_close(torch.log_softmax(out, 1), out)  # already log-probabilities
    for i in range(2):
        for j in range(2):
            sub = q[:, :, i::2, j::2]  # one of each column's 2 x 2 sub-columns
            torch.testing.assert_close(sub[:, 0:-1:2], p[:, :-1] / 2)  # front halves
            torch.testing.assert_close(sub[:, 1:-1:2], p[:, :-1] / 2)  # back halves
            torch.testing.assert_close(sub[:, -1], p[:, -1])  # no surface
            torch.testing.assert_close(out[:, :, i::2, j::2], out[:, :, ::2, ::2])
    # The expected first-surface depth (in coarse slices, of the slices' centres) is kept.
    centre = torch.arange(d).view(1, d, 1, 1) + 0.5
    fine_centre = (torch.arange(2 * d).view(1, 2 * d, 1, 1) + 0.5) / 2
    torch.testing.assert_close((q[:, :-1] * fine_centre).sum(1)[:, ::2, ::2], (p[:, :-1] * centre).sum(1))


# ---------------------------------------------------------------------------------------------- config
def test_refine_config_is_checked() -> None:
    base = _refined().model
    assert base.image_size == (32, 32)
    with pytest.raises(ConfigError, match="model.refine must be an integer >= 0"):
        SSZConfig(refine=-1)
    # 12^3 holds three levels (2^2) but not three levels and the refinement level below them (2^3).
    grid12 = {"grid": {"width": 12, "height": 12, "depth": 12}}
    assert tiny({"model": grid12}).model.refine == 0
    with pytest.raises(ConfigError, match=r"model.grid 12x12x12 must be divisible by .* = 8"):
        _refined(grid12)


def test_the_refined_model_wants_the_full_image() -> None:
    model = _refined().model.build().eval()
    with torch.no_grad():
        assert model(torch.rand(1, 3, 32, 32)).logits.shape == (1, 7, 16, 16, 16)
        with pytest.raises(ValueError, match=r"image must be \(B, 3, 32, 32\), got \(1, 3, 16, 16\)"):
            model(torch.rand(1, 3, 16, 16))


# ---------------------------------------------------------------------------------------------- shipped file
def test_shipped_refined_model_round_trip(tmp_path: Path) -> None:
    config = _refined().model
    torch.manual_seed(1)
    model = _woken(config.build())
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        want = model(image)
    for half in (False, True):
        path = tmp_path / f"half{half}.safetensors"
        save_model(path, model, config, training={"step": 3}, half=half)
        loaded = load_model(path)
        assert loaded.config.refine == 8 and loaded.config == config
        assert loaded.training == {"step": 3} and not loaded.network.training and loaded.network.refine is not None
        with torch.no_grad():
            got = loaded.network(image)
        for field in ("logits", "depth_logits", "surface_logits"):
            a, b = getattr(got, field), getattr(want, field)
            if half:  # float16 weights: close, not equal
                torch.testing.assert_close(a, b, atol=0.05 * float(b.abs().max()), rtol=0.05)
            else:
                assert torch.equal(a, b), field


# ---------------------------------------------------------------------------------------------- training
@pytest.mark.slow
def test_training_a_refined_model_from_a_coarse_one(tmp_path: Path) -> None:
    """A real CPU run (the streamed simulator, 16^3 grid): ``run.init`` gives the coarse model, the whole network
    learns with its new level. The loss falls, every weight moves (the level's zero-started heads included), and
    the shipped model reads back as the refined architecture."""
    coarse_cfg = _coarse()
    torch.manual_seed(2)
    coarse = _woken(coarse_cfg.model.build())
    path = tmp_path / "coarse.safetensors"
    save_model(path, coarse, coarse_cfg.model, half=False)
    steps = 24
    config = _refined(run={"init": str(path), "steps": steps, "eval_every": 12}, optim={"lr": 1e-2})
    result = Trainer(config, tmp_path / "run", device="cpu", progress=False).fit()
    assert result.step == steps
    with open(tmp_path / "run" / "metrics.csv", newline="") as f:
        losses = [float(r["loss/total"]) for r in csv.DictReader(f) if r.get("loss/total")]
    assert len(losses) == steps and all(math.isfinite(v) for v in losses)
    # The streamed samples differ from step to step: the halves of the run are compared.
    assert np.mean(losses[steps // 2:]) < 0.9 * np.mean(losses[:steps // 2]), losses
    state = read_checkpoint(tmp_path / "run" / LATEST).state["generator"]
    moved = [k for k, v in coarse.state_dict().items() if v.is_floating_point() and not torch.equal(state[k], v)]
    assert moved and {"refine.head.weight", "refine.depth_head.weight", "refine.surface_head.weight"} <= {
        k for k in state if k.startswith("refine.") and state[k].abs().sum() > 0}
    loaded = load_model(tmp_path / "run" / SHIPPED)
    assert loaded.config.refine == 8 and loaded.network.grid_shape == (16, 16, 16)
    assert loaded.network.base_shape == (8, 8, 8)

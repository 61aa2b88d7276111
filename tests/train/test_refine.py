"""The refinement level (``ModelConfig.refine``): a decoder level that doubles a trained model's output grid.

A fresh level loaded with the coarse model's weights (``run.init``) repeats the coarse model's answer on the fine
cells; the split of the column depth distribution; freezing the network below the level (gradients, BatchNorm
modes and statistics, the optimiser's parameters); the config checks; the shipped file; and a real CPU training
run of the level alone on top of a coarse model given by ``run.init``.

Everything uses :data:`.test_engine.TINY`'s 16^3 grid from 32^2 images with three levels: with ``refine`` the
network below works at 8^3 from the image averaged to 16^2.
"""

from __future__ import annotations

import copy
import csv
import dataclasses
import math
from pathlib import Path
from typing import Any

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("torch_one_thread")

import torch.nn.functional as F  # noqa: E402
from torch import nn  # noqa: E402

from fruxel.train.config import ConfigError, ModelConfig, TrainConfig  # noqa: E402
from fruxel.train.engine.checkpoint import LATEST, read_checkpoint  # noqa: E402
from fruxel.train.engine.trainer import SHIPPED, Trainer, _param_groups  # noqa: E402
from fruxel.train.export import build_generator, load_generator, save_shipped  # noqa: E402
from fruxel.train.models.generator import SSZGenerator, split_depth_logits  # noqa: E402

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


def _buffers(model: nn.Module, refine: bool) -> dict[str, torch.Tensor]:
    """Copies of the buffers (BatchNorm statistics) of the refinement level (``refine``) or of the rest."""
    return {k: v.clone() for k, v in model.named_buffers() if k.startswith("refine.") == refine}


def _repeat(x: torch.Tensor) -> torch.Tensor:
    """Each cell of ``(B, C, D, H, W)`` repeated 2 x 2 x 2."""
    return x.repeat_interleave(2, 2).repeat_interleave(2, 3).repeat_interleave(2, 4)


# ---------------------------------------------------------------------------------------------- starting point
@pytest.mark.parametrize(("detail_branch", "frozen", "scale"),
                         [(0, False, 2), (0, True, 2), (4, False, 2), (0, True, 1), (4, False, 1)])
def test_a_fresh_level_on_a_coarse_model_repeats_its_answer(tmp_path: Path, detail_branch: int,
                                                            frozen: bool, scale: int) -> None:
    """``run.init`` with a model of the grid halved: every weight but the level's is taken, and the refined model
    is the coarse one on the image averaged over 2 x 2 pixels, each cell repeated 2 x 2 x 2, each column's slice
    split in two halves, each column's surface class repeated 2 x 2. With ``refine_scale`` 1 the model below has
    the same grid and the refined model is exactly its answer on the averaged image. Once the level's
    zero-started heads are not zero, each of them changes its output."""
    extra = {"detail_branch": detail_branch} if detail_branch else {}
    coarse_cfg = _coarse(extra) if scale == 2 else tiny({"model": extra})
    torch.manual_seed(3)
    coarse = _woken(build_generator(coarse_cfg.model))
    path = tmp_path / "coarse.safetensors"
    save_shipped(path, coarse, coarse_cfg.model, half=False)
    config = _refined({"refine_frozen": frozen, "refine_scale": scale} | extra, run={"init": str(path)})
    assert config.model.image_size == tuple(2 * n for n in coarse_cfg.model.image_size)
    trainer = Trainer(config, tmp_path / "run", device="cpu", progress=False)
    trainer._build()
    fine = trainer.generator
    n = 16 // scale
    assert fine.grid_shape == (16, 16, 16) and fine.base_shape == (n, n, n)
    got, want = fine.state_dict(), coarse.state_dict()
    fresh = sorted(k for k in got if k not in want)
    assert fresh and all(k.startswith("refine.") for k in fresh) and not [k for k in want if k not in got]
    for k, v in want.items():
        assert torch.equal(got[k], v), k
    fine.eval()
    image = torch.rand(2, 3, *config.model.image_size)
    with torch.no_grad():
        a = coarse(F.avg_pool2d(image, 2), rules=False)
        b = fine(image, rules=False)
    assert b.logits.shape == (2, 7, 16, 16, 16) and b.depth_logits.shape == (2, 17, 16, 16)
    assert b.surface_logits.shape == (2, 7, 16, 16) and b.fine_logits is None
    if scale == 2:
        torch.testing.assert_close(b.logits, _repeat(a.logits))
        torch.testing.assert_close(b.depth_logits, split_depth_logits(a.depth_logits))
        torch.testing.assert_close(b.surface_logits, F.interpolate(a.surface_logits, scale_factor=2.0, mode="nearest"))
    else:
        for field in ("logits", "depth_logits", "surface_logits"):
            assert torch.equal(getattr(b, field), getattr(a, field)), field
    # The woken BatchNorms matter: the coarse model in training mode (batch statistics) answers otherwise.
    with torch.no_grad():
        assert (copy.deepcopy(coarse).train()(F.avg_pool2d(image, 2)).logits - a.logits).abs().max() > 1e-2
    # Each correction is wired to its output.
    for head, field in (("head", "logits"), ("depth_head", "depth_logits"), ("surface_head", "surface_logits")):
        with torch.no_grad():
            getattr(fine.refine, head).weight.normal_()
            c = fine(image, rules=False)
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


# ---------------------------------------------------------------------------------------------- freezing
def test_refine_frozen_trains_only_the_level() -> None:
    torch.manual_seed(0)
    model = _woken(build_generator(_refined({"refine_frozen": True}).model))
    with torch.no_grad():  # the level's corrections back at zero (see below)
        for head in (model.refine.head, model.refine.depth_head, model.refine.surface_head):
            head.weight.zero_()
            head.bias.zero_()
    model.train()
    assert model.refine_frozen
    for name, p in model.named_parameters():
        assert p.requires_grad == name.startswith("refine."), name
    modes = {n: m.training for n, m in model.named_modules() if n}
    assert model.training and all(v == n.startswith("refine") for n, v in modes.items()), modes
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        ref = model.eval()(image, rules=False)
    model.train()
    frozen, level = _buffers(model, False), _buffers(model, True)
    out = model(image)
    # The network below reads its running statistics in training mode too: with the level's corrections still
    # zero, the training pass is the eval pass.
    torch.testing.assert_close(out.logits, ref.logits)
    torch.testing.assert_close(out.depth_logits, ref.depth_logits)
    (out.logits.square().mean() + out.depth_logits.square().mean() + out.surface_logits.square().mean()).backward()
    for name, p in model.named_parameters():
        assert (p.grad is not None) == name.startswith("refine."), name
    for head in (model.refine.head, model.refine.depth_head, model.refine.surface_head):
        assert head.weight.grad.abs().sum() > 0
    for k, v in _buffers(model, False).items():
        assert torch.equal(v, frozen[k]), k
    assert any(not torch.equal(v, level[k]) for k, v in _buffers(model, True).items())
    # The optimiser is given the level's parameters only.
    groups = _param_groups(model, 0.01)
    assert sorted(id(p) for g in groups for p in g["params"]) == sorted(id(p) for p in model.refine.parameters())


def test_a_freshly_built_frozen_model_keeps_the_rest_in_eval_mode() -> None:
    """The trainer never calls ``.train()`` on the generator it builds (modules are built in training mode): a
    frozen model must start with the network below the level in eval mode."""
    model = build_generator(_refined({"refine_frozen": True}).model)
    assert model.training and model.refine.training
    assert all(not m.training for n, m in model.named_modules() if n and not n.startswith("refine")), \
        [n for n, m in model.named_modules() if n and not n.startswith("refine") and m.training]


def test_without_refine_frozen_everything_trains() -> None:
    torch.manual_seed(0)
    model = _woken(build_generator(_refined().model)).train()
    assert not model.refine_frozen and all(m.training for m in model.modules())
    assert all(p.requires_grad for p in model.parameters())
    before = _buffers(model, False)
    out = model(torch.rand(2, 3, 32, 32))
    (out.logits.square().mean() + out.depth_logits.square().mean() + out.surface_logits.square().mean()).backward()
    missing = [n for n, p in model.named_parameters() if p.grad is None]
    assert not missing, missing
    assert model.stem[0].weight.grad.abs().sum() > 0 and model.head.weight.grad.abs().sum() > 0
    assert model.depth_head.weight.grad.abs().sum() > 0
    assert not torch.equal(model.stem[1].running_mean, before["stem.1.running_mean"])
    assert sum(len(g["params"]) for g in _param_groups(model, 0.01)) == len(list(model.parameters()))


# ---------------------------------------------------------------------------------------------- config
def test_refine_config_is_checked() -> None:
    base = _refined().model
    base.check()
    with pytest.raises(ConfigError, match="model.refine"):
        ModelConfig(refine=-1).check()
    with pytest.raises(ConfigError, match="model.refine needs model.lift = 'depth', got 'copy'"):
        dataclasses.replace(base, lift="copy", surface_fusion=False).check()
    with pytest.raises(ConfigError, match="model.refine and model.fine_depth"):
        dataclasses.replace(base, fine_depth=4).check()
    with pytest.raises(ConfigError, match="model.refine_frozen needs model.refine"):
        dataclasses.replace(base, refine=0, refine_frozen=True).check()
    for bad in (0, 3, True):
        with pytest.raises(ConfigError, match=f"model.refine_scale must be 1 or 2, got {bad!r}"):
            dataclasses.replace(base, refine_scale=bad).check()
    with pytest.raises(ConfigError, match="model.refine_scale needs model.refine"):
        dataclasses.replace(base, refine=0, refine_scale=1).check()
    same = dataclasses.replace(base, refine_scale=1)
    same.check()  # 16^3 with three levels: the level adds no halving at scale 1
    assert same.image_size == (64, 64) and base.image_size == (32, 32)
    with pytest.raises(ValueError, match="refine_scale must be 1 or 2, got 3"):
        build_generator(dataclasses.replace(base, refine_scale=3))
    # 12^3 holds three levels (2^2) but not three levels and the refinement level below them (2^3).
    grid12 = dataclasses.replace(base, grid=dataclasses.replace(base.grid, width=12, height=12, depth=12))
    dataclasses.replace(grid12, refine=0).check()
    with pytest.raises(ConfigError, match=r"model.grid 12x12x12 must be divisible by .* = 8"):
        grid12.check()
    # The generator's own checks.
    with pytest.raises(ValueError, match="divisible by 8"):
        build_generator(grid12)
    with pytest.raises(ValueError, match="refine must be >= 0"):
        build_generator(dataclasses.replace(base, refine=-1))
    with pytest.raises(ValueError, match="refine and fine_depth cannot be combined"):
        build_generator(dataclasses.replace(base, fine_depth=4))
    with pytest.raises(ValueError, match="refine needs lift='depth'"):
        build_generator(dataclasses.replace(base, lift="copy", surface_fusion=False))


@pytest.mark.parametrize("scale", [2, 1])
def test_the_refined_model_wants_the_full_image(scale: int) -> None:
    model = build_generator(_refined({"refine_scale": scale}).model).eval()
    n = 64 // scale
    with torch.no_grad():
        assert model(torch.rand(1, 3, n, n)).logits.shape == (1, 7, 16, 16, 16)
        with pytest.raises(ValueError, match=rf"image must be \(B, 3, {n}, {n}\), got \(1, 3, 16, 16\)"):
            model(torch.rand(1, 3, 16, 16))


# ---------------------------------------------------------------------------------------------- shipped file
@pytest.mark.parametrize("frozen", [False, True])
def test_shipped_refined_model_round_trip(tmp_path: Path, frozen: bool) -> None:
    config = _refined({"refine_frozen": frozen}).model
    torch.manual_seed(1)
    model = _woken(build_generator(config))
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        want = model(image)
    for half in (False, True):
        path = tmp_path / f"half{half}.safetensors"
        save_shipped(path, model, config, {"step": 3}, half=half)
        loaded, got_config, training = load_generator(path)
        assert got_config.refine == 8 and got_config.refine_frozen == frozen and got_config == config
        assert training == {"step": 3} and not loaded.training and loaded.refine is not None
        assert loaded.refine_frozen == frozen
        with torch.no_grad():
            got = loaded(image)
        for field in ("logits", "depth_logits", "surface_logits"):
            a, b = getattr(got, field), getattr(want, field)
            if half:  # float16 weights: close, not equal
                torch.testing.assert_close(a, b, atol=0.05 * float(b.abs().max()), rtol=0.05)
            else:
                assert torch.equal(a, b), field


# ---------------------------------------------------------------------------------------------- training
@pytest.mark.parametrize("scale", [2, 1])
def test_training_the_frozen_level_on_a_coarse_model(tmp_path: Path, scale: int) -> None:
    """A real CPU run (the streamed simulator, 16^3 grid): ``run.init`` gives the coarse model, only the level
    learns. The loss falls, the level's weights move, and the coarse model's weights and BatchNorm statistics come
    out bit for bit as they went in, a mid-run evaluation (eval mode, then back to training) included. With
    ``refine_scale`` 1 the model below has the level's grid and the level reads an image twice as large."""
    coarse_cfg = _coarse() if scale == 2 else tiny()
    torch.manual_seed(2)
    coarse = _woken(build_generator(coarse_cfg.model))
    path = tmp_path / "coarse.safetensors"
    save_shipped(path, coarse, coarse_cfg.model, half=False)
    steps = 24
    config = _refined({"refine_frozen": True, "refine_scale": scale},
                      run={"init": str(path), "steps": steps, "eval_every": 12},
                      optim={"lr": 1e-2})
    result = Trainer(config, tmp_path / "run", device="cpu", progress=False).fit()
    assert result.step == steps
    with open(tmp_path / "run" / "metrics.csv", newline="") as f:
        losses = [float(r["loss/total"]) for r in csv.DictReader(f) if r.get("loss/total")]
    assert len(losses) == steps and all(math.isfinite(v) for v in losses)
    # The streamed samples differ from step to step: the halves of the run are compared.
    assert np.mean(losses[steps // 2:]) < 0.9 * np.mean(losses[:steps // 2]), losses
    state = read_checkpoint(tmp_path / "run" / LATEST).state["generator"]
    want = coarse.state_dict()
    assert sorted(k for k in state if k not in want) == sorted(k for k in state if k.startswith("refine."))
    for k, v in want.items():
        assert torch.equal(state[k], v), k
    torch.manual_seed(config.run.seed)  # the initialisation the trainer starts the level from
    fresh = {k: v for k, v in build_generator(config.model).named_parameters() if k.startswith("refine.")}
    moved = [k for k, v in fresh.items() if not torch.equal(state[k], v)]
    assert {"refine.head.weight", "refine.depth_head.weight", "refine.surface_head.weight"} <= set(moved)
    assert len(moved) == len(fresh), sorted(set(fresh) - set(moved))
    loaded, got_config, _ = load_generator(tmp_path / "run" / SHIPPED)
    assert got_config.refine == 8 and got_config.refine_frozen and loaded.grid_shape == (16, 16, 16)
    assert got_config.refine_scale == scale and loaded.base_shape == (16 // scale,) * 3

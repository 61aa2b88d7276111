"""SSZ's building blocks: those that replace a PyTorch layer by a faster computation of the same function, and the
surface fusion that writes the image-side heads' answer into the logits."""

from __future__ import annotations

import dataclasses
import math

import pytest
import torch
from torch import nn

from fruxel.classes import DEFAULT_CLASSES
from fruxel.errors import ConfigError
from fruxel.grid import FruxelGrid
from fruxel.train.models.blocks import Pointwise3d, SurfaceFusion
from fruxel.train.models.registry import ModelOutput, architecture, architectures, model_config_from_dict
from fruxel.train.models.ssz import SSZConfig


def small_config(**kw: object) -> SSZConfig:
    """A 16^3 SSZ from 32^2 images with a few thousand weights."""
    grid = FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0)
    base = {"grid": grid, "classes": DEFAULT_CLASSES, "levels": 3, "stem": 8, "encoder": (8, 8, 8),
            "encoder_blocks": (1, 1, 1), "topdown": (8, 8, 8), "decoder": (8, 8, 8), "decoder_blocks": (1, 1, 1)}
    return SSZConfig(**{**base, **kw})


def _wake_zero_started_branch(model: nn.Module, branch: nn.Sequential, image: torch.Tensor) -> None:
    """Check that a branch whose last BatchNorm starts at zero gets a gradient through it from one training pass on
    ``image``, then set that BatchNorm's weight to one and put ``model`` back in eval mode."""
    model.train()
    model(image).logits.square().mean().backward()
    last = branch[-1]
    assert last.weight.grad.abs().sum() > 0
    with torch.no_grad():
        last.weight.fill_(1.0)
    model.eval()


@pytest.mark.parametrize("bias", [True, False])
@pytest.mark.parametrize("layout", ["contiguous", "channels_last", "strided"])
def test_pointwise3d_is_the_1x1x1_convolution(bias: bool, layout: str) -> None:
    torch.manual_seed(0)
    pw = Pointwise3d(5, 3, bias=bias).double()
    torch.manual_seed(0)
    conv = nn.Conv3d(5, 3, 1, bias=bias).double()
    # Same initialisation and state-dict keys: models saved with Conv3d load into it.
    assert pw.state_dict().keys() == conv.state_dict().keys()
    for k, v in conv.state_dict().items():
        assert torch.equal(pw.state_dict()[k], v)
    x = torch.randn(2, 5, 4, 3, 6, dtype=torch.float64)
    if layout == "channels_last":
        x = x.contiguous(memory_format=torch.channels_last_3d)
    elif layout == "strided":
        x = torch.randn(2, 5, 4, 3, 12, dtype=torch.float64)[..., ::2]
    xa, xb = x.clone().requires_grad_(), x.clone().requires_grad_()
    ya, yb = pw(xa), conv(xb)
    torch.testing.assert_close(ya, yb)
    if layout == "channels_last":
        assert ya.is_contiguous(memory_format=torch.channels_last_3d)
    g = torch.randn_like(ya)
    ya.backward(g)
    yb.backward(g)
    torch.testing.assert_close(xa.grad, xb.grad)
    torch.testing.assert_close(pw.weight.grad, conv.weight.grad)
    if bias:
        torch.testing.assert_close(pw.bias.grad, conv.bias.grad)


def test_pointwise3d_keeps_the_autocast_dtype() -> None:
    pw = Pointwise3d(4, 2)
    x = torch.randn(1, 4, 2, 2, 2)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        y = pw(x)
        want = nn.functional.conv3d(x, pw.weight, pw.bias)
    assert y.dtype == want.dtype == torch.bfloat16


def test_surface_fusion_features_by_hand() -> None:
    """A column sure of its surface at slice 2 with class 3, and a column sure there is none, 5 slices deep."""
    d, classes = 5, 4
    depth = torch.full((1, d + 1, 1, 2), -30.0)
    depth[0, 2, 0, 0] = 30.0  # column 0: surface at slice 2
    depth[0, d, 0, 1] = 30.0  # column 1: no surface
    surface = torch.full((1, classes, 1, 2), -30.0)
    surface[0, 3, 0, 0] = 30.0
    surface[0, 0, 0, 1] = 30.0
    f = SurfaceFusion(classes).features(depth, surface)
    assert f.shape == (1, classes + 2, d, 1, 2) and f.dtype == torch.float32
    lo = math.log(SurfaceFusion.FLOOR)
    col = f[0, :, :, 0, 0]  # (C + 1, D)
    sure, never = 0.0, lo
    # In front of the surface (slices 0, 1): front is sure; behind is not.
    torch.testing.assert_close(col[0], torch.tensor([sure, sure, never, never, never]), atol=1e-5, rtol=0)
    torch.testing.assert_close(col[1], torch.tensor([never, never, never, sure, sure]), atol=1e-5, rtol=0)
    # The column's most likely slice is 2.
    torch.testing.assert_close(col[2], torch.tensor([never, never, sure, never, never]), atol=1e-5, rtol=0)
    # "Here, class c" is sure only at slice 2 for class 3 (feature 3 + c - 1); floored twice elsewhere.
    here3 = col[3 + 3 - 1]
    assert here3[2].abs() < 1e-5 and (here3[[0, 1, 3, 4]] <= lo + 1e-5).all()
    assert (col[3] <= lo + 1e-5).all() and (col[4] <= lo + 1e-5).all()
    # No surface: every slice is in front of it, none behind, none here; the (equal) slices are all modes.
    empty = f[0, :, :, 0, 1]
    torch.testing.assert_close(empty[0], torch.zeros(d), atol=1e-5, rtol=0)
    torch.testing.assert_close(empty[2], torch.zeros(d), atol=1e-5, rtol=0)
    assert (empty[1] <= lo + 1e-5).all() and (empty[3:] <= lo + 1e-5).all() and (empty >= 2 * lo - 1e-5).all()


def test_surface_fusion_marks_the_most_likely_slice_of_an_unsure_column() -> None:
    """A column spread over every slice (a plain wall at an unknown distance) still has one slice at 0."""
    depth = torch.zeros(1, 9, 1, 1)
    depth[0, 5] = 0.5
    f = SurfaceFusion(3).features(depth, torch.zeros(1, 3, 1, 1))
    mode = f[0, 2, :, 0, 0]
    assert mode[5].abs() < 1e-6 and (mode[[0, 1, 2, 3, 4, 6, 7]] < -0.4).all()
    # ... where no slice holds even a fifth of the probability.
    assert (torch.softmax(depth, dim=1) < 0.2).all()


def test_surface_fusion_starts_as_the_decoder_alone_and_learns() -> None:
    """The fusion's mix starts at zero: the logits are the decoder's own until it learns, and it gets a gradient;
    once it is not zero, the heads get one through it."""
    torch.manual_seed(0)
    fused = small_config().build()
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        t = fused.encode(image)
        depth = fused.depth_head(t[0]).float()
        assert not fused.fusion(depth, fused.surface_head(t[0]).float()).any()
    out = fused(image)
    out.logits.square().mean().backward()
    assert fused.fusion.mix.weight.grad.abs().sum() > 0
    with torch.no_grad():
        fused.fusion.mix.weight.normal_()
    fused.zero_grad()
    fused(image).logits.square().mean().backward()
    assert fused.surface_head.weight.grad.abs().sum() > 0


def test_the_network_honours_the_output_contract() -> None:
    """forward is the network alone: a ModelOutput with the logits and both column heads, the same in train and
    eval mode but for batch normalisation, and no rule applied (the argmax of a fresh model is its own)."""
    cfg = small_config()
    net = cfg.build().eval()
    out = net(torch.rand(2, 3, *cfg.image_size))
    assert isinstance(out, ModelOutput)
    assert out.logits.shape == (2, cfg.num_classes, *cfg.grid.shape)
    assert out.depth_logits.shape == (2, cfg.grid.depth + 1, cfg.grid.height, cfg.grid.width)
    assert out.surface_logits.shape == (2, cfg.num_classes, cfg.grid.height, cfg.grid.width)
    assert out.depth_logits.dtype == out.surface_logits.dtype == torch.float32
    assert net.image_size == cfg.image_size


def test_the_architecture_registry_builds_by_name() -> None:
    """A config names its architecture; the registry gives its class back, and a model config read from JSON
    builds the same network."""
    assert "ssz" in architectures() and architecture("ssz") is SSZConfig
    cfg = small_config(detail_branch=4)
    from fruxel.train.models.registry import model_config_to_dict

    d = model_config_to_dict(cfg)
    assert d["architecture"] == "ssz" and model_config_from_dict(d) == cfg
    with pytest.raises(ConfigError, match="unknown model.architecture 'nope'"):
        model_config_from_dict({"architecture": "nope"})
    torch.manual_seed(0)
    a = cfg.build().state_dict()
    torch.manual_seed(0)
    b = model_config_from_dict(d).build().state_dict()
    assert a.keys() == b.keys() and all(torch.equal(a[k], b[k]) for k in a)


@pytest.mark.parametrize("image_scale", [0, 1])
def test_detail_branch_reads_a_twice_larger_image_and_starts_as_the_model_on_the_pooled_image(
        image_scale: int) -> None:
    cfg = small_config(image_scale=image_scale)
    detailed_cfg = dataclasses.replace(cfg, detail_branch=4)
    assert detailed_cfg.image_size == (32 << image_scale, 32 << image_scale) == tuple(2 * n for n in cfg.image_size)
    torch.manual_seed(0)
    plain = cfg.build().eval()
    detailed = detailed_cfg.build().eval()
    missing, unexpected = detailed.load_state_dict(plain.state_dict(), strict=False)
    assert missing and all(k.startswith("detail_branch.") for k in missing) and not unexpected
    fine = torch.rand(2, 3, *detailed_cfg.image_size)
    pooled = torch.nn.functional.avg_pool2d(fine, 2)
    with torch.no_grad():
        torch.testing.assert_close(detailed(fine).logits, plain(pooled).logits)
    with pytest.raises(ValueError, match="image must be"):
        detailed(pooled)
    # Its last BatchNorm starts at zero but gets a gradient; once it is not zero, the finer image's content that the
    # pooled one does not hold changes the output.
    _wake_zero_started_branch(detailed, detailed.detail_branch, fine)
    with torch.no_grad():
        # Two images with the same 2 x 2 averages: only the branch can tell them apart.
        checker = torch.tensor([[0.1, -0.1], [-0.1, 0.1]]).repeat(fine.shape[2] // 2, fine.shape[3] // 2)
        other = (fine + checker).clamp(0, 1)
        other = other - torch.nn.functional.interpolate(torch.nn.functional.avg_pool2d(other - fine, 2),
                                                        scale_factor=2.0, mode="nearest")
        torch.testing.assert_close(torch.nn.functional.avg_pool2d(other, 2), pooled)
        assert (detailed(fine).logits - detailed(other).logits).abs().max() > 1e-3


@pytest.mark.parametrize(("changes", "words"), [
    ({"detail_branch": -1}, "model.detail_branch must be an integer >= 0"),
    ({"image_scale": 5}, r"model.image_scale must be an integer in \[0, 4\]"),
    ({"levels": 0}, "model.levels must be an integer >= 1"),
    ({"encoder": (8, 8)}, r"model.encoder needs one entry per level \(3\)"),
    ({"refine": 4, "levels": 5, "encoder": (8,) * 5, "encoder_blocks": (1,) * 5, "topdown": (8,) * 5,
      "decoder": (8,) * 5, "decoder_blocks": (1,) * 5}, r"divisible by 2\^levels"),
    ({"image_scale": True}, "model.image_scale must be an integer"),
])
def test_the_config_checks_itself_once_when_made(changes: dict[str, object], words: str) -> None:
    with pytest.raises(ConfigError, match=words):
        small_config(**changes)
    with pytest.raises(ConfigError, match=words):
        dataclasses.replace(small_config(), **changes)


def test_surface_fusion_forward_is_the_mix_of_its_features() -> None:
    """The forward pass never builds the C + 2 features; it must equal the 1x1x1 mix of them."""
    torch.manual_seed(0)
    fusion = SurfaceFusion(7)
    with torch.no_grad():
        fusion.mix.weight.normal_()
        fusion.mix.bias.normal_()
        fusion.mode.weight.normal_()
    depth, surface = torch.randn(2, 17, 4, 5) * 3, torch.randn(2, 7, 4, 5) * 3
    # The features' order: in front, behind, most likely slice, then here with each class.
    mix = fusion.mix.weight.view(7, 8)
    w = torch.cat([mix[:, :2], fusion.mode.weight.view(7, 1), mix[:, 2:]], dim=1)
    want = nn.functional.conv3d(fusion.features(depth, surface), w[..., None, None, None], fusion.mix.bias)
    got = fusion(depth, surface)
    assert got.shape == (2, 7, 16, 4, 5) and got.dtype == torch.float32
    torch.testing.assert_close(got, want, atol=1e-4, rtol=1e-5)
    # A model held in bfloat16 gets a bfloat16 term from float32 heads.
    got16 = fusion.to(torch.bfloat16)(depth, surface)
    assert got16.dtype == torch.bfloat16
    torch.testing.assert_close(got16.float(), want, atol=0.5, rtol=0.02)


def test_blocks_added_to_a_trained_network_start_as_the_identity() -> None:
    """A network grown by more blocks (2D encoder and 3D decoder) and started from a smaller one's weights (as
    ``run.init`` starts it) answers as the smaller one did: each fresh block is the identity, so a trained model can
    grow without losing what it learnt."""
    torch.manual_seed(0)
    small = small_config().build()
    with torch.no_grad():
        for p in small.parameters():  # "trained": no block is the identity any more
            p.add_(0.1 * torch.randn_like(p))
    small.eval()
    grown = small_config(encoder_blocks=(2, 2, 3), decoder_blocks=(1, 2, 2)).build().eval()
    missing, unexpected = grown.load_state_dict(small.state_dict(), strict=False)
    assert not unexpected
    assert any(".body." in k for k in missing)  # the new blocks are fresh
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        torch.testing.assert_close(grown(image).logits, small(image).logits)

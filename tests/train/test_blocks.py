"""SSZ's building blocks: those that replace a PyTorch layer by a faster computation of the same function, and the
surface fusion that writes the image-side heads' answer into the logits."""

from __future__ import annotations

import dataclasses
import itertools
import math

import pytest
import torch
from torch import nn

from fruxel.grid import FruxelGrid
from fruxel.train.config import ConfigError, ModelConfig
from fruxel.train.export import build_generator
from fruxel.train.models.blocks import Pointwise3d, SurfaceFusion
from fruxel.train.models.generator import (
    FILL_SURFACE_PROBABILITY,
    fill_columns,
    first_hit_classes,
    first_hit_label,
    first_hit_log_probs,
    inference_rules,
)


def _small_config(**kw: object) -> ModelConfig:
    grid = FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0)
    return ModelConfig(grid=grid, levels=3, stem=8, encoder=(8, 8, 8), encoder_blocks=(1, 1, 1), topdown=(8, 8, 8),
                       decoder=(8, 8, 8), decoder_blocks=(1, 1, 1), **kw)


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
    cfg = _small_config()
    torch.manual_seed(0)
    plain = build_generator(cfg)
    fused = build_generator(dataclasses.replace(cfg, surface_fusion=True))
    missing, unexpected = fused.load_state_dict(plain.state_dict(), strict=False)
    assert sorted(missing) == ["fusion.mix.bias", "fusion.mix.weight", "fusion.mode.weight"] and not unexpected
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        torch.testing.assert_close(fused(image).logits, plain(image).logits)
    # The mix starts at zero but gets a gradient, and once it is not zero the heads get one through it.
    out = fused(image)
    out.logits.square().mean().backward()
    assert fused.fusion.mix.weight.grad.abs().sum() > 0
    with torch.no_grad():
        fused.fusion.mix.weight.normal_()
    fused.zero_grad()
    out = fused(image)
    out.logits.square().mean().backward()
    assert fused.surface_head.weight.grad.abs().sum() > 0


def test_image_branch_starts_as_the_model_without_it_and_learns() -> None:
    cfg = _small_config()
    torch.manual_seed(0)
    plain = build_generator(cfg).eval()
    branched = build_generator(dataclasses.replace(cfg, image_branch=4)).eval()
    missing, unexpected = branched.load_state_dict(plain.state_dict(), strict=False)
    assert missing and all(k.startswith("image_branch.") for k in missing) and not unexpected
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        torch.testing.assert_close(branched(image).logits, plain(image).logits)
    # Its last BatchNorm starts at zero but gets a gradient; once it is not zero the branch changes the output.
    _wake_zero_started_branch(branched, branched.image_branch, image)
    with torch.no_grad():
        assert (branched(image).logits - plain(image).logits).abs().max() > 1e-3


def test_image_branch_needs_a_larger_image() -> None:
    with pytest.raises(ConfigError, match="image_branch needs model.image_scale >= 1"):
        ModelConfig(image_scale=0, image_branch=8).check()
    with pytest.raises(ConfigError, match="model.image_branch"):
        ModelConfig(image_branch=-1).check()


@pytest.mark.parametrize("image_scale", [0, 1])
def test_detail_branch_reads_a_twice_larger_image_and_starts_as_the_model_on_the_pooled_image(
        image_scale: int) -> None:
    cfg = _small_config(image_scale=image_scale)
    detailed_cfg = dataclasses.replace(cfg, detail_branch=4)
    assert detailed_cfg.image_size == (32 << image_scale, 32 << image_scale) == tuple(2 * n for n in cfg.image_size)
    torch.manual_seed(0)
    plain = build_generator(cfg).eval()
    detailed = build_generator(detailed_cfg).eval()
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


def test_detail_branch_config_is_checked() -> None:
    with pytest.raises(ConfigError, match="model.detail_branch"):
        ModelConfig(detail_branch=-1).check()
    with pytest.raises(ConfigError, match="detail_branch doubles the image"):
        ModelConfig(image_scale=4, detail_branch=8).check()


def test_surface_fusion_needs_the_depth_head() -> None:
    with pytest.raises(ConfigError, match="surface_fusion needs model.lift"):
        ModelConfig(lift="copy", surface_fusion=True).check()


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


# ------------------------------------------------------------------------------------------------ fill_columns
def _fill_reference(logits: torch.Tensor, depth_logits: torch.Tensor,
                    threshold: float = FILL_SURFACE_PROBABILITY) -> torch.Tensor:
    """Predicted labels after the rule, column by column: (B, D, H, W) int64."""
    labels = logits.argmax(1)
    none = torch.softmax(depth_logits.double(), dim=1)[:, -1]
    b_, _, h_, w_ = labels.shape
    for b in range(b_):
        for y in range(h_):
            for x in range(w_):
                column = logits[b, :, :, y, x].double()  # (C, D)
                if (labels[b, :, y, x] > 0).any() or none[b, y, x] >= threshold:
                    continue
                k = int((1 - torch.softmax(column, dim=0)[0]).argmax())
                labels[b, k, y, x] = int(column[1:, k].argmax()) + 1
    return labels


@pytest.mark.parametrize("threshold", [FILL_SURFACE_PROBABILITY, 0.85])
@pytest.mark.parametrize("dtype", [torch.float32, torch.bfloat16])
def test_fill_columns_gives_a_surface_to_the_columns_the_head_sees_one_in(dtype: torch.dtype,
                                                                         threshold: float) -> None:
    torch.manual_seed(1)
    logits = torch.randn(2, 5, 6, 4, 3) * 30  # large logits: bfloat16 spacing there is 0.25 to 1
    logits[:, 0] += 60.0  # most columns empty
    logits[0, 0, 2, 1, 1] = -100.0  # one column already has a surface
    depth_logits = torch.randn(2, 7, 4, 3) * 3
    depth_logits[:, -1] += 2.5  # "no surface" from 0.0003 to 0.96: both thresholds tried decide columns
    logits = logits.to(dtype)
    out = fill_columns(logits, depth_logits, threshold=threshold)
    assert out.dtype == dtype and out.shape == logits.shape
    torch.testing.assert_close(out[:, 1:], logits[:, 1:], rtol=0, atol=0)
    expected = _fill_reference(logits.float(), depth_logits, threshold)
    assert torch.equal(out.argmax(1), expected)
    before = (logits.argmax(1) > 0).any(1)
    after = (out.argmax(1) > 0).any(1)
    none = torch.softmax(depth_logits, 1)[:, -1]
    head_sees = none < threshold
    assert torch.equal(after, before | head_sees) and not torch.equal(after, before)
    # The draw has columns between the two thresholds tried, so the threshold decides some columns.
    assert ((none >= FILL_SURFACE_PROBABILITY) & (none < 0.85) & ~before).any()
    # Only filled columns change, each in one cell.
    changed = (out != logits).any(1)  # (B, D, H, W)
    assert torch.equal(changed.sum(1), (after & ~before).long())


@pytest.mark.parametrize("offset", [0.0, 0.7])
def test_generator_applies_its_inference_rules_only_in_eval_mode(offset: float) -> None:
    cfg = _small_config()
    torch.manual_seed(0)
    plain = build_generator(cfg)
    with torch.no_grad():  # every cell empty, every column with a surface by the depth head
        plain.head.bias[0] += 5.0
        plain.depth_head.bias[-1] -= 10.0
    filled = build_generator(dataclasses.replace(cfg, fill_columns=True, empty_offset=offset, fill_threshold=0.9))
    filled.load_state_dict(plain.state_dict())
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        plain.eval(), filled.eval()
        ref = plain(image)
        out = filled(image).logits
        shifted = ref.logits.clone()
        shifted[:, 0] += offset
        torch.testing.assert_close(out, fill_columns(shifted, ref.depth_logits, threshold=0.9))
        assert (ref.logits.argmax(1) == 0).all() and ((out.argmax(1) > 0).sum(1) == 1).all()
        plain.train(), filled.train()
        torch.testing.assert_close(filled(image).logits, plain(image).logits)
    with pytest.raises(ConfigError, match="fill_columns needs model.lift"):
        ModelConfig(lift="copy", fill_columns=True).check()
    with pytest.raises(ConfigError, match="model.empty_offset must be a finite number"):
        ModelConfig(empty_offset=math.inf).check()
    for bad in (0.0, 1.5, math.nan):
        with pytest.raises(ConfigError, match=r"model.fill_threshold must be in \(0, 1\]"):
            ModelConfig(fill_threshold=bad).check()


# --------------------------------------------------------------------------------------------- first_hit_label
def _first_hit_reference(logits: torch.Tensor) -> torch.Tensor:
    """``P(first hit = c)`` per column by enumerating every labelling of the column: (B, C, H, W) float64."""
    p = torch.softmax(logits.double(), dim=1)
    b_, c_, d_, h_, w_ = p.shape
    out = torch.zeros(b_, c_, h_, w_, dtype=torch.float64)
    for b, y, x in itertools.product(range(b_), range(h_), range(w_)):
        for seq in itertools.product(range(c_), repeat=d_):
            first = next((c for c in seq if c), 0)
            out[b, first, y, x] += math.prod(float(p[b, c, k, y, x]) for k, c in enumerate(seq))
    return out


def test_first_hit_log_probs_is_the_columns_first_hit_distribution() -> None:
    torch.manual_seed(2)
    logits = torch.randn(2, 3, 4, 2, 3) * 2.5
    logits[0, 0, 0, 0, 0] = -80.0  # a cell surely occupied: the cells behind it can never be the first hit
    got = first_hit_log_probs(logits)
    assert got.shape == (2, 3, 2, 3) and got.dtype == torch.float32
    torch.testing.assert_close(got.exp().double(), _first_hit_reference(logits), rtol=1e-5, atol=1e-6)
    shifted = logits.clone()
    shifted[:, 0] += 1.3
    torch.testing.assert_close(first_hit_log_probs(logits, 1.3), first_hit_log_probs(shifted))
    assert torch.isfinite(got).all()


def test_first_hit_label_names_the_board_the_cells_share() -> None:
    """A board spread over three cells, each 40 % furniture and 60 % empty, in front of a wall: the argmax shows
    the wall, the column's first hit is furniture with probability 1 - 0.6^3 = 0.78; only that cell changes."""
    c, d = 5, 6
    logits = torch.full((1, c, d, 2, 2), -20.0)
    logits[:, 0] = 0.0  # empty everywhere ...
    logits[0, 4, 1:4, 0, 0] = math.log(0.4 / 0.6)  # ... but column (0, 0): furniture 40 % in slices 1-3
    logits[0, 0, 5, 0, 0] = -20.0
    logits[0, 1, 5, 0, 0] = 5.0  # a wall in slice 5
    logits[0, 1, 2, 1, 1] = 3.0  # column (1, 1): a wall in slice 2, nothing else
    logits[0, 3, 4, 1, 1] = 9.0  # and a window behind it, which the first hit never is
    torch.testing.assert_close(first_hit_log_probs(logits)[0, 4, 0, 0].exp(), torch.tensor(1 - 0.6 ** 3))
    assert int(logits[0, :, 5, 0, 0].argmax()) == 1
    out = first_hit_label(logits, logits)
    labels, before = out.argmax(1), logits.argmax(1)
    assert int(labels[0, 5, 0, 0]) == 4  # the wall's cell now shows the board ...
    changed = (labels != before).nonzero().tolist()
    assert changed == [[0, 5, 0, 0]]  # ... and nothing else changed: columns without a hit stay empty
    torch.testing.assert_close(out[:, :, :5], logits[:, :, :5], rtol=0, atol=0)
    # After other rules, the first occupied cell of the ruled logits is relabelled (bfloat16 keeps the margin).
    ruled = logits.clone()
    ruled[0, 0, 3, 0, 0] = -30.0  # say a rule made slice 3 the first occupied cell, as furniture
    ruled[0, 1, 3, 0, 0] = 2.0  # ... with wall slightly ahead of furniture there
    out = first_hit_label(ruled.bfloat16(), logits)
    assert out.dtype == torch.bfloat16 and int(out.argmax(1)[0, 3, 0, 0]) == 4
    best = first_hit_classes(logits)
    assert best.shape == (1, 2, 2) and int(best[0, 0, 0]) == 4 and int(best[0, 1, 1]) == 1
    torch.testing.assert_close(first_hit_label(ruled, None, best=best), first_hit_label(ruled, logits))


def test_generator_applies_first_hit_label_after_its_other_rules() -> None:
    cfg = _small_config(fill_columns=True, empty_offset=0.5, fill_threshold=0.9)
    torch.manual_seed(4)
    plain = build_generator(cfg)
    labelled = build_generator(dataclasses.replace(cfg, first_hit_label=True))
    bare = build_generator(dataclasses.replace(cfg, fill_columns=False, empty_offset=0.0))
    labelled.load_state_dict(plain.state_dict())
    bare.load_state_dict(plain.state_dict())
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        plain.eval(), labelled.eval(), bare.eval()
        ruled, raw, out = plain(image).logits, bare(image).logits, labelled(image).logits
        torch.testing.assert_close(out, first_hit_label(ruled, raw))
        assert not torch.equal(out.argmax(1), ruled.argmax(1))  # the random weights' first hits do change
        labelled.train(), bare.train()
        torch.testing.assert_close(labelled(image).logits, bare(image).logits)  # training sees no rule


# ------------------------------------------------------------------------------------------------------ flip_average

def test_flip_average_averages_the_image_and_its_mirror_before_the_rules() -> None:
    cfg = _small_config(surface_fusion=True, fill_columns=True, empty_offset=0.5, fill_threshold=0.9,
                        first_hit_label=True)
    torch.manual_seed(5)
    ruled = build_generator(cfg)
    flipped = build_generator(dataclasses.replace(cfg, flip_average=True))
    bare = build_generator(dataclasses.replace(cfg, fill_columns=False, empty_offset=0.0, first_hit_label=False))
    for g in (flipped, bare):
        g.load_state_dict(ruled.state_dict())
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        ruled.eval(), flipped.eval(), bare.eval()
        a, m = bare(image), bare(image.flip(-1))
        # The mirror's outputs mirrored back along W (the last axis), then averaged.
        raw = (a.logits + m.logits.flip(-1)) / 2
        depth = (a.depth_logits + m.depth_logits.flip(-1)) / 2
        out = flipped(image)
        torch.testing.assert_close(out.depth_logits, depth)
        torch.testing.assert_close(out.surface_logits, (a.surface_logits + m.surface_logits.flip(-1)) / 2)
        want = first_hit_label(inference_rules(raw, depth, empty_offset=0.5, fill=True, fill_threshold=0.9), raw)
        torch.testing.assert_close(out.logits, want)
        # rules=False stops before the rules (the averaged network logits) and apply_rules adds them back.
        unruled = flipped(image, rules=False)
        torch.testing.assert_close(unruled.logits, raw)
        torch.testing.assert_close(flipped.apply_rules(unruled.logits, unruled.depth_logits), out.logits)
        assert not torch.allclose(out.logits, ruled(image).logits, atol=1e-3)  # the mirror does change the answer
        # The average is mirror-symmetric: the mirror image's prediction is the prediction mirrored.
        torch.testing.assert_close(flipped(image.flip(-1)).logits, out.logits.flip(-1))
        # One batch of both images (the GPU's way) gives what two passes (the CPU's) give.
        for x, y in zip(*(flipped._mirror_passes(image, batched=b) for b in (True, False)), strict=True):
            for u, v in zip(x, y, strict=True):
                torch.testing.assert_close(u, v)
        flipped.train(), ruled.train()
        torch.testing.assert_close(flipped(image).logits, ruled(image).logits)  # training sees one pass

"""The fine depth head: each column's first surface placed within a slice, trained on the simulator's rendered depth.

The rendered depth of a column's centre ray (constructed buffers, and a real sample against its own labels), the
head's targets and loss, the generator starting as the model it was fine-tuned from, the config checks, and real
training steps with the streamed simulator and the replay buffer.
"""

from __future__ import annotations

import csv
import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("torch_one_thread")

from fruxel.grid import FruxelGrid  # noqa: E402
from fruxel.train.config import ConfigError, LossConfig, ModelConfig, TrainConfig, override  # noqa: E402
from fruxel.train.engine.data import ReplayBuffer  # noqa: E402
from fruxel.train.export import build_generator  # noqa: E402
from fruxel.train.models.generator import SSZGenerator, SSZOutput  # noqa: E402
from fruxel.train.objective import SSZObjective, fine_depth_targets, surface_targets  # noqa: E402
from fruxel.train.sim.images import column_surface_depth  # noqa: E402

GRID = FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0)


def _small_config(**kw: object) -> ModelConfig:
    return ModelConfig(grid=GRID, levels=3, stem=8, encoder=(8, 8, 8), encoder_blocks=(1, 1, 1), topdown=(8, 8, 8),
                       decoder=(8, 8, 8), decoder_blocks=(1, 1, 1), **kw)


# ---------------------------------------------------------------------------------------------- rendered depth
@pytest.mark.parametrize("scale", [1, 3, 4])
def test_column_depth_of_a_plane_is_its_depth_on_the_centre_ray(scale: int) -> None:
    """On a plane, 1 / z is affine in the image: the value read for each column is the plane's depth exactly where
    the column's centre ray crosses it, whether that is a pixel's centre (odd scale) or a corner (even)."""
    w, h = 6, 4
    ys, xs = np.mgrid[0:h * scale, 0:w * scale] + 0.5  # pixel centres, image pixels
    inv = 0.25 + 0.01 * xs / scale - 0.02 * ys / scale
    got = column_surface_depth((1.0 / inv).astype(np.float32), w, h, tolerance=1.0)
    jc, ic = np.mgrid[0:h, 0:w] + 0.5  # column centres, grid columns
    want = 1.0 / (0.25 + 0.01 * ic - 0.02 * jc)
    assert got.shape == (h, w) and got.dtype == np.float32
    np.testing.assert_allclose(got, want, rtol=1e-5)


def test_column_depth_marks_edges_unknown_and_the_background_as_nothing() -> None:
    depth = np.full((8, 8), 2.0, np.float32)  # 4 x 4 columns of 2 x 2 pixels: each column's ray is a pixel corner
    depth[0:2, 0:2] = 0.0  # column (0, 0): background on every pixel around the ray
    depth[0:2, 2] = 0.0  # column (0, 1): half background, half surface
    depth[2:4, 4] = 3.0  # column (1, 2): a step of 1 m across the ray
    depth[4:6, 4] = 2.02  # column (2, 2): 2 cm of slope, within the tolerance
    got = column_surface_depth(depth, 4, 4, tolerance=0.05)
    assert math.isinf(got[0, 0]) and got[0, 0] > 0
    assert np.isnan(got[0, 1]) and np.isnan(got[1, 2])
    assert 2.0 < got[2, 2] < 2.02
    known = np.ones((4, 4), bool)
    known[0, :2] = known[1, 2] = known[2, 2] = False
    np.testing.assert_array_equal(got[known], 2.0)
    with pytest.raises(ValueError, match="depth image must be"):
        column_surface_depth(np.ones((8, 9), np.float32), 4, 4, tolerance=0.05)


def test_a_simulated_samples_surface_depth_agrees_with_its_labels() -> None:
    """The rendered surface of a column lies in the slice of the truth's first occupied cell, or in the slice
    before it (a cell holds a solid when its centre does: a surface in a slice's back half first fills the next
    one); further in front only where a board thinner than a slice holds no centre."""
    from fruxel.train.sim.config import ImageConfig, SimConfig
    from fruxel.train.sim.sample import SampleMaker

    grid = FruxelGrid(width=32, height=32, depth=32, z_near=0.5, z_far=8.0, hfov=60.0)
    config = SimConfig(grid=grid, image=ImageConfig(size=128), samples_per_scene=2, splits=(("train", 8),))
    with SampleMaker(config, 3) as maker:
        samples = [maker.make("train", i) for i in (0, 3, 6)]
    same = before = behind = count = 0
    for s in samples:
        assert s.surface_depth is not None and s.surface_depth.shape == (32, 32)
        first, _ = surface_targets(torch.from_numpy(s.labels[None].astype(np.int64)))
        k = first[0].numpy()
        ks = np.floor((s.surface_depth - grid.z_near) / grid.dz)
        known = np.isfinite(s.surface_depth) & (s.surface_depth >= grid.z_near) & (s.surface_depth < grid.z_far)
        known &= k < grid.depth
        count += int(known.sum())
        same += int((ks == k)[known].sum())
        before += int((ks == k - 1)[known].sum())
        behind += int((ks > k)[known].sum())
    assert count > 1000
    assert (same + before) / count > 0.85 and same / count > 0.3 and before / count > 0.3
    assert behind / count < 0.02


# ---------------------------------------------------------------------------------------------- targets and loss
def test_fine_targets_are_sub_slice_bins() -> None:
    dz, r = GRID.dz, 4
    z = torch.tensor([[0.5, 0.5 + dz * 0.26, 0.5 + dz * 3.9, 7.99, 8.0, 9.0, math.inf, math.nan, 0.3]])
    got = fine_depth_targets(z, GRID.z_near, dz, GRID.depth, r)
    assert got.tolist() == [[0, 1, 15, 16 * 4 - 1, 64, 64, 64, -100, -100]]


def test_fine_term_is_the_cross_entropy_over_the_known_columns() -> None:
    torch.manual_seed(0)
    r = 4
    fine = torch.randn(2, GRID.depth * r + 1, 16, 16, requires_grad=True)
    out = SSZOutput(logits=torch.randn(2, 7, 16, 16, 16), depth_logits=None, surface_logits=None, fine_logits=fine)
    labels = torch.zeros(2, 16, 16, 16, dtype=torch.uint8)
    z = torch.rand(2, 16, 16) * 9.0
    z[0, :4] = math.nan
    only = LossConfig(ce=0.0, iou=0.0, depth=0.0, surface=0.0, fine_depth=2.0)
    objective = SSZObjective(only, torch.ones(7), grid=GRID)
    terms = objective(out, labels, z)
    target = fine_depth_targets(z, GRID.z_near, GRID.dz, GRID.depth, r)
    known = target != -100
    expected = torch.nn.functional.cross_entropy(fine.detach().movedim(1, -1)[known], target[known])
    torch.testing.assert_close(terms["fine_depth"], expected)
    torch.testing.assert_close(terms["total"], 2.0 * expected)
    terms["total"].backward()
    assert fine.grad[0, :, :4].abs().sum() == 0 and fine.grad[0, :, 4:].abs().sum() > 0
    # No known column: zero, not NaN; no depth (shards) or no head: no term.
    nothing = objective(out, labels, torch.full_like(z, math.nan))["fine_depth"]
    assert nothing.item() == 0.0
    assert "fine_depth" not in objective(out, labels)
    assert "fine_depth" not in objective(dataclasses.replace(out, fine_logits=None), labels, z)


# ---------------------------------------------------------------------------------------------- generator
def test_generator_with_the_fine_head_starts_as_the_model_without_it() -> None:
    cfg = _small_config(image_scale=1)
    torch.manual_seed(0)
    plain = build_generator(cfg).eval()
    fine = build_generator(dataclasses.replace(cfg, fine_depth=4)).eval()
    missing, unexpected = fine.load_state_dict(plain.state_dict(), strict=False)
    assert sorted(missing) == ["fine_head.bias", "fine_head.weight", "lifts.0.from_fine.weight"] and not unexpected
    image = torch.rand(2, 3, 32, 32)
    with torch.no_grad():
        a, b = plain(image), fine(image)
    torch.testing.assert_close(b.logits, a.logits)
    assert a.fine_logits is None and b.fine_logits.shape == (2, 16 * 4 + 1, 16, 16)
    # The decoder's term starts at zero, gets a gradient, and once it is not zero the fine head steers the volume.
    fine.train()
    fine(image).logits.square().mean().backward()
    assert fine.lifts[0].from_fine.weight.grad.abs().sum() > 0
    fine.eval()
    with torch.no_grad():
        fine.lifts[0].from_fine.weight.normal_()
        assert (fine(image).logits - a.logits).abs().max() > 1e-3
    # Mirror averaging mirrors the fine logits back like the others.
    fine.flip_average = True
    with torch.no_grad():
        flipped = fine(image)
        fine.flip_average = False
        one, mirror = fine(image), fine(image.flip(-1))
    torch.testing.assert_close(flipped.fine_logits, (one.fine_logits + mirror.fine_logits.flip(-1)) * 0.5)


def test_fine_features_are_the_sub_bins_of_each_cell() -> None:
    torch.manual_seed(1)
    logits = torch.randn(2, 3 * 4 + 1, 5, 6)
    f = SSZGenerator.fine_features(logits, 4)
    p = torch.softmax(logits, 1)
    assert f.shape == (2, 4, 3, 5, 6) and f.is_contiguous()
    torch.testing.assert_close(f[:, 2, 1], p[:, 1 * 4 + 2])
    torch.testing.assert_close(f.sum((1, 2)), 1.0 - p[:, -1])


def test_fine_depth_config_is_checked() -> None:
    with pytest.raises(ConfigError, match="model.fine_depth"):
        ModelConfig(fine_depth=-1).check()
    with pytest.raises(ConfigError, match="fine_depth needs model.lift"):
        ModelConfig(lift="copy", surface_fusion=False, fine_depth=4).check()
    with pytest.raises(ConfigError, match="loss.fine_depth"):
        LossConfig(fine_depth=math.nan).check()
    base = TrainConfig.from_dict({"preset": "tiny", "model": {"fine_depth": 4}})
    with pytest.raises(ConfigError, match="loss.fine_depth needs data.source = 'stream'"):
        override(base, {"data": {"source": "shards", "root": "somewhere"}}, "").check()
    override(base, {"data": {"source": "shards", "root": "somewhere"}, "loss": {"fine_depth": 0.0}}, "").check()


# ---------------------------------------------------------------------------------------------- training
def test_replay_buffer_keeps_the_surface_depth_with_its_sample() -> None:
    buf = ReplayBuffer(8, (4, 4, 3), (2, 2, 2), torch.device("cpu"), seed=0)
    for n in range(3):
        ident = torch.arange(n * 4, n * 4 + 4)
        buf.add({"image": ident.view(4, 1, 1, 1).expand(4, 4, 4, 3).to(torch.uint8),
                 "labels": torch.zeros(4, 2, 2, 2, dtype=torch.uint8),
                 "surface_depth": ident.view(4, 1, 1).expand(4, 2, 2).float() + 0.5})
    drawn = buf.draw(16)
    torch.testing.assert_close(drawn["surface_depth"][:, 0, 0], drawn["image"][:, 0, 0, 0].float() + 0.5)
    with pytest.raises(ValueError, match="surface_depth"):
        buf.add({"image": torch.zeros(4, 4, 4, 3, dtype=torch.uint8), "labels": torch.zeros(4, 2, 2, 2,
                                                                                            dtype=torch.uint8)})


@pytest.mark.parametrize("replay", [0, 4])
def test_training_with_the_streamed_simulator_learns_the_fine_head(tmp_path: Path, replay: int) -> None:
    from fruxel.train.engine.trainer import Trainer

    from .test_engine import tiny

    config = tiny({"model": {"fine_depth": 4}, "data": {"replay": replay, "reuse": 2},
                   "loss": {"fine_depth": 2.0}, "run": {"steps": 30, "log_every": 1}, "optim": {"lr": 1e-2}})
    Trainer(config, tmp_path / "run", device="cpu", progress=False).fit()
    with open(tmp_path / "run" / "metrics.csv", newline="") as f:
        values = [float(r["loss/fine_depth"]) for r in csv.DictReader(f) if r.get("loss/fine_depth")]
    assert len(values) == 30 and all(math.isfinite(v) for v in values)
    # From about log(16 * 4 + 1) = 4.2 down: the head learns from the rendered depth.
    assert values[0] > 3.0 and np.mean(values[-5:]) < values[0] - 0.25


def test_fine_depth_estimate_reads_the_heads_most_likely_place() -> None:
    from fruxel.train.eval.own_view import fine_depth_estimate

    r = 4
    logits = np.full((2, GRID.depth * r + 1, 3, 3), -30.0)
    logits[0, 9] = 10.0  # slice 2, sub-bin 1: one bin only
    logits[1, 9] = logits[1, 10] = 10.0  # two neighbours equally likely: between their centres
    logits[1, -1, 0, 0] = 20.0  # column (0, 0) of sample 1: no surface
    logits[1, 40, 1, 1] = 10.5  # a far bin slightly likelier than the pair: read there, the pair is too far off
    z = fine_depth_estimate(logits, GRID)
    bin_centre = GRID.z_near + (np.arange(GRID.depth * r) + 0.5) * GRID.dz / r
    np.testing.assert_allclose(z[0], bin_centre[9])
    np.testing.assert_allclose(z[1, 2, 2], (bin_centre[9] + bin_centre[10]) / 2)
    assert math.isinf(z[1, 0, 0])
    np.testing.assert_allclose(z[1, 1, 1], bin_centre[40], rtol=1e-6)
    with pytest.raises(ValueError, match="fine_logits need"):
        fine_depth_estimate(logits[:, :-2], GRID)

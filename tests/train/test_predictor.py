"""fruxel.train.predict.Predictor: the forward pass it runs, eager on the CPU and replayed as CUDA graphs on CUDA
(the CUDA cases run where a GPU is, e.g. on the lent H100)."""

from __future__ import annotations

import pytest
import torch

from fruxel.train.config import preset
from fruxel.train.export import build_generator
from fruxel.train.predict import Predictor


def _predictor(device: str, graphs: bool, seed: int = 0) -> Predictor:
    torch.manual_seed(seed)
    m = preset("tiny").model
    return Predictor(build_generator(m), m, device, batch=2, graphs=graphs)


def test_cpu_runs_the_eager_pass() -> None:
    p = _predictor("cpu", graphs=True)
    assert not p.graphs
    x = torch.rand(2, 3, *p.config.image_size)
    with torch.no_grad():
        want = p.generator(x).logits.float()
    got = p.logits(x)
    assert got.shape == (2, p.config.num_classes, *p.config.grid.shape) and got.dtype == torch.float32
    assert torch.equal(got, want)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_cuda_graphs_replay_the_eager_pass() -> None:
    graphed, eager = _predictor("cuda", graphs=True), _predictor("cuda", graphs=False)
    assert graphed.graphs and not eager.graphs
    torch.manual_seed(1)
    xs = [torch.rand(b, 3, *graphed.config.image_size, device="cuda") for b in (2, 2, 1, 2)]
    outs = [graphed.logits(x) for x in xs]
    assert len(graphed._graphs) == 2  # one capture per input shape, replayed after
    for x, out in zip(xs, outs, strict=True):
        want = eager.logits(x)
        assert out.shape == want.shape
        torch.testing.assert_close(out, want, rtol=2e-2, atol=2e-2)  # bfloat16 compute; algorithms may differ
    # Every call's result is its own: a later replay does not overwrite an earlier one.
    assert not torch.equal(outs[0], outs[1])
    torch.testing.assert_close(outs[0], eager.logits(xs[0]), rtol=2e-2, atol=2e-2)

"""fruxel.train.predict.Predictor: the forward pass it runs, eager on the CPU and replayed as CUDA graphs on CUDA
(the CUDA cases run where a GPU is, e.g. on the lent H100)."""

from __future__ import annotations

import pytest
import torch

from fruxel.train.config import preset
from fruxel.train.predict import Predictor
from fruxel.train.rules import NO_RULES, InferenceRules, predict_logits


def _predictor(device: str, graphs: bool, seed: int = 0, **kw: object) -> Predictor:
    torch.manual_seed(seed)
    m = preset("tiny").model
    return Predictor(m.build(), m, device, batch=2, graphs=graphs, **kw)


def test_cpu_runs_the_eager_pass() -> None:
    p = _predictor("cpu", graphs=True)
    assert not p.graphs
    x = torch.rand(2, 3, *p.config.image_size)
    with torch.no_grad():
        want = p.network(x).logits.float()
    got = p.logits(x)
    assert got.shape == (2, p.config.num_classes, *p.config.grid.shape) and got.dtype == torch.float32
    assert torch.equal(got, want) and p.rules == NO_RULES
    # The Predictor applies its rules after the network.
    rules = InferenceRules(fill_columns=True, empty_offset=0.5, first_hit_label=True)
    ruled = Predictor(p.network, p.config, "cpu", rules=rules)
    with torch.no_grad():
        assert torch.equal(ruled.logits(x), predict_logits(p.network, x, rules))


def test_cpu_predicts_in_float32_and_run_applies_then() -> None:
    p = _predictor("cpu", graphs=True, compile=True, precision="bfloat16")
    assert p.precision == "float32" and not p.compiled  # both are CUDA options
    assert next(p.network.parameters()).dtype == torch.float32
    x = torch.rand(1, 3, *p.config.image_size)
    logits = p.logits(x)
    labels = p.run(x, then=lambda z: z.argmax(1).to(torch.uint8))
    assert labels.shape == (1, *p.config.grid.shape) and labels.dtype == torch.uint8
    assert torch.equal(labels, logits.argmax(1).to(torch.uint8))


def test_unknown_precision_is_refused() -> None:
    with pytest.raises(ValueError, match="precision must be one of"):
        _predictor("cpu", graphs=True, precision="float16")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
@pytest.mark.parametrize("compile", [False, True])
def test_cuda_graph_of_logits_and_kernels_replays_the_eager_pipeline(compile: bool) -> None:
    """Predictor.run captures the forward pass and Warp kernels on the logits in one graph; every replay gives
    what the same work gives uncaptured, for each new image."""
    from fruxel import kernels

    graphed, eager = _predictor("cuda", graphs=True, compile=compile), _predictor("cuda", graphs=False)
    assert graphed.precision == "bfloat16" and next(graphed.network.parameters()).dtype == torch.bfloat16
    grid = graphed.config.grid

    def labels_shell(logits: torch.Tensor) -> torch.Tensor:
        return kernels.shell(logits.argmax(1).to(torch.uint8), grid, [grid.camera()])

    torch.manual_seed(2)
    for _ in range(3):
        x = torch.rand(1, 3, *graphed.config.image_size, device="cuda")
        got = graphed.run(x, then=labels_shell).clone()
        want_logits = eager.logits(x)
        want = labels_shell(want_logits)
        # bfloat16 compute in both, but compiled kernels round differently: compare where the argmax is clear.
        top2 = want_logits.topk(2, dim=1).values
        clear = (top2[:, 0] - top2[:, 1]) > 0.1
        assert (got == want)[clear].float().mean() > 0.999
    assert graphed.captured == 1


@pytest.mark.skipif(not torch.cuda.is_available(), reason="CUDA graphs need a CUDA device")
def test_cuda_graphs_replay_the_eager_pass() -> None:
    graphed, eager = _predictor("cuda", graphs=True), _predictor("cuda", graphs=False)
    assert graphed.graphs and not eager.graphs
    torch.manual_seed(1)
    xs = [torch.rand(b, 3, *graphed.config.image_size, device="cuda") for b in (2, 2, 1, 2)]
    outs = [graphed.logits(x) for x in xs]
    assert graphed.captured == 2  # one capture per input shape, replayed after
    for x, out in zip(xs, outs, strict=True):
        want = eager.logits(x)
        assert out.shape == want.shape
        torch.testing.assert_close(out, want, rtol=2e-2, atol=2e-2)  # bfloat16 compute; algorithms may differ
    # Every call's result is its own: a later replay does not overwrite an earlier one.
    assert not torch.equal(outs[0], outs[1])
    torch.testing.assert_close(outs[0], eager.logits(xs[0]), rtol=2e-2, atol=2e-2)

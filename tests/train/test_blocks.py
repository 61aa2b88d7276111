"""SSZ's building blocks that replace a PyTorch layer by a faster computation of the same function."""

from __future__ import annotations

import pytest
import torch
from torch import nn

from fruxel.train.models.blocks import Pointwise3d


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

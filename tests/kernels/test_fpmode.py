"""``flush_denormals``: the block runs with denormals flushed, and the caller's mode comes back, even on error."""

from __future__ import annotations

import pytest

torch = pytest.importorskip("torch")

from fruxel.kernels.fpmode import flush_denormals  # noqa: E402


def _flushing() -> bool:
    return (torch.tensor([1e-39], dtype=torch.float32) * 2.0).item() == 0.0


def test_flush_denormals_sets_the_mode_for_the_block_only() -> None:
    assert not _flushing()
    with flush_denormals():
        assert _flushing()
    assert not _flushing()
    with flush_denormals(False):
        assert not _flushing()


def test_flush_denormals_restores_after_an_error_and_keeps_a_callers_mode() -> None:
    with pytest.raises(RuntimeError), flush_denormals():
        raise RuntimeError("inside")
    assert not _flushing()
    torch.set_flush_denormal(True)
    try:
        with flush_denormals():
            pass
        assert _flushing(), "a caller that flushes keeps flushing"
    finally:
        torch.set_flush_denormal(False)

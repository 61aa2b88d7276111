"""The CPU's floating-point mode for denormal numbers, set for a block of work and put back after."""

from __future__ import annotations

from collections.abc import Iterator
from contextlib import contextmanager


@contextmanager
def flush_denormals(enabled: bool = True) -> Iterator[None]:
    """Run the enclosed CPU work with denormals flushed to zero (FTZ/DAZ), restoring the caller's mode after.

    Denormal floats (below about 1.2e-38 in float32) take a slow microcode assist on x86 cores; GPUs flush them
    anyway. The mode is per thread and process-wide state that other code relies on (hypothesis, for one, refuses
    to draw floats while it is on), so it is only ever set for a block: probed with a denormal multiplication
    (zero when flushing is on) and put back as it was.

    Args:
        enabled: when False, do nothing (the block runs in the caller's mode).
    """
    if not enabled:
        yield
        return
    import torch

    was_on = (torch.tensor([1e-39], dtype=torch.float32) * 2.0).item() == 0.0
    if not was_on:
        torch.set_flush_denormal(True)
    try:
        yield
    finally:
        if not was_on:
            torch.set_flush_denormal(False)

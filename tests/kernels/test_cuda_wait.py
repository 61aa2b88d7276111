"""How the simulator's workers wait for CUDA (``fruxel.kernels.wp.runtime.set_cuda_wait``): the mode's name from
``$FRUXEL_CUDA_WAIT``, refused when unknown, and, on a machine with an NVIDIA driver, the scheduling flag set on the
primary context of a fresh process before its first context is made."""

from __future__ import annotations

import ctypes
import subprocess
import sys

import pytest

from fruxel.kernels.registry import BackendError
from fruxel.kernels.wp.runtime import CUDA_WAITS, cuda_wait, set_cuda_wait


def _driver() -> bool:
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    count = ctypes.c_int(0)
    return cuda.cuInit(0) == 0 and cuda.cuDeviceGetCount(ctypes.byref(count)) == 0 and count.value > 0


def test_the_mode_comes_from_the_environment_and_an_unknown_one_is_refused(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("FRUXEL_CUDA_WAIT", raising=False)
    assert cuda_wait() == "block"
    monkeypatch.setenv("FRUXEL_CUDA_WAIT", "auto")
    assert cuda_wait() == "auto"
    monkeypatch.setenv("FRUXEL_CUDA_WAIT", "busy")
    with pytest.raises(BackendError, match=r"^FRUXEL_CUDA_WAIT='busy': expected one of block, spin, yield, auto$"):
        cuda_wait()
    with pytest.raises(BackendError, match="CUDA wait mode 'never'"):
        set_cuda_wait("never")


@pytest.mark.skipif(_driver(), reason="a machine with an NVIDIA driver sets the flags (the test below)")
def test_without_a_driver_nothing_is_set() -> None:
    assert set_cuda_wait("block") is False


@pytest.mark.skipif(not _driver(), reason="needs an NVIDIA driver and device")
@pytest.mark.parametrize("mode", ["block", "spin"])
def test_the_primary_context_waits_as_asked(mode: str) -> None:
    """In a fresh process (no context yet): set the mode, make the context current through Warp, read its flags."""
    code = (
        "import ctypes\n"
        "from fruxel.kernels.wp.runtime import set_cuda_wait, warp\n"
        f"assert set_cuda_wait({mode!r})\n"
        "wp = warp(); wp.zeros(4, device='cuda:0'); wp.synchronize()\n"
        "cuda = ctypes.CDLL('libcuda.so.1'); dev = ctypes.c_int(); flags = ctypes.c_uint(); active = ctypes.c_int()\n"
        "cuda.cuDeviceGet(ctypes.byref(dev), 0)\n"
        "cuda.cuDevicePrimaryCtxGetState(dev, ctypes.byref(flags), ctypes.byref(active))\n"
        "print(flags.value & 7, active.value)\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.split()[-2:] == [str(CUDA_WAITS[mode]), "1"]

"""Warp runtime: importing and initialising NVIDIA Warp once, and naming its devices.

Warp is imported lazily, on the first question asked here, so that ``import fruxel.kernels`` never pays for it.
Initialisation is quiet (``wp.config.quiet``): the backend is a library and prints nothing.

Device names follow Warp's: ``"cpu"``, ``"cuda:0"``, ``"cuda:1"``; ``"cuda"`` means the current CUDA device.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
from collections.abc import Iterator
from functools import cache
from types import ModuleType
from typing import Any

from ..registry import BackendError, BackendUnavailable

_DEVICE_NAME = re.compile(r"^(cpu|cuda)(?::(\d+))?$")

# Printed by Warp's native library, straight to file descriptor 2, on every machine without an NVIDIA driver
# (no log level reaches it). On such machines the missing GPU is expected, so the line is noise.
_NO_DRIVER_NOTE = "Could not find or load the NVIDIA CUDA driver"


@contextlib.contextmanager
def _without_no_driver_note() -> Iterator[None]:
    """Capture what native code writes to stderr meanwhile, and pass it on without Warp's missing-driver line."""
    try:
        fd = sys.stderr.fileno()
    except (AttributeError, OSError, ValueError):
        # stderr is no real file (an embedding host, a test capture): nothing to filter at the descriptor.
        yield
        return
    sys.stderr.flush()
    saved = os.dup(fd)
    with tempfile.TemporaryFile() as cap:
        os.dup2(cap.fileno(), fd)
        try:
            yield
        finally:
            sys.stderr.flush()
            os.dup2(saved, fd)
            os.close(saved)
            cap.seek(0)
            lines = cap.read().decode(errors="replace").splitlines(keepends=True)
            kept = "".join(ln for ln in lines if _NO_DRIVER_NOTE not in ln)
            if kept:
                sys.stderr.write(kept)


@cache
def _load() -> tuple[ModuleType | None, str]:
    """Import and initialise Warp once: ``(warp module, "")``, or ``(None, why not)``."""
    try:
        import warp as wp
    except ImportError as e:
        return None, f"warp-lang is not importable ({e}); install it with: pip install 'fruxel[warp]'"
    try:
        wp.config.quiet = True  # Warp < 1.10; later versions use log levels
        level = getattr(wp.config, "log_level", None)
        if level is not None:
            # Silence the start-up banner and, on CPU-only machines, the missing-driver warning.
            wp.config.log_level = wp.LOG_ERROR
        with _without_no_driver_note():
            wp.init()
        if level is not None:
            # Start-up is over: keep Warp's real warnings, drop its per-module "load took" notes.
            wp.config.log_level = max(level, wp.LOG_WARNING)
    except Exception as e:  # noqa: BLE001 - any failure of a native library start-up means "unavailable"
        return None, f"Warp failed to initialise: {type(e).__name__}: {e}"
    return wp, ""


def warp() -> ModuleType:
    """The initialised ``warp`` module.

    Raises:
        BackendUnavailable: Warp is missing or failed to initialise.
    """
    wp, reason = _load()
    if wp is None:
        raise BackendUnavailable(reason)
    return wp


def cpu_available() -> bool:
    """True when Warp can build CPU kernels (its LLVM/Clang library is present; stripped installations lack it)."""
    wp = _load()[0]
    return wp is not None and wp.is_cpu_available()


def is_available() -> bool:
    """True when Warp imports, initialises and has a device it can build kernels for (CPU or CUDA)."""
    return cpu_available() or cuda_available()


def unavailable_reason() -> str:
    """Why :func:`is_available` is False, with an install hint; empty when Warp is available."""
    wp, reason = _load()
    if wp is None:
        return reason
    if not is_available():
        return "Warp finds no CUDA device and cannot build CPU kernels (its LLVM/Clang library is missing)"
    return ""


def cuda_available() -> bool:
    """True when Warp sees at least one CUDA device."""
    wp = _load()[0]
    return wp is not None and wp.get_cuda_device_count() > 0


def resolve_device(device: Any = None) -> str:
    """Normalise a device request to a Warp device name.

    Args:
        device: ``"cpu"``, ``"cuda"`` (the current CUDA device), ``"cuda:N"``, a ``torch.device`` or a
            ``warp.Device``; None picks ``"cuda:0"`` when a CUDA device exists, else ``"cpu"``.

    Returns:
        ``"cpu"`` or ``"cuda:N"``.

    Raises:
        BackendUnavailable: Warp is missing, or CUDA is asked for on a machine without a CUDA device.
        BackendError: a name that is no device, or a CUDA ordinal that does not exist here.
    """
    wp = warp()
    if device is None:
        return "cuda:0" if cuda_available() else resolve_device("cpu")
    name = str(device)
    m = _DEVICE_NAME.match(name)
    if m is None:
        raise BackendError(f"unknown Warp device {name!r}; use 'cpu', 'cuda' or 'cuda:N'")
    if m.group(1) == "cpu":
        if m.group(2) is not None:
            raise BackendError(f"unknown Warp device {name!r}; the CPU device is 'cpu'")
        if not wp.is_cpu_available():
            raise BackendUnavailable("Warp's CPU device needs its LLVM/Clang library, which this installation lacks")
        return "cpu"
    count = wp.get_cuda_device_count()
    if count == 0:
        raise BackendUnavailable(f"Warp device {name!r} requested, but Warp finds no CUDA device here; use 'cpu'")
    ordinal = wp.get_cuda_device().ordinal if m.group(2) is None else int(m.group(2))
    if ordinal >= count:
        raise BackendError(f"Warp device {name!r} does not exist: {count} CUDA device(s), cuda:0..cuda:{count - 1}")
    return f"cuda:{ordinal}"


CUDA_WAIT_ENV = "FRUXEL_CUDA_WAIT"
"""The environment variable that says how a simulator worker waits for its GPU work (:func:`set_cuda_wait`)."""
CUDA_WAITS = {"block": 0x4, "spin": 0x1, "yield": 0x2, "auto": 0x0}
"""Scheduling flags of a CUDA primary context by name: ``CU_CTX_SCHED_BLOCKING_SYNC``, ``_SPIN``, ``_YIELD``,
``_AUTO`` (CUDA's default: spin while the process has fewer contexts than the machine has cores)."""


def cuda_wait() -> str:
    """The CUDA wait mode :data:`CUDA_WAIT_ENV` asks for (default ``"block"``).

    Raises:
        BackendError: a name not in :data:`CUDA_WAITS`.
    """
    name = os.environ.get(CUDA_WAIT_ENV, "block")
    if name not in CUDA_WAITS:
        raise BackendError(f"{CUDA_WAIT_ENV}={name!r}: expected one of {', '.join(CUDA_WAITS)}")
    return name


def set_cuda_wait(mode: str | None = None) -> bool:
    """Set how this process's threads wait for CUDA work, on every visible device's primary context (the one Warp
    and torch use), before either makes it current.

    A simulator worker on a GPU spends much of its time waiting for its images and labels. Under CUDA's default a
    process with one context spins while it waits, so workers keep cores busy waiting while the host work of other
    workers' samples waits for a core. ``"block"`` sleeps until the GPU is done instead (a few microseconds more per
    wait). With one worker a core it makes no difference; with more workers than cores, which is how the simulator
    streams fastest on a GPU, it streams faster (BENCHMARKS.md, "## Simulator"). The simulator's workers call this
    once as they start.

    Args:
        mode: a name of :data:`CUDA_WAITS`; None: :func:`cuda_wait`.

    Returns:
        Whether the flags were set: False without an NVIDIA driver or device (nothing to set).

    Raises:
        BackendError: an unknown mode.
    """
    import ctypes

    name = cuda_wait() if mode is None else mode
    if name not in CUDA_WAITS:
        raise BackendError(f"CUDA wait mode {name!r}: expected one of {', '.join(CUDA_WAITS)}")
    try:
        cuda = ctypes.CDLL("libcuda.so.1")
    except OSError:
        return False
    count = ctypes.c_int(0)
    if cuda.cuInit(0) != 0 or cuda.cuDeviceGetCount(ctypes.byref(count)) != 0:
        return False
    set_flags = getattr(cuda, "cuDevicePrimaryCtxSetFlags_v2", None) or cuda.cuDevicePrimaryCtxSetFlags
    done = False
    for ordinal in range(count.value):
        device = ctypes.c_int(0)
        if cuda.cuDeviceGet(ctypes.byref(device), ordinal) == 0:
            done = set_flags(device, ctypes.c_uint(CUDA_WAITS[name])) == 0 or done
    return done

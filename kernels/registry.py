"""The one backend registry: names, availability, install hints and the default choice.

A backend is a module with the same functions and signatures as every other backend (see
:data:`OPERATIONS`). Backends are imported only when chosen, so a missing ``warp-lang`` or ``pyopencl``
fails only for the user who asks for it, with an install hint.
"""

from __future__ import annotations

import importlib
import sys
import types
import warnings
from dataclasses import dataclass
from functools import cache
from types import ModuleType
from typing import Any

from fruxel.errors import FruxelError

OPERATIONS = ("first_hit", "shell", "soft_first_hit")
"""Functions every backend package exposes, with identical signatures (see ``fruxel.kernels``); each lives in the
backend's submodule of the same name, beside its kernel source."""


class _BackendPackage(types.ModuleType):
    """Module type of a backend package: each operation's *function* under the operation's name, imported on
    first use.

    The import system binds a package attribute to a submodule when the submodule is first imported (by first
    use here, or by any ``import fruxel.kernels.wp.first_hit``), which would hide the function of the same name;
    ``__setattr__`` keeps the function instead.
    """

    def __getattr__(self, name: str) -> Any:
        if name in OPERATIONS:
            return getattr(importlib.import_module(f"{self.__name__}.{name}"), name)
        raise AttributeError(f"module {self.__name__!r} has no attribute {name!r}")

    def __setattr__(self, name: str, value: Any) -> None:
        if name in OPERATIONS and isinstance(value, types.ModuleType):
            value = getattr(value, name, value)
        super().__setattr__(name, value)


def backend_package(name: str) -> None:
    """Turn the package ``name`` (a backend's ``__init__`` passes ``__name__``) into a backend package: its
    :data:`OPERATIONS` resolve lazily to the functions of its submodules of the same names."""
    sys.modules[name].__class__ = _BackendPackage


class BackendUnavailable(FruxelError, RuntimeError):
    """Raised when a chosen backend cannot be imported or has no usable device; the message has an install hint."""


class BackendError(FruxelError, ValueError):
    """Raised for an unknown backend or device name."""


@dataclass(frozen=True)
class BackendInfo:
    """Static description of one backend."""

    name: str
    """Registry name: ``"warp"`` or ``"opencl"``."""
    module: str
    """Module implementing :data:`OPERATIONS`."""
    install_hint: str
    """What to run when the backend is missing."""
    device_hint: str = ""
    """What to install when the backend imports but finds no device it can run on (empty: nothing helps)."""


BACKENDS: dict[str, BackendInfo] = {
    "warp": BackendInfo("warp", "fruxel.kernels.wp", "pip install 'fruxel[warp]'  (NVIDIA Warp: warp-lang)"),
    "opencl": BackendInfo(
        "opencl",
        "fruxel.kernels.cl",
        "pip install 'fruxel[opencl]'  (pyopencl plus pocl-binary-distribution, PoCL's CPU OpenCL driver)",
        "a PoCL whose LLVM knows this CPU, on Debian or Ubuntu: sudo apt-get install -y --no-install-recommends "
        "pocl-opencl-icd (scripts/setup_env.sh does it when run as root)",
    ),
}


@cache
def _load(name: str) -> ModuleType:
    info = BACKENDS[name]
    try:
        mod = importlib.import_module(info.module)
    except ImportError as e:
        msg = f"backend {name!r} is not installed ({e}). Install it with: {info.install_hint}"
        raise BackendUnavailable(msg) from None
    return mod


def get_backend(name: str) -> ModuleType:
    """The module of backend ``name`` (``"warp"`` or ``"opencl"``), imported on first use.

    Raises:
        BackendError: an unknown name.
        BackendUnavailable: the backend's packages are missing or it finds no device; the message says what to
            install.
    """
    if name not in BACKENDS:
        raise BackendError(f"unknown backend {name!r}; choose one of {sorted(BACKENDS)}")
    mod = _load(name)
    if not mod.is_available():
        raise BackendUnavailable(no_device_message(name, mod.unavailable_reason()))
    return mod


def no_device_message(name: str, cause: str) -> str:
    """The one-line error of backend ``name`` finding no usable device: the cause and the fix."""
    hint = BACKENDS[name].device_hint
    return f"backend {name!r} found no usable device: {cause}" + (f". Fix: install {hint}" if hint else "")


def _try(name: str) -> ModuleType | None:
    try:
        return get_backend(name)
    except BackendUnavailable:
        return None


def available_backends() -> list[str]:
    """Backends usable here, fastest first, with Warp split by device: e.g. ``["warp-cuda", "warp-cpu", "opencl"]``.

    Test suites parametrise over this list (ids are these names).
    """
    out = []
    wp = _try("warp")
    cl = _try("opencl")
    if wp is not None and wp.cuda_available():
        out.append("warp-cuda")
    if wp is not None and wp.cpu_available():
        out.append("warp-cpu")
    if cl is not None:
        out.append("opencl")
    return out


def split_name(name: str) -> tuple[str, str | None]:
    """``"warp-cuda"`` -> ``("warp", "cuda")``, ``"opencl"`` -> ``("opencl", None)``: names from
    :func:`available_backends` back into ``(backend, device)`` arguments."""
    if name in BACKENDS:
        return name, None
    base, _, dev = name.partition("-")
    if base not in BACKENDS or not dev:
        raise BackendError(f"unknown backend {name!r}; choose one of {sorted(BACKENDS)} or {available_backends()}")
    return base, dev


def is_cuda_data(volume: Any) -> bool:
    """True when ``volume`` is a torch tensor on a CUDA device (checked without importing torch)."""
    dev = getattr(volume, "device", None)
    return getattr(dev, "type", None) == "cuda"


def resolve(backend: str | None, device: str | None, volume: Any = None) -> tuple[ModuleType, str | None]:
    """Pick the backend module and Warp device for a call.

    ``backend=None`` takes the best available: Warp on CUDA when a GPU is present, else OpenCL, else Warp on
    the CPU (single-threaded, hence last); an OpenCL that is installed but has no working device is skipped with
    one warning per process, naming the cause and the fix. ``device=None`` follows the data: a CUDA tensor stays
    on its device; other data goes to CUDA when the chosen backend is Warp and a GPU is present, else to the CPU.

    Returns:
        (module, device): device is a Warp device string (``"cpu"``, ``"cuda:0"``) for Warp, or the OpenCL
        device selector (None = first GPU, else first CPU) for OpenCL.
    """
    if backend is not None and "-" in backend:
        backend, dev2 = split_name(backend)
        device = device or dev2
    if backend is None:
        wp = _try("warp")
        if wp is not None and wp.cuda_available():
            backend = "warp"
        elif _try("opencl") is not None:
            backend = "opencl"
        elif wp is not None and wp.cpu_available():
            _warn_skipped("opencl", "Warp on the CPU")
            backend = "warp"
        else:
            raise BackendUnavailable(
                "no compute backend is installed. Install one with: "
                + " or ".join(info.install_hint for info in BACKENDS.values())
            )
    mod = get_backend(backend)
    if device is None and is_cuda_data(volume):
        device = str(volume.device)
    return mod, mod.resolve_device(device)


_warned: set[str] = set()
"""Backends whose fallback warning was given (once per process)."""


def _warn_skipped(name: str, instead: str) -> None:
    """Warn, once per process, that backend ``name`` is installed but cannot run here, so that ``instead`` runs; a
    backend that is simply not installed is skipped silently."""
    if name in _warned:
        return
    try:
        mod = _load(name)
    except BackendUnavailable:
        return
    _warned.add(name)
    warnings.warn(f"{no_device_message(name, mod.unavailable_reason())}; {instead} runs instead", RuntimeWarning,
                  stacklevel=3)


def describe(backend: str | None = None, device: str | None = None, volume: Any = None) -> str:
    """Name of the backend and device that :func:`resolve` picks for these arguments, for captions and logs:
    ``"opencl"``, ``"warp-cpu"``, ``"warp-cuda:0"``."""
    mod, dev = resolve(backend, device, volume)
    name = next(n for n, info in BACKENDS.items() if info.module == mod.__name__)
    return f"{name}-{dev}" if name == "warp" and dev else name

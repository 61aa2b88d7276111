"""OpenCL backend (pyopencl; PoCL on the CPU, or any OpenCL CPU/GPU device present).

The same functions and signatures as every other backend (see :mod:`fruxel.kernels.registry`). Each operation
lives in its own module beside its kernel source and is imported on first use, so that importing the backend
to ask :func:`is_available` stays cheap.
"""

from __future__ import annotations

import importlib
import sys
import types
from typing import Any

from .runtime import cpu_available, cuda_available, is_available, resolve_device, unavailable_reason

__all__ = ["cpu_available", "cuda_available", "first_hit", "is_available", "resolve_device", "shell", "soft_first_hit",
           "unavailable_reason"]

_OPERATIONS = {"first_hit": ".first_hit", "shell": ".shell", "soft_first_hit": ".soft_first_hit"}


def __getattr__(name: str) -> Any:
    if name in _OPERATIONS:
        return getattr(importlib.import_module(_OPERATIONS[name], __name__), name)
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class _Backend(types.ModuleType):
    """The package's module type: importing submodule ``.first_hit`` makes Python bind the package attribute
    ``first_hit`` to that module, which would hide the function of the same name; keep the function instead."""

    def __setattr__(self, name: str, value: Any) -> None:
        if name in _OPERATIONS and isinstance(value, types.ModuleType):
            value = getattr(value, name)
        super().__setattr__(name, value)


sys.modules[__name__].__class__ = _Backend

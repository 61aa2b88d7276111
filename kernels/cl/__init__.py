"""OpenCL backend (pyopencl; PoCL on the CPU, or any OpenCL CPU/GPU device present).

The same functions and signatures as every other backend (see :mod:`fruxel.kernels.registry`). Each operation
lives in its own module beside its kernel source and is imported on first use, so that importing the backend
to ask :func:`is_available` stays cheap.
"""

from __future__ import annotations

from ..registry import backend_package
from .runtime import cpu_available, cuda_available, is_available, resolve_device, unavailable_reason

__all__ = ["cpu_available", "cuda_available", "first_hit", "is_available", "resolve_device", "shell", "soft_first_hit",
           "unavailable_reason"]

backend_package(__name__)

"""Zero-copy conversions between numpy / torch and Warp, and the workspace of one kernel call.

Every Warp operation of fruxel runs the same way: inputs come as numpy arrays or torch tensors (CPU or CUDA),
kernels run on one Warp device, results go back in the caller's kind of array on the caller's device.
:class:`Workspace` holds that decision for one call:

* memory: torch callers get torch allocations on the compute device (torch's caching allocator is cheap and
  stream-ordered, and results need no conversion); numpy callers get numpy arrays wrapped without a copy when
  Warp runs on the CPU, Warp allocations when it runs on CUDA;
* stream: with torch on CUDA, torch's current stream of the device, so kernels run in order with the caller's
  torch work and nothing needs a host synchronisation; otherwise Warp's current stream of the device;
* inputs: wrapped without a copy where kind, device, dtype and layout allow, converted once otherwise;
* launches: replayed from a per-thread cache of Warp's recorded launches (``wp.launch(..., record_cmd=True)``, one
  per kernel overload, launch dimensions and buffer shapes) through the :class:`warp.Launch` methods
  ``set_param_at_index_from_ctype`` and ``launch``; an array argument is set again only where its address changed.
  A fraction of ``wp.launch``'s cost, which matters on CUDA, where a call's kernels take tens of microseconds;
* results: handed back as the caller's kind on the caller's device.

Warp documents the recorded launch and its setters, but not the ctypes structures they take, nor how long a recorded
launch stays valid. Three undocumented behaviours of Warp (1.19) are relied on, each checked by
``tests/kernels/test_wp_arrays.py``, so that a Warp upgrade that changes one fails there:

* the array descriptor (:data:`_ARRAY_DESCRIPTOR`, Warp's ``array_t``), which :meth:`Buffer.make_descriptor` fills
  without making a Warp array;
* the ``__ctype__()`` protocol by which Warp packs a struct argument (:class:`Packed` provides it for structures
  built directly; Warp's own struct instances have it);
* a recorded launch holds the module build it was recorded with, so it stays valid if Warp rebuilds the module.

Torch is imported only when the caller passes torch tensors, so the backend works without it.
"""

from __future__ import annotations

import ctypes
import math
import threading
from collections import OrderedDict
from typing import Any

import numpy as np

from ..inputs import is_torch
from .runtime import resolve_device, warp

wp = warp()

_ARRAY_DESCRIPTOR = type(wp.empty(1, dtype=wp.uint8, device="cpu").__ctype__())
"""Warp's array descriptor, ``array_t`` (fields ``data``, ``grad``, ``shape``, ``strides``, ``ndim``): the ctypes
structure a Warp array packs into a kernel parameter. Warp documents no constructor for it, so its type is taken
from what a Warp array's ``__ctype__()`` (the method Warp's own launches call) returns."""


def scalar_type(dtype: Any) -> Any:
    """The Warp scalar type of a Warp scalar, vector or matrix dtype (``wp.vec3`` -> ``wp.float32``)."""
    return getattr(dtype, "_wp_scalar_type_", dtype)


def inner_shape(dtype: Any) -> tuple[int, ...]:
    """Trailing axes a Warp dtype occupies in numpy / torch (``wp.vec3`` -> ``(3,)``, scalars -> ``()``)."""
    return tuple(getattr(dtype, "_shape_", ()))


def numpy_dtype(dtype: Any) -> np.dtype:
    """numpy dtype of a Warp scalar / vector dtype's scalar."""
    return np.dtype(wp.dtype_to_numpy(scalar_type(dtype)))


def torch_dtype(dtype: Any) -> Any:
    """torch dtype of a Warp scalar / vector dtype's scalar."""
    return wp.dtype_to_torch(scalar_type(dtype))


def device_of(x: Any) -> str:
    """Device string of a numpy array (``"cpu"``) or torch tensor (``"cpu"``, ``"cuda:0"``)."""
    if is_torch(x):
        d = x.device
        return "cpu" if d.type == "cpu" else f"{d.type}:{d.index if d.index is not None else 0}"
    return "cpu"


def compute_device(x: Any, device: Any = None) -> str:
    """The Warp device to compute on: ``device`` when given, else the CUDA device of a CUDA tensor ``x``, else
    the default (CUDA when present, else the CPU). See :func:`~fruxel.kernels.wp.runtime.resolve_device`."""
    if device is None and is_torch(x) and x.device.type == "cuda":
        device = device_of(x)
    return resolve_device(device)


class Buffer:
    """One C-contiguous array of a call on the compute device, seen as the caller's kind of array and by Warp.

    Vector dtypes (``wp.vec3``) consume trailing axes: a ``(B, h, w)`` Buffer of ``wp.vec3`` has a
    ``(B, h, w, 3)`` float32 ``native`` array. (A plain slotted class: a call makes several, and a frozen
    dataclass costs microseconds per construction.)

    Attributes:
        native: numpy array or torch tensor owning the memory, or (numpy callers on CUDA) a ``warp.array``.
        shape: Warp shape (without the trailing axes of a vector dtype).
        dtype: Warp dtype.
        ptr: address of the first element.
        device: Warp device the memory is on.
    """

    __slots__ = ("device", "dtype", "native", "ptr", "shape")

    def __init__(self, native: Any, shape: tuple[int, ...], dtype: Any, ptr: int, device: str) -> None:
        self.native = native
        self.shape = shape
        self.dtype = dtype
        self.ptr = ptr
        self.device = device

    @classmethod
    def of(cls, native: Any, dtype: Any, device: str) -> Buffer:
        """Wrap a C-contiguous numpy array, torch tensor or ``warp.array`` whose elements are ``dtype``."""
        if isinstance(native, np.ndarray):
            shape, ptr = native.shape, native.ctypes.data
        elif isinstance(native, wp.array):
            return cls(native, tuple(native.shape), dtype, native.ptr or 0, device)
        else:
            shape, ptr = tuple(native.shape), native.data_ptr()
        inner = len(inner_shape(dtype))
        return cls(native, shape[: len(shape) - inner] if inner else shape, dtype, ptr, device)

    def make_descriptor(self) -> Any:
        """A new Warp array descriptor (:data:`_ARRAY_DESCRIPTOR`) of this buffer, C-contiguous strides and no
        gradient, as a Warp array of it would pack itself; for launch parameters. It holds no reference to the
        memory."""
        n = len(self.shape)
        strides, acc = [0] * n, wp.types.type_size_in_bytes(self.dtype)
        for axis in range(n - 1, -1, -1):
            strides[axis] = acc
            acc *= self.shape[axis]
        desc = _ARRAY_DESCRIPTOR()
        desc.data = self.ptr
        desc.ndim = n
        desc.shape[:n] = self.shape
        desc.strides[:n] = strides
        return desc

    def array(self) -> Any:
        """This buffer as a ``warp.array`` (no copy)."""
        if isinstance(self.native, wp.array):
            return self.native
        if isinstance(self.native, np.ndarray):
            return wp.array(self.native, dtype=self.dtype, device="cpu", copy=False)
        return wp.from_torch(self.native, dtype=self.dtype, requires_grad=False)

    @property
    def size(self) -> int:
        """Number of Warp elements."""
        return math.prod(self.shape)


class Packed:
    """A struct launch argument already packed as its ctypes structure (Warp accepts anything with
    ``__ctype__``); building the ctypes structure directly is much cheaper than setting a Warp struct's fields."""

    __slots__ = ("value",)

    def __init__(self, value: ctypes.Structure) -> None:
        self.value = value

    def __ctype__(self) -> ctypes.Structure:
        return self.value


_local = threading.local()
_STREAM_CACHE_SIZE = 16


_COMMAND_CACHE_SIZE = 256
"""Prepared launches kept per thread (one per kernel overload, device, launch dimensions and buffer shapes)."""


def prepared_launches() -> OrderedDict:
    """This thread's cache of prepared launches, least recently used first: keyed by kernel, device, launch
    dimensions and buffer shapes (tests count and clear it)."""
    cache = getattr(_local, "commands", None)
    if cache is None:
        cache = _local.commands = OrderedDict()
    return cache


class _Prepared:
    """A recorded Warp launch (``wp.launch(..., record_cmd=True)``), replayed with each call's arguments.

    Arguments are written with :meth:`warp.Launch.set_param_at_index_from_ctype`: structs and scalars on every
    launch, arrays as descriptors owned here, set again only where the buffer's address changed since (a parameter
    keeps the value it was last set to). The first launch sets every argument, which also replaces the recording's
    references to the first call's arrays, so a cached command keeps no memory alive.

    Args:
        kernel, device, dim, args, block_dim: as for :meth:`Workspace.launch` (the first call's arguments).
    """

    __slots__ = ("cmd", "descriptors", "ptrs")

    def __init__(self, kernel: Any, device: str, dim: tuple[int, ...], args: list[Any], block_dim: int) -> None:
        values = [a.array() if isinstance(a, Buffer) else a for a in args]
        self.cmd = wp.launch(kernel, dim=dim, inputs=values, device=device, record_cmd=True,
                             block_dim=block_dim or None)
        self.descriptors = [a.make_descriptor() if isinstance(a, Buffer) else None for a in args]
        self.ptrs: list[int | None] = [None] * len(args)  # per array argument, the address last set (None: none)

    def launch(self, args: list[Any], stream: Any) -> None:
        """Write ``args`` into the command and launch it on ``stream`` (None: the device's current stream)."""
        cmd, descriptors, ptrs = self.cmd, self.descriptors, self.ptrs
        for i, a in enumerate(args):
            desc = descriptors[i]
            if desc is None:
                # Structs pack themselves (__ctype__); Warp scalars (wp.float64(x)) hold their value in .value.
                value = a.__ctype__() if hasattr(a, "__ctype__") else getattr(a, "value", a)
                cmd.set_param_at_index_from_ctype(i, value)
            elif a.ptr != ptrs[i]:
                desc.data = ptrs[i] = a.ptr
                cmd.set_param_at_index_from_ctype(i, desc)
        cmd.launch(stream)


def _torch_stream(device: Any) -> Any:
    """Warp's view of torch's current stream on ``device``, cached per stream handle (creating one per call would
    cost more than a launch)."""
    import torch

    handle = torch.cuda.current_stream(device).cuda_stream
    cache = getattr(_local, "streams", None)
    if cache is None:
        cache = _local.streams = OrderedDict()
    key = (str(device), handle)
    stream = cache.get(key)
    if stream is None:
        stream = cache[key] = wp.stream_from_torch(device)
        if len(cache) > _STREAM_CACHE_SIZE:
            cache.popitem(last=False)
    else:
        cache.move_to_end(key)
    return stream


class Workspace:
    """Memory, stream, launches and result conversion for one call of a Warp operation.

    Args:
        device: Warp device the kernels run on (``"cpu"``, ``"cuda:N"``).
        kind: the caller's kind of array, ``"numpy"`` or ``"torch"``.
        home: the caller's device (where its data lives and where results go back): ``"cpu"``, ``"cuda:N"``.
    """

    def __init__(self, device: str, kind: str, home: str = "cpu") -> None:
        if kind not in ("numpy", "torch"):
            raise ValueError(f"kind must be 'numpy' or 'torch', got {kind!r}")
        self.device = device
        self.kind = kind
        self.home = home
        self.is_cuda = device.startswith("cuda")
        self.stream = None
        if kind == "torch":
            import torch

            self._torch = torch
            self.torch_device = torch.device(device)
            if self.is_cuda:
                self.stream = _torch_stream(self.torch_device)

    @classmethod
    def like(cls, x: Any, device: str) -> Workspace:
        """The workspace for caller data ``x`` (numpy array or torch tensor) computed on Warp ``device``."""
        return cls(device, "torch" if is_torch(x) else "numpy", device_of(x))

    # ------------------------------------------------------------------ memory
    def empty(self, shape: tuple[int, ...], dtype: Any, *, zero: bool = False) -> Buffer:
        """A new C-contiguous array on the compute device, in the caller's kind where the device allows.

        Args:
            shape: Warp shape (without the trailing axes of a vector dtype).
            dtype: Warp dtype (``wp.int32``, ``wp.vec3``, ...).
            zero: fill with zeros (in stream order) rather than leave uninitialised.
        """
        full = tuple(shape) + inner_shape(dtype)
        if self.kind == "torch":
            make = self._torch.zeros if zero else self._torch.empty
            return Buffer.of(make(full, dtype=torch_dtype(dtype), device=self.torch_device), dtype, self.device)
        if not self.is_cuda:
            return Buffer.of((np.zeros if zero else np.empty)(full, dtype=numpy_dtype(dtype)), dtype, "cpu")
        # Warp allocates and zeroes on the device's current Warp stream, the stream this call launches on.
        return Buffer.of((wp.zeros if zero else wp.empty)(tuple(shape), dtype=dtype, device=self.device), dtype,
                         self.device)

    def input(self, x: Any, *, shape: tuple[int, ...] | None = None, dtype: Any = None) -> Buffer:
        """Caller data as a C-contiguous array on the compute device, without a copy where possible.

        A copy is made only where one is needed: another device, another dtype, or a layout that ``shape``
        cannot view. Dtype conversion happens before a device transfer when it narrows the data.

        Args:
            x: numpy array or torch tensor (CPU or CUDA).
            shape: reshape to this shape first (a view where the layout allows).
            dtype: Warp scalar dtype to convert to, or None to keep the data's dtype.
        """
        if self.kind == "torch" or is_torch(x):
            return self._torch_input(x, shape, dtype)
        a = np.asarray(x)
        if shape is not None:
            a = a.reshape(shape)
        a = np.ascontiguousarray(a, dtype=None if dtype is None else numpy_dtype(dtype))
        wdt = wp.dtype_from_numpy(a.dtype) if dtype is None else dtype
        if not self.is_cuda:
            return Buffer.of(a, wdt, "cpu")
        # Host-to-device copy, ordered on the device's current Warp stream like the launches that read it.
        return Buffer.of(wp.array(a, dtype=wdt, device=self.device), wdt, self.device)

    def _torch_input(self, x: Any, shape: tuple[int, ...] | None, dtype: Any) -> Buffer:
        import torch

        t = x.detach() if is_torch(x) else torch.from_numpy(np.ascontiguousarray(x))
        if shape is not None:
            t = t.reshape(shape)
        target = None if dtype is None else torch_dtype(dtype)
        if target is not None and target.itemsize <= t.dtype.itemsize:
            t = t.to(target)  # narrowing: convert before a transfer, which then moves fewer bytes
        t = t.to(self.device)
        if target is not None:
            t = t.to(target)
        t = t.contiguous()
        if self.is_cuda and self.kind != "torch":
            # A torch tensor in a numpy call on CUDA: torch wrote it on its own stream, which the Warp launches of
            # this call do not follow; wait for that stream.
            torch.cuda.current_stream(t.device).synchronize()
        return Buffer.of(t, dtype if dtype is not None else wp.dtype_from_torch(t.dtype), self.device)

    # ------------------------------------------------------------------ work
    def launch(self, kernel: Any, dim: tuple[int, ...], args: list[Any], block_dim: int = 0) -> None:
        """Launch ``kernel`` over ``dim`` on the compute device, on this call's stream (asynchronous on CUDA).

        The first launch of a kernel overload with given buffer shapes on a device records a Warp launch
        (resolving a generic kernel's overload from the buffers' dtypes); later launches write their arguments into
        it (:class:`_Prepared`). A launch copies its parameters (CUDA) or runs at once (CPU), so rewriting them
        afterwards is safe. A recorded launch runs the module build it was recorded with, which Warp's ``Launch``
        keeps loaded (module docstring), also if Warp rebuilds the module later; fruxel's modules get their kernels
        and options before their first launch, so that build is the current one.

        Args:
            kernel: a Warp kernel.
            dim: launch dimensions.
            args: the kernel's arguments in order: :class:`Buffer` for arrays, Warp struct instances or
                :class:`Packed` structures for structs, Python numbers for int32 / float32 scalars and Warp scalars
                (``wp.float64(x)``) for other scalar types.
            block_dim: CUDA threads per block; 0 takes Warp's default (256).
        """
        dim = tuple(int(x) for x in dim)
        if math.prod(dim) == 0:
            return
        cache = prepared_launches()
        key = (kernel, self.device, block_dim, dim, *(_arg_key(a) for a in args))
        prepared = cache.get(key)
        if prepared is None:
            prepared = _Prepared(kernel, self.device, dim, args, block_dim)
            cache[key] = prepared
            if len(cache) > _COMMAND_CACHE_SIZE:
                cache.popitem(last=False)
        else:
            cache.move_to_end(key)
        prepared.launch(args, self.stream)

    # ------------------------------------------------------------------ results
    def result(self, buf: Buffer | Any, *, shape: tuple[int, ...] | None = None, dtype: Any = None) -> Any:
        """``buf`` (a :class:`Buffer`, or an array of its ``native`` kind) as the caller's kind of array on the
        caller's device, reshaped to ``shape`` and converted to ``dtype`` (a numpy or torch dtype of the caller's
        kind) when given; no copy where none is needed.
        """
        n = buf.native if isinstance(buf, Buffer) else buf
        if self.kind == "torch":
            if shape is not None and n.shape != shape:
                n = n.reshape(shape)
            if dtype is not None and n.dtype != dtype:
                n = n.to(dtype)
            # A cross-device move is a torch copy in torch's stream order; only a copy to the CPU waits for it.
            return n if self.home == self.device else n.to(self.home)
        if not isinstance(n, np.ndarray):
            # Device-to-host copy: it waits for this call's kernels, because numpy callers get finished host data.
            n = n.numpy()
        if shape is not None:
            n = n.reshape(shape)
        return n if dtype is None else n.astype(dtype, copy=False)


def _arg_key(a: Any) -> Any:
    """What of a launch argument a prepared launch is specific to: a buffer's dtype and shape, a scalar's type."""
    if isinstance(a, Buffer):
        return (a.dtype, a.shape)
    return type(a)

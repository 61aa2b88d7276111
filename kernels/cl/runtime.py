"""OpenCL runtime of the fruxel kernels: device choice, one context and queue per device, programs built once
per context, host <-> device transfers, and conversions between the caller's arrays and host arrays.

Devices are probed, not trusted: the first time a device is considered, a tiny kernel is built and run on it
(:data:`PROBE_SOURCE`, once per process; PoCL caches the build across processes). A device whose compiler fails is
skipped, its compiler message kept for :func:`unavailable_reason` (the registry adds the fix). This matters on CPUs
newer than the LLVM inside a PoCL: the PyPI ``pocl-binary-distribution`` 3.0 (LLVM 14) fails every build on an AMD
Zen 5 (CPU family 26) with "unknown target CPU 'generic'", while Debian's ``pocl-opencl-icd`` (PoCL 3.1, LLVM 15)
compiles there, and pyopencl's ICD loader lists both when both are installed.

Device selectors (what :func:`resolve_device` returns and :func:`get_runtime` takes): ``None`` or ``"gpu"`` (the
first working GPU, else the first working CPU) or ``"cpu"`` (the first working CPU, else GPU). Candidates are tried
GPUs first; among CPU devices, PoCL before other drivers and the newer PoCL first (see :func:`rank`); the environment
variable ``FRUXEL_OPENCL_DEVICE`` keeps only the devices whose name or platform version contains its value. Warp-style
names (``"cuda"``, ``"cuda:1"``) map to ``"gpu"`` so that data on a CUDA device can ask for "the GPU" without
knowing about OpenCL platforms.

Memory: on a device that shares the host's memory (PoCL on the CPU) the caller's arrays and the result arrays
are wrapped as ``CL_MEM_USE_HOST_PTR`` buffers, so kernels read and write them in place with no copy; elsewhere
they are copied through device buffers kept in a per-runtime pool and reused by calls of the same size. No
result of a previous call is ever reused: the pool holds storage only.

Thread safety: every operation holds :attr:`Runtime.lock` for its whole call (kernel objects and pooled
buffers are shared state).

Builds are quiet (:func:`quiet_build`): a compiler that warns about a kernel (PoCL's clang writes "N warnings
generated." to the terminal itself, and pyopencl adds a two-line ``CompilerWarning`` on every later run, from its
cache) says nothing to the users of fruxel's commands. ``PYOPENCL_COMPILER_OUTPUT=1``, pyopencl's own switch, shows
the compilers' output again, for work on the kernels. A build that fails still raises with the compiler's message.
"""

from __future__ import annotations

import contextlib
import os
import re
import sys
import tempfile
import threading
import warnings
from collections.abc import Iterator
from dataclasses import dataclass, field
from functools import cache
from pathlib import Path
from typing import Any

import numpy as np

from ..inputs import VolumeSpec, is_torch
from ..registry import BackendError, BackendUnavailable, no_device_message

try:
    import pyopencl as cl
    import pyopencl.cltypes as cl_types

    _IMPORT_ERROR: str | None = None
except ImportError as _e:  # pragma: no cover - exercised only without pyopencl
    cl = cl_types = None
    _IMPORT_ERROR = str(_e)

BUILD_OPTIONS = ("-cl-fp32-correctly-rounded-divide-sqrt", "-cl-kernel-arg-info")
"""Options every fruxel program is built with: correctly rounded division and square root on every device (GPU
compilers otherwise approximate them), so that crossings are the float32 values kernels/traversal.py describes;
never ``-cl-fast-relaxed-math`` or ``-cl-mad-enable``, which would change results. The kernels' argument types
are kept (``-cl-kernel-arg-info``) so that :meth:`Runtime.kernel` can give pyopencl their types."""


PROBE_SOURCE = """
__kernel void probe_kernel(__global float* out)
{
    const int i = get_global_id(0);
    const float4 v = (float4)((float)i, 1.0f, 2.0f, 3.0f) + 1.0f;
    out[i] = (v.x + v.w) / 3.0f;
}

__kernel void lanes_kernel(__global int* out)
{
#if defined(__AVX512F__)
    out[0] = 16;
#else
    out[0] = 8;
#endif
}
"""
"""The kernel every candidate device must build (with :data:`BUILD_OPTIONS`) and run correctly before it is used,
and one that says how many float lanes the device's compiler makes vector code of (:attr:`Runtime.lanes`)."""

# ---------------------------------------------------------------------------------------------- devices
@dataclass(frozen=True)
class DeviceStatus:
    """A candidate OpenCL device and what its probe found."""

    device: Any
    """The ``pyopencl.Device``."""
    kind: str
    """``"gpu"`` or ``"cpu"``."""
    error: str | None
    """None when the probe kernel built and ran correctly, else why not (the compiler's message)."""

    @property
    def description(self) -> str:
        """``"name (platform version)"``, e.g. ``"pthread-skylake-avx512-AMD EPYC (OpenCL 3.0 PoCL 3.1+debian)"``."""
        return f"{self.device.name.strip()} ({platform_version(self.device)})"


def platform_version(device: Any) -> str:
    """The device's platform version string up to its build details, e.g. ``"OpenCL 3.0 PoCL 3.1+debian"``."""
    return device.platform.version.split("  ")[0].strip()


def pocl_version(device: Any) -> tuple[int, ...] | None:
    """``(major, minor)`` of the PoCL that runs ``device``, or None for another OpenCL driver."""
    m = re.search(r"PoCL (\d+)\.(\d+)", device.platform.version)
    return (int(m.group(1)), int(m.group(2))) if m else None


def rank(devices: list[Any]) -> list[Any]:
    """Candidates in the order they are tried: GPUs, then CPU devices run by PoCL, newest PoCL first, then other CPU
    drivers; ties keep the platforms' order."""

    def key(d: Any) -> tuple[int, tuple[int, ...]]:
        if d.type & cl.device_type.GPU:
            return (0, ())
        v = pocl_version(d)
        return (1, tuple(-x for x in v)) if v is not None else (2, ())

    return sorted(devices, key=key)


def _kind(device: Any) -> str:
    return "gpu" if device.type & cl.device_type.GPU else "cpu"


@cache
def _platform_devices() -> tuple[tuple[Any, ...], str]:
    """Every CPU and GPU OpenCL device in probe order (:func:`rank`), and why there is none."""
    if cl is None:
        return (), f"pyopencl is not importable ({_IMPORT_ERROR})"
    try:
        platforms = cl.get_platforms()
    except Exception as e:  # noqa: BLE001 - any ICD loader failure means "no device"
        return (), f"no OpenCL platform found ({one_line_message(str(e))})"
    devs = []
    for p in platforms:
        try:
            devs += [d for d in p.get_devices() if d.type & (cl.device_type.GPU | cl.device_type.CPU)]
        except Exception:  # noqa: BLE001, S112 - a broken platform must not hide the others
            continue
    return tuple(rank(devs)), "" if devs else "the OpenCL platforms have no CPU or GPU device"


@contextlib.contextmanager
def quiet_build() -> Iterator[None]:
    """Around an OpenCL build: no ``pyopencl.CompilerWarning``, and what the compiler writes to the process's
    standard error itself (clang's "N warnings generated.") is dropped, unless ``PYOPENCL_COMPILER_OUTPUT`` asks for
    it. Standard error is redirected at the file descriptor for the build's time (other threads' writes to it
    are dropped as well; builds take a moment, once per program and process)."""
    if os.environ.get("PYOPENCL_COMPILER_OUTPUT", "").strip().lower() not in ("", "0", "false", "no", "off"):
        yield
        return
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", cl.CompilerWarning)
        try:
            sys.stderr.flush()
            saved = os.dup(2)
        except (AttributeError, OSError, ValueError):
            saved = -1
        if saved < 0:
            yield
            return
        try:
            with tempfile.TemporaryFile() as sink:
                os.dup2(sink.fileno(), 2)
                yield
        finally:
            os.dup2(saved, 2)
            os.close(saved)


def one_line_message(message: str, limit: int = 400) -> str:
    """A compiler's or driver's message as one line: its error lines (else all of it), joined, shortened."""
    lines = [ln.strip() for ln in message.splitlines() if ln.strip()]
    errors = [ln for ln in lines if "error" in ln.lower() and not ln.startswith("clBuildProgram failed")]
    text = "; ".join(errors or lines)
    return text if len(text) <= limit else text[: limit - 3] + "..."


def probe_device(device: Any) -> str | None:
    """Build and run :data:`PROBE_SOURCE` on ``device`` (in its runtime, which is kept): None when it works, else
    why not."""
    try:
        rt = _runtime_for(device)
        out = np.zeros(4, np.float32)
        buf = cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY, out.nbytes)
        with quiet_build():
            prg = cl.Program(rt.context, PROBE_SOURCE).build(options=list(BUILD_OPTIONS))
        kernel = prg.probe_kernel
        kernel(rt.queue, (4,), None, buf)
        lanes = np.zeros(1, np.int32)
        lanes_buf = cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY, lanes.nbytes)
        prg.lanes_kernel(rt.queue, (1,), None, lanes_buf)
        cl.enqueue_copy(rt.queue, lanes, lanes_buf)
        cl.enqueue_copy(rt.queue, out, buf)  # blocking: the probe's only synchronisation
        rt.lanes = int(lanes[0])
    except Exception as e:  # noqa: BLE001 - whatever the driver raises, the device is unusable
        return one_line_message(str(e)) or type(e).__name__
    want = (np.arange(4, dtype=np.float32) + 1 + 4) / np.float32(3)
    if not np.array_equal(out, want):
        return f"the probe kernel ran but computed {out.tolist()} instead of {want.tolist()}"
    if rt.zero_copy:
        # Does the device write host arrays in place? Tried on an array aligned to 4 bytes only, the least any
        # result array has.
        raw = np.zeros(32, np.uint8)
        start = (-raw.ctypes.data) % 64 + 4
        host = raw[start:start + 16].view(np.float32)
        try:
            buf = cl.Buffer(rt.context, cl.mem_flags.WRITE_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=host)
            kernel(rt.queue, (4,), None, buf)
            rt.queue.finish()  # the kernel is done; no map
            rt.writes_in_place = bool(np.array_equal(host, want))
        except Exception:  # noqa: BLE001 - then results are mapped, as OpenCL asks
            rt.writes_in_place = False
    return None


_status: dict[int, DeviceStatus] = {}
"""Probe results by position in :func:`_platform_devices`, filled on first use."""


def _status_of(index: int) -> DeviceStatus:
    st = _status.get(index)
    if st is None:
        dev = _platform_devices()[0][index]
        st = DeviceStatus(device=dev, kind=_kind(dev), error=probe_device(dev))
        _status[index] = st
    return st


DEVICE_ENV = "FRUXEL_OPENCL_DEVICE"
"""Environment variable that restricts the candidates to devices whose ``"name (platform version)"`` contains its
value, e.g. ``FRUXEL_OPENCL_DEVICE="PoCL 3.0"`` to run on the PyPI PoCL where Debian's is installed too."""


def _chosen(index: int) -> bool:
    want = os.environ.get(DEVICE_ENV, "").strip()
    return not want or want in DeviceStatus(_platform_devices()[0][index], "", None).description


_chosen_by: dict[tuple[tuple[str, ...], str], Any] = {}
""":func:`_first_working`'s answers by kinds and :data:`DEVICE_ENV` value (every call asks it, several times)."""


def _first_working(kinds: tuple[str, ...]) -> Any | None:
    """The first device in probe order of one of ``kinds`` (in that order of preference) whose probe succeeds,
    probing candidates only until one does (only those :data:`DEVICE_ENV` admits)."""
    key = (kinds, os.environ.get(DEVICE_ENV, ""))
    if key not in _chosen_by:
        _chosen_by[key] = _search(kinds)
    return _chosen_by[key]


def _search(kinds: tuple[str, ...]) -> Any | None:
    devs = _platform_devices()[0]
    for kind in kinds:
        for i, d in enumerate(devs):
            if _kind(d) == kind and _chosen(i) and _status_of(i).error is None:
                return d
    return None


def device_report() -> list[DeviceStatus]:
    """Every candidate device with its probe result (probing those not yet probed), in probe order."""
    return [_status_of(i) for i in range(len(_platform_devices()[0]))]


def forget_devices() -> None:
    """Forget the device list and probe results (tests that swap the platforms use it)."""
    _platform_devices.cache_clear()
    _status.clear()
    _chosen_by.clear()


def is_available() -> bool:
    """True when pyopencl imports and some CPU or GPU OpenCL device builds and runs the probe kernel."""
    return _first_working(("gpu", "cpu")) is not None


def unavailable_reason() -> str:
    """Why :func:`is_available` is False: no device, or each device's probe failure (empty when it is True). The
    registry adds the fix (:data:`fruxel.kernels.registry.BACKENDS`)."""
    if is_available():
        return ""
    devs, reason = _platform_devices()
    if not devs:
        return reason
    report = [st for i, st in enumerate(device_report()) if _chosen(i)]
    if not report:
        names = "; ".join(st.description for st in device_report())
        return f"{DEVICE_ENV}={os.environ.get(DEVICE_ENV)!r} matches none of the OpenCL devices ({names})"
    failed = "; ".join(f"{st.description}: {st.error}" for st in report)
    return f"no OpenCL device can build a kernel here ({failed})"


def cpu_available() -> bool:
    """True when a working OpenCL CPU device exists (registry contract, same name in every backend)."""
    return _first_working(("cpu",)) is not None


def cuda_available() -> bool:
    """Always False: this backend never runs on CUDA itself (registry contract, used to rank backends)."""
    return False


def resolve_device(device: str | None) -> str | None:
    """Map a user's device argument onto an OpenCL device selector.

    Args:
        device: None (first GPU, else first CPU), ``"cpu"``, ``"gpu"``, or a Warp/torch CUDA name
            (``"cuda"``, ``"cuda:1"``), which asks for the first OpenCL GPU.

    Returns:
        None, ``"gpu"`` or ``"cpu"``; ``"gpu"`` only when a working OpenCL GPU exists (else the CPU is used).

    Raises:
        BackendError: any other name.
    """
    if device is None:
        return None
    name = str(device).strip().lower()
    if name == "cpu":
        return "cpu"
    if name == "gpu" or name == "cuda" or name.startswith("cuda:"):
        return "gpu" if _first_working(("gpu",)) is not None else "cpu"
    raise BackendError(f"unknown OpenCL device {device!r}; use None, 'cpu', 'gpu' or 'cuda[:n]'")


# ---------------------------------------------------------------------------------------------- runtime
@dataclass(eq=False)
class Runtime:
    """One OpenCL device with its context, in-order queue, program and kernel caches and buffer pool."""

    device: Any
    """The ``pyopencl.Device``."""
    context: Any
    """A context holding only :attr:`device`."""
    queue: Any
    """In-order command queue; every call enqueues on it and blocks once, at the end, for its results."""
    lock: threading.RLock = field(default_factory=threading.RLock)
    """Held by each operation for its whole call."""
    lanes: int = 8
    """Rays per work-item of the first-hit walk: 16 where the device's compiler targets AVX-512 (float16 is one
    register), else 8; set by the probe. (Vectors wider than the target's also made PoCL 3.0 lose the kernels of a
    program it reloaded from its cache.)"""
    writes_in_place: bool = False
    """True when the device's kernels write a USE_HOST_PTR buffer straight into its host array (seen by the probe,
    :func:`probe_device`, as PoCL does on the CPU): results then need only the queue's completion, no map."""
    _programs: dict[tuple[str, tuple[str, ...]], Any] = field(default_factory=dict)
    _kernels: dict[tuple[int, str], Any] = field(default_factory=dict)
    _pool: dict[str, Any] = field(default_factory=dict)

    @property
    def zero_copy(self) -> bool:
        """True when kernels can work on host arrays in place (the device is the host CPU)."""
        return bool(self.device.type & cl.device_type.CPU) and bool(self.device.host_unified_memory)

    @property
    def has_fp64(self) -> bool:
        """True when the device computes in double precision (``cl_khr_fp64``)."""
        return "cl_khr_fp64" in self.device.extensions

    def kernel(self, source: str, name: str, options: tuple[str, ...] = ()) -> Any:
        """Kernel ``name`` of ``source`` built with ``BUILD_OPTIONS + options``; each program is built once per
        context (cache key: source text and options), each kernel object made once per program."""
        key = (source, tuple(options))
        prg = self._programs.get(key)
        if prg is None:
            with quiet_build():
                prg = cl.Program(self.context, source).build(options=list(BUILD_OPTIONS + tuple(options)))
            self._programs[key] = prg
        kkey = (id(prg), name)
        k = self._kernels.get(kkey)
        if k is None:
            k = getattr(prg, name)
            types = _arg_dtypes(k)
            if types is not None:
                k.set_scalar_arg_dtypes(types)
            self._kernels[kkey] = k
        return k

    def scratch(self, name: str, nbytes: int) -> Any:
        """A device buffer of at least ``nbytes`` bytes for intermediate data, kept for the next call under the
        same ``name``; grown when too small. Its content on entry is undefined."""
        nbytes = max(int(nbytes), 1)
        buf = self._pool.get(name)
        if buf is None or buf.size < nbytes:
            buf = cl.Buffer(self.context, cl.mem_flags.READ_WRITE, nbytes)
            self._pool[name] = buf
        return buf

    def zero(self, buf: Any, nbytes: int) -> None:
        """Enqueue setting the first ``nbytes`` bytes of ``buf`` to 0."""
        cl.enqueue_fill_buffer(self.queue, buf, np.uint8(0), 0, int(nbytes))

    def input(self, name: str, arr: np.ndarray) -> Any:
        """A read-only view of the C-contiguous host array ``arr`` for kernels.

        Zero-copy devices get a ``USE_HOST_PTR`` buffer over ``arr`` itself; other devices get the pooled buffer
        ``name`` and a non-blocking upload. Either way ``arr`` must stay alive and unchanged until the call's
        final synchronisation.
        """
        if self.zero_copy:
            return cl.Buffer(self.context, cl.mem_flags.READ_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=arr)
        buf = self.scratch(name, arr.nbytes)
        cl.enqueue_copy(self.queue, buf, arr, is_blocking=False)
        return buf

    def output(self, name: str, arr: np.ndarray) -> Any:
        """A write-only device view of the C-contiguous host array ``arr``, which receives the data at
        :meth:`fetch`: ``arr`` itself on zero-copy devices, else the pooled buffer ``name``."""
        if self.zero_copy:
            return cl.Buffer(self.context, cl.mem_flags.WRITE_ONLY | cl.mem_flags.USE_HOST_PTR, hostbuf=arr)
        return self.scratch(name, arr.nbytes)

    def fetch(self, pairs: list[tuple[Any, np.ndarray]]) -> None:
        """Make the kernels' writes to each ``(buffer, arr)`` from :meth:`output` visible in ``arr``, and wait
        for every command of the call (the only host synchronisation of an operation)."""
        if not pairs:
            return
        if self.zero_copy and self.writes_in_place:
            pass  # the kernels write the arrays themselves: waiting for the queue (below) is enough
        elif self.zero_copy:
            # Mapping a USE_HOST_PTR buffer is the OpenCL way to make device writes visible in the host array (PoCL
            # maps in place, no copy). The maps are enqueued behind the kernels and waited for together: one
            # blocking map each costs a round trip to the driver's thread per output.
            maps = [cl.enqueue_map_buffer(self.queue, buf, cl.map_flags.READ, 0, arr.shape, arr.dtype,
                                          is_blocking=False)[0] for buf, arr in pairs]
            self.queue.finish()  # the maps are complete: the kernels wrote the arrays
            for m in maps:
                m.base.release(self.queue)
        else:
            for buf, arr in pairs:
                cl.enqueue_copy(self.queue, arr, buf, is_blocking=False)
        # Results are handed to the caller right after this: wait for the copies and unmaps, and thereby for
        # every kernel of the call, so that the input wrappers may be released too.
        self.queue.finish()


_SCALAR_TYPES = {"char": np.int8, "uchar": np.uint8, "short": np.int16, "ushort": np.uint16, "int": np.int32,
                 "uint": np.uint32, "long": np.int64, "ulong": np.uint64, "float": np.float32, "double": np.float64}


def _arg_dtypes(kernel: Any) -> list[Any] | None:
    """The numpy dtypes of a kernel's by-value arguments (None for buffers and anything else), from its argument
    info, for ``set_scalar_arg_dtypes``: pyopencl then packs each argument directly instead of trying it as every
    kind of argument in turn (20 us of C++ exceptions per launch on PoCL). None when the driver keeps no
    argument info."""
    try:
        out: list[Any] = []
        for i in range(kernel.num_args):
            private = kernel.get_arg_info(i, cl.kernel_arg_info.ADDRESS_QUALIFIER) == \
                cl.kernel_arg_address_qualifier.PRIVATE
            name = kernel.get_arg_info(i, cl.kernel_arg_info.TYPE_NAME).strip()
            vector = getattr(cl_types, name, None) if re.fullmatch(r"[a-z]+(2|3|4|8|16)", name) else None
            out.append(None if not private else _SCALAR_TYPES.get(name, vector))
        return out
    except cl.Error:
        return None


@cache
def _runtime_for(device: Any) -> Runtime:
    ctx = cl.Context([device])
    return Runtime(device=device, context=ctx, queue=cl.CommandQueue(ctx))


def get_runtime(selector: str | None) -> Runtime:
    """The cached :class:`Runtime` of a selector from :func:`resolve_device`: the first working device of the kind
    asked for (see the module docstring).

    Raises:
        BackendUnavailable: no OpenCL device works here; the message names each device's failure and the fix.
    """
    dev = _first_working(("cpu", "gpu") if selector == "cpu" else ("gpu", "cpu"))
    if dev is None:
        raise BackendUnavailable(no_device_message("opencl", unavailable_reason()))
    return _runtime_for(dev)


def source(module_file: str, stem: str | None = None) -> str:
    """The OpenCL source that lies beside a Python module: ``foo.py`` -> ``foo.cl``, or ``stem.cl`` in the same
    folder, with its ``#include "name.h"`` lines replaced by those headers (from the same folder, themselves
    resolved), so that the program text, which keys the build caches, is the whole program."""
    path = Path(module_file)
    return _resolve(path.with_suffix(".cl") if stem is None else path.with_name(f"{stem}.cl"))


_INCLUDE = re.compile(r'^\s*#\s*include\s+"([^"]+)"\s*$', re.MULTILINE)


def _resolve(path: Path, seen: tuple[Path, ...] = ()) -> str:
    if path in seen:
        raise ImportError(f"OpenCL header {path.name} includes itself (through {' -> '.join(p.name for p in seen)})")
    text = path.read_text(encoding="utf-8")

    def include(m: re.Match[str]) -> str:
        header = path.with_name(m.group(1))
        # #line keeps the compiler's messages pointing into the header, then back into the includer.
        after = text.count("\n", 0, m.end()) + 2
        return f'#line 1 "{header.name}"\n{_resolve(header, (*seen, path))}\n#line {after} "{path.name}"'

    return _INCLUDE.sub(include, text)


def defines(**values: int | float) -> tuple[str, ...]:
    """``-DNAME=value`` build options."""
    return tuple(f"-D{k}={v!r}" for k, v in values.items())


# ---------------------------------------------------------------------------------------------- host arrays
def host_array(volume: Any) -> np.ndarray:
    """The caller's volume as a C-contiguous numpy array on the host, of a dtype the kernels take (no copy when it
    already is one).

    torch tensors are detached and brought to the CPU; bfloat16 becomes float32 (OpenCL has no bfloat16). numpy's
    long double becomes float64, and data of the other byte order is swapped to the host's, because the kernels
    read raw native elements.
    """
    if is_torch(volume):
        import torch

        t = volume.detach()
        if t.dtype == torch.bfloat16:
            t = t.float()
        t = t.cpu() if t.device.type != "cpu" else t
        arr = t.numpy()
    else:
        arr = volume
    dtype = arr.dtype.newbyteorder("=")
    if dtype.kind == "f" and dtype.itemsize > 8:
        dtype = np.dtype(np.float64)
    return np.ascontiguousarray(arr, dtype=dtype)


def to_caller(arr: np.ndarray, spec: VolumeSpec, like: Any = None) -> Any:
    """A result array in the caller's kind and on its device.

    Args:
        arr: host result.
        spec: the validated input's description (kind and device).
        like: the input volume, whose dtype the result takes back where :func:`host_array` changed it (bfloat16,
            long double, the other byte order).
    """
    if spec.kind == "numpy":
        return arr if like is None or arr.dtype == like.dtype else arr.astype(like.dtype)
    import torch

    t = torch.from_numpy(arr)
    if like is not None and like.dtype == torch.bfloat16 and t.dtype == torch.float32:
        t = t.to(torch.bfloat16)
    return t.to(spec.device) if spec.device != "cpu" else t

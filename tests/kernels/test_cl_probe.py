"""The OpenCL device probe (kernels/cl/runtime.py): a device that cannot build a kernel is skipped with its
compiler's message, a working one is chosen over it, the newer PoCL is preferred, ``backend=None`` falls back to Warp
with one warning, and ``backend="opencl"`` fails with one line naming the cause and the fix.

The real failure (the PyPI PoCL on an AMD Zen 5: "unknown target CPU 'generic'") cannot be reproduced on every
machine, so it is simulated two ways: a probe kernel that really fails to compile on the real device (the real
compiler's message travels through), and stand-in devices placed before the real ones whose probe reports that
message.
"""

from __future__ import annotations

import os
import types
import warnings

import numpy as np
import pytest

from fruxel.grid import FruxelGrid
from fruxel.kernels import BackendUnavailable, available_backends, first_hit, get_backend
from fruxel.kernels import registry as reg

cl = pytest.importorskip("fruxel.kernels.cl")
runtime = pytest.importorskip("fruxel.kernels.cl.runtime")
if not cl.is_available():  # pragma: no cover - only without an OpenCL device
    pytest.skip(f"no OpenCL device: {cl.unavailable_reason()}", allow_module_level=True)
pyopencl = pytest.importorskip("pyopencl")

ZEN5 = "error: unknown target CPU 'generic'\nDevice pthread-AMD EPYC failed to build the program"
"""What the PyPI PoCL's compiler says on an AMD Zen 5."""
GRID = FruxelGrid(width=6, height=5, depth=4, z_near=0.5, z_far=3.0, hfov=60.0)


def _fake_cpu(pocl: str, name: str = "pthread-AMD EPYC") -> types.SimpleNamespace:
    """A stand-in for a ``pyopencl.Device``: a CPU device of a PoCL of version ``pocl``."""
    platform = types.SimpleNamespace(name="Portable Computing Language",
                                     version=f"OpenCL 3.0 PoCL {pocl}  Linux, Release, RELOC, LLVM 14.0.6")
    return types.SimpleNamespace(type=pyopencl.device_type.CPU, platform=platform, name=name)


@pytest.fixture
def fresh(monkeypatch: pytest.MonkeyPatch):
    """Probe from scratch, and again afterwards (the real devices' results come back)."""
    runtime.forget_devices()
    reg._warned.clear()
    yield monkeypatch
    monkeypatch.undo()
    runtime.forget_devices()
    reg._warned.clear()


def _with_devices(monkeypatch: pytest.MonkeyPatch, devices: list, broken: list) -> None:
    """Put ``devices`` in front of the real ones (ranked as the runtime ranks them); the probe of those in
    ``broken`` fails with :data:`ZEN5`, the others' probes run for real (stand-ins must not be probed for real)."""
    real_list = runtime._platform_devices.__wrapped__()[0]
    monkeypatch.setattr(runtime, "_platform_devices", lambda: (tuple(runtime.rank([*devices, *real_list])), ""))
    real_probe = runtime.probe_device

    def probe(device: object) -> str | None:
        if any(device is b for b in broken):
            return runtime.one_line_message(ZEN5)
        assert not isinstance(device, types.SimpleNamespace), "a working stand-in was probed for real"
        return real_probe(device)

    monkeypatch.setattr(runtime, "probe_device", probe)


def test_a_device_that_cannot_build_is_skipped_for_one_that_can(fresh: pytest.MonkeyPatch) -> None:
    newer = _fake_cpu("9.9")  # ranked first: the newest PoCL
    _with_devices(fresh, [newer], broken=[newer])
    rt = runtime.get_runtime(None)
    assert rt.device is not newer
    report = runtime.device_report()
    assert report[0].device is newer and "unknown target CPU 'generic'" in report[0].error
    assert any(st.error is None for st in report[1:])
    assert "opencl" in available_backends()
    hits = first_hit(np.ones(GRID.shape, np.uint8), GRID, GRID.camera(), backend="opencl")
    assert np.all(hits.label == 1)


def test_no_working_device_fails_with_the_cause_and_the_fix(fresh: pytest.MonkeyPatch) -> None:
    fake = _fake_cpu("3.0-rc2")
    fresh.setattr(runtime, "_platform_devices", lambda: ((fake,), ""))
    fresh.setattr(runtime, "probe_device", lambda device: runtime.one_line_message(ZEN5))
    assert not cl.is_available() and not cl.cpu_available()
    assert "opencl" not in available_backends()
    with pytest.raises(BackendUnavailable) as err:
        get_backend("opencl")
    msg = str(err.value)
    assert "\n" not in msg
    assert "pthread-AMD EPYC (OpenCL 3.0 PoCL 3.0-rc2)" in msg and "unknown target CPU 'generic'" in msg
    assert "apt-get install" in msg and "pocl-opencl-icd" in msg
    with pytest.raises(BackendUnavailable, match="pocl-opencl-icd"):
        first_hit(np.ones(GRID.shape, np.uint8), GRID, GRID.camera(), backend="opencl")
    with pytest.raises(BackendUnavailable, match="unknown target CPU"):
        runtime.get_runtime("cpu")


def test_best_available_falls_back_to_warp_with_one_warning(fresh: pytest.MonkeyPatch) -> None:
    try:
        wp = get_backend("warp")
    except BackendUnavailable:
        pytest.skip("Warp is not installed")
    if wp.cuda_available():
        pytest.skip("with a GPU, Warp on CUDA is chosen before OpenCL is considered")
    fake = _fake_cpu("3.0-rc2")
    fresh.setattr(runtime, "_platform_devices", lambda: ((fake,), ""))
    fresh.setattr(runtime, "probe_device", lambda device: runtime.one_line_message(ZEN5))
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        mod, dev = reg.resolve(None, None)
        hits = first_hit(np.ones(GRID.shape, np.uint8), GRID, GRID.camera())
        reg.resolve(None, None)
    assert mod is wp and dev == "cpu"
    assert np.all(hits.label == 1)
    found = [w for w in caught if issubclass(w.category, RuntimeWarning) and "opencl" in str(w.message)]
    assert len(found) == 1, [str(w.message) for w in caught]
    text = str(found[0].message)
    assert "unknown target CPU 'generic'" in text and "pocl-opencl-icd" in text and "Warp on the CPU" in text


def test_a_real_build_failure_is_caught_with_the_compilers_message(fresh: pytest.MonkeyPatch) -> None:
    """The real compiler, on the real devices, rejecting the probe: every device fails, each with the message."""
    fresh.setattr(runtime, "PROBE_SOURCE", "#error unknown target CPU 'generic'\n" + runtime.PROBE_SOURCE)
    assert not cl.is_available()
    report = runtime.device_report()
    assert report and all("unknown target CPU 'generic'" in st.error for st in report)
    assert "unknown target CPU 'generic'" in cl.unavailable_reason()


def test_a_device_that_computes_wrongly_is_skipped(fresh: pytest.MonkeyPatch) -> None:
    fresh.setattr(runtime, "PROBE_SOURCE", runtime.PROBE_SOURCE.replace("/ 3.0f", "/ 3.0001f"))
    assert not cl.is_available()
    assert "computed" in runtime.device_report()[0].error


def test_newer_pocl_first_and_gpus_before_cpus() -> None:
    old, new, other = _fake_cpu("3.0-rc2"), _fake_cpu("3.1+debian"), _fake_cpu("x")
    other.platform.name, other.platform.version = "Intel(R) OpenCL", "OpenCL 3.0 LINUX"
    gpu = types.SimpleNamespace(type=pyopencl.device_type.GPU, platform=other.platform, name="gpu")
    assert runtime.rank([other, old, gpu, new]) == [gpu, new, old, other]
    assert runtime.pocl_version(new) == (3, 1) and runtime.pocl_version(other) is None


def test_here_the_newest_working_pocl_is_chosen() -> None:
    """On the machine that runs the tests: the chosen CPU device is the newest PoCL that builds the probe (with
    both the PyPI and Debian's PoCL installed, Debian's 3.1)."""
    if os.environ.get(runtime.DEVICE_ENV):
        pytest.skip(f"{runtime.DEVICE_ENV} picks the device")
    working = [st.device for st in runtime.device_report() if st.error is None and st.kind == "cpu"]
    pocls = [d for d in working if runtime.pocl_version(d) is not None]
    if not pocls:
        pytest.skip("no working PoCL CPU device here")
    chosen = runtime.get_runtime("cpu").device
    assert runtime.pocl_version(chosen) == max(runtime.pocl_version(d) for d in pocls)


def test_the_environment_can_pick_the_device(fresh: pytest.MonkeyPatch) -> None:
    working = [st for st in runtime.device_report() if st.error is None]
    last = working[-1]
    fresh.setenv(runtime.DEVICE_ENV, last.description)
    assert runtime.get_runtime(None).device == last.device
    fresh.setenv(runtime.DEVICE_ENV, "no such device")
    assert not cl.is_available()
    with pytest.raises(BackendUnavailable, match=f"{runtime.DEVICE_ENV}='no such device' matches none"):
        get_backend("opencl")


WARNS = '#warning "fruxel test: the compiler warns"\n__kernel void k(__global float* o) { o[0] = 1.0f; }\n'
"""A kernel the compiler builds with a warning."""


def test_builds_say_nothing_unless_pyopencl_is_asked(capfd: pytest.CaptureFixture[str],
                                                     monkeypatch: pytest.MonkeyPatch) -> None:
    """A compiler's warnings are not the users': PoCL's clang writes "1 warning generated." to the terminal and
    pyopencl warns (CompilerWarning) on every later run. PYOPENCL_COMPILER_OUTPUT=1 shows them, for kernel work."""
    rt = runtime.get_runtime(None)
    monkeypatch.delenv("PYOPENCL_COMPILER_OUTPUT", raising=False)
    for text in (WARNS, WARNS + "// built again, from the caches\n"):
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            runtime.forget_devices()
            rt = runtime.get_runtime(None)
            assert rt.kernel(text, "k") is not None
        assert [str(w.message) for w in caught] == []
        assert capfd.readouterr().err == ""
    monkeypatch.setenv("PYOPENCL_COMPILER_OUTPUT", "1")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        rt.kernel(WARNS + "// asked for\n", "k")
    assert any(issubclass(w.category, pyopencl.CompilerWarning) and "fruxel test" in str(w.message) for w in caught)

"""What the Warp backend's launch path (kernels/wp/arrays.py) relies on in Warp, beyond its documented API, and
what it promises: these tests fail when a Warp upgrade changes one of those pieces.

* Array descriptors built without a Warp array (:meth:`Buffer.make_descriptor`) are byte for byte the ones Warp's
  own arrays pack into kernel parameters.
* Struct arguments packed directly (:func:`~fruxel.kernels.wp.traverse.camera_arg`) are byte for byte the ones
  Warp packs from its own struct instance.
* A recorded launch replayed through ``Launch.set_param_at_index_from_ctype`` reads each call's buffers, the cache
  of recorded launches keeps none of them alive, and a launch recorded before its module was rebuilt still runs.
"""

from __future__ import annotations

import ctypes
import gc
import weakref

import numpy as np
import pytest

from fruxel.camera import Camera

pytest.importorskip("warp")
torch = pytest.importorskip("torch")

from fruxel.kernels.wp import arrays  # noqa: E402 - after the skips: needs warp
from fruxel.kernels.wp.arrays import Buffer, Workspace  # noqa: E402
from fruxel.kernels.wp.runtime import warp  # noqa: E402
from fruxel.kernels.wp.traverse import CameraInfo, camera_arg  # noqa: E402

wp = warp()
DEVICES = [d for d, ok in (("cpu", wp.is_cpu_available()), ("cuda", wp.get_cuda_device_count() > 0)) if ok]


def raw(structure: ctypes.Structure) -> bytes:
    """The bytes of a ctypes structure, padding included (both sides are zero-initialised by ctypes)."""
    return ctypes.string_at(ctypes.addressof(structure), ctypes.sizeof(structure))


@wp.kernel
def scale_rows_kernel(x: wp.array2d(dtype=wp.float32), factor: float, y: wp.array2d(dtype=wp.float32)):
    """Test kernel: ``y = factor * x``, one thread per element; launch ``x.shape``."""
    i, j = wp.tid()
    y[i, j] = factor * x[i, j]


@pytest.mark.parametrize(("shape", "dtype"), [((7,), wp.uint8), ((3, 5), wp.int32), ((2, 3, 4), wp.vec3),
                                              ((2, 1, 3, 2), wp.float64)])
def test_descriptor_equals_warps_own(shape: tuple[int, ...], dtype: object) -> None:
    a = np.zeros(shape + arrays.inner_shape(dtype), dtype=arrays.numpy_dtype(dtype))
    warp_array = wp.array(a, dtype=dtype, device="cpu", copy=False)
    ours = Buffer.of(a, dtype, "cpu").make_descriptor()
    theirs = warp_array.__ctype__()
    assert type(ours) is type(theirs) is arrays._ARRAY_DESCRIPTOR
    assert raw(ours) == raw(theirs), "Warp's array descriptor changed: update Buffer.make_descriptor"


def test_packed_camera_equals_warps_struct() -> None:
    cam = Camera.look_at([0.3, -0.2, -0.8], [0.1, 0.2, 2.0], width=20, height=16, hfov=70.0)
    info = CameraInfo()
    info.fx, info.fy, info.cx, info.cy = (float(v) for v in (cam.fx, cam.fy, cam.cx, cam.cy))
    info.rotation = wp.mat33(*np.asarray(cam.rotation, np.float32).reshape(-1).tolist())
    info.origin = wp.vec3(*np.asarray(cam.position, np.float32).tolist())
    info.width, info.height = cam.width, cam.height
    assert raw(camera_arg(cam).__ctype__()) == raw(info.__ctype__()), "Warp's struct packing changed: camera_arg"


@pytest.mark.parametrize("device", DEVICES)
def test_replayed_launches_read_each_calls_buffers(device: str) -> None:
    # One recorded launch (same kernel, dims and shapes) serves every call: each call's inputs, outputs and
    # scalars must reach the kernel, whether a buffer's address changed or was reused.
    arrays.prepared_launches().clear()
    ws = Workspace(device, "torch", device)
    xs = [ws.input(torch.arange(6, dtype=torch.float32).reshape(2, 3) + 10 * n) for n in range(3)]
    outs = []
    for n, x in enumerate([*xs, xs[0]]):
        y = ws.empty((2, 3), wp.float32)
        ws.launch(scale_rows_kernel, (2, 3), [x, float(n + 1), y])
        outs.append((x.native.cpu().numpy() * (n + 1), y))
    for want, y in outs:
        np.testing.assert_array_equal(y.native.cpu().numpy(), want)
    assert sum(k[0] is scale_rows_kernel for k in arrays.prepared_launches()) == 1


@pytest.mark.parametrize("device", DEVICES)
def test_recorded_launches_keep_no_memory(device: str) -> None:
    # The cache outlives the call: the recorded launch must not hold the first call's tensors (a volume or a
    # batch of logits each), neither through its parameters nor through Warp's record of the launch arguments.
    arrays.prepared_launches().clear()
    ws = Workspace(device, "torch", device)
    x = torch.ones((2, 3), dtype=torch.float32, device=device)
    y = torch.empty((2, 3), dtype=torch.float32, device=device)
    refs = [weakref.ref(x), weakref.ref(y)]
    ws.launch(scale_rows_kernel, (2, 3), [ws.input(x), 2.0, Buffer.of(y, wp.float32, device)])
    if device == "cuda":
        torch.cuda.synchronize()  # the kernel has run before its memory goes
    assert float(y.sum()) == 12.0
    del x, y
    gc.collect()
    assert all(r() is None for r in refs), "a recorded launch keeps a call's array alive"
    assert len(arrays.prepared_launches()) == 1


@pytest.mark.parametrize("device", DEVICES)
def test_recorded_launch_survives_a_module_rebuild(device: str) -> None:
    # A kernel added to a module that has been loaded makes Warp rebuild and reload it; the launch recorded before
    # must still run (on the build it was recorded with), as Workspace replays it without recording it again.
    module = f"fruxel_test_rebuild_{device}"

    @wp.kernel(module=module)
    def add_one_kernel(x: wp.array(dtype=wp.float32)):
        """Test kernel: ``x += 1``, one thread per element."""
        x[wp.tid()] = x[wp.tid()] + 1.0

    arrays.prepared_launches().clear()
    ws = Workspace(device, "torch", device)
    x = torch.zeros(4, dtype=torch.float32, device=device)
    buf = Buffer.of(x, wp.float32, device)
    ws.launch(add_one_kernel, (4,), [buf])
    recorded = next(p.cmd for k, p in arrays.prepared_launches().items() if k[0] is add_one_kernel)

    @wp.kernel(module=module)
    def add_two_kernel(x: wp.array(dtype=wp.float32)):
        """Test kernel: ``x += 2``, one thread per element."""
        x[wp.tid()] = x[wp.tid()] + 2.0

    if device == "cuda":
        torch.cuda.synchronize()  # Workspace launched on torch's stream, wp.launch uses Warp's
    wp.launch(add_two_kernel, (4,), [buf.array()], device=device)
    wp.synchronize_device(device)
    # Warp internals, read here only to be sure the rebuild happened (else this test would prove nothing).
    assert recorded.module_exec not in add_one_kernel.module.execs.values(), "the module was not rebuilt"
    gc.collect()
    ws.launch(add_one_kernel, (4,), [buf])
    assert next(p.cmd for k, p in arrays.prepared_launches().items() if k[0] is add_one_kernel) is recorded
    np.testing.assert_array_equal(x.cpu().numpy(), np.full(4, 4.0, np.float32))

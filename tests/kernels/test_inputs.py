"""Bad input gets one clear error before anything runs, on every backend; the backend registry's choices."""

from __future__ import annotations

import importlib

import numpy as np
import pytest

import fruxel
import fruxel.kernels as kernels
from fruxel.camera import Camera, CameraError
from fruxel.grid import FruxelGrid
from fruxel.kernels import BackendError, BackendUnavailable, VolumeError
from fruxel.kernels import registry as reg

from .conftest import BACKENDS, REAL_BACKENDS, first_hit, shell

GRID = FruxelGrid(6, 5, 4, z_near=0.5, z_far=2.0, hfov=60.0)
CAM = Camera.from_hfov(8, 6, 60.0)


def _labels() -> np.ndarray:
    lab = np.zeros(GRID.shape, np.uint8)
    lab[2] = 3
    return lab


def _scores(dtype: type = np.float32) -> np.ndarray:
    return np.random.default_rng(0).normal(size=(1, 3) + GRID.shape).astype(dtype)


BAD_VOLUMES = {
    "D mismatch": np.zeros((5, 5, 6), np.uint8),
    "H mismatch": np.zeros((4, 4, 6), np.uint8),
    "W mismatch": np.zeros((4, 5, 7), np.uint8),
    "2D": np.zeros((5, 6), np.uint8),
    "6D": np.zeros((1, 1, 3, 4, 5, 6), np.float32),
    "5D labels": np.zeros((1, 1, 4, 5, 6), np.uint8),
    "complex": np.zeros(GRID.shape, np.complex64),
    "object": np.zeros(GRID.shape, object),
    "str": np.full(GRID.shape, "a"),
    "float 3D": np.zeros(GRID.shape, np.float32),
    "float 4D": np.zeros((1,) + GRID.shape, np.float32),
    "one channel": np.zeros((1, 1) + GRID.shape, np.float32),
    "NaN": _scores().copy(),
    "inf": _scores().copy(),
    "-inf probs": _scores().copy(),
    "label 256": np.full(GRID.shape, 256, np.int32),
    "label -1": np.full(GRID.shape, -1, np.int16),
    "empty batch": np.zeros((0,) + GRID.shape, np.uint8),
    "list": [[[0]]],
}
BAD_VOLUMES["NaN"][0, 1, 1, 1, 1] = np.nan
BAD_VOLUMES["inf"][0, 2, 0, 0, 0] = np.inf
BAD_VOLUMES["-inf probs"][0, 0, 3, 4, 5] = -np.inf


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("case", list(BAD_VOLUMES))
def test_bad_volume_is_refused(backend: str, case: str) -> None:
    vol = BAD_VOLUMES[case]
    with pytest.raises(VolumeError):
        first_hit(backend, vol, GRID, CAM)
    with pytest.raises(VolumeError):
        shell(backend, vol, GRID, [CAM])


@pytest.mark.parametrize("backend", BACKENDS)
def test_bad_torch_volume_is_refused(backend: str) -> None:
    torch = pytest.importorskip("torch")
    bad = torch.from_numpy(_scores())
    bad[0, 1, 0, 0, 0] = float("nan")
    with pytest.raises(VolumeError, match="NaN"):
        first_hit(backend, bad, GRID, CAM)
    with pytest.raises(VolumeError, match=r"\[0, 255\]"):
        shell(backend, torch.full(GRID.shape, 300, dtype=torch.int32), GRID, [CAM])
    with pytest.raises(VolumeError):
        first_hit(backend, torch.zeros(GRID.shape, dtype=torch.complex64), GRID, CAM)


@pytest.mark.parametrize("backend", BACKENDS)
@pytest.mark.parametrize("threshold", [0.0, -0.5, 1.0001, 2.0, float("nan")])
def test_threshold_outside_unit_interval_is_refused(backend: str, threshold: float) -> None:
    with pytest.raises(VolumeError, match="threshold"):
        first_hit(backend, _scores(), GRID, CAM, threshold=threshold)
    with pytest.raises(VolumeError, match="threshold"):
        shell(backend, _scores(), GRID, [CAM], threshold=threshold, probs=True)


@pytest.mark.parametrize("backend", BACKENDS)
def test_threshold_with_labels_is_refused(backend: str) -> None:
    with pytest.raises(VolumeError, match="threshold"):
        first_hit(backend, _labels(), GRID, CAM, threshold=0.5)


@pytest.mark.parametrize("backend", BACKENDS)
def test_bad_cameras_are_refused(backend: str) -> None:
    with pytest.raises(VolumeError, match="camera"):
        shell(backend, _labels(), GRID, [])
    with pytest.raises(VolumeError, match="Camera"):
        shell(backend, _labels(), GRID, [CAM, "not a camera"])
    with pytest.raises(VolumeError, match="Camera"):
        shell(backend, _labels(), GRID, [CAM, np.eye(4)])
    with pytest.raises((VolumeError, CameraError)):
        first_hit(backend, _labels(), GRID, "not a camera")
    # A dict (e.g. a camera's to_dict()) is reported as a dict, not by the type of its keys.
    for wrong in (CAM.to_dict(), CAM.to_json(), 3):
        with pytest.raises(VolumeError, match=f"sequence of them, got {type(wrong).__name__}$"):
            shell(backend, _labels(), GRID, wrong)


@pytest.mark.parametrize("backend", BACKENDS)
def test_good_input_after_bad_input_still_works(backend: str) -> None:
    """A refused call leaves no state behind: the next good call gives the right answer."""
    with pytest.raises(VolumeError):
        first_hit(backend, BAD_VOLUMES["NaN"], GRID, CAM)
    hits = first_hit(backend, _labels(), GRID, GRID.camera())
    assert np.all(hits.label == 3) and np.all(hits.cell // (GRID.width * GRID.height) == 2)


@pytest.mark.parametrize("backend", REAL_BACKENDS)
@pytest.mark.parametrize(("dtype", "native"), [(np.longdouble, np.float64), (">f4", np.float32), (">i4", np.int32)],
                         ids=["longdouble", ">f4", ">i4"])
def test_unusual_numpy_dtypes_work_and_come_back(backend: str, dtype: str, native: type) -> None:
    """numpy's long double and data in the other byte order (as read from some files) are taken like their
    native float64 / float32 / int32 counterparts, and shell gives them back in their own dtype."""
    vol = (_labels() if np.dtype(native).kind == "i" else _scores()).astype(native)
    odd = vol.astype(dtype)
    want, got = first_hit(backend, vol, GRID, CAM), first_hit(backend, odd, GRID, CAM)
    np.testing.assert_array_equal(got.cell, want.cell)
    np.testing.assert_array_equal(got.label, want.label)
    kept = shell(backend, odd, GRID, [CAM])
    assert kept.dtype == odd.dtype
    np.testing.assert_array_equal(kept.astype(native), shell(backend, vol, GRID, [CAM]))


def test_camera_construction_errors() -> None:
    skew = np.eye(4)
    skew[0, 1] = 0.1
    with pytest.raises(CameraError, match="rigid"):
        Camera(fx=10, fy=10, cx=4, cy=3, width=8, height=6, pose=skew)
    mirror = np.diag([1.0, 1.0, -1.0, 1.0])
    with pytest.raises(CameraError, match="rigid"):
        Camera(fx=10, fy=10, cx=4, cy=3, width=8, height=6, pose=mirror)
    scaled = np.diag([2.0, 2.0, 2.0, 1.0])
    with pytest.raises(CameraError):
        Camera(fx=10, fy=10, cx=4, cy=3, width=8, height=6, pose=scaled)
    for w, h in ((0, 6), (8, 0), (-1, 6)):
        with pytest.raises(CameraError):
            Camera(fx=10, fy=10, cx=4, cy=3, width=w, height=h)
    with pytest.raises(CameraError):
        Camera(fx=0.0, fy=10, cx=4, cy=3, width=8, height=6)
    with pytest.raises(CameraError):
        Camera(fx=float("nan"), fy=10, cx=4, cy=3, width=8, height=6)


# ---------------------------------------------------------------------------------------------- registry


def test_unknown_backend_name() -> None:
    names = ["cuda", "warp-", "opencl2", "numpy", "reference", "open-cl"]
    if "warp-cpu" in REAL_BACKENDS:
        names += ["warp-tpu", "warp-cuda:x"]
    for name in names:
        with pytest.raises(BackendError):
            kernels.first_hit(_labels(), GRID, CAM, backend=name)
    with pytest.raises(BackendError, match="unknown backend"):
        kernels.get_backend("vulkan")


def test_available_backends_order() -> None:
    names = kernels.available_backends()
    order = ["warp-cuda", "warp-cpu", "opencl"]
    assert set(names) <= set(order)
    assert names == [n for n in order if n in names]
    for n in names:
        base, dev = reg.split_name(n)
        assert base in reg.BACKENDS and (dev is None) == (base == "opencl")


@pytest.fixture
def without_opencl(monkeypatch: pytest.MonkeyPatch):
    """Make ``fruxel.kernels.cl`` fail to import, as when pyopencl is not installed."""
    real = importlib.import_module

    def fake(name: str, *args, **kwargs):
        if name == reg.BACKENDS["opencl"].module:
            raise ImportError("No module named 'pyopencl'")
        return real(name, *args, **kwargs)

    reg._load.cache_clear()
    monkeypatch.setattr(reg.importlib, "import_module", fake)
    yield
    monkeypatch.undo()
    reg._load.cache_clear()


def test_missing_backend_fails_only_when_chosen(without_opencl: None) -> None:
    with pytest.raises(BackendUnavailable, match=r"pip install 'fruxel\[opencl\]'"):
        kernels.get_backend("opencl")
    with pytest.raises(BackendUnavailable, match="opencl"):
        kernels.first_hit(_labels(), GRID, CAM, backend="opencl")
    names = kernels.available_backends()
    assert "opencl" not in names
    if "warp-cpu" in REAL_BACKENDS:
        assert "warp-cpu" in names
        hits = kernels.first_hit(_labels(), GRID, GRID.camera(), backend="warp")
        assert np.all(hits.label == 3)
        mod, dev = reg.resolve(None, None)
        assert mod is kernels.get_backend("warp") and dev == "cpu"


def test_resolve_defaults() -> None:
    if not REAL_BACKENDS:
        with pytest.raises(BackendUnavailable):
            reg.resolve(None, None)
        return
    mod, dev = reg.resolve(None, None, _labels())
    if "warp-cuda" in REAL_BACKENDS:
        assert mod is kernels.get_backend("warp") and str(dev).startswith("cuda")
    elif "opencl" in REAL_BACKENDS:
        assert mod is kernels.get_backend("opencl")
    else:
        assert mod is kernels.get_backend("warp") and dev == "cpu"
    if "warp-cpu" in REAL_BACKENDS:
        mod, dev = reg.resolve("warp-cpu", None)
        assert mod is kernels.get_backend("warp") and dev == "cpu"
        mod, dev = reg.resolve("warp", "cpu")
        assert dev == "cpu"


def test_public_names() -> None:
    for name in ("first_hit", "shell", "orbit_cameras", "available_backends", "Hits", "EMPTY_LOGIT"):
        assert hasattr(fruxel.kernels, name)

"""Tests of the ``fruxel-render`` command: every mode on the bundled model, logits input, and bad input.

Most runs call :func:`fruxel.cli.render.main` in this process (the renderer and the kernels stay warm, which
keeps the suite fast); the tests about imports, exit status and stderr run the command as a subprocess.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import fruxel
from fruxel import kernels
from fruxel.cli.render import main
from fruxel.data import SAMPLE_ROOM
from fruxel.render.frames import default_camera, occupied_points

ROOT = Path(__file__).resolve().parents[2]
SIZE = "96x72"
BACKEND = "warp" if any(b.startswith("warp") for b in kernels.available_backends()) else "opencl"
MODEL = fruxel.load(SAMPLE_ROOM)
VIEW = default_camera(MODEL.grid, 96, 72, points=occupied_points(MODEL.labels, MODEL.grid))
"""The default view of the sample room at :data:`SIZE`: fitted to its occupied cells."""
PALETTE = MODEL.classes.palette()
WALL, FLOOR, FURNITURE = (MODEL.classes.index(n) for n in ("wall", "floor", "furniture"))
HEAVY = ("torch", "warp", "pyrender", "pyopencl", "OpenGL")


def run_cli(*argv: str) -> int:
    return main([*map(str, argv)])


def read_png(path: Path) -> np.ndarray:
    assert path.is_file() and path.stat().st_size > 0
    return np.asarray(Image.open(path).convert("RGB"))


def colours_present(image: np.ndarray) -> set[int]:
    """Labels whose exact palette colour occurs in the image (flat shading)."""
    flat = image.reshape(-1, 3)
    return {c for c in range(1, len(PALETTE)) if np.any(np.all(flat == PALETTE[c], axis=1))}


def foreground_share(image: np.ndarray) -> float:
    return float(np.mean(np.any(image != 255, axis=-1)))


def subprocess_cli(*argv: str, env: dict[str, str] | None = None) -> subprocess.CompletedProcess[str]:
    code = "import sys; from fruxel.cli.render import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, env=env, timeout=120)


def error_lines(stderr: str) -> list[str]:
    # Warp announces a missing CUDA driver on stderr on CPU-only machines; that line is not the command's.
    return [line for line in stderr.splitlines() if line.strip() and "Warp CUDA warning" not in line]


# ---------------------------------------------------------------------------------------------------- help
def test_help_imports_no_heavy_module_and_is_quick() -> None:
    code = (
        "import sys\n"
        "from fruxel.cli.render import main\n"
        "try:\n    main(['--help'])\nexcept SystemExit as e:\n    assert e.code == 0\n"
        f"print('HEAVY=' + ','.join(m for m in {HEAVY!r} if m in sys.modules))\n"
    )
    t0 = time.perf_counter()
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=60)
    elapsed = time.perf_counter() - t0
    assert out.returncode == 0, out.stderr
    assert "usage: fruxel-render" in out.stdout
    assert out.stdout.strip().splitlines()[-1] == "HEAVY=", out.stdout.strip().splitlines()[-1]
    # numpy and fruxel's core only; a torch / warp / pyrender import would take seconds.
    assert elapsed < 5.0


def test_console_script_is_installed() -> None:
    exe = Path(sys.executable).with_name("fruxel-render")
    if not exe.exists():
        pytest.skip("fruxel-render is not installed in this environment (pip install -e .)")
    out = subprocess.run([str(exe), "--help"], capture_output=True, text=True, timeout=60)
    assert out.returncode == 0 and "--benchmark" in out.stdout


# ---------------------------------------------------------------------------------------------------- modes
@pytest.mark.parametrize(
    ("shell", "meshing"),
    [("none", "full"), ("none", "greedy"), ("own", "culled"), ("own", "greedy"), ("poses", "full"),
     ("poses", "greedy"), ("view", "culled"), ("view", "greedy")],
)
def test_mesh_mode_draws_class_colours(tmp_path: Path, shell: str, meshing: str) -> None:
    rc = run_cli("--backend", BACKEND, "--shell", shell, "--mesh", meshing, "--shading", "flat", "--no-legend",
                 "--size", SIZE, "--out", tmp_path)
    assert rc == 0
    img = read_png(tmp_path / "sample_room_mesh.png")
    assert img.shape == (72, 96, 3)
    assert {WALL, FLOOR, FURNITURE} <= colours_present(img)


def test_legend_leaves_the_frustum_apex_in_view(tmp_path: Path) -> None:
    """With --frustum the default view has the frustum's apex (the grid camera) near its bottom-left corner; the
    legend goes elsewhere rather than cover it."""
    for legend in ("", "--no-legend"):
        assert run_cli("--backend", BACKEND, "--size", "160x120", "--frustum", *([legend] if legend else []),
                       "--out", tmp_path / f"f{legend}.png") == 0
    with_legend, without = read_png(tmp_path / "f.png"), read_png(tmp_path / "f--no-legend.png")
    x, y, _ = default_camera(MODEL.grid, 160, 120).project(np.zeros(3))
    x, y = int(x), int(y)
    assert 0 <= x < 160 and 0 <= y < 120
    assert np.array_equal(with_legend[max(0, y - 4):y + 5, max(0, x - 4):x + 5],
                          without[max(0, y - 4):y + 5, max(0, x - 4):x + 5])
    assert not np.array_equal(with_legend, without)


def test_lit_mesh_with_legend_and_frustum(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert run_cli("--backend", BACKEND, "--size", "160x120", "--frustum", "--out", tmp_path) == 0
    out = capsys.readouterr().out.split()
    assert out == [str(tmp_path / "sample_room_mesh.png")]
    img = read_png(tmp_path / "sample_room_mesh.png")
    assert foreground_share(img) > 0.2
    # Lit faces are darker than their class colour, but the legend's swatches carry the exact colours.
    assert {WALL, FLOOR, FURNITURE} <= colours_present(img)


@pytest.mark.parametrize("fog", [False, True])
def test_raycast_mode(tmp_path: Path, fog: bool) -> None:
    args = ["--backend", BACKEND, "--mode", "raycast", "--size", SIZE, "--out", tmp_path, "--no-legend"]
    assert run_cli(*args, *(["--fog"] if fog else ["--shading", "flat"])) == 0
    img = read_png(tmp_path / "sample_room_raycast.png")
    assert img.shape == (72, 96, 3) and foreground_share(img) > 0.2
    if not fog:
        assert {WALL, FLOOR, FURNITURE} <= colours_present(img)


def test_raycast_image_is_first_hit(tmp_path: Path) -> None:
    assert run_cli("--backend", BACKEND, "--mode", "raycast", "--shading", "flat", "--no-legend", "--size", SIZE,
                   "--out", tmp_path) == 0
    img = read_png(tmp_path / "sample_room_raycast.png")
    hits = kernels.first_hit(MODEL.labels, MODEL.grid, VIEW, backend=BACKEND)
    expected = np.where((hits.label != 0)[..., None], PALETTE[hits.label], 255)
    assert np.array_equal(img, expected)


def test_both_mode_side_by_side(tmp_path: Path) -> None:
    assert run_cli("--backend", BACKEND, "--mode", "both", "--size", SIZE, "--out", tmp_path) == 0
    img = read_png(tmp_path / "sample_room_both.png")
    assert img.shape == (72, 2 * 96 + 2, 3)
    assert foreground_share(img[:, :96]) > 0.2 and foreground_share(img[:, 98:]) > 0.2


@pytest.mark.parametrize("suffix", [".glb", ".ply"])
def test_export(tmp_path: Path, suffix: str) -> None:
    trimesh = pytest.importorskip("trimesh")
    dest = tmp_path / f"room{suffix}"
    assert run_cli("--backend", BACKEND, "--size", SIZE, "--out", tmp_path, "--export", dest) == 0
    loaded = trimesh.load(dest, force="mesh", process=False)
    assert len(loaded.faces) > 0
    assert (tmp_path / "sample_room_mesh.png").is_file()


def test_orbit_gif(tmp_path: Path) -> None:
    assert run_cli("--backend", BACKEND, "--orbit", "3", "--size", SIZE, "--out", tmp_path) == 0
    path = tmp_path / "sample_room_mesh_orbit.gif"
    with Image.open(path) as gif:
        assert gif.n_frames == 3
        frames = []
        for f in range(3):
            gif.seek(f)
            frames.append(np.asarray(gif.convert("RGB")))
    assert all(foreground_share(f) > 0.1 for f in frames)
    assert not np.array_equal(frames[0], frames[1])


def test_orbit_mp4(tmp_path: Path) -> None:
    """imageio-ffmpeg is part of the render extra: an MP4 orbit decodes back into distinct, non-empty frames."""
    import imageio.v2 as imageio

    assert run_cli("--backend", BACKEND, "--orbit", "3", "--video", "mp4", "--size", SIZE, "--out", tmp_path) == 0
    frames = imageio.mimread(tmp_path / "sample_room_mesh_orbit.mp4", format="FFMPEG")
    assert len(frames) == 3
    assert all(foreground_share(np.asarray(f)[..., :3]) > 0.1 for f in frames)
    assert not np.array_equal(frames[0], frames[1])


def test_orbit_mp4_without_ffmpeg_says_so(
    tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch
) -> None:
    import importlib.util

    real = importlib.util.find_spec
    def find_spec(name: str, *args: object) -> object:
        return None if name == "imageio_ffmpeg" else real(name, *args)

    monkeypatch.setattr(importlib.util, "find_spec", find_spec)
    assert run_cli("--backend", BACKEND, "--orbit", "2", "--video", "mp4", "--size", SIZE, "--out", tmp_path) == 2
    err = capsys.readouterr().err
    assert "imageio-ffmpeg" in err and not list(tmp_path.glob("*.mp4"))


def test_camera_json_sets_view_and_size(tmp_path: Path) -> None:
    cam = MODEL.grid.camera().scaled(1.5)
    path = tmp_path / "cam.json"
    path.write_text(cam.to_json())
    assert run_cli("--backend", BACKEND, "--mode", "raycast", "--shading", "flat", "--no-legend", "--camera", path,
                   "--out", tmp_path) == 0
    img = read_png(tmp_path / "sample_room_raycast.png")
    assert img.shape == (cam.height, cam.width, 3)
    # The grid's own camera sees the back wall straight ahead in the middle of the image.
    assert tuple(img[cam.height // 3, cam.width // 2]) in {tuple(PALETTE[c]) for c in range(1, len(PALETTE))}


# ---------------------------------------------------------------------------------------------------- logits
def _logits(labels: np.ndarray, n_classes: int) -> np.ndarray:
    """Float32 logits ``(C, D, H, W)`` whose argmax is ``labels``."""
    rng = np.random.default_rng(0)
    lg = rng.normal(0.0, 0.1, (n_classes, *labels.shape)).astype(np.float32)
    np.put_along_axis(lg, labels[None].astype(np.int64), 3.0, axis=0)
    return lg


def test_npy_logits_with_sidecar_match_the_labels(tmp_path: Path) -> None:
    lg = _logits(MODEL.labels, len(MODEL.classes))
    np.save(tmp_path / "pred.npy", lg)
    (tmp_path / "pred.json").write_text(json.dumps(MODEL.grid.to_dict()))
    for name in ("pred.npy", None):
        args = ["--backend", BACKEND, "--mode", "raycast", "--shading", "flat", "--no-legend", "--size", SIZE,
                "--out", tmp_path]
        assert run_cli(*([tmp_path / name] if name else []), *args) == 0
    assert np.array_equal(read_png(tmp_path / "pred_raycast.png"), read_png(tmp_path / "sample_room_raycast.png"))


def test_logits_file_renders_like_its_labels(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A logits file (fruxel.save_logits, float16 here) carries its grid and classes; its ray cast is the labels'."""
    fruxel.save_logits(tmp_path / "pred.npz", _logits(MODEL.labels, len(MODEL.classes)).astype(np.float16),
                       MODEL.grid, MODEL.classes)
    for name in ("pred.npz", None):
        args = ["--backend", BACKEND, "--mode", "raycast", "--shading", "flat", "--no-legend", "--size", SIZE,
                "--out", tmp_path]
        assert run_cli(*([tmp_path / name] if name else []), *args) == 0
    assert np.array_equal(read_png(tmp_path / "pred_raycast.png"), read_png(tmp_path / "sample_room_raycast.png"))
    capsys.readouterr()
    _one_error_line(run_cli(tmp_path / "pred.npz", "--grid", "8", "--out", tmp_path), capsys.readouterr().err,
                    "--grid", "pred.npz")


def test_npy_logits_mesh_with_grid_option(tmp_path: Path) -> None:
    np.save(tmp_path / "bare.npy", _logits(MODEL.labels, len(MODEL.classes)))
    g = MODEL.grid
    spec = ["--grid", f"{g.width}x{g.height}x{g.depth}", "--z-near", g.z_near, "--z-far", g.z_far, "--hfov", g.hfov]
    assert run_cli(tmp_path / "bare.npy", *spec, "--backend", BACKEND, "--shading", "flat", "--no-legend",
                   "--size", SIZE, "--out", tmp_path) == 0
    assert {WALL, FLOOR, FURNITURE} <= colours_present(read_png(tmp_path / "bare_mesh.png"))


def test_pt_dict_logits(tmp_path: Path) -> None:
    torch = pytest.importorskip("torch")
    lg = torch.from_numpy(_logits(MODEL.labels, len(MODEL.classes)))
    torch.save({"logits": lg, "grid": MODEL.grid.to_dict(), "classes": MODEL.classes.to_dict()}, tmp_path / "p.pt")
    assert run_cli(tmp_path / "p.pt", "--backend", BACKEND, "--mode", "both", "--size", SIZE, "--out", tmp_path) == 0
    assert foreground_share(read_png(tmp_path / "p_both.png")) > 0.2


# ---------------------------------------------------------------------------------------------------- errors
def _one_error_line(rc: int, err: str, *words: str) -> None:
    assert rc == 2
    lines = error_lines(err)
    assert len(lines) == 1, err
    assert lines[0].startswith("fruxel-render: error: ")
    assert "Traceback" not in err
    for w in words:
        assert w in lines[0]


@pytest.mark.parametrize("kind", ["labels", "logits"])
def test_empty_model_says_so(tmp_path: Path, capsys: pytest.CaptureFixture[str], kind: str) -> None:
    """A model without an occupied cell (an untrained network's, say) renders, with a note on stderr and in the
    picture instead of a blank image; a model with cells gets no note."""
    empty = fruxel.FruxelModel(np.zeros(MODEL.grid.shape, np.uint8), MODEL.grid, MODEL.classes)
    path = tmp_path / "empty.npz"
    if kind == "labels":
        fruxel.save(path, empty)
    else:
        scores = np.zeros((len(MODEL.classes), *MODEL.grid.shape), np.float32)
        scores[0] = 1.0
        fruxel.save_logits(path, scores, MODEL.grid, MODEL.classes)
    assert run_cli(path, "--backend", BACKEND, "--size", "160x120", "--out", tmp_path / "out") == 0
    captured = capsys.readouterr()
    assert error_lines(captured.err) == [
        "fruxel-render: note: empty: every cell is empty; the picture shows no model"]
    img = read_png(tmp_path / "out" / "empty_mesh.png")
    assert 0 < foreground_share(img) < 0.2  # the note's text and panel, nothing else
    assert np.all(img[60:, :] == 255)  # below the note: background only
    assert run_cli("--backend", BACKEND, "--size", "160x120", "--out", tmp_path / "room") == 0
    assert "note" not in capsys.readouterr().err


def test_missing_model(tmp_path: Path) -> None:
    out = subprocess_cli(str(tmp_path / "nope.npz"), "--out", str(tmp_path))
    _one_error_line(out.returncode, out.stderr, "nope.npz")
    assert not list(tmp_path.glob("*.png"))


def test_corrupt_model(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / "bad.npz"
    bad.write_bytes(SAMPLE_ROOM.read_bytes()[:300])
    rc = run_cli(bad, "--out", tmp_path)
    _one_error_line(rc, capsys.readouterr().err, "bad.npz")


def test_corrupt_npy_and_missing_grid(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "junk.npy").write_bytes(b"\x93NUMPY garbage")
    _one_error_line(run_cli(tmp_path / "junk.npy", "--out", tmp_path), capsys.readouterr().err, "junk.npy")
    np.save(tmp_path / "bare.npy", np.zeros((7, 4, 4, 4), np.float32))
    _one_error_line(run_cli(tmp_path / "bare.npy", "--out", tmp_path), capsys.readouterr().err, "--grid")
    np.save(tmp_path / "obj.npy", np.array([{"a": 1}], dtype=object))
    _one_error_line(run_cli(tmp_path / "obj.npy", "--out", tmp_path), capsys.readouterr().err, "obj.npy")


def test_logits_of_the_wrong_shape(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    np.save(tmp_path / "x.npy", np.zeros((7, 4, 4, 4), np.float32))
    rc = run_cli(tmp_path / "x.npy", "--grid", "8", "--z-far", "5", "--out", tmp_path)
    _one_error_line(rc, capsys.readouterr().err, "(4, 4, 4)")


def test_unknown_backend_and_bad_options() -> None:
    out = subprocess_cli("--backend", "cuda-magic")
    _one_error_line(out.returncode, out.stderr, "--backend", "cuda-magic")
    out = subprocess_cli("--size", "big")
    _one_error_line(out.returncode, out.stderr, "--size")


def test_bad_camera_json(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    rc = run_cli("--camera", '{"fx": 1}', "--out", tmp_path)
    _one_error_line(rc, capsys.readouterr().err, "--camera (JSON text)", "camera keys")


def _camera_cases(tmp: Path) -> dict[str, tuple[str, tuple[str, ...]]]:
    """``--camera`` values that are not usable cameras, and the words their one error line must hold."""
    (tmp / "loop_a").symlink_to(tmp / "loop_b")
    (tmp / "loop_b").symlink_to(tmp / "loop_a")
    (tmp / "folder.json").mkdir()
    bent = MODEL.grid.camera().to_dict()
    bent["pose"][0][0] = 2.0
    (tmp / "bent.json").write_text(json.dumps(bent))
    (tmp / "list.json").write_text("[1, 2]")
    return {
        "binary file": (str(ROOT / "docs" / "demo.png"), ("--camera", "demo.png", "not a camera file")),
        "missing file": (str(tmp / "nope.json"), ("--camera", "nope.json", "no such file")),
        "folder": (str(tmp / "folder.json"), ("folder.json", "folder")),
        "link loop": (str(tmp / "loop_a"), ("loop_a", "symbolic links")),
        "pose not rigid": (str(tmp / "bent.json"), ("--camera", "bent.json", "rigid")),
        "not an object": (str(tmp / "list.json"), ("list.json", "JSON object")),
    }


@pytest.mark.parametrize("case", ["binary file", "missing file", "folder", "link loop", "pose not rigid",
                                  "not an object"])
def test_camera_files_that_are_not_cameras(tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str) -> None:
    """Every --camera problem is one line naming --camera and the file, with the right diagnosis (a missing
    file is missing, not malformed JSON)."""
    value, words = _camera_cases(tmp_path)[case]
    rc = run_cli("--backend", BACKEND, "--camera", value, "--out", tmp_path / "out")
    _one_error_line(rc, capsys.readouterr().err, *words)
    assert not (tmp_path / "out").exists()


def test_camera_and_a_different_size_are_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    cam = tmp_path / "cam.json"
    cam.write_text(MODEL.grid.camera().to_json())
    _one_error_line(run_cli("--camera", cam, "--size", "10x10", "--out", tmp_path), capsys.readouterr().err,
                    "--size", "--camera")


def _torch_files(tmp: Path) -> dict[str, tuple[str, tuple[str, ...]]]:
    torch = pytest.importorskip("torch")
    lg = torch.from_numpy(_logits(MODEL.labels, len(MODEL.classes)))
    torch.save([1, 2, 3], tmp / "list.pt")
    torch.save({"logits": [1, 2, 3]}, tmp / "dict_list.pt")
    torch.save({"logits": lg, "grid": {"width": -1}}, tmp / "bad_grid.pt")
    torch.save({"logits": lg, "grid": MODEL.grid.to_dict(), "classes": {"names": ["a"]}}, tmp / "bad_classes.pt")
    torch.save({"logits": lg.to(torch.bfloat16), "grid": MODEL.grid.to_dict()}, tmp / "bf16.pt")
    nan = lg.clone()
    nan[0, 0, 0, 0] = float("nan")
    torch.save({"logits": nan, "grid": MODEL.grid.to_dict()}, tmp / "nan.pt")
    # An object only unpickling could rebuild: weights_only refuses it, and so must we, in our own words.
    torch.save({"logits": lg, "grid": MODEL.grid.to_dict(), "extra": Path("x")}, tmp / "pickled.pt")
    return {
        "list": ("list.pt", ("list.pt", "holds a list", "logits tensor")),
        "dict with a list": ("dict_list.pt", ("dict_list.pt", "'logits' entry is a list")),
        "bad grid": ("bad_grid.pt", ("bad_grid.pt", "grid")),
        "bad classes": ("bad_classes.pt", ("bad_classes.pt", "classes")),
        "bfloat16": ("bf16.pt", ("bf16.pt", "bfloat16")),
        "NaN": ("nan.pt", ("nan.pt", "NaN")),
        "pickled object": ("pickled.pt", ("pickled.pt", "never unpickles")),
    }


@pytest.mark.parametrize("case", ["list", "dict with a list", "bad grid", "bad classes", "bfloat16", "NaN",
                                  "pickled object"])
def test_pt_files_that_are_not_logits(tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str) -> None:
    name, words = _torch_files(tmp_path)[case]
    rc = run_cli(tmp_path / name, "--grid", "64x48x64", "--z-far", "6", "--out", tmp_path) if case in (
        "list", "dict with a list") else run_cli(tmp_path / name, "--out", tmp_path)
    err = capsys.readouterr().err
    _one_error_line(rc, err, *words)
    # torch's advice to load with weights_only=False (which would run the file's code) is not repeated.
    assert "weights_only" not in err and "\x1b" not in err


def test_nan_npy_logits_name_the_file(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    lg = _logits(MODEL.labels, len(MODEL.classes))
    lg[3, 1, 2, 3] = np.inf
    np.save(tmp_path / "inf.npy", lg)
    (tmp_path / "inf.json").write_text(json.dumps(MODEL.grid.to_dict()))
    _one_error_line(run_cli(tmp_path / "inf.npy", "--out", tmp_path), capsys.readouterr().err, "inf.npy", "NaN")
    np.save(tmp_path / "ok.npy", _logits(MODEL.labels, len(MODEL.classes)))
    (tmp_path / "ok.json").write_text(json.dumps({"grid": MODEL.grid.to_dict(), "classes": {"x": 1}}))
    _one_error_line(run_cli(tmp_path / "ok.npy", "--out", tmp_path), capsys.readouterr().err, "ok.json", "classes")


def test_view_without_display() -> None:
    env = {k: v for k, v in os.environ.items() if k not in ("DISPLAY", "WAYLAND_DISPLAY")}
    out = subprocess_cli("--view", env=env)
    _one_error_line(out.returncode, out.stderr, "display")


def test_view_hands_a_lit_scene_to_the_viewer() -> None:
    """With a display, --view builds the shell mesh with normals and a camera and opens pyrender's Viewer (a stub
    here: no window can open in a test)."""
    code = (
        "from fruxel.render.compat import prepare_pyrender\n"
        "prepare_pyrender(headless=True)\n"
        "import pyrender\n"
        "seen = {}\n"
        "class Stub:\n"
        "    def __init__(self, scene, **kw):\n"
        "        prims = [p for m in scene.meshes for p in m.primitives]\n"
        "        seen.update(n=len(prims), normals=all(p.normals is not None for p in prims),\n"
        "                    camera=scene.main_camera_node is not None, size=kw['viewport_size'])\n"
        "pyrender.Viewer = Stub\n"
        "from fruxel.cli.render import main\n"
        f"rc = main(['--view', '--size', '96x72', '--backend', {BACKEND!r}])\n"
        "print('RESULT', rc, seen)\n"
    )
    env = dict(os.environ, DISPLAY=":99")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=env, timeout=120)
    assert out.returncode == 0, out.stderr
    line = next(x for x in out.stdout.splitlines() if x.startswith("RESULT"))
    assert line == "RESULT 0 {'n': 1, 'normals': True, 'camera': True, 'size': (96, 72)}"


def test_unwritable_output(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    blocker = tmp_path / "file"
    blocker.write_text("not a folder")
    rc = run_cli("--backend", BACKEND, "--mode", "raycast", "--size", SIZE, "--out", blocker / "sub")
    _one_error_line(rc, capsys.readouterr().err, "cannot write")


# ---------------------------------------------------------------------------------------------------- outputs
def test_export_makes_its_folder(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    dest = tmp_path / "newdir" / "sub" / "x.glb"
    assert run_cli("--backend", BACKEND, "--size", SIZE, "--out", tmp_path / "o2", "--export", dest) == 0
    assert capsys.readouterr().out.split() == [str(tmp_path / "o2" / "sample_room_mesh.png"), str(dest)]
    assert dest.stat().st_size > 0


def test_a_failed_output_leaves_nothing_behind(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """When the export cannot be written the image is not written either, the folder made for it goes again,
    and the error names the export, not a temporary file."""
    locked = tmp_path / "locked"
    locked.mkdir()
    locked.chmod(0o500)
    # root may write into a read-only folder; /proc takes no new files from anyone.
    dest = locked / "x.glb" if not os.access(locked, os.W_OK) else Path("/proc/x.glb")
    if not dest.parent.is_dir():
        pytest.skip("no folder here refuses new files")
    try:
        rc = run_cli("--backend", BACKEND, "--size", SIZE, "--out", tmp_path / "o2", "--export", dest)
    finally:
        locked.chmod(0o700)
    err = capsys.readouterr().err
    _one_error_line(rc, err, "cannot write", str(dest))
    assert ".tmp" not in err
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["locked"]


def test_a_failed_export_leaves_the_image_out_too(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                   monkeypatch: pytest.MonkeyPatch) -> None:
    """The same with a write that fails part way (here: a full disk while writing the export), as root too."""
    import fruxel.mesh

    def full_disk(mesh: object, suffix: str) -> bytes:
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(fruxel.mesh, "encode_mesh", full_disk)
    (tmp_path / "o2").mkdir()
    (tmp_path / "o2" / "sample_room_mesh.png").write_bytes(b"the old image")
    rc = run_cli("--backend", BACKEND, "--size", SIZE, "--out", tmp_path / "o2", "--export", tmp_path / "n" / "x.glb")
    err = capsys.readouterr().err
    _one_error_line(rc, err, "No space left")
    assert (tmp_path / "o2" / "sample_room_mesh.png").read_bytes() == b"the old image"
    assert sorted(p.name for p in tmp_path.rglob("*")) == ["o2", "sample_room_mesh.png"]


def test_stale_temporaries_of_killed_runs_are_removed(tmp_path: Path) -> None:
    """A run killed with SIGKILL leaves its temporary file; the next run writing the same output removes it."""
    stale = tmp_path / ".sample_room_mesh_orbit.gif.0123456789ab.tmp.gif"
    stale.write_bytes(b"half a gif")
    other = tmp_path / ".notes.txt.0123456789ab.tmp.txt"
    other.write_bytes(b"someone else's")
    old = time.time() - 600
    for p in (stale, other):
        os.utime(p, (old, old))
    assert run_cli("--backend", BACKEND, "--orbit", "2", "--size", SIZE, "--out", tmp_path) == 0
    assert sorted(p.name for p in tmp_path.iterdir()) == [other.name, "sample_room_mesh_orbit.gif"]


@pytest.mark.parametrize(("out", "extra", "written"), [
    ("pic.png", [], "pic.png"),
    ("pic.jpg", ["--mode", "raycast"], "pic.jpg"),
    ("sub/turn.gif", ["--orbit", "2"], "sub/turn.gif"),
    ("folder.v2", [], "folder.v2/sample_room_mesh.png"),
])
def test_out_with_an_image_or_video_suffix_is_the_file(tmp_path: Path, capsys: pytest.CaptureFixture[str], out: str,
                                                       extra: list[str], written: str) -> None:
    assert run_cli("--backend", BACKEND, "--size", SIZE, "--out", tmp_path / out, *extra) == 0
    assert capsys.readouterr().out.split() == [str(tmp_path / written)]
    target = tmp_path / written
    assert target.is_file()
    with Image.open(target) as im:
        assert im.format == {".png": "PNG", ".jpg": "JPEG", ".gif": "GIF"}[target.suffix]
        assert im.size == (96, 72)


@pytest.mark.parametrize(("out", "extra", "words"), [
    ("pic.png", ["--orbit", "2"], "--orbit writes a video"),
    ("turn.gif", [], "is a video"),
    ("turn.gif", ["--orbit", "2", "--video", "mp4"], "different formats"),
    ("x", ["--video", "mp4"], "--video"),
    ("x.png", ["--benchmark"], "must be a folder"),
    ("x", ["--view"], "--view"),
])
def test_out_that_does_not_fit_the_options_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str], out: str,
                                                      extra: list[str], words: str) -> None:
    rc = run_cli("--backend", BACKEND, "--size", SIZE, "--out", tmp_path / out, *extra)
    _one_error_line(rc, capsys.readouterr().err, words)
    assert not any(tmp_path.iterdir())


# ---------------------------------------------------------------------------------------------------- shells
def test_raycast_shows_the_shell_asked_for(tmp_path: Path) -> None:
    """--shell applies to ray casts: the own-view shell casts differently from the whole model, and the default
    ray cast is the whole model."""
    images = {}
    for shell in (None, "none", "own", "poses"):
        out = tmp_path / f"{shell}.png"
        args = ["--backend", BACKEND, "--mode", "raycast", "--shading", "flat", "--no-legend", "--size", SIZE]
        assert run_cli(*args, *(["--shell", shell] if shell else []), "--out", out) == 0
        images[shell] = read_png(out)
    assert np.array_equal(images[None], images["none"])
    assert not np.array_equal(images["own"], images["none"]) and not np.array_equal(images["poses"], images["none"])
    # The own-view shell keeps only what the grid camera sees: the ray cast through it shows less of the model.
    hits = kernels.first_hit(kernels.shell(MODEL.labels, MODEL.grid, MODEL.grid.camera(), backend=BACKEND),
                             MODEL.grid, VIEW, backend=BACKEND)
    np.testing.assert_array_equal(images["own"], np.where((hits.label != 0)[..., None], PALETTE[hits.label], 255))


def test_orbit_frames_the_model(tmp_path: Path) -> None:
    """Orbit frames show the model large and centred: framed on its occupied cells, not on the whole frustum."""
    labels = np.zeros_like(MODEL.labels)
    labels[20:30, 10:20, 40:52] = MODEL.labels[20:30, 10:20, 40:52]
    labels[20:30, 10:20, 40:52][labels[20:30, 10:20, 40:52] == 0] = FURNITURE
    fruxel.save(tmp_path / "small.npz", fruxel.FruxelModel(labels, MODEL.grid, MODEL.classes))
    assert run_cli(tmp_path / "small.npz", "--backend", BACKEND, "--orbit", "4", "--shell", "none", "--no-legend",
                   "--size", "120x90", "--out", tmp_path / "turn.gif") == 0
    with Image.open(tmp_path / "turn.gif") as gif:
        for f in range(4):
            gif.seek(f)
            fg = np.argwhere(np.any(np.asarray(gif.convert("RGB")) != 255, axis=-1))
            (y0, x0), (y1, x1) = fg.min(axis=0), fg.max(axis=0)
            # Large: the model spans most of the frame one way; about centred (the orbit turns around the
            # centre of the model's bounding box, so perspective moves its image a little).
            assert max((x1 - x0) / 120, (y1 - y0) / 90) > 0.6
            assert abs((x0 + x1) / 2 - 60) < 0.15 * 120 and abs((y0 + y1) / 2 - 45) < 0.15 * 90


def test_default_view_frames_the_model_and_with_frustum_the_frustum(tmp_path: Path) -> None:
    """A model that holds only cells near the camera (a photo of a near wall) fills the default view, about
    centred; with --frustum the view fits the frustum, where the same model is small."""
    labels = np.zeros_like(MODEL.labels)
    near = (slice(0, 16), slice(None), slice(None))  # the 16 nearest depth slices
    labels[near] = MODEL.labels[near]
    labels[12:16][labels[12:16] == 0] = WALL
    fruxel.save(tmp_path / "near.npz", fruxel.FruxelModel(labels, MODEL.grid, MODEL.classes))
    spans = {}
    for extra in ([], ["--frustum"]):
        out = tmp_path / f"near{len(extra)}.png"
        assert run_cli(tmp_path / "near.npz", "--backend", BACKEND, "--mode", "raycast", "--shading", "flat",
                       "--no-legend", "--size", "120x90", *extra, "--out", out) == 0
        fg = np.argwhere(np.any(read_png(out) != 255, axis=-1))
        (y0, x0), (y1, x1) = fg.min(axis=0), fg.max(axis=0)
        spans[bool(extra)] = max((x1 - x0) / 120, (y1 - y0) / 90)
        if not extra:
            assert abs((x0 + x1) / 2 - 60) < 0.15 * 120 and abs((y0 + y1) / 2 - 45) < 0.15 * 90
    assert spans[False] > 0.7 and spans[True] < 0.6 * spans[False]


def test_view_shell_frames_shade_each_new_mesh_once(monkeypatch: pytest.MonkeyPatch) -> None:
    """With a shell per view and lit shading, each orbit frame builds one pyrender mesh (its own, shaded for its
    camera; the previous one is not re-shaded on the way), and the frames equal those of fresh renderers."""
    from fruxel.cli.render import load_input
    from fruxel.render import frames as fr
    from fruxel.render import scene

    inp = load_input(None)
    opts = fr.RenderOptions(mode="mesh", shell="view", shading="lit", legend=False)
    cams = fr.orbit(inp.grid, default_camera(inp.grid, 160, 120), 3)
    calls = []
    real = scene.pyrender_mesh
    monkeypatch.setattr(scene, "pyrender_mesh", lambda *a, **k: calls.append(1) or real(*a, **k))
    frames = fr.FrameRenderer(inp, opts)
    images = [frames.mesh_image(c)[0] for c in cams]
    assert len(calls) == len(cams)
    for cam, img in zip(cams, images, strict=True):
        np.testing.assert_array_equal(img, fr.FrameRenderer(inp, opts).mesh_image(cam)[0])
    assert not np.array_equal(images[0], images[1])


# ---------------------------------------------------------------------------------------------------- limits
@pytest.mark.parametrize("option", ["--out", "--export"])
def test_an_empty_file_or_folder_name_is_refused(option: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    """``--out ""`` (an unset shell variable) wrote into the current folder."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        run_cli("--backend", BACKEND, "--size", SIZE, option, "")
    assert e.value.code == 2
    lines = error_lines(capsys.readouterr().err)
    assert len(lines) == 1 and lines[0].startswith("fruxel-render: error: ") and option in lines[0]
    assert not any(tmp_path.iterdir())


def huge_model_file(path: Path, width: int, height: int, depth: int) -> Path:
    """A small model file (a few hundred kB of compressed zeros) that declares a large grid."""
    grid = fruxel.FruxelGrid(width=width, height=height, depth=depth, z_near=0.5, z_far=8.0, hfov=60.0)
    meta = json.dumps({"format": "fruxel", "version": 1, "grid": grid.to_dict(),
                       "classes": fruxel.DEFAULT_CLASSES.to_dict()})
    # Zeros never touched are never allocated: np.zeros costs no memory until written.
    np.savez_compressed(path, labels=np.zeros((depth, height, width), np.uint8), meta=np.array(meta, dtype=np.str_))
    return path


def limited_memory_cli(limit: int, *argv: str) -> subprocess.CompletedProcess[str]:
    """The command in a process whose address space is limited to ``limit`` bytes (``ulimit -v``)."""
    import resource

    def limit_memory() -> None:
        resource.setrlimit(resource.RLIMIT_AS, (limit, limit))

    code = "import sys; from fruxel.cli.render import main; sys.exit(main(sys.argv[1:]))"
    return subprocess.run([sys.executable, "-c", code, *argv], capture_output=True, text=True, timeout=300,
                          preexec_fn=limit_memory)


@pytest.mark.skipif(not sys.platform.startswith("linux"), reason="needs Linux's address-space limit")
def test_a_grid_too_large_for_memory_is_refused_before_it_is_read(tmp_path: Path) -> None:
    """A file of compressed zeros declaring 268 million cells, in a process limited to 600 MB: refused in one line
    naming the file and the memory, from its header, before the labels are decompressed (and nothing written)."""
    huge = huge_model_file(tmp_path / "huge.npz", 1024, 1024, 256)
    assert huge.stat().st_size < 2_000_000
    out = tmp_path / "out"
    result = limited_memory_cli(600 << 20, str(huge), "--backend", BACKEND, "--size", SIZE, "--out", str(out))
    lines = error_lines(result.stderr)
    assert result.returncode == 2 and len(lines) == 1, result.stderr
    assert lines[0].startswith(f"fruxel-render: error: {huge}: ") and "1024x1024x256" in lines[0]
    assert "of memory, more than the" in lines[0] and "Traceback" not in result.stderr
    assert not out.exists()


def test_orbit_shows_its_progress_on_a_terminal(tmp_path: Path) -> None:
    """On a terminal, an orbit shows a bar while its frames are drawn and another while the video is encoded (a
    GIF maps every frame onto its palette once all are drawn)."""
    import fcntl
    import pty
    import struct
    import termios

    leader, follower = pty.openpty()
    fcntl.ioctl(follower, termios.TIOCSWINSZ, struct.pack("HHHH", 40, 120, 0, 0))
    code = "import sys; from fruxel.cli.render import main; sys.exit(main(sys.argv[1:]))"
    out = tmp_path / "orbit.gif"
    proc = subprocess.Popen([sys.executable, "-c", code, "--backend", BACKEND, "--size", SIZE, "--orbit", "6",
                             "--out", str(out)], stdout=subprocess.PIPE, stderr=follower)
    os.close(follower)
    seen = b""
    while True:
        try:
            chunk = os.read(leader, 65536)
        except OSError:  # the terminal closes with the process
            break
        if not chunk:
            break
        seen += chunk
    os.close(leader)
    assert proc.wait(timeout=120) == 0
    assert proc.stdout is not None and proc.stdout.read().decode().split() == [str(out)]
    text = seen.decode(errors="replace")
    assert "orbit:" in text and "/6 [" in text.split("encode:")[0], text
    assert "encode:" in text and "/6 [" in text.split("encode:")[1], text


@pytest.mark.skipif("opencl" not in kernels.available_backends(), reason="no OpenCL device")
def test_a_run_prints_its_files_and_nothing_else(tmp_path: Path) -> None:
    """Quiet by default: with fresh compiler caches (kernels built from source) and then with warm ones, a run
    prints the files it wrote and nothing on stderr (no compiler warnings, no notes)."""
    env = {**os.environ, "XDG_CACHE_HOME": str(tmp_path / "cache")}
    env.pop("PYOPENCL_COMPILER_OUTPUT", None)
    for run in ("cold", "warm"):
        out = tmp_path / run
        result = subprocess_cli("--backend", "opencl", "--mode", "both", "--size", SIZE, "--out", str(out), env=env)
        assert result.returncode == 0, result.stderr
        assert result.stdout.split() == [str(out / "sample_room_both.png")]
        assert error_lines(result.stderr) == [], result.stderr

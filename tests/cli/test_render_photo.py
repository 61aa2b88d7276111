"""``fruxel-render PHOTO``: SSZ predicts the photo's model, which is drawn beside the photo and its ground truth;
``make demo`` runs it on the two bundled photos. Runs call :func:`fruxel.cli.render.main` in this process."""

from __future__ import annotations

import re
import shlex
import shutil
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

import fruxel
from fruxel import kernels
from fruxel.cli.render import InputError, build_parser, is_photo, load_photo, main
from fruxel.data import PHOTO, PHOTO_TRUTH, PHOTO_TRUTH_128, ROOM_PHOTO, ROOM_TRUTH, SAMPLE_ROOM
from fruxel.render.compare import GAP, fit_height
from fruxel.train.predict import frame_image, load_image

from .errors import assert_one_error_line

ROOT = Path(__file__).resolve().parents[2]
TRUTH = fruxel.load(PHOTO_TRUTH)
PALETTE = TRUTH.classes.palette()
CLASSES = {name: TRUTH.classes.index(name) for name in TRUTH.classes.names}
W, H = 96, 72
"""Model panel size of these tests."""
BACKEND_ARGS = {"warp-cpu": ("--backend", "warp", "--device", "cpu"), "opencl": ("--backend", "opencl")}
"""fruxel-render's options for each CPU backend of fruxel.kernels.available_backends()."""


def run_cli(*argv: object) -> int:
    return main([str(a) for a in argv])


def read_png(path: Path) -> np.ndarray:
    assert path.is_file() and path.stat().st_size > 0
    return np.asarray(Image.open(path).convert("RGB"))


def colours_present(image: np.ndarray) -> set[str]:
    flat = image.reshape(-1, 3)
    return {n for n, c in CLASSES.items() if c and np.any(np.all(flat == PALETTE[c], axis=1))}


def find(picture: np.ndarray, panel: np.ndarray) -> list[tuple[int, int]]:
    """Top-left corners where ``panel`` occurs exactly in ``picture``."""
    ph, pw = panel.shape[:2]
    ys, xs = np.nonzero(np.all(picture == panel[0, 0], axis=-1))
    return [(int(y), int(x)) for y, x in zip(ys, xs, strict=True)
            if y + ph <= picture.shape[0] and x + pw <= picture.shape[1]
            and np.array_equal(picture[y:y + ph, x:x + pw], panel)]


@pytest.fixture(scope="module")
def photo_panel() -> np.ndarray:
    """The photo as its panel shows it at height H: framed to the grid's view, then scaled."""
    return fit_height(frame_image(load_image(PHOTO), TRUTH.grid, (512, 512)), H)


# ---------------------------------------------------------------------------------------------------- pictures
@pytest.mark.parametrize("backend", list(BACKEND_ARGS))
def test_photo_with_truth_on_each_backend(tmp_path: Path, backend: str, photo_panel: np.ndarray,
                                          capsys: pytest.CaptureFixture[str]) -> None:
    if backend not in kernels.available_backends():
        pytest.skip(f"{backend} is not available here: {kernels.available_backends()}")
    assert run_cli(PHOTO, "--truth", PHOTO_TRUTH, *BACKEND_ARGS[backend], "--mode", "both", "--shading", "flat",
                   "--size", f"{W}x{H}", "--out", tmp_path) == 0
    out = tmp_path / "photo_both.png"
    assert capsys.readouterr().out.split() == [str(out)]
    img = read_png(out)
    # Photo column (H wide: the grid is square), prediction and truth columns, each panel W wide.
    assert img.shape[1] == GAP + H + GAP + W + GAP + W + GAP
    assert img.shape[0] > 2 * H + GAP
    # The photo's panel, and every class of the room in the flat-shaded models.
    assert len(find(img, photo_panel)) == 1
    assert colours_present(img) == {"wall", "floor", "window", "furniture", "door", "sculpture"}


def test_photo_without_truth_has_two_columns(tmp_path: Path, photo_panel: np.ndarray) -> None:
    assert run_cli(PHOTO, "--mode", "raycast", "--size", f"{W}x{H}", "--out", tmp_path / "p.png") == 0
    img = read_png(tmp_path / "p.png")
    assert img.shape[1] == GAP + H + GAP + W + GAP
    assert find(img, photo_panel)


def test_title_states_the_own_view_accuracy() -> None:
    args = build_parser().parse_args([str(PHOTO), "--checkpoint", "ssz64", "--truth", str(PHOTO_TRUTH),
                                      "--device", "cpu"])
    inp, photo = load_photo(args)
    assert inp.volume.shape == (1, 7, 64, 64, 64) and inp.grid == TRUTH.grid
    assert "ssz64.safetensors" in photo.title and "98.4 %" in photo.title, photo.title
    assert photo.truth is not None and np.array_equal(photo.truth.volume, TRUTH.labels)


def test_the_default_model_reads_a_truth_of_fewer_classes_by_name(tmp_path: Path) -> None:
    """The default model (ssz64-any, nine classes) against the flat world's truth (seven), its table written in
    another order (wall and door swapped, their labels with them): the truth's labels are carried into the model's
    table by class name, and told the photo's camera the model finds the truth's own view."""
    from fruxel.classes import ClassTable
    from fruxel.model import FruxelModel

    order = [0, 5, 2, 3, 4, 1, 6]  # new label i holds the class of old label order[i]
    names = [TRUTH.classes.names[i] for i in order]
    labels = np.argsort(order).astype(np.uint8)[np.asarray(TRUTH.labels)]
    swapped = tmp_path / "swapped.npz"
    fruxel.save(swapped, FruxelModel(labels, TRUTH.grid, ClassTable.from_names(names)))
    args = build_parser().parse_args([str(PHOTO), "--truth", str(swapped), "--pitch", "10", "--height", "1.0",
                                      "--device", "cpu"])
    inp, photo = load_photo(args)
    assert inp.volume.shape == (1, 9, 64, 64, 64) and "ssz64-any.safetensors" in photo.title
    assert photo.truth is not None and photo.truth.classes == inp.classes
    model_names = inp.classes.names
    for old, name in enumerate(TRUTH.classes.names):  # each cell keeps its class, under the model's label id
        cells = np.asarray(TRUTH.labels) == old
        assert np.all(photo.truth.volume[cells] == model_names.index(name))
    accuracy = float(re.search(r"accuracy against swapped.npz: ([0-9.]+) %", photo.title).group(1))
    assert accuracy > 90.0, photo.title


def test_a_truth_with_a_class_the_model_lacks_is_one_line(tmp_path: Path) -> None:
    """A truth whose classes are not all the model's is refused before the render, naming both tables."""
    from fruxel.classes import ClassTable
    from fruxel.model import FruxelModel

    odd = tmp_path / "odd.npz"
    fruxel.save(odd, FruxelModel(np.asarray(TRUTH.labels), TRUTH.grid, ClassTable.from_names(
        ["empty", "wall", "floor", "window", "furniture", "door", "statue"])))
    args = build_parser().parse_args([str(PHOTO), "--truth", str(odd), "--device", "cpu"])
    with pytest.raises(InputError, match="odd.npz.*statue.*not all among"):
        load_photo(args)


def test_the_128_model_by_name_with_its_truth(tmp_path: Path) -> None:
    """``--checkpoint ssz128``: the shipped 128^3 model predicts the photo at its own 512 x 512 size; its title gives
    the own view against the 128^3 truth, and the 64^3 truth is refused with a line naming both grids."""
    args = build_parser().parse_args([str(PHOTO), "--checkpoint", "ssz128", "--truth", str(PHOTO_TRUTH_128),
                                      "--device", "cpu"])
    inp, photo = load_photo(args)
    assert inp.volume.shape == (1, 7, 128, 128, 128)
    assert "ssz128" in photo.title and "128x128x128" in photo.title and "98.5 %" in photo.title, photo.title
    args = build_parser().parse_args([str(PHOTO), "--checkpoint", "ssz128", "--truth", str(PHOTO_TRUTH)])
    with pytest.raises(InputError, match="64x64x64.*128x128x128"):
        load_photo(args)


def test_make_demo_command_lines_run(tmp_path: Path) -> None:
    """The Makefile's demo recipe, as written there, with its output folder moved into tmp_path: the furnished room
    and the robot's flat photo, each predicted by the default model told its camera, whose own view it reads."""
    recipe = [ln.strip() for ln in (ROOT / "Makefile").read_text().splitlines() if "bin/fruxel-render" in ln]
    assert len(recipe) == 2
    for line, photo, truth in zip(recipe, (ROOM_PHOTO, PHOTO), (ROOM_TRUTH, PHOTO_TRUTH), strict=True):
        argv = shlex.split(line)[1:]
        out = argv.index("--out")
        argv[out + 1] = str(tmp_path / argv[out + 1])
        argv = [str(ROOT / a) if (ROOT / a).is_file() else a for a in argv]
        assert argv[0] == str(photo) and str(truth) in argv and "--checkpoint" not in argv
        _, shown = load_photo(build_parser().parse_args([*argv, "--device", "cpu"]))
        accuracy = float(re.search(rf"accuracy against {truth.name}: ([0-9.]+) %", shown.title).group(1))
        assert accuracy > 80.0, shown.title
        assert main(argv) == 0
    pictures = sorted(p.name for p in tmp_path.rglob("*.png"))
    assert pictures == ["photo_both.png", "room_both.png"]
    img = read_png(tmp_path / "out" / "room_both.png")
    assert img.shape[0] > 700 and img.shape[1] > 1200


def test_photo_is_recognised_by_its_content(tmp_path: Path) -> None:
    snap = tmp_path / "snap.dat"
    shutil.copy(PHOTO, snap)
    assert is_photo(str(snap)) and is_photo(str(PHOTO)) and not is_photo(str(SAMPLE_ROOM))
    assert run_cli(snap, "--mode", "mesh", "--size", f"{W}x{H}", "--out", tmp_path) == 0
    assert (tmp_path / "snap_mesh.png").is_file()


def test_photo_orbit_and_export(tmp_path: Path) -> None:
    trimesh = pytest.importorskip("trimesh")
    assert run_cli(PHOTO, "--orbit", "2", "--size", f"{W}x{H}", "--out", tmp_path / "o.gif",
                   "--export", tmp_path / "pred.glb") == 0
    with Image.open(tmp_path / "o.gif") as gif:
        assert gif.n_frames == 2
    assert len(trimesh.load(tmp_path / "pred.glb", force="mesh", process=False).faces) > 1000


def test_wider_field_of_view_changes_the_prediction() -> None:
    """--hfov reaches the model: at 90 degrees the model sees the photo's middle 58 %, enlarged."""
    base = build_parser().parse_args([str(PHOTO), "--device", "cpu"])
    wide = build_parser().parse_args([str(PHOTO), "--hfov", "90", "--device", "cpu"])
    a, b = (load_photo(x)[0].volume.argmax(1) for x in (base, wide))
    assert float((a != b).float().mean()) > 0.002


# ---------------------------------------------------------------------------------------------------- errors
def _one_error_line(rc: int, err: str, *words: str) -> None:
    assert_one_error_line("fruxel-render", rc, err, *words)


@pytest.mark.parametrize(("case", "words"), [
    ("garbage", ("bad.png", "not a readable image")),
    ("truncated", ("bad.png", "not a readable image")),
    ("missing", ("bad.png", "no such file")),
    ("folder", ("bad.png", "not a regular file")),
])
def test_bad_photo(tmp_path: Path, capsys: pytest.CaptureFixture[str], case: str, words: tuple[str, ...]) -> None:
    bad = tmp_path / "bad.png"
    if case == "garbage":
        bad.write_bytes(b"this is not an image\n" * 10)
    elif case == "truncated":
        bad.write_bytes(PHOTO.read_bytes()[:300])
    elif case == "folder":
        bad.mkdir()
    _one_error_line(run_cli(bad, "--out", tmp_path / "out"), capsys.readouterr().err, *words)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("hfov", ["200", "0", "-10", "nan", "inf", "180"])
def test_bad_hfov(tmp_path: Path, capsys: pytest.CaptureFixture[str], hfov: str) -> None:
    _one_error_line(run_cli(PHOTO, "--hfov", hfov, "--out", tmp_path / "out"), capsys.readouterr().err, "--hfov",
                    "(0, 180)")
    assert not (tmp_path / "out").exists()


def test_hfov_that_is_no_number(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        run_cli(PHOTO, "--hfov", "wide", "--out", tmp_path)
    _one_error_line(e.value.code, capsys.readouterr().err, "--hfov", "wide")


@pytest.mark.parametrize(("argv", "words"), [
    (("--truth", SAMPLE_ROOM), ("--truth", "grid")),
    (("--truth", "missing.npz"), ("missing.npz",)),
    (("--checkpoint", "missing.safetensors"), ("missing.safetensors", "no such file")),
    (("--checkpoint", PHOTO_TRUTH), ("photo_truth.npz",)),
    (("--grid", "32"), ("--grid", "photo")),
    (("--z-far", "6"), ("--z-far", "photo")),
])
def test_options_that_do_not_fit_the_photo(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                           argv: tuple[object, ...], words: tuple[str, ...]) -> None:
    _one_error_line(run_cli(PHOTO, *argv, "--out", tmp_path / "out"), capsys.readouterr().err, *words)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize(("case", "words"), [
    ("tiny photo", ("tiny.png", "4x4")),
    ("strip photo", ("strip.png", "4000x50")),
    ("out under a file", ("--out", "file is a file")),
    ("image for an orbit", ("--orbit", "x.png")),
    ("missing camera", ("--camera", "missing.json")),
    ("export under a file", ("--export", "file is a file")),
])
def test_checks_come_before_the_prediction(case: str, words: tuple[str, ...], tmp_path: Path,
                                           capsys: pytest.CaptureFixture[str]) -> None:
    """With a model file that cannot load, the error is still the photo's, the camera's or the output's: every
    check that needs no model comes before it is loaded (and before the photo is predicted)."""
    broken = tmp_path / "broken.safetensors"
    broken.write_bytes(b"not a model")
    (tmp_path / "file").write_text("")
    tiny, strip = tmp_path / "tiny.png", tmp_path / "strip.png"
    Image.fromarray(np.zeros((4, 4, 3), np.uint8)).save(tiny)
    Image.fromarray(np.zeros((50, 4000, 3), np.uint8)).save(strip)
    out = tmp_path / "out"
    argv = {"tiny photo": (tiny, "--out", out), "strip photo": (strip, "--out", out),
            "out under a file": (PHOTO, "--out", tmp_path / "file" / "x.png"),
            "image for an orbit": (PHOTO, "--orbit", "3", "--out", tmp_path / "x.png"),
            "missing camera": (PHOTO, "--camera", tmp_path / "missing.json", "--out", out),
            "export under a file": (PHOTO, "--export", tmp_path / "file" / "x.glb", "--out", out)}[case]
    before = sorted(p.name for p in tmp_path.iterdir())
    rc = run_cli(*argv, "--checkpoint", broken)
    err = capsys.readouterr().err
    _one_error_line(rc, err, *words)
    assert "broken" not in err
    assert sorted(p.name for p in tmp_path.iterdir()) == before


def test_a_pickle_or_a_checkpoint_named_safetensors_is_one_line(tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """torch.load reads any file named .safetensors as safetensors: a traceback, before."""
    import pickle

    import torch

    pickled, archive = tmp_path / "pickled.safetensors", tmp_path / "last.safetensors"
    pickled.write_bytes(pickle.dumps({"generator": {"w": 1}}, protocol=2))
    torch.save({"generator": {"w": torch.zeros(2)}}, archive)
    for path, word in ((pickled, "Python pickle"), (archive, ".pt name")):
        _one_error_line(run_cli(PHOTO, "--checkpoint", path, "--out", tmp_path / "out"), capsys.readouterr().err,
                        str(path), word)
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("option", [("--truth", PHOTO_TRUTH), ("--checkpoint", PHOTO_TRUTH), ("--fit", "pad")])
def test_photo_options_without_a_photo(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                       option: tuple[object, ...]) -> None:
    _one_error_line(run_cli(SAMPLE_ROOM, *option, "--out", tmp_path), capsys.readouterr().err, str(option[0]),
                    "photo")

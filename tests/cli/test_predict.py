"""Tests of ``fruxel-predict``: photos of any size become model and logits files that fruxel reads back and
``fruxel-render`` draws; bad images, options and model files give one error line and exit status 2."""

from __future__ import annotations

import pickle
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

import fruxel
from fruxel.cli import predict as predict_cli

torch = pytest.importorskip("torch")

from fruxel.train.model_files import load_model  # noqa: E402 - needs torch
from fruxel.train.predict import load_image, prepare_image  # noqa: E402


def photo(path: Path, width: int, height: int, seed: int = 0) -> Path:
    """A photo-like picture: smooth colour gradients with a bright box, saved in the format of ``path``'s suffix."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    img = np.stack([x * 255 // max(1, width - 1), y * 255 // max(1, height - 1), np.full_like(x, 90)], -1)
    x0, y0 = int(rng.integers(0, max(1, width // 2))), int(rng.integers(0, max(1, height // 2)))
    img[y0:y0 + height // 3, x0:x0 + width // 3] = (230, 210, 40)
    Image.fromarray(img.astype(np.uint8)).save(path)
    return path


def error_line(capsys: pytest.CaptureFixture[str], prog: str = "fruxel-predict") -> str:
    """The command's one error line (Warp's own notices on stderr are not the command's)."""
    lines = [ln for ln in capsys.readouterr().err.splitlines() if ln.strip() and not ln.startswith("Warp ")]
    assert len(lines) == 1, lines
    assert lines[0].startswith(f"{prog}: error: "), lines[0]
    assert "Traceback" not in lines[0]
    return lines[0]


def expected_logits(model: Path, image: Path, **prepare: Any) -> np.ndarray:
    """The logits ``(C, D, H, W)`` float32 of one photo, computed here from the model and the photo directly."""
    loaded = load_model(model)
    gen, config = loaded.network, loaded.config
    img = prepare_image(load_image(image), config, **prepare)
    x = torch.from_numpy(np.array(img)).permute(2, 0, 1)[None].float() / 255.0
    with torch.no_grad():
        return gen(x).logits[0].numpy()


def test_png_and_odd_sized_jpeg_become_model_and_logits_files(shipped_model: Path, tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    png = photo(tmp_path / "room.png", 160, 120)
    jpg = photo(tmp_path / "odd.jpg", 97, 61, seed=1)
    out = tmp_path / "out"
    assert predict_cli.main([str(png), str(jpg), "--checkpoint", str(shipped_model), "--out", str(out), "--logits",
                             "--batch", "1"]) == 0
    printed = capsys.readouterr().out.split()
    names = ["room.npz", "room.logits.npz", "odd.npz", "odd.logits.npz"]
    assert printed == [str(out / n) for n in names]
    assert sorted(p.name for p in out.iterdir()) == sorted(names)

    config = load_model(shipped_model).config
    for stem, image in (("room", png), ("odd", jpg)):
        model = fruxel.load(out / f"{stem}.npz")
        logits = fruxel.load_logits(out / f"{stem}.logits.npz")
        assert model.grid == config.grid and logits.grid == config.grid
        assert model.classes == config.classes and logits.classes == config.classes
        assert logits.logits.dtype == np.float16 and logits.logits.shape == (7, 16, 16, 16)
        # Both files show the same cells: the labels are the argmax of the stored logits.
        np.testing.assert_array_equal(model.labels, logits.labels())
        want = expected_logits(shipped_model, image)
        np.testing.assert_allclose(logits.logits.astype(np.float32), want, rtol=2e-3, atol=2e-2)
        top2 = np.sort(want, axis=0)[-2:]
        clear = top2[1] - top2[0] > 0.05
        np.testing.assert_array_equal(model.labels[clear], want.argmax(0)[clear])
        assert len(np.unique(model.labels)) > 1, "the test model should predict several classes"


def test_predictions_are_read_by_fruxel_render(shipped_model: Path, tmp_path: Path) -> None:
    from fruxel.cli.render import main as render

    jpg = photo(tmp_path / "odd.jpg", 97, 61)
    out = tmp_path / "out"
    assert predict_cli.main([str(jpg), "--checkpoint", str(shipped_model), "--out", str(out), "--logits", "-q"]) == 0
    for name in ("odd.npz", "odd.logits.npz"):
        target = tmp_path / f"{name}.png"
        assert render([str(out / name), "--mode", "raycast", "--size", "48x36", "--out", str(target)]) == 0
        img = np.asarray(Image.open(target).convert("RGB"))
        assert img.shape == (36, 48, 3) and np.any(img != 255)


def test_both_model_file_forms_predict_the_same(shipped_model: Path, checkpoint_model: Path, tmp_path: Path) -> None:
    jpg = photo(tmp_path / "odd.jpg", 97, 61)
    for name, model in (("a", shipped_model), ("b", checkpoint_model)):
        assert predict_cli.main([str(jpg), "--checkpoint", str(model), "--out", str(tmp_path / name), "--logits",
                                 "-q", "--fit", "pad", "--hfov", "40"]) == 0
    a, b = (fruxel.load_logits(tmp_path / n / "odd.logits.npz") for n in "ab")
    np.testing.assert_array_equal(a.logits, b.logits)
    want = expected_logits(checkpoint_model, jpg, fit="pad", hfov=40.0)
    # A 40-degree photo in the 60-degree grid: the columns around it see grey and are left empty.
    from fruxel.train.predict import frame_coverage

    covered = frame_coverage((61, 97), a.grid, 40.0, "pad")
    assert covered.any() and not covered.all()
    np.testing.assert_allclose(a.logits.astype(np.float32)[..., covered], want[..., covered], rtol=2e-3, atol=2e-2)
    assert (a.labels()[:, ~covered] == 0).all()


def test_batches_give_the_predictions_of_single_images(shipped_model: Path, tmp_path: Path) -> None:
    images = [str(photo(tmp_path / f"p{i}.png", 50 + 7 * i, 40 + 3 * i, seed=i)) for i in range(3)]
    for batch in ("1", "2"):
        assert predict_cli.main([*images, "--checkpoint", str(shipped_model), "--out", str(tmp_path / batch),
                                 "--batch", batch, "--logits", "-q"]) == 0
    for i in range(3):
        one, two = (fruxel.load_logits(tmp_path / b / f"p{i}.logits.npz").logits.astype(np.float32) for b in "12")
        np.testing.assert_allclose(one, two, rtol=2e-3, atol=2e-2)


# ---------------------------------------------------------------------------------------------------- bad input
def test_duplicate_output_names_are_refused_before_any_work(shipped_model: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    x1, x2 = photo(tmp_path / "a" / "x.png", 40, 30), photo(tmp_path / "b" / "x.jpg", 40, 30)
    out = tmp_path / "out"
    assert predict_cli.main([str(x1), str(x2), "--checkpoint", str(shipped_model), "--out", str(out)]) == 2
    line = error_line(capsys)
    assert str(x1) in line and str(x2) in line and "x.npz" in line
    assert not out.exists()
    # x.logits.png would write x.logits.npz, the logits file of x.png.
    y1, y2 = photo(tmp_path / "y.png", 40, 30), photo(tmp_path / "y.logits.png", 40, 30)
    assert predict_cli.main([str(y1), str(y2), "--checkpoint", str(shipped_model), "--out", str(out)]) == 0
    assert predict_cli.main([str(y1), str(y2), "--checkpoint", str(shipped_model), "--out", str(out),
                             "--logits"]) == 2
    assert "y.logits.npz" in error_line(capsys)


@pytest.mark.parametrize("kind", ["missing", "garbage", "empty", "truncated", "folder", "text"])
def test_bad_images_give_one_line_and_write_nothing(kind: str, shipped_model: Path, tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    good = photo(tmp_path / "good.png", 40, 30)
    bad = tmp_path / "bad.png"
    if kind == "garbage":
        bad.write_bytes(np.random.default_rng(0).bytes(500))
    elif kind == "empty":
        bad.write_bytes(b"")
    elif kind == "truncated":
        bad.write_bytes(photo(tmp_path / "whole.png", 64, 48).read_bytes()[:80])
    elif kind == "folder":
        bad.mkdir()
    elif kind == "text":
        bad = tmp_path / "notes.jpg"
        bad.write_text("not a picture\n")
    out = tmp_path / "out"
    assert predict_cli.main([str(good), str(bad), "--checkpoint", str(shipped_model), "--out", str(out)]) == 2
    assert str(bad) in error_line(capsys)
    assert not out.exists(), "every image is checked before anything is written"


@pytest.mark.parametrize("value", ["0", "180", "-5", "nan", "inf", "wide"])
def test_bad_field_of_view(value: str, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    img = photo(tmp_path / "x.png", 40, 30)
    with pytest.raises(SystemExit) as e:
        predict_cli.main([str(img), "--hfov", value])
    assert e.value.code == 2
    line = error_line(capsys)
    assert "--hfov" in line and f"{value!r}" in line


def test_long_lens_photo_is_padded_at_the_models_scale(shipped_model: Path, tmp_path: Path) -> None:
    """A 1-degree photo in a 60-degree grid would need a frame of 264000^2 pixels at its own scale."""
    big = tmp_path / "tele.png"
    Image.fromarray(np.full((3000, 4000, 3), 200, np.uint8)).save(big)
    config = load_model(shipped_model).config
    img = prepare_image(load_image(big), config, hfov=1.0, fit="pad")
    covered = np.argwhere(np.any(img != 128, axis=-1))
    assert img.shape == (64, 64, 3) and 0 < len(covered) <= 4
    assert np.all(np.abs(covered - 31.5) <= 1.5), "the photo sits at the centre of the view"
    assert predict_cli.main([str(big), "--checkpoint", str(shipped_model), "--out", str(tmp_path / "o"), "--fit",
                             "pad", "--hfov", "1", "-q"]) == 0


def test_out_must_be_a_folder(shipped_model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    img = photo(tmp_path / "x.png", 40, 30)
    (tmp_path / "file").write_text("")
    assert predict_cli.main([str(img), "--checkpoint", str(shipped_model), "--out", str(tmp_path / "file")]) == 2
    assert "--out" in error_line(capsys)
    # A file name that does not exist yet is not made into a folder of that name.
    assert predict_cli.main([str(img), "--checkpoint", str(shipped_model), "--out", str(tmp_path / "x.npz")]) == 2
    assert "--out" in error_line(capsys) and not (tmp_path / "x.npz").exists()


class CreatesFile:
    """Unpickling this calls ``Path.touch(marker)``: a stand-in for code a hostile checkpoint would run."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple[Any, ...]:
        return (Path.touch, (self.marker,))


def bad_model_file(kind: str, tmp_path: Path, shipped_model: Path) -> tuple[Path, str]:
    """A model file that must be refused, and a word its error line must hold."""
    path = tmp_path / f"{kind}.model"
    marker = tmp_path / "ran"
    if kind == "missing":
        return path, "no such file"
    if kind == "folder":
        path.mkdir()
        return path, "not a regular file"
    if kind == "garbage":
        path.write_bytes(np.random.default_rng(1).bytes(4000))
    elif kind == "empty":
        path.write_bytes(b"")
    elif kind == "truncated":
        path.write_bytes(shipped_model.read_bytes()[:3000])
    elif kind == "pickled-zip":
        torch.save({"format": "fruxel-ssz-checkpoint", "generator": CreatesFile(marker)}, path)
        return path, "refused"
    elif kind == "pickled-raw":
        path.write_bytes(pickle.dumps({"generator": CreatesFile(marker)}, protocol=2))
        return path, "refused"
    elif kind == "foreign-safetensors":
        from safetensors.torch import save_file

        save_file({"w": torch.zeros(3)}, str(path), metadata={"format": "something-else"})
        return path, "format"
    elif kind == "wrong-shapes":
        from safetensors import safe_open
        from safetensors.torch import save_file

        with safe_open(str(shipped_model), framework="pt") as f:
            meta = f.metadata()
            state = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - safe_open has no items()
        state["head.weight"] = torch.zeros(3, 4, 1, 1, 1)
        save_file(state, str(path), metadata=meta)
        return path, "do not fit"
    elif kind == "plain-dict-checkpoint":
        torch.save({"step": 1}, path)
        return path, "not a fruxel SSZ checkpoint"
    elif kind == "pickle-named-safetensors":
        # torch.load reads a file named .safetensors as safetensors whatever it holds.
        path = tmp_path / "model.safetensors"
        path.write_bytes(pickle.dumps({"generator": CreatesFile(marker)}, protocol=2))
        return path, "Python pickle"
    elif kind == "checkpoint-named-safetensors":
        from fruxel.train.config import DataConfig, TrainConfig
        from fruxel.train.engine.checkpoint import save_checkpoint

        loaded = load_model(shipped_model)
        gen, config = loaded.network, loaded.config
        path = tmp_path / "last.safetensors"
        save_checkpoint(path, {"step": 0, "samples": 0, "generator": gen.state_dict()},
                        TrainConfig(model=config, data=DataConfig(world="flat")))
        return path, ".pt name"
    elif kind in ("int8-weights", "nan-weights"):
        from safetensors import safe_open
        from safetensors.torch import save_file

        with safe_open(str(shipped_model), framework="pt") as f:
            meta = f.metadata()
            state = {k: f.get_tensor(k) for k in f.keys()}  # noqa: SIM118 - safe_open has no items()
        if kind == "int8-weights":
            state = {k: (v * 100).clamp(-127, 127).to(torch.int8) if v.is_floating_point() else v
                     for k, v in state.items()}
        else:
            state["head.weight"].view(-1)[3] = float("nan")
        save_file(state, str(path), metadata=meta)
        return path, "int8" if kind == "int8-weights" else "NaN"
    return path, "not a readable"


BAD_MODELS = ["missing", "folder", "garbage", "empty", "truncated", "pickled-zip", "pickled-raw",
              "foreign-safetensors", "wrong-shapes", "plain-dict-checkpoint", "pickle-named-safetensors",
              "checkpoint-named-safetensors", "int8-weights", "nan-weights"]


@pytest.mark.parametrize("kind", BAD_MODELS)
def test_bad_model_files_give_one_line_and_run_nothing(kind: str, shipped_model: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    path, word = bad_model_file(kind, tmp_path, shipped_model)
    img = photo(tmp_path / "x.png", 40, 30)
    out = tmp_path / "out"
    assert predict_cli.main([str(img), "--checkpoint", str(path), "--out", str(out)]) == 2
    line = error_line(capsys)
    assert str(path) in line and word in line, line
    assert not (tmp_path / "ran").exists(), "a pickled object in the file was run"
    assert not out.exists()


def grey_photos(tmp_path: Path) -> tuple[np.ndarray, dict[str, Path]]:
    """An 8-bit grey picture and the same picture as a 16-bit grey PNG, a 32-bit float TIFF in [0, 1] and a plain
    8-bit grey PNG (the reference)."""
    v8 = np.asarray(Image.open(photo(tmp_path / "src.png", 80, 60)).convert("L"))
    files = {"grey8": tmp_path / "grey8.png", "grey16": tmp_path / "grey16.png", "float": tmp_path / "float.tif"}
    Image.fromarray(v8).save(files["grey8"])
    Image.fromarray(v8.astype(np.uint16) * 257).save(files["grey16"])
    Image.fromarray(v8.astype(np.float32) / 255.0).save(files["float"])
    return v8, files


def test_wide_grey_photos_are_read_as_the_same_picture(shipped_model: Path, tmp_path: Path) -> None:
    """A 16-bit grey PNG and a float TIFF hold the 8-bit picture scaled: they give its prediction (Pillow's own
    conversion read the first as white and the second as black)."""
    v8, files = grey_photos(tmp_path)
    assert Image.open(files["grey16"]).mode.startswith("I;16") and Image.open(files["float"]).mode == "F"
    for f in files.values():
        np.testing.assert_array_equal(load_image(f), np.repeat(v8[..., None], 3, axis=2))
    out = tmp_path / "out"
    assert predict_cli.main([*map(str, files.values()), "--checkpoint", str(shipped_model), "--out", str(out),
                             "--logits", "-q"]) == 0
    want = fruxel.load_logits(out / "grey8.logits.npz").logits
    for name in ("grey16", "float"):
        np.testing.assert_array_equal(fruxel.load_logits(out / f"{name}.logits.npz").logits, want)


@pytest.mark.parametrize(("kind", "word"), [("int32", "32-bit integer"), ("float-range", "from -1 to 2"),
                                            ("float-nan", "nan")])
def test_photos_whose_pixels_have_no_scale_are_refused(kind: str, word: str, shipped_model: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    bad = tmp_path / f"{kind}.tif"
    ramp = np.linspace(-1.0, 2.0, 40 * 30).reshape(30, 40)
    if kind == "int32":
        Image.fromarray((ramp * 1e6).astype(np.int32)).save(bad)
    else:
        values = ramp.astype(np.float32) if kind == "float-range" else np.full((30, 40), np.nan, np.float32)
        Image.fromarray(values).save(bad)
    out = tmp_path / "out"
    assert predict_cli.main([str(bad), "--checkpoint", str(shipped_model), "--out", str(out)]) == 2
    line = error_line(capsys)
    assert str(bad) in line and word in line, line
    assert not out.exists()


@pytest.mark.parametrize(("size", "word"), [((1, 1), "too small"), ((15, 200), "too small"),
                                            ((4000, 50), "strip"), ((50, 401), "strip")])
def test_photos_of_no_cameras_size_are_refused(size: tuple[int, int], word: str, shipped_model: Path,
                                               tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """Limits: at least MIN_PHOTO_SIDE pixels on the shorter side, at most MAX_PHOTO_ASPECT times as long as wide;
    the limits themselves pass."""
    from fruxel.cli.common import MAX_PHOTO_ASPECT, MIN_PHOTO_SIDE

    bad = photo(tmp_path / "odd.png", *size)
    out = tmp_path / "out"
    assert predict_cli.main([str(bad), "--checkpoint", str(shipped_model), "--out", str(out)]) == 2
    line = error_line(capsys)
    assert str(bad) in line and f"{size[0]}x{size[1]}" in line and word in line, line
    assert not out.exists()
    edge = [photo(tmp_path / "small.png", MIN_PHOTO_SIDE, MIN_PHOTO_SIDE),
            photo(tmp_path / "long.png", int(MAX_PHOTO_ASPECT * 20), 20)]
    assert predict_cli.main([*map(str, edge), "--checkpoint", str(shipped_model), "--out", str(out), "-q"]) == 0


def test_photos_and_the_output_folder_are_checked_before_the_model_loads(tmp_path: Path,
                                                                         capsys: pytest.CaptureFixture[str]) -> None:
    """With a model file that cannot load, the error is still the photo's or the folder's: they come first."""
    broken = tmp_path / "broken.safetensors"
    broken.write_bytes(b"not a model")
    good, missing = photo(tmp_path / "good.png", 40, 30), tmp_path / "missing.png"
    tiny = photo(tmp_path / "tiny.png", 4, 4)
    (tmp_path / "file").write_text("")
    for argv, word in (([good, missing], str(missing)), ([good, tiny], str(tiny)),
                       ([good, "--out", tmp_path / "file" / "sub"], "--out")):
        assert predict_cli.main([*map(str, argv), "--checkpoint", str(broken)]) == 2
        line = error_line(capsys)
        assert word in line and "broken" not in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.safetensors", "file", "good.png", "tiny.png"]


def test_an_empty_out_is_refused(shipped_model: Path, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    """``--out ""`` (an unset shell variable) would have written into the current folder."""
    img = photo(tmp_path / "x.png", 40, 30)
    work = tmp_path / "work"
    work.mkdir()
    monkeypatch.chdir(work)
    with pytest.raises(SystemExit) as e:
        predict_cli.main([str(img), "--checkpoint", str(shipped_model), "--out", ""])
    assert e.value.code == 2
    assert "--out" in error_line(capsys)
    assert not any(work.iterdir())


def test_help_is_instant_and_imports_nothing_heavy() -> None:
    code = ("import sys\nfrom fruxel.cli.predict import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n"
            "    pass\nheavy = [m for m in ('torch', 'warp', 'pyrender', 'PIL') if m in sys.modules]\nprint(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert "IMAGE" in out.stdout and out.stdout.strip().endswith("[]")


@pytest.mark.skipif(torch.cuda.is_available(), reason="this machine has a CUDA device")
def test_cuda_device_on_a_machine_without_one(shipped_model: Path, tmp_path: Path,
                                              capsys: pytest.CaptureFixture[str]) -> None:
    img = photo(tmp_path / "x.png", 40, 30)
    assert predict_cli.main([str(img), "--checkpoint", str(shipped_model), "--device", "cuda:0",
                             "--out", str(tmp_path / "o")]) == 2
    assert "--device cuda:0: no CUDA device here" in error_line(capsys)


def test_columns_of_the_padding_are_left_empty(shipped_model: Path, tmp_path: Path) -> None:
    """A wide photo padded to the grid's aspect (grey above and below): the rows of columns whose centre rays fall
    on the grey hold nothing; the rest are the model's own answer."""
    from fruxel.train.predict import frame_coverage

    image = photo(tmp_path / "wide.png", 200, 80)
    out = tmp_path / "out"
    assert predict_cli.main([str(image), "--checkpoint", str(shipped_model), "--out", str(out), "--fit", "pad",
                             "-q"]) == 0
    model = fruxel.load(out / "wide.npz")
    covered = frame_coverage((80, 200), model.grid, None, "pad")
    assert covered.any() and not covered.all() and not covered[0].any() and covered[model.grid.height // 2].all()
    assert not model.labels[:, ~covered].any()
    want = expected_logits(shipped_model, image, fit="pad").argmax(0)
    # The stored labels are the argmax of float16 logits: a near tie may fall the other way.
    assert ((model.labels[:, covered] != 0) != (want[:, covered] != 0)).mean() < 0.005
    assert want[:, ~covered].any(), "the model fills the padding when left to itself: the test would pass vacuously"

"""The photo commands' camera options (issue 39): ``--pitch``, ``--roll``, ``--height`` reach a model that reads the
camera; the field of view from ``--hfov``, ``--intrinsics`` or the photo's EXIF 35 mm focal length (absurd values
ignored with a warning); bad values give one error line naming the argument."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fruxel.cli import predict as predict_cli
from fruxel.cli import render as render_cli

from .conftest import small_model_config, widened_generator
from .test_predict import error_line, photo

torch = pytest.importorskip("torch")

from fruxel.train.predict import (  # noqa: E402
    FOCAL_35MM_BOUNDS,
    centre_intrinsics,
    exif_focal_35mm,
    hfov_from_focal_35mm,
)


def exif_jpeg(path: Path, focal: int | None, size: tuple[int, int] = (120, 80)) -> Path:
    """A JPEG with EXIF (through Pillow's own EXIF writer), ``FocalLengthIn35mmFilm`` = ``focal`` when given."""
    exif = Image.Exif()
    exif[0x010F] = "fruxel test camera"  # Make, so that the file has EXIF either way
    if focal is not None:
        exif.get_ifd(0x8769)[0xA405] = focal
    y, x = np.mgrid[0:size[1], 0:size[0]]
    img = np.stack([x * 2 % 256, y * 3 % 256, np.full_like(x, 90)], -1).astype(np.uint8)
    Image.fromarray(img).save(path, exif=exif)
    return path


def test_exif_focal_length_is_read_and_absurd_ones_ignored(tmp_path: Path) -> None:
    assert exif_focal_35mm(exif_jpeg(tmp_path / "f24.jpg", 24)) == (24.0, None)
    assert math.isclose(hfov_from_focal_35mm(24.0, 120, 80), math.degrees(2 * math.atan(36 / 48)))
    # Portrait: the long side spans 36 mm, the width two thirds of it.
    assert math.isclose(hfov_from_focal_35mm(24.0, 80, 120), math.degrees(2 * math.atan(24 / 48)))
    assert exif_focal_35mm(exif_jpeg(tmp_path / "none.jpg", None)) == (None, None)
    assert exif_focal_35mm(photo(tmp_path / "plain.png", 40, 30)) == (None, None)
    for bad in (2, 1000):
        focal, why = exif_focal_35mm(exif_jpeg(tmp_path / f"f{bad}.jpg", bad))
        assert focal is None and f"{bad} mm" in why and f"{FOCAL_35MM_BOUNDS[0]:g}-{FOCAL_35MM_BOUNDS[1]:g}" in why


def test_centre_intrinsics_crops_about_the_principal_point() -> None:
    img = np.zeros((100, 200, 3), dtype=np.uint8)
    img[:, 150] = 255
    out, hfov = centre_intrinsics(img, (100.0, 100.0, 150.0, 50.0))
    assert out.shape == (100, 100, 3) and out[:, 50].min() == 255  # the principal point's column in the middle
    assert math.isclose(hfov, 2 * math.degrees(math.atan(0.5)))
    stretched, _ = centre_intrinsics(img, (100.0, 50.0, 100.0, 50.0))
    assert stretched.shape[0] == 200  # rows stretched by fx / fy to square pixels
    with pytest.raises(ValueError, match="principal point"):
        centre_intrinsics(img, (100.0, 100.0, 250.0, 50.0))


@pytest.fixture(scope="module")
def camera_model(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A small model that reads the camera, as a shipped file."""
    from fruxel.train.model_files import save_model

    config = dataclasses.replace(small_model_config(), camera_inputs=True)
    path = tmp_path_factory.mktemp("cam") / "cam.safetensors"
    save_model(path, widened_generator(config), config, half=False)
    return path


def _logits(out: Path, name: str) -> np.ndarray:
    with np.load(out / f"{name}.logits.npz") as z:
        return z["logits"].astype(np.float32)


def test_predict_flags_reach_the_model(camera_model: Path, tmp_path: Path) -> None:
    jpg = exif_jpeg(tmp_path / "room.jpg", 28)
    runs = {}
    for name, flags in (("low", ["--pitch", "10", "--height", "1.0"]), ("high", ["--pitch", "10", "--height", "1.5"]),
                        ("unknown", []), ("again", ["--pitch", "10", "--height", "1.0"])):
        out = tmp_path / name
        assert predict_cli.main([str(jpg), "--checkpoint", str(camera_model), "--out", str(out), "--logits", "-q",
                                 "--device", "cpu", *flags]) == 0
        runs[name] = _logits(out, "room")
    assert np.array_equal(runs["low"], runs["again"])
    assert not np.allclose(runs["low"], runs["high"], atol=1e-3)
    assert not np.allclose(runs["low"], runs["unknown"], atol=1e-3)


def test_exif_field_of_view_is_used_unless_hfov_is_given(camera_model: Path, tmp_path: Path,
                                                         capsys: pytest.CaptureFixture[str]) -> None:
    jpg = exif_jpeg(tmp_path / "room.jpg", 20)
    hfov = f"{hfov_from_focal_35mm(20.0, 120, 80):.6f}"
    for name, flags in (("exif", []), ("given", ["--hfov", hfov]), ("grid", ["--hfov", "60"])):
        assert predict_cli.main([str(jpg), "--checkpoint", str(camera_model), "--out", str(tmp_path / name),
                                 "--logits", "-q", "--device", "cpu", *flags]) == 0
    exif, given, grid = (_logits(tmp_path / n, "room") for n in ("exif", "given", "grid"))
    np.testing.assert_allclose(exif, given, atol=1e-4)
    assert not np.allclose(exif, grid, atol=1e-3)
    absurd = exif_jpeg(tmp_path / "absurd.jpg", 1000)
    capsys.readouterr()
    assert predict_cli.main([str(absurd), "--checkpoint", str(camera_model), "--out", str(tmp_path / "a"), "-q",
                             "--device", "cpu"]) == 0
    warnings = [ln for ln in capsys.readouterr().err.splitlines() if "warning" in ln]
    assert len(warnings) == 1 and "1000 mm" in warnings[0] and warnings[0].startswith("fruxel-predict: warning:")


@pytest.mark.parametrize("flags, words", [
    (["--pitch", "95"], "--pitch"),
    (["--height", "-1", "--pitch", "5"], "--height"),
    (["--height", "1.2"], "--height"),
    (["--roll", "abc"], "--roll"),
    (["--intrinsics", "100,100,50"], "--intrinsics"),
    (["--intrinsics", "100,100,50,40", "--hfov", "60"], "--intrinsics"),
])
def test_bad_camera_values_give_one_error_line(camera_model: Path, tmp_path: Path, flags: list[str], words: str,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    jpg = exif_jpeg(tmp_path / "room.jpg", 28)
    try:
        rc = predict_cli.main([str(jpg), "--checkpoint", str(camera_model), "--out", str(tmp_path / "o"), *flags])
    except SystemExit as e:  # argparse's own usage errors
        rc = e.code
    assert rc == 2
    assert words in error_line(capsys)


def test_render_refuses_camera_options_without_a_photo(capsys: pytest.CaptureFixture[str]) -> None:
    assert render_cli.main(["--pitch", "10"]) == 2
    assert "--pitch" in error_line(capsys, "fruxel-render")


def test_eval_camera_known_parses() -> None:
    from fruxel.cli import eval as eval_cli

    parse = eval_cli.build_parser().parse_args
    assert parse(["--camera-known", "gravity,height"]).camera_known == [("gravity", "height")]
    assert parse(["--camera-known", "none"]).camera_known == [()]
    # Given again: one more setting, evaluated on the same samples.
    assert parse(["--camera-known", "gravity", "--camera-known", "none"]).camera_known == [("gravity",), ()]
    assert parse([]).camera_known is None  # what the test set records: both
    for bad in ("height", "pose", "gravity,size"):
        with pytest.raises(SystemExit):
            parse(["--camera-known", bad])


def test_camera_flags_for_a_model_that_reads_no_camera_say_so_in_one_line(shipped_model: Path, camera_model: Path,
                                                                           tmp_path: Path,
                                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """The shipped kind of model ignores --pitch and --height: one note says so, and the prediction is the plain one;
    a model that reads the camera gets no note."""
    jpg = exif_jpeg(tmp_path / "room.jpg", 28)
    outs = {}
    for name, model, flags in (("flags", shipped_model, ["--pitch", "12", "--height", "1.4"]),
                               ("plain", shipped_model, []), ("reads", camera_model, ["--pitch", "12"])):
        capsys.readouterr()
        outs[name] = tmp_path / name
        assert predict_cli.main([str(jpg), "--checkpoint", str(model), "--out", str(outs[name]), "--logits", "-q",
                                 "--device", "cpu", *flags]) == 0
        err = capsys.readouterr().err
        notes = [line for line in err.splitlines() if "reads no camera" in line]
        assert notes == ([f"{predict_cli.PROG}: note: this model reads no camera; --pitch, --height change nothing"]
                         if name == "flags" else [])
    assert np.array_equal(_logits(outs["flags"], "room"), _logits(outs["plain"], "room"))

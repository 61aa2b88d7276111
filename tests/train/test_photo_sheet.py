"""scripts/photo_sheet.py: photos beside what models read in them."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fruxel.data import PHOTO
from fruxel.train.eval.metrics import first_surface
from fruxel.train.predict import CameraPrior, load_image, load_predictor, prepare_image

from .conftest import load_script

ROOT = Path(__file__).resolve().parents[2]
CAMERA_TINY = ROOT / "tests" / "data" / "camera_tiny" / "model.safetensors"


def test_sheet_shows_each_models_own_view_of_each_photo(tmp_path: Path) -> None:
    """Two photos (a folder), two models, one told a camera: a row per photo and a legend strip below; each
    model's panel is its own-view labels in its class colours, as the model predicts them with that camera."""
    folder = tmp_path / "photos"
    folder.mkdir()
    Image.open(PHOTO).save(folder / "a.png")
    Image.open(PHOTO).transpose(Image.FLIP_LEFT_RIGHT).save(folder / "b.jpg")
    out = tmp_path / "sheet.png"
    size = 64
    load_script("photo_sheet").main([str(folder), "--model", "ssz64", "--model", str(CAMERA_TINY), "--pitch", "10",
                                     "--height", "1.0", "--size", str(size), "--out", str(out)])
    sheet = np.asarray(Image.open(out).convert("RGB"))
    assert sheet.shape == (2 * size + size // 2, 3 * size, 3)
    predictor = load_predictor(str(CAMERA_TINY), device="cpu", camera=CameraPrior(pitch=10.0, height=1.0))
    image = prepare_image(load_image(folder / "b.jpg"), predictor.config)
    (logits,) = predictor.predict([image])
    labels = first_surface(logits.argmax(0)[None])[0].numpy()
    want = np.asarray(predictor.config.classes.colours, dtype=np.uint8)[labels]
    want = np.asarray(Image.fromarray(want).resize((size, size), Image.NEAREST))
    panel = sheet[size:2 * size, 2 * size:3 * size]  # second photo, second model (no caption on that row)
    assert (panel == want).all(axis=-1).mean() > 0.99


def test_missing_photo_is_one_line(tmp_path: Path) -> None:
    with pytest.raises(SystemExit, match="no such photo"):
        load_script("photo_sheet").main([str(tmp_path / "none.jpg"), "--out", str(tmp_path / "x.png")])


def test_a_panel_too_small_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        load_script("photo_sheet").main([str(PHOTO), "--size", "-5", "--out", str(tmp_path / "x.png")])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--size must be at least 32" in err[0]
    assert not (tmp_path / "x.png").exists()

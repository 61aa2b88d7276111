"""Data folders of labelled photos (:mod:`fruxel.train.folder`): the simulator writes them (``fruxel-sim export``),
reading one back gives the simulator's samples, ``fruxel-train`` fine-tunes on one, and broken folders are one error
line naming the file.

Tiny settings: flat rooms from the robot's camera and from wider and narrower cameras, 16^3 grids, 32-pixel images.
"""

from __future__ import annotations

import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest

from fruxel.classes import DEFAULT_CLASSES
from fruxel.grid import FruxelGrid
from fruxel.train.folder import (
    DATASET_JSON,
    FolderError,
    check_folder,
    frame_photo,
    parse_camera,
    read_folder,
)
from fruxel.train.sim.cameras import CAMERA_KEYS, CameraConfig
from fruxel.train.sim.config import ImageConfig, SimConfig
from fruxel.train.sim.export import export_folder
from fruxel.train.sim.sample import SampleMaker

torch = pytest.importorskip("torch")

GRID = FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0)
CONFIG = SimConfig(grid=GRID, image=ImageConfig(size=32), samples_per_scene=2, world="flat", renderer="pyrender",
                   splits=(("train", 4), ("test", 2)))
"""Flat rooms from the robot's own camera: photos that are the network's image itself."""
SEED = 3
SIZE = (32, 32)
"""The model's image size, (height, width)."""
TRAIN: dict[str, Any] = {
    "preset": "tiny", "name": "folder-test",
    "model": {"grid": GRID.to_dict(), "classes": DEFAULT_CLASSES.to_dict(), "image_scale": 2, "levels": 3,
              "stem": 4, "encoder": [8, 8, 8], "encoder_blocks": [1, 1, 1], "encoder_expand": 2,
              "topdown": [8, 8, 8], "decoder": [4, 4, 4], "decoder_blocks": [1, 1, 1]},
    "data": {"world": "flat", "camera": "robot", "workers": 0, "eval_samples": 2, "frequency_samples": 2},
    "run": {"steps": 2, "batch_size": 2, "log_every": 1, "eval_every": 0, "checkpoint_every": 0,
            "tensorboard": False},
}
"""A config file of a 16^3 SSZ from 32^2 images with the default classes: the folder's grid and classes."""


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """CONFIG exported as a data folder."""
    out = tmp_path_factory.mktemp("folders") / "robot"
    export_folder(out, CONFIG, SEED, progress=False)
    return out


def _copy(folder: Path, tmp_path: Path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(folder, out)
    return out


def _model() -> Any:
    from fruxel.train.config import TrainConfig

    return TrainConfig.from_json(json.dumps(TRAIN)).model


# ---------------------------------------------------------------------------------------------- round trip
def _assert_same(folder: Path, config: SimConfig) -> None:
    """Every sample read back from ``folder`` is the simulator's: image, labels and camera."""
    fs = check_folder(folder, config.grid, config.classes.names)
    with SampleMaker(config, SEED) as maker:
        for split, n in config.splits:
            assert len(fs.splits[split]) == n
            for i in range(n):
                s, got = maker.make(split, i), fs.sample(split, i, (config.image_height, config.image_width))
                assert np.array_equal(got.image, s.image), (split, i)
                assert np.array_equal(got.labels, s.labels) and got.labels.dtype == np.uint8
                want = s.camera_arrays()
                assert sorted(got.camera) == sorted(CAMERA_KEYS) == sorted(want)
                for k in CAMERA_KEYS:
                    assert got.camera[k].dtype == want[k].dtype and got.camera[k].shape == np.shape(want[k]), k
                    if k == "coverage":
                        assert np.array_equal(got.camera[k], want[k])
                    else:
                        assert np.allclose(got.camera[k], want[k], rtol=0, atol=1e-9), (k, got.camera[k], want[k])


def test_export_reads_back_as_the_simulators_samples(folder: Path) -> None:
    d = json.loads((folder / DATASET_JSON).read_text())
    assert d["classes"] == list(DEFAULT_CLASSES.names) and d["grid"] == GRID.to_dict()
    assert d["splits"] == {"train": [f"train/{i:06d}" for i in range(4)], "test": ["test/000000", "test/000001"]}
    assert sorted(p.name for p in (folder / "test").iterdir()) == sorted(
        f"00000{i}.{s}" for i in range(2) for s in ("json", "npy", "png"))
    assert not [p for p in folder.parent.iterdir() if p.name.startswith(".")]  # no temporary folder left
    _assert_same(folder, CONFIG)


@pytest.mark.parametrize("hfov", [80.0, 40.0])
def test_framed_cameras_read_back_the_same(tmp_path: Path, hfov: float) -> None:
    from PIL import Image

    # A wider camera's photo is cropped to the grid's view, a narrower one's padded; the photo on disk is the
    # camera's own render, framed by the reader as the simulator frames it.
    config = CONFIG.replace(camera=CameraConfig(hfov=(hfov, hfov), pitch=(20.0, 20.0), roll=(5.0, 5.0)),
                            splits=(("train", 2),))
    export_folder(tmp_path / "f", config, SEED, progress=False)
    with SampleMaker(config, SEED) as maker:
        _, render = maker.make_with_render("train", 0)
    assert render.shape[1] != 32  # the photo is the camera's own, not the framed image
    assert np.array_equal(np.asarray(Image.open(tmp_path / "f/train/000000.png")), render)
    _assert_same(tmp_path / "f", config)


def test_the_batches_of_a_folder_are_the_streams(folder: Path) -> None:
    from fruxel.train.samples import BATCH_KEYS, SampleSource, split_size, training_batches

    model = _model()
    source = SampleSource("folder", str(folder))
    assert split_size(source, model, "train") == 4 and split_size(source, model, "test") == 2
    stream = SampleSource(camera="robot", world="flat", augment=False)
    got = next(training_batches(source, model, 4, batch=3, workers=1))
    want = next(training_batches(stream, model, 4, batch=3, workers=0))
    assert sorted(got) == sorted(want) == sorted(BATCH_KEYS)
    for k in ("image", "labels", "index"):
        assert got[k].dtype == want[k].dtype and got[k].shape == want[k].shape, k
    for k in CAMERA_KEYS:
        assert got["camera"][k].dtype == want["camera"][k].dtype, k
        assert got["camera"][k].shape == want["camera"][k].shape, k
    # Room order is shuffled per epoch for a folder, as for shards: the batch holds three of the four samples.
    assert len(set(got["index"].tolist())) == 3 and set(got["index"].tolist()) <= {0, 1, 2, 3}


# ---------------------------------------------------------------------------------------------- cameras
def test_unknown_camera_values_are_nan() -> None:
    cam = parse_camera({"intrinsics": [500.0, 500.0, 320.0, 240.0]}, (640, 480), "c.json")
    assert np.isnan(cam.pose).all() and np.isnan(cam.gravity).all() and math.isnan(cam.height)
    assert all(math.isnan(a) for a in cam.angles())
    cam = parse_camera({"intrinsics": [500, 500, 320, 240], "pitch": 20, "roll": -5, "height": 1.2}, (640, 480), "c")
    assert cam.angles() == pytest.approx((20.0, -5.0)) and cam.height == 1.2 and np.isnan(cam.pose).all()
    cam = parse_camera({"intrinsics": [500, 500, 320, 240], "gravity": [0, 2, 0]}, (640, 480), "c")
    assert np.allclose(cam.gravity, (0, 1, 0)) and cam.angles() == pytest.approx((0.0, 0.0))
    with pytest.raises(FolderError, match=r"^c.json: give at most one of pose, gravity, pitch and roll"):
        parse_camera({"intrinsics": [500, 500, 320, 240], "gravity": [0, 1, 0], "roll": 0}, (640, 480), "c.json")


def test_off_centre_principal_points_and_tall_pixels_are_framed_about_the_optical_centre(folder: Path) -> None:
    from PIL import Image

    photo = np.asarray(Image.open(folder / "train/000000.png"))
    fx, fy, cx, cy = json.loads((folder / "train/000000.json").read_text())["intrinsics"]
    want, cover, _ = frame_photo(photo, (fx, fy, cx, cy), GRID, SIZE)
    assert cover.all()
    # The same photo with 8 columns of noise on its right: the principal point is no longer in the middle.
    wide = np.concatenate([photo, np.random.default_rng(0).integers(0, 255, (32, 8, 3), dtype=np.uint8)], axis=1)
    got, cover, _ = frame_photo(wide, (fx, fy, cx, cy), GRID, SIZE)
    assert np.array_equal(got, want) and cover.all()
    # Rows stretched twice: fy = 2 fx.
    tall = np.repeat(photo, 2, axis=0)
    got, _, _ = frame_photo(tall, (fx, 2 * fy, cx, 2 * cy), GRID, SIZE)
    assert np.abs(got.astype(int) - want).mean() < 8


# ---------------------------------------------------------------------------------------------- training
def test_fruxel_train_fine_tunes_on_a_folder(folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]
                                             ) -> None:
    from fruxel.cli.train import main

    config = tmp_path / "c.json"
    config.write_text(json.dumps(TRAIN))
    assert main(["--config", str(config), "--data", str(folder), "--out", str(tmp_path / "run"), "-q"]) == 0
    assert {"last.pt", "model.safetensors", "metrics.csv"} <= {p.name for p in (tmp_path / "run").iterdir()}
    saved = json.loads((tmp_path / "run/config.json").read_text())
    assert saved["data"]["source"] == "folder" and saved["data"]["root"] == str(folder)
    assert capsys.readouterr().err == ""
    # The fine-tuned model calibrates on the folder too.
    from fruxel.cli.calibrate import main as calibrate

    out = tmp_path / "calibrated.safetensors"
    assert calibrate([str(tmp_path / "run/model.safetensors"), "--out", str(out), "--data", str(folder),
                      "--samples", "4", "--device", "cpu"]) == 0
    assert out.is_file() and "4 samples" in capsys.readouterr().out


def _error(tmp_path: Path, folder: Path, capsys: pytest.CaptureFixture[str]) -> str:
    from fruxel.cli.train import main

    config = tmp_path / "c.json"
    config.write_text(json.dumps(TRAIN))
    assert main(["--config", str(config), "--data", str(folder), "--out", str(tmp_path / "run"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fruxel-train: error: "), err
    assert not (tmp_path / "run").exists()
    return err[0]


def _labels(path: Path, value: Any) -> None:
    if isinstance(value, bytes):
        path.write_bytes(value)
    else:
        np.save(path, value, allow_pickle=True)


BROKEN = [
    ("train/000001.npy", None, "train/000001.npy: no such file"),
    ("train/000001.npy", np.zeros((8, 16, 16), np.uint8), "train/000001.npy: labels are uint8 (8, 16, 16)"),
    ("train/000001.npy", np.zeros((16, 16, 16), np.float32), "labels are float32"),
    ("train/000001.npy", np.array([{"a": 1}], dtype=object), "train/000001.npy: labels must be a C-ordered integer"),
    ("train/000001.npy", b"\x93NUMPY garbage", "train/000001.npy: not a .npy file"),
    ("train/000001.png", b"not a png", "train/000001.png: not a readable image"),
    ("train/000001.png", None, "train/000001.png: no such file (the sample's photo"),
    ("train/000001.json", b"{", "train/000001.json: not valid JSON"),
    ("train/000001.json", {"intrinsics": [-1, 27.7, 16, 16]}, "train/000001.json: intrinsics"),
    ("train/000001.json", {"intrinsics": [0.5, 0.5, 16, 16]}, "train/000001.json: fx 0.5 pixels gives"),
    ("train/000001.json", {"intrinsics": [27.7, 27.7, 40, 16]}, "principal point cx, cy inside the photo"),
    ("train/000001.json", {"intrinsics": [27.7, 27.7, 16, 16], "pitch": 10}, "give pitch and roll together"),
    ("train/000001.json", {"intrinsics": [27.7, 27.7, 16, 16], "pose": np.diag([2, 1, 1, 1]).tolist()},
     "pose is not a rigid transform"),
    ("train/000001.json", {"intrinsics": [27.7, 27.7, 16, 16], "focal": 3}, "unexpected ['focal']"),
    (DATASET_JSON, {"classes": ["empty", "wall"]}, "dataset.json: classes ['empty', 'wall'] are not the model's"),
    (DATASET_JSON, {"grid": {**GRID.to_dict(), "depth": 32}},
     "dataset.json: grid 16x16x32 z 0.5..8 m hfov 60 is not the model's"),
    (DATASET_JSON, {"version": 2}, "dataset.json: format version 2; this fruxel reads version 1"),
    (DATASET_JSON, {"format": "coco"}, "dataset.json: not a fruxel data folder description"),
    (DATASET_JSON, {"splits": {"train": ["../x"]}}, "dataset.json: sample '../x' of split 'train' is not a path"),
    (DATASET_JSON, {"splits": {"test": "test"}}, ": the data folder has no split 'train'"),
    (DATASET_JSON, {"splits": {"train": "train"}}, ": the data folder has no split 'test' (its splits: train)"),
    (DATASET_JSON, {"splits": {"train": "nowhere"}}, "/nowhere: no such folder"),
]


@pytest.mark.parametrize("name, content, words", BROKEN, ids=[w[:30] for _, _, w in BROKEN])
def test_broken_folders_give_one_line_naming_the_file(folder: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                      name: str, content: Any, words: str) -> None:
    out = _copy(folder, tmp_path)
    path = out / name
    if content is None:
        path.unlink()
    elif name.endswith(".npy"):
        _labels(path, content)
    elif isinstance(content, bytes):
        path.write_bytes(content)
    elif name == DATASET_JSON:
        path.write_text(json.dumps({**json.loads(path.read_text()), **content}))
    else:
        path.write_text(json.dumps(content))
    line = _error(tmp_path, out, capsys)
    assert f"{out}/" in line or f"{out}:" in line, line
    assert words in line, line


def test_labels_outside_the_class_table_stop_training_with_one_line(folder: Path, tmp_path: Path,
                                                                    capsys: pytest.CaptureFixture[str]) -> None:
    # Label values are checked when a sample is read (the check before training reads headers only).
    out = _copy(folder, tmp_path)
    bad = np.load(out / "train/000002.npy")
    bad[0, 0, 0] = 7
    np.save(out / "train/000002.npy", bad)
    from fruxel.cli.train import main

    config = tmp_path / "c.json"
    config.write_text(json.dumps(TRAIN))
    assert main(["--config", str(config), "--data", str(out), "--out", str(tmp_path / "run"), "-q"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{out}/train/000002.npy: labels 0 to 7 lie outside the 7 classes" in err[0], err


def test_subfolder_splits(folder: Path, tmp_path: Path) -> None:
    out = _copy(folder, tmp_path)
    d = json.loads((out / DATASET_JSON).read_text())
    (out / DATASET_JSON).write_text(json.dumps({**d, "splits": {"train": "train", "test": "test/"}}))
    fs = read_folder(out)
    assert fs.splits == {"train": tuple(f"train/{i:06d}" for i in range(4)), "test": ("test/000000", "test/000001")}


# ---------------------------------------------------------------------------------------------- export
def test_export_refuses_an_existing_folder_unless_overwrite(folder: Path, tmp_path: Path,
                                                            capsys: pytest.CaptureFixture[str]) -> None:
    from fruxel.cli.sim import main

    out = _copy(folder, tmp_path)
    argv = ["export", "--out", str(out), "--split", "train=2", "--grid", "16", "--image", "32", "--world", "flat",
            "--camera", "robot", "-q"]
    assert main(argv) == 2
    assert f"{out}: already exists (pass --overwrite to replace it)" in capsys.readouterr().err
    assert main([*argv, "--overwrite"]) == 0
    assert read_folder(out).splits == {"train": ("train/000000", "train/000001")}
    assert not (out / "test").exists() and sorted(p.name for p in tmp_path.iterdir()) == ["copy"]
    other = tmp_path / "other"
    other.mkdir()
    (other / "keep.txt").write_text("mine")
    assert main(["export", "--out", str(other), *argv[3:], "--overwrite"]) == 2
    assert "not a data folder" in capsys.readouterr().err and (other / "keep.txt").read_text() == "mine"

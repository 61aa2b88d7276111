"""The ``fruxel-sim`` command line: help, generate, errors, preview."""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from PIL import Image

from fruxel.classes import DEFAULT_CLASSES, HOME_CLASSES
from fruxel.cli.sim import main

TINY = ["--image", "32", "--grid", "16", "--samples-per-scene", "2"]
FLAT = ["--world", "flat", "--camera", "robot"]
"""The first data sets' style: flat-coloured rooms from the robot's mount, drawn by pyrender (fast, and no pack)."""


def test_help_is_instant_and_lists_the_commands() -> None:
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "fruxel.cli.sim", "--help"], capture_output=True, text=True,
                         check=True)
    assert "generate" in out.stdout and "preview" in out.stdout
    # No torch, pyrender or warp behind --help (a loaded 2-core machine still starts Python in ~1 s).
    assert time.perf_counter() - t < 10
    probe = ("import sys, fruxel.cli.sim; "
             "print(sorted(m for m in ('torch', 'pyrender', 'warp') if m in sys.modules))")
    mods = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert mods.stdout.strip() == "[]"
    with pytest.raises(SystemExit) as e:
        main(["generate", "--help"])
    assert e.value.code == 0


def test_generate_and_resume(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "ds"
    args = ["generate", "--out", str(out), "--samples", "5", "--shard-size", "2", "--seed", "3", "-q", *FLAT, *TINY]
    assert main(args) == 0
    m = json.loads((out / "manifest.json").read_text())
    assert m["complete"] and {k: v["samples"] for k, v in m["splits"].items()} == {"train": 4, "test": 1}
    assert m["image"] == {"width": 32, "height": 32} and m["grid"]["width"] == 16 and m["seed"] == 3
    stamps = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
    assert len(stamps) == 3
    assert main(args) == 0
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == stamps
    capsys.readouterr()
    # Another grid in the same folder is refused with one line naming the manifest.
    assert main([*args[:-len(TINY)], "--image", "32", "--grid", "8", "--samples-per-scene", "2"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "manifest.json" in err[0] and "other settings" in err[0]
    # A corrupt shard is refused the same way.
    shard = out / "train-00001.npz"
    shard.write_bytes(shard.read_bytes()[:100])
    assert main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and str(shard) in err[0] and "SHA-256" in err[0]


@pytest.mark.parametrize("extra, words", [
    (["--split", "train=3,test"], "NAME=SAMPLES"),
    (["--split", "train=3,test=1", "--samples", "5"], "does not match"),
    (["--grid", "16x12x16", "--image", "10"], "multiple of the grid width"),
    (["--z-near", "9"], "z_far must be > z_near"),
])
def test_bad_arguments_exit_2_with_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str],
                                            words: str) -> None:
    assert main(["generate", "--out", str(tmp_path / "x"), "-q", *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fruxel-sim: error:") and words in err[0]


@pytest.mark.parametrize("argv", [["generate"], ["generate", "--out", "x", "--image", "0"], ["nope"], [],
                                  ["generate", "--out", "x", "--renderer", "nope"]])
def test_argparse_errors_are_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(argv)
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and err[0].startswith("fruxel-sim") and "error:" in err[0]


def test_output_that_is_a_file_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    f = tmp_path / "file"
    f.write_text("x")
    assert main(["generate", "--out", str(f), "--samples", "2", "-q", *FLAT, *TINY]) == 2
    assert "not a folder" in capsys.readouterr().err


@pytest.mark.parametrize("argv", [["generate", "--samples", "2"], ["preview"]])
def test_an_empty_out_is_refused(argv: list[str], tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                 capsys: pytest.CaptureFixture[str]) -> None:
    """``--out ""`` would have been the current folder."""
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        main([*argv, "--out", ""])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and err[0].startswith("fruxel-sim") and "--out" in err[0]
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("command", ["generate", "preview"])
def test_an_output_under_a_file_is_refused_before_any_sample(command: str, tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "file").write_text("x")
    out = tmp_path / "file" / ("data" if command == "generate" else "sheet.png")
    extra = ["--samples", "2", "-q", *TINY] if command == "generate" else ["--image", "32", "--grid", "16"]
    extra += FLAT
    assert main([command, "--out", str(out), *extra]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--out" in err[0] and "is a file, not a folder" in err[0], err
    assert sorted(p.name for p in tmp_path.iterdir()) == ["file"]


def test_preview_writes_a_contact_sheet(tmp_path: Path) -> None:
    png = tmp_path / "sheet.png"
    assert main(["preview", "--out", str(png), "--seed", "1", "--count", "2", "--image", "64", "--grid", "32",
                 *FLAT]) == 0
    img = np.asarray(Image.open(png).convert("RGB"))
    assert img.shape[0] > 2 * 64 and img.shape[1] >= 3 * 64
    flat = img.reshape(-1, 3)
    palette = DEFAULT_CLASSES.palette()
    counts = {name: int((flat == palette[c]).all(axis=1).sum()) for c, name in enumerate(DEFAULT_CLASSES.names)}
    # Own-view label panels are drawn in the exact class colours: every room has walls and a floor in view.
    assert counts["wall"] > 100 and counts["floor"] > 100, counts
    # The ray-cast panel shades the same colours with light: darker versions of wall and floor appear as well.
    shaded = np.unique(flat, axis=0)
    assert len(shaded) > 200


def test_preview_writes_the_format_its_name_asks_for(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--out x.jpg is a JPEG (it used to hold PNG bytes); a suffix that is no image format is refused before any
    sample is made, in one line."""
    jpg = tmp_path / "sub" / "sheet.jpg"
    assert main(["preview", "--out", str(jpg), "--image", "32", "--grid", "16", "--samples-per-scene", "2",
                 *FLAT]) == 0
    with Image.open(jpg) as im:
        assert im.format == "JPEG"
    assert sorted(p.name for p in jpg.parent.iterdir()) == ["sheet.jpg"]
    capsys.readouterr()
    t = time.perf_counter()
    assert main(["preview", "--out", str(tmp_path / "sheet.xyz"), "--image", "32", "--grid", "16", *FLAT]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "sheet.xyz" in err[0] and ".png" in err[0]
    assert time.perf_counter() - t < 5 and not (tmp_path / "sheet.xyz").exists()


def test_preview_shows_a_test_set(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--test-set robot: the robot's mount in the flat world, labelled with the furnished rooms' classes (the set's
    samples as fruxel-eval makes them for a camera-aware model), --step rooms apart; an unknown set is one line."""
    from fruxel.train.sim.config import ImageConfig, SimConfig
    from fruxel.train.sim.images import preview_sheet
    from fruxel.train.sim.sample import SampleMaker
    from fruxel.train.sim.testsets import TEST_SETS

    png = tmp_path / "robot.png"
    assert main(["preview", "--out", str(png), "--test-set", "robot", "--count", "2", "--step", "2",
                 "--samples-per-scene", "2", "--image", "48", "--grid", "24"]) == 0
    flat = np.asarray(Image.open(png).convert("RGB")).reshape(-1, 3)
    assert (flat == HOME_CLASSES.palette()[HOME_CLASSES.names.index("wall")]).all(axis=1).sum() > 50
    config = TEST_SETS["robot"].config(SimConfig(image=ImageConfig(size=48), classes=HOME_CLASSES,
                                                 samples_per_scene=2, splits=(("test", 4),)))
    with SampleMaker(config, 0) as maker:
        sheet, made = preview_sheet(maker, config, "test", range(0, 4, 2), 0)
    assert [s.index for s in made] == [0, 2] and made[0].scene != made[1].scene
    assert all(abs(s.camera.height - 1.0) < 1e-6 and abs(s.camera.pitch - 10.0) < 1e-6 for s in made)
    assert sheet.ndim == 3 and sheet.shape[0] > 2 * 48
    capsys.readouterr()
    with pytest.raises(SystemExit) as stop:
        main(["preview", "--out", str(tmp_path / "x.png"), "--test-set", "nope"])
    assert stop.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "--test-set" in err[0] and "any-camera" in err[0]


def test_contact_sheet_titles_fit_their_panels() -> None:
    """Panel titles wrap within their panel: at small sizes they used to run into the next panel's title."""
    from fruxel.train.sim.images import contact_sheet

    black = np.zeros((40, 40, 3), np.uint8)
    panels = {"camera image": black, "ground truth, own view": black, "ground truth, second pose": black}
    sheet = contact_sheet([panels], DEFAULT_CLASSES.names, DEFAULT_CLASSES.palette(), ["sample 0"])
    pad = 8
    # Rows from below the sample title to the top of the panels hold only the panel titles; the gaps between
    # panel columns stay white there.
    dark = np.all(sheet == 0, axis=-1)
    top = int(np.flatnonzero(dark.sum(axis=1) >= 3 * 40)[0])
    band = sheet[pad + 18:top]
    assert band.shape[0] >= 2 * 18, "the long titles take more than one line"
    for gap in (pad + 40, pad + 40 + pad + 40):
        assert np.all(band[:, gap:gap + pad] == 255)


def test_camera_option(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``--camera robot`` makes data sets and sheets of the robot's own mount, which records nothing (configs as
    before cameras varied); ``--camera any``, the default, records its ranges."""
    robot, anyc = tmp_path / "robot", tmp_path / "any"
    assert main(["generate", "--out", str(robot), "--samples", "2", "-q", *FLAT, *TINY]) == 0
    assert main(["generate", "--out", str(anyc), "--samples", "2", "-q", "--world", "flat", *TINY]) == 0
    assert "camera" not in json.loads((robot / "manifest.json").read_text())["config"]
    m = json.loads((anyc / "manifest.json").read_text())
    assert m["version"] == 3 and m["config"]["camera"] == {"height": [0.3, 1.9], "pitch": [-20.0, 40.0],
                                                           "roll": [-10.0, 10.0], "hfov": [50.0, 80.0],
                                                           "aim": 120.0}
    png = tmp_path / "sheet.png"
    assert main(["preview", "--out", str(png), "--world", "flat", "--count", "2", *TINY]) == 0
    assert Image.open(png).size[0] >= 3 * 32
    capsys.readouterr()
    with pytest.raises(SystemExit) as e:
        main(["preview", "--out", str(png), "--camera", "phone"])
    err = capsys.readouterr().err.strip().splitlines()
    assert e.value.code == 2 and len(err) == 1 and "--camera" in err[0]


@pytest.mark.slow
def test_the_furnished_rooms_are_the_same_bytes_and_resume(tiny_pack: Path, tmp_path: Path) -> None:
    """The default world (furnished rooms from any camera, ray-traced): the same seed gives the same shard bytes in
    one process and in two, and a shard lost from a finished folder is made again, byte for byte."""
    args = ["--split", "train=4,test=2", "--shard-size", "2", "--seed", "5", "-q", "--assets", str(tiny_pack), *TINY]
    one, two = tmp_path / "one", tmp_path / "two"
    assert main(["generate", "--out", str(one), *args]) == 0
    assert main(["generate", "--out", str(two), "--workers", "2", *args]) == 0
    shards = sorted(p.name for p in one.glob("*.npz"))
    assert len(shards) == 3 and sorted(p.name for p in two.glob("*.npz")) == shards
    assert all((one / n).read_bytes() == (two / n).read_bytes() for n in shards)
    lost = two / shards[-1]
    lost.unlink()
    assert main(["generate", "--out", str(two), *args]) == 0
    assert lost.read_bytes() == (one / shards[-1]).read_bytes()
    assert json.loads((two / "manifest.json").read_text())["complete"]


def test_the_old_style_records_what_data_sets_made_before_recorded(tmp_path: Path) -> None:
    """``--world flat --camera robot``: the flat world drawn by pyrender with the default classes, a config with no
    world, camera or renderer in it (the digest of data sets made before the furnished rooms)."""
    out = tmp_path / "ds"
    assert main(["generate", "--out", str(out), "--samples", "2", "-q", *FLAT, *TINY]) == 0
    config = json.loads((out / "manifest.json").read_text())["config"]
    assert not {"world", "camera", "renderer", "home", "assets", "raytrace"} & set(config)
    assert config["classes"] == DEFAULT_CLASSES.to_dict()


def _class_ids(folder: Path) -> set[int]:
    """The label values of a data set's shards (read without pickle)."""
    ids: set[int] = set()
    for shard in folder.glob("*.npz"):
        with np.load(shard, allow_pickle=False) as z:
            for key in (k for k in z.files if k.startswith("labels_")):
                ids |= set(np.unique(z[key]).tolist())
    return ids


def test_the_furnished_rooms_from_any_camera_are_the_default(tiny_pack: Path, tmp_path: Path) -> None:
    """Without --world and --camera: the home world's rooms from the pack --assets names, from any camera, drawn by
    the ray tracer, labelled with the home classes (the ceiling and object among the labels); the preview's label
    panels are drawn in the home classes' colours."""
    out = tmp_path / "ds"
    assert main(["generate", "--out", str(out), "--samples", "4", "-q", "--assets", str(tiny_pack), *TINY]) == 0
    config = json.loads((out / "manifest.json").read_text())["config"]
    assert config["world"] == "home" and config["renderer"] == "raytrace" and config["assets"] == str(tiny_pack)
    assert config["camera"]["hfov"] == [50.0, 80.0] and config["classes"] == HOME_CLASSES.to_dict()
    ids = _class_ids(out)
    names = HOME_CLASSES.names
    assert {names.index("wall"), names.index("floor")} <= ids and names.index("object") in ids, ids
    # --renderer names another than the world's own.
    other = tmp_path / "pyrender"
    assert main(["generate", "--out", str(other), "--samples", "2", "-q", "--assets", str(tiny_pack),
                 "--renderer", "pyrender", *TINY]) == 0
    config = json.loads((other / "manifest.json").read_text())["config"]
    assert config["world"] == "home" and "renderer" not in config  # pyrender: the default of SimConfig
    png = tmp_path / "sheet.png"
    assert main(["preview", "--out", str(png), "--assets", str(tiny_pack), "--image", "48", "--grid", "24"]) == 0
    flat = np.asarray(Image.open(png).convert("RGB")).reshape(-1, 3)
    palette = HOME_CLASSES.palette()
    counts = {n: int((flat == palette[c]).all(axis=1).sum()) for c, n in enumerate(names)}
    assert counts["wall"] > 50 and counts["floor"] > 50, counts


@pytest.mark.parametrize("command", ["generate", "preview"])
def test_a_missing_asset_pack_is_one_line_before_anything_is_made(command: str, tmp_path: Path,
                                                                  monkeypatch: pytest.MonkeyPatch,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """The home world without its pack: one line naming the folder and ``make assets``, before any sample is made
    and before the output folder is made; from --assets or from $FRUXEL_ASSETS alike."""
    out = tmp_path / "new" / ("ds" if command == "generate" else "sheet.png")
    extra = ["--samples", "2", "-q"] if command == "generate" else []
    t = time.perf_counter()
    assert main([command, "--out", str(out), "--assets", str(tmp_path / "nowhere"), *extra, *TINY]) == 2
    monkeypatch.setenv("FRUXEL_ASSETS", str(tmp_path / "elsewhere"))
    assert main([command, "--out", str(out), *extra, *TINY]) == 2
    assert time.perf_counter() - t < 5
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 2 and all(e.startswith("fruxel-sim: error:") and "`make assets`" in e for e in err), err
    assert "nowhere: no asset pack there (--assets)" in err[0]
    assert "elsewhere: no asset pack there ($FRUXEL_ASSETS)" in err[1]
    assert sorted(p.name for p in tmp_path.iterdir()) == []

"""Tests of ``fruxel-eval``: end to end on streamed samples and on a data set, each number of report.json checked
against counts made here from the same samples; bad model files, data sets and options give one error line."""

from __future__ import annotations

import hashlib
import json
import shutil
import subprocess
import sys
from pathlib import Path
from typing import Any

import numpy as np
import pytest
from PIL import Image

from fruxel.cli import eval as eval_cli

from .conftest import SMALL_GRID
from .test_predict import BAD_MODELS, bad_model_file, error_line

torch = pytest.importorskip("torch")

from fruxel.train.eval.evaluate import count_views, novel_cameras  # noqa: E402 - needs torch
from fruxel.train.eval.metrics import Accumulator  # noqa: E402
from fruxel.train.eval.report import rules_text  # noqa: E402
from fruxel.train.model_files import load_model  # noqa: E402
from fruxel.train.sim.config import AugmentConfig, ImageConfig, SimConfig  # noqa: E402
from fruxel.train.sim.sample import SampleMaker  # noqa: E402
from fruxel.train.sim.testsets import TEST_SETS  # noqa: E402
from fruxel.train.sim.writer import generate  # noqa: E402

BATCH = 2


def streamed(split: str, count: int, seed: int = 0, test_set: str = "", **changes: Any) -> list[Any]:
    """The first ``count`` samples of a split of the stream the command makes for the small model (``changes``: of
    its config, e.g. its classes; ``test_set``: a held-out test set's stream made from that config)."""
    config = SimConfig(grid=SMALL_GRID, image=ImageConfig(size=64, augment=AugmentConfig(enabled=True)),
                       samples_per_scene=16, splits=((split, count),), **changes)
    if test_set:
        config = TEST_SETS[test_set].config(config)
    with SampleMaker(config, seed, backend="warp", device="cpu") as maker:
        return [maker.make(split, i) for i in range(count)]


def expected(model: Path, tests: list[Any], train_labels: list[np.ndarray] | None) -> dict[str, Accumulator]:
    """Counts of the model and the baselines made here: the model in batches of BATCH, the prior as a one-hot
    count, the oracle as each column's first occupied cell (no kernel), novel views through ``first_hit``."""
    loaded = load_model(model)
    gen, config = loaded.network, loaded.config
    rules: dict[str, list[torch.Tensor]] = {"model": [], "prior": [], "oracle": []}
    labels = torch.from_numpy(np.stack([s.labels for s in tests]))
    for i in range(0, len(tests), BATCH):
        img = torch.from_numpy(np.stack([s.image for s in tests[i:i + BATCH]])).permute(0, 3, 1, 2).float() / 255.0
        with torch.no_grad():
            rules["model"].append(gen(img).logits.argmax(1).to(torch.uint8))
    if train_labels is not None:
        onehot = np.stack(train_labels)[..., None] == np.arange(len(config.classes.names))
        mode = torch.from_numpy(onehot.sum(0).argmax(-1).astype(np.uint8))
        rules["prior"] = [mode.expand(len(tests), *mode.shape)]
    else:
        del rules["prior"]
    occupied = labels != 0
    first = occupied.to(torch.uint8).argmax(1, keepdim=True)
    rules["oracle"] = [labels * (torch.zeros_like(occupied).scatter_(1, first, True) & occupied)]
    accs = {}
    for name, parts in rules.items():
        pred = torch.cat(parts)
        acc = Accumulator(len(config.classes.names))
        acc.add_volumes(pred, labels)
        count_views(acc, pred, labels, config.grid, novel_cameras(config.grid))
        accs[name] = acc
    return accs


def check_report(out: Path, accs: dict[str, Accumulator], samples: int, examples: int) -> dict[str, Any]:
    report = json.loads((out / "report.json").read_text())
    assert list(report["results"]) == list(accs)
    names = tuple(report["classes"]["names"])
    for name, acc in accs.items():
        got = report["results"][name]
        assert got["confusion"] == acc.conf.tolist(), name
        want = acc.summary(names)
        assert got["samples"] == want["samples"] == samples
        for key in ("miou", "completion_iou", "own_view_accuracy", "novel_view_accuracy", "depth_error"):
            assert got[key] == pytest.approx(want[key], rel=1e-6), (name, key)
        # A class in neither the truth nor the prediction has no IoU (None in both).
        assert got["iou"].keys() == want["iou"].keys()
        for c, value in want["iou"].items():
            assert got["iou"][c] == (None if value is None else pytest.approx(value, rel=1e-6, nan_ok=True)), (name, c)
        assert got["counts"]["novel_pixels"] == acc.novel_pixels and got["counts"]["own_hits"] == acc.own_hits
    assert report["results"]["oracle"]["own_view_accuracy"] == 100.0
    assert sum(map(sum, report["results"]["model"]["confusion"])) == samples * int(np.prod(SMALL_GRID.shape))
    md = (out / "report.md").read_text()
    for name in accs:
        miou = report["results"][name]["miou"]
        assert f"{miou:.1f}" in md.split("## Metrics")[1].splitlines()[4]
    assert report["command"] in md and "## IoU per class (%)" in md and "![examples](examples.png)" in md
    rules = report["model"]["inference_rules"]
    assert set(rules) == {"fill_columns", "empty_offset", "fill_threshold", "first_hit_label", "flip_average"}
    assert f"inference rules: {rules_text(rules)}" in md
    sheet = np.asarray(Image.open(out / "examples.png").convert("RGB"))
    # Five 192-pixel tiles and the legend column per row, one row per example under two lines of text.
    assert sheet.shape == (36 + examples * 192, 5 * 192 + 130, 3)
    for r in range(examples):
        row = sheet[36 + r * 192:36 + (r + 1) * 192, :5 * 192]
        for t in range(5):
            assert np.ptp(row[:, t * 192:(t + 1) * 192]) > 0, f"tile {t} of example {r} is blank"
    return report


@pytest.mark.slow
def test_streamed_samples_end_to_end(shipped_model: Path, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "report"
    argv = ["--checkpoint", str(shipped_model), "--samples", "5", "--prior-samples", "6", "--batch", str(BATCH),
            "--out", str(out), "--examples", "3", "--device", "cpu"]
    assert eval_cli.main(argv) == 0
    printed = capsys.readouterr().out.splitlines()
    assert printed[1:] == [str(out / n) for n in ("report.md", "report.json", "examples.png")]
    assert "mIoU model" in printed[0] and "per-cell prior" in printed[0]
    accs = expected(shipped_model, streamed("test", 5), [s.labels for s in streamed("train", 6)])
    report = check_report(out, accs, 5, 3)
    assert report["prior"] == {"split": "train", "samples": 6}
    assert report["data"]["kind"] == "stream" and report["data"]["seed"] == 0 and report["data"]["samples"] == 5
    assert report["data"]["pack"] is None  # the flat world reads no asset pack
    assert report["command"] == "fruxel-eval " + " ".join(argv)
    assert report["model"]["file"] == str(shipped_model) and report["model"]["training"] == {"step": 0,
                                                                                             "note": "fresh"}
    # The model is not the oracle: the test would not notice swapped rules otherwise.
    assert report["results"]["model"]["confusion"] != report["results"]["oracle"]["confusion"]


def test_the_prior_is_cached_by_what_makes_it(shipped_model: Path, tmp_path: Path, cache_folder: Path) -> None:
    """The per-cell prior (minutes of simulation on a CPU) is kept in the cache, keyed by what makes it, and read
    back: an entry changed by hand shows in the next report, other samples or seeds get entries of their own, and
    a damaged entry is counted again and replaced."""
    import fruxel

    def evaluate(name: str, *extra: str) -> dict[str, Any]:
        argv = ["--checkpoint", str(shipped_model), "--samples", "2", "--prior-samples", "3", "--batch", str(BATCH),
                "--examples", "0", "--device", "cpu", "--out", str(tmp_path / name), "-q", *extra]
        assert eval_cli.main(argv) == 0
        return json.loads((tmp_path / name / "report.json").read_text())

    def entries() -> list[Path]:
        return sorted((cache_folder / "prior").rglob("*.npz"))

    first = evaluate("first")
    (entry,) = entries()
    cached = fruxel.load(entry)
    config = load_model(shipped_model).config
    train = np.stack([s.labels for s in streamed("train", 3)])
    mode = (train[..., None] == np.arange(len(config.classes.names))).sum(0).argmax(-1)
    np.testing.assert_array_equal(cached.labels, mode)
    assert cached.grid == config.grid and cached.classes == config.classes
    # Read back, not counted again: a prior of walls everywhere predicts class 1 in every cell.
    fruxel.save(entry, fruxel.FruxelModel(np.ones_like(mode, dtype=np.uint8), config.grid, config.classes))
    conf = np.array(evaluate("walls")["results"]["prior"]["confusion"])
    assert conf[:, 1].sum() == conf.sum() > 0
    assert evaluate("walls-again")["results"]["model"] == first["results"]["model"]
    # Another number of samples, another seed: other priors, other entries.
    evaluate("four", "--prior-samples", "4")
    evaluate("seed", "--seed", "1")
    assert len(entries()) == 3
    # A damaged entry is no error: the prior is counted again and the entry replaced.
    entry.write_bytes(b"damaged")
    assert evaluate("again")["results"]["prior"] == first["results"]["prior"]
    np.testing.assert_array_equal(fruxel.load(entry).labels, mode)
    assert [p.name for p in entry.parent.iterdir() if p.suffix != ".npz"] == [], "temporary files left behind"


def test_streamed_test_samples_are_cached_by_what_makes_them(shipped_model: Path, tmp_path: Path, cache_folder: Path,
                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    """The streamed samples an evaluation reads are kept in the cache and read back by the next evaluation of the
    same samples, which then simulates nothing and reports the same numbers; other samples get entries of their
    own, and a damaged entry is streamed again and replaced."""
    import fruxel.train.samples as samples

    def evaluate(name: str, *extra: str) -> dict[str, Any]:
        argv = ["--checkpoint", str(shipped_model), "--samples", "3", "--prior-samples", "0", "--batch", "2",
                "--examples", "0", "--device", "cpu", "--out", str(tmp_path / name), "-q", *extra]
        assert eval_cli.main(argv) == 0
        return json.loads((tmp_path / name / "report.json").read_text())

    def entries() -> list[Path]:
        return sorted((cache_folder / "samples").glob("*.npz"))

    first = evaluate("first")
    (entry,) = entries()
    with np.load(entry, allow_pickle=False) as f:
        np.testing.assert_array_equal(f["labels"], np.stack([s.labels for s in streamed("test", 3)]))
    stream = samples.split_batches
    with monkeypatch.context() as m:
        m.setattr(samples, "split_batches", lambda *a, **k: pytest.fail("streamed again"))
        again = evaluate("again")
    assert again["results"] == first["results"]
    # With the camera's bins the same entry serves: the camera records are kept whoever reads them.
    with monkeypatch.context() as m:
        m.setattr(samples, "split_batches", lambda *a, **k: pytest.fail("streamed again"))
        assert evaluate("bins", "--by-camera")["results"]["model"] == first["results"]["model"]
    assert samples.split_batches is stream
    evaluate("seed", "--seed", "1")
    evaluate("four", "--samples", "4")
    assert len(entries()) == 3
    entry.write_bytes(b"damaged")
    assert evaluate("damaged")["results"] == first["results"]
    with np.load(entry, allow_pickle=False) as f:
        assert f["images"].shape[0] == 3
    assert [p.name for p in entry.parent.iterdir() if p.suffix != ".npz"] == [], "temporary files left behind"


def test_the_robot_test_set_is_the_stream_of_earlier_reports(shipped_model: Path, tmp_path: Path,
                                                              cache_folder: Path) -> None:
    """``--test-set robot`` evaluates the samples (and counts the prior of) the model's own stream of the flat world
    from the robot's mount, as before test sets had names; the report names the set and says what it is."""
    def evaluate(name: str, *extra: str) -> dict[str, Any]:
        argv = ["--checkpoint", str(shipped_model), "--samples", "2", "--prior-samples", "2", "--batch", str(BATCH),
                "--examples", "0", "--device", "cpu", "--out", str(tmp_path / name), "-q", *extra]
        assert eval_cli.main(argv) == 0
        return json.loads((tmp_path / name / "report.json").read_text())

    plain, robot = evaluate("plain"), evaluate("robot", "--test-set", "robot")
    assert robot["results"] == plain["results"] and len(list((cache_folder / "prior").rglob("*.npz"))) == 1
    assert plain["data"]["test_set"] is None and "test set" not in (tmp_path / "plain" / "report.md").read_text()
    description = TEST_SETS["robot"].description
    assert robot["data"]["test_set"] == {"name": "robot", "description": description}
    assert "test set robot" in robot["data"]["source"]
    assert f"| test set | `robot`: {description} |" in (tmp_path / "robot" / "report.md").read_text()


def test_a_room_world_test_set_is_evaluated_and_its_prior_keyed_by_it(home_model: Path, tiny_pack: Path,
                                                                       tmp_path: Path, cache_folder: Path) -> None:
    """``--test-set any-camera-test-assets`` evaluates the furnished rooms of the held-out assets from any camera,
    drawn by the ray tracer from the pack --assets names: every number of the report is the count made here from
    that set's samples, and the per-cell prior is counted on (and cached under) that set's training split, not the
    model's own stream's."""
    from fruxel.classes import HOME_CLASSES
    from fruxel.cli.eval import prior_cache_path
    from fruxel.train.samples import SampleSource

    out = tmp_path / "report"
    name = "any-camera-test-assets"
    assert eval_cli.main(["--checkpoint", str(home_model), "--test-set", name, "--assets", str(tiny_pack),
                          "--samples", "3", "--prior-samples", "2", "--batch", str(BATCH), "--examples", "3",
                          "--device", "cpu", "--out", str(out), "-q"]) == 0
    made = {"test_set": name, "classes": HOME_CLASSES, "assets": str(tiny_pack)}
    tests, train = streamed("test", 3, **made), streamed("train", 2, **made)
    report = check_report(out, expected(home_model, tests, [s.labels for s in train]), 3, 3)
    assert report["data"]["test_set"]["name"] == name
    assert report["class_share"]["ceiling"] > 0 or report["class_share"]["object"] > 0, report["class_share"]
    config = load_model(home_model).config
    keys = {prior_cache_path(SampleSource(seed=0, assets=str(tiny_pack), test_set=t), config, 2)
            for t in ("", "any-camera", name)}
    assert len(keys) == 3 and [p.name for p in (cache_folder / "prior").rglob("*.npz")] == [
        prior_cache_path(SampleSource(seed=0, assets=str(tiny_pack), test_set=name), config, 2).name]


def test_a_rebuilt_asset_pack_keys_other_caches(home_model: Path, tiny_pack: Path, tmp_path: Path) -> None:
    """The furnished rooms are drawn from the asset pack, so a pack built again with other contents (same folder,
    other manifest) gives the streamed samples and the per-cell prior cache entries of their own."""
    import shutil

    from fruxel.cli.eval import prior_cache_path
    from fruxel.train.eval.sample_cache import samples_cache_path
    from fruxel.train.samples import SampleSource

    pack = tmp_path / "pack"
    shutil.copytree(tiny_pack, pack)
    config = load_model(home_model).config
    source = SampleSource(seed=0, assets=str(pack), test_set="any-camera")

    def keys() -> tuple[Path, Path]:
        return (prior_cache_path(source, config, 2),
                samples_cache_path(source, config, "test", 2, camera=True, device="cpu"))

    before = keys()
    assert keys() == before
    manifest = pack / "manifest.json"
    manifest.write_text(manifest.read_text() + "\n")
    after = keys()
    assert after[0] != before[0] and after[1] != before[1]


def test_a_model_of_the_furnished_rooms_is_evaluated_on_them_by_default(home_model: Path, shipped_model: Path,
                                                                       tiny_pack: Path, tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """Without --test-set a model that labels ceilings and objects is evaluated on the any-camera set (the pack from
    $FRUXEL_ASSETS), and a model of the flat world on its own stream, as before."""
    from fruxel.train.model_files import load_model
    from fruxel.train.sim.testsets import default_test_set

    assert default_test_set(load_model(home_model).config.classes) == "any-camera"
    assert default_test_set(load_model(shipped_model).config.classes) == ""
    monkeypatch.setenv("FRUXEL_ASSETS", str(tiny_pack))
    out = tmp_path / "report"
    assert eval_cli.main(["--checkpoint", str(home_model), "--samples", "2", "--prior-samples", "0", "--batch",
                          str(BATCH), "--examples", "0", "--device", "cpu", "--out", str(out), "-q"]) == 0
    report = json.loads((out / "report.json").read_text())
    assert report["data"]["test_set"]["name"] == "any-camera"
    # The pack the rooms were drawn from is named by its manifest's digest: reports on other packs do not compare.
    assert report["data"]["pack"] == hashlib.sha256((tiny_pack / "manifest.json").read_bytes()).hexdigest()


def test_test_sets_that_do_not_fit_are_refused_in_one_line(shipped_model: Path, home_model: Path, tmp_path: Path,
                                                           capsys: pytest.CaptureFixture[str]) -> None:
    """--test-set with --data, --assets without --test-set, a room-world set for a model without its classes, a
    missing pack: one line each, before any sample is made or the output folder is."""
    out = tmp_path / "out"

    def refused(model: Path, *argv: str) -> str:
        assert eval_cli.main(["--checkpoint", str(model), "--out", str(out), "--device", "cpu", *argv]) == 2
        assert not out.exists()
        return error_line(capsys, "fruxel-eval")

    line = refused(shipped_model, "--test-set", "robot", "--data", str(tmp_path))
    assert "--test-set robot" in line and "--data" in line
    assert "--assets" in refused(shipped_model, "--assets", str(tmp_path))
    line = refused(shipped_model, "--test-set", "any-camera")
    assert "--test-set any-camera" in line and "ceiling, object" in line and "--test-set robot" in line
    line = refused(home_model, "--test-set", "any-camera", "--assets", str(tmp_path / "nowhere"))
    assert "nowhere: no asset pack there (--assets)" in line and "`make assets`" in line
    with pytest.raises(SystemExit) as e:
        eval_cli.main(["--checkpoint", str(shipped_model), "--test-set", "kitchen", "--out", str(out)])
    assert e.value.code == 2 and "--test-set" in error_line(capsys, "fruxel-eval")


@pytest.fixture(scope="module")
def data_set(tmp_path_factory: pytest.TempPathFactory) -> Path:
    out = tmp_path_factory.mktemp("data") / "small"
    config = SimConfig(grid=SMALL_GRID, image=ImageConfig(size=64), samples_per_scene=2, shard_size=2,
                       splits=(("train", 4), ("test", 3)))
    generate(str(out), config, 5, progress=False)
    return out


def test_data_set_split_end_to_end(shipped_model: Path, checkpoint_model: Path, data_set: Path,
                                   tmp_path: Path) -> None:
    from fruxel.train.sim.dataset import ShardDataset

    out = tmp_path / "report"
    # The training checkpoint form, read by a DataLoader worker, with a prior asked for more samples than there are.
    assert eval_cli.main(["--checkpoint", str(checkpoint_model), "--data", str(data_set), "--batch", str(BATCH),
                          "--prior-samples", "10", "--out", str(out), "--workers", "1", "-q"]) == 0
    tests = [ShardDataset(str(data_set), "test").sample(i) for i in range(3)]
    train = [ShardDataset(str(data_set), "train").sample(i).labels for i in range(4)]
    accs = expected(checkpoint_model, tests, train)
    report = check_report(out, accs, 3, 3)
    assert report["prior"] == {"split": "train", "samples": 4}
    assert report["data"]["kind"] == "shards" and report["data"]["root"] == str(data_set)
    assert report["data"]["pack"] is None
    assert report["data"]["seed"] == 5 and report["data"]["split"] == "test"
    # The same weights in the shipped form give the same numbers.
    out2 = tmp_path / "report2"
    # No prior and no example picture asked for: neither is made, and the report does not point at a picture.
    assert eval_cli.main(["--checkpoint", str(shipped_model), "--data", str(data_set), "--samples", "2",
                          "--prior-samples", "0", "--examples", "0", "--out", str(out2), "-q"]) == 0
    r2 = json.loads((out2 / "report.json").read_text())
    assert list(r2["results"]) == ["model", "oracle"] and r2["prior"] is None
    assert r2["data"]["samples"] == 2
    assert r2["examples"] is None and sorted(p.name for p in out2.iterdir()) == ["report.json", "report.md"]
    md2 = (out2 / "report.md").read_text()
    assert "per-cell prior" not in md2.split("## Metrics")[1] and "examples.png" not in md2


def test_a_data_folder_of_the_same_samples_gives_the_same_report(shipped_model: Path, data_set: Path,
                                                                  tmp_path: Path) -> None:
    # The data set's samples exported as a data folder of labelled photos (docs/your-data.md) read back as the same
    # images and labels, so every number of the report is the same.
    from fruxel.train.sim.export import export_folder
    from fruxel.train.sim.manifest import MANIFEST, Manifest

    folder = tmp_path / "folder"
    export_folder(folder, Manifest.load(str(data_set / MANIFEST)).config, 5, progress=False)
    reports = []
    for data in (data_set, folder):
        out = tmp_path / data.name / "report"
        assert eval_cli.main(["--checkpoint", str(shipped_model), "--data", str(data), "--batch", str(BATCH),
                              "--prior-samples", "10", "--examples", "0", "--out", str(out), "-q"]) == 0
        reports.append(json.loads((out / "report.json").read_text()))
    assert reports[1]["data"]["kind"] == "folder" and reports[1]["prior"] == {"split": "train", "samples": 4}
    assert reports[1]["results"] == reports[0]["results"]


# ---------------------------------------------------------------------------------------------------- bad input
@pytest.mark.parametrize("kind", BAD_MODELS)
def test_bad_model_files_give_one_line_and_run_nothing(kind: str, shipped_model: Path, tmp_path: Path,
                                                       capsys: pytest.CaptureFixture[str]) -> None:
    path, word = bad_model_file(kind, tmp_path, shipped_model)
    out = tmp_path / "out"
    assert eval_cli.main(["--checkpoint", str(path), "--samples", "1", "--out", str(out)]) == 2
    line = error_line(capsys, "fruxel-eval")
    assert str(path) in line and word in line, line
    assert not (tmp_path / "ran").exists(), "a pickled object in the file was run"
    assert not out.exists()


def small_data_set(root: Path, **changes: Any) -> Path:
    kw: dict[str, Any] = {"grid": SMALL_GRID, "image": ImageConfig(size=64), "samples_per_scene": 2, "shard_size": 2,
                          "splits": (("test", 1),)}
    kw.update(changes)
    generate(str(root), SimConfig(**kw), 1, progress=False)
    return root


def test_data_sets_that_do_not_fit_are_refused(shipped_model: Path, data_set: Path, tmp_path: Path,
                                               capsys: pytest.CaptureFixture[str]) -> None:
    def refused(*argv: str) -> str:
        out = tmp_path / "out"
        assert eval_cli.main(["--checkpoint", str(shipped_model), "--out", str(out), *argv]) == 2
        assert not out.exists()
        return error_line(capsys, "fruxel-eval")

    other = small_data_set(tmp_path / "images32", image=ImageConfig(size=32))
    line = refused("--data", str(other))
    assert str(other) in line and "does not fit the model" in line and "images 32x32" in line
    no_train = small_data_set(tmp_path / "no-train")
    line = refused("--data", str(no_train))
    assert "train split" in line and "--prior-samples 0" in line
    assert "no such folder" in refused("--data", str(tmp_path / "nowhere"))
    (tmp_path / "plain").mkdir()
    assert "not a data set folder" in refused("--data", str(tmp_path / "plain"))
    line = refused("--data", str(data_set), "--split", "val")
    assert "no split 'val'" in line and "train, test" in line
    line = refused("--data", str(data_set), "--samples", "4")
    assert "--samples 4" in line and "3 samples" in line
    # Options of streamed samples do not apply to a data set, --split only to a data set.
    assert "--seed" in refused("--data", str(data_set), "--seed", "3")
    assert "--no-augment" in refused("--data", str(data_set), "--no-augment")
    assert "--split" in refused("--split", "train")
    assert "unknown backend" in refused("--backend", "cuda-magic")
    (tmp_path / "file").write_text("")
    assert "--out" in eval_cli_line(shipped_model, ["--out", str(tmp_path / "file")], capsys)
    # With no prior the data set without a train split is evaluated.
    assert eval_cli.main(["--checkpoint", str(shipped_model), "--data", str(no_train), "--prior-samples", "0",
                          "--examples", "1", "--out", str(tmp_path / "ok"), "-q"]) == 0


def test_inputs_and_outputs_are_checked_before_the_model_loads(tmp_path: Path,
                                                              capsys: pytest.CaptureFixture[str]) -> None:
    """With a model file that cannot load, the error is still the folder's: they are checked first."""
    broken = tmp_path / "broken.safetensors"
    broken.write_bytes(b"not a model")
    (tmp_path / "file").write_text("")
    for argv, word in ((["--data", str(tmp_path / "nowhere")], "nowhere"),
                       (["--out", str(tmp_path / "file" / "sub")], "--out")):
        line = eval_cli_line(broken, argv, capsys)
        assert word in line and "broken" not in line, line
    assert sorted(p.name for p in tmp_path.iterdir()) == ["broken.safetensors", "file"]


@pytest.mark.parametrize("option", ["--out", "--data"])
def test_an_empty_folder_name_is_refused(option: str, shipped_model: Path, tmp_path: Path,
                                         monkeypatch: pytest.MonkeyPatch, capsys: pytest.CaptureFixture[str]) -> None:
    monkeypatch.chdir(tmp_path)
    with pytest.raises(SystemExit) as e:
        eval_cli.main(["--checkpoint", str(shipped_model), "--samples", "1", option, ""])
    assert e.value.code == 2 and option in error_line(capsys, "fruxel-eval")
    assert not any(tmp_path.iterdir())


def eval_cli_line(model: Path, argv: list[str], capsys: pytest.CaptureFixture[str]) -> str:
    assert eval_cli.main(["--checkpoint", str(model), *argv]) == 2
    return error_line(capsys, "fruxel-eval")


@pytest.mark.parametrize("workers", ["0", "1"])
def test_corrupt_shard_gives_one_line(workers: str, shipped_model: Path, data_set: Path, tmp_path: Path,
                                      capsys: pytest.CaptureFixture[str]) -> None:
    broken = tmp_path / "broken"
    shutil.copytree(data_set, broken)
    shard = broken / "test-00000.npz"
    raw = bytearray(shard.read_bytes())
    raw[len(raw) // 2] ^= 0xFF
    shard.write_bytes(bytes(raw))
    assert eval_cli.main(["--checkpoint", str(shipped_model), "--data", str(broken), "--prior-samples", "0",
                          "--workers", workers, "--out", str(tmp_path / "out")]) == 2
    line = error_line(capsys, "fruxel-eval")
    assert "test-00000.npz" in line
    assert not (tmp_path / "out").exists()


def test_help_is_instant_and_imports_nothing_heavy() -> None:
    code = ("import sys\nfrom fruxel.cli.eval import main\ntry:\n    main(['--help'])\nexcept SystemExit:\n"
            "    pass\nheavy = [m for m in ('torch', 'warp', 'pyrender', 'PIL') if m in sys.modules]\nprint(heavy)")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, timeout=60)
    assert "--prior-samples" in out.stdout and out.stdout.strip().endswith("[]")

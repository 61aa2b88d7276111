"""Data sets of the simulator: deterministic shards, resume after a killed run, strict reading, and the same
samples streamed through the training engine's data path (``fruxel.train.samples``).

Everything runs on tiny settings (64x64 images, 16^3 grids, a few samples per shard) so that the whole file
takes well under a minute on two cores.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest

from fruxel.classes import ClassTable
from fruxel.grid import FruxelGrid
from fruxel.train.sim.config import (
    AugmentConfig,
    ConfigError,
    ImageConfig,
    SimConfig,
    parse_splits,
    scale_splits,
    scene_seed,
)
from fruxel.train.sim.manifest import MANIFEST, Manifest
from fruxel.train.sim.sample import SampleMaker
from fruxel.train.sim.shards import DatasetError, ShardReader, encode_shard, shard_specs
from fruxel.train.sim.writer import generate

torch = pytest.importorskip("torch")
from fruxel.train.samples import Batches, BlockPlan, BlockStream, rank_range  # noqa: E402 - needs torch
from fruxel.train.sim.dataset import ShardDataset, sample_tensors  # noqa: E402 - needs torch

CONFIG = SimConfig(
    grid=FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0),
    image=ImageConfig(size=64),
    samples_per_scene=3,
    shard_size=2,
    splits=(("train", 6), ("test", 2)),
)
SEED = 7


def _files(root: Path) -> dict[str, bytes]:
    return {p.name: p.read_bytes() for p in sorted(root.iterdir())}


@pytest.fixture(scope="module")
def reference(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """An uninterrupted in-process generation of CONFIG with SEED."""
    out = tmp_path_factory.mktemp("reference")
    generate(str(out), CONFIG, SEED, progress=False)
    return out


def _copy(reference: Path, tmp_path: Path) -> Path:
    out = tmp_path / "copy"
    shutil.copytree(reference, out)
    return out


# ---------------------------------------------------------------------------------------------- determinism
def test_same_seed_same_bytes_across_runs_and_workers(reference: Path, tmp_path: Path) -> None:
    files = _files(reference)
    assert sorted(files) == ["manifest.json", "test-00000.npz", "train-00000.npz", "train-00001.npz",
                             "train-00002.npz"]
    # Two spawned workers render in other processes, with other OpenGL contexts and other object addresses.
    again = tmp_path / "again"
    generate(str(again), CONFIG, SEED, workers=2, progress=False)
    assert _files(again) == files
    other = tmp_path / "other"
    generate(str(other), CONFIG.replace(splits=(("train", 2),)), SEED + 1, progress=False)
    assert (other / "train-00000.npz").read_bytes() != files["train-00000.npz"]


def test_manifest_records_the_data_set(reference: Path) -> None:
    m = json.loads((reference / MANIFEST).read_text())
    assert m["format"] == "fruxel-sim" and m["version"] == 3 and m["complete"] is True and m["seed"] == SEED
    assert m["grid"] == CONFIG.grid.to_dict() and m["classes"] == CONFIG.classes.to_dict()
    assert m["intrinsics"]["image"]["fx"] == pytest.approx(m["intrinsics"]["grid"]["fx"] * 64 / 16)
    assert [s["count"] for s in m["splits"]["train"]["shards"]] == [2, 2, 2]
    assert all(len(s["sha256"]) == 64 for sp in m["splits"].values() for s in sp["shards"])
    assert SimConfig.from_dict(m["config"]) == CONFIG
    loaded = Manifest.load(str(reference / MANIFEST))
    assert loaded.to_json() == (reference / MANIFEST).read_text()


def test_samples_are_a_function_of_seed_and_index() -> None:
    # Asked out of order and in a fresh maker, a sample is the same; the room changes every 3 samples.
    with SampleMaker(CONFIG, SEED) as a:
        s4 = a.make("train", 4)
        s0 = a.make("train", 0)
    with SampleMaker(CONFIG, SEED) as b:
        t0 = b.make("train", 0)
        t4 = b.make("train", 4)
    for x, y in ((s0, t0), (s4, t4)):
        for name, arr in x.arrays().items():
            np.testing.assert_array_equal(arr, y.arrays()[name], err_msg=name)
    assert (s4.scene, s4.frame) == (1, 1) and s4.scene_seed == scene_seed(SEED, "train", 1)
    assert s0.labels.shape == (16, 16, 16) and s0.image.shape == (64, 64, 3) and s0.labels.any()


def test_samples_take_their_label_ids_from_the_class_table() -> None:
    # The same samples with the classes reordered and extended: images and poses bit-identical, labels mapped.
    table = ClassTable.from_names(("sculpture", "door", "floor", "extra", "furniture", "window", "wall"))
    made = []
    for cfg in (CONFIG, CONFIG.replace(classes=table)):
        with SampleMaker(cfg, SEED) as maker:  # one OpenGL context at a time
            made.append([maker.make("train", i) for i in (0, 4)])
    lut = np.array([table.index(n) for n in CONFIG.classes.names], np.uint8)
    for x, y in zip(*made, strict=True):
        assert len(np.unique(x.labels)) >= 3
        np.testing.assert_array_equal(y.labels, lut[x.labels])
        assert y.image.tobytes() == x.image.tobytes() and y.pose.tobytes() == x.pose.tobytes()
    with pytest.raises(ConfigError, match="lacks the simulator's classes"):
        CONFIG.replace(classes=ClassTable.from_names(("wall", "floor")))


# ---------------------------------------------------------------------------------------------- resume
def test_resume_after_a_killed_run(reference: Path, tmp_path: Path) -> None:
    cfg = CONFIG.replace(splits=(("train", 24), ("test", 2)), shard_size=3)
    args = ["--split", "train=24,test=2", "--shard-size", "3", "--image", "64", "--grid", "16",
            "--samples-per-scene", "3", "--seed", str(SEED), "--world", "flat", "--camera", "robot"]
    out = tmp_path / "killed"
    proc = subprocess.Popen([sys.executable, "-m", "fruxel.cli.sim", "generate", "--out", str(out), "-q", *args],
                            stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    recorded: list[str] = []
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline and proc.poll() is None:
            try:
                m = json.loads((out / MANIFEST).read_text())
            except (OSError, ValueError):
                m = None
            if m is not None:
                recorded = [s["file"] for s in m["splits"]["train"]["shards"] if s["sha256"]]
                if recorded:
                    break
            time.sleep(0.002)
        proc.send_signal(signal.SIGKILL)
    finally:
        proc.kill()
        proc.wait()
    n_shards = len(shard_specs(cfg))
    assert 0 < len(recorded) < n_shards, "the run must be killed after its first shard and before its last"
    before = {f: os.stat(out / f) for f in recorded}
    stale = out / ".train-00007.npz.0123456789ab.tmp"
    stale.write_bytes(b"PK\x03\x04 half a shard")
    generate(str(out), cfg, SEED, progress=False)
    assert not stale.exists()
    for f, st in before.items():
        now = os.stat(out / f)
        assert (now.st_ino, now.st_mtime_ns) == (st.st_ino, st.st_mtime_ns), f"{f} was rewritten"
    full = tmp_path / "full"
    generate(str(full), cfg, SEED, progress=False)
    assert _files(out) == _files(full)
    # A finished folder is a no-op to resume.
    stamp = {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")}
    generate(str(out), cfg, SEED, progress=False)
    assert {p.name: p.stat().st_mtime_ns for p in out.glob("*.npz")} == stamp


def test_shard_written_before_the_manifest_update_is_adopted(reference: Path, tmp_path: Path) -> None:
    out = _copy(reference, tmp_path)
    m = json.loads((out / MANIFEST).read_text())
    m["splits"]["train"]["shards"][1]["sha256"] = None
    m["complete"] = False
    (out / MANIFEST).write_text(json.dumps(m, indent=1) + "\n")
    st = os.stat(out / "train-00001.npz")
    generate(str(out), CONFIG, SEED, progress=False)
    assert os.stat(out / "train-00001.npz").st_mtime_ns == st.st_mtime_ns
    assert _files(out) == _files(reference)


# ---------------------------------------------------------------------------------------------- refusal
def _assert_refused(fn, path: Path, words: str) -> None:
    with pytest.raises(DatasetError) as info:
        fn()
    assert str(path) in str(info.value) and words in str(info.value)
    # One error, no chained traceback: either nothing was being handled, or the context is suppressed.
    e = info.value
    assert e.__cause__ is None and (e.__context__ is None or e.__suppress_context__)


def test_truncated_shard_is_refused(reference: Path, tmp_path: Path) -> None:
    out = _copy(reference, tmp_path)
    shard = out / "train-00001.npz"
    data = shard.read_bytes()
    shard.write_bytes(data[: len(data) // 2])
    _assert_refused(lambda: generate(str(out), CONFIG, SEED, progress=False), shard, "SHA-256")
    ds = ShardDataset(out, "train")
    ds[0]
    _assert_refused(lambda: ds[2], shard, "SHA-256")
    # Without the hash check the damage is still found, by the zip and npy checks.
    _assert_refused(lambda: ShardDataset(out, "train", verify=False)[2], shard, "corrupt")


def test_foreign_shards_are_refused(reference: Path, tmp_path: Path) -> None:
    out = _copy(reference, tmp_path)
    shard = out / "train-00000.npz"
    np.savez(shard, labels=np.zeros((16, 16, 16), np.uint8))
    _assert_refused(lambda: generate(str(out), CONFIG, SEED, progress=False), shard, "SHA-256")
    _assert_refused(lambda: ShardDataset(out, "train", verify=False)[0], shard, "wrong members")
    # A real shard in the wrong place: right structure, wrong meta.
    shutil.copy(out / "train-00001.npz", shard)
    _assert_refused(lambda: ShardDataset(out, "train", verify=False)[0], shard, "meta shard is 1, expected 0")
    # Not yet recorded in the manifest: the file is read in full and refused.
    m = json.loads((out / MANIFEST).read_text())
    m["splits"]["train"]["shards"][0]["sha256"] = None
    m["complete"] = False
    (out / MANIFEST).write_text(json.dumps(m, indent=1) + "\n")
    _assert_refused(lambda: generate(str(out), CONFIG, SEED, progress=False), shard, "corrupt or foreign shard")
    shard.write_bytes(b"not a zip at all")
    _assert_refused(lambda: generate(str(out), CONFIG, SEED, progress=False), shard, "not a zip archive")


def test_object_arrays_are_refused_without_unpickling(reference: Path, tmp_path: Path) -> None:
    out = _copy(reference, tmp_path)
    spec = shard_specs(CONFIG)[0]
    with SampleMaker(CONFIG, SEED) as maker:
        samples = [maker.make("train", i) for i in spec.indices]
    data = encode_shard(spec, CONFIG, SEED, samples)
    import io
    import zipfile

    src = zipfile.ZipFile(io.BytesIO(data))
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w") as dst:
        for info in src.infolist():
            body = src.read(info)
            if info.filename == "pose_00000.npy":
                tmp = io.BytesIO()
                np.save(tmp, np.array([{"evil": 1}], dtype=object), allow_pickle=True)
                body = tmp.getvalue()
            dst.writestr(info, body)
    path = out / spec.file
    path.write_bytes(buf.getvalue())
    reader = ShardReader(str(path), spec, CONFIG, SEED)
    _assert_refused(lambda: reader.sample(0), path, "object array")
    reader.close()


def test_impossible_values_are_refused(tmp_path: Path) -> None:
    # Well-formed members with values no generator writes: a label outside the class table, a NaN pose.
    spec = shard_specs(CONFIG)[0]
    with SampleMaker(CONFIG, SEED) as maker:
        samples = [maker.make("train", i) for i in spec.indices]
    samples[0].labels[0, 0, 0] = len(CONFIG.classes)
    samples[1].pose[0, 3] = np.nan
    path = tmp_path / spec.file
    path.write_bytes(encode_shard(spec, CONFIG, SEED, samples))
    with ShardReader(str(path), spec, CONFIG, SEED) as reader:
        _assert_refused(lambda: reader.sample(0), path, "labels outside the 7 classes")
        _assert_refused(lambda: reader.sample(1), path, "non-finite pose")


def test_folder_of_other_settings_is_refused(reference: Path, tmp_path: Path) -> None:
    out = _copy(reference, tmp_path)
    other = CONFIG.replace(grid=FruxelGrid(width=16, height=16, depth=8, z_near=0.5, z_far=8.0, hfov=60.0))
    _assert_refused(lambda: generate(str(out), other, SEED, progress=False), out / MANIFEST, "grid")
    _assert_refused(lambda: generate(str(out), CONFIG, SEED + 1, progress=False), out / MANIFEST, "seed")
    m = json.loads((out / MANIFEST).read_text())
    m["grid"]["depth"] = 32
    (out / MANIFEST).write_text(json.dumps(m))
    _assert_refused(lambda: ShardDataset(out, "train"), out / MANIFEST, "contradict")
    m["version"] = 99
    (out / MANIFEST).write_text(json.dumps(m))
    _assert_refused(lambda: ShardDataset(out, "train"), out / MANIFEST, "version 99")
    # A folder of format version 1 (own-view images stored with every sample) is refused with what to do.
    m["version"] = 1
    (out / MANIFEST).write_text(json.dumps(m))
    _assert_refused(lambda: generate(str(out), CONFIG, SEED, progress=False), out / MANIFEST, "make the data set again")


def test_incomplete_data_set_is_refused_by_the_reader(reference: Path, tmp_path: Path) -> None:
    out = _copy(reference, tmp_path)
    m = json.loads((out / MANIFEST).read_text())
    m["splits"]["test"]["shards"][0]["sha256"] = None
    m["complete"] = False
    (out / MANIFEST).write_text(json.dumps(m, indent=1) + "\n")
    assert len(ShardDataset(out, "train")) == 6
    with pytest.raises(DatasetError, match="incomplete"):
        ShardDataset(out, "test")
    with pytest.raises(DatasetError, match="no split named 'val'"):
        ShardDataset(out, "val")


# ---------------------------------------------------------------------------------------------- torch
def test_shard_dataset_items(reference: Path) -> None:
    ds = ShardDataset(reference, "train")
    item = ds[5]
    assert item["image"].shape == (3, 64, 64) and item["image"].dtype == torch.float32
    assert 0.0 <= float(item["image"].min()) and float(item["image"].max()) <= 1.0
    # Labels stay uint8 until the device (an int64 128^3 volume would take 16 MiB per sample instead of 2).
    assert item["labels"].shape == (16, 16, 16) and item["labels"].dtype == torch.uint8
    assert item["pose"].shape == (4, 4) and int(item["index"]) == 5
    np.testing.assert_allclose(item["K"].numpy(), CONFIG.image_camera().K)
    # One source of truth: own-view images are first_hit of the labels on the device, not items of their own.
    assert sorted(item) == ["K", "camera", "image", "index", "labels", "pose"]
    with pytest.raises(IndexError):
        ds[6]


def _stream(plan: BlockPlan, **kwargs: object) -> BlockStream:
    """The engine's stream of CONFIG's training split, made by the simulator."""
    return BlockStream(plan, "stream", "train", sim_config=CONFIG, seed=SEED, **kwargs)


def _assert_blocks_equal(got: list[dict], want: list[dict]) -> None:
    assert len(got) == len(want) and len(got) > 0
    for a, b in zip(got, want, strict=True):
        assert a["index"].tolist() == b["index"].tolist()
        for name in ("image", "labels"):
            assert a[name].dtype == b[name].dtype and a[name].tobytes() == b[name].tobytes(), (a["index"], name)


def test_streamed_blocks_are_the_shards_bytes(reference: Path) -> None:
    """The training engine's stream made by the simulator gives the bytes of the shards the generator wrote for
    the same config and seed, from the start, from a resume position inside a room, and for one rank's rooms."""
    plan = BlockPlan(0, 6, CONFIG.samples_per_scene, None)
    shards = list(BlockStream(plan, "shards", "train", root=str(reference), stop_block=2))
    assert [b["index"].tolist() for b in shards] == [[0, 1, 2], [3, 4, 5]]
    ds = ShardDataset(reference, "train")
    for i in range(6):
        assert shards[i // 3]["image"][i % 3].tobytes() == ds.sample(i).image.tobytes()
    _assert_blocks_equal(list(_stream(plan, stop_block=2)), shards)
    # Resumed at block 1 with its first sample used: samples 4 and 5.
    tail = list(_stream(plan, first_block=1, skip=1, stop_block=2))
    assert [b["index"].tolist() for b in tail] == [[4, 5]]
    assert tail[0]["image"].tobytes() == shards[1]["image"][1:].tobytes()
    # Two ranks own disjoint whole rooms that together make the split; rank 1 streams the shards' second room.
    assert [rank_range(6, 3, r, 2) for r in range(2)] == [(0, 3), (3, 6)]
    lo, hi = rank_range(6, 3, 1, 2)
    _assert_blocks_equal(list(_stream(BlockPlan(lo, hi, 3, None), stop_block=1)), shards[1:])


@pytest.mark.slow
def test_batches_from_two_spawned_workers_equal_one_process(reference: Path) -> None:
    """Batches of the simulator's stream are the same bytes, in the same order, whether one process or two
    spawned DataLoader workers (each with its own renderer and meshes, blocks dealt round-robin) make them."""
    plan = BlockPlan(0, 6, CONFIG.samples_per_scene, None)
    made = {}
    for workers in (0, 2):
        batches = Batches(lambda block, skip: _stream(plan, first_block=block, skip=skip, stop_block=2), 2, workers)
        try:
            made[workers] = [next(batches) for _ in range(3)]
        finally:
            batches.close()
    ds = ShardDataset(reference, "train")
    for one, two in zip(made[0], made[2], strict=True):
        for name in ("image", "labels", "index"):
            assert torch.equal(one[name], two[name]), name
    assert [b["index"].tolist() for b in made[2]] == [[0, 1], [2, 3], [4, 5]]
    for b in made[2]:
        want = [ds.sample(int(i)) for i in b["index"]]
        assert b["image"].numpy().tobytes() == np.stack([s.image for s in want]).tobytes()
        assert b["labels"].numpy().tobytes() == np.stack([s.labels for s in want]).tobytes()


def test_sample_tensors_keep_bytes(reference: Path) -> None:
    s = ShardDataset(reference, "test").sample(1)
    t = sample_tensors(s, CONFIG)
    np.testing.assert_array_equal(np.rint(t["image"].numpy().transpose(1, 2, 0) * 255).astype(np.uint8), s.image)
    # The labels are the sample's own bytes, not a copy; a read-only array is copied rather than shared.
    assert t["labels"].dtype == torch.uint8 and np.shares_memory(t["labels"].numpy(), s.labels)
    s.labels.flags.writeable = False
    again = sample_tensors(s, CONFIG)["labels"]
    assert not np.shares_memory(again.numpy(), s.labels) and torch.equal(again, t["labels"])


# ---------------------------------------------------------------------------------------------- settings
def test_config_round_trip_and_splits() -> None:
    cfg = CONFIG.replace(image=ImageConfig(size=32, augment=AugmentConfig(enabled=False)))
    assert SimConfig.from_dict(json.loads(json.dumps(cfg.to_dict()))) == cfg
    assert cfg.digest() != CONFIG.digest()
    assert scale_splits(16000) == (("train", 15000), ("test", 1000))
    assert sum(n for _, n in scale_splits(7)) == 7
    assert parse_splits("train=3, val=2") == (("train", 3), ("val", 2))
    for bad in ("train", "train=x", "train=0", "Train=3", "a=1,a=2"):
        with pytest.raises(ConfigError):
            parse_splits(bad)
    with pytest.raises(ConfigError, match="multiple of the grid width"):
        CONFIG.replace(grid=FruxelGrid(width=16, height=12, depth=8, z_near=0.5, z_far=8.0, hfov=60.0),
                       image=ImageConfig(size=10))
    wide = CONFIG.replace(grid=FruxelGrid(width=16, height=12, depth=8, z_near=0.5, z_far=8.0, hfov=70.0))
    assert (wide.image_width, wide.image_height) == (64, 48)
    assert wide.trajectory.mount.hfov == 70.0


def test_gpu_sharing_hint_names_mps_only_when_stream_workers_share_a_gpu_without_it(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """Several streamed-simulator workers on one CUDA device without MPS's control pipe get one line naming the
    command; with the pipe there, on the CPU, with one worker or with stored data there is none."""
    from fruxel.train.samples import SampleSource, gpu_sharing_hint

    pipe = tmp_path / "mps"
    pipe.mkdir()
    monkeypatch.setenv("CUDA_MPS_PIPE_DIRECTORY", str(pipe))
    stream = SampleSource()
    hint = gpu_sharing_hint(stream, 15, "cuda:0")
    assert hint is not None and "nvidia-cuda-mps-control -d" in hint and "\n" not in hint and str(pipe) in hint
    assert gpu_sharing_hint(stream, 15, "cpu") is None and gpu_sharing_hint(stream, 1, "cuda:0") is None
    assert gpu_sharing_hint(SampleSource("shards", str(tmp_path)), 15, "cuda:0") is None
    (pipe / "control").write_text("")  # the daemon's named pipe stands there while it runs
    assert gpu_sharing_hint(stream, 15, "cuda:0") is None
    assert gpu_sharing_hint(stream, 48, "cuda:0") is None


def test_more_stream_workers_than_mps_serves_are_refused_in_one_line(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    """With MPS's control pipe there, 47 workers and the training process fit on one GPU and 48 do not; without MPS,
    on the CPU or with stored data, nothing is refused."""
    from fruxel.train.samples import SampleSource, check_mps_clients

    pipe = tmp_path / "mps"
    pipe.mkdir()
    monkeypatch.setenv("CUDA_MPS_PIPE_DIRECTORY", str(pipe))
    stream = SampleSource()
    check_mps_clients(stream, 60, "cuda:0")  # no daemon: the workers time-slice, slowly, but they run
    (pipe / "control").write_text("")
    check_mps_clients(stream, 47, "cuda:0")
    check_mps_clients(stream, 60, "cpu")
    check_mps_clients(SampleSource("shards", str(tmp_path)), 60, "cuda:0")
    with pytest.raises(ConfigError, match=r"^data.workers 48: with CUDA MPS on, one GPU serves at most 48 [^\n]*"
                                          r"use at most 47 workers a GPU$"):
        check_mps_clients(stream, 48, "cuda:1")


def test_a_missing_asset_pack_is_one_line_from_the_check_and_from_a_spawned_worker(tmp_path: Path) -> None:
    """The furnished rooms need the asset pack: the check before a run (``split_size``) names it at once, and a
    spawned worker that meets it missing anyway (batches made without that check) says so in one line too, not with
    the worker's traceback inside the message."""
    from fruxel.errors import ConfigError
    from fruxel.train.config import preset
    from fruxel.train.samples import SampleSource, split_size, training_batches

    model = preset("tiny").model
    source = SampleSource(world="home", camera="any", assets=str(tmp_path / "nowhere"))
    words = f"{tmp_path / 'nowhere'}: no asset pack there (data.assets)"
    with pytest.raises(ConfigError) as e:
        split_size(source, model, "train")
    assert str(e.value).startswith(words) and "make assets" in str(e.value)
    assert split_size(SampleSource(), model, "train") is None  # the flat world needs no pack
    batches = training_batches(source, model, 64, batch=2, workers=1)
    try:
        with pytest.raises(ConfigError) as e:
            next(batches)
    finally:
        batches.close()
    message = str(e.value)
    assert message.startswith(f"{tmp_path / 'nowhere'}: no asset pack there") and "make assets" in message
    assert "\n" not in message and "Traceback" not in message and "DataLoader" not in message


def test_a_stream_mixes_in_another_kind_of_room_by_each_rooms_own_draw(tiny_pack: Path) -> None:
    """``data.mix_set``: the rooms that ``mixed_room`` picks are made as the mix's (the robot's mount in the flat
    world), sample for sample what that test set's config makes of the training split; the others as the stream's
    own; the pick is the room's, the same with workers or without."""
    import dataclasses

    from fruxel.train.config import preset
    from fruxel.train.samples import SampleSource, mixed_room, sim_config, training_batches
    from fruxel.train.sim.sample import SampleMaker

    model = preset("tiny").model
    spp, rooms, share = 2, 4, 0.5
    seed = next(s for s in range(100) if len({mixed_room(s, r, share) for r in range(rooms)}) == 2)
    source = SampleSource(world="home", camera="any", assets=str(tiny_pack), samples_per_scene=spp, seed=seed,
                          mix_set="robot", mix_share=share)
    splits = (("train", 64),)
    own, mix = (sim_config(model, s, splits) for s in (source, dataclasses.replace(source, test_set="robot")))
    assert mix.world == "flat" and own.world == "home"
    for workers in (0, 2):
        batches = training_batches(source, model, 64, batch=spp * rooms, workers=workers)
        try:
            got = next(batches)
        finally:
            batches.close()
        assert got["index"].tolist() == list(range(spp * rooms))
        for i in range(spp * rooms):
            with SampleMaker(mix if mixed_room(seed, i // spp, share) else own, seed) as maker:
                want = maker.make("train", i)
            assert np.array_equal(got["image"][i].numpy(), want.image), (workers, i)
            assert np.array_equal(got["labels"][i].numpy(), want.labels), (workers, i)
    assert abs(np.mean([mixed_room(0, r, 0.2) for r in range(4000)]) - 0.2) < 0.02
    assert not any(mixed_room(0, r, 0.0) for r in range(100))
    assert "50% of its training rooms as test set robot's" in source.describe()


@pytest.mark.parametrize(("fields", "words"), [
    ({"mix_set": "kitchen"}, "data.mix_set must be one of any-camera, any-camera-test-assets, robot"),
    ({"mix_set": "robot", "mix_share": 1.0}, "data.mix_share must be a number in [0, 1), got 1.0"),
    ({"mix_set": "robot", "mix_share": True}, "data.mix_share must be a number in [0, 1)"),
    ({"mix_share": 0.2}, "data.mix_share needs data.mix_set"),
    ({"mix_set": "robot", "mix_share": 0.2, "source": "shards", "root": "x"}, "data.mix_set mixes streamed rooms"),
])
def test_a_bad_mix_is_refused_naming_its_field(fields: dict, words: str) -> None:
    from fruxel.errors import ConfigError
    from fruxel.train.config import DataConfig

    with pytest.raises(ConfigError) as e:
        DataConfig(**fields)
    assert str(e.value).startswith(words), str(e.value)

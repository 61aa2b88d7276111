"""The ``fruxel-train`` command line: help, config files and their errors, --print-config, Ctrl-C and --resume,
and torchrun with two processes.

Runs train a 16^3 SSZ from 32^2 images for a few steps on a data set made with ``fruxel-sim generate``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest

from fruxel.cli.train import main

CONFIG: dict[str, Any] = {
    "preset": "tiny", "name": "cli-test",
    "model": {"grid": {"width": 16, "height": 16, "depth": 16}, "levels": 3, "stem": 8, "encoder": [8, 12, 16],
              "encoder_blocks": [1, 1, 1], "topdown": [8, 12, 16], "decoder": [4, 8, 12],
              "decoder_blocks": [1, 1, 1]},
    "data": {"workers": 0, "samples_per_scene": 4, "eval_samples": 4, "frequency_samples": 4},
    "run": {"steps": 4, "batch_size": 2, "log_every": 1, "eval_every": 0, "checkpoint_every": 0,
            "tensorboard": False},
}
"""A config file for a 16^3 SSZ from 32^2 images (the data set's grid and image size)."""


@pytest.fixture(scope="module")
def data(tmp_path_factory: pytest.TempPathFactory, tiny_pack: Path) -> Path:
    """A data set of 16 training samples (4 rooms) and 4 test samples, 16^3 grids from 32^2 images: fruxel-sim's
    default, the furnished rooms of the tiny pack from any camera, labelled with the classes of the models' default
    (HOME_CLASSES)."""
    from fruxel.cli.sim import main as sim

    out = tmp_path_factory.mktemp("data")
    assert sim(["generate", "--out", str(out), "--split", "train=16,test=4", "--grid", "16", "--image", "32",
                "--samples-per-scene", "4", "--shard-size", "4", "--assets", str(tiny_pack), "-q"]) == 0
    return out


def _write(path: Path, config: Any) -> Path:
    path.write_text(config if isinstance(config, str) else json.dumps(config))
    return path


def _error_line(capsys: pytest.CaptureFixture[str]) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    assert err[0].startswith("fruxel-train: error: ")
    return err[0]


def test_help_is_instant_and_imports_no_torch() -> None:
    t = time.perf_counter()
    out = subprocess.run([sys.executable, "-m", "fruxel.cli.train", "--help"], capture_output=True, text=True,
                         check=True)
    assert "--resume" in out.stdout and "--print-config" in out.stdout and "ssz64" in out.stdout
    assert time.perf_counter() - t < 10
    probe = ("import sys, fruxel.cli.train; "
             "print(sorted(m for m in ('torch', 'pyrender', 'warp') if m in sys.modules))")
    mods = subprocess.run([sys.executable, "-c", probe], capture_output=True, text=True, check=True)
    assert mods.stdout.strip() == "[]"


@pytest.mark.parametrize("text, words", [
    ({"run": {"stepz": 3}}, "unknown config key 'run.stepz'"),
    ({"run": {"steps": "3"}}, "run.steps must be an integer"),
    ({"optim": {"lr": -1.0}}, "optim.lr must be a finite number >= 0"),
    ({"loss": {"shell_losses": {"weight_own_view": float("nan")}}},
     "loss.shell_losses.weight_own_view must be a finite number >= 0"),
    ({"model": {"architecture": "unet"}}, "unknown model.architecture 'unet'"),
    ({"version": 1, "model": {"fine_depth": 4}}, "model.fine_depth = 4 was removed"),
    ({"model": {"grid": {"width": 15}}}, "model.grid 15x64x64 must be divisible"),
    ({"preset": "huge"}, "unknown preset 'huge'"),
    ('{"run": {"steps": 3}', "not valid JSON"),
    ("[1, 2]", "must be a JSON object"),
])
def test_bad_config_files_give_one_line_naming_the_key(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                                       text: Any, words: str) -> None:
    path = _write(tmp_path / "bad.json", text)
    assert main(["--config", str(path), "--out", str(tmp_path / "run")]) == 2
    line = _error_line(capsys)
    assert str(path) in line and words in line, line
    assert not (tmp_path / "run").exists()


def test_missing_or_unreadable_config_files(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["--config", str(tmp_path / "none.json"), "--out", str(tmp_path / "run")]) == 2
    assert "none.json: No such file or directory" in _error_line(capsys)
    assert main(["--config", str(tmp_path), "--out", str(tmp_path / "run")]) == 2
    assert f"{tmp_path}: Is a directory" in _error_line(capsys)
    (tmp_path / "binary.json").write_bytes(b"\xff\xfe\x00")
    assert main(["--config", str(tmp_path / "binary.json"), "--out", str(tmp_path / "run")]) == 2
    assert "binary.json: not a text file" in _error_line(capsys)


@pytest.mark.parametrize("argv, words", [
    (["--preset", "tiny"], "--out RUN_DIR is required"),
    (["--out", "x"], "give --config FILE or --preset NAME"),
    (["--resume"], "--resume needs --out"),
    (["--resume", "--out", "x", "--preset", "tiny", "--batch-size", "4"], "--preset, --batch-size cannot be given"),
    (["--resume", "--out", "{tmp}/nothing"], "nothing/last.pt: no checkpoint to resume from"),
    (["--preset", "tiny", "--batch-size", "3", "--out", "{tmp}/run", "--data", "{tmp}/nodata"], "nodata"),
])
def test_option_errors_give_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
                                     words: str) -> None:
    assert main([a.format(tmp=tmp_path) for a in argv]) == 2
    assert words in _error_line(capsys)


@pytest.mark.parametrize("case", ["not-a-data-set", "missing", "other-grid", "out-under-a-file", "cuda"])
def test_runs_that_cannot_start_leave_nothing_behind(case: str, tmp_path: Path, data: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """Checked before the run folder is made: a run folder (with its config.json) was left by a --data that is no
    data set."""
    import torch

    wrong = tmp_path / "photos"
    wrong.mkdir()
    (wrong / "readme.txt").write_text("not a data set\n")
    (tmp_path / "file").write_text("")
    run = tmp_path / "run"
    argv, words = {
        "not-a-data-set": (["--data", str(wrong)], (str(wrong), "manifest")),
        "missing": (["--data", str(tmp_path / "none")], ("none",)),
        # The tiny preset is 32^3 from 64^2 images, the data set 16^3 from 32^2.
        "other-grid": (["--data", str(data)], (str(data), "16x16x16", "32x32x32")),
        "out-under-a-file": (["--out", str(tmp_path / "file" / "run")], ("--out", "file is a file")),
        "cuda": (["--device", "cuda"], ("--device cuda", "no CUDA device")),
    }[case]
    if case == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA device")
    before = sorted(p.name for p in tmp_path.iterdir())
    assert main(["--preset", "tiny", "--steps", "1", "--out", str(run), *argv]) == 2
    line = _error_line(capsys)
    assert all(w in line for w in words), line
    assert sorted(p.name for p in tmp_path.iterdir()) == before and not run.exists()
    assert sorted(p.name for p in wrong.iterdir()) == ["readme.txt"]


def test_a_missing_asset_pack_is_refused_before_the_run_starts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    """The tiny preset streams the furnished rooms, which need the asset pack: without one the run is refused in
    one line naming where it looked, before the run folder or any simulator worker is made."""
    monkeypatch.setenv("FRUXEL_ASSETS", str(tmp_path / "nowhere"))
    run = tmp_path / "run"
    assert main(["--preset", "tiny", "--steps", "1", "--out", str(run)]) == 2
    line = _error_line(capsys)
    assert f"{tmp_path / 'nowhere'}: no asset pack there ($FRUXEL_ASSETS)" in line and "make assets" in line
    assert not run.exists()


def test_an_unknown_cuda_wait_mode_is_refused_before_the_run_starts(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                                     capsys: pytest.CaptureFixture[str],
                                                                     tiny_pack: Path) -> None:
    """``$FRUXEL_CUDA_WAIT`` tells the simulator's workers how to wait for their GPU; a name they would refuse, each
    in its own process, is refused in one line before the run folder or any worker is made."""
    monkeypatch.setenv("FRUXEL_ASSETS", str(tiny_pack))
    monkeypatch.setenv("FRUXEL_CUDA_WAIT", "busy")
    run = tmp_path / "run"
    assert main(["--preset", "tiny", "--steps", "1", "--out", str(run)]) == 2
    assert "FRUXEL_CUDA_WAIT='busy': expected one of block, spin, yield, auto" in _error_line(capsys)
    assert not run.exists()


@pytest.mark.parametrize("option", ["--out", "--data"])
def test_an_empty_folder_name_is_refused(option: str, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                         capsys: pytest.CaptureFixture[str]) -> None:
    """``--out ""`` would have trained into the current folder."""
    monkeypatch.chdir(tmp_path)
    argv = ["--preset", "tiny", "--steps", "1", "--out", "run", option, ""]
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2 and option in _error_line(capsys)
    assert not any(tmp_path.iterdir())


@pytest.mark.parametrize("argv", [["--preset", "small"], ["--preset", "tiny", "--steps", "0"],
                                  ["--preset", "tiny", "--device", "gpu"], ["--preset", "tiny", "--time-limit", "-1"],
                                  ["--preset", "tiny", "--config", "x.json"]])
def test_parser_errors_give_one_line(argv: list[str], capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        main(argv)
    assert e.value.code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith("fruxel-train: error:")


def test_print_config_gives_a_file_to_start_from(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from fruxel.train.config import TrainConfig, override, preset

    assert main(["--preset", "ssz64", "--steps", "7", "--workers", "2", "--data", "DIR", "--print-config"]) == 0
    text = capsys.readouterr().out
    config = TrainConfig.from_json(text)
    assert config == override(preset("ssz64"), {"run": {"steps": 7}, "data": {"workers": 2, "source": "shards",
                                                                               "root": "DIR"}}, "")
    # The printed config is a complete config file: it reads back to itself and prints the same.
    assert main(["--config", str(_write(tmp_path / "full.json", text)), "--print-config"]) == 0
    assert capsys.readouterr().out == text


@pytest.mark.slow
def test_ctrl_c_writes_a_checkpoint_and_resume_continues(tmp_path: Path, data: Path,
                                                         capsys: pytest.CaptureFixture[str],
                                                         monkeypatch: pytest.MonkeyPatch,
                                                         torch_one_thread: None) -> None:
    """Ctrl-C during step 2 of 4 (raised inside the training loop) exits 130 after writing the checkpoint and the
    shipped model; ``--resume`` continues from step 2 to the end; a further ``--resume`` has nothing to train
    unless ``--steps`` asks for more."""
    from fruxel.train.engine.checkpoint import LATEST, read_checkpoint
    from fruxel.train.engine.run_folder import SHIPPED
    from fruxel.train.engine.step import PhaseTimer
    from fruxel.train.model_files import load_model

    config = _write(tmp_path / "c.json", CONFIG)
    run = tmp_path / "run"
    tick = PhaseTimer.tick

    def interrupting(self: PhaseTimer, step: int, phase: str | None) -> None:
        if phase is None and step == 2:  # as step 2 starts: Ctrl-C inside the training loop
            raise KeyboardInterrupt
        tick(self, step, phase)

    with monkeypatch.context() as m:
        m.setattr(PhaseTimer, "tick", interrupting)
        assert main(["--config", str(config), "--data", str(data), "--out", str(run), "--device", "cpu", "-q"]) == 130
    err = capsys.readouterr().err
    assert f"checkpoint of step 2 written to {run / LATEST}" in err and "--resume" in err
    assert err.strip().splitlines()[-1] == "fruxel-train: interrupted"
    ck = read_checkpoint(run / LATEST)
    assert ck.state["step"] == 2 and ck.config.name == "cli-test" and ck.config.data.root == str(data)
    for path in (run / LATEST, run / SHIPPED):
        load_model(path)

    assert main(["--resume", "--out", str(run), "--device", "cpu"]) == 0
    out = capsys.readouterr().out.strip().splitlines()
    assert len(out) == 1 and out[0].startswith(f"fruxel-train: {run}: step 4 of 4, 8 samples in "), out
    assert "; loss " in out[0] and "(ce " in out[0] and "held-out (4 samples): mIoU" in out[0]
    assert read_checkpoint(run / LATEST).state["step"] == 4
    assert main(["--resume", "--out", str(run), "--device", "cpu"]) == 0
    assert "nothing left to train" in capsys.readouterr().out
    assert main(["--resume", "--out", str(run), "--device", "cpu", "--steps", "5", "-q"]) == 0
    assert read_checkpoint(run / LATEST).state["step"] == 5


def test_a_checkpoint_holding_an_object_is_refused_on_resume(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    import torch

    class Trap:
        def __reduce__(self) -> tuple[Any, ...]:
            return (open, (str(tmp_path / "pwned"), "w"))

    (tmp_path / "run").mkdir()
    torch.save({"format": "fruxel-ssz-checkpoint", "payload": Trap()}, tmp_path / "run" / "last.pt")
    assert main(["--resume", "--out", str(tmp_path / "run")]) == 2
    assert "last.pt: refused" in _error_line(capsys)
    assert not (tmp_path / "pwned").exists()


@pytest.mark.slow
def test_torchrun_with_two_processes(tmp_path: Path, data: Path) -> None:
    """``torchrun --nproc_per_node 2 -m fruxel.cli.train`` on the CPU (gloo): both processes train their half of
    each batch (each with a spawned data worker, which imports the command's module again: the main guard), rank
    0 alone writes the run folder and prints the summary."""
    from fruxel.train.engine.checkpoint import LATEST, read_checkpoint

    config = _write(tmp_path / "c.json", CONFIG)
    run = tmp_path / "run"
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", "2",
           "-m", "fruxel.cli.train", "--config", str(config), "--data", str(data), "--out", str(run),
           "--device", "cpu", "--workers", "1", "--batch-size", "4"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    lines = [line for line in done.stdout.splitlines() if line.startswith("fruxel-train:")]
    assert len(lines) == 1 and "step 4 of 4, 16 samples" in lines[0], done.stdout
    st = read_checkpoint(run / LATEST).state
    assert st["step"] == 4 and st["samples"] == 16
    assert "Traceback" not in done.stderr and "killed by signal" not in done.stderr


# ---------------------------------------------------------------------------------------------- the run folder
def _train(config: Path, data: Path, run: Path, *more: str) -> int:
    return main(["--config", str(config), "--data", str(data), "--out", str(run), "--device", "cpu", "-q", *more])


@pytest.mark.slow
def test_a_new_run_never_replaces_a_run_by_accident(tmp_path: Path, data: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    """A folder that holds a run takes --resume or --overwrite; a plain new run is refused in one line and the
    earlier run's files stay byte for byte; --overwrite replaces them."""
    from fruxel.train.engine.checkpoint import LATEST, read_checkpoint

    config = _write(tmp_path / "c.json", CONFIG)
    run = tmp_path / "run"
    assert _train(config, data, run) == 0
    before = {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()}
    assert _train(config, data, run, "--steps", "2") == 2
    line = _error_line(capsys)
    assert str(run) in line and "holds a run" in line and "--resume" in line and "--overwrite" in line
    assert {p.name: p.read_bytes() for p in run.iterdir() if p.is_file()} == before
    assert _train(config, data, run, "--steps", "2", "--overwrite") == 0
    assert read_checkpoint(run / LATEST).state["step"] == 2
    assert main(["--resume", "--out", str(run), "--overwrite"]) == 2
    assert "--overwrite cannot be given with --resume" in _error_line(capsys)


@pytest.mark.slow
def test_two_runs_in_one_folder_at_once_are_refused(tmp_path: Path, data: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    """A second fruxel-train into a folder where one is training gets one line naming the holder; the first goes
    on undisturbed and finishes."""
    from fruxel.train.engine.checkpoint import LATEST, read_checkpoint

    long = {**CONFIG, "run": {**CONFIG["run"], "steps": 400, "log_every": 50}}
    config = _write(tmp_path / "c.json", long)
    run = tmp_path / "run"
    first = subprocess.Popen([sys.executable, "-m", "fruxel.cli.train", "--config", str(config), "--data", str(data),
                              "--out", str(run), "--device", "cpu", "-q"], stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120
        while not (run / ".lock").exists() or not (run / ".lock").read_text().strip():
            assert first.poll() is None and time.monotonic() < deadline, "the first run did not start"
            time.sleep(0.2)
        assert main(["--config", str(config), "--data", str(data), "--out", str(run), "--device", "cpu",
                     "--overwrite"]) == 2
        line = _error_line(capsys)
        assert "another run is training here" in line and f"process {first.pid}" in line
    finally:
        _, err = first.communicate(timeout=600)
    assert first.returncode == 0, err
    assert read_checkpoint(run / LATEST).state["step"] == 400


@pytest.mark.slow
def test_a_full_disk_at_a_checkpoint_is_one_line_and_the_logs_keep_to_the_checkpoint(tmp_path: Path,
                                                                                    data: Path) -> None:
    """The checkpoint cannot be written (files are limited below its size, as on a full disk): one line naming
    it, exit 2, no temporary file left, and metrics.csv holds no row past the checkpoint the folder has (none)."""
    import resource
    import signal

    config = _write(tmp_path / "c.json", {**CONFIG, "run": {**CONFIG["run"], "checkpoint_every": 2}})
    run = tmp_path / "run"

    def limit() -> None:
        signal.signal(signal.SIGXFSZ, signal.SIG_IGN)  # a write past the limit fails (EFBIG) instead of killing
        resource.setrlimit(resource.RLIMIT_FSIZE, (256 * 1024, 256 * 1024))

    out = subprocess.run([sys.executable, "-m", "fruxel.cli.train", "--config", str(config), "--data", str(data),
                          "--out", str(run), "--device", "cpu", "-q"], capture_output=True, text=True,
                         preexec_fn=limit, timeout=600)
    lines = out.stderr.strip().splitlines()
    assert out.returncode == 2 and len(lines) == 1 and "Traceback" not in out.stderr, out.stderr
    assert f"{run / 'last.pt'}: could not write the checkpoint of step 2" in lines[0]
    names = sorted(p.name for p in run.iterdir())
    assert "last.pt" not in names and not [n for n in names if ".tmp" in n], names
    rows = (run / "metrics.csv").read_text().strip().splitlines()
    assert rows[0].startswith("step") and len(rows) == 1, rows  # the header alone: no step was checkpointed
    assert "curves.png" not in names and "examples.png" not in names


@pytest.mark.slow
def test_what_killed_writers_left_is_cleaned_up(tmp_path: Path, data: Path) -> None:
    """A run killed while it wrote its checkpoint leaves a hidden temporary file beside last.pt: the next run in
    the folder (a resume or an overwrite) removes it."""

    config = _write(tmp_path / "c.json", {**CONFIG, "run": {**CONFIG["run"], "steps": 2}})
    run = tmp_path / "run"
    assert _train(config, data, run) == 0
    # The name the checkpoint writer gives its temporary file (fruxel.io.atomic_path: ".NAME.XXXXXXXXXXXX.tmpSUFFIX"),
    # as a SIGKILL during the write leaves it.
    (run / ".last.pt.0123456789ab.tmp.pt").write_bytes(b"half a checkpoint")
    left = sorted(p.name for p in run.iterdir() if ".tmp" in p.name)
    assert left and left[0].startswith(".last.pt.")
    assert main(["--resume", "--out", str(run), "--device", "cpu", "--steps", "3", "-q"]) == 0
    assert not [p.name for p in run.iterdir() if ".tmp" in p.name]

"""Tests of fruxel.cli.common: the one runner of every command, the shared argparse types, options made from
config dataclasses and the --grid options."""

from __future__ import annotations

import argparse
import ast
import dataclasses
import os
import re
import subprocess
import sys
from pathlib import Path

import pytest

from fruxel.cli.common import (
    EXIT_INTERRUPTED,
    EXIT_USAGE,
    OneLineParser,
    UsageError,
    add_grid_options,
    config_option,
    config_values,
    field_docs,
    field_of_view,
    grid_from_args,
    grid_size,
    image_size,
    positive_float,
    run,
    unit_fraction,
)
from fruxel.errors import FruxelError
from fruxel.grid import FruxelGrid, GridError

ROOT = Path(__file__).resolve().parents[2]
GRID = FruxelGrid(width=32, height=24, depth=16, z_near=0.5, z_far=6.0, hfov=60.0)


# ---------------------------------------------------------------------------------------------------- runner
def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="fruxel-test")
    p.add_argument("--n", type=int, default=1)
    return p


def test_run_returns_the_status_of_the_work() -> None:
    assert run(lambda a: None, _parser(), []) == 0
    assert run(lambda a: a.n, _parser(), ["--n", "3"]) == 3


@pytest.mark.parametrize(("error", "line"), [
    (GridError("z_far must be > z_near,\n  got 2"), "fruxel-test: error: z_far must be > z_near, got 2"),
    (UsageError("--orbit writes a video"), "fruxel-test: error: --orbit writes a video (see --help)"),
    (FileNotFoundError(2, "No such file or directory", "in/x.npz"), "fruxel-test: error: in/x.npz: No such file or "
                                                                    "directory"),
    (PermissionError(13, "Permission denied"), "fruxel-test: error: Permission denied"),
])
def test_known_errors_become_one_line_and_status_2(error: Exception, line: str,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    def work(args: argparse.Namespace) -> None:
        raise error

    assert run(work, _parser(), []) == EXIT_USAGE
    captured = capsys.readouterr()
    assert captured.err == line + "\n" and captured.out == ""


def test_interrupt_is_130(capsys: pytest.CaptureFixture[str]) -> None:
    def work(args: argparse.Namespace) -> None:
        raise KeyboardInterrupt

    assert run(work, _parser(), []) == EXIT_INTERRUPTED
    assert capsys.readouterr().err == "fruxel-test: interrupted\n"


@pytest.mark.parametrize("bug", [ValueError("plain"), TypeError("bug"), KeyError("k")])
def test_bugs_keep_their_traceback(bug: Exception) -> None:
    def work(args: argparse.Namespace) -> None:
        raise bug

    with pytest.raises(type(bug)):
        run(work, _parser(), [])


def _closed_pipe_run(code: str) -> subprocess.CompletedProcess[bytes]:
    """Run ``code`` in a fresh interpreter whose standard output is a pipe nobody reads (its reader already gone, as
    after ``| head`` exits)."""
    read_end, write_end = os.pipe()
    os.close(read_end)
    try:
        return subprocess.run([sys.executable, "-c", code], stdout=write_end, stderr=subprocess.PIPE, timeout=120)
    finally:
        os.close(write_end)


@pytest.mark.parametrize("command", [
    "from fruxel.cli.train import main; sys.exit(main(['--preset', 'tiny', '--print-config']))",
    "from fruxel.cli.render import main; sys.exit(main(['--help']))",
    # Lines printed one by one (the written paths of a command), the last at the interpreter's exit.
    "from fruxel.cli.common import OneLineParser, run\n"
    "sys.exit(run(lambda a: [print(i) for i in range(20000)] and None, OneLineParser(prog='x'), []))",
])
def test_a_closed_standard_output_ends_quietly_with_status_0(command: str) -> None:
    """Like the standard Unix tools: ``fruxel-train --print-config | head`` is no error."""
    out = _closed_pipe_run("import sys\n" + command)
    assert out.returncode == 0 and out.stderr == b"", out.stderr.decode()


def test_a_broken_pipe_elsewhere_is_an_error() -> None:
    """A pipe that breaks other than standard output (an encoder that died) stays an error line."""
    code = ("import sys\nfrom fruxel.cli.common import OneLineParser, run\n"
            "def work(args):\n    raise BrokenPipeError(32, 'Broken pipe')\n"
            "sys.exit(run(work, OneLineParser(prog='fruxel-x'), []))\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert out.returncode == EXIT_USAGE and out.stderr == "fruxel-x: error: Broken pipe\n"


def test_usage_errors_of_the_parser_are_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as e:
        run(lambda a: None, _parser(), ["--n", "x"])
    assert e.value.code == EXIT_USAGE
    err = capsys.readouterr().err.splitlines()
    assert len(err) == 1 and err[0].startswith("fruxel-test: error: argument --n") and err[0].endswith("(see --help)")


def test_every_library_error_is_a_fruxel_error() -> None:
    """Every exception class of the libraries derives from FruxelError, so that the runner reports it as one line
    (the strict archive reader's internal ArchiveError is always turned into a file error naming the file)."""
    internal = {"ArchiveError", "FruxelError"}
    found, bad = [], []
    for folder in ("fruxel", "kernels", "render", "train", "cli"):
        for path in (ROOT / folder).rglob("*.py"):
            for node in ast.walk(ast.parse(path.read_text(), str(path))):
                if not isinstance(node, ast.ClassDef) or node.name in internal:
                    continue
                bases = {b.id for b in node.bases if isinstance(b, ast.Name)}
                if bases & {"ValueError", "RuntimeError", "Exception", "OSError"}:
                    found.append(node.name)
                    if "FruxelError" not in bases:
                        bad.append(f"{path.relative_to(ROOT)}:{node.name}")
    assert len(found) >= 12 and not bad, bad


# ---------------------------------------------------------------------------------------------------- types
def test_image_and_grid_sizes() -> None:
    assert image_size("640x480") == (640, 480) and image_size(" 8 X 6 ") == (8, 6)
    assert grid_size("128") == (128, 128, 128) and grid_size("160x120x64") == (160, 120, 64)
    for bad in ("0x4", "4", "4x", "axb"):
        with pytest.raises(argparse.ArgumentTypeError):
            image_size(bad)
    for bad in ("0", "4x4", "4x4x4x4", "-3", "big"):
        with pytest.raises(argparse.ArgumentTypeError):
            grid_size(bad)
    with pytest.raises(argparse.ArgumentTypeError, match="--z-near, --z-far and --hfov"):
        grid_size("64,48,64,0.5,6,60")


@pytest.mark.parametrize(("parse", "good", "bad", "what"), [
    (unit_fraction, ["1", "0.25", "1e-3"], ["0", "1.5", "-0.1", "nan", "inf", "x"], "a number in (0, 1]"),
    (positive_float, ["5", "0.1", "1e9"], ["0", "-2", "nan", "inf", ""], "a positive number"),
    (field_of_view, ["60", "0.5", "179.9"], ["0", "180", "-10", "nan", "inf", "wide"], "degrees in (0, 180)"),
])
def test_bounded_numbers(parse, good: list[str], bad: list[str], what: str) -> None:
    for text in good:
        assert parse(text) == float(text)
    for text in bad:
        line = rf"^expected {re.escape(what)}, got {re.escape(repr(text))}$"
        with pytest.raises(argparse.ArgumentTypeError, match=line):
            parse(text)


# ---------------------------------------------------------------------------------------------------- dataclasses
@dataclasses.dataclass(frozen=True)
class _Config:
    """A config of the tests."""

    steps: int = 100
    """Optimiser steps to take, ``>= 1`` (see :class:`fruxel.FruxelGrid`, :func:`~fruxel.io.load`)."""
    rate: float | None = None
    """Learning rate; None picks one (100% sure)."""
    mode: str = "fast"
    """How to run."""
    fog: bool = False
    """Depth fog."""
    legend: bool = True
    """Draw the legend."""
    size: tuple[int, int] = (4, 3)
    """Image size."""


def test_field_docs_are_read_from_the_source() -> None:
    docs = field_docs(_Config)
    assert docs["steps"].startswith("Optimiser steps") and set(docs) == {f.name for f in dataclasses.fields(_Config)}


def test_config_options_take_defaults_types_and_help_from_the_dataclass(capsys: pytest.CaptureFixture[str]) -> None:
    p = OneLineParser(prog="x")
    config_option(p, _Config, "steps")
    config_option(p, _Config, "rate")
    config_option(p, _Config(mode="slow"), "mode", "--run-mode", choices=("fast", "slow"))
    config_option(p, _Config, "fog")
    config_option(p, _Config, "legend")
    config_option(p, _Config, "size", type=image_size)
    args = p.parse_args([])
    assert config_values(args, _Config) == {"steps": 100, "rate": None, "mode": "slow", "fog": False, "legend": True,
                                            "size": (4, 3)}
    args = p.parse_args(["--steps", "7", "--rate", "0.5", "--run-mode", "fast", "--fog", "--no-legend", "--size",
                         "8x6"])
    assert _Config(**config_values(args, _Config)) == _Config(7, 0.5, "fast", True, False, (8, 6))
    with pytest.raises(SystemExit):
        p.parse_args(["--steps", "1.5"])
    capsys.readouterr()
    with pytest.raises(SystemExit):
        p.parse_args(["--help"])
    text = " ".join(capsys.readouterr().out.split())
    assert "Optimiser steps to take, >= 1 (see fruxel.FruxelGrid, load). (default: 100)" in text
    assert "None picks one (100% sure)" in text
    # A --no-... flag says first that it turns the setting off, lest its help read as what the flag does.
    assert "--no-legend turn off (on by default): draw the legend." in text
    assert "--fog Depth fog. (default: off)" in text
    assert "How to run. (default: slow)" in text


# ---------------------------------------------------------------------------------------------------- grid
def _grid_parser(size_default: bool) -> argparse.ArgumentParser:
    p = OneLineParser(prog="x")
    add_grid_options(p, GRID, size_default=size_default)
    return p


def _negated_flags(help_text: str) -> dict[str, str]:
    """The --no-... options of a --help text, each with its help on one line."""
    lines = help_text.splitlines()
    found = {}
    for i, line in enumerate(lines):
        m = re.match(r"^  (--no-[-\w]+)(.*)$", line)
        if m:
            parts = [m.group(2)]
            for more in lines[i + 1:]:
                if not more.startswith(" " * 8) or more.strip().startswith("-"):
                    break
                parts.append(more)
            found[m.group(1)] = " ".join(" ".join(parts).split())
    return found


def test_flags_that_turn_a_setting_off_say_so_first(capsys: pytest.CaptureFixture[str]) -> None:
    """``--no-legend  Draw the class legend`` read as what the flag does: every --no-... flag's help says first that
    it turns the setting off (or says "without")."""
    from fruxel.cli import eval as eval_cli
    from fruxel.cli import predict, render, robot, sim, train

    found = []
    for main, argv in ((eval_cli.main, []), (predict.main, []), (render.main, []), (robot.main, []),
                       (train.main, []), (sim.main, ["generate"]), (sim.main, ["preview"])):
        with pytest.raises(SystemExit):
            main([*argv, "--help"])
        for flag, text in _negated_flags(capsys.readouterr().out).items():
            found.append(flag)
            assert text.startswith("turn off (on by default): ") or " without " in f" {text}", (main, flag, text)
    assert {"--no-legend", "--no-flip-average", "--no-augment"} <= set(found)


def test_grid_options_default_to_the_given_grid() -> None:
    p = _grid_parser(True)
    assert grid_from_args(p.parse_args([]), GRID) == GRID
    got = grid_from_args(p.parse_args(["--grid", "8", "--z-far", "9", "--hfov", "75"]), GRID)
    assert got == FruxelGrid(width=8, height=8, depth=8, z_near=0.5, z_far=9.0, hfov=75.0)
    got = grid_from_args(p.parse_args(["--grid", "8x6x4", "--z-near", "1"]), GRID)
    assert (got.width, got.height, got.depth, got.z_near, got.z_far) == (8, 6, 4, 1.0, 6.0)
    with pytest.raises(GridError, match="z_far must be > z_near"):
        grid_from_args(p.parse_args(["--z-near", "9"]), GRID)


def test_grid_without_a_default_size() -> None:
    p = _grid_parser(False)
    assert grid_from_args(p.parse_args([]), GRID, size_default=False) is None
    assert grid_from_args(p.parse_args(["--grid", "32x24x16"]), GRID, size_default=False) == GRID
    with pytest.raises(UsageError, match="--z-far .* give --grid"):
        grid_from_args(p.parse_args(["--z-far", "7"]), GRID, size_default=False)
    assert issubclass(UsageError, FruxelError)


# ---------------------------------------------------------------------------------------------------- outputs
def test_write_outputs_all_or_none(tmp_path: Path) -> None:
    from fruxel.cli.common import OutputError, write_outputs

    a, b = tmp_path / "new" / "deep" / "a.txt", tmp_path / "b.bin"
    b.write_bytes(b"old")

    def fail(tmp: Path) -> None:
        raise OSError(28, "No space left on device", str(tmp))

    with pytest.raises(OutputError, match=f"cannot write {b}: No space left on device$"):
        write_outputs([(a, lambda tmp: tmp.write_text("a")), (b, fail)])
    assert b.read_bytes() == b"old" and sorted(p.name for p in tmp_path.rglob("*")) == ["b.bin"]
    assert write_outputs([(a, lambda tmp: tmp.write_text("a")), (b, lambda tmp: tmp.write_bytes(b"new"))]) == [a, b]
    assert a.read_text() == "a" and b.read_bytes() == b"new"
    with pytest.raises(OutputError, match="is not a folder"):
        write_outputs([(b / "x.txt", lambda tmp: tmp.write_text("x"))])

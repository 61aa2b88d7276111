"""The package builds without setuptools warnings and carries its data files (pyproject.toml's packages and
package data)."""

from __future__ import annotations

import shutil
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
DATA_FILES = ("fruxel/train/data/ssz64.safetensors", "fruxel/train/data/ssz128.safetensors",
              "fruxel/train/data/ssz64-any.safetensors",
              "fruxel/data/sample_room.npz", "fruxel/data/photo.png", "fruxel/data/room.png",
              "fruxel/data/room_truth.npz", "fruxel/data/room_credits.md", "fruxel/kernels/cl/first_hit.cl",
              "fruxel/kernels/cl/ray.h")
"""Files the wheel must hold besides the modules: shipped models, bundled samples, OpenCL sources."""


def _tracked_files() -> list[str]:
    if shutil.which("git") is None or not (ROOT / ".git").exists():
        pytest.skip("needs the git checkout (its tracked files are what a clone builds)")
    out = subprocess.run(["git", "-C", str(ROOT), "ls-files", "-z"], capture_output=True, check=True)
    return [name for name in out.stdout.decode().split("\0") if name]


def test_the_wheel_builds_without_warnings_and_holds_the_data_files(tmp_path: Path) -> None:
    pytest.importorskip("setuptools")
    # A fresh clone's files (no build folders, no caches), with this worktree's pyproject.toml.
    src = tmp_path / "src"
    for name in _tracked_files():
        if (ROOT / name).is_file():
            (src / name).parent.mkdir(parents=True, exist_ok=True)
            shutil.copy(ROOT / name, src / name)
    # Without build isolation: the installed setuptools builds it, with no download.
    out = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-build-isolation", "--no-deps", "-w",
                          str(tmp_path / "dist"), str(src)], capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout + out.stderr
    log = out.stdout + out.stderr
    assert "BuildBackendWarning" not in log and "absent from the `packages` configuration" not in log, log
    (wheel,) = (tmp_path / "dist").glob("fruxel-*.whl")
    names = set(zipfile.ZipFile(wheel).namelist())
    assert not [f for f in DATA_FILES if f not in names], sorted(n for n in names if "/data/" in n)

"""``scripts/setup_env.sh`` (behind ``make env``) when another apt or dpkg holds its lock: it waits up to
``FRUXEL_APT_WAIT`` seconds, then gives up in one line; once the lock is free it goes on.

The script runs for real, with the real apt-get, on a copy of the project whose virtual environment is already
installed (so only its system-package step runs) and an apt of its own: ``APT_CONFIG`` points apt-get at empty
package lists, dpkg status and sources in a temporary folder, so nothing of the machine's apt is read, locked or
changed. The locks are held by this test process with ``fcntl`` locks, as apt and dpkg hold them.
"""

from __future__ import annotations

import fcntl
import hashlib
import os
import shutil
import subprocess
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
WAIT = 3
"""``FRUXEL_APT_WAIT`` of these tests, seconds."""

pytestmark = pytest.mark.skipif(
    not hasattr(os, "geteuid") or os.geteuid() != 0 or shutil.which("apt-get") is None,
    reason="the script installs system packages only as root with apt-get")


@pytest.fixture
def project(tmp_path: Path) -> Path:
    """A copy of the project's set-up files whose .venv counts as installed (its stamp matches)."""
    root = tmp_path / "project"
    (root / "scripts").mkdir(parents=True)
    shutil.copy(ROOT / "scripts" / "setup_env.sh", root / "scripts" / "setup_env.sh")
    for name in ("pyproject.toml", "constraints.txt"):
        shutil.copy(ROOT / name, root / name)
    python = root / ".venv" / "bin" / "python"
    python.parent.mkdir(parents=True)
    python.write_text("#!/bin/sh\nexit 0\n")
    python.chmod(0o755)
    stamp = hashlib.sha256((root / "pyproject.toml").read_bytes() + (root / "constraints.txt").read_bytes())
    (root / ".venv" / ".fruxel-installed").write_text(stamp.hexdigest() + "\n")
    return root


@pytest.fixture
def apt_root(tmp_path: Path) -> Path:
    """An apt of its own: empty lists, dpkg status and sources under one folder (``APT_CONFIG``)."""
    root = tmp_path / "apt"
    for d in ("lists/partial", "dpkg", "cache/archives/partial", "etc/sources.list.d", "etc/apt.conf.d",
              "etc/preferences.d", "log"):
        (root / d).mkdir(parents=True)
    (root / "dpkg" / "status").touch()
    (root / "etc" / "sources.list").touch()
    settings = {"Dir::State::Lists": "lists", "Dir::State::status": "dpkg/status", "Dir::Cache": "cache",
                "Dir::Etc::SourceList": "etc/sources.list", "Dir::Etc::SourceParts": "etc/sources.list.d",
                "Dir::Etc::Parts": "etc/apt.conf.d", "Dir::Etc::PreferencesParts": "etc/preferences.d",
                "Dir::Log": "log"}
    (root / "apt.conf").write_text("".join(f'{k} "{root / v}";\n' for k, v in settings.items()))
    return root


@pytest.fixture
def env(project: Path, apt_root: Path, tmp_path: Path) -> dict[str, str]:
    """The script's environment: its apt, a short wait, and an ldconfig that finds no EGL (so the script installs
    Mesa's EGL with apt-get whatever this machine has)."""
    bin_dir = tmp_path / "bin"
    bin_dir.mkdir()
    (bin_dir / "ldconfig").write_text("#!/bin/sh\nexit 0\n")
    (bin_dir / "ldconfig").chmod(0o755)
    return {**os.environ, "APT_CONFIG": str(apt_root / "apt.conf"), "FRUXEL_APT_WAIT": str(WAIT),
            "PATH": f"{bin_dir}{os.pathsep}{os.environ.get('PATH', '')}"}


class HeldLock:
    """An fcntl lock on ``path`` held by this process (as apt and dpkg lock), until :meth:`release`."""

    def __init__(self, path: Path) -> None:
        self.fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o640)
        fcntl.lockf(self.fd, fcntl.LOCK_EX | fcntl.LOCK_NB)

    def release(self) -> None:
        if self.fd >= 0:
            os.close(self.fd)
            self.fd = -1


@pytest.fixture
def held() -> Iterator[list[HeldLock]]:
    locks: list[HeldLock] = []
    yield locks
    for lock in locks:
        lock.release()


def _run(project: Path, env: dict[str, str]) -> tuple[subprocess.CompletedProcess[str], float]:
    t0 = time.monotonic()
    out = subprocess.run(["bash", str(project / "scripts" / "setup_env.sh")], env=env, capture_output=True,
                         text=True, timeout=120)
    return out, time.monotonic() - t0


def _lines(text: str) -> list[str]:
    return [line for line in text.splitlines() if line.strip()]


@pytest.mark.parametrize("lock", ["lists/lock", "dpkg/lock-frontend"])
def test_a_held_lock_is_waited_for_then_named_in_one_line(lock: str, project: Path, apt_root: Path,
                                                          env: dict[str, str], held: list[HeldLock]) -> None:
    held.append(HeldLock(apt_root / lock))
    out, seconds = _run(project, env)
    assert out.returncode == 100, out
    assert seconds >= WAIT, f"gave up after {seconds:.1f} s, before its {WAIT} s"
    err = _lines(out.stderr)
    assert len(err) == 1, out.stderr
    assert "another apt or dpkg still holds its lock" in err[0] and f"after {WAIT} s" in err[0]
    # apt names the holder of the lists' lock; waiting for dpkg's lock itself, it names only the lock.
    assert f"held by process {os.getpid()}" in err[0] or str(apt_root / lock) in err[0]
    assert "FRUXEL_APT_WAIT" in err[0]
    assert "E: " not in out.stderr, "apt's own lock messages are replaced by the one line"


def test_the_set_up_goes_on_once_the_lock_is_released(project: Path, apt_root: Path, env: dict[str, str],
                                                       held: list[HeldLock]) -> None:
    lock = HeldLock(apt_root / "lists" / "lock")
    held.append(lock)
    threading.Timer(1.0, lock.release).start()
    out, _ = _run(project, {**env, "FRUXEL_APT_WAIT": "60"})
    assert f"waiting up to 60 s for another apt or dpkg to finish (held by process {os.getpid()}" in out.stdout
    # The lists updated, it went on to install; its apt has no packages, so apt-get says so (no lock involved).
    assert "installing Mesa EGL" in out.stdout, out
    assert "still holds its lock" not in out.stderr
    assert "Unable to locate package" in out.stderr and out.returncode == 100

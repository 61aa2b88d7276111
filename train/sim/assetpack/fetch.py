"""Fetching the source packages into the cache folder, without root.

Debian packages: ``apt-get download NAME=VERSION`` (as any user; it needs the package lists of ``apt-get update``)
then ``dpkg-deb -x``. PyPI packages: ``python -m pip download --no-deps NAME==VERSION`` then unzip the wheel. Each
package lands in ``CACHE/<registry>/<name>-<version>/`` (see :attr:`.sources.Package.folder`) through a temporary
folder renamed at the end, so an interrupted fetch leaves nothing half unpacked under that name; a package
already there is not fetched again.
"""

from __future__ import annotations

import subprocess
import sys
import tempfile
import zipfile
from collections.abc import Iterable
from pathlib import Path

from .manifest import AssetPackError
from .sources import Package


def _run(cmd: list[str], cwd: Path, what: str) -> None:
    try:
        r = subprocess.run(cmd, cwd=cwd, capture_output=True, text=True, check=False)
    except FileNotFoundError:
        raise AssetPackError(f"{what}: {cmd[0]} not found (needed to fetch the sources)") from None
    if r.returncode != 0:
        last = (r.stderr.strip() or r.stdout.strip()).splitlines()[-1:] or ["no output"]
        raise AssetPackError(f"{what}: {' '.join(cmd)} failed ({last[0]})")


def _unpack(pkg: Package, work: Path, dest: Path) -> None:
    files = sorted(p for p in work.iterdir() if p.is_file())
    if len(files) != 1:
        raise AssetPackError(f"{pkg.name} {pkg.version}: expected one downloaded file, got {[p.name for p in files]}")
    if pkg.registry == "debian":
        _run(["dpkg-deb", "-x", str(files[0]), str(dest)], work, f"{pkg.name} {pkg.version}")
    else:
        try:
            with zipfile.ZipFile(files[0]) as zf:
                for info in zf.infolist():
                    if info.filename.startswith("/") or ".." in Path(info.filename).parts:
                        raise AssetPackError(f"{files[0]}: member {info.filename!r} leaves the archive")
                zf.extractall(dest)
        except zipfile.BadZipFile as e:
            raise AssetPackError(f"{files[0]}: not a wheel ({e})") from None


def fetch(pkg: Package, cache: Path) -> Path:
    """Fetch and unpack one package into the cache unless it is there; returns its tree.

    Raises:
        AssetPackError: the download or unpacking failed (e.g. the pinned version is no longer served).
    """
    dest = Path(cache).resolve() / pkg.folder
    if dest.is_dir():
        return dest
    dest.parent.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(dir=dest.parent, prefix=f".{dest.name}.") as tmp:
        work = Path(tmp) / "download"
        work.mkdir()
        if pkg.registry == "debian":
            _run(["apt-get", "download", f"{pkg.name}={pkg.version}"], work, f"{pkg.name} {pkg.version}")
        else:
            _run([sys.executable, "-m", "pip", "download", "--no-deps", "--quiet", "--dest", str(work),
                  f"{pkg.name}=={pkg.version}"], work, f"{pkg.name} {pkg.version}")
        tree = Path(tmp) / "tree"
        tree.mkdir()
        _unpack(pkg, work, tree)
        tree.rename(dest)
    return dest


def fetch_all(packages: Iterable[Package], cache: Path, *, offline: bool = False) -> list[Path]:
    """Fetch every package that is not in the cache yet.

    Args:
        packages: the packages.
        cache: the cache folder (created if missing).
        offline: fetch nothing; a missing package is an error.

    Raises:
        AssetPackError: a missing package while ``offline``, or a failed fetch.
    """
    out = []
    for pkg in packages:
        dest = cache / pkg.folder
        if not dest.is_dir() and offline:
            raise AssetPackError(f"{dest}: {pkg.name} {pkg.version} is not in the cache (and fetching is off)")
        out.append(fetch(pkg, cache))
    return out

"""The package layering of conventions section 6, checked on the source and on what imports actually load.

Libraries form one chain, ``fruxel -> kernels -> render -> train``: each imports only the layers before it. The
application layer (``cli/``, installed as ``fruxel.cli``) sits on top and may import any library; no library
imports it. Nothing of an application lives in a library: no argparse anywhere below ``cli/``, and the numpy-only
core holds no fonts, images, reports or benchmark plumbing either.
"""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "warp", "pyopencl", "pyrender", "trimesh", "OpenGL")
CHAIN = ("fruxel", "kernels", "render", "train")
"""The library folders in layer order."""
PACKAGE = {"fruxel": "fruxel", "kernels": "fruxel.kernels", "render": "fruxel.render", "train": "fruxel.train",
           "cli": "fruxel.cli"}
"""Import name of each top-level folder (pyproject.toml's package-dir)."""
APPLICATION = ("argparse", "fruxel.cli")
"""What only the application layer may import."""
CORE_EXTRA = ("torch", "warp", "pyopencl", "pyrender", "PIL", "matplotlib", "tqdm", "imageio")
"""Third-party packages the numpy-only core never imports (trimesh is allowed, lazily, for mesh export)."""


def _imported_modules(folder: str) -> set[tuple[str, str]]:
    """``(file, module)`` for every import statement in a top-level folder's Python files (lazy ones too)."""
    out = set()
    for path in (ROOT / folder).rglob("*.py"):
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.Import):
                out |= {(path.name, a.name) for a in node.names}
            elif isinstance(node, ast.ImportFrom) and node.module and node.level == 0:
                out.add((path.name, node.module))
    return out


def _forbidden(folder: str) -> tuple[str, ...]:
    if folder == "cli":
        return ()
    later = tuple(PACKAGE[f] for f in CHAIN[CHAIN.index(folder) + 1:])
    extra = {"fruxel": CORE_EXTRA, "kernels": ("pyrender", "trimesh")}.get(folder, ())
    return (*later, *APPLICATION, *extra)


@pytest.mark.parametrize("folder", [*CHAIN, "cli"])
def test_folder_imports_respect_layers(folder: str) -> None:
    forbidden = _forbidden(folder)

    def banned(m: str) -> bool:
        # "fruxel" itself is the core, which every layer may import; its sub-packages are matched one by one.
        return any(m == x or m.startswith(x + ".") for x in forbidden if x != "fruxel")

    bad = sorted((f, m) for f, m in _imported_modules(folder) if banned(m))
    assert not bad, f"{folder}/ imports what its layer may not: {bad}"


def test_the_rules_forbid_what_they_should() -> None:
    """The check itself: render may not import train or the CLIs, the core not PIL or argparse."""
    assert "fruxel.train" in _forbidden("render") and "fruxel.cli" in _forbidden("train")
    assert {"PIL", "argparse", "fruxel.kernels"} <= set(_forbidden("fruxel"))
    assert "fruxel.render" not in _forbidden("train") and _forbidden("cli") == ()


def test_importing_the_packages_loads_no_heavy_module() -> None:
    code = (
        "import sys, fruxel, fruxel.kernels, fruxel.render, fruxel.train, fruxel.mesh, fruxel.io;"
        f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "", f"import fruxel.* loaded {loaded}"


def _imports_of(path: Path, package: str) -> set[str]:
    """Every module ``path`` imports (lazy ones too), relative imports resolved against ``package`` (the file's
    own package, e.g. ``fruxel.train.eval``)."""
    out = set()
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            out |= {a.name for a in node.names}
        elif isinstance(node, ast.ImportFrom):
            base = package.split(".")[: len(package.split(".")) - node.level + 1] if node.level else []
            module = ".".join([*base, *([node.module] if node.module else [])])
            out |= {module} | {f"{module}.{a.name}" for a in node.names}
    return out


def test_evaluation_does_not_import_the_training_engine() -> None:
    """The engine evaluates during training through eval/; eval/ (metrics, reports, calibration) stands without
    the engine, and both take their samples from the one data module, fruxel.train.samples."""
    bad = sorted((p.name, m) for p in (ROOT / "train" / "eval").glob("*.py")
                 for m in _imports_of(p, "fruxel.train.eval") if m.startswith("fruxel.train.engine"))
    assert not bad, bad
    # The check itself resolves relative imports: the engine's lazy import of eval/ is seen.
    engine = {m for p in (ROOT / "train" / "engine").glob("*.py") for m in _imports_of(p, "fruxel.train.engine")}
    assert "fruxel.train.eval.evaluate" in engine and "fruxel.train.samples" in engine


MAX_FUNCTION_LINES = 80
"""Longest function (or method) allowed in train/ and cli/, lines from ``def`` to its last line."""


def test_functions_in_train_and_cli_stay_short() -> None:
    long = sorted((str(p.relative_to(ROOT)), n.name, n.end_lineno - n.lineno + 1)
                  for folder in ("train", "cli") for p in (ROOT / folder).rglob("*.py")
                  for n in ast.walk(ast.parse(p.read_text(), str(p)))
                  if isinstance(n, (ast.FunctionDef, ast.AsyncFunctionDef))
                  and n.end_lineno - n.lineno + 1 > MAX_FUNCTION_LINES)
    assert not long, long

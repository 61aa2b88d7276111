"""The package layering of SPEC section 6, checked on the source and on what imports actually load."""

from __future__ import annotations

import ast
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
HEAVY = ("torch", "warp", "pyopencl", "pyrender", "trimesh", "OpenGL")


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


@pytest.mark.parametrize(
    ("folder", "forbidden"),
    [
        # trimesh is allowed in the core, lazily, for mesh export (PLY, GLB) only.
        ("fruxel", ("fruxel.kernels", "fruxel.render", "fruxel.train", "torch", "warp", "pyopencl", "pyrender")),
        ("kernels", ("fruxel.render", "fruxel.train", "pyrender", "trimesh")),
        ("render", ("fruxel.train",)),
        ("train", ()),
    ],
)
def test_folder_imports_respect_layers(folder: str, forbidden: tuple[str, ...]) -> None:
    def banned(m: str) -> bool:
        return any(m == x or m.startswith(x + ".") for x in forbidden)

    bad = sorted((f, m) for f, m in _imported_modules(folder) if banned(m))
    assert not bad, f"{folder}/ imports what its layer may not: {bad}"


def test_importing_the_packages_loads_no_heavy_module() -> None:
    code = (
        "import sys, fruxel, fruxel.kernels, fruxel.render, fruxel.train, fruxel.mesh, fruxel.io;"
        f"print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "", f"import fruxel.* loaded {loaded}"

"""Markdown reports: rewriting one ``## `` section of a file such as BENCHMARKS.md and leaving the others.

Used by the visualisation benchmark (:mod:`fruxel.render.table1`) and the scripts in ``benchmarks/``; each owns
one section of the same file, and several may run one after another (or at once) on it.
"""

from __future__ import annotations

import os
import re
from pathlib import Path

from fruxel.io import atomic_write


def replace_markdown_section(path: str | os.PathLike[str], heading: str, text: str, *,
                             new_file: str = "# Benchmarks\n") -> None:
    """Replace the ``heading`` section of a Markdown file with ``text``, or append it; the other sections stay.

    A section runs from its heading line to the next ``## `` heading (its own ``### `` subsections included) or
    the end of the file. The file is rewritten atomically (:func:`fruxel.io.atomic_write`): several writers keep
    their own sections of one file, and readers never see half of it.

    Args:
        path: the Markdown file; a missing one starts as ``new_file``.
        heading: the section's heading line, e.g. ``"## Kernels"``.
        text: the whole new section, heading line included; one blank line is kept before the next section.
        new_file: the text of a file that does not exist yet (its title).
    """
    target = Path(path)
    old = target.read_text(encoding="utf-8") if target.exists() else new_file
    pattern = re.compile(rf"^{re.escape(heading)}\n.*?(?=^## |\Z)", re.MULTILINE | re.DOTALL)
    block = text.rstrip("\n") + "\n\n"
    new = pattern.sub(lambda _: block, old, count=1) if pattern.search(old) else old.rstrip("\n") + "\n\n" + block
    with atomic_write(target, "w") as f:
        f.write(new.rstrip("\n") + "\n")

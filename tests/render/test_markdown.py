"""Tests of fruxel.render.markdown: one section of a Markdown report rewritten, the others kept."""

from __future__ import annotations

from pathlib import Path

from fruxel.render.markdown import replace_markdown_section


def test_replace_markdown_section(tmp_path: Path) -> None:
    """The section (with its ### subsections) is replaced up to the next ## heading; others stay; a new file gets
    its title; a missing section is appended."""
    md = tmp_path / "B.md"
    replace_markdown_section(md, "## A", "## A\n\nfirst\n", new_file="# T\n")
    assert md.read_text() == "# T\n\n## A\n\nfirst\n"
    md.write_text("# T\n\n## A\n\nold\n\n### sub\n\nold too\n\n## B\n\nkeep\n")
    replace_markdown_section(md, "## A", "## A\n\nnew\n")
    assert md.read_text() == "# T\n\n## A\n\nnew\n\n## B\n\nkeep\n"
    replace_markdown_section(md, "## C", "## C\n\nlast")
    assert md.read_text().endswith("## B\n\nkeep\n\n## C\n\nlast\n")
    assert not list(tmp_path.glob(".*.tmp"))

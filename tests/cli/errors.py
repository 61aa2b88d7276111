"""What every command's bad input must look like, for the CLI tests: one line, ``PROG: error: ...``, exit 2."""

from __future__ import annotations


def error_lines(stderr: str) -> list[str]:
    """The non-blank lines of ``stderr`` other than Warp's note about a missing CUDA driver (CPU-only machines
    print it; it is not the command's)."""
    return [line for line in stderr.splitlines() if line.strip() and "Warp CUDA warning" not in line]


def assert_one_error_line(prog: str, rc: int, stderr: str, *words: str) -> None:
    """Exit status 2 and exactly one line ``PROG: error: ...`` holding every one of ``words``, no traceback."""
    lines = error_lines(stderr)
    assert rc == 2, stderr
    assert len(lines) == 1, stderr
    assert lines[0].startswith(f"{prog}: error: ") and "Traceback" not in stderr
    for w in words:
        assert w in lines[0], lines[0]

"""Bundled data: the procedural sample room (``sample_room.npz``, described by :mod:`fruxel.data.make_sample`)."""

from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent
"""Folder holding the bundled files."""

SAMPLE_ROOM = DATA_DIR / "sample_room.npz"
"""Path of the sample room model (load it with :func:`fruxel.load`)."""

"""Bundled data: the procedural sample room (``sample_room.npz``, described by :mod:`fruxel.data.make_sample`) and
two photos of held-out simulator rooms with their ground truth, the inputs of ``make demo``: a furnished room from
any camera (``room.png``, ``room_truth.npz``, ``room_credits.md``, written by ``scripts/make_room_photo.py``) and
the robot camera's view of a flat room (``photo.png``, ``photo_truth.npz``, written by
``scripts/make_photo.py``)."""

from __future__ import annotations

from pathlib import Path

DATA_DIR = Path(__file__).resolve().parent
"""Folder holding the bundled files."""

SAMPLE_ROOM = DATA_DIR / "sample_room.npz"
"""Path of the sample room model (load it with :func:`fruxel.load`)."""

PHOTO = DATA_DIR / "photo.png"
"""Path of the bundled photo: 512 x 512 RGB, a robot camera's view (horizontal field of view 60 degrees) of a room
of the flat world's test split, which no shipped SSZ model saw in training (ssz64, the robot's model, reads it
best)."""

PHOTO_TRUTH = DATA_DIR / "photo_truth.npz"
"""Path of the photo's ground truth, a fruxel model (64^3 cells, 0.5 to 8 m, 60 degrees) aligned with the photo's
camera (load it with :func:`fruxel.load`)."""

PHOTO_TRUTH_128 = DATA_DIR / "photo_truth128.npz"
"""The same truth on the 128^3 grid of ``train/data/ssz128.safetensors`` (the same frustum)."""

ROOM_PHOTO = DATA_DIR / "room.png"
"""Path of the bundled furnished-room photo: 512 x 512 RGB, a camera of the ``any-camera`` test set (its height,
pitch and roll: ``make demo``'s flags) in a room of its held-out test split, framed to a 60-degree view."""

ROOM_TRUTH = DATA_DIR / "room_truth.npz"
"""Path of the room photo's ground truth: a fruxel model (64^3 cells, 0.5 to 8 m, 60 degrees) with the furnished
rooms' classes (``fruxel.classes.HOME_CLASSES``), aligned with the photo's camera."""

ROOM_CREDITS = DATA_DIR / "room_credits.md"
"""The licence and credit of each pack asset the photo's room holds (every one CC0, CC-BY, MIT or public domain)."""

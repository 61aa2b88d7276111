"""The bundled furnished-room photo (``fruxel/data/room.png``, ``room_truth.npz``, ``room_credits.md``): the
held-out sample ``scripts/make_room_photo.py`` says it is, told to ``make demo`` with its own camera, and only
assets whose licence lets it be committed."""

from __future__ import annotations

import shlex
from pathlib import Path

import numpy as np
import pytest

import fruxel
from fruxel.data import ROOM_CREDITS, ROOM_PHOTO, ROOM_TRUTH
from fruxel.errors import ConfigError
from fruxel.train.model_files import read_model_file
from fruxel.train.predict import load_image

from .conftest import load_script

ROOT = Path(__file__).resolve().parents[2]


def _demo_flags(photo: Path) -> list[str]:
    """The camera options the Makefile's demo recipe gives for ``photo``."""
    line = next(ln for ln in (ROOT / "Makefile").read_text().splitlines() if f"data/{photo.name} " in ln)
    argv = shlex.split(line)
    return [a for i, a in enumerate(argv) for j in (i, i - 1) if argv[j] in ("--pitch", "--roll", "--height")]


def test_room_photo_is_for_the_default_model() -> None:
    """The truth is on the default model's grid with its classes, and the photo is square, as the grid's view."""
    truth = fruxel.load(ROOM_TRUTH)
    config = read_model_file(None).config
    assert truth.grid == config.grid and truth.classes == config.classes
    assert load_image(ROOM_PHOTO).shape == (512, 512, 3)
    assert len(set(np.unique(np.asarray(truth.labels)).tolist())) >= 7  # a room with most classes in view


def test_room_credits_are_committable_licences() -> None:
    from fruxel.train.sim.assetpack.licences import COMMITTABLE

    rows = [r.split("|") for r in ROOM_CREDITS.read_text().splitlines()[2:]]
    assert len(rows) > 10
    assert {r[3].strip() for r in rows} <= set(COMMITTABLE), "a credited asset is not committable"
    assert all(r[4].strip() for r in rows), "an asset without its credit"


def test_bundled_room_photo_is_the_test_set_sample() -> None:
    """The bundled files are the sample the script makes from the asset pack (labels exactly, the image within a
    grey level, the credits as written), and the Makefile tells the model that sample's camera. Needs the pack that
    ``make assets`` builds."""
    from fruxel.train.sim.rooms.library import resolve_pack

    try:
        pack = resolve_pack(None)
    except ConfigError:
        pytest.skip("needs the asset pack (make assets)")
    script = load_script("make_room_photo")
    sample, _, used = script.room_sample(pack)
    assert sample.split == "test" and sample.index == script.INDEX
    assert np.array_equal(fruxel.load(ROOM_TRUTH).labels, sample.labels), "room_truth.npz is stale"
    diff = np.abs(load_image(ROOM_PHOTO).astype(np.int16) - sample.image.astype(np.int16))
    assert diff.mean() < 1.0, "room.png is stale: run python scripts/make_room_photo.py"
    assert ROOM_CREDITS.read_text() == load_script("raytrace_sheet").credits_table(pack, used)
    assert _demo_flags(ROOM_PHOTO) == script.camera_flags(sample), "the Makefile's demo tells another camera"

"""A camera-aware SSZ reads its camera the way geometry says (issue 39): declared higher, the same photo's floor is
predicted farther away. A trained network (tests/data/camera_tiny, made by its make_model.py) on held-out rooms of
the simulator: random weights would show only that the prediction changes, not which way."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("torch_one_thread")

MODEL = Path(__file__).resolve().parents[1] / "data" / "camera_tiny" / "model.safetensors"


def _first_hits(labels: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per column, the first occupied cell's slice and its label (0 where the column is empty): ``(H, W)`` each."""
    occupied = labels != 0
    k = occupied.argmax(axis=0)
    first = np.take_along_axis(labels, k[None], axis=0)[0]
    return k, first


def _samples(config: object, count: int) -> list[object]:
    """``count`` test-split samples of the flat world from any camera, one room each, at the model's grid."""
    from fruxel.train.sim.cameras import camera_named
    from fruxel.train.sim.config import AugmentConfig, ImageConfig, SimConfig
    from fruxel.train.sim.sample import SampleMaker

    sim = SimConfig(grid=config.grid, image=ImageConfig(size=config.image_size[1], augment=AugmentConfig(False)),
                    splits=(("test", 16 * count),), camera=camera_named("any"), world="flat",
                    classes=config.classes)
    with SampleMaker(sim, 0) as maker:
        return [maker.make("test", 16 * n) for n in range(count)]


@pytest.mark.skipif(not MODEL.is_file(), reason="tests/data/camera_tiny/model.safetensors not made")
def test_a_camera_declared_half_a_metre_higher_moves_the_floor_away() -> None:
    from fruxel.train.predict import CameraPrior, load_predictor, prepare_image

    probe = load_predictor(str(MODEL), device="cpu", batch=1)
    config = probe.config
    assert config.reads_camera
    floor = config.classes.names.index("floor")
    shifts = []
    for s in _samples(config, 12):
        rec = s.camera
        image = prepare_image(s.image, config)
        firsts = {}
        for name, height in (("true", float(rec.height)), ("higher", float(rec.height) + 0.5)):
            prior = CameraPrior(pitch=float(rec.pitch), roll=float(rec.roll), height=height)
            predictor = load_predictor(str(MODEL), device="cpu", batch=1, camera=prior)
            (logits,) = predictor.predict([image])
            firsts[name] = _first_hits(logits.argmax(0).numpy())
        both = (firsts["true"][1] == floor) & (firsts["higher"][1] == floor)
        if both.sum() >= 5:
            shifts.append(float((firsts["higher"][0][both] - firsts["true"][0][both]).mean()))
    assert len(shifts) >= 3, f"too few samples with floor columns in both predictions: {shifts}"
    # The floor 0.5 m lower under the camera lies farther along every downward ray: where both predictions see
    # floor, its first cells move to later slices, in every sample (the grid's slices are 23 cm deep here; the
    # tiny model is weak, so the columns that see floor under both heights are few, and the samples with some).
    assert min(shifts) > 1.0, shifts

"""SSZ that reads the camera (``SSZConfig.camera_inputs``, issue 39): the conditioning changes the prediction where
it should, "unknown" runs, training withholds pieces at random, the simulator's angle conventions, evaluation with
the pose given or not, and a conditioned model through the shipped-file format."""

from __future__ import annotations

import dataclasses
import math
import tempfile
from pathlib import Path

import numpy as np
import pytest

torch = pytest.importorskip("torch")
pytestmark = pytest.mark.usefixtures("torch_one_thread")

from fruxel.errors import ConfigError  # noqa: E402
from fruxel.train.config import DataConfig  # noqa: E402
from fruxel.train.engine.data import ReplayBuffer, camera_with_dropout  # noqa: E402
from fruxel.train.eval.evaluate import evaluate_predictions, model_predict  # noqa: E402
from fruxel.train.models.conditioning import CameraInput  # noqa: E402
from fruxel.train.predict import CameraPrior, Predictor  # noqa: E402
from fruxel.train.rules import InferenceRules, predict_logits  # noqa: E402

from .test_blocks import small_config  # noqa: E402


def _net(camera: bool = True, seed: int = 0) -> tuple[object, torch.nn.Module]:
    config = small_config(camera_inputs=camera)
    torch.manual_seed(seed)
    return config, config.build().eval()


def _image(config: object, seed: int = 1) -> torch.Tensor:
    return torch.rand(1, 3, *config.image_size, generator=torch.Generator().manual_seed(seed))


def _camera(pitch: float, roll: float, height: float | None) -> CameraInput:
    return CameraPrior(pitch=pitch, roll=roll, height=height).camera_input(1)


@torch.no_grad()
def test_height_and_gravity_change_the_logits_and_unknown_runs() -> None:
    config, net = _net()
    image = _image(config)
    low, high = (net(image, _camera(10.0, 0.0, h)).logits for h in (1.0, 1.5))
    assert not torch.allclose(low, high, atol=1e-4)
    unknown = net(image).logits
    assert torch.equal(unknown, net(image, CameraInput.unknown(1)).logits)
    assert not torch.allclose(unknown, low, atol=1e-4)
    assert torch.isfinite(unknown).all()
    # Gravity alone differs from gravity and height, and the pitch matters.
    alone = net(image, _camera(10.0, 0.0, None)).logits
    assert not torch.allclose(alone, low, atol=1e-4)
    assert not torch.allclose(net(image, _camera(30.0, 0.0, 1.0)).logits, low, atol=1e-4)


@torch.no_grad()
def test_height_without_gravity_is_unknown() -> None:
    """A height means nothing without gravity: the conditioning ignores it there."""
    config, net = _net()
    image = _image(config)
    lone = CameraInput.of([[0.0, 1.0, 0.0]], [1.7], [[0, 1]])
    assert torch.equal(net(image, lone).logits, net(image).logits)


def test_a_nan_piece_is_unknown_whatever_the_flags_say() -> None:
    """A data folder's sample that gives no gravity or height holds NaN there (fruxel.train.folder): the camera
    input is then zero with flag 0, never NaN, so one such sample cannot poison a batch's loss."""
    nan = float("nan")
    camera = CameraInput.of([[0.0, 1.0, 0.0], [nan, nan, nan], [0.0, 1.0, 0.0]], [1.2, 1.3, nan],
                            [[1, 1], [1, 1], [1, 1]])
    assert torch.equal(camera.known, torch.tensor([[1.0, 1.0], [0.0, 1.0], [1.0, 0.0]]))
    assert torch.isfinite(camera.gravity).all() and torch.isfinite(camera.height).all()
    assert camera.gravity[1].abs().sum() == 0 and camera.height[2] == 0
    config, net = _net()
    image = _image(config).repeat(3, 1, 1, 1)
    assert torch.isfinite(net(image, camera).logits).all()


@torch.no_grad()
def test_unconditioned_network_has_no_camera_weights_and_ignores_a_camera() -> None:
    config, net = _net(camera=False)
    assert not config.reads_camera
    assert not any("camera" in k for k in net.state_dict())
    image = _image(config)
    assert torch.equal(net(image).logits, net(image, _camera(10.0, 0.0, 1.0)).logits)


def test_config_checks_camera_fields() -> None:
    with pytest.raises(ConfigError, match="model.camera_inputs"):
        small_config(camera_inputs=1)
    for bad in ((0.5,), (0.5, 1.5), (True, 0.1)):
        with pytest.raises(ConfigError, match="data.camera_dropout"):
            DataConfig(camera_dropout=bad)


@pytest.mark.parametrize("pitch, roll", [(0.0, 0.0), (25.0, 0.0), (-15.0, 8.0), (35.0, -10.0)])
def test_prior_gravity_follows_the_simulator_convention(pitch: float, roll: float) -> None:
    """``g = (sin r cos p, cos r cos p, sin p)`` (train/sim/cameras.py): pitch positive looking down, roll positive
    clockwise from behind (right side down, so gravity leans to +x)."""
    p, r = math.radians(pitch), math.radians(roll)
    want = [math.sin(r) * math.cos(p), math.cos(r) * math.cos(p), math.sin(p)]
    np.testing.assert_allclose(CameraPrior(pitch=pitch, roll=roll).gravity(), want, atol=1e-12)


def test_prior_checks_its_values() -> None:
    assert CameraPrior().gravity() is None
    np.testing.assert_allclose(CameraPrior(roll=0.0).gravity(), [0.0, 1.0, 0.0], atol=1e-12)
    for kw, field in (({"pitch": 95.0}, "pitch"), ({"roll": float("nan")}, "roll"), ({"pitch": 0.0, "height": 0.0},
                                                                                      "height")):
        with pytest.raises(ConfigError, match=field):
            CameraPrior(**kw)
    with pytest.raises(ConfigError, match="height needs"):
        CameraPrior(height=1.2)


def test_dropout_gives_known_and_unknown_rows() -> None:
    n = 64
    g = np.tile([0.0, 0.98, 0.2], (n, 1))
    record = {"gravity": torch.from_numpy(g), "height": torch.full((n,), 1.3, dtype=torch.float64)}
    cam = camera_with_dropout(record, (0.4, 0.4), np.random.default_rng(0), "cpu")
    k = cam.known.numpy()
    both, gravity_only, none = ((k == v).all(1).sum() for v in ([1, 1], [1, 0], [0, 0]))
    assert both and gravity_only and none and both + gravity_only + none == n
    assert (cam.gravity.numpy()[k[:, 0] == 0] == 0).all() and (cam.height.numpy()[k[:, 1] == 0] == 0).all()
    np.testing.assert_allclose(cam.height.numpy()[k[:, 1] == 1], 1.3)
    again = camera_with_dropout(record, (0.4, 0.4), np.random.default_rng(0), "cpu")
    assert torch.equal(again.known, cam.known)
    assert camera_with_dropout(record, (0.0, 0.0), np.random.default_rng(1), "cpu").known.all()
    assert not camera_with_dropout(record, (1.0, 0.0), np.random.default_rng(1), "cpu").known.any()


def test_replay_buffer_keeps_cameras() -> None:
    buf = ReplayBuffer(4, (2, 2, 3), (2, 2, 2), torch.device("cpu"), 0)
    batch = {"image": torch.zeros(2, 2, 2, 3, dtype=torch.uint8), "labels": torch.zeros(2, 2, 2, 2, dtype=torch.uint8),
             "camera": {"gravity": torch.tensor([[0.0, 1.0, 0.0], [0.0, 1.0, 0.0]], dtype=torch.float64),
                        "height": torch.tensor([0.7, 0.7], dtype=torch.float64)}}
    buf.add(batch)
    drawn = buf.draw(3)
    assert drawn["camera"]["height"].tolist() == [0.7] * 3
    assert drawn["camera"]["gravity"][:, 1].tolist() == [1.0] * 3


@torch.no_grad()
def test_mirror_average_mirrors_the_camera() -> None:
    """With ``flip_average`` a rolled camera's answer, mirrored, is the mirrored photo's with the roll reversed."""
    config, net = _net()
    image = _image(config)
    rules = InferenceRules(flip_average=True)
    a = predict_logits(net, image, rules, camera=_camera(10.0, 8.0, 1.0), batched_flip=False)
    b = predict_logits(net, image.flip(-1), rules, camera=_camera(10.0, -8.0, 1.0), batched_flip=True)
    torch.testing.assert_close(a, b.flip(-1), atol=1e-4, rtol=1e-4)


@torch.no_grad()
def test_predictor_passes_its_camera() -> None:
    config, net = _net()
    image = _image(config)
    prior = CameraPrior(pitch=10.0, height=1.0)
    got = Predictor(net, config, "cpu", camera=prior).logits(image)
    assert torch.equal(got, net(image, prior.camera_input(1)).logits)
    other = Predictor(net, config, "cpu", camera=CameraPrior(pitch=10.0, height=1.5)).logits(image)
    assert not torch.allclose(got, other, atol=1e-4)
    assert torch.equal(Predictor(net, config, "cpu").logits(image), net(image).logits)


@torch.no_grad()
def test_evaluation_tells_the_recorded_pose_or_nothing() -> None:
    config, net = _net()
    image = _image(config)
    labels = torch.zeros(1, *config.grid.shape, dtype=torch.uint8)
    record = {"gravity": torch.tensor([[0.0, math.cos(0.2), math.sin(0.2)]], dtype=torch.float64),
              "height": torch.tensor([1.0], dtype=torch.float64)}
    seen: dict[str, torch.Tensor] = {}

    def keeping(name: str, known: tuple[str, ...]) -> object:
        rule = model_predict(net, InferenceRules(), camera_known=known)

        def predict(image: torch.Tensor, truth: torch.Tensor, camera: object = None) -> torch.Tensor:
            seen[name] = rule(image, truth, camera)
            return seen[name]

        predict.reads_camera = True
        return predict

    evaluate_predictions({"given": keeping("given", ("gravity", "height")), "none": keeping("none", ())},
                         [(image, labels, record)], config.grid, config.classes, device=torch.device("cpu"),
                         novel=False)
    given = net(image, CameraInput.from_record(record)).logits.argmax(1)
    assert torch.equal(seen["given"], given.to(torch.uint8))
    assert torch.equal(seen["none"], net(image).logits.argmax(1).to(torch.uint8))


def test_conditioned_model_saves_and_loads_with_its_config() -> None:
    from fruxel.train.model_files import load_model, save_model

    config, net = _net()
    image = _image(config)
    with tempfile.TemporaryDirectory() as d:
        path = Path(d) / "cam.safetensors"
        save_model(path, net, config, half=False)
        m = load_model(str(path), device="cpu")
    assert m.config.camera_inputs and m.config == config
    cam = _camera(12.0, 0.0, 1.1)
    with torch.no_grad():
        assert torch.equal(m.network.eval()(image, cam).logits, net(image, cam).logits)


def test_a_few_real_training_steps_with_cameras(tmp_path: Path) -> None:
    """The engine trains a conditioned model on the simulator's samples (cameras withheld at random, through the
    replay buffer), and the trained network still tells a 1.0 m camera from a 1.5 m one."""
    from fruxel.train.engine.trainer import Trainer
    from fruxel.train.model_files import load_model

    from .test_engine import tiny

    c = tiny({"model": {"camera_inputs": True}, "data": {"camera_dropout": [0.5, 0.5], "replay": 4},
              "run": {"steps": 3}})
    result = Trainer(c, tmp_path / "run", progress=False).fit()
    assert result.step == 3 and math.isfinite(result.losses["total"])
    m = load_model(str(tmp_path / "run" / "model.safetensors"), device="cpu")
    net = m.network.eval()
    image = _image(m.config)
    with torch.no_grad():
        low, high = (net(image, _camera(10.0, 0.0, h)).logits for h in (1.0, 1.5))
    assert not torch.allclose(low, high, atol=1e-5)
    assert dataclasses.asdict(m.config)["camera_inputs"] is True


@torch.no_grad()
def test_refined_network_reads_the_camera_below_its_level() -> None:
    config = small_config(camera_inputs=True, refine=4)
    torch.manual_seed(0)
    net = config.build().eval()
    image = _image(config)
    low, high = (net(image, _camera(10.0, 0.0, h)).logits for h in (1.0, 1.5))
    assert low.shape[2:] == config.grid.shape and not torch.allclose(low, high, atol=1e-4)


@torch.no_grad()
def test_calibration_tells_the_recorded_pose() -> None:
    """The rules' sweep counts what evaluation with the pose given counts."""
    from fruxel.train.eval.calibrate import sweep_rules

    config, net = _net()
    image = _image(config)
    record = {"gravity": torch.tensor([[0.0, math.cos(0.3), math.sin(0.3)]], dtype=torch.float64),
              "height": torch.tensor([0.8], dtype=torch.float64)}
    labels = net(image, CameraInput.from_record(record)).logits.argmax(1).to(torch.uint8)  # its own answer: IoU 100
    accs = sweep_rules(net, [(image, labels, record)], [0.0], [0.5], config.num_classes, base=InferenceRules(),
                       device=torch.device("cpu"))
    assert next(iter(accs.values())).summary()["miou"] == pytest.approx(100.0)
    blind = sweep_rules(net, [(image, labels)], [0.0], [0.5], config.num_classes, base=InferenceRules(),
                        device=torch.device("cpu"))
    assert next(iter(blind.values())).summary()["miou"] < 99.0


@torch.no_grad()
def test_the_shipped_camera_aware_model_sees_the_floor_farther_from_a_higher_camera(tiny_pack: Path) -> None:
    """ssz64-any on a furnished room of the any-camera test set (the tiny pack's, no augmentation), told the
    sample's own pitch, roll and height, then a height 0.5 m more: the floor it sees in the image's bottom rows lies
    farther by about the heights' ratio (a ray meets the floor plane at a distance proportional to the camera's
    height), so the model reads the height as geometry. The furnished rooms are where it learnt cameras of every
    height; the flat world of the robot's mount (the bundled photo) it only ever saw from 1.0 m, and since any7
    it reads that height from the look alone."""
    from fruxel.train import samples
    from fruxel.train.predict import load_predictor, prepare_image
    from fruxel.train.sim.sample import SampleMaker

    config = load_predictor("ssz64-any", device="cpu").config
    source = samples.SampleSource(seed=0, assets=str(tiny_pack), test_set="any-camera", augment=False)
    with SampleMaker(samples.sim_config(config, source, (("test", 1),)), 0, backend="warp-cpu") as maker:
        s = maker.make("test", 0)
    c, g = s.camera, config.grid
    depths = []
    for height in (c.height, c.height + 0.5):
        p = load_predictor("ssz64-any", device="cpu", camera=CameraPrior(pitch=c.pitch, roll=c.roll, height=height))
        labels = next(iter(p.predict([prepare_image(s.image, p.config)]))).argmax(0).numpy()
        first = (labels != 0).argmax(axis=0)[-16:]  # (16, W): the first occupied slice of the bottom rows' columns
        floor = np.take_along_axis(labels[:, -16:], first[None], 0)[0] == p.config.classes.names.index("floor")
        # enough floor columns for their mean depth to mean something (the shipped weights find about 300 of 1,024)
        assert floor.sum() >= 24, f"height {height:.2f}: {floor.sum()} floor columns in the bottom rows"
        depths.append(float((g.z_near + (first[floor] + 0.5) * (g.z_far - g.z_near) / g.depth).mean()))
    expected = (c.height + 0.5) / c.height
    assert 0.85 * expected < depths[1] / depths[0] < 1.15 * expected, (depths, expected)


def _floor_rows(image: np.ndarray, camera: CameraPrior) -> tuple[np.ndarray, np.ndarray]:
    """ssz64-any's own-view floor of ``image`` told ``camera``: ``(H, W)`` bool, the columns whose first occupied
    cell is floor; and ``(H, W)`` float64, each column's ray's elevation above the horizontal that the camera's
    gravity implies, degrees (the grid frame is the camera's, OpenCV axes)."""
    from fruxel.train.eval.metrics import first_surface
    from fruxel.train.predict import load_predictor, prepare_image

    p = load_predictor("ssz64-any", device="cpu", camera=camera)
    labels = next(iter(p.predict([prepare_image(image, p.config)]))).argmax(0)
    floor = first_surface(labels[None])[0].numpy() == p.config.classes.names.index("floor")
    rays = p.config.grid.cell_centres()[0]
    rays = rays / np.linalg.norm(rays, axis=-1, keepdims=True)
    return floor, np.degrees(np.arcsin(rays @ -camera.gravity()))


@pytest.mark.parametrize("world", ["flat, the bundled photo", "furnished, the tiny pack"])
def test_the_camera_aware_model_puts_floor_in_the_bottom_rows_and_none_above_the_horizon(world: str,
                                                                                         tiny_pack: Path) -> None:
    """Issue 39's test of a photo told its pitch: floor in the bottom rows, none above the horizon line that the
    pitch implies (a floor cannot be seen looking up). On two photos with a known camera: the bundled flat-world
    photo (the robot's mount, 10 degrees down, 1.0 m) and a furnished room of the tiny pack's any-camera test set
    (the bundled room photo's pack is not in a clone)."""
    from fruxel.data import PHOTO
    from fruxel.train import samples
    from fruxel.train.predict import load_image, load_predictor
    from fruxel.train.sim.sample import SampleMaker

    if world.startswith("flat"):
        image, camera = load_image(PHOTO), CameraPrior(pitch=10.0, roll=0.0, height=1.0)
    else:
        config = load_predictor("ssz64-any", device="cpu").config
        source = samples.SampleSource(seed=0, assets=str(tiny_pack), test_set="any-camera", augment=False)
        with SampleMaker(samples.sim_config(config, source, (("test", 1),)), 0, backend="warp-cpu") as maker:
            s = maker.make("test", 0)
        image, camera = s.image, CameraPrior(pitch=s.camera.pitch, roll=s.camera.roll, height=s.camera.height)
    floor, elevation = _floor_rows(image, camera)
    assert floor[-16:].sum() >= 64, f"{floor[-16:].sum()} floor columns in the bottom 16 rows"
    assert not (floor & (elevation > 0)).any(), f"floor at up to {elevation[floor].max():.1f} degrees above"

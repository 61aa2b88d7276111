"""The three held-out test sets of the simulator (issue 38, item 5), defined once as named simulator configs.

=========================== ============================== ====================================================
name                        camera                         world and assets
=========================== ============================== ====================================================
``any-camera``              any camera (:data:`ANY_CAMERA`) the room world, training assets
``any-camera-test-assets``  any camera                     the room world, held-out test assets (never trained on)
``robot``                   the robot's own mount           the old flat style: the samples of earlier reports
=========================== ============================== ====================================================

A test set turns the config that would make a model's samples (its grid, classes and image size, the evaluation's
augmentation and split: :func:`fruxel.train.samples.sim_config`) into the test set's config (:meth:`TestSet.config`);
the rooms come from the evaluation's seed and split as always (``test``: seeds that training never uses). The
``robot`` set leaves that config as it is, so its samples are exactly those earlier reports were measured on.

The camera side is defined here. The world and asset side (``SimConfig.world``, ``"flat"`` or ``"home"``, and the
home world's choice of held-out assets) comes with the room generator (branch ``rooms38``): :func:`_world` is the
one place where it is connected, and :data:`ASSET_SIDE_CONNECTED` says whether it is. Until then the two sets of
the room world are refused by :meth:`TestSet.config`, and their camera side alone is had with
``camera_only=True`` (in the flat world).
"""

from __future__ import annotations

from dataclasses import dataclass

from fruxel.errors import ConfigError

from .cameras import ANY_CAMERA, ROBOT_CAMERA, CameraConfig
from .config import SimConfig

ASSET_SIDE_CONNECTED = False
"""Whether :func:`_world` applies the world and the asset split (True once the room generator is merged)."""


@dataclass(frozen=True)
class EvaluationSet:
    """One held-out test set (module docstring)."""

    name: str
    """Its name, e.g. ``"any-camera"``."""
    description: str
    """What it is, in words (for reports)."""
    camera: CameraConfig
    """The cameras its samples take."""
    world: str
    """``"home"`` (the room world) or ``"flat"`` (the old flat style)."""
    assets: str | None
    """The asset split its rooms are furnished from: ``"train"`` or ``"test"`` (held out); None for the flat
    world, which uses no assets."""

    def config(self, base: SimConfig, *, camera_only: bool = False) -> SimConfig:
        """The test set's config made from ``base`` (a model's sample config: grid, classes, image size, splits).

        Args:
            base: the config to start from (its camera, and world where there is one, are replaced).
            camera_only: apply the camera alone and keep ``base``'s world (for evaluating the cameras before the
                room world is connected; not the test set itself).

        Raises:
            ConfigError: a set of the room world while the world side is not connected (:data:`ASSET_SIDE_CONNECTED`).
        """
        config = base.replace(camera=self.camera)
        return config if camera_only else _world(config, self)


TEST_SETS: dict[str, EvaluationSet] = {s.name: s for s in (
    EvaluationSet("any-camera", "random cameras (0.3 to 1.9 m, pitch -20 to 40, roll within 10, 50 to 80 degrees "
                  "across) in rooms furnished from the training assets", ANY_CAMERA, "home", "train"),
    EvaluationSet("any-camera-test-assets", "random cameras in rooms furnished from held-out test assets, never "
                  "seen in training", ANY_CAMERA, "home", "test"),
    EvaluationSet("robot", "the robot's own mount (1.0 m, 10 degrees down) in the old flat style, as in earlier "
                  "reports", ROBOT_CAMERA, "flat", None),
)}
"""The test sets by name, in report order."""


def test_set(name: str) -> EvaluationSet:
    """The test set called ``name``.

    Raises:
        ConfigError: no such test set (the message lists them).
    """
    if name not in TEST_SETS:
        raise ConfigError(f"unknown test set {name!r}; test sets are {list(TEST_SETS)}")
    return TEST_SETS[name]


def _world(config: SimConfig, test_set: EvaluationSet) -> SimConfig:
    """``config`` in the test set's world, furnished from its asset split.

    TO CONNECT (lead, when merging rooms38): set ``SimConfig.world`` to ``test_set.world`` and, for the home world,
    choose the held-out assets when ``test_set.assets == "test"`` (``SimConfig.home``'s choice), training assets
    otherwise; then set :data:`ASSET_SIDE_CONNECTED`, which runs ``test_test_sets_world_and_assets`` of
    ``tests/train/test_cameras.py`` (its asset check is to be written then). The flat world is today's only world,
    so the ``robot`` set needs nothing.
    """
    if test_set.world == "flat":
        return config
    raise ConfigError(f"test set {test_set.name!r} needs the room world with {test_set.assets} assets, which this "
                      "fruxel does not have yet (the room generator is not merged); camera_only=True gives its cameras "
                      "in the flat world")

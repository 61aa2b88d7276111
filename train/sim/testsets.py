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

The ``robot`` set is the flat world drawn by its own renderer (``pyrender``) from the robot's mount; the two sets of
the room world are furnished rooms drawn by their renderer (``raytrace``), whose test rooms take their meshes,
textures and pictures from the pack split the set names (``HomeConfig.test_assets``). A room-world set needs a model
whose classes include ``ceiling`` and ``object`` (:data:`fruxel.classes.HOME_CLASSES`); the config refuses others in
one line.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

from fruxel.classes import ClassTable
from fruxel.errors import ConfigError

from .cameras import ANY_CAMERA, ROBOT_CAMERA, CameraConfig
from .config import WORLD_RENDERERS, SimConfig


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
            camera_only: apply the camera alone and keep ``base``'s world, renderer and assets (the cameras of the
                set in another world; not the test set itself).

        Raises:
            ConfigError: a set of the room world for classes without ``ceiling`` and ``object``.
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


def default_test_set(classes: ClassTable) -> str:
    """The test set a model is evaluated and calibrated on when none is named: ``"any-camera"`` for a model that
    labels the room world's classes (it learnt the furnished rooms), else ``""``: the model's own stream, the flat
    world from the robot's mount (the samples of earlier reports)."""
    from .rooms import CLASS_NAMES

    return "any-camera" if all(n in classes.names for n in CLASS_NAMES) else ""


def _world(config: SimConfig, test_set: EvaluationSet) -> SimConfig:
    """``config`` in the test set's world, drawn by that world's renderer, its test rooms furnished from the set's
    asset split (the flat world has no assets)."""
    changes: dict = {"world": test_set.world, "renderer": WORLD_RENDERERS[test_set.world]}
    if test_set.assets is not None:
        changes["home"] = dataclasses.replace(config.home, test_assets=test_set.assets)
    try:
        return config.replace(**changes)
    except ConfigError as e:
        raise ConfigError(f"test set {test_set.name!r}: {e}") from None

"""The simulator's renderer seam: what draws a sample's camera image, and the registry that names renderers.

A renderer turns a room (:class:`~.scene.Scene`) and a camera pose into the robot camera's image; the labels come
from the room's solids by ``fruxelize`` whatever the renderer. :class:`~.sample.SampleMaker` makes the renderer
named by :attr:`SimConfig.renderer <.config.SimConfig.renderer>` (:func:`make_renderer`), so a data set's images
come from the renderer its config names, and the config (recorded in its manifest) says which.

Protocol (:class:`Renderer`)
    A renderer is made by its factory from the data set's :class:`~.config.SimConfig`, ``factory(config)``, or
    ``factory(config, device=device)`` when the factory takes a ``device`` argument and the process asks for a
    device (a training rank's data workers draw on that rank's GPU: the Warp device name ``"cuda:N"`` or
    ``"cpu"``); it is then used as

    * ``set_scene(scene)``: the room to draw, its objects (meshes in the world frame, z up, metres, with their
      colours and PBR factors) and lights; :class:`~.sample.SampleMaker` calls it before every ``render``, so
      setting the room already set should cost nothing;
    * ``render(pose, rng)``, once per sample: ``pose`` is the ``(4, 4)`` float64 camera-to-world transform of the
      robot camera (OpenCV camera axes: x right, y down, z forward; world frame z up, metres), ``rng`` the
      sample's augmentation generator (:func:`~.config.augment_rng`), or None for an image without augmentation.
      It returns an ``(S * H / W, S, 3)`` uint8 RGB array (``config.image_height``, ``config.image_width``): the
      camera of :meth:`SimConfig.image_camera <.config.SimConfig.image_camera>`, in which pixel ``(x, y)`` covers
      ``[x, x + 1) x [y, y + 1)`` of :meth:`fruxel.Camera.project`, so the image lines up with the grid;
    * ``render(pose, rng, camera=camera)``, optional: the image of another camera, a :class:`fruxel.Camera` whose
      intrinsics and image size are drawn with (its own pose is ignored: ``pose`` places it), as an
      ``(camera.height, camera.width, 3)`` uint8 RGB array with the same pixel convention; ``camera=None`` is the
      call above. The simulator asks for it when ``SimConfig.camera`` draws fields of view other than the grid's
      (:mod:`.cameras` renders those at their own field of view and frames them onto the grid's view). A renderer
      without the ``camera`` argument still serves every config whose cameras all render the grid's view (the
      robot's, :data:`~.cameras.ROBOT_CAMERA`), and is refused with one clear error for the others
      (:func:`takes_camera`);
    * ``close()``: frees what it holds (idempotent).

    The image must be a function of the config, the room, the pose and the generator's state alone (the seed rule
    of :mod:`.config` makes every sample reproducible, in any process and any order): a renderer keeps no state
    that one ``render`` passes to the next, and one that augments draws from ``rng`` only. One renderer serves
    one process (an OpenGL or CUDA context does not cross ``fork``); the generator and the data workers make
    their own.

Registry
    :data:`RENDERERS` maps a name to a factory: a class (or any callable) taking the config, or the
    ``"module:attribute"`` path of one, imported when a renderer is first made, so that naming a renderer in a
    config imports nothing (``fruxel-sim --help`` stays instant; a config is checked without pyrender).
    ``"pyrender"`` (:class:`~.images.SceneRenderer`, offscreen OpenGL with PBR materials) is the default;
    ``"raytrace"`` (:class:`~.raytrace.renderer.RaytraceRenderer`, NVIDIA Warp, textures, soft shadows, a camera
    response) draws rooms like photographs.

Adding a renderer
    Write one class with the three methods above and an ``__init__(self, config)``, and register it: in this
    package, one line in :data:`RENDERERS`; elsewhere, ``register_renderer("name", MyRenderer)`` before the
    config naming it is made. :func:`~.writer.generate` hands its worker processes the registered factory of the
    config's renderer, so a class registered at run time works with several workers too (it must be importable by
    its module and name, as pickle requires); other spawned processes, such as the training engine's data workers,
    know the renderers of :data:`RENDERERS` and those that the modules they import register.
"""

from __future__ import annotations

import importlib
import inspect
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, Protocol, runtime_checkable

import numpy as np

from fruxel.errors import ConfigError

if TYPE_CHECKING:
    from .config import SimConfig
    from .scene import Scene

DEFAULT_RENDERER = "pyrender"
"""The renderer of every data set made before renderers had names, and of a config that names none."""


@runtime_checkable
class Renderer(Protocol):
    """Draws the robot camera's images of one room after another (see the module docstring)."""

    def set_scene(self, scene: Scene) -> None:
        """Make ``scene`` the room that :meth:`render` draws."""

    def render(self, pose: np.ndarray, rng: np.random.Generator | None) -> np.ndarray:
        """The ``(S * H / W, S, 3)`` uint8 RGB image of the current room from camera-to-world ``pose``
        (``(4, 4)``, OpenCV axes, world frame z up, metres), augmented with ``rng`` (None: no augmentation).

        A renderer that draws other cameras takes a third argument, ``camera: fruxel.Camera | None = None`` (the
        module docstring), and returns ``(camera.height, camera.width, 3)`` then."""

    def close(self) -> None:
        """Free what the renderer holds (idempotent)."""


RendererFactory = Callable[["SimConfig"], Renderer]
"""What makes a renderer: called with the data set's config (typically the renderer's class)."""

RENDERERS: dict[str, RendererFactory | str] = {
    DEFAULT_RENDERER: "fruxel.train.sim.images:SceneRenderer",
    "raytrace": "fruxel.train.sim.raytrace.renderer:RaytraceRenderer",
}
"""The renderers by name: a factory, or the ``"module:attribute"`` path of one (imported when first used)."""

_NAME_CHARS = set("abcdefghijklmnopqrstuvwxyz0123456789_-")


def register_renderer(name: str, factory: RendererFactory | str) -> None:
    """Make ``factory`` the renderer called ``name`` in this process.

    Args:
        name: 1-32 lower-case letters, digits, ``_`` or ``-``, not a name already registered.
        factory: a class (or callable) taking the :class:`~.config.SimConfig` and returning a :class:`Renderer`,
            or its ``"module:attribute"`` path.

    Raises:
        ConfigError: a malformed or taken name, or a factory that is neither callable nor a path.
    """
    if not isinstance(name, str) or not 1 <= len(name) <= 32 or not set(name) <= _NAME_CHARS:
        raise ConfigError(f"renderer name must be 1-32 lower-case letters, digits, '_' or '-', got {name!r}")
    if name in RENDERERS:
        raise ConfigError(f"a renderer named {name!r} is registered already ({_describe(RENDERERS[name])})")
    if not (callable(factory) or (isinstance(factory, str) and factory.count(":") == 1)):
        raise ConfigError(f"renderer {name!r}: the factory must be callable or a 'module:attribute' path, "
                          f"got {factory!r}")
    RENDERERS[name] = factory


def renderer_names() -> tuple[str, ...]:
    """The registered names, sorted."""
    return tuple(sorted(RENDERERS))


def check_renderer(name: Any) -> str:
    """``name`` if a renderer of that name is registered.

    Raises:
        ConfigError: no such renderer (the message lists the registered ones).
    """
    if not isinstance(name, str) or name not in RENDERERS:
        raise ConfigError(f"unknown renderer {name!r}; renderers are {list(renderer_names())} (a new one is "
                          "registered with fruxel.train.sim.renderer.register_renderer)")
    return name


def renderer_factory(name: str) -> RendererFactory:
    """The factory registered as ``name``, imported if it was given as a path.

    Raises:
        ConfigError: no such renderer, or a path that does not import (the message names it).
    """
    entry = RENDERERS[check_renderer(name)]
    if not isinstance(entry, str):
        return entry
    module, _, attribute = entry.partition(":")
    try:
        return getattr(importlib.import_module(module), attribute)
    except (ImportError, AttributeError) as e:
        raise ConfigError(f"renderer {name!r} ({entry}) cannot be imported: {e}") from None


def make_renderer(config: SimConfig, device: str | None = None) -> Renderer:
    """A new renderer of the kind ``config.renderer`` names, made for ``config``.

    Args:
        config: the simulator config.
        device: the Warp device (``"cpu"``, ``"cuda:N"``) the process computes on, handed to factories that take a
            ``device`` argument (module docstring); None: the renderer's own choice.

    Raises:
        ConfigError: an unknown renderer, or one that does not import.
    """
    factory = renderer_factory(config.renderer)
    if device is not None and _takes(factory, "device"):
        return factory(config, device=device)
    return factory(config)


def takes_camera(renderer: Any) -> bool:
    """Whether ``renderer.render`` takes the optional ``camera`` argument (module docstring)."""
    return _takes(renderer.render, "camera")


def _takes(function: Any, argument: str) -> bool:
    """Whether ``function`` can be called with the keyword ``argument``."""
    try:
        params = inspect.signature(function).parameters
    except (TypeError, ValueError):
        return False
    return argument in params or any(p.kind is inspect.Parameter.VAR_KEYWORD for p in params.values())


def _describe(entry: RendererFactory | str) -> str:
    if isinstance(entry, str):
        return entry
    return f"{getattr(entry, '__module__', '?')}.{getattr(entry, '__qualname__', repr(entry))}"

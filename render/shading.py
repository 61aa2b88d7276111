"""Shading of fruxel surfaces into colours: class colour, Lambert term from the face normal, optional depth fog.

One formula serves every image fruxel draws: ray-cast images (:mod:`fruxel.render.raycast`, the simulator's
previews) and the ``"lit"`` meshes of :mod:`fruxel.render.scene`, so that a mesh and a ray cast of the same view
look alike. A surface of class colour ``c`` with unit normal ``n`` (grid frame) is drawn as::

    c * (ambient + (1 - ambient) * clip(n . l, 0, 1))          l: unit direction towards the light

with ``l`` a head light given in the viewing camera's frame (it turns with the viewer). With fog on, a hit at
depth ``d`` then blends linearly into the background, from none at the fog range's near end to all at its far
end. Missed pixels get the background. Arithmetic is float32, on the hits' own device: numpy arrays on the
host, torch tensors where they are (a CUDA image is shaded on the GPU and only the finished uint8 image is
copied back), with the same operations in the same order for both, so both give the same bytes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

DEFAULT_BACKGROUND = (255, 255, 255)
"""RGB of pixels whose ray missed."""
DEFAULT_LIGHT = (-0.4, -0.7, -0.6)
"""Direction towards the light in the viewing camera's frame (OpenCV axes: above-left-behind the viewer)."""
DEFAULT_AMBIENT = 0.35
"""Share of a colour lit regardless of orientation."""
FOG_SPAN = 2.0
"""With automatic fog, the farthest hit keeps ``1 - 1 / FOG_SPAN`` of its colour: strong enough to read depth,
never fading a surface away."""
SHADINGS = ("lit", "flat")
"""``"lit"``: ambient + Lambert; ``"flat"``: class colours only (ambient 1)."""


@dataclass(frozen=True)
class RaycastStyle:
    """How ray-cast hits become colours."""

    shading: str = "lit"
    """``"lit"`` (ambient + Lambert from the head light) or ``"flat"`` (the class colour, unshaded)."""
    light: tuple[float, float, float] = DEFAULT_LIGHT
    """Direction towards the light in the viewing camera's frame (OpenCV axes)."""
    ambient: float = DEFAULT_AMBIENT
    """Share of the colour lit regardless of orientation, in [0, 1] (``"lit"`` only)."""
    fog: bool = False
    """Blend hits into the background with depth, linearly from the nearest hit (no fog) to the farthest
    (``1 / FOG_SPAN`` fog)."""
    background: tuple[int, int, int] = DEFAULT_BACKGROUND
    """RGB of pixels whose ray misses (and the fog colour)."""

    def __post_init__(self) -> None:
        if self.shading not in SHADINGS:
            raise ValueError(f"shading must be one of {SHADINGS}, got {self.shading!r}")
        if not 0.0 <= self.ambient <= 1.0:
            raise ValueError(f"ambient must be in [0, 1], got {self.ambient}")

    @property
    def effective_ambient(self) -> float:
        """The ambient share actually used: 1 for ``"flat"``."""
        return 1.0 if self.shading == "flat" else self.ambient


DEFAULT_STYLE = RaycastStyle()
"""The default style: lit, no fog, white background."""


def _unit(light: Any) -> np.ndarray:
    """``light`` as a float32 unit vector (normalised in float64)."""
    ldir = np.asarray(light, dtype=np.float64).reshape(3)
    return (ldir / max(float(np.linalg.norm(ldir)), 1e-12)).astype(np.float32)


def _intensity(normals: Any, ldir: Any, ambient: float) -> Any:
    # The one Lambert expression; numpy arrays and torch tensors take the same float32 operations.
    return ambient + (1.0 - ambient) * (normals @ ldir).clip(0.0, 1.0)


def lambert(normals: Any, light: Any, ambient: float) -> np.ndarray:
    """Intensity ``ambient + (1 - ambient) * clip(n . l, 0, 1)`` per normal.

    Args:
        normals: ``(..., 3)`` float unit normals (grid frame).
        light: ``(3,)`` direction towards the light in the same frame; normalised here.
        ambient: in [0, 1].

    Returns:
        ``(...)`` float32 intensities in ``[ambient, 1]``.
    """
    return _intensity(np.asarray(normals, dtype=np.float32), _unit(light), ambient)


def fog_range(depth: Any, hit: Any) -> tuple[float, float] | None:
    """``(near, far)`` of :attr:`RaycastStyle.fog` for hit depths ``(h, w)`` and mask ``(h, w)`` (numpy, or torch
    on any device), None if none hit."""
    if not bool(hit.any()):
        return None
    d = depth[hit]
    near, last = float(d.min()), float(d.max())
    return near, near + FOG_SPAN * max(last - near, 1e-6)


def is_torch(x: Any) -> bool:
    """True for a torch tensor (checked without importing torch)."""
    return type(x).__module__.startswith("torch") and hasattr(x, "detach")


def to_numpy(x: Any) -> np.ndarray:
    """A numpy array of a numpy array or a torch tensor (copied to the host when on a GPU)."""
    if is_torch(x):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def shade(hits: Any, camera: Any, palette: Any, style: RaycastStyle = DEFAULT_STYLE,
          fog: tuple[float, float] | None = None) -> np.ndarray:
    """The shaded image of one view's hits: ``(h, w, 3)`` uint8 RGB on the host.

    Args:
        hits: :class:`fruxel.kernels.Hits` of one image (no batch axis): ``label`` ``(h, w)`` integer (0 = miss),
            ``normal`` ``(h, w, 3)`` float (grid frame), ``depth`` ``(h, w)`` float (metres, viewing camera);
            numpy, or torch on any device (shaded there; only the finished image is copied back).
        camera: the :class:`fruxel.Camera` the hits were cast from; the head light turns with it.
        palette: ``(C, 3)`` uint8 class colours; every label must be below C.
        style: shading, light, fog and background.
        fog: with ``style.fog``, the ``(near, far)`` range of the fog in metres; None takes it from these hits
            (:func:`fog_range`). A picture shaded in pieces passes the whole picture's range.

    Raises:
        ValueError: a palette that is not ``(C, 3)``.
    """
    pal = np.asarray(palette, dtype=np.uint8)
    if pal.ndim != 2 or pal.shape[1] != 3:
        raise ValueError(f"palette must be (C, 3) uint8, got shape {pal.shape}")
    ldir = _unit(camera.rotation @ np.asarray(style.light, dtype=np.float64))
    bg = np.asarray(style.background, dtype=np.float32)
    label = hits.label
    if is_torch(label):
        import torch

        dev = label.device

        def f32(a: Any) -> Any:
            return torch.as_tensor(a, device=dev).to(torch.float32)

        xp, label = torch, label.long()
    else:
        xp = np

        def f32(a: Any) -> Any:
            return np.asarray(a, dtype=np.float32)

    hit = label != 0
    colour = f32(pal)[label] * _intensity(f32(hits.normal), f32(ldir), style.effective_ambient)[..., None]
    background = f32(bg)
    if style.fog:
        depth = f32(hits.depth)
        fr = fog_range(depth, hit) if fog is None else fog
        if fr is not None:
            f = ((depth - fr[0]) / (fr[1] - fr[0])).clip(0.0, 1.0)[..., None]
            colour = colour * (1.0 - f) + background * f
    image = xp.round(xp.where(hit[..., None], colour, background)).clip(0, 255)
    if xp is np:
        return image.astype(np.uint8)
    return image.to(xp.uint8).cpu().numpy()

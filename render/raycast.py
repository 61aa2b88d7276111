"""Ray-cast images of fruxel volumes: ``first_hit`` from the viewing camera, then shading per pixel.

No mesh is built, so a volume that changes every frame (a network's live output) costs one kernel launch and
one shading pass per image. The volume may be labels ``(D, H, W)`` or logits ``(1, C, D, H, W)``, numpy or
torch, on the CPU or CUDA; the kernel reads it where it is (no argmax on the host first).

Shading is :func:`fruxel.shading.shade_hits`'s formula: class colour times ``ambient + (1 - ambient) *
max(0, n . l)`` with ``n`` the entry-face normal and ``l`` a head light given in the camera frame, then optional
linear depth fog into the background. :func:`shade` computes it in float32 on the hits' own device (numpy, or
torch on CUDA), because shade_hits' float64 numpy pass alone takes about 50 ms for a 640 x 480 image on a
2-core machine, longer than the kernel; tests pin the two to each other within one colour level.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid
from fruxel.shading import DEFAULT_AMBIENT, DEFAULT_BACKGROUND, DEFAULT_LIGHT

# With fog on, the farthest hit keeps 1 - 1 / FOG_SPAN of its colour: strong enough to read depth, never
# fading a surface away.
FOG_SPAN = 2.0

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


def lambert(normals: Any, light: Any, ambient: float) -> np.ndarray:
    """Intensity ``ambient + (1 - ambient) * clip(n . l, 0, 1)`` per normal.

    Args:
        normals: ``(..., 3)`` float unit normals (grid frame).
        light: ``(3,)`` direction towards the light in the same frame; normalised here.
        ambient: in [0, 1].

    Returns:
        ``(...)`` float32 intensities in ``[ambient, 1]``.
    """
    ldir = np.asarray(light, dtype=np.float64).reshape(3)
    ldir = (ldir / max(float(np.linalg.norm(ldir)), 1e-12)).astype(np.float32)
    n = np.asarray(normals, dtype=np.float32)
    lam = np.clip(n @ ldir, np.float32(0.0), np.float32(1.0))
    return np.float32(ambient) + np.float32(1.0 - ambient) * lam


def _is_torch(x: Any) -> bool:
    return type(x).__module__.startswith("torch") and hasattr(x, "detach")


def to_numpy(x: Any) -> np.ndarray:
    """A numpy array of a numpy array or a torch tensor (copied to the host when on a GPU)."""
    if _is_torch(x):
        return x.detach().cpu().numpy()
    return np.asarray(x)


def first_hits(
    volume: Any,
    grid: FruxelGrid,
    camera: Camera,
    *,
    backend: str | None = None,
    device: str | None = None,
    threshold: float | None = None,
) -> Any:
    """``fruxel.kernels.first_hit`` for one image: a :class:`fruxel.kernels.Hits` without batch axis.

    Args:
        volume: labels ``(D, H, W)`` or scores ``(1, C, D, H, W)`` (a batch of one), numpy or torch.
        grid, camera: the volume's grid and the viewing camera.
        backend, device, threshold: as for ``first_hit``.

    Returns:
        Hits with ``(h, w)`` label / cell / depth and ``(h, w, 3)`` normal, in the volume's kind of array and on
        its device.
    """
    from fruxel import kernels

    hits = kernels.first_hit(volume, grid, camera, backend=backend, device=device, threshold=threshold)
    if hits.label.ndim == 3:
        hits = type(hits)(label=hits.label[0], cell=hits.cell[0], depth=hits.depth[0], normal=hits.normal[0])
    return hits


def fog_range(depth: Any, hit: Any) -> tuple[float, float] | None:
    """``(near, far)`` of :attr:`RaycastStyle.fog` for hit depths ``(h, w)`` and mask ``(h, w)`` (numpy, or torch
    on any device), None if none hit."""
    if not bool(hit.any()):
        return None
    d = depth[hit]
    near, last = float(d.min()), float(d.max())
    return near, near + FOG_SPAN * max(last - near, 1e-6)


def _shade_numpy(label: Any, normal: Any, depth: Any, palette: np.ndarray, light: np.ndarray, style: RaycastStyle
                 ) -> np.ndarray:
    label = np.asarray(label)
    hit = label != 0
    pal = palette.astype(np.float32)
    colour = pal[label] * lambert(normal, light, style.effective_ambient)[..., None]
    bg = np.asarray(style.background, dtype=np.float32)
    if style.fog:
        fr = fog_range(np.asarray(depth), hit)
        if fr is not None:
            f = np.clip((np.asarray(depth, dtype=np.float32) - fr[0]) / np.float32(fr[1] - fr[0]), 0.0, 1.0)[..., None]
            colour = colour * (1.0 - f) + bg * f
    colour[~hit] = bg
    return np.clip(np.rint(colour), 0, 255).astype(np.uint8)


def _shade_torch(label: Any, normal: Any, depth: Any, palette: np.ndarray, light: np.ndarray, style: RaycastStyle
                 ) -> np.ndarray:
    import torch

    dev = label.device
    hit = label != 0
    pal = torch.as_tensor(palette, dtype=torch.float32, device=dev)
    ldir = torch.as_tensor(light / max(float(np.linalg.norm(light)), 1e-12), dtype=torch.float32, device=dev)
    a = style.effective_ambient
    inten = a + (1.0 - a) * (normal.to(torch.float32) @ ldir).clamp(0.0, 1.0)
    colour = pal[label.long()] * inten[..., None]
    bg = torch.as_tensor(style.background, dtype=torch.float32, device=dev)
    if style.fog:
        d = depth.to(torch.float32)
        fr = fog_range(d, hit)
        if fr is not None:
            f = ((d - fr[0]) / (fr[1] - fr[0])).clamp(0.0, 1.0)[..., None]
            colour = colour * (1.0 - f) + bg * f
    colour = torch.where(hit[..., None], colour, bg)
    return colour.round().clamp(0, 255).to(torch.uint8).cpu().numpy()


def shade(hits: Any, camera: Camera, palette: Any, style: RaycastStyle = RaycastStyle()) -> np.ndarray:
    """The shaded image of one view's hits: ``(h, w, 3)`` uint8 RGB on the host.

    Args:
        hits: :class:`fruxel.kernels.Hits` of one image (no batch axis); numpy, or torch on any device (shaded
            there; only the finished image is copied back).
        camera: the camera the hits were cast from; the head light turns with it.
        palette: ``(C, 3)`` uint8 class colours; every label must be below C.
        style: shading, light, fog and background.
    """
    pal = np.asarray(palette, dtype=np.uint8)
    if pal.ndim != 2 or pal.shape[1] != 3:
        raise ValueError(f"palette must be (C, 3) uint8, got shape {pal.shape}")
    light = camera.rotation @ np.asarray(style.light, dtype=np.float64)
    if _is_torch(hits.label):
        return _shade_torch(hits.label, hits.normal, hits.depth, pal, light, style)
    return _shade_numpy(hits.label, hits.normal, hits.depth, pal, light, style)


def raycast_image(
    volume: Any,
    grid: FruxelGrid,
    camera: Camera,
    palette: Any,
    *,
    backend: str | None = None,
    device: str | None = None,
    threshold: float | None = None,
    style: RaycastStyle = RaycastStyle(),
) -> tuple[np.ndarray, np.ndarray]:
    """Ray-cast one image of a volume.

    Args:
        volume: labels ``(D, H, W)`` or scores ``(1, C, D, H, W)``, numpy or torch (see :func:`first_hits`).
        grid: the volume's grid.
        camera: the viewing camera (any pose).
        palette: ``(C, 3)`` uint8 class colours.
        backend, device, threshold: as for ``fruxel.kernels.first_hit``.
        style: shading (see :class:`RaycastStyle`).

    Returns:
        image: ``(h, w, 3)`` uint8 RGB.
        labels: ``(h, w)`` int32 label of each pixel's first hit, 0 on a miss.
    """
    hits = first_hits(volume, grid, camera, backend=backend, device=device, threshold=threshold)
    return shade(hits, camera, palette, style), to_numpy(hits.label).astype(np.int32, copy=False)

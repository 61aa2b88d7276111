"""The lights of a furnished room: one to four of varied kind and colour, and the sky's ambient light.

Which lights are on: ``HomeConfig.lights`` draws their number; the sun comes first (with ``HomeConfig.sun``'s
chance, when there is a window), then the room's fixtures in random order: ceiling fixtures (a spot shining down
or a point light just below the fixture) and lamps (a point light at the bulb, inside the shade). A lit fixture's
non-metal materials glow (``Material.emission``). A room with no fixture and no sun gets a point light below the
ceiling's middle.

Kinds and units (those of :class:`fruxel.train.sim.scene.Light`, as the flat rooms use them): the sun is a
directional light (2 to 6 lux, an angular radius of 0.3 to 1.7 degrees for soft shadows) coming in through a
window, from 10 to 55 degrees above the horizon and up to 55 degrees to the side of the window's normal; ceiling
fixtures 8 to 30 candela, lamps 3 to 12, with radii of a few centimetres. Colours come from a colour temperature
(sun 4500-6500 K, ceiling 2700-5000 K, lamps 2400-4000 K) and, one time in eight, a tint of a random hue. The
ambient light (``Scene.ambient``) is a pale sky colour (6500-12000 K) at a level of 0.02 to 0.12, brighter with
windows.
"""

from __future__ import annotations

import colorsys
import dataclasses
import math

import numpy as np

from ..scene import Light
from .draft import Home


def kelvin(t: float) -> np.ndarray:
    """``(3,)`` RGB in [0, 1] of a black body at ``t`` kelvin, brightest channel 1 (Tanner Helland's fit)."""
    t = t / 100.0
    r = 1.0 if t <= 66 else 1.292936186 * (t - 60) ** -0.1332047592
    g = 0.390081579 * math.log(t) - 0.631841444 if t <= 66 else 1.129890861 * (t - 60) ** -0.0755148492
    b = 1.0 if t >= 66 else 0.0 if t <= 19 else 0.543206789 * math.log(t - 10) - 1.196254089
    c = np.clip([r, g, b], 0.0, 1.0)
    return c / c.max()


def _colour(rng: np.random.Generator, temperature: tuple[float, float]) -> tuple[float, float, float]:
    c = kelvin(rng.uniform(*temperature))
    tint, hue, amount = rng.uniform(), rng.uniform(), rng.uniform(0.15, 0.4)
    if tint < 0.125:
        c = (1 - amount) * c + amount * np.array(colorsys.hsv_to_rgb(hue, 0.8, 1.0))
        c = c / c.max()
    return (float(c[0]), float(c[1]), float(c[2]))


def _pose(position: np.ndarray, z_axis: np.ndarray | None = None) -> np.ndarray:
    """Light-to-world transform at ``position`` whose local +z is ``z_axis`` (a light shines along local -z)."""
    pose = np.eye(4)
    pose[:3, 3] = position
    if z_axis is not None:
        z = z_axis / np.linalg.norm(z_axis)
        x = np.cross([0.0, 0.0, 1.0], z)
        x = x / np.linalg.norm(x) if np.linalg.norm(x) > 1e-9 else np.array([1.0, 0.0, 0.0])
        pose[:3, 0], pose[:3, 1], pose[:3, 2] = x, np.cross(z, x), z
    return pose


def lights(h: Home) -> tuple[list[Light], tuple[float, float, float]]:
    """The lights that are on and the ambient colour (module docstring)."""
    rng = h.rng
    n = int(rng.integers(h.cfg.lights[0], h.cfg.lights[1] + 1))
    out: list[Light] = []
    if h.windows and rng.uniform() < h.cfg.sun:
        out.append(_sun(h))
    for k in rng.permutation(len(h.lights)):
        if len(out) >= n:
            break
        kind, position, piece = h.lights[int(k)]
        out.append(_fixture(rng, kind, np.asarray(position, dtype=np.float64)))
        glow = float(rng.uniform(0.3, 1.0))
        piece.materials = [dataclasses.replace(m, emission=glow) if m.metallic < 0.5 else m for m in piece.materials]
    if not out:
        out.append(_fixture(rng, "ceiling", np.array([h.lx / 2, h.ly / 2, h.lz - 0.3])))
    level = rng.uniform(0.02, 0.12) * (1.5 if h.windows else 1.0)
    sky = kelvin(rng.uniform(6500, 12000)) * level
    return out, (float(sky[0]), float(sky[1]), float(sky[2]))


def _sun(h: Home) -> Light:
    """A directional light coming in through one of the windows."""
    rng = h.rng
    w = h.windows[int(rng.integers(len(h.windows)))]
    normal = h.walls[w.wall].normal
    side, up = rng.uniform(-0.95, 0.95), rng.uniform(math.radians(10), math.radians(55))
    c, s = math.cos(side), math.sin(side)
    inward = -np.array([c * normal[0] - s * normal[1], s * normal[0] + c * normal[1]])
    travel = np.array([math.cos(up) * inward[0], math.cos(up) * inward[1], -math.sin(up)])
    return Light("directional", _colour(rng, (4500, 6500)), float(rng.uniform(2.0, 6.0)), _pose(np.zeros(3), -travel),
                 radius=float(rng.uniform(0.005, 0.03)))


def _fixture(rng: np.random.Generator, kind: str, position: np.ndarray) -> Light:
    """A ceiling fixture's spot or point light, or a lamp's point light, at ``position``."""
    if kind == "ceiling":
        colour, intensity, radius = _colour(rng, (2700, 5000)), float(rng.uniform(8.0, 30.0)), rng.uniform(0.02, 0.15)
        if rng.uniform() < 0.5:
            inner = rng.uniform(0.3, 0.6)
            outer = min(inner + rng.uniform(0.15, 0.5), math.pi / 2 - 0.05)
            return Light("spot", colour, intensity, _pose(position), cone=(float(inner), float(outer)),
                         radius=float(radius))
        return Light("point", colour, intensity, _pose(position), radius=float(radius))
    return Light("point", _colour(rng, (2400, 4000)), float(rng.uniform(3.0, 12.0)), _pose(position),
                 radius=float(rng.uniform(0.02, 0.06)))

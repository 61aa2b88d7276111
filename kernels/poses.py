"""Predefined viewing poses for VMS: m cameras on an orbit or a sphere around the grid, looking at its centre.

The paper's simplification keeps the cells visible from a fixed set of poses. ``orbit_cameras`` builds that set
for any grid: the cameras share intrinsics, their optical axes pass through the centre of the frustum's
bounding box, and they stand at ``radius`` from it.
"""

from __future__ import annotations

import math

import numpy as np

from fruxel.camera import Camera, CameraError, look_at_grid, orbit_direction
from fruxel.grid import FruxelGrid


def orbit_cameras(
    grid: FruxelGrid,
    m: int = 6,
    *,
    layout: str = "orbit",
    radius: float | None = None,
    elevation: float = 25.0,
    azimuth_span: float = 120.0,
    width: int = 512,
    height: int = 512,
    hfov: float = 60.0,
) -> list[Camera]:
    """m cameras around the grid, each looking at the centre of the frustum's bounding box.

    Angles follow the grid frame (OpenCV: y down, z forward). Azimuth 0 is the grid's own viewing side (the
    camera stands towards -z, behind the apex, looking along +z); elevation lifts it towards -y (up).

    Args:
        grid: the grid to surround.
        m: number of cameras, >= 1.
        layout: ``"orbit"``: azimuths spread evenly over ``azimuth_span`` degrees centred on the front, at one
            ``elevation``. ``"sphere"``: a Fibonacci spiral over the whole sphere.
        radius: distance from the centre, metres. The default puts the box's bounding sphere inside the
            narrower of the horizontal and vertical fields of view with a 10% margin, so that every camera sees
            the whole grid whatever the image's aspect.
        elevation: degrees above the grid's horizontal plane, for ``"orbit"``.
        azimuth_span: degrees, for ``"orbit"``; 360 places cameras all round.
        width, height, hfov: image size and horizontal field of view of each camera.

    Returns:
        m cameras, ``(4, 4)`` float64 camera-to-grid poses.

    Raises:
        CameraError: m < 1, an unknown layout, or a non-positive radius.
    """
    if int(m) != m or m < 1:
        raise CameraError(f"m must be a positive integer, got {m}")
    box = grid.bounds()
    if radius is None:
        half_h = math.radians(hfov) / 2.0
        half_v = math.atan(math.tan(half_h) * height / width)
        sphere = 0.5 * float(np.linalg.norm(box[1] - box[0]))
        r = 1.1 * sphere / math.sin(min(half_h, half_v))
    else:
        r = float(radius)
    if not (math.isfinite(r) and r > 0):
        raise CameraError(f"radius must be > 0, got {radius}")
    if layout == "orbit":
        el = math.radians(elevation)
        span = math.radians(azimuth_span)
        if m == 1:
            az = np.zeros(1)
        elif abs(azimuth_span) >= 360.0:
            az = np.arange(m) * (2 * math.pi / m)
        else:
            az = np.linspace(-span / 2, span / 2, m)
        dirs = orbit_direction(az, el)
    elif layout == "sphere":
        idx = np.arange(m) + 0.5
        polar = np.arccos(1 - 2 * idx / m)
        az = math.pi * (1 + 5**0.5) * idx
        dirs = np.stack([np.sin(polar) * np.sin(az), -np.cos(polar), -np.sin(polar) * np.cos(az)], axis=-1)
    else:
        raise CameraError(f"layout must be 'orbit' or 'sphere', got {layout!r}")
    return [look_at_grid(grid, d, distance=r, width=width, height=height, hfov=hfov) for d in dirs]

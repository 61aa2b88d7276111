"""Viewing cameras (conventions section 3): pinhole intrinsics, image size and a camera-to-grid pose.

Axes are OpenCV's: x right, y down, z forward, in the camera frame and in the grid frame alike. The ray of
pixel ``(x, y)`` (column x, row y) has direction ``((x + 0.5 - cx) / fx, (y + 0.5 - cy) / fy, 1)`` in camera
coordinates, so the ray parameter ``t`` of a point equals its depth (z) in the viewing camera.

OpenGL / pyrender cameras look down -z with y up. :meth:`Camera.opengl_pose` returns the pose that pyrender
needs for the same view: ``pose @ diag(1, -1, -1, 1)`` (flip y and z of the camera frame; the grid frame is
unchanged, so a mesh built in grid coordinates is given to pyrender as it is).
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import FruxelError

if TYPE_CHECKING:
    from .grid import FruxelGrid

OPENCV_TO_OPENGL = np.diag([1.0, -1.0, -1.0, 1.0])
"""Right-multiply an OpenCV camera-to-world pose by this to get the OpenGL camera-to-world pose."""

# A pose whose rotation part is further than this from orthonormal (max abs entry of R^T R - I), or whose
# determinant differs from 1 by more, is not rigid.
RIGID_TOLERANCE = 1e-5

# Images larger than this many pixels are refused: a ray buffer would not fit in memory.
MAX_PIXELS = 2**28


def orbit_direction(azimuth: Any, elevation: Any) -> np.ndarray:
    """Unit direction from an orbit's centre to its eye, grid frame (OpenCV axes: y down, z forward).

    Azimuth 0 is the grid's own viewing side (the eye towards -z, behind the apex); positive azimuth turns towards
    +x. Elevation lifts the eye towards -y (up).

    Args:
        azimuth, elevation: radians, scalars or arrays (broadcast against each other).

    Returns:
        ``(..., 3)`` float64 unit vectors.
    """
    az, el = np.asarray(azimuth, np.float64), np.asarray(elevation, np.float64)
    return np.stack(np.broadcast_arrays(np.sin(az) * np.cos(el), -np.sin(el), -np.cos(az) * np.cos(el)), axis=-1)


class CameraError(FruxelError, ValueError):
    """Raised for impossible camera parameters: non-positive focal lengths or sizes, non-finite numbers,
    a pose that is not a rigid 4x4 transform."""


def check_pose(pose: Any) -> np.ndarray:
    """Validate a 4x4 rigid camera-to-grid transform; returns it as a new ``(4, 4)`` float64 array.

    Raises:
        CameraError: wrong shape, non-finite entries, a bottom row other than ``(0, 0, 0, 1)``, or a rotation
            block that is not orthonormal with determinant +1 (within ``RIGID_TOLERANCE``).
    """
    try:
        p = np.array(pose, dtype=np.float64)
    except (TypeError, ValueError):
        raise CameraError("pose must be a 4x4 numeric matrix") from None
    if p.shape != (4, 4):
        raise CameraError(f"pose must have shape (4, 4), got {p.shape}")
    if not np.all(np.isfinite(p)):
        raise CameraError("pose has NaN or infinite entries")
    if np.max(np.abs(p[3] - [0.0, 0.0, 0.0, 1.0])) > RIGID_TOLERANCE:
        raise CameraError(f"pose bottom row must be (0, 0, 0, 1), got {p[3].tolist()}")
    r = p[:3, :3]
    if np.max(np.abs(r.T @ r - np.eye(3))) > RIGID_TOLERANCE or abs(np.linalg.det(r) - 1.0) > RIGID_TOLERANCE:
        raise CameraError("pose is not rigid: its rotation block must be orthonormal with determinant +1")
    p[3] = [0.0, 0.0, 0.0, 1.0]
    return p


@dataclass(frozen=True, eq=False)
class Camera:
    """A pinhole viewing camera in the fruxel frame.

    Raises:
        CameraError: on construction, for non-finite or non-positive focal lengths, non-finite principal
            points, image sizes that are not positive integers (or exceed ``MAX_PIXELS``), or a non-rigid pose.
    """

    fx: float
    """Focal length along x, pixels, > 0."""
    fy: float
    """Focal length along y, pixels, > 0."""
    cx: float
    """Principal point x, pixels (the image's left edge is 0)."""
    cy: float
    """Principal point y, pixels (the image's top edge is 0)."""
    width: int
    """Image width in pixels, > 0."""
    height: int
    """Image height in pixels, > 0."""
    pose: np.ndarray = field(default_factory=lambda: np.eye(4))
    """``(4, 4)`` float64 camera-to-grid transform, OpenCV axes, rigid. Stored read-only."""

    def __post_init__(self) -> None:
        for name in ("fx", "fy", "cx", "cy"):
            try:
                v = float(getattr(self, name))
            except (TypeError, ValueError):
                raise CameraError(f"{name} must be a number, got {getattr(self, name)!r}") from None
            if not math.isfinite(v):
                raise CameraError(f"{name} must be finite, got {v}")
            object.__setattr__(self, name, v)
        if self.fx <= 0 or self.fy <= 0:
            raise CameraError(f"focal lengths must be > 0, got fx={self.fx}, fy={self.fy}")
        for name in ("width", "height"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, (int, np.integer)) or v <= 0:
                raise CameraError(f"image {name} must be a positive integer, got {v!r}")
            object.__setattr__(self, name, int(v))
        if self.width * self.height > MAX_PIXELS:
            raise CameraError(f"image of {self.width}x{self.height} pixels exceeds the limit of {MAX_PIXELS}")
        p = check_pose(self.pose)
        p.setflags(write=False)
        object.__setattr__(self, "pose", p)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, Camera):
            return NotImplemented
        return self.to_dict() == other.to_dict()

    def __hash__(self) -> int:
        return hash(self.to_json())

    # ------------------------------------------------------------------ constructors
    @classmethod
    def from_hfov(cls, width: int, height: int, hfov: float, pose: Any = None) -> Camera:
        """A camera with square pixels, centred principal point and the given horizontal field of view.

        Args:
            width, height: image size in pixels.
            hfov: horizontal field of view, degrees, in (0, 180).
            pose: ``(4, 4)`` camera-to-grid transform; identity when None.
        """
        hfov = float(hfov)
        if not 0 < hfov < 180:
            raise CameraError(f"hfov must be in (0, 180) degrees, got {hfov}")
        f = float(width) / (2.0 * math.tan(math.radians(hfov) / 2.0))
        return cls(fx=f, fy=f, cx=width / 2.0, cy=height / 2.0, width=width, height=height,
                   pose=np.eye(4) if pose is None else pose)

    @classmethod
    def look_at(
        cls,
        eye: Any,
        target: Any,
        up: Any = (0.0, -1.0, 0.0),
        width: int = 640,
        height: int = 480,
        hfov: float = 60.0,
    ) -> Camera:
        """A camera at ``eye`` looking at ``target``, with ``up`` giving the image's up direction.

        Args:
            eye: ``(3,)`` camera position, grid frame, metres.
            target: ``(3,)`` point the optical axis passes through, grid frame.
            up: ``(3,)`` world direction that appears up in the image. The grid frame is OpenCV's (y down),
                so the default ``(0, -1, 0)`` keeps the grid's own "up".
            width, height, hfov: image size in pixels and horizontal field of view in degrees.

        Raises:
            CameraError: ``eye == target``, non-finite input, or ``up`` parallel to the viewing direction.
        """
        eye = np.asarray(eye, dtype=np.float64).reshape(3)
        target = np.asarray(target, dtype=np.float64).reshape(3)
        up = np.asarray(up, dtype=np.float64).reshape(3)
        if not (np.all(np.isfinite(eye)) and np.all(np.isfinite(target)) and np.all(np.isfinite(up))):
            raise CameraError("look_at: eye, target and up must be finite")
        fwd = target - eye
        n = np.linalg.norm(fwd)
        if n < 1e-12:
            raise CameraError("look_at: eye and target coincide")
        z = fwd / n
        x = np.cross(-up, z)  # OpenCV is right-handed with y down: x = y x z, and y is close to -up
        nx = np.linalg.norm(x)
        if nx < 1e-9 * max(1.0, np.linalg.norm(up)):
            raise CameraError("look_at: up is parallel to the viewing direction")
        x /= nx
        y = np.cross(z, x)
        pose = np.eye(4)
        pose[:3, 0], pose[:3, 1], pose[:3, 2], pose[:3, 3] = x, y, z, eye
        return cls.from_hfov(width, height, hfov, pose)

    def with_pose(self, pose: Any) -> Camera:
        """The same intrinsics and image size with another camera-to-grid pose."""
        return Camera(self.fx, self.fy, self.cx, self.cy, self.width, self.height, pose)

    def scaled(self, factor: float) -> Camera:
        """The same view at ``factor`` times the resolution (image size rounded, intrinsics scaled)."""
        w = max(1, round(self.width * factor))
        h = max(1, round(self.height * factor))
        sx, sy = w / self.width, h / self.height
        return Camera(self.fx * sx, self.fy * sy, self.cx * sx, self.cy * sy, w, h, self.pose)

    # ------------------------------------------------------------------ geometry
    @property
    def K(self) -> np.ndarray:  # noqa: N802 - the field's name for the intrinsic matrix
        """``(3, 3)`` float64 intrinsic matrix."""
        return np.array([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])

    @property
    def position(self) -> np.ndarray:
        """``(3,)`` float64 optical centre in the grid frame."""
        return np.array(self.pose[:3, 3])

    @property
    def rotation(self) -> np.ndarray:
        """``(3, 3)`` float64 camera-to-grid rotation."""
        return np.array(self.pose[:3, :3])

    def ray_directions_camera(self) -> np.ndarray:
        """Ray directions of every pixel in camera coordinates: ``(height, width, 3)`` float64, z = 1."""
        xs = (np.arange(self.width, dtype=np.float64) + 0.5 - self.cx) / self.fx
        ys = (np.arange(self.height, dtype=np.float64) + 0.5 - self.cy) / self.fy
        d = np.empty((self.height, self.width, 3))
        d[..., 0] = xs[None, :]
        d[..., 1] = ys[:, None]
        d[..., 2] = 1.0
        return d

    def rays(self) -> tuple[np.ndarray, np.ndarray]:
        """Rays of every pixel in the grid frame.

        Returns:
            origins: ``(height, width, 3)`` float64, the optical centre repeated, grid frame.
            directions: ``(height, width, 3)`` float64, grid frame, *not* normalised: the camera-frame
                direction has z = 1, so ``origin + t * direction`` is at depth ``t`` in this camera.
        """
        d = self.ray_directions_camera() @ self.rotation.T
        o = np.broadcast_to(self.position, d.shape).copy()
        return o, d

    def project(self, points: Any) -> np.ndarray:
        """Pixel coordinates and depth of grid-frame points: ``(..., 3)`` float64 ``(x, y, depth)``.

        Pixel ``(x, y)``'s centre is at ``(x + 0.5, y + 0.5)`` in these continuous coordinates. Points behind
        the camera get a depth <= 0 and undefined pixel coordinates.
        """
        p = np.asarray(points, dtype=np.float64)
        pc = (p - self.position) @ self.rotation
        with np.errstate(divide="ignore", invalid="ignore"):
            x = self.fx * pc[..., 0] / pc[..., 2] + self.cx
            y = self.fy * pc[..., 1] / pc[..., 2] + self.cy
        return np.stack([x, y, pc[..., 2]], axis=-1)

    def opengl_pose(self) -> np.ndarray:
        """``(4, 4)`` float64 camera-to-grid pose with OpenGL axes (x right, y up, looking down -z), for pyrender."""
        return self.pose @ OPENCV_TO_OPENGL

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dictionary: intrinsics, image size and the pose as a nested list (row-major)."""
        return {
            "fx": self.fx, "fy": self.fy, "cx": self.cx, "cy": self.cy,
            "width": self.width, "height": self.height, "pose": self.pose.tolist(),
        }

    @classmethod
    def from_dict(cls, d: Any) -> Camera:
        """Inverse of :meth:`to_dict`. Raises ``CameraError`` on missing, extra or invalid keys."""
        if not isinstance(d, dict):
            raise CameraError(f"camera must be a JSON object, got {type(d).__name__}")
        names = ("fx", "fy", "cx", "cy", "width", "height", "pose")
        missing = [n for n in names if n not in d]
        extra = sorted(set(d) - set(names))
        if missing or extra:
            raise CameraError(f"camera keys: missing {missing}, unexpected {extra}")
        return cls(**{n: d[n] for n in names})

    def to_json(self) -> str:
        """JSON text of :meth:`to_dict`; floats round-trip exactly."""
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str) -> Camera:
        """Inverse of :meth:`to_json`. Raises ``CameraError`` on malformed text."""
        try:
            d = json.loads(text)
        except (TypeError, ValueError) as e:
            raise CameraError(f"camera JSON is malformed: {e}") from None
        return cls.from_dict(d)

    def __repr__(self) -> str:
        return (f"Camera(fx={self.fx:g}, fy={self.fy:g}, cx={self.cx:g}, cy={self.cy:g}, "
                f"width={self.width}, height={self.height}, position={self.position.round(4).tolist()})")


def look_at_grid(
    grid: FruxelGrid,
    direction: Any,
    *,
    distance: float | None = None,
    target: Any = None,
    points: Any = None,
    width: int = 640,
    height: int = 480,
    hfov: float = 60.0,
    margin: float = 0.0,
    centre: bool = False,
) -> Camera:
    """A camera looking at a grid: the one way fruxel frames a view of a grid or of what is in it.

    The eye stands at ``target + distance * direction`` and looks at ``target``, with the grid's up (``-y``) up in
    the image (``+z`` when the view is within 2.6 degrees of vertical, where ``-y`` is no longer usable). Every
    "camera around the grid" in fruxel comes from here: the predefined VMS poses
    (:func:`fruxel.kernels.orbit_cameras`), the shell losses' random novel views, the benchmark scene's oblique
    view (:func:`fruxel.data.rooms.oblique_camera`), ``fruxel-render``'s default view and orbits, and the
    simulator preview's second view.

    Args:
        grid: the grid looked at.
        direction: ``(3,)`` direction from the target towards the eye, grid frame (OpenCV axes); normalised here
            unless it is a unit vector already. :func:`orbit_direction` gives it from azimuth and elevation.
        distance: metres from the target to the eye. None fits it: the smallest distance at which every one of
            ``points`` projects into the image with ``margin`` of the width and height left free on each side
            (computed exactly: the view's rotation does not depend on the distance).
        target: ``(3,)`` point looked at, grid frame; default :meth:`FruxelGrid.centre` (the centre of the
            frustum's bounding box).
        points: ``(N, 3)`` points to fit, grid frame; default the frustum's 8 corners (the whole grid).
        width, height, hfov: image size in pixels and horizontal field of view in degrees.
        margin: share of the image width and height kept free on each side when fitting, in [0, 0.5).
        centre: when fitting, also move the target sideways (rounds of shift and refit, until the points' image is
            centred within ``_CENTRE_TOLERANCE`` pixels), for a still view; False keeps the target in the middle of
            the image (orbits that turn around one point).

    Returns:
        The camera, ``width x height`` pixels, ``fx = fy``, principal point at the image centre.

    Raises:
        CameraError: a zero or non-finite direction, a non-positive or non-finite distance, a margin outside
            [0, 0.5), or no points to fit.
    """
    d = np.asarray(direction, dtype=np.float64).reshape(3)
    n = float(np.linalg.norm(d))
    if not (math.isfinite(n) and n > 0.0):
        raise CameraError(f"look_at_grid: direction must be a finite non-zero vector, got {d.tolist()}")
    if abs(n - 1.0) > 1e-12:
        d = d / n
    # Straight above or below, the usual up (-y) is parallel to the view: +z is up instead.
    up = (0.0, -1.0, 0.0) if abs(d[1]) < 0.999 else (0.0, 0.0, 1.0)
    aim = grid.centre() if target is None else np.asarray(target, dtype=np.float64).reshape(3)
    if distance is not None:
        r = float(distance)
        if not (math.isfinite(r) and r > 0.0):
            raise CameraError(f"look_at_grid: distance must be > 0, got {distance}")
        return Camera.look_at(aim + r * d, aim, up=up, width=width, height=height, hfov=hfov)
    if not 0.0 <= margin < 0.5:
        raise CameraError(f"look_at_grid: margin must be in [0, 0.5), got {margin}")
    pts = grid.frustum_corners() if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 3)
    if len(pts) == 0 or not np.all(np.isfinite(pts)):
        raise CameraError("look_at_grid: no finite points to fit")
    scale = float(np.ptp(pts, axis=0).max()) + float(np.abs(pts - aim).max())
    # Any eye on the ray gives the same rotation; only the distance changes what the image shows.
    cam = Camera.look_at(aim + d, aim, up=up, width=width, height=height, hfov=hfov)
    r = _fit_distance(cam, pts - aim, margin, scale)
    for _ in range(_CENTRE_ROUNDS if centre else 0):
        cam = Camera.look_at(aim + r * d, aim, up=up, width=width, height=height, hfov=hfov)
        p = cam.project(pts)
        # Move the aim point sideways in the image plane by the offset of the points' image from the centre,
        # converted to metres at the aim point's depth, then fit the distance again.
        off_x = 0.5 * (p[:, 0].min() + p[:, 0].max()) - cam.cx
        off_y = 0.5 * (p[:, 1].min() + p[:, 1].max()) - cam.cy
        if max(abs(off_x), abs(off_y)) < _CENTRE_TOLERANCE:
            break
        aim = aim + r * (off_x / cam.fx * cam.rotation[:, 0] + off_y / cam.fy * cam.rotation[:, 1])
        r = _fit_distance(cam, pts - aim, margin, scale)
    return Camera.look_at(aim + r * d, aim, up=up, width=width, height=height, hfov=hfov)


_CENTRE_ROUNDS = 50
"""Most rounds of shift-and-refit of :func:`look_at_grid`'s ``centre``; a few usually do."""
_CENTRE_TOLERANCE = 0.01
"""Pixels by which the fitted points' image may be off centre when ``centre`` stops."""


def _fit_distance(cam: Camera, rel: np.ndarray, margin: float, scale: float) -> float:
    """The smallest eye distance from the aim point at which points ``rel`` (relative to the aim point, ``(N, 3)``
    grid frame) project inside ``cam``'s image less ``margin``; ``cam`` gives the view's rotation and intrinsics.

    In the camera frame a point is ``(a_x, a_y, a_z + r)`` with ``a = R^T rel``; it lies inside the image when
    ``a_z + r >= f |a| / (half extent - margin)`` along each image axis (the principal point is centred).
    """
    a = rel @ cam.rotation
    half_x = cam.width * (0.5 - margin)
    half_y = cam.height * (0.5 - margin)
    need = np.maximum(cam.fx * np.abs(a[:, 0]) / half_x, cam.fy * np.abs(a[:, 1]) / half_y) - a[:, 2]
    # In front of the camera as well, and never on the aim point itself (a model of one point).
    return max(float(need.max()), float((-a[:, 2]).max()) + 1e-9 * scale, 1e-6 * scale, 1e-9)

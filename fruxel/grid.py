"""The fruxel grid: a W x H x D label grid aligned with a camera frustum (conventions section 1).

Frame: the grid camera's frame, OpenCV axes (x right, y down, z forward), origin at the optical centre,
metres. A cell ``(k, j, i)`` is the truncated pyramid

    z_k <= z < z_{k+1},   u_i <= x / z < u_{i+1},   v_j <= y / z < v_{j+1}

with ``u_i = -tu + i * 2 tu / W``, ``v_j = -tv + j * 2 tv / H``, ``z_k = z_near + k (z_far - z_near) / D``,
``tu = tan(hfov / 2)`` and ``tv = tu * H / W`` (square pixels).

The *centre* of a cell is the point at the middle of its three parameter ranges,
``(u_c z_c, v_c z_c, z_c)`` with ``u_c = (u_i + u_{i+1}) / 2`` and so on. It lies on the centre ray of its
column, which is what conventions section 1 asks; it is not the cell's centroid (the centroid of a frustum piece
sits slightly deeper), and the field's froxel code uses the same parametric centre.

Corner ``c`` (0..7) of a cell is at ``(u_{i + (c & 1)}, v_{j + ((c >> 1) & 1)}, z_{k + (c >> 2)})``.
"""

from __future__ import annotations

import json
import math
from dataclasses import asdict, dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from .errors import FruxelError

if TYPE_CHECKING:
    from .camera import Camera

# A grid with more cells than this is refused: it would not fit any label volume a user could hold, and the
# file loader uses the same bound to refuse headers that claim absurd sizes before allocating anything.
MAX_CELLS = 2**34


class GridError(FruxelError, ValueError):
    """Raised for impossible grid parameters or out-of-range cell indices."""


def _as_int(name: str, value: Any) -> int:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        if isinstance(value, (float, np.floating)) and float(value).is_integer():
            return int(value)
        raise GridError(f"{name} must be a positive integer, got {value!r}")
    if value <= 0:
        raise GridError(f"{name} must be a positive integer, got {value!r}")
    return int(value)


def _as_float(name: str, value: Any) -> float:
    try:
        out = float(value)
    except (TypeError, ValueError):
        raise GridError(f"{name} must be a number, got {value!r}") from None
    if not math.isfinite(out):
        raise GridError(f"{name} must be finite, got {value!r}")
    return out


@dataclass(frozen=True)
class FruxelGrid:
    """Geometry of a fruxel grid (conventions section 1). Immutable and hashable; validated on construction.

    Raises:
        GridError: a non-positive or non-integer size, ``z_near <= 0``, ``z_far <= z_near``, a field of view
            outside (0, 180) degrees, a non-finite number, or more than ``MAX_CELLS`` cells.
    """

    width: int
    """W: number of columns across (along x / u)."""
    height: int
    """H: number of rows down (along y / v)."""
    depth: int
    """D: number of depth slices (along z)."""
    z_near: float
    """Distance of the first slice plane from the optical centre, metres, > 0."""
    z_far: float
    """Distance of the last slice plane, metres, > z_near."""
    hfov: float
    """Horizontal field of view in degrees, 0 < hfov < 180."""

    def __post_init__(self) -> None:
        for name in ("width", "height", "depth"):
            object.__setattr__(self, name, _as_int(name, getattr(self, name)))
        for name in ("z_near", "z_far", "hfov"):
            object.__setattr__(self, name, _as_float(name, getattr(self, name)))
        if self.z_near <= 0:
            raise GridError(f"z_near must be > 0, got {self.z_near}")
        if self.z_far <= self.z_near:
            raise GridError(f"z_far must be > z_near, got z_near={self.z_near}, z_far={self.z_far}")
        if not 0 < self.hfov < 180:
            raise GridError(f"hfov must be in (0, 180) degrees, got {self.hfov}")
        if self.width * self.height * self.depth > MAX_CELLS:
            raise GridError(f"grid of {self.width}x{self.height}x{self.depth} cells exceeds the limit of {MAX_CELLS}")

    # ------------------------------------------------------------------ sizes and plane boundaries
    @property
    def shape(self) -> tuple[int, int, int]:
        """Label volume shape ``(D, H, W)``."""
        return (self.depth, self.height, self.width)

    @property
    def n_cells(self) -> int:
        """Number of cells, ``D * H * W``."""
        return self.depth * self.height * self.width

    @property
    def tu(self) -> float:
        """Half extent of ``u = x / z``: ``tan(hfov / 2)``."""
        return math.tan(math.radians(self.hfov) / 2.0)

    @property
    def tv(self) -> float:
        """Half extent of ``v = y / z``: ``tu * H / W`` (square pixels)."""
        return self.tu * self.height / self.width

    @property
    def du(self) -> float:
        """Width of one column in u, ``2 tu / W``."""
        return 2.0 * self.tu / self.width

    @property
    def dv(self) -> float:
        """Height of one row in v, ``2 tv / H``."""
        return 2.0 * self.tv / self.height

    @property
    def dz(self) -> float:
        """Thickness of one slice in metres, ``(z_far - z_near) / D``."""
        return (self.z_far - self.z_near) / self.depth

    def u_bounds(self) -> np.ndarray:
        """Column boundaries ``u_i``, i = 0..W: ``(W + 1,)`` float64, planes ``x = u_i z``."""
        return -self.tu + np.arange(self.width + 1, dtype=np.float64) * self.du

    def v_bounds(self) -> np.ndarray:
        """Row boundaries ``v_j``, j = 0..H: ``(H + 1,)`` float64, planes ``y = v_j z``."""
        return -self.tv + np.arange(self.height + 1, dtype=np.float64) * self.dv

    def z_bounds(self) -> np.ndarray:
        """Slice boundaries ``z_k``, k = 0..D: ``(D + 1,)`` float64, planes ``z = z_k``, metres."""
        return self.z_near + np.arange(self.depth + 1, dtype=np.float64) * self.dz

    # ------------------------------------------------------------------ indices
    def check_index(self, k: Any, j: Any, i: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Validate integer cell indices (any broadcastable shapes); returns them as int64 arrays.

        Raises:
            GridError: a non-integer or out-of-range index.
        """
        out = []
        for name, idx, n in (("k", k, self.depth), ("j", j, self.height), ("i", i, self.width)):
            a = np.asarray(idx)
            if a.dtype.kind not in "iu":
                raise GridError(f"cell index {name} must be integer, got dtype {a.dtype}")
            a = a.astype(np.int64)
            if a.size and (a.min() < 0 or a.max() >= n):
                raise GridError(f"cell index {name} out of range [0, {n})")
            out.append(a)
        return out[0], out[1], out[2]

    def flat_index(self, k: Any, j: Any, i: Any) -> np.ndarray:
        """Flat cell index ``(k * H + j) * W + i`` (conventions section 2), int64, the indices' broadcast shape."""
        k, j, i = self.check_index(k, j, i)
        return (k * self.height + j) * self.width + i

    def unflatten(self, flat: Any) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """Inverse of :meth:`flat_index`: ``(k, j, i)`` int64 arrays of ``flat``'s shape."""
        f = np.asarray(flat)
        if f.dtype.kind not in "iu":
            raise GridError(f"flat index must be integer, got dtype {f.dtype}")
        f = f.astype(np.int64)
        if f.size and (f.min() < 0 or f.max() >= self.n_cells):
            raise GridError(f"flat index out of range [0, {self.n_cells})")
        k, rem = np.divmod(f, self.height * self.width)
        j, i = np.divmod(rem, self.width)
        return k, j, i

    # ------------------------------------------------------------------ points and cells
    def cell_centres(self) -> np.ndarray:
        """Centres of all cells: ``(D, H, W, 3)`` float64, grid frame, metres (see the module docstring)."""
        k, j, i = np.meshgrid(
            np.arange(self.depth), np.arange(self.height), np.arange(self.width), indexing="ij"
        )
        return self.cell_to_point(k, j, i)

    def cell_to_point(self, k: Any, j: Any, i: Any) -> np.ndarray:
        """Centre point of cells ``(k, j, i)``: ``(..., 3)`` float64, grid frame, broadcast shape of the indices."""
        k, j, i = self.check_index(k, j, i)
        z = self.z_near + (k + 0.5) * self.dz
        u = -self.tu + (i + 0.5) * self.du
        v = -self.tv + (j + 0.5) * self.dv
        return np.stack(np.broadcast_arrays(u * z, v * z, z), axis=-1)

    def point_to_cell(self, points: Any) -> np.ndarray:
        """Cell containing each point: ``(..., 3)`` int64 ``(k, j, i)``, all -1 for points outside the frustum.

        Args:
            points: ``(..., 3)`` float, grid frame, metres. Non-finite points are outside.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.shape[-1:] != (3,):
            raise GridError(f"points must have shape (..., 3), got {p.shape}")
        x, y, z = p[..., 0], p[..., 1], p[..., 2]
        with np.errstate(divide="ignore", invalid="ignore"):
            kf = np.floor((z - self.z_near) / self.dz)
            ifl = np.floor((x / z + self.tu) / self.du)
            jf = np.floor((y / z + self.tv) / self.dv)
        inside = (
            np.isfinite(kf) & np.isfinite(ifl) & np.isfinite(jf) & (z > 0)
            & (kf >= 0) & (kf < self.depth) & (jf >= 0) & (jf < self.height) & (ifl >= 0) & (ifl < self.width)
        )
        out = np.full(p.shape[:-1] + (3,), -1, dtype=np.int64)
        out[inside] = np.stack([kf[inside], jf[inside], ifl[inside]], axis=-1).astype(np.int64)
        return out

    def cell_corners(self, k: Any, j: Any, i: Any) -> np.ndarray:
        """The 8 corners of cells ``(k, j, i)``: ``(..., 8, 3)`` float64, grid frame.

        Corner ``c`` is at ``(u_{i + (c & 1)}, v_{j + ((c >> 1) & 1)}, z_{k + (c >> 2)})``. Neighbouring cells
        get bit-identical shared corners, because each corner is computed from its boundary indices alone.
        """
        k, j, i = (a[..., None] for a in self.check_index(k, j, i))
        c = np.arange(8)
        return self.corner_points(k + (c >> 2), j + ((c >> 1) & 1), i + (c & 1))

    def corner_points(self, kb: Any, jb: Any, ib: Any) -> np.ndarray:
        """Lattice points at boundary indices ``(kb, jb, ib)`` (0..D, 0..H, 0..W): ``(..., 3)`` float64.

        The point is ``(u_ib z_kb, v_jb z_kb, z_kb)``; every mesh vertex in fruxel comes from here, so
        equal boundary indices always give bit-identical coordinates.
        """
        kb, jb, ib = (np.asarray(a, dtype=np.int64) for a in (kb, jb, ib))
        z = self.z_near + kb * self.dz
        u = -self.tu + ib * self.du
        v = -self.tv + jb * self.dv
        return np.stack(np.broadcast_arrays(u * z, v * z, z), axis=-1)

    def slice_volumes(self) -> np.ndarray:
        """Volume of one cell in each slice, m^3: ``(D,)`` float64 (all cells of a slice are congruent in area).

        A cell is a frustum piece of cross-section ``du dv z^2``, so its volume is
        ``du dv (z_{k+1}^3 - z_k^3) / 3``.
        """
        zb = self.z_bounds()
        return self.du * self.dv * (zb[1:] ** 3 - zb[:-1] ** 3) / 3.0

    def cell_volumes(self) -> np.ndarray:
        """Volume of every cell, m^3: ``(D, H, W)`` float64."""
        return np.broadcast_to(self.slice_volumes()[:, None, None], self.shape).copy()

    def cell_extent(self) -> np.ndarray:
        """Size of the cells of each slice at their centre depth, metres: ``(D, 3)`` float64 (dx, dy, dz)."""
        zc = self.z_near + (np.arange(self.depth) + 0.5) * self.dz
        return np.stack([self.du * zc, self.dv * zc, np.full_like(zc, self.dz)], axis=-1)

    def frustum_corners(self) -> np.ndarray:
        """The 8 corners of the frustum: ``(8, 3)`` float64, grid frame, in :meth:`cell_corners` order (bit 0: far
        u side, bit 1: far v side, bit 2: far slice)."""
        c = np.arange(8)
        return self.corner_points((c >> 2) * self.depth, ((c >> 1) & 1) * self.height, (c & 1) * self.width)

    def bounds(self) -> np.ndarray:
        """Axis-aligned bounding box of the frustum: ``(2, 3)`` float64, rows min and max, grid frame."""
        corners = self.frustum_corners()
        return np.stack([corners.min(axis=0), corners.max(axis=0)])

    def centre(self) -> np.ndarray:
        """Centre of the frustum's bounding box, ``(3,)`` float64, grid frame: the look-at target for orbits."""
        return self.bounds().mean(axis=0)

    # ------------------------------------------------------------------ cameras
    def camera(self) -> Camera:
        """The grid's own camera: identity pose, W x H pixels, ``fx = fy = W / (2 tu)``, ``cx = W/2``, ``cy = H/2``.

        Its pixel ``(i, j)`` looks down column ``(j, i)`` through the centres of all the column's cells.
        """
        from .camera import Camera

        f = self.width / (2.0 * self.tu)
        return Camera(fx=f, fy=f, cx=self.width / 2.0, cy=self.height / 2.0, width=self.width, height=self.height)

    # ------------------------------------------------------------------ serialisation
    def to_dict(self) -> dict[str, Any]:
        """Plain-JSON dictionary of the six parameters."""
        return asdict(self)

    @classmethod
    def from_dict(cls, d: Any) -> FruxelGrid:
        """Inverse of :meth:`to_dict`. Raises ``GridError`` on missing, extra or invalid keys."""
        if not isinstance(d, dict):
            raise GridError(f"grid must be a JSON object, got {type(d).__name__}")
        names = ("width", "height", "depth", "z_near", "z_far", "hfov")
        missing = [n for n in names if n not in d]
        extra = sorted(set(d) - set(names))
        if missing or extra:
            raise GridError(f"grid keys: missing {missing}, unexpected {extra}")
        return cls(**{n: d[n] for n in names})

    def to_json(self) -> str:
        """JSON text of :meth:`to_dict`; floats round-trip exactly."""
        return json.dumps(self.to_dict())

    @classmethod
    def from_json(cls, text: str) -> FruxelGrid:
        """Inverse of :meth:`to_json`. Raises ``GridError`` on malformed text."""
        try:
            d = json.loads(text)
        except (TypeError, ValueError) as e:
            raise GridError(f"grid JSON is malformed: {e}") from None
        return cls.from_dict(d)

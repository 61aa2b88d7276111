"""The fruxel model container: a semantic label volume on a :class:`FruxelGrid` with its :class:`ClassTable`.

Labels are a ``(D, H, W)`` uint8 array indexed ``[k, j, i]`` (slice, row, column; conventions sections 1 and 2),
0 meaning empty. Float network outputs become labels through :func:`labels_from_scores`, which applies
conventions section 2's occupancy rule and is shared with the rest of the project.

Cartesian label grids (:meth:`FruxelModel.to_cartesian`, :meth:`FruxelModel.from_cartesian`) live in the grid
frame (OpenCV axes, metres) and are indexed ``[z, y, x]``, shape ``(Z, Y, X)``. ``origin`` is the *minimum
corner* of voxel ``[0, 0, 0]``, given as ``(x, y, z)``, and ``voxel_size`` is one edge length or
``(sx, sy, sz)``; voxel ``[z, y, x]`` covers ``origin + ([x, x+1) sx, [y, y+1) sy, [z, z+1) sz)`` and its centre
is ``origin + ((x + 0.5) sx, (y + 0.5) sy, (z + 0.5) sz)``. Resampling in either direction is by cell
centre: each target cell takes the label of the source cell that contains its centre.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from .classes import DEFAULT_CLASSES, ClassTable
from .errors import FruxelError
from .grid import MAX_CELLS, FruxelGrid


class ModelError(FruxelError, ValueError):
    """Raised for inconsistent model contents: labels of the wrong shape or dtype, labels outside the class
    table, non-finite scores, or malformed Cartesian grids and point sets."""


def _check_threshold(threshold: Any) -> float | None:
    if threshold is None:
        return None
    try:
        t = float(threshold)
    except (TypeError, ValueError):
        raise ModelError(f"threshold must be a number in [0, 1] or None, got {threshold!r}") from None
    if not 0.0 <= t <= 1.0:
        raise ModelError(f"threshold must be in [0, 1], got {threshold!r}")
    return t


def labels_from_scores(scores: Any, threshold: float | None = None, probs: bool = False, axis: int = 0) -> np.ndarray:
    """Labels from per-class scores, by conventions section 2's occupancy rule.

    A cell is occupied when its argmax class is not 0 or, where ``threshold`` is given, when
    ``1 - p(empty) >= threshold``. The label of an occupied cell is the argmax over the non-empty classes
    (ties go to the lowest label); an unoccupied cell gets 0.

    Args:
        scores: real array with the C classes along ``axis`` (e.g. ``(C, D, H, W)`` with ``axis=0`` or
            ``(B, C, D, H, W)`` with ``axis=1``, PyTorch NCDHW), channel 0 = empty; any float or integer
            dtype, or a CPU tensor that ``numpy.asarray`` accepts. 1 <= C <= 256.
        threshold: None for the argmax rule, else a number in [0, 1].
        probs: False: ``scores`` are logits and ``p`` is their softmax over the class axis. True: ``scores``
            are probabilities in [0, 1] and ``p(empty)`` is channel 0 as given (no renormalisation). Only the
            threshold rule depends on it, since softmax keeps the argmax.

    Returns:
        uint8 labels, the shape of ``scores`` without ``axis``.

    Raises:
        ModelError: non-numeric or non-finite scores, probabilities outside [0, 1], a bad threshold or axis,
            or more than 256 classes.
    """
    s = np.asarray(scores)
    if s.dtype.kind not in "fiu":
        raise ModelError(f"scores must be a real numeric array, got dtype {s.dtype}")
    if s.ndim == 0:
        raise ModelError("scores must have a class axis, got a scalar")
    if not -s.ndim <= axis < s.ndim:
        raise ModelError(f"axis {axis} out of range for scores of shape {s.shape}")
    s = np.moveaxis(s, axis, 0)
    n_classes = s.shape[0]
    if not 1 <= n_classes <= 256:
        raise ModelError(f"scores must have 1 to 256 classes along axis {axis}, got {n_classes}")
    t = _check_threshold(threshold)
    if s.dtype.kind == "f" and not np.all(np.isfinite(s)):
        raise ModelError("scores contain NaN or infinite values")
    if probs and s.size and (s.min() < 0 or s.max() > 1):
        raise ModelError(f"probabilities must lie in [0, 1], got range [{s.min()}, {s.max()}]; logits need probs=False")
    if n_classes == 1:
        return np.zeros(s.shape[1:], dtype=np.uint8)
    best = (np.argmax(s[1:], axis=0) + 1).astype(np.uint8)
    if t is None:
        # "The argmax over all C is not 0", with a tie against channel 0 going to 0 as in numpy's argmax.
        occupied = s[1:].max(axis=0) > s[0]
    elif probs:
        occupied = 1.0 - s[0].astype(np.float64) >= t
    else:
        # 1 - p(empty) as sum_{c>0} e_c / sum_c e_c avoids cancellation when p(empty) is close to 1.
        s64 = s.astype(np.float64)
        e = np.exp(s64 - s64.max(axis=0, keepdims=True))
        occupied = e[1:].sum(axis=0) / e.sum(axis=0) >= t
    return np.where(occupied, best, np.uint8(0))


def _as_origin_and_size(origin: Any, voxel_size: Any) -> tuple[np.ndarray, np.ndarray]:
    o = np.asarray(origin, dtype=np.float64)
    if o.shape != (3,) or not np.all(np.isfinite(o)):
        raise ModelError(f"origin must be 3 finite numbers (x, y, z), got {origin!r}")
    v = np.broadcast_to(np.asarray(voxel_size, dtype=np.float64), (3,)).copy()
    if not np.all(np.isfinite(v)) or np.any(v <= 0):
        raise ModelError(f"voxel_size must be positive and finite, got {voxel_size!r}")
    return o, v


def _check_labels(labels: Any, n_classes: int, what: str) -> np.ndarray:
    lab = np.asarray(labels)
    if lab.dtype.kind not in "iu":
        raise ModelError(f"{what} must be integers, got dtype {lab.dtype}")
    if lab.size and (lab.min() < 0 or lab.max() >= n_classes):
        raise ModelError(f"{what} must be in [0, {n_classes}) (the class table), got range [{lab.min()}, {lab.max()}]")
    return lab


@dataclass(frozen=True, eq=False)
class FruxelModel:
    """A semantic fruxel model: labels on a fruxel grid, with the names and colours of the classes.

    Models compare equal when their grids, class tables and labels are equal. They are not hashable.

    Raises:
        ModelError: on construction, for labels that are not integers, not of shape ``grid.shape``, or
            outside ``[0, len(classes))``; a grid or class table of the wrong type.
    """

    labels: np.ndarray
    """``(D, H, W)`` uint8 labels indexed ``[k, j, i]``, 0 = empty. Any integer input is validated, copied to
    uint8 and stored read-only; build a new model to change labels."""
    grid: FruxelGrid
    """Geometry of the cells."""
    classes: ClassTable = DEFAULT_CLASSES
    """Names and colours of the labels; every label is below ``len(classes)``."""

    def __post_init__(self) -> None:
        if not isinstance(self.grid, FruxelGrid):
            raise ModelError(f"grid must be a FruxelGrid, got {type(self.grid).__name__}")
        if not isinstance(self.classes, ClassTable):
            raise ModelError(f"classes must be a ClassTable, got {type(self.classes).__name__}")
        lab = np.asarray(self.labels)
        if lab.shape != self.grid.shape:
            raise ModelError(f"labels shape {lab.shape} does not match the grid's (D, H, W) = {self.grid.shape}")
        lab = _check_labels(lab, len(self.classes), "labels")
        out = np.array(lab, dtype=np.uint8, order="C")
        out.setflags(write=False)
        object.__setattr__(self, "labels", out)

    def __eq__(self, other: object) -> bool:
        if not isinstance(other, FruxelModel):
            return NotImplemented
        return self.grid == other.grid and self.classes == other.classes and np.array_equal(self.labels, other.labels)

    __hash__ = None  # type: ignore[assignment]

    def __repr__(self) -> str:
        g = self.grid
        return (f"FruxelModel({g.width}x{g.height}x{g.depth} cells, z {g.z_near:g}..{g.z_far:g} m, hfov {g.hfov:g}, "
                f"{self.n_occupied} occupied, {len(self.classes)} classes)")

    # ------------------------------------------------------------------ constructors
    @classmethod
    def empty(cls, grid: FruxelGrid, classes: ClassTable = DEFAULT_CLASSES) -> FruxelModel:
        """A model with every cell empty."""
        return cls(np.zeros(grid.shape, dtype=np.uint8), grid, classes)

    @classmethod
    def from_array(
        cls,
        array: Any,
        grid: FruxelGrid,
        classes: ClassTable = DEFAULT_CLASSES,
        threshold: float | None = None,
        probs: bool = False,
    ) -> FruxelModel:
        """A model from integer labels or from per-class float scores.

        Args:
            array: either integer labels ``(D, H, W)``, or float logits / probabilities ``(C, D, H, W)`` or
                ``(1, C, D, H, W)`` (NCDHW, channel 0 = empty) with ``C == len(classes)``; numpy arrays or CPU
                tensors. Floats become labels through :func:`labels_from_scores`.
            grid: the grid; its ``(D, H, W)`` must match the array's spatial shape.
            classes: the class table.
            threshold, probs: the occupancy rule for float input (see :func:`labels_from_scores`); they must
                keep their defaults for integer input.

        Raises:
            ModelError: a wrong shape or dtype, NaN or infinite scores, labels outside the class table.
        """
        a = np.asarray(array)
        if a.dtype.kind in "iu":
            if threshold is not None or probs:
                raise ModelError("threshold and probs apply to float scores, not to integer labels")
            if a.ndim != 3:
                raise ModelError(f"integer labels must have shape (D, H, W) = {grid.shape}, got {a.shape}")
            return cls(a, grid, classes)
        if a.dtype.kind != "f":
            raise ModelError(f"array must hold integer labels or float scores, got dtype {a.dtype}")
        if a.ndim == 5:
            if a.shape[0] != 1:
                raise ModelError(f"a batch of {a.shape[0]} volumes makes {a.shape[0]} models; pass one (C, D, H, W)")
            a = a[0]
        if a.ndim != 4:
            raise ModelError(f"float scores must have shape (C, D, H, W) or (1, C, D, H, W), got {np.shape(array)}")
        if a.shape[0] != len(classes):
            raise ModelError(f"scores have {a.shape[0]} channels but the class table has {len(classes)} classes")
        if a.shape[1:] != grid.shape:
            raise ModelError(f"scores spatial shape {a.shape[1:]} does not match the grid's (D, H, W) = {grid.shape}")
        return cls(labels_from_scores(a, threshold=threshold, probs=probs, axis=0), grid, classes)

    @classmethod
    def from_cartesian(
        cls,
        labels_xyz: Any,
        origin: Any,
        voxel_size: Any,
        grid: FruxelGrid,
        classes: ClassTable = DEFAULT_CLASSES,
    ) -> FruxelModel:
        """A model from a Cartesian label grid: each cell takes the label of the voxel containing its centre.

        Args:
            labels_xyz: ``(Z, Y, X)`` integer labels indexed ``[z, y, x]``, grid frame (module docstring).
            origin: ``(3,)`` ``(x, y, z)`` of the minimum corner of voxel ``[0, 0, 0]``, grid frame, metres.
            voxel_size: voxel edge in metres, a number or ``(sx, sy, sz)``.
            grid, classes: the fruxel grid and the class table; labels must be below ``len(classes)``.

        Returns:
            The model; cells whose centre lies outside the Cartesian grid are empty.
        """
        lab = np.asarray(labels_xyz)
        if lab.ndim != 3:
            raise ModelError(f"labels_xyz must have shape (Z, Y, X), got {lab.shape}")
        lab = _check_labels(lab, len(classes), "labels_xyz")
        o, v = _as_origin_and_size(origin, voxel_size)
        out = np.zeros(grid.shape, dtype=np.uint8)
        nx, ny, nz = lab.shape[2], lab.shape[1], lab.shape[0]
        for k in range(grid.depth):
            # One slice at a time keeps the centre buffer at (H, W, 3) for large grids.
            c = grid.cell_to_point(k, np.arange(grid.height)[:, None], np.arange(grid.width)[None, :])
            idx = np.floor((c - o) / v)
            inside = np.all(idx >= 0, axis=-1) & (idx[..., 0] < nx) & (idx[..., 1] < ny) & (idx[..., 2] < nz)
            ix, iy, iz = (idx[..., a][inside].astype(np.int64) for a in range(3))
            out[k][inside] = lab[iz, iy, ix]
        return cls(out, grid, classes)

    @classmethod
    def from_points(
        cls, points: Any, labels: Any, grid: FruxelGrid, classes: ClassTable = DEFAULT_CLASSES
    ) -> FruxelModel:
        """A model from labelled points: each cell takes the majority label of the points inside it.

        The rule: points outside the frustum are dropped; a point labelled 0 carries no class and does not
        vote, so a cell is occupied exactly when at least one non-empty point falls in it; among the labels of
        the points in a cell the most frequent wins, and ties go to the lowest label.

        Args:
            points: ``(N, 3)`` float, grid frame, metres; finite.
            labels: ``(N,)`` integer labels below ``len(classes)``.
            grid, classes: the fruxel grid and the class table.

        Raises:
            ModelError: wrong shapes, non-finite points, labels outside the class table.
        """
        p = np.asarray(points, dtype=np.float64)
        if p.ndim != 2 or p.shape[1] != 3:
            raise ModelError(f"points must have shape (N, 3), got {p.shape}")
        if not np.all(np.isfinite(p)):
            raise ModelError("points contain NaN or infinite coordinates")
        lab = np.asarray(labels)
        if lab.shape != (p.shape[0],):
            raise ModelError(f"labels must have shape ({p.shape[0]},) to match the points, got {lab.shape}")
        lab = _check_labels(lab, len(classes), "point labels").astype(np.int64)
        cells = grid.point_to_cell(p)
        keep = (cells[:, 0] >= 0) & (lab > 0)
        flat = (cells[keep, 0] * grid.height + cells[keep, 1]) * grid.width + cells[keep, 2]
        out = np.zeros(grid.n_cells, dtype=np.uint8)
        if flat.size:
            n = len(classes)
            pairs, counts = np.unique(flat * n + lab[keep], return_counts=True)
            cell, label = np.divmod(pairs, n)
            # Sorted by cell, then by count descending, then by label ascending: the first row of each cell wins.
            order = np.lexsort((label, -counts, cell))
            cell, label = cell[order], label[order]
            first = np.ones(cell.size, dtype=bool)
            first[1:] = cell[1:] != cell[:-1]
            out[cell[first]] = label[first]
        return cls(out.reshape(grid.shape), grid, classes)

    # ------------------------------------------------------------------ queries
    @property
    def occupied(self) -> np.ndarray:
        """``(D, H, W)`` bool mask of the occupied (non-empty) cells."""
        return self.labels != 0

    @property
    def n_occupied(self) -> int:
        """Number of occupied cells."""
        return int(np.count_nonzero(self.labels))

    def counts(self) -> np.ndarray:
        """Number of cells of each class: ``(C,)`` int64, entry ``c`` for label ``c`` (empty cells included)."""
        return np.bincount(self.labels.ravel(), minlength=len(self.classes)).astype(np.int64)

    def colours(self) -> np.ndarray:
        """Display colour of every cell: ``(D, H, W, 3)`` uint8 RGB from the class table."""
        return self.classes.colour_of(self.labels)

    # ------------------------------------------------------------------ conversions
    def to_points(self) -> tuple[np.ndarray, np.ndarray]:
        """Centres and labels of the occupied cells, in flat-index order.

        Returns:
            points: ``(N, 3)`` float64 cell centres, grid frame, metres (:meth:`FruxelGrid.cell_to_point`).
            labels: ``(N,)`` uint8 labels, all > 0.
        """
        k, j, i = np.nonzero(self.labels)
        return self.grid.cell_to_point(k, j, i).reshape(-1, 3), self.labels[k, j, i].copy()

    def to_cartesian(self, origin: Any, voxel_size: Any, shape: Any) -> np.ndarray:
        """Resample onto a Cartesian grid: each voxel takes the label of the cell containing its centre.

        Args:
            origin: ``(3,)`` ``(x, y, z)`` of the minimum corner of voxel ``[0, 0, 0]``, grid frame, metres.
            voxel_size: voxel edge in metres, a number or ``(sx, sy, sz)``.
            shape: ``(Z, Y, X)`` number of voxels along z, y and x.

        Returns:
            ``(Z, Y, X)`` uint8 labels indexed ``[z, y, x]``; 0 where the voxel centre is outside the frustum.
        """
        o, v = _as_origin_and_size(origin, voxel_size)
        try:
            nz, ny, nx = (int(s) for s in shape)
        except (TypeError, ValueError):
            raise ModelError(f"shape must be (Z, Y, X), got {shape!r}") from None
        if min(nz, ny, nx) < 0 or nz * ny * nx > MAX_CELLS:
            raise ModelError(f"shape must be 3 non-negative sizes of at most {MAX_CELLS} voxels in all, got {shape!r}")
        out = np.zeros((nz, ny, nx), dtype=np.uint8)
        xs = o[0] + (np.arange(nx) + 0.5) * v[0]
        ys = o[1] + (np.arange(ny) + 0.5) * v[1]
        for z in range(nz):
            # One z-plane at a time bounds the point buffer at (Y, X, 3).
            pts = np.empty((ny, nx, 3))
            pts[..., 0] = xs[None, :]
            pts[..., 1] = ys[:, None]
            pts[..., 2] = o[2] + (z + 0.5) * v[2]
            cells = self.grid.point_to_cell(pts)
            inside = cells[..., 0] >= 0
            out[z][inside] = self.labels[cells[inside, 0], cells[inside, 1], cells[inside, 2]]
        return out

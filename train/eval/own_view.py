"""Where own-view first-hit errors come from: the truth against what the camera actually sees.

The ground truth labels a cell by the solid that contains its *centre* (SPEC section 4, ``fruxelize``); the own
view's first hit is a column's first occupied cell. A camera, and so a network reading its image, sees the first
*surface* along the column instead. The two disagree where a solid along the column's centre ray contains no cell
centre (a board thinner than a cell's depth, 0.12 m at 64^3 over 0.5-8 m: the truth shows the wall behind it, or
a lattice of the board's cells where it happens to cross centres), and where the camera is closer than ``z_near``
to a surface (the image shows that surface; the truth starts behind it). :func:`visible_surface` casts each
column's centre ray against the scene's labelled meshes, and :class:`OwnViewBreakdown` splits the truth's own-view
pixels into

* ``clean``: the first surface seen lies in ``[z_near, z_far]`` and carries the truth's label,
* ``aliased``: it lies in that range but carries another label than the truth's first occupied cell,
* ``near``: the camera is closer than ``z_near`` to the first surface it sees,
* ``far``: the first surface seen lies beyond ``z_far``, or nothing is hit (the truth still hits: a rare grazing
  case),

and counts a prediction's own-view accuracy in each (``scripts/own_view_errors.py``). :func:`surface_extent` splits
the clean pixels further by how deep the first solid is along the ray: under a slice, whether the truth keeps it
depends on where within the slice it lies.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fruxel.grid import FruxelGrid

CATEGORIES = ("clean", "aliased", "near", "far")
"""The kinds of own-view pixel, in the order of :attr:`OwnViewBreakdown.hits`."""


class JoinedMeshes:
    """Labelled meshes joined into one mesh for many :func:`visible_surface` calls (the ray queries' acceleration
    structure is built with the first call and kept, as ``fruxelize``'s ``MeshSet`` keeps its upload).

    Args:
        meshes: ``(vertices (V, 3) float, faces (F, 3) int, label)`` per solid, world frame, metres (the input of
            ``fruxelize``, e.g. ``Scene.labelled_meshes()``).
    """

    def __init__(self, meshes: Sequence[tuple[np.ndarray, np.ndarray, int]]) -> None:
        import trimesh

        verts = [np.asarray(v, dtype=np.float64) for v, _, _ in meshes]
        start = np.cumsum([0] + [len(v) for v in verts[:-1]])
        faces = np.concatenate([np.asarray(f, dtype=np.int64) + s for (_, f, _), s in zip(meshes, start, strict=True)])
        self.mesh = trimesh.Trimesh(np.concatenate(verts), faces, process=False)
        """The joined mesh."""
        self.face_label = np.concatenate([np.full(len(f), int(lab), dtype=np.int64) for _, f, lab in meshes])
        """``(F,)`` int64 label of each face of :attr:`mesh`."""


def visible_surface(meshes: JoinedMeshes | Sequence[tuple[np.ndarray, np.ndarray, int]], grid: FruxelGrid,
                    pose: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first surface along each grid column's centre ray, as a camera sees it.

    Args:
        meshes: a :class:`JoinedMeshes` (faster for many poses of one scene), or the labelled meshes it takes.
        grid: the grid.
        pose: ``(4, 4)`` grid-camera-to-world transform, OpenCV axes.

    Returns:
        ``(labels (H, W) int64, depth (H, W) float64)``: the label of the first mesh surface hit and its depth along
        the camera's z axis in metres (from the optical centre, not from ``z_near``); 0 and ``inf`` where the ray
        hits nothing.
    """
    joined = meshes if isinstance(meshes, JoinedMeshes) else JoinedMeshes(meshes)
    pose = np.asarray(pose, dtype=np.float64)
    dirs = _centre_rays(grid, pose)
    origins = np.repeat(pose[None, :3, 3], len(dirs), axis=0)
    tri, ray, loc = _first_crossing(joined, origins, dirs)
    labels = np.zeros(len(dirs), dtype=np.int64)
    depth = np.full(len(dirs), np.inf)
    labels[ray] = joined.face_label[tri]
    depth[ray] = (loc - origins[ray]) @ pose[:3, 2]
    return labels.reshape(grid.height, grid.width), depth.reshape(grid.height, grid.width)


def surface_extent(meshes: JoinedMeshes, grid: FruxelGrid, pose: np.ndarray, depth: np.ndarray) -> np.ndarray:
    """How deep, along each column's centre ray, the solid behind the first surface of :func:`visible_surface`
    reaches: the depth of the next surface the ray crosses (the solid's back face, for the closed, separate solids
    of a simulated room) minus the first surface's.

    A solid thinner than a slice (``grid.dz``) along the ray holds a cell centre or not depending on where, within
    a slice, it lies: whether the truth keeps it is a matter of centimetres that the image barely shows.

    Args:
        meshes: the scene's :class:`JoinedMeshes`.
        grid: the grid.
        pose: ``(4, 4)`` grid-camera-to-world transform, OpenCV axes.
        depth: ``(H, W)`` float64 first-surface depths of :func:`visible_surface` (``inf``: nothing hit).

    Returns:
        ``(H, W)`` float64 extent along the camera's z axis in metres; ``inf`` where nothing is hit, or where the
        ray finds no surface behind the first one.
    """
    # From just behind the first surface: the ray is inside the solid, and its first crossing is the way out.
    _, rows, travelled = _cast_on(meshes, grid, pose, depth)
    extent = np.full(grid.height * grid.width, np.inf)
    extent[rows] = travelled
    return extent.reshape(grid.height, grid.width)


def label_behind(meshes: JoinedMeshes, grid: FruxelGrid, pose: np.ndarray, depth: np.ndarray,
                 extent: np.ndarray) -> np.ndarray:
    """The label of the next surface along each column's centre ray behind the first solid: what the truth shows
    there when that solid holds no cell centre (when the solid behind it holds one).

    Args:
        meshes: the scene's :class:`JoinedMeshes`.
        grid: the grid.
        pose: ``(4, 4)`` grid-camera-to-world transform, OpenCV axes.
        depth: ``(H, W)`` float64 first-surface depths of :func:`visible_surface` (``inf``: nothing hit).
        extent: ``(H, W)`` float64 :func:`surface_extent` of the same view.

    Returns:
        ``(H, W)`` int64 label of the first surface behind the first solid's back face; 0 where there is none.
    """
    # From just behind the back face: outside the solid, the next crossing is the next solid's front.
    back = np.asarray(depth, dtype=np.float64) + np.asarray(extent, dtype=np.float64)
    tri, rows, _ = _cast_on(meshes, grid, pose, back)
    out = np.zeros(grid.height * grid.width, dtype=np.int64)
    out[rows] = meshes.face_label[tri]
    return out.reshape(grid.height, grid.width)


def _cast_on(meshes: JoinedMeshes, grid: FruxelGrid, pose: np.ndarray, depth: np.ndarray
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Each column's centre ray cast again from just behind ``depth`` (``(H, W)`` metres; ``inf``: not cast) to its
    next crossing with the mesh: ``(face (K,), row-major column (K,), depth travelled from ``depth`` (K,))`` for the
    K rays that cross it."""
    pose = np.asarray(pose, dtype=np.float64)
    start = np.asarray(depth, dtype=np.float64).reshape(-1)
    cast = np.isfinite(start)
    if not cast.any():
        return np.zeros(0, dtype=np.int64), np.zeros(0, dtype=np.int64), np.zeros(0)
    eps = 1e-4  # past the surface at `depth`, so that it is not crossed again
    dirs = _centre_rays(grid, pose)[cast]
    origins = pose[None, :3, 3] + dirs * (start[cast, None] + eps)
    tri, ray, loc = _first_crossing(meshes, origins, dirs)
    return tri, np.flatnonzero(cast)[ray], (loc - origins[ray]) @ pose[:3, 2] + eps


def _centre_rays(grid: FruxelGrid, pose: np.ndarray) -> np.ndarray:
    """``(H * W, 3)`` float64 world-frame directions of the columns' centre rays, row-major, scaled to z = 1 in
    the camera frame (so that a ray parameter is a depth)."""
    j, i = np.meshgrid(np.arange(grid.height), np.arange(grid.width), indexing="ij")
    d = grid.cell_to_point(np.zeros_like(j), j, i).reshape(-1, 3)
    return (d / d[:, 2:3]) @ pose[:3, :3].T


def _first_crossing(meshes: JoinedMeshes, origins: np.ndarray, dirs: np.ndarray) -> tuple[np.ndarray, np.ndarray,
                                                                                      np.ndarray]:
    """The first crossing of each ray with the joined mesh: ``(face (K,), ray (K,), location (K, 3))`` for the K
    rays that cross it (trimesh's ``intersects_id`` without multiple hits)."""
    return meshes.mesh.ray.intersects_id(origins, dirs, multiple_hits=False, return_locations=True)


@dataclass
class OwnViewBreakdown:
    """Own-view pixels where the truth hits, by :data:`CATEGORIES`, and how many a prediction gets right in each."""

    hits: np.ndarray = field(default_factory=lambda: np.zeros(len(CATEGORIES), dtype=np.int64))
    """Pixels per category."""
    correct: np.ndarray = field(default_factory=lambda: np.zeros(len(CATEGORIES), dtype=np.int64))
    """... of which the prediction's first hit has the truth's label."""
    thin_hits: int = 0
    """``clean`` pixels whose first solid is thinner than a slice along the ray (counted when
    :meth:`add` gets ``seen_extent``)."""
    thin_correct: int = 0
    """... of which the prediction's first hit has the truth's label."""
    extents: int = 0
    """Views counted with ``seen_extent``."""

    def add(self, pred: np.ndarray, truth: np.ndarray, seen_label: np.ndarray, seen_depth: np.ndarray,
            grid: FruxelGrid, seen_extent: np.ndarray | None = None) -> None:
        """Count one view.

        Args:
            pred, truth: ``(H, W)`` integer labels of each column's first occupied cell (0 = none), e.g.
                :func:`fruxel.train.eval.metrics.first_surface` of the prediction and of the truth.
            seen_label, seen_depth: :func:`visible_surface` of the same view.
            grid: the grid.
            seen_extent: ``(H, W)`` :func:`surface_extent` of the same view, to split the clean pixels into thin
                (first solid under ``grid.dz`` deep along the ray) and the rest; None: not split.
        """
        hit = truth != 0
        in_range = (seen_depth >= grid.z_near) & (seen_depth <= grid.z_far)
        kinds = (in_range & (seen_label == truth), in_range & (seen_label != truth), seen_depth < grid.z_near,
                 seen_depth > grid.z_far)
        ok = pred == truth
        for c, m in enumerate(kinds):
            self.hits[c] += int((hit & m).sum())
            self.correct[c] += int((hit & m & ok).sum())
        if seen_extent is not None:
            thin = hit & kinds[0] & (seen_extent < grid.dz)
            self.thin_hits += int(thin.sum())
            self.thin_correct += int((thin & ok).sum())
            self.extents += 1

    def summary(self) -> dict[str, Any]:
        """Per category: its share of the truth's own-view pixels and the prediction's accuracy there (percent,
        None for an empty category); ``accuracy``: over all of them; ``lost``: points of that accuracy lost in each
        category. With extents counted, ``clean_thin`` and ``clean_thick`` split the clean pixels the same way."""
        total = int(self.hits.sum())

        def part(n: int, k: int) -> dict[str, float | None]:
            return {"share": 100.0 * n / total if total else None, "accuracy": 100.0 * k / n if n else None,
                    "lost": 100.0 * (n - k) / total if total else None}

        out: dict[str, Any] = {"pixels": total,
                               "accuracy": 100.0 * int(self.correct.sum()) / total if total else None}
        for c, name in enumerate(CATEGORIES):
            n, k = int(self.hits[c]), int(self.correct[c])
            out[name] = part(n, k)
        if self.extents:
            n, k = int(self.hits[0]), int(self.correct[0])
            out["clean_thin"] = part(self.thin_hits, self.thin_correct)
            out["clean_thick"] = part(n - self.thin_hits, k - self.thin_correct)
        return out


def holds_centre(depth: np.ndarray, extent: np.ndarray, grid: FruxelGrid) -> np.ndarray:
    """Whether a solid that a column's centre ray crosses from ``depth`` to ``depth + extent`` holds one of the
    column's cell centres (slice centres at ``z_near + (k + 1/2) dz``), i.e. whether the truth keeps it.

    Args:
        depth: first-surface depths along the camera's z axis, metres (any shape, float).
        extent: the solid's depth along the ray from there, metres (same shape; :func:`surface_extent`).
        grid: the grid.

    Returns:
        bool array of the same shape. Only the slices' spacing is used: a solid partly outside
        ``[z_near, z_far]`` is judged as if the slices went on.
    """
    dz = grid.dz
    first = grid.z_near + 0.5 * dz
    centre = first + np.ceil((np.asarray(depth, dtype=np.float64) - first) / dz) * dz  # the first at or behind depth
    return centre <= np.asarray(depth, dtype=np.float64) + np.asarray(extent, dtype=np.float64)


def depth_reader_accuracy(depth: np.ndarray, extent: np.ndarray, right_if_kept: np.ndarray,
                          right_if_dropped: np.ndarray, grid: FruxelGrid, sigma: float, draws: int = 32,
                          seed: int = 0) -> float:
    """How often an idealised reader of the image gets a thin solid's own-view pixel right, when it knows the solid's
    depth only to a Gaussian error of ``sigma``.

    The reader knows everything else: the solid's label, its extent along the ray, and what lies behind it. Seeing
    depth ``d + e`` (``e ~ N(0, sigma)``), it takes the solid's true start as ``N(d + e, sigma)`` and calls the solid
    kept when that makes :func:`holds_centre` at least as likely as not; it then answers the solid's label, else the
    label behind it. ``sigma = 0`` is a reader that knows the depth exactly; ``sigma = inf`` one that knows nothing
    of where within a slice the solid lies (it calls a solid kept when its extent is at least half a slice). An upper
    bound on what a network that reads depth that well can do, as far as :func:`holds_centre` is the truth's rule.

    Args:
        depth: ``(N,)`` float first-surface depths of the thin solids' pixels, metres.
        extent: ``(N,)`` float their extents along the ray, metres (under ``grid.dz``: thicker solids always hold a
            centre).
        right_if_kept: ``(N,)`` bool: the truth's first label is the solid's.
        right_if_dropped: ``(N,)`` bool: the truth's first label is the one behind the solid
            (:func:`label_behind`); both are true where the solid and what lies behind it share a label.
        grid: the grid.
        sigma: the reader's depth error (standard deviation), metres, >= 0 or ``inf``.
        draws: depth errors drawn per pixel.
        seed: seed of the draws.

    Returns:
        The share of the N pixels answered right, in [0, 1] (nan for N = 0).

    Raises:
        ValueError: ``sigma`` negative or NaN, or ``draws`` < 1.
    """
    if not sigma >= 0 or draws < 1:
        raise ValueError(f"sigma must be >= 0 and draws >= 1, got sigma={sigma}, draws={draws}")
    depth = np.asarray(depth, dtype=np.float64).reshape(-1)
    extent = np.asarray(extent, dtype=np.float64).reshape(-1)
    if_kept = np.asarray(right_if_kept, dtype=bool).reshape(-1)
    if_dropped = np.asarray(right_if_dropped, dtype=bool).reshape(-1)
    if not len(depth):
        return float("nan")
    dz = grid.dz

    def share(kept: np.ndarray) -> float:
        return float(np.where(kept, if_kept, if_dropped).mean())

    if sigma == 0:
        return share(holds_centre(depth, extent, grid))
    if np.isinf(sigma):
        return share(extent >= 0.5 * dz)
    from scipy.special import ndtr

    rng = np.random.default_rng(seed)
    first = grid.z_near + 0.5 * dz
    wraps = np.arange(-int(np.ceil(6.0 * sigma / dz)) - 1, int(np.ceil(6.0 * sigma / dz)) + 2) * dz  # (M,)
    right = 0.0
    for _ in range(draws):
        seen = depth + rng.normal(0.0, sigma, size=depth.shape)
        # The solid holds a centre when its true start lies within `extent` before one: start - centre in
        # [-extent, 0]; under the reader's belief, that probability summed over the centres near the seen start.
        offset = np.mod(seen - first, dz)[:, None] + wraps[None, :]  # (N, M): seen start minus each centre
        p = (ndtr((offset + extent[:, None]) / sigma) - ndtr(offset / sigma)).sum(axis=1)
        right += share(p >= 0.5)
    return right / draws


def fine_depth_estimate(fine_logits: np.ndarray, grid: FruxelGrid) -> np.ndarray:
    """Each column's first-surface depth as the fine depth head reads it (``model.fine_depth``): the mean of the
    bins' centres within one slice of its most likely bin, weighted by their probabilities.

    Args:
        fine_logits: ``(..., D * R + 1, H, W)`` float logits of the head (last bin: no surface).
        grid: the model's grid (D, z_near, slice thickness).

    Returns:
        ``(..., H, W)`` float64 camera-frame depths, metres; ``inf`` where "no surface" is the most likely bin.
    """
    logits = np.asarray(fine_logits, dtype=np.float64)
    n = logits.shape[-3] - 1
    bins = n // grid.depth
    if bins < 1 or n != bins * grid.depth:
        raise ValueError(f"fine_logits need D * R + 1 channels for D = {grid.depth}, got {n + 1}")
    p = np.exp(logits - logits.max(axis=-3, keepdims=True))
    p /= p.sum(axis=-3, keepdims=True)
    best = p.argmax(axis=-3)
    idx = np.arange(n).reshape(n, 1, 1)
    near = np.where(np.abs(idx - np.expand_dims(best, -3)) <= bins, p[..., :n, :, :], 0.0)
    centres = (grid.z_near + (np.arange(n) + 0.5) * grid.dz / bins).reshape(n, 1, 1)
    z = (near * centres).sum(axis=-3) / np.maximum(near.sum(axis=-3), 1e-12)
    return np.where(best == n, np.inf, z)


LABEL_SOURCES = ("model", "volume", "head", "both")
"""The names :func:`first_label_sources` returns, in order."""


def first_label_sources(raw: Any, surface_logits: Any, ruled: Any) -> dict[str, np.ndarray]:
    """Each column's own-view label with the class of its first occupied cell taken from other sources.

    The volume after the model's inference rules (``ruled``) decides which columns have a first occupied cell; its
    class is then read

    * ``model``: from the ruled volume itself (what the model predicts),
    * ``volume``: as the column's most likely first hit from the raw volume (:func:`~fruxel.train.models.generator.
      first_hit_classes`, what the ``first_hit_label`` rule gives),
    * ``head``: from the surface head alone (its most likely class other than "no surface"),
    * ``both``: from the two together, the sum of their log-probabilities (as if independent evidence).

    Only the class changes: a column that the ruled volume leaves empty is 0 under every source, so it stays wrong
    wherever the truth has a surface.

    Args:
        raw: ``(B, C, D, H, W)`` float tensor, the network's logits before the inference rules, grid frame.
        surface_logits: ``(B, C, H, W)`` float tensor, the surface head's logits (channel 0 = no surface).
        ruled: ``(B, C, D, H, W)`` float tensor, the logits after the model's rules (its eval-mode output).

    Returns:
        Source name -> ``(B, H, W)`` int64 labels (numpy), 0 where the ruled volume leaves the column empty.
    """
    import torch

    from ..models.generator import first_hit_log_probs
    from .metrics import first_surface

    model = first_surface(ruled.argmax(dim=1))
    has = model != 0
    volume = first_hit_log_probs(raw)[:, 1:]
    head = torch.log_softmax(surface_logits.float(), dim=1)[:, 1:]
    out = {LABEL_SOURCES[0]: model}
    for name, score in zip(LABEL_SOURCES[1:], (volume, head, volume + head), strict=True):
        out[name] = torch.where(has, score.argmax(dim=1) + 1, torch.zeros_like(model))
    return {k: v.cpu().numpy().astype(np.int64) for k, v in out.items()}


def plot_depth_readers(readers: Sequence[dict[str, float]], model_own: float, path: str, *, target: float = 97.0,
                       title: str = "") -> None:
    """Write a PNG of the own view that readers of thin solids with each depth error would give (the model's answers
    elsewhere), against the model's own view and the target.

    Args:
        readers: ``{"sigma": metres (inf allowed), "own_view": percent}`` per reader (``scripts/own_view_errors.py``).
        model_own: the model's own-view accuracy, percent.
        path: the PNG (written atomically).
        target: the own view's target, percent, drawn as a line.
        title: the figure's title.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fruxel.io import atomic_path

    finite = sorted((float(r["sigma"]), float(r["own_view"])) for r in readers if np.isfinite(float(r["sigma"])))
    blind = [float(r["own_view"]) for r in readers if not np.isfinite(float(r["sigma"]))]
    fig, ax = plt.subplots(figsize=(6.4, 3.8))
    if finite:
        xs, ys = zip(*finite, strict=True)
        ax.plot([100.0 * x for x in xs], ys, "o-", color="#1b9e77", label="reader of thin solids with this depth error")
    if blind:
        ax.axhline(blind[0], color="#1b9e77", ls=":", label="... with no depth within the slice")
    ax.axhline(model_own, color="#d95f02", ls="--", label=f"the model ({model_own:.2f} %)")
    ax.axhline(target, color="#7570b3", ls="-.", label=f"target ({target:g} %)")
    ax.set_xlabel("depth error of the reader (standard deviation, cm)")
    ax.set_ylabel("own-view first-hit accuracy (%)")
    ax.grid(alpha=0.3)
    ax.legend(fontsize=8, loc="upper right")
    if title:
        ax.set_title(title, fontsize=10)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110, format="png")
    plt.close(fig)

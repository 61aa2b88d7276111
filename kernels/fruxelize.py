"""Ground truth from labelled solids: ``fruxelize`` (conventions section 4).

Frames
    Meshes are given in the world frame (any right-handed frame in metres; the simulator's is z up). ``pose`` is
    the grid camera's camera-to-world 4x4 transform with OpenCV axes (x right, y down, z forward), exactly the
    pose a :class:`fruxel.Camera` built for the same view carries.

Rule: a cell gets the label of the solid that contains its centre (the centre of its parameter ranges, which
lies on the column's centre ray, see :mod:`fruxel.grid`). There is no occlusion: every cell of the full solid
model is labelled, hidden ones included.

Algorithm, per column ``(j, i)`` and part (on a GPU one Warp thread a pair, on the CPU one a column): the centre
ray ``o + t d`` with ``o`` the camera centre and ``d = R (u_c, v_c, 1)``, so that ``t`` is the depth in the grid
camera and the cell centres sit at ``t = z_near + (k + 1/2) dz``. Each mesh is split on the host into *parts*:

* every **closed** connected component (each directed edge has exactly one opposite partner) is its own part.
  Components are found by vertex index first, so that pieces which merely touch (boxes sharing a corner) stay
  apart; what is open by index is then welded by exact vertex position and split again, so that seams with
  duplicated vertices do not open a mesh. A closed part is labelled by the
  **signed crossing count** along the ray: the walk starts outside the part's bounding box (winding 0) and
  collects every crossing with repeated BVH ray queries (``wp.mesh_query_ray``), +1 through a front face and -1
  through a back face. For a closed mesh this running sum *is* the winding number of every point between two
  crossings, so a centre is inside when the sum there is non-zero (the non-zero rule: overlapping pieces, and
  inverted meshes, are still solid). The walk must end at sum 0; when it does not (a ray grazing a silhouette
  edge, coincident crossings merged, more than :data:`MAX_CROSSINGS` crossings), that column falls back, for
  that part only, to a per-centre majority vote of crossing parity along three fixed skew directions.
  Splitting into components matters: two boxes touching in one mesh share a face plane, their two crossings
  there coincide, and one ray query cannot report both.
* all **open** components of one mesh (not watertight, or inconsistently wound) form one part, labelled by the
  **generalised winding number** (Jacobson et al. 2013, ``wp.mesh_query_point_sign_winding_number``): a centre
  inside the part's bounding box is inside when the winding number there is >= 1/2. The open part is oriented
  first so that its signed volume is positive. On an open mesh this is the robust, documented extension of
  "inside": a box with one face missing still counts as solid (the winding number is about 1 deep inside it and
  falls through 1/2 across the missing face), a lone sheet has no inside (its winding number is below 1/2 on
  both sides), and centres outside the bounding box are outside. The number is smooth between two crossings of
  the surface, so the walk above cuts the ray at the crossings and evaluates each piece at its first, middle
  and last centre, filling the piece when the three agree and evaluating every centre when they do not. It
  costs a few BVH queries per piece, so watertight assets stay much faster.

Overlaps: the **later mesh in the list wins** (each cell keeps the highest index of the meshes that contain its
centre, an atomic maximum, then takes that mesh's label). The simulator lists floor, walls, windows, doors,
furniture, sculptures, so that windows and doors take precedence over the walls around their openings and
furniture over what it stands on. A mesh with label 0 carves its inside out of earlier ones.
"""

from __future__ import annotations

import hashlib
import importlib
from collections import OrderedDict
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from fruxel.camera import check_pose
from fruxel.errors import FruxelError
from fruxel.grid import FruxelGrid

from .inputs import MAX_LABEL, VolumeError
from .registry import BACKENDS, BackendError, BackendUnavailable, split_name

MAX_CROSSINGS = 32
"""Crossings one column may collect through one closed part before that part falls back to the parity vote."""


class MeshError(FruxelError, ValueError):
    """Raised for meshes ``fruxelize`` cannot take: wrong shapes, non-finite vertices, face indices out of range,
    labels outside [0, 255]."""


@dataclass(frozen=True)
class MeshParts:
    """Labelled meshes split into closed and open parts, ready for a backend (numpy, float64/int64).

    Parts are stored in priority order (the order of the input meshes); the parts of one mesh are consecutive.
    """

    closed_vertices: np.ndarray
    """``(Vc, 3)`` float64 welded vertices of every closed part, world frame."""
    closed_faces: np.ndarray
    """``(Fc, 3)`` int64 faces into ``closed_vertices``, sorted by part."""
    closed_group: np.ndarray
    """``(Fc,)`` int64 part index of each closed face (the BVH group of its part)."""
    open_meshes: list[tuple[np.ndarray, np.ndarray]]
    """One ``((V, 3) float64, (F, 3) int64)`` per open part, oriented to positive signed volume."""
    part_kind: np.ndarray
    """``(P,)`` int32: 0 closed (signed crossings), 1 open (generalised winding number)."""
    part_ref: np.ndarray
    """``(P,)`` int32: the part's own index for closed parts (its BVH group), its index in ``open_meshes`` for
    open ones."""
    part_label: np.ndarray
    """``(P,)`` int32 label written into the cells the part contains."""
    part_lo: np.ndarray
    """``(P, 3)`` float64 lower corner of the part's bounding box, padded outwards, world frame."""
    part_hi: np.ndarray
    """``(P, 3)`` float64 upper corner, padded outwards."""
    mesh_first_part: np.ndarray
    """``(M + 1,)`` int32: the parts of mesh ``m`` are ``mesh_first_part[m]:mesh_first_part[m + 1]``."""
    mesh_lo: np.ndarray
    """``(M, 3)`` float64 padded bounding box of each mesh (lower corner), for culling whole meshes per ray."""
    mesh_hi: np.ndarray
    """``(M, 3)`` float64 padded bounding box upper corner."""

    @property
    def n_parts(self) -> int:
        """Number of parts P."""
        return int(self.part_kind.shape[0])


def _as_triplet(item: Any, index: int) -> tuple[np.ndarray, np.ndarray, int]:
    """One input mesh as ``(vertices (V, 3) float64, faces (F, 3) int64, label)``, accepting three spellings:
    ``(vertices, faces, label)``, ``(mesh, label)`` with ``mesh.vertices`` / ``mesh.faces`` (trimesh), or an
    object with ``.mesh`` and ``.label`` (the simulator's ``SceneObject``)."""
    if hasattr(item, "mesh") and hasattr(item, "label"):
        mesh, label = item.mesh, item.label
        verts, faces = mesh.vertices, mesh.faces
    elif isinstance(item, (tuple, list)) and len(item) == 2 and hasattr(item[0], "vertices"):
        verts, faces, label = item[0].vertices, item[0].faces, item[1]
    elif isinstance(item, (tuple, list)) and len(item) == 3:
        verts, faces, label = item
    else:
        raise MeshError(f"mesh {index}: expected (vertices, faces, label), (mesh, label) or an object with .mesh "
                        f"and .label, got {type(item).__name__}")
    v = np.asarray(verts, dtype=np.float64)
    f = np.asarray(faces)
    if v.ndim != 2 or v.shape[1] != 3:
        raise MeshError(f"mesh {index}: vertices must have shape (V, 3), got {v.shape}")
    if not np.all(np.isfinite(v)):
        raise MeshError(f"mesh {index}: vertices contain NaN or infinite values")
    if f.size == 0:
        f = f.reshape(0, 3).astype(np.int64)
    if f.ndim != 2 or f.shape[1] != 3 or f.dtype.kind not in "iu":
        raise MeshError(f"mesh {index}: faces must be integer with shape (F, 3), got {f.shape} {f.dtype}")
    f = f.astype(np.int64)
    if f.size and (f.min() < 0 or f.max() >= len(v)):
        raise MeshError(f"mesh {index}: face indices out of range [0, {len(v)})")
    if isinstance(label, bool) or not isinstance(label, (int, np.integer)) or not 0 <= int(label) <= MAX_LABEL:
        raise MeshError(f"mesh {index}: label must be an integer in [0, {MAX_LABEL}], got {label!r}")
    return v, f, int(label)


def _drop_degenerate(faces: np.ndarray) -> np.ndarray:
    """Faces with three distinct vertex indices (a face with a repeated index has no area and no edges)."""
    return faces[(faces[:, 0] != faces[:, 1]) & (faces[:, 1] != faces[:, 2]) & (faces[:, 2] != faces[:, 0])]


def _weld(v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Merge vertices at exactly equal positions: unique ``(U, 3)`` vertices and ``(V,)`` int64 index of each."""
    order = np.lexsort(v.T[::-1])
    sv = v[order]
    new = np.ones(len(v), dtype=bool)
    new[1:] = np.any(sv[1:] != sv[:-1], axis=1)
    ids = np.cumsum(new) - 1
    inv = np.empty(len(v), dtype=np.int64)
    inv[order] = ids
    return sv[new], inv


def _components(faces: np.ndarray, n_vertices: int) -> np.ndarray:
    """Connected component of each face (faces sharing a vertex are connected): ``(F,)`` int64, 0..C-1.

    Numpy union-find by rounds: every edge hooks the larger of its two roots onto the smaller, then the parent
    pointers are shortcut to roots, until a round changes nothing (a few rounds, O(log n) in practice).
    """
    parent = np.arange(n_vertices, dtype=np.int64)
    u = np.concatenate([faces[:, 0], faces[:, 1]])
    v = np.concatenate([faces[:, 1], faces[:, 2]])
    while True:
        pu, pv = parent[u], parent[v]
        m = np.minimum(pu, pv)
        old = parent.copy()
        np.minimum.at(parent, pu, m)
        np.minimum.at(parent, pv, m)
        while True:
            pp = parent[parent]
            if np.array_equal(pp, parent):
                break
            parent = pp
        if np.array_equal(parent, old):
            break
    _, face_comp = np.unique(parent[faces[:, 0]], return_inverse=True)
    return face_comp.reshape(-1)


def _open_components(faces: np.ndarray, face_comp: np.ndarray, n_vertices: int) -> np.ndarray:
    """Which components are open: ``(C,)`` bool. A component is closed when every directed edge occurs once and
    its reverse occurs once too (watertight, manifold along edges, consistently wound)."""
    n_comp = int(face_comp.max()) + 1 if face_comp.size else 0
    a = faces.reshape(-1)
    b = faces[:, [1, 2, 0]].reshape(-1)
    key = a * n_vertices + b
    order = np.argsort(key, kind="stable")
    sk = key[order]
    dup = np.zeros(len(key), dtype=bool)
    same = sk[1:] == sk[:-1]
    dup[order[1:][same]] = True
    dup[order[:-1][same]] = True
    rkey = b * n_vertices + a
    pos = np.clip(np.searchsorted(sk, rkey), 0, max(len(sk) - 1, 0))
    missing = sk[pos] != rkey if len(sk) else np.zeros(0, dtype=bool)
    bad_edge = dup | missing
    is_open = np.zeros(n_comp, dtype=bool)
    is_open[np.repeat(face_comp, 3)[bad_edge]] = True
    return is_open


@dataclass(frozen=True)
class _SplitPlan:
    """How one mesh's faces split into closed parts and open faces: a function of the faces alone (and the vertex
    count), so a mesh met again (a furniture model in every room, moved) reuses it. Arrays are read-only.

    Attributes:
        closed_faces: ``(Fc, 3)`` int64, the closed components' faces, grouped by part (indices into the mesh's
            vertices).
        used: ``(Vc,)`` int64, the mesh's vertices those faces use, ascending.
        local: ``(Fc, 3)`` int64, ``closed_faces`` as indices into ``used``.
        rank: ``(Fc,)`` int64, each closed face's part, 0..P-1, ascending.
        starts: ``(P,)`` int64, each part's first row in ``closed_faces``.
        open_faces: ``(Fo, 3)`` int64, the faces of the open components.
        part_vertices: ``(Vc,)`` int64, ``used`` grouped by part (a vertex belongs to one component).
        vertex_starts: ``(P,)`` int64, each part's first entry in ``part_vertices``: a part's bounds are its
            vertices', a third to a sixth of its faces' corners.
    """

    closed_faces: np.ndarray
    used: np.ndarray
    local: np.ndarray
    rank: np.ndarray
    starts: np.ndarray
    open_faces: np.ndarray
    part_vertices: np.ndarray
    vertex_starts: np.ndarray


SPLIT_PLANS = 512
"""Split plans a process keeps (least recently used go first): more than the distinct meshes of a few rooms."""
_plans: OrderedDict[bytes, _SplitPlan] = OrderedDict()


def _split_plan(faces: np.ndarray, n_vertices: int) -> _SplitPlan:
    """The :class:`_SplitPlan` of ``faces`` ``(F, 3)`` int over ``n_vertices`` vertices, from the process's cache
    when the same faces were split before (keyed by their bytes' digest)."""
    faces = np.ascontiguousarray(faces, dtype=np.int64)
    key = hashlib.blake2b(faces.tobytes(), digest_size=16, person=n_vertices.to_bytes(8, "little")).digest()
    plan = _plans.get(key)
    if plan is not None:
        _plans.move_to_end(key)
        return plan
    comp = _components(faces, n_vertices)
    is_open = _open_components(faces, comp, n_vertices)
    closed = ~is_open[comp]
    fc = faces[closed]
    _, rank = np.unique(comp[closed], return_inverse=True)
    rank = rank.reshape(-1)
    order = np.argsort(rank, kind="stable")
    fc, rank = fc[order], rank[order]
    used, local = np.unique(fc, return_inverse=True)
    starts = np.flatnonzero(np.r_[True, rank[1:] != rank[:-1]]) if len(rank) else np.zeros(0, dtype=np.int64)
    vertex_part = np.zeros(n_vertices, dtype=np.int64)
    vertex_part[fc] = rank[:, None]
    part_vertices = used[np.argsort(vertex_part[used], kind="stable")]
    vp = vertex_part[part_vertices]
    vertex_starts = np.flatnonzero(np.r_[True, vp[1:] != vp[:-1]]) if len(vp) else np.zeros(0, dtype=np.int64)
    arrays = (fc, used, local.reshape(-1, 3), rank, starts, faces[is_open[comp]], part_vertices, vertex_starts)
    for a in arrays:
        a.setflags(write=False)  # shared by every later mesh with these faces
    plan = _SplitPlan(*arrays)
    _plans[key] = plan
    if len(_plans) > SPLIT_PLANS:
        _plans.popitem(last=False)
    return plan


def _pad(lo: np.ndarray, hi: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    # The walk must start strictly outside the part even after float32 rounding of world coordinates.
    pad = 1e-3 + 1e-6 * np.maximum(np.abs(lo), np.abs(hi)).max(axis=-1, keepdims=True)
    return lo - pad, hi + pad


def prepare_meshes(meshes: Sequence[Any]) -> MeshParts:
    """Validate labelled meshes and split them into parts (see the module docstring).

    Args:
        meshes: sequence of ``(vertices (V, 3) float, faces (F, 3) int, label int)``, ``(trimesh, label)`` or
            objects with ``.mesh`` and ``.label``; world frame; later meshes win where they overlap.

    Raises:
        MeshError: a malformed mesh (nothing is built).
    """
    triplets = [_as_triplet(m, n) for n, m in enumerate(meshes)]
    cv: list[np.ndarray] = []
    cf: list[np.ndarray] = []
    cg: list[np.ndarray] = []
    opened: list[tuple[np.ndarray, np.ndarray]] = []
    kinds: list[int] = []
    refs: list[int] = []
    labels: list[int] = []
    los: list[np.ndarray] = []
    his: list[np.ndarray] = []
    first = [0]
    n_cv = 0

    def keep_closed(v: np.ndarray, f: np.ndarray, label: int) -> np.ndarray:
        """Add the closed components of ``(v, f)`` as parts; return the faces of the open ones."""
        nonlocal n_cv
        plan = _split_plan(f, len(v))
        if len(plan.closed_faces):
            p0 = len(kinds)
            cv.append(v[plan.used])
            cf.append(plan.local + n_cv)
            cg.append(plan.rank + p0)
            n_cv += len(plan.used)
            pv = v[plan.part_vertices]
            los.extend(np.minimum.reduceat(pv, plan.vertex_starts))
            his.extend(np.maximum.reduceat(pv, plan.vertex_starts))
            n_new = len(plan.starts)
            kinds.extend([0] * n_new)
            refs.extend(range(p0, p0 + n_new))
            labels.extend([label] * n_new)
        return plan.open_faces

    for v, f, label in triplets:
        # Components by index first: pieces that only touch (boxes sharing a corner position) stay separate
        # closed parts. Only what is open then gets its vertices welded by position, which closes meshes whose
        # seams merely duplicate vertices.
        rest = keep_closed(v, _drop_degenerate(f), label)
        if len(rest):
            used, local = np.unique(rest, return_inverse=True)
            uv, inv = _weld(v[used])
            fo = keep_closed(uv, _drop_degenerate(inv[local.reshape(-1, 3)]), label)
            if len(fo):
                used, local = np.unique(fo, return_inverse=True)
                vo, fo = uv[used], local.reshape(-1, 3)
                tri = vo[fo]
                if np.einsum("ij,ij->i", tri[:, 0], np.cross(tri[:, 1], tri[:, 2])).sum() < 0:
                    fo = fo[:, ::-1].copy()
                kinds.append(1)
                refs.append(len(opened))
                labels.append(label)
                los.append(vo.min(axis=0))
                his.append(vo.max(axis=0))
                opened.append((vo, fo))
        first.append(len(kinds))
    n_parts = len(kinds)
    part_lo, part_hi = (np.array(x, dtype=np.float64).reshape(n_parts, 3) for x in (los, his))
    first_arr = np.array(first, dtype=np.int32)
    mesh_lo = np.zeros((len(triplets), 3))
    mesh_hi = np.zeros((len(triplets), 3))
    for m in range(len(triplets)):
        a, b = first_arr[m], first_arr[m + 1]
        if b > a:
            mesh_lo[m], mesh_hi[m] = part_lo[a:b].min(axis=0), part_hi[a:b].max(axis=0)
        else:
            mesh_lo[m], mesh_hi[m] = 1.0, -1.0  # an empty box: no ray enters it
    part_lo, part_hi = _pad(part_lo, part_hi)
    mesh_lo, mesh_hi = _pad(mesh_lo, mesh_hi)
    return MeshParts(
        closed_vertices=np.concatenate(cv) if cv else np.zeros((0, 3)),
        closed_faces=np.concatenate(cf) if cf else np.zeros((0, 3), dtype=np.int64),
        closed_group=np.concatenate(cg) if cg else np.zeros(0, dtype=np.int64),
        open_meshes=opened,
        part_kind=np.array(kinds, dtype=np.int32),
        part_ref=np.array(refs, dtype=np.int32),
        part_label=np.array(labels, dtype=np.int32),
        part_lo=part_lo,
        part_hi=part_hi,
        mesh_first_part=first_arr,
        mesh_lo=mesh_lo,
        mesh_hi=mesh_hi,
    )


def _warp_device(backend: str | None, device: str | None) -> str | None:
    """Check the backend name (only Warp implements ``fruxelize``) and return the device asked for."""
    base, dev = split_name(backend or "warp")  # BackendError for an unknown name
    if base != "warp":
        raise BackendError(f"fruxelize is implemented on the Warp backend only (CPU or CUDA); use backend='warp', "
                           f"not {backend!r}")
    return device or dev


def _warp_module() -> Any:
    try:
        return importlib.import_module("fruxel.kernels.wp.fruxelize")
    except ImportError as e:
        raise BackendUnavailable(f"fruxelize needs NVIDIA Warp ({e}). Install it with: "
                                 f"{BACKENDS['warp'].install_hint}") from None


class MeshSet:
    """Labelled meshes prepared and uploaded once, for many ``fruxelize`` calls on the same scene.

    A user-held object, not a cache: build it per scene, pass it to :func:`fruxelize` for every pose of that
    scene, and drop it with the scene. Building splits the meshes into parts and builds the BVHs (the "upload"
    column of BENCHMARKS.md's simulator table).

    Args:
        meshes: as for :func:`prepare_meshes`.
        backend: ``"warp"``, ``"warp-cpu"``, ``"warp-cuda"`` or None (Warp).
        device: Warp device (``"cpu"``, ``"cuda"``, ``"cuda:1"``); None takes CUDA when present, else the CPU.

    Attributes:
        parts: the host-side :class:`MeshParts` (numpy).
        device: the Warp device the meshes live on (``"cpu"``, ``"cuda:0"``).
        native: the backend's uploaded structures (Warp meshes and part arrays).

    Raises:
        MeshError: malformed meshes. BackendError, BackendUnavailable: another backend, or Warp missing.
    """

    def __init__(self, meshes: Sequence[Any], *, backend: str | None = "warp", device: str | None = None) -> None:
        dev = _warp_device(backend, device)
        self.parts: MeshParts = prepare_meshes(meshes)
        self.native: Any = _warp_module().build_mesh_set(self.parts, dev)
        self.device: str = self.native.device

    def __repr__(self) -> str:
        return f"MeshSet({len(self.parts.mesh_first_part) - 1} meshes, {self.parts.n_parts} parts, {self.device!r})"


def fruxelize(
    meshes: Sequence[Any] | MeshSet,
    grid: FruxelGrid,
    pose: Any,
    *,
    backend: str | None = "warp",
    device: str | None = None,
    return_fallbacks: bool = False,
) -> np.ndarray | tuple[np.ndarray, int]:
    """Label every cell of ``grid`` seen from ``pose`` by the labelled solid containing its centre.

    Args:
        meshes: a :class:`MeshSet`, or a sequence of ``(vertices (V, 3) float, faces (F, 3) int, label int)``
            (also ``(trimesh, label)`` or objects with ``.mesh`` / ``.label``), world frame, metres. Later meshes
            win where solids overlap.
        grid: the fruxel grid.
        pose: ``(4, 4)`` grid-camera-to-world transform, OpenCV axes (x right, y down, z forward).
        backend: ``"warp"`` (or ``"warp-cpu"`` / ``"warp-cuda"``, or None); OpenCL does not implement this
            operation.
        device: Warp device; None uses a MeshSet's device, else CUDA when present, else the CPU.
        return_fallbacks: also return how many (column, part) pairs needed the slow per-centre rule of a closed
            part (a diagnostic: 0 for clean watertight scenes, a few for rays grazing edges).

    Returns:
        labels ``(D, H, W)`` uint8 numpy array (0 = empty), or ``(labels, fallbacks)``.

    Raises:
        MeshError: malformed meshes. fruxel.CameraError: a pose that is not rigid.
        BackendError, BackendUnavailable: another backend, or Warp missing.
    """
    if not isinstance(grid, FruxelGrid):
        raise VolumeError(f"grid must be a fruxel.FruxelGrid, got {type(grid).__name__}")
    pose = check_pose(pose)
    if isinstance(meshes, MeshSet):
        dev = _warp_device(backend, device)
        if dev is not None and _warp_module().resolve_device(dev) != meshes.device:
            raise BackendError(f"this MeshSet lives on {meshes.device!r}, not on {dev!r}")
        mesh_set = meshes
    else:
        mesh_set = MeshSet(meshes, backend=backend, device=device)
    labels, fallbacks = _warp_module().fruxelize(mesh_set.native, grid, pose)
    return (labels, fallbacks) if return_fallbacks else labels

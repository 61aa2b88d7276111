"""Plain numpy float64 reference of the kernels, for tests only (never a product path).

:func:`ref_first_hit` follows :mod:`fruxel.kernels.traversal` step by step, vectorised across rays: every ray
advances in lockstep under numpy masks, the Python loop runs only over DDA steps (at most
``traversal.max_steps(grid)``), and there is no empty-space skipping, so it is the plain loop the backends'
skipping must reproduce.

One point where the reference reads the traversal text carefully (see :func:`_crossing_u`): the formula
``t_u = (u o_z - o_x) / (d_x - u d_z)`` solves the *linear* equation ``x(t) = u z(t)``, whose root lies where
``z < 0`` (behind the apex, on the mirrored half of the plane) when the ray's asymptotic ``u = d_x / d_z``
never reaches the boundary ahead. That root is no crossing; the reference takes the boundary ahead as never
crossed (``+inf``) unless ``s_i (d_x - u d_z) > 0``, the condition for ``x - u z`` to move towards zero where
``z > 0``.

Besides the reference operations, this module has the independent geometry the tests judge results by:
:func:`clip_param_box` (Cyrus-Beck against any box of the (u, v, z) parameter space, which is a convex
trapezoid in metres), :func:`brute_first_hit_bounds` (per-cell clipping of every ray against every occupied
cell, no DDA) and :func:`near_edge` (pixels whose ray passes close to a cell edge, where float32 backends may
legitimately differ from the float64 reference).
"""

from __future__ import annotations

from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid
from fruxel.kernels import traversal

# Entry kinds recorded per ray; the normal is built from the kind and the plane's boundary value.
_ENTRY_U, _ENTRY_V, _ENTRY_Z, _ENTRY_INSIDE = 0, 1, 2, 3


def _frustum_planes(grid: FruxelGrid) -> list[tuple[np.ndarray, float]]:
    """The six clip half-spaces ``n . p + c >= 0`` of traversal step 1, in its order (left .. far)."""
    u0, uw, v0, vh = -grid.tu, grid.tu, -grid.tv, grid.tv
    return [
        (np.array([1.0, 0.0, -u0]), 0.0),
        (np.array([-1.0, 0.0, uw]), 0.0),
        (np.array([0.0, 1.0, -v0]), 0.0),
        (np.array([0.0, -1.0, vh]), 0.0),
        (np.array([0.0, 0.0, 1.0]), -grid.z_near),
        (np.array([0.0, 0.0, -1.0]), grid.z_far),
    ]


def _u_normal(u: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Unit normal of the plane ``x = u z`` facing a ray whose u moves with sign ``s``: ``(n, 3)``."""
    n = np.stack([np.ones_like(u), np.zeros_like(u), -u], axis=-1)
    return -s[:, None] * n / np.linalg.norm(n, axis=-1, keepdims=True)


def _v_normal(v: np.ndarray, s: np.ndarray) -> np.ndarray:
    """Unit normal of the plane ``y = v z`` facing a ray whose v moves with sign ``s``: ``(n, 3)``."""
    n = np.stack([np.zeros_like(v), np.ones_like(v), -v], axis=-1)
    return -s[:, None] * n / np.linalg.norm(n, axis=-1, keepdims=True)


def _crossing_u(ub: np.ndarray, s: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Next crossing of the plane ``x = ub z`` for rays whose u moves with sign ``s`` (+inf when none).

    ``x - ub z`` changes at rate ``d_x - ub d_z``; where ``z > 0`` its sign is that of ``u - ub``, so the
    boundary ahead is reached only when that rate has the sign ``s``. Otherwise the root of the linear equation
    is behind the apex (``z < 0``), not a crossing.
    """
    den = d[:, 0] - ub * d[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (ub * o[:, 2] - o[:, 0]) / den
    return np.where((s * den > 0) & np.isfinite(t), t, np.inf)


def _crossing_v(vb: np.ndarray, s: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Next crossing of the plane ``y = vb z`` (see :func:`_crossing_u`)."""
    den = d[:, 1] - vb * d[:, 2]
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (vb * o[:, 2] - o[:, 1]) / den
    return np.where((s * den > 0) & np.isfinite(t), t, np.inf)


def _crossing_z(zb: np.ndarray, s: np.ndarray, o: np.ndarray, d: np.ndarray) -> np.ndarray:
    """Next crossing of the plane ``z = zb`` (+inf for rays with ``d_z = 0``)."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t = (zb - o[:, 2]) / d[:, 2]
    return np.where(s != 0, t, np.inf)


def ref_first_hit(labels: Any, grid: FruxelGrid, camera: Camera) -> dict[str, np.ndarray]:
    """First occupied cell along every pixel's ray, exactly as :mod:`fruxel.kernels.traversal`, in float64.

    Args:
        labels: ``(D, H, W)`` integer or bool label volume, 0 = empty.
        grid: the volume's grid.
        camera: the viewing camera (pose camera-to-grid).

    Returns:
        dict with ``label`` ``(h, w)`` int32 (0 on a miss), ``cell`` ``(h, w)`` int64 flat index (-1 on a miss),
        ``depth`` ``(h, w)`` float64 (the ray parameter t of the entry point, which is the depth in the viewing
        camera; 0 on a miss) and ``normal`` ``(h, w, 3)`` float64, unit, grid frame, facing the camera
        (zeros on a miss).
    """
    lab = np.asarray(labels)
    if lab.shape != grid.shape:
        raise ValueError(f"labels must have shape {grid.shape}, got {lab.shape}")
    D, H, W = grid.shape
    flat_lab = lab.reshape(-1).astype(np.int64)
    occ = flat_lab != 0
    o3, d3 = camera.rays()
    h, w = o3.shape[:2]
    o = o3.reshape(-1, 3)
    d = d3.reshape(-1, 3)
    n = o.shape[0]
    u0, v0, du, dv, zn, dz = -grid.tu, -grid.tv, grid.du, grid.dv, grid.z_near, grid.dz

    # Step 1: Cyrus-Beck clip; the entry plane is remembered only when it raises t_lo strictly.
    t_lo = np.zeros(n)
    t_hi = np.full(n, np.inf)
    miss = np.zeros(n, bool)
    entry_plane = np.full(n, -1)
    with np.errstate(divide="ignore", invalid="ignore"):
        for p, (nrm, c) in enumerate(_frustum_planes(grid)):
            a = d @ nrm
            b = o @ nrm + c
            miss |= (a == 0) & (b < 0)
            cand = -b / a
            raise_lo = (a > 0) & (cand > t_lo)
            t_lo = np.where(raise_lo, cand, t_lo)
            entry_plane = np.where(raise_lo, p, entry_plane)
            t_hi = np.where(a < 0, np.minimum(t_hi, cand), t_hi)
    miss |= t_lo >= t_hi

    label = np.zeros(n, np.int32)
    cell = np.full(n, -1, np.int64)
    depth = np.zeros(n)
    normal = np.zeros((n, 3))

    live = np.flatnonzero(~miss)
    o, d, t_lo, t_hi, entry_plane = o[live], d[live], t_lo[live], t_hi[live], entry_plane[live]

    # Step 2: entry cell, with the entry plane's family index set exactly.
    p = o + t_lo[:, None] * d
    with np.errstate(divide="ignore", invalid="ignore"):
        k = np.floor((p[:, 2] - zn) / dz)
        i = np.floor((p[:, 0] / p[:, 2] - u0) / du)
        j = np.floor((p[:, 1] / p[:, 2] - v0) / dv)
    k = np.clip(np.nan_to_num(k), 0, D - 1).astype(np.int64)
    i = np.clip(np.nan_to_num(i), 0, W - 1).astype(np.int64)
    j = np.clip(np.nan_to_num(j), 0, H - 1).astype(np.int64)
    i = np.where(entry_plane == 0, 0, np.where(entry_plane == 1, W - 1, i))
    j = np.where(entry_plane == 2, 0, np.where(entry_plane == 3, H - 1, j))
    k = np.where(entry_plane == 4, 0, np.where(entry_plane == 5, D - 1, k))

    # Step 3: step signs, constant along each ray.
    s_i = np.sign(d[:, 0] * o[:, 2] - d[:, 2] * o[:, 0])
    s_j = np.sign(d[:, 1] * o[:, 2] - d[:, 2] * o[:, 1])
    s_k = np.sign(d[:, 2])

    # Entry normal of the first cell: minus the entry plane's unit normal, or -d/|d| from inside.
    m = live.size
    ent_kind = np.full(m, _ENTRY_INSIDE)
    ent_val = np.zeros(m)
    ent_sign = np.zeros(m)
    for plane, kind, val, sgn in (
        (0, _ENTRY_U, u0, 1.0), (1, _ENTRY_U, -u0, -1.0), (2, _ENTRY_V, v0, 1.0), (3, _ENTRY_V, -v0, -1.0),
        (4, _ENTRY_Z, 0.0, 1.0), (5, _ENTRY_Z, 0.0, -1.0),
    ):
        sel = entry_plane == plane
        ent_kind[sel], ent_val[sel], ent_sign[sel] = kind, val, sgn

    # Step 4: first crossings from boundary indices.
    ib = i + (s_i > 0)
    jb = j + (s_j > 0)
    kb = k + (s_k > 0)
    t_u = _crossing_u(u0 + ib * du, s_i, o, d)
    t_v = _crossing_v(v0 + jb * dv, s_j, o, d)
    t_z = _crossing_z(zn + kb * dz, s_k, o, d)
    t_entry = t_lo.copy()

    # Step 5: lockstep loop over the rays still travelling.
    act = np.arange(m)
    done_hit = np.zeros(m, bool)
    for _ in range(traversal.max_steps(grid)):
        if act.size == 0:
            break
        flat = (k[act] * H + j[act]) * W + i[act]
        hit_now = occ[flat]
        done_hit[act[hit_now]] = True
        act = act[~hit_now]
        if act.size == 0:
            break
        tu, tv, tz = t_u[act], t_v[act], t_z[act]
        fam = np.where((tu <= tv) & (tu <= tz), 0, np.where(tv <= tz, 1, 2))
        tn = np.where(fam == 0, tu, np.where(fam == 1, tv, tz))
        ni = i[act] + np.where(fam == 0, s_i[act], 0).astype(np.int64)
        nj = j[act] + np.where(fam == 1, s_j[act], 0).astype(np.int64)
        nk = k[act] + np.where(fam == 2, s_k[act], 0).astype(np.int64)
        leave = (tn >= t_hi[act]) | (ni < 0) | (ni >= W) | (nj < 0) | (nj >= H) | (nk < 0) | (nk >= D)
        act, fam, tn, ni, nj, nk = act[~leave], fam[~leave], tn[~leave], ni[~leave], nj[~leave], nk[~leave]
        # The boundary just crossed is the old boundary-ahead index of the stepped family.
        crossed_u = u0 + ib[act] * du
        crossed_v = v0 + jb[act] * dv
        crossed_z = zn + kb[act] * dz
        i[act], j[act], k[act] = ni, nj, nk
        t_entry[act] = tn
        ent_kind[act] = fam
        ent_val[act] = np.where(fam == 0, crossed_u, np.where(fam == 1, crossed_v, crossed_z))
        ent_sign[act] = np.where(fam == 0, s_i[act], np.where(fam == 1, s_j[act], s_k[act]))
        for f, idx, bnd, sgn in ((0, i, ib, s_i), (1, j, jb, s_j), (2, k, kb, s_k)):
            sel = act[fam == f]
            bnd[sel] = idx[sel] + (sgn[sel] > 0)
        sel = act[fam == 0]
        t_u[sel] = _crossing_u(u0 + ib[sel] * du, s_i[sel], o[sel], d[sel])
        sel = act[fam == 1]
        t_v[sel] = _crossing_v(v0 + jb[sel] * dv, s_j[sel], o[sel], d[sel])
        sel = act[fam == 2]
        t_z[sel] = _crossing_z(zn + kb[sel] * dz, s_k[sel], o[sel], d[sel])

    hits = np.flatnonzero(done_hit)
    flat = (k[hits] * H + j[hits]) * W + i[hits]
    nrm = np.zeros((hits.size, 3))
    kind, val, sgn = ent_kind[hits], ent_val[hits], ent_sign[hits]
    sel = kind == _ENTRY_U
    nrm[sel] = _u_normal(val[sel], sgn[sel])
    sel = kind == _ENTRY_V
    nrm[sel] = _v_normal(val[sel], sgn[sel])
    sel = kind == _ENTRY_Z
    nrm[sel, 2] = -sgn[sel]
    sel = kind == _ENTRY_INSIDE
    dh = d[hits[sel]]
    nrm[sel] = -dh / np.linalg.norm(dh, axis=-1, keepdims=True)

    out_idx = live[hits]
    label[out_idx] = flat_lab[flat].astype(np.int32)
    cell[out_idx] = flat
    depth[out_idx] = t_entry[hits]
    normal[out_idx] = nrm
    return {
        "label": label.reshape(h, w),
        "cell": cell.reshape(h, w),
        "depth": depth.reshape(h, w),
        "normal": normal.reshape(h, w, 3),
    }


def ref_shell(labels: Any, grid: FruxelGrid, cameras: Camera | list[Camera]) -> np.ndarray:
    """The VMS shell by the reference traversal: cells that are some pixel's first hit keep their label.

    Args:
        labels: ``(D, H, W)`` or ``(B, D, H, W)`` integer labels.
        grid: the volume's grid.
        cameras: one camera or a list; every camera takes the general path (no own-view special case).

    Returns:
        Array of ``labels``' shape and dtype, 0 where the cell is no camera's first hit.
    """
    lab = np.asarray(labels)
    cams = [cameras] if isinstance(cameras, Camera) else list(cameras)
    if lab.ndim == 4:
        return np.stack([ref_shell(x, grid, cams) for x in lab])
    keep = np.zeros(grid.n_cells, bool)
    for cam in cams:
        c = ref_first_hit(lab, grid, cam)["cell"]
        keep[c[c >= 0]] = True
    return np.where(keep.reshape(grid.shape), lab, 0).astype(lab.dtype)


def ref_own_view_shell(labels: Any) -> np.ndarray:
    """The first occupied cell of every column kept, all else 0: ``(..., D, H, W)`` in, same shape and dtype out.

    Uses argmax of the occupancy along the depth axis (the first True), independently of any ray traversal.
    """
    lab = np.asarray(labels)
    occ = lab != 0
    first = np.argmax(occ, axis=-3)
    any_occ = occ.any(axis=-3)
    k = np.arange(lab.shape[-3]).reshape((-1, 1, 1))
    keep = (k == first[..., None, :, :]) & any_occ[..., None, :, :]
    return np.where(keep, lab, 0).astype(lab.dtype)


def ref_labels_from_scores(scores: Any, threshold: float | None = None, probs: bool = False) -> np.ndarray:
    """Labels of float scores by conventions section 2, computed in float64.

    Args:
        scores: ``(..., C, D, H, W)`` logits or probabilities, channel 0 = empty (numpy or torch CPU).
        threshold: None for the argmax rule (occupied when the argmax over all C is not 0); else occupied when
            ``1 - p(empty) >= threshold``, with p the softmax of logits or the probabilities themselves.
        probs: whether ``scores`` are probabilities.

    Returns:
        ``(..., D, H, W)`` int64: 0 where empty, else ``1 + argmax`` over channels ``1..C-1``.
    """
    s = np.asarray(scores.detach().cpu().double() if hasattr(scores, "detach") else scores, dtype=np.float64)
    cls = 1 + np.argmax(s[..., 1:, :, :, :], axis=-4)
    if threshold is None:
        occ = np.argmax(s, axis=-4) != 0
    else:
        if probs:
            p0 = s[..., 0, :, :, :]
        else:
            z = s - s.max(axis=-4, keepdims=True)
            e = np.exp(z)
            p0 = e[..., 0, :, :, :] / e.sum(axis=-4)
        occ = 1.0 - p0 >= threshold
    return np.where(occ, cls, 0).astype(np.int64)


# ---------------------------------------------------------------------------------------------- geometry oracles


def clip_param_box(
    o: np.ndarray, d: np.ndarray, u_lo: Any, u_hi: Any, v_lo: Any, v_hi: Any, z_lo: Any, z_hi: Any
) -> tuple[np.ndarray, np.ndarray]:
    """Interval of ``t >= 0`` in which rays lie inside parameter boxes ``u_lo <= x/z <= u_hi`` (etc.), z in range.

    Such a box is a convex trapezoid in metres (six half-spaces through the apex or at constant z), so
    Cyrus-Beck is exact. Everything broadcasts: rays ``(N, 1, 3)`` against boxes ``(M,)`` give ``(N, M)``.

    Args:
        o, d: ray origins and directions, ``(..., 3)`` float64, grid frame.
        u_lo, u_hi, v_lo, v_hi, z_lo, z_hi: the box bounds (u, v dimensionless; z in metres).

    Returns:
        (t_in, t_out): the ray is inside for ``t_in < t < t_out``; empty where ``t_in >= t_out``.
    """
    ox, oy, oz = o[..., 0], o[..., 1], o[..., 2]
    dx, dy, dz = d[..., 0], d[..., 1], d[..., 2]
    zero = np.zeros(np.broadcast(ox, u_lo, v_lo, z_lo).shape)
    t_in = zero.copy()
    t_out = zero + np.inf
    empty = zero.astype(bool)
    planes = (
        (dx - u_lo * dz, ox - u_lo * oz),
        (u_hi * dz - dx, u_hi * oz - ox),
        (dy - v_lo * dz, oy - v_lo * oz),
        (v_hi * dz - dy, v_hi * oz - oy),
        (dz + zero, oz - z_lo),
        (-dz + zero, z_hi - oz),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        for a, b in planes:
            a = a + zero
            b = b + zero
            empty |= (a == 0) & (b < 0)
            t = -b / a
            t_in = np.where(a > 0, np.maximum(t_in, t), t_in)
            t_out = np.where(a < 0, np.minimum(t_out, t), t_out)
    t_out = np.where(empty, -np.inf, t_out)
    return t_in, t_out


def cell_param_bounds(grid: FruxelGrid, cells: np.ndarray, margin: float) -> tuple[np.ndarray, ...]:
    """Bounds of cells ``(M, 3)`` int ``(k, j, i)`` shrunk by ``margin`` cell units (grown when negative).

    Returns:
        ``(u_lo, u_hi, v_lo, v_hi, z_lo, z_hi)``, each ``(M,)`` float64, for :func:`clip_param_box`.
    """
    k, j, i = (cells[:, c].astype(np.float64) for c in range(3))
    u0, v0 = -grid.tu, -grid.tv
    return (
        u0 + (i + margin) * grid.du, u0 + (i + 1 - margin) * grid.du,
        v0 + (j + margin) * grid.dv, v0 + (j + 1 - margin) * grid.dv,
        grid.z_near + (k + margin) * grid.dz, grid.z_near + (k + 1 - margin) * grid.dz,
    )


def brute_first_hit_bounds(
    labels: Any, grid: FruxelGrid, camera: Camera, margin: float = 1e-3
) -> dict[str, np.ndarray]:
    """What the first hit of each pixel must be, from clipping every ray against every occupied cell (no DDA).

    A ray that passes through an occupied cell shrunk by ``margin`` (cell units) certainly meets occupied space
    there; a ray that misses every cell grown by ``margin`` certainly meets none. Between the two lie rays
    through edges and corners, where either answer is right.

    Args:
        labels: ``(D, H, W)`` integer labels.
        grid: their grid.
        camera: viewing camera.
        margin: cell units.

    Returns:
        dict of ``(h, w)`` arrays: ``t_must`` float64, the earliest entry into a shrunk occupied cell (+inf when
        none: the ray may miss); ``t_may`` float64, the earliest entry into a grown occupied cell (+inf when
        none: the ray must miss); and ``(h, w, M)`` bool ``touch``, whether the ray meets each grown occupied
        cell, with ``cells`` ``(M,)`` int64 their flat indices and ``t_touch`` ``(h, w, M)`` their grown
        entries.
    """
    lab = np.asarray(labels)
    cells = np.argwhere(lab != 0)
    flat = np.flatnonzero(lab != 0)
    o, d = camera.rays()
    h, w = o.shape[:2]
    o = o.reshape(-1, 1, 3)
    d = d.reshape(-1, 1, 3)
    t_in, t_out = clip_param_box(o, d, *cell_param_bounds(grid, cells, margin))
    t_must = np.where(t_in < t_out, t_in, np.inf).min(axis=1, initial=np.inf)
    g_in, g_out = clip_param_box(o, d, *cell_param_bounds(grid, cells, -margin))
    touch = g_in < g_out
    t_may = np.where(touch, g_in, np.inf).min(axis=1, initial=np.inf)
    return {
        "t_must": t_must.reshape(h, w),
        "t_may": t_may.reshape(h, w),
        "touch": touch.reshape(h, w, -1),
        "t_touch": g_in.reshape(h, w, -1),
        "cells": flat,
    }


def param_coords(grid: FruxelGrid, points: np.ndarray) -> np.ndarray:
    """Continuous cell coordinates ``(..., 3)`` ``(fk, fj, fi)`` of grid-frame points: integers are planes."""
    p = np.asarray(points, dtype=np.float64)
    with np.errstate(divide="ignore", invalid="ignore"):
        fi = (p[..., 0] / p[..., 2] + grid.tu) / grid.du
        fj = (p[..., 1] / p[..., 2] + grid.tv) / grid.dv
    fk = (p[..., 2] - grid.z_near) / grid.dz
    return np.stack([fk, fj, fi], axis=-1)


def edge_distance(grid: FruxelGrid, points: np.ndarray) -> np.ndarray:
    """Distance of points to the nearest cell edge, in cell units of the parameter space: ``(...,)`` float64.

    An edge is where two of the three coordinates are integers, so this is the second smallest of the three
    distances to the nearest integer.
    """
    f = param_coords(grid, points)
    dist = np.abs(f - np.round(f))
    return np.sort(dist, axis=-1)[..., 1]


def near_edge(grid: FruxelGrid, camera: Camera, tol: float = 1e-4, until: Any = None) -> np.ndarray:
    """Pixels whose ray comes within ``tol`` of a cell edge, where float32 traversals may take another cell.

    Distances are in cell units of the (u, v, z) parameter space. The segment examined is the ray's part inside
    the frustum grown by ``tol`` (so rays grazing the frustum from outside count too), cut at ``until`` where
    given. At every crossing of a grid plane within it, the ray is near an edge when one of the two other
    coordinates is within ``tol`` of an integer. A camera within ``tol`` of any plane of the grown frustum is
    flagged for all its pixels (its starting cell is ambiguous).

    Args:
        grid: the grid.
        camera: viewing camera.
        tol: cell units.
        until: optional ``(h, w)`` ray parameter at which to stop (the reference hit depth); <= 0 or inf means
            the whole segment.

    Returns:
        ``(h, w)`` bool.
    """
    o3, d3 = camera.rays()
    h, w = o3.shape[:2]
    o = o3.reshape(-1, 3)
    d = d3.reshape(-1, 3)
    D, H, W = grid.shape
    u0, v0 = -grid.tu, -grid.tv
    ta, tb = clip_param_box(
        o, d, u0 - tol * grid.du, -u0 + tol * grid.du, v0 - tol * grid.dv, -v0 + tol * grid.dv,
        grid.z_near - tol * grid.dz, grid.z_far + tol * grid.dz,
    )
    if until is not None:
        u = np.asarray(until, np.float64).reshape(-1)
        tb = np.where((u > 0) & np.isfinite(u), np.minimum(tb, u * (1 + 1e-7) + 1e-12), tb)
    seg = ta < tb
    flag = np.zeros(o.shape[0], bool)
    fo = param_coords(grid, camera.position)
    inside = np.all((fo > -tol) & (fo < np.array([D, H, W]) + tol))
    if inside and np.any(np.abs(fo - np.round(fo)) <= tol):
        return np.ones((h, w), bool)
    idx = np.flatnonzero(seg)
    o, d, ta, tb = o[idx], d[idx], ta[idx], tb[idx]
    fa = param_coords(grid, o + ta[:, None] * d)
    fb = param_coords(grid, o + tb[:, None] * d)
    bounds = (
        (0, D, lambda n: (grid.z_near + n * grid.dz - o[:, 2]) / d[:, 2]),
        (1, H, lambda n: ((v0 + n * grid.dv) * o[:, 2] - o[:, 1]) / (d[:, 1] - (v0 + n * grid.dv) * d[:, 2])),
        (2, W, lambda n: ((u0 + n * grid.du) * o[:, 2] - o[:, 0]) / (d[:, 0] - (u0 + n * grid.du) * d[:, 2])),
    )
    near = np.zeros(idx.size, bool)
    with np.errstate(divide="ignore", invalid="ignore"):
        for axis, count, crossing in bounds:
            lo = np.ceil(np.minimum(fa[:, axis], fb[:, axis]) - tol)
            hi = np.floor(np.maximum(fa[:, axis], fb[:, axis]) + tol)
            lo = np.clip(np.nan_to_num(lo, nan=0.0), 0, count)
            hi = np.clip(np.nan_to_num(hi, nan=-1.0), -1, count)
            span = int(np.max(hi - lo, initial=-1)) + 1
            others = [a for a in range(3) if a != axis]
            for m in range(span):
                n = lo + m
                ok = n <= hi
                t = crossing(n)
                ok &= np.isfinite(t) & (t >= ta - 1e-9 * np.abs(ta) - 1e-12) & (t <= tb + 1e-9 * np.abs(tb) + 1e-12)
                f = param_coords(grid, o + np.where(ok, t, ta)[:, None] * d)
                dist = np.abs(f[:, others] - np.round(f[:, others]))
                near |= ok & np.any(dist <= tol, axis=1)
    flag[idx] = near
    return flag.reshape(h, w)

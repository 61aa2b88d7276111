"""The ray tracer's light paths: shadow and ambient rays ask the BVH of the faces that stop light and walk the few
glass and shining faces apart (``SceneData.opaque`` and ``clear``). Checked against a small reference that walks
every face of the room's one BVH, hit after hit, for rays between random points of a dressed room with glass panes
and a shining outdoor view behind them (real Warp kernels on the CPU, the tiny asset pack)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

pytest.importorskip("warp")

from fruxel.kernels.wp.runtime import warp  # noqa: E402
from fruxel.train.sim.raytrace.surfaces import (  # noqa: E402
    RAY_EPS,
    SceneData,
    glass_tint,
    open_distance,
    schlick,
    transmittance,
)

wp = warp()


@wp.func
def walk_transmittance(scene: SceneData, origin: wp.vec3, d: wp.vec3, distance: float) -> wp.vec3:
    """Reference: every face's first hit in turn along the ray, through the room's one BVH."""
    through = wp.vec3(1.0, 1.0, 1.0)
    t0 = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    panes = int(0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    for _ in range(64):
        if t0 >= distance:
            return through
        q = wp.mesh_query_ray(scene.mesh, origin + t0 * d, d, distance - t0)
        if not q.result:
            return through
        mat = scene.materials[scene.face_material[q.face]]
        if mat.emission <= 0.0:
            if mat.opacity >= 1.0 or panes >= scene.glass_layers:
                return wp.vec3(0.0, 0.0, 0.0)
            f = schlick(0.04, wp.abs(wp.dot(q.normal, d)))
            through = wp.cw_mul(through, glass_tint(mat.color)) * ((1.0 - mat.opacity) * (1.0 - f))
            panes = panes + 1
        t0 = t0 + q.t + RAY_EPS
    return through


@wp.func
def walk_open_distance(scene: SceneData, origin: wp.vec3, d: wp.vec3, distance: float) -> float:
    """Reference: the distance to the first face along the ray that is opaque and does not shine."""
    t0 = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    for _ in range(64):
        if t0 >= distance:
            return distance
        q = wp.mesh_query_ray(scene.mesh, origin + t0 * d, d, distance - t0)
        if not q.result:
            return distance
        mat = scene.materials[scene.face_material[q.face]]
        if mat.opacity >= 1.0 and mat.emission <= 0.0:
            return t0 + q.t
        t0 = t0 + q.t + RAY_EPS
    return distance


@wp.kernel
def compare_light_paths_kernel(scene: SceneData, starts: wp.array(dtype=wp.vec3), ends: wp.array(dtype=wp.vec3),
                               out: wp.array2d(dtype=wp.float32)):
    """Test kernel: one thread per ray from ``starts[i]`` to ``ends[i]`` (world frame, metres); ``out[i]`` holds
    the product's transmittance (3), the reference's (3), the product's open distance and the reference's.
    Launch ``len(starts)``; ``out`` is ``(N, 8)``."""
    i = wp.tid()
    w = ends[i] - starts[i]
    dist = wp.length(w)
    d = w / dist
    a = transmittance(scene, starts[i], d, dist)
    b = walk_transmittance(scene, starts[i], d, dist)
    for c in range(3):
        out[i, c] = a[c]
        out[i, 3 + c] = b[c]
    out[i, 6] = open_distance(scene, starts[i], d, dist)
    out[i, 7] = walk_open_distance(scene, starts[i], d, dist)


def _dressed_room(pack_dir: Path, seed: int):  # noqa: ANN202 - the renderer is imported with Warp
    from fruxel.grid import FruxelGrid
    from fruxel.train.sim.config import ImageConfig, SimConfig
    from fruxel.train.sim.raytrace.dressing import dress_scene
    from fruxel.train.sim.raytrace.renderer import RaytraceRenderer, open_pack
    from fruxel.train.sim.scene import RoomConfig, make_scene

    config = SimConfig(grid=FruxelGrid(16, 16, 16, 0.5, 8.0, 60.0), image=ImageConfig(size=32), renderer="raytrace",
                       assets=str(pack_dir)).replace(room=RoomConfig(ceiling=True))
    scene = dress_scene(make_scene(seed, config.room, config.classes), open_pack(str(pack_dir)), seed)
    renderer = RaytraceRenderer(config, device="cpu")
    renderer.set_scene(scene)
    return scene, renderer


@pytest.mark.parametrize("seed", [3, 5])
def test_shadow_and_ambient_rays_see_what_a_walk_over_every_face_sees(pack_dir: Path, seed: int) -> None:
    scene, renderer = _dressed_room(pack_dir, seed)
    with renderer:
        data = renderer._room.data
        assert 0 < data.clear_faces < len(renderer._room.arrays.faces), "the room has glass or a shining view"
        rng = np.random.default_rng(seed)
        size = np.asarray(scene.room_size, dtype=np.float64)
        # Points inside the room and a margin beyond its walls, so that rays cross walls, windows and the view.
        lo, hi = -0.2 * size, 1.2 * size
        starts = rng.uniform(lo, hi, (4000, 3)).astype(np.float32)
        ends = rng.uniform(lo, hi, (4000, 3)).astype(np.float32)
        out = wp.zeros((len(starts), 8), dtype=wp.float32, device="cpu")
        wp.launch(compare_light_paths_kernel, dim=len(starts), inputs=[
            data, wp.array(starts, dtype=wp.vec3, device="cpu"), wp.array(ends, dtype=wp.vec3, device="cpu"), out],
            device="cpu")
        got = out.numpy()
    through, walked = got[:, 0:3], got[:, 3:6]
    # A ray that grazes a face's edge may count it in one walk and not the other: a few in thousands.
    agree = np.all(np.abs(through - walked) < 1e-5, axis=1)
    assert agree.mean() > 0.995, f"{np.count_nonzero(~agree)} of {len(agree)} shadow rays disagree"
    shaded, clear = np.all(walked == 0.0, axis=1), np.all(walked == 1.0, axis=1)
    tinted = ~shaded & ~clear
    assert shaded.any() and clear.any() and tinted.any(), "rays blocked, free and through glass all occur"
    assert agree[tinted].mean() > 0.99, "rays through glass keep its tint"
    opened = np.isclose(got[:, 6], got[:, 7], rtol=0.0, atol=1e-4)
    assert opened.mean() > 0.995, f"{np.count_nonzero(~opened)} of {len(opened)} ambient rays disagree"

"""Profile of the OpenCL backend (PoCL on the CPU): whole calls and their parts, in steady state.

Scene: the kernel benchmark's (``fruxel.data.rooms``: ``room_volume(128)``, about 25 % occupied). Views: its
``oblique_camera`` at 512x512, a 512x512 camera above the room looking down into it (long rays through empty space), 6
``orbit_cameras`` at 512x512 for ``shell``, and the grid's own view for ``shell`` of ``(4, 7, 128, 128, 128)``
float32 logits.

Each measurement runs once to build and warm up, then ``--repeat`` times; it reports the median and the minimum
wall time and the median process CPU time (all threads; on an otherwise idle machine wall ~ CPU / cores).
Parts: the labels and their field alone, the traversal kernel alone (enqueue + wait), and the host overhead
(whole call minus device parts). ``--caps`` repeats everything for other distance caps (0: no skipping, every
iteration a plain step).

Usage: ``python benchmarks/profile_cl.py [--repeat 15] [--caps 0 4 15]``
"""

from __future__ import annotations

import argparse
import importlib
import time
from collections.abc import Callable

import numpy as np

from fruxel.camera import Camera
from fruxel.data import rooms
from fruxel.grid import FruxelGrid
from fruxel.kernels import orbit_cameras
from fruxel.kernels.cl import first_hit, occupancy, shell
from fruxel.kernels.cl.runtime import get_runtime, host_array
from fruxel.kernels.inputs import inspect_volume

first_hit_module = importlib.import_module("fruxel.kernels.cl.first_hit")
"""The module (the package attribute ``first_hit`` is its function): its program source."""


def above(g: FruxelGrid, size: int = 512) -> Camera:
    """Above the room looking down into it: rays cross the empty interior to the floor and furniture."""
    c = g.centre()
    return Camera.look_at(c + np.array([0.3, -6.0, 0.2]), c, width=size, height=size)


def measure(fn: Callable[[], object], repeat: int) -> dict[str, float]:
    """Median / min wall ms and median CPU ms of ``fn`` after one warm-up call."""
    fn()
    wall, cpu = [], []
    for _ in range(repeat):
        c0, t0 = time.process_time(), time.perf_counter()
        fn()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return {"median": 1e3 * float(np.median(wall)), "min": 1e3 * min(wall), "cpu": 1e3 * float(np.median(cpu))}


def fmt(name: str, m: dict[str, float]) -> str:
    return f"{name:<44s} median {m['median']:8.2f} ms   min {m['min']:8.2f} ms   cpu {m['cpu']:8.2f} ms"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--repeat", type=int, default=15)
    ap.add_argument("--caps", type=int, nargs="*", default=[occupancy.DIST_CAP],
                    help="distance caps of the field (occupancy.DIST_CAP; 0 = no skipping)")
    ap.add_argument("--skip-scores", action="store_true", help="skip the (4, 7, 128^3) logits shell")
    args = ap.parse_args()

    lab, g = rooms.room_volume(128)
    rt = get_runtime(None)
    print(f"device: {rt.device.name.strip()}  occupancy {np.mean(lab > 0):.3f}")
    cam_ob, cam_up = rooms.oblique_camera(g, 512), above(g)
    orbit = orbit_cameras(g, 6)
    spec = inspect_volume(lab, g)

    def field_only() -> None:
        with rt.lock:
            vol = occupancy.labels_from_host(rt, host_array(lab), spec, g)
            rt.queue.finish()  # timing: wait for the field kernels
            del vol

    def kernel_only(cam: Camera) -> Callable[[], None]:
        vol = occupancy.labels_from_host(rt, host_array(lab), spec, g)
        outs = [rt.scratch(f"prof{i}", cam.width * cam.height * s) for i, s in enumerate((4, 8, 4, 12))]
        k = rt.kernel(first_hit_module._SOURCE, "trace_first_hit_kernel", occupancy.trace_options(g.n_cells, rt.lanes))

        def run() -> None:
            k(rt.queue, occupancy.tile_global(cam, 1, rt.lanes), (*occupancy.TILE_LOCAL, 1), vol.labels, vol.field,
              *occupancy.trace_args(g, cam), *outs)
            rt.queue.finish()  # timing: wait for the kernel

        return run

    for cap in args.caps:
        occupancy.DIST_CAP = cap
        print(f"--- DIST_CAP = {cap}")
        print(fmt("labels upload + field", measure(field_only, args.repeat)))
        for name, cam in (("oblique", cam_ob), ("above", cam_up)):
            hits = first_hit(lab, g, cam)
            whole = measure(lambda cam=cam: first_hit(lab, g, cam), args.repeat)
            kern = measure(kernel_only(cam), args.repeat)
            print(fmt(f"first_hit {name} 512^2 (hit {np.mean(hits.hit):.2f})", whole))
            print(fmt(f"  traversal kernel only ({name})", kern))
            print(f"  host + field overhead ~ {whole['median'] - kern['median']:.2f} ms (median difference)")
        print(fmt("shell 6 orbit cameras 512^2", measure(lambda: shell(lab, g, orbit), args.repeat)))
        print(fmt("shell own view labels (128^3)", measure(lambda: shell(lab, g, g.camera()), args.repeat)))

    if not args.skip_scores:
        rng = np.random.default_rng(0)
        logits = rng.normal(size=(4, 7, *g.shape)).astype(np.float32)
        logits[:, 0] += np.where(lab > 0, -3.0, 3.0)[None]
        print(fmt("shell own view logits (4, 7, 128^3) float32",
                  measure(lambda: shell(logits, g, g.camera()), max(3, args.repeat // 3))))
        print(fmt("  of which inspect_volume (validation)",
                  measure(lambda: inspect_volume(logits, g), max(3, args.repeat // 3))))


if __name__ == "__main__":
    main()

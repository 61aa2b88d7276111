"""Profile the Warp backend's first_hit and shell on a room-like scene, on any Warp device.

    python benchmarks/profile_wp.py --device cpu
    python benchmarks/profile_wp.py --device cuda:0 --repeat 200

Scene: the kernel benchmark's (``fruxel.data.rooms``: ``room_volume(128)``, about 25 % occupied, and its
``oblique_camera``; ``orbit_cameras`` for ``shell``).
Cases (targets for an H100 in brackets):

* ``first_hit``  128^3 labels, 512^2 oblique view                       [<= 0.1 ms]
* ``first_hit``  256^3 labels, 1024^2 oblique view                      [<= 1 ms]
* ``first_hit``  (1, 7, 128^3) float32 logits, 512^2 (label pass included)
* ``shell``      128^3 labels, 6 orbit poses at 512^2                   [<= 1 ms]
* ``shell``      own view of (4, 7, 128^3) float32 logits               [<= 1 ms]

On CUDA the data are torch tensors on the device (zero copy, torch's stream) when torch has CUDA, else numpy;
times are per call, wall clock around ``repeat`` back-to-back calls closed by one synchronisation, so they include
the host overhead of a call; "kernels" adds up the GPU time of one call's kernels (Warp's activity timing). On the
CPU Warp runs one thread, and times are the median of single calls.

Options for experiments: ``--only TEXT`` (cases whose name contains it), ``--host`` (cProfile of the host side),
``--block-dim N``, ``--max-registers N`` and ``--fast-math`` for the ray-walking kernels.
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import time
from collections.abc import Callable
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.data import rooms
from fruxel.kernels import orbit_cameras
from fruxel.kernels.inputs import inspect_volume
from fruxel.kernels.wp import first_hit, shell, traverse
from fruxel.kernels.wp.runtime import resolve_device


def timed(fn: Callable[[], Any], device: str, repeat: int) -> float:
    """Milliseconds per call of ``fn`` on ``device`` (after two warm-up calls, which also compile)."""
    fn()
    fn()
    if device.startswith("cuda"):
        import warp as wp

        sync = _torch_sync(device) or (lambda: wp.synchronize_device(device))
        # Synchronise before and after the timed loop only: the calls queue asynchronously like a real pipeline.
        sync()
        t0 = time.perf_counter()
        for _ in range(repeat):
            fn()
        sync()
        return (time.perf_counter() - t0) / repeat * 1e3
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return statistics.median(times) * 1e3


def kernel_ms(fn: Callable[[], Any], device: str) -> str:
    """GPU time of the kernels of one call of ``fn`` (Warp's activity timing), or "" off CUDA."""
    if not device.startswith("cuda"):
        return ""
    import warp as wp

    fn()
    # timing_begin / timing_end synchronise the device, so that only this call's kernels are timed.
    wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
    fn()
    results = wp.timing_end()
    parts = ", ".join(f"{r.name.split('_kernel')[0]} {r.elapsed:.3f}" for r in results)
    return f"kernels {sum(r.elapsed for r in results):.3f} ms ({parts})"


def host_profile(fn: Callable[[], Any], device: str, calls: int = 300) -> None:
    """Print where the host time of ``calls`` calls of ``fn`` goes (cProfile, by own time)."""
    import cProfile
    import pstats

    fn()
    prof = cProfile.Profile()
    prof.enable()
    for _ in range(calls):
        fn()
    prof.disable()
    pstats.Stats(prof).sort_stats("tottime").print_stats(25)


def _torch_sync(device: str) -> Callable[[], None] | None:
    try:
        import torch
    except ImportError:
        return None
    if not torch.cuda.is_available():
        return None
    return lambda: torch.cuda.synchronize(device)


def _on_device(x: np.ndarray, device: str) -> Any:
    """Torch tensor on a CUDA device when torch has CUDA; numpy otherwise."""
    if device.startswith("cuda"):
        try:
            import torch

            if torch.cuda.is_available():
                return torch.from_numpy(x).to(device)
        except ImportError:
            pass
    return x


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--device", default=None, help="Warp device: cpu, cuda, cuda:N (default: CUDA if present)")
    ap.add_argument("--repeat", type=int, default=None, help="calls per case (default 5 on cpu, 100 on cuda)")
    ap.add_argument("--large", action="store_true", help="also run 256^3 @ 1024^2 on the CPU (slow there)")
    ap.add_argument("--only", default="", help="run only the cases whose name contains this text")
    ap.add_argument("--block-dim", type=int, default=None, help="CUDA block size of the ray-walking kernels")
    ap.add_argument("--fast-math", action="store_true", help="experiment: compile the ray kernels with fast math")
    ap.add_argument("--max-registers", type=int, default=None, help="experiment: register cap of the ray kernels")
    ap.add_argument("--host", action="store_true", help="print a cProfile of the host side of first_hit calls")
    args = ap.parse_args()
    device = resolve_device(args.device)
    if args.block_dim:
        traverse.TRACE_BLOCK_DIM = args.block_dim
    if args.max_registers:
        # Before the first launch, so that the modules are built with the cap.
        fh, sh = (importlib.import_module(f"fruxel.kernels.wp.{m}") for m in ("first_hit", "shell"))
        for kernel in (fh.trace_first_hit_kernel, sh.mark_shell_kernel):
            kernel.options["cuda_max_registers"] = args.max_registers
    if args.fast_math:
        import warp as wp

        for name in ("first_hit", "shell"):
            wp.set_module_options({"fast_math": True}, module=importlib.import_module(f"fruxel.kernels.wp.{name}"))
    cuda = device.startswith("cuda")
    repeat = args.repeat or (100 if cuda else 5)

    lab, grid = rooms.room_volume(128)
    print(f"device {device}, occupancy {np.mean(lab != 0):.3f}, repeat {repeat}")
    cams = orbit_cameras(grid, 6, width=512, height=512)
    oblique = rooms.oblique_camera(grid, 512)
    vol = _on_device(lab, device)

    def report(name: str, fn: Callable[[], Any], target: str = "", n: int = repeat) -> None:
        if args.only in name:
            print(f"{name:<52s} {timed(fn, device, n):9.3f} ms  {target}  {kernel_ms(fn, device)}", flush=True)

    report("first_hit 128^3 labels, 512^2 oblique", lambda: first_hit(vol, grid, oblique, device=device),
           "[H100 <= 0.1 ms]")
    if args.host:
        host_profile(lambda: first_hit(vol, grid, oblique, device=device), device)
    c = grid.centre()
    views = {
        "close oblique": Camera.look_at(c + [4.5, -6.0, -4.5], c, width=512, height=512),
        "above, looking down": Camera.look_at(c + [0.3, -6.0, 0.2], c, width=512, height=512),
    }
    for name, cam in views.items():
        h = first_hit(lab, grid, cam, device=device)
        report(f"first_hit 128^3 labels, 512^2 {name} (hit {np.mean(np.asarray(h.cell) >= 0):.2f})",
               lambda cam=cam: first_hit(vol, grid, cam, device=device))

    rng = np.random.default_rng(1)
    logits = rng.normal(size=(1, 7) + grid.shape).astype(np.float32)
    logits[:, 0] += 2.0
    logits[0, 1] += 6.0 * (lab != 0)
    vlog = _on_device(logits, device)
    report("first_hit (1,7,128^3) f32 logits, 512^2 oblique", lambda: first_hit(vlog, grid, oblique, device=device))
    report("shell 128^3 labels, 6 poses @ 512^2", lambda: shell(vol, grid, cams, device=device), "[H100 <= 1 ms]")
    vlog4 = _on_device(np.concatenate([logits] * 4), device)
    own = grid.camera()
    report("shell own view (4,7,128^3) f32 logits", lambda: shell(vlog4, grid, own, device=device),
           "[H100 <= 1 ms]")
    report("  of which inspect_volume (validation)", lambda: inspect_volume(vlog4, grid))
    report("shell own view 128^3 labels", lambda: shell(vol, grid, own, device=device))

    if cuda or args.large:
        lab_big, big = rooms.room_volume(256)
        vbig = _on_device(lab_big, device)
        cam_big = rooms.oblique_camera(big, 1024)
        report("first_hit 256^3 labels, 1024^2 oblique", lambda: first_hit(vbig, big, cam_big, device=device),
               "[H100 <= 1 ms]")


if __name__ == "__main__":
    main()

"""Tune the ray-walking kernels' launch shape on a CUDA device: block size and register cap.

    python benchmarks/tune_trace.py                                   # the default grid of variants
    python benchmarks/tune_trace.py --variants 128:0 64:64   # block:registers (0 = no cap)
    python benchmarks/tune_trace.py --variants 128:0 128:0:fm  # ...:fm compiles with fast math (diagnostic only)

Each variant runs in a fresh process with its own Warp kernel cache, so that the kernels are built with its
settings. It times, with Warp's CUDA event timing (kernels only, no host overhead), the first_hit trace kernel on
the kernel benchmark's scene (128^3 ``room_volume``, 512^2 oblique view) and the shell marking kernel over 6 orbit
poses, and checks that every variant returns exactly the first variant's hit cells. The settings it varies are
``traverse.TRACE_BLOCK_DIM`` and the kernels' ``cuda_max_registers`` option. Results so far are in
``benchmarks/PERF_NOTES.md``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import os
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

DEFAULT_VARIANTS = ["128:0", "64:0", "32:0", "256:0", "128:64", "128:80"]


def child(variant: str, reference: str, repeat: int, device: str = "cuda") -> dict:
    """Run one variant in this process and return its timings (milliseconds)."""
    import numpy as np
    import torch

    from fruxel.kernels.wp.runtime import warp

    wp = warp()
    wp.config.kernel_cache_dir = tempfile.mkdtemp(prefix="fruxel-tune-")
    block, regs, *flags = variant.split(":")
    from fruxel.kernels.wp import traverse

    traverse.TRACE_BLOCK_DIM = int(block)
    from fruxel.data import rooms
    from fruxel.kernels import orbit_cameras
    from fruxel.kernels.wp import first_hit, shell

    fh_mod = sys.modules["fruxel.kernels.wp.first_hit"]
    sh_mod = sys.modules["fruxel.kernels.wp.shell"]
    for kernel in (fh_mod.trace_first_hit_kernel, sh_mod.mark_shell_kernel):
        if int(regs):
            kernel.options["cuda_max_registers"] = int(regs)
    if "fm" in flags:
        for mod in (fh_mod, sh_mod):
            wp.set_module_options({"fast_math": True}, module=mod)

    lab, grid = rooms.room_volume(128)
    vol = torch.from_numpy(lab).to(device)
    cam = rooms.oblique_camera(grid, 512)
    cams = orbit_cameras(grid, 6, width=512, height=512)
    cells = first_hit(vol, grid, cam).cell.cpu().numpy()
    shell_out = shell(vol, grid, cams).cpu().numpy()
    same = differing = None
    if os.path.exists(reference):
        ref = np.load(reference)
        same = bool(np.array_equal(ref["cells"], cells) and np.array_equal(ref["shell"], shell_out))
        differing = int(np.count_nonzero(ref["cells"] != cells))
    else:
        np.savez(reference, cells=cells, shell=shell_out)

    def kernel_ms(fn, name: str) -> float:
        """Median summed time of the kernels whose names hold one of the ``|``-separated parts of ``name``."""
        runs = []
        for _ in range(repeat):
            wp.timing_begin(cuda_filter=wp.TIMING_KERNEL)
            fn()
            runs.append(sum(r.elapsed for r in wp.timing_end() if any(n in r.name for n in name.split("|"))))
        return statistics.median(runs)

    # The 32 pixels of the warp whose rays walk longest in this view (row 267, x 192-223, found with an
    # instrumented walk; PERF_NOTES.md): alone on the GPU, its kernel time is the walk's critical path.
    longest = dataclasses.replace(cam, width=32, height=1, cx=cam.cx - 192, cy=cam.cy - 267)
    batch4 = torch.stack([vol] * 4)
    for _ in range(3):
        first_hit(vol, grid, cam)
        shell(vol, grid, cams)
    return {
        "variant": variant,
        "first_hit trace ms": kernel_ms(lambda: first_hit(vol, grid, cam), "trace_first_hit"),
        "pyramid ms": kernel_ms(lambda: first_hit(vol, grid, cam), "pyramid|flag_"),
        "longest warp ms": kernel_ms(lambda: first_hit(vol, grid, longest), "trace_first_hit"),
        "B=4 trace ms per frame": kernel_ms(lambda: first_hit(batch4, grid, cam), "trace_first_hit") / 4,
        "shell 6 poses mark ms": kernel_ms(lambda: shell(vol, grid, cams), "mark_shell"),
        "same as first": same,
        "cells differing from first": differing,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--variants", nargs="+", default=DEFAULT_VARIANTS, help="block:registers[:fm]")
    ap.add_argument("--repeat", type=int, default=30, help="timed calls per kernel (median)")
    ap.add_argument("--device", default="cuda", help="torch device of the volume (cpu only checks the script)")
    ap.add_argument("--child", default=None, help=argparse.SUPPRESS)
    ap.add_argument("--reference", default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        print("RESULT " + json.dumps(child(args.child, args.reference, args.repeat, args.device)), flush=True)
        return 0
    reference = os.path.join(tempfile.mkdtemp(prefix="fruxel-tune-ref-"), "reference.npz")
    rows = []
    for v in args.variants:
        proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), "--child", v, "--reference", reference,
                               "--repeat", str(args.repeat), "--device", args.device], capture_output=True, text=True)
        line = next((x for x in proc.stdout.splitlines() if x.startswith("RESULT ")), None)
        if line is None:
            print(f"{v}: failed\n{proc.stdout[-2000:]}\n{proc.stderr[-3000:]}", flush=True)
            continue
        rows.append(json.loads(line[7:]))
        r = rows[-1]
        print(f"{v:>14s}  first_hit trace {r['first_hit trace ms']:.4f} ms  pyramid {r['pyramid ms']:.4f} ms  "
              f"longest warp {r['longest warp ms']:.4f} ms  B=4 {r['B=4 trace ms per frame']:.4f} ms/frame  "
              f"shell mark (6) {r['shell 6 poses mark ms']:.4f} ms  same {r['same as first']} "
              f"({r['cells differing from first']} cells differ)", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())

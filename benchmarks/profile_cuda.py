"""Where the time of the GPU cases goes: host issue time, GPU kernel time and latency, per case, on one CUDA device.

    python benchmarks/profile_cuda.py                     # every case
    python benchmarks/profile_cuda.py --only losses       # the cases whose name contains "losses"

Cases are the benchmarks' own (``bench_kernels.py``, ``bench_losses.py``), torch CUDA tensors in and out:

* ``first_hit``: 128^3 room labels, 512^2 oblique view;
* ``shell 6 poses``: the same volume, 6 orbit poses at 512^2;
* ``own-view shell``: ``(4, 7, 128^3)`` float32 logits;
* ``losses``: ``ShellLoss.losses`` forward + backward, ``(16, 7, 64^3)`` logits, own view + 2 novel views at 128^2;
* ``soft own view``: ``soft_first_hit`` from the own view, shell cross-entropy + depth L1, forward + backward.

Per case, in milliseconds per call:

* *latency*: median of single calls, each closed by a synchronisation (what ``bench_*.py`` report);
* *pipelined*: back-to-back calls closed by one synchronisation (a render or training loop that never waits);
* *host*: the time the host takes to issue one call, measured in that loop before the synchronisation (the GPU is
  then still working: when *host* is close to *pipelined*, the host is the bottleneck);
* *GPU*: the summed device time of one call's kernels and copies (torch's profiler, CUPTI), with the largest
  kernels listed.

Needs torch with CUDA; writes nothing (``--out FILE`` also writes the report as text).
"""

from __future__ import annotations

import argparse
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import bench_kernels  # noqa: E402
import bench_losses  # noqa: E402
import common  # noqa: E402

from fruxel.data import rooms  # noqa: E402
from fruxel.kernels import first_hit, orbit_cameras, shell  # noqa: E402
from fruxel.kernels.soft import soft_first_hit  # noqa: E402
from fruxel.train.losses import ShellLoss, ShellLossConfig, depth_l1, random_poses, shell_cross_entropy  # noqa: E402


def host_profile(fn: Callable[[], Any], calls: int = 100) -> str:
    """cProfile of the host side of ``calls`` calls (by own time), as text."""
    import cProfile
    import io
    import pstats

    prof = cProfile.Profile()
    prof.enable()
    for _ in range(calls):
        fn()
    prof.disable()
    torch.cuda.synchronize()
    text = io.StringIO()
    pstats.Stats(prof, stream=text).sort_stats("tottime").print_stats(22)
    return text.getvalue()


def report(name: str, fn: Callable[[], Any], repeat: int, out: list[str], host: bool = False) -> None:
    """Time one case (after three warm-up calls), print its line and largest kernels, and append them to ``out``;
    with ``host``, also a cProfile of its host side."""
    for _ in range(3):
        fn()
    lat = common.time_calls(fn, repeat, sync=torch.cuda.synchronize)["median_ms"]
    p = common.pipelined_ms(fn, repeat, torch.cuda.synchronize)
    pipe, host_ms = p["pipelined_ms"], p["host_ms"]
    gpu, rows = common.cuda_kernel_ms(fn)
    lines = [f"== {name}: latency {lat:.3f} ms, pipelined {pipe:.3f} ms, host {host_ms:.3f} ms, GPU {gpu:.3f} ms"]
    for kname, ms, n in rows[:12]:
        lines.append(f"     {ms:8.4f} ms x{n:<3d} {kname[:110]}")
    if host:
        lines.append(host_profile(fn))
    print("\n".join(lines), flush=True)
    out.extend(lines)


def host_parts(vol: Any, grid: Any, cam: Any, out: list[str], n: int = 2000) -> None:
    """Host microseconds of the pieces of a ``first_hit`` call (no synchronisation inside the loops)."""
    from fruxel.kernels import wp as wpb
    from fruxel.kernels.inputs import inspect_volume
    from fruxel.kernels.registry import resolve
    from fruxel.kernels.wp.arrays import Workspace

    def us(fn: Callable[[], Any]) -> float:
        for _ in range(10):
            fn()
        torch.cuda.synchronize()
        t0 = time.perf_counter()
        for _ in range(n):
            fn()
        t1 = time.perf_counter()
        torch.cuda.synchronize()
        return (t1 - t0) / n * 1e6

    parts = {
        "public first_hit": lambda: first_hit(vol, grid, cam),
        "wp.first_hit": lambda: wpb.first_hit(vol, grid, cam, device="cuda:0"),
        "resolve": lambda: resolve(None, None, vol),
        "inspect_volume": lambda: inspect_volume(vol, grid),
        "Workspace.like": lambda: Workspace("cuda:0", "torch", "cuda:0"),
        "torch.empty 1 MB": lambda: torch.empty((512, 512), dtype=torch.int32, device="cuda:0"),
        "torch.zeros 33 kB": lambda: torch.zeros((1, 33280), dtype=torch.uint8, device="cuda:0"),
        "current_stream": lambda: torch.cuda.current_stream(torch.device("cuda:0")).cuda_stream,
    }
    lines = ["== host parts (us per call): " + ", ".join(f"{k} {us(f):.1f}" for k, f in parts.items())]
    print(lines[0], flush=True)
    out.extend(lines)


def main(argv: list[str] | None = None) -> int:
    """Run the cases that ``--only`` selects on ``cuda:0`` and print (and with ``--out`` write) the report."""
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--only", default="", help="run only the cases whose name contains this text")
    ap.add_argument("--repeat", type=int, default=50, help="calls per timing")
    ap.add_argument("--out", default=None, help="also write the report to this text file")
    ap.add_argument("--host", action="store_true", help="add a cProfile of each case's host side")
    args = ap.parse_args(argv)
    dev = "cuda:0"
    out = [f"{torch.cuda.get_device_name(0)}, torch {torch.__version__}"]
    print(out[0])

    def want(name: str) -> bool:
        return args.only in name

    lab, grid = rooms.room_volume(128)
    vol = torch.from_numpy(lab).to(dev)
    cam = rooms.oblique_camera(grid, 512)
    if want("first_hit"):
        report("first_hit 128^3 @ 512^2", lambda: first_hit(vol, grid, cam), args.repeat, out, args.host)
    if want("host parts"):
        host_parts(vol, grid, cam, out)
    if want("first_hit extremes"):
        # The same view of an empty and of a full volume: the cost of a ray's set-up and exit, and of its first hit.
        for name, fill in (("empty", 0), ("full", 1)):
            v = torch.full_like(vol, fill)
            report(f"first_hit 128^3 @ 512^2, {name} volume", lambda v=v: first_hit(v, grid, cam), args.repeat, out)
    if want("shell 6 poses"):
        cams = orbit_cameras(grid, 6, width=512, height=512)
        report("shell 6 poses", lambda: shell(vol, grid, cams), args.repeat, out, args.host)
    if want("own-view shell"):
        logits = torch.from_numpy(bench_kernels.logits_batch(128)).to(dev)
        report("own-view shell (4,7,128^3)", lambda: shell(logits, grid, grid.camera()), args.repeat, out, args.host)
    if want("losses") or want("soft own view"):
        labels, logits, g64 = bench_losses.make_batch(64, 16, "scene", dev)
        logits.requires_grad_()
        loss = ShellLoss(g64, ShellLossConfig(novel_views=bench_losses.NOVEL, novel_size=bench_losses.NOVEL_SIZE))
        cams = [g64.camera()] + random_poses(g64, bench_losses.NOVEL, np.random.default_rng(1),
                                             width=bench_losses.NOVEL_SIZE[0], height=bench_losses.NOVEL_SIZE[1])
        targets = loss.targets(labels, cams)

        def losses() -> None:
            logits.grad = None
            loss.losses(logits, cams, targets).total.backward()

        def own() -> None:
            logits.grad = None
            h = soft_first_hit(logits, g64, g64.camera())
            own_t = targets.groups[0]
            (shell_cross_entropy(h, own_t[0]) + depth_l1(h, own_t[1], own_t[2])).backward()

        if want("losses"):
            report("losses fwd+bwd B=16", losses, args.repeat // 2, out, args.host)
        if want("soft own view"):
            report("soft own view fwd+bwd B=16", own, args.repeat // 2, out, args.host)
    if args.out:
        Path(args.out).write_text("\n".join(out) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

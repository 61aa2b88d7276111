"""fruxelize kernel benchmark: one thread a (part, column) pair against one thread a grid column.

``fruxelize`` labels every cell of a grid by the latest mesh whose solid holds its centre. Its Warp kernels walk one
part along one column's centre ray (``fruxel.kernels.wp.fruxelize``); on a CUDA device one thread takes a (part,
column) pair, on the CPU one thread a column loops over the parts of the meshes its ray meets. This script runs
both on the same furnished rooms from any camera (the simulator's own rooms and poses), alternating their order per
pose, with the device synchronised around each call: per kernel the median milliseconds of a call (labels copied
back included, as the simulator's workers take them), and the column kernel's time over the pair kernel's. Every
pose's two label volumes must be equal; the count is reported.

    python benchmarks/bench_fruxelize.py                               # this machine's CPU device: fruxelize-cpu.json
    python benchmarks/bench_fruxelize.py --device cuda:0 --tag h200 --no-write --json $OUT/fruxelize-h200.json
    python benchmarks/bench_fruxelize.py --report                      # the section from every fruxelize-*.json

Results go to ``benchmarks/results/fruxelize-{tag}.json``; unless ``--no-write``, the "## fruxelize kernels"
section of BENCHMARKS.md is rebuilt from every ``fruxelize-*.json`` there.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

SECTION = "## fruxelize kernels"
KERNELS = {"pairs": True, "columns": False}
"""The kernels by name: the ``pairs`` argument of ``fruxel.kernels.wp.fruxelize.fruxelize``."""


def measure(device: str, rooms: int, poses: int, grid: int) -> list[dict[str, Any]]:
    """Per kernel: the median ms of a call over every room and pose, and how many poses' labels agreed."""
    import importlib

    import numpy as np
    import warp as wp
    from bench_sim import make_config

    from fruxel.train.sim.sample import SampleMaker

    kernels = importlib.import_module("fruxel.kernels.wp.fruxelize")
    cfg = make_config(64, grid, 16 * rooms, 64, camera="any", renderer="raytrace", world="home")
    times: dict[str, list[float]] = {k: [] for k in KERNELS}
    parts, equal, count = [], 0, 0
    sps = cfg.samples_per_scene
    with SampleMaker(cfg, 0, device=device) as maker:
        for r in range(rooms):
            scene = maker.scene_of("train", r * sps)[0]
            frames = [maker.scene_of("train", r * sps + k)[1] for k in range(min(poses, sps))]
            native = scene.mesh_set(device=device).native
            parts.append(int(native.parts.kind.shape[0]))
            for pairs in KERNELS.values():  # compiles and warms both
                kernels.fruxelize(native, cfg.grid, frames[0], pairs=pairs)
            for k, pose in enumerate(frames):
                labels = {}
                for name in (KERNELS if k % 2 == 0 else list(KERNELS)[::-1]):
                    wp.synchronize()
                    t0 = time.perf_counter()
                    labels[name] = kernels.fruxelize(native, cfg.grid, pose, pairs=KERNELS[name])[0]
                    times[name].append((time.perf_counter() - t0) * 1000)
                equal += int(np.array_equal(labels["pairs"], labels["columns"]))
                count += 1
    rows = [{"kernel": k, "call_ms": statistics.median(v)} for k, v in times.items()]
    pairs_ms = rows[0]["call_ms"]
    for row in rows:
        row.update(over_pairs=row["call_ms"] / pairs_ms, grid=grid, rooms=rooms, poses=count, equal=equal,
                   median_parts=int(statistics.median(parts)))
    return rows


def section(runs: list[dict[str, Any]]) -> str:
    """The "## fruxelize kernels" Markdown section from stored runs."""
    lines = [SECTION, "", "`python benchmarks/bench_fruxelize.py` (its docstring has the GPU command): fruxelize's "
             "two kernels on the same furnished rooms from any camera, alternated per pose; medians of milliseconds "
             "per call with the device synchronised around it, labels copied back included. The pair kernel is "
             "CUDA's, the column kernel the CPU's.", ""]
    lines += [common.device_run_line(run) for run in runs]
    lines += ["", "| machine | device | grid | rooms | poses | parts (median) | kernel | ms a call | over the pair "
              "kernel's | labels equal |", "| --- | --- | ---: | ---: | ---: | ---: | --- | ---: | ---: | ---: |"]
    for run in runs:
        for r in run["results"]:
            lines.append(f"| {run['tag']} | {run['device']} | {r['grid']}^3 | {r['rooms']} | {r['poses']} | "
                         f"{r['median_parts']} | {r['kernel']} | {r['call_ms']:.2f} | {r['over_pairs']:.2f} | "
                         f"{r['equal']} of {r['poses']} |")
    return common.with_notes(lines, runs)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.add_device_run_options(p)
    p.add_argument("--rooms", type=int, default=4)
    p.add_argument("--poses", type=int, default=8, help="poses per room (at most its 16 frames)")
    p.add_argument("--grid", type=int, default=64, help="cells along each axis (default 64)")
    args = p.parse_args(argv)
    run = None
    if not args.report:
        run = common.device_run(args, measure(args.device, args.rooms, args.poses, args.grid))
    common.finish_device_run(args, run, "fruxelize", SECTION, section)


if __name__ == "__main__":
    main()

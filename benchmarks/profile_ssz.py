"""Where an SSZ training step's GPU time goes, kernel by kernel: ``torch.profiler`` over forward + objective +
backward of a preset's generator on a synthetic batch (random images and labels; no data loading, no optimiser).

    source .gpu/bin/device-env.sh && python benchmarks/profile_ssz.py --preset ssz64 --out $OUT/profile-ssz64.json

Prints the wall time of a step (the host free to run ahead, as in training: a step whose wall time is well
above its kernels' time is bound by launching them), the kernels that take the most device time (summed over
``--steps`` profiled steps, after ``--warm`` unprofiled ones) and the totals per kind of kernel (a rough grouping
by name: convolutions, depthwise 3D, elementwise, normalisation, reductions, copies). Companion of
``bench_ssz.py``, whose *train* part times the same step with streamed data and gives the phases (data, forward,
losses, backward, optimiser).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path
from typing import Any

KINDS = (("depthwise 3D", ("depthwise3d", "conv_depthwise3d")),
         ("convolution", ("conv", "gemm", "sm90", "xmma", "cutlass", "implicit")),
         ("normalisation", ("norm",)),
         ("reduction", ("reduce", "softmax", "nll", "cross_entropy")),
         ("copy / layout", ("copy", "cat", "transpose", "nchw", "nhwc", "memcpy", "memset")),
         ("elementwise", ("elementwise", "vectorized", "unrolled", "pointwise")))
"""Kinds of kernel, each with the name fragments that put a kernel in it (first match wins)."""


def kind_of(name: str) -> str:
    """The kind of a CUDA kernel from its (mangled or demangled) name."""
    low = name.lower()
    for kind, keys in KINDS:
        if any(k in low for k in keys):
            return kind
    return "other"


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--preset", default="ssz64")
    p.add_argument("--batch", type=int, default=None, help="batch (default: the preset's)")
    p.add_argument("--steps", type=int, default=5, help="profiled steps")
    p.add_argument("--warm", type=int, default=5, help="unprofiled steps first")
    p.add_argument("--top", type=int, default=30, help="kernels to print")
    p.add_argument("--channels-last", action="store_true", help="channels-last weights and input")
    p.add_argument("--compile", action="store_true", help="torch.compile the generator")
    p.add_argument("--inference", action="store_true", help="profile prediction instead: the forward pass alone, "
                   "eval mode, no gradients (with --compile as CUDA graphs, mode reduce-overhead)")
    p.add_argument("--ops", type=int, default=0, help="also print the N operators (with input shapes) that take "
                   "the most device time")
    p.add_argument("--out", default=None, help="write the table as JSON here")
    args = p.parse_args(argv)

    import torch
    from torch.profiler import ProfilerActivity, profile

    from fruxel.train.config import preset
    from fruxel.train.models.blocks import channels_last
    from fruxel.train.objective import SSZObjective

    if not torch.cuda.is_available():
        print("profile_ssz: needs CUDA", file=sys.stderr)
        return 2
    dev = torch.device("cuda")
    cfg = preset(args.preset)
    m = cfg.model
    batch = args.batch or cfg.run.batch_size
    g = m.build().to(dev)
    if args.channels_last:
        g = channels_last(g)
    obj = SSZObjective(cfg.loss, torch.ones(m.num_classes, device=dev))
    if args.inference:
        g.eval()
    f = torch.compile(g, mode="reduce-overhead" if args.inference else None) if args.compile else g
    x = torch.rand(batch, 3, *m.image_size, device=dev)
    if args.channels_last:
        x = x.contiguous(memory_format=torch.channels_last)
    y = torch.randint(0, m.num_classes, (batch, *m.grid.shape), device=dev, dtype=torch.uint8)

    def step() -> None:
        if args.inference:
            with torch.no_grad(), torch.autocast("cuda", dtype=torch.bfloat16):
                f(x)
            return
        with torch.autocast("cuda", dtype=torch.bfloat16):
            loss = obj(f(x), y)["total"]
        loss.backward()

    for _ in range(args.warm):
        step()
    torch.cuda.synchronize()  # the warm-up's kernels must not land in the timing
    t0 = time.perf_counter()
    for _ in range(args.warm):
        step()
    torch.cuda.synchronize()  # one wait for all the timed steps: the host runs ahead as in training
    wall = 1000.0 * (time.perf_counter() - t0) / args.warm
    activities = [ProfilerActivity.CUDA] + ([ProfilerActivity.CPU] if args.ops else [])
    with profile(activities=activities, record_shapes=bool(args.ops)) as prof:
        for _ in range(args.steps):
            step()
        torch.cuda.synchronize()  # the profiler reads every kernel of the profiled steps
    rows: dict[str, dict[str, Any]] = {}
    for ev in prof.events():
        if ev.device_type != torch.autograd.DeviceType.CUDA:
            continue
        r = rows.setdefault(ev.name, {"name": ev.name, "ms": 0.0, "calls": 0})
        r["ms"] += ev.device_time / 1000.0 / args.steps
        r["calls"] += 1
    table = sorted(rows.values(), key=lambda r: -r["ms"])
    for r in table:
        r["calls"] //= args.steps
        r["kind"] = kind_of(r["name"])
    total = sum(r["ms"] for r in table)
    kinds: dict[str, float] = {}
    for r in table:
        kinds[r["kind"]] = kinds.get(r["kind"], 0.0) + r["ms"]
    launches = sum(r["calls"] for r in table)
    what = ("prediction" if args.inference else "training") + (", compiled" if args.compile else "")
    print(f"{args.preset}, batch {batch}, {what}: {wall:.2f} ms a step (wall, "
          f"unprofiled), {total:.2f} ms of kernels ({launches} launches, {len(table)} distinct kernels)")
    for k, v in sorted(kinds.items(), key=lambda kv: -kv[1]):
        print(f"  {k:14s} {v:8.2f} ms  {100 * v / total:5.1f} %")
    for r in table[:args.top]:
        print(f"{r['ms']:8.3f} ms {r['calls']:4d}x  {r['kind']:13s} {r['name'][:110]}")
    if args.ops:
        print(prof.key_averages(group_by_input_shape=True).table(sort_by="self_device_time_total",
                                                                 row_limit=args.ops, max_name_column_width=40,
                                                                 max_shapes_column_width=90))
    if args.out:
        Path(args.out).write_text(json.dumps({"preset": args.preset, "batch": batch, "compiled": args.compile,
                                              "inference": args.inference,
                                              "wall_ms": wall, "launches": launches, "total_ms": total,
                                              "kinds": kinds, "kernels": table}, indent=1) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

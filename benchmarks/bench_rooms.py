"""Furnished-room benchmark: milliseconds to make one room of the "home" world (``make_home``) on one CPU core, with
the time of each of its stages, and the per-room cost that follows it on the streaming path (the solids prepared
for ``fruxelize``: ``prepare_meshes``, the host half of ``SampleMaker``'s upload).

A worker process keeps its asset pack decoded (meshes, support surfaces, texture colours) from room to room, so the
first rooms of a process pay for decoding what they use; the *cold* rows are the first ``--warm`` rooms of a fresh
process, the *warm* rows the rooms after them (what a data worker streams at). Rooms draw their room type, size and
contents from their seeds: seeds 0..N-1 of the train split.

    python benchmarks/bench_rooms.py                    # this machine: writes rooms-cpu.json and the section
    python benchmarks/bench_rooms.py --tag h100 --no-write --json $OUT/rooms-h100.json   # elsewhere: JSON only
    python benchmarks/bench_rooms.py --report           # rebuild the section from every rooms-*.json

Results go to ``benchmarks/results/rooms-{tag}.json``; unless ``--no-write``, the "## Furnished rooms" section of
BENCHMARKS.md is rebuilt from all ``rooms-*.json`` files there.

Target (the issue's throughput: 600 samples/s from 14 worker processes at 16 samples per room is 2.7 rooms/s per
worker, whose samples also need rendering and labels): a warm room well under a second on one core; this benchmark
holds it to 200 ms.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import sys
import time
from pathlib import Path
from typing import Any

os.environ.setdefault("OMP_NUM_THREADS", "1")
sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

SECTION = "## Furnished rooms"
TARGET_MS = 200.0
"""Warm milliseconds per room asked for (module docstring)."""


def bench(rooms: int, warm: int, assets: str | None) -> dict[str, Any]:
    """Time ``rooms`` rooms in this process; the first ``warm`` are the cold ones."""
    import numpy as np

    from fruxel.kernels.fruxelize import prepare_meshes
    from fruxel.train.sim.rooms import STAGES, library, make_home

    t0 = time.perf_counter()
    lib = library(assets)
    open_s = time.perf_counter() - t0
    rows = []
    for seed in range(rooms):
        stages: dict[str, float] = {}
        t = time.perf_counter()
        scene = make_home(seed, assets=lib, timings=stages)
        total = time.perf_counter() - t
        t = time.perf_counter()
        prepare_meshes(scene.labelled_meshes())
        upload = time.perf_counter() - t
        rows.append({"total": total, "upload": upload, "stages": stages, "objects": len(scene.objects),
                     "triangles": int(sum(len(o.mesh.faces) for o in scene.objects))})

    def summary(part: list[dict[str, Any]]) -> dict[str, Any]:
        ms = np.array([r["total"] for r in part]) * 1e3
        return {"rooms": len(part), "mean_ms": float(ms.mean()), "median_ms": float(np.median(ms)),
                "p90_ms": float(np.percentile(ms, 90)), "max_ms": float(ms.max()),
                "stages_ms": {s: float(np.mean([r["stages"].get(s, 0.0) for r in part]) * 1e3) for s in STAGES},
                "upload_ms": float(np.mean([r["upload"] for r in part]) * 1e3),
                "objects": float(np.mean([r["objects"] for r in part])),
                "triangles": float(np.mean([r["triangles"] for r in part]))}

    return {"open_pack_ms": open_s * 1e3, "cold": summary(rows[:warm]), "warm": summary(rows[warm:])}


def section(runs: list[dict[str, Any]]) -> str:
    """The "## Furnished rooms" Markdown section from stored runs."""
    from fruxel.train.sim.rooms import STAGES

    lines = [SECTION, "", "`python benchmarks/bench_rooms.py`: milliseconds to make one furnished room (`make_home`, "
             "the `home` world) in one process on one core, seeds 0..N-1 of the train split, and the per-room "
             "`prepare_meshes` (the host half of the upload for `fruxelize`) after it. *cold*: the first rooms of a "
             "fresh process, which decode the pack assets they use; *warm*: the rooms after them, as a data worker "
             "streams them.", ""]
    for run in runs:
        m = run["machine"]
        lines.append(f"- **{run['tag']}**: {m['cpu']}, {m['cores']} cores; run {run['date']}; Python "
                     f"{m['python']}, NumPy {m['versions'].get('numpy')}; opening the pack "
                     f"{run['result']['open_pack_ms']:.0f} ms; 1-minute load average before the run "
                     f"{m['load_average']:.2f}.")
    lines += ["", "| machine | rooms | mean ms | median ms | p90 ms | max ms | objects | triangles | "
              "prepare_meshes ms | target | met |", "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | "
              "---: | --- |"]
    for run in runs:
        for kind in ("cold", "warm"):
            r = run["result"][kind]
            met = ("yes" if r["mean_ms"] <= TARGET_MS else "**no**") if kind == "warm" else ""
            target = f"<= {TARGET_MS:g}" if kind == "warm" else ""
            lines.append(f"| {run['tag']} | {kind} {r['rooms']} | {r['mean_ms']:.0f} | {r['median_ms']:.0f} | "
                         f"{r['p90_ms']:.0f} | {r['max_ms']:.0f} | {r['objects']:.0f} | {r['triangles']:.0f} | "
                         f"{r['upload_ms']:.0f} | {target} | {met} |")
    lines += ["", "Milliseconds per stage of a warm room (`fruxel.train.sim.rooms.STAGES`, in the generator's "
              "order):", "", "| machine | " + " | ".join(STAGES) + " |", "| --- | " +
              " | ".join("---:" for _ in STAGES) + " |"]
    for run in runs:
        ms = run["result"]["warm"]["stages_ms"]
        lines.append(f"| {run['tag']} | " + " | ".join(f"{ms.get(s, 0.0):.1f}" for s in STAGES) + " |")
    lines.append("")
    return "\n".join(lines)


def load_results() -> list[dict[str, Any]]:
    """Every ``benchmarks/results/rooms-*.json``, CPU first."""
    runs = [json.loads(p.read_text()) for p in sorted(common.RESULTS.glob("rooms-*.json"))]
    return sorted(runs, key=lambda r: (r["tag"] != "cpu", r["tag"]))


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tag", default="cpu", help="machine tag of the results file rooms-TAG.json (default cpu)")
    p.add_argument("--rooms", type=int, default=200, help="rooms made in all (default 200)")
    p.add_argument("--warm", type=int, default=20, help="the first rooms, counted as cold (default 20)")
    p.add_argument("--assets", default=None, help="asset pack folder (default: $FRUXEL_ASSETS, else assets/pack)")
    p.add_argument("--no-write", action="store_true", help="write the JSON only, not BENCHMARKS.md")
    p.add_argument("--report", action="store_true", help="only rebuild the section from the JSON files")
    p.add_argument("--json", default=None, help="also copy the JSON here")
    args = p.parse_args(argv)
    if not args.report:
        if not 0 < args.warm < args.rooms:
            raise SystemExit(f"bench_rooms: --warm must be in [1, --rooms), got {args.warm}")
        info = common.machine_info(("numpy", "trimesh"))
        print(f"bench_rooms: {args.rooms} rooms ...", file=sys.stderr, flush=True)
        run = {"tag": args.tag, "date": dt.date.today().isoformat(), "machine": info,
               "result": bench(args.rooms, args.warm, args.assets)}
        text = json.dumps(run, indent=1) + "\n"
        common.write_text(common.RESULTS / f"rooms-{args.tag}.json", text)
        if args.json:
            common.write_text(Path(args.json), text)
        print(section([run]))
        if args.no_write:
            return
    common.replace_section(common.BENCHMARKS_MD, SECTION, section(load_results()))
    print(f"wrote the {SECTION!r} section of {common.BENCHMARKS_MD.name}")


if __name__ == "__main__":
    main()

"""Simulator benchmark: samples per second of the data set generator and of the streaming data set.

A sample is made end to end: room (``make_scene``), robot trajectory, mesh upload for ``fruxelize`` (once per
room), pyrender image with augmentation, ``fruxelize`` of the grid; ``generate`` also compresses and writes the
shards and the manifest.

Modes (``--mode``, comma-separated):

* ``generate``  — ``fruxel.train.sim.writer.generate`` into a temporary folder with ``--workers`` processes;
* ``streaming`` — the one data path: ``fruxel.train.samples.BlockStream`` of the simulator
  (``fruxelize`` on Warp, ``--device``) batched by ``Batches`` in spawned DataLoader workers, batches of 8;
* ``profile``   — one process, seconds per stage (no files), plus shard encoding.

``--camera any`` makes every case's samples with any camera (``fruxel.train.sim.cameras.ANY_CAMERA``: renders of
50 to 80 degrees framed onto the grid's view) instead of the robot's own mount; its rows say so.

Rates: *steady* counts from the moment every worker has delivered (start-up excluded), *end to end* from the call
to the last sample (process start-up, imports, EGL and Warp start included). Cases are ``SxG`` (image S^2,
grid G^3), default ``256x64,512x128``.

    python benchmarks/bench_sim.py                                   # this machine: writes sim-cpu.json
    python benchmarks/bench_sim.py --tag h100 --mode profile,streaming,generate \\
        --cases 128x64:2048,256x64:1024,512x128:512 --workers 16 --no-write      # on the H100: JSON only
    python benchmarks/bench_sim.py --report                          # section + chart from every sim-*.json

Results go to ``benchmarks/results/sim-{tag}.json``; unless ``--no-write``, the "## Simulator" section of
BENCHMARKS.md and ``benchmarks/results/sim.png`` are rebuilt from all ``sim-*.json`` files there.

Targets (from the issue): on the 2-core machine at least 10 samples/s at 256^2 with 64^3 and 2 samples/s at 512^2
with 128^3; on the H100 machine at least 150 samples/s at 128^2 with 64^3 when streaming.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import os
import re
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

CHART = common.RESULTS / "sim.png"
SECTION = "## Simulator"

VARIANT_DEFAULTS = {"camera": "robot", "renderer": "pyrender", "world": "flat", "rays": "", "per_room": 0}
"""What a case is made with unless ``--camera``, ``--renderer``, ``--world``, ``--rays`` or ``--samples-per-room``
say otherwise (results record only the choices that differ; ``per_room`` 0 is the simulator's default)."""
TARGETS = {("cpu", "256x64"): 10.0, ("cpu", "512x128"): 2.0, ("h100", "128x64"): 150.0}
"""Samples per second asked for, by (machine tag, case)."""
TARGET_MODES = {"cpu": ("generate",), "h100": ("streaming",)}
"""The modes each target is checked against."""
HOME_TARGET = 600.0
"""Samples per second asked of the furnished world's stream from any camera (256^2 images, 64^3 grids, ray-traced) on
one GPU machine (issue 38)."""


def parse_case(text: str) -> tuple[int, int, int | None]:
    """``"256x64"`` -> (image size 256, grid 64, None); ``"256x64:512"`` also fixes the sample count."""
    m = re.fullmatch(r"(\d+)x(\d+)(?::(\d+))?", text.strip())
    if not m:
        raise SystemExit(f"bench_sim: a case is SxG or SxG:N, e.g. 256x64 or 256x64:512, got {text!r}")
    return int(m.group(1)), int(m.group(2)), int(m.group(3)) if m.group(3) else None


def make_config(image: int, grid: int, samples: int, shard_size: int, augment: bool = True, camera: str = "robot",
                renderer: str = "pyrender", world: str = "flat", rays: str = "", per_room: int = 0) -> Any:
    """The generator settings of a case: the default grid geometry at ``grid^3``, ``image^2`` pixels, the cameras
    named ``camera`` (``fruxel.train.sim.cameras.CAMERAS``), drawn by ``renderer`` in ``world`` (the home world's
    classes, :data:`fruxel.classes.HOME_CLASSES`); ``rays`` ``"spp/edge/ao"`` sets the ray tracer's camera, edge
    and occlusion rays (``""``: its defaults); ``per_room`` samples are made in each room (0: the default)."""
    import dataclasses

    from fruxel.classes import DEFAULT_CLASSES, HOME_CLASSES
    from fruxel.grid import FruxelGrid
    from fruxel.train.sim.cameras import camera_named
    from fruxel.train.sim.config import AugmentConfig, ImageConfig, SimConfig
    from fruxel.train.sim.raytrace import RaytraceConfig

    counts = dict(zip(("samples_per_pixel", "edge_samples", "ao_samples"), map(int, rays.split("/")), strict=True)
                  ) if rays else {}
    return SimConfig(grid=FruxelGrid(grid, grid, grid, 0.5, 8.0, 60.0),
                     image=ImageConfig(size=image, augment=AugmentConfig(enabled=augment)),
                     shard_size=shard_size, splits=(("train", samples),), camera=camera_named(camera),
                     renderer=renderer, world=world, classes=HOME_CLASSES if world == "home" else DEFAULT_CLASSES,
                     raytrace=dataclasses.replace(RaytraceConfig(), **counts),
                     **({"samples_per_scene": per_room} if per_room else {}))


# ---------------------------------------------------------------------------------------------------- measuring
def bench_generate(image: int, grid: int, samples: int, workers: int, shard_size: int, backend: str | None,
                   device: str | None, **variant: Any) -> dict[str, Any]:
    """Time ``generate`` of ``samples`` samples with ``workers`` processes."""
    from fruxel.train.sim.writer import generate

    cfg = make_config(image, grid, samples, shard_size, **variant)
    marks: list[tuple[float, int]] = []
    with tempfile.TemporaryDirectory(prefix="bench_sim_") as out:
        t0 = time.perf_counter()
        generate(out, cfg, 0, workers=workers, backend=backend, device=device, progress=False,
                 callback=lambda done, total: marks.append((time.perf_counter(), done)))
        wall = time.perf_counter() - t0
        size = sum(os.path.getsize(os.path.join(out, f)) for f in os.listdir(out))
    return {"mode": "generate", **_rates(marks, t0, wall, samples, workers, workers),
            "bytes_per_sample": size / samples}


def bench_streaming(image: int, grid: int, samples: int, workers: int, batch: int, device: str | None,
                    **variant: Any) -> dict[str, Any]:
    """Time the engine's stream of ``samples`` simulated samples (``batch`` a batch; ``samples`` a multiple of
    it) with ``workers`` DataLoader workers."""
    from fruxel.train.samples import Batches, BlockPlan, BlockStream

    cfg = make_config(image, grid, samples, 64, **variant)
    plan = BlockPlan(0, samples, cfg.samples_per_scene, None)
    blocks = -(-samples // cfg.samples_per_scene)

    def stream(block: int, skip: int) -> BlockStream:
        return BlockStream(plan, "stream", "train", sim_config=cfg, seed=0, first_block=block, skip=skip,
                           device=device, stop_block=blocks)

    marks: list[tuple[float, int]] = []
    t0 = time.perf_counter()
    done = 0
    batches = Batches(stream, batch, workers)
    try:
        while done < samples:
            done += int(next(batches)["index"].shape[0])
            marks.append((time.perf_counter(), done))
    finally:
        batches.close()
    wall = time.perf_counter() - t0
    # Samples come a room (block) at a time from each worker: steady once every worker has delivered one.
    need = max(1, workers) * cfg.samples_per_scene
    return {"mode": "streaming", "batch": batch, **_rates(marks, t0, wall, samples, workers, need)}


def _rates(marks: list[tuple[float, int]], t0: float, wall: float, samples: int, workers: int,
           need: int) -> dict[str, Any]:
    """Steady rate from the first mark with ``need`` samples done (every worker has delivered once), end-to-end
    rate from t0."""
    need = max(1, need)
    start = next(((t, n) for t, n in marks if n >= need), marks[0] if marks else (t0, 0))
    end = marks[-1] if marks else (t0 + wall, samples)
    steady = (end[1] - start[1]) / (end[0] - start[0]) if end[0] > start[0] and end[1] > start[1] else float("nan")
    return {"workers": workers, "samples": samples, "wall_s": round(wall, 3), "steady_sps": round(steady, 2),
            "end_to_end_sps": round(samples / wall, 2), "startup_s": round(start[0] - t0, 2)}


def bench_profile(image: int, grid: int, samples: int, backend: str | None, device: str | None,
                  **variant: Any) -> dict[str, Any]:
    """Seconds per stage in one process, after one warm-up room; plus encoding one shard of the samples."""
    from fruxel.train.sim.sample import STAGES, SampleMaker
    from fruxel.train.sim.shards import ShardSpec, encode_shard

    first = variant.get("per_room") or cfg_sps()  # the warm-up room's samples
    cfg = make_config(image, grid, samples + first, samples + first, **variant)
    sps = cfg.samples_per_scene
    with SampleMaker(cfg, 0, backend=backend, device=device) as maker:
        for i in range(sps):
            maker.make("train", i)
        maker.timings = dict.fromkeys(STAGES, 0.0)
        t0 = time.perf_counter()
        made = [maker.make("train", i) for i in range(sps, sps + samples)]
        total = time.perf_counter() - t0
        timings = dict(maker.timings)
    t1 = time.perf_counter()
    data = encode_shard(ShardSpec("train", 1, sps, samples), cfg, 0, made)
    encode = time.perf_counter() - t1
    ms = {k: round(v / samples * 1000, 2) for k, v in timings.items()}
    ms["encode"] = round(encode / samples * 1000, 2)
    ms["total_make"] = round(total / samples * 1000, 2)
    return {"mode": "profile", "samples": samples, "ms_per_sample": ms, "bytes_per_sample": len(data) / samples,
            "sps_one_process": round(samples / (total + encode), 2)}


def cfg_sps() -> int:
    """Samples per room of the default settings (the profile skips the first room as warm-up)."""
    from fruxel.train.sim.config import SimConfig

    return SimConfig().samples_per_scene


# ---------------------------------------------------------------------------------------------------- machine
def machine() -> dict[str, Any]:
    """CPU model and cores, GPU (nvidia-smi), OpenGL renderer, library versions, load average."""
    m = common.machine_info({"numpy": "numpy", "torch": "torch", "warp": "warp-lang", "pyrender": "pyrender",
                             "trimesh": "trimesh"})
    return {"cpu": f"{m['cpu']}, {m['cores']} cores", "gpu": m["gpu"] or "", "gl": gl_renderer(),
            "python": m["python"], "load_before": m["load_average"], **m["versions"]}


def gl_renderer() -> str:
    """The OpenGL renderer string of an offscreen (EGL) context, e.g. ``llvmpipe (LLVM 15.0.7, 256 bits)``."""
    code = ("from fruxel.render.compat import prepare_pyrender; prepare_pyrender(True); import pyrender; "
            "s = pyrender.Scene(); s.add(pyrender.PerspectiveCamera(yfov=1.0)); "
            "r = pyrender.OffscreenRenderer(8, 8); r.render(s); "
            "from OpenGL.GL import glGetString, GL_RENDERER; print(glGetString(GL_RENDERER).decode()); r.delete()")
    try:
        out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
        return out.stdout.strip().splitlines()[-1] if out.stdout.strip() else f"unknown ({out.stderr.strip()[-200:]})"
    except (OSError, subprocess.TimeoutExpired) as e:
        return f"unknown ({e})"


# ---------------------------------------------------------------------------------------------------- report
def _image(r: dict[str, Any]) -> str:
    """A result's image column: ``S^2``, with its cameras when they are not the robot's."""
    camera = r.get("camera", "robot")
    return f"{r['image']}^2" + ("" if camera == "robot" else f", {camera} camera")


def _target(run: dict[str, Any], r: dict[str, Any]) -> float | None:
    """The samples/s asked of result ``r`` of ``run``, or None: the robot camera's targets by machine tag and case
    (the default variant only), the furnished world's on any GPU machine."""
    case, camera = f"{r['image']}x{r['grid']}", r.get("camera", "robot")
    if (r["mode"], case, camera, r.get("world"), r.get("renderer")) == ("streaming", "256x64", "any", "home",
                                                                          "raytrace"):
        return HOME_TARGET if run["machine"].get("gpu") else None
    plain = all(r.get(k, v) == v for k, v in VARIANT_DEFAULTS.items())
    if not plain or r["mode"] not in TARGET_MODES.get(run["tag"], ()):
        return None
    return TARGETS.get((run["tag"], case))


def load_results() -> list[dict[str, Any]]:
    """Every ``benchmarks/results/sim-*.json``, CPU first."""
    runs = [json.loads(p.read_text()) for p in sorted(common.RESULTS.glob("sim-*.json"))]
    return sorted(runs, key=lambda r: (r["tag"] != "cpu", r["tag"]))


def section(runs: list[dict[str, Any]]) -> str:
    """The "## Simulator" Markdown section."""
    lines = [SECTION, ""]
    lines.append("`python benchmarks/bench_sim.py` (see its docstring for the H100 command). A sample is made end "
                 "to end: room, robot trajectory, mesh upload (once per room, shared by its samples: 16 unless the "
                 "mode says how many a room), the image (pyrender unless the mode names another renderer) with "
                 "augmentation, `fruxelize`; `generate` also compresses and writes the shards. "
                 "*Steady* excludes start-up (process spawn, imports, EGL and Warp initialisation); *end to end* "
                 f"includes it. The furnished world's stream from any camera is held to {HOME_TARGET:g} samples/s on "
                 "one GPU machine (issue 38); where its time goes: docs/experiments.md, the 'Simulator speed' "
                 "entries.")
    lines.append("")
    for run in runs:
        m = run["machine"]
        gpu = f", {m['gpu']}" if m.get("gpu") else ""
        lines.append(f"- **{run['tag']}**: {m['cpu']}{gpu}; OpenGL: {m['gl']}; run {run['date']}; Python "
                     f"{m['python']}, torch {m.get('torch')}, Warp {m.get('warp')}; load average before the run "
                     f"{m.get('load_before', float('nan')):.2f}.")
    lines += ["", "| machine | mode | image | grid | workers | samples | steady samples/s | end-to-end samples/s | "
              "target | met |", "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
    for run in runs:
        for r in run["results"]:
            if r["mode"] == "profile":
                continue
            target = _target(run, r)
            met = "" if target is None else ("yes" if r["steady_sps"] >= target else "**no**")
            extra = ", ".join(("rays " if k == "rays" else "") + str(r[k]) + (" a room" if k == "per_room" else "")
                              for k in ("world", "renderer", "rays", "per_room")
                              if r.get(k, VARIANT_DEFAULTS[k]) != VARIANT_DEFAULTS[k])
            mode = r["mode"] + (f" ({extra})" if extra else "")
            lines.append(f"| {run['tag']} | {mode} | {_image(r)} | {r['grid']}^3 | {r['workers']} | "
                         f"{r['samples']} | {r['steady_sps']:.1f} | {r['end_to_end_sps']:.1f} | "
                         f"{'' if target is None else f'>= {target:g}'} | {met} |")
    profiles = [(run["tag"], r) for run in runs for r in run["results"] if r["mode"] == "profile"]
    if profiles:
        stages = ["scene", "trajectory", "upload", "render", "fruxelize", "own_view", "encode"]
        lines += ["", "Milliseconds per sample and stage, one process (`--mode profile`; scene, trajectory and "
                  "upload are per room, shared by its 16 samples; own_view: the own-view images that samples made "
                  "before format version 2 carried, - where a run had no such stage):", "",
                  "| machine | image | grid | " + " | ".join(stages) + " | samples/s | KiB/sample |",
                  "| --- | ---: | ---: | " + " | ".join("---:" for _ in stages) + " | ---: | ---: |"]
        for tag, r in profiles:
            ms = r["ms_per_sample"]
            lines.append(f"| {tag} | {_image(r)} | {r['grid']}^3 | "
                         + " | ".join(f"{ms[s]:.1f}" if s in ms else "-" for s in stages)
                         + f" | {r['sps_one_process']:.1f} | {r['bytes_per_sample'] / 1024:.0f} |")
    notes = [n for run in runs for n in run.get("notes", [])]
    if notes:
        lines += [""] + [f"- {n}" for n in notes]
    lines += ["", "![simulator benchmark](benchmarks/results/sim.png)", ""]
    return "\n".join(lines)


def chart(runs: list[dict[str, Any]], path: Path = CHART) -> None:
    """Bars of steady samples/s per machine, mode and case, with the targets as ticks."""
    plt = common.pyplot()
    bars = [(f"{run['tag']} {r['mode']}\n{_image(r)}/{r['grid']}^3 x{r['workers']}", r["steady_sps"],
             _target(run, r))
            for run in runs for r in run["results"] if r["mode"] != "profile"]
    if not bars:
        return
    fig, ax = plt.subplots(figsize=(max(5.0, 1.0 * len(bars)), 5.0))
    xs = range(len(bars))
    ax.bar(xs, [b[1] for b in bars], color="#4e79a7")
    for x, (_, v, target) in zip(xs, bars, strict=True):
        ax.text(x, v, f"{v:.1f}", ha="center", va="bottom", fontsize=8)
        if target is not None:
            ax.plot([x - 0.4, x + 0.4], [target, target], color="#e15759", lw=2)
    ax.set_xticks(list(xs), [b[0] for b in bars], fontsize=7, rotation=30, ha="right")  # long machine tags
    ax.set_yscale("log")
    ax.set_ylabel("samples / s (steady)")
    ax.set_title("fruxel-sim throughput (red: target)")
    common.save_figure(fig, path, dpi=110)


# ---------------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tag", default="cpu", help="machine tag of the results file sim-TAG.json (default cpu)")
    p.add_argument("--mode", default="generate,profile", help="comma-separated: generate, streaming, profile")
    p.add_argument("--cases", default="256x64,512x128",
                   help="comma-separated SxG or SxG:N (image S^2, grid G^3, N samples)")
    p.add_argument("--workers", type=int, default=2, help="processes for generate / DataLoader workers (default 2)")
    p.add_argument("--seconds", type=float, default=40.0,
                   help="aim for about this long per case and mode (sets the sample count; default 40)")
    p.add_argument("--samples", type=int, default=None, help="fixed sample count instead of --seconds")
    p.add_argument("--backend", default="warp", help="fruxelize backend of generate and profile (default warp; "
                   "streaming uses the engine's, warp)")
    p.add_argument("--device", default=None, help="Warp device (default: CUDA when present, else CPU)")
    p.add_argument("--renderer", default="pyrender", help="the renderer of the images (default pyrender; raytrace: "
                   "the ray-traced one)")
    p.add_argument("--world", default="flat", choices=("flat", "home"),
                   help="the rooms: the flat world (default) or the furnished home world (needs the asset pack)")
    p.add_argument("--note", action="append", default=[], help="a note to print under the table (repeatable)")
    p.add_argument("--no-write", action="store_true", help="write the JSON only, not BENCHMARKS.md or the chart")
    p.add_argument("--report", action="store_true", help="only rebuild the section and chart from the JSON files")
    p.add_argument("--json", default=None, help="also copy the JSON here (e.g. $OUT/sim-h100.json)")
    p.add_argument("--camera", default="robot", choices=("robot", "any"),
                   help="the cameras of the samples: the robot's own mount (default) or any camera")
    p.add_argument("--rays", default="", metavar="SPP/EDGE/AO",
                   help="the ray tracer's camera rays per pixel, extra rays on edges and occlusion rays, e.g. 1/3/2 "
                        "(default: RaytraceConfig's; benchmarks/bench_raytrace_samples.py says what they cost)")
    p.add_argument("--samples-per-room", type=int, default=0, metavar="N",
                   help="samples made in each room, 1-256 (default: the simulator's, SimConfig.samples_per_scene)")
    args = p.parse_args(argv)
    if not 0 <= args.samples_per_room <= 256:
        p.error(f"--samples-per-room wants 1 to 256, got {args.samples_per_room}")
    if args.rays and (len(args.rays.split("/")) != 3 or not all(v.isdigit() for v in args.rays.split("/"))):
        p.error(f"--rays wants SPP/EDGE/AO, e.g. 1/3/2; got {args.rays!r}")
    if args.report:
        runs = load_results()
        common.replace_section(common.BENCHMARKS_MD, SECTION, section(runs))
        chart(runs)
        print(section(runs))
        return
    modes = [m.strip() for m in args.mode.split(",") if m.strip()]
    variant = {"camera": args.camera, "renderer": args.renderer, "world": args.world, "rays": args.rays,
               "per_room": args.samples_per_room}
    info = machine()
    results: list[dict[str, Any]] = []
    guess = {64: 12.0, 128: 3.0}
    for case in args.cases.split(","):
        image, grid, fixed = parse_case(case)
        rate = guess.get(grid, 4.0) * max(1, args.workers) / 2
        n = fixed or args.samples or max(32, int(rate * args.seconds) // 16 * 16)
        for mode in modes:
            print(f"bench_sim: {args.tag} {mode} {image}^2 / {grid}^3 ...", file=sys.stderr, flush=True)
            if mode == "generate":
                shard = max(16, min(64, n // (2 * max(1, args.workers)) // 16 * 16))
                r = bench_generate(image, grid, n, args.workers, shard, args.backend, args.device, **variant)
            elif mode == "streaming":
                r = bench_streaming(image, grid, n // 8 * 8, args.workers, 8, args.device, **variant)
            elif mode == "profile":
                r = bench_profile(image, grid, min(n, 64), args.backend, args.device, **variant)
            else:
                raise SystemExit(f"bench_sim: unknown mode {mode!r}")
            r.update(image=image, grid=grid, **{k: v for k, v in variant.items() if v != VARIANT_DEFAULTS[k]})
            results.append(r)
            print(json.dumps(r), flush=True)
    run = {"tag": args.tag, "date": dt.date.today().isoformat(), "machine": info, "results": results,
           "notes": args.note}
    common.RESULTS.mkdir(parents=True, exist_ok=True)
    text = json.dumps(run, indent=1) + "\n"
    common.write_text(common.RESULTS / f"sim-{args.tag}.json", text)
    if args.json:
        common.write_text(Path(args.json), text)
    print(section([run]))
    if not args.no_write:
        runs = load_results()
        common.replace_section(common.BENCHMARKS_MD, SECTION, section(runs))
        chart(runs)


if __name__ == "__main__":
    main()

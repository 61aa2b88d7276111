"""Ray-traced renderer benchmark: milliseconds per room and per image of the ``"raytrace"`` renderer, by stage, and
images per second from several processes sharing the device.

Rooms: the old flat rooms (``make_scene`` with a ceiling) dressed with the asset pack's textures, glass, outdoor
views and soft lights by :mod:`fruxel.train.sim.raytrace.dressing` (a stand-in until the room generator assigns
materials), seen from the robot's trajectory. Settings: ``RaytraceConfig()`` defaults unless ``--spp`` /
``--shadow-samples`` / ``--ao-samples`` say otherwise; every image takes a camera response drawn from its sample's
generator.

Modes (``--mode``, comma-separated):

* ``profile`` — one process, the renderer's ``profile`` switch on (the device synchronised after every stage):
  per room ``arrays`` (the room flattened on the host), ``textures`` (pack textures decoded and uploaded, only the
  first time a process meets them), ``bvh``, ``upload`` (materials, lights, smoothed normals) and ``ambient``
  (probe rays, window panes); per image ``primary`` (camera rays, textures), ``lights`` (shadow rays), ``occlusion``,
  ``resolve`` (the lighting filter) and ``response`` (camera response, download, JPEG); ``occlusion`` holds the
  ambient-occlusion and the window rays (:mod:`fruxel.train.sim.raytrace.occlusion`). The first room is a
  warm-up (kernel loading); textures are counted from the second.
* ``throughput`` — ``--processes`` spawned processes, each rendering its own rooms (16 images a room, as the
  simulator's samples) without profiling for ``--seconds``: images per second of all together, the rate the
  renderer allows a data stream whose workers share one device.

    python benchmarks/bench_render.py                                   # this machine: writes render-cpu.json
    python benchmarks/bench_render.py --tag h100 --mode profile,throughput --processes 1,4,16 --no-write
    python benchmarks/bench_render.py --report                          # the section from every render-*.json

Results go to ``benchmarks/results/render-{tag}.json``; unless ``--no-write``, the "## Ray-traced renderer"
section of BENCHMARKS.md is rebuilt from all ``render-*.json`` files there. Target (issue 38): the stream of 256^2
samples at 600 per second on the H100 machine while training, so rendering must take well under 1/600 s of the
GPU per image and little of the 16 cores.
"""

from __future__ import annotations

import argparse
import datetime as dt
import json
import multiprocessing as mp
import sys
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

SECTION = "## Ray-traced renderer"
ROOM_STAGES = ("arrays", "textures", "bvh", "upload", "ambient")
IMAGE_STAGES = ("primary", "lights", "occlusion", "resolve", "response")
FRAMES = 16
"""Images per room (the simulator's samples per room)."""


def make_config(size: int, pack: str, spp: int | None, shadow: int | None, ao: int | None) -> Any:
    """The simulator config of a run: 64^3 grid of the default geometry, ``size^2`` images, ceilings."""
    import dataclasses

    from fruxel.grid import FruxelGrid
    from fruxel.train.sim.config import ImageConfig, SimConfig
    from fruxel.train.sim.raytrace import RaytraceConfig
    from fruxel.train.sim.scene import RoomConfig

    changes = {k: v for k, v in (("samples_per_pixel", spp), ("shadow_samples", shadow), ("ao_samples", ao))
               if v is not None}
    rt = dataclasses.replace(RaytraceConfig(), **changes)
    return SimConfig(grid=FruxelGrid(64, 64, 64, 0.5, 8.0, 60.0), image=ImageConfig(size=size), renderer="raytrace",
                     room=RoomConfig(ceiling=True), assets=pack, raytrace=rt)


def rooms(config: Any, first: int, count: int) -> list[tuple[Any, Any]]:
    """``count`` dressed rooms from seed ``first`` on, each with its trajectory's ``FRAMES`` poses."""
    from fruxel.train.sim.raytrace.dressing import dress_scene
    from fruxel.train.sim.raytrace.renderer import open_pack
    from fruxel.train.sim.robot import TrajectoryError, random_trajectory
    from fruxel.train.sim.scene import make_scene

    pack = open_pack(config.assets)
    out, seed = [], first
    while len(out) < count:
        scene = dress_scene(make_scene(seed, config.room, config.classes), pack, seed)
        try:
            poses = random_trajectory(scene, FRAMES, seed, **config.trajectory.kwargs()).poses
        except TrajectoryError:
            seed += 1
            continue
        out.append((scene, poses))
        seed += 1
    return out


# ---------------------------------------------------------------------------------------------------- measuring
def bench_profile(config: Any, n_rooms: int, device: str | None) -> dict[str, Any]:
    """Per-stage milliseconds per room and per image in one process (see the module docstring)."""
    import numpy as np

    from fruxel.train.sim.raytrace.renderer import STAGES, RaytraceRenderer

    todo = rooms(config, 0, n_rooms + 1)
    r = RaytraceRenderer(config, device=device)
    r.profile = True
    warm_scene, warm_poses = todo[0]
    r.set_scene(warm_scene)
    r.render(warm_poses[0], np.random.default_rng(0))
    r.timings = dict.fromkeys(STAGES, 0.0)
    images, faces, lights = 0, [], []
    t0 = time.perf_counter()
    for k, (scene, poses) in enumerate(todo[1:]):
        r.set_scene(scene)
        faces.append(sum(len(o.mesh.faces) for o in scene.objects))
        lights.append(len(scene.lights))
        for f, pose in enumerate(poses):
            r.render(pose, np.random.default_rng([k, f]))
            images += 1
    wall = time.perf_counter() - t0
    ms_room = {s: round(r.timings[s] / n_rooms * 1e3, 2) for s in ROOM_STAGES}
    ms_image = {s: round(r.timings[s] / images * 1e3, 2) for s in IMAGE_STAGES}
    ms_image["total"] = round(sum(r.timings[s] for s in IMAGE_STAGES) / images * 1e3, 2)
    return {"mode": "profile", "device": r.device, "rooms": n_rooms, "images": images,
            "ms_per_room": ms_room, "ms_per_image": ms_image, "wall_s": round(wall, 2),
            "faces_per_room": round(float(np.mean(faces))), "lights_per_room": round(float(np.mean(lights)), 1)}


def _worker(args: tuple[Any, int, float, str | None, Any]) -> tuple[int, float, float]:
    """One process of ``throughput``: (images, seconds, seconds of start-up) after rendering for ``seconds``."""
    import numpy as np

    from fruxel.train.sim.raytrace.renderer import RaytraceRenderer

    config, index, seconds, device, start = args
    t_start = time.perf_counter()
    r = RaytraceRenderer(config, device=device)
    first = 1000 + 97 * index
    warm = rooms(config, first, 1)[0]
    r.set_scene(warm[0])
    r.render(warm[1][0], np.random.default_rng(0))
    ready = time.perf_counter() - t_start
    start.wait()
    t0 = time.perf_counter()
    images, k = 0, 0
    while time.perf_counter() - t0 < seconds:
        scene, poses = rooms(config, first + 1 + k, 1)[0]
        r.set_scene(scene)
        for f, pose in enumerate(poses):
            r.render(pose, np.random.default_rng([index, k, f]))
            images += 1
        k += 1
    return images, time.perf_counter() - t0, ready


def bench_throughput(config: Any, processes: int, seconds: float, device: str | None) -> dict[str, Any]:
    """Images per second of ``processes`` spawned processes rendering at once (room making included)."""
    ctx = mp.get_context("spawn")
    with ctx.Manager() as manager:
        start = manager.Barrier(processes)
        with ctx.Pool(processes) as pool:
            got = pool.map(_worker, [(config, i, seconds, device, start) for i in range(processes)])
    images = sum(g[0] for g in got)
    wall = max(g[1] for g in got)
    return {"mode": "throughput", "processes": processes, "images": images, "seconds": round(wall, 2),
            "images_per_s": round(images / wall, 2), "startup_s": round(max(g[2] for g in got), 2)}


# ---------------------------------------------------------------------------------------------------- report
def load_results() -> list[dict[str, Any]]:
    """Every ``benchmarks/results/render-*.json``, CPU first."""
    runs = [json.loads(p.read_text()) for p in sorted(common.RESULTS.glob("render-*.json"))]
    return sorted(runs, key=lambda r: (r["tag"] != "cpu", r["tag"]))


def section(runs: list[dict[str, Any]]) -> str:
    """The "## Ray-traced renderer" Markdown section."""
    lines = [SECTION, "",
             "`python benchmarks/bench_render.py` (see its docstring for the H100 command): the `raytrace` renderer "
             "on flat rooms dressed with the asset pack (textures, glass, outdoor views, 1 sun and 1-3 lamps), "
             f"{FRAMES} images per room from the robot's trajectory, each with its camera response.", ""]
    for run in runs:
        m = run["machine"]
        gpu = f", {m['gpu']}" if m.get("gpu") else ""
        lines.append(f"- **{run['tag']}**: {m['cpu']}{gpu}; run {run['date']}; Python {m['python']}, Warp "
                     f"{m.get('warp')}; load average before the run {m.get('load_before', float('nan')):.2f}; "
                     f"settings {run['settings']}.")
    lines += ["", "Milliseconds per image by stage (`--mode profile`, the device synchronised after each stage; "
              "occlusion: the ambient-occlusion and window rays):", "",
              "| machine | device | image | " + " | ".join(IMAGE_STAGES) + " | total | images/s (one process) |",
              "| --- | --- | ---: | " + " | ".join("---:" for _ in IMAGE_STAGES) + " | ---: | ---: |"]
    profiles = [(run, r) for run in runs for r in run["results"] if r["mode"] == "profile"]
    for run, r in profiles:
        ms = r["ms_per_image"]
        lines.append(f"| {run['tag']} | {r['device']} | {r['image']}^2 | "
                     + " | ".join(f"{ms[s]:.1f}" for s in IMAGE_STAGES)
                     + f" | {ms['total']:.1f} | {1000.0 / ms['total']:.1f} |")
    lines += ["", f"Milliseconds per room (shared by its {FRAMES} images; textures: decoding and uploading the pack's "
              "textures the first time a process meets them):", "",
              "| machine | device | image | faces | lights | " + " | ".join(ROOM_STAGES) + " |",
              "| --- | --- | ---: | ---: | ---: | " + " | ".join("---:" for _ in ROOM_STAGES) + " |"]
    for run, r in profiles:
        ms = r["ms_per_room"]
        lines.append(f"| {run['tag']} | {r['device']} | {r['image']}^2 | {r['faces_per_room']} | "
                     f"{r['lights_per_room']} | " + " | ".join(f"{ms[s]:.1f}" for s in ROOM_STAGES) + " |")
    rates = [(run, r) for run in runs for r in run["results"] if r["mode"] == "throughput"]
    if rates:
        lines += ["", "Images per second of several processes rendering at once on one device (`--mode throughput`: "
                  "rooms made, dressed and uploaded in each process; no profiling):", "",
                  "| machine | image | processes | images | seconds | images/s |",
                  "| --- | ---: | ---: | ---: | ---: | ---: |"]
        for run, r in rates:
            lines.append(f"| {run['tag']} | {r['image']}^2 | {r['processes']} | {r['images']} | {r['seconds']:.1f} | "
                         f"{r['images_per_s']:.1f} |")
    notes = [n for run in runs for n in run.get("notes", [])]
    if notes:
        lines += [""] + [f"- {n}" for n in notes]
    lines.append("")
    return "\n".join(lines)


# ---------------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--tag", default="cpu", help="machine tag of the results file render-TAG.json (default cpu)")
    p.add_argument("--mode", default="profile,throughput", help="comma-separated: profile, throughput")
    p.add_argument("--sizes", default="256", help="comma-separated image sizes S (S^2 pixels; default 256)")
    p.add_argument("--rooms", type=int, default=4, help="rooms of the profile, after one warm-up (default 4)")
    p.add_argument("--processes", default="2", help="comma-separated process counts of throughput (default 2)")
    p.add_argument("--seconds", type=float, default=30.0, help="seconds of each throughput run (default 30)")
    p.add_argument("--pack", default="assets/pack", help="the asset pack (default assets/pack; `make assets`)")
    p.add_argument("--spp", type=int, default=None, help="samples per pixel (default: RaytraceConfig's)")
    p.add_argument("--shadow-samples", type=int, default=None, help="shadow rays per light and sample")
    p.add_argument("--ao-samples", type=int, default=None, help="occlusion rays per sample")
    p.add_argument("--device", default=None, help="Warp device (default: CUDA when present, else CPU)")
    p.add_argument("--note", action="append", default=[], help="a note to print under the tables (repeatable)")
    p.add_argument("--no-write", action="store_true", help="write the JSON only, not BENCHMARKS.md")
    p.add_argument("--report", action="store_true", help="only rebuild the section from the JSON files")
    p.add_argument("--json", default=None, help="also copy the JSON here (e.g. $OUT/render-h100.json)")
    args = p.parse_args(argv)
    if args.report:
        common.replace_section(common.BENCHMARKS_MD, SECTION, section(load_results()))
        return
    if not (Path(args.pack) / "manifest.json").is_file():
        raise SystemExit(f"bench_render: {args.pack}: no asset pack there (build one with `make assets`)")
    info = common.machine_info({"numpy": "numpy", "warp": "warp-lang"})
    machine = {"cpu": f"{info['cpu']}, {info['cores']} cores", "gpu": info["gpu"] or "", "python": info["python"],
               "load_before": info["load_average"], **info["versions"]}
    results: list[dict[str, Any]] = []
    modes = [m.strip() for m in args.mode.split(",") if m.strip()]
    settings = ""
    for size in (int(s) for s in args.sizes.split(",")):
        config = make_config(size, args.pack, args.spp, args.shadow_samples, args.ao_samples)
        rt = config.raytrace
        settings = (f"{rt.samples_per_pixel} camera rays per pixel (+{rt.edge_samples} on edges), "
                    f"{rt.shadow_samples} shadow ray(s) per light, {rt.ao_samples} occlusion and "
                    f"{rt.window_samples} window ray(s) per camera ray, filter radius {rt.denoise_radius}")
        for mode in modes:
            if mode == "profile":
                print(f"bench_render: {args.tag} profile {size}^2 ...", file=sys.stderr, flush=True)
                r = bench_profile(config, args.rooms, args.device)
                r["image"] = size
                results.append(r)
                print(json.dumps(r), flush=True)
            elif mode == "throughput":
                for n in (int(k) for k in args.processes.split(",")):
                    print(f"bench_render: {args.tag} throughput {size}^2 x{n} ...", file=sys.stderr, flush=True)
                    r = bench_throughput(config, n, args.seconds, args.device)
                    r["image"] = size
                    results.append(r)
                    print(json.dumps(r), flush=True)
            else:
                raise SystemExit(f"bench_render: unknown mode {mode!r}")
    run = {"tag": args.tag, "date": dt.date.today().isoformat(), "machine": machine, "settings": settings,
           "results": results, "notes": args.note}
    common.RESULTS.mkdir(parents=True, exist_ok=True)
    text = json.dumps(run, indent=1) + "\n"
    common.write_text(common.RESULTS / f"render-{args.tag}.json", text)
    if args.json:
        common.write_text(Path(args.json), text)
    print(section([run]))
    if not args.no_write:
        common.replace_section(common.BENCHMARKS_MD, SECTION, section(load_results()))


if __name__ == "__main__":
    main()

"""Ray-tracer sample counts: what each setting of camera and occlusion rays costs, and how far its images are from
a converged reference.

The renderer's cost per image grows with its camera rays per pixel (``samples_per_pixel``, plus ``edge_samples``
where a pixel is on an edge) and the rays each camera ray sends (shadow, occlusion, window rays:
``fruxel.train.sim.raytrace.RaytraceConfig``). For each setting ``spp/edge/ao`` of ``--settings`` and the
reference setting (8/8/8), on the furnished rooms from any camera (the simulator's own rooms and poses), in rounds
that alternate the settings' order per room: ``--images`` images of each room with the renderer's profile on
(the device synchronised after each stage), each image with the same camera response as the reference's. Reported
per setting: the median over rooms of milliseconds per image (tracing, filter and response stages), that time over
the first setting's, and the median PSNR (dB, 8-bit RGB) of its images against the reference's images. A sheet
(``raytrace-samples-{tag}.png``) shows the middle of each image at full resolution, one column per setting (the
reference last).

    python benchmarks/bench_raytrace_samples.py                       # this machine's CPU device
    python benchmarks/bench_raytrace_samples.py --device cuda:0 --tag h200 --no-write --json $OUT/rs.json
    python benchmarks/bench_raytrace_samples.py --report              # the section from the stored results

Results go to ``benchmarks/results/raytrace-samples-{tag}.json``; unless ``--no-write``, the "## Ray-tracer sample
counts" section of BENCHMARKS.md is rebuilt from every ``raytrace-samples-*.json`` there.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

SECTION = "## Ray-tracer sample counts"
STAGES = ("primary", "lights", "occlusion", "resolve", "response")
"""The renderer's per-image stages (``fruxel.train.sim.raytrace.renderer.STAGES``)."""
REFERENCE = (8, 8, 8)
"""The converged stand-in: 8 camera rays per pixel (+8 on edges), 8 occlusion rays each."""


def parse_settings(text: str) -> list[tuple[int, int, int]]:
    """``"2/2/2,1/3/2"`` -> ``[(2, 2, 2), (1, 3, 2)]`` (camera rays, edge rays, occlusion rays)."""
    try:
        out = [tuple(int(v) for v in s.split("/")) for s in text.split(",")]
    except ValueError:
        out = []
    if not out or any(len(s) != 3 for s in out):
        raise SystemExit(f"bench_raytrace_samples: --settings wants spp/edge/ao[,spp/edge/ao...], got {text!r}")
    return out  # type: ignore[return-value]


def measure(device: str, settings: list[tuple[int, int, int]], rooms: int, images: int,
            size: int) -> tuple[list[dict[str, Any]], Any]:
    """Per setting: median ms per image over rooms and median PSNR against :data:`REFERENCE`; and the sheet."""
    import dataclasses

    import numpy as np
    from bench_sim import make_config

    from fruxel.train.sim.config import augment_rng
    from fruxel.train.sim.raytrace.renderer import RaytraceRenderer
    from fruxel.train.sim.sample import SampleMaker

    cfg = make_config(size, 64, 16 * rooms, 64, camera="any", renderer="raytrace", world="home")
    sps = cfg.samples_per_scene
    every = [*settings, REFERENCE]
    ms: dict[tuple[int, int, int], list[float]] = {s: [] for s in every}
    shots: dict[tuple[int, int, int], list[np.ndarray]] = {s: [] for s in every}
    with SampleMaker(cfg, 0, device=device) as maker:
        for r in range(rooms):
            scene = maker.scene_of("train", r * sps)[0]
            poses = [maker.scene_of("train", r * sps + 1 + k * sps // images)[1] for k in range(images)]
            for s in (every if r % 2 == 0 else every[::-1]):
                rt = dataclasses.replace(cfg.raytrace, samples_per_pixel=s[0], edge_samples=s[1], ao_samples=s[2])
                with RaytraceRenderer(dataclasses.replace(cfg, raytrace=rt), device) as rend:
                    rend.profile = True
                    rend.set_scene(scene)
                    rend.render(poses[0], augment_rng(0, "train", 0))  # warms the kernels
                    rend.timings = dict.fromkeys(rend.timings, 0.0)
                    shots[s] += [rend.render(p, augment_rng(0, "train", r * sps + k)) for k, p in enumerate(poses)]
                    ms[s].append(sum(rend.timings[k] for k in STAGES) * 1000 / images)
    rows = []
    for s in settings:
        psnr = [10 * np.log10(255.0**2 / max(np.mean((a.astype(np.float64) - b.astype(np.float64)) ** 2), 1e-12))
                for a, b in zip(shots[s], shots[REFERENCE], strict=True)]
        rows.append({"spp": s[0], "edge": s[1], "ao": s[2], "image_ms": statistics.median(ms[s]),
                     "psnr_db": float(statistics.median(psnr)), "rooms": rooms, "images_per_room": images,
                     "image": size})
    for r in rows:
        r["ms_over_first"] = r["image_ms"] / rows[0]["image_ms"]
    c0, c1 = size // 4, size - size // 4  # the images' middle half, at full resolution: the noise shows
    sheet = np.concatenate([np.concatenate([a[c0:c1, c0:c1] for a in shots[s]], axis=0) for s in every], axis=1)
    return rows, sheet


def section(runs: list[dict[str, Any]]) -> str:
    """The "## Ray-tracer sample counts" Markdown section from stored runs."""
    lines = [SECTION, "", "`python benchmarks/bench_raytrace_samples.py` (its docstring has the GPU command): the "
             "ray tracer on the furnished rooms from any camera with fewer or more rays, settings alternated per "
             "room; medians over rooms of milliseconds per image (device synchronised after each stage) and over "
             f"images of the PSNR against {'/'.join(map(str, REFERENCE))} (camera/edge/occlusion rays), each image "
             "with its sample's camera response.", ""]
    lines += [common.device_run_line(run, f"sheet `benchmarks/results/raytrace-samples-{run['tag']}.png`")
              for run in runs]
    lines += ["", "| machine | device | image | rooms x images | camera rays | edge rays | occlusion rays | ms/image | "
              "time / first row's | PSNR vs reference (dB) |",
              "| --- | --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    for run in runs:
        for r in run["results"]:
            lines.append(f"| {run['tag']} | {run['device']} | {r['image']}^2 | {r['rooms']} x {r['images_per_room']} "
                         f"| {r['spp']} | {r['edge']} | {r['ao']} | {r['image_ms']:.1f} | {r['ms_over_first']:.2f} | "
                         f"{r['psnr_db']:.1f} |")
    return common.with_notes(lines, runs)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.add_device_run_options(p)
    p.add_argument("--settings", default="2/2/2,1/3/2,1/3/1",
                   help="comma-separated camera/edge/occlusion rays (default 2/2/2,1/3/2,1/3/1)")
    p.add_argument("--rooms", type=int, default=3)
    p.add_argument("--images", type=int, default=2, help="images per room and setting")
    p.add_argument("--image", type=int, default=256, help="image width in pixels (default 256)")
    args = p.parse_args(argv)
    run = None
    if not args.report:
        from PIL import Image

        from fruxel.io import atomic_write

        rows, sheet = measure(args.device, parse_settings(args.settings), args.rooms, args.images, args.image)
        run = common.device_run(args, rows)
        with atomic_write(common.RESULTS / f"raytrace-samples-{run['tag']}.png", "wb") as f:
            Image.fromarray(sheet).save(f, format="PNG")
    common.finish_device_run(args, run, "raytrace-samples", SECTION, section)


if __name__ == "__main__":
    main()

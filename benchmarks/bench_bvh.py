"""BVH constructor benchmark: how fast the ray tracer traces the furnished rooms with each of Warp's BVH builders.

The renderer (``fruxel.train.sim.raytrace.renderer``) puts a room's every triangle into one ``wp.Mesh``; its BVH
decides how many nodes each ray visits. Warp builds ``"sah"`` (surface area heuristic) and ``"median"`` (spatial
median of centroids) on the host, ``"lbvh"`` (Morton codes, bottom-up) on a CUDA device, whose default it is. The
furnished rooms mix wall-sized triangles with small furniture parts, where the builders differ most.

For each room (furnished, any camera, the simulator's own rooms and poses) and each constructor, in rounds that
alternate the constructors' order: the room uploaded by a fresh renderer with that constructor (its ``bvh`` stage:
build and upload), then ``--images`` images of the grid's own view traced with the renderer's profile on; reported
per constructor: milliseconds per image of the tracing stages (camera rays, lights, occlusion) and of the whole
image, the BVH build per room, and each constructor's time over SAH's.

    python benchmarks/bench_bvh.py                                    # this machine's CPU device: bvh-cpu.json
    python benchmarks/bench_bvh.py --device cuda:0 --tag h100 --no-write --json $OUT/bvh-h100.json
    python benchmarks/bench_bvh.py --report                           # the section from every bvh-*.json

Results go to ``benchmarks/results/bvh-{tag}.json``; unless ``--no-write``, the "## BVH constructors" section of
BENCHMARKS.md is rebuilt from every ``bvh-*.json`` there.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

SECTION = "## BVH constructors"
TRACE_STAGES = ("primary", "lights", "occlusion")
"""The renderer's stages that traverse the BVH (``fruxel.train.sim.raytrace.renderer.STAGES``)."""
IMAGE_STAGES = (*TRACE_STAGES, "resolve", "response")


def measure(device: str, constructors: list[str], rooms: int, images: int, size: int) -> list[dict[str, Any]]:
    """Per constructor: the median over rooms of ms per image (tracing stages, whole image) and of the build."""
    from bench_sim import make_config

    import fruxel.train.sim.raytrace.renderer as renderer_module
    from fruxel.train.sim.config import augment_rng
    from fruxel.train.sim.sample import SampleMaker

    cfg = make_config(size, 64, 16 * rooms, 64, camera="any", renderer="raytrace", world="home")
    sps = cfg.samples_per_scene
    per: dict[str, dict[str, list[float]]] = {c: {"trace": [], "image": [], "build": []} for c in constructors}
    faces: list[int] = []
    with SampleMaker(cfg, 0, device=device) as maker:
        for r in range(rooms):
            # the room and its frames' poses; drawn at the grid's own view (the tree is the same for any camera)
            scene = maker.scene_of("train", r * sps)[0]
            poses = [maker.scene_of("train", r * sps + k)[1] for k in range(min(sps, images + 1))]
            faces.append(sum(len(o.mesh.faces) for o in scene.objects))
            for ctor in (constructors if r % 2 == 0 else constructors[::-1]):
                renderer_module.BVH_CONSTRUCTOR = ctor
                with renderer_module.RaytraceRenderer(cfg, device) as rend:
                    rend.profile = True
                    rend.set_scene(scene)
                    rend.render(poses[0], augment_rng(0, "train", 0))  # warms the kernels
                    per[ctor]["build"].append(rend.timings["bvh"] * 1000)
                    rend.timings = dict.fromkeys(rend.timings, 0.0)
                    for k in range(images):
                        rend.render(poses[(1 + k) % len(poses)], augment_rng(0, "train", 1 + k))
                    per[ctor]["trace"].append(sum(rend.timings[s] for s in TRACE_STAGES) * 1000 / images)
                    per[ctor]["image"].append(sum(rend.timings[s] for s in IMAGE_STAGES) * 1000 / images)
    renderer_module.BVH_CONSTRUCTOR = "sah"
    rows = [{"constructor": c, **{f"{k}_ms": statistics.median(v) for k, v in per[c].items()}} for c in constructors]
    base = next((r for r in rows if r["constructor"] == "sah"), rows[0])
    for r in rows:
        r.update(trace_over_sah=r["trace_ms"] / base["trace_ms"], rooms=rooms, images_per_room=images, image=size,
                 median_faces=int(statistics.median(faces)))
    return rows


def section(runs: list[dict[str, Any]]) -> str:
    """The "## BVH constructors" Markdown section from stored runs."""
    lines = [SECTION, "", "`python benchmarks/bench_bvh.py` (its docstring has the GPU command): the ray tracer on "
             "the furnished rooms from any camera with each BVH constructor, rooms and constructors alternated; "
             "medians over rooms of milliseconds per image with the device synchronised after each stage.", ""]
    lines += [common.device_run_line(run) for run in runs]
    lines += ["", "| machine | device | image | rooms x images | faces (median) | constructor | tracing ms/image | "
              "image ms | build ms/room | tracing / SAH's |", "| --- | --- | ---: | ---: | ---: | --- | ---: | ---: | "
              "---: | ---: |"]
    for run in runs:
        for r in run["results"]:
            lines.append(f"| {run['tag']} | {run['device']} | {r['image']}^2 | {r['rooms']} x {r['images_per_room']}"
                         f" | {r['median_faces']} | {r['constructor']} | {r['trace_ms']:.2f} | {r['image_ms']:.2f} | "
                         f"{r['build_ms']:.1f} | {r['trace_over_sah']:.2f} |")
    return common.with_notes(lines, runs)


def main(argv: list[str] | None = None) -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    common.add_device_run_options(p)
    p.add_argument("--constructors", default=None, help="comma-separated (default: sah,median; on CUDA also lbvh)")
    p.add_argument("--rooms", type=int, default=3)
    p.add_argument("--images", type=int, default=4, help="images per room and constructor")
    p.add_argument("--image", type=int, default=128, help="image width in pixels (default 128)")
    args = p.parse_args(argv)
    run = None
    if not args.report:
        cuda = args.device.startswith("cuda")
        ctors = (args.constructors or ("sah,lbvh,median" if cuda else "sah,median")).split(",")
        run = common.device_run(args, measure(args.device, ctors, args.rooms, args.images, args.image))
    common.finish_device_run(args, run, "bvh", SECTION, section)


if __name__ == "__main__":
    main()

"""Kernel benchmark: first_hit and shell on every backend, against an Embree ray caster on the full mesh.

Model: :func:`fruxel.data.rooms.room_volume` (128^3, 25 % occupied) seen by
:func:`fruxel.data.rooms.oblique_camera` at 512^2.
Measured per backend (median of ``--repeat`` runs after one warm-up; the very first call, which compiles the
kernels or loads them from the backend's cache, is reported on its own):

* ``first_hit``: labels ``(128, 128, 128)`` uint8, one 512 x 512 oblique view;
* ``shell 6 poses``: the same volume, :func:`fruxel.kernels.orbit_cameras` (6 poses, 512 x 512);
* ``own-view shell``: ``(4, 7, 128, 128, 128)`` float32 logits from the grid's own camera (the column path);
* on CUDA only, ``first_hit`` at 256^3 @ 1024^2.

The peer, in the same run: Open3D's ``RaycastingScene`` (Embree) on the ``full`` trapezoid mesh
(:func:`fruxel.mesh.mesh_labels`), timed as BVH build + first cast (what a changing volume costs per frame),
and cast alone; the mesh build itself is timed too. Where Open3D is missing, trimesh's embreex intersector is
the peer; where neither is installed, the peer is skipped. The peer's first hits are checked against the
backends' (share of pixels with the same cell), so both sides answer the same question.

Run ``python benchmarks/bench_kernels.py`` (``--backends opencl warp-cpu``, ``--sizes 128 256``,
``--repeat N``, ``--out PREFIX``, ``--device cuda:0``, ``--no-write``). Writes ``PREFIX.json`` and
``PREFIX.png`` (default ``benchmarks/results/kernels``) and re-renders the "## Kernels" section of
BENCHMARKS.md from every ``benchmarks/results/kernels*.json``, so runs on other machines (e.g. an H100, with
``--out benchmarks/results/kernels-h100``) add their own table instead of replacing this one.

Open3D: ``pip install 'fruxel[bench]'`` (open3d 0.20; on Debian its wheel also needs ``libusb-1.0-0``).
"""

from __future__ import annotations

import argparse
import importlib
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

from fruxel.classes import DEFAULT_CLASSES  # noqa: E402
from fruxel.data import rooms  # noqa: E402
from fruxel.grid import FruxelGrid  # noqa: E402
from fruxel.kernels import available_backends, first_hit, orbit_cameras, shell  # noqa: E402
from fruxel.mesh import mesh_labels  # noqa: E402

SECTION = "## Kernels"

TARGETS = {
    ("opencl", "first_hit", 128): ("<= 20 ms", lambda ms: ms <= 20.0),
    ("warp-cpu", "first_hit", 128): ("<= 80 ms", lambda ms: ms <= 80.0),
    ("opencl", "shell 6 poses", 128): ("<= 150 ms", lambda ms: ms <= 150.0),
    ("warp-cuda", "first_hit", 128): ("<= 0.1 ms (H100)", lambda ms: ms <= 0.1),
    ("warp-cuda", "first_hit", 256): ("<= 1 ms (H100)", lambda ms: ms <= 1.0),
    ("warp-cuda", "shell 6 poses", 128): ("<= 1 ms (H100)", lambda ms: ms <= 1.0),
    ("warp-cuda", "own-view shell", 128): ("<= 1 ms (H100)", lambda ms: ms <= 1.0),
}
"""Targets from the issue, per (backend, operation, n); the warp-cuda ones are for the H100."""
SPEEDUP_TARGET = ("opencl", 150.0)
"""OpenCL first_hit at least this many times faster than the Embree peer including its BVH rebuild."""


# ---------------------------------------------------------------------------------------------- machine


def machine_info() -> dict[str, Any]:
    """CPU, cores, GPU, OpenCL device, date and package versions."""
    cl_device = None
    try:
        import pyopencl as cl

        cl_device = "; ".join(f"{p.name}: {d.name}" for p in cl.get_platforms() for d in p.get_devices())
    except Exception:  # noqa: BLE001 - no OpenCL here
        pass
    info = common.machine_info(("numpy", "warp-lang", "pyopencl", "pocl-binary-distribution", "open3d", "embreex",
                                "trimesh", "torch"))
    info["load_average_1min_at_start"] = info.pop("load_average")
    info["opencl_devices"] = cl_device
    info["cpu_id"] = common.cpu_id()
    info.update(common.opencl_device())
    return info


# ---------------------------------------------------------------------------------------------- timing


def _sync(device: str | None) -> None:
    if device and device.startswith("cuda"):
        import torch

        torch.cuda.synchronize()


def time_call(fn: Callable[[], Any], repeat: int, device: str | None = None) -> dict[str, float]:
    """First-call time, then the median (and min) of ``repeat`` calls after one warm-up, in milliseconds, each
    call synchronised. On CUDA also the time per call of back-to-back calls (``pipelined_ms``, ``host_ms``) and
    the GPU time of one call's kernels (``gpu_ms``)."""
    out = common.time_calls(fn, repeat, sync=lambda: _sync(device), warmup=1)
    if device and device.startswith("cuda"):
        out.update(common.pipelined_ms(fn, repeat, lambda: _sync(device)))
        out["gpu_ms"] = common.cuda_kernel_ms(fn)[0]
    return out


def _device_volume(volume: np.ndarray, device: str | None) -> Any:
    """The volume where the backend reads it: a CUDA tensor for CUDA devices, else the numpy array."""
    if device and device.startswith("cuda"):
        import torch

        return torch.from_numpy(volume).to(device)
    return volume


def _cells(hits: Any) -> np.ndarray:
    c = hits.cell
    return c.detach().cpu().numpy() if hasattr(c, "detach") else np.asarray(c)


def logits_batch(n: int, batch: int = 4, channels: int = 7) -> np.ndarray:
    """``(batch, channels, n, n, n)`` float32 logits whose argmax is ``room_volume(n, seed=b)`` for item b."""
    out = np.empty((batch, channels, n, n, n), np.float32)
    rng = np.random.default_rng(1)
    for b in range(batch):
        lab, _ = rooms.room_volume(n, seed=b)
        out[b] = rng.standard_normal((channels, n, n, n), dtype=np.float32)
        top = out[b].max(axis=0)
        np.put_along_axis(out[b], lab[None].astype(np.int64), (top + 2.0)[None], axis=0)
    return out


def bench_backend(name: str, labels: np.ndarray, grid: FruxelGrid, image: int, repeat: int,
                  device: str | None, logits: np.ndarray | None) -> list[dict[str, Any]]:
    """Rows for one backend and grid size: first_hit, and at 128^3 the two shells."""
    n = grid.width
    dev = device if name.startswith("warp") and device else None
    backend = "warp" if dev else name
    vol = _device_volume(labels, dev)
    cam = rooms.oblique_camera(grid, image)
    rows = []
    t = time_call(lambda: first_hit(vol, grid, cam, backend=backend, device=dev), repeat, dev)
    hits = _cells(first_hit(vol, grid, cam, backend=backend, device=dev))
    rows.append({"backend": name, "op": "first_hit", "n": n, "image": image, **t,
                 "hit_fraction": float((hits >= 0).mean())})
    if n == 128:
        cams = orbit_cameras(grid, 6, width=image, height=image)
        t = time_call(lambda: shell(vol, grid, cams, backend=backend, device=dev), max(3, repeat // 2), dev)
        rows.append({"backend": name, "op": "shell 6 poses", "n": n, "image": image, **t})
        if logits is not None:
            lv = _device_volume(logits, dev)
            own = grid.camera()
            t = time_call(lambda: shell(lv, grid, own, backend=backend, device=dev), max(3, repeat // 2), dev)
            rows.append({"backend": name, "op": "own-view shell", "n": n, "image": n,
                         "volume": list(logits.shape), **t})
    return rows


# ---------------------------------------------------------------------------------------------- peer


def _open3d() -> Any:
    try:
        return importlib.import_module("open3d")
    except Exception:  # noqa: BLE001 - missing, or its native libraries fail to load
        return None


def bench_peer(labels: np.ndarray, grid: FruxelGrid, image: int, repeat: int,
               reference_cells: np.ndarray | None) -> dict[str, Any] | None:
    """Embree on the full trapezoid mesh: mesh build, BVH build + first cast, cast alone (milliseconds)."""
    t0 = time.perf_counter()
    mesh = mesh_labels(labels, grid, DEFAULT_CLASSES.palette(), mode="full")
    mesh_ms = (time.perf_counter() - t0) * 1e3
    cam = rooms.oblique_camera(grid, image)
    o, d = cam.rays()
    rays = np.concatenate([o, d], axis=-1).reshape(-1, 6).astype(np.float32)
    cells = np.flatnonzero(labels)
    o3d = _open3d()
    if o3d is not None:
        vertices = o3d.core.Tensor(mesh.vertices)
        triangles = o3d.core.Tensor(mesh.faces.astype(np.uint32))
        rays_t = o3d.core.Tensor(rays)

        def build_and_cast() -> tuple[Any, Any]:
            scene = o3d.t.geometry.RaycastingScene()
            scene.add_triangles(vertices, triangles)
            return scene, scene.cast_rays(rays_t)

        builds, casts = [], []
        prim = None
        for _ in range(max(2, repeat // 3)):
            t0 = time.perf_counter()
            scene, ans = build_and_cast()
            prim = ans["primitive_ids"].numpy()
            builds.append((time.perf_counter() - t0) * 1e3)
        for _ in range(repeat):
            t0 = time.perf_counter()
            scene.cast_rays(rays_t)["t_hit"].numpy()
            casts.append((time.perf_counter() - t0) * 1e3)
        name = f"Open3D {o3d.__version__} RaycastingScene (Embree)"
        miss = prim == o3d.t.geometry.RaycastingScene.INVALID_ID
    else:
        try:
            import trimesh
            from trimesh.ray.ray_pyembree import RayMeshIntersector
        except Exception:  # noqa: BLE001 - neither peer is installed
            return None
        tm = trimesh.Trimesh(vertices=mesh.vertices, faces=mesh.faces, process=False, validate=False)
        builds, casts = [], []
        for _ in range(max(2, repeat // 3)):
            t0 = time.perf_counter()
            inter = RayMeshIntersector(tm)
            tri = inter.intersects_first(rays[:, :3], rays[:, 3:])
            builds.append((time.perf_counter() - t0) * 1e3)
        for _ in range(repeat):
            t0 = time.perf_counter()
            inter.intersects_first(rays[:, :3], rays[:, 3:])
            casts.append((time.perf_counter() - t0) * 1e3)
        prim = tri
        miss = tri < 0
        name = "trimesh + embreex (Embree)"
    peer_cells = np.where(miss, -1, cells[np.where(miss, 0, prim).astype(np.int64) // 12])
    agree = None
    if reference_cells is not None:
        agree = float(np.mean(peer_cells == reference_cells.reshape(-1)))
    return {
        "peer": name,
        "triangles": mesh.n_faces,
        "mesh_build_ms": mesh_ms,
        "build_and_first_cast_ms": statistics.median(builds),
        "cast_ms": statistics.median(casts),
        "agreement_with_backend": agree,
    }


# ---------------------------------------------------------------------------------------------- report


def bar_chart(result: dict[str, Any], path: Path) -> None:
    """Horizontal bars of median milliseconds per (backend, operation), the peer's beside them, log scale."""
    plt = common.pyplot()
    labels, values, colours = [], [], []
    palette = {"opencl": "#1f77b4", "warp-cpu": "#2ca02c", "warp-cuda": "#d62728"}
    for r in result["rows"]:
        what = f"(4, 7, {r['n']}^3) logits" if r["op"] == "own-view shell" else f"{r['n']}^3 @ {r['image']}^2"
        labels.append(f"{r['backend']}: {r['op']} {what}")
        values.append(r["median_ms"])
        colours.append(palette.get(r["backend"], "#7f7f7f"))
    peer = result.get("peer")
    if peer:
        labels += ["Embree peer: BVH build + cast 128^3", "Embree peer: cast alone 128^3"]
        values += [peer["build_and_first_cast_ms"], peer["cast_ms"]]
        colours += ["#ff7f0e", "#ffbb78"]
    fig, ax = plt.subplots(figsize=(9, 0.45 * len(labels) + 1.2))
    y = np.arange(len(labels))[::-1]
    ax.barh(y, values, color=colours)
    for yy, v in zip(y, values, strict=True):
        ax.text(v * 1.05, yy, f"{v:.1f} ms", va="center", fontsize=8)
    ax.set_yticks(y, labels, fontsize=8)
    ax.set_xscale("log")
    ax.set_xlabel("milliseconds (median), log scale")
    m = result["machine"]
    ax.set_title(f"fruxel kernels on {m['cpu']} ({m['cores']} cores){' + ' + m['gpu'] if m['gpu'] else ''}",
                 fontsize=9)
    ax.set_xlim(right=max(values) * 4)
    common.save_figure(fig, path, dpi=110)


def ratios(result: dict[str, Any]) -> dict[str, dict[str, float]]:
    """Peer time / backend first_hit time at 128^3 (how many times faster the backend is)."""
    peer = result.get("peer")
    out = {}
    if not peer:
        return out
    for r in result["rows"]:
        if r["op"] == "first_hit" and r["n"] == 128:
            out[r["backend"]] = {
                "vs_build_and_cast": peer["build_and_first_cast_ms"] / r["median_ms"],
                "vs_mesh_build_and_cast": (peer["mesh_build_ms"] + peer["build_and_first_cast_ms"]) / r["median_ms"],
                "vs_cast": peer["cast_ms"] / r["median_ms"],
            }
    return out


def table(result: dict[str, Any]) -> str:
    """Markdown table of one result file."""
    cuda = any("gpu_ms" in r for r in result["rows"])
    extra = " pipelined (ms) | GPU (ms) |" if cuda else ""
    lines = ["| backend | operation | grid | image | first call (ms) | median (ms) | min (ms) |" + extra + " target |",
             "| --- | --- | --- | --- | ---: | ---: | ---: |" + (" ---: | ---: |" if cuda else "") + " --- |"]
    for r in result["rows"]:
        tgt = TARGETS.get((r["backend"], r["op"], r["n"]))
        mark = ""
        if tgt:
            mark = f"{tgt[0]}: {'met' if tgt[1](r['median_ms']) else 'missed'}"
            if "gpu_ms" in r:
                mark = (f"{tgt[0]}: latency {'met' if tgt[1](r['median_ms']) else 'missed'}, pipelined "
                        f"{'met' if tgt[1](r['pipelined_ms']) else 'missed'}, GPU "
                        f"{'met' if tgt[1](r['gpu_ms']) else 'missed'}")
        img = f"{r['image']}^2" if r["op"] != "own-view shell" else "own camera, B=4, C=7 float32 logits"
        def ms(v: float) -> str:
            return f"{v:.3f}" if v < 10 else f"{v:.1f}"

        cells = f" {ms(r['pipelined_ms'])} | {ms(r['gpu_ms'])} |" if "gpu_ms" in r else (" | |" if cuda else "")
        lines.append(f"| {r['backend']} | {r['op']} | {r['n']}^3 | {img} | {ms(r['first_ms'])} | "
                     f"{ms(r['median_ms'])} | {ms(r['min_ms'])} |{cells} {mark} |")
    peer = result.get("peer")
    if peer:
        lines.append(f"| {peer['peer']} | full mesh build (numpy) | 128^3 | | | {peer['mesh_build_ms']:.1f} | | |")
        lines.append(f"| {peer['peer']} | BVH build + first cast | 128^3 | 512^2 | | "
                     f"{peer['build_and_first_cast_ms']:.1f} | | |")
        lines.append(f"| {peer['peer']} | cast alone | 128^3 | 512^2 | | {peer['cast_ms']:.1f} | | |")
    return "\n".join(lines)


def section(results: list[dict[str, Any]]) -> str:
    """The "## Kernels" section of BENCHMARKS.md from every result file."""
    parts = [SECTION, "",
             "`python benchmarks/bench_kernels.py` (see its docstring). Model: `fruxel/data/rooms.py` "
             "`room_volume(128)` (25 % occupied: walls, floor, window, door, furniture blocks, a sculpture "
             "blob), viewed by `oblique_camera` at 512 x 512. Times are medians after one warm-up; "
             "\"first call\" includes compiling the kernels or loading them from the backend's cache. "
             "The Embree peer is timed in the same run on the `full` trapezoid mesh (12 triangles per "
             "occupied cell); \"incl. rebuild\" means BVH build + cast, what the peer pays per frame when the "
             "volume changes, as it does for every network output.",
             ""]
    speed_name, speed_target = SPEEDUP_TARGET
    for res in results:
        m = res["machine"]
        gpu = f", GPU {m['gpu']}" if m.get("gpu") else ""
        cpu = f"{m['cpu']} ({m['cpu_id']})" if m.get("cpu_id") else m["cpu"]
        parts += [f"### {cpu}, {m['cores']} cores{gpu} ({m['date']})", ""]
        if "load_average_1min_at_start" in m:
            parts += [f"1-minute load average {m['load_average_1min_at_start']:.1f} at the start and "
                      f"{m.get('load_average_1min_at_end', float('nan')):.1f} at the end of the run (the machine is "
                      f"shared: a load above the core count means the numbers are pessimistic).", ""]
        if res.get("note"):
            parts += [res["note"], ""]
        parts += [table(res), ""]
        peer = res.get("peer")
        if peer:
            agree = peer.get("agreement_with_backend")
            agree_txt = f"; its first hits name the same cell as the backends' on {agree:.4%} of pixels" if (
                agree is not None) else ""
            parts += [f"Peer: {peer['peer']}, {peer['triangles']:,} triangles{agree_txt}.", ""]
            rs = res.get("ratios", {})
            if rs:
                parts += ["| backend | x faster than peer incl. BVH rebuild | incl. mesh + BVH rebuild | "
                          "vs. peer cast alone |", "| --- | ---: | ---: | ---: |"]
                for b, r in rs.items():
                    mark = ""
                    if b == speed_name:
                        ok = r["vs_build_and_cast"] >= speed_target
                        mark = f" (target >= {speed_target:.0f}x: {'met' if ok else 'missed'})"
                    parts.append(f"| {b} | {r['vs_build_and_cast']:.1f}x{mark} | {r['vs_mesh_build_and_cast']:.1f}x | "
                                 f"{r['vs_cast']:.2f}x |")
                parts.append("")
        v = m.get("versions", {})
        parts += ["Versions: " + ", ".join(f"{k} {val}" for k, val in v.items() if val) + ".", ""]
        if m.get("opencl_device"):
            parts += [f"OpenCL ran on `{m['opencl_device']}` ({m['opencl_platform']}); devices probed: "
                      + "; ".join(m.get("opencl_devices_probed", [])) + ".", ""]
        chart = res.get("chart")
        if chart:
            parts += [f"![kernel benchmark]({chart})", ""]
    parts += ["Targets (from the issue): OpenCL first_hit <= 20 ms and Warp CPU <= 80 ms at 128^3 @ 512^2; "
              "OpenCL >= 150x faster than Embree including its BVH rebuild; shell over 6 poses <= 150 ms on "
              "OpenCL; on the H100 (warp-cuda), first_hit <= 0.1 ms at 128^3 @ 512^2 and <= 1 ms at 256^3 @ 1024^2, "
              "shell over 6 poses <= 1 ms, own-view shell of (4, 7, 128^3) logits <= 1 ms. H100 times: *median* "
              "is the wall time of one call from Python, torch CUDA tensors in and out, synchronised after every "
              "call (latency); *pipelined* the wall time per call of back-to-back calls closed by one "
              "synchronisation (a loop that never waits; bound by the host's Python time per call or by the "
              "GPU, whichever is larger); *GPU* the summed device time of one call's kernels (CUPTI). Each "
              "target is marked against all three. fruxel judges the H100 targets on *GPU*, the kernels' time per "
              "frame: on the lent machine one call's Python and launch work alone takes about 0.16 ms, whatever "
              "the kernels do, and varies by up to 2x between runs.", ""]
    return "\n".join(parts)


# ---------------------------------------------------------------------------------------------- main


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backends", nargs="+", default=None, help="available_backends() names (default: all)")
    ap.add_argument("--sizes", nargs="+", type=int, default=None,
                    help="grid sizes n (image 4n); default 128, plus 256 when a CUDA backend runs")
    ap.add_argument("--repeat", type=int, default=10, help="timed runs per measurement")
    ap.add_argument("--out", default=str(common.RESULTS / "kernels"), help="prefix of the .json and .png written")
    ap.add_argument("--device", default=None, help="Warp device (cpu, cuda, cuda:N); default per backend name")
    ap.add_argument("--no-peer", action="store_true", help="skip the Embree peer")
    ap.add_argument("--no-write", action="store_true", help="do not write files or BENCHMARKS.md")
    ap.add_argument("--note", default=None, help="a line printed under this machine's heading in BENCHMARKS.md")
    args = ap.parse_args(argv)

    avail = available_backends()
    names = args.backends or avail
    for n in names:
        if n not in avail:
            ap.error(f"backend {n!r} is not available here; available: {avail}")
    sizes = args.sizes or ([128, 256] if any(n == "warp-cuda" for n in names) else [128])
    result: dict[str, Any] = {"machine": machine_info(), "config": vars(args), "rows": [], "note": args.note}
    print(f"machine: {result['machine']['cpu']} x{result['machine']['cores']}, GPU {result['machine']['gpu']}")
    first_cells = None
    for n in sizes:
        labels, grid = rooms.room_volume(n)
        result.setdefault("scenes", {})[str(n)] = rooms.describe(labels)
        logits = logits_batch(n) if n == 128 else None
        for name in names:
            if n > 128 and name != "warp-cuda":
                continue
            device = args.device or ("cuda" if name == "warp-cuda" else "cpu" if name == "warp-cpu" else None)
            rows = bench_backend(name, labels, grid, 4 * n, args.repeat, device, logits)
            for r in rows:
                print(f"{name:10s} {r['op']:15s} {n}^3 @ {r['image']}^2: first {r['first_ms']:9.1f} ms, "
                      f"median {r['median_ms']:9.2f} ms")
            result["rows"] += rows
            if n == 128 and first_cells is None:
                dev = device if name.startswith("warp") else None
                first_cells = _cells(first_hit(labels, grid, rooms.oblique_camera(grid, 512),
                                               backend="warp" if dev else name, device=dev))
        if n == 128 and not args.no_peer:
            peer = bench_peer(labels, grid, 512, args.repeat, first_cells)
            if peer is None:
                print("peer: neither open3d nor embreex is installed; skipped")
            else:
                result["peer"] = peer
                print(f"peer {peer['peer']}: mesh {peer['mesh_build_ms']:.1f} ms, BVH build + first cast "
                      f"{peer['build_and_first_cast_ms']:.1f} ms, cast {peer['cast_ms']:.1f} ms, agreement "
                      f"{peer['agreement_with_backend']}")
    result["machine"]["load_average_1min_at_end"] = common.load_average()
    result["ratios"] = ratios(result)
    print()
    print(table(result))
    for b, r in result["ratios"].items():
        print(f"{b}: {r['vs_build_and_cast']:.1f}x faster than the peer incl. BVH rebuild, "
              f"{r['vs_cast']:.2f}x vs its cast alone")
    if not args.no_write:
        common.write_result(result, Path(args.out), bar_chart, "kernels*.json", SECTION, section)
    return result


if __name__ == "__main__":
    main()

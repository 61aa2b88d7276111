"""OpenCL on the CPU: ``first_hit`` against a plain DDA, on a room and on a sparse scene, with Warp on the CPU too.

The peer is :file:`bench_dda.cl`, a plain single-level DDA (one work-item per pixel stepping cell by cell, no
empty-space skipping) with first_hit's four outputs (label, cell, depth, entry-face normal), run on the same OpenCL
device in the same run; it must agree with ``first_hit`` on every pixel, so both do the same job. Scenes, both
128^3 (:func:`fruxel.data.rooms.room_grid`) seen by :func:`fruxel.data.rooms.oblique_camera` at 512 x 512:

* ``room``: :func:`fruxel.data.rooms.room_volume` (25 % occupied: walls, floor, furniture, a sculpture);
* ``sparse``: a floor slab, a back wall and a dozen 20^3 boxes (:func:`sparse_volume`, about 8 % occupied): long
  rays through empty space.

Each measurement is called once to build and warm up, then the methods are timed in ``--repeat`` interleaved
rounds (one call each per round, so that load from other processes falls on all of them alike); medians and
minima are reported, and the ratio of the plain DDA's median to ``first_hit``'s (target: at least 5x on both
scenes). ``FRUXEL_OPENCL_DEVICE`` picks another OpenCL device (e.g. ``"PoCL 3.0"``: the PyPI PoCL where Debian's is
installed too).

Run ``python benchmarks/bench_dda.py`` (``--repeat N``, ``--backends opencl warp-cpu``, ``--out PREFIX``,
``--no-write``, ``--note``). Writes ``PREFIX.json`` and ``PREFIX.png`` (default ``benchmarks/results/dda``) and
re-renders the "## OpenCL on the CPU: first_hit against a plain DDA" section of BENCHMARKS.md from every
``benchmarks/results/dda*.json``.
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

from fruxel.camera import Camera  # noqa: E402
from fruxel.classes import DEFAULT_CLASSES  # noqa: E402
from fruxel.data import rooms  # noqa: E402
from fruxel.grid import FruxelGrid  # noqa: E402

SECTION = "## OpenCL on the CPU: first_hit against a plain DDA"
TARGET = 5.0
"""first_hit at least this many times faster than the plain DDA (median against median), on every scene."""
SOURCE = Path(__file__).with_suffix(".cl")
_IDS = {name: i for i, name in enumerate(DEFAULT_CLASSES.names)}


# ---------------------------------------------------------------------------------------------- scenes, peer
def sparse_volume(n: int = 128, boxes: int = 12, edge: int = 20, seed: int = 0) -> tuple[np.ndarray, FruxelGrid]:
    """A sparse ``n^3`` scene: a floor slab (the 2 bottom rows, y grows downwards), a back wall (the 2 last slices)
    and ``boxes`` cubes of ``edge`` cells at seeded places.

    Returns:
        labels ``(n, n, n)`` uint8 ``(D, H, W)`` (floor, wall and furniture ids) and :func:`rooms.room_grid`.
    """
    grid = rooms.room_grid(n)
    lab = np.zeros(grid.shape, np.uint8)
    lab[:, n - 2:, :] = _IDS["floor"]
    lab[n - 2:, :, :] = _IDS["wall"]
    rng = np.random.default_rng(seed)
    for _ in range(boxes):
        k, j, i = rng.integers(0, n - edge, 3)
        lab[k:k + edge, j:j + edge, i:i + edge] = _IDS["furniture"]
    return lab, grid


def plain_first_hit(rt: Any, labels: np.ndarray, grid: FruxelGrid, camera: Camera) -> tuple[np.ndarray, ...]:
    """First hits by the peer, :file:`bench_dda.cl`, on runtime ``rt`` (an :class:`fruxel.kernels.cl.runtime.Runtime`):
    the same four outputs as ``first_hit``.

    Args:
        rt: the OpenCL device's runtime.
        labels: ``(D, H, W)`` uint8 labels, 0 = empty.
        grid: their grid.
        camera: the viewing camera.

    Returns:
        label ``(h, w)`` int32 (0 on a miss), cell ``(h, w)`` int64 (flat index, -1 on a miss), depth ``(h, w)``
        float32 (z in the viewing camera, 0 on a miss) and normal ``(h, w, 3)`` float32 (entry face, grid frame, 0
        on a miss).
    """
    from fruxel.kernels import traversal
    from fruxel.kernels.cl import occupancy

    lab = np.ascontiguousarray(labels, dtype=np.uint8)
    h, w = camera.height, camera.width
    out = (np.empty((h, w), np.int32), np.empty((h, w), np.int64), np.empty((h, w), np.float32),
           np.empty((h, w, 3), np.float32))
    lx, ly = occupancy.TRACE_LOCAL  # the per-pixel kernels' work-group shape
    with rt.lock:
        k = rt.kernel(SOURCE.read_text(encoding="utf-8"), "plain_first_hit_kernel")
        outs = [(rt.output(f"plain_{i}", a), a) for i, a in enumerate(out)]
        k(rt.queue, (occupancy.round_up(w, lx), occupancy.round_up(h, ly)), (lx, ly), rt.input("plain_labels", lab),
          traversal.grid_params(grid), traversal.camera_params(camera), occupancy.cell_counts(grid), np.int32(w),
          np.int32(h), *(buf for buf, _ in outs))
        rt.fetch(outs)  # the call's one synchronisation: the results go to the caller
    return out


# ---------------------------------------------------------------------------------------------- measuring
def interleaved(fns: dict[str, Callable[[], Any]], repeat: int) -> dict[str, dict[str, float]]:
    """Wall time of each function in milliseconds: the first call alone, then ``repeat`` rounds of one call each."""
    out: dict[str, dict[str, float]] = {}
    for name, fn in fns.items():
        t0 = time.perf_counter()
        fn()
        out[name] = {"first_ms": (time.perf_counter() - t0) * 1e3}
    runs: dict[str, list[float]] = {name: [] for name in fns}
    for _ in range(repeat):
        for name, fn in fns.items():
            t0 = time.perf_counter()
            fn()
            runs[name].append((time.perf_counter() - t0) * 1e3)
    for name, r in runs.items():
        out[name].update(median_ms=statistics.median(r), min_ms=min(r), runs=len(r))
    return out


def measure_scene(name: str, labels: np.ndarray, grid: FruxelGrid, backends: list[str], repeat: int,
                  rt: Any) -> dict[str, Any]:
    """One scene: the methods' times, the agreement checks and the ratio."""
    from fruxel.kernels import first_hit

    cam = rooms.oblique_camera(grid, 512)
    fns: dict[str, Callable[[], Any]] = {}
    if "opencl" in backends:
        fns["plain DDA (OpenCL)"] = lambda: plain_first_hit(rt, labels, grid, cam)
        fns["first_hit (OpenCL)"] = lambda: first_hit(labels, grid, cam, backend="opencl")
    if "warp-cpu" in backends:
        fns["first_hit (Warp CPU)"] = lambda: first_hit(labels, grid, cam, backend="warp", device="cpu")
    row: dict[str, Any] = {"scene": name, "occupancy": float(np.mean(labels != 0)), "times": interleaved(fns, repeat)}
    if "opencl" in backends:
        hits = first_hit(labels, grid, cam, backend="opencl")
        label, cell, depth, normal = plain_first_hit(rt, labels, grid, cam)
        row["pixels"] = int(cell.size)
        row["hit_fraction"] = float(np.mean(hits.cell >= 0))
        row["plain_mismatches"] = int(np.sum((label != hits.label) | (cell != hits.cell)))
        row["plain_same_depth_normal"] = bool(np.array_equal(depth, hits.depth) and np.array_equal(normal, hits.normal))
        t = row["times"]
        row["ratio"] = t["plain DDA (OpenCL)"]["median_ms"] / t["first_hit (OpenCL)"]["median_ms"]
        row["ratio_min"] = t["plain DDA (OpenCL)"]["min_ms"] / t["first_hit (OpenCL)"]["min_ms"]
        if "warp-cpu" in backends:
            wcell = np.asarray(first_hit(labels, grid, cam, backend="warp", device="cpu").cell)
            row["warp_same_cell"] = float(np.mean(wcell == hits.cell))
    return row


def machine_info(rt: Any) -> dict[str, Any]:
    """CPU, cores, load, the OpenCL device and PoCL version, package versions."""
    info = common.machine_info(("numpy", "pyopencl", "pocl-binary-distribution", "warp-lang"))
    info["load_average_1min_at_start"] = info.pop("load_average")
    info["cpu_id"] = common.cpu_id()
    if rt is not None:
        info.update(common.opencl_device())
    return info


# ---------------------------------------------------------------------------------------------- report
def ms(v: float) -> str:
    return f"{v:.2f}" if v < 10 else f"{v:.1f}"


def table(result: dict[str, Any]) -> str:
    """Markdown table of one result file: one row per scene and method."""
    lines = ["| scene | occupied | method | first call (ms) | median (ms) | min (ms) | plain DDA / this (median) |",
             "| --- | ---: | --- | ---: | ---: | ---: | ---: |"]
    for row in result["scenes"]:
        plain = row["times"].get("plain DDA (OpenCL)")
        for method, t in row["times"].items():
            ratio = f"{plain['median_ms'] / t['median_ms']:.2f}x" if plain else ""
            if method == "first_hit (OpenCL)" and plain:
                ok = row["ratio"] >= TARGET
                ratio = f"**{row['ratio']:.2f}x** (target >= {TARGET:.0f}x: {'met' if ok else 'missed'})"
            lines.append(f"| {row['scene']} | {row['occupancy']:.1%} | {method} | {ms(t['first_ms'])} | "
                         f"{ms(t['median_ms'])} | {ms(t['min_ms'])} | {ratio} |")
    return "\n".join(lines)


def chart(result: dict[str, Any], path: Path) -> None:
    """Median milliseconds per scene and method, bars side by side, log scale, the ratio over first_hit's bar."""
    plt = common.pyplot()
    scenes = [r["scene"] for r in result["scenes"]]
    methods = list(result["scenes"][0]["times"])
    colours = {"plain DDA (OpenCL)": "#ff7f0e", "first_hit (OpenCL)": "#1f77b4", "first_hit (Warp CPU)": "#2ca02c"}
    fig, ax = plt.subplots(figsize=(7.5, 4.2))
    width = 0.8 / len(methods)
    x = np.arange(len(scenes))
    for m, method in enumerate(methods):
        vals = [r["times"][method]["median_ms"] for r in result["scenes"]]
        bars = ax.bar(x + (m - (len(methods) - 1) / 2) * width, vals, width, label=method,
                      color=colours.get(method, "#7f7f7f"))
        for b, v, r in zip(bars, vals, result["scenes"], strict=True):
            text = f"{v:.1f} ms"
            if method == "first_hit (OpenCL)" and "ratio" in r:
                text += f"\n{r['ratio']:.1f}x"
            ax.annotate(text, (b.get_x() + b.get_width() / 2, v), ha="center", va="bottom", fontsize=8)
    ax.set_yscale("log")
    ax.set_xticks(x, [f"{s}\n128^3 @ 512^2" for s in scenes])
    ax.set_ylabel("milliseconds per call (median), log scale")
    m = result["machine"]
    ax.set_title(f"first_hit against a plain DDA: {m['cpu']}, {m['cores']} cores, {m.get('opencl_platform', '')}",
                 fontsize=9)
    ax.legend(fontsize=8, loc="upper left")
    ax.set_ylim(top=max(t["median_ms"] for r in result["scenes"] for t in r["times"].values()) * 4)
    common.save_figure(fig, path, dpi=110)


def section(results: list[dict[str, Any]]) -> str:
    """The BENCHMARKS.md section from every result file."""
    parts = [SECTION, "",
             "`python benchmarks/bench_dda.py` (see its docstring). `first_hit` on OpenCL against a plain "
             "single-level DDA on the same device in the same run (`benchmarks/bench_dda.cl`: one work-item per "
             "pixel stepping cell by cell, with first_hit's four outputs), on two 128^3 scenes seen by "
             "`oblique_camera` at 512 x 512: `room` "
             "(`rooms.room_volume`) and `sparse` (a floor slab, a back wall and a dozen 20^3 boxes, "
             "`bench_dda.sparse_volume`). The methods are timed in interleaved rounds; the plain DDA gives the "
             "same label, cell, depth and normal as `first_hit` on every pixel (checked each run). Warp on the CPU "
             "is the other backend's `first_hit`. Target: `first_hit` at least 5x the plain DDA on both scenes. The "
             "peer is scalar code, as one writes a DDA; the same plain DDA over 16-ray tiles in vector lanes (the "
             "layout of `first_hit`'s walk, not kept) ran 2.7x faster than it, so that layout is part of the ratio "
             "and the empty-space skipping the rest (`benchmarks/PERF_NOTES.md`).", ""]
    for res in results:
        m = res["machine"]
        cpu = f"{m['cpu']} ({m['cpu_id']})" if m.get("cpu_id") else m["cpu"]
        parts += [f"### {cpu}, {m['cores']} cores, {m.get('opencl_platform', 'no OpenCL')} ({m['date']})", ""]
        parts += [f"OpenCL device `{m.get('opencl_device')}` ({m.get('opencl_platform')}, driver "
                  f"{m.get('opencl_driver')}); devices probed: " + "; ".join(m.get("opencl_devices_probed", [])) + ". "
                  f"1-minute load average {m['load_average_1min_at_start']:.1f} at the start and "
                  f"{m.get('load_average_1min_at_end', float('nan')):.1f} at the end; {res['config']['repeat']} "
                  "rounds.", ""]
        if res.get("note"):
            parts += [res["note"], ""]
        parts += [table(res), ""]
        checks = []
        for row in res["scenes"]:
            if "plain_mismatches" in row:
                c = (f"{row['scene']}: plain DDA and first_hit differ on {row['plain_mismatches']} of "
                     f"{row['pixels']:,} pixels ({row['hit_fraction']:.1%} hit), depths and normals "
                     f"{'bit-identical' if row.get('plain_same_depth_normal') else 'differ'}")
                if "warp_same_cell" in row:
                    c += f", Warp names the same cell on {row['warp_same_cell']:.4%}"
                checks.append(c)
        if checks:
            parts += ["Checks: " + "; ".join(checks) + ".", ""]
        v = m.get("versions", {})
        parts += ["Versions: " + ", ".join(f"{k} {val}" for k, val in v.items() if val) + ".", ""]
        if res.get("chart"):
            parts += [f"![first_hit against a plain DDA]({res['chart']})", ""]
    return "\n".join(parts)


# ---------------------------------------------------------------------------------------------- main
def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--repeat", type=int, default=15, help="interleaved timed rounds per scene")
    ap.add_argument("--backends", nargs="+", default=["opencl", "warp-cpu"], choices=["opencl", "warp-cpu"],
                    help="what to time (the plain DDA runs with opencl)")
    ap.add_argument("--scenes", nargs="+", default=["room", "sparse"], choices=["room", "sparse"])
    ap.add_argument("--out", default=str(common.RESULTS / "dda"), help="prefix of the .json and .png written")
    ap.add_argument("--no-write", action="store_true", help="do not write files or BENCHMARKS.md")
    ap.add_argument("--note", default=None, help="a line printed under this machine's heading in BENCHMARKS.md")
    args = ap.parse_args(argv)

    from fruxel.kernels import available_backends

    avail = available_backends()
    for b in args.backends:
        if b not in avail:
            ap.error(f"backend {b!r} is not available here; available: {avail}")
    rt = None
    if "opencl" in args.backends:
        from fruxel.kernels.cl.runtime import get_runtime

        rt = get_runtime(None)  # the device first_hit runs on by default
    result: dict[str, Any] = {"machine": machine_info(rt), "config": vars(args), "note": args.note, "scenes": []}
    m = result["machine"]
    print(f"machine: {m['cpu']} x{m['cores']}, OpenCL {m.get('opencl_device')} ({m.get('opencl_platform')})")
    for name in args.scenes:
        labels, grid = rooms.room_volume(128) if name == "room" else sparse_volume()
        row = measure_scene(name, labels, grid, args.backends, args.repeat, rt)
        result["scenes"].append(row)
        for method, t in row["times"].items():
            print(f"{name:7s} {method:22s} median {t['median_ms']:8.2f} ms  min {t['min_ms']:8.2f} ms")
        if "ratio" in row:
            print(f"{name:7s} plain DDA / first_hit: {row['ratio']:.2f}x (min/min {row['ratio_min']:.2f}x); "
                  f"{row['plain_mismatches']} pixels differ; depths and normals identical: "
                  f"{row['plain_same_depth_normal']}")
    result["machine"]["load_average_1min_at_end"] = common.load_average()
    print()
    print(table(result))
    if not args.no_write:
        common.write_result(result, Path(args.out), chart, "dda*.json", SECTION, section)
    return result


if __name__ == "__main__":
    main()

"""Meshing benchmark: build time and triangle count of the full, culled and greedy trapezoid meshes.

Model: :func:`fruxel.data.rooms.room_volume` (128^3, 25 % occupied; the model of the kernel benchmark and of
Table 1). Also reports the greedy / culled triangle ratio on the bundled sample room, and the interactive path's
input: the own-view VMS shell of the same model (the first occupied cell of each column, as ``kernels.shell``
with ``grid.camera()``), a few % of the grid.

Run ``python benchmarks/bench_mesh.py`` (``--repeats N``, ``--no-write``). Prints a table, replaces the
"## Meshing" section of BENCHMARKS.md and writes the bar chart ``benchmarks/results/mesh.png``.

Targets (from the issue): culled under 0.3 s on 128^3 at 25 %; greedy at least 10x fewer triangles than culled
on the sample room; greedy on the 128^3 own-view shell under 20 ms on one core (shell + greedy + draw at 30 FPS).
"""

from __future__ import annotations

import argparse
import datetime as dt
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

from fruxel.classes import DEFAULT_CLASSES  # noqa: E402
from fruxel.data import SAMPLE_ROOM, rooms  # noqa: E402
from fruxel.grid import FruxelGrid  # noqa: E402
from fruxel.io import load  # noqa: E402
from fruxel.mesh import MODES, mesh_labels  # noqa: E402

CHART = common.RESULTS / "mesh.png"
SECTION = "## Meshing"

CULLED_TARGET_S = 0.3
GREEDY_TARGET_RATIO = 10.0
SHELL_GREEDY_TARGET_MS = 20.0


def own_view_shell(labels: np.ndarray) -> np.ndarray:
    """The VMS shell from the grid's own camera: the first occupied cell of each column (conventions section 4).

    Args:
        labels: ``(D, H, W)`` uint8 labels.

    Returns:
        ``(D, H, W)`` uint8, the labels of the kept cells, 0 elsewhere.
    """
    occ = labels != 0
    k = occ.argmax(axis=0)
    jj, ii = np.nonzero(occ.any(axis=0))
    out = np.zeros_like(labels)
    out[k[jj, ii], jj, ii] = labels[k[jj, ii], jj, ii]
    return out


def time_mesh(labels: np.ndarray, grid: FruxelGrid, palette: np.ndarray, mode: str, repeats: int) -> tuple[float, int]:
    """Median build time in seconds over ``repeats`` runs (after one warm-up) and the triangle count."""
    mesh = mesh_labels(labels, grid, palette, mode)
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        mesh_labels(labels, grid, palette, mode)
        times.append(time.perf_counter() - t0)
    return float(np.median(times)), mesh.n_faces


def bar_chart(rows: list[dict], path: Path = CHART) -> None:
    """Two panels: build time (s) and triangle count (log scale) per mode."""
    plt = common.pyplot()
    modes = [r["mode"] for r in rows]
    colours = ["#aec7e8", "#ff7f0e", "#2ca02c"]
    fig, (ax_t, ax_n) = plt.subplots(1, 2, figsize=(9, 3.6))
    ax_t.bar(modes, [r["time"] for r in rows], color=colours)
    ax_t.axhline(CULLED_TARGET_S, color="k", ls="--", lw=1, label=f"culled target {CULLED_TARGET_S} s")
    ax_t.set_ylabel("build time, s (median)")
    ax_t.legend(fontsize=8)
    ax_n.bar(modes, [r["tris"] for r in rows], color=colours)
    ax_n.set_yscale("log")
    ax_n.set_ylabel("triangles")
    for ax, key, fmt in ((ax_t, "time", "{:.3f}"), (ax_n, "tris", "{:,}")):
        for i, r in enumerate(rows):
            ax.annotate(fmt.format(r[key]), (i, r[key]), ha="center", va="bottom", fontsize=8)
    fig.suptitle("Trapezoid meshing, 128^3 grid, 25 % occupied")
    common.save_figure(fig, path, dpi=120)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--no-write", action="store_true", help="print only; leave BENCHMARKS.md and the chart")
    args = parser.parse_args(argv)

    load_before = common.load_average()
    palette = DEFAULT_CLASSES.palette()
    labels, grid = rooms.room_volume(128)
    n_occ = int(np.count_nonzero(labels))
    rows = []
    for mode in MODES:
        t, n = time_mesh(labels, grid, palette, mode, args.repeats)
        rows.append({"mode": mode, "time": t, "tris": n})

    sample = load(SAMPLE_ROOM)
    sample_tris = {}
    for mode in MODES:
        t, n = time_mesh(sample.labels, sample.grid, sample.classes.palette(), mode, args.repeats)
        sample_tris[mode] = (t, n)
    ratio = sample_tris["culled"][1] / sample_tris["greedy"][1]

    shell = own_view_shell(labels)
    n_shell = int(np.count_nonzero(shell))
    shell_rows = []
    for mode in MODES:
        t, n = time_mesh(shell, grid, palette, mode, args.repeats)
        shell_rows.append({"mode": mode, "time": t, "tris": n})
    load_after = common.load_average()

    culled_t = rows[1]["time"]
    shell_greedy_ms = shell_rows[2]["time"] * 1e3
    g = sample.grid
    lines = [
        SECTION,
        "",
        f"`python benchmarks/bench_mesh.py` on {dt.date.today().isoformat()}, {common.cpu_description()}, "
        f"NumPy {np.__version__}; median of {args.repeats} runs after one warm-up, one thread. 1-minute load "
        f"average {load_before:.1f} before the runs, {load_after:.1f} after"
        + (" (the machine was loaded, so the times are noisy and on the slow side)."
           if max(load_before, load_after) >= common.usable_cores() else "."),
        "",
        f"Dense room: `fruxel/data/rooms.py` `room_volume(128)`, {grid.width}x{grid.height}x{grid.depth} grid, "
        f"{n_occ:,} occupied cells ({n_occ / labels.size:.1%}).",
        "",
        "| mode | triangles | triangles per occupied cell | build time (s) |",
        "| --- | ---: | ---: | ---: |",
    ]
    lines += [f"| {r['mode']} | {r['tris']:,} | {r['tris'] / n_occ:.2f} | {r['time']:.3f} |" for r in rows]
    lines += [
        "",
        f"Own-view VMS shell (the interactive path's input, remade every frame): the first occupied cell of each "
        f"column of the same model, {n_shell:,} cells kept ({n_shell / shell.size:.2%} of the grid).",
        "",
        "| mode | triangles | build time (ms) |",
        "| --- | ---: | ---: |",
    ]
    lines += [f"| {r['mode']} | {r['tris']:,} | {r['time'] * 1e3:.1f} |" for r in shell_rows]
    lines += [
        "",
        f"Sample room ({g.width}x{g.height}x{g.depth}, {sample.n_occupied:,} occupied cells): "
        + ", ".join(f"{m} {n:,} triangles in {t * 1e3:.1f} ms" for m, (t, n) in sample_tris.items())
        + f"; greedy has **{ratio:.1f}x** fewer triangles than culled.",
        "",
        f"Targets: culled under {CULLED_TARGET_S} s on 128^3 at 25 %: {culled_t:.3f} s "
        f"({'met' if culled_t < CULLED_TARGET_S else 'MISSED'}); greedy at least {GREEDY_TARGET_RATIO:.0f}x "
        f"fewer triangles than culled on the sample room: {ratio:.1f}x "
        f"({'met' if ratio >= GREEDY_TARGET_RATIO else 'MISSED'}); greedy on the 128^3 own-view shell under "
        f"{SHELL_GREEDY_TARGET_MS:.0f} ms (the mesh's share of a 30 FPS frame): {shell_greedy_ms:.1f} ms "
        f"({'met' if shell_greedy_ms < SHELL_GREEDY_TARGET_MS else 'MISSED'}). Culled and greedy visit only the "
        "occupied cells and their faces after one pass over the grid, so the shell meshes in a few ms.",
        "",
        "![meshing benchmark](benchmarks/results/mesh.png)",
    ]
    text = "\n".join(lines)
    print(text)
    if not args.no_write:
        common.replace_section(common.BENCHMARKS_MD, SECTION, text)
        bar_chart(rows)
        print(f"wrote {common.BENCHMARKS_MD} and {CHART}")


if __name__ == "__main__":
    main()

"""Shell-aware losses benchmark: forward + backward of :class:`fruxel.train.losses.ShellLoss` per backend, and the
pure-torch cumprod reference of the own view.

Setup: logits ``(B, 7, n, n, n)`` float32 (default n = 64) against the ground truth of
:func:`fruxel.data.rooms.room_volume` (one seed per batch item), from the grid's own view (n x n pixels) plus 2
seeded novel poses at 128 x 128 (:func:`fruxel.train.losses.random_poses`). ``--logits scene`` (default) makes
"mid-training" logits, the ground truth's class raised by 4 over normal noise of standard deviation 1.5; ``--logits
random`` makes standard normal logits, whose rays almost never reach a transmittance of exactly 0 and so run
through every cell (worst case).

Rows, each a median of ``--repeat`` runs after one warm-up (the first call, which builds the kernels or loads
them from the cache, is reported separately):

* ``shell losses fwd+bwd``: ``ShellLoss.losses`` (soft_first_hit on both camera groups, shell cross-entropy,
  depth L1, visible-weighted voxel cross-entropy) and ``backward()``, from ground-truth targets computed
  beforehand: what a training step pays when the data loader supplies the targets;
* ``+ ground truth``: the whole ``ShellLoss.__call__`` with ``first_hit`` and ``shell`` on the labels (a
  training step that draws new poses every batch);
* ``soft_first_hit own view``: the kernels alone, own view, shell cross-entropy + depth L1, fwd+bwd;
* ``torch cumprod own view``: the same losses on :func:`fruxel.kernels.soft.soft_first_hit_own_view_torch`
  (no kernels; autograd through ``cumprod``).

Run ``python benchmarks/bench_losses.py`` (``--backends opencl warp-cpu``, ``--batch 2``, ``--size 64``,
``--repeat N``, ``--logits scene|random``, ``--out PREFIX``, ``--device cuda``, ``--no-write``, ``--note``,
``--render``).
Writes ``PREFIX.json`` and ``PREFIX.png`` (default ``benchmarks/results/losses-<device>-b<B>``) and re-renders
the "## Shell-aware losses" section of BENCHMARKS.md from every ``benchmarks/results/losses*.json``.

On an H100::

    python benchmarks/bench_losses.py --backends warp-cuda --batch 16 --repeat 20 --out $OUT/losses-cuda-b16-scene

then copy ``losses-cuda-b16-scene.json`` and ``.png`` into ``benchmarks/results/`` and run
``python benchmarks/bench_losses.py --render`` to add them to BENCHMARKS.md.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

from fruxel.data import rooms  # noqa: E402
from fruxel.grid import FruxelGrid  # noqa: E402
from fruxel.kernels import available_backends  # noqa: E402
from fruxel.kernels.soft import soft_first_hit, soft_first_hit_own_view_torch  # noqa: E402
from fruxel.train.losses import (  # noqa: E402
    ShellLoss,
    ShellLossConfig,
    depth_l1,
    random_poses,
    shell_cross_entropy,
)

SECTION = "## Shell-aware losses"
CLASSES = 7
NOVEL = 2
NOVEL_SIZE = (128, 128)

TARGETS = {
    ("cpu", 2): ("<= 300 ms", 300.0),
    ("cuda", 16): ("<= 5 ms", 5.0),
}
"""Issue targets for ``shell losses fwd+bwd``, by (device kind, batch): this 2-core CPU for B = 2 (OpenCL and Warp
CPU), the H100 for B = 16."""


# ---------------------------------------------------------------------------------------------- machine
def machine(device: str) -> dict[str, Any]:
    """What the numbers were measured on."""
    m = common.machine_info({"warp": "warp-lang", "pyopencl": "pyopencl"})
    info: dict[str, Any] = {
        "date": m["date"],
        "cpu": m["cpu"],
        "cores": m["cores"],
        "torch": torch.__version__,
        "torch_threads": torch.get_num_threads(),
        "python": m["python"],
        "load_average": m["load_average"],
    }
    if device.startswith("cuda"):
        info["gpu"] = torch.cuda.get_device_name(torch.device(device))
    info.update({k: v for k, v in m["versions"].items() if v})
    cl = common.opencl_device()
    if cl:
        info["opencl"] = f"{cl['opencl_device']} ({cl['opencl_platform']})"
    return info


# ---------------------------------------------------------------------------------------------- timing
def _sync(device: str) -> None:
    if device.startswith("cuda"):
        torch.cuda.synchronize(torch.device(device))


def timed(fn: Callable[[], Any], device: str, repeat: int) -> dict[str, float]:
    """First call and median / min of ``repeat`` further calls, milliseconds, synchronised on CUDA; there also the
    time per call of back-to-back calls (``pipelined_ms``, ``host_ms``) and the GPU time of one call
    (``gpu_ms``)."""
    out = common.time_calls(fn, repeat, sync=lambda: _sync(device))
    if device.startswith("cuda"):
        out.update(common.pipelined_ms(fn, repeat, lambda: _sync(device)))
        out["gpu_ms"] = common.cuda_kernel_ms(fn)[0]
    return out


# ---------------------------------------------------------------------------------------------- setup
def make_batch(n: int, batch: int, kind: str, device: str) -> tuple[torch.Tensor, torch.Tensor, FruxelGrid]:
    """Ground-truth labels ``(B, n, n, n)`` uint8 and logits ``(B, 7, n, n, n)`` float32 on ``device``."""
    vols = [rooms.room_volume(n, 0.25, seed) for seed in range(batch)]
    grid = vols[0][1]
    labels = torch.from_numpy(np.stack([v[0] for v in vols]))
    rng = np.random.default_rng(0)
    if kind == "random":
        logits = rng.normal(size=(batch, CLASSES, *grid.shape))
    else:
        logits = 1.5 * rng.normal(size=(batch, CLASSES, *grid.shape))
        np.put_along_axis(logits, labels.numpy()[:, None].astype(np.int64), 4.0, axis=1)
    return labels.to(device), torch.from_numpy(logits).float().to(device), grid


def measure(backend: str, args: argparse.Namespace, device: str) -> dict[str, Any]:
    """Every row of one backend."""
    labels, logits, grid = make_batch(args.size, args.batch, args.logits, device)
    logits.requires_grad_()
    config = ShellLossConfig(novel_views=NOVEL, novel_size=NOVEL_SIZE, backend=backend, device=args.device)
    loss = ShellLoss(grid, config)
    cams = [grid.camera()] + random_poses(grid, NOVEL, np.random.default_rng(1), width=NOVEL_SIZE[0],
                                          height=NOVEL_SIZE[1])
    targets = loss.targets(labels, cams)

    def losses() -> None:
        logits.grad = None
        loss.losses(logits, cams, targets).total.backward()

    def full() -> None:
        logits.grad = None
        loss(logits, labels, cams).total.backward()

    own_t = targets.groups[0]

    def own(fn: Callable[[], Any]) -> Callable[[], None]:
        def run() -> None:
            logits.grad = None
            h = fn()
            (shell_cross_entropy(h, own_t[0]) + depth_l1(h, own_t[1], own_t[2])).backward()
        return run

    rows = {
        "shell losses fwd+bwd": timed(losses, device, args.repeat),
        "+ ground truth": timed(full, device, args.repeat),
        "soft_first_hit own view": timed(own(lambda: soft_first_hit(logits, grid, grid.camera(), backend=backend,
                                                                    device=args.device)), device, args.repeat),
    }
    return {"backend": backend, "rows": rows}


def measure_torch(args: argparse.Namespace, device: str) -> dict[str, Any]:
    """The pure-torch cumprod reference of the own view."""
    labels, logits, grid = make_batch(args.size, args.batch, args.logits, device)
    logits.requires_grad_()
    loss = ShellLoss(grid, ShellLossConfig(novel_views=0, backend=args.backends[0] if args.backends else None,
                                           device=args.device))
    (own_t,) = loss.targets(labels, [grid.camera()]).groups

    def run() -> None:
        logits.grad = None
        h = soft_first_hit_own_view_torch(logits, grid)
        (shell_cross_entropy(h, own_t[0]) + depth_l1(h, own_t[1], own_t[2])).backward()

    return {"backend": "torch", "rows": {"torch cumprod own view": timed(run, device, args.repeat)}}


# ---------------------------------------------------------------------------------------------- report
def table(result: dict[str, Any]) -> str:
    """Markdown table of one run."""
    dev = "cuda" if result["device"].startswith("cuda") else "cpu"
    target = TARGETS.get((dev, result["batch"]))
    cuda = dev == "cuda"
    extra = " pipelined ms | GPU ms |" if cuda else ""
    lines = ["| backend | measurement | median ms | min ms | first call ms |" + extra + " target |",
             "| --- | --- | ---: | ---: | ---: |" + (" ---: | ---: |" if cuda else "") + " --- |"]
    for entry in result["backends"]:
        for name, r in entry["rows"].items():
            mark = ""
            if target and name == "shell losses fwd+bwd":
                mark = f"{target[0]}: {'met' if r['median_ms'] <= target[1] else 'NOT met'}"
            cells = ""
            if cuda:
                cells = (f" {r['pipelined_ms']:,.1f} | {r['gpu_ms']:,.1f} |" if "gpu_ms" in r else " | |")
            lines.append(f"| {entry['backend']} | {name} | {r['median_ms']:,.1f} | {r['min_ms']:,.1f} | "
                         f"{r['first_ms']:,.0f} |{cells} {mark} |")
    return "\n".join(lines)


def chart(result: dict[str, Any], path: Path) -> None:
    """Horizontal bar chart of the medians."""
    plt = common.pyplot()
    labels, values = [], []
    for entry in result["backends"]:
        for name, r in entry["rows"].items():
            labels.append(f"{entry['backend']}: {name}")
            values.append(r["median_ms"])
    fig, ax = plt.subplots(figsize=(8, 0.45 * len(labels) + 1.2))
    ax.barh(range(len(labels)), values, color="#4c72b0")
    ax.set_yticks(range(len(labels)), labels)
    ax.invert_yaxis()
    ax.set_xlabel("milliseconds (median, forward + backward)")
    ax.set_title(f"Shell-aware losses, B = {result['batch']}, {result['size']}^3, 7 classes, "
                 f"own view + {NOVEL} x {NOVEL_SIZE[0]}^2 ({result['logits']} logits)", fontsize=9)
    for i, v in enumerate(values):
        ax.text(v, i, f" {v:,.1f}", va="center", fontsize=8)
    common.save_figure(fig, path, dpi=110)


def section(results: list[dict[str, Any]]) -> str:
    """The BENCHMARKS.md section from every stored run."""
    out = [SECTION, "",
           "`python benchmarks/bench_losses.py`: `ShellLoss` (soft_first_hit shell cross-entropy + depth L1 + "
           "visible-weighted voxel cross-entropy) forward + backward on logits `(B, 7, 64, 64, 64)` float32, from "
           f"the grid's own view (64 x 64) plus {NOVEL} novel poses at {NOVEL_SIZE[0]} x {NOVEL_SIZE[1]}; ground "
           "truth from `fruxel/data/rooms.py` `room_volume`. *shell losses fwd+bwd* takes the ground-truth targets "
           "(`first_hit`, `shell` of the labels) as given; *+ ground truth* computes them too. *soft_first_hit own "
           "view* and *torch cumprod own view* are the same computation (own view only, shell cross-entropy + depth "
           "L1), by the kernels and by the pure-torch cumprod reference. *scene* logits are the ground truth's class "
           "raised by 4 over noise of standard deviation 1.5 (mid-training); *random* logits are standard normal. "
           "Median and minimum of the timed runs; the first call includes building or loading the kernels. On this "
           "shared 2-core machine, any other busy process stalls torch's 2-thread operations (each waits for a "
           "descheduled thread), so a run with a busy neighbour reads several times slower: the minimum is the "
           "better guide, and the load average at the start is recorded. On CUDA, *pipelined* is the time per call of "
           "back-to-back calls closed by one synchronisation, and *GPU* the summed device time of one call's "
           "kernels (CUPTI); the target is judged on the median, each call synchronised.", ""]
    for res in sorted(results, key=lambda r: (r["device"], r["batch"], r["logits"])):
        m = res["machine"]
        where = m.get("gpu") or f"{m['cpu']}, {m['cores']} cores"
        out += [f"### {where}, B = {res['batch']}, {res['logits']} logits", "",
                f"{m['date']}; device {res['device']}; torch {m['torch']} ({m['torch_threads']} threads), "
                f"warp {m.get('warp', '-')}, pyopencl {m.get('pyopencl', '-')}"
                + (f" on `{m['opencl']}`" if m.get("opencl") else "") + "; load average at start "
                f"{m['load_average']:.1f}." + (f" {res['note']}" if res.get("note") else ""), "",
                table(res), ""]
        if res.get("png"):
            out += [f"![shell-aware losses]({res['png']})", ""]
    return "\n".join(out).rstrip() + "\n"


def write_section() -> None:
    """Re-render this benchmark's section of BENCHMARKS.md from every ``benchmarks/results/losses*.json``."""
    runs = [json.loads(f.read_text()) for f in sorted(common.RESULTS.glob("losses*.json"))]
    common.replace_section(common.BENCHMARKS_MD, SECTION, section(runs))


def main(argv: list[str] | None = None) -> dict[str, Any]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--backends", nargs="+", default=None, help="available_backends() names (default: all)")
    ap.add_argument("--batch", type=int, default=2, help="B")
    ap.add_argument("--size", type=int, default=64, help="n of the n^3 grid")
    ap.add_argument("--repeat", type=int, default=5, help="timed runs per measurement")
    ap.add_argument("--logits", choices=("scene", "random"), default="scene", help="how the logits are made")
    ap.add_argument("--device", default=None, help="torch / Warp device of the data (cpu, cuda, cuda:N)")
    ap.add_argument("--out", default=None, help="prefix of the .json and .png written")
    ap.add_argument("--no-write", action="store_true", help="do not write files or BENCHMARKS.md")
    ap.add_argument("--note", default=None, help="a sentence printed under this run's heading in BENCHMARKS.md")
    ap.add_argument("--render", action="store_true",
                    help="only re-render the BENCHMARKS.md section from benchmarks/results/losses*.json (e.g. after "
                         "copying in a run made on another machine)")
    args = ap.parse_args(argv)
    if args.render:
        write_section()
        return {}
    backends = args.backends or available_backends()
    device = args.device or ("cuda" if any(b == "warp-cuda" for b in backends) else "cpu")
    if device == "cuda":
        device = f"cuda:{torch.cuda.current_device()}"
    result: dict[str, Any] = {"batch": args.batch, "size": args.size, "logits": args.logits, "device": device,
                              "note": args.note, "machine": machine(device), "backends": []}
    for b in backends:
        result["backends"].append(measure(b, args, device))
    result["backends"].append(measure_torch(args, device))
    # A Warp staged without package metadata (the GPU machine) tells its version only once imported, which the
    # measurements have done by now.
    result["machine"].update({k: v for k, v in common.package_versions({"warp": "warp-lang"}).items() if v})
    print(table(result))
    if not args.no_write:
        tag = "cuda" if device.startswith("cuda") else "cpu"
        out = Path(args.out) if args.out else common.RESULTS / f"losses-{tag}-b{args.batch}-{args.logits}"
        out.parent.mkdir(parents=True, exist_ok=True)
        png = out.with_suffix(".png")
        chart(result, png)
        # Where the files end up beside BENCHMARKS.md (a run elsewhere, e.g. into a device's $OUT, is copied there).
        result["png"] = str((common.RESULTS / png.name).relative_to(common.ROOT))
        common.write_text(out.with_suffix(".json"), json.dumps(result, indent=1))
        write_section()
        print(f"wrote {out.with_suffix('.json')}, {png} and the {SECTION!r} section of {common.BENCHMARKS_MD.name}")
    return result


if __name__ == "__main__":
    main()

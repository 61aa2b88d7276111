"""Multi-GPU training benchmark: samples per second on 1, 2, 4 ... GPUs of one host with the simulator streaming,
the scaling efficiency against one GPU at the same per-GPU batch, peak memory, and where a step's time goes.

For each GPU count N (``--gpus 1 2 4``) the script starts ``torchrun --standalone --nproc_per_node N`` of itself
(``--rank-run``): every rank trains the preset with the global batch ``N x --batch-per-gpu`` and ``--workers``
simulator processes of its own (``auto``: the host's cores less one per rank, shared out), evaluation and
checkpoints off. Each rank writes what it saw: the samples/s of every logged window, the seconds it waited for its
batches (``TrainResult.data_seconds``: what the steps' compute did not hide), its peak memory. Then, unless
``--no-profile``, a short profiled run of the same size times each phase of a step (data, forward, loss,
backward with DDP's all-reduce, optimiser; the profiler synchronises at each boundary, so it is slower).
``--sim-alone`` also times the simulator streaming alone on every rank at once (no training), which tells whether
the simulator or the GPU limits a run.

``--variants`` measures other ways of running the step beside the engine's own (``engine``: the network compiled
before DDP wraps it, its passes replayed as CUDA graphs, ``run.cuda_graphs``), each on every GPU count: ``split``
(the engine until issue 37: graphs off, the DDP-wrapped network compiled, which DDPOptimizer splits at DDP's
buckets), ``whole`` (``split`` with ``torch._dynamo.config.optimize_ddp`` off: one graph, DDP's all-reduce after the
backward), ``inside`` (the engine with graphs off) and ``gcfreeze`` (the engine with ``gc.freeze()`` after the
start-up windows: the objects made until then, most of them the compiler's, leave the garbage collector's
generations, whose collections stall one rank at a time). On one GPU ``whole`` is ``split``, so its 1-GPU row is
left out. Stored rows without a variant ran ``split``; rows named ``cudagraphs`` ran what the engine does now. Each
rank also records the time between its steps and its collections (``StepClock``): a rank that stalls makes the
others wait at the next all-reduce.

``--curves`` trains 1 GPU and N GPUs at the same global batch for ``--curve-steps`` steps and draws both loss
curves in one PNG (the DDP run must learn as the single-GPU run does).

    python benchmarks/bench_ddp.py --gpus 1 2 --preset ssz64 --steps 300 --tag h100x2 --out $OUT/ddp-h100x2
    python benchmarks/bench_ddp.py --report          # the "## Multi-GPU training" section from results/ddp-*.json

Keep NVLink multicast off on the lent multi-GPU hosts: the script sets ``NCCL_NVLS_ENABLE=0`` for every run.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

SECTION = "## Multi-GPU training"
TARGETS = {2: 0.90, 4: 0.85, 8: 0.85}
"""Scaling efficiency asked for, by GPU count (issues 37 and 40)."""


# ---------------------------------------------------------------------------------------------------- one rank
def rank_run(args: argparse.Namespace) -> None:
    """One torchrun process: train, then write this rank's numbers to ``args.json.format(rank=...)``."""
    import torch

    from fruxel.train.config import override, preset
    from fruxel.train.engine.trainer import Trainer

    world = int(os.environ.get("WORLD_SIZE", "1"))
    rank = int(os.environ.get("RANK", "0"))
    variant_run = _apply_variant(args.variant, world)
    changes = {"data": {"workers": int(args.workers), "frequency_samples": 64},
               "run": {"steps": args.steps, "batch_size": args.batch_per_gpu * world if not args.global_batch
                       else args.global_batch, "eval_every": 0, "checkpoint_every": 0, "log_every": args.log_every,
                       "tensorboard": False, "time_limit": args.time_limit,
                       **variant_run}}
    config = override(override(preset(args.preset), changes, ""), json.loads(args.override), "")
    torch.cuda.reset_peak_memory_stats() if torch.cuda.is_available() else None
    trainer = Trainer(config, args.run_dir, device="cuda" if torch.cuda.is_available() else "cpu",
                      progress=False, profile=args.profile_run, warm=args.warm, evaluation=False, overwrite=True)
    clock = StepClock(freeze_at=args.skip_windows * args.log_every if args.variant == "gcfreeze" else None)
    trainer.callbacks.append(clock)
    t = time.perf_counter()
    result = trainer.fit()
    skip = args.skip_windows * args.log_every
    out = {"rank": rank, "step_ms": clock.percentiles(skip), "gc": clock.gc_summary(skip), "world": world,
           "steps": result.step, "samples": result.samples,
           "wall_s": time.perf_counter() - t, "train_s": result.seconds, "data_s": result.data_seconds,
           "rates": trainer.rates, "timings": result.timings, "peak_memory": result.peak_memory,
           "graph_skips": result.graph_skips,
           "workers": config.data.workers, "global_batch": config.run.batch_size, "losses": _loss_rows(args.run_dir)
           if rank == 0 else []}
    Path(args.json.format(rank=rank)).write_text(json.dumps(out) + "\n", encoding="utf-8")


class StepClock:
    """A trainer callback (duck-typed) that keeps the wall time between consecutive steps and the pauses of Python's
    garbage collector in this rank: a rank whose steps stall now and then (a collection, a late batch) makes every
    other rank wait for it at the next all-reduce, so the spread of step times, not only their mean, decides how
    well N GPUs scale."""

    def __init__(self, freeze_at: int | None = None) -> None:
        import gc

        self.freeze_at = freeze_at
        """Step after which ``gc.freeze()`` moves every object made so far out of the collector's generations."""
        self.marks: list[float] = []
        self.pauses: list[tuple[int, float, int]] = []
        self._gc_start = 0.0
        gc.callbacks.append(self._on_gc)

    def _on_gc(self, phase: str, info: dict[str, int]) -> None:
        if phase == "start":
            self._gc_start = time.perf_counter()
        else:
            self.pauses.append((info["generation"], time.perf_counter() - self._gc_start, len(self.marks)))

    def on_start(self, trainer: Any) -> None:
        self.marks.append(time.perf_counter())

    def on_step(self, trainer: Any, terms: Any) -> None:
        self.marks.append(time.perf_counter())
        if self.freeze_at is not None and len(self.marks) == self.freeze_at:
            import gc

            gc.collect()
            gc.freeze()

    def on_stop(self, trainer: Any, interrupted: bool = False) -> None:
        pass

    def on_close(self, trainer: Any) -> None:
        pass

    def percentiles(self, skip: int) -> dict[str, float]:
        """Milliseconds between steps after the first ``skip`` steps: median, 90th and 99th percentile, maximum."""
        gaps = sorted(1000.0 * (b - a) for a, b in zip(self.marks[skip:], self.marks[skip + 1:], strict=False))
        if not gaps:
            return {}
        pick = lambda q: gaps[min(len(gaps) - 1, int(q * len(gaps)))]  # noqa: E731
        return {"p50": round(pick(0.5), 2), "p90": round(pick(0.9), 2), "p99": round(pick(0.99), 2),
                "max": round(gaps[-1], 2), "mean": round(statistics.fmean(gaps), 2)}

    def gc_summary(self, skip: int) -> dict[str, float]:
        """Collections after the first ``skip`` steps: how many of the oldest generation, their total and longest
        milliseconds; how many of any generation and their total milliseconds."""
        late = [(g, p) for g, p, at in self.pauses if at > skip]
        old = [p for g, p in late if g == 2]
        return {"gen2": len(old), "gen2_ms": round(1000.0 * sum(old), 1),
                "gen2_max_ms": round(1000.0 * max(old, default=0.0), 1), "all": len(late),
                "all_ms": round(1000.0 * sum(p for _, p in late), 1)}


VARIANTS = ("engine", "split", "whole", "inside", "gcfreeze")
"""Ways of running the step (see the module's docstring); ``engine`` is the trainer's own."""


def _apply_variant(variant: str, world: int) -> dict[str, Any]:
    """Set this rank's process up for ``variant``; the run config's changes it needs."""
    import torch

    from fruxel.train.engine import trainer

    if variant == "whole":
        torch._dynamo.config.optimize_ddp = False
    if variant in ("split", "whole") and world > 1:
        plain = trainer._ddp
        trainer._ddp = lambda module, ids: torch.compile(plain(module, ids))
        return {"cuda_graphs": False, "compile": False}  # compiled here, around DDP
    return {"cuda_graphs": False} if variant in ("split", "inside") else {}


def _loss_rows(run_dir: str) -> list[tuple[int, float]]:
    """``(step, total loss)`` of the run's metrics.csv."""
    import csv

    with open(os.path.join(run_dir, "metrics.csv"), newline="", encoding="utf-8") as f:
        return [(int(r["step"]), float(r["loss/total"])) for r in csv.DictReader(f) if r.get("loss/total")]


def sim_alone(args: argparse.Namespace) -> None:
    """One torchrun process without training: stream this rank's batches for ``--sim-seconds`` and write the rate."""
    import torch

    from fruxel.train.config import override, preset
    from fruxel.train.samples import SampleSource, training_batches

    world, rank = int(os.environ.get("WORLD_SIZE", "1")), int(os.environ.get("RANK", "0"))
    local = int(os.environ.get("LOCAL_RANK", "0"))
    config = override(preset(args.preset), json.loads(args.override), "")
    batches = training_batches(SampleSource.of(config.data), config.model, config.data.train_samples,
                               batch=args.batch_per_gpu, workers=int(args.workers), rank=rank, world=world,
                               device=f"cuda:{local}" if torch.cuda.is_available() else "cpu")
    marks = []
    t0 = time.perf_counter()
    try:
        while time.perf_counter() - t0 < args.sim_seconds:
            marks.append((time.perf_counter(), len(next(batches)["index"])))
    finally:
        batches.close()
    warm = marks[len(marks) // 4:]  # the first quarter holds the workers' start-up
    rate = sum(n for _, n in warm[1:]) / max(warm[-1][0] - warm[0][0], 1e-9) if len(warm) > 1 else 0.0
    Path(args.json.format(rank=rank)).write_text(json.dumps({"rank": rank, "samples_per_s": rate}) + "\n")


# ---------------------------------------------------------------------------------------------------- driver
def _torchrun(n: int, extra: list[str], folder: Path) -> list[dict[str, Any]]:
    """Run this script under torchrun on ``n`` GPUs with ``extra`` arguments; the ranks' JSON results."""
    env = {**os.environ, "NCCL_NVLS_ENABLE": "0", "TORCH_SYMM_MEM_DISABLE_MULTICAST": "1",
           "NVSHMEM_DISABLE_NVLS": "1", "OMP_NUM_THREADS": "1"}
    json_pattern = str(folder / "rank{rank}.json")
    cmd = [sys.executable, "-m", "torch.distributed.run", "--standalone", "--nproc_per_node", str(n), __file__,
           *extra, "--json", json_pattern, "--run-dir", str(folder / "run")]
    subprocess.run(cmd, check=True, env=env)
    return [json.loads(Path(json_pattern.format(rank=r)).read_text()) for r in range(n)]


def _workers(args: argparse.Namespace, n: int) -> int:
    if args.workers != "auto":
        return int(args.workers)
    return max(1, (common.usable_cores() - n) // n)


def measure(args: argparse.Namespace, n: int, variant: str = "engine") -> dict[str, Any]:
    """Throughput, data wait, peak memory and (profiled) phases of training on ``n`` GPUs, the network compiled as
    ``variant`` says."""
    workers = _workers(args, n)
    base = ["--rank-run", "--preset", args.preset, "--batch-per-gpu", str(args.batch_per_gpu), "--workers",
            str(workers), "--override", args.override, "--log-every", str(args.log_every), "--variant", variant]
    with tempfile.TemporaryDirectory() as d:
        ranks = _torchrun(n, [*base, "--steps", str(args.steps), "--time-limit", str(args.time_limit)], Path(d))
    r0 = ranks[0]
    rates = r0["rates"][args.skip_windows:]
    if not rates:
        print(f"{n} GPU(s): {r0['steps']} steps, {len(r0['rates'])} logged windows, none after the "
              f"{args.skip_windows} start-up ones: no rate (raise --time-limit or --steps)", flush=True)
    row: dict[str, Any] = {
        "gpus": n, "variant": variant, "workers_per_rank": workers, "global_batch": r0["global_batch"],
        "steps": r0["steps"],
        "windows": len(rates), "samples_per_s": statistics.median(rates) if rates else None,
        "data_wait": [round(r["data_s"] / max(r["train_s"], 1e-9), 4) for r in ranks],
        "peak_memory_gib": max(r["peak_memory"] for r in ranks) / 2**30,
        "step_ms": [r.get("step_ms", {}) for r in ranks], "gc": [r.get("gc", {}) for r in ranks],
        "graph_skips": [r.get("graph_skips", 0) for r in ranks]}
    row["per_gpu"] = row["samples_per_s"] / n if rates else None
    if args.profile:
        with tempfile.TemporaryDirectory() as d:
            prof = _torchrun(n, [*base, "--steps", str(args.profile_steps), "--time-limit", "0", "--profile-run",
                                 "--warm", str(args.warm)], Path(d))
        row["phases_ms"] = [{k: round(1000.0 * v / r["timings"]["steps"], 2) for k, v in r["timings"].items()
                             if k != "steps"} for r in prof if r["timings"].get("steps")]
    if args.sim_alone:
        with tempfile.TemporaryDirectory() as d:
            sim = _torchrun(n, ["--sim-alone", "--preset", args.preset, "--batch-per-gpu", str(args.batch_per_gpu),
                                "--workers", str(workers), "--override", args.override, "--sim-seconds",
                                str(args.sim_seconds)], Path(d))
        row["sim_alone_samples_per_s"] = sum(r["samples_per_s"] for r in sim)
    print(f"{n} GPU(s), {variant}, {workers} workers each: {_num(row['samples_per_s'])} samples/s "
          f"({_num(row['per_gpu'])} per GPU), data wait {row['data_wait']}, peak {row['peak_memory_gib']:.1f} GiB, "
          f"graphs run without CUDA graphs {row['graph_skips']}", flush=True)
    return row


def _num(value: float | None) -> str:
    """A rate for the table, or "-" where none was measured."""
    return "-" if value is None else f"{value:.0f}"


def _rate(row: dict[str, Any]) -> float | None:
    """The row's samples/s, or None where the throughput run saw no logged window past its start-up (runs stored
    before rows said how many they had: fewer than 100 steps)."""
    if row.get("windows", 1 if row["steps"] >= 100 else 0) == 0:
        return None
    return row["samples_per_s"]


def curves(args: argparse.Namespace, n: int, png: Path) -> dict[str, Any]:
    """Loss curves of 1 GPU and ``n`` GPUs at the same global batch (``n x --batch-per-gpu``)."""
    runs = {}
    for g in (1, n):
        with tempfile.TemporaryDirectory() as d:
            ranks = _torchrun(g, ["--rank-run", "--preset", args.preset, "--global-batch",
                                  str(n * args.batch_per_gpu), "--workers", str(_workers(args, g)), "--override",
                                  args.override, "--steps", str(args.curve_steps), "--log-every", "10"], Path(d))
        runs[g] = ranks[0]["losses"]
    plt = common.pyplot()
    fig, ax = plt.subplots(figsize=(7, 4))
    for g, rows in runs.items():
        ax.plot([s for s, _ in rows], [v for _, v in rows], marker="o" if len(rows) < 30 else None, ms=3,
                label=f"{g} GPU{'s' if g > 1 else ''}")
    ax.set_yscale("log")
    ax.set_xlabel("step")
    ax.set_ylabel("training loss")
    ax.set_title(f"{args.preset}, global batch {n * args.batch_per_gpu}")
    ax.legend()
    common.save_figure(fig, png, 110)
    return {str(g): rows for g, rows in runs.items()}


# ---------------------------------------------------------------------------------------------------- report
def section(runs: list[dict[str, Any]]) -> str:
    """The BENCHMARKS.md section of every stored run."""
    lines = [SECTION, "", "Written by `benchmarks/bench_ddp.py --report` from `benchmarks/results/ddp-*.json`. "
             "Efficiency: samples/s per GPU on N GPUs over samples/s on one GPU of the same host, at the same "
             "per-GPU batch; targets " + ", ".join(f"{100 * v:.0f} % at {k}" for k, v in TARGETS.items()) + ".", ""]
    for run in runs:
        lines += [f"### {run['tag']}: {run['preset']}, {run['machine'].get('gpu') or 'no GPU'}, "
                  f"{run['machine'].get('cores', '?')} cores, {run['date']}"]
        lines += ["", "| GPUs | workers per GPU | global batch | samples/s | per GPU | efficiency "
                  "| data wait (per rank) | peak memory (GiB) | simulator alone (samples/s) |",
                  "| ---: | ---: | ---: | ---: | ---: | ---: | --- | ---: | ---: |"] if run["rows"] else []
        variants = any(r.get("variant", "split") != "split" for r in run["rows"])
        for r in run["rows"]:
            rate, one = _rate(r), _one_gpu_rate(run["rows"], r.get("variant", "split"))
            per_gpu = None if rate is None else rate / r["gpus"]
            eff = f"{100 * per_gpu / one:.0f} %" if one and per_gpu is not None else "-"
            waits = ", ".join(f"{100 * w:.0f} %" for w in r["data_wait"]) if rate is not None else "-"
            sim = f"{r['sim_alone_samples_per_s']:.0f}" if "sim_alone_samples_per_s" in r else "-"
            gpus = f"{r['gpus']} ({r.get('variant', 'split')})" if variants else str(r["gpus"])
            lines.append(f"| {gpus} | {r['workers_per_rank']} | {r['global_batch']} | {_num(rate)} | "
                         f"{_num(per_gpu)} | {eff} | {waits} | {r['peak_memory_gib']:.1f} | {sim} |")
        lines += _step_spread(run["rows"], variants)
        skipped = [r for r in run["rows"] if any(r.get("graph_skips", []))]
        if skipped:
            counts = "; ".join(f"{r['gpus']} GPU(s): {', '.join(map(str, r['graph_skips']))}" for r in skipped)
            lines += ["", f"Compiled graphs run without CUDA graphs (per rank; TORCH_LOGS=cudagraphs says why): "
                      f"{counts}."]
        phases = [(r["gpus"], r["phases_ms"][0]) for r in run["rows"] if r.get("phases_ms")]
        if phases:
            names = sorted({k for _, p in phases for k in p})
            lines += ["", "Where rank 0's step goes (profiled run, ms a step; the profiler synchronises at each "
                      "phase, so these steps are slower than the rows above):", "",
                      "| GPUs | " + " | ".join(names) + " |", "| ---: |" + " ---: |" * len(names)]
            lines += [f"| {g} | " + " | ".join(f"{p.get(k, 0.0):.1f}" for k in names) + " |" for g, p in phases]
        if run.get("curves"):
            lines += ["", _curves_line(run["curves"])]
        if run.get("curves_png"):
            lines += ["", f"![loss curves]({run['curves_png']})"]
        lines += [""] + [f"- {n}" for n in run.get("notes", [])] + [""]
    return "\n".join(lines).rstrip() + "\n"


def _step_spread(rows: list[dict[str, Any]], variants: bool) -> list[str]:
    """The table of each rank's time between steps and its garbage collections (rows measured with them)."""
    timed = [r for r in rows if any(r.get("step_ms", []))]
    if not timed:
        return []
    lines = ["", "Time between steps on each rank (ms: median / 90th percentile / longest, after the start-up "
             "windows), and the collections of Python's oldest generation (count, longest ms):", "",
             "| GPUs | step ms per rank | gen-2 collections per rank |", "| ---: | --- | --- |"]
    for r in timed:
        gpus = f"{r['gpus']} ({r.get('variant', 'split')})" if variants else str(r["gpus"])
        steps = "; ".join(f"{t['p50']:.1f} / {t['p90']:.1f} / {t['max']:.0f}" if t else "-" for t in r["step_ms"])
        gcs = "; ".join(f"{g['gen2']}, {g['gen2_max_ms']:.0f}" if g else "-" for g in r["gc"])
        lines.append(f"| {gpus} | {steps} | {gcs} |")
    return lines


def _curves_line(curves: dict[str, list[tuple[int, float]]]) -> str:
    """How far the loss curves of the GPU counts in ``curves`` (``{gpus: [(step, loss)]}``) agree: each one's mean
    training loss over the last third of its steps."""
    means = {}
    for gpus, rows in sorted(curves.items(), key=lambda kv: int(kv[0])):
        last = max(s for s, _ in rows)
        means[int(gpus)] = statistics.fmean(v for s, v in rows if s > 2 * last / 3)
    one = means[min(means)]
    parts = [f"{g} GPU{'s' if g > 1 else ''} {m:.3f}" + ("" if g == min(means) else f" ({m / one:.3f} of it)")
             for g, m in means.items()]
    return "Mean training loss over the last third of the steps: " + "; ".join(parts) + "."


def _one_gpu_rate(rows: list[dict[str, Any]], variant: str) -> float | None:
    """The 1-GPU samples/s that ``variant``'s rows are compared with: its own 1-GPU row, else ``split``'s (which
    compiles one GPU's network as ``whole`` does)."""
    for name in (variant, "split"):
        rate = next((_rate(r) for r in rows if r["gpus"] == 1 and r.get("variant", "split") == name), None)
        if rate is not None:
            return rate
    return None


def report() -> None:
    runs = [json.loads(p.read_text()) for p in sorted(common.RESULTS.glob("ddp-*.json"))]
    common.replace_section(common.BENCHMARKS_MD, SECTION, section(runs))


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--gpus", type=int, nargs="+", default=[1, 2])
    p.add_argument("--preset", default="ssz64")
    p.add_argument("--override", default="{}", help="JSON config overrides of every run")
    p.add_argument("--batch-per-gpu", type=int, default=32)
    p.add_argument("--global-batch", type=int, default=0, help=argparse.SUPPRESS)
    p.add_argument("--workers", default="auto", help="simulator processes per rank (auto: cores shared out)")
    p.add_argument("--variants", nargs="+", choices=VARIANTS, default=["engine"],
                   help="ways of running the step to measure (engine: the trainer's own)")
    p.add_argument("--variant", choices=VARIANTS, default="engine", help=argparse.SUPPRESS)
    p.add_argument("--steps", type=int, default=300, help="steps of each throughput run (0: none, e.g. --curves only)")
    p.add_argument("--time-limit", type=float, default=0.0, help="seconds a throughput run may train (0: none)")
    p.add_argument("--log-every", type=int, default=20)
    p.add_argument("--skip-windows", type=int, default=3, help="logged windows left out (compile, start-up)")
    p.add_argument("--no-profile", dest="profile", action="store_false")
    p.add_argument("--profile-steps", type=int, default=80)
    p.add_argument("--warm", type=int, default=40, help="steps left out of the profile")
    p.add_argument("--sim-alone", action="store_true")
    p.add_argument("--sim-seconds", type=float, default=60.0)
    p.add_argument("--curves", action="store_true")
    p.add_argument("--curve-steps", type=int, default=300)
    p.add_argument("--tag", default="local")
    p.add_argument("--note", action="append", default=[])
    p.add_argument("--out", default=None, help="PREFIX of PREFIX.json and PREFIX-curves.png (default results/ddp-TAG)")
    p.add_argument("--report", action="store_true", help="only re-render BENCHMARKS.md from the stored results")
    p.add_argument("--rank-run", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--profile-run", action="store_true", help=argparse.SUPPRESS)
    p.add_argument("--json", default="", help=argparse.SUPPRESS)
    p.add_argument("--run-dir", default="", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.report:
        report()
        return 0
    if args.rank_run:
        rank_run(args)
        return 0
    if args.sim_alone and args.json:
        sim_alone(args)
        return 0
    out = Path(args.out) if args.out else common.RESULTS / f"ddp-{args.tag}"
    result: dict[str, Any] = {"tag": args.tag, "preset": args.preset, "override": json.loads(args.override),
                              "date": time.strftime("%Y-%m-%d"), "notes": args.note,
                              "machine": {"gpu": common.gpu_name(), "cores": common.usable_cores(),
                                          "cpu": common.cpu_description()},
                              "rows": []}
    # Written again after each GPU count, so that a run cut short (a lent machine's time limit) keeps what it measured.
    for variant, n in ((v, n) for v in args.variants for n in args.gpus if args.steps > 0):
        if n == 1 and variant == "whole":
            continue  # on one GPU it compiles the network as split does
        result["rows"].append(measure(args, n, variant))
        common.write_text(Path(f"{out}.json"), json.dumps(result, indent=2) + "\n")
    if args.curves and max(args.gpus) > 1:
        png = Path(f"{out}-curves.png")
        result["curves"] = curves(args, max(args.gpus), png)
        result["curves_png"] = f"benchmarks/results/{png.name}"
        common.write_text(Path(f"{out}.json"), json.dumps(result, indent=2) + "\n")
    print(f"wrote {out}.json")
    return 0


if __name__ == "__main__":
    sys.exit(main())

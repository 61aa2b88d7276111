"""Plumbing shared by the benchmark scripts: where results go, what machine they ran on, timing a call, saving
a chart, and how each script rewrites its own section of BENCHMARKS.md.

The scripts run as ``python benchmarks/NAME.py`` (``benchmarks/`` is not a package) and import this module
with their own folder put first on ``sys.path``. The package (``fruxel.render``
included) never imports it.
"""

from __future__ import annotations

import datetime as dt
import importlib
import json
import os
import platform
import re
import statistics
import subprocess
import sys
import time
from collections.abc import Callable, Iterable, Mapping
from importlib import metadata
from pathlib import Path
from typing import Any

from fruxel.io import atomic_path, atomic_write
from fruxel.render.markdown import replace_markdown_section

ROOT = Path(__file__).resolve().parents[1]
"""The source checkout."""
BENCHMARKS_MD = ROOT / "BENCHMARKS.md"
"""The file of measured results; each script owns one ``## `` section of it."""
RESULTS = ROOT / "benchmarks" / "results"
"""JSON results and charts of the benchmarks."""

_NEW_FILE = "# Benchmarks\n\nMeasured results of the benchmarks in `benchmarks/`.\n"


# ---------------------------------------------------------------------------------------------- machine
def cpu_model() -> str:
    """The CPU's model name from ``lscpu``, else :mod:`platform`'s (e.g. ``"AMD EPYC 7B13"``)."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        out = ""
    m = re.search(r"^Model name:\s*(.+)$", out, re.MULTILINE)
    return m.group(1).strip() if m else platform.processor() or platform.machine()


def cpu_id() -> str:
    """The CPU's vendor family and model numbers and its widest vector extension, from ``lscpu`` (e.g.
    ``"family 25 model 17, AVX-512"``): what decides which LLVM (so which PoCL) knows the CPU, and the OpenCL walk's
    width. Empty when ``lscpu`` says nothing."""
    try:
        out = subprocess.run(["lscpu"], capture_output=True, text=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError):
        return ""
    family = re.search(r"^CPU family:\s*(\d+)$", out, re.MULTILINE)
    model = re.search(r"^Model:\s*(\d+)$", out, re.MULTILINE)
    found = re.search(r"^Flags:\s*(.+)$", out, re.MULTILINE)
    flags = set(found.group(1).split()) if found else set()
    vector = "AVX-512" if "avx512f" in flags else ("AVX2" if "avx2" in flags else "")
    parts = [f"family {family.group(1)} model {model.group(1)}" if family and model else "", vector]
    return ", ".join(p for p in parts if p)


def usable_cores() -> int:
    """The cores this process may run on (its CPU affinity where the platform has one, else all of them)."""
    if hasattr(os, "sched_getaffinity"):
        return len(os.sched_getaffinity(0))
    return os.cpu_count() or 1


def cpu_description() -> str:
    """``"MODEL, N cores"``: :func:`cpu_model` and :func:`usable_cores`."""
    return f"{cpu_model()}, {usable_cores()} cores"


def gpu_name() -> str | None:
    """The first NVIDIA GPU's name from ``nvidia-smi`` (e.g. ``"NVIDIA H100 80GB HBM3"``), or None."""
    try:
        out = subprocess.run(["nvidia-smi", "--query-gpu=name", "--format=csv,noheader"], capture_output=True,
                             text=True, check=True, timeout=30).stdout.strip()
    except (OSError, subprocess.CalledProcessError, subprocess.TimeoutExpired):
        return None
    return out.splitlines()[0] if out else None


def load_average() -> float:
    """The 1-minute load average, NaN where the platform has none. On the shared machines a load above the core
    count means the timings are pessimistic, so every run records it."""
    return os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")


def package_versions(names: Iterable[str] | Mapping[str, str]) -> dict[str, str | None]:
    """Installed versions of distributions, None for those missing. Reads the installed metadata, so nothing is
    imported (importing warp or torch would cost seconds and print), except for a package without metadata (a Warp
    copied onto the GPU machine without its package files): it is imported for its own version attribute then.

    Args:
        names: distribution names, e.g. ``("numpy", "warp-lang")``; or a mapping from the key wanted in the
            result to the distribution name, e.g. ``{"warp": "warp-lang"}``.

    Returns:
        Version by name (or by key), in the order given.
    """
    pairs = names.items() if isinstance(names, Mapping) else ((n, n) for n in names)
    out: dict[str, str | None] = {}
    for key, dist in pairs:
        try:
            out[key] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[key] = _imported_version(dist)
    return out


_MODULES = {"warp-lang": ("warp", "config.version"), "torch": ("torch", "__version__")}
"""Distributions whose module can say its version when no metadata is installed: (module, attribute path)."""


def _imported_version(dist: str) -> str | None:
    """The version the module reports (imported here when it is not yet: only a copy without metadata gets here,
    the GPU machine's Warp, whose results said "Warp None" while the module was still unimported), or None."""
    name, attr = _MODULES.get(dist, (None, None))
    if name and name not in sys.modules:
        try:
            importlib.import_module(name)
        except ImportError:
            return None
    value = sys.modules.get(name) if name else None
    for part in (attr or "").split("."):
        value = getattr(value, part, None)
    return str(value) if value is not None else None


def machine_info(packages: Iterable[str] | Mapping[str, str] = ()) -> dict[str, Any]:
    """What a run was measured on, as stored in the results JSON.

    Args:
        packages: distributions whose versions to record (see :func:`package_versions`).

    Returns:
        ``{"date": ISO date, "cpu": model, "cores": int, "gpu": name or None, "python": version,
        "load_average": 1-minute load at the call, "versions": {name: version or None}}``.
    """
    return {
        "date": dt.date.today().isoformat(),
        "cpu": cpu_model(),
        "cores": usable_cores(),
        "gpu": gpu_name(),
        "python": platform.python_version(),
        "load_average": load_average(),
        "versions": package_versions(packages),
    }


def opencl_device() -> dict[str, Any]:
    """The OpenCL device fruxel's calls run on by default, and every candidate's probe result
    (:mod:`fruxel.kernels.cl.runtime`): ``{"opencl_device": name, "opencl_platform": e.g. "OpenCL 3.0 PoCL
    3.1+debian", "opencl_driver": version, "opencl_devices_probed": ["name (platform): works" or the failure]}``;
    empty where OpenCL does not run."""
    try:
        from fruxel.kernels.cl import runtime

        rt = runtime.get_runtime(None)
        return {"opencl_device": rt.device.name.strip(), "opencl_platform": runtime.platform_version(rt.device),
                "opencl_driver": rt.device.driver_version,
                "opencl_devices_probed": [f"{st.description}: {'works' if st.error is None else st.error}"
                                          for st in runtime.device_report()]}
    except Exception:  # noqa: BLE001 - no OpenCL here, whatever the reason
        return {}


# ---------------------------------------------------------------------------------------------- timing, charts
def time_calls(fn: Callable[[], Any], repeat: int, sync: Callable[[], Any] | None = None,
               warmup: int = 0) -> dict[str, float]:
    """Wall time of ``fn()`` in milliseconds: the first call on its own (it may compile or load kernels), then,
    after ``warmup`` untimed calls, the median and minimum of ``repeat`` timed calls.

    Args:
        fn: the work to time; called ``1 + warmup + repeat`` times.
        repeat: timed calls (at least 1).
        sync: waits for the device's queued work (e.g. ``torch.cuda.synchronize``); called before the first call
            and after every call, so that each time covers the work itself. None for synchronous work.
        warmup: untimed calls between the first and the timed ones.

    Returns:
        ``{"first_ms", "median_ms", "min_ms", "runs"}`` (``runs`` = ``repeat``).
    """
    wait = sync or (lambda: None)
    wait()
    t0 = time.perf_counter()
    fn()
    wait()
    first = (time.perf_counter() - t0) * 1e3
    for _ in range(warmup):
        fn()
        wait()
    runs = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        wait()
        runs.append((time.perf_counter() - t0) * 1e3)
    return {"first_ms": first, "median_ms": statistics.median(runs), "min_ms": min(runs), "runs": len(runs)}


def pipelined_ms(fn: Callable[[], Any], repeat: int, sync: Callable[[], Any]) -> dict[str, float]:
    """Back-to-back calls of ``fn`` closed by one ``sync``: milliseconds per call, and the host's share (the time
    to issue a call, measured before the synchronisation). A render or training loop that never waits runs at
    the first; when the two are close, the host is the bottleneck."""
    sync()  # the device is idle when the clock starts
    t0 = time.perf_counter()
    for _ in range(repeat):
        fn()
    t1 = time.perf_counter()
    sync()  # every queued call is done when the clock stops
    t2 = time.perf_counter()
    return {"pipelined_ms": (t2 - t0) / repeat * 1e3, "host_ms": (t1 - t0) / repeat * 1e3}


def cuda_kernel_ms(fn: Callable[[], Any], calls: int = 10) -> tuple[float, list[tuple[str, float, int]]]:
    """Summed device time of one call's kernels and copies (torch's profiler, CUPTI), milliseconds, and the
    kernels by device time per call ``(name, ms, launches)``; needs torch with CUDA."""
    from collections import defaultdict

    import torch
    from torch.autograd import DeviceType
    from torch.profiler import ProfilerActivity, profile

    torch.cuda.synchronize()  # earlier work stays out of the profile
    with profile(activities=[ProfilerActivity.CPU, ProfilerActivity.CUDA]) as prof:
        for _ in range(calls):
            fn()
        torch.cuda.synchronize()  # every kernel of the calls ends inside the profile
    per: dict[str, list[float]] = defaultdict(list)
    for e in prof.events():
        if e.device_type == DeviceType.CUDA:
            per[e.name].append(e.device_time / 1e3)  # us -> ms
    rows = sorted(((name, sum(v) / calls, len(v) // calls) for name, v in per.items()), key=lambda r: -r[1])
    return sum(r[1] for r in rows), rows


def pyplot() -> Any:
    """``matplotlib.pyplot`` on the Agg backend (charts go to files, and the machines have no display); imported
    on first use, so that scripts run without matplotlib until they draw."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def save_figure(fig: Any, path: Path, dpi: int) -> None:
    """Lay out a matplotlib figure, write it to ``path`` (format by suffix, folder made, written atomically with
    :func:`fruxel.io.atomic_path`) and close it."""
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=dpi)
    finally:
        pyplot().close(fig)


def write_text(path: Path, text: str) -> None:
    """Write a result file (JSON) atomically (:func:`fruxel.io.atomic_write`), making its folder: an interrupted
    run leaves the previous results whole, and BENCHMARKS.md is rebuilt from them."""
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_write(path, "w") as f:
        f.write(text)


# ---------------------------------------------------------------------------------------------- BENCHMARKS.md
def replace_section(path: Path, heading: str, text: str) -> None:
    """Replace the ``heading`` section of BENCHMARKS.md-like ``path`` with ``text``, or append it
    (:func:`fruxel.render.markdown.replace_markdown_section`; a missing file gets this folder's title)."""
    replace_markdown_section(path, heading, text, new_file=_NEW_FILE)


def write_result(result: dict[str, Any], out: Path, chart: Callable[[dict[str, Any], Path], Any], pattern: str,
                 heading: str, section: Callable[[list[dict[str, Any]]], str]) -> None:
    """Write one benchmark run: ``out.png`` by ``chart`` (its path stored in ``result["chart"]``, relative to the
    repository when inside it), ``out.json``, then the ``heading`` section of BENCHMARKS.md rebuilt by ``section``
    from every result file of :data:`RESULTS` matching ``pattern`` (this run's and earlier machines')."""
    png = out.with_suffix(".png")
    chart(result, png)
    try:
        result["chart"] = str(png.resolve().relative_to(ROOT))
    except ValueError:
        result["chart"] = str(png)
    write_text(out.with_suffix(".json"), json.dumps(result, indent=1, default=str))
    files = sorted(RESULTS.glob(pattern))
    replace_section(BENCHMARKS_MD, heading, section([json.loads(f.read_text()) for f in files]))
    print(f"wrote {out.with_suffix('.json')}, {png} and the {heading!r} section of {BENCHMARKS_MD.name}")



# ------------------------------------------------------------------------- runs of one Warp device (bvh, rays)
def add_device_run_options(p: Any) -> None:
    """The options of a script that measures one Warp device and stores one JSON per run: ``--device``, ``--tag``,
    ``--note``, ``--no-write``, ``--json``, ``--report`` (read back by :func:`device_run` and
    :func:`finish_device_run`)."""
    p.add_argument("--device", default="cpu", help="Warp device: cpu (default) or cuda:N")
    p.add_argument("--tag", default=None, help="result name (default: the device kind)")
    p.add_argument("--note", action="append", default=[])
    p.add_argument("--no-write", action="store_true", help="write the results only, not BENCHMARKS.md")
    p.add_argument("--json", default=None, help="also copy the JSON here")
    p.add_argument("--report", action="store_true", help="only rebuild the section from the stored results")


def device_run(args: Any, results: list[dict[str, Any]]) -> dict[str, Any]:
    """The stored form of a run: tag (``--tag``, else ``cpu`` / ``cuda``), date, device, notes, machine
    (CPU, GPU, Warp and numpy versions) and ``results``."""
    info = machine_info({"warp": "warp-lang", "numpy": "numpy"})
    tag = args.tag or ("cuda" if args.device.startswith("cuda") else "cpu")
    return {"tag": tag, "date": dt.date.today().isoformat(), "device": args.device, "notes": args.note,
            "machine": {"cpu": cpu_description(), "gpu": info["gpu"] or "", **info["versions"]}, "results": results}


def device_run_line(run: dict[str, Any], extra: str = "") -> str:
    """The Markdown bullet that says where a :func:`device_run` ran (``extra``: more to say, e.g. its picture)."""
    m = run["machine"]
    gpu = f", {m['gpu']}" if m.get("gpu") else ""
    return (f"- **{run['tag']}**: {m['cpu']}{gpu}; device {run['device']}; run {run['date']}; Warp {m.get('warp')}"
            f"{'; ' + extra if extra else ''}.")


def with_notes(lines: list[str], runs: list[dict[str, Any]]) -> str:
    """A section's ``lines`` and then every run's notes as bullets, as one text ending in a newline."""
    notes = [n for run in runs for n in run.get("notes", [])]
    return "\n".join(lines + ([""] + [f"- {n}" for n in notes] if notes else [])) + "\n"


def finish_device_run(args: Any, run: dict[str, Any] | None, prefix: str, heading: str,
                      section: Callable[[list[dict[str, Any]]], str]) -> None:
    """Store ``run`` (None with ``--report``) as ``RESULTS/{prefix}-{tag}.json`` (and ``--json``), then, unless
    ``--no-write``, rebuild the ``heading`` section of BENCHMARKS.md from every ``{prefix}-*.json``."""
    if run is not None:
        text = json.dumps(run, indent=1)
        write_text(RESULTS / f"{prefix}-{run['tag']}.json", text)
        if args.json:
            write_text(Path(args.json), text)
        print(text)
        if args.no_write:
            return
    runs = [json.loads(f.read_text()) for f in sorted(RESULTS.glob(f"{prefix}-*.json"))]
    replace_section(BENCHMARKS_MD, heading, section(runs))
    print(section(runs))

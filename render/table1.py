"""Table 1 of the paper, reproduced and extended: display frame rate when the model changes every frame.

Setting: a live network (SSZ) outputs a new fruxel volume every frame, and the viewer shows it. Each frame
therefore gets a new tensor, and a frame costs everything from that tensor to pixels read back on the host:

* mesh rows (pyrender): **build** = shell kernel (none for the baseline), labels to the host, trapezoid mesh
  (:func:`fruxel.mesh.mesh_labels`) and the pyrender mesh (baked ``"lit"`` shading, :mod:`fruxel.render.scene`);
  **upload** = copy to the GPU (freeing the last frame's mesh); **draw** = ``OffscreenRenderer.render``, which
  finishes the frame and reads the colour and depth buffers back;
* ray-cast rows: **build** = ``first_hit`` from the viewing camera (synchronised), **draw** = per-pixel shading
  on the hits' device and the image's copy to the host. There is no mesh and no upload.

Rows: no simplification (every occupied cell as a hexahedron, the paper's baseline); the VMS shell from the
grid's own view as hexahedra (the paper's method), and with culled and greedy meshing; direct ray casting with
each backend. Columns: triangles, build / upload / draw ms (means over the frames), frame ms and FPS end to end,
the ratio to no simplification, and the FPS of an unchanging model (mesh rows: draw only; ray-cast rows: kernel
and shading again, since the kernel is the draw).

Frames: frame ``f`` is the base model rolled by ``f`` columns along ``i`` (``np.roll``), made before timing: a
new tensor every frame with the same content, so nothing can be cached while meshes keep their size. The slow
baseline gets fewer frames than the fast rows. On a CUDA device the frames are torch tensors on the GPU, as a
network's output would be; the kernels read them in place.

Model: :func:`fruxel.data.rooms.room_volume`, the model of the other benchmarks: the bundled sample room's layout
on an N^3 grid, filled with seeded random furniture and sculptures up to the wanted occupancy.

Results: a printed table, ``table1.json`` (runs keyed by machine, so the CPU and GPU runs sit side by side),
``table1.png`` (bar chart of FPS, log scale) and the "## Visualisation (Table 1)" section of BENCHMARKS.md.
"""

from __future__ import annotations

import datetime as dt
import importlib.util
import json
import os
import platform
import time
from dataclasses import asdict, dataclass, field, replace
from pathlib import Path
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.classes import DEFAULT_CLASSES, ClassTable
from fruxel.data import rooms
from fruxel.grid import FruxelGrid
from fruxel.io import atomic_path, atomic_write

from .frames import DEFAULT_SIZE
from .markdown import replace_markdown_section

SECTION = "## Visualisation (Table 1)"
"""Heading of this benchmark's section in BENCHMARKS.md."""
PAPER = {"baseline_fps": 1.0 / 30.0, "vms_fps": 14.0, "ratio": 420.0}
"""The paper's Table 1: no simplification at 1/30 FPS, the VMS shell at 14 FPS, 420 times faster."""
TARGET_RATIO = 1000.0
"""The issue's target: the best path at least this many times faster than no simplification, end to end."""
TARGET_SHELL_FPS = 30.0
"""The issue's target for shell + greedy mesh + draw in pyrender on the H100, per-frame model updates."""



@dataclass(frozen=True)
class Table1Config:
    """What Table 1 measures and how long."""

    n: int = 128
    """Edge of the generated N^3 model (ignored when a model is given)."""
    occupancy: float = 0.25
    """Share of occupied cells of the generated model."""
    seed: int = 0
    """Seed of the generated model."""
    size: tuple[int, int] = DEFAULT_SIZE
    """Viewing image ``(width, height)`` in pixels, for every row."""
    frames: int = 30
    """Timed frames of each fast row."""
    baseline_frames: int = 2
    """Timed frames of the no-simplification row (seconds each)."""
    backend: str | None = None
    """Backend of the shell kernel in the mesh rows; None for the best available."""
    device: str | None = None
    """Device of the frames and of Warp: ``"cpu"`` or ``"cuda[:N]"``; None: ``"cuda"`` where Warp finds a CUDA
    device, else the CPU."""
    raycast_backends: tuple[str, ...] = ("warp", "opencl")
    """One ray-cast row per entry: ``"warp"``, ``"opencl"`` or a name such as ``"warp-cuda"``."""
    shell: str = "own"
    """Shell source of the VMS rows: ``"own"`` (the grid's own view, the paper's) or ``"poses"``."""


@dataclass
class Row:
    """One line of Table 1 (times are means over the timed frames, milliseconds)."""

    name: str
    """What the row measures."""
    kind: str
    """``"mesh"`` or ``"raycast"``."""
    frames: int = 0
    """Timed frames."""
    triangles: float | None = None
    """Mean triangles per frame (None for ray casting)."""
    build_ms: float | None = None
    """Mesh rows: shell + mesh + pyrender mesh. Ray-cast rows: ``first_hit``."""
    upload_ms: float | None = None
    """Mesh rows: copy of the new mesh to the GPU."""
    draw_ms: float | None = None
    """Mesh rows: render and read back. Ray-cast rows: shading and copy of the image to the host."""
    frame_ms: float | None = None
    """Whole frame, end to end."""
    fps: float | None = None
    """``1000 / frame_ms``: frames per second with a new model every frame."""
    ratio: float | None = None
    """``fps`` over the no-simplification row's."""
    static_fps: float | None = None
    """Frames per second of an unchanging model."""
    note: str = ""
    """Why a row has no numbers, or what else to know."""


@dataclass
class Table1Result:
    """A whole run on one machine."""

    machine: dict[str, Any]
    """CPU, cores, GL renderer, GPU, date and versions."""
    config: dict[str, Any]
    """The :class:`Table1Config` used, as a dict."""
    model: dict[str, Any]
    """Grid, occupied cells and triangles of the full mesh."""
    rows: list[Row] = field(default_factory=list)
    """The table."""


# ---------------------------------------------------------------------------------------------------- model
def benchmark_model(cfg: Table1Config) -> tuple[np.ndarray, FruxelGrid, str]:
    """The base labels ``(D, H, W)`` uint8, their grid and a description of where they came from."""
    labels, grid = rooms.room_volume(n=cfg.n, occupancy=cfg.occupancy, seed=cfg.seed)
    return np.ascontiguousarray(labels, dtype=np.uint8), grid, "fruxel.data.rooms.room_volume"


def benchmark_camera(grid: FruxelGrid, size: tuple[int, int]) -> Camera:
    """The viewing camera: :func:`fruxel.data.rooms.oblique_camera`, as in the kernel benchmark."""
    return rooms.oblique_camera(grid, size)


def make_frames(labels: np.ndarray, n: int, device: str | None) -> list[Any]:
    """``n`` per-frame volumes: ``labels`` rolled by ``f`` columns for frame ``f``, on ``device``."""
    frames = [np.ascontiguousarray(np.roll(labels, f, axis=2)) for f in range(n)]
    if device is not None and device.startswith("cuda"):
        import torch

        frames = [torch.from_numpy(f).to(device) for f in frames]
    return frames


# ---------------------------------------------------------------------------------------------------- timing
def _sync(device: str | None) -> None:
    if device is not None and device.startswith("cuda"):
        import torch

        torch.cuda.synchronize(device)


def _shell_cameras(grid: FruxelGrid, shell: str) -> Any:
    from fruxel.kernels import orbit_cameras

    return grid.camera() if shell == "own" else orbit_cameras(grid)


def measure_mesh_row(
    name: str,
    frames: list[Any],
    grid: FruxelGrid,
    classes: ClassTable,
    camera: Camera,
    meshing: str,
    cfg: Table1Config,
    shell: str | None,
) -> Row:
    """Time a pyrender row: per frame build (shell, mesh, pyrender mesh), upload and draw.

    Args:
        name: row label.
        frames: per-frame label volumes (numpy, or torch on the device).
        grid, classes: the model's grid and classes.
        camera: the viewing camera.
        meshing: ``"full"``, ``"culled"`` or ``"greedy"``.
        cfg: backend and device of the shell kernel.
        shell: ``"own"`` / ``"poses"`` for a VMS row, None for no simplification.
    """
    from fruxel import kernels
    from fruxel.mesh import mesh_labels

    from .raycast import to_numpy
    from .scene import MeshStyle, MeshView

    palette = classes.palette()
    cams = None if shell is None else _shell_cameras(grid, shell)
    view = MeshView(grid, MeshStyle(shading="lit"))
    view.set_camera(camera)
    build, upload, draw, tris = [], [], [], []
    for vol in frames:
        t0 = time.perf_counter()
        if cams is not None:
            vol = kernels.shell(vol, grid, cams, backend=cfg.backend, device=cfg.device)
            _sync(cfg.device)
        lab = to_numpy(vol)
        mesh = mesh_labels(lab, grid, palette, mode=meshing)
        view.set_mesh(mesh)
        t1 = time.perf_counter()
        view.upload()
        t2 = time.perf_counter()
        view.render()
        t3 = time.perf_counter()
        build.append(t1 - t0)
        upload.append(t2 - t1)
        draw.append(t3 - t2)
        tris.append(mesh.n_faces)
    static = []
    for _ in range(len(frames)):
        t0 = time.perf_counter()
        view.render()
        static.append(time.perf_counter() - t0)
    view.set_mesh(mesh_labels(np.zeros(grid.shape, np.uint8), grid, palette))
    view.upload()
    frame = np.add(np.add(build, upload), draw)
    return Row(name=name, kind="mesh", frames=len(frames), triangles=float(np.mean(tris)),
               build_ms=1e3 * float(np.mean(build)), upload_ms=1e3 * float(np.mean(upload)),
               draw_ms=1e3 * float(np.mean(draw)), frame_ms=1e3 * float(np.mean(frame)),
               fps=1.0 / float(np.mean(frame)), static_fps=1.0 / float(np.mean(static)))


def measure_raycast_row(
    name: str, frames: list[Any], grid: FruxelGrid, classes: ClassTable, camera: Camera, backend: str,
    device: str | None,
) -> Row:
    """Time a ray-cast row: per frame ``first_hit`` (build) and shading to a host image (draw)."""
    from .raycast import RaycastStyle, first_hits, shade

    palette = classes.palette()
    style = RaycastStyle()

    def one(vol: Any) -> tuple[float, float]:
        t0 = time.perf_counter()
        hits = first_hits(vol, grid, camera, backend=backend, device=device)
        _sync(device)
        t1 = time.perf_counter()
        shade(hits, camera, palette, style)
        return t1 - t0, time.perf_counter() - t1

    one(frames[0])
    times = np.array([one(v) for v in frames])
    static = np.array([one(frames[-1]) for _ in frames])
    frame = times.sum(axis=1)
    return Row(name=name, kind="raycast", frames=len(frames), build_ms=1e3 * float(times[:, 0].mean()),
               draw_ms=1e3 * float(times[:, 1].mean()), frame_ms=1e3 * float(frame.mean()),
               fps=1.0 / float(frame.mean()), static_fps=1.0 / float(static.sum(axis=1).mean()))


def _backend_args(name: str, device: str | None) -> tuple[str, str | None]:
    from fruxel.kernels.registry import split_name

    base, dev = split_name(name)
    return base, dev if dev is not None else (device if base == "warp" else None)


def machine_info(device: str | None) -> dict[str, Any]:
    """CPU model, cores, GL renderer, GPU (for CUDA runs), date and package versions."""
    from .scene import gl_renderer_name

    cpu = platform.processor() or platform.machine()
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    except OSError:
        pass
    info: dict[str, Any] = {
        "cpu": cpu,
        "cores": len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count(),
        "gl_renderer": gl_renderer_name(),
        "date": dt.date.today().isoformat(),
        "python": platform.python_version(),
        "numpy": np.__version__,
    }
    for mod in ("pyrender", "warp", "pyopencl", "torch"):
        try:
            info[mod] = __import__(mod).__version__
        except Exception:  # noqa: BLE001 - a missing or broken optional package only leaves out its version
            continue
    if device is not None and device.startswith("cuda"):
        import torch

        info["gpu"] = torch.cuda.get_device_name(device)
    return info


def machine_tag(info: dict[str, Any]) -> str:
    """Short key of a machine in ``table1.json``: the GPU, or the GL renderer and the core count."""
    if "gpu" in info:
        return str(info["gpu"])
    gl = str(info["gl_renderer"]).split(" (")[0].split("/")[0]
    return f"{gl}, {info['cores']} cores"


def run(cfg: Table1Config, model: tuple[Any, FruxelGrid, ClassTable] | None = None, log: Any = print) -> Table1Result:
    """Measure Table 1.

    Args:
        cfg: sizes, frames, backends.
        model: ``(labels (D, H, W) uint8, grid, classes)`` to use instead of the generated room.
        log: called with progress lines (``print`` by default).

    Returns:
        The machine description, the model's statistics and the rows, the baseline first.
    """
    from fruxel import kernels
    from fruxel.mesh import mesh_labels

    from .scene import MeshStyle, MeshView

    if cfg.device is None and "warp-cuda" in kernels.available_backends():
        # The best available device, as a live network's output would sit there; numpy frames would keep every
        # kernel on the CPU.
        cfg = replace(cfg, device="cuda")
    if model is None:
        labels, grid, source = benchmark_model(cfg)
        classes = DEFAULT_CLASSES
    else:
        labels, grid, classes = model
        source = "given model"
    labels = np.ascontiguousarray(labels, dtype=np.uint8)
    camera = benchmark_camera(grid, cfg.size)
    n_fast = max(cfg.frames, cfg.baseline_frames)
    frames = make_frames(labels, n_fast, cfg.device)
    info = machine_info(cfg.device)
    log(f"Table 1 on {machine_tag(info)}: {grid.width}x{grid.height}x{grid.depth} model, "
        f"{int(np.count_nonzero(labels))} occupied cells, {cfg.size[0]}x{cfg.size[1]} images")
    # Shader compilation and kernel JIT happen once per process; keep them out of every row.
    warm = MeshView(grid, MeshStyle(shading="lit"))
    warm.set_camera(camera)
    small = np.zeros_like(labels)
    small[:, : max(1, grid.height // 8)] = labels[:, : max(1, grid.height // 8)]
    warm.set_mesh(mesh_labels(small, grid, classes.palette(), mode="greedy"))
    warm.render()
    kernels.shell(frames[0], grid, grid.camera(), backend=cfg.backend, device=cfg.device)
    result = Table1Result(machine=info, config=asdict(cfg), model={
        "source": source, "grid": grid.to_dict(), "occupied": int(np.count_nonzero(labels)),
        "full_triangles": 12 * int(np.count_nonzero(labels)),
    })
    shell_name = "own view" if cfg.shell == "own" else "6 poses"
    plan = [
        ("no simplification: every cell as a hexahedron (paper's baseline)", "full", None, cfg.baseline_frames),
        (f"VMS shell ({shell_name}) as hexahedra (paper's method)", "full", cfg.shell, n_fast),
        (f"VMS shell ({shell_name}), culled mesh", "culled", cfg.shell, n_fast),
        (f"VMS shell ({shell_name}), greedy mesh", "greedy", cfg.shell, n_fast),
    ]
    for name, meshing, shell, n in plan:
        log(f"  {name} ({n} frames) ...")
        row = measure_mesh_row(name, frames[:n], grid, classes, camera, meshing, cfg, shell)
        result.rows.append(row)
    for b in cfg.raycast_backends:
        name = f"ray cast, first_hit on {b}"
        try:
            base, dev = _backend_args(b, cfg.device)
            kernels.get_backend(base)
        except (kernels.BackendUnavailable, kernels.BackendError) as e:
            result.rows.append(Row(name=name, kind="raycast", note=f"unavailable: {e}"))
            continue
        log(f"  {name} ({n_fast} frames) ...")
        result.rows.append(measure_raycast_row(name, frames, grid, classes, camera, base, dev))
    base_fps = result.rows[0].fps
    for row in result.rows:
        if row.fps is not None and base_fps:
            row.ratio = row.fps / base_fps
    return result


# ---------------------------------------------------------------------------------------------------- output
def _fmt(v: float | None, digits: int = 1) -> str:
    if v is None:
        return "-"
    if v >= 100:
        return f"{v:,.0f}"
    if v >= 10 or digits == 0:
        return f"{v:.{max(digits - 1, 0)}f}" if digits else f"{v:.0f}"
    return f"{v:.{digits + 1}f}" if v < 1 else f"{v:.{digits}f}"


HEADER = ("method", "triangles", "build ms", "upload ms", "draw ms", "frame ms", "FPS", "x no simpl.", "static FPS")


def table_rows(result: Table1Result) -> list[tuple[str, ...]]:
    """The table's cells as strings, one tuple per row (the paper's row last)."""
    out = []
    for r in result.rows:
        if r.fps is None:
            out.append((r.name, "-", "-", "-", "-", "-", "unavailable" if r.note else "-", "-", "-"))
            continue
        out.append((r.name, "-" if r.triangles is None else f"{r.triangles:,.0f}", _fmt(r.build_ms),
                    _fmt(r.upload_ms), _fmt(r.draw_ms), _fmt(r.frame_ms), _fmt(r.fps, 2),
                    f"{r.ratio:,.0f}x" if r.ratio and r.ratio >= 10 else f"{r.ratio:.1f}x", _fmt(r.static_fps, 2)))
    out.append(("paper, Table 1: no simplification -> VMS shell", "-", "-", "-", "-", "-",
                f"{PAPER['baseline_fps']:.3f} -> {PAPER['vms_fps']:.0f}", f"{PAPER['ratio']:.0f}x", "-"))
    return out


def format_table(result: Table1Result) -> str:
    """A plain-text table for the terminal."""
    rows = [HEADER, *table_rows(result)]
    widths = [max(len(r[c]) for r in rows) for c in range(len(HEADER))]
    lines = []
    for i, r in enumerate(rows):
        lines.append("  ".join(r[c].ljust(widths[c]) if c == 0 else r[c].rjust(widths[c]) for c in range(len(r))))
        if i == 0:
            lines.append("  ".join("-" * w for w in widths))
    return "\n".join(lines)


def verdicts(result: Table1Result) -> list[str]:
    """The issue's targets, met or not, in words."""
    rows = [r for r in result.rows if r.fps is not None]
    best = max(rows[1:], key=lambda r: r.fps or 0.0, default=None)
    out = [f"{r.name}: {r.note}" for r in result.rows if r.fps is None and r.note]
    if best is not None and best.ratio is not None:
        ok = "met" if best.ratio >= TARGET_RATIO else "not met"
        out.append(f"best path: {best.name}, {best.ratio:,.0f}x no simplification end to end "
                   f"(target {TARGET_RATIO:,.0f}x: {ok})")
    greedy = next((r for r in rows if r.kind == "mesh" and "greedy" in r.name), None)
    if greedy is not None and greedy.fps is not None:
        if "gpu" in result.machine:
            ok = "met" if greedy.fps >= TARGET_SHELL_FPS else "not met"
            target = f"target {TARGET_SHELL_FPS:.0f} FPS on the H100: {ok}"
        else:
            target = f"the {TARGET_SHELL_FPS:.0f} FPS target is the H100's"
        out.append(f"interactive shell path (shell + greedy mesh + pyrender draw): {greedy.fps:.1f} FPS ({target})")
    return out


def markdown_run(tag: str, result: Table1Result) -> str:
    """One machine's results as a markdown subsection."""
    m = result.machine
    g = result.model["grid"]
    cfg = result.config
    lines = [
        f"### {tag}",
        "",
        f"{m['cpu']}, {m['cores']} cores; OpenGL: {m['gl_renderer']}" + (f"; GPU: {m['gpu']}" if "gpu" in m else "")
        + f"; {m['date']}. Device {cfg['device'] or 'cpu'}; pyrender {m.get('pyrender', '?')}, "
        f"warp {m.get('warp', '-')}, pyopencl {m.get('pyopencl', '-')}.",
        "",
        f"Model: {g['width']}x{g['height']}x{g['depth']} cells ({result.model['source']}), "
        f"{result.model['occupied']:,} occupied, {result.model['full_triangles']:,} triangles as hexahedra; "
        f"images {cfg['size'][0]}x{cfg['size'][1]}; {cfg['frames']} frames per fast row, "
        f"{cfg['baseline_frames']} for the baseline.",
        "",
        "| " + " | ".join(HEADER) + " |",
        "| " + " | ".join(["---"] + ["---:"] * (len(HEADER) - 1)) + " |",
    ]
    lines += ["| " + " | ".join(r) + " |" for r in table_rows(result)]
    lines += [""] + [f"- {v}" for v in verdicts(result)]
    return "\n".join(lines)


def markdown_section(runs: dict[str, Table1Result], chart: str = "benchmarks/results/table1.png") -> str:
    """The whole "## Visualisation (Table 1)" section for all recorded machines."""
    head = [
        SECTION,
        "",
        "The paper's Table 1, reproduced and extended: how fast a fruxel model can be shown when it changes "
        "every frame (a live network output). Each frame gets a new tensor and is timed end to end, from the "
        "tensor to pixels read back on the host: mesh rows = build (shell kernel, labels to host, trapezoid mesh, "
        "pyrender mesh with baked Lambert shading) + upload to the GPU + draw (render and read-back); ray-cast "
        "rows = `first_hit` from the viewing camera + shading to a host image (no mesh). *static FPS* is the "
        "rate for an unchanging model (mesh: draw only; ray cast: kernel and shading again). Frame f is the "
        "model rolled by f columns, made before timing.",
        "",
        "Run: `.venv/bin/python benchmarks/table1.py` (options: `--size WxH`, `--frames N`, `--grid N`, "
        "`--device cuda`, `--backends warp,opencl`), or `fruxel-render --benchmark`. Source: "
        "`render/table1.py`.",
        "",
        f"![Table 1 FPS]({chart})",
        "",
    ]
    body = [markdown_run(tag, res) for tag, res in runs.items()]
    return "\n".join(head) + "\n" + "\n\n".join(body) + "\n"


def write_chart(runs: dict[str, Table1Result], path: Path) -> Path:
    """Bar chart of FPS (log scale) per row and machine, with the paper's two values; written atomically."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names: list[str] = []
    for res in runs.values():
        for r in res.rows:
            if r.name not in names:
                names.append(r.name)
    labels = [*names, "paper: no simplification", "paper: VMS shell"]
    fig, ax = plt.subplots(figsize=(10, 0.55 * len(labels) + 1.6))
    n_runs = max(1, len(runs))
    h = 0.8 / n_runs
    y = np.arange(len(labels))
    for i, (tag, res) in enumerate(runs.items()):
        fps = {r.name: r.fps for r in res.rows if r.fps}
        vals = [fps.get(n, np.nan) for n in names] + [np.nan, np.nan]
        ax.barh(y + (i - (n_runs - 1) / 2) * h, vals, height=h, label=tag)
    ax.barh(y[-2:], [PAPER["baseline_fps"], PAPER["vms_fps"]], height=0.8 / n_runs, color="0.6", hatch="//",
            label="paper")
    ax.set_yticks(y, labels, fontsize=8)
    ax.invert_yaxis()
    ax.set_xscale("log")
    ax.set_xlabel("frames per second, new model every frame (log scale)")
    ax.set_title("Table 1: fruxel display rate, end to end")
    ax.grid(axis="x", which="both", alpha=0.3)
    ax.legend(fontsize=8, loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    try:
        with atomic_path(path) as tmp:
            fig.savefig(tmp, dpi=110)
    finally:
        plt.close(fig)
    return path


def _result_from_dict(d: dict[str, Any]) -> Table1Result:
    return Table1Result(machine=d["machine"], config=d["config"], model=d["model"],
                        rows=[Row(**r) for r in d["rows"]])


def load_runs(path: Path) -> dict[str, Table1Result]:
    """The runs recorded in a ``table1.json`` (empty when the file is missing or unreadable)."""
    if not path.is_file():
        return {}
    try:
        return {k: _result_from_dict(v) for k, v in json.loads(path.read_text())["runs"].items()}
    except (ValueError, KeyError, TypeError):
        return {}


def record(result: Table1Result | dict[str, Table1Result], results_dir: Path, markdown: Path | None) -> list[Path]:
    """Add runs to ``table1.json`` (replacing the same machines' earlier runs), redraw ``table1.png`` and, when
    ``markdown`` is given, rewrite its Table 1 section. All writes are atomic.

    Args:
        result: one run (keyed by :func:`machine_tag`) or runs keyed by machine (e.g. another machine's
            ``table1.json``, see :func:`load_runs`).
        results_dir: folder of ``table1.json`` and ``table1.png``.
        markdown: BENCHMARKS.md to update, or None.

    Returns:
        The files written (no chart where matplotlib is missing).
    """
    results_dir.mkdir(parents=True, exist_ok=True)
    jpath = results_dir / "table1.json"
    runs = load_runs(jpath)
    runs.update(result if isinstance(result, dict) else {machine_tag(result.machine): result})
    with atomic_write(jpath, "w") as f:
        f.write(json.dumps({"runs": {k: asdict(v) for k, v in runs.items()}}, indent=1) + "\n")
    written = [jpath]
    if importlib.util.find_spec("matplotlib") is not None:
        written.append(write_chart(runs, results_dir / "table1.png"))
    if markdown is not None:
        try:
            chart = os.path.relpath(results_dir / "table1.png", markdown.resolve().parent)
        except ValueError:
            chart = str(results_dir / "table1.png")
        update_markdown(markdown, markdown_section(runs, chart))
        written.append(markdown)
    return written


def update_markdown(path: Path, section: str) -> None:
    """Replace (or append) the Table 1 section of a markdown file, leaving every other section as it is."""
    replace_markdown_section(path, SECTION, section)

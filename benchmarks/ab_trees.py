"""Compare two source trees of fruxel on one machine: bit-identical Warp results, kernel timings, and the kernels'
CUDA code.

    python benchmarks/ab_trees.py --base e5471e1                       # CPU: results and timings, Warp CPU
    python benchmarks/ab_trees.py --base .ab-base --device cuda        # the same on CUDA (GPU time, latency)
    python benchmarks/ab_trees.py --base e5471e1 --ptx                 # sm_90 PTX of every Warp kernel, no GPU needed

``--base`` is a source tree (a folder with ``pyproject.toml``) or a git revision of this checkout, which is
extracted with ``git archive`` (``pyproject.toml``, ``fruxel``, ``kernels``, ``benchmarks/common.py``); where the
machine that runs the comparison has no git history (a lent GPU machine), extract it beforehand, e.g.
``mkdir .ab-base && git archive REV pyproject.toml fruxel kernels benchmarks/common.py | tar -x -C .ab-base``.
``--new`` defaults to this checkout. Each tree runs in processes of its own, which import ``fruxel`` from that tree
through the folders its ``pyproject.toml`` maps (``fruxel.kernels`` = ``kernels/``, ...) and times with that tree's
``benchmarks/common.py``: wall time per call (median, minimum) and, on the CPU, the process's CPU time per call
(which a busy neighbour moves less), on CUDA the pipelined time per call and the GPU time of a call's kernels
(CUPTI). Rounds alternate the trees' order, so that a busy neighbour slows both alike; the report gives per case
the median over rounds and new / base. The inputs are made once, by this checkout, and handed to both:

* ``first_hit`` of the kernel benchmark's scene (128^3 ``room_volume``, 512^2 ``oblique_camera``), alone and as a
  batch of 4; ``shell`` over 6 orbit poses; the own-view shell of ``(4, 7, 128^3)`` logits; on CUDA also
  ``first_hit`` at 256^3 @ 1024^2 (the rows of ``bench_kernels.py``);
* ``soft_first_hit`` forward + backward of the losses benchmark's logits (``(B, 7, 64^3)``: own view and 2 novel
  views at 128^2, a fixed weighted sum of the outputs as the loss), and of the own view alone;
* for results only: ``first_hit`` and ``shell`` from views inside, beside and behind the frustum, and
  ``soft_first_hit`` in float64.

Every output (labels, cells, depths, normals, shells, soft classes, depths and gradients) is compared bit for bit.
An output that a tree does not reproduce itself between two rounds (atomic additions in another order on CUDA)
is compared to a relative 1e-5 instead, and reported as such.

With ``--ptx`` each tree's Warp kernels are built for ``sm_90`` (NVRTC, no GPU needed) after a small run of every
operation on the CPU, and each kernel's PTX is compared, its names' hash suffixes and its label numbers set aside
(a kernel that differs only in virtual register numbers is reported as such, else its instruction counts): equal
PTX compiles to the same machine code, so the H100 runs it in the same time.

Writes nothing unless ``--out FILE`` (the report as text).
"""

from __future__ import annotations

import argparse
import json
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
BASE_PATHS = ["pyproject.toml", "fruxel", "kernels", "benchmarks/common.py"]
"""What a tree needs for this script, extracted from a git revision."""
REL_TOL = 1e-5
"""Relative tolerance for outputs that a tree does not reproduce itself (summation order of atomics)."""


# ---------------------------------------------------------------------------------------------- trees
def use_tree(tree: Path) -> None:
    """Import ``fruxel`` and its subpackages from ``tree`` in this process (before any of them is imported): a
    meta-path finder ahead of the installed one maps each package of ``tree``'s ``[tool.setuptools] package-dir``
    to its folder there."""
    import importlib.abc
    import importlib.machinery
    import importlib.util

    import tomllib

    config = tomllib.loads((tree / "pyproject.toml").read_text())
    mapping = {name: tree / folder for name, folder in config["tool"]["setuptools"]["package-dir"].items()}

    class TreeFinder(importlib.abc.MetaPathFinder):
        def find_spec(self, fullname: str, path: Any = None, target: Any = None) -> Any:
            if fullname in mapping:
                folder = mapping[fullname]
                return importlib.util.spec_from_file_location(fullname, folder / "__init__.py",
                                                              submodule_search_locations=[str(folder)])
            parent = fullname.rpartition(".")[0]
            if parent in mapping:  # fruxel.kernels.wp: the mapped parent's folder, not the import system's guess
                return importlib.machinery.PathFinder.find_spec(fullname, [str(mapping[parent])])
            return None

    sys.meta_path.insert(0, TreeFinder())
    sys.path.insert(0, str(tree / "benchmarks"))  # that tree's common.py


def resolve_tree(spec: str, workdir: Path) -> Path:
    """A tree folder as given, or the git revision ``spec`` of this checkout extracted under ``workdir``."""
    p = Path(spec)
    if (p / "pyproject.toml").is_file():
        return p.resolve()
    out = workdir / "base"
    out.mkdir(parents=True)
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", spec, *BASE_PATHS], capture_output=True)
    if archive.returncode != 0:
        raise SystemExit(f"--base {spec!r}: neither a source tree nor a git revision of {ROOT} "
                         f"({archive.stderr.decode().strip()})")
    subprocess.run(["tar", "-x", "-C", str(out)], input=archive.stdout, check=True)
    return out


# ---------------------------------------------------------------------------------------------- inputs
def make_inputs(folder: Path, device: str, batch: int) -> None:
    """Write every case's inputs (``.npy`` arrays and ``cases.json`` with grids and cameras) into ``folder``,
    made by this checkout's scene helpers."""
    import numpy as np

    sys.path.insert(0, str(HERE))
    import bench_kernels
    import bench_losses

    from fruxel.data import rooms
    from fruxel.kernels import orbit_cameras
    from fruxel.train.losses import random_poses

    def grid_dict(g: Any) -> dict[str, Any]:
        return {k: getattr(g, k) for k in ("width", "height", "depth", "z_near", "z_far", "hfov")}

    def cams(cs: list[Any]) -> list[dict[str, Any]]:
        return [{"fx": c.fx, "fy": c.fy, "cx": c.cx, "cy": c.cy, "width": c.width, "height": c.height,
                 "pose": np.asarray(c.pose).tolist()} for c in cs]

    lab, grid = rooms.room_volume(128)
    np.save(folder / "labels128.npy", lab)
    np.save(folder / "logits128.npy", bench_kernels.logits_batch(128))
    c = grid.centre()
    from fruxel.camera import Camera

    views = [
        Camera.look_at(c + [0.2, -0.3, -0.5], c + [0.5, 0.4, 1.5], width=96, height=80, hfov=90.0),  # inside
        Camera.look_at(c + [6.0, -1.0, 0.0], c, width=96, height=80),  # beside
        Camera.look_at(c + [0.3, -0.5, -12.0], c, width=96, height=80),  # behind the apex
        grid.camera(),
    ]
    labels64, logits64, g64 = bench_losses.make_batch(64, batch, "scene", "cpu")
    np.save(folder / "logits64.npy", logits64.numpy())
    novel = random_poses(g64, bench_losses.NOVEL, np.random.default_rng(1), width=bench_losses.NOVEL_SIZE[0],
                         height=bench_losses.NOVEL_SIZE[1])
    cases = {
        "grid128": grid_dict(grid), "oblique": cams([rooms.oblique_camera(grid, 512)]),
        "orbit6": cams(orbit_cameras(grid, 6, width=512, height=512)), "views": cams(views),
        "grid64": grid_dict(g64), "novel": cams(novel), "device": device,
    }
    if device.startswith("cuda"):
        lab256, grid256 = rooms.room_volume(256)
        np.save(folder / "labels256.npy", lab256)
        cases["grid256"] = grid_dict(grid256)
        cases["oblique256"] = cams([rooms.oblique_camera(grid256, 1024)])
    (folder / "cases.json").write_text(json.dumps(cases))


# ---------------------------------------------------------------------------------------------- child: results
def child_run(tree: Path, inputs: Path, out: Path, repeat: int) -> None:
    """In a process of its own: every case on ``tree``'s code; outputs to ``out`` (.npz), timings printed as a
    ``RESULT`` JSON line."""
    use_tree(tree)
    import common
    import numpy as np
    import torch

    from fruxel.camera import Camera
    from fruxel.grid import FruxelGrid
    from fruxel.kernels import first_hit, shell
    from fruxel.kernels.soft import soft_first_hit_groups

    cases = json.loads((inputs / "cases.json").read_text())
    dev = cases["device"]
    cuda = dev.startswith("cuda")

    def grid(name: str) -> FruxelGrid:
        return FruxelGrid(**cases[name])

    def cams(name: str) -> list[Camera]:
        return [Camera(**{**c, "pose": np.array(c["pose"])}) for c in cases[name]]

    def load(name: str) -> torch.Tensor:
        return torch.from_numpy(np.load(inputs / f"{name}.npy")).to(dev)

    def sync() -> None:
        if cuda:
            torch.cuda.synchronize()

    outputs: dict[str, np.ndarray] = {}
    times: dict[str, dict[str, Any]] = {}

    def keep(prefix: str, value: Any) -> None:
        if hasattr(value, "label"):
            for f in ("label", "cell", "depth", "normal"):
                keep(f"{prefix}.{f}", getattr(value, f))
        else:
            outputs[prefix] = value.detach().cpu().numpy() if torch.is_tensor(value) else np.asarray(value)

    def timed(name: str, fn: Any) -> None:
        for _ in range(2):
            fn()
        sync()
        row = common.time_calls(fn, repeat, sync=sync)
        if not cuda:
            # CPU time of this process: on a shared machine it moves less than wall time with the neighbours' load
            # (Warp runs CPU kernels on the calling thread).
            cpu = []
            for _ in range(repeat):
                t0 = time.process_time()
                fn()
                cpu.append((time.process_time() - t0) * 1e3)
            row["cpu_median_ms"], row["cpu_min_ms"] = statistics.median(cpu), min(cpu)
        if cuda:
            row.update(common.pipelined_ms(fn, repeat, sync))
            gpu, kernels = common.cuda_kernel_ms(fn)
            row["gpu_ms"] = gpu
            row["kernels"] = [(k[:60], ms) for k, ms, _n in kernels[:4]]
        times[name] = row

    g128 = grid("grid128")
    vol = load("labels128")
    cam = cams("oblique")[0]
    vol4 = torch.stack([vol] * 4)
    orbit = cams("orbit6")
    logits4 = load("logits128")

    def fh() -> Any:
        return first_hit(vol, g128, cam, backend="warp", device=dev)

    keep("first_hit", fh())
    timed("first_hit 128^3 @ 512^2", fh)
    keep("first_hit B=4", first_hit(vol4, g128, cam, backend="warp", device=dev))
    timed("first_hit B=4 (per call)", lambda: first_hit(vol4, g128, cam, backend="warp", device=dev))
    keep("shell 6 poses", shell(vol, g128, orbit, backend="warp", device=dev))
    timed("shell 6 poses", lambda: shell(vol, g128, orbit, backend="warp", device=dev))
    keep("own-view shell", shell(logits4, g128, g128.camera(), backend="warp", device=dev))
    timed("own-view shell (4, 7, 128^3)", lambda: shell(logits4, g128, g128.camera(), backend="warp", device=dev))
    for n, v in enumerate(cams("views")):
        keep(f"view {n}", first_hit(vol4, g128, v, backend="warp", device=dev))
    keep("shell views", shell(vol4, g128, cams("views"), backend="warp", device=dev))
    if cuda:
        g256, vol256, cam256 = grid("grid256"), load("labels256"), cams("oblique256")[0]
        keep("first_hit 256", first_hit(vol256, g256, cam256, backend="warp", device=dev))
        timed("first_hit 256^3 @ 1024^2", lambda: first_hit(vol256, g256, cam256, backend="warp", device=dev))

    g64 = grid("grid64")
    logits = load("logits64").requires_grad_()
    groups = [[g64.camera()], cams("novel")]

    def weight(x: torch.Tensor) -> torch.Tensor:
        """Fixed weights of one output in the loss (sin of the element index: no random state involved)."""
        return torch.sin(torch.arange(x.numel(), dtype=x.dtype, device=x.device) * 0.37).reshape(x.shape) + 1.0

    def soft(x: torch.Tensor, camera_groups: list[list[Camera]], g: FruxelGrid = g64) -> tuple[list[Any], Any]:
        x.grad = None
        hits = soft_first_hit_groups(x, g, camera_groups, backend="warp", device=dev)
        loss = sum((h.classes * weight(h.classes)).sum() + (h.depth * weight(h.depth)).sum() for h in hits)
        loss.backward()
        return hits, x.grad

    hits, grad = soft(logits, groups)
    for n, h in enumerate(hits):
        keep(f"soft group {n} classes", h.classes)
        keep(f"soft group {n} depth", h.depth)
        keep(f"soft group {n} depth_sum", h.depth_sum)
    keep("soft gradient", grad)
    timed(f"soft_first_hit fwd+bwd B={logits.shape[0]} (own + 2 novel)", lambda: soft(logits, groups))
    keep("soft own gradient", soft(logits, groups[:1])[1])
    timed(f"soft_first_hit own view fwd+bwd B={logits.shape[0]}", lambda: soft(logits, groups[:1]))
    small = logits[:1, :, ::2, ::2, ::2].detach().double().contiguous().requires_grad_()
    g32 = FruxelGrid(width=32, height=32, depth=32, z_near=g64.z_near, z_far=g64.z_far, hfov=g64.hfov)
    hits, grad = soft(small, [[g32.camera()], cams("views")[:3]], g32)
    for n, h in enumerate(hits):
        keep(f"soft float64 group {n} classes", h.classes)
        keep(f"soft float64 group {n} depth", h.depth)
    keep("soft float64 gradient", grad)

    np.savez(out, **outputs)
    print("RESULT " + json.dumps(times), flush=True)


# ---------------------------------------------------------------------------------------------- child: PTX
def child_ptx(tree: Path, out: Path) -> None:
    """In a process of its own: run every Warp operation once on the CPU (which defines every kernel, the
    soft_first_hit instances included), then build each Warp module of fruxel for sm_90 and write each kernel's
    normalised PTX into ``out`` (JSON: kernel name -> PTX)."""
    use_tree(tree)
    import gc
    import re

    import numpy as np
    import torch

    from fruxel.grid import FruxelGrid
    from fruxel.kernels import first_hit, orbit_cameras, shell
    from fruxel.kernels.soft import soft_first_hit_groups
    from fruxel.kernels.wp.runtime import warp

    wp = warp()
    g = FruxelGrid(width=8, height=8, depth=8, z_near=0.5, z_far=3.0, hfov=60.0)
    lab = np.zeros(g.shape, np.uint8)
    lab[4:, 5:, :] = 1
    cams = orbit_cameras(g, 2, width=8, height=8)
    first_hit(lab, g, cams[0], backend="warp", device="cpu")
    shell(lab, g, cams, backend="warp", device="cpu")
    shell(lab, g, g.camera(), backend="warp", device="cpu")
    for dtype in (torch.float32, torch.float64):
        x = torch.zeros((1, 7, *g.shape), dtype=dtype, requires_grad=True)
        hits = soft_first_hit_groups(x, g, [[g.camera()], cams], backend="warp", device="cpu")
        sum(h.classes.sum() + h.depth.sum() for h in hits).backward()
        shell(x.detach(), g, cams, backend="warp", device="cpu")
    modules = {k.module for k in gc.get_objects() if isinstance(k, wp.Kernel) and k.module.name.startswith(("fruxel",
                                                                                                          "wp_"))}
    ptx: dict[str, str] = {}
    with tempfile.TemporaryDirectory() as d:
        for m in sorted(modules, key=lambda m: m.name):
            if not m.kernels:
                continue
            # Kernels made by a factory live in modules named after their instance (scalar type, classes).
            tag = "" if m.name.startswith("fruxel.") else "[" + ",".join(re.findall(r"float\d+|(?<=_)\d+(?=_)",
                                                                                   m.name)) + "]"
            for path in wp.compile_aot_module(m, arch=90, use_ptx=True, module_dir=d):
                text = Path(path).read_bytes().rstrip(b"\0").decode()
                seen: dict[str, int] = {}
                for name, body in re.findall(r"\.visible \.entry (\w+)\((.*?)\n}\n", text, re.S):
                    # the kernel's name without its hash and factory (Warp names a kernel after its qualname)
                    base = re.sub(r"^.*__locals__", "", re.sub(r"_[0-9a-f]{8}_cuda_kernel_forward$", "", name)) + tag
                    seen[base] = seen.get(base, -1) + 1  # overloads of a generic kernel, in registration order
                    body = re.sub(r"\$L__BB\d+_", "$L__BB_", body.replace(name, "KERNEL"))  # labels count kernels
                    ptx[f"{base}#{seen[base]}"] = re.sub(r"_[0-9a-f]{8}_", "_", body)
    out.write_text(json.dumps(ptx))


def ptx_summary(body: str) -> dict[str, int]:
    """Instruction counts of a kernel's PTX: total, and divisions, branches, loads and stores."""
    import re

    ops = re.findall(r"^\s+(?:@%p\d+\s+)?([a-z][\w.]*)", body, re.M)
    return {"instructions": len(ops), "div": sum(o.startswith("div") for o in ops),
            "branches": sum(o.startswith("bra") for o in ops), "loads": sum(o.startswith("ld.global") for o in ops),
            "stores": sum(o.startswith("st.global") for o in ops)}


def register_free(body: str) -> str:
    """PTX with register numbers and labels set aside (what stays when only the allocation differs)."""
    import re

    return re.sub(r"\$L__\w+", "L", re.sub(r"%(r|rd|f|fd|p|rs)\d+", r"%\1", body))


# ---------------------------------------------------------------------------------------------- parent
def run_child(args: list[str]) -> str:
    proc = subprocess.run([sys.executable, str(Path(__file__).resolve()), *args], capture_output=True, text=True)
    if proc.returncode != 0:
        raise SystemExit(f"child {' '.join(args[:3])} failed:\n{proc.stdout[-3000:]}\n{proc.stderr[-5000:]}")
    return proc.stdout


def compare_results(paths: dict[str, list[Path]]) -> list[str]:
    """Lines comparing every output of the new tree's first run with the base's."""
    import numpy as np

    base, new = ([np.load(p) for p in paths[k]] for k in ("base", "new"))
    lines, same = [], 0
    for name in base[0].files:
        a, b = base[0][name], new[0][name] if name in new[0].files else None
        if b is None:
            lines.append(f"  {name}: missing in new")
            continue
        if a.shape != b.shape or a.dtype != b.dtype:
            lines.append(f"  {name}: shape/dtype {a.shape} {a.dtype} -> {b.shape} {b.dtype}")
        elif a.tobytes() == b.tobytes():
            same += 1
        else:
            self_repro = all(r[name].tobytes() == base[0][name].tobytes() for r in base[1:])
            diff = float(np.max(np.abs(a.astype(np.float64) - b.astype(np.float64))))
            scale = float(np.max(np.abs(a.astype(np.float64)))) or 1.0
            if not self_repro and diff <= REL_TOL * scale:
                lines.append(f"  {name}: not bit-reproducible within the base either (atomics); "
                             f"max difference {diff:.3g} of {scale:.3g}: within {REL_TOL:g}")
                same += 1
            else:
                lines.append(f"  {name}: DIFFERS, {int(np.count_nonzero(a != b))} of {a.size} values, "
                             f"max difference {diff:.3g}")
    return [f"results: {same} of {len(base[0].files)} outputs identical", *lines]


def timing_table(times: dict[str, list[dict[str, Any]]], cuda: bool) -> list[str]:
    """Per case and measure: median over rounds of each tree's value, and new / base."""
    measures = ["median_ms", "min_ms"] + (["pipelined_ms", "gpu_ms"] if cuda else ["cpu_median_ms", "cpu_min_ms"])
    lines = [f"{'case':<46s} {'measure':<14s} {'base':>10s} {'new':>10s} {'new/base':>9s}"]
    for case in times["base"][0]:
        for m in measures:
            b = statistics.median(r[case][m] for r in times["base"])
            n = statistics.median(r[case][m] for r in times["new"])
            lines.append(f"{case:<46s} {m:<14s} {b:10.4f} {n:10.4f} {n / b:9.3f}")
        if cuda:
            for tree in ("base", "new"):
                top = ", ".join(f"{k} {ms:.4f}" for k, ms in times[tree][-1][case]["kernels"])
                lines.append(f"    {tree} kernels: {top}")
    return lines


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--base", required=False, default=None, help="source tree folder or git revision (the old code)")
    ap.add_argument("--new", default=str(ROOT), help="source tree folder (default: this checkout)")
    ap.add_argument("--device", default="cpu", help="cpu or cuda (cuda:N)")
    ap.add_argument("--rounds", type=int, default=3, help="runs of each tree, alternating")
    ap.add_argument("--repeat", type=int, default=None, help="timed calls per case (default 10 on CPU, 50 on CUDA)")
    ap.add_argument("--batch", type=int, default=None, help="B of the soft_first_hit case (default 2 CPU, 16 CUDA)")
    ap.add_argument("--ptx", action="store_true", help="compare the kernels' sm_90 PTX instead")
    ap.add_argument("--out", default=None, help="also write the report to this text file")
    ap.add_argument("--child", nargs=3, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.child:
        task, tree, out = args.child
        if task == "ptx":
            child_ptx(Path(tree), Path(out))
        else:
            child_run(Path(tree), Path(task), Path(out), args.repeat)
        return 0
    if args.base is None:
        ap.error("--base is required")
    cuda = args.device.startswith("cuda")
    repeat = args.repeat or (50 if cuda else 10)
    work = Path(tempfile.mkdtemp(prefix="fruxel-ab-"))
    trees = {"base": resolve_tree(args.base, work), "new": Path(args.new).resolve()}
    report = [f"base: {args.base} ({trees['base']}), new: {trees['new']}, device {args.device}"]
    print(report[0], flush=True)
    if args.ptx:
        ptx = {}
        for name, tree in trees.items():
            path = work / f"{name}.json"
            run_child(["--child", "ptx", str(tree), str(path)])
            ptx[name] = json.loads(path.read_text())
        for kernel in sorted(set(ptx["base"]) | set(ptx["new"])):
            b, n = ptx["base"].get(kernel), ptx["new"].get(kernel)
            if b is None or n is None:
                verdict = "only in " + ("new" if b is None else "base")
            elif b == n:
                verdict = "identical PTX"
            elif register_free(b) == register_free(n):
                verdict = "same instructions, other virtual register numbers"
            else:
                sb, sn = ptx_summary(b), ptx_summary(n)
                verdict = "differs: " + ", ".join(f"{k} {sb[k]} -> {sn[k]}" for k in sb)
            report.append(f"  {kernel}: {verdict}")
            print(report[-1], flush=True)
    else:
        inputs = work / "inputs"
        inputs.mkdir()
        make_inputs(inputs, args.device, args.batch or (16 if cuda else 2))
        times: dict[str, list[dict[str, Any]]] = {"base": [], "new": []}
        paths: dict[str, list[Path]] = {"base": [], "new": []}
        for r in range(args.rounds):
            for name in (("base", "new") if r % 2 == 0 else ("new", "base")):
                out = work / f"{name}-{r}.npz"
                text = run_child(["--child", str(inputs), str(trees[name]), str(out), "--repeat", str(repeat)])
                times[name].append(json.loads(next(x for x in text.splitlines() if x.startswith("RESULT "))[7:]))
                paths[name].append(out)
                print(f"round {r + 1}: {name} done", flush=True)
        report += compare_results(paths)
        report += timing_table(times, cuda)
        print("\n".join(report[1:]), flush=True)
    if args.out:
        Path(args.out).write_text("\n".join(report) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

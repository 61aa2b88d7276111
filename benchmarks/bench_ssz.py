"""SSZ benchmark: the 3D up-convolution, training throughput with the simulator streaming in the same
run, and image -> logits (-> shell -> ray-cast) latency at batch 1.

Parts (``--parts``, default all):

* ``layers``: one decoder up-block's depthwise up-convolution, forward + backward, at the ``ssz64`` preset's
  level-0 shape (B x 16 x 32^3 -> 64^3): PyTorch's grouped ``ConvTranspose3d`` (4x4x4, stride 2) against
  nearest x2 + depthwise ``Conv3d`` 3x3x3, each contiguous and channels-last-3D, eager and ``torch.compile``d;
  on CUDA in bfloat16 (pytorch issues 37406 and 47341 report the grouped transposed and depthwise 3D kernels as
  slow).
* ``train``: ``Trainer`` of a preset for ``--steps`` steps with streamed samples (``--workers`` simulator
  processes), profiled: samples/s over the steps after the first 20, peak memory and where a step's time goes
  (data wait, forward, losses, backward, optimiser). Profiling synchronises at phase boundaries; a second,
  unprofiled measure gives the plain throughput.
* ``pointwise``: the decoder's 1x1x1 convolutions as :class:`~fruxel.train.models.blocks.Pointwise3d` computes
  them (a batched matrix product) against cuDNN's ``Conv3d`` on the same ``ssz64`` generator, in alternating
  rounds: forward + backward with the objective at batch 32 (eager), and batch-1 image -> logits replayed as a
  CUDA graph (:class:`~fruxel.train.predict.Predictor`); medians over the rounds.
* ``latency``: batch 1, image -> logits, and image -> logits -> own-view ``shell`` -> ``first_hit`` of a
  512 x 512 view -> shaded image, per preset, eager and compiled (``torch.compile(mode="reduce-overhead")``,
  CUDA graphs); with ``--predictor``, also through fruxel's own
  :class:`~fruxel.train.predict.Predictor` (the compiled pass, and the pass with the shell and ray cast, each
  replayed as one CUDA graph); median of ``--repeat`` calls, synchronised.
* ``predictor``: only the ``--predictor`` rows of ``latency`` (bfloat16 unless named), e.g. to check a model
  variant's budget: ``--parts predictor --model-override '{"camera_inputs": true}'``.
* ``rules``: batch 1, image -> logits of a trained model (``--checkpoint``, default ``ssz64``) on the bundled
  photo, with no inference rule, with the empty-logit offset and ``fill_columns``, with ``first_hit_label`` after
  them, and with ``flip_average`` before them all (the model file's own offset and threshold), in alternating rounds
  of ``--repeat`` calls each; medians,
  and each setting's time as a ratio of the plain pass measured in the same rounds. Trained logits, not a preset's
  random ones: the rules' reductions over the depth axis are much slower on random logits, whose cumulative sums
  reach denormal floats.

Run ``python benchmarks/bench_ssz.py --device cuda --out $OUT/ssz-h100`` on the H100 (writes ``PREFIX.json``);
``--render`` re-renders the "## SSZ" section of BENCHMARKS.md from every ``benchmarks/results/ssz*.json``.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import statistics
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

sys.path.insert(0, str(Path(__file__).resolve().parent))

import common  # noqa: E402

SECTION = "## SSZ"


def _sync(device: Any) -> None:
    import torch

    if device.type == "cuda":
        torch.cuda.synchronize(device)  # the timed region ends when its kernels have run


def _median_ms(fn: Any, device: Any, repeat: int, warm: int = 3) -> float:
    for _ in range(warm):
        fn()
    _sync(device)
    times = []
    for _ in range(repeat):
        t = time.perf_counter()
        fn()
        _sync(device)
        times.append((time.perf_counter() - t) * 1000.0)
    return statistics.median(times)


def bench_layers(device: Any, repeat: int, batch: int) -> list[dict[str, Any]]:
    """The up-convolution variants (see the module docstring)."""
    import torch
    from torch import nn

    dtype = torch.bfloat16 if device.type == "cuda" else torch.float32
    c, n = 16, 32
    rows = []
    for mode in ("transpose", "resize", "parity"):
        for cl in (False, True):
            for compiled in (False, True):
                if compiled and device.type != "cuda":
                    continue
                if mode == "transpose":
                    m = nn.ConvTranspose3d(c, c, 4, stride=2, padding=1, groups=c, bias=False)

                    def f(x: Any, m: Any = m) -> Any:
                        return m(x)
                elif mode == "parity":
                    from fruxel.train.models.blocks import Up3d

                    m = Up3d(c, c, "parity").up
                    w = torch.ones(1, c, 1, 2, 1, 2, 1, 2, device=device, dtype=dtype)

                    def f(x: Any, m: Any = m, w: Any = w) -> Any:
                        y = m(x)
                        b, ch, d, h, ww = y.shape
                        return (y[:, :, :, None, :, None, :, None] * w).reshape(b, ch, 2 * d, 2 * h, 2 * ww)
                else:
                    m = nn.Conv3d(c, c, 3, padding=1, groups=c, bias=False)

                    def f(x: Any, m: Any = m) -> Any:
                        return m(nn.functional.interpolate(x, scale_factor=2.0, mode="nearest"))
                m = m.to(device=device, dtype=dtype)
                fmt = torch.channels_last_3d if cl else torch.contiguous_format
                m = m.to(memory_format=fmt)
                x = torch.randn(batch, c, n, n, n, device=device, dtype=dtype).to(memory_format=fmt)
                x.requires_grad_(True)
                fn = torch.compile(f) if compiled else f

                def step(fn: Any = fn, x: Any = x) -> None:
                    fn(x).float().square().mean().backward()

                try:
                    ms = _median_ms(step, device, repeat)
                except Exception as e:  # noqa: BLE001 - a variant that fails is reported, not fatal
                    ms = float("nan")
                    print(f"  {mode} cl={cl} compiled={compiled}: {type(e).__name__}: {e}", file=sys.stderr)
                rows.append({"mode": mode, "channels_last": cl, "compiled": compiled, "ms": ms})
                print(f"layers {mode:9s} channels_last={cl!s:5s} compiled={compiled!s:5s} {ms:8.3f} ms", flush=True)
    return rows


def bench_pointwise(device: Any, rounds: int = 5, batch: int = 32) -> list[dict[str, Any]]:
    """``pointwise`` part (module docstring): Pointwise3d's product against cuDNN's 1x1x1 Conv3d."""
    import torch
    from torch import nn

    from fruxel.train.config import preset as get_preset
    from fruxel.train.models.blocks import Pointwise3d
    from fruxel.train.objective import SSZObjective
    from fruxel.train.predict import Predictor

    cfg = get_preset("ssz64")
    m = cfg.model
    g = m.build().to(device)
    obj = SSZObjective(cfg.loss, torch.ones(m.num_classes, device=device))
    x = torch.rand(batch, 3, *m.image_size, device=device)
    y = torch.randint(0, m.num_classes, (batch, *m.grid.shape), device=device, dtype=torch.uint8)
    x1 = torch.rand(1, 3, *m.image_size, device=device)
    forwards = {"matmul (Pointwise3d)": Pointwise3d.forward, "nn.Conv3d (cuDNN)": nn.Conv3d.forward}
    # Autocast keeps g's float32 weights, which the training rounds share.
    predictors = {k: Predictor(g, m, device, batch=1, precision="autocast") for k in forwards}
    times: dict[str, dict[str, list[float]]] = {k: {"train": [], "logits": []} for k in forwards}

    def step() -> None:
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=device.type == "cuda"):
            loss = obj(g(x), y)["total"]
        loss.backward()

    try:
        for _ in range(rounds):
            for name, fwd in forwards.items():
                Pointwise3d.forward = fwd  # type: ignore[method-assign]
                g.train()
                times[name]["train"].append(_median_ms(step, device, 5, warm=2))
                # Each predictor captures its graph with this variant's kernels on its first call.
                g.eval()
                pr = predictors[name]
                times[name]["logits"].append(_median_ms(lambda pr=pr: pr.logits(x1), device, 20, warm=3))
    finally:
        Pointwise3d.forward = forwards["matmul (Pointwise3d)"]  # type: ignore[method-assign]
    rows = []
    for name, t in times.items():
        row = {"form": name, "train_ms": statistics.median(t["train"]), "logits_ms": statistics.median(t["logits"]),
               "batch": batch, "rounds": rounds}
        rows.append(row)
        print(f"pointwise {name}: fwd+bwd batch {batch} {row['train_ms']:.1f} ms, batch-1 logits "
              f"{row['logits_ms']:.2f} ms", flush=True)
    return rows


def bench_train(preset: str, device: Any, steps: int, workers: int, overrides: dict[str, Any]) -> dict[str, Any]:
    """Profiled and plain training throughput of ``preset`` with streamed data."""
    import torch

    from fruxel.train.config import override
    from fruxel.train.config import preset as get_preset
    from fruxel.train.engine.trainer import Trainer

    cfg = override(get_preset(preset), {"data": {"workers": workers, "frequency_samples": 64},
                                        "run": {"steps": steps, "eval_every": 0, "checkpoint_every": 0,
                                                "log_every": 10}}, "")
    cfg = override(cfg, overrides, "")
    out: dict[str, Any] = {"preset": preset, "batch": cfg.run.batch_size, "workers": workers, "steps": steps,
                           "overrides": overrides, "compile": cfg.run.compile}
    for profile in (True, False):
        with tempfile.TemporaryDirectory() as d:
            torch.cuda.reset_peak_memory_stats() if device.type == "cuda" else None
            tr = Trainer(cfg, d, device=str(device), progress=False, profile=profile, warm=20, evaluation=False)
            t = time.perf_counter()
            res = tr.fit()
            wall = time.perf_counter() - t
        if profile:
            n = res.timings.get("steps", 0.0)
            out["phases_ms"] = {k: 1000.0 * v / n for k, v in res.timings.items() if k != "steps"} if n else {}
            out["peak_memory_gib"] = res.peak_memory / 2**30
            out["profiled_step_ms"] = sum(out["phases_ms"].values())
        else:
            out["wall_s"] = wall
            out["samples_per_s"] = _steady_rate(tr)
    phases = {k: round(v, 2) for k, v in out.get("phases_ms", {}).items()}
    print(f"train {preset}: {out.get('samples_per_s', float('nan')):.0f} samples/s, peak "
          f"{out.get('peak_memory_gib', 0):.1f} GiB, phases (ms) {phases}", flush=True)
    return out


def _steady_rate(trainer: Any) -> float:
    """Median samples/s of the logged windows after the first two (which hold the start-up)."""
    rates = trainer.rates[2:] or trainer.rates
    return float(statistics.median(rates)) if rates else float("nan")


LATENCY_FORMS = ("channels-last", "contiguous", "bf16")
"""How the batch-1 generator is held on CUDA: channels-last weights under bfloat16 autocast, contiguous weights
under autocast, or contiguous bfloat16 weights without autocast (no per-call weight casts)."""


def bench_latency(preset: str, device: Any, repeat: int, compiled: bool, frozen: bool = False,
                  form: str = "channels-last", model_override: dict[str, Any] | None = None) -> dict[str, Any]:
    """Batch-1 latency of image -> logits and image -> logits -> shell -> 512^2 ray-cast; ``frozen`` compiles with
    Inductor's freezing (weights as constants: batch norms folded into their convolutions, layouts chosen once);
    ``form`` one of :data:`LATENCY_FORMS` (CUDA only; the CPU runs float32 contiguous); ``model_override``
    replaces fields of the preset's model config."""
    import numpy as np
    import torch

    from fruxel import kernels
    from fruxel.camera import Camera, orbit_direction
    from fruxel.render.raycast import shade
    from fruxel.train.config import preset as get_preset
    from fruxel.train.models.blocks import channels_last

    cfg = get_preset(preset)
    m = dataclasses.replace(cfg.model, **(model_override or {}))
    gen = m.build().to(device).eval()
    cuda = device.type == "cuda"
    if cuda and form == "channels-last":
        gen = channels_last(gen)
    if cuda and form == "bf16":
        gen = gen.to(torch.bfloat16)
    h, w = m.image_size
    x = torch.rand(1, 3, h, w, device=device)
    auto = cuda and form != "bf16"

    def forward(img: Any) -> Any:
        with torch.no_grad(), torch.autocast(device.type, dtype=torch.bfloat16, enabled=auto):
            return gen(img.to(torch.bfloat16) if cuda and form == "bf16" else img).logits

    if frozen:
        import torch._inductor.config as inductor_config

        inductor_config.freezing = True
    try:
        fwd = torch.compile(forward, mode="reduce-overhead") if compiled else forward
        logits_ms = _median_ms(lambda: fwd(x), device, repeat, warm=5)
    finally:
        if frozen:
            inductor_config.freezing = False
    grid = m.grid
    centre = grid.centre()
    eye = centre + 1.2 * float(np.linalg.norm(grid.bounds()[1] - grid.bounds()[0])) * orbit_direction(0.6, 0.4)
    cam = Camera.look_at(eye, centre, width=512, height=512, hfov=60.0)
    palette = np.asarray(m.classes.palette(), dtype=np.uint8)

    def full() -> Any:
        logits = fwd(x)
        kept = kernels.shell(logits, grid, [grid.camera()])
        hits = kernels.first_hit(kept, grid, cam)
        one = type(hits)(label=hits.label[0], cell=hits.cell[0], depth=hits.depth[0], normal=hits.normal[0])
        return shade(one, cam, palette)

    row = {"preset": preset, "compiled": compiled, "frozen": frozen, "form": form if cuda else "float32",
           **({"model_override": model_override} if model_override else {}),
           "logits_ms": logits_ms,
           "full_ms": _median_ms(full, device, repeat, warm=5)}
    print(f"latency {preset} {row['form']} compiled={compiled} frozen={frozen}: "
          f"image->logits {row['logits_ms']:.2f} ms, "
          f"->shell->raycast 512^2 {row['full_ms']:.2f} ms", flush=True)
    return row


def bench_predictor_latency(preset: str, device: Any, repeat: int, precision: str, compile: bool = True,
                            model_override: dict[str, Any] | None = None, checkpoint: str | None = None
                            ) -> dict[str, Any]:
    """Batch-1 latency through fruxel's :class:`~fruxel.train.predict.Predictor` (CUDA): the forward pass
    (``torch.compile``d with ``compile``) replayed as one CUDA graph, and image -> logits -> own-view shell ->
    512^2 ``first_hit`` replayed as one graph (:meth:`~fruxel.train.predict.Predictor.run`) followed by the
    shading and the copy of the image to the host. The shell keeps the argmax labels' first hits, as the shell of
    the logits does under its argmax rule. ``checkpoint``: a model file instead of the preset's random weights."""
    import numpy as np
    import torch

    from fruxel import kernels
    from fruxel.camera import Camera, orbit_direction
    from fruxel.render.raycast import shade
    from fruxel.train.config import preset as get_preset
    from fruxel.train.model_files import load_model
    from fruxel.train.predict import Predictor
    from fruxel.train.rules import NO_RULES

    if checkpoint:
        loaded = load_model(checkpoint)
        gen, m, rules = loaded.network, loaded.config, loaded.rules
    else:
        m = dataclasses.replace(get_preset(preset).model, **(model_override or {}))
        gen, rules = m.build(), NO_RULES
    t0 = time.perf_counter()
    pred = Predictor(gen, m, device, batch=1, compile=compile, precision=precision, rules=rules)
    h, w = m.image_size
    x = torch.rand(1, 3, h, w, device=device)
    pred.logits(x)  # compiles and captures
    setup_s = time.perf_counter() - t0
    logits_ms = _median_ms(lambda: pred.logits(x), device, repeat, warm=5)
    grid = m.grid
    centre = grid.centre()
    eye = centre + 1.2 * float(np.linalg.norm(grid.bounds()[1] - grid.bounds()[0])) * orbit_direction(0.6, 0.4)
    cam = Camera.look_at(eye, centre, width=512, height=512, hfov=60.0)
    palette = np.asarray(m.classes.palette(), dtype=np.uint8)
    own = [grid.camera()]

    def hits_of(logits: Any) -> Any:
        kept = kernels.shell(logits.argmax(1).to(torch.uint8), grid, own)
        return kernels.first_hit(kept, grid, cam)

    def full() -> Any:
        hits = pred.run(x, then=hits_of)
        one = type(hits)(label=hits.label[0], cell=hits.cell[0], depth=hits.depth[0], normal=hits.normal[0])
        return shade(one, cam, palette)

    row = {"preset": preset if not checkpoint else f"{preset} ({Path(checkpoint).name})",
           "compiled": compile, "graphed": True, "form": f"Predictor, {precision}",
           **({"model_override": model_override} if model_override else {}),
           "setup_s": setup_s, "logits_ms": logits_ms, "full_ms": _median_ms(full, device, repeat, warm=5)}
    print(f"latency {row['preset']} {row['form']} compiled={compile}: image->logits {row['logits_ms']:.2f} ms, "
          f"->shell->raycast 512^2 {row['full_ms']:.2f} ms (setup {setup_s:.0f} s)", flush=True)
    return row


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--parts", nargs="+", default=["layers", "pointwise", "train", "latency", "rules"],
                   choices=["layers", "pointwise", "train", "latency", "rules", "predictor"])
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when present)")
    p.add_argument("--presets", nargs="+", default=["ssz64", "ssz128"])
    p.add_argument("--steps", type=int, default=120, help="training steps per preset")
    p.add_argument("--workers", type=int, default=15, help="simulator processes per training run")
    p.add_argument("--train-override", default="{}", help="JSON config overrides of the training runs")
    p.add_argument("--repeat", type=int, default=30)
    p.add_argument("--frozen", action="store_true", help="latency part: also compile with Inductor's freezing")
    p.add_argument("--forms", nargs="+", default=["channels-last"], choices=LATENCY_FORMS,
                   help="latency part on CUDA: also the compiled generator in these forms (LATENCY_FORMS)")
    p.add_argument("--predictor", nargs="*", default=None, choices=["bfloat16", "autocast"],
                   help="latency part on CUDA: also fruxel's Predictor (compiled pass and pipeline replayed as CUDA "
                        "graphs) in these precisions (none given: bfloat16)")
    p.add_argument("--checkpoint", default=None,
                   help="latency part, Predictor rows: also this model file (its own inference rules); rules "
                        "part: the model (default: ssz64, the model of the stored rows)")
    p.add_argument("--model-override", default="{}",
                   help='latency part: JSON fields of the presets\' ModelConfig, e.g. \'{"fill_columns": true}\'')
    p.add_argument("--batch", type=int, default=32, help="batch of the layers and pointwise parts")
    p.add_argument("--out", default=None, help="PREFIX of PREFIX.json (default benchmarks/results/ssz-<device>)")
    p.add_argument("--render", action="store_true", help="only re-render BENCHMARKS.md from the results")
    args = p.parse_args(argv)
    if args.render:
        render()
        return 0
    import torch

    device = torch.device(args.device or ("cuda" if torch.cuda.is_available() else "cpu"))
    result: dict[str, Any] = {"machine": common.machine_info(),
                              "device": str(device), "gpu": common.gpu_name(), "cpu": common.cpu_description(),
                              "torch": torch.__version__, "date": time.strftime("%Y-%m-%d")}
    if "layers" in args.parts:
        result["layers"] = bench_layers(device, args.repeat, args.batch)
    if "pointwise" in args.parts:
        result["pointwise"] = bench_pointwise(device, batch=args.batch)
    if "train" in args.parts:
        ov = json.loads(args.train_override)
        result["train"] = [bench_train(pr, device, args.steps, args.workers, ov) for pr in args.presets]
    if "latency" in args.parts:
        mo = json.loads(args.model_override)
        result["latency"] = [bench_latency(pr, device, args.repeat, c, model_override=mo) for pr in args.presets
                             for c in ((False, True) if device.type == "cuda" else (False,))]
        if device.type == "cuda":
            result["latency"] += [bench_latency(pr, device, args.repeat, True, form=f, model_override=mo)
                                  for pr in args.presets for f in args.forms if f != "channels-last"]
        if args.predictor is not None and device.type == "cuda":
            for prec in args.predictor or ["bfloat16"]:
                result["latency"] += [bench_predictor_latency(pr, device, args.repeat, prec, model_override=mo)
                                      for pr in args.presets]
                if args.checkpoint:
                    result["latency"].append(bench_predictor_latency(args.presets[0], device, args.repeat, prec,
                                                                     checkpoint=args.checkpoint))
        if args.frozen and device.type == "cuda":
            result["latency"] += [bench_latency(pr, device, args.repeat, True, frozen=True, model_override=mo)
                                  for pr in args.presets]
    if "predictor" in args.parts and device.type == "cuda":
        # The Predictor's batch-1 latency alone (no eager or plain compiled rows): a model variant's check.
        mo = json.loads(args.model_override)
        result.setdefault("latency", [])
        result["latency"] += [bench_predictor_latency(pr, device, args.repeat, prec, model_override=mo)
                              for prec in args.predictor or ["bfloat16"] for pr in args.presets]
    if "rules" in args.parts:
        result["rules"] = bench_rules(device, args.repeat, args.checkpoint)
    out = Path(args.out) if args.out else common.RESULTS / f"ssz-{device.type}"
    out.parent.mkdir(parents=True, exist_ok=True)
    Path(f"{out}.json").write_text(json.dumps(result, indent=2) + "\n", encoding="utf-8")
    print(f"wrote {out}.json")
    return 0


def bench_rules(device: Any, repeat: int, checkpoint: str | None = None) -> list[dict[str, Any]]:
    """``rules`` part (module docstring): batch-1 image -> logits of a trained model under each set of inference
    rules, in alternating rounds; medians and ratios to the plain pass."""
    import torch

    from fruxel.data import PHOTO
    from fruxel.train.model_files import load_model
    from fruxel.train.predict import load_image, prepare_image, to_tensor
    from fruxel.train.rules import NO_RULES, predict_logits

    loaded = load_model(checkpoint or "ssz64", device)
    gen, m, own = loaded.network, loaded.config, loaded.rules
    path = loaded.path
    x = to_tensor([prepare_image(load_image(PHOTO), m)], device)
    both = f"offset {own.empty_offset:g} + fill_columns {own.fill_threshold:g}"
    shifted = dataclasses.replace(NO_RULES, empty_offset=own.empty_offset, fill_columns=True,
                                  fill_threshold=own.fill_threshold)
    settings = {"none": NO_RULES, both: shifted,
                f"{both} + first_hit_label": dataclasses.replace(shifted, first_hit_label=True),
                f"flip_average + {both} + first_hit_label": dataclasses.replace(shifted, first_hit_label=True,
                                                                                 flip_average=True)}
    times: dict[str, list[float]] = {k: [] for k in settings}

    def call(rules: Any) -> None:
        with torch.no_grad():
            predict_logits(gen, x, rules)

    for _ in range(3):
        call(NO_RULES)
    for _ in range(repeat):
        for name, rules in settings.items():
            _sync(device)
            t = time.perf_counter()
            call(rules)
            _sync(device)
            times[name].append((time.perf_counter() - t) * 1000.0)
    plain = statistics.median(times["none"])
    rows = [{"model": Path(path).name, "rules": name, "logits_ms": statistics.median(times[name]),
             "ratio": statistics.median(times[name]) / plain} for name in settings]
    for r in rows:
        print(f"rules {r['rules']}: image->logits {r['logits_ms']:.2f} ms ({r['ratio']:.2f} x the plain pass)",
              flush=True)
    return rows


def _override(row: dict[str, Any]) -> str:
    """``" (field value, ...)"`` for a latency row measured with ``--model-override``, else empty."""
    ov = row.get("model_override")
    return " (" + ", ".join(f"{k} {json.dumps(v)}" for k, v in ov.items()) + ")" if ov else ""


def _fmt(v: Any, nd: int = 1) -> str:
    return "-" if v is None or v != v else f"{v:.{nd}f}"


def render() -> None:
    """Re-render the "## SSZ" section of BENCHMARKS.md from every ``benchmarks/results/ssz*.json``."""
    lines = [SECTION, "", "Written by `benchmarks/bench_ssz.py --render` from `benchmarks/results/ssz*.json`. Targets "
             "(issue 13): H100 bf16 training with data streamed in the same run, >= 400 samples/s at 64^3 from 128^2 "
             "and >= 20 samples/s at 128^3 from 512^2; batch-1 image -> logits <= 1 ms (64^3) and <= 5 ms (128^3); "
             "image -> logits -> shell -> 512^2 ray cast <= 3 ms (64^3) and <= 20 ms (128^3); 2 cores: predicting a "
             "64^3 model from one image <= 1 s.", ""]
    for path in sorted(common.RESULTS.glob("ssz*.json")):
        r = json.loads(path.read_text(encoding="utf-8"))
        m = r.get("machine", {})
        where = m.get("gpu") if r.get("device", "").startswith("cuda") else m.get("cpu")
        lines += [f"### {where}, {m.get('cores', '?')} cores ({r.get('date', '?')}, torch {r.get('torch', '?')}, "
                  f"load {_fmt(m.get('load_average'))})", "", f"`{path.name}`", ""]
        if r.get("note"):
            lines += [r["note"], ""]
        if r.get("layers"):
            lines += ["Up-convolution of one decoder level, B x 16 x 32^3 -> 64^3, forward + backward:", "",
                      "| form | channels-last | compiled | ms |", "| --- | --- | --- | ---: |"]
            lines += [f"| {x['mode']} | {x['channels_last']} | {x['compiled']} | {_fmt(x['ms'], 2)} |"
                      for x in r["layers"]]
            lines.append("")
        if r.get("variants"):
            lines += ["Whole `ssz64` generator with its objective, forward + backward, per design variant:", "",
                      "| up-convolution | group width | channels-last | compiled | ms / step | samples/s | note |",
                      "| --- | ---: | --- | --- | ---: | ---: | --- |"]
            lines += [f"| {x['upsample']} | {x['group_width']} | {x['channels_last']} | {x['compiled']} | "
                      f"{_fmt(x['ms'])} | {x['samples_per_s']:.0f} | {x.get('note', '')} |" for x in r["variants"]]
            lines.append("")
        if r.get("pointwise"):
            lines += ["The decoder's 1x1x1 convolutions, `ssz64` generator (alternating rounds, medians):", "",
                      "| form | forward + backward, batch " + str(r["pointwise"][0]["batch"]) + ", ms | "
                      "batch-1 image -> logits, ms |", "| --- | ---: | ---: |"]
            lines += [f"| {x['form']} | {_fmt(x['train_ms'])} | {_fmt(x['logits_ms'], 2)} |" for x in r["pointwise"]]
            lines.append("")
        if r.get("train"):
            lines += ["Training with the simulator streaming in the same run (profiled phases per step, ms; "
                      "samples/s from an unprofiled run):", "",
                      "| preset | compiled | batch | workers | samples/s | peak GiB | data | forward | losses | "
                      "backward | optimiser |", "| --- | --- |" + " ---: |" * 9]
            for x in r["train"]:
                ph = x.get("phases_ms", {})
                lines.append(f"| {x['preset']} | {bool(x.get('compile'))} | {x['batch']} | {x['workers']} | "
                             f"{_fmt(x.get('samples_per_s'), 0)} | "
                             f"{_fmt(x.get('peak_memory_gib'))} | " + " | ".join(
                                 _fmt(ph.get(k)) for k in ("data", "forward", "loss", "backward", "optimizer")) + " |")
            lines.append("")
        if r.get("latency"):
            lines += ["Batch 1 (median of synchronised calls):", "",
                      "| preset | form | compiled (CUDA graphs) | image -> logits, ms | + shell + 512^2 ray cast, ms | "
                      "note |", "| --- | --- | --- | ---: | ---: | --- |"]
            old_form = "channels-last" if r.get("device", "").startswith("cuda") else "float32"
            lines += [f"| {x['preset']}{_override(x)} | {x.get('form', old_form)} | "
                      f"{x['compiled']}{', frozen' if x.get('frozen') else ''} | "
                      f"{_fmt(x['logits_ms'], 2)} | {_fmt(x['full_ms'], 2)} | "
                      f"{x.get('note', '')} |" for x in r["latency"]]
            lines.append("")
        if r.get("rules"):
            lines += [f"Inference rules, batch 1, the bundled photo, `{r['rules'][0]['model']}` (alternating rounds, "
                      "medians):", "", "| rules | image -> logits, ms | against no rule |", "| --- | ---: | ---: |"]
            lines += [f"| {x['rules']} | {_fmt(x['logits_ms'], 2)} | {x['ratio']:.2f} x |" for x in r["rules"]]
            lines.append("")
    common.replace_section(common.BENCHMARKS_MD, SECTION, "\n".join(lines))
    print(f"rendered {SECTION} of {common.BENCHMARKS_MD}")


if __name__ == "__main__":
    sys.exit(main())

"""Split a model's own-view first-hit errors by what the truth allows (see fruxel.train.eval.own_view).

    python scripts/own_view_errors.py MODEL --data data/eval64 [--split test] [--samples 512] [--json OUT]

For each sample of a data set made by ``fruxel-sim generate``, the room is rebuilt from the data set's seed and each
grid column's centre ray is cast against its labelled meshes (what the camera sees); the truth's own-view pixels
are then split into clean / aliased / near / far (and the clean ones by the depth of their first solid along the
ray: under one slice or not), and the model's own-view accuracy is counted in each. Also
prints the share of errors in near-uniform images (pixel standard deviation below ``--uniform``, in 0-255 units:
the camera close to a plain surface). Last, for the pixels whose first solid is thinner than a slice, it compares
the model with an idealised reader that knows everything but the solid's depth, which it knows to a Gaussian error
of each ``--sigmas`` (``depth_reader_accuracy``): how well the network would have to read depth to keep more thin
boards right, and the own view that would give with the model's answers elsewhere. For a model with the fine depth
head (``model.fine_depth``), it also prints how far that head's depth is from the cast one, on the thin solids and on
every column that sees a surface in range. And it splits the errors into columns the prediction leaves empty and
columns whose first occupied cell has the wrong class, with the own view that other sources of that class would give
(``first_label_sources``: the raw volume's most likely first hit, the surface head, both). Runs on the CPU.
"""

from __future__ import annotations

import argparse
import sys
from collections.abc import Sequence

from fruxel.cli.common import OneLineParser, UsageError, run


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="own_view_errors.py", description=__doc__.split("\n\n")[0])
    p.add_argument("model", help="trained model (.safetensors or checkpoint)")
    p.add_argument("--data", required=True, help="data set folder (fruxel-sim generate)")
    p.add_argument("--split", default="test", help="split (default test)")
    p.add_argument("--samples", type=int, default=512, help="first N samples of the split (default 512)")
    p.add_argument("--batch", type=int, default=16, help="samples per batch")
    p.add_argument("--uniform", type=float, default=4.0,
                   help="an image whose pixel standard deviation (0-255, mean over RGB) is below this counts as "
                   "near-uniform (default 4)")
    p.add_argument("--sigmas", type=float, nargs="*", default=[0.0, 0.01, 0.02, 0.03, 0.05, 0.08, float("inf")],
                   help="depth errors (metres; inf allowed) of the idealised reader of thin solids "
                   "(default 0 0.01 0.02 0.03 0.05 0.08 inf)")
    p.add_argument("--png", default=None, help="also plot the readers' own view against the model's here")
    p.add_argument("--json", default=None, help="also write the summary as JSON here")
    return p


def _main(args: argparse.Namespace) -> None:
    import json

    import numpy as np
    import torch
    from tqdm import tqdm

    from fruxel.io import atomic_write
    from fruxel.train.eval.metrics import first_surface
    from fruxel.train.eval.own_view import (
        CATEGORIES,
        LABEL_SOURCES,
        JoinedMeshes,
        OwnViewBreakdown,
        depth_reader_accuracy,
        fine_depth_estimate,
        first_label_sources,
        label_behind,
        plot_depth_readers,
        surface_extent,
        visible_surface,
    )
    from fruxel.train.eval.samples import EvalData, batches, data_set_manifest, split_size
    from fruxel.train.export import load_generator
    from fruxel.train.sim.sample import SampleMaker

    if args.samples < 1 or args.batch < 1 or not args.uniform >= 0:
        raise UsageError("--samples and --batch must be >= 1 and --uniform >= 0")
    if not all(s >= 0 for s in args.sigmas):
        raise UsageError(f"--sigmas must be >= 0 (inf allowed), got {args.sigmas}")
    generator, config, _ = load_generator(args.model)
    manifest = data_set_manifest(args.data, config)
    data = EvalData(source="shards", root=args.data, seed=manifest.seed)
    count = min(args.samples, split_size(data, config, args.split))
    grid = manifest.config.grid
    maker = SampleMaker(manifest.config, manifest.seed, backend="warp-cpu", device="cpu")
    total, uniform = OwnViewBreakdown(), OwnViewBreakdown()
    n_uniform = index = 0
    thin: dict[str, list[np.ndarray]] = {"depth": [], "extent": [], "kept": [], "dropped": [], "ok": []}
    fine_errors: dict[str, list[np.ndarray]] = {"thin": [], "all": []}
    room, meshes = None, None
    label_right = dict.fromkeys(("empty", *LABEL_SOURCES), 0)  # truth-hit columns: left empty; right per source
    try:
        with tqdm(total=count, desc="own view", unit="sample", disable=None) as bar, torch.no_grad():
            for image, labels in batches(data, config, args.split, count, args.batch):
                out = generator(image.permute(0, 3, 1, 2).float() / 255, rules=False)
                ruled = generator.apply_rules(out.logits, out.depth_logits)
                pred = first_surface(ruled.argmax(1)).numpy()
                sources = first_label_sources(out.logits, out.surface_logits, ruled)
                fine = None if out.fine_logits is None else fine_depth_estimate(out.fine_logits.numpy(), grid)
                truth = first_surface(labels.long()).numpy()
                hit = truth != 0
                label_right["empty"] += int((hit & (pred == 0)).sum())
                for name, got in sources.items():
                    label_right[name] += int((hit & (got == truth)).sum())
                spread = image.float().std(dim=(1, 2)).mean(dim=1).numpy()  # (B,): per channel, then averaged
                for b in range(len(labels)):
                    scene, pose = maker.scene_of(args.split, index)
                    if scene is not room:  # consecutive samples share a room (held here: an id could be reused)
                        room, meshes = scene, JoinedMeshes(scene.labelled_meshes())
                    seen = visible_surface(meshes, grid, pose)
                    extent = surface_extent(meshes, grid, pose, seen[1])
                    total.add(pred[b], truth[b], *seen, grid, extent)
                    in_range = (seen[1] >= grid.z_near) & (seen[1] <= grid.z_far)
                    m = (truth[b] != 0) & in_range & (extent < grid.dz)
                    behind = label_behind(meshes, grid, pose, seen[1], np.where(m, extent, np.inf))
                    for key, v in (("depth", seen[1]), ("extent", extent), ("kept", truth[b] == seen[0]),
                                   ("dropped", truth[b] == behind), ("ok", pred[b] == truth[b])):
                        thin[key].append(v[m])
                    if fine is not None:
                        with np.errstate(invalid="ignore"):  # inf - inf where neither sees a surface
                            error = np.abs(fine[b] - seen[1])
                        fine_errors["thin"].append(error[m])
                        fine_errors["all"].append(error[in_range])
                    if spread[b] < args.uniform:
                        uniform.add(pred[b], truth[b], *seen, grid, extent)
                        n_uniform += 1
                    index += 1
                bar.update(len(labels))
    finally:
        maker.close()
    s = total.summary()
    u = uniform.summary()
    lost = 100.0 - s["accuracy"]
    print(f"{count} samples of {args.data} split {args.split}: own-view accuracy {s['accuracy']:.2f} % over "
          f"{s['pixels']} pixels where the truth hits")
    print("| pixels | share % | model accuracy % | points lost |\n| --- | ---: | ---: | ---: |")
    for name in (*CATEGORIES[:1], "clean_thin", "clean_thick", *CATEGORIES[1:]):
        c = s[name]
        acc = "n/a" if c["accuracy"] is None else f"{c['accuracy']:.2f}"
        label = {"clean_thin": "clean, first solid under a slice deep", "clean_thick": "clean, deeper"}.get(name, name)
        print(f"| {label} | {c['share']:.2f} | {acc} | {c['lost']:.2f} |")
    u_lost = (100.0 - u["accuracy"]) * u["pixels"] / s["pixels"] if u["pixels"] else 0.0
    print(f"near-uniform images (pixel std < {args.uniform:g}): {n_uniform} of {count} samples, "
          f"{100.0 * u['pixels'] / s['pixels']:.2f} % of the pixels, {u_lost:.2f} of the {lost:.2f} points lost")
    t = {k: np.concatenate(v) for k, v in thin.items()}
    n_thin, model_ok = len(t["ok"]), int(t["ok"].sum())
    readers = []
    if n_thin:
        print(f"solids thinner than a slice: {100.0 * n_thin / s['pixels']:.2f} % of the pixels; the truth shows the "
              f"solid's label on {100.0 * t['kept'].mean():.1f} % of them and the label behind it on "
              f"{100.0 * t['dropped'].mean():.1f} %; the model is right on {100.0 * model_ok / n_thin:.2f} %")
        print("| reader's depth error m | right on thin % | own view with the model elsewhere % |\n"
              "| ---: | ---: | ---: |")
        for sigma in args.sigmas:
            acc = depth_reader_accuracy(t["depth"], t["extent"], t["kept"], t["dropped"], grid, sigma)
            own = s["accuracy"] + 100.0 * (acc * n_thin - model_ok) / s["pixels"]
            readers.append({"sigma": sigma, "thin_accuracy": 100.0 * acc, "own_view": own})
            print(f"| {sigma:g} | {100.0 * acc:.2f} | {own:.2f} |")
    label_share = {"empty": 100.0 * label_right["empty"] / s["pixels"],
                   **{k: 100.0 * label_right[k] / s["pixels"] for k in LABEL_SOURCES}}
    print(f"columns where the truth hits and the prediction is empty: {label_share['empty']:.3f} %; own view with the "
          "first occupied cell's class from:\n| source | own view % |\n| --- | ---: |")
    for key, label in (("model", "the model (its rules)"), ("volume", "the raw volume's most likely first hit"),
                       ("head", "the surface head"), ("both", "the volume's first hit and the head together")):
        print(f"| {label} | {label_share[key]:.3f} |")
    fine_summary = {}
    if fine_errors["all"]:
        print("fine depth head against the cast depth:\n| columns | count | median error cm | within 1 cm % | "
              "within 2 cm % | within 3 cm % |\n| --- | ---: | ---: | ---: | ---: | ---: |")
        for key, label in (("thin", "first solid thinner than a slice"), ("all", "every surface in range")):
            e = np.concatenate(fine_errors[key]) if fine_errors[key] else np.zeros(0)
            row = {"count": int(e.size), "median_cm": 100.0 * float(np.median(e)) if e.size else None,
                   **{f"within_{c}cm": 100.0 * float((e < c / 100).mean()) if e.size else None for c in (1, 2, 3)}}
            fine_summary[key] = row
            if e.size:
                print(f"| {label} | {e.size} | {row['median_cm']:.2f} | {row['within_1cm']:.1f} | "
                      f"{row['within_2cm']:.1f} | {row['within_3cm']:.1f} |")
    if args.png and readers:
        plot_depth_readers(readers, s["accuracy"], args.png,
                           title=f"{count} samples of {args.data} ({args.split}): who would get thin solids right")
        print(f"wrote {args.png}")
    if args.json:
        out = {"model": args.model, "data": args.data, "split": args.split, "samples": count, **s,
               "uniform": {"threshold": args.uniform, "samples": n_uniform, **u, "points_lost": u_lost},
               "fine_depth": fine_summary, "label_sources": label_share,
               "thin": {"pixels": n_thin, "share": 100.0 * n_thin / s["pixels"],
                        "kept": 100.0 * float(t["kept"].mean()) if n_thin else None,
                        "behind": 100.0 * float(t["dropped"].mean()) if n_thin else None,
                        "model_accuracy": 100.0 * model_ok / n_thin if n_thin else None,
                        "readers": [{**r, "sigma": str(r["sigma"]) if np.isinf(r["sigma"]) else r["sigma"]}
                                    for r in readers]}}
        with atomic_write(args.json, "w") as f:
            f.write(json.dumps(out, indent=1, default=float) + "\n")
        print(f"wrote {args.json}")


def main(argv: Sequence[str] | None = None) -> int:
    return run(_main, _parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

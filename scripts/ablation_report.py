"""The loss ablation of the shipped SSZ (docs/experiments.md): a table and a chart from fruxel-eval reports.

Each run was trained at the same budget and seed (3000 steps of 32 samples, seed 0, the ``ssz64`` preset) with
one more loss term than the last, then evaluated on the same held-out samples with ``fruxel-eval``:

    python scripts/ablation_report.py A=eval-A/report.json B=eval-B/report.json C=eval-C/report.json \\
        --labels "voxel losses" "+ shell-aware" "+ adversarial" --png docs/ablation.png

Prints the Markdown table (mIoU, completion IoU, own- and novel-view first-hit accuracy, depth error) and writes
the chart.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

from fruxel.cli.common import OneLineParser, UsageError, run

ROWS = (("miou", "mIoU (%)"), ("completion_iou", "completion IoU (%)"), ("own_view_accuracy", "own-view accuracy (%)"),
        ("novel_view_accuracy", "novel-view accuracy (%)"), ("depth_error", "novel-view depth error (m)"))


def _parser() -> argparse.ArgumentParser:
    p = OneLineParser(prog="ablation_report.py", description=__doc__.split("\n\n")[0])
    p.add_argument("reports", nargs="+", help="NAME=report.json of each run, in ablation order")
    p.add_argument("--labels", nargs="+", help="what each run adds (default: the names)")
    p.add_argument("--png", type=Path, help="chart to write")
    return p


def _load(spec: str) -> tuple[str, dict[str, float]]:
    """``NAME=report.json`` -> the name and the report's model results; one-line errors for a bad argument."""
    name, eq, path = spec.partition("=")
    if not eq or not name or not path:
        raise UsageError(f"a report must be given as NAME=report.json, got {spec!r}")
    try:
        r = json.loads(Path(path).read_text(encoding="utf-8"))
        model = r["results"]["model"]
        for key, _ in ROWS:
            float(model[key])
    except (OSError, UnicodeDecodeError) as e:
        raise UsageError(f"{path}: cannot read: {e.strerror if isinstance(e, OSError) else e}") from None
    except ValueError as e:  # json.JSONDecodeError too
        raise UsageError(f"{path}: not a fruxel-eval report: {e}") from None
    except (KeyError, TypeError) as e:
        raise UsageError(f"{path}: not a fruxel-eval report: no results.model.{e} number") from None
    return name, model


def _main(args: argparse.Namespace) -> int:
    names, results = [], []
    for spec in args.reports:
        name, model = _load(spec)
        names.append(name)
        results.append(model)
    labels = args.labels or names
    if len(labels) != len(names):
        raise UsageError("give one label per report")
    head = "| metric | " + " | ".join(f"{n}: {lab}" for n, lab in zip(names, labels, strict=True)) + " |"
    lines = [head, "| --- |" + " ---: |" * len(names)]
    for key, title in ROWS:
        nd = 3 if key == "depth_error" else 1
        lines.append(f"| {title} | " + " | ".join(f"{r[key]:.{nd}f}" for r in results) + " |")
    print("\n".join(lines))
    if args.png:
        import matplotlib

        matplotlib.use("Agg")
        import matplotlib.pyplot as plt

        fig, axes = plt.subplots(1, 3, figsize=(12, 3.6))
        for ax, (key, title) in zip(axes, (ROWS[0], ROWS[3], ROWS[4]), strict=True):
            vals = [r[key] for r in results]
            bars = ax.bar(range(len(vals)), vals, color=["#8da0cb", "#66c2a5", "#fc8d62", "#e78ac3"][:len(vals)])
            ax.set_xticks(range(len(vals)), [f"{n}\n{lab}" for n, lab in zip(names, labels, strict=True)], fontsize=8)
            ax.set_title(title)
            lo, hi = min(vals), max(vals)
            pad = (hi - lo) * 0.6 + 1e-3
            ax.set_ylim(max(0.0, lo - pad), hi + pad)
            for b, v in zip(bars, vals, strict=True):
                ax.text(b.get_x() + b.get_width() / 2, v, f"{v:.3f}" if key == "depth_error" else f"{v:.1f}",
                        ha="center", va="bottom", fontsize=8)
            ax.grid(axis="y", alpha=0.3)
        fig.suptitle("SSZ loss ablation: same steps, samples and seed; held-out test rooms")
        fig.tight_layout()
        from fruxel.io import atomic_path

        with atomic_path(args.png) as tmp:
            fig.savefig(tmp, dpi=110, format="png")
        print(f"wrote {args.png}", file=sys.stderr)
    return 0


def main(argv: list[str] | None = None) -> int:
    return run(_main, _parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

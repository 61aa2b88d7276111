"""Where a run's numbers go: a CSV file of metrics per step (and TensorBoard when it is installed), and PNG
curves drawn from the CSV."""

from __future__ import annotations

import csv
import math
import os
from typing import Any

from fruxel.io import atomic_path

METRICS = "metrics.csv"
"""File name of the metrics table in a run folder."""
CURVES = "curves.png"
"""File name of the training curves in a run folder."""


class Logbook:
    """Appends metric rows to ``run_dir/metrics.csv`` (one column per name ever logged; the file is rewritten
    when a new name appears) and mirrors them to TensorBoard when ``torch.utils.tensorboard`` imports.

    Args:
        run_dir: the run's folder.
        resume_step: on resume, rows after this step (written by the interrupted run after its last checkpoint)
            are dropped, so the table never holds two rows for one step.
        tensorboard: try TensorBoard.
    """

    def __init__(self, run_dir: str, resume_step: int | None = None, tensorboard: bool = True) -> None:
        self.path = os.path.join(run_dir, METRICS)
        self.rows: list[dict[str, Any]] = []
        if resume_step is not None and os.path.exists(self.path):
            with open(self.path, newline="", encoding="utf-8") as f:
                self.rows = [r for r in csv.DictReader(f) if r.get("step") and int(float(r["step"])) <= resume_step]
        elif os.path.exists(self.path):
            os.remove(self.path)
        self.columns: list[str] = ["step"]
        for r in self.rows:
            for k in r:
                if k not in self.columns:
                    self.columns.append(k)
        self._rewrite()
        self.commit()
        self.tb = None
        if tensorboard:
            try:
                from torch.utils.tensorboard import SummaryWriter

                self.tb = SummaryWriter(os.path.join(run_dir, "tensorboard"))
            except Exception:  # noqa: BLE001 - TensorBoard is optional; any import problem means "not installed"
                self.tb = None

    def _rewrite(self) -> None:
        with atomic_path(self.path) as tmp, open(tmp, "w", newline="", encoding="utf-8") as f:
            w = csv.DictWriter(f, fieldnames=self.columns)
            w.writeheader()
            w.writerows(self.rows)

    def log(self, step: int, values: dict[str, float]) -> None:
        """Add one row (``step`` plus ``values``)."""
        row = {"step": step, **{k: (f"{v:.6g}" if isinstance(v, float) else v) for k, v in values.items()}}
        self.rows.append(row)
        new = [k for k in row if k not in self.columns]
        if new:
            self.columns += new
            self._rewrite()
        else:
            with open(self.path, "a", newline="", encoding="utf-8") as f:
                csv.DictWriter(f, fieldnames=self.columns).writerow(row)
        if self.tb is not None:
            for k, v in values.items():
                if isinstance(v, (int, float)) and math.isfinite(float(v)):
                    self.tb.add_scalar(k, float(v), step)

    def commit(self) -> None:
        """Mark the table as it is now as the checkpoint's: :meth:`rollback` returns here."""
        self._committed = (len(self.rows), list(self.columns), os.path.getsize(self.path))

    def rollback(self) -> None:
        """Drop the rows added since the last :meth:`commit` (a checkpoint that could not be written), so that the
        table never claims a step the run folder's checkpoint does not hold. Rows are appended, so the committed
        table is the start of the file: it is cut there in place, which needs no disk space (a full disk is the
        usual reason for a failed checkpoint). After a new column the file was rewritten, and so is it here."""
        n, columns, size = self._committed
        rewritten = columns != self.columns
        self.rows, self.columns = self.rows[:n], columns
        if rewritten:
            self._rewrite()
        else:
            os.truncate(self.path, size)

    def close(self) -> None:
        """Flush TensorBoard."""
        if self.tb is not None:
            self.tb.close()


def series(rows: list[dict[str, Any]], name: str) -> tuple[list[float], list[float]]:
    """``(steps, values)`` of the rows that have ``name``."""
    xs, ys = [], []
    for r in rows:
        v = r.get(name)
        if v not in (None, ""):
            xs.append(float(r["step"]))
            ys.append(float(v))
    return xs, ys


def plot_curves(rows: list[dict[str, Any]], path: str, title: str = "") -> None:
    """Draw the training curves as a PNG: the loss terms (log scale) and the evaluation metrics.

    Args:
        rows: metric rows as :class:`Logbook` keeps them.
        path: the PNG to write (atomically).
        title: a title over the figure.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = {k for r in rows for k in r if r.get(k) not in (None, "")}
    losses = sorted(k for k in names if k.startswith("loss/"))
    evals = [k for k in ("eval/miou", "eval/completion_iou", "eval/own_view_accuracy", "eval/novel_view_accuracy")
             if k in names]
    fig, axes = plt.subplots(1, 2, figsize=(12, 4.2))
    for k in losses:
        xs, ys = series(rows, k)
        # A short run logs a few points; a line through one point is invisible, so few points are marked.
        axes[0].plot(xs, ys, label=k.split("/", 1)[1], lw=1.2, marker="o" if len(xs) < 30 else None, ms=3)
    axes[0].set_yscale("log")
    axes[0].set_xlabel("step")
    axes[0].set_title("training losses")
    if losses:
        axes[0].legend(fontsize=8)
    for k in evals:
        xs, ys = series(rows, k)
        axes[1].plot(xs, ys, "o-", label=k.split("/", 1)[1], lw=1.2, ms=3)
    axes[1].set_xlabel("step")
    axes[1].set_ylabel("percent")
    axes[1].set_title("held-out evaluation")
    if evals:
        axes[1].legend(fontsize=8)
    for ax in axes:
        ax.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)

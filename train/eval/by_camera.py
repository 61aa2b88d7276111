"""Metrics against the camera: mIoU and own-view accuracy per bin of camera height and of camera pitch (issue 39's
chart), counted by the same :class:`~.metrics.Accumulator` as the report's overall numbers.

Each sample falls into one bin of each axis by its recorded camera (``batch["camera"]``,
:data:`fruxel.train.sim.cameras.CAMERA_KEYS`): its ``height`` above the floor (metres) and its ``pitch`` (degrees,
positive looking down). A bin ``i`` is ``edges[i] <= value < edges[i + 1]``, the last one closed at its top edge;
a sample outside the edges, or whose camera does not record the value (NaN: a data folder's photo without a
pose), is counted as such and in no bin. A bin's counts are those of its samples summed over every cell or pixel,
as the overall counts are: the counts of all bins add up to the overall ones for the samples inside the edges.

:func:`by_camera_section` writes the counts and metrics as the ``by_camera`` section of ``report.json``;
:func:`camera_chart` draws that section (``by_camera.png``), so the chart can always be drawn again from the JSON.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np
import torch

from fruxel.errors import ConfigError

from .metrics import Accumulator

HEIGHT_EDGES = tuple(round(0.3 + 0.2 * i, 6) for i in range(9))
"""Default camera-height bins: 0.3 to 1.9 m in 0.2 m steps (the any-camera test set's mounts lie inside)."""
PITCH_EDGES = tuple(float(e) for e in range(-20, 41, 10))
"""Default camera-pitch bins: -20 to 40 degrees (positive looking down) in 10 degree steps."""
AXES = {"height": ("m", "camera height above the floor"), "pitch": ("deg", "camera pitch, positive looking down")}
"""The binned axes: the camera record's key -> ``(unit, words)``."""
OUTSIDE = ("below", "above", "unrecorded")
"""What is counted of the samples in no bin: below the first edge, above the last, no recorded value (NaN)."""


@dataclass(frozen=True)
class CameraBins:
    """Bin edges of the camera axes; validated on construction (:class:`~fruxel.errors.ConfigError` naming the
    field)."""

    height: tuple[float, ...] = HEIGHT_EDGES
    """Edges of the camera-height bins, metres above the floor: at least two, finite, strictly increasing."""
    pitch: tuple[float, ...] = PITCH_EDGES
    """Edges of the camera-pitch bins, degrees (positive looking down): at least two, finite, strictly
    increasing."""

    def __post_init__(self) -> None:
        for axis in AXES:
            edges = getattr(self, axis)
            ok = (isinstance(edges, tuple) and len(edges) >= 2
                  and all(isinstance(e, (int, float)) and not isinstance(e, bool) and math.isfinite(e) for e in edges)
                  and all(a < b for a, b in zip(edges, edges[1:], strict=False)))
            if not ok:
                raise ConfigError(f"{axis} bin edges must be two or more finite, increasing numbers, got {edges!r}")

    def edges(self) -> dict[str, tuple[float, ...]]:
        """The edges by axis (keys of :data:`AXES`)."""
        return {axis: getattr(self, axis) for axis in AXES}


def bin_index(values: Any, edges: tuple[float, ...]) -> np.ndarray:
    """The bin of each value (module docstring).

    Args:
        values: ``(N,)`` float (any array or tensor; NaN: not recorded).
        edges: ``(K + 1,)`` increasing bin edges.

    Returns:
        ``(N,)`` int64: ``0..K-1`` the bin, ``-1`` below the first edge, ``K`` above the last, ``-2`` NaN.
    """
    v = np.asarray(values.cpu() if isinstance(values, torch.Tensor) else values, dtype=np.float64).reshape(-1)
    e = np.asarray(edges, dtype=np.float64)
    idx = np.searchsorted(e, v, side="right") - 1
    idx[v == e[-1]] = len(e) - 2  # the last bin includes its top edge
    idx[v > e[-1]] = len(e) - 1
    idx[np.isnan(v)] = -2
    return idx.astype(np.int64)


class CameraBinned:
    """One prediction rule's counts per camera bin: an :class:`Accumulator` per bin of each axis, plus the samples
    in no bin.

    Args:
        classes: C.
        bins: the bin edges.
    """

    def __init__(self, classes: int, bins: CameraBins) -> None:
        self.bins = bins
        self.accs = {axis: [Accumulator(classes) for _ in edges[1:]] for axis, edges in bins.edges().items()}
        """Per axis, one accumulator per bin (own-view counts and cell confusion; no novel views)."""
        self.outside = {axis: dict.fromkeys(OUTSIDE, 0) for axis in AXES}
        """Per axis, samples in no bin by why (:data:`OUTSIDE`)."""

    def add(self, pred: torch.Tensor, target: torch.Tensor, record: Mapping[str, Any]) -> None:
        """Count a batch into the bins of its cameras.

        Args:
            pred, target: ``(B, D, H, W)`` uint8 labels, grid frame (any device).
            record: the batch's camera record: ``height`` and ``pitch`` ``(B,)`` float64 (metres, degrees).
        """
        for axis, edges in self.bins.edges().items():
            idx = bin_index(record[axis], edges)
            for b in np.unique(idx).tolist():
                if 0 <= b < len(edges) - 1:
                    sel = torch.from_numpy(np.flatnonzero(idx == b)).to(pred.device)
                    self.accs[axis][b].add_volumes(pred[sel], target[sel])
                else:
                    why = "unrecorded" if b == -2 else "below" if b == -1 else "above"
                    self.outside[axis][why] += int((idx == b).sum())


def by_camera_section(binned: Mapping[str, CameraBinned], names: tuple[str, ...],
                      chart: str | None) -> dict[str, Any]:
    """The ``by_camera`` section of ``report.json``.

    Args:
        binned: the counts by rule key (the model's settings, :func:`fruxel.train.eval.report.rule_name`); all of
            one bins and one set of samples.
        names: the class names.
        chart: the chart's file beside the report, or None.

    Returns:
        Per axis (``height``, ``pitch``): ``unit``, ``edges``, ``samples`` per bin, ``outside`` (samples in no
        bin, :data:`OUTSIDE`), and per rule key: ``miou`` and ``own_view_accuracy`` per bin (percent; None where
        nothing was counted) with the counts behind them, ``confusion`` (per bin ``C x C`` ``[true][predicted]``),
        ``own_hits`` and ``own_correct``; then ``chart``.
    """
    first = next(iter(binned.values()))
    out: dict[str, Any] = {}
    for axis, edges in first.bins.edges().items():
        accs = {rule: b.accs[axis] for rule, b in binned.items()}
        summaries = {rule: [a.summary(names) for a in per_bin] for rule, per_bin in accs.items()}
        out[axis] = {
            "unit": AXES[axis][0],
            "edges": [float(e) for e in edges],
            "samples": [a.samples for a in first.accs[axis]],
            "outside": dict(first.outside[axis]),
            "miou": {r: [s["miou"] for s in ss] for r, ss in summaries.items()},
            "own_view_accuracy": {r: [s["own_view_accuracy"] for s in ss] for r, ss in summaries.items()},
            "confusion": {r: [a.conf.tolist() for a in per_bin] for r, per_bin in accs.items()},
            "own_hits": {r: [a.own_hits for a in per_bin] for r, per_bin in accs.items()},
            "own_correct": {r: [a.own_correct for a in per_bin] for r, per_bin in accs.items()},
        }
    out["chart"] = chart
    return out


LINE_STYLES = ("-", "--", ":", "-.")
"""Line style per camera-known setting, in order (then repeated)."""
METRIC_LINES = (("miou", "mIoU", "tab:blue", "o"), ("own_view_accuracy", "own-view accuracy", "tab:orange", "s"))
"""``(key, name, colour, marker)`` of the chart's lines."""


def camera_chart(section: Mapping[str, Any], labels: Mapping[str, str], path: str | os.PathLike[str], *,
                 title: str = "") -> None:
    """Write the chart of a ``by_camera`` section (:func:`by_camera_section`) as a PNG, atomically: a panel per
    axis with mIoU and own-view accuracy per bin (a colour per metric, a line style per rule) over grey bars of
    the samples per bin (right axis; their numbers in a row at the top).

    Args:
        section: the section, as in ``report.json``.
        labels: the legend's name of each rule key of the section (and its order).
        path: the PNG.
        title: a line over the panels.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    from fruxel.io import atomic_path

    fig, axes = plt.subplots(1, len(AXES), figsize=(6.0 * len(AXES), 4.6))
    for ax, axis in zip(np.atleast_1d(axes), AXES, strict=True):
        _panel(ax, section[axis], axis, labels)
    handles, names = np.atleast_1d(axes)[0].get_legend_handles_labels()
    # A legend column per rule (its metrics one under the other), so that long setting names fit the width.
    columns = len(labels) if len(labels) > 1 else len(METRIC_LINES)
    fig.legend(handles, names, loc="lower center", ncol=columns, fontsize=9, frameon=False)
    if title:
        fig.suptitle(title, fontsize=10)
    rows = -(-len(names) // columns)
    fig.tight_layout(rect=(0, 0.02 + 0.045 * rows, 1, 1))
    with atomic_path(path) as tmp:
        fig.savefig(tmp, dpi=110)
    plt.close(fig)


def _panel(ax: Any, part: Mapping[str, Any], axis: str, labels: Mapping[str, str]) -> None:
    """One axis' panel of :func:`camera_chart`."""
    edges = np.asarray(part["edges"], dtype=np.float64)
    centres, widths = (edges[1:] + edges[:-1]) / 2, np.diff(edges)
    counts = np.asarray(part["samples"])
    bars = ax.twinx()
    bars.bar(centres, counts, width=0.8 * widths, color="0.88", edgecolor="0.7", lw=0.5)
    bars.set_ylim(0, max(1, counts.max()) * 3.2)  # the bars keep to the panel's lower third, under the lines
    bars.set_ylabel("samples per bin", color="0.45", fontsize=8)
    bars.tick_params(axis="y", colors="0.45", labelsize=7)
    ax.set_zorder(bars.get_zorder() + 1)  # the lines over the bars
    ax.patch.set_visible(False)
    for r, (rule, label) in enumerate(labels.items()):
        for key, name, colour, marker in METRIC_LINES:
            ys = np.array([np.nan if v is None else v for v in part[key][rule]], dtype=np.float64)
            ax.plot(centres, ys, LINE_STYLES[r % len(LINE_STYLES)], color=colour, marker=marker, ms=4, lw=1.5,
                    label=f"{name}, {label}" if len(labels) > 1 or label else name)
    unit, words = AXES[axis]
    ax.set_xticks(edges)
    ax.set_xlim(edges[0], edges[-1])
    # The counts in a row above 100 %, where no curve can cover them.
    ax.set_ylim(0, 108)
    ax.set_yticks(range(0, 101, 20))
    for x, n in zip(centres, counts, strict=True):
        ax.text(x, 104, f"n={n}", ha="center", va="center", fontsize=7, color="0.3" if n else "0.6")
    ax.set_xlabel(f"{words} ({unit})")
    ax.set_ylabel("percent")
    ax.grid(alpha=0.3)
    where = {"below": f"below {edges[0]:g}", "above": f"above {edges[-1]:g}", "unrecorded": "unrecorded"}
    missed = ", ".join(f"{n} {where[k]}" for k, n in part["outside"].items() if n)
    ax.set_title(f"against {words}" + (f"; not in a bin: {missed}" if missed else ""), fontsize=10)

"""The training curves' PNG (train/engine/logbook.py)."""

from __future__ import annotations

from pathlib import Path

import matplotlib.figure
import pytest
from PIL import Image

from fruxel.train.engine.logbook import plot_curves


@pytest.mark.parametrize(("steps", "marked"), [(1, True), (5, True), (200, False)])
def test_loss_curves_mark_their_points_when_there_are_few(tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                                          steps: int, marked: bool) -> None:
    # A run of a few steps logs one loss row: a line through one point draws nothing, so the points are marked.
    rows = [{"step": 10 * (i + 1), "loss/total": 2.0 / (i + 1), "loss/ce": 1.0 / (i + 1)} for i in range(steps)]
    rows[-1].update({"eval/miou": 12.5, "eval/own_view_accuracy": 80.0})
    drawn = []
    save = matplotlib.figure.Figure.savefig

    def keep(fig, *args, **kwargs):  # noqa: ANN001, ANN002, ANN003, ANN202
        drawn.append([[(line.get_label(), len(line.get_xdata()), line.get_marker()) for line in ax.get_lines()]
                      for ax in fig.axes])
        return save(fig, *args, **kwargs)

    monkeypatch.setattr(matplotlib.figure.Figure, "savefig", keep)
    path = tmp_path / "curves.png"
    plot_curves(rows, str(path), title="run")
    losses, evals = drawn[0]
    assert sorted(label for label, _, _ in losses) == ["ce", "total"]
    assert all(n == steps for _, n, _ in losses)
    assert all((marker not in (None, "None", "", " ")) == marked for _, _, marker in losses)
    assert sorted(label for label, _, _ in evals) == ["miou", "own_view_accuracy"]
    with Image.open(path) as im:
        assert im.format == "PNG" and im.width > 500

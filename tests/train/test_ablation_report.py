"""scripts/ablation_report.py: the ablation's table and chart from fruxel-eval reports, and its one-line errors."""

from __future__ import annotations

import importlib.util
import json
from pathlib import Path

import pytest

ROOT = Path(__file__).parents[2]


def _script():  # noqa: ANN202
    spec = importlib.util.spec_from_file_location("ablation_report", ROOT / "scripts" / "ablation_report.py")
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def test_table_and_chart_from_two_reports(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    report = json.loads((ROOT / "docs" / "eval" / "ssz64-test8192.json").read_text())
    a, b = tmp_path / "a.json", tmp_path / "b.json"
    a.write_text(json.dumps(report))
    report["results"]["model"]["miou"] = 12.34
    b.write_text(json.dumps(report))
    png = tmp_path / "chart.png"
    assert _script().main([f"A={a}", f"B={b}", "--labels", "first", "second", "--png", str(png)]) == 0
    table = capsys.readouterr().out
    assert "| metric | A: first | B: second |" in table and "| 12.3 |" in table
    assert png.stat().st_size > 1000 and sorted(p.name for p in tmp_path.iterdir()) == ["a.json", "b.json",
                                                                                       "chart.png"]


@pytest.mark.parametrize("content, args, message", [
    (None, ["A={dir}/missing.json"], "missing.json: cannot read"),
    ("{not json", ["A={file}"], "not a fruxel-eval report"),
    ('{"results": {"model": {"miou": 1}}}', ["A={file}"], "no results.model.'completion_iou'"),
    ("{}", ["{file}"], "NAME=report.json"),
    ("{}", ["A={file}", "--labels", "x", "y"], None),
])
def test_bad_input_gets_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], content: str | None,
                                 args: list[str], message: str | None) -> None:
    file = tmp_path / "r.json"
    if content is not None:
        file.write_text(content)
    if message is None:  # a valid report, but two labels for one run
        file.write_text((ROOT / "docs" / "eval" / "ssz64-test8192.json").read_text())
        message = "one label per report"
    argv = [a.format(dir=tmp_path, file=file) for a in args]
    assert _script().main(argv) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err

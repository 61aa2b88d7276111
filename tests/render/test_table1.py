"""Tests of fruxel.render.table1 on a tiny run: every row measured, the table, the records and the markdown."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import pytest

import fruxel
from fruxel.data import SAMPLE_ROOM
from fruxel.data.rooms import room_volume
from fruxel.render import table1
from fruxel.render.table1 import SECTION, Table1Config, format_table, record, run, update_markdown

MODEL = fruxel.load(SAMPLE_ROOM)


@pytest.fixture(scope="module")
def result() -> table1.Table1Result:
    cfg = Table1Config(size=(64, 48), frames=2, baseline_frames=1, raycast_backends=("warp", "opencl", "vulkan"))
    return run(cfg, (MODEL.labels, MODEL.grid, MODEL.classes), log=lambda _: None)


def test_rows_and_ratios(result: table1.Table1Result) -> None:
    names = [r.name for r in result.rows]
    assert names[0].startswith("no simplification")
    assert sum("VMS shell" in n for n in names) == 3 and sum(n.startswith("ray cast") for n in names) == 3
    base = result.rows[0]
    assert base.ratio == pytest.approx(1.0) and base.triangles == 12 * MODEL.n_occupied
    for r in result.rows[:4]:
        assert r.frame_ms == pytest.approx(r.build_ms + r.upload_ms + r.draw_ms)
        assert r.fps == pytest.approx(1000.0 / r.frame_ms) and r.static_fps > 0
    shell_full, culled, greedy = result.rows[1:4]
    assert base.triangles > shell_full.triangles > culled.triangles > greedy.triangles > 0
    measured = [r for r in result.rows if r.kind == "raycast" and r.fps is not None]
    assert measured and all(r.triangles is None and r.upload_ms is None for r in measured)
    assert "unavailable" in result.rows[-1].note
    assert any("vulkan" in v for v in table1.verdicts(result))


def test_table_text(result: table1.Table1Result) -> None:
    text = format_table(result)
    assert "no simplification" in text and "420x" in text and "0.033 -> 14" in text
    assert len(text.splitlines()) == len(result.rows) + 3


def test_record_merges_machines_and_rewrites_only_its_section(result: table1.Table1Result, tmp_path: Path) -> None:
    md = tmp_path / "BENCHMARKS.md"
    md.write_text(f"# Benchmarks\n\n## Meshing\nkeep me\n\n{SECTION}\nold text\n\n## Kernels\nkeep me too\n")
    other = table1.Table1Result(machine=dict(result.machine, gpu="Test GPU"), config=result.config,
                                model=result.model, rows=result.rows)
    record(other, tmp_path / "results", md)
    written = record(result, tmp_path / "results", md)
    assert {p.name for p in written} == {"table1.json", "table1.png", "BENCHMARKS.md"}
    runs = json.loads((tmp_path / "results" / "table1.json").read_text())["runs"]
    assert set(runs) == {"Test GPU", table1.machine_tag(result.machine)}
    text = md.read_text()
    assert "keep me\n" in text and "## Kernels\nkeep me too" in text and "old text" not in text
    assert text.count(SECTION) == 1 and "### Test GPU" in text and "results/table1.png" in text
    assert (tmp_path / "results" / "table1.png").stat().st_size > 0


def test_update_markdown_creates_file(tmp_path: Path) -> None:
    md = tmp_path / "B.md"
    update_markdown(md, f"{SECTION}\n\nbody\n")
    assert md.read_text().startswith("# Benchmarks\n\n" + SECTION)


def test_room_volume_occupancy() -> None:
    labels, grid = room_volume(n=24, occupancy=0.2, seed=3)
    assert labels.shape == grid.shape == (24, 24, 24) and labels.dtype == np.uint8
    assert 0.2 <= np.mean(labels != 0) < 0.3
    again, _ = room_volume(n=24, occupancy=0.2, seed=3)
    assert np.array_equal(labels, again)


def test_benchmark_cli_writes_results(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    from fruxel.cli.render import main

    rc = main([str(SAMPLE_ROOM), "--benchmark", "--frames", "1", "--size", "48x36", "--backends", "opencl",
               "--out", str(tmp_path)])
    assert rc == 0
    out = capsys.readouterr().out
    assert "no simplification" in out and "paper" in out
    assert {p.name for p in tmp_path.iterdir()} >= {"table1.json", "table1.png", "table1.md"}


def test_benchmark_cli_rejects_unknown_backend_before_measuring(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from fruxel.cli.render import main

    rc = main(["--benchmark", "--backends", "warp,vulkn", "--out", str(tmp_path)])
    err = capsys.readouterr().err
    assert rc == 2 and err.count("\n") == 1 and "unknown backend 'vulkn'" in err
    assert not any(tmp_path.iterdir())

"""Every script in benchmarks/ starts and answers ``--help``: the scripts run outside the test suite (on lent
machines, for BENCHMARKS.md), so an import that a refactoring broke would otherwise surface only there."""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import pytest

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"
SCRIPTS = sorted(p for p in BENCHMARKS.glob("*.py") if p.name != "common.py")


def test_there_are_scripts() -> None:
    assert len(SCRIPTS) >= 8 and any(p.name == "table1.py" for p in SCRIPTS)


@pytest.mark.parametrize("script", SCRIPTS, ids=[p.stem for p in SCRIPTS])
def test_script_answers_help(script: Path) -> None:
    out = subprocess.run([sys.executable, str(script), "--help"], capture_output=True, text=True, timeout=120,
                         cwd=BENCHMARKS.parent)
    assert out.returncode == 0, out.stderr[-2000:]
    assert out.stdout.startswith("usage:"), out.stdout[:200]


def test_sim_bench_case_settings() -> None:
    """bench_sim's variant options reach the simulator's settings (a row's label says what it was made with)."""
    sys.path.insert(0, str(BENCHMARKS))
    try:
        import bench_sim
    finally:
        sys.path.remove(str(BENCHMARKS))
    plain = bench_sim.make_config(64, 16, 32, 16)
    varied = bench_sim.make_config(64, 16, 32, 16, rays="1/2/0", per_room=32)
    from fruxel.train.sim.config import SimConfig

    assert plain.samples_per_scene == SimConfig().samples_per_scene != 32 and varied.samples_per_scene == 32
    assert (varied.raytrace.samples_per_pixel, varied.raytrace.edge_samples, varied.raytrace.ao_samples) == (1, 2, 0)
    assert plain.raytrace.samples_per_pixel != 1

"""scripts/depth_noise_oracle.py: what a relative depth error leaves a reader perfect in everything else."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from .conftest import load_script, slab_volumes

ROOT = Path(__file__).resolve().parents[2]
Z_NEAR, DZ = 0.5, 0.25


@pytest.fixture(scope="module")
def oracle():
    return load_script("depth_noise_oracle")


def _truth(seed: int) -> np.ndarray:
    """``(2, 24, 5, 6)`` uint8: a slab three slices thick of class 1-3 in each column, somewhere in the middle."""
    return slab_volumes(seed, 24, (4, 16), 3)[0]


def _centre(k: np.ndarray) -> np.ndarray:
    return Z_NEAR + (k + 0.5) * DZ


def test_no_error_is_the_truth_and_an_error_moves_the_surface_by_its_factor(oracle) -> None:
    truth = _truth(0)
    none = np.zeros((2, 5, 6))
    np.testing.assert_array_equal(oracle.stretched(truth, none, Z_NEAR, DZ), truth)
    far = oracle.stretched(truth, none + 0.2, Z_NEAR, DZ)
    near = oracle.stretched(truth, none - 0.2, Z_NEAR, DZ)
    first = (truth != 0).argmax(axis=1)
    for moved, factor in ((far, 1.2), (near, 0.8)):
        got = _centre((moved != 0).argmax(axis=1))
        # The first moved cell lies within a slice of the true surface's near face times the factor.
        assert np.abs(got - (Z_NEAR + first * DZ) * factor).max() <= DZ
        assert set(np.unique(moved)) == set(np.unique(truth))


def test_cells_whose_source_lies_outside_the_grid_are_empty(oracle) -> None:
    truth = np.ones((1, 8, 1, 1), dtype=np.uint8)
    near = oracle.stretched(truth, np.full((1, 1, 1), -0.5), Z_NEAR, DZ)
    # z / 0.5 beyond the far face (0.5 + 8 * 0.25 = 2.5 m) from z = 1.25 m on: slices 3 to 7 empty.
    np.testing.assert_array_equal(near[0, :, 0, 0], [1, 1, 1, 0, 0, 0, 0, 0])


def test_the_score_is_perfect_without_error_and_falls_with_it(oracle) -> None:
    batches = [_truth(1), _truth(2)]
    results = oracle.oracle_miou(iter(batches), 4, Z_NEAR, DZ, [0.0, 0.02, 0.1, 0.3])
    mious = [m for m, _ in results]
    assert mious[0] == 100.0
    assert mious == sorted(mious, reverse=True) and mious[-1] < 50.0
    assert np.isnan(results[0][1][0])  # empty is not a class of the score


def test_first_surface_errors_are_relative_to_the_true_depth(oracle) -> None:
    truth = np.zeros((1, 10, 1, 3), dtype=np.uint8)
    truth[0, 4, 0, :] = 2
    pred = np.zeros_like(truth)
    pred[0, 6, 0, 0] = 1  # a column seen two slices deeper, of another class
    pred[0, 4, 0, 1] = 2  # a column right
    errors = oracle.first_surface_errors(pred, truth, Z_NEAR, DZ)  # column 2 has no predicted surface: left out
    np.testing.assert_allclose(errors, [_centre(6) / _centre(4) - 1.0, 0.0])


@pytest.mark.slow
def test_it_reads_fruxel_evals_samples(oracle, tmp_path: Path, monkeypatch: pytest.MonkeyPatch,
                                       capsys: pytest.CaptureFixture[str], tiny_pack: Path) -> None:
    """The tiny camera-aware model's grid on four streamed samples of the robot's test set: a line per sigma, the
    score falling with it, then the model's own first-surface REL."""
    monkeypatch.setenv("FRUXEL_ASSETS", str(tiny_pack))
    monkeypatch.setenv("FRUXEL_CACHE_DIR", str(tmp_path))
    model = ROOT / "tests" / "data" / "camera_tiny" / "model.safetensors"
    args = ["--model", str(model), "--test-set", "robot", "--samples", "4", "--batch", "4", "--sigma", "0,0.05",
            "--rel"]
    assert oracle.main(args) == 0
    lines = capsys.readouterr().out.strip().splitlines()
    assert [ln.split(":")[0] for ln in lines[:2]] == ["sigma 0 %", "sigma 5 %"]
    mious = [float(ln.split("mIoU ")[1].split()[0]) for ln in lines[:2]]
    assert mious[0] == 100.0 and mious[1] < 100.0
    assert len(lines) == 3 and "first-surface REL" in lines[2]


@pytest.mark.parametrize("script, args, says", [
    ("depth_noise_oracle", ["--sigma", "0.1,x"], "--sigma: not a list of numbers"),
    ("depth_noise_oracle", ["--sigma", "1.5"], "--sigma: each must be in [0, 1)"),
    ("depth_noise_oracle", ["--model", "no-such-model"], "no-such-model: no such file"),
    ("depth_noise_oracle", ["--samples", "0"], "--samples and --batch must be at least 1"),
    ("depth_tolerance", ["no-such-model"], "no-such-model: no such file"),
    ("depth_snap", ["no-such-model"], "no-such-model: no such file"),
])
def test_the_analysis_scripts_answer_bad_input_in_one_line(script: str, args: list[str], says: str,
                                                          capsys: pytest.CaptureFixture[str]) -> None:
    assert load_script(script).main(args) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and err[0].startswith(f"{script}.py: error: ") and says in err[0]

"""Own-view error breakdown (train/eval/own_view.py): the truth of fruxelize against what the camera sees."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from fruxel.grid import FruxelGrid
from fruxel.kernels.fruxelize import fruxelize
from fruxel.train.eval.metrics import first_surface
from fruxel.train.eval.own_view import (
    CATEGORIES,
    LABEL_SOURCES,
    JoinedMeshes,
    OwnViewBreakdown,
    depth_reader_accuracy,
    first_label_sources,
    holds_centre,
    label_behind,
    surface_extent,
    visible_surface,
)
from fruxel.train.sim.scene import boxes

GRID = FruxelGrid(width=16, height=16, depth=16, z_near=0.5, z_far=8.0, hfov=60.0)
WALL, BOARD, NEAR = 1, 4, 5


def _scene() -> list[tuple[np.ndarray, np.ndarray, int]]:
    """In the identity camera frame (z forward, y down): a thick wall across the view at 5-5.5 m; a 1 cm board in
    front of the left third, between two slices' centres (no cell centre inside it); a thick box in the right
    third, which contains centres; and a box closer than z_near in the bottom quarter's middle."""
    dz = GRID.dz
    gap = GRID.z_near + 4.0 * dz  # a slice boundary: the centres are dz / 2 either side
    wall = boxes([[-20, -20, 5.0]], [[20, 20, 5.5]])
    board = boxes([[-20, -20, gap - 0.005]], [[-0.5, 20, gap + 0.005]])
    thick = boxes([[0.5, -20, gap - 0.3]], [[20, 20, gap + 0.3]])
    near = boxes([[-0.2, 0.1, 0.2]], [[0.2, 0.3, 0.45]])
    return [(*wall, WALL), (*board, BOARD), (*thick, BOARD), (*near, NEAR)]


def test_visible_surface_and_the_breakdown_of_a_constructed_scene() -> None:
    meshes = _scene()
    pose = np.eye(4)
    labels, depth = visible_surface(meshes, GRID, pose)
    joined = JoinedMeshes(meshes)  # joined once, as for many poses of one scene: the same answer
    for _ in range(2):
        again = visible_surface(joined, GRID, pose)
        assert np.array_equal(again[0], labels) and np.array_equal(again[1], depth)
    truth = first_surface(torch.from_numpy(fruxelize(meshes, GRID, pose))[None].long())[0].numpy()
    centre = GRID.cell_to_point(np.zeros(16, int), np.full(16, 8), np.arange(16))
    u = centre[:, 0] / centre[:, 2]  # x / z of each column
    left, right = u * (GRID.z_near + 4.0 * GRID.dz) < -0.5, u * (GRID.z_near + 3.5 * GRID.dz) > 0.5
    row = 3  # above the near box
    # The board is seen where it is; the truth does not have it (no centre inside) and shows the wall behind.
    assert (labels[row, left] == BOARD).all() and (truth[row, left] == WALL).all()
    np.testing.assert_allclose(depth[row, left], GRID.z_near + 4.0 * GRID.dz - 0.005, atol=1e-6)
    extent = surface_extent(joined, GRID, pose, depth)
    behind = label_behind(joined, GRID, pose, depth, extent)
    assert (behind[row, left] == WALL).all() and (behind[row, right] == WALL).all()  # the wall behind board and box
    assert (label_behind(joined, GRID, pose, depth, np.full_like(extent, np.inf)) == 0).all()
    # The thick box is in both.
    assert (labels[row, right] == BOARD).all() and (truth[row, right] == BOARD).all()
    # The near box is seen before z_near; the truth starts behind it.
    near = depth < GRID.z_near
    assert near.any() and (labels[near] == NEAR).all() and not (truth == NEAR).any()

    b = OwnViewBreakdown()
    b.add(truth, truth, labels, depth, GRID)  # the truth itself: right everywhere
    hit = truth != 0
    assert int(b.hits.sum()) == int(hit.sum()) and (b.correct == b.hits).all()
    s = b.summary()
    assert s["accuracy"] == 100.0 and s["far"]["share"] == 0.0
    assert s["aliased"]["share"] > 10.0 and s["near"]["share"] > 0.0 and s["clean"]["share"] > 30.0
    assert sum(s[c]["share"] for c in CATEGORIES) == pytest.approx(100.0)

    seen = OwnViewBreakdown()
    seen.add(np.where((depth >= GRID.z_near) & (depth <= GRID.z_far), labels, 0), truth, labels, depth, GRID)
    r = seen.summary()  # a perfect reader of the image: right on clean pixels, wrong on the others
    assert r["clean"]["accuracy"] == 100.0 and r["aliased"]["accuracy"] == 0.0 and r["near"]["accuracy"] == 0.0
    assert r["accuracy"] == pytest.approx(r["clean"]["share"])
    assert r["aliased"]["lost"] + r["near"]["lost"] == pytest.approx(100.0 - r["accuracy"])


def test_surface_extent_splits_the_clean_pixels_by_depth_along_the_ray() -> None:
    # A 3 cm board around a slice's centre plane in front of the left part (the truth keeps it: clean, but thin),
    # and the 0.5 m wall behind.
    plane = GRID.z_near + 4.5 * GRID.dz
    wall = boxes([[-20, -20, 5.0]], [[20, 20, 5.5]])
    board = boxes([[-20, -20, plane - 0.015]], [[-0.5, 20, plane + 0.015]])
    meshes = [(*wall, WALL), (*board, BOARD)]
    pose = np.eye(4)
    joined = JoinedMeshes(meshes)
    labels, depth = visible_surface(joined, GRID, pose)
    extent = surface_extent(joined, GRID, pose, depth)
    truth = first_surface(torch.from_numpy(fruxelize(meshes, GRID, pose))[None].long())[0].numpy()
    on_board, on_wall = labels == BOARD, labels == WALL
    assert on_board.sum() > 20 and on_wall.sum() > 20 and (truth[on_board] == BOARD).all()
    np.testing.assert_allclose(extent[on_board], 0.03, atol=1e-6)
    np.testing.assert_allclose(extent[on_wall], 0.5, atol=1e-6)
    assert np.isinf(surface_extent(joined, GRID, pose, np.full_like(depth, np.inf))).all()
    # A prediction wrong on the board alone loses exactly the thin clean pixels.
    b = OwnViewBreakdown()
    b.add(np.where(on_board, WALL, truth), truth, labels, depth, GRID, extent)
    s = b.summary()
    assert s["clean"]["share"] == 100.0
    assert s["clean_thin"]["share"] == pytest.approx(100.0 * on_board.sum() / (truth != 0).sum())
    assert s["clean_thin"]["accuracy"] == 0.0 and s["clean_thick"]["accuracy"] == 100.0
    assert s["clean_thin"]["lost"] + s["clean_thick"]["lost"] == pytest.approx(s["clean"]["lost"])
    plain = OwnViewBreakdown()
    plain.add(truth, truth, labels, depth, GRID)  # without extents: no split
    assert "clean_thin" not in plain.summary()


def test_empty_breakdown_has_no_numbers() -> None:
    s = OwnViewBreakdown().summary()
    assert s["pixels"] == 0 and s["accuracy"] is None and s["clean"]["accuracy"] is None


def test_own_view_errors_script(tmp_path, capsys: pytest.CaptureFixture[str]) -> None:  # noqa: ANN001
    import dataclasses
    import importlib.util
    import json
    from pathlib import Path

    from fruxel.train.config import ModelConfig, TrainConfig
    from fruxel.train.engine.trainer import sim_config
    from fruxel.train.export import build_generator, save_shipped
    from fruxel.train.sim.writer import generate

    spec = importlib.util.spec_from_file_location("own_view_errors",
                                                  Path(__file__).parents[2] / "scripts" / "own_view_errors.py")
    script = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(script)
    cfg = ModelConfig(grid=GRID, levels=3, stem=8, encoder=(8, 8, 8), encoder_blocks=(1, 1, 1), topdown=(8, 8, 8),
                      decoder=(8, 8, 8), decoder_blocks=(1, 1, 1))
    data = tmp_path / "data"
    generate(str(data), dataclasses.replace(sim_config(TrainConfig(model=cfg)), splits=(("test", 3),), shard_size=4),
             0, progress=False)
    model = tmp_path / "m.safetensors"
    torch.manual_seed(0)
    save_shipped(model, build_generator(cfg), cfg, {}, half=False)
    out = tmp_path / "o.json"
    png = tmp_path / "readers.png"
    assert script.main([str(model), "--data", str(data), "--samples", "3", "--batch", "2", "--uniform", "1000",
                        "--sigmas", "0", "0.05", "inf", "--png", str(png), "--json", str(out)]) == 0
    printed = capsys.readouterr().out
    report = json.loads(out.read_text())
    assert report["samples"] == 3 and report["pixels"] > 0 and "| clean |" in printed
    assert sum(report[c]["share"] for c in CATEGORIES) == pytest.approx(100.0)
    assert report["clean_thin"]["share"] + report["clean_thick"]["share"] == pytest.approx(report["clean"]["share"])
    assert "| clean, first solid under a slice deep |" in printed
    # --uniform 1000: every image counts as near-uniform, so that part is the whole.
    assert report["uniform"]["samples"] == 3 and report["uniform"]["pixels"] == report["pixels"]
    assert report["uniform"]["points_lost"] == pytest.approx(100.0 - report["accuracy"])
    # The thin solids (under a slice deep, here 0.47 m) and the idealised readers of them.
    thin = report["thin"]
    assert thin["pixels"] > 0 and 0 <= thin["kept"] <= 100 and "| reader's depth error m |" in printed
    assert [r["sigma"] for r in thin["readers"]] == [0.0, 0.05, "inf"] and png.stat().st_size > 0
    exact, _, blind = (r["thin_accuracy"] for r in thin["readers"])
    assert exact >= blind and exact > 90.0
    # The first occupied cell's class from other sources: the model's own is the own view itself, and no source
    # can be right on a column the prediction leaves empty.
    sources = report["label_sources"]
    assert sources["model"] == pytest.approx(report["accuracy"]) and "| the surface head |" in printed
    assert all(0.0 <= sources[k] <= 100.0 - sources["empty"] + 1e-9 for k in LABEL_SOURCES)
    assert script.main([str(model), "--data", str(data), "--samples", "0"]) == 2
    assert len(capsys.readouterr().err.strip().splitlines()) == 1
    assert script.main([str(model), "--data", str(data), "--sigmas", "-1"]) == 2
    assert "--sigmas" in capsys.readouterr().err


def _thin_solids(n: int, seed: int = 1) -> tuple[np.ndarray, np.ndarray]:
    """n thin solids at uniform depths in range, extents uniform in [0, dz)."""
    rng = np.random.default_rng(seed)
    return rng.uniform(GRID.z_near, GRID.z_far - GRID.dz, n), rng.uniform(0.0, GRID.dz, n)


def test_holds_centre_agrees_with_the_cell_centres_counted_one_by_one() -> None:
    depth, extent = _thin_solids(2000)
    extent[:500] *= 3.0  # some thicker than a slice: they always hold one
    centres = GRID.z_near + (np.arange(GRID.depth) + 0.5) * GRID.dz
    brute = ((centres[None] >= depth[:, None]) & (centres[None] <= (depth + extent)[:, None])).any(axis=1)
    got = holds_centre(depth, extent, GRID)
    assert np.array_equal(got, brute)
    assert got[extent >= GRID.dz].all() and 0.2 < got.mean() < 0.9


def test_depth_reader_accuracy_falls_from_exact_to_blind_as_its_depth_error_grows() -> None:
    depth, extent = _thin_solids(4000)
    kept = holds_centre(depth, extent, GRID)
    blind = float(((extent >= 0.5 * GRID.dz) == kept).mean())
    assert depth_reader_accuracy(depth, extent, kept, ~kept, GRID, 0.0) == 1.0
    assert depth_reader_accuracy(depth, extent, kept, ~kept, GRID, float("inf")) == blind
    assert blind == pytest.approx(0.75, abs=0.03)  # E[max(L/dz, 1 - L/dz)] for L uniform in [0, dz)
    acc = [depth_reader_accuracy(depth, extent, kept, ~kept, GRID, s, draws=8) for s in (1e-4, 0.01, 0.03, 0.06, 2.0)]
    assert acc[0] > 0.99  # a tiny error: nearly always right (a wrong sign of the phase would not be)
    assert all(a > b for a, b in zip(acc, acc[1:-1], strict=False))
    assert acc[-1] == pytest.approx(blind, abs=0.02)  # a large error: no better than knowing nothing
    # The truth flipped: a reader that trusts its depth is now nearly always wrong.
    assert depth_reader_accuracy(depth, extent, ~kept, kept, GRID, 1e-4, draws=2) < 0.01
    # Where the solid and what lies behind it share a label, either call is right.
    same = np.arange(len(kept)) % 2 == 0
    assert depth_reader_accuracy(depth, extent, kept | same, ~kept | same, GRID, float("inf")) == pytest.approx(
        0.5 + 0.5 * float(((extent >= 0.5 * GRID.dz) == kept)[~same].mean()))
    assert np.isnan(depth_reader_accuracy(depth[:0], extent[:0], kept[:0], kept[:0], GRID, 0.01))
    for bad in (-0.01, float("nan")):
        with pytest.raises(ValueError, match="sigma"):
            depth_reader_accuracy(depth, extent, kept, ~kept, GRID, bad)


def test_plot_depth_readers_writes_a_png(tmp_path) -> None:
    from PIL import Image

    from fruxel.train.eval.own_view import plot_depth_readers

    path = tmp_path / "readers.png"
    readers = [{"sigma": s, "own_view": v} for s, v in ((0.0, 99.5), (0.02, 97.4), (0.05, 96.6), (float("inf"), 96.1))]
    plot_depth_readers(readers, 96.9, str(path), title="t")
    img = np.asarray(Image.open(path).convert("RGB")).astype(int)
    assert img.shape[0] > 200 and img.shape[1] > 300
    green = (abs(img - np.array([0x1B, 0x9E, 0x77])).sum(axis=2) < 40).sum()  # the readers' line is drawn
    assert green > 100
    assert [p.name for p in tmp_path.iterdir()] == ["readers.png"]  # no temporary file left


def test_first_label_sources_read_the_first_cells_class_from_each_source() -> None:
    # One batch of three columns along W (C = 3: empty, wall, board; D = 3). Column 0: the ruled volume's first cell
    # is a wall in slice 1; the raw volume makes a board the likelier first hit; the head says wall. Column 1: the
    # ruled volume's first cell is a board in slice 0; the head says wall, weakly. Column 2: empty.
    big = 10.0
    ruled = torch.full((1, 3, 3, 1, 3), -big)
    ruled[0, 0] = big  # every cell empty ...
    ruled[0, 0, 1, 0, 0], ruled[0, 1, 1, 0, 0] = -big, big  # ... but a wall in column 0's slice 1
    ruled[0, 0, 0, 0, 1], ruled[0, 2, 0, 0, 1] = -big, big  # and a board in column 1's slice 0
    raw = torch.zeros(1, 3, 3, 1, 3)
    raw[0, 2, 0, 0, 0] = 3.0  # column 0: a board is likely in slice 0, so the first hit is most likely a board
    raw[0, 2, :, 0, 1] = 3.0  # column 1: board everywhere
    head = torch.zeros(1, 3, 1, 3)
    head[0, 1, 0, 0] = 5.0  # column 0: wall, surely
    head[0, 1, 0, 1] = 0.5  # column 1: wall, a little likelier than a board
    got = first_label_sources(raw, head, ruled)
    assert set(got) == set(LABEL_SOURCES)
    assert got["model"].tolist() == [[[1, 2, 0]]]  # wall, board, empty
    assert got["volume"].tolist() == [[[2, 2, 0]]]
    assert got["head"].tolist() == [[[1, 1, 0]]]
    # Together: the head's sure wall outweighs the volume's board in column 0; the volume's sure board outweighs
    # the head's slight wall in column 1. The empty column stays empty under every source.
    assert got["both"].tolist() == [[[1, 2, 0]]]

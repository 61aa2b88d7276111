"""Tests of fruxel.render.raycast: shading matches fruxel.shading.shade_hits, on numpy and torch, and scores
give the same image as their labels."""

from __future__ import annotations

import numpy as np
import pytest

import fruxel
from fruxel.data import SAMPLE_ROOM
from fruxel.kernels import Hits
from fruxel.render.cli import default_camera
from fruxel.render.raycast import RaycastStyle, first_hits, fog_range, lambert, raycast_image, shade, to_numpy
from fruxel.shading import shade_hits

MODEL = fruxel.load(SAMPLE_ROOM)
PALETTE = MODEL.classes.palette()
CAM = default_camera(MODEL.grid, 120, 90)


@pytest.fixture(scope="module")
def hits() -> Hits:
    h = first_hits(MODEL.labels, MODEL.grid, CAM)
    return Hits(label=to_numpy(h.label), cell=to_numpy(h.cell), depth=to_numpy(h.depth), normal=to_numpy(h.normal))


@pytest.mark.parametrize("style", [RaycastStyle(), RaycastStyle(fog=True), RaycastStyle(shading="flat"),
                                   RaycastStyle(ambient=0.1, light=(0.3, -1.0, -0.2), background=(10, 20, 30))])
def test_shade_matches_shade_hits(hits: Hits, style: RaycastStyle) -> None:
    fog = fog_range(hits.depth, hits.label != 0) if style.fog else None
    expected = shade_hits(hits.label, hits.normal, hits.depth, PALETTE, CAM.rotation, light=style.light,
                          ambient=style.effective_ambient, fog=fog, background=style.background)
    got = shade(hits, CAM, PALETTE, style)
    assert got.dtype == np.uint8 and got.shape == expected.shape
    assert np.abs(got.astype(int) - expected.astype(int)).max() <= 1


def test_torch_hits_shade_like_numpy(hits: Hits) -> None:
    torch = pytest.importorskip("torch")
    th = Hits(*(torch.from_numpy(np.asarray(a)) for a in (hits.label, hits.cell, hits.depth, hits.normal)))
    for style in (RaycastStyle(), RaycastStyle(fog=True)):
        a = shade(th, CAM, PALETTE, style).astype(int)
        b = shade(hits, CAM, PALETTE, style).astype(int)
        assert np.abs(a - b).max() <= 1


def test_flat_shading_is_the_palette(hits: Hits) -> None:
    img = shade(hits, CAM, PALETTE, RaycastStyle(shading="flat"))
    expected = np.where((hits.label != 0)[..., None], PALETTE[hits.label], 255)
    assert np.array_equal(img, expected)


def test_scores_give_the_labels_image() -> None:
    rng = np.random.default_rng(1)
    lg = rng.normal(0.0, 0.1, (1, len(PALETTE), *MODEL.grid.shape)).astype(np.float32)
    np.put_along_axis(lg[0], MODEL.labels[None].astype(np.int64), 2.0, axis=0)
    a, la = raycast_image(lg, MODEL.grid, CAM, PALETTE)
    b, lb = raycast_image(MODEL.labels, MODEL.grid, CAM, PALETTE)
    assert np.array_equal(la, lb) and np.array_equal(a, b)
    assert la.dtype == np.int32 and la.shape == (CAM.height, CAM.width)


def test_lambert_range() -> None:
    n = np.array([[0, 0, -1], [0, 0, 1], [1, 0, 0]], np.float32)
    out = lambert(n, (0, 0, -2.0), 0.25)
    np.testing.assert_allclose(out, [1.0, 0.25, 0.25])


def test_style_validation() -> None:
    with pytest.raises(ValueError):
        RaycastStyle(shading="toon")
    with pytest.raises(ValueError):
        RaycastStyle(ambient=-0.1)

"""Tests of fruxel.render.raycast and fruxel.render.shading: shading matches a float64 numpy reference of its
formula, torch gives numpy's bytes, and scores give the same image as their labels."""

from __future__ import annotations

import numpy as np
import pytest

import fruxel
from fruxel.data import SAMPLE_ROOM
from fruxel.kernels import Hits
from fruxel.render.frames import default_camera
from fruxel.render.raycast import first_hits, raycast_image
from fruxel.render.shading import RaycastStyle, fog_range, lambert, shade, to_numpy

MODEL = fruxel.load(SAMPLE_ROOM)
PALETTE = MODEL.classes.palette()
CAM = default_camera(MODEL.grid, 120, 90)


def shade_hits(label: np.ndarray, normal: np.ndarray, depth: np.ndarray, palette: np.ndarray, rotation: np.ndarray,
               light: tuple[float, float, float], ambient: float, fog: tuple[float, float] | None,
               background: tuple[int, int, int]) -> np.ndarray:
    """Reference: the shading formula of fruxel.render.shading in float64 numpy, written out plainly."""
    ldir = rotation @ np.asarray(light, np.float64)
    ldir /= np.linalg.norm(ldir)
    colour = palette[label].astype(np.float64) * (ambient + (1 - ambient) * np.clip(normal @ ldir, 0, 1))[..., None]
    bg = np.asarray(background, np.float64)
    if fog is not None:
        f = np.clip((depth - fog[0]) / (fog[1] - fog[0]), 0, 1)[..., None]
        colour = colour * (1 - f) + bg * f
    return np.clip(np.rint(np.where((label != 0)[..., None], colour, bg)), 0, 255).astype(np.uint8)


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
    """One formula, the same float32 operations: torch tensors give numpy's bytes."""
    torch = pytest.importorskip("torch")
    th = Hits(*(torch.from_numpy(np.asarray(a)) for a in (hits.label, hits.cell, hits.depth, hits.normal)))
    for style in (RaycastStyle(), RaycastStyle(fog=True), RaycastStyle(shading="flat")):
        np.testing.assert_array_equal(shade(th, CAM, PALETTE, style), shade(hits, CAM, PALETTE, style))


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


@pytest.mark.parametrize("style", [RaycastStyle(shading="flat"), RaycastStyle(fog=True)])
def test_large_images_are_cast_in_bands(style: RaycastStyle, monkeypatch: pytest.MonkeyPatch) -> None:
    """Beyond MAX_TILE_PIXELS an image is cast in bands of rows; it equals the image cast at once (fog over the
    whole image's depth range, not per band)."""
    from fruxel.render import raycast

    whole, lw = raycast_image(MODEL.labels, MODEL.grid, CAM, PALETTE, style=style)
    monkeypatch.setattr(raycast, "MAX_TILE_PIXELS", 7 * CAM.width + 5)
    banded, lb = raycast_image(MODEL.labels, MODEL.grid, CAM, PALETTE, style=style)
    assert banded.shape == whole.shape and lb.dtype == np.int32
    assert np.mean(lb != lw) < 1e-3
    same = lb == lw
    assert np.abs(banded.astype(int) - whole.astype(int))[same].max() <= 1

"""The footprint experiment's network: it starts as the network it grows from, and each cell reads the image where
its floor footprint is seen (on the floor: its own pixel), nothing where that is not known or not seen."""

from __future__ import annotations

import dataclasses
import math

import torch

from fruxel.train.config import preset
from fruxel.train.models.conditioning import CameraInput

from .conftest import load_experiment

fl = load_experiment("footprint_lift")


def _pair() -> tuple[torch.nn.Module, torch.nn.Module, object]:
    base_cfg = preset("tiny").model
    cfg = fl.FootprintSSZConfig(**{f.name: getattr(base_cfg, f.name) for f in dataclasses.fields(base_cfg)})
    torch.manual_seed(0)
    base = base_cfg.build().eval()
    net = cfg.build().eval()
    missing = net.load_state_dict(base.state_dict(), strict=False).missing_keys
    assert missing and all(k.startswith("footprint.") for k in missing)
    return base, net, cfg


def _camera(pitch_deg: float, height: float, known: tuple[float, float] = (1.0, 1.0)) -> CameraInput:
    p = math.radians(pitch_deg)
    # OpenCV camera frame: a camera pitched down by p sees gravity at (0, cos p, sin p).
    return CameraInput.of([[0.0, math.cos(p), math.sin(p)]], [height], [list(known)])


def test_starts_as_the_network_it_grows_from_and_its_term_reads_the_told_pose_only() -> None:
    base, net, cfg = _pair()
    img = torch.rand(1, 3, *cfg.image_size, generator=torch.Generator().manual_seed(1))
    told, unknown = _camera(15.0, 1.2), CameraInput.unknown(1)
    with torch.no_grad():
        assert torch.equal(base(img, told).logits, net(img, told).logits)
        for conv in net.footprint:
            torch.nn.init.normal_(conv.weight, std=0.5)
            torch.nn.init.normal_(conv.bias, std=0.5)
        assert (base(img, told).logits - net(img, told).logits).abs().max() > 1e-3
        assert torch.equal(base(img, unknown).logits, net(img, unknown).logits)
        gravity_only = _camera(15.0, 1.2, (1.0, 0.0))
        assert torch.equal(base(img, gravity_only).logits, net(img, gravity_only).logits)


def test_a_cell_on_the_floor_is_seen_at_its_own_pixel_and_one_above_it_lower_in_the_image() -> None:
    _, net, cfg = _pair()
    g, h = cfg.grid, 1.2
    cam = _camera(20.0, h)
    xy, ok = net.footprint_points(cam, 0)
    xy = xy.view(g.depth, g.height, g.width, 2)
    centres = net.conditioning.centres0[0]  # (3, D, H, W)
    above = h - (cam.gravity[0].view(3, 1, 1, 1) * centres).sum(dim=0)
    k, j, i = (above.abs() < 0.01).nonzero(as_tuple=True)
    assert len(k) > 10
    pixel = 2.0 / g.width
    assert (xy[k, j, i, 0] - ((i + 0.5) / g.width * 2 - 1)).abs().max() < 0.1 * pixel
    assert (xy[k, j, i, 1] - ((j + 0.5) / g.height * 2 - 1)).abs().max() < 0.5 * pixel
    k, j, i = (above > 0.3).nonzero(as_tuple=True)
    assert bool((xy[k, j, i, 1] > (j + 0.5) / g.height * 2 - 1).all())
    assert ok.min() == 1.0


def test_footprints_behind_the_camera_or_not_told_are_not_read() -> None:
    _, net, _ = _pair()
    # Pitched 40 degrees up, the floor below a far cell near the top of the view lies behind the camera plane.
    _, ok = net.footprint_points(_camera(-40.0, 1.5), 0)
    assert 0.0 < ok.mean() < 1.0
    for known in ((0.0, 0.0), (1.0, 0.0), (0.0, 1.0)):
        _, ok = net.footprint_points(_camera(15.0, 1.2, known), 0)
        assert ok.max() == 0.0

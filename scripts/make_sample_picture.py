"""Draw the bundled sample room's picture (``fruxel/data/sample_room.png``, shown in the README).

Run ``python scripts/make_sample_picture.py [--out PATH]`` after ``python scripts/make_sample.py``. It lives
outside the package because it needs pyrender, which the numpy-only core (``fruxel/``) never imports: the culled
trapezoid mesh of the model, the frustum's edges, two directional lights, rendered offscreen from an oblique pose.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

import fruxel
from fruxel.data import SAMPLE_ROOM
from fruxel.io import atomic_path
from fruxel.model import FruxelModel

VIEW_EYE = (2.4, -8.0, -2.8)
"""Viewpoint of the picture, grid frame, metres: high above, right of and behind the grid camera."""
VIEW_TARGET = (0.4, -0.6, 3.8)
"""Point the picture's camera looks at, grid frame, metres: the middle of the frustum's occupied part."""


def render_picture(
    model: FruxelModel,
    path: Path,
    size: tuple[int, int] = (960, 720),
    eye: tuple[float, float, float] = VIEW_EYE,
    target: tuple[float, float, float] = VIEW_TARGET,
) -> None:
    """Render the model's culled mesh offscreen from an oblique pose and write a PNG.

    Args:
        model: the model to draw.
        path: PNG file to write.
        size: image ``(width, height)`` in pixels.
        eye: ``(3,)`` viewpoint, grid frame, metres.
        target: ``(3,)`` point looked at, grid frame, metres.
    """
    from PIL import Image

    from fruxel.camera import Camera
    from fruxel.mesh import mesh_labels, to_trimesh
    from fruxel.render.compat import import_pyrender
    from fruxel.render.scene import frustum_lines

    pyrender = import_pyrender(headless=True)

    mesh = mesh_labels(model.labels, model.grid, model.classes.palette(), mode="culled")
    scene = pyrender.Scene(bg_color=[1.0, 1.0, 1.0, 1.0], ambient_light=[0.35, 0.35, 0.35])
    scene.add(pyrender.Mesh.from_trimesh(to_trimesh(mesh), smooth=False))

    scene.add(frustum_lines(model.grid))  # the frustum's 12 edges give the grid's extent

    cam = Camera.look_at(eye=eye, target=target, width=size[0], height=size[1], hfov=50.0)
    yfov = 2.0 * np.arctan(size[1] / (2.0 * cam.fy))
    scene.add(pyrender.PerspectiveCamera(yfov=yfov, aspectRatio=size[0] / size[1]), pose=cam.opengl_pose())
    # A key light over the viewer's shoulder and a weaker fill from the other side, so that the three plane
    # families of the trapezoid faces get distinct shades.
    key = Camera.look_at(eye=(-4.0, -6.0, 0.5), target=target)
    fill = Camera.look_at(eye=(5.0, -2.0, 1.0), target=target)
    scene.add(pyrender.DirectionalLight(intensity=3.0), pose=key.opengl_pose())
    scene.add(pyrender.DirectionalLight(intensity=1.2), pose=fill.opengl_pose())

    renderer = pyrender.OffscreenRenderer(*size)
    try:
        color, _ = renderer.render(scene)
    finally:
        renderer.delete()
    with atomic_path(path) as tmp:
        Image.fromarray(color).save(tmp, optimize=True)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--model", type=Path, default=SAMPLE_ROOM, help="model .npz (default: the sample room)")
    parser.add_argument("--out", type=Path, default=SAMPLE_ROOM.with_suffix(".png"), help="PNG to write")
    args = parser.parse_args(argv)
    render_picture(fruxel.load(args.model), args.out)
    print(f"{args.out}: {args.out.stat().st_size} bytes")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

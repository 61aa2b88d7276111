"""Camera images of simulated rooms (pyrender offscreen, PBR materials) with appearance augmentation, and the
preview contact sheet. :class:`SceneRenderer` is the simulator's default renderer, ``"pyrender"`` (:mod:`.renderer`).

Camera
    The robot camera of :meth:`SimConfig.image_camera`: ``S x (S * H / W)`` pixels with the grid's field of view
    and the robot's camera-to-world pose (OpenCV axes, world frame z up), or any other camera given to
    :meth:`SceneRenderer.render` (intrinsics and image size; :mod:`.cameras` asks for those). pyrender gets the same
    intrinsics (``IntrinsicsCamera``) and the OpenGL pose ``pose @ diag(1, -1, -1, 1)``; pixel ``(x, y)`` of the
    image then covers ``[x, x + 1) x [y, y + 1)`` of :meth:`fruxel.Camera.project`, so the image lines up with the
    grid.

Scene
    Every :class:`SceneObject` becomes one pyrender mesh with a metallic-roughness material (base colour,
    metallic, roughness; alpha < 1, the window glass, is blended), drawn with flat normals (the simulator's
    solids are boxes and faceted shapes) and without face culling (asset meshes may be open or inside out).
    The scene's lights become pyrender directional and point lights; no shadows.

Augmentation (:class:`AugmentConfig`, one random generator per sample, values drawn in a fixed order whether
or not a step is enabled, so that turning one off does not reshuffle the others)
    before drawing: each light's intensity and colour, the ambient level, each object's base colour, and the
    saturation of the object and background colours; after drawing, on the RGB image in [0, 1]: exposure
    ``2 ** ev``, white balance (per-channel gains) and gamma (one lookup table per channel), then Gaussian noise
    and rounding to uint8.

Determinism: the same scene, pose and generator give the same bytes on the same machine and OpenGL driver
(Mesa's llvmpipe is deterministic; the image bytes of one sample can differ between GL drivers, e.g. llvmpipe
and NVIDIA, by rounding of the shading).

One offscreen renderer per process (:func:`fruxel.render.scene.renderers`): its OpenGL (EGL) context must not
cross a ``fork``; the generator and the training engine's data workers start with ``spawn``.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from fruxel.camera import OPENCV_TO_OPENGL, Camera, check_pose, look_at_grid
from fruxel.render.compat import default_font, import_pyrender
from fruxel.render.legend import wrap_text
from fruxel.render.scene import renderers

from .config import SimConfig

if TYPE_CHECKING:
    from .scene import Scene

_LUMA = np.array([0.299, 0.587, 0.114], dtype=np.float32)
"""Rec. 601 weights: the grey value that saturation changes blend with."""


_ORDERED_SCENE: list[type] = []


def _ordered_scene_class() -> type:
    """A ``pyrender.Scene`` whose mesh and light nodes iterate in the order they were added.

    pyrender keeps nodes in sets, ordered by object address, and draws meshes and sums lights in that order: the
    same scene then gives images that differ in the last bit of a few pixels from run to run (light sums in
    another order, coplanar faces resolved by another draw order). Fixed order makes the bytes reproducible.
    """
    if _ORDERED_SCENE:
        return _ORDERED_SCENE[0]
    pr = import_pyrender()

    class OrderedScene(pr.Scene):
        def add_node(self, node: Any, parent_node: Any = None) -> None:
            # pyrender's __init__ adds nodes before a subclass could set attributes up.
            order = self.__dict__.setdefault("_insertion", {})
            super().add_node(node, parent_node)
            order[node] = len(order)

        def _ordered(self, nodes: Any) -> list[Any]:
            return sorted(nodes, key=self.__dict__.setdefault("_insertion", {}).__getitem__)

        @property
        def mesh_nodes(self) -> list[Any]:
            return self._ordered(self._mesh_nodes)

        @property
        def point_light_nodes(self) -> list[Any]:
            return self._ordered(self._point_light_nodes)

        @property
        def spot_light_nodes(self) -> list[Any]:
            return self._ordered(self._spot_light_nodes)

        @property
        def directional_light_nodes(self) -> list[Any]:
            return self._ordered(self._directional_light_nodes)

        @property
        def light_nodes(self) -> list[Any]:
            return self._ordered(self._point_light_nodes | self._spot_light_nodes | self._directional_light_nodes)

    _ORDERED_SCENE.append(OrderedScene)
    return OrderedScene


@dataclass
class _Drawn:
    """The pyrender side of one room, kept for all frames of a trajectory."""

    scene: Any
    """``pyrender.Scene``."""
    camera: Any
    """The camera node."""
    materials: list[Any]
    """One ``MetallicRoughnessMaterial`` per scene object, in object order."""
    base_colours: np.ndarray
    """``(M, 4)`` float64 RGBA base colours as generated."""
    lights: list[Any]
    """The light objects (``DirectionalLight`` / ``PointLight``), in the scene's order."""
    light_colours: np.ndarray
    """``(L, 3)`` float64 light colours as generated."""
    light_intensities: np.ndarray
    """``(L,)`` float64 light intensities as generated, times ``ImageConfig.light_scale``."""


class SceneRenderer:
    """Offscreen images of simulated rooms from the robot camera; one per process, reused across rooms.

    The renderer called ``"pyrender"`` (the default of :attr:`SimConfig.renderer`; protocol in :mod:`.renderer`).

    Args:
        config: supplies the image size, clip planes, background and augmentation ranges, and the grid's field
            of view.

    Use :meth:`set_scene` once per room, then :meth:`render` per pose; :meth:`close` (or ``with``) frees the
    room. Images are drawn by the process's one offscreen renderer (:func:`fruxel.render.scene.renderers`).
    """

    def __init__(self, config: SimConfig) -> None:
        self.config = config
        """The generator settings."""
        self._pyrender = import_pyrender()
        self._drawn: _Drawn | None = None
        self._scene: Scene | None = None

    # ------------------------------------------------------------------ rooms
    def set_scene(self, scene: Scene) -> None:
        """Upload a room (meshes, materials, lights); the previous room's GPU buffers are released on the next
        draw."""
        if self._scene is scene and self._drawn is not None:
            return
        pr = self._pyrender
        img = self.config.image
        ps = _ordered_scene_class()(bg_color=(*img.background, 1.0), ambient_light=np.zeros(3))
        materials, colours = [], []
        for obj in scene.objects:
            colour = np.asarray(obj.color, dtype=np.float64)
            mat = pr.MetallicRoughnessMaterial(
                baseColorFactor=colour, metallicFactor=float(obj.metallic), roughnessFactor=float(obj.roughness),
                alphaMode="BLEND" if colour[3] < 1.0 else "OPAQUE", doubleSided=True,
            )
            ps.add(pr.Mesh.from_trimesh(obj.mesh, material=mat, smooth=False), name=obj.name)
            materials.append(mat)
            colours.append(colour)
        lights, lcol, lint = [], [], []
        for light in scene.lights:
            cls = pr.DirectionalLight if light.kind == "directional" else pr.PointLight
            lo = cls(color=np.asarray(light.color, dtype=np.float64),
                     intensity=float(light.intensity * img.light_scale))
            ps.add(lo, pose=np.asarray(light.pose, dtype=np.float64))
            lights.append(lo)
            lcol.append(light.color)
            lint.append(light.intensity * img.light_scale)
        cam = self.config.image_camera()
        node = ps.add(pr.IntrinsicsCamera(cam.fx, cam.fy, cam.cx, cam.cy, znear=img.clip_near, zfar=img.clip_far),
                      pose=np.eye(4))
        self._drawn = _Drawn(ps, node, materials, np.array(colours).reshape(-1, 4), lights,
                             np.array(lcol, dtype=np.float64).reshape(-1, 3), np.array(lint, dtype=np.float64))
        self._scene = scene

    # ------------------------------------------------------------------ frames
    def render(self, pose: Any, rng: np.random.Generator | None = None, camera: Camera | None = None) -> np.ndarray:
        """The image of the current room from one camera pose.

        Args:
            pose: ``(4, 4)`` camera-to-world transform, OpenCV axes, world frame (z up), metres.
            rng: the sample's augmentation generator (:func:`config.augment_rng`); None renders without
                augmentation.
            camera: the intrinsics and image size to draw with (its pose is ignored); None: the robot camera of
                :meth:`SimConfig.image_camera`.

        Returns:
            ``(h, w, 3)`` uint8 RGB image: ``(S * H / W, S)``, or ``camera``'s ``(height, width)``.

        Raises:
            RuntimeError: no room was set.
        """
        if self._drawn is None:
            raise RuntimeError("SceneRenderer.render() needs a room: call set_scene() first")
        d = self._drawn
        aug = self.config.image.augment
        post = self._prepare(d, rng if aug.enabled else None)
        cam = self.config.image_camera() if camera is None else camera
        intrinsics = d.camera.camera
        intrinsics.fx, intrinsics.fy, intrinsics.cx, intrinsics.cy = cam.fx, cam.fy, cam.cx, cam.cy
        d.scene.set_pose(d.camera, check_pose(pose) @ OPENCV_TO_OPENGL)
        renderer = renderers().get(cam.width, cam.height)
        colour, _ = renderer.render(d.scene, flags=self._pyrender.RenderFlags.SKIP_CULL_FACES)
        return _camera_response(colour, post, rng if aug.enabled else None)

    def _prepare(self, d: _Drawn, rng: np.random.Generator | None) -> dict[str, Any]:
        """Set lights, ambient and object colours for one frame; returns the draws of the image-space steps."""
        a = self.config.image.augment
        n_l, n_m = len(d.lights), len(d.materials)
        if rng is None:
            for light, c, i in zip(d.lights, d.light_colours, d.light_intensities, strict=True):
                light.color, light.intensity = c, float(i)
            d.scene.ambient_light = np.full(3, float(np.mean(a.ambient)))
            for mat, c in zip(d.materials, d.base_colours, strict=True):
                mat.baseColorFactor = c
            d.scene.bg_color = np.array([*self.config.image.background, 1.0])
            return {}
        scale = rng.uniform(*a.light_intensity, size=n_l)
        tint = rng.uniform(-a.light_tint, a.light_tint, size=(n_l, 3))
        ambient = rng.uniform(*a.ambient)
        jitter = rng.uniform(-a.object_colour, a.object_colour, size=(n_m, 3))
        post = {
            "ev": rng.uniform(*a.exposure),
            "gains": rng.uniform(1.0 - a.white_balance, 1.0 + a.white_balance, size=3),
            "saturation": rng.uniform(*a.saturation),
            "gamma": rng.uniform(*a.gamma),
            "noise": rng.uniform(*a.noise),
        }
        for n, light in enumerate(d.lights):
            light.color = np.clip(d.light_colours[n] + tint[n], 0.0, 1.0)
            light.intensity = float(d.light_intensities[n] * scale[n])
        d.scene.ambient_light = np.full(3, ambient)
        # Saturation acts on the colours of the scene rather than on the image: the image steps then stay per
        # channel (one lookup table), and for diffuse surfaces under near-white light the result is the same.
        sat = post["saturation"]
        for n, mat in enumerate(d.materials):
            c = d.base_colours[n].copy()
            c[:3] = _saturate(np.clip(c[:3] + jitter[n], 0.0, 1.0), sat)
            mat.baseColorFactor = c
        d.scene.bg_color = np.array([*_saturate(np.asarray(self.config.image.background, dtype=np.float64), sat),
                                     1.0])
        return post

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Free the room (idempotent). The OpenGL context is the process's one offscreen renderer
        (:func:`fruxel.render.scene.renderers`), shared with fruxel.render's images and closed at exit: pyrender
        ends the process-wide EGL display when any renderer is deleted, which would break the others."""
        self._drawn = None
        self._scene = None

    def __enter__(self) -> SceneRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _camera_response(colour: np.ndarray, post: dict[str, Any], rng: np.random.Generator | None) -> np.ndarray:
    """Exposure, white balance, gamma and noise on an ``(h, w, 3)`` uint8 image; returns ``(h, w, 3)`` uint8.

    The first three act on each channel alone, so they are one 256-entry table per channel, computed in float64
    from the draws and applied by indexing, rather than float arithmetic on every pixel (the ``render`` stage of
    the simulator's profile in BENCHMARKS.md includes them).
    """
    rgb = np.ascontiguousarray(colour[..., :3], dtype=np.uint8)
    if rng is None or not post:
        return rgb
    x = np.arange(256, dtype=np.float64) / 255.0
    scale = 2.0 ** post["ev"] * post["gains"]
    lut = np.rint(np.clip(x[None, :] * scale[:, None], 0.0, 1.0) ** post["gamma"] * 255.0).astype(np.uint8)
    out = np.empty_like(rgb)
    for c in range(3):
        np.take(lut[c], rgb[..., c], out=out[..., c])
    if post["noise"] > 0:
        noise = rng.standard_normal(out.shape, dtype=np.float32) * np.float32(post["noise"] * 255.0)
        noisy = out.astype(np.float32) + noise
        np.clip(np.rint(noisy, out=noisy), 0.0, 255.0, out=noisy)
        out = noisy.astype(np.uint8)
    return out


def _saturate(rgb: np.ndarray, factor: float) -> np.ndarray:
    """Blend ``(..., 3)`` float RGB in [0, 1] with its grey value: ``factor`` 1 keeps it, 0 makes it grey."""
    grey = rgb @ _LUMA.astype(np.float64)
    return np.clip(grey[..., None] + factor * (rgb - grey[..., None]), 0.0, 1.0)


# ---------------------------------------------------------------------------------------------------- preview
def second_camera(view_depth: Any, config: SimConfig, size: int) -> Camera:
    """A viewing camera beside the robot camera, for looking at a ground-truth volume in 3D.

    In the grid frame (OpenCV axes, the robot camera at the origin looking down +z): it looks at the point on
    the optical axis at the median depth ``d`` of the own-view depth image (the grid's middle depth when the
    view is empty), from ``(0.5 d, -0.35 d, 0)``: to the right of and above the robot camera, so that the
    volume's depth shows as parallax.

    Args:
        view_depth: ``(H, W)`` float own-view depth image, metres, 0 = empty.
        config: supplies the grid.
        size: width of the viewing image in pixels (the height follows the grid's aspect).
    """
    dep = np.asarray(view_depth, dtype=np.float64)
    hit = dep[dep > 0]
    grid = config.grid
    d = float(np.median(hit)) if hit.size else 0.5 * (grid.z_near + grid.z_far)
    height = max(1, round(size * grid.height / grid.width))
    # From the target (0, 0, d) to the eye (0.5 d, -0.35 d, 0).
    offset = np.array([0.5, -0.35, -1.0])
    return look_at_grid(grid, offset, distance=d * float(np.linalg.norm(offset)), target=(0.0, 0.0, d), width=size,
                        height=height, hfov=grid.hfov)


def preview_panels(sample: Any, config: SimConfig, *, second_view: bool = True, backend: str | None = None
                   ) -> dict[str, np.ndarray]:
    """The panels of a sample's preview (``fruxel-sim preview``): its camera image, the ground truth's own-view
    first-hit labels in the class colours (the grid's camera, whose view the image is framed onto), and, with
    ``second_view``, a ray-cast render of the ground-truth volume from :func:`second_camera`.

    Args:
        sample: a :class:`.sample.Sample`: ``image`` ``(h, w, 3)`` uint8 RGB, ``labels`` ``(D, H, W)`` uint8 in the
            grid frame.
        config: its simulator config (grid, classes, image size).
        second_view: add the render from the second camera.
        backend: the ``first_hit`` backend (None: the best available).

    Returns:
        ``{title: (h, w, 3) uint8 RGB}`` in column order, a row of :func:`contact_sheet`.
    """
    from fruxel.kernels import first_hit
    from fruxel.render.raycast import RaycastStyle, raycast_image

    grid, classes = config.grid, config.classes
    own = first_hit(sample.labels, grid, grid.camera(), backend=backend)
    panels = {"camera image": sample.image, "ground truth, own view": classes.colour_of(np.asarray(own.label))}
    if second_view:
        cam = second_camera(own.depth, config, config.image_width)
        panels["ground truth, second pose"], _ = raycast_image(sample.labels, grid, cam, classes.palette(),
                                                               backend=backend, style=RaycastStyle(fog=True))
    return panels


def preview_sheet(maker: Any, config: SimConfig, split: str, indices: Sequence[int], seed: int, *,
                  backend: str | None = None, what: str = "") -> tuple[np.ndarray, list[Any]]:
    """The contact sheet of ``fruxel-sim preview``: one row a sample, its :func:`preview_panels` and a title with the
    split, index, room, frame, seed, grid and camera, and the class legend.

    Args:
        maker: the :class:`.sample.SampleMaker` of ``config`` and ``seed`` that makes the samples.
        config: its simulator config.
        split: the split the samples are drawn from.
        indices: the samples' indices in ``split``, one row each.
        seed: the base seed (for the titles).
        backend: the ``first_hit`` backend of the panels (None: the best available).
        what: words put before each title (e.g. the test set's name); "" for none.

    Returns:
        The ``(h, w, 3)`` uint8 RGB sheet and the samples made, in row order.
    """
    g = config.grid
    rows, titles, made = [], [], []
    for i in indices:
        s = maker.make(split, i)
        made.append(s)
        rows.append(preview_panels(s, config, backend=backend))
        titles.append(f"{what}{split} sample {i} (room {s.scene}, frame {s.frame}), seed {seed}, "
                      f"grid {g.width}x{g.height}x{g.depth}; {camera_text(s)}")
    return contact_sheet(rows, config.classes.names, config.classes.palette(), titles), made


def camera_text(sample: Any) -> str:
    """A sample's camera in words: its height, pitch, roll and field of view."""
    c = sample.camera
    return f"camera {c.height:.2f} m, pitch {c.pitch:.1f}, roll {c.roll:.1f}, {c.hfov:.1f} deg across"


def contact_sheet(rows: Sequence[dict[str, np.ndarray]], names: Sequence[str], palette: Any,
                  titles: Sequence[str]) -> np.ndarray:
    """Compose preview panels into one image: a title row, one row per sample, a class legend.

    Args:
        rows: per sample, panels in column order as ``{title: (h, w, 3) uint8}``; every panel is scaled
            (nearest neighbour) to the first panel's height.
        names: class names (legend), label order.
        palette: ``(C, 3)`` uint8 class colours.
        titles: one caption per row (e.g. the split and sample index), drawn at the row's left.

    Returns:
        ``(h, w, 3)`` uint8 RGB sheet on a white background.
    """
    from PIL import Image, ImageDraw

    pad, caption = 8, 18
    panel_h = max(1, rows[0][next(iter(rows[0]))].shape[0])
    scaled = []
    for row in rows:
        out = []
        for title, img in row.items():
            pil = Image.fromarray(np.ascontiguousarray(img, dtype=np.uint8))
            w = max(1, round(pil.width * panel_h / pil.height))
            out.append((title, np.asarray(pil.resize((w, panel_h), Image.NEAREST))))
        scaled.append(out)
    font = default_font(13)
    measure = ImageDraw.Draw(Image.new("RGB", (1, 1)))
    # Panel titles wrap to their panel's width (narrow panels got overlapping titles).
    wrapped = [[wrap_text(name, panel.shape[1], font, measure) for name, panel in row] for row in scaled]
    title_lines = [max(len(lines) for lines in row) for row in wrapped]
    legend_w = pad + sum(30 + int(measure.textlength(n, font=font)) for n in names[1:])
    titles_w = pad + max(int(measure.textlength(t, font=font)) for t in titles) + pad
    width = max(pad + max(sum(p.shape[1] + pad for _, p in row) for row in scaled), legend_w, titles_w)
    legend_h = caption + 2 * pad
    height = pad + sum((1 + n) * caption + panel_h + pad for n in title_lines) + legend_h
    sheet = Image.new("RGB", (width, height), (255, 255, 255))
    draw = ImageDraw.Draw(sheet)
    y = pad
    for row, lines, n_lines, title in zip(scaled, wrapped, title_lines, titles, strict=True):
        draw.text((pad, y), title, fill=(0, 0, 0), font=font)
        y += caption
        x = pad
        for (_, panel), name_lines in zip(row, lines, strict=True):
            for i, line in enumerate(name_lines):
                draw.text((x, y + i * caption), line, fill=(60, 60, 60), font=font)
            sheet.paste(Image.fromarray(panel), (x, y + n_lines * caption))
            x += panel.shape[1] + pad
        y += n_lines * caption + panel_h + pad
    pal = np.asarray(palette, dtype=np.uint8)
    x = pad
    for c, name in enumerate(names):
        if c == 0:
            continue
        draw.rectangle((x, y + 2, x + 14, y + 16), fill=tuple(int(v) for v in pal[c]), outline=(0, 0, 0))
        draw.text((x + 20, y + 2), name, fill=(0, 0, 0), font=font)
        x += 30 + int(draw.textlength(name, font=font))
    return np.asarray(sheet).copy()

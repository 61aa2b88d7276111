"""Frames of a fruxel model for display: what to draw (:class:`RenderOptions`), the default and orbit views, and
:class:`FrameRenderer`, which turns a model and a camera into an image (mesh, ray cast, or both side by side).

This is the library behind ``fruxel-render`` (:mod:`fruxel.cli.render`); a program that shows a network's live
output uses it the same way::

    frames = FrameRenderer(RenderInput(logits, grid, classes, "live"), RenderOptions(mode="raycast"))
    image = frames.image(default_camera(grid, 640, 480))       # (480, 640, 3) uint8, with a legend

Shell sources (:attr:`RenderOptions.shell`): ``none`` keeps every occupied cell (the paper's baseline); ``own``
what the grid's own camera sees (the first occupied cell of each column); ``poses`` what ``poses`` cameras
around the grid see (:func:`fruxel.kernels.orbit_cameras`, as in the paper); ``view`` what the viewing camera
itself sees. By default the mesh shows the ``own`` shell and the ray cast the whole model; a shell chosen
explicitly applies to both (the ray cast then casts into the shell). ``shell`` and ``first_hit`` run on the
volume as it is (labels, or logits as the live pipeline has them); only the cells the shell keeps are turned
into labels for the mesh.

Views (:func:`fruxel.camera.look_at_grid` frames them all): the default still view stands 30 degrees right of
and 35 degrees above the grid camera's side with a 50 degree field of view, at the distance where the whole
frustum (or the points given, such as the model's occupied cells, as ``fruxel-render`` does) just fits the
image, aimed so that their image is centred; :func:`orbit` turns one circle at
that elevation around the model's occupied cells, at the distance where they fit every frame.
"""

from __future__ import annotations

import math
import os
import sys
from collections.abc import Iterable
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from fruxel.camera import Camera, look_at_grid, orbit_direction
from fruxel.classes import ClassTable
from fruxel.grid import FruxelGrid

from . import RenderError

if TYPE_CHECKING:
    from fruxel.mesh import TriMesh

MODES = ("mesh", "raycast", "both")
"""What an image shows: the mesh (pyrender), the ray cast (first_hit), or both side by side."""
SHELLS = ("none", "own", "poses", "view")
"""Shell sources (module docstring)."""
MESHINGS = ("full", "culled", "greedy")
"""Meshings of :func:`fruxel.mesh.mesh_labels`."""

DEFAULT_SIZE = (640, 480)
"""Image size ``(width, height)`` in pixels of the default view."""
DEFAULT_AZIMUTH = 30.0
"""Degrees to the right of the grid camera's side (seen from above) of the default viewing camera."""
DEFAULT_ELEVATION = 35.0
"""Degrees above the grid's horizontal plane of the default viewing camera and of orbits."""
DEFAULT_HFOV = 50.0
"""Horizontal field of view of the default viewing camera, degrees."""
FIT_MARGIN = 0.04
"""Share of the image width / height left free on each side when fitting the frustum into the view."""


# ---------------------------------------------------------------------------------------------------- input
@dataclass(frozen=True)
class RenderInput:
    """A model to render, as the kernels take it."""

    volume: Any
    """Labels ``(D, H, W)`` uint8 numpy, or scores ``(1, C, D, H, W)`` float (numpy or torch), NCDHW."""
    grid: FruxelGrid
    """The volume's :class:`fruxel.FruxelGrid`."""
    classes: ClassTable
    """The :class:`fruxel.ClassTable` of the labels / channels."""
    name: str
    """Stem of the output files."""

    @property
    def is_scores(self) -> bool:
        """True for float scores, False for labels."""
        return len(self.volume.shape) == 5

    def any_occupied(self, threshold: float | None = None) -> bool:
        """Whether any cell is occupied: a non-zero label, or for scores the rule of
        :attr:`RenderOptions.threshold` (``threshold``; None: the argmax)."""
        if not self.is_scores:
            return bool(np.any(self.volume))
        from fruxel.model import labels_from_scores

        from .shading import to_numpy

        return bool(np.any(labels_from_scores(to_numpy(self.volume[0]), threshold=threshold, axis=0)))


# ---------------------------------------------------------------------------------------------------- cameras
def default_camera(grid: FruxelGrid, width: int, height: int, points: Any = None) -> Camera:
    """The default viewing camera (module docstring): oblique, fitted to the frustum, its image centred.

    Args:
        grid: the model's grid.
        width, height: image size, pixels.
        points: ``(N, 3)`` points to fit instead of the frustum, grid frame (e.g. the occupied cells' corners of
            the models a picture compares, :func:`occupied_points`); None for the whole frustum.
    """
    d = orbit_direction(math.radians(DEFAULT_AZIMUTH), math.radians(DEFAULT_ELEVATION))
    return look_at_grid(grid, d, points=points, width=width, height=height, hfov=DEFAULT_HFOV, margin=FIT_MARGIN,
                        centre=True)


def orbit(grid: FruxelGrid, base: Camera, n: int, points: Any = None) -> list[Camera]:
    """``n`` cameras one turn around the model, starting at the default azimuth and elevation, at one distance.

    Args:
        grid: the model's grid.
        base: the viewing camera; its image size and horizontal field of view are kept.
        n: number of frames.
        points: ``(N, 3)`` points the frames must show, grid frame (:meth:`FrameRenderer.model_points`: the
            corners of the occupied cells, so that the model fills the frames); None for the whole frustum. The
            orbit turns around the centre of their bounding box.
    """
    hfov = math.degrees(2.0 * math.atan(base.width / (2.0 * base.fx)))
    pts = grid.frustum_corners() if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 3)
    centre = 0.5 * (pts.min(axis=0) + pts.max(axis=0))
    dirs = [orbit_direction(math.radians(DEFAULT_AZIMUTH + 360.0 * f / n), math.radians(DEFAULT_ELEVATION))
            for f in range(n)]
    fits = [look_at_grid(grid, d, target=centre, points=pts, width=base.width, height=base.height, hfov=hfov,
                         margin=FIT_MARGIN) for d in dirs]
    # One distance for the whole turn (the farthest fit), so the model does not breathe in and out.
    r = max(float(np.linalg.norm(c.position - centre)) for c in fits)
    return [look_at_grid(grid, d, distance=r, target=centre, width=base.width, height=base.height, hfov=hfov)
            for d in dirs]


# ---------------------------------------------------------------------------------------------------- rendering
@dataclass(frozen=True)
class RenderOptions:
    """What to draw and how (the CLI's choices)."""

    mode: str = "mesh"
    """``"mesh"`` (a trapezoid mesh in pyrender), ``"raycast"`` (first_hit per pixel) or ``"both"``, side by
    side."""
    shell: str | None = None
    """Shell source: ``"none"``, ``"own"``, ``"poses"`` or ``"view"`` for mesh and ray cast alike; None: ``"own"``
    for the mesh and ``"none"`` (the whole model) for the ray cast."""
    poses: int = 6
    """Number of cameras around the grid for the ``"poses"`` shell."""
    meshing: str = "greedy"
    """``"full"`` (a hexahedron per cell), ``"culled"`` (boundary faces) or ``"greedy"`` (boundary faces merged
    into rectangles), see :mod:`fruxel.mesh`."""
    shading: str = "lit"
    """``"lit"`` or ``"flat"``, for mesh and ray-cast images alike."""
    fog: bool = False
    """Depth fog in ray-cast images."""
    legend: bool = True
    """Draw the class legend."""
    frustum: bool = False
    """Draw the frustum's edges in mesh images."""
    backend: str | None = None
    """Kernel backend, ``"warp"`` or ``"opencl"``; unset (None): the best available."""
    device: str | None = None
    """Where Warp runs, ``"cpu"``, ``"cuda"`` or ``"cuda:N"``; unset (None): where the data are."""
    threshold: float | None = None
    """For logits: a cell is occupied when ``1 - p(empty) >= threshold``; unset (None): when its argmax is not
    the empty class."""

    @property
    def mesh_shell(self) -> str:
        """The shell source of mesh images."""
        return "own" if self.shell is None else self.shell

    @property
    def raycast_shell(self) -> str:
        """The shell source of ray-cast images."""
        return "none" if self.shell is None else self.shell


def shell_volume(inp: RenderInput, opts: RenderOptions, shell: str, camera: Camera) -> Any:
    """The volume after a shell: ``inp.volume`` itself for ``"none"``, else ``fruxel.kernels.shell`` of it (same
    shape, kind of array and device).

    Args:
        inp: the model.
        opts: the number of poses, backend, device and threshold.
        shell: the shell source (:data:`SHELLS`).
        camera: the viewing camera (for ``shell="view"``).
    """
    from fruxel import kernels

    if shell == "none":
        return inp.volume
    if shell == "own":
        cams = inp.grid.camera()
    elif shell == "poses":
        cams = kernels.orbit_cameras(inp.grid, opts.poses)
    else:
        cams = camera
    return kernels.shell(inp.volume, inp.grid, cams, backend=opts.backend, device=opts.device,
                         threshold=opts.threshold)


def volume_labels(volume: Any, inp: RenderInput, threshold: float | None) -> np.ndarray:
    """Labels ``(D, H, W)`` uint8 numpy of a volume of ``inp``'s kind (labels, or scores by the occupancy rule)."""
    from fruxel import labels_from_scores

    from .shading import to_numpy

    if inp.is_scores:
        return labels_from_scores(to_numpy(volume)[0], threshold=threshold, axis=0)
    return np.ascontiguousarray(to_numpy(volume), dtype=np.uint8)


def shell_labels(inp: RenderInput, opts: RenderOptions, camera: Camera) -> np.ndarray:
    """The labels to mesh: ``(D, H, W)`` uint8 numpy, the volume after the mesh's shell
    (:attr:`RenderOptions.mesh_shell`).

    Args:
        inp: the model.
        opts: shell source, backend and threshold.
        camera: the viewing camera (for ``shell="view"``).
    """
    return volume_labels(shell_volume(inp, opts, opts.mesh_shell, camera), inp, opts.threshold)


def build_mesh(inp: RenderInput, opts: RenderOptions, camera: Camera) -> TriMesh:
    """The :class:`fruxel.mesh.TriMesh` (grid frame) of the shell of ``inp`` seen from ``camera``."""
    from fruxel.mesh import mesh_labels

    return mesh_labels(shell_labels(inp, opts, camera), inp.grid, inp.classes.palette(), mode=opts.meshing)


def occupied_points(labels: Any, grid: FruxelGrid) -> np.ndarray | None:
    """The lattice points that are corners of occupied cells: ``(N, 3)`` float64, grid frame, what a view must
    show to show the whole model (the cells are convex, so their corners bound them); None when no cell is
    occupied.

    Args:
        labels: ``(D, H, W)`` integer labels, 0 = empty.
        grid: their grid.
    """
    occupied = np.asarray(labels) != 0
    if not occupied.any():
        return None
    d, h, w = occupied.shape
    corner = np.zeros((d + 1, h + 1, w + 1), dtype=bool)
    for dk in (0, 1):
        for dj in (0, 1):
            for di in (0, 1):
                corner[dk:dk + d, dj:dj + h, di:di + w] |= occupied
    return grid.corner_points(*np.nonzero(corner))


class FrameRenderer:
    """Draws the images of one model for a sequence of cameras, rebuilding the mesh (and the ray cast's shell)
    only when the shell changes (every frame for ``shell="view"``)."""

    def __init__(self, inp: RenderInput, opts: RenderOptions) -> None:
        self.inp = inp
        self.opts = opts
        self.mesh: TriMesh | None = None
        self._view: Any = None
        self._raycast_volume: Any = None

    def mesh_for(self, camera: Camera) -> TriMesh:
        """The mesh for ``camera``: built once, or per camera for ``shell="view"``."""
        if self.mesh is None or self.opts.mesh_shell == "view":
            self.mesh = build_mesh(self.inp, self.opts, camera)
        return self.mesh

    def model_points(self) -> np.ndarray | None:
        """The corners of the model's occupied cells (:func:`occupied_points`), grid frame: what a view of the
        model must show; None for an empty model."""
        return occupied_points(volume_labels(self.inp.volume, self.inp, self.opts.threshold), self.inp.grid)

    def mesh_image(self, camera: Camera) -> tuple[np.ndarray, list[int]]:
        """``(h, w, 3)`` uint8 pyrender image of the mesh and the labels it shows."""
        from .legend import present_labels
        from .scene import MeshStyle, MeshView

        mesh = self.mesh_for(camera)
        if self._view is None:
            self._view = MeshView(self.inp.grid, MeshStyle(shading=self.opts.shading, frustum=self.opts.frustum))
        # A new mesh is shaded once, for this camera: the old one is not re-shaded on the way.
        new = self._view.mesh is not mesh
        self._view.set_camera(camera, reshade=not new)
        if new:
            self._view.set_mesh(mesh)
        return self._view.render(), present_labels(mesh.labels)

    def raycast_volume(self, camera: Camera) -> Any:
        """The volume the ray cast sees: the model after :attr:`RenderOptions.raycast_shell`."""
        shell = self.opts.raycast_shell
        if shell == "view" or self._raycast_volume is None:
            self._raycast_volume = shell_volume(self.inp, self.opts, shell, camera)
        return self._raycast_volume

    def raycast_image(self, camera: Camera) -> tuple[np.ndarray, list[int]]:
        """``(h, w, 3)`` uint8 ray-cast image and the labels it shows."""
        from .legend import present_labels
        from .raycast import RaycastStyle, raycast_image

        style = RaycastStyle(shading=self.opts.shading, fog=self.opts.fog)
        img, labels = raycast_image(self.raycast_volume(camera), self.inp.grid, camera, self.inp.classes.palette(),
                                    backend=self.opts.backend, device=self.opts.device,
                                    threshold=self.opts.threshold, style=style)
        return img, present_labels(labels)

    def _backend_name(self) -> str:
        from fruxel import kernels

        return kernels.registry.describe(self.opts.backend, self.opts.device, self.inp.volume)

    def mesh_caption(self) -> str:
        """What the last mesh image shows, in words: shell, meshing and triangles."""
        return (f"mesh: shell {self.opts.mesh_shell}, {self.opts.meshing}, "
                f"{0 if self.mesh is None else self.mesh.n_faces} triangles")

    def raycast_caption(self) -> str:
        """What a ray-cast image shows, in words: the kernel's backend and the shell."""
        shell = self.opts.raycast_shell
        return f"ray cast: first_hit on {self._backend_name()}" + ("" if shell == "none" else f", shell {shell}")

    def picture(self, camera: Camera) -> tuple[np.ndarray, list[int]]:
        """The image of the chosen mode without legend (with captions for ``"both"``): ``(h, w', 3)`` uint8, and
        the labels it shows."""
        from .legend import draw_caption

        if self.opts.mode == "mesh":
            return self.mesh_image(camera)
        if self.opts.mode == "raycast":
            return self.raycast_image(camera)
        mimg, mp = self.mesh_image(camera)
        rimg, rp = self.raycast_image(camera)
        mimg = draw_caption(mimg, self.mesh_caption())
        rimg = draw_caption(rimg, self.raycast_caption())
        gap = np.full((mimg.shape[0], 2, 3), 160, np.uint8)
        return np.concatenate([mimg, gap, rimg], axis=1), sorted(set(mp) | set(rp))

    def image(self, camera: Camera) -> np.ndarray:
        """The image of the chosen mode, with legend (and captions for ``"both"``): ``(h, w', 3)`` uint8."""
        return self.images([camera])[0]

    def images(self, cameras: Iterable[Camera]) -> list[np.ndarray]:
        """The images of a sequence of views (an orbit), each as :meth:`image` gives it, with the legend in one
        corner for all of them (the one that hides the least over the whole sequence) listing every class any
        of them shows."""
        from .legend import draw_legend, legend_corner

        pictures = [self.picture(c) for c in cameras]
        if not self.opts.legend:
            return [p for p, _ in pictures]
        present = sorted({c for _, labels in pictures for c in labels})
        corner = legend_corner([p for p, _ in pictures], self.inp.classes, present)
        return [draw_legend(p, self.inp.classes, present, corner=corner) for p, _ in pictures]


def has_display() -> bool:
    """True when a window can be opened: macOS, Windows, or ``DISPLAY`` / ``WAYLAND_DISPLAY`` set."""
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def open_viewer(inp: RenderInput, opts: RenderOptions, camera: Camera) -> None:
    """Open pyrender's interactive Viewer on the mesh (pyrender's lights; its own camera controls).

    Raises:
        RenderError: no display, or the Viewer could not open a window.
    """
    if not has_display():
        raise RenderError("the interactive viewer needs a display (DISPLAY is not set); render offscreen instead")
    if os.environ.get("PYOPENGL_PLATFORM") == "egl":
        # EGL is headless; the Viewer needs the window system's GL. Only this process is affected.
        del os.environ["PYOPENGL_PLATFORM"]
    from .compat import import_pyrender
    from .scene import MeshStyle, clip_range, pyrender_mesh

    pyrender = import_pyrender(headless=False)
    mesh = build_mesh(inp, opts, camera)
    scene = pyrender.Scene(bg_color=[1.0, 1.0, 1.0, 1.0], ambient_light=[0.3, 0.3, 0.3])
    pm = pyrender_mesh(mesh, MeshStyle(shading="pbr"))
    if pm is not None:
        scene.add(pm)
    znear, zfar = clip_range(camera, inp.grid)
    yfov = 2.0 * math.atan(camera.height / (2.0 * camera.fy))
    scene.add(pyrender.PerspectiveCamera(yfov=yfov, znear=znear, zfar=zfar * 4.0,
                                         aspectRatio=camera.width / camera.height), pose=camera.opengl_pose())
    try:
        pyrender.Viewer(scene, viewport_size=(camera.width, camera.height), use_raymond_lighting=True,
                        window_title=f"fruxel: {inp.name}")
    except Exception as e:  # noqa: BLE001 - pyglet / OpenGL raise many types when no window can be opened
        raise RenderError(f"cannot open the viewer window: {type(e).__name__}: {e}") from None

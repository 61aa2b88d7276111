"""pyrender scenes of fruxel meshes: camera conversion, mesh upload and offscreen renderers.

Frames and conventions:

* Meshes (:class:`fruxel.mesh.TriMesh`) are in the grid frame (OpenCV axes, metres) and go to pyrender as they
  are; only the camera changes axes. A viewing camera (:class:`fruxel.Camera`, camera-to-grid pose, OpenCV axes)
  becomes a ``pyrender.IntrinsicsCamera(fx, fy, cx, cy, znear, zfar)`` at :meth:`Camera.opengl_pose`. pyrender's
  projection puts grid point ``p`` at window x ``fx * x_c / z_c + cx`` and, after its read-back flips the rows,
  at image row ``fy * y_c / z_c + cy`` (``(x_c, y_c, z_c)`` = ``p`` in the OpenCV camera frame), so a vertex
  lands exactly where :meth:`Camera.project` says, pixel ``(x, y)`` covering ``[x, x + 1) x [y, y + 1)``.
* Shading: ``"flat"`` draws every face in its class colour; ``"lit"`` bakes the ray-cast shading
  (:func:`fruxel.render.shading.lambert`: ambient plus Lambert from a head light, the ray cast's formula)
  into per-face colours and draws them unlit, so that mesh and ray-cast
  images of the same view look alike; ``"pbr"`` gives pyrender normals and linear colours for its own lights
  (the interactive Viewer, which has no unlit mode).

``"lit"`` and ``"pbr"`` need one colour or normal per face, so they give pyrender three vertices per triangle;
``"flat"`` uploads the indexed mesh.

pyrender is imported inside the functions (:func:`fruxel.render.compat.import_pyrender`), so importing this
module stays cheap.
"""

from __future__ import annotations

import atexit
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from fruxel.camera import Camera
from fruxel.grid import FruxelGrid
from fruxel.mesh import TriMesh

from .compat import import_pyrender
from .shading import DEFAULT_AMBIENT, DEFAULT_BACKGROUND, DEFAULT_LIGHT, lambert

if TYPE_CHECKING:
    import pyrender

SHADINGS = ("lit", "flat")
"""Shadings of offscreen mesh images (``"pbr"`` is for the interactive Viewer only)."""

MAX_TILE = 4096
"""Largest image side drawn at once; larger images are drawn in tiles (:meth:`MeshView.render`). pyrender's
multisampled framebuffers for a 16000 x 16000 image would take 8 GB, and OpenGL refuses sides beyond its
limits."""

# Share of the view depth range kept in front of the nearest and behind the farthest frustum corner: keeps
# the whole grid between the clip planes without wasting depth-buffer precision.
_CLIP_MARGIN = 0.05
# Nearest clip plane as a share of the farthest, for a camera inside or beside the frustum: 24-bit depth
# still separates faces a millimetre apart at 10 m.
_MIN_NEAR_RATIO = 1e-4


@dataclass(frozen=True)
class MeshStyle:
    """How a fruxel mesh is drawn."""

    shading: str = "lit"
    """``"lit"`` (baked ambient + Lambert head light, the ray-cast formula), ``"flat"`` (class colours only) or
    ``"pbr"`` (pyrender's own lights; for the interactive Viewer)."""
    light: tuple[float, float, float] = DEFAULT_LIGHT
    """Direction towards the light in the viewing camera's frame (OpenCV axes), for ``"lit"``."""
    ambient: float = DEFAULT_AMBIENT
    """Share of the colour lit regardless of orientation, in [0, 1], for ``"lit"``."""
    background: tuple[int, int, int] = DEFAULT_BACKGROUND
    """RGB of pixels that show no face."""
    frustum: bool = False
    """Also draw the grid frustum's 12 edges as grey lines."""

    def __post_init__(self) -> None:
        if self.shading not in (*SHADINGS, "pbr"):
            raise ValueError(f"shading must be one of {(*SHADINGS, 'pbr')}, got {self.shading!r}")
        if not 0.0 <= self.ambient <= 1.0:
            raise ValueError(f"ambient must be in [0, 1], got {self.ambient}")


# ---------------------------------------------------------------------------------------------------- camera
def clip_range(camera: Camera, grid: FruxelGrid) -> tuple[float, float]:
    """Near and far clip distances (metres, along the viewing axis) that keep the whole grid in view.

    The frustum is convex, so its corners bound the depth of every face in it.
    """
    depth = camera.project(grid.frustum_corners())[:, 2]
    far = float(depth.max())
    if far <= 0.0:
        # The grid is behind the camera: nothing can be seen, any valid range will do.
        return 0.01, 1.0
    far *= 1.0 + _CLIP_MARGIN
    near = float(depth.min()) * (1.0 - _CLIP_MARGIN)
    return max(near, far * _MIN_NEAR_RATIO), far


def pyrender_camera(camera: Camera, znear: float, zfar: float) -> pyrender.IntrinsicsCamera:
    """The pyrender camera with ``camera``'s intrinsics; place it at ``camera.opengl_pose()``.

    Args:
        camera: the viewing camera (OpenCV intrinsics in pixels).
        znear, zfar: clip distances in metres, ``0 < znear < zfar`` (see :func:`clip_range`).
    """
    pyrender = import_pyrender()
    return pyrender.IntrinsicsCamera(fx=camera.fx, fy=camera.fy, cx=camera.cx, cy=camera.cy, znear=znear, zfar=zfar)


# ---------------------------------------------------------------------------------------------------- meshes
def _unit_normals(tri: np.ndarray) -> np.ndarray:
    """Unit normals of triangles ``(F, 3, 3)`` float32 (counter-clockwise seen from the normal's side): ``(F, 3)``."""
    a = tri[:, 1] - tri[:, 0]
    b = tri[:, 2] - tri[:, 0]
    # Written out rather than np.cross, which moves axes and copies: this is on the per-frame path.
    n = np.empty_like(a)
    n[:, 0] = a[:, 1] * b[:, 2] - a[:, 2] * b[:, 1]
    n[:, 1] = a[:, 2] * b[:, 0] - a[:, 0] * b[:, 2]
    n[:, 2] = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    n /= np.maximum(np.sqrt(np.einsum("ij,ij->i", n, n)), np.float32(1e-30))[:, None]
    return n


def face_normals(mesh: TriMesh) -> np.ndarray:
    """Unit outward normal of every triangle: ``(F, 3)`` float32, grid frame (faces wind counter-clockwise seen
    from outside, see :mod:`fruxel.mesh`)."""
    return _unit_normals(np.take(mesh.vertices, mesh.faces, axis=0))


def vertex_arrays(
    mesh: TriMesh, style: MeshStyle, camera_rotation: Any = None
) -> tuple[np.ndarray, np.ndarray, np.ndarray | None, np.ndarray | None]:
    """The arrays pyrender draws for a mesh.

    Args:
        mesh: a fruxel mesh (grid frame).
        style: the shading; ``"lit"`` needs ``camera_rotation``.
        camera_rotation: ``(3, 3)`` camera-to-grid rotation of the viewing camera (the head light follows it).

    Returns:
        positions: ``(N, 3)`` float32, grid frame.
        colours: ``(N, 4)`` float32 RGBA in [0, 1].
        indices: ``(F, 3)`` int32 into ``positions`` for ``"flat"``; None when every triangle has its own three
            vertices (``N = 3 F``).
        normals: ``(N, 3)`` float32 for ``"pbr"``, else None.
    """
    if style.shading == "flat":
        return mesh.vertices, mesh.colors.astype(np.float32) * np.float32(1.0 / 255.0), mesh.faces, None
    tri = np.take(mesh.vertices, mesh.faces, axis=0)
    positions = tri.reshape(-1, 3)
    normals = _unit_normals(tri)
    # Every vertex of a face has the face's class colour, so the first vertex's colour is the face's.
    face_rgba = np.take(mesh.colors, mesh.faces[:, 0], axis=0).astype(np.float32)
    if style.shading == "lit":
        rot = np.eye(3) if camera_rotation is None else np.asarray(camera_rotation, dtype=np.float64)
        shade = lambert(normals, rot @ np.asarray(style.light, dtype=np.float64), style.ambient)
        face_rgba[:, :3] *= (shade * np.float32(1.0 / 255.0))[:, None]
        face_rgba[:, 3] = 1.0
        return positions, np.repeat(face_rgba, 3, axis=0), None, None
    # pyrender's lit shader raises the product of light and vertex colour to 1 / 2.2; linear colours make the
    # displayed colour the class colour under full light.
    face_rgba *= np.float32(1.0 / 255.0)
    face_rgba[:, :3] **= np.float32(2.2)
    return positions, np.repeat(face_rgba, 3, axis=0), None, np.repeat(normals, 3, axis=0)


def pyrender_mesh(mesh: TriMesh, style: MeshStyle = MeshStyle(), camera_rotation: Any = None) -> pyrender.Mesh | None:
    """A ``pyrender.Mesh`` of a fruxel mesh (see :func:`vertex_arrays`), or None when the mesh has no faces."""
    if mesh.n_faces == 0:
        return None
    pyrender = import_pyrender()
    positions, colours, indices, normals = vertex_arrays(mesh, style, camera_rotation)
    prim = pyrender.Primitive(
        positions=positions, normals=normals, color_0=colours, indices=indices, mode=pyrender.constants.GLTF.TRIANGLES
    )
    return pyrender.Mesh([prim])


def frustum_lines(grid: FruxelGrid) -> pyrender.Mesh:
    """The grid frustum's 12 edges as a grey line mesh (grid frame)."""
    pyrender = import_pyrender()
    edges = np.array([[0, 1], [2, 3], [4, 5], [6, 7], [0, 2], [1, 3], [4, 6], [5, 7], [0, 4], [1, 5], [2, 6], [3, 7]])
    positions = grid.frustum_corners().astype(np.float32)[edges.reshape(-1)]
    prim = pyrender.Primitive(
        positions=positions, color_0=np.tile(np.float32([0.35, 0.35, 0.35, 1.0]), (len(positions), 1)),
        mode=pyrender.constants.GLTF.LINES,
    )
    return pyrender.Mesh([prim])


# ---------------------------------------------------------------------------------------------------- renderers
class RendererPool:
    """One offscreen renderer (EGL, headless), created on first use, kept, and resized to each image asked for.

    One renderer rather than one per size: pyrender 0.1.45's EGL platform terminates the process-wide EGL
    display when a renderer is deleted, which breaks every other renderer still open. Resizing only re-creates
    the framebuffers (on the next draw after a size change), so orbits, benchmarks and tests that draw many
    frames of one size pay for the context once. :func:`renderers` is the process-wide pool.
    """

    def __init__(self) -> None:
        self._renderer: Any = None
        self._max_side: int | None = None

    def get(self, width: int, height: int) -> pyrender.OffscreenRenderer:
        """The renderer, set to draw ``width x height`` images."""
        if self._renderer is None:
            pyrender = import_pyrender()
            self._renderer = pyrender.OffscreenRenderer(viewport_width=int(width), viewport_height=int(height))
        self._renderer.viewport_width = int(width)
        self._renderer.viewport_height = int(height)
        return self._renderer

    def max_side(self) -> int:
        """The largest image side one draw may have: :data:`MAX_TILE`, or less where the OpenGL implementation
        allows less (``GL_MAX_RENDERBUFFER_SIZE``, ``GL_MAX_VIEWPORT_DIMS``; 16384 on Mesa's llvmpipe)."""
        if self._max_side is None:
            r = self.get(16, 16)
            # pyrender has no public call for this; its offscreen platform makes the context current.
            r._platform.make_current()
            from OpenGL.GL import GL_MAX_RENDERBUFFER_SIZE, GL_MAX_VIEWPORT_DIMS, glGetIntegerv

            limits = [int(v) for v in np.ravel(glGetIntegerv(GL_MAX_VIEWPORT_DIMS))]
            limits.append(int(np.ravel(glGetIntegerv(GL_MAX_RENDERBUFFER_SIZE))[0]))
            self._max_side = max(1, min(MAX_TILE, *limits))
        return self._max_side

    def close(self) -> None:
        """Delete the renderer (its GL context and buffers)."""
        r, self._renderer = self._renderer, None
        if r is not None:
            try:
                r.delete()
            except Exception:  # noqa: BLE001 - at interpreter exit the GL library may already be torn down
                pass


_POOL: RendererPool | None = None


def renderers() -> RendererPool:
    """The process-wide :class:`RendererPool`, closed at exit."""
    global _POOL
    if _POOL is None:
        _POOL = RendererPool()
        atexit.register(_POOL.close)
    return _POOL


def gl_renderer_name() -> str:
    """``glGetString(GL_RENDERER)`` of the offscreen context, e.g. ``"llvmpipe (LLVM 15.0.6, 256 bits)"``."""
    r = renderers().get(16, 16)
    r._platform.make_current()
    from OpenGL.GL import GL_RENDERER, glGetString

    name = glGetString(GL_RENDERER)
    return name.decode() if isinstance(name, bytes) else str(name)


# ---------------------------------------------------------------------------------------------------- scene
class MeshView:
    """A pyrender scene that shows one fruxel mesh from one viewing camera, drawn offscreen.

    Typical use: ``view.set_camera(cam); view.set_mesh(mesh); image = view.render()``. Replacing the mesh or
    the camera reuses the scene and the renderer; the GPU copy of a replaced mesh is freed on the next draw.
    """

    def __init__(self, grid: FruxelGrid, style: MeshStyle = MeshStyle(), pool: RendererPool | None = None) -> None:
        """Args:
            grid: the grid of the meshes shown (it sets the clip range and the optional frustum lines).
            style: shading and background.
            pool: where renderers come from; :func:`renderers` by default.
        """
        pyrender = import_pyrender()
        self.grid = grid
        self.style = style
        self._pool = renderers() if pool is None else pool
        bg = np.append(np.asarray(style.background, dtype=np.float64) / 255.0, 1.0)
        self.scene = pyrender.Scene(bg_color=bg, ambient_light=np.full(3, 0.3))
        self._camera: Camera | None = None
        self._camera_node: Any = None
        self._mesh: TriMesh | None = None
        self._mesh_node: Any = None
        self._shaded_for: np.ndarray | None = None
        if style.frustum:
            self.scene.add(frustum_lines(grid))
        flags = pyrender.RenderFlags
        self.flags = flags.NONE if style.shading == "pbr" else flags.FLAT

    @property
    def camera(self) -> Camera | None:
        """The current viewing camera."""
        return self._camera

    @property
    def mesh(self) -> TriMesh | None:
        """The mesh shown, None before :meth:`set_mesh`."""
        return self._mesh

    def set_camera(self, camera: Camera, *, reshade: bool = True) -> None:
        """View from ``camera`` (the image gets its size); re-shades a ``"lit"`` mesh when the view turned, unless
        ``reshade`` is False (the caller replaces the mesh next, which shades it for this camera)."""
        znear, zfar = clip_range(camera, self.grid)
        if self._camera_node is None:
            self._camera_node = self.scene.add(pyrender_camera(camera, znear, zfar), pose=camera.opengl_pose())
        else:
            cam = self._camera_node.camera
            cam.fx, cam.fy, cam.cx, cam.cy = camera.fx, camera.fy, camera.cx, camera.cy
            cam.znear, cam.zfar = znear, zfar
            self.scene.set_pose(self._camera_node, camera.opengl_pose())
        self._camera = camera
        if reshade and self._mesh is not None and self._needs_reshade():
            self.set_mesh(self._mesh)

    def _needs_reshade(self) -> bool:
        return (
            self.style.shading == "lit"
            and self._camera is not None
            and (self._shaded_for is None or not np.array_equal(self._shaded_for, self._camera.rotation))
        )

    def set_mesh(self, mesh: TriMesh) -> None:
        """Show ``mesh`` (grid frame) instead of the current one. ``"lit"`` shading uses the current camera."""
        rotation = None if self._camera is None else self._camera.rotation
        pm = pyrender_mesh(mesh, self.style, rotation)
        if self._mesh_node is not None:
            self.scene.remove_node(self._mesh_node)
            self._mesh_node = None
        if pm is not None:
            self._mesh_node = self.scene.add(pm)
        self._mesh = mesh
        self._shaded_for = rotation

    def renderer(self) -> pyrender.OffscreenRenderer:
        """The offscreen renderer of the current camera's image size."""
        if self._camera is None:
            raise ValueError("MeshView has no camera: call set_camera first")
        return self._pool.get(self._camera.width, self._camera.height)

    def upload(self) -> None:
        """Copy new meshes to the GPU and free replaced ones now, rather than inside the next :meth:`render`.

        Only a way to time the upload on its own; :meth:`render` does the same when it is not called. It uses
        pyrender 0.1.45's internal ``Renderer._update_context``, and does nothing where that is missing.
        """
        r = self.renderer()
        inner = getattr(r, "_renderer", None)
        if hasattr(inner, "_update_context") and hasattr(r, "_platform"):
            r._platform.make_current()
            inner._update_context(self.scene, self.flags)

    def render(self) -> np.ndarray:
        """Draw the scene and read it back: ``(height, width, 3)`` uint8 RGB, row 0 at the top.

        An image with a side above :meth:`RendererPool.max_side` is drawn in tiles of at most that size, each
        with the principal point moved to its place (the same projection, cut into pieces), so any image the
        camera allows (up to 2^28 pixels) can be drawn and the GPU memory of one draw stays bounded.
        """
        if self._camera is None:
            raise ValueError("MeshView has no camera: call set_camera first")
        cam = self._camera
        tile = self._pool.max_side()
        if cam.width <= tile and cam.height <= tile:
            colour, _ = self.renderer().render(self.scene, flags=self.flags)
            return np.ascontiguousarray(colour[..., :3])
        tw, th = min(cam.width, tile), min(cam.height, tile)
        renderer = self._pool.get(tw, th)
        node = self._camera_node.camera
        out = np.empty((cam.height, cam.width, 3), dtype=np.uint8)
        try:
            for y0 in range(0, cam.height, th):
                for x0 in range(0, cam.width, tw):
                    node.cx, node.cy = cam.cx - x0, cam.cy - y0
                    colour, _ = renderer.render(self.scene, flags=self.flags)
                    h, w = min(th, cam.height - y0), min(tw, cam.width - x0)
                    out[y0:y0 + h, x0:x0 + w] = colour[:h, :w, :3]
        finally:
            node.cx, node.cy = cam.cx, cam.cy
        return out


def render_mesh(
    mesh: TriMesh, grid: FruxelGrid, camera: Camera, style: MeshStyle = MeshStyle(), pool: RendererPool | None = None
) -> np.ndarray:
    """One offscreen image of a fruxel mesh: ``(camera.height, camera.width, 3)`` uint8 RGB."""
    view = MeshView(grid, style, pool)
    view.set_camera(camera)
    view.set_mesh(mesh)
    return view.render()


def decode_labels(image: Any, palette: Any, background: tuple[int, int, int] = (255, 255, 255)) -> np.ndarray:
    """Labels of a flat-shaded image: each pixel's nearest class colour, 0 for the background.

    Args:
        image: ``(h, w, 3)`` uint8 RGB.
        palette: ``(C, 3)`` uint8 class colours (row 0, the empty class, is ignored).
        background: RGB of pixels that show nothing.

    Returns:
        ``(h, w)`` int32 labels in ``[0, C)``.
    """
    img = np.asarray(image, dtype=np.int32)[..., :3]
    pal = np.asarray(palette, dtype=np.int32).copy()
    pal[0] = background
    d = ((img[..., None, :] - pal[None, None]) ** 2).sum(axis=-1)
    return np.argmin(d, axis=-1).astype(np.int32)

"""``fruxel-render``: show a fruxel model as a trapezoid mesh (pyrender) or a ray-cast image, or run Table 1.

Usage::

    fruxel-render [MODEL] [--backend {warp,opencl}] [--device cpu|cuda[:N]] [--mode {mesh,raycast,both}]
                  [--shell {none,own,poses,view}] [--mesh {full,culled,greedy}] [--size WxH] [--camera JSON]
                  [--out DIR] [--orbit N [--video {gif,mp4}]] [--export FILE.glb|FILE.ply] [--view] [--benchmark]

MODEL (default: the bundled sample room, ``fruxel.data.SAMPLE_ROOM``) is one of

* a fruxel model file ``.npz`` (:func:`fruxel.load`);
* a logits tensor ``(C, D, H, W)`` or ``(1, C, D, H, W)`` (NCDHW, channel 0 = empty) saved as ``.npy``
  (read with ``allow_pickle=False``) or ``.pt`` (``torch.load(weights_only=True)``). A bare tensor needs its
  grid, from (first found) ``--grid W,H,D,z_near,z_far,hfov``, a ``.pt`` dict ``{"logits": tensor, "grid":
  {...}}``, or a JSON sidecar beside the file (``X.npy`` + ``X.json``) holding a grid dict
  (:meth:`fruxel.FruxelGrid.to_dict`) or ``{"grid": {...}, "classes": {...}}``. Classes come from the ``.pt``
  dict's or the sidecar's ``"classes"`` (:meth:`fruxel.ClassTable.to_dict`), else the default classes (cut
  or extended to C). ``shell`` and ``first_hit`` run on the logits as they are, as the live pipeline does;
  only the cells kept by the shell are turned into labels for the mesh.

Shell sources (``--shell``): ``none`` meshes every occupied cell (the paper's baseline); ``own`` keeps what the
grid's own camera sees (the first occupied cell of each column; the default); ``poses`` what ``--poses M``
cameras around the grid see (:func:`fruxel.kernels.orbit_cameras`, as in the paper); ``view`` what the viewing
camera itself sees. Meshing (``--mesh``): ``full``, ``culled`` or ``greedy`` (the default; see
:mod:`fruxel.mesh`).

The viewing camera is ``--camera`` (a :meth:`fruxel.Camera.to_json` text, or a file holding one; its own
image size wins over ``--size``), or by default an oblique view: from 30 degrees right of and 35 degrees above
the grid camera's side, looking at the centre of the frustum's bounding box, at the distance where the whole
frustum just fits the image (hfov 50 degrees). ``--orbit N`` renders N frames on a circle at that elevation
around the same centre, one turn, into a GIF (or an MP4 when ``imageio-ffmpeg`` is installed).

Outputs go to ``--out`` (default ``out/``): ``NAME_mesh.png``, ``NAME_raycast.png``, ``NAME_both.png`` (mesh
and ray cast side by side) or ``NAME_MODE_orbit.gif|mp4``, written atomically; NAME is the model file's stem.
Every path written is printed. Bad input gives one line ``fruxel-render: error: ...`` on stderr and exit
status 2. ``--view`` opens pyrender's interactive Viewer instead (it needs a display).
"""

from __future__ import annotations

import argparse
import json
import math
import os
import re
import sys
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

from fruxel.cli import OneLineParser, device_name, positive_int, unit_fraction

if TYPE_CHECKING:
    import numpy as np

    from fruxel import Camera, ClassTable, FruxelGrid
    from fruxel.mesh import TriMesh

PROG = "fruxel-render"
MODES = ("mesh", "raycast", "both")
SHELLS = ("none", "own", "poses", "view")
MESHINGS = ("full", "culled", "greedy")
BACKENDS = ("warp", "opencl")
VIDEO_FORMATS = ("gif", "mp4")

DEFAULT_SIZE = (640, 480)
"""Image size ``(width, height)`` in pixels when neither ``--size`` nor ``--camera`` gives one."""
DEFAULT_AZIMUTH = 30.0
"""Degrees to the right of the grid camera's side (seen from above) of the default viewing camera."""
DEFAULT_ELEVATION = 35.0
"""Degrees above the grid's horizontal plane of the default viewing camera and of orbits."""
DEFAULT_HFOV = 50.0
"""Horizontal field of view of the default viewing camera, degrees."""
FIT_MARGIN = 0.04
"""Share of the image width / height left free on each side when fitting the frustum into the view."""


class InputError(ValueError):
    """A problem with what the user asked for (a file, an option value) that is none of fruxel's own errors."""


# ---------------------------------------------------------------------------------------------------- parsing
def _size(text: str) -> tuple[int, int]:
    m = re.fullmatch(r"\s*(\d+)\s*[xX,]\s*(\d+)\s*", text)
    if not m or int(m.group(1)) <= 0 or int(m.group(2)) <= 0:
        raise argparse.ArgumentTypeError(f"expected WxH with positive integers, e.g. 640x480, got {text!r}")
    return int(m.group(1)), int(m.group(2))


def _grid_spec(text: str) -> tuple[float, ...]:
    parts = [p for p in re.split(r"[,\s]+", text.strip()) if p]
    try:
        values = tuple(float(p) for p in parts)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected numbers, got {text!r}") from None
    if len(values) not in (1, 6):
        raise argparse.ArgumentTypeError(f"expected N or W,H,D,z_near,z_far,hfov, got {text!r}")
    return values


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (no heavy imports: ``--help`` must be instant)."""
    p = OneLineParser(
        prog=PROG,
        description="Render a fruxel model: a trapezoid mesh of what the camera sees (pyrender), a ray-cast image "
        "(first_hit), or both; or measure Table 1 (--benchmark).",
        epilog="MODEL may be a .npz fruxel model or a logits tensor (C,D,H,W) in .npy/.pt; a bare tensor takes its "
        "grid from --grid, a .pt dict {'logits', 'grid'} or a JSON sidecar X.json beside X.npy. Default view: "
        "oblique, 30 deg right and 35 deg above the grid camera's side, fitted to the frustum.",
    )
    p.add_argument("model", nargs="?", metavar="MODEL", help="model .npz or logits .npy/.pt (default: the sample room)")
    p.add_argument("--backend", choices=BACKENDS, default=None, help="kernel backend (default: the best available)")
    p.add_argument("--device", type=device_name, default=None, help="where Warp runs: cpu, cuda or cuda:N")
    p.add_argument("--mode", choices=MODES, default="mesh", help="mesh (pyrender), raycast (first_hit) or both")
    p.add_argument("--shell", choices=SHELLS, default="own",
                   help="cells to keep: none (all), own (grid camera; default), poses (M cameras), view (viewer)")
    p.add_argument("--poses", type=positive_int, default=6, metavar="M", help="cameras for --shell poses")
    p.add_argument("--mesh", dest="meshing", choices=MESHINGS, default="greedy", help="meshing (default greedy)")
    p.add_argument("--shading", choices=("lit", "flat"), default="lit", help="lit (Lambert) or flat class colours")
    p.add_argument("--fog", action="store_true", help="depth fog in ray-cast images")
    p.add_argument("--no-legend", dest="legend", action="store_false", help="leave out the class legend")
    p.add_argument("--frustum", action="store_true", help="draw the grid frustum's edges in mesh images")
    p.add_argument("--size", type=_size, default=None, metavar="WxH", help="image size (default 640x480)")
    p.add_argument("--camera", default=None, metavar="JSON", help="viewing camera: Camera JSON text or a file")
    p.add_argument("--grid", type=_grid_spec, default=None, metavar="SPEC",
                   help="W,H,D,z_near,z_far,hfov of a bare logits tensor; with --benchmark, N for an N^3 model")
    p.add_argument("--threshold", type=unit_fraction, default=None,
                   help="logits: occupied when 1 - p(empty) >= T (default: argmax rule)")
    p.add_argument("--out", type=Path, default=Path("out"), metavar="DIR", help="output folder (default out/)")
    p.add_argument("--orbit", type=positive_int, default=None, metavar="N", help="render an N-frame orbit")
    p.add_argument("--video", choices=VIDEO_FORMATS, default="gif", help="orbit format (mp4 needs imageio-ffmpeg)")
    p.add_argument("--fps", type=positive_int, default=12, help="orbit frames per second (default 12)")
    p.add_argument("--export", type=Path, default=None, metavar="FILE", help="also write the mesh to .glb or .ply")
    p.add_argument("--view", action="store_true", help="open pyrender's interactive Viewer (needs a display)")
    b = p.add_argument_group("Table 1 (--benchmark)")
    b.add_argument("--benchmark", action="store_true", help="measure Table 1 (per-frame model updates)")
    b.add_argument("--frames", type=positive_int, default=None, help="frames per fast row (default 30)")
    b.add_argument("--backends", default=None, metavar="LIST",
                   help="ray-cast rows, comma-separated, e.g. warp,opencl or warp-cuda (default: warp,opencl)")
    return p


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


def _grid_from_spec(spec: tuple[float, ...]) -> FruxelGrid:
    from fruxel import FruxelGrid

    w, h, d, zn, zf, hfov = spec
    return FruxelGrid(width=w, height=h, depth=d, z_near=zn, z_far=zf, hfov=hfov)


def _classes_for(n_channels: int, given: Any) -> ClassTable:
    from fruxel import DEFAULT_CLASSES, ClassTable

    if given is not None:
        table = ClassTable.from_dict(given)
        if len(table) != n_channels:
            raise InputError(f"the class table has {len(table)} classes but the logits have {n_channels} channels")
        return table
    if n_channels <= len(DEFAULT_CLASSES):
        return ClassTable(DEFAULT_CLASSES.names[:n_channels], DEFAULT_CLASSES.colours[:n_channels])
    extra = [f"class {c}" for c in range(len(DEFAULT_CLASSES), n_channels)]
    return DEFAULT_CLASSES.extended(*extra)


def _read_sidecar(path: Path) -> tuple[Any, Any]:
    side = path.with_suffix(".json")
    if not side.is_file():
        return None, None
    try:
        meta = json.loads(side.read_text(encoding="utf-8"))
    except (OSError, ValueError) as e:
        raise InputError(f"cannot read the grid sidecar {str(side)!r}: {e}") from None
    if isinstance(meta, dict) and "grid" in meta:
        return meta["grid"], meta.get("classes")
    return meta, None


def _load_tensor(path: Path) -> tuple[Any, Any, Any]:
    """The logits of a ``.npy`` / ``.pt`` file and the grid / classes dicts a ``.pt`` dict carries."""
    if path.suffix.lower() == ".npy":
        import numpy as np

        try:
            return np.load(path, allow_pickle=False), None, None
        except (OSError, ValueError, EOFError) as e:
            raise InputError(f"cannot read logits {str(path)!r}: {e}") from None
    try:
        import torch
    except ImportError:
        raise InputError(f"reading {str(path)!r} needs torch: pip install 'fruxel[train]'") from None
    try:
        obj = torch.load(path, map_location="cpu", weights_only=True)
    except Exception as e:  # noqa: BLE001 - torch raises many types for a damaged or unsafe file
        msg = str(e).splitlines()[0] if str(e) else type(e).__name__
        raise InputError(f"cannot read logits {str(path)!r}: {msg}") from None
    if isinstance(obj, dict):
        if "logits" not in obj:
            raise InputError(f"{str(path)!r} holds a dict without 'logits' (keys: {sorted(map(str, obj))})")
        return obj["logits"], obj.get("grid"), obj.get("classes")
    return obj, None, None


def load_input(model: str | None, grid_spec: tuple[float, ...] | None = None) -> RenderInput:
    """Read MODEL (see the module docstring).

    Raises:
        FruxelFileError: a missing or invalid ``.npz`` model.
        InputError: a missing, unreadable or misshapen tensor file, or no grid for it.
        GridError, ClassTableError: an invalid grid or class table.
    """
    import numpy as np

    import fruxel

    if model is None:
        from fruxel.data import SAMPLE_ROOM

        m = fruxel.load(SAMPLE_ROOM)
        return RenderInput(np.ascontiguousarray(m.labels), m.grid, m.classes, SAMPLE_ROOM.stem)
    path = Path(model)
    suffix = path.suffix.lower()
    if suffix not in (".npz", ".npy", ".pt", ".pth"):
        raise InputError(f"unknown model file type {str(path)!r}: expected .npz (model) or .npy / .pt (logits)")
    if suffix == ".npz":
        m = fruxel.load(path)
        return RenderInput(np.ascontiguousarray(m.labels), m.grid, m.classes, path.stem)
    if not path.is_file():
        raise InputError(f"no such file: {str(path)!r}")
    tensor, grid_dict, classes_dict = _load_tensor(path)
    side_grid, side_classes = _read_sidecar(path)
    if grid_spec is not None and len(grid_spec) == 6:
        grid = _grid_from_spec(grid_spec)
    elif grid_dict is not None or side_grid is not None:
        grid = fruxel.FruxelGrid.from_dict(grid_dict if grid_dict is not None else side_grid)
    else:
        raise InputError(f"{str(path)!r} is a bare tensor: give its grid with --grid W,H,D,z_near,z_far,hfov "
                         f"or a sidecar {str(path.with_suffix('.json'))!r}")
    shape = tuple(int(s) for s in tensor.shape)
    if len(shape) == 4:
        tensor = tensor[None]
    elif not (len(shape) == 5 and shape[0] == 1):
        raise InputError(f"logits in {str(path)!r} must have shape (C, D, H, W) or (1, C, D, H, W), got {shape}")
    kind = str(tensor.dtype)
    if "float" not in kind:
        raise InputError(f"logits in {str(path)!r} must be floating point, got dtype {kind}")
    if tuple(tensor.shape[2:]) != grid.shape:
        raise InputError(f"logits in {str(path)!r} have (D, H, W) = {tuple(tensor.shape[2:])} but the grid has "
                         f"{grid.shape}")
    classes = _classes_for(int(tensor.shape[1]), classes_dict if classes_dict is not None else side_classes)
    return RenderInput(tensor, grid, classes, path.stem)


# ---------------------------------------------------------------------------------------------------- cameras
def _look_from(grid: FruxelGrid, azimuth: float, elevation: float, width: int, height: int, hfov: float,
               centred: bool = True) -> Camera:
    """A camera at the given angles around the frustum, at the distance where the whole frustum just fits.

    Args:
        grid: the model's grid.
        azimuth, elevation: degrees; azimuth 0 stands behind the apex (towards -z), elevation lifts towards -y
            (grid frame, OpenCV axes).
        width, height, hfov: image size and horizontal field of view.
        centred: aim so that the frustum's image is centred (a still); False aims at the centre of its bounding
            box (orbits turn about that fixed point).
    """
    import numpy as np

    from fruxel import Camera
    from fruxel.camera import orbit_direction

    from .scene import frustum_corners

    d = orbit_direction(math.radians(azimuth), math.radians(elevation))
    corners = frustum_corners(grid)
    target = grid.centre()

    def fits(r: float) -> bool:
        p = Camera.look_at(target + r * d, target, width=width, height=height, hfov=hfov).project(corners)
        mx, my = FIT_MARGIN * width, FIT_MARGIN * height
        return bool(np.all(p[:, 2] > 0) and np.all((p[:, 0] >= mx) & (p[:, 0] <= width - mx))
                    and np.all((p[:, 1] >= my) & (p[:, 1] <= height - my)))

    def fit() -> float:
        hi = float(np.linalg.norm(grid.bounds()[1] - grid.bounds()[0]))
        while not fits(hi):
            hi *= 2.0
        lo = 0.0
        for _ in range(40):
            mid = 0.5 * (lo + hi)
            lo, hi = (lo, mid) if fits(mid) else (mid, hi)
        return hi

    r = fit()
    for _ in range(3 if centred else 0):
        cam = Camera.look_at(target + r * d, target, width=width, height=height, hfov=hfov)
        p = cam.project(corners)
        # Move the aim point sideways in the image plane by the offset of the frustum's image from the centre,
        # converted to metres at the aim point's depth, then fit the distance again.
        off_x = 0.5 * (p[:, 0].min() + p[:, 0].max()) - cam.cx
        off_y = 0.5 * (p[:, 1].min() + p[:, 1].max()) - cam.cy
        target = target + r * (off_x / cam.fx * cam.rotation[:, 0] + off_y / cam.fy * cam.rotation[:, 1])
        r = fit()
    return Camera.look_at(target + r * d, target, width=width, height=height, hfov=hfov)


def default_camera(grid: FruxelGrid, width: int, height: int) -> Camera:
    """The default viewing camera (module docstring): oblique, fitted to the frustum."""
    return _look_from(grid, DEFAULT_AZIMUTH, DEFAULT_ELEVATION, width, height, DEFAULT_HFOV)


def orbit(grid: FruxelGrid, base: Camera, n: int) -> list[Camera]:
    """``n`` cameras one turn around the frustum's centre, starting at the default azimuth, all at one distance.

    Args:
        grid: the model's grid.
        base: the viewing camera; its image size and horizontal field of view are kept.
        n: number of frames.
    """
    import numpy as np

    hfov = math.degrees(2.0 * math.atan(base.width / (2.0 * base.fx)))
    cams = [_look_from(grid, DEFAULT_AZIMUTH + 360.0 * f / n, DEFAULT_ELEVATION, base.width, base.height, hfov,
                       centred=False) for f in range(n)]
    # One distance for the whole turn (the farthest fit), so the model does not breathe in and out.
    centre = grid.centre()
    r = max(float(np.linalg.norm(c.position - centre)) for c in cams)
    return [c.with_pose(_pose_at(c, centre, r)) for c in cams]


def _pose_at(cam: Camera, centre: np.ndarray, r: float) -> np.ndarray:
    import numpy as np

    pose = np.array(cam.pose)
    d = pose[:3, 3] - centre
    pose[:3, 3] = centre + d * (r / float(np.linalg.norm(d)))
    return pose


def viewing_camera(text: str | None, grid: FruxelGrid, size: tuple[int, int] | None) -> Camera:
    """The camera of ``--camera`` (JSON text or a file) or :func:`default_camera` at ``size``."""
    from fruxel import Camera

    if text is None:
        w, h = size or DEFAULT_SIZE
        return default_camera(grid, w, h)
    if os.path.isfile(text):
        try:
            text = Path(text).read_text(encoding="utf-8")
        except OSError as e:
            raise InputError(f"cannot read camera file: {e}") from None
    return Camera.from_json(text)


# ---------------------------------------------------------------------------------------------------- rendering
@dataclass(frozen=True)
class RenderOptions:
    """What to draw and how (the CLI's choices)."""

    mode: str = "mesh"
    """``"mesh"``, ``"raycast"`` or ``"both"``."""
    shell: str = "own"
    """Shell source: ``"none"``, ``"own"``, ``"poses"`` or ``"view"``."""
    poses: int = 6
    """Number of cameras for ``shell="poses"``."""
    meshing: str = "greedy"
    """``"full"``, ``"culled"`` or ``"greedy"``."""
    shading: str = "lit"
    """``"lit"`` or ``"flat"``, for mesh and ray-cast images alike."""
    fog: bool = False
    """Depth fog in ray-cast images."""
    legend: bool = True
    """Draw the class legend."""
    frustum: bool = False
    """Draw the frustum's edges in mesh images."""
    backend: str | None = None
    """Kernel backend, None for the best available."""
    device: str | None = None
    """Warp device, None to follow the data."""
    threshold: float | None = None
    """Occupancy threshold for scores, None for the argmax rule."""


def shell_labels(inp: RenderInput, opts: RenderOptions, camera: Camera) -> np.ndarray:
    """The labels to mesh: ``(D, H, W)`` uint8 numpy, the volume after the chosen shell.

    Args:
        inp: the model.
        opts: shell source, backend and threshold.
        camera: the viewing camera (for ``shell="view"``).
    """
    import numpy as np

    from fruxel import kernels, labels_from_scores

    from .raycast import to_numpy

    if opts.shell == "none":
        vol = inp.volume
    else:
        if opts.shell == "own":
            cams = inp.grid.camera()
        elif opts.shell == "poses":
            cams = kernels.orbit_cameras(inp.grid, opts.poses)
        else:
            cams = camera
        vol = kernels.shell(inp.volume, inp.grid, cams, backend=opts.backend, device=opts.device,
                            threshold=opts.threshold)
    if inp.is_scores:
        return labels_from_scores(to_numpy(vol)[0], threshold=opts.threshold, axis=0)
    return np.ascontiguousarray(to_numpy(vol), dtype=np.uint8)


def build_mesh(inp: RenderInput, opts: RenderOptions, camera: Camera) -> TriMesh:
    """The :class:`fruxel.mesh.TriMesh` (grid frame) of the shell of ``inp`` seen from ``camera``."""
    from fruxel.mesh import mesh_labels

    return mesh_labels(shell_labels(inp, opts, camera), inp.grid, inp.classes.palette(), mode=opts.meshing)


class FrameRenderer:
    """Draws the images of one model for a sequence of cameras, rebuilding the mesh only when the shell changes."""

    def __init__(self, inp: RenderInput, opts: RenderOptions) -> None:
        self.inp = inp
        self.opts = opts
        self.mesh: TriMesh | None = None
        self._view: Any = None

    def mesh_for(self, camera: Camera) -> TriMesh:
        """The mesh for ``camera``: built once, or per camera for ``shell="view"``."""
        if self.mesh is None or self.opts.shell == "view":
            self.mesh = build_mesh(self.inp, self.opts, camera)
        return self.mesh

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

    def raycast_image(self, camera: Camera) -> tuple[np.ndarray, list[int]]:
        """``(h, w, 3)`` uint8 ray-cast image and the labels it shows."""
        from .legend import present_labels
        from .raycast import RaycastStyle, raycast_image

        style = RaycastStyle(shading=self.opts.shading, fog=self.opts.fog)
        img, labels = raycast_image(self.inp.volume, self.inp.grid, camera, self.inp.classes.palette(),
                                    backend=self.opts.backend, device=self.opts.device,
                                    threshold=self.opts.threshold, style=style)
        return img, present_labels(labels)

    def _backend_name(self) -> str:
        from fruxel import kernels

        return kernels.registry.describe(self.opts.backend, self.opts.device, self.inp.volume)

    def image(self, camera: Camera) -> np.ndarray:
        """The image of the chosen mode, with legend (and captions for ``"both"``): ``(h, w', 3)`` uint8."""
        import numpy as np

        from .legend import draw_caption, draw_legend

        if self.opts.mode == "mesh":
            img, present = self.mesh_image(camera)
        elif self.opts.mode == "raycast":
            img, present = self.raycast_image(camera)
        else:
            mimg, mp = self.mesh_image(camera)
            rimg, rp = self.raycast_image(camera)
            mimg = draw_caption(mimg, f"mesh: shell {self.opts.shell}, {self.opts.meshing}, "
                                      f"{0 if self.mesh is None else self.mesh.n_faces} triangles")
            rimg = draw_caption(rimg, f"ray cast: first_hit on {self._backend_name()}")
            gap = np.full((mimg.shape[0], 2, 3), 160, np.uint8)
            img, present = np.concatenate([mimg, gap, rimg], axis=1), sorted(set(mp) | set(rp))
        if self.opts.legend:
            img = draw_legend(img, self.inp.classes, present)
        return img


# ---------------------------------------------------------------------------------------------------- outputs
def write_png(path: Path, image: np.ndarray) -> Path:
    """Write ``(h, w, 3)`` uint8 RGB to ``path`` atomically (:func:`fruxel.io.atomic_path`), making its folder."""
    from PIL import Image

    from fruxel.io import atomic_path

    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        Image.fromarray(image).save(tmp, format="PNG")
    return path


def write_video(path: Path, frames: list[np.ndarray], fps: int) -> Path:
    """Write frames (each ``(h, w, 3)`` uint8) as a looping GIF or an MP4, atomically, by ``path``'s suffix.

    Raises:
        InputError: MP4 without ``imageio-ffmpeg``.
    """
    from fruxel.io import atomic_path

    mp4 = path.suffix.lower() == ".mp4"
    if mp4:
        import importlib.util

        if importlib.util.find_spec("imageio_ffmpeg") is None:
            raise InputError("MP4 output needs imageio-ffmpeg (pip install imageio-ffmpeg); or use --video gif")
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_path(path) as tmp:
        if mp4:
            import imageio.v2 as imageio
            import numpy as np

            # libx264 with yuv420p needs even sizes; pad by one row / column where needed.
            h, w = frames[0].shape[:2]
            frames = [np.pad(f, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") for f in frames]
            imageio.mimwrite(tmp, frames, format="FFMPEG", fps=fps, codec="libx264", macro_block_size=1)
        else:
            from PIL import Image

            ims = [Image.fromarray(f) for f in frames]
            ims[0].save(tmp, format="GIF", save_all=True, append_images=ims[1:], duration=round(1000 / fps), loop=0)
    return path


def _has_display() -> bool:
    if sys.platform in ("darwin", "win32"):
        return True
    return bool(os.environ.get("DISPLAY") or os.environ.get("WAYLAND_DISPLAY"))


def open_viewer(inp: RenderInput, opts: RenderOptions, camera: Camera) -> None:
    """Open pyrender's interactive Viewer on the mesh (pyrender's lights; its own camera controls).

    Raises:
        InputError: no display, or the Viewer could not open a window.
    """
    if not _has_display():
        raise InputError("--view needs a display (DISPLAY is not set); leave out --view to render offscreen to PNG")
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
                        window_title=f"{PROG}: {inp.name}")
    except Exception as e:  # noqa: BLE001 - pyglet / OpenGL raise many types when no window can be opened
        raise InputError(f"cannot open the viewer window: {type(e).__name__}: {e}") from None


def run_render(args: argparse.Namespace) -> list[Path]:
    """Render as asked; returns the files written (none for ``--view``)."""
    if args.export is not None and args.export.suffix.lower() not in (".glb", ".ply"):
        raise InputError(f"--export writes .glb or .ply, got {str(args.export)!r}")
    if args.grid is not None and len(args.grid) != 6:
        raise InputError("--grid N is for --benchmark; a logits tensor's grid is W,H,D,z_near,z_far,hfov")
    inp = load_input(args.model, args.grid)
    camera = viewing_camera(args.camera, inp.grid, args.size)
    opts = RenderOptions(mode=args.mode, shell=args.shell, poses=args.poses, meshing=args.meshing,
                         shading=args.shading, fog=args.fog, legend=args.legend, frustum=args.frustum,
                         backend=args.backend, device=args.device, threshold=args.threshold)
    if args.view:
        open_viewer(inp, opts, camera)
        return []
    written: list[Path] = []
    frames = FrameRenderer(inp, opts)
    if args.orbit is not None:
        from tqdm import tqdm

        cams = orbit(inp.grid, camera, args.orbit)
        # stderr, like the error lines; the bar disappears when done so scripts see only the written paths.
        images = [frames.image(c) for c in tqdm(cams, desc="orbit", unit="frame", leave=False, disable=None)]
        written.append(write_video(args.out / f"{inp.name}_{args.mode}_orbit.{args.video}", images, args.fps))
    else:
        written.append(write_png(args.out / f"{inp.name}_{args.mode}.png", frames.image(camera)))
    if args.export is not None:
        from fruxel.mesh import export_mesh

        written.append(export_mesh(frames.mesh_for(camera), args.export))
    return written


def _user_errors() -> tuple[type[BaseException], ...]:
    import fruxel
    from fruxel import kernels

    return (InputError, fruxel.FruxelFileError, fruxel.GridError, fruxel.CameraError, fruxel.ModelError,
            fruxel.ClassTableError, kernels.VolumeError, kernels.BackendUnavailable, kernels.BackendError)


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``fruxel-render``; returns the exit status (0, or 2 for bad input)."""
    args = build_parser().parse_args(argv)
    errors = _user_errors()
    try:
        if args.benchmark:
            from .table1 import run_cli

            written = run_cli(args)
        else:
            written = run_render(args)
    except errors as e:
        msg = " ".join(str(e).split())
        print(f"{PROG}: error: {msg}", file=sys.stderr)
        return 2
    except OSError as e:
        print(f"{PROG}: error: cannot write output: {e}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        return 130
    for path in written:
        print(path)
    return 0


if __name__ == "__main__":
    sys.exit(main())

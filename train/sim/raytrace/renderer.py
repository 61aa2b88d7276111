"""The ray-traced renderer, ``"raytrace"`` (:class:`RaytraceRenderer`): the host side that uploads rooms and runs
the kernels of this package for each image.

Per room (:meth:`RaytraceRenderer.set_scene`)
    every triangle of every object, solid or not, into one ``wp.Mesh`` (BVH) with each face's material (and two
    more BVHs, of the faces that stop light and of the glass and shining ones, for the shadow and ambient rays), the
    material table, the lights (:mod:`.scene_arrays`), the textures and images the materials name (loaded from
    the asset pack once per process and kept on the device across rooms, :mod:`.textures`), and the room's
    ambient light and the radiance of its window panes (:mod:`.ambient`).

Per image (:meth:`RaytraceRenderer.render`)
    the draws of the sample's generator, in this order: three kernel seeds (camera rays, lights, occlusion), the
    ambient factor, then the camera response's values (:func:`.response.draw_response`); then the camera rays
    (:mod:`.primary`), the lights with their shadows (:mod:`.lights`), the ambient rays (:mod:`.occlusion`),
    the pixels (:mod:`.resolve`) and the camera response (:mod:`.response`). Without a generator the seeds are
    fixed, the ambient factor is its range's middle and the response is neutral.

Device: CUDA when present, else Warp's CPU device (or the one given). The same room, pose and generator give the
same bytes on the same machine and device: every random number comes from the generator, and no kernel sums
with atomics.
"""

from __future__ import annotations

import time
from dataclasses import dataclass
from typing import Any

import numpy as np

from fruxel.camera import Camera, check_pose
from fruxel.kernels.wp.runtime import resolve_device, warp

from . import ambient as ambient_mod
from .buffers import Buffers, allocate
from .lights import shade_lights
from .normals import corner_normals
from .occlusion import trace_ambient
from .primary import trace_primary
from .resolve import resolve
from .response import develop, draw_response
from .scene_arrays import LIGHT_FIELDS, MATERIAL_FIELDS, SceneArrays, build_scene_arrays, srgb_to_linear
from .surfaces import LightData, MaterialData, SceneData
from .textures import TextureLayers

wp = warp()

STAGES = ("arrays", "textures", "bvh", "upload", "ambient", "primary", "lights", "occlusion", "resolve", "response")
"""Stages :attr:`RaytraceRenderer.timings` counts when ``profile`` is on: per room the first five (``arrays``: the
room flattened on the host; ``textures``: pack assets decoded and uploaded the first time a room uses them;
``bvh``: the BVH build (:data:`BVH_CONSTRUCTOR`) and upload; ``upload``: the other arrays and the smoothed
normals), per image the rest (``response`` includes the image's download and JPEG)."""

BVH_CONSTRUCTOR = "sah"
"""Warp's BVH builder for a room's mesh, on every device. SAH (built on the host, then uploaded to a CUDA device)
traces the furnished rooms, wall-sized triangles beside small furniture parts, much faster than a split at the
centroids' spatial median and somewhat faster than CUDA's own default, LBVH, whose GPU build is cheaper than SAH's
host build (BENCHMARKS.md, "## BVH constructors", ``benchmarks/bench_bvh.py``: the trade per sample)."""

_PACKS: dict[str, Any] = {}
"""Asset packs opened in this process, by resolved folder."""


def open_pack(folder: str | None) -> Any:
    """The :class:`~fruxel.train.sim.assetpack.AssetPack` the simulator config's ``assets`` names (resolved as the
    rooms resolve it: the folder, else ``$FRUXEL_ASSETS``, else the repository's), opened once per process.

    Raises:
        ConfigError: no pack there (the message names the folder and says how to build it).
        AssetPackError: a pack whose manifest or files are broken.
    """
    from ..assetpack import AssetPack
    from ..rooms.library import resolve_pack

    key = str(resolve_pack(folder).resolve())
    if key not in _PACKS:
        _PACKS[key] = AssetPack(key)
    return _PACKS[key]


@dataclass
class _Room:
    """A room on the device."""

    scene: Any
    arrays: SceneArrays
    meshes: tuple[Any, ...]
    """The ``wp.Mesh`` objects ``data`` names (kept so that their BVHs live as long as the room)."""
    data: Any
    ambient: np.ndarray
    """``(3,)`` the ambient irradiance estimate (before the per-sample factor)."""


def _light_meshes(arrays: SceneArrays, points: Any, device: Any) -> tuple[Any, Any | None, np.ndarray]:
    """The BVHs of the faces that stop light and of the others (:class:`~.surfaces.SceneData`).

    Returns:
        ``(opaque, clear, clear_face)``: the ``wp.Mesh`` of the faces whose material is opaque and does not shine,
        that of the rest (None when there is none) and ``(K,)`` int32 ``mesh`` face indices of ``clear``'s faces.
    """
    m, face_material = arrays.materials, arrays.face_material
    stops = (m["opacity"][face_material] >= 1.0) & (m["emission"][face_material] <= 0.0)
    faces = arrays.faces.astype(np.int32)

    def bvh(rows: np.ndarray) -> Any:
        return wp.Mesh(points=points, indices=wp.array(rows.ravel(), dtype=wp.int32, device=device),
                       bvh_constructor=BVH_CONSTRUCTOR)

    clear_face = np.flatnonzero(~stops).astype(np.int32)
    # A room of glass alone would leave nothing that stops light: one degenerate face, which no ray hits.
    opaque = bvh(faces[stops] if stops.any() else np.zeros((1, 3), np.int32))
    return opaque, bvh(faces[clear_face]) if len(clear_face) else None, clear_face


class RaytraceRenderer:
    """Images of rooms ray-traced with NVIDIA Warp (module docstring); one per process.

    Args:
        config: the :class:`~fruxel.train.sim.config.SimConfig`: image size, the camera, ``raytrace`` settings,
            the background of the sky.
        device: Warp device (None: CUDA when present, else the CPU).
    """

    def __init__(self, config: Any, device: str | None = None) -> None:
        self.config = config
        """The simulator config."""
        self.device = resolve_device(device)
        """The Warp device the images are computed on."""
        self.profile = False
        """When True, every stage is synchronised and timed into :attr:`timings` (slower)."""
        self.timings: dict[str, float] = dict.fromkeys(STAGES, 0.0)
        """Seconds per stage of :data:`STAGES` while ``profile`` was on."""
        self._layers: TextureLayers | None = None
        self._room: _Room | None = None
        self._buffers: Buffers | None = None

    # ------------------------------------------------------------------ rooms
    def set_scene(self, scene: Any) -> None:
        """Upload a room (see the module docstring); the same room again costs nothing.

        Raises:
            SceneArraysError: a mesh or material the renderer cannot draw (naming the object).
            AssetPackError: a texture or image missing from the pack, or no pack.
        """
        if self._room is not None and self._room.scene is scene:
            return
        rt = self.config.raytrace
        if self._layers is None:
            self._layers = TextureLayers(None, rt.texture_size, self.device)
        layers = self._layers
        t0 = self._mark()

        loading = [0.0]

        def lookup(role: str, asset_id: str) -> int:
            t = time.perf_counter()
            if layers.pack is None:
                layers.pack = open_pack(self.config.assets)
            layer = layers.layer(role, asset_id)
            loading[0] += time.perf_counter() - t
            return layer

        arrays = build_scene_arrays(scene, lookup, layers.tile_aspect)
        if self.profile:
            self.timings["textures"] += loading[0]
            t0 += loading[0]
        t1 = self._mark("arrays", t0)
        self._room = None
        dev = self.device
        points = wp.array(arrays.vertices, dtype=wp.vec3, device=dev)
        mesh = wp.Mesh(points=points, indices=wp.array(arrays.faces.ravel(), dtype=wp.int32, device=dev),
                       bvh_constructor=BVH_CONSTRUCTOR)
        opaque, clear, clear_face = _light_meshes(arrays, points, dev)
        t2 = self._mark("bvh", t1)
        data = SceneData()
        data.mesh = mesh.id
        data.opaque = opaque.id
        data.clear = clear.id if clear is not None else 0
        data.clear_face = wp.array(clear_face, dtype=wp.int32, device=dev)
        data.clear_faces = len(clear_face)
        data.face_material = wp.array(arrays.face_material, dtype=wp.int32, device=dev)
        data.corner_normals = corner_normals(points, arrays.faces, rt.smooth_angle, dev)
        data.materials = _struct_array(MaterialData, arrays.materials, MATERIAL_FIELDS, dev)
        data.lights = _struct_array(LightData, arrays.lights, LIGHT_FIELDS, dev)
        data.albedo_texels, data.normal_texels, data.srgb = layers.albedo, layers.normal, layers.srgb
        data.layer_size, data.levels = layers.size, layers.levels
        data.glass_layers = int(rt.glass_layers)
        data.sky = wp.vec3(*self._sky(arrays).astype(np.float32))
        data.portals = wp.array(arrays.portals, dtype=wp.int32, device=dev)
        data.portal_cdf = wp.array(arrays.portal_cdf, dtype=wp.float32, device=dev)
        data.portal_area = float(arrays.portal_area)
        data.portal_radiance = wp.zeros(len(arrays.portals), dtype=wp.vec3, device=dev)
        t3 = self._mark("upload", t2)
        ambient = ambient_mod.estimate_ambient(scene, data, int(scene.seed), rt.window_samples > 0, dev)
        data.portal_radiance = wp.array(ambient_mod.measure_portals(data, len(arrays.portals), int(scene.seed), dev),
                                        dtype=wp.vec3, device=dev)
        self._mark("ambient", t3)
        self._room = _Room(scene, arrays, (mesh, opaque, clear), data, ambient)

    def _sky(self, arrays: SceneArrays) -> np.ndarray:
        """Radiance of rays that leave the scene (``RaytraceConfig.sky``)."""
        lights = arrays.lights
        luma = lights["radiance"] @ np.array([0.2126, 0.7152, 0.0722], dtype=np.float32)
        level = float(np.sum(np.where(lights["kind"] == 0, luma, luma / 4.0)))
        bg = srgb_to_linear(self.config.image.background)
        return bg * self.config.raytrace.sky * level / np.pi

    @property
    def ambient(self) -> np.ndarray:
        """The current room's ambient irradiance estimate, ``(3,)`` linear RGB (before the per-sample factor)."""
        if self._room is None:
            raise RuntimeError("RaytraceRenderer has no room: call set_scene() first")
        return self._room.ambient.copy()

    # ------------------------------------------------------------------ images
    def render(self, pose: Any, rng: np.random.Generator | None = None, camera: Camera | None = None) -> np.ndarray:
        """The image of the current room from camera-to-world ``pose``.

        Args:
            pose: ``(4, 4)`` camera-to-world transform, OpenCV axes, world frame (z up), metres.
            rng: the sample's generator (None, or ``config.image.augment.enabled`` False: fixed seeds, neutral
                camera response).
            camera: the intrinsics and image size to draw with (its pose is ignored: ``pose`` places it); None: the
                network image's camera (:meth:`SimConfig.image_camera`). The simulator asks for another one when
                the config's cameras draw other fields of view (:mod:`..cameras`).

        Returns:
            ``(S * H / W, S, 3)`` uint8 RGB image, or ``camera``'s ``(height, width, 3)``.

        Raises:
            RuntimeError: no room was set.
        """
        if self._room is None:
            raise RuntimeError("RaytraceRenderer.render() needs a room: call set_scene() first")
        room, rt = self._room, self.config.raytrace
        pose = check_pose(pose)
        if not self.config.image.augment.enabled:
            rng = None  # an image "without augmentation" (fruxel-sim --no-augment): no random camera response
        if rng is None:
            seeds, factor = (1, 2, 3), float(np.mean(rt.ambient))
        else:
            seeds = tuple(int(s) for s in rng.integers(0, 2**31, size=3))
            factor = float(rng.uniform(*rt.ambient))
        draws = draw_response(rt.response, rng)
        cam = self.config.image_camera() if camera is None else camera
        h, w, spp = int(cam.height), int(cam.width), int(rt.samples_per_pixel)
        slots = spp + int(rt.edge_samples)
        b = self._buffers
        if b is None or (b.height, b.width, b.spp) != (h, w, slots):
            b = self._buffers = allocate(h, w, slots, self.device)
        irradiance = room.ambient * factor
        t0 = self._mark()
        trace_primary(room.data, b, pose, (cam.fx, cam.fy, cam.cx, cam.cy), irradiance / np.pi, seeds[0], spp,
                      self.device)
        t1 = self._mark("primary", t0)
        shade_lights(room.data, b, rt.shadow_samples, seeds[1], self.device)
        t2 = self._mark("lights", t1)
        trace_ambient(room.data, b, rt.ao_samples, rt.window_samples, rt.ao_distance, seeds[2], self.device)
        t3 = self._mark("occlusion", t2)
        resolve(b, irradiance, rt.denoise_radius, self.device)
        t4 = self._mark("resolve", t3)
        image = develop(b, draws, self.device)
        self._mark("response", t4)
        return image

    def radiance(self) -> np.ndarray:
        """The last image's linear radiance before the camera response: ``(H, W, 3)`` float32 (tools, tests)."""
        if self._buffers is None:
            raise RuntimeError("RaytraceRenderer.radiance() needs a rendered image")
        b = self._buffers
        return np.array(b.pixels.radiance.numpy(), dtype=np.float32).reshape(b.height, b.width, 3)

    def _mark(self, stage: str | None = None, since: float = 0.0) -> float:
        """With ``profile`` on: wait for the device and add the time since ``since`` to ``stage``."""
        if not self.profile:
            return 0.0
        wp.synchronize_device(self.device)
        now = time.perf_counter()
        if stage is not None:
            self.timings[stage] += now - since
        return now

    # ------------------------------------------------------------------ lifetime
    def close(self) -> None:
        """Free the room and the image buffers (idempotent); texture layers stay for the next room."""
        self._room = None
        self._buffers = None

    def __enter__(self) -> RaytraceRenderer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def _struct_array(cls: Any, columns: dict[str, np.ndarray], fields: tuple[str, ...], device: Any) -> Any:
    """The rows of ``columns`` as a Warp array of the struct ``cls`` (fields named as the columns, the rest zero) on
    ``device``, made through a numpy array of the struct's layout: a Python object a row and a field cost about 5 ms
    a room."""
    rows = np.zeros(len(columns[fields[0]]), dtype=cls.numpy_dtype())
    for name in fields:
        rows[name] = columns[name]
    return wp.array(rows, dtype=cls, device=device)

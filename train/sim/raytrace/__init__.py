"""The ray-traced renderer of the simulator, ``"raytrace"``: rooms drawn like photographs, in NVIDIA Warp on CUDA
(or Warp's CPU device).

Textures of real materials at metric scale with normal maps, images (paintings, the outdoor view behind windows),
GGX reflections, one to a few lights with soft shadows, glass, emitters, an ambient light estimated from the room
with ambient occlusion, anti-aliasing; then a camera response (exposure, white balance, filmic tone curve,
vignetting, blur, noise, JPEG) drawn per sample. The renderer decides the image only: labels come from the
scene's solids by ``fruxelize``.

Modules (host code beside its kernels):

* :mod:`.config` — :class:`RaytraceConfig`, :class:`CameraResponseConfig` (numpy only);
* :mod:`.renderer` — :class:`~.renderer.RaytraceRenderer`, the :mod:`..renderer` protocol;
* :mod:`.scene_arrays` — a room as flat arrays (triangles, materials, lights; numpy only);
* :mod:`.textures` — texture layers with mip levels on the device, and their filtering;
* :mod:`.surfaces` — the device data of a room and the shared device functions (rays through glass, materials,
  reflectance, sampling);
* :mod:`.primary`, :mod:`.lights`, :mod:`.occlusion`, :mod:`.resolve`, :mod:`.ambient` — the kernels of an image
  and of a room's ambient light;
* :mod:`.response` — the camera response;
* :mod:`.dressing` — a stand-in that gives the old flat rooms pack materials, for tests, benchmarks and previews
  until the room generator assigns materials itself.

Importing this package loads numpy only; Warp loads with :mod:`.renderer`.
"""

from __future__ import annotations

from .config import RESPONSE_STEPS, CameraResponseConfig, RaytraceConfig

__all__ = ["RESPONSE_STEPS", "CameraResponseConfig", "RaytraceConfig"]

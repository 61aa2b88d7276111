"""Settings of the ray-traced renderer (:class:`RaytraceConfig`) and of the camera response it applies to its images
(:class:`CameraResponseConfig`). numpy only: a config is made and checked without Warp.

Both are reachable from :attr:`SimConfig.raytrace <fruxel.train.sim.config.SimConfig.raytrace>` and recorded with
a data set whose config names the ``"raytrace"`` renderer.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fruxel.errors import ConfigError

from ..checks import check_range

RESPONSE_STEPS = ("exposure", "white_balance", "tone", "vignetting", "blur", "noise", "jpeg")
"""The random steps of the camera response, in the order they act on the image (blur and vignetting act on the
light reaching the sensor, before exposure and noise; JPEG last). A step left out of
:attr:`CameraResponseConfig.steps` keeps its neutral value; its random values are drawn all the same."""


def _check_int(name: str, value: Any, low: int, high: int) -> None:
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)) or not low <= value <= high:
        raise ConfigError(f"{name} must be an integer in [{low}, {high}], got {value!r}")


@dataclass(frozen=True)
class CameraResponseConfig:
    """What a camera does to the light of the scene, drawn per sample from the sample's generator.

    Every value below is drawn for every sample, in the order of the fields, whether or not its step is in
    :attr:`steps`, so that leaving a step out does not reshuffle the others. A step left out takes its neutral
    value (the one each field names). Without a generator (``rng`` None) every step is neutral: the image is
    metered to middle grey, developed with the plain filmic curve and encoded as sRGB.
    """

    enabled: bool = True
    """False: every step neutral, whatever :attr:`steps` says (the generator is still drawn from)."""
    steps: tuple[str, ...] = RESPONSE_STEPS
    """The steps applied, a subset of :data:`RESPONSE_STEPS`."""
    key: tuple[float, float] = (0.14, 0.32)
    """``exposure``: the grey level (linear, in [0, 1]) that auto-exposure maps the image's log-average luminance
    to; neutral 0.18 (a camera's meter)."""
    exposure_ev: tuple[float, float] = (-0.7, 0.7)
    """``exposure``: change in stops after auto-exposure (the image times ``2 ** ev``); neutral 0."""
    temperature: tuple[float, float] = (4000.0, 9000.0)
    """``white_balance``: the colour temperature (kelvin) of the light the camera balances for; 6500 neutral.
    Below it the image turns blue, above it orange (gains of the black body's colour at 6500 K over that at T)."""
    tint: tuple[float, float] = (-0.05, 0.05)
    """``white_balance``: green (positive) or magenta shift, a relative gain of the green channel; neutral 0."""
    contrast: tuple[float, float] = (0.85, 1.2)
    """``tone``: contrast of the filmic curve (a power of the exposed image about middle grey); neutral 1."""
    gamma: tuple[float, float] = (0.9, 1.12)
    """``tone``: exponent applied after the sRGB encoding; neutral 1."""
    saturation: tuple[float, float] = (0.8, 1.2)
    """``tone``: saturation factor (blend with the luminance); neutral 1."""
    vignetting: tuple[float, float] = (0.0, 0.45)
    """``vignetting``: light lost in the image corners (``1 - v r^2``, r = 1 at a corner); neutral 0."""
    defocus_px: tuple[float, float] = (0.0, 1.0)
    """``blur``: standard deviation of a Gaussian defocus blur, pixels; neutral 0."""
    motion_px: tuple[float, float] = (0.0, 3.0)
    """``blur``: length of a straight motion blur, pixels, in a uniform random direction; neutral 0."""
    motion_probability: float = 0.3
    """``blur``: the chance that a sample's blur is the motion blur rather than the defocus blur."""
    shot_noise: tuple[float, float] = (0.0, 0.025)
    """``noise``: photon (shot) noise, standard deviation ``s * sqrt(x)`` of an exposed value x; neutral 0."""
    read_noise: tuple[float, float] = (0.0, 0.008)
    """``noise``: sensor read noise, standard deviation in units of the exposed image; neutral 0."""
    jpeg_quality: tuple[int, int] = (45, 95)
    """``jpeg``: JPEG quality (PIL, 1-100) the image is compressed at and decoded from; neutral: not compressed."""

    def __post_init__(self) -> None:
        unknown = [s for s in self.steps if s not in RESPONSE_STEPS]
        if unknown or len(set(self.steps)) != len(self.steps):
            raise ConfigError(f"response steps must be distinct names of {list(RESPONSE_STEPS)}, got "
                              f"{list(self.steps)!r}")
        check_range("key", self.key, 1e-3, 1.0)
        check_range("exposure_ev", self.exposure_ev, -8.0, 8.0)
        check_range("temperature", self.temperature, 1500.0, 20000.0)
        check_range("tint", self.tint, -0.5, 0.5)
        check_range("contrast", self.contrast, 0.2, 5.0)
        check_range("gamma", self.gamma, 0.2, 5.0)
        check_range("saturation", self.saturation, 0.0, 4.0)
        check_range("vignetting", self.vignetting, 0.0, 1.0)
        check_range("defocus_px", self.defocus_px, 0.0, 3.0)
        check_range("motion_px", self.motion_px, 0.0, 8.0)
        check_range("shot_noise", self.shot_noise, 0.0, 1.0)
        check_range("read_noise", self.read_noise, 0.0, 1.0)
        check_range("jpeg_quality", self.jpeg_quality, 1, 100)
        if not 0.0 <= float(self.motion_probability) <= 1.0:
            raise ConfigError(f"motion_probability must be in [0, 1], got {self.motion_probability!r}")

    def active(self, step: str) -> bool:
        """Whether ``step`` (one of :data:`RESPONSE_STEPS`) is applied."""
        return bool(self.enabled) and step in self.steps


@dataclass(frozen=True)
class RaytraceConfig:
    """How the ray-traced renderer (``"raytrace"``) samples light, and the camera response on its images.

    Per pixel, :attr:`samples_per_pixel` camera rays (stratified within the pixel) find their first opaque surface
    through up to :attr:`glass_layers` glass surfaces; pixels on an edge (whose rays, or whose neighbours' first
    rays, found different surfaces) get :attr:`edge_samples` more, continuing the same stratified sequence. At each
    surface every light sends :attr:`shadow_samples` shadow rays to random points of the light (soft shadows),
    :attr:`ao_samples` short rays measure the occlusion of the ambient light, and
    :attr:`window_samples` rays to random points of the glass bring the light of what lies behind the windows. The
    cost of an image grows about as ``(samples_per_pixel + edge share * edge_samples) * (1 + lights *
    shadow_samples + ao_samples + window_samples)`` rays per pixel.
    """

    samples_per_pixel: int = 2
    """Camera rays per pixel (anti-aliasing, and the samples of shadows and occlusion), 1-16."""
    edge_samples: int = 2
    """More camera rays at pixels on an edge (anti-aliasing where it shows), 0-14; at most 16 rays a pixel in
    all."""
    shadow_samples: int = 1
    """Shadow rays per light and camera ray, 1-16 (a light's size makes its shadows soft)."""
    ao_samples: int = 2
    """Ambient-occlusion rays per camera ray, 0-16 (0: the ambient light is not occluded)."""
    window_samples: int = 1
    """Rays per camera ray to random points of the glass, for the light of what lies behind the windows, 0-16 (0:
    that light is part of the uniform ambient light)."""
    ao_distance: float = 0.4
    """Length of the ambient-occlusion rays, metres: how far a surface darkens another."""
    ambient: tuple[float, float] = (1.0, 2.2)
    """Range of the factor (drawn per sample) on the room's ambient light, the estimate of its indirect light
    from its lights, surfaces and windows (see :mod:`.ambient`)."""
    sky: float = 0.6
    """Radiance of rays that leave the scene (through an open ceiling), in units of ``(sun irradiance +
    point-light candela / 4) / pi``, times ``ImageConfig.background``."""
    glass_layers: int = 4
    """Glass surfaces (opacity < 1) a ray passes through before the next surface counts as opaque, 0-8."""
    texture_size: int = 256
    """Side of the square texture layers on the device, pixels (a power of two, 16-1024); pack textures and
    images are resampled to it."""
    smooth_angle: float = 35.0
    """Largest angle, degrees, between a face and its neighbours across a vertex for the normals to be smoothed
    there (0: every face flat); boxes keep their edges."""
    denoise_radius: int = 2
    """Half width, pixels, of the edge-aware filter of the diffuse lighting (shadows and occlusion; textures stay
    sharp), 0-4 (0: off)."""
    response: CameraResponseConfig = field(default_factory=CameraResponseConfig)
    """The camera response applied to every image."""

    def __post_init__(self) -> None:
        _check_int("samples_per_pixel", self.samples_per_pixel, 1, 16)
        _check_int("edge_samples", self.edge_samples, 0, 16 - self.samples_per_pixel)
        _check_int("shadow_samples", self.shadow_samples, 1, 16)
        _check_int("ao_samples", self.ao_samples, 0, 16)
        _check_int("window_samples", self.window_samples, 0, 16)
        _check_int("glass_layers", self.glass_layers, 0, 8)
        _check_int("denoise_radius", self.denoise_radius, 0, 4)
        _check_int("texture_size", self.texture_size, 16, 1024)
        if self.texture_size & (self.texture_size - 1):
            raise ConfigError(f"texture_size must be a power of two, got {self.texture_size}")
        if not 0.0 < float(self.ao_distance) <= 10.0:
            raise ConfigError(f"ao_distance must be in (0, 10] metres, got {self.ao_distance!r}")
        if not 0.0 <= float(self.sky) <= 100.0:
            raise ConfigError(f"sky must be in [0, 100], got {self.sky!r}")
        if not 0.0 <= float(self.smooth_angle) < 90.0:
            raise ConfigError(f"smooth_angle must be in [0, 90) degrees, got {self.smooth_angle!r}")
        check_range("ambient", self.ambient, 0.0, 10.0)
        if not isinstance(self.response, CameraResponseConfig):
            raise ConfigError(f"raytrace.response must be a CameraResponseConfig, got {type(self.response).__name__}")

"""The camera response: from the rendered radiance to the 8-bit sRGB image a camera would have saved.

Steps (:data:`.config.RESPONSE_STEPS`; ranges and neutral values in :class:`.config.CameraResponseConfig`), in
the order they act:

1. ``blur`` (:func:`blur_image_kernel`): a Gaussian defocus blur or a straight motion blur of the linear
   radiance;
2. ``vignetting``: ``1 - v r^2`` (``r`` = 1 at the corners);
3. auto-exposure (always): the image is scaled so that its log-average luminance becomes ``key`` (Reinhard's
   key value; :func:`meter_rows_kernel`, :func:`meter_image_kernel`); ``exposure`` draws ``key`` and adds
   ``ev`` stops;
4. ``noise``: shot noise ``s sqrt(x)`` and read noise, Gaussian, per channel of the exposed image;
5. ``white_balance``: channel gains of a black body at 6500 K over one at the drawn temperature, and a green
   tint, normalised to keep a white pixel's luminance;
6. ``tone``: saturation, the contrast about middle grey, the filmic curve (Narkowicz's ACES fit, always), the
   sRGB encoding (always) and a gamma;
7. ``jpeg``: compressed at the drawn quality with PIL and decoded again (on the host).

Steps 1-6 run on the device (:func:`develop_image_kernel`); the image comes to the host once.

Draws (:func:`draw_response`): every value is drawn from the sample's generator in the order of
:class:`ResponseDraws`' fields, whether or not its step is applied; a step that is off keeps its neutral values.
"""

from __future__ import annotations

import dataclasses
import io
import math
from dataclasses import dataclass

import numpy as np

from fruxel.kernels.wp.runtime import warp

from .buffers import Buffers, PixelBuffers
from .config import CameraResponseConfig

wp = warp()
wp.set_module_options({"enable_backward": False})

LUMA = (0.2126, 0.7152, 0.0722)
"""Rec. 709 luminance weights of linear sRGB."""
MIDDLE_GREY = 0.18
"""The key of a neutral exposure."""


@dataclass(frozen=True)
class ResponseDraws:
    """One sample's camera response (:class:`~.config.CameraResponseConfig` says what each value does)."""

    key: float = MIDDLE_GREY
    ev: float = 0.0
    temperature: float = 6500.0
    tint: float = 0.0
    contrast: float = 1.0
    gamma: float = 1.0
    saturation: float = 1.0
    vignetting: float = 0.0
    defocus_px: float = 0.0
    motion_px: float = 0.0
    motion_angle: float = 0.0
    """Radians, in [0, pi)."""
    motion: bool = False
    """Whether the blur is the motion blur (else the defocus blur)."""
    shot_noise: float = 0.0
    read_noise: float = 0.0
    jpeg_quality: int = 0
    """0: no JPEG."""
    noise_seed: int = 0
    """Seed of the noise kernel's random streams."""


_STEP_FIELDS = {
    "exposure": ("key", "ev"), "white_balance": ("temperature", "tint"), "tone": ("contrast", "gamma", "saturation"),
    "vignetting": ("vignetting",), "blur": ("defocus_px", "motion_px", "motion_angle", "motion"),
    "noise": ("shot_noise", "read_noise", "noise_seed"), "jpeg": ("jpeg_quality",),
}
"""The values each step sets; a step that is off keeps their neutral values (the defaults above)."""


def draw_response(config: CameraResponseConfig, rng: np.random.Generator | None) -> ResponseDraws:
    """The camera response of one sample: every value drawn from ``rng`` in a fixed order, then the steps that
    are off (or all, without a generator or with ``enabled`` False) reset to neutral."""
    if rng is None:
        return ResponseDraws()
    c = config
    drawn = ResponseDraws(
        key=float(rng.uniform(*c.key)), ev=float(rng.uniform(*c.exposure_ev)),
        temperature=float(rng.uniform(*c.temperature)), tint=float(rng.uniform(*c.tint)),
        contrast=float(rng.uniform(*c.contrast)), gamma=float(rng.uniform(*c.gamma)),
        saturation=float(rng.uniform(*c.saturation)), vignetting=float(rng.uniform(*c.vignetting)),
        defocus_px=float(rng.uniform(*c.defocus_px)), motion_px=float(rng.uniform(*c.motion_px)),
        motion_angle=float(rng.uniform(0.0, math.pi)), motion=bool(rng.uniform() < c.motion_probability),
        shot_noise=float(rng.uniform(*c.shot_noise)), read_noise=float(rng.uniform(*c.read_noise)),
        jpeg_quality=int(rng.integers(int(c.jpeg_quality[0]), int(c.jpeg_quality[1]) + 1)),
        noise_seed=int(rng.integers(0, 2**31)),
    )
    neutral = ResponseDraws()
    off = {name: getattr(neutral, name) for step, names in _STEP_FIELDS.items() if not c.active(step)
           for name in names}
    return dataclasses.replace(drawn, **off)


def blackbody_rgb(kelvin: float) -> np.ndarray:
    """Linear sRGB colour (green 1) of a black body at ``kelvin`` (1667-25000 K): the Planckian locus fit of Kim et
    al. (2002) in CIE xy, through XYZ."""
    t = float(np.clip(kelvin, 1667.0, 25000.0))
    if t <= 4000.0:
        x = -0.2661239e9 / t**3 - 0.2343589e6 / t**2 + 0.8776956e3 / t + 0.179910
    else:
        x = -3.0258469e9 / t**3 + 2.1070379e6 / t**2 + 0.2226347e3 / t + 0.240390
    if t <= 2222.0:
        y = -1.1063814 * x**3 - 1.34811020 * x**2 + 2.18555832 * x - 0.20219683
    elif t <= 4000.0:
        y = -0.9549476 * x**3 - 1.37418593 * x**2 + 2.09137015 * x - 0.16748867
    else:
        y = 3.0817580 * x**3 - 5.87338670 * x**2 + 3.75112997 * x - 0.37001483
    xyz = np.array([x / y, 1.0, (1.0 - x - y) / y])
    m = np.array([[3.2406, -1.5372, -0.4986], [-0.9689, 1.8758, 0.0415], [0.0557, -0.2040, 1.0570]])
    rgb = np.maximum(m @ xyz, 1e-3)
    return rgb / rgb[1]


def white_balance_gains(temperature: float, tint: float) -> np.ndarray:
    """``(3,)`` channel gains of a camera balanced for ``temperature`` under light that is white at 6500 K, with
    the green tint; a white pixel keeps its luminance."""
    gains = blackbody_rgb(6500.0) / blackbody_rgb(temperature)
    gains[1] *= 1.0 + tint
    return gains / float(np.dot(LUMA, gains))


# ---------------------------------------------------------------------------------------------------- kernels
@wp.func
def _bilinear(img: wp.array(dtype=wp.vec3), width: int, height: int, fx: float, fy: float) -> wp.vec3:
    """Bilinear value of a ``(H * W)`` image at continuous pixel position ``(fx, fy)`` (pixel centres at
    integers), clamped at the border."""
    x0 = int(wp.floor(fx))
    y0 = int(wp.floor(fy))
    ax = fx - float(x0)
    ay = fy - float(y0)
    out = wp.vec3(0.0, 0.0, 0.0)
    for dy in range(2):
        for dx in range(2):
            xx = wp.clamp(x0 + dx, 0, width - 1)
            yy = wp.clamp(y0 + dy, 0, height - 1)
            w = wp.where(dx == 1, ax, 1.0 - ax) * wp.where(dy == 1, ay, 1.0 - ay)
            out += w * img[yy * width + xx]
    return out


@wp.kernel
def blur_image_kernel(width: int, height: int, mode: int, sigma: float, half_length: float, direction: wp.vec2,
                      pixels: PixelBuffers):
    """One thread blurs pixel ``(x, y)`` of ``pixels.radiance`` (vec3, linear) into ``pixels.blurred``.

    Launch dims ``(H, W)``. ``mode`` 0: a copy; 1: Gaussian of standard deviation ``sigma`` pixels (taps within
    ``3 sigma``, at most 4 pixels); 2: the mean along the segment ``+-half_length`` pixels in unit ``direction``
    (x right, y down), sampled every half pixel, bilinear, clamped at the border.
    """
    y, x = wp.tid()
    p = y * width + x
    if mode == 1:
        radius = wp.min(4, int(wp.ceil(3.0 * sigma)))
        total = wp.vec3(0.0, 0.0, 0.0)
        weight = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
        for dy in range(-radius, radius + 1):
            for dx in range(-radius, radius + 1):
                xx = wp.clamp(x + dx, 0, width - 1)
                yy = wp.clamp(y + dy, 0, height - 1)
                w = wp.exp(-float(dx * dx + dy * dy) / (2.0 * sigma * sigma))
                total += w * pixels.radiance[yy * width + xx]
                weight += w
        pixels.blurred[p] = total / weight
    elif mode == 2:
        taps = 2 * int(wp.ceil(2.0 * half_length)) + 1
        total = wp.vec3(0.0, 0.0, 0.0)
        for t in range(taps):
            s = -half_length + 2.0 * half_length * float(t) / float(taps - 1)
            total += _bilinear(pixels.radiance, width, height, float(x) + s * direction[0],
                               float(y) + s * direction[1])
        pixels.blurred[p] = total / float(taps)
    else:
        pixels.blurred[p] = pixels.radiance[p]


@wp.func
def _vignette(x: int, y: int, width: int, height: int, strength: float) -> float:
    dx = (float(x) + 0.5) / float(width) - 0.5
    dy = (float(y) + 0.5) / float(height) - 0.5
    r2 = (dx * dx + dy * dy) / (0.25 + 0.25 * float(height * height) / float(width * width))
    return 1.0 - strength * r2


@wp.func
def _luminance(c: wp.vec3) -> float:
    return 0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]


@wp.kernel
def meter_rows_kernel(width: int, height: int, vignetting: float, pixels: PixelBuffers):
    """One thread sums the log luminance of row ``y`` of the blurred, vignetted image into ``pixels.meter[y]``
    (float; luminance floored at 1e-4). Launch dims ``(H,)``; a fixed order per row, so the sum is reproducible."""
    y = wp.tid()
    total = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    for x in range(width):
        lum = _luminance(pixels.blurred[y * width + x]) * _vignette(x, y, width, height, vignetting)
        total += wp.log(wp.max(lum, 1.0e-4))
    pixels.meter[y] = total


@wp.kernel
def meter_image_kernel(width: int, height: int, key: float, pixels: PixelBuffers):
    """One thread turns the row sums into the exposure factor ``key / exp(mean log luminance)``, written to
    ``pixels.meter[H]``. Launch dims ``(1,)``; ``key`` includes the exposure change (``key * 2^ev``)."""
    total = float(0.0)  # noqa: UP018 - Warp: a variable mutated later is declared dynamic
    for y in range(height):
        total += pixels.meter[y]
    pixels.meter[height] = key / wp.exp(total / float(width * height))


@wp.func
def _filmic(x: float) -> float:
    """Narkowicz's fit of the ACES filmic curve, [0, inf) -> [0, 1]."""
    v = wp.max(x, 0.0)
    return wp.clamp(v * (2.51 * v + 0.03) / (v * (2.43 * v + 0.59) + 0.14), 0.0, 1.0)


@wp.func
def _encode_srgb(c: float) -> float:
    return wp.where(c <= 0.0031308, 12.92 * c, 1.055 * wp.pow(c, 1.0 / 2.4) - 0.055)


@wp.kernel
def develop_image_kernel(width: int, height: int, vignetting: float, shot: float, read: float, seed: int,
                         gains: wp.vec3, saturation: float, contrast: float, gamma: float, pixels: PixelBuffers):
    """One thread develops pixel ``(x, y)``: ``pixels.blurred`` (vec3, linear radiance) times the vignetting and
    the exposure factor ``pixels.meter[H]``, plus noise, white balance, saturation, contrast, the filmic curve, the
    sRGB encoding and the gamma, written as 8-bit sRGB to ``pixels.image`` (vec3ub).

    Launch dims ``(H, W)``. ``shot``, ``read``: noise levels; ``seed``: the noise's seed (one stream per pixel);
    ``gains``: white-balance gains; the other scalars as in :class:`ResponseDraws`.
    """
    y, x = wp.tid()
    p = y * width + x
    c = pixels.blurred[p] * (_vignette(x, y, width, height, vignetting) * pixels.meter[height])
    if shot > 0.0 or read > 0.0:
        r = wp.rand_init(seed, p)
        for ch in range(3):
            v = wp.max(c[ch], 0.0)
            c[ch] = v + shot * wp.sqrt(v) * wp.randn(r) + read * wp.randn(r)
    c = wp.cw_mul(c, gains)
    lum = _luminance(c)
    c = wp.vec3(lum, lum, lum) + saturation * (c - wp.vec3(lum, lum, lum))
    out = wp.vec3ub()
    for ch in range(3):
        v = 0.18 * wp.pow(wp.max(c[ch], 0.0) / 0.18, contrast)
        e = wp.pow(_encode_srgb(_filmic(v)), gamma)
        out[ch] = wp.uint8(int(wp.floor(wp.clamp(e, 0.0, 1.0) * 255.0 + 0.5)))
    pixels.image[p] = out


def develop(buffers: Buffers, draws: ResponseDraws, device: str) -> np.ndarray:
    """Run the camera response on ``buffers.pixels.radiance``: ``(H, W, 3)`` uint8 sRGB."""
    h, w, px = buffers.height, buffers.width, buffers.pixels
    mode = 0
    if draws.motion and draws.motion_px > 0.05:
        mode = 2
    elif not draws.motion and draws.defocus_px > 0.05:
        mode = 1
    direction = wp.vec2(math.cos(draws.motion_angle), math.sin(draws.motion_angle))
    wp.launch(blur_image_kernel, dim=(h, w), device=device,
              inputs=[w, h, mode, float(draws.defocus_px), 0.5 * float(draws.motion_px), direction, px])
    wp.launch(meter_rows_kernel, dim=h, device=device, inputs=[w, h, float(draws.vignetting), px])
    wp.launch(meter_image_kernel, dim=1, device=device, inputs=[w, h, float(draws.key * 2.0**draws.ev), px])
    gains = white_balance_gains(draws.temperature, draws.tint).astype(np.float32)
    wp.launch(develop_image_kernel, dim=(h, w), device=device,
              inputs=[w, h, float(draws.vignetting), float(draws.shot_noise), float(draws.read_noise),
                      int(draws.noise_seed), wp.vec3(*gains), float(draws.saturation), float(draws.contrast),
                      float(draws.gamma), px])
    # On the CPU device numpy() is a view of the buffer the next image overwrites.
    image = np.array(px.image.numpy(), dtype=np.uint8).reshape(h, w, 3)
    return jpeg(image, draws.jpeg_quality)


def jpeg(image: np.ndarray, quality: int) -> np.ndarray:
    """``(H, W, 3)`` uint8 through JPEG compression at ``quality`` (1-100; 0 returns it unchanged)."""
    if quality <= 0:
        return np.ascontiguousarray(image)
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(image).save(buf, format="JPEG", quality=int(quality))
    buf.seek(0)
    with Image.open(buf) as im:
        return np.asarray(im.convert("RGB"), dtype=np.uint8).copy()

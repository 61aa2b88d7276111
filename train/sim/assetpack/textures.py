"""Textures and images for the asset pack: downscaling, normal maps (from the source or derived), JPEG encoding.

A normal map is derived from the albedo when the source has none: the luminance, high-passed (so that the
photo's lighting gradient does not become a slope) and scaled to the material's relief depth in metres
(:data:`.sources.RELIEF_M`), is the height field; its slopes, taken with wrap-around differences so the map
tiles like the texture, over the tile's metric pixel size give the normals. Encoding: tangent space, x along the
image's columns, y up the image, z out of the surface, stored as RGB ``(n + 1) / 2`` (OpenGL convention).
"""

from __future__ import annotations

import io

import numpy as np

from .manifest import AssetPackError


def decode_rgb(data: bytes, label: str) -> np.ndarray:
    """Image bytes as ``(H, W, 3)`` uint8 RGB (alpha dropped, palettes and greyscale expanded).

    Raises:
        AssetPackError: not a readable image.
    """
    from PIL import Image

    try:
        with Image.open(io.BytesIO(data)) as im:
            # Palette images may carry transparency; through RGBA, PIL drops it without a warning.
            return np.asarray((im.convert("RGBA") if im.mode == "P" else im).convert("RGB"), dtype=np.uint8)
    except (OSError, ValueError, SyntaxError) as e:
        raise AssetPackError(f"{label}: not a readable image ({type(e).__name__}: {e})") from None


def downscale(rgb: np.ndarray, max_side: int) -> np.ndarray:
    """``(H, W, 3)`` uint8 shrunk (Lanczos) so that its longer side is at most ``max_side``; never enlarged."""
    from PIL import Image

    h, w = rgb.shape[:2]
    s = max_side / max(h, w)
    if s >= 1:
        return rgb
    size = (max(1, round(w * s)), max(1, round(h * s)))
    return np.asarray(Image.fromarray(rgb).resize(size, Image.Resampling.LANCZOS), dtype=np.uint8)


def _blur_wrap(x: np.ndarray, sigma: float) -> np.ndarray:
    """Gaussian blur with wrap-around borders, through the FFT (the texture tiles)."""
    h, w = x.shape
    fy = np.fft.fftfreq(h)[:, None]
    fx = np.fft.rfftfreq(w)[None, :]
    g = np.exp(-2 * (np.pi * sigma) ** 2 * (fx**2 + fy**2))
    return np.fft.irfft2(np.fft.rfft2(x) * g, s=(h, w))


def derive_normal(albedo: np.ndarray, tile_width_m: float, relief_m: float) -> np.ndarray:
    """A tangent-space normal map from an albedo's luminance (see the module docstring).

    Args:
        albedo: ``(H, W, 3)`` uint8 sRGB.
        tile_width_m: metres the tile covers along its width.
        relief_m: the height range given to the luminance (metres).

    Returns:
        ``(H, W, 3)`` uint8, RGB-encoded unit normals.
    """
    lum = albedo.astype(np.float64) @ np.array([0.2126, 0.7152, 0.0722]) / 255.0
    h, w = lum.shape
    detail = lum - _blur_wrap(lum, max(h, w) / 16)
    detail = _blur_wrap(detail, 0.7)
    spread = np.percentile(detail, 98) - np.percentile(detail, 2)
    height = detail / max(spread, 1e-6) * relief_m
    px = tile_width_m / w
    dx = (np.roll(height, -1, axis=1) - np.roll(height, 1, axis=1)) / (2 * px)
    drow = (np.roll(height, -1, axis=0) - np.roll(height, 1, axis=0)) / (2 * px)
    # y points up the image (towards row 0), so the slope along +y is -d/drow and n_y = +d/drow.
    n = np.stack([-dx, drow, np.ones_like(dx)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.clip(np.round((n + 1) * 127.5), 0, 255).astype(np.uint8)


def normal_from_source(rgb: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """A source's RGB normal map resized to ``shape`` (H, W) and renormalised, as uint8 RGB."""
    from PIL import Image

    im = Image.fromarray(rgb).resize((shape[1], shape[0]), Image.Resampling.LANCZOS)
    n = np.asarray(im, dtype=np.float64) / 127.5 - 1.0
    n[..., 2] = np.maximum(n[..., 2], 1e-3)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.clip(np.round((n + 1) * 127.5), 0, 255).astype(np.uint8)


def jpeg_bytes(rgb: np.ndarray, quality: int) -> bytes:
    """``(H, W, 3)`` uint8 as baseline JPEG bytes (4:2:0, no metadata: the same pixels give the same bytes)."""
    from PIL import Image

    buf = io.BytesIO()
    Image.fromarray(rgb).save(buf, format="JPEG", quality=quality, optimize=True)
    return buf.getvalue()

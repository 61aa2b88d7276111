"""Texture layers on the device: every pack texture (albedo and normal map) and image a room uses, resampled to
one square size with its mip levels, in two growing arrays shared by all rooms of a process; and the device
functions that filter them.

Layout
    A layer of side ``S`` (``RaytraceConfig.texture_size``, a power of two) holds its mip levels ``l = 0 ..
    log2 S`` one after the other, level ``l`` of side ``s_l = S >> l`` starting at texel ``4 (S^2 - s_l^2) / 3``;
    a layer is ``(4 S^2 - 1) / 3`` texels. Texel ``(x, y)`` of level ``l`` of layer ``k`` is element ``k * stride
    + offset_l + y s_l + x`` of a ``vec4ub`` array, row 0 at the image's top. Albedo texels are sRGB (decoded
    through a 256-entry table before filtering); normal texels are tangent-space unit vectors stored as
    ``(n + 1) / 2`` (x right, y up the image, z out of the surface, the pack's convention).

Mip levels are box-filtered in linear light (albedo) or as vectors renormalised (normals) on the host. Layers
are added as rooms need them and never dropped (a pack's textures fit: a few hundred layers of 256^2 are about
90 KB each); the device arrays grow by doubling.

Filtering
    :func:`sample_albedo` and :func:`sample_normal` filter trilinearly: bilinear within the two mip levels around
    ``lod`` (repeating the tile, or clamping for images) and linear between them, with ``lod = log2`` of the
    texels one pixel's footprint covers, so that distant tiles do not alias.
"""

from __future__ import annotations

from collections.abc import Callable
from typing import Any

import numpy as np

from fruxel.kernels.wp.runtime import warp

wp = warp()
wp.set_module_options({"enable_backward": False})


def layer_stride(size: int) -> int:
    """Texels of one layer of side ``size`` with all its mip levels."""
    return (4 * size * size - 1) // 3


def _resize(channels: np.ndarray, size: int) -> np.ndarray:
    """``(h, w, c)`` float32 to ``(size, size, c)``: PIL's antialiased bilinear filter per channel."""
    from PIL import Image

    out = [np.asarray(Image.fromarray(np.ascontiguousarray(channels[..., c], dtype=np.float32), mode="F")
                      .resize((size, size), Image.BILINEAR)) for c in range(channels.shape[-1])]
    return np.stack(out, axis=-1)


def _mips(level0: np.ndarray) -> list[np.ndarray]:
    """The chain of 2x2 box-filtered levels of a ``(S, S, c)`` float array down to ``(1, 1, c)``."""
    out = [level0]
    while out[-1].shape[0] > 1:
        a = out[-1]
        out.append(0.25 * (a[0::2, 0::2] + a[1::2, 0::2] + a[0::2, 1::2] + a[1::2, 1::2]))
    return out


def albedo_texels(rgb: np.ndarray, size: int) -> np.ndarray:
    """An sRGB image as one layer: ``(H, W, 3)`` uint8 -> ``(layer_stride(size), 4)`` uint8 (sRGB, alpha 255)."""
    from .scene_arrays import srgb_to_linear

    lin = srgb_to_linear(np.asarray(rgb, dtype=np.float64) / 255.0).astype(np.float32)
    levels = []
    for level in _mips(_resize(lin, size)):
        c = np.clip(level.reshape(-1, 3), 0.0, 1.0)
        srgb = np.where(c <= 0.0031308, 12.92 * c, 1.055 * c ** (1 / 2.4) - 0.055)
        levels.append(np.concatenate([np.rint(srgb * 255.0), np.full((len(c), 1), 255.0)], axis=1))
    return np.concatenate(levels).astype(np.uint8)


def normal_texels(normal: np.ndarray, size: int) -> np.ndarray:
    """A normal map as one layer: ``(H, W, 3)`` float32 unit vectors -> ``(layer_stride(size), 4)`` uint8."""
    levels = []
    for level in _mips(_resize(np.asarray(normal, dtype=np.float32), size)):
        n = level.reshape(-1, 3)
        n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-6)
        levels.append(np.concatenate([np.rint((n + 1.0) * 127.5), np.full((len(n), 1), 255.0)], axis=1))
    return np.clip(np.concatenate(levels), 0, 255).astype(np.uint8)


class _GrowingLayers:
    """A device ``vec4ub`` array of layers that doubles its capacity when full."""

    def __init__(self, stride: int, device: str) -> None:
        self.stride, self.device, self.count = stride, device, 0
        self.array = wp.zeros(stride, dtype=wp.vec4ub, device=device)

    def add(self, texels: np.ndarray) -> int:
        capacity = self.array.shape[0] // self.stride
        if self.count == capacity:
            bigger = wp.zeros(2 * capacity * self.stride, dtype=wp.vec4ub, device=self.device)
            wp.copy(bigger, self.array, count=self.count * self.stride)
            self.array = bigger
        src = wp.array(np.ascontiguousarray(texels, dtype=np.uint8), dtype=wp.vec4ub, device=self.device)
        wp.copy(self.array, src, dest_offset=self.count * self.stride, count=self.stride)
        self.count += 1
        return self.count - 1


class TextureLayers:
    """The texture layers of one process on one device (module docstring), filled from an asset pack.

    Args:
        pack: an :class:`~fruxel.train.sim.assetpack.AssetPack`, or None when no scene names a pack asset.
        size: layer side, a power of two.
        device: Warp device.
    """

    def __init__(self, pack: Any, size: int, device: str) -> None:
        self.pack, self.size, self.device = pack, int(size), device
        self.levels = int(self.size).bit_length()
        """Mip levels per layer, ``log2 S + 1``."""
        stride = layer_stride(self.size)
        self._albedo = _GrowingLayers(stride, device)
        self._normal = _GrowingLayers(stride, device)
        self._index: dict[tuple[str, str], int] = {}
        self._aspect: dict[str, float] = {}
        self.srgb = wp.array(_srgb_table(), dtype=wp.float32, device=device)
        """``(256,)`` float32: the linear value of each sRGB byte."""

    @property
    def albedo(self) -> Any:
        """The ``vec4ub`` albedo (and image) layers."""
        return self._albedo.array

    @property
    def normal(self) -> Any:
        """The ``vec4ub`` normal-map layers."""
        return self._normal.array

    def layer(self, role: str, asset_id: str) -> int:
        """The layer of a pack asset, decoded and uploaded on first use: ``role`` ``"albedo"`` or ``"normal"`` of
        a texture, or ``"image"``.

        Raises:
            AssetPackError: no such asset in the pack, or an unreadable file.
        """
        key = (role, asset_id)
        if key not in self._index:
            if self.pack is None:
                raise RuntimeError("TextureLayers without a pack cannot load assets")
            if role == "image":
                self._index[key] = self._albedo.add(
                    self._texels(asset_id, "image", lambda: albedo_texels(self.pack.image(asset_id).pixels, self.size)))
            else:
                decoded: list[Any] = []

                def texture() -> Any:  # albedo and normal map decode together: once for both layers
                    if not decoded:
                        decoded.append(self.pack.texture(asset_id))
                    return decoded[0]

                self._index[("albedo", asset_id)] = self._albedo.add(
                    self._texels(asset_id, "albedo", lambda: albedo_texels(texture().albedo, self.size)))
                self._index[("normal", asset_id)] = self._normal.add(
                    self._texels(asset_id, "normal", lambda: normal_texels(texture().normal, self.size)))
                w, h = self.pack.entry(asset_id).size_m
                self._aspect[asset_id] = float(h / w) if w > 0 and h > 0 else 1.0
        return self._index[key]

    def _texels(self, asset_id: str, role: str, compute: Callable[[], np.ndarray]) -> np.ndarray:
        """One layer's texels, ``(layer_stride(size), 4)`` uint8: read from the machine's derived arrays, else
        ``compute()``-d from the pack's file of ``role`` and kept there (:mod:`..assetpack.derived`)."""
        from ..assetpack.derived import code_digest, derived_arrays

        name = f"{role}-{self.pack.entry(asset_id).sha256[role][:32]}-{self.size}-{code_digest(__name__)}"
        return derived_arrays().get(name, (layer_stride(self.size), 4), np.uint8, compute)

    def tile_aspect(self, texture_id: str) -> float:
        """A texture's tile height over its width (metres, from the pack's ``size_m``); its layers are loaded."""
        return self._aspect[texture_id]

    @property
    def layers(self) -> int:
        """Layers uploaded (albedo and images, normal maps)."""
        return self._albedo.count + self._normal.count


def _srgb_table() -> np.ndarray:
    from .scene_arrays import srgb_to_linear

    return srgb_to_linear(np.arange(256) / 255.0).astype(np.float32)


# ---------------------------------------------------------------------------------------------------- device
@wp.func
def _texel_index(layer: int, size: int, level: int, x: int, y: int, wrap: int) -> int:
    """Element of texel ``(x, y)`` (any integers: repeated or clamped into the level) of one layer's level."""
    s = size >> level
    xi = x
    yi = y
    if wrap != 0:
        xi = ((x % s) + s) % s
        yi = ((y % s) + s) % s
    else:
        xi = wp.clamp(x, 0, s - 1)
        yi = wp.clamp(y, 0, s - 1)
    return layer * ((4 * size * size - 1) // 3) + (4 * (size * size - s * s)) // 3 + yi * s + xi


@wp.func
def _level(texels: wp.array(dtype=wp.vec4ub), srgb: wp.array(dtype=wp.float32), layer: int, size: int, level: int,
           uv: wp.vec2, wrap: int, normal: int) -> wp.vec3:
    """Bilinear value of one mip level at ``uv`` (u right, v up, one tile per unit): the linear-light colour of
    sRGB texels, or with ``normal`` set the tangent-space normal (not renormalised) of ``(n + 1) / 2`` texels."""
    s = float(size >> level)
    fx = uv[0] * s - 0.5
    fy = (1.0 - uv[1]) * s - 0.5
    x0 = int(wp.floor(fx))
    y0 = int(wp.floor(fy))
    ax = fx - float(x0)
    ay = fy - float(y0)
    out = wp.vec3(0.0, 0.0, 0.0)
    for dy in range(2):
        for dx in range(2):
            t = texels[_texel_index(layer, size, level, x0 + dx, y0 + dy, wrap)]
            w = wp.where(dx == 1, ax, 1.0 - ax) * wp.where(dy == 1, ay, 1.0 - ay)
            if normal != 0:
                out += w * (wp.vec3(float(t[0]), float(t[1]), float(t[2])) / 127.5 - wp.vec3(1.0, 1.0, 1.0))
            else:
                out += w * wp.vec3(srgb[int(t[0])], srgb[int(t[1])], srgb[int(t[2])])
    return out


@wp.func
def sample_albedo(texels: wp.array(dtype=wp.vec4ub), srgb: wp.array(dtype=wp.float32), layer: int, size: int,
                  levels: int, uv: wp.vec2, lod: float, wrap: int) -> wp.vec3:
    """Trilinear linear-light colour of a layer at ``uv`` and level of detail ``lod`` (0 = full size); ``wrap``
    1 repeats the tile, 0 clamps to the edge (images)."""
    top = float(levels - 1)
    level = wp.clamp(lod, 0.0, top)
    l0 = int(wp.floor(level))
    l1 = wp.min(l0 + 1, levels - 1)
    a = level - float(l0)
    c0 = _level(texels, srgb, layer, size, l0, uv, wrap, 0)
    if a <= 0.0:
        return c0
    return (1.0 - a) * c0 + a * _level(texels, srgb, layer, size, l1, uv, wrap, 0)


@wp.func
def sample_normal(texels: wp.array(dtype=wp.vec4ub), srgb: wp.array(dtype=wp.float32), layer: int, size: int,
                  levels: int, uv: wp.vec2, lod: float) -> wp.vec3:
    """Trilinear unit tangent-space normal of a layer at ``uv`` and ``lod`` (tile repeated; ``srgb`` unused)."""
    top = float(levels - 1)
    level = wp.clamp(lod, 0.0, top)
    l0 = int(wp.floor(level))
    l1 = wp.min(l0 + 1, levels - 1)
    a = level - float(l0)
    n = _level(texels, srgb, layer, size, l0, uv, 1, 1)
    if a > 0.0:
        n = (1.0 - a) * n + a * _level(texels, srgb, layer, size, l1, uv, 1, 1)
    length = wp.length(n)
    if length < 1.0e-6:
        return wp.vec3(0.0, 0.0, 1.0)
    return n / length

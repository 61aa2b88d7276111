"""Image and video files of rendered frames, written atomically, in the format their name's suffix says.

Images (:data:`IMAGE_FORMATS`): PNG, JPEG, WebP, TIFF and BMP through Pillow. Videos (:data:`VIDEO_FORMATS`): a
looping GIF (Pillow) or an H.264 MP4 (imageio with ``imageio-ffmpeg``). Every file is written to a temporary
file beside it and moved into place when complete (:func:`fruxel.io.atomic_path`), so a reader never sees part
of one and a failure leaves any earlier file as it was.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Callable, Iterable, Sequence
from pathlib import Path
from typing import Any

import numpy as np

from fruxel.io import atomic_path

from . import RenderError

IMAGE_FORMATS = {".png": "PNG", ".jpg": "JPEG", ".jpeg": "JPEG", ".webp": "WEBP", ".tif": "TIFF", ".tiff": "TIFF",
                 ".bmp": "BMP"}
"""Image file suffixes (lower case) and the Pillow format each is written in."""
VIDEO_FORMATS = (".gif", ".mp4")
"""Video file suffixes (lower case)."""


def image_format(path: str | Path) -> str:
    """The Pillow format of an image file name (:data:`IMAGE_FORMATS`).

    Raises:
        RenderError: a suffix that is no image format.
    """
    fmt = IMAGE_FORMATS.get(Path(path).suffix.lower())
    if fmt is None:
        raise RenderError(f"{str(path)!r}: unknown image type {Path(path).suffix!r}; use one of "
                          f"{', '.join(sorted(IMAGE_FORMATS))}")
    return fmt


def save_image(file: str | Path, image: np.ndarray, fmt: str) -> None:
    """Write ``(h, w, 3)`` uint8 RGB to ``file`` (as it is, not atomically) in Pillow format ``fmt``."""
    from PIL import Image

    options = {"quality": 92} if fmt in ("JPEG", "WEBP") else {}
    Image.fromarray(np.ascontiguousarray(image)).save(file, format=fmt, **options)


def write_image(path: str | Path, image: np.ndarray) -> Path:
    """Write ``(h, w, 3)`` uint8 RGB to ``path`` atomically in the format of its suffix (:data:`IMAGE_FORMATS`).

    Args:
        path: the file; its folder must exist.
        image: the picture.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        RenderError: a suffix that is no image format.
        OSError: the file cannot be written.
    """
    path = Path(path)
    fmt = image_format(path)
    with atomic_path(path) as tmp:
        save_image(tmp, image, fmt)
    return path


def check_video_writer(path: str | Path) -> None:
    """Check that a video can be written to ``path`` before frames are rendered for it.

    Raises:
        RenderError: a suffix that is no video format, or MP4 without ``imageio-ffmpeg``.
    """
    suffix = Path(path).suffix.lower()
    if suffix not in VIDEO_FORMATS:
        raise RenderError(f"{str(path)!r}: unknown video type {suffix!r}; use .gif or .mp4")
    if suffix == ".mp4" and importlib.util.find_spec("imageio_ffmpeg") is None:
        raise RenderError("MP4 output needs imageio-ffmpeg (pip install imageio-ffmpeg); or write a .gif")


def save_video(file: str | Path, frames: Iterable[np.ndarray], fps: float, suffix: str,
               colours: Sequence[Sequence[int]] = (),
               progress: Callable[[Iterable[Any]], Iterable[Any]] | None = None) -> None:
    """Write frames (each ``(h, w, 3)`` uint8, one size) to ``file`` (as it is, not atomically) as a looping GIF or
    an MP4 by ``suffix`` (``file`` must end in it too: imageio picks its writer by the name).

    ``frames`` may be a generator: an MP4 is encoded as the frames come (memory holds one frame), a GIF once all
    have come. A GIF has one palette for all frames (:func:`gif_palette`) holding ``colours`` exactly (RGB uint8:
    the background, the class colours of flat faces and legend swatches). ``progress`` (e.g. a ``tqdm`` bar) wraps
    the frames as they are encoded: an MP4's as they come, a GIF's as each is mapped onto the palette.

    Raises:
        RenderError: no frames.
    """
    track = progress or (lambda it: it)
    if suffix.lower() == ".mp4":
        import imageio.v2 as imageio

        writer = None
        try:
            for f in track(frames):
                if writer is None:
                    writer = imageio.get_writer(file, format="FFMPEG", fps=fps, codec="libx264", macro_block_size=1)
                # libx264 with yuv420p needs even sizes; pad by one row / column where needed.
                h, w = f.shape[:2]
                writer.append_data(np.pad(f, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge"))
        finally:
            if writer is not None:
                writer.close()
        if writer is None:
            raise RenderError("no frames to write")
    else:
        from PIL import Image

        rgb = [np.ascontiguousarray(f[..., :3]) for f in frames]
        if not rgb:
            raise RenderError("no frames to write")
        palette = gif_palette(rgb, colours)
        ims = [Image.fromarray(f).quantize(palette=palette, dither=Image.Dither.FLOYDSTEINBERG) for f in track(rgb)]
        ims[0].save(file, format="GIF", save_all=True, append_images=ims[1:], duration=round(1000 / fps), loop=0)


GIF_PALETTE_FRAMES = 8
"""Frames (evenly spaced) that a GIF's one palette is made from."""


def gif_palette(frames: Sequence[np.ndarray], colours: Sequence[Sequence[int]] = ()) -> Any:
    """One 256-colour palette for all frames of a GIF (a ``"P"`` PIL image to quantise them with): ``colours``
    exactly, then the median-cut colours of up to :data:`GIF_PALETTE_FRAMES` evenly spaced frames. With a palette
    per frame, a class colour (a legend swatch, a wall) would change from frame to frame, and a colour covering
    few pixels (a swatch) would be merged away.

    Args:
        frames: ``(h, w, 3)`` uint8 RGB frames.
        colours: RGB colours to keep exactly (at most 128; repeats are dropped).
    """
    from PIL import Image

    keep = list(dict.fromkeys(tuple(int(v) for v in c[:3]) for c in colours))[:128]
    pick = np.unique(np.linspace(0, len(frames) - 1, min(len(frames), GIF_PALETTE_FRAMES)).round().astype(int))
    h = min(f.shape[0] for f in frames)
    mosaic = np.concatenate([frames[i][:h] for i in pick], axis=1)
    rest = Image.fromarray(mosaic).quantize(256 - len(keep), method=Image.Quantize.MEDIANCUT,
                                            dither=Image.Dither.NONE)
    others = np.asarray(rest.getpalette()[:3 * (256 - len(keep))], dtype=np.int32).reshape(-1, 3)
    if keep:
        # Pillow finds a pixel's palette entry among colours equal in their top 5 bits; a median-cut colour that
        # close to a kept one could take its pixels (white drawn as (253, 253, 253)).
        near = np.all(np.abs(others[:, None, :] - np.asarray(keep)[None]) < 8, axis=-1).any(axis=1)
        others = others[~near]
    values = [v for c in keep for v in c] + others.reshape(-1).tolist()
    palette = Image.new("P", (1, 1))
    palette.putpalette(values + [0] * (768 - len(values)))
    return palette


def write_video(path: str | Path, frames: Sequence[np.ndarray], fps: int) -> Path:
    """Write frames (each ``(h, w, 3)`` uint8) as a looping GIF or an MP4, atomically, by ``path``'s suffix.

    Returns:
        ``path`` as a :class:`~pathlib.Path`.

    Raises:
        RenderError: see :func:`check_video_writer`.
        OSError: the file cannot be written.
    """
    path = Path(path)
    check_video_writer(path)
    with atomic_path(path) as tmp:
        save_video(tmp, frames, fps, path.suffix)
    return path

"""Image and video files of rendered frames, written atomically, in the format their name's suffix says.

Images (:data:`IMAGE_FORMATS`): PNG, JPEG, WebP, TIFF and BMP through Pillow. Videos (:data:`VIDEO_FORMATS`): a
looping GIF (Pillow) or an H.264 MP4 (imageio with ``imageio-ffmpeg``). Every file is written to a temporary
file beside it and moved into place when complete (:func:`fruxel.io.atomic_path`), so a reader never sees part
of one and a failure leaves any earlier file as it was.
"""

from __future__ import annotations

import importlib.util
from collections.abc import Sequence
from pathlib import Path

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


def save_video(file: str | Path, frames: Sequence[np.ndarray], fps: int, suffix: str) -> None:
    """Write frames (each ``(h, w, 3)`` uint8) to ``file`` (as it is, not atomically) as a looping GIF or an MP4
    by ``suffix`` (``file`` must end in it too: imageio picks its writer by the name)."""
    if suffix.lower() == ".mp4":
        import imageio.v2 as imageio

        # libx264 with yuv420p needs even sizes; pad by one row / column where needed.
        h, w = frames[0].shape[:2]
        padded = [np.pad(f, ((0, h % 2), (0, w % 2), (0, 0)), mode="edge") for f in frames]
        imageio.mimwrite(file, padded, format="FFMPEG", fps=fps, codec="libx264", macro_block_size=1)
    else:
        from PIL import Image

        ims = [Image.fromarray(f) for f in frames]
        ims[0].save(file, format="GIF", save_all=True, append_images=ims[1:], duration=round(1000 / fps), loop=0)


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

"""Your own data: a folder of labelled images that ``fruxel-train --data DIR`` fine-tunes on (docs/your-data.md).

Layout
    ``DIR/dataset.json`` describes the set; every sample is three files sharing a name (a *stem*, a path relative to
    ``DIR`` with ``/`` separators, e.g. ``train/000001``)::

        {"format": "fruxel-folder", "version": 1,
         "grid": {"width": 64, "height": 64, "depth": 64, "z_near": 0.5, "z_far": 8.0, "hfov": 60.0},
         "classes": ["empty", "wall", "floor", ...],
         "splits": {"train": ["train/000001", ...], "test": "test"}}

    * ``STEM.png`` or ``STEM.jpg`` / ``.jpeg``: the photo, any size (:func:`fruxel.train.predict.load_image`);
    * ``STEM.json``: its camera (:func:`parse_camera`): ``intrinsics`` ``[fx, fy, cx, cy]`` in pixels of that
      photo (required); at most one of ``pose`` (4x4 camera-to-world, OpenCV axes, world z up), ``gravity`` (the
      direction of gravity in the camera frame) or ``pitch`` and ``roll`` (degrees); ``height`` above the floor
      (metres), optional;
    * ``STEM.npy``: the labels, ``(D, H, W)`` uint8 indexed ``[k, j, i]`` in the grid's frame (0 = empty; label ``c``
      is ``classes[c]``), read without pickle.

    A split is a list of stems, or the name of a subfolder: all the samples in it, by name. ``grid`` and
    ``classes`` must be the model's (a folder is labelled for one grid); the photos are framed onto the grid's view
    as the commands frame a photo (:func:`frame_photo`).

Camera of a batch
    A folder sample gives the same ``camera`` keys as a simulator sample (:data:`fruxel.train.sim.cameras.CAMERA_KEYS`),
    with what the folder does not say marked unknown by NaN: ``pose`` (all 16 entries) without a pose, ``gravity``,
    ``pitch`` and ``roll`` without a pose, gravity or pitch and roll, ``height`` without a height. The height is
    never computed from a pose (the world's origin need not lie on the floor).

Checking
    :func:`check_folder` reads ``dataset.json``, every camera file and the headers of every photo and label file
    before any training: a missing, corrupt or foreign file, labels of another shape or class table than the model's,
    or intrinsics that make no sense are one :class:`FolderError` naming the file. Reading a sample later
    (:meth:`FolderSet.sample`) checks the label values and decodes the photo.

numpy and Pillow, but for decoding a sample's photo, which :func:`fruxel.train.predict.load_image` does as for every
command (EXIF orientation, 16-bit grey).
"""

from __future__ import annotations

import json
import math
import os
from dataclasses import dataclass
from typing import Any

import numpy as np

from fruxel.errors import FruxelError
from fruxel.grid import FruxelGrid

DATASET_JSON = "dataset.json"
"""The file that makes a folder a fruxel data folder."""
FORMAT = "fruxel-folder"
"""The ``format`` value of :data:`DATASET_JSON`."""
VERSION = 1
"""The folder format's version."""
IMAGE_SUFFIXES = (".png", ".jpg", ".jpeg")
"""Photo file suffixes, in the order they are looked for."""
HFOV_RANGE = (1.0, 170.0)
"""Horizontal fields of view (degrees) the intrinsics may give; anything outside is a mistake (a focal length in
millimetres, say)."""
CAMERA_FIELDS = ("intrinsics", "pose", "gravity", "pitch", "roll", "height")
"""The keys a camera file may hold."""


class FolderError(FruxelError, ValueError):
    """A data folder that cannot be used; the message is one line naming the file and the problem."""


@dataclass(frozen=True)
class FolderCamera:
    """One sample's camera, as its file gives it, checked (unknown values are NaN)."""

    intrinsics: tuple[float, float, float, float]
    """``(fx, fy, cx, cy)`` in pixels of the photo as stored (conventions section 3)."""
    image_size: tuple[int, int]
    """``(width, height)`` of the photo, pixels (after its EXIF orientation)."""
    pose: np.ndarray
    """``(4, 4)`` float64 camera-to-world, OpenCV axes, world z up; all NaN when not given."""
    gravity: np.ndarray
    """``(3,)`` float64 unit direction of gravity in the camera frame (x right, y down, z ahead); NaN when unknown."""
    height: float
    """Optical centre above the floor, metres; NaN when unknown."""

    def angles(self) -> tuple[float, float]:
        """``(pitch, roll)`` in degrees of :attr:`gravity` (:mod:`fruxel.train.sim.cameras`: ``p = asin(g_z)``,
        ``r = atan2(g_x, g_y)``); NaN when it is unknown."""
        g = self.gravity
        if not np.all(np.isfinite(g)):
            return math.nan, math.nan
        return math.degrees(math.asin(max(-1.0, min(1.0, float(g[2]))))), math.degrees(math.atan2(g[0], g[1]))


@dataclass(frozen=True)
class FolderSample:
    """One sample read from a folder: what :class:`fruxel.train.samples.BlockStream` takes from a sample."""

    index: int
    """Index in its split."""
    image: np.ndarray
    """``(h, w, 3)`` uint8 RGB: the photo framed onto the grid's view at the model's image size."""
    labels: np.ndarray
    """``(D, H, W)`` uint8 labels, grid frame, indexed ``[k, j, i]``."""
    camera: dict[str, np.ndarray]
    """The camera keyed by :data:`fruxel.train.sim.cameras.CAMERA_KEYS` (module docstring)."""

    def camera_arrays(self) -> dict[str, np.ndarray]:
        """:attr:`camera` (the name a simulator sample gives it)."""
        return self.camera


# ---------------------------------------------------------------------------------------------------- reading JSON
def _read_json(path: str) -> Any:
    """The JSON value in ``path``; FolderError naming it when it is missing or not JSON."""
    if not os.path.isfile(path):
        raise FolderError(f"{path}: {'no such file' if not os.path.exists(path) else 'not a regular file'}")
    try:
        with open(path, encoding="utf-8") as f:
            return json.load(f)
    except (UnicodeDecodeError, ValueError) as e:
        raise FolderError(f"{path}: not valid JSON ({e})") from None
    except OSError as e:
        raise FolderError(f"{path}: cannot be read ({e.strerror or e})") from None


def _numbers(value: Any, n: int, what: str, path: str) -> list[float]:
    """``n`` finite numbers (not booleans) from a JSON list, else FolderError naming ``path`` and ``what``."""
    if not isinstance(value, list) or len(value) != n or not all(
            isinstance(v, (int, float)) and not isinstance(v, bool) and math.isfinite(v) for v in value):
        raise FolderError(f"{path}: {what} must be a list of {n} finite numbers, got {value!r}")
    return [float(v) for v in value]


def _number(d: dict[str, Any], key: str, path: str) -> float:
    return _numbers([d[key]], 1, key, path)[0]


def parse_camera(d: Any, size: tuple[int, int], path: str) -> FolderCamera:
    """A camera file's content, checked against its photo.

    Args:
        d: the parsed JSON (module docstring).
        size: ``(width, height)`` of the photo, pixels.
        path: the camera file, for messages.

    Raises:
        FolderError: unknown or missing keys, values that are not finite numbers, a focal length <= 0 or one giving
            a field of view outside :data:`HFOV_RANGE`, ``fx / fy`` outside [0.5, 2], a principal point outside the
            photo, a pose that is not a rigid transform, a zero gravity vector, pitch without roll (or the other way
            round), more than one of pose / gravity / pitch and roll, a height not in (0, 100] m.
    """
    if not isinstance(d, dict):
        raise FolderError(f"{path}: a camera file must hold a JSON object, got {type(d).__name__}")
    extra = sorted(str(k) for k in d if k not in CAMERA_FIELDS)
    if extra or "intrinsics" not in d:
        raise FolderError(f"{path}: camera keys are {', '.join(CAMERA_FIELDS)} (intrinsics required); "
                          + (f"unexpected {extra}" if extra else "no intrinsics"))
    fx, fy, cx, cy = _numbers(d["intrinsics"], 4, "intrinsics [fx, fy, cx, cy]", path)
    w, h = size
    if min(fx, fy) <= 0 or not 0.5 <= fx / fy <= 2.0 or not (0 < cx < w and 0 < cy < h):
        raise FolderError(f"{path}: intrinsics {[fx, fy, cx, cy]} make no sense for a {w}x{h} photo (need fx, fy > 0 "
                          "pixels of similar size and the principal point cx, cy inside the photo)")
    hfov = math.degrees(2.0 * math.atan(w / (2.0 * fx)))
    if not HFOV_RANGE[0] <= hfov <= HFOV_RANGE[1]:
        raise FolderError(f"{path}: fx {fx:g} pixels gives a {w}-pixel-wide photo a field of view of {hfov:.3g} "
                          f"degrees, outside {HFOV_RANGE[0]:g} to {HFOV_RANGE[1]:g} (fx is in pixels, not mm)")
    given = [k for k in ("pose", "gravity") if k in d] + (["pitch and roll"] if "pitch" in d or "roll" in d else [])
    if len(given) > 1:
        raise FolderError(f"{path}: give at most one of pose, gravity, pitch and roll; got {' and '.join(given)}")
    pose = np.full((4, 4), np.nan)
    gravity = np.full(3, np.nan)
    if "pose" in d:
        pose = _rigid(d["pose"], path)
        gravity = -pose[2, :3]  # world -z in camera axes: the rows of R are the world axes seen from the camera
    elif "gravity" in d:
        g = np.array(_numbers(d["gravity"], 3, "gravity", path))
        if np.linalg.norm(g) < 1e-6:
            raise FolderError(f"{path}: gravity {g.tolist()} has no direction")
        gravity = g / np.linalg.norm(g)
    elif "pitch" in d or "roll" in d:
        if "pitch" not in d or "roll" not in d:
            raise FolderError(f"{path}: give pitch and roll together (degrees; roll 0 for a level camera)")
        p, r = math.radians(_number(d, "pitch", path)), math.radians(_number(d, "roll", path))
        if not (abs(p) <= math.pi / 2 and abs(r) <= math.pi):
            raise FolderError(f"{path}: pitch must be within +-90 and roll within +-180 degrees")
        gravity = np.array([math.sin(r) * math.cos(p), math.cos(r) * math.cos(p), math.sin(p)])
    height = math.nan
    if "height" in d:
        height = _number(d, "height", path)
        if not 0.0 < height <= 100.0:
            raise FolderError(f"{path}: height must be in (0, 100] metres above the floor, got {height:g}")
    return FolderCamera((fx, fy, cx, cy), (int(w), int(h)), pose, gravity, height)


def _rigid(value: Any, path: str) -> np.ndarray:
    """A 4x4 camera-to-world rigid transform from JSON rows, checked."""
    if not isinstance(value, list) or len(value) != 4:
        raise FolderError(f"{path}: pose must be 4 rows of 4 numbers (camera-to-world), got {value!r}")
    m = np.array([_numbers(row, 4, "each pose row", path) for row in value])
    r = m[:3, :3]
    if not (np.allclose(m[3], (0, 0, 0, 1)) and np.allclose(r.T @ r, np.eye(3), atol=1e-4)
            and np.linalg.det(r) > 0):
        raise FolderError(f"{path}: pose is not a rigid transform (rotation and translation, last row 0 0 0 1)")
    return m


# ---------------------------------------------------------------------------------------------------- headers
def labels_header(path: str) -> tuple[tuple[int, ...], np.dtype]:
    """``(shape, dtype)`` of a ``.npy`` file from its header, without reading its data.

    Raises:
        FolderError: missing, not a ``.npy`` file, an object array, Fortran order (labels are ``[k, j, i]``
            C-ordered), or data shorter than the header says.
    """
    if not os.path.isfile(path):
        raise FolderError(f"{path}: no such file (the sample's labels)")
    try:
        with open(path, "rb") as f:
            version = np.lib.format.read_magic(f)
            fmt = np.lib.format
            read = {(1, 0): fmt.read_array_header_1_0, (2, 0): fmt.read_array_header_2_0}.get(version)
            if read is None:
                raise ValueError(f"format version {version} is not 1.0 or 2.0")
            shape, fortran, dtype = read(f)
            start = f.tell()
    except (ValueError, OSError, EOFError) as e:
        raise FolderError(f"{path}: not a .npy file ({e})") from None
    if dtype.hasobject or fortran:
        what = "objects" if dtype.hasobject else "Fortran-ordered"
        raise FolderError(f"{path}: labels must be a C-ordered integer array, not {what}")
    if os.path.getsize(path) - start < int(np.prod(shape)) * dtype.itemsize:
        raise FolderError(f"{path}: truncated file (the header says {shape} {dtype})")
    return tuple(shape), dtype


def image_size(path: str) -> tuple[int, int]:
    """``(width, height)`` of a photo after its EXIF orientation, from its header.

    Raises:
        FolderError: missing or not an image Pillow reads.
    """
    from PIL import Image, UnidentifiedImageError

    try:
        with Image.open(path) as im:
            w, h = im.size
            orientation = im.getexif().get(0x0112, 1)
    except (UnidentifiedImageError, OSError, ValueError, Image.DecompressionBombError) as e:
        raise FolderError(f"{path}: not a readable image ({type(e).__name__}: {e})") from None
    # EXIF orientations 5 to 8 turn the photo a quarter: load_image gives it upright, rows and columns swapped.
    return (h, w) if orientation in (5, 6, 7, 8) else (w, h)


# ---------------------------------------------------------------------------------------------------- framing
def centred(img: np.ndarray, intrinsics: tuple[float, float, float, float]) -> tuple[np.ndarray, float]:
    """A photo with its principal point brought to the middle and its pixels made square, the photo
    :func:`fruxel.train.framing.frame_image` expects.

    The photo is cropped to the widest window centred on ``(cx, cy)`` (whole pixels; the principal point ends up
    within half a pixel of the middle), then, when ``fx`` and ``fy`` differ, its rows are resized by ``fx / fy``.
    A photo whose principal point is already in the middle with ``fx == fy`` (every simulator camera) is returned as
    it is.

    Args:
        img: ``(h, w, 3)`` uint8 RGB.
        intrinsics: ``(fx, fy, cx, cy)`` in its pixels (checked by :func:`parse_camera`).

    Returns:
        ``(photo (h', w', 3) uint8, hfov)``: the photo and its horizontal field of view in degrees,
        ``2 atan(w' / (2 fx))``.
    """
    from PIL import Image

    fx, fy, cx, cy = intrinsics
    h, w = img.shape[:2]
    x0, x1 = round(cx - min(cx, w - cx)), round(cx + min(cx, w - cx))
    y0, y1 = round(cy - min(cy, h - cy)), round(cy + min(cy, h - cy))
    out = img[y0:max(y1, y0 + 1), x0:max(x1, x0 + 1)]
    if abs(fx / fy - 1.0) > 1e-6:
        rows = max(1, round(out.shape[0] * fx / fy))
        out = np.asarray(Image.fromarray(np.ascontiguousarray(out)).resize((out.shape[1], rows), Image.BILINEAR))
    return out, math.degrees(2.0 * math.atan(out.shape[1] / (2.0 * fx)))


def frame_photo(img: np.ndarray, intrinsics: tuple[float, float, float, float], grid: FruxelGrid,
                size: tuple[int, int]) -> tuple[np.ndarray, np.ndarray, float]:
    """A photo of known intrinsics framed onto a grid's view, as the commands frame a photo of known field of view.

    Args:
        img: ``(h, w, 3)`` uint8 RGB.
        intrinsics: ``(fx, fy, cx, cy)`` in its pixels.
        grid: the grid.
        size: ``(height, width)`` of the result, the model's image size.

    Returns:
        ``(image (height, width, 3) uint8, coverage (H, W) bool in the grid frame, hfov in degrees)``
        (:func:`centred`, :func:`fruxel.train.framing.frame_image`, :func:`~fruxel.train.framing.frame_coverage`).
    """
    from .framing import frame_coverage, frame_image

    photo, hfov = centred(img, intrinsics)
    return frame_image(photo, grid, size, hfov=hfov), frame_coverage(photo.shape, grid, hfov=hfov), hfov


# ---------------------------------------------------------------------------------------------------- the set
@dataclass(frozen=True)
class FolderSet:
    """A data folder, its ``dataset.json`` read and checked (:func:`read_folder`); picklable, for the DataLoader's
    workers."""

    root: str
    """The folder."""
    grid: FruxelGrid
    """The grid its labels are of."""
    classes: tuple[str, ...]
    """Class names in label order."""
    splits: dict[str, tuple[str, ...]]
    """Per split, its samples' stems, in order (sample ``i`` of a split is stem ``i``)."""

    def path(self, stem: str, suffix: str) -> str:
        """The file of ``stem`` with ``suffix`` (``".json"``, ``".npy"``)."""
        return os.path.join(self.root, *stem.split("/")) + suffix

    def image_path(self, stem: str) -> str:
        """The photo of ``stem``: the first of its :data:`IMAGE_SUFFIXES` files that exists.

        Raises:
            FolderError: none exists.
        """
        for suffix in IMAGE_SUFFIXES + tuple(s.upper() for s in IMAGE_SUFFIXES):
            if os.path.isfile(self.path(stem, suffix)):
                return self.path(stem, suffix)
        raise FolderError(f"{self.path(stem, '.png')}: no such file (the sample's photo: "
                          f"{' or '.join(IMAGE_SUFFIXES)})")

    def camera(self, stem: str) -> FolderCamera:
        """The checked camera of ``stem`` (:func:`parse_camera`), with its photo's size from the photo's header.

        Raises:
            FolderError: see :func:`parse_camera`, :func:`image_size`.
        """
        path = self.path(stem, ".json")
        return parse_camera(_read_json(path), image_size(self.image_path(stem)), path)

    def check_sample(self, stem: str) -> None:
        """Check the files of ``stem`` without decoding them: the camera against its photo's size, the labels'
        header against the grid.

        Raises:
            FolderError: naming the file.
        """
        self.camera(stem)
        path = self.path(stem, ".npy")
        shape, dtype = labels_header(path)
        if shape != self.grid.shape or dtype.kind not in "iu":
            raise FolderError(f"{path}: labels are {dtype} {shape}; the grid's are integer (D, H, W) = "
                              f"{self.grid.shape} (uint8, indexed [k, j, i])")

    def sample(self, split: str, index: int, size: tuple[int, int]) -> FolderSample:
        """Sample ``index`` of ``split``: its photo framed onto the grid's view at ``size`` (``(height, width)``),
        its labels and camera (module docstring).

        Raises:
            FolderError: a file that changed since it was checked, or labels outside the class table.
        """
        from .predict import ImageError, load_image

        stem = self.splits[split][index]
        cam = self.camera(stem)
        try:
            img = load_image(self.image_path(stem))
        except ImageError as e:
            raise FolderError(str(e)) from None
        if (img.shape[1], img.shape[0]) != cam.image_size:
            raise FolderError(f"{self.image_path(stem)}: the photo changed while training read it")
        image, coverage, hfov = frame_photo(img, cam.intrinsics, self.grid, size)
        labels = self._labels(stem)
        pitch, roll = cam.angles()
        camera = {"intrinsics": np.array(cam.intrinsics, dtype=np.float64),
                  "image_size": np.array(cam.image_size, dtype=np.int64), "pose": cam.pose.astype(np.float64),
                  "height": np.float64(cam.height), "gravity": cam.gravity.astype(np.float64),
                  "pitch": np.float64(pitch), "roll": np.float64(roll), "hfov": np.float64(hfov),
                  "coverage": coverage}
        return FolderSample(index, image, labels, camera)

    def _labels(self, stem: str) -> np.ndarray:
        """``(D, H, W)`` uint8 labels of ``stem``, read without pickle and checked against the grid and classes."""
        path = self.path(stem, ".npy")
        try:
            labels = np.load(path, allow_pickle=False)
        except (ValueError, OSError, EOFError) as e:
            raise FolderError(f"{path}: not a .npy file of labels ({e})") from None
        if labels.shape != self.grid.shape or labels.dtype.kind not in "iu":
            raise FolderError(f"{path}: labels are {labels.dtype} {labels.shape}; the grid's are (D, H, W) = "
                              f"{self.grid.shape} uint8")
        if labels.size and (labels.min() < 0 or labels.max() >= len(self.classes)):
            raise FolderError(f"{path}: labels {labels.min()} to {labels.max()} lie outside the {len(self.classes)} "
                              f"classes of {DATASET_JSON} (0 to {len(self.classes) - 1})")
        return np.ascontiguousarray(labels, dtype=np.uint8)


def grid_words(g: FruxelGrid) -> str:
    """A grid in words, e.g. ``"64x64x64 z 0.5..8 m hfov 60"``."""
    return f"{g.width}x{g.height}x{g.depth} z {g.z_near:g}..{g.z_far:g} m hfov {g.hfov:g}"


def is_folder_set(root: str | os.PathLike[str]) -> bool:
    """Whether ``root`` is a data folder of this format (it holds :data:`DATASET_JSON`)."""
    return os.path.isfile(os.path.join(os.fsdecode(root), DATASET_JSON))


def dataset_json(grid: FruxelGrid, classes: Any, splits: dict[str, list[str]]) -> dict[str, Any]:
    """The content of a :data:`DATASET_JSON` (module docstring).

    Args:
        grid: the labels' grid.
        classes: class names in label order (``"empty"`` first).
        splits: per split, its stems (or a subfolder's name).
    """
    return {"format": FORMAT, "version": VERSION, "grid": grid.to_dict(), "classes": list(classes),
            "splits": splits}


def read_folder(root: str | os.PathLike[str]) -> FolderSet:
    """A data folder's ``dataset.json``, read and checked (the samples are not: :func:`check_folder`).

    Raises:
        FolderError: no such folder or file, not JSON, another format or a later version, a bad grid, class table or
            split (an empty one, a stem leaving the folder, a subfolder that does not exist).
    """
    from fruxel.classes import ClassTable

    root = os.fsdecode(root)
    path = os.path.join(root, DATASET_JSON)
    if not os.path.isdir(root):
        raise FolderError(f"{root}: {'no such folder' if not os.path.exists(root) else 'not a folder'}")
    d = _read_json(path)
    keys = ("format", "version", "grid", "classes", "splits")
    if not isinstance(d, dict) or d.get("format") != FORMAT:
        raise FolderError(f"{path}: not a fruxel data folder description (needs \"format\": \"{FORMAT}\")")
    if sorted(d) != sorted(keys):
        raise FolderError(f"{path}: keys must be {', '.join(keys)}, got {', '.join(sorted(map(str, d)))}")
    if d["version"] != VERSION:
        raise FolderError(f"{path}: format version {d['version']!r}; this fruxel reads version {VERSION}")
    try:
        grid = FruxelGrid.from_dict(d["grid"])
        classes = ClassTable.from_names(d["classes"]).names if isinstance(d["classes"], list) else None
    except (ValueError, TypeError) as e:
        raise FolderError(f"{path}: {e}") from None
    if classes is None or tuple(classes) != tuple(d["classes"]):
        raise FolderError(f"{path}: classes must be a list of class names starting with \"empty\", got "
                          f"{d['classes']!r}")
    if not isinstance(d["splits"], dict) or not d["splits"]:
        raise FolderError(f"{path}: splits must be an object of split name -> list of samples or subfolder name")
    splits = {str(name): _split(root, path, str(name), v) for name, v in d["splits"].items()}
    return FolderSet(root, grid, tuple(classes), splits)


def _split(root: str, path: str, name: str, value: Any) -> tuple[str, ...]:
    """The stems of one split: a list of stems, or every sample (``.json`` file) of a subfolder, by name."""
    if isinstance(value, str):
        folder = os.path.join(root, *value.strip("/").split("/"))
        if not os.path.isdir(folder):
            raise FolderError(f"{folder}: no such folder (split {name!r} of {path})")
        value = [f"{value.strip('/')}/{f[:-5]}" for f in sorted(os.listdir(folder)) if f.endswith(".json")]
    if not isinstance(value, list) or not value or not all(isinstance(s, str) and s for s in value):
        raise FolderError(f"{path}: split {name!r} must be a non-empty list of sample names or a subfolder's name")
    for stem in value:
        parts = stem.split("/")
        if stem.startswith("/") or ".." in parts or "\\" in stem:
            raise FolderError(f"{path}: sample {stem!r} of split {name!r} is not a path inside the folder "
                              "(relative, with / separators, no ..)")
    return tuple(value)


def check_folder(root: str | os.PathLike[str], grid: FruxelGrid, classes: Any) -> FolderSet:
    """A data folder, checked whole against a model before any training: its ``dataset.json``, then every sample's
    camera and the headers of its photo and labels (:meth:`FolderSet.check_sample`).

    Args:
        root: the folder.
        grid: the model's grid.
        classes: the model's class names in label order.

    Raises:
        FolderError: see :func:`read_folder`; a grid or class table other than the model's; the first sample whose
            files are missing or wrong (naming the file).
    """
    fs = read_folder(root)
    path = os.path.join(fs.root, DATASET_JSON)
    if fs.grid != grid:
        raise FolderError(f"{path}: grid {grid_words(fs.grid)} is not the model's ({grid_words(grid)})")
    if fs.classes != tuple(classes):
        raise FolderError(f"{path}: classes {list(fs.classes)} are not the model's ({list(classes)})")
    for stems in fs.splits.values():
        for stem in stems:
            fs.check_sample(stem)
    return fs


def folder_digest(root: str | os.PathLike[str]) -> str:
    """A SHA-256 hex digest that changes when a data folder does: of its ``dataset.json`` and the name, size and
    modification time of every file under it (a cache key; the files' contents are not read)."""
    import hashlib

    root = os.fsdecode(root)
    digest = hashlib.sha256()
    with open(os.path.join(root, DATASET_JSON), "rb") as f:
        digest.update(f.read())
    for folder, _, files in sorted(os.walk(root)):
        for name in sorted(files):
            st = os.stat(os.path.join(folder, name))
            digest.update(f"{os.path.relpath(os.path.join(folder, name), root)}\0{st.st_size}\0{st.st_mtime_ns}\0"
                          .encode())
    return digest.hexdigest()

"""The live robot demo (the paper's case study): a robot drives through a room it was never trained on, and each
camera image goes through SSZ, the shell and the display while it drives.

Sources and timing
    The camera is the simulator's (:class:`fruxel.train.sim.sample.SampleMaker`): room ``scene`` of the *test*
    split, whose rooms come from seeds the training split never uses, driven along a random collision-free
    trajectory (:func:`fruxel.train.sim.robot.random_trajectory`, ``steps_per_frame`` simulation steps of 0.1 s
    per frame), without appearance augmentation (lighting does not flicker between frames). Rendering the camera
    image stands in for a real camera and is not timed; nor is the ground truth (``fruxelize`` at the camera's
    pose, and its panel), which a real robot would not have. A frame's end-to-end time runs from the camera image
    in hand to the displayed frame: the photo brought to the model's input (:func:`.predict.frame_image`), SSZ's
    logits, ``fruxel.kernels.shell`` of the logits, labels and greedy trapezoid mesh of what the shell keeps, the
    pyrender draw of the chase view, and the composed picture (:func:`fruxel.render.compare.compose`). Writing the
    video file is not timed (it stands in for the screen).

Chase view
    A camera riding behind and above the robot (:class:`ChaseView`), level with the floor, looking where the robot
    camera looks. It is fixed in the robot camera's frame, which is the grid frame, so it is one constant
    :class:`fruxel.Camera` for the whole drive, and every model shows from the same place relative to the robot.

Shell
    ``"own"``: what the robot camera sees of the prediction (the first occupied cell of each column, the VMS of
    the grid's own camera); ``"chase"``: what the chase camera sees of it (hidden cells dropped, so more of the
    room behind objects shows).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from fruxel.camera import Camera
from fruxel.classes import ClassTable
from fruxel.errors import ConfigError, FruxelError
from fruxel.grid import FruxelGrid

from .sim.robot import CameraMount

SHELLS = ("own", "chase")
"""Shell sources of the live demo (module docstring)."""
STAGES = ("input", "ssz", "shell", "mesh", "draw", "compose")
"""The timed stages of a frame, in order (module docstring): frame_image and upload, SSZ, shell, labels and
mesh, pyrender draw, composed picture."""


class LiveError(FruxelError, ValueError):
    """Impossible settings of the live demo."""


@dataclass(frozen=True)
class ChaseView:
    """Where the chase camera rides, relative to the robot camera, level with the floor (metres, degrees)."""

    back: float = 1.5
    """Distance behind the robot camera, along its heading."""
    above: float = 2.5
    """Height above the robot camera: high enough to look down onto the floor and over furniture."""
    ahead: float = 3.0
    """The point looked at lies this far ahead of the robot camera ..."""
    drop: float = 1.2
    """... and this far below it (below the floor at the default mount): the view then shows the frustum's apex,
    where the robot camera is, near its bottom edge."""
    hfov: float = 60.0
    """Horizontal field of view of the chase camera."""


def chase_camera(mount: CameraMount, width: int, height: int, view: ChaseView = ChaseView()) -> Camera:
    """The chase camera in the grid frame (the robot camera's: OpenCV axes, metres).

    Args:
        mount: the robot camera's mount (its tilt decides where the floor's up points in the grid frame).
        width, height: image size, pixels.
        view: where the chase camera rides.

    Returns:
        The camera; constant over a drive (module docstring).
    """
    t = math.radians(mount.tilt)
    # The robot camera looks down by the tilt: in its frame the world's up is (0, -cos t, -sin t) and the level
    # heading (0, -sin t, cos t).
    up = np.array([0.0, -math.cos(t), -math.sin(t)])
    ahead = np.array([0.0, -math.sin(t), math.cos(t)])
    eye = -view.back * ahead + view.above * up
    target = view.ahead * ahead - view.drop * up
    return Camera.look_at(eye, target, up=up, width=width, height=height, hfov=view.hfov)


def to_labels(volume: Any) -> np.ndarray:
    """``(D, H, W)`` uint8 numpy labels of a volume: labels ``(D, H, W)`` as they are, logits ``(1, C, D, H, W)``
    (numpy or torch, on any device) by their argmax (conventions section 2; on the GPU for CUDA tensors, so that only
    the labels cross to the host)."""
    if hasattr(volume, "detach"):
        import torch

        if volume.ndim == 5:
            volume = volume[0].argmax(dim=0)
        return volume.to(torch.uint8).cpu().numpy()
    from fruxel.model import labels_from_scores

    v = np.asarray(volume)
    return labels_from_scores(v[0], axis=0) if v.ndim == 5 else np.ascontiguousarray(v, dtype=np.uint8)


class ShellDisplay:
    """A volume -> its shell -> a greedy trapezoid mesh -> a pyrender image from one camera.

    Args:
        grid, classes: the volumes' grid and class table.
        camera: the viewing camera (grid frame).
        shell: ``"own"`` (the grid camera's shell) or ``"chase"`` (the viewing camera's).
        backend, device: kernel backend and Warp device of the shell (None: the best available, where the data
            are).
        frustum: draw the grid frustum's edges (they meet at the robot camera).
    """

    def __init__(self, grid: FruxelGrid, classes: ClassTable, camera: Camera, *, shell: str = "own",
                 backend: str | None = None, device: str | None = None, frustum: bool = True) -> None:
        if shell not in SHELLS:
            raise LiveError(f"shell must be one of {SHELLS}, got {shell!r}")
        self.grid, self.classes, self.camera = grid, classes, camera
        self.shell_cameras = grid.camera() if shell == "own" else camera
        self.backend, self.device = backend, device
        self.frustum = frustum
        self._view: Any = None
        self.mesh: Any = None
        """The last :class:`fruxel.mesh.TriMesh` made."""

    def mesh_of(self, volume: Any, times: dict[str, float]) -> Any:
        """The shell's greedy mesh of ``volume`` (labels ``(D, H, W)`` or logits ``(1, C, D, H, W)``, numpy or
        torch), adding the seconds of ``"shell"`` and ``"mesh"`` to ``times``."""
        from fruxel import kernels
        from fruxel.mesh import mesh_labels

        t0 = time.perf_counter()
        kept = kernels.shell(volume, self.grid, self.shell_cameras, backend=self.backend, device=self.device)
        _synchronise(kept)
        t1 = time.perf_counter()
        self.mesh = mesh_labels(to_labels(kept), self.grid, self.classes.palette(), mode="greedy")
        t2 = time.perf_counter()
        times["shell"] = times.get("shell", 0.0) + t1 - t0
        times["mesh"] = times.get("mesh", 0.0) + t2 - t1
        return self.mesh

    def draw(self, volume: Any, times: dict[str, float] | None = None) -> np.ndarray:
        """``(h, w, 3)`` uint8 image of ``volume``'s shell from the camera; stage seconds go to ``times``."""
        times = {} if times is None else times
        mesh = self.mesh_of(volume, times)
        t0 = time.perf_counter()
        if self._view is None:
            # Made on the first draw: the interactive viewer uses mesh_of alone, and its window's OpenGL platform
            # must be chosen before pyrender is first imported.
            from fruxel.render.scene import MeshStyle, MeshView

            self._view = MeshView(self.grid, MeshStyle(shading="lit", frustum=self.frustum))
            self._view.set_camera(self.camera)
        self._view.set_mesh(mesh)
        image = self._view.render()
        times["draw"] = times.get("draw", 0.0) + time.perf_counter() - t0
        return image


def _synchronise(x: Any) -> None:
    """Wait for a CUDA tensor's work (so that a stage's time is its own, not the next stage's)."""
    if getattr(x, "is_cuda", False):
        import torch

        torch.cuda.synchronize(x.device)


@dataclass(frozen=True)
class RobotDemoConfig:
    """What the live demo drives through and how it shows it (``fruxel-robot``'s options)."""

    frames: int = 100
    """Frames to drive (``steps_per_frame`` x 0.1 s of robot time each)."""
    scene: int = 7
    """Room of the simulator's test split (rooms the training never saw); room 7's drive passes a window, a table
    and a sofa."""
    seed: int = 0
    """Base seed of the simulator (0: the shipped model's training seed, whose test split holds out its rooms)."""
    size: int = 256
    """Height of each panel in pixels (the chase views are 4:3)."""
    steps_per_frame: int = 1
    """Robot simulation steps (0.1 s each) per frame."""
    shell: str = "own"
    """Shell of the prediction: ``own`` (what the robot camera sees) or ``chase`` (what the chase camera sees)."""
    backend: str | None = None
    """Kernel backend, ``warp`` or ``opencl``; unset: the best available."""
    device: str | None = None
    """Where SSZ and Warp run, ``cpu``, ``cuda`` or ``cuda:N``; unset: CUDA when present."""
    checkpoint: str | None = None
    """SSZ model file (shipped ``.safetensors`` or training checkpoint) or a shipped model's name (``ssz64``,
    ``ssz128``, ``ssz64-any``); unset: the robot's own model, ``ssz64`` (not the default for photos)."""
    threads: int | None = None
    """torch's CPU threads for SSZ; unset: half the cores (at least 1), leaving the rest to the simulator, OpenGL
    and the kernels. torch's own default, a thread per core, stalls whenever another process takes a core (its
    threads wait for each other; :func:`fruxel.train.predict.share_cpu`)."""
    chase: ChaseView = field(default_factory=ChaseView)
    """Where the chase camera rides."""
    compile: bool = False
    """On CUDA, compile SSZ's forward pass with ``torch.compile`` before the drive (it takes a while) and replay the
    compiled pass as a CUDA graph (:class:`fruxel.train.predict.Predictor`)."""
    flip_average: bool = True
    """Keep the model's ``flip_average`` rule (each camera image and its mirror image predicted and averaged) when
    its file has it on; off, SSZ runs once a frame, faster at the other rules' accuracy (BENCHMARKS.md)."""

    def __post_init__(self) -> None:
        for name in ("frames", "size", "steps_per_frame"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 1:
                raise ConfigError(f"{name} must be a positive integer, got {v!r}")
        if self.threads is not None and (isinstance(self.threads, bool) or not isinstance(self.threads, int)
                                         or self.threads < 1):
            raise ConfigError(f"threads must be a positive integer, got {self.threads!r}")
        for name in ("scene", "seed"):
            v = getattr(self, name)
            if isinstance(v, bool) or not isinstance(v, int) or v < 0:
                raise ConfigError(f"{name} must be a non-negative integer, got {v!r}")
        if self.size > 2048:
            raise ConfigError(f"size must be at most 2048 pixels, got {self.size}")
        if self.shell not in SHELLS:
            raise ConfigError(f"shell must be one of {SHELLS}, got {self.shell!r}")


@dataclass(frozen=True)
class LiveFrame:
    """One displayed frame of the demo."""

    index: int
    """Frame number, from 0."""
    picture: np.ndarray
    """``(h, w, 3)`` uint8: camera image | prediction | truth, with headings, FPS and legend."""
    seconds: float
    """End-to-end time of the frame (module docstring)."""
    stages: dict[str, float]
    """Seconds per stage of :data:`STAGES`."""


class RobotDemo:
    """The live demo's sources and pipeline (module docstring); :meth:`frames` drives.

    Args:
        config: the settings (checked here).
    """

    def __init__(self, config: RobotDemoConfig) -> None:
        from .model_files import ROBOT_MODEL
        from .predict import CameraPrior, load_predictor, share_cpu
        from .sim.cameras import ROBOT_CAMERA
        from .sim.config import AugmentConfig, ImageConfig, SimConfig, TrajectoryConfig

        self.config = config
        share_cpu(config.threads)
        trajectory = TrajectoryConfig(steps_per_frame=config.steps_per_frame)
        # The robot knows its mount: a model that reads the camera is told its pitch, roll (level) and height.
        mount = trajectory.mount
        prior = CameraPrior(pitch=float(mount.tilt), roll=0.0, height=float(mount.height))
        self.predictor = load_predictor(config.checkpoint or ROBOT_MODEL, device=config.device, batch=1,
                                        compile=config.compile, camera=prior)
        if not config.flip_average:  # before the first frame: the Predictor compiles and captures then
            self.predictor.rules = dataclasses.replace(self.predictor.rules, flip_average=False)
        mc = self.predictor.config
        self.grid, self.classes = mc.grid, mc.classes
        cam_w = config.size
        cam_h = round(cam_w * self.grid.height / self.grid.width)
        if (cam_w * self.grid.height) % self.grid.width:
            raise LiveError(f"size {cam_w} times the grid's height {self.grid.height} must be a multiple of its "
                            f"width {self.grid.width}")
        # The robot's own mount, whatever the simulator's default camera: the chase view rides on it.
        self.sim = SimConfig(grid=self.grid, image=ImageConfig(size=cam_w, augment=AugmentConfig(enabled=False)),
                             classes=self.classes, samples_per_scene=config.frames, trajectory=trajectory,
                             splits=(("train", 1), ("test", (config.scene + 1) * config.frames)),
                             camera=ROBOT_CAMERA)
        self.camera_height = cam_h
        self.chase = chase_camera(self.sim.trajectory.mount, round(config.size * 4 / 3), config.size, config.chase)
        # The prediction's kernels follow its logits (where SSZ ran); the truth's numpy labels go to the same device
        # (a GPU machine may have no CPU backend: the staged Warp there has no CPU compiler).
        where = str(self.predictor.device) if self.predictor.device.type == "cuda" else config.device
        self.prediction = ShellDisplay(self.grid, self.classes, self.chase, shell=config.shell,
                                       backend=config.backend, device=config.device)
        self.truth = ShellDisplay(self.grid, self.classes, self.chase, shell=config.shell,
                                  backend=config.backend, device=where)

    @property
    def split(self) -> str:
        """The simulator split driven through."""
        return "test"

    def camera_frames(self) -> Iterator[Any]:
        """The simulator's samples of the drive, in order (camera image, truth labels, pose): not timed."""
        from .sim.sample import SampleMaker

        start = self.config.scene * self.config.frames
        with SampleMaker(self.sim, self.config.seed) as maker:
            for f in range(self.config.frames):
                yield maker.make(self.split, start + f)

    def predict(self, image: np.ndarray, times: dict[str, float]) -> Any:
        """SSZ's logits ``(1, C, D, H, W)`` of a camera image, on the predictor's device; stage seconds go to
        ``times`` (``input``, ``ssz``)."""
        from .predict import frame_image, to_tensor

        t0 = time.perf_counter()
        x = to_tensor([frame_image(image, self.grid, self.predictor.config.image_size)], self.predictor.device)
        t1 = time.perf_counter()
        logits = self.predictor.logits(x)
        _synchronise(logits)
        times["input"] = times.get("input", 0.0) + t1 - t0
        times["ssz"] = times.get("ssz", 0.0) + time.perf_counter() - t1
        return logits

    def headings(self) -> tuple[str, str, str]:
        """Headings of the three panels."""
        return ("robot camera (not timed)", "SSZ prediction, chase view", "ground truth, chase view")

    def frames(self, fps_window: int = 10) -> Iterator[LiveFrame]:
        """Drive: one :class:`LiveFrame` per camera frame.

        Args:
            fps_window: frames over which the FPS shown on screen is averaged.
        """
        from fruxel.render.compare import Layout, caption_size, fit_height
        from fruxel.render.legend import draw_caption

        recent: list[float] = []
        layout: Layout | None = None
        labels = list(range(1, len(self.classes)))
        device = self.predictor.device.type
        shell = "robot camera's" if self.config.shell == "own" else "chase camera's"
        for f, sample in enumerate(self.camera_frames()):
            truth_panel = self.truth.draw(sample.labels)
            times: dict[str, float] = {}
            t0 = time.perf_counter()
            logits = self.predict(sample.image, times)
            panel = self.prediction.draw(logits, times)
            t1 = time.perf_counter()
            fps = f"{len(recent) / sum(recent):.1f} FPS" if recent else "-- FPS"
            size = caption_size(self.config.size)
            panel = draw_caption(panel, f"{fps} end to end ({device})", size)
            camera_panel = draw_caption(fit_height(sample.image, self.config.size), f"frame {f + 1}", size)
            title = (f"test room {self.config.scene} (seed {self.config.seed}), never trained on: SSZ "
                     f"{self.grid.width}x{self.grid.height}x{self.grid.depth}, {shell} shell, mesh every frame")
            columns = [[camera_panel], [panel], [truth_panel]]
            if layout is None:
                # The title, headings and legend are drawn once; each frame only fills the panels in.
                layout = Layout([[c[0].shape[:2]] for c in columns], self.headings(), self.classes, labels,
                                title=title)
            picture = layout.fill(columns)
            t2 = time.perf_counter()
            times["compose"] = t2 - t1
            seconds = t2 - t0
            recent = (recent + [seconds])[-fps_window:]
            yield LiveFrame(f, picture, seconds, {s: times.get(s, 0.0) for s in STAGES})


def summarise(frames: list[LiveFrame], skip: int = 1) -> dict[str, Any]:
    """End-to-end statistics of a drive: frames per second and milliseconds per stage.

    Args:
        frames: the frames (their pictures are not used).
        skip: first frames left out (the first call of each stage sets up kernels and buffers).

    Returns:
        ``{"frames", "fps_mean", "ms_mean", "ms_median", "ms_p90", "stages_ms": {stage: mean}}``; the FPS is
        frames over the summed end-to-end time.
    """
    kept = frames[skip:] if len(frames) > skip else frames
    if not kept:
        return {"frames": 0}
    ms = np.array([f.seconds for f in kept]) * 1000.0
    return {
        "frames": len(kept),
        "fps_mean": float(1000.0 * len(kept) / ms.sum()),
        "ms_mean": float(ms.mean()),
        "ms_median": float(np.median(ms)),
        "ms_p90": float(np.percentile(ms, 90)),
        "stages_ms": {s: float(1000.0 * np.mean([f.stages[s] for f in kept])) for s in STAGES},
    }

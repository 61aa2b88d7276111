"""``fruxel-robot``: the live robot demo, the paper's case study. A robot drives through a room of the simulator's
test split (never trained on); each camera image goes through SSZ, the shell and the display while it drives.

Usage::

    fruxel-robot [--frames N] [--scene I] [--seed S] [--size PX] [--steps-per-frame K] [--shell {own,chase}]
                 [--backend {warp,opencl}] [--device cpu|cuda[:N]] [--checkpoint FILE] [--threads N]
                 [--out FILE.mp4|FILE.gif] [--fps F] [--view]

Display: with a display (``DISPLAY`` or ``WAYLAND_DISPLAY`` set) and no ``--out``, live in pyrender's
interactive viewer: the predicted model's shell mesh from the chase camera, replaced every frame, with the frames
per second in the window; the simulator then renders the camera images in a process of its own (as a camera
would deliver them) and the drive runs as fast as the pipeline goes. Otherwise (or with ``--out``) into a video:
``out/robot.mp4`` by default, or ``--out FILE.mp4|FILE.gif``, each frame three panels (camera image | predicted
model from a chase view behind and above the robot | ground truth from the same view) with the frames per second
on screen; the video plays at robot time (``--fps``, default 10 / ``--steps-per-frame``).

Frames per second are end to end, from the camera image in hand to the displayed frame: input mapping, SSZ, shell,
mesh, draw, composed picture (:mod:`fruxel.train.live` says exactly what is timed). The simulator's rendering of
the camera image stands in for a real camera and is not timed, nor is the ground truth. The last lines printed
give the FPS and the milliseconds per stage over the frames after the first (whose calls set kernels up).

``--size`` is a whole multiple of the model grid's width (64 for ``ssz64``, 128 for ``ssz128``): the simulator
renders the camera image at a whole multiple of the grid. The device, the model's grid and the output file are
checked before the model is built. Errors are one line ``fruxel-robot: error: ...`` with exit status 2
(:func:`fruxel.cli.common.run`).
"""

from __future__ import annotations

import argparse
import os
import sys
from pathlib import Path
from typing import Any

from .common import (
    OneLineParser,
    UsageError,
    check_output_file,
    config_option,
    config_values,
    device_name,
    non_negative_int,
    path_name,
    positive_float,
    positive_int,
    run,
    torch_device,
    write_outputs,
)

PROG = "fruxel-robot"
DEFAULT_OUT = Path("out/robot.mp4")
"""The video written when there is no display and no ``--out``."""
BACKENDS = ("warp", "opencl")
QUEUE_FRAMES = 2
"""Camera frames the simulator's process may render ahead of the live viewer."""
LINGER: float | None = None
"""Seconds the live viewer stays open after the drive; None: until its window is closed."""


def build_parser() -> argparse.ArgumentParser:
    """The argument parser (no heavy imports: ``--help`` must be instant)."""
    from fruxel.train.live import SHELLS, RobotDemoConfig

    p = OneLineParser(
        prog=PROG,
        description="The live robot demo: a robot drives through a held-out room of the simulator; each camera image "
        "goes through SSZ, the shell and the display (pyrender's viewer when there is a display, else a video: "
        "camera | prediction | truth from a chase view, with end-to-end frames per second).",
        epilog="Timed end to end: from the camera image in hand to the displayed frame; the simulator's rendering of "
        "the camera image (a stand-in for a real camera) and the ground truth are not timed.",
    )
    config_option(p, RobotDemoConfig, "frames", type=positive_int, metavar="N")
    config_option(p, RobotDemoConfig, "scene", type=non_negative_int, metavar="I")
    config_option(p, RobotDemoConfig, "seed", type=non_negative_int, metavar="S")
    config_option(p, RobotDemoConfig, "size", type=positive_int, metavar="PX")
    config_option(p, RobotDemoConfig, "steps_per_frame", type=positive_int, metavar="K")
    config_option(p, RobotDemoConfig, "shell", choices=SHELLS)
    config_option(p, RobotDemoConfig, "backend", choices=BACKENDS)
    config_option(p, RobotDemoConfig, "device", type=device_name, metavar="cpu|cuda[:N]")
    config_option(p, RobotDemoConfig, "checkpoint", metavar="FILE")
    config_option(p, RobotDemoConfig, "threads", type=positive_int, metavar="N")
    config_option(p, RobotDemoConfig, "compile")
    config_option(p, RobotDemoConfig, "flip_average")
    p.add_argument("--out", type=path_name, default=None, metavar="FILE",
                   help=f"write the video here (.mp4 or .gif) instead of showing the viewer (default without a "
                   f"display: {DEFAULT_OUT})")
    p.add_argument("--fps", type=positive_float, default=None, metavar="F",
                   help="playback rate of the video (default: robot time, 10 / --steps-per-frame)")
    p.add_argument("--view", action="store_true", help="show pyrender's viewer (needs a display; the default there)")
    return p


def demo_config(args: argparse.Namespace) -> Any:
    """The demo's settings (:class:`fruxel.train.live.RobotDemoConfig`) from the parsed options."""
    from fruxel.train.live import RobotDemoConfig

    return RobotDemoConfig(**config_values(args, RobotDemoConfig))


def _summary_line(frames: list[Any], device: str) -> str:
    from fruxel.train.live import summarise

    s = summarise(frames)
    if not s["frames"]:
        return "no frames timed"
    stages = ", ".join(f"{k} {v:.0f}" for k, v in s["stages_ms"].items())
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else float("nan")
    cores = len(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else os.cpu_count()
    return (f"{s['fps_mean']:.1f} FPS end to end on {device} over {s['frames']} frames after the first (mean "
            f"{s['ms_mean']:.0f} ms a frame: {stages} ms); camera images and ground truth not timed; load average "
            f"{load:.1f} on {cores} cores")


# ---------------------------------------------------------------------------------------------------- video
def _write_video(args: argparse.Namespace, out: Path) -> list[str]:
    import dataclasses

    import numpy as np
    from tqdm import tqdm

    from fruxel.render.images import save_video
    from fruxel.train.live import RobotDemo

    config = demo_config(args)
    demo = RobotDemo(config)
    fps = args.fps if args.fps is not None else 10.0 / config.steps_per_frame
    timed: list[Any] = []

    def pictures() -> Any:
        # stderr, like the error lines; the bar disappears when done so scripts see only what is printed.
        for frame in tqdm(demo.frames(), total=config.frames, desc="drive", unit="frame", leave=False, disable=None):
            timed.append(dataclasses.replace(frame, picture=np.empty(0, np.uint8)))
            yield frame.picture

    keep = [(255, 255, 255), *demo.classes.palette()[1:]]

    def encode(frames: Any) -> Any:
        # An MP4 is encoded as the drive goes (its bar says all); a GIF once it is over, with a bar of its own.
        return frames if out.suffix.lower() == ".mp4" else tqdm(frames, total=config.frames, desc="encode",
                                                                 unit="frame", leave=False, disable=None)

    write_outputs([(out, lambda tmp: save_video(tmp, pictures(), fps, out.suffix, keep, encode))])
    return [str(out), _summary_line(timed, demo.predictor.device.type)]


# ---------------------------------------------------------------------------------------------------- viewer
def camera_process(sim: dict[str, Any], seed: int, split: str, start: int, frames: int, queue: Any,
                   stop: Any) -> None:
    """The simulator as a camera, in a process of its own (the live viewer's): puts ``(image, labels)`` of each
    frame on ``queue``, then None; returns early once ``stop`` (an event) is set. Renders with EGL, apart from the
    viewer's window system OpenGL."""
    import queue as queues

    os.environ["PYOPENGL_PLATFORM"] = "egl"
    from fruxel.train.sim.config import SimConfig
    from fruxel.train.sim.sample import SampleMaker

    def put(item: Any) -> bool:
        while not stop.is_set():
            try:
                queue.put(item, timeout=0.2)
                return True
            except queues.Full:
                continue
        return False

    try:
        with SampleMaker(SimConfig.from_dict(sim), seed) as maker:
            for f in range(frames):
                s = maker.make(split, start + f)
                if not put((s.image, s.labels)):
                    return
    finally:
        put(None)


def _stop_camera(camera: Any, frames_queue: Any, stop: Any) -> None:
    """End the camera process: ask it to stop, take what it queued (so that it is not blocked putting), wait."""
    import queue as queues
    import time

    stop.set()
    deadline = time.monotonic() + 30.0  # a frame takes well under a second; a hung simulator is killed
    camera.join(timeout=0.5)
    while camera.is_alive():
        if time.monotonic() > deadline:
            camera.kill()
            camera.join()
            break
        try:
            frames_queue.get(timeout=0.2)
        except queues.Empty:
            camera.join(timeout=0.5)
    frames_queue.close()


def _viewer_pyrender() -> Any:
    """pyrender on the window system's OpenGL, or one RenderError saying why not."""
    from fruxel.render import RenderError
    from fruxel.render.compat import import_pyrender
    from fruxel.render.frames import has_display

    if not has_display():
        raise RenderError("the live viewer needs a display (DISPLAY is not set); write a video with --out FILE.mp4")
    if os.environ.get("PYOPENGL_PLATFORM") == "egl":
        # EGL is headless; the viewer needs the window system's OpenGL. Only this process is affected.
        del os.environ["PYOPENGL_PLATFORM"]
    # A headless pyglet opens no window (the viewer's thread would die at once).
    os.environ.pop("PYGLET_HEADLESS", None)
    try:
        return import_pyrender(headless=False)
    except Exception as e:  # noqa: BLE001 - PyOpenGL / pyglet raise many types when the window system is missing
        raise RenderError(f"cannot use the window system's OpenGL ({type(e).__name__}: {e}); write a video with "
                          "--out FILE.mp4") from None


def _viewer_scene(pyrender: Any, demo: Any) -> tuple[Any, dict[str, Any]]:
    """The viewer's scene (the grid's frustum, the chase camera) and its caption."""
    import math

    import numpy as np

    from fruxel.render.scene import clip_range, frustum_lines

    grid, cam = demo.grid, demo.chase
    scene = pyrender.Scene(bg_color=[1.0, 1.0, 1.0, 1.0], ambient_light=[0.3, 0.3, 0.3])
    scene.add(frustum_lines(grid))
    znear, zfar = clip_range(cam, grid)
    scene.add(pyrender.PerspectiveCamera(yfov=2.0 * math.atan(cam.height / (2.0 * cam.fy)), znear=znear,
                                         zfar=zfar * 4.0, aspectRatio=cam.width / cam.height), pose=cam.opengl_pose())
    caption = {"text": "waiting for the camera...", "location": pyrender.constants.TextAlign.TOP_LEFT,
               "font_name": "OpenSans-Regular", "font_pt": 16, "color": np.array([0.1, 0.1, 0.1, 1.0]), "scale": 1.0}
    return scene, caption


def _show_viewer(args: argparse.Namespace) -> list[str]:
    import multiprocessing
    import threading

    from fruxel.render import RenderError
    from fruxel.train.live import RobotDemo

    pyrender = _viewer_pyrender()
    config = demo_config(args)
    demo = RobotDemo(config)
    cam = demo.chase
    ctx = multiprocessing.get_context("spawn")
    frames_queue, stop = ctx.Queue(maxsize=QUEUE_FRAMES), ctx.Event()
    camera = ctx.Process(target=camera_process, daemon=True,
                         args=(demo.sim.to_dict(), config.seed, demo.split, config.scene * config.frames,
                               config.frames, frames_queue, stop))
    camera.start()
    scene, caption = _viewer_scene(pyrender, demo)
    failures: list[BaseException] = []
    hook = threading.excepthook

    def keep(info: Any) -> None:
        # The viewer's thread failing (no window) becomes this command's one error line, not a traceback.
        failures.append(info.exc_value)

    threading.excepthook = keep
    try:
        viewer = pyrender.Viewer(scene, viewport_size=(2 * cam.width, 2 * cam.height), run_in_thread=True,
                                 use_raymond_lighting=True, caption=[caption],
                                 window_title=f"{PROG}: SSZ prediction of test room {config.scene}, chase view")
    except Exception as e:  # noqa: BLE001 - pyglet / OpenGL raise many types when no window can be opened
        threading.excepthook = hook
        _stop_camera(camera, frames_queue, stop)
        raise RenderError(f"cannot open the viewer window: {type(e).__name__}: {e}") from None
    try:
        timed = _drive_viewer(viewer, scene, caption, demo, frames_queue, failures)
    finally:
        threading.excepthook = hook
        _stop_camera(camera, frames_queue, stop)
    return [_summary_line(timed, demo.predictor.device.type)]


def _drive_viewer(viewer: Any, scene: Any, caption: dict[str, Any], demo: Any, frames_queue: Any,
                  failures: list[BaseException]) -> list[Any]:
    """Show the prediction of each camera image the camera process sends, until the drive ends or the window
    closes; then leave the window open (for :data:`LINGER` seconds when set). Returns the frames' timings."""
    import queue as queues
    import time

    import numpy as np

    from fruxel.render import RenderError
    from fruxel.render.scene import MeshStyle, pyrender_mesh
    from fruxel.train.live import STAGES, LiveFrame

    config, device = demo.config, demo.predictor.device.type
    timed: list[Any] = []
    node = None
    recent: list[float] = []

    def alive() -> bool:
        # pyrender marks the viewer active before its thread opens the window, and never unmarks it when the
        # thread fails; its thread (a private attribute) tells.
        thread = getattr(viewer, "_thread", None)
        return viewer.is_active and (thread is None or thread.is_alive())

    while alive():
        try:
            item = frames_queue.get(timeout=0.5)
        except queues.Empty:
            continue
        if item is None:
            break
        image, _ = item
        times: dict[str, float] = {}
        t0 = time.perf_counter()
        pm = pyrender_mesh(demo.prediction.mesh_of(demo.predict(image, times), times), MeshStyle(shading="pbr"))
        fps = f"{len(recent) / sum(recent):.1f} FPS" if recent else "-- FPS"
        with viewer.render_lock:
            if node is not None:
                scene.remove_node(node)
            node = scene.add(pm) if pm is not None else None
            caption["text"] = f"frame {len(timed) + 1}/{config.frames}: {fps} end to end ({device})"
        seconds = time.perf_counter() - t0
        times["draw"] = times.get("draw", 0.0) + seconds - sum(times.values())
        recent = (recent + [seconds])[-10:]
        timed.append(LiveFrame(len(timed), np.empty(0, np.uint8), seconds, {s: times.get(s, 0.0) for s in STAGES}))
    if not alive() and viewer.is_active:
        why = f"{type(failures[0]).__name__}: {failures[0]}" if failures else "its thread ended"
        raise RenderError(f"the viewer's window failed ({why}); write a video with --out FILE.mp4")
    if alive():
        with viewer.render_lock:
            caption["text"] = f"drive over: {caption['text'].split(': ', 1)[-1]}; close the window to quit"
        end = None if LINGER is None else time.monotonic() + LINGER
        while alive() and (end is None or time.monotonic() < end):
            time.sleep(0.2)
        if alive():
            viewer.close_external()
    return timed


# ---------------------------------------------------------------------------------------------------- entry
def _check_model(config: Any) -> None:
    """The device and the model's grid against ``--size``, before the model is built or the simulator started.

    Raises:
        UsageError: a CUDA device on a machine without one; a ``--size`` that is not a whole multiple of the
            model grid's width (the simulator renders the camera image at a whole multiple of the grid's size).
        ModelFileError: an unusable ``--checkpoint``.
    """
    from fruxel.train.model_files import ROBOT_MODEL, model_path, read_model_file

    torch_device(config.device)
    path = model_path(config.checkpoint or ROBOT_MODEL)
    grid = read_model_file(path).config.grid
    if config.size % grid.width:
        below = max(grid.width, config.size - config.size % grid.width)
        raise UsageError(f"--size {config.size}: the camera image must be a whole multiple of the model grid's width "
                         f"({grid.width} columns, {os.path.basename(path)}), e.g. {below} or {below + grid.width}")


def _main(args: argparse.Namespace) -> int:
    from fruxel.render.frames import has_display
    from fruxel.render.images import check_video_writer

    config = demo_config(args)
    if args.view and args.out is not None:
        raise UsageError("--view shows the drive in a window and writes no file: leave out --out")
    viewer = args.view or (args.out is None and has_display())
    if viewer:
        if args.fps is not None:
            raise UsageError("--fps is the playback rate of a video (--out)")
    else:
        out = args.out if args.out is not None else DEFAULT_OUT
        check_video_writer(out)
        check_output_file(out, "--out")
    _check_model(config)
    lines = _show_viewer(args) if viewer else _write_video(args, out)
    for line in lines:
        print(line)
    return 0


def main(argv: list[str] | None = None) -> int:
    """Entry point of ``fruxel-robot``; returns the exit status (0, 2 for bad input, 130 when interrupted)."""
    return run(_main, build_parser(), argv)


if __name__ == "__main__":
    sys.exit(main())

"""The environment simulator: procedural rooms, the paper's mobile robot, and ground truth by ray casting.

* :mod:`.scene` — rooms with walls (with real openings), floor, windows, doors, furniture and sculptures,
  lights and a free-space map, from a seed (:func:`make_scene`), labelled with the ids of a class table;
* :mod:`.assets` — optional real meshes: a folder per class, and Sweet Home 3D ``.sh3f`` libraries;
* :mod:`.assetpack` — the asset pack built by ``fruxel-sim assets`` (textures with normal maps, meshes with parts,
  pictures; licence manifest, train/test split) and :class:`~.assetpack.AssetPack`, its checked reader;
* :mod:`.robot` — the mobile robot of conventions section 7 (:func:`simulate`), its camera mount, and collision-free
  random or scripted trajectories giving one camera pose per frame;
* :mod:`.renderer` — what draws the camera images: the renderer protocol and the registry of renderers by name
  (:class:`.images.SceneRenderer`, pyrender, is the default; :mod:`.raytrace`, ray-traced in Warp with textures,
  soft shadows and a camera response, is ``"raytrace"``), chosen by ``SimConfig.renderer``;
* :mod:`.cameras` — the camera each trajectory draws (``SimConfig.camera``: the robot's own mount, or any height,
  pitch, roll and field of view), its render framed onto the grid's view, and each sample's camera record;
  :mod:`.testsets` — the held-out test sets as named configs;
* ground truth: :func:`fruxel.kernels.fruxelize` labels a grid from the scene's solids; what the grid's own
  camera sees of them is ``fruxel.kernels.first_hit(labels, grid, grid.camera())``;
* data sets: :mod:`.sample` (a sample and its maker), :mod:`.shards` (shard files), :mod:`.manifest` (the data
  set folder), :mod:`.writer` (``generate``), :mod:`.dataset` (reading shards with torch; training streams through
  :mod:`fruxel.train.samples`).

World frame: right-handed, metres, z up, the floor's top at z = 0 and the room's interior in
``[0, Lx] x [0, Ly] x [0, Lz]``. Camera poses are camera-to-world 4x4 matrices with OpenCV camera axes
(x right, y down, z forward), so ``fruxel.Camera(..., pose=T)`` and ``fruxelize(meshes, grid, T)`` work in world
coordinates directly.
"""

from __future__ import annotations

from fruxel.kernels.fruxelize import MeshSet

from .assets import Asset, AssetError, AssetLibrary, load_asset_folder, load_sh3f
from .robot import (
    CameraMount,
    RobotParams,
    RobotStates,
    Trajectory,
    TrajectoryError,
    camera_poses,
    constant_commands,
    random_trajectory,
    segment_commands,
    simulate,
    trajectory_from_commands,
)
from .scene import (
    CLASS_NAMES,
    FreeSpace,
    Light,
    RoomConfig,
    Scene,
    SceneError,
    SceneObject,
    make_scene,
)

__all__ = [
    "CLASS_NAMES",
    "Asset",
    "AssetError",
    "AssetLibrary",
    "CameraMount",
    "FreeSpace",
    "Light",
    "MeshSet",
    "RobotParams",
    "RobotStates",
    "RoomConfig",
    "Scene",
    "SceneError",
    "SceneObject",
    "Trajectory",
    "TrajectoryError",
    "camera_poses",
    "constant_commands",
    "load_asset_folder",
    "load_sh3f",
    "make_scene",
    "random_trajectory",
    "segment_commands",
    "simulate",
    "trajectory_from_commands",
]

"""A run's observations view by view, for the exporters (COLMAP, ROS 2 bags): what each trial saw of each pose.

The features come from the public API's batches (`wiredsl.api` over `wiredsl.run`; `wiredsl.export.trials` runs
them and `split` turns each batch into Trials), never re-derived: corners
(pixels and feature ids) and strokes (polylines in pixels). Each view also carries its *nominal* camera and pose:
the camera the scene declares and the robot's path pose, which is what a researcher's calibration file and
ground truth say, whatever calibration_error drew for a trial.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

import numpy as np

CAMERAS = ("left", "right")


@dataclass
class View:
    """One camera's view of one path pose in one trial."""

    pose: int
    side: str  # "left" or "right"
    R: np.ndarray  # (3, 3) and t (3,): nominal P_cam = R P_world + t
    t: np.ndarray
    corner: np.ndarray  # (k,) index into the scene's corners (World.corners), in the batch's order
    corner_uv: np.ndarray  # (k, 2) pixels (origin at the top-left pixel's centre, as every wiredsl output)
    strokes: list = field(default_factory=list)  # (feature id, segment, kind, closed, pts (n, 2))


@dataclass
class Trial:
    trial: int
    views: list[View]


@dataclass
class Source:
    """What every trial shares: the scene, its rig's nominal cameras, the world's corners and feature names."""

    scene: object
    cameras: dict  # side -> scene Camera
    mounts: dict  # side -> (rotation (3, 3) camera -> robot, position (3,))
    corners: np.ndarray  # (C, 3) world points
    corner_names: list[str]  # "placement.feature" of each corner
    feature_ids: list[str]
    poses: list[int]  # the path's pose indices, in order
    robot: list[tuple[np.ndarray, np.ndarray]]  # world_from_robot (R, t) of each pose
    stamps_ns: list[int] | None = None  # each pose's time on the trajectory file's clock (None: the path has none)


def stamps_ns(path) -> list[int] | None:
    """Each pose's time in integer nanoseconds on the clock of the trajectory file the path was read from: the
    file's first timestamp (exact) plus the pose's seconds from it; a file without a clock of its own (KITTI poses
    with a rate) starts at 0. None for a path without times (poses written in the scene)."""
    if path.times is None:
        return None
    start = path.start_ns or 0
    return [start + round(t * 1e9) for t in path.times]


def source(scene, world) -> Source:
    """The shared part of an export of `scene` (a rig and a path are required: ValueError otherwise)."""
    from wiredsl.engine import geometry

    if scene.rig is None:
        raise ValueError(f"scene '{scene.name}' has no rig: nothing to export")
    if scene.path is None:
        raise ValueError(f"scene '{scene.name}' has no path: the export needs the robot's poses")
    cameras = {side: scene.camera(getattr(scene.rig, side).camera) for side in CAMERAS}
    mounts = {side: (np.array(getattr(scene.rig, side).rotation, dtype=float),
                     np.array(getattr(scene.rig, side).position, dtype=float)) for side in CAMERAS}
    poses = list(range(len(scene.path.poses)))
    robot = [geometry.world_from_robot(scene.path.pose(i)) for i in poses]
    robot = [(np.asarray(R, dtype=float), np.asarray(t, dtype=float)) for R, t in robot]
    return Source(scene, cameras, mounts, np.asarray(world.corners, dtype=float),
                  [world.feature_ids[f] for f in world.corner_fid], list(world.feature_ids), poses, robot,
                  stamps_ns(scene.path))


def camera_from_world(src: Source, pose: int, side: str) -> tuple[np.ndarray, np.ndarray]:
    """The nominal (R, t) of camera `side` at path pose `pose`: P_cam = R P_world + t."""
    from wiredsl.engine import geometry

    m = getattr(src.scene.rig, side)
    R, t = geometry.camera_from_world(src.scene.path.pose(pose), m.rotation, m.position)
    return np.asarray(R, dtype=float), np.asarray(t, dtype=float)


def split(batch, nominal: dict, fid_corner: dict) -> Iterator[Trial]:
    """A Batch's arrays as one Trial a trial, views in (pose, camera) order (`nominal`: each (pose, side)'s
    camera_from_world; `fid_corner`: feature id -> corner row)."""
    corners, crows = batch["corners"], batch["corner_rows"]
    pts, start, strokes = batch["pts"], batch["start"], batch["strokes"]
    views = batch["views"]
    for trial in batch.trials.tolist():
        out = []
        for _, pose, cam in sorted({tuple(int(x) for x in r) for r in views if r[0] == trial}):
            side = CAMERAS[cam]
            here = (crows[:, 0] == trial) & (crows[:, 1] == pose) & (crows[:, 2] == cam)
            ids = np.array([fid_corner[int(f)] for f in crows[here, 3]], dtype=np.int64)
            R, t = nominal[(pose, side)]
            v = View(pose, side, R, t, ids, np.asarray(corners[here], dtype=float).reshape(-1, 2))
            for k in np.flatnonzero((strokes[:, 0] == trial) & (strokes[:, 1] == pose) & (strokes[:, 2] == cam)):
                row = strokes[k]
                v.strokes.append((int(row[3]), int(row[4]), int(row[5]), bool(row[7]),
                                  np.asarray(pts[start[k]:start[k + 1]], dtype=float)))
            out.append(v)
        yield Trial(int(trial), out)

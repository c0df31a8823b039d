"""The robot's motion along its path, and what a camera sees of it: velocities from a continuous-time
interpolation of the path's poses, the robot's pose at times near a pose's (a stereo pair's sync offset), and the
rolling-shutter projection (each point imaged from the camera's pose at its own row's time).

Within a frame (a readout, a sync offset: milliseconds) the robot moves with its velocity at the pose, a constant
twist in the world frame: world_from_robot(tau) = (exp([w] tau) R_wr, t_wr + v tau). The velocities (v, w) at a
pose are the tangents, at that pose, of the piecewise cubic Hermite interpolation through the poses at their times
whose tangents are the three-point derivatives (the derivative of the parabola through a pose and its two
neighbours; one-sided at the ends): exact for a straight run at a constant speed.

A path without times (no `speed`, a trajectory file without timestamps) stands still at every pose: nothing here
is used for it, and a scene that declares no readout and no sync never imports this module.
"""

from __future__ import annotations

import math

import numpy as np

from wiredsl.diagnostics import Diagnostic, WiredslError
from wiredsl.engine import geometry

ROW_TOL = 1e-9  # px: the rolling-shutter fixed point stops when an iteration moves a point's row by no more
MAX_ITERATIONS = 100


def _log_rotation(R: np.ndarray) -> np.ndarray:
    """Rotation vectors (n, 3) of rotations R (n, 3, 3) (angles below pi)."""
    c = np.clip((np.trace(R, axis1=1, axis2=2) - 1.0) / 2.0, -1.0, 1.0)
    theta = np.arccos(c)
    axis = np.stack([R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]], axis=1)
    s = np.sin(theta)
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(s > 1e-12, theta / (2.0 * s), 0.5)  # small angles: the skew part is the vector itself
    return axis * scale[:, None]


def velocities(path) -> tuple[np.ndarray, np.ndarray]:
    """The robot's world-frame velocity v (n, 3) (of its origin, m/s) and angular velocity w (n, 3) (rad/s) at
    each pose of a path with times: the three-point derivatives (see the module's docstring)."""
    times = np.asarray(path.times, dtype=float)
    n = len(times)
    poses = [geometry.world_from_robot(path.pose(i)) for i in range(n)]
    if n < 2:
        return np.zeros((n, 3)), np.zeros((n, 3))
    R = np.stack([p[0] for p in poses])
    t = np.stack([p[1] for p in poses])
    h = np.diff(times)
    dp = np.diff(t, axis=0) / h[:, None]  # each interval's mean velocity
    dr = _log_rotation(np.einsum("nij,nkj->nik", R[1:], R[:-1])) / h[:, None]  # R_{i+1} R_i^T: world frame

    def tangents(d):
        out = np.empty((n, 3))
        out[0], out[-1] = d[0], d[-1]
        h0, h1 = h[:-1, None], h[1:, None]
        out[1:-1] = (h1 * d[:-1] + h0 * d[1:]) / (h0 + h1)
        return out

    return tangents(dp), tangents(dr)


def _rotate_back(d: np.ndarray, w: np.ndarray, tau) -> np.ndarray:
    """exp([w] tau)^T d for points d (..., 3), angular velocity w (3,) and times tau (...,) (Rodrigues)."""
    speed = math.sqrt(float(w @ w))
    if speed == 0.0:
        return d
    k = w / speed
    theta = -speed * np.asarray(tau, dtype=float)[..., None]
    c, s = np.cos(theta), np.sin(theta)
    return d * c + np.cross(k, d) * s + k * (d @ k)[..., None] * (1.0 - c)


def moved(X: np.ndarray, tau, robot: np.ndarray, v: np.ndarray, w: np.ndarray) -> np.ndarray:
    """World points X (..., 3) as the robot at time tau (...,) sees them, put back in the world frame of the robot
    at time 0 (at `robot`, its origin in the world): exp([w] tau)^T (X - robot - v tau) + robot. A camera's
    pose at time 0 then images them as the camera at tau images X."""
    tau = np.asarray(tau, dtype=float)
    return _rotate_back(X - robot - v * tau[..., None], w, tau) + robot


def robot_at(pose, v: np.ndarray, w: np.ndarray, tau: float) -> tuple[float, ...]:
    """The robot's pose `tau` seconds after `pose` (moving with v, w): the 12 numbers of its [R | t]."""
    R, t = geometry.world_from_robot(pose)
    E = _rotate_back(np.eye(3), w, -tau).T  # exp([w] tau): columns of rotated unit vectors
    return tuple(float(x) for x in np.column_stack([E @ R, t + v * tau]).ravel())


def rolling_pixels(X: np.ndarray, pixels, readout: float, height: float, robot: np.ndarray, v: np.ndarray,
                   w: np.ndarray) -> np.ndarray:
    """Pixels (..., 2) of world points X (..., 3) under a rolling shutter: row r is exposed at readout r / height
    after the camera's time 0, and each point is imaged from the camera's pose at its own row's time.

    `pixels` maps world points (..., 3), as the camera's pose at time 0 sees them, to pixels (..., 2). The row
    time is the fixed point of r = row(X seen at readout r / height), iterated from r = row at time 0 until an
    iteration moves the row by no more than ROW_TOL px, each point on its own (a converged point's row is kept,
    as a loop a point would give). It converges when q = readout |dr/dt| / height < 1, |dr/dt| the point's image
    speed across rows: the error then shrinks by q an iteration. A row beyond the image takes the time of the
    image's nearest row (the map stays bounded where the lens folds or a point nears the camera); points whose
    pixels are not finite (not imaged) stop at once."""
    uv = pixels(X)
    row = uv[..., 1]
    active = np.isfinite(row)
    for _ in range(MAX_ITERATIONS):
        if not active.any():
            return uv
        tau = readout * np.clip(np.where(active, row, 0.0), 0.0, height) / height  # rows beyond the image: its ends
        new = pixels(moved(X, tau, robot, v, w))
        with np.errstate(invalid="ignore"):
            step = np.abs(np.clip(new[..., 1], 0.0, height) - np.clip(row, 0.0, height))
        uv = np.where(active[..., None], new, uv)
        row = uv[..., 1]
        active &= np.isfinite(row) & ~(step <= ROW_TOL)
    if active.any():
        raise WiredslError([Diagnostic(
            "error", "E152", f"rolling shutter: the row time of {int(active.sum())} point(s) did not converge in "
            f"{MAX_ITERATIONS} iterations", None,
            "the image moves across more rows during the readout than the image has: a shorter readout, or a "
            "slower robot")])
    return uv


def view_motions(scene, index: int) -> dict[str, tuple | None]:
    """Each side's motion at path pose `index`: (robot pose at the camera's own time, rolling shutter or None),
    the rolling shutter as (readout, height, robot origin, v, w); None for a side that neither moves (no sync)
    nor reads out rows over time."""
    out: dict[str, tuple | None] = {}
    path, rig = scene.path, scene.rig
    v = w = None
    for side in ("left", "right"):
        cam = scene.camera(getattr(rig, side).camera)
        tau = rig.sync if side == "right" else 0.0
        if path.times is None or (tau == 0.0 and cam.readout == 0.0):
            out[side] = None
            continue
        if v is None:
            vs, ws = velocities_of(path)
            v, w = vs[index], ws[index]
        pose = path.pose(index) if tau == 0.0 else robot_at(path.pose(index), v, w, tau)
        rolling = None
        if cam.readout > 0:
            rolling = (cam.readout, float(cam.height), geometry.world_from_robot(pose)[1], v, w)
        out[side] = (pose, rolling)
    return out


_VELOCITIES: dict[int, tuple] = {}


def velocities_of(path) -> tuple[np.ndarray, np.ndarray]:
    """`velocities(path)`, computed once per path object."""
    key = id(path)
    hit = _VELOCITIES.get(key)
    if hit is None or hit[0] is not path:
        hit = _VELOCITIES[key] = (path, *velocities(path))
        if len(_VELOCITIES) > 64:
            _VELOCITIES.pop(next(iter(_VELOCITIES)))
    return hit[1], hit[2]


def moving(scene) -> bool:
    """Whether the scene's cameras see the robot's motion (a readout or a sync, on a path with times)."""
    if scene.rig is None or scene.path is None or scene.path.times is None:
        return False
    return scene.rig.sync != 0.0 or any(scene.camera(getattr(scene.rig, s).camera).readout > 0
                                        for s in ("left", "right"))

"""A trial's observations as a COLMAP text model: cameras.txt, images.txt (with 2D points), points3D.txt.

- One camera a rig side (CAMERA_ID 1 left, 2 right), the *nominal* lens in the COLMAP model that is the same
  function: radtan -> PINHOLE, OPENCV or FULL_OPENCV (the fewest coefficients that hold it), equidistant ->
  OPENCV_FISHEYE, fov -> FOV (omega = w), eucm -> EUCM, and unified without Mei's radtan -> EUCM (alpha =
  xi / (1 + xi), beta = 1, focal lengths / (1 + xi): the same projection). COLMAP has no double-sphere model
  and no unified model with distortion: those are refused (`ColmapLensError`) unless `undistort`, which writes
  a PINHOLE camera of the same fx, fy, cx, cy and each 2D point moved to where that pinhole images its ray (the
  lens's own unprojection), for any lens.
- One image a view, IMAGE_ID = 2 pose + camera + 1, named `<side>_<pose:03d>.png` (render's names), posed at
  the nominal camera pose (cam_from_world: the rig's mounts at the path's poses, the ground truth).
- Points: the scene's corners (POINT3D_ID = corner index + 1, the same in every trial, so tracks can be
  compared across trials), each with the track of the views that observed it; a corner fewer than two views
  observed is left out (one view's observation stays in images.txt with POINT3D_ID -1). ERROR is the track's
  mean distance (px) between each observation and the nominal projection.
- Times: COLMAP's model has none. When the path was read from a trajectory file with timestamps, `times.txt`
  beside the model lists each image's time as TUM RGB-D's `rgb.txt` does, `timestamp filename` a line (seconds
  on the file's clock, to the nanosecond, `observations.stamps_ns`), in IMAGE_ID order.
- Lines are not written: COLMAP's model holds points only (the ROS 2 bag carries the strokes).
- COLMAP puts the top-left pixel's centre at (0.5, 0.5), wiredsl at (0, 0): cx, cy and every 2D point are
  written half a pixel further right and down, so COLMAP's projection equals the exported points.
- Observations COLMAP cannot project (a corner behind the camera's image plane, Z <= 0, seen by a lens wider
  than 180 deg) are left out and counted in `Model.behind`.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wiredsl.files import require_finite
from wiredsl.io.observations import CAMERAS, Source, Trial

HALF_PIXEL = 0.5  # COLMAP's top-left pixel centre is (0.5, 0.5); wiredsl's is (0, 0)
MODELS = ("PINHOLE", "OPENCV", "FULL_OPENCV", "OPENCV_FISHEYE", "FOV", "EUCM")


class ColmapLensError(ValueError):
    """A lens COLMAP has no model for (without --undistort)."""


@dataclass
class Model:
    files: dict  # name -> text
    behind: int  # observations left out: behind the camera's image plane
    undistorted_out: int  # with undistort: observations whose ray left the lens's valid region


MIN_TRACK = 2  # views a 3D point needs (COLMAP's own models, and its bundle adjuster, hold no shorter track)
CHECKED_WITH = "3.8"  # the COLMAP whose model_analyzer and bundle_adjuster read these models in the tests


def colmap_camera(cam) -> tuple[str, list[float]]:
    """(COLMAP model name, params) of a wiredsl Camera with the same projection (pixel convention aside)."""
    fx, fy = cam.f * cam.ax, cam.f * cam.ay
    base = [fx, fy, cam.cx, cam.cy]
    d = cam.distortion
    if d == "radtan":
        if cam.k3 == cam.k4 == cam.k5 == cam.k6 == 0.0:
            if cam.k1 == cam.k2 == cam.p1 == cam.p2 == 0.0:
                return "PINHOLE", base
            return "OPENCV", base + [cam.k1, cam.k2, cam.p1, cam.p2]
        return "FULL_OPENCV", base + [cam.k1, cam.k2, cam.p1, cam.p2, cam.k3, cam.k4, cam.k5, cam.k6]
    if d == "equidistant":
        return "OPENCV_FISHEYE", base + [cam.k1, cam.k2, cam.k3, cam.k4]
    if d == "fov":
        return "FOV", base + [cam.w]
    if d == "eucm":
        return "EUCM", base + [cam.alpha, cam.beta]
    if d == "unified" and cam.k1 == cam.k2 == cam.p1 == cam.p2 == 0.0:
        s = 1.0 + cam.xi
        return "EUCM", [fx / s, fy / s, cam.cx, cam.cy, cam.xi / s, 1.0]
    what = "the double-sphere model" if d == "ds" else "the unified model with Mei's radtan distortion"
    raise ColmapLensError(f"camera '{cam.name}' has {what} ('{d}'), which COLMAP has no camera model for (it has "
                          f"{', '.join(MODELS)} for wiredsl's lenses): give --undistort to write a PINHOLE camera "
                          "and undistorted points, or export a ROS 2 bag (--format rosbag2)")


def _seconds(ns: int) -> str:
    """Integer nanoseconds as exact decimal seconds."""
    sign, ns = ("-", -ns) if ns < 0 else ("", ns)
    return f"{sign}{ns // 1_000_000_000}.{ns % 1_000_000_000:09d}"


def _num(x: float) -> str:
    return repr(float(x))


def model(src: Source, trial: Trial, undistort: bool = False) -> Model:
    """The COLMAP text files of one trial's views."""
    from wiredsl.engine import geometry
    from wiredsl.io.calibration_slam import _quaternion

    cams = {}
    for i, side in enumerate(CAMERAS):
        cam = src.cameras[side]
        name, params = ("PINHOLE", [cam.f * cam.ax, cam.f * cam.ay, cam.cx, cam.cy]) if undistort else \
            colmap_camera(cam)
        params = list(params)
        params[2] += HALF_PIXEL
        params[3] += HALF_PIXEL
        cams[side] = (i + 1, name, require_finite(np.array(params), f"camera {cam.name}'s parameters"))
    lines_c = ["# Camera list with one line of data per camera:",
               "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]",
               f"# Number of cameras: {len(cams)}"]
    for side in CAMERAS:
        cid, name, params = cams[side]
        cam = src.cameras[side]
        lines_c.append(" ".join([str(cid), name, str(cam.width), str(cam.height), *(_num(p) for p in params)]))

    tracks: dict[int, list[tuple[int, int]]] = {}
    errors: dict[int, list[float]] = {}
    body, behind, lost, n_obs = [], 0, 0, 0
    for v in sorted(trial.views, key=lambda v: (v.pose, CAMERAS.index(v.side))):
        cam = src.cameras[v.side]
        image_id = 2 * v.pose + CAMERAS.index(v.side) + 1
        P_cam = src.corners[v.corner] @ v.R.T + v.t if len(v.corner) else np.zeros((0, 3))
        keep = P_cam[:, 2] > 0
        behind += int((~keep).sum())
        uv = v.corner_uv
        if undistort and len(uv):
            rays, ok = geometry.pixels_to_rays(uv, cam)
            ok &= rays[:, 2] > 0
            lost += int((keep & ~ok).sum())
            keep &= ok
            z = np.where(keep, rays[:, 2], 1.0)
            uv = np.column_stack([cam.f * cam.ax * rays[:, 0] / z + cam.cx, cam.f * cam.ay * rays[:, 1] / z + cam.cy])
        if not keep.any():
            nominal = np.zeros((0, 2))
        elif undistort:  # the pinhole's projection
            X, Y, Z = P_cam[keep].T
            nominal = np.column_stack([cam.f * cam.ax * X / Z + cam.cx, cam.f * cam.ay * Y / Z + cam.cy])
        else:
            nominal = geometry.cam_to_pixels(P_cam[keep], cam)
        points = []
        for j, (pid, (u, w)) in enumerate(zip(v.corner[keep] + 1, uv[keep], strict=True)):
            tracks.setdefault(int(pid), []).append((image_id, j))
            points.append((u + HALF_PIXEL, w + HALF_PIXEL, int(pid)))
        if keep.any():
            for pid, e in zip(v.corner[keep] + 1, np.hypot(*(uv[keep] - nominal).T), strict=True):
                errors.setdefault(int(pid), []).append(float(e))
        n_obs += len(points)
        q = _quaternion(v.R)  # x, y, z, w
        q = [q[3], q[0], q[1], q[2]] if q[3] >= 0 else [-q[3], -q[0], -q[1], -q[2]]
        head = require_finite(np.array([*q, *v.t]), f"image {image_id}'s pose")
        body.append(" ".join([str(image_id), *(_num(x) for x in head), str(cams[v.side][0]),
                              f"{v.side}_{v.pose:03d}.png"]))
        flat = require_finite(np.array([(u, w) for u, w, _ in points]).reshape(-1, 2), f"image {image_id}'s points")
        body.append((flat, points))
    # a corner seen in one view only is no 3D point (COLMAP's models never hold one: bundle_adjuster asserts a
    # track of at least 2); its observation stays a 2D point with POINT3D_ID -1, so the indexes hold
    single = {pid for pid, t in tracks.items() if len(t) < MIN_TRACK}
    for pid in single:
        del tracks[pid]
    body = [line if isinstance(line, str) else
            " ".join(f"{_num(u)} {_num(w)} {-1 if pid in single else pid}"
                     for (u, w), (_, _, pid) in zip(*line, strict=True)) for line in body]
    n_images = len(body) // 2
    lines_i = ["# Image list with two lines of data per image:",
               "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME",
               "#   POINTS2D[] as (X, Y, POINT3D_ID)",
               f"# Number of images: {n_images}, mean observations per image: "
               f"{n_obs / n_images if n_images else 0:g}"] + body

    lines_p = ["# 3D point list with one line of data per point:",
               "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)",
               f"# Number of points: {len(tracks)}, mean track length: "
               f"{sum(map(len, tracks.values())) / len(tracks) if tracks else 0:g}"]
    for pid in sorted(tracks):
        X = require_finite(src.corners[pid - 1], f"corner {src.corner_names[pid - 1]}")
        err = float(np.mean(errors[pid])) if pid in errors else 0.0
        lines_p.append(" ".join([str(pid), *(_num(x) for x in X), "255 255 255", _num(err),
                                 *(f"{i} {j}" for i, j in tracks[pid])]))
    named = [("cameras.txt", lines_c), ("images.txt", lines_i), ("points3D.txt", lines_p)]
    if src.stamps_ns is not None:
        views = sorted((2 * v.pose + CAMERAS.index(v.side) + 1, v) for v in trial.views)
        named.append(("times.txt", ["# image times on the trajectory file's clock (seconds), as TUM's rgb.txt",
                                    "# timestamp filename"] +
                      [f"{_seconds(src.stamps_ns[v.pose])} {v.side}_{v.pose:03d}.png" for _, v in views]))
    files = {name: "\n".join(lines) + "\n" for name, lines in named}
    return Model(files, behind, lost)

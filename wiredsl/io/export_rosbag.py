"""A trial's observations as a ROS 2 bag (rosbag2, sqlite3 storage, CDR), written by the `rosbags` library.

Pose i of the path is stamped with its time on the trajectory file's clock when the path was read from a file
with timestamps (`observations.stamps_ns`: the file's own nanoseconds, so the bag lines up with the dataset's
ground truth and images), else START + i * period. Topics (frames: `world`, `base_link`, `left_camera`,
`right_camera`, the cameras' frames in ROS's optical convention, x right, y down, z forward, as wiredsl's):

| topic | type | what |
|---|---|---|
| `/tf_static` | tf2_msgs/msg/TFMessage | base_link -> left_camera, right_camera: the rig's mounts (once) |
| `/tf` | tf2_msgs/msg/TFMessage | world -> base_link: the robot's path pose (ground truth), each pose |
| `/<side>/camera_info` | sensor_msgs/msg/CameraInfo | the nominal camera, each pose |
| `/<side>/corners` | sensor_msgs/msg/PointCloud | the corners the view saw, VINS-Mono's feature layout |
| `/<side>/strokes` | wiredsl_msgs/msg/Strokes | the lines, polylines, ellipses and silhouettes as polylines |
| `/wiredsl/landmarks` | sensor_msgs/msg/PointCloud | the scene's corners in the world frame, channel `id` (once) |

Corners: a point (x, y, 1) a corner, its ray by the nominal camera's unprojection on the z = 1 plane, with
channels `id_of_point` (the corner's index + 1: COLMAP's POINT3D_ID and the landmarks' `id`), `u_of_point`,
`v_of_point` (pixels, float32) and `velocity_x`, `velocity_y` (0): what VINS-Mono's feature tracker publishes.
A corner whose ray does not meet the z = 1 plane (a lens wider than 180 deg) is left out.
"""

from __future__ import annotations

import os
import sqlite3
from pathlib import Path

import numpy as np

from wiredsl.files import require_finite
from wiredsl.io.observations import CAMERAS, Source, Trial

START_NS = 1_000_000_000  # pose 0's stamp: 1 s (0 is "no time" to tf2)
MAX_SEC = 2**31 - 1  # builtin_interfaces/Time's sec is an int32
STROKE_MSG = """\
# wiredsl_msgs/msg/Stroke: one feature's image in one view, a polyline in pixels
string feature      # placement.feature, as the scene names it
int32 segment       # polyline segment, or silhouette side (0, 1); -1 when none
uint8 kind          # 0 straight (a line segment: its two end points), 1 curve (a line under distortion), 2 ellipse
bool closed         # the last vertex joins the first (a whole ellipse)
float64[] u         # the vertices, pixels (origin at the top-left pixel's centre)
float64[] v
"""
STROKES_MSG = """\
# wiredsl_msgs/msg/Strokes: every stroke of one view
std_msgs/Header header
wiredsl_msgs/msg/Stroke[] strokes
"""
TYPES = {"wiredsl_msgs/msg/Stroke": STROKE_MSG, "wiredsl_msgs/msg/Strokes": STROKES_MSG}


def typestore():
    """The ROS 2 Humble types with wiredsl's two messages registered (a reader registers them the same way)."""
    from rosbags.typesys import Stores, get_types_from_msg, get_typestore

    store = get_typestore(Stores.ROS2_HUMBLE)
    for name, text in TYPES.items():
        store.register(get_types_from_msg(text, name))
    return store


def distortion(cam) -> tuple[str, list[float]]:
    """CameraInfo's distortion_model and d of a camera: plumb_bob, rational_polynomial and equidistant as ROS
    names them; the wide-angle models ROS has no name for under wiredsl's: unified (xi, k1, k2, p1, p2),
    eucm (alpha, beta), ds (xi, alpha), fov (w)."""
    from wiredsl.io.calibration import distortion_vector

    d = cam.distortion
    if d == "radtan":
        v = distortion_vector(cam).tolist()
        return ("rational_polynomial" if len(v) == 8 else "plumb_bob"), v
    if d == "equidistant":
        return "equidistant", distortion_vector(cam).tolist()
    return d, {"unified": [cam.xi, cam.k1, cam.k2, cam.p1, cam.p2], "eucm": [cam.alpha, cam.beta],
               "ds": [cam.xi, cam.alpha], "fov": [cam.w]}[d]


def _stamp(store, ns: int):
    return store.types["builtin_interfaces/msg/Time"](sec=ns // 1_000_000_000, nanosec=ns % 1_000_000_000)


def _header(store, ns: int, frame: str):
    return store.types["std_msgs/msg/Header"](stamp=_stamp(store, ns), frame_id=frame)


def _transform(store, ns: int, parent: str, child: str, R: np.ndarray, t: np.ndarray):
    from wiredsl.io.calibration_slam import _quaternion

    T = store.types
    x, y, z, w = _quaternion(R)
    t = require_finite(np.asarray(t, dtype=float), f"{parent} -> {child}")
    return T["geometry_msgs/msg/TransformStamped"](
        header=_header(store, ns, parent), child_frame_id=child,
        transform=T["geometry_msgs/msg/Transform"](
            translation=T["geometry_msgs/msg/Vector3"](x=float(t[0]), y=float(t[1]), z=float(t[2])),
            rotation=T["geometry_msgs/msg/Quaternion"](x=x, y=y, z=z, w=w)))


def camera_info(store, cam, ns: int, frame: str):
    model, d = distortion(cam)
    K = [cam.f * cam.ax, 0.0, cam.cx, 0.0, cam.f * cam.ay, cam.cy, 0.0, 0.0, 1.0]
    P = [K[0], 0.0, K[2], 0.0, 0.0, K[4], K[5], 0.0, 0.0, 0.0, 1.0, 0.0]
    T = store.types
    return T["sensor_msgs/msg/CameraInfo"](
        header=_header(store, ns, frame), height=int(cam.height), width=int(cam.width), distortion_model=model,
        d=require_finite(np.array(d, dtype=float), f"camera {cam.name}'s distortion"),
        k=np.array(K), r=np.eye(3).ravel(), p=np.array(P), binning_x=0, binning_y=0,
        roi=T["sensor_msgs/msg/RegionOfInterest"](x_offset=0, y_offset=0, height=0, width=0, do_rectify=False))


def _cloud(store, ns: int, frame: str, xyz: np.ndarray, channels: dict):
    T = store.types
    pts = [T["geometry_msgs/msg/Point32"](x=float(a), y=float(b), z=float(c))
           for a, b, c in require_finite(np.asarray(xyz, dtype=float).reshape(-1, 3), f"{frame} points",
                                         np.float32)]
    chans = [T["sensor_msgs/msg/ChannelFloat32"](name=n, values=require_finite(np.asarray(v, dtype=float),
                                                                                f"{frame} {n}", np.float32))
             for n, v in channels.items()]
    return T["sensor_msgs/msg/PointCloud"](header=_header(store, ns, frame), points=pts, channels=chans)


def corner_cloud(store, src: Source, view, ns: int) -> tuple[object, int]:
    """The view's corners as VINS-Mono's PointCloud, and how many were left out (no ray in front)."""
    from wiredsl.engine import geometry

    cam = src.cameras[view.side]
    uv = view.corner_uv
    if len(uv):
        rays, ok = geometry.pixels_to_rays(uv, cam)
        ok &= rays[:, 2] > 0
    else:
        rays, ok = np.zeros((0, 3)), np.zeros(0, dtype=bool)
    z = np.where(ok, rays[:, 2], 1.0)
    xyz = np.column_stack([rays[:, 0] / z, rays[:, 1] / z, np.ones(len(rays))])[ok]
    n = int(ok.sum())
    return _cloud(store, ns, f"{view.side}_camera", xyz, {
        "id_of_point": view.corner[ok] + 1, "u_of_point": uv[ok, 0], "v_of_point": uv[ok, 1],
        "velocity_x": np.zeros(n), "velocity_y": np.zeros(n)}), len(uv) - n


def strokes(store, src: Source, view, ns: int):
    T = store.types
    out = [T["wiredsl_msgs/msg/Stroke"](feature=src.feature_ids[fid], segment=seg, kind=kind, closed=closed,
                                         u=require_finite(pts[:, 0].copy(), "a stroke"),
                                         v=require_finite(pts[:, 1].copy(), "a stroke"))
           for fid, seg, kind, closed, pts in view.strokes]
    return T["wiredsl_msgs/msg/Strokes"](header=_header(store, ns, f"{view.side}_camera"), strokes=out)


def write(path: Path, src: Source, trial: Trial, period_ns: int) -> int:
    """Write one trial's bag at `path` (which must not exist); the number of corners left out."""
    from rosbags.rosbag2 import Writer

    store = typestore()
    stamp = stamps(src, period_ns)
    check_stamps(stamp.values())
    try:
        return _write(path, src, trial, stamp, store, Writer)
    except sqlite3.Error as exc:  # the bag's storage: a full disk, a read-only folder
        import errno

        full = "full" in str(exc).lower()
        raise OSError(errno.ENOSPC if full else errno.EIO, os.strerror(errno.ENOSPC) if full else f"sqlite3: {exc}",
                      str(path)) from None


def stamps(src: Source, period_ns: int) -> dict[int, int]:
    """Each pose's stamp (ns): the trajectory's, or 1 s + pose x period."""
    return {p: src.stamps_ns[p] if src.stamps_ns is not None else START_NS + p * period_ns for p in src.poses}


def check_stamps(stamps) -> None:
    """ValueError unless every stamp (ns) fits a ROS 2 Time, whose sec is an int32 (up to 2038-01-19 03:14:07)."""
    secs = [ns // 1_000_000_000 for ns in stamps]
    bad = [s for s in secs if not -MAX_SEC - 1 <= s <= MAX_SEC]
    if bad:
        raise ValueError(f"a pose stamped {bad[0]} s does not fit a ROS 2 Time (its seconds are an int32: at most "
                         f"{MAX_SEC} s, 2038-01-19 03:14:07 UTC); shift the trajectory's times or shorten --period")


def _write(path: Path, src: Source, trial: Trial, stamp: dict, store, Writer) -> int:
    left_out = 0
    with Writer(path, version=9) as writer:
        conns = {}

        def put(topic: str, msgtype: str, ns: int, msg) -> None:
            if topic not in conns:
                conns[topic] = writer.add_connection(topic, msgtype, typestore=store)
            writer.write(conns[topic], ns, store.serialize_cdr(msg, msgtype))

        first = stamp[src.poses[0]]
        mounts = [_transform(store, first, "base_link", f"{side}_camera", *src.mounts[side]) for side in CAMERAS]
        put("/tf_static", "tf2_msgs/msg/TFMessage", first, store.types["tf2_msgs/msg/TFMessage"](transforms=mounts))
        put("/wiredsl/landmarks", "sensor_msgs/msg/PointCloud", first,
            _cloud(store, first, "world", src.corners, {"id": np.arange(1, len(src.corners) + 1)}))
        views = {(v.pose, v.side): v for v in trial.views}
        for p in src.poses:
            ns = stamp[p]
            R, t = src.robot[p]
            put("/tf", "tf2_msgs/msg/TFMessage", ns,
                store.types["tf2_msgs/msg/TFMessage"](transforms=[_transform(store, ns, "world", "base_link", R, t)]))
            for side in CAMERAS:
                put(f"/{side}/camera_info", "sensor_msgs/msg/CameraInfo", ns,
                    camera_info(store, src.cameras[side], ns, f"{side}_camera"))
                v = views.get((p, side))
                if v is None:
                    continue
                cloud, lost = corner_cloud(store, src, v, ns)
                left_out += lost
                put(f"/{side}/corners", "sensor_msgs/msg/PointCloud", ns, cloud)
                put(f"/{side}/strokes", "wiredsl_msgs/msg/Strokes", ns, strokes(store, src, v, ns))
    return left_out

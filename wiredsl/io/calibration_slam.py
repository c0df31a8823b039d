"""Calibration files of visual-inertial SLAM tools: camodocal's YAML (VINS-Mono / VINS-Fusion: PINHOLE, MEI,
KANNALA_BRANDT) and basalt's calibration JSON (cereal: pinhole, pinhole-radtan8, kb4, ucm, eucm, ds, fov); read
into `camera_file.CameraFile`s and written back (with Kalibr camchains) by `rig_files`.

Conventions, from the tools' sources:
- camodocal MEI: m = (x, y) / (z + xi d), then radtan k1, k2, p1, p2 on m, u = gamma1 m_x + u0 (wiredsl's unified);
  KANNALA_BRANDT: theta_d = theta + k2 theta^3 + k3 theta^5 + k4 theta^7 + k5 theta^9, u = mu x + u0 (wiredsl's
  equidistant with k1..k4 = k2..k5; camodocal's writer puts k2..k5 under projection_parameters, other tools under
  distortion_parameters: both are read).
- basalt ucm: m = (x, y) / (alpha d + (1 - alpha) z) with its own fx: Mei's xi = alpha / (1 - alpha) and
  fx_mei = fx / (1 - alpha); T_imu_cam[i] maps camera i's points into the IMU frame (p, q: x y z w).
"""

from __future__ import annotations

import json
import math

import numpy as np

from wiredsl.io.camera_file import (
    SUPPORTED,
    CalibrationFileError,
    CameraFile,
    _intrinsics,
    _kind,
    _num,
    _with_pose,
)

CAMODOCAL = ("PINHOLE", "MEI", "KANNALA_BRANDT")
BASALT = ("pinhole", "pinhole-radtan8", "kb4", "ucm", "eucm", "ds", "fov")


def is_camodocal(doc: dict) -> bool:
    return "model_type" in doc and any(k in doc for k in ("projection_parameters", "distortion_parameters"))


def is_basalt(doc: dict) -> bool:
    v = doc.get("value0")
    return isinstance(v, dict) and "intrinsics" in v


def _block(doc: dict, key: str) -> dict:
    v = doc.get(key, {})
    if not isinstance(v, dict):
        raise CalibrationFileError(f"{key} must be a mapping of names to numbers, is {_kind(v)}")
    return v


def _values(block: dict, names, what: str, default=None) -> list[float]:
    out = []
    for n in names:
        if n not in block and default is None:
            raise CalibrationFileError(f"no '{n}' in {what}")
        out.append(_num(block.get(n, default), f"{what}: {n}"))
    return out


def camodocal(doc: dict) -> list[CameraFile]:
    """One camodocal camera (model_type PINHOLE, MEI or KANNALA_BRANDT)."""
    kind = doc.get("model_type")
    if kind not in CAMODOCAL:
        raise CalibrationFileError(f"camodocal model_type '{kind}' is not supported: wiredsl reads camodocal's "
                                   f"{', '.join(CAMODOCAL)}; {SUPPORTED}")
    name = doc.get("camera_name") if isinstance(doc.get("camera_name"), str) else "camera"
    size = [doc.get("image_width"), doc.get("image_height")] if "image_width" in doc else None
    proj, dist = _block(doc, "projection_parameters"), _block(doc, "distortion_parameters")
    if kind == "PINHOLE":
        fx, fy, cx, cy = _values(proj, ("fx", "fy", "cx", "cy"), "projection_parameters")
        D, model = _values(dist, ("k1", "k2", "p1", "p2"), "distortion_parameters", 0.0), "radtan"
    elif kind == "MEI":
        fx, fy, cx, cy = _values(proj, ("gamma1", "gamma2", "u0", "v0"), "projection_parameters")
        xi = _values(_block(doc, "mirror_parameters"), ("xi",), "mirror_parameters")
        D, model = xi + _values(dist, ("k1", "k2", "p1", "p2"), "distortion_parameters", 0.0), "unified"
    else:
        fx, fy, cx, cy = _values(proj, ("mu", "mv", "u0", "v0"), "projection_parameters")
        both = {**dist, **proj}
        D, model = _values(both, ("k2", "k3", "k4", "k5"), "KANNALA_BRANDT's parameters", 0.0), "equidistant"
    return [_intrinsics(name, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], D, size, model)]


def basalt(doc: dict) -> list[CameraFile]:
    """basalt's calibration: value0.intrinsics[i] ({camera_type, intrinsics}), resolution[i], T_imu_cam[i]."""
    v = doc["value0"]
    intr = v.get("intrinsics")
    if not isinstance(intr, list) or not intr:
        raise CalibrationFileError("value0.intrinsics must be a list of cameras")
    res, poses = v.get("resolution", []), v.get("T_imu_cam", [])
    out, T_imu = [], []
    for i, c in enumerate(intr):
        name = f"cam{i}"
        if not isinstance(c, dict) or not isinstance(c.get("intrinsics"), dict):
            raise CalibrationFileError(f"value0.intrinsics[{i}] must hold camera_type and intrinsics")
        kind, p = c.get("camera_type"), c["intrinsics"]
        if kind not in BASALT:
            raise CalibrationFileError(f"{name}: basalt camera_type '{kind}' is not supported: wiredsl reads basalt's "
                                       f"{', '.join(BASALT)}; {SUPPORTED}")
        fx, fy, cx, cy = _values(p, ("fx", "fy", "cx", "cy"), f"{name}'s intrinsics")
        if kind == "pinhole":
            model, D = "radtan", None
        elif kind == "pinhole-radtan8":
            model, D = "radtan", _values(p, ("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), f"{name}'s intrinsics")
        elif kind == "kb4":
            model, D = "equidistant", _values(p, ("k1", "k2", "k3", "k4"), f"{name}'s intrinsics")
        elif kind == "ucm":
            (alpha,) = _values(p, ("alpha",), f"{name}'s intrinsics")
            if not 0 <= alpha < 1:
                raise CalibrationFileError(f"{name}: basalt's ucm alpha must be in [0, 1), is {alpha:g}")
            model, D = "unified", [alpha / (1 - alpha), 0.0, 0.0, 0.0, 0.0]
            fx, fy = fx / (1 - alpha), fy / (1 - alpha)
        else:
            model = kind
            D = _values(p, {"eucm": ("alpha", "beta"), "ds": ("xi", "alpha"), "fov": ("w",)}[kind],
                        f"{name}'s intrinsics")
        size = res[i] if i < len(res) else None
        cam = _intrinsics(name, [[fx, 0, cx], [0, fy, cy], [0, 0, 1]], D, size, model)
        T_imu.append(_pose(poses[i], f"value0.T_imu_cam[{i}]") if i < len(poses) else None)
        if i > 0 and T_imu[i] is not None and T_imu[i - 1] is not None:
            M = np.linalg.inv(T_imu[i]) @ T_imu[i - 1]  # previous camera -> IMU -> this camera
            cam = _with_pose(cam, M[:3, :3], M[:3, 3], f"T_imu_cam of cam{i - 1} and {name}")
        out.append(cam)
    return out


def _pose(p, what: str) -> np.ndarray:
    if not isinstance(p, dict):
        raise CalibrationFileError(f"{what} must be a mapping px, py, pz, qx, qy, qz, qw")
    px, py, pz, qx, qy, qz, qw = _values(p, ("px", "py", "pz", "qx", "qy", "qz", "qw"), what)
    n = math.sqrt(qx * qx + qy * qy + qz * qz + qw * qw)
    if abs(n - 1) > 1e-3:
        raise CalibrationFileError(f"{what}: the quaternion's norm is {n:.6g}, not 1")
    x, y, z, w = qx / n, qy / n, qz / n, qw / n
    M = np.eye(4)
    M[:3, :3] = [[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                 [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                 [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]]
    M[:3, 3] = [px, py, pz]
    return M


# --------------------------------------------------------------------------- writing

def _numbers(c) -> dict:
    return {"fx": c.f * c.ax, "fy": c.f * c.ay, "cx": c.cx, "cy": c.cy}


def camodocal_yaml(name: str, c) -> str | None:
    """A camera as camodocal writes it (PINHOLE for radtan with k1, k2, p1, p2 only; MEI; KANNALA_BRANDT), or None
    for a lens camodocal has no model for."""
    n = _numbers(c)
    head = ["%YAML:1.0", "---"]
    if c.distortion == "radtan" and (c.k3, c.k4, c.k5, c.k6) == (0, 0, 0, 0):
        body = ["model_type: PINHOLE", f"camera_name: {name}", f"image_width: {c.width}", f"image_height: {c.height}",
                "distortion_parameters:", *_items(k1=c.k1, k2=c.k2, p1=c.p1, p2=c.p2),
                "projection_parameters:", *_items(**n)]
    elif c.distortion == "unified":
        body = ["model_type: MEI", f"camera_name: {name}", f"image_width: {c.width}", f"image_height: {c.height}",
                "mirror_parameters:", *_items(xi=c.xi), "distortion_parameters:",
                *_items(k1=c.k1, k2=c.k2, p1=c.p1, p2=c.p2), "projection_parameters:",
                *_items(gamma1=n["fx"], gamma2=n["fy"], u0=c.cx, v0=c.cy)]
    elif c.distortion == "equidistant":
        body = ["model_type: KANNALA_BRANDT", f"camera_name: {name}", f"image_width: {c.width}",
                f"image_height: {c.height}", "projection_parameters:",
                *_items(k2=c.k1, k3=c.k2, k4=c.k3, k5=c.k4, mu=n["fx"], mv=n["fy"], u0=c.cx, v0=c.cy)]
    else:
        return None
    return "\n".join(head + body) + "\n"


def _items(**kv) -> list[str]:
    return [f"   {k}: {float(v)!r}" for k, v in kv.items()]


def basalt_json(cams: list, poses: list[np.ndarray]) -> str:
    """basalt's calibration JSON of cameras with their T_imu_cam (4x4, camera points into the rig's frame)."""
    intr = []
    for c in cams:
        p = _numbers(c)
        if c.distortion == "radtan":
            rad = (c.k1, c.k2, c.p1, c.p2, c.k3, c.k4, c.k5, c.k6)
            kind = "pinhole-radtan8" if any(rad) else "pinhole"
            if any(rad):
                p.update(zip(("k1", "k2", "p1", "p2", "k3", "k4", "k5", "k6"), rad, strict=True))
        elif c.distortion == "equidistant":
            kind = "kb4"
            p.update(k1=c.k1, k2=c.k2, k3=c.k3, k4=c.k4)
        elif c.distortion == "unified" and not any((c.k1, c.k2, c.p1, c.p2)):  # basalt's ucm: no radtan
            kind, alpha = "ucm", c.xi / (1 + c.xi)
            p = {"fx": p["fx"] * (1 - alpha), "fy": p["fy"] * (1 - alpha), "cx": c.cx, "cy": c.cy, "alpha": alpha}
        elif c.distortion == "unified":
            raise CalibrationFileError("basalt's ucm has no radtan: a unified camera with k1, k2, p1, p2 cannot be "
                                       "written as basalt's")
        else:
            kind = c.distortion
            p.update({k: getattr(c, k) for k in {"eucm": ("alpha", "beta"), "ds": ("xi", "alpha"),
                                                  "fov": ("w",)}[kind]})
        intr.append({"camera_type": kind, "intrinsics": {k: float(v) for k, v in p.items()}})
    T = []
    for M in poses:
        q = _quaternion(M[:3, :3])
        T.append({"px": float(M[0, 3]), "py": float(M[1, 3]), "pz": float(M[2, 3]),
                  "qx": q[0], "qy": q[1], "qz": q[2], "qw": q[3]})
    doc = {"value0": {"T_imu_cam": T, "intrinsics": intr, "resolution": [[c.width, c.height] for c in cams]}}
    return json.dumps(doc, indent=4) + "\n"


def _quaternion(R: np.ndarray) -> list[float]:
    from scipy.spatial.transform import Rotation

    return [float(x) for x in Rotation.from_matrix(R).as_quat()]  # x, y, z, w


def kalibr_yaml(cams: list, T_cn_cnm1: list[np.ndarray | None]) -> str:
    """A Kalibr camchain: each camera's camera_model, intrinsics, distortion and resolution, and T_cn_cnm1."""
    lines = []
    for i, (c, M) in enumerate(zip(cams, T_cn_cnm1, strict=True)):
        n = _numbers(c)
        base = [n["fx"], n["fy"], c.cx, c.cy]
        model, dmodel, lead, d = {
            "radtan": ("pinhole", "radtan", [], [c.k1, c.k2, c.p1, c.p2]),
            "equidistant": ("pinhole", "equidistant", [], [c.k1, c.k2, c.k3, c.k4]),
            "unified": ("omni", "radtan", [c.xi], [c.k1, c.k2, c.p1, c.p2]),
            "eucm": ("eucm", "none", [c.alpha, c.beta], []),
            "ds": ("ds", "none", [c.xi, c.alpha], []),
            "fov": ("pinhole", "fov", [], [c.w])}[c.distortion]
        if c.distortion == "radtan" and any((c.k3, c.k4, c.k5, c.k6)):
            raise CalibrationFileError("Kalibr's radtan has k1, k2, p1, p2 only: a camera with k3..k6 cannot be "
                                       "written as Kalibr's")
        lines += [f"cam{i}:"]
        if M is not None:
            lines += ["  T_cn_cnm1:"] + [f"  - [{', '.join(repr(float(x)) for x in row)}]" for row in M]
        lines += [f"  camera_model: {model}", f"  distortion_coeffs: [{', '.join(repr(float(x)) for x in d)}]",
                  f"  distortion_model: {dmodel}",
                  f"  intrinsics: [{', '.join(repr(float(x)) for x in lead + base)}]",
                  f"  resolution: [{c.width}, {c.height}]"]
    return "\n".join(lines) + "\n"

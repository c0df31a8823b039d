"""One camera as a calibration file describes it (`CameraFile`), and the checked reading of a file's values into
it, shared by the readers of calibration.py (OpenCV, ROS, Kalibr, ORB-SLAM) and calibration_slam.py (camodocal,
basalt): numbers finite and bounded, K unskewed, a supported distortion model, R a rotation."""

from __future__ import annotations

import re
from dataclasses import dataclass, field, replace

import numpy as np

MAX_VALUE = 1e12  # any number a calibration file gives: products of a few stay far from overflow
MIN_FOCAL = 1e-6  # px: a focal length below is no camera, and its square underflows
RADTAN = ("plumb_bob", "radtan", "rational_polynomial", "pinhole", "none")
EQUIDISTANT = ("equidistant", "fisheye", "kannalabrandt8", "kannala_brandt", "kb4")
WIDE = ("unified", "eucm", "ds", "fov")  # wiredsl's wide-angle models; a CameraFile's dist is MODEL_KEYS' order
WIDE_KEYS = {"unified": ("xi", "k1", "k2", "p1", "p2"), "eucm": ("alpha", "beta"), "ds": ("xi", "alpha"), "fov": ("w",)}
SUPPORTED = ("wiredsl's lens models are pinhole with radtan distortion (plumb_bob, rational_polynomial, radtan8), "
             "equidistant (Kannala-Brandt: kb4, KANNALA_BRANDT, KannalaBrandt8), unified (Mei: omni, MEI, ucm), "
             "eucm (extended unified), ds (double sphere) and fov (ATAN)")


class CalibrationFileError(ValueError):
    """A calibration file that cannot be used, with a message for a diagnostic."""


@dataclass(frozen=True)
class CameraFile:
    """One camera as a calibration file describes it."""

    name: str
    fx: float
    fy: float
    cx: float
    cy: float
    dist: tuple[float, ...]  # radtan: OpenCV's (k1, k2, p1, p2, k3, k4, k5, k6); equidistant: (k1, k2, k3, k4);
    # the others: WIDE_KEYS' numbers (unified: xi, k1, k2, p1, p2)
    width: int | None
    height: int | None
    R: np.ndarray | None = None  # (3, 3): from the previous camera's frame to this one's, X = R X_prev + T
    T: np.ndarray | None = None  # (3,) in the file's units (metres for Kalibr and ROS)
    sigma: dict[str, float] = field(default_factory=dict)  # standard deviations, by wiredsl parameter name
    model: str = "radtan"  # or "equidistant", "unified", "eucm", "ds", "fov" (geometry.MODELS)
    notes: tuple[str, ...] = ()  # doubts about the file, for a warning
    intrinsics: bool = True  # False for an extrinsics-only file (stereo_calib's extrinsics.yml)
    error: str | None = None  # why this camera of a stereo file cannot be read (said where it is read, once)
    pose_notes: tuple[str, ...] = ()  # doubts about R, T: warned at the rig's `relative`, not at the camera


def _kind(v) -> str:
    if isinstance(v, dict):
        return "a mapping"
    if isinstance(v, list | tuple):
        return "a list"
    if isinstance(v, str):
        return "text"
    if v is None:
        return "nothing"
    if isinstance(v, bool):
        return "a yes/no value"
    return "a number" if isinstance(v, int | float) else type(v).__name__


def _matrix(m: dict, what: str) -> np.ndarray:
    """A {rows, cols, data[, dt]} node (OpenCV's or ROS's) as an array, or an error naming `what`."""
    rows, cols, data = m.get("rows"), m.get("cols"), m.get("data")
    try:
        rows, cols = _count(rows), _count(cols)
    except CalibrationFileError:
        raise CalibrationFileError(f"{what}: a matrix needs whole 'rows' and 'cols'") from None
    channels = re.match(r"\s*(\d*)", str(m.get("dt", ""))).group(1)
    n = rows * cols * (int(channels) if channels and int(channels) < 8 else 1)
    if isinstance(data, str):
        data = data.split()
    if not isinstance(data, list):
        raise CalibrationFileError(f"{what}: a matrix's data must be a list of numbers, is {_kind(data)}")
    a = _floats(data, what)
    if a.size != n or n == 0:
        raise CalibrationFileError(f"{what}: a {rows}x{cols} matrix needs {n} values, not {a.size}")
    if str(m.get("dt", "")).strip().endswith("f"):  # single precision: the values OpenCV (and the tool) see
        a = a.astype(np.float32).astype(float)
    return a.reshape(rows, cols, -1) if n != rows * cols else a.reshape(rows, cols)


def _count(v) -> int:
    if isinstance(v, bool) or not isinstance(v, int | float | str):
        raise CalibrationFileError("not a count")
    try:
        f = float(v)
    except ValueError:
        raise CalibrationFileError("not a count") from None
    if not (f.is_integer() and 0 < f <= 1e6):
        raise CalibrationFileError("not a count")
    return int(f)


def _floats(v, what: str, n: int | None = None) -> np.ndarray:
    """A flat float array from a matrix node or a (nested) list of numbers, finite, optionally of n values."""
    if isinstance(v, dict):
        v = _matrix(v, what)
    elif isinstance(v, int | float) and not isinstance(v, bool):
        v = [v]
    ok = isinstance(v, np.ndarray) or (isinstance(v, list) and _numbers(v))
    if not ok:
        raise CalibrationFileError(f"{what} must be numbers, is {_kind(v)}")
    a = np.asarray(v, dtype=float).ravel()
    if n is not None and a.size != n:
        raise CalibrationFileError(f"{what} must have {n} values, not {a.size}")
    if not np.all(np.isfinite(a)):
        raise CalibrationFileError(f"{what} has a value that is not finite")
    if a.size and np.abs(a).max() > MAX_VALUE:
        raise CalibrationFileError(f"{what} has a value beyond {MAX_VALUE:g} (|{np.abs(a).max():g}|)")
    return a


def _numbers(v: list, depth: int = 0) -> bool:
    """A list of numbers, or of equal-length lists of numbers (a matrix written as rows)."""
    if depth > 2:
        return False
    if all(isinstance(x, int | float | str) and not isinstance(x, bool) for x in v):
        try:
            [float(x) for x in v]
        except ValueError:
            return False
        return True
    return (all(isinstance(x, list) for x in v) and len({len(x) for x in v}) == 1
            and all(_numbers(x, depth + 1) for x in v))


def _num(v, what: str) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise CalibrationFileError(f"{what} must be a number, is {_kind(v)}")
    return float(_floats([v], what)[0])


def _intrinsics(name: str, K, D, size, model: str = "plumb_bob") -> CameraFile:
    K = _floats(K, f"{name}: the camera matrix", 9).reshape(3, 3)
    if K[0, 1] != 0:
        raise CalibrationFileError(f"{name}: skewed camera matrices are not supported (K[0,1] = {K[0, 1]:g}, "
                                   "must be 0)")
    if K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise CalibrationFileError(f"{name}: the camera matrix must be [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]")
    if not (K[0, 0] >= MIN_FOCAL and K[1, 1] >= MIN_FOCAL):
        raise CalibrationFileError(f"{name}: the focal lengths fx, fy must be at least {MIN_FOCAL:g} px, are "
                                   f"{K[0, 0]:g}, {K[1, 1]:g}")
    kind, dist = _distortion(name, D, model)
    return CameraFile(name, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]), dist, *_size(name, size),
                      model=kind)


def _distortion(name: str, D, model) -> tuple[str, tuple[float, ...]]:
    """(model, coefficients): radtan as OpenCV's 8-vector, equidistant as (k1, k2, k3, k4)."""
    if not isinstance(model, str):
        raise CalibrationFileError(f"{name}: the distortion model must be a name, is {_kind(model)}")
    m = model.strip().lower()
    d = _floats(D, f"{name}: the distortion coefficients") if D is not None else np.zeros(0)
    if m in WIDE:
        want = len(WIDE_KEYS[m])
        if d.size != want:
            raise CalibrationFileError(f"{name}: the {m} model has {want} numbers ({', '.join(WIDE_KEYS[m])}), "
                                       f"the file has {d.size}")
        return m, tuple(float(x) for x in d)
    if m in EQUIDISTANT:
        if d.size > 4:
            raise CalibrationFileError(f"{name}: an equidistant (fisheye) lens has 4 coefficients k1..k4, "
                                       f"the file has {d.size}")
        return "equidistant", tuple(float(x) for x in np.pad(d, (0, 4 - d.size)))
    if m not in RADTAN:
        raise CalibrationFileError(f"{name}: distortion model '{model}' is not supported: {SUPPORTED}")
    if d.size > 14 or d.size not in (0, 1, 2, 3, 4, 5, 8, 12, 14):
        raise CalibrationFileError(f"{name}: OpenCV's distortion vector has 4, 5, 8, 12 or 14 values, the file "
                                   f"has {d.size}")
    if np.any(d[8:12] != 0):
        raise CalibrationFileError(f"{name}: thin-prism distortion (s1..s4 = {_list(d[8:12])}) is not supported; "
                                   "recalibrate without CALIB_THIN_PRISM_MODEL")
    if np.any(d[12:14] != 0):
        raise CalibrationFileError(f"{name}: tilted-sensor distortion (taux, tauy = {_list(d[12:14])}) is not "
                                   "supported; recalibrate without CALIB_TILTED_MODEL")
    return "radtan", tuple(float(x) for x in np.pad(d[:8], (0, max(0, 8 - d.size))))


def _list(a) -> str:
    return ", ".join(f"{x:g}" for x in a)


def _size(name: str, size) -> tuple[int | None, int | None]:
    if size is None:
        return None, None
    w, h = _floats(size, f"{name}: the image size", 2)
    if not (w > 0 and h > 0 and w.is_integer() and h.is_integer() and max(w, h) <= 1e9):
        raise CalibrationFileError(f"{name}: the image size must be whole pixels > 0, is {w:g} x {h:g}")
    return int(w), int(h)


ROTATION_ROUNDED = 1e-4  # R R^T - I beyond this (R written with under 4 digits) is W143; below, rounding is mended


def _with_pose(cam: CameraFile, R, T, what: str = "R and T") -> CameraFile:
    R = _floats(R, f"{cam.name}: the rotation", 9).reshape(3, 3)
    T = _floats(T, f"{cam.name}: the translation", 3)
    off = float(np.abs(R @ R.T - np.eye(3)).max())
    if off > 1e-3 or np.linalg.det(R) < 0:
        raise CalibrationFileError(f"{cam.name}: {what}: R is not a rotation matrix (R R^T must be I and "
                                   "det R = 1, to 1e-3)")
    notes = cam.pose_notes
    if off > 1e-12:  # values rounded to a few digits (OpenVINS' KAIST file has 5): the nearest rotation
        U, _, Vt = np.linalg.svd(R)
        R = U @ Vt
    if off > ROTATION_ROUNDED:  # fewer than 4 digits: the nearest rotation differs by more than rounding's 1e-4
        notes += (f"{what} (the pose of {cam.name} relative to the camera before it): R is a rotation only to "
                  f"{off:.2g} (rounded values); the nearest rotation is used",)
    return replace(cam, R=R, T=T, pose_notes=notes)

"""Calibration files from the tools that make them: OpenCV, ROS and Kalibr.

Read: OpenCV `cv2.FileStorage` YAML (`%YAML:1.0`, `!!opencv-matrix`) or XML
with `camera_matrix` / `distortion_coefficients` (one camera) or `M1`, `D1`,
`M2`, `D2` (`K1`... also), `R`, `T` (a stereo pair, as `stereoCalibrate`
gives them); ROS `camera_info` YAML; Kalibr `camchain.yaml` (`cam0`, `cam1`:
`intrinsics`, `distortion_coeffs`, `resolution`, `T_cn_cnm1`) and Kalibr's
`results-cam.txt` for its standard deviations. Written: OpenCV YAML and ROS
YAML, so the cameras a trial used can go to anyone's code.

Conventions (as the tools have them): intrinsics in pixels, K = [[fx, 0, cx],
[0, fy, cy], [0, 0, 1]]; distortion OpenCV's (k1, k2, p1, p2), which is ours,
with k3 and higher refused unless zero; extrinsics map the first camera's
frame to the second's, X2 = R X1 + T, T in metres (Kalibr's T_cn_cnm1 is the
same map as a 4x4 matrix). In wiredsl terms f = fx, ax = 1, ay = fy / fx.
"""

from __future__ import annotations

import math
import re
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from wiredsl.io.files import require_finite

FORMATS = ("opencv", "ros", "kalibr")


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
    dist: tuple[float, float, float, float]  # OpenCV's k1, k2, p1, p2
    width: int | None
    height: int | None
    R: np.ndarray | None = None  # (3, 3): from the previous camera's frame to this one's, X = R X_prev + T
    T: np.ndarray | None = None  # (3,) metres
    sigma: dict[str, float] = field(default_factory=dict)  # standard deviations, by wiredsl parameter name


# --------------------------------------------------------------------------- reading

def read(path: str | Path, fmt: str | None = None) -> list[CameraFile]:
    """The cameras of a calibration file, in file order (format guessed when not given)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise CalibrationFileError(f"cannot read {path}: {exc.strerror}") from None
    if len(raw) > 4 << 20:
        raise CalibrationFileError(f"{path} is over 4 MiB: not a calibration file")
    try:
        text = raw.decode("utf-8")
    except UnicodeDecodeError:
        raise CalibrationFileError(f"{path} is not UTF-8 text") from None
    if path.name.endswith(".txt") and (fmt in (None, "kalibr")):
        return _kalibr_results(text)
    if text.lstrip().startswith("<"):
        if fmt not in (None, "opencv"):
            raise CalibrationFileError(f"{path} is XML, which only OpenCV writes (format opencv)")
        return _opencv(_xml(text))
    doc = _yaml(text)
    if not isinstance(doc, dict):
        raise CalibrationFileError("expected a mapping of names to values at the top of the file")
    fmt = fmt or ("kalibr" if "cam0" in doc else "ros" if "camera_name" in doc or "distortion_model" in doc
                  else "opencv")
    return {"opencv": _opencv, "ros": _ros, "kalibr": _kalibr}[fmt](doc)


def _yaml(text: str) -> object:
    try:
        import yaml
    except ImportError:
        raise CalibrationFileError("reading YAML calibration files needs PyYAML: pip install 'wiredsl[calib]'") \
            from None

    class Loader(yaml.SafeLoader):
        pass

    def matrix(loader, node):
        m = loader.construct_mapping(node, deep=True)
        return _as_matrix(m)

    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", matrix)
    # OpenCV writes "%YAML:1.0", which YAML readers refuse (the directive is "%YAML 1.0").
    text = re.sub(r"^%YAML:1\.0\s*\n", "", text)
    try:
        return yaml.load(text, Loader=Loader)  # noqa: S506 (a SafeLoader with one constructor)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise CalibrationFileError(f"not valid YAML{where}: {getattr(exc, 'problem', exc)}") from None


def _xml(text: str) -> dict:
    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise CalibrationFileError(f"not valid XML: {exc}") from None
    out: dict = {}
    for node in root:
        if node.get("type_id") == "opencv-matrix":
            out[node.tag] = _as_matrix({c.tag: (c.text or "").strip() for c in node})
        else:
            words = (node.text or "").split()
            try:
                values = [float(w) for w in words]
                out[node.tag] = values[0] if len(values) == 1 else values
            except ValueError:
                out[node.tag] = (node.text or "").strip()
    return out


def _as_matrix(m: dict) -> np.ndarray:
    try:
        rows, cols = int(m["rows"]), int(m["cols"])
        data = m["data"]
        data = [float(x) for x in (data.split() if isinstance(data, str) else data)]
    except (KeyError, TypeError, ValueError):
        raise CalibrationFileError("a matrix needs rows, cols and data") from None
    if len(data) != rows * cols:
        raise CalibrationFileError(f"a {rows}x{cols} matrix needs {rows * cols} values, has {len(data)}")
    return np.array(data, dtype=float).reshape(rows, cols)


def _get(doc: dict, *names: str):
    for n in names:
        if n in doc:
            return doc[n]
    raise CalibrationFileError(f"no '{names[0]}' in the file" + (f" (nor {', '.join(names[1:])})" if names[1:] else ""))


def _intrinsics(name: str, K, D, size, model: str = "plumb_bob") -> CameraFile:
    K = np.asarray(K, dtype=float)
    if K.shape != (3, 3):
        raise CalibrationFileError(f"{name}: the camera matrix must be 3x3, is {'x'.join(map(str, K.shape))}")
    if K[0, 1] != 0 or K[1, 0] != 0 or K[2, 0] != 0 or K[2, 1] != 0 or K[2, 2] != 1:
        raise CalibrationFileError(f"{name}: skewed camera matrices are not supported (K[0,1] must be 0)")
    return CameraFile(name, float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2]),
                      _distortion(name, D, model), *_size(size))


def _distortion(name: str, D, model: str) -> tuple[float, float, float, float]:
    if model not in ("plumb_bob", "radtan", "rational_polynomial"):
        raise CalibrationFileError(f"{name}: distortion model '{model}' is not supported: wiredsl's camera has "
                                   "OpenCV's k1, k2, p1, p2 (plumb_bob / radtan)")
    d = [float(x) for x in np.asarray(D if D is not None else [], dtype=float).ravel()]
    if len(d) < 4:
        d += [0.0] * (4 - len(d))
    if any(x != 0 for x in d[4:]):
        raise CalibrationFileError(f"{name}: distortion coefficients beyond k1, k2, p1, p2 (k3 = {d[4]:g}...) are not "
                                   "supported; recalibrate with them fixed at zero")
    if not all(math.isfinite(x) for x in d):
        raise CalibrationFileError(f"{name}: distortion coefficients must be finite")
    return tuple(d[:4])


def _size(size) -> tuple[int | None, int | None]:
    if size is None:
        return None, None
    w, h = (float(x) for x in np.asarray(size, dtype=float).ravel()[:2])
    if not (w > 0 and h > 0 and w.is_integer() and h.is_integer()):
        raise CalibrationFileError(f"image size must be whole pixels > 0, got {w:g} x {h:g}")
    return int(w), int(h)


def _opencv(doc: dict) -> list[CameraFile]:
    size = doc.get("image_size", doc.get("imageSize"))
    if size is None and "image_width" in doc:
        size = (doc["image_width"], doc["image_height"])
    if "camera_matrix" in doc or "cameraMatrix" in doc:
        K = _get(doc, "camera_matrix", "cameraMatrix")
        D = doc.get("distortion_coefficients", doc.get("dist_coeffs", doc.get("distCoeffs")))
        return [_intrinsics("camera", K, D, size)]
    first = _intrinsics("M1", _get(doc, "M1", "K1", "cameraMatrix1"), doc.get("D1", doc.get("distCoeffs1")), size)
    second = _intrinsics("M2", _get(doc, "M2", "K2", "cameraMatrix2"), doc.get("D2", doc.get("distCoeffs2")), size)
    R, T = doc.get("R"), doc.get("T")
    if R is not None and T is not None:
        second = _with_pose(second, np.asarray(R, float), np.asarray(T, float).ravel())
    return [first, second]


def _with_pose(cam: CameraFile, R: np.ndarray, T: np.ndarray) -> CameraFile:
    if R.shape != (3, 3) or T.shape != (3,):
        raise CalibrationFileError("R must be 3x3 and T three values")
    if not (np.all(np.isfinite(R)) and np.all(np.isfinite(T))):
        raise CalibrationFileError("R and T must be finite")
    if np.abs(R @ R.T - np.eye(3)).max() > 1e-6 or np.linalg.det(R) < 0:
        raise CalibrationFileError("R is not a rotation matrix (R R^T must be I, det R = 1, to 1e-6)")
    return CameraFile(**{**cam.__dict__, "R": R, "T": T})


def _ros(doc: dict) -> list[CameraFile]:
    K = _get(doc, "camera_matrix", "K")
    D = doc.get("distortion_coefficients", doc.get("D"))
    return [_intrinsics(str(doc.get("camera_name", "camera")), _ros_matrix(K, 3, 3),
                        None if D is None else _ros_matrix(D, None, None), (doc.get("image_width"),
                        doc.get("image_height")) if "image_width" in doc else None,
                        str(doc.get("distortion_model", "plumb_bob")))]


def _ros_matrix(m, rows, cols) -> np.ndarray:
    if isinstance(m, dict):
        return _as_matrix(m)
    a = np.asarray(m, dtype=float)
    return a.reshape(rows, cols) if rows else a


def _kalibr(doc: dict) -> list[CameraFile]:
    out = []
    for i in range(len(doc)):
        cam = doc.get(f"cam{i}")
        if cam is None:
            break
        name = f"cam{i}"
        if cam.get("camera_model", "pinhole") != "pinhole":
            raise CalibrationFileError(f"{name}: camera model '{cam['camera_model']}' is not supported (pinhole only)")
        fu, fv, pu, pv = (float(x) for x in _get(cam, "intrinsics"))
        K = [[fu, 0, pu], [0, fv, pv], [0, 0, 1]]
        c = _intrinsics(name, K, cam.get("distortion_coeffs"), cam.get("resolution"),
                        str(cam.get("distortion_model", "radtan")))
        if i > 0 and "T_cn_cnm1" in cam:
            M = np.asarray(cam["T_cn_cnm1"], dtype=float)
            if M.shape != (4, 4):
                raise CalibrationFileError(f"{name}: T_cn_cnm1 must be 4x4")
            c = _with_pose(c, M[:3, :3], M[:3, 3])
        out.append(c)
    if not out:
        raise CalibrationFileError("no 'cam0' in the file")
    return out


_PLUSMINUS = re.compile(r"^\s*(\w[\w ]*?):\s*\[([^\]]*)\]\s*\+-\s*\[([^\]]*)\]", re.M)


def _kalibr_results(text: str) -> list[CameraFile]:
    """Kalibr's results-cam.txt: each camera's projection and distortion with their standard deviations."""
    blocks = re.split(r"^(cam\d+)\b.*$", text, flags=re.M)
    out = []
    for name, body in zip(blocks[1::2], blocks[2::2], strict=False):
        found = {m.group(1).strip(): ([float(x) for x in m.group(2).replace(",", " ").split()],
                                      [float(x) for x in m.group(3).replace(",", " ").split()])
                 for m in _PLUSMINUS.finditer(body.split("baseline", 1)[0])}
        if "projection" not in found:
            raise CalibrationFileError(f"{name}: no 'projection: [...] +- [...]' line")
        (fu, fv, pu, pv), (sfu, sfv, spu, spv) = found["projection"]
        d, sd = found.get("distortion", ([0.0] * 4, [0.0] * 4))
        sigma = {"f": sfu, "ay": math.hypot(sfv / fu, fv * sfu / fu**2), "cx": spu, "cy": spv,
                 "k": sd[0], "k2": sd[1], "p1": sd[2], "p2": sd[3]}
        out.append(CameraFile(name, fu, fv, pu, pv, _distortion(name, d, "radtan"), None, None, sigma=sigma))
    base = re.search(r"baseline T_1_0:(.*?)(?:^\S|\Z)", text, flags=re.M | re.S)
    if base and len(out) > 1:
        found = {m.group(1).strip(): [float(x) for x in m.group(3).replace(",", " ").split()]
                 for m in _PLUSMINUS.finditer(base.group(1))}
        extra = {}
        if "t" in found:
            extra.update(zip(("tx", "ty", "tz"), found["t"], strict=False))
        if "q" in found:  # a small rotation of angle theta has quaternion vector part theta / 2
            extra.update(zip(("rx", "ry", "rz"), (2 * s for s in found["q"][:3]), strict=False))
        out[1] = CameraFile(**{**out[1].__dict__, "sigma": {**out[1].sigma, **extra}})
    if not out:
        raise CalibrationFileError("no 'camN' block with a 'projection: [...] +- [...]' line")
    return out


# --------------------------------------------------------------------------- writing

def opencv_yaml(cams: list[dict], R: np.ndarray | None = None, T: np.ndarray | None = None) -> str:
    """OpenCV FileStorage YAML: one camera as camera_matrix / distortion_coefficients, two as M1, D1, M2, D2, R, T.

    Each camera is {"K": (3, 3), "D": (n,), "width": int, "height": int} and optionally "model": an
    "equidistant" camera's D is OpenCV's fisheye (k1..k4), named by a `distortion_model: equidistant` line.
    """
    lines = ["%YAML:1.0", "---"]
    first = cams[0]
    lines += [f"image_width: {first['width']}", f"image_height: {first['height']}"]
    if first.get("model", "radtan") != "radtan":
        lines.append(f"distortion_model: {first['model']}")
    if len(cams) == 1:
        lines += _cv_matrix("camera_matrix", first["K"]) + _cv_matrix("distortion_coefficients", first["D"][None, :])
    else:
        for i, c in enumerate(cams, 1):
            lines += _cv_matrix(f"M{i}", c["K"]) + _cv_matrix(f"D{i}", c["D"][None, :])
        lines += _cv_matrix("R", R) + _cv_matrix("T", np.asarray(T).reshape(3, 1))
    return "\n".join(lines) + "\n"


def _cv_matrix(name: str, a: np.ndarray) -> list[str]:
    a = np.asarray(a, dtype=float)
    data = ", ".join(repr(float(x)) for x in require_finite(a, f"calibration matrix {name}").ravel())
    return [f"{name}: !!opencv-matrix", f"   rows: {a.shape[0]}", f"   cols: {a.shape[1]}", "   dt: d",
            f"   data: [ {data} ]"]


def ros_yaml(name: str, cam: dict, R: np.ndarray | None = None, P: np.ndarray | None = None) -> str:
    """ROS camera_info YAML (plumb_bob, rational_polynomial for 8 coefficients, or equidistant for a camera
    whose "model" is); P defaults to [K | 0]."""
    K = np.asarray(cam["K"], dtype=float)
    R = np.eye(3) if R is None else np.asarray(R, dtype=float)
    P = np.hstack([K, np.zeros((3, 1))]) if P is None else np.asarray(P, dtype=float)

    def block(key, a):
        a = np.asarray(a, dtype=float)
        rows, cols = (1, a.size) if a.ndim == 1 else a.shape
        return [f"{key}:", f"  rows: {rows}", f"  cols: {cols}",
                "  data: [" + ", ".join(repr(float(x)) for x in require_finite(a, f"{name} {key}").ravel()) + "]"]

    lines = [f"image_width: {cam['width']}", f"image_height: {cam['height']}", f"camera_name: {name}"]
    model = "equidistant" if cam.get("model") == "equidistant" else \
        "rational_polynomial" if len(cam["D"]) == 8 else "plumb_bob"
    lines += block("camera_matrix", K) + [f"distortion_model: {model}"] + block("distortion_coefficients", cam["D"])
    lines += block("rectification_matrix", R) + block("projection_matrix", P)
    return "\n".join(lines) + "\n"


# --------------------------------------------------------------------------- a scene's rig as files

def rig_files(scene) -> dict[str, str]:
    """The rig's cameras as files: OpenCV stereo YAML (M1, D1, M2, D2, R, T) and one ROS camera_info each."""
    rig, cams = scene.rig, {c.name: c for c in scene.cameras}
    mats = {}
    for side in ("left", "right"):
        c = cams[getattr(rig, side).camera]
        K = np.array([[c.f * c.ax, 0, c.cx], [0, c.f * c.ay, c.cy], [0, 0, 1.0]])
        mats[side] = {"K": K, "D": distortion_vector(c), "width": c.width, "height": c.height, "model": c.distortion}
    R, T = stereo_extrinsics(rig)
    return {"stereo.yaml": opencv_yaml([mats["left"], mats["right"]], R, T),
            "left.yaml": ros_yaml("left", mats["left"]), "right.yaml": ros_yaml("right", mats["right"])}


def distortion_vector(cam) -> np.ndarray:
    """A camera's coefficients as OpenCV takes them: fisheye (k1, k2, k3, k4); else (k1, k2, p1, p2, k3), with
    k4, k5, k6 too when the rational model is used (8)."""
    if cam.distortion == "equidistant":
        return np.array([cam.k1, cam.k2, cam.k3, cam.k4])
    d = [cam.k1, cam.k2, cam.p1, cam.p2, cam.k3]
    return np.array(d + [cam.k4, cam.k5, cam.k6] if (cam.k4, cam.k5, cam.k6) != (0.0, 0.0, 0.0) else d)


def stereo_extrinsics(rig) -> tuple[np.ndarray, np.ndarray]:
    """(R, T) from the left camera's frame to the right's, X_r = R X_l + T, from the rig's mounts."""
    R_l, p_l = np.array(rig.left.rotation), np.array(rig.left.position)  # camera -> robot
    R_r, p_r = np.array(rig.right.rotation), np.array(rig.right.position)
    return R_r.T @ R_l, R_r.T @ (p_l - p_r)

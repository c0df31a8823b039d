"""Calibration files as the tools that write them do: OpenCV, ROS, Kalibr and ORB-SLAM.

Read:
- OpenCV `cv2.FileStorage` YAML in its own dialect (`%YAML:1.0` with a trailing comment, `data:[` with
  no space, `!!opencv-matrix`), XML and JSON: `camera_matrix` / `distortion_coefficients` (also the
  calibration tutorial's `Camera_Matrix` / `Distortion_Coefficients`, `cameraMatrix`, `K`, `D`), a
  `stereoCalibrate` pair's `M1`, `D1`, `M2`, `D2` (or `K1`...), `R`, `T`, and `stereo_calib`'s extrinsics
  file alone (`R`, `T`). Other matrices of the file (`image_points` of dt `2f`...) are never read.
- ROS `camera_info` YAML (camera_calibration_parsers) and message dumps: ROS 1 (`height`, `width`, `K`,
  `D`, `R`, `P`) and ROS 2 (`k`, `d`, `r`, `p`); recognised by their keys.
- Kalibr camchains (`cam0` ... `camN`; T_cn_cnm1, or extrinsics derived from two cameras' `T_cam_imu`
  or OpenVINS' `T_imu_cam`) and `results-cam.txt` (its standard deviations).
- ORB-SLAM2/3 settings: `Camera.fx`..., `Camera1.fx`..., `Camera2`, `Stereo.T_c1_c2`, and ORB-SLAM2's
  raw stereo `LEFT.K`, `LEFT.D`, `RIGHT.K`... with the rectification `LEFT.R`, `RIGHT.R`, `RIGHT.P`.

Distortion models: radtan (OpenCV's k1, k2, p1, p2, k3, k4, k5, k6: ROS plumb_bob and
rational_polynomial, Kalibr radtan) and equidistant (OpenCV fisheye, Kannala-Brandt: k1..k4; ROS
equidistant and fisheye, Kalibr equidistant, ORB-SLAM3 KannalaBrandt8). Refused, naming what: OpenCV's
thin-prism (s1..s4) and tilt (taux, tauy) terms, Kalibr's omni, ds, eucm and fov models, skewed K.

Conventions (as the tools have them): intrinsics in pixels, K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]];
extrinsics map the previous camera's frame to this one's, X = R X_prev + T (Kalibr's T_cn_cnm1 is that
map), T in the file's units (OpenCV's are the board's, often millimetres: the compiler warns).
"""

from __future__ import annotations

import json
import math
import re
from dataclasses import replace
from pathlib import Path

import numpy as np

from wiredsl import install_hint
from wiredsl.files import require_finite
from wiredsl.io.camera_file import (
    EQUIDISTANT,
    MIN_FOCAL,
    CalibrationFileError,
    CameraFile,
    _distortion,
    _floats,
    _intrinsics,
    _kind,
    _num,
    _with_pose,
)

FORMATS = ("opencv", "ros", "kalibr", "camodocal", "basalt")
MAX_BYTES = 4 << 20
MAX_DEPTH = 64  # nesting of a calibration file's mappings and lists (real ones have 3)


class _Matrix(dict):
    """An `!!opencv-matrix` (or FileStorage JSON/XML matrix) node, converted only when a reader uses it."""


# --------------------------------------------------------------------------- reading

def read(path: str | Path, fmt: str | None = None) -> list[CameraFile]:
    """The cameras of a calibration file, in file order (format recognised from the content when not given)."""
    path = Path(path)
    try:
        raw = path.read_bytes()
    except OSError as exc:
        raise CalibrationFileError(f"cannot read {path}: {exc.strerror}") from None
    if len(raw) > MAX_BYTES:
        raise CalibrationFileError(f"{path.name} is over {MAX_BYTES >> 20} MiB: not a calibration file")
    try:
        text = raw.decode("utf-8-sig")
    except UnicodeDecodeError:
        raise CalibrationFileError(f"{path.name} is not UTF-8 text") from None
    if fmt in (None, "kalibr") and _is_kalibr_results(text, path):
        return _kalibr_results(text)
    head = text.lstrip()
    if head.startswith("<"):
        if fmt not in (None, "opencv"):
            raise CalibrationFileError("the file is XML, which only OpenCV writes (format opencv)")
        doc = _xml(text)
    elif head.startswith("{"):
        doc = _json(text)
    else:
        doc = _yaml(text)
    if not isinstance(doc, dict):
        raise CalibrationFileError(f"expected a mapping of names to values at the top of the file, found {_kind(doc)}")
    from wiredsl.io import calibration_slam as slam

    if fmt in (None, "camodocal") and slam.is_camodocal(doc):
        return slam.camodocal(doc)
    if fmt in (None, "basalt") and slam.is_basalt(doc):
        return slam.basalt(doc)
    if fmt in ("camodocal", "basalt"):
        raise CalibrationFileError(f"the file is not {fmt}'s: " + ("no model_type with projection_parameters"
                                                                    if fmt == "camodocal" else "no value0.intrinsics"))
    if fmt == "opencv" and _is_ros(doc):  # the format named is not the file's, as for camodocal and basalt
        raise CalibrationFileError("the file is not OpenCV's: it is a ROS camera_info (camera_name, "
                                   "distortion_model, K or projection_matrix); write `format ros`, or leave the "
                                   "format out")
    fmt = fmt or ("kalibr" if _is_kalibr(doc) else "ros" if _is_ros(doc) else "opencv")
    return {"opencv": _opencv, "ros": _ros, "kalibr": _kalibr}[fmt](doc)


def _is_kalibr_results(text: str, path: Path) -> bool:
    if path.suffix == ".txt":
        return True
    return bool(re.search(r"^\s*projection:\s*\[.*\]\s*\+-", text, flags=re.M)) and "Calibration results" in text


def _is_kalibr(doc: dict) -> bool:
    return any(isinstance(k, str) and re.fullmatch(r"cam\d+", k) for k in doc)


def _is_ros(doc: dict) -> bool:
    keys = {k for k in doc if isinstance(k, str)}
    if keys & {"M1", "K1", "cameraMatrix1"}:  # a stereo pair is OpenCV's (with a distortion_model when a fisheye)
        return False
    return bool(keys & {"camera_name", "distortion_model", "projection_matrix", "rectification_matrix"}) or (
        {"height", "width"} <= keys and bool(keys & {"K", "k"}))


# ---- the three containers: YAML (OpenCV's dialect), XML, JSON

def _yaml(text: str) -> object:
    try:
        import yaml
    except ImportError:
        raise CalibrationFileError(f"reading YAML calibration files needs PyYAML: {install_hint('calib')}") \
            from None

    # libyaml's composer is fast but recursive in C: only for texts whose nesting is bounded by their
    # brackets and line prefixes, and without aliases; the others get the Python composer's bounded depth
    prefix = max((len(line) - len(line.lstrip(" \t-?")) for line in text.splitlines()), default=0)
    shallow = text.count("[") + text.count("{") + prefix < 4 * MAX_DEPTH and "*" not in text
    base = getattr(yaml, "CSafeLoader", yaml.SafeLoader) if shallow else yaml.SafeLoader

    class Loader(base):
        depth = 0

        def compose_node(self, parent, index):  # bounded nesting, no aliases: never a RecursionError or a bomb
            if self.check_event(yaml.AliasEvent):
                raise CalibrationFileError("YAML aliases (*name) are not used by calibration tools")
            self.depth += 1
            try:
                if self.depth > MAX_DEPTH:
                    raise CalibrationFileError(f"the file nests mappings or lists over {MAX_DEPTH} deep")
                return super().compose_node(parent, index)
            finally:
                self.depth -= 1

    def matrix(loader, node):
        if not isinstance(node, yaml.MappingNode):
            raise CalibrationFileError(f"an !!opencv-matrix at line {node.start_mark.line + 1} is not a mapping")
        return _Matrix(loader.construct_mapping(node, deep=True))

    Loader.add_constructor("tag:yaml.org,2002:opencv-matrix", matrix)
    Loader.add_implicit_resolver(  # 1e5, 2E-3: floats to OpenCV and JSON, text to YAML 1.1
        "tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:[0-9]+(?:\.[0-9]*)?|\.[0-9]+)[eE][-+]?[0-9]+$"),
        list("-+0123456789."))
    # OpenCV writes "%YAML:1.0" (YAML's directive is "%YAML 1.0"), may follow it with a comment, and
    # reads "key:value" with no space after the colon ("data:[" in ORB-SLAM's files).
    text = re.sub(r"\A\s*%YAML:\d+\.\d+[^\n]*\n", "", text)
    text = re.sub(r"^(\s*[A-Za-z_][\w.\-]*):(?=[^\s:/])", r"\1: ", text, flags=re.M)
    if base is not yaml.SafeLoader:
        del Loader.compose_node  # libyaml composes in C
    try:
        return yaml.load(text, Loader=Loader)  # noqa: S506 (a SafeLoader with one constructor)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark is not None else ""
        raise CalibrationFileError(f"not valid YAML{where}: {getattr(exc, 'problem', None) or exc}") from None
    except RecursionError:  # a scalar or flow nesting the composer's bound does not see
        raise CalibrationFileError(f"the file nests over {MAX_DEPTH} deep") from None


def _json(text: str) -> object:
    depth = deepest = 0
    for ch in re.sub(r'"(?:[^"\\]|\\.)*"', '""', text):  # brackets outside strings
        if ch in "[{":
            depth += 1
            deepest = max(deepest, depth)
        elif ch in "]}":
            depth -= 1
    if deepest > MAX_DEPTH:
        raise CalibrationFileError(f"the file nests mappings or lists over {MAX_DEPTH} deep")
    try:
        doc = json.loads(text, object_hook=lambda d: _Matrix(d) if d.get("type_id") == "opencv-matrix" else d)
    except ValueError:  # OpenCV 3 wrote numbers such as "1." into JSON, which its reader takes: so does YAML
        return _yaml(text)
    return doc


def _xml(text: str) -> dict:
    import xml.etree.ElementTree as ET

    try:
        root = ET.fromstring(text)
    except ET.ParseError as exc:
        raise CalibrationFileError(f"not valid XML: {exc}") from None
    out: dict = {}
    for node in root:
        if node.get("type_id") == "opencv-matrix":
            out[node.tag] = _Matrix({c.tag: (c.text or "").strip() for c in node})
        elif len(node):
            out[node.tag] = {c.tag: (c.text or "").strip() for c in node}
        else:
            words = (node.text or "").split()
            try:
                values = [float(w) for w in words]
                out[node.tag] = values[0] if len(values) == 1 else values
            except ValueError:
                out[node.tag] = (node.text or "").strip().strip('"')
    return out


# ---- values, checked for type before use


def _first(doc: dict, *names: str):
    return next((doc[n] for n in names if n in doc), None)


def _get(doc: dict, *names: str):
    v = _first(doc, *names)
    if v is None:
        raise CalibrationFileError(f"no '{names[0]}' in the file" + (f" (nor {', '.join(names[1:])})"
                                                                     if names[1:] else ""))
    return v


# ---- cameras


def _transform(v, what: str) -> np.ndarray:
    M = _floats(v, what, 16).reshape(4, 4)
    if np.abs(M[3] - [0, 0, 0, 1]).max() > 1e-9:
        raise CalibrationFileError(f"{what}: a 4x4 rigid transform's last row is [0, 0, 0, 1]")
    return M


def _inverse(M: np.ndarray) -> np.ndarray:
    out = np.eye(4)
    out[:3, :3] = M[:3, :3].T
    out[:3, 3] = -M[:3, :3].T @ M[:3, 3]
    return out


# ---- OpenCV (and ORB-SLAM, which writes FileStorage YAML)

_K = ("camera_matrix", "Camera_Matrix", "cameraMatrix", "CameraMatrix", "K", "k", "intrinsic_matrix")
_D = ("distortion_coefficients", "Distortion_Coefficients", "dist_coeffs", "distCoeffs", "distortion", "D", "d")


def _opencv_size(doc: dict, name: str):
    size = _first(doc, "image_size", "imageSize", "image_Size")
    if size is None:
        w = _first(doc, "image_width", "image_Width", "imageWidth", "width")
        h = _first(doc, "image_height", "image_Height", "imageHeight", "height")
        if w is not None or h is not None:
            size = [_num(w, f"{name}: the image width"), _num(h, f"{name}: the image height")]
    return size


def _opencv(doc: dict) -> list[CameraFile]:
    if any(k in doc for k in ("Camera.fx", "Camera1.fx", "LEFT.K")):
        return _orbslam(doc)
    fisheye = doc.get("fisheye_model") in (1, True) or str(doc.get("distortion_model", "")).lower() in EQUIDISTANT
    model = "equidistant" if fisheye else "plumb_bob"
    size = _opencv_size(doc, "camera")
    if any(k in doc for k in _K):
        return [_intrinsics("camera", _get(doc, *_K), _first(doc, *_D), size, model)]
    names = [("M1", "K1", "cameraMatrix1"), ("M2", "K2", "cameraMatrix2")]
    if not any(n in doc for ns in names for n in ns):
        if "R" in doc and "T" in doc:  # stereo_calib's extrinsics.yml: the pose, the intrinsics elsewhere
            blank = CameraFile("first", math.nan, math.nan, math.nan, math.nan, (), None, None, intrinsics=False)
            return [blank, _with_pose(replace(blank, name="second"), doc["R"], doc["T"])]
        raise CalibrationFileError("no camera matrix in the file: expected camera_matrix (or Camera_Matrix, "
                                   "cameraMatrix), M1 and M2 with R and T, or R and T alone")
    d1, d2 = _first(doc, "D1", "distCoeffs1"), _first(doc, "D2", "distCoeffs2")
    if (d1 is None) != (d2 is None):  # OpenCV writes both or, for a distortion-free pair, neither
        given, missing = ("D1", "D2 (distCoeffs2)") if d2 is None else ("D2", "D1 (distCoeffs1)")
        raise CalibrationFileError(f"the file names {given} but not {missing}: one camera's distortion is "
                                   "missing (a pair without distortion names neither)")
    first, second = (_camera_or_error(key, _get(doc, *ns), d, size, model)
                     for key, ns, d in (("M1", names[0], d1), ("M2", names[1], d2)))
    if "R" in doc and "T" in doc:
        second = _with_pose(second, doc["R"], doc["T"])
    return [first, second]


def _camera_or_error(name: str, K, D, size, model: str) -> CameraFile:
    """One camera of a stereo pair; a camera the reader refuses (thin-prism terms...) is kept as its error, said
    only where that camera is read (the other camera and the pair's R, T stay usable)."""
    try:
        return _intrinsics(name, K, D, size, model)
    except CalibrationFileError as exc:
        return CameraFile(name, math.nan, math.nan, math.nan, math.nan, (), None, None, error=str(exc))


def _orbslam(doc: dict) -> list[CameraFile]:
    """ORB-SLAM2/3 settings: the raw stereo pair (LEFT.K, ...) when given, else Camera[1|2].fx, ..."""
    kind = str(doc.get("Camera.type", "PinHole")).strip()
    fisheye = kind.lower() in EQUIDISTANT or doc.get("Camera.bFishEye") in (1, True)
    if "LEFT.K" in doc:  # ORB-SLAM2's EuRoC: raw cameras and the rectification they were given
        cams = []
        for side in ("LEFT", "RIGHT"):
            if f"{side}.K" not in doc:
                break
            size = None
            if f"{side}.width" in doc or f"{side}.height" in doc:
                size = [doc.get(f"{side}.width"), doc.get(f"{side}.height")]
            cams.append(_intrinsics(side, doc[f"{side}.K"], doc.get(f"{side}.D"), size,
                                    "equidistant" if fisheye else "plumb_bob"))
        if len(cams) == 2 and all(k in doc for k in ("LEFT.R", "RIGHT.R", "RIGHT.P")):
            R1 = _floats(doc["LEFT.R"], "LEFT.R", 9).reshape(3, 3)
            R2 = _floats(doc["RIGHT.R"], "RIGHT.R", 9).reshape(3, 3)
            P2 = _floats(doc["RIGHT.P"], "RIGHT.P", 12).reshape(3, 4)
            if P2[0, 0] == 0 or P2[1, 1] == 0:
                raise CalibrationFileError("RIGHT.P: its focal length is zero")
            t = np.array([P2[0, 3] / P2[0, 0], P2[1, 3] / P2[1, 1], 0.0])  # X_r' = X_l' + t in rectified frames
            cams[1] = _with_pose(cams[1], R2.T @ R1, R2.T @ t, "LEFT.R, RIGHT.R and RIGHT.P")
        return cams
    cams = []
    for prefix in ("Camera1", "Camera2") if "Camera1.fx" in doc else ("Camera", "Camera2"):
        if f"{prefix}.fx" not in doc:
            break
        v = {k: _num(doc[f"{prefix}.{k}"], f"{prefix}.{k}") for k in ("fx", "fy", "cx", "cy")
             if f"{prefix}.{k}" in doc}
        missing = [k for k in ("fx", "fy", "cx", "cy") if k not in v]
        if missing:
            raise CalibrationFileError(f"no '{prefix}.{missing[0]}' in the file")
        coeffs = ("k1", "k2", "k3", "k4") if fisheye else ("k1", "k2", "p1", "p2", "k3")
        D = [_num(doc.get(f"{prefix}.{k}", 0.0), f"{prefix}.{k}") for k in coeffs]
        size = None
        for p in (prefix, "Camera"):
            if f"{p}.width" in doc:
                size = [doc.get(f"{p}.width"), doc.get(f"{p}.height")]
                break
        K = [[v["fx"], 0, v["cx"]], [0, v["fy"], v["cy"]], [0, 0, 1]]
        cams.append(_intrinsics(prefix, K, D, size, "equidistant" if fisheye else "plumb_bob"))
    if len(cams) == 2 and "Tlr" in doc:  # before ORB-SLAM3 1.0: Tlr maps the right camera's points into the left's
        M = _floats(doc["Tlr"], "Tlr")
        if M.size not in (12, 16):
            raise CalibrationFileError(f"Tlr must be a 3x4 or 4x4 matrix, has {M.size} values")
        M = _inverse(_transform(np.concatenate([M[:12], [0, 0, 0, 1]]), "Tlr"))
        cams[1] = _with_pose(cams[1], M[:3, :3], M[:3, 3], "Tlr")
    elif len(cams) == 2 and "Stereo.T_c1_c2" in doc:
        M = _inverse(_transform(doc["Stereo.T_c1_c2"], "Stereo.T_c1_c2"))  # T_c1_c2 maps camera 2's points to 1's
        cams[1] = _with_pose(cams[1], M[:3, :3], M[:3, 3], "Stereo.T_c1_c2")
    return cams


# ---- ROS

def _ros(doc: dict) -> list[CameraFile]:
    name = doc.get("camera_name", "camera")
    name = name if isinstance(name, str) and name else "camera"
    K = _get(doc, "camera_matrix", "K", "k")
    D = _first(doc, "distortion_coefficients", "D", "d")
    size = None
    if any(k in doc for k in ("image_width", "image_height")):
        size = [doc.get("image_width"), doc.get("image_height")]
    elif any(k in doc for k in ("width", "height")):
        size = [doc.get("width"), doc.get("height")]
    model = doc.get("distortion_model", "plumb_bob")
    cam = _intrinsics(name, K, D, size, model)
    P = _first(doc, "projection_matrix", "P", "p")
    if cam.model == "radtan" and isinstance(model, str) and model.lower() == "plumb_bob" and D is not None:
        n = _floats(D, f"{name}: the distortion coefficients").size
        fp = _floats(P, f"{name}: the projection matrix", 12)[0] if P is not None else cam.fx
        if n == 4 and not 0.5 <= fp / cam.fx <= 2:
            cam = replace(cam, notes=(
                f"{name}: labelled plumb_bob but has 4 coefficients (plumb_bob has 5) and a projection matrix "
                f"whose focal length ({fp:.4g} px) is far from K's ({cam.fx:.4g} px): ROS's fisheye calibrator "
                "wrote such files; if this camera is a fisheye, the file's distortion_model must be equidistant",))
    return [cam]


# ---- Kalibr

def _kalibr(doc: dict) -> list[CameraFile]:
    out: list[CameraFile] = []
    T_imu: list[np.ndarray | None] = []
    for i in range(len(doc)):
        name = f"cam{i}"
        if name not in doc:
            break
        cam = doc[name]
        if not isinstance(cam, dict):
            raise CalibrationFileError(f"{name} must be a mapping (camera_model, intrinsics, ...), is {_kind(cam)}")
        model = cam.get("camera_model", "pinhole")
        if not isinstance(model, str):
            raise CalibrationFileError(f"{name}: camera_model must be a name, is {_kind(model)}")
        dmodel = cam.get("distortion_model", "none" if model in ("ds", "eucm") else "radtan")
        c = _kalibr_intrinsics(name, model, dmodel, cam)
        c = replace(c, name=name)
        if "T_cam_imu" in cam:
            T_imu.append(_transform(cam["T_cam_imu"], f"{name}: T_cam_imu"))
        elif "T_imu_cam" in cam:  # OpenVINS' files: the inverse
            T_imu.append(_inverse(_transform(cam["T_imu_cam"], f"{name}: T_imu_cam")))
        else:
            T_imu.append(None)
        if i > 0 and "T_cn_cnm1" in cam:
            M = _transform(cam["T_cn_cnm1"], f"{name}: T_cn_cnm1")
            c = _with_pose(c, M[:3, :3], M[:3, 3], "T_cn_cnm1")
        elif i > 0 and T_imu[i] is not None and T_imu[i - 1] is not None:
            M = T_imu[i] @ _inverse(T_imu[i - 1])  # previous camera -> IMU -> this camera
            c = _with_pose(c, M[:3, :3], M[:3, 3], f"T_cam_imu of cam{i - 1} and {name}")
        out.append(c)
    if not out:
        raise CalibrationFileError("no 'cam0' in the file")
    return out


# Kalibr's camera models (aslam_cv's camera geometries): intrinsics before fu, fv, pu, pv, and the distortion
# models each takes ("none" is no distortion): the names of kalibr_calibrate_cameras' --models, camera-distortion
KALIBR_CAMERAS = {"pinhole": ((), ("radtan", "equidistant", "fov", "none")), "omni": (("xi",), ("radtan", "none")),
                  "eucm": (("alpha", "beta"), ("none",)), "ds": (("xi", "alpha"), ("none",))}


def _kalibr_intrinsics(name: str, model, dmodel, cam: dict) -> CameraFile:
    """One camchain camera: pinhole-radtan, -equi, -fov or -none, omni-radtan or -none, eucm-none, ds-none."""
    if not isinstance(model, str) or not isinstance(dmodel, str):
        raise CalibrationFileError(f"{name}: camera_model and distortion_model must be names")
    if model not in KALIBR_CAMERAS or dmodel not in KALIBR_CAMERAS[model][1]:
        known = ", ".join(f"{m}-{d}" for m, (_, ds) in KALIBR_CAMERAS.items() for d in ds)
        what = f"camera model '{model}'" if model not in KALIBR_CAMERAS else f"camera '{model}-{dmodel}'"
        raise CalibrationFileError(f"{name}: Kalibr {what} is not supported: wiredsl reads Kalibr's {known}")
    extra = KALIBR_CAMERAS[model][0]
    values = _floats(_get(cam, "intrinsics"), f"{name}: intrinsics [{', '.join((*extra, 'fu', 'fv', 'pu', 'pv'))}]",
                     len(extra) + 4)
    lead, (fu, fv, pu, pv) = list(values[:len(extra)]), values[len(extra):]
    d = cam.get("distortion_coeffs") if dmodel != "none" else None
    if model == "pinhole":
        kind = {"fov": "fov", "none": "radtan"}.get(dmodel, dmodel)
        D = d if kind != "radtan" or d is not None else None
    elif model == "omni":
        kind, D = "unified", lead + (list(_floats(d, f"{name}: distortion_coeffs [k1, k2, r1, r2]", 4)) if d is not None
                                     else [0.0] * 4)
    else:
        kind, D = model, lead
    c = _intrinsics(name, [[fu, 0, pu], [0, fv, pv], [0, 0, 1]], D, cam.get("resolution"), kind)
    return replace(c, name=name)


_PLUSMINUS = re.compile(r"^\s*(\w[\w ]*?):\s*\[([^\]]*)\]\s*\+-\s*\[([^\]]*)\]")


def _kalibr_results(text: str) -> list[CameraFile]:
    """Kalibr's results-cam.txt (lines indented with spaces, or a TAB before late 2022): each camera's
    projection and distortion, and each baseline, with their standard deviations."""
    cams: list[dict] = []
    baselines: dict[int, dict] = {}
    block: dict | None = None
    for n, line in enumerate(text.splitlines(), 1):
        s = line.strip()
        head = re.fullmatch(r"(cam\d+)\s*(?:\(.*\))?\s*:?", s)
        if head:
            block = {"name": head.group(1), "line": n}
            cams.append(block)
            continue
        base = re.match(r"baseline T_(\d+)_(\d+)\s*:", s)
        if base:
            block = baselines.setdefault(int(base.group(1)), {"line": n})
            continue
        if block is None:
            continue
        if s.startswith("type:"):
            block["type"] = s[5:].strip()
            continue
        m = _PLUSMINUS.match(line)
        if m:
            what = f"line {n}: '{m.group(1).strip()}'"
            values, sigmas = ([float(x) for x in _floats(g.replace(",", " ").split(), what)] for g in m.group(2, 3))
            block[m.group(1).strip()] = (values, sigmas, n)
    out = [_kalibr_camera(c) for c in cams]
    if not out:
        raise CalibrationFileError("no 'camN' block with a 'projection: [...] +- [...]' line: not Kalibr's "
                                   "results-cam.txt")
    for i, b in baselines.items():
        if 0 < i < len(out):
            extra = {}
            for key, names in (("t", ("tx", "ty", "tz")), ("q", ("rx", "ry", "rz"))):
                if key in b:
                    if len(b[key][1]) != 3:
                        raise CalibrationFileError(f"line {b[key][2]}: '{key}' needs 3 standard deviations")
                    # q's are already rotation-vector sigmas in radians: aslam perturbs the quaternion by an
                    # axis-angle update (sm::kinematics::updateQuat), and Kalibr prints that update's std
                    extra.update(zip(names, b[key][1], strict=True))
            out[i] = replace(out[i], sigma={**out[i].sigma, **extra})
    return out


def _kalibr_camera(c: dict) -> CameraFile:
    name, kind = c["name"], c.get("type", "")
    for word, model in (("Omni", "an 'omni'"), ("DoubleSphere", "a 'ds'"), ("ExtendedUnified", "an 'eucm'"),
                        ("Fov", "a 'fov'")):
        if word in kind:
            raise CalibrationFileError(f"{name}: Kalibr's results-cam.txt of {model} camera is not read (its "
                                       "standard deviations are of other numbers): read the camchain YAML")
    equidistant = "Equidistant" in kind
    if "projection" not in c:
        raise CalibrationFileError(f"{name} (line {c['line']}): no 'projection: [...] +- [...]' line")
    p, sp, n = c["projection"]
    if len(p) != 4 or len(sp) != 4:
        raise CalibrationFileError(f"line {n}: a pinhole projection has 4 values [fu, fv, pu, pv] and 4 standard "
                                   f"deviations, this has {len(p)} and {len(sp)}")
    (fu, fv, pu, pv), (sfu, sfv, spu, spv) = p, sp
    if not (fu >= MIN_FOCAL and fv >= MIN_FOCAL):
        raise CalibrationFileError(f"line {n}: the focal lengths must be at least {MIN_FOCAL:g} px")
    d, sd, dn = c.get("distortion", ([], [], c["line"]))
    want = 4 if (equidistant or "Distorted" in kind or d) else 0
    if len(d) != want or len(sd) != want:
        raise CalibrationFileError(f"line {dn}: {'an equidistant' if equidistant else 'a radtan'} distortion has "
                                   f"{want} values and {want} standard deviations, this has {len(d)} and {len(sd)}")
    sigma = {"f": sfu, "ay": math.hypot(sfv / fu, fv * sfu / fu**2), "cx": spu, "cy": spv}
    names = ("k", "k2", "k3", "k4") if equidistant else ("k", "k2", "p1", "p2")
    sigma.update(zip(names, sd, strict=False))
    model, dist = _distortion(name, d, "equidistant" if equidistant else "radtan")
    return CameraFile(name, fu, fv, pu, pv, dist, None, None, sigma=sigma, model=model)


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
    """The rig's cameras as files: OpenCV stereo YAML (M1, D1, M2, D2, R, T) and one ROS camera_info each, with the
    stereo rectification R and P that ROS's stereo nodes use (two radtan or two equidistant cameras of one image size;
    otherwise R = I and P = [K | 0]), for the lenses OpenCV and ROS have (radtan, equidistant); and for the SLAM tools
    a Kalibr camchain (camchain.yaml), basalt's calibration (basalt_calib.json, with T_imu_cam the mounts on the robot)
    and camodocal's YAML a camera (left_camodocal.yaml, right_camodocal.yaml), each when it has the rig's lenses."""
    from wiredsl.io import calibration_slam as slam

    rig, cams = scene.rig, {c.name: c for c in scene.cameras}
    lenses = [cams[getattr(rig, side).camera] for side in ("left", "right")]
    R, T = rig.stereo_extrinsics()
    out: dict[str, str] = {}
    if all(c.distortion in ("radtan", "equidistant") for c in lenses):
        out.update(_opencv_rig_files(rig, lenses, R, T))
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, T
    mounts = []
    for side in ("left", "right"):
        m = getattr(rig, side)
        P = np.eye(4)
        P[:3, :3], P[:3, 3] = np.array(m.rotation), np.array(m.position)  # camera -> robot
        mounts.append(P)
    for name, write in (("camchain.yaml", lambda: slam.kalibr_yaml(lenses, [None, M])),
                        ("basalt_calib.json", lambda: slam.basalt_json(lenses, mounts))):
        try:
            out[name] = write()
        except CalibrationFileError:  # a lens the format has not: that file is not written
            pass
    for side, c in zip(("left", "right"), lenses, strict=True):
        text = slam.camodocal_yaml(side, c)
        if text is not None:
            out[f"{side}_camodocal.yaml"] = text
    return out


def _opencv_rig_files(rig, lenses, R, T) -> dict[str, str]:
    mats = {}
    for side, c in zip(("left", "right"), lenses, strict=True):
        K = np.array([[c.f * c.ax, 0, c.cx], [0, c.f * c.ay, c.cy], [0, 0, 1.0]])
        mats[side] = {"K": K, "D": distortion_vector(c), "width": c.width, "height": c.height, "model": c.distortion}
    rect: dict = {"left": {}, "right": {}}
    left, right = mats["left"], mats["right"]
    rectify = {"radtan": stereo_rectify, "equidistant": fisheye_stereo_rectify}.get(left["model"])
    size = (left["width"], left["height"])
    if rectify and left["model"] == right["model"] and size == (right["width"], right["height"]) \
            and np.linalg.norm(T) > 0:
        with np.errstate(all="ignore"):  # a wild lens's corners may not undistort: then no rectification
            R1, R2, P1, P2 = rectify(left["K"], left["D"], right["K"], right["D"], size, R, T)
        if all(np.all(np.isfinite(m)) for m in (R1, R2, P1, P2)):
            rect = {"left": {"R": R1, "P": P1}, "right": {"R": R2, "P": P2}}
    return {"stereo.yaml": opencv_yaml([left, right], R, T), "left.yaml": ros_yaml("left", left, **rect["left"]),
            "right.yaml": ros_yaml("right", right, **rect["right"])}


def stereo_rectify(K1, D1, K2, D2, size: tuple[int, int], R, T):
    """R1, R2, P1, P2 as `cv2.stereoRectify` gives them (alpha -1, CALIB_ZERO_DISPARITY), which is ROS's
    stereo convention: R rectifies each camera, P2[0, 3] = Tx = -fx' * baseline. OpenCV's steps, with its
    single-precision image corners: half the rotation to each camera, then the baseline turned onto x;
    f' the mean of the cameras' fy; the centre from the undistorted corners of each image."""
    R, T = np.asarray(R, dtype=float), np.asarray(T, dtype=float).ravel()
    R1, R2, idx = _rectifying_rotations(R, T)
    t = R2 @ T
    fc = (K1[idx ^ 1, idx ^ 1] + K2[idx ^ 1, idx ^ 1]) / 2
    nx, ny = size
    corners = np.array([[0, 0], [nx - 1, 0], [0, ny - 1], [nx - 1, ny - 1]], dtype=np.float32).astype(float)
    centres = []
    for K, D, Rk in ((K1, D1, R1), (K2, D2, R2)):
        xy = _undistort(corners, np.asarray(K, dtype=float), np.asarray(D, dtype=float)).astype(np.float32)
        X = np.column_stack([xy.astype(float), np.ones(4)]) @ Rk.T
        uv = (fc * X[:, :2] / X[:, 2:]).astype(np.float32).astype(float)
        centres.append(np.array([(nx - 1) / 2, (ny - 1) / 2]) - uv.mean(axis=0))
    cc = (centres[0] + centres[1]) / 2
    P1 = np.array([[fc, 0, cc[0], 0], [0, fc, cc[1], 0], [0, 0, 1, 0]])
    P2 = P1.copy()
    P2[idx, 3] = t[idx] * fc
    return R1, R2, P1, P2


def _rectifying_rotations(R: np.ndarray, T: np.ndarray, axis: int | None = None):
    """R1, R2 and the baseline's axis (0: x, 1: y) as OpenCV's stereoRectify (and its fisheye twin, which
    always takes x) turn the cameras: half the rotation to each, then the baseline onto the axis."""
    from scipy.spatial.transform import Rotation

    r_r = Rotation.from_rotvec(-0.5 * Rotation.from_matrix(R).as_rotvec()).as_matrix()
    t = r_r @ T
    idx = (0 if abs(t[0]) > abs(t[1]) else 1) if axis is None else axis
    c, nt = t[idx], float(np.linalg.norm(t))
    uu = np.zeros(3)
    uu[idx] = 1.0 if c > 0 else -1.0
    ww = np.cross(t, uu)
    nw = float(np.linalg.norm(ww))
    if nw > 0:
        ww *= math.acos(min(1.0, abs(c) / nt)) / nw
    wR = Rotation.from_rotvec(ww).as_matrix()
    return wR @ r_r.T, wR @ r_r, idx


def fisheye_stereo_rectify(K1, D1, K2, D2, size: tuple[int, int], R, T):
    """R1, R2, P1, P2 of an equidistant (Kannala-Brandt) rig as `cv2.fisheye.stereoRectify` gives them with
    CALIB_ZERO_DISPARITY, balance 0 and fov_scale 1 (ROS's stereo convention, P2[0, 3] = Tx = -f' * baseline).
    OpenCV's steps: the rotations of `stereo_rectify` with the baseline always on x; each camera's new focal
    length from the midpoints of its image's four sides, undistorted and rotated (the largest of the four
    focal lengths that put a midpoint on its side: balance 0); f' the smaller of the two cameras'; the
    principal point the mean of the two.

    OpenCV's rule needs each midpoint's pinhole image: a lens whose sides reach 90 deg off the rectified axis
    (a field of view of 180 deg or more) has none, and OpenCV then returns NaN, a focal length near 0, or one
    from midpoints its undistortion turned through the centre (theta past 90 deg).
    There f' is the smaller of the two cameras' own fy (the equidistant image's scale at its centre) and the
    principal point the mean of the two cameras' own: the rotations and Tx / f' stay OpenCV's."""
    R, T = np.asarray(R, dtype=float), np.asarray(T, dtype=float).ravel()
    R1, R2, _ = _rectifying_rotations(R, T, axis=0)
    w, h = size
    mids = np.array([[w // 2, 0], [w, h // 2], [w // 2, h], [0, h // 2]], dtype=float)
    news = []
    cams = [(np.asarray(K, dtype=float), np.asarray(D, dtype=float).ravel(), Rk) for K, D, Rk in
            ((K1, D1, R1), (K2, D2, R2))]
    for K, D, Rk in cams:
        xy = _undistort_fisheye(mids, K, D)
        X = np.column_stack([xy, np.ones(4)]) @ Rk.T
        if not (np.all(np.isfinite(X)) and np.all(X[:, 2] > 1e-6 * np.linalg.norm(X, axis=1))):
            news = [(K[1, 1], K[:2, 2]) for K, _, _ in cams]  # a side at or past 90 deg: no pinhole image
            break
        p = X[:, :2] / X[:, 2:]
        cn = p.mean(axis=0)
        aspect = K[0, 0] / K[1, 1]
        cn[1] *= aspect  # y in x's pixel units
        p[:, 1] *= aspect
        fs = [w * 0.5 / (cn[0] - p[:, 0].min()), w * 0.5 / (p[:, 0].max() - cn[0]),
              h * 0.5 * aspect / (cn[1] - p[:, 1].min()), h * 0.5 * aspect / (p[:, 1].max() - cn[1])]
        f = max(fs)
        c = -cn * f + np.array([w, h * aspect]) * 0.5
        news.append((f / aspect, np.array([c[0], c[1] / aspect])))
    fc = min(news[0][0], news[1][0])
    cc = (news[0][1] + news[1][1]) / 2
    P1 = np.array([[fc, 0, cc[0], 0], [0, fc, cc[1], 0], [0, 0, 1, 0]])
    P2 = P1.copy()
    P2[0, 3] = (R2 @ T)[0] * fc
    return R1, R2, P1, P2


def _undistort_fisheye(uv: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Normalised points from pixels under the equidistant model, as `cv2.fisheye.undistortPoints`: theta_d
    clipped to [-pi/2, pi/2], theta by Newton's method; NaN where no theta of the same sign solves it."""
    from wiredsl.engine.geometry import fisheye_theta

    pw = np.column_stack([(uv[:, 0] - K[0, 2]) / K[0, 0], (uv[:, 1] - K[1, 2]) / K[1, 1]])
    theta_d = np.minimum(np.hypot(pw[:, 0], pw[:, 1]), math.pi / 2)
    theta, residual = fisheye_theta(theta_d, *D[:4])
    with np.errstate(divide="ignore", invalid="ignore"):
        scale = np.where(theta_d > 1e-8, np.tan(theta) / np.where(theta_d > 0, theta_d, 1.0), 1.0)
    bad = (theta_d > 1e-8) & ~((theta > 0) & (theta < math.pi / 2) & (residual < 1e-9))
    return pw * np.where(bad, np.nan, scale)[:, None]


def _undistort(uv: np.ndarray, K: np.ndarray, D: np.ndarray) -> np.ndarray:
    """Normalised points from pixels under OpenCV's radtan model, as `cv2.undistortPoints` (5 iterations)."""
    k = np.zeros(8)
    k[:min(8, D.size)] = D.ravel()[:8]
    x0 = (uv[:, 0] - K[0, 2]) / K[0, 0]
    y0 = (uv[:, 1] - K[1, 2]) / K[1, 1]
    x, y = x0.copy(), y0.copy()
    stopped = np.zeros(x.shape, dtype=bool)  # a negative icdist stops that point at its distorted position
    for _ in range(5):
        r2 = x * x + y * y
        icdist = (1 + ((k[7] * r2 + k[6]) * r2 + k[5]) * r2) / (1 + ((k[4] * r2 + k[1]) * r2 + k[0]) * r2)
        stop = ~stopped & (icdist < 0)
        dx = 2 * k[2] * x * y + k[3] * (r2 + 2 * x * x)
        dy = k[2] * (r2 + 2 * y * y) + 2 * k[3] * x * y
        x = np.where(stopped, x, np.where(stop, x0, (x0 - dx) * icdist))
        y = np.where(stopped, y, np.where(stop, y0, (y0 - dy) * icdist))
        stopped |= stop
    return np.column_stack([x, y])


def distortion_vector(cam) -> np.ndarray:
    """A camera's coefficients as OpenCV takes them: fisheye (k1, k2, k3, k4); else (k1, k2, p1, p2, k3), with
    k4, k5, k6 too when the rational model is used (8)."""
    if cam.distortion == "equidistant":
        return np.array([cam.k1, cam.k2, cam.k3, cam.k4])
    d = [cam.k1, cam.k2, cam.p1, cam.p2, cam.k3]
    return np.array(d + [cam.k4, cam.k5, cam.k6] if (cam.k4, cam.k5, cam.k6) != (0.0, 0.0, 0.0) else d)


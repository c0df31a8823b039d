"""Real calibration files (tests/data/calibration, origins in its README): every file is read into a scene,
and its cameras project as OpenCV projects the file's own values, read independently by cv2.FileStorage."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import camera_scene, compile_text

from wiredsl.engine import geometry
from wiredsl.io import calibration as cf

CORPUS = Path(__file__).parent / "data" / "calibration"


def _node(fs, key):
    n = fs.getNode(key)
    return None if n.empty() else n


def _mat(node) -> np.ndarray:
    if node.isMap() and node.getNode("dt").empty():  # ROS {rows, cols, data}
        data = node.getNode("data")
        return np.array([data.at(i).real() for i in range(data.size())])
    if node.isSeq():
        out = []
        for i in range(node.size()):
            item = node.at(i)
            out.extend(_mat(item).ravel() if item.isSeq() else [item.real()])
        return np.array(out)
    return np.asarray(node.mat(), dtype=float)


def _oracle(path: Path) -> list[dict]:
    """Each camera's K, D and model as cv2.FileStorage reads the file (by the keys each tool writes)."""
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    assert fs.isOpened()
    keys = fs.root().keys()
    cams = []
    if "cam0" in keys:  # Kalibr
        for i in range(10):
            cam = _node(fs, f"cam{i}")
            if cam is None:
                break
            fu, fv, pu, pv = _mat(cam.getNode("intrinsics"))
            model = cam.getNode("distortion_model").string()
            cams.append({"K": [[fu, 0, pu], [0, fv, pv], [0, 0, 1]], "D": _mat(cam.getNode("distortion_coeffs")),
                         "model": "equidistant" if model == "equidistant" else "radtan"})
    elif "LEFT.K" in keys:  # ORB-SLAM2's raw stereo pair
        cams = [{"K": _mat(fs.getNode(f"{s}.K")), "D": _mat(fs.getNode(f"{s}.D")), "model": "radtan"}
                for s in ("LEFT", "RIGHT")]
    elif "Camera.fx" in keys or "Camera1.fx" in keys:  # ORB-SLAM settings
        fisheye = fs.getNode("Camera.type").string() == "KannalaBrandt8"
        for p in ("Camera1", "Camera2") if "Camera1.fx" in keys else ("Camera", "Camera2"):
            if f"{p}.fx" not in keys:
                break
            g = {k: fs.getNode(f"{p}.{k}").real() for k in ("fx", "fy", "cx", "cy", "k1", "k2", "k3", "k4", "p1", "p2")}
            D = [g[k] for k in (("k1", "k2", "k3", "k4") if fisheye else ("k1", "k2", "p1", "p2", "k3"))]
            cams.append({"K": [[g["fx"], 0, g["cx"]], [0, g["fy"], g["cy"]], [0, 0, 1]], "D": np.array(D),
                         "model": "equidistant" if fisheye else "radtan"})
    elif "M1" in keys:  # stereo_calib
        cams = [{"K": _mat(fs.getNode(f"M{i}")), "D": _mat(fs.getNode(f"D{i}")), "model": "radtan"} for i in (1, 2)]
    else:  # one camera: OpenCV's calibration sample or ROS camera_info
        model = fs.getNode("distortion_model").string() if "distortion_model" in keys else "plumb_bob"
        cams = [{"K": _mat(fs.getNode("camera_matrix")), "D": _mat(fs.getNode("distortion_coefficients")),
                 "model": "equidistant" if model in ("equidistant", "fisheye") else "radtan"}]
    for c in cams:
        c["K"] = np.asarray(c["K"], dtype=float).reshape(3, 3)
        c["D"] = np.asarray(c["D"], dtype=float).ravel()
    return cams


def _scene(path: Path, entry: str) -> str:
    return camera_scene(f'size (640px, 480px)\n  read "{path}" entry {entry}')


FILES = sorted(p.name for p in CORPUS.iterdir() if p.suffix in (".yaml", ".yml")  # the wide-angle lenses' files
               and not p.name.startswith("vinsfusion_"))  # are test_calibration_slam.py's


def test_the_corpus_is_there():
    assert len(FILES) >= 14


@pytest.mark.parametrize("name", FILES)
def test_every_real_file_projects_as_opencv_projects_its_own_values(name, tmp_path):
    path = CORPUS / name
    oracle = _oracle(path)
    read = cf.read(path)
    assert len(read) == len(oracle)
    rng = np.random.default_rng(17)
    X = np.column_stack([rng.uniform(-0.6, 0.6, 40), rng.uniform(-0.45, 0.45, 40), np.ones(40)])
    X *= rng.uniform(0.5, 8.0, 40)[:, None]  # points within about 60 degrees of the axis, 0.5 to 8 m away
    for i, (want, got) in enumerate(zip(oracle, read, strict=True)):
        assert got.model == want["model"]
        assert (got.fx, got.fy, got.cx, got.cy) == (want["K"][0, 0], want["K"][1, 1], want["K"][0, 2], want["K"][1, 2])
        d = np.zeros(4 if got.model == "equidistant" else 8)
        d[:want["D"].size] = want["D"]
        assert np.array_equal(got.dist, d)
        # the camera as a scene compiles it (through `read`), projected by the engine and by OpenCV
        size_given = got.width is None
        text = _scene(path, ("first", "second")[i])
        if not size_given:
            text = text.replace("  size (640px, 480px)\n", "")
        scene, warnings = compile_text(text, str(tmp_path / "a.wd"))
        cam = scene.cameras[0]
        _check_fold_warning(cam, want["K"], d, [w.message for w in warnings if w.code == "W147"])
        ours = geometry.cam_to_pixels(X, cam)
        if got.model == "equidistant":
            theirs = cv2.fisheye.projectPoints(X[:, None, :], np.zeros(3), np.zeros(3), want["K"], d)[0]
        else:
            theirs = cv2.projectPoints(X, np.zeros(3), np.zeros(3), want["K"], d)[0]
        assert np.abs(ours - theirs.reshape(-1, 2)).max() < 1e-6, name


def _T(R, t):
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = R, t
    return M


@pytest.mark.parametrize("name, second_from_first", [
    # Kalibr's T_cn_cnm1 is the map itself
    ("openvins_rs_t265_kalibr_imucam_chain.yaml",
     lambda fs: _mat(fs.getNode("cam1").getNode("T_cn_cnm1")).reshape(4, 4)),
    # from each camera's T_cam_imu: cam1 <- imu <- cam0
    ("openvins_tum_vi_kalibr_imucam_chain.yaml", lambda fs: _mat(fs.getNode("cam1").getNode("T_cam_imu")).reshape(4, 4)
     @ np.linalg.inv(_mat(fs.getNode("cam0").getNode("T_cam_imu")).reshape(4, 4))),
    # OpenVINS' T_imu_cam: the inverse
    ("openvins_euroc_mav_kalibr_imucam_chain.yaml", lambda fs: np.linalg.inv(
        _mat(fs.getNode("cam1").getNode("T_imu_cam")).reshape(4, 4)) @ _mat(fs.getNode("cam0").getNode("T_imu_cam"))
     .reshape(4, 4)),
    # ORB-SLAM3's Tlr (before 1.0) maps the right camera's points into the left's
    ("orbslam3_old_Stereo_RealSense_T265.yaml", lambda fs: np.linalg.inv(np.vstack([fs.getNode("Tlr").mat().astype(
        float), [0, 0, 0, 1]]))),
    # ORB-SLAM3's T_c1_c2 maps camera 2's points into camera 1's
    ("orbslam3_Stereo_TUM-VI.yaml", lambda fs: np.linalg.inv(fs.getNode("Stereo.T_c1_c2").mat().astype(float))),
    # ORB-SLAM2's rectification: R2 X_r = R1 X_l + (P2[0,3] / fx', 0, 0)
    ("orbslam2_Stereo_EuRoC.yaml", lambda fs: _T(
        fs.getNode("RIGHT.R").mat().T @ fs.getNode("LEFT.R").mat(),
        fs.getNode("RIGHT.R").mat().T @ [fs.getNode("RIGHT.P").mat()[0, 3] / fs.getNode("RIGHT.P").mat()[0, 0], 0, 0])),
])
def test_a_real_stereo_files_extrinsics_place_the_right_camera(name, second_from_first, tmp_path):
    path = CORPUS / name
    M = second_from_first(cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ))
    text = _scene(path, "first").replace("  size (640px, 480px)\n", "").replace(
        "camera c {", f'camera c2 {{\n  read "{path}" entry second\n}}\ncamera c {{').replace(
        "right c at (0, -0.06, 1) looking (1, 0, 0)", f'right c2 relative "{path}"')
    scene, warnings = compile_text(text, str(tmp_path / "a.wd"))
    R, T = scene.rig.stereo_extrinsics()
    tol = 1e-6 if "orbslam3" in name else 1e-9  # an inverse against a transpose (its T_c1_c2 is single precision)
    assert np.abs(R - M[:3, :3]).max() < tol and np.abs(T - M[:3, 3]).max() < tol / 10
    assert 0.05 < np.linalg.norm(T) < 0.15 and not [w for w in warnings if w.code == "W144"]


def _check_fold_warning(cam, K, d, messages: list[str]) -> None:
    """W147 against OpenCV: the largest image radius cv2.projectPoints reaches along the x axis (rays up to
    89.9 deg off axis; beyond the fold its images come back inwards) is the warning's radius, and a camera
    without the warning loses under 1.5% of its image to the fold."""
    if cam.distortion == "equidistant":  # images beyond 90 deg, where cv2.fisheye (x = X / Z) does not go
        assert not messages or cam.fov is None
        return
    theta = np.radians(np.linspace(0.0, 89.9, 20000))
    rays = np.column_stack([np.sin(theta), np.zeros_like(theta), np.cos(theta)])
    uv = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, d)[0].reshape(-1, 2)
    reach = np.max(uv[:, 0] - K[0, 2])  # px along x
    u, v = np.meshgrid(np.linspace(0.5, cam.width - 0.5, 64), np.linspace(0.5, cam.height - 0.5, 48))
    lost = np.mean(np.hypot(u - cam.cx, (v - cam.cy) * cam.f * cam.ax / (cam.f * cam.ay)) > reach)
    if messages:
        (m,) = messages
        said = float(m.split("farther than ")[1].split(" px")[0])
        assert abs(said - reach) < 5e-3 * reach and lost > 0.005, (m, reach, lost)
    else:
        assert lost < 0.015, (reach, lost)

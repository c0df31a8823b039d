"""Calibration files of visual-inertial SLAM tools with the wide-angle lenses (tests/data/calibration, origins in its
README): VINS-Fusion's camodocal YAML (PINHOLE, MEI), basalt's JSON (ds, eucm, kb4), Kalibr omni / ds / eucm / fov
chains, read into scenes and projected against each file's own values read independently (cv2.FileStorage, json) and
projected by the model's published formulas (mpmath, test_wide_lenses.mp_pixel) or OpenCV; unknown models refused by
name; export-calibration writes Kalibr, basalt and camodocal files that read back to the same cameras."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest
from helpers import camera_scene, compile_text
from test_wide_lenses import mp_pixel

from wiredsl.engine import geometry
from wiredsl.io import calibration as cf
from wiredsl.scene import Camera

CORPUS = Path(__file__).parent / "data" / "calibration"


def _scene(path: Path, entry: str = "first", fmt: str = "") -> str:
    return camera_scene(f'read "{path}" entry {entry}{fmt}')


def _oracle(path: Path) -> list[Camera]:
    """Each camera as the file gives it, read by cv2.FileStorage (YAML) or json, as a wiredsl Camera."""
    if path.suffix == ".json":
        v = json.loads(path.read_text())["value0"]
        out = []
        for c, (w, h) in zip(v["intrinsics"], v["resolution"], strict=True):
            p = c["intrinsics"]
            kw = {"distortion": {"kb4": "equidistant"}.get(c["camera_type"], c["camera_type"])}
            kw.update({k: p[k] for k in ("k1", "k2", "k3", "k4", "xi", "alpha", "beta", "w") if k in p})
            out.append(Camera(name="o", f=p["fx"], ay=p["fy"] / p["fx"], cx=p["cx"], cy=p["cy"], width=w, height=h,
                              **kw))
        return out
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_READ)
    if not fs.getNode("model_type").empty():  # camodocal
        def g(block, key):
            return fs.getNode(block).getNode(key).real()

        kind = fs.getNode("model_type").string()
        w, h = int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real())
        d = {k: g("distortion_parameters", k) for k in ("k1", "k2", "p1", "p2")}
        if kind == "MEI":
            fx, fy, cx, cy = (g("projection_parameters", k) for k in ("gamma1", "gamma2", "u0", "v0"))
            return [Camera(name="o", f=fx, ay=fy / fx, cx=cx, cy=cy, width=w, height=h, distortion="unified",
                           xi=g("mirror_parameters", "xi"), **d)]
        fx, fy, cx, cy = (g("projection_parameters", k) for k in ("fx", "fy", "cx", "cy"))
        return [Camera(name="o", f=fx, ay=fy / fx, cx=cx, cy=cy, width=w, height=h, **d)]
    raise AssertionError(path)


def _reference(P: np.ndarray, cam: Camera) -> np.ndarray:
    """The file's own camera projected independently: mpmath on the papers' formulas, OpenCV for pinhole and KB."""
    K = np.array([[cam.f * cam.ax, 0, cam.cx], [0, cam.f * cam.ay, cam.cy], [0, 0, 1.0]])
    if cam.distortion == "radtan":
        return cv2.projectPoints(P, np.zeros(3), np.zeros(3), K, np.array([cam.k1, cam.k2, cam.p1, cam.p2]))[0] \
            .reshape(-1, 2)
    if cam.distortion == "equidistant":
        return cv2.fisheye.projectPoints(P[:, None, :], np.zeros(3), np.zeros(3), K,
                                         np.array([cam.k1, cam.k2, cam.k3, cam.k4]))[0].reshape(-1, 2)
    return np.array([[float(v) for v in mp_pixel(p, cam)] for p in P])


WIDE = sorted(p.name for p in CORPUS.iterdir() if p.name.startswith(("vinsfusion_", "basalt_")))


def test_the_wide_angle_corpus_is_there():
    assert len(WIDE) >= 8


@pytest.mark.parametrize("name", WIDE)
def test_every_wide_angle_file_projects_as_its_own_values_do_to_1e_6_px(name, tmp_path):
    path = CORPUS / name
    oracle = _oracle(path)
    read = cf.read(path)
    assert len(read) == len(oracle)
    rng = np.random.default_rng(26)
    for i, want in enumerate(oracle):
        scene, _ = compile_text(_scene(path, ("first", "second")[i]), str(tmp_path / "a.wd"))
        cam = scene.cameras[0]
        assert cam.distortion == want.distortion
        limit = min(geometry.lens_limit(cam), np.radians(85 if want.distortion in ("radtan", "equidistant") else 120))
        theta = limit * 0.98 * rng.uniform(0, 1, 200) ** 0.5
        phi = rng.uniform(-np.pi, np.pi, 200)
        P = rng.uniform(0.3, 10, 200)[:, None] * np.column_stack(
            [np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)])
        ours, theirs = geometry.cam_to_pixels(P, cam), _reference(P, want)
        inside = (np.abs(theirs - [cam.cx, cam.cy]) < 2 * cam.width).all(axis=1)
        assert inside.sum() > 100 and np.abs(ours - theirs)[inside].max() < 1e-6, name


def test_basalt_extrinsics_place_the_second_camera():
    """cam1 from cam0: T_imu_cam[1]^-1 T_imu_cam[0], from the quaternions (x y z w) by scipy."""
    from scipy.spatial.transform import Rotation

    v = json.loads((CORPUS / "basalt_euroc_ds_calib.json").read_text())["value0"]["T_imu_cam"]
    T = []
    for p in v:
        M = np.eye(4)
        M[:3, :3] = Rotation.from_quat([p["qx"], p["qy"], p["qz"], p["qw"]]).as_matrix()
        M[:3, 3] = [p["px"], p["py"], p["pz"]]
        T.append(M)
    want = np.linalg.inv(T[1]) @ T[0]
    got = cf.read(CORPUS / "basalt_euroc_ds_calib.json")[1]
    assert np.abs(got.R - want[:3, :3]).max() < 1e-12 and np.abs(got.T - want[:3, 3]).max() < 1e-12
    assert 0.10 < np.linalg.norm(got.T) < 0.12  # EuRoC's 11 cm baseline


def _kalibr(tmp_path: Path, cam0: str, cam1: str) -> Path:
    path = tmp_path / "camchain.yaml"
    path.write_text(f"cam0:\n{cam0}cam1:\n  T_cn_cnm1:\n  - [1.0, 0.0, 0.0, -0.11]\n  - [0.0, 1.0, 0.0, 0.0]\n"
                    f"  - [0.0, 0.0, 1.0, 0.0]\n  - [0.0, 0.0, 0.0, 1.0]\n{cam1}")
    return path


def test_kalibr_omni_ds_eucm_and_fov_chains_read_as_their_models(tmp_path):
    """Kalibr's layouts (intrinsics [xi, fu, fv, pu, pv], [xi, alpha, ...], [alpha, beta, ...], distortion fov [w])
    with the real VINS-Fusion MEI and basalt DS values: projected as those files' own cameras."""
    mei = _oracle(CORPUS / "vinsfusion_mynteye_left_mei.yaml")[0]
    ds = _oracle(CORPUS / "basalt_tumvi_512_ds_calib.json")[0]
    omni = (f"  camera_model: omni\n  intrinsics: [{mei.xi!r}, {mei.f!r}, {mei.f * mei.ay!r}, {mei.cx!r}, {mei.cy!r}]\n"
            f"  distortion_model: radtan\n  distortion_coeffs: [{mei.k1!r}, {mei.k2!r}, {mei.p1!r}, {mei.p2!r}]\n"
            f"  resolution: [{mei.width}, {mei.height}]\n")
    dsb = (f"  camera_model: ds\n  intrinsics: [{ds.xi!r}, {ds.alpha!r}, {ds.f!r}, {ds.f * ds.ay!r}, {ds.cx!r}, "
           f"{ds.cy!r}]\n  distortion_model: none\n  distortion_coeffs: []\n  resolution: [512, 512]\n")
    eucm = "  camera_model: eucm\n  intrinsics: [0.6, 1.1, 190.0, 191.0, 256.0, 255.0]\n  distortion_model: none\n" \
           "  distortion_coeffs: []\n  resolution: [512, 512]\n"
    fov = "  camera_model: pinhole\n  intrinsics: [260.0, 261.0, 320.0, 240.0]\n  distortion_model: fov\n" \
          "  distortion_coeffs: [0.93]\n  resolution: [640, 480]\n"
    rng = np.random.default_rng(3)
    P = rng.uniform(-1, 1, (100, 3)) + [0, 0, 2.5]
    for a, b, want in ((omni, dsb, (mei, ds)), (eucm, fov, None)):
        got = cf.read(_kalibr(tmp_path, a, b))
        assert [c.model for c in got] == (["unified", "ds"] if want else ["eucm", "fov"])
        assert np.abs(got[1].T - [-0.11, 0, 0]).max() == 0
        if want:
            for i, w in enumerate(want):
                scene, _ = compile_text(_scene(tmp_path / "camchain.yaml", ("first", "second")[i]),
                                        str(tmp_path / "a.wd"))
                assert np.abs(geometry.cam_to_pixels(P, scene.cameras[0]) - _reference(P, w)).max() < 1e-6
        else:
            assert got[0].dist == (0.6, 1.1) and got[1].dist == (0.93,)


@pytest.mark.parametrize("text,name", [
    ("%YAML:1.0\n---\nmodel_type: SCARAMUZZA\ncamera_name: c\nimage_width: 640\nimage_height: 480\n"
     "projection_parameters:\n   a0: -1.0\n", "SCARAMUZZA"),
    ('{"value0": {"intrinsics": [{"camera_type": "bal", "intrinsics": {"fx": 1, "fy": 1, "cx": 0, "cy": 0}}]}}',
     "bal"),
    ("cam0:\n  camera_model: omni\n  intrinsics: [0.9, 300, 300, 320, 240]\n  distortion_model: equidistant\n"
     "  distortion_coeffs: [0, 0, 0, 0]\n  resolution: [640, 480]\n", "omni-equidistant"),
    ("cam0:\n  camera_model: scaramuzza\n  intrinsics: [1, 2, 3, 4]\n  resolution: [640, 480]\n", "scaramuzza"),
])
def test_a_model_wiredsl_does_not_implement_is_refused_by_name(tmp_path, text, name):
    path = tmp_path / ("c.json" if text.startswith("{") else "c.yaml")
    path.write_text(text)
    with pytest.raises(cf.CalibrationFileError) as err:
        cf.read(path)
    msg = str(err.value)
    assert f"'{name}'" in msg and ("wiredsl's lens models are" in msg or "wiredsl reads" in msg), msg
    from click.testing import CliRunner

    from wiredsl.cli import main

    (tmp_path / "s.wd").write_text(_scene(path))
    r = CliRunner().invoke(main, ["check", str(tmp_path / "s.wd")])
    assert r.exit_code == 1 and name in r.output and "Traceback" not in r.output


@pytest.mark.parametrize("lens,files", [
    ("  distortion ds\n  xi -0.2\n  alpha 0.57\n", ("camchain.yaml", "basalt_calib.json")),
    ("  distortion unified\n  xi 1.4\n  k1 -0.3\n  p1 0.001\n", ("camchain.yaml", "left_camodocal.yaml")),
    ("  distortion eucm\n  alpha 0.6\n  beta 1.1\n", ("camchain.yaml", "basalt_calib.json")),
    ("  distortion fov\n  w 52deg\n", ("camchain.yaml", "basalt_calib.json")),
    ("  distortion equidistant\n  k1 0.01\n", ("camchain.yaml", "basalt_calib.json", "left_camodocal.yaml"))])
def test_export_calibration_writes_slam_files_that_read_back_to_the_same_cameras(tmp_path, lens, files):
    from click.testing import CliRunner
    from test_wide_lenses import _scene as wide_scene

    from wiredsl.cli import main

    path = wide_scene(tmp_path, lens, "  calibration covariance order [left.f] matrix [[1e-6]]")
    r = CliRunner().invoke(main, ["export-calibration", str(path), "-o", str(tmp_path / "out")])
    assert r.exit_code == 0, r.output
    from wiredsl.language.compile import compile_file

    scene = compile_file(str(path))[0]
    left, right = (scene.camera(getattr(scene.rig, s).camera) for s in ("left", "right"))
    R, T = scene.rig.stereo_extrinsics()
    rng = np.random.default_rng(5)
    P = rng.uniform(-1, 1, (50, 3)) + [0, 0, 2.0]
    for name in files:
        text = _scene(tmp_path / "out" / name)
        for i, want in enumerate((left, right) if name != "left_camodocal.yaml" else (left,)):
            got, _ = compile_text(text.replace("entry first", f"entry {('first', 'second')[i]}"),
                                  str(tmp_path / "a.wd"))
            assert np.abs(geometry.cam_to_pixels(P, got.cameras[0]) - geometry.cam_to_pixels(P, want)).max() < 1e-9
        if name != "left_camodocal.yaml":
            second = cf.read(tmp_path / "out" / name)[1]
            assert np.abs(second.R - R).max() < 1e-12 and np.abs(second.T - T).max() < 1e-12

"""Calibration files: OpenCV (read back from cv2.FileStorage itself), ROS and Kalibr, in scenes and exported."""

from __future__ import annotations

import textwrap

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from helpers import compile_text

from wiredsl.cli import main
from wiredsl.diagnostics import WiredslError
from wiredsl.engine.simulate import Options, simulate
from wiredsl.io import calibration as cf
from wiredsl.language.compile import compile_file

K = np.array([[612.5, 0, 318.25], [0, 624.75, 241.5], [0, 0, 1.0]])
D = np.array([[-0.021, 0.0013, 0.0004, -0.0002]])


def _fs_write(path, **items):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in items.items():
        fs.write(k, v)
    fs.release()


@pytest.mark.parametrize("suffix", [".yaml", ".xml"])
def test_files_written_by_cv2_filestorage_are_read(tmp_path, suffix):
    one = tmp_path / f"one{suffix}"
    _fs_write(one, image_width=640, image_height=480, camera_matrix=K, distortion_coefficients=D)
    (c,) = cf.read(one)
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (612.5, 624.75, 318.25, 241.5, 640, 480)
    assert c.dist == (*D.ravel(), 0, 0, 0, 0) and c.model == "radtan"
    rvec = np.array([0.01, -0.2, 0.03])
    R, T = cv2.Rodrigues(rvec)[0], np.array([[-0.12], [0.001], [0.002]])
    two = tmp_path / f"two{suffix}"
    _fs_write(two, M1=K, D1=D, M2=K * [[1.01], [1.01], [1]], D2=D * 0.5, R=R, T=T)
    first, second = cf.read(two)
    assert first.R is None and np.array_equal(second.R, R) and np.array_equal(second.T, T.ravel())
    assert second.fx == pytest.approx(612.5 * 1.01, abs=0) and second.dist[:4] == tuple(D.ravel() * 0.5)


def _camera_text(body: str) -> str:
    return textwrap.dedent(f"""\
        wiredsl 1
        model m {{
          line a from (2, -0.5, 0.3) to (2, 0.5, 1.8)
          ellipse e centre (3, 0, 1) normal (1, 0.2, 0) axis (0, 0, 1) radii (0.3, 0.2)
        }}
        place m as p
        camera c {{
        {textwrap.indent(body, '  ')}
        }}
        rig r {{
          left c at (0, 0.06, 1) looking (1, 0, 0)
          right c at (0, -0.06, 1) looking (1, 0, 0)
        }}
        path run {{ pose (0, 0) }}
        """)


def test_a_camera_read_from_a_file_projects_exactly_as_the_same_camera_declared(tmp_path):
    _fs_write(tmp_path / "cam.yaml", image_width=640, image_height=480, camera_matrix=K, distortion_coefficients=D)
    read, _ = compile_text(_camera_text('read "cam.yaml"'), str(tmp_path / "a.wd"))
    k1, k2, p1, p2 = D.ravel()
    declared, _ = compile_text(_camera_text(
        f"focal 612.5px\naspect (1, {624.75 / 612.5!r})\ncentre (318.25px, 241.5px)\nsize (640px, 480px)\n"
        f"k1 {float(k1)!r}\nk2 {float(k2)!r}\np1 {float(p1)!r}\np2 {float(p2)!r}"), str(tmp_path / "b.wd"))
    assert read.cameras == declared.cameras
    a, b = simulate(read, Options()), simulate(declared, Options())
    for va, vb in ((a[0].left, b[0].left), (a[0].right, b[0].right)):
        assert [f.fid for f in va.features] == [f.fid for f in vb.features] and va.features
        for fa, fb in zip(va.features, vb.features, strict=True):
            assert np.array_equal(fa.points, fb.points)
    # and OpenCV agrees with the projection of the read camera
    cam = read.cameras[0]
    X = np.array([[0.3, -0.2, 2.0], [-0.4, 0.1, 3.5]])
    ours = cf_project(cam, X)
    theirs = cv2.projectPoints(X, np.zeros(3), np.zeros(3), K, D)[0].reshape(-1, 2)
    assert np.abs(ours - theirs).max() < 1e-9


def cf_project(cam, X):
    from wiredsl.engine import geometry

    return geometry.cam_to_pixels(X, cam)


def test_statements_beside_read_override_the_file(tmp_path):
    _fs_write(tmp_path / "cam.yaml", image_width=640, image_height=480, camera_matrix=K, distortion_coefficients=D)
    scene, _ = compile_text(_camera_text('k2 0\nread "cam.yaml"\ncentre (320px, 240px)'), str(tmp_path / "a.wd"))
    cam = scene.cameras[0]
    assert (cam.k2, cam.cx, cam.cy, cam.f) == (0.0, 320.0, 240.0, 612.5)


ROS = """\
image_width: 752
image_height: 480
camera_name: narrow_stereo/left
camera_matrix:
  rows: 3
  cols: 3
  data: [461.6, 0.0, 362.7, 0.0, 460.3, 248.1, 0.0, 0.0, 1.0]
distortion_model: plumb_bob
distortion_coefficients:
  rows: 1
  cols: 5
  data: [-0.2917, 0.0742, 0.0003, -0.0001, 0.0]
rectification_matrix:
  rows: 3
  cols: 3
  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]
projection_matrix:
  rows: 3
  cols: 4
  data: [461.6, 0, 362.7, 0, 0, 460.3, 248.1, 0, 0, 0, 1, 0]
"""

R_KALIBR = cv2.Rodrigues(np.array([0.00006, 0.00376, -0.00231]))[0]
T_KALIBR = np.array([-0.11007, 0.00039, -0.00085])
KALIBR = """\
cam0:
  camera_model: pinhole
  intrinsics: [461.6, 460.3, 362.7, 248.1]
  distortion_model: radtan
  distortion_coeffs: [-0.2917, 0.0742, 0.0003, -0.0001]
  resolution: [752, 480]
  rostopic: /cam0/image_raw
cam1:
  T_cn_cnm1:
""" + "".join(f"  - [{', '.join(repr(float(x)) for x in row)}]\n" for row in np.vstack(
    [np.hstack([R_KALIBR, T_KALIBR[:, None]]), [[0, 0, 0, 1.0]]])) + """\
  camera_model: pinhole
  intrinsics: [460.0, 459.1, 373.2, 254.8]
  distortion_model: radtan
  distortion_coeffs: [-0.2838, 0.0691, 0.0002, 0.00002]
  resolution: [752, 480]
"""

KALIBR_RESULTS = """\
Calibration results
===================
Reprojection error squarred (cam0):  mean 0.12, median 0.09, std: 0.1
cam0 (/cam0/image_raw):
    type: <class 'aslam_cv.libaslam_cv_python.DistortedPinholeCameraGeometry'>
    distortion: [-0.2917 0.0742 0.0003 -0.0001] +- [0.0021 0.0034 0.0001 0.0001]
    projection: [461.6 460.3 362.7 248.1] +- [0.31 0.30 0.52 0.41]
    reprojection error: [0.0, 0.0] +- [0.21, 0.19]

cam1 (/cam1/image_raw):
    type: <class 'aslam_cv.libaslam_cv_python.DistortedPinholeCameraGeometry'>
    distortion: [-0.2838 0.0691 0.0002 0.00002] +- [0.0020 0.0031 0.0001 0.0001]
    projection: [460.0 459.1 373.2 254.8] +- [0.29 0.28 0.50 0.40]
    reprojection error: [0.0, 0.0] +- [0.20, 0.18]

baseline T_1_0:
    q: [0.0000 0.0019 -0.0012 0.99999] +- [0.0003 0.0004 0.0001]
    t: [-0.1101 0.0004 -0.0009] +- [0.0001 0.0001 0.0003]
"""


def test_ros_and_kalibr_files(tmp_path):
    (tmp_path / "left.yaml").write_text(ROS)
    (c,) = cf.read(tmp_path / "left.yaml")
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (461.6, 460.3, 362.7, 248.1, 752, 480)
    assert c.dist == (-0.2917, 0.0742, 0.0003, -0.0001, 0, 0, 0, 0)
    (tmp_path / "camchain.yaml").write_text(KALIBR)
    c0, c1 = cf.read(tmp_path / "camchain.yaml")
    assert c0.R is None and (c1.fx, c1.width) == (460.0, 752) and c1.T == pytest.approx([-0.11007, 0.00039, -0.00085])
    (tmp_path / "results-cam.txt").write_text(KALIBR_RESULTS)
    r0, r1 = cf.read(tmp_path / "results-cam.txt")
    assert r0.sigma["f"] == 0.31 and r0.sigma["cx"] == 0.52 and r0.sigma["k"] == 0.0021
    assert r1.sigma["tx"] == 0.0001 and r1.sigma["tz"] == 0.0003
    assert r1.sigma["rx"] == 0.0003  # Kalibr prints rotation-vector sigmas: taken as they are


def test_a_rig_from_a_kalibr_camchain(tmp_path):
    (tmp_path / "camchain.yaml").write_text(KALIBR)
    text = _camera_text('read "camchain.yaml"').replace(
        "camera c {", "camera c1 {\n  read \"camchain.yaml\" entry second\n}\ncamera c {").replace(
        "right c at (0, -0.06, 1) looking (1, 0, 0)", 'right c1 relative "camchain.yaml"')
    scene, _ = compile_text(text, str(tmp_path / "a.wd"))
    R, T = scene.rig.stereo_extrinsics()
    assert np.abs(R - R_KALIBR).max() < 1e-12 and np.abs(T - T_KALIBR).max() < 1e-12


def test_export_round_trips_through_opencv_and_back_into_a_scene(tmp_path):
    out = tmp_path / "cal"
    r = CliRunner().invoke(main, ["export-calibration", "scenes/lab.wd", "-o", str(out)])
    assert r.exit_code == 0, r.output
    scene, _, _ = compile_file("scenes/lab.wd")
    cams = {c.name: c for c in scene.cameras}
    fs = cv2.FileStorage(str(out / "stereo.yaml"), cv2.FILE_STORAGE_READ)  # OpenCV's own reader
    for i, side in ((1, "left"), (2, "right")):
        c = cams[getattr(scene.rig, side).camera]
        assert np.array_equal(fs.getNode(f"M{i}").mat(), [[c.f * c.ax, 0, c.cx], [0, c.f * c.ay, c.cy], [0, 0, 1]])
        assert np.array_equal(fs.getNode(f"D{i}").mat().ravel(), [c.k1, c.k2, c.p1, c.p2, c.k3])  # OpenCV's five
    R, T = fs.getNode("R").mat(), fs.getNode("T").mat().ravel()
    # the right camera seen from the left through OpenCV's R, T equals the rig's own geometry
    R_l, p_l = np.array(scene.rig.left.rotation), np.array(scene.rig.left.position)
    R_r, p_r = np.array(scene.rig.right.rotation), np.array(scene.rig.right.position)
    X_l = np.array([0.3, -0.1, 2.5])
    P = R_l @ X_l + p_l
    assert np.abs(R @ X_l + T - R_r.T @ (P - p_r)).max() < 1e-12
    # and back: the exported files rebuild the same cameras and mount
    left, right = scene.rig.left, scene.rig.right
    text = (tmp_path / "lab.wd")
    lab = open("scenes/lab.wd").read()
    lab = lab.replace('include "models/', f'include "{__import__("os").path.abspath("scenes/models")}/')
    lab = lab.replace('file "lab.info"', f'file "{__import__("os").path.abspath("scenes/lab.info")}"')
    start = lab.index("camera cam_l {")
    end = lab.index("rig head {")
    lab = lab[:start] + 'camera cam_l {\n  read "cal/stereo.yaml"\n}\ncamera cam_r {\n  read "cal/stereo.yaml" ' \
                        'entry second\n}\n' + lab[end:]
    lab = lab.replace(lab[lab.index("  right cam_r"):lab.index("\n", lab.index("  right cam_r"))],
                      '  right cam_r relative "cal/stereo.yaml"')
    text.write_text(lab)
    again, _, _ = compile_file(text)
    cams2 = {c.name: c for c in again.cameras}
    for c in ("cam_l", "cam_r"):
        a, b = cams[c].model_dump(), cams2[c].model_dump()
        assert all(abs(a[k] - b[k]) <= 1e-12 * max(1, abs(a[k])) if isinstance(a[k], float) else a[k] == b[k]
                   for k in a if k != "name")
    assert np.abs(np.array(again.rig.right.rotation) - right.rotation).max() < 1e-12
    assert np.abs(np.array(again.rig.right.position) - right.position).max() < 1e-12
    assert again.rig.left == left
    ros = cf.read(out / "right.yaml", "ros")[0]
    assert (ros.fx, ros.cx, ros.dist[:4]) == (cams["cam_r"].f * cams["cam_r"].ax, cams["cam_r"].cx,
                                              (cams["cam_r"].k1, 0.0, 0.0, 0.0))


def test_export_of_a_trial_writes_the_rig_that_trial_saw(tmp_path):
    """The exported cameras of trial K are those in `build --trial K`'s own dump (its views' cameras and poses)."""
    args = ["scenes/lab.wd", "--trial", "3", "--seed", "7"]
    assert CliRunner().invoke(main, ["export-calibration", "-o", str(tmp_path / "a"), *args]).exit_code == 0
    built = CliRunner().invoke(main, ["build", "-o", str(tmp_path / "b"), "--no-svg", "--pose", "0", *args])
    assert built.exit_code == 0
    view = __import__("json").loads((tmp_path / "b" / "features.json").read_text())["poses"][0]
    fs = cv2.FileStorage(str(tmp_path / "a" / "stereo.yaml"), cv2.FILE_STORAGE_READ)
    for i, side in ((1, "left"), (2, "right")):
        c = view[side]["camera"]
        M = [[c["f"] * c["ax"], 0, c["cx"]], [0, c["f"] * c["ay"], c["cy"]], [0, 0, 1]]
        assert np.abs(fs.getNode(f"M{i}").mat() - M).max() < 1e-9
        assert np.abs(fs.getNode(f"D{i}").mat().ravel() - [c["k1"], c["k2"], c["p1"], c["p2"], c["k3"]]).max() < 1e-15
    R_l, t_l = np.array(view["left"]["rotation"]), np.array(view["left"]["translation"])
    R_r, t_r = np.array(view["right"]["rotation"]), np.array(view["right"]["translation"])
    assert np.abs(fs.getNode("R").mat() - R_r @ R_l.T).max() < 1e-12
    assert np.abs(fs.getNode("T").mat().ravel() - (t_r - R_r @ R_l.T @ t_l)).max() < 1e-12
    nominal = CliRunner().invoke(main, ["export-calibration", "scenes/lab.wd", "-o", str(tmp_path / "n")])
    assert nominal.exit_code == 0
    assert (tmp_path / "a" / "stereo.yaml").read_bytes() != (tmp_path / "n" / "stereo.yaml").read_bytes()
    r = CliRunner().invoke(main, ["export-calibration", "scenes/lab.wd", "--trial", "3"])
    assert r.exit_code == 2 and "--seed" in r.output


@pytest.mark.parametrize("content, message", [
    (KALIBR.replace("radtan", "fov", 1), "the fov model has 1 numbers (w), the file has 4"),
    (KALIBR.replace("camera_model: pinhole", "camera_model: omni", 1), "intrinsics [xi, fu, fv, pu, pv] must have 5"),
    (KALIBR.replace("camera_model: pinhole", "camera_model: scaramuzza", 1), "camera model 'scaramuzza' is not"),
    (ROS.replace("cols: 5\n  data: [-0.2917, 0.0742, 0.0003, -0.0001, 0.0]",
                 "cols: 12\n  data: [-0.2917, 0.0742, 0.0003, -0.0001, 0, 0, 0, 0, 0.001, 0, 0, 0]"),
     "thin-prism distortion (s1..s4 = 0.001, 0, 0, 0)"),
    ("cam0: [1, 2\n", "not valid YAML"),
    ("%YAML:1.0\nfoo: 1\n", "no camera matrix in the file"),
])
def test_bad_calibration_files_get_a_diagnostic_at_the_path(tmp_path, content, message):
    (tmp_path / "bad.yaml").write_text(content)
    text = _camera_text('read "bad.yaml"')
    with pytest.raises(WiredslError) as err:
        compile_text(text, str(tmp_path / "a.wd"))
    (d,) = [d for d in err.value.diagnostics if d.code == "E141"]
    line = text.splitlines()[d.span.line - 1]
    assert message in d.message and line[d.span.col - 1:].startswith('"bad.yaml"')


def test_relative_needs_extrinsics_and_excludes_at(tmp_path):
    _fs_write(tmp_path / "cam.yaml", image_width=640, image_height=480, camera_matrix=K, distortion_coefficients=D)
    text = _camera_text('read "cam.yaml"').replace("right c at (0, -0.06, 1) looking (1, 0, 0)",
                                                   'right c relative "cam.yaml"')
    with pytest.raises(WiredslError) as err:
        compile_text(text, str(tmp_path / "a.wd"))
    assert [d.code for d in err.value.diagnostics] == ["E141"] and "no extrinsics" in err.value.diagnostics[0].message
    text = _camera_text('read "cam.yaml"').replace("right c at (0, -0.06, 1) looking (1, 0, 0)",
                                                   'right c at (0, 0, 1) relative "cam.yaml"')
    with pytest.raises(WiredslError) as err:
        compile_text(text, str(tmp_path / "a.wd"))
    assert [d.code for d in err.value.diagnostics] == ["E103"]


def test_kalibr_standard_deviations_become_the_rigs_calibration_uncertainty(tmp_path):
    (tmp_path / "camchain.yaml").write_text(KALIBR)
    (tmp_path / "results-cam.txt").write_text(KALIBR_RESULTS)
    text = _camera_text('read "camchain.yaml"').replace(
        "right c at (0, -0.06, 1) looking (1, 0, 0)",
        'right c at (0, -0.06, 1) looking (1, 0, 0)\n  calibration covariance kalibr "results-cam.txt"')
    scene, _ = compile_text(text, str(tmp_path / "a.wd"))
    c = scene.rig.calibration
    assert c.kind == "covariance" and c.order[:3] == ["left.f", "left.ay", "left.cx"] and "right.tz" in c.order
    M = np.array(c.matrix)
    assert M[c.order.index("left.cx"), c.order.index("left.cx")] == pytest.approx(0.52**2)
    assert M[c.order.index("right.tz"), c.order.index("right.tz")] == pytest.approx(0.0003**2)
    assert np.count_nonzero(M - np.diag(np.diag(M))) == 0
    two = 'kalibr "results-cam.txt" order [right.tx, left.f]'
    subset, _ = compile_text(text.replace('kalibr "results-cam.txt"', two), str(tmp_path / "a.wd"))
    assert subset.rig.calibration.order == ["right.tx", "left.f"]
    with pytest.raises(WiredslError) as err:
        compile_text(text.replace('kalibr "results-cam.txt"', 'kalibr "results-cam.txt" order [left.rx]'),
                     str(tmp_path / "a.wd"))
    assert [d.code for d in err.value.diagnostics] == ["E104"]


def test_ros_export_carries_the_stereo_rectification_as_cv2_stereo_rectify_gives_it(tmp_path):
    """right.yaml's R and P are ROS's stereo convention: P's Tx = -fx' * baseline; both as cv2.stereoRectify."""
    out = tmp_path / "cal"
    assert CliRunner().invoke(main, ["export-calibration", "scenes/lab.wd", "-o", str(out)]).exit_code == 0
    fs = cv2.FileStorage(str(out / "stereo.yaml"), cv2.FILE_STORAGE_READ)
    size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
    T = fs.getNode("T").mat()
    want = cv2.stereoRectify(fs.getNode("M1").mat(), fs.getNode("D1").mat(), fs.getNode("M2").mat(),
                             fs.getNode("D2").mat(), size, fs.getNode("R").mat(), T)[:4]
    for side, R_want, P_want in (("left", want[0], want[2]), ("right", want[1], want[3])):
        ros = cv2.FileStorage(str(out / f"{side}.yaml"), cv2.FILE_STORAGE_READ)
        R = np.array([ros.getNode("rectification_matrix").getNode("data").at(i).real() for i in range(9)]).reshape(3, 3)
        P = np.array([ros.getNode("projection_matrix").getNode("data").at(i).real() for i in range(12)]).reshape(3, 4)
        assert np.abs(R - R_want).max() < 1e-12 and np.abs(P - P_want).max() < 1e-9
        assert ros.getNode("distortion_model").string() == "plumb_bob"
        assert ros.getNode("distortion_coefficients").getNode("cols").real() == 5
    assert P[0, 3] == pytest.approx(-P[0, 0] * np.linalg.norm(T), rel=1e-3)  # Tx = -fx' * baseline
    assert P_want[0, 3] != 0 and want[2][0, 3] == 0  # the right camera carries the baseline, the left none


def test_stereo_rectify_matches_opencv_for_random_rigs():
    rng = np.random.default_rng(5)
    for _ in range(50):
        K1 = np.array([[rng.uniform(400, 900), 0, rng.uniform(300, 340)], [0, rng.uniform(400, 900), 240], [0, 0, 1]])
        K2 = K1 + np.diag([rng.uniform(-5, 5), rng.uniform(-5, 5), 0])
        D1, D2 = rng.normal(0, 0.08, 5), rng.normal(0, 0.08, 8)  # strong lenses too: OpenCV's stopping rule
        R = cv2.Rodrigues(rng.normal(0, 0.05, 3))[0]
        T = np.array([[-0.12], [0.002], [0.001]]) + rng.normal(0, 0.003, (3, 1))
        size = (640 + int(rng.integers(0, 3)), 480 + int(rng.integers(0, 3)))
        want = cv2.stereoRectify(K1, D1, K2, D2, size, R, T)[:4]
        got = cf.stereo_rectify(K1, D1, K2, D2, size, R, T)
        for a, b in zip(want, got, strict=True):
            assert np.abs(a - b).max() < 1e-9


def _fisheye_rigs(n: int, seed: int):
    """Random fisheye rigs (about 100 to 150 deg across) with OpenCV's flag of whether it can rectify them:
    its undistortion of a side's midpoint gives up (-1e6) where its Newton steps do not converge."""
    rng = np.random.default_rng(seed)
    for _ in range(n):
        f = rng.uniform(600, 800)
        K1 = np.array([[f, 0, rng.uniform(620, 660)], [0, f * rng.uniform(0.98, 1.02), rng.uniform(460, 500)],
                       [0, 0, 1]])
        K2 = K1 + np.diag([rng.uniform(-5, 5), rng.uniform(-5, 5), 0])
        D1, D2 = rng.normal(0, 0.02, 4), rng.normal(0, 0.02, 4)
        R = cv2.Rodrigues(rng.normal(0, 0.05, 3))[0]
        T = np.array([[-0.12], [0.002], [0.001]]) + rng.normal(0, 0.003, (3, 1))
        w, h = 1280 + int(rng.integers(0, 3)), 960 + int(rng.integers(0, 3))
        mids = np.array([[[w // 2, 0], [w, h // 2], [w // 2, h], [0, h // 2]]], dtype=float)
        ok = all((cv2.fisheye.undistortPoints(mids, K, D) > -1e5).all() for K, D in ((K1, D1), (K2, D2)))
        yield (K1, D1, K2, D2, (w, h), R, T), ok


def test_fisheye_stereo_rectify_matches_opencv_for_random_rigs():
    """cv2.fisheye.stereoRectify with CALIB_ZERO_DISPARITY, balance 0, fov_scale 1: every matrix to 1e-9."""
    compared = 0
    for args, ok in _fisheye_rigs(50, 5):
        want = cv2.fisheye.stereoRectify(*args, cv2.CALIB_ZERO_DISPARITY, balance=0.0, fov_scale=1.0)[:4]
        got = cf.fisheye_stereo_rectify(*args)
        assert np.abs(want[0] - got[0]).max() < 1e-12 and np.abs(want[1] - got[1]).max() < 1e-12
        assert np.all(np.isfinite(got[2])) and got[3][0, 3] < 0
        if ok:
            compared += 1
            assert np.abs(want[2] - got[2]).max() < 1e-9 and np.abs(want[3] - got[3]).max() < 1e-9
    assert compared >= 45


def test_ros_export_of_a_190_degree_fisheye_rig_is_rectified(tmp_path):
    """scenes/fisheye.wd: past 180 deg OpenCV's new focal length is meaningless (its undistortion turns the
    sides' midpoints, 95 deg off the axis, through the centre to the opposite side): R1, R2 and Tx / f' are
    OpenCV's, f' the smaller of the cameras' fy and the principal point the mean of theirs (documented rule)."""
    out = tmp_path / "cal"
    r = CliRunner().invoke(main, ["export-calibration", "scenes/fisheye.wd", "-o", str(out)])
    assert r.exit_code == 0, r.output
    fs = cv2.FileStorage(str(out / "stereo.yaml"), cv2.FILE_STORAGE_READ)
    size = (int(fs.getNode("image_width").real()), int(fs.getNode("image_height").real()))
    M1, M2, T = fs.getNode("M1").mat(), fs.getNode("M2").mat(), fs.getNode("T").mat()
    want = cv2.fisheye.stereoRectify(M1, fs.getNode("D1").mat(), M2, fs.getNode("D2").mat(), size,
                                     fs.getNode("R").mat(), T, cv2.CALIB_ZERO_DISPARITY)[:4]
    top = np.array([[[size[0] // 2, 0]]], dtype=float)
    assert cv2.fisheye.undistortPoints(top, M1, fs.getNode("D1").mat())[0, 0, 1] > 0  # the top turned to the bottom
    f = min(M1[1, 1], M2[1, 1])
    for side, R_want in (("left", want[0]), ("right", want[1])):
        ros = cv2.FileStorage(str(out / f"{side}.yaml"), cv2.FILE_STORAGE_READ)
        R = np.array([ros.getNode("rectification_matrix").getNode("data").at(i).real() for i in range(9)]).reshape(3, 3)
        P = np.array([ros.getNode("projection_matrix").getNode("data").at(i).real() for i in range(12)]).reshape(3, 4)
        assert np.abs(R - R_want).max() < 1e-12 and ros.getNode("distortion_model").string() == "equidistant"
        assert P[0, 0] == P[1, 1] == pytest.approx(f, rel=1e-15)
        assert P[:2, 2] == pytest.approx((M1[:2, 2] + M2[:2, 2]) / 2, rel=1e-15)
    assert P[0, 3] / P[0, 0] == pytest.approx((want[1] @ T)[0, 0], rel=1e-12)  # Tx = -f' * baseline
    assert P[0, 3] == pytest.approx(-f * np.linalg.norm(T), rel=1e-3)

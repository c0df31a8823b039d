"""Calibration files as the tools write them (beyond the real corpus): FileStorage JSON and 2-channel
matrices, the names each tool uses, ROS message dumps, Kalibr chains and results in every layout, the
warnings on silently wrong cameras, and malformed files (E141 at the path, never a crash)."""

from __future__ import annotations

import textwrap

import cv2
import numpy as np
import pytest
from click.testing import CliRunner
from helpers import compile_text

from wiredsl.cli import main
from wiredsl.diagnostics import WiredslError
from wiredsl.io import calibration as cf

K = np.array([[612.5, 0, 318.25], [0, 624.75, 241.5], [0, 0, 1.0]])
D5 = np.array([[-0.21, 0.013, 0.0004, -0.0002, 0.031]])  # OpenCV's default five, k3 free


def _fs_write(path, **items):
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in items.items():
        fs.write(k, v)
    fs.release()


def _scene(cameras: str, rig: str = "left c at (0, 0.06, 1) looking (1, 0, 0)\n"
                                     "right c at (0, -0.06, 1) looking (1, 0, 0)") -> str:
    return textwrap.dedent("""\
        wiredsl 1
        model m {
          line a from (2, -0.5, 0.3) to (2, 0.5, 1.8)
        }
        place m as p
        """) + cameras + "\nrig r {\n" + textwrap.indent(rig, "  ") + "\n}\npath run { pose (0, 0) }\n"


def _compile(tmp_path, cameras, rig=None):
    text = _scene(cameras, rig) if rig else _scene(cameras)
    return compile_text(text, str(tmp_path / "a.wd"))


def _error(tmp_path, cameras, rig=None):
    with pytest.raises(WiredslError) as err:
        _compile(tmp_path, cameras, rig)
    return [d for d in err.value.diagnostics if d.severity == "error"]


# ------------------------------------------------------------------ containers and names

@pytest.mark.parametrize("suffix", [".json", ".yaml", ".xml"])
def test_filestorage_in_every_container_with_other_matrices_beside(tmp_path, suffix):
    path = tmp_path / f"cam{suffix}"
    image_points = np.random.default_rng(1).uniform(0, 600, (8, 54, 2)).astype(np.float32)  # dt "2f"
    _fs_write(path, image_Width=640, image_Height=480, Camera_Matrix=K, Distortion_Coefficients=D5.T,
              Image_points=image_points, Per_View_Reprojection_Errors=np.ones((8, 1), np.float32))
    (c,) = cf.read(path)
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height, c.model) == (612.5, 624.75, 318.25, 241.5, 640, 480, "radtan")
    assert c.dist == (-0.21, 0.013, 0.0004, -0.0002, 0.031, 0, 0, 0)
    scene, _ = _compile(tmp_path, f'camera c {{\n  read "cam{suffix}"\n}}')
    assert scene.cameras[0].k3 == 0.031


def test_opencv_fisheye_and_rational_files(tmp_path):
    _fs_write(tmp_path / "fish.yaml", image_width=640, image_height=480, camera_matrix=K,
              distortion_coefficients=np.array([[0.01, -0.002, 0.0003, -0.00004]]), fisheye_model=1)
    (c,) = cf.read(tmp_path / "fish.yaml")
    assert c.model == "equidistant" and c.dist == (0.01, -0.002, 0.0003, -0.00004)
    rational = np.array([[-0.2, 0.01, 0.001, 0.002, 0.03, 0.1, 0.02, 0.003]])
    _fs_write(tmp_path / "rat.yaml", image_width=640, image_height=480, camera_matrix=K,
              distortion_coefficients=rational)
    scene, _ = _compile(tmp_path, 'camera c {\n  read "rat.yaml"\n}')
    cam = scene.cameras[0]
    assert (cam.k1, cam.k2, cam.p1, cam.p2, cam.k3, cam.k4, cam.k5, cam.k6) == tuple(rational.ravel())


def test_stereo_calibs_two_files_intrinsics_and_extrinsics(tmp_path):
    R = cv2.Rodrigues(np.array([0.01, -0.03, 0.002]))[0]
    T = np.array([[-0.11], [0.001], [0.002]])
    _fs_write(tmp_path / "intrinsics.yml", M1=K, D1=D5, M2=K * [[1.01], [1.01], [1]], D2=D5 * 0.5)
    _fs_write(tmp_path / "extrinsics.yml", R=R, T=T, R1=np.eye(3), R2=np.eye(3), P1=np.eye(3, 4), P2=np.eye(3, 4),
              Q=np.eye(4))
    cameras = ('camera c {\n  read "intrinsics.yml"\n  size (640px, 480px)\n}\n'
               'camera c2 {\n  read "intrinsics.yml" entry second\n  size (640px, 480px)\n}')
    scene, warnings = _compile(tmp_path, cameras, 'left c at (0, 0.06, 1) looking (1, 0, 0)\n'
                                                  'right c2 relative "extrinsics.yml"')
    R_got, T_got = scene.rig.stereo_extrinsics()
    assert np.abs(R_got - R).max() < 1e-12 and np.abs(T_got - T.ravel()).max() < 1e-12 and not warnings
    (e,) = _error(tmp_path, 'camera c {\n  read "extrinsics.yml"\n}')
    assert e.code == "E141" and "extrinsics only" in e.message


ROS_MSG = """\
header:
  seq: 0
  stamp: {secs: 0, nsecs: 0}
  frame_id: camera
height: 480
width: 640
distortion_model: plumb_bob
D: [-0.21, 0.013, 0.0004, -0.0002, 0.031]
K: [612.5, 0.0, 318.25, 0.0, 624.75, 241.5, 0.0, 0.0, 1.0]
R: [1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0]
P: [612.5, 0.0, 318.25, 0.0, 0.0, 624.75, 241.5, 0.0, 0.0, 0.0, 1.0, 0.0]
binning_x: 0
"""


@pytest.mark.parametrize("text", [
    ROS_MSG,  # ROS 1 `rostopic echo`
    ROS_MSG.replace("\nD:", "\nd:").replace("\nK:", "\nk:").replace("\nR:", "\nr:").replace("\nP:", "\np:"),  # ROS 2
    ROS_MSG.replace("distortion_model: plumb_bob\n", ""),  # no model: by its keys
    "image_width: 640\nimage_height: 480\ncamera_matrix:\n  rows: 3\n  cols: 3\n  data: [612.5, 0, 318.25, 0, "
    "624.75, 241.5, 0, 0, 1]\ndistortion_coefficients:\n  rows: 1\n  cols: 5\n  data: [-0.21, 0.013, 0.0004, "
    "-0.0002, 0.031]\n",  # a camera_info YAML without camera_name nor distortion_model
])
def test_ros_files_and_message_dumps(tmp_path, text):
    (tmp_path / "info.yaml").write_text(text)
    (c,) = cf.read(tmp_path / "info.yaml")
    assert (c.fx, c.fy, c.cx, c.cy, c.width, c.height) == (612.5, 624.75, 318.25, 241.5, 640, 480)
    assert c.dist == (-0.21, 0.013, 0.0004, -0.0002, 0.031, 0, 0, 0)
    if "camera_name" in text or "distortion_model" in text or "\nK:" in text or "\nk:" in text:
        with pytest.raises(cf.CalibrationFileError, match="not OpenCV's"):  # read as the wrong format: refused
            cf.read(tmp_path / "info.yaml", "opencv")
    else:  # OpenCV's keys alone: it is OpenCV's too
        (again,) = cf.read(tmp_path / "info.yaml", "opencv")
        assert again.fx == 612.5


def _kalibr_cam(i, model="radtan", coeffs=(-0.28, 0.07, 0.0002, 0.00002), T=None, extra=""):
    lines = [f"cam{i}:", "  camera_model: pinhole", f"  intrinsics: [{460 + i}, {459 + i}, 370.5, 250.25]",
             f"  distortion_model: {model}", f"  distortion_coeffs: [{', '.join(map(repr, coeffs))}]",
             "  resolution: [752, 480]"]
    if T is not None:
        lines += ["  T_cn_cnm1:"] + [f"  - [{', '.join(repr(float(x)) for x in row)}]" for row in T]
    return "\n".join(lines) + "\n" + extra


def _pose(rvec, t):
    M = np.eye(4)
    M[:3, :3], M[:3, 3] = cv2.Rodrigues(np.array(rvec, dtype=float))[0], t
    return M


def test_a_kalibr_chain_of_three_cameras_and_pinhole_none(tmp_path):
    T1, T2 = _pose([0.001, 0.02, -0.003], [-0.1, 0.001, 0.0]), _pose([0.002, -0.01, 0.001], [-0.09, -0.002, 0.001])
    chain = _kalibr_cam(0) + _kalibr_cam(1, T=T1) + _kalibr_cam(2, "none", (), T=T2)
    (tmp_path / "chain.yaml").write_text(chain)
    cams = cf.read(tmp_path / "chain.yaml")
    assert [c.name for c in cams] == ["cam0", "cam1", "cam2"] and cams[2].dist == (0,) * 8
    # a rig of the chain's cam1 and cam2: the extrinsics between those entries
    cameras = ('camera a {\n  read "chain.yaml" entry cam1\n}\ncamera b {\n  read "chain.yaml" entry cam2\n}')
    scene, _ = _compile(tmp_path, cameras, 'left a at (0, 0.05, 1) looking (1, 0, 0)\nright b relative "chain.yaml"')
    R, T = scene.rig.stereo_extrinsics()
    assert np.abs(R - T2[:3, :3]).max() < 1e-12 and np.abs(T - T2[:3, 3]).max() < 1e-12
    # and cam0 to cam2 composes the two steps
    cameras = cameras.replace("entry cam1", "entry cam0")
    scene, _ = _compile(tmp_path, cameras, 'left a at (0, 0.05, 1) looking (1, 0, 0)\nright b relative "chain.yaml"')
    R, T = scene.rig.stereo_extrinsics()
    M = T2 @ T1
    assert np.abs(R - M[:3, :3]).max() < 1e-12 and np.abs(T - M[:3, 3]).max() < 1e-12
    e = _error(tmp_path, cameras.replace("entry cam0", "entry cam5"))[0]
    assert e.code == "E104" and "has 3 cameras (cam0, cam1, cam2); there is no cam5" in e.message


@pytest.mark.parametrize("content, message", [
    (_kalibr_cam(0).replace("pinhole", "ds"), "Kalibr camera 'ds-radtan' is not supported"),
    (_kalibr_cam(0).replace("pinhole", "eucm"), "Kalibr camera 'eucm-radtan' is not supported"),
    (_kalibr_cam(0).replace("pinhole", "scaramuzza"), "Kalibr camera model 'scaramuzza' is not supported"),
    ("%YAML:1.0\ncamera_matrix: !!opencv-matrix\n  rows: 3\n  cols: 3\n  dt: d\n  data: [500, 0, 320, 0, 500, 240, "
     "0, 0, 1]\ndistortion_coefficients: !!opencv-matrix\n  rows: 1\n  cols: 14\n  dt: d\n  data: [-0.2, 0.01, 0, 0, "
     "0, 0, 0, 0, 0, 0, 0, 0, 0.001, 0]\n", "tilted-sensor distortion (taux, tauy = 0.001, 0)"),
])
def test_models_wiredsl_lacks_are_refused_by_name(tmp_path, content, message):
    (tmp_path / "bad.yaml").write_text(content)
    (e,) = _error(tmp_path, 'camera c {\n  read "bad.yaml"\n}')
    assert e.code == "E141" and message in e.message and e.span.line == 7


# ------------------------------------------------------------------ Kalibr's results-cam.txt

def _results(indent: str, geometry: str = "DistortedPinholeCameraGeometry", dist="[-0.29 0.085 0.0009 -0.0004]",
             sdist="[0.001 0.002 0.0001 0.0001]") -> str:
    """Kalibr's printParameters layout: TAB-indented before late 2022, spaces since."""
    cams = "".join(
        f"{indent}cam{i} (/cam{i}/image_raw):\n"
        f"{indent} type: <class 'aslam_cv.libaslam_cv_python.{geometry}'>\n"
        f"{indent} distortion: {dist} +- {sdist}\n"
        f"{indent} projection: [530.  531.5 401.5 268. ] +- [0.3 0.3 0.2 0.2]\n"
        f"{indent} reprojection error: [0.000012, -0.000003] +- [0.120000, 0.090000]\n\n" for i in (0, 1))
    return ("Calibration results \n====================\nCamera-system parameters:\n" + cams
            + f"{indent}baseline T_1_0:\n{indent} q: [ 0.003 -0.005  0.001  0.99998] +- [0.0004 0.0002 0.0001]\n"
            + f"{indent} t: [-0.0627  0.0006 -0.0004] +- [0.0001 0.0002 0.0003]\n\n")


@pytest.mark.parametrize("indent", ["\t", "    "])
def test_kalibr_results_in_both_layouts(tmp_path, indent):
    (tmp_path / "results-cam.txt").write_text(_results(indent))
    c0, c1 = cf.read(tmp_path / "results-cam.txt")
    assert c0.sigma["f"] == 0.3 and c0.sigma["k"] == 0.001 and c1.sigma["p2"] == 0.0001
    # q's +- are Kalibr's rotation-vector standard deviations (rad): the variance is not 4x
    assert (c1.sigma["rx"], c1.sigma["ry"], c1.sigma["rz"]) == (0.0004, 0.0002, 0.0001)
    assert (c1.sigma["tx"], c1.sigma["ty"], c1.sigma["tz"]) == (0.0001, 0.0002, 0.0003)


def test_kalibr_results_of_other_models(tmp_path):
    (tmp_path / "eq.txt").write_text(_results("\t", "EquidistantDistortedPinholeCameraGeometry"))
    c0, _ = cf.read(tmp_path / "eq.txt")
    assert c0.model == "equidistant" and (c0.sigma["k"], c0.sigma["k2"], c0.sigma["k3"], c0.sigma["k4"]) == (
        0.001, 0.002, 0.0001, 0.0001) and "p1" not in c0.sigma
    (tmp_path / "none.txt").write_text(_results("\t", "PinholeCameraGeometry", "[]", "[]"))
    c0, _ = cf.read(tmp_path / "none.txt")
    assert c0.dist == (0,) * 8 and "k" not in c0.sigma
    for geometry, model in (("DistortedOmniCameraGeometry", "an 'omni'"), ("FovDistortedPinholeCameraGeometry",
                                                                           "a 'fov'"),
                            ("DoubleSphereCameraGeometry", "a 'ds'"), ("ExtendedUnifiedCameraGeometry", "an 'eucm'")):
        (tmp_path / "x.txt").write_text(_results("\t", geometry))
        with pytest.raises(cf.CalibrationFileError, match=f"results-cam.txt of {model} camera is not read"):
            cf.read(tmp_path / "x.txt")
    (tmp_path / "five.txt").write_text(_results("\t").replace("401.5 268. ] +- [0.3 0.3", "401.5 268. 1] +- [0.3 0.3"))
    with pytest.raises(cf.CalibrationFileError, match="a pinhole projection has 4 values"):
        cf.read(tmp_path / "five.txt")


@pytest.mark.parametrize("text", ["garbage\n", "cam0\n projection: [1 2 3 4] +- [a b c d]\n", "\x00\x01", ""])
def test_a_garbage_kalibr_results_file_is_e141(tmp_path, text):
    (tmp_path / "results-cam.txt").write_text(text)
    errors = _error(tmp_path, 'camera c {\n  focal 500px\n  size (640px, 480px)\n}',
                    'left c at (0, 0.06, 1) looking (1, 0, 0)\nright c at (0, -0.06, 1) looking (1, 0, 0)\n'
                    'calibration covariance kalibr "results-cam.txt"')
    assert [e.code for e in errors] == ["E141"]


# ------------------------------------------------------------------ silent wrong cameras

def test_a_fisheye_labelled_plumb_bob_is_warned(tmp_path):
    """ROS's fisheye calibrator wrote such files: 4 coefficients, P's focal length a third of K's."""
    text = ("image_width: 640\nimage_height: 480\ncamera_name: fisheye\ncamera_matrix:\n  rows: 3\n  cols: 3\n"
            "  data: [290.1, 0, 321.2, 0, 289.8, 241.7, 0, 0, 1]\ndistortion_model: plumb_bob\n"
            "distortion_coefficients:\n  rows: 1\n  cols: 4\n  data: [0.0251, -0.0123, 0.0041, -0.0007]\n"
            "rectification_matrix:\n  rows: 3\n  cols: 3\n  data: [1, 0, 0, 0, 1, 0, 0, 0, 1]\n"
            "projection_matrix:\n  rows: 3\n  cols: 4\n  data: [97.2, 0, 320.5, 0, 0, 97.1, 240.3, 0, 0, 0, 1, 0]\n")
    (tmp_path / "fish.yaml").write_text(text)
    _, warnings = _compile(tmp_path, 'camera c {\n  read "fish.yaml"\n}')
    (w,) = [w for w in warnings if w.code == "W143"]
    assert "labelled plumb_bob but has 4 coefficients" in w.message and "equidistant" in w.message
    (tmp_path / "fish.yaml").write_text(text.replace("plumb_bob", "equidistant"))
    _, warnings = _compile(tmp_path, 'camera c {\n  read "fish.yaml"\n}')
    assert not [w for w in warnings if w.code == "W143"]


def test_a_stereo_translation_in_millimetres_is_an_error_unless_its_unit_is_given(tmp_path):
    """Issue 35: a 120 m baseline read from an OpenCV file was only W144, and every later command went on with
    it. Now E146 (with the hint) unless the read says its unit: `units mm` scales T to 0.12 m, `units m` keeps
    it (the author's word). The swapped sides are still W144, and so is a written rig over 5 m wide."""
    R = np.eye(3)
    _fs_write(tmp_path / "mm.yaml", image_width=640, image_height=480, M1=K, D1=D5, M2=K, D2=D5, R=R,
              T=np.array([[-120.0], [0.5], [0.2]]))
    cameras = 'camera c {\n  read "mm.yaml"\n}\ncamera c2 {\n  read "mm.yaml" entry second\n}'
    rig = 'left c at (0, 0.06, 1) looking (1, 0, 0)\nright c2 relative "mm.yaml"'
    (e,) = _error(tmp_path, cameras, rig)
    assert e.code == "E146" and "120 m apart: did you mean millimetres?" in e.message and "board" in e.hint
    assert 'units mm' in e.hint and (e.span.line, e.span.col) == (14, 21)  # at `relative`
    scene, warnings = _compile(tmp_path, cameras, rig + " units mm")
    _, T = scene.rig.stereo_extrinsics()
    assert np.allclose(T, [-0.12, 0.0005, 0.0002]) and not [w for w in warnings if w.code == "W144"]
    scene, warnings = _compile(tmp_path, cameras, rig + " units m")  # said to be metres: taken as written
    assert np.isclose(np.linalg.norm(scene.rig.stereo_extrinsics()[1]), np.linalg.norm([120, 0.5, 0.2]))
    assert not [w for w in warnings if w.code == "W144"]
    (e,) = _error(tmp_path, cameras, 'left c at (0, 0.06, 1) looking (1, 0, 0) units mm\nright c2 relative "mm.yaml"')
    assert e.code == "E103" and "needs 'relative'" in e.message
    _fs_write(tmp_path / "mm.yaml", image_width=640, image_height=480, M1=K, D1=D5, M2=K, D2=D5, R=R,
              T=np.array([[0.12], [0.0], [0.0]]))
    _, warnings = _compile(tmp_path, cameras, rig)
    (w,) = [w for w in warnings if w.code == "W144"]
    assert "right camera is 0.12 m to the left of the left camera" in w.message
    _, warnings = _compile(tmp_path, 'camera c {\n  focal 500px\n  size (640px, 480px)\n}',
                           'left c at (0, -0.06, 1) looking (1, 0, 0)\nright c at (0, 0.06, 1) looking (1, 0, 0)')
    assert [w.code for w in warnings] == ["W144"]


@pytest.mark.parametrize("given, missing", [("D1", "D2"), ("D2", "D1")])
def test_a_stereo_file_naming_one_cameras_distortion_only_is_an_error(tmp_path, given, missing):
    """Issue 35: a stereo file without D2 compiled a distortion-free right camera (k1 = 0 where the lens has
    -0.21) and `check` said `1 file ok`. Naming neither is a distortion-free pair, as OpenCV writes it."""
    _fs_write(tmp_path / "s.yaml", image_width=640, image_height=480, M1=K, M2=K, R=np.eye(3),
              T=np.array([[-0.12], [0.0], [0.0]]), **{given: D5})
    (e,) = _error(tmp_path, 'camera c {\n  read "s.yaml" entry second\n}')
    assert e.code == "E141" and f"names {given} but not {missing}" in e.message
    (tmp_path / "a.wd").write_text(_scene('camera c {\n  read "s.yaml" entry second\n}'))
    r = CliRunner().invoke(main, ["check", str(tmp_path / "a.wd")])
    assert r.exit_code == 1 and f"but not {missing}" in r.stderr and "Traceback" not in r.output
    _fs_write(tmp_path / "s.yaml", image_width=640, image_height=480, M1=K, M2=K, R=np.eye(3),
              T=np.array([[-0.12], [0.0], [0.0]]))
    scene, _ = _compile(tmp_path, 'camera c {\n  read "s.yaml" entry second\n}')
    assert scene.cameras[0].k1 == 0.0


def test_a_size_beside_read_scales_the_camera_matrix(tmp_path):
    _fs_write(tmp_path / "cam.yaml", image_width=1280, image_height=960, camera_matrix=K * [[2], [2], [1]],
              distortion_coefficients=D5)
    scene, warnings = _compile(tmp_path, 'camera c {\n  read "cam.yaml"\n  size (640px, 480px)\n}')
    cam = scene.cameras[0]
    assert (cam.f * cam.ax, cam.f * cam.ay, cam.cx, cam.cy) == pytest.approx((612.5, 624.75, 318.25, 241.5), abs=1e-12)
    (w,) = [w for w in warnings if w.code == "W143"]
    assert "differs from the calibration file's (1280, 960)" in w.message
    # a centre given beside it is kept; another aspect ratio is no rescale
    scene, _ = _compile(tmp_path, 'camera c {\n  read "cam.yaml"\n  size (640px, 480px)\n  centre (300px, 200px)\n}')
    assert (scene.cameras[0].cx, scene.cameras[0].f) == (300, 612.5)
    (e,) = _error(tmp_path, 'camera c {\n  read "cam.yaml"\n  size (640px, 400px)\n}')
    assert e.code == "E110" and "not the calibration file's (1280, 960) scaled" in e.message


# ------------------------------------------------------------------ malformed files: E141 at the path

KALIBR_OK = _kalibr_cam(0)


@pytest.mark.parametrize("content", [
    KALIBR_OK.replace("distortion_coeffs: [-0.28, 0.07, 0.0002, 2e-05]", "distortion_coeffs: {a: 1}"),
    KALIBR_OK.replace("resolution: [752, 480]", "resolution: {w: 752, h: 480}"),
    KALIBR_OK.replace("resolution: [752, 480]", "resolution: [752, 480.5]"),
    KALIBR_OK.replace("intrinsics: [460, 459, 370.5, 250.25]", "intrinsics: 'fast'"),
    KALIBR_OK.replace("intrinsics: [460, 459, 370.5, 250.25]", "intrinsics: [460, 459, [370.5], 250.25]"),
    KALIBR_OK.replace("intrinsics: [460, 459, 370.5, 250.25]", "intrinsics: [0, 459, 370.5, 250.25]"),
    KALIBR_OK.replace("intrinsics: [460, 459, 370.5, 250.25]", "intrinsics: [.nan, 459, 370.5, 250.25]"),
    KALIBR_OK.replace("intrinsics: [460, 459, 370.5, 250.25]", "intrinsics: [1e308, 1e308, 370.5, 250.25]"),
    KALIBR_OK.replace("camera_model: pinhole", "camera_model: [pinhole]"),
    "cam0:\n- 1\n- 2\n",  # Kalibr's cam0 as a list
    "cam0: 3\n",
    "camera_matrix: {rows: 3, cols: 3, data: 7}\n",
    "camera_matrix: {rows: three, cols: 3, data: [1, 2]}\n",
    "camera_matrix: !!opencv-matrix [1, 2, 3]\n",
    "camera_matrix: {rows: 3, cols: 3, data: [500, 0, 320, 0, 500, 240, 0, 0, 1]}\ndistortion_model: {x: 1}\n"
    "distortion_coefficients: [0.1]\n",
    "a: &x [1, 2]\nb: *x\n",
    "[" * 500 + "]" * 500 + "\n",  # nested 500 deep
    "a:\n" + "".join(" " * (i + 1) + f"b{i}:\n" for i in range(500)),
    '{"a": ' * 500 + "1" + "}" * 500,
    '{"camera_matrix": {"type_id": "opencv-matrix", "rows": 3, "cols": 3, "dt": "d", "data": "x"}}',
    "<?xml version='1.0'?><opencv_storage><camera_matrix type_id='opencv-matrix'><rows>3</rows><cols>3</cols>"
    "<dt>d</dt><data>1 2</data></camera_matrix></opencv_storage>",
    "M1: 1\nM2: [1, 2]\n",
    "R: [1, 0]\nT: [0, 0, 1]\n",
    "Camera.fx: 500\nCamera.fy: [500]\nCamera.cx: 320\nCamera.cy: 240\n",
    "LEFT.K: 5\n",
    "%YAML:1.0\n\x00",
])
def test_malformed_calibration_files_are_e141_at_the_path(tmp_path, content):
    (tmp_path / "bad.yaml").write_text(content)
    errors = _error(tmp_path, 'camera c {\n  read "bad.yaml"\n  size (640px, 480px)\n}')
    assert [e.code for e in errors] == ["E141"], errors
    assert (errors[0].span.line, errors[0].span.col) == (7, 8)


def test_a_fisheye_rig_exported_reads_back_as_the_same_cameras(tmp_path):
    from click.testing import CliRunner

    from wiredsl.cli import main

    cameras = ("camera c {\n  focal 290px\n  size (640px, 480px)\n  distortion equidistant\n  k1 0.02\n  k2 -0.01\n"
               "  k3 0.003\n  k4 -0.0004\n}")
    (tmp_path / "a.wd").write_text(_scene(cameras))
    assert CliRunner().invoke(main, ["export-calibration", str(tmp_path / "a.wd"), "-o", str(tmp_path / "cal")]
                              ).exit_code == 0
    for name in ("stereo.yaml", "left.yaml", "right.yaml"):
        c = cf.read(tmp_path / "cal" / name)[-1]
        assert (c.model, c.fx, c.dist) == ("equidistant", 290.0, (0.02, -0.01, 0.003, -0.0004)), name
    fs = cv2.FileStorage(str(tmp_path / "cal" / "stereo.yaml"), cv2.FILE_STORAGE_READ)
    assert np.array_equal(fs.getNode("D2").mat().ravel(), [0.02, -0.01, 0.003, -0.0004])


def test_a_size_given_for_a_file_without_one_is_checked_against_its_centre(tmp_path):
    (tmp_path / "kitti.yaml").write_text("%YAML:1.0\nCamera.fx: 718.856\nCamera.fy: 718.856\nCamera.cx: 607.1928\n"
                                         "Camera.cy: 185.2157\n")
    _, warnings = _compile(tmp_path, 'camera c {\n  read "kitti.yaml"\n  size (1241px, 376px)\n}')
    assert not [w for w in warnings if w.code == "W143"]
    _, warnings = _compile(tmp_path, 'camera c {\n  read "kitti.yaml"\n  size (600px, 376px)\n}')
    (w,) = [w for w in warnings if w.code == "W143"]
    assert "centre (607.193, 185.216) is outside the 600 x 376 image" in w.message


def test_a_focal_length_that_underflows_is_refused(tmp_path):
    """Found by the fuzzing: Kalibr's projection with fu = 1e-320 divided by fu**2 = 0."""
    (tmp_path / "results-cam.txt").write_text(_results("\t").replace("[530.  531.5", "[1e-320  531.5"))
    with pytest.raises(cf.CalibrationFileError, match="focal lengths must be at least 1e-06 px"):
        cf.read(tmp_path / "results-cam.txt")

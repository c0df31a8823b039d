"""Issue 35, item 7: messages that pointed wrong, each as the user met it."""

from __future__ import annotations

from click.testing import CliRunner

from wiredsl.cli import main

EIGHT_SECONDS = "\n".join(f"{100 + 0.5 * i:.4f} {0.1 * i:.4f} 0 0 0 0 0 1" for i in range(17)) + "\n"


def _check(tmp_path, path_block: str):
    (tmp_path / "t8.txt").write_text(EIGHT_SECONDS)
    f = tmp_path / "w.wd"
    f.write_text(f"wiredsl 1\npath run {{\n{path_block}\n}}\n")
    return CliRunner().invoke(main, ["check", str(f)])


def test_a_window_past_the_end_of_the_file_names_the_window_and_the_files_span(tmp_path):
    """Was: "the window from 10 s to 0 s holds no pose (the file spans 0 s)" for an 8 s file."""
    r = _check(tmp_path, '  read "t8.txt" from 10s')
    assert r.exit_code == 1
    assert "t8.txt: the window from 10 s holds no pose: the file spans 0 s to 8 s" \
        in r.stderr
    r = _check(tmp_path, '  read "t8.txt" from 10s to 12s')
    assert "the window from 10 s to 12 s holds no pose: the file spans 0 s to 8 s" in r.stderr


def test_pipeline_none_on_a_scene_without_pipelines_points_at_no_effects(tmp_path):
    """Was: "no pipeline 'none' ... (it has: none)"."""
    for command in (["render", "--edges", "none"], ["build"]):
        r = CliRunner().invoke(main, [command[0], "tests/data/table_box_cup.wd", "--pipeline", "none",
                                      "-o", str(tmp_path / command[0]), *command[1:]])
        assert r.exit_code == 2, r.output
        assert "no pipeline 'none' in tests/data/table_box_cup.wd (it has: the built-in paper); --no-effects " \
               "draws the ideal projection" in " ".join(r.output.split())


def test_a_refused_camera_of_a_stereo_file_is_said_once_where_it_is_read(tmp_path):
    """Was: one thin-prism E141 printed three times (each read of the file: `read`, `read ... entry second`,
    `relative`), naming M1 at the `entry second` read. Now once, at the read of that camera; the other camera
    and the pair's R, T stay usable."""
    cv2 = __import__("pytest").importorskip("cv2")
    import numpy as np

    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1.0]])
    fs = cv2.FileStorage(str(tmp_path / "prism.yaml"), cv2.FILE_STORAGE_WRITE)
    for k, v in dict(image_width=640, image_height=480, M1=K, D1=np.array([[-0.17, 0.02, 0, 0, 0, 0, 0, 0, 0.001, 0,
                                                                           0, 0]]),
                     M2=K, D2=np.array([[-0.17, 0.02, 0, 0, 0]]), R=np.eye(3), T=np.array([[-0.12], [0], [0]])).items():
        fs.write(k, v)
    fs.release()
    rig = ('rig r {\n  left c at (0, 0.06, 1) looking (1, 0, 0)\n  right c2 relative "prism.yaml"\n}\n'
           'camera c2 {\n  read "prism.yaml" entry second\n}\n')
    f = tmp_path / "p.wd"
    f.write_text('wiredsl 1\ncamera c {\n  read "prism.yaml"\n}\n' + rig)
    r = CliRunner().invoke(main, ["check", str(f)])
    errors = [x for x in r.stderr.splitlines() if "error[" in x]
    assert r.exit_code == 1 and len(errors) == 1, errors
    assert "p.wd:3:8: error[E141]: calibration file prism.yaml: M1: thin-prism distortion" in errors[0]
    f.write_text("wiredsl 1\ncamera c {\n  focal 600px\n  size (640px, 480px)\n}\n" + rig)
    r = CliRunner().invoke(main, ["check", str(f)])
    assert r.exit_code == 0, r.output  # M2 and R, T are fine


def _stereo(path, R):
    import cv2
    import numpy as np

    K = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1.0]])
    D = np.array([[-0.17, 0.02, 0, 0, 0]])
    fs = cv2.FileStorage(str(path), cv2.FILE_STORAGE_WRITE)
    for k, v in dict(image_width=640, image_height=480, M1=K, D1=D, M2=K, D2=D, R=R,
                     T=np.array([[-0.12], [0], [0]])).items():
        fs.write(k, v)
    fs.release()


ROUNDED = ('wiredsl 1\ncamera c {\n  read "r.yaml"\n}\ncamera c2 {\n  read "r.yaml" entry second\n}\n'
           'rig r {\n  left c at (0, 0.06, 1) looking (1, 0, 0)\n  right c2 relative "r.yaml"\n}\n')


def test_a_rotation_rounded_to_five_digits_is_mended_quietly_and_fewer_are_w143_at_relative(tmp_path):
    """Was: W143 labelled `M2:`, at the camera's `read ... entry second`, on every command, for R rounded to 1e-5
    (OpenVINS' files). Now: 5 digits (R R^T within 1e-4 of I) are mended to the nearest rotation without a word;
    3 digits are W143 once, at the rig's `relative`, naming the pose."""
    pytest = __import__("pytest")
    pytest.importorskip("cv2")
    import numpy as np
    from scipy.spatial.transform import Rotation

    from wiredsl.language.compile import compile_file

    exact = Rotation.from_rotvec([0.01, 0.02, 0.005]).as_matrix()
    (tmp_path / "s.wd").write_text(ROUNDED.replace("r.yaml", "r5.yaml"))
    _stereo(tmp_path / "r5.yaml", np.round(exact, 5))
    scene, diags, _ = compile_file(tmp_path / "s.wd")
    assert not [d for d in diags if d.code == "W143"]
    R = np.array(scene.rig.right.rotation)
    assert np.allclose(R @ R.T, np.eye(3), atol=1e-14)
    (tmp_path / "s.wd").write_text(ROUNDED.replace("r.yaml", "r3.yaml"))
    _stereo(tmp_path / "r3.yaml", np.round(exact, 3))
    _, diags, _ = compile_file(tmp_path / "s.wd")
    (w,) = [d for d in diags if d.code == "W143"]
    assert (w.span.line, w.span.col) == (10, 21)  # at `relative "r3.yaml"`
    assert w.message.startswith("calibration file r3.yaml: R and T (the pose of M2 relative to the camera before")


def test_a_compile_warning_through_the_environment_points_at_the_users_line(tmp_path):
    """Was: raised at a line of wiredsl's own code (wiredsl/gym.py)."""
    import warnings

    pytest = __import__("pytest")
    wg = pytest.importorskip("wiredsl.gym")
    scene = tmp_path / "s.wd"
    scene.write_text(open("scenes/lab.wd").read().replace("rotate z 15deg", "rotate z 0.2"))  # W111: 0.2 deg?
    (tmp_path / "models").symlink_to(__import__("pathlib").Path("scenes/models").resolve())
    (tmp_path / "lab.info").symlink_to(__import__("pathlib").Path("scenes/lab.info").resolve())
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        wg.WiredslEnv(scene, wg.Task("reach", "bin1"))
    mine = [w for w in caught if "W111" in str(w.message)]
    assert mine and all(w.filename == __file__ for w in mine), [(w.filename, w.lineno) for w in caught]

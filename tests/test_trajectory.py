"""Paths read from trajectory files: real excerpts of TUM, EuRoC and KITTI files against independent readings,
slerp resampling against known midpoints, 6-DoF projection against OpenCV, floor paths unchanged."""

from __future__ import annotations

import math
from pathlib import Path

import cv2
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from wiredsl.diagnostics import WiredslError
from wiredsl.engine import geometry
from wiredsl.engine.simulate import Options, simulate
from wiredsl.io import trajectory
from wiredsl.language.compile import compile_file

DATA = Path(__file__).parent / "data" / "trajectories"


def rows(name: str, sep: str | None = None) -> np.ndarray:
    """The file's numeric rows, read here without the reader under test."""
    text = (DATA / name).read_text()
    return np.array([[float(w) for w in line.split(sep)] for line in text.splitlines()
                     if line.strip() and not line.startswith("#")])


def rot(axis: str, deg: float) -> np.ndarray:
    c, s = math.cos(math.radians(deg)), math.sin(math.radians(deg))
    return {"x": np.array([[1, 0, 0], [0, c, -s], [0, s, c]]), "y": np.array([[c, 0, s], [0, 1, 0], [-s, 0, c]]),
            "z": np.array([[c, -s, 0], [s, c, 0], [0, 0, 1]])}[axis]


def scene_file(tmp_path: Path, path_block: str, files: dict[str, str], rig: str = "") -> Path:
    for name, text in files.items():
        (tmp_path / name).write_text(text)
    f = tmp_path / "s.wd"
    f.write_text(f"wiredsl 1\n{rig}\npath run {{\n{path_block}\n}}\n")
    return f


@pytest.mark.parametrize("name", ["tum_fr1_xyz_groundtruth.txt", "tum_fr1_xyz_rgbdslam.txt"])
def test_tum_excerpts_read_as_scipy_reads_their_quaternions(name):
    a = rows(name)
    traj = trajectory.read((DATA / name).read_text())
    assert trajectory.guess_format((DATA / name).read_text()) == "tum"
    np.testing.assert_allclose(traj.times, a[:, 0] - a[0, 0], atol=1e-6)
    assert traj.times[1] == round(float(a[1, 0] - a[0, 0]), 6)  # exact: the printed digits, not float64 noise
    np.testing.assert_array_equal(traj.positions, a[:, 1:4])
    np.testing.assert_allclose(traj.rotations, Rotation.from_quat(a[:, 4:8]).as_matrix(), atol=1e-12)
    assert traj.normalised == ()  # 4 and 6 printed digits are rounding, normalised silently
    # fr1/xyz's camera looks down at the desk: its optical axis (z) points below the horizon
    assert np.all(traj.rotations[:, 2, 2] < -0.4)


def test_euroc_excerpt_has_w_first_and_nanoseconds():
    a = rows("euroc_MH_01_easy_groundtruth.csv", ",")
    traj = trajectory.read((DATA / "euroc_MH_01_easy_groundtruth.csv").read_text())
    np.testing.assert_allclose(np.diff(traj.times), [0.00499968, 0.005000192, 0.004999936], atol=1e-9)
    np.testing.assert_array_equal(traj.positions, a[:, 1:4])
    wxyz = a[:, 4:8]
    expected = Rotation.from_quat(wxyz[:, [1, 2, 3, 0]]).as_matrix()
    np.testing.assert_allclose(traj.rotations, expected, atol=1e-12)
    wrong = Rotation.from_quat(wxyz).as_matrix()  # read as TUM's w-last: a different rotation altogether
    assert np.abs(traj.rotations - wrong).max() > 0.5


def test_kitti_excerpt_is_the_matrix_itself_with_times_or_a_rate():
    a = rows("kitti_00_poses.txt").reshape(-1, 3, 4)
    times = trajectory.read_times((DATA / "kitti_00_times.txt").read_text())
    traj = trajectory.read((DATA / "kitti_00_poses.txt").read_text(), None, times)
    np.testing.assert_array_equal(traj.positions, a[:, :, 3])
    np.testing.assert_allclose(traj.rotations, a[:, :, :3], atol=2e-6)  # 7 printed digits
    np.testing.assert_allclose(traj.rotations @ traj.rotations.transpose(0, 2, 1),
                               np.broadcast_to(np.eye(3), a[:, :, :3].shape), atol=1e-12)
    np.testing.assert_array_equal(traj.times, rows("kitti_00_times.txt")[:, 0])
    assert trajectory.read((DATA / "kitti_00_poses.txt").read_text(), "kitti", rate=10.0).times[3] == 0.3
    assert trajectory.read((DATA / "kitti_00_poses.txt").read_text()).times is None


def test_slerp_resampling_gives_known_midpoints():
    axis = np.array([1.0, 2.0, 2.0]) / 3.0
    q1 = Rotation.from_rotvec(axis * math.radians(100)).as_quat()
    text = f"0 0 0 0 0 0 0 1\n2 2 4 -2 {q1[0]} {q1[1]} {q1[2]} {q1[3]}\n"
    P, R = trajectory.resample(trajectory.read(text, "tum"), every=0.5)
    assert len(P) == 5
    np.testing.assert_allclose(P[2], [1, 2, -1], atol=1e-15)
    for k, frac in enumerate([0, 0.25, 0.5, 0.75, 1.0]):  # about the same axis, by that fraction of 100 degrees
        np.testing.assert_allclose(R[k], Rotation.from_rotvec(axis * math.radians(100 * frac)).as_matrix(),
                                   atol=1e-12)


def test_resampling_a_real_file_matches_scipy_slerp_and_window():
    text = (DATA / "tum_fr1_xyz_rgbdslam.txt").read_text()
    traj = trajectory.read(text)
    P, R = trajectory.resample(traj, every=0.05, start=0.2, end=0.6)
    t = traj.times - traj.times[0]
    ts = 0.2 + 0.05 * np.arange(9)
    from scipy.spatial.transform import Slerp

    expected = Slerp(t, Rotation.from_matrix(traj.rotations))(ts).as_matrix()
    np.testing.assert_allclose(R, expected, atol=1e-12)
    np.testing.assert_allclose(P[:, 2], np.interp(ts, t, traj.positions[:, 2]), atol=1e-15)
    P2, _ = trajectory.resample(traj, start=0.2, end=0.6, limit=3)  # the file's own poses in the window
    np.testing.assert_array_equal(P2, traj.positions[(t >= 0.2) & (t <= 0.6)][:3])


def test_plain_csv_with_units_and_angles():
    text = "t [ms], x [mm], y [mm], z [mm], roll [deg], pitch [deg], yaw [deg]\n0, 1000, 2000, 300, 10, -20, 30\n"
    traj = trajectory.read(text)
    np.testing.assert_allclose(traj.positions, [[1, 2, 0.3]])
    np.testing.assert_allclose(traj.rotations[0], rot("z", 30) @ rot("y", -20) @ rot("x", 10), atol=1e-15)


def test_near_unit_quaternions_are_normalised_with_a_warning(tmp_path):
    f = scene_file(tmp_path, '  read "a.tum"', {"a.tum": "0 1 2 0 0 0 0 1\n1 1 2 0 0 0 0 0.98\n1.5 1 2 0 0 0 0 1.01\n"})
    scene, diags, _ = compile_file(f)
    warnings = [d for d in diags if d.code == "W145"]
    assert [(d.span.line, d.message) for d in warnings] == [(2, "quaternion of length 0.98 normalised (and 1 more)")]
    np.testing.assert_allclose(np.array(scene.path.transforms)[:, :, :3], np.broadcast_to(np.eye(3), (3, 3, 3)))


def test_a_6dof_path_projects_where_opencv_says(tmp_path):
    """A path with roll and pitch read from a CSV: a corner's pixel against cv2.projectPoints, with rvec and
    tvec composed here from the file's angles, the body offset and the camera mount."""
    rig = ("model m {\n  corner c at (0, 0, 0)\n}\nplace m as p at (3m, 0.4m, 0.5m)\n"
           "camera cam {\n  focal 500px\n  size (640px, 480px)\n  centre (330px, 250px)\n  k1 -0.08\n  k2 0.01\n}\n"
           "rig r {\n  left cam at (0.1m, 0.05m, 0.2m) looking (1, 0.1, -0.1)\n"
           "  right cam at (0.1m, -0.05m, 0.2m) looking (1, 0.1, -0.1)\n}\n")
    csv = "t,x,y,z,roll [deg],pitch [deg],yaw [deg]\n0,0.5,0.2,1.0,12,-9,8\n1,0.7,0.1,1.1,-7,6,-5\n"
    f = scene_file(tmp_path, '  read "r.csv"\n  body at (0.05m, 0, 0.3m) rotate z 10deg\n'
                             '  world at (0.2m, -0.1m, 0.05m) rotate x 3deg', {"r.csv": csv}, rig)
    scene, _, _ = compile_file(f)
    results = simulate(scene, Options(visibility="all"))
    mount = scene.rig.left
    K = np.array([[500.0, 0, 330], [0, 500, 250], [0, 0, 1]])
    for result, (x, y, z, roll, pitch, yaw) in zip(results, [(0.5, 0.2, 1.0, 12, -9, 8),
                                                             (0.7, 0.1, 1.1, -7, 6, -5)], strict=True):
        T_world_file = np.eye(4)
        T_world_file[:3, :3], T_world_file[:3, 3] = rot("x", 3), [0.2, -0.1, 0.05]
        T_file_body = np.eye(4)
        T_file_body[:3, :3], T_file_body[:3, 3] = rot("z", yaw) @ rot("y", pitch) @ rot("x", roll), [x, y, z]
        T_robot_body = np.eye(4)
        T_robot_body[:3, :3], T_robot_body[:3, 3] = rot("z", 10), [0.05, 0, 0.3]
        T_robot_cam = np.eye(4)
        T_robot_cam[:3, :3], T_robot_cam[:3, 3] = np.array(mount.rotation), mount.position
        T_cam_world = np.linalg.inv(T_world_file @ T_file_body @ np.linalg.inv(T_robot_body) @ T_robot_cam)
        rvec, _ = cv2.Rodrigues(T_cam_world[:3, :3])
        want, _ = cv2.projectPoints(np.array([[3.0, 0.4, 0.5]]), rvec, T_cam_world[:3, 3], K,
                                    np.array([-0.08, 0.01, 0, 0, 0]))
        corner = [f for f in result.left.features if f.kind == "corner"]
        assert len(corner) == 1
        np.testing.assert_allclose(corner[0].points[0], want[0, 0], atol=1e-6)
        assert abs(geometry.floor_pose(result.pose)[2]) < 0.5


def test_planar_poses_give_the_same_extrinsics_bit_for_bit():
    rng = np.random.default_rng(17)
    for _ in range(50):
        pose = tuple(float(v) for v in rng.uniform(-5, 5, 3))
        Rm = Rotation.from_rotvec(rng.normal(size=3)).as_matrix()
        pm = rng.normal(size=3)
        R_wr = geometry.rot_z(pose[2])  # the floor formula as it was before 6-DoF poses
        R_cw = (R_wr @ Rm).T
        t_cw = -R_cw @ (R_wr @ pm + np.array([pose[0], pose[1], 0.0]))
        R, t = geometry.camera_from_world(pose, Rm, pm)
        assert np.array_equal(R, R_cw) and np.array_equal(t, t_cw)
        as_matrix = np.column_stack([R_wr, [pose[0], pose[1], 0.0]])  # the same pose as [R | t]
        R2, t2 = geometry.camera_from_world(tuple(as_matrix.ravel()), Rm, pm)
        np.testing.assert_allclose(R2, R, atol=1e-15)
        np.testing.assert_allclose(t2, t, atol=1e-14)
        assert geometry.floor_pose(tuple(as_matrix.ravel()))[2] == pytest.approx(math.remainder(pose[2], math.tau))


def test_world_from_robot_takes_a_4x4():
    T = np.eye(4)
    T[:3, :3], T[:3, 3] = rot("y", 20), [1, 2, 3]
    R, t = geometry.world_from_robot(T)
    assert np.array_equal(R, T[:3, :3]) and np.array_equal(t, [1, 2, 3])
    with pytest.raises(ValueError):
        geometry.world_from_robot(np.eye(3))


def test_kitti_with_the_left_camera_as_body_and_a_turned_world(tmp_path):
    """KITTI's poses are camera 0's in camera 0's first frame (z forward, y down): with `body camera left` and
    the world turned so that z is forward and -y up, the car drives along the scene's x, its camera level."""
    rig = ("camera cam {\n  focal 700px\n  size (1241px, 376px)\n}\n"
           "rig r {\n  left cam at (0, 0, 0) looking (1, 0, 0)\n  right cam at (0, -0.54m, 0) looking (1, 0, 0)\n}\n")
    (tmp_path / "poses.txt").write_text((DATA / "kitti_00_poses.txt").read_text())
    (tmp_path / "times.txt").write_text((DATA / "kitti_00_times.txt").read_text())
    f = scene_file(tmp_path, '  read "poses.txt" format kitti times "times.txt"\n  body camera left\n'
                             '  world at (0, 0, 1.65m) rotate x -90deg rotate z -90deg', {}, rig)
    scene, _, _ = compile_file(f)
    T = np.array(scene.path.transforms)
    a = rows("kitti_00_poses.txt").reshape(-1, 3, 4)
    np.testing.assert_allclose(T[:, 0, 3], a[:, 2, 3], atol=1e-12)  # forward (KITTI z) is the scene's x
    np.testing.assert_allclose(T[:, 1, 3], -a[:, 0, 3], atol=1e-12)  # KITTI x (right) is the scene's -y
    np.testing.assert_allclose(T[:, 2, 3], 1.65 - a[:, 1, 3], atol=1e-12)  # KITTI y (down) is the scene's -z
    np.testing.assert_allclose(T[0, :, :3], np.eye(3), atol=1e-9)  # at the first frame the robot is level


def test_kalibr_t_cam_imu_places_the_imu_body(tmp_path):
    """EuRoC's ground truth is the IMU's pose: with Kalibr's T_cam_imu the left camera lands where the IMU
    pose composed with T_imu_cam (EuRoC's own cam0 T_BS) puts it."""
    rig = ("camera cam {\n  focal 458px\n  size (752px, 480px)\n}\n"
           "rig r {\n  left cam at (0.1m, 0.2m, 0.3m) looking (1, 0.2, -0.1)\n"
           "  right cam at (0.1m, 0.1m, 0.3m) looking (1, 0.2, -0.1)\n}\n")
    for name in ("euroc_MH_01_easy_groundtruth.csv", "kalibr_euroc_camchain_imucam.yaml"):
        (tmp_path / name).write_text((DATA / name).read_text())
    f = scene_file(tmp_path, '  read "euroc_MH_01_easy_groundtruth.csv"\n'
                             '  body kalibr "kalibr_euroc_camchain_imucam.yaml"', {}, rig)
    scene, _, _ = compile_file(f)
    T_BS = np.array([[0.0148655429818, -0.999880929698, 0.00414029679422, -0.0216401454975],
                     [0.999557249008, 0.0149672133247, 0.025715529948, -0.064676986768],
                     [-0.0257744366974, 0.00375618835797, 0.999660727178, 0.00981073058949], [0, 0, 0, 1]])
    a = rows("euroc_MH_01_easy_groundtruth.csv", ",")
    for i in range(len(a)):
        T_world_imu = np.eye(4)
        T_world_imu[:3, :3] = Rotation.from_quat(a[i, [5, 6, 7, 4]]).as_matrix()
        T_world_imu[:3, 3] = a[i, 1:4]
        want = T_world_imu @ T_BS  # the camera in the world
        R_cw, t_cw = geometry.camera_from_world(scene.path.pose(i), scene.rig.left.rotation, scene.rig.left.position)
        np.testing.assert_allclose(R_cw.T, want[:3, :3], atol=1e-9)
        np.testing.assert_allclose(-R_cw.T @ t_cw, want[:3, 3], atol=1e-9)


def test_a_6dof_dump_carries_the_transform_and_floor_dumps_do_not(tmp_path):
    from wiredsl.io.emit import features

    f = scene_file(tmp_path, '  read "a.tum"', {"a.tum": "0 1 2 0.5 0.1 0 0 0.995\n"},
                   "camera c {\n  focal 500px\n  size (640px, 480px)\n}\n"
                   "rig r {\n  left c at (0, 0.1, 0) looking (1, 0, 0)\n"
                   "  right c at (0, -0.1, 0) looking (1, 0, 0)\n}\n")
    scene, _, _ = compile_file(f)
    doc = features(scene, None, simulate(scene)).model_dump(mode="json")
    assert len(doc["poses"][0]["transform"]) == 3 and doc["poses"][0]["pose"][:2] == [1.0, 2.0]
    floor = scene.model_copy(update={"path": scene.path.model_copy(update={"poses": [(1.0, 2.0, 0.0)],
                                                                           "transforms": None})})
    doc = features(floor, None, simulate(floor)).model_dump(mode="json")
    assert "transform" not in doc["poses"][0] and "transforms" not in floor.model_dump(mode="json")["path"]


@pytest.mark.parametrize("name", sorted(p.name for p in DATA.iterdir() if p.suffix in (".txt", ".csv")))
def test_mutated_trajectory_files_never_crash(name):
    """Seeded mutations of every real excerpt: read and resampled, each is a TrajectoryError or poses."""
    text = (DATA / name).read_text()
    rng = np.random.default_rng(sum(map(ord, name)))
    tokens = ["nan", "inf", "-1e400", "", ",", " ", "#", "1e308", "0", "x", "\t", "\n", "1,2", "-0"]
    for _ in range(150):
        words = text.replace("\n", " \n ").split(" ")
        for _ in range(int(rng.integers(1, 4))):
            words[int(rng.integers(len(words)))] = tokens[int(rng.integers(len(tokens)))]
        mutated = " ".join(words).replace(" \n ", "\n")
        fmt = [None, *trajectory.FORMATS][int(rng.integers(5))]
        try:
            traj = trajectory.read(mutated, fmt, rate=10.0 if fmt == "kitti" else None)
            P, R = trajectory.resample(traj, every=0.01 if traj.times is not None else None, max_poses=100_000)
        except trajectory.TrajectoryError:
            continue
        assert np.all(np.isfinite(P)) and np.all(np.isfinite(R))


def test_a_missing_trajectory_file_is_e010(tmp_path):
    f = scene_file(tmp_path, '  read "nothere.tum"', {})
    with pytest.raises(WiredslError) as err:
        compile_file(f)
    assert [d.code for d in err.value.diagnostics] == ["E010"]
    assert "no such file" in err.value.diagnostics[0].message


def test_an_oversized_trajectory_file_is_refused_unread(tmp_path):
    big = tmp_path / "big.tum"
    with open(big, "wb") as fh:  # sparse: 17 MiB on paper, nothing on disk
        fh.truncate(17 << 20)
    f = scene_file(tmp_path, '  read "big.tum"', {})
    with pytest.raises(WiredslError) as err:
        compile_file(f)
    d = err.value.diagnostics[0]
    assert (d.code, d.span.line, d.span.col) == ("E010", 4, 8) and "over the limit of 16,777,216" in d.message


def test_body_placed_two_ways_is_refused(tmp_path):
    f = scene_file(tmp_path, '  read "a.tum"\n  body at (0, 0, 1) camera left', {"a.tum": "0 1 2 0 0 0 0 1\n"})
    with pytest.raises(WiredslError) as err:
        compile_file(f)
    assert [(d.code, d.message) for d in err.value.diagnostics] == [
        ("E103", "'camera' and 'at' both place the body: keep one")]


def test_a_body_placed_by_a_rig_that_failed_is_not_told_the_scene_has_no_rig(tmp_path):
    """A rig whose right mount's calibration file is missing is reported at the file; the path's `body camera
    left` is not also told "the scene has no rig" (E102), which sent a reader looking for a missing statement."""
    rig = ("camera c {\n  focal 700px\n  size (640px, 480px)\n}\n"
           "rig r {\n  left c at (0, 0, 0) looking (1, 0, 0)\n  right c relative \"missing.yml\"\n}\n")
    f = scene_file(tmp_path, '  read "a.tum"\n  body camera left', {"a.tum": "0 1 2 0 0 0 0 1\n"}, rig)
    with pytest.raises(WiredslError) as err:
        compile_file(f)
    codes = [d.code for d in err.value.diagnostics]
    assert codes and "E102" not in codes, codes
    f = scene_file(tmp_path, '  read "a.tum"\n  body camera left', {"a.tum": "0 1 2 0 0 0 0 1\n"})
    with pytest.raises(WiredslError) as err:  # without a rig statement it still is E102
        compile_file(f)
    assert [d.code for d in err.value.diagnostics] == ["E102"]


@pytest.mark.parametrize(("block", "warned"), [
    ('  read "p.txt" format kitti', "rises"),  # KITTI's z is forward: the car would climb 9 m
    ('  read "p.txt" format kitti\n  world rotate x -90deg rotate z -90deg', "up (z) axis"),  # camera as robot
    ('  read "p.txt" format kitti\n  world rotate x -90deg rotate z -90deg\n  body camera left', None),
    ('  read "e.csv"', "up (z) axis"),  # EuRoC's IMU frame has x up
])
def test_a_robot_on_its_side_or_climbing_is_warned(tmp_path, block, warned):
    f = scene_file(tmp_path, block, {"p.txt": (DATA / "kitti_00_poses.txt").read_text(),
                                     "e.csv": (DATA / "euroc_MH_01_easy_groundtruth.csv").read_text()},
                   "camera c {\n  focal 700px\n  size (1241px, 376px)\n}\n"
                   "rig r {\n  left c at (0, 0, 0) looking (1, 0, 0)\n  right c at (0, -0.5, 0) looking (1, 0, 0)\n}\n")
    _, diags, _ = compile_file(f)
    messages = [d.message for d in diags if d.code == "W146"]
    assert (warned is None and not messages) or (warned is not None and any(warned in m for m in messages))


def test_a_csv_without_a_time_column_takes_its_declared_rate(tmp_path):
    """`rate 4` on a CSV of x, y, yaw: poses 0.25 s apart, resampled `every 0.125s` to midpoints; a rate on a
    CSV with its own t column, or neither, is E145 with a hint."""
    text = "x [m], y [m], yaw [deg]\n0, 0, 0\n1, 0, 90\n1, 1, 180\n"
    traj = trajectory.read(text, rate=4.0)
    np.testing.assert_array_equal(traj.times, [0, 0.25, 0.5])
    f = scene_file(tmp_path, '  read "r.csv" rate 4 every 0.125s', {"r.csv": text})
    scene, _, _ = compile_file(f)
    T = np.array(scene.path.transforms)
    assert len(T) == 5
    np.testing.assert_allclose(T[1, :, 3], [0.5, 0, 0], atol=1e-12)  # halfway in position and in yaw (45 deg)
    np.testing.assert_allclose(T[1, :, :3], rot("z", 45), atol=1e-12)
    for block, files, message in (
            ('  read "t.csv" rate 4', {"t.csv": "t, x, y, yaw\n0, 0, 0, 0\n"}, "its own timestamps (column 't')"),
            ('  read "r.csv"', {"r.csv": text}, "(or declare 'rate' for poses at a fixed rate)")):
        with pytest.raises(WiredslError) as err:
            compile_file(scene_file(tmp_path, block, files))
        assert [d.code for d in err.value.diagnostics] == ["E145"] and message in err.value.diagnostics[0].message


@pytest.mark.parametrize("header, message", [
    ("t, x, y, z, qx, qy, qz, qw, yaw", "the orientation twice: a quaternion and yaw"),
    ("t, x, y, z, qx, qy, qz, qw, roll, pitch", "the orientation twice: a quaternion and roll, pitch"),
    ("t, x, y, z, qx, qy, qz, yaw", "part of a quaternion: no column qw")])
def test_an_orientation_given_two_ways_or_in_part_is_refused_at_the_header(tmp_path, header, message):
    """A CSV with a quaternion and Euler angles (or three of a quaternion's four columns) is E145 at its header
    line, not read silently with one of them ignored."""
    row = ", ".join(["0"] * (header.count(",") + 1))
    f = scene_file(tmp_path, '  read "q.csv"', {"q.csv": f"{header}\n{row}\n"})
    with pytest.raises(WiredslError) as err:
        compile_file(f)
    (d,) = err.value.diagnostics
    assert d.code == "E145" and message in d.message and d.span.line == 1


# --------------------------------------------------------------------------- files as they are

def _fr2_desk_like(n: int = 2000, repeat_at: int = 1000) -> tuple[str, int]:
    """A TUM ground truth in fr2/desk's layout (3 comment lines, 100 Hz motion capture, 4 decimals) with the pose of
    row `repeat_at` followed by a second row at the same timestamp, as fr2/desk has one; and that row's line."""
    t0 = 1311868164.3633
    k = np.arange(n)
    rows_ = []
    for i in k:
        a = 0.002 * i
        q = Rotation.from_euler("xyz", [0.3 * math.sin(a), 0.2, a]).as_quat()
        rows_.append(f"{t0 + 0.01 * i:.4f} {1.2 + math.cos(a):.4f} {-0.6 + math.sin(a):.4f} {1.45 + 0.01 * a:.4f} "
                     + " ".join(f"{v:.4f}" for v in q))
    dup = rows_[repeat_at].split()
    dup[1] = f"{float(dup[1]) + 0.0003:.4f}"
    rows_.insert(repeat_at + 1, " ".join(dup))
    head = "# ground truth trajectory\n# file: 'rgbd_dataset_freiburg2_desk.bag'\n# timestamp tx ty tz qx qy qz qw\n"
    return head + "\n".join(rows_) + "\n", 3 + repeat_at + 2


def _evo_tum(text: str) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """evo's TUM reader, as evo/tools/file_interface.py read_tum_trajectory_file (MichaelGrupp/evo @ 26d0953): rows
    split on spaces after dropping `#` lines, every row kept (duplicates too), stamps, xyz and the quaternion rolled
    to w first. Returns (stamps, xyz, rotation matrices) of all rows. (Checked once against evo 1.38.1 itself,
    installed apart: the same rows, to 1e-15.)"""
    raw = [line.split(" ") for line in text.splitlines() if line and not line.startswith("#")]
    mat = np.array(raw).astype(float)
    quat = np.roll(mat[:, 4:], 1, axis=1)  # w x y z, as evo keeps it
    R = Rotation.from_quat(np.roll(quat, -1, axis=1)).as_matrix()  # scipy takes x y z w
    return mat[:, 0], mat[:, 1:4], R


def test_a_repeated_timestamp_is_dropped_with_one_warning_and_the_poses_are_evos(tmp_path):
    text, line = _fr2_desk_like()
    f = scene_file(tmp_path, '  read "groundtruth.txt"', {"groundtruth.txt": text})
    scene, diags, _ = compile_file(f)
    warned = [d for d in diags if d.severity == "warning"]
    assert [(d.code, d.span.line) for d in warned] == [("W148", line)], [d.message for d in warned]
    assert f"line {line} repeats the timestamp of line {line - 1}" in warned[0].message
    stamps, xyz, R = _evo_tum(text)
    first = np.concatenate([[True], stamps[1:] != stamps[:-1]])  # the rows evo's association uses
    assert len(stamps) == 2001 and first.sum() == 2000
    traj = trajectory.read(text)
    np.testing.assert_array_equal(traj.positions, xyz[first])
    np.testing.assert_allclose(traj.rotations, R[first], atol=1e-12)
    np.testing.assert_allclose(traj.times, stamps[first] - stamps[0], atol=1e-6)  # wiredsl's: from the first pose
    assert traj.repeated == ((line, line - 1),)
    assert len(scene.path.transforms) == 2000


def test_lines_outside_the_window_are_not_judged(tmp_path):
    text, _ = _fr2_desk_like(400, 300)  # the repeat 3 s in
    lines = text.splitlines()
    lines[3 + 350] = lines[3 + 350].replace(lines[3 + 350].split()[0], "1311868160.0000")  # goes back, 3.5 s in
    text = "\n".join(lines) + "\n"
    f = scene_file(tmp_path, '  read "gt.txt" from 0.5s to 2s', {"gt.txt": text})
    scene, diags, _ = compile_file(f)
    assert not [d for d in diags if d.severity in ("warning", "error")]
    assert len(scene.path.transforms) == 151  # 0.5 s to 2 s at 100 Hz
    f = scene_file(tmp_path, '  read "gt.txt" from 0.5s', {"gt.txt": text})
    with pytest.raises(WiredslError) as err:
        compile_file(f)
    assert "does not increase" in str(err.value) and f"gt.txt:{3 + 350 + 1}:" in str(err.value)


def test_many_repeats_are_one_warning_naming_the_lines(tmp_path):
    text = "0 0 0 0 0 0 0 1\n0 0.1 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n1 1 0 0 0 0 0 1\n2 2 0 0 0 0 0 1\n"
    f = scene_file(tmp_path, '  read "a.tum"', {"a.tum": text})
    scene, diags, _ = compile_file(f)
    (w,) = [d for d in diags if d.code == "W148"]
    assert w.span.line == 2 and "also lines 4, 5" in w.message
    assert [t[0][3] for t in scene.path.transforms] == [0.0, 1.0, 2.0]

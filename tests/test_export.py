"""`wiredsl export`: COLMAP text models read back by pycolmap, ROS 2 bags read back by rosbags (their own readers)."""

from __future__ import annotations

import hashlib
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

from wiredsl.cli import main
from wiredsl.engine.world import build_world

pycolmap = pytest.importorskip("pycolmap")  # the test extra installs it: skipped only outside it
pytest.importorskip("rosbags")

SCENE = """wiredsl 1
scene exp
units length m angle deg

model cage {
  polyline floor closed through (0, 0, 0) (4, 0, 0) (4, 4, 0) (0, 4, 0)
  polyline top closed through (0, 0, 2) (4, 0, 2) (4, 4, 2) (0, 4, 2)
  line ne from (4, 4, 0) to (4, 4, 2)
  line se from (4, 0, 0) to (4, 0, 2)
  ellipse ring centre (3, 2, 1) normal (1, 0, 0) axis (0, 1, 0) radii (0.3, 0.3)
  corner f_ne at (4, 4, 0) joins floor ne
  corner f_se at (4, 0, 0) joins floor se
  corner t_ne at (4, 4, 2) joins top ne
  corner t_se at (4, 0, 2) joins top se
  corner f_nw at (0, 4, 0)
  corner t_nw at (0, 4, 2)
  corner f_sw at (0, 0, 0)
  corner mid at (4, 2, 1)
}
place cage as room

camera cam {
  focal 300px
  size (640px, 480px)
  centre (321.5px, 238.2px)
LENS
}

rig head {
  left cam at (0, 0.06, 1.2) looking (1, 0, -0.1)
  right cam at (0, -0.06, 1.2) looking (1, 0, -0.1)
}

path run {
  pose (0.6, 2) heading 0
  pose (1.0, 1.8) heading 15
  pose (1.4, 2.3) heading -20
}

pipeline noisy default {
  approx_error sigma 0.3px
  corner_loss keep 0.8
  corner_mismatch fraction 10% radius 5px
}
"""

LENSES = {  # lens lines -> the COLMAP model it is written as
    "pinhole": ("", "PINHOLE"),
    "opencv": ("  k1 -0.1\n  k2 0.02\n  p1 0.001\n  p2 -0.0005", "OPENCV"),
    "rational": ("  k1 -0.1\n  k2 0.02\n  p1 0.001\n  p2 -0.0005\n  k3 0.001\n  k4 0.01\n  k5 0.002\n  k6 0.0005",
                 "FULL_OPENCV"),
    "equidistant": ("  distortion equidistant\n  k1 -0.0049\n  k2 0.0398\n  k3 -0.0372\n  k4 0.0067\n  fov 190deg",
                    "OPENCV_FISHEYE"),
    "fov": ("  distortion fov\n  w 52deg", "FOV"),
    "eucm": ("  distortion eucm\n  alpha 0.6\n  beta 1.1\n  fov 200deg", "EUCM"),
    "unified": ("  distortion unified\n  xi 0.9\n  fov 190deg", "EUCM"),
    "ds": ("  distortion ds\n  xi -0.2\n  alpha 0.57", None),
    "unified_radtan": ("  distortion unified\n  xi 1.1\n  k1 -0.05", None),
}


def _scene(tmp_path: Path, lens: str) -> Path:
    path = tmp_path / f"{lens}.wd"
    path.write_text(SCENE.replace("LENS\n", LENSES[lens][0] + "\n"))
    return path


def _export(*args):
    return CliRunner().invoke(main, ["export", *map(str, args)])


def _reprojection(model: Path) -> tuple[float, int, object]:
    """pycolmap's largest |projection of the 3D point - the 2D point| (px) over every observation of the model."""
    rec = pycolmap.Reconstruction(str(model))
    worst, n = 0.0, 0
    for image in rec.images.values():
        for p in image.points2D:
            assert p.has_point3D()
            uv = image.project_point(rec.points3D[p.point3D_id].xyz)
            worst = max(worst, float(np.abs(uv - p.xy).max()))
            n += 1
    return worst, n, rec


def _ideal(path: Path):
    import wiredsl

    scene = wiredsl.compile(path)
    return scene, next(iter(wiredsl.simulate(scene, trials=1, seed=0, pipeline=wiredsl.api.Pipeline(name="i"))))


@pytest.mark.parametrize("lens", [k for k, (_, m) in LENSES.items() if m is not None])
def test_colmap_reads_the_ideal_model_and_reprojects_every_point_onto_its_2d_point(tmp_path, lens):
    import wiredsl

    path = _scene(tmp_path, lens)
    r = _export(path, "--format", "colmap", "--no-effects", "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    worst, n, rec = _reprojection(tmp_path / "out" / "ideal")
    assert worst < 1e-6, worst
    assert {c.model.name for c in rec.cameras.values()} == {LENSES[lens][1]}
    scene, batch = _ideal(path)
    assert n == len(batch["corners"]) > 10  # every corner the ideal build has, none dropped
    # the images' poses are the nominal cameras the API gives (an independent path: Simulator.camera)
    sim = wiredsl.Simulator(scene, seed=0, pipeline=wiredsl.api.Pipeline(name="i"))
    for image in rec.images.values():
        side, pose = image.name[:-4].split("_")
        cam = sim.camera(int(pose), side)
        T = image.cam_from_world().matrix()
        assert np.abs(T[:, :3] - cam.R).max() < 1e-12 and np.abs(T[:, 3] - cam.t).max() < 1e-12
    world = build_world(scene)
    for pid, point in rec.points3D.items():
        assert np.array_equal(point.xyz, world.corners[pid - 1])
        assert point.track.length() >= 1


@pytest.mark.parametrize("lens", ["ds", "unified_radtan"])
def test_a_lens_colmap_lacks_is_refused_by_name_unless_undistorted(tmp_path, lens):
    path = _scene(tmp_path, lens)
    r = _export(path, "--format", "colmap", "--no-effects", "-o", tmp_path / "out")
    assert r.exit_code == 1 and "Traceback" not in r.output, r.output
    assert f"('{lens.split('_')[0]}')" in r.output and "--undistort" in r.output
    assert not (tmp_path / "out").exists()
    r = _export(path, "--format", "colmap", "--no-effects", "--undistort", "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    worst, n, rec = _reprojection(tmp_path / "out" / "ideal")
    assert worst < 1e-6 and n > 10, (worst, n)
    assert {c.model.name for c in rec.cameras.values()} == {"PINHOLE"}


def test_colmap_carries_each_trials_disturbed_corners(tmp_path):
    import wiredsl

    path = _scene(tmp_path, "opencv")
    r = _export(path, "--format", "colmap", "--trials", "3", "--seed", "11", "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    scene = wiredsl.compile(path)
    batch = next(iter(wiredsl.simulate(scene, trials=3, seed=11)))
    world = build_world(scene)
    corner_of = {int(f): i for i, f in enumerate(world.corner_fid)}
    for trial in range(3):
        rec = pycolmap.Reconstruction(str(tmp_path / "out" / f"trial_{trial:05d}"))
        got = {}
        for image in rec.images.values():
            side, pose = image.name[:-4].split("_")
            for p in image.points2D:
                got[(int(pose), side, p.point3D_id)] = p.xy - 0.5  # COLMAP's pixel centres are at .5
        rows, uv = batch["corner_rows"], batch["corners"]
        want = {(int(r[1]), ("left", "right")[r[2]], corner_of[int(r[3])] + 1): uv[i]
                for i, r in enumerate(rows) if r[0] == trial}
        assert got.keys() == want.keys() and len(want) > 5
        assert max(np.abs(got[k] - want[k]).max() for k in want) < 1e-9


def _bag_messages(bag: Path) -> list[tuple[str, int, object]]:
    from rosbags.rosbag2 import Reader

    from wiredsl.io.export_rosbag import typestore

    store = typestore()
    with Reader(bag) as reader:
        return [(c.topic, t, store.deserialize_cdr(raw, c.msgtype)) for c, t, raw in reader.messages()]


@pytest.mark.parametrize("lens", ["opencv", "eucm"])
def test_the_rosbag_reads_back_with_every_message_and_stamp(tmp_path, lens):
    from wiredsl.engine import geometry

    path = _scene(tmp_path, lens)
    r = _export(path, "--format", "rosbag2", "--no-effects", "--period", "0.25", "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    msgs = _bag_messages(tmp_path / "out" / "ideal")
    scene, batch = _ideal(path)
    cam = scene.camera("cam")
    world = build_world(scene)
    n_poses = len(scene.path.poses)
    stamps = [1_000_000_000 + i * 250_000_000 for i in range(n_poses)]
    by_topic: dict[str, list] = {}
    for topic, t, m in msgs:
        by_topic.setdefault(topic, []).append((t, m))
        if hasattr(m, "header"):
            assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == t
    per_pose = ["/tf", "/left/camera_info", "/right/camera_info", "/left/corners", "/right/corners",
                "/left/strokes", "/right/strokes"]
    assert sorted(by_topic) == sorted(per_pose + ["/tf_static", "/wiredsl/landmarks"])
    for topic in per_pose:
        assert [t for t, _ in by_topic[topic]] == stamps, topic
    # /tf: world -> base_link is the path's pose
    for i, (_, m) in enumerate(by_topic["/tf"]):
        tr = m.transforms[0]
        assert (tr.header.frame_id, tr.child_frame_id) == ("world", "base_link")
        R, t = geometry.world_from_robot(scene.path.pose(i))
        q = tr.transform.rotation
        from scipy.spatial.transform import Rotation

        assert np.abs(Rotation.from_quat([q.x, q.y, q.z, q.w]).as_matrix() - R).max() < 1e-12
        v = tr.transform.translation
        assert np.abs(np.array([v.x, v.y, v.z]) - t).max() < 1e-12
    info = by_topic["/left/camera_info"][0][1]
    assert (info.width, info.height) == (640, 480) and info.k[0] == info.k[4] == 300.0 and info.k[2] == 321.5
    np.testing.assert_allclose(info.k, [cam.f * cam.ax, 0, cam.cx, 0, cam.f * cam.ay, cam.cy, 0, 0, 1], rtol=1e-15)
    assert info.distortion_model == {"opencv": "plumb_bob", "eucm": "eucm"}[lens]
    # corners: VINS-Mono's layout; (x, y) the true normalised point of the 3D corner, u, v the exported pixel
    rows, uv = batch["corner_rows"], batch["corners"]
    corner_of = {int(f): i for i, f in enumerate(world.corner_fid)}
    n_seen = 0
    for side in ("left", "right"):
        for pose, (_, m) in enumerate(by_topic[f"/{side}/corners"]):
            ch = {c.name: np.asarray(c.values) for c in m.channels}
            assert list(ch) == ["id_of_point", "u_of_point", "v_of_point", "velocity_x", "velocity_y"]
            mine = [i for i, r in enumerate(rows) if r[1] == pose and r[2] == ("left", "right").index(side)]
            assert ch["id_of_point"].tolist() == [corner_of[int(rows[i, 3])] + 1 for i in mine]
            assert np.abs(ch["u_of_point"] - uv[mine, 0]).max() < 1e-4
            R, t = geometry.camera_from_world(scene.path.pose(pose), getattr(scene.rig, side).rotation,
                                              getattr(scene.rig, side).position)
            P = world.corners[ch["id_of_point"].astype(int) - 1] @ np.asarray(R).T + t
            xy = np.array([[p.x, p.y] for p in m.points])
            assert np.abs(xy - P[:, :2] / P[:, 2:]).max() < 1e-6 and all(p.z == 1 for p in m.points)
            n_seen += len(mine)
    assert n_seen == len(rows) > 10
    # strokes: every polyline of the build, at full precision
    pts, start, strokes = batch["pts"], batch["start"], batch["strokes"]
    got = [(s.feature, s.segment, s.kind, tuple(s.u), tuple(s.v)) for side in ("left", "right")
           for _, m in by_topic[f"/{side}/strokes"] for s in m.strokes]
    want = [(world.feature_ids[r[3]], int(r[4]), int(r[5]), tuple(pts[start[k]:start[k + 1], 0]),
             tuple(pts[start[k]:start[k + 1], 1])) for k, r in sorted(enumerate(strokes), key=lambda e: (e[1][2],
                                                                                                     e[1][1]))]
    assert got == want and len(want) > 10
    landmarks = by_topic["/wiredsl/landmarks"][0][1]
    assert np.abs(np.array([[p.x, p.y, p.z] for p in landmarks.points]) - world.corners).max() < 1e-6


def _digest(folder: Path) -> dict[str, str]:
    return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
            for p in sorted(folder.rglob("*")) if p.is_file()}


@pytest.mark.parametrize("fmt", ["colmap", "rosbag2"])
def test_disturbed_exports_are_byte_identical_for_one_seed(tmp_path, fmt):
    path = _scene(tmp_path, "opencv")
    runs = {}
    for name, seed in (("a", 3), ("b", 3), ("c", 4)):
        r = _export(path, "--format", fmt, "--trials", "2", "--seed", seed, "-o", tmp_path / name)
        assert r.exit_code == 0, r.output
        runs[name] = _digest(tmp_path / name)
    assert len(runs["a"]) >= 5 and runs["a"] == runs["b"]
    assert runs["a"]["manifest.json"] != runs["c"]["manifest.json"]
    assert any(runs["a"][k] != runs["c"][k] for k in runs["a"] if k.startswith("trial_00001/"))


def test_a_failed_export_leaves_the_old_folder_whole_and_no_temporaries(tmp_path):
    good = _scene(tmp_path, "opencv")
    assert _export(good, "--format", "colmap", "--no-effects", "-o", tmp_path / "out").exit_code == 0
    before = _digest(tmp_path / "out")
    r = _export(_scene(tmp_path, "ds"), "--format", "colmap", "--no-effects", "-o", tmp_path / "out")
    assert r.exit_code == 1
    assert _digest(tmp_path / "out") == before
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]
    (tmp_path / "mine").mkdir()
    (tmp_path / "mine" / "notes.txt").write_text("keep")
    r = _export(good, "--format", "colmap", "--no-effects", "-o", tmp_path / "mine")
    assert r.exit_code == 2 and "did not write" in r.output  # a folder of someone else's files is not replaced


@pytest.mark.parametrize("edit,args,code,words", [
    (lambda s: s[:s.index("rig head")] + s[s.index("path run"):], [], 1, "no rig"),
    (lambda s: s[:s.index("path run")] + s[s.index("pipeline noisy"):], [], 1, "no path"),
    (lambda s: s.replace("corner mid at", "corner mid att"), [], 1, "error["),
    (lambda s: s, ["--undistort", "--format", "rosbag2"], 2, "--undistort is for --format colmap"),
    (lambda s: s, ["--pipeline", "nope"], 2, "no pipeline 'nope'"),
    (lambda s: s, ["--trials", "0"], 2, "--trials"),
])
def test_bad_input_is_a_diagnostic_never_a_traceback(tmp_path, edit, args, code, words):
    path = tmp_path / "s.wd"
    path.write_text(edit(SCENE.replace("LENS\n", "")))
    fmt = [] if "--format" in args else ["--format", "colmap"]
    r = _export(path, *fmt, *args, "-o", tmp_path / "out")
    assert r.exit_code == code and words in r.output and "Traceback" not in r.output, r.output
    assert not (tmp_path / "out").exists()


@pytest.mark.parametrize("visibility, shown", [("auto", "exact"), ("scene", "scene"), ("all", "all")])
def test_export_hides_what_build_hides_with_the_same_default(tmp_path, visibility, shown):
    """scenes/meshes.wd: a corner of the crate behind the ball. export's --visibility is build's (the same
    default, auto, which chooses exact here), so each image's 2D points are the corners build's dump keeps."""
    import json

    ex = CliRunner().invoke(main, ["export", "scenes/meshes.wd", "--format", "colmap", "-o", str(tmp_path / "ex"),
                                   "--visibility", visibility])
    assert ex.exit_code == 0, ex.output
    assert json.loads((tmp_path / "ex" / "manifest.json").read_text())["visibility"] == shown
    b = CliRunner().invoke(main, ["build", "scenes/meshes.wd", "--no-svg", "-o", str(tmp_path / "b"),
                                  "--visibility", visibility])
    assert b.exit_code == 0, b.output
    dump = json.loads((tmp_path / "b" / "features.json").read_text())
    want = [len(p[side]["corners"]) for p in dump["poses"] for side in ("left", "right")]
    rows = [r for r in (tmp_path / "ex" / "ideal" / "images.txt").read_text().splitlines() if r and r[0] != "#"]
    got = [len(r.split()) // 3 for r in rows[1::2]]  # each image: a header row, then (x, y, point id) triples
    assert got == want
    assert sum(want) == {"auto": 39, "scene": 40, "all": 48}[visibility]  # the ball does hide a corner

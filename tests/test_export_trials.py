"""`wiredsl export --trial K` (one Monte-Carlo trial, the same draws as `build --trial K`) and the trajectory's
times in the exports, read back by the formats' own readers (pycolmap, rosbags)."""

from __future__ import annotations

import hashlib
import json
from collections import defaultdict
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from test_export import _bag_messages, _export, _scene

from wiredsl.cli import main
from wiredsl.engine.world import build_world

pycolmap = pytest.importorskip("pycolmap")  # the test extra installs them: skipped only outside it
pytest.importorskip("rosbags")


def _build_trial(path: Path, trial: int, seed: int, trials: int) -> dict:
    r = CliRunner().invoke(main, ["build", str(path), "--seed", str(seed), "--trials", str(trials), "--trial",
                                  str(trial), "--no-svg", "-o", "-"])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


def test_export_trial_k_gives_build_trial_ks_corners(tmp_path):
    """The COLMAP export of --trial 2 holds, view by view, the corners `build --trial 2` writes (same seed): the
    same sources at the same pixels (the build's 6 decimals); and nothing of the other trials."""
    import wiredsl

    path = _scene(tmp_path, "opencv")
    r = _export(path, "--format", "colmap", "--trials", "4", "--trial", "2", "--seed", "11", "-o", tmp_path / "out")
    assert r.exit_code == 0, r.output
    assert sorted(p.name for p in (tmp_path / "out").iterdir()) == ["manifest.json", "trial_00002"]
    manifest = json.loads((tmp_path / "out" / "manifest.json").read_text())
    assert manifest["trial"] == 2 and manifest["folders"] == ["trial_00002"]
    world = build_world(wiredsl.compile(path))
    names = [world.feature_ids[f] for f in world.corner_fid]
    rec = pycolmap.Reconstruction(str(tmp_path / "out" / "trial_00002"))
    got = defaultdict(list)
    for image in rec.images.values():
        side, pose = image.name[:-4].split("_")
        for p in image.points2D:
            got[(int(pose), side)].append((names[p.point3D_id - 1], *(p.xy - 0.5)))  # COLMAP's centres at .5
    doc = _build_trial(path, 2, 11, 4)
    assert doc["trial"] == 2
    want = {(p["index"], side): [(c["source"], *c["at"]) for c in p[side]["corners"]] for p in doc["poses"]
            for side in ("left", "right")}
    assert {k for k, v in want.items() if v} == set(got)
    n = 0
    for key, corners in want.items():
        mine = sorted(got.get(key, []))
        assert [c[0] for c in mine] == sorted(c[0] for c in corners), key
        assert np.abs(np.array([c[1:] for c in mine]) - np.array([c[1:] for c in sorted(corners)])).max() < 1e-6
        n += len(corners)
    assert n > 10
    other = _build_trial(path, 1, 11, 4)  # another trial's corners differ: the comparison can fail
    assert [p["left"]["corners"] for p in other["poses"]] != [p["left"]["corners"] for p in doc["poses"]]


@pytest.mark.parametrize("fmt", ["colmap", "rosbag2"])
def test_export_trial_k_alone_is_the_runs_trial_k_byte_for_byte(tmp_path, fmt):
    path = _scene(tmp_path, "opencv")
    for name, extra in (("all", ["--trials", "3"]), ("one", ["--trial", "1"])):
        r = _export(path, "--format", fmt, "--seed", "5", *extra, "-o", tmp_path / name)
        assert r.exit_code == 0, r.output

    def digest(folder: Path) -> dict:
        return {str(p.relative_to(folder)): hashlib.sha256(p.read_bytes()).hexdigest()
                for p in sorted(folder.rglob("*")) if p.is_file()}

    assert digest(tmp_path / "one" / "trial_00001") == digest(tmp_path / "all" / "trial_00001")
    assert digest(tmp_path / "one" / "trial_00001") != digest(tmp_path / "all" / "trial_00000")


def test_export_trial_beyond_the_runs_trials_is_a_usage_error(tmp_path):
    path = _scene(tmp_path, "opencv")
    r = _export(path, "--format", "colmap", "--trials", "3", "--trial", "3", "-o", tmp_path / "out")
    assert r.exit_code == 2 and "trial 3 is not in 0..2" in r.output and not (tmp_path / "out").exists()


EUROC = "#timestamp, p_RS_R_x [m], p_RS_R_y [m], p_RS_R_z [m], q_RS_w [], q_RS_x [], q_RS_y [], q_RS_z []" \
    + "".join(f", c{i}" for i in range(9)) + "\n"
STAMPS = [1403636580838555648, 1403636580888555264, 1403636580938555904]  # EuRoC's nanoseconds, past 2^53
POSES = [(0.6, 2.0, 0.0), (1.0, 1.8, 0.0), (1.4, 2.3, 0.0)]


def _trajectory_scene(tmp_path: Path, path_block: str) -> Path:
    path = _scene(tmp_path, "opencv")
    text = path.read_text()
    a = text.index("path run {")
    path.write_text(text[:a] + path_block + text[text.index("}", a) + 1:])
    return path


def test_the_bag_and_the_colmap_model_carry_the_trajectory_files_own_times(tmp_path):
    """A path read from a EuRoC file: every per-pose message of the bag is stamped with the file's nanoseconds,
    exactly (header and bag time); COLMAP's times.txt gives each image the same time in exact decimal seconds, and
    pycolmap still reads the model."""
    (tmp_path / "gt.csv").write_text(EUROC + "".join(
        f"{s},{x},{y},{z},1,0,0,0" + ",0" * 9 + "\n" for s, (x, y, z) in zip(STAMPS, POSES, strict=True)))
    path = _trajectory_scene(tmp_path, 'path run {\n  read "gt.csv"\n}')
    r = _export(path, "--format", "rosbag2", "--no-effects", "-o", tmp_path / "bag")
    assert r.exit_code == 0, r.output
    assert json.loads((tmp_path / "bag" / "manifest.json").read_text())["clock"] == "trajectory"
    by_topic = defaultdict(list)
    for topic, t, m in _bag_messages(tmp_path / "bag" / "ideal"):
        by_topic[topic].append(t)
        if hasattr(m, "header"):
            assert m.header.stamp.sec * 10**9 + m.header.stamp.nanosec == t
    for topic in ("/tf", "/left/camera_info", "/right/corners", "/left/strokes"):
        assert by_topic[topic] == STAMPS, topic
    r = _export(path, "--format", "colmap", "--no-effects", "-o", tmp_path / "colmap")
    assert r.exit_code == 0, r.output
    lines = [x.split() for x in (tmp_path / "colmap" / "ideal" / "times.txt").read_text().splitlines()
             if not x.startswith("#")]
    from decimal import Decimal

    rec = pycolmap.Reconstruction(str(tmp_path / "colmap" / "ideal"))
    assert sorted(name for _, name in lines) == sorted(im.name for im in rec.images.values()) and len(lines) == 6
    for stamp, name in lines:
        assert int(Decimal(stamp) * 10**9) == STAMPS[int(name[-7:-4])], (stamp, name)


def test_a_resampled_path_is_stamped_at_its_samples(tmp_path):
    """A TUM file resampled every 0.25 s: pose k at the file's first timestamp + 0.25 k s (to the nanosecond);
    a path written in the scene keeps the period's stamps."""
    (tmp_path / "gt.tum").write_text("".join(f"{1305031102.175304 + 0.5 * i:.6f} {x} {y} {z} 0 0 0 1\n"
                                             for i, (x, y, z) in enumerate(POSES)))
    path = _trajectory_scene(tmp_path, 'path run {\n  read "gt.tum" every 0.25s\n}')
    r = _export(path, "--format", "rosbag2", "--no-effects", "-o", tmp_path / "bag")
    assert r.exit_code == 0, r.output
    got = [t for topic, t, _ in _bag_messages(tmp_path / "bag" / "ideal") if topic == "/tf"]
    assert got == [1305031102175304000 + k * 250_000_000 for k in range(5)]
    path = _scene(tmp_path, "opencv")
    r = _export(path, "--format", "rosbag2", "--no-effects", "-o", tmp_path / "plain")
    assert json.loads((tmp_path / "plain" / "manifest.json").read_text())["clock"] == "period"
    assert [t for topic, t, _ in _bag_messages(tmp_path / "plain" / "ideal") if topic == "/tf"] == \
        [1_000_000_000 + k * 100_000_000 for k in range(3)]

"""The public Python API: compile, simulate and Simulator against what `build` writes and `load` reads."""

from __future__ import annotations

import os
import re
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner

import wiredsl
from wiredsl.cli import main
from wiredsl.scene import Pipeline

LAB = "scenes/lab.wd"
ROOT = Path(__file__).resolve().parent.parent


def build(tmp_path: Path, *args: str) -> Path:
    out = tmp_path / "out"
    result = CliRunner().invoke(main, ["build", LAB, "-o", str(out), "--no-svg", "--format", "npz", *args])
    assert result.exit_code == 0, result.output
    return out / "features.npz"


def same_records(a: list[dict], b: list[dict]) -> None:
    """Equal records: every field exactly, pixels within float32 rounding (the npz keeps float32)."""
    assert len(a) == len(b) and len(a) > 0
    for x, y in zip(a, b, strict=True):
        assert x.keys() == y.keys(), (x, y)
        for k in x:
            if k in ("points", "at"):
                assert np.allclose(x[k], y[k], rtol=2e-7, atol=1e-4), (k, x, y)
            else:
                assert x[k] == y[k], (k, x, y)


@pytest.fixture(scope="module")
def lab():
    return wiredsl.compile(LAB)


def test_importing_wiredsl_loads_no_numpy():
    import subprocess

    code = "import sys, wiredsl; wiredsl.__all__; print('numpy' in sys.modules, 'wiredsl.api' in sys.modules)"
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True, cwd=ROOT)
    assert out.stdout.split() == ["False", "False"]


def test_simulate_gives_what_load_reads_from_the_same_build(tmp_path, lab):
    path = build(tmp_path, "--seed", "11", "--trials", "300", "--pose", "1", "--pose", "4")
    batches = list(wiredsl.simulate(lab, trials=300, seed=11, poses=[1, 4]))
    assert [b.n_trials for b in batches] == [256, 44]  # bounded batches, like build's
    arrays = wiredsl.load(path, arrays=True)
    for name in ("strokes", "corner_rows", "views", "view_cameras", "view_poses"):
        got = np.concatenate([b[name] for b in batches])
        assert np.array_equal(got, arrays[name]), name
    for name in ("pts", "corners"):
        got = np.concatenate([b[name] for b in batches])
        assert got.dtype == np.float64 and np.array_equal(got.astype(np.float32), arrays[name]), name
    same_records(batches[1].records(), wiredsl.load(path, trial=range(256, 300)))
    same_records(batches[0].records()[:2000], wiredsl.load(path, trial=range(0, 256))[:2000])


def test_simulate_of_an_ideal_run_is_builds_trial_zero(tmp_path, lab):
    path = build(tmp_path, "--no-effects", "--pose", "2")
    (batch,) = wiredsl.simulate(lab, trials=5, seed=0, pipeline=lab.pipelines[0].model_copy(update={"stages": []}),
                                poses=[2])
    assert batch.n_trials == 1 and batch.trials.tolist() == [0]
    assert np.array_equal(batch["conic_rows"], wiredsl.load(path, arrays=True)["conic_rows"])
    same_records(batch.records(), wiredsl.load(path))


@pytest.mark.parametrize("engine", ["numpy", "kernel"])
def test_observe_a_path_pose_is_builds_pose_of_that_trial_bit_for_bit(engine, lab):
    pytest.importorskip("numba") if engine == "kernel" else None
    built = {b.n_trials: b for b in wiredsl.simulate(lab, trials=8, seed=2024, poses=[3], engine=engine)}[8]
    sim = wiredsl.Simulator(lab, seed=2024, engine=engine)
    for trial in (0, 5):
        seen = sim.observe(3, trial=trial)
        rows = built["strokes"][:, 0] == trial
        mine = seen["strokes"]
        assert np.array_equal(mine, built["strokes"][rows])
        keep = np.repeat(rows, np.diff(built["start"]))
        assert np.array_equal(seen["pts"], built["pts"][keep])  # float64 both: bit for bit
        crows = built["corner_rows"][:, 0] == trial
        assert np.array_equal(seen["corners"], built["corners"][crows])


def test_observe_of_an_arbitrary_pose_equals_the_path_pose_it_is(lab):
    sim = wiredsl.Simulator(lab, seed=9)
    at = lab.path.poses[2]
    by_index = sim.observe(2, trial=3)
    by_pose = sim.observe(tuple(at), trial=3, step=2)
    assert np.array_equal(by_index["pts"], by_pose["pts"])
    c, s = np.cos(at[2]), np.sin(at[2])
    T = np.array([[c, -s, 0, at[0]], [s, c, 0, at[1]], [0, 0, 1, 0], [0, 0, 0, 1]])
    assert np.allclose(sim.observe(T, trial=3, step=2)["pts"], by_index["pts"], atol=1e-9)
    other_step = sim.observe(tuple(at), trial=3, step=7)  # other draws
    assert not np.array_equal(other_step["pts"], by_index["pts"][: len(other_step["pts"])]) \
        or len(other_step["pts"]) != len(by_index["pts"])


def test_a_scene_without_a_path_is_observed_at_the_callers_poses(lab, tmp_path):
    """A closed loop's scene needs no path: the lab with its path deleted gives, at the lab's pose 2 with step 2,
    what the lab gives at its path pose 2 (every stage, the calibration draws too). A path index is refused by
    name, and `build` still needs a path (E102)."""
    import shutil

    shutil.copytree("scenes", tmp_path / "scenes")
    pathless = tmp_path / "scenes" / "lab.wd"
    pathless.write_text(re.sub(r"\npath run \{[^}]*\}\n", "\n", Path(LAB).read_text()))
    scene = wiredsl.compile(pathless)
    assert scene.path is None
    sim, with_path = wiredsl.Simulator(scene, seed=9), wiredsl.Simulator(lab, seed=9)
    got = sim.observe(tuple(lab.path.poses[2]), trial=3, step=2)
    want = with_path.observe(2, trial=3)
    assert len(got["pts"]) > 100 and np.array_equal(got["pts"], want["pts"])
    assert got.records() == want.records()
    with pytest.raises(ValueError, match="has no path: pass a robot pose"):
        sim.observe(0)
    r = CliRunner().invoke(main, ["build", str(pathless), "-o", str(tmp_path / "out")])
    assert r.exit_code == 1 and "E102" in r.output and "needs a path to be built" in r.output


def test_observe_a_6dof_path_pose_under_other_draws_and_as_its_transform(monkeypatch):
    """A path read from a trajectory file: observe(i, step=K) was refused (its pose has 12 numbers), and a
    tilted 4x4 too. Its transform, observed as an arbitrary pose with step i, is the path's pose i exactly
    (the nearest view-point chosen from the transform's floor position, not from R's first row)."""
    lab = Path(LAB).read_text()
    tum = (ROOT / "tests/data/trajectories/tum_fr1_xyz_groundtruth.txt").as_posix()
    run = 'path run {\n  straight from (0.8m, 2.5m) to (3.2m, 1.5m) step 0.4m\n}'
    assert run in lab  # the lab's view-points decide what each pose sees
    monkeypatch.chdir(ROOT / "scenes")  # the text's includes
    scene = wiredsl.compile(lab.replace(run, f'path run {{\n  read "{tum}"\n  body camera left\n'
                                             '  world at (2m, 1.5m, 0) rotate z 20deg\n}'))
    sim = wiredsl.Simulator(scene, seed=4, pipeline=Pipeline(name="none"), visibility="scene")  # the lists'
    for i in range(len(scene.path.poses)):
        M = np.vstack([np.array(scene.path.transforms[i], dtype=float), [0, 0, 0, 1]])
        assert abs(M[2, 2] - 1) > 1e-6  # tilted: a handheld camera's roll and pitch
        by_index, by_transform = sim.observe(i), sim.observe(M, step=i)
        (ideal, _, _), = by_transform.disturbed
        assert ideal.viewpoint == by_index.disturbed[0][0].viewpoint == "g3_2"  # nearest to (3.49, 2.82)
        assert np.array_equal(by_index["strokes"], by_transform["strokes"])
        assert np.allclose(by_index["pts"], by_transform["pts"], atol=1e-9)
        assert np.array_equal(sim.observe(i, step=7)["strokes"][:, 2:], by_index["strokes"][:, 2:])


def test_observe_refuses_what_is_not_a_rigid_pose(lab):
    sim = wiredsl.Simulator(lab, seed=1)
    mirrored = np.diag([1.0, -1.0, 1.0, 1.0])
    with pytest.raises(ValueError, match="rigid transform"):
        sim.observe(mirrored, step=0)
    with pytest.raises(ValueError, match="needs step"):
        sim.observe((0.0, 0.0, 0.0))
    with pytest.raises(ValueError, match="not in 0.."):
        sim.observe(999)
    with pytest.raises(ValueError, match="not finite"):
        sim.observe((np.nan, 0, 0), step=1)


@pytest.mark.parametrize("bad", [-1, 2**63, 1.5, True, "7"])
def test_seeds_trials_and_steps_out_of_range_are_refused_by_name(lab, bad):
    """As the command line's --seed and --trial: integers in range, else a ValueError naming the argument
    (never numpy's OverflowError, a truncated 1.5 or a trial numbered -1)."""
    with pytest.raises(ValueError, match="seed must be an integer"):
        next(wiredsl.simulate(lab, trials=1, seed=bad))
    with pytest.raises(ValueError, match="seed must be an integer"):
        wiredsl.Simulator(lab, seed=bad)
    sim = wiredsl.Simulator(lab, seed=1)
    with pytest.raises(ValueError, match="trial must be an integer"):
        sim.observe(0, trial=bad)
    with pytest.raises(ValueError, match="step must be an integer"):
        sim.observe((1.0, 2.0, 0.0), step=bad)
    with pytest.raises(ValueError, match="trials must be an integer"):
        next(wiredsl.simulate(lab, trials=bad if bad != 2**63 else 0, seed=1))


@pytest.mark.parametrize(("kwargs", "message"), [
    ({"visibility": "bogus"}, "visibility must be one of auto, scene, exact, all"),  # was the scene's lists, silently
    ({"cameras": "none"}, "cameras must be one of both, left"),  # was the left camera alone, silently
])
def test_simulator_options_are_checked(lab, kwargs, message):
    with pytest.raises(ValueError, match=message):
        wiredsl.Simulator(lab, seed=1, **kwargs)


@pytest.mark.parametrize("poses", [[], [0.5], "0", [True]])
def test_simulate_refuses_poses_that_are_not_path_indices(lab, poses):
    """[] ran every pose, 0.5 pose 0 and "0" the characters of a string."""
    with pytest.raises(ValueError, match="poses must be"):
        next(wiredsl.simulate(lab, trials=1, seed=1, poses=poses))


def test_observe_refuses_a_pose_beyond_the_languages_lengths(lab):
    """1e300 m squared overflows: a pose is held to the 1e9 m a scene's lengths are (E110), with plain numbers."""
    sim = wiredsl.Simulator(lab, seed=1)
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        with pytest.raises(ValueError, match=r"pose \(1e\+300, 1.0, 0.0\) is beyond 1e\+09 m"):
            sim.observe((1e300, 1.0, 0.0), step=0)
        far = np.eye(4)
        far[0, 3] = -2e9
        with pytest.raises(ValueError, match="beyond"):
            sim.observe(far, step=0)
        with pytest.raises(ValueError, match=r"pose \(nan, 1.0, 0.0\) is not finite"):
            sim.observe((np.nan, 1, 0), step=0)
    assert sim.observe((1e9, 1.0, 0.0), step=0).n_trials == 1


def test_observe_follows_the_nearest_viewpoint(lab):
    """With the view-points' lists (visibility="scene"; the default removes hidden lines exactly, issue 35)."""
    sim = wiredsl.Simulator(lab, seed=1, pipeline=lab.pipelines[0].model_copy(update={"stages": []}),
                            visibility="scene")
    vp = lab.viewpoints
    for k, (x, y) in enumerate(vp.points[:3]):
        seen = sim.observe((x, y, 0.0), step=50 + k)
        view = seen.disturbed[0][0]
        assert view.viewpoint == vp.names[k]


def test_compile_error_carries_the_diagnostics_check_prints(tmp_path):
    bad = tmp_path / "bad.wd"
    bad.write_text("scene s\nmodel m {\n  line a (0, 0, 0) (1, 0, 0)\n  line a (0, 0, 0) (0, 1, 0)\n}\n")
    with pytest.raises(wiredsl.CompileError) as err:
        wiredsl.compile(str(bad))
    checked = CliRunner().invoke(main, ["check", str(bad)])
    assert checked.exit_code == 1
    assert [d.code for d in err.value.diagnostics] == re.findall(r"error\[(E\d+)\]", checked.stderr)
    assert str(err.value) + "\n" == checked.stderr
    assert f"{bad}:4:" in str(err.value) and "^" in str(err.value)
    with pytest.raises(wiredsl.CompileError, match=r"<string>:1:"):
        wiredsl.compile("scene\n")


@pytest.mark.parametrize("source", [None, b"wiredsl 1\n", 5])
def test_compile_refuses_what_is_neither_text_nor_a_path(source):
    """None was compiled as the text 'None' (E012, E100), bytes as "b'wiredsl 1\\n'"."""
    with pytest.raises(TypeError, match="scene text .str. or a path"):
        wiredsl.compile(source)


def test_compile_takes_text_and_paths_alike(lab, monkeypatch):
    text = Path(LAB).read_text()
    monkeypatch.chdir("scenes")  # a text's includes and files: from the current folder
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        assert wiredsl.compile(Path("lab.wd")).models == lab.models
    from_text = wiredsl.compile(text)
    assert [m.name for m in from_text.models] == [m.name for m in lab.models]


def readme_examples() -> list[str]:
    """The Python API page's examples (docs/reference/api.md)."""
    return re.findall(r"```python\n(.*?)```", (ROOT / "docs/reference/api.md").read_text(), re.S)


def test_the_api_page_examples_run(tmp_path, monkeypatch, capsys):
    """Every example runs, and a `print(...)  # text` line prints what its comment shows (up to a `...`)."""
    blocks = readme_examples()
    assert len(blocks) >= 3
    namespace: dict = {}
    for block in blocks:
        exec(compile(block, "docs/reference/api.md", "exec"), namespace)  # noqa: S102 - the page's own examples
    printed = capsys.readouterr().out
    shown = re.findall(r"^\s*print\(.*\)\s+# (.+)$", "".join(blocks), re.M)
    assert shown
    for text in shown:
        assert text.split("...")[0].strip() in printed, (text, printed)


# --- closed-loop helpers: the rig's cameras at a pose, features by name, same-pose observations cached --------


def _corners_by_source(batch, side: str) -> dict[str, np.ndarray]:
    return {r["source"]: np.array(r["at"]) for r in batch.select(kind="corner", camera=side)}


def _world_corners(sim) -> dict[str, np.ndarray]:
    world = sim.run.world
    return {world.feature_ids[int(f)]: np.asarray(x, dtype=float)
            for f, x in zip(world.corner_fid, world.corners, strict=True)}


def _cv2_project(cam, X: np.ndarray) -> np.ndarray:
    import cv2

    rvec, _ = cv2.Rodrigues(cam.R)
    if cam.model == "equidistant":
        uv, _ = cv2.fisheye.projectPoints(X.reshape(-1, 1, 3), rvec, cam.t, cam.K, cam.dist)
    else:
        uv, _ = cv2.projectPoints(X, rvec, cam.t, cam.K, cam.dist)
    return uv.reshape(-1, 2)


@pytest.mark.parametrize("path", ["scenes/lab.wd", "scenes/fisheye.wd"])
@pytest.mark.parametrize("pose", [3, (1.7, 2.2, 0.4)])
def test_nominal_cameras_project_as_opencv_does(path, pose):
    """The nominal K, distortion, R and t at a pose, given to cv2.projectPoints (cv2.fisheye for an equidistant
    lens), put each corner where the engine's ideal projection does."""
    scene = wiredsl.compile(path)
    sim = wiredsl.Simulator(scene, seed=1, pipeline=Pipeline(name="none"))
    seen = sim.observe(pose, step=None if isinstance(pose, int) else 9)
    where = _world_corners(sim)
    n = 0
    for side in ("left", "right"):
        cam = sim.camera(pose, side)
        assert cam.model == scene.camera(getattr(scene.rig, side).camera).distortion
        got = _corners_by_source(seen, side)
        uv = _cv2_project(cam, np.array([where[s] for s in got]))
        assert np.abs(uv - np.array(list(got.values()))).max() < 1e-6
        n += len(got)
    assert n >= 6


def test_the_projection_matrix_is_the_undistorted_projection():
    """P = K [R | t] gives what OpenCV's undistortPoints makes of the engine's distorted corners."""
    import cv2

    scene = wiredsl.compile("scenes/lab.wd")
    sim = wiredsl.Simulator(scene, seed=1, pipeline=Pipeline(name="none"))
    cam = sim.camera(2, "right")
    assert cam.P.shape == (3, 4) and np.any(cam.dist)
    got = _corners_by_source(sim.observe(2), "right")
    where = _world_corners(sim)
    X = np.column_stack([np.array([where[s] for s in got]), np.ones(len(got))])
    h = X @ cam.P.T
    ideal = h[:, :2] / h[:, 2:]
    und = cv2.undistortPoints(np.array(list(got.values())).reshape(-1, 1, 2), cam.K, cam.dist, P=cam.K,
                              criteria=(cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12))
    assert len(got) >= 3 and np.abs(und.reshape(-1, 2) - ideal).max() < 1e-4


def test_a_trials_cameras_are_the_ones_its_corners_were_projected_with(monkeypatch):
    """Under calibration_error alone, trial K's corners are where cv2.projectPoints puts them with the cameras
    `camera(pose, side, trial=K)` gives, and those differ from the nominal ones."""
    monkeypatch.chdir("scenes")
    text = Path("lab.wd").read_text() + "\npipeline calib_only {\n  calibration_error sigma 1\n}\n"
    scene = wiredsl.compile(text)
    sim = wiredsl.Simulator(scene, seed=5, pipeline="calib_only")
    where = _world_corners(sim)
    for trial in (0, 3):
        for pose in (1, (2.0, 2.4, -0.3)):
            seen = sim.observe(pose, trial=trial, step=None if isinstance(pose, int) else 4)
            for side in ("left", "right"):
                cam, nominal = sim.camera(pose, side, trial=trial), sim.camera(pose, side)
                assert np.abs(cam.K - nominal.K).max() > 1e-3
                got = _corners_by_source(seen, side)
                uv = _cv2_project(cam, np.array([where[s] for s in got]))
                assert len(got) >= 2 and np.abs(uv - np.array(list(got.values()))).max() < 1e-6
    with pytest.raises(ValueError, match="trial"):
        sim.camera(1, "left", trial=-1)
    with pytest.raises(ValueError, match="side"):
        sim.camera(1, "middle")


def test_features_are_selected_by_placement_name_and_declared_kind(lab):
    sim = wiredsl.Simulator(lab, seed=7, pipeline=Pipeline(name="none"))
    assert set(sim.select(placement="bin1")) == {s for s in sim.kinds if s.startswith("bin1.")}
    lines = sim.select(kind="line")
    assert lines and all(sim.kinds[s] == "line" for s in lines)
    seen = sim.observe(3).select(kind="line")
    assert seen and {r["source"] for r in seen} <= set(lines)
    assert any(r["kind"] == "polyline" for r in seen)  # a line's image under distortion is a curve
    assert sim.observe(3).select(placement="table1", feature="top_a")[0]["source"] == "table1.top_a"
    for bad, match in ((dict(placement="bin"), "did you mean 'bin[12]'"), (dict(kind="lines"), "did you mean 'line'"),
                       (dict(placement="bin1", feature="top_a"), "no feature of placement 'bin1'")):
        with pytest.raises(ValueError, match=match):
            sim.select(**bad)


def test_the_same_observation_is_cached_and_equals_a_fresh_one(lab):
    sim = wiredsl.Simulator(lab, seed=7, pipeline="paper")
    a = sim.observe(2, trial=1)
    assert sim.observe(2, trial=1) is a
    assert sim.observe(2, trial=2) is not a and sim.observe((1.0, 2.0, 0.1), trial=1, step=2) is not a
    fresh = wiredsl.Simulator(lab, seed=7, pipeline="paper").observe(2, trial=1)
    for name in a.keys():
        assert np.array_equal(a[name], fresh[name]), name
    for k in range(70):  # bounded: the oldest is dropped
        sim.observe(2, trial=10 + k)
    assert len(sim._seen) == wiredsl.api.OBSERVED and sim.observe(2, trial=1) is not a


def test_a_small_simulate_decides_its_engine_as_build_does_and_loads_no_numba(tmp_path):
    """engine="auto" in the API is build's choice (run.settle_auto_engine): a 3-trial run of the lab is too small
    for the compiled kernel to pay for loading numba, so it runs on numpy, numba never imported (before, the API
    ran the kernel for any size, and on a fresh install compiled it first: some 43 s of CPU for one trial), and
    gives build's values for those trials."""
    import json
    import subprocess

    probe = ("import json, sys, numpy as np, wiredsl\n"
             "lab = wiredsl.compile('scenes/lab.wd')\n"
             "(b,) = list(wiredsl.simulate(lab, trials=3, seed=11))\n"
             "np.savez(sys.argv[1], pts=b['pts'], strokes=b['strokes'])\n"
             "print(json.dumps('numba' in sys.modules))\n")
    out = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "api.npz")], cwd=ROOT, capture_output=True,
                         text=True, check=True)
    assert json.loads(out.stdout.splitlines()[-1]) is False, out.stderr
    built = wiredsl.load(build(tmp_path, "--trials", "3", "--seed", "11"), arrays=True)
    api = np.load(tmp_path / "api.npz")
    assert np.array_equal(api["strokes"], built["strokes"])
    assert np.array_equal(api["pts"].astype(np.float32), built["pts"])


def test_a_simulator_on_a_fresh_install_observes_on_numpy_and_compiles_nothing(tmp_path):
    """Simulator(engine="auto") is a stream of one-trial views: with numba's cache empty (a private
    NUMBA_CACHE_DIR, as on a fresh install) it observes on numpy, so the first `observe` compiles nothing (before,
    the closed-loop example's first step compiled the kernel: 43 s of CPU, COMPILE_SECONDS), and its batch is
    engine="kernel"'s (the suite's warm cache) exactly; with the loop cached, auto runs the kernel."""
    import json
    import subprocess

    probe = ("import json, sys, numpy as np, wiredsl\n"
             "lab = wiredsl.compile('scenes/lab.wd')\n"
             "sim = wiredsl.Simulator(lab, seed=5, pipeline='paper')\n"
             "b = sim.observe((1.0, 1.2, 0.2), trial=3, step=1)\n"
             "np.savez(sys.argv[1], pts=b['pts'], strokes=b['strokes'])\n"
             "print(json.dumps([sim.run.engine, len(sim.run.compiled_stages())]))\n")
    env = dict(os.environ, NUMBA_CACHE_DIR=str(tmp_path / "numba"))
    out = subprocess.run([sys.executable, "-c", probe, str(tmp_path / "auto.npz")], cwd=ROOT, capture_output=True,
                         text=True, check=True, env=env)
    engine, compiled = json.loads(out.stdout.splitlines()[-1])
    assert engine == "numpy" and compiled > 0, out.stderr
    assert not list((tmp_path / "numba").rglob("*.nbc")), "numba compiled something"
    lab = wiredsl.compile(ROOT / "scenes" / "lab.wd")
    warm = wiredsl.Simulator(lab, seed=5, pipeline="paper")
    assert warm.run.engine in ("auto", "kernel")  # the suite's warm-up compiled the loop
    kernel = wiredsl.Simulator(lab, seed=5, pipeline="paper", engine="kernel").observe((1.0, 1.2, 0.2), trial=3,
                                                                                          step=1)
    auto = np.load(tmp_path / "auto.npz")
    assert np.array_equal(auto["strokes"], kernel["strokes"])
    assert np.array_equal(auto["pts"], kernel["pts"])

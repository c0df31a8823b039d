"""wiredsl.gym: Gymnasium's checker passes, an episode replays bit for bit from its seed, the observation encodes
what the Simulator sees, and the tasks reward and end as declared."""

from __future__ import annotations

import math
import subprocess
import sys
import warnings
from pathlib import Path

import numpy as np
import pytest

gymnasium = pytest.importorskip("gymnasium")  # the `gym` extra, part of `test`

import wiredsl  # noqa: E402
import wiredsl.gym as wg  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent
LAB = ROOT / "scenes" / "lab.wd"


@pytest.fixture(scope="module")
def lab():
    return wiredsl.compile(LAB)


@pytest.mark.parametrize("motion,task", [("planar", wg.Task("reach", "bin1")), ("6dof", wg.Task("track", "table1"))])
def test_gymnasiums_checker_passes(lab, motion, task):
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker's warnings too
        check_env(wg.WiredslEnv(lab, task, motion=motion), skip_render_check=True)


def episode(env, seed: int, steps: int = 12):
    obs, info = env.reset(seed=seed)
    actions = np.random.default_rng(seed).uniform(-1, 1, (steps, env.action_space.shape[0])).astype(np.float32)
    trace = [(obs, 0.0, info)]
    for a in actions:
        obs, reward, terminated, truncated, info = env.step(a * np.float32(0.5))
        trace.append((obs, reward, info))
        if terminated or truncated:
            break
    return trace


@pytest.mark.parametrize("motion", ["planar", "6dof"])
def test_an_episode_replays_bit_for_bit_from_its_seed(lab, motion):
    task = wg.Task("reach", "bin1")
    a = episode(wg.WiredslEnv(lab, task, motion=motion), seed=11)
    b = episode(wg.WiredslEnv(lab, task, motion=motion), seed=11)
    assert len(a) == len(b) > 5
    for (oa, ra, ia), (ob, rb, ib) in zip(a, b, strict=True):
        assert ra == rb and ia == ib
        for key in oa:
            assert oa[key].tobytes() == ob[key].tobytes(), key
    c = episode(wg.WiredslEnv(lab, task, motion=motion), seed=12)
    assert c[0][2]["trial"] != a[0][2]["trial"]
    assert a[0][0]["pose"].tobytes() != c[0][0]["pose"].tobytes()


def test_the_observation_encodes_what_the_simulator_sees(lab):
    env = wg.WiredslEnv(lab, wg.Task("reach", "bin1"), max_corners=4, max_segments=16)
    obs, info = env.reset(seed=3)
    obs, *_ , info = env.step(np.array([0.4, 0.2], np.float32))
    pose = tuple(float(v) for v in env._pose)
    seen = wiredsl.Simulator(lab, seed=0).observe(pose, trial=info["trial"], step=1)  # the env's default seed 0
    for cam, name in ((0, "left"), (1, "right")):
        camera = lab.camera(getattr(lab.rig, name).camera)
        size = np.array([camera.width, camera.height])
        corners = [np.array(r["at"]) for r in seen.records() if r["kind"] == "corner" and r["camera"] == name]
        n = min(len(corners), 4)
        assert n and obs["corner_mask"][cam].sum() == n
        assert np.allclose(obs["corners"][cam, :n], np.array(corners[:n]) / size, atol=1e-6)
        first = next(r for r in seen.records() if r["kind"] != "corner" and r["camera"] == name)
        assert np.allclose(obs["segments"][cam, 0], np.concatenate(first["points"][:2]) / np.tile(size, 2), atol=1e-6)
        assert obs["segment_mask"][cam].sum() == 16  # the lab fills every slot
    assert np.allclose(obs["pose"], pose, atol=1e-6)


def test_reaching_the_goal_pays_and_ends_the_episode(lab):
    env = wg.WiredslEnv(lab, wg.Task("reach", "bin1"), start_noise=0.0)
    obs, info = env.reset(seed=0)
    gx, gy, gh = info["goal"]
    assert math.isclose(math.hypot(gx - 4.6, gy - 3.2), 1.2)  # 1.2 m from bin1's origin
    for _ in range(env.max_steps):
        x, y, h = (float(v) for v in obs["pose"])
        d = math.hypot(gx - x, gy - y)
        want = math.atan2(gy - y, gx - x) if d > 0.05 else gh
        err = math.atan2(math.sin(want - h), math.cos(want - h))
        fwd = min(d / env.step_length, 1.0) if abs(err) < 0.3 and d > 0.05 else 0.0
        obs, reward, terminated, truncated, info = env.step(np.array([fwd, np.clip(err / env.turn, -1, 1)]))
        if terminated or truncated:
            break
    assert terminated and not truncated and reward > 9 and info["distance"] <= env.task.tolerance


def test_leaving_the_area_ends_the_episode_with_a_penalty(lab):
    env = wg.WiredslEnv(lab, wg.Task("reach", "bin1"), start_noise=0.0)
    env.reset(seed=0)
    env._pose[2] += math.pi  # face away from the room
    for _ in range(env.max_steps):
        _, reward, terminated, truncated, _ = env.step(np.array([1.0, 0.0], np.float32))
        if terminated or truncated:
            break
    assert terminated and reward < -9
    obs, _ = env.reset(seed=0)  # a further step would carry the robot further out, beyond the observation space
    assert env.observation_space.contains(obs)
    env._pose[2] += math.pi
    while not any(env.step(np.array([1.0, 0.0], np.float32))[2:4]):
        pass
    with pytest.raises(RuntimeError, match="the episode has ended"):
        env.step(np.array([1.0, 0.0], np.float32))
    obs, _ = env.reset(seed=1)
    assert env.observation_space.contains(obs)


def test_keeping_the_target_in_view_pays_and_losing_it_ends_the_episode(lab):
    env = wg.WiredslEnv(lab, wg.Task("track", "table1", patience=2), start_noise=0.0)
    env.reset(seed=0)
    _, reward, terminated, _, info = env.step(np.zeros(2, np.float32))
    assert reward == 1.0 and not terminated and info["seen"] >= 1
    rewards = []
    for _ in range(12):  # turn on the spot, away from the table
        _, reward, terminated, _, info = env.step(np.array([0.0, 1.0], np.float32))
        rewards.append(reward)
        if terminated:
            break
    assert terminated and rewards[-2:] == [0.0, 0.0] and info["seen"] == 0


def test_bad_arguments_are_refused_by_name(lab):
    with pytest.raises(ValueError, match="did you mean 'bin1'"):
        wg.WiredslEnv(lab, wg.Task("reach", "bim1"))
    with pytest.raises(ValueError, match="'reach' or 'track'"):
        wg.Task("fetch", "bin1")
    with pytest.raises(ValueError, match="planar"):
        wg.WiredslEnv(lab, wg.Task("reach", "bin1"), motion="flying")
    with pytest.raises(RuntimeError, match="reset"):
        wg.WiredslEnv(lab, wg.Task("reach", "bin1")).step(np.zeros(2, np.float32))


def test_the_visibility_is_the_simulators_and_scene_keeps_hidden_lines(lab):
    """visibility="scene" (the view-point lists: about 4x less CPU a step on the lab) gives the Simulator's own
    observation with that visibility, which keeps more line than the default's exact hidden lines (the lab has
    faces); a bad value is refused by name."""
    pose = (2.0, 1.5, 0.3)
    fast = wg.WiredslEnv(lab, wg.Task("reach", "bin1"), visibility="scene").sim.observe(pose, trial=0, step=1)
    alone = wiredsl.Simulator(lab, seed=0, visibility="scene").observe(pose, trial=0, step=1)
    exact = wg.WiredslEnv(lab, wg.Task("reach", "bin1")).sim.observe(pose, trial=0, step=1)
    assert np.array_equal(fast["pts"], alone["pts"]) and np.array_equal(fast["strokes"], alone["strokes"])

    def length(b):
        return sum(np.linalg.norm(np.diff(p, axis=0), axis=1).sum() for p in np.split(b["pts"], b["start"][1:-1]))

    assert length(fast) > 1.02 * length(exact)
    with pytest.raises(ValueError, match="exact"):
        wg.WiredslEnv(lab, wg.Task("reach", "bin1"), visibility="hidden")


def test_gymnasium_makes_it_by_id():
    env = gymnasium.make("wiredsl/Scene-v0", scene=str(LAB), task=wg.Task("track", "table1"))
    obs, _ = env.reset(seed=1)
    assert env.observation_space.contains(obs)


def test_the_example_evaluates_a_policy(tmp_path):
    out = tmp_path / "evaluate.json"
    proc = subprocess.run([sys.executable, str(ROOT / "examples/gym/evaluate.py"), "--episodes", "2", "-o", str(out)],
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stderr
    import json

    results = {r["policy"]: r for r in json.loads(out.read_text())}
    assert results["goal"]["success_rate"] == 1.0 and results["random"]["success_rate"] < 1.0

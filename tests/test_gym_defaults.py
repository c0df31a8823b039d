"""Issue 35, item 8: Gymnasium conventions -- `make` with no arguments (the lab's reach task) passes the checker,
the API reference shows WiredslEnv's and Task's signatures, the reach goal faces the target with the rig's cameras
(not the robot's nose), and `import wiredsl.gym` without gymnasium names its extra."""

from __future__ import annotations

import inspect
import math
import re
import subprocess
import sys
import warnings
from pathlib import Path

import pytest

gymnasium = pytest.importorskip("gymnasium")

import wiredsl  # noqa: E402
import wiredsl.gym as wg  # noqa: E402

ROOT = Path(__file__).resolve().parent.parent


def test_make_with_no_arguments_is_the_labs_reach_task_and_passes_check_env():
    from gymnasium.utils.env_checker import check_env

    with warnings.catch_warnings():
        warnings.simplefilter("error")  # the checker's warnings, and any of wiredsl's, fail the test
        env = gymnasium.make("wiredsl/Scene-v0")
        check_env(env.unwrapped, skip_render_check=True)
    base = env.unwrapped
    assert Path(base.scene.source).name == "lab.wd" and base.task == wg.Task("reach", "bin1")
    obs, info = env.reset(seed=3)
    assert env.observation_space.contains(obs) and math.isfinite(info["distance"])
    with pytest.raises(ValueError, match="give a task"):
        wg.WiredslEnv(ROOT / "scenes" / "lab.wd")


def test_the_default_lab_ships_in_the_wheel():
    """The wheel's force-include holds the lab and what it includes, where wiredsl.gym looks for it."""
    text = (ROOT / "pyproject.toml").read_text()
    lab = (ROOT / "scenes" / "lab.wd").read_text()
    needed = {"scenes/lab.wd"} | {f"scenes/{m}" for m in re.findall(r'"([^"]+)"', lab) if "/" not in m} | \
        {"scenes/" + m.split("/")[0] for m in re.findall(r'include "([^"]+)"', lab)}
    for path in needed:
        assert f'"{path}" = "wiredsl/{path}"' in text, path


def test_a_side_looking_rig_sees_the_target_at_the_goal():
    """tests/data/table_box_cup.wd's rig looks to the robot's right: at the reach goal both cameras see the box
    (facing it with the robot's nose, as before, they saw none of it)."""
    scene = wiredsl.compile(ROOT / "tests" / "data" / "table_box_cup.wd")
    assert math.isclose(wg.rig_yaw(scene.rig), -math.pi / 2, abs_tol=1e-9)
    task = wg.Task("reach", "box1")
    goal = wg.WiredslEnv(scene, task).reset(seed=0)[1]["goal"]
    env = wg.WiredslEnv(scene, task, start=goal, start_noise=0.0)
    _, info = env.reset(seed=0)
    assert info["distance"] < 1e-9 and info["seen"] >= 4
    lab = wiredsl.compile(ROOT / "scenes" / "lab.wd")  # a forward-looking rig: the robot faces the target
    env = wg.WiredslEnv(lab, wg.Task("reach", "bin1"))
    (gx, gy, heading), (tx, ty) = env.goal_xy.tolist() + [env.goal_heading], env.target_xy
    assert abs(wg.rig_yaw(lab.rig)) < 1e-9 and math.isclose(heading, math.atan2(ty - gy, tx - gx))


def test_the_api_reference_shows_the_signatures():
    """mkdocstrings shows a class's signature from its __init__ when merged into the class (and __init__ has no
    page of its own without a docstring); every parameter is described."""
    page = (ROOT / "docs" / "reference" / "api.md").read_text()
    block = page[page.index("::: wiredsl.gym"):]
    assert "merge_init_into_class: true" in block and "show_signature: true" in block
    for cls, doc in ((wg.WiredslEnv, wg.WiredslEnv.__init__.__doc__), (wg.Task, wg.Task.__doc__)):
        for name in inspect.signature(cls).parameters:
            assert re.search(rf"^\s+{name}: \S", doc, re.M), (cls.__name__, name)


def test_import_without_gymnasium_names_the_extra(tmp_path):
    block = tmp_path / "gymnasium"
    block.mkdir()
    (block / "__init__.py").write_text("raise ImportError('No module named gymnasium')\n")
    r = subprocess.run([sys.executable, "-c", "import wiredsl.gym"], capture_output=True, text=True,
                       env={"PYTHONPATH": f"{tmp_path}:{ROOT}", "PATH": "/usr/bin:/bin"})
    assert r.returncode == 1
    assert r.stderr.strip().splitlines()[-1] == \
        "ImportError: wiredsl.gym needs gymnasium: pip install '.[gym]' in wiredsl's checkout"

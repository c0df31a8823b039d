"""The examples under examples/: a plug-in package installed from a copy outside the repository, and the
closed loop. The plug-in's measure must reach a study table and its effect a build's manifest (on the numpy
engine: it ships no compiled kernel)."""

from __future__ import annotations

import csv
import json
import math
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
EXAMPLE = ROOT / "examples" / "pnp_plugin"

pytest.importorskip("cv2")


@pytest.fixture(scope="module")
def plugin_site(tmp_path_factory) -> Path:
    """The example package copied out of the repository and installed (not editable) into a folder of its own."""
    tmp = tmp_path_factory.mktemp("plugin")
    copy = tmp / "wiredsl-pnp"
    shutil.copytree(EXAMPLE, copy, ignore=shutil.ignore_patterns("build", "*.egg-info", "__pycache__"))
    site = tmp / "site"
    r = subprocess.run([sys.executable, "-m", "pip", "install", "-q", "--no-deps", "--no-build-isolation",
                        "--target", str(site), str(copy)], capture_output=True, text=True)
    assert r.returncode == 0, r.stderr
    return site


def wiredsl(site: Path, *args: str, cwd: Path) -> subprocess.CompletedProcess:
    env = {**os.environ, "PYTHONPATH": os.pathsep.join([str(site), os.environ.get("PYTHONPATH", "")])}
    return subprocess.run([sys.executable, "-m", "wiredsl", *args], capture_output=True, text=True, env=env, cwd=cwd)


def example_scene(tmp: Path, study: str, cut: str = "# Which source") -> Path:
    """The example's scene with its include made absolute (the copy lives outside the repository), cut before
    the line starting with `cut`, with `study` appended."""
    text = (EXAMPLE / "scenes" / "pnp_lab.wd").read_text()
    text = text.replace('include "../../../scenes/lab.wd"', f"include {json.dumps(str(ROOT / 'scenes/lab.wd'))}")
    path = tmp / "pnp_lab.wd"
    path.write_text(text[:text.index(cut)] + study)
    return path


def test_installed_plugin_is_listed_checked_built_and_measured(plugin_site, tmp_path):
    listed = wiredsl(plugin_site, "plugins", cwd=tmp_path)
    assert listed.returncode == 0, listed.stderr
    rows = {tuple(line.split("\t")[:3]) for line in listed.stdout.splitlines()}
    assert ("effect", "radial_corner_noise", "wiredsl-pnp 0.1.0") in rows
    assert ("measure", "pnp", "wiredsl-pnp 0.1.0") in rows

    scene = example_scene(tmp_path, """study pnp_small {
  pipeline corners
  vary radial_corner_noise.sigma values [0, 1px]
  trials 3
  poses [0, 2]
  seed 5
  measure pnp
}
""")
    r = wiredsl(plugin_site, "check", str(scene), cwd=tmp_path)
    assert r.returncode == 0, r.stderr

    r = wiredsl(plugin_site, "build", str(scene), "--pipeline", "corners", "--trials", "3", "--format", "npz",
                "--seed", "1", "-o", str(tmp_path / "b"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    manifest = json.loads((tmp_path / "b" / "manifest.json").read_text())
    assert manifest["engines"]["radial_corner_noise"] == "numpy"
    assert manifest["ran"]["radial_corner_noise"] > 0

    r = wiredsl(plugin_site, "study", str(scene), "pnp_small", "--executor", "inprocess", "--no-plots",
                "-o", str(tmp_path / "s"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    with open(tmp_path / "s" / "table.csv") as fh:
        table = [row for row in csv.DictReader(fh) if row["measure"] == "pnp"]
    stats = {row["statistic"] for row in table}
    assert stats == {"rotation_error", "position_error", "solved", "corners"}
    solved = [float(row["mean"]) for row in table if row["statistic"] == "solved"]
    assert min(solved) > 0.5  # the board's twelve corners give a pose in most trials
    for row in table:
        assert math.isfinite(float(row["mean"])), row


def test_without_the_plugin_the_scene_is_refused_by_name(tmp_path):
    """No entry point, no code: the names are unknown, with a diagnostic at each use (never an import)."""
    scene = example_scene(tmp_path, "")
    env = {k: v for k, v in os.environ.items() if k != "PYTHONPATH"}
    r = subprocess.run([sys.executable, "-m", "wiredsl", "check", str(scene)], capture_output=True, text=True,
                       env=env, cwd=tmp_path)
    if "radial_corner_noise" not in r.stderr and r.returncode == 0:
        pytest.skip("the example plug-in is installed in this environment")
    assert r.returncode == 1 and "radial_corner_noise" in r.stderr, r.stderr


def test_pnp_recovers_the_pose_without_disturbance(tmp_path):
    """The measure against the truth: undisturbed corners give each camera's pose to numerical precision."""
    sys.path.insert(0, str(EXAMPLE))
    try:
        from wiredsl_pnp.pnp import PnP
    finally:
        sys.path.remove(str(EXAMPLE))
    import wiredsl
    from wiredsl.scene import Pipeline

    scene = wiredsl.compile(example_scene(tmp_path, "", cut="# The paper's seven"))  # the board, no plug-in stage
    sim = wiredsl.Simulator(scene, seed=0, pipeline=Pipeline(name="none"))
    params = PnP.Params()
    board = PnP.prepare(params, sim.run)
    solved = 0
    for i in range(len(sim.scene.path.poses)):
        (result, sets, _), = sim.observe(i).disturbed
        got = PnP.measure(params, board, result, sets, 1)
        if got["corners"][0] >= params.min_corners:
            solved += 1
            assert got["solved"][0] == 1
            assert got["rotation_error"][0] < 1e-5 and got["position_error"][0] < 1e-6, (i, got)
    assert solved >= 3


def test_closed_loop_reaches_the_bin_and_degrades_with_lateral_shift(tmp_path):
    sys.path.insert(0, str(ROOT / "examples" / "closed_loop"))
    try:
        import drive_to_bin
    finally:
        sys.path.pop(0)
    assert drive_to_bin.main(["--trials", "6", "--shifts", "0,32", "--no-plot", "-o", str(tmp_path)]) == 0
    first = (tmp_path / "closed_loop.json").read_bytes()
    rows = json.loads(first)["rows"]
    assert rows[0]["success_rate"] == 1.0 and rows[0]["mean_stop_error_m"] < 0.05
    assert rows[1]["success_rate"] < rows[0]["success_rate"]
    # the same seed, the same file
    assert drive_to_bin.main(["--trials", "6", "--shifts", "0,32", "--no-plot", "-o", str(tmp_path / "again")]) == 0
    assert (tmp_path / "again" / "closed_loop.json").read_bytes() == first


def test_closed_loop_refuses_bad_arguments_before_it_drives(tmp_path, monkeypatch, capsys):
    """Usage errors (exit 2, no traceback, nothing written): no trials (was a ZeroDivisionError after the
    loop), a shift that is not a number, and a plot without matplotlib (was an ImportError after every trial)."""
    sys.path.insert(0, str(ROOT / "examples" / "closed_loop"))
    try:
        import drive_to_bin
    finally:
        sys.path.pop(0)
    for argv in (["--trials", "0", "--no-plot"], ["--shifts", "0,x", "--no-plot"], ["--shifts", "nan", "--no-plot"],
                 ["--shifts", "-1", "--no-plot"], ["--max-steps", "0", "--no-plot"], ["--seed", "-1", "--no-plot"],
                 ["--shifts", "0,5000", "--no-plot"]):  # beyond lateral_shift's 1000 px: was a CompileError
        with pytest.raises(SystemExit) as stop:
            drive_to_bin.main([*argv, "-o", str(tmp_path)])
        assert stop.value.code == 2, argv
    monkeypatch.setitem(sys.modules, "matplotlib", None)  # as if not installed
    with pytest.raises(SystemExit) as stop:
        drive_to_bin.main(["--trials", "1", "-o", str(tmp_path)])
    assert stop.value.code == 2
    assert "pip install '.[plot]'" in capsys.readouterr().err
    assert not list(tmp_path.iterdir())

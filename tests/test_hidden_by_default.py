"""Issue 35, item 1: where a scene has faces and computed view-point lists, `auto` (the default of build, study,
export, the API and the Gymnasium environment) removes hidden lines exactly, unless unaffordable, and then draws
the lists with W129 at the statement that made it so. tests/data/table_box_cup.wd is the user's scene: a table
with a box and a cup on it, a side-looking rig on a robot driving past, view-points with `visibility auto`.

The oracle is independent of the engine: each drawn point of the table's top, its legs and the cup's base is
lifted back to 3D along its camera ray (onto the plane or line it lies on), and the segment from the camera
centre to it is tested against the box, the cup's solid and the table top (each shrunk by 4 mm)."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
from click.testing import CliRunner

from wiredsl import run as runs
from wiredsl.cli import main

SCENE = "tests/data/table_box_cup.wd"
BOX = (np.array([2.75, -0.1, 0.75]), np.array([3.05, 0.1, 1.0]))
CUP = (np.array([2.6, 0.25]), 0.05, 0.75, 0.85)
TOP = (np.array([2.4, -0.4]), np.array([3.6, 0.4]), 0.75)
LEGS = {"a": (-0.55, -0.35), "b": (0.55, -0.35), "c": (0.55, 0.35), "d": (-0.55, 0.35)}
M = 0.004


def _hidden(C, X) -> bool:
    """Does the open segment C -> X pass through the box, the cup or the table top (shrunk by M)?"""
    P = C + np.linspace(0.0, 1.0, 3000)[:-30, None] * (X - C)
    lo, hi = BOX
    if np.any(np.all((P > lo + M) & (P < hi - M), axis=1)):
        return True
    c, r, z0, z1 = CUP
    if np.any((np.linalg.norm(P[:, :2] - c, axis=1) < r - M) & (P[:, 2] > z0 + M) & (P[:, 2] < z1 - M)):
        return True
    a, b, z = TOP
    above = np.sign(P[:, 2] - z)
    return any(np.all((P[i, :2] > a + M) & (P[i, :2] < b - M)) for i in np.flatnonzero(above[:-1] != above[1:]))


def _strokes(view):
    """(source, (n, 2) pixels) of every drawn stroke, conics sampled along their ellipse."""
    for f in view["lines"] + view["polylines"]:
        p = np.array(f["points"])
        yield f["source"], np.concatenate([p[:-1] + s * (p[1:] - p[:-1]) for s in np.linspace(0, 1, 8, False)])
    for f in view["conics"]:
        t = np.linspace(0, 2 * np.pi, 200, endpoint=False)
        (cx, cy), (a, b), g = f["centre"], f["axes"], f["angle"]
        x, y = a * np.cos(t), b * np.sin(t)
        yield f["source"], np.column_stack([cx + x * np.cos(g) - y * np.sin(g), cy + x * np.sin(g) + y * np.cos(g)])


def hidden_points(dump) -> dict[str, int]:
    """Per feature of the table and the cup's base: drawn sample points that a camera cannot see."""
    out: dict[str, int] = {}
    for pose in dump["poses"]:
        for side in ("left", "right"):
            v = pose[side]
            cam, R, t = v["camera"], np.array(v["rotation"]), np.array(v["translation"])
            C = -R.T @ t  # the camera centre: X_cam = R X + t
            for src, q in _strokes(v):
                if not src.startswith(("table1.", "cup1.base")):
                    continue
                rays = np.column_stack([(q[:, 0] - cam["cx"]) / cam["f"], (q[:, 1] - cam["cy"]) / cam["f"],
                                        np.ones(len(q))]) @ R
                for u in rays:
                    if src.startswith("table1.leg"):  # onto the vertical leg: the ray's closest point to it
                        xy = np.array(LEGS[src[-1]]) + [3.0, 0.0]
                        X = C + np.dot(xy - C[:2], u[:2]) / np.dot(u[:2], u[:2]) * u
                    else:  # the top's edges and the cup's base lie in the plane z = 0.75
                        X = C + (0.75 - C[2]) / u[2] * u
                    out[src] = out.get(src, 0) + _hidden(C, X)
    return out


def _build(tmp_path, *extra):
    out = tmp_path / ("out" + "".join(extra).replace("-", ""))
    r = CliRunner().invoke(main, ["build", SCENE, "-o", str(out), "--no-effects", "--no-svg", "--force", *extra])
    assert r.exit_code == 0, r.output
    return json.loads((out / "features.json").read_text()), json.loads((out / "manifest.json").read_text()), r


def test_build_draws_no_hidden_line_through_a_face_by_default(tmp_path):
    dump, manifest, r = _build(tmp_path)
    assert manifest["visibility"] == "exact" and "W129" not in r.stderr
    assert sum(hidden_points(dump).values()) == 0
    # the lists (what auto drew before): the table's back edge through the box, the far legs through the top,
    # the far half of the cup's base -- the oracle sees each
    listed, manifest, _ = _build(tmp_path, "--visibility", "scene")
    assert manifest["visibility"] == "scene"
    n = hidden_points(listed)
    assert n["table1.top"] > 0 and n["cup1.base"] > 0 and n["table1.leg_b"] + n["table1.leg_c"] > 0


def test_the_api_the_environment_a_study_and_export_use_the_same_rule(tmp_path):
    import wiredsl
    from wiredsl.engine.world import build_world
    from wiredsl.scene import Study
    from wiredsl.study import shards

    scene = wiredsl.compile(SCENE)
    assert wiredsl.Simulator(scene, seed=0, pipeline=None).run.options.visibility == "exact"
    ideal = next(iter(wiredsl.simulate(scene, trials=1, seed=0, pipeline=None)))
    dump, _, _ = _build(tmp_path)
    drawn = sum(len(p[s][k]) for p in dump["poses"] for s in ("left", "right") for k in ("lines", "polylines"))
    assert sum(1 for r in ideal.records() if r["kind"] in ("line", "polyline")) == drawn  # build's records
    study = Study.model_validate({"name": "p", "design": "grid", "trials": 2, "factors": [],
                                  "measures": [{"name": "detection_rate"}]})
    assert shards.visibility(study, scene, build_world(scene)).mode == "exact"
    gym = pytest.importorskip("wiredsl.gym")
    env = gym.WiredslEnv(scene, task=gym.Task("track", "box1"))
    assert env.sim.run.options.visibility == "exact"
    out = tmp_path / "colmap"
    r = CliRunner().invoke(main, ["export", SCENE, "--format", "colmap", "-o", str(out), "--no-effects"])
    assert r.exit_code == 0, r.output
    assert json.loads((out / "manifest.json").read_text())["visibility"] == "exact"


def test_over_the_budget_w129_is_said_at_the_viewpoints_everywhere(tmp_path, monkeypatch):
    """With the budget below the scene's estimate: the lists, and W129 located at the `viewpoints` statement
    (build), in the study's first lines, and as the API's UserWarning."""
    import wiredsl
    from wiredsl.scene import Study
    from wiredsl.study import run_study

    monkeypatch.setattr(runs, "AUTO_EXACT_SECONDS", 0.1)
    _, manifest, r = _build(tmp_path)
    assert manifest["visibility"] == "scene"
    line = next(x for x in r.stderr.splitlines() if "W129" in x)
    assert re.match(r".*table_box_cup\.wd:56:1: warning\[W129\]: hidden lines are not removed: 10 views x 12 "
                    r"occluding triangles", line), line
    scene = wiredsl.compile(SCENE)
    with pytest.warns(UserWarning, match="W129: hidden lines are not removed"):
        wiredsl.Simulator(scene, seed=0, pipeline=None)
    said = []
    study = Study.model_validate({"name": "p", "design": "grid", "trials": 2, "factors": [],
                                  "measures": [{"name": "survival"}]})
    _, _, program = __import__("wiredsl.language.compile", fromlist=["x"]).compile_file(SCENE)
    run_study(scene, study, tmp_path / "st", executor="inprocess", echo=said.append, program=program)
    assert any(re.match(r".*table_box_cup\.wd:56:1: warning\[W129\]", s) for s in said), said
    assert json.loads((tmp_path / "st" / "manifest.json").read_text())["visibility"] == "scene"

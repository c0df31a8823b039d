"""`build --visibility auto` (the default, issue 25): exact hidden lines where a scene's faces would hide what the
view-points' lists cannot say and it is affordable, else the lists and warning W129."""

from __future__ import annotations

import json
import re

import numpy as np
import pytest
import trimesh
from click.testing import CliRunner
from helpers import EYE_RIG

from wiredsl import run as runs
from wiredsl.cli import main
from wiredsl.engine.world import build_world
from wiredsl.language.compile import compile_file


def _build(tmp_path, scene: str, *extra: str):
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["build", scene, "-o", str(out), "--no-effects", "--no-svg", "--force", *extra])
    assert r.exit_code == 0, r.output
    return json.loads((out / "features.json").read_text()), json.loads((out / "manifest.json").read_text()), r


def _through_the_ball(dump) -> int:
    """Points of the cone's silhouette (sampled along its lines) inside the image of the ball, 1 px in from its
    outline, over every view: the cone stands behind the ball in scenes/meshes.wd."""
    inside = 0
    for pose in dump["poses"]:
        for view in (pose["left"], pose["right"]):
            strokes = view["lines"] + view["polylines"]
            ball = np.concatenate([np.array(f["points"]) for f in strokes if f["source"] == "ball1.surface"])
            centre = ball.mean(axis=0)
            radius = np.linalg.norm(ball - centre, axis=1).min()
            for f in strokes:
                if f["source"] == "cone1.side1":
                    p = np.array(f["points"])
                    s = np.linspace(0, 1, 50)[:, None, None]
                    q = (p[:-1] + s * (p[1:] - p[:-1])).reshape(-1, 2)
                    inside += int((np.linalg.norm(q - centre, axis=1) < radius - 1.0).sum())
    return inside


def test_the_default_removes_the_cones_silhouette_behind_the_ball(tmp_path):
    dump, manifest, _ = _build(tmp_path, "scenes/meshes.wd")
    assert manifest["visibility"] == "exact"
    assert _through_the_ball(dump) == 0
    listed, manifest, _ = _build(tmp_path, "scenes/meshes.wd", "--visibility", "scene")
    assert manifest["visibility"] == "scene"
    assert _through_the_ball(listed) > 0  # the view-points' whole-feature lists draw it through the ball


@pytest.mark.parametrize("name, mode", [("lab", "exact"), ("fisheye", "exact"), ("box", "scene"),
                                        ("cylinder", "scene"), ("handheld", "exact"), ("meshes", "exact")])
def test_what_auto_chooses_for_the_example_scenes(name, mode):
    """Faces with computed lists (lab, fisheye: issue 35, the lists drew the table's legs through its top), with
    no view-points (handheld) or a mesh's surfaces: exact; authored lists (box) are kept; no faces (cylinder):
    nothing to decide."""
    scene = compile_file(f"scenes/{name}.wd")[0]
    choice = runs.choose_visibility(scene, build_world(scene), 2 * len(scene.path.poses))
    assert (choice.mode, choice.warning) == (mode, None)


def test_exact_beyond_the_budget_warns_w129_at_the_mesh_and_keeps_the_lists(tmp_path, monkeypatch):
    """A budget between one view's estimate and six views' (the ball's exact views cost some 0.15 s of CPU each,
    benchmarks/visibility_cost.py: the default budget takes them, so the test lowers it)."""
    ball = trimesh.creation.icosphere(subdivisions=6, radius=0.4)  # 81,920 triangles
    ball.export(tmp_path / "ball.stl")
    (tmp_path / "s.wd").write_text("""wiredsl 1
model m {
  mesh read "ball.stl"
}
place m as m1 at (2m, 0, 1m)
""" + EYE_RIG + """path p {
  straight from (0, 0) to (0.2m, 0) step 0.1m
}
""")
    scene = compile_file(tmp_path / "s.wd")[0]
    world = build_world(scene)
    triangles = len(world.triangles)
    seconds = runs.exact_seconds(world, 6)
    monkeypatch.setattr(runs, "AUTO_EXACT_SECONDS", 2 * runs.exact_seconds(world, 1))
    assert seconds > runs.AUTO_EXACT_SECONDS  # 3 poses x 2 cameras: over the budget
    _, manifest, r = _build(tmp_path, str(tmp_path / "s.wd"))
    assert manifest["visibility"] == "scene"
    warning = next(line for line in r.stderr.splitlines() if "W129" in line)
    assert re.match(r".*s\.wd:3:3: warning\[W129\]", warning), warning
    assert f"{triangles:,} occluding triangles" in warning and "--visibility exact" in warning
    import wiredsl  # the API says it as a UserWarning, with the API's remedy

    with pytest.warns(UserWarning, match=r'W129: .*`visibility="exact"` changes the answer'):
        wiredsl.simulate(scene, trials=1, seed=0, pipeline=None)
    # one pose and one camera are affordable: exact, and no warning
    _, manifest, r = _build(tmp_path, str(tmp_path / "s.wd"), "--pose", "0", "--cameras", "left")
    assert manifest["visibility"] == "exact" and "W129" not in r.stderr



def test_build_the_api_and_studies_share_one_default():
    """wiredsl.DEFAULT_VISIBILITY is build's --visibility default and the API's visibility= default."""
    import inspect

    import wiredsl
    from wiredsl import api

    assert wiredsl.DEFAULT_VISIBILITY == "auto"
    option = next(p for p in main.commands["build"].params if p.name == "visibility")
    assert option.default == wiredsl.DEFAULT_VISIBILITY
    for fn in (api.simulate, api.Simulator.__init__):
        assert inspect.signature(fn).parameters["visibility"].default == wiredsl.DEFAULT_VISIBILITY


def test_the_api_removes_hidden_lines_by_default_as_build_does(tmp_path):
    """wiredsl.simulate and Simulator on scenes/meshes.wd: the cone's silhouette is not drawn through the ball
    by default (auto: exact), and is with visibility="scene" -- the same answers as build's."""
    import wiredsl

    scene = wiredsl.compile("scenes/meshes.wd")
    ideal = {vis: next(iter(wiredsl.simulate(scene, trials=1, seed=0, pipeline=None, **kw)))
             for vis, kw in (("auto", {}), ("scene", {"visibility": "scene"}))}
    build, _, _ = _build(tmp_path, "scenes/meshes.wd")
    listed, _, _ = _build(tmp_path, "scenes/meshes.wd", "--visibility", "scene")
    for vis, dump in (("auto", build), ("scene", listed)):  # the API's records are build's
        rec = ideal[vis].records()
        got = sum(1 for r in rec if r["source"] == "cone1.side1")
        want = sum(1 for p in dump["poses"] for v in (p["left"], p["right"]) for f in v["lines"] + v["polylines"]
                   if f["source"] == "cone1.side1")
        assert got == want
    sim = wiredsl.Simulator(scene, seed=0, pipeline=None)
    assert sim.run.options.visibility == "exact"
    assert wiredsl.Simulator(scene, seed=0, pipeline=None, visibility="scene").run.options.visibility == "scene"


def test_a_study_decides_once_for_all_its_points(tmp_path):
    """A study's visibility (shards.visibility): the mesh scene's few views are affordable (exact) when its
    factors vary only the pipeline (one shared projection); when a factor varies the cameras, every point
    projects its own and 512 points x 6 views of 1,422 triangles are over the budget: the lists, with W129."""
    from wiredsl.scene import Study
    from wiredsl.study import shards

    scene = compile_file("scenes/meshes.wd")[0]
    world = build_world(scene)
    pipeline_only = Study.model_validate({"name": "p", "design": "grid", "trials": 4, "factors": [],
                                          "measures": [{"name": "detection_rate"}]})
    assert shards.visibility(pipeline_only, scene, world).mode == "exact"
    assert shards.options(pipeline_only, scene, world).visibility == "exact"
    cams = Study.model_validate({**pipeline_only.model_dump(), "factors": [
        {"stage": "camera.eye", "param": "f", "values": [float(v) for v in np.linspace(490, 510, 512)]}]})
    choice = shards.visibility(cams, scene, world)
    assert choice.mode == "scene" and f"{512 * 6:,} views x 1,422 occluding triangles" in choice.warning
    # what a study's author can do about it: a study has no --visibility or --pose, but poses and points
    assert "study's `poses`" in choice.warning and "--visibility" not in choice.warning
    assert shards.options(cams, scene, world).visibility == "scene"


def test_check_reports_the_cost_of_exact_visibility_for_meshes(tmp_path):
    r = CliRunner().invoke(main, ["check", "scenes/meshes.wd"])
    assert r.exit_code == 0
    note = next(line for line in r.stderr.splitlines() if "exact visibility:" in line)
    assert "6 views x 1,422 occluding triangles" in note and "uses exact hidden lines" in note
    r = CliRunner().invoke(main, ["check", "scenes/lab.wd"])  # no meshes: no such note
    assert r.exit_code == 0 and "exact visibility:" not in r.stderr


def test_a_studys_manifest_records_the_visibility_its_points_used(tmp_path):
    """manifest.json says which hidden lines every point of the study had: the mesh scene's one pose, whose
    projection the points share, is affordable exactly (as build's default gives it: its manifest says the
    same), and the manifest is valid against schema/study-manifest.schema.json."""
    from wiredsl.io import schema
    from wiredsl.scene import Study
    from wiredsl.study import run_study

    scene = compile_file("scenes/meshes.wd")[0]
    study = Study.model_validate({"name": "p", "design": "grid", "trials": 2, "poses": [0], "factors": [],
                                  "measures": [{"name": "survival"}]})
    run_study(scene, study, tmp_path / "st", executor="inprocess")
    manifest = json.loads((tmp_path / "st" / "manifest.json").read_text())
    assert schema.problems(manifest) == []
    _, built, _ = _build(tmp_path, "scenes/meshes.wd", "--pose", "0")
    assert manifest["visibility"] == built["visibility"] == "exact"

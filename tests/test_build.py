"""`wiredsl build`: golden dumps, schema validity, SVG, determinism, no NaN whatever the pose."""

from __future__ import annotations

import json
import math
import os
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest
from click.testing import CliRunner
from hypothesis import given, settings
from hypothesis import strategies as st

from wiredsl.cli import main
from wiredsl.engine.simulate import Options, simulate
from wiredsl.engine.world import build_world
from wiredsl.io import emit, schema
from wiredsl.language.compile import compile_file

BUILDABLE = ["lab", "cylinder", "box", "handheld", "meshes"]
GOLDEN = Path("tests/golden")


def build_json(scene: str, *extra: str) -> dict:
    r = CliRunner().invoke(main, ["build", f"scenes/{scene}.wd", "-o", "-", "--no-effects", *extra])
    assert r.exit_code == 0, r.output
    return json.loads(r.stdout)


def _close(a, b, path="") -> list[str]:
    """Differences between two JSON values, numbers compared to 1e-6."""
    if isinstance(a, dict) and isinstance(b, dict):
        if a.keys() != b.keys():
            return [f"{path}: keys {sorted(a.keys() ^ b.keys())}"]
        return [d for k in a for d in _close(a[k], b[k], f"{path}/{k}")]
    if isinstance(a, list) and isinstance(b, list):
        if len(a) != len(b):
            return [f"{path}: length {len(a)} != {len(b)}"]
        return [d for i, (x, y) in enumerate(zip(a, b, strict=True)) for d in _close(x, y, f"{path}/{i}")]
    if isinstance(a, float | int) and isinstance(b, float | int) and not isinstance(a, bool):
        return [] if abs(a - b) <= 1e-6 else [f"{path}: {a} != {b}"]
    return [] if a == b else [f"{path}: {a!r} != {b!r}"]


@pytest.mark.parametrize("scene", BUILDABLE)
def test_golden_dump(scene):
    """The build against its golden dump; the tool_version each records (the golden's is the version that wrote
    it, kept so that it is a valid dump) is left out of the comparison."""
    got = build_json(scene)
    path = GOLDEN / f"{scene}.features.json"
    if os.environ.get("WIREDSL_UPDATE_GOLDEN") == "1":
        path.write_text(json.dumps(got, indent=1, sort_keys=True) + "\n")
    want = json.loads(path.read_text())
    assert isinstance(got.pop("tool_version"), str) and isinstance(want.pop("tool_version"), str)
    diffs = _close(got, want)
    assert not diffs, f"{len(diffs)} differences, first: {diffs[:5]} (WIREDSL_UPDATE_GOLDEN=1 to accept)"


def test_golden_dumps_are_valid_dumps():
    """`wiredsl validate` accepts every golden file: they are what the tool writes, tool_version included."""
    goldens = sorted(str(p) for p in GOLDEN.glob("*.features.json"))
    assert len(goldens) == len(BUILDABLE)
    r = CliRunner().invoke(main, ["validate", *goldens])
    assert r.exit_code == 0, r.output


@pytest.mark.parametrize("scene", BUILDABLE)
def test_dump_validates_against_the_features_schema(scene):
    assert schema.problems(build_json(scene)) == []


def test_build_writes_dump_and_one_svg_a_pose(tmp_path):
    out = tmp_path / "out"
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "-o", str(out), "--no-effects"])
    assert r.exit_code == 0, r.output
    dump = json.loads((out / "features.json").read_text())
    svgs = sorted(out.glob("pose_*.svg"))
    assert len(svgs) == len(dump["poses"]) == 7
    root = ET.parse(svgs[0]).getroot()
    assert root.tag.endswith("svg") and root.get("viewBox")
    panes = [t.text for t in root.iter("{http://www.w3.org/2000/svg}text")]
    assert "left camera (cam_l)" in panes and "right camera (cam_r)" in panes
    assert any(t.startswith("top view") for t in panes)
    first = {p.name: p.read_bytes() for p in out.iterdir()}
    assert CliRunner().invoke(main, ["build", "scenes/lab.wd", "-o", str(out), "--no-effects"]).exit_code == 0
    assert {p.name: p.read_bytes() for p in out.iterdir()} == first  # byte-identical, no stray temp files


def test_every_pose_sees_something_in_the_lab():
    """By default (exact hidden lines, issue 35) and with the view-points' lists, whose nearest view-point each
    pose records (exact uses none: null)."""
    for visibility in ("auto", "scene"):
        dump = build_json("lab", "--visibility", visibility)
        for pose in dump["poses"]:
            for side in ("left", "right"):
                v = pose[side]
                assert len(v["lines"]) + len(v["polylines"]) > 5
            assert (pose["viewpoint"] is not None) == (visibility == "scene")


def test_undistorted_lines_are_segments_and_ellipses_have_conics():
    dump = build_json("cylinder")
    left = dump["poses"][0]["left"]
    sides = [f for f in left["lines"] if f["source"] == "can1.side"]
    assert sorted(f["segment"] for f in sides) == [0, 1]
    assert {c["source"] for c in left["conics"]} == {"can1.top", "can1.bottom"}
    assert all(p["closed"] for p in left["polylines"])


def test_pose_selection_and_bad_pose():
    dump = build_json("lab", "--pose", "2", "--pose", "4")
    assert [p["index"] for p in dump["poses"]] == [2, 4]
    r = CliRunner().invoke(main, ["build", "scenes/lab.wd", "-o", "-", "--pose", "99"])
    assert r.exit_code == 2 and "pose 99 is not in 0..6" in r.output


def test_tolerance_changes_polyline_density():
    coarse = build_json("lab", "--tolerance", "1")
    fine = build_json("lab", "--tolerance", "0.01")
    count = lambda d: sum(len(p["points"]) for pose in d["poses"] for p in pose["left"]["polylines"])  # noqa: E731
    assert count(fine) > 2 * count(coarse)
    assert CliRunner().invoke(main, ["build", "scenes/lab.wd", "--tolerance", "0"]).exit_code == 2


def test_exact_visibility_shows_parts_of_what_all_shows():
    exact = build_json("lab", "--visibility", "exact")
    every = build_json("lab", "--visibility", "all")
    parts = 0
    for a, b in zip(exact["poses"], every["poses"], strict=True):
        sa = {f["source"] for f in a["left"]["polylines"]}
        sb = {f["source"] for f in b["left"]["polylines"]}
        assert sa <= sb  # hidden-line removal only takes away
        parts += sum(f["occluded"] for f in a["left"]["polylines"])
    assert parts > 0


def test_scene_without_path_is_a_diagnostic():
    r = CliRunner().invoke(main, ["build", "scenes/calibration.wd", "-o", "-"])
    assert r.exit_code == 1 and "needs a path to be built" in r.stderr


SCENE, _, _ = compile_file("scenes/lab.wd")
WORLD = build_world(SCENE)


@settings(max_examples=60, deadline=None)
@given(x=st.floats(-2, 8), y=st.floats(-2, 7), heading=st.floats(-math.pi, math.pi),
       tilt=st.floats(-1.5, 1.5))
def test_no_nan_or_infinity_whatever_the_pose(x, y, heading, tilt):
    """Robot anywhere, even inside objects or walls, camera pitched anywhere: output is finite."""
    mount = SCENE.rig.left.model_copy(update={"rotation": tuple(map(tuple, _pitched(tilt)))})
    rig = SCENE.rig.model_copy(update={"left": mount})
    path = SCENE.path.model_copy(update={"poses": [(x, y, heading)]})
    scene = SCENE.model_copy(update={"rig": rig, "path": path})
    results = simulate(scene, Options(visibility="all"), WORLD)
    text = emit.to_json(emit.features(scene, WORLD, results))  # allow_nan=False raises on NaN
    assert "NaN" not in text and "Infinity" not in text


def _pitched(tilt: float) -> np.ndarray:
    c, s = math.cos(tilt), math.sin(tilt)
    look = np.array([c, 0.0, s])
    x = np.cross(look, [0, 0, 1.0])
    x /= np.linalg.norm(x)
    return np.column_stack([x, np.cross(look, x), look])

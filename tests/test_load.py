"""wiredsl.load round-trips every dump format; npz layout documented; manifests and npz validate; R, t exact."""

from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest
from click.testing import CliRunner

import wiredsl
from wiredsl.cli import main
from wiredsl.engine.world import build_world
from wiredsl.io import layout
from wiredsl.io.load import DumpError
from wiredsl.language.compile import compile_file
from wiredsl.scene import Camera

LAB = "scenes/lab.wd"


def build(tmp_path: Path, name: str, *args: str) -> Path:
    out = tmp_path / name
    result = CliRunner().invoke(main, ["build", LAB, "-o", str(out), "--no-svg", *args])
    assert result.exit_code == 0, result.output
    return out


def same_records(a: list[dict], b: list[dict], px: float) -> None:
    """Equal records: every field exactly, pixel coordinates within px (npz holds float32)."""
    assert len(a) == len(b) and len(a) > 0
    for x, y in zip(a, b, strict=True):
        assert x.keys() == y.keys(), (x, y)
        for k in x:
            if k in ("points", "at", "centre", "axes", "angle", "arc") and x[k] is not None:
                assert np.allclose(x[k], y[k], rtol=0, atol=px), (k, x, y)
            else:
                assert x[k] == y[k], (k, x, y)


@pytest.fixture(scope="module")
def disturbed(tmp_path_factory):
    tmp = tmp_path_factory.mktemp("dumps")
    seed = ["--seed", "11", "--pose", "1", "--pose", "4", "--visibility", "exact"]  # parts through the effects
    return {"npz": build(tmp, "npz", *seed, "--trials", "3", "--format", "npz") / "features.npz",
            "jsonl": build(tmp, "jsonl", *seed, "--trials", "3", "--format", "jsonl") / "features.jsonl",
            "json": [build(tmp, f"j{k}", *seed, "--trial", str(k)) / "features.json" for k in range(3)],
            "dir": tmp}


def test_every_format_loads_to_the_same_records_for_the_same_seed_and_trials(disturbed):
    from_json = [r for p in disturbed["json"] for r in wiredsl.load(p)]
    same_records(wiredsl.load(disturbed["jsonl"]), from_json, px=0)
    same_records(wiredsl.load(disturbed["npz"]), from_json, px=1e-4)  # float32 pixels (about 3e-5 at 640 px)
    assert any(r["occluded"] for r in from_json)  # hidden-line parts went through every effect


def test_selection_by_trial_pose_and_camera(disturbed):
    recs = wiredsl.load(disturbed["npz"], trial=2, pose=4, camera="right")
    assert recs and {(r["trial"], r["pose"], r["camera"]) for r in recs} == {(2, 4, "right")}
    same_records(recs, wiredsl.load(disturbed["json"][2], pose=[4], camera=1), px=1e-4)
    arrays = wiredsl.load(disturbed["npz"], trial=[0, 1], arrays=True)
    strokes = arrays["strokes"]
    assert set(strokes[:, layout.column("trial")].tolist()) == {0, 1}
    assert len(arrays["start"]) == len(strokes) + 1 and arrays["start"][-1] == len(arrays["pts"])
    assert arrays["manifest"]["seed"] == 11


def test_the_scenes_own_camera_names_select_in_a_json_dump(disturbed):
    """Issue 15: camera="cam_l" raised `tuple.index(x): x not in tuple`."""
    for path in (disturbed["jsonl"], disturbed["json"][1]):
        assert wiredsl.load(path, camera="cam_l") == wiredsl.load(path, camera="left")
        assert wiredsl.load(path, camera=["cam_r"]) == wiredsl.load(path, camera=1)
    with pytest.raises(DumpError, match=r"no camera 'cam_x': choose 'left', 'right', 0 or 1, "
                                                r"or the scene's 'cam_l' and 'cam_r'"):
        wiredsl.load(disturbed["jsonl"], camera="cam_x")
    with pytest.raises(DumpError, match=r"no camera 'cam_l': .* \(an npz dump knows its cameras by side"):
        wiredsl.load(disturbed["npz"], camera="cam_l")
    with pytest.raises(DumpError, match="no camera 2"):
        wiredsl.load(disturbed["npz"], camera=2)


@pytest.mark.parametrize("kind", ["npz", "jsonl"])
def test_a_trial_or_pose_outside_the_dump_names_what_it_holds(disturbed, kind):
    """Issue 15: these returned [] without a word."""
    with pytest.raises(DumpError, match="holds no trial 3: it holds trials 0-2"):
        wiredsl.load(disturbed[kind], trial=3)
    with pytest.raises(DumpError, match="holds no pose 2, 9: it holds poses 1, 4"):
        wiredsl.load(disturbed[kind], pose=[1, 2, 9])
    with pytest.raises(DumpError, match="holds no trial 0: it holds trial 2"):
        wiredsl.load(disturbed["json"][2], trial=0)
    assert wiredsl.load(disturbed[kind], trial=range(3), pose=(1, 4)) == wiredsl.load(disturbed[kind])


def test_a_file_that_is_not_a_dump_says_what_it_is(disturbed, tmp_path):
    """Issue 15: a manifest, a study table or an SVG raised KeyError or JSONDecodeError."""
    svg = tmp_path / "view.svg"
    svg.write_text('<svg xmlns="http://www.w3.org/2000/svg" width="640" height="480"></svg>\n')
    table = tmp_path / "table.csv"
    table.write_text("sigma,measure,statistic,mean\n0.1,survival,mean,0.5\n")
    study = tmp_path / "study.json"
    study.write_text(json.dumps({"document": "study", "rows": []}))
    npz = tmp_path / "other.npz"
    np.savez(npz, x=np.arange(3))
    cases = [(disturbed["dir"] / "npz" / "manifest.json", "this is a run manifest, not a dump"),
             (study, "this is a study table, not a dump"), (svg, "is an SVG image, not a dump"),
             (table, "is a CSV table, not a dump"), (npz, "is an npz file but not a wiredsl dump")]
    for path, says in cases:
        with pytest.raises(DumpError, match=says) as err:
            wiredsl.load(path)
        assert "pass features.json, features.jsonl or features.npz" in str(err.value)


@pytest.mark.parametrize("damage, says", [
    (lambda f: f.update(points=True), "polylines/0/points: Input should be a valid array"),
    (lambda f: f["points"][0].append(1.0), "polylines/0/points/0: Tuple should have at most 2 items"),
    (lambda f: f.update(kind="blob"), "polylines/0/kind"),
    (lambda f: f.pop("source"), "polylines/0/source: Field required")])
def test_a_dump_with_a_value_of_the_wrong_type_or_shape_is_refused_at_its_line(disturbed, tmp_path, damage, says):
    """A damaged JSON-lines dump (one value edited on its third line) is a DumpError naming the line and the
    value's place, not records passed on with `points: true` or a KeyError."""
    lines = disturbed["jsonl"].read_text().splitlines()
    doc = json.loads(lines[2])
    view = next(p[s] for p in doc["poses"] for s in ("left", "right") if p[s] and p[s]["polylines"])
    damage(view["polylines"][0])
    lines[2] = json.dumps(doc)
    bad = tmp_path / "features.jsonl"
    bad.write_text("\n".join(lines) + "\n")
    with pytest.raises(DumpError) as err:
        wiredsl.load(bad)
    assert f"{bad}: line 3 is not a features document wiredsl wrote: poses/" in str(err.value)
    assert says in str(err.value) and f"`wiredsl validate {bad}`" in str(err.value)


def test_ideal_npz_carries_occlusion_fragments_and_closed_like_json(tmp_path):
    args = ["--no-effects", "--visibility", "exact", "--pose", "1", "--pose", "4"]
    npz = build(tmp_path, "n", *args, "--format", "npz") / "features.npz"
    js = build(tmp_path, "j", *args) / "features.json"
    a, b = wiredsl.load(npz), wiredsl.load(js)
    same_records(a, b, px=1e-4)
    assert any(r["occluded"] and r["fragment"] is not None for r in a)
    strokes = wiredsl.load(npz, arrays=True)["strokes"]
    assert strokes[:, layout.column("occluded")].any() and strokes[:, layout.column("closed")].any()


def test_npz_views_hold_the_json_cameras_rotations_and_translations(disturbed):
    a = wiredsl.load(disturbed["npz"], trial=2, arrays=True)
    doc = json.loads(disturbed["json"][2].read_text())
    rows = {tuple(r): k for k, r in enumerate(a["views"].tolist())}
    assert len(rows) == 2 * len(doc["poses"])
    for p in doc["poses"]:
        for cam, side in enumerate(layout.CAMERAS):
            k = rows[(2, p["index"], cam)]
            v = p[side]
            assert a["view_poses"][k].tolist() == [*np.ravel(v["rotation"]), *v["translation"]]  # bit for bit
            camera = Camera.model_validate(v["camera"])
            want = [float(layout.camera_value(camera, c)) for c in layout.CAMERA_COLUMNS]
            assert a["view_cameras"][k].tolist() == want


def test_ideal_conics_round_trip_through_npz(tmp_path):
    args = ["--no-effects", "--visibility", "all"]
    out = tmp_path / "cyl"
    for fmt in ("json", "npz"):
        r = CliRunner().invoke(main, ["build", "scenes/cylinder.wd", "-o", str(out / fmt), "--no-svg", *args,
                                      "--format", fmt])
        assert r.exit_code == 0, r.output
    a, b = wiredsl.load(out / "npz" / "features.npz"), wiredsl.load(out / "json" / "features.json")
    assert any(r["kind"] == "conic" for r in b)
    same_records(a, b, px=1e-4)


def test_manifests_and_npz_validate_and_a_broken_npz_does_not(disturbed, tmp_path):
    manifest = disturbed["dir"] / "npz" / "manifest.json"
    assert json.loads(manifest.read_text())["document"] == "manifest"
    result = CliRunner().invoke(main, ["validate", str(manifest), str(disturbed["npz"])])
    assert result.exit_code == 0, result.output
    data = dict(np.load(disturbed["npz"]))
    data["b00000_strokes"] = data["b00000_strokes"][:, :7]  # the old seven-column layout
    broken = tmp_path / "old.npz"
    np.savez(broken, **data)
    result = CliRunner().invoke(main, ["validate", str(broken)])
    assert result.exit_code == 1 and "b00000_strokes: shape (" in result.output and "expected (S, 11)" in result.output
    (tmp_path / "text.npz").write_text("not a zip")
    result = CliRunner().invoke(main, ["validate", str(tmp_path / "text.npz")])
    assert result.exit_code == 1 and "not an npz file" in result.output
    result = CliRunner().invoke(main, ["schema", "manifest"])
    assert json.loads(result.output)["properties"]["document"]["const"] == "manifest"


def test_reprojection_with_opencv_from_the_dumped_rotation_and_translation(tmp_path):
    out = build(tmp_path, "ideal", "--no-effects", "--visibility", "all")
    doc = json.loads((out / "features.json").read_text())
    scene, _, _ = compile_file(LAB)
    w = build_world(scene)
    where = {w.feature_ids[f]: p for f, p in zip(w.corner_fid, w.corners, strict=True)}
    worst, n = 0.0, 0
    for p in doc["poses"]:
        for side in ("left", "right"):
            v = p[side]
            c = v["camera"]
            K = np.array([[c["f"] * c["ax"], 0, c["cx"]], [0, c["f"] * c["ay"], c["cy"]], [0, 0, 1.0]])
            dist = np.array([c["k1"], c["k2"], c["p1"], c["p2"]])
            rvec, _ = cv2.Rodrigues(np.array(v["rotation"]))
            for corner in v["corners"]:
                uv, _ = cv2.projectPoints(where[corner["source"]][None], rvec, np.array(v["translation"]), K, dist)
                worst = max(worst, float(np.abs(uv.ravel() - corner["at"]).max()))
                n += 1
    assert n > 20
    assert worst <= 1e-6  # the dump's pixel rounding; R and t are written at full precision


def test_the_dumps_page_documents_the_npz_layout():
    from wiredsl import docgen

    page = Path("docs/reference/dumps.md").read_text(encoding="utf-8")
    assert layout.markdown().strip() in docgen.expand(page)


def test_importing_wiredsl_does_not_import_numpy():
    code = "import sys, wiredsl; assert 'numpy' not in sys.modules; assert callable(wiredsl.load)"
    subprocess.run([sys.executable, "-c", code], check=True)


def test_a_device_or_fifo_is_refused_unopened(tmp_path):
    fifo = tmp_path / "features.jsonl"
    os.mkfifo(fifo)
    for path in (fifo, "/dev/zero"):
        with pytest.raises(DumpError, match="is not a regular file"):
            wiredsl.load(path)


@pytest.mark.parametrize("effects", [False, True])
def test_mesh_contours_round_trip_through_npz_like_json(tmp_path, effects):
    """scenes/meshes.wd: the smooth ball's occluding contour is `contour: true` in the JSON dump; the npz
    carries it (stroke column `contour`) and wiredsl.load gives the same records from both."""
    scene = tmp_path / "m.wd"  # scenes/meshes.wd with a pipeline (edge loss cuts contours into fragments)
    scene.write_text(f'wiredsl 1\ninclude "{Path("scenes/meshes.wd").resolve().as_posix()}"\n'
                     "pipeline p default {\n  edge_loss fraction 40%\n  approx_error sigma 0.3px\n}\n")

    def build_mesh(name, *args):
        out = tmp_path / name
        r = CliRunner().invoke(main, ["build", str(scene), "-o", str(out), "--no-svg", "--pose", "1", *args])
        assert r.exit_code == 0, r.output
        return out

    if effects:  # trial 1 of a disturbed run: the npz holds trials 0 and 1
        js = wiredsl.load(build_mesh("j", "--seed", "3", "--trial", "1") / "features.json")
        npz_path = build_mesh("n", "--seed", "3", "--trials", "2", "--format", "npz") / "features.npz"
        npz = wiredsl.load(npz_path, trial=1)
    else:
        js = wiredsl.load(build_mesh("j", "--no-effects") / "features.json")
        npz_path = build_mesh("n", "--no-effects", "--format", "npz") / "features.npz"
        npz = wiredsl.load(npz_path)
    same_records(npz, js, px=1e-4)
    marked = [r for r in npz if r.get("contour")]
    assert marked and {r["source"] for r in marked} == {r["source"] for r in js if r.get("contour")}
    strokes = wiredsl.load(npz_path, arrays=True)["strokes"]
    assert strokes[:, layout.column("contour")].sum() >= len(marked) > 0

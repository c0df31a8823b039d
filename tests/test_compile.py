"""The compiler: constructs, units, semantics, collected errors."""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from helpers import compile_text, errors_of

from wiredsl.diagnostics import WiredslError
from wiredsl.language.compile import compile_file

SCENES = sorted(Path("scenes").glob("*.wd"))


@pytest.mark.parametrize("path", SCENES, ids=[p.stem for p in SCENES])
def test_every_scene_compiles_clean(path):
    scene, warnings, _ = compile_file(path)
    assert warnings == []
    assert scene.name


def test_lab_has_every_construct():
    scene, _, program = compile_file("scenes/lab.wd")
    assert len(program.files) == 3  # lab.wd and its two includes
    kinds = {k for m in scene.models for k in ("lines", "polylines", "ellipses", "silhouettes", "corners", "faces")
             if getattr(m, k)}
    assert kinds == {"lines", "polylines", "ellipses", "silhouettes", "corners", "faces"}
    assert scene.rig.calibration.kind == "information" and len(scene.rig.calibration.order) == 14
    assert scene.pipeline().name == "paper"
    assert [s.effect for s in scene.pipeline().stages] == [
        "calibration_error", "edge_loss", "lateral_shift", "approx_error", "corner_loss", "corner_mismatch",
        "stereo_mismatch"]
    # the included furniture file is in cm: the table top sits 0.75 m up
    table = scene.model("table")
    assert table.polylines[0].points[0] == pytest.approx((-0.6, -0.4, 0.75))


def test_units_are_normalised_to_si():
    scene, _ = compile_text("""wiredsl 1
model m { line a from (10mm, 2cm, 0.5m) to (1, 0, 0) }
place m as p at (0, 0, 0) rotate z 90deg rotate x 1.5707963267948966rad
pipeline q { stereo_mismatch band 0.1rad fraction 2% disparity 7px }
""")
    line = scene.model("m").lines[0]
    assert line.start == pytest.approx((0.01, 0.02, 0.5))
    R = np.array(scene.placements[0].rotation)
    # rotate z then x (world axes): x -> y -> z
    assert R @ [1, 0, 0] == pytest.approx([0, 0, 1], abs=1e-12)
    params = scene.pipelines[0].stages[0].params
    assert (params["band"], params["fraction"], params["disparity"]) == pytest.approx((0.1, 0.02, 7.0))


def test_units_statement_changes_bare_numbers():
    scene, _ = compile_text("wiredsl 1\nunits length mm angle rad\nmodel m { line a from (0, 0, 0) to (500, 0, 0) }\n"
                            "place m as p ypr (1.5707963267948966, 0, 0)\n")
    assert scene.model("m").lines[0].end == pytest.approx((0.5, 0, 0))
    assert np.array(scene.placements[0].rotation) @ [1, 0, 0] == pytest.approx([0, 1, 0], abs=1e-12)


def test_omitted_parameters_take_the_papers_values():
    scene, _ = compile_text("wiredsl 1\npipeline p {\n calibration_error\n edge_loss\n lateral_shift\n approx_error\n"
                            " corner_loss\n corner_mismatch\n stereo_mismatch\n}\n")
    got = {s.effect: s.params for s in scene.pipelines[0].stages}
    assert got == {
        "calibration_error": {"sigma": 0.01, "cutoff": 1e-9},
        "edge_loss": {"fraction": 0.29},
        "lateral_shift": {"range": 3.0},
        "approx_error": {"sigma": 0.15},
        "corner_loss": {"keep": 0.85},
        "corner_mismatch": {"fraction": 0.01, "radius": 10.0},
        "stereo_mismatch": {"band": pytest.approx(math.radians(5)), "fraction": 0.01, "disparity": 20.0},
    }


def test_out_of_order_pipeline_warns():
    scene, warnings = compile_text("wiredsl 1\npipeline p {\n  stereo_mismatch\n  edge_loss\n}\n")
    assert [(w.code, w.span.line) for w in warnings] == [("W161", 4)]
    assert "departs from the data flow" in warnings[0].message


def test_all_errors_of_a_file_are_reported():
    errs = errors_of("""wiredsl 1
model m {
  line a from (0, 0, 0) to (0, 0, 0)
  ellipse e centre (0, 0, 0) normal (0, 0, 0) axis (1, 0, 0) radii (1, 1)
  line a from (0, 0, 0) to (1, 0, 0)
}
place n as p
pipeline q { edge_loss fraction 2 }
""")
    assert errs == [
        "3:3: E120 line 'a' has zero length",
        "4:37: E121 ellipse 'e' has a zero normal",
        "5:8: E105 duplicate feature 'a'",
        "7:7: E104 unknown model 'n'",
        "8:33: E110 edge_loss fraction: must be <= 1, got 2",
    ]


def test_camera_like_inherits_and_overrides():
    scene, _ = compile_text("wiredsl 1\ncamera a {\n focal 6mm\n pixel 0.01mm\n size (640px, 480px)\n k 0.1\n}\n"
                            "camera b like a { k1 0.3 }\ncamera c like b\n")
    a, b, c = (scene.camera(n) for n in "abc")
    assert a.f == pytest.approx(600) and a.k1 == pytest.approx(-0.1)
    assert (a.cx, a.cy) == (320, 240)
    assert b.f == a.f and b.k1 == 0.3 and c == b.model_copy(update={"name": "c"})


def test_camera_mount_frame_is_opencv_convention():
    scene, _ = compile_text("wiredsl 1\ncamera c { focal 600px\n size (640px, 480px) }\n"
                            "rig r { left c at (0, 0, 1) looking (1, 0, 0)\n"
                            " right c at (0, -0.1, 1) looking (1, 0, 0) }\n")
    R = np.array(scene.rig.left.rotation)  # robot_from_camera
    assert R @ [0, 0, 1] == pytest.approx([1, 0, 0])  # optical axis forward
    assert R @ [1, 0, 0] == pytest.approx([0, -1, 0])  # image x to the robot's right
    assert R @ [0, 1, 0] == pytest.approx([0, 0, -1])  # image y down


def test_grid_mesh_counts_and_names():
    scene, _ = compile_text("wiredsl 1\nviewpoints m { grid from (0, 0) to (2m, 1m) spacing 0.5m }\n")
    vp = scene.viewpoints
    assert len(vp.names) == 5 * 3 and len(vp.triangles) == 2 * 4 * 2
    assert vp.names[0] == "g0_0" and vp.points[-1] == pytest.approx((2, 1))


def test_straight_path_steps_and_heading():
    scene, _ = compile_text("wiredsl 1\npath p { straight from (0, 0) to (0, 1m) step 25cm }\n")
    poses = np.array(scene.path.poses)
    assert poses.shape == (5, 3)
    assert poses[:, 1] == pytest.approx([0, 0.25, 0.5, 0.75, 1])
    assert poses[:, 2] == pytest.approx([math.pi / 2] * 5)


def test_authored_visibility_expands_wildcards():
    scene, _, _ = compile_file("scenes/box.wd")
    vis = scene.viewpoints.visible
    assert "crate.south" not in vis["v_c"]  # faces occlude but are never emitted
    assert len(vis["v_c"]) == 8 and set(vis["v_s"]) < set(vis["v_c"])


def test_tina_and_plain_matrix_files_agree(tmp_path):
    M = [[2.0, 0.5], [0.5, 1.0]]
    (tmp_path / "plain.txt").write_text("2 0.5\n0.5 1\n")
    (tmp_path / "tina.cov").write_text("2 mask\n2 0.5 0.5 1\n600 320\n")
    for name in ("plain.txt", "tina.cov"):
        (tmp_path / "s.wd").write_text(
            f'wiredsl 1\ncamera c {{ focal 600px\n size (640px, 480px) }}\nrig r {{ left c at (0, 0, 1) '
            f'looking (1, 0, 0)\n right c at (0, -0.1, 1) looking (1, 0, 0)\n calibration covariance file '
            f'"{name}" order [left.f, left.cx] }}\n')
        scene, _, _ = compile_file(tmp_path / "s.wd")
        assert scene.rig.calibration.matrix == M


def test_many_errors_are_capped_in_the_report():
    from wiredsl.diagnostics import MAX_REPORTED, WiredslError, render

    text = "wiredsl 1\nmodel m {\n" + "".join(f"  line l{i} from (0, 0, 0) to (0, 0, 0)\n" for i in range(30)) + "}\n"
    with pytest.raises(WiredslError) as info:
        compile_text(text)
    out = render(info.value.diagnostics, {})
    assert out.count("error[E120]") == MAX_REPORTED
    assert out.rstrip().endswith(f"... and {30 - MAX_REPORTED} more")


def test_the_scene_is_named_by_its_own_file_not_by_what_it_includes(tmp_path):
    """`scene` in an included file names that file's builds: the including file takes its own `scene`, else its
    file name (the lab study was named `lab` and its default output folders were the lab's); a root file that
    names itself twice is still E105."""
    (tmp_path / "base.wd").write_text("wiredsl 1\nscene base\n")
    (tmp_path / "named.wd").write_text('wiredsl 1\ninclude "base.wd"\nscene mine\n')
    (tmp_path / "plain.wd").write_text('wiredsl 1\ninclude "base.wd"\n')
    (tmp_path / "twice.wd").write_text('wiredsl 1\ninclude "base.wd"\nscene a\nscene b\n')
    assert [compile_file(tmp_path / f"{n}.wd")[0].name for n in ("base", "named", "plain")] == ["base", "mine", "plain"]
    assert compile_file("scenes/studies/lab_study.wd")[0].name == "lab_study"
    with pytest.raises(WiredslError) as err:
        compile_file(tmp_path / "twice.wd")
    assert [(d.code, d.span.line, d.message) for d in err.value.diagnostics] == [(
        "E105", 4, "the scene is named twice")]


def test_checked_models_equal_validated_ones_and_leave_the_rest_to_validation():
    """`scene.checked` skips validation only for values validation would pass unchanged: for the others (an int
    for a float, out of bounds, non-finite, an unknown key, a wrong Literal, a string for a number) it validates,
    so its result or its error is pydantic's own."""
    import math

    import pydantic

    from wiredsl.effects import REGISTRY
    from wiredsl.scene import Camera, checked, plainly_valid, same_nodes

    cam = dict(name="c", f=500.0, cx=320.0, cy=240.0, width=640, height=480)
    good = [(Camera, cam), (Camera, {**cam, "distortion": "fov", "w": 0.5, "fov": 2.0}), (Camera, {**cam, "fov": None}),
            (REGISTRY["edge_loss"].Params, {"fraction": 0.3}), (REGISTRY["calibration_error"].Params, {})]
    for model, values in good:
        assert plainly_valid(model, values), values
        assert same_nodes(checked(model, **values), model(**values)) is None
    Edge = REGISTRY["edge_loss"].Params
    bad = [(Camera, {**cam, "f": 500}), (Camera, {**cam, "f": -1.0}), (Camera, {**cam, "f": math.inf}),
           (Camera, {**cam, "width": 640.0}), (Camera, {**cam, "width": True}), (Camera, {**cam, "distortion": "x"}),
           (Camera, {**cam, "fov": 7.0}), (Camera, {**cam, "colour": "red"}), (Edge, {"fraction": 1}),
           (Edge, {"fraction": 1.5}), (Edge, {"fraction": math.nan}), (Edge, {"fraction": "0.3"}),
           (Edge, {"fraction": True})]
    for model, values in bad:
        assert not plainly_valid(model, values), values
        try:
            expected = model(**values)
        except pydantic.ValidationError as exc:
            with pytest.raises(pydantic.ValidationError) as got:
                checked(model, **values)
            assert got.value.errors() == exc.errors()
        else:  # validation converts it (1 to 1.0): checked gives the converted value too
            assert same_nodes(checked(model, **values), expected) is None


def test_dumped_equals_pydantics_dump_and_falls_back_where_it_is_not_plain():
    """`scene.dumped` gives `model_dump(mode="json")` type for type for every scene's cameras (the lens numbers
    left out at their defaults, those set kept) and whole scene, and pydantic's own dump where a value is not plain
    (a non-finite number stays one, as the model's ser_json_inf_nan dumps it, for the writers to refuse)."""
    import math

    from wiredsl.scene import _NOT_PLAIN, Camera, _plain_dump, dumped, same_nodes

    scenes = sorted(Path("scenes").glob("*.wd"))
    assert len(scenes) >= 5
    for path in scenes:
        scene, _, _ = compile_file(path)
        for node in [scene, *scene.cameras]:
            assert same_nodes(dumped(node), node.model_dump(mode="json")) is None, path
    cam = Camera(name="c", f=500.0, cx=320.0, cy=240.0, width=640, height=480, distortion="eucm", alpha=0.5)
    d = dumped(cam)
    assert d["alpha"] == 0.5 and "beta" not in d and "xi" not in d and d == cam.model_dump(mode="json")
    odd = Camera.model_construct(name="c", f=math.inf, cx=320.0, cy=240.0, width=640, height=480)
    assert _plain_dump(odd) is _NOT_PLAIN and dumped(odd)["f"] == math.inf


def test_params_dump_equals_model_dump_and_leaves_excluded_fields_to_pydantic():
    """`plugins.params_dump` gives `model_dump()` type for type for every built-in effect's parameters, and
    pydantic's own dump for a model whose dump is not its fields (an excluded field, a serializer)."""
    from pydantic import Field, field_serializer

    from wiredsl.effects import BUILTIN
    from wiredsl.effects.base import Params
    from wiredsl.plugins import params_dump
    from wiredsl.scene import same_nodes

    for effect in BUILTIN.values():
        p = effect.Params()
        assert same_nodes(params_dump(p), p.model_dump()) is None, effect.name

    class Hidden(Params):
        a: float = 1.0
        b: float = Field(2.0, exclude=True)

    class Doubled(Params):
        a: float = 1.0

        @field_serializer("a")
        def _twice(self, v):
            return 2 * v

    assert params_dump(Hidden()) == {"a": 1.0} and params_dump(Doubled()) == {"a": 2.0}

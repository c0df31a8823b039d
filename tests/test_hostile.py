"""Hostile input to the language: files that are not files, include bombs, magnitudes, silent wrong results."""

from __future__ import annotations

import json
import math
import os
import time

import numpy as np
import pytest
from click.testing import CliRunner
from helpers import compile_text, errors_of

from wiredsl.cli import main
from wiredsl.diagnostics import WiredslError
from wiredsl.io import sources
from wiredsl.language import ast
from wiredsl.language.compile import compile_file
from wiredsl.language.compile_camera import camera_rotation, rotation

CAMERA = "camera c {\n focal 600px\n size (640px, 480px)\n}\n"
RIG = "rig r {\n left c at (0, 0.1, 1) looking (1, 0, 0)\n right c at (0, -0.1, 1) looking (1, 0, 0)\n}\n"


def check(*args: str):
    return CliRunner().invoke(main, ["check", *args])


def diagnostics(path) -> list[dict]:
    r = CliRunner().invoke(main, ["check", "--diagnostics", "json", str(path)])
    assert r.exit_code == 1, r.output
    return json.loads(r.stderr)["diagnostics"]


def warnings_of(text: str) -> list:
    return [w for w in compile_text(text)[1] if w.severity == "warning"]


# --------------------------------------------------------------------------- files that are not files

def test_include_of_a_fifo_is_refused_without_opening_it(tmp_path):
    os.mkfifo(tmp_path / "pipe.wd")
    (tmp_path / "s.wd").write_text('wiredsl 1\ninclude "pipe.wd"\n')
    (d,) = diagnostics(tmp_path / "s.wd")  # would block forever if the FIFO were opened
    assert (d["code"], d["line"], d["column"]) == ("E010", 2, 9)
    assert "not a regular file" in d["message"]


def test_include_of_dev_stdin_is_refused(tmp_path):
    (tmp_path / "s.wd").write_text('wiredsl 1\ninclude "/dev/stdin"\n')
    (d,) = diagnostics(tmp_path / "s.wd")
    assert d["code"] == "E010" and d["line"] == 2


def test_symlink_loop_is_a_diagnostic(tmp_path):
    os.symlink(tmp_path / "b.wd", tmp_path / "a.wd")
    os.symlink(tmp_path / "a.wd", tmp_path / "b.wd")
    (tmp_path / "s.wd").write_text('wiredsl 1\ninclude "a.wd"\n')
    (d,) = diagnostics(tmp_path / "s.wd")
    assert (d["code"], d["line"], d["column"]) == ("E010", 2, 9)
    r = check(str(tmp_path / "a.wd"))  # and as the root file
    assert r.exit_code == 1 and "E010" in r.stderr and "internal" not in r.stderr


def test_a_file_over_the_size_limit_is_refused_before_it_is_read(tmp_path, monkeypatch):
    monkeypatch.setattr(sources, "MAX_SOURCE_BYTES", 1000)
    (tmp_path / "big.wd").write_text("# " + "x" * 2000 + "\n")
    (tmp_path / "s.wd").write_text('wiredsl 1\ninclude "big.wd"\n')
    (d,) = ast.load(tmp_path / "s.wd").errors  # reported with the rest of the file's errors
    assert d.code == "E010" and "over the limit of 1,000" in d.message and d.span.line == 2


def test_root_file_not_utf8_points_at_the_bad_byte(tmp_path):
    (tmp_path / "s.wd").write_bytes(b"wiredsl 1\nscene ok\nscene b\xe9d\n")
    (d,) = diagnostics(tmp_path / "s.wd")
    assert (d["code"], d["line"], d["column"]) == ("E010", 3, 8)


def test_included_file_not_utf8_points_into_it_with_a_note(tmp_path):
    (tmp_path / "inc.wd").write_bytes(b"\xff\n")
    (tmp_path / "s.wd").write_text('wiredsl 1\ninclude "inc.wd"\n')
    (d,) = diagnostics(tmp_path / "s.wd")
    assert (d["code"], d["line"], d["column"]) == ("E010", 1, 1) and d["file"].endswith("inc.wd")
    assert "included from" in d["notes"][0]


# --------------------------------------------------------------------------- includes

def test_repeated_includes_are_read_once(tmp_path):
    """Five levels of ten includes of the next level: 10^5 paths through the tree, 6 files to read."""
    (tmp_path / "l5.wd").write_text("model leaf { line a from (0, 0, 0) to (1, 0, 0) }\n")
    for level in range(4, -1, -1):
        (tmp_path / f"l{level}.wd").write_text(f'include "l{level + 1}.wd"\n' * 10)
    (tmp_path / "s.wd").write_text('wiredsl 1\ninclude "l0.wd"\ninclude "l0.wd"\n')
    t0 = time.perf_counter()
    scene, _, program = compile_file(tmp_path / "s.wd")
    assert time.perf_counter() - t0 < 5  # was 19 s (120 s with models in the leaves); now milliseconds
    assert len(program.files) == 7 and [m.name for m in scene.models] == ["leaf"]


def test_include_once_still_finds_cycles(tmp_path):
    (tmp_path / "a.wd").write_text('include "b.wd"\n')
    (tmp_path / "b.wd").write_text('include "a.wd"\n')
    (tmp_path / "s.wd").write_text('wiredsl 1\ninclude "a.wd"\ninclude "b.wd"\n')
    (d,) = diagnostics(tmp_path / "s.wd")
    assert d["code"] == "E011" and "include cycle" in d["message"]


def test_a_thousand_deep_include_chain_is_a_diagnostic(tmp_path):
    for i in range(1000):
        (tmp_path / f"d{i}.wd").write_text(f'include "d{i + 1}.wd"\n')
    (tmp_path / "d1000.wd").write_text("scene deep\n")
    (tmp_path / "s.wd").write_text('wiredsl 1\ninclude "d0.wd"\n')
    (d,) = diagnostics(tmp_path / "s.wd")
    assert d["code"] == "E011" and "deeper than 64" in d["message"]
    assert d["file"].endswith(f"d{ast.MAX_INCLUDE_DEPTH - 2}.wd") and d["line"] == 1  # the 65th file is refused


def test_a_chain_at_the_depth_limit_compiles(tmp_path):
    for i in range(ast.MAX_INCLUDE_DEPTH - 2):
        (tmp_path / f"d{i}.wd").write_text(f'include "d{i + 1}.wd"\n')
    (tmp_path / f"d{ast.MAX_INCLUDE_DEPTH - 2}.wd").write_text("scene deep\n")
    (tmp_path / "s.wd").write_text('wiredsl 1\ninclude "d0.wd"\n')
    scene, _, program = compile_file(tmp_path / "s.wd")
    assert len(program.files) == ast.MAX_INCLUDE_DEPTH and any(
        str(f).endswith(f"d{ast.MAX_INCLUDE_DEPTH - 2}.wd") for f in program.files)
    assert scene.name == "s"  # the deepest file's `scene` names its own builds, not the including scene


# --------------------------------------------------------------------------- numbers and derived sizes

@pytest.mark.parametrize("stmt", [
    "place m as p rotate z 1e999",
    "place m as p ypr (0, 1e999, 0)",
    "place m as p at (1e999, 0, 0)",
    "path q { pose (0, 0) heading -1e999 }",
    "path q { straight from (0, 0) to (1e999, 0) step 1 }",
    "viewpoints v { grid from (0, 0) to (1, 1) spacing 1e999 }",
    "model n { face f through (0, 0, 0) (1, 0, 0) (1e999, 1, 0) }",
    "pipeline q { edge_loss fraction 1e999 }",
    "wiredsl 1e999",
])
def test_an_infinite_literal_is_e109_at_its_span(stmt):
    errs = errors_of("wiredsl 1\nmodel m { line a from (0, 0, 0) to (1, 0, 0) }\n" + stmt + "\n")
    e109 = [e for e in errs if " E109 " in e or " E106 " in e]
    assert e109 and e109[0].startswith("3:"), errs


@pytest.mark.parametrize("stmt, code", [
    ("viewpoints v { grid from (-1e9, -1e9) to (1e9, 1e9) spacing 1e-320 }", "E151"),
    ("path q { straight from (-1e9, 0) to (1e9, 0) step 5e-324 }", "E151"),
    ("model n { ellipse e centre (0, 0, 0) normal (1e308, 1e308, 0) axis (0, 0, 1e308) radii (1, 1) }", None),
    ("model n { ellipse e centre (0, 0, 0) normal (0, 0, 1) axis (1, 0, 0) radii (1, 1) range (-1e308, 1e308) }",
     "E110"),
    ("camera d {\n focal 1e9m\n pixel 1e-9mm\n size (640px, 480px)\n}", "E110"),
])
def test_overflowing_derived_sizes_are_diagnostics(stmt, code):
    errs = errors_of("wiredsl 1\n" + stmt + "\n")
    assert [e.split()[1] for e in errs][:1] == ([code] if code else []), errs


def test_pose_statements_are_counted_against_the_limit(monkeypatch):
    from wiredsl.language import compile as comp

    monkeypatch.setattr(comp, "MAX_POSES", 3)
    errs = errors_of("wiredsl 1\npath p {\n" + " pose (0, 0)\n" * 4 + "}\n")
    assert errs == ["6:2: E151 more than 3 poses"]


def test_huge_direction_normalises_exactly():
    scene, _ = compile_text("wiredsl 1\nmodel n { ellipse e centre (0, 0, 0) normal (1e308, 1e308, 0) "
                            "axis (0, 0, 1e308) radii (1, 1) }\n")
    e = scene.model("n").ellipses[0]
    assert e.normal == pytest.approx((math.sqrt(0.5), math.sqrt(0.5), 0)) and e.axis == pytest.approx((0, 0, 1))


def test_huge_matrix_eigenvalues_are_judged_without_overflow():
    from wiredsl.language.compile_camera import matrix_problem

    assert matrix_problem(np.array([[1e100, 0], [0, 1e100]])) is None
    assert "eigenvalue -1e+100" in matrix_problem(np.array([[0, 1e100], [1e100, 0]]))
    assert "beyond the limit" in matrix_problem(np.array([[1e300, 0], [0, 1]]))


def test_compile_prints_no_non_finite_number():
    r = CliRunner().invoke(main, ["compile", "scenes/lab.wd"])
    assert r.exit_code == 0
    json.loads(r.stdout, parse_constant=lambda c: pytest.fail(f"{c} in compiled JSON"))


# --------------------------------------------------------------------------- silent wrong results

def test_bare_focal_in_metres_warns_with_a_millimetre_hint():
    (w,) = warnings_of("wiredsl 1\ncamera c {\n focal 4\n pixel 0.006mm\n size (640px, 480px)\n}\n")
    assert (w.code, w.span.line, w.span.col, w.hint) == ("W111", 3, 8, "did you mean 4mm?")
    assert "0.055 deg" in w.message


@pytest.mark.parametrize("focal, warned", [("6", True), ("0.08", False), ("0.006", False)])
def test_a_bare_focal_of_a_lens_in_metres_warns_whatever_the_pixel(focal, warned):
    """focal 6 with 10 um pixels is f = 600,000 px, a plausible view of a 6 m lens: still a unit forgotten."""
    found = warnings_of(f"wiredsl 1\ncamera c {{\n focal {focal}\n pixel 0.01mm\n size (640px, 480px)\n}}\n")
    assert [(w.code, w.hint) for w in found] == ([("W111", f"did you mean {focal}mm?")] if warned else [])


@pytest.mark.parametrize("focal, warned", [("0.5px", True), ("1px", False), ("640000px", False),
                                           ("640001px", True), ("6mm", False)])
def test_focal_warning_thresholds(focal, warned):
    text = f"wiredsl 1\ncamera c {{\n focal {focal}\n pixel 0.01mm\n size (640px, 480px)\n}}\n"
    ws = warnings_of(text)
    assert bool(ws) == warned and all(w.hint is None for w in ws)  # px was written: no unit to suggest


@pytest.mark.parametrize("angle, warned", [("0.35", True), ("-0.5", True), ("0", False), ("1", False),
                                           ("0.35deg", False), ("0.35rad", False), ("15", False)])
def test_bare_small_angle_warns_in_degrees(angle, warned):
    text = f"wiredsl 1\nmodel m {{ line a from (0, 0, 0) to (1, 0, 0) }}\nplace m as p rotate z {angle}\n"
    ws = warnings_of(text)
    assert bool(ws) == warned
    if warned:
        assert ws[0].hint == f"{angle} is degrees; did you mean {angle}rad?" and ws[0].span.line == 3


def test_no_small_angle_warning_when_the_file_says_radians():
    assert warnings_of("wiredsl 1\nunits angle rad\nmodel m { line a from (0, 0, 0) to (1, 0, 0) }\n"
                       "place m as p rotate z 0.35\n") == []


def test_bare_fraction_over_one_hints_a_percentage():
    with pytest.raises(WiredslError) as err:
        compile_text("wiredsl 1\npipeline p {\n edge_loss fraction 29\n}\n")
    (d,) = err.value.diagnostics
    assert d.hint == "did you mean 29%?"
    with pytest.raises(WiredslError) as err:
        compile_text("wiredsl 1\npipeline p {\n edge_loss fraction 150%\n}\n")
    assert err.value.diagnostics[0].hint is None  # written as a percentage already


def test_one_line_block_is_one_message():
    errs = errors_of("wiredsl 1\ncamera c { focal 4mm pixel 0.006mm }\n")
    assert errs == ["2:22: E101 'pixel' starts another statement: a block holds one statement a line"]


def test_calibration_error_needs_a_calibration():
    errs = errors_of("wiredsl 1\n" + CAMERA + RIG + "pipeline p {\n calibration_error\n}\n")
    assert errs == ["11:2: E162 calibration_error needs a calibration, and rig 'r' has none"]
    rig = RIG.replace("}\n", " calibration covariance order [left.f] matrix [[1]]\n}\n")
    assert errors_of("wiredsl 1\n" + CAMERA + rig + "pipeline p {\n calibration_error\n}\n") == []


def test_unknown_units_word_is_reported_not_used():
    errs = errors_of("wiredsl 1\nunits length furlong angle rad\nmodel m { line a from (0, 0, 0) to (1, 0, 0) }\n")
    assert errs == ["2:14: E106 'furlong' is not a unit"]


# --------------------------------------------------------------------------- located diagnostics, conventions

def test_unicode_line_separators_are_not_line_breaks():
    """Found by the fuzz campaign: fmt split lines where the lexer does not (U+2028, U+0085), losing comments."""
    from wiredsl.diagnostics import render
    from wiredsl.language.fmt import format_text

    text = "wiredsl 1\n# a \u2028 b\nscene x # c\x85d\nscene 1\n"
    once = format_text(text)
    assert once == text.replace("x # c", "x  # c") and format_text(once) == once
    with pytest.raises(WiredslError) as err:
        compile_text(text)
    assert " 4 | scene 1" in render(err.value.diagnostics, {"t.wd": text})


def test_needs_a_rig_points_at_the_file(tmp_path):
    (tmp_path / "s.wd").write_text("wiredsl 1\nscene lonely\n")
    r = CliRunner().invoke(main, ["build", str(tmp_path / "s.wd"), "-o", str(tmp_path / "out"),
                                  "--format", "json"])
    assert r.exit_code == 1
    assert f"{tmp_path / 's.wd'}:1:1: error[E102]: scene 'lonely' needs a rig" in r.stderr


def test_viewdep_file_problems_are_located(tmp_path):
    from wiredsl.io.viewdep import read as read_viewdep

    scene, _ = compile_text("wiredsl 1\n", str(tmp_path / "s.wd"))
    (tmp_path / "v.json").write_text('{\n  "document": "viewdep",\n  oops\n}\n')
    with pytest.raises(WiredslError) as err:
        read_viewdep(tmp_path / "v.json", scene)
    d = err.value.diagnostics[0]
    assert (d.code, d.span.line, d.span.col) == ("E010", 3, 3)
    (tmp_path / "v.json").write_text('{"document": "viewdep"}\n')
    with pytest.raises(WiredslError) as err:
        read_viewdep(tmp_path / "v.json", scene)
    d = err.value.diagnostics[0]
    assert d.code == "E142" and (d.span.line, d.span.col) == (1, 1) and d.span.file.endswith("v.json")


def test_ypr_is_rz_ry_rx_and_rotate_steps_are_world_axes():
    y, p, r = 0.3, -0.7, 1.1
    scene, _ = compile_text("wiredsl 1\nunits angle rad\nmodel m { line a from (0, 0, 0) to (1, 0, 0) }\n"
                            f"place m as a ypr ({y}, {p}, {r})\nplace m as b rotate x {r} rotate y {p} rotate z {y}\n")
    Ra, Rb = (np.array(pl.rotation) for pl in scene.placements)
    assert Ra == pytest.approx(rotation("z", y) @ rotation("y", p) @ rotation("x", r), abs=1e-15)
    assert Ra == pytest.approx(Rb, abs=1e-15)
    # independently (OpenCV's axis-angle): yaw about z, then pitch about the turned y, then roll about the new x
    import cv2

    def turn(axis, angle):
        return cv2.Rodrigues(np.asarray(axis, float) * angle)[0]

    R1 = turn([0, 0, 1], y)
    R2 = turn(R1[:, 1], p) @ R1
    R3 = turn(R2[:, 0], r) @ R2
    assert Ra == pytest.approx(R3, abs=1e-12)


def test_roll_turns_the_camera_right_handed_about_its_viewing_direction():
    look = np.array([1.0, 0.0, 0.0])
    R0, R = camera_rotation(look, 0.0), camera_rotation(look, math.radians(10))
    # the same as rotating the camera frame by +roll about its own z (optical) axis
    assert R == pytest.approx(R0 @ rotation("z", math.radians(10)), abs=1e-15)
    # looking along robot x, image x is robot -y (right); +10 deg turns image x towards image y (down, robot -z)
    assert R[:, 0] == pytest.approx([0, -math.cos(math.radians(10)), -math.sin(math.radians(10))], abs=1e-15)
